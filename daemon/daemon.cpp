#include "daemon/daemon.h"

#include <fcntl.h>
#include <signal.h>
#include <sys/eventfd.h>
#include <sys/resource.h>
#include <sys/statvfs.h>
#include <syslog.h>
#include <unistd.h>

#include <spdlog/spdlog.h>

#include <algorithm>
#include <csignal>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <limits>

#include "daemon/export_path.h"
#include "daemon/recorder.h"
#include "daemon/recording_export.h"
#include "daemon/rig_check.h"
#include "daemon/rig_setup.h"
#include "drivers/aravis_camera.h"
#include "drivers/frame.h"
#include "drivers/skewed_clock_camera.h"
#include "formats/osim.h"
#include "formats/text_util.h"
#include "model/compare.h"
#include "model/default_model.h"
#include "model/model_io.h"
#include "reconstruction/calibration.h"
#include "report/fit_report_html.h"
#include "reconstruction/calibration_file.h"
#include "sim/live_rig.h"
#include "sim/simulate.h"
#include "solver/fit_report_json.h"
#include "solver/global_fit.h"

namespace mocap::daemon {

namespace {

// The nice value of a fit job and its workers (Daemon::StartFit): below the live pipeline.
constexpr int kFitNice = 10;
// model.apply: how long the tracking thread may take to take the model (a frame arrives every
// 5 ms; a frame's start is ~0.1 s; a second more covers a descheduled thread).
constexpr std::uint64_t kApplyTimeoutNs = 2'000'000'000;

using Json = nlohmann::json;
namespace fs = std::filesystem;

double SecondsSince(std::uint64_t ns) { return (drivers::MonotonicNs() - ns) * 1e-9; }

// Parameter readers: each names the parameter in its error ("params.height_m: expected a number").
struct Params {
  explicit Params(const Json& params) : j(params) {}
  const Json& j;
  std::string error;
  bool Has(const char* k) const { return j.contains(k) && !j.at(k).is_null(); }
  bool String(const char* k, std::string* out, bool required) {
    if (!Has(k)) {
      if (required) error = std::string("params.") + k + ": missing";
      return !required;
    }
    if (!j.at(k).is_string()) {
      error = std::string("params.") + k + ": expected a string";
      return false;
    }
    *out = j.at(k).get<std::string>();
    return true;
  }
  bool Number(const char* k, double* out, double lo, double hi, bool required) {
    if (!Has(k)) {
      if (required) error = std::string("params.") + k + ": missing";
      return !required;
    }
    if (!j.at(k).is_number()) {
      error = std::string("params.") + k + ": expected a number";
      return false;
    }
    const double v = j.at(k).get<double>();
    if (!(v >= lo && v <= hi)) {
      error = std::string("params.") + k + ": " + std::to_string(v) + " is outside [" +
              std::to_string(lo) + ", " + std::to_string(hi) + "]";
      return false;
    }
    *out = v;
    return true;
  }
  bool Int(const char* k, std::int64_t* out, std::int64_t lo, std::int64_t hi, bool required) {
    if (!Has(k)) {
      if (required) error = std::string("params.") + k + ": missing";
      return !required;
    }
    if (!j.at(k).is_number_integer()) {
      error = std::string("params.") + k + ": expected an integer";
      return false;
    }
    const std::int64_t v = j.at(k).get<std::int64_t>();
    if (v < lo || v > hi) {
      error = std::string("params.") + k + ": " + std::to_string(v) + " is outside [" +
              std::to_string(lo) + ", " + std::to_string(hi) + "]";
      return false;
    }
    *out = v;
    return true;
  }
  bool Bool(const char* k, bool* out) {
    if (!Has(k)) return true;
    if (!j.at(k).is_boolean()) {
      error = std::string("params.") + k + ": expected true or false";
      return false;
    }
    *out = j.at(k).get<bool>();
    return true;
  }
};

bool EndsWith(const std::string& s, const std::string& suffix) {
  if (s.size() < suffix.size()) return false;
  for (std::size_t i = 0; i < suffix.size(); ++i)
    if (std::tolower(static_cast<unsigned char>(s[s.size() - suffix.size() + i])) != suffix[i]) return false;
  return true;
}

const char* TrackStateName(int s) {
  if (s < 0) return "none";
  return ekf::ToString(static_cast<ekf::TrackState>(s));
}

}  // namespace

namespace {
// Threads that libraries start before main() (OpenBLAS's pool, at load time) do not block the
// signals, and the kernel may hand a process-directed SIGTERM to one of them: without a handler
// its default action kills the daemon mid-commit. The handler forwards the signal to the loop
// through a pipe (write() is async-signal-safe); a signal that finds every thread blocking it
// stays pending for sd-event's signalfd instead. Either way the loop handles it once.
int g_signal_pipe[2] = {-1, -1};
void ForwardSignal(int sig) {
  const int saved = errno;
  const unsigned char b = static_cast<unsigned char>(sig);
  [[maybe_unused]] ssize_t n = ::write(g_signal_pipe[1], &b, 1);
  errno = saved;
}
}  // namespace

Daemon::Daemon(DaemonConfig config, DaemonOptions options)
    : config_(std::move(config)), options_(std::move(options)) {}

Daemon::~Daemon() { Stop(); }

void Daemon::PostToLoop(std::function<void()> task) {
  {
    std::lock_guard<std::mutex> lock(tasks_mutex_);
    tasks_.push_back(std::move(task));
  }
  const std::uint64_t one = 1;
  [[maybe_unused]] ssize_t n = ::write(wake_fd_, &one, sizeof one);
}

Status Daemon::Start() {
  started_ns_ = drivers::MonotonicNs();
  // 1. The protocol (part of the configuration).
  if (config_.protocol_file.empty()) {
    protocol_ = sim::DefaultProtocol();
  } else {
    MOCAP_RETURN_IF_ERROR(sim::LoadProtocolJson(config_.protocol_file, &protocol_));
  }

  // 2. The loop.
  int r = sd_event_new(&loop_);
  if (r < 0) return Status::Error(std::string("sd_event_new: ") + std::strerror(-r));
  wake_fd_ = eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
  if (wake_fd_ < 0) return Status::Error(std::string("eventfd: ") + std::strerror(errno));
  sd_event_add_io(loop_, &wake_source_, wake_fd_, EPOLLIN, &OnWake, this);
  // The frames (and the threads' tasks) before any client: sd-event dispatches one pending
  // source per iteration, the most important first, so between two bounded reads of a flooding
  // client the loop takes the frames that arrived meanwhile. At equal priority the frames waited
  // their turn among the clients and a 10,000-request flood filled the loop's 64-frame queue on
  // a loaded 2-core host (DaemonFaults.MisbehavingClientsCannotStopTheRig, CI 28 Nov 2026).
  if (wake_source_) sd_event_source_set_priority(wake_source_, SD_EVENT_PRIORITY_IMPORTANT);
  sigset_t mask;
  sigemptyset(&mask);
  sigaddset(&mask, SIGTERM);
  sigaddset(&mask, SIGINT);
  sigaddset(&mask, SIGHUP);
  sigprocmask(SIG_BLOCK, &mask, nullptr);
  for (int sig : {SIGTERM, SIGINT, SIGHUP}) {
    sd_event_source* s = nullptr;
    if (sd_event_add_signal(loop_, &s, sig, &OnSignal, this) >= 0) signal_sources_.push_back(s);
  }
  if (g_signal_pipe[0] < 0 && pipe2(g_signal_pipe, O_NONBLOCK | O_CLOEXEC) < 0)
    return Status::Error(std::string("pipe: ") + std::strerror(errno));
  {
    sd_event_source* s = nullptr;
    sd_event_add_io(loop_, &s, g_signal_pipe[0], EPOLLIN, &OnSignalPipe, this);
    signal_sources_.push_back(s);
    struct sigaction sa {};
    sa.sa_handler = ForwardSignal;
    sigemptyset(&sa.sa_mask);
    sa.sa_flags = SA_RESTART;
    for (int sig : {SIGTERM, SIGINT, SIGHUP}) sigaction(sig, &sa, nullptr);
  }

  // 3. The store.
  {
    std::unique_ptr<Store> store;
    MOCAP_RETURN_IF_ERROR(Store::Open(config_.state_dir, &store));
    store_ = std::move(store);
    // The default export directory (daemon/export_path.h); a failure shows at the first export.
    std::error_code ec;
    fs::create_directories(config_.state_dir + "/exports", ec);
  }

  // 4. The cameras: each opened with its settings; one that does not open is awaited and the
  // rig starts degraded, unless fewer than [rig] min_cameras open (rig_setup.h OpenRigCameras).
  std::vector<std::unique_ptr<drivers::AravisCamera>> cameras;
  std::vector<drivers::CameraSettings> camera_settings;
  if (config_.simulated_cameras > 0) {
    drivers::CameraSettings settings = CameraSettingsOf(config_, -1);
    settings.pixel_format = drivers::PixelFormat::kMono8;  // what the simulated rig draws
    sim::LiveRigOptions ro;
    ro.cameras = config_.simulated_cameras;
    ro.width = config_.width;
    ro.height = config_.height;
    ro.rate_hz = config_.rate_hz;
    ro.seed = config_.subject_seed;
    ro.centroid_noise_px = config_.centroid_noise_px;
    ro.protocol = &protocol_;
    // sync = "ptp": the fakes are PTP cameras (their PtpStatus set by sim.camera), each with its
    // own clock ([[rig.camera]] sim_clock_offset_ms), scheduled like real ones (rig_setup.h).
    ro.ptp_features = config_.sync == "ptp";
    if (ro.ptp_features)
      for (const CameraConfig& c : config_.cameras)
        ro.clock_offsets_ns.push_back(static_cast<std::int64_t>(std::llround(c.sim_clock_offset_ms * 1e6)));
    MOCAP_RETURN_IF_ERROR(sim::LiveRig::Create(ro, &sim_rig_));
    for (int c : options_.test_absent_cameras)
      if (c >= 0 && c < config_.simulated_cameras) sim_rig_->fakes().SetPresent(c, false);
    cameras = sim_rig_->MakeCameras();
    camera_settings.assign(cameras.size(), settings);
    // Real cameras listed after the fakes join the rig (config.h): a GigE Vision fake on
    // loopback that a test stops, to lose a camera over the network rather than by the hot-plug
    // path. Their intrinsics come from the calibration file only (below).
    for (std::size_t i = cameras.size(); i < config_.cameras.size(); ++i) {
      cameras.push_back(std::make_unique<drivers::AravisCamera>(config_.cameras[i].id));
      camera_settings.push_back(CameraSettingsOf(config_, static_cast<int>(i)));
    }
    if (static_cast<int>(cameras.size()) == config_.simulated_cameras)
      start_cameras_ = sim_rig_->IntrinsicsOnly();
  } else {
    for (std::size_t i = 0; i < config_.cameras.size(); ++i) {
      cameras.push_back(std::make_unique<drivers::AravisCamera>(config_.cameras[i].id));
      camera_settings.push_back(CameraSettingsOf(config_, static_cast<int>(i)));
    }
  }
  if (cameras.empty()) return Status::Error(config_.source + ": the rig has no cameras");
  std::vector<drivers::AravisCamera*> aravis;
  for (auto& cam : cameras) aravis.push_back(cam.get());
  {
    int code = 0;
    if (Status st = OpenRigCameras(aravis, camera_settings, config_.min_cameras,
                                   &missing_at_start_, &code);
        !st) {
      start_exit_code_ = code;
      return Status::Error("[rig] " + st.message());
    }
  }
  std::vector<char> opened(aravis.size(), 1);
  for (const MissingCamera& m : missing_at_start_) {
    opened[m.index] = 0;
    spdlog::error("[[rig.camera]] '{}' did not open ({}); the rig starts without it, degraded, "
                  "and takes it when it appears", m.id, m.why);
  }
  for (std::size_t i = 0; i < aravis.size(); ++i) {
    if (!opened[i]) continue;
    const drivers::AravisCamera& cam = *aravis[i];
    for (const std::string& r : cam.Applied().refused_optional)
      spdlog::warn("camera '{}': optional feature refused: {}", cam.id(), r);
    if (const drivers::AppliedUsbTransfer& u = cam.Applied().usb; u.applied)
      spdlog::info("camera '{}': USB3 Vision {} I/O, throughput limit {} ({} MB/s), transfers "
                   "of {} KiB, {} MiB submitted at most (Aravis 0.8's)",
                   cam.id(), u.mode, u.throughput_limit_mode.empty() ? "-" : u.throughput_limit_mode,
                   u.throughput_limit_mb_s, u.maximum_transfer_bytes / 1024,
                   u.maximum_submit_bytes >> 20);
  }
  aravis_cameras_ = aravis;
  std::vector<std::unique_ptr<drivers::CameraSource>> sources;
  for (auto& cam : cameras) sources.push_back(std::move(cam));
  if (config_.simulated_cameras > 0) {
    for (std::size_t i = 0; i < sources.size(); ++i) {
      // Free run: each fake's clock as configured (its own offset and rate).
      const CameraConfig* c = i < config_.cameras.size() ? &config_.cameras[i] : nullptr;
      if (c && config_.sync != "ptp" && (c->sim_clock_offset_ms != 0 || c->sim_clock_drift_ppm != 0 ||
                c->sim_arrival_wait_us != 0)) {
        drivers::ClockSkew skew;
        skew.offset_ns = static_cast<std::int64_t>(std::llround(c->sim_clock_offset_ms * 1e6));
        skew.drift_ppm = c->sim_clock_drift_ppm;
        skew.arrival_wait_us = c->sim_arrival_wait_us;
        skew.seed = i + 1;
        sources[i] = std::make_unique<drivers::SkewedClockCamera>(std::move(sources[i]), skew);
        spdlog::info("simulated camera {}: clock offset {} ms, drift {} ppm, arrivals wait {} us "
                     "on average", sources[i]->id(), c->sim_clock_offset_ms,
                     c->sim_clock_drift_ppm, c->sim_arrival_wait_us);
      }
    }
    if (config_.sync == "free-run")
      spdlog::warn("[rig] sync = \"free-run\" on a simulated rig: frame sets are grouped by each "
                   "fake's clock fitted against the host's");
  } else {
    if (config_.sync == "free-run") {
      spdlog::warn("[rig] sync = \"free-run\": frame sets are grouped by each camera's clock "
                   "fitted against the host's; they are only as good as that estimate, and "
                   "free-running cameras do not expose together");
    }
    for (const MissingCamera& m : missing_at_start_)
      if (config_.sync == "trigger" && m.id == config_.trigger_master)
        spdlog::error("[rig] trigger_master '{}' is missing: the other cameras get no trigger "
                      "until it appears", m.id);
  }
  // PTP: every camera locked to one clock before the rig streams (daemon/ptp_monitor.h). Every
  // camera has its source, in the rig's order: one the rig started without is not judged while
  // it is awaited, and joins the monitor when it opens (PTP enabled and its exposures scheduled
  // by the same Open path: drivers/aravis_camera.h "Exposure schedule").
  if (config_.sync == "ptp")
    for (drivers::AravisCamera* cam : aravis) ptp_sources_.push_back(std::make_unique<AravisPtpSource>(cam));
  for (std::size_t i = 0; i < aravis.size(); ++i) {
    if (!opened[i] || config_.sync != "ptp") continue;
    const drivers::AppliedSettings& a = aravis[i]->Applied();
    if (a.ptp_schedule.empty())
      spdlog::warn("camera '{}': exposures not scheduled on the PTP clock (free-running at its own "
                   "phase; the rig check shows how far from the others)", aravis[i]->id());
    else
      spdlog::info("camera '{}': exposures scheduled by Synchronous Free Run at {} Hz, mid-tick "
                   "(start {} ticks)", aravis[i]->id(), a.schedule_rate_hz, a.schedule_start_ticks);
  }
  if (!ptp_sources_.empty()) {
    std::vector<PtpStatusSource*> ptp;
    for (auto& p : ptp_sources_) ptp.push_back(p.get());
    MOCAP_RETURN_IF_ERROR(WaitForPtpLock(ptp, config_.ptp_lock_timeout_s, &ptp_));
    for (std::size_t i = 0; i < ptp_.states.size(); ++i)
      spdlog::info("camera '{}': PTP {}{}", ptp[i]->camera_id(), ptp_.states[i].status,
                   ptp_.states[i].has_offset
                       ? ", " + std::to_string(ptp_.states[i].offset_from_master_ns) + " ns from the master"
                       : "");
    ptp_.rounds = 0;  // the running monitor's rounds count from its own first
    ptp_monitor_ = std::make_unique<PtpMonitor>(ptp, PtpMonitorOptions{},
                                                [this] { PostToLoop([this] { UpdatePtp(); }); });
  }
  // The rig calibration: the configured file, else the newest stored one.
  std::vector<reconstruction::CameraModel> calibrated;
  {
    std::vector<std::string> ids;
    for (const auto& s : sources) ids.push_back(s->id());
    reconstruction::CalibrationFile cal;
    Status have = Status::Error("none");
    if (!config_.calibration_file.empty()) {
      have = reconstruction::ReadCalibrationJson(config_.calibration_file, &cal);
      if (!have) return Status::Error("[rig] calibration: " + have.message());
      calibration_version_ = 0;
    } else {
      // The calibration that was live before a restart, else the newest.
      CalibrationRecord rec;
      std::string live;
      const std::int64_t wanted =
          store_->GetState("calibration_version", &live) ? std::atoll(live.c_str()) : 0;
      if (store_->GetCalibration(wanted, &rec) || store_->GetCalibration(0, &rec)) {
        have = reconstruction::ParseCalibrationJson(
            rec.calibration_json, "stored calibration " + std::to_string(rec.version), &cal);
        if (have) calibration_version_ = static_cast<int>(rec.version);
      }
    }
    if (have) {
      Status m = reconstruction::MatchCalibrationToRig(cal, ids, &calibrated);
      if (!m && !config_.calibration_file.empty())
        return Status::Error("[rig] calibration: " + m.message());
      if (!m) calibrated.clear(), calibration_version_ = 0;
      if (start_cameras_.empty()) start_cameras_ = calibrated;
    }
  }
  if (start_cameras_.empty() && config_.simulated_cameras == 0)
    return Status::Error(config_.source +
                         ": a real rig needs [rig] calibration (at least the cameras' intrinsics)");
  if (start_cameras_.empty() && config_.num_cameras() > config_.simulated_cameras)
    return Status::Error(config_.source + ": a simulated rig that real cameras join needs [rig] "
                                          "calibration (the real cameras' intrinsics)");

  // 5. The pipeline.
  LivePipelineOptions po;
  po.capture.detection_threads = config_.detection_threads;
  po.capture.rig_sync = RigSyncOf(config_);
  po.capture.rate_hz = config_.rate_hz;
  po.capture.detection.threshold = config_.detection_threshold;
  po.capture.detection.sigma_floor_px = std::max(0.01, config_.centroid_noise_px);
  po.tracker.rate_hz = config_.rate_hz;
  po.tracker.sigma_m = config_.tracker_sigma_m;
  po.tracker.gate_chi2 = config_.tracker_gate_chi2;
  po.exposure_us = config_.exposure_us;
  po.capture.test_hold = options_.test_hold;
  pipeline_ = std::make_unique<LivePipeline>(std::move(sources), po, [this] {
    const std::uint64_t one = 1;
    [[maybe_unused]] ssize_t n = ::write(wake_fd_, &one, sizeof one);
  });
  pipeline_->SetImageSize(config_.width, config_.height);
  if (!calibrated.empty()) MOCAP_RETURN_IF_ERROR(pipeline_->SetCalibration(calibrated));
  MOCAP_RETURN_IF_ERROR(pipeline_->Start());
  if (ptp_monitor_) MOCAP_RETURN_IF_ERROR(ptp_monitor_->Start());
  if (sim_rig_) {
    if (calibrated.empty()) sim_rig_->scene().ShowEmpty();
    else sim_rig_->scene().StandStatic();
  }
  ResumeLive();

  // 6. The recorder (its own store connection).
  {
    std::unique_ptr<Store> store, checkpointer;
    StoreOptions so;
    so.mark_interrupted_recordings = false;  // done by the loop's store above
    MOCAP_RETURN_IF_ERROR(Store::Open(config_.state_dir, &checkpointer, so));
    so.wal_autocheckpoint_pages = 0;  // the checkpointer's thread does it (daemon/store.h)
    MOCAP_RETURN_IF_ERROR(Store::Open(config_.state_dir, &store, so));
    // Each chunk committed within 100 ms of its oldest frame's last image reaching the host and
    // the WAL synced after it on a thread of the recorder's (daemon/recorder.h, store.h "Crashes
    // and power cuts"): a crash loses at most the last 100 ms of the recording
    // (tests/test_daemon_faults.cpp measures it), a power cut as much where fsync keeps up.
    recorder_ = std::make_unique<Recorder>(pipeline_.get(), std::move(store),
                                           std::move(checkpointer), /*loss_budget_ms=*/100);
    recorder_->Start();
  }

  // 7. The socket.
  ControlServerOptions so;
  so.socket_path = config_.socket_path;
  so.control_group = config_.control_group;
  so.max_clients = config_.max_clients;
  so.max_line_bytes = config_.max_line_bytes;
  so.max_pending = config_.max_pending_requests;
  so.stream_queue_frames = config_.subscriber_queue_frames;
  server_ = std::make_unique<ControlServer>(
      loop_, so,
      [this](const ClientInfo& c, const Json& id, const std::string& m, const Json& p) {
        OnRequest(c, id, m, p);
      },
      [this](std::uint64_t c) { OnDisconnect(c); },
      [](int priority, const std::string& message) {
        if (priority <= LOG_ERR) spdlog::error("{}", message);
        else if (priority == LOG_WARNING) spdlog::warn("{}", message);
        else spdlog::info("{}", message);
      });
  server_->hello_daemon = "mocapd " + options_.version;
  MOCAP_RETURN_IF_ERROR(server_->Listen(options_.listen_fd));
  sd_event_add_time_relative(loop_, &timer_source_, CLOCK_MONOTONIC, 100000, 10000, &OnTimer, this);
  sd_event_source_set_enabled(timer_source_, SD_EVENT_ON);
  spdlog::info("mocapd {} ready: {} camera(s){}, {} at {} Hz, socket {}, state in {}",
               options_.version, pipeline_->num_cameras(),
               config_.simulated_cameras > 0 ? " (simulated)" : "",
               calibrated.empty() ? "uncalibrated" : "calibrated", config_.rate_hz,
               config_.socket_path, config_.state_dir);
  return Status::Ok();
}

int Daemon::Run() {
  const int r = sd_event_loop(loop_);
  if (r < 0) {
    spdlog::error("event loop: {}", std::strerror(-r));
    return 1;
  }
  return exit_code_;
}

bool Daemon::RunOnce(std::uint64_t timeout_us) {
  if (!loop_ || sd_event_get_state(loop_) == SD_EVENT_FINISHED) return false;
  const int r = sd_event_run(loop_, timeout_us);
  if (r < 0) spdlog::error("event loop: {}", std::strerror(-r));
  return r >= 0 && sd_event_get_state(loop_) != SD_EVENT_FINISHED;
}

void Daemon::Stop() {
  if (stopped_) return;
  stopped_ = true;
  // Already stopping: a second SIGTERM (systemd's, after a shutdown request) must not kill the
  // process half-way through committing the recording.
  for (int sig : {SIGTERM, SIGINT, SIGHUP}) std::signal(sig, SIG_IGN);
  // Reverse order: socket, recording, jobs, pipeline, store.
  if (server_) server_->Close();
  if (recording_ && pipeline_) {
    pipeline_->SetRecording(false);
    if (recorder_) recorder_->End();
  }
  if (collection_ && pipeline_) pipeline_->StopWandCollection();
  if (job_) {
    job_->cancel->store(true);
    if (job_->thread.joinable()) job_->thread.join();
  }
  if (recorder_) recorder_->Stop();  // commits what is queued
  if (ptp_monitor_) ptp_monitor_->Stop();  // reads the cameras: before they close
  if (pipeline_) pipeline_->Stop();
  if (recording_ && store_) {
    store_->FinishRecording(recording_->id, RecordingState::kInterrupted, "", "the daemon stopped");
  }
  recording_.reset();
  // Tasks posted by the workers during the stop refer to state that is going: drop them.
  {
    std::lock_guard<std::mutex> lock(tasks_mutex_);
    tasks_.clear();
  }
  recorder_.reset();
  ptp_monitor_.reset();
  pipeline_.reset();
  sim_rig_.reset();
  server_.reset();
  store_.reset();
  if (timer_source_) timer_source_ = sd_event_source_disable_unref(timer_source_);
  if (wake_source_) wake_source_ = sd_event_source_disable_unref(wake_source_);
  for (auto*& s : signal_sources_) s = sd_event_source_disable_unref(s);
  signal_sources_.clear();
  if (wake_fd_ >= 0) ::close(wake_fd_), wake_fd_ = -1;
  if (loop_) loop_ = sd_event_unref(loop_);
}


int Daemon::OnSignalPipe(sd_event_source*, int fd, uint32_t, void* self) {
  unsigned char b = 0;
  while (::read(fd, &b, 1) == 1) {
    struct signalfd_siginfo si {};
    si.ssi_signo = b;
    OnSignal(nullptr, &si, self);
  }
  return 0;
}

int Daemon::OnSignal(sd_event_source*, const struct signalfd_siginfo* si, void* self) {
  auto* d = static_cast<Daemon*>(self);
  if (si->ssi_signo == SIGHUP) {
    spdlog::info("SIGHUP: re-reading {}", d->options_.config_path);
    Request r;
    r.client.id = 0;
    d->ConfigReload(r);
    return 0;
  }
  spdlog::info("{}: stopping", si->ssi_signo == SIGTERM ? "SIGTERM" : "SIGINT");
  sd_event_exit(d->loop_, 0);
  return 0;
}

int Daemon::OnWake(sd_event_source*, int fd, uint32_t, void* self) {
  auto* d = static_cast<Daemon*>(self);
  std::uint64_t n;
  [[maybe_unused]] ssize_t got = ::read(fd, &n, sizeof n);
  std::deque<std::function<void()>> tasks;
  {
    std::lock_guard<std::mutex> lock(d->tasks_mutex_);
    tasks.swap(d->tasks_);
  }
  for (auto& t : tasks) t();
  d->DrainFrames();
  return 0;
}

int Daemon::OnTimer(sd_event_source* s, uint64_t usec, void* self) {
  auto* d = static_cast<Daemon*>(self);
  d->Tick();
  sd_event_source_set_time(s, usec + 100000);
  sd_event_source_set_enabled(s, SD_EVENT_ON);
  return 0;
}

void Daemon::DrainFrames() {
  if (!pipeline_) return;
  LiveFrame f;
  int n = 0;
  while (n < 64 && pipeline_->PopFrame(&f)) {
    ++n;
    last_frame_ = f.frame;
    Stream(f);
    last_live_ = std::move(f);
  }
}

// ---------------------------------------------------------------------------------------------
// Requests

void Daemon::Fail(const Request& r, const std::string& code, const std::string& message) {
  if (r.client.id == 0) {
    spdlog::warn("{}: {}", r.method, message);
    return;
  }
  server_->ReplyError(r.client.id, r.id, code, message);
}

void Daemon::Progress(const Request& r, const std::string& job, Json fields) {
  if (r.client.id == 0 || !server_) return;
  fields["event"] = "progress";
  fields["id"] = r.id;
  fields["job"] = job;
  if (!fields.contains("fraction")) fields["fraction"] = nullptr;
  if (!fields.contains("eta_s")) fields["eta_s"] = nullptr;
  server_->SendEvent(r.client.id, fields);
}

void Daemon::OnDisconnect(std::uint64_t client) { subscribers_.erase(client); }

void Daemon::OnRequest(const ClientInfo& client, const Json& id, const std::string& method,
                       const Json& params) {
  Request r{client, id, method, params};
  using Handler = void (Daemon::*)(const Request&);
  struct Entry {
    Handler handler;
    bool control;
  };
  static const std::map<std::string, Entry> kMethods = {
      {"status", {nullptr, false}},
      {"cameras", {nullptr, false}},
      {"cameras.check", {&Daemon::CamerasCheck, false}},
      {"config.reload", {&Daemon::ConfigReload, true}},
      {"rig.calibrate.start", {&Daemon::RigCalibrateStart, true}},
      {"rig.calibrate.finish", {&Daemon::RigCalibrateFinish, true}},
      {"rig.calibrate.cancel", {&Daemon::RigCalibrateCancel, true}},
      {"rig.calibrate.apply", {&Daemon::RigCalibrateApply, true}},
      {"calibration.list", {&Daemon::CalibrationList, false}},
      {"subject.create", {&Daemon::SubjectCreate, true}},
      {"subject.select", {&Daemon::SubjectSelect, true}},
      {"subject.list", {&Daemon::SubjectList, false}},
      {"protocol.show", {&Daemon::ProtocolShow, false}},
      {"record.start", {&Daemon::RecordStart, true}},
      {"record.stop", {&Daemon::RecordStop, true}},
      {"recording.list", {&Daemon::RecordingList, false}},
      {"fit.start", {&Daemon::FitStart, true}},
      {"fit.cancel", {&Daemon::FitCancel, true}},
      {"model.list", {&Daemon::ModelList, false}},
      {"model.apply", {&Daemon::ModelApply, true}},
      {"export", {&Daemon::Export, true}},
      {"subscribe", {&Daemon::Subscribe, false}},
      {"unsubscribe", {&Daemon::Unsubscribe, false}},
      {"shutdown", {nullptr, true}},
      {"sim.camera", {&Daemon::SimCamera, true}},
  };
  auto it = kMethods.find(method);
  if (it == kMethods.end()) {
    Fail(r, error_code::kUnknownMethod, "unknown method '" + method + "'");
    return;
  }
  bool needs_control = it->second.control;
  // Exporting back over the socket only reads.
  // (Compared as JSON: `params.value("inline", false)` threw on a non-boolean "inline", outside
  // the try below, and any client could stop the daemon with one line.)
  if (method == "export" && params.contains("inline") && params["inline"] == true)
    needs_control = false;
  if (needs_control && !client.may_control) {
    Fail(r, error_code::kForbidden,
         method + " changes state: it needs root or membership of group '" +
             config_.control_group + "' (uid " + std::to_string(client.uid) + " may only read)");
    return;
  }
  try {
    if (method == "status") {
      server_->Reply(client.id, id, Status_());
    } else if (method == "cameras") {
      server_->Reply(client.id, id, CamerasJson());
    } else if (method == "shutdown") {
      server_->Reply(client.id, id, {{"stopping", true}});
      spdlog::info("shutdown requested by uid {}", client.uid);
      sd_event_exit(loop_, 0);
    } else {
      (this->*(it->second.handler))(r);
    }
  } catch (const std::exception& e) {
    // nlohmann throws on a type mismatch the checks above missed: a bug, reported, not fatal.
    Fail(r, error_code::kInternal, method + ": " + e.what());
  }
}

Json Daemon::CamerasJson() const {
  Json cams = Json::array();
  if (!pipeline_) return {{"cameras", cams}};
  const double up = std::max(1e-3, SecondsSince(started_ns_));
  const std::vector<CameraHealth> health = pipeline_->DetectionHealthSnapshot();
  const CapturePipelineStats sync = pipeline_->Stats(/*timings=*/false).capture;
  for (int c = 0; c < pipeline_->num_cameras(); ++c) {
    drivers::CameraSource& cam = pipeline_->camera(c);
    const auto& k = cam.Counters();
    const CameraHealth& h = health[static_cast<std::size_t>(c)];
    const bool streaming = cam.State() == drivers::CameraState::kStreaming;
    const double silent_s = c < static_cast<int>(sync.camera_silent_s.size()) ? sync.camera_silent_s[c] : 0.0;
    Json problem;
    if (!streaming) problem = cam.LastError();
    else if (silent_s > 0)
      problem = fmt::format("no frame for {:.2f} s while the other cameras deliver", silent_s);
    cams.push_back({{"id", cam.id()},
                    {"connected", streaming},
                    {"silent_s", streaming && silent_s > 0 ? Json(silent_s) : Json()},
                    {"problem", problem},
                    {"frames", k.complete.load()},
                    {"fps", k.complete.load() / up},
                    {"incomplete", k.missing_packets.load() + k.size_mismatches.load()},
                    {"dropped", k.underruns.load()},
                    {"not_received", k.not_received.load()},
                    {"losses", k.losses.load()},
                    {"nonfinite_centroids", h.nonfinite_centroids},
                    {"overfull_sets", h.overfull_sets},
                    {"reprojection_px", h.reprojection_samples > 0 && h.reprojection_px > 0
                                            ? Json(h.reprojection_px) : Json()},
                    {"calibration_suspect", h.calibration_suspect},
                    {"resyncs", c < static_cast<int>(sync.camera_resyncs.size()) ? sync.camera_resyncs[c] : 0},
                    {"clock_offset_ms", c < static_cast<int>(sync.camera_clock_offset_ms.size())
                                            ? sync.camera_clock_offset_ms[c] : 0.0},
                    {"clock_drift_ppm", c < static_cast<int>(sync.camera_clock_drift_ppm.size())
                                            ? sync.camera_clock_drift_ppm[c] : 0.0},
                    {"width", config_.width},
                    {"height", config_.height}});
  }
  return {{"cameras", cams}};
}

Json Daemon::Status_() const {
  Json j;
  j["state"] = stopped_ ? "stopping" : "running";
  j["version"] = options_.version;
  j["uptime_s"] = SecondsSince(started_ns_);
  Json rig = {{"simulated", config_.simulated_cameras > 0},
              {"cameras", pipeline_ ? pipeline_->num_cameras() : 0},
              {"rate_hz", config_.rate_hz},
              {"calibrated", pipeline_ && pipeline_->calibrated()},
              {"calibration_version", calibration_version_ > 0 ? Json(calibration_version_) : Json()}};
  if (sim_rig_) {
    rig["virtual_subject"] = {{"height_m", sim_rig_->scene().height_m()},
                              {"seed", config_.subject_seed}};
  }
  j["rig"] = rig;
  j["sync"] = SyncJson();
  j["cameras"] = CamerasJson()["cameras"];
  {
    // Bad data, summed over the cameras; the cameras whose calibration looks off, by id.
    Json suspect = Json::array();
    std::uint64_t nonfinite = 0, overfull = 0;
    for (const Json& cam : j["cameras"]) {
      nonfinite += cam.value("nonfinite_centroids", std::uint64_t{0});
      overfull += cam.value("overfull_sets", std::uint64_t{0});
      if (cam.value("calibration_suspect", false)) suspect.push_back(cam["id"]);
    }
    j["health"] = {{"nonfinite_centroids", nonfinite},
                   {"overfull_sets", overfull},
                   {"calibration_suspect", suspect}};
  }
  if (pipeline_) {
    // The timing percentiles cost milliseconds: at most once a second, however many clients ask
    // (a flood of status requests must not hold the loop off the frames).
    const std::uint64_t now = drivers::MonotonicNs();
    if (now - stats_cached_ns_ > 1000000000ull) {
      stats_cache_ = pipeline_->Stats();
      stats_cached_ns_ = now;
    }
    LivePipelineStats st = pipeline_->Stats(/*timings=*/false);
    st.capture.latency_ms_p50 = stats_cache_.capture.latency_ms_p50;
    st.capture.latency_ms_p99 = stats_cache_.capture.latency_ms_p99;
    st.track_ms_p50 = stats_cache_.track_ms_p50;
    st.track_ms_p99 = stats_cache_.track_ms_p99;
    j["sets"] = {{"total", st.capture.frame_sets},
                 {"incomplete", st.capture.incomplete_sets},
                 {"dropped", st.capture.dropped_frame_sets},
                 {"undelivered", st.capture.undelivered_frame_sets},
                 {"warmup", st.capture.warmup_sets},
                 {"mismatched", st.capture.mismatched_sets}};
    j["tracker"] = {{"state", TrackStateName(st.tracker_state)},
                    {"labelled", st.labelled},
                    {"markers", st.markers},
                    {"frames_tracked", st.frames_tracked},
                    {"frames_tracking", st.frames_tracking},
                    {"loop_dropped", st.loop_dropped},
                    {"recorder_dropped", st.recorder_dropped},
                    {"searches_skipped", st.searches_skipped}};
    auto depth = [](const QueueDepth& q) {
      return Json{{"depth", q.depth}, {"max", q.max_depth}, {"capacity", q.capacity}};
    };
    j["queues"] = {{"frames", depth(st.capture.frame_queue)},
                   {"detections", depth(st.capture.detection_queue)},
                   {"points", depth(st.capture.point_queue)},
                   {"loop", depth(st.loop_queue)},
                   {"recorder", depth(st.recorder_queue)}};
    j["latency_ms"] = {{"p50", st.capture.latency_ms_p50},
                       {"p99", st.capture.latency_ms_p99},
                       {"track_p50", st.track_ms_p50},
                       {"track_p99", st.track_ms_p99},
                       {"track_max", st.track_ms_max}};
    j["frame"] = last_frame_;
  }
  j["subject"] = subject_ ? Json{{"id", subject_->id}, {"name", subject_->name}} : Json();
  j["live_model_version"] = live_model_version_ > 0 ? Json(live_model_version_) : Json();
  j["model_version"] = nullptr;
  if (subject_ && store_) {
    ModelRecord latest;
    if (store_->GetModel(subject_->id, 0, &latest)) j["model_version"] = latest.version;
  }
  if (recording_) {
    j["recording"] = {{"id", recording_->id},
                      {"movement", recording_->movement},
                      {"frames", recorder_ ? recorder_->frames() : 0},
                      {"seconds", SecondsSince(recording_->started_ns)}};
  } else {
    j["recording"] = nullptr;
  }
  if (collection_) j["job"] = {{"kind", "rig.calibrate"}, {"phase", "collect"}};
  else if (job_) j["job"] = {{"kind", job_->kind}, {"fraction", job_->fraction}};
  else j["job"] = nullptr;
  std::uint64_t db = 0;
  if (store_) store_->Usage(&db);
  struct statvfs vfs {};
  std::uint64_t free_bytes = 0;
  if (statvfs(config_.state_dir.c_str(), &vfs) == 0)
    free_bytes = static_cast<std::uint64_t>(vfs.f_bavail) * vfs.f_frsize;
  j["storage"] = {{"dir", config_.state_dir}, {"db_bytes", db}, {"free_bytes", free_bytes}};
  {
    // RSS beside the heap in use tells a leak from memory the allocator keeps (process_memory.h).
    const std::uint64_t now = drivers::MonotonicNs();
    if (now - memory_cached_ns_ > 1000000000ull && ReadProcessMemory(&memory_cache_)) memory_cached_ns_ = now;
    j["memory"] = {{"rss_bytes", memory_cache_.rss_bytes},
                   {"heap_in_use_bytes", memory_cache_.heap_in_use_bytes},
                   {"heap_free_bytes", memory_cache_.heap_free_bytes}};
  }
  if (recorder_) {
    // What the recorder's commit deadline keeps in reserve (daemon/recorder.h): a disk whose
    // WAL sync outgrows the 100 ms budget shows here before a power cut would show it.
    j["storage"]["commit_ms_max"] = recorder_->slowest_recent_commit_ms();
    j["storage"]["wal_sync_ms_max"] = recorder_->slowest_recent_sync_ms();
    j["storage"]["wal_sync_failures"] = recorder_->sync_failures();
  }
  j["clients"] = server_ ? server_->client_count() : 0;
  // Where a slow subscriber's frames went: the loop never waits for one, its frames are dropped
  // at its connection (daemon/control_server.h) and counted here.
  Json subscribers = Json::array();
  for (const auto& [client, sub] : subscribers_) {
    subscribers.push_back({{"client", client},
                           {"streams", sub.streams},
                           {"decimation", sub.decimation},
                           {"sent", sub.sent},
                           {"dropped", sub.dropped}});
  }
  j["subscribers"] = subscribers;
  return j;
}

void Daemon::ConfigReload(const Request& r) {
  ReloadNotice reload_notice(options_.notifier);  // RELOADING=1 now, READY=1 on return
  DaemonConfig fresh;
  if (options_.config_path.empty()) {
    Fail(r, error_code::kUnavailable, "mocapd was started without a config file");
    return;
  }
  if (Status s = LoadConfig(options_.config_path, &fresh); !s) {
    spdlog::error("config.reload: {} (the running configuration is unchanged)", s.message());
    Fail(r, error_code::kFailed, s.message() + " (the running configuration is unchanged)");
    return;
  }
  // Command-line overrides stay in force.
  fresh.state_dir = config_.state_dir;
  fresh.socket_path = config_.socket_path;
  if (!options_.export_dirs.empty()) fresh.export_dirs = options_.export_dirs;
  Json applied = Json::array(), restart = Json::array();
  for (const ConfigChange& c : DiffConfig(config_, fresh)) {
    (c.needs_restart ? restart : applied).push_back(c.key);
  }
  // What can change live (daemon/config.h DiffConfig): the control limits and group, the
  // protocol, the fit's defaults. The protocol is loaded first: a file that does not parse keeps
  // the running one, as a config that does not validate does.
  if (fresh.protocol_file != config_.protocol_file) {
    sim::Protocol protocol = sim::DefaultProtocol();
    if (!fresh.protocol_file.empty()) {
      if (Status s = sim::LoadProtocolJson(fresh.protocol_file, &protocol); !s) {
        spdlog::error("config.reload: {} (the running configuration is unchanged)", s.message());
        Fail(r, error_code::kFailed, s.message() + " (the running configuration is unchanged)");
        return;
      }
    }
    protocol_ = std::move(protocol);
  }
  config_.protocol_file = fresh.protocol_file;
  config_.max_clients = fresh.max_clients;
  config_.max_line_bytes = fresh.max_line_bytes;
  config_.max_pending_requests = fresh.max_pending_requests;
  config_.control_group = fresh.control_group;
  config_.fit_threads = fresh.fit_threads;
  config_.fit_max_iterations = fresh.fit_max_iterations;
  config_.fit_groups = fresh.fit_groups;
  config_.fit_coarse_frames = fresh.fit_coarse_frames;
  config_.export_dirs = fresh.export_dirs;
  config_.subscriber_queue_frames = fresh.subscriber_queue_frames;
  server_->SetLimits(fresh.max_clients, fresh.max_line_bytes, fresh.max_pending_requests,
                     fresh.subscriber_queue_frames);
  server_->SetControlGroup(fresh.control_group);
  spdlog::info("config reloaded from {}: {} applied, {} need a restart", options_.config_path,
               applied.size(), restart.size());
  if (r.client.id != 0)
    server_->Reply(r.client.id, r.id,
                   {{"reloaded", true}, {"applied", applied}, {"needs_restart", restart}});
}

// ---------------------------------------------------------------------------------------------
// Rig calibration

void Daemon::RigCalibrateStart(const Request& r) {
  Params p(r.params);
  double seconds = 20;
  if (!p.Number("seconds", &seconds, 1, 600, false)) return Fail(r, error_code::kInvalidParams, p.error);
  if (collection_ || (job_ && job_->kind == "rig.calibrate"))
    return Fail(r, error_code::kConflict, "a rig calibration is already running");
  if (recording_) return Fail(r, error_code::kConflict, "a recording is running; stop it first");
  collection_ = Collection{r, seconds, drivers::MonotonicNs(), -1};
  if (sim_rig_) sim_rig_->scene().WaveWand(seconds);  // the virtual operator waves the wand
  pipeline_->StartWandCollection();
  spdlog::info("rig calibration: collecting wand frames for {} s", seconds);
  server_->Reply(r.client.id, r.id, {{"collecting", true}, {"seconds", seconds}});
}

void Daemon::RigCalibrateCancel(const Request& r) {
  if (!collection_) return Fail(r, error_code::kConflict, "no rig calibration is collecting");
  pipeline_->StopWandCollection();
  collection_.reset();
  if (sim_rig_) sim_rig_->scene().StandStatic();
  server_->Reply(r.client.id, r.id, {{"cancelled", true}});
}

void Daemon::RigCalibrateFinish(const Request& r) {
  if (!collection_) return Fail(r, error_code::kConflict, "rig.calibrate.start first");
  if (job_) return Fail(r, error_code::kConflict, "a " + job_->kind + " job is running");
  std::vector<reconstruction::DetectionSet> wand = pipeline_->StopWandCollection();
  collection_.reset();
  if (wand.size() < 20)
    return Fail(r, error_code::kFailed,
                "only " + std::to_string(wand.size()) +
                    " wand frames were seen by two cameras or more; wave the wand through the "
                    "volume for longer");
  job_ = std::make_unique<Job>();
  job_->kind = "rig.calibrate";
  job_->request = r;
  job_->cancel = std::make_shared<std::atomic<bool>>(false);
  auto cancel = job_->cancel;
  std::vector<reconstruction::CameraModel> start = start_cameras_;
  std::vector<reconstruction::CameraModel> truth;
  // The fakes' truth, when they are the whole rig (no real camera joined: config.h).
  if (sim_rig_ && static_cast<int>(sim_rig_->true_cameras().size()) == pipeline_->num_cameras())
    truth = sim_rig_->true_cameras();
  LivePipeline* pipeline = pipeline_.get();
  sim::LiveScene* scene = sim_rig_ ? &sim_rig_->scene() : nullptr;
  job_->thread = std::thread([this, r, cancel, start, truth, pipeline, scene,
                              wand = std::move(wand)]() mutable {
    // The L-frame on the floor for a second (a real operator lays it down before finishing).
    if (scene) scene->ShowLFrame(1.5);
    std::this_thread::sleep_for(std::chrono::milliseconds(300));
    pipeline->StartWandCollection();
    std::this_thread::sleep_for(std::chrono::milliseconds(1000));
    std::vector<reconstruction::DetectionSet> lframe = pipeline->StopWandCollection();
    if (scene) scene->StandStatic();
    reconstruction::WandCalibrationOptions wo;
    wo.num_threads = 1;
    wo.lm.callbacks.push_back([this, r, cancel](const solver::IterationSummary& it) {
      Json ev = {{"phase", "solve"}, {"iteration", it.iteration}, {"cost", it.cost},
                 {"message", "bundle adjustment iteration " + std::to_string(it.iteration) +
                                 ": cost " + std::to_string(it.cost)}};
      PostToLoop([this, r, ev] { Progress(r, "rig.calibrate", ev); });
      return !cancel->load();
    });
    std::vector<reconstruction::CameraModel> calibrated;
    reconstruction::WandCalibrationSummary summary;
    Status s = reconstruction::CalibrateWand(start, wand, lframe, wo, &calibrated, &summary);
    Json result;
    std::string json_text;
    if (s) {
      reconstruction::CalibrationFile file =
          reconstruction::CalibrationFileOf(calibrated, summary, wo.wand);
      Json cams = Json::array();
      for (std::size_t c = 0; c < file.cameras.size(); ++c) {
        reconstruction::CalibratedCamera& cc = file.cameras[c];
        Json cj = {{"id", cc.camera.id},
                   {"reprojection_rms_px", cc.reprojection_rms_px},
                   {"wand_frames", cc.wand_frames}};
        if (c < truth.size() && summary.lab_frame_from_lframe) {
          double pos = 0, ang = 0;
          reconstruction::CameraPoseError(cc.camera, truth[c], &pos, &ang);
          cc.position_error_mm = 1000 * pos;
          cc.orientation_error_deg = ang * 180 / M_PI;
          cj["position_error_mm"] = cc.position_error_mm;
          cj["orientation_error_deg"] = cc.orientation_error_deg;
        }
        cams.push_back(cj);
      }
      json_text = reconstruction::CalibrationJsonString(file);
      result = {{"reprojection_rms_px", summary.reprojection_rms_px},
                {"wand_length_error_mm", summary.wand_length_error_mm_rms},
                {"wand_frames", summary.wand_frames_used},
                {"lframe_frames", lframe.size()},
                {"lab_frame", file.lab_frame},
                {"termination", summary.BriefReport()},
                {"cameras", cams}};
      if (!truth.empty() && summary.lab_frame_from_lframe) {
        double pmax = 0, amax = 0;
        for (const auto& c : file.cameras) {
          pmax = std::max(pmax, c.position_error_mm);
          amax = std::max(amax, c.orientation_error_deg);
        }
        result["truth"] = {{"position_error_mm_max", pmax}, {"orientation_error_deg_max", amax}};
      }
    }
    const bool cancelled = cancel->load();
    PostToLoop([this, r, s, result, json_text, summary, cancelled]() mutable {
      if (job_ && job_->thread.joinable()) job_->thread.join();
      job_.reset();
      if (cancelled) return Fail(r, error_code::kCancelled, "rig calibration cancelled");
      if (!s) {
        spdlog::error("rig calibration failed: {}", s.message());
        return Fail(r, error_code::kFailed, "rig calibration failed: " + s.message());
      }
      std::int64_t version = 0;
      if (Status st = store_->AddCalibration(json_text, summary.reprojection_rms_px,
                                             summary.wand_length_error_mm_rms,
                                             "mocapd " + options_.version + " rig.calibrate",
                                             &version);
          !st)
        return Fail(r, error_code::kFailed, st.message());
      result["version"] = version;
      spdlog::info("rig calibration {}: reprojection RMS {:.3f} px, wand length error {:.3f} mm",
                   version, summary.reprojection_rms_px, summary.wand_length_error_mm_rms);
      server_->Reply(r.client.id, r.id, result);
    });
  });
}

void Daemon::RigCalibrateApply(const Request& r) {
  Params p(r.params);
  std::int64_t version = 0;
  if (!p.Int("version", &version, 1, INT64_MAX, false))
    return Fail(r, error_code::kInvalidParams, p.error);
  CalibrationRecord rec;
  if (Status s = store_->GetCalibration(version, &rec); !s)
    return Fail(r, error_code::kNotFound, s.message());
  reconstruction::CalibrationFile cal;
  Status s = reconstruction::ParseCalibrationJson(
      rec.calibration_json, "stored calibration " + std::to_string(rec.version), &cal);
  std::vector<std::string> ids;
  for (int c = 0; c < pipeline_->num_cameras(); ++c) ids.push_back(pipeline_->camera(c).id());
  std::vector<reconstruction::CameraModel> cams;
  if (s) s = reconstruction::MatchCalibrationToRig(cal, ids, &cams);
  if (s) s = pipeline_->SetCalibration(cams);
  if (!s) return Fail(r, error_code::kFailed, "calibration " + std::to_string(rec.version) + ": " + s.message());
  calibration_version_ = static_cast<int>(rec.version);
  RememberLive();
  spdlog::info("rig calibration {} applied from frame {}", rec.version, last_frame_ + 1);
  server_->Reply(r.client.id, r.id, {{"version", rec.version}, {"from_frame", last_frame_ + 1}});
}

void Daemon::CalibrationList(const Request& r) {
  std::vector<CalibrationRecord> list;
  if (Status s = store_->ListCalibrations(&list); !s) return Fail(r, error_code::kFailed, s.message());
  Json out = Json::array();
  for (const auto& c : list)
    out.push_back({{"version", c.version},
                   {"created_at", c.created_at},
                   {"reprojection_rms_px", c.reprojection_rms_px},
                   {"wand_length_error_mm", c.wand_length_error_mm},
                   {"live", c.version == calibration_version_}});
  server_->Reply(r.client.id, r.id, {{"calibrations", out}});
}

// ---------------------------------------------------------------------------------------------
// Subjects and models

Status Daemon::LoadSubjectModel(const SubjectRecord& subject, int version,
                                std::shared_ptr<Model>* out, int* got_version,
                                ekf::ModelOrigin* origin) {
  ModelRecord rec;
  MOCAP_RETURN_IF_ERROR(store_->GetModel(subject.id, version, &rec));
  auto model = std::make_shared<Model>();
  MOCAP_RETURN_IF_ERROR(ParseModelJson(rec.model_json,
                                       "subject " + subject.name + " model v" +
                                           std::to_string(rec.version),
                                       model.get()));
  *out = std::move(model);
  *got_version = static_cast<int>(rec.version);
  if (origin)
    *origin = rec.fit_report_id ? ekf::ModelOrigin::kFittedToSubject : ekf::ModelOrigin::kGeneric;
  return Status::Ok();
}

void Daemon::SubjectCreate(const Request& r) {
  Params p(r.params);
  std::string name, model_arg = "default";
  double height = 0;
  if (!p.String("name", &name, true) || !p.Number("height_m", &height, 0.5, 2.5, true) ||
      !p.String("model", &model_arg, false))
    return Fail(r, error_code::kInvalidParams, p.error);
  if (name.empty() || name.size() > 128)
    return Fail(r, error_code::kInvalidParams, "params.name: 1 to 128 characters");
  Model model;
  std::string osim_text;
  if (model_arg == "default") {
    const Model full = DefaultFullBodyModel(height);
    if (Status s = full.WithMarkers(sim::SimulatedMarkers(full, false), &model); !s)
      return Fail(r, error_code::kInternal, "the default model: " + s.message());
  } else if (EndsWith(model_arg, ".osim")) {
    formats::OsimImport import;
    if (Status s = formats::ImportOsim(model_arg, &import); !s)
      return Fail(r, error_code::kFailed, s.message());
    for (const std::string& what : import.ignored) spdlog::warn("{}: {}", model_arg, what);
    model = import.model;
    if (Status s = formats::detail::ReadWholeFile(model_arg, &osim_text); !s)
      return Fail(r, error_code::kFailed, s.message());
  } else if (EndsWith(model_arg, ".json")) {
    if (Status s = LoadModelJson(model_arg, &model); !s)
      return Fail(r, error_code::kFailed, s.message());
  } else {
    return Fail(r, error_code::kInvalidParams,
                "params.model: \"default\", or the path of an .osim or .json model, got '" +
                    model_arg + "'");
  }
  SubjectRecord rec;
  if (Status s = store_->CreateSubject(name, height, model_arg, osim_text, ModelToJsonString(model),
                                       "mocapd " + options_.version + " subject.create", &rec);
      !s) {
    const bool taken = s.message().find("already") != std::string::npos;
    return Fail(r, taken ? error_code::kConflict : error_code::kFailed, s.message());
  }
  spdlog::info("subject '{}' created (id {}, {:.2f} m, model {})", name, rec.id, height, model_arg);
  server_->Reply(r.client.id, r.id, {{"id", rec.id}, {"name", rec.name}, {"model_version", 1}});
}

Status Daemon::SelectSubject(const SubjectRecord& subject, int version) {
  std::shared_ptr<Model> model;
  int got = 0;
  ekf::ModelOrigin origin = ekf::ModelOrigin::kGeneric;
  MOCAP_RETURN_IF_ERROR(LoadSubjectModel(subject, version, &model, &got, &origin));
  subject_ = subject;
  live_model_ = model;
  live_model_version_ = got;
  pipeline_->SetSubjectModel(model, got, origin);
  RememberLive();
  return Status::Ok();
}

// What is live goes to the store (daemon_state), so that a restart -- a crash, the watchdog, an
// upgrade -- resumes it. A failure here (a full disk) is logged; the live state itself is fine.
void Daemon::RememberLive() {
  Status s = store_->SetState("subject", subject_ ? std::to_string(subject_->id) : "");
  if (s) s = store_->SetState("live_model_version", std::to_string(live_model_version_));
  if (s) s = store_->SetState("calibration_version", std::to_string(calibration_version_));
  if (!s) spdlog::warn("cannot remember what is live: {}", s.message());
}

// After a restart: the subject, model and calibration that were live.
void Daemon::ResumeLive() {
  std::string subject_id, version;
  if (!store_->GetState("subject", &subject_id) || subject_id.empty()) return;
  store_->GetState("live_model_version", &version);
  SubjectRecord rec;
  if (Status s = store_->GetSubject(std::atoll(subject_id.c_str()), &rec); !s) {
    spdlog::warn("cannot resume the subject that was live: {}", s.message());
    return;
  }
  if (Status s = SelectSubject(rec, std::atoi(version.c_str())); !s) {
    spdlog::warn("cannot resume subject '{}': {}", rec.name, s.message());
    return;
  }
  spdlog::info("resumed subject '{}' with model v{}", rec.name, live_model_version_);
}

void Daemon::SubjectSelect(const Request& r) {
  Params p(r.params);
  std::string name;
  std::int64_t id = 0;
  if (!p.String("name", &name, false) || !p.Int("id", &id, 1, INT64_MAX, false))
    return Fail(r, error_code::kInvalidParams, p.error);
  if (name.empty() && id == 0) return Fail(r, error_code::kInvalidParams, "params.name or params.id: missing");
  if (recording_) return Fail(r, error_code::kConflict, "a recording is running; stop it first");
  if (job_ && job_->kind == "fit") return Fail(r, error_code::kConflict, "a fit is running");
  SubjectRecord rec;
  Status s = name.empty() ? store_->GetSubject(id, &rec) : store_->FindSubject(name, &rec);
  if (!s) return Fail(r, error_code::kNotFound, s.message());
  if (s = SelectSubject(rec, 0); !s) return Fail(r, error_code::kFailed, s.message());
  spdlog::info("subject '{}' selected: tracking with model v{}", rec.name, live_model_version_);
  server_->Reply(r.client.id, r.id,
                 {{"id", rec.id}, {"name", rec.name}, {"model_version", live_model_version_}});
}

void Daemon::SubjectList(const Request& r) {
  std::vector<SubjectRecord> list;
  if (Status s = store_->ListSubjects(&list); !s) return Fail(r, error_code::kFailed, s.message());
  Json out = Json::array();
  for (const auto& s : list) {
    std::vector<ModelRecord> models;
    store_->ListModels(s.id, &models);
    std::vector<RecordingInfo> recs;
    store_->ListRecordings(s.id, &recs);
    out.push_back({{"id", s.id},
                   {"name", s.name},
                   {"height_m", s.height_m},
                   {"model_source", s.model_source},
                   {"model_versions", models.size()},
                   {"recordings", recs.size()},
                   {"created_at", s.created_at},
                   {"selected", subject_ && subject_->id == s.id}});
  }
  server_->Reply(r.client.id, r.id, {{"subjects", out}});
}

void Daemon::ProtocolShow(const Request& r) {
  Json moves = Json::array();
  for (const sim::Movement& m : protocol_.movements) {
    Json ex = Json::array();
    for (const sim::Excitation& e : m.excitations)
      ex.push_back({{"coordinate", e.coordinate},
                    {"min_deg", e.min_deg},
                    {"max_deg", e.max_deg},
                    {"required", e.required}});
    moves.push_back({{"name", m.name},
                     {"description", m.description},
                     {"duration_s", m.duration_s},
                     {"excitations", ex}});
  }
  server_->Reply(r.client.id, r.id, {{"name", protocol_.name}, {"movements", moves}});
}

// ---------------------------------------------------------------------------------------------
// Recordings

void Daemon::RecordStart(const Request& r) {
  Params p(r.params);
  std::string movement;
  double duration = 0, amplitude = 1.0, scale = 1.0;
  if (!p.String("movement", &movement, true) || !p.Number("duration_s", &duration, 0.1, 3600, false) ||
      !p.Number("sim_amplitude", &amplitude, 0.0, 2.0, false) ||
      !p.Number("sim_duration_scale", &scale, 0.1, 10.0, false))
    return Fail(r, error_code::kInvalidParams, p.error);
  const sim::Movement* m = protocol_.Find(movement);
  if (!m) {
    std::string names;
    for (const auto& mv : protocol_.movements) names += (names.empty() ? "" : ", ") + mv.name;
    return Fail(r, error_code::kNotFound,
                "movement '" + movement + "' is not in the protocol (" + names + ")");
  }
  if (ptp_monitor_) {
    UpdatePtp();
    if (!ptp_.locked)
      return Fail(r, error_code::kUnavailable,
                  "the rig is not locked to one PTP clock (" + ptp_.why +
                      "): its frame sets would mix instants; recording refused");
  }
  if (!subject_) return Fail(r, error_code::kConflict, "select a subject first (subject.select)");
  if (!pipeline_->calibrated())
    return Fail(r, error_code::kUnavailable, "the rig is not calibrated (rig.calibrate.*)");
  if (recording_) return Fail(r, error_code::kConflict, "recording " + std::to_string(recording_->id) + " is running");
  if (collection_) return Fail(r, error_code::kConflict, "a rig calibration is collecting");
  if ((p.Has("sim_amplitude") || p.Has("sim_duration_scale")) && !sim_rig_)
    return Fail(r, error_code::kUnavailable, "sim_* parameters need a simulated rig");
  double lead = 0;
  if (sim_rig_) {
    double start = 0, end = 0;
    if (Status s = sim_rig_->scene().Perform(movement, amplitude, scale, &start, &end); !s)
      return Fail(r, error_code::kFailed, s.message());
    lead = std::max(0.0, start - sim_rig_->scene().SceneTimeNow());
    if (duration <= 0) duration = (end - start) + lead + 0.5;
  }
  if (duration <= 0) duration = m->duration_s + 1.0;
  std::vector<std::string> marker_names, coordinate_names;
  for (const auto& mk : live_model_->markers()) marker_names.push_back(mk.name);
  for (const auto& c : live_model_->coordinates()) coordinate_names.push_back(c.name);
  std::int64_t id = 0;
  if (Status s = store_->BeginRecording(subject_->id, movement, config_.rate_hz, marker_names,
                                        coordinate_names, live_model_version_,
                                        "mocapd " + options_.version + " record.start", &id);
      !s)
    return Fail(r, error_code::kFailed, s.message());
  recording_ = Recording{id, r, movement, duration, drivers::MonotonicNs(), -1, false, {}};
  {
    const LivePipelineStats st = pipeline_->Stats(/*timings=*/false);
    recording_->sets_dropped_at_start = st.capture.dropped_frame_sets;
    recording_->sets_not_exposed_at_start = st.capture.undelivered_frame_sets;
    recording_->recorder_dropped_at_start = st.recorder_dropped;
  }
  recorder_->Begin(id, static_cast<int>(marker_names.size()), static_cast<int>(coordinate_names.size()),
                   [this](std::int64_t rec, Status s, std::int64_t frames) {
    PostToLoop([this, rec, s, frames] {
      if (!recording_ || recording_->id != rec) return;
      if (!s) {
        // The disk is full (or the store failed otherwise): the recording stops, what was
        // committed stays readable, tracking and the stream go on.
        std::string why = s.message();
        struct statvfs vfs {};
        if (statvfs(config_.state_dir.c_str(), &vfs) == 0)
          why += "; " + std::to_string(static_cast<std::uint64_t>(vfs.f_bavail) * vfs.f_frsize / 1024) +
                 " kB free in " + config_.state_dir;
        spdlog::error("recording {} stopped: {} ({} frames kept)", rec, why, frames);
        pipeline_->SetRecording(false);
        FinishInStore(rec, RecordingState::kFailed, "", why);
        Fail(recording_->request, error_code::kFailed,
             "recording " + std::to_string(rec) + " stopped: " + why + " (" +
                 std::to_string(frames) + " frames kept)");
        recording_.reset();
        return;
      }
      FinishRecording();
    });
  });
  pipeline_->SetRecording(true);
  spdlog::info("recording {} ({}) started for {:.1f} s", id, movement, duration);
}

void Daemon::RecordStop(const Request& r) {
  if (!recording_) return Fail(r, error_code::kConflict, "no recording is running");
  if (!recording_->stopping) {
    recording_->stopping = true;
    pipeline_->SetRecording(false);
    recorder_->End();
  }
  server_->Reply(r.client.id, r.id, {{"stopped", recording_->id}});
}

// A recording's end written to the store; when that fails too (the disk is still full), it is
// retried every second from Tick until it succeeds, and a restart before then finds the recording
// "interrupted" with its frames (daemon/store.h).
void Daemon::FinishInStore(std::int64_t id, RecordingState state, const std::string& coverage,
                           const std::string& note) {
  if (Status s = store_->FinishRecording(id, state, coverage, note); !s) {
    spdlog::error("recording {}: cannot mark it {} yet: {} (retried every second)", id,
                  ToString(state), s.message());
    pending_finishes_.push_back({id, state, coverage, note});
  }
}

// Runs when the recorder has committed every frame of the recording.
void Daemon::FinishRecording() {
  Recording rec = std::move(*recording_);
  recording_.reset();
  std::vector<RecordedFrame> frames;
  Status s = store_->ReadFrames(rec.id, &frames);
  Json coverage = {{"ok", false}, {"excitations", Json::array()}};
  std::string advice;
  double tracking = 0;
  // The tracker's coordinates in degrees (recording_export.h); frames it was not tracking are
  // NaN, which the check ignores.
  formats::CoordinateTable table;
  int tracked = 0;
  if (s) {
    RecordingInfo info;
    std::vector<bool> rotational;
    s = store_->GetRecording(rec.id, &info);
    if (s) s = RotationalCoordinates(*live_model_, info.coordinate_names, &rotational);
    if (s) s = RecordingToCoordinateTable(info, frames, rotational, true, {}, &table);
    for (std::size_t f = 0; s && f < frames.size(); ++f) {
      if (frames[f].tracker_state == static_cast<int>(ekf::TrackState::kTracking)) ++tracked;
      else table.values.row(static_cast<Eigen::Index>(f)).setConstant(std::numeric_limits<double>::quiet_NaN());
    }
  }
  if (s) {
    tracking = frames.empty() ? 0.0 : static_cast<double>(tracked) / frames.size();
    const sim::Movement* m = protocol_.Find(rec.movement);
    bool ok = m != nullptr && tracked > 0;
    // The tracker runs the subject's current model, before the fit a nominal one: its angles
    // carry that model's zero offsets and gain errors, so the span reached is checked, within
    // 3 deg or 15 % of it, and the range may sit up to 20 deg from the protocol's
    // (sim/protocol.h ExcitationCheckOptions). 40 % of a range fails by far.
    sim::ExcitationCheckOptions check;
    check.tolerance_deg = 3.0;
    check.tolerance_fraction = 0.15;
    check.max_offset_deg = 20.0;
    for (const sim::ExcitationCheck& c : sim::CheckExcitations(*m, table, check)) {
      Json e = {{"coordinate", c.coordinate}, {"min_deg", c.min_deg}, {"max_deg", c.max_deg},
                {"required", c.required}, {"ok", c.ok}};
      e["reached_min_deg"] = std::isfinite(c.reached_min_deg) ? Json(c.reached_min_deg) : Json();
      e["reached_max_deg"] = std::isfinite(c.reached_max_deg) ? Json(c.reached_max_deg) : Json();
      coverage["excitations"].push_back(e);
      if (c.required && !c.ok) {
        ok = false;
        if (advice.empty()) {
          char buf[256];
          const double lo = std::isfinite(c.reached_min_deg) ? c.reached_min_deg : 0;
          const double hi = std::isfinite(c.reached_max_deg) ? c.reached_max_deg : 0;
          std::snprintf(buf, sizeof buf,
                        "repeat %s: %s moved through %.0f deg ([%.0f, %.0f]) of the %.0f deg "
                        "required ([%.0f, %.0f])",
                        rec.movement.c_str(), c.coordinate.c_str(), hi - lo, lo, hi,
                        c.max_deg - c.min_deg, c.min_deg, c.max_deg);
          advice = buf;
        }
      }
    }
    if (tracked == 0) advice = "repeat " + rec.movement + ": the subject was never tracked";
    coverage["ok"] = ok;
  }
  // Cameras missing from the recording's sets (unplugged, lost): noted with the recording.
  Json gaps = Json::array();
  for (const CameraGap& g : recorder_->CameraGaps()) {
    const std::string id = g.camera < pipeline_->num_cameras() ? pipeline_->camera(g.camera).id()
                                                               : std::to_string(g.camera);
    gaps.push_back({{"camera", id}, {"missing_frames", g.missing_frames}, {"outages", g.outages},
                    {"first_frame", g.first_frame}, {"last_frame", g.last_frame}});
    spdlog::warn("recording {}: camera {} missing from {} sets ({} outage(s), frames {}..{})",
                 rec.id, id, g.missing_frames, g.outages, g.first_frame, g.last_frame);
  }
  coverage["camera_gaps"] = gaps;
  // Frames missing from the recording's sequence, and where they went: sets no camera exposed
  // (lost in transport, or a simulated camera the loaded host did not schedule), sets the daemon
  // dropped (a full queue, too late for their set), frames the recorder's queue had no room for.
  // Nothing is missing silently: the reply, the stored coverage and the log say how many.
  std::uint64_t missing = 0;
  for (std::size_t f = 1; f < frames.size(); ++f)
    if (frames[f].frame > frames[f - 1].frame + 1) missing += frames[f].frame - frames[f - 1].frame - 1;
  Json losses;
  {
    const LivePipelineStats st = pipeline_->Stats(/*timings=*/false);
    // A counter below its start value was reset with the pipeline: all it counts is since then.
    auto since = [](std::uint64_t now, std::uint64_t start) { return now >= start ? now - start : now; };
    losses = {{"missing_frames", missing},
              {"sets_not_exposed", since(st.capture.undelivered_frame_sets, rec.sets_not_exposed_at_start)},
              {"sets_dropped", since(st.capture.dropped_frame_sets, rec.sets_dropped_at_start)},
              {"recorder_dropped", since(st.recorder_dropped, rec.recorder_dropped_at_start)}};
  }
  coverage["losses"] = losses;
  if (missing > 0)
    spdlog::warn("recording {}: {} frames missing from its sequence (meanwhile {} sets not exposed "
                 "by any camera, {} dropped by the daemon, {} frames by the recorder's queue)",
                 rec.id, missing, losses["sets_not_exposed"].get<std::uint64_t>(),
                 losses["sets_dropped"].get<std::uint64_t>(),
                 losses["recorder_dropped"].get<std::uint64_t>());
  // The rig's sync failed during the recording (PTP lock lost): its sets may mix instants, so
  // it does not pass (the fit never uses it) and the advice says why.
  coverage["sync_faults"] = rec.sync_faults;
  if (!rec.sync_faults.empty()) {
    coverage["ok"] = false;
    advice = "repeat " + rec.movement + ": " + rec.sync_faults.front();
    spdlog::warn("recording {}: {}", rec.id, rec.sync_faults.front());
  }
  FinishInStore(rec.id, s ? RecordingState::kComplete : RecordingState::kFailed, coverage.dump(),
                s ? "" : s.message());
  const double seconds = frames.empty() ? 0 : frames.back().time_s - frames.front().time_s;
  spdlog::info("recording {} ({}): {} frames, tracking {:.1f} %, coverage {}{}", rec.id,
               rec.movement, frames.size(), 100 * tracking,
               coverage["ok"].get<bool>() ? "ok" : "NOT ok", advice.empty() ? "" : ": " + advice);
  if (!s) return Fail(rec.request, error_code::kFailed, s.message());
  server_->Reply(rec.request.client.id, rec.request.id,
                 {{"recording", rec.id},
                  {"movement", rec.movement},
                  {"frames", frames.size()},
                  {"seconds", seconds},
                  {"tracking_fraction", tracking},
                  {"coverage", coverage},
                  {"camera_gaps", gaps},
                  {"losses", losses},
                  {"sync_faults", rec.sync_faults},
                  {"advice", advice.empty() ? Json() : Json(advice)}});
}

void Daemon::RecordingList(const Request& r) {
  Params p(r.params);
  std::string name;
  if (!p.String("subject", &name, false)) return Fail(r, error_code::kInvalidParams, p.error);
  std::int64_t subject_id = 0;
  if (!name.empty()) {
    SubjectRecord rec;
    if (Status s = store_->FindSubject(name, &rec); !s) return Fail(r, error_code::kNotFound, s.message());
    subject_id = rec.id;
  }
  std::vector<RecordingInfo> list;
  if (Status s = store_->ListRecordings(subject_id, &list); !s) return Fail(r, error_code::kFailed, s.message());
  Json out = Json::array();
  for (const auto& rec : list) {
    bool ok = false;
    try {
      const Json cov = Json::parse(rec.coverage_json.empty() ? "null" : rec.coverage_json);
      ok = cov.is_object() && cov.value("ok", false);
    } catch (...) {
    }
    out.push_back({{"id", rec.id}, {"subject_id", rec.subject_id}, {"movement", rec.movement},
                   {"state", ToString(rec.state)}, {"frames", rec.frame_count}, {"rate_hz", rec.rate_hz},
                   {"coverage_ok", ok}, {"started_at", rec.started_at}});
  }
  server_->Reply(r.client.id, r.id, {{"recordings", out}});
}

// ---------------------------------------------------------------------------------------------
// The fit

void Daemon::FitStart(const Request& r) {
  Params p(r.params);
  // Defaults from the config's [fit]; the request may override each.
  std::int64_t max_iterations = config_.fit_max_iterations, threads = config_.fit_threads;
  std::string groups = config_.fit_groups;
  if (!p.Int("max_iterations", &max_iterations, 1, 10000, false) ||
      !p.Int("threads", &threads, 0, 256, false) || !p.String("groups", &groups, false))
    return Fail(r, error_code::kInvalidParams, p.error);
  solver::FitOptions fo;
  fo.lm.max_iterations = static_cast<int>(max_iterations);
  fo.num_threads = static_cast<int>(threads);
  fo.coarse.enabled = config_.fit_coarse_frames > 0;
  if (config_.fit_coarse_frames > 0) fo.coarse.coarse_frames = config_.fit_coarse_frames;
  if (!groups.empty()) {
    if (Status s = fo.SetGroups(groups); !s) return Fail(r, error_code::kInvalidParams, "params.groups: " + s.message());
  }
  if (!subject_) return Fail(r, error_code::kConflict, "select a subject first (subject.select)");
  if (job_) return Fail(r, error_code::kConflict, "a " + job_->kind + " job is running");
  if (recording_) return Fail(r, error_code::kConflict, "a recording is running");
  // Per movement, the latest recording that passed its coverage check.
  std::vector<RecordingInfo> list;
  if (Status s = store_->ListRecordings(subject_->id, &list); !s) return Fail(r, error_code::kFailed, s.message());
  std::map<std::string, RecordingInfo> chosen;
  for (const auto& rec : list) {
    if (rec.state != RecordingState::kComplete) continue;
    bool ok = false;
    try {
      const Json cov = Json::parse(rec.coverage_json.empty() ? "null" : rec.coverage_json);
      ok = cov.is_object() && cov.value("ok", false);
    } catch (...) {
    }
    if (!ok) continue;
    auto it = chosen.find(rec.movement);
    if (it == chosen.end() || it->second.id < rec.id) chosen[rec.movement] = rec;
  }
  if (chosen.empty())
    return Fail(r, error_code::kConflict,
                "subject '" + subject_->name + "' has no recording that passed its coverage check");
  // The fit starts from the live model: the one the tracker ran when it recorded the poses that
  // start the fit (not the latest stored version, which may be a cancelled fit's).
  std::shared_ptr<Model> model;
  int version = 0;
  if (Status s = LoadSubjectModel(*subject_, live_model_version_, &model, &version); !s)
    return Fail(r, error_code::kFailed, s.message());

  job_ = std::make_unique<Job>();
  job_->kind = "fit";
  job_->request = r;
  job_->cancel = std::make_shared<std::atomic<bool>>(false);
  auto cancel = job_->cancel;
  const std::string state_dir = config_.state_dir;
  const SubjectRecord subject = *subject_;
  std::shared_ptr<const Model> truth;
  if (sim_rig_) truth = std::make_shared<Model>(sim_rig_->scene().truth());
  spdlog::info("fit of subject '{}' (model v{}) over {} recordings", subject.name, version, chosen.size());
  job_->thread = std::thread([this, r, cancel, fo, chosen, model, version, state_dir, subject, truth]() mutable {
    // The fit is batch work beside a live rig: it yields the CPU to the pipeline. Linux keeps
    // the nice value per thread and a thread's new threads inherit it, so the solver's workers
    // run at nice kFitNice too (raising one's own nice needs no privilege; the unit lets
    // setpriority through its filter, and starts mocapd at nice -10). At the default priority a fit on a 2-core capture PC
    // took the pipeline's CPU: bench/soak counted 1.2 % of frame sets dropped during fits.
    if (setpriority(PRIO_PROCESS, static_cast<id_t>(gettid()), kFitNice) != 0)
      spdlog::warn("fit: cannot lower its priority (nice {}): {}", kFitNice, std::strerror(errno));
    const auto t0 = std::chrono::steady_clock::now();
    // What the fit hands to the loop; everything else it made is freed at the end of the block.
    Status s;
    Json reply;
    std::string report_text, model_text;
    {
      // Each worker thread has its own store connection (WAL: readers beside the writer).
      std::unique_ptr<Store> store;
      StoreOptions so;
      so.mark_interrupted_recordings = false;  // the daemon's first store did it at start-up
      s = Store::Open(state_dir, &store, so);
      std::vector<solver::FitTrial> trials;
      std::vector<std::string> names;
      for (const auto& [movement, rec] : chosen) {
        if (!s) break;
        std::vector<RecordedFrame> frames;
        RecordingInfo info;
        s = store->GetRecording(rec.id, &info);
        if (s) s = store->ReadFrames(rec.id, &frames);
        if (!s) break;
        solver::FitTrial t;
        s = RecordingToMarkerTrial(info, frames, {}, &t.markers);
        if (!s) break;
        t.markers.name = movement;
        t.initial_coordinates.setConstant(static_cast<Eigen::Index>(frames.size()),
                                          model->num_coordinates(),
                                          std::numeric_limits<double>::quiet_NaN());
        bool any = false;
        for (std::size_t f = 0; f < frames.size(); ++f) {
          if (frames[f].tracker_state != static_cast<int>(ekf::TrackState::kTracking) ||
              frames[f].coordinates.size() != model->num_coordinates())
            continue;
          t.initial_coordinates.row(static_cast<Eigen::Index>(f)) = frames[f].coordinates.transpose();
          any = true;
        }
        if (!any) t.initial_coordinates.resize(0, 0);  // per-frame IK instead
        names.push_back(movement + " (recording " + std::to_string(rec.id) + ")");
        trials.push_back(std::move(t));
      }
      solver::FitResult result;
      int iterations_seen = 0;
      fo.lm.callbacks.push_back([this, r, cancel, &iterations_seen, &fo, t0](const solver::IterationSummary& it) {
        ++iterations_seen;
        const double elapsed = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        const double fraction = std::min(0.99, static_cast<double>(iterations_seen) / std::max(1, fo.lm.max_iterations / 4));
        char msg[200];
        std::snprintf(msg, sizeof msg, "%siteration %d: cost %.6e", it.coarse ? "coarse " : "", it.iteration, it.cost);
        Json ev = {{"phase", it.coarse ? "coarse" : "solve"}, {"iteration", it.iteration}, {"cost", it.cost},
                   {"fraction", fraction}, {"eta_s", elapsed / fraction * (1 - fraction)}, {"message", msg}};
        PostToLoop([this, r, ev, fraction] {
          if (job_) job_->fraction = fraction;
          Progress(r, "fit", ev);
        });
        return !cancel->load();
      });
      fo.lm.cancel = cancel.get();
      if (s) s = solver::FitModel(*model, trials, fo, &result);
      if (s) {
        // Each joint against its functional estimate per recording (solver/fit_trust.h): the
        // stored report and its page say whether to trust the model, as `mocap fit`'s do (no
        // better minimum adopted: FitTrustOptions::adopt_better_minimum is off, as there).
        Json report = solver::FitReportJson(result.report, trials, names);
        solver::FitTrust trust;
        solver::FitTrustOptions trust_options;
        trust_options.fit = fo;  // its profile checks solve the fit's problem again (fit_trust.h)
        trust_options.fit.lm.callbacks.clear();  // no progress events from those solves
        if (Status t = solver::CheckFitTrust(*model, result, trials, trust_options, &trust); t)
          report["joint_checks"] = solver::FitTrustJson(trust);
        else
          spdlog::warn("fit: joint checks: {}", t.message());
        report_text = report.dump();
        model_text = ModelToJsonString(result.model);
        ModelComparison diff;
        if (CompareModels(*model, result.model, &diff)) reply["diff"] = Json::parse(ComparisonToJsonString(diff));
        if (truth) {
          ModelComparison against;
          if (CompareModels(*truth, result.model, &against)) {
            reply["truth"] = {{"joint_centre_error_mm_max", against.joint_centre_error_mm.max},
                              {"joint_centre_error_mm_rms", against.joint_centre_error_mm.rms},
                              {"axis_error_deg_max", against.axis_error_deg.max},
                              {"segment_length_error_pct_max", against.segment_length_error_pct.max},
                              {"marker_error_mm_rms", against.marker_error_mm.rms}};
          }
          ModelComparison nominal;
          if (CompareModels(*truth, *model, &nominal))
            reply["truth_before"] = {{"joint_centre_error_mm_max", nominal.joint_centre_error_mm.max},
                                     {"joint_centre_error_mm_rms", nominal.joint_centre_error_mm.rms}};
        }
        reply["report"] = report;
      }
    }  // the fit's trials, workspaces and result freed
    // The fit's working set (~230 MB in use at its peak, on this thread's malloc arena) is free
    // now, but glibc gives the kernel back only free memory at the top of a heap: the rest stays
    // resident, 64 MB more after most fits. Measured (BENCHMARKS.md "Soak", a fit a minute):
    // without this, RSS 365 -> 771 MB after 15 fits while the heap in use came back to 332-333
    // MB after each (no leak: the allocator's, not ours); with it, 366-406 MB. malloc_trim(0)
    // gives back the free pages of every arena (51-64 MB here, in 22-200 ms on the loaded
    // machine): on the fit's thread at its low priority, not on the loop, and once per fit, so
    // the arena locks it takes in turn cost the pipeline's threads nothing per frame.
    // MALLOC_ARENA_MAX=2 instead did not stop the steps (364 -> 497 MB after 6 fits).
    const auto trim_t0 = std::chrono::steady_clock::now();
    const std::uint64_t released = ReleaseFreeHeapMemory();
    spdlog::info("fit: {:.0f} MB of freed memory given back to the system in {:.0f} ms", released / 1048576.0,
                 std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - trim_t0).count());
    PostToLoop([this, r, s, reply, report_text, model_text, subject, version]() mutable {
      if (job_ && job_->thread.joinable()) job_->thread.join();
      job_.reset();
      if (!s) {
        spdlog::error("fit of '{}' failed: {}", subject.name, s.message());
        return Fail(r, error_code::kFailed, "fit failed: " + s.message());
      }
      std::int64_t report_id = 0;
      ModelRecord mr;
      Status st = store_->AddFitReport(subject.id, report_text,
                                       "mocapd " + options_.version + " fit.start", &report_id);
      if (st)
        st = store_->AddModel(subject.id, model_text,
                              "mocapd " + options_.version + " fit of v" + std::to_string(version),
                              report_id, &mr);
      if (!st) return Fail(r, error_code::kFailed, st.message());
      reply["model_version"] = mr.version;
      reply["report_id"] = report_id;
      spdlog::info("fit of '{}': model v{} stored ({}, marker RMS {:.2f} mm)", subject.name,
                   mr.version, reply["report"].value("termination", ""),
                   reply["report"].value("marker_rms_mm", 0.0));
      const std::string termination = reply["report"].value("termination", "");
      if (termination == "USER_CANCELLED")
        return Fail(r, error_code::kCancelled,
                    "fit cancelled; the best result so far is stored as model v" +
                        std::to_string(mr.version));
      server_->Reply(r.client.id, r.id, reply);
    });
  });
}

void Daemon::FitCancel(const Request& r) {
  if (!job_ || job_->kind != "fit") return Fail(r, error_code::kConflict, "no fit is running");
  job_->cancel->store(true);
  spdlog::info("fit cancel requested by uid {}", r.client.uid);
  server_->Reply(r.client.id, r.id, {{"cancelling", true}});
}

void Daemon::ModelList(const Request& r) {
  Params p(r.params);
  std::string name;
  if (!p.String("subject", &name, false)) return Fail(r, error_code::kInvalidParams, p.error);
  SubjectRecord subject;
  if (!name.empty()) {
    if (Status s = store_->FindSubject(name, &subject); !s) return Fail(r, error_code::kNotFound, s.message());
  } else if (subject_) {
    subject = *subject_;
  } else {
    return Fail(r, error_code::kConflict, "no subject selected; name one (params.subject)");
  }
  std::vector<ModelRecord> models;
  if (Status s = store_->ListModels(subject.id, &models); !s) return Fail(r, error_code::kFailed, s.message());
  Json out = Json::array();
  for (const auto& m : models)
    out.push_back({{"version", m.version},
                   {"produced_by", m.produced_by},
                   {"created_at", m.created_at},
                   {"fit_report", m.fit_report_id ? Json(*m.fit_report_id) : Json()},
                   {"live", subject_ && subject_->id == subject.id && m.version == live_model_version_}});
  server_->Reply(r.client.id, r.id, {{"subject", subject.name}, {"models", out}});
}

void Daemon::ModelApply(const Request& r) {
  Params p(r.params);
  std::int64_t version = 0;
  if (!p.Int("version", &version, 1, INT64_MAX, false)) return Fail(r, error_code::kInvalidParams, p.error);
  if (!subject_) return Fail(r, error_code::kConflict, "select a subject first (subject.select)");
  std::shared_ptr<Model> model;
  int got = 0;
  ekf::ModelOrigin origin = ekf::ModelOrigin::kGeneric;
  if (Status s = LoadSubjectModel(*subject_, static_cast<int>(version), &model, &got, &origin); !s)
    return Fail(r, error_code::kNotFound, s.message());
  if (applying_) return Fail(r, error_code::kConflict, "another model.apply is in progress");
  // The tracking thread takes the model between two frames, and answers on the loop: a frame can
  // be long (the tracker's start), and the loop keeps answering meanwhile.
  const std::int64_t subject_id = subject_->id;
  std::shared_ptr<const Model> shared = model;
  if (Status s = pipeline_->RequestSwap(
          model, got, origin,
          [this, r, shared, got, subject_id](Status result, std::uint64_t from) {
            PostToLoop([this, r, shared, got, subject_id, result, from] {
              ModelApplied(r, shared, got, subject_id, result, from);
            });
          });
      !s)
    return Fail(r, error_code::kFailed, "model v" + std::to_string(got) + ": " + s.message());
  applying_ = r;
  apply_deadline_ns_ = drivers::MonotonicNs() + kApplyTimeoutNs;
}

void Daemon::ModelApplied(const Request& r, std::shared_ptr<const Model> model, int version,
                          std::int64_t subject_id, Status result, std::uint64_t from_frame) {
  applying_.reset();
  if (!result)
    return Fail(r, error_code::kFailed, "model v" + std::to_string(version) + ": " + result.message());
  // A select after the tracking thread took the model: the select's tracker replaces it.
  if (!subject_ || subject_->id != subject_id)
    return Fail(r, error_code::kConflict, "the subject changed while its model was applied");
  live_model_ = std::move(model);
  live_model_version_ = version;
  RememberLive();
  spdlog::info("model v{} of '{}' live from frame {}", version, subject_->name, from_frame);
  server_->Reply(r.client.id, r.id, {{"version", version}, {"from_frame", from_frame}});
}

// ---------------------------------------------------------------------------------------------
// Export

void Daemon::Export(const Request& r) {
  Params p(r.params);
  std::string kind, format, path, subject_name;
  std::int64_t id = 0;
  bool inline_ = false;
  if (!p.String("kind", &kind, true) || !p.String("format", &format, true) ||
      !p.Int("id", &id, 1, INT64_MAX, true) || !p.String("path", &path, false) ||
      !p.Bool("inline", &inline_) || !p.String("subject", &subject_name, false))
    return Fail(r, error_code::kInvalidParams, p.error);
  if (inline_ == !path.empty())
    return Fail(r, error_code::kInvalidParams, "give one of params.path or params.inline: true");
  if (!path.empty() && path[0] != '/')
    return Fail(r, error_code::kInvalidParams, "params.path: an absolute path, got '" + path + "'");
  // The format names the staging file: only the formats some kind exports (each kind checks its
  // own below).
  static const std::set<std::string> kFormats = {"c3d", "trc", "mot", "json", "osim", "html"};
  if (!kFormats.count(format))
    return Fail(r, error_code::kInvalidParams,
                "params.format: one of c3d, trc, mot, json, osim, html, got '" + format + "'");
  // A path is checked (and opened, not truncated) before any work: a path outside the allowed
  // directories is refused at once (daemon/export_path.h). The export is written to a staging
  // file in the state directory and copied into the path only once it succeeded.
  ExportFile out;
  if (!inline_) {
    if (Status open = OpenExportFile(path, config_.AllowedExportDirs(), config_.state_dir, &out); !open) {
      spdlog::warn("export refused for uid {}: {}", r.client.uid, open.message());
      return Fail(r, out.forbidden ? error_code::kForbidden : error_code::kFailed, open.message());
    }
  }
  struct CloseOnReturn {
    int fd;
    ~CloseOnReturn() {
      if (fd >= 0) close(fd);
    }
  } close_out{out.fd};
  const std::string target =
      config_.state_dir + "/.export-" + std::to_string(r.client.id) + "." + format;
  Status s;
  if (kind == "recording") {
    RecordingInfo info;
    std::vector<RecordedFrame> frames;
    s = store_->GetRecording(id, &info);
    if (!s) return Fail(r, error_code::kNotFound, s.message());
    s = store_->ReadFrames(id, &frames);
    std::shared_ptr<Model> model;
    int got = 0;
    SubjectRecord subject;
    if (s) s = store_->GetSubject(info.subject_id, &subject);
    if (s) s = LoadSubjectModel(subject, static_cast<int>(info.model_version), &model, &got);
    if (s) {
      std::vector<bool> rotational;
      if (s) s = RotationalCoordinates(*model, info.coordinate_names, &rotational);
      if (!s) {
      } else if (format == "c3d") s = ExportRecordingC3d(info, frames, target);
      else if (format == "trc") s = ExportRecordingTrc(info, frames, target);
      else if (format == "mot") s = ExportRecordingMot(info, frames, rotational, target);
      else return Fail(r, error_code::kInvalidParams, "params.format: a recording exports as c3d, trc or mot");
    }
  } else if (kind == "model" || kind == "report") {
    SubjectRecord subject;
    if (!subject_name.empty()) s = store_->FindSubject(subject_name, &subject);
    else if (subject_) subject = *subject_;
    else return Fail(r, error_code::kConflict, "no subject selected; name one (params.subject)");
    if (!s) return Fail(r, error_code::kNotFound, s.message());
    if (kind == "report") {
      FitReportRecord rep;
      s = store_->GetFitReport(id, &rep);
      if (!s) return Fail(r, error_code::kNotFound, s.message());
      if (format != "json" && format != "html")
        return Fail(r, error_code::kInvalidParams, "params.format: a report exports as json or html");
      std::string text = rep.report_json;
      if (format == "html") {  // the page of `mocap fit --html`: the report, the model it made, the one before
        std::vector<ModelRecord> models;
        s = store_->ListModels(rep.subject_id, &models);
        auto made = std::find_if(models.begin(), models.end(), [&](const ModelRecord& m) { return m.fit_report_id == id; });
        if (s && (made == models.end() || made == models.begin()))
          s = Status::Error("fit report " + std::to_string(id) + ": no stored model version came from it");
        report::FitReportPage page;
        if (s) s = report::FitReportPageFromJson(rep.report_json, std::prev(made)->model_json, made->model_json, &page);
        for (const Json& t : s ? page.report["per_trial"] : Json::array()) {  // "movement (recording N)"
          const std::string file = t.value("file", "");
          RecordingInfo info;
          const std::size_t at = file.rfind("(recording ");
          if (at != std::string::npos && store_->GetRecording(std::atoll(file.c_str() + at + 11), &info) &&
              !info.coverage_json.empty())
            (void)report::AppendCoverageRows(info.movement, info.coverage_json, &page.coverage);
        }
        page.model_file = subject.model_source;
        page.software_version = "mocapd " + options_.version;
        page.date = rep.created_at;
        if (s) s = report::WriteFitReportHtml(page, &text);
      }
      if (s) s = formats::detail::WriteWholeFile(target, text);
    } else {
      ModelRecord rec;
      s = store_->GetModel(subject.id, static_cast<int>(id), &rec);
      if (!s) return Fail(r, error_code::kNotFound, s.message());
      if (format == "json") {
        s = formats::detail::WriteWholeFile(target, rec.model_json);
      } else if (format == "osim") {
        if (subject.osim_text.empty())
          return Fail(r, error_code::kUnavailable,
                      "subject '" + subject.name + "' has no .osim model; export as json");
        formats::OsimImport import;
        Model fitted;
        s = formats::ImportOsimText(subject.osim_text, subject.model_source, &import);
        if (s) s = ParseModelJson(rec.model_json, "model", &fitted);
        if (s) s = formats::ExportOsim(fitted, import, target);
      } else {
        return Fail(r, error_code::kInvalidParams, "params.format: a model exports as json or osim");
      }
    }
  } else {
    return Fail(r, error_code::kInvalidParams,
                "params.kind: recording, model or report, got '" + kind + "'");
  }
  std::error_code ec;
  if (!s) {
    fs::remove(target, ec);
    return Fail(r, error_code::kFailed, s.message());
  }
  const auto bytes = fs::file_size(target, ec);
  if (!inline_) {
    s = CopyIntoExportFile(target, out.fd, out.path);
    fs::remove(target, ec);
    if (!s) return Fail(r, error_code::kFailed, s.message());
    spdlog::info("exported {} {} as {} to {}", kind, id, format, out.path);
    return server_->Reply(r.client.id, r.id, {{"path", out.path}, {"bytes", bytes}});
  }
  std::string content;
  s = formats::detail::ReadWholeFile(target, &content);
  fs::remove(target, ec);
  if (!s) return Fail(r, error_code::kFailed, s.message());
  if (content.size() > (4u << 20))
    return Fail(r, error_code::kInvalidParams, "too large to send inline (" +
                                                   std::to_string(content.size()) +
                                                   " bytes); give params.path");
  Json reply = {{"bytes", content.size()}, {"format", format}};
  if (format == "c3d") {
    static const char* kB64 = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    std::string b64;
    b64.reserve((content.size() + 2) / 3 * 4);
    for (std::size_t i = 0; i < content.size(); i += 3) {
      std::uint32_t v = static_cast<std::uint8_t>(content[i]) << 16;
      if (i + 1 < content.size()) v |= static_cast<std::uint8_t>(content[i + 1]) << 8;
      if (i + 2 < content.size()) v |= static_cast<std::uint8_t>(content[i + 2]);
      b64 += kB64[v >> 18 & 63];
      b64 += kB64[v >> 12 & 63];
      b64 += i + 1 < content.size() ? kB64[v >> 6 & 63] : '=';
      b64 += i + 2 < content.size() ? kB64[v & 63] : '=';
    }
    reply["content_base64"] = b64;
  } else {
    reply["content"] = content;
  }
  server_->Reply(r.client.id, r.id, reply);
}

// ---------------------------------------------------------------------------------------------
// Simulated rig: a camera unplugged and plugged back (the hot-plug path of a USB3 Vision camera:
// the device refused while absent, the camera told it left, then that it arrived).

void Daemon::SimCamera(const Request& r) {
  if (!sim_rig_) return Fail(r, error_code::kUnavailable, "sim.camera needs a simulated rig");
  Params p(r.params);
  std::int64_t camera = -1;
  bool present = true;
  std::string ptp_status;
  double ptp_offset_ns = 0;
  if (!p.Int("camera", &camera, 0, config_.simulated_cameras - 1, true) || !p.Bool("present", &present) ||
      !p.String("ptp", &ptp_status, false) || !p.Number("ptp_offset_ns", &ptp_offset_ns, -1e12, 1e12, false))
    return Fail(r, error_code::kInvalidParams, p.error);
  if (p.Has("ptp")) {
    // The state the camera's PtpStatus reads from now on (its fake's PTP features).
    if (config_.sync != "ptp")
      return Fail(r, error_code::kUnavailable, "params.ptp: the simulated rig runs sync = \"" +
                                                   config_.sync + "\", not \"ptp\"");
    if (Status st = sim_rig_->fakes().SetPtpState(static_cast<int>(camera), ptp_status,
                                                  static_cast<std::int64_t>(ptp_offset_ns));
        !st)
      return Fail(r, error_code::kInvalidParams, "params.ptp: " + st.message());
    const std::string id = aravis_cameras_[static_cast<std::size_t>(camera)]->id();
    spdlog::warn("simulated rig: camera {} PTP status {}", id, ptp_status);
    if (!p.Has("present")) return server_->Reply(r.client.id, r.id, {{"camera", id}, {"ptp", ptp_status}});
  }
  if (!p.Has("present")) return Fail(r, error_code::kInvalidParams, "params.present: missing");
  auto* cam = aravis_cameras_[static_cast<std::size_t>(camera)];
  if (!cam) return Fail(r, error_code::kInternal, "camera " + std::to_string(camera) + " is not an Aravis camera");
  sim_rig_->fakes().SetPresent(static_cast<int>(camera), present);
  if (present) cam->NotifyArrived();
  else cam->NotifyRemoved();
  spdlog::warn("simulated rig: camera {} {}", cam->id(), present ? "plugged back" : "unplugged");
  server_->Reply(r.client.id, r.id, {{"camera", cam->id()}, {"present", present}});
}

// ---------------------------------------------------------------------------------------------
// Synchronisation and the rig check

void Daemon::UpdatePtp() {
  if (!ptp_monitor_) return;
  const PtpRigState now = ptp_monitor_->Snapshot();
  if (!now.checked || now.rounds == ptp_.rounds) return;
  const bool was_locked = ptp_.locked;
  ptp_ = now;
  if (was_locked && !now.locked) {
    spdlog::error("PTP lock lost: {}", now.why);
    if (recording_) {
      char at[32];
      std::snprintf(at, sizeof at, "%.2f", SecondsSince(recording_->started_ns));
      recording_->sync_faults.push_back("PTP lock lost " + std::string(at) + " s into the recording: " + now.why);
    }
  } else if (!was_locked && now.locked) {
    spdlog::info("PTP: every camera locked to one clock again");
  }
}

Json Daemon::SyncJson() const {
  Json j = {{"mode", config_.sync}};
  if (config_.simulated_cameras > 0 && config_.sync == "trigger") j["mode"] = "shared-clock";
  if (ptp_monitor_) {
    j["locked"] = ptp_.checked ? Json(ptp_.locked) : Json();
    j["unlocked_cameras"] = ptp_.unlocked_cameras;
    j["why"] = ptp_.locked ? Json() : Json(ptp_.why);
    j["lock_losses"] = ptp_.lock_losses;
  }
  return j;
}

Json Daemon::RigCheckJson() const {
  RigCheckInput in;
  in.sync = SyncJson()["mode"].get<std::string>();
  in.rate_hz = config_.rate_hz;
  in.links = RigLinkLoads(config_);
  if (!pipeline_) return RigCheckReport(in);
  const CapturePipelineStats st = pipeline_->Stats(/*timings=*/false).capture;
  auto at = [](const auto& v, int c, auto fallback) {
    return c < static_cast<int>(v.size()) ? v[static_cast<std::size_t>(c)] : fallback;
  };
  for (int c = 0; c < pipeline_->num_cameras(); ++c) {
    drivers::CameraSource& cam = pipeline_->camera(c);
    const drivers::CameraCounters& k = cam.Counters();
    CameraCheckInput ci;
    ci.id = cam.id();
    for (const LinkLoad& l : in.links)
      for (const std::string& id : l.cameras)
        if (id == ci.id) ci.link = l.link;
    ci.streaming = cam.State() == drivers::CameraState::kStreaming;
    ci.complete = k.complete.load();
    ci.missing_packets = k.missing_packets.load();
    ci.size_mismatches = k.size_mismatches.load();
    ci.other_errors = k.other_errors.load() + k.wrong_format.load();
    ci.underruns = k.underruns.load();
    ci.not_received = k.not_received.load();
    ci.timeouts = k.timeouts.load();
    ci.losses = k.losses.load();
    ci.reopens = k.reopens.load();
    if (c < static_cast<int>(aravis_cameras_.size()) && aravis_cameras_[c])
      ci.has_packet_statistics =
          aravis_cameras_[c]->PacketStatistics(&ci.resent_packets, &ci.missing_stream_packets);
    ci.clock_fitted = at(st.camera_clock_fitted, c, false);
    ci.clock_offset_ms = at(st.camera_clock_offset_ms, c, 0.0);
    ci.clock_drift_ppm = at(st.camera_clock_drift_ppm, c, 0.0);
    ci.clock_residual_us = at(st.camera_clock_residual_us, c, 0.0);
    ci.count_mismatches = at(st.camera_count_mismatches, c, std::uint64_t{0});
    ci.tick_phase = at(st.camera_tick_phase, c, -1.0);
    ci.trigger_master = !config_.trigger_master.empty() && ci.id == config_.trigger_master;
    if (c < static_cast<int>(ptp_.states.size())) {
      ci.ptp = ptp_.states[c];
      ci.ptp_error = ptp_.errors[c];
    }
    in.cameras.push_back(ci);
  }
  in.sets = st.frame_sets;
  in.incomplete_sets = st.incomplete_sets;
  in.dropped_sets = st.dropped_frame_sets;
  in.mismatched_sets = st.mismatched_sets;
  in.ptp_checked = ptp_.checked;
  in.ptp_locked = ptp_.locked;
  in.ptp_why = ptp_.why;
  return RigCheckReport(in);
}

void Daemon::CamerasCheck(const Request& r) {
  UpdatePtp();
  const Json report = RigCheckJson();
  if (!report.value("ok", false))
    spdlog::warn("cameras.check: {}", report["problems"].dump());
  server_->Reply(r.client.id, r.id, report);
}

// ---------------------------------------------------------------------------------------------
// Live stream

void Daemon::Subscribe(const Request& r) {
  static const std::set<std::string> kStreams = {"points", "markers", "pose", "status"};
  Subscriber sub;
  auto it = r.params.find("streams");
  if (it != r.params.end()) {
    if (!it->is_array()) return Fail(r, error_code::kInvalidParams, "params.streams: expected an array of names");
    for (const Json& s : *it) {
      if (!s.is_string() || !kStreams.count(s.get<std::string>()))
        return Fail(r, error_code::kInvalidParams,
                    "params.streams: each one of points, markers, pose, status; got " + s.dump());
      sub.streams.insert(s.get<std::string>());
    }
  } else {
    sub.streams = {"markers"};
  }
  Params p(r.params);
  std::int64_t decimation = 1;
  if (!p.Int("decimation", &decimation, 1, 10000, false)) return Fail(r, error_code::kInvalidParams, p.error);
  sub.decimation = static_cast<int>(decimation);
  subscribers_[r.client.id] = sub;
  server_->Reply(r.client.id, r.id,
                 {{"subscribed", Json(std::vector<std::string>(sub.streams.begin(), sub.streams.end()))},
                  {"decimation", sub.decimation}});
}

void Daemon::Unsubscribe(const Request& r) {
  subscribers_.erase(r.client.id);
  server_->Reply(r.client.id, r.id, {{"unsubscribed", true}});
}

void Daemon::Stream(const LiveFrame& f) {
  if (subscribers_.empty()) return;
  // One serialisation per combination of streams, shared by the subscribers that want it.
  std::map<std::set<std::string>, std::string> lines;
  const double t_sent = drivers::MonotonicNs() * 1e-9;
  // Sending may find a client gone and drop it, which erases it from subscribers_ (OnDisconnect):
  // so the loop runs over a copy of the ids, never over the map it may change.
  std::vector<std::uint64_t> clients;
  clients.reserve(subscribers_.size());
  for (const auto& [client, sub] : subscribers_) clients.push_back(client);
  for (const std::uint64_t client : clients) {
    auto found = subscribers_.find(client);
    if (found == subscribers_.end()) continue;
    const Subscriber& sub = found->second;
    if (f.frame % sub.decimation != 0) continue;
    auto it = lines.find(sub.streams);
    if (it == lines.end()) {
      Json j = {{"event", "frame"}, {"frame", f.frame}, {"t_mid", f.t_mid_s},
                {"t_sent", t_sent}, {"host_first_ns", f.first_host_ns},
                {"host_last_ns", f.last_host_ns}, {"host_points_ns", f.points_ready_ns},
                {"host_tracked_ns", f.tracked_ns}, {"host_sent_ns", drivers::MonotonicNs()}};
      if (sub.streams.count("markers") && live_model_ && f.markers.cols() == live_model_->num_markers()) {
        Json ms = Json::array();
        for (Eigen::Index m = 0; m < f.markers.cols(); ++m) {
          const bool seen = f.markers.col(m).allFinite();
          const Eigen::Vector3d v = seen ? Eigen::Vector3d(f.markers.col(m))
                                         : (m < f.predicted.cols() ? Eigen::Vector3d(f.predicted.col(m))
                                                                   : Eigen::Vector3d::Zero());
          Json mj = {{"name", live_model_->markers()[m].name}, {"x", v.x()}, {"y", v.y()}, {"z", v.z()},
                     {"occluded", !seen}, {"filled", !seen}};
          if (seen && m < static_cast<Eigen::Index>(f.residual_mm.size()) && std::isfinite(f.residual_mm[m]))
            mj["residual_mm"] = f.residual_mm[m];
          ms.push_back(mj);
        }
        j["markers"] = ms;
      }
      if (sub.streams.count("points")) {
        Json ps = Json::array();
        for (const auto& p : f.points) ps.push_back({p.x(), p.y(), p.z()});
        j["points"] = ps;
      }
      if (sub.streams.count("pose")) {
        j["pose"] = {{"tracker", TrackStateName(f.tracker_state)},
                     {"model_version", f.model_version},
                     {"coordinates", std::vector<double>(f.coordinates.data(),
                                                         f.coordinates.data() + f.coordinates.size())}};
      }
      if (sub.streams.count("status")) {
        j["health"] = {{"cameras_present", f.cameras_present}, {"labelled", f.labelled}};
      }
      it = lines.emplace(sub.streams, j.dump(-1, ' ', false, Json::error_handler_t::replace) + "\n").first;
    }
    const bool sent = server_->SendStream(client, it->second);
    found = subscribers_.find(client);
    if (found == subscribers_.end()) continue;
    (sent ? found->second.sent : found->second.dropped) += 1;
  }
}

// ---------------------------------------------------------------------------------------------
// Periodic work

void Daemon::NoteSilentCameras() {
  const std::vector<double> silent = pipeline_->Stats(/*timings=*/false).capture.camera_silent_s;
  silent_noted_.resize(silent.size(), false);
  for (std::size_t c = 0; c < silent.size(); ++c) {
    drivers::CameraSource& cam = pipeline_->camera(static_cast<int>(c));
    const bool now = silent[c] > 0 && cam.State() == drivers::CameraState::kStreaming;
    if (now == silent_noted_[c]) continue;
    silent_noted_[c] = now;
    if (now)
      spdlog::warn("camera {} delivered no frame for {:.2f} s while the others did: its frame sets "
                   "go on without it{}", cam.id(), silent[c], recording_ ? " (a gap in the recording)" : "");
    else if (cam.State() == drivers::CameraState::kStreaming)
      spdlog::info("camera {} delivers frames again", cam.id());
  }
}

void Daemon::Tick() {
  DrainFrames();
  if (applying_ && drivers::MonotonicNs() > apply_deadline_ns_ && pipeline_->WithdrawSwap()) {
    const Request r = *applying_;
    applying_.reset();
    Fail(r, error_code::kFailed, "the tracking stage did not take the model within 2 s (no frames?)");
  }
  if (!pending_finishes_.empty() && ++ticks_since_retry_ >= 10) {
    ticks_since_retry_ = 0;
    std::vector<PendingFinish> retry;
    retry.swap(pending_finishes_);
    for (const PendingFinish& f : retry) {
      if (Status s = store_->FinishRecording(f.id, f.state, f.coverage, f.note); s) {
        spdlog::info("recording {} marked {} (the store accepts writes again)", f.id, ToString(f.state));
      } else {
        pending_finishes_.push_back(f);
      }
    }
  }
  UpdatePtp();
  if (pipeline_) NoteSilentCameras();
  if (options_.notifier && pipeline_) {
    ServiceSnapshot s = PipelineSnapshot(*pipeline_, config_);
    if (ptp_monitor_ && ptp_.checked && !ptp_.locked) s.ptp_unlocked = ptp_.unlocked_cameras;
    if (subject_) s.subject = subject_->name;
    s.model_version = live_model_version_;
    if (recording_) s.recording = recording_->movement;
    s.job = collection_ ? "rig.calibrate" : job_ ? job_->kind : "";
    if (options_.notifier->Tick(s, drivers::MonotonicNs())) {
      const std::string& stage = options_.notifier->stalled();
      if (stage.empty()) spdlog::info("watchdog: every pipeline stage progresses again");
      else spdlog::error("watchdog: the {} stage made no progress within half the watchdog "
                         "interval: pings withheld, systemd will restart mocapd", stage);
    }
  }
  if (collection_) {
    const double t = SecondsSince(collection_->started_ns);
    if (t - collection_->last_progress_s >= 0.5) {
      collection_->last_progress_s = t;
      int frames = 0;
      std::vector<int> per_camera;
      std::vector<double> coverage;
      pipeline_->WandProgress(&frames, &per_camera, &coverage);
      const double fraction = std::min(1.0, t / collection_->seconds);
      Progress(collection_->request, "rig.calibrate",
               {{"phase", "collect"}, {"frames", frames}, {"wand_frames_per_camera", per_camera},
                {"coverage_per_camera", coverage}, {"fraction", fraction},
                {"eta_s", std::max(0.0, collection_->seconds - t)},
                {"message", std::to_string(frames) + " wand frames"}});
    }
    if (t >= collection_->seconds) {
      // Collection ends by itself; the frames wait for rig.calibrate.finish.
      Progress(collection_->request, "rig.calibrate",
               {{"phase", "collected"}, {"fraction", 1.0}, {"message", "wand collection done; rig.calibrate.finish"}});
      collection_->seconds = 1e18;  // no more progress events
    }
  }
  if (recording_) {
    const double t = SecondsSince(recording_->started_ns);
    if (t - recording_->last_progress_s >= 0.5) {
      recording_->last_progress_s = t;
      const double fraction = std::min(1.0, t / recording_->duration_s);
      Progress(recording_->request, "record",
               {{"phase", "record"}, {"frames", recorder_->frames()}, {"seconds", t},
                {"fraction", fraction}, {"eta_s", std::max(0.0, recording_->duration_s - t)},
                {"message", recording_->movement + ": " + std::to_string(recorder_->frames()) + " frames"}});
    }
    if (t >= recording_->duration_s && !recording_->stopping) {
      recording_->stopping = true;
      pipeline_->SetRecording(false);
      recorder_->End();
    }
  }
}

}  // namespace mocap::daemon
