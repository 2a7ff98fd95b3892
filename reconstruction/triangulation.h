// Triangulation: the 2D centroids of one DetectionSet -> unlabelled 3D points, each with its
// reprojection residual and the (camera, centroid) pairs it was made from.
//
// Why it is not just "intersect the rays": the centroids carry no labels, so which centroid of
// camera A belongs with which of camera B is unknown. The epipolar constraint (a point of A lies
// on the epipolar line x_B^T E x_A = 0 in B, E = [t]x R the essential matrix of the pair,
// Hartley & Zisserman 2nd ed. §9.6) is necessary but not sufficient: with ~40 markers, a centroid
// of A lies within a pixel of the epipolar lines of several centroids of B whenever markers share
// an epipolar plane (markers at the same height seen by two cameras at the same height), and every
// such pair triangulates to a "ghost" — a 3D point where there is no marker. A third camera
// disambiguates: a true marker projects onto a centroid in the other cameras that see it, a ghost
// almost never does. So correspondence is hypothesise-and-verify:
//
//   1. Undistort every centroid once to normalised image coordinates (the camera's Newton
//      inverse of the distortion), so the epipolar test and the projections into other cameras
//      are cheap pinhole algebra.
//   2. Visit the camera pairs widest first (the angle their centres subtend at the point the rig
//      looks at, closest to 90 degrees first: the best-conditioned intersections). For each pair,
//      every pair of still-unused centroids within `epipolar_gate_sigmas` of each other's
//      epipolar line is a hypothesis: triangulate it from the two rays (linear, step 4), require
//      it in front of both cameras and inside the volume, project it into every other present
//      camera and collect, per camera, the nearest unused centroid within `support_gate_sigmas`.
//   3. Accept greedily, the hypotheses with the most views first (then the smallest epipolar
//      distance); a centroid belongs to at most one point, so a hypothesis whose pair centroids an
//      earlier one took is dropped (superseded) and a taken supporting view is ignored. Pair by
//      pair for hypotheses of 3+ views (each pair's points leave the later pairs less to match);
//      over all pairs at once for two-view hypotheses, which have no third camera to vouch for
//      them, so that a centroid goes to its most consistent partner.
//   4. For an accepted hypothesis: multi-view linear triangulation (the DLT of H&Z §12.2 in its
//      inhomogeneous form, X = (x, y, z, 1): marker points are never at infinity, and its 3x3
//      normal equations are cheaper than the SVD of the homogeneous 2n x 4 system), then
//      Levenberg–Marquardt on the reprojection error in pixels, each view weighted by 1 / its
//      centroid's sigma (the maximum likelihood estimate for Gaussian centroid noise, H&Z §12.3),
//      with the camera model's analytic Jacobian (distortion included). A view whose residual
//      exceeds `outlier_gate_sigmas` is dropped and the point refined again; the refined point is
//      then projected into the cameras it lacks to pick up views the two-view estimate missed.
//   5. Ghost rejection: a point survives only with at least the pass's number of views, all in
//      front of their cameras, inside the volume, and an RMS reprojection residual at most
//      `max_residual_px`.
//   6. Points closer than `min_separation_m` are one marker split in two: merged and refined.
//   The passes: first only points with >= 3 views (a ghost with three consistent views is rare;
//   a ghost with two is only as rare as the epipolar band is thin), then, among the centroids
//   still unused, points with 2 views, with the tighter `two_view_gate_sigmas` — so a marker
//   seen by exactly two cameras is still reconstructed, but cannot steal the centroids of a
//   better-supported point. Two unrelated centroids (say two stray reflections) that happen to
//   satisfy the epipolar constraint are indistinguishable from such a marker in one frame set:
//   with 3 uniform strays per camera on the simulated rig, 0.45% of the points are such ghosts,
//   0.30% with the capture volume bounded (bench/triangulate); their number grows with the
//   square of the strays per camera (3% at 10 per camera). The tracker, which labels points
//   against its predicted markers, is what ignores them.
//
// Gates are in units of sigma, the centroid's sigma_px combined with `calibration_sigma_px` (the
// rig's calibration error, which the centroid noise does not include), so they follow the
// detector's own uncertainty.
//
// Threads: a Triangulator is immutable after Create and may be shared; each thread passes its
// own TriangulationWorkspace. Once the workspace has seen frame sets as large, no heap memory is
// allocated (the output vector keeps its capacity too).
//
// Accuracy (bench/triangulate, 8 cameras at 4 m, f = 1000 px, sigma 0.1 px): the refined points
// reach the Cramer-Rao bound of the views they use (RMS 3D error 0.323 mm against a bound of
// 0.322 mm); the DLT alone is 1.5% above it.
#pragma once
#include <Eigen/Core>
#include <array>
#include <cstdint>
#include <limits>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "model/status.h"
#include "reconstruction/camera_model.h"
#include "reconstruction/centroid.h"

namespace mocap::reconstruction {

// A point keeps at most this many views (the design's rigs have 4-16 cameras); a larger rig
// works, each point keeping its first kMaxPointViews views.
inline constexpr int kMaxPointViews = 16;

struct TriangulationOptions {
  // Calibration error of the rig, in pixels, added in quadrature to each centroid's sigma in
  // every gate (not in the least-squares weights).
  double calibration_sigma_px = 0.05;
  // A centroid pair matches when each lies within this many combined sigmas of the other's
  // epipolar line.
  double epipolar_gate_sigmas = 4.0;
  // The same gate in the two-view pass, where it is the only evidence for a match (no third
  // camera confirms it): tighter, so fewer coincidences (strays, unrelated centroids) pass, at
  // the cost of 0.3% of the true two-view matches (a 1-D Gaussian beyond 3 sigma).
  double two_view_gate_sigmas = 3.0;
  // A centroid supports a hypothesis when it lies within this many sigmas of its projection.
  double support_gate_sigmas = 5.0;
  // After refinement, a view whose residual exceeds this many sigmas is dropped.
  double outlier_gate_sigmas = 5.0;
  // A point whose RMS reprojection residual exceeds this is rejected as a ghost.
  double max_residual_px = 1.0;
  // Fewest views of a point: 2 reconstructs markers seen by only two cameras; 3 trades those
  // for fewer ghosts.
  int min_views = 2;
  // A two-view point needs its rays at least this far from parallel and from opposite (cameras
  // facing each other): otherwise it is poorly located along the rays.
  double min_two_view_angle_deg = 2.0;
  // A point must be at least this far in front of every camera that sees it.
  double min_depth_m = 0.05;
  // The capture volume, in the world frame: points outside it are rejected. Unbounded by default.
  Eigen::Vector3d volume_min = Eigen::Vector3d::Constant(-std::numeric_limits<double>::infinity());
  Eigen::Vector3d volume_max = Eigen::Vector3d::Constant(std::numeric_limits<double>::infinity());
  // Levenberg–Marquardt iterations per refinement (it converges in 2-3 from the DLT).
  int max_iterations = 10;
  // A camera with more centroids than this (a flare, a reflection flooding the image) is ignored
  // for this frame set, so the pair matching stays bounded; the summary counts it.
  int max_centroids_per_camera = 1000;
  // Two points closer than this are one marker split in two (it happens when a marker is hidden
  // in a camera where another marker projects within a pixel or so of it, and the cameras that
  // accepted the wrong centroid lie nearly in one plane with the point, so they cannot tell): they
  // are merged, views pooled one per camera, and refined again, dropping the outlier. Below the
  // centre distance of two touching markers (6.4 mm is the smallest common body marker).
  double min_separation_m = 0.006;

  bool IsValid(std::string* error) const;
};

// One camera's view of a point: which centroid of which camera.
struct PointView {
  std::int32_t camera = -1;    // index in the rig / DetectionSet::cameras
  std::int32_t centroid = -1;  // index in that camera's CameraDetections::centroids
};

struct TriangulatedPoint {
  Eigen::Vector3d position = Eigen::Vector3d::Zero();  // world frame, metres
  double residual_px = 0.0;  // RMS over the views of the reprojection error's norm, pixels
  int camera_count = 0;      // valid entries of `views`, ordered by camera
  std::array<PointView, kMaxPointViews> views{};
};

struct TriangulationSummary {
  int cameras_used = 0;         // present cameras whose centroids were used
  int cameras_overfull = 0;     // present cameras ignored for > max_centroids_per_camera
  int centroids = 0;            // centroids of the cameras used
  int candidates = 0;           // epipolar pair matches in front of both cameras, in volume
  int accepted = 0;             // points returned
  int rejected_ghosts = 0;      // hypotheses refined and rejected (residual, views, depth)
  int superseded = 0;           // hypotheses whose centroids a better one had taken
  int merged = 0;               // points merged into a closer-than-min_separation neighbour
  int unmatched_centroids = 0;  // centroids of the cameras used that no point took
};

// A single observation for the low-level functions: camera index, pixel, sigma.
struct PointObservation {
  int camera = -1;
  Eigen::Vector2d pixel = Eigen::Vector2d::Zero();
  double sigma_px = 0.1;
};

// Multi-view linear triangulation (inhomogeneous DLT, H&Z §12.2) from distorted pixels: each view
// undistorted, rows weighted by focal / sigma. False when fewer than two views or the rays are
// (near) parallel.
bool TriangulateLinear(const std::vector<CameraModel>& rig,
                       std::span<const PointObservation> observations, Eigen::Vector3d* position);

// The whitened reprojection residual of one view, (project(X) - pixel) / sigma, and its 2x3
// Jacobian with respect to the world point X (the camera model's analytic Jacobian times R).
Eigen::Vector2d WhitenedReprojectionResidual(const CameraModel& camera,
                                             const PointObservation& observation,
                                             const Eigen::Vector3d& position,
                                             Eigen::Matrix<double, 2, 3>* jacobian = nullptr);

// Levenberg–Marquardt on the sum of squared whitened residuals, from *position. Writes the RMS
// pixel residual (as TriangulatedPoint::residual_px). False if a view is (or the iteration went)
// behind its camera or the problem is degenerate; *position is then the last good iterate.
bool RefinePosition(const std::vector<CameraModel>& rig,
                    std::span<const PointObservation> observations, int max_iterations,
                    Eigen::Vector3d* position, double* residual_px);

class TriangulationWorkspace;

namespace internal {
// A pair match and the views it collected, before refinement.
struct Hypothesis {
  Eigen::Vector3d position = Eigen::Vector3d::Zero();
  double epipolar_cost = 0;  // squared epipolar distance in combined sigmas
  int view_count = 0;        // views[0], views[1]: the pair's cameras
  std::array<PointView, kMaxPointViews> views{};
};
}  // namespace internal

class Triangulator {
 public:
  // Checks the options and every camera of the rig (intrinsics, R a rotation, t finite) and
  // precomputes the pair geometry. The error names the camera and what is wrong with it.
  static Status Create(std::vector<CameraModel> rig, const TriangulationOptions& options,
                       std::unique_ptr<Triangulator>* triangulator);

  // Triangulates one frame set into *points (cleared first). *summary may be null. Fails, with
  // a message naming the camera and centroid, on a set that does not match the rig (camera
  // count, present flags, camera index) or a centroid that is not finite or has sigma <= 0.
  Status Triangulate(const DetectionSet& set, TriangulationWorkspace* workspace,
                     std::vector<TriangulatedPoint>* points,
                     TriangulationSummary* summary = nullptr) const;

  const std::vector<CameraModel>& rig() const { return rig_; }
  const TriangulationOptions& options() const { return options_; }

  // The camera pairs in the order they are visited: sin of the angle the two centres subtend
  // at the rig's focus (the point closest to all optical axes), largest first.
  struct CameraPair {
    int a = 0, b = 0;
    Eigen::Matrix3d essential;  // x_b^T E x_a = 0 in normalised coordinates
    double score = 0;
  };
  const std::vector<CameraPair>& pairs() const { return pairs_; }

 private:
  Triangulator() = default;
  Status Validate(const DetectionSet& set) const;
  void MergeClosePoints(const DetectionSet& set, TriangulationWorkspace* ws,
                        std::vector<TriangulatedPoint>* points,
                        TriangulationSummary* summary) const;
  void RunPass(const DetectionSet& set, int min_views, TriangulationWorkspace* ws,
               std::vector<TriangulatedPoint>* points, TriangulationSummary* summary) const;
  void AcceptHypotheses(const DetectionSet& set, int min_views, TriangulationWorkspace* ws,
                        std::vector<TriangulatedPoint>* points,
                        TriangulationSummary* summary) const;
  bool Solve(const DetectionSet& set, int min_views, internal::Hypothesis* h,
             TriangulationWorkspace* ws, TriangulatedPoint* point) const;
  int FindSupport(const TriangulationWorkspace& ws, int camera, const Eigen::Vector3d& x) const;

  std::vector<CameraModel> rig_;
  TriangulationOptions options_;
  std::vector<double> focal_;  // sqrt(fx fy) per camera: pixels per normalised unit
  std::vector<CameraPair> pairs_;
  double cos_min_two_view_angle_ = 1;
  double calibration_sigma2_ = 0;
};

// Per-thread scratch memory of Triangulator::Triangulate; reuse it across frame sets.
class TriangulationWorkspace {
 public:
  TriangulationWorkspace() = default;

 private:
  friend class Triangulator;
  struct CameraScratch {
    bool active = false;
    std::vector<Eigen::Vector2d> xy;  // undistorted normalised coordinates per centroid
    std::vector<double> gate;         // gating sigma per centroid, normalised units
    std::vector<std::uint8_t> state;  // kFree, kTaken (by a point) or kUnusable
  };
  std::vector<CameraScratch> cameras_;
  std::vector<int> unused_a_, unused_b_;
  std::vector<Eigen::Vector3d> lines_b_;  // E^T x_b per unused centroid of camera b
  std::vector<internal::Hypothesis> hypotheses_;
  std::vector<int> order_;
  std::vector<PointObservation> observations_;
};

// Convenience: Create + Triangulate with a fresh workspace (allocates; for tests and tools).
Status Triangulate(const DetectionSet& set, const std::vector<CameraModel>& rig,
                   const TriangulationOptions& options, std::vector<TriangulatedPoint>* points,
                   TriangulationSummary* summary = nullptr);

}  // namespace mocap::reconstruction
