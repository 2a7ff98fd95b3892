// The tracking scene (sim/tracking_scene.h) against its own truth, and `mocap track` end to end
// against the tracking targets of issue 5, with the nominal and with the true model.
#include <gtest/gtest.h>
#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <set>
#include <string>
#include <vector>

#include "ekf/tracker.h"
#include "formats/mot.h"
#include "model/default_model.h"
#include "model/model_io.h"
#include "formats/trc.h"
#include "sim/simulate.h"
#include "sim/track_run.h"
#include "sim/tracking_scene.h"
#include "tests/file_test_util.h"

namespace fs = std::filesystem;
using mocap::sim::TrackingScene;
using mocap::sim::TrackingSceneOptions;
using mocap::testutil::CommandResult;
using mocap::testutil::Mocap;

namespace {

TrackingSceneOptions ShortScene() {
  TrackingSceneOptions o;
  o.seed = 11;
  o.movements = {"static", "squats"};
  o.duration_scale = 0.6;
  return o;
}

double Dist(const TrackingScene& s, int f, int a, int b) {
  return (s.true_markers.row(f).segment<3>(3 * a) - s.true_markers.row(f).segment<3>(3 * b)).norm();
}

TEST(TrackingScene, LabelsNameTheTrueMarkerOfEveryPoint) {
  TrackingSceneOptions o = ShortScene();
  o.ghosts = 6;
  o.occlusion = 0.05;
  TrackingScene s;
  ASSERT_TRUE(mocap::sim::MakeTrackingScene(o, &s).ok());
  ASSERT_GT(s.num_frames(), 500);
  EXPECT_EQ(s.num_markers(), 39);
  const double bound = 6 * 0.5e-3 * std::sqrt(3.0);  // 6 sigma of 0.5 mm noise, 3D
  long ghosts = 0, markers = 0, persistent_repeats = 0;
  int bad_ghost = 0;
  for (int f = 0; f < s.num_frames(); ++f) {
    ASSERT_EQ(s.points[f].cols(), static_cast<long>(s.labels[f].size()));
    std::set<int> seen;
    int frame_ghosts = 0;
    for (int i = 0; i < s.points[f].cols(); ++i) {
      const int m = s.labels[f][i];
      const Eigen::Vector3d p = s.points[f].col(i);
      ASSERT_TRUE(p.allFinite());
      if (m >= 0) {
        EXPECT_TRUE(seen.insert(m).second) << "marker " << m << " twice in frame " << f;
        EXPECT_LT((p - s.true_markers.row(f).segment<3>(3 * m).transpose()).norm(), bound);
        ++markers;
        continue;
      }
      EXPECT_EQ(m, mocap::sim::kGhostLabel);
      ++frame_ghosts;
      double nearest = 1e9;
      for (int k = 0; k < s.num_markers(); ++k)
        nearest = std::min(nearest, (p - s.true_markers.row(f).segment<3>(3 * k).transpose()).norm());
      if (nearest > o.ghost_radius_m + 0.01) ++bad_ghost;
      // A reflection that stays: the same ghost point in the previous frame (lab-fixed ones).
      if (f > 0)
        for (int j = 0; j < s.points[f - 1].cols(); ++j)
          if (s.labels[f - 1][j] < 0 && (s.points[f - 1].col(j) - p).norm() < 0.004) ++persistent_repeats;
    }
    EXPECT_EQ(frame_ghosts, o.ghosts) << "frame " << f;
    ghosts += frame_ghosts;
  }
  EXPECT_EQ(bad_ghost, 0) << "ghosts farther than ghost_radius_m from every marker";
  EXPECT_EQ(markers, s.visible_samples());
  EXPECT_EQ(markers + s.occluded_samples + s.hidden_samples, static_cast<long>(s.num_frames()) * 39);
  // About a quarter of the ghosts are lab-fixed reflections (half persistent, half of those fixed).
  EXPECT_GT(persistent_repeats, ghosts / 10);
  // Shuffled: the first point is not always the same marker.
  std::set<int> first;
  for (int f = 0; f < s.num_frames(); ++f) first.insert(s.labels[f][0]);
  EXPECT_GT(first.size(), 10u);
}

TEST(TrackingScene, OcclusionsRemoveTheFractionAskedInGaps) {
  TrackingSceneOptions o = ShortScene();
  o.occlusion = 0.08;
  TrackingScene s;
  ASSERT_TRUE(mocap::sim::MakeTrackingScene(o, &s).ok());
  const long total = static_cast<long>(s.num_frames()) * s.num_markers();
  EXPECT_NEAR(static_cast<double>(s.occluded_samples) / total, 0.08, 0.001);
  EXPECT_EQ(s.visible_samples(), total - s.occluded_samples);
  // Gaps, not scattered samples: runs of missing frames are 5 frames or longer (bar the last
  // gap drawn, which stops when the fraction is reached).
  int short_runs = 0, runs = 0;
  for (int m = 0; m < s.num_markers(); ++m) {
    int run = 0;
    for (int f = 0; f <= s.num_frames(); ++f) {
      bool present = f == s.num_frames();
      if (!present)
        for (int l : s.labels[f]) present |= l == m;
      if (!present) {
        ++run;
      } else if (run > 0) {
        ++runs;
        short_runs += run < 5;
        run = 0;
      }
    }
  }
  EXPECT_GT(runs, 20);
  EXPECT_LE(short_runs, 1);
}

TEST(TrackingScene, SwapTrapsBringMarkersWithin15mm) {
  TrackingSceneOptions o = ShortScene();
  TrackingScene plain, trapped;
  ASSERT_TRUE(mocap::sim::MakeTrackingScene(o, &plain).ok());
  o.swap_traps = true;
  ASSERT_TRUE(mocap::sim::MakeTrackingScene(o, &trapped).ok());
  ASSERT_EQ(trapped.segments.back().name, "swap_traps");
  const mocap::sim::SceneSegment& seg = trapped.segments.back();
  std::set<std::pair<std::string, std::string>> pairs;
  int in_traps = 0;
  for (const mocap::sim::TrapMoment& t : trapped.traps) {
    // The listed distance is the truth's.
    EXPECT_NEAR(Dist(trapped, t.frame, t.marker_a, t.marker_b), t.distance_m, 1e-12);
    EXPECT_LT(t.distance_m, 0.015);
    if (t.frame >= seg.begin && t.frame < seg.end) {
      ++in_traps;
      pairs.insert({trapped.marker_names[t.marker_a], trapped.marker_names[t.marker_b]});
    }
  }
  // Four planned traps, each passed on the way out and on the way back.
  EXPECT_GE(in_traps, 8);
  // The four planned pairs (the scene's marker order: pelvis, thigh before the arms), and the
  // neighbours that come close with them (the other wrist and forearm markers of meeting hands).
  for (const auto& planned : std::vector<std::pair<std::string, std::string>>{
           {"RTHI", "RFIN"}, {"LTHI", "LFIN"}, {"LWRA", "RWRA"}, {"RASI", "RWRB"}})
    EXPECT_TRUE(pairs.count(planned)) << planned.first << "-" << planned.second;
  // The planned closest approach is 8 mm: the passes come close to it.
  double closest = 1.0;
  for (const auto& t : trapped.traps) closest = std::min(closest, t.distance_m);
  EXPECT_LT(closest, 0.010);
  // Every run of frames within 15 mm was found: scan the truth independently at the trap segment.
  int frames_close = 0;
  for (int f = seg.begin; f < seg.end; ++f)
    for (int a = 0; a < 39; ++a)
      for (int b = a + 1; b < 39; ++b) frames_close += Dist(trapped, f, a, b) < 0.015;
  EXPECT_GT(frames_close, in_traps);
  std::printf("swap traps: %d trap moments in the trap movement, %zu in the scene without it, "
              "closest %.1f mm\n", in_traps, plain.traps.size(), 1000 * closest);
}

// Subjects whose hand does not reach the front of the hip with the arm alone (seeds 21, 70 and 73:
// 15-40 mm short) lean towards it (TrapPlan::lean), and their scenes have every trap: the sweep
// had no scene for them.
TEST(TrackingScene, SwapTrapsLeanWhereTheArmAloneDoesNotReach) {
  for (std::uint64_t seed : {21, 70, 73}) {
    TrackingSceneOptions o = ShortScene();
    o.seed = seed;
    o.swap_traps = true;
    TrackingScene scene;
    const mocap::Status s = mocap::sim::MakeTrackingScene(o, &scene);
    ASSERT_TRUE(s.ok()) << "seed " << seed << ": " << s.message();
    const mocap::sim::SceneSegment& seg = scene.segments.back();
    ASSERT_EQ(seg.name, "swap_traps");
    std::set<std::pair<std::string, std::string>> pairs;
    for (const mocap::sim::TrapMoment& t : scene.traps)
      if (t.frame >= seg.begin && t.frame < seg.end)
        pairs.insert({scene.marker_names[t.marker_a], scene.marker_names[t.marker_b]});
    for (const auto& planned : std::vector<std::pair<std::string, std::string>>{
             {"RTHI", "RFIN"}, {"LTHI", "LFIN"}, {"LWRA", "RWRA"}, {"RASI", "RWRB"}})
      EXPECT_TRUE(pairs.count(planned)) << "seed " << seed << ": " << planned.first << "-" << planned.second;
  }
}

TEST(TrackingScene, SameSeedSameSceneAndTheSubjectOfMocapSim) {
  TrackingSceneOptions o = ShortScene();
  o.ghosts = 3;
  o.occlusion = 0.02;
  o.swap_traps = true;
  TrackingScene a, b, c;
  ASSERT_TRUE(mocap::sim::MakeTrackingScene(o, &a).ok());
  ASSERT_TRUE(mocap::sim::MakeTrackingScene(o, &b).ok());
  ASSERT_EQ(a.num_frames(), b.num_frames());
  for (int f = 0; f < a.num_frames(); ++f) {
    ASSERT_EQ(a.labels[f], b.labels[f]);
    ASSERT_TRUE(a.points[f] == b.points[f]) << "frame " << f;
  }
  o.seed = 12;
  ASSERT_TRUE(mocap::sim::MakeTrackingScene(o, &c).ok());
  EXPECT_NE(a.height_m, c.height_m);

  // The subject and the first movement are those of `mocap sim --seed 11`.
  mocap::sim::SimulationOptions so;
  so.seed = 11;
  so.rate_hz = 200;
  so.duration_scale = 0.6;
  mocap::sim::SimulatedSession session;
  ASSERT_TRUE(mocap::sim::SimulateSession(so, &session).ok());
  EXPECT_EQ(a.height_m, session.height_m);
  ASSERT_EQ(a.segments.front().name, "static");
  const auto& st = session.trials.front();
  ASSERT_EQ(a.segments.front().end, st.markers.num_frames());
  for (int f = 0; f < st.markers.num_frames(); f += 17)
    for (int m = 0; m < 39; ++m)
      EXPECT_NEAR((a.true_markers.row(f).segment<3>(3 * m) - st.markers.positions.row(f).segment<3>(3 * m)).norm(),
                  0.0, 5e-3)  // the simulator's markers carry 0.5 mm noise
          << "frame " << f << " marker " << a.marker_names[m];
}

TEST(TrackingScene, ContinuousAcrossMovements) {
  TrackingSceneOptions o = ShortScene();
  o.movements = {"static", "squats", "shoulder_circles_l"};
  TrackingScene s;
  ASSERT_TRUE(mocap::sim::MakeTrackingScene(o, &s).ok());
  ASSERT_EQ(s.segments.size(), 5u);  // static, transition, squats, transition, shoulder circles
  // Where movements are joined no marker jumps: at 200 Hz a step of 5 mm is 1 m/s, what a
  // transition between two near-neutral poses does not reach.
  auto step = [&](int f) {
    double worst = 0;
    for (int m = 0; m < 39; ++m)
      worst = std::max(worst, (s.true_markers.row(f).segment<3>(3 * m) -
                               s.true_markers.row(f - 1).segment<3>(3 * m)).norm());
    return worst;
  };
  for (const mocap::sim::SceneSegment& g : s.segments) {
    if (g.begin > 0) EXPECT_LT(step(g.begin), 0.005) << "entering " << g.name << " at " << g.begin;
    if (g.name != "transition") continue;
    for (int f = g.begin; f < g.end; ++f) EXPECT_LT(step(f), 0.005) << "transition frame " << f;
  }
}

TEST(TrackingScene, FaultsDoWhatTheySay) {
  using mocap::sim::SceneFault;
  TrackingSceneOptions o = ShortScene();
  o.movements = {"static", "squats", "trunk_rom"};
  o.ghosts = 2;
  {
    o.fault = SceneFault::kAllOccluded;
    TrackingScene s;
    ASSERT_TRUE(mocap::sim::MakeTrackingScene(o, &s).ok());
    EXPECT_EQ(s.fault_end - s.fault_begin, 200);
    for (int f = s.fault_begin; f < s.fault_end; ++f)
      for (int l : s.labels[f]) EXPECT_LT(l, 0);
    int after = 0;
    for (int l : s.labels[s.fault_end]) after += l >= 0;
    EXPECT_EQ(after, 39);
  }
  {
    o.fault = SceneFault::kLeaveAndReenter;
    TrackingScene s;
    ASSERT_TRUE(mocap::sim::MakeTrackingScene(o, &s).ok());
    int empty = 0;
    for (int f = s.fault_begin; f < s.fault_end; ++f) {
      int n = 0;
      for (int l : s.labels[f]) n += l >= 0;
      empty += n == 0;
    }
    EXPECT_GE(empty, 200) << "out of the volume for at least the second asked";
    const Eigen::Vector3d before = s.true_coordinates.row(s.fault_begin).head<3>();
    const Eigen::Vector3d after = s.true_coordinates.row(s.fault_end).head<3>();
    EXPECT_GT((after - before).head<2>().norm(), 1.0) << "back elsewhere";
    int back = 0;
    for (int l : s.labels[s.fault_end]) back += l >= 0;
    EXPECT_EQ(back, 39);
  }
  {
    o.fault = SceneFault::kSecondPerson;
    TrackingScene s;
    ASSERT_TRUE(mocap::sim::MakeTrackingScene(o, &s).ok());
    int second = 0;
    for (int l : s.labels.back()) second += l == mocap::sim::kSecondPersonLabel;
    EXPECT_EQ(second, 39) << "the second person is in the volume at the end";
    for (int l : s.labels[s.fault_begin - 1]) EXPECT_NE(l, mocap::sim::kSecondPersonLabel);
  }
  {
    o.fault = SceneFault::kNanFrame;
    TrackingScene s;
    ASSERT_TRUE(mocap::sim::MakeTrackingScene(o, &s).ok());
    EXPECT_TRUE(s.points[s.fault_begin].array().isNaN().all());
    const Eigen::Matrix3Xd& mixed = s.points[s.fault_end - 1];
    int nan = 0, real = 0;
    for (int i = 0; i < mixed.cols(); ++i) (mixed.col(i).allFinite() ? real : nan)++;
    EXPECT_GT(nan, 10);
    EXPECT_EQ(real, 41);
  }
}

TEST(TrackingScene, BadOptionsAreNamed) {
  TrackingSceneOptions o = ShortScene();
  TrackingScene s;
  o.movements = {"static", "cartwheel"};
  mocap::Status st = mocap::sim::MakeTrackingScene(o, &s);
  ASSERT_FALSE(st.ok());
  EXPECT_NE(st.message().find("cartwheel"), std::string::npos) << st.message();
  o = ShortScene();
  o.occlusion = 0.7;
  st = mocap::sim::MakeTrackingScene(o, &s);
  ASSERT_FALSE(st.ok());
  EXPECT_NE(st.message().find("occlusion"), std::string::npos) << st.message();
  o = ShortScene();
  o.fault = mocap::sim::SceneFault::kLeaveAndReenter;
  o.fault_time_s = 3.0;  // the scene is about 5 s long: no room to leave and come back
  st = mocap::sim::MakeTrackingScene(o, &s);
  ASSERT_FALSE(st.ok());
  EXPECT_NE(st.message().find("does not fit"), std::string::npos) << st.message();
}

// --- mocap track end to end ---------------------------------------------------------------

class TrackCli : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = fs::path(MOCAP_TEST_TMP) / "track_cli" / std::to_string(::getpid());
    fs::remove_all(dir_);
    fs::create_directories(dir_);
    // The nominal and true models exactly as `mocap sim --seed 11` writes them.
    const CommandResult r = Mocap("sim --out " + P("sim") + " --seed 11 --duration-scale 0.2");
    ASSERT_EQ(r.status, 0) << r.output;
  }
  static void TearDownTestSuite() { fs::remove_all(dir_); }
  static std::string P(const std::string& rel) { return (dir_ / rel).string(); }
  static nlohmann::json Stats(const std::string& rel) {
    std::ifstream in(dir_ / rel / "stats.json");
    return nlohmann::json::parse(in);
  }
  // The scene of the targets: static pose, squats, shoulder circles, then the swap traps; four
  // ghosts per frame, 2 % of the samples occluded.
  static std::string Scene() {
    return "track --simulate --seed 11 --movements static,squats,shoulder_circles_l "
           "--duration-scale 0.6 --ghosts 4 --occlusion 0.02 --swap-traps";
  }
  // Runs one of issue 5's commands with `model` and checks its labelling targets.
  // `mocap track` at issue 5's conditions; RunIssueConditions also expects every target.
  static nlohmann::json TrackAtIssueConditions(const std::string& model, int seed);
  static nlohmann::json RunIssueConditions(const std::string& model, int seed = 1) {
    const nlohmann::json s = TrackAtIssueConditions(model, seed);
    if (!s.is_null()) ExpectTargets(s);
    return s;
  }
  static void ExpectTargets(const nlohmann::json& s) {
    for (const char* key : {"frames", "label_accuracy", "wrong_labels", "swaps_longer_than_5_frames",
                            "reinitialisations", "update_us_p50", "update_us_p99", "marker_rms_mm",
                            "joint_angle_rms_deg", "trap_moments", "first_tracking_frame"})
      ASSERT_TRUE(s.contains(key)) << key;
    const long samples = s["marker_samples"].get<long>();
    EXPECT_GT(samples, 100000);
    EXPECT_GE(s["trap_moments"].get<int>(), 8);
    EXPECT_GE(s["label_accuracy"].get<double>(), 0.9995) << s.dump(1);
    EXPECT_LE(s["wrong_labels"].get<double>(), 1e-4 * samples) << s.dump(1);
    EXPECT_EQ(s["swaps_longer_than_5_frames"].get<int>(), 0);
    EXPECT_EQ(s["nan_poses"].get<int>(), 0);
    // Automatic initialisation from the static pose: tracking within its first 0.1 s, once.
    EXPECT_GE(s["first_tracking_frame"].get<int>(), 0);
    EXPECT_LT(s["first_tracking_frame"].get<int>(), 20);
    EXPECT_EQ(s["reinitialisations"].get<int>(), 0);
    EXPECT_GT(s["update_us_p50"].get<double>(), 0.0);
    EXPECT_GE(s["update_us_p99"].get<double>(), s["update_us_p50"].get<double>());
    ASSERT_TRUE(s.contains("update_cpu_us_p50") && s.contains("update_cpu_us_p99"));
    EXPECT_GT(s["update_cpu_us_p50"].get<double>(), 0.0);
    EXPECT_GE(s["update_cpu_us_p99"].get<double>(), s["update_cpu_us_p50"].get<double>());
  }
  static inline fs::path dir_;
};

TEST_F(TrackCli, NominalModelMeetsTheLabellingTargets) {
  const CommandResult r = Mocap(Scene() + " --model " + P("sim/nominal.model.json") + " --out " + P("nominal"));
  ASSERT_EQ(r.status, 0) << r.output;
  EXPECT_NE(r.output.find("frame "), std::string::npos) << "progress lines";
  const nlohmann::json s = Stats("nominal");
  std::printf("nominal model: %s\n", s.dump().c_str());
  ExpectTargets(s);
  // The outputs: labelled markers and coordinates, one row per frame.
  mocap::formats::MarkerTrial labelled;
  ASSERT_TRUE(mocap::formats::ReadTrc(P("nominal/labelled.trc"), &labelled).ok());
  EXPECT_EQ(labelled.num_frames(), s["frames"].get<int>());
  EXPECT_EQ(labelled.num_markers(), 39);
  mocap::formats::CoordinateTable angles;
  ASSERT_TRUE(mocap::formats::ReadMot(P("nominal/coordinates.mot"), &angles).ok());
  EXPECT_EQ(angles.num_frames(), s["frames"].get<int>());
  EXPECT_TRUE(angles.in_degrees);
  EXPECT_GE(angles.FindColumn("knee_angle_r"), 0);
}

TEST_F(TrackCli, TrueModelMeetsTheTargetsAndTheAnglesAreWithinADegree) {
  const CommandResult r = Mocap(Scene() + " --model " + P("sim/truth.model.json") + " --out " + P("truth"));
  ASSERT_EQ(r.status, 0) << r.output;
  const nlohmann::json s = Stats("truth");
  std::printf("true model: %s\n", s.dump().c_str());
  ExpectTargets(s);
  EXPECT_LE(s["joint_angle_rms_deg"].get<double>(), 1.0);
  EXPECT_LT(s["marker_rms_mm"].get<double>(), 2.0);
}

// The whole protocol as `mocap sim` makes it (75 s at 200 Hz, 4 ghosts, 2 % occluded, the swap
// traps), with the true model: every movement, not only the short take above.
TEST_F(TrackCli, WholeProtocolWithTheTrueModel) {
  const CommandResult r = Mocap("track --simulate --seed 1 --ghosts 4 --occlusion 0.02 --swap-traps "
                                "--model truth --out " + P("whole"));
  ASSERT_EQ(r.status, 0) << r.output;
  const nlohmann::json s = Stats("whole");
  EXPECT_GT(s["frames"].get<int>(), 14000);
  std::printf("whole protocol, true model: accuracy %.6f, wrong %d, swaps %d, angles %.3f deg, "
              "markers below 0.999: ", s["label_accuracy"].get<double>(), s["wrong_labels"].get<int>(),
              s["swaps_longer_than_5_frames"].get<int>(), s["joint_angle_rms_deg"].get<double>());
  for (const auto& [name, a] : s["per_marker_accuracy"].items())
    if (a.get<double>() < 0.999) std::printf("%s %.3f ", name.c_str(), a.get<double>());
  std::printf("\n");
  ExpectTargets(s);
  EXPECT_LE(s["joint_angle_rms_deg"].get<double>(), 1.0);
}

// Issue 5's own conditions, its exact commands: the whole protocol as one take (14,880 frames at
// 200 Hz), 5 ghosts per frame, 10 % of the marker samples occluded in gaps of 5-30 frames, the
// swap traps; the nominal and the true model. About 5 s each. The update time is printed but not
// asserted: on a shared machine its wall-clock p99 is the scheduler's (bench/track_vs_ik.cpp
// measures the CPU time).
nlohmann::json TrackCli::TrackAtIssueConditions(const std::string& model, int seed) {
  const std::string dir = "issue_" + model + "_" + std::to_string(seed);
  const CommandResult r = Mocap("track --simulate --seed " + std::to_string(seed) +
                                " --ghosts 5 --occlusion 0.1 --swap-traps --model " + model +
                                " --out " + P(dir));
  EXPECT_EQ(r.status, 0) << r.output;
  if (r.status != 0) return {};
  const nlohmann::json s = Stats(dir);
  std::printf("issue conditions, %s model, seed %d: accuracy %.6f, wrong %d, swaps %d, angles %.3f "
              "deg, update p50 %.0f us p99 %.0f us\n", model.c_str(), seed,
              s["label_accuracy"].get<double>(),
              s["wrong_labels"].get<int>(), s["swaps_longer_than_5_frames"].get<int>(),
              s["joint_angle_rms_deg"].get<double>(), s["update_us_p50"].get<double>(),
              s["update_us_p99"].get<double>());
  EXPECT_EQ(s["frames"].get<int>(), 14880);
  EXPECT_GT(s["marker_samples"].get<long>(), 500000);
  return s;
}

TEST_F(TrackCli, IssueConditionsNominalModel) { RunIssueConditions("nominal"); }

TEST_F(TrackCli, IssueConditionsTrueModelAnglesWithinADegree) {
  const nlohmann::json s = RunIssueConditions("truth");
  ASSERT_FALSE(s.is_null());
  EXPECT_LE(s["joint_angle_rms_deg"].get<double>(), 1.0);
}

// Another subject and session. With the nominal model, pelvis markers back from an occlusion sit
// 2-5 cm from where the pose (pulled by the legs' and trunk's model error) predicts them, beyond
// their gates for seconds (0.99822 of the labels before a marker was looked for where its
// segment's labelled markers put it; now the segment registration, ekf/tracker_labelling.cpp).
TEST_F(TrackCli, IssueConditionsNominalModelSeed2) { RunIssueConditions("nominal", 2); }

// A reflection riding 15 mm beside the right finger marker took its label the frame the marker
// was occluded and kept it for 117 frames after the marker came back (189 wrong labels, two swaps
// longer than 5 frames, before points seen beside a marker were kept from it).
TEST_F(TrackCli, IssueConditionsTrueModelSeed5) {
  const nlohmann::json s = RunIssueConditions("truth", 5);
  ASSERT_FALSE(s.is_null());
  EXPECT_LE(s["joint_angle_rms_deg"].get<double>(), 1.0);
}

// Markers on two-marker segments (RKNE on the thigh in squats, LELB on the upper arm in shoulder
// circles and elbow flexion) come back from occlusions 25-40 mm from a prediction that carries
// the nominal model's error, steadily so, beyond their gates for up to 111 frames (0.99934 of
// the labels before such a marker was found where its segment's rigid geometry puts it: the
// segment registration, ekf/tracker_labelling.cpp).
TEST_F(TrackCli, IssueConditionsNominalModelSeed3) { RunIssueConditions("nominal", 3); }

// In the first second, in the static pose, RANK is hidden at frame 78 and a lab-fixed ghost 78 mm
// away sits in its still wide gate: it took the label for 17 frames (a swap longer than 5 frames,
// with either model) before a marker that has held its point for 20 frames was kept, in a fresh
// track too, from the points seen beside it.
TEST_F(TrackCli, IssueConditionsTrueModelSeed3) {
  const nlohmann::json s = RunIssueConditions("truth", 3);
  ASSERT_FALSE(s.is_null());
  EXPECT_LE(s["joint_angle_rms_deg"].get<double>(), 1.0);
}

// The harder scene's start (8 ghosts a frame, 15 % occluded), seed 6, the static pose only (3 s,
// about a second to run). The search places the right shank 6-8 cm off and leaves RKNE, RTIB, RANK
// and RHEE unlabelled; one frame later RANK's point lay in both RANK's and RHEE's wide
// first-second gates and the assignment gave it to RHEE by the misplaced pose, a label the
// point track then kept (0.952 of the labels, 474 wrong, 7 swaps longer than 5 frames; over the
// whole protocol, RHEE on RANK's point to the end). A point two unlabelled markers could each take
// afresh is now left to neither (ekf/tracker_labelling.cpp, LabelByGating): 0.99915, 17 wrong.
TEST_F(TrackCli, AnUndecidedStartIsLeftUnlabelled) {
  const CommandResult r = Mocap("track --simulate --seed 6 --ghosts 8 --occlusion 0.15 --movements static "
                                "--model nominal --out " + P("undecided_start"));
  ASSERT_EQ(r.status, 0) << r.output;
  const nlohmann::json s = Stats("undecided_start");
  EXPECT_EQ(s["frames"].get<int>(), 600);
  EXPECT_GE(s["label_accuracy"].get<double>(), 0.999) << s.dump(1);
  EXPECT_EQ(s["swaps_longer_than_5_frames"].get<int>(), 0) << s.dump(1);
  EXPECT_LE(s["wrong_labels"].get<int>(), 30) << s.dump(1);
}

// The issue's scene (5 ghosts a frame, 10 % occluded), seed 37, the static pose only (3 s). The
// start labels every marker right, but with the offsets learnt at the slow gain alone (as the
// tracker does by default, marker_offset_prior_frames 0) each gate keeps the 25 mm prior's ~10 cm
// width for seconds: LTOE, hidden for a few frames, takes a ghost in that gate when it comes back
// and the point track keeps it for 320 frames (0.984 of the labels, 325 wrong, LTOE right in
// 0.34 of its samples). Learnt as the mean of the residuals while the subject stands still
// (marker_offset_prior_frames 1), a marker seen in the static is looked for where it was seen:
// every label right. Both are asserted, so the test says what the option changes.
TEST(TrackStaticStart, OffsetsLearntAsTheMeanWhileStillKeepAReturningMarkerOffAGhost) {
  mocap::sim::TrackingSceneOptions o;
  o.seed = 37;
  o.ghosts = 5;
  o.occlusion = 0.1;
  o.movements = {"static"};
  mocap::sim::TrackingScene scene;
  ASSERT_TRUE(mocap::sim::MakeTrackingScene(o, &scene).ok());
  // At the model's own size, the offsets' option alone (scaled to the subject, the default
  // since the eighteenth session, the prior of a marker the start labelled is the scaled
  // placement's residual and its gate as narrow: every label right either way, asserted below).
  auto run = [&](double prior_frames, bool scaled = false) {
    mocap::ekf::TrackerOptions topt;
    topt.rate_hz = o.rate_hz;
    topt.marker_offset_prior_frames = prior_frames;
    if (!scaled) topt.init_scale_to_subject = mocap::ekf::TrackerOptions::ScaleToSubject::kWhenTheModelDoesNotFit;
    mocap::ekf::Tracker tracker(std::make_shared<const mocap::Model>(scene.nominal), topt);
    return mocap::sim::TrackScene(scene, &tracker);
  };
  const mocap::sim::TrackRun slow = run(0.0);
  ASSERT_TRUE(slow.scored);
  std::printf("static start, seed 37, offsets at the slow gain: accuracy %.6f, wrong %ld, swaps %d\n",
              slow.score.accuracy(), static_cast<long>(slow.score.wrong),
              slow.score.swaps_longer_than_5_frames);
  EXPECT_GE(slow.score.swaps_longer_than_5_frames, 1);
  const mocap::sim::TrackRun mean = run(1.0);
  ASSERT_TRUE(mean.scored);
  std::printf("static start, seed 37, offsets as the mean while still: accuracy %.6f, wrong %ld, "
              "swaps %d\n", mean.score.accuracy(), static_cast<long>(mean.score.wrong),
              mean.score.swaps_longer_than_5_frames);
  EXPECT_EQ(mean.frames, 600);
  EXPECT_GE(mean.score.accuracy(), 0.999);
  EXPECT_EQ(mean.score.swaps_longer_than_5_frames, 0);
  EXPECT_LE(mean.score.wrong, 10);
  const mocap::sim::TrackRun scaled = run(0.0, true);
  ASSERT_TRUE(scaled.scored);
  std::printf("static start, seed 37, scaled to the subject, offsets at the slow gain: accuracy %.6f, "
              "wrong %ld, swaps %d\n", scaled.score.accuracy(), static_cast<long>(scaled.score.wrong),
              scaled.score.swaps_longer_than_5_frames);
  EXPECT_GE(scaled.score.accuracy(), 0.9999);
  EXPECT_EQ(scaled.score.swaps_longer_than_5_frames, 0);
  EXPECT_LE(scaled.score.wrong, 10);
}

namespace {
// The first `frames` frames of the sweep's scene of the issue's conditions (bench/track_sweep: the
// whole protocol as one take, 5 ghosts a frame, 10 % occluded, the swap traps) for `seed`,
// recorded at `rate_hz` (track_sweep --rate), tracked with the nominal model and the default
// options (told the rate); *scene gets the scene as tracked.
mocap::sim::TrackRun TrackIssueScene(std::uint64_t seed, int frames, mocap::sim::TrackingScene* scene,
                                     mocap::ekf::InitialisationSummary* start = nullptr,
                                     double rate_hz = 200.0, bool true_model = false) {
  mocap::sim::TrackingSceneOptions o;
  o.seed = seed;
  o.rate_hz = rate_hz;
  o.ghosts = 5;
  o.occlusion = 0.1;
  o.swap_traps = true;
  EXPECT_TRUE(mocap::sim::MakeTrackingScene(o, scene).ok());
  EXPECT_GT(scene->num_frames(), frames);
  scene->times.resize(frames);
  scene->points.resize(frames);
  scene->labels.resize(frames);
  mocap::ekf::TrackerOptions topt;
  topt.rate_hz = o.rate_hz;
  mocap::ekf::Tracker tracker(
      std::make_shared<const mocap::Model>(true_model ? scene->truth : scene->nominal), topt);
  mocap::sim::TrackRun run = mocap::sim::TrackScene(*scene, &tracker);
  if (start) *start = tracker.initialisation();
  return run;
}

int SceneMarker(const mocap::sim::TrackingScene& scene, const std::string& name) {
  for (int i = 0; i < scene.num_markers(); ++i)
    if (scene.marker_names[i] == name) return i;
  return -1;
}

// The issue's scene for `seed`, its first `frames` frames, where the start leaves `marker`'s label
// empty and the gate gives it its own point from the next frame: started at frame 0, no
// re-initialisation, no swap, at most 2 wrong labels, the marker right in all but 2 of its samples.
mocap::sim::TrackRun ExpectAStartLabelLeftEmptyThenRight(std::uint64_t seed, int frames,
                                                         const std::string& marker) {
  mocap::sim::TrackingScene scene;
  const mocap::sim::TrackRun run = TrackIssueScene(seed, frames, &scene);
  EXPECT_TRUE(run.scored);
  const int k = SceneMarker(scene, marker);
  EXPECT_GE(k, 0) << marker;
  if (!run.scored || k < 0) return run;
  std::printf("seed %llu, 5 ghosts, frames 0-%d: accuracy %.6f, wrong %ld, swaps %d; %s %ld of %ld right\n",
              static_cast<unsigned long long>(seed), frames - 1, run.score.accuracy(),
              static_cast<long>(run.score.wrong), run.score.swaps_longer_than_5_frames, marker.c_str(),
              run.marker_correct[k], run.marker_samples[k]);
  EXPECT_EQ(run.first_tracking, 0);
  EXPECT_EQ(run.reinitialisations(), 0);
  EXPECT_EQ(run.score.swaps_longer_than_5_frames, 0);
  EXPECT_LE(run.score.wrong, 2);
  EXPECT_GE(run.marker_correct[k], run.marker_samples[k] - 2);
  return run;
}
}  // namespace

// The sweep's scene of the issue's conditions (5 ghosts a frame, 10 % occluded, the swap traps),
// seed 37, its first 900 frames (the static and the first hip arcs). Its start stood between the
// sweep and its target: the search turned the right ankle 0.46 rad and the subtalar -0.42 rad
// from the static pose to put RTOE on a reflection 10 mm from the turned foot's toe; the
// reflection stayed 339 frames, RTOE on it all that time, then unlabelled with the foot turned
// for 460 frames more (0.998520 of the whole take's labels, the worst of seeds 1-50). The toe
// marker alone decides the subtalar turn: fitted without it, the rest of the body puts RTOE 71 mm
// from that point and 41 mm from its own, unclaimed. Which configuration is right one frame
// cannot say; the start leaves the label empty (LeaveSelfDecidedLabelsEmpty) with the foot where
// the rest of the body puts it, and the gate takes RTOE's own point from the next frame. Labels
// asserted against the truth.
TEST(TrackStaticStart, ALabelThatAloneTurnsItsLimbOntoAReflectionIsLeftEmpty) {
  const mocap::sim::TrackRun run = ExpectAStartLabelLeftEmptyThenRight(37, 900, "RTOE");
  EXPECT_GE(run.score.accuracy(), 0.9999);
}

// The issue's conditions, seed 22, its first 14,700 frames (to the swap traps' right hand over
// the right hip). RASI vanished under the hand in the frame RWRB's point appeared 9 mm from where
// RASI's would be; the point track went on to RWRB's point and RASI's label with it, for 12
// frames while the point moved off with the hand (the sweep's worst seed at 5 ghosts, 0.999899,
// and in every other scene of the sweep too). A point continuing a label's track that an
// unlabelled marker of another segment explains better is now left empty for the gates to decide.
TEST(TrackSwapTraps, AHandOverAHipMarkerDoesNotCarryTheHipsLabelAway) {
  mocap::sim::TrackingScene scene;
  const mocap::sim::TrackRun run = TrackIssueScene(22, 14700, &scene);
  ASSERT_TRUE(run.scored);
  std::printf("seed 22, 5 ghosts, frames 0-14699: accuracy %.6f, wrong %ld, swaps %d, longest %d\n",
              run.score.accuracy(), static_cast<long>(run.score.wrong),
              run.score.swaps_longer_than_5_frames, run.score.longest_wrong_run);
  EXPECT_EQ(run.reinitialisations(), 0);
  EXPECT_EQ(run.score.swaps_longer_than_5_frames, 0);
  EXPECT_LE(run.score.longest_wrong_run, 2);
}

// The issue's conditions, seed 47, its first 4,800 frames (into the ankle circles). RFIN was
// hidden from frame 4,732 with the hand still, its prediction 1 mm from its point; at 4,752 a
// reflection was born 30 mm from it, riding with the hand, inside a gate 18 mm in standard
// deviation (the wrist angles' process noise at the bound for the fastest motion), and RFIN held
// it for 30 frames. A hidden marker's gate now scales its prediction's covariance by what the
// forecasts of its place showed (ekf/tracker.h, "Hidden markers' gates").
TEST(TrackAnkleCircles, AStillHandsHiddenFingerMarkerDoesNotTakeAReflectionBesideIt) {
  mocap::sim::TrackingScene scene;
  const mocap::sim::TrackRun run = TrackIssueScene(47, 4800, &scene);
  ASSERT_TRUE(run.scored);
  const int fin = SceneMarker(scene, "RFIN");
  ASSERT_GE(fin, 0);
  std::printf("seed 47, 5 ghosts, frames 0-4799: accuracy %.6f, wrong %ld, swaps %d, longest %d; "
              "RFIN %ld of %ld right\n",
              run.score.accuracy(), static_cast<long>(run.score.wrong),
              run.score.swaps_longer_than_5_frames, run.score.longest_wrong_run,
              run.marker_correct[fin], run.marker_samples[fin]);
  EXPECT_EQ(run.reinitialisations(), 0);
  EXPECT_EQ(run.score.swaps_longer_than_5_frames, 0);
  EXPECT_LE(run.score.longest_wrong_run, 2);
}

// The issue's scene for `seed`, its first `frames` frames, where a toe marker hidden with its
// heel marker labelled comes back: no re-initialisation, and the toe right in all but `missed` of
// its samples (seed 122's one swap, 6 frames of two arm markers, is another matter).
void ExpectAToeBackBesideItsHeelLabelled(std::uint64_t seed, int frames, const std::string& toe,
                                         long missed) {
  mocap::sim::TrackingScene scene;
  const mocap::sim::TrackRun run = TrackIssueScene(seed, frames, &scene);
  ASSERT_TRUE(run.scored);
  const int k = SceneMarker(scene, toe);
  ASSERT_GE(k, 0);
  std::printf("seed %d, 5 ghosts, frames 0-%d: accuracy %.6f, wrong %ld, swaps %d; %s %ld of %ld right\n",
              static_cast<int>(seed), frames - 1, run.score.accuracy(),
              static_cast<long>(run.score.wrong), run.score.swaps_longer_than_5_frames, toe.c_str(),
              static_cast<long>(run.marker_correct[k]), static_cast<long>(run.marker_samples[k]));
  EXPECT_EQ(run.reinitialisations(), 0);
  EXPECT_GE(run.marker_correct[k], run.marker_samples[k] - missed);
}

// Seeds 96 and 122 of the issue's scene (never tuned on), their first 7,700 and 9,400 frames. A
// toe marker hidden with its heel labelled: the heel lies 5-9 mm from the subtalar axis, so it
// tells that angle less than the joint's range does (about 0.8 rad in standard deviation a frame),
// and each heel residual the nominal model leaves turned the foot about the heel -- the subtalar
// angle ran to its range in 0.2-0.3 s with the foot still. LTOE came back 59 mm from its
// prediction (seed 96, the squats), outside its narrowed gate, and was left unlabelled for 6,880
// frames, to the end of the take (0.9868 of the take's labels); RTOE 175 mm (seed 122, the right
// shoulder circles), 550 frames. A coordinate an update tells less than its range does is now left
// where the prediction put it (ekf/tracker.h, "Weakly observed coordinates").
TEST(TrackSquats, AToeHiddenBesideItsLabelledHeelIsNotTurnedAboutIt) {
  ExpectAToeBackBesideItsHeelLabelled(96, 7700, "LTOE", 20);
  ExpectAToeBackBesideItsHeelLabelled(122, 9400, "RTOE", 30);
}

// The issue's conditions (5 ghosts a frame, 10 % occluded, the swap traps), seed 81 (a seed
// none of the tracker's rules was tuned on), its first 900 frames. A reflection stands beside the
// right hand for the whole static: two placements of the hand came within the ambiguity margin
// (RWRA on its own point, or on RWRB's with RWRB unlabelled), and the whole start was refused for
// seven frames; at the eighth, with RFIN hidden, a third placement with the hand turned won (RWRA
// on RWRB's point, RWRB on the reflection 47 mm off, RFIN on RWRA's point) and the track kept it
// for the whole session (0.955 of the labels). The start now takes what the close placements
// agree on and leaves the markers they dispute empty (InitialisationSummary::undecided); the
// gates label them from the next frames. Labels asserted against the truth.
TEST(TrackStaticStart, AStartLeavesTheMarkersItsClosePlacementsDisputeEmpty) {
  mocap::sim::TrackingScene scene;
  mocap::ekf::InitialisationSummary start;
  const mocap::sim::TrackRun run = TrackIssueScene(81, 900, &scene, &start);
  ASSERT_TRUE(run.scored);
  std::printf("seed 81, 5 ghosts, frames 0-899: started at frame %d with %d markers undecided; accuracy "
              "%.6f, wrong %ld, swaps %d\n", run.first_tracking, start.undecided,
              run.score.accuracy(), static_cast<long>(run.score.wrong), run.score.swaps_longer_than_5_frames);
  EXPECT_EQ(run.first_tracking, 0);
  EXPECT_GE(start.undecided, 2);
  EXPECT_EQ(run.reinitialisations(), 0);
  EXPECT_EQ(run.score.swaps_longer_than_5_frames, 0);
  for (const char* name : {"RWRA", "RWRB", "RFIN"}) {
    const int k = SceneMarker(scene, name);
    ASSERT_GE(k, 0) << name;
    EXPECT_GE(run.marker_correct[k], run.marker_samples[k] - 5) << name;
  }
  EXPECT_GE(run.score.accuracy(), 0.9999);
}

// The issue's conditions, seed 120 (a hold-out seed), the static's first 300 frames. The start
// placed RWRB 11 mm from a reflection and 25 mm from its own point, and labelled the reflection:
// by the forearm's rigid distances (to the elbow centre, RFRM and RWRA) the two fit the nominal
// model about equally (6.6/10.5/11.8 mm off against 20.7/4.2/5.3 mm), and the placement, fitted
// to the label, only follows it. RWRB held the reflection for 71 frames (the hold-out's longest
// wrong run, at 8 ghosts too). The start now leaves such a label empty and follows both points
// until their motion or their end decides (ekf/tracker.h, "Deferred labels"): RWRB waits
// unlabelled and then takes its own point. Labels asserted against the truth.
TEST(TrackStaticStart, ALabelTheSegmentsDistancesCannotDecideIsDeferred) {
  mocap::sim::TrackingScene scene;
  mocap::ekf::InitialisationSummary start;
  const mocap::sim::TrackRun run = TrackIssueScene(120, 300, &scene, &start);
  ASSERT_TRUE(run.scored);
  const int k = SceneMarker(scene, "RWRB");
  ASSERT_GE(k, 0);
  std::printf("seed 120, 5 ghosts, frames 0-299: started at frame %d with %d markers undecided; accuracy "
              "%.6f, wrong %ld, swaps %d, longest %d; RWRB %ld of %ld right\n", run.first_tracking,
              start.undecided, run.score.accuracy(), static_cast<long>(run.score.wrong),
              run.score.swaps_longer_than_5_frames, run.score.longest_wrong_run, run.marker_correct[k],
              run.marker_samples[k]);
  EXPECT_EQ(run.first_tracking, 0);
  EXPECT_GE(start.undecided, 1);
  EXPECT_EQ(run.reinitialisations(), 0);
  EXPECT_EQ(run.score.swaps_longer_than_5_frames, 0);
  EXPECT_LE(run.score.longest_wrong_run, 2);
  EXPECT_LE(run.score.wrong, 2);
  // Unlabelled while the reflection lives (62 frames), right from then on.
  EXPECT_GE(run.marker_correct[k], run.marker_samples[k] - 70);
}

// The harder scene (8 ghosts a frame, 15 % occluded, the swap traps), seed 127 (a hold-out seed),
// the static's 600 frames. The start labelled RKNE right, but a reflection 40 mm from
// its place fitted the thigh's distances (to RTHI and the hip centre) better (a chi-square of 0.9
// against 1.7), so RKNE's label was deferred; a standing subject's sway moves the reflection's
// distance to RTHI by 1-1.6 mm, under the 1 cm that rules a candidate out, and nothing decided:
// RKNE unlabelled until both points were lost at frame 368. A distance's mean over 0.1 s shows the
// sway (ekf/tracker.h, "Deferred labels"): the reflection is ruled out at frame 100 and RKNE
// takes its own point. Labels asserted against the truth.
TEST(TrackStaticStart, ADeferredLabelIsDecidedByTheSwayOfAStillStance) {
  mocap::sim::TrackingSceneOptions o;
  o.seed = 127;
  o.ghosts = 8;
  o.occlusion = 0.15;
  o.swap_traps = true;
  mocap::sim::TrackingScene scene;
  ASSERT_TRUE(mocap::sim::MakeTrackingScene(o, &scene).ok());
  const int frames = 600;
  scene.times.resize(frames);
  scene.points.resize(frames);
  scene.labels.resize(frames);
  mocap::ekf::TrackerOptions topt;
  topt.rate_hz = o.rate_hz;
  mocap::ekf::Tracker tracker(std::make_shared<const mocap::Model>(scene.nominal), topt);
  const mocap::sim::TrackRun run = mocap::sim::TrackScene(scene, &tracker);
  ASSERT_TRUE(run.scored);
  const int k = SceneMarker(scene, "RKNE");
  ASSERT_GE(k, 0);
  std::printf("seed 127, 8 ghosts, frames 0-599: started at frame %d with %d markers undecided; accuracy %.6f, "
              "wrong %ld, swaps %d; RKNE %ld of %ld right\n", run.first_tracking,
              tracker.initialisation().undecided, run.score.accuracy(), static_cast<long>(run.score.wrong),
              run.score.swaps_longer_than_5_frames, run.marker_correct[k], run.marker_samples[k]);
  EXPECT_EQ(run.first_tracking, 0);
  EXPECT_GE(tracker.initialisation().undecided, 1);
  EXPECT_EQ(run.reinitialisations(), 0);
  EXPECT_EQ(run.score.swaps_longer_than_5_frames, 0);
  EXPECT_LE(run.score.wrong, 2);
  // Unlabelled for the first 0.6 s at most (100 frames of the deferral and what hides it).
  EXPECT_GE(run.marker_correct[k], run.marker_samples[k] - 120);
}

// The issue's conditions, seed 69 (never tuned on), the static's first 600 frames. The start put
// LTOE on a reflection, turning the foot by 4.6 times the prior's departure of the pose without
// that label; without it the rest of the body puts LTOE 85 mm from the reflection and 63 mm from
// LTOE's own point, unclaimed. The test for a label that alone turns its limb
// (LeaveSelfDecidedLabelsEmpty) asked for a second point within the search's 5 cm radius and
// kept the label: LTOE on the reflection for 311 frames, and its offset learnt there cost two
// more swaps later (0.975 of the take's labels). A second point nearer than the labelled one
// is enough: the label is left empty and the gate takes LTOE's own point.
TEST(TrackStaticStart, ALabelThatTurnsItsLimbPastANearerPointIsLeftEmpty) {
  ExpectAStartLabelLeftEmptyThenRight(69, 600, "LTOE");
}

namespace {
// The first `frames` frames of the sweep's scene (bench/track_sweep: the whole protocol as one
// take, the swap traps) for `seed` at 8 ghosts a frame, 15 % occluded, tracked with the nominal
// model at `scale` (the other options the defaults).
mocap::sim::TrackRun TrackHarderScene(std::uint64_t seed, std::vector<std::string> movements, int frames,
                                      mocap::ekf::TrackerOptions::ScaleToSubject scale,
                                      std::vector<double>* segment_scales, bool true_model = false) {
  mocap::sim::TrackingSceneOptions o;
  o.seed = seed;
  o.ghosts = 8;
  o.occlusion = 0.15;
  o.swap_traps = movements.empty();
  o.movements = std::move(movements);
  mocap::sim::TrackingScene scene;
  EXPECT_TRUE(mocap::sim::MakeTrackingScene(o, &scene).ok());
  if (frames < scene.num_frames()) {
    scene.times.resize(frames);
    scene.points.resize(frames);
    scene.labels.resize(frames);
  }
  mocap::ekf::TrackerOptions topt;
  topt.rate_hz = o.rate_hz;
  topt.init_scale_to_subject = scale;
  mocap::ekf::Tracker tracker(std::make_shared<const mocap::Model>(true_model ? scene.truth : scene.nominal), topt);
  mocap::sim::TrackRun run = mocap::sim::TrackScene(scene, &tracker);
  *segment_scales = tracker.initialisation().segment_scales;
  return run;
}
}  // namespace

// The sweep's harder scene (8 ghosts a frame, 15 % occluded), seeds 10 and 24, their first 1,400
// frames (the static pose and the first hip arcs). In the first second each gate is as wide as
// the offsets' prior (the nominal model's 25 mm: ~10 cm with the gate), and a wrist marker hidden
// at frame 7 (seed 10: RWRB, at either size) or 56 (seed 24: LWRA, scaled) took a ghost 96-106 mm
// away; the limb search later put its mate on its point (seed 10: RWRA on RWRB's point from frame
// 155 to 1,342 at the model's own size, 0.951 of these frames' labels; for the whole session
// scaled: 0.969 and 0.934 of the labels over the protocol; seed 24 scaled: 0.997). Scaled to the subject, a marker the start labelled is within the scaled placement's
// residual (7-9 mm RMS) of its point, and that is what its offset's prior then says is unknown
// (ekf/tracker_initialisation.cpp, TryInitialise): its gate narrows to ~4 cm and neither ghost is
// taken. Both sizes are asserted, so the test says what the default changes.
TEST(TrackScaledStart, AHiddenWristMarkerTakesNoGhost) {
  using Scale = mocap::ekf::TrackerOptions::ScaleToSubject;
  ASSERT_EQ(mocap::ekf::TrackerOptions{}.init_scale_to_subject, Scale::kAlways);
  auto print = [](std::uint64_t seed, const char* size, const mocap::sim::TrackRun& run) {
    std::printf("seed %d, 8 ghosts, frames 0-1399, %s: accuracy %.6f, wrong %ld, swaps %d\n",
                static_cast<int>(seed), size, run.score.accuracy(), static_cast<long>(run.score.wrong),
                run.score.swaps_longer_than_5_frames);
  };
  for (std::uint64_t seed : {10, 24}) {
    std::vector<double> scales;
    if (seed == 10) {  // seed 24's ghost, 103 mm away at the model's own size, was not taken there
      const mocap::sim::TrackRun own = TrackHarderScene(seed, {}, 1400, Scale::kWhenTheModelDoesNotFit, &scales);
      ASSERT_TRUE(own.scored);
      EXPECT_TRUE(scales.empty());
      print(seed, "the model's own size", own);
      EXPECT_GE(own.score.swaps_longer_than_5_frames, 1);
    }
    const mocap::sim::TrackRun scaled = TrackHarderScene(seed, {}, 1400, Scale::kAlways, &scales);
    ASSERT_TRUE(scaled.scored);
    EXPECT_FALSE(scales.empty());
    print(seed, "scaled to the subject", scaled);
    EXPECT_EQ(scaled.frames, 1400);
    EXPECT_EQ(scaled.reinitialisations(), 0);
    EXPECT_EQ(scaled.score.swaps_longer_than_5_frames, 0) << "seed " << seed;
    EXPECT_LE(scaled.score.wrong, 5) << "seed " << seed;
    EXPECT_GE(scaled.score.accuracy(), 0.999) << "seed " << seed;
  }
}

namespace {
// The first `frames` frames of the harder scene for `seed`, scaled to the subject (the default):
// no re-initialisation, no swap longer than 5 frames, no wrong run longer than 2 frames.
void ExpectTheHarderSceneLabelledRight(std::uint64_t seed, int frames, bool true_model = false) {
  std::vector<double> scales;
  const mocap::sim::TrackRun run = TrackHarderScene(
      seed, {}, frames, mocap::ekf::TrackerOptions::ScaleToSubject::kAlways, &scales, true_model);
  ASSERT_TRUE(run.scored);
  std::printf("seed %llu, 8 ghosts, %s model, frames 0-%d: accuracy %.6f, wrong %ld, swaps %d, longest %d\n",
              static_cast<unsigned long long>(seed), true_model ? "true" : "nominal", frames - 1, run.score.accuracy(),
              static_cast<long>(run.score.wrong), run.score.swaps_longer_than_5_frames,
              run.score.longest_wrong_run);
  EXPECT_EQ(run.reinitialisations(), 0);
  EXPECT_EQ(run.score.swaps_longer_than_5_frames, 0);
  EXPECT_LE(run.score.longest_wrong_run, 2);
}
}  // namespace

// Seed 11 of the harder scene, its first 4,400 frames. LASI is hidden from frame ~4,080; at 4,112
// a reflection riding 88 mm from its prediction (the pelvis held by its three other markers, the
// gate 5 mm in sd) took its label for 10 frames, until its own point came back 9 mm from the
// prediction. The segment registration had put it there: the pelvis's rigid fit to the four
// points spread the 88 mm over every marker (18, 14, 13, 13 mm), each within its own 18 mm
// tolerance, and only the fit's whole chi-square (41 on 6 degrees of freedom) tells (ekf/
// tracker_labelling.cpp, SegmentFitCost).
TEST(TrackHarderScene, ARigidFitDoesNotSpreadAReflectionOverTheSegment) {
  ExpectTheHarderSceneLabelledRight(11, 4400);
}

// Seed 35 of the harder scene, its first 1,600 frames. LFHD hidden, the head held by its three
// other markers: the segment registration gave it a reflection 33-38 mm from its place for 13
// frames. With the reflection as a fourth anchor the head's rigid fit spread the error over the
// four, each residual within its tolerance and the whole fit's chi-square within its tail. A
// label given anew is now also judged by where the other anchors alone put it (its deleted
// residual, against the point's variance and the others' fit's covariance).
TEST(TrackHarderScene, ALabelGivenAnewIsJudgedByWhereTheOtherAnchorsPutIt) {
  ExpectTheHarderSceneLabelledRight(35, 1600);
}

// Seed 21 of the harder scene, its first 8,300 frames. The right foot's heel marker hidden, the
// limb search turned the foot to put RTOE on a reflection at its distance from the ankle, and
// the label held 69 frames. The test that a limb search's one new label on a point with no rigid
// past is refused asked for the marker to be its segment's only marker (a hand's finger marker);
// a foot whose other marker is hidden turns as freely: now the only marker of its segment that
// the placement labels.
TEST(TrackHarderScene, ALimbSearchDoesNotTurnAFootOntoAPointWithNoRigidPast) {
  ExpectTheHarderSceneLabelledRight(21, 8300);
}

// Seed 34 of the harder scene, its first 9,900 frames. The left forearm turned while its wrist
// markers were hidden by turns, and the track came out of it with the pair crossed (LWRA on
// LWRB's point), its forearm marker left unlabelled. The segment registration's re-check found
// the exchange and set both labels right, but the filter, on probation, had not yet moved: the
// next frame's gates, about the crossed pose, gave the points back crossed: in these frames 217
// wrong labels, 8 swaps, the longest 62 frames (the whole take: 1,394, 25 and 299, 0.9865, the
// sweep's worst seed). A label the registration's re-check moved to another point outside its
// gate now keeps the point that continues it to its second frame, when its limb is placed anew.
TEST(TrackHarderScene, ALabelTheRegistrationSetsRightSurvivesTheNextFramesGate) {
  ExpectTheHarderSceneLabelledRight(34, 9900);
}

// Seed 42 of the harder scene, its first 14,100 frames. LTOE hidden in the swap traps; 90 ms
// later its gate, grown about the foot's free turn, took a lasting reflection 57 mm off, and the
// label followed the reflection for 389 frames (397 wrong labels). A point that continues an
// unclaimed track is now
// taken afresh only when the marker's prediction explains it clearly better than the density of
// lasting reflections does.
TEST(TrackHarderScene, AHiddenMarkersGrownGateDoesNotTakeALastingReflection) {
  ExpectTheHarderSceneLabelledRight(42, 14100);
}

// Seed 33 of the harder scene tracked with the true model, its first 5,600 frames. In the ankle
// circles LTOE was hidden, its heel marker labelled; a reflection riding with the shank stayed
// about 60-70 mm from LTOE's prediction, and the limb search turned the foot about the line from
// the ankle centre to the heel to put LTOE on it. The gate then followed the reflection for 106
// frames (109 wrong labels), and the foot stayed off its markers for 350 frames more. A new label
// the limb search gives a marker its segment does not pin (fewer than three mates labelled; only
// a marker alone on its segment before) now needs a past that moved rigidly with the segment.
TEST(TrackHarderScene, ALimbSearchDoesNotTurnAFootAboutItsHeelOntoAReflection) {
  ExpectTheHarderSceneLabelledRight(33, 5600, true);
}

// Seed 24 of the harder scene tracked with the true model, its first 4,600 frames (into the
// ankle circles). LFIN hidden with the hand still: a reflection born 40 mm from its point, riding
// with the hand, came into its gate (18 mm in standard deviation about a prediction 1 mm off) and
// held the label for 35 frames. As seed 47 at 5 ghosts (TrackAnkleCircles): a hidden marker's
// gate now has the spread the forecasts of its place showed.
TEST(TrackHarderScene, AStillHandsHiddenFingerMarkerDoesNotTakeAReflectionBesideIt) {
  ExpectTheHarderSceneLabelledRight(24, 4600, true);
}

// Seed 10 of the harder scene tracked with the true model, its first 200 frames (the static
// start). RWRB hidden from frame 7; at frame 26, in the track's first second (whose labels the
// limb search may revise), a reflection appeared 63 mm from RWRA and the limb search's best
// placement of the forearm put RWRA on it and RWRB on RWRA's point: the forearm turned 7 cm at
// once, and RWRB held RWRA's point for 51 frames. The placement replaces the limb's coordinates
// at full trust, so a label it gives now needs a point the last frame had (the gates' labels go
// through probation for the same reason).
TEST(TrackHarderScene, ALimbSearchDoesNotPlaceALimbOnAPointNewInThisFrame) {
  ExpectTheHarderSceneLabelledRight(10, 200, true);
}

// Seeds 93 and 101 of the harder scene tracked with the true model, their first 300 and 700
// frames (the static start; seeds the rules were never tuned on). In the track's first second
// a foot's toe marker was hidden (93: LTOE from frame 2, its heel labelled; 101: RTOE from frame
// 165, the heel hidden too) and a still reflection stood 145-163 mm from its place;
// the limb search, whose rule for an unpinned new label (UnpinnedMarkerWithoutPast) did not
// hold in the first second, turned the foot onto it: 65 and 378 wrong frames. With the subject
// standing still the reflection's past is as still as the marker's would be, so a lone new label
// on a still point is no evidence that the point is the marker, in the first second too.
TEST(TrackHarderScene, ALimbSearchInTheFirstSecondDoesNotTurnAFootOntoAStillReflection) {
  ExpectTheHarderSceneLabelledRight(93, 300, true);
  ExpectTheHarderSceneLabelledRight(101, 700, true);
}

// Seed 159 of the harder scene (a hold-out seed), its first 9,500 frames (into the left elbow's
// flexion-pronation). The forearm turned while its markers were hidden; from frame 9427 LWRB held
// LWRA's point (LWRB's own point and LFRM hidden), LWRA unlabelled beside it. The limb re-check
// waits for a point no marker holds that moved rigidly with the limb: LFRM's and LWRB's came back
// at 9451-9453 but stood still (the forearm barely moving) until ~9460. The re-check was tried
// only on every 20th frame of LWRA's unlabelled run, and a one-frame label at 9459 (dropped the
// next frame) restarted that run: LWRB on LWRA's point for 46 frames, to 9472. A label that does
// not last past its first frame now leaves its marker stuck, and the check runs every 5 frames
// (a rigid past is judged over 5): 38 frames, the re-check's placement taken at frame 9464.
TEST(TrackHarderScene, ALimbReCheckRunsWhenItsEvidenceComesBack) {
  std::vector<double> scales;
  const mocap::sim::TrackRun run =
      TrackHarderScene(159, {}, 9500, mocap::ekf::TrackerOptions::ScaleToSubject::kAlways, &scales);
  ASSERT_TRUE(run.scored);
  std::printf("seed 159, 8 ghosts, frames 0-9499: accuracy %.6f, wrong %ld, swaps %d, longest %d\n",
              run.score.accuracy(), static_cast<long>(run.score.wrong), run.score.swaps_longer_than_5_frames,
              run.score.longest_wrong_run);
  EXPECT_EQ(run.reinitialisations(), 0);
  EXPECT_LE(run.score.longest_wrong_run, 40);
  EXPECT_LE(run.score.wrong, 40);
}

// Seed 10 of the harder scene, the static pose alone (3 s; another draw of ghosts and gaps than
// the whole protocol's). At the model's own size the start put RTOE on a ghost, and the point
// track kept it there for 111 frames (0.975 of the labels). The scaled search labels RTOE on its
// own point and RKNE besides; when the scaled labelling was taken only if it kept every label the
// model's own size gave, the wrong one stayed. Now each labelling is fitted with the scales free
// to it alone, and the scaled one, clearly better (6.3 against 10.3 x 10^-3 m^2), starts: 2 wrong
// labels, none longer than a frame. Since the twentieth session the start at the model's own size
// leaves that label empty too (a label that turns its limb past a nearer unclaimed point:
// LeaveSelfDecidedLabelsEmpty; RTOE's own point 107 mm from where the rest of the body puts it,
// the reflection 122 mm): both
// sizes are asserted.
TEST(TrackScaledStart, AScaledLabellingThatFitsClearlyBetterStarts) {
  using Scale = mocap::ekf::TrackerOptions::ScaleToSubject;
  std::vector<double> scales;
  const mocap::sim::TrackRun own = TrackHarderScene(10, {"static"}, 600, Scale::kWhenTheModelDoesNotFit, &scales);
  ASSERT_TRUE(own.scored);
  std::printf("seed 10, 8 ghosts, static, the model's own size: accuracy %.6f, wrong %ld, swaps %d\n",
              own.score.accuracy(), static_cast<long>(own.score.wrong), own.score.swaps_longer_than_5_frames);
  EXPECT_EQ(own.score.swaps_longer_than_5_frames, 0);
  EXPECT_GE(own.score.accuracy(), 0.9995);
  const mocap::sim::TrackRun scaled = TrackHarderScene(10, {"static"}, 600, Scale::kAlways, &scales);
  ASSERT_TRUE(scaled.scored);
  EXPECT_FALSE(scales.empty());
  std::printf("seed 10, 8 ghosts, static, scaled to the subject: accuracy %.6f, wrong %ld, swaps %d\n",
              scaled.score.accuracy(), static_cast<long>(scaled.score.wrong), scaled.score.swaps_longer_than_5_frames);
  EXPECT_EQ(scaled.frames, 600);
  EXPECT_EQ(scaled.first_tracking, 0);
  EXPECT_LE(scaled.score.wrong, 2);
  EXPECT_EQ(scaled.score.swaps_longer_than_5_frames, 0);
  EXPECT_GE(scaled.score.accuracy(), 0.9999);
}

namespace {
// The issue's scene for `seed` recorded at `rate_hz`, its first `frames` frames: started at frame
// 0, no re-initialisation, no swap longer than 5 frames, no wrong run longer than 2 frames, and
// at least `min_accuracy` of the labels.
void ExpectTheIssueSceneAtRateLabelledRight(std::uint64_t seed, double rate_hz, int frames,
                                            double min_accuracy, bool true_model = false) {
  mocap::sim::TrackingScene scene;
  const mocap::sim::TrackRun run = TrackIssueScene(seed, frames, &scene, nullptr, rate_hz, true_model);
  ASSERT_TRUE(run.scored);
  std::printf("seed %llu, 5 ghosts, %g Hz, %s model, frames 0-%d: accuracy %.6f, wrong %ld, swaps %d, longest %d\n",
              static_cast<unsigned long long>(seed), rate_hz, true_model ? "true" : "nominal", frames - 1, run.score.accuracy(),
              static_cast<long>(run.score.wrong), run.score.swaps_longer_than_5_frames,
              run.score.longest_wrong_run);
  EXPECT_EQ(run.frames, frames);
  EXPECT_EQ(run.first_tracking, 0);
  EXPECT_EQ(run.reinitialisations(), 0);
  EXPECT_EQ(run.score.swaps_longer_than_5_frames, 0);
  EXPECT_LE(run.score.longest_wrong_run, 2);
  EXPECT_GE(run.score.accuracy(), min_accuracy);
}
}  // namespace

// The issue's scene at 50 Hz (a gait lab's rate), seed 16, its first 3,000 frames (to the end of
// the right wrist circles). Over the quiet minute before, the learnt process noise of the
// wrist's coordinates fell towards its floor: their markers' innovations (1-2 mm) lay inside a
// spread the measurement variance, an upper bound, made half of, and counted at a weight near 0
// only ever said "too large". When the circles began, the innovations beyond the whole spread
// were weighed as little; the hand fell behind its points, RWRA, RWRB and RFIN were left
// unlabelled 10-160 frames with their points 0.2-0.5 m from their predictions, and a wrist pair
// crossed for 20 frames (the sweep's worst seed at 50 Hz, 0.9945). At 40 Hz and up the
// innovations are now matched against the prediction's part plus the learnt model error, and
// those beyond the whole spread count in full (ekf/tracker.cpp, LearnProcessNoise).
TEST(TrackFrameRate, AHandFollowsTheWristCirclesAfterAQuietMinuteAt50Hz) {
  ExpectTheIssueSceneAtRateLabelledRight(16, 50.0, 3000, 0.999);
}

// The issue's scene at 50 Hz, seed 15, its first 300 frames (the static start). LTOE, labelled
// from frame 0 beside a reflection fixed 10-11 cm away, was hidden at frames 12-13; at frame 14
// its gate, still as wide as the start's (the learnt process noise has had 0.3 s), took the
// reflection, and the label followed it for 54 frames. In the track's first second a marker's
// seen-beside records keep it from such a point only once it has held its point for a while:
// that was 20 frames, 0.1 s at 200 Hz but 0.4 s here; it is now 0.1 s at any rate.
TEST(TrackFrameRate, AToeMarkerHeldAQuarterSecondTakesNoReflectionItWasSeenBesideAt50Hz) {
  ExpectTheIssueSceneAtRateLabelledRight(15, 50.0, 300, 0.999);
}

// The issue's scene at 50 Hz with the true model, seed 13, its first 3,200 frames (through the
// right elbow's flexion-pronation, pronation -89..85 degrees in 2 s). From frame 2649 the right
// forearm and hand were labelled one marker round: RWRA on RWRB's point, RFIN on RWRA's, RWRB
// unlabelled with its own point 44 mm from its prediction -- every label on a point, every
// distance the gates check right, so nothing revisited it after the track's first second: 496
// frames wrong at a stretch, ~1,900 in the take. The limb re-check searches such a limb with its
// labels free and takes the placement that labels more of it: 43 frames wrong at a stretch
// (the stuck marker waits kStuckFrames, 0.4 s here, and the first placements the search finds
// cross the wrist pair and are refused).
TEST(TrackFrameRate, ALimbLabelledOneMarkerRoundIsReCheckedAt50Hz) {
  mocap::sim::TrackingScene scene;
  const mocap::sim::TrackRun run = TrackIssueScene(13, 3200, &scene, nullptr, 50.0, true);
  ASSERT_TRUE(run.scored);
  std::printf("seed 13, 5 ghosts, 50 Hz, true model, frames 0-3199: accuracy %.6f, wrong %ld, swaps %d, longest %d\n",
              run.score.accuracy(), static_cast<long>(run.score.wrong),
              run.score.swaps_longer_than_5_frames, run.score.longest_wrong_run);
  EXPECT_EQ(run.first_tracking, 0);
  EXPECT_EQ(run.reinitialisations(), 0);
  EXPECT_LE(run.score.longest_wrong_run, 50);
  EXPECT_LE(run.score.wrong, 100);
  EXPECT_GE(run.score.accuracy(), 0.998);
}

// The points written by --write-points, read back as TRC and as C3D, give the same labels.
TEST_F(TrackCli, PointsFilesTrackLikeTheSimulation) {
  const std::string scene =
      "track --simulate --seed 11 --movements static,squats --duration-scale 0.4 --ghosts 2 --model " +
      P("sim/nominal.model.json");
  CommandResult r = Mocap(scene + " --write-points --out " + P("pts_sim"));
  ASSERT_EQ(r.status, 0) << r.output;
  r = Mocap("convert " + P("pts_sim/points.trc") + " " + P("pts_sim/points.c3d"));
  ASSERT_EQ(r.status, 0) << r.output;
  mocap::formats::MarkerTrial reference;
  ASSERT_TRUE(mocap::formats::ReadTrc(P("pts_sim/labelled.trc"), &reference).ok());
  for (const char* ext : {"trc", "c3d"}) {
    const std::string out = std::string("pts_") + ext;
    r = Mocap("track --points " + P("pts_sim/points.") + ext + " --model " + P("sim/nominal.model.json") +
              " --out " + P(out));
    ASSERT_EQ(r.status, 0) << r.output;
    const nlohmann::json s = Stats(out);
    EXPECT_EQ(s["frames"], reference.num_frames());
    EXPECT_FALSE(s.contains("label_accuracy")) << "no truth with a points file";
    mocap::formats::MarkerTrial labelled;
    ASSERT_TRUE(mocap::formats::ReadTrc(P(out + "/labelled.trc"), &labelled).ok());
    ASSERT_EQ(labelled.num_frames(), reference.num_frames());
    long same = 0, total = 0;
    for (int f = 0; f < labelled.num_frames(); ++f)
      for (int m = 0; m < 39; ++m) {
        if (!reference.Has(f, m)) continue;
        ++total;
        same += labelled.Has(f, m) && (labelled.At(f, m) - reference.At(f, m)).norm() < 1e-6;
      }
    EXPECT_GT(total, 0);
    EXPECT_GE(static_cast<double>(same), 0.999 * total) << ext;
  }
}

TEST_F(TrackCli, BadInputGetsAClearError) {
  struct Case {
    std::string args, expect;
  };
  fs::create_directories(P("bad"));
  std::ofstream(P("bad/garbage.trc")) << "not a trc file\n";
  mocap::Model renamed = mocap::sim::MismatchedModel(mocap::DefaultFullBodyModel(), 1, 0.0, "X_");
  ASSERT_TRUE(mocap::SaveModelJson(P("bad/renamed.json"), renamed).ok());
  const std::string sim = "track --simulate --duration-scale 0.3 ";
  const std::vector<Case> cases = {
      {"track --out " + P("bad/o"), "either --simulate or --points"},
      {sim + "--points " + P("bad/garbage.trc") + " --out " + P("bad/o"), "either --simulate or --points"},
      {"track --points " + P("bad/none.trc") + " --out " + P("bad/o"), "none.trc"},
      {"track --points " + P("bad/garbage.trc") + " --out " + P("bad/o"), "garbage.trc"},
      {"track --points " + P("bad/garbage.trc") + " --model nominal --out " + P("bad/o"), "garbage.trc"},
      {sim + "--movements static --fault meteor --out " + P("bad/o"), "--fault meteor"},
      {sim + "--movements static,cartwheel --out " + P("bad/o"), "cartwheel"},
      {sim + "--movements static --occlusion 0.9 --out " + P("bad/o"), "occlusion"},
      {sim + "--movements static --model " + P("bad/renamed.json") + " --out " + P("bad/o"), "none of the simulated subject's"},
      {sim + "--movements static --model " + P("bad/missing.json") + " --out " + P("bad/o"), "missing.json"},
      {sim + "--movements static --up w --out " + P("bad/o"), "--up w"},
      {sim + "--movements static --scale-to-subject sometimes --out " + P("bad/o"), "--scale-to-subject: sometimes"},
      {sim + "--movements static --marker-map " + P("bad/map.txt") + " --out " + P("bad/o"), "--marker-map"},
      {sim + "--movements static --marker-set " + P("bad/set.xml") + " --out " + P("bad/o"), "--marker-set"},
  };
  for (const Case& c : cases) {
    const CommandResult r = Mocap(c.args);
    EXPECT_NE(r.status, 0) << c.args;
    EXPECT_NE(r.output.find(c.expect), std::string::npos) << c.args << "\n" << r.output;
    EXPECT_EQ(r.output.find("terminate"), std::string::npos) << r.output;
  }
}

// --- mocap fit --initial ---------------------------------------------------------------------

class FitInitial : public TrackCli {};

std::map<std::string, nlohmann::json> Parameters(const nlohmann::json& report) {
  std::map<std::string, nlohmann::json> out;
  for (const auto& p : report["parameters"]) out[p["name"].get<std::string>()] = p;
  return out;
}

// The same fitted model whether the fit starts from per-frame IK or from given poses: the
// problem has one minimum near the truth, and both starts reach it. Both runs stop when an
// iteration lowers the cost by less than 1e-6 of it, which leaves the slowest directions (a
// weakly excited ankle) a fraction of their standard deviation apart: every determined parameter
// must agree to half its standard deviation, and marker and joint-centre positions to 0.5 mm.
void ExpectSameFit(const nlohmann::json& a, const nlohmann::json& b) {
  ASSERT_TRUE(a["converged"].get<bool>());
  ASSERT_TRUE(b["converged"].get<bool>());
  // The stopping rule (an iteration gaining less than 1e-6 of the cost) can end one run in a
  // slow valley a few 1e-4 of the cost above the other: what must agree is the model, and the fit
  // quality to a hundredth of a millimetre of marker RMS.
  const double ca = a["final_cost"].get<double>(), cb = b["final_cost"].get<double>();
  EXPECT_NEAR(a["marker_rms_mm"].get<double>(), b["marker_rms_mm"].get<double>(), 0.01);
  const auto pa = Parameters(a), pb = Parameters(b);
  ASSERT_EQ(pa.size(), pb.size());
  double worst = 0;
  std::string which;
  for (const auto& [name, p] : pa) {
    if (!p["determined"].get<bool>()) continue;
    const double d = std::abs(p["value"].get<double>() - pb.at(name)["value"].get<double>()) /
                     std::max(p["std"].get<double>(), 1e-12);
    if (d > worst) worst = d, which = name;
    const std::string group = p["group"].get<std::string>();
    if (group == "centres" || group == "markers")
      EXPECT_LT(std::abs(p["value"].get<double>() - pb.at(name)["value"].get<double>()), 5e-4) << name;
  }
  EXPECT_LT(worst, 0.5) << "determined parameter " << which << " differs by " << worst << " standard deviations";
  std::printf("same fit: final cost %.3f vs %.3f, largest difference %.3f std (%s)\n", ca, cb, worst, which.c_str());
}

TEST_F(FitInitial, TrueCoordinatesStartGivesTheSameModelAsIk) {
  const std::string trials = P("sim/static.trc") + " " + P("sim/squats.trc") + " " + P("sim/hip_star_arc_l.trc");
  const std::string fit = "fit --threads 2 --model " + P("sim/nominal.model.json") + " " + trials;
  CommandResult r = Mocap(fit + " --out " + P("fit_ik/fit.json") + " --report " + P("fit_ik/r.json"));
  ASSERT_EQ(r.status, 0) << r.output;
  r = Mocap(fit + " --initial " + P("sim/static.mot") + " " + P("sim/squats.mot") + " " +
            P("sim/hip_star_arc_l.mot") + " --out " + P("fit_init/fit.json") + " --report " + P("fit_init/r.json"));
  ASSERT_EQ(r.status, 0) << r.output;
  EXPECT_NE(r.output.find("starting poses from"), std::string::npos) << r.output;
  std::ifstream a(P("fit_ik/r.json")), b(P("fit_init/r.json"));
  const nlohmann::json ra = nlohmann::json::parse(a), rb = nlohmann::json::parse(b);
  // The given poses were the start, not IK's: the nominal model misfits the true poses (the
  // subject's geometry differs) where IK bends every pose to it. (The iterations no longer tell
  // them apart: the stages before the last stop at the same 4 + 4 either way.)
  EXPECT_GT(rb["initial_marker_rms_mm"].get<double>(), ra["initial_marker_rms_mm"].get<double>() + 5.0);
  ExpectSameFit(ra, rb);

  // Frames without a pose (NaN rows, as where the tracker was not tracking): solved by IK.
  mocap::formats::CoordinateTable squats;
  ASSERT_TRUE(mocap::formats::ReadMot(P("sim/squats.mot"), &squats).ok());
  ASSERT_GT(squats.num_frames(), 80);
  squats.values.topRows(10).setConstant(std::nan(""));
  squats.values.middleRows(40, 30).setConstant(std::nan(""));
  fs::create_directories(P("fit_gaps"));
  ASSERT_TRUE(mocap::formats::WriteMot(P("fit_gaps/squats.mot"), squats).ok());
  r = Mocap(fit + " --initial " + P("sim/static.mot") + " " + P("fit_gaps/squats.mot") + " " +
            P("sim/hip_star_arc_l.mot") + " --out " + P("fit_gaps/fit.json") + " --report " + P("fit_gaps/r.json"));
  ASSERT_EQ(r.status, 0) << r.output;
  EXPECT_NE(r.output.find("40 frames without one: by IK"), std::string::npos) << r.output;
  std::ifstream c(P("fit_gaps/r.json"));
  ExpectSameFit(ra, nlohmann::json::parse(c));
}

// The tracker's output is a fit's input: labelled.trc the trial, coordinates.mot its start.
TEST_F(FitInitial, TrackerOutputStartsTheFit) {
  const CommandResult t = Mocap("track --simulate --seed 11 --movements static,squats,hip_star_arc_l "
                                "--duration-scale 0.5 --model " + P("sim/nominal.model.json") +
                                " --out " + P("fit_track"));
  ASSERT_EQ(t.status, 0) << t.output;
  const std::string fit = "fit --threads 2 --model " + P("sim/nominal.model.json") + " " + P("fit_track/labelled.trc");
  CommandResult r = Mocap(fit + " --out " + P("fit_track/ik/fit.json") + " --report " + P("fit_track/ik/r.json"));
  ASSERT_EQ(r.status, 0) << r.output;
  r = Mocap(fit + " --initial " + P("fit_track/coordinates.mot") + " --out " + P("fit_track/init/fit.json") +
            " --report " + P("fit_track/init/r.json"));
  ASSERT_EQ(r.status, 0) << r.output;
  std::ifstream a(P("fit_track/ik/r.json")), b(P("fit_track/init/r.json"));
  ExpectSameFit(nlohmann::json::parse(a), nlohmann::json::parse(b));
}

TEST_F(FitInitial, BadInitialPosesGetAClearError) {
  // Tables derived from a good one: a column dropped, a foreign column, a frame cut, a row half NaN.
  mocap::formats::CoordinateTable good;
  ASSERT_TRUE(mocap::formats::ReadMot(P("sim/static.mot"), &good).ok());
  fs::create_directories(P("bad_init"));
  auto write = [&](const std::string& name, mocap::formats::CoordinateTable t) {
    EXPECT_TRUE(mocap::formats::WriteMot(P("bad_init/" + name), t).ok());
    return P("bad_init/" + name);
  };
  mocap::formats::CoordinateTable dropped = good;
  const int knee = dropped.FindColumn("knee_angle_r");
  dropped.column_names.erase(dropped.column_names.begin() + knee);
  mocap::formats::RowMatrix v(good.num_frames(), good.values.cols() - 1);
  v << good.values.leftCols(knee), good.values.rightCols(good.values.cols() - knee - 1);
  dropped.values = v;
  mocap::formats::CoordinateTable foreign = good;
  foreign.column_names[knee] = "knee_flexion_right";
  mocap::formats::CoordinateTable cut = good;
  cut.values.conservativeResize(good.num_frames() - 5, Eigen::NoChange);
  cut.times.resize(good.num_frames() - 5);
  mocap::formats::CoordinateTable half = good;
  half.values(3, knee) = std::nan("");
  mocap::formats::CoordinateTable none = good;
  none.values.setConstant(std::nan(""));
  const std::string fit = "fit --model " + P("sim/nominal.model.json") + " " + P("sim/static.trc") +
                          " --out " + P("bad_init/fit.json") + " --initial ";
  struct Case {
    std::string initial, expect;
  };
  const std::vector<Case> cases = {
      {write("dropped.mot", dropped), "no column for 1 coordinate(s) of model"},
      {write("foreign.mot", foreign), "'knee_flexion_right' is not a coordinate"},
      {write("cut.mot", cut), "frames, its trial has"},
      {write("half.mot", half), "frame 4 are partly missing"},
      {write("none.mot", none), "no frame has a pose"},
      {P("bad_init/absent.mot"), "absent.mot"},
      {P("sim/static.mot") + " " + P("sim/squats.mot"), "2 .mot file(s) for 1 trial(s)"},
  };
  for (const Case& c : cases) {
    const CommandResult r = Mocap(fit + c.initial);
    EXPECT_NE(r.status, 0) << c.initial;
    EXPECT_NE(r.output.find(c.expect), std::string::npos) << c.initial << "\n" << r.output;
  }
  // A squats .mot for the static trial: the frame counts differ, and the message says so.
  const CommandResult r = Mocap(fit + P("sim/squats.mot"));
  EXPECT_NE(r.status, 0);
  EXPECT_NE(r.output.find("squats.mot (for " + P("sim/static.trc") + "): has"), std::string::npos) << r.output;
}

}  // namespace
