# Board part of the irtrack boot script for the armv7 CI image: QEMU's 32-bit virt machine
# (qemu-system-arm -M virt, U-Boot's qemu_arm build). `cargo xtask image armv7` puts it before
# image/update/boot.cmd (the Yocto layer does the same with files/<MACHINE>/boot-board.cmd).
# Disk and console are the arm64 image's (virtio 0, the PL011 as ttyAMA0); what differs is the
# kernel: each slot carries an ARM zImage, which bootz starts (booti is arm64's). The device
# tree is QEMU's, at ${fdt_addr}, as U-Boot's extlinux boot of the single-root image used it.
setenv irtrack_iface virtio
setenv irtrack_devnum 0
setenv irtrack_root /dev/vda
setenv irtrack_console ttyAMA0
setenv irtrack_boot 'load ${irtrack_iface} ${irtrack_devnum}:${irtrack_part} ${kernel_addr_r} /boot/zImage; load ${irtrack_iface} ${irtrack_devnum}:${irtrack_part} ${ramdisk_addr_r} /boot/initrd.gz; setenv irtrack_initrd_size ${filesize}; bootz ${kernel_addr_r} ${ramdisk_addr_r}:${irtrack_initrd_size} ${fdt_addr}'
