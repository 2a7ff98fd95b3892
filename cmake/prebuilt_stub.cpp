// The one source of a library whose objects come from the main build (cmake/prebuilt_core.cmake):
// CMake needs a source for a library target, and this file has nothing to compile on purpose.
