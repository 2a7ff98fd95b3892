// libFuzzer target for mocapd's request dispatch (daemon/daemon.cpp): the input is what one
// client sends on the control socket, handled by a real Daemon in this process -- its control
// server, its dispatch into every method, its store (SQLite in a temporary state directory) and
// its jobs -- on a simulated rig cut down to what the dispatch needs at the pipeline boundary:
// two cameras of 64 x 48 pixels at 50 Hz (daemon/config.h; sim/live_rig.h), calibrated from the
// start (their true poses, stored as calibration 1), so that the pipeline costs next to nothing
// and yet every method's path is reachable (record.start needs a calibrated rig; sim.camera and
// the virtual subject need a simulated one). The fuzzer's thread is both the client and the
// daemon's loop (Daemon::RunOnce), as tests/control_server_test_util.h drives the server alone.
//
// Whatever the bytes, the daemon must not crash, leak or hit undefined behaviour (ASan/UBSan),
// and it must answer EVERY request line exactly once, with a result or a documented error code
// (never `internal`: that is an exception a method's checks missed), in valid JSON
// (fuzz/control_replies.h) -- long methods too: what the input leaves running (a recording, a
// wand collection, a fit) is stopped by a second client, the operator, as one would
// (record.stop, rig.calibrate.cancel, fit.cancel), and its reply must then come within 8 s.
// `shutdown` stops the daemon: the replies still owed are then lost with the connection (the
// daemon stops), and the next input finds a new daemon started on the same state directory, as
// systemd would restart it -- which must succeed.
//
// fuzz/seeds/daemon/ holds one session of every method; fuzz/daemon.dict the method and
// parameter names, so that mutations reach each method's parameters.
#include <grp.h>
#include <unistd.h>

#include <spdlog/spdlog.h>

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <memory>
#include <set>
#include <string>
#include <string_view>

#include "daemon/config.h"
#include "daemon/daemon.h"
#include "daemon/store.h"
#include "fuzz/control_replies.h"
#include "reconstruction/calibration_file.h"
#include "sim/live_rig.h"
#include "tests/control_server_test_util.h"

namespace {

namespace md = mocap::daemon;
using mocap::fuzz::Check;
using Clock = std::chrono::steady_clock;

constexpr std::size_t kMaxLineBytes = 4096;  // small, so that the fuzzer reaches the limit
constexpr int kCameras = 2, kWidth = 64, kHeight = 48, kRateHz = 50;
// An operator's stop, cancel or the end of a job answers within this, or the input is a hang.
constexpr std::chrono::milliseconds kAnswerDeadline{8000};  // below fuzz.sh's -timeout=10
// The input's requests that are still unanswered this long after the last reply are long ones
// left running: the operator stops them.
constexpr std::chrono::milliseconds kQuietBeforeStop{30};

// Every documented error code but `internal` (daemon/PROTOCOL.md).
const std::set<std::string>& AllowedCodes() {
  static const std::set<std::string> codes = {
      "parse_error", "invalid_request", "line_too_long", "unknown_method", "invalid_params",
      "forbidden",   "not_found",       "conflict",      "busy",           "unavailable",
      "failed",      "cancelled"};
  return codes;
}

class DaemonHarness {
 public:
  DaemonHarness() {
    spdlog::set_level(spdlog::level::off);  // the daemon's log: thousands of lines a second
    std::string pattern = (std::filesystem::temp_directory_path() / "mocap-fuzz-daemon-XXXXXX").string();
    Check(mkdtemp(pattern.data()) != nullptr, "mkdtemp");
    dir_ = pattern;
    std::filesystem::create_directories(dir_ + "/exports");
    // The control group: the fuzzer's own, so that both clients may change state as root may.
    const group* g = getgrgid(getgid());
    Check(g != nullptr, "the fuzzer's group has no name");
    std::ofstream(dir_ + "/mocapd.toml")
        << "[rig]\nsimulated = " << kCameras << "\nsubject_seed = 1\nrate = " << kRateHz
        << "\nwidth = " << kWidth << "\nheight = " << kHeight
        << "\ndetection_threads = 1\n[storage]\nstate_dir = \"" << dir_ << "/state\"\nexport_dirs = [\""
        << dir_ << "/exports\"]\n[control]\nsocket = \"" << dir_ << "/control.sock\"\ngroup = \""
        << g->gr_name << "\"\nmax_line_bytes = " << kMaxLineBytes << "\n[fit]\nthreads = 1\n";
    StoreTrueCalibration();
    Start();
  }
  ~DaemonHarness() {
    daemon_.reset();
    std::filesystem::remove_all(dir_);
  }

  // One client sends `input` and stays until every request line is answered (or the connection
  // ends); returns what it read.
  std::string Exchange(std::string_view input) {
    const int restarts = restarts_;
    mocap::testing::LoopClient client(socket_path());
    Check(client.connected(), "cannot connect to the daemon");
    client.Send(input);
    const mocap::fuzz::ExpectedReplies expected = mocap::fuzz::Expected(input, kMaxLineBytes);
    std::unique_ptr<mocap::testing::LoopClient> operator_client;
    int answers = -1;
    Clock::time_point last_answer = Clock::now();
    const Clock::time_point deadline = last_answer + kAnswerDeadline;
    for (;;) {
      client.Step([this] { return Turn(); });
      if (operator_client) operator_client->Step([this] { return Turn(); });
      if (client.closed() || restarts_ != restarts) break;
      const mocap::fuzz::Replies got =
          mocap::fuzz::ParseReplies(client.received(), AllowedCodes(), /*events=*/true);
      if (got.answers != answers) answers = got.answers, last_answer = Clock::now();
      if (client.all_sent() && answers >= expected.answers) break;
      const Clock::time_point now = Clock::now();
      if (!operator_client && client.all_sent() &&
          now - last_answer > kQuietBeforeStop)
        operator_client = StopWhatRuns();
      Check(now < deadline, "requests unanswered within 8 s");
    }
    std::string got = client.received();
    client.Close();
    // Whatever the input left running stops before the next one (it would refuse its
    // record.start, rig.calibrate.start or fit.start otherwise).
    if (restarts_ == restarts) Settle(StopWhatRuns());
    return got;
  }

  bool restarted_since(int restarts) const { return restarts_ != restarts; }
  int restarts() const { return restarts_; }

 private:
  std::string socket_path() const { return dir_ + "/control.sock"; }

  // The rig's true cameras as calibration 1 in the store (the daemon starts with the newest).
  void StoreTrueCalibration() {
    mocap::sim::LiveRigOptions ro;
    ro.cameras = kCameras;
    ro.width = kWidth;
    ro.height = kHeight;
    ro.rate_hz = kRateHz;
    ro.seed = 1;
    std::unique_ptr<mocap::sim::LiveRig> rig;
    Check(mocap::sim::LiveRig::Create(ro, &rig).ok(), "sim::LiveRig::Create");
    mocap::reconstruction::CalibrationFile file;
    for (const auto& c : rig->true_cameras()) file.cameras.push_back({c});
    std::unique_ptr<md::Store> store;
    Check(md::Store::Open(dir_ + "/state", &store).ok(), "Store::Open");
    std::int64_t version = 0;
    Check(store->AddCalibration(mocap::reconstruction::CalibrationJsonString(file), 0, 0,
                                "fuzz_daemon: the simulated rig's truth", &version)
              .ok(),
          "Store::AddCalibration");
  }

  void Start() {
    md::DaemonConfig config;
    const mocap::Status loaded = md::LoadConfig(dir_ + "/mocapd.toml", &config);
    if (!loaded) std::fprintf(stderr, "%s\n", loaded.message().c_str());
    Check(loaded.ok(), "the fuzzer's mocapd.toml does not load");
    md::DaemonOptions options;
    options.config_path = dir_ + "/mocapd.toml";
    daemon_ = std::make_unique<md::Daemon>(config, options);
    const mocap::Status started = daemon_->Start();
    if (!started) std::fprintf(stderr, "mocapd start: %s\n", started.message().c_str());
    Check(started.ok(), "mocapd does not start (again) on its state directory");
  }

  // One turn of the daemon's loop; after a `shutdown`, a new daemon on the same state.
  bool Turn() {
    if (daemon_->RunOnce(1000)) return true;
    daemon_->Stop();
    daemon_.reset();
    Start();
    ++restarts_;
    return true;
  }

  // The operator stops what may be running; each request is answered (conflict when nothing
  // of its kind ran).
  std::unique_ptr<mocap::testing::LoopClient> StopWhatRuns() {
    auto c = std::make_unique<mocap::testing::LoopClient>(socket_path());
    Check(c->connected(), "the operator cannot connect");
    c->Send(R"({"id":1,"method":"record.stop"})" "\n"
            R"({"id":2,"method":"rig.calibrate.cancel"})" "\n"
            R"({"id":3,"method":"fit.cancel"})" "\n");
    return c;
  }
  // Waits until the operator's requests are answered.
  void Settle(std::unique_ptr<mocap::testing::LoopClient> c) {
    const int restarts = restarts_;
    const Clock::time_point deadline = Clock::now() + kAnswerDeadline;
    while (!c->closed() && restarts_ == restarts) {
      c->Step([this] { return Turn(); });
      if (mocap::fuzz::ParseReplies(c->received(), AllowedCodes(), true).answers == 3) return;
      Check(Clock::now() < deadline, "the operator's stop unanswered within 8 s");
    }
  }

  std::string dir_;
  std::unique_ptr<md::Daemon> daemon_;
  int restarts_ = 0;
};

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  static DaemonHarness* harness = [] {
    // Stopped at exit, before the statics its threads use are destroyed (libFuzzer ends with
    // exit(); the handler registered last runs first).
    static DaemonHarness* h = new DaemonHarness();
    std::atexit([] { delete h; });
    return h;
  }();
  const std::string_view input(reinterpret_cast<const char*>(data), size);
  const int restarts = harness->restarts();
  const Clock::time_point t0 = Clock::now();
  const std::string output = harness->Exchange(input);
  static const bool print = std::getenv("MOCAP_FUZZ_PRINT") != nullptr;  // to read an input's run
  if (print)
    std::fprintf(stderr, "%s(%.0f ms)\n", output.c_str(),
                 std::chrono::duration<double, std::milli>(Clock::now() - t0).count());
  const mocap::fuzz::Replies got =
      mocap::fuzz::ParseReplies(output, AllowedCodes(), /*events=*/true);
  const mocap::fuzz::ExpectedReplies expected = mocap::fuzz::Expected(input, kMaxLineBytes);
  if (harness->restarted_since(restarts)) {
    // `shutdown`: the daemon stopped and the replies it owed went with the connection.
    Check(got.answers <= expected.answers, "more replies than requests");
    return 0;
  }
  Check(got.answers == expected.answers, "not every request line answered exactly once");
  Check(got.ended_too_long == expected.too_long,
        "line_too_long where no line was too long, or none where one was");
  return 0;
}
