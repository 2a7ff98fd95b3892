#include "reconstruction/reflection_mask.h"

#include <algorithm>
#include <cmath>

#include "reconstruction/detection.h"

namespace mocap::reconstruction {

bool ReflectionMaskOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& what) {
    if (error) *error = "reflection mask options: " + what;
    return false;
  };
  if (threshold < 1 || threshold > 65535)
    return fail("threshold " + std::to_string(threshold) + " is outside [1, 65535]");
  if (margin_px < 0 || margin_px > 1000) return fail("margin_px must be in [0, 1000]");
  if (!(min_fraction > 0 && min_fraction <= 1)) return fail("min_fraction must be in (0, 1]");
  return true;
}

ReflectionMask::ReflectionMask(int width, int height)
    : width_(std::max(width, 0)), height_(std::max(height, 0)),
      bits_(static_cast<std::size_t>(width_) * height_, 0) {}

void ReflectionMask::Set(int x, int y, bool masked) {
  if (x < 0 || y < 0 || x >= width_ || y >= height_) return;
  bits_[static_cast<std::size_t>(y) * width_ + x] = masked ? 1 : 0;
}

int ReflectionMask::masked_pixels() const {
  return static_cast<int>(std::count(bits_.begin(), bits_.end(), std::uint8_t{1}));
}

Status ReflectionMaskBuilder::Add(const drivers::ImageView& image) {
  MOCAP_RETURN_IF_ERROR(CheckImage(image));
  std::string error;
  if (!options_.IsValid(&error)) return Status::Error(error);
  const int max_value = (1 << drivers::BitDepth(image.format)) - 1;
  if (options_.threshold > max_value)
    return Status::Error("reflection mask: threshold " + std::to_string(options_.threshold) +
                         " is above the largest " + drivers::ToString(image.format) + " value " +
                         std::to_string(max_value));
  if (frames_ == 0) {
    width_ = image.width;
    height_ = image.height;
    format_ = image.format;
    counts_.assign(static_cast<std::size_t>(width_) * height_, 0);
  } else if (image.width != width_ || image.height != height_ || image.format != format_) {
    return Status::Error("reflection mask: frame " + std::to_string(frames_ + 1) + " is " +
                         std::to_string(image.width) + " x " + std::to_string(image.height) + " " +
                         drivers::ToString(image.format) + ", the first was " +
                         std::to_string(width_) + " x " + std::to_string(height_) + " " +
                         drivers::ToString(format_));
  }
  const int t = options_.threshold;
  for (int y = 0; y < height_; ++y) {
    std::uint16_t* c = counts_.data() + static_cast<std::size_t>(y) * width_;
    if (format_ == drivers::PixelFormat::kMono8) {
      const std::uint8_t* row = image.row8(y);
      for (int x = 0; x < width_; ++x) c[x] += (row[x] >= t && c[x] < 0xFFFF);
    } else {
      const std::uint16_t* row = image.row16(y);
      for (int x = 0; x < width_; ++x) c[x] += (row[x] >= t && c[x] < 0xFFFF);
    }
  }
  ++frames_;
  return Status::Ok();
}

Status ReflectionMaskBuilder::Build(ReflectionMask* mask) const {
  if (mask == nullptr) return Status::Error("reflection mask: output is null");
  if (frames_ == 0) return Status::Error("reflection mask: no frame of the empty volume was added");
  const int need = std::max(
      1, static_cast<int>(std::ceil(options_.min_fraction * std::min(frames_, 0xFFFF) - 1e-9)));
  const int w = width_, h = height_, r = options_.margin_px;
  // Seed pixels, then a separable square dilation: rows (running window over x), then columns.
  std::vector<std::uint8_t> seed(static_cast<std::size_t>(w) * h), rows(seed.size());
  for (std::size_t i = 0; i < seed.size(); ++i) seed[i] = counts_[i] >= need;
  for (int y = 0; y < h; ++y) {
    const std::uint8_t* s = seed.data() + static_cast<std::size_t>(y) * w;
    std::uint8_t* o = rows.data() + static_cast<std::size_t>(y) * w;
    // last: the x of the last seed pixel seen so far (left to right), first pass marks
    // [last - r, last + r].
    int last = -1 - 2 * r - 1;
    for (int x = 0; x < w; ++x) {
      if (s[x]) last = x;
      o[x] = (x - last) <= r;
    }
    int next = w + 2 * r + 1;
    for (int x = w - 1; x >= 0; --x) {
      if (s[x]) next = x;
      if (next - x <= r) o[x] = 1;
    }
  }
  ReflectionMask out(w, h);
  for (int x = 0; x < w; ++x) {
    int last = -1 - 2 * r - 1;
    for (int y = 0; y < h; ++y) {
      if (rows[static_cast<std::size_t>(y) * w + x]) last = y;
      out.bits_[static_cast<std::size_t>(y) * w + x] = (y - last) <= r;
    }
    int next = h + 2 * r + 1;
    for (int y = h - 1; y >= 0; --y) {
      if (rows[static_cast<std::size_t>(y) * w + x]) next = y;
      if (next - y <= r) out.bits_[static_cast<std::size_t>(y) * w + x] = 1;
    }
  }
  *mask = std::move(out);
  return Status::Ok();
}

}  // namespace mocap::reconstruction
