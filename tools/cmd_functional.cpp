// mocap functional: a joint's functional centre (SCoRE) and axis (SARA) from one trial, from the
// markers of the joint's two segments alone (solver/functional_joints.h). The model only says
// which markers sit on which segment; its geometry is not used, so the estimate is a reference
// independent of `mocap fit`.
#include <spdlog/spdlog.h>

#include <cmath>
#include <memory>
#include <nlohmann/json.hpp>

#include "solver/functional_joints.h"
#include "tools/command.h"
#include "tools/trial_inputs.h"

namespace mocap::tools {
namespace {

struct FunctionalArgs {
  std::string model_path;
  std::string marker_set;
  std::string marker_map;
  std::string trial;
  std::string joint;
  bool json = false;
  solver::FunctionalJointOptions options;
};

nlohmann::json Vec(const Eigen::Vector3d& v) { return {v.x(), v.y(), v.z()}; }

nlohmann::json FitJson(const solver::FunctionalFit& fit) {
  return {{"frames_used", fit.frames_used},
          {"residual_rms_mm", fit.residual_rms_mm},
          {"condition", std::isfinite(fit.condition) ? nlohmann::json(fit.condition) : nullptr},
          {"rotation_spread_deg", Vec(fit.rotation_spread_deg)},
          {"excited", fit.excited},
          {"note", fit.note}};
}

// Means over the frames where both clusters have a pose: the centre and the axis point in the lab
// (metres), and the axis direction (signs aligned with the first frame's).
struct LabMeans {
  Eigen::Vector3d centre = Eigen::Vector3d::Zero(), axis = Eigen::Vector3d::Zero(),
                  axis_point = Eigen::Vector3d::Zero();
};
LabMeans MeansInLab(const solver::FunctionalJoint& fj, int frames) {
  LabMeans m;
  int n = 0;
  Eigen::Vector3d first = Eigen::Vector3d::Zero();
  for (int f = 0; f < frames; ++f) {
    const Eigen::Vector3d c = fj.CentreInLab(f);
    if (!c.allFinite()) continue;
    Eigen::Vector3d a = fj.AxisInLab(f);
    if (n == 0) first = a;
    if (a.dot(first) < 0) a = -a;
    m.centre += c;
    m.axis += a;
    m.axis_point += fj.AxisPointInLab(f);
    ++n;
  }
  if (n > 0) {
    m.centre /= n;
    m.axis_point /= n;
    m.axis.normalize();
  }
  return m;
}

std::string Join(const std::vector<std::string>& names) {
  std::string out;
  for (const std::string& n : names) out += (out.empty() ? "" : " ") + n;
  return out;
}

int RunFunctional(const FunctionalArgs& args) {
  std::string why;
  if (!args.options.IsValid(&why)) {
    spdlog::error("mocap functional: {}", why);
    return 2;
  }
  ModelInput model;
  if (Status s = LoadModelInput(args.model_path, args.marker_set, &model); !s) {
    spdlog::error("{}", s.message());
    return 1;
  }
  std::vector<formats::MarkerTrial> trials;
  MarkerMatch match;
  if (Status s = LoadTrials({args.trial}, args.marker_map, model.model, &trials, &match); !s) {
    spdlog::error("{}", s.message());
    return 1;
  }
  const formats::MarkerTrial& trial = trials[0];
  solver::FunctionalJoint fj;
  if (Status s = solver::EstimateFunctionalJoint(model.model, trial, args.joint, args.options, &fj);
      !s) {
    spdlog::error("{}: {}", args.trial, s.message());
    return 1;
  }
  const LabMeans lab = MeansInLab(fj, trial.num_frames());
  // A hinge, a universal joint or a knee that turns about one axis is described by its axis;
  // every other joint by its centre (solver::DescribedByAxis).
  const bool axis_joint = fj.axis_joint;
  const solver::FunctionalFit& primary = axis_joint ? fj.axis.fit : fj.centre.fit;
  if (!primary.excited)
    spdlog::warn("{}: {} of {} is not to be trusted: {}", args.trial,
                 axis_joint ? "the axis" : "the centre", fj.joint, primary.note);

  if (args.json) {
    nlohmann::json j;
    j["joint"] = fj.joint;
    j["type"] = ToString(fj.type);
    j["trial"] = args.trial;
    j["frames"] = trial.num_frames();
    j["parent"] = {{"segment", fj.parent_segment},
                   {"markers", fj.parent_markers},
                   {"cluster_rms_mm", fj.parent.rms_mm}};
    j["child"] = {{"segment", fj.child_segment},
                  {"markers", fj.child_markers},
                  {"cluster_rms_mm", fj.child.rms_mm}};
    j["centre"] = {{"method", "SCoRE"},
                   {"in_parent_cluster_m", Vec(fj.centre.in_parent)},
                   {"in_child_cluster_m", Vec(fj.centre.in_child)},
                   {"lab_mean_m", Vec(lab.centre)},
                   {"std_mm", fj.centre.std_mm},
                   {"fit", FitJson(fj.centre.fit)}};
    j["axis"] = {{"method", "SARA"},
                 {"direction_parent_cluster", Vec(fj.axis.direction_parent)},
                 {"direction_child_cluster", Vec(fj.axis.direction_child)},
                 {"direction_lab_mean", Vec(lab.axis)},
                 {"point_lab_mean_m", Vec(lab.axis_point)},
                 {"direction_std_deg", fj.axis.direction_std_deg},
                 {"point_std_mm", fj.axis.point_std_mm},
                 {"fit", FitJson(fj.axis.fit)}};
    std::printf("%s\n", j.dump(2).c_str());
    return 0;
  }
  std::printf("%s (%s) in %s: %s [%s] -> %s [%s]; clusters fit to %.2f / %.2f mm RMS\n",
              fj.joint.c_str(), ToString(fj.type), args.trial.c_str(), fj.parent_segment.c_str(),
              Join(fj.parent_markers).c_str(), fj.child_segment.c_str(),
              Join(fj.child_markers).c_str(), fj.parent.rms_mm, fj.child.rms_mm);
  const auto& c = fj.centre;
  std::printf("SCoRE centre: lab mean (%.1f, %.1f, %.1f) mm, std %.2f mm, residual %.2f mm RMS over "
              "%d frames, rotation spread %.1f / %.1f / %.1f deg, condition %.1f%s%s\n",
              1000 * lab.centre.x(), 1000 * lab.centre.y(), 1000 * lab.centre.z(), c.std_mm,
              c.fit.residual_rms_mm, c.fit.frames_used, c.fit.rotation_spread_deg[0],
              c.fit.rotation_spread_deg[1], c.fit.rotation_spread_deg[2], c.fit.condition,
              c.fit.excited ? "" : "; NOT EXCITED: ", c.fit.note.c_str());
  const auto& a = fj.axis;
  std::printf("SARA axis: lab mean direction (%.3f, %.3f, %.3f) through (%.1f, %.1f, %.1f) mm, "
              "std %.2f deg / %.2f mm, residual %.2f mm RMS%s%s\n",
              lab.axis.x(), lab.axis.y(), lab.axis.z(), 1000 * lab.axis_point.x(),
              1000 * lab.axis_point.y(), 1000 * lab.axis_point.z(), a.direction_std_deg,
              a.point_std_mm, a.fit.residual_rms_mm, a.fit.excited ? "" : "; NOT EXCITED: ",
              a.fit.note.c_str());
  return 0;
}

const CommandRegistrar kRegisterFunctional("functional", [](CLI::App& app, int* exit_code) {
  auto args = std::make_shared<FunctionalArgs>();
  CLI::App* cmd = app.add_subcommand(
      "functional",
      "a joint's functional centre (SCoRE) and axis (SARA) from the markers of its two segments");
  cmd->add_option("--model", args->model_path,
                  "model (.osim or .json): which markers are on which segment")
      ->required();
  cmd->add_option("--marker-set", args->marker_set, "OpenSim MarkerSet .xml for an .osim model");
  cmd->add_option("--marker-map", args->marker_map, "marker-name map (model_name = file_name)");
  cmd->add_option("--trial", args->trial, "the functional trial (.c3d or .trc)")->required();
  cmd->add_option("--joint", args->joint, "the joint, e.g. hip_r")->required();
  cmd->add_option("--min-rotation-deg", args->options.min_rotation_deg,
                  "RMS rotation spread below which the joint counts as not excited")
      ->capture_default_str();
  cmd->add_option("--bootstrap", args->options.bootstrap_samples,
                  "bootstrap resamples for the standard deviations (0: none)")
      ->capture_default_str();
  cmd->add_flag("--json", args->json, "print one JSON object");
  cmd->callback([args, exit_code] { *exit_code = RunFunctional(*args); });
});

}  // namespace
}  // namespace mocap::tools
