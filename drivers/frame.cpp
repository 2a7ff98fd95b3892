#include <cmath>
#include <string>

#include "drivers/camera_source.h"
#include "drivers/frame.h"

namespace mocap::drivers {

const char* ToString(PixelFormat f) {
  switch (f) {
    case PixelFormat::kMono8: return "Mono8";
    case PixelFormat::kMono12: return "Mono12";
    case PixelFormat::kMono16: return "Mono16";
    case PixelFormat::kMono12Packed: return "Mono12Packed";
  }
  return "unknown";
}

void UnpackMono12Packed(const std::uint8_t* packed, std::size_t packed_stride, int width,
                        int height, std::uint16_t* out, std::size_t out_stride_bytes) {
  for (int y = 0; y < height; ++y) {
    const std::uint8_t* in = packed + packed_stride * y;
    auto* row = reinterpret_cast<std::uint16_t*>(reinterpret_cast<std::uint8_t*>(out) +
                                                 out_stride_bytes * y);
    int x = 0;
    for (; x + 1 < width; x += 2, in += 3) {
      row[x] = static_cast<std::uint16_t>(in[0] << 4 | (in[1] & 0x0F));
      row[x + 1] = static_cast<std::uint16_t>(in[2] << 4 | in[1] >> 4);
    }
    if (x < width) row[x] = static_cast<std::uint16_t>(in[0] << 4 | (in[1] & 0x0F));
  }
}

const char* ToString(FrameStatus s) {
  switch (s) {
    case FrameStatus::kComplete: return "complete";
    case FrameStatus::kMissingPackets: return "missing packets";
    case FrameStatus::kTimeout: return "timeout";
    case FrameStatus::kUnderrun: return "underrun";
    case FrameStatus::kSizeMismatch: return "size mismatch";
    case FrameStatus::kWrongFormat: return "wrong pixel format";
    case FrameStatus::kOther: return "other error";
  }
  return "unknown";
}

const char* ToString(TriggerMode m) {
  switch (m) {
    case TriggerMode::kFreeRun: return "free run";
    case TriggerMode::kHardwareLine: return "hardware line";
    case TriggerMode::kSoftware: return "software";
  }
  return "unknown";
}

const char* ToString(PtpSchedule s) {
  return s == PtpSchedule::kSyncFreeRun ? "sync-free-run" : "none";
}

bool ParsePtpSchedule(const std::string& text, PtpSchedule* schedule) {
  if (text == "sync-free-run") *schedule = PtpSchedule::kSyncFreeRun;
  else if (text == "none") *schedule = PtpSchedule::kNone;
  else return false;
  return true;
}

const char* ToString(CameraState s) {
  switch (s) {
    case CameraState::kClosed: return "closed";
    case CameraState::kStreaming: return "streaming";
    case CameraState::kLost: return "lost";
  }
  return "unknown";
}

bool CameraSettings::IsValid(std::string* error) const {
  auto fail = [&](const std::string& what) {
    if (error) *error = "camera settings: " + what;
    return false;
  };
  if (!(exposure_us > 0) || !std::isfinite(exposure_us)) return fail("exposure_us must be > 0");
  if (!std::isfinite(gain_db) || gain_db < 0) return fail("gain_db must be >= 0");
  if (!(frame_rate_hz > 0) || !std::isfinite(frame_rate_hz)) {
    return fail("frame_rate_hz must be > 0");
  }
  if (exposure_us * 1e-6 > 1.0 / frame_rate_hz) {
    return fail("exposure_us is longer than one frame period at frame_rate_hz");
  }
  if (roi_x < 0 || roi_y < 0 || roi_width < 0 || roi_height < 0) {
    return fail("ROI offsets and sizes must be >= 0");
  }
  if (trigger_line < 0) return fail("trigger_line must be >= 0");
  if (buffer_count < 2) return fail("buffer_count must be >= 2");
  if (!(timeout_ms > 0)) return fail("timeout_ms must be > 0");
  if (std::string why; !usb.IsValid(&why)) return fail(why);
  return true;
}

}  // namespace mocap::drivers
