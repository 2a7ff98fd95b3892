// The capture pipeline (daemon/capture_pipeline.h) on in-process simulated cameras drawing the
// simulated subject: points against the truth, a camera lost and back while the others go on,
// a clean stop, bad options; and its bounded queue. The live pipeline around it
// (daemon/live_pipeline.h): subject.select's tracker and model.apply's swap, in order.
#include <gtest/gtest.h>


#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstring>
#include <memory>
#include <mutex>
#include <thread>

#include "daemon/bounded_queue.h"
#include "daemon/capture_pipeline.h"
#include "daemon/live_pipeline.h"
#include "drivers/simulated_camera.h"
#include "model/default_model.h"
#include "reconstruction/triangulation.h"
#include "sim/camera_rig.h"
#include "sim/reconstruction_score.h"
#include "sim/renderer.h"
#include "sim/simulate.h"

namespace mocap {
namespace {

TEST(BoundedQueue, KeepsOrderRefusesWhenFullAndDrainsAfterClose) {
  daemon::BoundedQueue<int> q(3);
  int a = 1, b = 2, c = 3, d = 4;
  EXPECT_TRUE(q.TryPush(std::move(a)));
  EXPECT_TRUE(q.TryPush(std::move(b)));
  EXPECT_TRUE(q.TryPush(std::move(c)));
  EXPECT_FALSE(q.TryPush(std::move(d)));  // full: the producer learns at once
  int out = 0;
  ASSERT_TRUE(q.Pop(&out, std::chrono::milliseconds(0)));
  EXPECT_EQ(out, 1);
  q.Close();
  int e = 5;
  EXPECT_FALSE(q.TryPush(std::move(e)));  // closed
  ASSERT_TRUE(q.Pop(&out, std::chrono::milliseconds(0)));
  EXPECT_EQ(out, 2);
  ASSERT_TRUE(q.Pop(&out, std::chrono::milliseconds(0)));
  EXPECT_EQ(out, 3);
  EXPECT_FALSE(q.Pop(&out, std::chrono::milliseconds(10)));  // closed and drained
}

// The high-water mark keeps the deepest fill after the queue drained (a soak samples it once a
// minute; the instantaneous depth would read 0).
TEST(BoundedQueue, DepthKeepsTheMostItHeld) {
  daemon::BoundedQueue<int> q(4);
  EXPECT_EQ(q.Depth().max_depth, 0u);
  for (int i = 0; i < 3; ++i) EXPECT_TRUE(q.TryPush(int(i)));
  int out = 0;
  for (int i = 0; i < 3; ++i) ASSERT_TRUE(q.Pop(&out, std::chrono::milliseconds(0)));
  EXPECT_TRUE(q.TryPush(int(7)));
  const daemon::QueueDepth d = q.Depth();
  EXPECT_EQ(d.depth, 1u);
  EXPECT_EQ(d.max_depth, 3u);
  EXPECT_EQ(d.capacity, 4u);
  for (int i = 0; i < 5; ++i) q.TryPush(int(i));  // fills it; the fifth is refused
  EXPECT_EQ(q.Depth().max_depth, 4u);
}

TEST(RecentSamples, KeepsTheLatestAndTakesPercentilesOfThem) {
  daemon::RecentSamples r(4);
  EXPECT_EQ(r.Percentile(50), 0.0);  // empty
  for (double v : {100.0, 200.0, 1.0, 2.0, 3.0, 4.0}) r.Add(v);  // 100 and 200 fall out
  EXPECT_EQ(r.Percentile(100), 4.0);
  EXPECT_EQ(r.Percentile(50), 2.0);
  EXPECT_EQ(r.Percentile(1), 1.0);
}

TEST(CapturePipeline, ACameraWithoutFramesWhileTheOthersDeliverIsSilent) {
  constexpr std::uint64_t kS = 1'000'000'000;
  const std::uint64_t now = 100 * kS;
  // Camera 1 last delivered 0.7 s ago, the others within the 0.5 s.
  std::vector<double> silent = daemon::SilentCameraSeconds({now - kS / 10, now - 7 * kS / 10, now - 3 * kS / 10}, now, 0.5);
  ASSERT_EQ(silent.size(), 3u);
  EXPECT_EQ(silent[0], 0.0);
  EXPECT_NEAR(silent[1], 0.7, 1e-9);
  EXPECT_EQ(silent[2], 0.0);
  // Exactly at the bound: not yet.
  EXPECT_EQ(daemon::SilentCameraSeconds({now, now - kS / 2}, now, 0.5)[1], 0.0);
  // The whole rig stopped (trigger off, the host descheduled): no camera is singled out.
  EXPECT_EQ(daemon::SilentCameraSeconds({now - kS, now - 2 * kS}, now, 0.5), (std::vector<double>{0.0, 0.0}));
  EXPECT_EQ(daemon::SilentCameraSeconds({now - 3 * kS}, now, 0.5), std::vector<double>{0.0});
  // A frame stamped after `now` (read on another thread meanwhile) is a camera that delivers.
  silent = daemon::SilentCameraSeconds({now + 1000, now - kS}, now, 0.5);
  EXPECT_EQ(silent[0], 0.0);
  EXPECT_NEAR(silent[1], 1.0, 1e-9);
  EXPECT_TRUE(daemon::SilentCameraSeconds({}, now, 0.5).empty());
}

// A rig of simulated cameras at 100 Hz watching the simulated subject, and its pipeline.
struct Rig {
  static constexpr double kRate = 100.0;
  std::vector<reconstruction::CameraModel> cameras;
  sim::SimulatedSession session;
  std::shared_ptr<const sim::Scene> scene;
  std::unique_ptr<sim::Renderer> renderer;
  std::vector<drivers::SimulatedCamera*> sources;  // owned by the pipeline
  std::unique_ptr<reconstruction::Triangulator> triangulator;
  std::unique_ptr<daemon::CapturePipeline> pipeline;

  explicit Rig(int n, daemon::CapturePipelineOptions options = {},
               std::vector<drivers::SimulatedCameraOptions> camera_options = {}) {
    sim::CameraRigOptions ro;
    ro.cameras = n;
    cameras = sim::MakeCameraRig(ro);
    sim::SimulationOptions so;
    so.noise_mm = 0;
    so.rate_hz = kRate;
    EXPECT_TRUE(sim::SimulateSession(so, &session).ok());
    scene = sim::MakeSessionScene(session);
    sim::RendererOptions rend;
    rend.frame_rate_hz = kRate;
    renderer = std::make_unique<sim::Renderer>(cameras, scene, rend);
    EXPECT_TRUE(renderer->status().ok()) << renderer->status().message();
    drivers::CameraSettings settings;
    settings.frame_rate_hz = kRate;
    std::vector<std::unique_ptr<drivers::CameraSource>> owned;
    for (int c = 0; c < n; ++c) {
      auto cam = std::make_unique<drivers::SimulatedCamera>(
          c, renderer->Generator(),
          c < static_cast<int>(camera_options.size()) ? camera_options[c]
                                                      : drivers::SimulatedCameraOptions{});
      EXPECT_TRUE(cam->Open(settings).ok());
      sources.push_back(cam.get());
      owned.push_back(std::move(cam));
    }
    EXPECT_TRUE(reconstruction::Triangulator::Create(cameras, {}, &triangulator).ok());
    auto ws = std::make_shared<reconstruction::TriangulationWorkspace>();
    auto pts = std::make_shared<std::vector<reconstruction::TriangulatedPoint>>();
    daemon::TriangulateFn fn = [this, ws, pts](const reconstruction::DetectionSet& set,
                                               daemon::PointFrame* out) {
      MOCAP_RETURN_IF_ERROR(triangulator->Triangulate(set, ws.get(), pts.get()));
      out->points.clear();
      for (const auto& p : *pts) out->points.push_back(p.position);
      return Status::Ok();
    };
    options.detection.threshold = 60;
    // The renderer's centroid jitter is the rig's 2D error (as `mocap capture` sets it).
    options.detection.sigma_floor_px = rend.centroid_noise_px;
    pipeline = std::make_unique<daemon::CapturePipeline>(std::move(owned), fn, options);
  }

  // Collects point frames for `seconds` of wall time.
  std::vector<daemon::PointFrame> Collect(double seconds) {
    std::vector<daemon::PointFrame> frames;
    const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(seconds);
    while (std::chrono::steady_clock::now() < end) {
      daemon::PointFrame pf;
      if (pipeline->PopPoints(&pf, 20)) frames.push_back(std::move(pf));
    }
    return frames;
  }

  sim::ReconstructionScore Score(const std::vector<daemon::PointFrame>& frames) const {
    sim::ReconstructionScore score;
    for (const auto& pf : frames) {
      sim::ScoreRenderedFrame(*renderer, *scene, pf.sequence, pf.present_mask, pf.points, 0.005,
                              &score);
    }
    return score;
  }
};

TEST(CapturePipeline, SimulatedRigGivesTheSubjectsMarkers) {
  Rig rig(6);
  ASSERT_TRUE(rig.pipeline->Start().ok());
  std::vector<daemon::PointFrame> frames = rig.Collect(2.0);
  rig.pipeline->Stop();
  for (daemon::PointFrame pf; rig.pipeline->PopPoints(&pf, 0);) frames.push_back(std::move(pf));
  const daemon::CapturePipelineStats st = rig.pipeline->Stats();
  // 2 s at 100 Hz, less start-up.
  EXPECT_GE(frames.size(), 180u);
  EXPECT_EQ(st.frame_sets, frames.size());
  const sim::ReconstructionScore score = rig.Score(frames);
  std::printf("%zu sets, %llu incomplete, %llu dropped; recall %.4f, rms %.3f mm, ghosts %.4f, "
              "latency p50 %.2f ms\n",
              frames.size(), static_cast<unsigned long long>(st.incomplete_sets),
              static_cast<unsigned long long>(st.dropped_frame_sets), score.recall(),
              score.rms_mm(), score.ghost_fraction(), st.latency_ms_p50);
  std::printf("Cramer-Rao bound of the same views %.3f mm\n", score.rms_bound_mm());
  EXPECT_GE(score.recall(), 0.99);
  EXPECT_LT(score.rms_mm(), 0.5);
  // Detection and triangulation together stay near the best any unbiased estimator can do from
  // the same views at the renderer's centroid noise.
  EXPECT_GT(score.rms_bound_mm(), 0.1);
  EXPECT_LT(score.rms_mm(), 1.1 * score.rms_bound_mm());
  EXPECT_LT(score.ghost_fraction(), 0.01);
  EXPECT_GT(score.true_visible, 30 * 180);  // the subject's markers were in view
  // Sequences strictly increase: sets come out in order, none twice.
  for (std::size_t i = 1; i < frames.size(); ++i) {
    EXPECT_GT(frames[i].sequence, frames[i - 1].sequence);
  }
  // Every buffer went back to its camera: the cameras never ran out (no underruns).
  for (auto* cam : rig.sources) EXPECT_EQ(cam->Counters().underruns.load(), 0u) << cam->id();
}

TEST(CapturePipeline, LostCameraIsReportedOthersGoOnAndItComesBack) {
  daemon::CapturePipelineOptions o;
  o.sync.timeout_ns = 30'000'000;  // a missing camera's sets leave after 30 ms
  Rig rig(5, o);
  ASSERT_TRUE(rig.pipeline->Start().ok());
  std::vector<daemon::PointFrame> before = rig.Collect(0.5);
  rig.sources[2]->Lose();
  std::vector<daemon::PointFrame> during = rig.Collect(0.6);
  rig.sources[2]->Restore();
  std::vector<daemon::PointFrame> after = rig.Collect(0.8);
  rig.pipeline->Stop();
  const daemon::CapturePipelineStats st = rig.pipeline->Stats();
  EXPECT_EQ(st.camera_losses[2], 1u);
  for (int c : {0, 1, 3, 4}) EXPECT_EQ(st.camera_losses[c], 0u) << c;
  // During the loss the others go on: sets without camera 2, still with points.
  int without = 0;
  for (const auto& pf : during) {
    if (!(pf.present_mask >> 2 & 1)) {
      ++without;
      EXPECT_EQ(pf.cameras_present, 4);
      EXPECT_GT(pf.points.size(), 20u);
    }
  }
  EXPECT_GT(without, 30);
  EXPECT_GT(st.incomplete_sets, 30u);
  // Afterwards camera 2 is back in the sets.
  int with_two = 0;
  for (const auto& pf : after) with_two += (pf.present_mask >> 2 & 1) ? 1 : 0;
  EXPECT_GT(with_two, 20);
  EXPECT_EQ(rig.sources[2]->Counters().reopens.load(), 1u);
  const sim::ReconstructionScore score = rig.Score(during);
  EXPECT_GE(score.recall(), 0.98);
  EXPECT_LT(score.ghost_fraction(), 0.01);
}

// The sets of a rig after a fault: how many hold every camera, and the reconstruction against
// the renderer's truth (a frame in the wrong set shows as error and ghosts: the subject moves
// ~10 mm in a frame period).
void ExpectSetsRight(const Rig& rig, const std::vector<daemon::PointFrame>& frames,
                     const char* after, int cameras, double min_complete) {
  ASSERT_GT(frames.size(), 40u) << after;
  int complete = 0;
  for (const auto& pf : frames) complete += pf.cameras_present == cameras ? 1 : 0;
  const sim::ReconstructionScore score = rig.Score(frames);
  std::printf("after %s: %zu sets, %.1f %% complete; recall %.4f, rms %.3f mm, ghosts %.4f\n",
              after, frames.size(), 100.0 * complete / frames.size(), score.recall(),
              score.rms_mm(), score.ghost_fraction());
  EXPECT_GE(static_cast<double>(complete) / frames.size(), min_complete) << after;
  EXPECT_GE(score.recall(), 0.98) << after;
  EXPECT_LT(score.rms_mm(), 0.5) << after;
  EXPECT_LT(score.ghost_fraction(), 0.01) << after;
  for (std::size_t i = 1; i < frames.size(); ++i)
    ASSERT_GT(frames[i].sequence, frames[i - 1].sequence) << after;
}

// Runs `rig` for 1.2 s (camera `late` starting late), reconnects camera `returning` missing
// `missed` frames, and checks the sets once the late camera is in and after the return.
// `then_s`: seconds more collected after the reconnect's sets, before the stop.
daemon::CapturePipelineStats RunLateStartAndReconnect(Rig* rig, int late, int returning, int missed,
                                                      const std::string& what, double then_s = 0) {
  EXPECT_TRUE(rig->pipeline->Start().ok());
  const std::vector<daemon::PointFrame> start = rig->Collect(1.2);
  rig->sources[returning]->Reconnect(missed);
  rig->Collect(0.5);  // the outage and the returned camera's first frames
  const std::vector<daemon::PointFrame> after = rig->Collect(1.0);
  if (then_s > 0) rig->Collect(then_s);
  rig->pipeline->Stop();
  std::vector<daemon::PointFrame> late_started;
  for (const auto& pf : start)
    if (pf.present_mask >> late & 1) late_started.push_back(pf);
  const int n = static_cast<int>(rig->sources.size());
  ExpectSetsRight(*rig, late_started, ("a late start (" + what + ")").c_str(), n, 0.95);
  ExpectSetsRight(*rig, after,
                  ("a reconnect that missed " + std::to_string(missed) + " frames (" + what + ")").c_str(),
                  n, 0.95);
  return rig->pipeline->Stats();
}

// Free run: five cameras with clocks of their own (epochs seconds apart, drifts of -120..+150
// ppm, 20 us of timestamp jitter), one starting 300 ms late, one unplugged for 25 frames, which
// comes back with its ids and clock restarted. Sets are grouped by each camera's fitted host
// time and numbered by time: after each fault they must be the renderer's instants.
TEST(CapturePipeline, FreeRunCamerasWithOwnClocksAreSetByFittedTime) {
  daemon::CapturePipelineOptions o;
  o.rig_sync = daemon::CapturePipelineOptions::RigSync::kFreeRun;
  o.rate_hz = Rig::kRate;
  o.sync.timeout_ns = 40'000'000;
  std::vector<drivers::SimulatedCameraOptions> co(5);
  const double drift[5] = {0, 150, -120, 40, 90};
  for (int c = 0; c < 5; ++c) {
    co[c].clock_offset_ns = 1'700'000'000LL * c + 12'345'678LL;
    co[c].clock_drift_ppm = drift[c];
    co[c].timestamp_jitter_ns = 20'000;
  }
  co[3].start_delay_ms = 300;
  Rig rig(5, o, co);
  const daemon::CapturePipelineStats st = RunLateStartAndReconnect(&rig, 3, 1, 25, "free run", 3.0);
  EXPECT_EQ(st.camera_losses[1], 1u);
  EXPECT_EQ(st.camera_resyncs[1], 1u);
  for (int c = 1; c < 5; ++c)
    std::printf("camera %d: fitted drift %.1f ppm (truth %.0f)\n", c,
                st.camera_clock_drift_ppm[c], drift[c]);
  // The drift of a camera that never restarted is found over ~5.7 s of frames arriving on a
  // loaded host (the fit's window holds 10 s at 100 Hz). Over the first 2.7 s alone the fit
  // scattered by +-30 ppm beside two busy nice-10 cores here and left the 50 ppm bound on a
  // loaded CI host (27 Nov 2026). On a loaded host the in-process cameras fall behind and
  // catch up slowly, so even the runs' earliest arrivals carry a backlog that changes over the
  // take (a dump beside four busy cores: 0.53 ms at the start, 0 at the end, a 90 ppm slope over
  // 5.7 s). No lower envelope sees through that; a longer span dilutes it, so the test now spans
  // twice as long (six loaded runs here: -168 to -107 ppm).
  EXPECT_NEAR(st.camera_clock_drift_ppm[2], -120.0, 50.0);
}

// A triggered rig: sets by trigger count. Camera 2 starts 250 ms late (its ids begin at 1) and
// camera 1 is unplugged for 30 frames (its ids restart): both are put back on the rig's count by
// the time since the rig's newest frame, and the timestamp check finds every set consistent.
TEST(CapturePipeline, TriggerRigPutsALateAndAReturningCameraOnTheRightTrigger) {
  daemon::CapturePipelineOptions o;
  o.rig_sync = daemon::CapturePipelineOptions::RigSync::kTrigger;
  o.rate_hz = Rig::kRate;
  o.sync.timeout_ns = 40'000'000;
  std::vector<drivers::SimulatedCameraOptions> co(4);
  for (int c = 0; c < 4; ++c) co[c].clock_offset_ns = 900'000'000LL * c;
  co[2].start_delay_ms = 250;
  Rig rig(4, o, co);
  const daemon::CapturePipelineStats st = RunLateStartAndReconnect(&rig, 2, 1, 30, "trigger");
  EXPECT_EQ(st.camera_resyncs[1], 1u);
  std::printf("trigger rig: %llu sets mismatched by timestamps\n",
              static_cast<unsigned long long>(st.mismatched_sets));
  EXPECT_EQ(st.mismatched_sets, 0u);
  // Neither the late start nor the return is a count that disagrees with its own timestamps.
  for (int c = 0; c < 4; ++c) EXPECT_EQ(st.camera_count_mismatches[c], 0u) << "camera " << c;
}

// A triggered camera whose counter slips one pulse ahead of its exposures (a glitch on its
// trigger line): the frame after the slip advanced its id by two and its timestamp by one
// period. The rig check's count-vs-timestamp figure finds that one frame and no other, on that
// camera only; the sync's timestamp check then finds its sets one trigger off.
TEST(CapturePipeline, TriggerRigCountsTheFrameWhoseCountSlippedFromItsTimestamp) {
  daemon::CapturePipelineOptions o;
  o.rig_sync = daemon::CapturePipelineOptions::RigSync::kTrigger;
  o.rate_hz = Rig::kRate;
  o.sync.timeout_ns = 40'000'000;
  std::vector<drivers::SimulatedCameraOptions> co(3);
  for (int c = 0; c < 3; ++c) co[c].clock_offset_ns = 700'000'000LL * c;
  Rig rig(3, o, co);
  ASSERT_TRUE(rig.pipeline->Start().ok());
  rig.Collect(1.5);  // the clocks' drift fits need 128 frames before the check judges a set
  rig.sources[1]->SlipCount(1);
  rig.Collect(1.0);
  rig.pipeline->Stop();
  const daemon::CapturePipelineStats st = rig.pipeline->Stats();
  std::printf("slipped count: mismatches per camera %llu %llu %llu, sets mismatched %llu\n",
              static_cast<unsigned long long>(st.camera_count_mismatches[0]),
              static_cast<unsigned long long>(st.camera_count_mismatches[1]),
              static_cast<unsigned long long>(st.camera_count_mismatches[2]),
              static_cast<unsigned long long>(st.mismatched_sets));
  EXPECT_EQ(st.camera_count_mismatches[0], 0u);
  EXPECT_EQ(st.camera_count_mismatches[1], 1u);
  EXPECT_EQ(st.camera_count_mismatches[2], 0u);
  EXPECT_GT(st.mismatched_sets, 50u);
}

// A sequence that no camera delivered (every camera skipped the tick: a rig of fakes in a
// descheduled process) is not a set the daemon lost; one whose frames reached the daemon and were
// dropped at its full queue (detection held for longer than the queue holds) is.
TEST(CapturePipeline, SetsNoCameraDeliveredAreToldApartFromTheDaemonsLosses) {
  daemon::CapturePipelineOptions o;
  o.rig_sync = daemon::CapturePipelineOptions::RigSync::kTrigger;
  o.rate_hz = Rig::kRate;
  o.sync.timeout_ns = 40'000'000;
  std::atomic<bool> hold{false};
  o.test_hold = [&hold](const char* stage) {
    while (std::strcmp(stage, "detection") == 0 && hold.load())
      std::this_thread::sleep_for(std::chrono::milliseconds(1));
  };
  std::vector<drivers::SimulatedCameraOptions> co(3);
  for (auto& c : co) c.unexposed_every = 25;  // the same ticks on every camera
  Rig rig(3, o, co);
  ASSERT_TRUE(rig.pipeline->Start().ok());
  const std::vector<daemon::PointFrame> frames = rig.Collect(1.6);
  const daemon::CapturePipelineStats before = rig.pipeline->Stats();
  std::printf("skipped ticks: %llu sets undelivered, %llu dropped, %zu frames\n",
              static_cast<unsigned long long>(before.undelivered_frame_sets),
              static_cast<unsigned long long>(before.dropped_frame_sets), frames.size());
  ASSERT_GE(frames.size(), 40u);
  for (const daemon::PointFrame& f : frames) EXPECT_NE(f.sequence % 25, 0u) << "an unexposed tick came out";
  // About one in 25 of the sets handed out (the first ones may precede the first gap).
  EXPECT_GE(before.undelivered_frame_sets, frames.size() / 25 - 1);
  EXPECT_LE(before.undelivered_frame_sets, frames.size() / 24 + 2);
  // None lost by the pipeline, unless a grab thread fell so far behind on a loaded host that a
  // camera's ring overflowed (underruns, the daemon's: a set can be lost only with them).
  std::uint64_t underruns = 0;
  for (const drivers::SimulatedCamera* c : rig.sources) underruns += c->Counters().underruns.load();
  EXPECT_LE(before.dropped_frame_sets, underruns);
  hold = true;  // 2 s of detection stopped: the 128-frame queues (1.28 s) overflow
  std::this_thread::sleep_for(std::chrono::milliseconds(2000));
  hold = false;
  rig.Collect(0.6);
  rig.pipeline->Stop();
  const daemon::CapturePipelineStats after = rig.pipeline->Stats();
  std::printf("detection held 2 s: %llu frames dropped at the queue, sets dropped %llu, undelivered %llu\n",
              static_cast<unsigned long long>(after.frames_dropped),
              static_cast<unsigned long long>(after.dropped_frame_sets),
              static_cast<unsigned long long>(after.undelivered_frame_sets));
  // Lost at the full queues, or in the cameras' rings for want of the buffers the queued frames
  // held: the daemon's either way.
  std::uint64_t underruns_after = 0;
  for (const drivers::SimulatedCamera* c : rig.sources) underruns_after += c->Counters().underruns.load();
  std::printf("  ... and %llu frames lost in the cameras' rings (underruns)\n",
              static_cast<unsigned long long>(underruns_after - underruns));
  EXPECT_GT(after.frames_dropped + (underruns_after - underruns), 3u * 40);
  EXPECT_GE(after.dropped_frame_sets, 40u);
  // The unexposed ticks of those 2.6 s go on being counted as such (about 10).
  EXPECT_LE(after.undelivered_frame_sets - before.undelivered_frame_sets, 12u);
}

TEST(CapturePipeline, RecordingStartsAtTheFirstCompleteSet) {
  Rig rig(4);
  // Camera 3 starts late: its first 30 frames (0.3 s) never arrive.
  rig.sources[3]->DropFrames(30);
  ASSERT_TRUE(rig.pipeline->Start().ok());
  std::vector<daemon::PointFrame> frames = rig.Collect(0.8);
  rig.pipeline->Stop();
  for (daemon::PointFrame pf; rig.pipeline->PopPoints(&pf, 0);) frames.push_back(std::move(pf));
  const daemon::CapturePipelineStats st = rig.pipeline->Stats();
  ASSERT_FALSE(frames.empty());
  EXPECT_TRUE(st.recording);
  EXPECT_EQ(frames.front().cameras_present, 4);  // nothing before the rig was live
  // The sets camera 3 missed, then 20 complete ones (start_complete_sets) before the recording.
  EXPECT_GE(st.warmup_sets, 25u + 19u);
  EXPECT_LE(st.warmup_sets, 35u + 19u);
  EXPECT_GT(st.warmup_ms, 350.0);
  EXPECT_TRUE(st.cameras_missing_at_start.empty());
  EXPECT_EQ(st.frame_sets, frames.size());
  EXPECT_EQ(st.dropped_frame_sets, 0u);  // warm-up sets are not losses of the recording
}

TEST(CapturePipeline, ACameraSilentAtStartDoesNotHoldTheRecording) {
  daemon::CapturePipelineOptions o;
  o.start_timeout_ms = 200;
  o.sync.timeout_ns = 30'000'000;
  Rig rig(4, o);
  rig.sources[1]->Lose();  // never streams
  ASSERT_TRUE(rig.pipeline->Start().ok());
  std::vector<daemon::PointFrame> frames = rig.Collect(0.8);
  rig.pipeline->Stop();
  const daemon::CapturePipelineStats st = rig.pipeline->Stats();
  EXPECT_TRUE(st.recording);
  EXPECT_EQ(st.cameras_missing_at_start, std::vector<int>{1});
  EXPECT_GE(st.warmup_ms, 200.0);
  EXPECT_GE(st.warmup_sets, 10u);
  ASSERT_GT(frames.size(), 30u);  // the three others recorded
  std::size_t all_three = 0;
  for (const auto& pf : frames) {
    EXPECT_EQ(pf.present_mask & 0b0010u, 0u);
    all_three += pf.present_mask == 0b1101u;
  }
  // (A set may leave without one of them when the 30 ms sync timeout meets a busy machine.)
  EXPECT_GE(all_three, frames.size() * 9 / 10);
  EXPECT_GT(frames.front().points.size(), 20u);

  daemon::CapturePipelineOptions waiting_off;
  waiting_off.start_on_complete_set = false;
  Rig eager(3, waiting_off);
  eager.sources[2]->DropFrames(20);
  ASSERT_TRUE(eager.pipeline->Start().ok());
  std::vector<daemon::PointFrame> eager_frames = eager.Collect(0.4);
  eager.pipeline->Stop();
  ASSERT_FALSE(eager_frames.empty());
  EXPECT_EQ(eager_frames.front().cameras_present, 2);  // recorded from the first set
  EXPECT_EQ(eager.pipeline->Stats().warmup_sets, 0u);
}

TEST(CapturePipeline, BadSetUpIsRefusedWithAReason) {
  // Each bad option refuses the start with an error naming it; Stop is harmless when never started.
  auto expect_refused = [](void (*spoil)(daemon::CapturePipelineOptions*), const char* field) {
    daemon::CapturePipelineOptions o;
    spoil(&o);
    Rig rig(2, o);
    const Status s = rig.pipeline->Start();
    EXPECT_FALSE(s.ok()) << field;
    EXPECT_NE(s.message().find(field), std::string::npos) << s.message();
    rig.pipeline->Stop();
  };
  expect_refused([](daemon::CapturePipelineOptions* o) { o->detection_threads = 0; }, "detection_threads");
  expect_refused([](daemon::CapturePipelineOptions* o) { o->start_timeout_ms = -1; }, "start_timeout_ms");
  expect_refused([](daemon::CapturePipelineOptions* o) { o->start_complete_sets = 0; },
                 "start_complete_sets");
  expect_refused([](daemon::CapturePipelineOptions* o) { o->camera_silence_s = -1; }, "camera_silence_s");

  daemon::CapturePipeline empty({}, [](const reconstruction::DetectionSet&, daemon::PointFrame*) {
    return Status::Ok();
  });
  const Status e = empty.Start();
  ASSERT_FALSE(e.ok());
  EXPECT_NE(e.message().find("no cameras"), std::string::npos) << e.message();
}

// subject.select then model.apply before the next frame (a lab selects a subject and applies
// its model at once): the select's new tracker starts on the applied model. The frames are held
// back (test_hold) until both requests are in, so the apply always finds the select pending;
// before the fix it replaced the select and failed with "no subject is being tracked", and no
// tracker ever started.
// A live pipeline on two blank simulated cameras whose frames are held back (test_hold) until
// Open(): requests made before it are all pending when the tracking thread sees its first frame.
// Two blank 64 x 48 simulated cameras at `rate_hz`, open: no points, so a tracker never starts.
std::vector<std::unique_ptr<drivers::CameraSource>> BlankCameras(double rate_hz) {
  drivers::SimulatedCameraOptions co;
  co.width = 64;
  co.height = 48;
  drivers::CameraSettings settings;
  settings.frame_rate_hz = rate_hz;
  std::vector<std::unique_ptr<drivers::CameraSource>> cameras;
  for (int c = 0; c < 2; ++c) {
    auto cam = std::make_unique<drivers::SimulatedCamera>(
        c, [](int, std::uint64_t, std::uint8_t* data, int w, int h, std::ptrdiff_t stride, drivers::PixelFormat) {
          for (int y = 0; y < h; ++y) std::fill(data + y * stride, data + y * stride + w, 0);
        },
        co);
    EXPECT_TRUE(cam->Open(settings).ok());
    cameras.push_back(std::move(cam));
  }
  return cameras;
}

class HeldPipeline {
 public:
  HeldPipeline() {
    daemon::LivePipelineOptions options;
    options.capture.start_on_complete_set = false;
    options.capture.test_hold = [this](const char* stage) {
      if (std::string(stage) != "grab") return;
      std::unique_lock<std::mutex> lock(mutex_);
      open_cv_.wait(lock, [&] { return open_; });
    };
    live_ = std::make_unique<daemon::LivePipeline>(BlankCameras(100), options, [] {});
    EXPECT_TRUE(live_->Start().ok());
    const Model full = DefaultFullBodyModel(1.7);
    selected_ = std::make_shared<Model>();
    EXPECT_TRUE(full.WithMarkers(sim::SimulatedMarkers(full, false), selected_.get()).ok());
    applied_ = std::make_shared<Model>(*selected_);
  }
  ~HeldPipeline() {
    Open();
    live_->Stop();
  }
  void Open() {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      open_ = true;
    }
    open_cv_.notify_all();
  }
  // The first frame out of the pipeline (false: none within 5 s).
  bool FirstFrame(daemon::LiveFrame* frame) {
    const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(5);
    while (std::chrono::steady_clock::now() < until) {
      if (live_->PopFrame(frame)) return true;
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    return false;
  }
  daemon::LivePipeline& live() { return *live_; }
  std::shared_ptr<const Model> selected() const { return selected_; }
  std::shared_ptr<const Model> applied() const { return applied_; }

 private:
  std::mutex mutex_;
  std::condition_variable open_cv_;
  bool open_ = false;
  std::shared_ptr<Model> selected_, applied_;
  std::unique_ptr<daemon::LivePipeline> live_;
};

TEST(LivePipeline, ModelAppliedRightAfterASelectStartsTheTrackerOnIt) {
  HeldPipeline held;
  held.live().SetSubjectModel(held.selected(), 1);
  Status swapped = Status::Error("not returned");
  std::uint64_t from_frame = 0;
  std::thread apply([&] {
    swapped = held.live().SwapModel(held.applied(), 2, ekf::ModelOrigin::kFittedToSubject, &from_frame);
  });
  std::this_thread::sleep_for(std::chrono::milliseconds(100));  // the apply waits for a frame
  held.Open();
  apply.join();
  EXPECT_TRUE(swapped.ok()) << swapped.message();
  EXPECT_GT(from_frame, 0u);
  daemon::LiveFrame frame;
  ASSERT_TRUE(held.FirstFrame(&frame)) << "no frame from the live pipeline";
  EXPECT_EQ(frame.model_version, 2);  // the applied model, not the selected one
  EXPECT_GE(frame.tracker_state, 0) << "no tracker";
  EXPECT_EQ(static_cast<int>(frame.markers.cols()), held.applied()->num_markers());
}

// model.apply does not block the daemon's loop (RequestSwap): its answer comes from the tracking
// thread. One not taken in time is withdrawn (WithdrawSwap: the daemon's 2 s), its answer never
// given, and a select it rode on starts on the select's own model; a second apply replaces the
// first, which is answered with an error.
TEST(LivePipeline, AModelApplyIsAnsweredOnceWithdrawnOrReplaced) {
  HeldPipeline held;
  held.live().SetSubjectModel(held.selected(), 1);
  std::atomic<int> answers{0}, failed{0};
  auto done = [&](Status result, std::uint64_t) {
    ++answers;
    failed += !result.ok();
  };
  ASSERT_TRUE(held.live().RequestSwap(held.applied(), 2, ekf::ModelOrigin::kFittedToSubject, done).ok());
  EXPECT_TRUE(held.live().WithdrawSwap());
  EXPECT_FALSE(held.live().WithdrawSwap()) << "nothing left to withdraw";
  // Replaced: the first is answered with an error at once, the second by the tracking thread.
  ASSERT_TRUE(held.live().RequestSwap(held.applied(), 3, ekf::ModelOrigin::kFittedToSubject, done).ok());
  EXPECT_EQ(answers.load(), 0);
  std::atomic<int> second{0};
  std::uint64_t second_from = 0;
  ASSERT_TRUE(held.live()
                  .RequestSwap(held.applied(), 4, ekf::ModelOrigin::kFittedToSubject,
                               [&](Status result, std::uint64_t from) {
                                 EXPECT_TRUE(result.ok()) << result.message();
                                 second_from = from;
                                 ++second;
                               })
                  .ok());
  EXPECT_EQ(answers.load(), 1);
  EXPECT_EQ(failed.load(), 1);
  held.Open();
  daemon::LiveFrame frame;
  ASSERT_TRUE(held.FirstFrame(&frame)) << "no frame from the live pipeline";
  EXPECT_EQ(frame.model_version, 4);
  EXPECT_EQ(second.load(), 1);
  EXPECT_GT(second_from, 0u);
  EXPECT_EQ(answers.load(), 1) << "the withdrawn and the replaced apply are answered once in all";
}

// Withdrawn from a select it rode on, the select starts on its own model.
TEST(LivePipeline, AWithdrawnApplyLeavesTheSelectOnItsOwnModel) {
  HeldPipeline held;
  held.live().SetSubjectModel(held.selected(), 1);
  bool answered = false;
  ASSERT_TRUE(held.live()
                  .RequestSwap(held.applied(), 2, ekf::ModelOrigin::kFittedToSubject,
                               [&](Status, std::uint64_t) { answered = true; })
                  .ok());
  EXPECT_TRUE(held.live().WithdrawSwap());
  held.Open();
  daemon::LiveFrame frame;
  ASSERT_TRUE(held.FirstFrame(&frame)) << "no frame from the live pipeline";
  EXPECT_EQ(frame.model_version, 1);
  EXPECT_GE(frame.tracker_state, 0) << "no tracker";
  EXPECT_FALSE(answered);
}

// While the tracker searches for the subject (it is not tracking) and newer point frames wait,
// it searches the newest only (LivePipelineStats::searches_skipped): a search takes tens of ms
// and, run on every frame while the subject cannot be found, let the point queue overflow and
// the capture drop frames. The frames between are published untracked, none lost. The tracking
// thread is held for 300 ms (stage "track") while two blank 100 Hz cameras deliver: about 30
// frames wait; a tracker with a model and no points never starts.
TEST(LivePipeline, WhileSearchingItSearchesTheNewestWaitingFrameAndPublishesTheRest) {
  std::mutex mutex;
  std::condition_variable cv;
  bool hold = false, holding = false;
  daemon::LivePipelineOptions options;
  options.capture.start_on_complete_set = false;
  options.capture.test_hold = [&](const char* stage) {
    if (std::string(stage) != "track") return;
    std::unique_lock<std::mutex> lock(mutex);
    if (!hold) return;
    holding = true;
    cv.notify_all();
    cv.wait(lock, [&] { return !hold; });
    holding = false;
  };
  daemon::LivePipeline live(BlankCameras(100), options, [] {});
  ASSERT_TRUE(live.Start().ok());
  const Model full = DefaultFullBodyModel(1.7);
  auto model = std::make_shared<Model>();
  ASSERT_TRUE(full.WithMarkers(sim::SimulatedMarkers(full, false), model.get()).ok());
  live.SetSubjectModel(model, 1);
  std::vector<daemon::LiveFrame> frames;
  auto drain = [&](int ms) {
    const auto until = std::chrono::steady_clock::now() + std::chrono::milliseconds(ms);
    while (std::chrono::steady_clock::now() < until) {
      daemon::LiveFrame f;
      while (live.PopFrame(&f)) frames.push_back(std::move(f));
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
  };
  drain(200);
  ASSERT_FALSE(frames.empty()) << "no frame from the live pipeline";
  const std::uint64_t skipped_before = live.Stats(false).searches_skipped;
  {
    std::unique_lock<std::mutex> lock(mutex);
    hold = true;
    ASSERT_TRUE(cv.wait_for(lock, std::chrono::seconds(5), [&] { return holding; })) << "the tracking thread never held";
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(300));
  const std::size_t waiting = live.Stats(false).capture.point_queue.depth;
  {
    std::lock_guard<std::mutex> lock(mutex);
    hold = false;
  }
  cv.notify_all();
  drain(300);
  const daemon::LivePipelineStats st = live.Stats(false);
  live.Stop();
  EXPECT_GE(waiting, 20u);
  // Every waiting frame but the newest went through unsearched (a frame or two may arrive while
  // the backlog drains).
  EXPECT_GE(st.searches_skipped - skipped_before, waiting - 1);
  EXPECT_EQ(st.capture.dropped_frame_sets, 0u);
  EXPECT_EQ(st.loop_dropped, 0u);
  // None lost: the published frames are consecutive, each one untracked and unlabelled.
  for (std::size_t i = 1; i < frames.size(); ++i) EXPECT_EQ(frames[i].frame, frames[i - 1].frame + 1) << i;
  for (const daemon::LiveFrame& f : frames) {
    EXPECT_NE(f.tracker_state, static_cast<int>(ekf::TrackState::kTracking));
    EXPECT_EQ(f.labelled, 0);
  }
}

}  // namespace
}  // namespace mocap
