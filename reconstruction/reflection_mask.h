// Static-reflection mask: the parts of a camera's image that are bright while the capture volume
// is EMPTY (another camera's strobe ring, a shiny screw, a window), learnt once and used to drop
// the detections that fall on them.
//
// Learning: for each pixel, the number of empty-volume frames in which it was >= threshold. A
// pixel bright in at least `min_fraction` of the frames is a reflection pixel (a fraction, not
// "ever", so that one noise spike does not punch a hole; not "always", so that a reflection
// flickering around the threshold is still caught). The reflection pixels are then dilated by
// `margin_px` (a square of side 2 margin + 1, i.e. Chebyshev distance, done as two separable
// running-maximum passes): a reflection's extent changes with noise, exposure and vibration of
// the camera, and its edge pixels may be below the threshold in the learning frames.
//
// Use: DetectMarkers drops a blob whose CENTROID (rounded to a pixel) lies in the mask. It does
// not clip pixels out of blobs: a marker passing next to a reflection keeps all its pixels and an
// unbiased centre, and only a blob centred on a reflection is dropped. A marker whose image merges
// with a reflection is one blob for detection; it is dropped when the merged centre falls in the
// mask, and triangulation's reprojection check has to reject it otherwise.
#pragma once
#include <cstdint>
#include <string>
#include <vector>

#include "drivers/frame.h"
#include "model/status.h"

namespace mocap::reconstruction {

struct ReflectionMaskOptions {
  int threshold = 64;          // image units, as DetectionOptions::threshold (use the same or lower)
  int margin_px = 3;           // dilation of the reflection pixels
  double min_fraction = 0.25;  // of the learning frames in which a pixel must be bright

  bool IsValid(std::string* error) const;
};

class ReflectionMask {
 public:
  ReflectionMask() = default;
  // An empty (all-clear) mask of this size.
  ReflectionMask(int width, int height);

  int width() const { return width_; }
  int height() const { return height_; }
  bool empty() const { return width_ == 0; }
  // False outside the image.
  bool Contains(int x, int y) const {
    if (x < 0 || y < 0 || x >= width_ || y >= height_) return false;
    return bits_[static_cast<std::size_t>(y) * width_ + x] != 0;
  }
  void Set(int x, int y, bool masked);
  int masked_pixels() const;

 private:
  friend class ReflectionMaskBuilder;
  int width_ = 0, height_ = 0;
  std::vector<std::uint8_t> bits_;  // one byte per pixel, row-major
};

// Accumulates frames of the empty volume, then builds the mask.
class ReflectionMaskBuilder {
 public:
  explicit ReflectionMaskBuilder(const ReflectionMaskOptions& options = {}) : options_(options) {}
  // The first frame fixes the size and pixel format; later frames must match. Errors: invalid
  // image or options, threshold beyond the bit depth, a frame of another size or format.
  Status Add(const drivers::ImageView& image);
  int frames() const { return frames_; }
  // Error when no frame was added.
  Status Build(ReflectionMask* mask) const;

 private:
  ReflectionMaskOptions options_;
  int frames_ = 0;
  int width_ = 0, height_ = 0;
  drivers::PixelFormat format_ = drivers::PixelFormat::kMono8;
  std::vector<std::uint16_t> counts_;  // frames in which each pixel was bright (saturating)
};

}  // namespace mocap::reconstruction
