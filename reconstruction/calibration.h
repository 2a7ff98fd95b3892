// Extrinsic camera calibration by waving a wand, as Vicon, Qualisys and OptiTrack do it.
//
// A wand carries three markers on a straight line at known, UNEQUAL distances (e.g. 0, 200 and
// 500 mm), so in every image its markers can be told apart from each other and from stray
// reflections without knowing any camera pose: three centroids that are collinear and whose
// spacing ratio matches the wand's (IdentifyWand). The ratio of distances along a line is an
// affine invariant, not a projective one; a wand 0.5 m long seen from 3–5 m is close enough to
// affine that a tolerance of a few per cent separates 0.4 from its mirror 0.6, and the bundle
// adjustment then sees the exact perspective. A wand frame therefore gives three labelled point
// correspondences between every pair of cameras that saw it, over the whole volume.
//
// Calibration (CalibrateWand) then runs:
//  1. Pairwise relative poses. For every camera pair, the undistorted (normalised) correspondences
//     give an essential matrix, by the five-point algorithm inside RANSAC (Nistér 2004, through
//     cv::findEssentialMat), decomposed into R, t and checked for points in front of both cameras
//     (cv::recoverPose; Hartley & Zisserman, "Multiple View Geometry", 2nd ed., §9.6). Its unknown
//     scale is fixed by the wand: the triangulated wand must have its true length.
//  2. A spanning tree of camera pairs, the one with the most shared wand frames (maximum spanning
//     tree, Prim), chains the pairwise poses into poses of every camera in camera 0's frame. Pairs
//     with many shared frames have the best-conditioned essential matrices; the tree uses each
//     camera's best link, and the bundle adjustment removes what chaining accumulates.
//  3. Bundle adjustment (Triggs, McLauchlan, Hartley, Fitzgibbon, "Bundle Adjustment — A Modern
//     Synthesis", 2000) of every camera pose and every wand pose on the project's sparse
//     Levenberg–Marquardt (solver/levenberg_marquardt.h) with the Schur complement onto the
//     cameras (solver/schur_solver.h): the wand poses are the independent frame blocks and the
//     cameras the shared parameters — the arrow structure of the body fit. Each wand pose has
//     FIVE parameters (position and direction of a line; the roll about a line of points is not
//     observable), and its markers sit at their known spacing along it, so the wand's length —
//     the metric scale — is part of the model, not a soft constraint (WandBundleProblem).
//     Camera 0 is held fixed (the gauge: six degrees of freedom; the scale is fixed by the wand).
//     Observations that do not fit after the first solve (mis-identified wands) are dropped and
//     the problem solved again.
//  4. Lab frame. A static L-frame (3–4 markers at known positions on the floor) seen by the
//     calibrated cameras is triangulated and a rigid transform (Kabsch/Umeyama, no scale: the wand
//     fixed it) maps the cameras into the lab frame the L-frame defines.
//
// Quality, as the commercial systems report it: the reprojection RMS per camera, and the
// wand-length error — each marker triangulated on its own with the calibrated cameras, no wand
// model, and the distance between the end markers compared with the true length. The latter
// measures the 3D accuracy of the calibration (Qualisys warns above 3 mm; a good 8-camera
// calibration gives a fraction of a millimetre).
#pragma once

#include <Eigen/Core>
#include <string>
#include <vector>

#include "model/status.h"
#include "reconstruction/camera_model.h"
#include "reconstruction/centroid.h"
#include "solver/levenberg_marquardt.h"

namespace mocap::reconstruction {

// The wand: its markers' positions along its axis (metres), in an order that makes the spacing
// unequal, e.g. {0, 0.2, 0.5}. The first and last are the ends.
struct Wand {
  std::vector<double> marker_positions_m = {0.0, 0.2, 0.5};

  double length_m() const { return marker_positions_m.back() - marker_positions_m.front(); }
  // (position of the middle marker - first) / length: 0.4 for the default wand.
  double middle_ratio() const {
    return (marker_positions_m[1] - marker_positions_m[0]) / length_m();
  }
  bool IsValid(std::string* error) const;
};

// The L-frame: markers at known positions in the lab frame (metres), lying on the floor; they
// define the lab origin and axes. Default: origin, 0.2 and 0.6 m along x, 0.4 m along y (no
// symmetry, so the markers can be matched to the model by their distances alone).
struct LFrame {
  std::vector<Eigen::Vector3d> markers_m = {
      {0.0, 0.0, 0.0}, {0.2, 0.0, 0.0}, {0.6, 0.0, 0.0}, {0.0, 0.4, 0.0}};
  bool IsValid(std::string* error) const;
};

// Finds the wand in one image's centroids. Returns false if no triple, or more than one, matches
// (ambiguous: the image is better left out). *markers gets the wand's markers in Wand order.
struct WandIdentificationOptions {
  double collinearity_px = 2.0;    // distance of the middle centroid from the line of the ends
  double ratio_tolerance = 0.06;   // |measured middle ratio - wand's|
  double min_separation_px = 4.0;  // centroids closer than this may be merged blobs
  bool IsValid(std::string* error) const;
};
bool IdentifyWand(const std::vector<Centroid>& centroids, const Wand& wand,
                  const WandIdentificationOptions& options, std::vector<Eigen::Vector2d>* markers);

struct WandCalibrationOptions {
  Wand wand;
  LFrame lframe;
  WandIdentificationOptions identification;
  // Pairs sharing fewer wand frames get no essential matrix of their own.
  int min_shared_frames = 12;
  double ransac_threshold_px = 1.0;  // essential-matrix RANSAC, in pixels (of the mean focal)
  // After the first solve, observations with a marker error above
  // max(outlier_min_px, outlier_sigmas * RMS) are dropped and the problem is solved again.
  double outlier_min_px = 1.0;
  double outlier_sigmas = 6.0;
  // Also refine each camera's fx, fy, cx, cy, k1, k2 (from intrinsics that are close already).
  bool refine_intrinsics = false;
  // The bundle adjustment's solver options; its callbacks report progress, and one returning
  // false cancels the calibration (an error saying so).
  solver::LmOptions lm = DefaultLm();
  int num_threads = 1;

  static solver::LmOptions DefaultLm() {
    solver::LmOptions o;
    o.max_iterations = 100;
    o.function_tolerance = 1e-10;
    return o;
  }
  bool IsValid(std::string* error) const;
};

// One camera's share of the result.
struct CameraCalibrationStats {
  std::string id;
  int wand_frames = 0;             // wand frames in which it took part in the final solve
  int rejected = 0;                // its observations dropped as outliers
  double reprojection_rms_px = 0;  // RMS of the 2D reprojection error norm, final solve
};

enum class CalibrationTermination { kSuccess, kFailure };

struct WandCalibrationSummary {
  CalibrationTermination termination = CalibrationTermination::kFailure;
  std::string message;
  int wand_frames_total = 0;       // frames given
  int wand_frames_identified = 0;  // identified in >= 2 cameras
  int wand_frames_used = 0;        // in the final bundle adjustment
  int observations = 0;            // camera-frame wand observations in the final solve
  int rejected_observations = 0;
  std::vector<std::pair<int, int>> tree;  // spanning tree edges (parent, child)
  std::vector<int> tree_shared_frames;    // shared frames on each edge
  solver::LmSummary first_solve, final_solve;
  std::vector<CameraCalibrationStats> cameras;
  double reprojection_rms_px = 0;          // RMS of 2D error norm over every observation
  double initial_reprojection_rms_px = 0;  // before the bundle adjustment (chained poses)
  double wand_length_error_mm_rms = 0;     // free triangulation, end-to-end distance - true length
  double wand_length_error_mm_mean = 0;
  bool lab_frame_from_lframe = false;  // false: the frame of camera 0
  double lframe_residual_mm_rms = 0;   // triangulated L-frame vs its model, after alignment
  double seconds = 0;

  std::string BriefReport() const;
  std::string FullReport() const;
};

// Calibrates the extrinsics of `cameras` (whose ids and intrinsics are given; R, t are ignored)
// from wand frames and, if not empty, static L-frame frames. Each DetectionSet has one entry per
// camera, in the order of `cameras`. *calibrated receives the cameras with their poses (lab frame
// of the L-frame, else camera 0's frame) and, with refine_intrinsics, their refined intrinsics.
Status CalibrateWand(const std::vector<CameraModel>& cameras,
                     const std::vector<DetectionSet>& wand_frames,
                     const std::vector<DetectionSet>& lframe_frames,
                     const WandCalibrationOptions& options, std::vector<CameraModel>* calibrated,
                     WandCalibrationSummary* summary);

// Least-squares triangulation of one point seen by several cameras, through the rig's own
// triangulation (reconstruction/triangulation.h: TriangulateLinear, then RefinePosition on the
// pixel reprojection error, the views weighted alike), for cameras that are not a rig yet. False
// if fewer than two views or the point is not in front of them.
bool TriangulatePoint(const std::vector<const CameraModel*>& cameras,
                      const std::vector<Eigen::Vector2d>& pixels, Eigen::Vector3d* point);

// Pose error of a camera against a reference: centre distance (metres) and rotation angle
// (radians) of R_est R_true^T.
void CameraPoseError(const CameraModel& estimated, const CameraModel& truth, double* position_m,
                     double* angle_rad);

}  // namespace mocap::reconstruction
