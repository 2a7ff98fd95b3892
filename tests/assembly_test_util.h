// The fit's own assembly of a frame's normal equations (FrameEvaluator::AddNormalEquations, from
// per-segment sums) against the Schur solver's assembly from the same evaluator's residual blocks
// (per-marker products): the same problem seen through a wrapper whose evaluator offers the
// blocks alone.
#pragma once

#include <gtest/gtest.h>

#include <memory>
#include <utility>
#include <vector>

#include "solver/arrow_problem.h"
#include "solver/schur_solver.h"

namespace mocap::testutil {

class BlocksOnlyEvaluator : public solver::FrameEvaluator {
 public:
  explicit BlocksOnlyEvaluator(std::unique_ptr<solver::FrameEvaluator> inner) : inner_(std::move(inner)) {}
  bool Evaluate(int frame, const double* y, bool with_jacobians) override {
    return inner_->Evaluate(frame, y, with_jacobians);
  }
  bool EvaluatePoseJacobians(int frame, const double* y) override { return inner_->EvaluatePoseJacobians(frame, y); }
  int num_blocks() const override { return inner_->num_blocks(); }
  const solver::ResidualBlock& block(int i) const override { return inner_->block(i); }

 private:
  std::unique_ptr<solver::FrameEvaluator> inner_;
};

class BlocksOnlyProblem : public solver::ArrowProblem {
 public:
  explicit BlocksOnlyProblem(solver::ArrowProblem* inner) : inner_(inner) {}
  int num_frames() const override { return inner_->num_frames(); }
  int frame_dim() const override { return inner_->frame_dim(); }
  int shared_dim() const override { return inner_->shared_dim(); }
  int num_residuals() const override { return inner_->num_residuals(); }
  bool SetShared(const Eigen::VectorXd& p) override { return inner_->SetShared(p); }
  std::unique_ptr<solver::FrameEvaluator> NewEvaluator() const override {
    return std::make_unique<BlocksOnlyEvaluator>(inner_->NewEvaluator());
  }
  const Eigen::VectorXd& prior_weight() const override { return inner_->prior_weight(); }
  const Eigen::VectorXd& prior_target() const override { return inner_->prior_target(); }
  bool FramePrior(int frame, const double** weight, const double** target) const override {
    return inner_->FramePrior(frame, weight, target);
  }
  const Eigen::MatrixXd& shared_rows() const override { return inner_->shared_rows(); }
  void BlockStructure(std::vector<std::vector<int>>* y_columns,
                      std::vector<std::vector<int>>* p_columns) const override {
    inner_->BlockStructure(y_columns, p_columns);
  }

 private:
  solver::ArrowProblem* inner_;
};

// Linearises `problem` at x both ways (with the reduction at an anticipated damping, as the fit
// runs it) and compares the cost, gradient, diagonal and damped step: equal to rounding when the
// problem's assembly is the blocks' products summed another way.
inline void ExpectAssemblyMatchesBlocks(solver::ArrowProblem* problem, const Eigen::VectorXd& x) {
  BlocksOnlyProblem blocks(problem);
  solver::ArrowSchurProblem assembled(problem, 2), plain(&blocks, 2);
  const double lambda = 1e-3;
  Eigen::VectorXd g[2], d[2], dx[2];
  double cost[2];
  solver::ArrowSchurProblem* solvers[2] = {&assembled, &plain};
  for (int k = 0; k < 2; ++k) {
    solvers[k]->AnticipateDamping(lambda, 1e-6, 1e32);
    ASSERT_TRUE(solvers[k]->Linearize(x, &cost[k], &g[k], &d[k]));
    const Eigen::VectorXd damping = lambda * d[k].cwiseMax(1e-6).cwiseMin(1e32);
    ASSERT_TRUE(solvers[k]->SolveDamped(damping, &dx[k]));
  }
  EXPECT_EQ(cost[0], cost[1]);  // the residuals are the blocks' in both
  const int nf = problem->num_frames(), ny = problem->frame_dim(), np = problem->shared_dim();
  auto expect_close = [](const Eigen::VectorXd& a, const Eigen::VectorXd& b, double tol, const char* what) {
    const double scale = b.cwiseAbs().maxCoeff();
    int bad = 0;
    for (Eigen::Index i = 0; i < a.size(); ++i)
      if (!(std::abs(a[i] - b[i]) <= tol * scale) && ++bad <= 5)
        ADD_FAILURE() << what << " entry " << i << ": " << a[i] << " against " << b[i] << " (largest " << scale << ")";
  };
  const Eigen::Index frames = static_cast<Eigen::Index>(nf) * ny;
  expect_close(g[0].head(frames), g[1].head(frames), 1e-11, "frame gradient");
  expect_close(g[0].tail(np), g[1].tail(np), 1e-11, "shared gradient");
  expect_close(d[0], d[1], 1e-11, "diagonal");
  expect_close(dx[0].head(frames), dx[1].head(frames), 1e-8, "frame step");
  expect_close(dx[0].tail(np), dx[1].tail(np), 1e-8, "shared step");
  EXPECT_GT(dx[1].tail(np).cwiseAbs().maxCoeff(), 0.0);
}

}  // namespace mocap::testutil
