# Precompiled headers, one set for the whole build. Most of a translation unit's compile time
# here is parsing the same headers (Eigen, nlohmann/json, the standard library; GoogleTest and
# GoogleMock in the tests): 6-9 s of a test file's ~18 s on a 2-core CI machine. They are
# precompiled once, by mocap_pch (and mocap_test_pch for the tests), and every target reuses
# them (REUSE_FROM) rather than precompiling its own: most targets here are one file, for which
# a per-target precompiled header would cost as much as it saves.
#
# Reuse needs the same compiler flags as the precompiling target; a target whose flags differ
# gets the compiler's invalid-PCH warning (-Winvalid-pch, which CMake adds) and falls back to
# parsing the headers, so a mismatch costs time, never correctness. The headers are included
# before each file's own: nothing in this tree defines a macro that changes them.
# -DMOCAP_PCH=OFF builds without (the headers each file names then have to be complete, which
# the sanitizer build, scripts/sanitizer_build.sh, keeps checked).
option(MOCAP_PCH "Precompile the common headers once and reuse them in every target" ON)

set(MOCAP_PCH_HEADERS
    <algorithm> <array> <atomic> <chrono> <cmath> <cstdint> <cstdio> <cstdlib> <cstring>
    <filesystem> <fstream> <functional> <map> <memory> <mutex> <optional> <random> <set>
    <sstream> <string> <thread> <unordered_map> <utility> <vector>
    <Eigen/Dense> <nlohmann/json.hpp>)

# Called last in the top-level CMakeLists.txt: every library and executable defined by then
# reuses the set; the test executables (tests/, systemd/'s test) the one with GoogleTest too.
function(mocap_reuse_precompiled_headers)
  if(NOT MOCAP_PCH)
    return()
  endif()
  add_library(mocap_pch OBJECT ${PROJECT_SOURCE_DIR}/cmake/pch.cpp)
  target_link_libraries(mocap_pch PRIVATE Eigen3::Eigen nlohmann_json::nlohmann_json)
  target_compile_options(mocap_pch PRIVATE -pthread)
  target_precompile_headers(mocap_pch PRIVATE ${MOCAP_PCH_HEADERS})
  add_library(mocap_test_pch OBJECT ${PROJECT_SOURCE_DIR}/cmake/pch.cpp)
  target_link_libraries(mocap_test_pch PRIVATE Eigen3::Eigen nlohmann_json::nlohmann_json
                        GTest::gtest GTest::gmock)
  target_compile_options(mocap_test_pch PRIVATE -pthread)
  target_precompile_headers(mocap_test_pch PRIVATE ${MOCAP_PCH_HEADERS}
                            <gtest/gtest.h> <gmock/gmock.h>)
  set(dirs ${PROJECT_SOURCE_DIR})
  while(dirs)
    list(POP_FRONT dirs dir)
    get_property(subdirs DIRECTORY ${dir} PROPERTY SUBDIRECTORIES)
    list(APPEND dirs ${subdirs})
    get_property(targets DIRECTORY ${dir} PROPERTY BUILDSYSTEM_TARGETS)
    foreach(t ${targets})
      get_target_property(type ${t} TYPE)
      if(t MATCHES "^mocap_(test_)?pch$" OR NOT type MATCHES "^(STATIC_LIBRARY|EXECUTABLE)$")
        continue()
      endif()
      # The set's own needs, on every target: its headers' include paths (a target that never
      # used Eigen has none), and -pthread, which defines _REENTRANT, a macro the standard
      # headers read: a PCH made with it is refused by a file compiled without, and back.
      target_include_directories(${t} SYSTEM PRIVATE
          $<TARGET_PROPERTY:Eigen3::Eigen,INTERFACE_INCLUDE_DIRECTORIES>
          $<TARGET_PROPERTY:nlohmann_json::nlohmann_json,INTERFACE_INCLUDE_DIRECTORIES>)
      target_compile_options(${t} PRIVATE -pthread)
      # test_* (tests/, and systemd/'s test of the units) are the GoogleTest executables.
      if(t MATCHES "^test_")
        target_precompile_headers(${t} REUSE_FROM mocap_test_pch)
      else()
        target_precompile_headers(${t} REUSE_FROM mocap_pch)
      endif()
    endforeach()
  endwhile()
endfunction()
