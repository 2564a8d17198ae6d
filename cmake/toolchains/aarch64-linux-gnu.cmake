# 64-bit ARM (Debian arm64) with Debian's cross toolchain (crossbuild-essential-arm64); the tests
# run under qemu-user. Use through scripts/cross.sh arm64 (docs/ARM.md).
set(SMS_CROSS_TRIPLET aarch64-linux-gnu)
set(SMS_CROSS_PROCESSOR aarch64)
set(SMS_CROSS_QEMU qemu-aarch64-static)
include(${CMAKE_CURRENT_LIST_DIR}/cross-common.cmake)
