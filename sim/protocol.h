// The calibration protocol as DATA: the movements the subject performs for the global fit, in
// order, each with the coordinates it must excite and the range each must reach. The daemon
// checks every recording against it (CheckExcitations) and says which movement to repeat; the
// simulator (sim/simulate.h) turns the same description into motion.
//
// File format (JSON, angles in degrees):
//   {"format": "mocap-protocol", "version": 1, "name": "...",
//    "movements": [
//      {"name": "squats", "description": "...", "duration_s": 5.5,
//       "period_s": 3.0,        // optional: slowest cycle of the motion (simulator hint)
//       "background": 1.0,      // optional: how much the other joints wander (simulator hint)
//       "excitations": [
//         {"coordinate": "hip_flexion_l", "min_deg": 0, "max_deg": 90},
//         {"coordinate": "knee_angle_l", "min_deg": 0, "max_deg": 100, "follow": "hip_flexion_l"},
//         {"coordinate": "pelvis_tilt", "min_deg": -15, "max_deg": 0, "follow": "hip_flexion_l",
//          "anti_phase": true, "required": false},
//         {"coordinate": "ankle_angle_l", ..., "window": [0, 0.5]}]}]}
//
// An excitation is REQUIRED by default: the recording must cover [min_deg, max_deg]. One with
// "required": false only shapes the motion (a knee that bends a little during a hip arc, the
// pelvis that tilts in a squat). "follow" makes a coordinate move in phase with another one of
// the same movement (a squat's knees follow its hips): it reaches its min when the leader reaches
// its min (its max with "anti_phase"). "window" restricts the excitation to a part of the
// movement, as fractions of its duration (left ankle first, then right).
#pragma once
#include <string>
#include <vector>

#include "formats/marker_data.h"
#include "model/model.h"
#include "model/status.h"

namespace mocap::sim {

struct Excitation {
  std::string coordinate;  // a rotational coordinate of the model
  double min_deg = 0.0;    // the range the coordinate must reach during the movement
  double max_deg = 0.0;
  bool required = true;       // false: a motion hint, not checked
  std::string follow;         // leader coordinate in the same movement, or empty
  bool anti_phase = false;    // with follow: max when the leader is at its min
  double window_begin = 0.0;  // active part of the movement, fractions of its duration
  double window_end = 1.0;
};

struct Movement {
  std::string name;  // also the trial's name (<name>.trc)
  std::string description;
  double duration_s = 0.0;
  double period_s = 2.5;     // slowest cycle of the simulated motion
  double background = 1.0;   // scale of the other joints' wandering in the simulation
  std::vector<Excitation> excitations;

  const Excitation* Find(const std::string& coordinate) const;
};

// A part of a movement with its own required excitations (their "window"): the ankle circles
// move the left ankle in the first half, then the right. The report draws them as bands inside
// the trial's RMS strip, so a rise of the residual is seen against what the subject was moving.
struct MovementPhase {
  double begin = 0.0, end = 1.0;         // fractions of the movement's duration
  std::vector<std::string> coordinates;  // the required excitations active in it, in order
};

struct Protocol {
  std::string name;
  std::vector<Movement> movements;

  double TotalDuration() const;
  const Movement* Find(const std::string& movement) const;
};

// The movement's phases, one per distinct window of its required excitations, ordered by
// begin (then end); a movement whose excitations all span it is one phase [0, 1]. A trial is one
// movement (the daemon records one per recording, `mocap sim` writes <movement>.trc), so these
// are the only parts a trial has.
std::vector<MovementPhase> MovementPhases(const Movement& movement);

// The default full-body calibration protocol (sim/default_protocol.json, embedded at build time;
// ~60 s in total). Its coordinates are those of mocap::DefaultFullBodyModel.
const Protocol& DefaultProtocol();
const std::string& DefaultProtocolJson();

// Parse and structural validation (names, numbers, windows, follow targets). Errors name the
// source and the field: "p.json: movements[3].excitations[1].min_deg: expected a number".
Status ParseProtocolJson(const std::string& text, const std::string& source_name,
                         Protocol* protocol);
Status LoadProtocolJson(const std::string& path, Protocol* protocol);
std::string ProtocolToJsonString(const Protocol& protocol);

// Checks the protocol against a model: every excitation names a rotational coordinate of the
// model and its range lies within the coordinate's limits.
Status ValidateProtocol(const Protocol& protocol, const Model& model);

// What a recording reached for one excitation.
struct ExcitationCheck {
  std::string coordinate;
  double min_deg = 0.0, max_deg = 0.0;          // required
  double reached_min_deg = 0.0, reached_max_deg = 0.0;  // NaN when the column is absent/empty
  bool required = true;
  bool ok = false;  // reached_min <= min + tolerance and reached_max >= max - tolerance
};

// Compares a table of coordinates (a recording's IK result, or the simulator's truth) with a
// movement's excitations. Rotational columns are read in the table's unit (in_degrees).
// NaN samples are ignored. The result has one entry per excitation, in order.
std::vector<ExcitationCheck> CheckExcitations(const Movement& movement,
                                              const formats::CoordinateTable& table,
                                              double tolerance_deg = 0.0);

// How a recording is held against a movement's ranges.
struct ExcitationCheckOptions {
  double tolerance_deg = 0.0;
  // The tolerance is at least this fraction of the required span: a tracker on a model before
  // its fit reads a one-marker segment's angle (a hand with its finger marker) with a gain error
  // of several per cent (wrist flexion through 87 of the 100 deg the subject moved).
  double tolerance_fraction = 0.0;
  // < 0: the ranges are absolute (the simulator's truth). >= 0: the reached range may sit up to
  // this far from the required one, and only its span must be reached (within the tolerance).
  // For a live check with a model before its fit: the tracker's angles then carry the nominal
  // model's zero offsets (a trunk 15 deg off with markers 2 cm from where the model puts them),
  // while what identifies a joint is how far it moved, not where its model puts zero.
  double max_offset_deg = -1.0;
};
std::vector<ExcitationCheck> CheckExcitations(const Movement& movement,
                                              const formats::CoordinateTable& table,
                                              const ExcitationCheckOptions& options);

}  // namespace mocap::sim
