// The wand bundle adjustment as an arrow-structured least-squares problem (solver/arrow_problem.h),
// solved by the same Levenberg–Marquardt and Schur elimination as the body-model fit.
//
//   frame blocks y_f (5): the wand at frame f — its centre o (3, metres) and its direction as
//       d = (d0 + a e1 + b e2) / |d0 + a e1 + b e2|, with d0 the frame's initial direction and
//       e1, e2 a basis of its normal plane. A direction has two degrees of freedom; this chart is
//       regular everywhere near d0 (no pole, unlike two spherical angles), and the bundle
//       adjustment never moves a direction far from its triangulated start. Marker k is at
//       o + (s_k - s_mean) d: the wand's spacing is exact, so its length is the metric scale.
//   shared p, per camera: a rotation vector w with R = exp(w) R0 (R0 the starting rotation, so
//       w stays small and away from the 2 pi singularity), the translation t, and with
//       refine_intrinsics fx, fy, cx, cy, k1, k2. Camera 0's pose is held fixed (the gauge:
//       Triggs et al. 2000, §9); a weak prior keeps refined intrinsics near their start, which
//       the wand data then override.
//   residuals: for every camera that saw the wand at frame f and each wand marker, the 2D
//       reprojection error in pixels (camera_model.h's OpenCV distortion).
//
// Jacobians are analytic: d exp(w) v / dw = -[exp(w) v]_x J_l(w), J_l the left Jacobian of SO(3)
// (Barfoot, "State Estimation for Robotics", 2017, ch. 7); the rest is the chain rule through
// CameraModel::ProjectCameraPoint.
#pragma once

#include <Eigen/Core>
#include <memory>
#include <vector>

#include "reconstruction/camera_model.h"
#include "solver/arrow_problem.h"

namespace mocap::reconstruction {

// One camera's view of the wand at one frame: its markers' pixels in Wand order.
struct WandObservation {
  int camera = -1;
  Eigen::Vector2d pixels[3];
};

struct WandFrame {
  std::vector<WandObservation> observations;
  // The chart of the frame's direction (see above): d0 unit, e1, e2 orthonormal to it.
  Eigen::Vector3d d0 = Eigen::Vector3d::UnitX(), e1 = Eigen::Vector3d::UnitY(),
                  e2 = Eigen::Vector3d::UnitZ();
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();  // starting centre
  void SetDirection(const Eigen::Vector3d& direction);
};

class WandBundleProblem : public solver::ArrowProblem {
 public:
  static constexpr int kPose = 6, kIntrinsics = 6;
  // marker_offsets_m: each wand marker's position along the wand relative to the wand centre.
  // prior_intrinsics: where the weak intrinsics priors pull (the intrinsics the calibration
  // started from, when `cameras` are already refined); empty: the cameras' own.
  WandBundleProblem(std::vector<CameraModel> cameras, std::vector<WandFrame> frames,
                    std::vector<double> marker_offsets_m, bool refine_intrinsics,
                    int fixed_camera = 0, const std::vector<CameraModel>& prior_intrinsics = {});

  int num_frames() const override { return static_cast<int>(frames_.size()); }
  int frame_dim() const override { return 5; }
  int shared_dim() const override { return shared_dim_; }
  int num_residuals() const override { return 2 * 3 * num_observations_ + prior_rows_; }
  bool SetShared(const Eigen::VectorXd& p) override;
  std::unique_ptr<solver::FrameEvaluator> NewEvaluator() const override;
  const Eigen::VectorXd& prior_weight() const override { return prior_weight_; }
  const Eigen::VectorXd& prior_target() const override { return prior_target_; }
  void BlockStructure(std::vector<std::vector<int>>* y_columns,
                      std::vector<std::vector<int>>* p_columns) const override;

  // The starting point x = [y_1 .. y_F, p] (frames at their starting centre and direction).
  Eigen::VectorXd InitialState() const;
  // Cameras at shared values p (as set by the last SetShared).
  const std::vector<CameraModel>& cameras() const { return current_; }
  const std::vector<WandFrame>& frames() const { return frames_; }
  // Wand direction and marker positions (world) of frame f at y.
  Eigen::Vector3d Direction(int f, const double* y) const;
  Eigen::Vector3d MarkerPosition(int f, const double* y, int k) const;
  // Free index of camera c's parameter j (pose 0..5, intrinsics 6..11); -1 if fixed.
  int shared_index(int camera, int j) const { return index_[camera][j]; }

 private:
  friend class WandFrameEvaluator;
  std::vector<CameraModel> initial_, current_;
  std::vector<WandFrame> frames_;
  std::vector<double> offsets_;
  bool refine_intrinsics_;
  int num_observations_ = 0;
  int shared_dim_ = 0;
  int prior_rows_ = 0;
  std::vector<std::vector<int>> index_;         // [camera][12]
  std::vector<Eigen::Matrix3d> left_jacobian_;  // J_l(w) per camera at the last SetShared
  Eigen::VectorXd prior_weight_, prior_target_, start_;
};

// Rodrigues' formula and the left Jacobian of SO(3) (the cross-product matrix: Skew,
// model/rigid_align.h).
Eigen::Matrix3d ExpSO3(const Eigen::Vector3d& w);
Eigen::Matrix3d LeftJacobianSO3(const Eigen::Vector3d& w);

}  // namespace mocap::reconstruction
