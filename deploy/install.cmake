# What `cmake --install` puts where (docs/INSTALL.md); the Debian package (debian/, built by
# scripts/package.sh) is made from the same rules. Included by the top-level CMakeLists.txt.
set(CMAKE_INSTALL_DOCDIR share/doc/sms-gateway CACHE PATH "Documentation (README, docs/, examples)")
include(GNUInstallDirs)

install(TARGETS sms-gateway sms-sim RUNTIME DESTINATION ${CMAKE_INSTALL_BINDIR})

# The systemd units (the gateway, and the simulator for trying it) name the programs by their full
# path: rewritten at install time for the prefix the files actually go to. Installed with prefix
# /usr they go to /lib/systemd/system (Debian 12 keeps units there until the /usr merge is
# complete); any other prefix gets PREFIX/lib/systemd/system (/usr/local/lib/systemd/system is on
# systemd's search path).
install(CODE "
  if(CMAKE_INSTALL_PREFIX STREQUAL \"/usr\")
    set(unit_dir /lib/systemd/system)
  else()
    set(unit_dir \"\${CMAKE_INSTALL_PREFIX}/lib/systemd/system\")
  endif()
  foreach(name sms-gateway.service sms-sim.service)
    file(READ \"${PROJECT_SOURCE_DIR}/deploy/\${name}\" unit)
    string(REPLACE \"/usr/bin/sms-\" \"\${CMAKE_INSTALL_PREFIX}/${CMAKE_INSTALL_BINDIR}/sms-\" unit \"\${unit}\")
    file(WRITE \"${CMAKE_BINARY_DIR}/deploy/\${name}\" \"\${unit}\")
    file(INSTALL \"${CMAKE_BINARY_DIR}/deploy/\${name}\" DESTINATION \"\${unit_dir}\"
         PERMISSIONS OWNER_READ OWNER_WRITE GROUP_READ WORLD_READ)
  endforeach()
")

# Manual pages (generated from --help and config/README.md by scripts/man.sh; a test keeps them current).
install(FILES docs/man/sms-gateway.1 docs/man/sms-sim.1 DESTINATION ${CMAKE_INSTALL_MANDIR}/man1)
install(FILES docs/man/sms-gateway.yaml.5 DESTINATION ${CMAKE_INSTALL_MANDIR}/man5)

# The README of the installed product (the source tree's README.md is about building and testing),
# then the documents in the source tree's layout, so their links to one another keep their sense.
install(FILES deploy/README.installed.md DESTINATION ${CMAKE_INSTALL_DOCDIR} RENAME README.md)
install(DIRECTORY docs/ DESTINATION ${CMAKE_INSTALL_DOCDIR}/docs FILES_MATCHING PATTERN "*.md" PATTERN man EXCLUDE)
# The README's screenshots of the browser console (docs/CONSOLE.md).
install(DIRECTORY docs/screenshots/ DESTINATION ${CMAKE_INSTALL_DOCDIR}/docs/screenshots FILES_MATCHING PATTERN "*.png")
install(FILES config/README.md DESTINATION ${CMAKE_INSTALL_DOCDIR}/config)
install(DIRECTORY config/examples/ DESTINATION ${CMAKE_INSTALL_DOCDIR}/config/examples FILES_MATCHING PATTERN "*.yaml")
# ... and where Debian's users look for examples (the container image has them there too).
install(CODE "file(CREATE_LINK config/examples
  \"\$ENV{DESTDIR}\${CMAKE_INSTALL_PREFIX}/${CMAKE_INSTALL_DOCDIR}/examples\" SYMBOLIC)")

# The Wireshark dissector for the bus monitor's captures (docs/MONITOR.md "Opening a capture").
install(FILES deploy/wireshark/sms_servo.lua DESTINATION ${CMAKE_INSTALL_DATADIR}/sms-gateway/wireshark)

# Prometheus alerting and recording rules for /metrics (docs/OPERATIONS.md "Alerting").
install(FILES deploy/prometheus/sms-gateway-rules.yml DESTINATION ${CMAKE_INSTALL_DATADIR}/sms-gateway/prometheus)
