// What detection hands to sync and triangulation: 2D marker centroids per camera, grouped into
// sets of the same instant across the rig.
#pragma once
#include <Eigen/Core>
#include <cstdint>
#include <vector>

namespace mocap::reconstruction {

// One detected blob in one image, in pixels (centre of the top-left pixel = (0, 0)).
struct Centroid {
  Eigen::Vector2d pixel = Eigen::Vector2d::Zero();
  double sigma_px = 0.1;   // standard deviation of the centroid along each image axis
  float area_px = 0;       // bright pixels in the blob
  float roundness = 1;     // minor / major axis of the blob's second moments, in (0, 1]
  float peak = 0;          // highest pixel value, in the image's units
};

// The detections of one camera image.
struct CameraDetections {
  int camera = -1;
  std::uint64_t sequence = 0;  // the frame's unwrapped id (drivers/frame.h)
  std::uint64_t device_timestamp_ns = 0;
  std::uint64_t host_timestamp_ns = 0;
  std::uint64_t received_ns = 0;  // drivers::Frame::received_ns (0: host_timestamp_ns)
  // The camera's stream generation: +1 each time it came back after a loss (its clock and ids
  // restarted). The capture pipeline re-synchronises the camera (FrameSync::ResyncCamera) when
  // it changes.
  std::uint32_t stream_epoch = 0;
  std::vector<Centroid> centroids;
};

// The detections of every camera of the rig at one instant. `cameras` has one entry per camera
// of the rig; present[c] is false where camera c's image was missing (dropped, incomplete, lost):
// an incomplete set is still triangulated from the cameras it has.
struct DetectionSet {
  std::uint64_t sequence = 0;
  std::uint64_t timestamp_ns = 0;     // device time of the set (median of the cameras')
  std::uint64_t first_arrival_ns = 0; // host time the first image of the set arrived
  std::vector<CameraDetections> cameras;
  std::vector<bool> present;
  int present_count() const {
    int n = 0;
    for (bool p : present) n += p;
    return n;
  }
};

}  // namespace mocap::reconstruction
