SUMMARY = "irtrack optical tracking service"
DESCRIPTION = "irtrackd captures two or more IR cameras through V4L2, finds the hand-held \
tool's LED, triangulates it and streams positions over TCP to a robot controller. It shows \
its state on GPIO status LEDs and takes calibration parameters over the network."
HOMEPAGE = "https://example.invalid/irtrack"
BUGTRACKER = "https://example.invalid/irtrack/issues"
SECTION = "console/utils"
# The workspace is dual-licensed and ships no license files of its own.
LICENSE = "MIT | Apache-2.0"
# nooelint: oelint.var.licenseremotefile - the sources carry no license texts; the common ones are exact
LIC_FILES_CHKSUM = "file://${COMMON_LICENSE_DIR}/MIT;md5=0835ade698e0bcf8506ecda2f7b4f302 \
                    file://${COMMON_LICENSE_DIR}/Apache-2.0;md5=89aea4e17d99a7cacdbeed46a0096b10"

PV = "0.1.0+git"

# The repository's URL; a site with its own mirror overrides SRC_URI in a bbappend. The pinned
# commit (SRCREV) is in irtrack-source.inc, shared with irtrack-update. For development build a
# checkout instead: INHERIT += "externalsrc" and EXTERNALSRC:pn-irtrackd = "/path/to/irtrack"
# (what yocto-layer/kas/irtrack.yml does).
SRC_URI = "git://example.invalid/irtrack.git;protocol=https;branch=main \
           file://irtrackd.toml \
           file://99-irtrack.rules \
           "
require recipes-irtrack/irtrack-source.inc

# scarthgap (the layer's LAYERSERIES_COMPAT) unpacks fetched sources into WORKDIR.
S = "${WORKDIR}/git"

inherit cargo systemd useradd

# crate:// sources with checksums, generated from Cargo.lock (`cargo xtask image crates`), so
# do_compile runs offline.
require ${BPN}-crates.inc

# Only the board service; host-tools (OpenCV) stays on the PC.
CARGO_BUILD_FLAGS:append = " -p irtrack-firmware --bin irtrackd"

# The camera-board and solver roles over Zenoh (docs/cluster.md), built in by default so one
# image serves every board of a cell; `PACKAGECONFIG:remove:pn-irtrackd = "cluster"` in a
# distro or local.conf leaves them out (standalone only, about 10 MB smaller binary).
PACKAGECONFIG ??= "cluster"
PACKAGECONFIG[cluster] = ",,,"
CARGO_BUILD_FLAGS:append = "${@bb.utils.contains('PACKAGECONFIG', 'cluster', ' --features cluster', '', d)}"

USERADD_PACKAGES = "${PN}"
GROUPADD_PARAM:${PN} = "--system irtrack"
USERADD_PARAM:${PN} = "--system --no-create-home --home-dir ${localstatedir}/lib/irtrackd \
                       --shell /sbin/nologin --gid irtrack irtrack"

# The PTP units run ptp4l/phc2sys (meta-oe's linuxptp) with the config irtrackd generates from
# [clock]; with `ptp = false` (the default) their ExecCondition skips them (docs/cluster.md).
SYSTEMD_SERVICE:${PN} = "irtrackd.service irtrack-ptp4l.service irtrack-phc2sys.service"
SYSTEMD_AUTO_ENABLE:${PN} = "enable"

do_install:append() {
    install -d ${D}${systemd_system_unitdir}
    install -m 0644 ${S}/systemd/irtrackd.service ${D}${systemd_system_unitdir}/
    install -m 0644 ${S}/systemd/irtrack-ptp4l.service ${D}${systemd_system_unitdir}/
    install -m 0644 ${S}/systemd/irtrack-phc2sys.service ${D}${systemd_system_unitdir}/
    install -d ${D}${sysconfdir}/irtrack
    install -m 0644 ${WORKDIR}/irtrackd.toml ${D}${sysconfdir}/irtrack/irtrackd.toml
    install -d ${D}${sysconfdir}/irtrack/trusted-keys
    install -d ${D}${nonarch_base_libdir}/udev/rules.d
    install -m 0644 ${WORKDIR}/99-irtrack.rules ${D}${nonarch_base_libdir}/udev/rules.d/
    install -d ${D}${systemd_system_unitdir}/irtrackd.service.d
    install -m 0644 ${S}/systemd/irtrackd-realtime.conf ${D}${systemd_system_unitdir}/irtrackd.service.d/realtime.conf
}

# The real-time drop-in (RestrictRealtime=no, LimitRTPRIO=90) for [realtime] fifo_priority and
# [cluster] transport_fifo_priority, in a package of its own: adding it to an image is the
# per-installation choice the main unit leaves open (systemd/irtrackd-realtime.conf).
PACKAGES =+ "${PN}-realtime"
FILES:${PN}-realtime += "${systemd_system_unitdir}/irtrackd.service.d/realtime.conf"
FILES:${PN} += "${systemd_system_unitdir}/irtrackd.service \
                ${systemd_system_unitdir}/irtrack-ptp4l.service \
                ${systemd_system_unitdir}/irtrack-phc2sys.service \
                ${nonarch_base_libdir}/udev/rules.d/99-irtrack.rules"
CONFFILES:${PN} = "${sysconfdir}/irtrack/irtrackd.toml"

# ptp4l and phc2sys for irtrack-ptp4l.service and irtrack-phc2sys.service. linuxptp >= 4.0 also
# gives the read-only socket /var/run/ptp4lro that the sandboxed irtrackd reads clock.ptp from.
RDEPENDS:${PN} += "linuxptp"
RDEPENDS:${PN}-realtime += "${PN}"
