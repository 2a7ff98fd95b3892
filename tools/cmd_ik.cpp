// mocap ik: per-frame inverse kinematics of marker trials with a model as given (no geometry
// fitted): joint angles out as .mot, marker RMS per trial printed.
//
// Output naming: with one trial the angles go to --out exactly; with several, to
// <out stem>_<trial stem>.mot beside --out (angles.mot + walk1.trc, run2.c3d -> angles_walk1.mot,
// angles_run2.mot).
#include <spdlog/spdlog.h>

#include <chrono>
#include <cmath>
#include <filesystem>
#include <memory>

#include "solver/inverse_kinematics.h"
#include "tools/command.h"
#include "tools/trial_inputs.h"

namespace mocap::tools {
namespace {

namespace fs = std::filesystem;

struct IkArgs {
  InputArgs in;
  std::string out;
};

int RunIk(const IkArgs& args) {
  if (!HasExtension(args.out, ".mot")) {
    spdlog::error("--out {}: expected a .mot file", args.out);
    return 2;
  }
  Inputs inputs;
  if (!LoadInputs(args.in, &inputs)) return 1;
  const Model& model = inputs.model.model;
  const std::vector<formats::MarkerTrial>& trials = inputs.trials;
  for (size_t a = 0; a < trials.size(); ++a)
    for (size_t b = 0; b < a; ++b)
      if (trials[a].name == trials[b].name) {
        spdlog::error("{} and {} would both write {}_{}.mot: give the trials distinct file names", args.in.trials[b],
                      args.in.trials[a], fs::path(args.out).stem().string(), trials[a].name);
        return 2;
      }
  const fs::path out(args.out);
  if (out.has_parent_path()) fs::create_directories(out.parent_path());
  const Geometry geometry(model);
  solver::InverseKinematics ik(model, geometry);
  for (size_t t = 0; t < trials.size(); ++t) {
    const formats::MarkerTrial& trial = trials[t];
    const auto start = std::chrono::steady_clock::now();
    // The trial's markers in model order (NaN where the trial lacks one).
    formats::RowMatrix measured(trial.num_frames(), 3 * model.num_markers());
    measured.setConstant(std::nan(""));
    int matched = 0;
    for (int m = 0; m < model.num_markers(); ++m) {
      const int c = trial.FindMarker(model.markers()[m].name);
      if (c < 0) continue;
      measured.middleCols(3 * m, 3) = trial.positions.middleCols(3 * c, 3);
      ++matched;
    }
    for (int f = 0; f < measured.rows(); ++f)
      for (int m = 0; m < model.num_markers(); ++m)
        if (!measured.row(f).segment<3>(3 * m).allFinite()) measured.row(f).segment<3>(3 * m).setConstant(std::nan(""));
    if (matched == 0) {
      spdlog::error("{}: none of its {} markers is in the model", args.in.trials[t], trial.num_markers());
      return 1;
    }
    Eigen::MatrixXd z;
    std::vector<double> frame_rms;
    if (Status s = ik.SolveTrial(measured, &z, &frame_rms); !s) {
      spdlog::error("{}: {}", args.in.trials[t], s.message());
      return 1;
    }
    // RMS over every marker sample of the trial (3D distances): frames weighted by their samples.
    double sum_sq = 0, worst = 0;
    long samples = 0;
    for (int f = 0; f < z.rows(); ++f) {
      int n = 0;
      for (int m = 0; m < model.num_markers(); ++m) n += std::isfinite(measured(f, 3 * m)) ? 1 : 0;
      if (n < 3) continue;  // such a frame keeps its neighbour's pose and is not solved
      sum_sq += frame_rms[f] * frame_rms[f] * n;
      samples += n;
      worst = std::max(worst, frame_rms[f]);
    }
    const fs::path path = trials.size() == 1
                              ? out
                              : out.parent_path() / (out.stem().string() + "_" + trial.name + ".mot");
    if (Status s = WriteAngles(path.string(), inputs.model, model, trial, z); !s) {
      spdlog::error("{}", s.message());
      return 1;
    }
    const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    std::printf("%s: %d frames, %d model markers, marker RMS %.3f mm (worst frame %.3f mm), %.2f s -> %s\n",
                args.in.trials[t].c_str(), trial.num_frames(), matched,
                1000.0 * std::sqrt(sum_sq / std::max(1L, samples)), 1000.0 * worst, seconds,
                path.string().c_str());
  }
  return 0;
}

const CommandRegistrar kRegisterIk("ik", [](CLI::App& app, int* exit_code) {
  auto args = std::make_shared<IkArgs>();
  CLI::App* cmd = app.add_subcommand(
      "ik", "per-frame inverse kinematics with the model as given: joint angles (.mot) and marker RMS");
  AddInputOptions(cmd, &args->in);
  cmd->add_option("--out", args->out,
                  "joint angles (.mot); with several trials, <stem>_<trial>.mot beside it")->required();
  cmd->callback([args, exit_code] { *exit_code = RunIk(*args); });
});

}  // namespace
}  // namespace mocap::tools
