#include "solver/fit_report_json.h"

#include <cmath>

namespace mocap::solver {

nlohmann::json FitReportJson(const FitReport& r, const std::vector<FitTrial>& trials,
                             const std::vector<std::string>& trial_sources) {
  nlohmann::json j;
  j["frames"] = r.frames;
  j["trials"] = r.trials;
  j["markers"] = r.markers;
  j["marker_samples"] = r.marker_samples;
  j["unknowns"] = r.unknowns;
  j["residuals"] = r.residuals;
  j["iterations"] = r.solver.num_iterations();  // every stage's (FitReport::stages)
  j["iterations_every_frame"] = r.IterationsOnEveryFrame();
  // Of those, the search for a better minimum after the schedule (solver/fit_trust.h).
  j["iterations_better_minimum"] = r.IterationsSearchingBetterMinimum();
  // The solve's history (the report page's convergence plot): cost and marker RMS (without the
  // priors; null where the solver did not measure it) after each iteration.
  j["iteration_history"] = nlohmann::json::array();
  for (const IterationSummary& it : r.solver.iterations)
    j["iteration_history"].push_back(
        {{"iteration", it.iteration}, {"cost", it.cost},
         {"marker_rms_mm", std::isfinite(it.data_rms) ? nlohmann::json(it.data_rms) : nlohmann::json()},
         {"accepted", it.step_accepted}, {"lambda", it.lambda}, {"seconds", it.total_seconds}});
  // The coarse-to-fine start (solver/coarse_to_fine.h): its subset, iterations and pose pass.
  j["coarse"] = {{"used", r.coarse.used},
                 {"fallback", r.coarse.fallback},
                 {"frames", r.coarse.coarse_frames},
                 {"iterations", r.coarse.coarse.num_iterations()},
                 {"seconds", r.coarse.coarse.total_seconds},
                 {"pose_seconds", r.coarse.pose_seconds},
                 {"start_cost", r.coarse.fine_start_cost}};
  // The schedule's stages (solver/global_fit.h, FitModel).
  j["stages"] = nlohmann::json::array();
  for (const FitStageSummary& st : r.stages)
    j["stages"].push_back({{"name", st.name},
                           {"groups", st.groups},
                           {"iterations", st.iterations},
                           {"termination", ToString(st.termination)},
                           {"initial_marker_rms_mm", st.initial_marker_rms_mm},
                           {"marker_rms_mm", st.marker_rms_mm},
                           {"marker_sigma_mm", st.marker_sigma_mm},
                           {"residual_correlation_frames", st.residual_correlation_frames},
                           {"frames", st.frames},
                           {"better_minimum_search", st.better_minimum_search},
                           {"seconds", st.seconds}});
  j["held_joints"] = nlohmann::json::object();
  for (const auto& [joint, why] : r.held_joints) j["held_joints"][joint] = why;
  j["attached_markers"] = nlohmann::json::array();
  for (const AttachedMarker& a : r.attached_markers)
    j["attached_markers"].push_back({{"name", a.name},
                                     {"segment", a.segment},
                                     {"spread_mm", a.spread_mm},
                                     {"runner_up_mm", a.runner_up_mm},
                                     {"samples", a.samples},
                                     {"why_not", a.why_not}});
  j["placed_markers"] = nlohmann::json::array();
  for (const PlacedMarker& p : r.placed_markers)
    j["placed_markers"].push_back({{"name", p.name},
                                   {"segment", p.segment},
                                   {"from_model_mm", p.from_model_mm},
                                   {"spread_mm", p.spread_mm},
                                   {"samples", p.samples},
                                   {"why_not", p.why_not}});
  j["residual_sigma_mm"] = r.residual_sigma_mm;
  j["residual_correlation_frames"] = r.residual_correlation_frames;
  j["reposed"] = r.reposed;
  j["rescued_frames"] = r.rescued_frames;
  j["static_trials"] = r.static_trials;
  j["far_moved_markers"] = nlohmann::json::array();
  for (const auto& f : r.far_moved_markers)
    j["far_moved_markers"].push_back({{"marker", f.name}, {"segment", f.segment}, {"distance_mm", f.distance_mm}});
  j["scaling_marker_weights"] = nlohmann::json::object();
  for (const auto& [name, w] : r.scaling_marker_weights) j["scaling_marker_weights"][name] = w;
  j["initial_cost"] = r.solver.initial_cost;
  j["final_cost"] = r.solver.final_cost;
  j["initial_marker_rms_mm"] = r.initial_marker_rms_mm;
  j["marker_rms_mm"] = r.marker_rms_mm;
  j["fitted_marker_rms_mm"] = r.fitted_marker_rms_mm;
  j["per_trial"] = nlohmann::json::array();
  for (size_t t = 0; t < trials.size(); ++t) {
    nlohmann::json tj = {{"name", trials[t].markers.name},
                         {"frames", trials[t].markers.num_frames()},
                         {"rate_hz", trials[t].markers.rate_hz}};
    if (t < trial_sources.size()) tj["file"] = trial_sources[t];
    if (t < r.per_trial_rms_mm.size()) tj["marker_rms_mm"] = r.per_trial_rms_mm[t];
    if (t < r.per_trial_samples.size()) tj["marker_samples"] = r.per_trial_samples[t];
    if (t < r.per_frame_rms_mm.size()) {  // null for a frame without marker samples
      nlohmann::json frames = nlohmann::json::array();
      for (double v : r.per_frame_rms_mm[t])
        frames.push_back(std::isfinite(v) ? nlohmann::json(v) : nlohmann::json());
      tj["per_frame_rms_mm"] = std::move(frames);
    }
    j["per_trial"].push_back(tj);
  }
  j["per_marker_rms_mm"] = nlohmann::json::object();
  for (const auto& [name, v] : r.per_marker_rms_mm) j["per_marker_rms_mm"][name] = v;
  // FitOptions::marker_sigma_rounds: the rounds run and each marker's sigma in the final solve.
  j["marker_sigma_rounds"] = r.marker_sigma_rounds;
  j["marker_sigma_mm"] = nlohmann::json::object();
  for (const auto& [name, v] : r.marker_sigma_mm) j["marker_sigma_mm"][name] = v;
  // FitOptions::robust_loss: which loss, and how many samples of which markers it down-weighted.
  nlohmann::json robust = {{"loss", ToString(r.robust_loss)}};
  if (r.robust_loss != RobustLoss::kNone) {
    robust["scale_sigmas"] = r.robust_scale;
    robust["sigma_mm"] = r.robust_sigma_mm;
    robust["rounds"] = r.robust_rounds;
    robust["downweighted_samples"] = r.robust_downweighted;
    robust["per_marker"] = nlohmann::json::object();
    for (const FitReport::RobustMarker& m : r.robust_markers)
      robust["per_marker"][m.name] = {{"samples", m.samples},
                                      {"downweighted", m.downweighted},
                                      {"mean_weight", m.mean_weight}};
  }
  j["robust_loss"] = std::move(robust);
  j["wall_seconds"] = r.wall_seconds;
  j["ik_seconds"] = r.ik_seconds;
  j["solve_seconds"] = r.solve_seconds;
  j["converged"] = r.converged();
  j["termination"] = ToString(r.solver.termination);
  j["termination_message"] = r.solver.message;
  j["undetermined"] = r.undetermined;
  j["median_marker_rms_mm"] = r.median_marker_rms_mm;
  j["outlier_markers"] = nlohmann::json::object();
  for (const auto& [name, rms] : r.outlier_markers) j["outlier_markers"][name] = rms;
  j["marker_diagnoses"] = nlohmann::json::array();
  for (const MarkerDiagnosis& d : r.marker_diagnoses) {
    nlohmann::json e = {{"marker", d.marker},       {"rms_mm", d.rms_mm},
                        {"kind", ToString(d.kind)}, {"segment", d.segment},
                        {"rides_on", d.rides_on},   {"spread_on_segment_mm", d.spread_on_segment_mm},
                        {"spread_on_best_mm", d.spread_on_best_mm}, {"text", d.text}};
    if (!d.other_marker.empty()) e["other_marker"] = d.other_marker;
    if (d.kind == MarkerDiagnosis::Kind::kStretch) {
      e["trial"] = d.trial;
      e["first_frame"] = d.first_frame;
      e["last_frame"] = d.last_frame;
      e["stretch_rms_mm"] = d.stretch_rms_mm;
      e["elsewhere_rms_mm"] = d.elsewhere_rms_mm;
    }
    j["marker_diagnoses"].push_back(e);
  }
  j["unmatched_trial_markers"] = r.unmatched_trial_markers;
  j["unobserved_model_markers"] = r.unobserved_model_markers;
  j["parameters"] = nlohmann::json::array();
  for (const auto& e : r.parameters)
    j["parameters"].push_back({{"name", e.name}, {"group", ToString(e.group)}, {"initial", e.initial},
                               {"value", e.value}, {"std", e.std}, {"determined", e.determined}});
  return j;
}

nlohmann::json FitTrustJson(const FitTrust& trust) {
  nlohmann::json joints = nlohmann::json::array();
  for (const JointTrust& jt : trust.joints) {
    nlohmann::json checks = nlohmann::json::array();
    for (const FunctionalCheck& c : jt.checks) {
      nlohmann::json cj = {{"trial", c.trial}, {"estimated", c.estimated}, {"excited", c.excited},
                           {"note", c.note}, {"frames", c.frames}};
      if (c.excited) {
        cj["far"] = c.far;
        if (jt.axis_joint) {
          cj["axis_angle_deg"] = c.axis_angle_deg;
          cj["axis_spread_deg"] = c.axis_spread_deg;
          cj["functional_axis_std_deg"] = c.functional_axis_std_deg;
          cj["axis_line_distance_mm"] = c.axis_line_distance_mm;
        } else {
          cj["centre_distance_mm"] = c.centre_distance_mm;
          cj["centre_spread_mm"] = c.centre_spread_mm;
          cj["functional_std_mm"] = c.functional_std_mm;
        }
      }
      checks.push_back(std::move(cj));
    }
    nlohmann::json landmarks = nlohmann::json::array();
    for (const LandmarkCheck& l : jt.landmarks)
      landmarks.push_back({{"markers", {l.first, l.second}},
                           {"trial", l.trial},
                           {"frames", l.frames},
                           {"centre_from_midpoint_mm", l.centre_from_midpoint_mm},
                           {"generic_from_midpoint_mm", l.generic_from_midpoint_mm},
                           {"far", l.far}});
    nlohmann::json regression = nlohmann::json::array();
    for (const RegressionCheck& r : jt.regression)
      regression.push_back({{"method", r.method},
                            {"markers", r.markers},
                            {"trial", r.trial},
                            {"frames", r.frames},
                            {"pelvis_width_mm", r.pelvis_width_mm},
                            {"pelvis_depth_mm", r.pelvis_depth_mm},
                            {"offset_mm", {r.offset_mm.x(), r.offset_mm.y(), r.offset_mm.z()}},
                            {"centre_from_regression_mm", r.centre_from_regression_mm},
                            {"generic_from_regression_mm", r.generic_from_regression_mm},
                            {"far", r.far}});
    nlohmann::json profile = nlohmann::json::array();
    for (const ProfileCheck& pc : jt.profile)
      profile.push_back({{"trial", pc.trial},
                         {"centre_distance_mm", pc.centre_distance_mm},
                         {"axis_angle_deg", pc.axis_angle_deg},
                         {"delta_chi2", pc.delta_chi2},
                         {"free_centre_moved_mm", pc.free_centre_moved_mm},
                         {"marker_rms_free_mm", pc.marker_rms_free_mm},
                         {"marker_rms_held_mm", pc.marker_rms_held_mm},
                         {"iterations_free", pc.iterations_free},
                         {"iterations_held", pc.iterations_held},
                         {"told_apart", pc.told_apart},
                         {"held_fits_better", pc.held_fits_better},
                         {"released", pc.released},
                         {"released_delta_chi2", pc.released_delta_chi2},
                         {"iterations_released", pc.iterations_released},
                         {"adopted", pc.adopted},
                         {"note", pc.note}});
    joints.push_back({{"joint", jt.joint},
                      {"type", ToString(jt.type)},
                      {"axis_joint", jt.axis_joint},
                      {"from_generic_mm", jt.from_generic_mm},
                      {"axis_from_generic_deg", jt.axis_from_generic_deg},
                      {"fitted_std_mm", jt.centre_fitted ? nlohmann::json(jt.fitted_std_mm) : nlohmann::json()},
                      {"undetermined", jt.undetermined},
                      {"best_trial", jt.best_check >= 0 ? nlohmann::json(jt.checks[jt.best_check].trial)
                                                        : nlohmann::json()},
                      {"second_trial", jt.second_check >= 0 ? nlohmann::json(jt.checks[jt.second_check].trial)
                                                            : nlohmann::json()},
                      {jt.axis_joint ? "functional_between_trials_deg" : "functional_between_trials_mm",
                       jt.second_check >= 0 ? nlohmann::json(jt.functional_between_trials) : nlohmann::json()},
                      {"trials", std::move(checks)},
                      {"landmarks", std::move(landmarks)},
                      {"regression", std::move(regression)},
                      {"profile", std::move(profile)}});
  }
  return joints;
}

}  // namespace mocap::solver
