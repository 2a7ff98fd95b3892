// mocapd under faults and load (issue 17), against the real executable on the simulated rig:
//  - SIGKILL at random moments of a session (recording, fit, model.apply): what was recorded up
//    to the last 100 ms is on disk, marked interrupted, readable and exportable; the database is
//    intact; subjects, calibrations and models are unchanged;
//  - clients that misbehave in every way a client can: the daemon answers the others, its memory
//    stays bounded, the loop never falls behind the pipeline because of them;
//  - a camera whose calibration is 5 cm off: status names it (its reprojection error), the
//    others stay clean, tracking goes on.
#include <sys/socket.h>
#include <sys/un.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

#include "daemon/store.h"
#include "drivers/aravis_fake.h"
#include "formats/c3d.h"
#include "reconstruction/calibration_file.h"
#include "sim/live_rig.h"
#include "tests/daemon_gtest_util.h"
#include "tests/daemon_test_util.h"
#include "tests/store_test_util.h"

namespace mocap {
namespace {

using daemon::ControlClient;
using daemon::ControlReply;
using nlohmann::json;
using testing::DaemonProcess;
using testing::NotifySocket;

using testing::Call;

// The rigs' rates. These tests assert that nothing but the fault costs a frame set, which
// presumes a mocapd that keeps up with its rig: the release build does with 8 cameras at 200 Hz.
// The ASan + UBSan build (build-fuzz/, `scripts/sanitize_daemon.sh faults`) renders and detects
// several times slower and lost half the sets there (tracking lost, the loop queue full, no
// sanitizer report; at a quarter of the rate still a third); it runs the same tests on the same
// rigs at an eighth of the rate, so that the premise holds again. Counts of frames are written
// as seconds x rate: each assertion means the same at either rate.
#if defined(__SANITIZE_ADDRESS__)
#define MOCAP_TEST_UNDER_ASAN 1
#elif defined(__has_feature)
#if __has_feature(address_sanitizer)
#define MOCAP_TEST_UNDER_ASAN 1
#endif
#endif
#ifdef MOCAP_TEST_UNDER_ASAN
constexpr int kRateDivisor = 8;
#else
constexpr int kRateDivisor = 1;
#endif
constexpr int kRigRateHz = 200 / kRateDivisor;  // the 8-camera rigs (1280 x 1024)
// The light rigs (LightRig: 4 cameras, 640 x 512): a camera lost, a camera calibrated 5 cm off.
// 100 Hz, not 200, because a simulated camera is only as punctual as its thread: Aravis's fake
// sleeps to the first tick after it wakes, so a fake woken more than a period late skips a tick
// (a set without that camera) that no real camera would skip. On the shared 2-core machine
// other sessions' time slices (kernel.sched_autogroup_enabled: nice ranks tasks only within one
// session, so neither a RESOURCE_LOCK nor nice keeps them off) delay a thread by 5-10 ms: at
// 200 Hz cameras never unplugged missed 6-38 sets in 6 s, a third of the runs over 0.1 s of
// sets; at 100 Hz none in 8 runs at load 9.
constexpr int kLightRigRateHz = 100 / kRateDivisor;
// A subscriber's queue: the default's 2 s of frames (400 at 200 Hz) at either rate.
constexpr int kSubscriberQueueFrames = 400 / kRateDivisor;
// Bounds on the time mocapd takes to do work (not on the rig's time): the ASan build's CPU work
// takes about three times as long (the flood's 10,000 status requests: 1.4 s, 8-10 s under
// ASan beside other load).
#ifdef MOCAP_TEST_UNDER_ASAN
constexpr double kSlowdown = 3;
#else
constexpr double kSlowdown = 1;
#endif

std::string RigToml(int cameras, int seed) {
  return "[rig]\nsimulated = " + std::to_string(cameras) + "\nsubject_seed = " + std::to_string(seed) +
         "\nrate = " + std::to_string(kRigRateHz) + "\n";
}

// The config ([rig] table) of simulated rig `ro` calibrated with its true cameras, written to
// DIR/calib.json; `edit` may change the calibration first (a knocked camera). "" on failure. No
// wand calibration: 10 s of CI time each, and a rig of 4 cameras cannot calibrate with the wand
// (its L-frame's markers are not all seen by 3 cameras).
std::string CalibratedLightRigToml(const std::string& dir, const sim::LiveRigOptions& ro,
                                   const std::function<void(reconstruction::CalibrationFile*)>& edit = {}) {
  std::unique_ptr<sim::LiveRig> rig;
  if (!sim::LiveRig::Create(ro, &rig).ok()) return "";
  reconstruction::CalibrationFile cal;
  for (const auto& cam : rig->true_cameras()) cal.cameras.push_back({cam});
  if (edit) edit(&cal);
  if (!reconstruction::WriteCalibrationJson(dir + "/calib.json", cal).ok()) return "";
  return "[rig]\nsimulated = " + std::to_string(ro.cameras) + "\nwidth = " + std::to_string(ro.width) +
         "\nheight = " + std::to_string(ro.height) + "\nrate = " + std::to_string(static_cast<int>(ro.rate_hz)) +
         "\nsubject_seed = " + std::to_string(ro.seed) + "\ncalibration = \"calib.json\"\n";
}

// A test of what a fault costs must not also measure how much spare CPU the machine has: the
// 8-camera rig at 1280 x 1024 takes 0.7 of a core to render and detect, this one an eighth.
sim::LiveRigOptions LightRig(double rate_hz, std::uint64_t seed) {
  sim::LiveRigOptions ro;
  ro.cameras = 4;
  ro.width = 640;
  ro.height = 512;
  ro.rate_hz = rate_hz;
  ro.seed = seed;
  return ro;
}

double WallSeconds() {
  return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}

long RssKb(pid_t pid) {
  std::ifstream f("/proc/" + std::to_string(pid) + "/status");
  std::string line;
  while (std::getline(f, line))
    if (line.rfind("VmRSS:", 0) == 0) return std::stol(line.substr(6));
  return -1;
}

// SIGKILL at 20 random moments: during recordings, during a fit, during model.apply.
TEST(DaemonFaults, KilledAtRandomMomentsLosesAtMostTheLast100ms) {
  const std::string dir = testing::MakeTempDir("mocapd-kill");
  DaemonProcess d(dir, RigToml(8, 2));
  ASSERT_OK(d.Start());
  std::unique_ptr<ControlClient> c;
  ASSERT_OK(d.Connect(&c));
  ASSERT_OK(testing::CalibrateRigAndSelectSubject(c.get(), 10, "S01"));
  json first = Call(c.get(), "record.start", {{"movement", "static"}, {"sim_duration_scale", 0.5}});
  ASSERT_EQ(first["coverage"]["ok"], true) << first.dump();

  std::mt19937 rng(17);
  const std::string db = d.state_dir() + "/" + daemon::Store::kFileName;
  int interrupted_checked = 0;
  for (int cycle = 0; cycle < 20; ++cycle) {
    SCOPED_TRACE("cycle " + std::to_string(cycle));
    // What is on disk before the kill.
    const json calibrations = Call(c.get(), "calibration.list")["calibrations"];
    const json models = Call(c.get(), "model.list", {{"subject", "S01"}})["models"];
    std::vector<std::string> model_json;
    for (const json& m : models)
      model_json.push_back(Call(c.get(), "export", {{"kind", "model"}, {"id", m["version"]},
                                                    {"format", "json"}, {"inline", true}, {"subject", "S01"}})["content"]);
    const int kind = cycle % 5;  // 0-2: recording, 3: fit, 4: model.apply
    std::int64_t id = 0;
    double killed_at = 0;
    // A subscriber notes the last frame the daemon had before the kill: on a machine too loaded
    // to keep the rig live, frames are lost at the cameras, not by the recorder, and what is
    // measured is what the recorder lost of the frames that existed.
    std::unique_ptr<ControlClient> watcher;
    ASSERT_OK(d.Connect(&watcher));
    Call(watcher.get(), "subscribe", {{"streams", {"pose"}}});
    double last_streamed = 0;
    if (kind <= 2) {
      ASSERT_OK(c->Send("record.start", {{"movement", "squats"}}, &id));
      const auto until = std::chrono::steady_clock::now() +
                         std::chrono::milliseconds(300 + rng() % 1500);
      while (std::chrono::steady_clock::now() < until) {
        json ev;
        bool got = false;
        if (!watcher->NextEvent(&ev, 5, &got).ok()) break;
        if (got && ev.value("event", "") == "frame") last_streamed = ev["t_mid"];
      }
    } else if (kind == 3) {
      ASSERT_OK(c->Send("fit.start", json::object(), &id));
      std::this_thread::sleep_for(std::chrono::milliseconds(rng() % 1500));
    } else {
      ASSERT_OK(c->Send("model.apply", json::object(), &id));
      std::this_thread::sleep_for(std::chrono::milliseconds(rng() % 5));
    }
    killed_at = WallSeconds();
    d.Kill(SIGKILL);
    c.reset();
    watcher.reset();

    EXPECT_EQ(testing::RawSql(db, "PRAGMA integrity_check"), "ok");
    ASSERT_OK(d.Start());
    ASSERT_OK(d.Connect(&c));
    // Nothing that was stored changed.
    EXPECT_EQ(Call(c.get(), "calibration.list")["calibrations"], calibrations);
    const json models_after = Call(c.get(), "model.list", {{"subject", "S01"}})["models"];
    ASSERT_GE(models_after.size(), models.size());
    for (std::size_t k = 0; k < models.size(); ++k) {
      EXPECT_EQ(models_after[k]["version"], models[k]["version"]);
      EXPECT_EQ(Call(c.get(), "export", {{"kind", "model"}, {"id", models[k]["version"]},
                                         {"format", "json"}, {"inline", true}, {"subject", "S01"}})["content"],
                model_json[k]);
    }
    EXPECT_EQ(Call(c.get(), "subject.list")["subjects"].size(), 1u);
    EXPECT_EQ(Call(c.get(), "status")["subject"]["name"], "S01") << "the live subject was not resumed";
    if (kind <= 2) {
      // The recording: interrupted, its frames up to 100 ms before the kill, exportable.
      const json recs = Call(c.get(), "recording.list")["recordings"];
      ASSERT_FALSE(recs.empty());
      const json& last = recs.back();
      EXPECT_EQ(last["state"], "interrupted") << last.dump();
      std::unique_ptr<daemon::Store> store;
      daemon::StoreOptions so;
      so.mark_interrupted_recordings = false;
      ASSERT_OK(daemon::Store::Open(d.state_dir(), &store, so));
      std::vector<daemon::RecordedFrame> frames;
      ASSERT_OK(store->ReadFrames(last["id"], &frames));
      ASSERT_GT(last_streamed, 0) << "no frame flowed during the recording";
      ASSERT_FALSE(frames.empty());
      // The rig's clock is the host's wall clock (the fake cameras' timestamps).
      const double lost_s = killed_at - frames.back().time_s;
      const double behind_stream_s = last_streamed - frames.back().time_s;
      std::printf("cycle %d: killed %.3f s after the last stored frame (%zu frames), which is %.3f s "
                  "before the last frame streamed\n", cycle, lost_s, frames.size(), behind_stream_s);
      EXPECT_LE(behind_stream_s, 0.100);
      EXPECT_GT(lost_s, -0.05);
      const std::string c3d = dir + "/interrupted.c3d";
      Call(c.get(), "export", {{"kind", "recording"}, {"id", last["id"]}, {"format", "c3d"}, {"path", c3d}});
      formats::MarkerTrial trial;
      {
        const Status s = formats::ReadC3d(c3d, &trial);
        EXPECT_TRUE(s.ok()) << s.message();
        EXPECT_GE(trial.num_frames(), static_cast<int>(frames.size()));
      }
      ++interrupted_checked;
    }
    Call(c.get(), "subject.select", {{"name", "S01"}});
    // The rig live again and the subject tracked before the next moment is drawn.
    for (int i = 0; i < 100 && Call(c.get(), "status")["tracker"]["state"] != "tracking"; ++i)
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  EXPECT_EQ(interrupted_checked, 12);
  EXPECT_EQ(d.Stop(), 0) << d.LogTail();
  EXPECT_EQ(testing::RawSql(db, "PRAGMA integrity_check"), "ok");
}

// The storage fills up mid-recording (a 24 MB tmpfs in a mount namespace of the daemon's own):
// the recording stops with an error naming the cause, what was written stays readable, tracking
// and the stream go on, and recording works again once space is freed.
TEST(DaemonFaults, DiskFullStopsTheRecordingNotTheRig) {
  if (geteuid() != 0 || system("command -v unshare >/dev/null 2>&1") != 0)
    GTEST_SKIP() << "needs root and unshare(1) for a tmpfs in a private mount namespace";
  const std::string dir = testing::MakeTempDir("mocapd-full");
  DaemonProcess d(dir, RigToml(8, 4));
  std::filesystem::create_directories(d.state_dir());
  d.SetWrapper({"unshare", "-m", "--propagation", "private", "sh", "-c",
                "mount -t tmpfs -o size=24m tmpfs \"$0\" && exec \"$@\"", d.state_dir()});
  ASSERT_OK(d.Start());
  std::unique_ptr<ControlClient> c;
  ASSERT_OK(d.Connect(&c));
  ASSERT_OK(testing::CalibrateRigAndSelectSubject(c.get(), 10, "S01"));
  // Fill the tmpfs (seen from outside through the daemon's /proc/PID/root) but for ~1.5 MB:
  // about three seconds of recording at 200 Hz (24 at the sanitized build's 25 Hz; the
  // recording asks for 30).
  const std::string inside = "/proc/" + std::to_string(d.pid()) + "/root" + d.state_dir();
  const json before = Call(c.get(), "status");
  const std::uint64_t free_bytes = before["storage"]["free_bytes"];
  ASSERT_LT(free_bytes, 25u << 20) << "the state directory is not the small tmpfs";
  {
    std::ofstream filler(inside + "/filler", std::ios::binary);
    const std::string block(1 << 20, 'x');
    for (std::uint64_t left = free_bytes; left > (3u << 19); left -= block.size())
      filler.write(block.data(), block.size());
  }
  ControlReply full;
  ASSERT_OK(c->Call("record.start", {{"movement", "squats"}, {"duration_s", 30}}, &full));
  EXPECT_EQ(full.error_code, "failed");
  EXPECT_NE(full.error_message.find("full"), std::string::npos) << full.error_message;
  EXPECT_NE(full.error_message.find("frames kept"), std::string::npos) << full.error_message;
  EXPECT_NE(d.Log().find("stopped"), std::string::npos);
  // The rig goes on: tracking, the stream.
  const json during = Call(c.get(), "status");
  EXPECT_EQ(during["tracker"]["state"], "tracking");
  std::unique_ptr<ControlClient> watcher;
  ASSERT_OK(d.Connect(&watcher));
  Call(watcher.get(), "subscribe", {{"streams", {"markers"}}});
  int streamed = 0;
  for (int i = 0; i < 50; ++i) {
    json ev;
    bool got = false;
    ASSERT_OK(watcher->NextEvent(&ev, 1000, &got));
    streamed += got && ev.value("event", "") == "frame";
  }
  EXPECT_GE(streamed, 45);
  // Space freed: the failed recording is marked so and readable; recording works again.
  std::filesystem::remove(inside + "/filler");
  std::this_thread::sleep_for(std::chrono::milliseconds(1500));
  const json recs = Call(c.get(), "recording.list")["recordings"];
  ASSERT_EQ(recs.size(), 1u);
  EXPECT_EQ(recs[0]["state"], "failed");
  EXPECT_GT(recs[0]["frames"].get<int>(), 0.5 * kRigRateHz);  // half a second
  json again = Call(c.get(), "record.start", {{"movement", "static"}, {"sim_duration_scale", 0.5}});
  EXPECT_EQ(again["coverage"]["ok"], true) << again.dump();
  EXPECT_EQ(d.Stop(), 0) << d.LogTail();
}

TEST(DaemonFaults, ACameraCalibratedFiveCentimetresOffIsNamedInStatus) {
  // The simulated rig's true calibration, written as the config's calibration file with camera 2
  // moved by 5 cm: what a knocked camera looks like to the daemon.
  const std::string dir = testing::MakeTempDir("mocapd-miscalibrated");
  std::string knocked_id;
  const std::string toml = CalibratedLightRigToml(dir, LightRig(kLightRigRateHz, 6),
                                                  [&](reconstruction::CalibrationFile* cal) {
    const Eigen::Vector3d moved(0.03, -0.03, 0.028);  // 5.0 cm
    cal->cameras[2].camera.t -= cal->cameras[2].camera.R * moved;
    knocked_id = cal->cameras[2].camera.id;
  });
  ASSERT_FALSE(toml.empty());
  DaemonProcess d(dir, toml);
  ASSERT_OK(d.Start());
  std::unique_ptr<ControlClient> c;
  ASSERT_OK(d.Connect(&c));
  json st;
  const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(30);
  while (std::chrono::steady_clock::now() < until) {
    st = Call(c.get(), "status");
    if (!st["health"]["calibration_suspect"].empty()) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
  }
  std::printf("health %s\n", st["health"].dump().c_str());
  for (const json& cam : st["cameras"])
    std::printf("%s: reprojection %s px\n", cam["id"].get<std::string>().c_str(), cam["reprojection_px"].dump().c_str());
  ASSERT_EQ(st["health"]["calibration_suspect"], json::array({knocked_id})) << st.dump();
  for (int cam = 0; cam < 4; ++cam) {
    const json& k = st["cameras"][cam];
    EXPECT_EQ(k["calibration_suspect"], cam == 2) << cam;
    ASSERT_TRUE(k["reprojection_px"].is_number()) << k.dump();
    if (cam == 2) EXPECT_GT(k["reprojection_px"].get<double>(), 5.0);
    else EXPECT_LT(k["reprojection_px"].get<double>(), 1.0) << cam;
  }
  EXPECT_EQ(st["health"]["nonfinite_centroids"], 0);
  EXPECT_EQ(st["health"]["overfull_sets"], 0);
  EXPECT_EQ(st["sets"]["dropped"], 0);
}

// Seconds from `since` until camera `k` streams again (connected, and 0.1 s of frames past
// `frames_then`), polling `status` on `c` for up to `limit_s`; -1 if it did not. `last`: the
// last status.
double SecondsUntilStreaming(ControlClient* c, int k, std::uint64_t frames_then,
                             std::chrono::steady_clock::time_point since, double limit_s, json* last) {
  while (std::chrono::steady_clock::now() - since < std::chrono::duration<double>(limit_s)) {
    *last = Call(c, "status");
    if ((*last)["cameras"][k]["connected"] == true &&
        (*last)["cameras"][k]["frames"].get<std::uint64_t>() > frames_then + 0.1 * kLightRigRateHz)
      return std::chrono::duration<double>(std::chrono::steady_clock::now() - since).count();
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  return -1;
}

// The camera-loss tests' recording `id` on the light rig, once finished: tracked throughout,
// the cameras not lost under 0.1 s of sets missed each (on a loaded machine any camera may
// miss a stray set). Returns the lost camera's gap (null when it has none).
json LostCameraGap(ControlClient* c, std::int64_t id, const std::string& lost_id) {
  ControlReply rec;
  if (Status s = c->Wait(id, &rec); !s.ok() || !rec.ok()) {
    ADD_FAILURE() << "the recording: " << s.message() << rec.error_message;
    return nullptr;
  }
  EXPECT_GT(rec.result["tracking_fraction"].get<double>(), 0.95) << rec.result.dump().substr(0, 500);
  const json gaps = rec.result["camera_gaps"];
  std::printf("camera gaps: %s\n", gaps.dump().c_str());
  json lost;
  for (const json& g : gaps) {
    if (g["camera"] == lost_id) lost = g;
    else EXPECT_LT(g["missing_frames"].get<int>(), 0.1 * kLightRigRateHz) << gaps.dump();
  }
  EXPECT_FALSE(lost.is_null()) << lost_id << " has no gap: " << gaps.dump();
  return lost;
}

// A camera unplugged mid-recording and plugged back: the others go on recording, sets are
// triangulated from the cameras left, status says so, the recording notes the gap, and the camera
// is taken back within 2 s of its return without a restart.
// On the light rig (CalibratedLightRigToml: 3 cameras left still see the subject).
TEST(DaemonFaults, CameraLostMidRecordingIsNotedAndTakenBack) {
  const std::string dir = testing::MakeTempDir("mocapd-unplug");
  const std::string toml = CalibratedLightRigToml(dir, LightRig(kLightRigRateHz, 5));
  ASSERT_FALSE(toml.empty());
  DaemonProcess d(dir, toml);
  ASSERT_OK(d.Start());
  std::unique_ptr<ControlClient> c, other;
  ASSERT_OK(d.Connect(&c));
  ASSERT_OK(d.Connect(&other));
  const json rig = Call(c.get(), "status")["rig"];
  Call(c.get(), "subject.create", {{"name", "S01"}, {"height_m", rig["virtual_subject"]["height_m"]}});
  Call(c.get(), "subject.select", {{"name", "S01"}});
  std::this_thread::sleep_for(std::chrono::seconds(2));
  std::int64_t id = 0;
  ASSERT_OK(c->Send("record.start", {{"movement", "squats"}, {"duration_s", 6}}, &id));
  std::this_thread::sleep_for(std::chrono::seconds(1));
  Call(other.get(), "sim.camera", {{"camera", 3}, {"present", false}});
  std::this_thread::sleep_for(std::chrono::milliseconds(700));
  const json away = Call(other.get(), "status");
  EXPECT_EQ(away["cameras"][3]["connected"], false) << away["cameras"].dump();
  EXPECT_EQ(away["cameras"][2]["connected"], true);
  EXPECT_EQ(away["tracker"]["state"], "tracking");
  std::this_thread::sleep_for(std::chrono::milliseconds(800));
  Call(other.get(), "sim.camera", {{"camera", 3}, {"present", true}});
  const auto back_at = std::chrono::steady_clock::now();
  const std::uint64_t frames_then = Call(other.get(), "status")["cameras"][3]["frames"];
  json st;
  const double back_s = SecondsUntilStreaming(other.get(), 3, frames_then, back_at, 3, &st);
  std::printf("camera 3 streaming again %.2f s after its return\n", back_s);
  EXPECT_GE(back_s, 0) << "the camera was not taken back";
  EXPECT_LE(back_s, 2.0);
  // The unplugged camera's gap: from the unplug to the first sets after its return, 1.5 s plus
  // the reopen (more than 1.25 s, less than 4 s of sets).
  const json gap = LostCameraGap(c.get(), id, "MOCAPSIM3");
  ASSERT_FALSE(gap.is_null());
  EXPECT_GT(gap["missing_frames"].get<int>(), 1.25 * kLightRigRateHz) << gap.dump();
  EXPECT_LT(gap["missing_frames"].get<int>(), kLightRigRateHz * 4) << gap.dump();
  EXPECT_NE(d.Log().find("MOCAPSIM3 missing from"), std::string::npos);
  // The recorder's commits were each followed by a WAL sync of its own (power-cut durability,
  // daemon/recorder.h), none failed.
  const json storage = Call(c.get(), "status")["storage"];
  std::printf("recorder: slowest recent commit %.2f ms, WAL sync %.2f ms\n",
              storage["commit_ms_max"].get<double>(), storage["wal_sync_ms_max"].get<double>());
  EXPECT_GT(storage["wal_sync_ms_max"].get<double>(), 0.0) << storage.dump();
  EXPECT_EQ(storage["wal_sync_failures"], 0) << storage.dump();
  EXPECT_EQ(d.Stop(), 0) << d.LogTail();
}

// A GigE Vision camera lost under the real mocapd (issue 17, item 2): Aravis's GigE fake on
// loopback, run by this test, joins the light rig as its fifth camera (config.h: real cameras
// listed after the fakes), over real GVCP/GVSP sockets. Stopped mid-recording (its GVCP answers
// and stream packets stop, as when a cable is pulled: Aravis's heartbeat fails), then started
// again. It draws no marker: what counts is that it streams, leaves and is taken back while
// the other cameras go on.
TEST(DaemonFaults, GigECameraStoppedMidRecordingIsNotedAndTakenBack) {
  const std::string dir = testing::MakeTempDir("mocapd-gige-lost");
  drivers::GvFakeCamera gige("MOCAPGV17", 4,
                             [](int, std::uint64_t, std::uint8_t* data, int w, int h,
                                std::ptrdiff_t stride, drivers::PixelFormat) {
                               for (int y = 0; y < h; ++y) std::fill(data + y * stride, data + y * stride + w, 0);
                             },
                             640, 512);
  ASSERT_OK(gige.Create(60));  // test_aravis_gige's fakes may hold 127.0.0.1 for a while
  const sim::LiveRigOptions ro = LightRig(kLightRigRateHz, 7);
  std::string toml = CalibratedLightRigToml(dir, ro, [&](reconstruction::CalibrationFile* cal) {
    auto gige_camera = cal->cameras[0];  // any pose: it sees nothing
    gige_camera.camera.id = gige.device_id();
    cal->cameras.push_back(gige_camera);
  });
  ASSERT_FALSE(toml.empty());
  // Jumbo packets on loopback (MTU 64 KiB): 40 packets a frame, not 220. A receive buffer of
  // 4 MiB: with Aravis's "auto" (one payload) a descheduled stream thread lost up to every other
  // frame whole at the socket (51-85 of 100 fps delivered; counted `not_received` since), and
  // the lost camera's gap would not be the time it was away.
  toml += "packet_size = 8192\nsocket_buffer_bytes = 4194304\n";
  for (int k = 0; k < ro.cameras; ++k) toml += "[[rig.camera]]\nid = \"MOCAPSIM" + std::to_string(k) + "\"\n";
  toml += "[[rig.camera]]\nid = \"" + gige.device_id() + "\"\n";
  DaemonProcess d(dir, toml);
  NotifySocket notify(dir + "/notify");  // STATUS=, as systemd would get it
  ASSERT_TRUE(notify.bound());
  d.SetEnvironment({{"NOTIFY_SOCKET", dir + "/notify"}});
  ASSERT_OK(d.Start());
  std::unique_ptr<ControlClient> c, other;
  ASSERT_OK(d.Connect(&c));
  ASSERT_OK(d.Connect(&other));
  const int kGige = ro.cameras;
  json st = Call(c.get(), "status");
  ASSERT_EQ(st["cameras"].size(), static_cast<std::size_t>(ro.cameras + 1)) << st["cameras"].dump();
  ASSERT_EQ(st["cameras"][kGige]["id"], gige.device_id());
  Call(c.get(), "subject.create", {{"name", "S01"}, {"height_m", st["rig"]["virtual_subject"]["height_m"]}});
  Call(c.get(), "subject.select", {{"name", "S01"}});
  std::this_thread::sleep_for(std::chrono::seconds(2));
  st = Call(c.get(), "status");
  EXPECT_EQ(st["cameras"][kGige]["connected"], true) << st["cameras"][kGige].dump();
  EXPECT_GT(st["cameras"][kGige]["frames"].get<double>(), kLightRigRateHz) << st["cameras"].dump();
  {
    // Every frame the fake sent in a second is in `status`: delivered, incomplete, dropped or
    // not received (whole frames lost before mocapd took them: drivers/camera_source.h).
    auto counted = [&](const json& cam) {
      return cam["frames"].get<double>() + cam["incomplete"].get<double>() + cam["dropped"].get<double>() +
             cam["not_received"].get<double>();
    };
    const double sent0 = static_cast<double>(gige.FramesDrawn());
    const double counted0 = counted(Call(c.get(), "status")["cameras"][kGige]);
    std::this_thread::sleep_for(std::chrono::seconds(1));
    const double sent1 = static_cast<double>(gige.FramesDrawn());
    st = Call(c.get(), "status");
    std::printf("GigE camera: %.0f frames sent in 1 s, %.0f counted (%s)\n", sent1 - sent0,
                counted(st["cameras"][kGige]) - counted0, st["cameras"][kGige].dump().c_str());
    EXPECT_NEAR(counted(st["cameras"][kGige]) - counted0, sent1 - sent0, 3);
  }
  std::int64_t id = 0;
  ASSERT_OK(c->Send("record.start", {{"movement", "squats"}, {"duration_s", 10}}, &id));
  std::this_thread::sleep_for(std::chrono::seconds(1));
  gige.Destroy();
  const auto gone_at = std::chrono::steady_clock::now();
  auto since_gone = [&] { return std::chrono::duration<double>(std::chrono::steady_clock::now() - gone_at).count(); };
  // Noted in a gap once it has sent nothing for max(0.5 s, 20 periods) while the others deliver
  // (daemon/capture_pipeline.h camera_silence_s): status says so (`silent_s`, its `problem`)
  // and so does STATUS=, long before Aravis's heartbeat gives the control channel up (~6 s).
  double gap_s = -1, status_line_s = -1, lost_s = -1;
  std::string status_line;
  while (since_gone() < 8) {
    st = Call(other.get(), "status");
    if (gap_s < 0 && st["cameras"][kGige]["silent_s"].is_number()) {
      gap_s = since_gone();
      EXPECT_EQ(st["cameras"][kGige]["connected"], true) << "Aravis gave up first: " << st["cameras"][kGige].dump();
      EXPECT_NE(st["cameras"][kGige]["problem"].dump().find("no frame for"), std::string::npos)
          << st["cameras"][kGige].dump();
      for (int k = 0; k < ro.cameras; ++k) EXPECT_TRUE(st["cameras"][k]["silent_s"].is_null()) << k;
      status_line = notify.WaitForStatus("no frames from " + gige.device_id(), 2);
      status_line_s = since_gone();
    }
    if (st["cameras"][kGige]["connected"] == false) {
      lost_s = since_gone();
      break;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  std::printf("GigE camera in a gap (status) %.2f s after it stopped, STATUS= by %.2f s (%s); "
              "lost (Aravis's heartbeat) %.2f s after\n", gap_s, status_line_s, status_line.c_str(), lost_s);
  ASSERT_GE(gap_s, 0) << "the stopped GigE camera was never noted silent: " << st["cameras"].dump();
  // 0.5 s of silence at 100 Hz (20 periods are 0.2 s), then the status poll's 50 ms: measured
  // 0.51-0.53 s at load 10-14 (BENCHMARKS.md "Faults"; under ASan's 12 Hz 1.71 s against its
  // 1.67 s of silence); 0.5 s more for a loaded machine's status round trip.
  const double silence_s = std::max(0.5, 20.0 / kLightRigRateHz);
  EXPECT_LE(gap_s, silence_s + 0.5 * kSlowdown);
  EXPECT_FALSE(status_line.empty()) << "no STATUS= naming the silent camera";
  EXPECT_NE(d.Log().find("camera " + gige.device_id() + " delivered no frame for"), std::string::npos) << d.LogTail();
  ASSERT_GE(lost_s, 0) << "the stopped GigE camera still reads connected: " << st["cameras"].dump();
  for (int k = 0; k < ro.cameras; ++k) EXPECT_EQ(st["cameras"][k]["connected"], true) << k;
  EXPECT_EQ(st["tracker"]["state"], "tracking");
  ASSERT_OK(gige.Create(10));
  const auto back_at = std::chrono::steady_clock::now();
  const std::uint64_t frames_then = st["cameras"][kGige]["frames"];
  const double back_s = SecondsUntilStreaming(other.get(), kGige, frames_then, back_at, 5, &st);
  std::printf("GigE camera streaming again %.2f s after its return\n", back_s);
  EXPECT_GE(back_s, 0) << "the GigE camera was not taken back: " << st["cameras"].dump();
  EXPECT_LE(back_s, 2.0);
  // Its gap: from the stop to its first sets after the return, what the test measured (the loss
  // takes Aravis's GigE heartbeat about 6 s to notice; the gap starts at the stop all the same)
  // within 0.5 s.
  const json gap = LostCameraGap(c.get(), id, gige.device_id());
  ASSERT_FALSE(gap.is_null());
  const double away_s = lost_s + back_s;
  EXPECT_GT(gap["missing_frames"].get<double>(), (away_s - 0.5) * kLightRigRateHz) << gap.dump();
  EXPECT_LT(gap["missing_frames"].get<double>(), (away_s + 0.5) * kLightRigRateHz) << gap.dump();
  EXPECT_NE(d.Log().find(gige.device_id() + " missing from"), std::string::npos) << d.LogTail();
  EXPECT_EQ(d.Stop(), 0) << d.LogTail();
}

// A raw connection (the client library would refuse to send most of this).
int RawConnect(const std::string& path) {
  const int fd = socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0);
  sockaddr_un addr{};
  addr.sun_family = AF_UNIX;
  std::snprintf(addr.sun_path, sizeof addr.sun_path, "%s", path.c_str());
  if (connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0) {
    close(fd);
    return -1;
  }
  timeval tv{10, 0};
  setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
  return fd;
}

// Reads until `n` lines have arrived or the connection ends; returns them.
std::vector<std::string> ReadLines(int fd, std::size_t n) {
  std::vector<std::string> lines;
  std::string buffer;
  char buf[65536];
  while (lines.size() < n) {
    const ssize_t got = recv(fd, buf, sizeof buf, 0);
    if (got <= 0) break;
    buffer.append(buf, static_cast<std::size_t>(got));
    for (std::size_t nl; (nl = buffer.find('\n')) != std::string::npos;) {
      lines.push_back(buffer.substr(0, nl));
      buffer.erase(0, nl + 1);
    }
  }
  return lines;
}

TEST(DaemonFaults, MisbehavingClientsCannotStopTheRig) {
  const std::string dir = testing::MakeTempDir("mocapd-clients");
  DaemonProcess d(dir, "[rig]\nsimulated = 4\nwidth = 640\nheight = 512\nrate = " +
                           std::to_string(kRigRateHz) + "\n"
                       "[control]\nmax_clients = 256\nsubscriber_queue_frames = " +
                           std::to_string(kSubscriberQueueFrames) + "\n");
  ASSERT_OK(d.Start());
  std::unique_ptr<ControlClient> good;
  ASSERT_OK(d.Connect(&good, 10000));
  Call(good.get(), "subject.create", {{"name", "S01"}, {"height_m", 1.7}});
  // Selected: the markers stream carries every model marker (predicted where unseen), ~4 kB a
  // frame, so a subscriber that does not read falls behind within a second.
  Call(good.get(), "subject.select", {{"name", "S01"}});
  std::this_thread::sleep_for(std::chrono::seconds(1));
  const json before = Call(good.get(), "status");
  const long rss_before = RssKb(d.pid());
  ASSERT_GT(rss_before, 0);

  // Garbage, invalid UTF-8: each a structured error; the connection goes on.
  {
    const int fd = RawConnect(d.socket());
    ASSERT_GE(fd, 0);
    ReadLines(fd, 1);  // hello
    const std::string garbage = std::string("\x00\x01\x02 not json \xff\n", 16) +
                                "{\"id\":1,\"method\":\"st\xc3\x28tus\"}\n";
    ASSERT_EQ(send(fd, garbage.data(), garbage.size(), MSG_NOSIGNAL), static_cast<ssize_t>(garbage.size()));
    const auto replies = ReadLines(fd, 2);
    ASSERT_EQ(replies.size(), 2u);
    for (const std::string& r : replies) EXPECT_NE(r.find("\"parse_error\""), std::string::npos) << r;
    close(fd);
  }
  // A 100 MB line: refused after max_line_bytes, the connection closed.
  {
    const int fd = RawConnect(d.socket());
    ASSERT_GE(fd, 0);
    ReadLines(fd, 1);
    const std::string chunk(1 << 20, 'a');
    std::size_t sent = 0;
    for (int i = 0; i < 100; ++i) {
      const ssize_t n = send(fd, chunk.data(), chunk.size(), MSG_NOSIGNAL);
      if (n <= 0) break;
      sent += static_cast<std::size_t>(n);
    }
    const auto replies = ReadLines(fd, 1);
    ASSERT_EQ(replies.size(), 1u);
    EXPECT_NE(replies[0].find("\"line_too_long\""), std::string::npos) << replies[0];
    EXPECT_LT(sent, 100u << 20) << "the daemon kept reading a line it had refused";
    close(fd);
  }
  // 1,000 connections opened and dropped at once.
  for (int i = 0; i < 1000; ++i) {
    const int fd = RawConnect(d.socket());
    if (fd >= 0) close(fd);
  }
  // 200 idle connections kept open, a subscriber that never reads, 50 clients gone mid-reply.
  std::vector<int> idle;
  for (int i = 0; i < 200; ++i) idle.push_back(RawConnect(d.socket()));
  EXPECT_EQ(std::count(idle.begin(), idle.end(), -1), 0);
  const int sleeper = RawConnect(d.socket());
  {
    const std::string sub = "{\"id\":1,\"method\":\"subscribe\",\"params\":{\"streams\":[\"markers\",\"points\",\"pose\",\"status\"]}}\n";
    ASSERT_EQ(send(sleeper, sub.data(), sub.size(), MSG_NOSIGNAL), static_cast<ssize_t>(sub.size()));
  }
  for (int i = 0; i < 50; ++i) {
    const int fd = RawConnect(d.socket());
    const std::string req = "{\"id\":1,\"method\":\"export\",\"params\":{\"kind\":\"model\",\"id\":1,\"subject\":\"S01\",\"format\":\"json\",\"inline\":true}}\n";
    send(fd, req.data(), req.size(), MSG_NOSIGNAL);
    close(fd);
  }
  // A flood: 10,000 requests pipelined as fast as the socket takes them, the replies read by
  // another thread; meanwhile a well-behaved client is answered promptly.
  const int flood = RawConnect(d.socket());
  ASSERT_GE(flood, 0);
  std::atomic<std::size_t> flood_replies{0};
  std::thread reader([&] { flood_replies = ReadLines(flood, 10001).size(); });
  const auto t0 = std::chrono::steady_clock::now();
  std::string burst;
  for (int i = 0; i < 10000; ++i) burst += "{\"id\":" + std::to_string(i) + ",\"method\":\"status\"}\n";
  std::thread writer([&] { send(flood, burst.data(), burst.size(), MSG_NOSIGNAL); });
  double worst_s = 0;
  for (int i = 0; i < 10; ++i) {
    const auto a = std::chrono::steady_clock::now();
    Call(good.get(), "status");
    worst_s = std::max(worst_s, std::chrono::duration<double>(std::chrono::steady_clock::now() - a).count());
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  writer.join();
  reader.join();
  const double flood_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  std::printf("flood: %zu replies (hello included) to 10,000 requests in %.2f s; a good client's "
              "worst status %.3f s\n", flood_replies.load(), flood_s, worst_s);
  EXPECT_EQ(flood_replies.load(), 10001u);
  EXPECT_LT(worst_s, 1.0 * kSlowdown);
  close(flood);

  // The sleeper, when it finally reads, is told how many frames it lost.
  std::this_thread::sleep_for(std::chrono::seconds(2));
  bool told = false;
  {
    std::string buffer;
    char buf[65536];
    const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(5);
    while (!told && std::chrono::steady_clock::now() < until) {
      const ssize_t got = recv(sleeper, buf, sizeof buf, 0);
      if (got <= 0) break;
      buffer.append(buf, static_cast<std::size_t>(got));
      told = buffer.find("\"event\":\"dropped\"") != std::string::npos;
      if (buffer.size() > (1u << 20)) buffer.erase(0, buffer.size() - 64);
    }
  }
  EXPECT_TRUE(told) << "a subscriber that did not read was never told it lost frames";
  close(sleeper);
  for (int fd : idle)
    if (fd >= 0) close(fd);

  const json after = Call(good.get(), "status");
  const long rss_after = RssKb(d.pid());
  std::printf("RSS %ld kB -> %ld kB; frame sets dropped %llu -> %llu; loop dropped %llu -> %llu\n",
              rss_before, rss_after, before["sets"]["dropped"].get<unsigned long long>(),
              after["sets"]["dropped"].get<unsigned long long>(),
              before["tracker"]["loop_dropped"].get<unsigned long long>(),
              after["tracker"]["loop_dropped"].get<unsigned long long>());
  EXPECT_LT(rss_after - rss_before, 100 * 1024) << "memory grew with the clients";
  // The loop took every frame the pipeline handed it: no client held it off.
  EXPECT_EQ(after["tracker"]["loop_dropped"], before["tracker"]["loop_dropped"]);
  EXPECT_EQ(after["tracker"]["recorder_dropped"], 0);
  // The queues' high-water marks: frames went through each, and the loop's never filled.
  for (const char* q : {"frames", "detections", "points", "loop"}) {
    const json& depth = after["queues"][q];
    EXPECT_GE(depth["max"].get<int>(), 1) << q;
    EXPECT_LE(depth["max"].get<int>(), depth["capacity"].get<int>()) << q;
  }
  EXPECT_LT(after["queues"]["loop"]["max"].get<int>(), after["queues"]["loop"]["capacity"].get<int>());
  const std::string log = d.Log();
  EXPECT_NE(log.find("line longer than"), std::string::npos) << "the refused client is not in the log";
  EXPECT_EQ(d.Stop(), 0) << d.LogTail();
}

}  // namespace
}  // namespace mocap
