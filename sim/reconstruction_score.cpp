#include "sim/reconstruction_score.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <tuple>

#include <Eigen/Cholesky>

#include "sim/renderer.h"

namespace mocap::sim {

double ReconstructionScore::rms_mm() const {
  return matched ? 1e3 * std::sqrt(sum_squared_error_m2 / matched) : 0.0;
}
double ReconstructionScore::rms_bound_mm() const {
  return bounded ? 1e3 * std::sqrt(sum_bound_variance_m2 / bounded) : 0.0;
}

void ReconstructionScore::Add(const ReconstructionScore& o) {
  true_visible += o.true_visible;
  recovered += o.recovered;
  reconstructed += o.reconstructed;
  ghosts += o.ghosts;
  sum_squared_error_m2 += o.sum_squared_error_m2;
  matched += o.matched;
  matched_beyond_1mm += o.matched_beyond_1mm;
  sum_bound_variance_m2 += o.sum_bound_variance_m2;
  bounded += o.bounded;
}

void ScoreFrame(const std::vector<Eigen::Vector3d>& truth, const std::vector<bool>& seen_by_two,
                const std::vector<Eigen::Vector3d>& points, double match_radius_m,
                ReconstructionScore* score, const std::vector<double>* bound_variance_m2) {
  const double r2 = match_radius_m * match_radius_m;
  std::vector<std::tuple<double, int, int>> pairs;  // (squared distance, point, marker)
  for (int p = 0; p < static_cast<int>(points.size()); ++p) {
    for (int m = 0; m < static_cast<int>(truth.size()); ++m) {
      if (!truth[m].allFinite()) continue;
      const double d2 = (points[p] - truth[m]).squaredNorm();
      if (d2 <= r2) pairs.emplace_back(d2, p, m);
    }
  }
  std::sort(pairs.begin(), pairs.end());
  std::vector<bool> point_used(points.size(), false), marker_used(truth.size(), false);
  for (const auto& [d2, p, m] : pairs) {
    if (point_used[p] || marker_used[m]) continue;
    point_used[p] = marker_used[m] = true;
    score->sum_squared_error_m2 += d2;
    ++score->matched;
    if (d2 > 1e-6) ++score->matched_beyond_1mm;
    if (bound_variance_m2 != nullptr && m < static_cast<int>(bound_variance_m2->size()) &&
        std::isfinite((*bound_variance_m2)[m])) {
      score->sum_bound_variance_m2 += (*bound_variance_m2)[m];
      ++score->bounded;
    }
  }
  for (int m = 0; m < static_cast<int>(truth.size()); ++m) {
    if (m < static_cast<int>(seen_by_two.size()) && seen_by_two[m] && truth[m].allFinite()) {
      ++score->true_visible;
      score->recovered += marker_used[m];
    }
  }
  score->reconstructed += static_cast<std::int64_t>(points.size());
  for (bool used : point_used) score->ghosts += !used;
}

double CentroidScore::rms_px_per_axis() const {
  return matched ? std::sqrt(sum_squared_px2 / (2.0 * matched)) : 0.0;
}

void ScoreCentroids(const Renderer& renderer, int camera, std::uint64_t sequence,
                    const std::vector<Eigen::Vector2d>& centroids, double radius_px,
                    CentroidScore* score) {
  FrameTruth ft;
  renderer.Truth(camera, sequence, &ft);
  std::vector<std::tuple<double, int, int>> pairs;  // (squared distance, centroid, blob)
  const double r2 = radius_px * radius_px;
  for (int c = 0; c < static_cast<int>(centroids.size()); ++c) {
    for (int b = 0; b < static_cast<int>(ft.blobs.size()); ++b) {
      const double d2 = (centroids[c] - ft.blobs[b].projected).squaredNorm();
      if (d2 <= r2) pairs.emplace_back(d2, c, b);
    }
  }
  std::sort(pairs.begin(), pairs.end());
  std::vector<bool> used_c(centroids.size(), false), used_b(ft.blobs.size(), false);
  for (const auto& [d2, c, b] : pairs) {
    if (used_c[c] || used_b[b]) continue;
    used_c[c] = used_b[b] = true;
    score->sum_squared_px2 += d2;
    ++score->matched;
  }
}

void ScoreRenderedFrame(const Renderer& renderer, const Scene& scene, std::uint64_t sequence,
                        std::uint64_t present_mask, const std::vector<Eigen::Vector3d>& points,
                        double match_radius_m, ReconstructionScore* score) {
  const int nm = scene.marker_count();
  std::vector<Eigen::Vector3d> truth(nm);
  std::vector<int> views(nm, 0);
  std::vector<std::vector<int>> seen_in(nm);  // cameras whose image shows marker m
  FrameTruth ft;
  double time_s = 0;
  bool any = false;
  for (int c = 0; c < renderer.camera_count() && c < 64; ++c) {
    if (!(present_mask >> c & 1)) continue;
    renderer.Truth(c, sequence, &ft);
    time_s = ft.time_s;
    any = true;
    for (const BlobTruth& b : ft.blobs) {
      if (b.marker >= 0 && b.marker < nm) {
        ++views[b.marker];
        seen_in[b.marker].push_back(c);
      }
    }
  }
  if (!any) return;
  scene.Positions(time_s, truth.data());
  std::vector<bool> seen_by_two(nm);
  for (int m = 0; m < nm; ++m) seen_by_two[m] = views[m] >= 2;
  // The bound at the renderer's centroid noise (the detector's own error comes on top).
  const double sigma = renderer.options().centroid_noise_px;
  std::vector<double> bound(nm, std::numeric_limits<double>::quiet_NaN());
  if (sigma > 0) {
    for (int m = 0; m < nm; ++m) {
      if (views[m] < 2 || !truth[m].allFinite()) continue;
      Eigen::Matrix3d information = Eigen::Matrix3d::Zero();
      for (int c : seen_in[m]) {
        const reconstruction::CameraModel& cam = renderer.cameras()[c];
        Eigen::Matrix<double, 2, 3> j;
        cam.ProjectCameraPoint(cam.ToCamera(truth[m]), &j);
        const Eigen::Matrix<double, 2, 3> jw = j * cam.R;
        information += jw.transpose() * jw / (sigma * sigma);
      }
      const Eigen::LDLT<Eigen::Matrix3d> ldlt(information);
      if (ldlt.info() == Eigen::Success && ldlt.isPositive()) {
        bound[m] = ldlt.solve(Eigen::Matrix3d::Identity()).trace();
      }
    }
  }
  ScoreFrame(truth, seen_by_two, points, match_radius_m, score, &bound);
}

}  // namespace mocap::sim
