// The global fit on a synthetic subject: recovers the true geometry, reports honestly.
#include <gtest/gtest.h>

#include "fit_test_util.h"
#include "model/default_model.h"
#include "solver/global_fit.h"

using namespace mocap;

namespace {
Model NominalWithoutOptional() {
  Model m = DefaultFullBodyModel();
  std::vector<int> keep;
  for (int i = 0; i < m.num_markers(); ++i)
    if (!m.markers()[i].optional) keep.push_back(i);
  return m.WithMarkers(keep);
}
}  // namespace

TEST(GlobalFit, RecoversSphericalJointCentresAndReachesTheNoiseFloor) {
  std::mt19937_64 rng(11);
  const Model nominal = NominalWithoutOptional();
  const Eigen::VectorXd p_true = testutil::PerturbedParameters(nominal, rng);
  const Model truth = nominal.WithParameters(p_true);
  const double noise = 0.0005;
  std::vector<solver::FitTrial> trials(1);
  trials[0].markers = testutil::SimulateRandomMotion(truth, 1000, noise, rng);
  solver::FitOptions options;
  solver::FitResult result;
  Status s = solver::FitModel(nominal, trials, options, &result);
  ASSERT_TRUE(s.ok()) << s.message();
  const auto& r = result.report;
  std::printf("%s\n%s", r.BriefReport().c_str(), r.solver.FullReport().c_str());
  EXPECT_TRUE(r.converged());
  // 3D marker distance RMS for per-coordinate noise sigma is sigma*sqrt(3), less the fitted dof.
  const double expected = 1000 * noise * std::sqrt(3.0 * (1.0 - double(r.unknowns) / r.residuals));
  EXPECT_NEAR(r.marker_rms_mm, expected, 0.1 * expected);
  // Joint centres of spherical joints are fully determined: compare in the world at a pose.
  Geometry gt(truth), gf(result.model);
  ModelData dt(truth), df(result.model);
  const Eigen::VectorXd z = result.coordinates[0].row(500).transpose();
  ForwardKinematics(result.model, gf, z, &df);
  // The fitted pose of frame 500 places the fitted model; compare with the true model placed by
  // the true pose... poses differ by gauge, so compare centres relative to the pelvis frame.
  for (const char* joint : {"hip_l", "hip_r", "lumbar", "shoulder_l", "neck"}) {
    const int j = truth.FindJoint(joint);
    const int parent = truth.joints()[j].parent;
    const Eigen::Vector3d ct = truth.segments()[parent].scale * truth.joints()[j].centre;
    const Eigen::Vector3d cf = result.model.segments()[parent].scale * result.model.joints()[j].centre;
    EXPECT_LT((ct - cf).norm(), 0.002) << joint;
  }
  EXPECT_LT(r.undetermined.size(), r.parameters.size());
  for (const auto& e : r.parameters) {
    EXPECT_TRUE(std::isfinite(e.value)) << e.name;
    EXPECT_TRUE(std::isfinite(e.std)) << e.name;
  }
}
TEST(GlobalFit, DebugPrintUndetermined) {
  std::mt19937_64 rng(11);
  const Model nominal = NominalWithoutOptional();
  const Model truth = nominal.WithParameters(testutil::PerturbedParameters(nominal, rng));
  std::vector<solver::FitTrial> trials(1);
  trials[0].markers = testutil::SimulateRandomMotion(truth, 1000, 0.0005, rng);
  solver::FitOptions options;
  solver::FitResult result;
  ASSERT_TRUE(solver::FitModel(nominal, trials, options, &result).ok());
  for (auto& e : result.report.parameters) printf("%s %.3g %.3g %.3g | ", e.name.c_str(), e.initial, e.value, e.std);
  printf("\n");
}
