# irtrack A/B boot script for U-Boot (compiled to boot.scr by `cargo xtask image build` with
# mkimage). RAUC's `uboot` back end keeps BOOT_ORDER and BOOT_<slot>_LEFT in a U-Boot
# environment on this FAT partition (fw_setenv/fw_printenv with /etc/fw_env.config); this
# U-Boot stores its own environment elsewhere, so the script reads and writes it itself.
#
# Each boot takes one attempt from the first slot in BOOT_ORDER that has attempts left; the
# booted system gives them back (`rauc status mark-good`) once irtrackd is healthy. A slot
# that never gets there runs out of attempts and the next slot in BOOT_ORDER is booted.
#
# The counters are kept twice, in libubootenv's redundant layout (docs/updates.md, "Boot
# counters"): uboot.env (copy 0) and uboot-redund.env (copy 1), 0x4000 bytes each: CRC32
# (little-endian) of the data, one flags byte, then the data ("name=value" strings, each
# ended by a NUL, an empty string last). A copy counts only if it is whole and its CRC
# matches; of two valid copies the one with the higher flags byte wins (255 -> 0 wraps: 0
# wins over 255), as libubootenv decides. Every write, here and by fw_setenv, goes to the
# copy that did not win, with the winner's flags + 1, so a power cut during a write leaves the
# winning copy untouched and the next boot reads it.

# The board's part: where the SD card is, which console, and how to load and start the chosen
# slot's kernel. The defaults are QEMU's arm64 virt machine (this image); a board sets them
# before this script runs (the Yocto layer puts its files/<MACHINE>/boot-board.cmd first).
test -n "${irtrack_iface}" || setenv irtrack_iface virtio
test -n "${irtrack_devnum}" || setenv irtrack_devnum 0
test -n "${irtrack_root}" || setenv irtrack_root /dev/vda
test -n "${irtrack_console}" || setenv irtrack_console ttyAMA0
# Kernel and initramfs come from the slot itself, so an update replaces them with the modules.
test -n "${irtrack_boot}" || setenv irtrack_boot 'load ${irtrack_iface} ${irtrack_devnum}:${irtrack_part} ${kernel_addr_r} /boot/Image; load ${irtrack_iface} ${irtrack_devnum}:${irtrack_part} ${ramdisk_addr_r} /boot/initrd.gz; setenv irtrack_initrd_size ${filesize}; booti ${kernel_addr_r} ${ramdisk_addr_r}:${irtrack_initrd_size} ${fdt_addr}'

# Scratch memory is at kernel_addr_r (the kernel is loaded there only later): each copy as
# read, the copy to write, and a buffer in `env import/export -c` layout (CRC, then the
# data), which has no flags byte. `env export` clears its whole maximum environment size
# after the address it is given, so that buffer comes last.
setexpr irtrack_c0 ${kernel_addr_r} + 0
setexpr irtrack_c1 ${kernel_addr_r} + 10000
setexpr irtrack_out ${kernel_addr_r} + 20000
setexpr irtrack_env ${kernel_addr_r} + 100000
setexpr irtrack_env_data ${irtrack_env} + 4

setenv irtrack_ok0 no
setenv irtrack_ok1 no
for irtrack_i in 0 1; do
    if test "${irtrack_i}" = "0"; then
        setenv irtrack_file uboot.env
        setenv irtrack_at ${irtrack_c0}
    else
        setenv irtrack_file uboot-redund.env
        setenv irtrack_at ${irtrack_c1}
    fi
    setenv irtrack_valid no
    # Cleared first: a short (truncated) file must not be completed by older memory.
    mw.b ${irtrack_at} 0 4000
    if load ${irtrack_iface} ${irtrack_devnum}:1 ${irtrack_at} ${irtrack_file}; then
        if test "${filesize}" = "4000"; then
            # env import -c checks the CRC; it wants the data right after the CRC.
            cp.b ${irtrack_at} ${irtrack_env} 4
            setexpr irtrack_from ${irtrack_at} + 5
            cp.b ${irtrack_from} ${irtrack_env_data} 3ffb
            if env import -c ${irtrack_env} 3fff BOOT_ORDER BOOT_A_LEFT BOOT_B_LEFT; then
                setenv irtrack_valid yes
            fi
        else
            echo "irtrack-boot: ${irtrack_file} is ${filesize} bytes, not 4000"
        fi
    fi
    if test "${irtrack_i}" = "0"; then
        setenv irtrack_ok0 ${irtrack_valid}
    else
        setenv irtrack_ok1 ${irtrack_valid}
    fi
done

setexpr irtrack_f0_at ${irtrack_c0} + 4
setexpr irtrack_f1_at ${irtrack_c1} + 4
setexpr.b irtrack_f0 *${irtrack_f0_at}
setexpr.b irtrack_f1 *${irtrack_f1_at}
setenv irtrack_cur none
if test "${irtrack_ok0}${irtrack_ok1}" = "yesyes"; then
    setenv irtrack_cur 0
    if itest.b *${irtrack_f1_at} -gt *${irtrack_f0_at}; then
        setenv irtrack_cur 1
    fi
    if test "${irtrack_f0}" = "ff" && test "${irtrack_f1}" = "0"; then
        setenv irtrack_cur 1
    fi
    if test "${irtrack_f1}" = "ff" && test "${irtrack_f0}" = "0"; then
        setenv irtrack_cur 0
    fi
elif test "${irtrack_ok0}" = "yes"; then
    setenv irtrack_cur 0
elif test "${irtrack_ok1}" = "yes"; then
    setenv irtrack_cur 1
fi

# Only the winner's values count (a valid loser was imported above as well).
setenv BOOT_ORDER
setenv BOOT_A_LEFT
setenv BOOT_B_LEFT
if test "${irtrack_cur}" = "none"; then
    # Nothing to trust (both copies lost): start over, and write copy 0 first.
    echo "irtrack-boot: no valid boot counter copy (uboot.env ${irtrack_ok0}, uboot-redund.env ${irtrack_ok1}); using BOOT_ORDER=A B with 3 attempts each"
    setenv irtrack_flags 0
    setenv irtrack_next_file uboot.env
else
    if test "${irtrack_cur}" = "0"; then
        setenv irtrack_at ${irtrack_c0}
        setenv irtrack_flags ${irtrack_f0}
        setenv irtrack_next_file uboot-redund.env
    else
        setenv irtrack_at ${irtrack_c1}
        setenv irtrack_flags ${irtrack_f1}
        setenv irtrack_next_file uboot.env
    fi
    cp.b ${irtrack_at} ${irtrack_env} 4
    setexpr irtrack_from ${irtrack_at} + 5
    cp.b ${irtrack_from} ${irtrack_env_data} 3ffb
    env import -c ${irtrack_env} 3fff BOOT_ORDER BOOT_A_LEFT BOOT_B_LEFT
    echo "irtrack-boot: boot counters from copy ${irtrack_cur} (flags 0x${irtrack_flags}; uboot.env valid ${irtrack_ok0} flags 0x${irtrack_f0}, uboot-redund.env valid ${irtrack_ok1} flags 0x${irtrack_f1})"
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
    # Neither slot has attempts left (both failed): give both their attempts back and start
    # over rather than leaving the board without a system.
    echo "irtrack-boot: no slot with attempts left; resetting both to 3"
    setenv BOOT_A_LEFT 3
    setenv BOOT_B_LEFT 3
fi

# Write the new counters into the copy that did not win, with flags + 1 (setexpr numbers are
# hex: `% 100` wraps 255 to 0).
# The attempt is counted before the kernel starts, so a hang anywhere after this costs it.
setexpr irtrack_next_flags ${irtrack_flags} + 1
setexpr irtrack_next_flags ${irtrack_next_flags} % 100
env export -c -s 3fff ${irtrack_env} BOOT_ORDER BOOT_A_LEFT BOOT_B_LEFT
mw.b ${irtrack_out} 0 4000
cp.b ${irtrack_env} ${irtrack_out} 4
setexpr irtrack_to ${irtrack_out} + 4
mw.b ${irtrack_to} ${irtrack_next_flags}
setexpr irtrack_to ${irtrack_out} + 5
cp.b ${irtrack_env_data} ${irtrack_to} 3ffb
fatwrite ${irtrack_iface} ${irtrack_devnum}:1 ${irtrack_out} ${irtrack_next_file} 4000

if test "x${irtrack_slot}" = "x"; then
    reset
fi

echo "irtrack-boot: slot ${irtrack_slot} (BOOT_ORDER=${BOOT_ORDER}, A left ${BOOT_A_LEFT}, B left ${BOOT_B_LEFT}; written to ${irtrack_next_file} with flags 0x${irtrack_next_flags})"

setenv bootargs "console=${irtrack_console} root=${irtrack_root}${irtrack_part} rootwait quiet rauc.slot=${irtrack_slot}"
run irtrack_boot
echo "irtrack-boot: booting slot ${irtrack_slot} failed"
# The attempt is spent; the next reset tries again or falls back.
reset
