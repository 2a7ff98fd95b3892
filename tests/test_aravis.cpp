// The Aravis backend against Aravis's own in-process fake cameras (drivers/aravis_fake.h): the
// real arv_camera / arv_stream code paths, images from our generator.
#include <arv.h>
#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <thread>
#include <vector>

#include "drivers/aravis_camera.h"
#include "drivers/aravis_fake.h"
#include "sim/camera_rig.h"
#include "sim/renderer.h"
#include "sim/simulate.h"
#include "tests/aravis_test_util.h"
#include "tests/cpu_time_test_util.h"


namespace mocap::drivers {
namespace {

using testing::CheckPattern;
using testing::DrawPattern;
using testing::IdOf;

FakeRigOptions SmallRig(int n) {
  FakeRigOptions o;
  o.cameras = n;
  o.width = 320;
  o.height = 256;
  return o;
}

TEST(AravisFake, CamerasStreamWithSettingsReadBackAndWrappingIds) {
  AravisFakeRig rig(SmallRig(4), DrawPattern);
  CameraSettings s;
  s.exposure_us = 800;
  s.gain_db = 2;
  s.frame_rate_hz = 500;
  s.roi_x = 16;
  s.roi_y = 8;
  s.roi_width = 256;
  s.roi_height = 192;
  s.pixel_format = PixelFormat::kMono16;
  s.buffer_count = 8;
  std::vector<std::unique_ptr<AravisCamera>> cams;
  for (int i = 0; i < rig.size(); ++i) {
    cams.push_back(rig.MakeCamera(i));
    ASSERT_TRUE(cams.back()->Open(s).ok()) << cams.back()->Open(s).message();
    const AppliedSettings& a = cams.back()->Applied();
    EXPECT_DOUBLE_EQ(a.exposure_us, 800);
    EXPECT_DOUBLE_EQ(a.gain_db, 2);
    EXPECT_NEAR(a.frame_rate_hz, 500, 1.0);  // the fake stores the period in whole us
    EXPECT_EQ(a.roi_x, 16);
    EXPECT_EQ(a.roi_y, 8);
    EXPECT_EQ(a.width, 256);
    EXPECT_EQ(a.height, 192);
    EXPECT_EQ(a.pixel_format, PixelFormat::kMono16);
    EXPECT_EQ(a.trigger_source, "");
  }
  // 200 frames per camera: the fakes' ids start at 65401, so every camera wraps.
  constexpr int kFrames = 200;
  std::vector<std::thread> threads;
  std::vector<int> bad(rig.size(), 0), wraps(rig.size(), 0), gaps(rig.size(), 0),
      got(rig.size(), 0);
  for (int i = 0; i < rig.size(); ++i) {
    ASSERT_TRUE(cams[i]->Start().ok());
    threads.emplace_back([&, i] {
      AravisCamera& cam = *cams[i];
      std::uint64_t last_seq = 0, last_ts = 0;
      std::uint16_t last_id = 0;
      for (int k = 0; got[i] < kFrames && k < 4 * kFrames; ++k) {
        Frame f;
        if (cam.Grab(&f) != GrabResult::kFrame) continue;
        std::uint64_t stamped = 0;
        if (f.camera != i || f.image.width != 256 || f.image.height != 192 ||
            f.image.format != PixelFormat::kMono16 || !CheckPattern(f, &stamped) ||
            IdOf(stamped) != f.frame_id || IdOf(f.sequence) != f.frame_id) {
          ++bad[i];
        }
        if (got[i] > 0) {
          if (f.sequence <= last_seq || f.device_timestamp_ns <= last_ts) ++bad[i];
          // GigE-style ids skip 0: across the wrap the sequence steps by 2 (65535 -> 65537).
          if (f.sequence != last_seq + (f.frame_id < last_id ? 2 : 1)) ++gaps[i];
          if (f.frame_id < last_id) {
            ++wraps[i];
            EXPECT_EQ(last_id, 65535);
            EXPECT_EQ(f.frame_id, 1);
          }
        }
        last_seq = f.sequence;
        last_ts = f.device_timestamp_ns;
        last_id = f.frame_id;
        ++got[i];
        cam.Release(f);
      }
    });
  }
  for (auto& t : threads) t.join();
  for (int i = 0; i < rig.size(); ++i) {
    cams[i]->Stop();
    EXPECT_EQ(got[i], kFrames) << "camera " << i;
    EXPECT_EQ(bad[i], 0) << "camera " << i;
    EXPECT_EQ(wraps[i], 1) << "camera " << i;
    EXPECT_EQ(gaps[i], 0) << "camera " << i;
    EXPECT_EQ(cams[i]->Counters().complete.load(), static_cast<std::uint64_t>(kFrames));
  }
}

TEST(AravisFake, SoftwareTriggerMono8) {
  AravisFakeRig rig(SmallRig(1), DrawPattern);
  auto cam = rig.MakeCamera(0);
  CameraSettings s;
  s.trigger = TriggerMode::kSoftware;
  s.frame_rate_hz = 100;
  s.timeout_ms = 300;
  ASSERT_TRUE(cam->Open(s).ok());
  EXPECT_EQ(cam->Applied().trigger_source, "Software");
  ASSERT_TRUE(cam->Start().ok());
  Frame f;
  for (int k = 0; k < 3; ++k) {
    ASSERT_TRUE(cam->Trigger().ok());
    ASSERT_EQ(cam->Grab(&f), GrabResult::kFrame);
    std::uint64_t stamped;
    EXPECT_TRUE(CheckPattern(f, &stamped));
    EXPECT_EQ(f.image.format, PixelFormat::kMono8);
    EXPECT_EQ(f.image.width, 320);
    cam->Release(f);
  }
  cam->Stop();
  // Free-run cameras refuse Trigger().
  auto free_cam = rig.MakeCamera(0);
  ASSERT_TRUE(free_cam->Open(CameraSettings{}).ok());
  Status t = free_cam->Trigger();
  EXPECT_FALSE(t.ok());
  EXPECT_NE(t.message().find("kSoftware"), std::string::npos) << t.message();
}

TEST(AravisFake, BadSettingsGiveClearErrors) {
  AravisFakeRig rig(SmallRig(1), DrawPattern);
  auto cam = rig.MakeCamera(0);
  auto expect_error = [&](CameraSettings s, const std::vector<std::string>& words) {
    Status st = cam->Open(s);
    ASSERT_FALSE(st.ok());
    for (const std::string& w : words) {
      EXPECT_NE(st.message().find(w), std::string::npos) << st.message() << " lacks " << w;
    }
  };
  CameraSettings s;
  s.gain_db = 20;  // the fake's gain is 0..10
  expect_error(s, {"MOCAPSIM0", "gain 20", "0..10"});
  s = {};
  s.roi_width = 400;  // sensor is 320 wide
  expect_error(s, {"ROI", "320x256 sensor"});
  s = {};
  s.pixel_format = PixelFormat::kMono12;
  expect_error(s, {"Mono12", "not supported", "Mono16"});
  s = {};
  s.frame_rate_hz = 4000;
  s.exposure_us = 100;
  expect_error(s, {"frame rate 4000", "0.1..1000"});
  s = {};
  s.trigger = TriggerMode::kHardwareLine;
  s.trigger_line = 5;
  expect_error(s, {"Line5", "Line0"});
  s = {};
  s.exposure_us = -1;
  expect_error(s, {"exposure_us"});
  // And good ones still open afterwards, through both orders of exposure and frame rate: 60 ms
  // is longer than the period of the fresh fake (25 Hz: 40 ms), so the rate goes first; 400 us
  // is not. (The fake does not enforce the dependency a real camera has; this runs both paths.)
  s = {};
  s.exposure_us = 60000;
  s.frame_rate_hz = 10;
  ASSERT_TRUE(cam->Open(s).ok());
  EXPECT_DOUBLE_EQ(cam->Applied().exposure_us, 60000);
  EXPECT_NEAR(cam->Applied().frame_rate_hz, 10, 0.01);
  s.exposure_us = 400;
  s.frame_rate_hz = 500;
  ASSERT_TRUE(cam->Open(s).ok());
  EXPECT_DOUBLE_EQ(cam->Applied().exposure_us, 400);
  EXPECT_NEAR(cam->Applied().frame_rate_hz, 500, 1);
}

// Auto exposure/gain off and read back; a feature the camera lacks is an error naming camera and
// feature unless the settings mark it optional (then it is listed as refused).
TEST(AravisFake, AutoOffStrobeAndPtpRefusedUnlessOptional) {
  AravisFakeRig rig(SmallRig(1), DrawPattern);
  auto cam = rig.MakeCamera(0);
  CameraSettings s;
  ASSERT_TRUE(cam->Open(s).ok());
  EXPECT_EQ(cam->Applied().gain_auto, "Off");   // the fake has GainAuto
  EXPECT_EQ(cam->Applied().exposure_auto, "");  // ... and no ExposureAuto: manual anyway
  EXPECT_TRUE(cam->Applied().refused_optional.empty());
  EXPECT_EQ(cam->Applied().packet_size, 0);     // not a GigE device
  // USB3 transfer settings belong to USB3 Vision cameras only: this one takes none.
  s.usb.mode = UsbMode::kAsync;
  s.usb.throughput_limit_mb_s = 300;
  ASSERT_TRUE(cam->Open(s).ok());
  EXPECT_FALSE(cam->Applied().usb.applied);
  EXPECT_TRUE(cam->Applied().refused_optional.empty());
  s.usb = {};
  s.strobe_line = 1;  // the fake has no digital I/O
  Status st = cam->Open(s);
  ASSERT_FALSE(st.ok());
  EXPECT_NE(st.message().find("MOCAPSIM0: LineSource: the camera has no LineSelector"),
            std::string::npos) << st.message();
  EXPECT_NE(st.message().find("optional"), std::string::npos) << st.message();
  s.optional_features = {"LineSource"};
  st = cam->Open(s);
  ASSERT_TRUE(st.ok()) << st.message();
  ASSERT_EQ(cam->Applied().refused_optional.size(), 1u);
  EXPECT_EQ(cam->Applied().refused_optional[0].rfind("LineSource: ", 0), 0u);
  EXPECT_EQ(cam->Applied().strobe_source, "");
  s.ptp = true;
  st = cam->Open(s);
  ASSERT_FALSE(st.ok());
  EXPECT_NE(st.message().find("MOCAPSIM0: PtpEnable: the camera has neither PtpEnable nor "
                              "GevIEEE1588"), std::string::npos) << st.message();
  s.optional_features.push_back("PtpEnable");
  ASSERT_TRUE(cam->Open(s).ok());
  EXPECT_FALSE(cam->Applied().ptp_enabled);
  PtpState ptp;
  st = cam->Ptp(&ptp);
  ASSERT_FALSE(st.ok());
  EXPECT_NE(st.message().find("PTP is not enabled"), std::string::npos);
  // Mono12Packed where the camera does not offer it: named, with what it offers.
  s = {};
  s.pixel_format = PixelFormat::kMono12Packed;
  st = cam->Open(s);
  ASSERT_FALSE(st.ok());
  EXPECT_NE(st.message().find("Mono12Packed"), std::string::npos) << st.message();
}

// A frame's received time is when Aravis received it (the buffer's system timestamp), not when
// it was popped: a frame left waiting in the output queue shows its wait.
TEST(AravisFake, HostTimeIsTheBuffersSystemTimestamp) {
  AravisFakeRig rig(SmallRig(1), DrawPattern);
  auto cam = rig.MakeCamera(0);
  CameraSettings s;
  s.frame_rate_hz = 100;
  ASSERT_TRUE(cam->Open(s).ok());
  ASSERT_TRUE(cam->Start().ok());
  Frame f;
  ASSERT_EQ(cam->Grab(&f), GrabResult::kFrame);
  cam->Release(f);
  // Leave the next frames in the queue for 100 ms.
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  ASSERT_EQ(cam->Grab(&f), GrabResult::kFrame);
  const std::uint64_t popped = MonotonicNs();
  const double waited_ms = (popped - f.received_ns) * 1e-6;
  EXPECT_GE(f.host_timestamp_ns, f.received_ns);
  EXPECT_LE(f.host_timestamp_ns, popped);
  cam->Release(f);
  cam->Stop();
  std::printf("a frame left in the queue: host time %.1f ms before the pop\n", waited_ms);
  EXPECT_GT(waited_ms, 50.0);   // it arrived ~90 ms before it was popped
  EXPECT_LT(waited_ms, 1000.0);
}

TEST(Ptp, LockedMeansAllSlavesAndAtMostOneMaster) {
  std::string why;
  EXPECT_TRUE(PtpLocked({"a", "b", "c"}, {{"Master"}, {"Slave"}, {"Slave"}}, &why)) << why;
  EXPECT_TRUE(PtpLocked({"a", "b"}, {{"Slave"}, {"Slave"}}, &why)) << why;  // external master
  EXPECT_FALSE(PtpLocked({"a", "b", "c"}, {{"Master"}, {"Listening"}, {"Slave"}}, &why));
  EXPECT_EQ(why, "not locked: b (Listening)");
  EXPECT_FALSE(PtpLocked({"a", "b"}, {{"Master"}, {"Master"}}, &why));
  EXPECT_EQ(why, "2 cameras are PTP masters (a, b): the rig has more than one clock");
  EXPECT_FALSE(PtpLocked({"a"}, {{""}}, &why));
  EXPECT_EQ(why, "not locked: a (no status)");
}

TEST(Mono12Packed, UnpacksTwoPixelsFromThreeBytes) {
  // Pixels 0xABC, 0x123, 0xFFF (odd width: the last pair half used), two rows.
  const std::uint8_t packed[] = {0xAB, 0x3C, 0x12, 0xFF, 0x0F, 0x00,   // row 0 (5 bytes + pad)
                                 0x00, 0xF0, 0xFF, 0x80, 0x01, 0x00};  // row 1: 0x000, 0xFFF, 0x801
  std::uint16_t out[2][3] = {};
  UnpackMono12Packed(packed, 6, 3, 2, &out[0][0], sizeof out[0]);
  EXPECT_EQ(out[0][0], 0xABC);
  EXPECT_EQ(out[0][1], 0x123);
  EXPECT_EQ(out[0][2], 0xFFF);
  EXPECT_EQ(out[1][0], 0x000);
  EXPECT_EQ(out[1][1], 0xFFF);
  EXPECT_EQ(out[1][2], 0x801);
  EXPECT_EQ(WireRowBytes(PixelFormat::kMono12Packed, 3), 5u);
  EXPECT_EQ(WireRowBytes(PixelFormat::kMono12Packed, 1280), 1920u);
  EXPECT_EQ(BitDepth(PixelFormat::kMono12Packed), 12);
}

// Frames of the wrong pixel format or size (the device changed behind the backend's back) are
// counted and never delivered; good frames flow again once the device is back to the settings.
TEST(AravisFake, WrongFormatAndSizeCountedNotDelivered) {
  AravisFakeRig rig(SmallRig(1), DrawPattern);
  auto cam = rig.MakeCamera(0);
  CameraSettings s;
  s.pixel_format = PixelFormat::kMono16;
  s.frame_rate_hz = 500;
  s.timeout_ms = 200;
  ASSERT_TRUE(cam->Open(s).ok());
  ASSERT_TRUE(cam->Start().ok());
  auto grab_n = [&](int n, int* frames) {
    for (int k = 0; k < n; ++k) {
      Frame f;
      if (cam->Grab(&f) == GrabResult::kFrame) {
        ++*frames;
        std::uint64_t stamped;
        EXPECT_TRUE(CheckPattern(f, &stamped));
        EXPECT_EQ(f.image.format, PixelFormat::kMono16);
        EXPECT_EQ(f.image.width, 320);
        cam->Release(f);
      }
    }
  };
  int frames = 0;
  grab_n(10, &frames);
  EXPECT_EQ(frames, 10);
  ArvFakeCamera* fake = rig.FakeCamera(0);
  ASSERT_NE(fake, nullptr);

  arv_fake_camera_write_register(fake, ARV_FAKE_CAMERA_REGISTER_PIXEL_FORMAT,
                                 ARV_PIXEL_FORMAT_MONO_8);
  std::this_thread::sleep_for(std::chrono::milliseconds(30));
  const CameraCounters& c = cam->Counters();
  auto wrong_before = static_cast<int>(c.wrong_format.load());
  frames = 0;
  grab_n(30, &frames);
  // At most the buffers already filled before the change (the pool) come out as frames; every
  // other grab is a counted wrong-format buffer.
  EXPECT_LE(frames, s.buffer_count);
  EXPECT_EQ(static_cast<int>(c.wrong_format.load()) - wrong_before, 30 - frames);

  arv_fake_camera_write_register(fake, ARV_FAKE_CAMERA_REGISTER_PIXEL_FORMAT,
                                 ARV_PIXEL_FORMAT_MONO_16);
  arv_fake_camera_write_register(fake, ARV_FAKE_CAMERA_REGISTER_WIDTH, 288);
  std::this_thread::sleep_for(std::chrono::milliseconds(30));
  const auto size_before = static_cast<int>(c.size_mismatches.load());
  wrong_before = static_cast<int>(c.wrong_format.load());
  frames = 0;
  grab_n(30, &frames);
  EXPECT_LE(frames, s.buffer_count);
  // Buffers filled while the format was still wrong count as such; the rest as size mismatches.
  EXPECT_EQ(static_cast<int>(c.size_mismatches.load()) - size_before +
                static_cast<int>(c.wrong_format.load()) - wrong_before,
            30 - frames);
  EXPECT_GE(static_cast<int>(c.size_mismatches.load()) - size_before, 30 - s.buffer_count);

  arv_fake_camera_write_register(fake, ARV_FAKE_CAMERA_REGISTER_WIDTH, 320);
  std::this_thread::sleep_for(std::chrono::milliseconds(30));
  frames = 0;
  grab_n(40, &frames);
  EXPECT_GE(frames, 40 - s.buffer_count);
  cam->Stop();
}

// A caller holding every buffer starves the stream: Aravis counts the images it could not
// store, and the backend reports them as underruns.
TEST(AravisFake, UnderrunsWhenTheCallerHoldsEveryBuffer) {
  AravisFakeRig rig(SmallRig(1), DrawPattern);
  auto cam = rig.MakeCamera(0);
  CameraSettings s;
  s.frame_rate_hz = 500;
  s.buffer_count = 2;
  s.timeout_ms = 200;
  ASSERT_TRUE(cam->Open(s).ok());
  ASSERT_TRUE(cam->Start().ok());
  Frame a, b, c;
  ASSERT_EQ(cam->Grab(&a), GrabResult::kFrame);
  ASSERT_EQ(cam->Grab(&b), GrabResult::kFrame);
  std::this_thread::sleep_for(std::chrono::milliseconds(60));  // ~30 frame periods, no buffer
  cam->Release(a);
  cam->Release(b);
  ASSERT_EQ(cam->Grab(&c), GrabResult::kFrame);
  cam->Release(c);
  EXPECT_GE(cam->Counters().underruns.load(), 10u);
  cam->Stop();
}

// The other ways in: an ArvCamera made by the caller, a serial number, a hardware trigger line.
TEST(AravisFake, AdoptedCameraSerialLookupAndHardwareTrigger) {
  GError* e = nullptr;
  ArvDevice* device = arv_fake_device_new("ADOPTED1", &e);
  ASSERT_NE(device, nullptr);
  ArvCamera* arv_cam = arv_camera_new_with_device(device, &e);
  ASSERT_NE(arv_cam, nullptr);
  g_object_unref(device);
  {
    AravisCamera cam("ADOPTED1", arv_cam);
    CameraSettings s;
    s.roi_width = 128;
    s.roi_height = 64;
    s.frame_rate_hz = 200;
    ASSERT_TRUE(cam.Open(s).ok());
    ASSERT_TRUE(cam.Start().ok());
    Frame f;
    ASSERT_EQ(cam.Grab(&f), GrabResult::kFrame);  // the fake's own test pattern
    EXPECT_EQ(f.image.width, 128);
    EXPECT_EQ(f.image.height, 64);
    cam.Release(f);
    cam.Stop();
    Status st = cam.Reopen();  // no factory: says so
    ASSERT_FALSE(st.ok());
    EXPECT_NE(st.message().find("factory"), std::string::npos) << st.message();
  }
  g_object_unref(arv_cam);

  // Aravis's Fake interface lists one fake camera: id "Fake_1", serial "1".
  arv_enable_interface("Fake");
  std::unique_ptr<AravisCamera> by_serial;
  ASSERT_TRUE(AravisCamera::FromSerial("1", {}, &by_serial).ok());
  EXPECT_EQ(by_serial->id(), "Fake_1");
  CameraSettings s;
  s.trigger = TriggerMode::kHardwareLine;
  s.trigger_line = 0;
  s.roi_width = 64;
  s.roi_height = 64;
  Status st = by_serial->Open(s);
  ASSERT_TRUE(st.ok()) << st.message();
  EXPECT_EQ(by_serial->Applied().trigger_source, "Line0");
  std::unique_ptr<AravisCamera> none;
  st = AravisCamera::FromSerial("NOSUCHCAM", {}, &none);
  ASSERT_FALSE(st.ok());
  EXPECT_NE(st.message().find("NOSUCHCAM"), std::string::npos);
  // The message lists what was found (a GigE fake of a test running in parallel may be there).
  const std::string& m = st.message();
  const auto open = m.find("(found: ");
  ASSERT_NE(open, std::string::npos) << m;
  const std::string list = ", " + m.substr(open + 8, m.find(')', open) - open - 8) + ",";
  EXPECT_NE(list.find(", 1,"), std::string::npos) << m;
  arv_disable_interface("Fake");
}

TEST(AravisFake, MissingDeviceNamesIt) {
  AravisCamera cam("NoSuchVendor-NoSuchModel-000");
  Status st = cam.Open(CameraSettings{});
  ASSERT_FALSE(st.ok());
  EXPECT_NE(st.message().find("cannot open camera 'NoSuchVendor-NoSuchModel-000'"),
            std::string::npos)
      << st.message();
  Frame f;
  EXPECT_EQ(cam.Grab(&f), GrabResult::kStopped);
  EXPECT_FALSE(cam.Start().ok());
}

// What `mocap capture` runs in simulation: the full rig (8 cameras, 1280x1024, 200 Hz) of Aravis
// fake cameras drawing the simulated subject with the renderer. Every checked frame shows the
// truth's blobs; the delivered rate and the CPU it costs are printed (not asserted: the machine
// is shared).
TEST(AravisFake, FullRigRendersTheSimulatedSubject) {
  sim::SimulationOptions so;
  so.noise_mm = 0;
  so.missing = 0;
  so.duration_scale = 0.2;
  sim::SimulatedSession session;
  ASSERT_TRUE(sim::SimulateSession(so, &session).ok());
  const auto rig = sim::MakeCameraRig({});
  sim::RendererOptions render_options;
  render_options.sequence_origin = kAravisFakeFirstFrameId;
  sim::Renderer renderer(rig, sim::MakeSessionScene(session), render_options);
  ASSERT_TRUE(renderer.status().ok());
  FakeRigOptions fo;
  fo.cameras = static_cast<int>(rig.size());
  AravisFakeRig fakes(fo, renderer.Generator());
  std::vector<std::unique_ptr<AravisCamera>> cams;
  CameraSettings s;
  s.frame_rate_hz = 200;
  s.buffer_count = 8;
  s.timeout_ms = 200;
  for (int i = 0; i < fakes.size(); ++i) {
    cams.push_back(fakes.MakeCamera(i));
    ASSERT_TRUE(cams[i]->Open(s).ok());
  }
  const double cpu0 = testutil::ProcessCpuSeconds();
  const auto t0 = std::chrono::steady_clock::now();
  for (auto& c : cams) ASSERT_TRUE(c->Start().ok());
  std::atomic<bool> stop{false};
  std::vector<int> frames(cams.size(), 0), checked(cams.size(), 0), misses(cams.size(), 0);
  std::vector<std::thread> threads;
  for (int i = 0; i < fakes.size(); ++i) {
    threads.emplace_back([&, i] {
      sim::FrameTruth truth;
      while (!stop.load()) {
        Frame f;
        if (cams[i]->Grab(&f) != GrabResult::kFrame) continue;
        if (frames[i] == 0) {
          renderer.Truth(i, f.sequence, &truth);
          if (truth.time_s > 0.1) ++misses[i];  // the first frames show the scene's start
        }
        if (frames[i]++ % 20 == 0) {
          renderer.Truth(i, f.sequence, &truth);
          for (const sim::BlobTruth& b : truth.blobs) {
            const int x = int(std::lround(b.drawn.x())), y = int(std::lround(b.drawn.y()));
            ++checked[i];
            if (f.image.row8(y)[x] < 100) ++misses[i];
          }
        }
        cams[i]->Release(f);
      }
    });
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(1000));
  stop = true;
  for (auto& t : threads) t.join();
  const double wall = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const double cpu = testutil::ProcessCpuSeconds() - cpu0;
  int total = 0;
  for (int i = 0; i < fakes.size(); ++i) {
    cams[i]->Stop();
    total += frames[i];
    EXPECT_GE(frames[i], 20) << "camera " << i;
    EXPECT_GE(checked[i], 20) << "camera " << i;
    EXPECT_EQ(misses[i], 0) << "camera " << i;
  }
  std::printf("8 fake cameras 1280x1024 @ 200 Hz with the renderer: %.0f frames/s per camera "
              "delivered, %.2f CPU cores (fake streams + renderer + grab loops)\n",
              total / wall / fakes.size(), cpu / wall);
}

}  // namespace
}  // namespace mocap::drivers
