#include "reconstruction/camera_model.h"

#include <cmath>
#include <Eigen/LU>

namespace mocap::reconstruction {

bool CameraIntrinsics::IsValid(std::string* error) const {
  auto fail = [&](const char* what) {
    if (error) *error = std::string("camera intrinsics: ") + what;
    return false;
  };
  if (width <= 0 || height <= 0) return fail("width and height must be positive");
  for (double v : {fx, fy, cx, cy, k1, k2, p1, p2, k3}) {
    if (!std::isfinite(v)) return fail("a parameter is not finite");
  }
  if (fx <= 0 || fy <= 0) return fail("fx and fy must be positive");
  return true;
}

Eigen::Vector2d Distort(const CameraIntrinsics& k, const Eigen::Vector2d& xy,
                        Eigen::Matrix2d* jacobian) {
  const double x = xy.x(), y = xy.y();
  const double r2 = x * x + y * y;
  const double radial = 1 + r2 * (k.k1 + r2 * (k.k2 + r2 * k.k3));
  const Eigen::Vector2d out(x * radial + 2 * k.p1 * x * y + k.p2 * (r2 + 2 * x * x),
                            y * radial + k.p1 * (r2 + 2 * y * y) + 2 * k.p2 * x * y);
  if (jacobian) {
    // d radial / d r2, and d r2 / dx = 2x, d r2 / dy = 2y.
    const double dradial = k.k1 + r2 * (2 * k.k2 + 3 * r2 * k.k3);
    const double drx = 2 * x * dradial, dry = 2 * y * dradial;
    (*jacobian)(0, 0) = radial + x * drx + 2 * k.p1 * y + 6 * k.p2 * x;
    (*jacobian)(0, 1) = x * dry + 2 * k.p1 * x + 2 * k.p2 * y;
    (*jacobian)(1, 0) = y * drx + 2 * k.p1 * x + 2 * k.p2 * y;
    (*jacobian)(1, 1) = radial + y * dry + 6 * k.p1 * y + 2 * k.p2 * x;
  }
  return out;
}

Eigen::Vector2d CameraModel::ProjectCameraPoint(const Eigen::Vector3d& pc,
                                                Eigen::Matrix<double, 2, 3>* jacobian) const {
  const CameraIntrinsics& k = intrinsics;
  const double iz = 1.0 / pc.z();
  const Eigen::Vector2d xy(pc.x() * iz, pc.y() * iz);
  Eigen::Matrix2d dd;
  const Eigen::Vector2d d = Distort(k, xy, jacobian ? &dd : nullptr);
  if (jacobian) {
    Eigen::Matrix<double, 2, 3> dxy;
    dxy << iz, 0, -xy.x() * iz, 0, iz, -xy.y() * iz;
    Eigen::Matrix<double, 2, 3> j = dd * dxy;
    j.row(0) *= k.fx;
    j.row(1) *= k.fy;
    *jacobian = j;
  }
  return {k.fx * d.x() + k.cx, k.fy * d.y() + k.cy};
}

bool CameraModel::Project(const Eigen::Vector3d& world, Eigen::Vector2d* pixel) const {
  const Eigen::Vector3d pc = ToCamera(world);
  *pixel = ProjectCameraPoint(pc);
  return pc.z() > 0;
}

Eigen::Vector2d CameraModel::Undistort(const Eigen::Vector2d& pixel) const {
  const CameraIntrinsics& k = intrinsics;
  const Eigen::Vector2d target((pixel.x() - k.cx) / k.fx, (pixel.y() - k.cy) / k.fy);
  Eigen::Vector2d xy = target;
  for (int it = 0; it < 20; ++it) {
    Eigen::Matrix2d j;
    const Eigen::Vector2d r = Distort(k, xy, &j) - target;
    if (r.squaredNorm() < 1e-26) break;
    xy -= j.partialPivLu().solve(r);
  }
  return xy;
}

Eigen::Vector3d CameraModel::RayDirection(const Eigen::Vector2d& pixel) const {
  const Eigen::Vector2d xy = Undistort(pixel);
  return (R.transpose() * Eigen::Vector3d(xy.x(), xy.y(), 1.0)).normalized();
}

}  // namespace mocap::reconstruction
