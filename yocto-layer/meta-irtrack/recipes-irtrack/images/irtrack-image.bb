SUMMARY = "irtrack appliance image"
DESCRIPTION = "Minimal systemd image for the board of the irtrack optical tracker: irtrackd \
with its udev rules, linuxptp for the clocks of multi-board rigs, RAUC A/B updates with \
automatic rollback, plus V4L2 and GPIO tools for bring-up."
HOMEPAGE = "https://example.invalid/irtrack"
LICENSE = "MIT"

inherit core-image

IMAGE_INSTALL = "packagegroup-core-boot \
                 irtrackd \
                 rauc \
                 irtrack-update \
                 linuxptp \
                 libgpiod-tools \
                 v4l-utils \
                 ${CORE_IMAGE_EXTRA_INSTALL} \
                 "
IMAGE_LINGUAS = ""

# SD card with A/B root slots and a data partition (wic/irtrack-sdcard-ab.wks, docs/updates.md).
# The ext4 root file system is also kept: it is what an update bundle carries (docs/updates.md,
# "Yocto").
IMAGE_FSTYPES = "wic.xz wic.bmap ext4"
WKS_FILE ?= "irtrack-sdcard-ab.wks"
# boot.scr and the first boot counters come from irtrack-update's deploy step; a machine that
# sets IMAGE_BOOT_FILES itself lists them with its boot loader files (conf/machine/pandaboard.conf).
IMAGE_BOOT_FILES ?= "boot.scr uboot.env uboot-redund.env"
WKS_FILE_DEPENDS:append = " irtrack-update"
