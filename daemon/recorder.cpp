#include "daemon/recorder.h"

#include <fcntl.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <iterator>
#include <limits>

#include "drivers/frame.h"

namespace mocap::daemon {
namespace {

constexpr double kPollMs = 10;  // how long the recorder waits for a frame before it looks again
constexpr double kMinWaitMs = 20;  // the smallest chunk, in time (4 frames at 200 Hz)

}  // namespace

RecordedFrame ToRecordedFrame(const LiveFrame& f, int num_markers, int num_coordinates) {
  RecordedFrame r;
  r.frame = f.frame;
  r.time_s = f.t_mid_s;
  r.points = f.points;
  if (f.markers.cols() != num_markers || f.coordinates.size() != num_coordinates) {
    constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
    r.markers.setConstant(3, num_markers, kNaN);
    r.marker_flags.assign(static_cast<std::size_t>(num_markers), 1);  // occluded
    r.coordinates.setConstant(num_coordinates, kNaN);
    r.tracker_state = static_cast<std::int8_t>(ekf::TrackState::kInitialising);
    return r;
  }
  r.markers = f.markers;
  r.marker_flags.assign(static_cast<std::size_t>(f.markers.cols()), 0);
  for (Eigen::Index m = 0; m < f.markers.cols(); ++m)
    if (!f.markers.col(m).allFinite()) r.marker_flags[m] = 1;  // occluded
  r.coordinates = f.coordinates;
  r.tracker_state = static_cast<std::int8_t>(f.tracker_state < 0 ? 0 : f.tracker_state);
  return r;
}

Recorder::Recorder(LivePipeline* pipeline, std::unique_ptr<Store> store,
                   std::unique_ptr<Store> checkpointer, int loss_budget_ms, double checkpoint_s)
    : pipeline_(pipeline),
      store_(std::move(store)),
      checkpointer_(std::move(checkpointer)),
      loss_budget_ms_(loss_budget_ms),
      checkpoint_s_(checkpoint_s) {}

Recorder::~Recorder() { Stop(); }

void Recorder::Start() {
  running_ = true;
  thread_ = std::thread([this] { Loop(); });
  sync_thread_ = std::thread([this] { SyncLoop(); });
  if (checkpointer_) {
    checkpoint_thread_ = std::thread([this] {
      NameThisThread("checkpoint");
      std::unique_lock<std::mutex> lock(stop_mutex_);
      while (!stop_cv_.wait_for(lock, std::chrono::duration<double>(checkpoint_s_),
                                [this] { return !running_.load(); })) {
        lock.unlock();
        checkpointer_->Checkpoint();  // a failure is retried at the next one; the WAL holds all
        lock.lock();
      }
    });
  }
}

void Recorder::Stop() {
  {
    std::lock_guard<std::mutex> lock(stop_mutex_);
    if (!running_.exchange(false)) return;
  }
  stop_cv_.notify_all();
  if (thread_.joinable()) thread_.join();
  {
    std::lock_guard<std::mutex> lock(sync_mutex_);  // so the syncer cannot miss the wake-up
  }
  sync_cv_.notify_all();
  if (sync_thread_.joinable()) sync_thread_.join();
  if (checkpoint_thread_.joinable()) checkpoint_thread_.join();
  if (checkpointer_) checkpointer_->Checkpoint();
}

void Recorder::Begin(std::int64_t id, int num_markers, int num_coordinates, DoneFn done) {
  std::lock_guard<std::mutex> lock(mutex_);
  recording_ = id;
  num_markers_ = num_markers;
  num_coordinates_ = num_coordinates;
  done_ = std::move(done);
  ending_ = false;
  error_ = Status::Ok();
  chunk_.clear();
  gaps_.clear();
  in_gap_.clear();
  frames_ = 0;
}

std::vector<CameraGap> Recorder::CameraGaps() const {
  std::lock_guard<std::mutex> lock(mutex_);
  std::vector<CameraGap> out;
  for (const CameraGap& g : gaps_)
    if (g.missing_frames > 0) out.push_back(g);
  return out;
}

void Recorder::End() {
  std::lock_guard<std::mutex> lock(mutex_);
  if (recording_ != 0) ending_ = true;
}

Status Recorder::Commit(std::unique_lock<std::mutex>& lock) {
  oldest_host_ns_ = 0;
  if (chunk_.empty() || recording_ == 0) {
    chunk_.clear();
    return Status::Ok();
  }
  std::vector<RecordedFrame> frames;
  frames.swap(chunk_);
  const std::int64_t id = recording_;  // Begin() only comes after this recording's `done`
  lock.unlock();
  const auto t0 = std::chrono::steady_clock::now();
  Status s = store_->AppendFrames(id, frames);
  const double ms =
      std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  lock.lock();
  commit_ms_[commit_index_++ % 32] = ms;
  slowest_commit_ms_ = *std::max_element(std::begin(commit_ms_), std::end(commit_ms_));
  if (s) frames_ += static_cast<std::int64_t>(frames.size());
  {
    std::lock_guard<std::mutex> sync_lock(sync_mutex_);
    ++commits_;
  }
  sync_cv_.notify_one();
  return s;
}

void Recorder::SyncLoop() {
  NameThisThread("wal-sync");
  // Any descriptor of the WAL file syncs its data (fdatasync works on the file, not the
  // descriptor); SQLite keeps the same file while a connection is open (a checkpoint restarts it
  // from its start, it does not replace it).
  const std::string wal = store_ ? store_->path() + "-wal" : std::string();
  int fd = -1;
  std::unique_lock<std::mutex> lock(sync_mutex_);
  for (;;) {
    sync_cv_.wait(lock, [this] { return commits_ > synced_ || !running_.load(); });
    if (commits_ == synced_) break;  // stopping, nothing left to sync
    const std::uint64_t target = commits_;
    lock.unlock();
    if (fd < 0 && !wal.empty()) fd = open(wal.c_str(), O_RDONLY | O_CLOEXEC);
    const auto t0 = std::chrono::steady_clock::now();
    const bool ok = fd >= 0 && fdatasync(fd) == 0;
    const double ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    if (!ok) ++sync_failures_;  // the next commit tries again; the checkpoints sync too
    sync_ms_[sync_index_++ % 32] = ms;
    slowest_sync_ms_ = *std::max_element(std::begin(sync_ms_), std::end(sync_ms_));
    lock.lock();
    synced_ = target;
  }
  if (fd >= 0) close(fd);
}

void Recorder::Loop() {
  NameThisThread("recorder");
  int idle_polls = 0;
  for (;;) {
    LiveFrame f;
    const bool got = pipeline_->PopRecorded(&f, static_cast<int>(kPollMs));
    std::unique_lock<std::mutex> lock(mutex_);
    if (got) {
      idle_polls = 0;
      if (recording_ != 0 && error_) {
        if (chunk_.empty()) oldest_host_ns_ = f.last_host_ns ? f.last_host_ns : drivers::MonotonicNs();
        chunk_.push_back(ToRecordedFrame(f, num_markers_, num_coordinates_));
        if (static_cast<int>(gaps_.size()) < f.num_cameras) {
          gaps_.resize(f.num_cameras);
          in_gap_.resize(f.num_cameras, 0);
          for (int c = 0; c < f.num_cameras; ++c) gaps_[c].camera = c;
        }
        for (int c = 0; c < f.num_cameras && c < 64; ++c) {
          const bool missing = !(f.present_mask >> c & 1);
          if (missing) {
            CameraGap& g = gaps_[c];
            if (!in_gap_[c]) ++g.outages;
            if (g.missing_frames++ == 0) g.first_frame = f.frame;
            g.last_frame = f.frame;
          }
          in_gap_[c] = missing;
        }
      }
    } else {
      ++idle_polls;
    }
    // Due once the oldest frame waiting has used the budget but a poll, the slowest recent
    // commit and two of the slowest recent syncs (recorder.h); never more often than kMinWaitMs.
    const double oldest_ms =
        oldest_host_ns_ ? (static_cast<double>(drivers::MonotonicNs()) - static_cast<double>(oldest_host_ns_)) / 1e6
                        : 0;
    const double wait_ms = std::max(kMinWaitMs, loss_budget_ms_ - kPollMs - slowest_commit_ms_.load() -
                                                    2 * slowest_sync_ms_.load());
    const bool due = !chunk_.empty() && oldest_ms >= wait_ms;
    // The last frames of a recording: the pipeline's flag is off, so once the queue has been
    // empty for two polls (20 ms) nothing more is coming for it.
    const bool finishing = ending_ && !got && idle_polls >= 2;
    if ((due || finishing) && error_) error_ = Commit(lock);
    if (recording_ != 0 && (finishing || !error_ || !running_)) {
      if (error_) error_ = Commit(lock);
      DoneFn done = std::move(done_);
      const std::int64_t id = recording_;
      const Status status = error_;
      recording_ = 0;
      ending_ = false;
      done_ = nullptr;
      chunk_.clear();
      lock.unlock();
      if (done) done(id, status, frames_.load());
      continue;
    }
    if (!running_ && !got) break;
  }
}

}  // namespace mocap::daemon
