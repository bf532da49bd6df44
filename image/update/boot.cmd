# irtrack A/B boot script for U-Boot (compiled to boot.scr by `cargo xtask image build` with
# mkimage). RAUC's `uboot` back end keeps BOOT_ORDER and BOOT_<slot>_LEFT in uboot.env on this
# FAT partition (fw_setenv/fw_printenv with /etc/fw_env.config); this U-Boot stores its own
# environment elsewhere, so the script imports and writes that file itself.
#
# Each boot takes one attempt from the first slot in BOOT_ORDER that has attempts left; the
# booted system gives them back (`rauc status mark-good`) once irtrackd is healthy. A slot
# that never gets there runs out of attempts and the next slot in BOOT_ORDER is booted.

# The counters go through memory at kernel_addr_r (the kernel is loaded there only later);
# loadaddr is where this script itself was loaded.
setenv BOOT_ORDER
setenv BOOT_A_LEFT
setenv BOOT_B_LEFT
if load virtio 0:1 ${kernel_addr_r} uboot.env; then
    env import -c ${kernel_addr_r} 0x4000 BOOT_ORDER BOOT_A_LEFT BOOT_B_LEFT
fi
test -n "${BOOT_ORDER}" || setenv BOOT_ORDER "A B"
test -n "${BOOT_A_LEFT}" || setenv BOOT_A_LEFT 3
test -n "${BOOT_B_LEFT}" || setenv BOOT_B_LEFT 3

setenv irtrack_slot
for BOOT_SLOT in "${BOOT_ORDER}"; do
    if test "x${irtrack_slot}" != "x"; then
        # a slot was chosen already
    elif test "x${BOOT_SLOT}" = "xA"; then
        if test ${BOOT_A_LEFT} -gt 0; then
            setexpr BOOT_A_LEFT ${BOOT_A_LEFT} - 1
            setenv irtrack_slot A
            setenv irtrack_part 2
        fi
    elif test "x${BOOT_SLOT}" = "xB"; then
        if test ${BOOT_B_LEFT} -gt 0; then
            setexpr BOOT_B_LEFT ${BOOT_B_LEFT} - 1
            setenv irtrack_slot B
            setenv irtrack_part 3
        fi
    fi
done

if test "x${irtrack_slot}" = "x"; then
    # Neither slot has attempts left (both failed, or the file was lost): give both their
    # attempts back and start over rather than leaving the board without a system.
    echo "irtrack-boot: no slot with attempts left; resetting both to 3"
    setenv BOOT_A_LEFT 3
    setenv BOOT_B_LEFT 3
    env export -c -s 0x4000 ${kernel_addr_r} BOOT_ORDER BOOT_A_LEFT BOOT_B_LEFT
    fatwrite virtio 0:1 ${kernel_addr_r} uboot.env 0x4000
    reset
fi

echo "irtrack-boot: slot ${irtrack_slot} (BOOT_ORDER=${BOOT_ORDER}, A left ${BOOT_A_LEFT}, B left ${BOOT_B_LEFT})"
# The attempt is counted before the kernel starts, so a hang anywhere after this line costs it.
env export -c -s 0x4000 ${kernel_addr_r} BOOT_ORDER BOOT_A_LEFT BOOT_B_LEFT
fatwrite virtio 0:1 ${kernel_addr_r} uboot.env 0x4000

# Kernel and initramfs come from the slot itself, so an update replaces them with the modules.
load virtio 0:${irtrack_part} ${kernel_addr_r} /boot/Image
load virtio 0:${irtrack_part} ${ramdisk_addr_r} /boot/initrd.gz
setenv irtrack_initrd_size ${filesize}
setenv bootargs "console=ttyAMA0 root=/dev/vda${irtrack_part} rootwait quiet rauc.slot=${irtrack_slot}"
booti ${kernel_addr_r} ${ramdisk_addr_r}:${irtrack_initrd_size} ${fdt_addr}
echo "irtrack-boot: booting slot ${irtrack_slot} failed"
# The attempt is spent; the next reset tries again or falls back.
reset
