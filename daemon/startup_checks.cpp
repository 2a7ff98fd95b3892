#include "daemon/startup_checks.h"

#include <arv.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <filesystem>

#include "daemon/config.h"
#include "drivers/usb_hotplug.h"

namespace mocap::daemon {

namespace {

StartupCheck Fail(int code, std::string message) { return {Status::Error(std::move(message)), code}; }

}  // namespace

StartupCheck CheckStateDir(const std::string& state_dir) {
  const std::string key = "[storage] state_dir '" + state_dir + "'";
  struct stat st {};
  if (stat(state_dir.c_str(), &st) != 0) {
    if (errno != ENOENT) return Fail(kExitNoPermission, key + ": " + std::strerror(errno));
    // Not there: Store::Open creates it, which needs a writable parent.
    std::filesystem::path parent = std::filesystem::path(state_dir).parent_path();
    while (!parent.empty() && stat(parent.c_str(), &st) != 0 && errno == ENOENT)
      parent = parent.parent_path();
    if (parent.empty()) parent = ".";
    if (access(parent.c_str(), W_OK | X_OK) != 0)
      return Fail(kExitCannotCreate, key + ": does not exist and cannot be created in '" +
                                         parent.string() + "' by uid " + std::to_string(getuid()) +
                                         ": " + std::strerror(errno));
    return {};
  }
  if (!S_ISDIR(st.st_mode)) return Fail(kExitConfig, key + ": exists and is not a directory");
  if (access(state_dir.c_str(), R_OK | W_OK | X_OK) != 0)
    return Fail(kExitNoPermission, key + ": not readable and writable by uid " +
                                       std::to_string(getuid()) + ": " + std::strerror(errno));
  return {};
}

StartupCheck CheckSocketPath(const std::string& socket_path) {
  struct stat st {};
  if (lstat(socket_path.c_str(), &st) != 0) return {};  // absent: created at start
  if (!S_ISSOCK(st.st_mode))
    return Fail(kExitConfig, "[control] socket '" + socket_path +
                                 "': exists and is not a socket (remove it or choose another path)");
  return {};
}

StartupCheck CheckStartup(const DaemonConfig& config, bool socket_activated) {
  if (StartupCheck c = CheckStateDir(config.state_dir); !c.ok()) return c;
  if (!socket_activated) return CheckSocketPath(config.socket_path);
  return {};
}

std::string UsbfsAdvice(const DaemonConfig& config, const std::string& usbfs_path) {
  if (config.simulated_cameras > 0 || config.cameras.empty()) return "";
  arv_update_device_list();
  int usb = 0;
  for (const CameraConfig& c : config.cameras) {
    for (unsigned i = 0; i < arv_get_n_devices(); ++i) {
      const char* id = arv_get_device_id(i);
      const char* serial = arv_get_device_serial_nbr(i);
      const char* protocol = arv_get_device_protocol(i);
      if (!((id && c.id == id) || (serial && c.id == serial))) continue;
      if (protocol && std::strcmp(protocol, "USB3Vision") == 0) ++usb;
      break;
    }
  }
  if (usb == 0) return "";
  drivers::CameraSettings settings;
  settings.pixel_format = drivers::PixelFormat::kMono8;
  settings.buffer_count = 32;  // as Daemon::Start opens them
  const Status s = drivers::CheckUsbfsMemory(
      drivers::UsbfsBytesNeeded(usb, settings, config.width, config.height), usbfs_path);
  return s.ok() ? "" : s.message();
}

}  // namespace mocap::daemon
