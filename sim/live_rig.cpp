#include "sim/live_rig.h"

#include <chrono>
#include <cmath>
#include <cstdio>

#include "sim/camera_rig.h"

namespace mocap::sim {

bool LiveRigOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& what) {
    if (error) *error = "simulated rig: " + what;
    return false;
  };
  auto show = [](double v) {
    char buf[32];
    std::snprintf(buf, sizeof buf, "%g", v);
    return std::string(buf);
  };
  if (cameras < 2 || cameras > 32)
    return fail("cameras must be in [2, 32] (got " + std::to_string(cameras) + ")");
  // The Aravis fake's sensor is at most 2048 x 2048.
  if (width < 16 || height < 16 || width > 2048 || height > 2048)
    return fail("width and height must be in [16, 2048] (got " + std::to_string(width) + " x " +
                std::to_string(height) + ")");
  if (!(rate_hz >= 1 && rate_hz <= 2000))
    return fail("rate_hz must be in [1, 2000] (got " + show(rate_hz) + ")");
  if (!(centroid_noise_px >= 0 && centroid_noise_px <= 5))
    return fail("centroid_noise_px must be in [0, 5] (got " + show(centroid_noise_px) + ")");
  if (serial_prefix.empty() || serial_prefix.size() > 20)
    return fail("serial_prefix must have 1..20 characters (got '" + serial_prefix + "')");
  return true;
}

Status LiveRig::Create(const LiveRigOptions& options, std::unique_ptr<LiveRig>* out) {
  std::string error;
  if (!options.IsValid(&error)) return Status::Error(error);
  std::unique_ptr<LiveRig> rig(new LiveRig());
  rig->options_ = options;

  CameraRigOptions rig_options;
  rig_options.cameras = options.cameras;
  rig_options.width = options.width;
  rig_options.height = options.height;
  rig_options.seed = options.seed;
  if (!rig_options.IsValid(&error)) return Status::Error("simulated rig: " + error);
  rig->cameras_ = MakeCameraRig(rig_options);

  drivers::FakeRigOptions fake_options;
  fake_options.cameras = options.cameras;
  fake_options.width = options.width;
  fake_options.height = options.height;
  fake_options.clock_sequence_rate_hz = options.rate_hz;
  fake_options.serial_prefix = options.serial_prefix;
  fake_options.ptp_features = options.ptp_features;
  fake_options.clock_offsets_ns = options.clock_offsets_ns;
  if (!fake_options.IsValid(&error)) return Status::Error("simulated rig: " + error);

  // Scene time 0 is the tick at which the rig is created.
  const std::uint64_t origin = drivers::SequenceOfTimestamp(
      static_cast<std::uint64_t>(std::chrono::duration_cast<std::chrono::nanoseconds>(
                                     std::chrono::system_clock::now().time_since_epoch())
                                     .count()),
      options.rate_hz);
  LiveSceneOptions scene_options;
  scene_options.seed = options.seed;
  scene_options.protocol = options.protocol;
  scene_options.rate_hz = options.rate_hz;
  scene_options.sequence_origin = origin;
  MOCAP_RETURN_IF_ERROR(LiveScene::Create(scene_options, &rig->scene_));

  RendererOptions render_options;
  render_options.frame_rate_hz = options.rate_hz;
  render_options.seed = options.seed;
  render_options.centroid_noise_px = options.centroid_noise_px;
  render_options.sequence_origin = origin;
  rig->renderer_ = std::make_unique<Renderer>(rig->cameras_, rig->scene_, render_options);
  if (!rig->renderer_->status()) return rig->renderer_->status();

  rig->fakes_ = std::make_unique<drivers::AravisFakeRig>(fake_options, rig->renderer_->Generator());
  for (int c = 0; c < options.cameras; ++c) rig->cameras_[c].id = rig->fakes_->serial(c);
  *out = std::move(rig);
  return Status::Ok();
}

LiveRig::~LiveRig() = default;

std::vector<reconstruction::CameraModel> LiveRig::IntrinsicsOnly() const {
  std::vector<reconstruction::CameraModel> out = cameras_;
  for (reconstruction::CameraModel& c : out) {
    c.R.setIdentity();
    c.t.setZero();
  }
  return out;
}

std::vector<std::unique_ptr<drivers::AravisCamera>> LiveRig::MakeCameras() {
  std::vector<std::unique_ptr<drivers::AravisCamera>> cameras;
  for (int c = 0; c < fakes_->size(); ++c) cameras.push_back(fakes_->MakeCamera(c));
  return cameras;
}

}  // namespace mocap::sim
