// The camera model: a pinhole with radial and tangential lens distortion, with exactly OpenCV's
// parameters and conventions (cv::projectPoints, cv::calibrateCamera), so intrinsics from an
// OpenCV checkerboard calibration load as they are.
//
//   X_c = R X_w + t                      (world/lab -> camera; the camera looks along +z_c,
//                                         x_c to the right in the image, y_c down)
//   x = X_c.x / X_c.z,  y = X_c.y / X_c.z,  r2 = x^2 + y^2
//   x' = x (1 + k1 r2 + k2 r2^2 + k3 r2^3) + 2 p1 x y + p2 (r2 + 2 x^2)
//   y' = y (1 + k1 r2 + k2 r2^2 + k3 r2^3) + p1 (r2 + 2 y^2) + 2 p2 x y
//   u = fx x' + cx,  v = fy y' + cy      (pixels; the centre of the top-left pixel is (0, 0))
#pragma once
#include <Eigen/Core>
#include <Eigen/Geometry>
#include <string>

namespace mocap::reconstruction {

struct CameraIntrinsics {
  int width = 0;   // pixels
  int height = 0;
  double fx = 0, fy = 0, cx = 0, cy = 0;
  double k1 = 0, k2 = 0, p1 = 0, p2 = 0, k3 = 0;  // OpenCV order: k1 k2 p1 p2 k3

  bool IsValid(std::string* error) const;
};

struct CameraModel {
  std::string id;  // the camera's id or serial, to match a calibration to a rig
  CameraIntrinsics intrinsics;
  Eigen::Matrix3d R = Eigen::Matrix3d::Identity();  // world -> camera
  Eigen::Vector3d t = Eigen::Vector3d::Zero();

  Eigen::Vector3d centre() const { return -R.transpose() * t; }  // in the world frame
  Eigen::Vector3d ToCamera(const Eigen::Vector3d& world) const { return R * world + t; }

  // False when the point is behind the camera (z_c <= 0); *pixel is still written.
  bool Project(const Eigen::Vector3d& world, Eigen::Vector2d* pixel) const;
  // Projection of a point given in the CAMERA frame, with d(u,v)/d(X_c) when `jacobian` is set.
  Eigen::Vector2d ProjectCameraPoint(const Eigen::Vector3d& camera_point,
                                     Eigen::Matrix<double, 2, 3>* jacobian = nullptr) const;
  // Pixel -> normalised, undistorted image coordinates (x, y) (z_c = 1), by Newton's method on
  // the distortion map (to 1e-12; OpenCV's undistortPoints uses a fixed 5-step iteration).
  Eigen::Vector2d Undistort(const Eigen::Vector2d& pixel) const;
  // The ray through a pixel, in the world frame: centre() + s * direction, direction unit.
  Eigen::Vector3d RayDirection(const Eigen::Vector2d& pixel) const;
};

// Distortion of normalised coordinates (x, y) -> (x', y'), with its 2x2 Jacobian if asked.
Eigen::Vector2d Distort(const CameraIntrinsics& k, const Eigen::Vector2d& xy,
                        Eigen::Matrix2d* jacobian = nullptr);

}  // namespace mocap::reconstruction
