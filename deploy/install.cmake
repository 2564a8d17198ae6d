# What `cmake --install` puts where, and the Debian package CPack builds from it
# (README "Install"; scripts/package.sh). Included by the top-level CMakeLists.txt.
set(CMAKE_INSTALL_DOCDIR share/doc/sms-gateway CACHE PATH "Documentation (README, docs/, examples)")
include(GNUInstallDirs)

install(TARGETS sms-gateway sms-sim RUNTIME DESTINATION ${CMAKE_INSTALL_BINDIR})

# The systemd unit names the program by its full path: rewritten at install time for the prefix
# the files actually go to (/usr in the package, /usr/local for a plain `cmake --install`).
install(CODE "
  file(READ \"${PROJECT_SOURCE_DIR}/deploy/sms-gateway.service\" unit)
  string(REPLACE \"/usr/local/bin/\" \"\${CMAKE_INSTALL_PREFIX}/${CMAKE_INSTALL_BINDIR}/\" unit \"\${unit}\")
  file(WRITE \"${CMAKE_BINARY_DIR}/deploy/sms-gateway.service\" \"\${unit}\")
")
install(FILES ${CMAKE_BINARY_DIR}/deploy/sms-gateway.service DESTINATION lib/systemd/system)

install(FILES README.md DESTINATION ${CMAKE_INSTALL_DOCDIR})
install(FILES docs/DECISIONS.md docs/OPERATIONS.md docs/REGISTER_MAP.md docs/RTU_PANELS.md DESTINATION ${CMAKE_INSTALL_DOCDIR})
install(FILES config/README.md DESTINATION ${CMAKE_INSTALL_DOCDIR} RENAME CONFIGURATION.md)
install(DIRECTORY config/examples/ DESTINATION ${CMAKE_INSTALL_DOCDIR}/examples FILES_MATCHING PATTERN "*.yaml")

set(CPACK_GENERATOR DEB)
set(CPACK_PACKAGE_NAME sms-gateway)
set(CPACK_PACKAGE_VENDOR "sms-gateway developers")
set(CPACK_PACKAGE_CONTACT "sms-gateway developers <sms-gateway@localhost>")
set(CPACK_PACKAGE_DESCRIPTION_SUMMARY "Modbus TCP gateway for RS-485 serial-bus servos (Feetech FF FF, D5 5D, SMSMB)")
set(CPACK_PACKAGE_DESCRIPTION "PLCs and HMIs drive Feetech SCS/STS/SMS, D5 5D and SMS Modbus-RTU servos over \
Modbus TCP: control tables as registers, a poll cache for feedback, SYNC WRITE groups, a watchdog and an e-stop latch; \
with a servo simulator (sms-sim) and integrator tools (scan, set-id, set-baud).")
set(CPACK_DEBIAN_FILE_NAME DEB-DEFAULT)  # sms-gateway_VERSION_ARCH.deb
set(CPACK_DEBIAN_PACKAGE_SECTION net)
set(CPACK_DEBIAN_PACKAGE_PRIORITY optional)
# Library dependencies from the binaries (dpkg-shlibdeps), plus what the maintainer scripts use.
set(CPACK_DEBIAN_PACKAGE_SHLIBDEPS ON)
set(CPACK_DEBIAN_PACKAGE_DEPENDS "adduser")
set(CPACK_DEBIAN_PACKAGE_CONTROL_EXTRA
    ${PROJECT_SOURCE_DIR}/deploy/debian/postinst ${PROJECT_SOURCE_DIR}/deploy/debian/prerm
    ${PROJECT_SOURCE_DIR}/deploy/debian/postrm)
set(CPACK_DEBIAN_PACKAGE_CONTROL_STRICT_PERMISSION ON)
set(CPACK_STRIP_FILES ON)
include(CPack)
