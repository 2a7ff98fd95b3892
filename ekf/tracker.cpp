#include "ekf/tracker.h"

#include <Eigen/Cholesky>
#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <limits>

#include "ekf/assignment.h"
#include "ekf/filter.h"

namespace mocap::ekf {

namespace {
constexpr double kForbidden = 1e9;  // cost of a pair the gate excludes (finite: see assignment.h)
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

bool Fail(std::string* error, const char* message) {
  if (error) *error = message;
  return false;
}
}  // namespace

bool TrackerOptions::IsValid(std::string* error) const {
  if (!(rate_hz > 0) || !std::isfinite(rate_hz)) return Fail(error, "rate_hz must be > 0");
  if (!(jerk_psd_rotational > 0) || !(jerk_psd_translational > 0))
    return Fail(error, "jerk_psd_rotational and jerk_psd_translational must be > 0");
  if (!(sigma_m > 0)) return Fail(error, "sigma_m must be > 0");
  if (!(gate_chi2 > 0)) return Fail(error, "gate_chi2 must be > 0");
  if (max_points < 1) return Fail(error, "max_points must be >= 1");
  if (divergence_frames < 1) return Fail(error, "divergence_frames must be >= 1");
  if (!(min_labelled_fraction >= 0 && min_labelled_fraction <= 1))
    return Fail(error, "min_labelled_fraction must be in [0, 1]");
  if (!(max_nis_per_dof > 0)) return Fail(error, "max_nis_per_dof must be > 0");
  if (!(up.norm() > 0.5) || !up.allFinite()) return Fail(error, "up must be a non-zero vector");
  if (init_headings < 1) return Fail(error, "init_headings must be >= 1");
  if (init_iterations < 3) return Fail(error, "init_iterations must be >= 3");
  if (!(init_max_rms_m > 0)) return Fail(error, "init_max_rms_m must be > 0");
  if (!(init_min_fraction > 0 && init_min_fraction <= 1))
    return Fail(error, "init_min_fraction must be in (0, 1]");
  if (!(init_ambiguity_ratio >= 1)) return Fail(error, "init_ambiguity_ratio must be >= 1");
  if (!static_pose.allFinite()) return Fail(error, "static_pose must be finite");
  for (double s : {init_sigma_rotational, init_sigma_translational, init_sigma_velocity_rotational,
                   init_sigma_velocity_translational, init_sigma_acceleration_rotational,
                   init_sigma_acceleration_translational})
    if (!(s > 0)) return Fail(error, "the init_sigma_* must be > 0");
  if (!(swap_inflation_rotational >= 0) || !(swap_inflation_translational >= 0))
    return Fail(error, "swap_inflation_* must be >= 0");
  return true;
}

const char* ToString(TrackState state) {
  switch (state) {
    case TrackState::kInitialising: return "initialising";
    case TrackState::kTracking: return "tracking";
    case TrackState::kLost: return "lost";
  }
  return "unknown";
}

struct Tracker::Impl {
  // --- model ---
  std::shared_ptr<const Model> model;
  TrackerOptions options;
  Geometry geometry;
  ModelData data;
  int nz = 0, nm = 0;
  std::vector<char> rotational, wraps;
  Eigen::VectorXd marker_weight;  // w_m / sigma_m^2
  // The root joint, for placing hypotheses: its rotations as signed coordinate axes (for an
  // Euler decomposition) and its translations before any rotation (moving along fixed axes).
  bool root_euler = false;
  int root_rot_coord[3] = {-1, -1, -1}, root_rot_axis[3] = {0, 0, 0};
  double root_rot_sign[3] = {1, 1, 1};
  std::vector<std::pair<int, Eigen::Vector3d>> root_translations;
  std::vector<char> root_free;

  // --- state ---
  Eigen::VectorXd x;  // [z; z'; z'']
  Eigen::MatrixXd P;
  Eigen::VectorXd jerk_psd;
  double last_time = kNaN;
  bool had_track = false;
  Eigen::VectorXd z_good;  // last pose that passed the divergence test
  int bad_frames = 0;
  TrackOutput out;

  // --- per-frame workspace (sized in Allocate) ---
  std::vector<int> valid;  // input indices of the finite points, compacted
  Eigen::Matrix3Xd points;
  Eigen::VectorXd zbuf;
  Eigen::Matrix3Xd predicted;
  std::vector<Eigen::Matrix<double, 3, Eigen::Dynamic>> jac;
  Eigen::Matrix<double, 3, Eigen::Dynamic> jp;
  std::vector<Eigen::Matrix3d> s_inv;
  std::vector<double> reject_sq;
  Eigen::MatrixXd cost;
  std::vector<int> row_to_col;
  LinearAssignment lap;
  Eigen::MatrixXd A;
  Eigen::VectorXd b;
  CoordinateUpdate update;

  void SetModel(std::shared_ptr<const Model> m);
  void Allocate();
  void ResetState();
  double Dt(double time_s) const;
  void Predict(double dt);
  void Linearise(const Eigen::VectorXd& z);
  void LabelByGating(int np);
  int ApplyLabels(int np);
  bool FilterUpdate(double* nis);
  void Wrap(Eigen::VectorXd* z) const;
  bool TryInitialise(int np);

  // Initialisation pieces.
  struct Hypothesis {
    double score = std::numeric_limits<double>::infinity();
    double rms = 0;
    int labelled = 0;
    std::vector<int> assignment;  // per marker: compact point index or -1
    Eigen::VectorXd z;
  };
  bool PlaceRoot(const Eigen::VectorXd& start, const Eigen::Matrix3d& turn,
                 const Eigen::Vector3d& centroid, Eigen::VectorXd* z);
  Hypothesis Icp(Eigen::VectorXd z, int np);
};

void Tracker::Impl::SetModel(std::shared_ptr<const Model> m) {
  model = std::move(m);
  const Model& md = *model;
  nz = md.num_coordinates();
  nm = md.num_markers();
  geometry = Geometry(md);
  data = ModelData(md);
  rotational.assign(nz, 0);
  wraps.assign(nz, 0);
  for (int i = 0; i < nz; ++i) rotational[i] = md.coordinates()[i].rotational;
  // Wrapped: drives only identity rotations and its range covers a full turn.
  std::vector<char> only_identity_rotation(nz, 1), drives(nz, 0);
  for (const Joint& j : md.joints())
    for (const JointElement& e : j.elements) {
      if (e.coordinate < 0) continue;
      drives[e.coordinate] = 1;
      if (e.kind != ElementKind::kRotation || !e.function.IsIdentity())
        only_identity_rotation[e.coordinate] = 0;
    }
  for (const DerivedCoordinate& d : md.derived_coordinates())
    if (d.source >= 0) only_identity_rotation[d.source] = 0;
  for (int i = 0; i < nz; ++i) {
    const Coordinate& co = md.coordinates()[i];
    wraps[i] = drives[i] && only_identity_rotation[i] && co.rotational &&
               co.max_value - co.min_value >= 2 * M_PI - 1e-9;
  }
  marker_weight.resize(nm);
  for (int k = 0; k < nm; ++k)
    marker_weight[k] = md.markers()[k].weight / (options.sigma_m * options.sigma_m);

  // Root placement.
  const Joint& root = md.joints()[0];
  root_translations.clear();
  root_free.assign(nz, 0);
  int nrot = 0;
  bool euler = true, rotations_started = false;
  for (const JointElement& e : root.elements) {
    if (e.coordinate >= 0) root_free[e.coordinate] = 1;
    if (e.kind == ElementKind::kTranslation) {
      if (!rotations_started && e.coordinate >= 0 && e.function.IsIdentity())
        root_translations.emplace_back(e.coordinate, root.orientation * e.axis);
      continue;
    }
    rotations_started = true;
    if (nrot >= 3 || e.coordinate < 0 || !e.function.IsIdentity()) {
      euler = false;
      continue;
    }
    Eigen::Index k;
    const double largest = e.axis.cwiseAbs().maxCoeff(&k);
    if (std::abs(largest - 1.0) > 1e-12) euler = false;
    root_rot_coord[nrot] = e.coordinate;
    root_rot_axis[nrot] = static_cast<int>(k);
    root_rot_sign[nrot] = e.axis[k] > 0 ? 1.0 : -1.0;
    ++nrot;
  }
  root_euler = euler && nrot == 3 && root_rot_axis[0] != root_rot_axis[1] &&
               root_rot_axis[1] != root_rot_axis[2];
}

void Tracker::Impl::Allocate() {
  const int mp = options.max_points;
  valid.clear();
  valid.reserve(mp);
  points.resize(3, mp);
  zbuf.resize(nz);
  predicted.resize(3, nm);
  jac.resize(nm);
  for (int k = 0; k < nm; ++k) jac[k].resize(3, model->marker_coordinates(k).size());
  jp.resize(3, std::max(1, model->max_chain_coordinates()));
  s_inv.resize(nm);
  reject_sq.resize(nm);
  cost.resize(nm, mp + nm);
  row_to_col.resize(nm);
  lap.Reserve(nm, mp + nm);
  A.resize(nz, nz);
  b.resize(nz);
  update.Resize(nz);
  out.marker_of_point.reserve(mp);
  out.point_of_marker.reserve(nm);
  jerk_psd.resize(nz);
  for (int i = 0; i < nz; ++i)
    jerk_psd[i] = rotational[i] ? options.jerk_psd_rotational : options.jerk_psd_translational;
}

void Tracker::Impl::ResetState() {
  x = Eigen::VectorXd::Zero(3 * nz);
  P = Eigen::MatrixXd::Identity(3 * nz, 3 * nz);
  const Eigen::VectorXd start =
      options.static_pose.size() == nz ? options.static_pose : model->DefaultCoordinates();
  x.head(nz) = start;
  z_good = start;
  had_track = false;
  bad_frames = 0;
  last_time = kNaN;
  out.state = TrackState::kInitialising;
  out.z = start;
  out.labelled = 0;
  out.reinitialised = false;
  out.nis = 0;
  out.nis_dof = 0;
}

double Tracker::Impl::Dt(double time_s) const {
  const double nominal = 1.0 / options.rate_hz;
  if (!std::isfinite(last_time) || !std::isfinite(time_s)) return nominal;
  const double dt = time_s - last_time;
  return dt > 0 ? dt : nominal;
}

void Tracker::Impl::Predict(double dt) { PredictConstantAcceleration(dt, jerk_psd, &x, &P); }

// Marker predictions and Jacobians at z.
void Tracker::Impl::Linearise(const Eigen::VectorXd& z) {
  ForwardKinematics(*model, geometry, z, &data);
  for (int m = 0; m < nm; ++m) {
    predicted.col(m) = MarkerPosition(*model, geometry, data, m);
    MarkerJacobian(*model, geometry, data, m, &jac[m], static_cast<Eigen::Matrix3Xd*>(nullptr));
  }
}

// Mahalanobis gating with S_m = J_m P_zz J_m^T + R_m and the optimal assignment.
void Tracker::Impl::LabelByGating(int np) {
  const double gate = options.gate_chi2;
  for (int m = 0; m < nm; ++m) {
    const std::vector<int>& cols = model->marker_coordinates(m);
    const int k = static_cast<int>(cols.size());
    const auto& J = jac[m];
    auto JP = jp.leftCols(k);
    for (int bcol = 0; bcol < k; ++bcol) {
      JP.col(bcol).setZero();
      for (int a = 0; a < k; ++a) JP.col(bcol) += J.col(a) * P(cols[a], cols[bcol]);
    }
    Eigen::Matrix3d S = JP * J.transpose();
    S.diagonal().array() += 1.0 / marker_weight[m];
    s_inv[m] = S.inverse();
    // d^2 >= |e|^2 / lambda_max(S) >= |e|^2 / trace(S): a cheap test before the quadratic form.
    reject_sq[m] = gate * S.trace();
  }
  auto C = cost.topLeftCorner(nm, np + nm);
  for (int m = 0; m < nm; ++m) {
    const Eigen::Vector3d p = predicted.col(m);
    for (int k = 0; k < np; ++k) {
      const Eigen::Vector3d e = points.col(k) - p;
      double d2 = kForbidden;
      if (e.squaredNorm() < reject_sq[m]) {
        const double q = e.dot(s_inv[m] * e);
        if (q < gate) d2 = q;
      }
      C(m, k) = d2;
    }
    C.row(m).tail(nm).setConstant(kForbidden);
    C(m, np + m) = gate;
  }
  lap.Solve(C, row_to_col.data());
}

// Turns row_to_col (columns < np are points) into the output labels; returns the count.
int Tracker::Impl::ApplyLabels(int np) {
  int labelled = 0;
  for (int m = 0; m < nm; ++m) {
    const int col = row_to_col[m];
    if (col < 0 || col >= np) {
      row_to_col[m] = -1;
      continue;
    }
    const int input = valid[col];
    out.point_of_marker[m] = input;
    out.marker_of_point[input] = m;
    ++labelled;
  }
  out.labelled = labelled;
  return labelled;
}

// The information-form update of tracker.h with the labelled markers of row_to_col (Linearise
// already called at the predicted z).
bool Tracker::Impl::FilterUpdate(double* nis) {
  A.setZero();
  b.setZero();
  double nu_r_nu = 0;
  for (int m = 0; m < nm; ++m) {
    if (row_to_col[m] < 0) continue;
    const double w = marker_weight[m];
    const Eigen::Vector3d nu = points.col(row_to_col[m]) - predicted.col(m);
    nu_r_nu += w * nu.squaredNorm();
    const std::vector<int>& cols = model->marker_coordinates(m);
    const auto& J = jac[m];
    for (size_t a = 0; a < cols.size(); ++a) {
      b[cols[a]] += w * J.col(a).dot(nu);
      for (size_t k = 0; k <= a; ++k) A(cols[a], cols[k]) += w * J.col(a).dot(J.col(k));
    }
  }
  A.triangularView<Eigen::StrictlyUpper>() = A.transpose();
  return update.Apply(A, b, nu_r_nu, &x, &P, nis);
}

void Tracker::Impl::Wrap(Eigen::VectorXd* z) const {
  for (int i = 0; i < nz; ++i)
    if (wraps[i]) (*z)[i] = std::remainder((*z)[i], 2 * M_PI);
}

// ---------------------------------------------------------------------------------------------
// Initialisation

// z = start with the root turned by `turn` (world, about the root's origin) and shifted so that
// the model's marker centroid lands on `centroid`.
bool Tracker::Impl::PlaceRoot(const Eigen::VectorXd& start, const Eigen::Matrix3d& turn,
                              const Eigen::Vector3d& centroid, Eigen::VectorXd* z) {
  *z = start;
  const Joint& root = model->joints()[0];
  if (!turn.isIdentity(1e-12)) {
    if (!root_euler) return false;
    ForwardKinematics(*model, geometry, *z, &data);
    const Eigen::Matrix3d target = turn * data.segment_rotation[root.child];
    // The root's rotation elements compose root.orientation * R(a0) R(a1) R(a2); earlier
    // translations do not rotate.
    const Eigen::Vector3d angles = (root.orientation.transpose() * target)
                                       .eulerAngles(root_rot_axis[0], root_rot_axis[1],
                                                    root_rot_axis[2]);
    for (int i = 0; i < 3; ++i) (*z)[root_rot_coord[i]] = root_rot_sign[i] * angles[i];
  }
  ForwardKinematics(*model, geometry, *z, &data);
  Eigen::Vector3d mc = Eigen::Vector3d::Zero();
  for (int m = 0; m < nm; ++m) mc += MarkerPosition(*model, geometry, data, m);
  const Eigen::Vector3d shift = centroid - mc / nm;
  for (const auto& [coord, axis] : root_translations) (*z)[coord] += axis.dot(shift);
  return true;
}

// ICP-like search from z: assign markers to points by distance (optimal assignment with a
// shrinking radius), one damped Gauss-Newton step on the pose (first the root alone), reassign.
Tracker::Impl::Hypothesis Tracker::Impl::Icp(Eigen::VectorXd z, int np) {
  const Eigen::VectorXd start = z;
  const int iters = options.init_iterations;
  const int root_only = iters / 3;
  // Weak prior towards the start (metres^2 per rad^2 / per m^2): pins what the markers leave free.
  constexpr double kPriorRot = 0.01 * 0.01 / (0.5 * 0.5), kPriorTrans = 0.01 * 0.01 / (1.0 * 1.0);
  Eigen::MatrixXd N(nz, nz), Nd(nz, nz);
  Eigen::VectorXd g(nz), step(nz), trial(nz);
  Eigen::LLT<Eigen::MatrixXd> llt(nz);
  std::vector<int> assign(nm, -1), previous(nm, -2);
  auto Cost = [&](const Eigen::VectorXd& zz, const std::vector<char>* free) {
    ForwardKinematics(*model, geometry, zz, &data);
    double s = 0;
    for (int m = 0; m < nm; ++m)
      if (assign[m] >= 0)
        s += (MarkerPosition(*model, geometry, data, m) - points.col(assign[m])).squaredNorm();
    for (int i = 0; i < nz; ++i)
      if (!free || (*free)[i])
        s += (rotational[i] ? kPriorRot : kPriorTrans) * (zz[i] - start[i]) * (zz[i] - start[i]);
    return s;
  };
  double radius = 0.25;
  double lambda = 1e-3;
  for (int it = 0; it < iters; ++it) {
    const bool root_stage = it < root_only;
    radius = root_stage ? 0.25 : std::max(0.04, 0.12 - 0.02 * (it - root_only));
    Linearise(z);
    auto C = cost.topLeftCorner(nm, np + nm);
    const double r2 = radius * radius;
    for (int m = 0; m < nm; ++m) {
      for (int k = 0; k < np; ++k) {
        const double d2 = (points.col(k) - predicted.col(m)).squaredNorm();
        C(m, k) = d2 < r2 ? d2 : kForbidden;
      }
      C.row(m).tail(nm).setConstant(kForbidden);
      C(m, np + m) = r2;
    }
    lap.Solve(C, row_to_col.data());
    for (int m = 0; m < nm; ++m) assign[m] = row_to_col[m] < np ? row_to_col[m] : -1;
    const bool same = assign == previous;
    previous = assign;

    // Normal equations of the assigned markers + prior.
    const std::vector<char>* free = root_stage ? &root_free : nullptr;
    N.setZero();
    g.setZero();
    for (int m = 0; m < nm; ++m) {
      if (assign[m] < 0) continue;
      const Eigen::Vector3d r = predicted.col(m) - points.col(assign[m]);
      const std::vector<int>& cols = model->marker_coordinates(m);
      const auto& J = jac[m];
      for (size_t a = 0; a < cols.size(); ++a) {
        g[cols[a]] += J.col(a).dot(r);
        for (size_t k = 0; k < cols.size(); ++k) N(cols[a], cols[k]) += J.col(a).dot(J.col(k));
      }
    }
    for (int i = 0; i < nz; ++i) {
      const double w = rotational[i] ? kPriorRot : kPriorTrans;
      N(i, i) += w;
      g[i] += w * (z[i] - start[i]);
      if (free && !(*free)[i]) {
        N.row(i).setZero();
        N.col(i).setZero();
        N(i, i) = 1;
        g[i] = 0;
      }
    }
    const double c0 = Cost(z, free);
    bool accepted = false;
    for (int tries = 0; tries < 6 && !accepted; ++tries) {
      Nd = N;
      Nd.diagonal() += lambda * N.diagonal();
      llt.compute(Nd);
      if (llt.info() != Eigen::Success) {
        lambda *= 10;
        continue;
      }
      step = -llt.solve(g);
      trial = z + step;
      if (Cost(trial, free) < c0) {
        z = trial;
        lambda = std::max(1e-7, lambda * 0.3);
        accepted = true;
      } else {
        lambda *= 10;
      }
    }
    if (!root_stage && same && (!accepted || step.norm() < 1e-6) && radius <= 0.04) break;
  }
  // Final assignment at the final pose and its score.
  Hypothesis h;
  Linearise(z);
  const double r2 = radius * radius;
  auto C = cost.topLeftCorner(nm, np + nm);
  for (int m = 0; m < nm; ++m) {
    for (int k = 0; k < np; ++k) {
      const double d2 = (points.col(k) - predicted.col(m)).squaredNorm();
      C(m, k) = d2 < r2 ? d2 : kForbidden;
    }
    C.row(m).tail(nm).setConstant(kForbidden);
    C(m, np + m) = r2;
  }
  h.score = lap.Solve(C, row_to_col.data());
  h.assignment.assign(nm, -1);
  double sum = 0;
  for (int m = 0; m < nm; ++m)
    if (row_to_col[m] < np) {
      h.assignment[m] = row_to_col[m];
      sum += C(m, row_to_col[m]);
      ++h.labelled;
    }
  h.rms = h.labelled > 0 ? std::sqrt(sum / h.labelled) : std::numeric_limits<double>::infinity();
  Wrap(&z);
  h.z = z;
  return h;
}

bool Tracker::Impl::TryInitialise(int np) {
  if (np < options.init_min_fraction * nm) return false;
  const Eigen::Vector3d centroid = points.leftCols(np).rowwise().mean();
  std::vector<Eigen::VectorXd> starts;
  starts.push_back(options.static_pose.size() == nz ? options.static_pose
                                                    : model->DefaultCoordinates());
  if (had_track) starts.push_back(z_good);
  const Eigen::Vector3d up = options.up.normalized();
  std::vector<Hypothesis> hyps;
  for (const Eigen::VectorXd& s : starts) {
    const int headings = root_euler ? options.init_headings : 1;
    for (int k = 0; k < headings; ++k) {
      const Eigen::Matrix3d turn =
          Eigen::AngleAxisd(2 * M_PI * k / headings, up).toRotationMatrix();
      Eigen::VectorXd z;
      if (!PlaceRoot(s, turn, centroid, &z)) continue;
      hyps.push_back(Icp(z, np));
    }
  }
  if (hyps.empty()) return false;
  int best = 0;
  for (size_t i = 1; i < hyps.size(); ++i)
    if (hyps[i].score < hyps[best].score) best = static_cast<int>(i);
  const Hypothesis& h = hyps[best];
  if (h.labelled < options.init_min_fraction * nm || !(h.rms <= options.init_max_rms_m))
    return false;
  // Unambiguous: no hypothesis that labels >= 3 markers differently comes close.
  for (const Hypothesis& o : hyps) {
    int differ = 0;
    for (int m = 0; m < nm; ++m) differ += o.assignment[m] != h.assignment[m];
    if (differ >= 3 && o.score < options.init_ambiguity_ratio * h.score) return false;
  }

  // Start the filter at the found pose, at rest, and update it with the found labels.
  x.setZero();
  x.head(nz) = h.z;
  P.setZero();
  for (int i = 0; i < nz; ++i) {
    const bool r = rotational[i];
    const double s0 = r ? options.init_sigma_rotational : options.init_sigma_translational;
    const double s1 =
        r ? options.init_sigma_velocity_rotational : options.init_sigma_velocity_translational;
    const double s2 = r ? options.init_sigma_acceleration_rotational
                        : options.init_sigma_acceleration_translational;
    P(i, i) = s0 * s0;
    P(nz + i, nz + i) = s1 * s1;
    P(2 * nz + i, 2 * nz + i) = s2 * s2;
  }
  zbuf = x.head(nz);
  Linearise(zbuf);
  for (int m = 0; m < nm; ++m) row_to_col[m] = h.assignment[m];
  ApplyLabels(np);
  double nis = 0;
  if (!FilterUpdate(&nis)) return false;
  zbuf = x.head(nz);
  Wrap(&zbuf);
  x.head(nz) = zbuf;
  out.nis = nis;
  out.nis_dof = 3 * out.labelled;
  return true;
}

// ---------------------------------------------------------------------------------------------

Tracker::Tracker(std::shared_ptr<const Model> model, TrackerOptions options) : impl_(new Impl) {
  impl_->options = std::move(options);
  impl_->SetModel(std::move(model));
  impl_->Allocate();
  impl_->ResetState();
}

Tracker::~Tracker() = default;

const TrackOutput& Tracker::Update(double time_s, const Eigen::Ref<const Eigen::Matrix3Xd>& pts) {
  Impl& s = *impl_;
  TrackOutput& out = s.out;
  const int nin = static_cast<int>(pts.cols());
  out.marker_of_point.assign(nin, -1);
  out.point_of_marker.assign(s.nm, -1);
  out.labelled = 0;
  out.reinitialised = false;
  out.nis = 0;
  out.nis_dof = 0;
  s.valid.clear();
  for (int k = 0; k < nin && static_cast<int>(s.valid.size()) < s.options.max_points; ++k)
    if (pts.col(k).allFinite()) {
      s.points.col(s.valid.size()) = pts.col(k);
      s.valid.push_back(k);
    }
  const int np = static_cast<int>(s.valid.size());
  const double dt = s.Dt(time_s);
  s.last_time = time_s;

  if (out.state == TrackState::kTracking) {
    s.Predict(dt);
    s.zbuf = s.x.head(s.nz);
    s.Linearise(s.zbuf);
    s.LabelByGating(np);
    const int labelled = s.ApplyLabels(np);
    double nis = 0;
    bool ok = labelled == 0 || s.FilterUpdate(&nis);
    if (ok) {
      s.zbuf = s.x.head(s.nz);
      s.Wrap(&s.zbuf);
      s.x.head(s.nz) = s.zbuf;
      ok = s.x.allFinite();
    }
    out.nis = nis;
    out.nis_dof = 3 * labelled;
    const bool bad = !ok || labelled < s.options.min_labelled_fraction * s.nm ||
                     (labelled > 0 && nis > s.options.max_nis_per_dof * out.nis_dof);
    if (ok && !bad) {
      s.bad_frames = 0;
      s.z_good = s.x.head(s.nz);
    } else if (++s.bad_frames >= s.options.divergence_frames || !ok) {
      out.state = TrackState::kLost;
    }
  }
  if (out.state != TrackState::kTracking) {
    std::fill(out.marker_of_point.begin(), out.marker_of_point.end(), -1);
    std::fill(out.point_of_marker.begin(), out.point_of_marker.end(), -1);
    out.labelled = 0;
    if (s.TryInitialise(np)) {
      out.state = TrackState::kTracking;
      out.reinitialised = true;
      s.had_track = true;
      s.bad_frames = 0;
      s.z_good = s.x.head(s.nz);
    } else {
      std::fill(out.marker_of_point.begin(), out.marker_of_point.end(), -1);
      std::fill(out.point_of_marker.begin(), out.point_of_marker.end(), -1);
      out.labelled = 0;
      out.nis = 0;
      out.nis_dof = 0;
    }
  }
  if (out.state == TrackState::kTracking)
    out.z = s.x.head(s.nz);
  else
    out.z = s.z_good;
  return out;
}

Status Tracker::SwapModel(std::shared_ptr<const Model> model) {
  if (!model) return Status::Error("SwapModel: no model");
  Impl& s = *impl_;
  const Model& old = *s.model;
  if (model->num_coordinates() != old.num_coordinates())
    return Status::Error("SwapModel: the new model has " +
                         std::to_string(model->num_coordinates()) + " coordinates, the tracker " +
                         std::to_string(old.num_coordinates()));
  if (model->num_markers() != old.num_markers())
    return Status::Error("SwapModel: the new model has " + std::to_string(model->num_markers()) +
                         " markers, the tracker " + std::to_string(old.num_markers()));
  for (int i = 0; i < old.num_coordinates(); ++i)
    if (model->coordinates()[i].name != old.coordinates()[i].name)
      return Status::Error("SwapModel: coordinate " + std::to_string(i) + " is '" +
                           model->coordinates()[i].name + "', the tracker's is '" +
                           old.coordinates()[i].name + "'");
  for (int i = 0; i < old.num_markers(); ++i)
    if (model->markers()[i].name != old.markers()[i].name)
      return Status::Error("SwapModel: marker " + std::to_string(i) + " is '" +
                           model->markers()[i].name + "', the tracker's is '" +
                           old.markers()[i].name + "'");
  s.SetModel(std::move(model));
  s.Allocate();
  for (int i = 0; i < s.nz; ++i)
    s.P(i, i) += s.rotational[i] ? s.options.swap_inflation_rotational
                                 : s.options.swap_inflation_translational;
  return Status::Ok();
}

TrackState Tracker::state() const { return impl_->out.state; }
void Tracker::Reset() { impl_->ResetState(); }
const Model& Tracker::model() const { return *impl_->model; }
const TrackerOptions& Tracker::options() const { return impl_->options; }
const TrackOutput& Tracker::output() const { return impl_->out; }
const Eigen::MatrixXd& Tracker::covariance() const { return impl_->P; }
Eigen::VectorXd Tracker::velocities() const { return impl_->x.segment(impl_->nz, impl_->nz); }
Eigen::VectorXd Tracker::accelerations() const { return impl_->x.tail(impl_->nz); }

}  // namespace mocap::ekf
