// mocapd and systemd's service manager (sd_notify(3), Type=notify): readiness, status, watchdog,
// reload and stop, in one place so that the daemon's loop only says what happened.
//
// Readiness. `READY=1` is a promise that the service does what it is for: a capture PC's mocapd
// is for streaming cameras, so READY waits for the pipeline's first frame sets (the capture
// pipeline's "rig live": CapturePipelineStats::recording), not for Start() returning. Clients
// are served before that (the control socket is listening, under socket activation even before
// mocapd runs), only systemd's ordering (After=mocapd.service) waits. A rig that cannot stream
// all its cameras does not hold start-up hostage (TimeoutStartSec would kill it, Restart would
// loop): the capture pipeline starts with the cameras it has after its start timeout, and READY
// is sent with `STATUS=degraded: ...` naming the missing cameras; a rig of which no camera
// streams at all is declared degraded `ReadinessOptions::no_frames_timeout_s` after start.
//
// Health. `WATCHDOG=1` says the pipeline is alive, not merely the loop: the loop sends it only
// when every stage progressed since the previous ping (a hung detection worker behind a loop
// that still answers requests must get the service restarted). Per-stage progress counters
// (frames grabbed, frames detected, sets synced, frames tracked) are compared over the interval;
// a stage is hung when it had work (its input moved, or frames wait in its queue) and its
// output did not move, the grab stage when cameras say they stream and no frame came. A rig with no streaming camera (all unplugged, an idle bench)
// has nothing to process: that is degraded, announced in STATUS, not a hang. The ping is sent
// every half watchdog interval (sd_watchdog_enabled(3)'s advice), so a hang stops the pings
// within one interval plus one tick.
//
// Reload. `RELOADING=1` (with `MONOTONIC_USEC=`, which systemd 253+ requires with
// Type=notify-reload and older ones ignore) ... `READY=1` around config.reload/SIGHUP, whatever
// the outcome: systemd keeps the unit "reloading" until READY comes back.
//
// Without NOTIFY_SOCKET (run by hand, in the daemon tests) sd_notify is a no-op and all of this
// is silent; WATCHDOG_USEC unset means no watchdog.
//
// The decisions (ready? which stage is hung? the status line) are pure functions of snapshots,
// so they are tested without a service manager (tests/test_daemon_systemd.cpp); the class only
// adds the clock and sd_notify.
#pragma once
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

namespace mocap::daemon {

class LivePipeline;
struct DaemonConfig;

// Cumulative counters of the pipeline's stages; only differences between two snapshots matter.
struct PipelineProgress {
  std::uint64_t frames_grabbed = 0;   // images handed over by the cameras
  std::uint64_t frames_dropped = 0;   // ... of which dropped (the detection queue was full)
  std::uint64_t frames_detected = 0;  // images through marker detection
  std::uint64_t sets_synced = 0;      // frame sets out of the sync (warm-up included)
  std::uint64_t frames_tracked = 0;   // frame sets through the tracking stage
  int cameras_streaming = 0;          // cameras whose state is kStreaming now, silent ones not
};

// What STATUS= and READY depend on, as the loop sees it at one tick.
struct ServiceSnapshot {
  PipelineProgress progress;
  int cameras = 0;                            // configured (and opened)
  std::vector<std::string> missing_cameras;   // ids of cameras not streaming
  // ids of cameras that say they stream but delivered no frame for a while as the others did
  // (capture_pipeline.h camera_silence_s: a pulled GigE cable, long before its driver gives up)
  std::vector<std::string> silent_cameras;
  std::vector<std::string> suspect_calibration;  // ids whose reprojection error is off
  std::vector<std::string> ptp_unlocked;         // sync = "ptp": ids not locked to the clock
  double rate_hz = 0;
  bool simulated = false;
  bool rig_live = false;                      // the capture pipeline's first sets are out
  std::string subject;                        // "" when none is selected
  int model_version = 0;                      // of the live model (0: none)
  std::string recording;                      // the movement being recorded, "" when none
  std::string job;                            // "fit", "rig.calibrate", "" when none
};

// The snapshot's one-line summary:
//   "8/8 cameras 200 Hz, tracking subject S012 (model v3), recording squats"
//   "degraded: 6/8 cameras 200 Hz (missing cam3, cam7), idle"
//   "degraded: 7/8 cameras 200 Hz (no frames from cam4), idle"   (silent_cameras)
//   "8/8 cameras 200 Hz (calibration off: cam3), idle"   (daemon/detection_health.h)
//   "degraded: 8/8 cameras 200 Hz (PTP unlocked: cam2), idle"   (daemon/ptp_monitor.h)
//   "starting: 3/8 cameras 200 Hz (missing ...), idle"   (no frame set out yet)
// `gave_up_waiting`: no frame set came out within the start-up's timeout, the daemon runs
// degraded ("degraded: no frame set yet: 0/8 cameras ...").
std::string StatusLine(const ServiceSnapshot& s, bool gave_up_waiting = false);

// Which stage did not progress from `before` to `after` although it had work ("" if none):
// "detection", "sync", "tracking" or "grab". A stage has work when its input moved, detection
// also when frames wait for it; the grab stage when a camera says it streams. Downstream stages
// are judged first: a held detection stage soon stops the grab too (the frames it holds in its
// queue are the cameras' buffers), and the culprit is the stage with work waiting.
std::string StalledStage(const PipelineProgress& before, const PipelineProgress& after);

struct ServiceNotifierOptions {
  // Declared ready (degraded) this long after Start() when no frame set came out; the unit's
  // TimeoutStartSec must be longer.
  double no_frames_timeout_s = 15;
  // From sd_watchdog_enabled() (WATCHDOG_USEC); 0: no watchdog.
  std::uint64_t watchdog_usec = 0;
};

class ServiceNotifier {
 public:
  // Reads the watchdog interval from the environment (WATCHDOG_USEC/WATCHDOG_PID).
  static ServiceNotifierOptions FromEnvironment();
  explicit ServiceNotifier(ServiceNotifierOptions options) : options_(options) {}

  // The daemon's Start() returned; `now_ns` is CLOCK_MONOTONIC.
  void Started(std::uint64_t now_ns);
  // Every loop tick (100 ms): READY once live, STATUS when the line changed, WATCHDOG when due
  // and healthy. True when stalled() changed (a stage hung, or every stage moves again).
  bool Tick(const ServiceSnapshot& snapshot, std::uint64_t now_ns);
  // The stage found hung at the last watchdog check ("" if none).
  const std::string& stalled() const { return stalled_; }
  void Reloading();
  void Reloaded();
  void Stopping();
  // Start-up failed: STATUS names the cause, ERRNO=/EXIT_STATUS= for `systemctl status`.
  static void StartFailed(const std::string& message, int exit_code);

  bool ready() const { return ready_; }
  std::uint64_t pings() const { return pings_; }

 private:
  void Send(const std::string& message);

  ServiceNotifierOptions options_;
  std::uint64_t started_ns_ = 0;
  bool ready_ = false;
  bool reloading_ = false;
  std::string last_status_;
  std::uint64_t pings_ = 0;
  std::uint64_t last_check_ns_ = 0;
  std::optional<PipelineProgress> last_progress_;
  std::string stalled_;
};

// RELOADING=1 for its lifetime, READY=1 at its end (every return path of a reload). Null: none.
class ReloadNotice {
 public:
  explicit ReloadNotice(ServiceNotifier* notifier) : notifier_(notifier) {
    if (notifier_) notifier_->Reloading();
  }
  ~ReloadNotice() {
    if (notifier_) notifier_->Reloaded();
  }
  ReloadNotice(const ReloadNotice&) = delete;
  ReloadNotice& operator=(const ReloadNotice&) = delete;

 private:
  ServiceNotifier* notifier_;
};

// The snapshot's pipeline part (progress, cameras, rig live) from the running pipeline and the
// configuration; the caller adds subject, model, recording and job.
ServiceSnapshot PipelineSnapshot(LivePipeline& pipeline, const DaemonConfig& config);

}  // namespace mocap::daemon
