// The simulated rig of mocapd in one object: N Aravis fake cameras (drivers/aravis_fake.h) whose
// images the renderer (sim/renderer.h) draws of a live virtual subject (sim/live_scene.h), read
// through the same Aravis backend as real cameras — what `mocap capture --simulate` builds around
// a pre-simulated protocol, built here around a subject that does what the operator asks. So a
// simulated rig is a configuration of the daemon ([rig] simulated = N), not a code path of its
// own: the daemon opens its cameras from here and drives the scene with the commands the
// operator gives (wave the wand, lay the L-frame, perform a movement).
//
// The rig's cameras are sim::MakeCameraRig(seed, N) (the truth that a rig calibration is scored
// against), with each camera's id set to its fake's serial (<serial_prefix><index>) — the id
// the AravisCamera reports — so a calibration computed from these cameras matches them by id.
//
// Time: the fakes number images by the tick of the host's real-time clock at rate_hz (a
// hardware-synchronised rig); the renderer's and the scene's sequence origin is the tick at which
// the rig was created, so scene time 0 is the creation. A grabbed frame's tick is
// drivers::SequenceOfTimestamp(frame.device_timestamp_ns, rate_hz) (RenderedSequence): that is
// the sequence to ask the renderer's Truth() about.
//
// Lifetime: the LiveRig must outlive the camera sources it opened (their fake devices draw
// through its renderer).
#pragma once
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "drivers/aravis_fake.h"
#include "drivers/camera_source.h"
#include "drivers/frame.h"
#include "model/status.h"
#include "reconstruction/camera_model.h"
#include "sim/live_scene.h"
#include "sim/protocol.h"
#include "sim/renderer.h"

namespace mocap::sim {

struct LiveRigOptions {
  int cameras = 8;
  int width = 1280, height = 1024;
  double rate_hz = 200.0;
  std::uint64_t seed = 1;            // the rig and the subject (as mocap capture --simulate --seed)
  double centroid_noise_px = 0.1;    // the renderer's centroid jitter
  const Protocol* protocol = nullptr;  // nullptr: DefaultProtocol(); copied
  std::string serial_prefix = "MOCAPSIM";
  // The fakes as PTP cameras (drivers::FakeRigOptions::ptp_features) with their own clocks
  // offset by clock_offsets_ns (per camera; missing: 0).
  bool ptp_features = false;
  std::vector<std::int64_t> clock_offsets_ns;

  bool IsValid(std::string* error) const;
};

class LiveRig {
 public:
  static Status Create(const LiveRigOptions& options, std::unique_ptr<LiveRig>* rig);
  ~LiveRig();
  LiveRig(const LiveRig&) = delete;
  LiveRig& operator=(const LiveRig&) = delete;

  const LiveRigOptions& options() const { return options_; }
  LiveScene& scene() { return *scene_; }
  const LiveScene& scene() const { return *scene_; }
  const Renderer& renderer() const { return *renderer_; }
  drivers::AravisFakeRig& fakes() { return *fakes_; }

  // The true cameras (poses and intrinsics), ids = the cameras' ids.
  const std::vector<reconstruction::CameraModel>& true_cameras() const { return cameras_; }
  // The true cameras with their poses forgotten (R = I, t = 0): what a rig calibration starts
  // from (reconstruction/calibration.h: intrinsics known, extrinsics to find).
  std::vector<reconstruction::CameraModel> IntrinsicsOnly() const;

  // Every camera (in rig order), not yet opened: open each with settings whose frame_rate_hz
  // is rate_hz (the fakes are clocked at rate_hz whatever they are told). A camera made absent
  // (fakes().SetPresent) refuses to open until it is present again.
  std::vector<std::unique_ptr<drivers::AravisCamera>> MakeCameras();

  // The renderer's sequence of a grabbed frame (its clock tick), and its scene time.
  std::uint64_t RenderedSequence(const drivers::Frame& frame) const {
    return drivers::SequenceOfTimestamp(frame.device_timestamp_ns, options_.rate_hz);
  }
  double SceneTimeOf(const drivers::Frame& frame) const {
    return scene_->SceneTimeOf(RenderedSequence(frame));
  }

 private:
  LiveRig() = default;

  LiveRigOptions options_;
  std::vector<reconstruction::CameraModel> cameras_;
  std::shared_ptr<LiveScene> scene_;
  std::unique_ptr<Renderer> renderer_;
  std::unique_ptr<drivers::AravisFakeRig> fakes_;  // after renderer_: destroyed before it
};

}  // namespace mocap::sim
