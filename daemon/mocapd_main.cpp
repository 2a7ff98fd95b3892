// mocapd: the motion-capture daemon (daemon/daemon.h). Usage:
//   mocapd [--config /etc/mocapd/mocapd.toml] [--state-dir DIR] [--socket PATH]
//          [--export-dir DIR ...] [--check-config]
// Logs to stderr with syslog priority prefixes ("<6>...") so that journald files each line at its
// level; run by hand on a terminal, the lines are plain. Under systemd (mocapd.service,
// Type=notify) it reports readiness, status and health through sd_notify
// (daemon/service_notify.h); exit codes: 0 stopped, 78 configuration, 73/77 storage directory,
// 69 cameras or store unavailable (daemon/startup_checks.h).
#include <systemd/sd-daemon.h>
#include <unistd.h>

#include <CLI/CLI.hpp>
#include <spdlog/pattern_formatter.h>
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <memory>
#include <sstream>
#include <vector>
#include <string>
#include <thread>

#include "daemon/config.h"
#include "daemon/daemon.h"
#include "daemon/service_notify.h"
#include "daemon/startup_checks.h"
#include "drivers/frame.h"

namespace {

// "%*" in the pattern: the syslog priority of the message's level, as sd-daemon(3) describes.
class SyslogPriorityFlag : public spdlog::custom_flag_formatter {
 public:
  void format(const spdlog::details::log_msg& msg, const std::tm&,
              spdlog::memory_buf_t& dest) override {
    int p = 6;
    switch (msg.level) {
      case spdlog::level::trace:
      case spdlog::level::debug: p = 7; break;
      case spdlog::level::info: p = 6; break;
      case spdlog::level::warn: p = 4; break;
      case spdlog::level::err: p = 3; break;
      case spdlog::level::critical: p = 2; break;
      default: break;
    }
    const char text[4] = {'<', static_cast<char>('0' + p), '>', 0};
    dest.append(text, text + 3);
  }
  std::unique_ptr<custom_flag_formatter> clone() const override {
    return std::make_unique<SyslogPriorityFlag>();
  }
};

void SetupLogging() {
  auto logger = spdlog::stderr_color_mt("mocapd");
  if (isatty(STDERR_FILENO)) {
    logger->set_pattern("%H:%M:%S.%e %^%l%$ %v");
  } else {
    auto formatter = std::make_unique<spdlog::pattern_formatter>();
    formatter->add_flag<SyslogPriorityFlag>('*').set_pattern("%*%v");
    logger->set_formatter(std::move(formatter));
  }
  logger->flush_on(spdlog::level::info);
  spdlog::set_default_logger(logger);
}

// Set before Daemon::Stop(): a held stage lets go so the pipeline's threads can be joined.
std::atomic<bool> g_stopping{false};

// Test hooks (built with MOCAP_TEST_HOOKS, tests/test_daemon_systemd.cpp): while the file named
// by MOCAP_TEST_HOLD_FILE exists, the pipeline stage named by MOCAP_TEST_HOLD_STAGE ("grab" or
// "detection") waits, as a hung stage would. Why the environment and not a config key: the
// configuration is the admin's interface and is validated key by key; a hook there would be
// documented, diffed on reload and shipped. An environment variable set by the test's fork, read
// only in a test build, touches nothing else.
void InstallTestHooks([[maybe_unused]] mocap::daemon::DaemonOptions* options) {
#ifdef MOCAP_TEST_HOOKS
  if (const char* absent = std::getenv("MOCAP_TEST_ABSENT_CAMERAS")) {
    std::stringstream list(absent);
    for (std::string item; std::getline(list, item, ',');)
      if (!item.empty()) options->test_absent_cameras.push_back(std::atoi(item.c_str()));
    spdlog::warn("test hook: simulated cameras {} unplugged at start", absent);
  }
  const char* file = std::getenv("MOCAP_TEST_HOLD_FILE");
  const char* stage = std::getenv("MOCAP_TEST_HOLD_STAGE");
  if (!file || !stage) return;
  spdlog::warn("test hook: the {} stage waits while {} exists", stage, file);
  options->test_hold = [path = std::string(file), held = std::string(stage)](const char* at) {
    if (held != at) return;
    while (!g_stopping.load() && access(path.c_str(), F_OK) == 0)
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
  };
#endif
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"mocapd: the motion-capture daemon (cameras, tracking, recordings, the body-model fit)"};
  std::string config_path = "/etc/mocapd/mocapd.toml", state_dir, socket_path;
  bool check = false;
  app.add_option("--config", config_path, "configuration file (TOML)")->capture_default_str();
  app.add_option("--state-dir", state_dir, "storage directory (overrides [storage] dir)");
  app.add_option("--socket", socket_path, "control socket path (overrides [control] socket)");
  std::vector<std::string> export_dirs;
  app.add_option("--export-dir", export_dirs,
                 "a directory `export` may write beneath (repeatable; overrides [storage] export_dirs)");
  app.add_flag("--check-config", check, "validate the configuration and exit");
  app.set_version_flag("--version", "mocapd 0.1.0");
  CLI11_PARSE(app, argc, argv);
  SetupLogging();

  namespace md = mocap::daemon;
  md::DaemonConfig config;
  if (mocap::Status s = md::LoadConfig(config_path, &config); !s) {
    spdlog::error("{}", s.message());
    if (!check) md::ServiceNotifier::StartFailed("configuration: " + s.message(), md::kExitConfig);
    return md::kExitConfig;
  }
  if (!state_dir.empty()) config.state_dir = state_dir;
  if (!socket_path.empty()) config.socket_path = socket_path;
  for (std::string& d : export_dirs) d = std::filesystem::absolute(d).lexically_normal().string();
  if (!export_dirs.empty()) config.export_dirs = export_dirs;
  std::string error;
  if (!config.IsValid(&error)) {
    spdlog::error("{}: {}", config_path, error);
    if (!check) md::ServiceNotifier::StartFailed("configuration: " + error, md::kExitConfig);
    return md::kExitConfig;
  }
  // The rig's bandwidth is a configuration error too (daemon/startup_checks.h).
  if (const md::StartupCheck c = md::CheckRigBandwidth(config); !c.ok() && config.simulated_cameras > 0) {
    // Its fakes carry nothing: the planned links' budget is the rig check's to report.
    spdlog::warn("{}: simulated rig: {} (mocapctl cameras --check fails on it)", config_path,
                 c.status.message());
  } else if (!c.ok()) {
    spdlog::error("{}: {}", config_path, c.status.message());
    if (!check) md::ServiceNotifier::StartFailed(c.status.message(), c.exit_code);
    return c.exit_code;
  }
  if (check) {
    std::printf("%s", md::DescribeRigBandwidth(config).c_str());
    std::printf("%s: ok (%s rig of %d cameras at %g Hz; state in %s; socket %s)\n",
                config_path.c_str(), config.simulated_cameras > 0 ? "simulated" : "camera",
                config.simulated_cameras > 0 ? config.simulated_cameras
                                             : static_cast<int>(config.cameras.size()),
                config.rate_hz, config.state_dir.c_str(), config.socket_path.c_str());
    return 0;
  }

  md::DaemonOptions options;
  options.config_path = config_path;
  options.export_dirs = export_dirs;
  // Socket activation: systemd hands over the listening control socket (mocapd.socket).
  const int fds = sd_listen_fds(1);
  if (fds == 1) options.listen_fd = SD_LISTEN_FDS_START;
  else if (fds > 1) spdlog::warn("systemd passed {} sockets; using the first", fds);

  if (const md::StartupCheck c = md::CheckStartup(config, options.listen_fd >= 0); !c.ok()) {
    spdlog::error("{}", c.status.message());
    md::ServiceNotifier::StartFailed(c.status.message(), c.exit_code);
    return c.exit_code;
  }
  if (const std::string advice = md::UsbfsAdvice(config); !advice.empty()) spdlog::warn("{}", advice);

  md::ServiceNotifier notifier(md::ServiceNotifier::FromEnvironment());
  options.notifier = &notifier;
  InstallTestHooks(&options);
  md::Daemon daemon(config, options);
  if (mocap::Status s = daemon.Start(); !s) {
    spdlog::error("start-up failed: {}", s.message());
    md::ServiceNotifier::StartFailed(s.message(), daemon.StartExitCode());
    g_stopping = true;
    daemon.Stop();
    return daemon.StartExitCode();
  }
  // READY=1 follows from the loop's tick once the cameras stream (daemon/service_notify.h).
  notifier.Started(mocap::drivers::MonotonicNs());
  const int code = daemon.Run();
  notifier.Stopping();
  g_stopping = true;
  spdlog::info("stopping: socket, recording, jobs, cameras, store");
  daemon.Stop();
  spdlog::info("stopped");
  return code;
}
