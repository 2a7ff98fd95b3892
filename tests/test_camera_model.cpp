// The camera model against OpenCV's published conventions, its Jacobian against finite
// differences, and the simulated rig against what a lab rig must do (see the volume).
#include <gtest/gtest.h>

#include "reconstruction/camera_model.h"
#include "sim/camera_rig.h"

namespace mocap {
namespace {

using reconstruction::CameraModel;

CameraModel TestCamera() {
  CameraModel c;
  c.intrinsics = {1280, 1024, 1010.0, 1005.0, 641.5, 509.0, -0.08, 0.02, 0.0007, -0.0004, 0.003};
  c.R = Eigen::AngleAxisd(0.3, Eigen::Vector3d(0.2, 1, 0.1).normalized()).toRotationMatrix();
  c.t = Eigen::Vector3d(0.1, -0.2, 3.0);
  return c;
}

TEST(CameraModel, ProjectsLikeOpenCvFormula) {
  // A hand-evaluated point: camera at the origin, no rotation.
  CameraModel c;
  c.intrinsics = {640, 480, 500, 500, 320, 240, 0.1, 0.0, 0.0, 0.0, 0.0};
  Eigen::Vector2d uv;
  ASSERT_TRUE(c.Project(Eigen::Vector3d(0.2, 0.1, 1.0), &uv));
  const double r2 = 0.05, radial = 1 + 0.1 * r2;
  EXPECT_NEAR(uv.x(), 500 * 0.2 * radial + 320, 1e-12);
  EXPECT_NEAR(uv.y(), 500 * 0.1 * radial + 240, 1e-12);
  EXPECT_FALSE(c.Project(Eigen::Vector3d(0.2, 0.1, -1.0), &uv));
}

TEST(CameraModel, JacobianMatchesFiniteDifferences) {
  const CameraModel c = TestCamera();
  const Eigen::Vector3d p(0.3, -0.25, 2.7);
  Eigen::Matrix<double, 2, 3> j;
  c.ProjectCameraPoint(p, &j);
  for (int k = 0; k < 3; ++k) {
    const double h = 1e-6;
    Eigen::Vector3d a = p, b = p;
    a[k] += h;
    b[k] -= h;
    const Eigen::Vector2d fd = (c.ProjectCameraPoint(a) - c.ProjectCameraPoint(b)) / (2 * h);
    EXPECT_NEAR((j.col(k) - fd).norm(), 0.0, 1e-5 * fd.norm() + 1e-6) << "column " << k;
  }
}

TEST(CameraModel, UndistortInvertsProjection) {
  const CameraModel c = TestCamera();
  for (double x = -0.5; x <= 0.5; x += 0.1) {
    for (double y = -0.4; y <= 0.4; y += 0.1) {
      const Eigen::Vector3d pc(x, y, 1.0);
      const Eigen::Vector2d uv = c.ProjectCameraPoint(pc);
      const Eigen::Vector2d xy = c.Undistort(uv);
      EXPECT_NEAR(xy.x(), x, 1e-11);
      EXPECT_NEAR(xy.y(), y, 1e-11);
    }
  }
  // The ray through the projection of a world point passes through the point.
  const Eigen::Vector3d w(0.4, 0.2, 1.1);
  Eigen::Vector2d uv;
  ASSERT_TRUE(c.Project(w, &uv));
  const Eigen::Vector3d d = c.RayDirection(uv);
  const Eigen::Vector3d v = w - c.centre();
  EXPECT_NEAR((v - v.dot(d) * d).norm(), 0.0, 1e-10);
}

TEST(CameraModel, InvalidIntrinsicsAreNamed) {
  reconstruction::CameraIntrinsics k{640, 480, -1, 500, 320, 240};
  std::string error;
  EXPECT_FALSE(k.IsValid(&error));
  EXPECT_NE(error.find("fx"), std::string::npos) << error;
}

TEST(CameraRig, EveryCameraSeesTheVolumeAndRigIsReproducible) {
  sim::CameraRigOptions o;
  const auto rig = sim::MakeCameraRig(o);
  ASSERT_EQ(rig.size(), 8u);
  // Corners of the volume the simulated subject moves in.
  for (const CameraModel& c : rig) {
    std::string error;
    ASSERT_TRUE(c.intrinsics.IsValid(&error)) << error;
    EXPECT_NEAR((c.R * c.R.transpose() - Eigen::Matrix3d::Identity()).norm(), 0, 1e-12);
    EXPECT_GT(c.R.determinant(), 0);
    for (double x : {-1.0, 1.0}) {
      for (double y : {-1.0, 1.0}) {
        for (double z : {0.0, 1.9}) {
          Eigen::Vector2d uv;
          ASSERT_TRUE(c.Project(Eigen::Vector3d(x, y, z), &uv)) << c.id;
          EXPECT_GT(uv.x(), 0) << c.id;
          EXPECT_LT(uv.x(), c.intrinsics.width - 1) << c.id;
          EXPECT_GT(uv.y(), 0) << c.id;
          EXPECT_LT(uv.y(), c.intrinsics.height - 1) << c.id;
        }
      }
    }
  }
  const auto again = sim::MakeCameraRig(o);
  EXPECT_EQ(rig[3].t, again[3].t);
  o.seed = 2;
  EXPECT_NE(sim::MakeCameraRig(o)[3].t, rig[3].t);
}

}  // namespace
}  // namespace mocap
