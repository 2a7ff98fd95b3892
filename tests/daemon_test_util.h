// The daemon tier's harness (tests/test_daemon*.cpp and bench/daemon_latency.cpp): the real
// `mocapd` executable started on a simulated-rig config in a temporary state directory, driven
// through its socket with the real client (daemon/control_client.h), as an operator's mocapctl
// would. No GoogleTest here: the benchmark uses it too.
#pragma once
#include <fcntl.h>
#include <poll.h>
#include <grp.h>
#include <pwd.h>
#include <signal.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/un.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <memory>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "daemon/control_client.h"

namespace mocap::testing {

inline std::string MakeTempDir(const std::string& prefix) {
  std::string pattern = (std::filesystem::temp_directory_path() / (prefix + "-XXXXXX")).string();
  char* made = mkdtemp(pattern.data());
  return made ? std::string(made) : std::string();
}

// A simulated rig of `cameras` Aravis fake cameras; `extra` is appended to the file.
inline std::string SimulatedRigToml(int cameras, int seed, const std::string& extra = "") {
  return "[rig]\nsimulated = " + std::to_string(cameras) + "\nsubject_seed = " +
         std::to_string(seed) + "\nrate = 200\n" + extra;
}

// Runs `body` in a child process as `user` (its group, no supplementary groups) and returns
// what it returned, through a pipe: how a test is a client outside the control group. "setuid
// failed" when the child could not become that user; "" when the user does not exist.
inline std::string RunAsUser(const std::string& user, const std::function<std::string()>& body) {
  const passwd* pw = getpwnam(user.c_str());
  int pipefd[2];
  if (!pw || pipe(pipefd) != 0) return "";
  const uid_t uid = pw->pw_uid;
  const gid_t gid = pw->pw_gid;
  const pid_t child = fork();
  if (child == 0) {
    close(pipefd[0]);
    const std::string out = setgroups(0, nullptr) == 0 && setgid(gid) == 0 && setuid(uid) == 0
                                ? body()
                                : std::string("setuid failed");
    [[maybe_unused]] ssize_t n = write(pipefd[1], out.data(), out.size());
    _exit(0);
  }
  close(pipefd[1]);
  std::string got;
  char buf[4096];
  for (ssize_t n; (n = read(pipefd[0], buf, sizeof buf)) > 0;) got.append(buf, static_cast<std::size_t>(n));
  close(pipefd[0]);
  waitpid(child, nullptr, 0);
  return got;
}

// The mocapd the tests start: this build's, or the one MOCAP_TEST_MOCAPD names.
// scripts/sanitize_daemon.sh runs this build's daemon-tier tests against build-fuzz/'s mocapd
// (ASan + UBSan): the daemon is what the tier checks, and compiling the tests' own executables
// under the sanitizers too cost CI's critical path two more large links for no coverage of
// mocapd.
inline std::string MocapdPath() {
  const char* path = std::getenv("MOCAP_TEST_MOCAPD");
  return path != nullptr && *path != '\0' ? std::string(path) : std::string(MOCAPD_PATH);
}

class DaemonProcess {
 public:
  static constexpr int kDeployedNice = -10;
  // Writes `toml` to DIR/mocapd.toml and starts mocapd on it with DIR/state and DIR/control.sock.
  DaemonProcess(const std::string& dir, const std::string& toml,
                std::string executable = MocapdPath())
      : dir_(dir), executable_(std::move(executable)), export_dirs_{dir} {
    std::ofstream(dir_ + "/mocapd.toml") << toml;
  }
  ~DaemonProcess() { Kill(SIGKILL); }

  // A command the daemon runs under (e.g. an `unshare -m` that mounts a small tmpfs on the state
  // directory first); its last argument is followed by mocapd's command line.
  void SetWrapper(std::vector<std::string> wrapper) { wrapper_ = std::move(wrapper); }
  // Where `export` may write (mocapd --export-dir); by default DIR, where the tests export.
  void SetExportDirs(std::vector<std::string> dirs) { export_dirs_ = std::move(dirs); }
  // Environment variables set for mocapd (NOTIFY_SOCKET, test hooks).
  void SetEnvironment(std::vector<std::pair<std::string, std::string>> env) { env_ = std::move(env); }
  std::string socket() const { return dir_ + "/control.sock"; }
  std::string state_dir() const { return dir_ + "/state"; }
  std::string log_path() const { return dir_ + "/mocapd.log"; }

  // Starts it and waits until its socket answers (up to `timeout_s`).
  Status Start(double timeout_s = 30) {
    pid_ = fork();
    if (pid_ == 0) {
      // As deployed: the unit starts mocapd at nice -10 (systemd/mocapd.service.in, Nice=) so
      // that batch work beside it cannot take the rig's CPU; the other tests run at nice 10
      // (tests/CMakeLists.txt). Only root may raise a priority; elsewhere mocapd runs at 0.
      if (geteuid() == 0) setpriority(PRIO_PROCESS, 0, kDeployedNice);
      const int log = open(log_path().c_str(), O_WRONLY | O_CREAT | O_APPEND, 0644);
      if (log >= 0) {
        dup2(log, STDERR_FILENO);
        dup2(log, STDOUT_FILENO);
      }
      for (const auto& [name, value] : env_) setenv(name.c_str(), value.c_str(), 1);
      const std::string config = dir_ + "/mocapd.toml", state = state_dir(), sock = socket();
      std::vector<std::string> args = wrapper_;
      for (const std::string& a : {executable_, std::string("--config"), config,
                                   std::string("--state-dir"), state, std::string("--socket"), sock})
        args.push_back(a);
      for (const std::string& d : export_dirs_) args.insert(args.end(), {"--export-dir", d});
      std::vector<char*> argv;
      for (std::string& a : args) argv.push_back(a.data());
      argv.push_back(nullptr);
      execvp(argv[0], argv.data());
      _exit(127);
    }
    const auto until = std::chrono::steady_clock::now() + std::chrono::duration<double>(timeout_s);
    while (std::chrono::steady_clock::now() < until) {
      int status = 0;
      if (waitpid(pid_, &status, WNOHANG) == pid_) {
        pid_ = -1;
        return Status::Error("mocapd exited during start-up (status " + std::to_string(status) +
                             "); log:\n" + Log());
      }
      std::unique_ptr<daemon::ControlClient> c;
      daemon::ControlClientOptions o;
      o.socket_path = socket();
      if (daemon::ControlClient::Connect(o, &c)) return Status::Ok();
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
    return Status::Error("mocapd did not answer within " + std::to_string(timeout_s) +
                         " s; log:\n" + Log());
  }

  Status Connect(std::unique_ptr<daemon::ControlClient>* out, int timeout_ms = 300000) const {
    daemon::ControlClientOptions o;
    o.socket_path = socket();
    o.reply_timeout_ms = timeout_ms;
    return daemon::ControlClient::Connect(o, out);
  }

  // SIGTERM and wait (up to timeout_s); the exit status, or -1 when it had to be killed.
  int Stop(double timeout_s = 20) {
    if (pid_ <= 0) return -1;
    kill(pid_, SIGTERM);
    const auto until = std::chrono::steady_clock::now() + std::chrono::duration<double>(timeout_s);
    while (std::chrono::steady_clock::now() < until) {
      int status = 0;
      if (waitpid(pid_, &status, WNOHANG) == pid_) {
        pid_ = -1;
        return WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    Kill(SIGKILL);
    return -1;
  }
  void Kill(int sig) {
    if (pid_ <= 0) return;
    kill(pid_, sig);
    int status = 0;
    waitpid(pid_, &status, 0);
    pid_ = -1;
  }
  bool running() const { return pid_ > 0 && kill(pid_, 0) == 0; }
  pid_t pid() const { return pid_; }

  // The whole log, to search (a tail missed a line followed by ~900 lines of clients that
  // reset their connections: DaemonFaults.MisbehavingClientsCannotStopTheRig, 28 Nov 2026).
  std::string Log() const {
    std::ifstream f(log_path());
    return std::string((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  }
  // Its last 20,000 characters, to print with a failure.
  std::string LogTail() const {
    const std::string s = Log();
    return s.size() > 20000 ? "..." + s.substr(s.size() - 20000) : s;
  }

 private:
  std::string dir_;
  std::string executable_;
  std::vector<std::string> wrapper_;
  std::vector<std::string> export_dirs_;
  std::vector<std::pair<std::string, std::string>> env_;
  pid_t pid_ = -1;
};

// The start of every session on a simulated rig, as an operator does it: wave the wand for
// `wand_seconds`, calibrate, apply, create the subject at the virtual subject's height and select
// it; then give the tracker `settle_seconds` to find the subject. Errors name the request.
inline Status CalibrateRigAndSelectSubject(daemon::ControlClient* c, double wand_seconds,
                                           const std::string& subject, double settle_seconds = 2) {
  auto call = [&](const std::string& method, const nlohmann::json& params,
                  nlohmann::json* result) -> Status {
    daemon::ControlReply r;
    MOCAP_RETURN_IF_ERROR(c->Call(method, params, &r));
    if (!r.ok()) return Status::Error(method + ": " + r.error_code + ": " + r.error_message);
    if (result) *result = r.result;
    return Status::Ok();
  };
  nlohmann::json status;
  MOCAP_RETURN_IF_ERROR(call("rig.calibrate.start", {{"seconds", wand_seconds}}, nullptr));
  std::this_thread::sleep_for(std::chrono::duration<double>(wand_seconds));
  MOCAP_RETURN_IF_ERROR(call("rig.calibrate.finish", nlohmann::json::object(), nullptr));
  MOCAP_RETURN_IF_ERROR(call("rig.calibrate.apply", nlohmann::json::object(), nullptr));
  MOCAP_RETURN_IF_ERROR(call("status", nlohmann::json::object(), &status));
  const double height = status["rig"]["virtual_subject"]["height_m"];
  MOCAP_RETURN_IF_ERROR(call("subject.create", {{"name", subject}, {"height_m", height}}, nullptr));
  MOCAP_RETURN_IF_ERROR(call("subject.select", {{"name", subject}}, nullptr));
  std::this_thread::sleep_for(std::chrono::duration<double>(settle_seconds));
  return Status::Ok();
}

// The benches' start (bench/daemon_latency.cpp, bench/soak.cpp): starts `d`, connects `c` (reply
// timeout `timeout_ms`) and calibrates the rig and selects subject `subject` on it, saying so on
// stderr as `who`. Errors name the step.
inline Status StartCalibratedSession(DaemonProcess* d, std::unique_ptr<daemon::ControlClient>* c,
                                     const std::string& who, const std::string& subject,
                                     int timeout_ms = 300000) {
  MOCAP_RETURN_IF_ERROR(d->Start());
  MOCAP_RETURN_IF_ERROR(d->Connect(c, timeout_ms));
  std::fprintf(stderr, "%s: calibrating the rig, creating the subject...\n", who.c_str());
  return CalibrateRigAndSelectSubject(c->get(), 12, subject, 3);
}

// The service manager's end of NOTIFY_SOCKET, for the STATUS= lines mocapd sends.
class NotifySocket {
 public:
  explicit NotifySocket(const std::string& path) : path_(path) {
    fd_ = socket(AF_UNIX, SOCK_DGRAM | SOCK_CLOEXEC, 0);
    sockaddr_un a{};
    a.sun_family = AF_UNIX;
    std::snprintf(a.sun_path, sizeof a.sun_path, "%s", path.c_str());
    bound_ = fd_ >= 0 && bind(fd_, reinterpret_cast<sockaddr*>(&a), sizeof a) == 0;
  }
  ~NotifySocket() {
    if (fd_ >= 0) close(fd_);
    unlink(path_.c_str());
  }
  bool bound() const { return bound_; }
  // The first STATUS= line containing `text` within `timeout_s`, or "".
  std::string WaitForStatus(const std::string& text, double timeout_s) {
    const auto until = std::chrono::steady_clock::now() + std::chrono::duration<double>(timeout_s);
    char buf[4096];
    while (std::chrono::steady_clock::now() < until) {
      pollfd p{fd_, POLLIN, 0};
      if (poll(&p, 1, 50) <= 0) continue;
      const ssize_t n = recv(fd_, buf, sizeof buf, 0);
      if (n <= 0) continue;
      const std::string message(buf, static_cast<std::size_t>(n));
      const std::size_t at = message.find("STATUS=");
      if (at == std::string::npos) continue;
      const std::string line = message.substr(at, message.find('\n', at) - at);
      if (line.find(text) != std::string::npos) return line;
    }
    return "";
  }

 private:
  std::string path_;
  int fd_ = -1;
  bool bound_ = false;
};

}  // namespace mocap::testing
