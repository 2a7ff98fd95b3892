// The rig check (`mocapctl cameras --check`, cameras.check; daemon/rig_check.h) and the PTP lock
// monitored while streaming (daemon/ptp_monitor.h), against the real mocapd on the simulated
// rig, read through the real mocapctl:
//  - free run: fakes whose clocks were given an offset and a drift ([[rig.camera]]
//    sim_clock_offset_ms / sim_clock_drift_ppm), and whose arrivals wait 300 us on average
//    (sim_arrival_wait_us), are reported with that offset and drift;
//  - a link planned over its budget shows its negative headroom and fails the check (exit 5);
//  - PTP: a camera that loses its lock (sim.camera ptp) fails the check, shows in status, gets
//    record.start refused naming it, and marks a recording it happens during.
#include <poll.h>
#include <sys/socket.h>
#include <sys/un.h>

#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <thread>

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "tests/daemon_gtest_util.h"
#include "tests/daemon_test_util.h"

namespace mocap {
namespace {

using daemon::ControlClient;
using daemon::ControlReply;
using nlohmann::json;
using ::testing::HasSubstr;
using testing::DaemonProcess;
using testing::NotifySocket;

using testing::Call;

// `mocapctl --json cameras --check` on the daemon's socket: its exit status and the report.
int RigCheck(const DaemonProcess& d, json* report) {
  const std::string cmd = std::string(MOCAPCTL_TOOL) + " --socket " + d.socket() + " --json cameras --check";
  FILE* p = popen(cmd.c_str(), "r");
  if (!p) return -1;
  std::string out;
  char buf[4096];
  for (std::size_t n; (n = fread(buf, 1, sizeof buf, p)) > 0;) out.append(buf, n);
  const int status = pclose(p);
  *report = json::parse(out, nullptr, false);
  return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
}

std::string Camera(int i) { return "MOCAPSIM" + std::to_string(i); }

TEST(DaemonRigCheck, FreeRunReportsTheClockOffsetAndDriftEachCameraWasGiven) {
  const std::string dir = testing::MakeTempDir("mocapd-rigcheck-free");
  std::string cams;
  for (int i = 0; i < 4; ++i) {
    cams += "[[rig.camera]]\nid = \"" + Camera(i) + "\"\ninterface = \"10gige\"\nlink = \"nic" +
            std::to_string(i) + "\"\nsim_arrival_wait_us = 300\n";
    if (i == 2) cams += "sim_clock_offset_ms = 3.0\n";
    if (i == 3) cams += "sim_clock_drift_ppm = 100\n";
  }
  // Small images: the clocks are what is checked, and the host is shared with other work.
  DaemonProcess d(dir, testing::SimulatedRigToml(4, 3, "width = 320\nheight = 256\nsync = \"free-run\"\n" + cams));
  ASSERT_OK(d.Start());
  // The check passes once the fits have their drift (a few hundred frames); the figures are
  // read once the fits' window is full (1024 frames, 5.1 s), as a lab would after a minute.
  json report;
  int status = -1;
  const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(40);
  while (std::chrono::steady_clock::now() < until) {
    status = RigCheck(d, &report);
    bool full = report.is_object() && report["cameras"].size() == 4;
    for (const json& cam : report.value("cameras", json::array()))
      full = full && cam["frames"]["complete"].get<int>() > 1100;
    if (status == 0 && full) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(500));
  }
  ASSERT_EQ(status, 0) << report.dump(1) << d.LogTail();
  EXPECT_EQ(report["ok"], true);
  EXPECT_EQ(report["sync"]["mode"], "free-run");
  const json& c = report["cameras"];
  ASSERT_EQ(c.size(), 4u);
  // The offsets against the rig's median camera: the one put in, within a 50th of a period
  // (the lower envelope of 64 waits of 300 us on average is a few microseconds late) plus the
  // uncertainty the check itself reports, the fits' residual: on a host loaded by other work
  // the fakes' own arrivals wait too, whole runs of them, and the residual says by how much.
  // The drift likewise, over the fit's 5.1 s window.
  double residual_ms = 0;
  for (const json& cam : c) residual_ms = std::max(residual_ms, cam["sync"]["clock_residual_us"].get<double>() * 1e-3);
  const double drift_tolerance_ppm = 5.0 + residual_ms * 1e3 / 5.1;
  for (int i = 0; i < 3; ++i) {
    EXPECT_EQ(c[i]["ok"], true) << c[i].dump();
    EXPECT_NEAR(c[i]["sync"]["offset_from_rig_ms"].get<double>(), i == 2 ? 3.0 : 0.0, 0.1 + residual_ms)
        << c[i].dump();
    EXPECT_NEAR(c[i]["sync"]["clock_drift_ppm"].get<double>(), 0.0, drift_tolerance_ppm) << c[i].dump();
    EXPECT_EQ(c[i]["link"], "nic" + std::to_string(i));
  }
  EXPECT_NEAR(c[3]["sync"]["clock_drift_ppm"].get<double>(), 100.0, drift_tolerance_ppm) << c[3].dump();
  for (const json& cam : c) {
    EXPECT_EQ(cam["sync"]["clock_fitted"], true);
    // The runs' best arrivals scatter by the best of 64 waits: microseconds, not a period.
    EXPECT_GT(cam["sync"]["clock_residual_us"].get<double>(), 0.0) << cam.dump();
    EXPECT_LT(cam["sync"]["clock_residual_us"].get<double>(), 0.25 * 5000) << cam.dump();
    EXPECT_TRUE(cam["packets"].is_null()) << "the in-process fakes have no GigE packet statistics";
  }
  ASSERT_EQ(report["links"].size(), 4u);
  // 320 x 256 Mono8 at 200 Hz: 16.4 MB/s of images, 17.2 on the wire in 1500-byte GVSP packets.
  EXPECT_NEAR(report["links"][0]["headroom_mb_s"].get<double>(), 1250 - 17.2, 0.1) << report["links"].dump();
  std::printf("free run: offsets from the rig %.3f %.3f %.3f ms, drifts %.1f %.1f %.1f %.1f ppm, "
              "residual %.1f us\n",
              c[0]["sync"]["offset_from_rig_ms"].get<double>(), c[1]["sync"]["offset_from_rig_ms"].get<double>(),
              c[2]["sync"]["offset_from_rig_ms"].get<double>(), c[0]["sync"]["clock_drift_ppm"].get<double>(),
              c[1]["sync"]["clock_drift_ppm"].get<double>(), c[2]["sync"]["clock_drift_ppm"].get<double>(),
              c[3]["sync"]["clock_drift_ppm"].get<double>(), c[2]["sync"]["clock_residual_us"].get<double>());
  EXPECT_EQ(d.Stop(), 0) << d.LogTail();
}

TEST(DaemonRigCheck, ALinkOverItsBudgetShowsNegativeHeadroomAndFails) {
  const std::string dir = testing::MakeTempDir("mocapd-rigcheck-link");
  std::string cams;
  for (int i = 0; i < 4; ++i)
    cams += "[[rig.camera]]\nid = \"" + Camera(i) + "\"\n" + (i < 2 ? "link = \"eth1\"\n" : "");
  // A simulated rig starts over budget (its fakes carry nothing) and says so in its log.
  DaemonProcess d(dir, testing::SimulatedRigToml(4, 3, cams));
  ASSERT_OK(d.Start());
  std::this_thread::sleep_for(std::chrono::seconds(2));
  json report;
  EXPECT_EQ(RigCheck(d, &report), 5) << report.dump(1);
  EXPECT_EQ(report["ok"], false);
  ASSERT_EQ(report["links"].size(), 1u) << "only the planned link is checked";
  const json& link = report["links"][0];
  EXPECT_EQ(link["link"], "eth1");
  EXPECT_EQ(link["cameras"], json({Camera(0), Camera(1)}));
  // 1280 x 1024 Mono8 at 200 Hz: 262.1 MB/s of images a camera, 275.4 on the wire in 1500-byte
  // GVSP packets; two on one GigE link of 125 MB/s.
  EXPECT_NEAR(link["needed_mb_s"].get<double>(), 2 * 275.4, 0.5);
  EXPECT_NEAR(link["headroom_mb_s"].get<double>(), 125 - 2 * 275.4, 0.5);
  EXPECT_EQ(link["ok"], false);
  // (On a host loaded by other work a camera may also have lost frames: not this test's point.)
  EXPECT_THAT(report["problems"].dump(), HasSubstr("link 'eth1' (gige): its 2 camera(s) need 550.8 MB/s"));
  EXPECT_THAT(report["problems"].dump(), ::testing::Not(HasSubstr("link 'MOCAPSIM")));
  EXPECT_EQ(report["cameras"][0]["link"], "eth1");
  EXPECT_TRUE(report["cameras"][2]["link"].is_null());
  EXPECT_EQ(report["sync"]["mode"], "shared-clock");
  EXPECT_THAT(d.Log(), HasSubstr("simulated rig: [rig] bandwidth: link 'eth1'"));
  EXPECT_EQ(d.Stop(), 0) << d.LogTail();
}

TEST(DaemonRigCheck, APtpCameraLosingItsLockIsNamedRefusedAndMarksTheRecording) {
  const std::string dir = testing::MakeTempDir("mocapd-rigcheck-ptp");
  DaemonProcess d(dir, testing::SimulatedRigToml(6, 4, "sync = \"ptp\"\n"));
  NotifySocket notify(dir + "/notify");
  ASSERT_TRUE(notify.bound());
  setenv("NOTIFY_SOCKET", (dir + "/notify").c_str(), 1);  // mocapd inherits it
  const Status started = d.Start();
  unsetenv("NOTIFY_SOCKET");
  ASSERT_OK(started);
  std::unique_ptr<ControlClient> c;
  ASSERT_OK(d.Connect(&c));
  json report;
  // Straight after the start the cameras have too few frames to be judged.
  EXPECT_EQ(RigCheck(d, &report), 5) << report.dump(1);
  EXPECT_THAT(report["problems"].dump(), HasSubstr("too few frames so far"));
  std::this_thread::sleep_for(std::chrono::seconds(3));
  // Locked: no PTP problem (frames lost on a host loaded by other work would be the only ones).
  RigCheck(d, &report);
  EXPECT_EQ(report["sync"]["locked"], true) << report.dump(1);
  EXPECT_THAT(report["problems"].dump(), ::testing::Not(HasSubstr("PTP"))) << report.dump(1);
  for (const json& cam : report["cameras"]) EXPECT_EQ(cam["sync"]["locked"], true) << cam.dump();
  EXPECT_EQ(report["cameras"][1]["sync"]["status"], "Slave");

  // Camera 1 falls back to listening: within a monitor round (0.5 s) everything says so.
  Call(c.get(), "sim.camera", {{"camera", 1}, {"ptp", "Listening"}});
  std::this_thread::sleep_for(std::chrono::milliseconds(1200));
  const json st = Call(c.get(), "status");
  EXPECT_EQ(st["sync"]["locked"], false) << st["sync"].dump();
  EXPECT_EQ(st["sync"]["unlocked_cameras"], json({Camera(1)}));
  const std::string line = notify.WaitForStatus("PTP unlocked", 3);
  EXPECT_THAT(line, HasSubstr("STATUS=degraded: 6/6 simulated cameras 200 Hz (PTP unlocked: " + Camera(1) + ")"));
  EXPECT_EQ(RigCheck(d, &report), 5) << report.dump(1);
  EXPECT_EQ(report["cameras"][1]["ok"], false);
  EXPECT_EQ(report["cameras"][1]["sync"]["status"], "Listening");
  EXPECT_EQ(report["cameras"][1]["problems"][0], "PTP not locked (status Listening)");
  EXPECT_EQ(report["cameras"][0]["sync"]["locked"], true);
  EXPECT_THAT(report["problems"].dump(), HasSubstr("PTP: not locked: " + Camera(1) + " (Listening)"));
  ControlReply refused;
  ASSERT_OK(c->Call("record.start", {{"movement", "static"}}, &refused));
  EXPECT_EQ(refused.error_code, "unavailable");
  EXPECT_THAT(refused.error_message, HasSubstr(Camera(1) + " (Listening)"));
  EXPECT_THAT(d.Log(), HasSubstr("PTP lock lost: not locked: " + Camera(1)));

  // Locked again: the check passes; then the lock goes during a recording, which is marked.
  Call(c.get(), "sim.camera", {{"camera", 1}, {"ptp", "Slave"}});
  std::this_thread::sleep_for(std::chrono::milliseconds(1200));
  EXPECT_EQ(Call(c.get(), "status")["sync"]["locked"], true);
  ASSERT_OK(testing::CalibrateRigAndSelectSubject(c.get(), 8, "S01"));
  std::int64_t id = 0;
  ASSERT_OK(c->Send("record.start", {{"movement", "static"}, {"duration_s", 3}}, &id));
  std::this_thread::sleep_for(std::chrono::seconds(1));
  Call(c.get(), "sim.camera", {{"camera", 4}, {"ptp", "Uncalibrated"}});
  ControlReply rec;
  ASSERT_OK(c->Wait(id, &rec));
  ASSERT_TRUE(rec.ok()) << rec.error_message;
  ASSERT_EQ(rec.result["sync_faults"].size(), 1u) << rec.result.dump().substr(0, 800);
  EXPECT_THAT(rec.result["sync_faults"][0].get<std::string>(), HasSubstr(Camera(4) + " (Uncalibrated)"));
  EXPECT_EQ(rec.result["coverage"]["ok"], false);
  EXPECT_THAT(rec.result["advice"].get<std::string>(), HasSubstr("PTP lock lost"));
  EXPECT_EQ(Call(c.get(), "recording.list")["recordings"][0]["coverage_ok"], false);
  EXPECT_EQ(d.Stop(), 0) << d.LogTail();
}

}  // namespace
}  // namespace mocap
