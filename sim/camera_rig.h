// The simulated camera rig: N cameras on a ring around the capture volume, as a lab mounts them
// on the walls, alternately high and low so that every marker is seen from above and from the
// side; each aims at a point near the volume's centre with a small random error, and has a lens
// with small random distortion. The same seed gives the same rig. The volume is the one the
// simulated subject moves in (sim/simulate.h: within about 1 m of the origin, 0 to 2 m high).
#pragma once
#include <cstdint>
#include <string>
#include <vector>

#include "reconstruction/camera_model.h"

namespace mocap::sim {

struct CameraRigOptions {
  int cameras = 8;
  int width = 1280;
  int height = 1024;
  double focal_px = 1000.0;     // about 65 x 54 degrees at 1280 x 1024
  double ring_radius_m = 3.5;
  double low_height_m = 1.6;    // even cameras
  double high_height_m = 2.8;   // odd cameras
  double aim_height_m = 0.9;
  double aim_jitter_m = 0.15;   // random offset of each camera's aim point
  double distortion = 0.05;     // |k1| at most; k2, p1, p2 proportionally smaller
  std::uint64_t seed = 1;

  bool IsValid(std::string* error) const;
};

std::vector<reconstruction::CameraModel> MakeCameraRig(const CameraRigOptions& options);

}  // namespace mocap::sim
