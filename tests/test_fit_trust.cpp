// The report's per-joint trust table (solver/fit_trust.h): the fitted centre against its functional
// estimate on each trial and against the generic model, on a simulated session whose truth is
// known, on welk007's real hip trial through `mocap fit --report`, and the inputs it refuses.
#include <gtest/gtest.h>

#include <set>

#include <filesystem>
#include <nlohmann/json.hpp>

#include "model/kinematics.h"
#include "sim/protocol.h"
#include "sim/simulate.h"
#include "solver/fit_report_json.h"
#include "solver/fit_trust.h"
#include "solver/global_fit.h"
#include "tests/file_test_util.h"

using namespace mocap;

namespace {

// A hip star arc and a knee flexion, rigid clusters (the medial markers give femur and tibia
// three markers each), fitted from the nominal model.
struct SimulatedFit {
  sim::SimulatedSession session;
  std::vector<solver::FitTrial> trials;
  solver::FitResult result;
};

const SimulatedFit& Fit() {
  static const SimulatedFit* fit = [] {
    auto* out = new SimulatedFit;
    sim::Protocol protocol;
    protocol.name = "trust";
    for (const char* name : {"hip_star_arc_r", "knee_flexion_r"})
      protocol.movements.push_back(*sim::DefaultProtocol().Find(name));
    sim::SimulationOptions options;
    options.seed = 11;
    options.noise_mm = 0.5;
    options.medial_markers = true;
    Status s = sim::SimulateSession(options, protocol, &out->session);
    EXPECT_TRUE(s.ok()) << s.message();
    for (const sim::SimulatedTrial& t : out->session.trials) out->trials.push_back({t.markers, {}});
    s = solver::FitModel(out->session.nominal, out->trials, solver::FitOptions(), &out->result);
    EXPECT_TRUE(s.ok()) << s.message();
    return out;
  }();
  return *fit;
}

// The fit's result with its hip_r centre moved `metres` along the pelvis's x axis.
solver::FitResult WithHipMoved(const solver::FitResult& result, double metres) {
  solver::FitResult moved = result;
  const Model& m = result.model;
  const int j = m.FindJoint("hip_r");
  Eigen::VectorXd p = m.InitialParameters();
  p[m.centre_index(j)] += metres / p[m.scale_index(m.joints()[j].parent)];
  EXPECT_TRUE(m.WithParameters(p, &moved.model).ok());
  return moved;
}

const solver::JointTrust& Joint(const solver::FitTrust& trust, const std::string& name) {
  for (const auto& j : trust.joints)
    if (j.joint == name) return j;
  ADD_FAILURE() << "no joint " << name;
  return trust.joints.front();
}

TEST(FitTrust, FittedCentresAgreeWithFunctionalOnTheTrialsThatExciteThem) {
  const SimulatedFit& fit = Fit();
  ASSERT_TRUE(fit.result.report.converged()) << fit.result.report.BriefReport();
  solver::FitTrustOptions options;
  options.joints = {"hip_r", "knee_r"};
  solver::FitTrust trust;
  const Status s = solver::CheckFitTrust(fit.session.nominal, fit.result, fit.trials, options, &trust);
  ASSERT_TRUE(s.ok()) << s.message();
  ASSERT_EQ(trust.joints.size(), 2u);
  EXPECT_EQ(trust.undetermined, fit.result.report.undetermined);
  EXPECT_EQ(trust.outlier_markers, fit.result.report.outlier_markers);

  const solver::JointTrust& hip = Joint(trust, "hip_r");
  EXPECT_FALSE(hip.axis_joint);
  ASSERT_EQ(hip.checks.size(), 2u);
  const solver::FunctionalCheck& arc = hip.checks[0];
  const solver::FunctionalCheck& knee_trial = hip.checks[1];
  EXPECT_EQ(arc.trial, "hip_star_arc_r");
  std::printf("hip_r: %.2f mm from SCoRE on %s (spread %.2f mm, SCoRE sd %.2f mm, %d frames); %.2f mm from "
              "the generic, fit sd %.2f mm\n",
              arc.centre_distance_mm, arc.trial.c_str(), arc.centre_spread_mm, arc.functional_std_mm, arc.frames,
              hip.from_generic_mm, hip.fitted_std_mm);
  ASSERT_TRUE(arc.excited) << arc.note;
  EXPECT_GT(arc.frames, 400);
  // Both the fit and SCoRE are within about 1 mm of the truth on rigid clusters.
  EXPECT_LT(arc.centre_distance_mm, 2.0);
  EXPECT_GT(arc.functional_std_mm, 0.0);
  EXPECT_LT(arc.centre_spread_mm, 3.0);
  // The knee flexion trial does not show the hip's centre: no figure, a reason.
  EXPECT_TRUE(knee_trial.estimated);
  EXPECT_FALSE(knee_trial.excited);
  EXPECT_NE(knee_trial.note.find("two axes"), std::string::npos) << knee_trial.note;
  EXPECT_EQ(hip.best_check, 0);
  // The hip has no translation: its centre in the parent is the geometry's scaled centre, in
  // either model.
  const int hip_index = fit.session.nominal.FindJoint("hip_r");
  EXPECT_NEAR(hip.from_generic_mm,
              1000.0 * (Geometry(fit.result.model).centre_scaled[hip_index] - Geometry(fit.session.nominal).centre_scaled[hip_index]).norm(),
              1e-6);
  EXPECT_GT(hip.from_generic_mm, 1.0);
  EXPECT_TRUE(hip.centre_fitted);
  EXPECT_GT(hip.fitted_std_mm, 0.0);
  EXPECT_LT(hip.fitted_std_mm, 2.0);
  EXPECT_FALSE(hip.undetermined);

  const solver::JointTrust& knee = Joint(trust, "knee_r");
  EXPECT_TRUE(knee.axis_joint);
  const solver::FunctionalCheck& flex = knee.checks[1];
  std::printf("knee_r: axis %.3f deg from SARA on %s (spread %.3f deg, SARA sd %.3f deg), centre %.2f mm from "
              "its line\n",
              flex.axis_angle_deg, flex.trial.c_str(), flex.axis_spread_deg, flex.functional_axis_std_deg,
              flex.axis_line_distance_mm);
  ASSERT_TRUE(flex.excited) << flex.note;
  EXPECT_LT(flex.axis_angle_deg, 1.0);
  EXPECT_LT(flex.axis_line_distance_mm, 2.0);
  EXPECT_EQ(knee.best_check, 1);

  // The next most precise trial's estimate and its distance from the headline's: none for the
  // hip (one trial excites it); for every joint, the excited non-headline check with the smallest
  // sd, and the distance between the two estimates in the parent's frame.
  EXPECT_EQ(hip.second_check, -1);
  for (const solver::JointTrust* jt : {&hip, &knee}) {
    int second = -1;
    for (int c = 0; c < static_cast<int>(jt->checks.size()); ++c) {
      const auto sd = [&](int k) {
        return jt->axis_joint ? jt->checks[k].functional_axis_std_deg : jt->checks[k].functional_std_mm;
      };
      if (jt->checks[c].excited && c != jt->best_check && (second < 0 || sd(c) < sd(second))) second = c;
    }
    EXPECT_EQ(jt->second_check, second) << jt->joint;
    if (second < 0) continue;
    const solver::FunctionalCheck& a = jt->checks[jt->best_check];
    const solver::FunctionalCheck& b = jt->checks[second];
    const double expected =
        jt->axis_joint ? std::acos(std::min(1.0, std::abs(a.functional_axis_in_parent.dot(b.functional_axis_in_parent)))) * 180.0 / M_PI
                       : 1000.0 * (a.functional_centre_in_parent - b.functional_centre_in_parent).norm();
    EXPECT_NEAR(jt->functional_between_trials, expected, 1e-9) << jt->joint;
    std::printf("%s: functional estimates on %s and %s %.3f %s apart\n", jt->joint.c_str(), a.trial.c_str(),
                b.trial.c_str(), jt->functional_between_trials, jt->axis_joint ? "deg" : "mm");
    // Rigid clusters, 0.5 mm noise: two trials that excite the joint agree.
    EXPECT_LT(jt->functional_between_trials, jt->axis_joint ? 2.0 : 3.0) << jt->joint;
  }

  // The JSON the report page reads.
  const nlohmann::json j = solver::FitTrustJson(trust);
  ASSERT_EQ(j.size(), 2u);
  EXPECT_EQ(j[0]["joint"], "hip_r");
  EXPECT_EQ(j[0]["best_trial"], "hip_star_arc_r");
  EXPECT_NEAR(j[0]["trials"][0]["centre_distance_mm"].get<double>(), arc.centre_distance_mm, 1e-12);
  EXPECT_FALSE(j[0]["trials"][1]["excited"].get<bool>());
  EXPECT_FALSE(j[0]["trials"][1].contains("centre_distance_mm"));
  EXPECT_TRUE(j[1]["trials"][1].contains("axis_angle_deg"));
  EXPECT_FALSE(j[1]["trials"][1].contains("centre_distance_mm"));  // SCoRE's centre: no hinge reference
  EXPECT_FALSE(j[0]["trials"][0].contains("axis_angle_deg"));
  EXPECT_TRUE(j[0]["second_trial"].is_null());
  EXPECT_TRUE(j[0]["functional_between_trials_mm"].is_null());
  EXPECT_FALSE(j[1].contains("functional_between_trials_mm"));  // an axis joint's is in degrees
  EXPECT_EQ(j[1]["functional_between_trials_deg"].is_null(), knee.second_check < 0);
}

// A fitted model whose hip centre is moved 10 mm along the pelvis's x axis: the check reports
// the 10 mm (the functional estimate does not depend on the model's geometry).
TEST(FitTrust, AMovedCentreShowsItsDistance) {
  const SimulatedFit& fit = Fit();
  const solver::FitResult moved = WithHipMoved(fit.result, 0.010);
  solver::FitTrustOptions options;
  options.joints = {"hip_r"};
  solver::FitTrust before, after;
  ASSERT_TRUE(solver::CheckFitTrust(fit.session.nominal, fit.result, fit.trials, options, &before).ok());
  ASSERT_TRUE(solver::CheckFitTrust(fit.session.nominal, moved, fit.trials, options, &after).ok());
  const double d0 = before.joints[0].checks[0].centre_distance_mm, d1 = after.joints[0].checks[0].centre_distance_mm;
  std::printf("hip_r moved 10 mm: %.2f mm from SCoRE (was %.2f)\n", d1, d0);
  EXPECT_NEAR(d1, 10.0, d0 + 0.01);
  EXPECT_EQ(after.joints[0].checks[0].functional_std_mm, before.joints[0].checks[0].functional_std_mm);
}

// The profile check (fit_trust.h): the fit solved again free and with the hip held at SCoRE's
// centre. Here every check counts as far (far_mm tiny) so that it runs. On the fitted result the
// free solve stays where the fit ended, holding the centre costs what its distance from the
// fitted centre is worth against the fit's own standard deviation, and told_apart follows the
// chi-square; on a result whose hip was moved 10 mm the free solve goes back (the fit was not at
// its minimum) and says so.
TEST(FitTrust, ProfileHoldsTheCentreAtItsFunctionalEstimate) {
  const SimulatedFit& fit = Fit();
  solver::FitTrustOptions options;
  options.joints = {"hip_r"};
  options.far_mm = 1e-6;
  solver::FitTrust trust;
  ASSERT_TRUE(solver::CheckFitTrust(fit.session.nominal, fit.result, fit.trials, options, &trust).ok());
  const solver::JointTrust& hip = Joint(trust, "hip_r");
  ASSERT_EQ(hip.profile.size(), 1u);
  const solver::ProfileCheck& p = hip.profile[0];
  const double sigma_mm = hip.fitted_std_mm;
  std::printf("hip_r held at SCoRE (%.2f mm away, fit sd %.3f mm): chi-square +%.2f, free moved %.3f mm, "
              "iterations %d / %d, RMS %.4f -> %.4f mm\n",
              p.centre_distance_mm, sigma_mm, p.delta_chi2, p.free_centre_moved_mm, p.iterations_free,
              p.iterations_held, p.marker_rms_free_mm, p.marker_rms_held_mm);
  EXPECT_EQ(p.trial, "hip_star_arc_r");
  EXPECT_LT(p.free_centre_moved_mm, 0.05);
  EXPECT_GT(p.delta_chi2, 0.0);
  EXPECT_GE(p.marker_rms_held_mm, p.marker_rms_free_mm);
  // A 3-D centre held d away costs about (d / sd)^2 where sd is the fit's (its covariance).
  const double expected = std::pow(p.centre_distance_mm / sigma_mm, 2);
  EXPECT_GT(p.delta_chi2, 0.2 * expected);
  EXPECT_LT(p.delta_chi2, 5.0 * expected);
  EXPECT_EQ(p.told_apart, p.delta_chi2 > options.told_apart_chi2);
  // In the report's JSON.
  const nlohmann::json j = solver::FitTrustJson(trust);
  ASSERT_EQ(j[0]["profile"].size(), 1u);
  EXPECT_DOUBLE_EQ(j[0]["profile"][0]["delta_chi2"].get<double>(), p.delta_chi2);

  const solver::FitResult moved = WithHipMoved(fit.result, 0.010);
  solver::FitTrust off;
  ASSERT_TRUE(solver::CheckFitTrust(fit.session.nominal, moved, fit.trials, options, &off).ok());
  ASSERT_EQ(Joint(off, "hip_r").profile.size(), 1u);
  std::printf("hip_r moved 10 mm: the free solve moved it %.2f mm\n", Joint(off, "hip_r").profile[0].free_centre_moved_mm);
  EXPECT_GT(Joint(off, "hip_r").profile[0].free_centre_moved_mm, 5.0);

  options.profile_far_centres = false;
  ASSERT_TRUE(solver::CheckFitTrust(fit.session.nominal, fit.result, fit.trials, options, &trust).ok());
  EXPECT_TRUE(Joint(trust, "hip_r").profile.empty());
}

// A fit that ended in a worse minimum is released from the functional estimate and the better
// minimum adopted (fit_trust.h, CheckFitTrustAndAdopt). The worse minimum is made here by the
// re-solves' own priors, which are centred where each solve starts: centres and markers pinned
// there (sigma 10 um), the fit handed in with its hip moved 10 mm stays there solved free, while
// held at SCoRE, and released from there, it fits far better. (A real one: biobuddy's left
// ankle, test_real_fit.)
TEST(FitTrust, AWorseMinimumIsReleasedFromTheFunctionalEstimateAndAdopted) {
  const SimulatedFit& fit = Fit();
  solver::FitTrustOptions options;
  options.joints = {"hip_r"};
  options.far_mm = 1.0;
  options.fit.prior_sigma_position_m = 1e-5;
  options.adopt_better_minimum = true;  // off by default (fit_trust.h)
  solver::FitResult result = WithHipMoved(fit.result, 0.010);
  const solver::FitReport before = result.report;
  solver::FitTrust trust;
  ASSERT_TRUE(solver::CheckFitTrustAndAdopt(fit.session.nominal, fit.trials, options, &result, &trust).ok());
  const solver::JointTrust& hip = Joint(trust, "hip_r");
  ASSERT_GE(hip.profile.size(), 1u);
  const solver::ProfileCheck& p = hip.profile[0];
  std::printf("hip_r moved 10 mm, pinned: held at SCoRE chi-square %+.1f, released %+.1f (%d iterations), adopted %d; "
              "now %.2f mm from SCoRE\n",
              p.delta_chi2, p.released_delta_chi2, p.iterations_released, p.adopted,
              hip.checks[hip.best_check].centre_distance_mm);
  EXPECT_TRUE(p.held_fits_better);
  EXPECT_TRUE(p.released);
  EXPECT_TRUE(p.adopted);
  EXPECT_LT(p.released_delta_chi2, -options.told_apart_chi2);
  EXPECT_EQ(trust.adopted_joint, "hip_r");
  EXPECT_DOUBLE_EQ(trust.adopted_delta_chi2, p.released_delta_chi2);
  EXPECT_FALSE(trust.better_minimum.has_value());
  // The fit is the adopted one: its hip back where the first fit had it, and the checks made on it.
  const int j = fit.result.model.FindJoint("hip_r");
  const Eigen::VectorXd p0 = fit.result.model.InitialParameters(), p1 = result.model.InitialParameters();
  EXPECT_LT(1000.0 * (p1.segment<3>(fit.result.model.centre_index(j)) - p0.segment<3>(fit.result.model.centre_index(j)))
                         .norm() * p0[fit.result.model.scale_index(fit.result.model.joints()[j].parent)],
            1.0);
  EXPECT_LT(hip.checks[hip.best_check].centre_distance_mm, 2.0);
  // The report keeps the schedule's account and adds the two solves.
  const solver::FitReport& r = result.report;
  ASSERT_EQ(r.stages.size(), before.stages.size() + 2);
  EXPECT_FALSE(r.stages[before.stages.size() - 1].better_minimum_search);
  EXPECT_TRUE(r.stages.end()[-2].better_minimum_search);
  EXPECT_TRUE(r.stages.end()[-1].better_minimum_search);
  EXPECT_EQ(r.stages.end()[-1].iterations, p.iterations_released);
  EXPECT_EQ(r.IterationsSearchingBetterMinimum(), r.stages.end()[-2].iterations + r.stages.end()[-1].iterations);
  EXPECT_EQ(r.solver.num_iterations(), before.solver.num_iterations() + r.IterationsSearchingBetterMinimum());
  EXPECT_LT(r.marker_rms_mm, p.marker_rms_free_mm);  // (before.marker_rms_mm is the unmoved fit's)
  for (const solver::ParameterEstimate& e : r.parameters)
    for (const solver::ParameterEstimate& b : before.parameters)
      if (b.name == e.name) EXPECT_EQ(e.initial, b.initial) << e.name;
  const nlohmann::json json = solver::FitTrustJson(trust);
  EXPECT_TRUE(json[0]["profile"][0]["adopted"].get<bool>());

  // Off (the default): the worse minimum is reported, the fit kept.
  options.adopt_better_minimum = false;
  solver::FitResult kept = WithHipMoved(fit.result, 0.010);
  ASSERT_TRUE(solver::CheckFitTrustAndAdopt(fit.session.nominal, fit.trials, options, &kept, &trust).ok());
  EXPECT_TRUE(trust.adopted_joint.empty());
  ASSERT_EQ(Joint(trust, "hip_r").profile.size(), 1u);
  EXPECT_TRUE(Joint(trust, "hip_r").profile[0].held_fits_better);
  EXPECT_FALSE(Joint(trust, "hip_r").profile[0].released);
  EXPECT_EQ(kept.report.stages.size(), before.stages.size());
}

// The landmark check (fit_trust.h): the knee's epicondyle markers are found by their geometry,
// the fitted centre lies where the model puts it against their measured midpoint, and a centre
// moved 40 mm is flagged far.
TEST(FitTrust, KneeCentreAgainstItsEpicondyleMarkers) {
  const SimulatedFit& fit = Fit();
  solver::FitTrustOptions options;
  options.joints = {"knee_r", "hip_r"};
  solver::FitTrust trust;
  ASSERT_TRUE(solver::CheckFitTrust(fit.session.nominal, fit.result, fit.trials, options, &trust).ok());
  EXPECT_TRUE(Joint(trust, "hip_r").landmarks.empty());  // no marker pair straddles a hip
  const auto& knee = Joint(trust, "knee_r").landmarks;
  ASSERT_EQ(knee.size(), 1u);
  const std::set<std::string> pair = {knee[0].first, knee[0].second};
  EXPECT_EQ(pair, (std::set<std::string>{"RKNE", "RKNM"}));
  EXPECT_GT(knee[0].frames, 100);
  // The simulated subject wears its markers off the nominal places (up to 10 mm): the fitted
  // centre is where the truth has it against them, but for the centre's component along the
  // knee's axis, which the fit holds at the model's (a hinge's convention the data cannot see;
  // up to 15 mm in the truth, 3.6 mm here).
  const Model& truth = fit.session.truth;
  const Geometry g(truth);
  ModelData d(truth);
  ForwardKinematics(truth, g, truth.DefaultCoordinates(), &d);
  const double true_offset_mm =
      1000.0 * (JointCentre(truth, d, truth.FindJoint("knee_r")) -
                0.5 * (MarkerPosition(truth, g, d, truth.FindMarker("RKNE")) +
                       MarkerPosition(truth, g, d, truth.FindMarker("RKNM"))))
                   .norm();
  std::printf("knee_r: %.2f mm from its epicondyles' midpoint (the truth's offset %.2f mm, the nominal's %.2f mm)\n",
              knee[0].centre_from_midpoint_mm, true_offset_mm, knee[0].generic_from_midpoint_mm);
  EXPECT_NEAR(knee[0].centre_from_midpoint_mm, true_offset_mm, 5.0);
  EXPECT_FALSE(knee[0].far);

  solver::FitResult moved = fit.result;
  const Model& m = fit.result.model;
  const int j = m.FindJoint("knee_r");
  Eigen::VectorXd p = m.InitialParameters();
  p[m.centre_index(j) + 1] += 0.040 / p[m.scale_index(m.joints()[j].parent)];
  ASSERT_TRUE(m.WithParameters(p, &moved.model).ok());
  solver::FitTrust after;
  ASSERT_TRUE(solver::CheckFitTrust(fit.session.nominal, moved, fit.trials, options, &after).ok());
  const auto& off = Joint(after, "knee_r").landmarks;
  ASSERT_EQ(off.size(), 1u);
  EXPECT_GT(off[0].centre_from_midpoint_mm, 40.0 - knee[0].centre_from_midpoint_mm - 0.5);
  EXPECT_TRUE(off[0].far);
}

// The hips against Harrington's regression from the pelvis markers (fit_trust.h): found by their
// names (RASI, LASI, RPSI, LPSI), the fitted right hip where the truth has it against the prediction
// from the measured markers, the generic model's own offset beside it; a hip moved 25 mm sideways
// is flagged far; the knees and the lumbar joint have none.
TEST(FitTrust, HipsAgainstTheRegressionFromThePelvisMarkers) {
  const SimulatedFit& fit = Fit();
  solver::FitTrustOptions options;
  options.joints = {"hip_r", "hip_l", "knee_r"};
  solver::FitTrust trust;
  ASSERT_TRUE(solver::CheckFitTrust(fit.session.nominal, fit.result, fit.trials, options, &trust).ok());
  EXPECT_TRUE(Joint(trust, "knee_r").regression.empty());
  // The truth's own offset from the regression, computed here from its markers in its default
  // pose: x anterior, z to the right ASIS, y up (Harrington et al. 2007).
  const Model& truth = fit.session.truth;
  const Geometry g(truth);
  ModelData d(truth);
  ForwardKinematics(truth, g, truth.DefaultCoordinates(), &d);
  auto at = [&](const char* name) { return MarkerPosition(truth, g, d, truth.FindMarker(name)); };
  const Eigen::Vector3d ra = at("RASI"), la = at("LASI"), back = 0.5 * (at("RPSI") + at("LPSI"));
  const Eigen::Vector3d origin = 0.5 * (ra + la);
  const Eigen::Vector3d right = (ra - la).normalized();
  const Eigen::Vector3d anterior = ((origin - back) - (origin - back).dot(right) * right).normalized();
  const Eigen::Vector3d up = right.cross(anterior);
  const double pw = (ra - la).norm(), pd = (origin - back).norm();
  for (const char* hip : {"hip_r", "hip_l"}) {
    const auto& r = Joint(trust, hip).regression;
    ASSERT_EQ(r.size(), 1u) << hip;
    const double side = std::string(hip) == "hip_r" ? 1.0 : -1.0;
    const Eigen::Vector3d c = JointCentre(truth, d, truth.FindJoint(hip)) - origin;
    const Eigen::Vector3d predicted(-0.24 * pd - 0.0099, -0.30 * pw - 0.0109, side * (0.33 * pw + 0.0073));
    const double truth_mm = 1000.0 * (Eigen::Vector3d(c.dot(anterior), c.dot(up), c.dot(right)) - predicted).norm();
    std::printf("%s: %.2f mm from Harrington's regression (the truth's %.2f, the generic model's %.2f), PW %.1f mm\n",
                hip, r[0].centre_from_regression_mm, truth_mm, r[0].generic_from_regression_mm, r[0].pelvis_width_mm);
    EXPECT_EQ(r[0].markers, (std::vector<std::string>{"RASI", "LASI", "RPSI", "LPSI"}));
    EXPECT_GT(r[0].frames, 100);
    EXPECT_NEAR(r[0].pelvis_width_mm, 1000.0 * pw, 3.0);  // the markers' noise and placement
    // The right hip's centre is fitted where the truth has it (its trial excites it); the left
    // one, which no trial moves, keeps the nominal model's place: only its figure is reported.
    if (side > 0) EXPECT_NEAR(r[0].centre_from_regression_mm, truth_mm, 3.0);
  }
  solver::FitResult moved = fit.result;
  const Model& m = fit.result.model;
  const int j = m.FindJoint("hip_r");
  Eigen::VectorXd p = m.InitialParameters();
  // 25 mm along the pelvis's lateral axis (the default model's y points left).
  p[m.centre_index(j) + 1] -= 0.025 / p[m.scale_index(m.joints()[j].parent)];
  ASSERT_TRUE(m.WithParameters(p, &moved.model).ok());
  solver::FitTrust after;
  ASSERT_TRUE(solver::CheckFitTrust(fit.session.nominal, moved, fit.trials, options, &after).ok());
  const auto& before_r = Joint(trust, "hip_r").regression[0];
  const auto& after_r = Joint(after, "hip_r").regression[0];
  EXPECT_NEAR(after_r.offset_mm.z() - before_r.offset_mm.z(), 25.0, 1.0);
  EXPECT_TRUE(after_r.far);
  EXPECT_EQ(Joint(after, "hip_l").regression[0].offset_mm, Joint(trust, "hip_l").regression[0].offset_mm);
}

// The landmark names labs use are read as sides of the spines; others are not.
TEST(FitTrust, PelvisLandmarkNamesOfLabMarkerSets) {
  EXPECT_EQ(solver::PelvisLandmarkSide("RASI", "asi"), 'r');
  EXPECT_EQ(solver::PelvisLandmarkSide("r.ASIS", "asi"), 'r');
  EXPECT_EQ(solver::PelvisLandmarkSide("L.ASIS_study", "asi"), 'l');
  EXPECT_EQ(solver::PelvisLandmarkSide("ASIS_left", "asi"), 'l');
  EXPECT_EQ(solver::PelvisLandmarkSide("R_PSIS", "psi"), 'r');
  EXPECT_EQ(solver::PelvisLandmarkSide("LPSI", "psi"), 'l');
  EXPECT_EQ(solver::PelvisLandmarkSide("RASI", "psi"), 0);
  EXPECT_EQ(solver::PelvisLandmarkSide("midASIS", "asi"), 0);
  EXPECT_EQ(solver::PelvisLandmarkSide("RASIS_cluster", "asi"), 0);
  EXPECT_EQ(solver::PelvisLandmarkSide("Rasi2", "asi"), 0);
}

// Every joint by default; a segment with too few markers is a note, not an error.
TEST(FitTrust, EveryJointByDefaultWithReasons) {
  const SimulatedFit& fit = Fit();
  solver::FitTrust trust;
  const Status s = solver::CheckFitTrust(fit.session.nominal, fit.result, fit.trials, {}, &trust);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(static_cast<int>(trust.joints.size()), fit.session.nominal.num_joints() - 1);  // all but the root
  int unestimated = 0;
  for (const auto& j : trust.joints)
    for (const auto& c : j.checks)
      if (!c.estimated) {
        ++unestimated;
        EXPECT_NE(c.note.find("at least 3 on each segment"), std::string::npos) << j.joint << ": " << c.note;
      }
  EXPECT_GT(unestimated, 0);
}

TEST(FitTrust, RefusesWhatDoesNotMatch) {
  const SimulatedFit& fit = Fit();
  solver::FitTrust trust;
  solver::FitTrustOptions options;
  options.joints = {"hip_q"};
  Status s = solver::CheckFitTrust(fit.session.nominal, fit.result, fit.trials, options, &trust);
  EXPECT_FALSE(s.ok());
  EXPECT_NE(s.message().find("no joint 'hip_q'"), std::string::npos) << s.message();
  options.joints = {fit.session.nominal.joints()[0].name};
  s = solver::CheckFitTrust(fit.session.nominal, fit.result, fit.trials, options, &trust);
  EXPECT_FALSE(s.ok());
  EXPECT_NE(s.message().find("to the lab"), std::string::npos) << s.message();
  options.joints = {};
  std::vector<solver::FitTrial> one = {fit.trials[0]};
  s = solver::CheckFitTrust(fit.session.nominal, fit.result, one, options, &trust);
  EXPECT_FALSE(s.ok());
  EXPECT_NE(s.message().find("1 trials but coordinates of 2"), std::string::npos) << s.message();
  solver::FitResult cut = fit.result;
  cut.coordinates[1].conservativeResize(10, Eigen::NoChange);
  s = solver::CheckFitTrust(fit.session.nominal, cut, fit.trials, options, &trust);
  EXPECT_FALSE(s.ok());
  EXPECT_NE(s.message().find("trial 'knee_flexion_r'"), std::string::npos) << s.message();
  options.functional.min_frames = 1;
  s = solver::CheckFitTrust(fit.session.nominal, fit.result, fit.trials, options, &trust);
  EXPECT_FALSE(s.ok());
  EXPECT_NE(s.message().find("min_frames"), std::string::npos) << s.message();
}

// welk007, one `mocap fit` of the generic model to the static and the hip functional trial: the
// report's joint checks hold hip_r against SCoRE on the functional trial and say the static
// trial does not excite it. 10 iterations keep the test short (its first IK alone takes most of
// its time); the figures are printed, the fit's accuracy on this subject is issue 14's business
// (measured: 18 mm from SCoRE after 10 iterations, 48 mm after 50, NO_CONVERGENCE).
TEST(FitTrust, RealHipTrialInTheFitReport) {
  SKIP_WITHOUT_SHARED_DATA();
  const std::string dir = testutil::SharedData() + "/welk007_hipfunc/";
  const std::string report = testutil::TmpPath("fit_trust", ".report.json");
  const std::string fitted = testutil::TmpPath("fit_trust", ".fitted.osim");
  const testutil::CommandResult r =
      testutil::Mocap("fit --model " + dir + "unscaled_generic.osim " + dir + "c3d_Trimmed_static1.c3d " + dir +
                      "c3d_Trimmed_RHJC1.c3d --out " + fitted + " --report " + report +
                      " --threads 2 --max-iterations 10");
  ASSERT_EQ(r.status, 0) << r.output;
  EXPECT_NE(r.output.find("hip_r: fitted centre"), std::string::npos) << r.output;
  const nlohmann::json j = nlohmann::json::parse(testutil::ReadBytes(report), nullptr, false);
  ASSERT_TRUE(j.contains("joint_checks")) << "no joint_checks in " << report;
  const nlohmann::json* hip = nullptr;
  for (const auto& jc : j["joint_checks"])
    if (jc["joint"] == "hip_r") hip = &jc;
  ASSERT_NE(hip, nullptr);
  ASSERT_EQ((*hip)["trials"].size(), 2u);
  const auto& fstatic = (*hip)["trials"][0];
  const auto& func = (*hip)["trials"][1];
  EXPECT_EQ(fstatic["trial"], "c3d_Trimmed_static1");
  EXPECT_FALSE(fstatic["excited"].get<bool>());
  EXPECT_FALSE(fstatic["note"].get<std::string>().empty());
  ASSERT_TRUE(func["excited"].get<bool>()) << func.dump();
  EXPECT_EQ((*hip)["best_trial"], "c3d_Trimmed_RHJC1");
  EXPECT_GT(func["frames"].get<int>(), 1000);
  const double distance = func["centre_distance_mm"], sd = func["functional_std_mm"];
  std::printf("welk007 hip_r: %.1f mm from SCoRE (SCoRE sd %.2f mm, spread %.1f mm), %.1f mm from the "
              "generic model (fit sd %.2f mm); marker RMS %.2f mm\n",
              distance, sd, func["centre_spread_mm"].get<double>(), (*hip)["from_generic_mm"].get<double>(),
              (*hip)["fitted_std_mm"].get<double>(), j["marker_rms_mm"].get<double>());
  EXPECT_GT(sd, 0.1);
  EXPECT_LT(sd, 10.0);
  EXPECT_TRUE(std::isfinite(distance));
}

}  // namespace
