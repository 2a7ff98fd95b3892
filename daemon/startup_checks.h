// mocapd's start-up checks and exit codes: what systemd (and the admin reading the journal) is
// told when the daemon cannot start.
//
// Why checks before Daemon::Start(): the causes an admin fixes in a file (the configuration, the
// storage directory's ownership, a stray file at the socket's path) must not crash-loop through
// Restart=on-failure, and must be named with the setting that points at them. So they are
// checked first, each failure is one line naming the cause and the setting
//   [storage] state_dir '/var/lib/mocapd': not writable by uid 998: Permission denied
// and each has its own exit code (sysexits.h, which `systemctl status` shows by name), of which
// the unit's RestartPreventExitStatus= lists the ones no restart can cure. What fails later, in
// Start() (a camera not found, a camera refusing the pixel format, the store), is a resource
// that may come back (a camera plugged in again): EX_UNAVAILABLE, and systemd retries.
//
// A rig of USB3 Vision cameras also needs the kernel's usbfs memory limit raised
// (drivers/usb_hotplug.h CheckUsbfsMemory); UsbfsAdvice says what to set, as a warning: the
// cameras still stream, losing frames, so it is not a reason to refuse to start.
//
// The rig's bandwidth (CheckRigBandwidth) is a configuration error, checked before any camera is
// opened and by `mocapd --check-config`: a link asked to carry more than it can drops packets
// and frames on every set, and no camera says why. So per link (the cameras sharing one NIC port,
// switch uplink or USB host controller: [[rig.camera]] link), the bandwidth the cameras need,
// width x height x bytes per pixel x rate plus the protocol's overhead, is set against what the
// link carries, and an over-budget rig is refused with the link, its cameras, the figures and
// what would fit (a lower rate, a smaller ROI, a packed pixel format, a faster link).
// Figures (MB = 1e6 bytes):
//   gige    125 MB/s on the wire; each GVSP packet of `packet_size` bytes (1500 unless
//           configured; jumbo frames up to 9000) carries packet_size - 36 bytes of image (IP 20,
//           UDP 8, GVSP 8) and costs packet_size + 38 on the wire (Ethernet header, FCS,
//           preamble, inter-frame gap): 1500-byte packets leave 119 MB/s for images.
//   10gige  the same at 1250 MB/s.
//   usb3    400 MB/s of images: USB 3.0 (Gen 1) signals 5 Gb/s, 500 MB/s after 8b/10b, of
//           which bulk transfers sustain about 400 on a host controller of its own.
#pragma once
#include <string>
#include <vector>

#include "daemon/config.h"  // ConfiguredBytesPerPixel
#include "model/status.h"

namespace mocap::daemon {

struct DaemonConfig;

// Exit codes of mocapd (sysexits.h values).
constexpr int kExitUnavailable = 69;  // EX_UNAVAILABLE: cameras (or the store) could not be started
constexpr int kExitCannotCreate = 73; // EX_CANTCREAT: the storage directory cannot be created
constexpr int kExitNoPermission = 77; // EX_NOPERM: the storage directory is not accessible
constexpr int kExitConfig = 78;       // EX_CONFIG: the configuration (file, values, socket path)

// A start-up check's outcome: Ok, or the message and the exit code to leave with.
struct StartupCheck {
  Status status;
  int exit_code = 0;
  bool ok() const { return status.ok(); }
};

// The storage directory exists (or its parent lets it be created) and is readable, writable and
// searchable by this process.
StartupCheck CheckStateDir(const std::string& state_dir);
// Nothing but a socket (or nothing) at the control socket's path. Only when mocapd creates the
// socket itself; under socket activation systemd made it.
StartupCheck CheckSocketPath(const std::string& socket_path);
// Both, for the configuration (skipping the socket when `socket_activated`).
StartupCheck CheckStartup(const DaemonConfig& config, bool socket_activated);

// One link of the rig and what its cameras need of it.
struct LinkLoad {
  std::string link;       // [[rig.camera]] link, or the camera's id for a link of its own
  std::string interface;  // "gige" | "10gige" | "usb3"
  std::vector<std::string> cameras;
  double capacity_mb_s = 0;  // on the wire (GigE) or of images (USB3)
  double needed_mb_s = 0;    // the same measure, of its cameras at the configured image and rate
  double image_mb_s = 0;     // images alone, per camera
};
// Per link, in the order of the cameras' first appearance. A simulated rig's cameras count only
// where they name a link ([[rig.camera]] link): the real rig it stands for, being planned.
std::vector<LinkLoad> RigLinkLoads(const DaemonConfig& config);
// Ok when every link carries its cameras; else kExitConfig and a message naming the link, its
// cameras, the figures and what would fit. mocapd refuses to start a real rig over budget; a
// simulated one starts (its fakes carry nothing) and its rig check (daemon/rig_check.h) fails.
StartupCheck CheckRigBandwidth(const DaemonConfig& config);
// One line per link ("link 'eth1' (gige): 2 cameras need 110.2 of 125.0 MB/s (88 %)"), and the
// usbfs budget of the USB3 cameras read from `usbfs_path`: what `mocapd --check-config` prints.
std::string DescribeRigBandwidth(const DaemonConfig& config,
                                 const std::string& usbfs_path =
                                     "/sys/module/usbcore/parameters/usbfs_memory_mb");

// For a rig with USB3 Vision cameras (found among Aravis's devices by the configured ids or
// serials): what to set when the usbfs memory limit is too small for their stream buffers ("" if
// nothing, or no USB camera). `usbfs_path` is the kernel's parameter file.
std::string UsbfsAdvice(const DaemonConfig& config,
                        const std::string& usbfs_path = "/sys/module/usbcore/parameters/usbfs_memory_mb");

}  // namespace mocap::daemon
