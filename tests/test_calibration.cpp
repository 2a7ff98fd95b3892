// Camera calibration: the wand bundle adjustment's Jacobians, wand identification, the simulated
// 8-camera wand calibration against the true rig, the calibration file, checkerboard intrinsics.
#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <cstdio>

#include "reconstruction/calibration.h"
#include "reconstruction/calibration_problem.h"
#include "sim/camera_rig.h"
#include "sim/random.h"
#include "sim/wand.h"
#include "solver/arrow_problem.h"

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
  so.duration_s = 2;
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
    fr.SetDirection(tm[2] - tm[0] + 0.05 * Eigen::Vector3d(rng.Normal(), rng.Normal(), rng.Normal()));
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
      for (int j = 0; j < 3; ++j) x[x.size() - problem.shared_dim() + problem.shared_index(c, j)] += 0.05 * rng.Normal();
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
  double seconds = 0;
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
    const auto t0 = std::chrono::steady_clock::now();
    WandCalibrationOptions co;
    r.status = CalibrateWand(r.truth, simulation.wand_frames, simulation.lframe_frames, co,
                             &r.calibrated, &r.summary);
    r.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
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
  std::printf("calibration %.2f s; worst position %.3f mm, orientation %.4f deg\n", run.seconds,
              1000 * worst_pos, worst_ang * 180 / M_PI);
  EXPECT_LE(run.summary.reprojection_rms_px, 0.15);
  EXPECT_LE(run.summary.wand_length_error_mm_rms, 0.3);
  EXPECT_TRUE(run.summary.lab_frame_from_lframe);
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
  EXPECT_NE(s.message().find("never seen by two cameras at once"), std::string::npos) << s.message();
}

}  // namespace
}  // namespace mocap::reconstruction
