// `mocap`: the offline toolbox (sim, fit, model, ...). Each subcommand lives in tools/cmd_*.cpp.
#include <spdlog/spdlog.h>

#include <algorithm>

#include "tools/command.h"

int main(int argc, char** argv) {
  CLI::App app{"mocap — offline toolbox of mocapd: simulate, fit and inspect body models"};
  app.require_subcommand(1);
  int exit_code = 0;
  auto& commands = mocap::tools::CommandRegistry::All();
  std::sort(commands.begin(), commands.end(),
            [](const auto& a, const auto& b) { return a.first < b.first; });
  for (auto& [name, setup] : commands) setup(app, &exit_code);
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    // --help and --version exit 0; a usage error (unknown option, bad or missing value) exits 2,
    // as getopt-style tools do, rather than with CLI11's internal error numbers.
    return app.exit(e) == 0 ? 0 : 2;
  }
  return exit_code;
}
