// `mocap capture --simulate`: the capture half of mocapd on simulated hardware, in real time.
//
// The simulated subject of `mocap sim --seed N` (noise-free markers: the image noise is the
// renderer's) performs the protocol in front of N simulated cameras (sim/camera_rig.h). Each
// camera is an Aravis fake device (drivers/aravis_fake.h) whose images the renderer draws
// (sim/renderer.h), read through the same Aravis backend as real GigE Vision / USB3 Vision
// cameras; the frames go through the capture pipeline (daemon/capture_pipeline.h: detection,
// sync, triangulation, one thread per stage, bounded queues) and the unlabelled 3D points are
// written as C3D (generic labels P001..; slot order within a frame means nothing). Since the
// truth is known, stats.json also scores the points: recall, 3D RMS and ghosts
// (sim/reconstruction_score.h).
#include <spdlog/spdlog.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <memory>
#include <nlohmann/json.hpp>

#include "daemon/capture_pipeline.h"
#include "drivers/aravis_fake.h"
#include "formats/c3d.h"
#include "reconstruction/calibration_file.h"
#include "reconstruction/triangulation.h"
#include "sim/camera_rig.h"
#include "sim/reconstruction_score.h"
#include "sim/renderer.h"
#include "sim/simulate.h"
#include "tools/command.h"

namespace {

using mocap::Status;

struct CaptureArgs {
  bool simulate = false;
  int cameras = 8;
  double seconds = 5.0;
  double rate_hz = 200.0;
  std::uint64_t seed = 1;
  int width = 1280;
  int height = 1024;
  int threads = 2;
  std::string calibration;  // empty: triangulate with the true rig
  double centroid_noise_px = 0.1;  // the renderer's centroid jitter
  std::string out;
};

// A point is a match within this distance of a true marker (the reconstruction error is a
// fraction of a millimetre; markers are centimetres apart).
constexpr double kMatchRadiusM = 0.005;

mocap::formats::MarkerTrial PointsTrial(const std::vector<mocap::daemon::PointFrame>& frames,
                                        double rate_hz) {
  std::size_t slots = 1;
  for (const auto& f : frames) slots = std::max(slots, f.points.size());
  mocap::formats::MarkerTrial t;
  t.name = "points";
  t.rate_hz = rate_hz;
  for (std::size_t s = 0; s < slots; ++s) {
    char name[16];
    std::snprintf(name, sizeof name, "P%03zu", s + 1);
    t.marker_names.push_back(name);
  }
  t.positions.setConstant(static_cast<int>(frames.size()), 3 * static_cast<int>(slots),
                          std::numeric_limits<double>::quiet_NaN());
  for (std::size_t f = 0; f < frames.size(); ++f) {
    t.frame_numbers.push_back(static_cast<int>(f) + 1);
    t.times.push_back(f / rate_hz);
    for (std::size_t p = 0; p < frames[f].points.size(); ++p) {
      t.positions.row(f).segment<3>(3 * p) = frames[f].points[p].transpose();
    }
  }
  return t;
}

int RunCapture(const CaptureArgs& a) {
  namespace fs = std::filesystem;
  using namespace mocap;
  if (!a.simulate) {
    spdlog::error("mocap capture: only --simulate is available from the command line; real "
                  "cameras are run by mocapd");
    return 2;
  }
  if (a.cameras < 2 || a.cameras > 32) {
    spdlog::error("mocap capture: --cameras must be in [2, 32], got {}", a.cameras);
    return 2;
  }
  if (!(a.seconds > 0) || a.seconds > 3600) {
    spdlog::error("mocap capture: --seconds must be in (0, 3600], got {}", a.seconds);
    return 2;
  }
  if (!(a.rate_hz >= 1) || a.rate_hz > 2000) {
    spdlog::error("mocap capture: --rate must be in [1, 2000] Hz, got {}", a.rate_hz);
    return 2;
  }
  if (!(a.centroid_noise_px >= 0) || a.centroid_noise_px > 5) {
    spdlog::error("mocap capture: --centroid-noise-px must be in [0, 5], got {}",
                  a.centroid_noise_px);
    return 2;
  }
  if (a.threads < 1 || a.threads > 64) {
    spdlog::error("mocap capture: --threads must be in [1, 64], got {}", a.threads);
    return 2;
  }
  std::error_code ec;
  fs::create_directories(a.out, ec);
  if (ec || !fs::is_directory(a.out)) {
    spdlog::error("mocap capture: cannot create output directory '{}': {}", a.out,
                  ec ? ec.message() : "not a directory");
    return 1;
  }

  // The rig, and what triangulation believes about it.
  sim::CameraRigOptions rig_options;
  rig_options.cameras = a.cameras;
  rig_options.width = a.width;
  rig_options.height = a.height;
  rig_options.seed = a.seed;
  std::string error;
  if (!rig_options.IsValid(&error)) {
    spdlog::error("mocap capture: {}", error);
    return 2;
  }
  const std::vector<reconstruction::CameraModel> true_rig = sim::MakeCameraRig(rig_options);
  std::vector<reconstruction::CameraModel> rig = true_rig;
  if (!a.calibration.empty()) {
    reconstruction::CalibrationFile cal;
    if (Status s = reconstruction::ReadCalibrationJson(a.calibration, &cal); !s) {
      spdlog::error("mocap capture: {}", s.message());
      return 2;
    }
    std::vector<std::string> ids;
    for (const auto& cam : true_rig) ids.push_back(cam.id);
    if (Status s = reconstruction::MatchCalibrationToRig(cal, ids, &rig); !s) {
      spdlog::error("mocap capture: {}", s.message());
      return 2;
    }
  }

  // The subject, noise-free: the noise is the images'.
  sim::SimulationOptions sim_options;
  sim_options.seed = a.seed;
  sim_options.noise_mm = 0;
  sim_options.rate_hz = a.rate_hz;
  sim::SimulatedSession session;
  if (Status s = sim::SimulateSession(sim_options, &session); !s) {
    spdlog::error("mocap capture: {}", s.message());
    return 2;
  }
  std::shared_ptr<const sim::Scene> scene = sim::MakeSessionScene(session);
  sim::RendererOptions render_options;
  render_options.frame_rate_hz = a.rate_hz;
  render_options.seed = a.seed;
  render_options.centroid_noise_px = a.centroid_noise_px;
  // Scene time 0 (the protocol's static pose) is the tick at which the capture starts.
  render_options.sequence_origin = drivers::SequenceOfTimestamp(
      static_cast<std::uint64_t>(std::chrono::duration_cast<std::chrono::nanoseconds>(
                                     std::chrono::system_clock::now().time_since_epoch())
                                     .count()),
      a.rate_hz);
  sim::Renderer renderer(true_rig, scene, render_options);
  if (!renderer.status()) {
    spdlog::error("mocap capture: {}", renderer.status().message());
    return 2;
  }

  drivers::FakeRigOptions fake_options;
  fake_options.cameras = a.cameras;
  fake_options.width = a.width;
  fake_options.height = a.height;
  fake_options.clock_sequence_rate_hz = a.rate_hz;
  drivers::AravisFakeRig fakes(fake_options, renderer.Generator());
  drivers::CameraSettings settings;
  settings.frame_rate_hz = a.rate_hz;
  settings.exposure_us = std::min(500.0, 0.5e6 / a.rate_hz);
  settings.pixel_format = drivers::PixelFormat::kMono8;
  settings.buffer_count = 32;
  std::vector<std::unique_ptr<drivers::CameraSource>> sources;
  for (int c = 0; c < a.cameras; ++c) {
    std::unique_ptr<drivers::AravisCamera> cam = fakes.MakeCamera(c);
    if (Status s = cam->Open(settings); !s) {
      spdlog::error("mocap capture: camera {}: {}", cam->id(), s.message());
      return 1;
    }
    sources.push_back(std::move(cam));
  }

  std::unique_ptr<reconstruction::Triangulator> triangulator;
  if (Status s = reconstruction::Triangulator::Create(rig, {}, &triangulator); !s) {
    spdlog::error("mocap capture: {}", s.message());
    return 2;
  }
  auto workspace = std::make_shared<reconstruction::TriangulationWorkspace>();
  auto points_buffer = std::make_shared<std::vector<reconstruction::TriangulatedPoint>>();
  daemon::TriangulateFn triangulate = [&triangulator, workspace, points_buffer](
                                          const reconstruction::DetectionSet& set,
                                          daemon::PointFrame* out) {
    MOCAP_RETURN_IF_ERROR(triangulator->Triangulate(set, workspace.get(), points_buffer.get()));
    out->points.clear();
    out->residual_px.clear();
    out->camera_count.clear();
    for (const auto& p : *points_buffer) {
      out->points.push_back(p.position);
      out->residual_px.push_back(static_cast<float>(p.residual_px));
      out->camera_count.push_back(static_cast<std::uint8_t>(p.camera_count));
    }
    return Status::Ok();
  };

  daemon::CapturePipelineOptions pipeline_options;
  pipeline_options.detection_threads = a.threads;
  pipeline_options.keep_detections = true;  // to score the centroids against the truth
  // The fakes share the host clock and expose on its frame ticks, but each counts frames from its
  // own start: sets are gathered by tick (a PTP-synchronised rig).
  pipeline_options.rig_sync = daemon::CapturePipelineOptions::RigSync::kSharedClock;
  pipeline_options.rate_hz = a.rate_hz;
  // The renderer's dark level is 3 % of full scale and a marker peaks near 90 %.
  pipeline_options.detection.threshold = 60;
  // Each centroid's uncertainty floor is the 2D error the rig actually has beyond the pixel
  // noise the detector models (on a real rig: the calibration's reprojection RMS); here the
  // renderer's jitter. Without it triangulation weighs cameras by blob size alone.
  pipeline_options.detection.sigma_floor_px = std::max(0.01, a.centroid_noise_px);
  daemon::CapturePipeline pipeline(std::move(sources), triangulate, pipeline_options);
  std::printf("mocap capture: %d simulated Aravis cameras %dx%d at %g Hz, subject seed %llu, "
              "%g s\n",
              a.cameras, a.width, a.height, a.rate_hz, static_cast<unsigned long long>(a.seed),
              a.seconds);
  std::fflush(stdout);
  if (Status s = pipeline.Start(); !s) {
    spdlog::error("mocap capture: {}", s.message());
    return 1;
  }

  const auto start = std::chrono::steady_clock::now();
  const std::size_t wanted = static_cast<std::size_t>(std::llround(a.seconds * a.rate_hz));
  std::vector<daemon::PointFrame> frames;
  frames.reserve(wanted + 16);
  double next_report = 1.0;
  for (;;) {
    const double elapsed =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    if (frames.size() >= wanted || elapsed > a.seconds + 10.0) break;
    daemon::PointFrame pf;
    if (pipeline.PopPoints(&pf, 50)) frames.push_back(std::move(pf));
    if (elapsed >= next_report) {
      const daemon::CapturePipelineStats st = pipeline.Stats();
      std::printf("  %5.1f s: %zu frame sets, %llu dropped, %llu incomplete, latency p99 %.2f ms\n",
                  elapsed, frames.size(), static_cast<unsigned long long>(st.dropped_frame_sets),
                  static_cast<unsigned long long>(st.incomplete_sets), st.latency_ms_p99);
      std::fflush(stdout);
      next_report += 1.0;
    }
  }
  pipeline.Stop();
  // What was still queued when the cameras stopped.
  for (daemon::PointFrame pf; pipeline.PopPoints(&pf, 0);) frames.push_back(std::move(pf));
  const double wall_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  const daemon::CapturePipelineStats st = pipeline.Stats();

  // Score against the truth: the scene at the time each camera drew its image.
  sim::ReconstructionScore score;
  sim::CentroidScore centroid_score;
  std::vector<Eigen::Vector2d> pixels;
  for (daemon::PointFrame& pf : frames) {
    sim::ScoreRenderedFrame(renderer, *scene, pf.sequence, pf.present_mask, pf.points,
                            kMatchRadiusM, &score);
    for (const reconstruction::CameraDetections& d : pf.detections) {
      if (d.camera < 0 || !(pf.present_mask >> d.camera & 1)) continue;
      pixels.clear();
      for (const auto& c : d.centroids) pixels.push_back(c.pixel);
      sim::ScoreCentroids(renderer, d.camera, pf.sequence, pixels, 1.0, &centroid_score);
    }
    pf.detections.clear();
    pf.detections.shrink_to_fit();
  }

  const fs::path dir(a.out);
  const std::string points_path = (dir / "points.c3d").string();
  if (!frames.empty()) {
    if (Status s = formats::WriteC3d(points_path, PointsTrial(frames, a.rate_hz)); !s) {
      spdlog::error("mocap capture: {}", s.message());
      return 1;
    }
  }
  // The simulated cameras run in this process: a tick they skipped while it was descheduled
  // (undelivered) is this run falling behind real time as much as a set it dropped.
  const bool real_time = st.dropped_frame_sets == 0 && st.undelivered_frame_sets == 0 && frames.size() >= wanted &&
                         st.frames_dropped == 0 && st.detections_dropped == 0;
  nlohmann::json j;
  j["cameras"] = a.cameras;
  j["width"] = a.width;
  j["height"] = a.height;
  j["rate_hz"] = a.rate_hz;
  j["seconds"] = a.seconds;
  j["seed"] = a.seed;
  j["calibration"] = a.calibration.empty() ? "true rig" : a.calibration;
  j["wall_seconds"] = wall_s;
  j["frame_sets"] = frames.size();
  j["dropped_frame_sets"] = st.dropped_frame_sets;
  j["undelivered_frame_sets"] = st.undelivered_frame_sets;
  j["incomplete_sets"] = st.incomplete_sets;
  j["frames_grabbed"] = st.frames_grabbed;
  j["frames_incomplete"] = st.frames_incomplete;
  j["frames_dropped"] = st.frames_dropped;
  j["detections_dropped"] = st.detections_dropped;
  j["detection_errors"] = st.detection_errors;
  j["sync_errors"] = st.sync_errors;
  j["triangulation_errors"] = st.triangulation_errors;
  j["late_frames"] = st.late_frames;
  j["warmup_sets"] = st.warmup_sets;
  j["warmup_ms"] = st.warmup_ms;
  j["cameras_missing_at_start"] = st.cameras_missing_at_start;
  j["camera_losses"] = st.camera_losses;
  j["real_time"] = real_time;
  j["centroid_noise_px"] = a.centroid_noise_px;
  j["centroid_error_px_rms"] = centroid_score.rms_px_per_axis();
  j["recall"] = score.recall();
  j["rms_3d_mm"] = score.rms_mm();
  // No unbiased triangulation of the same views at the renderer's centroid noise does better.
  j["rms_3d_cramer_rao_mm"] = score.rms_bound_mm();
  j["ghost_fraction"] = score.ghost_fraction();
  j["points_beyond_1mm"] = score.matched_beyond_1mm;
  j["true_markers_seen_by_two"] = score.true_visible;
  j["points"] = score.reconstructed;
  j["detect_ms_p50"] = st.detect_ms_p50;
  j["detect_ms_p99"] = st.detect_ms_p99;
  j["triangulate_ms_p50"] = st.triangulate_ms_p50;
  j["triangulate_ms_p99"] = st.triangulate_ms_p99;
  j["latency_ms_p50"] = st.latency_ms_p50;
  j["latency_ms_p99"] = st.latency_ms_p99;
  j["points_file"] = frames.empty() ? "" : "points.c3d";
  const std::string stats_path = (dir / "stats.json").string();
  std::ofstream f(stats_path);
  f << j.dump(2) << "\n";
  if (!f) {
    spdlog::error("mocap capture: cannot write '{}'", stats_path);
    return 1;
  }
  std::printf("mocap capture: %zu frame sets (%llu dropped, %llu incomplete) in %.1f s; recall "
              "%.4f, 3D RMS %.3f mm, ghosts %.4f; detect p50 %.3f ms, triangulate p50 %.3f ms, "
              "latency p99 %.2f ms%s -> %s\n",
              frames.size(), static_cast<unsigned long long>(st.dropped_frame_sets),
              static_cast<unsigned long long>(st.incomplete_sets), wall_s, score.recall(),
              score.rms_mm(), score.ghost_fraction(), st.detect_ms_p50, st.triangulate_ms_p50,
              st.latency_ms_p99, real_time ? "" : " (NOT real time)", a.out.c_str());
  std::printf("mocap capture: the rig was live %.0f ms after its first frame set (%llu warm-up "
              "sets before the recording)\n",
              st.warmup_ms, static_cast<unsigned long long>(st.warmup_sets));
  if (!st.cameras_missing_at_start.empty()) {
    std::string ids;
    for (int c : st.cameras_missing_at_start) ids += (ids.empty() ? "" : ", ") + std::to_string(c);
    spdlog::warn("mocap capture: camera(s) {} delivered nothing in the first {} ms; the recording "
                 "started without them",
                 ids, pipeline_options.start_timeout_ms);
  }
  if (!real_time) {
    spdlog::warn("mocap capture: the pipeline did not keep up: {} frame sets dropped, {} frames "
                 "dropped before detection (see {})",
                 st.dropped_frame_sets, st.frames_dropped, stats_path);
  }
  return 0;
}

void SetupCapture(CLI::App& app, int* exit_code) {
  auto args = std::make_shared<CaptureArgs>();
  CLI::App* cmd = app.add_subcommand(
      "capture", "Capture unlabelled 3D points (simulated cameras through the Aravis API)");
  cmd->add_flag("--simulate", args->simulate,
                "Simulated subject and cameras (Aravis fake devices)");
  cmd->add_option("--cameras", args->cameras, "Number of cameras")->capture_default_str();
  cmd->add_option("--seconds", args->seconds, "Length of the capture (s)")->capture_default_str();
  cmd->add_option("--rate", args->rate_hz, "Frame rate (Hz)")->capture_default_str();
  cmd->add_option("--seed", args->seed, "Subject and rig seed (as mocap sim --seed)")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  cmd->add_option("--width", args->width, "Image width (px)")->capture_default_str();
  cmd->add_option("--height", args->height, "Image height (px)")->capture_default_str();
  cmd->add_option("--threads", args->threads, "Detection threads")->capture_default_str();
  cmd->add_option("--centroid-noise-px", args->centroid_noise_px,
                  "Centroid jitter the renderer adds (px per axis), on top of the detector's own")
      ->capture_default_str();
  cmd->add_option("--calibration", args->calibration,
                  "Calibration file (mocap calibrate) to triangulate with, instead of the true rig");
  cmd->add_option("--out", args->out, "Output directory: points.c3d, stats.json")->required();
  cmd->callback([args, exit_code] { *exit_code = RunCapture(*args); });
}

const mocap::tools::CommandRegistrar kCaptureRegistrar("capture", SetupCapture);

}  // namespace
