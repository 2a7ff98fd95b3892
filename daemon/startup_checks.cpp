#include "daemon/startup_checks.h"

#include <arv.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstring>
#include <filesystem>

#include "daemon/config.h"
#include "drivers/usb_hotplug.h"

namespace mocap::daemon {

namespace {

StartupCheck Fail(int code, std::string message) { return {Status::Error(std::move(message)), code}; }

std::string Mb(double v) {
  char b[32];
  std::snprintf(b, sizeof b, "%.1f", v);
  return b;
}

constexpr int kDefaultPacketSize = 1500;
constexpr int kGvspHeaderBytes = 36;   // IP 20 + UDP 8 + GVSP 8, inside the packet
constexpr int kEthernetWireBytes = 38;  // header 14 + FCS 4 + preamble 8 + gap 12, around it

// Image bytes per wire byte on a GigE Vision link.
double GigeEfficiency(const DaemonConfig& c) {
  const double packet = c.packet_size > 0 ? c.packet_size : kDefaultPacketSize;
  return (packet - kGvspHeaderBytes) / (packet + kEthernetWireBytes);
}

double CapacityMbS(const std::string& interface) {
  if (interface == "10gige") return 1250.0;
  if (interface == "usb3") return 400.0;
  return 125.0;
}

// The camera's configured bytes per buffer: the usbfs memory a stream buffer pins.
double FrameBytes(const DaemonConfig& c) {
  return static_cast<double>(c.width) * c.height * ConfiguredBytesPerPixel(c.pixel_format);
}

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

std::vector<LinkLoad> RigLinkLoads(const DaemonConfig& config) {
  std::vector<LinkLoad> links;
  const double image_mb_s = CameraImageMbS(config);
  for (const CameraConfig& cam : config.cameras) {
    // A simulated rig's fakes carry nothing over a wire: only the links it plans are checked.
    if (config.simulated_cameras > 0 && cam.link.empty()) continue;
    const std::string name = cam.link.empty() ? cam.id : cam.link;
    LinkLoad* link = nullptr;
    for (LinkLoad& l : links)
      if (l.link == name) link = &l;
    if (!link) {
      links.push_back({name, cam.interface, {}, CapacityMbS(cam.interface), 0, image_mb_s});
      link = &links.back();
    }
    link->cameras.push_back(cam.id);
    const bool gige = cam.interface != "usb3";
    link->needed_mb_s += gige ? image_mb_s / GigeEfficiency(config) : image_mb_s;
  }
  return links;
}

StartupCheck CheckRigBandwidth(const DaemonConfig& config) {
  for (const CameraConfig& cam : config.cameras) {
    for (const CameraConfig& other : config.cameras) {
      if (cam.link.empty() || cam.link != other.link || cam.interface == other.interface) continue;
      return Fail(kExitConfig, "[rig] cameras '" + cam.id + "' (" + cam.interface + ") and '" +
                                   other.id + "' (" + other.interface + ") share link '" +
                                   cam.link + "': one link has one interface");
    }
  }
  std::string problems;
  for (const LinkLoad& l : RigLinkLoads(config)) {
    if (l.needed_mb_s <= l.capacity_mb_s) continue;
    const bool gige = l.interface != "usb3";
    const double efficiency = gige ? GigeEfficiency(config) : 1.0;
    const double n = static_cast<double>(l.cameras.size());
    // What one camera may send of the link's images: its share.
    const double share_bytes_s = l.capacity_mb_s * 1e6 * efficiency / n;
    const double bpp = ConfiguredBytesPerPixel(config.pixel_format);
    const int max_rate = static_cast<int>(share_bytes_s / FrameBytes(config));
    const int max_height = static_cast<int>(share_bytes_s / (config.width * bpp * config.rate_hz));
    std::string names;
    for (const std::string& c : l.cameras) names += (names.empty() ? "'" : ", '") + c + "'";
    std::string fix = "rig.rate <= " + std::to_string(max_rate) + " Hz, or a ROI of " +
                      std::to_string(config.width) + " x <= " + std::to_string(max_height) +
                      " px (rig.height) at " + Mb(config.rate_hz) + " Hz";
    if (bpp > 1.5) fix += ", or pixel_format \"Mono12Packed\" (1.5 bytes/px) or \"Mono8\"";
    if (l.interface == "gige") fix += ", or a 10gige link";
    if (l.cameras.size() > 1) fix += ", or fewer cameras on the link (link = \"...\" per camera)";
    if (gige && config.packet_size < 8000) fix += "; jumbo frames (packet_size = 9000) save a few %";
    problems += std::string(problems.empty() ? "" : "; ") + "link '" + l.link + "' (" +
                l.interface + ") carries " + std::to_string(l.cameras.size()) + " camera" +
                (l.cameras.size() > 1 ? "s " : " ") + names + " needing " + Mb(l.needed_mb_s) +
                " MB/s of its " + Mb(l.capacity_mb_s) + " MB/s (each camera " +
                std::to_string(config.width) + "x" + std::to_string(config.height) + " " +
                config.pixel_format + " at " + Mb(config.rate_hz) + " Hz is " + Mb(l.image_mb_s) +
                " MB/s of images). To fit: " + fix;
  }
  if (problems.empty()) return {};
  return Fail(kExitConfig, "[rig] bandwidth: " + problems);
}

std::string DescribeRigBandwidth(const DaemonConfig& config, const std::string& usbfs_path) {
  std::string out;
  int usb = 0;
  for (const LinkLoad& l : RigLinkLoads(config)) {
    char line[256];
    std::snprintf(line, sizeof line, "link '%s' (%s): %zu camera%s need %.1f of %.1f MB/s (%.0f %%)\n",
                  l.link.c_str(), l.interface.c_str(), l.cameras.size(),
                  l.cameras.size() > 1 ? "s" : "", l.needed_mb_s, l.capacity_mb_s,
                  100.0 * l.needed_mb_s / l.capacity_mb_s);
    out += line;
    if (l.interface == "usb3") usb += static_cast<int>(l.cameras.size());
  }
  if (usb > 0) {
    // As Daemon::Start opens them: 32 buffers a camera.
    const auto needed = static_cast<std::size_t>(usb * 32 * FrameBytes(config));
    const Status s = drivers::CheckUsbfsMemory(needed, usbfs_path);
    out += s.ok() ? "usbfs memory: enough for " + std::to_string(usb) + " USB3 cameras' buffers (" +
                        Mb(needed / 1048576.0) + " MB)\n"
                  : "warning: " + s.message() + "\n";
  }
  return out;
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
