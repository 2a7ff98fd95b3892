// The recorder: frames of the running recording from the live pipeline to SQLite, in chunks of at
// most `chunk_ms` per transaction, each fsynced before it returns, so a crash or a power cut loses
// at most that much plus one commit (daemon/store.h, "Power cuts").
//
// It runs on its own thread with its own store connection (SQLite in WAL mode lets it write while
// the loop's connection reads), so neither a slow disk nor a big commit ever holds the event loop
// or the tracking stage; the pipeline hands frames over through a bounded queue of several
// seconds (daemon/live_pipeline.h), and a full queue is counted, never waited for.
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

// A LiveFrame as stored.
RecordedFrame ToRecordedFrame(const LiveFrame& frame);

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
           std::unique_ptr<Store> checkpointer, int chunk_ms = 100, double checkpoint_s = 5.0);
  ~Recorder();

  void Start();
  void Stop();

  // Frames go to recording `id` from now on (the caller then turns the pipeline's recording on).
  // `done` is called once: after End(), or at the first failure to commit.
  void Begin(std::int64_t id, DoneFn done);
  // The caller has turned the pipeline's recording off: commit what is queued, then `done`.
  void End();
  std::int64_t frames() const { return frames_.load(); }
  // The cameras missing from the current (or the last finished) recording's sets; kept until the
  // next Begin, so the loop reads them once `done` has been called.
  std::vector<CameraGap> CameraGaps() const;

 private:
  void Loop();
  Status Commit();

  LivePipeline* pipeline_;
  std::unique_ptr<Store> store_;
  std::unique_ptr<Store> checkpointer_;
  int chunk_ms_;
  double checkpoint_s_;
  std::thread thread_, checkpoint_thread_;
  std::mutex stop_mutex_;
  std::condition_variable stop_cv_;
  std::atomic<bool> running_{false};

  mutable std::mutex mutex_;
  std::int64_t recording_ = 0;  // 0: none
  bool ending_ = false;
  DoneFn done_;
  Status error_;
  std::vector<RecordedFrame> chunk_;
  std::vector<CameraGap> gaps_;     // per camera of the rig
  std::vector<char> in_gap_;
  std::atomic<std::int64_t> frames_{0};
};

}  // namespace mocap::daemon
