#include "sim/simulate.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <nlohmann/json.hpp>

#include "model/kinematics.h"
#include "sim/random.h"

namespace mocap::sim {
namespace {

constexpr double kDeg = M_PI / 180.0;
// Irrational frequency ratios for the leaders of one movement (1, golden, plastic, and the real
// roots of x^3 = x^2 + 1, x^3 = 2x^2 - x + 1, x^4 = x + 1): no two are commensurate, so
// coordinates excited together never lock into one closed curve.
constexpr double kFrequencyRatios[] = {1.0, 1.6180340, 1.3247180, 1.4655712, 1.7548777, 1.2207440};
constexpr int kNumRatios = sizeof(kFrequencyRatios) / sizeof(kFrequencyRatios[0]);
// Floor contact: the sole lies 0.039 x height below the ankle centre (Winter's ankle height),
// from 0.05 x (height / 1.75) behind the ankle to 0.15 x (height / 1.75) in front of it.
constexpr double kSoleFraction = 0.039;
// Softness of "lowest point of the feet" (metres): small enough to keep the feet on the floor,
// large enough that the weight moves smoothly from one foot to the other.
constexpr double kContactSoftness = 0.005;
// A guard against options that would exhaust memory (2 million frames of 43 markers is ~2 GB).
constexpr long kMaxFrames = 2'000'000;

// The neutral pose and how much each coordinate wanders when the movement does not excite it:
// arms about 20 deg away from the body (so arm markers do not sit on the torso), elbows and knees
// slightly bent, a few degrees of wander everywhere.
struct Posture {
  double neutral_deg = 0.0;
  double wander_deg = 2.0;
};

Posture PostureOf(const std::string& coordinate) {
  struct Entry {
    const char* prefix;
    Posture posture;
  };
  static const Entry table[] = {
      {"pelvis_tilt", {0.0, 2.0}},  {"pelvis_list", {0.0, 1.5}},   {"pelvis_rotation", {0.0, 4.0}},
      {"lumbar_", {0.0, 2.0}},      {"neck_", {0.0, 3.0}},         {"hip_flexion", {0.0, 2.0}},
      {"hip_adduction", {0.0, 1.5}}, {"hip_rotation", {0.0, 2.0}}, {"knee_angle", {4.0, 2.0}},
      {"ankle_angle", {3.0, 2.0}},  {"subtalar_angle", {0.0, 1.5}}, {"arm_flex", {3.0, 4.0}},
      {"arm_add", {-20.0, 3.0}},    {"arm_rot", {0.0, 4.0}},       {"elbow_flex", {15.0, 4.0}},
      {"pro_sup", {0.0, 6.0}},      {"wrist_flex", {0.0, 4.0}},    {"wrist_dev", {0.0, 3.0}},
  };
  for (const Entry& e : table)
    if (coordinate.rfind(e.prefix, 0) == 0) return e.posture;
  return Posture();
}

// Two sinusoids of random phase: a slow one and a faster one; |value| <= amplitude.
struct Wander {
  double a1 = 0, w1 = 0, p1 = 0, a2 = 0, w2 = 0, p2 = 0;
  double At(double t) const { return a1 * std::sin(w1 * t + p1) + a2 * std::sin(w2 * t + p2); }
};

Wander MakeWander(Random& rng, double amplitude, double f1_lo, double f1_hi, double f2_lo,
                  double f2_hi) {
  Wander w;
  w.a1 = 0.65 * amplitude;
  w.w1 = 2 * M_PI * rng.Uniform(f1_lo, f1_hi);
  w.p1 = rng.Uniform(0, 2 * M_PI);
  w.a2 = 0.35 * amplitude;
  w.w2 = 2 * M_PI * rng.Uniform(f2_lo, f2_hi);
  w.p2 = rng.Uniform(0, 2 * M_PI);
  return w;
}

// C2 ramp from 0 (x <= 0) to 1 (x >= 1).
double Smootherstep(double x) {
  if (x <= 0.0) return 0.0;
  if (x >= 1.0) return 1.0;
  return x * x * x * (x * (6.0 * x - 15.0) + 10.0);
}

// One coordinate's motion during a movement (angles in degrees, translations in metres).
struct Channel {
  double neutral = 0.0;
  Wander wander;
  bool excited = false;
  double centre = 0.0, amplitude = 0.0, sign = 1.0;  // of the excitation
  double omega = 0.0, phase = 0.0;                   // of s(t), shared with the leader
  double t0 = 0.0, t1 = 0.0, ramp = 1.0;             // window and its ramps, seconds

  double Envelope(double t) const {
    if (!excited || t <= t0 || t >= t1) return 0.0;
    return Smootherstep((t - t0) / ramp) * Smootherstep((t1 - t) / ramp);
  }
  double At(double t) const {
    const double w = wander.At(t);
    if (!excited) return neutral + w;
    const double env = Envelope(t);
    const double s = std::sin(omega * (t - t0) + phase);
    return neutral + (1.0 - env) * w + env * (centre - neutral + sign * amplitude * s);
  }
};

// Where the simulator finds the pelvis in the model: the root joint must start with translations
// along the lab's x, y, z (so a world offset of the body is a change of those three coordinates).
struct RootLayout {
  int tx = -1, ty = -1, tz = -1;
  int yaw = -1;  // the root's rotation about z, if any: the direction the subject faces
  std::vector<int> feet;  // segments whose name starts with "foot": the floor contact
};

Status FindRootLayout(const Model& model, RootLayout* layout) {
  const Joint* root = nullptr;
  for (const Joint& j : model.joints())
    if (j.parent < 0) root = &j;
  const std::string why = "the simulator needs a root joint that starts with translations along "
                          "x, y and z and has no fixed offset or orientation";
  if (!root || root->elements.size() < 3 || !root->centre.isZero() ||
      !root->orientation.isIdentity())
    return Status::Error("model '" + model.name() + "': " + why);
  int* t[3] = {&layout->tx, &layout->ty, &layout->tz};
  for (int k = 0; k < 3; ++k) {
    const JointElement& e = root->elements[k];
    if (e.kind != ElementKind::kTranslation || e.coordinate < 0 ||
        e.function.kind != CoordinateFunction::Kind::kIdentity ||
        !e.axis.isApprox(Eigen::Vector3d::Unit(k)))
      return Status::Error("model '" + model.name() + "': " + why);
    *t[k] = e.coordinate;
  }
  for (size_t k = 3; k < root->elements.size(); ++k) {
    const JointElement& e = root->elements[k];
    if (e.kind == ElementKind::kRotation && e.coordinate >= 0 &&
        std::abs(e.axis.z()) > 0.99) {
      layout->yaw = e.coordinate;
      break;
    }
  }
  for (int s = 0; s < model.num_segments(); ++s)
    if (model.segments()[s].name.rfind("foot", 0) == 0) layout->feet.push_back(s);
  return Status::Ok();
}

struct MovementPlan {
  int frames = 0;
  std::vector<Channel> channels;  // per model coordinate
  double base_x = 0.0, base_y = 0.0;
  Wander sway_x, sway_y;
};

MovementPlan PlanMovement(const Model& model, const RootLayout& root, const Movement& movement,
                          const SimulationOptions& options, int index) {
  MovementPlan plan;
  const double duration = movement.duration_s * options.duration_scale;
  plan.frames = std::max(2, static_cast<int>(std::lround(duration * options.rate_hz)));
  const double span = (plan.frames - 1) / options.rate_hz;  // time of the last frame
  Random rng(options.seed, Stream::kMotion, static_cast<std::uint64_t>(index));
  const double bg = movement.background;

  // Where the subject stands and faces; how the pelvis drifts (slow) and sways (faster).
  const double base_yaw = rng.Uniform(-180.0, 180.0);
  plan.base_x = rng.Uniform(-0.5, 0.5);
  plan.base_y = rng.Uniform(-0.5, 0.5);
  plan.sway_x = MakeWander(rng, 0.025 * bg, 0.02, 0.06, 0.15, 0.4);
  plan.sway_y = MakeWander(rng, 0.025 * bg, 0.02, 0.06, 0.15, 0.4);

  // Every coordinate's wander is drawn whether or not it is excited, so the draws do not depend
  // on the protocol's content.
  plan.channels.resize(model.num_coordinates());
  for (int c = 0; c < model.num_coordinates(); ++c) {
    const Coordinate& coord = model.coordinates()[c];
    Channel& ch = plan.channels[c];
    const Posture posture = PostureOf(coord.name);
    ch.wander = MakeWander(rng, posture.wander_deg * bg, 0.1, 0.3, 0.3, 0.8);
    ch.neutral = posture.neutral_deg;
    if (c == root.yaw) ch.neutral = base_yaw;
    if (!coord.rotational) {  // the pelvis translations are set by PoseMovement
      ch.wander = Wander();
      ch.neutral = 0.0;
    }
  }

  // Excitations: leaders first (their periods), then followers copy their leader's s(t).
  struct Lead {
    int coordinate;
    double period, plateau;
  };
  std::vector<Lead> leads;
  for (const Excitation& e : movement.excitations) {
    const int c = model.FindCoordinate(e.coordinate);
    Channel& ch = plan.channels[c];
    ch.excited = true;
    ch.centre = 0.5 * (e.min_deg + e.max_deg);
    const double half = 0.5 * (e.max_deg - e.min_deg);
    // A small margin past both ends, so sampling never stops just short of the range.
    ch.amplitude = half + std::max(0.04 * half, 1.0);
    ch.sign = e.anti_phase ? -1.0 : 1.0;
    ch.t0 = e.window_begin * span;
    ch.t1 = e.window_end * span;
    // Ramps in and out of at most 0.5 s: the excitation keeps most of its window.
    ch.ramp = std::min(0.5, 0.15 * (ch.t1 - ch.t0));
    ch.phase = rng.Uniform(0, 2 * M_PI);
    if (e.follow.empty()) {
      const double ratio = kFrequencyRatios[leads.size() % kNumRatios];
      leads.push_back({c, movement.period_s / ratio, (ch.t1 - ch.t0) - 2.0 * ch.ramp});
    }
  }
  // One full period inside the plateau reaches both ends of the range whatever the phase; when
  // the plateau is too short, all periods shrink together (keeping the ratios).
  double shrink = 1.0;
  for (const Lead& l : leads) shrink = std::min(shrink, l.plateau / l.period);
  for (const Lead& l : leads) plan.channels[l.coordinate].omega = 2 * M_PI / (l.period * shrink);
  for (const Excitation& e : movement.excitations) {
    if (e.follow.empty()) continue;
    Channel& ch = plan.channels[model.FindCoordinate(e.coordinate)];
    const Channel& leader = plan.channels[model.FindCoordinate(e.follow)];
    ch.omega = leader.omega;
    ch.phase = leader.phase;
  }
  return plan;
}

using formats::RowMatrix;

// The soles' heel and toe points, and where each stands in the neutral pose. The independent
// segment scales give the virtual subject a leg-length difference of several centimetres, so in
// the neutral pose one foot is higher than the other; each point's height is measured from its
// own neutral height (its baseline), so "the foot that carries the weight" means the one raised
// least from where it stands, not simply the one on the longer leg.
struct FootContacts {
  std::vector<Eigen::Vector3d> point;  // in the foot frame, scaled
  std::vector<int> segment;
  std::vector<double> baseline;  // neutral-pose height above the lowest neutral point
  int size() const { return static_cast<int>(point.size()); }
};

FootContacts MakeFootContacts(const Model& truth, const Geometry& geometry, const RootLayout& root,
                              double height_m) {
  FootContacts feet;
  const double k = height_m / 1.75, sole = kSoleFraction * height_m;
  for (int s : root.feet)
    for (double x : {-0.05 * k, 0.15 * k}) {
      feet.point.push_back(geometry.scale[s] * Eigen::Vector3d(x, 0.0, -sole));
      feet.segment.push_back(s);
    }
  Eigen::VectorXd z(truth.num_coordinates());
  for (int c = 0; c < truth.num_coordinates(); ++c)
    z[c] = truth.coordinates()[c].rotational ? PostureOf(truth.coordinates()[c].name).neutral_deg * kDeg
                                             : 0.0;
  ModelData data(truth);
  ForwardKinematics(truth, geometry, z, &data);
  double lowest = std::numeric_limits<double>::infinity();
  for (int i = 0; i < feet.size(); ++i) {
    const int s = feet.segment[i];
    feet.baseline.push_back((data.segment_position[s] + data.segment_rotation[s] * feet.point[i]).z());
    lowest = std::min(lowest, feet.baseline.back());
  }
  for (double& b : feet.baseline) b -= lowest;
  return feet;
}

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
  std::vector<Eigen::Vector3d> point(np), previous_point(np);
  std::vector<double> weight(np), previous_weight(np);
  Eigen::Vector2d anchor = Eigen::Vector2d::Zero(), anchor0 = Eigen::Vector2d::Zero();
  const double default_height = truth.coordinates()[root.tz].default_value;

  for (int f = 0; f < nf; ++f) {
    const double t = f / rate_hz;
    for (int c = 0; c < nc; ++c) {
      const double v = plan.channels[c].At(t);
      z[c] = truth.coordinates()[c].rotational ? v * kDeg : v;
    }
    z[root.tx] = z[root.ty] = z[root.tz] = 0.0;
    ForwardKinematics(truth, geometry, z, &data);

    Eigen::Vector3d offset(plan.base_x + plan.sway_x.At(t), plan.base_y + plan.sway_y.At(t),
                           default_height);
    if (np > 0) {
      double lowest = std::numeric_limits<double>::infinity();
      for (int i = 0; i < np; ++i) {
        const int s = feet.segment[i];
        point[i] = data.segment_position[s] + data.segment_rotation[s] * feet.point[i];
        lowest = std::min(lowest, point[i].z() - feet.baseline[i]);
      }
      double sum = 0.0;
      for (int i = 0; i < np; ++i)
        sum += weight[i] = std::exp(-(point[i].z() - feet.baseline[i] - lowest) / kContactSoftness);
      for (int i = 0; i < np; ++i) weight[i] /= sum;
      const double soft_lowest = lowest - kContactSoftness * std::log(sum);
      if (f == 0) {
        for (int i = 0; i < np; ++i) anchor += weight[i] * point[i].head<2>();
        anchor0 = anchor;
      } else {
        for (int i = 0; i < np; ++i)
          anchor += 0.5 * (weight[i] + previous_weight[i]) *
                    (point[i].head<2>() - previous_point[i].head<2>());
      }
      offset.head<2>() -= anchor - anchor0;
      offset.z() = -soft_lowest;
      std::swap(point, previous_point);
      std::swap(weight, previous_weight);
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
                                const std::vector<RowMatrix>& z, const Eigen::VectorXd& mean,
                                const SimulationOptions& options) {
  const int nc = truth.num_coordinates();
  // Second moments about the session mean, per movement: the artefact is scaled so that its RMS
  // is sta_mm in the movement that moves the marker most. Scaling over the whole session instead
  // would put all of a joint's artefact into the one movement that moves it (head markers swinging
  // by four times sta_mm during neck range of motion).
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
    map.gain *= options.sta_mm * 1e-3 / std::sqrt(mean_square);
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

void AddNoise(double sigma_m, Random& rng, RowMatrix* positions) {
  for (int f = 0; f < positions->rows(); ++f)
    for (int c = 0; c < positions->cols(); ++c) (*positions)(f, c) += sigma_m * rng.Normal();
}

// Occlusions: gaps of 5..30 frames at random markers and times until `fraction` of the samples
// are gone (gaps may overlap and merge; the last one may overshoot by a few samples).
void RemoveSamples(double fraction, Random& rng, RowMatrix* positions) {
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

}  // namespace

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

  if (options.sta_mm > 0.0) {
    Eigen::VectorXd mean = Eigen::VectorXd::Zero(truth.num_coordinates());
    for (const RowMatrix& zm : z) mean += zm.colwise().sum().transpose();
    mean /= static_cast<double>(std::max(1L, total));
    const std::vector<StaMap> maps = MakeStaMaps(truth, markers, z, mean, options);
    for (int i = 0; i < nmov; ++i) AddSta(truth, geometry, markers, maps, mean, z[i], &positions[i]);
  }

  SimulatedSession out;
  out.options = options;
  out.height_m = subject.height_m;
  // The session's models carry exactly the markers it records: a marker no trial shows is not
  // fitted, and comparing an unfitted marker with the truth would only measure its nominal offset.
  MOCAP_RETURN_IF_ERROR(subject.nominal.WithMarkers(markers, &out.nominal));
  {
    const Model& full = subject.nominal;
    const int first_marker = full.num_markers() > 0 ? full.marker_index(0) : full.num_parameters();
    Eigen::VectorXd p(out.nominal.num_parameters());
    p.head(first_marker) = subject.truth_parameters.head(first_marker);
    for (size_t i = 0; i < markers.size(); ++i)
      p.segment<3>(out.nominal.marker_index(static_cast<int>(i))) =
          subject.truth_parameters.segment<3>(full.marker_index(markers[i]));
    out.truth_parameters = p;
  }
  out.protocol = protocol;
  std::vector<std::string> marker_names, coordinate_names;
  for (int m : markers) marker_names.push_back(truth.markers()[m].name);
  for (const Coordinate& c : truth.coordinates()) coordinate_names.push_back(c.name);
  for (int i = 0; i < nmov; ++i) {
    const std::string& name = protocol.movements[i].name;
    if (options.noise_mm > 0.0) {
      Random rng(options.seed, Stream::kNoise, static_cast<std::uint64_t>(i));
      AddNoise(options.noise_mm * 1e-3, rng, &positions[i]);
    }
    if (options.missing > 0.0) {
      Random rng(options.seed, Stream::kMissing, static_cast<std::uint64_t>(i));
      RemoveSamples(options.missing, rng, &positions[i]);
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
  MOCAP_RETURN_IF_ERROR(subject.truth.WithMarkers(markers, &out.truth));
  *session = std::move(out);
  return Status::Ok();
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
