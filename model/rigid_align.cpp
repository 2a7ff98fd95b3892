#include "model/rigid_align.h"

#include <Eigen/Eigenvalues>
#include <Eigen/SVD>
#include <algorithm>
#include <cmath>

namespace mocap {

bool SpansPlane(const Eigen::Matrix3Xd& x) {
  const Eigen::Matrix3Xd c = x.colwise() - x.rowwise().mean();
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig(c * c.transpose(), Eigen::EigenvaluesOnly);
  return std::sqrt(std::max(0.0, eig.eigenvalues()[1])) > 1e-6;
}

Eigen::Matrix3d Skew(const Eigen::Vector3d& v) {
  Eigen::Matrix3d s;
  s << 0, -v.z(), v.y(), v.z(), 0, -v.x(), -v.y(), v.x(), 0;
  return s;
}

Eigen::Matrix3d KabschRotation(const Eigen::Matrix3d& h) {
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(h, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d fix = Eigen::Matrix3d::Identity();
  fix(2, 2) = (svd.matrixV() * svd.matrixU().transpose()).determinant() < 0 ? -1.0 : 1.0;
  return svd.matrixV() * fix * svd.matrixU().transpose();
}

std::optional<RigidTransform> RigidAlign(const Eigen::Matrix3Xd& src, const Eigen::Matrix3Xd& dst) {
  if (src.cols() < 3 || src.cols() != dst.cols() || !SpansPlane(src) || !SpansPlane(dst))
    return std::nullopt;
  // Written out because Eigen::umeyama trips GCC 12's -Warray-bounds under AVX.
  const Eigen::Vector3d cs = src.rowwise().mean(), cd = dst.rowwise().mean();
  const Eigen::Matrix3d h = (src.colwise() - cs) * (dst.colwise() - cd).transpose();
  RigidTransform r;
  r.rotation = KabschRotation(h);
  r.translation = cd - r.rotation * cs;
  return r;
}

}  // namespace mocap
