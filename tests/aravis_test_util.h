// Helpers shared by the Aravis fake-camera tests: an image generator whose every pixel is a
// known function of (camera, sequence), and a check that a delivered frame is exactly that
// image — so a frame with missing packets, or pixels from another frame, cannot pass.
#pragma once
#include <cstdint>
#include <cstring>

#include "drivers/camera_source.h"
#include "drivers/frame.h"

namespace mocap::drivers::testing {

inline std::uint32_t PatternValue(int camera, std::uint64_t sequence, int x, int y) {
  return static_cast<std::uint32_t>(x * 3 + y * 5 + sequence * 7 + camera * 31);
}

// Writes the sequence in the first 8 bytes of row 0 and the pattern everywhere else.
inline void DrawPattern(int camera, std::uint64_t sequence, std::uint8_t* data, int width,
                        int height, std::ptrdiff_t stride, PixelFormat format) {
  for (int y = 0; y < height; ++y) {
    std::uint8_t* row = data + stride * y;
    if (format == PixelFormat::kMono8) {
      for (int x = 0; x < width; ++x) row[x] = PatternValue(camera, sequence, x, y) & 0xFF;
    } else {
      auto* r16 = reinterpret_cast<std::uint16_t*>(row);
      for (int x = 0; x < width; ++x) r16[x] = PatternValue(camera, sequence, x, y) & 0xFFFF;
    }
  }
  if (width * BytesPerPixel(format) >= 8) std::memcpy(data, &sequence, 8);
}

// The sequence the generator stamped, and whether every other pixel matches it.
inline bool CheckPattern(const Frame& f, std::uint64_t* stamped) {
  const ImageView& im = f.image;
  std::uint64_t s = 0;
  std::memcpy(&s, im.data, 8);
  *stamped = s;
  const int skip = 8 / BytesPerPixel(im.format);
  for (int y = 0; y < im.height; ++y) {
    for (int x = (y == 0 ? skip : 0); x < im.width; ++x) {
      const std::uint32_t want = PatternValue(f.camera, s, x, y);
      const std::uint32_t got = im.format == PixelFormat::kMono8 ? im.row8(y)[x] : im.row16(y)[x];
      const std::uint32_t mask = im.format == PixelFormat::kMono8 ? 0xFF : 0xFFFF;
      if (got != (want & mask)) return false;
    }
  }
  return true;
}

// The 16-bit frame id of an unwrapped sequence (its low 16 bits, as FrameIdUnwrapper keeps them).
inline std::uint16_t IdOf(std::uint64_t sequence) {
  return static_cast<std::uint16_t>(sequence & 0xFFFFu);
}

}  // namespace mocap::drivers::testing
