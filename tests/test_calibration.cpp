// Camera calibration: the wand bundle adjustment's Jacobians, wand identification, the simulated
// 8-camera wand calibration against the true rig, the calibration file, checkerboard intrinsics.
#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>

#include "model/rigid_align.h"
#include "reconstruction/calibration.h"
#include "reconstruction/calibration_file.h"
#include "reconstruction/calibration_intrinsics.h"
#include "reconstruction/calibration_problem.h"
#include "sim/camera_rig.h"
#include "sim/random.h"
#include "sim/wand.h"
#include "solver/arrow_problem.h"
#include "tests/cpu_time_test_util.h"

namespace mocap::reconstruction {
namespace {

std::vector<CameraModel> TrueRig(int cameras = 8, std::uint64_t seed = 1) {
  sim::CameraRigOptions o;
  o.cameras = cameras;
  o.seed = seed;
  return sim::MakeCameraRig(o);
}

// Dense Jacobian of one frame's residuals (rows in block order) against [y_f, p].
void FrameJacobian(WandBundleProblem& problem, int f, const Eigen::VectorXd& x, bool analytic,
                   Eigen::MatrixXd* j, Eigen::VectorXd* r) {
  const int ny = 5, np = problem.shared_dim();
  auto eval = [&](const Eigen::VectorXd& xx, Eigen::VectorXd* res, Eigen::MatrixXd* jac) {
    EXPECT_TRUE(problem.SetShared(xx.tail(np)));
    auto ev = problem.NewEvaluator();
    EXPECT_TRUE(ev->Evaluate(f, xx.data() + ny * f, jac != nullptr));
    int rows = 0;
    for (int b = 0; b < ev->num_blocks(); ++b) rows += ev->block(b).rows;
    res->resize(rows);
    if (jac) jac->setZero(rows, ny + np);
    int row = 0;
    for (int b = 0; b < ev->num_blocks(); ++b) {
      const solver::ResidualBlock& blk = ev->block(b);
      for (int i = 0; i < blk.rows; ++i) {
        (*res)[row + i] = blk.residual[i];
        if (!jac) continue;
        for (int c = 0; c < blk.num_y; ++c)
          (*jac)(row + i, blk.y_index[c]) += blk.jy[c * solver::kMaxBlockRows + i];
        for (int c = 0; c < blk.num_p; ++c)
          if (blk.p_index[c] >= 0)
            (*jac)(row + i, ny + blk.p_index[c]) += blk.jp[c * solver::kMaxBlockRows + i];
      }
      row += blk.rows;
    }
  };
  if (analytic) {
    eval(x, r, j);
    return;
  }
  Eigen::VectorXd r0;
  eval(x, &r0, nullptr);
  *r = r0;
  j->setZero(r0.size(), ny + np);
  for (int c = 0; c < ny + np; ++c) {
    const int xi = c < ny ? ny * f + c : static_cast<int>(x.size()) - np + (c - ny);
    const double h = 1e-6 * std::max(1.0, std::abs(x[xi]));
    Eigen::VectorXd xp = x, xm = x, rp, rm;
    xp[xi] += h;
    xm[xi] -= h;
    eval(xp, &rp, nullptr);
    eval(xm, &rm, nullptr);
    j->col(c) = (rp - rm) / (2 * h);
  }
}

TEST(WandBundle, JacobiansMatchFiniteDifferences) {
  const std::vector<CameraModel> rig = TrueRig(4);
  sim::WandSimulationOptions so;
  so.duration_s = 6;
  so.subsample = 50;
  so.max_strays = 0;
  so.lframe_frames = 0;
  sim::WandSimulation simulation;
  ASSERT_TRUE(sim::SimulateWand(rig, so, &simulation).ok());
  const Wand wand;
  const std::vector<double> offsets = {-0.7 / 3, -0.1 / 3, 0.8 / 3};
  std::vector<WandFrame> frames;
  sim::Random rng(7);
  for (size_t f = 0; f < simulation.wand_frames.size(); ++f) {
    WandFrame fr;
    for (int c = 0; c < 4; ++c) {
      std::vector<Eigen::Vector2d> m;
      if (!IdentifyWand(simulation.wand_frames[f].cameras[c].centroids, wand, {}, &m)) continue;
      WandObservation o;
      o.camera = c;
      for (int k = 0; k < 3; ++k) o.pixels[k] = m[k];
      fr.observations.push_back(o);
    }
    if (fr.observations.size() < 2) continue;
    const auto& tm = simulation.wand_markers[f];
    fr.SetDirection(tm[2] - tm[0] +
                    0.05 * Eigen::Vector3d(rng.Normal(), rng.Normal(), rng.Normal()));
    fr.centre = (tm[0] + tm[1] + tm[2]) / 3.0;
    frames.push_back(fr);
  }
  ASSERT_GE(frames.size(), 2u);
  for (bool intrinsics : {false, true}) {
    WandBundleProblem problem(rig, frames, offsets, intrinsics, 0);
    Eigen::VectorXd x = problem.InitialState();
    // Away from the start: non-zero chart coordinates and rotation vectors.
    for (int i = 0; i < x.size() - problem.shared_dim(); ++i) x[i] += 0.01 * rng.Normal();
    for (int c = 1; c < 4; ++c)
      for (int j = 0; j < 3; ++j)
        x[x.size() - problem.shared_dim() + problem.shared_index(c, j)] += 0.05 * rng.Normal();
    for (int f = 0; f < problem.num_frames(); ++f) {
      Eigen::MatrixXd ja, jn;
      Eigen::VectorXd ra, rn;
      FrameJacobian(problem, f, x, true, &ja, &ra);
      FrameJacobian(problem, f, x, false, &jn, &rn);
      ASSERT_EQ(ja.rows(), jn.rows());
      EXPECT_LT((ra - rn).norm(), 1e-12);
      for (int c = 0; c < ja.cols(); ++c) {
        const double scale = std::max(1.0, jn.col(c).norm());
        EXPECT_LT((ja.col(c) - jn.col(c)).norm() / scale, 1e-5)
            << "frame " << f << " column " << c << (intrinsics ? " (intrinsics)" : "");
      }
    }
  }
}

TEST(WandBundle, LeftJacobianOfSO3) {
  sim::Random rng(3);
  for (int trial = 0; trial < 5; ++trial) {
    const Eigen::Vector3d w(rng.Normal(), rng.Normal(), rng.Normal());
    const Eigen::Vector3d v(rng.Normal(), rng.Normal(), rng.Normal());
    const Eigen::Matrix3d analytic = -Skew(ExpSO3(w) * v) * LeftJacobianSO3(w);
    for (int k = 0; k < 3; ++k) {
      const double h = 1e-6;
      const Eigen::Vector3d dw = h * Eigen::Vector3d::Unit(k);
      const Eigen::Vector3d numeric = (ExpSO3(w + dw) * v - ExpSO3(w - dw) * v) / (2 * h);
      EXPECT_LT((analytic.col(k) - numeric).norm(), 1e-8);
    }
  }
}

TEST(WandIdentification, FindsTheWandAmongStrays) {
  const Wand wand;
  std::vector<Centroid> c(6);
  const Eigen::Vector2d a(100, 200), dir = Eigen::Vector2d(3, 1).normalized();
  c[3].pixel = a;
  c[0].pixel = a + 0.4 * 300 * dir;
  c[5].pixel = a + 300 * dir;
  c[1].pixel = {700, 100};
  c[2].pixel = {50, 900};
  c[4].pixel = {640, 512};
  std::vector<Eigen::Vector2d> m;
  ASSERT_TRUE(IdentifyWand(c, wand, {}, &m));
  EXPECT_LT((m[0] - c[3].pixel).norm(), 1e-12);
  EXPECT_LT((m[1] - c[0].pixel).norm(), 1e-12);
  EXPECT_LT((m[2] - c[5].pixel).norm(), 1e-12);
  // Reversed spacing (middle at 0.6 from the first end) is the same wand seen the other way.
  c[0].pixel = a + 0.6 * 300 * dir;
  ASSERT_TRUE(IdentifyWand(c, wand, {}, &m));
  EXPECT_LT((m[0] - c[5].pixel).norm(), 1e-12);
  // Equal spacing is not the wand.
  c[0].pixel = a + 0.5 * 300 * dir;
  EXPECT_FALSE(IdentifyWand(c, wand, {}, &m));
  // Off the line by 5 px: not the wand.
  c[0].pixel = a + 0.4 * 300 * dir + Eigen::Vector2d(-dir.y(), dir.x()) * 5.0;
  EXPECT_FALSE(IdentifyWand(c, wand, {}, &m));
}

struct CalibrationRun {
  std::vector<CameraModel> truth, calibrated;
  WandCalibrationSummary summary;
  Status status;
  double cpu_seconds = 0;
};

const CalibrationRun& EightCameraRun() {
  static CalibrationRun run = [] {
    CalibrationRun r;
    r.truth = TrueRig(8);
    sim::WandSimulationOptions so;
    so.seed = 11;
    sim::WandSimulation simulation;
    r.status = sim::SimulateWand(r.truth, so, &simulation);
    if (!r.status.ok()) return r;
    // CPU time (every thread's): a wall-clock bound would measure the tests beside it.
    const double t0 = testutil::ProcessCpuSeconds();
    WandCalibrationOptions co;
    r.status = CalibrateWand(r.truth, simulation.wand_frames, simulation.lframe_frames, co,
                             &r.calibrated, &r.summary);
    r.cpu_seconds = testutil::ProcessCpuSeconds() - t0;
    return r;
  }();
  return run;
}

TEST(WandCalibration, EightSimulatedCamerasMeetTheTargets) {
  const CalibrationRun& run = EightCameraRun();
  ASSERT_TRUE(run.status.ok()) << run.status.message();
  std::printf("%s", run.summary.FullReport().c_str());
  double worst_pos = 0, worst_ang = 0;
  for (size_t c = 0; c < run.truth.size(); ++c) {
    double pos, ang;
    CameraPoseError(run.calibrated[c], run.truth[c], &pos, &ang);
    std::printf("camera %zu: position error %.3f mm, orientation error %.4f deg\n", c, 1000 * pos,
                ang * 180 / M_PI);
    worst_pos = std::max(worst_pos, pos);
    worst_ang = std::max(worst_ang, ang);
  }
  std::printf("calibration %.2f CPU s; worst position %.3f mm, orientation %.4f deg\n", run.cpu_seconds,
              1000 * worst_pos, worst_ang * 180 / M_PI);
  // The targets of the issue (0.1 px noise per axis gives an RMS error norm of 0.1 sqrt(2)).
  EXPECT_LE(run.summary.reprojection_rms_px, 0.15);
  EXPECT_GE(run.summary.reprojection_rms_px, 0.12);  // below: the residuals over-fit the noise
  EXPECT_LE(run.summary.wand_length_error_mm_rms, 0.3);
  EXPECT_LT(std::abs(run.summary.wand_length_error_mm_mean), 0.05);  // metric scale unbiased
  EXPECT_TRUE(run.summary.lab_frame_from_lframe);
  EXPECT_LT(run.summary.lframe_residual_mm_rms, 0.2);
  // Seeds 1-7 of `mocap calibrate --simulate` gave at most 0.85 mm and 0.011 deg.
  EXPECT_LT(1000 * worst_pos, 1.5);
  EXPECT_LT(worst_ang * 180 / M_PI, 0.02);
  EXPECT_EQ(run.summary.final_solve.termination, solver::TerminationType::kConvergence);
  EXPECT_GE(run.summary.wand_frames_used, 550);
  EXPECT_LT(run.cpu_seconds, 10.0);
}

// Mis-identified wands — the middle centroid 4% of the wand's image length off along the line,
// so the triple still passes as the wand, in 3% of the images — are found after the first
// solve, dropped, and the calibration is as good as without them.
TEST(WandCalibration, CorruptedObservationsAreRejected) {
  const std::vector<CameraModel> truth = TrueRig(8);
  sim::WandSimulationOptions so;
  so.seed = 12;
  so.duration_s = 20;
  so.max_strays = 0;  // each image holds the wand only
  sim::WandSimulation simulation;
  ASSERT_TRUE(sim::SimulateWand(truth, so, &simulation).ok());
  sim::Random rng(99);
  int corrupted = 0;
  for (DetectionSet& set : simulation.wand_frames)
    for (CameraDetections& cam : set.cameras) {
      if (cam.centroids.size() != 3 || rng.Uniform() >= 0.03) continue;
      // The ends are the farthest pair; the other centroid is the middle one.
      int mid = 0;
      double longest = 0;
      for (int i = 0; i < 3; ++i) {
        const double d =
            (cam.centroids[(i + 1) % 3].pixel - cam.centroids[(i + 2) % 3].pixel).norm();
        if (d > longest) longest = d, mid = i;
      }
      const Eigen::Vector2d line =
          cam.centroids[(mid + 2) % 3].pixel - cam.centroids[(mid + 1) % 3].pixel;
      cam.centroids[mid].pixel += (rng.Uniform() < 0.5 ? 0.04 : -0.04) * line;
      ++corrupted;
    }
  std::vector<CameraModel> out;
  WandCalibrationSummary summary;
  const Status s =
      CalibrateWand(truth, simulation.wand_frames, simulation.lframe_frames, {}, &out, &summary);
  ASSERT_TRUE(s.ok()) << s.message();
  std::printf("corrupted %d images; %s\n", corrupted, summary.BriefReport().c_str());
  std::printf("rejected %d observations\n", summary.rejected_observations);
  EXPECT_GT(corrupted, 50);
  // Some corrupted images lose the wand altogether (the shifted ratio leaves the tolerance);
  // those that pass as a wand must be caught: 71 of 97 here.
  EXPECT_GT(summary.rejected_observations, corrupted / 2);
  EXPECT_LE(summary.rejected_observations, corrupted);
  EXPECT_LE(summary.reprojection_rms_px, 0.15);
  EXPECT_LE(summary.wand_length_error_mm_rms, 0.35);
  for (size_t c = 0; c < truth.size(); ++c) {
    double pos, ang;
    CameraPoseError(out[c], truth[c], &pos, &ang);
    EXPECT_LT(1000 * pos, 1.5) << c;
    EXPECT_LT(ang * 180 / M_PI, 0.02) << c;
  }
}

// Starting focal lengths 1% wrong: with the intrinsics refined, the bundle adjustment recovers
// them; without, the poses absorb the error (tens of mm).
TEST(WandCalibration, RefinedIntrinsicsRecoverAWrongFocalLength) {
  const std::vector<CameraModel> truth = TrueRig(8);
  sim::WandSimulationOptions so;
  so.seed = 13;
  sim::WandSimulation simulation;
  ASSERT_TRUE(sim::SimulateWand(truth, so, &simulation).ok());
  std::vector<CameraModel> start = truth;
  sim::Random rng(21);
  for (CameraModel& c : start) {
    c.intrinsics.fx *= 1 + 0.01 * rng.Normal();
    c.intrinsics.fy *= 1 + 0.01 * rng.Normal();
  }
  for (bool refine : {false, true}) {
    WandCalibrationOptions co;
    co.refine_intrinsics = refine;
    std::vector<CameraModel> out;
    WandCalibrationSummary summary;
    const Status s =
        CalibrateWand(start, simulation.wand_frames, simulation.lframe_frames, co, &out, &summary);
    ASSERT_TRUE(s.ok()) << s.message();
    double worst_pos = 0, worst_f = 0, worst_c = 0;
    for (size_t c = 0; c < truth.size(); ++c) {
      double pos, ang;
      CameraPoseError(out[c], truth[c], &pos, &ang);
      worst_pos = std::max(worst_pos, pos);
      const CameraIntrinsics &e = out[c].intrinsics, &t = truth[c].intrinsics;
      worst_f = std::max({worst_f, std::abs(e.fx - t.fx), std::abs(e.fy - t.fy)});
      worst_c = std::max({worst_c, std::abs(e.cx - t.cx), std::abs(e.cy - t.cy)});
    }
    std::printf("refine %d: %s\n  worst position %.2f mm, focal %.2f px, principal point %.2f px\n",
                refine, summary.BriefReport().c_str(), 1000 * worst_pos, worst_f, worst_c);
    if (!refine) {
      EXPECT_GT(summary.reprojection_rms_px, 0.3);
      EXPECT_GT(1000 * worst_pos, 10.0);
    } else {
      EXPECT_LE(summary.reprojection_rms_px, 0.15);
      EXPECT_LE(summary.wand_length_error_mm_rms, 0.3);
      // This seed: 0.48 px, 0.92 px, 1.98 mm. `mocap calibrate --simulate --refine-intrinsics
      // --intrinsics-error 0.01`, seeds 1-5: focal <= 1.41 px, principal point <= 1.26 px,
      // position <= 5.6 mm (a focal error and a camera's distance trade against each other).
      EXPECT_LT(worst_f, 2.5);
      EXPECT_LT(worst_c, 2.5);
      EXPECT_LT(1000 * worst_pos, 8.0);
    }
  }
}

TEST(WandCalibration, ACameraThatSharesNoWandFramesIsNamed) {
  const std::vector<CameraModel> rig = TrueRig(4);
  sim::WandSimulationOptions so;
  so.duration_s = 5;
  so.lframe_frames = 0;
  sim::WandSimulation simulation;
  ASSERT_TRUE(sim::SimulateWand(rig, so, &simulation).ok());
  for (DetectionSet& set : simulation.wand_frames) set.cameras[2].centroids.clear();
  std::vector<CameraModel> out;
  WandCalibrationSummary summary;
  const Status s = CalibrateWand(rig, simulation.wand_frames, {}, {}, &out, &summary);
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.message().find("camera(s) 'sim-2' (at most 0 shared) share too few wand frames"),
            std::string::npos)
      << s.message();
}

TEST(WandCalibration, ACallbackCancelsIt) {
  const std::vector<CameraModel> rig = TrueRig(4);
  sim::WandSimulationOptions so;
  so.duration_s = 10;
  so.lframe_frames = 0;
  sim::WandSimulation simulation;
  ASSERT_TRUE(sim::SimulateWand(rig, so, &simulation).ok());
  WandCalibrationOptions co;
  int calls = 0;
  co.lm.callbacks.push_back([&](const solver::IterationSummary&) { return ++calls < 2; });
  std::vector<CameraModel> out;
  WandCalibrationSummary summary;
  const Status s = CalibrateWand(rig, simulation.wand_frames, {}, co, &out, &summary);
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(calls, 2);
  EXPECT_NE(s.message().find("cancelled"), std::string::npos) << s.message();
}

// An L-frame whose markers are not where the options say: refused, not silently misaligned.
TEST(WandCalibration, AnLFrameOfTheWrongLayoutIsAClearError) {
  const std::vector<CameraModel> rig = TrueRig(8);
  sim::WandSimulationOptions so;
  so.duration_s = 10;
  so.lframe.markers_m = {{0, 0, 0}, {0.25, 0, 0}, {0.6, 0, 0}, {0, 0.4, 0}};  // 0.25, not 0.2
  sim::WandSimulation simulation;
  ASSERT_TRUE(sim::SimulateWand(rig, so, &simulation).ok());
  std::vector<CameraModel> out;
  WandCalibrationSummary summary;
  const Status s =
      CalibrateWand(rig, simulation.wand_frames, simulation.lframe_frames, {}, &out, &summary);
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.message().find("L-frame: no 4 of the 4 reconstructed points match its marker layout"),
            std::string::npos)
      << s.message();
}

TEST(WandCalibration, DetectionSetsOfAnotherRigAreAClearError) {
  const std::vector<CameraModel> rig = TrueRig(4);
  sim::WandSimulationOptions so;
  so.duration_s = 2;
  so.lframe_frames = 0;
  sim::WandSimulation simulation;
  ASSERT_TRUE(sim::SimulateWand(rig, so, &simulation).ok());
  std::vector<CameraModel> three(rig.begin(), rig.begin() + 3), out;
  WandCalibrationSummary summary;
  const Status s = CalibrateWand(three, simulation.wand_frames, {}, {}, &out, &summary);
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.message().find("wand frame 0 has 4 camera entries, the rig has 3"), std::string::npos)
      << s.message();
}

TEST(WandCalibration, AWandNeverSeenByTwoCamerasIsAClearError) {
  const std::vector<CameraModel> rig = TrueRig(4);
  sim::WandSimulationOptions so;
  so.duration_s = 3;
  so.lframe_frames = 0;
  sim::WandSimulation simulation;
  ASSERT_TRUE(sim::SimulateWand(rig, so, &simulation).ok());
  // Keep each frame's detections in one camera only.
  for (size_t f = 0; f < simulation.wand_frames.size(); ++f)
    for (int c = 0; c < 4; ++c)
      if (c != static_cast<int>(f % 4)) simulation.wand_frames[f].cameras[c].centroids.clear();
  std::vector<CameraModel> out;
  WandCalibrationSummary summary;
  const Status s = CalibrateWand(rig, simulation.wand_frames, {}, {}, &out, &summary);
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.message().find("never seen by two cameras at once"), std::string::npos)
      << s.message();
}

// ---- The calibration file ----

int RunTool(const std::string& command) { return std::system(command.c_str()); }

std::string TmpPath(const std::string& name) {
  std::filesystem::create_directories(MOCAP_TEST_TMP);
  return std::string(MOCAP_TEST_TMP) + "/calibration_" + name;
}

TEST(CalibrationFile, RoundTripsExactly) {
  CalibrationFile file;
  for (const CameraModel& c : TrueRig(3)) {
    CalibratedCamera cc;
    cc.camera = c;
    cc.reprojection_rms_px = 0.125;
    cc.wand_frames = 500;
    file.cameras.push_back(cc);
  }
  file.lab_frame = "L-frame";
  file.reprojection_rms_px = 0.13;
  file.wand_length_error_mm_rms = 0.25;
  file.wand_markers_m = {0, 0.2, 0.5};
  const std::string path = TmpPath("roundtrip.json");
  ASSERT_TRUE(WriteCalibrationJson(path, file).ok());
  CalibrationFile back;
  const Status s = ReadCalibrationJson(path, &back);
  ASSERT_TRUE(s.ok()) << s.message();
  ASSERT_EQ(back.cameras.size(), 3u);
  for (int c = 0; c < 3; ++c) {
    const CameraModel &a = file.cameras[c].camera, &b = back.cameras[c].camera;
    EXPECT_EQ(a.id, b.id);
    EXPECT_EQ((a.R - b.R).norm(), 0.0);
    EXPECT_EQ((a.t - b.t).norm(), 0.0);
    EXPECT_EQ(a.intrinsics.fx, b.intrinsics.fx);
    EXPECT_EQ(a.intrinsics.k1, b.intrinsics.k1);
    EXPECT_EQ(a.intrinsics.width, b.intrinsics.width);
    EXPECT_EQ(back.cameras[c].wand_frames, 500);
  }
  EXPECT_EQ(back.lab_frame, "L-frame");
  EXPECT_EQ(back.wand_length_error_mm_rms, 0.25);
  EXPECT_TRUE(std::isnan(back.wand_length_error_mm_mean));
  std::vector<CameraModel> ordered;
  ASSERT_TRUE(MatchCalibrationToRig(back, {"sim-2", "sim-0", "sim-1"}, &ordered).ok());
  EXPECT_EQ(ordered[0].id, "sim-2");
  EXPECT_EQ(ordered[2].id, "sim-1");
}

// A valid one-camera document with one piece replaced.
std::string OneCamera(const std::string& replace_from = "", const std::string& replace_to = "") {
  std::string doc = R"({"format": "mocap-calibration", "version": 1, "cameras": [
    {"id": "cam-A", "width": 1280, "height": 1024, "fx": 1000, "fy": 1000, "cx": 640, "cy": 512,
     "k1": -0.05, "k2": 0.01, "p1": 0, "p2": 0, "k3": 0,
     "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "t": [0, 0, 4]}]})";
  if (!replace_from.empty()) {
    const size_t at = doc.find(replace_from);
    EXPECT_NE(at, std::string::npos) << replace_from;
    doc.replace(at, replace_from.size(), replace_to);
  }
  return doc;
}

void ExpectError(const std::string& doc, const std::string& expected) {
  CalibrationFile f;
  const Status s = ParseCalibrationJson(doc, "cal.json", &f);
  ASSERT_FALSE(s.ok()) << "accepted a document that should fail with: " << expected;
  EXPECT_NE(s.message().find(expected), std::string::npos) << s.message();
  EXPECT_EQ(s.message().rfind("cal.json: ", 0), 0u) << s.message();
}

TEST(CalibrationFile, BadFilesGetClearErrors) {
  CalibrationFile f;
  ASSERT_TRUE(ParseCalibrationJson(OneCamera(), "cal.json", &f).ok());
  ExpectError("{\"format\": \"mocap-calibration\", ", "not valid JSON");
  ExpectError("[1, 2]", "expected a JSON object");
  ExpectError(OneCamera("mocap-calibration", "mocap-model"),
              "format: expected \"mocap-calibration\"");
  ExpectError(OneCamera("\"version\": 1", "\"version\": 7"), "version: unsupported");
  ExpectError(OneCamera("\"fx\": 1000", "\"fx\": \"big\""), "cameras[0].fx: expected a number");
  ExpectError(OneCamera("\"fy\": 1000", "\"fy\": -3"), "cameras[0]: fx and fy must be positive");
  ExpectError(OneCamera("\"width\": 1280", "\"width\": 12.5"), "cameras[0]: width and height");
  ExpectError(OneCamera("\"cy\": 512,", ""), "cameras[0].cy: missing");
  ExpectError(OneCamera("[0, 1, 0]", "[0, 2, 0]"), "cameras[0].R: not a rotation matrix");
  ExpectError(OneCamera("[0, 0, 1]]", "[0, 0, -1]]"), "cameras[0].R: not a rotation matrix");
  ExpectError(OneCamera("[0, 1, 0]", "[0, 1]"), "cameras[0].R: expected 3 rows of 3 numbers");
  ExpectError(OneCamera("\"t\": [0, 0, 4]", "\"t\": [0, 4]"), "cameras[0].t: expected 3 numbers");
  ExpectError(OneCamera("\"cameras\": [", "\"cameras\": [], \"x\": ["), "cameras: no cameras");
  // A second camera with the same id.
  std::string two = OneCamera();
  const size_t open = two.find("{\"id\"");
  const size_t close = two.rfind("]}");
  two.insert(close, ", " + two.substr(open, close - open));
  ExpectError(two, "cameras[1].id: duplicate camera id 'cam-A'");
  // A file that does not exist.
  const Status missing = ReadCalibrationJson(TmpPath("does_not_exist.json"), &f);
  ASSERT_FALSE(missing.ok());
  EXPECT_NE(missing.message().find("cannot open"), std::string::npos);
}

TEST(CalibrationFile, WandObservationsRoundTripAndBadOnesAreNamed) {
  const std::vector<CameraModel> rig = TrueRig(3);
  sim::WandSimulationOptions so;
  so.duration_s = 1;
  so.lframe_frames = 2;
  so.dropout = 0.3;
  sim::WandSimulation simulation;
  ASSERT_TRUE(sim::SimulateWand(rig, so, &simulation).ok());
  WandObservations obs;
  obs.camera_ids = {"a", "b", "c"};
  obs.wand_frames = simulation.wand_frames;
  obs.lframe_frames = simulation.lframe_frames;
  const std::string path = TmpPath("obs.json");
  ASSERT_TRUE(WriteWandObservationsJson(path, obs).ok());
  WandObservations back;
  const Status s = ReadWandObservationsJson(path, &back);
  ASSERT_TRUE(s.ok()) << s.message();
  ASSERT_EQ(back.wand_frames.size(), obs.wand_frames.size());
  ASSERT_EQ(back.lframe_frames.size(), 2u);
  int absent = 0;
  for (size_t f = 0; f < obs.wand_frames.size(); ++f)
    for (int c = 0; c < 3; ++c) {
      EXPECT_EQ(back.wand_frames[f].present[c], obs.wand_frames[f].present[c]);
      absent += !obs.wand_frames[f].present[c];
      ASSERT_EQ(back.wand_frames[f].cameras[c].centroids.size(),
                obs.wand_frames[f].cameras[c].centroids.size());
      for (size_t i = 0; i < obs.wand_frames[f].cameras[c].centroids.size(); ++i)
        EXPECT_EQ(back.wand_frames[f].cameras[c].centroids[i].pixel,
                  obs.wand_frames[f].cameras[c].centroids[i].pixel);
    }
  EXPECT_GT(absent, 0);
  const std::string bad = TmpPath("obs_bad.json");
  std::ofstream(bad)
      << R"({"format": "mocap-wand-observations", "version": 1, "cameras": ["a", "b"],
    "wand_frames": [[[[1, 2]], null], [[[1, 2]]]]})";
  const Status e = ReadWandObservationsJson(bad, &back);
  ASSERT_FALSE(e.ok());
  EXPECT_NE(e.message().find("wand_frames[1]: expected one entry per camera (2)"),
            std::string::npos)
      << e.message();
}

TEST(CalibrationFile, ACalibrationOfOtherCamerasIsRefused) {
  CalibrationFile f;
  ASSERT_TRUE(ParseCalibrationJson(OneCamera(), "cal.json", &f).ok());
  std::vector<CameraModel> ordered;
  Status s = MatchCalibrationToRig(f, {"cam-A", "cam-B"}, &ordered);
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.message().find("it has 1 cameras, the rig 2"), std::string::npos) << s.message();
  EXPECT_NE(s.message().find("not calibrated: 'cam-B'"), std::string::npos) << s.message();
  s = MatchCalibrationToRig(f, {"cam-Z"}, &ordered);
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.message().find("unknown to the rig: 'cam-A'"), std::string::npos) << s.message();
}

// ---- Checkerboard intrinsics on rendered images ----

// Renders a checkerboard (inner corners nx x ny, square sq) seen through `cam` at board pose
// (R_b, t_b: board -> camera), 3 x 3 supersampled, with N(0, 2) grey-level noise. `rays` holds the
// undistorted normalised coordinates of every subsample (the same for every image).
GrayImage RenderBoard(const CameraModel& cam, const std::vector<Eigen::Vector2f>& rays,
                      const Eigen::Matrix3d& rb, const Eigen::Vector3d& tb, int nx, int ny,
                      double sq, sim::Random& rng) {
  const int w = cam.intrinsics.width, h = cam.intrinsics.height, ss = 3;
  GrayImage im;
  im.width = w;
  im.height = h;
  im.pixels.resize(static_cast<size_t>(w) * h);
  const Eigen::Vector3d n = rb.col(2);
  const double nt = n.dot(tb);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) {
      double sum = 0;
      for (int s = 0; s < ss * ss; ++s) {
        const Eigen::Vector2f& r = rays[(static_cast<size_t>(y) * w + x) * ss * ss + s];
        const Eigen::Vector3d d(r.x(), r.y(), 1.0);
        const double dn = n.dot(d);
        double v = 90;  // background
        if (std::abs(dn) > 1e-9 && nt / dn > 0) {
          const Eigen::Vector3d b = rb.transpose() * (nt / dn * d - tb);
          if (b.x() > -2 * sq && b.x() < (nx + 1) * sq && b.y() > -2 * sq &&
              b.y() < (ny + 1) * sq) {
            v = 220;  // white margin
            if (b.x() > -sq && b.x() < nx * sq && b.y() > -sq && b.y() < ny * sq) {
              const int i = static_cast<int>(std::floor(b.x() / sq)),
                        j = static_cast<int>(std::floor(b.y() / sq));
              if (((i + j) & 1) == 0) v = 30;
            }
          }
        }
        sum += v;
      }
      const double g = sum / (ss * ss) + 2.0 * rng.Normal();
      im.pixels[static_cast<size_t>(y) * w + x] =
          static_cast<std::uint8_t>(std::clamp(g, 0.0, 255.0));
    }
  return im;
}

TEST(CheckerboardIntrinsics, RecoversTheTrueIntrinsicsFromRenderedImages) {
  CameraModel cam;
  CameraIntrinsics& k = cam.intrinsics;
  k.width = 640;
  k.height = 480;
  k.fx = 610;
  k.fy = 612;
  k.cx = 326;
  k.cy = 236;
  k.k1 = -0.12;
  k.k2 = 0.03;
  k.p1 = 0.0005;
  k.p2 = -0.0004;
  const int ss = 3;
  std::vector<Eigen::Vector2f> rays(static_cast<size_t>(k.width) * k.height * ss * ss);
  for (int y = 0; y < k.height; ++y)
    for (int x = 0; x < k.width; ++x)
      for (int s = 0; s < ss * ss; ++s) {
        const Eigen::Vector2d px(x + ((s % ss) + 0.5) / ss - 0.5, y + ((s / ss) + 0.5) / ss - 0.5);
        rays[(static_cast<size_t>(y) * k.width + x) * ss * ss + s] =
            cam.Undistort(px).cast<float>();
      }
  CheckerboardOptions opt;  // 9 x 6 inner corners, 30 mm
  const double sq = opt.square_m;
  sim::Random rng(5);
  std::vector<GrayImage> images;
  for (int i = 0; i < 12; ++i) {
    // Tilted up to ~35 degrees about random in-plane axes, 0.45-0.7 m away, spread over the image.
    const double tilt = 0.6 * (0.3 + 0.7 * rng.Uniform());
    const double axis_angle = rng.Uniform(0, 2 * M_PI);
    const Eigen::Matrix3d rb =
        (Eigen::AngleAxisd(rng.Uniform(-0.3, 0.3), Eigen::Vector3d::UnitZ()) *
         Eigen::AngleAxisd(tilt, Eigen::Vector3d(std::cos(axis_angle), std::sin(axis_angle), 0)))
            .toRotationMatrix();
    const double z = rng.Uniform(0.45, 0.7);
    const Eigen::Vector3d centre(rng.Uniform(-0.12, 0.12) * z / 0.6,
                                 rng.Uniform(-0.08, 0.08) * z / 0.6, z);
    const Eigen::Vector3d board_centre(4 * sq, 2.5 * sq, 0);
    const Eigen::Vector3d tb = centre - rb * board_centre;
    images.push_back(
        RenderBoard(cam, rays, rb, tb, opt.inner_corners_x, opt.inner_corners_y, sq, rng));
  }
  CameraIntrinsics est;
  IntrinsicsSummary summary;
  const Status s = CalibrateIntrinsics(images, opt, &est, &summary);
  ASSERT_TRUE(s.ok()) << s.message();
  std::printf(
      "%s\n  fx %.3f (%.3f) fy %.3f (%.3f) cx %.3f (%.3f) cy %.3f (%.3f) k1 %.5f (%.5f) "
      "k2 %.5f (%.5f)\n",
      summary.BriefReport().c_str(), est.fx, k.fx, est.fy, k.fy, est.cx, k.cx, est.cy, k.cy, est.k1,
      k.k1, est.k2, k.k2);
  EXPECT_GE(summary.images_used, 10);
  EXPECT_LT(summary.rms_px, 0.1);
  EXPECT_NEAR(est.fx, k.fx, 1.5);  // 0.25 %; measured 0.6 px
  EXPECT_NEAR(est.fy, k.fy, 1.5);
  EXPECT_NEAR(est.cx, k.cx, 1.0);
  EXPECT_NEAR(est.cy, k.cy, 1.0);
  EXPECT_NEAR(est.k1, k.k1, 0.005);

  // The same images as files through `mocap calibrate --checkerboard`.
  std::string files;
  for (size_t i = 0; i < images.size(); ++i) {
    const std::string path = TmpPath("board" + std::to_string(i) + ".pgm");
    std::ofstream f(path, std::ios::binary);
    f << "P5\n" << images[i].width << " " << images[i].height << "\n255\n";
    f.write(reinterpret_cast<const char*>(images[i].pixels.data()),
            static_cast<std::streamsize>(images[i].pixels.size()));
    files += " " + path;
  }
  const std::string out = TmpPath("board.json");
  ASSERT_EQ(RunTool(std::string(MOCAP_TOOL) + " calibrate --checkerboard" + files +
                    " --camera-id cam-7 --board 9x6 --square-mm 30 --out " + out + " > " +
                    TmpPath("board.log") + " 2>&1"),
            0);
  CalibrationFile file;
  ASSERT_TRUE(ReadCalibrationJson(out, &file).ok());
  ASSERT_EQ(file.cameras.size(), 1u);
  EXPECT_EQ(file.cameras[0].camera.id, "cam-7");
  EXPECT_NEAR(file.cameras[0].camera.intrinsics.fx, est.fx, 1e-6);
  EXPECT_NEAR(file.cameras[0].camera.intrinsics.k1, est.k1, 1e-9);
}

TEST(CheckerboardIntrinsics, NoBoardIsAClearError) {
  GrayImage blank;
  blank.width = 320;
  blank.height = 240;
  blank.pixels.assign(320 * 240, 128);
  CameraIntrinsics est;
  IntrinsicsSummary summary;
  const Status s = CalibrateIntrinsics(std::vector<GrayImage>(5, blank), {}, &est, &summary);
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.message().find("board was found in 0 of 5 images"), std::string::npos) << s.message();
}

// ---- The command ----

TEST(CalibrateCommand, SimulatesCalibratesAndWritesAFileThatReadsBack) {
  const std::string out = TmpPath("cli.json"), obs = TmpPath("cli_obs.json"),
                    truth = TmpPath("cli_truth.json"), log = TmpPath("cli.log");
  std::filesystem::remove(out);
  ASSERT_EQ(RunTool(std::string(MOCAP_TOOL) +
                    " calibrate --simulate --cameras 6 --seed 4 --duration 15 --quiet"
                    " --out " +
                    out + " --save-observations " + obs + " --save-truth " + truth + " > " + log +
                    " 2>&1"),
            0);
  std::ifstream f(log);
  const std::string text((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  EXPECT_NE(text.find("reprojection_rms_px 0.1"), std::string::npos) << text;
  EXPECT_NE(text.find("wand_length_error_mm_rms"), std::string::npos) << text;
  EXPECT_NE(text.find("position_error_mm_max"), std::string::npos) << text;
  CalibrationFile file, reference;
  ASSERT_TRUE(ReadCalibrationJson(out, &file).ok());
  ASSERT_TRUE(ReadCalibrationJson(truth, &reference).ok());
  ASSERT_EQ(file.cameras.size(), 6u);
  EXPECT_EQ(file.lab_frame, "L-frame");
  EXPECT_LE(file.reprojection_rms_px, 0.15);
  for (size_t c = 0; c < 6; ++c) {
    EXPECT_LT(file.cameras[c].position_error_mm, 2.0);
    double pos, ang;
    CameraPoseError(file.cameras[c].camera, reference.cameras[c].camera, &pos, &ang);
    EXPECT_NEAR(1000 * pos, file.cameras[c].position_error_mm, 1e-6);
  }
  // The same centroids from the file give the same calibration.
  const std::string out2 = TmpPath("cli2.json");
  ASSERT_EQ(RunTool(std::string(MOCAP_TOOL) + " calibrate --quiet --observations " + obs +
                    " --intrinsics " + truth + " --truth " + truth + " --out " + out2 + " > " +
                    log + " 2>&1"),
            0);
  CalibrationFile again;
  ASSERT_TRUE(ReadCalibrationJson(out2, &again).ok());
  for (size_t c = 0; c < 6; ++c)
    EXPECT_LT((again.cameras[c].camera.centre() - file.cameras[c].camera.centre()).norm(), 1e-9);
  // Intrinsics of other cameras: refused, naming them.
  CalibrationFile other = reference;
  other.cameras.pop_back();
  const std::string five = TmpPath("cli_five.json");
  ASSERT_TRUE(WriteCalibrationJson(five, other).ok());
  EXPECT_EQ(RunTool(std::string(MOCAP_TOOL) + " calibrate --quiet --observations " + obs +
                    " --intrinsics " + five + " --out " + out2 + " > " + log + " 2>&1") >>
                8,
            2);
  std::ifstream g(log);
  const std::string err((std::istreambuf_iterator<char>(g)), std::istreambuf_iterator<char>());
  EXPECT_NE(err.find("not calibrated: 'sim-5'"), std::string::npos) << err;
}

}  // namespace
}  // namespace mocap::reconstruction
