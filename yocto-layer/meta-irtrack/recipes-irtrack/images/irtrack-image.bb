SUMMARY = "irtrack appliance image"
DESCRIPTION = "Minimal systemd image for the board of the irtrack optical tracker: irtrackd \
with its udev rules, linuxptp for the clocks of multi-board rigs, plus V4L2 and GPIO tools \
for bring-up."
HOMEPAGE = "https://example.invalid/irtrack"
LICENSE = "MIT"

inherit core-image

IMAGE_INSTALL = "packagegroup-core-boot \
                 irtrackd \
                 linuxptp \
                 libgpiod-tools \
                 v4l-utils \
                 ${CORE_IMAGE_EXTRA_INSTALL} \
                 "
IMAGE_LINGUAS = ""

# SD card: vfat boot partition (U-Boot, kernel, device tree) and ext4 root.
IMAGE_FSTYPES = "wic.xz wic.bmap"
WKS_FILE ?= "irtrack-sdcard.wks"
