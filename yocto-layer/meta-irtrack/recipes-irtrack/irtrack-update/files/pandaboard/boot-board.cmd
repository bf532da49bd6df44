# Board part of the irtrack boot script for the Pandaboard (MACHINE = "pandaboard"): the SD
# card is mmc 0, the slots carry /boot/zImage and the device trees, and U-Boot's OMAP4 board
# code names the right one (Panda or Panda ES) in ${fdtfile}.
setenv irtrack_iface mmc
setenv irtrack_devnum 0
setenv irtrack_root /dev/mmcblk0p
setenv irtrack_console ttyS2,115200n8
setenv irtrack_boot 'load ${irtrack_iface} ${irtrack_devnum}:${irtrack_part} ${kernel_addr_r} /boot/zImage; load ${irtrack_iface} ${irtrack_devnum}:${irtrack_part} ${fdt_addr_r} /boot/${fdtfile}; bootz ${kernel_addr_r} - ${fdt_addr_r}'
