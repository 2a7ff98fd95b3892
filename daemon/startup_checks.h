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
#pragma once
#include <string>

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

// For a rig with USB3 Vision cameras (found among Aravis's devices by the configured ids or
// serials): what to set when the usbfs memory limit is too small for their stream buffers ("" if
// nothing, or no USB camera). `usbfs_path` is the kernel's parameter file.
std::string UsbfsAdvice(const DaemonConfig& config,
                        const std::string& usbfs_path = "/sys/module/usbcore/parameters/usbfs_memory_mb");

}  // namespace mocap::daemon
