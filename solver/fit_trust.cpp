#include "solver/fit_trust.h"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cctype>
#include <cmath>
#include <map>
#include <set>

#include "model/kinematics.h"

namespace mocap::solver {
namespace {

constexpr double kRadToDeg = 180.0 / M_PI;

double AngleDeg(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {  // sign-free
  const double c = std::abs(a.normalized().dot(b.normalized()));
  return kRadToDeg * std::acos(std::min(1.0, c));
}


// A point and the rotation axes of joint j in its parent segment's frame, for the pose in `data`.
struct InParent {
  Eigen::Vector3d centre;
  std::vector<Eigen::Vector3d> axes;  // the joint's rotation elements, in element order
};
InParent JointInParent(const Model& model, const Geometry& g, const ModelData& d, int j) {
  const Joint& jt = model.joints()[j];
  const Eigen::Matrix3d& r = d.segment_rotation[jt.parent];
  InParent out;
  out.centre = r.transpose() * (JointCentre(model, d, j) - d.segment_position[jt.parent]);
  for (size_t e = 0; e < jt.elements.size(); ++e)
    if (jt.elements[e].kind == ElementKind::kRotation)
      out.axes.push_back(r.transpose() * d.element_rotation[j][e] * g.axis[j][e]);
  return out;
}

// The fitted model against one trial's functional estimate of joint j (see the header's "Frame
// of the comparison").
void CompareWithFunctional(const Model& fitted, const Geometry& g, int j, const FunctionalJoint& fj,
                           const Eigen::MatrixXd& z, bool axis_joint, FunctionalCheck* check) {
  const Joint& jt = fitted.joints()[j];
  ModelData d(fitted);
  Eigen::Vector3d fit_centre = Eigen::Vector3d::Zero(), fun_centre = Eigen::Vector3d::Zero(),
                  fun_axis = Eigen::Vector3d::Zero(), fun_point = Eigen::Vector3d::Zero();
  std::vector<Eigen::Vector3d> fit_axes, centres, axes;
  // A joint whose rotations all follow one angle but about more than one axis (the walker knee's
  // flexion with its coupled rotations) has no one fitted axis that SARA's estimates: SARA finds
  // the axis fixed in both segments that best explains their relative rotation, tilted from the
  // flexion axis by the coupled ones (8 deg on OpenCap's model). Its reference is the same
  // estimate made on the fitted model's own relative rotations over the same frames: the axis a
  // (in the parent) and b (in the child) minimising sum_f |a - R_f b|^2, |a| = |b| = 1.
  const bool coupled = axis_joint && jt.type != JointType::kHinge && jt.type != JointType::kUniversal;
  Eigen::Matrix<double, 6, 6> rotations = Eigen::Matrix<double, 6, 6>::Zero();
  for (int f = 0; f < z.rows(); ++f) {
    const Eigen::Vector3d c = fj.CentreInLab(f);
    if (!c.allFinite() || !z.row(f).allFinite()) continue;
    ForwardKinematics(fitted, g, z.row(f).transpose(), &d);
    const InParent p = JointInParent(fitted, g, d, j);
    const Eigen::Matrix3d rt = d.segment_rotation[jt.parent].transpose();
    const Eigen::Vector3d& o = d.segment_position[jt.parent];
    centres.push_back(rt * (c - o));
    fit_centre += p.centre;
    if (fit_axes.empty()) fit_axes.assign(p.axes.size(), Eigen::Vector3d::Zero());
    for (size_t k = 0; k < p.axes.size(); ++k) fit_axes[k] += p.axes[k];
    if (coupled) {
      Eigen::Matrix<double, 3, 6> row;
      row << Eigen::Matrix3d::Identity(), -(rt * d.segment_rotation[jt.child]);
      rotations += row.transpose() * row;
    }
    Eigen::Vector3d a = rt * fj.AxisInLab(f);
    if (!axes.empty() && a.dot(axes.front()) < 0) a = -a;
    axes.push_back(a);
    fun_axis += a;
    fun_point += rt * (fj.AxisPointInLab(f) - o);
  }
  check->frames = static_cast<int>(centres.size());
  if (centres.empty()) {
    check->excited = false;
    check->note = "no frame has both segments' clusters and a fitted pose";
    return;
  }
  const double n = static_cast<double>(centres.size());
  fit_centre /= n;
  if (!axis_joint) {  // a hinge's motion does not show a centre: SCoRE's is no reference there
    for (const Eigen::Vector3d& c : centres) fun_centre += c;
    fun_centre /= n;
    double spread = 0;
    for (const Eigen::Vector3d& c : centres) spread += (c - fun_centre).squaredNorm();
    check->centre_distance_mm = 1000.0 * (fit_centre - fun_centre).norm();
    check->functional_centre_in_parent = fun_centre;
    check->centre_spread_mm = 1000.0 * std::sqrt(spread / n);
    check->functional_std_mm = fj.centre.std_mm;
    return;
  }
  fun_axis.normalize();
  fun_point /= n;
  double angle = 180.0;  // the fitted rotation axis nearest the functional one
  if (coupled) {
    const Eigen::SelfAdjointEigenSolver<Eigen::Matrix<double, 6, 6>> eigen(rotations);
    fit_axes = {eigen.eigenvectors().col(0).head<3>().normalized()};
  }
  for (const Eigen::Vector3d& a : fit_axes) angle = std::min(angle, AngleDeg(a, fun_axis));
  double spread_deg = 0;
  for (const Eigen::Vector3d& a : axes) spread_deg += std::pow(AngleDeg(a, fun_axis), 2);
  const Eigen::Vector3d off = fit_centre - fun_point;
  check->axis_angle_deg = angle;
  check->axis_spread_deg = std::sqrt(spread_deg / n);
  check->functional_axis_std_deg = fj.axis.direction_std_deg;
  check->axis_line_distance_mm = 1000.0 * (off - off.dot(fun_axis) * fun_axis).norm();
  check->functional_axis_in_parent = fun_axis;
}

// Whether trial t sees every marker of `columns` (its column indices) in frame f.
bool SeesAll(const formats::MarkerTrial& m, const std::vector<int>& columns, int f) {
  for (int c : columns)
    if (!m.positions.row(f).segment<3>(3 * c).allFinite()) return false;
  return true;
}

// The trial to measure landmarks on: a static one first (fit.report.static_trials), else the one
// with the most frames that see every marker of `names`; -1 when none does. *columns: per trial,
// the names' column indices (empty where one is missing).
int LandmarkTrial(const FitResult& fit, const std::vector<FitTrial>& trials, const std::vector<std::string>& names,
                  std::vector<std::vector<int>>* columns) {
  const std::vector<std::string>& statics = fit.report.static_trials;
  int chosen = -1, chosen_frames = 0;
  bool chosen_static = false;
  columns->assign(trials.size(), {});
  for (size_t t = 0; t < trials.size(); ++t) {
    const formats::MarkerTrial& m = trials[t].markers;
    std::vector<int> c;
    for (const std::string& name : names) c.push_back(m.FindMarker(name));
    if (std::find(c.begin(), c.end(), -1) != c.end()) continue;
    (*columns)[t] = c;
    int frames = 0;
    for (int f = 0; f < m.num_frames(); ++f) frames += SeesAll(m, c, f);
    const bool is_static = std::find(statics.begin(), statics.end(), m.name) != statics.end();
    if (frames == 0) continue;
    if (chosen < 0 || (is_static && !chosen_static) || (is_static == chosen_static && frames > chosen_frames))
      chosen = static_cast<int>(t), chosen_frames = frames, chosen_static = is_static;
  }
  return chosen;
}

// The fitted centre of joint j against the measured midpoint of the pair (indices into
// `initial`'s markers, looked up by name in the trials). False when no trial sees both.
bool MeasureLandmarks(const Model& initial, const Model& fitted, const FitResult& fit,
                      const std::vector<FitTrial>& trials, int j, std::pair<int, int> pair,
                      LandmarkCheck* check) {
  check->first = initial.markers()[pair.first].name;
  check->second = initial.markers()[pair.second].name;
  std::vector<std::vector<int>> columns;
  const int chosen = LandmarkTrial(fit, trials, {check->first, check->second}, &columns);
  if (chosen < 0) return false;
  const formats::MarkerTrial& m = trials[chosen].markers;
  const int ca = columns[chosen][0], cb = columns[chosen][1];
  const Geometry g(fitted);
  ModelData d(fitted);
  double sum = 0;
  int n = 0;
  for (int f = 0; f < m.num_frames(); ++f) {
    const Eigen::Vector3d xa = m.positions.row(f).segment<3>(3 * ca).transpose();
    const Eigen::Vector3d xb = m.positions.row(f).segment<3>(3 * cb).transpose();
    const Eigen::VectorXd z = fit.coordinates[chosen].row(f).transpose();
    if (!xa.allFinite() || !xb.allFinite() || !z.allFinite()) continue;
    ForwardKinematics(fitted, g, z, &d);
    sum += (JointCentre(fitted, d, j) - 0.5 * (xa + xb)).norm();
    ++n;
  }
  if (n == 0) return false;
  check->trial = m.name;
  check->frames = n;
  check->centre_from_midpoint_mm = 1000.0 * sum / n;
  return true;
}

// The pelvis landmarks of a model (fit_trust.h): marker indices, -1 where absent.
struct PelvisLandmarks {
  int right_asis = -1, left_asis = -1, right_psis = -1, left_psis = -1, sacrum = -1;
  bool complete() const {
    return right_asis >= 0 && left_asis >= 0 && ((right_psis >= 0 && left_psis >= 0) || sacrum >= 0);
  }
  std::vector<int> markers() const {
    std::vector<int> m = {right_asis, left_asis};
    if (right_psis >= 0 && left_psis >= 0) m.insert(m.end(), {right_psis, left_psis});
    else m.push_back(sacrum);
    return m;
  }
};

}  // namespace

char PelvisLandmarkSide(const std::string& name, const std::string& stem) {
  std::string s;
  for (char c : name)
    if (std::isalnum(static_cast<unsigned char>(c))) s += static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  if (s.size() > 5 && s.compare(s.size() - 5, 5, "study") == 0) s.resize(s.size() - 5);
  const size_t at = s.find(stem);
  if (at == std::string::npos) return 0;
  size_t end = at + stem.size();
  if (end < s.size() && s[end] == 's') ++end;  // ASIS, PSIS
  const std::string rest = s.substr(0, at) + s.substr(end);
  if (rest == "r" || rest == "right") return 'r';
  if (rest == "l" || rest == "left") return 'l';
  return 0;
}

namespace {

// The landmarks among the markers of `segment`.
PelvisLandmarks FindPelvisLandmarks(const Model& model, int segment) {
  PelvisLandmarks p;
  for (int m = 0; m < model.num_markers(); ++m) {
    const Marker& mk = model.markers()[m];
    if (mk.segment != segment) continue;
    std::string lower;
    for (char c : mk.name) lower += static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
    if (const char a = PelvisLandmarkSide(mk.name, "asi"); a == 'r') p.right_asis = m;
    else if (a == 'l') p.left_asis = m;
    else if (const char b = PelvisLandmarkSide(mk.name, "psi"); b == 'r') p.right_psis = m;
    else if (b == 'l') p.left_psis = m;
    else if (lower.find("sacr") != std::string::npos) p.sacrum = m;
  }
  return p;
}

// The landmarks' pelvis frame (fit_trust.h) from their positions (right ASIS, left ASIS, then the
// PSIS or the sacrum): origin, rotation (columns anterior, superior, right), width and depth.
// False when the points do not make a frame.
bool PelvisFrame(const std::vector<Eigen::Vector3d>& at, Eigen::Vector3d* origin, Eigen::Matrix3d* axes,
                 double* width, double* depth) {
  const Eigen::Vector3d mid_asis = 0.5 * (at[0] + at[1]);
  const Eigen::Vector3d back = at.size() == 4 ? Eigen::Vector3d(0.5 * (at[2] + at[3])) : at[2];
  Eigen::Vector3d right = at[0] - at[1];
  *width = right.norm();
  if (!(*width > 1e-6)) return false;
  right /= *width;
  Eigen::Vector3d anterior = mid_asis - back;
  *depth = anterior.norm();
  anterior -= anterior.dot(right) * right;
  if (!(anterior.norm() > 1e-6)) return false;
  anterior.normalize();
  axes->col(0) = anterior;
  axes->col(1) = right.cross(anterior);  // superior
  axes->col(2) = right;
  *origin = mid_asis;
  return true;
}

// Harrington et al. 2007 in that frame (metres; `side` +1 right, -1 left).
Eigen::Vector3d HarringtonHip(double width, double depth, double side) {
  return Eigen::Vector3d(-0.24 * depth - 0.0099, -0.30 * width - 0.0109, side * (0.33 * width + 0.0073));
}

// The regression check of hip j (fit_trust.h); false when the model has no such landmarks on the
// joint's parent, the centre is not lateral (not a hip), or no trial sees every landmark.
bool MeasureRegression(const Model& initial, const Model& fitted, const FitResult& fit,
                       const std::vector<FitTrial>& trials, int j, RegressionCheck* check) {
  const int pelvis = initial.joints()[j].parent;
  const PelvisLandmarks lm = FindPelvisLandmarks(initial, pelvis);
  if (!lm.complete()) return false;
  const std::vector<int> markers = lm.markers();
  // The generic model in its default pose: which side the joint is on, and its own offset.
  const Geometry gi(initial);
  ModelData di(initial);
  ForwardKinematics(initial, gi, initial.DefaultCoordinates(), &di);
  std::vector<Eigen::Vector3d> at;
  for (int m : markers) at.push_back(MarkerPosition(initial, gi, di, m));
  Eigen::Vector3d origin;
  Eigen::Matrix3d axes;
  double width = 0, depth = 0;
  if (!PelvisFrame(at, &origin, &axes, &width, &depth)) return false;
  const Eigen::Vector3d generic = axes.transpose() * (JointCentre(initial, di, j) - origin);
  if (std::abs(generic.z()) < 0.03 || generic.y() > 0) return false;  // not beside and below: no hip
  const double side = generic.z() > 0 ? 1.0 : -1.0;
  check->generic_from_regression_mm = 1000.0 * (generic - HarringtonHip(width, depth, side)).norm();
  for (int m : markers) check->markers.push_back(initial.markers()[m].name);
  std::vector<std::vector<int>> columns;
  const int chosen = LandmarkTrial(fit, trials, check->markers, &columns);
  if (chosen < 0) return false;
  const formats::MarkerTrial& m = trials[chosen].markers;
  const Geometry g(fitted);
  ModelData d(fitted);
  Eigen::Vector3d centre_sum = Eigen::Vector3d::Zero();
  double width_sum = 0, depth_sum = 0;
  int n = 0;
  for (int f = 0; f < m.num_frames(); ++f) {
    const Eigen::VectorXd z = fit.coordinates[chosen].row(f).transpose();
    if (!SeesAll(m, columns[chosen], f) || !z.allFinite()) continue;
    for (size_t k = 0; k < markers.size(); ++k)
      at[k] = m.positions.row(f).segment<3>(3 * columns[chosen][k]).transpose();
    if (!PelvisFrame(at, &origin, &axes, &width, &depth)) continue;
    ForwardKinematics(fitted, g, z, &d);
    centre_sum += axes.transpose() * (JointCentre(fitted, d, j) - origin);
    width_sum += width;
    depth_sum += depth;
    ++n;
  }
  if (n == 0) return false;
  check->trial = m.name;
  check->frames = n;
  check->pelvis_width_mm = 1000.0 * width_sum / n;
  check->pelvis_depth_mm = 1000.0 * depth_sum / n;
  check->offset_mm = 1000.0 * (centre_sum / n - HarringtonHip(width_sum / n, depth_sum / n, side));
  check->centre_from_regression_mm = check->offset_mm.norm();
  return true;
}

// FitTrustOptions::profile_far_centres: the options of the re-solves, those of the fit's last
// stage (see the header).
FitOptions ProfileOptions(const FitResult& fit, const FitTrustOptions& options) {
  FitOptions o = options.fit;
  o.staged = false;
  o.fit_scales = false;  // the schedule's last stage keeps the first stage's scales
  if (!fit.report.stages.empty()) o.marker_sigma_m = 1e-3 * fit.report.stages.back().marker_sigma_mm;
  for (const auto& held : fit.report.held_joints)
    for (const ParameterInfo& p : fit.model.parameters())
      if (p.name.rfind(held.first + ".centre.", 0) == 0 || p.name.rfind(held.first + ".axis", 0) == 0)
        o.held_parameters.push_back(p.name);
  return o;
}

// The parameters p with the axis angles of joint j's rotation element e (its k-th) turned so
// that the axis, in the parent's frame, is `target` (either sign): Gauss-Newton on the two
// angles with a numerical Jacobian of the model's own kinematics, so that it holds for any joint
// frame. False if the model refuses a step or the axis does not reach the target.
bool AxisAnglesTowards(const Model& model, int j, int e, int k, const Eigen::Vector3d& target,
                       Eigen::VectorXd* p) {
  const int a = model.axis_index(j, e);
  if (a < 0) return false;
  auto axis_at = [&](const Eigen::VectorXd& q, Eigen::Vector3d* axis) {
    Model m;
    if (!model.WithParameters(q, &m).ok()) return false;
    const Geometry g(m);
    ModelData d(m);
    ForwardKinematics(m, g, m.DefaultCoordinates(), &d);
    const InParent in = JointInParent(m, g, d, j);
    if (k >= static_cast<int>(in.axes.size())) return false;
    *axis = in.axes[k].normalized();
    return true;
  };
  Eigen::Vector3d axis;
  if (!axis_at(*p, &axis)) return false;
  const Eigen::Vector3d t = (axis.dot(target) < 0 ? -target : target).normalized();
  for (int it = 0; it < 20; ++it) {
    if (!axis_at(*p, &axis)) return false;
    const Eigen::Vector3d r = axis - t;
    if (r.norm() < 1e-9) return true;
    Eigen::Matrix<double, 3, 2> jac;
    for (int c = 0; c < 2; ++c) {
      Eigen::VectorXd q = *p;
      q[a + c] += 1e-6;
      Eigen::Vector3d moved;
      if (!axis_at(q, &moved)) return false;
      jac.col(c) = (moved - axis) / 1e-6;
    }
    const Eigen::Vector2d step = (jac.transpose() * jac).ldlt().solve(-jac.transpose() * r);
    p->segment<2>(a) += step;
  }
  return axis_at(*p, &axis) && (axis - t).norm() < 1e-6;
}

// The fit solved again from its own result by `model` (the fitted model, or it with a centre
// moved) and the fit's poses.
Status Resolve(const Model& model, const FitResult& fit, const std::vector<FitTrial>& trials,
               const FitOptions& o, FitResult* out) {
  std::vector<FitTrial> from = trials;
  for (size_t t = 0; t < from.size(); ++t) from[t].initial_coordinates = fit.coordinates[t];
  return FitModel(model, from, o, out);
}

}  // namespace

bool FitTrustOptions::IsValid(std::string* error) const {
  std::string why;
  if (!functional.IsValid(&why)) {
    if (error) *error = "functional: " + why;
    return false;
  }
  if (!(far_mm > 0) || !(far_deg > 0) || !(far_landmark_mm > 0) || !(far_regression_mm > 0)) {
    if (error) *error = "far_mm, far_deg, far_landmark_mm and far_regression_mm must be > 0";
    return false;
  }
  if (!(told_apart_chi2 > 0) || !(told_apart_chi2_axis > 0)) {
    if (error) *error = "told_apart_chi2 and told_apart_chi2_axis must be > 0";
    return false;
  }
  if (profile_far_centres && !fit.IsValid(&why)) {
    if (error) *error = "fit: " + why;
    return false;
  }
  return true;
}

Status CheckFitTrust(const Model& initial, const FitResult& fit, const std::vector<FitTrial>& trials,
                     const FitTrustOptions& options, FitTrust* trust) {
  std::string why;
  if (!options.IsValid(&why)) return Status::Error("fit trust: " + why);
  const Model& fitted = fit.model;
  if (fit.coordinates.size() != trials.size())
    return Status::Error("fit trust: " + std::to_string(trials.size()) + " trials but coordinates of " +
                         std::to_string(fit.coordinates.size()));
  for (size_t t = 0; t < trials.size(); ++t)
    if (fit.coordinates[t].rows() != trials[t].markers.num_frames() ||
        fit.coordinates[t].cols() != fitted.num_coordinates())
      return Status::Error("fit trust: trial '" + trials[t].markers.name + "' has " +
                           std::to_string(trials[t].markers.num_frames()) + " frames, its fitted coordinates " +
                           std::to_string(fit.coordinates[t].rows()) + " x " +
                           std::to_string(fit.coordinates[t].cols()) + " (expected x " +
                           std::to_string(fitted.num_coordinates()) + ")");
  if (fitted.num_joints() != initial.num_joints())
    return Status::Error("fit trust: the fitted model has " + std::to_string(fitted.num_joints()) +
                         " joints, the initial model '" + initial.name() + "' " +
                         std::to_string(initial.num_joints()));
  for (int j = 0; j < fitted.num_joints(); ++j)
    if (fitted.joints()[j].name != initial.joints()[j].name)
      return Status::Error("fit trust: joint " + std::to_string(j) + " is '" + fitted.joints()[j].name +
                           "' in the fitted model, '" + initial.joints()[j].name + "' in the initial one");
  std::vector<int> joints;
  if (options.joints.empty()) {
    for (int j = 0; j < fitted.num_joints(); ++j)
      if (fitted.joints()[j].parent >= 0) joints.push_back(j);
  } else {
    for (const std::string& name : options.joints) {
      const int j = fitted.FindJoint(name);
      if (j < 0) return Status::Error("fit trust: the model has no joint '" + name + "'");
      if (fitted.joints()[j].parent < 0)
        return Status::Error("fit trust: joint '" + name + "' joins its segment to the lab: no functional estimate");
      joints.push_back(j);
    }
  }

  const FitReport& report = fit.report;
  const std::set<std::string> undetermined(report.undetermined.begin(), report.undetermined.end());
  std::map<std::string, const ParameterEstimate*> parameters;
  for (const ParameterEstimate& e : report.parameters) parameters[e.name] = &e;

  const Geometry g_fit(fitted), g_initial(initial);
  ModelData d_fit(fitted), d_initial(initial);
  ForwardKinematics(fitted, g_fit, fitted.DefaultCoordinates(), &d_fit);
  ForwardKinematics(initial, g_initial, initial.DefaultCoordinates(), &d_initial);

  FitTrust out;
  out.outlier_markers = report.outlier_markers;
  out.undetermined = report.undetermined;
  for (int j : joints) {
    const Joint& jt = fitted.joints()[j];
    JointTrust jtr;
    jtr.joint = jt.name;
    jtr.type = jt.type;
    jtr.axis_joint = DescribedByAxis(jt);
    const InParent pf = JointInParent(fitted, g_fit, d_fit, j), pi = JointInParent(initial, g_initial, d_initial, j);
    jtr.from_generic_mm = 1000.0 * (pf.centre - pi.centre).norm();
    for (size_t k = 0; k < std::min(pf.axes.size(), pi.axes.size()); ++k)
      jtr.axis_from_generic_deg = std::max(jtr.axis_from_generic_deg, AngleDeg(pf.axes[k], pi.axes[k]));
    double variance = 0;
    for (const char* xyz : {"x", "y", "z"}) {
      const std::string name = jt.name + ".centre." + xyz;
      auto it = parameters.find(name);
      if (it == parameters.end() || !it->second->fitted) continue;
      jtr.centre_fitted = true;
      variance += it->second->std * it->second->std;
      jtr.undetermined |= !it->second->determined || undetermined.count(name) > 0;
    }
    // The centre parameter is unscaled in the parent; the report's figures are scaled.
    jtr.fitted_std_mm = 1000.0 * g_fit.scale[jt.parent] * std::sqrt(variance);
    for (size_t t = 0; t < trials.size(); ++t) {
      FunctionalCheck check;
      check.trial = trials[t].markers.name;
      FunctionalJoint fj;
      if (Status s = EstimateFunctionalJoint(fitted, trials[t].markers, jt.name, options.functional, &fj); !s) {
        check.note = s.message();
      } else {
        check.estimated = true;
        const FunctionalFit& primary = jtr.axis_joint ? fj.axis.fit : fj.centre.fit;
        check.excited = primary.excited;
        check.note = primary.note;
        if (check.excited) {
          CompareWithFunctional(fitted, g_fit, j, fj, fit.coordinates[t], jtr.axis_joint, &check);
          check.far = check.excited && (jtr.axis_joint ? check.axis_angle_deg > options.far_deg
                                                       : check.centre_distance_mm > options.far_mm);
        }
      }
      // The headline is the most precise estimate, by its own bootstrap sd: the trial made for
      // the joint. By the most frames (the earlier rule) biobuddy's right knee was judged on the
      // trunk trial (1,047 frames, SARA sd 7.9 deg: 42 deg "far") instead of its own (217
      // frames, 0.5 deg: 7 deg).
      auto precision_sd = [&](const FunctionalCheck& c) {
        return jtr.axis_joint ? c.functional_axis_std_deg : c.functional_std_mm;
      };
      if (check.excited &&
          (jtr.best_check < 0 || precision_sd(check) < precision_sd(jtr.checks[jtr.best_check])))
        jtr.best_check = static_cast<int>(jtr.checks.size());
      jtr.checks.push_back(std::move(check));
    }
    for (int c = 0; c < static_cast<int>(jtr.checks.size()); ++c) {
      const FunctionalCheck& check = jtr.checks[c];
      const double sd = jtr.axis_joint ? check.functional_axis_std_deg : check.functional_std_mm;
      if (!check.excited || c == jtr.best_check) continue;
      const FunctionalCheck* second = jtr.second_check < 0 ? nullptr : &jtr.checks[jtr.second_check];
      if (second == nullptr || sd < (jtr.axis_joint ? second->functional_axis_std_deg : second->functional_std_mm))
        jtr.second_check = c;
    }
    if (jtr.second_check >= 0) {
      const FunctionalCheck& a = jtr.checks[jtr.best_check];
      const FunctionalCheck& b = jtr.checks[jtr.second_check];
      jtr.functional_between_trials =
          jtr.axis_joint ? AngleDeg(a.functional_axis_in_parent, b.functional_axis_in_parent)
                         : 1000.0 * (a.functional_centre_in_parent - b.functional_centre_in_parent).norm();
    }
    if (const auto pair = LandmarkPairAbout(initial, j); pair.first >= 0) {
      LandmarkCheck lc;
      if (MeasureLandmarks(initial, fitted, fit, trials, j, pair, &lc)) {
        const Eigen::Vector3d mid = 0.5 * (MarkerPosition(initial, g_initial, d_initial, pair.first) +
                                           MarkerPosition(initial, g_initial, d_initial, pair.second));
        lc.generic_from_midpoint_mm = 1000.0 * (JointCentre(initial, d_initial, j) - mid).norm();
        lc.far = lc.centre_from_midpoint_mm > lc.generic_from_midpoint_mm + options.far_landmark_mm;
        jtr.landmarks.push_back(std::move(lc));
      }
    }
    if (!jtr.axis_joint) {
      RegressionCheck rc;
      if (MeasureRegression(initial, fitted, fit, trials, j, &rc)) {
        rc.far = rc.centre_from_regression_mm > options.far_regression_mm;
        jtr.regression.push_back(std::move(rc));
      }
    }
    out.joints.push_back(std::move(jtr));
  }
  // FitTrustOptions::profile_far_centres (see the header).
  const FitOptions o = ProfileOptions(fit, options);  // the same for every joint's re-solves
  FitResult free_fit;
  bool free_solved = false;
  Status free_status = Status::Ok();
  for (JointTrust& jtr : out.joints) {
    if (!options.profile_far_centres || jtr.best_check < 0) continue;
    const FunctionalCheck& best = jtr.checks[jtr.best_check];
    if (!best.far) continue;
    const int j = fitted.FindJoint(jtr.joint);
    bool held = false;
    for (const auto& h : report.held_joints) held |= h.first == jtr.joint;
    if (j < 0 || held || fitted.centre_index(j) < 0) continue;
    if (!jtr.axis_joint && !jtr.centre_fitted) continue;
    // Axis joints: the fitted rotation axis nearest SARA's, and its element.
    int axis_element = -1, axis_k = -1;
    if (jtr.axis_joint) {
      const Joint& jt = fitted.joints()[j];
      const InParent in = JointInParent(fitted, g_fit, d_fit, j);
      double nearest = 1e9;
      for (size_t e = 0, k = 0; e < jt.elements.size(); ++e) {
        if (jt.elements[e].kind != ElementKind::kRotation) continue;
        const double angle = AngleDeg(in.axes[k], best.functional_axis_in_parent);
        if (fitted.axis_index(j, static_cast<int>(e)) >= 0 && angle < nearest) {
          nearest = angle;
          axis_element = static_cast<int>(e);
          axis_k = static_cast<int>(k);
        }
        ++k;
      }
      if (axis_element < 0) continue;  // axes not fitted
    }
    ProfileCheck pc;
    pc.trial = best.trial;
    pc.centre_distance_mm = jtr.axis_joint ? 0.0 : best.centre_distance_mm;
    pc.axis_angle_deg = jtr.axis_joint ? best.axis_angle_deg : 0.0;
    // A check that cannot be made says why; it never fails the fit it checks.
    auto unmade = [&](const std::string& why) {
      pc.note = why;
      jtr.profile.push_back(pc);
    };
    if (!free_solved) {
      free_status = Resolve(fitted, fit, trials, o, &free_fit);
      if (free_status.ok() && !free_fit.report.solver.IsSolutionUsable())
        free_status = Status::Error(free_fit.report.solver.message);
      free_solved = true;
    }
    if (!free_status.ok()) {
      unmade("the fit solved again from its result failed: " + free_status.message());
      continue;
    }
    const InParent now = JointInParent(fitted, g_fit, d_fit, j);
    const Geometry g_free(free_fit.model);
    ModelData d_free(free_fit.model);
    ForwardKinematics(free_fit.model, g_free, free_fit.model.DefaultCoordinates(), &d_free);
    const InParent free_now = JointInParent(free_fit.model, g_free, d_free, j);
    const double free_moved_mm = 1000.0 * (free_now.centre - now.centre).norm();
    Eigen::VectorXd p = fitted.InitialParameters();
    FitOptions held_centre = o;
    if (jtr.axis_joint) {
      // The axis angles turned onto SARA's axis.
      if (!AxisAnglesTowards(fitted, j, axis_element, axis_k, best.functional_axis_in_parent, &p)) {
        unmade("the model's axis parameters cannot turn the axis onto the functional one");
        continue;
      }
      const int a = fitted.axis_index(j, axis_element);
      held_centre.fixed_parameters.push_back(fitted.parameters()[a].name);
      held_centre.fixed_parameters.push_back(fitted.parameters()[a + 1].name);
    } else {
      // The centre parameter moved by the difference, in the parent's unscaled frame.
      p.segment<3>(fitted.centre_index(j)) +=
          (best.functional_centre_in_parent - now.centre) / g_fit.scale[fitted.joints()[j].parent];
      for (const char* xyz : {"x", "y", "z"}) held_centre.fixed_parameters.push_back(jtr.joint + ".centre." + xyz);
    }
    Model moved;
    if (Status s = fitted.WithParameters(p, &moved); !s) {
      unmade("the model refuses the functional estimate: " + s.message());
      continue;
    }
    FitResult held_fit;
    Status held_status = Resolve(moved, fit, trials, held_centre, &held_fit);
    if (held_status.ok() && !held_fit.report.solver.IsSolutionUsable())
      held_status = Status::Error(held_fit.report.solver.message);
    if (!held_status.ok()) {
      unmade("the fit with it held there failed: " + held_status.message());
      continue;
    }
    pc.delta_chi2 = 2.0 * (held_fit.report.solver.final_cost - free_fit.report.solver.final_cost);
    pc.free_centre_moved_mm = free_moved_mm;
    pc.marker_rms_free_mm = free_fit.report.marker_rms_mm;
    pc.marker_rms_held_mm = held_fit.report.marker_rms_mm;
    pc.iterations_free = free_fit.report.solver.num_iterations();
    pc.iterations_held = held_fit.report.solver.num_iterations();
    // A centre is three numbers, an axis direction two.
    const double threshold = jtr.axis_joint ? options.told_apart_chi2_axis : options.told_apart_chi2;
    pc.told_apart = pc.delta_chi2 > threshold;
    pc.held_fits_better = pc.delta_chi2 < -threshold;
    // FitTrustOptions::adopt_better_minimum: released, the held fit finds its own minimum. Not
    // only where the held fit is the lower: where a held solve ends in a flat valley is the
    // solver's path (biobuddy's left ankle, held at SARA: -19.7 with one damping rule, +12.2 with
    // another), the minimum its basin holds is not.
    if (options.adopt_better_minimum) {
      FitResult released;
      Status rs = Resolve(held_fit.model, held_fit, trials, o, &released);
      if (rs.ok() && released.report.solver.IsSolutionUsable()) {
        pc.released = true;
        pc.released_delta_chi2 = 2.0 * (released.report.solver.final_cost - free_fit.report.solver.final_cost);
        pc.iterations_released = released.report.solver.num_iterations();
        if (pc.released_delta_chi2 < -threshold &&
            (!out.better_minimum || pc.released_delta_chi2 < out.better_minimum->delta_chi2))
          out.better_minimum = BetterMinimum{jtr.joint, pc.released_delta_chi2, std::move(held_fit), std::move(released)};
      }
    }
    jtr.profile.push_back(std::move(pc));
  }
  *trust = std::move(out);
  return Status::Ok();
}

Status CheckFitTrustAndAdopt(const Model& initial, const std::vector<FitTrial>& trials,
                             const FitTrustOptions& options, FitResult* fit, FitTrust* trust) {
  MOCAP_RETURN_IF_ERROR(CheckFitTrust(initial, *fit, trials, options, trust));
  if (!trust->better_minimum) return Status::Ok();
  BetterMinimum better = std::move(*trust->better_minimum);
  trust->better_minimum.reset();
  ProfileCheck first;
  for (const JointTrust& j : trust->joints)
    if (j.joint == better.joint)
      for (const ProfileCheck& p : j.profile)
        if (p.released) first = p;
  first.adopted = true;

  const FitOptions o = ProfileOptions(*fit, options);
  const FitReport& from = fit->report;
  FitResult adopted = std::move(better.released);
  FitReport& r = adopted.report;
  // The schedule's account, then the two solves that found the better minimum.
  std::vector<FitStageSummary> stages = from.stages;
  if (stages.empty()) stages.push_back(StageSummary("all parameters", options.fit, from));
  stages.push_back(StageSummary(better.joint + " held at its functional estimate", o, better.held.report));
  stages.push_back(StageSummary("all parameters, released from there", o, r));
  stages.end()[-1].better_minimum_search = stages.end()[-2].better_minimum_search = true;
  std::vector<IterationSummary> iterations = from.solver.iterations;
  for (const LmSummary* s : {&better.held.report.solver, &r.solver})
    iterations.insert(iterations.end(), s->iterations.begin(), s->iterations.end());
  r.solver.iterations = std::move(iterations);
  r.solver.initial_cost = from.solver.initial_cost;
  r.solver.num_linear_solves += from.solver.num_linear_solves + better.held.report.solver.num_linear_solves;
  r.solver.total_seconds += from.solver.total_seconds + better.held.report.solver.total_seconds;
  r.stages = std::move(stages);
  r.initial_marker_rms_mm = from.initial_marker_rms_mm;
  r.held_joints = from.held_joints;
  r.attached_markers = from.attached_markers;
  r.placed_markers = from.placed_markers;
  r.scaling_marker_weights = from.scaling_marker_weights;
  r.far_moved_markers = from.far_moved_markers;
  r.coarse = from.coarse;
  r.reposed = r.reposed || from.reposed;
  r.rescued_frames += from.rescued_frames + better.held.report.rescued_frames;
  r.ik_seconds += from.ik_seconds + better.held.report.ik_seconds;
  r.solve_seconds += from.solve_seconds + better.held.report.solve_seconds;
  r.wall_seconds += from.wall_seconds + better.held.report.wall_seconds;
  // A held joint's parameters stay undetermined; the caller's model is the parameters' start.
  for (const std::string& name : o.held_parameters)
    if (std::find(r.undetermined.begin(), r.undetermined.end(), name) == r.undetermined.end())
      r.undetermined.push_back(name);
  std::map<std::string, double> initial_value;
  for (const ParameterEstimate& e : from.parameters) initial_value[e.name] = e.initial;
  for (ParameterEstimate& e : r.parameters)
    if (auto it = initial_value.find(e.name); it != initial_value.end()) e.initial = it->second;
  *fit = std::move(adopted);

  FitTrustOptions again = options;
  again.adopt_better_minimum = false;
  MOCAP_RETURN_IF_ERROR(CheckFitTrust(initial, *fit, trials, again, trust));
  trust->adopted_joint = better.joint;
  trust->adopted_delta_chi2 = better.delta_chi2;
  for (JointTrust& j : trust->joints)
    if (j.joint == better.joint) j.profile.insert(j.profile.begin(), first);
  return Status::Ok();
}

}  // namespace mocap::solver
