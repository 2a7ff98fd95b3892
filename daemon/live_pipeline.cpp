#include "daemon/live_pipeline.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <limits>
#include <string>

#include "drivers/frame.h"

namespace mocap::daemon {

using drivers::MonotonicNs;

bool LivePipelineOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& m) {
    if (error) *error = m;
    return false;
  };
  if (!capture.IsValid(error)) return false;
  if (!tracker.IsValid(error)) return false;
  if (loop_queue_capacity < 1) return fail("loop_queue_capacity must be >= 1");
  if (recorder_queue_capacity < 1) return fail("recorder_queue_capacity must be >= 1");
  if (wand_subsample < 1) return fail("wand_subsample must be >= 1");
  if (max_wand_frames < 1) return fail("max_wand_frames must be >= 1");
  if (!(exposure_us >= 0)) return fail("exposure_us must be >= 0");
  if (std::string e; !health.IsValid(&e)) return fail("health: " + e);
  return true;
}

LivePipeline::LivePipeline(std::vector<std::unique_ptr<drivers::CameraSource>> cameras,
                           LivePipelineOptions options, std::function<void()> wake)
    : options_(std::move(options)),
      wake_(std::move(wake)),
      loop_queue_(static_cast<std::size_t>(std::max(1, options_.loop_queue_capacity))),
      recorder_queue_(static_cast<std::size_t>(std::max(1, options_.recorder_queue_capacity))) {
  health_ = std::make_unique<DetectionHealth>(static_cast<int>(cameras.size()), options_.health);
  auto workspace = std::make_shared<reconstruction::TriangulationWorkspace>();
  auto buffer = std::make_shared<std::vector<reconstruction::TriangulatedPoint>>();
  auto scratch = std::make_shared<reconstruction::DetectionSet>();
  // Runs on the sync thread, once per set: the calibration in force is whatever pointer it
  // loads here, so a new calibration takes effect between two sets.
  TriangulateFn triangulate = [this, workspace, buffer, scratch](
                                  const reconstruction::DetectionSet& set, PointFrame* out) {
    std::shared_ptr<reconstruction::Triangulator> t;
    {
      std::lock_guard<std::mutex> lock(triangulator_mutex_);
      t = triangulator_;
    }
    out->points.clear();
    out->residual_px.clear();
    out->camera_count.clear();
    if (!t) return Status::Ok();  // uncalibrated: 2D detections only
    // Without the non-finite centroids and the cameras flooded with blobs (counted).
    const reconstruction::DetectionSet& clean = health_->Sanitize(set, scratch.get());
    MOCAP_RETURN_IF_ERROR(t->Triangulate(clean, workspace.get(), buffer.get()));
    health_->Observe(clean, *buffer, t->rig());
    for (const auto& p : *buffer) {
      out->points.push_back(p.position);
      out->residual_px.push_back(static_cast<float>(p.residual_px));
      out->camera_count.push_back(static_cast<std::uint8_t>(p.camera_count));
    }
    return Status::Ok();
  };
  const int n = static_cast<int>(cameras.size());
  capture_ = std::make_unique<CapturePipeline>(std::move(cameras), std::move(triangulate),
                                               options_.capture);
  wand_per_camera_.assign(n, 0);
  wand_cells_.assign(n, std::vector<std::uint8_t>(64, 0));
}

LivePipeline::~LivePipeline() { Stop(); }

Status LivePipeline::Start() {
  std::string error;
  if (!options_.IsValid(&error)) return Status::Error("live pipeline: " + error);
  MOCAP_RETURN_IF_ERROR(capture_->Start());
  running_ = true;
  track_thread_ = std::thread([this] { TrackLoop(); });
  return Status::Ok();
}

void LivePipeline::Stop() {
  if (!running_.exchange(false)) return;
  capture_->Stop();
  if (track_thread_.joinable()) track_thread_.join();
  loop_queue_.Close();
  recorder_queue_.Close();
  SwapDone orphan;
  {
    std::lock_guard<std::mutex> lock(request_mutex_);
    orphan = std::move(request_.done);
    request_ = {};
  }
  if (orphan) orphan(Status::Error("the pipeline stopped before the model was applied"), 0);
}

Status LivePipeline::SetCalibration(const std::vector<reconstruction::CameraModel>& cameras) {
  if (cameras.empty()) {
    std::lock_guard<std::mutex> lock(triangulator_mutex_);
    triangulator_.reset();
    return Status::Ok();
  }
  if (static_cast<int>(cameras.size()) != num_cameras()) {
    return Status::Error("calibration has " + std::to_string(cameras.size()) +
                         " cameras, the rig " + std::to_string(num_cameras()));
  }
  std::unique_ptr<reconstruction::Triangulator> t;
  MOCAP_RETURN_IF_ERROR(reconstruction::Triangulator::Create(cameras, {}, &t));
  std::shared_ptr<reconstruction::Triangulator> shared(std::move(t));
  std::lock_guard<std::mutex> lock(triangulator_mutex_);
  triangulator_ = std::move(shared);
  health_->ResetReprojection();  // the errors of the old calibration say nothing of the new
  return Status::Ok();
}

bool LivePipeline::calibrated() const {
  std::lock_guard<std::mutex> lock(triangulator_mutex_);
  return triangulator_ != nullptr;
}

void LivePipeline::SetSubjectModel(std::shared_ptr<const Model> model, int version,
                                   ekf::ModelOrigin origin) {
  SwapDone replaced;
  {
    std::lock_guard<std::mutex> lock(request_mutex_);
    replaced = std::move(request_.done);
    request_ = {};
    request_.pending = true;
    request_.swap = false;
    request_.model = std::move(model);
    request_.version = version;
    request_.origin = origin;
  }
  if (replaced) replaced(Status::Error("another subject was selected before the model was applied"), 0);
}

Status LivePipeline::RequestSwap(std::shared_ptr<const Model> model, int version,
                                 ekf::ModelOrigin origin, SwapDone done) {
  SwapDone replaced;
  {
    std::lock_guard<std::mutex> lock(request_mutex_);
    if (!running_) return Status::Error("the pipeline is not running");
    if (request_.pending && !request_.swap && request_.model) {
      // subject.select's new tracker has not started yet (it starts at the next frame): the
      // tracker starts on this model instead. Replacing the request would lose the select, and
      // the swap would find no tracker ("no subject is being tracked") right after a select.
      if (!request_.selected) {
        request_.selected = request_.model;
        request_.selected_version = request_.version;
        request_.selected_origin = request_.origin;
      }
    } else {
      replaced = std::move(request_.done);
      request_ = {};
      request_.pending = true;
      request_.swap = true;
    }
    if (!replaced) replaced = std::move(request_.done);
    request_.model = std::move(model);
    request_.version = version;
    request_.origin = origin;
    request_.done = std::move(done);
  }
  if (replaced) replaced(Status::Error("another model was applied before this one"), 0);
  return Status::Ok();
}

bool LivePipeline::WithdrawSwap() {
  std::lock_guard<std::mutex> lock(request_mutex_);
  if (!request_.pending || !request_.done) return false;
  if (request_.swap) {
    request_ = {};
  } else {  // the select stays, on its own model
    request_.model = std::move(request_.selected);
    request_.version = request_.selected_version;
    request_.origin = request_.selected_origin;
    request_.selected = nullptr;
    request_.done = nullptr;
  }
  return true;
}

Status LivePipeline::SwapModel(std::shared_ptr<const Model> model, int version,
                               ekf::ModelOrigin origin, std::uint64_t* from_frame,
                               std::chrono::milliseconds timeout) {
  struct Outcome {
    std::mutex mutex;
    std::condition_variable cv;
    bool done = false;
    Status result;
    std::uint64_t from_frame = 0;
  };
  auto outcome = std::make_shared<Outcome>();
  MOCAP_RETURN_IF_ERROR(RequestSwap(std::move(model), version, origin,
                                    [outcome](Status result, std::uint64_t from) {
                                      std::lock_guard<std::mutex> lock(outcome->mutex);
                                      outcome->done = true;
                                      outcome->result = std::move(result);
                                      outcome->from_frame = from;
                                      outcome->cv.notify_all();
                                    }));
  std::unique_lock<std::mutex> lock(outcome->mutex);
  if (!outcome->cv.wait_for(lock, timeout, [&] { return outcome->done; })) {
    lock.unlock();
    if (WithdrawSwap())
      return Status::Error("the tracking stage did not take the model within " +
                           std::to_string(timeout.count()) + " ms (no frames?)");
    lock.lock();  // taken meanwhile: its answer is on its way
    outcome->cv.wait(lock, [&] { return outcome->done; });
  }
  if (from_frame) *from_frame = outcome->from_frame;
  return outcome->result;
}

void LivePipeline::StartWandCollection() {
  capture_->KeepDetections(true);  // the 2D detections are handed out only while collecting
  std::lock_guard<std::mutex> lock(wand_mutex_);
  collecting_ = true;
  wand_seen_ = 0;
  wand_frames_.clear();
  std::fill(wand_per_camera_.begin(), wand_per_camera_.end(), 0);
  for (auto& cells : wand_cells_) std::fill(cells.begin(), cells.end(), 0);
}

std::vector<reconstruction::DetectionSet> LivePipeline::StopWandCollection() {
  capture_->KeepDetections(false);
  std::lock_guard<std::mutex> lock(wand_mutex_);
  collecting_ = false;
  return std::move(wand_frames_);
}

void LivePipeline::WandProgress(int* frames, std::vector<int>* per_camera,
                                std::vector<double>* coverage) const {
  std::lock_guard<std::mutex> lock(wand_mutex_);
  *frames = static_cast<int>(wand_frames_.size());
  *per_camera = wand_per_camera_;
  coverage->clear();
  for (const auto& cells : wand_cells_) {
    int n = 0;
    for (std::uint8_t c : cells) n += c;
    coverage->push_back(n / 64.0);
  }
}

void LivePipeline::CollectWand(PointFrame& pf) {
  std::lock_guard<std::mutex> lock(wand_mutex_);
  if (!collecting_) return;
  if (wand_seen_++ % options_.wand_subsample != 0) return;
  if (static_cast<int>(wand_frames_.size()) >= options_.max_wand_frames) return;
  reconstruction::DetectionSet set;
  set.sequence = pf.sequence;
  set.timestamp_ns = pf.timestamp_ns;
  set.cameras = std::move(pf.detections);  // not needed downstream of the collector
  set.present.assign(set.cameras.size(), false);
  int seen = 0;
  for (std::size_t c = 0; c < set.cameras.size(); ++c) {
    set.present[c] = c < 64 && (pf.present_mask >> c & 1);
    if (!set.present[c]) continue;
    const auto& d = set.cameras[c];
    if (d.centroids.size() >= 3) {
      ++seen;
      if (c < wand_per_camera_.size()) ++wand_per_camera_[c];
      for (const auto& ctr : d.centroids) {
        const int gx = std::clamp(static_cast<int>(ctr.pixel.x() * 8 / std::max(1, width_)), 0, 7);
        const int gy = std::clamp(static_cast<int>(ctr.pixel.y() * 8 / std::max(1, height_)), 0, 7);
        if (c < wand_cells_.size()) wand_cells_[c][gy * 8 + gx] = 1;
      }
    }
  }
  if (seen >= 2) wand_frames_.push_back(std::move(set));
}

void LivePipeline::TrackLoop() {
  NameThisThread("track");
  Eigen::Matrix3Xd points;
  for (;;) {
    PointFrame pf;
    if (!capture_->PopPoints(&pf, 50)) {
      if (!running_) break;
      continue;
    }
    if (options_.capture.test_hold) options_.capture.test_hold("track");
    // Requests from the loop, between two frames.
    {
      SwapDone done;
      Status result;
      {
        std::lock_guard<std::mutex> lock(request_mutex_);
        if (request_.pending) {
          if (!request_.swap) {
            tracker_.reset();
            if (request_.model) {
              ekf::TrackerOptions to = options_.tracker;
              tracker_ = std::make_unique<ekf::Tracker>(request_.model, to, request_.origin);
            }
            model_version_ = request_.version;
          } else if (!tracker_) {
            result = Status::Error("no subject is being tracked");
          } else {
            result = tracker_->SwapModel(request_.model, request_.origin);
            if (result) model_version_ = request_.version;
          }
          done = std::move(request_.done);
          request_ = {};
        }
      }
      if (done) done(std::move(result), pf.sequence);
    }
    CollectWand(pf);

    LiveFrame lf;
    lf.frame = pf.sequence;
    lf.t_mid_s = pf.timestamp_ns * 1e-9 + options_.exposure_us * 0.5e-6;
    lf.first_host_ns = pf.first_host_ns;
    lf.last_host_ns = pf.last_host_ns;
    lf.points_ready_ns = pf.ready_host_ns;
    lf.cameras_present = pf.cameras_present;
    lf.present_mask = pf.present_mask;
    lf.num_cameras = capture_->num_cameras();
    lf.points = std::move(pf.points);
    lf.model_version = model_version_;
    const auto t0 = std::chrono::steady_clock::now();
    // While the tracker searches and newer frames wait, the search is left to the newest
    // (LivePipelineStats::searches_skipped): this frame goes on untracked.
    const bool skip_search = tracker_ && tracker_->state() != ekf::TrackState::kTracking &&
                             capture_->PointsWaiting() > 0;
    if (tracker_) {
      const int np = static_cast<int>(lf.points.size());
      const ekf::TrackOutput* out = nullptr;
      if (!skip_search) {
        points.resize(3, np);
        for (int i = 0; i < np; ++i) points.col(i) = lf.points[i];
        out = &tracker_->Update(lf.t_mid_s, points);
      }
      const int nm = tracker_->model().num_markers();
      lf.tracker_state = static_cast<int>(out ? out->state : tracker_->state());
      lf.labelled = out ? out->labelled : 0;
      lf.coordinates = out ? out->z : tracker_->output().z;
      lf.markers.setConstant(3, nm, std::numeric_limits<double>::quiet_NaN());
      lf.predicted = tracker_->predicted_markers();
      lf.residual_mm.assign(nm, std::numeric_limits<float>::quiet_NaN());
      for (int m = 0; out && m < nm && m < static_cast<int>(out->point_of_marker.size()); ++m) {
        const int p = out->point_of_marker[m];
        if (p < 0 || p >= np) continue;
        lf.markers.col(m) = points.col(p);
        if (m < lf.predicted.cols())
          lf.residual_mm[m] = static_cast<float>(1000 * (points.col(p) - lf.predicted.col(m)).norm());
      }
    }
    const double track_ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    lf.tracked_ns = MonotonicNs();
    {
      std::lock_guard<std::mutex> lock(stats_mutex_);
      ++stats_.frames_tracked;
      stats_.searches_skipped += skip_search;
      if (lf.tracker_state == static_cast<int>(ekf::TrackState::kTracking)) ++stats_.frames_tracking;
      stats_.tracker_state = lf.tracker_state;
      stats_.labelled = lf.labelled;
      stats_.markers = static_cast<int>(lf.markers.cols());
      stats_.model_version = model_version_;
      track_ms_.Add(track_ms);
      stats_.track_ms_max = std::max(stats_.track_ms_max, track_ms);
    }
    Publish(std::move(lf));
  }
}

void LivePipeline::Publish(LiveFrame&& frame) {
  if (recording_.load()) {
    LiveFrame copy = frame;
    if (!recorder_queue_.TryPush(std::move(copy))) {
      std::lock_guard<std::mutex> lock(stats_mutex_);
      ++stats_.recorder_dropped;
    }
  }
  if (!loop_queue_.TryPush(std::move(frame))) {
    std::lock_guard<std::mutex> lock(stats_mutex_);
    ++stats_.loop_dropped;
    return;
  }
  if (wake_) wake_();
}

LivePipelineStats LivePipeline::Stats(bool timings) const {
  LivePipelineStats s;
  {
    std::lock_guard<std::mutex> lock(stats_mutex_);
    s = stats_;
    if (timings) {
      s.track_ms_p50 = track_ms_.Percentile(50);
      s.track_ms_p99 = track_ms_.Percentile(99);
    }
  }
  s.capture = capture_->Stats(timings);
  s.loop_queue = loop_queue_.Depth();
  s.recorder_queue = recorder_queue_.Depth();
  return s;
}

}  // namespace mocap::daemon
