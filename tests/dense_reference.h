// The dense reference for the solver tests: the full Jacobian J and residuals r of an
// ArrowProblem at x (rows: each frame's prior rows and residual blocks, then the shared prior
// rows, then the shared dense rows), so that steps can be checked against dense normal equations.
#pragma once
#include <gtest/gtest.h>

#include <Eigen/Core>
#include <vector>

#include "solver/arrow_problem.h"

namespace mocap::testutil {

// Dense J (rows: all frame blocks then prior rows then gauge rows) and r at x.
inline void DenseJacobian(solver::ArrowProblem& problem, const Eigen::VectorXd& x, Eigen::MatrixXd* j,
                   Eigen::VectorXd* r) {
  const int nf = problem.num_frames(), ny = problem.frame_dim(), np = problem.shared_dim();
  const int n = nf * ny + np;
  std::vector<Eigen::RowVectorXd> rows;
  std::vector<double> res;
  ASSERT_TRUE(problem.SetShared(x.tail(np)));
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

}  // namespace mocap::testutil
