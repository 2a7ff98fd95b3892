// mocapd: the daemon's state and its methods (daemon/PROTOCOL.md), on one sd-event loop.
//
// One process, two kinds of thread, one owner per piece of state (shared/DESIGN.md, "The daemon"):
//   - the event loop (this class, one thread) owns the control socket and its clients, the state
//     machine (selected subject, live model, running recording, running job) and the store
//     connection for metadata. It never waits on the pipeline or on a client: frames come through
//     the live pipeline's bounded queue, woken by an eventfd; work done elsewhere comes back as a
//     task posted to the loop (PostToLoop), also through an eventfd.
//   - the pipeline (daemon/live_pipeline.h), which knows nothing of clients, and its recorder
//     thread (frames to SQLite, each committed and fsynced within 100 ms, daemon/recorder.h);
//   - workers for long jobs (rig calibration, the fit) that report progress through the loop and
//     can be cancelled; a job's result becomes state only when the loop applies it.
//
// Start in dependency order -- config, store, cameras, pipeline, socket, ready -- and stop in
// reverse: socket first (no new requests), the running recording committed and closed, jobs
// cancelled and joined, the pipeline stopped (cameras closed), the store closed.
//
// A simulated rig is a config ([rig] simulated = N): Aravis fake cameras drawn by the renderer
// from a virtual subject (sim/live_scene.h) who does what the operator asks (record.start makes
// it perform the movement; rig.calibrate.start makes the virtual operator wave the wand).
#pragma once
#include <systemd/sd-event.h>

#include <atomic>
#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include <nlohmann/json.hpp>

#include "daemon/config.h"
#include "daemon/control_server.h"
#include "daemon/live_pipeline.h"
#include "daemon/process_memory.h"
#include "daemon/rig_setup.h"
#include "daemon/ptp_monitor.h"
#include "daemon/service_notify.h"
#include "daemon/store.h"
#include "model/model.h"
#include "model/status.h"
#include "sim/protocol.h"

namespace mocap::sim {
class LiveRig;
}

namespace mocap::daemon {

class Recorder;

struct DaemonOptions {
  std::string config_path;  // for config.reload / SIGHUP
  int listen_fd = -1;       // socket activation: a listening socket from systemd
  // mocapd --export-dir: overrides [storage] export_dirs, at start and at every reload.
  std::vector<std::string> export_dirs;
  std::string version = "0.1.0";
  // systemd's notifications (daemon/service_notify.h), fed by the loop's tick; null: none.
  ServiceNotifier* notifier = nullptr;
  // CapturePipelineOptions::test_hold (test builds only, daemon/mocapd_main.cpp).
  std::function<void(const char* stage)> test_hold;
  // Simulated rig: cameras unplugged when mocapd starts (test builds only: a degraded start).
  std::vector<int> test_absent_cameras;
};

class Daemon {
 public:
  Daemon(DaemonConfig config, DaemonOptions options);
  ~Daemon();
  Daemon(const Daemon&) = delete;
  Daemon& operator=(const Daemon&) = delete;

  // Starts everything in dependency order; on failure, what was started is stopped again and
  // StartExitCode() is the exit code that names the cause (daemon/startup_checks.h).
  Status Start();
  int StartExitCode() const { return start_exit_code_; }
  // Runs the loop until SIGTERM/SIGINT or `shutdown`; returns the exit code.
  int Run();
  // One turn of the loop instead, waiting up to `timeout_us` for an event: for a caller that
  // is also a client on the same thread (fuzz/fuzz_daemon.cpp drives the dispatch so, without a
  // process or a thread between its bytes and the daemon). False once the loop has exited
  // (`shutdown`, SIGTERM) or failed; then Stop(), as after Run().
  bool RunOnce(std::uint64_t timeout_us);
  // Stops everything in reverse order (idempotent).
  void Stop();

 private:
  using Json = nlohmann::json;
  struct Request {
    ClientInfo client;
    Json id;
    std::string method;
    Json params;
  };
  // A method's outcome when it answers at once.
  struct MethodError {
    std::string code, message;
  };

  // Loop plumbing.
  static int OnSignal(sd_event_source* s, const struct signalfd_siginfo* si, void* self);
  static int OnSignalPipe(sd_event_source* s, int fd, uint32_t revents, void* self);
  static int OnWake(sd_event_source* s, int fd, uint32_t revents, void* self);
  static int OnTimer(sd_event_source* s, uint64_t usec, void* self);
  void PostToLoop(std::function<void()> task);
  void DrainFrames();
  void Tick();  // every 100 ms: progress events, recording end, status
  // Logs a camera falling silent (no frame while the others deliver) and its end, once each.
  void NoteSilentCameras();

  // Requests.
  void OnRequest(const ClientInfo& client, const Json& id, const std::string& method,
                 const Json& params);
  void OnDisconnect(std::uint64_t client);
  void Fail(const Request& r, const std::string& code, const std::string& message);
  void Progress(const Request& r, const std::string& job, Json fields);

  Json Status_() const;
  Json CamerasJson() const;
  Json RigCheckJson() const;  // cameras.check (daemon/rig_check.h)
  Json SyncJson() const;      // status.sync
  // sync = "ptp": takes the monitor's newest reading (Tick): logs a change of lock and marks a
  // running recording that lost it.
  void UpdatePtp();
  void ConfigReload(const Request& r);
  void RigCalibrateStart(const Request& r);
  void RigCalibrateFinish(const Request& r);
  void RigCalibrateCancel(const Request& r);
  void RigCalibrateApply(const Request& r);
  void CalibrationList(const Request& r);
  void SubjectCreate(const Request& r);
  void SubjectSelect(const Request& r);
  void SubjectList(const Request& r);
  void ProtocolShow(const Request& r);
  void RecordStart(const Request& r);
  void RecordStop(const Request& r);
  void RecordingList(const Request& r);
  void FitStart(const Request& r);
  void FitCancel(const Request& r);
  void ModelList(const Request& r);
  void ModelApply(const Request& r);
  // The tracking thread's answer to model.apply, on the loop.
  void ModelApplied(const Request& r, std::shared_ptr<const Model> model, int version,
                    std::int64_t subject_id, Status result, std::uint64_t from_frame);
  void Export(const Request& r);
  void Subscribe(const Request& r);
  void Unsubscribe(const Request& r);
  void SimCamera(const Request& r);
  void CamerasCheck(const Request& r);

  void FinishRecording();
  void FinishInStore(std::int64_t id, RecordingState state, const std::string& coverage,
                     const std::string& note);
  struct PendingFinish {
    std::int64_t id;
    RecordingState state;
    std::string coverage, note;
  };
  std::vector<PendingFinish> pending_finishes_;
  int ticks_since_retry_ = 0;
  Status SelectSubject(const SubjectRecord& subject, int version);  // version 0: the latest
  void RememberLive();
  void ResumeLive();
  // *origin (optional): fitted to the subject when a fit produced that version (the tracker then
  // does not scale it at every start; ekf::ModelOrigin).
  Status LoadSubjectModel(const SubjectRecord& subject, int version, std::shared_ptr<Model>* out,
                          int* got_version, ekf::ModelOrigin* origin = nullptr);
  void Stream(const LiveFrame& frame);

  DaemonConfig config_;
  DaemonOptions options_;
  sim::Protocol protocol_;

  sd_event* loop_ = nullptr;
  int wake_fd_ = -1;
  sd_event_source* wake_source_ = nullptr;
  sd_event_source* timer_source_ = nullptr;
  std::vector<sd_event_source*> signal_sources_;
  std::mutex tasks_mutex_;
  std::deque<std::function<void()>> tasks_;

  std::unique_ptr<Store> store_;
  std::unique_ptr<sim::LiveRig> sim_rig_;  // simulated rigs only
  std::vector<reconstruction::CameraModel> start_cameras_;  // intrinsics (poses unknown)
  std::unique_ptr<LivePipeline> pipeline_;
  // The pipeline's cameras that are Aravis cameras (packet statistics, hot-plug), by index;
  // nullptr where not.
  std::vector<drivers::AravisCamera*> aravis_cameras_;
  // sync = "ptp": each camera's state (AravisPtpSource, every camera in the rig's order; the
  // simulated rig's fakes have PTP features, set by sim.camera) and the monitor reading them
  // while the rig streams.
  std::vector<std::unique_ptr<PtpStatusSource>> ptp_sources_;
  std::unique_ptr<PtpMonitor> ptp_monitor_;
  PtpRigState ptp_;  // the loop's copy of the newest reading
  std::unique_ptr<Recorder> recorder_;
  std::unique_ptr<ControlServer> server_;
  std::uint64_t started_ns_ = 0;
  bool stopped_ = false;
  int exit_code_ = 0;
  int start_exit_code_ = 69;  // kExitUnavailable
  std::vector<MissingCamera> missing_at_start_;  // cameras that did not open at start

  // State (the loop's).
  std::optional<SubjectRecord> subject_;
  std::shared_ptr<const Model> live_model_;
  int live_model_version_ = 0;
  // A model.apply the tracking thread has not answered yet (one at a time), and when Tick gives
  // up on it (no frames: the tracking thread takes a model between two frames).
  std::optional<Request> applying_;
  std::uint64_t apply_deadline_ns_ = 0;
  int calibration_version_ = 0;  // live calibration (0: none)
  std::uint64_t last_frame_ = 0;
  LiveFrame last_live_;           // the newest frame (status)
  mutable LivePipelineStats stats_cache_;  // with timings, refreshed at most once a second
  mutable std::uint64_t stats_cached_ns_ = 0;
  // Per camera: its silence (capture_pipeline.h camera_silence_s) was logged and not yet its end.
  std::vector<bool> silent_noted_;
  mutable ProcessMemory memory_cache_;  // refreshed at most once a second (mallinfo2 locks arenas)
  mutable std::uint64_t memory_cached_ns_ = 0;

  // The running recording.
  struct Recording {
    std::int64_t id = 0;
    Request request;
    std::string movement;
    double duration_s = 0;
    std::uint64_t started_ns = 0;
    double last_progress_s = -1;
    bool stopping = false;
    std::optional<Request> stopper;
    // What went wrong with the rig's synchronisation while it ran (PTP lock lost: the cameras
    // and when), noted with the recording; it then fails its coverage check.
    std::vector<std::string> sync_faults;
    // The pipeline's loss counters when it began: the recording's own losses are the change.
    std::uint64_t sets_dropped_at_start = 0, sets_not_exposed_at_start = 0,
                  recorder_dropped_at_start = 0;
  };
  std::optional<Recording> recording_;

  // Rig calibration collection.
  struct Collection {
    Request request;
    double seconds = 20;
    std::uint64_t started_ns = 0;
    double last_progress_s = -1;
  };
  std::optional<Collection> collection_;

  // The running job (one at a time: rig calibration's bundle adjustment or the fit).
  struct Job {
    std::string kind;  // "rig.calibrate" or "fit"
    Request request;
    std::shared_ptr<std::atomic<bool>> cancel;
    double fraction = 0;
    std::thread thread;
  };
  std::unique_ptr<Job> job_;

  // Subscribers: client -> streams and decimation.
  struct Subscriber {
    std::set<std::string> streams;
    int decimation = 1;
    std::uint64_t sent = 0, dropped = 0;
  };
  std::map<std::uint64_t, Subscriber> subscribers_;
};

}  // namespace mocap::daemon
