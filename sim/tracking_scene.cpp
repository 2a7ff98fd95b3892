#include "sim/tracking_scene.h"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>

#include "model/kinematics.h"
#include "sim/random.h"
#include "sim/simulate.h"

namespace mocap::sim {
namespace {

constexpr double kNan = std::numeric_limits<double>::quiet_NaN();
constexpr double kDeg = M_PI / 180.0;
// Index offsets of the sub-streams drawn from the reserved streams (sim/random.h).
constexpr std::uint64_t kGhostBirths = 0, kGhostShuffle = 1;
constexpr std::uint64_t kNoiseIndex = 0x747261636bULL;  // "track": not a movement index of kNoise

double Smootherstep(double x) {
  if (x <= 0.0) return 0.0;
  if (x >= 1.0) return 1.0;
  return x * x * x * (x * (6.0 * x - 15.0) + 10.0);
}

std::string Show(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%g", v);
  return buf;
}

// The root's horizontal translations and its rotation about the vertical: a rigid motion of the
// whole body about a vertical axis is a change of these three coordinates only (the default model's
// root is tx, ty, tz, then a rotation about z, then the others).
struct Root {
  int tx = -1, ty = -1, yaw = -1;
};

Status FindRoot(const Model& model, Root* root) {
  for (const Joint& j : model.joints()) {
    if (j.parent >= 0) continue;
    if (j.elements.size() >= 4 && j.elements[0].kind == ElementKind::kTranslation &&
        j.elements[0].axis.isApprox(Eigen::Vector3d::UnitX()) &&
        j.elements[1].kind == ElementKind::kTranslation &&
        j.elements[1].axis.isApprox(Eigen::Vector3d::UnitY()) &&
        j.elements[3].kind == ElementKind::kRotation &&
        j.elements[3].axis.isApprox(Eigen::Vector3d::UnitZ()) && j.orientation.isIdentity() &&
        j.centre.isZero()) {
      root->tx = j.elements[0].coordinate;
      root->ty = j.elements[1].coordinate;
      root->yaw = j.elements[3].coordinate;
      if (root->tx >= 0 && root->ty >= 0 && root->yaw >= 0) return Status::Ok();
    }
  }
  return Status::Error("model '" + model.name() +
                       "': the tracking scene needs a root joint starting with x, y, z "
                       "translations and a rotation about z");
}

Eigen::Vector2d Xy(const Root& r, const Eigen::VectorXd& z) { return {z[r.tx], z[r.ty]}; }

// Turns the body by `yaw` about the vertical through `centre`, then moves it by `shift`.
void MoveRigidly(const Root& r, double yaw, const Eigen::Vector2d& centre,
                 const Eigen::Vector2d& shift, Eigen::VectorXd* z) {
  const Eigen::Vector2d xy = Xy(r, *z) - centre;
  const double c = std::cos(yaw), s = std::sin(yaw);
  (*z)[r.tx] = c * xy.x() - s * xy.y() + centre.x() + shift.x();
  (*z)[r.ty] = s * xy.x() + c * xy.y() + centre.y() + shift.y();
  (*z)[r.yaw] += yaw;
}

// The chosen movements of a session as one continuous stream of coordinates (rows: frames).
void BuildStream(const SimulatedSession& session, const std::vector<int>& movements,
                 const Root& root, int transition_frames, std::vector<Eigen::VectorXd>* rows,
                 std::vector<SceneSegment>* segments) {
  const Model& model = session.truth;
  for (size_t k = 0; k < movements.size(); ++k) {
    const SimulatedTrial& trial = session.trials[movements[k]];
    const int nf = trial.coordinates.num_frames();
    std::vector<Eigen::VectorXd> z(nf);
    for (int f = 0; f < nf; ++f) z[f] = TrueCoordinates(model, trial.coordinates, f);
    if (!rows->empty()) {
      const Eigen::VectorXd end = rows->back();
      const double yaw = end[root.yaw] - z[0][root.yaw];
      const Eigen::Vector2d centre = Xy(root, z[0]);
      const Eigen::Vector2d shift = Xy(root, end) - centre;
      for (Eigen::VectorXd& row : z) MoveRigidly(root, yaw, centre, shift, &row);
      SceneSegment t{"transition", static_cast<int>(rows->size()), 0};
      for (int i = 1; i <= transition_frames; ++i) {
        const double u = Smootherstep(static_cast<double>(i) / (transition_frames + 1));
        rows->push_back(end + u * (z[0] - end));
      }
      t.end = static_cast<int>(rows->size());
      if (t.end > t.begin) segments->push_back(t);
    }
    SceneSegment s{trial.markers.name, static_cast<int>(rows->size()), 0};
    for (Eigen::VectorXd& row : z) rows->push_back(std::move(row));
    s.end = static_cast<int>(rows->size());
    segments->push_back(s);
  }
}

// --- swap traps -------------------------------------------------------------------------------

struct TrapPlan {
  const char* marker_a;
  const char* marker_b;
  std::vector<const char*> free;  // coordinates that move
  // Moved as well when `free` alone cannot bring the markers together: a subject whose hand does
  // not reach the front of the hip with the arm alone (the hand-on-hip trap fell 15-40 mm short
  // on seeds 21, 70 and 73, which had no scene) leans towards it, as a person does.
  std::vector<const char*> lean = {};
};

std::vector<TrapPlan> TrapPlans() {
  const std::vector<const char*> arm_r = {"arm_flex_r", "arm_add_r", "arm_rot_r", "elbow_flex_r",
                                          "pro_sup_r", "wrist_flex_r", "wrist_dev_r"};
  const std::vector<const char*> arm_l = {"arm_flex_l", "arm_add_l", "arm_rot_l", "elbow_flex_l",
                                          "pro_sup_l", "wrist_flex_l", "wrist_dev_l"};
  auto join = [](std::vector<const char*> a, const std::vector<const char*>& b) {
    a.insert(a.end(), b.begin(), b.end());
    return a;
  };
  return {
      {"RFIN", "RTHI", join({"lumbar_bending"}, arm_r)},  // side bend, hand down the thigh
      {"LFIN", "LTHI", join({"lumbar_bending"}, arm_l)},
      {"LWRA", "RWRA", join(arm_l, arm_r)},               // hands meet in front
      {"RWRB", "RASI", arm_r, {"lumbar_bending", "lumbar_rotation"}},  // hand on the hip
  };
}

// Relative position p_a - p_b and its Jacobian over the free coordinates.
void Relative(const Model& model, const Geometry& g, ModelData* data, const Eigen::VectorXd& z,
              int a, int b, const std::vector<int>& free, Eigen::Vector3d* rel,
              Eigen::Matrix3Xd* jac) {
  ForwardKinematics(model, g, z, data);
  *rel = MarkerPosition(model, g, *data, a) - MarkerPosition(model, g, *data, b);
  jac->setZero(3, static_cast<Eigen::Index>(free.size()));
  for (int pass = 0; pass < 2; ++pass) {
    const int m = pass == 0 ? a : b;
    const std::vector<int>& cols = model.marker_coordinates(m);
    Eigen::Matrix3Xd jm(3, cols.size());
    MarkerJacobian(model, g, *data, m, &jm, static_cast<Eigen::Matrix3Xd*>(nullptr));
    for (size_t c = 0; c < cols.size(); ++c)
      for (size_t k = 0; k < free.size(); ++k)
        if (free[k] == cols[c]) jac->col(k) += (pass == 0 ? 1.0 : -1.0) * jm.col(c);
  }
}

// The smallest change of the free coordinates (Gauss-Newton, minimum-norm steps) that puts
// p_a - p_b at `target`. Returns the remaining error (m).
double SolveTrapPose(const Model& model, const Geometry& g, ModelData* data,
                     const Eigen::VectorXd& base, int a, int b, const std::vector<int>& free,
                     const Eigen::Vector3d& target, Eigen::VectorXd* delta) {
  Eigen::Vector3d rel;
  Eigen::Matrix3Xd jac;
  double error = 0;
  for (int it = 0; it < 60; ++it) {
    Eigen::VectorXd z = base;
    for (size_t k = 0; k < free.size(); ++k) z[free[k]] += (*delta)[k];
    Relative(model, g, data, z, a, b, free, &rel, &jac);
    const Eigen::Vector3d r = rel - target;
    error = r.norm();
    if (error < 1e-7) break;
    const Eigen::Matrix3d jjt = jac * jac.transpose() + 1e-6 * Eigen::Matrix3d::Identity();
    Eigen::VectorXd step = -jac.transpose() * jjt.ldlt().solve(r);
    const double longest = step.cwiseAbs().maxCoeff();
    if (longest > 0.3) step *= 0.3 / longest;  // small steps: stay on the near branch
    *delta += step;
  }
  return error;
}

// Appends the swap-trap movement (from the stream's last pose). Fails when a pose cannot be
// solved (a model without the markers or coordinates it needs).
Status AppendTraps(const Model& model, const TrackingSceneOptions& o,
                   std::vector<Eigen::VectorXd>* rows, std::vector<SceneSegment>* segments) {
  const Geometry g(model);
  ModelData data(model);
  const Eigen::VectorXd base = rows->back();
  const double rest_s = 0.2, move_s = 1.6, overshoot = 1.3;
  SceneSegment seg{"swap_traps", static_cast<int>(rows->size()), 0};
  for (const TrapPlan& plan : TrapPlans()) {
    const int a = model.FindMarker(plan.marker_a), b = model.FindMarker(plan.marker_b);
    if (a < 0 || b < 0)
      return Status::Error(std::string("swap traps: the model lacks marker ") + plan.marker_a + " or " +
                           plan.marker_b);
    // First the markers on top of each other; then miss by trap_distance_m across their path,
    // on the side marker a comes from. Returns the remaining error.
    std::vector<int> free;
    Eigen::VectorXd delta;
    auto solve = [&](const std::vector<const char*>& coordinates) {
      free.clear();
      for (const char* c : coordinates) free.push_back(model.FindCoordinate(c));
      if (std::count(free.begin(), free.end(), -1) > 0) return std::numeric_limits<double>::infinity();
      delta = Eigen::VectorXd::Zero(static_cast<Eigen::Index>(free.size()));
      SolveTrapPose(model, g, &data, base, a, b, free, Eigen::Vector3d::Zero(), &delta);
      Eigen::Vector3d rel0, rel;
      Eigen::Matrix3Xd jac;
      Relative(model, g, &data, base, a, b, free, &rel0, &jac);
      Eigen::VectorXd z = base;
      for (size_t k = 0; k < free.size(); ++k) z[free[k]] += delta[k];
      Relative(model, g, &data, z, a, b, free, &rel, &jac);
      const Eigen::Vector3d v = (jac * delta).normalized();  // d(p_a - p_b)/dw at the meeting
      Eigen::Vector3d side = rel0 - rel0.dot(v) * v;
      if (side.norm() < 1e-9) side = v.unitOrthogonal();
      const Eigen::Vector3d target = o.trap_distance_m * side.normalized();
      return SolveTrapPose(model, g, &data, base, a, b, free, target, &delta);
    };
    double error = solve(plan.free);
    if (error > 1e-4 && !plan.lean.empty()) {
      std::vector<const char*> leaning = plan.free;
      leaning.insert(leaning.end(), plan.lean.begin(), plan.lean.end());
      error = solve(leaning);
    }
    if (!std::isfinite(error))
      return Status::Error(std::string("swap traps: the model lacks a coordinate that moves ") + plan.marker_a +
                           " to " + plan.marker_b);
    if (error > 1e-4)
      return Status::Error(std::string("swap traps: cannot bring ") + plan.marker_a + " to " +
                           plan.marker_b);
    const int rest = static_cast<int>(std::lround(rest_s * o.rate_hz));
    const int move = static_cast<int>(std::lround(move_s * o.rate_hz));
    for (int i = 0; i < rest; ++i) rows->push_back(base);
    for (int i = 0; i < move; ++i) {
      const double s = std::sin(M_PI * (i + 0.5) / move);
      Eigen::VectorXd zi = base;
      for (size_t k = 0; k < free.size(); ++k) zi[free[k]] += overshoot * s * s * delta[k];
      rows->push_back(zi);
    }
  }
  for (int i = 0; i < static_cast<int>(std::lround(rest_s * o.rate_hz)); ++i) rows->push_back(base);
  seg.end = static_cast<int>(rows->size());
  segments->push_back(seg);
  return Status::Ok();
}

// Every run of frames in which two markers are within kTrapDistanceM.
std::vector<TrapMoment> FindTraps(const formats::RowMatrix& x, int nm) {
  std::vector<TrapMoment> out;
  const int nf = static_cast<int>(x.rows());
  for (int a = 0; a < nm; ++a)
    for (int b = a + 1; b < nm; ++b) {
      TrapMoment current;
      bool open = false;
      for (int f = 0; f <= nf; ++f) {
        const double d = f < nf ? (x.row(f).segment<3>(3 * a) - x.row(f).segment<3>(3 * b)).norm()
                                : kNan;
        if (d < kTrapDistanceM) {
          if (!open || d < current.distance_m) current = {f, a, b, d};
          open = true;
        } else if (open) {
          out.push_back(current);
          open = false;
        }
      }
    }
  std::sort(out.begin(), out.end(),
            [](const TrapMoment& p, const TrapMoment& q) { return p.frame < q.frame; });
  return out;
}

// Occlusions as the simulator makes them: gaps of 5..30 frames at random markers and times.
long Occlude(double fraction, Random& rng, int nf, int nm, std::vector<char>* seen) {
  const long total = static_cast<long>(nf) * nm;
  const long target = std::lround(fraction * total);
  long removed = 0;
  for (long attempt = 0; removed < target && attempt < 1000 * target; ++attempt) {
    const int m = rng.UniformInt(0, nm - 1);
    const int length = std::min(nf, rng.UniformInt(5, 30));
    const int start = rng.UniformInt(0, nf - length);
    for (int f = start; f < start + length && removed < target; ++f) {
      char& s = (*seen)[static_cast<size_t>(f) * nm + m];
      if (!s) continue;
      s = 0;
      ++removed;
    }
  }
  return removed;
}

void Positions(const Model& model, const std::vector<Eigen::VectorXd>& rows,
               formats::RowMatrix* out) {
  const Geometry g(model);
  ModelData data(model);
  Eigen::Matrix3Xd p(3, model.num_markers());
  out->resize(static_cast<Eigen::Index>(rows.size()), 3 * model.num_markers());
  for (size_t f = 0; f < rows.size(); ++f) {
    ForwardKinematics(model, g, rows[f], &data);
    MarkerPositions(model, g, data, &p);
    for (int m = 0; m < model.num_markers(); ++m) out->row(f).segment<3>(3 * m) = p.col(m).transpose();
  }
}

}  // namespace

const char* ToString(SceneFault fault) {
  switch (fault) {
    case SceneFault::kNone: return "none";
    case SceneFault::kAllOccluded: return "all_occluded";
    case SceneFault::kLeaveAndReenter: return "leave_reenter";
    case SceneFault::kSecondPerson: return "second_person";
    case SceneFault::kNanFrame: return "nan_frame";
  }
  return "?";
}

bool ParseSceneFault(const std::string& name, SceneFault* fault) {
  for (SceneFault f : {SceneFault::kNone, SceneFault::kAllOccluded, SceneFault::kLeaveAndReenter,
                       SceneFault::kSecondPerson, SceneFault::kNanFrame})
    if (name == ToString(f)) {
      *fault = f;
      return true;
    }
  return false;
}

bool TrackingSceneOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& m) {
    if (error) *error = m;
    return false;
  };
  if (!(std::isfinite(rate_hz) && rate_hz >= 10.0 && rate_hz <= 2000.0))
    return fail("rate_hz must be in [10, 2000] (got " + Show(rate_hz) + ")");
  if (!(std::isfinite(noise_mm) && noise_mm >= 0.0 && noise_mm <= 20.0))
    return fail("noise_mm must be in [0, 20] (got " + Show(noise_mm) + ")");
  if (!(std::isfinite(duration_scale) && duration_scale > 0.0 && duration_scale <= 100.0))
    return fail("duration_scale must be in (0, 100] (got " + Show(duration_scale) + ")");
  if (!(std::isfinite(transition_s) && transition_s >= 0.0 && transition_s <= 10.0))
    return fail("transition_s must be in [0, 10] (got " + Show(transition_s) + ")");
  if (ghosts < 0 || ghosts > 1000)
    return fail("ghosts must be in [0, 1000] (got " + std::to_string(ghosts) + ")");
  if (!(ghost_radius_m > 0.0 && ghost_radius_m <= 2.0))
    return fail("ghost_radius_m must be in (0, 2] (got " + Show(ghost_radius_m) + ")");
  if (!(ghost_min_distance_m >= 0.0 && ghost_min_distance_m < ghost_radius_m))
    return fail("ghost_min_distance_m must be in [0, ghost_radius_m) (got " +
                Show(ghost_min_distance_m) + ")");
  if (!(persistent_ghost_fraction >= 0.0 && persistent_ghost_fraction <= 1.0))
    return fail("persistent_ghost_fraction must be in [0, 1] (got " +
                Show(persistent_ghost_fraction) + ")");
  if (!(occlusion >= 0.0 && occlusion <= 0.5))
    return fail("occlusion must be a fraction in [0, 0.5] (got " + Show(occlusion) + ")");
  if (!(trap_distance_m >= 0.0 && trap_distance_m < kTrapDistanceM))
    return fail("trap_distance_m must be in [0, 0.015) (got " + Show(trap_distance_m) + ")");
  if (!std::isfinite(fault_time_s))
    return fail("fault_time_s must be finite (got " + Show(fault_time_s) + ")");
  if (!(fault_duration_s > 0.0 && fault_duration_s <= 60.0))
    return fail("fault_duration_s must be in (0, 60] (got " + Show(fault_duration_s) + ")");
  if (!(volume_half_width_m >= 1.5 && volume_half_width_m <= 50.0))
    return fail("volume_half_width_m must be in [1.5, 50] (got " + Show(volume_half_width_m) + ")");
  return true;
}

long TrackingScene::visible_samples() const {
  long n = 0;
  for (const std::vector<int>& l : labels)
    for (int v : l) n += v >= 0 ? 1 : 0;
  return n;
}

formats::MarkerTrial TrackingScene::PointsTrial(const std::string& name) const {
  formats::MarkerTrial t;
  t.name = name;
  t.rate_hz = options.rate_hz;
  int n = 0;
  for (const Eigen::Matrix3Xd& p : points) n = std::max(n, static_cast<int>(p.cols()));
  n = std::max(n, 1);
  for (int i = 0; i < n; ++i) t.marker_names.push_back("P" + std::to_string(i + 1));
  t.positions.setConstant(num_frames(), 3 * n, kNan);
  for (int f = 0; f < num_frames(); ++f) {
    t.frame_numbers.push_back(f + 1);
    t.times.push_back(times[f]);
    for (int i = 0; i < points[f].cols(); ++i)
      t.positions.row(f).segment<3>(3 * i) = points[f].col(i).transpose();
  }
  return t;
}

formats::CoordinateTable TrackingScene::TrueCoordinateTable(const std::string& name) const {
  formats::CoordinateTable t;
  t.name = name;
  t.in_degrees = true;
  t.times = times;
  for (const Coordinate& c : truth.coordinates()) t.column_names.push_back(c.name);
  t.values = true_coordinates;
  for (int c = 0; c < truth.num_coordinates(); ++c)
    if (truth.coordinates()[c].rotational) t.values.col(c) /= kDeg;
  return t;
}

Status MakeTrackingScene(const TrackingSceneOptions& o, TrackingScene* scene) {
  std::string why;
  if (!o.IsValid(&why)) return Status::Error("tracking scene: " + why);
  SimulationOptions so;
  so.seed = o.seed;
  so.rate_hz = o.rate_hz;
  so.noise_mm = 0.0;
  so.duration_scale = o.duration_scale;
  SimulatedSession session;
  MOCAP_RETURN_IF_ERROR(SimulateSession(so, &session));
  const Model& truth = session.truth;
  Root root;
  MOCAP_RETURN_IF_ERROR(FindRoot(truth, &root));

  std::vector<int> chosen;
  if (o.movements.empty()) {
    for (size_t i = 0; i < session.trials.size(); ++i) chosen.push_back(static_cast<int>(i));
  } else {
    for (const std::string& name : o.movements) {
      int found = -1;
      for (size_t i = 0; i < session.trials.size(); ++i)
        if (session.trials[i].markers.name == name) found = static_cast<int>(i);
      if (found < 0) {
        std::string known;
        for (const SimulatedTrial& t : session.trials) known += (known.empty() ? "" : ", ") + t.markers.name;
        return Status::Error("tracking scene: movements: no movement '" + name +
                             "' in the protocol (it has " + known + ")");
      }
      chosen.push_back(found);
    }
  }

  TrackingScene out;
  out.options = o;
  out.height_m = session.height_m;
  out.nominal = session.nominal;
  out.truth = session.truth;
  for (const Marker& m : truth.markers()) out.marker_names.push_back(m.name);
  const int nm = truth.num_markers();
  const int transition = static_cast<int>(std::lround(o.transition_s * o.rate_hz));

  std::vector<Eigen::VectorXd> rows;
  BuildStream(session, chosen, root, transition, &rows, &out.segments);
  if (o.swap_traps) MOCAP_RETURN_IF_ERROR(AppendTraps(truth, o, &rows, &out.segments));
  const int nf = static_cast<int>(rows.size());
  auto frames_of = [&](double seconds) { return static_cast<int>(std::lround(seconds * o.rate_hz)); };

  // The fault's frames.
  const int f0 = o.fault_time_s >= 0 ? frames_of(o.fault_time_s) : static_cast<int>(0.4 * nf);
  const int walk = frames_of(1.5), away = frames_of(o.fault_duration_s);
  if (o.fault != SceneFault::kNone) {
    int length = 0;
    switch (o.fault) {
      case SceneFault::kAllOccluded: length = away; break;
      case SceneFault::kLeaveAndReenter: length = 2 * walk + away; break;
      case SceneFault::kSecondPerson: length = nf - f0; break;
      case SceneFault::kNanFrame: length = 11; break;
      case SceneFault::kNone: break;
    }
    if (f0 < 1 || f0 + length > nf || length < 1)
      return Status::Error("tracking scene: the fault '" + std::string(ToString(o.fault)) +
                           "' at " + Show(f0 / o.rate_hz) + " s does not fit in the scene of " +
                           Show(nf / o.rate_hz) + " s: choose more movements or an earlier fault_time_s");
    out.fault_begin = f0;
    out.fault_end = f0 + length;
  }

  // Leaving the volume and coming back elsewhere: a rigid motion of the rest of the stream.
  if (o.fault == SceneFault::kLeaveAndReenter) {
    const Eigen::Vector2d centre = Xy(root, rows[f0]);
    const double limit = o.volume_half_width_m + 1.5;  // pelvis this far out: every marker is out
    const Eigen::Vector2d out_dir = centre.norm() > 0.05 ? Eigen::Vector2d(centre.normalized())
                                                         : Eigen::Vector2d(1.0, 0.0);
    const Eigen::Vector2d exit = (limit - out_dir.dot(centre)) * out_dir;
    const double turn = 100.0 * kDeg;
    const Eigen::Vector2d in_dir(-out_dir.y(), out_dir.x());  // another side of the volume
    const Eigen::Vector2d place = 1.2 * in_dir - 0.3 * out_dir;  // where it ends up (shift)
    const Eigen::Vector2d entry = (limit - in_dir.dot(centre + place)) * in_dir;
    for (int f = f0; f < nf; ++f) {
      const int k = f - f0;
      if (k < walk + away) {
        const double u = Smootherstep(static_cast<double>(k + 1) / walk);
        MoveRigidly(root, 0.0, centre, u * exit, &rows[f]);
      } else {
        const double u = Smootherstep(static_cast<double>(k - walk - away + 1) / walk);
        MoveRigidly(root, turn, centre, place + (1.0 - u) * entry, &rows[f]);
      }
    }
  }

  Positions(truth, rows, &out.true_markers);
  out.true_coordinates.resize(nf, truth.num_coordinates());
  for (int f = 0; f < nf; ++f) out.true_coordinates.row(f) = rows[f].transpose();
  out.times.resize(nf);
  for (int f = 0; f < nf; ++f) out.times[f] = f / o.rate_hz;
  out.traps = FindTraps(out.true_markers, nm);

  // What is seen: occlusions, then the fault, then the capture volume.
  std::vector<char> seen(static_cast<size_t>(nf) * nm, 1);
  if (o.occlusion > 0.0) {
    Random rng(o.seed, Stream::kOcclusion);
    out.occluded_samples = Occlude(o.occlusion, rng, nf, nm, &seen);
  }
  auto inside = [&](const Eigen::Vector3d& p) {
    return std::abs(p.x()) <= o.volume_half_width_m && std::abs(p.y()) <= o.volume_half_width_m;
  };
  for (int f = 0; f < nf; ++f)
    for (int m = 0; m < nm; ++m) {
      char& s = seen[static_cast<size_t>(f) * nm + m];
      if (!s) continue;
      const bool hidden =
          (o.fault == SceneFault::kAllOccluded && f >= out.fault_begin && f < out.fault_end) ||
          (o.fault == SceneFault::kNanFrame && f == out.fault_begin) ||
          !inside(out.true_markers.row(f).segment<3>(3 * m).transpose());
      if (hidden) {
        s = 0;
        ++out.hidden_samples;
      }
    }

  // The second person: another subject performing the protocol, walking in at 1.5 m.
  formats::RowMatrix second;
  if (o.fault == SceneFault::kSecondPerson) {
    SimulationOptions so2 = so;
    so2.seed = SubSeed(o.seed, Stream::kSecondPerson);
    SimulatedSession s2;
    MOCAP_RETURN_IF_ERROR(SimulateSession(so2, &s2));
    std::vector<int> all;
    for (size_t i = 0; i < s2.trials.size(); ++i) all.push_back(static_cast<int>(i));
    std::vector<Eigen::VectorXd> rows2;
    std::vector<SceneSegment> ignored;
    BuildStream(s2, all, root, transition, &rows2, &ignored);
    Random rng(o.seed, Stream::kSecondPerson);
    const double angle = rng.Uniform(0, 2 * M_PI), facing = rng.Uniform(0, 2 * M_PI);
    const Eigen::Vector2d dir(std::cos(angle), std::sin(angle));
    const Eigen::Vector2d place = Xy(root, rows[f0]) + 1.5 * dir;
    const Eigen::Vector2d start = place + 4.0 * dir;  // outside the volume
    const int n2 = nf - f0;
    std::vector<Eigen::VectorXd> placed(n2);
    const Eigen::Vector2d origin = Xy(root, rows2[0]);
    for (int k = 0; k < n2; ++k) {
      Eigen::VectorXd z = rows2[std::min<size_t>(k, rows2.size() - 1)];
      const double u = Smootherstep(static_cast<double>(k + 1) / (2 * walk));
      MoveRigidly(root, facing, origin, start + u * (place - start) - origin, &z);
      placed[k] = z;
    }
    Positions(s2.truth, placed, &second);
  }

  // Ghosts, noise, shuffling.
  const int persistent = static_cast<int>(std::lround(o.ghosts * o.persistent_ghost_fraction));
  struct Reflection {
    int until = -1;
    int marker = 0;
    bool fixed = true;
    Eigen::Vector3d where = Eigen::Vector3d::Zero();  // lab point, or offset from the marker
  };
  std::vector<Reflection> reflections(persistent);
  Random ghost_rng(o.seed, Stream::kGhosts, kGhostBirths);
  Random shuffle_rng(o.seed, Stream::kGhosts, kGhostShuffle);
  Random noise_rng(o.seed, Stream::kNoise, kNoiseIndex);
  const double sigma = o.noise_mm * 1e-3;
  // A point near the body, away from every marker (a few tries).
  auto near_body = [&](int f, int* marker) {
    Eigen::Vector3d p;
    for (int attempt = 0; attempt < 20; ++attempt) {
      *marker = ghost_rng.UniformInt(0, nm - 1);
      p = out.true_markers.row(f).segment<3>(3 * *marker).transpose() +
          ghost_rng.InBall(o.ghost_radius_m);
      double nearest = std::numeric_limits<double>::infinity();
      for (int m = 0; m < nm; ++m)
        nearest = std::min(nearest, (out.true_markers.row(f).segment<3>(3 * m).transpose() - p).norm());
      if (nearest >= o.ghost_min_distance_m) break;
    }
    return p;
  };

  out.points.resize(nf);
  out.labels.resize(nf);
  std::vector<Eigen::Vector3d> pts;
  std::vector<int> lab;
  for (int f = 0; f < nf; ++f) {
    pts.clear();
    lab.clear();
    for (int m = 0; m < nm; ++m) {
      if (!seen[static_cast<size_t>(f) * nm + m]) continue;
      Eigen::Vector3d p = out.true_markers.row(f).segment<3>(3 * m).transpose();
      for (int k = 0; k < 3; ++k) p[k] += sigma * noise_rng.Normal();
      pts.push_back(p);
      lab.push_back(m);
    }
    for (int g = 0; g < o.ghosts; ++g) {
      Eigen::Vector3d p;
      if (g < persistent) {
        Reflection& r = reflections[g];
        if (f >= r.until) {
          r.until = f + std::max(1, static_cast<int>(std::lround(ghost_rng.Uniform(0.2, 2.0) * o.rate_hz)));
          r.fixed = ghost_rng.Uniform() < 0.5;
          const Eigen::Vector3d at = near_body(f, &r.marker);
          r.where = r.fixed ? at : Eigen::Vector3d(at - out.true_markers.row(f).segment<3>(3 * r.marker).transpose());
        }
        p = r.fixed ? r.where
                    : Eigen::Vector3d(out.true_markers.row(f).segment<3>(3 * r.marker).transpose() + r.where);
      } else {
        int unused;
        p = near_body(f, &unused);
      }
      for (int k = 0; k < 3; ++k) p[k] += sigma * noise_rng.Normal();
      if (!inside(p)) continue;
      pts.push_back(p);
      lab.push_back(kGhostLabel);
    }
    if (second.rows() > 0 && f >= f0) {
      for (int m = 0; m < second.cols() / 3; ++m) {
        Eigen::Vector3d p = second.row(f - f0).segment<3>(3 * m).transpose();
        for (int k = 0; k < 3; ++k) p[k] += sigma * noise_rng.Normal();
        if (!inside(p)) continue;
        pts.push_back(p);
        lab.push_back(kSecondPersonLabel);
      }
    }
    // Fisher-Yates.
    for (int i = static_cast<int>(pts.size()) - 1; i > 0; --i) {
      const int j = shuffle_rng.UniformInt(0, i);
      std::swap(pts[i], pts[j]);
      std::swap(lab[i], lab[j]);
    }
    if (o.fault == SceneFault::kNanFrame && f == out.fault_begin) {
      // Every point NaN (the markers of this frame were removed above: they are not seen).
      for (Eigen::Vector3d& p : pts) p.setConstant(kNan);
      for (int& l : lab) l = kNanLabel;
      if (pts.empty()) {
        pts.push_back(Eigen::Vector3d::Constant(kNan));
        lab.push_back(kNanLabel);
      }
    }
    if (o.fault == SceneFault::kNanFrame && f == out.fault_end - 1) {
      // NaN columns between the real points.
      std::vector<Eigen::Vector3d> p2;
      std::vector<int> l2;
      for (size_t i = 0; i < pts.size(); ++i) {
        if (i % 2 == 0) {
          p2.push_back(Eigen::Vector3d::Constant(kNan));
          l2.push_back(kNanLabel);
        }
        p2.push_back(pts[i]);
        l2.push_back(lab[i]);
      }
      pts.swap(p2);
      lab.swap(l2);
    }
    out.points[f].resize(3, static_cast<Eigen::Index>(pts.size()));
    for (size_t i = 0; i < pts.size(); ++i) out.points[f].col(static_cast<Eigen::Index>(i)) = pts[i];
    out.labels[f] = lab;
  }
  *scene = std::move(out);
  return Status::Ok();
}

LabelScorer::LabelScorer(int num_markers)
    : run_(num_markers, 0), wrong_now_(num_markers, 0), marker_samples_(num_markers, 0),
      marker_correct_(num_markers, 0) {}

LabelScore LabelScorer::Add(const std::vector<int>& truth, const std::vector<int>& given) {
  LabelScore frame;
  std::fill(wrong_now_.begin(), wrong_now_.end(), 0);
  const size_t n = std::min(truth.size(), given.size());
  for (int t : truth) {
    if (t < 0) continue;
    ++frame.samples;
    if (t < static_cast<int>(marker_samples_.size())) ++marker_samples_[t];
  }
  for (size_t i = 0; i < n; ++i) {
    const int g = given[i], t = truth[i];
    if (g < 0) continue;
    if (g == t) {
      ++frame.correct;
      if (t < static_cast<int>(marker_correct_.size())) ++marker_correct_[t];
      continue;
    }
    ++frame.wrong;
    if (t == kSecondPersonLabel) ++frame.wrong_on_second_person;
    else if (t < 0) ++frame.wrong_on_ghosts;
    if (g < static_cast<int>(wrong_now_.size())) wrong_now_[g] = 1;
  }
  for (size_t m = 0; m < run_.size(); ++m) {
    if (wrong_now_[m]) ++run_[m];
    else Close(static_cast<int>(m));
  }
  total_.samples += frame.samples;
  total_.correct += frame.correct;
  total_.wrong += frame.wrong;
  total_.wrong_on_ghosts += frame.wrong_on_ghosts;
  total_.wrong_on_second_person += frame.wrong_on_second_person;
  return frame;
}

void LabelScorer::Close(int m) {
  if (run_[m] > 5) ++total_.swaps_longer_than_5_frames;
  total_.longest_wrong_run = std::max(total_.longest_wrong_run, run_[m]);
  run_[m] = 0;
}

LabelScore LabelScorer::Finish() {
  for (size_t m = 0; m < run_.size(); ++m) Close(static_cast<int>(m));
  return total_;
}

std::vector<int> SceneMarkerOf(const Model& model, const TrackingScene& scene) {
  std::vector<int> out(model.num_markers(), -1);
  for (int m = 0; m < model.num_markers(); ++m)
    for (int k = 0; k < scene.num_markers(); ++k)
      if (scene.marker_names[k] == model.markers()[m].name) out[m] = k;
  return out;
}

Model MismatchedModel(const Model& model, std::uint64_t seed, double displacement_m,
                      const std::string& prefix) {
  std::vector<Marker> markers = model.markers();
  Random rng(seed, Stream::kSecondPerson, 7);
  for (Marker& m : markers) {
    Eigen::Vector3d d(rng.Normal(), rng.Normal(), rng.Normal());
    d = d.normalized() * displacement_m / model.segments()[m.segment].scale;
    m.position += d;
    m.name = prefix + m.name;
  }
  Model out;
  Status s = Model::Build(model.name() + "_mismatched", model.segments(), model.joints(),
                          model.coordinates(), markers, model.derived_coordinates(), &out);
  (void)s;  // the structure is the model's own: it builds
  return out;
}

}  // namespace mocap::sim
