// The Schur-complement LM step equals the dense solution of the same damped normal equations.
#include <gtest/gtest.h>

#include "dense_reference.h"
#include "fit_test_util.h"
#include "solver/global_fit.h"
#include "solver/marker_fit_problem.h"
#include "solver/schur_solver.h"
#include "tests/model_test_util.h"

using namespace mocap;



// With and without the per-frame cache, on one and two threads; 40 frames, so each thread's
// stacked rank updates are flushed both when full and at the end of its chunk.
struct SchurCase {
  int threads;
  double cache_budget_bytes;
};
class ArrowSchurStep : public ::testing::TestWithParam<SchurCase> {};

// The damped step from the Schur solver against the dense normal equations of the same problem
// (with `options`' free parameters), also when Linearize anticipated the damping, and after a
// rejected step's new damping; the shared covariance against the dense inverse.
void ExpectStepMatchesDense(const solver::FitOptions& options, const SchurCase& c) {
  std::mt19937_64 rng(5);
  Model nominal = DefaultFullBodyModel();
  const Model truth = mocap::testutil::Baked(nominal, testutil::PerturbedParameters(nominal, rng));
  Eigen::MatrixXd z_true;
  const int nf = 40;
  formats::MarkerTrial trial = testutil::SimulateRandomMotion(truth, nf, 0.0005, rng, &z_true);
  // Some missing samples, so frames differ in structure.
  trial.positions.block(2, 0, 1, 6).setConstant(NAN);
  trial.positions.block(17, 30, 3, 3).setConstant(NAN);
  solver::MarkerFitProblem problem(nominal, trial.positions, options);
  const int ny = nominal.num_coordinates(), np = problem.shared_dim();
  Eigen::VectorXd x(nf * ny + np);
  for (int f = 0; f < nf; ++f) x.segment(f * ny, ny) = z_true.row(f).transpose();
  x.tail(np) = problem.InitialShared() + 0.001 * Eigen::VectorXd::Random(np);
  // Frame priors towards poses a little off the current ones, so their rows have residuals.
  Eigen::VectorXd targets = x;
  targets.head(nf * ny) += 0.01 * Eigen::VectorXd::Random(nf * ny);
  problem.SetFramePriorTargets(targets);
  solver::ArrowSchurProblem schur(&problem, c.threads, c.cache_budget_bytes);
  EXPECT_EQ(schur.caches_frames(), c.cache_budget_bytes > 0);
  double cost;
  Eigen::VectorXd g, d;
  ASSERT_TRUE(schur.Linearize(x, &cost, &g, &d));
  Eigen::MatrixXd j;
  Eigen::VectorXd r;
  testutil::DenseJacobian(problem, x, &j, &r);
  EXPECT_NEAR(cost, 0.5 * r.squaredNorm(), 1e-9 * cost);
  const Eigen::VectorXd g_dense = j.transpose() * r;
  EXPECT_LT((g - g_dense).norm(), 1e-9 * g_dense.norm());
  const Eigen::MatrixXd jtj = j.transpose() * j;
  EXPECT_LT((d - jtj.diagonal()).norm(), 1e-9 * jtj.diagonal().norm());
  const Eigen::VectorXd damping = 1e-3 * jtj.diagonal().cwiseMax(1e-6);
  Eigen::VectorXd dx;
  ASSERT_TRUE(schur.SolveDamped(damping, &dx));
  Eigen::MatrixXd a = jtj;
  a.diagonal() += damping;
  const Eigen::VectorXd dx_dense = a.ldlt().solve(-g_dense);
  EXPECT_LT((dx - dx_dense).norm(), 1e-6 * dx_dense.norm())
      << "frames part " << (dx - dx_dense).head(nf * ny).norm() << " shared part "
      << (dx - dx_dense).tail(np).norm();
  // The same step when Linearize anticipated this damping and reduced the frames in its pass.
  const double lambda = 1e-3, min_diagonal = 1e-6, max_diagonal = 1e32;
  schur.AnticipateDamping(lambda, min_diagonal, max_diagonal);
  ASSERT_TRUE(schur.Linearize(x, &cost, &g, &d));
  const int passes = schur.reduction_passes();
  Eigen::VectorXd dx2;
  ASSERT_TRUE(schur.SolveDamped(lambda * d.cwiseMax(min_diagonal).cwiseMin(max_diagonal), &dx2));
  EXPECT_EQ(schur.reduction_passes(), passes) << "the anticipated reduction was not used";
  EXPECT_LT((dx2 - dx_dense).norm(), 1e-6 * dx_dense.norm());
  // A different damping (a rejected step) forms the system anew.
  ASSERT_TRUE(schur.SolveDamped(2.0 * damping, &dx2));
  EXPECT_EQ(schur.reduction_passes(), passes + 1);
  schur.AnticipateDamping(0, 0, 0);
  // Covariance = inverse of the undamped normal matrix's Schur complement = p-block of inverse.
  Eigen::MatrixXd cov;
  ASSERT_TRUE(schur.SharedCovariance(x, &cov, 1e-12));
  Eigen::MatrixXd inv = jtj.ldlt().solve(Eigen::MatrixXd::Identity(jtj.rows(), jtj.cols()));
  EXPECT_LT((cov - inv.bottomRightCorner(np, np)).norm(), 1e-5 * inv.bottomRightCorner(np, np).norm());
}

TEST_P(ArrowSchurStep, MatchesDenseNormalEquations) { ExpectStepMatchesDense(solver::FitOptions(), GetParam()); }

// With only the joint axes fitted, a joint's rows and its parent's reach the same shared columns
// and form one row group of 6-7 rows (a leg's ankle, knee and hip; an arm's), so the reduction
// eliminates the pelvis's and the trunk's rows against more than three rows of an earlier group
// at once (ReduceFrame takes them three at a time); the full parameter set never does.
TEST_P(ArrowSchurStep, MatchesDenseNormalEquationsWithWideRowGroups) {
  solver::FitOptions options;
  options.fit_scales = options.fit_centres = options.fit_markers = false;
  {
    Model nominal = DefaultFullBodyModel();
    std::mt19937_64 rng(5);
    formats::MarkerTrial trial = testutil::SimulateRandomMotion(nominal, 3, 0.0005, rng);
    solver::MarkerFitProblem problem(nominal, trial.positions, options);
    solver::ArrowSchurProblem schur(&problem, 1);
    const std::string structure = schur.DescribeStructure();
    // Group lines read "  rows FIRST+COUNT: ..."; a group of more than three rows before the last.
    int wide_before_last = 0, groups = 0, last_wide = 0;
    for (size_t at = structure.find("rows "); at != std::string::npos; at = structure.find("rows ", at + 1)) {
      const int count = std::stoi(structure.substr(structure.find('+', at) + 1));
      ++groups;
      wide_before_last += last_wide;
      last_wide = count > 3;
    }
    ASSERT_GT(groups, 1) << structure;
    ASSERT_GT(wide_before_last, 0) << structure;
  }
  ExpectStepMatchesDense(options, GetParam());
}

// Geodesic acceleration (LmOptions::geodesic_acceleration): the Schur solver's a equals the dense
// -(J^T J + D)^-1 J^T r_vv, r_vv = (2 / h) ((r(x + h v) - r(x)) / h - J v), with v the damped step
// and the same damping; without the per-frame cache it declines (LM then takes the plain step).
TEST_P(ArrowSchurStep, GeodesicAccelerationMatchesDenseFiniteDifference) {
  std::mt19937_64 rng(7);
  Model nominal = DefaultFullBodyModel();
  const Model truth = mocap::testutil::Baked(nominal, testutil::PerturbedParameters(nominal, rng));
  Eigen::MatrixXd z_true;
  const int nf = 20;  // dense reference: (20 x 38 + shared)^2
  formats::MarkerTrial trial = testutil::SimulateRandomMotion(truth, nf, 0.0005, rng, &z_true);
  trial.positions.block(5, 0, 2, 6).setConstant(NAN);
  solver::FitOptions options;
  solver::MarkerFitProblem problem(nominal, trial.positions, options);
  const int ny = nominal.num_coordinates(), np = problem.shared_dim();
  Eigen::VectorXd x(nf * ny + np);
  // Poses 0.05 rad off and the nominal geometry: a step large enough to curve.
  for (int f = 0; f < nf; ++f) x.segment(f * ny, ny) = z_true.row(f).transpose() + 0.05 * Eigen::VectorXd::Random(ny);
  x.tail(np) = problem.InitialShared();
  problem.SetFramePriorTargets(x);
  solver::ArrowSchurProblem schur(&problem, GetParam().threads, GetParam().cache_budget_bytes);
  double cost;
  Eigen::VectorXd g, d, v, a;
  ASSERT_TRUE(schur.Linearize(x, &cost, &g, &d));
  const Eigen::VectorXd damping = 1e-3 * d.cwiseMax(1e-6);
  // Before any damped solve there is no factorisation to reuse.
  EXPECT_FALSE(schur.SolveAcceleration(damping, Eigen::VectorXd::Zero(x.size()), 0.02, &a));
  ASSERT_TRUE(schur.SolveDamped(damping, &v));
  const double h = 0.02;
  if (!schur.caches_frames()) {
    EXPECT_FALSE(schur.SolveAcceleration(damping, v, h, &a));
    return;
  }
  EXPECT_FALSE(schur.SolveAcceleration(2.0 * damping, v, h, &a)) << "another damping than the last solve's";
  ASSERT_TRUE(schur.SolveAcceleration(damping, v, h, &a));
  Eigen::MatrixXd j, j_shifted;
  Eigen::VectorXd r, r_shifted;
  testutil::DenseJacobian(problem, x, &j, &r);
  testutil::DenseJacobian(problem, x + h * v, &j_shifted, &r_shifted);
  ASSERT_EQ(r.size(), r_shifted.size());
  const Eigen::VectorXd rvv = (2.0 / h) * ((r_shifted - r) / h - j * v);
  Eigen::MatrixXd m = j.transpose() * j;
  m.diagonal() += damping;
  const Eigen::VectorXd a_dense = m.ldlt().solve(-(j.transpose() * rvv));
  ASSERT_GT(a_dense.norm(), 1e-6 * v.norm()) << "no curvature along v: the test would prove nothing";
  EXPECT_LT((a - a_dense).norm(), 1e-6 * a_dense.norm())
      << "frames part " << (a - a_dense).head(nf * ny).norm() << " shared part " << (a - a_dense).tail(np).norm();
  // The step still solves the same system after the acceleration pass (factor and cache intact).
  Eigen::VectorXd v2;
  ASSERT_TRUE(schur.SolveDamped(damping, &v2));
  EXPECT_LT((v2 - v).norm(), 1e-9 * v.norm());
}

INSTANTIATE_TEST_SUITE_P(CacheAndThreads, ArrowSchurStep,
                         ::testing::Values(SchurCase{1, 1e9}, SchurCase{2, 1e9}, SchurCase{2, 0.0}),
                         [](const ::testing::TestParamInfo<SchurCase>& info) {
                           return std::to_string(info.param.threads) + "threads" +
                                  (info.param.cache_budget_bytes > 0 ? "Cached" : "Uncached");
                         });

// The symbolic analysis finds the tree: leaves are eliminated first, the root's six coordinates
// last, and only the root's rows reach every shared column.
TEST(ArrowSchur, EliminatesLeavesFirstAndOnlyTheRootReachesEveryParameter) {
  Model nominal = DefaultFullBodyModel();
  std::mt19937_64 rng(5);
  formats::MarkerTrial trial = testutil::SimulateRandomMotion(nominal, 3, 0.0005, rng);
  solver::MarkerFitProblem problem(nominal, trial.positions, solver::FitOptions());
  solver::ArrowSchurProblem schur(&problem, 1);
  const std::vector<int>& order = schur.elimination_order();
  ASSERT_EQ(order.size(), 38u);
  std::vector<int> last(order.end() - 6, order.end());
  std::sort(last.begin(), last.end());
  EXPECT_EQ(last, (std::vector<int>{0, 1, 2, 3, 4, 5})) << "the pelvis (root) is eliminated last";
  const int first_joint = nominal.coordinates()[order.front()].joint;
  for (const Joint& j : nominal.joints()) EXPECT_NE(j.parent, nominal.joints()[first_joint].child) << "a leaf comes first";
  const std::string structure = schur.DescribeStructure();
  const std::string full = std::to_string(problem.shared_dim()) + " columns in [0, " +
                           std::to_string(problem.shared_dim() - 1) + "] contiguous";
  EXPECT_EQ(structure.find(full), structure.rfind(full)) << structure;  // exactly one group
  EXPECT_NE(structure.find("rows 32+6: " + full), std::string::npos) << structure;
}
