// The exposure schedule of a PTP rig (drivers/aravis_camera.h "Exposure schedule"), on Aravis's
// fake cameras given the PTP features (drivers/aravis_fake.h FakeRigOptions::ptp_features):
//  - Synchronous Free Run is applied and read back; a camera without it is an error naming the
//    camera and the feature unless SyncFreeRunTimerEnable is optional;
//  - cameras whose own clocks are 1.3, -0.7 and 2.9 ms off the master, scheduled, expose on one
//    tick: every set the pipeline groups (kSharedClock) holds images of one instant;
//  - a camera not scheduled (its fake lacks the features, marked optional) free-runs at its own
//    clock's phase: its images join sets 2.1 ms away from the others', and the rig check names it.
#include <algorithm>
#include <cstdio>
#include <cstring>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "daemon/capture_pipeline.h"
#include "daemon/rig_check.h"
#include "drivers/aravis_camera.h"
#include "drivers/aravis_fake.h"
#include "tests/daemon_gtest_util.h"

namespace mocap {
namespace {

using ::testing::HasSubstr;

constexpr double kRate = 100.0;  // a 10 ms period

drivers::ImageGenerator Blank() {
  return [](int, std::uint64_t, std::uint8_t* data, int w, int h, std::ptrdiff_t stride,
            drivers::PixelFormat) {
    for (int y = 0; y < h; ++y) std::memset(data + y * stride, 0, static_cast<std::size_t>(w));
  };
}

drivers::FakeRigOptions PtpRig() {
  drivers::FakeRigOptions fo;
  fo.cameras = 4;
  fo.width = 64;
  fo.height = 48;
  fo.clock_sequence_rate_hz = kRate;
  fo.ptp_features = true;
  fo.clock_offsets_ns = {1'300'000, -700'000, 2'900'000, 2'900'000};
  fo.without_sync_free_run = {3};
  return fo;
}

drivers::CameraSettings PtpSettings() {
  drivers::CameraSettings s;
  s.frame_rate_hz = kRate;
  s.exposure_us = 500;
  s.buffer_count = 8;
  s.ptp = true;
  return s;
}

TEST(PtpSchedule, SynchronousFreeRunIsAppliedReadBackAndItsAbsenceNamed) {
  drivers::AravisFakeRig fakes(PtpRig(), Blank());
  auto scheduled = fakes.MakeCamera(0);
  drivers::CameraSettings s = PtpSettings();
  ASSERT_OK(scheduled->Open(s));
  const drivers::AppliedSettings& a = scheduled->Applied();
  EXPECT_TRUE(a.ptp_enabled);
  EXPECT_EQ(a.ptp_schedule, "sync-free-run");
  EXPECT_EQ(a.schedule_rate_hz, kRate);
  EXPECT_EQ(a.schedule_start_ticks, 5'000'000);  // half a period, in ns (a 1 GHz clock)
  drivers::PtpState st;
  ASSERT_OK(scheduled->Ptp(&st));
  EXPECT_EQ(st.status, "Slave");
  ASSERT_OK(fakes.SetPtpState(0, "Uncalibrated", -1234));
  ASSERT_OK(scheduled->Ptp(&st));
  EXPECT_EQ(st.status, "Uncalibrated");
  EXPECT_EQ(st.offset_from_master_ns, -1234);
  EXPECT_THAT(fakes.SetPtpState(0, "Locked").message(), HasSubstr("'Locked' is none of Initializing"));
  s.ptp_schedule = drivers::PtpSchedule::kNone;
  ASSERT_OK(scheduled->Open(s));
  EXPECT_EQ(scheduled->Applied().ptp_schedule, "");

  auto unscheduled = fakes.MakeCamera(3);
  s = PtpSettings();
  Status opened = unscheduled->Open(s);
  ASSERT_FALSE(opened.ok());
  EXPECT_THAT(opened.message(), HasSubstr("MOCAPSIM3: SyncFreeRunTimerEnable: the camera has no "
                                          "SyncFreeRunTimerTriggerRateAbs (no Synchronous Free Run)"));
  s.optional_features = {"SyncFreeRunTimerEnable"};
  ASSERT_OK(unscheduled->Open(s));
  EXPECT_TRUE(unscheduled->Applied().ptp_enabled);
  EXPECT_EQ(unscheduled->Applied().ptp_schedule, "");
  ASSERT_EQ(unscheduled->Applied().refused_optional.size(), 1u);
  EXPECT_THAT(unscheduled->Applied().refused_optional[0], HasSubstr("SyncFreeRunTimerEnable: "));
}

TEST(PtpSchedule, ScheduledCamerasExposeOnOneTickWhateverTheirClocksAndAnUnscheduledOneIsNamed) {
  drivers::AravisFakeRig fakes(PtpRig(), Blank());
  std::vector<std::unique_ptr<drivers::CameraSource>> cameras;
  drivers::CameraSettings s = PtpSettings();
  s.optional_features = {"SyncFreeRunTimerEnable"};  // camera 3's fake lacks it
  for (int c = 0; c < 4; ++c) {
    auto cam = fakes.MakeCamera(c);
    ASSERT_OK(cam->Open(s));
    EXPECT_EQ(cam->Applied().ptp_schedule, c < 3 ? "sync-free-run" : "") << c;
    cameras.push_back(std::move(cam));
  }
  // Per complete set: its scheduled cameras' timestamps' spread, and camera 3's distance from
  // them (signed, ns).
  std::mutex mutex;
  std::vector<std::int64_t> spreads, unscheduled_offsets;
  daemon::TriangulateFn record = [&](const reconstruction::DetectionSet& set, daemon::PointFrame*) {
    if (set.present_count() != 4) return Status::Ok();
    std::uint64_t lo = UINT64_MAX, hi = 0;
    for (int c = 0; c < 3; ++c) {
      lo = std::min(lo, set.cameras[c].device_timestamp_ns);
      hi = std::max(hi, set.cameras[c].device_timestamp_ns);
    }
    std::lock_guard<std::mutex> lock(mutex);
    spreads.push_back(static_cast<std::int64_t>(hi - lo));
    unscheduled_offsets.push_back(static_cast<std::int64_t>(set.cameras[3].device_timestamp_ns - lo));
    return Status::Ok();
  };
  daemon::CapturePipelineOptions o;
  o.rig_sync = daemon::CapturePipelineOptions::RigSync::kSharedClock;
  o.rate_hz = kRate;
  o.detection_threads = 1;
  o.start_on_complete_set = false;
  daemon::CapturePipeline pipeline(std::move(cameras), record, o);
  ASSERT_OK(pipeline.Start());
  const auto end = std::chrono::steady_clock::now() + std::chrono::milliseconds(1500);
  while (std::chrono::steady_clock::now() < end) {
    daemon::PointFrame pf;
    pipeline.PopPoints(&pf, 20);
  }
  const daemon::CapturePipelineStats st = pipeline.Stats(/*timings=*/false);
  daemon::RigCheckInput in;
  in.sync = "ptp";
  in.rate_hz = kRate;
  in.ptp_checked = in.ptp_locked = true;
  for (int c = 0; c < 4; ++c) {
    daemon::CameraCheckInput ci;
    ci.id = pipeline.camera(c).id();
    ci.streaming = pipeline.camera(c).State() == drivers::CameraState::kStreaming;
    ci.complete = pipeline.camera(c).Counters().complete.load();
    ci.ptp.status = "Slave";
    ci.tick_phase = st.camera_tick_phase[c];
    in.cameras.push_back(ci);
  }
  pipeline.Stop();

  std::lock_guard<std::mutex> lock(mutex);
  // 1.5 s at 100 Hz: 150 ticks; a loaded host drops some, never most.
  ASSERT_GE(spreads.size(), 60u);
  // Scheduled: one instant per set, to the nanosecond, mid-tick, whatever each camera's own clock.
  EXPECT_EQ(*std::max_element(spreads.begin(), spreads.end()), 0);
  for (int c = 0; c < 3; ++c) EXPECT_NEAR(st.camera_tick_phase[c], 0.5, 1e-6) << c;
  // Not scheduled: camera 3 exposes at its own clock's phase, 2.9 ms into the tick, 2.1 ms
  // before the others, in every set it shares with them.
  EXPECT_NEAR(st.camera_tick_phase[3], 0.29, 1e-6);
  for (std::int64_t d : unscheduled_offsets) ASSERT_EQ(d, -2'100'000);
  // The rig check names it, and only it.
  daemon::RigCheckOptions judge;
  judge.min_seconds_of_frames = 0.5;  // the run is short
  const nlohmann::json report = daemon::RigCheckReport(in, judge);
  std::printf("rig check: %s\n", report["problems"].dump().c_str());
  ASSERT_EQ(report["problems"].size(), 1u) << report.dump(1);
  EXPECT_THAT(report["problems"][0].get<std::string>(),
              HasSubstr("camera 'MOCAPSIM3': exposes -2100 us off the rig's other cameras within the tick"));
  EXPECT_NEAR(report["cameras"][3]["sync"]["phase_from_rig_us"].get<double>(), -2100, 0.01);
  EXPECT_NEAR(report["cameras"][0]["sync"]["phase_from_rig_us"].get<double>(), 0, 0.01);
}

}  // namespace
}  // namespace mocap
