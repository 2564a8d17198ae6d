# Shared part of the ARM toolchain files (aarch64-linux-gnu.cmake, arm-linux-gnueabihf.cmake):
# Debian's cross compilers and the target's libraries, found either as multiarch packages on this
# machine (dpkg --add-architecture; the libraries live in /usr/lib/<triplet>) or in a sysroot made
# from the target's packages (SMS_CROSS_SYSROOT). scripts/cross.sh sets everything up; docs/ARM.md.
# Expects SMS_CROSS_TRIPLET, SMS_CROSS_PROCESSOR and SMS_CROSS_QEMU from the including file.
set(CMAKE_SYSTEM_NAME Linux)
set(CMAKE_SYSTEM_PROCESSOR ${SMS_CROSS_PROCESSOR})
set(CMAKE_C_COMPILER ${SMS_CROSS_TRIPLET}-gcc)
set(CMAKE_CXX_COMPILER ${SMS_CROSS_TRIPLET}-g++)
# find_library and find_package look in /usr/lib/<triplet> first, never in the build machine's.
set(CMAKE_LIBRARY_ARCHITECTURE ${SMS_CROSS_TRIPLET})

# The sysroot and the extra prefixes reach try_compile and every re-configure through these.
set(SMS_CROSS_SYSROOT "$ENV{SMS_CROSS_SYSROOT}" CACHE PATH "Target root made from the target's packages (empty: multiarch)")
set(SMS_CROSS_PREFIXES "$ENV{SMS_CROSS_PREFIXES}" CACHE STRING "Extra target prefixes (packages that cannot be co-installed)")
list(APPEND CMAKE_TRY_COMPILE_PLATFORM_VARIABLES SMS_CROSS_SYSROOT SMS_CROSS_PREFIXES)

if(SMS_CROSS_SYSROOT)
  set(CMAKE_SYSROOT ${SMS_CROSS_SYSROOT})
  set(CMAKE_FIND_ROOT_PATH ${SMS_CROSS_SYSROOT} ${SMS_CROSS_PREFIXES})
  # Build tools (protoc) are the build machine's; libraries, headers and packages the target's.
  set(CMAKE_FIND_ROOT_PATH_MODE_PROGRAM NEVER)
  set(CMAKE_FIND_ROOT_PATH_MODE_LIBRARY ONLY)
  set(CMAKE_FIND_ROOT_PATH_MODE_INCLUDE ONLY)
  set(CMAKE_FIND_ROOT_PATH_MODE_PACKAGE ONLY)
  # The build machine's pkg-config, pointed at the sysroot: the target's pkg-config wrapper comes
  # with the target's pkgconf package, which is in the sysroot, not on the machine (debhelper's
  # cross build names it all the same: replaced here).
  set(PKG_CONFIG_EXECUTABLE pkg-config CACHE FILEPATH "pkg-config, with the sysroot's search path" FORCE)
  set(ENV{PKG_CONFIG_SYSROOT_DIR} ${SMS_CROSS_SYSROOT})
  set(ENV{PKG_CONFIG_LIBDIR} "${SMS_CROSS_SYSROOT}/usr/lib/${SMS_CROSS_TRIPLET}/pkgconfig:${SMS_CROSS_SYSROOT}/usr/share/pkgconfig")
  set(CMAKE_CROSSCOMPILING_EMULATOR ${SMS_CROSS_QEMU} -L ${SMS_CROSS_SYSROOT})
else()
  # Multiarch: the target's libraries are in /usr/lib/<triplet>, its headers in /usr/include
  # (arch-specific ones in /usr/include/<triplet>, which the cross compiler searches itself).
  set(CMAKE_PREFIX_PATH ${SMS_CROSS_PREFIXES})
  set(ENV{PKG_CONFIG_LIBDIR} "/usr/lib/${SMS_CROSS_TRIPLET}/pkgconfig:/usr/share/pkgconfig")
  # The target's dynamic loader and libraries are at their usual paths: qemu needs no prefix.
  set(CMAKE_CROSSCOMPILING_EMULATOR ${SMS_CROSS_QEMU})
endif()
