// mocapd under systemd (daemon/service_notify.h, daemon/startup_checks.h, systemd/): the real
// mocapd executable started the way mocapd.socket starts it (systemd-socket-activate on a
// temporary socket), talking sd_notify to a datagram socket this test owns as the service
// manager would; the start-up errors; the units checked by systemd-analyze; the .deb.
//
// A two-camera simulated rig at 640x512 keeps the daemon's start-up to about half a second.
#include <poll.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/un.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <mutex>
#include <regex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

#include "daemon/rig_setup.h"
#include "daemon/service_notify.h"
#include "drivers/aravis_fake.h"
#include "daemon/startup_checks.h"
#include "tests/daemon_test_util.h"

namespace mocap {
namespace {

using daemon::PipelineProgress;
using daemon::ServiceSnapshot;
using nlohmann::json;
using Clock = std::chrono::steady_clock;

double SecondsSince(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

// The service manager's end of NOTIFY_SOCKET: every datagram, split into its lines, with the
// time it arrived.
class NotifyListener {
 public:
  struct Message {
    double t = 0;  // seconds since the listener started
    std::string text;
  };
  explicit NotifyListener(const std::string& path) : path_(path), t0_(Clock::now()) {
    fd_ = socket(AF_UNIX, SOCK_DGRAM | SOCK_CLOEXEC, 0);
    sockaddr_un a{};
    a.sun_family = AF_UNIX;
    std::snprintf(a.sun_path, sizeof a.sun_path, "%s", path.c_str());
    bound_ = fd_ >= 0 && bind(fd_, reinterpret_cast<sockaddr*>(&a), sizeof a) == 0;
    thread_ = std::thread([this] { Run(); });
  }
  ~NotifyListener() {
    stop_ = true;
    thread_.join();
    if (fd_ >= 0) close(fd_);
    unlink(path_.c_str());
  }
  bool bound() const { return bound_; }
  double Now() const { return SecondsSince(t0_); }
  std::vector<Message> Messages() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return messages_;
  }
  // The first message at or after `from` (seconds) containing `line` as one of its lines, waiting
  // up to `timeout_s`; its index or -1.
  int WaitFor(const std::string& line, double timeout_s, double from = 0) const {
    const auto until = Clock::now() + std::chrono::duration<double>(timeout_s);
    do {
      const std::vector<Message> m = Messages();
      for (std::size_t i = 0; i < m.size(); ++i)
        if (m[i].t >= from && HasLine(m[i].text, line)) return static_cast<int>(i);
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    } while (Clock::now() < until);
    return -1;
  }
  static bool HasLine(const std::string& text, const std::string& line) {
    std::istringstream in(text);
    for (std::string l; std::getline(in, l);)
      if (l == line || (line.back() == '=' && l.rfind(line, 0) == 0)) return true;
    return false;
  }
  static std::string Field(const std::string& text, const std::string& key) {
    std::istringstream in(text);
    for (std::string l; std::getline(in, l);)
      if (l.rfind(key + "=", 0) == 0) return l.substr(key.size() + 1);
    return "";
  }
  // Times of WATCHDOG=1 within [from, to).
  std::vector<double> Pings(double from, double to) const {
    std::vector<double> t;
    for (const Message& m : Messages())
      if (m.t >= from && m.t < to && HasLine(m.text, "WATCHDOG=1")) t.push_back(m.t);
    return t;
  }

 private:
  void Run() {
    char buf[4096];
    while (!stop_) {
      pollfd p{fd_, POLLIN, 0};
      if (poll(&p, 1, 20) <= 0) continue;
      const ssize_t n = recv(fd_, buf, sizeof buf, 0);
      if (n <= 0) continue;
      std::lock_guard<std::mutex> lock(mutex_);
      messages_.push_back({Now(), std::string(buf, n)});
    }
  }
  std::string path_;
  Clock::time_point t0_;
  int fd_ = -1;
  bool bound_ = false;
  std::atomic<bool> stop_{false};
  mutable std::mutex mutex_;
  std::vector<Message> messages_;
  std::thread thread_;
};

std::string SmallRigToml() {
  return testing::SimulatedRigToml(2, 5, "width = 640\nheight = 512\n");
}

std::string ReadAll(const std::string& path) {
  std::ifstream f(path);
  return std::string((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
}

// Waits for `pid` up to `timeout_s`: its exit code, 128 + signal, or -1 (still running).
int WaitExit(pid_t pid, double timeout_s) {
  const auto until = Clock::now() + std::chrono::duration<double>(timeout_s);
  while (Clock::now() < until) {
    int status = 0;
    if (waitpid(pid, &status, WNOHANG) == pid)
      return WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  return -1;
}

// ---------------------------------------------------------------------------------------------
// The decisions, without a service manager.

// The rig's cameras at start: an absent camera and one that refuses a setting are awaited (the
// rig starts degraded) unless fewer than min_cameras open; the exit code tells a configuration
// (every missing camera answered and refused: no restart cures it) from an absence.
TEST(RigCameras, MissingCamerasAreAwaitedUnlessFewerThanTheMinimumOpen) {
  drivers::FakeRigOptions fo;
  fo.cameras = 3;
  fo.width = 64;
  fo.height = 48;
  fo.serial_prefix = "DEGRADED";
  drivers::AravisFakeRig fakes(fo, [](int, std::uint64_t, std::uint8_t*, int, int, std::ptrdiff_t,
                                         drivers::PixelFormat) {});
  auto make = [&] {
    std::vector<std::unique_ptr<drivers::AravisCamera>> cams;
    for (int i = 0; i < 3; ++i) cams.push_back(fakes.MakeCamera(i));
    return cams;
  };
  drivers::CameraSettings good;
  good.frame_rate_hz = 50;
  good.timeout_ms = 100;
  drivers::CameraSettings refused = good;
  refused.pixel_format = drivers::PixelFormat::kMono12Packed;  // the fakes do not offer it

  // Camera 0 refuses its pixel format, camera 2 is unplugged: one opens.
  fakes.SetPresent(2, false);
  {
    auto cams = make();
    std::vector<drivers::AravisCamera*> p{cams[0].get(), cams[1].get(), cams[2].get()};
    std::vector<daemon::MissingCamera> missing;
    int code = -1;
    Status st = daemon::OpenRigCameras(p, {refused, good, good}, 2, &missing, &code);
    ASSERT_FALSE(st.ok());
    EXPECT_EQ(code, daemon::kExitUnavailable);  // camera 2 may come back
    EXPECT_NE(st.message().find("1 of 3 cameras opened, fewer than min_cameras = 2"), std::string::npos)
        << st.message();
    EXPECT_NE(st.message().find("Mono12Packed"), std::string::npos) << st.message();
    EXPECT_NE(st.message().find("DEGRADED2"), std::string::npos) << st.message();
    ASSERT_EQ(missing.size(), 2u);
    EXPECT_EQ(missing[0].index, 0);
    EXPECT_TRUE(missing[0].device_found);
    EXPECT_EQ(missing[1].index, 2);
    EXPECT_FALSE(missing[1].device_found);

    // With one camera enough: a degraded start. The absent camera, started, streams once it
    // is plugged in.
    st = daemon::OpenRigCameras(p, {refused, good, good}, 1, &missing, &code);
    ASSERT_TRUE(st.ok()) << st.message();
    EXPECT_EQ(code, 0);
    ASSERT_EQ(missing.size(), 2u);
    ASSERT_TRUE(cams[2]->Start().ok());
    EXPECT_EQ(cams[2]->State(), drivers::CameraState::kLost);
    EXPECT_NE(cams[2]->LastError().find("device not found"), std::string::npos) << cams[2]->LastError();
    drivers::Frame f;
    EXPECT_EQ(cams[2]->Grab(&f), drivers::GrabResult::kLost);
    fakes.SetPresent(2, true);
    bool got = false;
    for (int i = 0; i < 200 && !got; ++i) {
      if (cams[2]->Grab(&f) == drivers::GrabResult::kFrame) {
        got = true;
        EXPECT_EQ(f.image.width, 64);
        cams[2]->Release(f);
      }
    }
    EXPECT_TRUE(got) << cams[2]->LastError();
    EXPECT_EQ(cams[2]->State(), drivers::CameraState::kStreaming);
    EXPECT_EQ(cams[2]->LastError(), "");
    cams[2]->Stop();
  }

  // Only refusals short of the minimum: a configuration error, which no restart cures.
  {
    auto cams = make();
    std::vector<drivers::AravisCamera*> p{cams[0].get(), cams[1].get(), cams[2].get()};
    std::vector<daemon::MissingCamera> missing;
    int code = -1;
    const Status st = daemon::OpenRigCameras(p, {refused, good, good}, 3, &missing, &code);
    ASSERT_FALSE(st.ok());
    EXPECT_EQ(code, daemon::kExitConfig) << st.message();
  }
}

TEST(ServiceStatus, OneLineSummary) {
  ServiceSnapshot s;
  s.cameras = 8;
  s.progress.cameras_streaming = 8;
  s.rate_hz = 200;
  s.rig_live = true;
  EXPECT_EQ(daemon::StatusLine(s), "8/8 cameras 200 Hz, idle");
  s.subject = "S012";
  s.model_version = 3;
  s.recording = "squats";
  EXPECT_EQ(daemon::StatusLine(s), "8/8 cameras 200 Hz, tracking subject S012 (model v3), recording squats");
  s.progress.cameras_streaming = 6;
  s.missing_cameras = {"cam3", "cam7"};
  s.recording.clear();
  s.job = "fit";
  EXPECT_EQ(daemon::StatusLine(s),
            "degraded: 6/8 cameras 200 Hz (missing cam3, cam7), tracking subject S012 (model v3), fitting");
  s.suspect_calibration = {"cam5"};  // daemon/detection_health.h
  EXPECT_EQ(daemon::StatusLine(s), "degraded: 6/8 cameras 200 Hz (missing cam3, cam7) (calibration off: cam5), "
                                   "tracking subject S012 (model v3), fitting");
  // A camera that says it streams and delivers nothing while the others do (a pulled GigE
  // cable before Aravis's heartbeat gives up): degraded at once, named.
  s.missing_cameras.clear();
  s.suspect_calibration.clear();
  s.silent_cameras = {"GV01"};
  s.progress.cameras_streaming = 7;
  EXPECT_EQ(daemon::StatusLine(s), "degraded: 7/8 cameras 200 Hz (no frames from GV01), "
                                   "tracking subject S012 (model v3), fitting");
  s = {};
  s.cameras = 2;
  s.rate_hz = 100;
  s.simulated = true;
  s.missing_cameras = {"a", "b"};
  EXPECT_EQ(daemon::StatusLine(s), "starting: 0/2 simulated cameras 100 Hz (missing a, b), idle");
  EXPECT_EQ(daemon::StatusLine(s, true),
            "degraded: no frame set yet: 0/2 simulated cameras 100 Hz (missing a, b), idle");
}

TEST(ServiceWatchdog, AStageIsHungWhenItsInputMovedAndItsOutputDidNot) {
  // {grabbed, dropped, detected, sets, tracked, cameras streaming}
  const PipelineProgress a{100, 0, 100, 50, 50, 2};
  PipelineProgress b{200, 0, 200, 100, 100, 2};
  EXPECT_EQ(daemon::StalledStage(a, b), "");
  b = {100, 0, 100, 50, 50, 2};  // cameras say they stream, no frame came, nothing waits
  EXPECT_EQ(daemon::StalledStage(a, b), "grab");
  b = {200, 0, 100, 50, 50, 2};
  EXPECT_EQ(daemon::StalledStage(a, b), "detection");
  // Detection held long enough that the cameras' buffers all wait in its queue: the grab stops
  // too, and detection, with work waiting, is the stage named.
  const PipelineProgress held{164, 0, 100, 50, 50, 2};
  EXPECT_EQ(daemon::StalledStage(held, held), "detection");
  // Frames dropped at the full queue are not waiting.
  EXPECT_EQ(daemon::StalledStage(PipelineProgress{164, 64, 100, 50, 50, 0},
                                 PipelineProgress{164, 64, 100, 50, 50, 0}), "");
  b = {200, 0, 200, 50, 50, 2};
  EXPECT_EQ(daemon::StalledStage(a, b), "sync");
  b = {200, 0, 200, 100, 50, 2};
  EXPECT_EQ(daemon::StalledStage(a, b), "tracking");
  const PipelineProgress idle{100, 0, 100, 50, 50, 0};
  EXPECT_EQ(daemon::StalledStage(idle, idle), "");
}

// The notifier in this process, its NOTIFY_SOCKET this test's.
class ServiceNotifier : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(listener_.bound());
    setenv("NOTIFY_SOCKET", path_.c_str(), 1);
  }
  void TearDown() override { unsetenv("NOTIFY_SOCKET"); }
  // What arrived (after the datagrams in flight).
  std::vector<NotifyListener::Message> Received() {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    return listener_.Messages();
  }

 private:
  std::string path_ = testing::MakeTempDir("mocapd-notifier") + "/notify";
  NotifyListener listener_{path_};
};

TEST_F(ServiceNotifier, ReadyOnceLiveStatusOnChangePingsOnlyWhileHealthy) {
  daemon::ServiceNotifierOptions o;
  o.watchdog_usec = 1000000;  // check every 0.5 s
  o.no_frames_timeout_s = 5;
  daemon::ServiceNotifier n(o);
  const std::uint64_t s0 = 1000000000000ull, ms = 1000000;
  n.Started(s0);
  ServiceSnapshot s;
  s.cameras = 2;
  s.rate_hz = 200;
  s.progress.cameras_streaming = 2;
  n.Tick(s, s0 + 100 * ms);  // not live yet
  EXPECT_FALSE(n.ready());
  s.rig_live = true;
  s.progress = {400, 0, 400, 200, 190, 2};
  n.Tick(s, s0 + 200 * ms);
  EXPECT_TRUE(n.ready());
  n.Tick(s, s0 + 300 * ms);  // same line: no STATUS
  s.progress = {600, 0, 600, 300, 290, 2};
  n.Tick(s, s0 + 600 * ms);  // first check: baseline, ping
  s.progress = {800, 0, 800, 400, 390, 2};
  n.Tick(s, s0 + 1100 * ms);  // progressed: ping
  EXPECT_EQ(n.pings(), 2u);
  s.progress = {1000, 0, 800, 400, 390, 2};  // detection held
  EXPECT_TRUE(n.Tick(s, s0 + 1600 * ms));
  EXPECT_EQ(n.stalled(), "detection");
  EXPECT_EQ(n.pings(), 2u);
  s.progress = {1200, 0, 1200, 500, 490, 2};
  EXPECT_TRUE(n.Tick(s, s0 + 2100 * ms));
  EXPECT_EQ(n.stalled(), "");
  EXPECT_EQ(n.pings(), 3u);
  {
    daemon::ReloadNotice reload(&n);
  }
  n.Stopping();
  std::vector<std::string> got;
  for (const auto& m : Received()) got.push_back(m.text);
  ASSERT_EQ(got.size(), 9u);
  EXPECT_EQ(got[0], "STATUS=starting: waiting for the cameras' first frame sets");
  EXPECT_EQ(got[1], "STATUS=starting: 2/2 cameras 200 Hz, idle");
  EXPECT_EQ(got[2], "READY=1\nSTATUS=2/2 cameras 200 Hz, idle");
  EXPECT_EQ(got[3], "WATCHDOG=1");
  EXPECT_EQ(got[4], "WATCHDOG=1");
  EXPECT_EQ(got[5], "WATCHDOG=1");  // after the hold: the ping at 2.1 s, none at 1.6 s
  EXPECT_TRUE(std::regex_match(got[6], std::regex("RELOADING=1\nMONOTONIC_USEC=[0-9]+\nSTATUS=.*")))
      << got[6];
  EXPECT_EQ(got[7], "READY=1\nSTATUS=2/2 cameras 200 Hz, idle");
  EXPECT_EQ(got[8], "STOPPING=1\nSTATUS=stopping");
}

// A rig of which no camera ever streams does not hold start-up hostage: READY after the
// timeout, degraded, the cameras named; and no watchdog hang (nothing to process).
TEST_F(ServiceNotifier, NoFrameSetWithinTheTimeoutIsReadyDegraded) {
  daemon::ServiceNotifierOptions o;
  o.watchdog_usec = 2000000;
  o.no_frames_timeout_s = 15;
  daemon::ServiceNotifier n(o);
  const std::uint64_t s0 = 5000000000ull, s = 1000000000;
  n.Started(s0);
  ServiceSnapshot snap;
  snap.cameras = 2;
  snap.rate_hz = 200;
  snap.missing_cameras = {"Basler-1", "Basler-2"};
  for (std::uint64_t t = 1; t < 15; ++t) n.Tick(snap, s0 + t * s);
  EXPECT_FALSE(n.ready());
  n.Tick(snap, s0 + 15 * s);
  EXPECT_TRUE(n.ready());
  for (std::uint64_t t = 16; t < 20; ++t) n.Tick(snap, s0 + t * s);
  int ready = 0;
  for (const auto& m : Received()) {
    if (!NotifyListener::HasLine(m.text, "READY=1")) continue;
    ++ready;
    EXPECT_EQ(NotifyListener::Field(m.text, "STATUS"),
              "degraded: no frame set yet: 0/2 cameras 200 Hz (missing Basler-1, Basler-2), idle");
  }
  EXPECT_EQ(ready, 1);
  EXPECT_EQ(n.pings(), 19u);  // every check (1 s apart), none withheld: an idle rig is not hung
  EXPECT_EQ(n.stalled(), "");
}

// ---------------------------------------------------------------------------------------------
// The real mocapd, socket-activated, with a NOTIFY_SOCKET and a watchdog.

// Starts mocapd as mocapd.socket would (systemd-socket-activate: the socket is made first and
// mocapd is executed with it when the first client connects), with NOTIFY_SOCKET = DIR/notify,
// a watchdog of 1 s and the test hook holding `hold_stage` while DIR/hold exists. The pid is
// mocapd's (exec keeps it).
pid_t StartSocketActivated(const std::string& dir, const std::string& hold_stage) {
  std::ofstream(dir + "/mocapd.toml") << SmallRigToml();
  const pid_t pid = fork();
  if (pid != 0) return pid;
  const int fd = open((dir + "/mocapd.log").c_str(), O_WRONLY | O_CREAT | O_APPEND, 0644);
  dup2(fd, STDERR_FILENO);
  dup2(fd, STDOUT_FILENO);
  // systemd-socket-activate passes on only the variables named with -E.
  const std::string e_notify = "NOTIFY_SOCKET=" + dir + "/notify";
  const std::string e_pid = "WATCHDOG_PID=" + std::to_string(getpid());
  const std::string e_file = "MOCAP_TEST_HOLD_FILE=" + dir + "/hold";
  const std::string e_stage = "MOCAP_TEST_HOLD_STAGE=" + hold_stage;
  const std::string config = dir + "/mocapd.toml", state = dir + "/state", sock = dir + "/control.sock";
  execlp("systemd-socket-activate", "systemd-socket-activate", "-l", sock.c_str(), "-E",
         e_notify.c_str(), "-E", "WATCHDOG_USEC=1000000", "-E", e_pid.c_str(), "-E",
         e_file.c_str(), "-E", e_stage.c_str(), MOCAPD_PATH, "--config", config.c_str(),
         "--state-dir", state.c_str(), "--socket", sock.c_str(), static_cast<char*>(nullptr));
  _exit(127);
}

// A failed assertion leaves no mocapd behind.
struct KillOnExit {
  pid_t pid;
  ~KillOnExit() {
    if (kill(pid, 0) == 0) kill(pid, SIGKILL), waitpid(pid, nullptr, 0);
  }
};

// Connects to the activation socket as soon as it listens (which starts mocapd); the connected
// descriptor or -1. systemd-socket-activate binds before it listens: refused in between.
int ConnectWhenListening(const std::string& sock) {
  sockaddr_un a{};
  a.sun_family = AF_UNIX;
  std::snprintf(a.sun_path, sizeof a.sun_path, "%s", sock.c_str());
  for (int i = 0; i < 500; ++i) {
    const int fd = socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0);
    if (connect(fd, reinterpret_cast<sockaddr*>(&a), sizeof a) == 0) return fd;
    close(fd);
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  return -1;
}

// Holds a stage (DIR/hold) for 2.5 s: at most the one ping whose window began before the hold,
// the log names the stage; let go, the pings come back.
void ExpectHoldStopsThePings(const NotifyListener& notify, const std::string& dir,
                             const std::string& stage) {
  const double hold0 = notify.Now();
  std::ofstream(dir + "/hold") << "held\n";
  std::this_thread::sleep_for(std::chrono::milliseconds(2500));
  const std::vector<double> during = notify.Pings(hold0, notify.Now());
  EXPECT_LE(during.size(), 1u) << stage;
  if (!during.empty()) {
    EXPECT_LT(during[0] - hold0, 0.7) << stage;
  }
  const std::string log = ReadAll(dir + "/mocapd.log");
  EXPECT_NE(log.find("watchdog: the " + stage + " stage made no progress"), std::string::npos) << log;
  const double release0 = notify.Now();
  unlink((dir + "/hold").c_str());
  EXPECT_GE(notify.WaitFor("WATCHDOG=1", 2.0, release0), 0) << stage << ": the pings did not come back";
}

TEST(MocapdUnderSystemd, ActivatedReadyStatusWatchdogReloadHangAndStop) {
  const std::string dir = testing::MakeTempDir("mocapd-systemd");
  ASSERT_FALSE(dir.empty());
  const std::string sock = dir + "/control.sock", log = dir + "/mocapd.log";
  NotifyListener notify(dir + "/notify");
  ASSERT_TRUE(notify.bound());

  const pid_t pid = StartSocketActivated(dir, "detection");
  ASSERT_GT(pid, 0);
  const KillOnExit reaper{pid};

  // The socket exists before mocapd runs; a client connecting now starts it (as mocapd.socket
  // does) and is served once the loop runs, before or after READY.
  const int fd = ConnectWhenListening(sock);
  ASSERT_GE(fd, 0) << strerror(errno);
  const double connected_at = notify.Now();
  EXPECT_TRUE(notify.Messages().empty()) << "mocapd talked to the manager before a client came";
  std::unique_ptr<daemon::ControlClient> client;
  daemon::ControlClientOptions co;
  co.reply_timeout_ms = 30000;
  ASSERT_TRUE(daemon::ControlClient::Adopt(fd, co, &client).ok()) << ReadAll(log);
  daemon::ControlReply status;
  ASSERT_TRUE(client->Call("status", json::object(), &status).ok());
  ASSERT_TRUE(status.ok()) << status.error_message;

  // READY=1 only once the rig streams: its warm-up of complete sets is behind it.
  const int ready = notify.WaitFor("READY=1", 20);
  ASSERT_GE(ready, 0) << ReadAll(log);
  const NotifyListener::Message ready_msg = notify.Messages()[ready];
  EXPECT_GT(ready_msg.t, connected_at);
  EXPECT_EQ(NotifyListener::Field(ready_msg.text, "STATUS"), "2/2 simulated cameras 200 Hz, idle");
  ASSERT_TRUE(client->Call("status", json::object(), &status).ok());
  EXPECT_GE(status.result["sets"]["warmup"].get<int>() + status.result["sets"]["total"].get<int>(), 20)
      << status.result.dump();
  const std::vector<NotifyListener::Message> before_ready = notify.Messages();
  for (int i = 0; i < ready; ++i) {
    EXPECT_FALSE(NotifyListener::HasLine(before_ready[i].text, "READY=1"));
    const std::string st = NotifyListener::Field(before_ready[i].text, "STATUS");
    if (!st.empty()) {
      EXPECT_EQ(st.rfind("starting: ", 0), 0u) << st;
    }
  }

  // STATUS follows the state: a subject selected.
  ASSERT_TRUE(client->Call("subject.create", {{"name", "S01"}, {"height_m", 1.75}}, &status).ok());
  ASSERT_TRUE(status.ok()) << status.error_message;
  ASSERT_TRUE(client->Call("subject.select", {{"name", "S01"}}, &status).ok());
  ASSERT_TRUE(status.ok()) << status.error_message;
  const int tracking = notify.WaitFor("STATUS=2/2 simulated cameras 200 Hz, tracking subject S01 (model v1)", 3);
  EXPECT_GE(tracking, 0);

  // WATCHDOG=1 every half interval (0.5 s at WATCHDOG_USEC = 1 s), never a gap of the interval.
  const double w0 = notify.Now();
  std::this_thread::sleep_for(std::chrono::milliseconds(3000));
  std::vector<double> pings = notify.Pings(w0, notify.Now());
  EXPECT_GE(pings.size(), 5u);
  EXPECT_LE(pings.size(), 7u);
  for (std::size_t i = 1; i < pings.size(); ++i) EXPECT_LT(pings[i] - pings[i - 1], 0.8);

  // SIGHUP: RELOADING=1 ... READY=1.
  const double h0 = notify.Now();
  kill(pid, SIGHUP);
  const int reloading = notify.WaitFor("RELOADING=1", 3, h0);
  ASSERT_GE(reloading, 0);
  EXPECT_FALSE(NotifyListener::Field(notify.Messages()[reloading].text, "MONOTONIC_USEC").empty());
  const int reloaded = notify.WaitFor("READY=1", 3, notify.Messages()[reloading].t);
  EXPECT_GT(reloaded, reloading);

  // The detection stage held: the pings stop within the interval, and come back once let go.
  ExpectHoldStopsThePings(notify, dir, "detection");

  // SIGTERM: STOPPING=1 and a clean exit.
  const double t0 = notify.Now();
  kill(pid, SIGTERM);
  const int code = WaitExit(pid, 20);
  EXPECT_EQ(code, 0) << ReadAll(log);
  EXPECT_GE(notify.WaitFor("STOPPING=1", 1, t0), 0);
  std::printf("READY %.2f s after the client connected; stopped in %.2f s\n",
              ready_msg.t - connected_at, notify.Now() - t0);
}

// The cameras stop delivering (the grab threads held, as a camera that still says it streams and
// sends nothing): the grab stage is hung, the pings stop.
TEST(MocapdUnderSystemd, CamerasThatStopDeliveringStopThePings) {
  const std::string dir = testing::MakeTempDir("mocapd-grabhang");
  ASSERT_FALSE(dir.empty());
  NotifyListener notify(dir + "/notify");
  ASSERT_TRUE(notify.bound());
  const pid_t pid = StartSocketActivated(dir, "grab");
  ASSERT_GT(pid, 0);
  const KillOnExit reaper{pid};
  const int fd = ConnectWhenListening(dir + "/control.sock");
  ASSERT_GE(fd, 0);
  ASSERT_GE(notify.WaitFor("READY=1", 20), 0) << ReadAll(dir + "/mocapd.log");
  ASSERT_GE(notify.WaitFor("WATCHDOG=1", 2, notify.Now()), 0);
  ExpectHoldStopsThePings(notify, dir, "grab");
  close(fd);
  kill(pid, SIGTERM);
  EXPECT_EQ(WaitExit(pid, 20), 0) << ReadAll(dir + "/mocapd.log");
}

// ---------------------------------------------------------------------------------------------
// Bad input at start-up: one error line naming the cause and the setting, the exit code.

struct StartResult {
  int code = -1;
  std::vector<std::string> errors;  // lines at error priority ("<3>")
  std::string log;
};

StartResult StartMocapd(const std::string& dir, const std::vector<std::string>& args,
                        const std::vector<std::pair<std::string, std::string>>& env = {}) {
  const std::string log = dir + "/start.log";
  unlink(log.c_str());
  const pid_t pid = fork();
  if (pid == 0) {
    for (const auto& [name, value] : env) setenv(name.c_str(), value.c_str(), 1);
    const int fd = open(log.c_str(), O_WRONLY | O_CREAT | O_APPEND, 0644);
    dup2(fd, STDERR_FILENO);
    dup2(fd, STDOUT_FILENO);
    std::vector<char*> argv{const_cast<char*>("mocapd")};
    for (const auto& a : args) argv.push_back(const_cast<char*>(a.c_str()));
    argv.push_back(nullptr);
    execv(MOCAPD_PATH, argv.data());
    _exit(127);
  }
  StartResult r;
  r.code = WaitExit(pid, 30);
  if (r.code < 0) kill(pid, SIGKILL), waitpid(pid, nullptr, 0);
  r.log = ReadAll(log);
  std::istringstream in(r.log);
  for (std::string l; std::getline(in, l);)
    if (l.rfind("<3>", 0) == 0) r.errors.push_back(l);
  return r;
}

TEST(MocapdUnderSystemd, BadInputAtStartUpNamesTheCauseAndExitsWithItsCode) {
  const std::string dir = testing::MakeTempDir("mocapd-badstart");
  ASSERT_FALSE(dir.empty());
  const std::string config = dir + "/mocapd.toml";
  std::ofstream(config) << SmallRigToml();
  std::ofstream(dir + "/plain") << "not a directory, not a socket\n";

  // A missing configuration file.
  StartResult r = StartMocapd(dir, {"--config", dir + "/absent.toml"});
  EXPECT_EQ(r.code, daemon::kExitConfig) << r.log;
  ASSERT_EQ(r.errors.size(), 1u) << r.log;
  EXPECT_NE(r.errors[0].find(dir + "/absent.toml: cannot read"), std::string::npos) << r.errors[0];

  // A storage directory that is a file, and one under a file (not accessible).
  r = StartMocapd(dir, {"--config", config, "--state-dir", dir + "/plain", "--socket", dir + "/c.sock"});
  EXPECT_EQ(r.code, daemon::kExitConfig) << r.log;
  ASSERT_EQ(r.errors.size(), 1u) << r.log;
  EXPECT_NE(r.errors[0].find("[storage] state_dir '" + dir + "/plain': exists and is not a directory"),
            std::string::npos) << r.errors[0];
  r = StartMocapd(dir, {"--config", config, "--state-dir", dir + "/plain/state", "--socket", dir + "/c.sock"});
  EXPECT_EQ(r.code, daemon::kExitNoPermission) << r.log;
  ASSERT_EQ(r.errors.size(), 1u) << r.log;
  EXPECT_NE(r.errors[0].find("[storage] state_dir '" + dir + "/plain/state': Not a directory"),
            std::string::npos) << r.errors[0];

  // A socket path that exists and is not a socket.
  r = StartMocapd(dir, {"--config", config, "--state-dir", dir + "/state", "--socket", dir + "/plain"});
  EXPECT_EQ(r.code, daemon::kExitConfig) << r.log;
  ASSERT_EQ(r.errors.size(), 1u) << r.log;
  EXPECT_NE(r.errors[0].find("[control] socket '" + dir + "/plain': exists and is not a socket"),
            std::string::npos) << r.errors[0];
  EXPECT_TRUE(std::filesystem::is_regular_file(dir + "/plain")) << "the file was removed";

  // A real rig whose camera is not there: unavailable (systemd retries; the camera may come back).
  // 50 Hz: the default 1280 x 1024 Mono8 at 100 Hz would not fit a GigE link, and the bandwidth
  // check (startup_checks.h) refuses that first, as a configuration error.
  const std::string real = dir + "/real.toml";
  std::ofstream(real) << "[rig]\nrate = 50\n[[rig.camera]]\nid = \"No-Such-Camera-0\"\n";
  r = StartMocapd(dir, {"--config", real, "--state-dir", dir + "/state", "--socket", dir + "/c.sock"});
  EXPECT_EQ(r.code, daemon::kExitUnavailable) << r.log;
  ASSERT_EQ(r.errors.size(), 1u) << r.log;
  EXPECT_NE(r.errors[0].find("camera 'No-Such-Camera-0'"), std::string::npos) << r.errors[0];
}

// A camera missing at start (unplugged): the rig starts without it, READY says "degraded" and
// names it, `status` says why; plugged in, it joins the rig without a restart and STATUS says
// so. With [rig] min_cameras above what opened, start-up fails naming the camera instead.
// A PTP rig (its fakes with the PTP features, drivers/aravis_fake.h): the missing camera is not
// judged while awaited (the rig starts locked, degraded), and once it appears it is PTP-enabled,
// scheduled and monitored like the others (daemon/ptp_monitor.h).
TEST(MocapdUnderSystemd, ACameraMissingAtStartIsADegradedStartAndJoinsWhenItAppears) {
  const std::string dir = testing::MakeTempDir("mocapd-degraded");
  ASSERT_FALSE(dir.empty());
  NotifyListener notify(dir + "/notify");
  ASSERT_TRUE(notify.bound());
  const std::string rig = testing::SimulatedRigToml(3, 5, "width = 640\nheight = 512\nsync = \"ptp\"\n");
  {
    testing::DaemonProcess d(dir, rig);
    d.SetEnvironment({{"NOTIFY_SOCKET", dir + "/notify"}, {"MOCAP_TEST_ABSENT_CAMERAS", "1"}});
    const Status started = d.Start();
    ASSERT_TRUE(started.ok()) << started.message();
    const int ready = notify.WaitFor("READY=1", 30);
    ASSERT_GE(ready, 0) << d.LogTail();
    std::unique_ptr<daemon::ControlClient> c;
    ASSERT_TRUE(d.Connect(&c).ok());
    daemon::ControlReply st;
    ASSERT_TRUE(c->Call("status", json::object(), &st).ok());
    ASSERT_TRUE(st.ok()) << st.error_message;
    const json cams = st.result["cameras"];
    ASSERT_EQ(cams.size(), 3u) << cams.dump();
    const std::string missing = cams[1]["id"];
    EXPECT_EQ(cams[1]["connected"], false) << cams.dump();
    ASSERT_TRUE(cams[1]["problem"].is_string()) << cams.dump();
    EXPECT_NE(cams[1]["problem"].get<std::string>().find(missing), std::string::npos) << cams.dump();
    EXPECT_EQ(cams[0]["connected"], true);
    EXPECT_EQ(cams[2]["connected"], true);
    EXPECT_TRUE(cams[0]["problem"].is_null()) << cams.dump();
    EXPECT_EQ(NotifyListener::Field(notify.Messages()[ready].text, "STATUS"),
              "degraded: 2/3 simulated cameras 200 Hz (missing " + missing + "), idle");
    // One error line in the journal names the camera, the setting and the way out.
    const std::string log = d.Log();
    int lines = 0;
    std::istringstream in(log);
    for (std::string l; std::getline(in, l);)
      if (l.rfind("<3>", 0) == 0) {
        ++lines;
        EXPECT_NE(l.find("[[rig.camera]] '" + missing + "' did not open"), std::string::npos) << l;
        EXPECT_NE(l.find("degraded"), std::string::npos) << l;
      }
    EXPECT_EQ(lines, 1) << log;
    EXPECT_EQ(st.result["sync"]["locked"], true) << st.result["sync"].dump();
    ASSERT_TRUE(c->Call("cameras.check", json::object(), &st).ok());
    EXPECT_TRUE(st.result["cameras"][1]["sync"]["status"].is_null()) << st.result["cameras"][1].dump();

    // Plugged in: streaming within 2 s, and STATUS no longer degraded.
    const double plugged = notify.Now();
    ASSERT_TRUE(c->Call("sim.camera", {{"camera", 1}, {"present", true}}, &st).ok());
    ASSERT_TRUE(st.ok()) << st.error_message;
    double joined_s = -1;
    while (notify.Now() - plugged < 4) {
      ASSERT_TRUE(c->Call("status", json::object(), &st).ok());
      if (st.result["cameras"][1]["connected"] == true &&
          st.result["cameras"][1]["frames"].get<std::uint64_t>() > 20) {
        joined_s = notify.Now() - plugged;
        break;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    std::printf("the missing camera streams %.2f s after it was plugged in\n", joined_s);
    EXPECT_GE(joined_s, 0) << "the camera did not join; log:\n" << d.LogTail();
    EXPECT_LE(joined_s, 2.0);
    EXPECT_TRUE(st.result["cameras"][1]["problem"].is_null()) << st.result["cameras"].dump();
    EXPECT_GE(notify.WaitFor("STATUS=3/3 simulated cameras 200 Hz, idle", 3, plugged), 0);
    // It joined the PTP monitor: its own PtpStatus is read, scheduled on the rig's ticks, and
    // its lock lost is the rig's (each within a monitor round, 0.5 s).
    for (const double read = notify.Now(); notify.Now() - read < 1.5;) {
      ASSERT_TRUE(c->Call("cameras.check", json::object(), &st).ok());
      if (st.result["cameras"][1]["sync"]["status"] == "Slave") break;
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
    EXPECT_EQ(st.result["cameras"][1]["sync"]["status"], "Slave") << st.result["cameras"][1].dump();
    ASSERT_TRUE(st.result["cameras"][1]["sync"]["tick_phase"].is_number()) << st.result["cameras"][1].dump();
    EXPECT_NEAR(st.result["cameras"][1]["sync"]["tick_phase"].get<double>(), 0.5, 1e-6);  // mid-tick
    ASSERT_TRUE(c->Call("sim.camera", {{"camera", 1}, {"ptp", "Listening"}}, &st).ok());
    std::this_thread::sleep_for(std::chrono::milliseconds(1200));
    ASSERT_TRUE(c->Call("status", json::object(), &st).ok());
    EXPECT_EQ(st.result["sync"]["locked"], false) << st.result["sync"].dump();
    EXPECT_EQ(st.result["sync"]["unlocked_cameras"], json({missing}));
    EXPECT_EQ(d.Stop(), 0) << d.LogTail();
  }

  // Fewer cameras than [rig] min_cameras: no degraded start, the camera named, unavailable.
  std::ofstream(dir + "/strict.toml") << testing::SimulatedRigToml(3, 5, "width = 640\nheight = 512\nmin_cameras = 3\n");
  const StartResult r =
      StartMocapd(dir, {"--config", dir + "/strict.toml", "--state-dir", dir + "/state2", "--socket",
                        dir + "/c2.sock"},
                  {{"MOCAP_TEST_ABSENT_CAMERAS", "1"}});
  EXPECT_EQ(r.code, daemon::kExitUnavailable) << r.log;
  ASSERT_EQ(r.errors.size(), 1u) << r.log;
  EXPECT_NE(r.errors[0].find("2 of 3 cameras opened, fewer than min_cameras = 3"), std::string::npos)
      << r.errors[0];
}

}  // namespace
}  // namespace mocap

// ---------------------------------------------------------------------------------------------
// The units, installed into a temporary root, and the Debian package.

#ifdef MOCAPD_BUILD_DIR
namespace mocap {
namespace {

// Runs `command` through the shell; its exit code and its output (stdout and stderr).
int Shell(const std::string& command, std::string* output) {
  output->clear();
  FILE* p = popen((command + " 2>&1").c_str(), "r");
  if (!p) return -1;
  char buf[4096];
  for (std::size_t n; (n = fread(buf, 1, sizeof buf, p)) > 0;) output->append(buf, n);
  const int status = pclose(p);
  return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
}

bool Have(const std::string& program) {
  std::string out;
  return Shell("command -v " + program, &out) == 0;
}

// `cmake --install` of the build into DESTDIR=root.
void InstallInto(const std::string& root) {
  std::string out;
  ASSERT_EQ(Shell("DESTDIR='" + root + "' cmake --install '" MOCAPD_BUILD_DIR "' --component mocapd", &out), 0)
      << out;
}

TEST(SystemdUnits, InstalledUnitsVerifyCleanAndScoreAtMost1_5) {
  if (!Have("systemd-analyze"))
    GTEST_SKIP() << "systemd-analyze is not installed (Debian package systemd; scripts/deps.sh)";
  const std::string root = testing::MakeTempDir("mocapd-units");
  ASSERT_FALSE(root.empty());
  InstallInto(root);
  const std::string units = root + MOCAPD_INSTALLED_UNIT_DIR;
  ASSERT_TRUE(std::filesystem::exists(units + "/mocapd.service"));
  ASSERT_TRUE(std::filesystem::exists(root + MOCAPD_INSTALLED_SBIN));
  // verify --root loads every unit a unit refers to from the root and checks the commands there:
  // the targets (sockets.target, multi-user.target, ...) and /bin/kill come from the host's
  // systemd and procps packages, as on the capture PC.
  std::string out;
  ASSERT_EQ(Shell("cp -n /lib/systemd/system/*.target '" + units + "/' && mkdir -p '" + root +
                      "/bin' && cp /bin/kill '" + root + "/bin/kill'",
                  &out),
            0)
      << out;
  const int verify = Shell("systemd-analyze verify --root='" + root + "' " MOCAPD_INSTALLED_UNIT_DIR
                           "/mocapd.service " MOCAPD_INSTALLED_UNIT_DIR "/mocapd.socket",
                           &out);
  EXPECT_EQ(verify, 0) << out;
  EXPECT_EQ(out, "") << "systemd-analyze verify is not clean";

  ASSERT_EQ(Shell("systemd-analyze security --offline=yes --root='" + root + "' mocapd.service", &out), 0)
      << out;
  std::smatch m;
  ASSERT_TRUE(std::regex_search(out, m, std::regex("Overall exposure level for mocapd.service: ([0-9.]+)")))
      << out;
  const double exposure = std::stod(m[1]);
  std::printf("systemd-analyze security: exposure %.1f\n", exposure);
  EXPECT_LE(exposure, 1.5) << out;
  // Every setting the score would like tighter is named in a comment of the unit, with why.
  const std::string unit = ReadAll(units + "/mocapd.service");
  std::istringstream lines(out);
  int flagged = 0;
  for (std::string l; std::getline(lines, l);) {
    if (l.rfind("✗ ", 0) != 0) continue;
    ++flagged;
    std::string key = l.substr(std::string("✗ ").size());
    key = key.substr(0, key.find_first_of("=/ "));
    EXPECT_TRUE(std::regex_search(unit, std::regex("\n#[^\n]*" + key + "[^\n]*\\(score\\)")))
        << key << " is flagged by the score and not explained in a comment: " << l;
  }
  EXPECT_GT(flagged, 0);
}

TEST(DebianPackage, BuildsWithDependenciesAndInstallsIntoAThrowAwayRoot) {
  for (const char* tool : {"cpack", "dpkg-deb", "dpkg-shlibdeps", "dpkg"})
    if (!Have(tool)) GTEST_SKIP() << tool << " is not installed (scripts/deps.sh: dpkg-dev)";
  const std::string dir = testing::MakeTempDir("mocapd-deb");
  ASSERT_FALSE(dir.empty());
  std::string out, arch;
  ASSERT_EQ(Shell("dpkg --print-architecture", &arch), 0);
  arch.erase(arch.find_last_not_of("\n") + 1);
  ASSERT_EQ(Shell("cd '" + dir + "' && cpack -G DEB --config '" MOCAPD_BUILD_DIR "/CPackConfig.cmake' -B '" +
                      dir + "'",
                  &out),
            0)
      << out;
  const std::string deb = dir + "/mocapd_" MOCAPD_VERSION "_" + arch + ".deb";
  ASSERT_TRUE(std::filesystem::exists(deb)) << out;

  ASSERT_EQ(Shell("dpkg-deb --contents '" + deb + "'", &out), 0) << out;
  for (const std::string path :
       {MOCAPD_INSTALLED_SBIN, MOCAPD_INSTALLED_BIN, MOCAPD_INSTALLED_CONFIG,
        MOCAPD_INSTALLED_UNIT_DIR "/mocapd.service", MOCAPD_INSTALLED_UNIT_DIR "/mocapd.socket",
        MOCAPD_INSTALLED_SYSUSERS, MOCAPD_INSTALLED_TMPFILES, MOCAPD_INSTALLED_UDEV,
        MOCAPD_INSTALLED_SYSCTL, MOCAPD_INSTALLED_DOC_DIR "/README.md"})
    EXPECT_NE(out.find(" ." + path + "\n"), std::string::npos) << path << " not in the package:\n" << out;

  ASSERT_EQ(Shell("dpkg-deb --field '" + deb + "' Package Version Architecture Depends", &out), 0) << out;
  EXPECT_NE(out.find("Package: mocapd\n"), std::string::npos) << out;
  EXPECT_NE(out.find("Version: " MOCAPD_VERSION "\n"), std::string::npos) << out;
  // From dpkg-shlibdeps on what the binaries link, and systemd for the maintainer scripts.
  for (const char* dep : {"systemd (>=", "libaravis-0.8-0", "libsqlite3-0", "libsystemd0", "libc6"})
    EXPECT_NE(out.find(dep), std::string::npos) << dep << " missing from " << out;
  ASSERT_EQ(Shell("dpkg-deb --info '" + deb + "' conffiles", &out), 0) << out;
  EXPECT_EQ(out, std::string(MOCAPD_INSTALLED_CONFIG) + "\n");

  // Installed into a throw-away root: dpkg --root with the maintainer scripts run outside a
  // chroot (DPKG_ROOT set; the root has no shell to chroot into), its dependencies not there.
  if (geteuid() != 0) GTEST_SKIP() << "installing the package into a root needs root (dpkg --root)";
  const std::string root = dir + "/root";
  ASSERT_EQ(Shell("mkdir -p '" + root + "/var/lib/dpkg/info' '" + root + "/var/lib/dpkg/updates' '" +
                      root + "/etc' && touch '" + root + "/var/lib/dpkg/status' '" + root +
                      "/var/lib/dpkg/available'",
                  &out),
            0);
  const std::string dpkg = "dpkg --root='" + root + "' --force-script-chrootless --force-depends --log=/dev/null ";
  ASSERT_EQ(Shell(dpkg + "-i '" + deb + "'", &out), 0) << out;
  EXPECT_TRUE(std::regex_search(ReadAll(root + "/etc/passwd"),
                                std::regex("(^|\n)mocap:x:[0-9]+:[0-9]+:[^:]*:/var/lib/mocapd:")))
      << ReadAll(root + "/etc/passwd");
  EXPECT_TRUE(std::regex_search(ReadAll(root + "/etc/group"), std::regex("(^|\n)mocap:x:[0-9]+:")));
  EXPECT_TRUE(std::filesystem::is_regular_file(root + MOCAPD_INSTALLED_CONFIG));
  EXPECT_TRUE(std::filesystem::is_regular_file(root + MOCAPD_INSTALLED_UNIT_DIR "/mocapd.service"));
  EXPECT_TRUE(std::filesystem::is_symlink(root + "/etc/systemd/system/sockets.target.wants/mocapd.socket"))
      << "the socket is not enabled";
  struct stat st {};
  ASSERT_EQ(stat((root + "/var/lib/mocapd").c_str(), &st), 0);
  EXPECT_EQ(st.st_mode & 07777, 0750u);
  // The shipped configuration is valid as it is.
  ASSERT_EQ(Shell(std::string(MOCAPD_PATH) + " --check-config --config '" + root + MOCAPD_INSTALLED_CONFIG + "'", &out), 0)
      << out;
  EXPECT_NE(out.find("simulated rig of 8 cameras"), std::string::npos) << out;
  // Removed: the conffile stays (until purge), the units go.
  ASSERT_EQ(Shell(dpkg + "-r mocapd", &out), 0) << out;
  EXPECT_TRUE(std::filesystem::exists(root + MOCAPD_INSTALLED_CONFIG));
  EXPECT_FALSE(std::filesystem::exists(root + MOCAPD_INSTALLED_UNIT_DIR "/mocapd.service"));
  ASSERT_EQ(Shell(dpkg + "-P mocapd", &out), 0) << out;
  EXPECT_FALSE(std::filesystem::exists(root + MOCAPD_INSTALLED_CONFIG));
  EXPECT_FALSE(std::filesystem::exists(root + "/etc/systemd/system/sockets.target.wants/mocapd.socket"));
}

}  // namespace
}  // namespace mocap
#endif  // MOCAPD_BUILD_DIR
