// Private to the tracker: the state and workspace that ekf/tracker.cpp (the filter and the
// frame's sequence), ekf/tracker_labelling.cpp (which point is which marker) and
// ekf/tracker_initialisation.cpp (finding the subject without labels, and a limb again) share.
// Not installed, not included outside ekf/. See ekf/tracker.h for the design.
#pragma once

#include <Eigen/Cholesky>
#include <Eigen/Core>
#include <algorithm>
#include <cmath>
#include <limits>
#include <memory>
#include <vector>

#include "ekf/assignment.h"
#include "ekf/filter.h"
#include "ekf/tracker.h"
#include "model/kinematics.h"

namespace mocap::ekf::internal {
// The cost of a pair the gate excludes (finite: see assignment.h).
inline constexpr double kForbidden = 1e9;
// A point that continues a marker's first point after a gap moves as the prediction does within
// this (a frame is 5 ms: 1 cm is 2 m/s of unpredicted motion; random ghosts jump decimetres).
inline constexpr double kProbationDistance = 0.01;
// Following a point back in time (NonRigidTrack): its largest step between frames (5 m/s at
// 200 Hz), the frames it must have been seen to be judged, and how much its distance to a joint
// centre may vary on a rigid segment (noise, and the predicted centre's error).
inline constexpr double kTrackStep = 0.025;
inline constexpr int kMinTrackFrames = 5;
inline constexpr double kRigidTolerance = 0.01;
// RigidWithSegment: how far the followed point must have moved for its rigidity to count.
inline constexpr double kRegistrationTravel = 0.02;
// How long the record of a point seen beside a marker holds (SeenBeside): about the longest life
// of a stray reflection.
inline constexpr double kBesideSeconds = 2.0;
// DropLabelsAMateFitsBetter: how much better (in the rigid fit's chi-square) a mate must fit a
// point for the marker's label to be left empty: a likelihood ratio of e^(1/2). Seed 13's wrist
// marker on its drifted mate's point: 1.8-3.4 better as the mate; seed 31's wrist marker back
// 17 mm from its prediction on its own point: 0.4 better as the mate, a difference of offsets.
inline constexpr double kMateFitMargin = 1.0;
// The error of a predicted joint centre (a nominal model's centres are 1-2 cm off).
inline constexpr double kJointCentreTolerance = 0.02;
// The chi-square value with `dof` degrees of freedom that has the tail probability of the 3-dof
// `gate_chi2` (Wilson and Hilferty 1931: (x/k)^(1/3) is nearly normal, mean 1 - 2/(9k), variance
// 2/(9k); within 2 % of the exact quantile from 3 dof up at the 1e-3 tail). A gate on a fit's
// whole cost, where each residual's own gate lets one outlier through spread over the others.
inline double ChiSquareAtGateTail(double gate_chi2, int dof) {
  const double z = (std::cbrt(gate_chi2 / 3.0) - 1.0 + 2.0 / 27.0) / std::sqrt(2.0 / 27.0);
  const double a = 2.0 / (9.0 * dof);
  const double c = 1.0 - a + z * std::sqrt(a);
  return dof * c * c * c;
}
inline constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
// Two markers of one segment this near (unscaled) are stacked on one point (StackedOnOnePoint,
// model/model.h; the fit's FitOptions::stacked_marker_tolerance_m is the same).
inline constexpr double kStackedTolerance = 0.001;

}  // namespace mocap::ekf::internal

namespace mocap::ekf {

using namespace internal;  // the shared constants, for the members' defaults

struct Tracker::Impl {
  // --- model ---
  std::shared_ptr<const Model> model;
  TrackerOptions options;
  Geometry geometry;
  ModelData data;
  int nz = 0, nm = 0;
  // Per marker: whether the tracker labels it (not in options.unseen_markers, not stacked with
  // another marker of its segment); how many it labels.
  std::vector<char> seen;
  int nm_seen = 0;
  // Turns the lab's vertical (options.up) onto the model's (options.model_up): every input point
  // goes through it, so the model's root angles describe a subject standing as the model stands
  // whatever the lab's axes (an upside-down lab would need pelvis tilt and list near 180 degrees,
  // outside their ranges, which the search and the filter keep to).
  Eigen::Matrix3d lab_to_model = Eigen::Matrix3d::Identity();
  std::vector<char> rotational, wraps;
  // Per coordinate: the information its range gives (12 / width^2: the inverse variance of a
  // uniform distribution over it; 0 without a finite range). An update whose measurements tell a
  // coordinate something, but less than that (the diagonal of J^T R^-1 J, an upper bound on what
  // they tell it with the others free), leaves it, its velocity and its acceleration where the
  // prediction put them (FilterUpdate): what such a measurement would move it by is the
  // measurements' systematic error, seen through a lever too short to resolve it (tracker.h,
  // "Weakly observed coordinates").
  std::vector<double> range_information;
  Eigen::VectorXd marker_variance;  // sigma_m^2 / w_m
  // Online marker offsets (see tracker.h): per marker, in its segment's frame, and how many
  // frames have contributed since the last (re)initialisation.
  std::vector<Eigen::Vector3d> offset;
  // The part of marker_offset_sigma^2 still unknown: the offset estimate's variance over the
  // prior's (LearnOffsets).
  std::vector<double> offset_unknown;
  // Per marker, the offset's prior (standard deviation per coordinate): marker_offset_sigma, the
  // nominal model's error; for a marker the start labelled on a model scaled to the subject,
  // what the scaled placement left unexplained (TryInitialise).
  std::vector<double> offset_sigma;
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
  std::vector<int> coordinate_depth, marker_depth, segment_depth;
  int max_depth = 0;

  // --- state ---
  Eigen::VectorXd x;  // [z; z'; z'']
  Eigen::MatrixXd P;
  Eigen::VectorXd jerk_psd;
  // The process noise learnt from the innovations (tracker.h, "Process noise"): per coordinate,
  // the factor on jerk_psd, and the spectral densities it gives (jerk_psd_now, what Predict
  // uses).
  std::vector<double> q_scale;
  Eigen::VectorXd jerk_psd_now;
  // Per marker: the trace of its predicted position's covariance J P_zz J^T (ComputeGates).
  std::vector<double> prediction_trace;
  // Per coordinate, this frame's measured markers' squared innovations and predicted spreads
  // (with the measurement variances), each weighted by the part the prediction makes of its
  // spread, and those weights and the markers' count, each marker's shared among the
  // coordinates of its chain as they make its predicted covariance (FilterUpdate).
  Eigen::VectorXd q_innovation, q_predicted, q_weight, q_count;
  // A hidden marker's gate (tracker.h, "Hidden markers' gates"; ComputeGates, HiddenScale): per
  // marker, the factor on its prediction's covariance while it is not labelled, learnt
  // (LearnHiddenScale) from the forecasts every update makes of where each marker's prediction
  // would be kHiddenHorizonSeconds on were it hidden from then (ForecastHidden): a ring of
  // hidden_horizon_frames slots, each stamped with the update count it was made at (-1: none).
  static constexpr double kHiddenHorizonSeconds = 0.25;
  static constexpr double kMinHiddenScale = 1.0 / 16;
  static constexpr double kHiddenScaleSeconds = 0.5;
  std::vector<double> hidden_scale;
  // Per marker: the nearest ancestor segment with markers the tracker sees (-1: none, the
  // root's markers; not learnt), in whose frame its forecast is judged, and which of its chain's
  // coordinates lie below that segment (its own: what moves it when it alone is hidden), as
  // indices into its chain (marker_coordinates).
  std::vector<int> hidden_anchor;
  std::vector<std::vector<int>> hidden_own;
  int hidden_horizon_frames = 0;  // 0: fewer than kUnobservedFrames at the rate (not learnt)
  // 40 Hz and up: the rates at which a frame's motion is a small part of a joint's range and the
  // hidden markers' forecasts run. The learnt process noise's matching (FilterUpdate) and the
  // weakly observed coordinates' rule (tracker.h) split on the same rate; below it the prediction
  // makes the gates and a frame's weak measurement is still the best evidence of its motion.
  bool HighRate() const { return hidden_horizon_frames > 0; }
  int hidden_count = 0;
  std::vector<int> hidden_made;
  std::vector<Eigen::Matrix3Xd> hidden_point;
  std::vector<Eigen::VectorXd> hidden_spread;
  Eigen::Matrix3d hidden_phi = Eigen::Matrix3d::Identity();
  double hidden_unit_qvar = 0, hidden_dt = 0;
  Eigen::VectorXd hidden_z;
  ModelData hidden_data;
  // The factor on a hidden marker's prediction covariance in its gate: the learnt one over the
  // horizon the forecasts cover, back to 1 over as long again (past the horizon they say nothing:
  // a limb that stood still may have started moving).
  double HiddenScale(int m) const {
    if (!HighRate()) return 1.0;
    const double beyond = static_cast<double>(unlabelled_run[m] - hidden_horizon_frames) /
                          hidden_horizon_frames;
    return hidden_scale[m] + (1.0 - hidden_scale[m]) * std::clamp(beyond, 0.0, 1.0);
  }
  void ForecastHidden(double dt);
  void LearnHiddenScale(double dt);
  // Moves each q_scale towards the factor that makes its share of the innovations as large as
  // the predicted covariance says, over process_noise_time_constant_s.
  void LearnProcessNoise(double dt);
  double last_time = kNaN;
  bool had_track = false;
  int unfit_searches = 0;  // searches in a row refused for the model's size (init_scale_after_s)
  ModelOrigin origin = ModelOrigin::kGeneric;  // the model's (ekf/tracker.h): how a start scales it
  std::vector<double> segment_fit_chi2;  // ChiSquareAtGateTail(gate_chi2, dof), by dof
  Eigen::VectorXd z_good;  // last pose that passed the divergence test
  Eigen::VectorXd z_static;  // the search's starting pose (options.static_pose or the default)
  int bad_frames = 0;
  TrackOutput out;
  InitialisationSummary init;

  // --- per-frame workspace (sized in Allocate) ---
  std::vector<int> valid;  // input indices of the finite points, compacted
  Eigen::Matrix3Xd points;
  Eigen::VectorXd zbuf, dz;
  Eigen::VectorXd x_prior;  // FilterUpdate: the prediction, for the coordinates it leaves there
  Eigen::Matrix3Xd predicted;
  std::vector<Eigen::Matrix<double, 3, Eigen::Dynamic>> jac;
  Eigen::Matrix<double, 3, Eigen::Dynamic> jp;
  std::vector<Eigen::Matrix3d> s_inv;
  // The gate of a marker not labelled in the last frame with its prediction's part scaled by
  // HiddenScale: the gate test only (LabelByGating); the densities and the other tests read s_inv.
  std::vector<Eigen::Matrix3d> s_inv_hidden;  // valid where hidden_gated (HiddenScale < 1)
  std::vector<char> hidden_gated;
  std::vector<double> reject_sq;
  std::vector<int> gated_by;  // per point: how many markers' gates hold it
  Eigen::MatrixXd cost;
  std::vector<int> row_to_col;
  std::vector<int> assigned;  // LabelByGating: the assignment before undecided labels are dropped
  LinearAssignment lap;
  Eigen::MatrixXd A;
  Eigen::VectorXd b;
  CoordinateUpdate update;
  // Probation of a marker coming back (see tracker.h): per marker, whether this frame's update
  // uses its label, how many consecutive frames it has been labelled, and where its point and
  // prediction were in the last frame.
  std::vector<char> measured;
  std::vector<int> labelled_run;
  // The provisional window (ReviewProvisionalLabels): per marker, the rival point it is compared
  // with (where it was in the last frame), the frames they have been compared over, and the sums
  // of the two points' rigid residuals (RigidResidual) over them. The window covers an occlusion
  // (5-30 frames in the simulated scenes) after a wrong label was given; a rival is judged over
  // kRivalFrames of its track (a single-frame ghost is none); it must fit the marker's distances
  // within kRivalFit (a nominal model's toe marker: 14 mm off; a wrist marker's point taken for
  // the finger marker's on a mispredicted wrist centre: 14-25 mm), and either with half the RMS
  // residual (kRivalRatio of the mean square) of a label itself off by kRivalFloor or more (a
  // nominal model's right labels are 1-3 mm off their distances), or at half the RMS distance
  // from where the marker was of a label 2 cm or more from there (kPriorFloor). The radius: a
  // toe marker's own point came back 116 mm from the reflection it had been placed on (seed 4).
  // SwapModel restarts all of it (the distances are the model's).
  static constexpr int kProvisionalFrames = 40;
  static constexpr int kRivalFrames = 5;
  static constexpr double kRivalRadius = 0.15;
  static constexpr double kRivalRatio = 0.25;
  static constexpr double kRivalFloor = 0.005;
  static constexpr double kRivalFit = 0.015;
  Eigen::Matrix3Xd rival_last;
  std::vector<int> rival_frames;
  std::vector<double> own_residual, rival_residual;
  // Per point of this frame: a marker's (ReviewProvisionalLabels, then WithholdDoubtfulReturns).
  std::vector<char> claimed_now;
  // Where each marker's point last was while its label was committed, and where it was when the
  // present window began: relative to its joint centre, in its parent segment's frame (a marker
  // hidden for a few frames is near there; a placement that moved it by decimetres is not
  // evidence against that). And per marker the window's sums of the squared distances from that
  // place of its point and of its rival.
  Eigen::Matrix3Xd committed_rel, window_rel;
  std::vector<char> has_committed_rel, has_window_rel;
  std::vector<double> own_prior, rival_prior;
  static constexpr double kPriorFloor = 0.02;
  // Marker m's segment's parent (-1: the root's), for the frame of committed_rel.
  int ParentSegment(int m) const {
    return model->joints()[model->segments()[model->markers()[m].segment].joint].parent;
  }
  void ReviewProvisionalLabels(int np);
  // The mean square, over marker m's anchors (its joint centre, its segment's labelled markers),
  // of the difference between p's distance to each and the marker's predicted distance (both
  // fixed on a rigid segment, whatever its pose); NaN without anchors.
  double RigidResidual(int m, const Eigen::Vector3d& p) const;
  Eigen::Matrix3Xd last_point, last_predicted;
  int measured_count = 0;
  // Whether the subject stood still between the last frame and this one (ChooseMeasurements): the
  // median displacement of the markers measured in both is within kStillDisplacement plus
  // kStillSpeed x dt. Only then are the offsets learnt as a mean (LearnOffsets).
  bool subject_still = false;
  double frame_dt = 0;
  std::vector<double> moved_buf;
  static constexpr double kStillDisplacement = 0.002;
  static constexpr double kStillSpeed = 0.1;
  void ChooseMeasurements();
  // TrackerOptions::min_return_probability: the density of unclaimed points near the body (per
  // m^3, averaged over clutter_time_constant_s; negative until a tracking frame measured it), and
  // the reported labels of markers on their first frame back that clutter explains about as well.
  double clutter_density = -1;
  // The same for the lasting reflections: unclaimed points near the body that continue an
  // unclaimed point of the last frame. A marker whose gate grew while it was hidden does not take
  // such a point afresh when a lasting reflection explains it about as well (LabelByGating).
  double lasting_clutter_density = -1;
  // Whether marker m, taking afresh point k that continues an unclaimed track, is less likely to
  // be on it than a lasting reflection is (min_return_probability against
  // lasting_clutter_density).
  bool LastingClutterExplains(int m, int k, int np) const;
  // N(e; 0, S_m): the density of a point at innovation e under marker m's prediction (per m^3).
  double PredictionDensity(int m, const Eigen::Vector3d& e) const {
    return std::pow(2 * M_PI, -1.5) * std::sqrt(std::max(s_inv[m].determinant(), 0.0)) *
           std::exp(-0.5 * e.dot(s_inv[m] * e));
  }
  void WithholdDoubtfulReturns(int np, double dt);
  // The last kHistory tracking frames' points and predicted joint centres (a ring), to follow a
  // point back in time (NonRigidTrack).
  static constexpr int kHistory = 20;
  std::vector<Eigen::Matrix3Xd> hist_points;
  std::vector<int> hist_count;
  std::vector<std::vector<char>> hist_claimed;  // per frame, per point: a marker's
  std::vector<std::vector<int>> hist_marker_point;  // per frame, per marker: its point or -1
  std::vector<std::vector<Eigen::Vector3d>> hist_centre;
  std::vector<Eigen::Vector3d> centre_now;  // this frame's predicted joint centres
  int hist_head = 0, hist_size = 0;
  void PushHistory(int np);
  bool NonRigidTrack(int m, const Eigen::Vector3d& p) const;
  // Follows p back (see NonRigidTrack): the frames it was seen, and the spread of its distance
  // to marker m's joint centre over them.
  int TrackBack(int m, const Eigen::Vector3d& p, double* spread) const;
  // The point of history slot `slot` a point at q continues: the nearest within a frame's motion
  // (kTrackStep) that no marker claimed then, or that was `own` (a marker's own label); -1 none.
  int PastPoint(int slot, const Eigen::Vector3d& q, int own) const;
  // Which markers each unclaimed point has been seen beside (see SeenBeside): per point of the
  // last good frame, per marker, the last tracking frame in which that marker was measured on
  // another point while this point's track was alive (kNever: not within its track).
  static constexpr int kNever = std::numeric_limits<int>::min() / 2;
  std::vector<int> beside_prev, beside_now;
  // This frame's labels left empty because the segment's rigid geometry fits the point better as
  // a mate (DropLabelsAMateFitsBetter): (point, marker) pairs, entered in the point's record as if
  // seen beside the marker (PushHistory), so that the verdict follows the point's track into the
  // frames whose anchors are too few to give it again. Sized nm in Allocate.
  std::vector<std::pair<int, int>> doubted;
  int doubted_count = 0;
  // Deferred labels (tracker.h, "Deferred labels"): per marker, the points the start could not
  // tell apart by its segment's rigid distances within the model's distance error, followed
  // frame by frame until their motion decides. Each candidate's point in the last frame, whether
  // its track still lives, whether its distance to an anchor (a mate labelled at the deferral)
  // changed by more than kRigidTolerance (then it is not on the segment), and those distances at
  // the deferral. `point`: this frame's point continuing each candidate (MatchDeferrals), -1 none.
  static constexpr int kDeferCandidates = 4;
  static constexpr int kDeferAnchors = 4;
  struct Deferral {
    int n = 0;  // candidates; 0: the marker's label is not deferred
    int frames = 0;
    Eigen::Vector3d at[kDeferCandidates];
    int point[kDeferCandidates];
    char alive[kDeferCandidates];
    char ruled_out[kDeferCandidates];
    int lived[kDeferCandidates];  // frames its track was followed
    int died[kDeferCandidates];   // the deferral's frame it was lost in

    int anchor[kDeferAnchors];
    int nanchors = 0;
    double d0[kDeferCandidates][kDeferAnchors];
    // Each distance's mean over blocks of kStillBlockSeconds: the first block's (the reference,
    // `mean0`, once `blocks` > 0) and the running block's sum and count.
    double mean0[kDeferCandidates][kDeferAnchors];
    int blocks[kDeferCandidates][kDeferAnchors];
    double sum[kDeferCandidates][kDeferAnchors];
    int count[kDeferCandidates][kDeferAnchors];
    int decided = -1;  // the one candidate left when the others are ruled out or gone
  };
  std::vector<Deferral> deferral;
  // A candidate lost for this long is gone (longer than the occlusions of a marker in view: the
  // simulated gaps are 5-30 frames, 25-150 ms at 200 Hz).
  static constexpr double kDeferGoneSeconds = 0.2;
  // A standing subject sways a few millimetres, under kRigidTolerance; a distance's mean over a
  // block of frames (the noise of one frame's divided by the block's root length) shows it: a
  // candidate whose block mean distance to an anchor differs from its first block's by more than
  // kStillTolerance is not on the segment.
  static constexpr double kStillBlockSeconds = 0.1;
  static constexpr double kStillTolerance = 0.001;
  // Follows each deferred marker's candidates into this frame (nearest within kTrackStep) and
  // says which is decided; ends a deferral none of whose candidates is left.
  void MatchDeferrals(int np);
  // After the frame's labels: each live candidate's distances to the anchors labelled now; a
  // deferral ends when its marker has held a label kHeldFrames with no other candidate alive, or
  // after kBesideSeconds (about the longest life of a stray reflection).
  void JudgeDeferrals();
  // Whether marker m may not take point k: k continues a candidate of m's deferral that is not
  // the decided one, or the decided one is hidden (m waits for it).
  bool DeferralExcludes(int m, int k) const {
    const Deferral& d = deferral[m];
    if (d.n == 0) return false;
    if (d.decided >= 0 && !d.alive[d.decided]) return true;  // its point hidden: nothing else
    for (int c = 0; c < d.n; ++c)
      if (d.alive[c] && d.point[c] == k && c != d.decided) return true;
    return false;
  }
  // Per marker: its longest run of labelled frames since the (re)initialisation.
  std::vector<int> held_run;
  // Per marker: moved by the segment registration from one point to another this frame
  // (RegisterSegments), so that next frame the point continuing its track stays its label
  // outside the gate (LabelByGating).
  std::vector<char> registered;
  // A marker has held its point once its held_run spans kHeldSeconds (20 frames at 200 Hz; at
  // least 2): in the track's first second its seen-beside records then count (SeenBeside). In
  // seconds, not frames: 20 frames are 0.4 s at 50 Hz, longer than a static start's first
  // occlusions, and a toe marker labelled for 13 frames (0.26 s) and hidden for 2 was not kept
  // from the lab-fixed reflection 11 cm away that it had been seen beside all along; it took it
  // and kept it for 54 frames (simulated seed 15 at 50 Hz).
  static constexpr double kHeldSeconds = 0.1;
  int HeldFrames() const {
    return std::max(2, static_cast<int>(std::lround(kHeldSeconds * options.rate_hz)));
  }
  // LastingClutterExplains' "held" is still kHeldFrames frames: in seconds (2 frames at 12.5 Hz)
  // it changed EkfTracker.LearntProcessNoiseLabelsALowFrameRate's run at the bound's noise (434
  // -> 475 wrong) and nothing at 50-100 Hz.
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
  // A point that continues a label's track but that an unlabelled marker of another segment
  // explains better is left empty (LabelByGating).
  void LeaveHandedOffPointsEmpty(int np);
  std::vector<int> handoff_rivals;  // its unlabelled markers (sized nm in Allocate)
  bool SeenBeside(int m, int k, int np) const;
  // Marker m held a wrong point: its seen-beside records (made under that label) go, and the
  // label no longer counts as held.
  void ForgetRecords(int m) {
    for (size_t j = static_cast<size_t>(m); j < beside_prev.size(); j += nm) beside_prev[j] = kNever;
    held_run[m] = 0;
  }

  // sigma_m^2 / w_m plus what is not yet known of the marker's offset.
  double MeasurementVariance(int m) const {
    const double s0 = offset_sigma[m], s1 = options.marker_offset_floor;
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
    std::fill(offset_sigma.begin(), offset_sigma.end(), options.marker_offset_sigma);
  }
  void SetModel(std::shared_ptr<const Model> m);
  void Allocate();
  void ResetState();
  double Dt(double time_s) const;
  void Predict(double dt);
  void Linearise(const Eigen::VectorXd& z);
  void LabelByGating(int np);
  // The gates (s_inv, reject_sq, prediction_trace) of every marker at the present
  // linearisation and P.
  void ComputeGates();
  // LabelByGating's parts: the optimal assignment of a frame where a point lies in two gates, and
  // the fresh labels whose point a segment's rigid geometry gives to a mate, left empty.
  void AssignContested(int np);
  void DropLabelsAMateFitsBetter(int np);
  // Segment registration (see tracker.h, "Labelling"): per segment, its seen markers (depth
  // order: parents first), and the workspace of the enumeration.
  std::vector<std::vector<int>> segment_markers;
  std::vector<int> segment_order;
  static constexpr int kSegmentCandidates = 4;   // unclaimed points tried per unlabelled marker
  static constexpr int kSegmentMaxOpen = 6;      // markers enumerated per segment
  static constexpr int kSegmentMaxFreed = 2;     // labelled markers re-opened in one hypothesis
  static constexpr int kMaxSegmentMarkers = 16;  // larger segments are not registered
  // Per open marker: its unclaimed candidates, plus the points of the re-opened labelled mates.
  static constexpr int kSegmentMaxChoices = kSegmentCandidates + kSegmentMaxFreed + 1;
  static constexpr int kStuckFrames = 20;        // a marker unlabelled this long is stuck
  // Rigid fits (SegmentFitCost) per frame, over all segments: the bound on the registration's
  // time (a search cut short by it decides nothing).
  static constexpr int kSegmentFitBudget = 600;
  // ... of which one segment's re-check may take (the forearm's takes about 30; a trunk segment's
  // many markers at one distance from its joint would take the whole budget, often).
  static constexpr int kReCheckFitBudget = 100;
  struct SegmentSearch {
    int open[kSegmentMaxOpen];                         // the markers enumerated (ms order)
    int cand[kSegmentMaxOpen][kSegmentMaxChoices];     // their candidate points
    int ncand[kSegmentMaxOpen];
    int choice[kSegmentMaxOpen];
    int nopen = 0;
    // The segment's unlabelled markers and their unclaimed candidates (nearest first).
    int unl[kSegmentMaxOpen], unl_cand[kSegmentMaxOpen][kSegmentCandidates], unl_n[kSegmentMaxOpen];
    int nunl = 0;
    // The best labelling of the segment's markers (ms order; point or -1), its label count and
    // cost, and the least cost of a different labelling with as many labels.
    int best_point[kMaxSegmentMarkers];
    int best_labels = 0;
    double best_cost = 0, runner_up = 0;
    int fits = 0;  // this frame's
    int fit_limit = 0;  // where the enumeration stops
  } seg;
  // Enumerates segment `segment` with its unlabelled markers and the labelled ones in `freed`
  // (indices into its marker list) open; updates seg.best_* and seg.runner_up. False when the
  // frame's fit budget ran out.
  bool EnumerateSegment(int segment, const int* freed, int nfreed);
  // Whether a stuck marker's segment has its labels re-checked this frame: every frame of the
  // marker's first kStuckFrames stuck (before another marker takes the point a swap left over),
  // then every kStuckFrames-th (a check every frame of a long run cost the p99 about 15 %).
  bool ReCheckDue(int m) const {
    const int run = unlabelled_run[m];
    return run >= kStuckFrames && (run < 2 * kStuckFrames || run % kStuckFrames == 0);
  }
  void RegisterSegments(int np);
  // Whether point k, followed back through the unclaimed points of the last frames, has been for
  // kMinTrackFrames or more at constant distances (within kRigidTolerance) from marker m's joint
  // centre and from each labelled marker of its segment: rigid with the segment over time.
  bool RigidWithSegment(int m, int k) const;
  // What that past shows: shorter than kMinTrackFrames; a distance that changed; rigid but with
  // less travel than kRegistrationTravel (a reflection fixed in the lab is rigid with a segment at
  // rest); or rigid over that travel.
  enum class PastWithSegment { kShort, kNotRigid, kStill, kRigid };
  PastWithSegment SegmentPast(int m, int k) const;
  // The rigid fit of segment `segment` with `labelling` (per marker of segment_markers[segment]:
  // its point, or -1): false when fewer than 3 anchors or an anchor lies outside its tolerance;
  // else *cost = sum of squared residuals over the anchors' variances.
  bool SegmentFitCost(int segment, const int* labelling, double* cost) const;
  // How far a marker may lie from where its segment's rigid fit puts it: its gate on its own
  // variance, plus the predicted joint centre's error.
  double SegmentTolerance(int m) const {
    return std::sqrt(options.gate_chi2 * (MeasurementVariance(m) + model_error[m])) +
           kJointCentreTolerance;
  }
  // Rigid-group labelling of loose segments (LabelLooseSegments; tracker.h, "Rigid groups"): a
  // segment whose best-held marker's prediction is uncertain over more than half the distance to
  // its nearest neighbouring marker (12 Hz: a swinging shank or foot 4-11 cm off its prediction,
  // its markers 5-6 cm apart) has its markers labelled as one rigid body about its joint centre,
  // the prediction only a prior. Per segment: whether it was so labelled this frame, and the pose
  // the group's fit found (world = R local + t, local in the segment's frame about its joint
  // centre), which places its children's joint centres (centre_now) for their own groups.
  std::vector<char> segment_loose, segment_fitted, segment_wants_fit;
  std::vector<Eigen::Matrix3d> fit_rotation;
  std::vector<Eigen::Vector3d> fit_translation, centre_predicted;
  std::vector<double> centre_variance;  // per segment: of centre_now (m^2)
  static constexpr int kGroupCandidates = 5;  // points tried per marker, nearest (Mahalanobis) first
  // Labels a group's labelling must give: with the joint centre, four anchors, so that the fit
  // is over-determined. Two markers and the centre fix only three distances, which a mirror image
  // fits as well (a simulated forearm turned about its axis, its wrist markers 40 mm off their
  // predictions at 200 Hz: one wrist marker took the other's long-held point, 202 frames wrong on
  // seed 9 at 8 ghosts).
  static constexpr int kMinGroupLabels = 3;
  // The group's labelling is taken when every differently labelling pose costs this much more
  // (twice a log-likelihood ratio); where the runner-up comes nearer, only the labels the two
  // agree on are the group's.
  static constexpr double kGroupMargin = 6.0;
  // A segment is labelled as a group only while the track holds it: a marker of it labelled
  // within this time.
  static constexpr double kGroupRecentSeconds = 0.5;
  void LabelLooseSegments(int np);
  bool LooseSegment(int segment) const;
  // A segment pose's fit (FitSegmentPose): the anchors' weighted centroid, their weights' sum
  // and the covariance of the fit's rotation (NaN where the anchors do not fix it), which say how
  // well the fit places a point carried with the segment (PlacedVariance).
  struct FitPrecision {
    Eigen::Vector3d centroid = Eigen::Vector3d::Zero();
    double weight = 0;
    Eigen::Matrix3d rotation_covariance = Eigen::Matrix3d::Zero();
  };
  std::vector<FitPrecision> fit_precision;
  bool FitSegmentPose(int segment, Eigen::Matrix3d* R, Eigen::Vector3d* t, FitPrecision* fit) const;
  // The variance (per coordinate) of point q placed by segment's last pose fit: the fit's
  // translation and its rotation's error carried out to q. NaN where the rotation is not fixed.
  double PlacedVariance(int segment, const Eigen::Vector3d& q) const;
  // The segment whose fitted pose places a loose segment's joint centre: its parent or, past
  // segments without seen markers (a talus between a shank and a foot: no fit of its own), the
  // nearest ancestor with markers; -1 at the root.
  int PlacingSegment(int segment) const;
  int ApplyLabels(int np);
  bool FilterUpdate(double* nis, double dt);
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
  // The optimal assignment of the seen markers at tree depth <= depth to the points within
  // `radius` of their predictions (Linearise first), a marker free to stay unassigned at
  // radius^2: *assign (size nm) gets each marker's point or -1; returns the truncated cost.
  double AssignWithin(int np, double radius, int depth, std::vector<int>* assign);
  // `held`: an assignment held for the first kHeldIterations steps (ExchangeLabels).
  Hypothesis Icp(Eigen::VectorXd z, int np, const std::vector<int>* held = nullptr);
  static constexpr int kHeldIterations = 15;
  // Tries the best hypothesis with each pair of its labels whose points lie within
  // kExchangeRadius exchanged; appends what it refines to *hyps and returns the index of the
  // best it kept (see the definition).
  int ExchangeLabels(std::vector<Hypothesis>* hyps, int best, int np);
  // The whole search at the present geometry (TryInitialise): the best hypothesis, or -1 with
  // init.reason set.
  int Search(int np, std::vector<Hypothesis>* hyps);
  static constexpr const char* kTooFewLabelled = "too few markers labelled";
  static constexpr const char* kResidualTooLarge = "residual too large";
  // Fits per-segment scales and the pose to h's points and sets the geometry to them (see the
  // definition). With `held`, to that labelling alone (no reassignment), the fitted pose and
  // the labelled markers' RMS distance written to *fitted (z, rms) and each labelled marker's
  // distance to *distance (0 for the others); returns the fit's truncated cost (a seen marker
  // left unlabelled counts the search's final radius squared).
  double ScaleToSubject(const Hypothesis& h, int np, const std::vector<int>* held = nullptr,
                        Hypothesis* fitted = nullptr, std::vector<double>* distance = nullptr);
  static constexpr int kScaleIterations = 20;
  // The search's weak prior on coordinate i (m^2 per rad^2 / per m^2: 1 cm per half a radian or
  // per metre): pins what the markers leave free.
  double SearchPrior(int i) const { return rotational[i] ? 0.01 * 0.01 / (0.5 * 0.5) : 0.01 * 0.01; }
  // At the last Linearise (at z): N = sum J^T J + w W and g = sum J^T r + w W (z - centre) over
  // the markers labelled in `assign` (per marker: its point or -1), W the search's prior.
  void LabelNormalEquations(const std::vector<int>& assign, const Eigen::VectorXd& z,
                            const Eigen::VectorXd& centre, double prior_weight, Eigen::MatrixXd* N,
                            Eigen::VectorXd* g) const;
  // The labels' squared distances at z plus the prior's (over the coordinates `free` marks; all
  // when nullptr).
  double LabelCost(const std::vector<int>& assign, const Eigen::VectorXd& z, const Eigen::VectorXd& centre,
                   double prior_weight, const std::vector<char>* free);
  // Damped Gauss-Newton on the fixed labels `assign` (per marker: its point or -1) from *z, with
  // the search's weak prior centred at `centre`, within the joint ranges; returns the cost.
  double HeldFit(Eigen::VectorXd* z, const Eigen::VectorXd& centre, const std::vector<int>& assign,
                 int iterations);
  static constexpr int kHeldFitIterations = 10;
  // The start's labels that alone turn their limb, where a second configuration is at hand, left
  // empty and h refitted without them (see the definition); returns how many.
  int LeaveSelfDecidedLabelsEmpty(Hypothesis* h, int np);
  // The start's labels whose segment's rigid distances (to its joint centre and its labelled
  // mates, each within the model's distance error) fit an unclaimed point better: left empty in
  // h, deferred with their candidates (TryInitialise). Returns how many.
  int DeferAmbiguousStartLabels(Hypothesis* h, int np);
  // The start's prior's mode for a placement z: the static pose, the root where z has it.
  Eigen::VectorXd StaticPoseAt(const Eigen::VectorXd& z) const;
  // h's labels of the markers `empty` marks left empty, and h refitted without them (HeldFit,
  // the prior centred at `centre`): the limbs go where their other markers and the prior put
  // them. Returns how many labels it emptied.
  int LeaveLabelsEmpty(Hypothesis* h, const std::vector<char>& empty, const Eigen::VectorXd& centre);
  // h's labelled count and their RMS distance from the predictions of the last Linearise.
  void CountLabels(Hypothesis* h) const;
  // The least a scaled start's offsets' prior may be (m; TryInitialise).
  static constexpr double kScaledOffsetSigmaFloor = 0.01;
  // The scales stay within [1 / kScaleLimit, kScaleLimit] of the model's own: a humerus 33 % long
  // (the first limit tried, 0.75-1.33) fits an arm's markers shifted one along the arm (simulated
  // seeds 19, 40, 48: the elbow marker on the forearm's point, that one on the wrist's).
  static constexpr double kScaleLimit = 1.18;
  // The geometry's parameters (the model's own, or the subject's scales ScaleToSubject found).
  Eigen::VectorXd geometry_params;
  void SetGeometry(const Eigen::VectorXd& p) {
    geometry_params = p;
    geometry.Set(*model, p);
  }
  static constexpr double kExchangeRadius = 0.10;

  // Local re-acquisition of a limb (see tracker.h): per marker, consecutive tracking frames
  // without a label; per joint, the coordinates and markers of its subtree; per marker, the
  // joint whose subtree is searched again when it stays unlabelled. Workspace sized in Allocate.
  std::vector<int> unlabelled_run, marker_limb;
  // Per marker, tracking frames without a label that lasted past its first frame: a label
  // dropped after one frame (a guess the next frame's gate or registration took back) does not
  // end a marker's being stuck, as it ends its unlabelled run (LimbLabelsInDoubt).
  std::vector<int> stuck_run;
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
  // Per joint: the joints whose child segments move with its limb's coordinates (its subtree,
  // and any joint a limb coordinate also drives, with what hangs below), parents first. The limb
  // search places only these (ForwardKinematics over a joint list) after placing the whole body
  // once: at 5 starts of 10 steps, a pass over the whole body per trial pose was most of its time.
  std::vector<std::vector<int>> limb_joint_list;
  std::vector<int> llocal;  // per coordinate: its index among the limb's, or -1
  void LineariseLimb(int joint, const Eigen::VectorXd& z);
  std::vector<int> lcand, lassign, lbest_assign, lrow_to_col, lfree, lheld;
  // ltaken: per point, a marker's; lunanchored: per coordinate, in a search for a limb with no
  // label, whether no marker below its joint is labelled (ReacquireLimb starts it across its
  // range, and past it by kLimbRangeSlack).
  std::vector<char> ltaken, lunanchored;
  void Reacquire(int np);
  // The limb searched for a stuck marker m: marker_limb[m], or when none of that limb's markers
  // is labelled, the smallest subtree above it that holds a labelled marker (within
  // kMaxLimbCoords). A limb with no label has no pose of its own to start from, and its parent's
  // pose is only as good as the markers that hold it: a forearm flexed 90 degrees turns the
  // upper arm's estimate about its long axis, which the elbow markers alone hold loosely.
  int AnchoredLimb(int m) const;
  // Frames tracked since the last (re)initialisation. The labels of a fresh track come from a
  // search over one frame and can be wrong on a whole limb (self-consistently: a thigh turned
  // about its long axis); labels that tracking has kept are not. So for the first second a limb
  // search may relabel the limb's markers and is tried whenever any unclaimed point is near;
  // after it, it keeps the labels the limb has and is tried only for a point at the rigid-body
  // distances of the marker (RigidlyPlausible).
  int tracked_frames = 0;
  bool FreshTrack() const { return tracked_frames < options.rate_hz * kFreshTrackSeconds; }
  static constexpr double kFreshTrackSeconds = 1.0;
  // `except`: a labelled marker whose point k is, left out of the distances (LimbLabelsInDoubt).
  bool RigidlyPlausible(int m, int k, bool anywhere = false, int except = -1) const;
  bool UnpinnedMarkerWithoutPast(int m, int k, const std::vector<int>& placement) const;
  bool NewThisFrame(int k) const;
  bool Followable(int m) const;
  // Labelled mates that pin a marker's place on its segment in a frame (not only its distances).
  static constexpr int kPinningMates = 3;
  bool OnSegmentSphere(int m, const Eigen::Vector3d& p) const;
  // `unheld`: searched for a marker whose own limb has no label (AnchoredLimb). `relabel`: a
  // re-check (LimbLabelsInDoubt): the limb's labelled markers may be moved, as in a fresh track.
  bool ReacquireLimb(int joint, int np, bool place, bool unheld, bool relabel = false);
  // The limb re-check (tracker.h, "Limb re-acquisition"): the limb of a marker stuck for
  // kStuckFrames beside a point one of its limb's labelled markers holds, where that point is
  // the stuck marker's by the rigid geometry (RigidlyPlausible without the holder): a limb
  // labelled one marker round (a wrist marker on the other's point, the finger marker on the
  // freed one) keeps every label on a point and no gate ever sees it. -1: none this frame.
  int LimbLabelsInDoubt(int np) const;
  bool recheck_waited = false;  // a re-check gave way to another limb's search when last due
  // Markers a re-check moved to another point this frame: their seen-beside records were made
  // under the wrong labels and go after this frame's are pushed (PushHistory).
  std::vector<char> relabelled;
  // Per marker: labelled this frame outside its gate (not measured: its limb is placed anew).
  std::vector<char> beyond_gate;
  // Per coordinate: whether the last update's measurements observed it (pinned it: see
  // kObservedSigmas), and for how many consecutive frames they have not (see Predict).
  std::vector<char> observed;
  std::vector<int> unobserved_frames;
  static constexpr double kUnobservedSeconds = 0.05;
  static constexpr int kUnobservedFrames = 10;
  // A coordinate counts as observed when the frame's measurements alone pin it within this many
  // of its initialisation sigmas (init_sigma_rotational / _translational: 0.1 rad, 2 cm). Tried
  // on seeds 1, 3, 6, 44, 48 (5 ghosts, 10 %): at 1 and 0.5 seed 3 fell below its test's 0.9995
  // (0.99947, 0.99950 from 0.99953); at 2 it holds (0.99958) and seed 44 gains as much (0.980 ->
  // 0.996).
  static constexpr double kObservedSigmas = 2.0;
  double LimbAssign(int joint, const Eigen::VectorXd& z, int nc, double radius);
  // Whether this limb search may move the limb's labels: in a fresh track, or a re-check.
  bool lrelabel = false;
  bool LimbRelabels() const { return lrelabel || FreshTrack(); }
};

}  // namespace mocap::ekf
