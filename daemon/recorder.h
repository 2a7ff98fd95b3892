// The recorder: frames of the running recording from the live pipeline to SQLite, in chunks, one
// transaction each; a second thread makes each commit durable (fdatasync of the WAL file).
//
// Two bounds, two mechanisms (daemon/store.h, "Crashes and power cuts"):
//   - a crash of the process loses what was not yet committed: a commit (synchronous=NORMAL)
//     hands its pages to the OS, which writes them whatever happens to the process. So the
//     recorder commits each chunk before its oldest frame is 100 ms old (counted from the
//     frame's last image reaching the host, LiveFrame::last_host_ns, so the pipeline's own
//     latency is inside the budget);
//   - a power cut also loses what the OS had not written yet. The syncer thread fdatasyncs the
//     WAL after each commit, so a frame is on the disk once the first fdatasync that starts after
//     its commit returns. The recorder's deadline keeps the slowest recent commit and two of the
//     slowest recent syncs (one in flight, then the frame's own) in reserve:
//         commit when oldest frame's age >= 100 ms - 10 ms poll - commit_max - 2 * sync_max
//     (maxima of the last 32; at least 20 ms, so a disk whose fsync alone eats the budget gets
//     frequent small commits, not one a frame). On a local SSD (fsync ~1 ms) that is one commit
//     every ~85 ms; on the project's loaded virtual disk (fsync p50 8 ms, p99 38 ms,
//     BENCHMARKS.md) every 20 ms, and the power-cut bound is then the disk's, not ours.
// Why not synchronous=FULL (fsync inside each commit): the commit would wait for the disk, and
// frames arriving meanwhile would wait with it -- a 400 ms fsync (seen on this machine under
// load) then costs 400 ms of recording to a plain crash, which the OS would otherwise have kept.
// With the fsync on its own thread, a slow disk delays only power-cut durability.
//
// It runs on its own thread with its own store connection (SQLite in WAL mode lets it write while
// the loop's connection reads), so neither a slow disk nor a big commit ever holds the event loop
// or the tracking stage; the pipeline hands frames over through a bounded queue of several
// seconds (daemon/live_pipeline.h), and a full queue is counted, never waited for. The writes and
// syncs run outside the recorder's lock, so the loop (Begin/End/CameraGaps) never waits for them.
#pragma once
#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <vector>
#include <string>
#include <thread>

#include "daemon/live_pipeline.h"
#include "daemon/store.h"

namespace mocap::daemon {

// A LiveFrame as stored in a recording of `num_markers` markers and `num_coordinates`
// coordinates (its model's). A frame the tracker labelled with another model -- none yet, or the
// previous subject's, in the frames between subject.select and the tracking thread taking the
// new model -- is stored untracked (every marker NaN and occluded, coordinates NaN, state
// initialising) with its points: the store refuses a frame of another shape, and the recording
// would fail on the first frame when it starts right after a subject.select.
RecordedFrame ToRecordedFrame(const LiveFrame& frame, int num_markers, int num_coordinates);

// One camera's absence from a recording's frame sets (unplugged, lost, its images dropped).
struct CameraGap {
  int camera = -1;
  std::int64_t missing_frames = 0;  // sets recorded without it
  int outages = 0;                  // separate runs of such sets
  std::uint64_t first_frame = 0, last_frame = 0;  // the first and last set without it
};

class Recorder {
 public:
  // Called on the recorder's thread when a recording has ended (all its frames committed) or
  // failed (the first error, e.g. the disk is full; the frames before it stay on disk).
  using DoneFn = std::function<void(std::int64_t recording, Status status, std::int64_t frames)>;

  // `store` commits the frames (open it with wal_autocheckpoint_pages = 0); `checkpointer`, a
  // second connection to the same database, checkpoints the WAL every `checkpoint_s` on a thread
  // of its own, so no commit of the recorder waits for a checkpoint's fsync (daemon/store.h).
  Recorder(LivePipeline* pipeline, std::unique_ptr<Store> store,
           std::unique_ptr<Store> checkpointer, int loss_budget_ms = 100,
           double checkpoint_s = 5.0);
  ~Recorder();

  void Start();
  void Stop();

  // Frames go to recording `id` from now on (the caller then turns the pipeline's recording on).
  // `done` is called once: after End(), or at the first failure to commit.
  // Its model has `num_markers` markers and `num_coordinates` coordinates (ToRecordedFrame).
  void Begin(std::int64_t id, int num_markers, int num_coordinates, DoneFn done);
  // The caller has turned the pipeline's recording off: commit what is queued, then `done`.
  void End();
  std::int64_t frames() const { return frames_.load(); }
  // The longest of the last 32 commits and WAL syncs (ms): what the deadline keeps in reserve.
  double slowest_recent_commit_ms() const { return slowest_commit_ms_.load(); }
  double slowest_recent_sync_ms() const { return slowest_sync_ms_.load(); }
  std::uint64_t sync_failures() const { return sync_failures_.load(); }
  // The cameras missing from the current (or the last finished) recording's sets; kept until the
  // next Begin, so the loop reads them once `done` has been called.
  std::vector<CameraGap> CameraGaps() const;

 private:
  void Loop();
  // Commits the chunk (called with `lock` held; released during the write).
  Status Commit(std::unique_lock<std::mutex>& lock);

  LivePipeline* pipeline_;
  std::unique_ptr<Store> store_;
  std::unique_ptr<Store> checkpointer_;
  void SyncLoop();

  int loss_budget_ms_;
  std::uint64_t oldest_host_ns_ = 0;  // the chunk's oldest frame's last image (0: empty chunk)
  // The last 32 durations, rings (commit_ms_ the recorder thread's, sync_ms_ the syncer's).
  double commit_ms_[32] = {};
  int commit_index_ = 0;
  double sync_ms_[32] = {};
  int sync_index_ = 0;
  std::atomic<double> slowest_commit_ms_{0}, slowest_sync_ms_{0};
  std::atomic<std::uint64_t> sync_failures_{0};
  // The syncer: commits_ counts commits made, synced_ those made durable.
  std::thread sync_thread_;
  std::mutex sync_mutex_;
  std::condition_variable sync_cv_;
  std::uint64_t commits_ = 0, synced_ = 0;
  double checkpoint_s_;
  std::thread thread_, checkpoint_thread_;
  std::mutex stop_mutex_;
  std::condition_variable stop_cv_;
  std::atomic<bool> running_{false};

  mutable std::mutex mutex_;
  std::int64_t recording_ = 0;  // 0: none
  int num_markers_ = 0, num_coordinates_ = 0;  // of the recording's model (ToRecordedFrame)
  bool ending_ = false;
  DoneFn done_;
  Status error_;
  std::vector<RecordedFrame> chunk_;
  std::vector<CameraGap> gaps_;     // per camera of the rig
  std::vector<char> in_gap_;
  std::atomic<std::int64_t> frames_{0};
};

}  // namespace mocap::daemon
