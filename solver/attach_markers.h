// Markers a trial has and the model lacks — a thigh or shank cluster a lab adds to a generic
// marker set, an extra medial marker — are data the fit would otherwise throw away, and they are
// often the best data there is (a rigid four-marker plate moves far less on the skin than one
// thigh wand). Each one is attached to the segment it rides on, found from the poses a first
// solve gives: in the frame of the segment that carries it, a marker stays put; in the frame of
// any other segment it moves as that segment's joints move. So for every segment the marker's
// position in the segment frame is taken over every frame where it is seen, and its spread (RMS
// distance from the mean) measured; the segment with the smallest spread wins if that spread is
// small (AttachOptions::max_spread_mm, the skin motion of a cluster) and clearly smaller than
// the runner-up's (min_ratio: in a trial where a joint does not move, the two segments it joins
// carry every marker alike, and a guess between them would be a silent wrong answer). The
// marker joins the model at its mean position, optional (other labs' data lack it); markers that
// no segment carries clearly are left out and named, with why.
#pragma once

#include <Eigen/Core>
#include <string>
#include <utility>
#include <vector>

#include "formats/marker_data.h"
#include "model/model.h"
#include "model/status.h"

namespace mocap::solver {

struct AttachOptions {
  double max_spread_mm = 15.0;  // a cluster's skin motion is 10-30 mm peak (Leardini et al. 2005)
  double min_ratio = 2.0;       // runner-up's spread / winner's
  // The winner's spread counts as at least this (mm, about a marker's noise): trials that move
  // no joint (a static posture: every spread 0) tell no segment from another.
  double spread_floor_mm = 1.0;
  int min_samples = 20;         // frames in which the marker and a pose are both there
  bool IsValid(std::string* error) const;
};

struct AttachedMarker {
  std::string name;
  std::string segment;       // empty when not attached
  double spread_mm = 0;      // on the chosen (or best) segment
  double runner_up_mm = 0;   // on the second best segment
  int samples = 0;
  std::string why_not;       // empty when attached
};

// Where a marker's trajectory sits on every segment: per segment, its mean position in the
// segment's frame (scaled, as measured) and its spread about that mean (RMS distance, mm), over
// every frame where the marker and a finite pose are both there (`samples`). The carrying
// segment is the one with the smallest spread; also used to diagnose a model's marker whose
// residual stays high (solver/marker_diagnosis.h).
struct MarkerOnSegments {
  std::vector<Eigen::Vector3d> mean_local;  // per segment, m
  std::vector<double> spread_mm;            // per segment
  int samples = 0;
};
// `names[i]`'s result in (*out)[i]; a name no trial has gets samples = 0.
Status MarkerSpreadOnSegments(const Model& model, const std::vector<formats::MarkerTrial>& trials,
                              const std::vector<Eigen::MatrixXd>& poses,
                              const std::vector<std::string>& names,
                              std::vector<MarkerOnSegments>* out);

// `poses[t]`: trial t's coordinates (frames x model coordinates) for `model`'s geometry. Every
// trial marker whose name `model` lacks is considered. *out: `model` with the attached markers
// appended (unscaled positions, optional); *report: every marker considered, attached or not.
Status AttachTrialMarkers(const Model& model, const std::vector<formats::MarkerTrial>& trials,
                          const std::vector<Eigen::MatrixXd>& poses, const AttachOptions& options,
                          Model* out, std::vector<AttachedMarker>* report);

// A static trial (one posture: a lab's calibration trial) moves no joint, so the rule above
// tells no segment from another: every segment carries every marker alike. What the posture does
// show is where the marker sits among the model's markers: a lab puts an extra thigh marker
// beside the thigh's, a medial knee marker across the knee from the lateral one. Each of `names`
// (trial markers the model lacks) goes to the segment of the model marker nearest to it in the
// trials (mean distance over the frames where both are seen, the data's own positions) when
// every model marker of any other segment is at least `min_ratio` times as far, and that nearest
// one is within max_distance_mm (beside it: a marker farther from every marker of the model rides
// on something the model may not have, gait2354's elbow markers on its armless torso); else it is left
// out and named, with why (biobuddy's S1, a sacral marker 129 mm from the torso's T10 and 135
// mm from the pelvis's LPSI: a guess either way). Placed as AttachTrialMarkers places (mean position in the
// segment's frame over `poses`, optional); `report` gets one entry per name, spread_mm and
// runner_up_mm there being the two distances (mm).
Status AttachMarkersByProximity(const Model& model, const std::vector<formats::MarkerTrial>& trials,
                                const std::vector<Eigen::MatrixXd>& poses, const std::vector<std::string>& names,
                                double min_ratio, double max_distance_mm, int min_samples, Model* out,
                                std::vector<AttachedMarker>* report);

// A generic model may name a lab's cluster markers without knowing where the lab puts them, and
// stack them on one point of their segment (welk007's generic model has r_thigh1..5 at one point
// of femur_r, 7-29 cm from where its lab's are; the shank's and the other thigh's alike). A fit
// that starts from those places poses the first solve to fit five markers to one point: welk007's
// standing trial came out with 70 deg ankles and a 23 deg hyperextended knee, and every scale and
// marker after it followed. Such markers carry no information about where they are, only about
// which segment they ride on, so they are treated like the trial markers the model lacks, except
// that their segment is known: left out of the first solve, then placed where the trials put them
// on that segment (PlaceMarkersOnTheirSegments).
//
// The model markers that the trials see and that share their place on a segment with another
// such marker (within tolerance_m, unscaled): indices into model.markers(), in model order.
std::vector<int> StackedMarkers(const Model& model, const std::vector<formats::MarkerTrial>& trials,
                                double tolerance_m);

struct PlacedMarker {
  std::string name;
  std::string segment;
  double from_model_mm = 0;  // distance from the model's (placeholder) place, scaled
  double spread_mm = 0;      // RMS motion about its place in the segment's frame
  int samples = 0;
  std::string why_not;       // empty when placed: else kept at the model's place
};

// `markers` (copies of model markers, e.g. StackedMarkers' from the model they came from) added
// to `model` on their own segments (by name, so `model` may be a stage's copy), each at its mean
// position in that segment's frame over the frames of `poses` (as MarkerSpreadOnSegments) when
// seen in at least options.min_samples of them, else at the place the marker gives. Unlike
// AttachTrialMarkers no spread limit applies: the segment is the model's word, and the spread is
// reported for the reader to judge.
Status PlaceMarkersOnTheirSegments(const Model& model, const std::vector<formats::MarkerTrial>& trials,
                                   const std::vector<Eigen::MatrixXd>& poses, const std::vector<Marker>& markers,
                                   const AttachOptions& options, Model* out, std::vector<PlacedMarker>* report);

// A model marker its author put on a joint centre -- OpenCap's RHJC_study and LHJC_study on the
// pelvis of its LaiUhlrich2022 model, a model made for a Plug-in Gait export's RHJC -- and that
// the trials see is not a skin marker: its trajectory is another tool's estimate of the centre
// (OpenCap's marker augmenter, a regression). Fitted as a skin marker its place on the segment
// would be free, and the fitted centre would not follow it (the OpenCap-style subject:
// a right hip 105 mm from the pipeline's own hip-centre markers); OpenSim keeps it where the
// author put it, at the centre, so its Scale and IK carry the centre with it. Tied here, it is a
// point of the centre itself: moved to the joint's child segment at its origin (the centre, in
// every pose) and its place held (FitOptions::fixed_markers), as AddFunctionalCentres's virtual
// markers are; after the fit, UntieCentreMarkers puts it back on its own segment at the fitted
// centre.
struct CentreMarker {
  std::string marker, joint;
  int segment = -1;                                   // its own segment in the model
  Eigen::Vector3d position = Eigen::Vector3d::Zero();  // its own place there (unscaled)
  double from_centre_mm = 0;                           // from the centre, the model's default pose
};

// The model markers that `trials` see and that lie within tolerance_m of a joint centre in the
// model's default pose, on that joint's parent or child segment (the nearest joint's, where two
// are that close), moved onto the centre (*model rebuilt) and named in *tied, model order.
Status TieCentreMarkers(const std::vector<formats::MarkerTrial>& trials, double tolerance_m, Model* model,
                        std::vector<CentreMarker>* tied);
// Each of `tied` back on its own segment, at its joint's centre in *fitted (the fitted centre in
// the parent's frame, or the child's origin). Errors name a marker or joint *fitted lacks.
Status UntieCentreMarkers(const std::vector<CentreMarker>& tied, Model* fitted);

// The two landmark markers about joint j (the femoral epicondyles about a knee, the malleoli
// about an ankle), found in the model's default pose by geometry, not by name (labs name them
// every way): two markers of the joint's parent or child segment 5-20 cm apart, their line within
// 30 deg of the joint's first rotation axis, their midpoint within 3.5 cm of its centre (gait2354's
// ankle is 3.2 cm below its malleoli; its patellofemoral joint, 4.5 cm from the epicondyles, is
// not theirs). Marker indices, or {-1, -1}.
std::pair<int, int> LandmarkPairAbout(const Model& model, int j);

}  // namespace mocap::solver
