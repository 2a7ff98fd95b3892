// The tracker (ekf/tracker.h) in the fault scenes of sim/tracking_scene.h: all markers occluded
// for a second, the subject leaving the volume and coming back elsewhere, a second person, a frame
// of NaN points, a model whose markers do not match the data. In every case the tracker says what
// state it is in, never gives a NaN pose, and recovers by itself.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <functional>
#include <memory>

#include "ekf/tracker.h"
#include "sim/tracking_scene.h"

namespace {

using mocap::ekf::Tracker;
using mocap::ekf::TrackState;
using mocap::sim::SceneFault;
using mocap::sim::TrackingScene;

// Long enough to leave, stay out a second and come back (0.4 + 1.5 + 1 + 1.5 s), and to watch
// the recovery afterwards.
mocap::sim::TrackingSceneOptions FaultScene(SceneFault fault) {
  mocap::sim::TrackingSceneOptions o;
  o.seed = 5;
  o.movements = {"static", "squats", "trunk_rom"};
  o.duration_scale = 0.6;
  o.ghosts = 2;
  o.fault = fault;
  return o;
}

struct TrackRun {
  std::vector<TrackState> state;
  std::vector<mocap::sim::LabelScore> frame;  // per frame
  std::vector<std::vector<int>> given;        // per frame: scene marker per point
  int nan_poses = 0;
  int bad_states = 0;
};

// Runs `tracker` over the scene; `before(f)` is called before frame f.
TrackRun Track(const TrackingScene& scene, Tracker* tracker, const std::function<void(int)>& before = {}) {
  TrackRun run;
  std::vector<int> scene_marker = mocap::sim::SceneMarkerOf(tracker->model(), scene);
  mocap::sim::LabelScorer scorer(scene.num_markers());
  for (int f = 0; f < scene.num_frames(); ++f) {
    if (before) before(f);
    if (tracker->model().num_markers() != static_cast<int>(scene_marker.size()))
      scene_marker = mocap::sim::SceneMarkerOf(tracker->model(), scene);
    const mocap::ekf::TrackOutput& o = tracker->Update(scene.times[f], scene.points[f]);
    const TrackState s = o.state;
    if (s != TrackState::kTracking && s != TrackState::kLost && s != TrackState::kInitialising)
      ++run.bad_states;
    if (o.state != tracker->state()) ++run.bad_states;
    run.state.push_back(s);
    if (!o.z.allFinite() || o.z.size() != tracker->model().num_coordinates()) ++run.nan_poses;
    std::vector<int> given(scene.points[f].cols(), -1);
    for (size_t i = 0; i < given.size() && i < o.marker_of_point.size(); ++i)
      if (o.marker_of_point[i] >= 0) given[i] = scene_marker[o.marker_of_point[i]];
    run.frame.push_back(scorer.Add(scene.labels[f], given));
    run.given.push_back(given);
  }
  return run;
}

// First frame at or after `from` where the tracker tracks with 90 % of the visible markers
// correctly labelled and no wrong label; -1 if never.
int Recovered(const TrackRun& run, int from) {
  for (int f = from; f < static_cast<int>(run.state.size()); ++f) {
    const mocap::sim::LabelScore& s = run.frame[f];
    if (run.state[f] == TrackState::kTracking && s.samples > 0 && s.wrong == 0 &&
        s.correct >= 0.9 * static_cast<double>(s.samples))
      return f;
  }
  return -1;
}

mocap::sim::LabelScore Sum(const TrackRun& run, int begin, int end) {
  mocap::sim::LabelScore t;
  for (int f = begin; f < end; ++f) {
    t.samples += run.frame[f].samples;
    t.correct += run.frame[f].correct;
    t.wrong += run.frame[f].wrong;
    t.wrong_on_second_person += run.frame[f].wrong_on_second_person;
  }
  return t;
}

bool EverNot(const TrackRun& run, TrackState state, int begin, int end) {
  for (int f = begin; f < end; ++f)
    if (run.state[f] != state) return true;
  return false;
}

std::unique_ptr<Tracker> MakeTracker(const mocap::Model& model) {
  mocap::ekf::TrackerOptions o;
  o.rate_hz = 200;
  return std::make_unique<Tracker>(std::make_shared<const mocap::Model>(model), o);
}

// Before the fault the tracker is tracking well (the scene starts from the static pose).
void ExpectTrackingBefore(const TrackRun& run, int fault_begin) {
  const int start = Recovered(run, 0);
  ASSERT_GE(start, 0) << "never started tracking";
  EXPECT_LT(start, 100) << "initialisation from the static pose took " << start << " frames";
  const mocap::sim::LabelScore before = Sum(run, start, fault_begin);
  EXPECT_GE(before.accuracy(), 0.999);
}

// Automatic initialisation from the static pose, whoever the subject (seed) and wherever it
// faces: tracking, with every visible marker labelled right, within the first 0.1 s.
TEST(TrackFaults, InitialisesFromTheStaticPoseOfAnySubject) {
  for (std::uint64_t seed : {1, 2, 5, 11}) {
    mocap::sim::TrackingSceneOptions o;
    o.seed = seed;
    o.movements = {"static"};
    o.duration_scale = 0.1;  // 0.3 s
    TrackingScene scene;
    ASSERT_TRUE(mocap::sim::MakeTrackingScene(o, &scene).ok());
    auto tracker = MakeTracker(scene.nominal);
    const TrackRun run = Track(scene, tracker.get());
    EXPECT_EQ(run.nan_poses, 0);
    const int start = Recovered(run, 0);
    EXPECT_GE(start, 0) << "seed " << seed << ": not tracking after " << scene.num_frames() << " frames";
    EXPECT_LT(start, 20) << "seed " << seed;
  }
}

TEST(TrackFaults, AllMarkersOccludedForASecond) {
  TrackingScene scene;
  ASSERT_TRUE(mocap::sim::MakeTrackingScene(FaultScene(SceneFault::kAllOccluded), &scene).ok());
  auto tracker = MakeTracker(scene.nominal);
  const TrackRun run = Track(scene, tracker.get());
  EXPECT_EQ(run.nan_poses, 0);
  EXPECT_EQ(run.bad_states, 0);
  ExpectTrackingBefore(run, scene.fault_begin);
  // A second with nothing but ghosts: the tracker says it has lost the subject, and labels no ghost.
  EXPECT_TRUE(EverNot(run, TrackState::kTracking, scene.fault_begin, scene.fault_end))
      << "still 'tracking' through a second without markers";
  EXPECT_EQ(Sum(run, scene.fault_begin, scene.fault_end).wrong, 0) << "ghosts labelled as markers";
  const int back = Recovered(run, scene.fault_end);
  ASSERT_GE(back, 0) << "never recovered";
  std::printf("all occluded: recovered %d frames after the markers came back\n", back - scene.fault_end);
  EXPECT_LT(back - scene.fault_end, 200) << "recovery took more than 1 s";
  EXPECT_GE(Sum(run, back, scene.num_frames()).accuracy(), 0.999);
}

TEST(TrackFaults, LeavingTheVolumeAndComingBackElsewhere) {
  TrackingScene scene;
  ASSERT_TRUE(mocap::sim::MakeTrackingScene(FaultScene(SceneFault::kLeaveAndReenter), &scene).ok());
  auto tracker = MakeTracker(scene.nominal);
  const TrackRun run = Track(scene, tracker.get());
  EXPECT_EQ(run.nan_poses, 0);
  EXPECT_EQ(run.bad_states, 0);
  ExpectTrackingBefore(run, scene.fault_begin);
  EXPECT_TRUE(EverNot(run, TrackState::kTracking, scene.fault_begin, scene.fault_end))
      << "still 'tracking' while the subject was outside the volume";
  const int back = Recovered(run, scene.fault_end);
  ASSERT_GE(back, 0) << "never found the subject again";
  std::printf("leave and re-enter: recovered %d frames after the subject was back in\n",
              back - scene.fault_end);
  EXPECT_LT(back - scene.fault_end, 200);
  EXPECT_GE(Sum(run, back, scene.num_frames()).accuracy(), 0.999);
}

TEST(TrackFaults, ASecondPersonIsNotLabelled) {
  TrackingScene scene;
  ASSERT_TRUE(mocap::sim::MakeTrackingScene(FaultScene(SceneFault::kSecondPerson), &scene).ok());
  auto tracker = MakeTracker(scene.nominal);
  const TrackRun run = Track(scene, tracker.get());
  EXPECT_EQ(run.nan_poses, 0);
  EXPECT_EQ(run.bad_states, 0);
  ExpectTrackingBefore(run, scene.fault_begin);
  const mocap::sim::LabelScore during = Sum(run, scene.fault_begin, scene.num_frames());
  std::printf("second person: accuracy %.5f, %ld labels on the second person\n", during.accuracy(),
              during.wrong_on_second_person);
  EXPECT_EQ(during.wrong_on_second_person, 0);
  EXPECT_GE(during.accuracy(), 0.999);
  EXPECT_FALSE(EverNot(run, TrackState::kTracking, scene.fault_begin, scene.num_frames()))
      << "a second person made the tracker drop the subject";
}

TEST(TrackFaults, AFrameOfNaNPoints) {
  TrackingScene scene;
  ASSERT_TRUE(mocap::sim::MakeTrackingScene(FaultScene(SceneFault::kNanFrame), &scene).ok());
  auto tracker = MakeTracker(scene.nominal);
  const TrackRun run = Track(scene, tracker.get());
  EXPECT_EQ(run.nan_poses, 0);
  EXPECT_EQ(run.bad_states, 0);
  ExpectTrackingBefore(run, scene.fault_begin);
  // No NaN point is labelled; the frame with NaN columns between the points is labelled right.
  for (int f = scene.fault_begin; f < scene.fault_end; ++f)
    for (size_t i = 0; i < scene.labels[f].size(); ++i)
      if (scene.labels[f][i] == mocap::sim::kNanLabel) EXPECT_EQ(run.given[f][i], -1) << "frame " << f;
  const mocap::sim::LabelScore mixed = run.frame[scene.fault_end - 1];
  EXPECT_EQ(mixed.wrong, 0);
  EXPECT_GE(mixed.correct, 0.9 * static_cast<double>(mixed.samples));
  // One empty frame is not a loss: the track goes on.
  const int back = Recovered(run, scene.fault_begin + 1);
  EXPECT_GE(back, 0);
  EXPECT_LT(back - scene.fault_begin, 20);
  EXPECT_GE(Sum(run, scene.fault_begin, scene.num_frames()).accuracy(), 0.999);
}

// A model whose markers sit 5 cm from where the subject wears them: the tracker reports its
// state and never gives NaN; given the right model (SwapModel, as after a fit) it tracks.
TEST(TrackFaults, AModelWhoseMarkersDoNotMatchTheData) {
  mocap::sim::TrackingSceneOptions o = FaultScene(SceneFault::kNone);
  // The right model arrives while the subject moves (squatting), not in the static pose.
  o.movements = {"squats", "trunk_rom"};
  TrackingScene scene;
  ASSERT_TRUE(mocap::sim::MakeTrackingScene(o, &scene).ok());
  const mocap::Model wrong = mocap::sim::MismatchedModel(scene.nominal, 3, 0.05);
  auto tracker = MakeTracker(wrong);
  // Half a second with the wrong model (each frame of a failing search for the subject is slow),
  // then the right one.
  const int swap = 100;
  mocap::Status swapped;
  const TrackRun run = Track(scene, tracker.get(), [&](int f) {
    if (f == swap) swapped = tracker->SwapModel(std::make_shared<const mocap::Model>(scene.nominal));
  });
  ASSERT_TRUE(swapped.ok()) << swapped.message();
  EXPECT_EQ(run.nan_poses, 0);
  EXPECT_EQ(run.bad_states, 0);
  const mocap::sim::LabelScore mismatched = Sum(run, 0, swap);
  std::printf("mismatched model: accuracy %.4f, %ld wrong labels before the swap\n",
              mismatched.accuracy(), mismatched.wrong);
  const int back = Recovered(run, swap);
  ASSERT_GE(back, 0) << "never tracked after the right model was swapped in";
  EXPECT_LT(back - swap, 200);
  EXPECT_GE(Sum(run, back, scene.num_frames()).accuracy(), 0.999);

  // A model with other marker names cannot replace the tracker's: a clear error, the track kept.
  const mocap::Model renamed = mocap::sim::MismatchedModel(scene.nominal, 3, 0.0, "X_");
  const mocap::Status s = tracker->SwapModel(std::make_shared<const mocap::Model>(renamed));
  EXPECT_FALSE(s.ok());
  EXPECT_FALSE(s.message().empty());
  EXPECT_EQ(tracker->model().markers()[0].name, scene.nominal.markers()[0].name);
}

}  // namespace
