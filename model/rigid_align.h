// The best rigid motion between two paired point sets (Kabsch; Umeyama without scale). Used to
// compare models (model/compare.h) and to place a model on measured markers before inverse
// kinematics (solver/inverse_kinematics.h).
#pragma once
#include <Eigen/Core>
#include <optional>

namespace mocap {

// x -> R x + t.
struct RigidTransform {
  Eigen::Matrix3d rotation = Eigen::Matrix3d::Identity();
  Eigen::Vector3d translation = Eigen::Vector3d::Zero();
  Eigen::Vector3d Point(const Eigen::Vector3d& x) const { return rotation * x + translation; }
  Eigen::Vector3d Direction(const Eigen::Vector3d& x) const { return rotation * x; }
};

// True when the points (columns) are not all on one line (spread > 1 micrometre across it).
bool SpansPlane(const Eigen::Matrix3Xd& points);

// Kabsch's step, the one place it is written: the proper rotation R maximising trace(R H) for the
// cross-covariance H = sum (src_i - mean src)(dst_i - mean dst)^T, i.e. the R of the best rigid
// fit (the reflection a plain SVD may give is turned into the nearest rotation). For callers that
// accumulate H themselves without allocating (the tracker, per marker per frame).
Eigen::Matrix3d KabschRotation(const Eigen::Matrix3d& cross_covariance);

// [v]x, the cross-product matrix: Skew(v) w = v x w.
Eigen::Matrix3d Skew(const Eigen::Vector3d& v);

// The proper rotation R and translation t minimising sum |R src_i + t - dst_i|^2 (columns
// paired), or nothing when fewer than 3 points are given or either set is collinear.
std::optional<RigidTransform> RigidAlign(const Eigen::Matrix3Xd& src, const Eigen::Matrix3Xd& dst);

}  // namespace mocap
