// `mocap calibrate`: camera extrinsics by wand waving (reconstruction/calibration.h).
//
//   mocap calibrate --simulate [--cameras N] [--seed N] --out CAL.json
//       simulates an operator waving the wand through the true rig (sim/camera_rig.h,
//       sim/wand.h) and laying the L-frame, calibrates, and compares with the truth.
//   mocap calibrate --observations OBS.json --intrinsics CAMS.json... --out CAL.json [--truth
//   T.json]
//       calibrates from recorded 2D centroids (--save-observations writes that file from a
//       simulation; --save-truth writes the true rig as a calibration file).
//   mocap calibrate --checkerboard IMAGE... --camera-id ID [--board 9x6] [--square-mm 30]
//       --out CAM.json
//       one camera's intrinsics from checkerboard images (reconstruction/calibration_intrinsics.h),
//       written as a one-camera calibration file (pose: identity) for --intrinsics.
//
// Prints the reprojection RMS, the wand-length error and, where the truth is known, every
// camera's position (mm) and orientation (deg) error — in the lab frame the L-frame defines, no
// alignment; without an L-frame, both rigs expressed in their camera 0's frame — and writes them
// into the calibration file.
#include <spdlog/spdlog.h>

#include <cmath>
#include <cstdio>
#include <memory>

#include "reconstruction/calibration.h"
#include "reconstruction/calibration_file.h"
#include "reconstruction/calibration_intrinsics.h"
#include "sim/camera_rig.h"
#include "sim/random.h"
#include "sim/wand.h"
#include "tools/command.h"

namespace {

namespace rc = mocap::reconstruction;

struct CalibrateArgs {
  bool simulate = false;
  int cameras = 8;
  std::uint64_t seed = 1;
  std::string out;
  std::string observations, truth, save_observations, save_truth;
  std::vector<std::string> intrinsics;
  std::vector<std::string> checkerboard;
  std::string camera_id = "camera";
  std::string board = "9x6";
  double square_mm = 30.0;
  double noise_px = 0.1;
  double duration_s = 30.0;
  int strays = 2;
  bool no_lframe = false;
  bool refine_intrinsics = false;
  double intrinsics_error = 0.0;  // simulation: relative error of the starting focal lengths
  int threads = 1;
  bool quiet = false;
};

// Both rigs in the frame of their camera 0 (when no L-frame fixed the lab frame).
std::vector<rc::CameraModel> InCameraZeroFrame(std::vector<rc::CameraModel> rig) {
  const Eigen::Matrix3d r0 = rig[0].R;
  const Eigen::Vector3d t0 = rig[0].t;
  // X_0 = R0 X + t0  =>  X = R0^T (X_0 - t0);  X_c = R R0^T X_0 + (t - R R0^T t0).
  for (rc::CameraModel& c : rig) {
    const Eigen::Matrix3d r = c.R * r0.transpose();
    c.t = c.t - r * t0;
    c.R = r;
  }
  return rig;
}

int RunCheckerboard(const CalibrateArgs& args) {
  rc::CheckerboardOptions options;
  char x = 0;
  if (std::sscanf(args.board.c_str(), "%d%c%d", &options.inner_corners_x, &x,
                  &options.inner_corners_y) != 3 ||
      x != 'x') {
    spdlog::error("mocap calibrate: --board {}: expected inner corners as COLSxROWS, e.g. 9x6",
                  args.board);
    return 2;
  }
  options.square_m = args.square_mm / 1000.0;
  std::string error;
  if (!options.IsValid(&error)) {
    spdlog::error("mocap calibrate: {}", error);
    return 2;
  }
  rc::CalibratedCamera cc;
  cc.camera.id = args.camera_id;
  rc::IntrinsicsSummary summary;
  if (mocap::Status s = rc::CalibrateIntrinsicsFromFiles(args.checkerboard, options,
                                                         &cc.camera.intrinsics, &summary);
      !s) {
    spdlog::error("mocap calibrate: {}", s.message());
    return 1;
  }
  for (int i : summary.rejected)
    spdlog::warn("{}: no {} board found; image left out", args.checkerboard[i], args.board);
  const rc::CameraIntrinsics& k = cc.camera.intrinsics;
  std::printf("%s\nfx %.3f fy %.3f cx %.3f cy %.3f k1 %.6f k2 %.6f p1 %.6f p2 %.6f k3 %.6f\n",
              summary.BriefReport().c_str(), k.fx, k.fy, k.cx, k.cy, k.k1, k.k2, k.p1, k.p2, k.k3);
  cc.reprojection_rms_px = summary.rms_px;
  rc::CalibrationFile file;
  file.lab_frame = "none (intrinsics only)";
  file.cameras.push_back(cc);
  if (mocap::Status s = rc::WriteCalibrationJson(args.out, file); !s) {
    spdlog::error("mocap calibrate: {}", s.message());
    return 1;
  }
  spdlog::info("wrote {}", args.out);
  return 0;
}

int RunCalibrate(const CalibrateArgs& args) {
  if (!args.checkerboard.empty()) {
    if (args.simulate || !args.observations.empty()) {
      spdlog::error(
          "mocap calibrate: --checkerboard calibrates intrinsics alone; it does not "
          "combine with --simulate or --observations");
      return 2;
    }
    return RunCheckerboard(args);
  }
  if (args.simulate == !args.observations.empty()) {
    spdlog::error(
        "mocap calibrate: give one of --simulate, --observations OBS.json or "
        "--checkerboard IMAGE...");
    return 2;
  }
  std::vector<rc::CameraModel> start, truth;
  rc::WandCalibrationOptions options;
  options.refine_intrinsics = args.refine_intrinsics;
  options.num_threads = args.threads;
  std::vector<rc::DetectionSet> wand_frames, lframe_frames;

  if (args.simulate) {
    mocap::sim::CameraRigOptions rig;
    rig.cameras = args.cameras;
    rig.seed = args.seed;
    std::string error;
    if (!rig.IsValid(&error)) {
      spdlog::error("mocap calibrate: --cameras: {}", error);
      return 2;
    }
    truth = mocap::sim::MakeCameraRig(rig);
    mocap::sim::WandSimulationOptions so;
    so.seed = args.seed;
    so.noise_px = args.noise_px;
    so.duration_s = args.duration_s;
    so.max_strays = args.strays;
    so.lframe_frames = args.no_lframe ? 0 : so.lframe_frames;
    mocap::sim::WandSimulation simulation;
    if (mocap::Status s = mocap::sim::SimulateWand(truth, so, &simulation); !s) {
      spdlog::error("mocap calibrate: {}", s.message());
      return 2;
    }
    wand_frames = std::move(simulation.wand_frames);
    lframe_frames = std::move(simulation.lframe_frames);
    // The calibration starts from the intrinsics (as a checkerboard gave them), not the poses.
    start = truth;
    mocap::sim::Random rng(args.seed, mocap::sim::Stream::kWand, 100);
    for (rc::CameraModel& c : start) {
      c.R.setIdentity();
      c.t.setZero();
      if (args.intrinsics_error > 0) {
        c.intrinsics.fx *= 1 + args.intrinsics_error * rng.Normal();
        c.intrinsics.fy *= 1 + args.intrinsics_error * rng.Normal();
      }
    }
    spdlog::info(
        "simulated {} cameras (seed {}), {} wand frames over {:.0f} s, {} L-frame frames, "
        "noise {} px",
        truth.size(), args.seed, wand_frames.size(), args.duration_s, lframe_frames.size(),
        args.noise_px);
    if (!args.save_observations.empty()) {
      rc::WandObservations obs;
      for (const rc::CameraModel& c : truth) obs.camera_ids.push_back(c.id);
      obs.wand = options.wand;
      obs.lframe = so.lframe;
      obs.wand_frames = wand_frames;
      obs.lframe_frames = lframe_frames;
      if (mocap::Status s = rc::WriteWandObservationsJson(args.save_observations, obs); !s) {
        spdlog::error("mocap calibrate: {}", s.message());
        return 1;
      }
      spdlog::info("wrote the 2D observations to {}", args.save_observations);
    }
    if (!args.save_truth.empty()) {
      rc::CalibrationFile tf;
      tf.lab_frame = "L-frame";
      for (const rc::CameraModel& c : truth) tf.cameras.push_back({c});
      if (mocap::Status s = rc::WriteCalibrationJson(args.save_truth, tf); !s) {
        spdlog::error("mocap calibrate: {}", s.message());
        return 1;
      }
      spdlog::info("wrote the true rig to {}", args.save_truth);
    }
  } else {
    rc::WandObservations obs;
    if (mocap::Status s = rc::ReadWandObservationsJson(args.observations, &obs); !s) {
      spdlog::error("mocap calibrate: {}", s.message());
      return 2;
    }
    if (args.intrinsics.empty()) {
      spdlog::error(
          "mocap calibrate: --observations needs --intrinsics CAMS.json... (calibration "
          "files whose intrinsics start the calibration)");
      return 2;
    }
    // The cameras of every --intrinsics file, together (one file per camera, as --checkerboard
    // writes them, or one for the rig).
    rc::CalibrationFile intr;
    mocap::Status s;
    for (const std::string& path : args.intrinsics) {
      rc::CalibrationFile one;
      if (s = rc::ReadCalibrationJson(path, &one); !s) break;
      for (const rc::CalibratedCamera& c : one.cameras) {
        for (const rc::CalibratedCamera& d : intr.cameras)
          if (d.camera.id == c.camera.id)
            s = mocap::Status::Error(path + ": camera '" + c.camera.id +
                                     "' is also in an earlier --intrinsics file");
        intr.cameras.push_back(c);
      }
      if (!s) break;
    }
    if (s) s = rc::MatchCalibrationToRig(intr, obs.camera_ids, &start);
    if (!s) {
      spdlog::error("mocap calibrate: --intrinsics: {}", s.message());
      return 2;
    }
    if (!args.truth.empty()) {
      rc::CalibrationFile tf;
      s = rc::ReadCalibrationJson(args.truth, &tf);
      if (s) s = rc::MatchCalibrationToRig(tf, obs.camera_ids, &truth);
      if (!s) {
        spdlog::error("mocap calibrate: --truth {}: {}", args.truth, s.message());
        return 2;
      }
    }
    options.wand = obs.wand;
    options.lframe = obs.lframe;
    wand_frames = std::move(obs.wand_frames);
    if (!args.no_lframe) lframe_frames = std::move(obs.lframe_frames);
    spdlog::info("{}: {} cameras, {} wand frames, {} L-frame frames", args.observations,
                 start.size(), wand_frames.size(), lframe_frames.size());
  }

  if (!args.quiet)
    options.lm.callbacks.push_back([](const mocap::solver::IterationSummary& it) {
      spdlog::info("bundle adjustment iteration {:3d}  cost {:.6e}  |step| {:.3e}  lambda {:.1e}{}",
                   it.iteration, it.cost, it.step_norm, it.lambda,
                   it.step_accepted ? "" : "  (rejected)");
      return true;
    });
  std::vector<rc::CameraModel> calibrated;
  rc::WandCalibrationSummary summary;
  if (mocap::Status s =
          rc::CalibrateWand(start, wand_frames, lframe_frames, options, &calibrated, &summary);
      !s) {
    spdlog::error("mocap calibrate: {}", s.message());
    return 1;
  }
  std::printf("%s", summary.FullReport().c_str());

  rc::CalibrationFile file = rc::CalibrationFileOf(calibrated, summary, options.wand);
  std::printf("reprojection_rms_px %.4f\nwand_length_error_mm_rms %.4f\n",
              summary.reprojection_rms_px, summary.wand_length_error_mm_rms);
  if (!truth.empty()) {
    const bool lab = summary.lab_frame_from_lframe;
    const std::vector<rc::CameraModel> t = lab ? truth : InCameraZeroFrame(truth);
    const std::vector<rc::CameraModel> e = lab ? calibrated : InCameraZeroFrame(calibrated);
    std::printf("camera pose errors against the truth (%s):\n",
                lab ? "lab frame of the L-frame, no alignment" : "both rigs in camera 0's frame");
    double worst_p = 0, worst_a = 0, ss_p = 0;
    for (size_t c = 0; c < e.size(); ++c) {
      double p, a;
      rc::CameraPoseError(e[c], t[c], &p, &a);
      file.cameras[c].position_error_mm = 1000 * p;
      file.cameras[c].orientation_error_deg = a * 180 / M_PI;
      std::printf("  %-12s position_error_mm %.3f  orientation_error_deg %.4f", e[c].id.c_str(),
                  1000 * p, a * 180 / M_PI);
      if (args.refine_intrinsics) {
        const rc::CameraIntrinsics &ke = e[c].intrinsics, &kt = t[c].intrinsics;
        std::printf("  fx_error_px %+.3f  fy_error_px %+.3f  cx_error_px %+.3f  cy_error_px %+.3f",
                    ke.fx - kt.fx, ke.fy - kt.fy, ke.cx - kt.cx, ke.cy - kt.cy);
      }
      std::printf("\n");
      worst_p = std::max(worst_p, 1000 * p);
      worst_a = std::max(worst_a, a * 180 / M_PI);
      ss_p += 1e6 * p * p;
    }
    std::printf(
        "position_error_mm_max %.3f\nposition_error_mm_rms %.3f\norientation_error_deg_max "
        "%.4f\n",
        worst_p, std::sqrt(ss_p / e.size()), worst_a);
  }
  if (mocap::Status s = rc::WriteCalibrationJson(args.out, file); !s) {
    spdlog::error("mocap calibrate: {}", s.message());
    return 1;
  }
  spdlog::info("wrote {}", args.out);
  return 0;
}

void SetupCalibrate(CLI::App& app, int* exit_code) {
  auto args = std::make_shared<CalibrateArgs>();
  CLI::App* cmd = app.add_subcommand(
      "calibrate",
      "Calibrate the camera rig by wand waving (simulated or from recorded centroids)");
  cmd->add_option("--out", args->out, "Calibration file to write (JSON)")->required();
  cmd->add_flag("--simulate", args->simulate,
                "Simulate the wand waving through a simulated rig and compare with its truth");
  cmd->add_option("--cameras", args->cameras, "Simulated cameras")
      ->check(CLI::Range(2, 64))
      ->capture_default_str();
  cmd->add_option("--seed", args->seed, "Random seed (rig and wand path)")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  cmd->add_option("--noise-px", args->noise_px, "Simulated centroid noise per axis (px)")
      ->check(CLI::Range(0.0, 5.0))
      ->capture_default_str();
  cmd->add_option("--duration", args->duration_s, "Simulated waving time (s)")
      ->check(CLI::Range(1.0, 600.0))
      ->capture_default_str();
  cmd->add_option("--strays", args->strays, "Simulated stray centroids per image, at most")
      ->check(CLI::Range(0, 50))
      ->capture_default_str();
  cmd->add_option("--intrinsics-error", args->intrinsics_error,
                  "Simulation: relative error (sigma) of the starting focal lengths; use with "
                  "--refine-intrinsics")
      ->check(CLI::Range(0.0, 0.05));
  cmd->add_option("--observations", args->observations,
                  "Calibrate from recorded 2D centroids (mocap-wand-observations JSON)");
  cmd->add_option("--intrinsics", args->intrinsics,
                  "Calibration files whose intrinsics start the calibration (with --observations)");
  cmd->add_option("--checkerboard", args->checkerboard,
                  "Checkerboard images of one camera: calibrate its intrinsics")
      ->check(CLI::ExistingFile);
  cmd->add_option("--camera-id", args->camera_id, "With --checkerboard: the camera's id")
      ->capture_default_str();
  cmd->add_option("--board", args->board, "With --checkerboard: inner corners, COLSxROWS")
      ->capture_default_str();
  cmd->add_option("--square-mm", args->square_mm, "With --checkerboard: square size (mm)")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  cmd->add_option("--truth", args->truth, "Calibration file to compare with (with --observations)");
  cmd->add_option("--save-observations", args->save_observations,
                  "Simulation: also write the 2D centroids (input of --observations)");
  cmd->add_option("--save-truth", args->save_truth,
                  "Simulation: also write the true rig as a calibration file");
  cmd->add_flag("--no-lframe", args->no_lframe, "Ignore the L-frame: the lab frame is camera 0's");
  cmd->add_flag("--refine-intrinsics", args->refine_intrinsics,
                "Also refine fx, fy, cx, cy, k1, k2 of every camera in the bundle adjustment");
  cmd->add_option("--threads", args->threads, "Threads of the bundle adjustment")
      ->check(CLI::Range(1, 256))
      ->capture_default_str();
  cmd->add_flag("--quiet", args->quiet, "No per-iteration progress");
  cmd->callback([args, exit_code] { *exit_code = RunCalibrate(*args); });
}

const mocap::tools::CommandRegistrar kCalibrateRegistrar("calibrate", SetupCalibrate);

}  // namespace
