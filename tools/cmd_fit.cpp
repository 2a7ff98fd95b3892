// mocap fit: the global body-model fit of a model to labelled marker trials.
#include <spdlog/spdlog.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <csignal>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <map>
#include <sstream>
#include <nlohmann/json.hpp>

#include "formats/mot.h"
#include "formats/osim.h"
#include "formats/text_util.h"
#include "formats/trc.h"
#include "model/kinematics.h"
#include "model/model_io.h"
#include "report/fit_report_html.h"
#include "sim/protocol.h"
#include "solver/fit_report_json.h"
#include "solver/fit_trust.h"
#include "solver/functional_joints.h"
#include "solver/global_fit.h"
#include "tools/command.h"
#include "tools/trial_inputs.h"

namespace mocap::tools {
namespace {

namespace fs = std::filesystem;
std::atomic<bool> g_interrupted{false};

struct FitArgs {
  InputArgs in;
  std::string out;
  std::string report;
  std::string html;
  std::string protocol;  // for --html: the protocol whose coverage the page shows ("default" or a file)
  int threads = 0;
  std::string groups = "scales,centres,axes,markers";
  int max_iterations = 150;  // over every stage of the schedule
  int coarse_frames = solver::CoarseToFineOptions().coarse_frames;  // 0: no coarse-to-fine start
  int stage_frames = solver::FitOptions().stage_frames;
  int marker_sigma_rounds = solver::FitOptions().marker_sigma_rounds;  // 0: one sigma for all
  int scaling_marker_rounds = solver::FitOptions().scaling_marker_rounds;
  bool coordinate_limits = true;
  double fixed_marker_sigma_mm = 1000.0 * solver::FitOptions().prior_sigma_fixed_marker_m;
  bool place_stacked_markers = solver::FitOptions().place_stacked_markers;
  std::vector<std::string> initial;  // one .mot per trial: starting poses instead of IK
  std::string functional;  // joints (comma-separated) whose SCoRE centres join the fit as data
  double functional_sigma_mm = 5.0;
  bool single_stage = false;  // no automatic schedule (solver::FitOptions::staged)
  bool adopt_better_minimum = false;  // solver::FitTrustOptions::adopt_better_minimum
  std::string robust_loss = solver::ToString(solver::FitOptions().robust_loss);
  double robust_scale = solver::FitOptions().robust_scale;
};

formats::MarkerTrial JointCentreTrial(const Model& model, const formats::MarkerTrial& trial,
                                      const Eigen::MatrixXd& z) {
  formats::MarkerTrial out;
  out.name = trial.name + "_joint_centres";
  out.rate_hz = trial.rate_hz;
  out.frame_numbers = trial.frame_numbers;
  out.times = trial.times;
  for (const auto& j : model.joints()) out.marker_names.push_back(j.name);
  out.positions.resize(z.rows(), 3 * model.num_joints());
  Geometry g(model);
  ModelData d(model);
  for (int f = 0; f < z.rows(); ++f) {
    ForwardKinematics(model, g, z.row(f).transpose(), &d);
    for (int j = 0; j < model.num_joints(); ++j)
      out.positions.row(f).segment<3>(3 * j) = JointCentre(model, d, j).transpose();
  }
  return out;
}

void LogJointChecks(const solver::FitTrust& trust) {
  std::string never_excited, no_clusters;
  for (const solver::JointTrust& j : trust.joints)
    for (const solver::LandmarkCheck& l : j.landmarks)
      spdlog::log(l.far ? spdlog::level::warn : spdlog::level::info,
                  "{}: fitted centre {:.1f} mm from the midpoint of {} and {} on {} (the generic model's: {:.1f} mm){}",
                  j.joint, l.centre_from_midpoint_mm, l.first, l.second, l.trial, l.generic_from_midpoint_mm,
                  l.far ? ": the skeleton is off its landmarks there, more than the generic model puts it" : "");
  for (const solver::JointTrust& j : trust.joints)
    for (const solver::RegressionCheck& r : j.regression)
      spdlog::log(r.far ? spdlog::level::warn : spdlog::level::info,
                  "{}: fitted centre {:.1f} mm from {}'s regression on {} (pelvis width {:.0f} mm, depth {:.0f} mm; "
                  "the generic model's: {:.1f} mm){}",
                  j.joint, r.centre_from_regression_mm, r.method, r.trial, r.pelvis_width_mm, r.pelvis_depth_mm,
                  r.generic_from_regression_mm,
                  r.far ? ": further than the regression's own error; see the functional check" : "");
  for (const solver::JointTrust& j : trust.joints) {
    const std::string generic = fmt::format("{:.1f} mm from the generic model's{}", j.from_generic_mm,
                                            j.centre_fitted ? fmt::format(" (fit sd {:.1f} mm)", j.fitted_std_mm)
                                                            : std::string(" (not fitted)"));
    if (j.best_check < 0) {
      bool estimated = false;
      for (const auto& c : j.checks) estimated |= c.estimated;
      (estimated ? never_excited : no_clusters) += (estimated ? never_excited : no_clusters).empty() ? j.joint : ", " + j.joint;
      continue;
    }
    const solver::FunctionalCheck& c = j.checks[j.best_check];
    if (j.second_check >= 0)
      spdlog::info("{}: its functional {} on {} is {:.1f} {} from the one on {}: a reference is worth no more than "
                   "that, whatever its sd",
                   j.joint, j.axis_joint ? "axis" : "centre", j.checks[j.second_check].trial,
                   j.functional_between_trials, j.axis_joint ? "deg" : "mm", c.trial);
    if (j.axis_joint)
      spdlog::log(c.far ? spdlog::level::warn : spdlog::level::info,
                  "{}: fitted axis {:.1f} deg from its functional (SARA) axis on {} (spread {:.1f} deg, SARA sd "
                  "{:.2f} deg), fitted centre {:.1f} mm from that axis; centre {}",
                  j.joint, c.axis_angle_deg, c.trial, c.axis_spread_deg, c.functional_axis_std_deg,
                  c.axis_line_distance_mm, generic);
    else
      spdlog::log(c.far ? spdlog::level::warn : spdlog::level::info,
                  "{}: fitted centre {:.1f} mm from its functional (SCoRE) centre on {} (spread {:.1f} mm, SCoRE "
                  "sd {:.2f} mm), {}",
                  j.joint, c.centre_distance_mm, c.trial, c.centre_spread_mm, c.functional_std_mm, generic);
  }
  for (const solver::JointTrust& j : trust.joints)
    for (const solver::ProfileCheck& p : j.profile)
      if (!p.note.empty())
        spdlog::warn("{}: not held at its functional estimate on {}: {}", j.joint, p.trial, p.note);
      else
        spdlog::log(p.told_apart ? spdlog::level::info : spdlog::level::warn,
                  "{}: held at its functional {} on {} ({}) the fit's chi-square changes by {:+.1f} "
                  "(marker RMS {:.3f} -> {:.3f} mm): {}{}",
                  j.joint, j.axis_joint ? "axis (SARA)" : "centre (SCoRE)", p.trial,
                  j.axis_joint ? fmt::format("{:.1f} deg away", p.axis_angle_deg)
                               : fmt::format("{:.1f} mm away", p.centre_distance_mm),
                  p.delta_chi2, p.marker_rms_free_mm, p.marker_rms_held_mm,
                  p.free_centre_moved_mm > 1.0
                      ? fmt::format("solved again free from the fit (its priors then centred on the fit's "
                                    "values), the centre moved {:.1f} mm; ",
                                    p.free_centre_moved_mm)
                      : std::string(),
                  p.told_apart         ? "the data tell the two apart and side with the fit's"
                  : p.held_fits_better ? "the functional estimate fits the data better: the fit ended in a worse "
                                         "minimum than the one there; check the joint's markers and trials"
                                       : "the data cannot tell the two apart (within the chi-square's 95 % "
                                         "quantile): another reference must choose");
  for (const solver::JointTrust& j : trust.joints)
    for (const solver::ProfileCheck& p : j.profile)
      if (p.released)
        spdlog::log(p.adopted ? spdlog::level::warn : spdlog::level::info,
                    "{}: released from its functional estimate on {}, the fit ends {:+.1f} in chi-square from its "
                    "first minimum ({} iterations): {}",
                    j.joint, p.trial, p.released_delta_chi2, p.iterations_released,
                    p.adopted ? "a better minimum, ADOPTED: the fitted model and poses are that fit's, the checks "
                                "above made on it"
                              : "not adopted");
  if (!trust.adopted_joint.empty())
    spdlog::warn("the fit's first minimum was not the best one: the fit released from {}'s functional estimate "
                 "ended {:.1f} lower in chi-square and is the result (the report's last two stages)",
                 trust.adopted_joint, -trust.adopted_delta_chi2);
  if (!never_excited.empty())
    spdlog::info("joints no trial excites (no functional reference): {}", never_excited);
  if (!no_clusters.empty())
    spdlog::info("joints without 3 markers on each segment in any trial (no functional reference): {}",
                 no_clusters);
}

int RunFit(const FitArgs& args) {
  const bool osim_out = HasExtension(args.out, ".osim");
  if (!osim_out && !HasExtension(args.out, ".json")) {
    spdlog::error("--out {}: expected a .json or .osim model file", args.out);
    return 2;
  }
  if (osim_out && !HasExtension(args.in.model_path, ".osim")) {
    spdlog::error("--out {}: an .osim is written from an OpenSim model; {} is not one (write .json)",
                  args.out, args.in.model_path);
    return 2;
  }
  Inputs inputs;
  if (!LoadInputs(args.in, &inputs)) return 1;
  const int model_markers = inputs.model.model.num_markers();
  // The generic model as given: its markers make the clusters of the joint checks (without the
  // virtual markers --functional adds), and the report compares the fitted centres with its.
  const Model generic = inputs.model.model;
  // Markers the model puts on a joint centre (OpenCap's RHJC_study): points of the centre, not
  // skin markers (solver/attach_markers.h); back on their own segments before the model is written.
  std::vector<solver::CentreMarker> centre_markers;
  if (Status s = solver::TieCentreMarkers(inputs.trials, 0.002, &inputs.model.model, &centre_markers); !s) {
    spdlog::error("{}", s.message());
    return 1;
  }
  for (const solver::CentreMarker& c : centre_markers)
    spdlog::info("{}: the model puts it on {}'s centre ({:.1f} mm away): read as another tool's estimate of that "
                 "centre, fitted as a point of the centre, not as a skin marker",
                 c.marker, c.joint, c.from_centre_mm);
  std::vector<std::string> virtual_markers;
  if (!args.functional.empty()) {
    std::vector<std::string> joints, notes;
    std::stringstream list(args.functional);
    for (std::string j; std::getline(list, j, ',');)
      if (!j.empty()) joints.push_back(j);
    const double weight = std::pow(1.0 / args.functional_sigma_mm, 2);  // marker sigma is 1 mm
    if (Status s = solver::AddFunctionalCentres(joints, solver::FunctionalJointOptions(),
                                                weight, &inputs.model.model, &inputs.trials,
                                                &virtual_markers, &notes);
        !s) {
      spdlog::error("--functional: {}", s.message());
      return 2;
    }
    for (const std::string& n : notes) spdlog::info("--functional: {}", n);
  }
  const Model& model = inputs.model.model;
  solver::FitOptions options;
  options.fixed_markers = virtual_markers;
  for (const solver::CentreMarker& c : centre_markers) options.fixed_markers.push_back(c.marker);  // before --functional's
  if (Status s = options.SetGroups(args.groups); !s) {
    spdlog::error("--fit: {}", s.message());
    return 2;
  }
  options.num_threads = args.threads;
  options.staged = !args.single_stage;
  options.lm.max_iterations = args.max_iterations;
  options.marker_sigma_rounds = args.marker_sigma_rounds;
  options.scaling_marker_rounds = args.scaling_marker_rounds;
  if (!args.coordinate_limits) {
    options.coordinate_limit_sigma_rad = options.coordinate_limit_sigma_m = 0;
    options.ik.coordinate_limit_stiffness = 0;
  }
  options.place_stacked_markers = args.place_stacked_markers;
  options.prior_sigma_fixed_marker_m = args.fixed_marker_sigma_mm / 1000.0;
  if (Status s = solver::ParseRobustLoss(args.robust_loss, &options.robust_loss); !s) {
    spdlog::error("--robust-loss: {}", s.message());
    return 2;
  }
  options.robust_scale = args.robust_scale;
  options.stage_frames = args.stage_frames;
  options.coarse.enabled = args.coarse_frames > 0;
  if (args.coarse_frames > 0) {
    options.coarse.coarse_frames = args.coarse_frames;
    options.coarse.min_frames = std::max(options.coarse.min_frames, 2 * args.coarse_frames);
  }
  std::vector<solver::FitTrial> trials;
  for (auto& t : inputs.trials) trials.push_back({std::move(t), {}});
  if (!args.initial.empty()) {
    if (args.initial.size() != trials.size()) {
      spdlog::error("--initial: {} .mot file(s) for {} trial(s): give one per trial, in the same order",
                    args.initial.size(), trials.size());
      return 2;
    }
    for (size_t t = 0; t < trials.size(); ++t) {
      formats::CoordinateTable table;
      if (Status s = formats::ReadMot(args.initial[t], &table); !s) {
        spdlog::error("--initial: {}", s.message());
        return 2;
      }
      if (Status s = solver::InitialCoordinatesFromTable(model, table, trials[t].markers.num_frames(),
                                                         args.initial[t] + " (for " + args.in.trials[t] + ")",
                                                         &trials[t].initial_coordinates);
          !s) {
        spdlog::error("--initial: {}", s.message());
        return 2;
      }
      int missing = 0;
      for (int f = 0; f < trials[t].initial_coordinates.rows(); ++f)
        missing += trials[t].initial_coordinates.row(f).array().isNaN().all() ? 1 : 0;
      if (missing == trials[t].initial_coordinates.rows()) {
        spdlog::error("--initial: {}: no frame has a pose (all NaN)", args.initial[t]);
        return 2;
      }
      spdlog::info("{}: starting poses from {}{}", args.in.trials[t], args.initial[t],
                   missing > 0 ? " (" + std::to_string(missing) + " frames without one: by IK)" : "");
    }
  }
  options.lm.callbacks.push_back([](const solver::IterationSummary& it) {
    spdlog::info("{}iteration {:3d}  cost {:.6e}  change {:.3e}  |gradient| {:.3e}  |step| {:.3e}  "
                 "lambda {:.2e}  {:.2f} s",
                 it.coarse ? "coarse " : "", it.iteration, it.cost, it.cost_change, it.gradient_max_norm, it.step_norm, it.lambda,
                 it.total_seconds);
    return !g_interrupted.load();
  });
  std::signal(SIGINT, [](int) { g_interrupted = true; });
  spdlog::info("fitting {} ({} trials); Ctrl-C stops after the current iteration and keeps the result",
               args.in.model_path, trials.size());
  solver::FitResult result;
  Status s = solver::FitModel(model, trials, options, &result);
  std::signal(SIGINT, SIG_DFL);
  if (!s) {
    spdlog::error("{}", s.message());
    return 1;
  }
  for (const solver::AttachedMarker& a : result.report.attached_markers) {
    if (a.why_not.empty())
      spdlog::info("trial marker {} (not in the model) attached to {}: it moves {:.1f} mm RMS in its frame, "
                   "{:.1f} mm in the next best segment's",
                   a.name, a.segment, a.spread_mm, a.runner_up_mm);
    else
      spdlog::warn("trial marker {} (not in the model) left out: {}", a.name, a.why_not);
  }
  {
    // Placeholders of a generic model, one line per segment.
    std::map<std::string, std::string> per_segment;
    for (const solver::PlacedMarker& p : result.report.placed_markers) {
      std::string& line = per_segment[p.segment];
      line += (line.empty() ? "" : ", ") +
              (p.why_not.empty() ? fmt::format("{} {:.0f} mm away (moves {:.1f} mm RMS there)", p.name,
                                               p.from_model_mm, p.spread_mm)
                                 : p.name + ": " + p.why_not);
    }
    for (const auto& [segment, line] : per_segment)
      spdlog::info("{}: the model stacks these markers on one point (placeholders), so they were placed where "
                   "the trials put them: {}",
                   segment, line);
  }
  if (!result.report.scaling_marker_weights.empty()) {
    std::string list;
    for (const auto& [name, w] : result.report.scaling_marker_weights)
      list += (list.empty() ? "" : ", ") + name + fmt::format(" ({:.2f})", w);
    spdlog::info("scaled with these markers down-weighted, the model's place for them being far from the data's: {}",
                 list);
  }
  {  // one warning per segment, its farthest-moved markers first
    std::vector<std::pair<std::string, std::string>> by_segment;
    for (const auto& f : result.report.far_moved_markers) {
      auto it = std::find_if(by_segment.begin(), by_segment.end(), [&](const auto& s) { return s.first == f.segment; });
      if (it == by_segment.end()) it = by_segment.insert(by_segment.end(), {f.segment, ""});
      it->second += (it->second.empty() ? "" : ", ") + f.name + fmt::format(" {:.0f} mm", f.distance_mm);
    }
    for (const auto& [segment, list] : by_segment)
      spdlog::warn("{}: markers moved far from the model's places ({}): more than markers misplaced, its poses are "
                   "likely wrong; check the skeleton against its markers",
                   segment, list);
  }
  for (const std::string& name : result.report.static_trials)
    spdlog::info("trial '{}' is static (its markers hardly move): its frames count as one posture", name);
  for (const auto& [joint, why] : result.report.held_joints)
    spdlog::info("{}: {} held at the model's (the trials do not move it: {})", joint,
                 why.find("axes only") == std::string::npos ? "centre and axes" : "axes", why);
  const solver::FitReport& r = result.report;
  for (const auto& [name, rms] : r.per_marker_rms_mm)
    for (const std::string& v : virtual_markers)
      if (name == v)
        spdlog::info("{}: the fitted centre is {:.1f} mm RMS from its functional (SCoRE) estimate",
                     v.substr(0, v.find('@')), rms);
  if (!virtual_markers.empty()) {
    std::vector<int> keep(model_markers);
    for (int m = 0; m < model_markers; ++m) keep[m] = m;
    Model without;
    if (Status w = result.model.WithMarkers(keep, &without); !w) {
      spdlog::error("{}", w.message());
      return 1;
    }
    result.model = std::move(without);
  }
  // Whether to trust the model (issue 14): each joint against its functional estimate on every
  // trial, and against the generic model; with --adopt-better-minimum, a release from a
  // functional estimate that ends lower becomes the fit (solver/fit_trust.h), so this comes
  // before the lines below, which are then the adopted fit's. Not with --functional: its prior
  // is the lab's choice, and the re-solves run without it (the checks say what they find).
  solver::FitTrust trust;
  solver::FitTrustOptions trust_options;
  trust_options.fit = options;  // the profile checks solve the fit's problem again
  trust_options.adopt_better_minimum = args.adopt_better_minimum && virtual_markers.empty();
  if (Status t = solver::CheckFitTrustAndAdopt(generic, trials, trust_options, &result, &trust); !t) {
    spdlog::error("joint checks: {}", t.message());
    return 1;
  }
  LogJointChecks(trust);
  if (!r.undetermined.empty())
    spdlog::warn("{} parameters not determined by these trials (kept near the initial model): {}{}",
                 r.undetermined.size(), r.undetermined.front(), r.undetermined.size() > 1 ? ", ..." : "");
  for (const auto& [name, rms] : r.outlier_markers) {
    const auto d = std::find_if(r.marker_diagnoses.begin(), r.marker_diagnoses.end(),
                                [&](const solver::MarkerDiagnosis& x) { return x.marker == name; });
    if (d != r.marker_diagnoses.end())
      spdlog::warn("marker {} ({:.1f}x the median marker's {:.1f} mm)", d->text,
                   rms / std::max(1e-9, r.median_marker_rms_mm), r.median_marker_rms_mm);
    else
      spdlog::warn("marker {} fits to {:.1f} mm RMS, {:.1f}x the median marker's {:.1f} mm: mislabelled, "
                   "slipping, or attached to another body than the model's?",
                   name, rms, rms / std::max(1e-9, r.median_marker_rms_mm), r.median_marker_rms_mm);
  }
  if (r.coarse.used || r.coarse.fallback) std::printf("%s\n", r.coarse.BriefReport().c_str());
  std::printf("%s\n%s\n", r.solver.BriefReport().c_str(), r.BriefReport().c_str());

  if (Status u = solver::UntieCentreMarkers(centre_markers, &result.model); !u) {
    spdlog::error("{}", u.message());
    return 1;
  }
  fs::path out(args.out);
  if (out.has_parent_path()) fs::create_directories(out.parent_path());
  if (Status w = osim_out ? formats::ExportOsim(result.model, inputs.model.import, args.out)
                          : SaveModelJson(args.out, result.model);
      !w) {
    spdlog::error("{}", w.message());
    return 1;
  }
  const fs::path dir = out.has_parent_path() ? out.parent_path() : fs::path(".");
  for (size_t t = 0; t < trials.size(); ++t) {
    const auto& trial = trials[t].markers;
    const std::string base = trial.name.empty() ? "trial" + std::to_string(t + 1) : trial.name;
    const fs::path mot = dir / (base + ".fitted.mot");
    const fs::path centres = dir / (base + ".joint_centres.trc");
    Status w = WriteAngles(mot.string(), inputs.model, result.model, trial, result.coordinates[t]);
    if (w) w = formats::WriteTrc(centres.string(), JointCentreTrial(result.model, trial, result.coordinates[t]));
    if (!w) {
      spdlog::error("{}", w.message());
      return 1;
    }
  }
  for (size_t t = 0; t < trials.size(); ++t)
    spdlog::info("{}: marker RMS {:.2f} mm", args.in.trials[t], r.per_trial_rms_mm[t]);
  spdlog::info("wrote {} and, per trial, <trial>.fitted.mot and <trial>.joint_centres.trc in {}",
               args.out, dir.string());

  nlohmann::json report_json = solver::FitReportJson(r, trials, args.in.trials);
  report_json["joint_checks"] = solver::FitTrustJson(trust);
  if (!args.report.empty()) {
    std::ofstream f(args.report);
    f << report_json.dump(1) << "\n";
    if (!f) {
      spdlog::error("{}: cannot write the report", args.report);
      return 1;
    }
  }
  if (!args.html.empty()) {
    report::FitReportPage page;
    page.report = report_json;
    page.initial = model;
    page.fitted = result.model;
    page.model_file = args.in.model_path;
    page.options = {{"fit", args.groups},
                    {"max_iterations", args.max_iterations},
                    {"coarse_frames", args.coarse_frames},
                    {"stage_frames", args.stage_frames},
                    {"marker_sigma_rounds", args.marker_sigma_rounds},
                    {"scaling_marker_rounds", args.scaling_marker_rounds},
                    {"coordinate_limits", args.coordinate_limits},
                    {"place_stacked_markers", args.place_stacked_markers},
                    {"fixed_marker_sigma_mm", args.fixed_marker_sigma_mm},
                    {"robust_loss", args.robust_loss},
                    {"robust_scale", args.robust_scale},
                    {"schedule", args.single_stage ? "single stage" : "automatic"},
                    {"threads", args.threads},
                    {"initial poses", args.initial.empty() ? "inverse kinematics" : "given (.mot)"}};
    if (!args.functional.empty()) {
      page.options["functional"] = args.functional;
      page.options["functional_sigma_mm"] = args.functional_sigma_mm;
    }
    if (!args.protocol.empty()) {
      // Each trial named after a protocol movement (as `mocap sim` names them) is checked with
      // the fitted poses: the range each excitation reached against the range required.
      sim::Protocol protocol = sim::DefaultProtocol();
      if (args.protocol != "default")
        if (Status p = sim::LoadProtocolJson(args.protocol, &protocol); !p) {
          spdlog::error("--protocol: {}", p.message());
          return 2;
        }
      page.options["protocol"] = args.protocol;
      const Model& fitted = result.model;
      for (size_t t = 0; t < trials.size(); ++t) {
        const sim::Movement* movement = protocol.Find(trials[t].markers.name);
        if (movement == nullptr) continue;
        formats::CoordinateTable table;
        table.values = result.coordinates[t];
        for (int c = 0; c < fitted.num_coordinates(); ++c) {
          table.column_names.push_back(fitted.coordinates()[c].name);
          if (fitted.coordinates()[c].rotational) table.values.col(c) *= 180.0 / M_PI;
        }
        // A movement in parts (its excitations' windows) gets its phases as bands in its strip.
        const std::vector<sim::MovementPhase> phases = sim::MovementPhases(*movement);
        const int last = std::max(0, static_cast<int>(table.values.rows()) - 1);
        if (phases.size() > 1)
          for (const sim::MovementPhase& p : phases) {
            std::string label;
            for (const std::string& c : p.coordinates) label += (label.empty() ? "" : ", ") + c;
            page.bands.push_back({movement->name, label, static_cast<int>(std::lround(p.begin * last)),
                                  static_cast<int>(std::lround(p.end * last))});
          }
        for (const sim::ExcitationCheck& e : sim::CheckExcitations(*movement, table, sim::ExcitationCheckOptions()))
          page.coverage.push_back({movement->name, e.coordinate, e.min_deg, e.max_deg, e.reached_min_deg,
                                   e.reached_max_deg, e.required, e.ok});
      }
    }
    page.software_version = "mocap " MOCAP_VERSION;
    const std::time_t now = std::chrono::system_clock::to_time_t(std::chrono::system_clock::now());
    char date[32];
    std::strftime(date, sizeof date, "%Y-%m-%d %H:%M UTC", std::gmtime(&now));
    page.date = date;
    std::string html;
    Status h = report::WriteFitReportHtml(page, &html);
    if (h) h = formats::detail::WriteWholeFile(args.html, html);
    if (!h) {
      spdlog::error("--html {}: {}", args.html, h.message());
      return 1;
    }
    spdlog::info("wrote the report page {}", args.html);
  }
  return 0;
}

const CommandRegistrar kRegisterFit("fit", [](CLI::App& app, int* exit_code) {
  auto args = std::make_shared<FitArgs>();
  CLI::App* cmd = app.add_subcommand("fit", "fit a body model to labelled marker trials (global sparse LM)");
  AddInputOptions(cmd, &args->in);
  cmd->add_option("--out", args->out, "fitted model to write (.json, or .osim from an .osim model)")->required();
  cmd->add_option("--report", args->report, "JSON report to write");
  cmd->add_option("--html", args->html,
                  "report page to write: one self-contained HTML file (skeleton views, residuals, "
                  "convergence), opens without a network and prints to A4");
  cmd->add_option("--protocol", args->protocol,
                  "with --html: show the coverage of this protocol (\"default\" or a .json) by "
                  "the trials named after its movements, with the fitted poses");
  cmd->add_option("--threads", args->threads, "worker threads (0: all cores)")->check(CLI::NonNegativeNumber);
  cmd->add_option("--fit", args->groups, "parameter groups: scales,centres,axes,markers (or all, none)");
  cmd->add_option("--max-iterations", args->max_iterations, "iteration limit")->check(CLI::PositiveNumber);
  cmd->add_option("--coarse-frames", args->coarse_frames,
                  "frames of the coarse-to-fine start, used from 3,000 frames (or twice this) on "
                  "(0: LM on all frames from the start)")
      ->check(CLI::NonNegativeNumber);
  cmd->add_option("--stage-frames", args->stage_frames,
                  "frames the schedule's stages before the last solve, every k-th of each trial; the "
                  "last stage solves every frame (0: every stage on every frame)")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  cmd->add_option("--marker-sigma-rounds", args->marker_sigma_rounds,
                  "rounds of re-weighting each marker by its own residual spread after a converged "
                  "solve (never above the stage's marker sigma; 0: one sigma for every marker; see README)")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  cmd->add_option("--scaling-marker-rounds", args->scaling_marker_rounds,
                  "rounds of re-weighting each marker in the scales stage by how far the model's place for it "
                  "is from the data's (Cauchy; for generic models whose cluster markers are guesses; 0: off)")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  cmd->add_option("--coordinate-limits", args->coordinate_limits,
                  "hold each clamped coordinate of the model (OpenSim <clamped>true</clamped>) inside its range, "
                  "as OpenSim's IK does (true/false)")
      ->capture_default_str();
  cmd->add_option("--fixed-marker-sigma-mm", args->fixed_marker_sigma_mm,
                  "prior sigma of the markers the model fixes on landmarks (OpenSim <fixed>true</fixed>); "
                  "the others have --prior-sigma-position")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  cmd->add_option("--place-stacked-markers", args->place_stacked_markers,
                  "model markers stacked on one point of a segment (a generic model's placeholders for a "
                  "lab's cluster) are left out of the first stage and placed where the trials put them (true/false)")
      ->capture_default_str();
  cmd->add_option("--robust-loss", args->robust_loss,
                  "none, huber or cauchy: marker samples beyond --robust-scale marker sigmas are "
                  "down-weighted (iteratively reweighted), so a mislabelled or slipping marker cannot "
                  "drag its segment; the report counts them per marker (see README)")
      ->check(CLI::IsMember({"none", "huber", "cauchy"}))
      ->capture_default_str();
  cmd->add_option("--robust-scale", args->robust_scale,
                  "the robust loss's scale, in marker sigmas (the median marker's residual RMS per coordinate)")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  cmd->add_option("--functional", args->functional,
                  "joints (e.g. hip_r,hip_l) whose functional centres (SCoRE, per trial that "
                  "excites them) pull the fit's centres, as a virtual marker at each");
  cmd->add_option("--functional-sigma-mm", args->functional_sigma_mm,
                  "how far (mm, 1 sigma) a fitted centre may sit from its functional estimate")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  cmd->add_flag("--adopt-better-minimum", args->adopt_better_minimum,
                "release each profiled joint's fit held at its functional estimate and adopt the lowest release "
                "below the chi-square quantile (solver/fit_trust.h; off: a lower cost was not a better model on "
                "the real recordings)");
  cmd->add_flag("--single-stage", args->single_stage,
               "no automatic schedule: every group free from the first iteration (by default, with "
               "centres or axes fitted, scales and markers are fitted first, then everything)");
  cmd->add_option("--initial", args->initial,
                  "starting poses: one .mot per trial, same order (e.g. coordinates.mot of `mocap "
                  "track`), instead of per-frame IK; NaN rows are solved by IK");
  cmd->callback([args, exit_code] { *exit_code = RunFit(*args); });
});

}  // namespace
}  // namespace mocap::tools
