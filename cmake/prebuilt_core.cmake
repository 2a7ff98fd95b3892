# The sanitizer build's numeric core, taken from the main build (scripts/sanitizer_build.sh).
#
# build-fuzz/ (clang, ASan + UBSan + libFuzzer's coverage) compiles the numeric core without the
# sanitizers anyway (fuzz/CMakeLists.txt says why: no untrusted input reaches it). Compiling it
# there a second time was half of that build, and that build is the critical path of CI's test
# run on 2 cores. With MOCAP_PREBUILT_DIR set to the main build (gcc, same -march), each library
# named below keeps its target, its include paths and its dependencies, but its objects are the
# main build's archive: the target itself compiles one empty file, and whatever links it links
# the main build's archive right after it, before its own dependencies.
#
# Why mixing the two compilers is sound here: both use the Itanium C++ ABI and the same libstdc++
# headers; NDEBUG and EIGEN_RUNTIME_NO_MALLOC are set in both builds; and Eigen's fixed-size
# types take their alignment from the vector ISA, so scripts/sanitizer_build.sh reuses the main
# build only when clang and gcc see the same AVX/AVX-512 macros with the main build's -march (it
# compiles everything otherwise). An inline function compiled by both is taken from one of them
# by the linker: at worst an uninstrumented copy, never a wrong one.
set(MOCAP_PREBUILT_DIR "" CACHE PATH
    "A main build whose numeric-core archives the sanitizer build links instead of compiling them")
# The numeric core: what the sanitizer build compiles uninstrumented (fuzz/CMakeLists.txt) or
# links from MOCAP_PREBUILT_DIR. Included before fuzz/ for that list.
set(MOCAP_NUMERIC_CORE_LIBS mocap_solver mocap_report mocap_ekf mocap_sim mocap_reconstruction)

function(mocap_link_prebuilt_core)
  if(NOT MOCAP_PREBUILT_DIR)
    return()
  endif()
  set(linked "")
  foreach(lib ${MOCAP_NUMERIC_CORE_LIBS})
    if(NOT TARGET ${lib})
      continue()
    endif()
    get_target_property(dir ${lib} BINARY_DIR)
    file(RELATIVE_PATH rel ${PROJECT_BINARY_DIR} ${dir})
    set(archive ${MOCAP_PREBUILT_DIR}/${rel}/lib${lib}.a)
    if(NOT EXISTS ${archive})
      message(WARNING "MOCAP_PREBUILT_DIR: ${archive} does not exist; ${lib} is compiled here")
      continue()
    endif()
    list(APPEND linked ${lib})
    set_property(TARGET ${lib} PROPERTY SOURCES ${PROJECT_SOURCE_DIR}/cmake/prebuilt_stub.cpp)
    get_target_property(interface ${lib} INTERFACE_LINK_LIBRARIES)
    if(NOT interface)
      set(interface "")
    endif()
    set_property(TARGET ${lib} PROPERTY INTERFACE_LINK_LIBRARIES ${archive} ${interface})
  endforeach()
  message(STATUS "Linking ${linked} from ${MOCAP_PREBUILT_DIR}")
endfunction()
