#include "solver/attach_markers.h"

#include <algorithm>
#include <cmath>
#include <map>

#include "model/kinematics.h"

namespace mocap::solver {

bool AttachOptions::IsValid(std::string* error) const {
  auto fail = [&](const char* what) {
    if (error) *error = what;
    return false;
  };
  if (!(max_spread_mm > 0)) return fail("max_spread_mm must be > 0");
  if (!(min_ratio >= 1)) return fail("min_ratio must be >= 1");
  if (min_samples < 2) return fail("min_samples must be >= 2");
  return true;
}

Status AttachTrialMarkers(const Model& model, const std::vector<formats::MarkerTrial>& trials,
                          const std::vector<Eigen::MatrixXd>& poses, const AttachOptions& options,
                          Model* out, std::vector<AttachedMarker>* report) {
  std::string why;
  if (!options.IsValid(&why)) return Status::Error("attach markers: " + why);
  if (poses.size() != trials.size())
    return Status::Error("attach markers: " + std::to_string(poses.size()) + " pose tables for " +
                         std::to_string(trials.size()) + " trials");
  const int ns = model.num_segments();
  // Per candidate marker, per segment: sum and sum of squares of the local position, count.
  struct Sums {
    std::vector<Eigen::Vector3d> sum;
    std::vector<double> sum_sq;
    int n = 0;
  };
  std::map<std::string, Sums> candidates;
  std::vector<std::string> order;
  const Geometry geometry(model);
  ModelData data(model);
  for (size_t t = 0; t < trials.size(); ++t) {
    const formats::MarkerTrial& trial = trials[t];
    if (poses[t].rows() != trial.num_frames() || poses[t].cols() != model.num_coordinates())
      return Status::Error("attach markers: trial '" + trial.name + "': poses are " +
                           std::to_string(poses[t].rows()) + "x" + std::to_string(poses[t].cols()));
    std::vector<int> columns;
    for (int c = 0; c < trial.num_markers(); ++c) {
      const std::string& name = trial.marker_names[c];
      if (model.FindMarker(name) >= 0) continue;
      columns.push_back(c);
      if (candidates.emplace(name, Sums{std::vector<Eigen::Vector3d>(ns, Eigen::Vector3d::Zero()),
                                        std::vector<double>(ns, 0.0), 0})
              .second)
        order.push_back(name);
    }
    if (columns.empty()) continue;
    for (int f = 0; f < trial.num_frames(); ++f) {
      if (!poses[t].row(f).allFinite()) continue;
      bool any = false;
      for (int c : columns) any = any || trial.positions.row(f).segment<3>(3 * c).allFinite();
      if (!any) continue;
      ForwardKinematics(model, geometry, poses[t].row(f).transpose(), &data);
      for (int c : columns) {
        const Eigen::Vector3d x = trial.positions.row(f).segment<3>(3 * c).transpose();
        if (!x.allFinite()) continue;
        Sums& s = candidates[trial.marker_names[c]];
        for (int k = 0; k < ns; ++k) {
          const Eigen::Vector3d local = data.segment_rotation[k].transpose() * (x - data.segment_position[k]);
          s.sum[k] += local;
          s.sum_sq[k] += local.squaredNorm();
        }
        ++s.n;
      }
    }
  }
  std::vector<Marker> markers = model.markers();
  report->clear();
  for (const std::string& name : order) {
    const Sums& s = candidates[name];
    AttachedMarker a;
    a.name = name;
    a.samples = s.n;
    if (s.n < options.min_samples) {
      a.why_not = "seen with a pose in " + std::to_string(s.n) + " frames, fewer than " +
                  std::to_string(options.min_samples);
      report->push_back(a);
      continue;
    }
    int best = -1, second = -1;
    std::vector<double> spread(ns);
    for (int k = 0; k < ns; ++k) {
      const Eigen::Vector3d mean = s.sum[k] / s.n;
      spread[k] = 1000.0 * std::sqrt(std::max(0.0, s.sum_sq[k] / s.n - mean.squaredNorm()));
      if (best < 0 || spread[k] < spread[best]) {
        second = best;
        best = k;
      } else if (second < 0 || spread[k] < spread[second]) {
        second = k;
      }
    }
    a.spread_mm = spread[best];
    a.runner_up_mm = second >= 0 ? spread[second] : 0.0;
    const std::string seg = model.segments()[best].name;
    char text[200];
    if (a.spread_mm > options.max_spread_mm) {
      std::snprintf(text, sizeof text, "moves %.1f mm RMS even on %s, the segment it follows best (limit %.0f mm)",
                    a.spread_mm, seg.c_str(), options.max_spread_mm);
      a.why_not = text;
    } else if (second >= 0 && a.runner_up_mm < options.min_ratio * a.spread_mm) {
      std::snprintf(text, sizeof text,
                    "rides on %s (%.1f mm) and %s (%.1f mm) alike: the trials do not move the joint between them enough to tell",
                    seg.c_str(), a.spread_mm, model.segments()[second].name.c_str(), a.runner_up_mm);
      a.why_not = text;
    } else {
      a.segment = seg;
      Marker m;
      m.name = name;
      m.segment = best;
      m.position = s.sum[best] / s.n / model.segments()[best].scale;  // unscaled, like the model's
      m.optional = true;
      markers.push_back(m);
    }
    report->push_back(a);
  }
  if (markers.size() == model.markers().size()) {
    *out = model;
    return Status::Ok();
  }
  return Model::Build(model.name(), model.segments(), model.joints(), model.coordinates(), markers,
                      model.derived_coordinates(), out);
}

}  // namespace mocap::solver
