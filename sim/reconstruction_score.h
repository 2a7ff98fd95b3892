// Scores reconstructed (unlabelled) 3D points against the simulated truth, the way the capture
// targets are stated:
//   recall          fraction of true markers seen by >= 2 cameras that were reconstructed;
//   rms_3d_mm       RMS distance of reconstructed points to the true markers they match;
//   ghost_fraction  reconstructed points that match no true marker / all reconstructed points.
// Matching is one-to-one and greedy by distance (closest pairs first) within a radius: with
// markers centimetres apart and errors of a fraction of a millimetre, greedy equals optimal.
#pragma once
#include <Eigen/Core>
#include <cstdint>
#include <vector>

namespace mocap::sim {

class Renderer;
class Scene;

struct ReconstructionScore {
  std::int64_t true_visible = 0;   // true markers seen by >= 2 cameras
  std::int64_t recovered = 0;      // ... of which a reconstructed point matched
  std::int64_t reconstructed = 0;  // reconstructed points
  std::int64_t ghosts = 0;         // reconstructed points matching no true marker
  double sum_squared_error_m2 = 0; // over every matched point
  std::int64_t matched = 0;
  std::int64_t matched_beyond_1mm = 0;  // matched points more than 1 mm from their marker
  // The Cramer-Rao bound of the matched points: the sum over them of trace((sum over the views
  // of J^T J / sigma^2)^-1), J the projection's Jacobian, sigma the renderer's centroid noise.
  // No unbiased triangulation of the same views does better (ScoreRenderedFrame fills it).
  double sum_bound_variance_m2 = 0;
  std::int64_t bounded = 0;

  double recall() const { return true_visible ? double(recovered) / true_visible : 1.0; }
  double ghost_fraction() const { return reconstructed ? double(ghosts) / reconstructed : 0.0; }
  double rms_mm() const;
  double rms_bound_mm() const;  // 0 when no bound was computed
  void Add(const ReconstructionScore& other);
};

// Adds one frame set. `truth` holds every true marker (NaN rows for markers that do not exist
// in this frame); `seen_by_two[m]` whether marker m was visible in >= 2 cameras;
// `bound_variance_m2`, if given, marker m's Cramer-Rao variance (NaN: none).
void ScoreFrame(const std::vector<Eigen::Vector3d>& truth, const std::vector<bool>& seen_by_two,
                const std::vector<Eigen::Vector3d>& points, double match_radius_m,
                ReconstructionScore* score,
                const std::vector<double>* bound_variance_m2 = nullptr);

// Centroid error of detections against what the renderer drew: each centroid within
// `radius_px` of a visible marker's projected centre is matched to the nearest (one-to-one, as
// ScoreFrame). The error is the pipeline's whole 2D error: the renderer's centroid jitter plus
// the detector's own.
struct CentroidScore {
  std::int64_t matched = 0;
  double sum_squared_px2 = 0;  // over both axes
  double rms_px_per_axis() const;
};
void ScoreCentroids(const Renderer& renderer, int camera, std::uint64_t sequence,
                    const std::vector<Eigen::Vector2d>& centroids, double radius_px,
                    CentroidScore* score);

// Adds one frame set of rendered cameras: the truth is what `renderer` drew for `sequence` in
// the cameras of `present_mask` (bit c: camera c's image is in the set; a missing image saw
// nothing), and the scene's markers at that image's time.
void ScoreRenderedFrame(const Renderer& renderer, const Scene& scene, std::uint64_t sequence,
                        std::uint64_t present_mask, const std::vector<Eigen::Vector3d>& points,
                        double match_radius_m, ReconstructionScore* score);

}  // namespace mocap::sim
