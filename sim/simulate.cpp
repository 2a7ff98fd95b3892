#include "sim/simulate.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <nlohmann/json.hpp>

#include "model/compare.h"
#include "model/kinematics.h"
#include "sim/motion.h"
#include "sim/random.h"
#include "sim/sta_table.h"

namespace mocap::sim {
namespace {

constexpr double kDeg = M_PI / 180.0;
// A guard against options that would exhaust memory (2 million frames of 43 markers is ~2 GB).
constexpr long kMaxFrames = 2'000'000;

using formats::RowMatrix;

// Poses a movement: the true coordinates (model units: radians, metres) and the noise-free marker
// positions (metres, 3 columns per marker of `markers`). The pelvis translation is placed frame
// by frame: its height puts the feet on the floor (a soft minimum over the sole points' heights
// above their baselines), and its horizontal position follows the planned sway minus the
// accumulated motion of the weight-bearing foot (the soft-minimum weights times the points'
// frame-to-frame displacements), so the stance foot stays where it is.
void PoseMovement(const Model& truth, const Geometry& geometry, const RootLayout& root,
                  const FootContacts& feet, const MovementPlan& plan,
                  const std::vector<int>& markers, double rate_hz, RowMatrix* z_out,
                  RowMatrix* positions) {
  const int nf = plan.frames, nc = truth.num_coordinates();
  const int nm = static_cast<int>(markers.size()), np = feet.size();
  z_out->resize(nf, nc);
  positions->resize(nf, 3 * nm);
  ModelData data(truth);
  Eigen::VectorXd z(nc);
  std::vector<Eigen::Vector3d> point(np);
  std::vector<double> weight(np);
  StanceDrift drift(np);
  const double default_height = truth.coordinates()[root.tz].default_value;

  for (int f = 0; f < nf; ++f) {
    const double t = f / rate_hz;
    plan.Coordinates(truth, t, &z);
    z[root.tx] = z[root.ty] = z[root.tz] = 0.0;
    ForwardKinematics(truth, geometry, z, &data);

    const Eigen::Vector2d sway = plan.Sway(t);
    Eigen::Vector3d offset(sway.x(), sway.y(), default_height);
    if (np > 0) {
      const double soft_lowest = SoleContact(feet, data, point.data(), weight.data());
      offset.head<2>() -= drift.Add(point.data(), weight.data());
      offset.z() = -soft_lowest;
    }
    z[root.tx] = offset.x();
    z[root.ty] = offset.y();
    z[root.tz] = offset.z();
    z_out->row(f) = z.transpose();
    // The root translations come first and act along the lab axes: adding the offset to the
    // positions of the untranslated pose is the same as posing with it.
    for (int i = 0; i < nm; ++i)
      positions->row(f).segment<3>(3 * i) =
          (MarkerPosition(truth, geometry, data, markers[i]) + offset).transpose();
  }
}

// Soft-tissue artefact maps, one per simulated marker: displacement in the segment frame =
// gain * (q - mean)[coordinates], scaled to the requested RMS over the whole session.
struct StaMap {
  std::vector<int> coordinates;  // rotational coordinates of the joints adjacent to the segment
  Eigen::Matrix3Xd gain;
};

std::vector<StaMap> MakeStaMaps(const Model& truth, const std::vector<int>& markers,
                                const std::vector<double>& rms_mm, const std::vector<RowMatrix>& z,
                                const Eigen::VectorXd& mean, const SimulationOptions& options) {
  // Second moments about the session mean, per movement: the artefact is scaled so that its RMS
  // is the marker's amplitude (rms_mm: sta_mm x its STA table ratio) in the movement that moves
  // the marker most. Scaling over the whole session instead would put all of a joint's artefact
  // into the one movement that moves it (head markers swinging by four times their amplitude
  // during neck range of motion).
  std::vector<Eigen::MatrixXd> covs;
  for (const RowMatrix& zm : z) {
    const Eigen::MatrixXd centred = zm.rowwise() - mean.transpose();
    covs.push_back(centred.transpose() * centred / static_cast<double>(std::max<Eigen::Index>(1, zm.rows())));
  }

  std::vector<StaMap> maps(markers.size());
  for (size_t i = 0; i < markers.size(); ++i) {
    const int m = markers[i];
    const int s = truth.markers()[m].segment;
    StaMap& map = maps[i];
    for (const Joint& j : truth.joints()) {
      const bool proximal = j.child == s && j.parent >= 0;
      const bool distal = j.parent == s;
      if (!proximal && !distal) continue;
      for (const JointElement& e : j.elements)
        if (e.coordinate >= 0 && truth.coordinates()[e.coordinate].rotational)
          map.coordinates.push_back(e.coordinate);
    }
    const int k = static_cast<int>(map.coordinates.size());
    Random rng(options.seed, Stream::kSta, static_cast<std::uint64_t>(m));
    map.gain.resize(3, k);
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < k; ++c) map.gain(r, c) = rng.Normal();
    Eigen::MatrixXd sub(k, k);
    double mean_square = 0;
    for (const Eigen::MatrixXd& cov : covs) {
      for (int a = 0; a < k; ++a)
        for (int b = 0; b < k; ++b) sub(a, b) = cov(map.coordinates[a], map.coordinates[b]);
      mean_square = std::max(mean_square, (map.gain * sub * map.gain.transpose()).trace());
    }
    if (k == 0 || !(mean_square > 1e-18)) {
      map.gain.setZero();  // nothing moves this segment relative to its neighbours
      continue;
    }
    map.gain *= rms_mm[i] * 1e-3 / std::sqrt(mean_square);
  }
  return maps;
}

void AddSta(const Model& truth, const Geometry& geometry, const std::vector<int>& markers,
            const std::vector<StaMap>& maps, const Eigen::VectorXd& mean, const RowMatrix& z,
            RowMatrix* positions) {
  ModelData data(truth);
  Eigen::VectorXd q(truth.num_coordinates());
  for (int f = 0; f < z.rows(); ++f) {
    q = z.row(f).transpose();
    ForwardKinematics(truth, geometry, q, &data);
    for (size_t i = 0; i < markers.size(); ++i) {
      const StaMap& map = maps[i];
      Eigen::Vector3d local = Eigen::Vector3d::Zero();
      for (size_t c = 0; c < map.coordinates.size(); ++c)
        local += map.gain.col(c) * (q[map.coordinates[c]] - mean[map.coordinates[c]]);
      const int s = truth.markers()[markers[i]].segment;
      positions->row(f).segment<3>(3 * i) += (data.segment_rotation[s] * local).transpose();
    }
  }
}

}  // namespace

void AddMarkerNoise(double sigma_m, Random& rng, RowMatrix* positions) {
  for (int f = 0; f < positions->rows(); ++f)
    for (int c = 0; c < positions->cols(); ++c) (*positions)(f, c) += sigma_m * rng.Normal();
}

void RemoveMarkerSamples(double fraction, Random& rng, RowMatrix* positions) {
  const int nf = static_cast<int>(positions->rows());
  const int nm = static_cast<int>(positions->cols() / 3);
  const long total = static_cast<long>(nf) * nm;
  const long target = std::lround(fraction * total);
  if (target <= 0 || nm == 0) return;
  std::vector<char> gone(static_cast<size_t>(total), 0);
  long removed = 0;
  const double nan = std::numeric_limits<double>::quiet_NaN();
  for (long attempt = 0; removed < target && attempt < 1000 * target; ++attempt) {
    const int m = rng.UniformInt(0, nm - 1);
    const int length = std::min(nf, rng.UniformInt(5, 30));
    const int start = rng.UniformInt(0, nf - length);
    for (int f = start; f < start + length; ++f) {
      char& g = gone[static_cast<size_t>(f) * nm + m];
      if (g) continue;
      g = 1;
      ++removed;
      positions->row(f).segment<3>(3 * m).setConstant(nan);
    }
  }
}

bool SimulationOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& message) {
    if (error) *error = message;
    return false;
  };
  auto show = [](double v) {
    char buf[32];
    std::snprintf(buf, sizeof buf, "%g", v);
    return std::string(buf);
  };
  if (!(std::isfinite(noise_mm) && noise_mm >= 0.0))
    return fail("noise_mm must be a finite number >= 0 (got " + show(noise_mm) + ")");
  if (!(std::isfinite(sta_mm) && sta_mm >= 0.0))
    return fail("sta_mm must be a finite number >= 0 (got " + show(sta_mm) + ")");
  if (!(missing >= 0.0 && missing < 0.9))
    return fail("missing must be a fraction in [0, 0.9) (got " + show(missing) + ")");
  if (!(std::isfinite(rate_hz) && rate_hz > 0.0 && rate_hz <= 10000.0))
    return fail("rate_hz must be in (0, 10000] (got " + show(rate_hz) + ")");
  if (!(std::isfinite(duration_scale) && duration_scale > 0.0 && duration_scale <= 1000.0))
    return fail("duration_scale must be in (0, 1000] (got " + show(duration_scale) +
                ")");
  std::string subject_error;
  if (!subject.IsValid(&subject_error)) return fail("subject." + subject_error);
  return true;
}

int SimulatedSession::total_frames() const {
  int n = 0;
  for (const SimulatedTrial& t : trials) n += t.markers.num_frames();
  return n;
}

std::vector<int> SimulatedMarkers(const Model& model, bool optional_markers) {
  std::vector<int> out;
  for (int m = 0; m < model.num_markers(); ++m)
    if (optional_markers || !model.markers()[m].optional) out.push_back(m);
  return out;
}

Eigen::VectorXd TrueCoordinates(const Model& model, const formats::CoordinateTable& table,
                                int frame) {
  Eigen::VectorXd z = model.DefaultCoordinates();
  for (size_t k = 0; k < table.column_names.size(); ++k) {
    const int c = model.FindCoordinate(table.column_names[k]);
    if (c < 0) continue;
    const double v = table.values(frame, static_cast<Eigen::Index>(k));
    z[c] = model.coordinates()[c].rotational && table.in_degrees ? v * kDeg : v;
  }
  return z;
}

Status MakeSessionModels(const VirtualSubject& subject, const std::vector<int>& markers,
                         SessionModels* models) {
  SessionModels out;
  // The session's models carry exactly the markers it records: a marker no trial shows is not
  // fitted, and comparing an unfitted marker with the truth would only measure its nominal offset.
  MOCAP_RETURN_IF_ERROR(subject.nominal.WithMarkers(markers, &out.nominal));
  const Model& full = subject.nominal;
  const int first_marker = full.num_markers() > 0 ? full.marker_index(0) : full.num_parameters();
  Eigen::VectorXd p(out.nominal.num_parameters());
  p.head(first_marker) = subject.truth_parameters.head(first_marker);
  for (size_t i = 0; i < markers.size(); ++i)
    p.segment<3>(out.nominal.marker_index(static_cast<int>(i))) =
        subject.truth_parameters.segment<3>(full.marker_index(markers[i]));
  out.truth_parameters = p;
  MOCAP_RETURN_IF_ERROR(subject.truth.WithMarkers(markers, &out.truth));
  *models = std::move(out);
  return Status::Ok();
}

Status SimulateSession(const SimulationOptions& options, SimulatedSession* session) {
  return SimulateSession(options, DefaultProtocol(), session);
}

Status SimulateSession(const SimulationOptions& options, const Protocol& protocol,
                       SimulatedSession* session) {
  std::string error;
  if (!options.IsValid(&error)) return Status::Error("invalid simulation options: " + error);
  VirtualSubject subject;
  MOCAP_RETURN_IF_ERROR(MakeVirtualSubject(options.seed, options.subject, &subject));
  const Model& truth = subject.truth;
  if (Status s = ValidateProtocol(protocol, truth); !s) return s;
  RootLayout root;
  if (Status s = FindRootLayout(truth, &root); !s) return s;

  const int nmov = static_cast<int>(protocol.movements.size());
  std::vector<MovementPlan> plans;
  long total = 0;
  for (int i = 0; i < nmov; ++i) {
    plans.push_back(PlanMovement(truth, root, protocol.movements[i], options, i));
    total += plans.back().frames;
  }
  const std::vector<int> markers = SimulatedMarkers(truth, options.medial_markers);
  if (total > kMaxFrames)
    return Status::Error("simulation too large: " + std::to_string(total) + " frames (at most " +
                         std::to_string(kMaxFrames) + "); lower rate_hz or duration_scale");

  const Geometry geometry(truth);
  const FootContacts feet = MakeFootContacts(truth, geometry, root, subject.height_m);
  std::vector<RowMatrix> z(nmov), positions(nmov);
  for (int i = 0; i < nmov; ++i)
    PoseMovement(truth, geometry, root, feet, plans[i], markers, options.rate_hz, &z[i],
                 &positions[i]);

  std::vector<double> sta_rms_mm;
  for (int m : markers)
    sta_rms_mm.push_back(options.sta_mm * DefaultStaTable().RatioOf(truth.markers()[m].name));
  if (options.sta_mm > 0.0) {
    Eigen::VectorXd mean = Eigen::VectorXd::Zero(truth.num_coordinates());
    for (const RowMatrix& zm : z) mean += zm.colwise().sum().transpose();
    mean /= static_cast<double>(std::max(1L, total));
    const std::vector<StaMap> maps = MakeStaMaps(truth, markers, sta_rms_mm, z, mean, options);
    for (int i = 0; i < nmov; ++i) AddSta(truth, geometry, markers, maps, mean, z[i], &positions[i]);
  }

  SimulatedSession out;
  out.options = options;
  out.height_m = subject.height_m;
  out.sta_rms_mm = std::move(sta_rms_mm);
  SessionModels models;
  MOCAP_RETURN_IF_ERROR(MakeSessionModels(subject, markers, &models));
  out.nominal = std::move(models.nominal);
  out.truth_parameters = std::move(models.truth_parameters);
  out.protocol = protocol;
  std::vector<std::string> marker_names, coordinate_names;
  for (int m : markers) marker_names.push_back(truth.markers()[m].name);
  for (const Coordinate& c : truth.coordinates()) coordinate_names.push_back(c.name);
  for (int i = 0; i < nmov; ++i) {
    const std::string& name = protocol.movements[i].name;
    if (options.noise_mm > 0.0) {
      Random rng(options.seed, Stream::kNoise, static_cast<std::uint64_t>(i));
      AddMarkerNoise(options.noise_mm * 1e-3, rng, &positions[i]);
    }
    if (options.missing > 0.0) {
      Random rng(options.seed, Stream::kMissing, static_cast<std::uint64_t>(i));
      RemoveMarkerSamples(options.missing, rng, &positions[i]);
    }
    const int nf = plans[i].frames;
    SimulatedTrial trial;
    trial.markers.name = name;
    trial.markers.rate_hz = options.rate_hz;
    trial.markers.marker_names = marker_names;
    trial.markers.frame_numbers.resize(nf);
    trial.markers.times.resize(nf);
    for (int f = 0; f < nf; ++f) {
      trial.markers.frame_numbers[f] = f + 1;
      trial.markers.times[f] = f / options.rate_hz;
    }
    trial.markers.positions = std::move(positions[i]);
    trial.coordinates.name = name;
    trial.coordinates.column_names = coordinate_names;
    trial.coordinates.times = trial.markers.times;
    trial.coordinates.in_degrees = true;
    trial.coordinates.values = std::move(z[i]);
    for (int c = 0; c < truth.num_coordinates(); ++c)
      if (truth.coordinates()[c].rotational) trial.coordinates.values.col(c) /= kDeg;
    out.trials.push_back(std::move(trial));
  }
  out.truth = std::move(models.truth);
  *session = std::move(out);
  return Status::Ok();
}

std::vector<double> JointCentreTrackRmsMm(const SimulatedSession& session, const Model& fitted,
                                          const std::vector<Eigen::MatrixXd>& coordinates) {
  return JointCentreTrackRmsMm(session.truth, session.trials, fitted, coordinates);
}

std::vector<double> JointCentreTrackRmsMm(const Model& truth, const std::vector<SimulatedTrial>& trials,
                                          const Model& fitted, const std::vector<Eigen::MatrixXd>& coordinates) {
  const Geometry gt(truth), gf(fitted);
  ModelData dt(truth), df(fitted);
  std::vector<double> sum(truth.num_joints(), 0.0);
  long n = 0;
  for (size_t t = 0; t < trials.size() && t < coordinates.size(); ++t)
    for (int f = 0; f < trials[t].markers.num_frames(); ++f) {
      ForwardKinematics(truth, gt, TrueCoordinates(truth, trials[t].coordinates, f), &dt);
      ForwardKinematics(fitted, gf, coordinates[t].row(f).transpose(), &df);
      for (int j = 0; j < truth.num_joints(); ++j) {
        Eigen::Vector3d d = JointCentre(fitted, df, j) - JointCentre(truth, dt, j);
        if (const int e = AlongAxisGaugeElement(truth.joints()[j]); e >= 0) {
          const Eigen::Vector3d u = (dt.element_rotation[j][e] * gt.axis[j][e]).normalized();
          d -= d.dot(u) * u;
        }
        sum[j] += d.squaredNorm();
      }
      ++n;
    }
  for (double& v : sum) v = 1000.0 * std::sqrt(v / std::max(1L, n));
  return sum;
}

std::string SessionSummaryJson(const SimulatedSession& session) {
  using json = nlohmann::ordered_json;  // keeps "format" and "version" first
  const SimulationOptions& o = session.options;
  json doc;
  doc["format"] = "mocap-sim-subject";
  doc["version"] = 1;
  doc["seed"] = o.seed;
  doc["height_m"] = session.height_m;
  doc["options"] = {{"seed", o.seed},
                    {"noise_mm", o.noise_mm},
                    {"sta_mm", o.sta_mm},
                    {"missing", o.missing},
                    {"rate_hz", o.rate_hz},
                    {"duration_scale", o.duration_scale},
                    {"medial_markers", o.medial_markers},
                    {"subject",
                     {{"min_height_m", o.subject.min_height_m},
                      {"max_height_m", o.subject.max_height_m},
                      {"scale_spread", o.subject.scale_spread},
                      {"centre_mm", o.subject.centre_mm},
                      {"axis_deg", o.subject.axis_deg},
                      {"marker_mm", o.subject.marker_mm}}}};
  doc["nominal_model"] = "nominal.model.json";
  doc["truth_model"] = "truth.model.json";
  doc["protocol"] = session.protocol.name;
  doc["coordinates_unit"] = "degrees for rotations, metres for translations (.mot inDegrees=yes)";
  json markers = json::array();
  if (!session.trials.empty())
    for (const std::string& n : session.trials.front().markers.marker_names) markers.push_back(n);
  doc["markers"] = markers;
  // Each marker's artefact amplitude (sta_mm x its class's ratio, sim/sta_table.h).
  json sta = json::object();
  for (size_t i = 0; i < session.sta_rms_mm.size() && i < markers.size(); ++i)
    sta[markers[i].get<std::string>()] = session.sta_rms_mm[i];
  doc["sta_rms_mm"] = sta;
  json movements = json::array();
  for (size_t i = 0; i < session.trials.size(); ++i) {
    const SimulatedTrial& t = session.trials[i];
    json m;
    m["name"] = t.markers.name;
    m["frames"] = t.markers.num_frames();
    m["duration_s"] = t.markers.num_frames() / o.rate_hz;
    m["trc"] = t.markers.name + ".trc";
    m["mot"] = t.markers.name + ".mot";
    movements.push_back(m);
  }
  doc["movements"] = movements;
  doc["total_frames"] = session.total_frames();
  return doc.dump(2) + "\n";
}

}  // namespace mocap::sim
