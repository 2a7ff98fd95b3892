// Simulated wand calibration: an operator waves a 3-marker wand through the capture volume, then
// lays the L-frame on the floor; the TRUE rig (sim/camera_rig.h) sees both.
//
// The wand's path is smooth and random: each coordinate of its centre and of its direction is a
// sum of a few sinusoids with random frequencies (0.05–0.4 Hz) and phases, scaled to the volume,
// so the wand sweeps the whole volume in every orientation, as an operator is told to. The
// detections are what 2D detection would hand over: UNLABELLED centroids in random order, with
// N(0, noise_px) per axis, a few stray reflections per image, markers behind a camera or outside
// its image unseen, markers whose images nearly coincide merged into one centroid (a wand pointing
// at a camera), and random whole-image dropouts. So calibration has to find the wand in every
// image itself (reconstruction/calibration.h: IdentifyWand).
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <string>
#include <vector>

#include "model/status.h"
#include "reconstruction/calibration.h"
#include "reconstruction/camera_model.h"
#include "reconstruction/centroid.h"

namespace mocap::sim {

struct WandSimulationOptions {
  double duration_s = 30.0;
  double rate_hz = 100.0;
  int subsample = 5;  // keep every n-th frame (30 s at 100 Hz -> 600 frames)
  Eigen::Vector3d volume_centre_m = {0.0, 0.0, 1.0};
  Eigen::Vector3d volume_half_size_m = {1.0, 1.0, 0.8};  // the wand centre stays inside
  double noise_px = 0.1;   // centroid noise, standard deviation per image axis
  double merge_px = 3.0;   // marker images closer than this merge into one centroid
  double dropout = 0.01;   // probability that a camera's image of a frame is lost
  int max_strays = 2;      // stray centroids per image: uniform in [0, max_strays]
  int lframe_frames = 50;  // static frames of the L-frame (0: none)
  reconstruction::Wand wand;
  reconstruction::LFrame lframe;
  std::uint64_t seed = 1;

  bool IsValid(std::string* error) const;
};

struct WandSimulation {
  std::vector<reconstruction::DetectionSet> wand_frames;
  std::vector<reconstruction::DetectionSet> lframe_frames;
  // Ground truth: the wand's markers (world, metres) at every kept frame, in Wand order.
  std::vector<std::vector<Eigen::Vector3d>> wand_markers;
};

// The wand's smooth random path as a function of time: each coordinate of the centre, and of the
// direction, is a sum of a few sinusoids of random frequency (0.05–0.4 Hz), phase and amplitude,
// drawn from (seed, Stream::kWand). SimulateWand samples it; the live simulated rig
// (sim/live_scene.h) evaluates it at the time each camera takes its image.
class WandPath {
 public:
  // The path of SimulateWand(options) (its seed, volume and wand).
  explicit WandPath(const WandSimulationOptions& options);
  WandPath(std::uint64_t seed, const Eigen::Vector3d& volume_centre_m,
           const Eigen::Vector3d& volume_half_size_m, const reconstruction::Wand& wand);

  // The wand's three markers (world, metres, in Wand order) at time t. No allocation.
  void Markers(double t, Eigen::Vector3d markers[3]) const;

 private:
  // A smooth random signal in [-1, 1].
  struct Signal {
    static constexpr int kTerms = 4;
    double freq[kTerms], phase[kTerms], amp[kTerms];
    double operator()(double t) const;
  };
  Eigen::Vector3d centre_m_, half_size_m_;
  double offsets_m_[3];  // each marker's position along the wand from the wand's mean
  Signal centre_[3], direction_[3];
};

// Simulates with the rig `truth` (the cameras' true poses and intrinsics).
Status SimulateWand(const std::vector<reconstruction::CameraModel>& truth,
                    const WandSimulationOptions& options, WandSimulation* out);

}  // namespace mocap::sim
