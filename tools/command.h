// Subcommands of `mocap` register themselves: each tools/cmd_*.cpp defines a static
// CommandRegistrar whose function adds a CLI11 subcommand and, when it runs, sets the exit code.
#pragma once
#include <CLI/CLI.hpp>
#include <functional>
#include <string>
#include <vector>

namespace mocap::tools {

using CommandSetup = std::function<void(CLI::App& app, int* exit_code)>;

struct CommandRegistry {
  static std::vector<std::pair<std::string, CommandSetup>>& All() {
    static std::vector<std::pair<std::string, CommandSetup>> commands;
    return commands;
  }
};

struct CommandRegistrar {
  CommandRegistrar(std::string name, CommandSetup setup) {
    CommandRegistry::All().emplace_back(std::move(name), std::move(setup));
  }
};

}  // namespace mocap::tools
