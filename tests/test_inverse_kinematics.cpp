// Per-frame inverse kinematics from nothing (InverseKinematics::Initialise): whatever the lab's
// vertical (Z, Y, -Z, a lying subject) and the subject's heading, the pose is found without being
// told, to the exactness of noise-free data.
#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <random>

#include "model/default_model.h"
#include "model/kinematics.h"
#include "model_test_util.h"
#include "solver/inverse_kinematics.h"

using namespace mocap;

namespace {

Eigen::Matrix3Xd Markers(const Model& m, const Eigen::VectorXd& z) {
  const Geometry g(m);
  ModelData d(m);
  ForwardKinematics(m, g, z, &d);
  Eigen::Matrix3Xd x(3, m.num_markers());
  for (int k = 0; k < m.num_markers(); ++k) x.col(k) = MarkerPosition(m, g, d, k);
  return x;
}

}  // namespace

TEST(InverseKinematics, InitialiseFindsTheSubjectWhateverTheLabsVertical) {
  const Model m = DefaultFullBodyModel();
  const Geometry g(m);
  solver::InverseKinematics ik(m, g);
  std::mt19937 rng(5);
  using Eigen::AngleAxisd;
  using Eigen::Vector3d;
  const std::vector<std::pair<const char*, Eigen::Matrix3d>> labs = {
      {"Z up", Eigen::Matrix3d::Identity()},
      {"Y up (OpenSim)", AngleAxisd(-M_PI / 2, Vector3d::UnitX()).toRotationMatrix()},
      {"-Z up (upside down)", AngleAxisd(M_PI, Vector3d::UnitY()).toRotationMatrix()},
      {"X up (lying)", AngleAxisd(M_PI / 2, Vector3d::UnitY()).toRotationMatrix()},
  };
  for (const auto& [name, lab] : labs) {
    for (int k = 0; k < 3; ++k) {
      // A standing subject with moderately bent joints, turned to some heading about its own
      // vertical, in a lab whose axes are `lab`.
      Eigen::VectorXd z = m.DefaultCoordinates() + 0.3 * (testutil::RandomPose(m, rng) - m.DefaultCoordinates());
      const Eigen::Matrix3d heading = AngleAxisd(2.1 * k + 0.4, Vector3d::UnitZ()).toRotationMatrix();
      Eigen::Matrix3Xd measured = (lab * heading) * Markers(m, z);
      measured.colwise() += Vector3d(1.5, -0.7, 0.3);
      Eigen::VectorXd solved;
      const solver::IkFrameResult r = ik.Initialise(measured, &solved);
      EXPECT_LT(r.rms_m, 1e-6) << name << ", heading " << k;
    }
  }
  // Any orientation at all (uniform random rotations) and larger joint angles.
  std::normal_distribution<double> n(0, 1);
  int found = 0;
  const int tries = 40;
  for (int k = 0; k < tries; ++k) {
    const Eigen::Quaterniond q(n(rng), n(rng), n(rng), n(rng));
    const Eigen::VectorXd z = m.DefaultCoordinates() + 0.6 * (testutil::RandomPose(m, rng) - m.DefaultCoordinates());
    Eigen::Matrix3Xd measured = q.normalized().toRotationMatrix() * Markers(m, z);
    Eigen::VectorXd solved;
    found += ik.Initialise(measured, &solved).rms_m < 1e-6;
  }
  EXPECT_EQ(found, tries);
}

// A gap (IkOptions::bridge_gaps): the right hand's only marker hidden for frames 40-59, every
// coordinate moving linearly in time. The wrist angles, which nothing else in those frames
// observes, follow the interpolation between the frames that see the marker (the truth here);
// without bridging they stay where the frame before the gap left them.
TEST(InverseKinematics, GapFramesAreBridgedFromTheFramesThatSeeTheHiddenMarkers) {
  const Model m = DefaultFullBodyModel();
  const Geometry g(m);
  const int nz = m.num_coordinates(), nm = m.num_markers(), nf = 100;
  const int flex = m.FindCoordinate("wrist_flex_r"), dev = m.FindCoordinate("wrist_dev_r");
  const int fin = m.FindMarker("RFIN");
  ASSERT_GE(flex, 0);
  ASSERT_GE(dev, 0);
  ASSERT_GE(fin, 0);
  std::mt19937 rng(9);
  std::uniform_real_distribution<double> u(-0.3, 0.3);
  Eigen::VectorXd z0 = m.DefaultCoordinates(), dz(nz);
  for (int c = 0; c < nz; ++c) dz[c] = u(rng);
  dz[flex] = 0.8;
  dz[dev] = -0.6;
  Eigen::MatrixXd truth(nf, nz);
  Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> measured(nf, 3 * nm);
  for (int f = 0; f < nf; ++f) {
    truth.row(f) = (z0 + dz * (double(f) / (nf - 1))).transpose();
    const Eigen::Matrix3Xd x = Markers(m, truth.row(f).transpose());
    for (int k = 0; k < nm; ++k) measured.block(f, 3 * k, 1, 3) = x.col(k).transpose();
  }
  measured.block(40, 3 * fin, 20, 3).setConstant(std::numeric_limits<double>::quiet_NaN());
  double bridged_error = 0, unbridged_error = 0;
  for (bool bridge : {true, false}) {
    solver::IkOptions options;
    options.bridge_gaps = bridge;
    solver::InverseKinematics ik(m, g, options);
    Eigen::MatrixXd z;
    ASSERT_TRUE(ik.SolveTrial(measured, &z).ok());
    double& error = bridge ? bridged_error : unbridged_error;
    for (int f = 40; f < 60; ++f)
      for (int c : {flex, dev}) error = std::max(error, std::abs(z(f, c) - truth(f, c)));
    // The frames that see every marker are unaffected.
    EXPECT_LT((z.row(10) - truth.row(10)).lpNorm<Eigen::Infinity>(), 1e-5);
  }
  EXPECT_LT(bridged_error, 1e-3);
  EXPECT_GT(unbridged_error, 0.1);
}

// A rotation driven by its own coordinate looks the same a whole turn on, so a frame solve may end
// any number of turns away (measured: subtalar angles 4 turns off in gaps, which the global fit's
// frame priors then fought). Solve returns each such coordinate at its representative nearest its
// range's centre (a joint narrower than a turn) or nearest its start (the free root's heading,
// range +-2 pi, so that a turning subject stays continuous), the markers unchanged.
TEST(InverseKinematics, PeriodicCoordinatesComeBackFromWholeTurns) {
  const Model m = DefaultFullBodyModel();
  const Geometry g(m);
  const std::vector<char> periodic = solver::PeriodicCoordinates(m);
  const int subtalar = m.FindCoordinate("subtalar_angle_r"), wrist = m.FindCoordinate("wrist_flex_l");
  const int heading = m.FindCoordinate("pelvis_rotation"), tx = m.FindCoordinate("pelvis_tx");
  ASSERT_GE(subtalar, 0);
  ASSERT_GE(wrist, 0);
  ASSERT_GE(heading, 0);
  ASSERT_GE(tx, 0);
  EXPECT_TRUE(periodic[subtalar]);
  EXPECT_TRUE(periodic[heading]);
  EXPECT_FALSE(periodic[tx]);  // a translation
  std::mt19937 rng(4);
  std::uniform_real_distribution<double> u(-0.2, 0.2);
  Eigen::VectorXd truth = m.DefaultCoordinates();
  for (int c = 0; c < m.num_coordinates(); ++c) truth[c] += u(rng);
  const Eigen::Matrix3Xd measured = Markers(m, truth);
  Eigen::VectorXd z = truth;
  z[subtalar] += 4 * M_PI;
  z[wrist] -= 2 * M_PI;
  z[heading] += 2 * M_PI;
  solver::InverseKinematics ik(m, g);
  const solver::IkFrameResult r = ik.Solve(measured, &z);
  EXPECT_LT(r.rms_m, 1e-6);
  EXPECT_NEAR(z[subtalar], truth[subtalar], 1e-6);
  EXPECT_NEAR(z[wrist], truth[wrist], 1e-6);
  EXPECT_NEAR(z[heading], truth[heading] + 2 * M_PI, 1e-6);
  EXPECT_LT((Markers(m, z) - measured).cwiseAbs().maxCoeff(), 1e-6);
}
