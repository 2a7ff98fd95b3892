// The live virtual subject: what the simulated rig's cameras see while mocapd runs. Instead of a
// whole protocol simulated in advance (sim/simulate.h, `mocap capture --simulate`), the scene does
// what the operator asks, when asked, as a person in the lab would be told:
//   - before the rig is calibrated, someone waves the wand through the empty volume
//     (WaveWand), then lays the L-frame on the floor (ShowLFrame);
//   - the subject steps in and stands still (StandStatic), and performs one movement of the
//     protocol when asked (Perform), then stands still again; a subject who does only part of a
//     movement is Perform(name, 0.4): 40 % of the excursion, so the coverage check fails.
//
// Markers (marker_count()): the subject's simulated markers (the same set and order as
// SimulateSession records: SimulatedMarkers of the truth model), then the wand's 3 markers (Wand
// order), then the L-frame's. A marker that is not in the volume is NaN (the renderer draws
// nothing for it).
//
// The motion is SimulateSession's motion generator (sim/motion.h), evaluated at the time each
// camera takes its image: a movement's coordinates are the same functions of time as in
// `mocap sim --seed N --rate R` (same seed, same movement index: same phases, periods and
// wander), except that the live subject stands at the middle of the volume facing +x instead of
// at a random place and heading per movement. Every movement starts and ends in the neutral pose
// (the simulator's quintic envelopes); at each command the new motion is blended into the old one
// over `blend_s` (a quintic ramp; shorter for a movement whose excitations ramp up faster, so
// the blend never eats into the range a short movement must reach), so the joint angles stay
// C2-continuous across commands whatever the wander was doing (the pelvis's horizontal
// correction below is interpolated linearly between frame-rate samples: continuous). The feet stay on the floor (the
// pelvis height comes from the pose, every frame) and the stance foot does not skate during a
// movement (the simulator's stance drift, integrated once per command at the frame rate, when
// the command is given); standing still, the subject steps back onto its mark in 1.5 s, since
// the drifts of successive movements add up (a hip arc moves the pelvis by up to 25 cm).
//
// Time. The renderer's scene time of frame `sequence` is (sequence - sequence_origin) / rate_hz
// (sim/renderer.h); the Aravis fakes number frames by the tick of the host's real-time clock
// (drivers/aravis_fake.h, clock_sequence_rate_hz), so scene time is real time shifted by the
// origin. SceneTimeNow() reads that clock. A command takes effect at SceneTimeNow() +
// command_lead_s, so the images the cameras have already taken do not change; its start (and end)
// scene times are returned, for the daemon to know which frames show the movement.
//
// Threads. Commands come from the daemon's thread (they are serialised among themselves);
// Positions() is called from every camera's thread. The schedule of what happens when is a short
// list of phases replaced as a whole under a mutex; a command computes its phases (allocating)
// before it takes the mutex. Positions() evaluates the pose under that mutex with workspaces
// allocated at construction, so it never allocates, and the cameras that ask for the same time
// (all of them, without timing jitter) share one forward-kinematics evaluation (cached).
#pragma once
#include <Eigen/Core>
#include <cstdint>
#include <functional>
#include <limits>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "model/kinematics.h"
#include "model/model.h"
#include "model/status.h"
#include "reconstruction/calibration.h"
#include "sim/motion.h"
#include "sim/protocol.h"
#include "sim/renderer.h"
#include "sim/subject.h"
#include "sim/wand.h"

namespace mocap::sim {

struct LiveSceneOptions {
  // The subject: the seed and options of `mocap sim` give the same person (height, truth model).
  std::uint64_t seed = 1;
  SubjectOptions subject;
  bool medial_markers = false;        // also the optional medial knee/ankle markers
  const Protocol* protocol = nullptr;  // nullptr: DefaultProtocol(); copied
  // The clock (see the header comment): rate_hz and sequence_origin are the renderer's.
  double rate_hz = 200.0;
  std::uint64_t sequence_origin = 0;
  // Host real time in ns since the epoch (the fakes' device clock); empty: CLOCK_REALTIME.
  std::function<std::uint64_t()> clock_ns;
  double command_lead_s = 0.05;  // a command takes effect this long after it is given
  double blend_s = 0.5;          // the old motion fades into the new one over this time
  // The calibration objects and the volume the wand sweeps (as WandSimulationOptions).
  reconstruction::Wand wand;
  reconstruction::LFrame lframe;
  Eigen::Vector3d wand_volume_centre_m = {0.0, 0.0, 1.0};
  Eigen::Vector3d wand_volume_half_size_m = {1.0, 1.0, 0.8};

  bool IsValid(std::string* error) const;
};

// What the volume holds at a given time.
enum class LiveActivity { kEmpty, kWand, kLFrame, kStatic, kMovement };
const char* ToString(LiveActivity activity);

class LiveScene : public Scene {
 public:
  // Fails on invalid options or a protocol that does not fit the subject's model. The scene
  // starts empty.
  static Status Create(const LiveSceneOptions& options, std::shared_ptr<LiveScene>* scene);
  ~LiveScene() override;
  LiveScene(const LiveScene&) = delete;
  LiveScene& operator=(const LiveScene&) = delete;

  // ---- Scene (the renderer's side; any thread) ----
  int marker_count() const override { return lframe_begin_ + lframe_count(); }
  // No allocation; NaN for the markers not in the volume at time_s.
  void Positions(double time_s, Eigen::Vector3d* positions) const override;

  // The marker layout: [0, subject_marker_count()) the subject (truth().markers() order), then
  // wand_marker_begin() + 0..2, then lframe_marker_begin() + 0..lframe_count()-1.
  int subject_marker_count() const { return truth_.num_markers(); }
  int wand_marker_begin() const { return truth_.num_markers(); }
  int lframe_marker_begin() const { return lframe_begin_; }
  int lframe_count() const { return static_cast<int>(options_.lframe.markers_m.size()); }

  // ---- The clock ----
  double SceneTimeNow() const;
  double SceneTimeOf(std::uint64_t sequence) const;  // the renderer's time of a frame

  // ---- Commands (the daemon's thread; each returns the scene time it takes effect at) ----
  double ShowEmpty();  // nobody and nothing in the volume
  // The wand sweeps the volume for duration_s (in (0, 3600]), then the volume is empty.
  // Successive wavings continue one path (WandPath with the scene's seed).
  Status WaveWand(double duration_s, double* start_time_s = nullptr);
  // The L-frame lies on the floor for duration_s (in (0, 3600]), then the volume is empty.
  Status ShowLFrame(double duration_s, double* start_time_s = nullptr);
  // The subject stands in the protocol's static pose (its movement without excitations, or the
  // neutral pose) with its small wander and sway, until the next command.
  double StandStatic();
  // The subject performs `movement` of the protocol once, from *start_time_s to *end_time_s
  // (its duration_s x duration_scale), then stands still. `amplitude` in [0, 1.5] scales the
  // excursion of every excited coordinate from neutral; duration_scale in (0, 100] as
  // SimulationOptions::duration_scale. An unknown name is an error listing the movements.
  Status Perform(const std::string& movement, double amplitude = 1.0, double duration_scale = 1.0,
                 double* start_time_s = nullptr, double* end_time_s = nullptr);

  // ---- Truth (any thread) ----
  LiveActivity ActivityAt(double scene_time_s) const;
  // The subject's z (model units: radians, metres; truth()'s coordinates) at that time; false
  // when the subject is not in the volume.
  bool TrueCoordinates(double scene_time_s, Eigen::VectorXd* z) const;
  // The wand's markers (Wand order); false when the wand is not in the volume.
  bool TrueWandMarkers(double scene_time_s, std::vector<Eigen::Vector3d>* markers) const;

  const Model& truth() const { return truth_; }      // the true geometry, the simulated markers
  const Model& nominal() const { return nominal_; }  // the default model scaled to the height
  const Eigen::VectorXd& truth_parameters() const { return truth_parameters_; }  // nominal layout
  double height_m() const { return height_m_; }
  const Protocol& protocol() const { return protocol_; }
  const LiveSceneOptions& options() const { return options_; }

 private:
  struct SubjectTrack;
  struct Phase;
  struct Workspace;
  using Schedule = std::vector<Phase>;

  LiveScene() = default;
  static int PhaseAt(const Schedule& schedule, double t);
  // The subject's pose in phase k of `schedule` at time t: ws->z (translations included) and
  // the offset of the pelvis (the root translations).
  void EvaluateSubject(const Schedule& schedule, int k, double t, Workspace* ws) const;
  // The rotational coordinates (root translations 0) into ws->own[depth], blended with the
  // phases before; returns the planned horizontal sway.
  Eigen::Vector2d BlendedPose(const Schedule& schedule, int k, double t, int depth,
                              Workspace* ws) const;
  // Appends a subject phase starting at `begin`, integrates its stance drift over `samples`
  // frames, then brings the pelvis back onto the mark over `return_samples` frames.
  void AppendSubject(Schedule* schedule, const MovementPlan& plan, LiveActivity activity,
                     int movement, double begin, int samples, int return_samples) const;
  void AppendStatic(Schedule* schedule, double begin) const;
  // Installs the phases `build` appends at ts = now + lead (a copy of the schedule truncated at
  // ts); retried with a longer lead if building took longer than the lead.
  double Command(const std::function<void(double ts, Schedule*)>& build);
  void WriteSubjectMarkers(const Workspace& ws, Eigen::Vector3d* out) const;

  LiveSceneOptions options_;
  Protocol protocol_;
  Model truth_, nominal_;
  Eigen::VectorXd truth_parameters_;
  double height_m_ = 0.0;
  Geometry geometry_;
  RootLayout root_;
  FootContacts feet_;
  std::unique_ptr<WandPath> wand_path_;
  MovementPlan static_plan_;
  int lframe_begin_ = 0;

  std::mutex command_mutex_;  // serialises commands
  double next_wand_time_ = 0.0;  // (command_mutex_) where the next waving continues the path
  mutable std::mutex mutex_;     // the schedule, the workspace and the cache
  std::unique_ptr<Schedule> schedule_;
  std::unique_ptr<Workspace> workspace_;
  mutable bool cache_valid_ = false;
  mutable double cache_time_ = 0.0;
  mutable std::vector<Eigen::Vector3d> cache_;
};

}  // namespace mocap::sim
