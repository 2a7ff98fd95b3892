// Frame-set sync across cameras (reconstruction/frame_sync.h): wrapping ids, missing cameras,
// late and duplicate frames, the window bound, timeouts, and timestamps with per-camera clock
// offsets, drift and jitter.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <random>
#include <vector>

#include "drivers/frame.h"
#include "reconstruction/frame_sync.h"

namespace mocap::reconstruction {
namespace {

constexpr std::uint64_t kMs = 1'000'000;

CameraDetections Det(int camera, std::uint64_t sequence, std::uint64_t host_ns,
                     std::uint64_t device_ns = 0) {
  CameraDetections d;
  d.camera = camera;
  d.sequence = sequence;
  d.host_timestamp_ns = host_ns;
  d.device_timestamp_ns = device_ns;
  Centroid c;
  c.pixel = Eigen::Vector2d(camera, static_cast<double>(sequence));  // identifies the frame
  d.centroids.push_back(c);
  return d;
}

FrameSyncOptions SeqOptions(int cameras) {
  FrameSyncOptions o;
  o.num_cameras = cameras;
  o.mode = FrameSyncOptions::Mode::kSequence;
  o.timeout_ns = 0;
  return o;
}

TEST(FrameSync, WrappingIdsFromSourcesThatUnwrappedDifferently) {
  // Three cameras, 16-bit ids through the wrap. Camera 2 starts two frames late, after the wrap,
  // so its own unwrapper calls id 0 sequence 0 while the others call it 65,536.
  FrameSync sync;
  ASSERT_TRUE(sync.Reset(SeqOptions(3)).ok());
  drivers::FrameIdUnwrapper unwrap[3];
  std::vector<DetectionSet> out;
  std::uint16_t id = 65530;
  for (int f = 0; f < 20; ++f, ++id) {
    for (int c = 0; c < 3; ++c) {
      if (c == 2 && f < 6) continue;  // camera 2 not started yet (first id 0)
      ASSERT_TRUE(sync.Add(Det(c, unwrap[c].Next(id), f * 5 * kMs), &out).ok());
    }
  }
  sync.Flush(&out);
  ASSERT_EQ(out.size(), 20u);
  for (std::size_t i = 0; i < out.size(); ++i) {
    EXPECT_EQ(out[i].sequence, 65530u + i);  // rig-unwrapped, increasing across the wrap
    EXPECT_EQ(out[i].present_count(), i < 6 ? 2 : 3);
    for (int c = 0; c < 3; ++c) {
      if (!out[i].present[c]) continue;
      // Every member has the same 16-bit id.
      EXPECT_EQ(out[i].cameras[c].sequence & 0xFFFF, (65530u + i) & 0xFFFF);
    }
  }
  EXPECT_EQ(sync.counters().complete, 14u);
  EXPECT_EQ(sync.counters().incomplete, 6u);
  EXPECT_EQ(sync.counters().missing[2], 6u);
  EXPECT_EQ(sync.counters().late, 0u);
}

TEST(FrameSync, MissingCameraGivesAnIncompleteSetReleasedByTheNextCompleteOne) {
  FrameSync sync;
  ASSERT_TRUE(sync.Reset(SeqOptions(3)).ok());
  std::vector<DetectionSet> out;
  for (std::uint64_t s = 100; s < 103; ++s)
    for (int c = 0; c < 3; ++c) {
      if (s == 101 && c == 1) continue;  // camera 1 lost frame 101
      ASSERT_TRUE(sync.Add(Det(c, s, s * kMs), &out).ok());
      if (s == 101) EXPECT_EQ(out.size(), 1u);  // 101 waits for camera 1
    }
  ASSERT_EQ(out.size(), 3u);
  EXPECT_EQ(out[1].sequence, 101u);
  EXPECT_FALSE(out[1].present[1]);
  EXPECT_TRUE(out[1].present[0] && out[1].present[2]);
  EXPECT_TRUE(out[1].cameras[1].centroids.empty());
  EXPECT_EQ(out[1].cameras[1].camera, 1);
  EXPECT_EQ(out[1].cameras[2].centroids[0].pixel.y(), 101);
  EXPECT_EQ(out[2].sequence, 102u);
  EXPECT_EQ(out[2].present_count(), 3);
  EXPECT_EQ(sync.counters().complete, 2u);
  EXPECT_EQ(sync.counters().incomplete, 1u);
  EXPECT_EQ(sync.counters().missing[1], 1u);
  EXPECT_EQ(sync.pending(), 0);
}

TEST(FrameSync, LateAndDuplicateFramesAreCountedAndDropped) {
  FrameSync sync;
  ASSERT_TRUE(sync.Reset(SeqOptions(2)).ok());
  std::vector<DetectionSet> out;
  ASSERT_TRUE(sync.Add(Det(0, 10, 0), &out).ok());
  ASSERT_TRUE(sync.Add(Det(0, 10, 1), &out).ok());  // duplicate, set 10 still pending
  EXPECT_EQ(sync.counters().duplicate, 1u);
  ASSERT_TRUE(sync.Add(Det(0, 11, 2), &out).ok());
  ASSERT_TRUE(sync.Add(Det(1, 11, 3), &out).ok());  // 11 complete: 10 goes out incomplete
  ASSERT_EQ(out.size(), 2u);
  ASSERT_TRUE(sync.Add(Det(1, 10, 4), &out).ok());  // camera 1's frame 10 arrives too late
  ASSERT_TRUE(sync.Add(Det(1, 11, 5), &out).ok());  // and a repeat of an emitted set: late too
  EXPECT_EQ(sync.counters().late, 2u);
  EXPECT_EQ(out.size(), 2u);
  EXPECT_EQ(out[0].cameras[0].centroids.size(), 1u);  // the first copy was kept
  EXPECT_EQ(sync.counters().frames, 6u);
  EXPECT_EQ(sync.counters().complete, 1u);
  EXPECT_EQ(sync.counters().incomplete, 1u);
}

TEST(FrameSync, WindowBoundsMemoryWhenACameraDies) {
  FrameSyncOptions o = SeqOptions(3);
  o.max_pending_sets = 4;
  FrameSync sync;
  ASSERT_TRUE(sync.Reset(o).ok());
  std::vector<DetectionSet> out;
  for (std::uint64_t s = 0; s < 50; ++s)
    for (int c = 0; c < 2; ++c) {  // camera 2 is gone
      ASSERT_TRUE(sync.Add(Det(c, s, s * kMs), &out).ok());
      EXPECT_LE(sync.pending(), 4);
    }
  EXPECT_EQ(out.size(), 46u);
  sync.Flush(&out);
  ASSERT_EQ(out.size(), 50u);
  for (std::size_t i = 0; i < out.size(); ++i) {
    EXPECT_EQ(out[i].sequence, i);
    EXPECT_EQ(out[i].present_count(), 2);
  }
  EXPECT_EQ(sync.counters().incomplete, 50u);
  EXPECT_EQ(sync.counters().missing[2], 50u);
}

TEST(FrameSync, TimeoutReleasesAStalledSet) {
  FrameSyncOptions o = SeqOptions(2);
  o.timeout_ns = 20 * kMs;
  FrameSync sync;
  ASSERT_TRUE(sync.Reset(o).ok());
  std::vector<DetectionSet> out;
  ASSERT_TRUE(sync.Add(Det(0, 5, 100 * kMs), &out).ok());
  sync.Poll(119 * kMs, &out);
  EXPECT_TRUE(out.empty());
  sync.Poll(120 * kMs, &out);
  ASSERT_EQ(out.size(), 1u);
  EXPECT_EQ(out[0].present_count(), 1);
  EXPECT_EQ(out[0].first_arrival_ns, 100 * kMs);
  // The camera that stalled delivers later: late.
  ASSERT_TRUE(sync.Add(Det(1, 5, 125 * kMs), &out).ok());
  EXPECT_EQ(sync.counters().late, 1u);
  // A frame's own arrival time also expires older sets.
  ASSERT_TRUE(sync.Add(Det(0, 6, 130 * kMs), &out).ok());
  ASSERT_TRUE(sync.Add(Det(1, 7, 151 * kMs), &out).ok());
  ASSERT_EQ(out.size(), 2u);
  EXPECT_EQ(out[1].sequence, 6u);
}

TEST(FrameSync, TimestampModeWithOffsetsDriftJitterAndDrops) {
  // Four cameras at 200 Hz. Each device clock has its own epoch (seconds apart); camera 3 runs
  // 150 ppm fast (3 ms over the run: beyond the 2 ms tolerance unless the offset tracks it);
  // exposure timestamps jitter by 20 us; images reach the host 1-1.8 ms later, in an order
  // shuffled by that latency. Some frames are lost. Every emitted set must hold frames of one
  // trigger only; a lost frame gives exactly one incomplete set.
  const int n = 4;
  const std::int64_t epoch[n] = {0, 3'200'000'000LL, 1'700'000'000LL, 123'456'789LL};
  const double rate[n] = {1.0, 1.0, 1.0, 1.0 + 150e-6};
  const std::uint64_t period = 5 * kMs;
  std::mt19937 rng(4);
  std::normal_distribution<double> jitter(0, 20'000);
  std::uniform_real_distribution<double> latency(1.0 * kMs, 1.8 * kMs);
  struct Arrival {
    std::uint64_t host;
    CameraDetections d;
  };
  std::vector<Arrival> arrivals;
  const int frames = 4000;  // 20 s
  std::vector<std::pair<int, int>> lost = {{2, 50}, {0, 1200}, {3, 3000}};
  for (int f = 0; f < frames; ++f) {
    const std::uint64_t t = 10'000 * kMs + f * period;  // common (true) time
    for (int c = 0; c < n; ++c) {
      if (std::find(lost.begin(), lost.end(), std::make_pair(c, f)) != lost.end()) continue;
      const auto device = static_cast<std::uint64_t>(epoch[c] + rate[c] * t + jitter(rng));
      const auto host = static_cast<std::uint64_t>(t + latency(rng));
      // The sequence carries the true frame index so the test can check the grouping.
      arrivals.push_back({host, Det(c, f, host, device)});
    }
  }
  std::stable_sort(arrivals.begin(), arrivals.end(),
                   [](const Arrival& a, const Arrival& b) { return a.host < b.host; });
  FrameSyncOptions o;
  o.num_cameras = n;
  o.mode = FrameSyncOptions::Mode::kTimestamp;
  o.tolerance_ns = 2 * kMs;
  o.timeout_ns = 50 * kMs;
  FrameSync sync;
  ASSERT_TRUE(sync.Reset(o).ok());
  std::vector<DetectionSet> out;
  for (Arrival& a : arrivals) ASSERT_TRUE(sync.Add(std::move(a.d), &out).ok());
  sync.Flush(&out);
  ASSERT_EQ(out.size(), static_cast<std::size_t>(frames));
  int incomplete = 0;
  for (int f = 0; f < frames; ++f) {
    const DetectionSet& s = out[f];
    for (int c = 0; c < n; ++c)
      if (s.present[c]) ASSERT_EQ(s.cameras[c].sequence, static_cast<std::uint64_t>(f)) << "set " << f;
    if (s.present_count() < n) {
      ++incomplete;
      bool expected = false;
      for (int c = 0; c < n; ++c)
        expected |= std::find(lost.begin(), lost.end(), std::make_pair(c, f)) != lost.end();
      EXPECT_TRUE(expected)
          << "set " << f;
    }
  }
  EXPECT_EQ(incomplete, 3);
  EXPECT_EQ(sync.counters().complete, static_cast<std::uint64_t>(frames - 3));
  EXPECT_EQ(sync.counters().late + sync.counters().duplicate, 0u);
  // The offsets found the epochs (relative to camera 0) to within the latency spread and tracked
  // camera 3's drift.
  for (int c = 1; c < 3; ++c)
    EXPECT_NEAR(sync.offset_ns(c) - sync.offset_ns(0), epoch[c], 0.5 * kMs) << c;
}

TEST(FrameSync, ACameraThatRestartsIsResynchronisedInTimestampMode) {
  // Two cameras at 100 Hz; after frame 100 camera 1 is re-plugged: its clock restarts at zero.
  FrameSyncOptions o;
  o.num_cameras = 2;
  o.mode = FrameSyncOptions::Mode::kTimestamp;
  o.tolerance_ns = 2 * kMs;
  o.timeout_ns = 0;
  FrameSync sync;
  ASSERT_TRUE(sync.Reset(o).ok());
  std::vector<DetectionSet> out;
  const std::uint64_t period = 10 * kMs;
  auto run = [&](int from, int to, std::int64_t epoch1) {
    for (int f = from; f < to; ++f) {
      const std::uint64_t t = 1000 * kMs + f * period;
      ASSERT_TRUE(sync.Add(Det(0, f, t + kMs, t + 5'000 * kMs), &out).ok());
      ASSERT_TRUE(sync.Add(Det(1, f, t + kMs, t + epoch1), &out).ok());
    }
  };
  run(0, 100, 77 * kMs);
  ASSERT_EQ(sync.counters().complete, 100u);
  ASSERT_TRUE(sync.ResyncCamera(1).ok());
  // The restarted clock reads about -1 s against the old offset: without the resync its frames
  // would all be late.
  run(100, 200, -static_cast<std::int64_t>(1000 * kMs) - 100 * static_cast<std::int64_t>(period));
  sync.Flush(&out);
  EXPECT_EQ(sync.counters().late, 0u);
  EXPECT_EQ(sync.counters().complete, 200u);
  for (const DetectionSet& s : out) ASSERT_EQ(s.cameras[0].sequence, s.cameras[1].sequence);
  // Sequence mode refuses, naming why.
  ASSERT_TRUE(sync.Reset(SeqOptions(2)).ok());
  const Status s = sync.ResyncCamera(1);
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.message().find("sequence mode"), std::string::npos);
}

// A camera clock 3.2 s off the host's and 80 ppm fast; frames reach the host 100 us after the
// exposure plus an exponential wait (mean 300 us), and for one second of the run every frame waits
// 4 ms more (a loaded host). The fit must map device time onto the host clock to within the
// best latency's scatter, whatever the load, and find the drift.
TEST(ClockFit, FindsOffsetAndDriftFromArrivalsThatOnlyEverWait) {
  std::mt19937 rng(7);
  std::exponential_distribution<double> wait(1.0 / 300'000.0);
  const double drift = 80e-6;
  const std::int64_t epoch = 3'200'000'000LL;
  ClockFit fit;
  const std::uint64_t period = 5 * kMs;  // 200 Hz
  double worst_us = 0;
  for (int f = 0; f < 6000; ++f) {  // 30 s
    const std::uint64_t t = 50'000 * kMs + f * period;  // true exposure, host clock
    const auto device = static_cast<std::uint64_t>(epoch + (1 + drift) * static_cast<double>(t));
    double latency = 100'000 + wait(rng);
    if (f >= 3000 && f < 3200) latency += 4 * kMs;
    fit.Add(device, t + static_cast<std::uint64_t>(latency));
    if (f >= 200) {
      const double err_us = (fit.ToHost(device) - static_cast<std::int64_t>(t) - 100'000) * 1e-3;
      worst_us = std::max(worst_us, std::abs(err_us));
    }
  }
  std::printf("clock fit: drift %.2f ppm (truth 80), worst error %.1f us after 1 s\n",
              fit.drift_ppm(), worst_us);
  EXPECT_TRUE(fit.drift_fitted());
  EXPECT_NEAR(fit.drift_ppm(), 80.0, 3.0);
  // The best of 64 exponential waits of mean 300 us is ~5 us late; a whole frame period is 5 ms.
  EXPECT_LT(worst_us, 30.0);
  // A restart forgets the old line: the next sample alone sets the offset.
  fit.Reset();
  EXPECT_EQ(fit.samples(), 0);
  fit.Add(1000, 2000);
  EXPECT_EQ(fit.ToHost(1000), 2000);
  EXPECT_FALSE(fit.drift_fitted());
}

// The residual says how well the line is known: near zero while every run has a frame that
// barely waited, the loaded second's 4 ms while that second is in the window (its runs' best
// frames all waited), near zero again once it has left the window (1024 frames, 5.1 s).
TEST(ClockFit, ResidualIsTheWaitOfTheRunsWhoseBestFrameStillWaited) {
  std::mt19937 rng(11);
  std::exponential_distribution<double> wait(1.0 / 300'000.0);
  ClockFit fit;
  const std::uint64_t period = 5 * kMs;
  double during = 0, after = 0, before = 0;
  for (int f = 0; f < 3000; ++f) {
    const std::uint64_t t = 10'000 * kMs + f * period;
    double latency = 100'000 + wait(rng);
    if (f >= 1200 && f < 1400) latency += 4 * kMs;
    fit.Add(t + 777, t + static_cast<std::uint64_t>(latency));
    if (f == 1199) before = fit.residual_ns();
    if (f == 1450) during = fit.residual_ns();
    if (f == 2999) after = fit.residual_ns();
  }
  std::printf("clock fit residual: %.1f us before, %.1f us with the loaded second, %.1f us after\n",
              before * 1e-3, during * 1e-3, after * 1e-3);
  EXPECT_LT(before, 30'000);
  EXPECT_GT(during, 3.9 * kMs);
  EXPECT_LT(during, 4.2 * kMs);
  EXPECT_LT(after, 30'000);
  fit.Reset();
  EXPECT_EQ(fit.residual_ns(), 0);
}

// A camera whose own timestamps jitter (20 us, gaussian: the free-run rig of the capture
// pipeline's tests) over 2.7 s at 100 Hz, its frames waiting as on a loaded host (exponential,
// mean 300 us, and one run in four of 17 frames waiting 0.5-2 ms more even at its best). The
// runs' earliest arrivals then scatter by tens of us on both sides of the line, and a support
// line through two neighbouring ones, 0.17 s apart, tilts by their difference over 0.17 s: 60
// ppm for 10 us. The slope refitted through every run that did not wait averages that scatter:
// over 400 such recordings of a -120 ppm clock the drift's RMS error is 11.8 ppm and 1 is more
// than 50 ppm off (the support line alone: 17.4 ppm, 7 of them).
TEST(ClockFit, DriftFromShortRecordingsWithJitteredStampsOnALoadedHost) {
  const double drift = -120e-6;
  double sum_sq = 0;
  int beyond_50 = 0;
  const int recordings = 400;
  for (int seed = 0; seed < recordings; ++seed) {
    std::mt19937 rng(1000 + seed);
    std::exponential_distribution<double> wait(1.0 / 300'000.0);
    std::normal_distribution<double> jitter(0.0, 20'000.0);
    std::uniform_real_distribution<double> extra(0.5e6, 2e6);
    std::uniform_int_distribution<int> loaded(0, 3);
    ClockFit fit;
    const std::uint64_t period = 10 * kMs;  // 100 Hz
    double run_extra = 0;
    for (int f = 0; f < 270; ++f) {
      if (f % 17 == 0) run_extra = loaded(rng) == 0 ? extra(rng) : 0.0;
      const std::uint64_t t = 20'000 * kMs + f * period;
      const auto device = static_cast<std::uint64_t>(
          1'700'000'000.0 + (1 + drift) * static_cast<double>(t) + jitter(rng));
      const double latency = 100'000 + wait(rng) + run_extra;
      fit.Add(device, t + static_cast<std::uint64_t>(latency));
    }
    ASSERT_TRUE(fit.drift_fitted());
    const double err = fit.drift_ppm() + 120.0;
    sum_sq += err * err;
    beyond_50 += std::abs(err) > 50 ? 1 : 0;
  }
  const double rms = std::sqrt(sum_sq / recordings);
  std::printf("clock fit, %d short jittered recordings: drift RMS error %.1f ppm, %d beyond 50 ppm\n",
              recordings, rms, beyond_50);
  EXPECT_LT(rms, 13.0);
  EXPECT_LE(beyond_50, 2);
}

TEST(ClockFit, BadOptionsAreNamed) {
  std::string error;
  ClockFitOptions o;
  o.segments = 1;
  EXPECT_FALSE(o.IsValid(&error));
  EXPECT_NE(error.find("segments 1"), std::string::npos) << error;
  o = ClockFitOptions();
  o.min_samples_for_drift = 4;
  EXPECT_FALSE(o.IsValid(&error));
  EXPECT_NE(error.find("min_samples_for_drift 4"), std::string::npos) << error;
}

// A triggered rig grouped by trigger count, checked by timestamps: camera 1 misses one trigger
// without its id counter noticing (its ids run one ahead from frame 300 on). The sets still
// complete, but the check counts every set after the slip as mismatched; none before it.
TEST(FrameSync, SequenceModeTimestampCheckCatchesACameraOneTriggerOff) {
  FrameSyncOptions o = SeqOptions(2);
  o.check_tolerance_ns = 1 * kMs;
  FrameSync sync;
  ASSERT_TRUE(sync.Reset(o).ok());
  std::vector<DetectionSet> out;
  const std::uint64_t period = 10 * kMs;
  std::uint64_t mismatched_at_slip = 0;
  for (int f = 0; f < 600; ++f) {
    const std::uint64_t t = 1000 * kMs + f * period;
    if (f == 300) mismatched_at_slip = sync.counters().mismatched;
    ASSERT_TRUE(sync.Add(Det(0, f, t + kMs / 2, t + 5'000 * kMs), &out).ok());
    const std::uint64_t id1 = f < 300 ? f : f - 1;  // frame f reported as the previous trigger
    ASSERT_TRUE(sync.Add(Det(1, id1, t + kMs / 2, t + 77 * kMs), &out).ok());
  }
  sync.Flush(&out);
  EXPECT_EQ(mismatched_at_slip, 0u);
  EXPECT_GE(sync.counters().mismatched, 280u);
  // The offsets of the two clocks are found (device - common time).
  EXPECT_NEAR(static_cast<double>(sync.offset_ns(0) - sync.offset_ns(1)), 4'923.0 * kMs,
              0.01 * kMs);
}

TEST(FrameSync, TimestampModeWithKnownOffsets) {
  FrameSyncOptions o;
  o.num_cameras = 2;
  o.mode = FrameSyncOptions::Mode::kTimestamp;
  o.estimate_offsets = false;
  o.camera_offsets_ns = {0, 7 * kMs};
  o.tolerance_ns = kMs;
  o.timeout_ns = 0;
  FrameSync sync;
  ASSERT_TRUE(sync.Reset(o).ok());
  std::vector<DetectionSet> out;
  ASSERT_TRUE(sync.Add(Det(0, 1, 0, 100 * kMs), &out).ok());
  ASSERT_TRUE(sync.Add(Det(1, 9, 0, 107 * kMs + 300'000), &out).ok());
  ASSERT_EQ(out.size(), 1u);
  EXPECT_EQ(out[0].present_count(), 2);
  EXPECT_EQ(out[0].sequence, 1u);  // the lowest-numbered camera's
  // A frame near an emitted set is late; a duplicate within tolerance of a pending one counted.
  ASSERT_TRUE(sync.Add(Det(0, 2, 0, 100 * kMs + 500'000), &out).ok());
  EXPECT_EQ(sync.counters().late, 1u);
  ASSERT_TRUE(sync.Add(Det(0, 3, 0, 105 * kMs), &out).ok());
  ASSERT_TRUE(sync.Add(Det(0, 3, 0, 105 * kMs + 200'000), &out).ok());
  EXPECT_EQ(sync.counters().duplicate, 1u);
}

TEST(FrameSync, BadOptionsAndCamerasAreErrors) {
  FrameSync sync;
  std::vector<DetectionSet> out;
  Status s = sync.Add(Det(0, 0, 0), &out);
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.message().find("Reset"), std::string::npos);
  FrameSyncOptions o;
  s = sync.Reset(o);
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.message().find("num_cameras 0"), std::string::npos) << s.message();
  o = SeqOptions(2);
  o.max_pending_sets = 0;
  s = sync.Reset(o);
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.message().find("max_pending_sets"), std::string::npos) << s.message();
  o = SeqOptions(2);
  o.mode = FrameSyncOptions::Mode::kTimestamp;
  o.estimate_offsets = false;
  o.camera_offsets_ns = {1, 2, 3};
  s = sync.Reset(o);
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.message().find("3 entries for 2 cameras"), std::string::npos) << s.message();
  ASSERT_TRUE(sync.Reset(SeqOptions(2)).ok());
  s = sync.Add(Det(2, 0, 0), &out);
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.message().find("camera 2 is outside the rig's 2 cameras"), std::string::npos);
  s = sync.Add(Det(-1, 0, 0), &out);
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(sync.counters().frames, 0u);
}

}  // namespace
}  // namespace mocap::reconstruction
