// drivers/: the simulated camera, frame-id unwrapping, the usbfs check, the hot-plug monitor, and
// a USB removal simulated through the hot-plug hook against Aravis fake cameras.
#include <gtest/gtest.h>
#include <libusb-1.0/libusb.h>

#include <atomic>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <thread>
#include <vector>

#include "drivers/aravis_fake.h"
#include "drivers/simulated_camera.h"
#include "drivers/usb_hotplug.h"
#include "sim/camera_rig.h"
#include "sim/renderer.h"
#include "tests/aravis_test_util.h"

namespace mocap::drivers {
namespace {

using testing::CheckPattern;
using testing::DrawPattern;

SimulatedCameraOptions Small() {
  SimulatedCameraOptions o;
  o.width = 64;
  o.height = 48;
  o.unpaced = true;
  o.first_frame_id = 65530;
  return o;
}

TEST(SimulatedCamera, WrappingIdsPatternAndTimestamps) {
  SimulatedCamera cam(2, DrawPattern, Small());
  CameraSettings s;
  s.pixel_format = PixelFormat::kMono16;
  s.frame_rate_hz = 250;
  ASSERT_TRUE(cam.Open(s).ok());
  ASSERT_TRUE(cam.Start().ok());
  std::uint64_t last = 0, last_ts = 0;
  int wraps = 0;
  std::uint16_t last_id = 0;
  for (int k = 0; k < 20; ++k) {
    Frame f;
    ASSERT_EQ(cam.Grab(&f), GrabResult::kFrame);
    std::uint64_t stamped;
    EXPECT_TRUE(CheckPattern(f, &stamped));
    EXPECT_EQ(stamped, f.sequence);
    EXPECT_EQ(f.camera, 2);
    EXPECT_EQ(f.image.format, PixelFormat::kMono16);
    EXPECT_EQ(f.sequence & 0xFFFF, f.frame_id);  // what frame sync relies on
    if (k > 0) {
      const std::uint64_t step = f.frame_id < last_id ? 2 : 1;  // no id 0: 65535 -> 1
      EXPECT_EQ(f.sequence, last + step);
      EXPECT_EQ(f.device_timestamp_ns - last_ts, step * 4000000u);  // 1 / 250 Hz
      if (f.frame_id < last_id) {
        ++wraps;
        EXPECT_EQ(last_id, 65535);
        EXPECT_EQ(f.frame_id, 1);
      }
    }
    last = f.sequence;
    last_ts = f.device_timestamp_ns;
    last_id = f.frame_id;
    cam.Release(f);
  }
  EXPECT_EQ(wraps, 1);
  EXPECT_EQ(cam.Counters().complete.load(), 20u);
}

TEST(SimulatedCamera, PacedAtTheFrameRate) {
  SimulatedCameraOptions o = Small();
  o.unpaced = false;
  SimulatedCamera cam(0, DrawPattern, o);
  CameraSettings s;
  s.frame_rate_hz = 200;
  ASSERT_TRUE(cam.Open(s).ok());
  ASSERT_TRUE(cam.Start().ok());
  const auto t0 = std::chrono::steady_clock::now();
  for (int k = 0; k < 21; ++k) {
    Frame f;
    ASSERT_EQ(cam.Grab(&f), GrabResult::kFrame);
    cam.Release(f);
  }
  const double s_elapsed = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  EXPECT_GE(s_elapsed, 0.099);  // frame 20 is due 100 ms after frame 0
  EXPECT_LT(s_elapsed, 1.0);
}

TEST(SimulatedCamera, InjectedFaults) {
  SimulatedCamera cam(0, DrawPattern, Small());
  CameraSettings s;
  s.buffer_count = 3;
  ASSERT_TRUE(cam.Open(s).ok());
  ASSERT_TRUE(cam.Start().ok());
  Frame f;
  ASSERT_EQ(cam.Grab(&f), GrabResult::kFrame);
  const std::uint64_t s0 = f.sequence;
  cam.Release(f);
  // Dropped frames never arrive: the sequence jumps.
  cam.DropFrames(3);
  ASSERT_EQ(cam.Grab(&f), GrabResult::kFrame);
  EXPECT_EQ(f.sequence, s0 + 4);
  cam.Release(f);
  // Incomplete frames are counted, not delivered.
  cam.FailFrames(2, FrameStatus::kMissingPackets);
  EXPECT_EQ(cam.Grab(&f), GrabResult::kIncomplete);
  EXPECT_EQ(cam.Grab(&f), GrabResult::kIncomplete);
  EXPECT_EQ(cam.Counters().missing_packets.load(), 2u);
  // A caller holding every buffer: underrun.
  Frame held[3];
  for (Frame& h : held) ASSERT_EQ(cam.Grab(&h), GrabResult::kFrame);
  EXPECT_EQ(cam.Grab(&f), GrabResult::kIncomplete);
  EXPECT_EQ(cam.Counters().underruns.load(), 1u);
  for (Frame& h : held) cam.Release(h);
  // Lost, then back.
  cam.Lose();
  EXPECT_EQ(cam.Grab(&f), GrabResult::kLost);
  EXPECT_EQ(cam.Grab(&f), GrabResult::kLost);
  EXPECT_EQ(cam.State(), CameraState::kLost);
  EXPECT_EQ(cam.Counters().losses.load(), 1u);
  cam.Restore();
  ASSERT_EQ(cam.Grab(&f), GrabResult::kFrame);
  EXPECT_EQ(cam.State(), CameraState::kStreaming);
  EXPECT_EQ(cam.Counters().reopens.load(), 1u);
  EXPECT_GT(f.sequence, held[2].sequence);
  cam.Release(f);
}

TEST(SimulatedCamera, SoftwareTriggerAndBadSettings) {
  SimulatedCamera cam(0, DrawPattern, Small());
  CameraSettings s;
  s.trigger = TriggerMode::kSoftware;
  s.timeout_ms = 30;
  ASSERT_TRUE(cam.Open(s).ok());
  ASSERT_TRUE(cam.Start().ok());
  Frame f;
  EXPECT_EQ(cam.Grab(&f), GrabResult::kTimeout);
  ASSERT_TRUE(cam.Trigger().ok());
  ASSERT_EQ(cam.Grab(&f), GrabResult::kFrame);
  cam.Release(f);

  CameraSettings bad;
  bad.roi_x = 60;
  bad.roi_width = 10;
  Status st = cam.Open(bad);
  ASSERT_FALSE(st.ok());
  EXPECT_NE(st.message().find("does not fit the 64x48 sensor"), std::string::npos) << st.message();
  bad = {};
  bad.buffer_count = 1;
  st = cam.Open(bad);
  ASSERT_FALSE(st.ok());
  EXPECT_NE(st.message().find("buffer_count"), std::string::npos) << st.message();
}

// The simulated camera shows the renderer's scene: the truth's blobs are bright in the frame.
TEST(SimulatedCamera, ShowsTheRenderedScene) {
  const auto rig = sim::MakeCameraRig({});
  std::vector<Eigen::Vector3d> points;
  for (int i = 0; i < 10; ++i) points.emplace_back(0.1 * i - 0.5, 0.05 * i, 0.3 + 0.15 * i);
  sim::Renderer renderer(rig, sim::MakeStaticScene(points));
  SimulatedCameraOptions o;
  o.unpaced = true;
  SimulatedCamera cam(5, renderer.Generator(), o);
  ASSERT_TRUE(cam.Open(CameraSettings{}).ok());
  ASSERT_TRUE(cam.Start().ok());
  Frame f;
  ASSERT_EQ(cam.Grab(&f), GrabResult::kFrame);
  sim::FrameTruth truth;
  renderer.Truth(5, f.sequence, &truth);
  ASSERT_GE(truth.blobs.size(), 5u);
  for (const sim::BlobTruth& b : truth.blobs) {
    const int x = int(std::lround(b.drawn.x())), y = int(std::lround(b.drawn.y()));
    EXPECT_GT(f.image.row8(y)[x], 100) << "marker " << b.marker;
  }
  EXPECT_LT(f.image.row8(0)[0], 20);
  cam.Release(f);
}

std::string WriteTemp(const std::string& name, const std::string& text) {
  std::filesystem::create_directories(MOCAP_TEST_TMP);
  const std::string path = std::string(MOCAP_TEST_TMP) + "/" + name;
  std::ofstream(path) << text;
  return path;
}

TEST(Usbfs, TooSmallSaysHowToFixIt) {
  CameraSettings s;  // 16 buffers, Mono8
  const std::size_t need = UsbfsBytesNeeded(8, s, 1280, 1024);
  EXPECT_EQ(need, 8u * 16u * 1280u * 1024u);
  const std::string small = WriteTemp("usbfs_16", "16\n");
  Status st = CheckUsbfsMemory(need, small);
  ASSERT_FALSE(st.ok());
  EXPECT_NE(st.message().find("too small"), std::string::npos) << st.message();
  EXPECT_NE(st.message().find("160 MB"), std::string::npos) << st.message();
  EXPECT_NE(st.message().find("echo 1000 > " + small), std::string::npos) << st.message();
  EXPECT_NE(st.message().find("usbcore.usbfs_memory_mb=1000"), std::string::npos);
  EXPECT_TRUE(CheckUsbfsMemory(need, WriteTemp("usbfs_2000", "2000\n")).ok());
  EXPECT_TRUE(CheckUsbfsMemory(need, WriteTemp("usbfs_0", "0\n")).ok());  // unlimited
  st = CheckUsbfsMemory(need, WriteTemp("usbfs_bad", "lots\n"));
  ASSERT_FALSE(st.ok());
  EXPECT_NE(st.message().find("not a number"), std::string::npos) << st.message();
  st = CheckUsbfsMemory(need, std::string(MOCAP_TEST_TMP) + "/no_such_file");
  ASSERT_FALSE(st.ok());
  EXPECT_NE(st.message().find("no_such_file"), std::string::npos) << st.message();
}

// Where this libusb has hot-plug, the monitor must start for real (its libusb thread running, the
// callback registered): a monitor that silently fails would leave USB cameras to the polling
// fallback without anyone noticing. Where it has none, Start() says so.
TEST(UsbHotplug, StartsForRealWhereLibusbHasHotplugOrSaysWhy) {
  std::atomic<int> events{0};
  UsbHotplugMonitor monitor([&](UsbEvent, const UsbDeviceInfo&) { ++events; });
  const bool has_hotplug = libusb_has_capability(LIBUSB_CAP_HAS_HOTPLUG) != 0;
  std::printf("libusb %s hot-plug\n", has_hotplug ? "has" : "has no");
  for (int round = 0; round < 2; ++round) {
    Status st = monitor.Start();
    if (has_hotplug) ASSERT_TRUE(st.ok()) << st.message();
    if (st.ok()) {
      EXPECT_TRUE(monitor.running());
    } else {
      EXPECT_NE(st.message().find("USB hot-plug"), std::string::npos) << st.message();
      EXPECT_FALSE(monitor.running());
      std::printf("hot-plug unavailable here: %s\n", st.message().c_str());
    }
    monitor.Stop();
    EXPECT_FALSE(monitor.running());
    monitor.Stop();  // harmless twice
  }
  const int before = events.load();  // USB3 Vision devices present, if any (none in CI)
  monitor.Inject(UsbEvent::kLeft, UsbDeviceInfo{0x1234, 0x5678, 1, 2, "X"});
  EXPECT_EQ(events.load(), before + 1);
}

// A USB camera unplugged mid-stream (simulated: the fake device is made absent and the hot-plug
// hook reports it left): it is marked lost, the other cameras go on, and it is reopened when the
// hook reports it arrived again.
TEST(UsbHotplug, SimulatedRemovalLosesOneCameraAndReopensIt) {
  FakeRigOptions ro;
  ro.cameras = 3;
  ro.width = 160;
  ro.height = 128;
  AravisFakeRig rig(ro, DrawPattern);
  std::vector<std::unique_ptr<AravisCamera>> cams;
  CameraSettings s;
  s.frame_rate_hz = 200;
  s.timeout_ms = 100;
  for (int i = 0; i < 3; ++i) {
    AravisCameraOptions o;
    o.auto_reopen = false;  // only the arrival event may bring it back
    cams.push_back(rig.MakeCamera(i, o));
    ASSERT_TRUE(cams[i]->Open(s).ok());
    ASSERT_TRUE(cams[i]->Start().ok());
  }
  UsbHotplugMonitor monitor([&](UsbEvent e, const UsbDeviceInfo& d) {
    for (int i = 0; i < 3; ++i) {
      if (rig.serial(i) != d.serial) continue;
      if (e == UsbEvent::kLeft) cams[i]->NotifyRemoved();
      else cams[i]->NotifyArrived();
    }
  });
  std::atomic<bool> stop{false};
  std::atomic<int> frames[3] = {0, 0, 0};
  std::atomic<int> bad{0};
  std::vector<std::thread> threads;
  for (int i = 0; i < 3; ++i) {
    threads.emplace_back([&, i] {
      std::uint64_t last = 0;
      bool any = false;
      while (!stop.load()) {
        Frame f;
        if (cams[i]->Grab(&f) != GrabResult::kFrame) continue;
        std::uint64_t stamped;
        // The image drawn for a sequence is the frame delivered with it, also after the reopen.
        if (!CheckPattern(f, &stamped) || stamped != f.sequence || (any && f.sequence <= last)) {
          ++bad;
        }
        last = f.sequence;
        any = true;
        ++frames[i];
        cams[i]->Release(f);
      }
    });
  }
  auto wait_for = [](auto pred, double seconds) {
    const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(seconds);
    while (!pred() && std::chrono::steady_clock::now() < end) {
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
    return pred();
  };
  ASSERT_TRUE(wait_for([&] { return frames[0] > 20 && frames[1] > 20 && frames[2] > 20; }, 5));

  rig.SetPresent(1, false);
  monitor.Inject(UsbEvent::kLeft, UsbDeviceInfo{0, 0, 0, 0, rig.serial(1)});
  ASSERT_TRUE(wait_for([&] { return cams[1]->State() == CameraState::kLost; }, 2));
  EXPECT_EQ(cams[1]->Counters().losses.load(), 1u);
  const int lost_at = frames[1], others_at = frames[0] + frames[2];
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  EXPECT_EQ(frames[1].load(), lost_at);                 // nothing from the lost camera
  EXPECT_GE(frames[0] + frames[2] - others_at, 40);     // the others went on (~80 expected)
  EXPECT_EQ(cams[1]->State(), CameraState::kLost);      // no arrival: still lost

  rig.SetPresent(1, true);
  monitor.Inject(UsbEvent::kArrived, UsbDeviceInfo{0, 0, 0, 0, rig.serial(1)});
  ASSERT_TRUE(wait_for([&] { return frames[1] > lost_at + 20; }, 5));
  EXPECT_EQ(cams[1]->State(), CameraState::kStreaming);
  EXPECT_EQ(cams[1]->Counters().reopens.load(), 1u);
  stop = true;
  for (auto& t : threads) t.join();
  EXPECT_EQ(bad.load(), 0);
  EXPECT_EQ(cams[0]->Counters().losses.load(), 0u);
  EXPECT_EQ(cams[2]->Counters().losses.load(), 0u);
}

}  // namespace
}  // namespace mocap::drivers
