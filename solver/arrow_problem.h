// Nonlinear least squares with the arrow structure of bundle adjustment:
//
//     x = [y_1 ... y_F, p],
//     cost = 1/2 sum_f (||r_f(y_f, p)||^2 + ||B_f (y_f - y0_f)||^2)
//            + 1/2 ||A (p - p0)||^2 + 1/2 ||G (p - p0)||^2
//
// Frame f's residuals depend only on its own block y_f and on the shared parameters p; the
// shared parameters also carry a diagonal prior A and a few dense rows G; each frame may carry a diagonal
// prior B_f. The global body-model fit (frames = time
// steps, y_f = coordinates z_f, p = geometry) and camera bundle adjustment (frames = wand
// poses or points, p = cameras) both have this shape. Residuals come in small row blocks, each
// touching a listed subset of y_f and of p, so Jacobians stay sparse without a general sparse
// matrix type.
#pragma once

#include <Eigen/Core>
#include <algorithm>
#include <cmath>
#include <memory>
#include <vector>

namespace mocap::solver {

constexpr int kMaxBlockRows = 3;

// One block of up to kMaxBlockRows residual rows. Jacobians are column-major with leading
// dimension kMaxBlockRows. A p column index of -1 marks a parameter that is held fixed.
// `kind` is the block's index in ArrowProblem::BlockStructure, whose y and p columns it has
// (the Schur solver's precomputed scatter maps are per kind).
struct ResidualBlock {
  int kind = -1;
  int rows = 0;
  const double* residual = nullptr;
  int num_y = 0;
  const int* y_index = nullptr;
  const double* jy = nullptr;
  int num_p = 0;
  const int* p_index = nullptr;
  const double* jp = nullptr;
};

// Adds one residual block's J_y^T J_y (lower triangle of u, column-major ny x ny, by y index) and
// J_y^T r (g). The common case, three rows and ascending y columns (a marker on its chain), is
// written out: it is the inner loop of every per-frame solve that has no faster assembly
// (FrameEvaluator::PoseNormalEquations).
inline void AddBlockNormalEquations(const ResidualBlock& blk, int ny, double* u, double* g) {
  const int n = blk.num_y;
  const int* y = blk.y_index;
  bool ascending = blk.rows == 3;
  for (int a = 1; a < n && ascending; ++a) ascending = y[a - 1] < y[a];
  if (ascending) {
    const double r0 = blk.residual[0], r1 = blk.residual[1], r2 = blk.residual[2];
    for (int c = 0; c < n; ++c) {
      const double* jc = blk.jy + c * kMaxBlockRows;
      const double j0 = jc[0], j1 = jc[1], j2 = jc[2];
      g[y[c]] += j0 * r0 + j1 * r1 + j2 * r2;
      double* col = u + static_cast<size_t>(y[c]) * ny;
      for (int a = c; a < n; ++a) {
        const double* ja = blk.jy + a * kMaxBlockRows;
        col[y[a]] += j0 * ja[0] + j1 * ja[1] + j2 * ja[2];
      }
    }
    return;
  }
  for (int a = 0; a < n; ++a) {
    const double* ja = blk.jy + a * kMaxBlockRows;
    double ga = 0;
    for (int r = 0; r < blk.rows; ++r) ga += ja[r] * blk.residual[r];
    g[y[a]] += ga;
    for (int c = 0; c <= a; ++c) {
      const double* jc = blk.jy + c * kMaxBlockRows;
      double sum = 0;
      for (int r = 0; r < blk.rows; ++r) sum += ja[r] * jc[r];
      const int hi = std::max(y[a], y[c]), lo = std::min(y[a], y[c]);
      u[static_cast<size_t>(lo) * ny + hi] += sum;
    }
  }
}

// Where a frame's normal-equation entries go in an elimination solver's own storage
// (FrameEvaluator::AddNormalEquations): U's entry of y columns (i, j), either order, at
// u_offset[i * ny + j]; W's entry of y column i and shared column q at w_offset[i * np + q], -1
// where the solver keeps none (no residual block has both).
struct NormalLayout {
  int ny = 0, np = 0;
  const int* u_offset = nullptr;
  const int* w_offset = nullptr;
};

// Evaluates one frame at a time; one per thread, so it may keep scratch space.
class FrameEvaluator {
 public:
  virtual ~FrameEvaluator() = default;
  // Evaluates frame f at y (frame_dim values) and the shared values last given to
  // ArrowProblem::SetShared. Returns false if any residual is not finite.
  virtual bool Evaluate(int frame, const double* y, bool with_jacobians) = 0;
  // As Evaluate with Jacobians, except that only the y Jacobians need be formed (the blocks'
  // jp may be stale): for per-frame solves with the shared parameters held fixed.
  virtual bool EvaluatePoseJacobians(int frame, const double* y) { return Evaluate(frame, y, true); }
  // Frame f's normal equations in its own block at y (the shared values held): J_y^T J_y ADDED to
  // the lower triangle of u (column-major ny x ny, by y index) and J_y^T r to g, over its residual
  // blocks (not its frame prior). False if a residual is not finite. This default sums the blocks
  // of EvaluatePoseJacobians; a problem that knows its Jacobians' structure may assemble them
  // with less work (MarkerFitProblem: from per-segment sums). The blocks are left with the
  // frame's residuals at y, as Evaluate leaves them (EvaluatedFrameSquaredNorm reads them); their
  // Jacobians are unspecified.
  virtual bool PoseNormalEquations(int frame, const double* y, int ny, double* u, double* g) {
    if (!EvaluatePoseJacobians(frame, y)) return false;
    for (int k = 0; k < num_blocks(); ++k) AddBlockNormalEquations(block(k), ny, u, g);
    return true;
  }
  // After Evaluate with Jacobians: ADDS the frame's residual blocks' J_y^T J_y into u, J_y^T J_p
  // into w (both through `layout`), J_y^T r into gy (by y index) and J_p^T r into gp (by shared
  // index), all summed over the blocks as the blocks' own products would be; gy and gp may be
  // null (no gradients wanted). False (nothing added) where the problem has no such assembly: the
  // caller then forms them from the blocks.
  virtual bool AddNormalEquations(const NormalLayout& layout, double* u, double* w, double* gy, double* gp) {
    return false;
  }
  virtual int num_blocks() const = 0;
  virtual const ResidualBlock& block(int i) const = 0;
};

class ArrowProblem {
 public:
  virtual ~ArrowProblem() = default;
  virtual int num_frames() const = 0;
  virtual int frame_dim() const = 0;
  virtual int shared_dim() const = 0;          // free shared parameters
  virtual int num_residuals() const = 0;       // frame rows + prior rows
  // Sets p for the evaluators that follow (not concurrently with Evaluate).
  virtual bool SetShared(const Eigen::VectorXd& p) = 0;
  virtual std::unique_ptr<FrameEvaluator> NewEvaluator() const = 0;
  // Prior rows r_i = weight_i (p_i - target_i); weight 0 means none.
  virtual const Eigen::VectorXd& prior_weight() const = 0;
  virtual const Eigen::VectorXd& prior_target() const = 0;
  // Optional diagonal prior rows on a frame's own block, r_i = weight_i (y_i - target_i): pins
  // what the frame's residuals leave free (a coordinate whose markers are all missing). Both
  // arrays hold frame_dim values; return false for none.
  virtual bool FramePrior(int frame, const double** weight, const double** target) const {
    return false;
  }
  // Moves frame f's block y to an equivalent one (every residual the same) nearest its frame
  // prior's target, if the problem has such symmetries (a joint angle and the same angle a whole
  // turn on). Returns whether y changed; y's cost can only fall. None by default.
  virtual bool WrapFramePose(int frame, double* y) const { return false; }
  // Further rows on the shared parameters alone, r = G (p - target), G dense (few rows): the
  // body fit's gauge constraints. Empty by default.
  virtual const Eigen::MatrixXd& shared_rows() const {
    static const Eigen::MatrixXd kNone;
    return kNone;
  }
  // Every kind of residual block a frame can have, as its y columns and its p columns (-1 =
  // fixed). The Schur solver's symbolic analysis (elimination order, fill, which p columns each
  // eliminated row reaches) is computed once from it, so it must cover every block of every frame.
  virtual void BlockStructure(std::vector<std::vector<int>>* y_columns,
                              std::vector<std::vector<int>>* p_columns) const = 0;
};

// Frame f's own rows at y, from an evaluator that has just evaluated f at y (Evaluate or
// PoseNormalEquations): the sum of squares (not halved) of its blocks' residuals and of its
// frame prior. False if it is not finite. One function for both, so a sum taken after
// PoseNormalEquations is FrameSquaredNorm's to the bit.
inline bool EvaluatedFrameSquaredNorm(const ArrowProblem& problem, const FrameEvaluator& evaluator, int f,
                                      const double* y, double* sum) {
  double s = 0;
  for (int k = 0; k < evaluator.num_blocks(); ++k) {
    const ResidualBlock& b = evaluator.block(k);
    for (int r = 0; r < b.rows; ++r) s += b.residual[r] * b.residual[r];
  }
  const double *w, *target;
  if (problem.FramePrior(f, &w, &target))
    for (int i = 0; i < problem.frame_dim(); ++i) s += (w[i] * (y[i] - target[i])) * (w[i] * (y[i] - target[i]));
  *sum = s;
  return std::isfinite(s);
}

// Frame f's own rows at y, for the shared values last set: the sum of squares (not halved) of
// its residuals and of its frame prior. False if it is not finite.
inline bool FrameSquaredNorm(const ArrowProblem& problem, FrameEvaluator* evaluator, int f,
                             const double* y, double* sum) {
  if (!evaluator->Evaluate(f, y, false)) return false;
  return EvaluatedFrameSquaredNorm(problem, *evaluator, f, y, sum);
}

// ||A (p - p0)||^2 + ||G (p - p0)||^2: the shared parameters' own rows (twice their cost).
inline double SharedRowsSquaredNorm(const ArrowProblem& problem, const Eigen::VectorXd& p) {
  const Eigen::VectorXd delta = p - problem.prior_target();
  double sum = problem.prior_weight().cwiseProduct(delta).squaredNorm();
  const Eigen::MatrixXd& g = problem.shared_rows();
  if (g.rows() > 0) sum += (g * delta).squaredNorm();
  return sum;
}

// The widest residual block of a BlockStructure: its most y columns and most p columns (at least 1).
inline void WidestBlock(const std::vector<std::vector<int>>& y_columns,
                        const std::vector<std::vector<int>>& p_columns, int* max_y, int* max_p) {
  *max_y = *max_p = 1;
  for (size_t b = 0; b < y_columns.size(); ++b) {
    *max_y = std::max<int>(*max_y, static_cast<int>(y_columns[b].size()));
    *max_p = std::max<int>(*max_p, static_cast<int>(p_columns[b].size()));
  }
}

}  // namespace mocap::solver
