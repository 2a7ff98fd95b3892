#include "sim/wand.h"

#include <algorithm>
#include <cmath>

#include "sim/random.h"

namespace mocap::sim {

namespace {

// Sub-streams of Stream::kWand.
enum : std::uint64_t { kPath = 0, kNoise = 1, kStrays = 2, kDropout = 3, kLFrame = 4 };

// One camera's detections of a set of world points: projection, merging, noise, strays.
reconstruction::CameraDetections Detect(const reconstruction::CameraModel& cam, int camera,
                                        const std::vector<Eigen::Vector3d>& points,
                                        const WandSimulationOptions& o, Random& noise,
                                        Random& strays) {
  reconstruction::CameraDetections det;
  det.camera = camera;
  std::vector<Eigen::Vector2d> seen;
  for (const Eigen::Vector3d& p : points) {
    Eigen::Vector2d u;
    if (!cam.Project(p, &u)) continue;
    if (u.x() < 0 || u.y() < 0 || u.x() > cam.intrinsics.width - 1 ||
        u.y() > cam.intrinsics.height - 1)
      continue;
    seen.push_back(u);
  }
  // Blobs closer than merge_px are one centroid at their mean.
  std::vector<char> merged(seen.size(), 0);
  std::vector<Eigen::Vector2d> blobs;
  for (size_t i = 0; i < seen.size(); ++i) {
    if (merged[i]) continue;
    Eigen::Vector2d sum = seen[i];
    int n = 1;
    for (size_t j = i + 1; j < seen.size(); ++j)
      if (!merged[j] && (seen[j] - seen[i]).norm() < o.merge_px) {
        merged[j] = 1;
        sum += seen[j];
        ++n;
      }
    blobs.push_back(sum / n);
  }
  for (Eigen::Vector2d& b : blobs)
    b += o.noise_px * Eigen::Vector2d(noise.Normal(), noise.Normal());
  const int ns = o.max_strays > 0 ? strays.UniformInt(0, o.max_strays) : 0;
  for (int s = 0; s < ns; ++s)
    blobs.emplace_back(strays.Uniform(0, cam.intrinsics.width - 1),
                       strays.Uniform(0, cam.intrinsics.height - 1));
  // Unlabelled: random order.
  for (int i = static_cast<int>(blobs.size()) - 1; i > 0; --i)
    std::swap(blobs[i], blobs[strays.UniformInt(0, i)]);
  for (const Eigen::Vector2d& b : blobs) {
    reconstruction::Centroid c;
    c.pixel = b;
    c.sigma_px = o.noise_px;
    det.centroids.push_back(c);
  }
  return det;
}

}  // namespace

double WandPath::Signal::operator()(double t) const {
  double v = 0;
  for (int i = 0; i < kTerms; ++i) v += amp[i] * std::sin(2 * M_PI * freq[i] * t + phase[i]);
  return v;
}

WandPath::WandPath(const WandSimulationOptions& o)
    : WandPath(o.seed, o.volume_centre_m, o.volume_half_size_m, o.wand) {}

WandPath::WandPath(std::uint64_t seed, const Eigen::Vector3d& volume_centre_m,
                   const Eigen::Vector3d& volume_half_size_m, const reconstruction::Wand& wand)
    : centre_m_(volume_centre_m), half_size_m_(volume_half_size_m) {
  Random path(seed, Stream::kWand, kPath);
  // Drawn in this order: the centre's x, y, z, then the direction's.
  for (Signal* signal : {&centre_[0], &centre_[1], &centre_[2], &direction_[0], &direction_[1],
                         &direction_[2]}) {
    double total = 0;
    for (int i = 0; i < Signal::kTerms; ++i) {
      signal->freq[i] = path.Uniform(0.05, 0.4);
      signal->phase[i] = path.Uniform(0, 2 * M_PI);
      signal->amp[i] = path.Uniform(0.5, 1.0);
      total += signal->amp[i];
    }
    for (double& a : signal->amp) a /= total;
  }
  const std::vector<double>& s = wand.marker_positions_m;
  const double s_mean = (s[0] + s[1] + s[2]) / 3.0;
  for (int k = 0; k < 3; ++k) offsets_m_[k] = s[k] - s_mean;
}

void WandPath::Markers(double t, Eigen::Vector3d markers[3]) const {
  Eigen::Vector3d c, d;
  for (int k = 0; k < 3; ++k) {
    c[k] = centre_m_[k] + half_size_m_[k] * centre_[k](t);
    d[k] = direction_[k](t);
  }
  if (d.norm() < 1e-3) d = Eigen::Vector3d::UnitX();
  d.normalize();
  for (int k = 0; k < 3; ++k) markers[k] = c + offsets_m_[k] * d;
}

bool WandSimulationOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& what) {
    if (error) *error = "wand simulation: " + what;
    return false;
  };
  if (!(duration_s > 0 && duration_s <= 3600)) return fail("duration_s must be in (0, 3600]");
  if (!(rate_hz > 0 && rate_hz <= 2000)) return fail("rate_hz must be in (0, 2000]");
  if (subsample < 1) return fail("subsample must be >= 1");
  if (!volume_centre_m.allFinite() || !(volume_half_size_m.minCoeff() > 0) ||
      !volume_half_size_m.allFinite())
    return fail("the volume must be finite with positive half sizes");
  if (!(noise_px >= 0 && noise_px < 10)) return fail("noise_px must be in [0, 10)");
  if (!(merge_px >= 0)) return fail("merge_px must be >= 0");
  if (!(dropout >= 0 && dropout < 1)) return fail("dropout must be in [0, 1)");
  if (max_strays < 0 || max_strays > 50) return fail("max_strays must be in [0, 50]");
  if (lframe_frames < 0) return fail("lframe_frames must be >= 0");
  std::string e;
  if (!wand.IsValid(&e) || !lframe.IsValid(&e)) return fail(e);
  return true;
}

Status SimulateWand(const std::vector<reconstruction::CameraModel>& truth,
                    const WandSimulationOptions& o, WandSimulation* out) {
  std::string error;
  if (!o.IsValid(&error)) return Status::Error(error);
  if (truth.size() < 2) return Status::Error("wand simulation: needs at least 2 cameras");
  *out = WandSimulation{};
  const int nc = static_cast<int>(truth.size());
  Random noise(o.seed, Stream::kWand, kNoise), strays(o.seed, Stream::kWand, kStrays),
      dropout(o.seed, Stream::kWand, kDropout);
  const WandPath path(o);
  const int total = static_cast<int>(std::floor(o.duration_s * o.rate_hz));
  for (int i = 0; i < total; i += o.subsample) {
    const double t = i / o.rate_hz;
    std::vector<Eigen::Vector3d> markers(3);
    path.Markers(t, markers.data());
    reconstruction::DetectionSet set;
    set.sequence = static_cast<std::uint64_t>(i);
    set.timestamp_ns = static_cast<std::uint64_t>(std::llround(t * 1e9));
    set.cameras.resize(nc);
    set.present.assign(nc, true);
    for (int cam = 0; cam < nc; ++cam) {
      set.cameras[cam] = Detect(truth[cam], cam, markers, o, noise, strays);
      set.cameras[cam].sequence = set.sequence;
      if (dropout.Uniform() < o.dropout) {
        set.present[cam] = false;
        set.cameras[cam].centroids.clear();
      }
    }
    out->wand_frames.push_back(std::move(set));
    out->wand_markers.push_back(std::move(markers));
  }
  // The L-frame lies still; the same stray process adds reflections that change every frame.
  for (int f = 0; f < o.lframe_frames; ++f) {
    reconstruction::DetectionSet set;
    set.sequence = static_cast<std::uint64_t>(f);
    set.cameras.resize(nc);
    set.present.assign(nc, true);
    for (int cam = 0; cam < nc; ++cam)
      set.cameras[cam] = Detect(truth[cam], cam, o.lframe.markers_m, o, noise, strays);
    out->lframe_frames.push_back(std::move(set));
  }
  return Status::Ok();
}

}  // namespace mocap::sim
