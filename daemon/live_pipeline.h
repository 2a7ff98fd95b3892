// The live pipeline of mocapd: the capture pipeline (daemon/capture_pipeline.h: acquisition,
// detection, sync + triangulation) plus a tracking stage (ekf/tracker.h), publishing each frame's
// result to the daemon's event loop and, while a recording is on, to the recorder.
//
//   CapturePipeline --point frames--> tracking thread --LiveFrame--> loop queue (drops, counted)
//                                                      \--LiveFrame--> recorder queue (never for a
//                                                                       client; full = counted loss)
//                                                      \--DetectionSet--> wand collector (rig
//                                                                       calibration, subsampled)
//
// It knows nothing of clients. Everything the loop changes while frames flow goes in "between two
// frames": the triangulation (a new rig calibration) is one shared_ptr the sync thread loads at
// each set; the tracker's model (model.apply) and the subject (subject.select) are requests the
// tracking thread takes before its next frame and answers with the frame they took effect at.
// So no lock is held across a frame and no frame is lost to a swap.
//
// Why a recorder queue separate from the loop's: the loop may be busy (a client's 1 MB request,
// a burst of replies) and is allowed to lose frames for the live stream; a recording is not. The
// recorder (daemon/recorder.h) drains its own queue and commits each frame within 100 ms.
#pragma once
#include <atomic>
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include <Eigen/Core>

#include "daemon/bounded_queue.h"
#include "daemon/capture_pipeline.h"
#include "daemon/detection_health.h"
#include "ekf/tracker.h"
#include "model/model.h"
#include "model/status.h"
#include "reconstruction/camera_model.h"
#include "reconstruction/triangulation.h"

namespace mocap::daemon {

// One frame set's result, as the loop, the stream and the recorder see it.
struct LiveFrame {
  std::uint64_t frame = 0;            // the rig's frame-set sequence
  double t_mid_s = 0;                 // mid-exposure time (device clock, seconds)
  std::uint64_t first_host_ns = 0;    // CLOCK_MONOTONIC: first image of the set handed over
  std::uint64_t last_host_ns = 0;     // ... last image of the set handed over
  std::uint64_t points_ready_ns = 0;  // triangulation done
  std::uint64_t tracked_ns = 0;       // tracker done (the frame is published)
  int cameras_present = 0;
  std::uint64_t present_mask = 0;     // bit c: camera c's image is in the set
  int num_cameras = 0;                // of the rig
  std::vector<Eigen::Vector3d> points;  // unlabelled 3D points (metres)
  // The tracker's view (empty when no subject is selected).
  int tracker_state = -1;            // -1 no tracker, else ekf::TrackState
  int labelled = 0;
  Eigen::Matrix3Xd markers;          // per model marker: its point, NaN where not labelled
  Eigen::Matrix3Xd predicted;        // per model marker: where the model put it (fills gaps)
  std::vector<float> residual_mm;    // per model marker: |point - prediction|, NaN if occluded
  Eigen::VectorXd coordinates;       // z
  int model_version = 0;             // of the tracker's model at this frame
};

struct LivePipelineOptions {
  CapturePipelineOptions capture;
  ekf::TrackerOptions tracker;
  int loop_queue_capacity = 64;       // frames waiting for the event loop (320 ms at 200 Hz)
  int recorder_queue_capacity = 2000; // 10 s at 200 Hz: the recorder commits within 100 ms
  int wand_subsample = 4;             // keep every n-th set while collecting wand frames
  int max_wand_frames = 4000;
  double exposure_us = 500;           // t_mid = set time + exposure / 2
  DetectionHealthOptions health;      // bad data at the triangulation stage
  bool IsValid(std::string* error) const;
};

struct LivePipelineStats {
  CapturePipelineStats capture;
  std::uint64_t frames_tracked = 0;      // frames through the tracking stage
  std::uint64_t frames_tracking = 0;     // ... in state kTracking
  std::uint64_t loop_dropped = 0;        // the loop's queue was full
  std::uint64_t recorder_dropped = 0;    // the recorder's queue was full (a recording lost frames)
  // Frames passed on untracked because the tracker was searching for the subject (not tracking)
  // and newer frames already waited: each search takes tens of ms, a frame period is 5 ms, and a
  // search on every frame while the subject cannot be found (out of view, a wrong model) let the
  // point queue overflow and the capture drop frames -- from a recording too. Searching on the
  // newest frame only costs nothing: a search starts from one frame's points, and the frames
  // between carry no labels either way. The frames are published and recorded as they are.
  std::uint64_t searches_skipped = 0;
  QueueDepth loop_queue, recorder_queue;
  double track_ms_p50 = 0, track_ms_p99 = 0;
  // The slowest frame through the tracking stage since the pipeline started: the tracker's start
  // (its search for the subject among unlabelled points, tens of ms once) is the usual one. The
  // capture pipeline's point queue (point_queue_capacity, 1.28 s at 200 Hz) holds the frames that
  // arrive meanwhile, and the stage, at ~0.1 ms a frame, drains them within a frame period or two:
  // queues.points.max in the status shows how many waited.
  double track_ms_max = 0;
  int tracker_state = -1;
  int labelled = 0;
  int markers = 0;
  int model_version = 0;
};

class LivePipeline {
 public:
  // `wake` is called (from the tracking thread) after a frame is queued for the loop: the loop
  // writes an eventfd there. It must not block.
  LivePipeline(std::vector<std::unique_ptr<drivers::CameraSource>> cameras,
               LivePipelineOptions options, std::function<void()> wake);
  ~LivePipeline();
  LivePipeline(const LivePipeline&) = delete;
  LivePipeline& operator=(const LivePipeline&) = delete;

  Status Start();
  void Stop();

  // The loop's side.
  bool PopFrame(LiveFrame* out) { return loop_queue_.Pop(out, std::chrono::milliseconds(0)); }
  // The recorder's side (waits up to timeout_ms).
  bool PopRecorded(LiveFrame* out, int timeout_ms) {
    return recorder_queue_.Pop(out, std::chrono::milliseconds(timeout_ms));
  }

  // Triangulation with these cameras from the next set on (empty: no triangulation, the rig is
  // uncalibrated). Errors: a camera count that is not the rig's, an invalid camera.
  Status SetCalibration(const std::vector<reconstruction::CameraModel>& cameras);
  bool calibrated() const;

  // A new tracker on `model` from the next frame (subject.select): it initialises itself from the
  // static pose. nullptr: no tracking. `origin`: a fit's model is the subject's size already
  // (ekf::ModelOrigin).
  void SetSubjectModel(std::shared_ptr<const Model> model, int version,
                       ekf::ModelOrigin origin = ekf::ModelOrigin::kGeneric);
  // The tracker keeps its track and takes `model` between two frames (model.apply). Right after
  // SetSubjectModel (its tracker not started yet), the new tracker starts on `model` instead.
  // Does not block: `done` is called once, from the tracking thread when it has taken the model
  // (with the first frame it applies to) or failed (another model's coordinates or markers, no
  // tracker), or with an error when the request is replaced (SetSubjectModel, another swap) or
  // the pipeline stops. The tracking thread takes requests between frames, and a frame can be
  // long (the tracker's start: ~0.1 s, seconds under a sanitizer): the daemon's loop must not
  // wait for it. Fails at once (`done` not called) when the pipeline is not running.
  using SwapDone = std::function<void(Status result, std::uint64_t from_frame)>;
  Status RequestSwap(std::shared_ptr<const Model> model, int version, ekf::ModelOrigin origin,
                     SwapDone done);
  // Withdraws the swap RequestSwap asked for if the tracking thread has not taken it yet (true:
  // withdrawn, its `done` will not be called; false: taken or failed already, or none pending).
  bool WithdrawSwap();
  // RequestSwap, waiting up to `timeout` for the tracking thread (tests and tools).
  Status SwapModel(std::shared_ptr<const Model> model, int version, ekf::ModelOrigin origin,
                   std::uint64_t* from_frame, std::chrono::milliseconds timeout = std::chrono::seconds(2));

  // Frames go to the recorder while on.
  void SetRecording(bool on) { recording_.store(on); }
  bool recording() const { return recording_.load(); }

  // Wand collection for rig calibration: sets (every wand_subsample-th) go to a buffer.
  void StartWandCollection();
  // Stops and hands over what was collected.
  std::vector<reconstruction::DetectionSet> StopWandCollection();
  // While collecting: how many, and per camera how many images had >= 3 centroids and the
  // fraction of an 8 x 8 grid of its image the centroids visited.
  void WandProgress(int* frames, std::vector<int>* per_camera, std::vector<double>* coverage) const;

  // timings = false: the counters only (cheap; see CapturePipeline::Stats).
  LivePipelineStats Stats(bool timings = true) const;
  int num_cameras() const { return capture_ ? capture_->num_cameras() : 0; }
  // Bad data per camera (daemon/detection_health.h): non-finite centroids dropped, sets sat out
  // for too many blobs, the reprojection error against the others and whether it is suspect.
  std::vector<CameraHealth> DetectionHealthSnapshot() const { return health_->Snapshot(); }
  drivers::CameraSource& camera(int c) { return capture_->camera(c); }
  // Camera image size, for the coverage grid.
  void SetImageSize(int width, int height) { width_ = width; height_ = height; }

 private:
  void TrackLoop();
  void Publish(LiveFrame&& frame);
  void CollectWand(PointFrame& pf);  // takes pf's detections

  LivePipelineOptions options_;
  std::function<void()> wake_;
  std::unique_ptr<CapturePipeline> capture_;
  BoundedQueue<LiveFrame> loop_queue_;
  BoundedQueue<LiveFrame> recorder_queue_;
  std::atomic<bool> running_{false};
  std::atomic<bool> recording_{false};
  std::thread track_thread_;

  // Triangulation: the sync thread loads it per set.
  // Before the capture pipeline: its sync thread uses it from the first set on.
  std::unique_ptr<DetectionHealth> health_;
  mutable std::mutex triangulator_mutex_;
  std::shared_ptr<reconstruction::Triangulator> triangulator_;

  // Requests to the tracking thread.
  struct ModelRequest {
    bool pending = false;
    bool swap = false;  // true: SwapModel; false: a new tracker
    std::shared_ptr<const Model> model;
    int version = 0;
    ekf::ModelOrigin origin = ekf::ModelOrigin::kGeneric;
    SwapDone done;  // RequestSwap's, also when a select's tracker takes the swap's model
    // A swap carried by a select's request: the select's own model, back if it is withdrawn.
    std::shared_ptr<const Model> selected;
    int selected_version = 0;
    ekf::ModelOrigin selected_origin = ekf::ModelOrigin::kGeneric;
  };
  std::mutex request_mutex_;
  ModelRequest request_;

  // The tracking thread's.
  std::unique_ptr<ekf::Tracker> tracker_;
  int model_version_ = 0;

  // Wand collection.
  mutable std::mutex wand_mutex_;
  bool collecting_ = false;
  std::uint64_t wand_seen_ = 0;
  std::vector<reconstruction::DetectionSet> wand_frames_;
  std::vector<int> wand_per_camera_;
  std::vector<std::vector<std::uint8_t>> wand_cells_;  // per camera, 64 cells
  int width_ = 1280, height_ = 1024;

  mutable std::mutex stats_mutex_;
  LivePipelineStats stats_;
  RecentSamples track_ms_{1 << 14};
};

}  // namespace mocap::daemon
