// Levenberg–Marquardt linear algebra for arrow-structured problems (solver/arrow_problem.h) by
// eliminating every frame block: the damped normal equations
//
//     [ U   W ] [dy]     [g_y]        U = blockdiag(U_f) = J_y^T J_y + D_y
//     [ W^T V ] [dp] = - [g_p]        W_f = J_yf^T J_pf,  V = J_p^T J_p + D_p + A^T A + G^T G
//
// reduce to the dense Schur complement  S = V - sum_f W_f^T U_f^{-1} W_f  on the shared
// parameters (a few hundred), solved by dense Cholesky; then each dy_f = -U_f^{-1}(g_yf + W_f dp)
// independently. This is the reduced camera system of bundle adjustment (Triggs et al., "Bundle
// Adjustment — A Modern Synthesis", 2000, §6.1) with frames in place of points.
//
// Two structural facts make it fast for kinematic trees:
//  * U_f has the sparsity of a tree (coordinates couple only along a kinematic chain); eliminated
//    leaves first (minimum degree finds that order), its Cholesky factor L_f has no fill.
//  * With that order, row i of Y_f = L_f^{-1} W_f is non-zero only on the shared parameters that
//    affect the subtree below coordinate i; so S -= Y^T Y is a sum of small dense outer products
//    over row groups, and only the root's rows touch every shared parameter.
// Both patterns are found once, symbolically, from ArrowProblem::BlockStructure.
// Each frame's U_f and W_f are cached between the linearisation and the solves when they fit in
// `cache_budget_bytes`, so a step (and a rejected step's re-solve) costs no Jacobian evaluation;
// above the budget nothing per frame is stored and the Jacobian is re-evaluated in each pass, so
// memory stays O(frames x frame_dim) and 60,000 frames fit easily. Frames are processed in
// parallel with per-thread accumulators.
#pragma once

#include <Eigen/Core>
#include <memory>
#include <vector>

#include "solver/arrow_problem.h"
#include "solver/levenberg_marquardt.h"

namespace mocap::solver {

class ArrowSchurProblem : public LmProblem {
 public:
  static constexpr double kDefaultCacheBudgetBytes = 1.0 * (1 << 30);
  ArrowSchurProblem(ArrowProblem* problem, int num_threads,
                    double cache_budget_bytes = kDefaultCacheBudgetBytes);
  bool caches_frames() const { return cached_; }
  ~ArrowSchurProblem() override;

  int num_parameters() const override;
  int num_residuals() const override;
  bool Cost(const Eigen::VectorXd& x, double* cost) override;
  bool Linearize(const Eigen::VectorXd& x, double* cost, Eigen::VectorXd* gradient,
                 Eigen::VectorXd* jtj_diagonal) override;
  bool SolveDamped(const Eigen::VectorXd& damping, Eigen::VectorXd* dx) override;

  // Covariance of the shared parameters at the last linearisation point, (S^{-1} with no
  // damping on p), in the units of the residuals. Frame blocks that the data leave singular get
  // a ridge of `frame_ridge` relative to their diagonal. False if S is not positive definite.
  bool SharedCovariance(Eigen::MatrixXd* covariance, double frame_ridge = 1e-10);

  // Per-frame squared residual sums at x (for per-marker statistics the problem computes itself).
  const std::vector<int>& elimination_order() const { return order_; }

 private:
  struct ThreadState;
  void Analyse();
  void AccumulateFrame(ThreadState& ts) const;
  bool BackSubstitutionTerms(ThreadState& ts, int f, const Eigen::VectorXd& dp);
  Eigen::Map<Eigen::MatrixXd> CachedU(int f) {
    return Eigen::Map<Eigen::MatrixXd>(u_cache_.data() + static_cast<size_t>(f) * ny_ * ny_, ny_, ny_);
  }
  Eigen::Map<Eigen::MatrixXd> CachedW(int f) {
    return Eigen::Map<Eigen::MatrixXd>(w_cache_.data() + static_cast<size_t>(f) * ny_ * np_, ny_, np_);
  }
  double SharedRowsSquaredNorm(const Eigen::VectorXd& p) const;
  // Pass 1: accumulates S (lower triangle) and the reduced right-hand side over all frames.
  bool FormReducedSystem(const Eigen::VectorXd& damping, Eigen::MatrixXd* s, Eigen::VectorXd* rhs);

  ArrowProblem* problem_;
  int num_threads_;
  int nf_, ny_, np_;
  int max_block_y_ = 1, max_block_p_ = 1;  // widest residual block (from BlockStructure)
  std::vector<int> order_;     // elimination order: position -> y index
  std::vector<int> position_;  // y index -> position
  struct RowGroup {
    int first_row, num_rows;   // in elimination order
    std::vector<int> columns;  // p columns reached (sorted)
    bool contiguous;           // columns == [columns.front(), columns.back()]
  };
  std::vector<RowGroup> groups_;
  std::vector<std::unique_ptr<ThreadState>> threads_;
  Eigen::VectorXd x_, gradient_;
  bool cached_ = false;
  std::vector<double> u_cache_, w_cache_;  // per frame U_f (elimination order) and W_f
  Eigen::MatrixXd v_total_;                // sum of V_f (lower), with the cache
};

}  // namespace mocap::solver
