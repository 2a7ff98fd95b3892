// The tracker (ekf/tracker.h) run offline over a sequence of unlabelled point frames, timed frame by
// frame and, where the true label of every point is known, scored against it. One loop for every
// place that asks "how well does the tracker label this?": `mocap track` (a simulated scene or a
// points file), bench/track_sweep (many seeds in parallel) and the tests on real recordings with
// their labels removed. Keeping it in one place keeps the figures of the three comparable: the
// same scorer (LabelScorer: a swap is a marker labelled on a point that is not it in consecutive
// frames), the same clocks, the same count of re-initialisations.
//
// Timing: each Update's wall-clock time and the thread's CPU time. On a shared machine the wall
// clock's tail is other processes' time slices; the CPU time's is the tracker's own work.
#pragma once
#include <Eigen/Core>
#include <functional>
#include <memory>
#include <vector>

#include "ekf/tracker.h"
#include "formats/marker_data.h"
#include "sim/tracking_scene.h"

namespace mocap::sim {

struct TrackRun {
  int frames = 0;
  std::vector<ekf::TrackState> states;          // per frame
  Eigen::MatrixXd z;                            // frames x coordinates; NaN where not tracking
  Eigen::MatrixXi point_of_marker;              // frames x model markers: point index or -1
  std::vector<double> update_us, update_cpu_us; // per frame: wall clock and thread CPU time
  int state_count[3] = {0, 0, 0};               // by TrackState
  int initialisations = 0;                      // frames with TrackOutput::reinitialised
  int nan_poses = 0;
  int first_tracking = -1;
  int backfilled_frames = 0;                    // BackfillBeforeStart's
  int backfilled_labels = 0;                    // and its labels added in the frames after the start
  double points_per_frame_mean = 0, points_per_frame_max = 0;
  // With truth labels only:
  bool scored = false;
  LabelScore score;                             // totals (LabelScorer::Finish)
  std::vector<LabelScore> frame_scores;         // per frame
  std::vector<long> marker_samples, marker_correct;  // per truth label

  int frames_tracking() const { return state_count[static_cast<int>(ekf::TrackState::kTracking)]; }
  int reinitialisations() const { return initialisations > 0 ? initialisations - 1 : 0; }
};

// The input: times (seconds) and points (metres, columns, NaN columns allowed) per frame and,
// optionally, the truth: per frame and point the index of the marker it is among `num_labels`
// (or a negative k*Label of sim/tracking_scene.h), with `label_of_marker` giving each model
// marker's index among those (-1: a model marker the truth does not name, e.g. a virtual one).
struct TrackInput {
  const std::vector<double>* times = nullptr;
  const std::vector<Eigen::Matrix3Xd>* points = nullptr;
  const std::vector<std::vector<int>>* labels = nullptr;  // null: no scoring
  std::vector<int> label_of_marker;
  int num_labels = 0;
};

// Runs `tracker` over every frame. `after(f, output)` (optional) sees each frame's output.
TrackRun RunTracker(const TrackInput& input, ekf::Tracker* tracker,
                    const std::function<void(int, const ekf::TrackOutput&)>& after = {});

// Offline only (a recording read from a file, `mocap track --points`): the frames before the
// run's first start (run->first_tracking), which the live tracker leaves unlabelled while its
// start is refused, labelled by a fresh tracker of `options` run backward in time from that start
// (from 20 frames after first_tracking down to frame 0, times mirrored so they increase: the lead-
// in lets it pick up the markers a start leaves to the frames after it, as the forward run did),
// and each frame before the start that it tracks takes its labels, pose and state; in the lead-in
// itself, where both runs track, a marker the forward run has not labelled yet takes the backward
// run's label when the two runs agree on that marker wherever both label it there and the forward
// run gave that point to no other marker. The run is scored again. A whole-trial labeller does as
// much (Nexus, QTM label a trial from any frame, both ways); the real-time tracker cannot look
// back, and the simulated sweep measures that tracker, so it does not backfill. Returns the frames
// filled.
int BackfillBeforeStart(const TrackInput& input, std::shared_ptr<const Model> model,
                        const ekf::TrackerOptions& options, TrackRun* run);

// Offline too: the lab's vertical of a recording when nobody said it (`mocap track --points`
// without --up). Labs differ -- Z up in most C3D files, Y in OpenSim's TRC files, -Z in a data
// set turned upside down -- and the tracker's start needs it (its search turns the points so that
// the lab's vertical is the model's). Each of the six axes is tried by a fresh tracker of
// `options` over the first `frames` frames; a wrong vertical does not start (the start needs 80 %
// of the markers within 3 cm of a posed model). The axis that starts first wins, ties going to the
// one that labels more markers there, then to the order z, y, -z, -y, x, -x. *started: that
// frame (-1: no axis started; options.up is returned). *labelled: the markers it labelled there.
Eigen::Vector3d FindLabVertical(const TrackInput& input, const std::shared_ptr<const Model>& model,
                                const ekf::TrackerOptions& options, int frames, int* started, int* labelled);

// RunTracker over a simulated scene, scored against its labels (model markers matched by name).
TrackRun TrackScene(const TrackingScene& scene, ekf::Tracker* tracker,
                    const std::function<void(int, const ekf::TrackOutput&)>& after = {});

// A labelled trial (a real recording) made into what the tracker sees live: per frame, its
// present samples as unlabelled points, shuffled (when shuffle_seed != 0) so that no column order
// gives the labels away, plus `ghosts` random points a frame within ghost_radius_m of the frame's
// markers (and at least ghost_min_distance_m from each: a point closer would be the marker); with,
// per point, the index of the model marker of the same name (or kGhostLabel: a ghost or a trial
// marker the model lacks). Times from 0.
struct UnlabelledTrial {
  std::vector<double> times;
  std::vector<Eigen::Matrix3Xd> points;
  std::vector<std::vector<int>> labels;  // model marker index or kGhostLabel
  std::vector<char> model_marker_present;  // per model marker: any sample in the trial
  TrackInput Input(int num_model_markers) const;  // scored against the labels, identity map
};
struct UnlabelOptions {
  std::uint64_t shuffle_seed = 1;
  int ghosts = 0;
  double ghost_radius_m = 0.3;
  double ghost_min_distance_m = 0.03;
};
UnlabelledTrial Unlabel(const formats::MarkerTrial& trial, const Model& model,
                        const UnlabelOptions& options = {});

}  // namespace mocap::sim
