// Frames: what every camera source (drivers/camera_source.h) hands to detection.
//
// A Frame is a VIEW of one image in a buffer that the source owns (Aravis: a stream buffer of the
// pre-allocated pool; simulated: a ring of images). It stays valid until the frame is released
// back to the source, so detection reads the pixels in place: no copy on the hot path.
//
// Frame ids: GigE Vision 1.x and USB3 Vision block ids as Aravis reports them are 16 bit on GigE
// (they wrap every 65,536 frames, ~5.5 min at 200 Hz) and the sources extend them to a 64-bit
// `sequence` (FrameIdUnwrapper below), which is what sync across cameras uses.
#pragma once
#include <cstddef>
#include <cstdint>
#include <ctime>
#include <cstring>

namespace mocap::drivers {

// kMono12Packed is a format on the wire only (GigE Vision's Mono12Packed: two pixels in three
// bytes, a quarter less bandwidth than Mono12): the source unpacks it, and the frames it hands
// out are Mono12 (16-bit words), which is what BytesPerPixel and BitDepth describe.
enum class PixelFormat : std::uint8_t { kMono8, kMono12, kMono16, kMono12Packed };

inline int BytesPerPixel(PixelFormat f) { return f == PixelFormat::kMono8 ? 1 : 2; }
inline int BitDepth(PixelFormat f) {
  return f == PixelFormat::kMono8 ? 8 : (f == PixelFormat::kMono16 ? 16 : 12);
}
// Bytes of one row as the camera sends it.
inline std::size_t WireRowBytes(PixelFormat f, int width) {
  return f == PixelFormat::kMono12Packed ? (static_cast<std::size_t>(width) * 3 + 1) / 2
                                         : static_cast<std::size_t>(width) * BytesPerPixel(f);
}
// Unpacks GigE Vision Mono12Packed rows (per pixel pair: byte 0 = p0 bits 11..4, byte 1 = p1
// bits 3..0 << 4 | p0 bits 3..0, byte 2 = p1 bits 11..4) into 16-bit words.
void UnpackMono12Packed(const std::uint8_t* packed, std::size_t packed_stride, int width,
                        int height, std::uint16_t* out, std::size_t out_stride_bytes);
const char* ToString(PixelFormat f);

// Why a buffer did or did not become a usable frame. Only kComplete frames reach detection; the
// others are counted per camera (CameraCounters) and never parsed.
enum class FrameStatus : std::uint8_t {
  kComplete,
  kMissingPackets,  // GigE Vision packets lost (ARV_BUFFER_STATUS_MISSING_PACKETS)
  kTimeout,         // the buffer was not filled in time
  kUnderrun,        // no free buffer when the image arrived
  kSizeMismatch,    // payload does not match width x height x bytes per pixel
  kWrongFormat,     // pixel format other than the configured one
  kOther,
};
const char* ToString(FrameStatus s);

// A row-major image, stride in bytes. Mono12 is stored unpacked in 16-bit little-endian words.
struct ImageView {
  const std::uint8_t* data = nullptr;
  int width = 0;
  int height = 0;
  std::ptrdiff_t stride = 0;  // bytes from one row to the next
  PixelFormat format = PixelFormat::kMono8;

  std::size_t size_bytes() const { return static_cast<std::size_t>(stride) * height; }
  const std::uint8_t* row8(int y) const { return data + stride * y; }
  const std::uint16_t* row16(int y) const {
    return reinterpret_cast<const std::uint16_t*>(data + stride * y);
  }
};

// The host clock of Frame::host_timestamp_ns and of every latency figure: CLOCK_MONOTONIC, ns.
inline std::uint64_t MonotonicNs() {
  timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return static_cast<std::uint64_t>(ts.tv_sec) * 1000000000ull + ts.tv_nsec;
}

// The index of the frame-period tick a device timestamp falls in, at `rate_hz`: the frame's
// number on a rig whose cameras share one clock and expose on its ticks (PTP; Aravis's fakes).
inline std::uint64_t SequenceOfTimestamp(std::uint64_t timestamp_ns, double rate_hz) {
  return static_cast<std::uint64_t>(static_cast<long double>(timestamp_ns) * rate_hz / 1e9L);
}

struct Frame {
  int camera = -1;                  // index of the camera in the rig
  std::uint16_t frame_id = 0;       // as the device numbers it (wraps)
  std::uint64_t sequence = 0;       // frame_id unwrapped (FrameIdUnwrapper)
  std::uint64_t device_timestamp_ns = 0;
  std::uint64_t host_timestamp_ns = 0;  // CLOCK_MONOTONIC when the source handed the buffer over
  // CLOCK_MONOTONIC when the transport began receiving the image (Aravis: the buffer's system
  // timestamp), earlier than host_timestamp_ns by the wait in the driver's queue; 0: unknown
  // (then host_timestamp_ns). Latency figures and clock fits start here; the sync's timeouts
  // count from host_timestamp_ns, when the pipeline could first have the frame.
  std::uint64_t received_ns = 0;
  std::uint32_t stream_epoch = 0;  // set by the capture pipeline: +1 after each loss of the camera
  FrameStatus status = FrameStatus::kComplete;
  ImageView image;
  const void* handle = nullptr;     // the source's buffer, for CameraSource::Release
};

// Extends 16-bit frame ids to a monotonic 64-bit sequence. A step back of more than half the
// range is a wrap; a smaller step back (a stale or repeated id) returns the sequence it maps to
// without advancing.
class FrameIdUnwrapper {
 public:
  std::uint64_t Next(std::uint16_t id) {
    if (!started_) {
      started_ = true;
      last_ = id;
      base_ = 0;
      return id;
    }
    const std::uint16_t delta = static_cast<std::uint16_t>(id - last_);
    if (delta < 0x8000u) {
      if (id < last_) base_ += 0x10000u;
      last_ = id;
      return base_ + id;
    }
    // A step backwards: place it before the last id without moving the base.
    const std::uint64_t last_seq = base_ + last_;
    const std::uint64_t back = static_cast<std::uint16_t>(last_ - id);
    return last_seq >= back ? last_seq - back : 0;
  }

 private:
  bool started_ = false;
  std::uint16_t last_ = 0;
  std::uint64_t base_ = 0;
};

}  // namespace mocap::drivers
