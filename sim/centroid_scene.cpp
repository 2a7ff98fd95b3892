#include "sim/centroid_scene.h"

#include <algorithm>

#include "sim/random.h"

namespace mocap::sim {

CentroidScene MakeCentroidScene(const std::vector<reconstruction::CameraModel>& rig,
                                const std::vector<Eigen::Vector3d>& markers,
                                const CentroidSceneOptions& o, std::uint64_t frame) {
  using reconstruction::Centroid;
  Random rng(o.seed, Stream::kImageNoise, frame);
  CentroidScene s;
  const int nc = static_cast<int>(rig.size());
  s.set.cameras.resize(nc);
  s.set.present.assign(nc, true);
  s.label.resize(nc);
  s.observed.assign(markers.size(), {});
  const double sigma = std::max(o.noise_px, 0.01);
  for (int c = 0; c < nc; ++c) {
    const reconstruction::CameraModel& cam = rig[c];
    std::vector<std::pair<Centroid, int>> list;
    for (std::size_t m = 0; m < markers.size(); ++m) {
      Eigen::Vector2d uv;
      if (!cam.Project(markers[m], &uv)) continue;
      if (uv.x() < 0 || uv.y() < 0 || uv.x() > cam.intrinsics.width - 1 ||
          uv.y() > cam.intrinsics.height - 1) {
        continue;
      }
      if (rng.Uniform() < o.hide) continue;
      if (o.visible && !o.visible(c, static_cast<int>(m))) continue;
      Centroid k;
      k.pixel = uv + o.noise_px * Eigen::Vector2d(rng.Normal(), rng.Normal());
      k.sigma_px = sigma;
      list.push_back({k, static_cast<int>(m)});
    }
    for (int r = 0; r < o.strays; ++r) {
      Centroid k;
      k.pixel = {rng.Uniform(0, cam.intrinsics.width - 1),
                 rng.Uniform(0, cam.intrinsics.height - 1)};
      k.sigma_px = sigma;
      list.push_back({k, -1});
    }
    for (int i = static_cast<int>(list.size()) - 1; i > 0; --i) {
      std::swap(list[i], list[rng.UniformInt(0, i)]);
    }
    s.set.cameras[c].camera = c;
    for (const auto& [k, m] : list) {
      if (m >= 0) s.observed[m].push_back({c, static_cast<int>(s.label[c].size())});
      s.set.cameras[c].centroids.push_back(k);
      s.label[c].push_back(m);
    }
  }
  return s;
}

}  // namespace mocap::sim
