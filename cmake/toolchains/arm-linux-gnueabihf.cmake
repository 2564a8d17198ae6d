# 32-bit ARM, hard float (Debian armhf: ARMv7, Thumb-2, VFPv3-D16) with Debian's cross toolchain
# (crossbuild-essential-armhf); the tests run under qemu-user. Use through scripts/cross.sh armhf
# (docs/ARM.md).
set(SMS_CROSS_TRIPLET arm-linux-gnueabihf)
set(SMS_CROSS_PROCESSOR armv7l)
set(SMS_CROSS_QEMU qemu-arm-static)
include(${CMAKE_CURRENT_LIST_DIR}/cross-common.cmake)
# GCC's note that passing some structs by value changed in GCC 7.1 concerns linking with code built
# by GCC 6 or older; everything here is Debian 12's GCC 12. (A note, not a warning: kept quiet.)
set(CMAKE_CXX_FLAGS_INIT "-Wno-psabi")
