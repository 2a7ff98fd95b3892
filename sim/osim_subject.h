// A simulated subject of ANY model — an imported OpenSim model with its marker set, not only our
// default one — so that the fit from a generic model can be scored against a known truth on the
// models labs bring (sim/simulate.h simulates the default model and protocol only).
//
// The truth is the generic model with its geometry perturbed the way a subject differs from it
// (sim/subject.h PerturbedParameters: segment scales, joint centres, markers on their segments,
// optionally axes; seeded). The subject does not follow a protocol of ours: it is posed by given
// coordinate trajectories — OpenSim's own output (.mot of its IK or Scale tool), so the motions
// are a real subject's, e.g. a walk that excites the hips and knees in one plane — and the
// markers are the truth's forward kinematics plus the capture's Gaussian noise and gaps
// (AddMarkerNoise, RemoveMarkerSamples: the same as `mocap sim`'s).
//
// The poses are the .mot's coordinates applied to the TRUTH: the same joint angles on different
// geometry, as a lab's subject would perform the movement. A motion must have a column for every
// coordinate of the model and no column the model does not know (formats::PosesFromTable).
#pragma once
#include <Eigen/Core>
#include <cstdint>
#include <string>
#include <vector>

#include "formats/marker_data.h"
#include "model/model.h"
#include "model/status.h"
#include "sim/simulate.h"
#include "sim/subject.h"

namespace mocap::sim {

struct OsimSubjectOptions {
  std::uint64_t seed = 1;
  // How the subject differs from the generic model: scales within +-8 %, every joint centre
  // within 10 mm and every marker within 10 mm of where the generic model has them (after
  // scaling). Axes are the generic model's (axis_deg 0) unless set. Heights are not used.
  SubjectOptions geometry{.scale_spread = 0.08, .centre_mm = 10.0, .axis_deg = 0.0, .marker_mm = 10.0};
  double noise_mm = 0.5;  // standard deviation per coordinate
  double missing = 0.0;   // fraction of marker samples lost in gaps of 5..30 frames, [0, 0.9)

  // False, with a message naming the option, for values the simulator cannot honour.
  bool IsValid(std::string* error) const;
};

// One movement to perform: the coordinate trajectories (table.name names the trial; rows give
// the frames and times, which must increase) and where they came from, for messages.
struct PrescribedMotion {
  formats::CoordinateTable table;
  std::string source;  // e.g. the .mot's path
  // The model markers the trial records, by name (a lab's walk has no medial knee markers, its
  // static trial has them); empty: every marker of the model. Virtual markers of a model (a
  // *_HJC, a midpoint) are no data: leave them out.
  std::vector<std::string> markers;
};

struct OsimSubject {
  Model generic;  // the fit's starting point: the given model, unchanged
  Model truth;    // generic.WithParameters(truth_parameters)
  Eigen::VectorXd truth_parameters;  // in the generic model's layout
  // One per motion, in order: the markers it records (model order), metres, NaN in gaps, the
  // motion's times (frame numbers from 1); the true coordinates as sim/simulate.h's trials hold
  // them (model order, rotational ones in degrees), so TrueCoordinates and JointCentreTrackRmsMm
  // apply.
  std::vector<SimulatedTrial> trials;
};

// Errors, naming the motion's source and what is wrong: invalid options, a model without
// markers, a motion without rows, with times that do not increase, a column the model lacks, a
// coordinate it has no column for, or a recorded marker the model lacks.
Status SimulateOsimSubject(const Model& generic, const std::vector<PrescribedMotion>& motions,
                           const OsimSubjectOptions& options, OsimSubject* out);

// A motion holding row `row` of `table` for `frames` frames at `rate_hz`, with only the columns
// of `model`'s coordinates (model order): a static trial from the single pose OpenSim's Scale
// tool solved, whose output (subject01_static_output.mot) is a whole state — coordinates, their
// speeds ("_u"), muscle states, marker locations ("R.ASIS_tx") — in one row. Errors name the
// table and the coordinate it lacks, a row it does not have, frames < 1 or a rate <= 0.
Status HoldPose(const Model& model, const formats::CoordinateTable& table, int row, int frames,
                double rate_hz, formats::CoordinateTable* out);

}  // namespace mocap::sim
