#include "sim/camera_rig.h"

#include <cmath>

#include "sim/random.h"

namespace mocap::sim {

bool CameraRigOptions::IsValid(std::string* error) const {
  auto fail = [&](const char* what) {
    if (error) *error = std::string("camera rig: ") + what;
    return false;
  };
  if (cameras < 2 || cameras > 64) return fail("cameras must be in [2, 64]");
  if (width < 16 || height < 16 || width > 16384 || height > 16384) {
    return fail("width and height must be in [16, 16384]");
  }
  if (!(focal_px > 0)) return fail("focal_px must be > 0");
  if (!(ring_radius_m > 1.5)) return fail("ring_radius_m must be > 1.5 (outside the volume)");
  if (!(aim_jitter_m >= 0) || !(distortion >= 0) || distortion > 0.3) {
    return fail("aim_jitter_m must be >= 0 and distortion in [0, 0.3]");
  }
  return true;
}

std::vector<reconstruction::CameraModel> MakeCameraRig(const CameraRigOptions& o) {
  Random rng(o.seed, Stream::kRig);
  std::vector<reconstruction::CameraModel> rig(o.cameras);
  for (int i = 0; i < o.cameras; ++i) {
    reconstruction::CameraModel& cam = rig[i];
    cam.id = "sim-" + std::to_string(i);
    reconstruction::CameraIntrinsics& k = cam.intrinsics;
    k.width = o.width;
    k.height = o.height;
    k.fx = o.focal_px * rng.Uniform(0.98, 1.02);
    k.fy = k.fx * rng.Uniform(0.999, 1.001);
    k.cx = 0.5 * (o.width - 1) + rng.Uniform(-8, 8);
    k.cy = 0.5 * (o.height - 1) + rng.Uniform(-8, 8);
    k.k1 = -o.distortion * rng.Uniform(0.5, 1.0);
    k.k2 = 0.2 * o.distortion * rng.Uniform(-1, 1);
    k.p1 = 0.01 * o.distortion * rng.Uniform(-1, 1);
    k.p2 = 0.01 * o.distortion * rng.Uniform(-1, 1);
    k.k3 = 0.0;

    const double angle = 2 * M_PI * (i + 0.5) / o.cameras + rng.Uniform(-0.1, 0.1);
    const Eigen::Vector3d centre(o.ring_radius_m * std::cos(angle),
                                 o.ring_radius_m * std::sin(angle),
                                 (i % 2 == 0) ? o.low_height_m : o.high_height_m);
    const Eigen::Vector3d aim(rng.Uniform(-1, 1) * o.aim_jitter_m,
                              rng.Uniform(-1, 1) * o.aim_jitter_m,
                              o.aim_height_m + rng.Uniform(-1, 1) * o.aim_jitter_m);
    // Camera axes in the world: z along the view, x to the image's right (horizontal), y down.
    const Eigen::Vector3d z = (aim - centre).normalized();
    const Eigen::Vector3d x = z.cross(Eigen::Vector3d::UnitZ()).normalized();
    const Eigen::Vector3d y = z.cross(x);
    Eigen::Matrix3d cam_to_world;
    cam_to_world << x, y, z;
    cam.R = cam_to_world.transpose();
    cam.t = -cam.R * centre;
  }
  return rig;
}

}  // namespace mocap::sim
