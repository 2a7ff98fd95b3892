#include "sim/track_run.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <ctime>
#include <numeric>
#include <random>

namespace mocap::sim {
namespace {

// This thread's CPU time (microseconds).
double ThreadCpuUs() {
  timespec t;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
  return static_cast<double>(t.tv_sec) * 1e6 + static_cast<double>(t.tv_nsec) * 1e-3;
}

// The run scored against input.labels from its labels (run->point_of_marker), frame by frame.
void Score(const TrackInput& input, TrackRun* run) {
  run->scored = input.labels != nullptr;
  if (!run->scored) return;
  const std::vector<Eigen::Matrix3Xd>& frames = *input.points;
  LabelScorer scorer(input.num_labels);
  run->frame_scores.assign(run->frames, LabelScore());
  std::vector<int> given;
  for (int f = 0; f < run->frames; ++f) {
    given.assign(frames[f].cols(), -1);
    for (int m = 0; m < run->point_of_marker.cols() && m < static_cast<int>(input.label_of_marker.size()); ++m)
      if (const int i = run->point_of_marker(f, m); i >= 0) given[i] = input.label_of_marker[m];
    run->frame_scores[f] = scorer.Add((*input.labels)[f], given);
  }
  run->score = scorer.Finish();
  run->marker_samples = scorer.marker_samples();
  run->marker_correct = scorer.marker_correct();
}

}  // namespace

TrackRun RunTracker(const TrackInput& input, ekf::Tracker* tracker,
                    const std::function<void(int, const ekf::TrackOutput&)>& after) {
  using Clock = std::chrono::steady_clock;
  const std::vector<Eigen::Matrix3Xd>& frames = *input.points;
  const int nf = static_cast<int>(frames.size());
  const int nm = tracker->model().num_markers(), nz = tracker->model().num_coordinates();
  TrackRun run;
  run.frames = nf;
  run.states.resize(nf);
  run.z.setConstant(nf, nz, std::nan(""));
  run.point_of_marker.setConstant(nf, nm, -1);
  run.update_us.reserve(nf);
  run.update_cpu_us.reserve(nf);
  double sum_points = 0;
  for (int f = 0; f < nf; ++f) {
    const Eigen::Matrix3Xd& points = frames[f];
    sum_points += static_cast<double>(points.cols());
    run.points_per_frame_max = std::max(run.points_per_frame_max, static_cast<double>(points.cols()));
    const double cpu_start = ThreadCpuUs();
    const auto start = Clock::now();
    const ekf::TrackOutput& o = tracker->Update((*input.times)[f], points);
    run.update_us.push_back(std::chrono::duration<double, std::micro>(Clock::now() - start).count());
    run.update_cpu_us.push_back(ThreadCpuUs() - cpu_start);
    run.states[f] = o.state;
    ++run.state_count[static_cast<int>(o.state)];
    if (o.reinitialised) ++run.initialisations;
    if (!o.z.allFinite() || o.z.size() != nz) ++run.nan_poses;
    if (o.state == ekf::TrackState::kTracking) {
      if (run.first_tracking < 0) run.first_tracking = f;
      if (o.z.size() == nz) run.z.row(f) = o.z.transpose();
    }
    for (int m = 0; m < nm && m < static_cast<int>(o.point_of_marker.size()); ++m) {
      const int i = o.point_of_marker[m];
      if (i >= 0 && i < points.cols()) run.point_of_marker(f, m) = i;
    }
    if (after) after(f, o);
  }
  run.points_per_frame_mean = sum_points / std::max(1, nf);
  Score(input, &run);
  return run;
}

constexpr int kBackfillLeadInFrames = 20;

int BackfillBeforeStart(const TrackInput& input, std::shared_ptr<const Model> model,
                        const ekf::TrackerOptions& options, TrackRun* run) {
  const int start = run->first_tracking;
  if (start <= 0) return 0;
  const std::vector<double>& times = *input.times;
  const int nm = run->point_of_marker.cols(), nz = static_cast<int>(run->z.cols());
  ekf::Tracker backward(std::move(model), options);
  // From a little after the start, so that markers a start leaves for the following frames to
  // pick up (a head marker, a forearm) are labelled by the time the backward run passes it.
  const int from = std::min(run->frames - 1, start + kBackfillLeadInFrames);
  int filled = 0;
  // The backward run's labels in the lead-in, where both runs may track (-1: none).
  Eigen::MatrixXi lead_in = Eigen::MatrixXi::Constant(from - start + 1, nm, -1);
  for (int f = from; f >= 0; --f) {
    const ekf::TrackOutput& o = backward.Update(times[from] - times[f], (*input.points)[f]);
    if (o.state != ekf::TrackState::kTracking) continue;
    if (f >= start) {
      if (o.point_of_marker.size() == static_cast<size_t>(nm))
        for (int m = 0; m < nm; ++m) lead_in(f - start, m) = o.point_of_marker[m];
      continue;
    }
    ++filled;
    --run->state_count[static_cast<int>(run->states[f])];
    run->states[f] = o.state;
    ++run->state_count[static_cast<int>(o.state)];
    if (o.z.size() == nz) run->z.row(f) = o.z.transpose();
    for (int m = 0; m < nm && m < static_cast<int>(o.point_of_marker.size()); ++m) {
      const int i = o.point_of_marker[m];
      run->point_of_marker(f, m) = i >= 0 && i < (*input.points)[f].cols() ? i : -1;
    }
  }
  // In the lead-in, a marker the forward run's start left for later frames (gait2354's Top.Head
  // to its third frame) takes the backward run's label where the forward run has none, when the
  // two runs agree on that marker wherever both label it there (at least once) and the forward
  // run gave that point to no other marker: the forward run's labels stand.
  for (int m = 0; m < nm; ++m) {
    int agree = 0, disagree = 0;
    for (int f = start; f <= from; ++f) {
      const int a = run->point_of_marker(f, m), b = lead_in(f - start, m);
      if (a >= 0 && b >= 0) (a == b ? agree : disagree) += 1;
    }
    if (agree == 0 || disagree > 0) continue;
    for (int f = start; f <= from; ++f) {
      const int i = lead_in(f - start, m);
      if (i < 0 || i >= (*input.points)[f].cols() || run->point_of_marker(f, m) >= 0 ||
          run->states[f] != ekf::TrackState::kTracking)
        continue;
      bool taken = false;
      for (int k = 0; k < nm && !taken; ++k) taken = run->point_of_marker(f, k) == i;
      if (taken) continue;
      run->point_of_marker(f, m) = i;
      ++run->backfilled_labels;
    }
  }
  for (int f = 0; f < start && run->first_tracking == start; ++f)
    if (run->states[f] == ekf::TrackState::kTracking) run->first_tracking = f;
  run->backfilled_frames = filled;
  Score(input, run);
  return filled;
}

Eigen::Vector3d FindLabVertical(const TrackInput& input, const std::shared_ptr<const Model>& model,
                                const ekf::TrackerOptions& options, int frames, int* started, int* labelled) {
  const std::vector<Eigen::Vector3d> axes = {Eigen::Vector3d::UnitZ(),  Eigen::Vector3d::UnitY(),
                                             -Eigen::Vector3d::UnitZ(), -Eigen::Vector3d::UnitY(),
                                             Eigen::Vector3d::UnitX(),  -Eigen::Vector3d::UnitX()};
  Eigen::Vector3d best = options.up;
  *started = -1;
  *labelled = 0;
  const int n = std::min<int>(frames, static_cast<int>(input.points->size()));
  for (const Eigen::Vector3d& up : axes) {
    ekf::TrackerOptions o = options;
    o.up = up;
    ekf::Tracker tracker(model, o);
    // Past the best start found so far an axis cannot win.
    const int last = *started >= 0 ? std::min(n - 1, *started) : n - 1;
    for (int f = 0; f <= last; ++f) {
      const ekf::TrackOutput& out = tracker.Update((*input.times)[f], (*input.points)[f]);
      if (out.state != ekf::TrackState::kTracking) continue;
      if (*started < 0 || f < *started || out.labelled > *labelled) {
        *started = f;
        *labelled = out.labelled;
        best = up;
      }
      break;
    }
  }
  return best;
}

TrackRun TrackScene(const TrackingScene& scene, ekf::Tracker* tracker,
                    const std::function<void(int, const ekf::TrackOutput&)>& after) {
  TrackInput input;
  input.times = &scene.times;
  input.points = &scene.points;
  input.labels = &scene.labels;
  input.label_of_marker = SceneMarkerOf(tracker->model(), scene);
  input.num_labels = scene.num_markers();
  return RunTracker(input, tracker, after);
}

TrackInput UnlabelledTrial::Input(int num_model_markers) const {
  TrackInput in;
  in.times = &times;
  in.points = &points;
  in.labels = &labels;
  in.label_of_marker.resize(num_model_markers);
  std::iota(in.label_of_marker.begin(), in.label_of_marker.end(), 0);
  in.num_labels = num_model_markers;
  return in;
}

UnlabelledTrial Unlabel(const formats::MarkerTrial& trial, const Model& model,
                        const UnlabelOptions& options) {
  UnlabelledTrial out;
  const int nf = trial.num_frames(), nt = trial.num_markers();
  std::vector<int> model_of(nt, kGhostLabel);
  out.model_marker_present.assign(model.num_markers(), 0);
  for (int i = 0; i < nt; ++i) model_of[i] = model.FindMarker(trial.marker_names[i]);
  for (int i = 0; i < nt; ++i)
    if (model_of[i] < 0) model_of[i] = kGhostLabel;
  std::mt19937_64 rng(options.shuffle_seed);
  std::uniform_real_distribution<double> unit(-1.0, 1.0);
  out.times.resize(nf);
  out.points.resize(nf);
  out.labels.resize(nf);
  std::vector<int> order;
  std::vector<Eigen::Vector3d> pts;
  std::vector<int> lab;
  for (int f = 0; f < nf; ++f) {
    out.times[f] = trial.times.size() == static_cast<size_t>(nf)
                       ? trial.times[f] - trial.times[0]
                       : f / (trial.rate_hz > 0 ? trial.rate_hz : 1.0);
    pts.clear();
    lab.clear();
    for (int i = 0; i < nt; ++i)
      if (trial.Has(f, i)) {
        pts.push_back(trial.At(f, i));
        lab.push_back(model_of[i]);
        if (model_of[i] >= 0) out.model_marker_present[model_of[i]] = 1;
      }
    const int real = static_cast<int>(pts.size());
    for (int g = 0, tries = 0; real > 0 && g < options.ghosts && tries < 1000; ++tries) {
      const Eigen::Vector3d p =
          pts[static_cast<size_t>(rng() % real)] +
          options.ghost_radius_m * Eigen::Vector3d(unit(rng), unit(rng), unit(rng));
      bool clear = true;
      for (int i = 0; i < real && clear; ++i) clear = (pts[i] - p).norm() >= options.ghost_min_distance_m;
      if (!clear) continue;
      pts.push_back(p);
      lab.push_back(kGhostLabel);
      ++g;
    }
    order.resize(pts.size());
    std::iota(order.begin(), order.end(), 0);
    if (options.shuffle_seed != 0) std::shuffle(order.begin(), order.end(), rng);
    out.points[f].resize(3, static_cast<Eigen::Index>(pts.size()));
    out.labels[f].resize(pts.size());
    for (size_t i = 0; i < pts.size(); ++i) {
      out.points[f].col(static_cast<Eigen::Index>(i)) = pts[order[i]];
      out.labels[f][i] = lab[order[i]];
    }
  }
  return out;
}

}  // namespace mocap::sim
