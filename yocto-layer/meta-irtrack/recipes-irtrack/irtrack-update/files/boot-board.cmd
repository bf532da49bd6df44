# Board part of the irtrack boot script for QEMU's arm64 virt machine (MACHINE = "qemuarm64"):
# the disk is virtio 0, the slots carry /boot/Image, and QEMU passes the device tree.
setenv irtrack_iface virtio
setenv irtrack_devnum 0
setenv irtrack_root /dev/vda
setenv irtrack_console ttyAMA0
setenv irtrack_boot 'load ${irtrack_iface} ${irtrack_devnum}:${irtrack_part} ${kernel_addr_r} /boot/Image; booti ${kernel_addr_r} - ${fdt_addr}'
