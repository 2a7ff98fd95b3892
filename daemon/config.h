// mocapd's configuration: one TOML file (/etc/mocapd/mocapd.toml by default) that says what the
// rig is, where the state lives, who may control the daemon and how much a client may cost.
// The store (SQLite) says what happened; this file only says what the daemon is.
//
// The file, every key (DaemonConfig below holds the defaults; daemon/examples/simulated-rig.toml
// is a whole file):
//
//   [rig]
//   simulated = 8               # > 0: that many Aravis fake cameras drawn by the renderer
//   subject_seed = 1            # the simulated rig's virtual subject (as `mocap sim --seed`)
//   rate = 200                  # Hz, [1, 2000]
//   width = 1280                # px
//   height = 1024
//   exposure_us = 500           # < the frame period
//   gain_db = 0
//   detection_threshold = 60    # image units (0..255 for Mono8)
//   centroid_noise_px = 0.1     # simulated rig only
//   detection_threads = 2
//   min_cameras = 2             # start degraded while at least this many cameras open (the rest
//                               # join when they appear); fewer: refuse to start (rig_setup.h)
//   calibration = "calib.json"  # camera calibration; absent: uncalibrated until rig.calibrate
//   sync = "trigger"            # "trigger" | "ptp" | "free-run" (daemon/capture_pipeline.h RigSync;
//                               # a simulated rig's fakes share the host's clock: "trigger" runs
//                               # as "ptp"; "ptp" gives the fakes PTP features: sim.camera sets
//                               # their state, sim_clock_offset_ms their own clocks; "free-run"
//                               # fits each fake's clock, sim_clock_* skew them)
//   trigger_master = ""         # trigger: the camera whose strobe triggers the others ("": an
//                               # external trigger generator drives every camera)
//   trigger_line = 1            # trigger: the cameras' trigger input, Line<n>
//   ptp_lock_timeout_s = 10     # ptp: how long start-up waits for every camera to lock
//   ptp_schedule = "sync-free-run"  # ptp: how exposures are put on the clock's ticks:
//                               # "sync-free-run" (Basler's SyncFreeRunTimer*, mid-tick) | "none"
//                               # (left to the cameras; the rig check shows their phase)
//   pixel_format = "Mono8"      # "Mono8" | "Mono12" | "Mono12Packed" | "Mono16"
//   packet_size = 0             # GigE: bytes per stream packet (0: negotiated; > 1500: jumbo frames)
//   packet_delay_ns = 0         # GigE: inter-packet delay (several cameras on one switch port)
//   packet_resend = "always"    # GigE: "always" | "never" (Aravis's resend requests)
//   socket_buffer_bytes = 0     # GigE: stream socket receive buffer (0: one payload, Aravis's auto)
//   [[rig.camera]]              # one per camera (a simulated rig may omit them; listed, the
//                               # first `simulated` are its fakes, and any after them are real
//                               # Aravis cameras that join it: a GigE Vision fake on loopback
//                               # that a test stops. Such a rig needs [rig] calibration.)
//   id = "Aravis-Fake-GV01"     # GenICam id or serial
//   backend = "aravis"          # "aravis" | "simulated"
//   exposure_us = 0             # 0: the rig's; gain_db = -1: the rig's; detection_threshold = 0: the rig's
//   masks = [ { x = 0, y = 900, width = 1280, height = 124 } ]   # pixels never detected (reflections)
//   interface = "gige"          # "gige" | "10gige" | "usb3": what its link carries (rig check)
//   link = ""                   # cameras with one link name share a link (a NIC port, a switch
//                               # uplink, a USB host controller); "": a link of its own. On a
//                               # simulated rig only cameras with a link are in the rig check
//                               # (the rig being planned), and over budget is not refused
//   strobe_line = -1            # Line<n> driven by ExposureActive (the IR ring; a trigger
//                               # master's output); -1: none
//   optional = ""               # GenICam features this camera may refuse, comma separated
//                               # ("ExposureAuto,GevSCPD"); any other refusal is an error
//   usb_mode = "default"        # usb3: "default" | "sync" | "async" (Aravis's libusb I/O)
//   usb_throughput_limit_mb_s = 0   # usb3: DeviceLinkThroughputLimit (0: none); below what the
//                               # camera sends at the configured image and rate is an error
//   sim_clock_offset_ms = 0     # simulated rig, sync = "free-run": this fake's clock offset
//   sim_clock_drift_ppm = 0     # ... and rate error (drivers/skewed_clock_camera.h)
//   sim_arrival_wait_us = 0     # ... and the mean wait its frames' arrivals get (the fit's noise)
//   [storage]   state_dir = "/var/lib/mocapd"
//               export_dirs = ["/srv/mocap/exports"]   # where `export` may write (default:
//                                                      # state_dir/exports; daemon/export_path.h)
//   [control]   socket = "/run/mocapd/control.sock", group = "mocap", max_clients = 64,
//               max_line_bytes = 1048576, subscriber_queue_frames = 400, max_pending_requests = 64
//   [protocol]  file = "protocol.json"          # absent: the built-in protocol
//   [tracker]   sigma_m = 0.004, gate_chi2 = 16.27
//   [fit]       threads = 0, max_iterations = 50, groups = "scales,centres,axes,markers",
//               coarse_frames = 800             # defaults of `fit.start` (a request may override)
//
// Why typos are errors: an unknown key or table is refused with its name and line. A misspelt
// `max_client = 8` that silently kept the default of 64 would look applied and not be.
//
// Why every error names file:line:key: the operator reads it in the journal of a daemon that
// refused to start (or a reload that was refused) and must find the line without guessing:
//   /etc/mocapd/mocapd.toml:12: rig.rate: expected a number in [1, 2000], got "fast"
//
// Relative paths in the file (calibration, state_dir, socket, protocol file) are relative to the
// file's directory, not to the daemon's working directory (which is / under systemd), so a
// config and the files beside it can be moved together.
//
// Command-line overrides (mocapd --state-dir, --socket) are set on the parsed struct; IsValid
// checks the result again, naming the key they override.
//
// Reload (SIGHUP, config.reload): the new file is parsed and validated completely before
// anything changes; DiffConfig says what changed and which of those changes can be applied to
// the running daemon (limits, the control group, the export directories, the protocol, fit
// defaults) and which need a
// restart (the rig, the storage directory, the socket).
#pragma once
#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "model/status.h"

namespace mocap::daemon {

// A rectangle of a camera's image whose pixels are never detected (a reflection, a lamp).
struct MaskRect {
  int x = 0, y = 0;           // top-left pixel
  int width = 0, height = 0;  // >= 1, within the image
  bool operator==(const MaskRect&) const = default;
};

struct CameraConfig {
  std::string id;                  // GenICam device id or serial number
  std::string backend = "aravis";  // "aravis" | "simulated"
  // Per-camera overrides of the rig's settings; the sentinel keeps the rig's.
  double exposure_us = 0;          // 0: the rig's
  double gain_db = -1;             // -1: the rig's
  int detection_threshold = 0;     // 0: the rig's
  std::vector<MaskRect> masks;
  std::string interface = "gige";  // "gige" | "10gige" | "usb3"
  std::string link;                // "": its own
  int strobe_line = -1;            // -1: none
  std::string optional;            // features it may refuse, comma separated
  // USB3 Vision transfer (interface "usb3" only): Aravis's libusb I/O mode, and the camera's
  // DeviceLinkThroughputLimit (MB/s, 0: no limit). drivers/usb_transfer.h says what each does.
  std::string usb_mode = "default";  // "default" | "sync" | "async"
  double usb_throughput_limit_mb_s = 0;
  // Simulated rigs with sync = "free-run" only: this camera's clock, as SkewedClockCamera
  // (drivers/skewed_clock_camera.h) puts it on the fake's: an offset and a rate error.
  double sim_clock_offset_ms = 0;
  double sim_clock_drift_ppm = 0;
  double sim_arrival_wait_us = 0;  // mean exponential wait added to each frame's arrival
  bool operator==(const CameraConfig&) const = default;
};

struct DaemonConfig {
  std::string source;  // the file it came from ("" when built in code); not compared by DiffConfig

  // [rig]
  int simulated_cameras = 0;       // simulated = N: a simulated rig of N Aravis fake cameras
                                   // (then cameras[N..] are real ones joining it)
  std::uint64_t subject_seed = 1;  // the simulated rig's virtual subject (as `mocap sim --seed`)
  double rate_hz = 200;
  int width = 1280, height = 1024;
  double exposure_us = 500;
  double gain_db = 0;
  int detection_threshold = 60;
  double centroid_noise_px = 0.1;  // simulated rig only
  int detection_threads = 2;
  int min_cameras = 2;  // fewer open at start: refuse to start; else degraded (rig_setup.h)
  std::vector<CameraConfig> cameras;  // [[rig.camera]]; a real rig needs at least one
  std::string calibration_file;       // empty: uncalibrated until rig.calibrate
  std::string sync = "trigger";       // "trigger" | "ptp" | "free-run"
  std::string trigger_master;         // "": an external trigger generator
  int trigger_line = 1;
  double ptp_lock_timeout_s = 10;
  std::string ptp_schedule = "sync-free-run";  // drivers::PtpSchedule
  std::string pixel_format = "Mono8";
  int packet_size = 0;                // 0: negotiated
  int packet_delay_ns = 0;
  std::string packet_resend = "always";
  int socket_buffer_bytes = 0;        // 0: one payload

  // [storage]
  std::string state_dir = "/var/lib/mocapd";
  // The directories `export` may write beneath (absolute). Empty: state_dir/exports only, so a
  // client cannot have the daemon's user write anywhere it was not told to (daemon/export_path.h).
  std::vector<std::string> export_dirs;
  std::vector<std::string> AllowedExportDirs() const {
    return export_dirs.empty() ? std::vector<std::string>{state_dir + "/exports"} : export_dirs;
  }

  // [control]
  std::string socket_path = "/run/mocapd/control.sock";
  std::string control_group = "mocap";  // members (and root) may change state; others only read
  int max_clients = 64;
  std::size_t max_line_bytes = 1 << 20;  // one request line, and one line a client must accept
  int subscriber_queue_frames = 400;     // stream frames waiting per subscriber (within 3 MiB):
                                        // 2 s at 200 Hz; beyond, a slower subscriber loses frames
  int max_pending_requests = 64;         // per client

  // [protocol]
  std::string protocol_file;  // empty: the built-in protocol (sim/protocol.h DefaultProtocol)

  // [tracker]: as ekf::TrackerOptions's (a test keeps the defaults equal).
  double tracker_sigma_m = 0.004;  // marker measurement noise, model error included (m)
  double tracker_gate_chi2 = 16.27;  // marker-to-point gate (chi-square, 3 dof; 99.9 %)

  // [fit]: defaults of fit.start (the request may override each), as `mocap fit`'s options.
  int fit_threads = 0;  // 0: all cores
  int fit_max_iterations = 50;
  std::string fit_groups = "scales,centres,axes,markers";  // solver::FitOptions::SetGroups
  // 0: no coarse-to-fine start; default solver::CoarseToFineOptions's (a test keeps them equal).
  int fit_coarse_frames = 800;

  int num_cameras() const {
    return std::max(simulated_cameras, static_cast<int>(cameras.size()));
  }
  // Every value in range and the values consistent with each other (exposure within the frame
  // period, masks within the image, camera ids unique, ...). The error names the key as the
  // file spells it ("rig.camera[2].gain_db: ..."), without a line: this struct has none.
  bool IsValid(std::string* error) const;
};

// Bytes per pixel of a configured pixel format (Mono12Packed: 1.5); 0 for an unknown name.
double ConfiguredBytesPerPixel(const std::string& pixel_format);
// What one camera sends of images at the configured image, pixel format and rate, MB/s (1e6 B).
double CameraImageMbS(const DaemonConfig& config);

// Parses `text` (a TOML document) as the configuration read from `source` (a path: it names the
// file in errors and relative paths are resolved against its directory). On error `out` is
// left untouched, so a refused reload keeps the running configuration.
Status ParseConfig(const std::string& text, const std::string& source, DaemonConfig* out);
// Reads and parses the file at `path` (made absolute first, so that the paths it holds stay
// right after the daemon changes directory).
Status LoadConfig(const std::string& path, DaemonConfig* out);

// One difference between two configurations.
struct ConfigChange {
  std::string key;     // as the file spells it: "control.max_clients", "rig.camera", ...
  bool needs_restart = false;  // false: the running daemon can apply it (config.reload)
  bool operator==(const ConfigChange&) const = default;
};
// What differs from `a` to `b`, in the file's order of the keys; any change to the cameras
// ([[rig.camera]]) comes last, as one change. The rig (cameras, rate, image, simulation), the
// storage directory and the socket need a restart: they are what the running pipeline, store
// and listening socket were built from. Limits apply to new clients and new subscriptions; the
// group to the next request; the calibration file, protocol and fit defaults to the next job
// that uses them.
std::vector<ConfigChange> DiffConfig(const DaemonConfig& a, const DaemonConfig& b);

}  // namespace mocap::daemon
