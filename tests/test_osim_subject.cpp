// The fit from a generic OpenSim model that is not our default one, scored against a known truth
// (sim/osim_subject.h): gait2354 with its Scale marker set, posed by OpenSim's own IK of the walk
// and by the static pose its Scale tool solved, each trial recording the markers its real
// recording has. What a held-back subject would show about the fit on a lab's model, with the
// truth known. The real-data tests skip where ../shared/data is absent.
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <random>
#include <utility>

#include <nlohmann/json.hpp>

#include "formats/mot.h"
#include "formats/osim.h"
#include "formats/trc.h"
#include "model/compare.h"
#include "model/default_model.h"
#include "model/kinematics.h"
#include "sim/osim_subject.h"
#include "solver/attach_markers.h"
#include "solver/fit_trust.h"
#include "solver/global_fit.h"
#include "solver/inverse_kinematics.h"
#include "solver/marker_fit_problem.h"
#include "tests/assembly_test_util.h"
#include "tests/file_test_util.h"
#include "tests/osim_test_util.h"

namespace fs = std::filesystem;
using namespace mocap;
using mocap::testutil::SharedData;

namespace {

// Three poses of every coordinate of `model` (degrees for rotational ones, as a .mot).
formats::CoordinateTable SmallMotion(const Model& model) {
  formats::CoordinateTable t;
  t.name = "small";
  t.times = {0.0, 0.01, 0.02};
  t.values.resize(3, model.num_coordinates());
  for (int c = 0; c < model.num_coordinates(); ++c) {
    t.column_names.push_back(model.coordinates()[c].name);
    const bool rot = model.coordinates()[c].rotational;
    for (int f = 0; f < 3; ++f)
      t.values(f, c) = model.coordinates()[c].default_value * (rot ? 180.0 / M_PI : 1.0) + (rot ? 5.0 * f : 0.01 * f);
  }
  return t;
}

std::string Gait(const std::string& file) { return SharedData() + "/opensim_gait2354_subject01/" + file; }

// gait2354_simbody.osim with the 39 markers of gait2354_Scale_MarkerSet.xml: the generic model.
Model Gait2354Generic() {
  formats::OsimImport im;
  Status s = formats::ImportOsim(Gait("gait2354_simbody.osim"), &im);
  EXPECT_TRUE(s.ok()) << s.message();
  s = formats::LoadOsimMarkerSet(Gait("gait2354_Scale_MarkerSet.xml"), &im);
  EXPECT_TRUE(s.ok()) << s.message();
  return im.model;
}

// The markers of `model` that the real trial `trc` has.
std::vector<std::string> RecordedModelMarkers(const Model& model, const std::string& trc) {
  formats::MarkerTrial trial;
  const Status s = formats::ReadTrc(Gait(trc), &trial);
  EXPECT_TRUE(s.ok()) << s.message();
  std::vector<std::string> names;
  for (const Marker& m : model.markers())
    if (trial.FindMarker(m.name) >= 0) names.push_back(m.name);
  return names;
}

sim::PrescribedMotion Motion(const std::string& file, const std::string& name) {
  sim::PrescribedMotion m;
  m.source = Gait(file);
  const Status s = formats::ReadMot(m.source, &m.table);
  EXPECT_TRUE(s.ok()) << s.message();
  m.table.name = name;
  return m;
}

// A 1 s static trial holding the Scale tool's static pose, and the walk (OpenSim's IK, 73
// frames at 60 Hz), each recording the model markers its real trial has: the walk has no knee or
// ankle markers (subject01_walk1.trc), the static trial every one.
std::vector<sim::PrescribedMotion> Gait2354Motions(const Model& model) {
  sim::PrescribedMotion walk = Motion("reference_outputs/subject01_walk1_ik.mot", "subject01_walk1");
  sim::PrescribedMotion stat = Motion("reference_outputs/subject01_static_output.mot", "subject01_static");
  formats::CoordinateTable held;
  const Status s = sim::HoldPose(model, stat.table, 0, 60, 60.0, &held);
  EXPECT_TRUE(s.ok()) << s.message();
  stat.table = held;
  stat.markers = RecordedModelMarkers(model, "subject01_static.trc");
  walk.markers = RecordedModelMarkers(model, "subject01_walk1.trc");
  return {stat, walk};
}

struct Gait2354Outcome {
  solver::FitResult fit;
  std::vector<double> lab_mm;  // per joint: JointCentreTrackRmsMm against the truth
  ModelComparison cmp;         // truth vs fit, in the segments' frames
};

Gait2354Outcome FitGait2354(const Model& generic, const std::vector<sim::PrescribedMotion>& motions,
                            const sim::OsimSubjectOptions& options, const solver::FitOptions& fit_options) {
  Gait2354Outcome out;
  sim::OsimSubject subject;
  Status s = sim::SimulateOsimSubject(generic, motions, options, &subject);
  EXPECT_TRUE(s.ok()) << s.message();
  std::vector<solver::FitTrial> trials;
  for (const auto& t : subject.trials) trials.push_back({t.markers, {}});
  s = solver::FitModel(generic, trials, fit_options, &out.fit);
  EXPECT_TRUE(s.ok()) << s.message();
  if (!s.ok()) return out;
  EXPECT_TRUE(CompareModels(subject.truth, out.fit.model, &out.cmp).ok());
  out.lab_mm = sim::JointCentreTrackRmsMm(subject.truth, subject.trials, out.fit.model, out.fit.coordinates);
  return out;
}

bool Held(const solver::FitReport& r, const std::string& joint) {
  for (const auto& [name, why] : r.held_joints)
    if (name == joint) return true;
  return false;
}

// A fit at the noise: marker RMS within 10 % of the noise's share of the residuals, the
// unknowns' degrees of freedom taken out.
void ExpectMarkerRmsAtTheNoise(const solver::FitReport& r, double noise_mm) {
  const double expected = noise_mm * std::sqrt(3.0 * (1.0 - double(r.unknowns) / (3.0 * r.marker_samples)));
  EXPECT_NEAR(r.marker_rms_mm, expected, 0.1 * expected);
}

}  // namespace

// The truth differs from the generic model by what the options say, and the trials are the
// truth's markers at the motion's poses, plus the noise and gaps asked for.
TEST(OsimSubject, TruthIsTheGenericModelPerturbedAndTrialsItsMarkers) {
  const Model generic = DefaultFullBodyModel();
  sim::PrescribedMotion motion{SmallMotion(generic), "small.mot", {}};
  sim::OsimSubjectOptions options;
  options.noise_mm = 0.0;
  sim::OsimSubject subject;
  ASSERT_TRUE(sim::SimulateOsimSubject(generic, {motion}, options, &subject).ok());
  const Eigen::VectorXd p0 = generic.InitialParameters(), p = subject.truth_parameters;
  bool any_scale_moved = false;
  for (int s = 0; s < generic.num_segments(); ++s) {
    const double ratio = p[generic.scale_index(s)] / p0[generic.scale_index(s)];
    EXPECT_LE(std::abs(ratio - 1.0), 0.08 + 1e-12) << generic.segments()[s].name;
    any_scale_moved |= std::abs(ratio - 1.0) > 0.01;
  }
  EXPECT_TRUE(any_scale_moved);
  for (int j = 0; j < generic.num_joints(); ++j) {
    const int ci = generic.centre_index(j);
    if (ci < 0) continue;
    const double s = p[generic.scale_index(generic.joints()[j].parent)];
    EXPECT_LE(1000 * s * (p.segment<3>(ci) - p0.segment<3>(ci)).norm(), 10.0 + 1e-9) << generic.joints()[j].name;
  }
  for (int m = 0; m < generic.num_markers(); ++m) {
    const double s = p[generic.scale_index(generic.markers()[m].segment)];
    EXPECT_LE(1000 * s * (p.segment<3>(generic.marker_index(m)) - p0.segment<3>(generic.marker_index(m))).norm(),
              10.0 + 1e-9)
        << generic.markers()[m].name;
  }
  // Noise-free trials are the truth's forward kinematics at the .mot's poses (degrees -> radians).
  ASSERT_EQ(subject.trials.size(), 1u);
  const formats::MarkerTrial& trial = subject.trials[0].markers;
  ASSERT_EQ(trial.num_frames(), 3);
  ASSERT_EQ(trial.marker_names.size(), static_cast<size_t>(generic.num_markers()));
  const Geometry g(subject.truth);
  ModelData d(subject.truth);
  for (int f = 0; f < 3; ++f) {
    Eigen::VectorXd z = generic.DefaultCoordinates();
    for (int c = 0; c < generic.num_coordinates(); ++c)
      z[c] = motion.table.values(f, c) * (generic.coordinates()[c].rotational ? M_PI / 180.0 : 1.0);
    ForwardKinematics(subject.truth, g, z, &d);
    for (int m = 0; m < generic.num_markers(); ++m)
      EXPECT_LT((trial.At(f, m) - MarkerPosition(subject.truth, g, d, m)).norm(), 1e-12) << generic.markers()[m].name;
  }
  // Noise of the standard deviation asked for; gaps of the fraction asked for; a recorded subset.
  formats::CoordinateTable long_table;
  ASSERT_TRUE(sim::HoldPose(generic, motion.table, 1, 2000, 100.0, &long_table).ok());
  sim::PrescribedMotion still{long_table, "still", {"LASI", "RASI", "LPSI", "RPSI"}};
  sim::OsimSubject noisy, clean;
  options.noise_mm = 2.0;
  options.missing = 0.1;
  ASSERT_TRUE(sim::SimulateOsimSubject(generic, {still}, options, &noisy).ok());
  options.noise_mm = 0.0;
  options.missing = 0.0;
  ASSERT_TRUE(sim::SimulateOsimSubject(generic, {still}, options, &clean).ok());
  const formats::MarkerTrial& n = noisy.trials[0].markers;
  ASSERT_EQ(n.marker_names, std::vector<std::string>({"LASI", "RASI", "LPSI", "RPSI"}));
  double sum_sq = 0;
  int samples = 0, nan = 0;
  for (int f = 0; f < n.num_frames(); ++f)
    for (int m = 0; m < 4; ++m) {
      if (!n.Has(f, m)) {
        ++nan;
        continue;
      }
      sum_sq += (n.At(f, m) - clean.trials[0].markers.At(f, m)).squaredNorm();
      ++samples;
    }
  EXPECT_NEAR(1000 * std::sqrt(sum_sq / (3.0 * samples)), 2.0, 0.05);
  EXPECT_NEAR(nan / 8000.0, 0.1, 0.01);
}

TEST(OsimSubject, ErrorsNameWhatIsWrong) {
  const Model generic = DefaultFullBodyModel();
  const sim::OsimSubjectOptions options;
  sim::OsimSubject out;
  auto error = [&](const sim::PrescribedMotion& m, const sim::OsimSubjectOptions& o = sim::OsimSubjectOptions()) {
    const Status s = sim::SimulateOsimSubject(generic, {m}, o, &out);
    EXPECT_FALSE(s.ok());
    return s.message();
  };
  sim::PrescribedMotion foreign{SmallMotion(generic), "walk.mot", {}};
  foreign.table.column_names.push_back("elbow_flexion_x");
  foreign.table.values.conservativeResize(Eigen::NoChange, foreign.table.values.cols() + 1);
  foreign.table.values.rightCols(1).setZero();
  EXPECT_NE(error(foreign).find("walk.mot: column 'elbow_flexion_x' is not a coordinate"), std::string::npos);
  sim::PrescribedMotion lacking{SmallMotion(generic), "walk.mot", {}};
  const std::string first = lacking.table.column_names[0];
  lacking.table.column_names.erase(lacking.table.column_names.begin());
  lacking.table.values = Eigen::MatrixXd(lacking.table.values.rightCols(lacking.table.values.cols() - 1));
  EXPECT_NE(error(lacking).find("no column for 1 coordinate(s) of model '" + generic.name() + "': " + first),
            std::string::npos);
  sim::PrescribedMotion backwards{SmallMotion(generic), "walk.mot", {}};
  backwards.table.times[2] = 0.0;
  EXPECT_NE(error(backwards).find("walk.mot: time 0.000000 (row 3) does not increase"), std::string::npos);
  sim::PrescribedMotion unknown_marker{SmallMotion(generic), "walk.mot", {"LASI", "R.ASIS"}};
  EXPECT_NE(error(unknown_marker).find("recorded marker 'R.ASIS' is not in model"), std::string::npos);
  sim::OsimSubjectOptions bad;
  bad.missing = 0.95;
  EXPECT_NE(error({SmallMotion(generic), "", {}}, bad).find("missing must be a fraction"), std::string::npos);
  bad = sim::OsimSubjectOptions();
  bad.geometry.scale_spread = 0.6;
  EXPECT_NE(error({SmallMotion(generic), "", {}}, bad).find("geometry: scale_spread"), std::string::npos);
  formats::CoordinateTable held;
  EXPECT_NE(sim::HoldPose(generic, SmallMotion(generic), 3, 10, 100.0, &held).message().find("motion 'small': no row 3"),
            std::string::npos);
  EXPECT_EQ(sim::SimulateOsimSubject(Model(), {}, options, &out).ok(), false);
}

// gait2354 fitted from gait2354_simbody.osim, as a lab runs it (FitModel's defaults), on five
// subjects (seeds 1-5) walking OpenSim's IK of subject01_walk1 after a static trial, 0.5 mm
// noise, 5 % of the samples in gaps on seed 5. What the trials excite decides what can be
// recovered, and the report must say which is which:
//  - knees (flexion 21.6 deg RMS in the walk): fitted. Their centres across the flexion axis,
//    in the lab, within 2 mm RMS of the truth (seeds 1-20 measured: at most 1.3 mm; the
//    generic model scaled would be the 5-31 mm of CompareModels' "generic" column).
//  - hips (second rotation 4.1 deg RMS: the walk is a flexion) and ankles (5.7 deg): held at the
//    scaled generic model's (FitOptions::min_excitation_deg, 10 deg) and reported so. Their error
//    is then the subject's own deviation from the generic model (<= 10 mm here by construction)
//    plus what the scales' error moves them: hips within 12 mm, ankles within 20 mm (seeds 1-20:
//    at most 10.0 and 18.3 mm). With the hold lowered to 2 deg the same data give hips <= 4 mm,
//    ankles <= 9.5 mm (bench figures in BENCHMARKS.md): the hold is what costs them here.
//  - marker RMS within 10 % of what the noise leaves; converged in at most 30 iterations.
TEST(OsimSubject, Gait2354FitFromTheGenericModelRecoversWhatTheWalkExcites) {
  SKIP_WITHOUT_SHARED_DATA();
  const Model generic = Gait2354Generic();
  const std::vector<sim::PrescribedMotion> motions = Gait2354Motions(generic);
  for (int seed = 1; seed <= 5; ++seed) {
    SCOPED_TRACE("seed " + std::to_string(seed));
    sim::OsimSubjectOptions options;
    options.seed = seed;
    if (seed == 5) options.missing = 0.05;
    const Gait2354Outcome o = FitGait2354(generic, motions, options, solver::FitOptions());
    const solver::FitReport& r = o.fit.report;
    ASSERT_FALSE(o.lab_mm.empty());
    std::printf("seed %d: %s\n", seed, r.BriefReport().c_str());
    for (const auto& jd : o.cmp.joints)
      std::printf("  %-11s lab %6.2f mm RMS, in the segments %6.2f mm%s\n", jd.joint.c_str(),
                  o.lab_mm[generic.FindJoint(jd.joint)], jd.centre_error_mm, Held(r, jd.joint) ? "  (held)" : "");
    EXPECT_TRUE(r.converged()) << r.solver.message;
    EXPECT_LE(r.solver.num_iterations(), 30);
    ExpectMarkerRmsAtTheNoise(r, options.noise_mm);
    for (const char* side : {"_r", "_l"}) {
      const std::string knee = std::string("knee") + side, hip = std::string("hip") + side,
                        ankle = std::string("ankle") + side;
      EXPECT_FALSE(Held(r, knee));
      EXPECT_LE(o.lab_mm[generic.FindJoint(knee)], 2.0) << knee;
      EXPECT_TRUE(Held(r, hip));
      EXPECT_LE(o.lab_mm[generic.FindJoint(hip)], 12.0) << hip;
      EXPECT_TRUE(Held(r, ankle));
      EXPECT_LE(o.lab_mm[generic.FindJoint(ankle)], 20.0) << ankle;
    }
  }
}

// The fit's normal equations from per-segment sums (MarkerFitProblem's evaluator,
// PoseNormalEquations and AddNormalEquations) on a model with what the default one lacks: a knee whose one coordinate
// drives a rotation and translations on splines (two elements of one coordinate, translation
// columns scaled with the femur), and coordinates clamped to their ranges. They must equal the
// per-marker sums of the evaluator's Jacobians (tests/test_fit.cpp checks those) to rounding.
TEST(OsimSubject, Gait2354NormalEquationsFromSegmentSumsArePerMarkerSums) {
  SKIP_WITHOUT_SHARED_DATA();
  const Model model = Gait2354Generic();
  const int nz = model.num_coordinates(), nm = model.num_markers(), nf = 6;
  std::mt19937_64 rng(3);
  std::normal_distribution<double> angle(0.0, 0.5), noise(0.0, 0.01);
  std::vector<Eigen::VectorXd> poses(nf, Eigen::VectorXd(nz));
  formats::RowMatrix measured(nf, 3 * nm);
  ModelData data(model);
  const Geometry geometry(model);
  for (int f = 0; f < nf; ++f) {
    for (int c = 0; c < nz; ++c) poses[f][c] = model.coordinates()[c].default_value + angle(rng);
    Eigen::VectorXd truth = poses[f];
    for (int c = 0; c < nz; ++c) truth[c] += 0.1 * angle(rng);
    ForwardKinematics(model, geometry, truth, &data);
    for (int m = 0; m < nm; ++m) {
      const Eigen::Vector3d x = MarkerPosition(model, geometry, data, m);
      for (int k = 0; k < 3; ++k) measured(f, 3 * m + k) = f > 0 && m % (f + 2) == 0 ? NAN : x[k] + noise(rng);
    }
  }
  solver::FitOptions options;
  options.coordinate_limit_sigma_rad = 0.01;
  options.coordinate_limit_sigma_m = 0.001;
  solver::MarkerFitProblem problem(model, measured, options);
  ASSERT_TRUE(problem.SetShared(problem.InitialShared()));
  auto evaluator = problem.NewEvaluator();
  int coupled = 0;
  for (const Joint& jt : model.joints())
    for (size_t e = 0; e < jt.elements.size(); ++e)
      for (size_t k = 0; k < e; ++k)
        coupled += jt.elements[e].coordinate >= 0 && jt.elements[e].coordinate == jt.elements[k].coordinate &&
                   !jt.elements[e].function.IsConstant() && !jt.elements[k].function.IsConstant();
  EXPECT_GT(coupled, 0);  // the test covers an element pair of one coordinate
  for (int f = 0; f < nf; ++f) {
    Eigen::MatrixXd u_sums = Eigen::MatrixXd::Zero(nz, nz), u_blocks = u_sums;
    Eigen::VectorXd g_sums = Eigen::VectorXd::Zero(nz), g_blocks = g_sums;
    ASSERT_TRUE(evaluator->PoseNormalEquations(f, poses[f].data(), nz, u_sums.data(), g_sums.data()));
    ASSERT_TRUE(evaluator->FrameEvaluator::PoseNormalEquations(f, poses[f].data(), nz, u_blocks.data(), g_blocks.data()));
    const double u_scale = u_blocks.cwiseAbs().maxCoeff(), g_scale = g_blocks.cwiseAbs().maxCoeff();
    for (int j = 0; j < nz; ++j) {
      EXPECT_NEAR(g_sums[j], g_blocks[j], 1e-11 * g_scale) << "frame " << f << " coordinate " << j;
      for (int i = j; i < nz; ++i)
        EXPECT_NEAR(u_sums(i, j), u_blocks(i, j), 1e-11 * u_scale) << "frame " << f << " entry " << i << ", " << j;
    }
  }
  // The whole linearisation (W_f and the shared gradient too: the knee's centre column carries
  // its translations scaled with the femur) against the Schur solver's per-marker products.
  Eigen::VectorXd x(nf * nz + problem.shared_dim());
  for (int f = 0; f < nf; ++f) x.segment(f * nz, nz) = poses[f];
  x.tail(problem.shared_dim()) = problem.InitialShared();
  problem.SetFramePriorTargets(x);
  testutil::ExpectAssemblyMatchesBlocks(&problem, x);
}

// The sweep behind the bounds above (run with --gtest_also_run_disabled_tests): seeds 1-20, one
// line each. Environment: MISSING (fraction), NOISE (mm), MIN_EXCITATION_DEG (the fit's hold).
TEST(OsimSubject, DISABLED_Gait2354Sweep) {
  SKIP_WITHOUT_SHARED_DATA();
  const Model generic = Gait2354Generic();
  const auto motions = Gait2354Motions(generic);
  auto env = [](const char* name, double fallback) {
    return std::getenv(name) ? std::atof(std::getenv(name)) : fallback;
  };
  solver::FitOptions fit_options;
  fit_options.min_excitation_deg = env("MIN_EXCITATION_DEG", fit_options.min_excitation_deg);
  for (int seed = 1; seed <= 20; ++seed) {
    sim::OsimSubjectOptions options;
    options.seed = seed;
    options.missing = env("MISSING", 0.0);
    options.noise_mm = env("NOISE", options.noise_mm);
    const Gait2354Outcome o = FitGait2354(generic, motions, options, fit_options);
    ASSERT_FALSE(o.lab_mm.empty());
    std::printf("seed %2d  rms %.2f mm  %2d it %s |", seed, o.fit.report.marker_rms_mm,
                o.fit.report.solver.num_iterations(), o.fit.report.converged() ? "conv" : "NOCONV");
    for (const char* joint : {"hip_r", "hip_l", "knee_r", "knee_l", "ankle_r", "ankle_l", "back"})
      std::printf(" %s %5.1f", joint, o.lab_mm[generic.FindJoint(joint)]);
    std::printf("\n");
  }
}

namespace {

std::string Welk(const std::string& file) { return SharedData() + "/welk007_hipfunc/" + file; }

// A motion of `model` from a real trial: our IK of every `step`-th frame of `trc`, as a .mot
// would hold it (degrees), recording the markers of `record` that the trial has.
sim::PrescribedMotion IkMotion(const Model& model, const std::string& trc, int step, const Model& record) {
  sim::PrescribedMotion out;
  formats::MarkerTrial trial;
  Status s = formats::ReadTrc(trc, &trial);
  EXPECT_TRUE(s.ok()) << s.message();
  const int nf = (trial.num_frames() + step - 1) / step;
  formats::RowMatrix measured(nf, 3 * model.num_markers());
  measured.setConstant(std::nan(""));
  for (int m = 0; m < model.num_markers(); ++m) {
    const int k = trial.FindMarker(model.markers()[m].name);
    if (k < 0) continue;
    for (int f = 0; f < nf; ++f) measured.row(f).segment<3>(3 * m) = trial.positions.row(f * step).segment<3>(3 * k);
  }
  const Geometry g(model);
  solver::InverseKinematics ik(model, g);
  Eigen::MatrixXd z;
  s = ik.SolveTrial(measured, &z);
  EXPECT_TRUE(s.ok()) << s.message();
  out.source = trc;
  out.table.name = trial.name;
  out.table.in_degrees = true;
  out.table.values = z;
  for (int c = 0; c < model.num_coordinates(); ++c) {
    out.table.column_names.push_back(model.coordinates()[c].name);
    if (model.coordinates()[c].rotational) out.table.values.col(c) *= 180.0 / M_PI;
  }
  for (int f = 0; f < nf; ++f) out.table.times.push_back(trial.times[f * step]);
  for (const Marker& m : record.markers())
    if (trial.FindMarker(m.name) >= 0) out.markers.push_back(m.name);
  return out;
}

struct WelkOutcome {
  solver::FitResult fit;
  std::vector<double> lab_mm;  // per joint: JointCentreTrackRmsMm against the truth
};

// welk007's generic model (Rajagopal-based: CustomJoint knees with coupled rotations and
// translations, wrists and hands, 72 markers with virtual ones) as the generic model; the
// motions are our IK, with the hand-scaled model, of every 30th frame of the static trial and
// every 6th of the right hip's functional trial (204 frames); each trial records the generic
// model's markers its real recording has (no virtual ones, no thigh clusters: the model has
// only placeholders for them). The fit starts from the generic model, or from the truth.
WelkOutcome FitWelk(int seed, bool from_truth, const solver::FitOptions& fit_options = solver::FitOptions()) {
  static const auto* setup = [] {
    auto* out = new std::pair<formats::OsimImport, std::vector<sim::PrescribedMotion>>;
    formats::OsimImport hand;
    EXPECT_TRUE(formats::ImportOsim(Welk("manually_scaled.osim"), &hand).ok());
    EXPECT_TRUE(formats::ImportOsim(Welk("unscaled_generic.osim"), &out->first).ok());
    out->second = {IkMotion(hand.model, Welk("derived_trc/c3d_Trimmed_static1.trc"), 30, out->first.model),
                   IkMotion(hand.model, Welk("derived_trc/c3d_Trimmed_RHJC1.trc"), 6, out->first.model)};
    return out;
  }();
  const Model& generic = setup->first.model;
  WelkOutcome out;
  sim::OsimSubjectOptions options;
  options.seed = seed;
  sim::OsimSubject subject;
  Status s = sim::SimulateOsimSubject(generic, setup->second, options, &subject);
  EXPECT_TRUE(s.ok()) << s.message();
  std::vector<solver::FitTrial> trials;
  for (const auto& t : subject.trials) trials.push_back({t.markers, {}});
  if (const char* dir = std::getenv("WRITE_TRC"))  // for `mocap fit` by hand
    for (const auto& t : subject.trials)
      EXPECT_TRUE(formats::WriteTrc(std::string(dir) + "/" + t.markers.name + ".trc", t.markers).ok());
  s = solver::FitModel(from_truth ? subject.truth : generic, trials, fit_options, &out.fit);
  EXPECT_TRUE(s.ok()) << s.message();
  if (!s.ok()) return out;
  out.lab_mm = sim::JointCentreTrackRmsMm(subject.truth, subject.trials, out.fit.model, out.fit.coordinates);
  std::printf("seed %d from the %s: %s\n", seed, from_truth ? "truth" : "generic model",
              out.fit.report.BriefReport().c_str());
  for (const char* joint : {"hip_r", "hip_l", "walker_knee_r", "walker_knee_l"})
    std::printf("  %-14s lab %6.2f mm RMS%s\n", joint, out.lab_mm[generic.FindJoint(joint)],
                Held(out.fit.report, joint) ? "  (held)" : "");
  return out;
}

}  // namespace

// The hips of welk007's model fitted from the generic model on three subjects (seeds 1-3): the
// right hip's functional trial excites both hips (the left is the stance leg): right within
// 3 mm, left within 6 mm RMS in the lab (seeds 1-7 measured: 0.55-1.43 and 0.69-4.76 mm).
TEST(OsimSubject, Welk007HipsFromTheGenericModel) {
  SKIP_WITHOUT_SHARED_DATA();
  for (int seed = 1; seed <= 3; ++seed) {
    SCOPED_TRACE("seed " + std::to_string(seed));
    const WelkOutcome o = FitWelk(seed, false);
    ASSERT_FALSE(o.lab_mm.empty());
    const solver::FitReport& r = o.fit.report;
    EXPECT_TRUE(r.converged()) << r.solver.message;
    EXPECT_LE(r.solver.num_iterations(), 30);
    EXPECT_LE(o.lab_mm[o.fit.model.FindJoint("hip_r")], 3.0);
    EXPECT_LE(o.lab_mm[o.fit.model.FindJoint("hip_l")], 6.0);
  }
}

namespace {
// The right knee's centre as the report gives it: its standard deviation (mm, the three
// coordinates' in quadrature, scaled by the femur's scale) and whether a coordinate of it is
// named undetermined.
std::pair<double, bool> KneeUncertainty(const solver::FitResult& fit) {
  const std::string knee = "walker_knee_r";
  double var = 0;
  for (const solver::ParameterEstimate& e : fit.report.parameters)
    if (e.name.rfind(knee + ".centre.", 0) == 0) var += e.std * e.std;
  bool undetermined = false;
  for (const std::string& name : fit.report.undetermined) undetermined |= name.rfind(knee + ".centre.", 0) == 0;
  const Joint& joint = fit.model.joints()[fit.model.FindJoint(knee)];
  return {1000 * fit.model.segments()[joint.parent].scale * std::sqrt(var), undetermined};
}
}  // namespace

// NOT MET, hence disabled: from the generic model the fit stops, CONVERGENCE, in a worse minimum
// than the one at the truth (seeds 1-7: marker RMS 0.801-0.837 mm against 0.761-0.771, right knee
// 2.5-8.8 mm RMS in the lab against 0.3-0.6). Why (BENCHMARKS.md, "welk007's model": figures):
// the fit holds what its design says the data cannot place at the scaled generic model's, and the
// fit from the truth holds it at the truth's. The right knee leans on two such holds: its held
// ankle and subtalar joint (2.9 and 6.2 deg of rotation, below FitOptions::min_excitation_deg)
// below it, and the femur's orientation against its markers, which a gauge row fixes although the
// walker knee below it has no axis parameters to follow it. Released (holds at 2 deg and the rows
// that are no gauge dropped, or the holds as 10 mm priors) the fit from the generic model reaches
// the truth's RMS within 0.2 % (and the fit from the truth then lands 1.3-3.2 mm off too: the
// data place this knee to a few mm), but on the real recordings the same releases let the knees,
// hips and ankles follow the skin (welk007's right knee 13 -> 22-34 mm from its epicondyles,
// gait2354's hips 0.1 -> 22 mm from OpenSim's). The holds stay; the report now counts them
// (Welk007ReportsTheRightKneeAsUncertainAsItIs).
TEST(OsimSubject, DISABLED_Welk007ReachesTheMinimumAtTheTruth) {
  SKIP_WITHOUT_SHARED_DATA();
  for (int seed = 1; seed <= 3; ++seed) {
    SCOPED_TRACE("seed " + std::to_string(seed));
    const WelkOutcome generic = FitWelk(seed, false), truth = FitWelk(seed, true);
    ASSERT_FALSE(generic.lab_mm.empty());
    ASSERT_FALSE(truth.lab_mm.empty());
    EXPECT_LE(generic.fit.report.marker_rms_mm, 1.01 * truth.fit.report.marker_rms_mm);
    EXPECT_LE(generic.lab_mm[generic.fit.model.FindJoint("walker_knee_r")], 2.0);
  }
}

// What the report says of the right knee that the fit from the generic model misplaces (see
// above): not the 0.1-0.3 mm standard deviation it gave while 2.5-8.8 mm off, but one that
// counts what the fit held at the generic model's (FitOptions::held_parameters, the rows that
// hold an observable direction) at what a scaled generic model is worth: the centre named
// undetermined, and the lab error within 3 of its standard deviations (seeds 1-7: sd 3.2-3.7 mm,
// errors 0.8-2.7 sd, 6 of 7 named undetermined).
TEST(OsimSubject, Welk007ReportsTheRightKneeAsUncertainAsItIs) {
  SKIP_WITHOUT_SHARED_DATA();
  for (int seed = 1; seed <= 3; ++seed) {
    SCOPED_TRACE("seed " + std::to_string(seed));
    const WelkOutcome o = FitWelk(seed, false);
    ASSERT_FALSE(o.lab_mm.empty());
    EXPECT_TRUE(o.fit.report.converged()) << o.fit.report.solver.message;
    const double error_mm = o.lab_mm[o.fit.model.FindJoint("walker_knee_r")];
    const auto [sd_mm, undetermined] = KneeUncertainty(o.fit);
    std::printf("  right knee %.2f mm from the truth, reported sd %.2f mm%s\n", error_mm, sd_mm,
                undetermined ? ", undetermined" : "");
    EXPECT_TRUE(undetermined);
    EXPECT_LE(error_mm, 3.0 * sd_mm);
  }
}

// The sweep behind Welk007ReachesTheMinimumAtTheTruth (run with --gtest_also_run_disabled_tests):
// seeds 1-SEEDS (environment, default 7), one line each: marker RMS from the generic model and
// from the truth, the right knee's lab RMS from each, the report's sd of that centre and whether
// it names it undetermined. HELD_SIGMA_MM (environment): FitOptions::held_centre_sigma_m in mm
// (0: the report counts the holds as exact, as before the sixteenth session; the fit is the same).
TEST(OsimSubject, DISABLED_Welk007Sweep) {
  SKIP_WITHOUT_SHARED_DATA();
  const int seeds = std::getenv("SEEDS") ? std::atoi(std::getenv("SEEDS")) : 7;
  solver::FitOptions options;
  if (const char* held = std::getenv("HELD_SIGMA_MM")) options.held_centre_sigma_m = 1e-3 * std::atof(held);
  if (options.held_centre_sigma_m == 0) options.held_axis_sigma_rad = 0;
  for (int seed = 1; seed <= seeds; ++seed) {
    const WelkOutcome g = FitWelk(seed, false, options), t = FitWelk(seed, true, options);
    ASSERT_FALSE(g.lab_mm.empty());
    ASSERT_FALSE(t.lab_mm.empty());
    const int k = g.fit.model.FindJoint("walker_knee_r");
    const auto [sd, undetermined] = KneeUncertainty(g.fit);
    const auto [sd_truth, undetermined_truth] = KneeUncertainty(t.fit);
    std::printf("SWEEP seed %d  rms %.3f / %.3f mm  (%+.2f %%)  knee_r %.2f / %.2f mm  sd %.2f / %.2f mm%s%s  it %d / %d\n",
                seed, g.fit.report.marker_rms_mm, t.fit.report.marker_rms_mm,
                100 * (g.fit.report.marker_rms_mm / t.fit.report.marker_rms_mm - 1), g.lab_mm[k], t.lab_mm[k], sd,
                sd_truth, undetermined ? "  undetermined" : "", undetermined_truth ? "  (truth: undetermined)" : "",
                g.fit.report.solver.num_iterations(), t.fit.report.solver.num_iterations());
  }
}

namespace {

std::string TestData(const std::string& file) { return std::string(MOCAP_SOURCE_DIR) + "/tests/data/" + file; }

// OpenCap's generic model (tests/data/laiuhlrich2022_skeleton.osim: its joints, constraints and
// bodies as in opencap-core) with the augmenter's 43 markers, as OpenCap scales it.
formats::OsimImport LaiUhlrich2022() {
  formats::OsimImport im;
  Status s = formats::ImportOsim(TestData("laiuhlrich2022_skeleton.osim"), &im);
  EXPECT_TRUE(s.ok()) << s.message();
  s = formats::LoadOsimMarkerSet(TestData("laiuhlrich2022_markers_augmenter.xml"), &im);
  EXPECT_TRUE(s.ok()) << s.message();
  return im;
}

// A motion of `model` at 60 Hz for `seconds`: every coordinate at its default (radians, metres)
// but those `set` gives, as a function of time (degrees for rotational ones, as a .mot holds them).
sim::PrescribedMotion MotionOf(const Model& model, const std::string& name, double seconds,
                               const std::function<void(double t, std::map<std::string, double>* deg)>& set) {
  sim::PrescribedMotion m;
  m.source = name;
  m.table.name = name;
  m.table.in_degrees = true;
  const int nf = static_cast<int>(std::lround(seconds * 60.0));
  m.table.values.resize(nf, model.num_coordinates());
  for (const Coordinate& c : model.coordinates()) m.table.column_names.push_back(c.name);
  for (int f = 0; f < nf; ++f) {
    const double t = f / 60.0;
    m.table.times.push_back(t);
    std::map<std::string, double> v;
    set(t, &v);
    for (int c = 0; c < model.num_coordinates(); ++c) {
      const Coordinate& co = model.coordinates()[c];
      const auto it = v.find(co.name);
      m.table.values(f, c) = it != v.end() ? it->second : co.default_value * (co.rotational ? 180.0 / M_PI : 1.0);
    }
  }
  return m;
}

// OpenCap's protocol for a lower-limb session: a standing static trial and two squats (hips and
// knees 5 -> 100 deg and back, the ankles dorsiflexed 25 deg, the trunk leaning, the thighs
// abducting and rotating a little, the arms reaching forward), the second wider and more rotated.
// `hip_sway_deg`: the right thigh's ab/adduction sway (4 deg; more moves the right hip past the
// fit's excitation rule while the left stays below it).
std::vector<sim::PrescribedMotion> OpenCapMotions(const Model& model, double hip_sway_deg = 4.0) {
  auto standing = [](std::map<std::string, double>* v) {
    (*v)["pelvis_ty"] = 0.93;
    for (const char* s : {"_r", "_l"}) {
      (*v)[std::string("knee_angle") + s] = 5;
      (*v)[std::string("arm_add") + s] = -15;
      (*v)[std::string("elbow_flex") + s] = 15;
      (*v)[std::string("pro_sup") + s] = 60;
    }
  };
  auto squat = [&](double period, double abduct, double rotate, double phase) {
    return [=](double t, std::map<std::string, double>* v) {
      standing(v);
      const double u = 0.5 * (1 - std::cos(2 * M_PI * t / period));  // 0 standing, 1 deepest
      (*v)["pelvis_ty"] = 0.93 - 0.33 * u;
      (*v)["pelvis_tx"] = -0.08 * u;
      (*v)["pelvis_tilt"] = -25 * u;
      (*v)["pelvis_rotation"] = 5 * std::sin(2 * M_PI * t / 3.1);
      (*v)["lumbar_extension"] = -15 * u;
      for (int side = 0; side < 2; ++side) {
        const std::string s = side == 0 ? "_r" : "_l";
        const double w = 2 * M_PI * t / (2.3 + 0.4 * side) + phase;
        (*v)["hip_flexion" + s] = 5 + 95 * u;
        (*v)["hip_adduction" + s] = -abduct * u + (side == 0 ? hip_sway_deg : 4.0) * std::sin(w);
        (*v)["hip_rotation" + s] = rotate * u + 8 * std::cos(w);
        (*v)["knee_angle" + s] = 5 + 95 * u;
        (*v)["ankle_angle" + s] = 25 * u;
        (*v)["subtalar_angle" + s] = 4 * std::sin(w);
        (*v)["arm_flex" + s] = 70 * u;
        (*v)["elbow_flex" + s] = 15 + 30 * u;
      }
    };
  };
  return {MotionOf(model, "static", 1.0, [&](double, std::map<std::string, double>* v) { standing(v); }),
          MotionOf(model, "squats1", 5.0, squat(2.5, 8, 5, 0.0)),
          MotionOf(model, "squats2", 4.0, squat(2.0, 15, 15, 1.3))};
}

// The video keypoints OpenCap's TRC holds beside the augmenter's markers (the pose detector's
// Neck, RShoulder, ..., RBigToe: opencap-core's getOpenPoseMarkers_lowerExtremity2 and the
// upper-limb ones), which the model lacks: each at its anatomical point of the truth (a joint
// centre, a landmark of the foot, the shoulders' midpoint) plus what a pose detector adds, a
// slow error of up to 15 mm per axis that follows the movement rather than any bone, and 3 mm of
// jitter.
void AddVideoKeypoints(const Model& truth, int seed, std::vector<sim::SimulatedTrial>* trials) {
  struct Keypoint {
    std::string name;
    std::vector<std::string> joints;  // the mean of these joints' centres
    std::string marker;               // or this truth marker
  };
  const std::vector<Keypoint> keypoints = {
      {"Neck", {"acromial_r", "acromial_l"}, ""}, {"RShoulder", {"acromial_r"}, ""},
      {"LShoulder", {"acromial_l"}, ""},          {"RElbow", {"elbow_r"}, ""},
      {"LElbow", {"elbow_l"}, ""},                {"RWrist", {"radius_hand_r"}, ""},
      {"LWrist", {"radius_hand_l"}, ""},          {"RHip", {"hip_r"}, ""},
      {"LHip", {"hip_l"}, ""},                    {"RKnee", {"walker_knee_r"}, ""},
      {"LKnee", {"walker_knee_l"}, ""},           {"RAnkle", {"ankle_r"}, ""},
      {"LAnkle", {"ankle_l"}, ""},                {"RHeel", {}, "r_calc_study"},
      {"LHeel", {}, "L_calc_study"},              {"RSmallToe", {}, "r_5meta_study"},
      {"LSmallToe", {}, "L_5meta_study"},         {"RBigToe", {}, "r_toe_study"},
      {"LBigToe", {}, "L_toe_study"}};
  const Geometry g(truth);
  ModelData d(truth);
  std::mt19937_64 rng(2000 + seed);
  std::uniform_real_distribution<double> amplitude(-0.015, 0.015), period(1.5, 4.0), phase(0, 2 * M_PI);
  std::normal_distribution<double> jitter(0.0, 0.003);
  for (sim::SimulatedTrial& t : *trials) {
    formats::MarkerTrial& m = t.markers;
    const int first = m.num_markers(), nf = m.num_frames();
    formats::RowMatrix positions(nf, 3 * (first + static_cast<int>(keypoints.size())));
    positions.leftCols(3 * first) = m.positions;
    std::vector<std::array<double, 9>> slow(keypoints.size());
    for (auto& w : slow)
      for (int a = 0; a < 3; ++a) w[3 * a] = amplitude(rng), w[3 * a + 1] = period(rng), w[3 * a + 2] = phase(rng);
    for (int f = 0; f < nf; ++f) {
      ForwardKinematics(truth, g, sim::TrueCoordinates(truth, t.coordinates, f), &d);
      for (size_t k = 0; k < keypoints.size(); ++k) {
        Eigen::Vector3d p = Eigen::Vector3d::Zero();
        if (keypoints[k].marker.empty()) {
          for (const std::string& j : keypoints[k].joints) p += JointCentre(truth, d, truth.FindJoint(j));
          p /= static_cast<double>(keypoints[k].joints.size());
        } else {
          p = MarkerPosition(truth, g, d, truth.FindMarker(keypoints[k].marker));
        }
        for (int a = 0; a < 3; ++a)
          p[a] += slow[k][3 * a] * std::sin(2 * M_PI * m.times[f] / slow[k][3 * a + 1] + slow[k][3 * a + 2]) + jitter(rng);
        positions.row(f).segment<3>(3 * (first + static_cast<int>(k))) = p.transpose();
      }
    }
    for (const Keypoint& k : keypoints) m.marker_names.push_back(k.name);
    m.positions = std::move(positions);
  }
}

struct OpenCapSession {
  int seed = 1;
  double noise_mm = 0.7;
  // The augmenter's own error, for the sweep: a slow error on every augmented marker (a constant
  // and a 1-4 s sinusoid per axis, each up to this, mm). 0: none (the test's subject).
  double augmenter_error_mm = 0.0;
  double hip_sway_deg = 4.0;  // OpenCapMotions
  double scale_spread = 0.10;  // the truth's segment scales within 1 +- this
  bool keypoints = true;      // AddVideoKeypoints
  // The fit ties the markers the model puts on a joint centre to it, as `mocap fit` does
  // (solver::TieCentreMarkers); false: fitted as skin markers (before the eighteenth session).
  bool tie_centre_markers = true;
};

struct OpenCapOutcome {
  sim::OsimSubject subject;
  Model fitted_from;                      // the generic model with its centre markers tied
  std::vector<solver::FitTrial> trials;   // as fitted
  solver::FitResult fit;
  std::vector<double> lab_mm;  // per joint: JointCentreTrackRmsMm against the truth
};

// A subject of OpenCap's model: the truth is the generic model with each segment scaled by
// 0.9-1.1, joint centres moved up to 10 mm and markers up to 5 mm on their segments, at 60 Hz.
// The hip-centre markers are what OpenCap's augmenter writes for them: the true centres plus the
// noise, not points of the pelvis's skin.
OpenCapOutcome SimulateOpenCapSubject(const OpenCapSession& session) {
  static const formats::OsimImport* generic = new formats::OsimImport(LaiUhlrich2022());
  const Model& model = generic->model;
  OpenCapOutcome out;
  sim::OsimSubjectOptions options;
  options.seed = session.seed;
  options.noise_mm = session.noise_mm;
  options.geometry.scale_spread = session.scale_spread;
  options.geometry.marker_mm = 5.0;
  Status s = sim::SimulateOsimSubject(model, OpenCapMotions(model, session.hip_sway_deg), options, &out.subject);
  EXPECT_TRUE(s.ok()) << s.message();
  const Model& truth = out.subject.truth;
  const Geometry g(truth);
  ModelData d(truth);
  std::mt19937_64 rng(1000 + session.seed);
  std::normal_distribution<double> noise(0.0, 1e-3 * options.noise_mm);
  for (sim::SimulatedTrial& t : out.subject.trials)
    for (const auto& [marker, joint] : {std::pair{"RHJC_study", "hip_r"}, std::pair{"LHJC_study", "hip_l"}}) {
      const int k = t.markers.FindMarker(marker), j = truth.FindJoint(joint);
      EXPECT_GE(k, 0);
      EXPECT_GE(j, 0);
      for (int f = 0; f < t.markers.num_frames(); ++f) {
        ForwardKinematics(truth, g, sim::TrueCoordinates(truth, t.coordinates, f), &d);
        const Eigen::Vector3d c = JointCentre(truth, d, j);
        for (int a = 0; a < 3; ++a) t.markers.positions(f, 3 * k + a) = c[a] + noise(rng);
      }
    }
  if (session.augmenter_error_mm > 0) {
    std::mt19937_64 r(3000 + session.seed);
    const double most = 1e-3 * session.augmenter_error_mm;
    std::uniform_real_distribution<double> size(-most, most), period(1.0, 4.0), phase(0, 2 * M_PI);
    for (sim::SimulatedTrial& t : out.subject.trials)
      for (int k = 0; k < t.markers.num_markers(); ++k)
        for (int a = 0; a < 3; ++a) {
          const double offset = size(r), amplitude = size(r), tau = period(r), phi = phase(r);
          for (int f = 0; f < t.markers.num_frames(); ++f)
            t.markers.positions(f, 3 * k + a) +=
                offset + amplitude * std::sin(2 * M_PI * t.markers.times[f] / tau + phi);
        }
  }
  if (session.keypoints) AddVideoKeypoints(truth, session.seed, &out.subject.trials);
  if (const char* dir = std::getenv("WRITE_TRC"))  // for `mocap fit` by hand
    for (const auto& t : out.subject.trials)
      EXPECT_TRUE(formats::WriteTrc(std::string(dir) + "/" + t.markers.name + ".trc", t.markers).ok());
  return out;
}

// The session fitted from the generic model as `mocap fit --model` fits it (its steps,
// tools/cmd_fit.cpp): the markers the model puts on a joint centre tied to it, FitModel with its
// defaults, the tied markers back on their own segments.
OpenCapOutcome FitOpenCapSubject(const OpenCapSession& session, solver::FitOptions options = solver::FitOptions()) {
  OpenCapOutcome out = SimulateOpenCapSubject(session);
  std::vector<formats::MarkerTrial> markers;
  for (const auto& t : out.subject.trials) markers.push_back(t.markers);
  Model model = out.subject.generic;
  std::vector<solver::CentreMarker> tied;
  if (session.tie_centre_markers) {
    const Status s = solver::TieCentreMarkers(markers, 0.002, &model, &tied);
    EXPECT_TRUE(s.ok()) << s.message();
    EXPECT_EQ(tied.size(), 2u);
  }
  for (const auto& c : tied) options.fixed_markers.push_back(c.marker);
  for (auto& m : markers) out.trials.push_back({std::move(m), {}});
  out.fitted_from = model;
  Status s = solver::FitModel(model, out.trials, options, &out.fit);
  EXPECT_TRUE(s.ok()) << s.message();
  if (!s.ok()) return out;
  s = solver::UntieCentreMarkers(tied, &out.fit.model);
  EXPECT_TRUE(s.ok()) << s.message();
  out.lab_mm = sim::JointCentreTrackRmsMm(out.subject.truth, out.subject.trials, out.fit.model, out.fit.coordinates);
  return out;
}

// Joint j's lab error (fitted centre minus true, RMS over every frame of every trial, mm) split
// into its part along the axis of the joint's first rotation element (the truth's, in the lab)
// and the part across it. A walker knee's centre along its flexion axis is all but a gauge: only
// its small coupled rotations see it, and the report names it undetermined.
std::pair<double, double> AlongAcrossMm(const OpenCapOutcome& o, int j) {
  const Model& truth = o.subject.truth;
  const Model& fitted = o.fit.model;
  const Geometry gt(truth), gf(fitted);
  ModelData dt(truth), df(fitted);
  const auto& elements = truth.joints()[j].elements;
  int e = 0;
  while (e < static_cast<int>(elements.size()) && elements[e].kind != ElementKind::kRotation) ++e;
  if (e == static_cast<int>(elements.size())) return {0.0, 0.0};
  double along = 0, across = 0;
  long n = 0;
  for (size_t t = 0; t < o.subject.trials.size(); ++t)
    for (int f = 0; f < o.subject.trials[t].markers.num_frames(); ++f) {
      ForwardKinematics(truth, gt, sim::TrueCoordinates(truth, o.subject.trials[t].coordinates, f), &dt);
      ForwardKinematics(fitted, gf, o.fit.coordinates[t].row(f).transpose(), &df);
      const Eigen::Vector3d d = JointCentre(fitted, df, j) - JointCentre(truth, dt, j);
      const Eigen::Vector3d u = (dt.element_rotation[j][e] * gt.axis[j][e]).normalized();
      along += std::pow(d.dot(u), 2);
      across += (d - d.dot(u) * u).squaredNorm();
      ++n;
    }
  return {1000 * std::sqrt(along / n), 1000 * std::sqrt(across / n)};
}

void PrintOpenCap(const OpenCapSession& session, const OpenCapOutcome& o) {
  std::printf("seed %d: %s\n", session.seed, o.fit.report.BriefReport().c_str());
  for (const char* joint : {"hip_r", "hip_l", "walker_knee_r", "walker_knee_l", "ankle_r", "ankle_l"}) {
    const int j = o.fit.model.FindJoint(joint);
    const auto [along, across] = AlongAcrossMm(o, j);
    std::printf("  %-14s lab %6.2f mm RMS (along its first axis %6.2f, across %6.2f)%s\n", joint, o.lab_mm[j],
                along, across, Held(o.fit.report, joint) ? "  (held)" : "");
  }
}

bool NamedUndetermined(const solver::FitReport& r, const std::string& parameter) {
  return std::find(r.undetermined.begin(), r.undetermined.end(), parameter) != r.undetermined.end();
}

}  // namespace

// OpenCap's generic model LaiUhlrich2022 fitted as a lab would fit an OpenCap session with
// `mocap fit --model LaiUhlrich2022.osim static squats1 squats2` (no stages, no groups by hand),
// on three subjects (seeds 1-3): the augmenter's 43 markers at 0.7 mm noise, its hip-centre
// markers at the true centres, and the 19 video keypoints the TRC also holds (not in the model:
// left out, as they ride on two segments alike). What the squats excite is recovered:
//  - converged in at most 30 iterations (seeds 1-3: 17; seeds 1-7 measured: 17-23, and 17-25 with
//    the truth's scales spread to +-30 %), marker RMS within 10 % of what the noise leaves (+5.3,
//    +5.3, +6.9 %);
//  - hips within 1 mm RMS in the lab (0.44-0.53 mm; seeds 1-7: at most 0.56), fitted: the hip-centre markers place them
//    although the squats turn them only 5-9.6 deg about their second axis (FitOptions::
//    min_excitation_deg). Held there as before this session, they were 0.72-1.98 mm off, and
//    seed 3's marker RMS 14 % above the noise's;
//  - knees across their flexion axis within 4 mm (1.4-3.7 mm; seeds 1-7: 0.4-3.7), along it named undetermined
//    (0.6-7.6 mm: only the walker knee's small coupled rotations see it);
//  - ankles (dorsiflexion 25 deg: 8.5-9.0 deg RMS, below min_excitation_deg) held and reported
//    so, within what the subject's own deviation and the scales leave (0.7-10.0 mm; seeds 1-7:
//    at most 10.3).
TEST(OsimSubject, OpenCapSquatsFromLaiUhlrich2022) {
  for (int seed = 1; seed <= 3; ++seed) {
    SCOPED_TRACE("seed " + std::to_string(seed));
    OpenCapSession session;
    session.seed = seed;
    const OpenCapOutcome o = FitOpenCapSubject(session);
    ASSERT_FALSE(o.lab_mm.empty());
    PrintOpenCap(session, o);
    const solver::FitReport& r = o.fit.report;
    EXPECT_TRUE(r.converged()) << r.solver.message;
    EXPECT_LE(r.solver.num_iterations(), 30);
    ExpectMarkerRmsAtTheNoise(r, session.noise_mm);
    const Model& m = o.fit.model;
    for (const char* side : {"_r", "_l"}) {
      const std::string hip = std::string("hip") + side, knee = std::string("walker_knee") + side,
                        ankle = std::string("ankle") + side;
      EXPECT_FALSE(Held(r, hip));
      EXPECT_LE(o.lab_mm[m.FindJoint(hip)], 1.0) << hip;
      EXPECT_FALSE(Held(r, knee));
      EXPECT_LE(AlongAcrossMm(o, m.FindJoint(knee)).second, 4.0) << knee;
      EXPECT_TRUE(NamedUndetermined(r, knee + ".centre.x")) << knee;
      EXPECT_TRUE(Held(r, ankle));
      EXPECT_LE(o.lab_mm[m.FindJoint(ankle)], 12.0) << ankle;
    }
  }
}

// The report's functional check of OpenCap's walker knees: a knee whose rotations all follow its
// flexion angle turns about one axis, so its reference is SARA's axis (solver::DescribedByAxis),
// compared with the same estimate made on the fitted model's own motion (its coupled rotations
// tilt that axis from the flexion axis). The fitted knee axes are the truth's (the subject's
// axes are the generic model's), so each squat trial's check must find them within 1 deg (seed 1:
// 0.07-0.20 deg; SARA's own sd 0.5-0.7 deg). Before this session SCoRE judged them as ball joints, "not excited" (1.5 deg about a
// second axis): no reference at all; with SARA against the flexion axis alone, 7.6-8.2 deg apart
// and a warning on a right fit.
TEST(OsimSubject, OpenCapWalkerKneesAreCheckedAgainstSara) {
  OpenCapSession session;
  const OpenCapOutcome o = FitOpenCapSubject(session);
  ASSERT_FALSE(o.lab_mm.empty());
  solver::FitTrustOptions options;
  options.joints = {"walker_knee_r", "walker_knee_l"};
  solver::FitTrust trust;
  const Status s = solver::CheckFitTrust(o.fitted_from, o.fit, o.trials, options, &trust);
  ASSERT_TRUE(s.ok()) << s.message();
  ASSERT_EQ(trust.joints.size(), 2u);
  for (const solver::JointTrust& knee : trust.joints) {
    SCOPED_TRACE(knee.joint);
    EXPECT_TRUE(knee.axis_joint);
    ASSERT_EQ(knee.checks.size(), 3u);
    EXPECT_FALSE(knee.checks[0].excited);  // the static trial
    for (int t = 1; t < 3; ++t) {
      const solver::FunctionalCheck& c = knee.checks[t];
      std::printf("%s on %s: fitted axis %.2f deg from SARA's (SARA sd %.2f deg), centre %.1f mm from its line\n",
                  knee.joint.c_str(), c.trial.c_str(), c.axis_angle_deg, c.functional_axis_std_deg,
                  c.axis_line_distance_mm);
      ASSERT_TRUE(c.excited) << c.note;
      EXPECT_LT(c.axis_angle_deg, 1.0);
      EXPECT_FALSE(c.far);
    }
  }
}

// The same session through the command a lab types, on the files OpenCap would give it (the
// trials as TRC, the model and its marker set as .osim and .xml): `mocap fit --model
// laiuhlrich2022_skeleton.osim --marker-set laiuhlrich2022_markers_augmenter.xml static.trc
// squats1.trc squats2.trc --out fitted.osim --report report.json`. What it writes, read back --
// the fitted OpenSim model and each trial's .mot of OpenSim coordinates -- puts the hips within
// 1 mm RMS of the truth in the lab and the knees across their axes within 4 mm (seed 1: 0.44-0.48
// and 1.4-3.7 mm, as the library fit); the report says what a lab needs to read: converged, the 19
// keypoints unmatched, no model marker unseen, the hips not held, the knees checked against SARA.
TEST(OsimSubject, OpenCapSessionThroughMocapFit) {
  OpenCapSession session;
  const OpenCapOutcome o = SimulateOpenCapSubject(session);
  const fs::path dir = testutil::FreshDir("osim_subject", "opencap");
  std::string trials;
  for (const auto& t : o.subject.trials) {
    const std::string path = (dir / (t.markers.name + ".trc")).string();
    ASSERT_TRUE(formats::WriteTrc(path, t.markers).ok());
    trials += " " + path;
  }
  const auto r = testutil::Mocap("fit --model " + TestData("laiuhlrich2022_skeleton.osim") + " --marker-set " +
                                 TestData("laiuhlrich2022_markers_augmenter.xml") + trials + " --out " +
                                 (dir / "fitted.osim").string() + " --report " + (dir / "report.json").string());
  ASSERT_EQ(r.status, 0) << r.output;
  EXPECT_NE(r.output.find("RHJC_study: the model puts it on hip_r's centre"), std::string::npos) << r.output;
  nlohmann::json report;
  std::ifstream(dir / "report.json") >> report;
  EXPECT_EQ(report["termination"], "CONVERGENCE");
  EXPECT_LE(report["iterations"].get<int>(), 30);
  EXPECT_EQ(report["unmatched_trial_markers"].size(), 19u);
  EXPECT_TRUE(report["unobserved_model_markers"].empty());
  EXPECT_EQ(report["held_joints"].dump().find("hip_"), std::string::npos) << report["held_joints"].dump();
  int knees = 0;
  for (const auto& j : report["joint_checks"]) {
    if (j["joint"] != "walker_knee_r" && j["joint"] != "walker_knee_l") continue;
    ++knees;
    EXPECT_TRUE(j["axis_joint"].get<bool>()) << j["joint"];
    for (const auto& t : j["trials"])
      if (t["trial"] != "static") EXPECT_LT(t["axis_angle_deg"].get<double>(), 1.0) << j["joint"] << " " << t["trial"];
  }
  EXPECT_EQ(knees, 2);

  formats::OsimImport fitted;
  Status s = formats::ImportOsim((dir / "fitted.osim").string(), &fitted);
  ASSERT_TRUE(s.ok()) << s.message();
  std::vector<Eigen::MatrixXd> poses;
  for (const auto& t : o.subject.trials) {
    formats::CoordinateTable table;
    s = formats::ReadMot((dir / (t.markers.name + ".fitted.mot")).string(), &table);
    ASSERT_TRUE(s.ok()) << s.message();
    ASSERT_EQ(table.num_frames(), t.markers.num_frames());
    const std::vector<int> column = testutil::CoordinateColumns(fitted.model, table);
    Eigen::MatrixXd z(table.num_frames(), fitted.model.num_coordinates());
    for (int f = 0; f < table.num_frames(); ++f) z.row(f) = testutil::OsimPose(fitted, table, column, f).transpose();
    poses.push_back(z);
  }
  const std::vector<double> lab_mm = sim::JointCentreTrackRmsMm(o.subject.truth, o.subject.trials, fitted.model, poses);
  OpenCapOutcome as_written = o;
  as_written.fit.model = fitted.model;
  as_written.fit.coordinates = poses;
  for (const char* side : {"_r", "_l"}) {
    const std::string hip = std::string("hip") + side, knee = std::string("walker_knee") + side;
    const double across = AlongAcrossMm(as_written, fitted.model.FindJoint(knee)).second;
    std::printf("written: %s %.2f mm, %s %.2f mm across its axis\n", hip.c_str(),
                lab_mm[fitted.model.FindJoint(hip)], knee.c_str(), across);
    EXPECT_LE(lab_mm[fitted.model.FindJoint(hip)], 1.0) << hip;
    EXPECT_LE(across, 4.0) << knee;
  }
}

// The sweep behind OpenCapSquatsFromLaiUhlrich2022 (run with --gtest_also_run_disabled_tests), one block per seed:
// SEEDS (default 3), AUGMENTER_MM (the augmenter's slow error, OpenCapSession::augmenter_error_mm;
// 10 gives the 8-9 mm RMS of a real OpenCap session), HIP_SWAY_DEG (the right thigh's sway),
// NO_TIE (the hip-centre markers fitted as skin markers), NO_KEYPOINTS, MIN_EXCITATION_DEG
// (FitOptions::min_excitation_deg), SCALE_SPREAD (OpenCapSession::scale_spread).
TEST(OsimSubject, DISABLED_OpenCapSweep) {
  const int seeds = std::getenv("SEEDS") ? std::atoi(std::getenv("SEEDS")) : 3;
  for (int seed = 1; seed <= seeds; ++seed) {
    OpenCapSession session;
    session.seed = seed;
    if (const char* e = std::getenv("AUGMENTER_MM")) session.augmenter_error_mm = std::atof(e);
    if (const char* e = std::getenv("HIP_SWAY_DEG")) session.hip_sway_deg = std::atof(e);
    if (const char* e = std::getenv("SCALE_SPREAD")) session.scale_spread = std::atof(e);
    session.tie_centre_markers = std::getenv("NO_TIE") == nullptr;
    session.keypoints = std::getenv("NO_KEYPOINTS") == nullptr;
    solver::FitOptions options;
    if (const char* e = std::getenv("MIN_EXCITATION_DEG")) options.min_excitation_deg = std::atof(e);
    const OpenCapOutcome o = FitOpenCapSubject(session, options);
    ASSERT_FALSE(o.lab_mm.empty());
    PrintOpenCap(session, o);
  }
}
