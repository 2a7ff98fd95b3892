// The fit from a generic OpenSim model that is not our default one, scored against a known truth
// (sim/osim_subject.h): gait2354 with its Scale marker set, posed by OpenSim's own IK of the walk
// and the static pose its Scale tool solved. What held-back subjects would show about the fit on
// a lab's model, here with the truth known. Skipped where ../shared/data is absent.
#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>

#include "formats/mot.h"
#include "formats/osim.h"
#include "formats/trc.h"
#include "model/compare.h"
#include "model/kinematics.h"
#include "sim/osim_subject.h"
#include "solver/global_fit.h"
#include "tests/file_test_util.h"

using namespace mocap;
using mocap::testutil::SharedData;

namespace {

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

// The walk (OpenSim's IK, 73 frames at 60 Hz) and a 1 s static trial holding the Scale tool's
// static pose.
std::vector<sim::PrescribedMotion> Gait2354Motions(const Model& model) {
  sim::PrescribedMotion walk = Motion("reference_outputs/subject01_walk1_ik.mot", "subject01_walk1");
  sim::PrescribedMotion stat = Motion("reference_outputs/subject01_static_output.mot", "subject01_static");
  formats::CoordinateTable held;
  const Status s = sim::HoldPose(model, stat.table, 0, 60, 60.0, &held);
  EXPECT_TRUE(s.ok()) << s.message();
  stat.table = held;
  // Each trial records the model markers its real recording has: the walk has no knee or ankle
  // markers (subject01_walk1.trc), the static trial every one.
  stat.markers = RecordedModelMarkers(model, "subject01_static.trc");
  walk.markers = RecordedModelMarkers(model, "subject01_walk1.trc");
  return {stat, walk};
}

}  // namespace

TEST(OsimSubject, Gait2354FromTheGenericModel) {
  SKIP_WITHOUT_SHARED_DATA();
  const Model generic = Gait2354Generic();
  sim::OsimSubjectOptions options;
  sim::OsimSubject subject;
  Status s = sim::SimulateOsimSubject(generic, Gait2354Motions(generic), options, &subject);
  ASSERT_TRUE(s.ok()) << s.message();
  std::vector<solver::FitTrial> trials;
  for (const auto& t : subject.trials) trials.push_back({t.markers, {}});
  const auto t0 = std::chrono::steady_clock::now();
  solver::FitResult fit;
  s = solver::FitModel(generic, trials, solver::FitOptions(), &fit);
  ASSERT_TRUE(s.ok()) << s.message();
  std::printf("%s\n  %.2f s\n", fit.report.BriefReport().c_str(),
              std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
  ModelComparison truth_vs_fit, truth_vs_generic;
  ASSERT_TRUE(CompareModels(subject.truth, fit.model, &truth_vs_fit).ok());
  ASSERT_TRUE(CompareModels(subject.truth, generic, &truth_vs_generic).ok());
  const std::vector<double> lab = sim::JointCentreTrackRmsMm(subject.truth, subject.trials, fit.model, fit.coordinates);
  for (size_t k = 0; k < truth_vs_fit.joints.size(); ++k) {
    const auto& jd = truth_vs_fit.joints[k];
    std::printf("  %-14s centre %7.2f mm (generic %7.2f)  axis %6.2f deg  lab %7.2f mm RMS (%s)\n", jd.joint.c_str(),
                jd.centre_error_mm, truth_vs_generic.joints[k].centre_error_mm, jd.axis_error_deg,
                lab[subject.truth.FindJoint(jd.joint)], jd.basis.c_str());
  }
  for (const auto& sd : truth_vs_fit.segments) std::printf("  %-28s %+6.2f %%\n", sd.name.c_str(), sd.error_pct);
  for (const auto& [name, rms] : fit.report.per_marker_rms_mm) std::printf("  %-16s %.2f mm\n", name.c_str(), rms);
  for (const auto& [joint, why] : fit.report.held_joints) std::printf("  held %s: %s\n", joint.c_str(), why.c_str());
  std::printf("  undetermined:");
  for (const auto& u : fit.report.undetermined) std::printf(" %s", u.c_str());
  std::printf("\n");
}

TEST(OsimSubject, DISABLED_Sweep) {
  const Model generic = Gait2354Generic();
  const auto motions = Gait2354Motions(generic);
  const double missing = std::getenv("MISSING") ? std::atof(std::getenv("MISSING")) : 0.0;
  const double noise = std::getenv("NOISE") ? std::atof(std::getenv("NOISE")) : 0.5;
  const std::vector<std::string> names = {"hip_r", "hip_l", "knee_r", "knee_l", "ankle_r", "ankle_l", "back"};
  for (int seed = 1; seed <= 20; ++seed) {
    sim::OsimSubjectOptions options;
    options.seed = seed;
    options.missing = missing;
    options.noise_mm = noise;
    sim::OsimSubject subject;
    ASSERT_TRUE(sim::SimulateOsimSubject(generic, motions, options, &subject).ok());
    std::vector<solver::FitTrial> trials;
    for (const auto& t : subject.trials) trials.push_back({t.markers, {}});
    solver::FitResult fit;
    solver::FitOptions fo;
    if (std::getenv("MINEXC")) fo.min_excitation_deg = std::atof(std::getenv("MINEXC"));
    ASSERT_TRUE(solver::FitModel(generic, trials, fo, &fit).ok());
    ModelComparison c, g;
    ASSERT_TRUE(CompareModels(subject.truth, fit.model, &c).ok());
    ASSERT_TRUE(CompareModels(subject.truth, generic, &g).ok());
    const auto lab = sim::JointCentreTrackRmsMm(subject.truth, subject.trials, fit.model, fit.coordinates);
    std::printf("seed %2d rms %.2f it %2d %s |", seed, fit.report.marker_rms_mm, fit.report.solver.num_iterations(),
                fit.report.converged() ? "C" : "N");
    for (const auto& n : names) {
      for (size_t k = 0; k < c.joints.size(); ++k)
        if (c.joints[k].joint == n)
          std::printf(" %s %5.1f/%5.1f(g%5.1f)", n.c_str(), c.joints[k].centre_error_mm, lab[subject.truth.FindJoint(n)],
                      g.joints[k].centre_error_mm);
    }
    std::printf("\n");
  }
}
