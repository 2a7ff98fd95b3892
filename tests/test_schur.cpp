// The Schur-complement LM step equals the dense solution of the same damped normal equations.
#include <gtest/gtest.h>

#include "fit_test_util.h"
#include "solver/global_fit.h"
#include "solver/marker_fit_problem.h"
#include "solver/schur_solver.h"

using namespace mocap;

namespace {
// Dense J (rows: all frame blocks then prior rows then gauge rows) and r at x.
void DenseJacobian(solver::MarkerFitProblem& problem, const Eigen::VectorXd& x, Eigen::MatrixXd* j,
                   Eigen::VectorXd* r) {
  const int nf = problem.num_frames(), ny = problem.frame_dim(), np = problem.shared_dim();
  const int n = nf * ny + np;
  std::vector<Eigen::RowVectorXd> rows;
  std::vector<double> res;
  problem.SetShared(x.tail(np));
  auto ev = problem.NewEvaluator();
  for (int f = 0; f < nf; ++f) {
    const double *w, *target;
    if (problem.FramePrior(f, &w, &target))
      for (int i = 0; i < ny; ++i) {
        Eigen::RowVectorXd row = Eigen::RowVectorXd::Zero(n);
        row[f * ny + i] = w[i];
        rows.push_back(row);
        res.push_back(w[i] * (x[f * ny + i] - target[i]));
      }
    ASSERT_TRUE(ev->Evaluate(f, x.data() + f * ny, true));
    for (int b = 0; b < ev->num_blocks(); ++b) {
      const auto& blk = ev->block(b);
      for (int k = 0; k < blk.rows; ++k) {
        Eigen::RowVectorXd row = Eigen::RowVectorXd::Zero(n);
        for (int a = 0; a < blk.num_y; ++a) row[f * ny + blk.y_index[a]] += blk.jy[a * 3 + k];
        for (int c = 0; c < blk.num_p; ++c)
          if (blk.p_index[c] >= 0) row[nf * ny + blk.p_index[c]] += blk.jp[c * 3 + k];
        rows.push_back(row);
        res.push_back(blk.residual[k]);
      }
    }
  }
  const Eigen::VectorXd delta = x.tail(np) - problem.prior_target();
  for (int i = 0; i < np; ++i) {
    Eigen::RowVectorXd row = Eigen::RowVectorXd::Zero(n);
    row[nf * ny + i] = problem.prior_weight()[i];
    rows.push_back(row);
    res.push_back(problem.prior_weight()[i] * delta[i]);
  }
  const Eigen::MatrixXd& g = problem.shared_rows();
  for (int i = 0; i < g.rows(); ++i) {
    Eigen::RowVectorXd row = Eigen::RowVectorXd::Zero(n);
    row.tail(np) = g.row(i);
    rows.push_back(row);
    res.push_back(g.row(i).dot(delta));
  }
  j->resize(rows.size(), n);
  r->resize(rows.size());
  for (size_t i = 0; i < rows.size(); ++i) {
    j->row(i) = rows[i];
    (*r)[i] = res[i];
  }
}
}  // namespace

TEST(ArrowSchur, StepMatchesDenseNormalEquations) {
  std::mt19937_64 rng(5);
  Model nominal = DefaultFullBodyModel();
  const Model truth = nominal.WithParameters(testutil::PerturbedParameters(nominal, rng));
  Eigen::MatrixXd z_true;
  formats::MarkerTrial trial = testutil::SimulateRandomMotion(truth, 6, 0.0005, rng, &z_true);
  // Some missing samples, so frames differ in structure.
  trial.positions.block(2, 0, 1, 6).setConstant(NAN);
  solver::FitOptions options;
  solver::MarkerFitProblem problem(nominal, trial.positions, options);
  const int nf = 6, ny = nominal.num_coordinates(), np = problem.shared_dim();
  Eigen::VectorXd x(nf * ny + np);
  for (int f = 0; f < nf; ++f) x.segment(f * ny, ny) = z_true.row(f).transpose();
  x.tail(np) = problem.InitialShared() + 0.001 * Eigen::VectorXd::Random(np);
  // Frame priors towards poses a little off the current ones, so their rows have residuals.
  Eigen::VectorXd targets = x;
  targets.head(nf * ny) += 0.01 * Eigen::VectorXd::Random(nf * ny);
  problem.SetFramePriorTargets(targets);
  solver::ArrowSchurProblem schur(&problem, 2);
  double cost;
  Eigen::VectorXd g, d;
  ASSERT_TRUE(schur.Linearize(x, &cost, &g, &d));
  Eigen::MatrixXd j;
  Eigen::VectorXd r;
  DenseJacobian(problem, x, &j, &r);
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
  // Covariance = inverse of the undamped normal matrix's Schur complement = p-block of inverse.
  Eigen::MatrixXd cov;
  ASSERT_TRUE(schur.SharedCovariance(&cov, 1e-12));
  Eigen::MatrixXd inv = jtj.ldlt().solve(Eigen::MatrixXd::Identity(jtj.rows(), jtj.cols()));
  EXPECT_LT((cov - inv.bottomRightCorner(np, np)).norm(), 1e-5 * inv.bottomRightCorner(np, np).norm());
}

TEST(ArrowSchur, DISABLED_PrintStructure) {
  Model nominal = DefaultFullBodyModel();
  std::mt19937_64 rng(5);
  formats::MarkerTrial trial = testutil::SimulateRandomMotion(nominal, 3, 0.0005, rng);
  solver::MarkerFitProblem problem(nominal, trial.positions, solver::FitOptions());
  solver::ArrowSchurProblem schur(&problem, 1);
  std::printf("%s", schur.DescribeStructure().c_str());
}
