#include "daemon/recorder.h"

#include <chrono>

namespace mocap::daemon {

RecordedFrame ToRecordedFrame(const LiveFrame& f) {
  RecordedFrame r;
  r.frame = f.frame;
  r.time_s = f.t_mid_s;
  r.points = f.points;
  r.markers = f.markers;
  r.marker_flags.assign(static_cast<std::size_t>(f.markers.cols()), 0);
  for (Eigen::Index m = 0; m < f.markers.cols(); ++m)
    if (!f.markers.col(m).allFinite()) r.marker_flags[m] = 1;  // occluded
  r.coordinates = f.coordinates;
  r.tracker_state = static_cast<std::int8_t>(f.tracker_state < 0 ? 0 : f.tracker_state);
  return r;
}

Recorder::Recorder(LivePipeline* pipeline, std::unique_ptr<Store> store,
                   std::unique_ptr<Store> checkpointer, int chunk_ms, double checkpoint_s)
    : pipeline_(pipeline),
      store_(std::move(store)),
      checkpointer_(std::move(checkpointer)),
      chunk_ms_(chunk_ms),
      checkpoint_s_(checkpoint_s) {}

Recorder::~Recorder() { Stop(); }

void Recorder::Start() {
  running_ = true;
  thread_ = std::thread([this] { Loop(); });
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
  if (checkpoint_thread_.joinable()) checkpoint_thread_.join();
  if (checkpointer_) checkpointer_->Checkpoint();
}

void Recorder::Begin(std::int64_t id, DoneFn done) {
  std::lock_guard<std::mutex> lock(mutex_);
  recording_ = id;
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

Status Recorder::Commit() {
  if (chunk_.empty() || recording_ == 0) return Status::Ok();
  Status s = store_->AppendFrames(recording_, chunk_);
  if (s) frames_ += static_cast<std::int64_t>(chunk_.size());
  chunk_.clear();
  return s;
}

void Recorder::Loop() {
  NameThisThread("recorder");
  auto last_commit = std::chrono::steady_clock::now();
  int idle_polls = 0;
  for (;;) {
    LiveFrame f;
    const bool got = pipeline_->PopRecorded(&f, 10);
    std::unique_lock<std::mutex> lock(mutex_);
    if (got) {
      idle_polls = 0;
      if (recording_ != 0 && error_) {
        chunk_.push_back(ToRecordedFrame(f));
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
    const auto now = std::chrono::steady_clock::now();
    const bool due =
        std::chrono::duration<double, std::milli>(now - last_commit).count() >= chunk_ms_;
    // The last frames of a recording: the pipeline's flag is off, so once the queue has been
    // empty for two polls (20 ms) nothing more is coming for it.
    const bool finishing = ending_ && !got && idle_polls >= 2;
    if ((due || finishing) && error_) {
      error_ = Commit();
      last_commit = now;
    }
    if (recording_ != 0 && (finishing || !error_ || !running_)) {
      if (error_) error_ = Commit();
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
