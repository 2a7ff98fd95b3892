// The simulated session: a virtual subject (sim/subject.h) performs every movement of a protocol
// (sim/protocol.h) in front of a perfect-but-noisy capture system, giving marker trajectories
// with KNOWN true coordinates and geometry — what accuracy is measured against.
//
// Motion (per movement, from the protocol's data):
//   - every excited coordinate follows  neutral + env(t) (centre - neutral + amp s(t)),
//     s a sinusoid and amp = half-range plus a small margin, so the range is reached; env is a
//     quintic (C2) ramp 0 -> 1 -> 0 over the excitation's window, so each movement starts and
//     ends in the neutral pose. Leaders get periods period_s / r_k with r_k irrational ratios
//     (1, 1.618, 1.325, ...), so several coordinates excited together (the "circles") trace
//     Lissajous figures that cover their 2-D range rather than one closed curve. If the window's
//     plateau is shorter than a period the movement's periods are shortened together, so every
//     required range is reached at any duration_scale. Followers share their leader's s(t).
//   - every other coordinate wanders a little about the neutral pose (two sinusoids of random
//     phase, a few degrees; arms 20 deg away from the body, elbows 15 deg and knees 4 deg bent).
//   - the pelvis faces a random direction and stands at a random place per movement, with a few
//     degrees of tilt/list/yaw wander and a few cm of horizontal sway and drift. Its height is
//     set every frame so the lowest point of the feet (a sole 0.039 x height below the ankle
//     centre, Winter) touches the floor z = 0, and its horizontal position compensates the
//     motion of the foot that carries the weight — so a squat lowers the pelvis and the stance
//     foot does not skate when the other leg swings.
// Markers: forward kinematics of the TRUE model, plus
//   - soft-tissue artefact (sta_mm > 0): marker m on segment S moves, in S's frame, by
//     B_m (q_adj - mean q_adj), with q_adj the rotational coordinates of the joints adjacent to S
//     (its own proximal joint unless it is the root, and its child joints) and B_m a random
//     3 x k matrix scaled so that the RMS length of the displacement is sta_mm x ratio(m) in the
//     movement that moves the marker most (and less in the others): smooth, correlated with the
//     joint angles. ratio(m) comes from the marker's class in the STA table (sim/sta_table.h,
//     sim/default_sta_table.json, with its sources): 1 for a thigh wand, 0.6-0.8 for the other
//     soft-tissue markers, 0.25 for bony landmarks, 1 for a marker the table does not name. So
//     sta_mm is the artefact of soft tissue (the thigh's), not of every marker: skin over a
//     malleolus does not move like skin over the quadriceps;
//   - Gaussian noise of standard deviation noise_mm on each coordinate, independent per sample;
//   - occlusions (missing > 0): gaps of 5..30 frames at random markers and times until that
//     fraction of the trial's marker samples is NaN.
// Every random choice uses its own stream (sim/random.h): the same options give bit-identical
// sessions, and e.g. the noise does not change the motion.
#pragma once
#include <Eigen/Core>
#include <cstdint>
#include <string>
#include <vector>

#include "formats/marker_data.h"
#include "model/model.h"
#include "model/status.h"
#include "sim/protocol.h"
#include "sim/random.h"
#include "sim/subject.h"

namespace mocap::sim {

struct SimulationOptions {
  std::uint64_t seed = 1;
  double noise_mm = 0.5;        // standard deviation per coordinate
  // Soft-tissue artefact: RMS of a thigh marker in its most active movement, mm; every other
  // marker gets sta_mm x its class's ratio in DefaultStaTable() (bony landmarks a quarter).
  double sta_mm = 0.0;
  double missing = 0.0;         // fraction of marker samples lost, in [0, 0.9)
  double rate_hz = 100.0;
  double duration_scale = 1.0;  // multiplies each movement's duration: more cycles, same speeds
  bool medial_markers = false;  // also simulate the optional medial knee/ankle markers
  SubjectOptions subject;

  // False, with a message naming the option, for values the simulator cannot honour.
  bool IsValid(std::string* error) const;
};

struct SimulatedTrial {
  // Marker trajectories in metres, named like the movement; missing samples are NaN. Frame
  // numbers start at 1, times at 0.
  formats::MarkerTrial markers;
  // The true coordinates per frame, OpenSim .mot convention: in_degrees = true, rotational
  // coordinates in DEGREES, translations in METRES; one column per model coordinate, in model
  // order. TrueCoordinates() converts a row back to the model's z (radians, metres).
  formats::CoordinateTable coordinates;
};

struct SimulatedSession {
  SimulationOptions options;
  double height_m = 0.0;
  // Per recorded marker (trial column order): its artefact's RMS in its most active movement,
  // mm (sta_mm x its STA table ratio).
  std::vector<double> sta_rms_mm;
  Model nominal;  // the fit's starting point, with the markers the session records
  Model truth;    // the true geometry, with the same markers
  Eigen::VectorXd truth_parameters;  // p of the truth in the nominal model's layout
  Protocol protocol;
  std::vector<SimulatedTrial> trials;  // one per protocol movement, in order

  int total_frames() const;
};

// Simulates the default protocol, or `protocol`, with the default full-body model. Fails (with
// a message) on invalid options or a protocol that does not fit the model.
Status SimulateSession(const SimulationOptions& options, SimulatedSession* session);
Status SimulateSession(const SimulationOptions& options, const Protocol& protocol,
                       SimulatedSession* session);

// Indices into `model`'s markers of the markers a simulation records: the required ones, plus the
// optional ones when `optional_markers` is set.
std::vector<int> SimulatedMarkers(const Model& model, bool optional_markers);

// The models of a simulation that records `markers` (SimulatedMarkers) of `subject`, as
// SimulatedSession holds them: the nominal and true models with exactly those markers, and the
// truth's parameters in the nominal model's layout.
struct SessionModels {
  Model nominal;
  Model truth;
  Eigen::VectorXd truth_parameters;
};
// Errors: a marker index the subject's models do not have (Model::WithMarkers).
Status MakeSessionModels(const VirtualSubject& subject, const std::vector<int>& markers,
                         SessionModels* models);

// What the simulated capture adds to true marker positions (frames x 3 markers, metres), shared by
// every simulation (this one, sim/osim_subject.h):
//   Gaussian noise of standard deviation sigma_m on each coordinate, independent per sample;
void AddMarkerNoise(double sigma_m, Random& rng, formats::RowMatrix* positions);
//   occlusions: gaps of 5..30 frames at random markers and times, NaN, until `fraction` of the
//   samples are gone (gaps may overlap and merge; the last one may overshoot by a few samples).
void RemoveMarkerSamples(double fraction, Random& rng, formats::RowMatrix* positions);

// Row `frame` of a SimulatedTrial's coordinate table as the model's z (radians, metres).
Eigen::VectorXd TrueCoordinates(const Model& model, const formats::CoordinateTable& table,
                                int frame);

// A fit of the session held against its truth where a lab reads it: per joint of the truth, the
// RMS over every frame of every trial of the distance (mm) between the joint centre of `fitted`
// posed by `coordinates` (one matrix per trial, frames x fitted.num_coordinates(), the fit's
// poses) and the true centre of the truth posed by the true coordinates; for a hinge only the
// part across its true axis (a hinge's centre along its axis is a convention; likewise for any
// joint with one moving rotation, model/compare.h AlongAxisGaugeElement). `fitted` must
// have the truth's joints, in the same order.
std::vector<double> JointCentreTrackRmsMm(const SimulatedSession& session, const Model& fitted,
                                          const std::vector<Eigen::MatrixXd>& coordinates);
// The same for any simulation: its truth and its trials (sim/osim_subject.h).
std::vector<double> JointCentreTrackRmsMm(const Model& truth, const std::vector<SimulatedTrial>& trials,
                                          const Model& fitted, const std::vector<Eigen::MatrixXd>& coordinates);

// subject.json of `mocap sim`: seed, height, options, protocol name, markers, each marker's
// artefact amplitude (sta_rms_mm) and the movements with their frame counts and file names.
std::string SessionSummaryJson(const SimulatedSession& session);

}  // namespace mocap::sim
