// `mocap sim`: a virtual subject with known true geometry performs the calibration protocol;
// writes the nominal and true models, one TRC (mm) and one MOT (true coordinates, degrees) per
// movement, and subject.json describing the session.
#include <spdlog/spdlog.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <memory>

#include "formats/mot.h"
#include "formats/trc.h"
#include "model/model_io.h"
#include "sim/simulate.h"
#include "tools/command.h"

namespace {

struct SimArgs {
  std::string out;
  std::string protocol;  // empty: the default protocol
  mocap::sim::SimulationOptions options;
};

// SimulationOptions::IsValid names the field; the user typed the flag.
std::string FlagOf(const std::string& message) {
  static const std::pair<const char*, const char*> flags[] = {
      {"noise_mm", "--noise-mm"}, {"sta_mm", "--sta-mm"},  {"missing", "--missing"},
      {"rate_hz", "--rate"},      {"duration_scale", "--duration-scale"}};
  for (const auto& [field, flag] : flags)
    if (message.rfind(field, 0) == 0) return std::string(flag) + ": ";
  return "";
}

int RunSim(const SimArgs& args) {
  namespace fs = std::filesystem;
  std::string error;
  if (!args.options.IsValid(&error)) {
    spdlog::error("mocap sim: {}{}", FlagOf(error), error);
    return 2;
  }
  mocap::sim::Protocol protocol = mocap::sim::DefaultProtocol();
  if (!args.protocol.empty()) {
    if (mocap::Status s = mocap::sim::LoadProtocolJson(args.protocol, &protocol); !s) {
      spdlog::error("mocap sim: {}", s.message());
      return 2;
    }
  }
  std::error_code ec;
  fs::create_directories(args.out, ec);
  if (ec || !fs::is_directory(args.out)) {
    spdlog::error("mocap sim: cannot create output directory '{}': {}", args.out,
                  ec ? ec.message() : "not a directory");
    return 1;
  }

  mocap::sim::SimulatedSession session;
  if (mocap::Status s = mocap::sim::SimulateSession(args.options, protocol, &session); !s) {
    spdlog::error("mocap sim: {}", s.message());
    return 2;
  }

  const fs::path dir(args.out);
  auto check = [](const mocap::Status& s) {
    if (!s) spdlog::error("mocap sim: {}", s.message());
    return s.ok();
  };
  if (!check(mocap::SaveModelJson((dir / "nominal.model.json").string(), session.nominal)) ||
      !check(mocap::SaveModelJson((dir / "truth.model.json").string(), session.truth)))
    return 1;
  for (const mocap::sim::SimulatedTrial& trial : session.trials) {
    const std::string stem = (dir / trial.markers.name).string();
    if (!check(mocap::formats::WriteTrc(stem + ".trc", trial.markers)) ||
        !check(mocap::formats::WriteMot(stem + ".mot", trial.coordinates)))
      return 1;
  }
  {
    const std::string path = (dir / "subject.json").string();
    std::ofstream f(path, std::ios::binary);
    f << mocap::sim::SessionSummaryJson(session);
    if (!f) {
      spdlog::error("mocap sim: cannot write '{}'", path);
      return 1;
    }
  }

  const int frames = session.total_frames();
  const int markers = session.trials.empty() ? 0 : session.trials.front().markers.num_markers();
  std::printf("mocap sim: seed %llu, subject %.3f m, %zu movements, %d frames (%.1f s at %g Hz), "
              "%d markers, noise %g mm, STA %g mm, missing %g%% -> %s\n",
              static_cast<unsigned long long>(args.options.seed), session.height_m,
              session.trials.size(), frames, frames / args.options.rate_hz, args.options.rate_hz,
              markers, args.options.noise_mm, args.options.sta_mm, 100.0 * args.options.missing,
              args.out.c_str());
  return 0;
}

void SetupSim(CLI::App& app, int* exit_code) {
  auto args = std::make_shared<SimArgs>();
  CLI::App* cmd = app.add_subcommand(
      "sim", "Simulate a virtual subject (known true model) performing the calibration protocol");
  cmd->add_option("--out", args->out, "Output directory (created)")->required();
  cmd->add_option("--seed", args->options.seed, "Random seed: same seed, same session")
      ->check(CLI::NonNegativeNumber)  // CLI11 would otherwise wrap -1 to 2^64 - 1
      ->capture_default_str();
  cmd->add_option("--noise-mm", args->options.noise_mm,
                  "Marker noise, standard deviation per coordinate (mm)")
      ->capture_default_str();
  cmd->add_option("--sta-mm", args->options.sta_mm,
                  "Soft-tissue artefact (mm): RMS on a soft-tissue thigh marker; every marker gets "
                  "this times its class's ratio in sim/default_sta_table.json (bony landmarks "
                  "0.25, unlisted markers 1)")
      ->capture_default_str();
  cmd->add_option("--missing", args->options.missing,
                  "Fraction of marker samples lost in 5..30-frame gaps, [0, 0.9)")
      ->capture_default_str();
  cmd->add_option("--rate", args->options.rate_hz, "Frame rate (Hz)")->capture_default_str();
  cmd->add_option("--duration-scale", args->options.duration_scale,
                  "Multiplies every movement's duration (more cycles, same speeds)")
      ->capture_default_str();
  cmd->add_flag("--medial", args->options.medial_markers,
                "Also simulate the medial knee and ankle markers (LKNM RKNM LMMA RMMA)");
  cmd->add_option("--protocol", args->protocol,
                  "Protocol JSON file (default: the built-in full-body protocol)");
  cmd->callback([args, exit_code] { *exit_code = RunSim(*args); });
}

const mocap::tools::CommandRegistrar kSimRegistrar("sim", SetupSim);

}  // namespace
