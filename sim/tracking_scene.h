// What the real-time tracker (ekf/tracker.h) sees, with the answers: per frame, a SHUFFLED set of
// unlabelled 3D points — the subject's markers plus noise, minus occlusions, plus ghosts — and,
// per point, which model marker it truly is (or that it is none).
//
// The subject and its movements are those of `mocap sim --seed N` (sim/simulate.h: same seed,
// same body, same motion of every movement), but joined into ONE continuous recording, as the
// live filter sees a session: each movement is moved rigidly (about the vertical and along the
// floor) so that it starts where and facing how the previous one ended, and a short transition
// (transition_s, a C2 blend of the coordinates) joins the end pose of one to the start pose of the
// next. Marker positions come from the TRUE model's forward kinematics of those coordinates.
//
// On top (each from its own random stream, sim/random.h, so e.g. adding ghosts does not move the
// occlusions):
//   - noise: Gaussian, noise_mm per coordinate, on every marker sample;
//   - occlusions: gaps of 5..30 frames at random markers and times until `occlusion` of the
//     subject's marker samples are gone (as the simulator's `missing` option);
//   - ghosts: `ghosts` points per frame within ghost_radius_m of the body's markers and at least
//     ghost_min_distance_m from every marker where they appear. A share of them
//     (persistent_ghost_fraction) are stray reflections that live 0.2..2 s, either fixed in the lab
//     or riding along with a marker (a reflection of it in something shiny); the others are
//     random points, new each frame;
//   - swap traps (swap_traps): a movement appended at the end in which markers of different
//     segments pass within a few millimetres of each other — the right and the left hand sliding
//     down the side of the thigh in a side bend (FIN past THI), the hands meeting in front of the
//     body (WRA past WRA), a hand on the hip (WRB past ASI). Each pose of closest approach is
//     solved exactly (Gauss-Newton on the arm's and trunk's coordinates) for a miss distance of
//     trap_distance_m across the markers' relative path; the arm moves past it and back, so each
//     trap gives two close passes. `traps` lists every moment (in any part of the scene) where
//     two markers truly come within 15 mm, found from the true positions, not from the plan.
//   - one fault (fault), starting at fault_time_s:
//       kAllOccluded      every marker of the subject gone for fault_duration_s (ghosts stay);
//       kLeaveAndReenter  the subject glides out of the capture volume (a box of
//                         volume_half_width_m about the origin; points outside are not seen),
//                         stays out for fault_duration_s and comes back in elsewhere, turned by
//                         ~100 degrees, and carries on from there;
//       kSecondPerson     a second simulated subject (its own seed) walks in at ~1.3 m from the
//                         subject and stays: its markers are points that are no marker of ours;
//       kNanFrame         a frame whose points are all NaN, and ten frames later a frame whose
//                         real points are interleaved with NaN columns.
//     A model whose markers do not match the data is not a property of the scene: see
//     MismatchedModel below.
#pragma once
#include <Eigen/Core>
#include <cstdint>
#include <string>
#include <vector>

#include "formats/marker_data.h"
#include "model/model.h"
#include "model/status.h"

namespace mocap::sim {

enum class SceneFault { kNone, kAllOccluded, kLeaveAndReenter, kSecondPerson, kNanFrame };
const char* ToString(SceneFault fault);  // "none", "all_occluded", "leave_reenter", ...
// Parses the names ToString gives; false for anything else.
bool ParseSceneFault(const std::string& name, SceneFault* fault);

// Labels of points that are not a marker of the subject.
constexpr int kGhostLabel = -1;
constexpr int kSecondPersonLabel = -2;
constexpr int kNanLabel = -3;  // a NaN column (kNanFrame)

struct TrackingSceneOptions {
  std::uint64_t seed = 1;       // the subject and movements of `mocap sim --seed N`
  double rate_hz = 200.0;
  double noise_mm = 0.5;
  double duration_scale = 1.0;  // of every protocol movement (sim/simulate.h)
  // Protocol movements, in the order performed; empty: the whole default protocol. The scene
  // starts with the first one: the static pose, when it is "static".
  std::vector<std::string> movements;
  double transition_s = 0.5;

  int ghosts = 0;  // per frame
  double ghost_radius_m = 0.3;
  double ghost_min_distance_m = 0.03;
  double persistent_ghost_fraction = 0.5;

  double occlusion = 0.0;  // fraction of the subject's marker samples, in [0, 0.5]

  bool swap_traps = false;
  double trap_distance_m = 0.008;

  SceneFault fault = SceneFault::kNone;
  double fault_time_s = -1.0;      // < 0: at 40 % of the scene
  double fault_duration_s = 1.0;   // all markers occluded / time spent outside the volume
  double volume_half_width_m = 2.5;

  bool IsValid(std::string* error) const;
};

// Two markers of the subject within 15 mm of each other: one entry per pair and per run of
// consecutive frames, at the frame of closest approach.
struct TrapMoment {
  int frame = 0;
  int marker_a = 0, marker_b = 0;  // indices into the scene's markers, a < b
  double distance_m = 0.0;         // true (noise-free) distance at `frame`
};
constexpr double kTrapDistanceM = 0.015;

// A named stretch of frames [begin, end).
struct SceneSegment {
  std::string name;  // a movement's name, "transition", "swap_traps"
  int begin = 0, end = 0;
};

struct TrackingScene {
  TrackingSceneOptions options;
  double height_m = 0.0;
  Model nominal;  // the session's models (sim/simulate.h), with the markers the scene shows,
  Model truth;    // in the same order
  std::vector<std::string> marker_names;  // of nominal/truth: label m names marker_names[m]
  std::vector<SceneSegment> segments;
  std::vector<TrapMoment> traps;
  int fault_begin = -1, fault_end = -1;   // frames of the fault, [begin, end); -1 without one

  std::vector<double> times;                // seconds, from 0
  std::vector<Eigen::Matrix3Xd> points;     // per frame: metres, shuffled
  std::vector<std::vector<int>> labels;     // per frame, per point: marker index or a k*Label
  formats::RowMatrix true_markers;          // frames x 3 markers: noise-free, also when unseen
  Eigen::MatrixXd true_coordinates;         // frames x truth.num_coordinates(): z (rad, m)
  long occluded_samples = 0;                // marker samples removed by `occlusion`
  long hidden_samples = 0;                  // ... by the fault (not already occluded)

  int num_frames() const { return static_cast<int>(times.size()); }
  int num_markers() const { return static_cast<int>(marker_names.size()); }
  // Samples of subject markers present among the points (what label accuracy counts).
  long visible_samples() const;
  // The points as a marker file of generic names P1..Pn (n: the most points of any frame),
  // frame f's points in its first columns and NaN after: what `mocap track --points` reads.
  formats::MarkerTrial PointsTrial(const std::string& name = "points") const;
  // The true coordinates as a .mot table (degrees), truth model's coordinate names.
  formats::CoordinateTable TrueCoordinateTable(const std::string& name = "truth") const;
};

// Builds the scene. Errors name the option (an unknown movement, a fraction out of range).
Status MakeTrackingScene(const TrackingSceneOptions& options, TrackingScene* scene);

// Label accuracy against the scene's truth, frame by frame, in the terms of the tracking targets.
struct LabelScore {
  long samples = 0;             // subject marker samples present among the points
  long correct = 0;             // ... given their own marker's label
  long wrong = 0;               // points given a label that is not theirs
  long wrong_on_ghosts = 0;     // ... of which ghosts or NaN points
  long wrong_on_second_person = 0;
  // A swap: marker m labelled on a point that is not m in consecutive frames. Runs longer than
  // 5 frames, and the longest run.
  int swaps_longer_than_5_frames = 0;
  int longest_wrong_run = 0;
  double accuracy() const { return samples > 0 ? static_cast<double>(correct) / samples : 1.0; }
};

class LabelScorer {
 public:
  explicit LabelScorer(int num_markers);
  // truth: the scene's labels of the frame's points; given[i]: the scene marker index the tracker
  // gave point i, or -1. Returns this frame's counts (runs are only counted by Finish).
  LabelScore Add(const std::vector<int>& truth, const std::vector<int>& given);
  // The totals, with the runs still open at the end closed.
  LabelScore Finish();
  // Per scene marker: its samples present, and those given its label.
  const std::vector<long>& marker_samples() const { return marker_samples_; }
  const std::vector<long>& marker_correct() const { return marker_correct_; }

 private:
  void Close(int marker);
  LabelScore total_;
  std::vector<int> run_;
  std::vector<char> wrong_now_;
  std::vector<long> marker_samples_, marker_correct_;
};

// Scene marker index of each of `model`'s markers, by name (-1 when the scene has no such marker).
std::vector<int> SceneMarkerOf(const Model& model, const TrackingScene& scene);

// A model whose markers do not match the subject's: `model` with every marker moved by
// displacement_m on its segment in a random direction (seeded), and its markers renamed with
// `prefix` when not empty. What a lab gets when the wrong subject's model or marker set is loaded.
Model MismatchedModel(const Model& model, std::uint64_t seed, double displacement_m = 0.05,
                      const std::string& prefix = "");

}  // namespace mocap::sim
