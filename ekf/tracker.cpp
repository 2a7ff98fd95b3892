#include "ekf/tracker.h"

#include <Eigen/Cholesky>
#include <Eigen/Geometry>
#include <Eigen/SVD>
#include <algorithm>
#include <cmath>
#include <limits>
#include <random>

#include "ekf/assignment.h"
#include "ekf/filter.h"

namespace mocap::ekf {

namespace {
constexpr double kForbidden = 1e9;  // cost of a pair the gate excludes (finite: see assignment.h)
// A point that continues a marker's first point after a gap moves as the prediction does within
// this (a frame is 5 ms: 1 cm is 2 m/s of unpredicted motion; random ghosts jump decimetres).
constexpr double kProbationDistance = 0.01;
// Following a point back in time (NonRigidTrack): its largest step between frames (5 m/s at
// 200 Hz), the frames it must have been seen to be judged, and how much its distance to a joint
// centre may vary on a rigid segment (noise, and the predicted centre's error).
constexpr double kTrackStep = 0.025;
constexpr int kMinTrackFrames = 5;
constexpr double kRigidTolerance = 0.01;
// How long the record of a point seen beside a marker holds (SeenBeside): about the longest life
// of a stray reflection.
constexpr double kBesideSeconds = 2.0;
// The error of a predicted joint centre (a nominal model's centres are 1-2 cm off).
constexpr double kJointCentreTolerance = 0.02;
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
  if (!(velocity_time_constant_s > 0) || !(acceleration_time_constant_s > 0))
    return Fail(error, "velocity_time_constant_s and acceleration_time_constant_s must be > 0");
  if (!(gate_chi2 > 0)) return Fail(error, "gate_chi2 must be > 0");
  if (!(marker_offset_sigma >= 0) || !(marker_offset_floor >= 0))
    return Fail(error, "marker_offset_sigma and marker_offset_floor must be >= 0");
  if (!(marker_offset_time_constant_s > 0))
    return Fail(error, "marker_offset_time_constant_s must be > 0");
  if (swap_offset_count < 0) return Fail(error, "swap_offset_count must be >= 0");
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
  // Per marker: whether the data can show it (not in options.unseen_markers); how many can.
  std::vector<char> seen;
  int nm_seen = 0;
  // Turns the lab's vertical (options.up) onto the model's (options.model_up): every input point
  // goes through it, so the model's root angles describe a subject standing as the model stands
  // whatever the lab's axes (an upside-down lab would need pelvis tilt and list near 180 degrees,
  // outside their ranges, which the search and the filter keep to).
  Eigen::Matrix3d lab_to_model = Eigen::Matrix3d::Identity();
  std::vector<char> rotational, wraps;
  Eigen::VectorXd marker_variance;  // sigma_m^2 / w_m
  // Online marker offsets (see tracker.h): per marker, in its segment's frame, and how many
  // frames have contributed since the last (re)initialisation.
  std::vector<Eigen::Vector3d> offset;
  std::vector<double> offset_unknown;  // (1 - gain)^frames seen: the part still unknown
  // Per marker: the mean square (per coordinate) of its residuals after the update, averaged
  // like the offsets: the model error that the pose and the offset do not explain.
  std::vector<double> model_error;
  // The root joint, for placing hypotheses: its rotations as signed coordinate axes (for an
  // Euler decomposition) and its translations before any rotation (moving along fixed axes).
  bool root_euler = false;
  int root_rot_coord[3] = {-1, -1, -1}, root_rot_axis[3] = {0, 0, 0};
  double root_rot_sign[3] = {1, 1, 1};
  std::vector<std::pair<int, Eigen::Vector3d>> root_translations;
  std::vector<char> root_free;
  // Depth in the tree (root joint 0) of each coordinate's joint and each marker's segment.
  std::vector<int> coordinate_depth, marker_depth;
  int max_depth = 0;

  // --- state ---
  Eigen::VectorXd x;  // [z; z'; z'']
  Eigen::MatrixXd P;
  Eigen::VectorXd jerk_psd;
  double last_time = kNaN;
  bool had_track = false;
  Eigen::VectorXd z_good;  // last pose that passed the divergence test
  int bad_frames = 0;
  TrackOutput out;
  InitialisationSummary init;

  // --- per-frame workspace (sized in Allocate) ---
  std::vector<int> valid;  // input indices of the finite points, compacted
  Eigen::Matrix3Xd points;
  Eigen::VectorXd zbuf, dz;
  Eigen::Matrix3Xd predicted;
  std::vector<Eigen::Matrix<double, 3, Eigen::Dynamic>> jac;
  Eigen::Matrix<double, 3, Eigen::Dynamic> jp;
  std::vector<Eigen::Matrix3d> s_inv;
  std::vector<double> reject_sq;
  std::vector<int> gated_by;  // per point: how many markers' gates hold it
  Eigen::MatrixXd cost;
  std::vector<int> row_to_col;
  LinearAssignment lap;
  Eigen::MatrixXd A;
  Eigen::VectorXd b;
  CoordinateUpdate update;
  // Probation of a marker coming back (see tracker.h): per marker, whether this frame's update
  // uses its label, how many consecutive frames it has been labelled, and where its point and
  // prediction were in the last frame.
  std::vector<char> measured;
  std::vector<int> labelled_run;
  Eigen::Matrix3Xd last_point, last_predicted;
  int measured_count = 0;
  void ChooseMeasurements();
  // The last kHistory tracking frames' points and predicted joint centres (a ring), to follow a
  // point back in time (NonRigidTrack).
  static constexpr int kHistory = 20;
  std::vector<Eigen::Matrix3Xd> hist_points;
  std::vector<int> hist_count;
  std::vector<std::vector<char>> hist_claimed;  // per frame, per point: a marker's
  std::vector<std::vector<Eigen::Vector3d>> hist_centre;
  std::vector<Eigen::Vector3d> centre_now;  // this frame's predicted joint centres
  int hist_head = 0, hist_size = 0;
  void PushHistory(int np);
  bool NonRigidTrack(int m, const Eigen::Vector3d& p) const;
  // Follows p back (see NonRigidTrack): the frames it was seen, and the spread of its distance
  // to marker m's joint centre over them.
  int TrackBack(int m, const Eigen::Vector3d& p, double* spread) const;
  bool RejoinAtOffset(int m, int np);
  // The one point not in ltaken within sqrt(radius2) of `where`; -1 when none or several.
  int OnlyFreePointNear(const Eigen::Vector3d& where, double radius2, int np) const {
    int found = -1;
    for (int k = 0; k < np; ++k)
      if (!ltaken[k] && (points.col(k) - where).squaredNorm() < radius2) {
        if (found >= 0) return -1;
        found = k;
      }
    return found;
  }
  // Which markers each unclaimed point has been seen beside (see SeenBeside): per point of the
  // last good frame, per marker, the last tracking frame in which that marker was measured on
  // another point while this point's track was alive (kNever: not within its track).
  static constexpr int kNever = std::numeric_limits<int>::min() / 2;
  std::vector<int> beside_prev, beside_now;
  // Per marker: its longest run of labelled frames since the (re)initialisation.
  std::vector<int> held_run;
  static constexpr int kHeldFrames = 20;
  Eigen::Matrix3Xd prev_points;
  std::vector<char> prev_free;
  std::vector<int> prev_free_list;  // the indices of prev_free's points
  int prev_np = 0, prev_free_count = 0;
  int frame_index = 0;
  mutable std::vector<int> pred_cache;  // per point of this frame: Predecessor, -2 not yet known
  int Predecessor(int k, int np) const;
  // Per point of this frame: the marker whose track it continues (see FollowLabelledTracks), or -1.
  std::vector<int> track_owner;
  void FollowLabelledTracks(int np);
  bool SeenBeside(int m, int k, int np) const;

  // sigma_m^2 / w_m plus what is not yet known of the marker's offset.
  double MeasurementVariance(int m) const {
    const double s0 = options.marker_offset_sigma, s1 = options.marker_offset_floor;
    return marker_variance[m] + s0 * s0 * offset_unknown[m] + s1 * s1;
  }
  double OffsetGain() const {
    return 1.0 / std::max(1.0, options.marker_offset_time_constant_s * options.rate_hz);
  }
  void LearnOffsets(const Eigen::VectorXd& dz);
  void ClearOffsets(int count) {
    std::fill(offset.begin(), offset.end(), Eigen::Vector3d::Zero());
    std::fill(offset_unknown.begin(), offset_unknown.end(), std::pow(1.0 - OffsetGain(), count));
    std::fill(model_error.begin(), model_error.end(), 0.0);
  }
  void SetModel(std::shared_ptr<const Model> m);
  void Allocate();
  void ResetState();
  double Dt(double time_s) const;
  void Predict(double dt);
  void Linearise(const Eigen::VectorXd& z);
  void LabelByGating(int np);
  void PickUpOnSegment(int np);
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

  // Local re-acquisition of a limb (see tracker.h): per marker, consecutive tracking frames
  // without a label; per joint, the coordinates and markers of its subtree; per marker, the
  // joint whose subtree is searched again when it stays unlabelled. Workspace sized in Allocate.
  std::vector<int> unlabelled_run, marker_limb;
  std::vector<std::vector<char>> limb_coord;
  std::vector<std::vector<int>> limb_markers;
  static constexpr int kMaxLimbCoords = 12;  // larger subtrees are left to the global search
  using LimbMatrix = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, 0, kMaxLimbCoords,
                                   kMaxLimbCoords>;
  using LimbVector = Eigen::Matrix<double, Eigen::Dynamic, 1, 0, kMaxLimbCoords, 1>;
  LimbMatrix lN, lNd;
  LimbVector lg, lstep;
  Eigen::Matrix3Xd lsaved;  // predicted, kept across a search (predicted_markers())
  Eigen::VectorXd ltrial, lz, lstart, lbest, lz0;
  Eigen::LLT<LimbMatrix> lllt;
  std::vector<std::vector<int>> limb_coord_list;
  std::vector<int> llocal;  // per coordinate: its index among the limb's, or -1
  void LineariseLimb(int joint, const Eigen::VectorXd& z);
  std::vector<int> lcand, lassign, lbest_assign, lrow_to_col, lfree;
  std::vector<char> ltaken;
  void Reacquire(int np);
  // Frames tracked since the last (re)initialisation. The labels of a fresh track come from a
  // search over one frame and can be wrong on a whole limb (self-consistently: a thigh turned
  // about its long axis); labels that tracking has kept are not. So for the first second a limb
  // search may relabel the limb's markers and is tried whenever any unclaimed point is near;
  // after it, it keeps the labels the limb has and is tried only for a point at the rigid-body
  // distances of the marker (RigidlyPlausible).
  int tracked_frames = 0;
  bool FreshTrack() const { return tracked_frames < options.rate_hz * kFreshTrackSeconds; }
  static constexpr double kFreshTrackSeconds = 1.0;
  bool RigidlyPlausible(int m, int k) const;
  bool OnSegmentSphere(int m, const Eigen::Vector3d& p) const;
  bool ReacquireLimb(int joint, int np);
  double LimbAssign(int joint, const Eigen::VectorXd& z, int nc, double radius);
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
  marker_variance.resize(nm);
  for (int k = 0; k < nm; ++k)
    marker_variance[k] = options.sigma_m * options.sigma_m / md.markers()[k].weight;
  seen.assign(nm, 1);
  for (int k = 0; k < nm; ++k)
    for (const std::string& name : options.unseen_markers)
      if (md.markers()[k].name == name) seen[k] = 0;
  nm_seen = static_cast<int>(std::count(seen.begin(), seen.end(), 1));
  offset.assign(nm, Eigen::Vector3d::Zero());
  offset_unknown.assign(nm, 1.0);
  model_error.assign(nm, 0.0);

  // Depths (joints are parents first).
  std::vector<int> segment_depth(md.num_segments(), 0);
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
  const int mp = options.max_points;
  valid.clear();
  valid.reserve(mp);
  points.resize(3, mp);
  zbuf.resize(nz);
  dz.resize(nz);
  predicted.resize(3, nm);
  jac.resize(nm);
  for (int k = 0; k < nm; ++k) jac[k].resize(3, model->marker_coordinates(k).size());
  jp.resize(3, std::max(1, model->max_chain_coordinates()));
  s_inv.resize(nm);
  reject_sq.resize(nm);
  gated_by.resize(mp);
  cost.resize(nm, mp + nm);
  row_to_col.resize(nm);
  lap.Reserve(nm, mp + nm);
  A.resize(nz, nz);
  b.resize(nz);
  update.Resize(nz);
  out.marker_of_point.reserve(mp);
  out.point_of_marker.reserve(nm);
  unlabelled_run.assign(nm, 0);
  measured.assign(nm, 0);
  labelled_run.assign(nm, 0);
  hist_points.assign(kHistory, Eigen::Matrix3Xd::Zero(3, mp));
  hist_count.assign(kHistory, 0);
  hist_claimed.assign(kHistory, std::vector<char>(mp, 0));
  hist_centre.assign(kHistory,
                     std::vector<Eigen::Vector3d>(model->num_segments(), Eigen::Vector3d::Zero()));
  centre_now.assign(model->num_segments(), Eigen::Vector3d::Zero());
  hist_head = hist_size = 0;
  beside_prev.assign(static_cast<size_t>(mp) * nm, kNever);
  held_run.assign(nm, 0);
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
  PredictConstantAcceleration(dt, jerk_psd, std::exp(-dt / options.velocity_time_constant_s),
                              std::exp(-dt / options.acceleration_time_constant_s), &x, &P);
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

// Mahalanobis gating with S_m = J_m P_zz J_m^T + R_m and the optimal assignment.
void Tracker::Impl::LabelByGating(int np) {
  const double gate = options.gate_chi2;
  for (int m = 0; m < nm; ++m) {
    const std::vector<int>& cols = model->marker_coordinates(m);
    const int k = static_cast<int>(cols.size());
    const auto& J = jac[m];
    auto JP = jp.leftCols(k);
    // Summed in a register, not into JP: accumulating in memory made every term wait for the
    // previous one's store (this loop was most of the labelling's time).
    for (int bcol = 0; bcol < k; ++bcol) {
      const double* p_col = &P(0, cols[bcol]);
      Eigen::Vector3d sum = Eigen::Vector3d::Zero();
      for (int a = 0; a < k; ++a) sum += J.col(a) * p_col[cols[a]];
      JP.col(bcol) = sum;
    }
    Eigen::Matrix3d S = JP.lazyProduct(J.transpose());  // 3 x k x 3: no GEMM machinery
    S.diagonal().array() += MeasurementVariance(m) + (labelled_run[m] > 0 ? model_error[m] : 0.0);
    s_inv[m] = S.inverse();
    // d^2 >= |e|^2 / lambda_max(S) >= |e|^2 / trace(S): a cheap test before the quadratic form.
    reject_sq[m] = gate * S.trace();
  }
  auto C = cost.topLeftCorner(nm, np + nm);
  std::fill(gated_by.begin(), gated_by.begin() + np, 0);
  std::fill(pred_cache.begin(), pred_cache.begin() + np, -2);
  bool contested = false;
  FollowLabelledTracks(np);
  for (int m = 0; m < nm; ++m) {
    const Eigen::Vector3d p = predicted.col(m);
    double best = gate;
    int best_k = np + m;  // its own "missing" column
    if (!seen[m]) {
      C.row(m).head(np).setConstant(kForbidden);
      row_to_col[m] = best_k;
      continue;
    }
    for (int k = 0; k < np; ++k) {
      const Eigen::Vector3d e = points.col(k) - p;
      double d2 = kForbidden;
      if (e.squaredNorm() < reject_sq[m] && (track_owner[k] < 0 || track_owner[k] == m)) {
        const double q = e.dot(s_inv[m] * e);
        if (q < gate && OnSegmentSphere(m, points.col(k)) &&
            (labelled_run[m] > 0 || !NonRigidTrack(m, points.col(k))) &&
            !SeenBeside(m, k, np)) {
          d2 = q;
          contested |= ++gated_by[k] > 1;
          if (q < best) {
            best = q;
            best_k = k;
          }
        }
      }
      C(m, k) = d2;
    }
    row_to_col[m] = best_k;
  }
  // When no point lies in two gates, each marker's nearest gated point is the optimum; only
  // contested frames (markers crossing, a ghost between two markers) need the assignment.
  if (!contested) return;
  for (int m = 0; m < nm; ++m) {
    C.row(m).tail(nm).setConstant(kForbidden);
    C(m, np + m) = gate;
  }
  lap.Solve(C, row_to_col.data());
}

// Labels follow point tracks. A point that continues the point a marker was labelled on in the
// last frame (mutual nearest neighbours between the two frames, after moving the last point as the
// marker's prediction moved, within a frame's motion kTrackStep) is that marker's or nobody's: no
// other marker's gate takes it. Markers are centimetres apart and a frame is 5 ms, so a point
// track does not jump from one marker to another; what the frame-by-frame assignment alone did
// was let a marker back from an occlusion, with a wide gate, take its neighbour's point (a wrist
// marker on the other wrist marker's point, the neighbour left unlabelled) and the filter then
// settle in the shifted pose for seconds.
void Tracker::Impl::FollowLabelledTracks(int np) {
  std::fill(track_owner.begin(), track_owner.begin() + np, -1);
  if (prev_np == 0) return;
  const double step2 = kTrackStep * kTrackStep;
  for (int a = 0; a < nm; ++a) {
    if (labelled_run[a] <= 0) continue;
    const Eigen::Vector3d shift = predicted.col(a) - last_predicted.col(a);
    const Eigen::Vector3d q = last_point.col(a) + shift;
    int nearest = -1;
    double best = step2;
    for (int k = 0; k < np; ++k) {
      const double d2 = (points.col(k) - q).squaredNorm();
      if (d2 < best) {
        best = d2;
        nearest = k;
      }
    }
    if (nearest < 0) continue;
    // Mutual: no other point of the last frame is nearer to it.
    const Eigen::Vector3d back = points.col(nearest) - shift;
    bool mutual = true;
    for (int j = 0; j < prev_np && mutual; ++j)
      mutual = (prev_points.col(j) - back).squaredNorm() >= best ||
               (prev_points.col(j) - last_point.col(a)).squaredNorm() < 1e-18;
    if (mutual) track_owner[nearest] = track_owner[nearest] < 0 ? a : nm;  // two claims: nobody's
  }
}

// A marker the gates left unlabelled while three or more other markers of its segment are
// labelled this frame is looked for where those markers put it: the rigid motion that carries
// their predictions onto their points (Kabsch), applied to its own prediction. The gate measures
// a marker against the pose, and the pose of a segment held by few of its own markers and many of
// the rest of the body (the pelvis, the root, under the legs' and the trunk's) carries the whole
// chain's model error with a nominal model: a marker back from an occlusion is found 2-5 cm from
// its prediction, beyond its gate for as long as that error lasts, while where it sits among its
// segment's labelled markers does not depend on the pose. It takes the one unclaimed point within
// its gate around that position (its variance and its neighbours'), when that point's past does
// not rule it out; the label goes through probation like any other (ChooseMeasurements). Not in
// a fresh track, whose points' past is not judged (FreshTrack): there the gates are still wide.
void Tracker::Impl::PickUpOnSegment(int np) {
  for (int m = 0; m < nm; ++m)
    if (row_to_col[m] >= np) row_to_col[m] = -1;
  if (FreshTrack()) return;
  bool claims_known = false;
  for (int m = 0; m < nm; ++m) {
    if (row_to_col[m] >= 0 || !seen[m]) continue;
    const int segment = model->markers()[m].segment;
    int mates = 0;
    Eigen::Vector3d cp = Eigen::Vector3d::Zero(), cq = Eigen::Vector3d::Zero();
    double var = 0;
    for (int a = 0; a < nm; ++a)
      if (a != m && row_to_col[a] >= 0 && model->markers()[a].segment == segment) {
        ++mates;
        cp += predicted.col(a);
        cq += points.col(row_to_col[a]);
        var += MeasurementVariance(a);
      }
    if (mates < 3) continue;
    cp /= mates;
    cq /= mates;
    Eigen::Matrix3d H = Eigen::Matrix3d::Zero();
    for (int a = 0; a < nm; ++a)
      if (a != m && row_to_col[a] >= 0 && model->markers()[a].segment == segment)
        H += (predicted.col(a) - cp) * (points.col(row_to_col[a]) - cq).transpose();
    const Eigen::JacobiSVD<Eigen::Matrix3d> svd(H, Eigen::ComputeFullU | Eigen::ComputeFullV);
    Eigen::Matrix3d D = Eigen::Matrix3d::Identity();
    D(2, 2) = (svd.matrixV() * svd.matrixU().transpose()).determinant() < 0 ? -1.0 : 1.0;
    const Eigen::Matrix3d R = svd.matrixV() * D * svd.matrixU().transpose();
    const Eigen::Vector3d where = R * (predicted.col(m) - cp) + cq;
    const double gate2 = options.gate_chi2 * (MeasurementVariance(m) + var / mates);
    if (!claims_known) {
      std::fill(ltaken.begin(), ltaken.begin() + np, 0);
      for (int a = 0; a < nm; ++a)
        if (row_to_col[a] >= 0) ltaken[row_to_col[a]] = 1;
      claims_known = true;
    }
    const int found = OnlyFreePointNear(where, gate2, np);
    if (found < 0 || NonRigidTrack(m, points.col(found)) || SeenBeside(m, found, np)) continue;
    row_to_col[m] = found;
    ltaken[found] = 1;
  }
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
    if (row_to_col[m] < 0 || !measured[m]) continue;
    const double w = 1.0 / (MeasurementVariance(m) + model_error[m]);
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
  if (!update.Apply(A, b, nu_r_nu, &x, &P, nis)) return false;
  dz = x.head(nz) - zbuf;
  LearnOffsets(dz);
  return true;
}

// Each labelled marker's residual after the update (linearised: nu - J_m dz), in its segment's
// frame, moves its offset by a small constant gain (an exponential average over the time
// constant): slow, so that the pose converges first and the offsets take only what the pose
// cannot explain -- a gain of 1 on the first frame would freeze an initial pose error into the
// offsets for good.
void Tracker::Impl::LearnOffsets(const Eigen::VectorXd& dzv) {
  const double k = OffsetGain();
  for (int m = 0; m < nm; ++m) {
    if (row_to_col[m] < 0 || !measured[m]) continue;
    const std::vector<int>& cols = model->marker_coordinates(m);
    Eigen::Vector3d r = points.col(row_to_col[m]) - predicted.col(m);
    for (size_t a = 0; a < cols.size(); ++a) r -= jac[m].col(a) * dzv[cols[a]];
    offset[m] += k * (data.segment_rotation[model->markers()[m].segment].transpose() * r);
    model_error[m] += k * (r.squaredNorm() / 3.0 - model_error[m]);
    offset_unknown[m] *= 1.0 - k;
  }
}

void Tracker::Impl::PushHistory(int np) {
  hist_points[hist_head].leftCols(np) = points.leftCols(np);
  hist_count[hist_head] = np;
  std::vector<char>& claimed = hist_claimed[hist_head];
  std::fill(claimed.begin(), claimed.begin() + np, 0);
  for (int m = 0; m < nm; ++m)
    if (row_to_col[m] >= 0) claimed[row_to_col[m]] = 1;
  for (size_t i = 0; i < centre_now.size(); ++i) hist_centre[hist_head][i] = centre_now[i];
  hist_head = (hist_head + 1) % kHistory;
  hist_size = std::min(hist_size + 1, kHistory);

  // A marker that lost its label this frame while another marker now holds its last point (one
  // marker is one point) held the wrong one: what it was seen beside was recorded under that
  // label (a head initialised turned about, its front markers on the back markers' points, their
  // own points unclaimed beside them), so it is forgotten, and the label no longer counts as held.
  for (int m = 0; m < nm; ++m) {
    if (row_to_col[m] >= 0 || unlabelled_run[m] != 1) continue;
    for (int a = 0; a < nm; ++a)
      if (a != m && row_to_col[a] >= 0 &&
          (points.col(row_to_col[a]) - last_point.col(m)).squaredNorm() < kTrackStep * kTrackStep) {
        for (size_t j = static_cast<size_t>(m); j < beside_prev.size(); j += nm) beside_prev[j] = kNever;
        held_run[m] = 0;
        break;
      }
  }
  // Each unclaimed point inherits its predecessor's record and adds the markers measured now.
  ++frame_index;
  for (int k = 0; k < np; ++k) {
    int* now = beside_now.data() + static_cast<size_t>(k) * nm;
    if (claimed[k]) continue;
    const int pred = Predecessor(k, np);
    const int* before = pred >= 0 ? beside_prev.data() + static_cast<size_t>(pred) * nm : nullptr;
    for (int a = 0; a < nm; ++a)
      now[a] = row_to_col[a] >= 0 && row_to_col[a] != k && measured[a] ? frame_index
               : before ? before[a]
                        : kNever;
  }
  beside_prev.swap(beside_now);
  prev_points.leftCols(np) = points.leftCols(np);
  prev_free_count = 0;
  for (int k = 0; k < np; ++k) {
    prev_free[k] = !claimed[k];
    if (!claimed[k]) prev_free_list[prev_free_count++] = k;
  }
  prev_np = np;
}

// The last good frame's unclaimed point that point k continues: its nearest point of that frame
// within a frame's motion (kTrackStep), when k is also that point's nearest of this frame (mutual
// nearest neighbours: a reflection riding 15 mm from its marker is not confused with it) and
// it was not a marker's (k then continues that marker); -1 otherwise.
int Tracker::Impl::Predecessor(int k, int np) const {
  if (pred_cache[k] != -2) return pred_cache[k];
  const Eigen::Vector3d p = points.col(k);
  int pred = -1;
  double best = kTrackStep * kTrackStep;
  // The few unclaimed points first: most points (the markers') have none near and stop here.
  for (int f = 0; f < prev_free_count; ++f) {
    const int j = prev_free_list[f];
    const double d2 = (prev_points.col(j) - p).squaredNorm();
    if (d2 < best) {
      best = d2;
      pred = j;
    }
  }
  for (int j = 0; j < prev_np && pred >= 0; ++j)
    if (!prev_free[j] && (prev_points.col(j) - p).squaredNorm() < best) pred = -1;
  for (int i = 0; i < np && pred >= 0; ++i)
    if (i != k && (points.col(i) - prev_points.col(pred)).squaredNorm() < best) pred = -1;
  pred_cache[k] = pred;
  return pred;
}

// Whether point p has been seen beside marker m: followed back frame by frame, it was there, as
// another point, while m was measured, within the last kBesideSeconds. One marker is one point,
// so p is not m: it is a reflection that came with m (riding along with it, or fixed near where
// it passed) and outlived m's occlusion. Such a ghost keeps its distances to m's segment (it
// moves with the marker), so NonRigidTrack passes it, and its history ring (kHistory frames) is
// shorter than an occlusion; this record is carried for as long as the point is followed. The
// evidence expires, so that a point the track wrongly left unclaimed beside a wrong label is not
// kept from its marker for good.
bool Tracker::Impl::SeenBeside(int m, int k, int np) const {
  // A fresh track's labels may be wrong (see FreshTrack): there only a marker labelled in the last
  // frame, or one that held its point for kHeldFrames, is kept from the reflection beside the
  // point it loses (an ankle marker hidden in the static pose, a lab-fixed ghost 8 cm away in its
  // still wide gate); a marker without either may be the one whose point was measured as
  // another's. A held label that proves wrong loses its records (PushHistory).
  if (prev_np == 0 || (FreshTrack() && labelled_run[m] == 0 && held_run[m] < kHeldFrames))
    return false;
  const int pred = Predecessor(k, np);
  if (pred < 0) return false;
  return frame_index - beside_prev[static_cast<size_t>(pred) * nm + m] <=
         kBesideSeconds * options.rate_hz;
}

// Whether point p, followed back through the last frames (the nearest unclaimed point within a
// frame's motion), changed its distance to marker m's joint centre: a marker keeps it (rigid
// body), a ghost does not -- a reflection fixed in the lab or riding along with another marker,
// which can live for seconds near the body. Only a point seen for kMinTrackFrames can be judged;
// a marker coming back from an occlusion has no past and passes (the labelled points it may
// pass near, a hand sliding over the thigh marker, are other markers' past, not its own).
bool Tracker::Impl::NonRigidTrack(int m, const Eigen::Vector3d& p) const {
  // A fresh track's limb may be wrongly placed, its joint centres with it (see FreshTrack).
  if (FreshTrack()) return false;
  double spread = 0;
  return TrackBack(m, p, &spread) >= kMinTrackFrames && spread > kRigidTolerance;
}

int Tracker::Impl::TrackBack(int m, const Eigen::Vector3d& p, double* spread) const {
  const int segment = model->markers()[m].segment;
  Eigen::Vector3d q = p;
  const double r0 = (p - centre_now[segment]).norm();
  double lo = r0, hi = r0;
  int length = 1;
  for (int h = 1; h <= hist_size; ++h) {
    const int slot = (hist_head - h + kHistory) % kHistory;
    const Eigen::Matrix3Xd& pts = hist_points[slot];
    int nearest = -1;
    double best = kTrackStep * kTrackStep;
    const std::vector<char>& claimed = hist_claimed[slot];
    for (int k = 0; k < hist_count[slot]; ++k) {
      if (claimed[k]) continue;
      const double d2 = (pts.col(k) - q).squaredNorm();
      if (d2 < best) {
        best = d2;
        nearest = k;
      }
    }
    if (nearest < 0) break;
    q = pts.col(nearest);
    const double r = (q - hist_centre[slot][segment]).norm();
    lo = std::min(lo, r);
    hi = std::max(hi, r);
    ++length;
  }
  *spread = hi - lo;
  return length;
}

// A marker coming back after frames without a label is labelled at once but enters the update
// only from its second consecutive frame, and only if its point moved from the first frame's
// as its prediction did. Half of the ghosts near a body are single-frame reflections: one in the
// gate of a hidden marker whose segment is loosely held (a toe with only the heel seen: the gate
// is several centimetres long) would otherwise be trusted at the marker's full precision, move
// the segment by as much, shrink its covariance there, and leave the true marker outside the
// gate when it reappears (a limb lost for the 20 frames before its search). The next frame's
// point of a ghost is another one or none. A true marker costs one frame of information.
void Tracker::Impl::ChooseMeasurements() {
  measured_count = 0;
  for (int m = 0; m < nm; ++m) {
    const int col = row_to_col[m];
    if (col < 0) {
      measured[m] = 0;
      labelled_run[m] = 0;
      continue;
    }
    const Eigen::Vector3d p = points.col(col), q = predicted.col(m);
    if (labelled_run[m] == 1) {
      const Eigen::Vector3d moved = (p - last_point.col(m)) - (q - last_predicted.col(m));
      measured[m] = moved.squaredNorm() <= kProbationDistance * kProbationDistance;
      if (!measured[m]) labelled_run[m] = 0;  // a different point: this is its first frame
    } else {
      measured[m] = labelled_run[m] > 1;
    }
    ++labelled_run[m];
    held_run[m] = std::max(held_run[m], labelled_run[m]);
    last_point.col(m) = p;
    last_predicted.col(m) = q;
    measured_count += measured[m];
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
    // Two angle triples give the same rotation, (a0, a1, a2) and (a0 + pi, pi - a1, a2 + pi)
    // ((a0 + pi, -a1, a2 + pi) for a proper Euler sequence); Eigen returns a0 in [0, pi]. Take
    // the one nearer the start, or a subject facing the other half of the room would be tracked
    // upside down in its root angles (same markers, tilt and list near pi).
    const bool proper = root_rot_axis[0] == root_rot_axis[2];
    Eigen::Vector3d other(angles[0] + M_PI, proper ? -angles[1] : M_PI - angles[1],
                          angles[2] + M_PI);
    double da = 0, db = 0;
    for (int i = 0; i < 3; ++i) {
      const double s0 = start[root_rot_coord[i]] * root_rot_sign[i];
      da += std::pow(std::remainder(angles[i] - s0, 2 * M_PI), 2);
      db += std::pow(std::remainder(other[i] - s0, 2 * M_PI), 2);
    }
    const Eigen::Vector3d& chosen = db < da ? other : angles;
    for (int i = 0; i < 3; ++i)
      (*z)[root_rot_coord[i]] =
          root_rot_sign[i] * std::remainder(chosen[i], 2 * M_PI);
  }
  ForwardKinematics(*model, geometry, *z, &data);
  Eigen::Vector3d mc = Eigen::Vector3d::Zero();
  for (int m = 0; m < nm; ++m)
    if (seen[m]) mc += MarkerPosition(*model, geometry, data, m);
  const Eigen::Vector3d shift = centroid - mc / std::max(1, nm_seen);
  for (const auto& [coord, axis] : root_translations) (*z)[coord] += axis.dot(shift);
  return true;
}

// ICP-like search from z: assign markers to points by distance (optimal assignment), one damped
// Gauss-Newton step on the pose, reassign. The body is placed from the root outwards: stage d
// frees the joints at depth <= d of the tree and assigns only the markers they carry, so a
// distal marker is paired only once its parent segments are in place (the two wrist markers,
// 7 cm apart, would otherwise cross while the arm is still beside the body, and the forearm turn
// half a revolution into a mirrored local minimum). A final stage refines everything with a
// radius shrinking to 4 cm.
Tracker::Impl::Hypothesis Tracker::Impl::Icp(Eigen::VectorXd z, int np) {
  const Eigen::VectorXd start = z;
  // Weak prior towards the start (metres^2 per rad^2 / per m^2): pins what the markers leave free.
  const double prior_rot = 0.01 * 0.01 / (0.5 * 0.5), prior_trans = 0.01 * 0.01 / (1.0 * 1.0);
  const int stages = max_depth + 1, per_stage = 3;
  const int iters = stages * per_stage + options.init_iterations;
  Eigen::MatrixXd N(nz, nz), Nd(nz, nz);
  Eigen::VectorXd g(nz), step(nz), trial(nz);
  Eigen::LLT<Eigen::MatrixXd> llt(nz);
  std::vector<int> assign(nm, -1), previous(nm, -2);
  std::vector<char> free(nz, 1), active(nm, 1);
  Eigen::VectorXd lower(nz), upper(nz);
  for (int i = 0; i < nz; ++i) {
    // The start itself may be outside (a user's static pose): never clamp it back.
    lower[i] = std::min(model->coordinates()[i].min_value, z[i]);
    upper[i] = std::max(model->coordinates()[i].max_value, z[i]);
  }
  auto Cost = [&](const Eigen::VectorXd& zz) {
    ForwardKinematics(*model, geometry, zz, &data);
    double s = 0;
    for (int m = 0; m < nm; ++m)
      if (assign[m] >= 0)
        s += (MarkerPosition(*model, geometry, data, m) - points.col(assign[m])).squaredNorm();
    for (int i = 0; i < nz; ++i)
      if (free[i])
        s += (rotational[i] ? prior_rot : prior_trans) * (zz[i] - start[i]) * (zz[i] - start[i]);
    return s;
  };
  double radius = 0.25;
  double lambda = 1e-3;
  for (int it = 0; it < iters; ++it) {
    const int stage = it / per_stage;  // >= stages: the final stage
    const bool final_stage = stage >= stages;
    const int depth = final_stage ? max_depth : stage;
    for (int i = 0; i < nz; ++i) free[i] = coordinate_depth[i] <= depth;
    for (int m = 0; m < nm; ++m) active[m] = seen[m] && marker_depth[m] <= depth;
    radius = stage == 0 ? 0.25
             : !final_stage ? 0.15
                            : std::max(options.init_radius_m,
                                       0.12 - 0.02 * (it - stages * per_stage));
    Linearise(z);
    auto C = cost.topLeftCorner(nm, np + nm);
    const double r2 = radius * radius;
    for (int m = 0; m < nm; ++m) {
      for (int k = 0; k < np; ++k) {
        const double d2 = (points.col(k) - predicted.col(m)).squaredNorm();
        C(m, k) = active[m] && d2 < r2 ? d2 : kForbidden;
      }
      C.row(m).tail(nm).setConstant(kForbidden);
      C(m, np + m) = r2;
    }
    lap.Solve(C, row_to_col.data());
    for (int m = 0; m < nm; ++m) assign[m] = row_to_col[m] < np ? row_to_col[m] : -1;
    const bool same = assign == previous;
    previous = assign;

    // Normal equations of the assigned markers + prior.
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
      const double w = rotational[i] ? prior_rot : prior_trans;
      N(i, i) += w;
      g[i] += w * (z[i] - start[i]);
      if (!free[i]) {
        N.row(i).setZero();
        N.col(i).setZero();
        N(i, i) = 1;
        g[i] = 0;
      }
    }
    const double c0 = Cost(z);
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
      // Within the model's joint ranges: a foot turned 120 degrees can match heel and toe
      // markers to each other's points, a pose no subject takes.
      for (int i = 0; i < nz; ++i)
        if (!wraps[i]) trial[i] = std::clamp(trial[i], lower[i], upper[i]);
      if (Cost(trial) < c0) {
        z = trial;
        lambda = std::max(1e-7, lambda * 0.3);
        accepted = true;
      } else {
        lambda *= 10;
      }
    }
    if (final_stage && same && (!accepted || step.norm() < 1e-6) && radius <= options.init_radius_m)
      break;
  }
  // Final assignment at the final pose and its score.
  Hypothesis h;
  Linearise(z);
  const double r2 = radius * radius;
  auto C = cost.topLeftCorner(nm, np + nm);
  for (int m = 0; m < nm; ++m) {
    for (int k = 0; k < np; ++k) {
      const double d2 = (points.col(k) - predicted.col(m)).squaredNorm();
      C(m, k) = seen[m] && d2 < r2 ? d2 : kForbidden;
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
  ++init.attempts;
  init.accepted = false;
  init.hypotheses = 0;
  init.best_score = init.runner_up_score = init.rms_m = 0;
  init.labelled = 0;
  if (np < options.init_min_fraction * nm_seen) {
    init.reason = "too few points";
    return false;
  }
  ClearOffsets(0);
  const Eigen::Vector3d centroid = points.leftCols(np).rowwise().mean();
  std::vector<Eigen::VectorXd> starts;
  starts.push_back(options.static_pose.size() == nz ? options.static_pose
                                                    : model->DefaultCoordinates());
  if (had_track) starts.push_back(z_good);
  // The points are turned so that the lab's vertical is the model's (lab_to_model).
  const Eigen::Vector3d up = options.model_up.normalized();
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
  if (hyps.empty()) {
    init.reason = "the root cannot be placed";
    return false;
  }
  auto Best = [&] {
    int b = 0;
    for (size_t i = 1; i < hyps.size(); ++i)
      if (hyps[i].score < hyps[b].score) b = static_cast<int>(i);
    return b;
  };
  // Variants: the best placement with the joints of the static pose perturbed. A few limbs can
  // settle in a wrong but self-consistent configuration (a ghost standing in for a wrist
  // marker); starting them elsewhere lets the right configuration win on its score.
  {
    const Eigen::VectorXd base = hyps[Best()].z;
    const Eigen::VectorXd& pose = starts[0];
    // First the static pose blended towards the middle of each joint's range (bent elbows and
    // knees: the wrist markers of a straight arm sit, 7 cm apart, along the very direction in
    // which a 15 degree elbow flexion moves them, so a straight start pairs each with the
    // other's point), then random perturbations.
    std::mt19937 rng(12345);
    std::uniform_real_distribution<double> u(-1.0, 1.0);
    const double blends[] = {0.1, 0.2, 0.3};
    const int blend_count = options.init_variants > 0 ? 3 : 0;
    for (int v = 0; v < blend_count + options.init_variants; ++v) {
      Eigen::VectorXd z = pose;
      for (int i = 0; i < nz; ++i) {
        const Coordinate& co = model->coordinates()[i];
        if (root_free[i]) {
          z[i] = base[i];
        } else if (!rotational[i]) {
          continue;
        } else if (v < blend_count) {
          if (co.max_value - co.min_value < 2 * M_PI)
            z[i] += blends[v] * (0.5 * (co.min_value + co.max_value) - z[i]);
        } else {
          z[i] += options.init_variant_rad * u(rng);
        }
      }
      hyps.push_back(Icp(z, np));
    }
  }
  init.hypotheses = static_cast<int>(hyps.size());
  const int best = Best();
  const Hypothesis& h = hyps[best];
  init.best_score = h.score;
  init.rms_m = h.rms;
  init.labelled = h.labelled;
  // Unambiguous: no hypothesis that labels >= 3 markers differently comes close.
  double runner_up = std::numeric_limits<double>::infinity();
  for (const Hypothesis& o : hyps) {
    int differ = 0;
    for (int m = 0; m < nm; ++m) differ += o.assignment[m] != h.assignment[m];
    if (differ >= 3) runner_up = std::min(runner_up, o.score);
  }
  init.runner_up_score = std::isfinite(runner_up) ? runner_up : 0.0;
  if (h.labelled < options.init_min_fraction * nm_seen) {
    init.reason = "too few markers labelled";
    return false;
  }
  if (!(h.rms <= options.init_max_rms_m)) {
    init.reason = "residual too large";
    return false;
  }
  const double variance = std::max(h.rms * h.rms / 3.0, 1e-6);
  if (runner_up < options.init_ambiguity_ratio * h.score ||
      runner_up - h.score < options.init_ambiguity_margin * variance) {
    init.reason = "ambiguous";
    return false;
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
  // The search's labels are all measured at once (they were chosen together, not one by one).
  for (int m = 0; m < nm; ++m) {
    measured[m] = row_to_col[m] >= 0;
    labelled_run[m] = measured[m] ? 2 : 0;
    if (measured[m]) {
      last_point.col(m) = points.col(row_to_col[m]);
      last_predicted.col(m) = predicted.col(m);
    }
  }
  double nis = 0;
  if (!FilterUpdate(&nis)) {
    init.reason = "the first update failed";
    return false;
  }
  zbuf = x.head(nz);
  Wrap(&zbuf);
  x.head(nz) = zbuf;
  out.nis = nis;
  out.nis_dof = 3 * out.labelled;
  std::fill(unlabelled_run.begin(), unlabelled_run.end(), 0);
  tracked_frames = 0;
  hist_size = 0;
  prev_np = 0;
  std::fill(held_run.begin(), held_run.end(), 0);
  init.accepted = true;
  init.reason.clear();
  return true;
}


// ---------------------------------------------------------------------------------------------
// Local re-acquisition of a limb. While the rest of the body tracks, a limb can settle in a wrong
// but self-consistent pose (a foot left with its heel marker only, a thigh turned about its long
// axis after a re-initialisation) from which its other markers' gates never meet their points
// again. When a marker has been unlabelled for kLimbFrames tracking frames, the subtree of the
// joint that moves it is searched again ICP-like among the points the rest of the body did not
// take, from its current pose and a few restarts; a clearly better, unambiguous placement that
// keeps the limb's present labels replaces the limb's coordinates, with their velocities and
// accelerations zeroed and their covariance reset to the initialisation's. Allocation-free.
namespace {
constexpr int kLimbFrames = 20;        // 0.1 s at 200 Hz
constexpr int kLimbIterations = 10;
constexpr double kLimbFinalRadius = 0.05;
constexpr double kLimbMaxRms = 0.03;
constexpr double kRejoinRadius = 0.05;    // RejoinAtOffset: twice a nominal model's marker error
constexpr double kLimbNearRadius = 0.25;  // an unclaimed point this near a due marker
constexpr double kLimbCentreTolerance = 0.02;
}  // namespace

// Assigns the limb's markers among the candidate points by distance at z (within radius);
// lassign receives compact point indices (or -1); returns the truncated cost.
// Predictions and Jacobians of the limb's markers only.
void Tracker::Impl::LineariseLimb(int joint, const Eigen::VectorXd& z) {
  ForwardKinematics(*model, geometry, z, &data);
  for (int m : limb_markers[joint]) {
    predicted.col(m) = MarkerPosition(*model, geometry, data, m) +
                       data.segment_rotation[model->markers()[m].segment] * offset[m];
    MarkerJacobian(*model, geometry, data, m, &jac[m], static_cast<Eigen::Matrix3Xd*>(nullptr));
  }
}

double Tracker::Impl::LimbAssign(int joint, const Eigen::VectorXd& z, int nc, double radius) {
  LineariseLimb(joint, z);
  const double r2 = radius * radius;
  // The limb's labelled markers keep their points: only its unlabelled ones are assigned.
  double total = 0;
  int ns = 0;
  for (int m : limb_markers[joint]) {
    if (row_to_col[m] >= 0 && !FreshTrack()) {
      lassign[m] = row_to_col[m];
      total += std::min(r2, (points.col(row_to_col[m]) - predicted.col(m)).squaredNorm());
    } else {
      lfree[ns++] = m;
    }
  }
  if (ns == 0) return total;
  auto C = cost.topLeftCorner(ns, nc + ns);
  for (int r = 0; r < ns; ++r) {
    const int m = lfree[r];
    for (int c = 0; c < nc; ++c) {
      const double d2 = (points.col(lcand[c]) - predicted.col(m)).squaredNorm();
      C(r, c) = d2 < r2 ? d2 : kForbidden;
    }
    C.row(r).tail(ns).setConstant(kForbidden);
    C(r, nc + r) = r2;
  }
  total += lap.Solve(C, lrow_to_col.data());
  for (int r = 0; r < ns; ++r)
    lassign[lfree[r]] = lrow_to_col[r] < nc ? lcand[lrow_to_col[r]] : -1;
  return total;
}

bool Tracker::Impl::ReacquireLimb(int joint, int np) {
  const std::vector<int>& rows = limb_markers[joint];
  const std::vector<char>& freec = limb_coord[joint];
  const int ns = static_cast<int>(rows.size());
  const std::vector<int>& lcoords = limb_coord_list[joint];
  const int nl = static_cast<int>(lcoords.size());
  if (ns < 2 || nl < 1 || nl > kMaxLimbCoords) return false;
  for (int l = 0; l < nl; ++l) llocal[lcoords[l]] = l;
  lsaved = predicted;
  struct Restore {  // llocal back to all -1 and the predictions back, on every return
    Impl& s;
    const std::vector<int>& c;
    ~Restore() {
      for (int i : c) s.llocal[i] = -1;
      s.predicted = s.lsaved;
    }
  } restore{*this, lcoords};
  // Candidates: the points no marker took (the limb's labelled markers keep theirs).
  std::fill(ltaken.begin(), ltaken.begin() + np, 0);
  for (int m = 0; m < nm; ++m)
    if (row_to_col[m] >= 0) ltaken[row_to_col[m]] = 1;
  int current = 0;
  for (int m : rows) current += row_to_col[m] >= 0;
  if (FreshTrack())
    for (int m : rows)
      if (row_to_col[m] >= 0) ltaken[row_to_col[m]] = 0;
  int nc = 0;
  for (int k = 0; k < np; ++k)
    if (!ltaken[k]) lcand[nc++] = k;
  if (nc == 0 || current == ns) return false;

  const double prior_rot = 0.01 * 0.01 / (0.5 * 0.5), prior_trans = 0.01 * 0.01 / (1.0 * 1.0);
  auto Cost = [&](const Eigen::VectorXd& zz) {
    ForwardKinematics(*model, geometry, zz, &data);
    double c = 0;
    for (int m : rows)
      if (lassign[m] >= 0)
        c += (MarkerPosition(*model, geometry, data, m) +
              data.segment_rotation[model->markers()[m].segment] * offset[m] -
              points.col(lassign[m]))
                 .squaredNorm();
    for (int i = 0; i < nz; ++i)
      if (freec[i])
        c += (rotational[i] ? prior_rot : prior_trans) * (zz[i] - lstart[i]) * (zz[i] - lstart[i]);
    return c;
  };
  lz0 = x.head(nz);
  std::mt19937 rng(777);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  const int starts = 5;
  double best = std::numeric_limits<double>::infinity(), runner_up = best;
  int best_labelled = 0;
  double best_sum = 0;
  for (int v = 0; v < starts; ++v) {
    lstart = lz0;
    for (int i = 0; i < nz; ++i) {
      if (!freec[i] || !rotational[i]) continue;
      const Coordinate& co = model->coordinates()[i];
      if (v == 1 || v == 2) {
        if (co.max_value - co.min_value < 2 * M_PI)
          lstart[i] += (v == 1 ? 0.25 : 0.5) * (0.5 * (co.min_value + co.max_value) - lstart[i]);
      } else if (v > 2) {
        lstart[i] += options.init_variant_rad * u(rng);
      }
    }
    Wrap(&lstart);
    lz = lstart;
    double lambda = 1e-3;
    for (int it = 0; it < kLimbIterations; ++it) {
      const double radius = std::max(kLimbFinalRadius, 0.15 - 0.01 * it);
      LimbAssign(joint, lz, nc, radius);
      lN.setZero(nl, nl);
      lg.setZero(nl);
      for (int m : rows) {
        if (lassign[m] < 0) continue;
        const Eigen::Vector3d r = predicted.col(m) - points.col(lassign[m]);
        const std::vector<int>& cols = model->marker_coordinates(m);
        const auto& J = jac[m];
        for (size_t a = 0; a < cols.size(); ++a) {
          const int la = llocal[cols[a]];
          if (la < 0) continue;
          lg[la] += J.col(a).dot(r);
          for (size_t k = 0; k < cols.size(); ++k)
            if (llocal[cols[k]] >= 0) lN(la, llocal[cols[k]]) += J.col(a).dot(J.col(k));
        }
      }
      for (int l = 0; l < nl; ++l) {
        const int i = lcoords[l];
        const double w = rotational[i] ? prior_rot : prior_trans;
        lN(l, l) += w;
        lg[l] += w * (lz[i] - lstart[i]);
      }
      const double c0 = Cost(lz);
      bool accepted = false;
      for (int tries = 0; tries < 6 && !accepted; ++tries) {
        lNd = lN;
        lNd.diagonal() += lambda * lN.diagonal();
        lllt.compute(lNd);
        if (lllt.info() != Eigen::Success) {
          lambda *= 10;
          continue;
        }
        lstep = lllt.solve(lg);
        ltrial = lz;
        for (int l = 0; l < nl; ++l) ltrial[lcoords[l]] -= lstep[l];
        Wrap(&ltrial);
        if (Cost(ltrial) < c0) {
          lz = ltrial;
          lambda = std::max(1e-7, lambda * 0.3);
          accepted = true;
        } else {
          lambda *= 10;
        }
      }
    }
    const double score = LimbAssign(joint, lz, nc, kLimbFinalRadius);
    int labelled = 0;
    double sum = 0;
    for (int m : rows)
      if (lassign[m] >= 0) {
        ++labelled;
        sum += (points.col(lassign[m]) - predicted.col(m)).squaredNorm();
      }
    int differ = 0;
    if (std::isfinite(best))
      for (int m : rows) differ += lassign[m] != lbest_assign[m];
    if (score < best) {
      if (differ >= 2) runner_up = best;
      best = score;
      best_labelled = labelled;
      best_sum = sum;
      lbest = lz;
      for (int m : rows) lbest_assign[m] = lassign[m];
    } else if (differ >= 2) {
      runner_up = std::min(runner_up, score);
    }
  }
  if (best_labelled <= current) return false;
  const double rms = std::sqrt(best_sum / best_labelled);
  if (!(rms <= kLimbMaxRms)) return false;
  // Every marker of the placement, kept or new, within its own gate on the measurement noise
  // alone (what it would be gated with once the limb's covariance has shrunk again): an RMS
  // within kLimbMaxRms also passes a placement that puts one marker on a ghost 3 cm away.
  LineariseLimb(joint, lbest);
  for (int m : rows)
    if (lbest_assign[m] >= 0 &&
        (points.col(lbest_assign[m]) - predicted.col(m)).squaredNorm() >
            options.gate_chi2 * MeasurementVariance(m))
      return false;
  // A new label on a point that has been around without keeping its distance to the marker's
  // joint centre is a lasting ghost (a lone finger marker's two angles fit any point at the right
  // distance from the wrist).
  for (int m : rows)
    if (lbest_assign[m] >= 0 && row_to_col[m] < 0 &&
        (NonRigidTrack(m, points.col(lbest_assign[m])) ||
         SeenBeside(m, lbest_assign[m], np)))
      return false;
  const double variance = std::max(rms * rms / 3.0, 1e-6);
  if (std::isfinite(runner_up) && runner_up - best < options.init_ambiguity_margin * variance)
    return false;
  // Accept: the limb's coordinates at rest at the found pose, their covariance reset.
  for (int i = 0; i < nz; ++i) {
    if (!freec[i]) continue;
    const bool r = rotational[i];
    const double s[3] = {
        r ? options.init_sigma_rotational : options.init_sigma_translational,
        r ? options.init_sigma_velocity_rotational : options.init_sigma_velocity_translational,
        r ? options.init_sigma_acceleration_rotational
          : options.init_sigma_acceleration_translational};
    x[i] = lbest[i];
    x[nz + i] = 0;
    x[2 * nz + i] = 0;
    for (int blk = 0; blk < 3; ++blk) {
      const int idx = blk * nz + i;
      P.row(idx).setZero();
      P.col(idx).setZero();
      P(idx, idx) = s[blk] * s[blk];
    }
  }
  return true;
}

// Whether point p lies at marker m's distance from its segment's joint centre (within the
// marker's noise and the predicted centre's error): a segment turns about its joint, so that
// distance is the one thing about a marker that no error in the segment's angles changes. The
// Mahalanobis gate is long along the directions an uncertain joint angle moves the marker; a
// point of the neighbouring segment can sit inside it (a finger marker's gate, its hand held by
// that marker alone, over a wrist marker's point 4-5 cm nearer the wrist) and the filter then
// bends the limb to keep it. The root's origin is as uncertain as the root itself: not tested.
bool Tracker::Impl::OnSegmentSphere(int m, const Eigen::Vector3d& p) const {
  const int segment = model->markers()[m].segment;
  if (marker_depth[m] == 0) return true;
  const Eigen::Vector3d centre = centre_now[segment];
  const double radius = (predicted.col(m) - centre).norm();
  const double tol = std::sqrt(options.gate_chi2 * (MeasurementVariance(m) + model_error[m])) +
                     kJointCentreTolerance;
  return std::abs((p - centre).norm() - radius) <= tol;
}

// Whether point k could be marker m with m's segment anywhere: within kLimbNearRadius of its
// prediction, and at m's distance from the segment's other labelled markers and from its joint
// centre (rigid-body distances, whatever the pose). Ghosts near the body are nearly always within
// the radius; few also sit on these spheres, so a hidden marker rarely sets off a search.
bool Tracker::Impl::RigidlyPlausible(int m, int k) const {
  const Eigen::Vector3d p = points.col(k), pm = predicted.col(m);
  if ((p - pm).squaredNorm() >= kLimbNearRadius * kLimbNearRadius) return false;
  const int segment = model->markers()[m].segment;
  const double var_m = MeasurementVariance(m);
  // The joint centre is predicted, not measured: allow for the parent's pose and for a nominal
  // model's joint centres.
  const Eigen::Vector3d centre = data.segment_position[segment];
  if (std::abs((p - centre).norm() - (pm - centre).norm()) >
      std::sqrt(options.gate_chi2 * var_m) + kLimbCentreTolerance)
    return false;
  for (int a = 0; a < nm; ++a) {
    if (a == m || row_to_col[a] < 0 || model->markers()[a].segment != segment) continue;
    const double tol = std::sqrt(options.gate_chi2 * (var_m + MeasurementVariance(a)));
    if (std::abs((p - points.col(row_to_col[a])).norm() - (pm - predicted.col(a)).norm()) > tol)
      return false;
  }
  return true;
}

void Tracker::Impl::Reacquire(int np) {
  ++tracked_frames;
  for (int m = 0; m < nm; ++m) unlabelled_run[m] = row_to_col[m] < 0 ? unlabelled_run[m] + 1 : 0;
  // One search per frame: the largest limb (nearest the root) among those due, and only when an
  // unclaimed point lies near the marker's prediction (a hidden marker costs nothing).
  int joint = -1;
  bool claimed_known = false;
  for (int m = 0; m < nm; ++m) {
    const int run = unlabelled_run[m];
    if (run < kLimbFrames || run % kLimbFrames != 0 || marker_limb[m] < 0) continue;
    if (!claimed_known) {
      std::fill(ltaken.begin(), ltaken.begin() + np, 0);
      for (int k = 0; k < nm; ++k)
        if (row_to_col[k] >= 0) ltaken[row_to_col[k]] = 1;
      claimed_known = true;
    }
    bool near = false;
    for (int k = 0; k < np && !near; ++k)
      near = !ltaken[k] && (FreshTrack() ? (points.col(k) - predicted.col(m)).squaredNorm() <
                                               kLimbNearRadius * kLimbNearRadius
                                         : RigidlyPlausible(m, k));
    if (!near || RejoinAtOffset(m, np)) continue;
    if (joint < 0 || marker_limb[m] < joint) joint = marker_limb[m];  // parents come first
  }
  if (joint >= 0) ReacquireLimb(joint, np);
}

// A marker back from an occlusion outside its gate, where the pose it is predicted from carries
// a nominal model's error that its learnt offset no longer matches (a knee marker in a deep
// squat, an elbow marker in a shoulder circle: 25-40 mm off, and steadily so), while the rest of
// the limb is tracked, so the limb search finds no better pose. Its point is recognised by its
// past instead of its place: the one unclaimed point within kRejoinRadius of the prediction that
// has been followed for kMinTrackFrames at a constant distance from the marker's joint centre
// (rigid with the segment) and was never seen beside the marker (SeenBeside: not a reflection
// that came with it). The marker's offset is moved onto that point; the next frame's gate takes
// it, through probation like any returning marker. Not in a fresh track, whose pasts are not
// judged.
bool Tracker::Impl::RejoinAtOffset(int m, int np) {
  if (FreshTrack()) return false;
  const int found = OnlyFreePointNear(predicted.col(m), kRejoinRadius * kRejoinRadius, np);
  if (found < 0) return false;
  double spread = 0;
  if (TrackBack(m, points.col(found), &spread) < kMinTrackFrames || spread > kRigidTolerance ||
      SeenBeside(m, found, np))
    return false;
  const int segment = model->markers()[m].segment;
  offset[m] += data.segment_rotation[segment].transpose() * (points.col(found) - predicted.col(m));
  return true;
}

// ---------------------------------------------------------------------------------------------

Tracker::Tracker(std::shared_ptr<const Model> model, TrackerOptions options) : impl_(new Impl) {
  impl_->options = std::move(options);
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
  s.last_time = time_s;

  if (out.state == TrackState::kTracking) {
    s.Predict(dt);
    s.zbuf = s.x.head(s.nz);
    s.Linearise(s.zbuf);
    for (size_t i = 0; i < s.centre_now.size(); ++i) s.centre_now[i] = s.data.segment_position[i];
    s.LabelByGating(np);
    s.PickUpOnSegment(np);
    const int labelled = s.ApplyLabels(np);
    s.ChooseMeasurements();
    double nis = 0;
    bool ok = s.measured_count == 0 || s.FilterUpdate(&nis);
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
  const bool same_segments = model->num_segments() == old.num_segments();
  // What the labelling has learnt of the points does not depend on the model: the probation runs,
  // the 20-frame history, the seen-beside records, the held runs and the last frame's points. A
  // swap that wiped them left the next frame without a measurement (every marker back on
  // probation) and restarted the ghost protections; so they are carried over the re-allocation.
  auto measured = std::move(s.measured);
  auto labelled_run = std::move(s.labelled_run);
  auto unlabelled_run = std::move(s.unlabelled_run);
  auto last_point = std::move(s.last_point);
  auto last_predicted = std::move(s.last_predicted);
  auto hist_points = std::move(s.hist_points);
  auto hist_count = std::move(s.hist_count);
  auto hist_claimed = std::move(s.hist_claimed);
  auto hist_centre = std::move(s.hist_centre);
  const int hist_head = s.hist_head, hist_size = s.hist_size;
  auto beside_prev = std::move(s.beside_prev);
  auto held_run = std::move(s.held_run);
  auto prev_points = std::move(s.prev_points);
  auto prev_free = std::move(s.prev_free);
  auto prev_free_list = std::move(s.prev_free_list);
  const int prev_np = s.prev_np, prev_free_count = s.prev_free_count;
  s.SetModel(std::move(model));
  s.Allocate();
  s.measured = std::move(measured);
  s.labelled_run = std::move(labelled_run);
  s.unlabelled_run = std::move(unlabelled_run);
  s.last_point = std::move(last_point);
  s.last_predicted = std::move(last_predicted);
  s.hist_points = std::move(hist_points);
  s.hist_count = std::move(hist_count);
  s.hist_claimed = std::move(hist_claimed);
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
  s.prev_np = prev_np;
  s.prev_free_count = prev_free_count;
  // The new model's markers are where the fit put them: forget the old model's corrections, but
  // trust the new positions more than a nominal model's.
  s.ClearOffsets(s.options.swap_offset_count);
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
