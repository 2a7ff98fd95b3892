// Functional joint centres and axes from the markers of the two segments a joint connects, with
// no body model in the loop: SCoRE (symmetrical centre of rotation estimation, Ehrig et al. 2006,
// J Biomech 39:2798) for a ball joint's centre and SARA (symmetrical axis of rotation approach,
// Ehrig et al. 2007, J Biomech 40:2150) for a hinge's axis. Written here from the papers'
// equations: an estimate independent of the global fit (solver/global_fit.h), to check it against
// and to start it from.
//
// Method.
//  1. Each segment's markers are a rigid cluster. Its shape is the markers' mean configuration
//     (generalised Procrustes over the frames where every marker is seen, origin at the shape's
//     centroid); its pose in frame t, lab <- cluster (R_t, d_t), is the Kabsch fit of the shape to
//     the markers seen in t (at least 3, not on one line). Soft-tissue artefact and noise make the
//     fit's RMS (reported) non-zero.
//  2. A point fixed in both clusters (c_p in the parent's, c_c in the child's) satisfies
//         R_p,t c_p + d_p,t = R_c,t c_c + d_c,t      for every t,
//     i.e. A_t x = b_t with A_t = [R_p,t  -R_c,t] (3 x 6), x = (c_p, c_c), b_t = d_c,t - d_p,t.
//     SCoRE is the linear least-squares solution of the stacked system; the lab centre of frame t
//     is the midpoint of the two transformed points (symmetrical: neither segment is the fixed one).
//  3. For a hinge every point of the axis satisfies the system, so A = [A_t] has a one-dimensional
//     null space (n_p, n_c): the axis direction in both clusters. SARA takes the right singular
//     vector of A's smallest singular value as the axis and the least-squares solution in the
//     other five directions as the point on it (the point of the axis nearest both cluster
//     centroids in the minimum-norm sense).
// The normal matrix N = sum_t A_t^T A_t (6 x 6) and g = sum_t A_t^T b_t are all either method
// needs, so the uncertainty comes cheaply from a moving-block bootstrap over frames (blocks of
// consecutive frames, because soft-tissue artefact makes neighbouring frames' errors alike):
// the standard deviation of the estimate over resampled trials.
//
// Excitation. A joint that did not rotate cannot show its centre: N is singular along the
// directions the motion never exercised. The report gives N's condition number and the RMS spread
// of the relative rotation (child cluster in parent cluster) about its three principal axes, in
// degrees, largest first. A centre needs two axes moved (the second spread at least
// min_rotation_deg); an axis needs one. An estimate from a trial that does not excite the joint is
// returned, flagged `excited = false` with a note that says why, so a caller can refuse it.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <string>
#include <vector>

#include "formats/marker_data.h"
#include "model/model.h"
#include "model/rigid_align.h"
#include "model/status.h"

namespace mocap::solver {

struct FunctionalJointOptions {
  int min_frames = 30;                // frames in which both clusters have a pose
  double min_rotation_deg = 5.0;      // RMS spread that counts as "excited" (see above)
  int bootstrap_samples = 200;        // 0: no uncertainty
  double bootstrap_block_s = 0.25;    // block length of the bootstrap, seconds
  std::uint64_t seed = 1;             // of the bootstrap's draws: results are reproducible
  bool IsValid(std::string* error) const;
};

// The rigid poses of one marker cluster over a trial.
struct ClusterTrack {
  std::vector<int> columns;           // the trial's marker indices of the cluster
  Eigen::Matrix3Xd shape;             // mean shape, cluster frame (centroid at the origin), metres
  std::vector<RigidTransform> pose;   // per frame: lab <- cluster
  std::vector<char> valid;            // per frame: the pose was found (>= 3 markers seen)
  double rms_mm = 0;                  // RMS distance of the seen markers from the posed shape
};

// Tracks the cluster of the trial's markers `columns` (at least 3). Errors: fewer than 3 markers,
// no frame in which all of them are seen, markers all on one line.
Status TrackCluster(const formats::MarkerTrial& trial, const std::vector<int>& columns,
                    ClusterTrack* track);

// What both estimates report about the data.
struct FunctionalFit {
  int frames_used = 0;
  double residual_rms_mm = 0;         // RMS of |A_t x - b_t| over the frames used
  double condition = 0;               // sqrt(largest / smallest eigenvalue of N)
  Eigen::Vector3d rotation_spread_deg = Eigen::Vector3d::Zero();  // descending
  bool excited = false;
  std::string note;                   // why not excited (empty when excited)
};

// SCoRE: a ball joint's centre in both clusters' frames.
struct CentreEstimate {
  FunctionalFit fit;
  Eigen::Vector3d in_parent = Eigen::Vector3d::Zero();   // cluster frames, metres
  Eigen::Vector3d in_child = Eigen::Vector3d::Zero();
  Eigen::Matrix3d covariance_parent = Eigen::Matrix3d::Zero();  // bootstrap, m^2
  double std_mm = 0;                  // sqrt(trace(covariance_parent)), mm
};

// SARA: a hinge's axis (unit directions) and a point on it, in both clusters' frames.
struct AxisEstimate {
  FunctionalFit fit;
  Eigen::Vector3d direction_parent = Eigen::Vector3d::UnitX();
  Eigen::Vector3d direction_child = Eigen::Vector3d::UnitX();
  Eigen::Vector3d point_parent = Eigen::Vector3d::Zero();
  Eigen::Vector3d point_child = Eigen::Vector3d::Zero();
  double direction_std_deg = 0;       // bootstrap RMS angle from the estimate
  double point_std_mm = 0;            // bootstrap, perpendicular to the axis
};

// Both estimates from two tracked clusters of the same trial. Errors: tracks of different
// lengths, fewer than options.min_frames frames with both poses, invalid options.
Status EstimateCentre(const ClusterTrack& parent, const ClusterTrack& child, double rate_hz,
                      const FunctionalJointOptions& options, CentreEstimate* centre);
Status EstimateAxis(const ClusterTrack& parent, const ClusterTrack& child, double rate_hz,
                    const FunctionalJointOptions& options, AxisEstimate* axis);

// A joint of a model, estimated from one trial: the clusters are the model's markers on the
// joint's parent segment and on its child segment (by name, as the trial has them).
// Whether a joint is described by its axis (SARA) rather than its centre (SCoRE): a hinge, a
// universal joint, and a joint whose moving rotations all follow one or two coordinates -- an
// OpenSim knee whose translations and small coupled rotations follow its flexion angle
// (gait2354's knee, the walker knee of Rajagopal's and OpenCap's models) turns about one axis,
// and a centre needs rotation about two: on OpenCap's squats SCoRE called the walker knees "not
// excited" (1.5 deg about the second axis) while SARA has them.
bool DescribedByAxis(const Joint& joint);

struct FunctionalJoint {
  std::string joint;
  JointType type = JointType::kCustom;
  bool axis_joint = false;  // DescribedByAxis: its reference is `axis`, not `centre`
  std::string parent_segment, child_segment;
  std::vector<std::string> parent_markers, child_markers;  // the clusters' markers
  ClusterTrack parent, child;
  CentreEstimate centre;
  AxisEstimate axis;
  // The centre in the lab in frame f (midpoint of the two clusters' points); NaN where a pose is
  // missing. Likewise the axis direction (mean of the two clusters' directions).
  Eigen::Vector3d CentreInLab(int f) const;
  Eigen::Vector3d AxisInLab(int f) const;
  Eigen::Vector3d AxisPointInLab(int f) const;
};

// Errors name what is wrong: an unknown joint (and the model's joints), the root joint (its
// parent is the lab, which has no markers), a segment with fewer than 3 markers in the trial
// (naming the segment and the markers it has).
Status EstimateFunctionalJoint(const Model& model, const formats::MarkerTrial& trial,
                               const std::string& joint, const FunctionalJointOptions& options,
                               FunctionalJoint* result);

// The functional centres as data for the global fit (solver/global_fit.h): for each joint, a
// virtual marker "<joint>@functional" at the origin of the joint's child segment (which is the
// joint centre) with marker weight `weight`, and, in each trial in which the joint's centre is
// excited, that marker's samples: the SCoRE centre in the lab, frame by frame. The fit then pulls
// the model's centre towards the functional one as much as the weight says, and the marker's
// residual RMS is the distance between the two. The caller keeps the virtual markers' positions
// fixed (FitOptions::fixed_markers = *virtual_markers). A trial with too few markers on either
// segment, or that does not excite the joint, adds no samples and a line to *notes; a joint
// that no trial excites is an error; on error *model, *trials and *virtual_markers are unchanged.
Status AddFunctionalCentres(const std::vector<std::string>& joints,
                            const FunctionalJointOptions& options, double weight, Model* model,
                            std::vector<formats::MarkerTrial>* trials,
                            std::vector<std::string>* virtual_markers,
                            std::vector<std::string>* notes);

}  // namespace mocap::solver
