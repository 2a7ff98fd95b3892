// The tracker (ekf/tracker.h) where the lab is not ours (issue 15, item 3): a lab whose vertical
// is not the model's, a model with virtual markers no data shows, and the real recordings of
// ../shared/data with their labels removed and the points shuffled per frame (sim::Unlabel),
// scored against the original labels.
//
// Real recordings: welk007 (Motion Analysis, 100 Hz, Z up) against its OpenSim models (Y up, 16
// virtual markers such as R_HJC that no trial has), OpenSim's gait2354 example subject (60 Hz, Y
// up) against the generic Gait2354 model, biobuddy's P01 (Vicon Plug-in Gait + 21 extra markers,
// 12 Hz, -Z up) against the default model. The targets (>= 0.999 without ghosts, >= 0.995
// with 5 a frame, no swap > 5 frames) hold on the two static trials, welk007's hip trial with its
// scaled model, and -- with the generic models calibrated on the subject's static trial first, as
// a lab labels (solver/subject_calibration.h) -- welk007's hip trial and gait2354's walk; the
// DISABLED_ tests below hold them where they are not met (BENCHMARKS.md, "Real recordings,
// unlabelled").
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <cstdio>
#include <memory>
#include <string>

#include <nlohmann/json.hpp>

#include "ekf/tracker.h"
#include "file_test_util.h"
#include "formats/marker_file.h"
#include "formats/osim.h"
#include "model/default_model.h"
#include "sim/track_run.h"
#include "sim/tracking_scene.h"
#include "solver/subject_calibration.h"

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

// The scene's first `frames` frames.
mocap::sim::TrackingScene FirstFrames(mocap::sim::TrackingScene scene, int frames) {
  scene.times.resize(frames);
  scene.points.resize(frames);
  scene.labels.resize(frames);
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
  const mocap::sim::TrackingScene first_second = FirstFrames(scene, 200);  // each failed search costs ~20 ms
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

// A model smaller than the subject (legs, trunk and arms 10 % short, as a generic model is for a
// tall subject: OpenSim's gait2354 femurs are 15 % short of its example subject's): its best
// placement leaves too many markers beyond the search's 5 cm, and as given it does not start.
// Scaled to the subject from that placement (TrackerOptions::init_scale_to_subject), it starts at
// once and labels as the right-sized model does, and the scales it found undo the shortening.
// (Only the legs 15 % short, it starts as given with knees and ankles crossed, 0.854 of the
// labels, and the scaled search, which would change those labels, is not taken: ekf/tracker.h.)
TEST(TrackLab, AModelTooSmallIsScaledToTheSubject) {
  const mocap::sim::TrackingScene scene = FirstFrames(ShortScene(), 100);
  const mocap::Model& n = scene.nominal;
  Eigen::VectorXd p = n.InitialParameters();
  std::vector<int> shortened;
  for (const char* name : {"femur_l", "femur_r", "tibia_l", "tibia_r", "torso", "humerus_l", "humerus_r", "forearm_l", "forearm_r"}) {
    const int s = n.FindSegment(name);
    ASSERT_GE(s, 0) << name;
    p[n.scale_index(s)] *= 0.9;
    shortened.push_back(s);
  }
  mocap::Model small;
  ASSERT_TRUE(n.WithParameters(p, &small).ok());
  mocap::ekf::TrackerOptions o;
  o.init_scale_to_subject = mocap::ekf::TrackerOptions::ScaleToSubject::kNever;
  const mocap::sim::TrackingScene first = FirstFrames(scene, 40);  // each refused search costs ~40 ms
  const mocap::sim::TrackRun as_given = Track(first, small, o);
  o.init_scale_to_subject = mocap::ekf::TrackerOptions::ScaleToSubject::kWhenTheModelDoesNotFit;
  // By default the size is judged over init_scale_after_s of refused searches (below); here
  // from the first one.
  o.init_scale_after_s = 0;
  mocap::ekf::Tracker tracker(std::make_shared<const mocap::Model>(small), o);
  const mocap::sim::TrackRun scaled = mocap::sim::TrackScene(scene, &tracker);
  const std::vector<double>& found = tracker.initialisation().segment_scales;
  std::printf("model 10 %% short: as given accuracy %.6f (first tracking frame %d); scaled %.6f (first %d), "
              "wrong %ld, swaps > 5 frames %d; scales",
              as_given.score.accuracy(), as_given.first_tracking, scaled.score.accuracy(), scaled.first_tracking,
              scaled.score.wrong, scaled.score.swaps_longer_than_5_frames);
  for (int s : shortened) std::printf(" %s %.3f", n.segments()[s].name.c_str(), found.empty() ? 0.0 : found[s]);
  std::printf("\n");
  ASSERT_EQ(found.size(), static_cast<size_t>(n.num_segments()));
  // The absolute scales: every one grew from the short model's, and the legs' (the segments
  // with the most markers below them) are back within 5 % of the right-sized model's. (The
  // nominal model is not the subject either: one frame sized the torso 0.94 and a forearm 1.06.)
  const Eigen::VectorXd right = n.InitialParameters();
  for (int s : shortened) {
    EXPECT_GT(found[s], 0.9 * right[n.scale_index(s)] + 0.02) << n.segments()[s].name;
    if (n.segments()[s].name.find("femur") == 0 || n.segments()[s].name.find("tibia") == 0)
      EXPECT_NEAR(found[s], right[n.scale_index(s)], 0.05) << n.segments()[s].name;
  }
  EXPECT_GE(scaled.first_tracking, 0);
  EXPECT_LE(scaled.first_tracking, 5);
  EXPECT_GE(scaled.score.accuracy(), 0.999);
  EXPECT_EQ(scaled.score.swaps_longer_than_5_frames, 0);
  EXPECT_EQ(as_given.frames_tracking(), 0);
  // The default waits 0.25 s (50 frames at 200 Hz) of searches refused for the model's size
  // before it scales, then starts as above: no wrong label.
  mocap::ekf::TrackerOptions d;
  mocap::ekf::Tracker waiting(std::make_shared<const mocap::Model>(small), d);
  const mocap::sim::TrackRun later = mocap::sim::TrackScene(scene, &waiting);
  std::printf("by default: first tracking frame %d, wrong %ld\n", later.first_tracking, later.score.wrong);
  EXPECT_GE(later.first_tracking, 49);
  EXPECT_LE(later.first_tracking, 55);
  EXPECT_EQ(later.score.wrong, 0);
}

// A forearm the start cannot place: the search starts from a pose with the right elbow flexed
// 100 degrees while the subject's arm hangs (welk007's hip trial the other way round), so it
// labels all but the right forearm's 4 markers, whose limb then has no label. The limb search
// places it with the whole arm from the first tracking frame (ekf/tracker.h, "Limb
// re-acquisition"); before, RFRM came at frame 77, RWRA at 45, RWRB and RFIN not in these 200
// frames (0.898750 of the labels).
TEST(TrackLab, AForearmTheStartLeavesIsPlacedAtOnce) {
  const mocap::sim::TrackingScene scene = FirstFrames(ShortScene(), 200);
  const mocap::Model& n = scene.nominal;
  Eigen::VectorXd pose(n.num_coordinates());
  for (int i = 0; i < n.num_coordinates(); ++i) pose[i] = n.coordinates()[i].default_value;
  int elbow = -1;
  for (int i = 0; i < n.num_coordinates(); ++i)
    if (n.coordinates()[i].name == "elbow_flex_r") elbow = i;
  ASSERT_GE(elbow, 0);
  pose[elbow] = 100 * M_PI / 180;
  mocap::ekf::TrackerOptions o;
  o.static_pose = pose;
  mocap::ekf::Tracker tracker(std::make_shared<const mocap::Model>(n), o);
  std::vector<int> first_label(n.num_markers(), -1);
  int start_labelled = -1;
  const mocap::sim::TrackRun run =
      mocap::sim::TrackScene(scene, &tracker, [&](int f, const mocap::ekf::TrackOutput& out) {
        if (out.reinitialised && start_labelled < 0) start_labelled = out.labelled;
        for (int m = 0; m < n.num_markers(); ++m)
          if (out.point_of_marker[m] >= 0 && first_label[m] < 0) first_label[m] = f;
      });
  std::printf("right elbow flexed at the start: accuracy %.6f, %ld wrong, first tracking frame %d, the start labelled %d;",
              run.score.accuracy(), run.score.wrong, run.first_tracking, start_labelled);
  for (const char* name : {"RFRM", "RWRA", "RWRB", "RFIN"})
    std::printf(" %s from %d", name, first_label[n.FindMarker(name)]);
  std::printf("\n");
  ASSERT_EQ(run.first_tracking, 0);
  EXPECT_EQ(start_labelled, n.num_markers() - 4) << "the start labels all but the right forearm";
  for (const char* name : {"RFRM", "RWRA", "RWRB", "RFIN"}) {
    EXPECT_GE(first_label[n.FindMarker(name)], 1) << name;
    EXPECT_LE(first_label[n.FindMarker(name)], 2) << name;
  }
  EXPECT_EQ(run.score.wrong, 0);
  EXPECT_GE(run.score.accuracy(), 0.998);  // 0.998889: the forearm's 4 markers missing 2 frames
}

struct RealResult {
  mocap::sim::TrackRun run;
  std::string summary;
};

// The trial unlabelled and shuffled (plus `ghosts` a frame), tracked with `model`; the model's
// markers that the trial never shows are the tracker's unseen markers (what `mocap track
// --points` does with a labelled file). The models are not the subjects': scaled to them at the
// start (`mocap track --scale-to-subject always`). `keep_every` n > 1: only every n-th frame
// of the trial (a lower frame rate, the same motion).
RealResult TrackRecording(const std::string& trial_path, const mocap::Model& model, const Eigen::Vector3d& up,
                          const Eigen::Vector3d& model_up, int ghosts,
                          mocap::ekf::TrackerOptions::ScaleToSubject scale =
                              mocap::ekf::TrackerOptions::ScaleToSubject::kAlways,
                          int keep_every = 1) {
  mocap::formats::MarkerTrial trial;
  const mocap::Status read = mocap::formats::ReadMarkerFile(trial_path, &trial);
  EXPECT_TRUE(read.ok()) << read.message();
  if (keep_every > 1) {
    const int kept = (trial.num_frames() + keep_every - 1) / keep_every;
    mocap::formats::MarkerTrial thinned = trial;
    thinned.rate_hz = trial.rate_hz / keep_every;
    thinned.positions.resize(kept, trial.positions.cols());
    thinned.times.resize(kept);
    thinned.frame_numbers.resize(kept);
    for (int f = 0; f < kept; ++f) {
      thinned.positions.row(f) = trial.positions.row(f * keep_every);
      thinned.times[f] = trial.times[f * keep_every];
      thinned.frame_numbers[f] = trial.frame_numbers[f * keep_every];
    }
    trial = std::move(thinned);
  }
  mocap::sim::UnlabelOptions uo;
  uo.ghosts = ghosts;
  const mocap::sim::UnlabelledTrial frames = mocap::sim::Unlabel(trial, model, uo);
  mocap::ekf::TrackerOptions o;
  o.rate_hz = trial.rate_hz;
  o.init_scale_to_subject = scale;
  o.up = up;
  o.model_up = model_up;
  for (int m = 0; m < model.num_markers(); ++m)
    if (!frames.model_marker_present[m]) o.unseen_markers.push_back(model.markers()[m].name);
  const auto shared = std::make_shared<const mocap::Model>(model);
  mocap::ekf::Tracker tracker(shared, o);
  const mocap::sim::TrackInput input = frames.Input(model.num_markers());
  RealResult r;
  // Why the search refused, on each frame before the track started (the first few).
  std::string refusals;
  r.run = mocap::sim::RunTracker(input, &tracker,
                                 [&](int f, const mocap::ekf::TrackOutput& out) {
                                   if (out.state == TrackState::kTracking || f >= 8) return;
                                   const mocap::ekf::InitialisationSummary& i = tracker.initialisation();
                                   refusals += "\n  frame " + std::to_string(f) + ": " + i.reason + " (" +
                                               std::to_string(i.labelled) + " labelled, rms " +
                                               std::to_string(i.rms_m) + " m, score " +
                                               std::to_string(i.best_score) + ", runner-up " +
                                               std::to_string(i.runner_up_score) + ")";
                                 });
  const int started = r.run.first_tracking;
  mocap::sim::BackfillBeforeStart(input, shared, o, &r.run);  // as `mocap track --points` does
  char line[512];
  std::snprintf(line, sizeof line,
                "%s, %d ghosts: %d frames, %d tracking (started at %d, backfilled %d), %d re-inits, accuracy %.6f, %ld "
                "wrong, swaps > 5 frames %d, longest wrong run %d; last search: %s",
                trial_path.c_str(), ghosts, r.run.frames, r.run.frames_tracking(), started, r.run.backfilled_frames,
                r.run.reinitialisations(), r.run.score.accuracy(), r.run.score.wrong,
                r.run.score.swaps_longer_than_5_frames, r.run.score.longest_wrong_run,
                tracker.initialisation().reason.c_str());
  r.summary = line;
  std::string scales;
  const std::vector<double>& sc = tracker.initialisation().segment_scales;
  for (size_t k = 0; k < sc.size(); ++k)
    if (std::abs(sc[k] - 1.0) > 0.01)
      scales += " " + model.segments()[k].name + " " + std::to_string(sc[k]).substr(0, 5);
  if (!scales.empty()) scales = "\n  scaled to the subject:" + scales;
  std::printf("%s%s%s\n", line, refusals.c_str(), scales.c_str());
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

// The targets on `trial` without ghosts and with 5 a frame: >= 0.999 / 0.995 of the
// labels right, no swap longer than 5 frames; `from_the_first_frame`: also tracking every frame.
void ExpectTheTargets(const std::string& trial, const mocap::Model& model, const Eigen::Vector3d& up,
                      const Eigen::Vector3d& model_up, bool from_the_first_frame,
                      mocap::ekf::TrackerOptions::ScaleToSubject scale =
                          mocap::ekf::TrackerOptions::ScaleToSubject::kAlways) {
  for (int ghosts : {0, 5}) {
    const RealResult r = TrackRecording(trial, model, up, model_up, ghosts, scale);
    if (from_the_first_frame) {
      EXPECT_EQ(r.run.first_tracking, 0) << r.summary;
      EXPECT_EQ(r.run.frames_tracking(), r.run.frames) << r.summary;
    }
    EXPECT_GE(r.run.score.accuracy(), ghosts == 0 ? 0.999 : 0.995) << r.summary;
    EXPECT_EQ(r.run.score.swaps_longer_than_5_frames, 0) << r.summary;
  }
}

std::string Welk(const std::string& file) { return mocap::testutil::SharedData() + "/welk007_hipfunc/" + file; }

// Z-up lab, Y-up OpenSim model (the subject's hand-scaled one), 16 virtual markers: the issue's
// targets. Before the sixth session the tracker never started (54 points < 80 % of 72 markers);
// then it held every frame with the wrist pairs crossed (radius and ulna markers: 0.923 without
// ghosts, 0.948 with 5), since every search starts the forearm at the near end of its 90 degree
// pronation range and the subject holds it at the far end; exchanging the pair is now a
// hypothesis of the search (ekf/tracker.h, "Initialisation and recovery"). With 5 ghosts C7 was
// then lost from frame 22 (0.987); scaled to the subject at the start it is not (1.000).
TEST(TrackReal, Welk007StaticMeetsTheTargetsWithItsScaledOpenSimModel) {
  SKIP_WITHOUT_SHARED_DATA();
  ExpectTheTargets(Welk("c3d_Trimmed_static1.c3d"), OsimModel(Welk("manually_scaled.osim")),
                   Eigen::Vector3d::UnitZ(), Eigen::Vector3d::UnitY(), true);
}

// The functional hip trial (1224 frames, 48 markers) with the subject's hand-scaled model. The
// subject holds the forearms flexed about 90 degrees in front, pronated past the model's range:
// the start's search, from arms hanging, labels neither forearm, and until the fourteenth session
// their 6 markers were never labelled (0.869547, 0 wrong; with 5 ghosts 117-132 wrong). Now the
// limb search places each forearm with its whole arm from the first tracking frames (ekf/
// tracker.h, "Limb re-acquisition": a limb with no label), its wrist markers exchanged right:
// 0.999716, 0 wrong, with and without ghosts.
TEST(TrackReal, Welk007HipTrialMeetsTheTargetsWithItsScaledOpenSimModel) {
  SKIP_WITHOUT_SHARED_DATA();
  ExpectTheTargets(Welk("c3d_Trimmed_RHJC1.c3d"), OsimModel(Welk("manually_scaled.osim")),
                   Eigen::Vector3d::UnitZ(), Eigen::Vector3d::UnitY(), true);
}

// The targets on welk007 with its generic model: NOT MET. Sixth session: never started,
// the search labelling 19-29 of 52 markers (a labelled IK of that model on the static trial leaves
// 84 mm RMS, the scaled model 14.7 mm). Thirteenth: its 14 stacked cluster markers unseen and the
// model scaled to the subject, static 0.578 / 0.535 with 5 ghosts (from frames 18 / 2; the
// stacked markers never labelled, 1,112 / 1,482 wrong), RHJC1 0.015 / 0.436 (from frames 1189 /
// 198). Fourteenth (main since `always` scales only a start the model's own size accepted, and
// this branch alike): static 0.511785 / 0.516835 (from frames 50 / 12), RHJC1 never starts /
// 0.012374. The target cannot be met with this model: r_thigh1..5 (and each shank's) share one
// point of their segment, so which cluster point is r_thigh3 is not in the model -- any labelling
// of them is a guess among 5! permutations, and leaving them unlabelled caps the accuracy at
// 38/52 of the samples. (Main 9fbd3ee today: static 0.605025 / 0.537037; seventeenth session,
// rigid groups: static 0.623673 / 0.594600, RHJC1 never starts / 0.011251.) Calibrated on the
// static trial first, as a lab does, the model knows them: the hip trial meets the targets (below).
TEST(TrackReal, DISABLED_Welk007MeetsTheTargetsWithItsGenericModel) {
  SKIP_WITHOUT_SHARED_DATA();
  const mocap::Model model = OsimModel(Welk("unscaled_generic.osim"));
  for (const char* trial : {"c3d_Trimmed_static1.c3d", "c3d_Trimmed_RHJC1.c3d"})
    ExpectTheTargets(Welk(trial), model, Eigen::Vector3d::UnitZ(), Eigen::Vector3d::UnitY(), false);
}

// Biobuddy P01 with the default model: NOT MET. Sixth session 0.059 without ghosts, 0.230 with 5
// (the 21 extra markers near the Plug-in Gait ones take their places); thirteenth, scaled to the
// subject at the start, 0.605 and 0.328 (fourteenth: 0.604884 and 0.328449). Why (fourteenth):
// from the start (frame 9) RTHI is on RTHID's point (375 frames), LTIB and RTIB on TIBD's (381,
// 260), RBAK on T6's (312), LTOE on LNAV's (292): this lab wears RTHI and the TIBs 4-8 cm higher
// than the default model places them, and its extra THID and TIBD at about the model's heights
// (distance from the knee marker at frame 20: model THI 213 mm, RTHI 279, RTHID 209; model TIB
// 222, LTIB 184, LTIBD 237, RTIB 139, RTIBD 194). Both points are rigid with the segment, so no
// rule of the tracker tells them apart: the model's marker places decide, and they are the extra
// markers'. From frame ~300 (12 Hz, the hip's fastest swings) the track breaks up (everything
// on anything for ~200 frames). (Main 9fbd3ee today: 0.621636 / 0.391697; seventeenth session,
// rigid groups: 0.847326 / 0.769915, the extra markers' places still the model's.) Calibrated on the
// anatomical posture the extra markers are the subject model's and RTHI is right in every frame;
// what is left is the 12 Hz frame rate (below).
TEST(TrackReal, DISABLED_BiobuddyRightHipMeetsTheTargetsWithTheDefaultModel) {
  SKIP_WITHOUT_SHARED_DATA();
  ExpectTheTargets(mocap::testutil::SharedData() + "/biobuddy_p01_lowerlimb/Test_func_rhip.c3d",
                   mocap::DefaultFullBodyModel(1.75), -Eigen::Vector3d::UnitZ(), Eigen::Vector3d::UnitZ(), false);
}

// The subject model a lab labels with (solver/subject_calibration.h): `generic` fitted to the
// labelled static trial, the trial's markers it lacks attached. A static trial is one posture:
// cheap to fit (two threads, as CI has).
mocap::Model Calibrated(const mocap::Model& generic, const std::string& static_trial) {
  mocap::formats::MarkerTrial trial;
  const mocap::Status read = mocap::formats::ReadMarkerFile(static_trial, &trial);
  EXPECT_TRUE(read.ok()) << read.message();
  mocap::solver::SubjectCalibrationOptions o;
  o.fit.num_threads = 2;
  mocap::Model subject;
  mocap::solver::SubjectCalibrationSummary summary;
  const mocap::Status s = mocap::solver::CalibrateSubject(generic, trial, o, &subject, &summary);
  EXPECT_TRUE(s.ok()) << s.message();
  std::printf("%s: %s\n", static_trial.c_str(), summary.BriefReport().c_str());
  for (const std::string& n : summary.NotAttached()) std::printf("  not attached: %s\n", n.c_str());
  return s.ok() ? subject : generic;
}

// welk007 with its generic model calibrated on the static trial, as a lab would: the 16 stacked
// cluster placeholders placed where the static trial puts them (which cluster point is r_thigh3
// is in the static trial's labels, not in the model), the segments scaled. Then the functional
// hip trial unlabelled: the targets, as with the hand-scaled model (0.999745 with and
// without ghosts, 0 wrong; the generic model as given: never starts / 0.012374).
TEST(TrackReal, Welk007HipTrialMeetsTheTargetsWithItsGenericModelCalibratedOnTheStaticTrial) {
  SKIP_WITHOUT_SHARED_DATA();
  const mocap::Model subject = Calibrated(OsimModel(Welk("unscaled_generic.osim")), Welk("c3d_Trimmed_static1.c3d"));
  ExpectTheTargets(Welk("c3d_Trimmed_RHJC1.c3d"), subject, Eigen::Vector3d::UnitZ(), Eigen::Vector3d::UnitY(), true,
                   mocap::ekf::TrackerOptions::ScaleToSubject::kWhenTheModelDoesNotFit);
}

// The same trial with every 8th frame kept (12.5 Hz, 153 frames): the motion between two frames
// is no longer the prediction's (a marker 5.1 mm from its constant-velocity prediction at the
// median, 63.6 mm at the 95th percentile; the swinging foot's 4-15 cm from the tracker's). The
// issue's targets: NOT MET. Before the sixteenth session 0.797794 without ghosts (1,230 wrong, 24
// swaps > 5 frames): the right arm's labels shifted along the arm from the first tracking frame
// (the start's labels not followed as point tracks, the unlabelled forearm marker's gate 30 cm
// wide) and a foot's gate a metre wide (the process noise at its 200 Hz bound). The process noise
// learnt from the innovations and the start's labels followed: 0.958333 (65 wrong, 3 swaps > 5
// frames) / 0.932190 with 5 ghosts (187 wrong, 7 swaps); main before the seventeenth session
// 0.963508 (86 wrong, 3 swaps) / 0.939270 (198 wrong, 7), the right foot and shank swapping.
// Seventeenth, their markers labelled as rigid groups (ekf/tracker.h, "Rigid groups"): 0.987609
// (13 wrong) / 0.986928 (15 wrong), no swap longer than 5 frames; what is left is markers missed
// in the fastest swings, where the points lie beyond the gates (BENCHMARKS.md, "Real recordings,
// unlabelled"). Twenty-third: those were the right foot's, whose group's sphere about its joint
// centre was 12 cm off: the foot hangs from the talus, which has no markers and so no fit, and
// its centre stayed where the prediction put it; carried by the shank's fit (ekf/tracker.h,
// "Rigid groups") 0.994009 (2 wrong) / 0.993873 (3 wrong). What is left (0 ghosts: 42 samples
// missed, 41 of them the forearms' in frames 0-9, and L_forearm and L_wrist_ulna crossed in
// frame 2) is the forearms' start: the start leaves them (flexed away from the static pose),
// the limb search places one arm a frame from frame 1, and its right labels then fail the
// probation's 1 cm motion test (the limb was placed at rest; 80 ms later it has moved 2-7 cm),
// so they are not measured and are withheld as doubtful returns until a frame's motion happens
// to match.
TEST(TrackReal, Welk007HipTrialAt12HzWithItsCalibratedModel) {
  SKIP_WITHOUT_SHARED_DATA();
  const mocap::Model subject = Calibrated(OsimModel(Welk("unscaled_generic.osim")), Welk("c3d_Trimmed_static1.c3d"));
  for (int ghosts : {0, 5}) {
    const RealResult r = TrackRecording(Welk("c3d_Trimmed_RHJC1.c3d"), subject, Eigen::Vector3d::UnitZ(),
                                        Eigen::Vector3d::UnitY(), ghosts,
                                        mocap::ekf::TrackerOptions::ScaleToSubject::kWhenTheModelDoesNotFit, 8);
    EXPECT_EQ(r.run.frames, 153);
    EXPECT_EQ(r.run.frames_tracking(), r.run.frames) << r.summary;
    // What is reached (0.994009, 2 wrong; 0.993873 with ghosts, 3 wrong: 0.987337 / 0.986928
    // before the twenty-third session), not the accuracy targets; the swap target is met.
    EXPECT_GE(r.run.score.accuracy(), ghosts == 0 ? 0.994 : 0.9938) << r.summary;
    EXPECT_EQ(r.run.score.swaps_longer_than_5_frames, 0) << r.summary;
  }
}

std::string Bio(const std::string& file) {
  return mocap::testutil::SharedData() + "/biobuddy_p01_lowerlimb/" + file;
}

// Biobuddy P01 with the default model calibrated on its anatomical posture: RTHI and the TIBs
// fitted to where this lab wears them, and 17 of its 21 extra markers attached to the segments
// whose markers they sit beside (S1 between torso and pelvis, the medial ankles and LNAV between
// tibia and foot are not). The start no longer puts RTHI on RTHID's point (375 frames with the
// default model as given, 0.604884 of the labels): every right-thigh marker right in every frame,
// 0.907628 of the labels of the 60-marker subject model (the extra ones counted too).
TEST(TrackReal, BiobuddyCalibratedModelTellsTheLabsExtraMarkersApart) {
  SKIP_WITHOUT_SHARED_DATA();
  const mocap::Model subject = Calibrated(mocap::DefaultFullBodyModel(1.75), Bio("anatomical_posture.c3d"));
  const std::vector<std::pair<const char*, const char*>> on = {
      {"LTHIB", "femur_l"}, {"LTHID", "femur_l"}, {"LKNEM", "femur_l"}, {"LTIBF", "tibia_l"}, {"LTIBD", "tibia_l"},
      {"RTHIB", "femur_r"}, {"RTHID", "femur_r"}, {"RKNEM", "femur_r"}, {"RTIBF", "tibia_r"}, {"RTIBD", "tibia_r"},
      {"LTOE5", "foot_l"},  {"RTOE5", "foot_r"},  {"RNAV", "foot_r"},   {"S3", "pelvis"},    {"T6", "torso"},
      {"T1", "torso"},      {"C2", "torso"}};
  for (const auto& [marker, segment] : on) {
    const int m = subject.FindMarker(marker);
    ASSERT_GE(m, 0) << marker;
    EXPECT_EQ(subject.segments()[subject.markers()[m].segment].name, segment) << marker;
  }
  for (const char* left_out : {"S1", "LANKM", "RANKM", "LNAV"}) EXPECT_LT(subject.FindMarker(left_out), 0) << left_out;
  const RealResult r = TrackRecording(Bio("Test_func_rhip.c3d"), subject, -Eigen::Vector3d::UnitZ(),
                                      Eigen::Vector3d::UnitZ(), 0,
                                      mocap::ekf::TrackerOptions::ScaleToSubject::kWhenTheModelDoesNotFit);
  for (const char* marker : {"RTHI", "RTHID", "RTHIB", "RKNE", "RKNEM"}) {
    const int m = subject.FindMarker(marker);
    EXPECT_EQ(r.run.marker_correct[m], r.run.marker_samples[m]) << marker;
  }
  // 0.907628 before the seventeenth session; 1.000000 since the shanks and feet of the swinging
  // leg are labelled as rigid groups (ekf/tracker.h, "Rigid groups").
  EXPECT_GE(r.run.score.accuracy(), 0.999) << r.summary;
}

// The targets on biobuddy's functional trials with that subject model: met on the right
// hip and both knee trials since the seventeenth session (the test after this one), on the left
// hip's (this test) since the eighteenth. The trials are 12 Hz (the uploader kept one frame in ten): from frame to
// frame a swinging foot or shank moves off its constant-velocity prediction by 40 mm (median;
// 107 mm at the 95th percentile: RTOE, RHEE, RANK, RTIB, RTIBF on the right hip trial), more
// than the 47-65 mm between the lab's neighbouring markers (TIB and TIBF, TOE and TOE5, THI and
// THIB), so a frame-to-frame tracker's prediction cannot say which is which. The feet and shanks
// of the moving leg swap (right hip: 0.907628 / 0.901640 with 5 ghosts, 35 / 53 swaps longer than
// 5 frames; left hip 0.876182; right knee 0.949638; left knee 0.968006). The same cause on data
// that meet the targets: welk007's hip trial, 100 Hz, 0.999745 with its calibrated model, every
// 8th frame kept (12.5 Hz: prediction error 95th percentile 1.5 -> 63.6 mm) 0.808824
// (BENCHMARKS.md, "Real recordings, unlabelled"). Sixteenth session, the process noise learnt
// from the innovations (the bound's made every 12 Hz gate a metre wide) and the start's labels
// followed as point tracks: right hip 0.980369 / 0.979484 with 5 ghosts (16 swaps > 5 frames),
// left hip 0.928303 / 0.928778 (58 / 49), right knee 0.998436 / 0.998354 (0 swaps), left knee
// 0.978257 / 0.978092 (1) -- still short of the targets. Seventeenth (main before it: right hip
// 0.981492 / 0.981185, 18 / 17 swaps; left hip 0.932357 / 0.932393, 62 / 52; right knee 0.998436
// both; left knee 0.978919 / 0.978671, 1 each): a segment whose prediction is looser than its
// markers' spacing has them labelled as one rigid body about its joint centre, placed by its
// parent's fitted pose (ekf/tracker.h, "Rigid groups"): right hip 1.000000 / 0.999966, right knee
// 0.999753 both, 0 wrong -- the targets -- left hip 0.992659 / 0.990905 (39 / 45 wrong, 0 / 1
// swaps > 5 frames), left knee 0.981151 both (3 wrong, 0 swaps). What was left on the left leg:
// its fastest swings put the shank's and foot's points 7-20 cm from their predictions, beyond
// the gates the group's candidates are taken from, and the leg is lost for a few frames (left
// knee: its foot then stayed 13 cm off, unlabelled, for the last 20 frames of the trial: the limb
// search came every 20 frames, 1.7 s at 12 Hz). The limb search's period is now 0.1 s (20 frames
// at 200 Hz, as before), at least 2 frames (a label's probation): left knee 0.999917 both (1
// wrong) -- the targets --, left hip 0.994010 / 0.993243 (0 swaps > 5 frames), right knee 0.999342
// both (2 wrong; 0.999753 with the 20 frames). Eighteenth: what the left hip lost was its foot in
// the fastest swings, 8-10 cm from its prediction, at the edge of its gates (LTOE, LTOE5 and LHEE
// missed or on each other's points and the unmodelled LNAV's; one such label measured drove the
// ankle to its range, where it stayed for a second). That error is the swinging shank's, which
// the shank's group fit has just measured: a loose segment's gates are now centred on its
// markers' predictions moved as its fitted parent moved its joint centre (ekf/tracker.h, "Rigid
// groups"): left hip 0.999963 / 0.999671 (0 / 1 wrong), left knee 1.000000 both, right hip and
// right knee as before.
TEST(TrackReal, BiobuddyFunctionalTrialsMeetTheTargetsWithTheDefaultModelCalibratedOnTheStaticTrial) {
  SKIP_WITHOUT_SHARED_DATA();
  const mocap::Model subject = Calibrated(mocap::DefaultFullBodyModel(1.75), Bio("anatomical_posture.c3d"));
  for (const char* trial : {"Test_func_lhip.c3d"})
    ExpectTheTargets(Bio(trial), subject, -Eigen::Vector3d::UnitZ(), Eigen::Vector3d::UnitZ(), true,
                     mocap::ekf::TrackerOptions::ScaleToSubject::kWhenTheModelDoesNotFit);
}

// The right hip and knee trials and the left knee trial meet the targets (above).
TEST(TrackReal, BiobuddyRightHipAndBothKneeTrialsMeetTheTargetsWithTheCalibratedModel) {
  SKIP_WITHOUT_SHARED_DATA();
  const mocap::Model subject = Calibrated(mocap::DefaultFullBodyModel(1.75), Bio("anatomical_posture.c3d"));
  for (const char* trial : {"Test_func_rhip.c3d", "Test_func_rknee.c3d", "Test_func_lknee.c3d"})
    ExpectTheTargets(Bio(trial), subject, -Eigen::Vector3d::UnitZ(), Eigen::Vector3d::UnitZ(), false,
                     mocap::ekf::TrackerOptions::ScaleToSubject::kWhenTheModelDoesNotFit);
}

std::string Gait2354(const std::string& file) {
  return mocap::testutil::SharedData() + "/opensim_gait2354_subject01/" + file;
}

// OpenSim's example subject (60 Hz, Y up, 10 arm and head markers the marker set does not model:
// points that are nobody's), against the generic Gait2354 model with its marker set. Static: as
// given 0.999316 without ghosts and 0.988632 with 5 (R.Ankle.Lat missed 122 frames); scaled to
// the subject at the start (femurs 1.10-1.12, OpenSim's own scaling 1.147) 0.999915 both.
TEST(TrackReal, Gait2354StaticMeetsTheTargetsWithItsGenericModel) {
  SKIP_WITHOUT_SHARED_DATA();
  ExpectTheTargets(Gait2354("subject01_static.trc"),
                   OsimModel(Gait2354("gait2354_simbody.osim"), Gait2354("gait2354_Scale_MarkerSet.xml")),
                   Eigen::Vector3d::UnitY(), Eigen::Vector3d::UnitY(), true);
}

// The walk (151 frames): met since the sixteenth session (below). As given the search refuses
// the first 5 frames (the generic
// model's residual just over 3 cm) and then labels every marker right: 0.9656 / 0.9590 with 5
// ghosts, all of it the late start. Scaled to the subject (when the model does not fit, frame 1),
// 0.958 / 0.9925 (L.Acromium on an unmodelled arm marker's point for 143 frames without
// ghosts). Scaled always (thirteenth session): 0.9113 / 0.8656, the search as given being
// refused as ambiguous on frame 0 and the scaled one at frames 4 and 1 turning the torso (the
// acromion markers on each other's and an arm marker's points; the torso carries 4 markers, 2 of
// them mirror images, among 6 unmodelled arm and head markers). Fourteenth: `always` scales only a start the model's own
// size accepted, so as given: 0.965606 / 0.958983, 0 wrong, from frames 5 / 6 (frames 0-4 refused:
// ambiguous, then a residual of 30.1-30.4 mm, just over init_max_rms_m). Fifteenth: the frames
// before the start are labelled backward from it, as `mocap track --points` does
// (sim::BackfillBeforeStart): 0.998718 with and without ghosts, 0 wrong; what is left is Top.Head
// in 3 of the first frames (its backward run picks it up a few frames after its own start).
// Sixteenth: those 6 samples were all in the forward run's first frames, at and after its start
// (frame 5: Top.Head, R.Acromium, V.Sacral, L.Shank.Front; frames 6-7: Top.Head), the markers a
// start leaves for later frames; the backward run, tracking since frame 25, had labelled them
// there. Where both runs track, a marker the forward run has not labelled takes the backward
// run's label on a point the forward run gave nobody, when the two runs agree on that marker
// wherever both label it: 1.000000 without ghosts, 0.999786 with 5, 0 wrong.
TEST(TrackReal, Gait2354WalkMeetsTheTargetsWithItsGenericModel) {
  SKIP_WITHOUT_SHARED_DATA();
  ExpectTheTargets(Gait2354("subject01_walk1.trc"),
                   OsimModel(Gait2354("gait2354_simbody.osim"), Gait2354("gait2354_Scale_MarkerSet.xml")),
                   Eigen::Vector3d::UnitY(), Eigen::Vector3d::UnitY(), true);
}

// The walk with the generic model calibrated on the subject's static trial (scaled, its markers
// fitted; the 10 arm and head markers beside none of its segments' left out): every frame
// labelled (without ghosts the search starts at frame 3, the frames before labelled backward;
// with 5 at frame 0), 0.999573 of the labels with and without ghosts, 0 wrong (the acromion
// markers missed in one frame each).
TEST(TrackReal, Gait2354WalkMeetsTheTargetsWithItsGenericModelCalibratedOnTheStaticTrial) {
  SKIP_WITHOUT_SHARED_DATA();
  const mocap::Model subject =
      Calibrated(OsimModel(Gait2354("gait2354_simbody.osim"), Gait2354("gait2354_Scale_MarkerSet.xml")),
                 Gait2354("subject01_static.trc"));
  ExpectTheTargets(Gait2354("subject01_walk1.trc"), subject, Eigen::Vector3d::UnitY(), Eigen::Vector3d::UnitY(), true,
                   mocap::ekf::TrackerOptions::ScaleToSubject::kWhenTheModelDoesNotFit);
}

// `mocap track --calibrate STATIC` does the above and writes the subject model; that model, and
// the one `mocap fit --out fitted.osim STATIC` writes, track the trial as the calibration's own
// run does (the .osim written and read back loses nothing the tracker uses).
TEST(TrackReal, TheCliCalibratesOnTheStaticTrialAndItsModelTracksAsWell) {
  SKIP_WITHOUT_SHARED_DATA();
  const std::string out = mocap::testutil::TmpPath("track_real", "calibrate");
  const std::string points = " --points " + Welk("c3d_Trimmed_RHJC1.c3d") + " --unlabel --ghosts 5 --up z --out ";
  auto stats = [](const std::string& dir) {
    std::ifstream in(dir + "/stats.json");
    return nlohmann::json::parse(in);
  };
  mocap::testutil::CommandResult r =
      mocap::testutil::Mocap("track --model " + Welk("unscaled_generic.osim") + " --calibrate " +
                             Welk("c3d_Trimmed_static1.c3d") + " --threads 2" + points + out + "_calibrated");
  ASSERT_EQ(r.status, 0) << r.output;
  EXPECT_NE(r.output.find("r_thigh3 (a placeholder stacked with others in the model) placed on femur_r"),
            std::string::npos)
      << r.output;
  EXPECT_NE(r.output.find("subject calibration: marker RMS"), std::string::npos) << r.output;
  const nlohmann::json calibrated = stats(out + "_calibrated");
  ASSERT_TRUE(calibrated.contains("calibration")) << calibrated.dump(1);
  EXPECT_EQ(calibrated["calibration"]["placed"].size(), 16u);
  EXPECT_LT(calibrated["calibration"]["marker_rms_mm"].get<double>(), 5.0);
  r = mocap::testutil::Mocap("track --model " + out + "_calibrated/calibrated.osim" + points + out + "_written");
  ASSERT_EQ(r.status, 0) << r.output;
  r = mocap::testutil::Mocap("fit --model " + Welk("unscaled_generic.osim") + " --threads 2 --out " + out +
                             "_fit/fitted.osim " + Welk("c3d_Trimmed_static1.c3d"));
  ASSERT_EQ(r.status, 0) << r.output;
  r = mocap::testutil::Mocap("track --model " + out + "_fit/fitted.osim" + points + out + "_fitted");
  ASSERT_EQ(r.status, 0) << r.output;
  const nlohmann::json written = stats(out + "_written"), fitted = stats(out + "_fitted");
  std::printf("welk007 RHJC1, 5 ghosts: calibrated %.6f (%d wrong), its written model %.6f, mocap fit's %.6f\n",
              calibrated["label_accuracy"].get<double>(), calibrated["wrong_labels"].get<int>(),
              written["label_accuracy"].get<double>(), fitted["label_accuracy"].get<double>());
  EXPECT_GE(calibrated["label_accuracy"].get<double>(), 0.995);
  EXPECT_EQ(calibrated["wrong_labels"].get<int>(), 0);
  for (const nlohmann::json* j : {&written, &fitted}) {
    EXPECT_DOUBLE_EQ((*j)["label_accuracy"].get<double>(), calibrated["label_accuracy"].get<double>());
    EXPECT_EQ((*j)["wrong_labels"].get<int>(), 0);
    EXPECT_EQ((*j)["swaps_longer_than_5_frames"].get<int>(), 0);
  }
}

// `mocap track --points` on a file labels the frames before its first start backward from it
// (sim::BackfillBeforeStart); --no-backfill leaves them as the live tracker does. The gait2354
// walk, its labels removed, its lab's vertical not given: started at frame 6, the first 5 frames
// filled (0.965606 -> 0.998718; 1.000000 since the lead-in's labels are merged too), none of them
// wrong.
TEST(TrackReal, TheCliLabelsTheFramesBeforeTheStartBackward) {
  SKIP_WITHOUT_SHARED_DATA();
  const std::string out = mocap::testutil::TmpPath("track_real", "walk");
  const std::string cmd = "track --points " + Gait2354("subject01_walk1.trc") + " --model " +
                          Gait2354("gait2354_simbody.osim") + " --marker-set " +
                          Gait2354("gait2354_Scale_MarkerSet.xml") + " --unlabel --out ";
  auto stats = [](const std::string& dir) {
    std::ifstream in(dir + "/stats.json");
    return nlohmann::json::parse(in);
  };
  mocap::testutil::CommandResult r = mocap::testutil::Mocap(cmd + out + "_both");
  ASSERT_EQ(r.status, 0) << r.output;
  // Not told the lab's vertical (--up auto): OpenSim's Y, found by the axis the tracker starts on.
  EXPECT_NE(r.output.find("the lab's vertical: y (the tracker starts there at frame 6"), std::string::npos)
      << r.output;
  r = mocap::testutil::Mocap(cmd + out + "_live --no-backfill");
  ASSERT_EQ(r.status, 0) << r.output;
  const nlohmann::json both = stats(out + "_both"), live = stats(out + "_live");
  std::printf("walk: backfilled %d frames: accuracy %.6f (live %.6f), wrong %d\n", both["backfilled_frames"].get<int>(),
              both["label_accuracy"].get<double>(), live["label_accuracy"].get<double>(),
              both["wrong_labels"].get<int>());
  EXPECT_EQ(live["backfilled_frames"].get<int>(), 0);
  EXPECT_EQ(both["backfilled_frames"].get<int>(), 5);
  EXPECT_GE(both["label_accuracy"].get<double>(), 0.998);
  EXPECT_GT(both["label_accuracy"].get<double>(), live["label_accuracy"].get<double>() + 0.03);
  EXPECT_EQ(both["wrong_labels"].get<int>(), 0);
  EXPECT_EQ(both["swaps_longer_than_5_frames"].get<int>(), 0);
}


}  // namespace
