#include "daemon/detection_health.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace mocap::daemon {

bool DetectionHealthOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& m) {
    if (error) *error = m;
    return false;
  };
  if (max_centroids_per_camera < 1) return fail("max_centroids_per_camera must be >= 1");
  if (sample_every < 1) return fail("sample_every must be >= 1");
  if (window < 1 || min_samples < 1 || min_samples > window)
    return fail("need 1 <= min_samples <= window");
  if (!(match_radius_px > 0) || !(suspect_px > 0)) return fail("radii must be > 0");
  return true;
}

DetectionHealth::DetectionHealth(int num_cameras, DetectionHealthOptions options)
    : options_(options), cameras_(static_cast<std::size_t>(std::max(0, num_cameras))) {
  for (PerCamera& c : cameras_) c.ring.assign(static_cast<std::size_t>(options_.window), 0.f);
  sort_scratch_.reserve(static_cast<std::size_t>(options_.window));
}

const reconstruction::DetectionSet& DetectionHealth::Sanitize(
    const reconstruction::DetectionSet& set, reconstruction::DetectionSet* scratch) {
  auto finite = [](const reconstruction::Centroid& c) { return c.pixel.allFinite(); };
  bool clean = true;
  for (std::size_t c = 0; c < set.cameras.size() && clean; ++c) {
    if (c < set.present.size() && !set.present[c]) continue;
    const auto& cs = set.cameras[c].centroids;
    clean = static_cast<int>(cs.size()) <= options_.max_centroids_per_camera &&
            std::all_of(cs.begin(), cs.end(), finite);
  }
  if (clean) return set;

  scratch->sequence = set.sequence;
  scratch->timestamp_ns = set.timestamp_ns;
  scratch->first_arrival_ns = set.first_arrival_ns;
  scratch->present = set.present;
  scratch->cameras.resize(set.cameras.size());
  std::lock_guard<std::mutex> lock(mutex_);
  for (std::size_t c = 0; c < set.cameras.size(); ++c) {
    const reconstruction::CameraDetections& in = set.cameras[c];
    reconstruction::CameraDetections& out = scratch->cameras[c];
    out.camera = in.camera;
    out.sequence = in.sequence;
    out.device_timestamp_ns = in.device_timestamp_ns;
    out.host_timestamp_ns = in.host_timestamp_ns;
    out.centroids.clear();
    const bool present = c >= set.present.size() || set.present[c];
    if (!present) continue;
    PerCamera* health = c < cameras_.size() ? &cameras_[c] : nullptr;
    if (static_cast<int>(in.centroids.size()) > options_.max_centroids_per_camera) {
      if (c < scratch->present.size()) scratch->present[c] = false;
      if (health) ++health->counts.overfull_sets;
      continue;
    }
    for (const reconstruction::Centroid& k : in.centroids) {
      if (finite(k)) {
        out.centroids.push_back(k);
      } else if (health) {
        ++health->counts.nonfinite_centroids;
      }
    }
  }
  return *scratch;
}

void DetectionHealth::Observe(const reconstruction::DetectionSet& set,
                              const std::vector<reconstruction::TriangulatedPoint>& points,
                              const std::vector<reconstruction::CameraModel>& cameras) {
  if (observed_++ % static_cast<std::uint64_t>(options_.sample_every) != 0) return;
  const std::size_t n = std::min({cameras.size(), set.cameras.size(), cameras_.size()});
  std::lock_guard<std::mutex> lock(mutex_);
  for (const reconstruction::TriangulatedPoint& p : points) {
    if (p.camera_count < 3 || !p.position.allFinite()) continue;
    for (std::size_t c = 0; c < n; ++c) {
      if (c < set.present.size() && !set.present[c]) continue;
      const auto& centroids = set.cameras[c].centroids;
      Eigen::Vector2d pixel;
      if (centroids.empty() || !cameras[c].Project(p.position, &pixel)) continue;
      double error = std::numeric_limits<double>::infinity();
      for (int v = 0; v < p.camera_count; ++v) {
        const reconstruction::PointView& view = p.views[static_cast<std::size_t>(v)];
        if (view.camera == static_cast<int>(c) && view.centroid >= 0 &&
            view.centroid < static_cast<int>(centroids.size()))
          error = (centroids[static_cast<std::size_t>(view.centroid)].pixel - pixel).norm();
      }
      if (!std::isfinite(error)) {  // not used by the triangulation: its nearest blob, if close
        for (const reconstruction::Centroid& k : centroids) error = std::min(error, (k.pixel - pixel).norm());
        if (!(error <= options_.match_radius_px)) continue;
      }
      PerCamera& h = cameras_[c];
      h.ring[static_cast<std::size_t>(h.next)] = static_cast<float>(error);
      h.next = (h.next + 1) % options_.window;
      h.filled = std::min(h.filled + 1, options_.window);
      h.changed = true;
    }
  }
}

void DetectionHealth::ResetReprojection() {
  std::lock_guard<std::mutex> lock(mutex_);
  for (PerCamera& c : cameras_) {
    c.next = c.filled = 0;
    c.median = 0;
    c.changed = false;
  }
}

std::vector<CameraHealth> DetectionHealth::Snapshot() const {
  std::lock_guard<std::mutex> lock(mutex_);
  std::vector<CameraHealth> out;
  out.reserve(cameras_.size());
  for (PerCamera& c : cameras_) {
    CameraHealth h = c.counts;
    h.reprojection_samples = c.filled;
    if (c.filled >= options_.min_samples) {
      if (c.changed) {
        sort_scratch_.assign(c.ring.begin(), c.ring.begin() + c.filled);
        auto mid = sort_scratch_.begin() + c.filled / 2;
        std::nth_element(sort_scratch_.begin(), mid, sort_scratch_.end());
        c.median = *mid;
        c.changed = false;
      }
      h.reprojection_px = c.median;
      h.calibration_suspect = h.reprojection_px > options_.suspect_px;
    }
    out.push_back(h);
  }
  return out;
}

}  // namespace mocap::daemon
