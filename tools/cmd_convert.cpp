// `mocap convert IN OUT`: marker trajectories between C3D and TRC, the format of each file chosen
// by its extension (.c3d / .trc, any case; C3D -> C3D and TRC -> TRC work too). Exit 2 for a usage
// error (unknown extension, bad option), 1 when a file cannot be read or written.
#include <spdlog/spdlog.h>

#include <cstdio>
#include <filesystem>
#include <memory>
#include <string>

#include "formats/c3d.h"
#include "formats/marker_file.h"
#include "formats/trc.h"
#include "tools/command.h"
#include "tools/trial_inputs.h"

namespace {

using mocap::formats::MarkerFileKind;
using mocap::formats::MarkerFileKindOf;

struct ConvertArgs {
  std::string in, out;
  bool keep_label_prefix = false;
  std::string units = "mm";
};

int RunConvert(const ConvertArgs& args) {
  for (const std::string& path : {args.in, args.out}) {
    if (MarkerFileKindOf(path) == MarkerFileKind::kUnknown) {
      spdlog::error("mocap convert: {}: unknown file type (expected a .c3d or .trc extension)",
                    path);
      return 2;
    }
  }
  if (args.units != "mm" && args.units != "m") {
    spdlog::error("mocap convert: --units {}: expected mm or m", args.units);
    return 2;
  }
  std::error_code ec;
  if (std::filesystem::equivalent(args.in, args.out, ec)) {
    spdlog::error("mocap convert: {} is both the input and the output", args.in);
    return 2;
  }

  mocap::formats::MarkerTrial trial;
  mocap::formats::C3dReadOptions c3d_options;
  c3d_options.strip_label_prefix = !args.keep_label_prefix;
  mocap::Status s = mocap::formats::ReadMarkerFile(args.in, &trial, c3d_options);
  if (!s) {
    spdlog::error("mocap convert: {}", s.message());
    return 1;
  }
  mocap::tools::LogSkippedPoints(args.in, trial);
  if (MarkerFileKindOf(args.out) == MarkerFileKind::kC3d) {
    s = mocap::formats::WriteC3d(args.out, trial);
  } else {
    mocap::formats::TrcWriteOptions options;
    options.units = args.units;
    s = mocap::formats::WriteTrc(args.out, trial, options);
  }
  if (!s) {
    spdlog::error("mocap convert: {}", s.message());
    return 1;
  }
  int missing = 0;
  for (int f = 0; f < trial.num_frames(); ++f) {
    for (int m = 0; m < trial.num_markers(); ++m) missing += !trial.Has(f, m);
  }
  std::printf("mocap convert: %s -> %s: %d frames, %d markers at %g Hz, %d missing samples\n",
              args.in.c_str(), args.out.c_str(), trial.num_frames(), trial.num_markers(),
              trial.rate_hz, missing);
  return 0;
}

void SetupConvert(CLI::App& app, int* exit_code) {
  auto args = std::make_shared<ConvertArgs>();
  CLI::App* cmd = app.add_subcommand(
      "convert", "Convert marker trajectories between C3D and TRC (by file extension)");
  cmd->add_option("IN", args->in, "Input file (.c3d or .trc)")->required();
  cmd->add_option("OUT", args->out, "Output file (.c3d or .trc), overwritten")->required();
  cmd->add_flag("--keep-label-prefix", args->keep_label_prefix,
                "C3D input: keep subject prefixes such as 'FullBody_static:' in marker labels");
  cmd->add_option("--units", args->units, "TRC output units: mm or m")->capture_default_str();
  cmd->callback([args, exit_code] { *exit_code = RunConvert(*args); });
}

const mocap::tools::CommandRegistrar kConvertRegistrar("convert", SetupConvert);

}  // namespace
