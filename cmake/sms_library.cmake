# Layering the build enforces (gateway/README.md, docs/DECISIONS.md "Where things live").
#
# Every library's headers are included by their path from the project root
# (`#include "gateway/bus/bus_engine.h"`), but no target has the project root as an include
# directory. Each library gets an include root of its own in the build tree holding only its own
# folder: build/include/<target>/gateway/bus/ with a link to each header of gateway/bus/ (and to
# its subfolders of headers that are not a library of their own, such as modbus_map/tables/).
# That root is the library's PUBLIC include directory, so a target can include the headers of
# exactly the libraries it links, directly or through their PUBLIC links: an include of a library
# the target does not link is a compile error, and the "depends on" column of gateway/README.md is
# what the build allows.
#
# Use:
#   sms_library(<target> [STATIC|SHARED|INTERFACE] [SOURCES <file>...] [HEADERS <file>...])
#     add_library(<target> ...) plus its include root: the headers of the folder of the
#     CMakeLists.txt that calls it (HEADERS: only these, for a folder that holds more than one
#     library, as tests/support does). Then link as usual, PUBLIC for what the library's own
#     headers include, PRIVATE for what only its sources use:
#       sms_library(gateway_console SOURCES console.cpp)
#       target_link_libraries(gateway_console PUBLIC gateway_units PRIVATE spdlog::spdlog)
#   sms_include_folder(<target> <PUBLIC|PRIVATE|INTERFACE> <folder> [HEADERS <file>...])
#     the same include root for a target that is not made by sms_library: a test program's
#     own folder (PRIVATE, done by sms_add_test), or a folder whose sources a target compiles
#     itself (tests/fuzz compiles two files of gateway/modbus_tcp/).
#
# A header added to a folder reaches the include root when CMake runs again (the glob below asks
# the build to re-run it when a folder's list of headers changes).

set(SMS_INCLUDE_ROOTS ${CMAKE_BINARY_DIR}/include)

function(sms_include_folder target scope folder)
  cmake_parse_arguments(ARG "" "" "HEADERS" ${ARGN})
  get_filename_component(folder ${folder} ABSOLUTE)
  file(RELATIVE_PATH relative ${PROJECT_SOURCE_DIR} ${folder})
  set(root ${SMS_INCLUDE_ROOTS}/${target})
  set(staged ${root}/${relative})
  # Made anew at each configure, so a header that was removed or moved leaves no link behind.
  file(REMOVE_RECURSE ${staged})
  file(MAKE_DIRECTORY ${staged})
  if(ARG_HEADERS)
    set(headers ${ARG_HEADERS})
  else()
    file(GLOB headers CONFIGURE_DEPENDS RELATIVE ${folder} ${folder}/*.h ${folder}/*.hpp)
    # Subfolders of headers belong to this library unless they are a library (or tests) of their own.
    file(GLOB entries RELATIVE ${folder} ${folder}/*)
    foreach(entry ${entries})
      if(IS_DIRECTORY ${folder}/${entry} AND NOT EXISTS ${folder}/${entry}/CMakeLists.txt)
        file(GLOB_RECURSE nested CONFIGURE_DEPENDS ${folder}/${entry}/*.h)
        if(nested)
          file(CREATE_LINK ${folder}/${entry} ${staged}/${entry} SYMBOLIC)
        endif()
      endif()
    endforeach()
  endif()
  foreach(header ${headers})
    if(NOT EXISTS ${folder}/${header})
      message(FATAL_ERROR "sms_include_folder(${target}): ${folder}/${header} does not exist")
    endif()
    file(CREATE_LINK ${folder}/${header} ${staged}/${header} SYMBOLIC)
  endforeach()
  target_include_directories(${target} ${scope} $<BUILD_INTERFACE:${root}>)
endfunction()

function(sms_library target)
  cmake_parse_arguments(ARG "STATIC;SHARED;INTERFACE" "" "SOURCES;HEADERS" ${ARGN})
  if(ARG_UNPARSED_ARGUMENTS)
    message(FATAL_ERROR "sms_library(${target}): unknown arguments ${ARG_UNPARSED_ARGUMENTS}")
  endif()
  if(ARG_INTERFACE)
    add_library(${target} INTERFACE)
    set(scope INTERFACE)
  else()
    set(kind "")
    if(ARG_STATIC)
      set(kind STATIC)
    elseif(ARG_SHARED)
      set(kind SHARED)
    endif()
    add_library(${target} ${kind} ${ARG_SOURCES})
    set(scope PUBLIC)
  endif()
  if(ARG_HEADERS)
    sms_include_folder(${target} ${scope} ${CMAKE_CURRENT_SOURCE_DIR} HEADERS ${ARG_HEADERS})
  else()
    sms_include_folder(${target} ${scope} ${CMAKE_CURRENT_SOURCE_DIR})
  endif()
endfunction()

# sms_compile_alone(<source>...): sources that include <asm/termbits.h> (tty/termios2_io.h, for
# the termios2 ioctls) never share a unity batch (CMAKE_UNITY_BUILD, scripts/test.sh) with one
# that includes <termios.h>: both define struct termios. Each compiles on its own.
function(sms_compile_alone)
  set_source_files_properties(${ARGN} DIRECTORY ${CMAKE_CURRENT_SOURCE_DIR} PROPERTIES SKIP_UNITY_BUILD_INCLUSION ON)
endfunction()
