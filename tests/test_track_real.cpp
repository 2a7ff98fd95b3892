// The tracker (ekf/tracker.h) where the lab is not ours (issue 15, item 3): a lab whose vertical
// is not the model's, a model with virtual markers no data shows, and the real recordings of
// ../shared/data with their labels removed and the points shuffled per frame (sim::Unlabel),
// scored against the original labels.
//
// Real recordings: welk007 (Motion Analysis, 100 Hz, Z up) against its OpenSim models (Y up, 16
// virtual markers such as R_HJC that no trial has), biobuddy's P01 (Vicon Plug-in Gait + 21 extra
// markers, 12 Hz, -Z up) against the default model. The targets (>= 0.999 without ghosts,
// >= 0.995 with 5 a frame, no swap > 5 frames) are the DISABLED_ tests below: not met yet.
#include <gtest/gtest.h>

#include <cstdio>
#include <memory>
#include <string>

#include "ekf/tracker.h"
#include "file_test_util.h"
#include "formats/marker_file.h"
#include "formats/osim.h"
#include "model/default_model.h"
#include "sim/track_run.h"
#include "sim/tracking_scene.h"

namespace {

using mocap::ekf::TrackState;

mocap::sim::TrackingScene ShortScene() {
  mocap::sim::TrackingSceneOptions o;
  o.seed = 4;
  o.movements = {"static", "squats", "trunk_rom"};
  o.duration_scale = 0.4;
  o.ghosts = 3;
  o.occlusion = 0.05;
  mocap::sim::TrackingScene scene;
  EXPECT_TRUE(mocap::sim::MakeTrackingScene(o, &scene).ok());
  return scene;
}

mocap::sim::TrackRun Track(const mocap::sim::TrackingScene& scene, const mocap::Model& model,
                           const mocap::ekf::TrackerOptions& options) {
  mocap::ekf::Tracker tracker(std::make_shared<const mocap::Model>(model), options);
  return mocap::sim::TrackScene(scene, &tracker);
}

// The same scene in a lab whose vertical is -Z (turned half a revolution about Y, as biobuddy's
// data): told `up`, the tracker labels it as it labels the upright one. Without the turn onto the
// model's vertical it cannot: the default model's pelvis tilt and list stop at 90 degrees.
TEST(TrackLab, UpsideDownLabTracksLikeTheUprightOne) {
  const mocap::sim::TrackingScene upright = ShortScene();
  mocap::sim::TrackingScene turned = upright;
  const Eigen::Matrix3d half_turn = Eigen::AngleAxisd(M_PI, Eigen::Vector3d::UnitY()).toRotationMatrix();
  for (Eigen::Matrix3Xd& p : turned.points) p = half_turn * p;
  mocap::ekf::TrackerOptions o;
  const mocap::sim::TrackRun a = Track(upright, upright.nominal, o);
  o.up = -Eigen::Vector3d::UnitZ();
  const mocap::sim::TrackRun b = Track(turned, turned.nominal, o);
  std::printf("upright: accuracy %.6f, first tracking frame %d; upside down: %.6f, %d\n",
              a.score.accuracy(), a.first_tracking, b.score.accuracy(), b.first_tracking);
  EXPECT_GE(a.score.accuracy(), 0.999);
  EXPECT_GE(b.score.accuracy(), 0.999);
  EXPECT_LE(b.first_tracking, a.first_tracking + 2);
  EXPECT_EQ(b.score.swaps_longer_than_5_frames, 0);
  EXPECT_EQ(b.reinitialisations(), 0);
}

// The model in Y-up axes (an OpenSim model's) in the Z-up lab: model_up says so.
TEST(TrackLab, YUpModelInAZUpLab) {
  const mocap::sim::TrackingScene scene = ShortScene();
  // The scene's points turned so that its Z (the subject's vertical) becomes Y: a Y-up lab.
  mocap::sim::TrackingScene y_up = scene;
  const Eigen::Matrix3d z_to_y = Eigen::AngleAxisd(-M_PI / 2, Eigen::Vector3d::UnitX()).toRotationMatrix();
  for (Eigen::Matrix3Xd& p : y_up.points) p = z_to_y * p;
  mocap::ekf::TrackerOptions o;
  o.up = Eigen::Vector3d::UnitY();
  const mocap::sim::TrackRun run = Track(y_up, scene.nominal, o);
  std::printf("Y-up lab: accuracy %.6f, first tracking frame %d\n", run.score.accuracy(), run.first_tracking);
  EXPECT_GE(run.score.accuracy(), 0.999);
  EXPECT_GE(run.first_tracking, 0);
  EXPECT_LE(run.first_tracking, 5);
  EXPECT_EQ(run.score.swaps_longer_than_5_frames, 0);
}

// A model with 12 virtual markers (joint centres and mid-points) besides the 39 worn ones: 39
// of 51 is less than init_min_fraction (0.8), so counted over all markers the tracker never
// starts. Told they are unseen, it starts, labels as before and never gives a virtual marker a
// point.
TEST(TrackLab, VirtualMarkersAreNeitherCountedNorLabelled) {
  const mocap::sim::TrackingScene scene = ShortScene();
  std::vector<mocap::Marker> markers = scene.nominal.markers();
  std::vector<std::string> virtual_names;
  for (int s = 0; s < scene.nominal.num_segments() && virtual_names.size() < 12; ++s) {
    mocap::Marker v;
    v.name = "virtual_" + scene.nominal.segments()[s].name;
    v.segment = s;
    v.position = Eigen::Vector3d(0.0, 0.0, 0.01);
    markers.push_back(v);
    virtual_names.push_back(v.name);
  }
  mocap::Model with_virtual;
  const mocap::Model& n = scene.nominal;
  ASSERT_TRUE(mocap::Model::Build(n.name(), n.segments(), n.joints(), n.coordinates(), markers,
                                  n.derived_coordinates(), &with_virtual)
                  .ok());
  mocap::ekf::TrackerOptions o;
  mocap::sim::TrackingScene first_second = scene;  // each failed search costs ~20 ms
  first_second.times.resize(200);
  first_second.points.resize(200);
  first_second.labels.resize(200);
  const mocap::sim::TrackRun counted = Track(first_second, with_virtual, o);
  EXPECT_EQ(counted.frames_tracking(), 0) << "39 of 51 markers can never be 80 %";
  o.unseen_markers = virtual_names;
  o.unseen_markers.push_back("a marker no model has");
  mocap::ekf::Tracker tracker(std::make_shared<const mocap::Model>(with_virtual), o);
  int virtual_labels = 0;
  const int first_virtual = scene.nominal.num_markers();
  const mocap::sim::TrackRun run =
      mocap::sim::TrackScene(scene, &tracker, [&](int, const mocap::ekf::TrackOutput& out) {
        for (int m = first_virtual; m < with_virtual.num_markers(); ++m)
          virtual_labels += out.point_of_marker[m] >= 0;
      });
  std::printf("with 12 virtual markers, told: accuracy %.6f, first tracking frame %d\n",
              run.score.accuracy(), run.first_tracking);
  EXPECT_GE(run.score.accuracy(), 0.999);
  EXPECT_LE(run.first_tracking, 5);
  EXPECT_EQ(virtual_labels, 0);
}

struct RealResult {
  mocap::sim::TrackRun run;
  std::string summary;
};

// The trial unlabelled and shuffled (plus `ghosts` a frame), tracked with `model`; the model's
// markers that the trial never shows are the tracker's unseen markers (what `mocap track
// --points` does with a labelled file).
RealResult TrackRecording(const std::string& trial_path, const mocap::Model& model, const Eigen::Vector3d& up,
                          const Eigen::Vector3d& model_up, int ghosts) {
  mocap::formats::MarkerTrial trial;
  const mocap::Status read = mocap::formats::ReadMarkerFile(trial_path, &trial);
  EXPECT_TRUE(read.ok()) << read.message();
  mocap::sim::UnlabelOptions uo;
  uo.ghosts = ghosts;
  const mocap::sim::UnlabelledTrial frames = mocap::sim::Unlabel(trial, model, uo);
  mocap::ekf::TrackerOptions o;
  o.rate_hz = trial.rate_hz;
  o.up = up;
  o.model_up = model_up;
  for (int m = 0; m < model.num_markers(); ++m)
    if (!frames.model_marker_present[m]) o.unseen_markers.push_back(model.markers()[m].name);
  mocap::ekf::Tracker tracker(std::make_shared<const mocap::Model>(model), o);
  RealResult r;
  // Why the search refused, on each frame before the track started (the first few).
  std::string refusals;
  r.run = mocap::sim::RunTracker(frames.Input(model.num_markers()), &tracker,
                                 [&](int f, const mocap::ekf::TrackOutput& out) {
                                   if (out.state == TrackState::kTracking || f >= 8) return;
                                   const mocap::ekf::InitialisationSummary& i = tracker.initialisation();
                                   refusals += "\n  frame " + std::to_string(f) + ": " + i.reason + " (" +
                                               std::to_string(i.labelled) + " labelled, rms " +
                                               std::to_string(i.rms_m) + " m, score " +
                                               std::to_string(i.best_score) + ", runner-up " +
                                               std::to_string(i.runner_up_score) + ")";
                                 });
  char line[512];
  std::snprintf(line, sizeof line,
                "%s, %d ghosts: %d frames, %d tracking (first %d), %d re-inits, accuracy %.6f, %ld "
                "wrong, swaps > 5 frames %d, longest wrong run %d; last search: %s",
                trial_path.c_str(), ghosts, r.run.frames, r.run.frames_tracking(), r.run.first_tracking,
                r.run.reinitialisations(), r.run.score.accuracy(), r.run.score.wrong,
                r.run.score.swaps_longer_than_5_frames, r.run.score.longest_wrong_run,
                tracker.initialisation().reason.c_str());
  r.summary = line;
  std::printf("%s%s\n", line, refusals.c_str());
  for (int m = 0; m < model.num_markers(); ++m)
    if (r.run.marker_samples[m] > 0 && r.run.marker_correct[m] < 0.99 * r.run.marker_samples[m])
      std::printf("  %s: %ld of %ld right\n", model.markers()[m].name.c_str(), r.run.marker_correct[m],
                  r.run.marker_samples[m]);
  return r;
}

// An OpenSim model, with its marker set when the .osim has none inside (gait2354's).
mocap::Model OsimModel(const std::string& path, const std::string& marker_set = "") {
  mocap::formats::OsimImport import;
  mocap::Status s = mocap::formats::ImportOsim(path, &import);
  EXPECT_TRUE(s.ok()) << s.message();
  if (s.ok() && !marker_set.empty()) s = mocap::formats::LoadOsimMarkerSet(marker_set, &import);
  EXPECT_TRUE(s.ok()) << s.message();
  return import.model;
}

std::string Welk(const std::string& file) { return mocap::testutil::SharedData() + "/welk007_hipfunc/" + file; }

// Z-up lab, Y-up OpenSim model (the subject's hand-scaled one), 16 virtual markers: before, the
// tracker never started (54 points < 80 % of 72 markers). Now it starts on the first frame and
// holds every frame; what it still gets wrong is the wrist pair (radius and ulna swapped: a swap
// of two markers is not among the hypotheses the initialisation's ambiguity test compares).
TEST(TrackReal, Welk007StaticStartsWithItsScaledOpenSimModel) {
  SKIP_WITHOUT_SHARED_DATA();
  const mocap::Model model = OsimModel(Welk("manually_scaled.osim"));
  for (int ghosts : {0, 5}) {
    const RealResult r = TrackRecording(Welk("c3d_Trimmed_static1.c3d"), model, Eigen::Vector3d::UnitZ(),
                                        Eigen::Vector3d::UnitY(), ghosts);
    EXPECT_EQ(r.run.first_tracking, 0) << r.summary;
    EXPECT_EQ(r.run.frames_tracking(), r.run.frames) << r.summary;
    EXPECT_GE(r.run.score.accuracy(), 0.92) << r.summary;
  }
}

// The targets on the real recordings. Not met (sixth session): welk007 static with the
// scaled model 0.923 (wrists swapped), the right-hip trial 0.94; with unscaled_generic.osim the
// search labels 19-29 of 52 markers (a labelled IK of that model on the static trial leaves 84 mm
// RMS, the scaled model 14.7 mm: the generic model does not fit this subject within the 5 cm the
// search matches in); biobuddy P01 with the default model starts late and wrongly (0.059 without
// ghosts, 0.230 with 5: the 21 extra markers near the Plug-in Gait ones take their places).
TEST(TrackReal, DISABLED_Welk007MeetsTheTargetsWithItsGenericModel) {
  SKIP_WITHOUT_SHARED_DATA();
  const mocap::Model model = OsimModel(Welk("unscaled_generic.osim"));
  for (const char* trial : {"c3d_Trimmed_static1.c3d", "c3d_Trimmed_RHJC1.c3d"})
    for (int ghosts : {0, 5}) {
      const RealResult r = TrackRecording(Welk(trial), model, Eigen::Vector3d::UnitZ(), Eigen::Vector3d::UnitY(),
                                          ghosts);
      EXPECT_GE(r.run.score.accuracy(), ghosts == 0 ? 0.999 : 0.995) << r.summary;
      EXPECT_EQ(r.run.score.swaps_longer_than_5_frames, 0) << r.summary;
    }
}

TEST(TrackReal, DISABLED_BiobuddyRightHipMeetsTheTargetsWithTheDefaultModel) {
  SKIP_WITHOUT_SHARED_DATA();
  const mocap::Model model = mocap::DefaultFullBodyModel(1.75);
  const std::string trial = mocap::testutil::SharedData() + "/biobuddy_p01_lowerlimb/Test_func_rhip.c3d";
  for (int ghosts : {0, 5}) {
    const RealResult r = TrackRecording(trial, model, -Eigen::Vector3d::UnitZ(), Eigen::Vector3d::UnitZ(), ghosts);
    EXPECT_GE(r.run.score.accuracy(), ghosts == 0 ? 0.999 : 0.995) << r.summary;
    EXPECT_EQ(r.run.score.swaps_longer_than_5_frames, 0) << r.summary;
  }
}

std::string Gait2354(const std::string& file) {
  return mocap::testutil::SharedData() + "/opensim_gait2354_subject01/" + file;
}

// OpenSim's example subject (60 Hz, Y up, 10 arm and head markers the marker set does not model:
// points that are nobody's), against the generic Gait2354 model with its marker set.
TEST(TrackReal, Gait2354MeetsTheTargetsWithItsGenericModel) {
  SKIP_WITHOUT_SHARED_DATA();
  const mocap::Model model =
      OsimModel(Gait2354("gait2354_simbody.osim"), Gait2354("gait2354_Scale_MarkerSet.xml"));
  for (const char* trial : {"subject01_static.trc", "subject01_walk1.trc"})
    for (int ghosts : {0, 5}) {
      const RealResult r = TrackRecording(Gait2354(trial), model, Eigen::Vector3d::UnitY(),
                                          Eigen::Vector3d::UnitY(), ghosts);
      EXPECT_GE(r.run.score.accuracy(), ghosts == 0 ? 0.999 : 0.995) << r.summary;
      EXPECT_EQ(r.run.score.swaps_longer_than_5_frames, 0) << r.summary;
    }
}

}  // namespace
