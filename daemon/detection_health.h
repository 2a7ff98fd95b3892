// What a broken or miscalibrated camera does to the live pipeline, caught at the triangulation
// stage (daemon/live_pipeline.h) and counted per camera for `status` / `cameras`:
//
//   - non-finite centroids (NaN or infinite pixels from a broken camera or driver) are dropped
//     before triangulation: one NaN would otherwise poison every epipolar match it takes part in
//     and, through the least squares, the point it ends in;
//   - a camera with more than `max_centroids_per_camera` blobs in one image (sunlight, a
//     reflective watch: ten times the markers) is left out of that set, which is triangulated from
//     the other cameras. Matching is quadratic in the blobs of a camera pair, so this is what
//     bounds the time a set takes; the set itself is never lost;
//   - a camera whose calibration is wrong (moved, knocked: 5 cm is tens of pixels) is found by
//     its reprojection error: every `sample_every`-th set, each triangulated point seen by at
//     least 3 cameras is projected into every present camera and compared with that camera's
//     centroid (the one triangulation used, else the nearest within `match_radius_px`). The other
//     cameras pin the point, so the error piles up in the camera that is off. A camera whose
//     median error over its last `window` samples exceeds `suspect_px` (a calibrated rig: a few
//     tenths of a pixel) is flagged, and status names it.
//
// Threads: Sanitize and Observe run on the sync thread (one set at a time) and allocate nothing
// once warm; Snapshot is called from the loop and takes a short lock.
#pragma once
#include <cstdint>
#include <mutex>
#include <string>
#include <vector>

#include "reconstruction/camera_model.h"
#include "reconstruction/centroid.h"
#include "reconstruction/triangulation.h"

namespace mocap::daemon {

struct DetectionHealthOptions {
  // Beyond this many blobs in one image the camera sits the set out. 256: five times the default
  // model's 43 markers plus room for a second subject; ten times the usual count is far above.
  int max_centroids_per_camera = 256;
  int sample_every = 10;           // sets between two reprojection samples (cost: ~1/10 of a set)
  int window = 500;                // samples per camera the median is taken over
  int min_samples = 50;            // before this many, no verdict
  double match_radius_px = 40;     // a point's nearest centroid farther than this: no sample
  double suspect_px = 2.0;         // median reprojection error that flags a camera
  bool IsValid(std::string* error) const;
};

struct CameraHealth {
  std::uint64_t nonfinite_centroids = 0;  // centroids dropped for a NaN or infinite pixel
  std::uint64_t overfull_sets = 0;        // sets the camera sat out for too many blobs
  double reprojection_px = 0;             // median over the window (0 before min_samples)
  int reprojection_samples = 0;           // in the window
  bool calibration_suspect = false;       // reprojection_px > suspect_px
};

class DetectionHealth {
 public:
  explicit DetectionHealth(int num_cameras, DetectionHealthOptions options = {});

  // Returns `set` itself when it is clean, else `scratch` filled with a copy without the
  // non-finite centroids and with the overfull cameras marked absent (counted). `scratch` keeps
  // its capacity from set to set.
  const reconstruction::DetectionSet& Sanitize(const reconstruction::DetectionSet& set,
                                               reconstruction::DetectionSet* scratch);
  // After triangulating `set` (the sanitized one) into `points` with `cameras`: samples the
  // per-camera reprojection errors every sample_every-th call.
  void Observe(const reconstruction::DetectionSet& set,
               const std::vector<reconstruction::TriangulatedPoint>& points,
               const std::vector<reconstruction::CameraModel>& cameras);
  // A new calibration: the reprojection windows start again (the counters stay).
  void ResetReprojection();

  std::vector<CameraHealth> Snapshot() const;

 private:
  struct PerCamera {
    CameraHealth counts;
    std::vector<float> ring;  // the last `window` reprojection errors
    int next = 0;
    int filled = 0;
    bool changed = false;  // since the median was last taken (a flood of status requests
                           // must not sort the window each time)
    double median = 0;
  };
  DetectionHealthOptions options_;
  mutable std::mutex mutex_;
  mutable std::vector<PerCamera> cameras_;  // Snapshot caches the medians
  std::uint64_t observed_ = 0;
  mutable std::vector<float> sort_scratch_;
};

}  // namespace mocap::daemon
