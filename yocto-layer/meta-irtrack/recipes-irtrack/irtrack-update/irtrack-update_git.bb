SUMMARY = "A/B updates of the irtrack board (RAUC slots, boot script, health check)"
DESCRIPTION = "What makes the irtrack image updatable in place (docs/updates.md): RAUC's slot \
configuration for the layout of wic/irtrack-sdcard-ab.wks, the U-Boot boot script that picks \
the slot and counts boot attempts, the health check that marks a slot good once irtrackd is \
healthy, the root agent that runs RAUC for the unprivileged irtrackd, and the data partition \
that updates never write. The scripts are the CI image's own (image/update in the repository)."
HOMEPAGE = "https://example.invalid/irtrack"
BUGTRACKER = "https://example.invalid/irtrack/issues"
SECTION = "base"
LICENSE = "MIT | Apache-2.0"
# nooelint: oelint.var.licenseremotefile - the sources carry no license texts; the common ones are exact
LIC_FILES_CHKSUM = "file://${COMMON_LICENSE_DIR}/MIT;md5=0835ade698e0bcf8506ecda2f7b4f302 \
                    file://${COMMON_LICENSE_DIR}/Apache-2.0;md5=89aea4e17d99a7cacdbeed46a0096b10"

# mkimage (boot.scr) and mkenvimage (the first boot counters).
DEPENDS = "u-boot-tools-native"

PV = "0.1.0+git"

# The repository (as irtrackd's recipe; SRCREV in irtrack-source.inc). boot-board.cmd is the
# board's part of the boot script (files/<MACHINE>/ wins over files/).
SRC_URI = "git://example.invalid/irtrack.git;protocol=https;branch=main \
           file://system.conf.in \
           file://boot-board.cmd \
           file://irtrack-update-agent.service \
           file://irtrack-health.service \
           file://var-lib-irtrackd.mount \
           file://irtrack-update.tmpfiles \
           "

require recipes-irtrack/irtrack-source.inc

S = "${WORKDIR}/git"

inherit systemd deploy

# Bundles name the board type they are for; RAUC refuses one made for another.
IRTRACK_COMPATIBLE ?= "irtrack-${MACHINE}"
# Partitions 2 and 3 of the SD card are the slots, 4 the data partition (the .wks file).
IRTRACK_DISK ?= "/dev/mmcblk0p"
IRTRACK_DISK:qemuarm64 = "/dev/vda"
# The update CA's certificate (`cargo xtask image update-keys` makes the CA on the PC): RAUC
# installs only bundles signed under it. Set it in local.conf; the build stops without it.
IRTRACK_UPDATE_CA ?= ""
# The size of the U-Boot environment file boot.scr and fw_setenv share (fw_env.config).
IRTRACK_UBOOT_ENV_SIZE ?= "0x4000"

SYSTEMD_SERVICE:${PN} = "irtrack-update-agent.service irtrack-health.service var-lib-irtrackd.mount"
SYSTEMD_AUTO_ENABLE:${PN} = "enable"

do_compile() {
    sed -e 's|@COMPATIBLE@|${IRTRACK_COMPATIBLE}|g' -e 's|@DISK@|${IRTRACK_DISK}|g' \
        ${WORKDIR}/system.conf.in > ${B}/system.conf
    # The board's settings first, then the repository's slot selection and counting.
    cat ${WORKDIR}/boot-board.cmd ${S}/image/update/boot.cmd > ${B}/boot.cmd
    uboot-mkimage -A arm -O linux -T script -C none -n "irtrack A/B" -d ${B}/boot.cmd ${B}/boot.scr
    # The counters in libubootenv's redundant layout (CRC, flags byte, data), as both copies
    # (boot.scr and fw_setenv then write the one that did not win; docs/updates.md).
    printf 'BOOT_ORDER=A B\nBOOT_A_LEFT=3\nBOOT_B_LEFT=3\n' > ${B}/uboot-env.txt
    uboot-mkenvimage -r -s ${IRTRACK_UBOOT_ENV_SIZE} -o ${B}/uboot.env ${B}/uboot-env.txt
    cp ${B}/uboot.env ${B}/uboot-redund.env
    printf '# Written by the irtrack-update recipe; read by irtrack-health and RAUC handlers.\nVERSION=%s\nBUILD=%s\nCOMPATIBLE=%s\n' \
        "${@d.getVar('PV').split('+')[0]}" "${SRCPV}" "${IRTRACK_COMPATIBLE}" > ${B}/release
}

do_install() {
    if [ -z "${IRTRACK_UPDATE_CA}" ] || [ ! -f "${IRTRACK_UPDATE_CA}" ]; then
        bbfatal "IRTRACK_UPDATE_CA must name the update CA's certificate (PEM), e.g. in local.conf; made on the PC by cargo xtask image update-keys (docs/updates.md)"
    fi
    install -d ${D}${sysconfdir}/rauc ${D}${sysconfdir}/irtrack
    install -m 0644 ${B}/system.conf ${D}${sysconfdir}/rauc/system.conf
    install -m 0644 ${IRTRACK_UPDATE_CA} ${D}${sysconfdir}/rauc/ca.cert.pem
    install -m 0644 ${S}/image/update/rootfs/etc/fw_env.config ${D}${sysconfdir}/fw_env.config
    install -m 0644 ${B}/release ${D}${sysconfdir}/irtrack/release
    install -d ${D}${nonarch_libdir}/irtrack ${D}${sbindir}
    install -m 0755 ${S}/image/update/rootfs/usr/lib/irtrack/rauc-pre-install ${D}${nonarch_libdir}/irtrack/
    install -m 0755 ${S}/image/update/rootfs/usr/lib/irtrack/rauc-post-install ${D}${nonarch_libdir}/irtrack/
    install -m 0755 ${S}/image/update/rootfs/usr/sbin/irtrack-health ${D}${sbindir}/
    install -m 0755 ${S}/image/update/rootfs/usr/sbin/irtrack-update-agent ${D}${sbindir}/
    install -d ${D}${systemd_system_unitdir}
    install -m 0644 ${WORKDIR}/irtrack-update-agent.service ${D}${systemd_system_unitdir}/
    install -m 0644 ${WORKDIR}/irtrack-health.service ${D}${systemd_system_unitdir}/
    install -m 0644 ${WORKDIR}/var-lib-irtrackd.mount ${D}${systemd_system_unitdir}/
    install -d ${D}${nonarch_libdir}/tmpfiles.d
    install -m 0644 ${WORKDIR}/irtrack-update.tmpfiles ${D}${nonarch_libdir}/tmpfiles.d/irtrack-update.conf
    # Mount points of the boot partition (boot counters) and the data partition (fstab by wic).
    install -d ${D}/uboot ${D}/data
}

# boot.scr and both copies of the first boot counters go on the boot partition (IMAGE_BOOT_FILES).
do_deploy() {
    install -m 0644 ${B}/boot.scr ${DEPLOYDIR}/boot.scr
    install -m 0644 ${B}/uboot.env ${DEPLOYDIR}/uboot.env
    install -m 0644 ${B}/uboot-redund.env ${DEPLOYDIR}/uboot-redund.env
}
addtask deploy after do_compile before do_build

FILES:${PN} += "${nonarch_libdir}/irtrack ${nonarch_libdir}/tmpfiles.d ${systemd_system_unitdir} /uboot /data"
CONFFILES:${PN} = "${sysconfdir}/rauc/system.conf ${sysconfdir}/fw_env.config"

# The health check reads irtrackd's /status; the slots carry their own kernel and device tree.
RDEPENDS:${PN} = "busybox irtrackd kernel-image rauc"
RDEPENDS:${PN}:append:pandaboard = " kernel-devicetree"
