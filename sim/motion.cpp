#include "sim/motion.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <string>

#include "sim/random.h"
#include "sim/simulate.h"

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

}  // namespace

double Smootherstep(double x) {
  if (x <= 0.0) return 0.0;
  if (x >= 1.0) return 1.0;
  return x * x * x * (x * (6.0 * x - 15.0) + 10.0);
}

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

void MovementPlan::Coordinates(const Model& model, double t, Eigen::VectorXd* z) const {
  const int nc = model.num_coordinates();
  for (int c = 0; c < nc; ++c) {
    const double v = channels[c].At(t);
    (*z)[c] = model.coordinates()[c].rotational ? v * kDeg : v;
  }
}

MovementPlan PlanMovement(const Model& model, const RootLayout& root, const Movement& movement,
                          const SimulationOptions& options, int index, double amplitude) {
  MovementPlan plan;
  const double duration = movement.duration_s * options.duration_scale;
  plan.frames = std::max(2, static_cast<int>(std::lround(duration * options.rate_hz)));
  const double span = (plan.frames - 1) / options.rate_hz;  // time of the last frame
  plan.span_s = span;
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
    if (!coord.rotational) {  // the pelvis translations are set by the floor contact
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
    ch.gain = amplitude;
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

double SoleContact(const FootContacts& feet, const ModelData& data, Eigen::Vector3d* point,
                   double* weight) {
  const int np = feet.size();
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
  return lowest - kContactSoftness * std::log(sum);
}

Eigen::Vector2d StanceDrift::Add(const Eigen::Vector3d* point, const double* weight) {
  const int np = static_cast<int>(point_.size());
  if (first_) {
    for (int i = 0; i < np; ++i) anchor_ += weight[i] * point[i].head<2>();
    anchor0_ = anchor_;
    first_ = false;
  } else {
    for (int i = 0; i < np; ++i)
      anchor_ += 0.5 * (weight[i] + weight_[i]) * (point[i].head<2>() - point_[i].head<2>());
  }
  std::copy(point, point + np, point_.begin());
  std::copy(weight, weight + np, weight_.begin());
  return anchor_ - anchor0_;
}

}  // namespace mocap::sim
