# The Pandaboard (conf/machine/pandaboard.conf): linux-yocto's kernel cache has no OMAP4 board
# description, so the kernel's own omap2plus_defconfig configures it, with a fragment for what
# irtrackd needs (UVC cameras, the GPIO character device). Only this machine is affected.
FILESEXTRAPATHS:prepend:pandaboard := "${THISDIR}/files:"
COMPATIBLE_MACHINE:pandaboard = "pandaboard"
KMACHINE:pandaboard = "pandaboard"
KBUILD_DEFCONFIG:pandaboard = "omap2plus_defconfig"
KCONFIG_MODE:pandaboard = "alldefconfig"
SRC_URI:append:pandaboard = " file://irtrack-pandaboard.cfg"
