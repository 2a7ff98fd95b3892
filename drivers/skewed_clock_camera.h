// A camera whose clock is not the host's: wraps any CameraSource and rewrites each frame's device
// timestamp as a clock with its own offset and rate would have stamped it,
//   device' = device + offset_ns + drift_ppm x 1e-6 x (device - the first frame's device time).
// and, with `arrival_wait_us`, its arrival as a transport that makes frames wait would report
// it: received_ns (and host_timestamp_ns) later by an exponential wait of that mean, which only
// ever adds (the lower envelope the clock fit relies on stays the fake's exact arrival).
// The images, ids and every other field are the wrapped camera's.
//
// Why: the simulated rig's Aravis fakes all stamp with the host's real-time clock (one clock, as
// a PTP-locked rig), so a free-running rig of cameras with clocks of their own, whose offsets
// and drifts the sync must fit (reconstruction/clock_fit.h), cannot be had from them. Wrapped,
// they can, and the daemon's tests check that the rig check (mocapctl cameras --check) reports
// the offset and drift that were put in ([[rig.camera]] sim_clock_offset_ms, sim_clock_drift_ppm,
// sim_arrival_wait_us): Aravis's fakes report a frame received the instant it was taken, which
// would leave the fit nothing to estimate.
#pragma once
#include <cstdint>
#include <memory>
#include <random>

#include "drivers/camera_source.h"

namespace mocap::drivers {

struct ClockSkew {
  std::int64_t offset_ns = 0;
  double drift_ppm = 0;  // > 0: the clock runs fast
  double arrival_wait_us = 0;  // mean of the exponential wait added to each arrival; 0: none
  std::uint64_t seed = 1;
};

class SkewedClockCamera final : public CameraSource {
 public:
  SkewedClockCamera(std::unique_ptr<CameraSource> camera, ClockSkew skew)
      : camera_(std::move(camera)), skew_(skew), rng_(skew.seed) {}

  const std::string& id() const override { return camera_->id(); }
  Status Open(const CameraSettings& settings) override { return camera_->Open(settings); }
  Status Start() override { return camera_->Start(); }
  void Stop() override { camera_->Stop(); }
  GrabResult Grab(Frame* frame) override;
  void Release(const Frame& frame) override { camera_->Release(frame); }
  Status Trigger() override { return camera_->Trigger(); }
  CameraState State() const override { return camera_->State(); }
  const CameraCounters& Counters() const override { return camera_->Counters(); }
  CameraSource& wrapped() { return *camera_; }

 private:
  std::unique_ptr<CameraSource> camera_;
  ClockSkew skew_;
  bool have_origin_ = false;  // the grab thread's
  std::uint64_t origin_ns_ = 0;
  std::mt19937_64 rng_;
};

}  // namespace mocap::drivers
