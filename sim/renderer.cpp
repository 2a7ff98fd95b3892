#include "sim/renderer.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <mutex>

#include "sim/random.h"
#include "sim/simulate.h"

namespace mocap::sim {
namespace {

using drivers::PixelFormat;

// ---- Random draws as hashes of their coordinates (order- and thread-independent). ----

std::uint64_t Key(std::uint64_t a, std::uint64_t b, std::uint64_t c = 0, std::uint64_t d = 0,
                  std::uint64_t e = 0) {
  return Mix64(Mix64(Mix64(Mix64(a ^ 0x51ed2701u) + b) + c) + d) + e;
}
double UniformOf(std::uint64_t h) { return static_cast<double>(Mix64(h) >> 11) * 0x1.0p-53; }
double NormalOf(std::uint64_t h) {
  const double u1 = 1.0 - UniformOf(h);
  const double u2 = UniformOf(h ^ 0x9e3779b97f4a7c15ULL);
  return std::sqrt(-2.0 * std::log(u1)) * std::cos(2.0 * M_PI * u2);
}
// Tags that keep the kJitter draws of different purposes apart.
constexpr std::uint64_t kTagTiming = 1, kTagCentroid = 2, kTagOcclusion = 3;

// ---- The blob profile: a disc of radius u (in PSF sigmas) convolved with a unit Gaussian,
// at distance v (in sigmas) from the centre. ----

// exp(-x) I0(x), Abramowitz & Stegun 9.8.1 / 9.8.2 (relative error < 2e-7).
double I0e(double x) {
  x = std::fabs(x);
  if (x <= 3.75) {
    const double t = (x / 3.75) * (x / 3.75);
    const double i0 = 1.0 + t * (3.5156229 + t * (3.0899424 + t * (1.2067492 + t * (0.2659732 +
                      t * (0.0360768 + t * 0.0045813)))));
    return std::exp(-x) * i0;
  }
  const double t = 3.75 / x;
  const double p = 0.39894228 + t * (0.01328592 + t * (0.00225319 + t * (-0.00157565 +
                   t * (0.00916281 + t * (-0.02057706 + t * (0.02635537 + t * (-0.01647633 +
                   t * 0.00392377)))))));
  return p / std::sqrt(x);
}

double DiscGauss(double v, double u) {
  if (u <= 0) return 0.0;
  int n = std::max(16, static_cast<int>(std::ceil(u * 8.0)));
  n += n & 1;
  const double h = u / n;
  double sum = 0;
  for (int k = 0; k <= n; ++k) {
    const double rho = k * h;
    const double f = rho * std::exp(-0.5 * (v - rho) * (v - rho)) * I0e(v * rho);
    sum += f * (k == 0 || k == n ? 1.0 : (k & 1 ? 4.0 : 2.0));
  }
  return sum * h / 3.0;
}

struct ProfileTable {
  static constexpr double kUMax = 16.0, kDu = 0.125, kVMax = 22.0, kDv = 1.0 / 16.0;
  static constexpr int kNu = static_cast<int>(kUMax / kDu) + 2;
  static constexpr int kNv = static_cast<int>(kVMax / kDv) + 2;
  std::vector<float> values;  // kNu x kNv

  ProfileTable() : values(static_cast<std::size_t>(kNu) * kNv) {
    for (int iu = 0; iu < kNu; ++iu) {
      for (int iv = 0; iv < kNv; ++iv) {
        values[static_cast<std::size_t>(iu) * kNv + iv] =
            static_cast<float>(DiscGauss(iv * kDv, iu * kDu));
      }
    }
  }
};

const ProfileTable& Profile() {
  static const ProfileTable table;  // thread-safe one-time build (~tens of ms)
  return table;
}

// Per-blob view of the table row for its radius.
struct ProfileRow {
  const float* row0 = nullptr;
  const float* row1 = nullptr;
  float fu = 0;
  bool edge = false;  // radius beyond the table: the straight-edge profile
  double u = 0;

  ProfileRow() = default;
  explicit ProfileRow(double u_in) : u(u_in) {
    const ProfileTable& t = Profile();
    if (u >= ProfileTable::kUMax) {
      edge = true;
      return;
    }
    const double x = u / ProfileTable::kDu;
    const int iu = static_cast<int>(x);
    fu = static_cast<float>(x - iu);
    row0 = t.values.data() + static_cast<std::size_t>(iu) * ProfileTable::kNv;
    row1 = row0 + ProfileTable::kNv;
  }
  double operator()(double v) const {
    if (edge) return 0.5 * std::erfc((v - u) * M_SQRT1_2);
    const double x = v / ProfileTable::kDv;
    if (x >= ProfileTable::kNv - 1) return 0.0;
    const int iv = static_cast<int>(x);
    const float fv = static_cast<float>(x - iv);
    const float a = row0[iv] + fv * (row0[iv + 1] - row0[iv]);
    const float b = row1[iv] + fv * (row1[iv + 1] - row1[iv]);
    return a + fu * (b - a);
  }
};

int FullScale(PixelFormat f) {
  return f == PixelFormat::kMono8 ? 255 : (f == PixelFormat::kMono12 ? 4095 : 65535);
}
int FormatSlot(PixelFormat f) {
  return f == PixelFormat::kMono8 ? 0 : (f == PixelFormat::kMono12 ? 1 : 2);
}

void FillRect(std::uint8_t* data, std::ptrdiff_t stride, PixelFormat f, int x0, int y0, int x1,
              int y1, int value) {
  for (int y = y0; y < y1; ++y) {
    std::uint8_t* row = data + stride * y;
    if (f == PixelFormat::kMono8) {
      std::memset(row + x0, value, static_cast<std::size_t>(x1 - x0));
    } else {
      std::fill(reinterpret_cast<std::uint16_t*>(row) + x0,
                reinterpret_cast<std::uint16_t*>(row) + x1, static_cast<std::uint16_t>(value));
    }
  }
}

// ---- Scenes ----

class SessionScene final : public Scene {
 public:
  explicit SessionScene(const SimulatedSession& session) {
    for (const SimulatedTrial& t : session.trials) {
      if (t.markers.num_frames() == 0 || !(t.markers.rate_hz > 0)) continue;
      Part p;
      p.positions = t.markers.positions;
      p.rate = t.markers.rate_hz;
      p.start = duration_;
      p.frames = t.markers.num_frames();
      duration_ += p.frames / p.rate;
      markers_ = markers_ == 0 ? t.markers.num_markers() : std::min(markers_, t.markers.num_markers());
      parts_.push_back(std::move(p));
    }
  }
  int marker_count() const override { return markers_; }
  double duration_s() const override { return duration_; }
  void Positions(double t, Eigen::Vector3d* out) const override {
    const double nan = std::numeric_limits<double>::quiet_NaN();
    if (parts_.empty()) {
      for (int m = 0; m < markers_; ++m) out[m].setConstant(nan);
      return;
    }
    std::size_t k = 0;
    while (k + 1 < parts_.size() && t >= parts_[k + 1].start) ++k;
    const Part& p = parts_[k];
    const double x = std::clamp((t - p.start) * p.rate, 0.0, double(p.frames - 1));
    const int i0 = static_cast<int>(x);
    const int i1 = std::min(i0 + 1, p.frames - 1);
    const double w = x - i0;
    for (int m = 0; m < markers_; ++m) {
      const Eigen::Vector3d a = p.positions.row(i0).segment<3>(3 * m).transpose();
      const Eigen::Vector3d b = p.positions.row(i1).segment<3>(3 * m).transpose();
      out[m] = a + w * (b - a);  // NaN if either sample is missing
    }
  }

 private:
  struct Part {
    formats::RowMatrix positions;
    double rate = 0, start = 0;
    int frames = 0;
  };
  std::vector<Part> parts_;
  int markers_ = 0;
  double duration_ = 0;
};

class StaticScene final : public Scene {
 public:
  explicit StaticScene(std::vector<Eigen::Vector3d> p) : points_(std::move(p)) {}
  int marker_count() const override { return static_cast<int>(points_.size()); }
  void Positions(double, Eigen::Vector3d* out) const override {
    std::copy(points_.begin(), points_.end(), out);
  }

 private:
  std::vector<Eigen::Vector3d> points_;
};

class CallbackScene final : public Scene {
 public:
  CallbackScene(int n, std::function<void(double, Eigen::Vector3d*)> f, double d)
      : n_(n), f_(std::move(f)), d_(d) {}
  int marker_count() const override { return n_; }
  double duration_s() const override { return d_; }
  void Positions(double t, Eigen::Vector3d* out) const override { f_(t, out); }

 private:
  int n_;
  std::function<void(double, Eigen::Vector3d*)> f_;
  double d_;
};

// A table of standard normal variates for the pixel noise (indexed by a pixel hash).
constexpr int kNoiseTableBits = 14;
const std::vector<float>& NoiseTable(std::uint64_t seed) {
  static std::mutex mutex;
  static std::unordered_map<std::uint64_t, std::vector<float>> tables;
  std::lock_guard<std::mutex> lock(mutex);
  auto it = tables.find(seed);
  if (it == tables.end()) {
    std::vector<float> t(1u << kNoiseTableBits);
    Random r(seed, Stream::kImageNoise);
    for (float& v : t) v = static_cast<float>(r.Normal());
    it = tables.emplace(seed, std::move(t)).first;
  }
  return it->second;
}

}  // namespace

std::shared_ptr<const Scene> MakeSessionScene(const SimulatedSession& session) {
  return std::make_shared<SessionScene>(session);
}
std::shared_ptr<const Scene> MakeStaticScene(std::vector<Eigen::Vector3d> points) {
  return std::make_shared<StaticScene>(std::move(points));
}
std::shared_ptr<const Scene> MakeCallbackScene(int markers,
                                               std::function<void(double, Eigen::Vector3d*)> f,
                                               double duration_s) {
  return std::make_shared<CallbackScene>(markers, std::move(f), duration_s);
}

bool RendererOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& what) {
    if (error) *error = "renderer options: " + what;
    return false;
  };
  auto finite_nonneg = [](double v) { return std::isfinite(v) && v >= 0; };
  if (!(frame_rate_hz > 0) || !std::isfinite(frame_rate_hz)) return fail("frame_rate_hz must be > 0");
  if (!(marker_diameter_m > 0) || !std::isfinite(marker_diameter_m)) {
    return fail("marker_diameter_m must be > 0");
  }
  if (!(psf_sigma_px >= 0.2) || !std::isfinite(psf_sigma_px)) {
    return fail("psf_sigma_px must be >= 0.2 (a narrower PSF aliases on the pixel grid)");
  }
  if (!finite_nonneg(marker_intensity)) return fail("marker_intensity must be >= 0");
  if (!finite_nonneg(background) || background >= 1) return fail("background must be in [0, 1)");
  if (!finite_nonneg(read_noise) || !finite_nonneg(shot_noise)) {
    return fail("read_noise and shot_noise must be >= 0");
  }
  if (!finite_nonneg(noise_margin_px)) return fail("noise_margin_px must be >= 0");
  if (!finite_nonneg(centroid_noise_px)) return fail("centroid_noise_px must be >= 0");
  if (!finite_nonneg(min_depth_m)) return fail("min_depth_m must be >= 0");
  if (reflections_per_camera < 0) return fail("reflections_per_camera must be >= 0");
  if (!finite_nonneg(reflection_radius_px) || !finite_nonneg(reflection_intensity)) {
    return fail("reflection_radius_px and reflection_intensity must be >= 0");
  }
  if (!(occlusion_probability >= 0 && occlusion_probability <= 1)) {
    return fail("occlusion_probability must be in [0, 1]");
  }
  if (occlusion_block_frames < 1) return fail("occlusion_block_frames must be >= 1");
  if (!finite_nonneg(timing_jitter_s)) return fail("timing_jitter_s must be >= 0");
  return true;
}

Renderer::Renderer(std::vector<reconstruction::CameraModel> cameras,
                   std::shared_ptr<const Scene> scene, RendererOptions options)
    : cameras_(std::move(cameras)), scene_(std::move(scene)), options_(options) {
  std::string error;
  if (!options_.IsValid(&error)) {
    status_ = Status::Error(error);
  } else if (scene_ == nullptr) {
    status_ = Status::Error("renderer: no scene");
  } else {
    for (std::size_t c = 0; c < cameras_.size() && status_.ok(); ++c) {
      if (!cameras_[c].intrinsics.IsValid(&error)) {
        status_ = Status::Error("renderer: camera " + std::to_string(c) + ": " + error);
      }
    }
  }
  Profile();  // build the table now, not in the first frame
  noise_ = &NoiseTable(options_.seed);
  for (PixelFormat f : {PixelFormat::kMono8, PixelFormat::kMono12, PixelFormat::kMono16}) {
    std::vector<std::uint16_t>& dark = dark_[FormatSlot(f)];
    const int full = FullScale(f);
    const bool noisy = options_.read_noise > 0 || options_.shot_noise > 0;
    dark.resize(noise_->size());
    for (std::size_t i = 0; i < dark.size(); ++i) {
      const double v = options_.background + (noisy ? options_.read_noise * (*noise_)[i] : 0.0);
      dark[i] = static_cast<std::uint16_t>(std::clamp(static_cast<int>(v * full + 0.5), 0, full));
    }
  }
  const int n = scene_ ? scene_->marker_count() : 0;
  for (std::size_t c = 0; c < cameras_.size(); ++c) {
    auto st = std::make_unique<CameraState>();
    st->positions.resize(n);
    st->blobs.reserve(n + options_.reflections_per_camera);
    Random r(options_.seed, Stream::kReflections, c);
    for (int k = 0; k < options_.reflections_per_camera; ++k) {
      Blob b;
      b.x = b.px = r.Uniform(0, cameras_[c].intrinsics.width - 1);
      b.y = b.py = r.Uniform(0, cameras_[c].intrinsics.height - 1);
      b.radius = options_.reflection_radius_px;
      b.intensity = options_.reflection_intensity;
      b.marker = -1;
      st->reflections.push_back(b);
    }
    states_.push_back(std::move(st));
  }
}

Renderer::~Renderer() = default;

drivers::ImageGenerator Renderer::Generator() {
  return [this](int camera, std::uint64_t sequence, std::uint8_t* data, int width, int height,
                std::ptrdiff_t stride, PixelFormat format) {
    Render(camera, sequence, data, width, height, stride, format);
  };
}

void Renderer::ForgetBuffers() {
  for (auto& st : states_) {
    std::lock_guard<std::mutex> lock(st->mutex);
    st->buffers.clear();
  }
}

void Renderer::ComputeBlobs(int camera, std::uint64_t sequence,
                            std::vector<Eigen::Vector3d>* positions, std::vector<Blob>* blobs,
                            double* time_s) const {
  const RendererOptions& o = options_;
  const reconstruction::CameraModel& cam = cameras_[camera];
  const auto frame = static_cast<std::int64_t>(sequence - o.sequence_origin);
  double t = static_cast<double>(frame) / o.frame_rate_hz;
  if (o.timing_jitter_s > 0) {
    t += o.timing_jitter_s *
         NormalOf(Key(SubSeed(o.seed, Stream::kJitter), kTagTiming, camera, sequence));
  }
  const double period = scene_->duration_s();
  if (period > 0) {
    t = std::fmod(t, period);
    if (t < 0) t += period;
  }
  *time_s = t;
  scene_->Positions(t, positions->data());
  blobs->clear();
  const int w = cam.intrinsics.width, h = cam.intrinsics.height;
  const double f = 0.5 * (cam.intrinsics.fx + cam.intrinsics.fy);
  const std::uint64_t jitter_seed = SubSeed(o.seed, Stream::kJitter);
  const std::uint64_t block =
      static_cast<std::uint64_t>(frame >= 0 ? frame : 0) / o.occlusion_block_frames;
  for (int m = 0; m < static_cast<int>(positions->size()); ++m) {
    const Eigen::Vector3d& p = (*positions)[m];
    if (!p.allFinite()) continue;
    if (o.occlusion_probability > 0 &&
        UniformOf(Key(jitter_seed, kTagOcclusion, camera, m, block)) < o.occlusion_probability) {
      continue;
    }
    const Eigen::Vector3d xc = cam.ToCamera(p);
    if (xc.z() < std::max(o.min_depth_m, 1e-6)) continue;
    const Eigen::Vector2d uv = cam.ProjectCameraPoint(xc);
    if (!(uv.x() >= 0 && uv.y() >= 0 && uv.x() <= w - 1 && uv.y() <= h - 1)) continue;
    Blob b;
    b.px = uv.x();
    b.py = uv.y();
    b.x = uv.x();
    b.y = uv.y();
    if (o.centroid_noise_px > 0) {
      const std::uint64_t k = Key(jitter_seed, kTagCentroid, camera, sequence, m);
      b.x += o.centroid_noise_px * NormalOf(k);
      b.y += o.centroid_noise_px * NormalOf(k + 0x1234567);
    }
    b.radius = f * 0.5 * o.marker_diameter_m / xc.z();
    b.intensity = o.marker_intensity;
    b.marker = m;
    blobs->push_back(b);
  }
}

void Renderer::Truth(int camera, std::uint64_t sequence, FrameTruth* truth) const {
  truth->camera = camera;
  truth->sequence = sequence;
  truth->blobs.clear();
  truth->reflections.clear();
  if (!status_.ok() || camera < 0 || camera >= camera_count()) return;
  std::vector<Eigen::Vector3d> positions(scene_->marker_count());
  std::vector<Blob> blobs;
  ComputeBlobs(camera, sequence, &positions, &blobs, &truth->time_s);
  for (const Blob& b : blobs) {
    truth->blobs.push_back({b.marker, {b.px, b.py}, {b.x, b.y}, b.radius});
  }
  for (const Blob& b : states_[camera]->reflections) {
    truth->reflections.push_back({-1, {b.px, b.py}, {b.x, b.y}, b.radius});
  }
}

void Renderer::Render(int camera, std::uint64_t sequence, std::uint8_t* data, int width,
                      int height, std::ptrdiff_t stride, PixelFormat format) {
  if (data == nullptr || width <= 0 || height <= 0) return;
  const int full = FullScale(format);
  const RendererOptions& o = options_;
  const int bg = static_cast<int>(std::lround(o.background * full));
  if (!status_.ok() || camera < 0 || camera >= camera_count()) {
    FillRect(data, stride, format, 0, 0, width, height, bg);
    return;
  }
  CameraState& st = *states_[camera];
  std::lock_guard<std::mutex> lock(st.mutex);

  // 1. Reset what was drawn in this buffer last time (or all of it, the first time).
  auto it = st.buffers.find(data);
  if (it == st.buffers.end()) {
    it = st.buffers.emplace(data, BufferRecord{}).first;
    it->second.rects.reserve(256);
    it->second.width = -1;
  }
  BufferRecord& rec = it->second;
  if (rec.width != width || rec.height != height || rec.stride != stride || rec.format != format) {
    FillRect(data, stride, format, 0, 0, width, height, bg);
    rec.width = width;
    rec.height = height;
    rec.stride = stride;
    rec.format = format;
  } else {
    for (const Rect& r : rec.rects) FillRect(data, stride, format, r.x0, r.y0, r.x1, r.y1, bg);
  }
  rec.rects.clear();

  // 2. The blobs of this frame, then the static reflections.
  double time_s;
  ComputeBlobs(camera, sequence, &st.positions, &st.blobs, &time_s);
  st.blobs.insert(st.blobs.end(), st.reflections.begin(), st.reflections.end());

  // 3. Draw each blob's rectangle: background + every blob reaching the pixel + noise.
  const double s = o.psf_sigma_px, inv_s = 1.0 / s;
  const bool noisy = o.read_noise > 0 || o.shot_noise > 0;
  const std::vector<float>& noise = *noise_;
  const std::uint16_t* dark = dark_[FormatSlot(format)].data();
  const std::uint64_t noise_key = Key(SubSeed(o.seed, Stream::kImageNoise), camera, sequence);
  const double read2 = o.read_noise * o.read_noise, shot2 = o.shot_noise * o.shot_noise;
  const int n = static_cast<int>(st.blobs.size());
  constexpr int kMaxNear = 16;
  for (int i = 0; i < n; ++i) {
    const Blob& b = st.blobs[i];
    const double support = b.radius + 4.5 * s;
    const double ext = support + (noisy ? o.noise_margin_px : 0.0);
    Rect r{std::max(0, static_cast<int>(std::floor(b.x - ext))),
           std::max(0, static_cast<int>(std::floor(b.y - ext))),
           std::min(width, static_cast<int>(std::ceil(b.x + ext)) + 1),
           std::min(height, static_cast<int>(std::ceil(b.y + ext)) + 1)};
    if (r.x0 >= r.x1 || r.y0 >= r.y1) continue;
    rec.rects.push_back(r);
    // The blobs whose light reaches this rectangle (itself included).
    struct Near {
      float x, y, intensity, support2;
      ProfileRow row;
    } near[kMaxNear];
    int nn = 0;
    for (int j = 0; j < n && nn < kMaxNear; ++j) {
      const Blob& c = st.blobs[j];
      const double sj = c.radius + 4.5 * s;
      if (c.x + sj < r.x0 || c.x - sj > r.x1 || c.y + sj < r.y0 || c.y - sj > r.y1) continue;
      near[nn] = {static_cast<float>(c.x), static_cast<float>(c.y),
                  static_cast<float>(c.intensity), static_cast<float>(sj * sj),
                  ProfileRow(c.radius * inv_s)};
      ++nn;
    }
    for (int y = r.y0; y < r.y1; ++y) {
      std::uint8_t* row = data + stride * y;
      // One hash a row, the row's pixels consecutive entries of the table from there: rows
      // (and frames, cameras) start at independent places, so no two neighbouring pixels of a
      // blob share a variate unless two rows' starts fall within a rectangle's width of each
      // other (about 1 in 800).
      const std::uint64_t row_start =
          noisy ? Mix64(noise_key + (static_cast<std::uint64_t>(y) << 32)) : 0;
      for (int x = r.x0; x < r.x1; ++x) {
        const std::size_t ni =
            (row_start + static_cast<std::uint64_t>(x)) & ((1u << kNoiseTableBits) - 1);
        double signal = 0;
        for (int k = 0; k < nn; ++k) {
          const float dx = x - near[k].x, dy = y - near[k].y;
          const float d2 = dx * dx + dy * dy;
          if (d2 < near[k].support2) {
            signal += near[k].intensity * near[k].row(std::sqrt(d2) * inv_s);
          }
        }
        int q;
        if (signal <= 0) {
          q = dark[ni];
        } else {
          double v = o.background + signal;
          if (noisy) v += std::sqrt(read2 + shot2 * signal) * noise[ni];
          q = std::clamp(static_cast<int>(v * full + 0.5), 0, full);
        }
        if (format == PixelFormat::kMono8) {
          row[x] = static_cast<std::uint8_t>(q);
        } else {
          reinterpret_cast<std::uint16_t*>(row)[x] = static_cast<std::uint16_t>(q);
        }
      }
    }
  }
}

}  // namespace mocap::sim
