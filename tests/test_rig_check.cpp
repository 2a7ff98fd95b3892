// The parts of issue 18's rig checks that run without a daemon or a camera:
//  - USB3 Vision transfer settings (drivers/usb_transfer.h) applied through a fake device: mode,
//    throughput limit on and read back, off, refusals named (or listed when optional), and their
//    configuration keys and validation errors;
//  - the rig check's verdicts (daemon/rig_check.h) on figures with a known answer;
//  - the PTP monitor (daemon/ptp_monitor.h): rounds, lock losses, unreadable cameras;
//  - STATUS= naming unlocked cameras; a skewed camera clock (drivers/skewed_clock_camera.h).
#include <map>
#include <memory>
#include <string>
#include <thread>

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "daemon/config.h"
#include "daemon/ptp_monitor.h"
#include "daemon/rig_check.h"
#include "daemon/rig_setup.h"
#include "daemon/service_notify.h"
#include "daemon/startup_checks.h"
#include "drivers/simulated_camera.h"
#include "drivers/skewed_clock_camera.h"
#include "drivers/usb_transfer.h"

namespace mocap {
namespace {

using ::testing::HasSubstr;

// A USB3 camera's features as a map; each can be absent, refuse writes, or round what it takes.
class FakeUsbDevice final : public drivers::UsbTransferDevice {
 public:
  struct Integer {
    std::int64_t value = 0, min = 0, max = 0, increment = 1;
  };
  std::map<std::string, Integer> integers;
  std::map<std::string, std::string> strings;
  std::map<std::string, std::string> refuse;  // feature -> the device's error
  drivers::UsbMode mode_set = drivers::UsbMode::kDefault;
  int mode_calls = 0;

  // A camera with SFNC's link limit: 40..500 MB/s in 1 kB/s steps, mode Off.
  static FakeUsbDevice WithLimit() {
    FakeUsbDevice d;
    d.integers["DeviceLinkThroughputLimit"] = {400'000'000, 40'000'000, 500'000'000, 1000};
    d.strings["DeviceLinkThroughputLimitMode"] = "Off";
    return d;
  }

  void SetUsbMode(drivers::UsbMode mode) override {
    mode_set = mode;
    ++mode_calls;
  }
  bool HasFeature(const std::string& f) override { return integers.count(f) || strings.count(f); }
  Status SetInteger(const std::string& f, std::int64_t v) override {
    if (refuse.count(f)) return Status::Error(refuse[f]);
    if (!integers.count(f)) return Status::Error("feature '" + f + "' not found");
    Integer& i = integers[f];
    i.value = v / i.increment * i.increment;
    return Status::Ok();
  }
  Status GetInteger(const std::string& f, std::int64_t* v) override {
    if (!integers.count(f)) return Status::Error("feature '" + f + "' not found");
    *v = integers[f].value;
    return Status::Ok();
  }
  Status IntegerBounds(const std::string& f, std::int64_t* lo, std::int64_t* hi) override {
    if (!integers.count(f)) return Status::Error("feature '" + f + "' not found");
    *lo = integers[f].min;
    *hi = integers[f].max;
    return Status::Ok();
  }
  Status SetString(const std::string& f, const std::string& v) override {
    if (refuse.count(f)) return Status::Error(refuse[f]);
    if (!strings.count(f)) return Status::Error("feature '" + f + "' not found");
    strings[f] = v;
    return Status::Ok();
  }
  Status GetString(const std::string& f, std::string* v) override {
    if (!strings.count(f)) return Status::Error("feature '" + f + "' not found");
    *v = strings[f];
    return Status::Ok();
  }
};

Status Apply(FakeUsbDevice* d, drivers::UsbTransferSettings s, drivers::AppliedUsbTransfer* applied,
             std::vector<std::string>* refused = nullptr, std::vector<std::string> optional = {}) {
  std::vector<std::string> ignored;
  return drivers::ApplyUsbTransfer("cam7", s, optional, d, applied, refused ? refused : &ignored);
}

TEST(UsbTransfer, AsyncModeAndALimitAreSetSwitchedOnAndReadBack) {
  FakeUsbDevice d = FakeUsbDevice::WithLimit();
  drivers::UsbTransferSettings s;
  s.mode = drivers::UsbMode::kAsync;
  s.throughput_limit_mb_s = 300;
  drivers::AppliedUsbTransfer a;
  ASSERT_TRUE(Apply(&d, s, &a).ok());
  EXPECT_EQ(d.mode_calls, 1);
  EXPECT_EQ(d.mode_set, drivers::UsbMode::kAsync);
  EXPECT_TRUE(a.applied);
  EXPECT_EQ(a.mode, "async");
  EXPECT_EQ(d.integers["DeviceLinkThroughputLimit"].value, 300'000'000);
  EXPECT_EQ(d.strings["DeviceLinkThroughputLimitMode"], "On");
  EXPECT_EQ(a.throughput_limit_mode, "On");
  EXPECT_DOUBLE_EQ(a.throughput_limit_mb_s, 300.0);
  EXPECT_EQ(a.maximum_transfer_bytes, 1u << 20);  // Aravis 0.8's, fixed
  // A camera rounding to its 1 kB/s step is within the 1 % the read-back allows.
  s.throughput_limit_mb_s = 123.4567;
  ASSERT_TRUE(Apply(&d, s, &a).ok());
  EXPECT_EQ(d.integers["DeviceLinkThroughputLimit"].value, 123'456'000);
  EXPECT_NEAR(a.throughput_limit_mb_s, 123.456, 1e-9);
}

TEST(UsbTransfer, NoLimitSwitchesALimitLeftOnOff) {
  FakeUsbDevice d = FakeUsbDevice::WithLimit();
  d.strings["DeviceLinkThroughputLimitMode"] = "On";  // another program left it on
  drivers::AppliedUsbTransfer a;
  ASSERT_TRUE(Apply(&d, {}, &a).ok());
  EXPECT_EQ(d.strings["DeviceLinkThroughputLimitMode"], "Off");
  EXPECT_EQ(a.throughput_limit_mode, "Off");
  EXPECT_EQ(a.mode, "default");
  // A camera without the features needs nothing for "no limit".
  FakeUsbDevice bare;
  EXPECT_TRUE(Apply(&bare, {}, &a).ok());
  EXPECT_EQ(a.throughput_limit_mode, "");
}

TEST(UsbTransfer, RefusalsNameCameraAndFeatureUnlessOptional) {
  drivers::UsbTransferSettings s;
  s.throughput_limit_mb_s = 300;
  drivers::AppliedUsbTransfer a;
  FakeUsbDevice bare;  // no DeviceLinkThroughputLimit at all
  Status st = Apply(&bare, s, &a);
  ASSERT_FALSE(st.ok());
  EXPECT_THAT(st.message(), HasSubstr("cam7: DeviceLinkThroughputLimit: the camera has no "
                                      "DeviceLinkThroughputLimit to hold it to 300 MB/s"));
  std::vector<std::string> refused;
  ASSERT_TRUE(Apply(&bare, s, &a, &refused, {"DeviceLinkThroughputLimit"}).ok());
  ASSERT_EQ(refused.size(), 1u);
  EXPECT_THAT(refused[0], HasSubstr("DeviceLinkThroughputLimit: the camera has no"));

  FakeUsbDevice d = FakeUsbDevice::WithLimit();
  s.throughput_limit_mb_s = 600;  // above its 500
  st = Apply(&d, s, &a);
  EXPECT_THAT(st.message(), HasSubstr("cam7: DeviceLinkThroughputLimit: 600 MB/s outside the "
                                      "camera's range 40..500 MB/s"));
  s.throughput_limit_mb_s = 300;
  d.refuse["DeviceLinkThroughputLimitMode"] = "access denied";
  st = Apply(&d, s, &a);
  EXPECT_THAT(st.message(), HasSubstr("cam7: DeviceLinkThroughputLimitMode: refused On (access denied)"));
  d.refuse.clear();
  d.integers["DeviceLinkThroughputLimit"].increment = 50'000'000;  // 300 -> 300, 320 -> 300
  s.throughput_limit_mb_s = 320;
  st = Apply(&d, s, &a);
  EXPECT_THAT(st.message(), HasSubstr("DeviceLinkThroughputLimit: set to 320 MB/s, reads back 300 MB/s"));
  s.throughput_limit_mb_s = -1;
  EXPECT_THAT(Apply(&d, s, &a).message(), HasSubstr("throughput_limit_mb_s -1 is outside"));
}

daemon::DaemonConfig Parse(const std::string& text, Status* status) {
  daemon::DaemonConfig c;
  *status = daemon::ParseConfig(text, "/etc/mocapd/mocapd.toml", &c);
  return c;
}

TEST(UsbTransfer, ConfigKeysReachTheCameraSettingsAndBadOnesAreNamed) {
  const std::string rig = "[rig]\nrate = 100\nwidth = 1280\nheight = 1024\n";
  Status s;
  daemon::DaemonConfig c = Parse(rig + "[[rig.camera]]\nid = \"u0\"\ninterface = \"usb3\"\n"
                                       "usb_mode = \"async\"\nusb_throughput_limit_mb_s = 200\n"
                                       "[[rig.camera]]\nid = \"g0\"\n",
                                 &s);
  ASSERT_TRUE(s.ok()) << s.message();
  drivers::CameraSettings u = daemon::CameraSettingsOf(c, 0), g = daemon::CameraSettingsOf(c, 1);
  EXPECT_EQ(u.usb.mode, drivers::UsbMode::kAsync);
  EXPECT_DOUBLE_EQ(u.usb.throughput_limit_mb_s, 200);
  EXPECT_EQ(g.usb.mode, drivers::UsbMode::kDefault);
  EXPECT_DOUBLE_EQ(g.usb.throughput_limit_mb_s, 0);

  Parse(rig + "[[rig.camera]]\nid = \"u0\"\ninterface = \"usb3\"\nusb_mode = \"fast\"\n", &s);
  EXPECT_THAT(s.message(), HasSubstr("mocapd.toml:8: rig.camera[0].usb_mode: expected one of "
                                     "\"default\", \"sync\", \"async\", got \"fast\""));
  Parse(rig + "[[rig.camera]]\nid = \"g0\"\nusb_mode = \"async\"\n", &s);
  EXPECT_THAT(s.message(), HasSubstr("rig.camera[0].usb_mode: \"async\" on a gige camera"));
  Parse(rig + "[[rig.camera]]\nid = \"g0\"\ninterface = \"10gige\"\nusb_throughput_limit_mb_s = 300\n", &s);
  EXPECT_THAT(s.message(), HasSubstr("rig.camera[0].usb_throughput_limit_mb_s: 300 on a 10gige camera"));
  // 1280 x 1024 Mono8 at 100 Hz is 131.1 MB/s: a 100 MB/s limit would drop frames.
  Parse(rig + "[[rig.camera]]\nid = \"u0\"\ninterface = \"usb3\"\nusb_throughput_limit_mb_s = 100\n", &s);
  EXPECT_THAT(s.message(), HasSubstr("rig.camera[0].usb_throughput_limit_mb_s: 100 MB/s is below "
                                     "the 131.1 MB/s the camera sends (1280x1024 Mono8 at 100 Hz)"));
}

TEST(SimulatedClocks, OnlyASimulatedFreeRunRigTakesThemAndOnlyItsPlannedLinksAreChecked) {
  Status s;
  Parse("[rig]\nsync = \"free-run\"\n[[rig.camera]]\nid = \"a\"\nsim_clock_offset_ms = 2\n", &s);
  EXPECT_THAT(s.message(), HasSubstr("rig.camera[0].sim_clock_offset_ms: a simulated camera's clock on a real rig"));
  Parse("[rig]\nsimulated = 1\nsync = \"ptp\"\n[[rig.camera]]\nid = \"a\"\nsim_clock_drift_ppm = 20\n", &s);
  EXPECT_THAT(s.message(), HasSubstr("rig.camera[0].sim_clock_drift_ppm: needs rig.sync = \"free-run\""));
  daemon::DaemonConfig c = Parse("[rig]\nsimulated = 3\nsync = \"free-run\"\n"
                                 "[[rig.camera]]\nid = \"a\"\nlink = \"eth1\"\nsim_clock_offset_ms = 2\n"
                                 "[[rig.camera]]\nid = \"b\"\nlink = \"eth1\"\n[[rig.camera]]\nid = \"c\"\n",
                                 &s);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(daemon::RigSyncOf(c), daemon::CapturePipelineOptions::RigSync::kFreeRun);
  const auto links = daemon::RigLinkLoads(c);
  ASSERT_EQ(links.size(), 1u);
  EXPECT_EQ(links[0].cameras, (std::vector<std::string>{"a", "b"}));
  EXPECT_FALSE(daemon::CheckRigBandwidth(c).ok());
}

// A camera's clock 2.5 ms ahead and 200 ppm fast: each frame's device time is rewritten so.
TEST(SimulatedClocks, ASkewedCameraStampsWithItsOwnOffsetAndRate) {
  drivers::SimulatedCameraOptions o;
  o.width = 64;
  o.height = 48;
  o.unpaced = true;
  auto blank = [](int, std::uint64_t, std::uint8_t*, int, int, std::ptrdiff_t, drivers::PixelFormat) {};
  auto inner = std::make_unique<drivers::SimulatedCamera>(0, blank, o);
  drivers::SimulatedCamera* plain = inner.get();
  drivers::SkewedClockCamera cam(std::move(inner), {2'500'000, 200});
  drivers::CameraSettings s;
  s.frame_rate_hz = 100;
  const Status opened = cam.Open(s);
  ASSERT_TRUE(opened.ok()) << opened.message();
  ASSERT_TRUE(cam.Start().ok());
  std::uint64_t first = 0;
  for (int i = 0; i < 101; ++i) {
    drivers::Frame f;
    ASSERT_EQ(cam.Grab(&f), drivers::GrabResult::kFrame);
    if (i == 0) {
      first = f.device_timestamp_ns;
      // The simulated camera's own clock starts at 0 (its origin): the offset is all there is.
      EXPECT_EQ(first, 2'500'000u);
    }
    if (i == 100) {
      // 100 frames at 100 Hz: 1 s of the host's clock is 1 s + 200 us of the camera's.
      EXPECT_EQ(static_cast<std::int64_t>(f.device_timestamp_ns - first), 1'000'200'000);
    }
    cam.Release(f);
  }
  EXPECT_EQ(cam.id(), plain->id());
  EXPECT_EQ(cam.Counters().complete.load(), 101u);
  cam.Stop();
}

daemon::CameraCheckInput Healthy(const std::string& id) {
  daemon::CameraCheckInput c;
  c.id = id;
  c.streaming = true;
  c.complete = 2000;
  c.clock_fitted = true;
  c.ptp.status = "Slave";
  return c;
}

TEST(RigCheck, VerdictsFollowTheFiguresAndNameWhatFails) {
  daemon::RigCheckInput in;
  in.sync = "free-run";
  in.rate_hz = 200;  // a 5 ms period: the residual limit is 1250 us
  for (int i = 0; i < 3; ++i) in.cameras.push_back(Healthy("c" + std::to_string(i)));
  in.cameras[0].clock_offset_ms = 1000.0;
  in.cameras[1].clock_offset_ms = 1000.5;
  in.cameras[2].clock_offset_ms = 997.0;
  nlohmann::json r = daemon::RigCheckReport(in);
  EXPECT_EQ(r["ok"], true) << r.dump(1);
  EXPECT_DOUBLE_EQ(r["cameras"][2]["sync"]["offset_from_rig_ms"].get<double>(), -3.0);  // median c0
  EXPECT_DOUBLE_EQ(r["cameras"][1]["sync"]["offset_from_rig_ms"].get<double>(), 0.5);

  in.cameras[1].clock_residual_us = 1300;
  in.cameras[2].underruns = 21;  // 1.05 % of 2000
  r = daemon::RigCheckReport(in);
  EXPECT_EQ(r["ok"], false);
  ASSERT_EQ(r["problems"].size(), 2u) << r["problems"].dump();
  EXPECT_THAT(r["problems"][0].get<std::string>(), HasSubstr("camera 'c1': clock fit residual 1300 us exceeds 1250 us"));
  EXPECT_THAT(r["problems"][1].get<std::string>(), HasSubstr("camera 'c2': 21 frames lost (0 incomplete, 21 underruns, 0 not received) of 2000"));
  EXPECT_EQ(r["cameras"][0]["ok"], true);
  in.cameras[2].underruns = 20;  // exactly 1 %: passes
  in.cameras[1].clock_residual_us = 1250;
  EXPECT_EQ(daemon::RigCheckReport(in)["ok"], true);

  in.sync = "trigger";
  in.cameras[1].count_mismatches = 1;
  in.sets = 2000;
  in.mismatched_sets = 3;  // 0.15 %
  r = daemon::RigCheckReport(in);
  ASSERT_EQ(r["problems"].size(), 2u) << r["problems"].dump();
  EXPECT_THAT(r["problems"][0].get<std::string>(), HasSubstr("camera 'c1': 1 frames whose count disagreed"));
  EXPECT_THAT(r["problems"][1].get<std::string>(), HasSubstr("3 of 2000 sets"));

  in.sync = "ptp";
  in.cameras[1].count_mismatches = 0;
  in.ptp_checked = true;
  in.ptp_locked = true;
  in.cameras[0].ptp.status = "Master";
  r = daemon::RigCheckReport(in);
  EXPECT_EQ(r["ok"], true) << r.dump(1);
  EXPECT_EQ(r["sync"]["master"], "c0");
  in.cameras[1].ptp.has_offset = true;
  in.cameras[1].ptp.offset_from_master_ns = -100'000;  // 100 us: at the limit, passes
  EXPECT_EQ(daemon::RigCheckReport(in)["ok"], true);
  in.cameras[1].ptp.offset_from_master_ns = -100'001;
  r = daemon::RigCheckReport(in);
  ASSERT_EQ(r["problems"].size(), 1u) << r.dump(1);
  EXPECT_EQ(r["problems"][0], "camera 'c1': PTP offset from the master -100001 ns exceeds 100 us (not converged)");
  in.cameras[1].ptp.offset_from_master_ns = 40;
  // Tick phases: cameras scheduled mid-tick agree; one 0.21 of a period (1.05 ms at 200 Hz) off
  // the rig's median is named, one 0.1 off (the limit) is not; a wrap (0.98 against 0.02) is 0.04.
  for (auto& c : in.cameras) c.tick_phase = 0.5;
  in.cameras[2].tick_phase = 0.6;
  r = daemon::RigCheckReport(in);
  EXPECT_EQ(r["ok"], true) << r.dump(1);
  EXPECT_DOUBLE_EQ(r["sync"]["tick_phase"].get<double>(), 0.5);
  EXPECT_NEAR(r["cameras"][2]["sync"]["phase_from_rig_us"].get<double>(), 500, 1e-6);
  in.cameras[2].tick_phase = 0.29;
  r = daemon::RigCheckReport(in);
  ASSERT_EQ(r["problems"].size(), 1u) << r.dump(1);
  EXPECT_EQ(r["problems"][0], "camera 'c2': exposes -1050 us off the rig's other cameras within the tick "
                              "(-0.21 of a period; tick phase 0.29, the rig's 0.50): not exposing on the "
                              "PTP clock's ticks (its exposure schedule, SyncFreeRunTimer*, is off or was "
                              "refused), so its images join sets of another instant");
  for (auto& c : in.cameras) c.tick_phase = 0.02;
  in.cameras[2].tick_phase = 0.98;
  EXPECT_EQ(daemon::RigCheckReport(in)["ok"], true);
  for (auto& c : in.cameras) c.tick_phase = -1;
  in.cameras[2].ptp_error = "c2: cannot read PtpStatus (timeout)";
  in.cameras[2].ptp.status.clear();
  in.ptp_locked = false;
  in.ptp_why = "not read: c2";
  r = daemon::RigCheckReport(in);
  EXPECT_THAT(r["problems"].dump(), HasSubstr("camera 'c2': PTP state not read: c2: cannot read PtpStatus"));

  in = {};
  in.sync = "shared-clock";
  in.rate_hz = 200;
  in.cameras.push_back(Healthy("x"));
  in.links.push_back({"eth1", "gige", {"x"}, 125.0, 126.0, 0});
  r = daemon::RigCheckReport(in);
  EXPECT_DOUBLE_EQ(r["links"][0]["headroom_mb_s"].get<double>(), -1.0);
  EXPECT_THAT(r["problems"][0].get<std::string>(), HasSubstr("link 'eth1' (gige): its 1 camera(s) need 126.0 MB/s"));
}

// A source whose state the test sets, and that can fail to be read.
class ScriptedPtp final : public daemon::PtpStatusSource {
 public:
  explicit ScriptedPtp(std::string id) : id_(std::move(id)) {}
  const std::string& camera_id() const override { return id_; }
  Status Read(drivers::PtpState* s) override {
    if (!error.empty()) return Status::Error(id_ + ": " + error);
    s->status = status;
    return Status::Ok();
  }
  std::string status = "Slave", error;

 private:
  std::string id_;
};

TEST(PtpMonitor, CountsLockLossesAndNamesTheCameras) {
  ScriptedPtp a("a"), b("b"), m("m");
  m.status = "Master";
  int changes = 0;
  daemon::PtpMonitor monitor({&a, &b, &m}, {}, [&] { ++changes; });
  daemon::PtpRigState s = monitor.CheckNow();
  EXPECT_TRUE(s.locked);
  EXPECT_EQ(changes, 1);  // the first reading
  b.status = "Listening";
  s = monitor.CheckNow();
  EXPECT_FALSE(s.locked);
  EXPECT_EQ(s.why, "not locked: b (Listening)");
  EXPECT_EQ(s.unlocked_cameras, std::vector<std::string>{"b"});
  EXPECT_EQ(s.lock_losses, 1u);
  EXPECT_EQ(changes, 2);
  s = monitor.CheckNow();  // still unlocked: not a second loss, no change
  EXPECT_EQ(s.lock_losses, 1u);
  EXPECT_EQ(changes, 2);
  b.status = "Slave";
  a.error = "cannot read PtpStatus (timeout)";
  s = monitor.CheckNow();
  EXPECT_FALSE(s.locked);
  EXPECT_EQ(s.why, "not locked: a (no status); not read: a (a: cannot read PtpStatus (timeout))");
  EXPECT_EQ(s.errors[0], "a: cannot read PtpStatus (timeout)");
  a.error.clear();
  b.status = "Master";  // two masters: two clocks
  s = monitor.CheckNow();
  EXPECT_FALSE(s.locked);
  EXPECT_THAT(s.why, HasSubstr("2 cameras are PTP masters (b, m)"));
  EXPECT_EQ(s.rounds, 5u);
  // The thread: rounds keep coming every interval.
  b.status = "Slave";
  daemon::PtpMonitorOptions fast;
  fast.interval_s = 0.02;
  daemon::PtpMonitor running({&a, &b, &m}, fast);
  ASSERT_TRUE(running.Start().ok());
  std::this_thread::sleep_for(std::chrono::milliseconds(300));
  running.Stop();
  EXPECT_GE(running.Snapshot().rounds, 5u);
  EXPECT_TRUE(running.Snapshot().locked);
  fast.interval_s = 0;
  std::string error;
  EXPECT_FALSE(fast.IsValid(&error));
  EXPECT_THAT(error, HasSubstr("interval_s"));
}

TEST(PtpMonitor, StatusLineNamesTheUnlockedCameras) {
  daemon::ServiceSnapshot s;
  s.cameras = 8;
  s.progress.cameras_streaming = 8;
  s.rate_hz = 200;
  s.rig_live = true;
  s.ptp_unlocked = {"cam2", "cam5"};
  EXPECT_EQ(daemon::StatusLine(s), "degraded: 8/8 cameras 200 Hz (PTP unlocked: cam2, cam5), idle");
}

}  // namespace
}  // namespace mocap
