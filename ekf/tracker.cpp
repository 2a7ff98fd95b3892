// The tracker's filter and the sequence of one frame (ekf/tracker.h has the whole design): the
// model-dependent set-up (wrapped coordinates, limbs, root placement), the constant-acceleration
// prediction, the marker predictions and Jacobians, the information-form update with the labels
// the labelling chose (ekf/tracker_labelling.cpp), the online marker offsets, the divergence test,
// and SwapModel. What it decides: the pose and its covariance given the labels, and when the track
// is lost. Which point is which marker is decided in tracker_labelling.cpp; finding the subject
// with no labels, and a limb again, in tracker_initialisation.cpp.
#include "ekf/tracker.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>

#include "ekf/tracker_impl.h"

namespace mocap::ekf {

using namespace internal;

namespace {
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
  if (!(velocity_time_constant_s > 0) || !(acceleration_time_constant_s > 0))
    return Fail(error, "velocity_time_constant_s and acceleration_time_constant_s must be > 0");
  if (!(gate_chi2 > 0)) return Fail(error, "gate_chi2 must be > 0");
  if (!(process_noise_time_constant_s >= 0))
    return Fail(error, "process_noise_time_constant_s must be >= 0");
  if (!(min_process_noise_scale > 0 && min_process_noise_scale <= 1))
    return Fail(error, "min_process_noise_scale must be in (0, 1]");
  if (!(min_return_probability >= 0 && min_return_probability < 1))
    return Fail(error, "min_return_probability must be in [0, 1)");
  if (!(clutter_time_constant_s > 0)) return Fail(error, "clutter_time_constant_s must be > 0");
  if (!(marker_offset_sigma >= 0) || !(marker_offset_floor >= 0))
    return Fail(error, "marker_offset_sigma and marker_offset_floor must be >= 0");
  if (!(marker_offset_time_constant_s > 0))
    return Fail(error, "marker_offset_time_constant_s must be > 0");
  if (swap_offset_count < 0) return Fail(error, "swap_offset_count must be >= 0");
  if (!(marker_offset_prior_frames >= 0))
    return Fail(error, "marker_offset_prior_frames must be >= 0");
  if (max_points < 1) return Fail(error, "max_points must be >= 1");
  if (divergence_frames < 1) return Fail(error, "divergence_frames must be >= 1");
  if (!(min_labelled_fraction >= 0 && min_labelled_fraction <= 1))
    return Fail(error, "min_labelled_fraction must be in [0, 1]");
  if (!(max_nis_per_dof > 0)) return Fail(error, "max_nis_per_dof must be > 0");
  if (!(up.norm() > 0.5) || !up.allFinite()) return Fail(error, "up must be a non-zero vector");
  if (!(model_up.norm() > 0.5) || !model_up.allFinite())
    return Fail(error, "model_up must be a non-zero vector");
  if (init_headings < 1) return Fail(error, "init_headings must be >= 1");
  if (init_variants < 0 || !(init_variant_rad >= 0))
    return Fail(error, "init_variants and init_variant_rad must be >= 0");
  if (init_iterations < 3) return Fail(error, "init_iterations must be >= 3");
  if (!(init_max_rms_m > 0)) return Fail(error, "init_max_rms_m must be > 0");
  if (!(init_min_fraction > 0 && init_min_fraction <= 1))
    return Fail(error, "init_min_fraction must be in (0, 1]");
  if (!(init_ambiguity_ratio >= 1)) return Fail(error, "init_ambiguity_ratio must be >= 1");
  if (!(init_ambiguity_margin >= 0)) return Fail(error, "init_ambiguity_margin must be >= 0");
  if (!(init_radius_m > 0)) return Fail(error, "init_radius_m must be > 0");
  if (!(init_scale_sigma > 0)) return Fail(error, "init_scale_sigma must be > 0");
  if (!(init_scale_after_s >= 0)) return Fail(error, "init_scale_after_s must be >= 0");
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

bool ParseScaleToSubject(const std::string& name, TrackerOptions::ScaleToSubject* mode) {
  using Scale = TrackerOptions::ScaleToSubject;
  if (name == "never") *mode = Scale::kNever;
  else if (name == "when-needed") *mode = Scale::kWhenTheModelDoesNotFit;
  else if (name == "always") *mode = Scale::kAlways;
  else return false;
  return true;
}

void Tracker::Impl::SetModel(std::shared_ptr<const Model> m) {
  model = std::move(m);
  const Model& md = *model;
  nz = md.num_coordinates();
  nm = md.num_markers();
  geometry = Geometry(md);
  geometry_params = md.InitialParameters();
  data = ModelData(md);
  hidden_data = ModelData(md);
  rotational.assign(nz, 0);
  range_information.assign(nz, 0.0);
  wraps.assign(nz, 0);
  for (int i = 0; i < nz; ++i) {
    const Coordinate& co = md.coordinates()[i];
    rotational[i] = co.rotational;
    // A uniform distribution over the range: its variance width^2 / 12 (none for a coordinate
    // without a finite range).
    const double width = co.max_value - co.min_value;
    if (co.min_value > -1e8 && co.max_value < 1e8 && width > 0)
      range_information[i] = 12.0 / (width * width);
  }
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
  marker_variance.resize(nm);
  for (int k = 0; k < nm; ++k)
    marker_variance[k] = options.sigma_m * options.sigma_m / md.markers()[k].weight;
  seen.assign(nm, 1);
  for (int k = 0; k < nm; ++k)
    for (const std::string& name : options.unseen_markers)
      if (md.markers()[k].name == name) seen[k] = 0;
  // Markers the model cannot place (tracker.h, "Initialisation and recovery": stacked on one
  // point of their segment) are treated as unseen.
  const std::vector<char> stacked = StackedOnOnePoint(md, seen, kStackedTolerance);
  for (int k = 0; k < nm; ++k)
    if (stacked[k]) seen[k] = 0;
  nm_seen = static_cast<int>(std::count(seen.begin(), seen.end(), 1));
  offset.assign(nm, Eigen::Vector3d::Zero());
  offset_unknown.assign(nm, 1.0);
  offset_sigma.assign(nm, options.marker_offset_sigma);
  model_error.assign(nm, 0.0);

  // Depths (joints are parents first).
  segment_depth.assign(md.num_segments(), 0);
  max_depth = 0;
  for (const Joint& j : md.joints()) {
    const int d = j.parent < 0 ? 0 : segment_depth[j.parent] + 1;
    segment_depth[j.child] = d;
    max_depth = std::max(max_depth, d);
  }
  coordinate_depth.assign(nz, 0);
  for (int i = 0; i < nz; ++i) {
    const int j = md.coordinates()[i].joint;
    coordinate_depth[i] = j >= 0 ? segment_depth[md.joints()[j].child] : 0;
  }
  marker_depth.resize(nm);
  for (int k = 0; k < nm; ++k) marker_depth[k] = segment_depth[md.markers()[k].segment];

  // Segments' seen markers, segments with any in depth order (parents first).
  segment_markers.assign(md.num_segments(), {});
  for (int k = 0; k < nm; ++k)
    if (seen[k]) segment_markers[md.markers()[k].segment].push_back(k);
  segment_order.clear();
  for (int d = 0; d <= max_depth; ++d)
    for (int sgm = 0; sgm < md.num_segments(); ++sgm)
      if (!segment_markers[sgm].empty() && segment_depth[sgm] == d) segment_order.push_back(sgm);

  // Limbs: each joint's subtree (joints are parents first, so a joint's descendants follow it).
  const int nj = static_cast<int>(md.joints().size());
  limb_coord.assign(nj, std::vector<char>(nz, 0));
  limb_markers.assign(nj, {});
  {
    std::vector<char> in(md.num_segments(), 0);
    for (int j = 0; j < nj; ++j) {
      std::fill(in.begin(), in.end(), 0);
      in[md.joints()[j].child] = 1;
      for (int i = j + 1; i < nj; ++i) {
        const Joint& ji = md.joints()[i];
        if (ji.parent >= 0 && in[ji.parent]) in[ji.child] = 1;
      }
      for (int i = j; i < nj; ++i)
        if (in[md.joints()[i].child])
          for (const JointElement& e : md.joints()[i].elements)
            if (e.coordinate >= 0) limb_coord[j][e.coordinate] = 1;
      for (int k = 0; k < nm; ++k)
        if (in[md.markers()[k].segment] && seen[k]) limb_markers[j].push_back(k);
    }
  }
  limb_coord_list.assign(nj, {});
  for (int j = 0; j < nj; ++j)
    for (int i = 0; i < nz; ++i)
      if (limb_coord[j][i]) limb_coord_list[j].push_back(i);
  limb_joint_list.assign(nj, {});
  {
    std::vector<char> moved(md.num_segments(), 0);
    for (int j = 0; j < nj; ++j) {
      std::fill(moved.begin(), moved.end(), 0);
      for (int i = 0; i < nj; ++i) {
        const Joint& ji = md.joints()[i];
        bool moves = i == j || (ji.parent >= 0 && moved[ji.parent]);
        for (const JointElement& e : ji.elements) moves |= e.coordinate >= 0 && limb_coord[j][e.coordinate];
        if (!moves) continue;
        moved[ji.child] = 1;
        limb_joint_list[j].push_back(i);
      }
    }
  }
  marker_limb.assign(nm, -1);
  for (int k = 0; k < nm; ++k) {
    int j = md.segments()[md.markers()[k].segment].joint;
    // Up to the first joint that moves something (a welded segment rides on its parent's) and
    // carries another marker: the limb's labelled markers hold the search (a hand with its one
    // finger marker is searched with the forearm's).
    while (j > 0) {
      bool moves = false;
      for (char c : limb_coord[j]) moves |= c != 0;
      if (moves && limb_markers[j].size() >= 2) break;
      const int parent = md.joints()[j].parent;
      j = parent >= 0 ? md.segments()[parent].joint : -1;
    }
    // The root is the global search's business, and so are subtrees too large for a local one.
    marker_limb[k] = seen[k] && j > 0 && static_cast<int>(limb_coord_list[j].size()) <= kMaxLimbCoords
                         ? j
                         : -1;
  }

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
  // SegmentFitCost's whole-fit gate per degrees of freedom (3 x up to 16 anchors - 6), not
  // computed in the frame's loop.
  segment_fit_chi2.assign(3 * 16 + 1, 0.0);
  for (int dof = 1; dof < static_cast<int>(segment_fit_chi2.size()); ++dof)
    segment_fit_chi2[dof] = ChiSquareAtGateTail(options.gate_chi2, dof);
  const int mp = options.max_points;
  valid.clear();
  valid.reserve(mp);
  points.resize(3, mp);
  zbuf.resize(nz);
  x_prior.resize(3 * nz);
  dz.resize(nz);
  predicted.resize(3, nm);
  jac.resize(nm);
  for (int k = 0; k < nm; ++k) jac[k].resize(3, model->marker_coordinates(k).size());
  jp.resize(3, std::max(1, model->max_chain_coordinates()));
  s_inv.resize(nm);
  s_inv_hidden.resize(nm);
  hidden_gated.assign(nm, 0);
  reject_sq.resize(nm);
  gated_by.resize(mp);
  cost.resize(nm, mp + nm);
  row_to_col.resize(nm);
  assigned.resize(nm);
  lap.Reserve(nm, mp + nm);
  A.resize(nz, nz);
  b.resize(nz);
  update.Resize(nz);
  out.marker_of_point.reserve(mp);
  out.point_of_marker.reserve(nm);
  unlabelled_run.assign(nm, 0);
  stuck_run.assign(nm, 0);
  measured.assign(nm, 0);
  moved_buf.assign(nm, 0.0);
  beyond_gate.assign(nm, 0);
  relabelled.assign(nm, 0);
  observed.assign(nz, 1);
  unobserved_frames.assign(nz, 0);
  labelled_run.assign(nm, 0);
  rival_last = Eigen::Matrix3Xd::Zero(3, nm);
  rival_frames.assign(nm, 0);
  own_residual.assign(nm, 0.0);
  rival_residual.assign(nm, 0.0);
  claimed_now.assign(mp, 0);
  committed_rel = window_rel = Eigen::Matrix3Xd::Zero(3, nm);
  has_committed_rel.assign(nm, 0);
  has_window_rel.assign(nm, 0);
  own_prior.assign(nm, 0.0);
  rival_prior.assign(nm, 0.0);
  hist_points.assign(kHistory, Eigen::Matrix3Xd::Zero(3, mp));
  hist_count.assign(kHistory, 0);
  hist_claimed.assign(kHistory, std::vector<char>(mp, 0));
  hist_marker_point.assign(kHistory, std::vector<int>(nm, -1));
  hist_centre.assign(kHistory,
                     std::vector<Eigen::Vector3d>(model->num_segments(), Eigen::Vector3d::Zero()));
  centre_now.assign(model->num_segments(), Eigen::Vector3d::Zero());
  segment_loose.assign(model->num_segments(), 0);
  segment_fitted.assign(model->num_segments(), 0);
  segment_wants_fit.assign(model->num_segments(), 0);
  fit_rotation.assign(model->num_segments(), Eigen::Matrix3d::Identity());
  fit_translation.assign(model->num_segments(), Eigen::Vector3d::Zero());
  fit_precision.assign(model->num_segments(), FitPrecision());
  centre_predicted.assign(model->num_segments(), Eigen::Vector3d::Zero());
  centre_variance.assign(model->num_segments(), 0.0);
  hist_head = hist_size = 0;
  beside_prev.assign(static_cast<size_t>(mp) * nm, kNever);
  held_run.assign(nm, 0);
  deferral.assign(nm, Deferral());
  registered.assign(nm, 0);
  handoff_rivals.assign(nm, -1);
  doubted.assign(nm, {-1, -1});
  doubted_count = 0;
  beside_now.assign(static_cast<size_t>(mp) * nm, kNever);
  prev_points.setZero(3, mp);
  prev_free.assign(mp, 0);
  prev_free_list.assign(mp, 0);
  prev_np = prev_free_count = 0;
  pred_cache.assign(mp, -2);
  track_owner.assign(mp, -1);
  last_point.setZero(3, nm);
  last_predicted.setZero(3, nm);
  llocal.assign(nz, -1);
  lsaved.resize(3, nm);
  ltrial.resize(nz);
  lz.resize(nz);
  lstart.resize(nz);
  lbest.resize(nz);
  lz0.resize(nz);
  lcand.assign(mp, 0);
  lassign.assign(nm, -1);
  lbest_assign.assign(nm, -1);
  lrow_to_col.assign(nm, -1);
  lfree.assign(nm, -1);
  ltaken.assign(mp, 0);
  lunanchored.assign(nz, 0);
  lheld.assign(nm, -1);
  jerk_psd.resize(nz);
  for (int i = 0; i < nz; ++i)
    jerk_psd[i] = rotational[i] ? options.jerk_psd_rotational : options.jerk_psd_translational;
  q_scale.assign(nz, 1.0);
  jerk_psd_now = jerk_psd;
  prediction_trace.assign(nm, 0.0);
  q_innovation.setZero(nz);
  q_predicted.setZero(nz);
  q_weight.setZero(nz);
  q_count.setZero(nz);
  hidden_scale.assign(nm, 1.0);
  hidden_anchor.assign(nm, -1);
  hidden_own.assign(nm, {});
  for (int m = 0; m < nm; ++m) {
    std::vector<int> joints;
    int segment = model->markers()[m].segment;
    for (;;) {
      const int j = model->segments()[segment].joint;
      joints.push_back(j);
      const int parent = model->joints()[j].parent;
      if (parent < 0) break;
      bool has_seen = false;
      for (int a : segment_markers[parent]) has_seen |= seen[a] != 0;
      if (has_seen) {
        hidden_anchor[m] = parent;
        break;
      }
      segment = parent;
    }
    const std::vector<int>& cols = model->marker_coordinates(m);
    hidden_own[m].clear();
    for (size_t a = 0; a < cols.size(); ++a)
      if (std::find(joints.begin(), joints.end(), model->coordinates()[cols[a]].joint) !=
          joints.end())
        hidden_own[m].push_back(static_cast<int>(a));
  }
  // Only where a frame is short against the horizon: at lower rates (12.5 Hz) the learnt process
  // noise already sees the prediction in each frame's innovation.
  hidden_horizon_frames = static_cast<int>(std::lround(kHiddenHorizonSeconds * options.rate_hz));
  if (hidden_horizon_frames < kUnobservedFrames) hidden_horizon_frames = 0;
  const int slots = std::max(hidden_horizon_frames, 1);
  hidden_made.assign(slots, -1);
  hidden_point.assign(slots, Eigen::Matrix3Xd::Zero(3, nm));
  hidden_spread.assign(slots, Eigen::VectorXd::Zero(nm));
  hidden_z.setZero(nz);
  hidden_dt = 0;
  hidden_count = 0;
}

void Tracker::Impl::ResetState() {
  x = Eigen::VectorXd::Zero(3 * nz);
  P = Eigen::MatrixXd::Identity(3 * nz, 3 * nz);
  const Eigen::VectorXd start =
      options.static_pose.size() == nz ? options.static_pose : model->DefaultCoordinates();
  x.head(nz) = start;
  z_good = start;
  z_static = start;
  had_track = false;
  unfit_searches = 0;
  clutter_density = -1;
  lasting_clutter_density = -1;
  std::fill(q_scale.begin(), q_scale.end(), 1.0);
  std::fill(hidden_scale.begin(), hidden_scale.end(), 1.0);
  std::fill(hidden_made.begin(), hidden_made.end(), -1);
  jerk_psd_now = jerk_psd;
  // A new subject may come: the model at its own size again (ScaleToSubject).
  SetGeometry(model->InitialParameters());
  bad_frames = 0;
  last_time = kNaN;
  out.state = TrackState::kInitialising;
  init = InitialisationSummary();
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

void Tracker::Impl::Predict(double dt) {
  // P whole only in its coordinates' block, which the gates read, until the update (which reads
  // the lower triangle and writes P whole) or Update's mirror when there is none.
  PredictConstantAccelerationLower(dt, jerk_psd_now,
                                   std::exp(-dt / options.velocity_time_constant_s),
                                   std::exp(-dt / options.acceleration_time_constant_s), &x, &P);
  // A coordinate no measurement has observed for kUnobservedFrames frames stops within
  // kUnobservedSeconds: what it did before is no evidence of where it went (the knee of a leg
  // whose shank and foot markers are all hidden ran on its last velocity to the end of its range,
  // 40 cm from the markers when they came back). A shorter gap keeps the extrapolation that picks
  // a marker up again. Applied as F = diag(1, d, d) on that coordinate, so P stays F P F^T.
  const double d = std::exp(-dt / kUnobservedSeconds);
  for (int i = 0; i < nz; ++i) {
    unobserved_frames[i] = observed[i] ? 0 : unobserved_frames[i] + 1;
    if (unobserved_frames[i] < kUnobservedFrames) continue;
    for (int idx : {nz + i, 2 * nz + i}) {
      x[idx] *= d;
      P.row(idx) *= d;
      P.col(idx) *= d;
    }
  }
}

// Marker predictions and Jacobians at z.
void Tracker::Impl::Linearise(const Eigen::VectorXd& z) {
  ForwardKinematics(*model, geometry, z, &data);
  for (int m = 0; m < nm; ++m) {
    predicted.col(m) = MarkerPosition(*model, geometry, data, m) +
                       data.segment_rotation[model->markers()[m].segment] * offset[m];
    MarkerJacobian(*model, geometry, data, m, &jac[m], static_cast<Eigen::Matrix3Xd*>(nullptr));
  }
}

// The information-form update of tracker.h with the labelled markers of row_to_col (Linearise
// already called at the predicted z).
bool Tracker::Impl::FilterUpdate(double* nis, double dt) {
  A.setZero();
  b.setZero();
  std::fill(beyond_gate.begin(), beyond_gate.end(), 0);
  std::fill(observed.begin(), observed.end(), 0);
  double nu_r_nu = 0;
  // The start's update (dt 0) and a tracker told not to learn its process noise skip its sums.
  const bool learn_noise = dt > 0 && options.process_noise_time_constant_s > 0;
  if (learn_noise) {
    q_innovation.setZero();
    q_predicted.setZero();
    q_weight.setZero();
    q_count.setZero();
  }
  for (int m = 0; m < nm; ++m) {
    if (row_to_col[m] < 0) continue;
    const Eigen::Vector3d nu = points.col(row_to_col[m]) - predicted.col(m);
    // A label outside the marker's gate (a segment registration's: its point is where the
    // segment's rigid geometry puts it, not where the pose predicts it) is not measured: one
    // linearised step of decimetres threw whole legs off the body, and a step scaled down to the
    // gate still left the limb a velocity that ran on after the label was lost. Its limb is
    // placed anew by the limb search instead (Reacquire), at rest.
    beyond_gate[m] = nu.dot(s_inv[m] * nu) > options.gate_chi2;
    if (!measured[m] || beyond_gate[m]) continue;
    const double w = 1.0 / (MeasurementVariance(m) + model_error[m]);
    nu_r_nu += w * nu.squaredNorm();
    const std::vector<int>& cols = model->marker_coordinates(m);
    const auto& J = jac[m];
    if (learn_noise) {
      // Each marker's part in its coordinates' process noise (LearnProcessNoise): its squared
      // innovation against its predicted spread (with the measurement variance), weighted by how
      // far the prediction makes more than half of that spread (2 f - 1: where the measurement
      // noise makes the gate, at 200 Hz, the innovations say little about q), shared among its
      // chain's coordinates as they make its prediction's covariance. At 40 Hz and up
      // (LearnProcessNoise) against the prediction's part plus the learnt model error, and in
      // full beyond the whole spread.
      double share = 0;
      for (size_t a = 0; a < cols.size(); ++a) share += J.col(a).squaredNorm() * P(cols[a], cols[a]);
      const double spread = prediction_trace[m] + 3.0 / w;
      if (share > 0 && spread > 0) {
        const bool fast = HighRate();
        const double expected = fast ? prediction_trace[m] + 3.0 * model_error[m] : spread;
        const double f = fast && nu.squaredNorm() > spread
                             ? 1.0
                             : std::max(0.0, 2.0 * prediction_trace[m] / spread - 1.0);
        for (size_t a = 0; a < cols.size(); ++a) {
          const double c = J.col(a).squaredNorm() * P(cols[a], cols[a]) / share;
          q_innovation[cols[a]] += c * f * nu.squaredNorm();
          q_predicted[cols[a]] += c * f * expected;
          q_weight[cols[a]] += c * f;
          q_count[cols[a]] += c;
        }
      }
    }
    for (size_t a = 0; a < cols.size(); ++a) {
      b[cols[a]] += w * J.col(a).dot(nu);
      for (size_t k = 0; k <= a; ++k) A(cols[a], cols[k]) += w * J.col(a).dot(J.col(k));
    }
  }
  // Observed (see Predict): this frame's measurements alone pin the coordinate within
  // kObservedSigmas x its initialisation sigma. Being in a measured marker's chain is not enough:
  // a heel marker 5 mm from the subtalar axis, the foot's only marker while the toe is hidden, is
  // in that angle's chain but bounds it only to about 0.6 rad, and the angle ran on its velocity
  // with every heel residual until the toe came back 10-20 cm from its prediction (and the
  // heel's offset learnt the turned pose: 66 mm on seed 44).
  for (int i = 0; i < nz; ++i) {
    const double s = kObservedSigmas * (rotational[i] ? options.init_sigma_rotational
                                                      : options.init_sigma_translational);
    observed[i] = A(i, i) * s * s >= 1.0;
  }
  A.triangularView<Eigen::StrictlyUpper>() = A.transpose();
  if (HighRate()) x_prior = x;
  if (!update.Apply(A, b, nu_r_nu, &x, &P, nis)) return false;
  // A coordinate the measurements tell less than its range does stays where the prediction put it
  // (range_information; tracker.h, "Weakly observed coordinates").
  if (HighRate())
    for (int i = 0; i < nz; ++i)
      if (A(i, i) > 0 && A(i, i) < range_information[i])
        for (int idx : {i, nz + i, 2 * nz + i}) x[idx] = x_prior[idx];
  if (learn_noise) LearnProcessNoise(dt);
  if (dt > 0) LearnHiddenScale(dt);
  dz = x.head(nz) - zbuf;
  LearnOffsets(dz);
  if (dt > 0) ForecastHidden(dt);
  return true;
}

// A hidden marker's gate (tracker.h, "Hidden markers' gates"). Every update forecasts each
// marker kHiddenHorizonSeconds ahead as its prediction would run were it hidden from now on: the
// state carried open-loop, each coordinate stopping after kUnobservedFrames as Predict stops an
// unobserved one, judged in the frame of the nearest ancestor segment with markers (which stay
// in view and hold it while the marker is hidden), with the spread of that prediction over the
// coordinates below that segment (the posterior's part carried so, exactly, and the process
// noise's). LearnHiddenScale compares each measured marker's point with the forecast made for
// it a horizon ago.
void Tracker::Impl::ForecastHidden(double dt) {
  if (!HighRate()) return;
  const int N = hidden_horizon_frames;
  if (std::abs(dt - hidden_dt) > 1e-9 * dt) {
    const double beta = std::exp(-dt / options.velocity_time_constant_s);
    const double alpha = std::exp(-dt / options.acceleration_time_constant_s);
    const double d = std::exp(-dt / kUnobservedSeconds);
    const double h = 0.5 * dt * dt, d2 = dt * dt, d3 = d2 * dt, d4 = d3 * dt, d5 = d4 * dt;
    Eigen::Matrix3d F, Q, D = Eigen::Vector3d(1, d, d).asDiagonal();
    F << 1, dt, h, 0, beta, beta * dt, 0, 0, alpha;
    Q << d5 / 20, d4 / 8, d3 / 6, d4 / 8, d3 / 3, d2 / 2, d3 / 6, d2 / 2, dt;
    Eigen::Matrix3d phi = Eigen::Matrix3d::Identity(), sigma = Eigen::Matrix3d::Zero();
    for (int k = 1; k <= N; ++k) {
      phi = F * phi;
      sigma = F * sigma * F.transpose() + Q;
      if (k >= kUnobservedFrames) {
        phi = D * phi;
        sigma = D * sigma * D;
      }
    }
    hidden_phi = phi;
    hidden_unit_qvar = sigma(0, 0);
    hidden_dt = dt;
  }
  const int slot = hidden_count % N;
  hidden_made[slot] = hidden_count++;
  const Eigen::Matrix3d& f = hidden_phi;
  hidden_z = f(0, 0) * x.head(nz) + f(0, 1) * x.segment(nz, nz) + f(0, 2) * x.tail(nz);
  Wrap(&hidden_z);
  ForwardKinematics(*model, geometry, hidden_z, &hidden_data);
  // The forecast's covariance of coordinates i and j: (F^N P F^N^T)(i, j), from the nine blocks.
  auto carried = [&](int i, int j) {
    double c = 0;
    for (int k = 0; k < 3; ++k)
      for (int l = 0; l < 3; ++l) c += f(0, k) * f(0, l) * P(k * nz + i, l * nz + j);
    return c;
  };
  for (int m = 0; m < nm; ++m) {
    const int anchor = hidden_anchor[m];
    if (anchor < 0) continue;
    hidden_point[slot].col(m) =
        hidden_data.segment_rotation[anchor].transpose() *
        (MarkerPosition(*model, geometry, hidden_data, m) +
         hidden_data.segment_rotation[model->markers()[m].segment] * offset[m] -
         hidden_data.segment_position[anchor]);
    const std::vector<int>& cols = model->marker_coordinates(m);
    const auto& J = jac[m];
    double t = 0;
    for (int a : hidden_own[m]) {
      t += J.col(a).squaredNorm() * jerk_psd_now[cols[a]] * hidden_unit_qvar;
      for (int b : hidden_own[m]) t += J.col(a).dot(J.col(b)) * carried(cols[a], cols[b]);
    }
    hidden_spread[slot][m] = std::max(t, 0.0);
  }
}

// Covariance matching (Mehra 1972) on the forecasts' spread: per marker, |e|^2 (less its learnt
// model error: the measurement variance bounds the noise from above, and taken off it left a
// still hand's factor at a tenth of what its forecasts showed) over the spread, capped at 1
// (never wider than the filter's own), averaged over kHiddenScaleSeconds with LearnProcessNoise's
// weight 2 f - 1 for the forecast's share f of the spread -- and in full where the error passes
// the whole spread, so that a factor learnt while a limb stood still rises as soon as it moves --
// and floored at kMinHiddenScale.
void Tracker::Impl::LearnHiddenScale(double dt) {
  if (!HighRate()) return;
  const int N = hidden_horizon_frames;
  const int slot = hidden_count % N;
  if (hidden_made[slot] != hidden_count - N) return;
  const double gain = std::min(1.0, dt / kHiddenScaleSeconds);
  for (int m = 0; m < nm; ++m) {
    const int anchor = hidden_anchor[m];
    if (anchor < 0 || row_to_col[m] < 0 || !measured[m] || beyond_gate[m]) continue;
    const double pred = hidden_spread[slot][m];
    if (!(pred > 0)) continue;
    const double noise = 3.0 * (MeasurementVariance(m) + model_error[m]);
    const double e2 = (data.segment_rotation[anchor].transpose() *
                           (points.col(row_to_col[m]) - data.segment_position[anchor]) -
                       hidden_point[slot].col(m))
                          .squaredNorm();
    const double target = std::min(1.0, std::max(0.0, e2 - 3.0 * model_error[m]) / pred);
    const double weight =
        e2 > pred + noise ? 1.0 : std::max(0.0, 2.0 * pred / (pred + noise) - 1.0);
    hidden_scale[m] = std::clamp(hidden_scale[m] + gain * weight * (target - hidden_scale[m]),
                                 kMinHiddenScale, 1.0);
  }
}

// Covariance matching (tracker.h, "Process noise"; Mehra 1972): with the labels right, a
// measured marker's squared innovation is, on average, its predicted spread (J P_zz J^T plus its
// measurement variance). FilterUpdate shares each marker's among its chain's coordinates, weighted
// by how much of the spread the prediction makes; each coordinate's factor on the bound moves by
// (ratio - 1) times that weight over the time constant (an arithmetic average: a burst of fast
// motion counts at its size), the ratio capped at kMaxRatio, the factor kept within
// [min_process_noise_scale, 1]. Wrong labels and ghosts make the innovations larger, which only
// moves the factor back towards the bound.
// What is matched, and why it differs at 40 Hz and up: the measurement variance is an upper
// bound (it holds the model's error), so against a spread made with it the innovations are
// smaller than it says at any q -- the estimate is biased low by the bound's slack -- and where
// the measurement makes half the spread or more (40-100 Hz) they pulled a quiet limb's factors to
// the floor over a quiet minute, while the innovations that said the motion had started were
// weighed near 0 (the scene at 50 Hz: a hand lost for 10-160 frames in the wrist
// circles, wrist pairs crossed for 14-24 frames on half the seeds). There each innovation is
// matched against the prediction's part plus the marker's learnt model error (the mean square of
// its residuals, LearnOffsets: the measurement's variance as seen, not its bound; Mohamed &
// Schwarz 1999), and one beyond its whole spread with the bound -- which the slack cannot have
// made -- counts in full, so the factor rises as soon as the limb moves (the hidden gates' factor
// is learnt so, LearnHiddenScale). The weight of those within it is still 2 f - 1 of the spread
// with the bound: how much of the gate the prediction makes. Either part alone does not mend it
// (50 Hz, seeds 1-20: 256 -> 267 and 152 wrong labels; both, 58); the model error in the weight
// too sends every factor to the floor (8,949: the filter's prediction spread is itself made with
// the bound, its posterior, and stays above the innovations with q at the floor). Not below 40 Hz
// (hidden_horizon_frames 0), where the prediction makes the gates and the within innovations
// count nearly in full already: there it widened the gates (test_ekf's 12.5 Hz run 109 -> 149
// wrong labels; biobuddy's left hip trial at 12 Hz, LPSI and S3 exchanged for 138 frames).
void Tracker::Impl::LearnProcessNoise(double dt) {
  constexpr double kMaxRatio = 16.0;
  const double gain = std::min(1.0, dt / options.process_noise_time_constant_s);
  for (int i = 0; i < nz; ++i) {
    if (!(q_predicted[i] > 0) || !(q_count[i] > 0)) continue;
    const double ratio = std::min(q_innovation[i] / q_predicted[i], kMaxRatio);
    const double informed = q_weight[i] / q_count[i];
    q_scale[i] = std::clamp(q_scale[i] * (1.0 + gain * informed * (ratio - 1.0)),
                            options.min_process_noise_scale, 1.0);
    jerk_psd_now[i] = q_scale[i] * jerk_psd[i];
  }
}

// Each labelled marker's residual after the update (linearised: nu - J_m dz), in its segment's
// frame, is a measurement of its offset: where the subject wears the marker on its segment, a
// constant the nominal model misplaces by centimetres. While the subject stands still
// (subject_still, ChooseMeasurements) the offset is estimated as the average of those residuals,
// weighed against the prior (marker_offset_sigma, worth marker_offset_prior_frames frames of
// residuals) in information form with a forgetting factor:
//     info_n = (1 - g) info_{n-1} + 1 / n0,   gain_n = 1 / (n0 info_n),   unknown_n = 1 / info_n
// (g = OffsetGain(), n0 = marker_offset_prior_frames; info_0 = 1: the prior alone): over a
// marker's first still frames a running mean (gain 1/2, 1/3, ... for n0 = 1) whose unknown part,
// the gate's share of the prior, shrinks as 1/(1 + n / n0); after 1/g frames the gain is g
// (steady state: unknown = g n0), so a later pause changes nothing. In motion the gain is g, the
// exponential average over the time constant that follows a nominal model's pose-dependent
// error: slow, so that the pose converges first and the offsets take only what the pose cannot
// explain.
// Why: the simulated sessions start in a static posture, where a marker's residual says where it
// sits on its segment; learnt at the slow gain alone, the offsets of the start's labels stayed
// unknown for seconds, every gate was ~10 cm wide on the 25 mm prior, and a marker hidden for a
// frame of the static took a ghost 7-10 cm from its point (seeds 41, 46, 48 at 5 ghosts: RASI,
// RHEE, C7, RFHD), or jumped from its own point 35 mm off to a ghost 9 mm from its half-learnt
// prediction (seed 44, LANK, then kept from its point for 2 s as seen beside it). Learnt as the
// mean, a marker seen in the static is looked for where it was seen. Off by default: a label the
// first frames gave wrong is learnt as fast, and the segment's geometry then agrees with it
// (BENCHMARKS.md, seventeenth session: seeds 57, 63, 78). Not in motion: residuals
// there carry the pose's lag and error, and learnt as a mean from the first frame they froze it
// into the offsets (gait2354's walk, which starts walking: 0.967 of the labels; welk007's hip
// trial at 12 Hz, 0.910; a start after a second of occlusion mid-movement, 0.974). n0 = 0: the
// slow gain always (the tracker before issue 15).
void Tracker::Impl::LearnOffsets(const Eigen::VectorXd& dzv) {
  const double g = OffsetGain();
  const double n0 = options.marker_offset_prior_frames;
  for (int m = 0; m < nm; ++m) {
    if (row_to_col[m] < 0 || !measured[m]) continue;
    const std::vector<int>& cols = model->marker_coordinates(m);
    Eigen::Vector3d r = points.col(row_to_col[m]) - predicted.col(m);
    for (size_t a = 0; a < cols.size(); ++a) r -= jac[m].col(a) * dzv[cols[a]];
    double k = g;
    if (n0 > 0 && subject_still) {
      const double info = (1.0 - g) / std::max(offset_unknown[m], 1e-12) + 1.0 / n0;
      k = 1.0 / (n0 * info);
      offset_unknown[m] = 1.0 / info;
    } else {
      offset_unknown[m] *= 1.0 - g;
    }
    offset[m] += k * (data.segment_rotation[model->markers()[m].segment].transpose() * r);
    model_error[m] += g * (r.squaredNorm() / 3.0 - model_error[m]);
  }
}

// Wraps the full-turn coordinates and keeps the others inside the model's ranges: a segment
// left with one marker (a foot with its toe marker hidden) can otherwise swing into a pose no
// subject takes, fit the remaining marker there, and never meet the hidden one again.
void Tracker::Impl::Wrap(Eigen::VectorXd* z) const {
  const auto& co = model->coordinates();
  for (int i = 0; i < nz; ++i) {
    if (wraps[i])
      (*z)[i] = std::remainder((*z)[i], 2 * M_PI);
    else
      (*z)[i] = std::clamp((*z)[i], co[i].min_value, co[i].max_value);
  }
}

// ---------------------------------------------------------------------------------------------

Tracker::Tracker(std::shared_ptr<const Model> model, TrackerOptions options, ModelOrigin origin)
    : impl_(new Impl) {
  impl_->options = std::move(options);
  impl_->origin = origin;
  impl_->lab_to_model = Eigen::Quaterniond::FromTwoVectors(impl_->options.up.normalized(),
                                                            impl_->options.model_up.normalized())
                            .toRotationMatrix();
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
      s.points.col(s.valid.size()) = s.lab_to_model * pts.col(k);
      s.valid.push_back(k);
    }
  const int np = static_cast<int>(s.valid.size());
  const double dt = s.Dt(time_s);
  s.frame_dt = dt;
  s.last_time = time_s;

  if (out.state == TrackState::kTracking) {
    s.Predict(dt);
    s.zbuf = s.x.head(s.nz);
    s.Linearise(s.zbuf);
    for (size_t i = 0; i < s.centre_now.size(); ++i) s.centre_now[i] = s.data.segment_position[i];
    s.LabelByGating(np);
    s.LabelLooseSegments(np);
    s.RegisterSegments(np);
    s.ReviewProvisionalLabels(np);
    const int labelled = s.ApplyLabels(np);
    s.ChooseMeasurements();
    s.WithholdDoubtfulReturns(np, dt);
    double nis = 0;
    if (s.measured_count == 0) {
      ++s.hidden_count;  // the forecasts' chain is broken
      std::fill(s.observed.begin(), s.observed.end(), 0);
      std::fill(s.beyond_gate.begin(), s.beyond_gate.end(), 0);
    }
    bool ok = s.measured_count == 0 || s.FilterUpdate(&nis, dt);
    // Without an update P's upper triangle is still the prediction's stale one (Predict).
    if (s.measured_count == 0 || !ok) MirrorLowerToUpper(&s.P);
    if (ok) {
      s.zbuf = s.x.head(s.nz);
      s.Wrap(&s.zbuf);
      s.x.head(s.nz) = s.zbuf;
      ok = s.x.allFinite();
    }
    out.nis = nis;
    out.nis_dof = 3 * s.measured_count;
    const bool bad = !ok || labelled < s.options.min_labelled_fraction * s.nm_seen ||
                     (labelled > 0 && nis > s.options.max_nis_per_dof * out.nis_dof);
    if (ok && !bad) {
      s.bad_frames = 0;
      s.Reacquire(np);
      s.PushHistory(np);
      s.z_good = s.x.head(s.nz);
    } else if (s.prev_np = 0; ++s.bad_frames >= s.options.divergence_frames || !ok) {
      out.state = TrackState::kLost;
      s.init.attempts = 0;
    }
  }
  if (out.state != TrackState::kTracking) {
    std::fill(out.marker_of_point.begin(), out.marker_of_point.end(), -1);
    std::fill(out.point_of_marker.begin(), out.point_of_marker.end(), -1);
    out.labelled = 0;
    if (s.TryInitialise(np)) {
      out.state = TrackState::kTracking;
      out.reinitialised = true;
      std::fill(s.hidden_made.begin(), s.hidden_made.end(), -1);
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

Status Tracker::SwapModel(std::shared_ptr<const Model> model, ModelOrigin origin) {
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
  const bool same_segments = model->num_segments() == old.num_segments();
  // What the labelling has learnt of the points does not depend on the model: the probation runs,
  // the 20-frame history, the seen-beside records, the held runs and the last frame's points. A
  // swap that wiped them left the next frame without a measurement (every marker back on
  // probation) and restarted the ghost protections; so they are carried over the re-allocation.
  auto measured = std::move(s.measured);
  auto labelled_run = std::move(s.labelled_run);
  auto unlabelled_run = std::move(s.unlabelled_run);
  auto stuck_run = std::move(s.stuck_run);
  auto last_point = std::move(s.last_point);
  auto last_predicted = std::move(s.last_predicted);
  auto hist_points = std::move(s.hist_points);
  auto hist_count = std::move(s.hist_count);
  auto hist_claimed = std::move(s.hist_claimed);
  auto hist_marker_point = std::move(s.hist_marker_point);
  auto hist_centre = std::move(s.hist_centre);
  const int hist_head = s.hist_head, hist_size = s.hist_size;
  auto beside_prev = std::move(s.beside_prev);
  auto held_run = std::move(s.held_run);
  auto prev_points = std::move(s.prev_points);
  auto prev_free = std::move(s.prev_free);
  auto prev_free_list = std::move(s.prev_free_list);
  auto q_scale = std::move(s.q_scale);  // the subject's motion, not the model's
  auto hidden_scale = std::move(s.hidden_scale);  // likewise
  const int prev_np = s.prev_np, prev_free_count = s.prev_free_count;
  s.SetModel(std::move(model));
  s.Allocate();
  s.measured = std::move(measured);
  s.labelled_run = std::move(labelled_run);
  s.unlabelled_run = std::move(unlabelled_run);
  s.stuck_run = std::move(stuck_run);
  s.last_point = std::move(last_point);
  s.last_predicted = std::move(last_predicted);
  s.hist_points = std::move(hist_points);
  s.hist_count = std::move(hist_count);
  s.hist_claimed = std::move(hist_claimed);
  s.hist_marker_point = std::move(hist_marker_point);
  if (same_segments) {
    // The predicted joint centres of the past frames move by the fit's correction (millimetres
    // to centimetres); the rigidity test they feed allows 1 cm of spread, and the ring renews in
    // 20 frames.
    s.hist_centre = std::move(hist_centre);
    s.hist_head = hist_head;
    s.hist_size = hist_size;
  }
  s.beside_prev = std::move(beside_prev);
  s.held_run = std::move(held_run);
  s.prev_points = std::move(prev_points);
  s.prev_free = std::move(prev_free);
  s.prev_free_list = std::move(prev_free_list);
  s.q_scale = std::move(q_scale);
  s.hidden_scale = std::move(hidden_scale);
  for (int i = 0; i < s.nz; ++i) s.jerk_psd_now[i] = s.q_scale[i] * s.jerk_psd[i];
  s.prev_np = prev_np;
  s.prev_free_count = prev_free_count;
  // The new model's markers are where the fit put them: forget the old model's corrections, but
  // trust the new positions more than a nominal model's.
  s.ClearOffsets(s.options.swap_offset_count);
  s.origin = origin;
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
const InitialisationSummary& Tracker::initialisation() const { return impl_->init; }
const Eigen::Matrix3Xd& Tracker::predicted_markers() const { return impl_->predicted; }
const Eigen::MatrixXd& Tracker::covariance() const { return impl_->P; }
Eigen::VectorXd Tracker::velocities() const { return impl_->x.segment(impl_->nz, impl_->nz); }
Eigen::VectorXd Tracker::accelerations() const { return impl_->x.tail(impl_->nz); }

}  // namespace mocap::ekf
