// The fit from a generic OpenSim model that is not our default one, scored against a known truth
// (sim/osim_subject.h): gait2354 with its Scale marker set, posed by OpenSim's own IK of the walk
// and by the static pose its Scale tool solved, each trial recording the markers its real
// recording has. What a held-back subject would show about the fit on a lab's model, with the
// truth known. The real-data tests skip where ../shared/data is absent.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <random>
#include <utility>

#include "formats/mot.h"
#include "formats/osim.h"
#include "formats/trc.h"
#include "model/compare.h"
#include "model/default_model.h"
#include "model/kinematics.h"
#include "sim/osim_subject.h"
#include "solver/global_fit.h"
#include "solver/inverse_kinematics.h"
#include "solver/marker_fit_problem.h"
#include "tests/assembly_test_util.h"
#include "tests/file_test_util.h"

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
    const double expected =
        options.noise_mm * std::sqrt(3.0 * (1.0 - double(r.unknowns) / (3.0 * r.marker_samples)));
    EXPECT_NEAR(r.marker_rms_mm, expected, 0.1 * expected);
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
