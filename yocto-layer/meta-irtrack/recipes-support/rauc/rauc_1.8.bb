SUMMARY = "RAUC update client: signed A/B root file system updates"
DESCRIPTION = "The update tool of the irtrack board (docs/updates.md): installs a signed \
bundle into the root file system slot that is not running and keeps U-Boot's boot counters, \
so a system that does not come up healthy is left for the previous one. The same release as \
Debian 12's package, which the CI image carries. With meta-rauc in the build, its recipe \
(a newer release) can be used instead: mask this one with BBMASK."
HOMEPAGE = "https://rauc.io"
BUGTRACKER = "https://github.com/rauc/rauc/issues"
SECTION = "base"
LICENSE = "LGPL-2.1-only"
LIC_FILES_CHKSUM = "file://COPYING;md5=4fbd65380cdd255951079008b364516c"

# gdbus-codegen (glib-2.0-native) generates the D-Bus installer interface at build time.
DEPENDS = "dbus glib-2.0 glib-2.0-native json-glib openssl"

# The v1.8 tag.
SRC_URI = "git://github.com/rauc/rauc.git;protocol=https;branch=master"
SRCREV = "bfbf94caf4e3deb3fcef69c8c14a3ac673707153"

S = "${WORKDIR}/git"

inherit autotools pkgconfig systemd

# Bundles are installed from a local file (irtrackd's upload or `rauc install FILE`): no
# network or streaming mode, hence no libcurl or libnl. MBR partitions: no libfdisk.
EXTRA_OECONF = "--disable-network --disable-streaming --enable-service --enable-json \
                --disable-gpt --disable-valgrind --disable-code-coverage \
                --with-systemdunitdir=${systemd_system_unitdir} \
                --with-dbuspolicydir=${datadir}/dbus-1/system.d \
                --with-dbussystemservicedir=${datadir}/dbus-1/system-services \
                --with-dbusinterfacesdir=${datadir}/dbus-1/interfaces"

SYSTEMD_SERVICE:${PN} = "rauc.service"

FILES:${PN} += "${datadir}/dbus-1 ${systemd_system_unitdir}/rauc.service ${libexecdir}/rauc-service.sh"

# Bundles are squashfs images (unsquashfs); the uboot back end keeps the boot counters with
# fw_printenv/fw_setenv.
RDEPENDS:${PN} = "libubootenv-bin squashfs-tools"
