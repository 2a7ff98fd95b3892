#include "solver/attach_markers.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <map>

#include "model/kinematics.h"

namespace mocap::solver {

namespace {

// A trial marker attached to `segment` where the trials put it in that segment's frame (scaled),
// written unscaled like the model's own; optional, as the trials may not all show it.
Marker MarkerAt(const Model& model, const std::string& name, int segment, const Eigen::Vector3d& local) {
  Marker m;
  m.name = name;
  m.segment = segment;
  m.position = local / model.segments()[segment].scale;
  m.optional = true;
  return m;
}

// The model with `markers` (its own and the attached ones after them); the model itself when none
// was attached.
Status WithMarkers(const Model& model, const std::vector<Marker>& markers, Model* out) {
  if (markers.size() == model.markers().size()) {
    *out = model;
    return Status::Ok();
  }
  return Model::Build(model.name(), model.segments(), model.joints(), model.coordinates(), markers,
                      model.derived_coordinates(), out);
}

}  // namespace

bool AttachOptions::IsValid(std::string* error) const {
  auto fail = [&](const char* what) {
    if (error) *error = what;
    return false;
  };
  if (!(max_spread_mm > 0)) return fail("max_spread_mm must be > 0");
  if (!(min_ratio >= 1)) return fail("min_ratio must be >= 1");
  if (!(spread_floor_mm >= 0)) return fail("spread_floor_mm must be >= 0");
  if (min_samples < 2) return fail("min_samples must be >= 2");
  return true;
}

Status MarkerSpreadOnSegments(const Model& model, const std::vector<formats::MarkerTrial>& trials,
                              const std::vector<Eigen::MatrixXd>& poses,
                              const std::vector<std::string>& names,
                              std::vector<MarkerOnSegments>* out) {
  if (poses.size() != trials.size())
    return Status::Error("marker spread: " + std::to_string(poses.size()) + " pose tables for " +
                         std::to_string(trials.size()) + " trials");
  const int ns = model.num_segments();
  // Per marker, per segment: sum and sum of squares of the local position.
  std::vector<std::vector<Eigen::Vector3d>> sum(names.size(),
                                                std::vector<Eigen::Vector3d>(ns, Eigen::Vector3d::Zero()));
  std::vector<std::vector<double>> sum_sq(names.size(), std::vector<double>(ns, 0.0));
  std::vector<int> count(names.size(), 0);
  const Geometry geometry(model);
  ModelData data(model);
  for (size_t t = 0; t < trials.size(); ++t) {
    const formats::MarkerTrial& trial = trials[t];
    if (poses[t].rows() != trial.num_frames() || poses[t].cols() != model.num_coordinates())
      return Status::Error("marker spread: trial '" + trial.name + "': poses are " +
                           std::to_string(poses[t].rows()) + "x" + std::to_string(poses[t].cols()) +
                           ", expected " + std::to_string(trial.num_frames()) + "x" +
                           std::to_string(model.num_coordinates()));
    std::vector<std::pair<int, int>> columns;  // (name index, trial column)
    for (size_t i = 0; i < names.size(); ++i)
      if (const int c = trial.FindMarker(names[i]); c >= 0) columns.emplace_back(static_cast<int>(i), c);
    if (columns.empty()) continue;
    for (int f = 0; f < trial.num_frames(); ++f) {
      if (!poses[t].row(f).allFinite()) continue;
      bool any = false;
      for (const auto& [i, c] : columns) any = any || trial.positions.row(f).segment<3>(3 * c).allFinite();
      if (!any) continue;
      ForwardKinematics(model, geometry, poses[t].row(f).transpose(), &data);
      for (const auto& [i, c] : columns) {
        const Eigen::Vector3d x = trial.positions.row(f).segment<3>(3 * c).transpose();
        if (!x.allFinite()) continue;
        for (int k = 0; k < ns; ++k) {
          const Eigen::Vector3d local = data.segment_rotation[k].transpose() * (x - data.segment_position[k]);
          sum[i][k] += local;
          sum_sq[i][k] += local.squaredNorm();
        }
        ++count[i];
      }
    }
  }
  out->assign(names.size(), MarkerOnSegments{});
  for (size_t i = 0; i < names.size(); ++i) {
    MarkerOnSegments& m = (*out)[i];
    m.samples = count[i];
    m.mean_local.assign(ns, Eigen::Vector3d::Zero());
    m.spread_mm.assign(ns, 0.0);
    if (count[i] == 0) continue;
    for (int k = 0; k < ns; ++k) {
      m.mean_local[k] = sum[i][k] / count[i];
      m.spread_mm[k] = 1000.0 * std::sqrt(std::max(0.0, sum_sq[i][k] / count[i] - m.mean_local[k].squaredNorm()));
    }
  }
  return Status::Ok();
}

Status AttachTrialMarkers(const Model& model, const std::vector<formats::MarkerTrial>& trials,
                          const std::vector<Eigen::MatrixXd>& poses, const AttachOptions& options,
                          Model* out, std::vector<AttachedMarker>* report) {
  std::string why;
  if (!options.IsValid(&why)) return Status::Error("attach markers: " + why);
  const int ns = model.num_segments();
  // The trial markers the model lacks, in order of first appearance.
  std::vector<std::string> order;
  for (const formats::MarkerTrial& trial : trials)
    for (const std::string& name : trial.marker_names)
      if (model.FindMarker(name) < 0 && std::find(order.begin(), order.end(), name) == order.end())
        order.push_back(name);
  std::vector<MarkerOnSegments> spreads;
  if (Status s = MarkerSpreadOnSegments(model, trials, poses, order, &spreads); !s)
    return Status::Error("attach markers: " + s.message());
  std::vector<Marker> markers = model.markers();
  report->clear();
  for (size_t i = 0; i < order.size(); ++i) {
    const std::string& name = order[i];
    const MarkerOnSegments& s = spreads[i];
    AttachedMarker a;
    a.name = name;
    a.samples = s.samples;
    if (s.samples < options.min_samples) {
      a.why_not = "seen with a pose in " + std::to_string(s.samples) + " frames, fewer than " +
                  std::to_string(options.min_samples);
      report->push_back(a);
      continue;
    }
    int best = -1, second = -1;
    const std::vector<double>& spread = s.spread_mm;
    for (int k = 0; k < ns; ++k) {
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
    } else if (second >= 0 &&
               a.runner_up_mm < options.min_ratio * std::max(a.spread_mm, options.spread_floor_mm)) {
      std::snprintf(text, sizeof text,
                    "rides on %s (%.1f mm) and %s (%.1f mm) alike: the trials do not move the joint between them enough to tell",
                    seg.c_str(), a.spread_mm, model.segments()[second].name.c_str(), a.runner_up_mm);
      a.why_not = text;
    } else {
      a.segment = seg;
      markers.push_back(MarkerAt(model, name, best, s.mean_local[best]));
    }
    report->push_back(a);
  }
  return WithMarkers(model, markers, out);
}

Status AttachMarkersByProximity(const Model& model, const std::vector<formats::MarkerTrial>& trials,
                                const std::vector<Eigen::MatrixXd>& poses, const std::vector<std::string>& names,
                                double min_ratio, double max_distance_mm, int min_samples, Model* out,
                                std::vector<AttachedMarker>* report) {
  if (!(min_ratio >= 1)) return Status::Error("attach markers by proximity: min_ratio must be >= 1");
  for (const std::string& name : names)
    if (model.FindMarker(name) >= 0)
      return Status::Error("attach markers by proximity: model " + model.name() + " already has a marker '" + name +
                           "'");
  std::vector<MarkerOnSegments> spreads;
  if (Status s = MarkerSpreadOnSegments(model, trials, poses, names, &spreads); !s)
    return Status::Error("attach markers by proximity: " + s.message());
  const int nm = model.num_markers(), ns = model.num_segments();
  // Per name, per model marker: the sum and count of their distances in frames with both.
  std::vector<std::vector<double>> sum(names.size(), std::vector<double>(nm, 0.0));
  std::vector<std::vector<int>> count(names.size(), std::vector<int>(nm, 0));
  for (const formats::MarkerTrial& t : trials) {
    std::vector<int> model_column(nm, -1);
    for (int m = 0; m < nm; ++m) model_column[m] = t.FindMarker(model.markers()[m].name);
    for (size_t i = 0; i < names.size(); ++i) {
      const int c = t.FindMarker(names[i]);
      if (c < 0) continue;
      for (int f = 0; f < t.num_frames(); ++f) {
        if (!t.Has(f, c)) continue;
        const Eigen::Vector3d x = t.At(f, c);
        for (int m = 0; m < nm; ++m)
          if (model_column[m] >= 0 && t.Has(f, model_column[m])) {
            sum[i][m] += (t.At(f, model_column[m]) - x).norm();
            ++count[i][m];
          }
      }
    }
  }
  std::vector<Marker> markers = model.markers();
  report->clear();
  for (size_t i = 0; i < names.size(); ++i) {
    AttachedMarker a;
    a.name = names[i];
    a.samples = spreads[i].samples;
    // The nearest model marker of each segment.
    std::vector<double> nearest(ns, std::numeric_limits<double>::infinity());
    for (int m = 0; m < nm; ++m)
      if (count[i][m] >= min_samples) {
        const int s = model.markers()[m].segment;
        nearest[s] = std::min(nearest[s], 1000.0 * sum[i][m] / count[i][m]);
      }
    int best = -1, second = -1;
    for (int s = 0; s < ns; ++s) {
      if (best < 0 || nearest[s] < nearest[best]) {
        second = best;
        best = s;
      } else if (second < 0 || nearest[s] < nearest[second]) {
        second = s;
      }
    }
    char text[200];
    if (a.samples < min_samples || best < 0 || !std::isfinite(nearest[best])) {
      std::snprintf(text, sizeof text, "seen with a pose and a model marker in fewer than %d frames", min_samples);
      a.why_not = text;
      report->push_back(a);
      continue;
    }
    a.spread_mm = nearest[best];
    a.runner_up_mm = second >= 0 ? nearest[second] : std::numeric_limits<double>::infinity();
    if (a.spread_mm > max_distance_mm) {
      std::snprintf(text, sizeof text, "%.0f mm from the nearest model marker (on %s): beside none (limit %.0f mm)",
                    a.spread_mm, model.segments()[best].name.c_str(), max_distance_mm);
      a.why_not = text;
    } else if (a.runner_up_mm < min_ratio * a.spread_mm) {
      std::snprintf(text, sizeof text,
                    "as near to %s's markers (%.0f mm) as to %s's (%.0f mm): the posture does not tell",
                    model.segments()[best].name.c_str(), a.spread_mm, model.segments()[second].name.c_str(),
                    a.runner_up_mm);
      a.why_not = text;
    } else {
      a.segment = model.segments()[best].name;
      markers.push_back(MarkerAt(model, names[i], best, spreads[i].mean_local[best]));
    }
    report->push_back(a);
  }
  return WithMarkers(model, markers, out);
}

std::vector<int> StackedMarkers(const Model& model, const std::vector<formats::MarkerTrial>& trials,
                                double tolerance_m) {
  const int nm = model.num_markers();
  std::vector<char> seen(nm, 0);
  for (const formats::MarkerTrial& t : trials)
    for (const std::string& name : t.marker_names)
      if (const int m = model.FindMarker(name); m >= 0) seen[m] = 1;
  const std::vector<char> stacked = StackedOnOnePoint(model, seen, tolerance_m);
  std::vector<int> out;
  for (int m = 0; m < nm; ++m)
    if (stacked[m]) out.push_back(m);
  return out;
}

Status PlaceMarkersOnTheirSegments(const Model& model, const std::vector<formats::MarkerTrial>& trials,
                                   const std::vector<Eigen::MatrixXd>& poses, const std::vector<Marker>& markers,
                                   const AttachOptions& options, Model* out, std::vector<PlacedMarker>* report) {
  std::string why;
  if (!options.IsValid(&why)) return Status::Error("place markers: " + why);
  std::vector<std::string> names;
  for (const Marker& m : markers) {
    if (m.segment < 0 || m.segment >= model.num_segments())
      return Status::Error("place markers: marker '" + m.name + "' has no segment of model " + model.name());
    if (model.FindMarker(m.name) >= 0)
      return Status::Error("place markers: model " + model.name() + " already has a marker '" + m.name + "'");
    names.push_back(m.name);
  }
  std::vector<MarkerOnSegments> spreads;
  if (Status s = MarkerSpreadOnSegments(model, trials, poses, names, &spreads); !s)
    return Status::Error("place markers: " + s.message());
  std::vector<Marker> all = model.markers();
  report->clear();
  for (size_t i = 0; i < markers.size(); ++i) {
    Marker m = markers[i];
    const int seg = m.segment;
    const double scale = model.segments()[seg].scale;
    PlacedMarker p;
    p.name = m.name;
    p.segment = model.segments()[seg].name;
    p.samples = spreads[i].samples;
    if (p.samples < options.min_samples) {
      p.why_not = "seen with a pose in " + std::to_string(p.samples) + " frames, fewer than " +
                  std::to_string(options.min_samples) + ": kept at the model's place";
    } else {
      const Eigen::Vector3d local = spreads[i].mean_local[seg] / scale;  // unscaled, like the model's
      p.from_model_mm = 1000.0 * scale * (local - m.position).norm();
      p.spread_mm = spreads[i].spread_mm[seg];
      m.position = local;
    }
    all.push_back(m);
    report->push_back(p);
  }
  return Model::Build(model.name(), model.segments(), model.joints(), model.coordinates(), all,
                      model.derived_coordinates(), out);
}

Status TieCentreMarkers(const std::vector<formats::MarkerTrial>& trials, double tolerance_m, Model* model,
                        std::vector<CentreMarker>* tied) {
  tied->clear();
  if (!(tolerance_m > 0)) return Status::Error("tie centre markers: the tolerance must be > 0");
  const Geometry g(*model);
  ModelData d(*model);
  ForwardKinematics(*model, g, model->DefaultCoordinates(), &d);
  std::vector<Marker> markers = model->markers();
  for (int m = 0; m < model->num_markers(); ++m) {
    bool seen = false;
    for (const formats::MarkerTrial& t : trials) {
      const int c = t.FindMarker(markers[m].name);
      for (int f = 0; c >= 0 && f < t.num_frames() && !seen; ++f) seen = t.Has(f, c);
    }
    if (!seen) continue;
    const Eigen::Vector3d x = MarkerPosition(*model, g, d, m);
    int nearest = -1;
    double distance = tolerance_m;
    for (int j = 0; j < model->num_joints(); ++j) {
      const Joint& jt = model->joints()[j];
      if (jt.parent < 0 || (markers[m].segment != jt.parent && markers[m].segment != jt.child)) continue;
      const double r = (x - JointCentre(*model, d, j)).norm();
      if (r <= distance) distance = r, nearest = j;
    }
    if (nearest < 0) continue;
    tied->push_back({markers[m].name, model->joints()[nearest].name, markers[m].segment, markers[m].position,
                     1000.0 * distance});
    markers[m].segment = model->joints()[nearest].child;
    markers[m].position.setZero();
  }
  if (tied->empty()) return Status::Ok();
  return Model::Build(model->name(), model->segments(), model->joints(), model->coordinates(), markers,
                      model->derived_coordinates(), model);
}

Status UntieCentreMarkers(const std::vector<CentreMarker>& tied, Model* fitted) {
  if (tied.empty()) return Status::Ok();
  std::vector<Marker> markers = fitted->markers();
  const Eigen::VectorXd p = fitted->InitialParameters();
  for (const CentreMarker& c : tied) {
    const int m = fitted->FindMarker(c.marker), j = fitted->FindJoint(c.joint);
    if (m < 0 || j < 0)
      return Status::Error("untie centre markers: the fitted model has no " +
                           (m < 0 ? "marker '" + c.marker + "'" : "joint '" + c.joint + "'"));
    const Joint& jt = fitted->joints()[j];
    markers[m].segment = c.segment;
    markers[m].position =
        c.segment == jt.child ? Eigen::Vector3d::Zero() : Eigen::Vector3d(p.segment<3>(fitted->centre_index(j)));
  }
  return Model::Build(fitted->name(), fitted->segments(), fitted->joints(), fitted->coordinates(), markers,
                      fitted->derived_coordinates(), fitted);
}

std::pair<int, int> LandmarkPairAbout(const Model& model, int j) {
  const Geometry g(model);
  ModelData d(model);
  ForwardKinematics(model, g, model.DefaultCoordinates(), &d);
  const Joint& jt = model.joints()[j];
  Eigen::Vector3d axis = Eigen::Vector3d::Zero();
  for (size_t e = 0; e < jt.elements.size() && axis.isZero(); ++e)
    if (jt.elements[e].kind == ElementKind::kRotation && !jt.elements[e].function.IsConstant())
      axis = d.element_rotation[j][e] * g.axis[j][e];
  if (axis.isZero()) return {-1, -1};
  const Eigen::Vector3d centre = JointCentre(model, d, j);
  std::vector<std::pair<int, Eigen::Vector3d>> near;
  for (int m = 0; m < model.num_markers(); ++m) {
    const int s = model.markers()[m].segment;
    if (s != jt.parent && s != jt.child) continue;
    const Eigen::Vector3d x = MarkerPosition(model, g, d, m);
    if ((x - centre).norm() < 0.12) near.emplace_back(m, x);
  }
  std::pair<int, int> best{-1, -1};
  double best_offset = 0.035;
  for (size_t a = 0; a < near.size(); ++a)
    for (size_t b = a + 1; b < near.size(); ++b) {
      const Eigen::Vector3d v = near[b].second - near[a].second;
      const double separation = v.norm();
      if (separation < 0.05 || separation > 0.2 ||
          std::abs(v.normalized().dot(axis.normalized())) < std::cos(M_PI / 6))
        continue;
      const double offset = (0.5 * (near[a].second + near[b].second) - centre).norm();
      if (offset <= best_offset) best_offset = offset, best = {near[a].first, near[b].first};
    }
  return best;
}

}  // namespace mocap::solver
