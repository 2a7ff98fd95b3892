#include "daemon/service_notify.h"

#include <systemd/sd-daemon.h>
#include <time.h>

#include <algorithm>
#include <cstdio>

#include "daemon/config.h"
#include "daemon/live_pipeline.h"

namespace mocap::daemon {

namespace {

std::string Number(double v) {
  char text[32];
  std::snprintf(text, sizeof text, "%g", v);
  return text;
}

std::uint64_t MonotonicUsec() {
  timespec ts{};
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return static_cast<std::uint64_t>(ts.tv_sec) * 1000000u + ts.tv_nsec / 1000;
}

}  // namespace

std::string StatusLine(const ServiceSnapshot& s, bool gave_up_waiting) {
  std::string line;
  if (!s.rig_live) line = gave_up_waiting ? "degraded: no frame set yet: " : "starting: ";
  else if (!s.missing_cameras.empty() || !s.silent_cameras.empty() || !s.ptp_unlocked.empty())
    line = "degraded: ";
  line += std::to_string(s.progress.cameras_streaming) + "/" + std::to_string(s.cameras) +
          (s.simulated ? " simulated" : "") + " cameras " + Number(s.rate_hz) + " Hz";
  // " (what: id1, id2)" for each list of cameras that has any.
  const auto cameras = [&line](const char* what, const std::vector<std::string>& ids) {
    if (ids.empty()) return;
    line += std::string(" (") + what;
    for (std::size_t i = 0; i < ids.size(); ++i) line += (i ? ", " : "") + ids[i];
    line += ")";
  };
  cameras("missing ", s.missing_cameras);
  cameras("no frames from ", s.silent_cameras);
  cameras("calibration off: ", s.suspect_calibration);
  cameras("PTP unlocked: ", s.ptp_unlocked);
  std::string activity;
  if (!s.subject.empty()) {
    activity = "tracking subject " + s.subject +
               (s.model_version > 0 ? " (model v" + std::to_string(s.model_version) + ")"
                                    : " (unfitted model)");
  }
  if (!s.recording.empty()) activity += (activity.empty() ? "" : ", ") + ("recording " + s.recording);
  if (s.job == "fit") activity += (activity.empty() ? "" : ", ") + std::string("fitting");
  else if (!s.job.empty()) activity += (activity.empty() ? "" : ", ") + s.job;
  line += ", " + (activity.empty() ? std::string("idle") : activity);
  return line;
}

std::string StalledStage(const PipelineProgress& before, const PipelineProgress& after) {
  const auto moved = [](std::uint64_t a, std::uint64_t b) { return b > a; };
  const std::uint64_t waiting_for_detection =
      after.frames_grabbed - std::min(after.frames_grabbed, after.frames_dropped + after.frames_detected);
  if (!moved(before.frames_detected, after.frames_detected) &&
      (moved(before.frames_grabbed, after.frames_grabbed) || waiting_for_detection > 0))
    return "detection";
  if (moved(before.frames_detected, after.frames_detected) &&
      !moved(before.sets_synced, after.sets_synced))
    return "sync";
  if (moved(before.sets_synced, after.sets_synced) &&
      !moved(before.frames_tracked, after.frames_tracked))
    return "tracking";
  if (after.cameras_streaming > 0 && !moved(before.frames_grabbed, after.frames_grabbed))
    return "grab";
  return "";
}

ServiceNotifierOptions ServiceNotifier::FromEnvironment() {
  ServiceNotifierOptions o;
  std::uint64_t usec = 0;
  // > 0 only when WATCHDOG_USEC is set and WATCHDOG_PID, if set, is this process. The variables
  // are left in place (unset_environment = 0): mocapd starts no child that could misuse them.
  if (sd_watchdog_enabled(0, &usec) > 0) o.watchdog_usec = usec;
  return o;
}

void ServiceNotifier::Send(const std::string& message) { sd_notify(0, message.c_str()); }

void ServiceNotifier::Started(std::uint64_t now_ns) {
  started_ns_ = now_ns;
  last_check_ns_ = now_ns;
  last_status_ = "starting: waiting for the cameras' first frame sets";
  Send("STATUS=" + last_status_);
}

bool ServiceNotifier::Tick(const ServiceSnapshot& snapshot, std::uint64_t now_ns) {
  const bool waited_out = now_ns - started_ns_ >= options_.no_frames_timeout_s * 1e9;
  const std::string line = StatusLine(snapshot, waited_out);
  if (!ready_ && (snapshot.rig_live || waited_out)) {
    ready_ = true;
    last_status_ = line;
    Send("READY=1\nSTATUS=" + line);
  } else if (line != last_status_) {
    last_status_ = line;
    Send("STATUS=" + line);
  }
  if (options_.watchdog_usec == 0) return false;
  if (now_ns - last_check_ns_ < options_.watchdog_usec * 1000 / 2) return false;
  last_check_ns_ = now_ns;
  const std::string before = stalled_;
  stalled_ = last_progress_ ? StalledStage(*last_progress_, snapshot.progress) : "";
  last_progress_ = snapshot.progress;
  if (stalled_.empty()) {
    Send("WATCHDOG=1");
    ++pings_;
  }
  return stalled_ != before;
}

void ServiceNotifier::Reloading() {
  reloading_ = true;
  Send("RELOADING=1\nMONOTONIC_USEC=" + std::to_string(MonotonicUsec()) +
       "\nSTATUS=reloading the configuration");
}

void ServiceNotifier::Reloaded() {
  if (!reloading_) return;
  reloading_ = false;
  // Before the first READY, the start-up's READY ends the reload too: systemd waits for it.
  if (!ready_) return;
  Send("READY=1\nSTATUS=" + last_status_);
}

void ServiceNotifier::Stopping() { Send("STOPPING=1\nSTATUS=stopping"); }

void ServiceNotifier::StartFailed(const std::string& message, int exit_code) {
  sd_notifyf(0, "STATUS=start-up failed: %s\nEXIT_STATUS=%d", message.c_str(), exit_code);
}

ServiceSnapshot PipelineSnapshot(LivePipeline& pipeline, const DaemonConfig& config) {
  ServiceSnapshot s;
  const LivePipelineStats st = pipeline.Stats(/*timings=*/false);  // every 100 ms
  s.progress.frames_grabbed = st.capture.frames_grabbed;
  s.progress.frames_dropped = st.capture.frames_dropped;
  s.progress.frames_detected = st.capture.frames_detected;
  s.progress.sets_synced =
      st.capture.frame_sets + st.capture.warmup_sets + st.capture.dropped_frame_sets +
      st.capture.undelivered_frame_sets;
  s.progress.frames_tracked = st.frames_tracked;
  s.cameras = pipeline.num_cameras();
  for (int c = 0; c < s.cameras; ++c) {
    drivers::CameraSource& cam = pipeline.camera(c);
    const bool silent = c < static_cast<int>(st.capture.camera_silent_s.size()) && st.capture.camera_silent_s[c] > 0;
    if (cam.State() != drivers::CameraState::kStreaming) s.missing_cameras.push_back(cam.id());
    else if (silent) s.silent_cameras.push_back(cam.id());
    else ++s.progress.cameras_streaming;
  }
  const std::vector<CameraHealth> health = pipeline.DetectionHealthSnapshot();
  for (int c = 0; c < s.cameras && c < static_cast<int>(health.size()); ++c)
    if (health[c].calibration_suspect) s.suspect_calibration.push_back(pipeline.camera(c).id());
  s.rate_hz = config.rate_hz;
  s.simulated = config.simulated_cameras > 0;
  s.rig_live = st.capture.recording;
  return s;
}

}  // namespace mocap::daemon
