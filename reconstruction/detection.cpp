#include "reconstruction/detection.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>

#include <Eigen/Cholesky>

#include "reconstruction/reflection_mask.h"

#if defined(__AVX2__)
#include <immintrin.h>
#endif

namespace mocap::reconstruction {

bool DetectionOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& what) {
    if (error) *error = "detection options: " + what;
    return false;
  };
  if (threshold < 1 || threshold > 65535)
    return fail("threshold " + std::to_string(threshold) + " is outside [1, 65535]");
  if (min_area_px < 1) return fail("min_area_px must be >= 1");
  if (max_area_px < min_area_px) return fail("max_area_px is below min_area_px");
  if (!(min_roundness >= 0 && min_roundness <= 1))
    return fail("min_roundness must be in [0, 1]");
  if (!(overlap_roundness >= 0 && overlap_roundness <= 1))
    return fail("overlap_roundness must be in [0, 1]");
  if (!(split_min_roundness >= 0 && split_min_roundness <= 1))
    return fail("split_min_roundness must be in [0, 1]");
  if (!(split_min_separation_px > 0) || !std::isfinite(split_min_separation_px))
    return fail("split_min_separation_px must be finite and > 0");
  if (!(split_min_gain > 0 && split_min_gain <= 1))
    return fail("split_min_gain must be in (0, 1]");
  if (!(read_noise_dn >= 0) || !std::isfinite(read_noise_dn))
    return fail("read_noise_dn must be finite and >= 0");
  if (!(shot_noise_gain >= 0) || !std::isfinite(shot_noise_gain))
    return fail("shot_noise_gain must be finite and >= 0");
  if (!(sigma_floor_px >= 0) || !std::isfinite(sigma_floor_px))
    return fail("sigma_floor_px must be finite and >= 0");
  if (max_centroids < 1) return fail("max_centroids must be >= 1");
  if (saturation_level < 0 || saturation_level > 65535)
    return fail("saturation_level " + std::to_string(saturation_level) + " is outside [0, 65535]");
  if (centroid != CentroidMethod::kThresholdWeighted && centroid != CentroidMethod::kGaussianWindowed)
    return fail("unknown centroid method");
  if (!std::isfinite(background_dn) || background_dn < 0 || background_dn >= threshold)
    return fail("background_dn must be finite, >= 0 and below the threshold");
  return true;
}

Status CheckImage(const drivers::ImageView& image) {
  const auto format = static_cast<int>(image.format);
  if (format < 0 || format > static_cast<int>(drivers::PixelFormat::kMono16))
    return Status::Error("image: unknown pixel format " + std::to_string(format) +
                         " (expected Mono8, Mono12 or Mono16)");
  if (image.data == nullptr) return Status::Error("image: null pixel data");
  if (image.width <= 0 || image.height <= 0)
    return Status::Error("image: size " + std::to_string(image.width) + " x " +
                         std::to_string(image.height) + " is not positive");
  const std::ptrdiff_t row_bytes =
      static_cast<std::ptrdiff_t>(image.width) * drivers::BytesPerPixel(image.format);
  if (image.stride < row_bytes)
    return Status::Error("image: stride " + std::to_string(image.stride) + " bytes is below width " +
                         std::to_string(image.width) + " x " +
                         std::to_string(drivers::BytesPerPixel(image.format)) + " bytes (" +
                         drivers::ToString(image.format) + ")");
  if (image.format != drivers::PixelFormat::kMono8 &&
      ((image.stride % 2) != 0 || reinterpret_cast<std::uintptr_t>(image.data) % 2 != 0))
    return Status::Error("image: " + std::string(drivers::ToString(image.format)) +
                         " rows must start on 2-byte boundaries (stride " +
                         std::to_string(image.stride) + ", data at an odd address?)");
  return Status::Ok();
}

void DetectionWorkspace::Reserve(int max_runs_per_row, int max_blobs) {
  previous_.reserve(static_cast<std::size_t>(std::max(max_runs_per_row, 0)));
  current_.reserve(static_cast<std::size_t>(std::max(max_runs_per_row, 0)));
  parent_.reserve(static_cast<std::size_t>(std::max(max_blobs, 0)));
  candidates_.reserve(static_cast<std::size_t>(std::max(max_blobs, 0)));
  queue_.reserve(static_cast<std::size_t>(std::max(max_blobs, 0)));
  blobs_.reserve(static_cast<std::size_t>(std::max(max_blobs, 0)));
  for (std::vector<double>* v : {&gx_, &gy_, &gxd_, &gxdd_, &gxd2_}) v->reserve(128);
  window_.reserve(128 * 128);
}

std::size_t DetectionWorkspace::CapacityBytes() const {
  return (previous_.capacity() + current_.capacity()) * sizeof(Run) +
         parent_.capacity() * sizeof(int) + blobs_.capacity() * sizeof(Blob) +
         candidates_.capacity() * sizeof(Candidate) + queue_.capacity() * sizeof(int) +
         (gx_.capacity() + gy_.capacity() + gxd_.capacity() + gxdd_.capacity() + gxd2_.capacity() +
          window_.capacity()) * sizeof(double);
}

namespace {

// Walks the bright-pixel bit mask of a block of `nbits` (<= 64) pixels starting at x = base
// (bit i: pixel base + i is bright) and emits its runs [x0, x1). `open` is the start of a run
// that continues from the previous block, or -1; a run reaching the end of the block stays open.
template <class Emit>
inline void WalkMask(std::uint64_t m, int base, int nbits, int* open, Emit& emit) {
  const std::uint64_t valid = nbits == 64 ? ~0ull : ((1ull << nbits) - 1);
  if (*open >= 0) {
    const std::uint64_t zeros = ~m & valid;
    if (zeros == 0) return;  // the whole block is bright: the run goes on
    const int e = __builtin_ctzll(zeros);
    emit(*open, base + e);
    *open = -1;
    m &= ~0ull << e;
  }
  while (m != 0) {
    const int s = __builtin_ctzll(m);
    const std::uint64_t zeros = ~m & valid & (~0ull << s);
    if (zeros == 0) {
      *open = base + s;
      return;
    }
    const int e = __builtin_ctzll(zeros);
    emit(base + s, base + e);
    m &= ~0ull << e;
  }
}

// Four doubles (AVX2 where the target has it; GCC/Clang lower it to pairs of SSE2 otherwise).
typedef double V4 __attribute__((vector_size(32)));
inline V4 Load4(const double* p) {
  V4 v;
  std::memcpy(&v, p, sizeof(v));
  return v;
}
inline double Sum4(V4 v) { return (v[0] + v[1]) + (v[2] + v[3]); }

// The tail of a row (fewer than 64 pixels), scalar.
template <class P, class Emit>
inline void ScanTail(const P* row, int x, int width, int threshold, int* open, Emit& emit) {
  while (x < width) {
    const int n = std::min(64, width - x);
    std::uint64_t m = 0;
    for (int i = 0; i < n; ++i) m |= static_cast<std::uint64_t>(row[x + i] >= threshold) << i;
    WalkMask(m, x, n, open, emit);
    x += n;
  }
  if (*open >= 0) {
    emit(*open, width);
    *open = -1;
  }
}

// Portable scan: GCC/Clang vector extensions (32-byte vectors, lowered to whatever the target has).
template <class P, class Emit>
void ScanRowPortable(const P* row, int width, int threshold, Emit& emit) {
  constexpr int kLanes = 32 / sizeof(P);
  typedef P Vec __attribute__((vector_size(32)));
  Vec vt;
  for (int i = 0; i < kLanes; ++i) vt[i] = static_cast<P>(threshold);
  int open = -1;
  int x = 0;
  for (; x + 64 <= width; x += 64) {
    std::uint64_t any = 0;
    for (int k = 0; k < 64; k += kLanes) {
      Vec v;
      std::memcpy(&v, row + x + k, 32);
      const auto ge = v >= vt;  // lanes of all ones where bright
      std::uint64_t words[4];
      std::memcpy(words, &ge, 32);
      any |= words[0] | words[1] | words[2] | words[3];
    }
    if (any == 0) {
      if (open >= 0) {
        emit(open, x);
        open = -1;
      }
      continue;
    }
    std::uint64_t m = 0;
    for (int i = 0; i < 64; ++i) m |= static_cast<std::uint64_t>(row[x + i] >= threshold) << i;
    WalkMask(m, x, 64, &open, emit);
  }
  ScanTail(row, x, width, threshold, &open, emit);
}

#if defined(__AVX2__)
// AVX2, 8-bit: the block's maximum (two loads, one max), one unsigned compare (max(v, t) == v
// <=> v >= t), one test; a bright block is turned into a 64-bit mask with two movemasks.
template <class Emit>
void ScanRowAvx2(const std::uint8_t* row, int width, int threshold, Emit& emit) {
  const __m256i vt = _mm256_set1_epi8(static_cast<char>(threshold));
  int open = -1;
  int x = 0;
  for (; x + 64 <= width; x += 64) {
    const __m256i a = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(row + x));
    const __m256i b = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(row + x + 32));
    const __m256i mx = _mm256_max_epu8(a, b);
    const __m256i ge = _mm256_cmpeq_epi8(_mm256_max_epu8(mx, vt), mx);
    if (_mm256_testz_si256(ge, ge)) {
      if (open >= 0) {
        emit(open, x);
        open = -1;
      }
      continue;
    }
    const std::uint32_t ma = static_cast<std::uint32_t>(
        _mm256_movemask_epi8(_mm256_cmpeq_epi8(_mm256_max_epu8(a, vt), a)));
    const std::uint32_t mb = static_cast<std::uint32_t>(
        _mm256_movemask_epi8(_mm256_cmpeq_epi8(_mm256_max_epu8(b, vt), b)));
    WalkMask(static_cast<std::uint64_t>(ma) | (static_cast<std::uint64_t>(mb) << 32), x, 64, &open,
             emit);
  }
  ScanTail(row, x, width, threshold, &open, emit);
}

// AVX2, 16-bit: 64 pixels are four loads; the 16-bit compare results are packed to bytes
// (packs works per 128-bit lane, hence the 64-bit permute that restores pixel order).
template <class Emit>
void ScanRowAvx2(const std::uint16_t* row, int width, int threshold, Emit& emit) {
  const __m256i vt = _mm256_set1_epi16(static_cast<short>(static_cast<std::uint16_t>(threshold)));
  auto ge16 = [&](__m256i v) { return _mm256_cmpeq_epi16(_mm256_max_epu16(v, vt), v); };
  auto mask32 = [&](__m256i c0, __m256i c1) {
    const __m256i packed = _mm256_permute4x64_epi64(_mm256_packs_epi16(c0, c1), 0xD8);
    return static_cast<std::uint32_t>(_mm256_movemask_epi8(packed));
  };
  int open = -1;
  int x = 0;
  for (; x + 64 <= width; x += 64) {
    const auto* p = reinterpret_cast<const __m256i*>(row + x);
    const __m256i a = _mm256_loadu_si256(p), b = _mm256_loadu_si256(p + 1);
    const __m256i c = _mm256_loadu_si256(p + 2), d = _mm256_loadu_si256(p + 3);
    const __m256i mx = _mm256_max_epu16(_mm256_max_epu16(a, b), _mm256_max_epu16(c, d));
    const __m256i ge = ge16(mx);
    if (_mm256_testz_si256(ge, ge)) {
      if (open >= 0) {
        emit(open, x);
        open = -1;
      }
      continue;
    }
    const std::uint64_t lo = mask32(ge16(a), ge16(b));
    const std::uint64_t hi = mask32(ge16(c), ge16(d));
    WalkMask(lo | (hi << 32), x, 64, &open, emit);
  }
  ScanTail(row, x, width, threshold, &open, emit);
}
#endif

}  // namespace

// The connected-component pass and the per-blob reduction; a friend of the workspace.
class DetectionScanner {
 public:
  DetectionScanner(DetectionWorkspace* ws, const DetectionOptions& options, int width, int height,
                   int max_value)
      : ws_(*ws), options_(options), width_(width), height_(height), max_value_(max_value),
        var_const_(options.read_noise_dn * options.read_noise_dn + 1.0 / 12.0),
        gain_(options.shot_noise_gain),
        floor2_(options.sigma_floor_px * options.sigma_floor_px) {
    ws_.previous_.clear();
    ws_.current_.clear();
    ws_.parent_.clear();
    ws_.blobs_.clear();
  }

  // Scans the image; each blob is closed (filtered, its thresholded centre computed) on the first
  // row that no longer touches it, and refined as soon as the scan has passed the bottom of its
  // window: the window's rows were read moments ago and are still in cache.
  template <class P>
  Status Run(const drivers::ImageView& image, const ReflectionMask* mask,
             std::vector<Centroid>* out, DetectionStats* stats) {
    out->clear();
    mask_ = mask;
    ws_.candidates_.clear();
    ws_.queue_.clear();
    const int t = options_.threshold;
    auto emit = [this](int x0, int x1) { ws_.current_.push_back({x0, x1, -1}); };
    for (int y = 0; y < height_; ++y) {
      const P* row = reinterpret_cast<const P*>(image.data + image.stride * y);
#if defined(__AVX2__)
      if (!options_.force_portable_scan)
        ScanRowAvx2(row, width_, t, emit);
      else
        ScanRowPortable(row, width_, t, emit);
#else
      ScanRowPortable(row, width_, t, emit);
#endif
      if (!ws_.current_.empty() || !ws_.previous_.empty()) LinkRow(row, y);
      if (!ws_.queue_.empty()) RefineReady<P>(image, y);
    }
    // Blobs that reach the last row.
    for (int i = 0; i < static_cast<int>(ws_.blobs_.size()); ++i)
      if (ws_.parent_[i] == i && !ws_.blobs_[i].closed) Close(i);
    RefineReady<P>(image, height_);
    st_.runs = runs_;
    if (stats) *stats = st_;
    if (too_many_)
      return Status::Error("detection: more than " + std::to_string(options_.max_centroids) +
                           " blobs pass the filters (max_centroids); is threshold " +
                           std::to_string(options_.threshold) + " at the background level?");
    // Output in order of each blob's first pixel (labels are created in raster order).
    std::sort(ws_.candidates_.begin(), ws_.candidates_.end(),
              [](const DetectionWorkspace::Candidate& l, const DetectionWorkspace::Candidate& r) {
                return l.blob < r.blob;
              });
    for (const DetectionWorkspace::Candidate& c : ws_.candidates_) {
      if (!c.dropped) out->push_back(c.centroid);
    }
    return Status::Ok();
  }

 private:
  struct Window {
    int x0, x1, y0, y1;  // inclusive
  };
  Window WindowOf(const DetectionWorkspace::Blob& b, double s) const {
    const int m = static_cast<int>(std::ceil(2.5 * s));
    return {std::max(0, b.x_min - m), std::min(width_ - 1, b.x_max + m), std::max(0, b.y_min - m),
            std::min(height_ - 1, b.y_max + m)};
  }

  // A finished blob: filters, shape, thresholded centre and its uncertainty; queued for the
  // windowed refinement.
  void Close(int i) {
    DetectionWorkspace::Blob& b = ws_.blobs_[i];
    b.closed = true;
    ++st_.blobs;
    if (b.n < options_.min_area_px) { ++st_.too_small; return; }
    if (b.n > options_.max_area_px) { ++st_.too_large; return; }
    if (b.border && options_.drop_border_blobs) { ++st_.at_border; return; }
    const double cx = b.wx / b.w, cy = b.wy / b.w;
    // Weighted central second moments, plus a unit pixel's own 1/12.
    const double mxx = std::max(b.wxx / b.w - cx * cx, 0.0) + 1.0 / 12.0;
    const double myy = std::max(b.wyy / b.w - cy * cy, 0.0) + 1.0 / 12.0;
    const double mxy = b.wxy / b.w - cx * cy;
    const double half_tr = 0.5 * (mxx + myy);
    const double rad = std::sqrt(0.25 * (mxx - myy) * (mxx - myy) + mxy * mxy);
    const double major = half_tr + rad, minor = std::max(half_tr - rad, 0.0);
    const double roundness = std::sqrt(minor / major);
    const bool windowed =
        options_.centroid == DetectionOptions::CentroidMethod::kGaussianWindowed;
    const bool try_split = windowed && options_.split_overlapping &&
                           roundness < options_.overlap_roundness &&
                           roundness >= options_.split_min_roundness;
    if (roundness < options_.min_roundness && !try_split) { ++st_.not_round; return; }
    if (mask_ != nullptr && mask_->Contains(static_cast<int>(std::lround(cx)),
                                            static_cast<int>(std::lround(cy)))) {
      ++st_.masked;
      return;
    }
    if (st_.accepted >= options_.max_centroids) {
      too_many_ = true;
      return;
    }
    ++st_.accepted;
    // Thresholded uncertainty from the running sums: sum (x_i - cx)^2 and sum w_i (x_i - cx)^2.
    const double t1 = options_.threshold - 1.0;
    const double n = static_cast<double>(b.n);
    const double ux = std::max(static_cast<double>(b.sxx) - 2 * cx * b.sx + n * cx * cx, 0.0);
    const double uy = std::max(static_cast<double>(b.syy) - 2 * cy * b.sy + n * cy * cy, 0.0);
    const double wx2 = std::max(b.wxx - cx * cx * b.w, 0.0);
    const double wy2 = std::max(b.wyy - cy * cy * b.w, 0.0);
    // var_i = var_const + gain * value_i, value_i = w_i + threshold - 1.
    const double var_x = (var_const_ * ux + gain_ * (wx2 + t1 * ux)) / (b.w * b.w);
    const double var_y = (var_const_ * uy + gain_ * (wy2 + t1 * uy)) / (b.w * b.w);
    DetectionWorkspace::Candidate cand;
    cand.blob = i;
    if (roundness < options_.overlap_roundness) cand.overlap_var = major - minor;
    cand.try_split = try_split;
    cand.keep_single = roundness >= options_.min_roundness;
    if (try_split) {
      // The major axis and the split's starting offset along it.
      const double angle = 0.5 * std::atan2(2 * mxy, mxx - myy);
      const double half = std::sqrt(std::max(major - minor, 0.25));
      cand.split_dx = half * std::cos(angle);
      cand.split_dy = half * std::sin(angle);
      cand.split_s2 = minor;
      cand.split_mxx = mxx;
      cand.split_myy = myy;
      cand.split_mxy = mxy;
    }
    cand.centroid.pixel = Eigen::Vector2d(cx, cy);
    cand.centroid.sigma_px = std::sqrt(std::max(var_x, var_y) + floor2_ + cand.overlap_var);
    cand.centroid.area_px = static_cast<float>(b.n);
    cand.centroid.roundness = static_cast<float>(roundness);
    cand.centroid.peak = static_cast<float>(b.peak);
    if (options_.centroid == DetectionOptions::CentroidMethod::kGaussianWindowed) {
      // A saturated spot is a plateau with a sharp rim; a wider window averages over more of
      // the rim's sampling phases (measured: max error 0.05 -> 0.03 px at sigma 1.2-1.4 px).
      const double factor = b.peak >= max_value_ ? 3.0 : 1.3;
      cand.s = std::max(0.7, factor * std::sqrt(0.5 * (mxx + myy)));
      cand.ready_row = WindowOf(b, cand.s).y1;
      ws_.queue_.push_back(static_cast<int>(ws_.candidates_.size()));
    }
    ws_.candidates_.push_back(cand);
  }

  // Refines the queued blobs whose window lies entirely in rows <= y.
  template <class P>
  void RefineReady(const drivers::ImageView& image, int y) {
    std::vector<int>& q = ws_.queue_;
    for (std::size_t k = 0; k < q.size();) {
      DetectionWorkspace::Candidate& c = ws_.candidates_[q[k]];
      if (c.ready_row > y) {
        ++k;
        continue;
      }
      q[k] = q.back();
      q.pop_back();
      if (c.try_split) {
        ++st_.split_attempts;
        Centroid second;
        if (SplitTwo<P>(image, ws_.blobs_[c.blob], c, &c.centroid, &second)) {
          DetectionWorkspace::Candidate other = c;  // `c` may move with the push
          other.centroid = second;
          other.try_split = false;
          ws_.candidates_.push_back(other);
          ++st_.accepted;
          ++st_.split;
          continue;
        }
        if (!c.keep_single) {
          c.dropped = true;
          ++st_.not_round;
          --st_.accepted;
          continue;
        }
      }
      double x = c.centroid.pixel.x(), yc = c.centroid.pixel.y(), var_x = 0, var_y = 0;
      if (RefineGaussian<P>(image, ws_.blobs_[c.blob], c.s, var_const_, gain_, &x, &yc, &var_x,
                            &var_y)) {
        c.centroid.pixel = Eigen::Vector2d(x, yc);
        c.centroid.sigma_px = std::sqrt(std::max(var_x, var_y) + floor2_ + c.overlap_var);
      }
    }
  }

  // Levenberg-Marquardt on sum_i (v_i - model(q, x_i, y_i))^2 over the pixels, from *q; model
  // writes d model / d q when asked. Returns the final cost; *jtj (if given) is J^T J there.
  // Tiny fixed-size problems (N <= 7, tens of pixels): Eigen's fixed matrices, no allocation.
  template <int N, class Model>
  static double FitSmallModel(int n, const double* px, const double* py, const double* pv,
                              Eigen::Matrix<double, N, 1>* q, Model model,
                              Eigen::Matrix<double, N, N>* jtj_out) {
    using VecN = Eigen::Matrix<double, N, 1>;
    using MatN = Eigen::Matrix<double, N, N>;
    auto evaluate = [&](const VecN& at, MatN* jtj, VecN* jtr) {
      double cost = 0;
      if (jtj) {
        jtj->setZero();
        jtr->setZero();
      }
      VecN j;
      for (int i = 0; i < n; ++i) {
        const double r = pv[i] - model(at, px[i], py[i], jtj ? &j : nullptr);
        cost += r * r;
        if (jtj) {
          for (int a = 0; a < N; ++a) {
            for (int b = 0; b <= a; ++b) (*jtj)(a, b) += j[a] * j[b];
          }
          *jtr += j * r;
        }
      }
      if (jtj) {
        for (int a = 0; a < N; ++a) {
          for (int b = a + 1; b < N; ++b) (*jtj)(a, b) = (*jtj)(b, a);
        }
      }
      return cost;
    };
    MatN jtj;
    VecN jtr;
    double cost = evaluate(*q, &jtj, &jtr);
    double lambda = 1e-3;
    for (int iteration = 0; iteration < 20; ++iteration) {
      MatN a = jtj;
      a.diagonal() *= 1.0 + lambda;
      a.diagonal().array() += 1e-12;
      const VecN step = a.ldlt().solve(jtr);
      if (!step.allFinite()) break;
      const VecN trial = *q + step;
      const double trial_cost = evaluate(trial, nullptr, nullptr);
      if (trial_cost < cost) {
        *q = trial;
        const bool small = step.norm() < 1e-5 * (1.0 + q->norm());
        cost = evaluate(*q, &jtj, &jtr);
        lambda = std::max(lambda * 0.3, 1e-9);
        if (small) break;
      } else {
        lambda *= 10;
        if (lambda > 1e8) break;  // no descent left: a minimum
      }
    }
    if (jtj_out) *jtj_out = jtj;
    return cost;
  }

  // Two Gaussian spots of one width fitted to an elongated blob (detection.h, "Splitting"). True
  // with both centroids written when the fit finds two distinct spots; false (nothing written)
  // otherwise.
  template <class P>
  bool SplitTwo(const drivers::ImageView& image, const DetectionWorkspace::Blob& b,
                const DetectionWorkspace::Candidate& cand, Centroid* first, Centroid* second) {
    // The blob's bounding box and a ring of one pixel: where the two spots' light is.
    const Window w{std::max(0, b.x_min - 1), std::min(width_ - 1, b.x_max + 1),
                   std::max(0, b.y_min - 1), std::min(height_ - 1, b.y_max + 1)};
    DetectionWorkspace& ws = ws_;
    const std::size_t cap = static_cast<std::size_t>(w.x1 - w.x0 + 1) * (w.y1 - w.y0 + 1);
    if (ws.split_x_.size() < cap) {
      ws.split_x_.resize(cap);
      ws.split_y_.resize(cap);
      ws.split_v_.resize(cap);
    }
    // The usable pixels: not another blob's, not saturated (a plateau no Gaussian fits).
    const double bg = options_.background_dn;
    const int t = options_.threshold;
    int n = 0;
    double peak = 0;
    for (int y = w.y0; y <= w.y1; ++y) {
      const P* row = reinterpret_cast<const P*>(image.data + image.stride * y);
      const bool inside_rows = y >= b.y_min && y <= b.y_max;
      for (int x = w.x0; x <= w.x1; ++x) {
        const int v = row[x];
        if (v >= t && !(inside_rows && x >= b.x_min && x <= b.x_max)) continue;
        if (v >= max_value_) continue;
        ws.split_x_[n] = x;
        ws.split_y_[n] = y;
        ws.split_v_[n] = v - bg;
        peak = std::max(peak, v - bg);
        ++n;
      }
    }
    if (n < 24 || !(peak > 0)) return false;
    const double* px = ws.split_x_.data();
    const double* py = ws.split_y_.data();
    const double* pv = ws.split_v_.data();
    const double cx = cand.centroid.pixel.x(), cy = cand.centroid.pixel.y();
    // TWO round spots of one width: x1 y1 x2 y2 A1 A2 log(s^2).
    using Vec7 = Eigen::Matrix<double, 7, 1>;
    using Mat7 = Eigen::Matrix<double, 7, 7>;
    Vec7 p;
    p << cx - cand.split_dx, cy - cand.split_dy, cx + cand.split_dx, cy + cand.split_dy, peak, peak,
        std::log(std::max(cand.split_s2, 0.25));
    Mat7 jtj;
    const double cost = FitSmallModel<7>(n, px, py, pv, &p, [](const Vec7& q, double x, double y,
                                                             Vec7* j) {
      const double inv_s2 = std::exp(-q[6]);
      const double d1x = x - q[0], d1y = y - q[1], d2x = x - q[2], d2y = y - q[3];
      const double r1 = d1x * d1x + d1y * d1y, r2 = d2x * d2x + d2y * d2y;
      const double g1 = std::exp(-0.5 * r1 * inv_s2), g2 = std::exp(-0.5 * r2 * inv_s2);
      if (j) {
        *j << q[4] * g1 * d1x * inv_s2, q[4] * g1 * d1y * inv_s2, q[5] * g2 * d2x * inv_s2,
            q[5] * g2 * d2y * inv_s2, g1, g2, 0.5 * inv_s2 * (q[4] * g1 * r1 + q[5] * g2 * r2);
      }
      return q[4] * g1 + q[5] * g2;
    }, &jtj);
    // Two distinct spots of comparable brightness, each within the blob (a spot the fit moved
    // out into the margin is noise, not a marker).
    const double a1 = p[4], a2 = p[5];
    if (!(a1 > 0 && a2 > 0) || std::min(a1, a2) < 0.2 * std::max(a1, a2)) return false;
    const Eigen::Vector2d c1(p[0], p[1]), c2(p[2], p[3]);
    if ((c1 - c2).norm() < options_.split_min_separation_px) return false;
    for (const Eigen::Vector2d& c : {c1, c2}) {
      if (c.x() < b.x_min - 0.5 || c.x() > b.x_max + 0.5 || c.y() < b.y_min - 0.5 ||
          c.y() > b.y_max + 0.5) {
        return false;
      }
    }
    // The alternative: ONE spot, elliptical (a marker's image stretched by motion or the lens),
    // parameters x y A and the inverse covariance's a b c; started from the blob's moments.
    using Vec6 = Eigen::Matrix<double, 6, 1>;
    Vec6 e;
    {
      const double inv_det = 1.0 / std::max(cand.split_mxx * cand.split_myy -
                                                cand.split_mxy * cand.split_mxy, 1e-6);
      e << cx, cy, peak, cand.split_myy * inv_det, cand.split_mxx * inv_det,
          -cand.split_mxy * inv_det;
    }
    const double ellipse_cost = FitSmallModel<6>(n, px, py, pv, &e, [](const Vec6& q, double x,
                                                                       double y, Vec6* j) {
      const double dx = x - q[0], dy = y - q[1];
      const double quad = q[3] * dx * dx + q[4] * dy * dy + 2 * q[5] * dx * dy;
      const double g = std::exp(-0.5 * quad);
      const double ag = q[2] * g;
      if (j) {
        *j << ag * (q[3] * dx + q[5] * dy), ag * (q[5] * dx + q[4] * dy), g, -0.5 * ag * dx * dx,
            -0.5 * ag * dy * dy, -ag * dx * dy;
      }
      return ag;
    }, nullptr);
    // Two spots only where they explain the blob clearly better than one oval spot does.
    if (!(cost < options_.split_min_gain * ellipse_cost)) return false;
    // Covariance: residual variance x (J^T J)^-1.
    const double residual_var = cost / std::max(1, n - 7);
    const Eigen::LDLT<Mat7> ldlt(jtj);
    if (ldlt.info() != Eigen::Success) return false;
    const Mat7 cov = residual_var * ldlt.solve(Mat7::Identity());
    if (!cov.allFinite()) return false;
    *second = *first;
    first->pixel = c1;
    second->pixel = c2;
    first->sigma_px = std::sqrt(std::max(cov(0, 0), cov(1, 1)) + floor2_);
    second->sigma_px = std::sqrt(std::max(cov(2, 2), cov(3, 3)) + floor2_);
    // area_px, roundness and peak stay the blob's: both centroids say where they came from.
    return true;
  }

  // The Gaussian-windowed centre (see detection.h), Newton's method from (*x, *y). False (and
  // nothing written) when the window holds no signal or the centre runs off by more than a pixel.
  template <class P>
  bool RefineGaussian(const drivers::ImageView& image, const DetectionWorkspace::Blob& b, double s,
                      double var_const, double gain, double* x, double* y, double* var_x,
                      double* var_y) {
    const Window win_box = WindowOf(b, s);
    const int x0 = win_box.x0, x1 = win_box.x1, y0 = win_box.y0, y1 = win_box.y1;
    const int nx = x1 - x0 + 1, ny = y1 - y0 + 1;
    DetectionWorkspace& ws = ws_;
    auto fit = [](std::vector<double>& v, std::size_t n) {
      if (v.size() < n) v.resize(n);
      return v.data();
    };
    // Rows padded to a multiple of 4 doubles (zeros) for the 4-wide loops below.
    const int nxp = (nx + 3) & ~3;
    double* gx = fit(ws.gx_, nxp);
    double* gxd = fit(ws.gxd_, nxp);
    double* gxdd = fit(ws.gxdd_, nxp);
    double* gy = fit(ws.gy_, ny);
    double* win = fit(ws.window_, static_cast<std::size_t>(nxp) * ny);
    for (int i = nx; i < nxp; ++i) gx[i] = gxd[i] = gxdd[i] = 0;
    // The window, background-subtracted, as doubles: read once, used by every Newton pass.
    // A bright pixel outside the blob's bounding box belongs to another blob: it is left out
    // (set to the background), so that a neighbouring marker does not pull the centre.
    const double bg = options_.background_dn;
    const int t = options_.threshold;
    for (int j = 0; j < ny; ++j) {
      const P* row = reinterpret_cast<const P*>(image.data + image.stride * (y0 + j)) + x0;
      double* out = win + static_cast<std::size_t>(j) * nxp;
      const int y = y0 + j;
      const bool inside_rows = y >= b.y_min && y <= b.y_max;
      for (int i = 0; i < nx; ++i) {
        const int x = x0 + i;
        const bool foreign = row[i] >= t && !(inside_rows && x >= b.x_min && x <= b.x_max);
        out[i] = foreign ? 0.0 : row[i] - bg;
      }
      for (int i = nx; i < nxp; ++i) out[i] = 0;
    }
    const double inv2s2 = 0.5 / (s * s), inv_s2 = 1.0 / (s * s);
    const double k = std::exp(-inv_s2);  // ratio of consecutive ratios, see Gauss below
    // exp(-d_i^2 / 2s^2) at d_i = start + i, by the recurrence g_{i+1} = g_i q_i,
    // q_{i+1} = q_i k: three exp() per axis instead of one per sample.
    auto gauss = [&](double start, int n, double* g) {
      if (start * start * inv2s2 > 600) {  // the recurrence would start from an underflow
        for (int i = 0; i < n; ++i) g[i] = std::exp(-(start + i) * (start + i) * inv2s2);
        return;
      }
      double gi = std::exp(-start * start * inv2s2);
      double q = std::exp(-(2 * start + 1) * inv2s2);
      for (int i = 0; i < n; ++i) {
        g[i] = gi;
        gi *= q;
        q *= k;
      }
    };
    double cx = *x, cy = *y;
    const double start_x = cx, start_y = cy;
    constexpr int kMaxSteps = 10;
    for (int step = 0; step < kMaxSteps; ++step) {
      gauss(x0 - cx, nx, gx);
      gauss(y0 - cy, ny, gy);
      for (int i = 0; i < nx; ++i) {
        const double d = x0 + i - cx;
        gxd[i] = gx[i] * d;
        gxdd[i] = gx[i] * d * d;
      }
      double sum = 0, sx = 0, sy = 0, sxx = 0, syy = 0;
      for (int j = 0; j < ny; ++j) {
        const double* row = win + static_cast<std::size_t>(j) * nxp;
        V4 rs = {0, 0, 0, 0}, rsx = rs, rsxx = rs;
        for (int i = 0; i < nxp; i += 4) {
          const V4 v = Load4(row + i);
          rs += v * Load4(gx + i);
          rsx += v * Load4(gxd + i);
          rsxx += v * Load4(gxdd + i);
        }
        const double g = gy[j], dy = y0 + j - cy;
        const double r0 = Sum4(rs);
        sum += r0 * g;
        sx += Sum4(rsx) * g;
        sy += r0 * g * dy;
        sxx += Sum4(rsxx) * g;
        syy += r0 * g * dy * dy;
      }
      if (!(sum > 0)) return false;
      // Newton on F(c) = sum (x - c) w G(x - c), F'(c) = -(sum - sxx / s^2); the fixed-point
      // step where that curvature is not clearly positive.
      double den_x = sum - sxx * inv_s2, den_y = sum - syy * inv_s2;
      if (den_x < 0.2 * sum) den_x = sum;
      if (den_y < 0.2 * sum) den_y = sum;
      const double step_x = std::clamp(sx / den_x, -1.0, 1.0);
      const double step_y = std::clamp(sy / den_y, -1.0, 1.0);
      cx += step_x;
      cy += step_y;
      if (std::abs(cx - start_x) > 1.0 || std::abs(cy - start_y) > 1.0) return false;
      if (std::abs(step_x) < 1e-3 && std::abs(step_y) < 1e-3) break;  // Newton: next is < 1e-6
      if (step == kMaxSteps - 1) return false;
    }
    // Uncertainty at the final centre: sum var_i (x_i - c)^2 G_i^2 / D^2 (see detection.h), with
    // var_i = var_const + gain (w_i + bg), so per row only sum w G^2 and sum w G^2 d^2 are needed.
    gauss(x0 - cx, nx, gx);
    gauss(y0 - cy, ny, gy);
    double* g2 = gxd;     // reused: G^2
    double* g2d2 = gxdd;  // G^2 d^2
    double* gd2 = fit(ws.gxd2_, nxp);  // G d^2
    double sum_g2 = 0, sum_g2d2 = 0;
    for (int i = 0; i < nxp; ++i) {
      const double d = x0 + i - cx;
      const double g = i < nx ? gx[i] : 0.0;
      g2[i] = g * g;
      g2d2[i] = g * g * d * d;
      gd2[i] = g * d * d;
      sum_g2 += g2[i];
      sum_g2d2 += g2d2[i];
    }
    double sum = 0, sxx = 0, syy = 0, nvx = 0, nvy = 0;
    for (int j = 0; j < ny; ++j) {
      const double* row = win + static_cast<std::size_t>(j) * nxp;
      V4 rs = {0, 0, 0, 0}, rsxx = rs, rw2 = rs, rw2d2 = rs;
      for (int i = 0; i < nxp; i += 4) {
        const V4 v = Load4(row + i);
        rs += v * Load4(gx + i);
        rsxx += v * Load4(gd2 + i);
        rw2 += v * Load4(g2 + i);
        rw2d2 += v * Load4(g2d2 + i);
      }
      const double rv = (var_const + gain * bg) * sum_g2 + gain * Sum4(rw2);
      const double rvxx = (var_const + gain * bg) * sum_g2d2 + gain * Sum4(rw2d2);
      const double g = gy[j], dy = y0 + j - cy;
      const double r0 = Sum4(rs);
      sum += r0 * g;
      sxx += Sum4(rsxx) * g;
      syy += r0 * g * dy * dy;
      nvx += rvxx * g * g;
      nvy += rv * g * g * dy * dy;
    }
    double den_x = sum - sxx * inv_s2, den_y = sum - syy * inv_s2;
    if (den_x < 0.2 * sum) den_x = sum;
    if (den_y < 0.2 * sum) den_y = sum;
    *x = cx;
    *y = cy;
    *var_x = nvx / (den_x * den_x);
    *var_y = nvy / (den_y * den_y);
    return true;
  }

  int Find(int i) {
    std::vector<int>& p = ws_.parent_;
    int r = i;
    while (p[r] != r) r = p[r];
    while (p[i] != r) {
      const int next = p[i];
      p[i] = r;
      i = next;
    }
    return r;
  }

  // Unites two roots; the older (smaller) label stays the root and takes the other's sums.
  int Unite(int a, int b) {
    if (a > b) std::swap(a, b);
    ws_.parent_[b] = a;
    DetectionWorkspace::Blob& ra = ws_.blobs_[a];
    const DetectionWorkspace::Blob& rb = ws_.blobs_[b];
    ra.n += rb.n;
    ra.sx += rb.sx;
    ra.sy += rb.sy;
    ra.sxx += rb.sxx;
    ra.syy += rb.syy;
    ra.w += rb.w;
    ra.wx += rb.wx;
    ra.wy += rb.wy;
    ra.wxx += rb.wxx;
    ra.wyy += rb.wyy;
    ra.wxy += rb.wxy;
    ra.peak = std::max(ra.peak, rb.peak);
    ra.border = ra.border || rb.border;
    ra.x_min = std::min(ra.x_min, rb.x_min);
    ra.x_max = std::max(ra.x_max, rb.x_max);
    ra.y_min = std::min(ra.y_min, rb.y_min);
    ra.y_max = std::max(ra.y_max, rb.y_max);
    return a;
  }

  int NewBlob() {
    const int label = static_cast<int>(ws_.blobs_.size());
    ws_.parent_.push_back(label);
    DetectionWorkspace::Blob b{};
    b.x_min = b.y_min = std::numeric_limits<int>::max();
    b.x_max = b.y_max = -1;
    ws_.blobs_.push_back(b);
    return label;
  }

  template <class P>
  void Accumulate(DetectionWorkspace::Blob& b, const P* row, int x0, int x1, int y) {
    const int t1 = options_.threshold - 1;
    std::int64_t s0 = 0, s1 = 0, s2 = 0;
    int peak = 0;
    for (int x = x0; x < x1; ++x) {
      const int v = row[x];
      const std::int64_t w = v - t1;
      const std::int64_t k = x - x0;
      s0 += w;
      s1 += w * k;
      s2 += w * k * k;
      peak = std::max(peak, v);
    }
    const double X0 = x0, Y = y;
    const double w = static_cast<double>(s0);
    const double wx = static_cast<double>(s1) + X0 * w;
    const double wxx = static_cast<double>(s2) + 2 * X0 * static_cast<double>(s1) + X0 * X0 * w;
    b.w += w;
    b.wx += wx;
    b.wy += Y * w;
    b.wxx += wxx;
    b.wyy += Y * Y * w;
    b.wxy += Y * wx;
    const std::int64_t len = x1 - x0;
    auto sum_sq = [](std::int64_t n) { return n * (n + 1) * (2 * n + 1) / 6; };  // 0^2..n^2
    b.n += len;
    b.sx += len * x0 + len * (len - 1) / 2;
    b.sxx += sum_sq(x1 - 1) - sum_sq(x0 - 1);
    b.sy += len * y;
    b.syy += len * static_cast<std::int64_t>(y) * y;
    b.peak = std::max(b.peak, peak);
    if (x0 == 0 || x1 == width_ || y == 0 || y == height_ - 1) b.border = true;
    b.x_min = std::min(b.x_min, x0);
    b.x_max = std::max(b.x_max, x1 - 1);
    b.y_min = std::min(b.y_min, y);
    b.y_max = std::max(b.y_max, y);
  }

  // Joins the runs of row y to those of the row above (8-connectivity) and adds their sums.
  template <class P>
  void LinkRow(const P* row, int y) {
    std::vector<DetectionWorkspace::Run>& prev = ws_.previous_;
    std::vector<DetectionWorkspace::Run>& cur = ws_.current_;
    runs_ += static_cast<int>(cur.size());
    std::size_t i = 0;
    for (DetectionWorkspace::Run& r : cur) {
      // prev[i] cannot touch r (nor any later run of this row) when it ends before r.x0 - 1.
      while (i < prev.size() && prev[i].x1 < r.x0) ++i;
      int label = -1;
      for (std::size_t j = i; j < prev.size() && prev[j].x0 <= r.x1; ++j) {
        const int root = Find(prev[j].label);
        if (label < 0)
          label = root;
        else if (root != label)
          label = Unite(label, root);
      }
      if (label < 0) label = NewBlob();
      r.label = label;
      Accumulate(ws_.blobs_[label], row, r.x0, r.x1, y);
    }
    // A blob of the row above that no run of this row touched is finished.
    for (const DetectionWorkspace::Run& r : prev) {
      const int root = Find(r.label);
      if (!ws_.blobs_[root].closed && ws_.blobs_[root].y_max < y) Close(root);
    }
    std::swap(prev, cur);
    cur.clear();
  }

  DetectionWorkspace& ws_;
  const DetectionOptions& options_;
  const int width_, height_;
  const int max_value_;  // the level at which pixels clip
  const double var_const_, gain_, floor2_;  // noise model (detection.h)
  const ReflectionMask* mask_ = nullptr;
  DetectionStats st_;
  bool too_many_ = false;
  int runs_ = 0;
};

Status DetectMarkers(const drivers::ImageView& image, const DetectionOptions& options,
                     const ReflectionMask* mask, DetectionWorkspace* workspace,
                     std::vector<Centroid>* centroids, DetectionStats* stats) {
  if (workspace == nullptr || centroids == nullptr)
    return Status::Error("detection: workspace and centroids must not be null");
  centroids->clear();
  if (stats) *stats = DetectionStats{};
  MOCAP_RETURN_IF_ERROR(CheckImage(image));
  std::string error;
  if (!options.IsValid(&error)) return Status::Error(error);
  const int max_value = (1 << drivers::BitDepth(image.format)) - 1;
  if (options.threshold > max_value)
    return Status::Error("detection: threshold " + std::to_string(options.threshold) +
                         " is above the largest " + drivers::ToString(image.format) + " value " +
                         std::to_string(max_value));
  if (mask != nullptr && !mask->empty() &&
      (mask->width() != image.width || mask->height() != image.height))
    return Status::Error("detection: reflection mask is " + std::to_string(mask->width()) + " x " +
                         std::to_string(mask->height()) + ", image is " +
                         std::to_string(image.width) + " x " + std::to_string(image.height));
  const int saturation = options.saturation_level > 0 ? std::min(options.saturation_level, max_value)
                                                      : max_value;
  DetectionScanner scanner(workspace, options, image.width, image.height, saturation);
  const ReflectionMask* used_mask = mask != nullptr && !mask->empty() ? mask : nullptr;
  if (image.format == drivers::PixelFormat::kMono8)
    return scanner.Run<std::uint8_t>(image, used_mask, centroids, stats);
  return scanner.Run<std::uint16_t>(image, used_mask, centroids, stats);
}

}  // namespace mocap::reconstruction
