#include "drivers/skewed_clock_camera.h"

#include <cmath>

namespace mocap::drivers {

GrabResult SkewedClockCamera::Grab(Frame* frame) {
  const GrabResult r = camera_->Grab(frame);
  if (r != GrabResult::kFrame) return r;
  if (!have_origin_) {
    have_origin_ = true;
    origin_ns_ = frame->device_timestamp_ns;
  }
  const double since = static_cast<double>(static_cast<std::int64_t>(frame->device_timestamp_ns - origin_ns_));
  frame->device_timestamp_ns = static_cast<std::uint64_t>(
      static_cast<std::int64_t>(frame->device_timestamp_ns) + skew_.offset_ns +
      std::llround(skew_.drift_ppm * 1e-6 * since));
  if (skew_.arrival_wait_us > 0) {
    const auto wait_ns = static_cast<std::uint64_t>(
        std::exponential_distribution<double>(1.0 / (skew_.arrival_wait_us * 1e3))(rng_));
    if (frame->received_ns != 0) frame->received_ns += wait_ns;
    frame->host_timestamp_ns += wait_ns;
  }
  return r;
}

}  // namespace mocap::drivers
