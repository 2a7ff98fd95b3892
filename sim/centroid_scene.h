// Simulated 2D detections without images: every marker projected through every camera of a rig,
// with Gaussian centroid noise, hidden observations and stray centroids, each camera's centroids
// shuffled, and the truth of which marker each centroid is. For triangulation tests and
// benchmarks, where rendering and detecting images would only add time (the image path is
// sim/renderer.h + reconstruction/detection.h).
#pragma once
#include <Eigen/Core>
#include <cstdint>
#include <functional>
#include <utility>
#include <vector>

#include "reconstruction/camera_model.h"
#include "reconstruction/centroid.h"

namespace mocap::sim {

struct CentroidSceneOptions {
  double noise_px = 0.1;  // per axis; also each centroid's sigma_px (at least 0.01)
  double hide = 0.0;      // fraction of 2D observations hidden
  int strays = 3;         // stray reflections per camera, uniform over the image
  std::uint64_t seed = 1;
  // If set, whether marker m may be seen by camera c at all (before hiding).
  std::function<bool(int camera, int marker)> visible;
};

// One frame set. label[c][i] is the marker of centroid i of camera c, or -1 for a stray;
// observed[m] lists marker m's (camera, centroid) pairs. A marker behind a camera or outside its
// image is not seen by it. The same (options, frame) gives the same scene.
struct CentroidScene {
  reconstruction::DetectionSet set;
  std::vector<std::vector<int>> label;
  std::vector<std::vector<std::pair<int, int>>> observed;
};

CentroidScene MakeCentroidScene(const std::vector<reconstruction::CameraModel>& rig,
                                const std::vector<Eigen::Vector3d>& markers,
                                const CentroidSceneOptions& options, std::uint64_t frame);

}  // namespace mocap::sim
