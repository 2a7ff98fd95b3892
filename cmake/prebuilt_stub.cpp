// The one file of a library whose objects come from the main build (cmake/prebuilt_core.cmake).
namespace mocap::prebuilt_core {
int linked_from_the_main_build = 0;
}  // namespace mocap::prebuilt_core
