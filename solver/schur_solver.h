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
// Structure makes it fast for kinematic trees (all of it found once, symbolically, from
// ArrowProblem::BlockStructure):
//  * U_f has the sparsity of a tree (coordinates couple only along a kinematic chain); eliminated
//    leaves first (minimum degree finds that order), its Cholesky factor L_f has no fill.
//  * With that order, row i of W_f and of Y_f = L_f^{-1} W_f is non-zero only on the shared
//    parameters that move the subtree below coordinate i, and an ancestor's set contains its
//    descendants'. Rows with one pattern form a row group; W_f and Y_f are stored compactly, each
//    group as a dense block over its own columns (a fifth of the dense 38 x 200 matrix for the
//    full body), and the forward substitution runs group by group, a child group's columns
//    subtracted from ours as precomputed runs of consecutive columns (2-10 per child: vector
//    operations, not an indexed scatter); each group's share of the reduced right-hand side is
//    summed over its own columns and scattered once per thread.
//  * S -= Y^T Y is then a sum of one dense outer product per group. Each group's rows are
//    stacked over many frames and applied as one tall rank update (a matrix product near peak
//    speed) into a per-group accumulator, scattered into S once per thread; only the root's rows
//    reach every shared column, and go straight into S.
//  * V = sum_f J_pf^T J_pf does not depend on the damping: it is formed once per linearisation,
//    per residual-block kind, by the same stacked rank updates.
//  * U_f, W_f and the gradients come from the problem itself where it can form them with less
//    work than the blocks' products (FrameEvaluator::AddNormalEquations, through NormalLayout:
//    MarkerFitProblem sums them per segment); V and the cost still come from the blocks.
//  * U_f is factored by a Cholesky that skips L_f's zeros (336 of 703 for the full body).
//  * LM announces the damping of its next solve (AnticipateDamping), so Linearize reduces each
//    frame while its U_f and W_f are hot: an accepted step costs three passes over the frames
//    (cost, linearise + reduce, back-substitute), not four.
// Each frame's U_f, damped factor L_f and compact W_f are cached between the passes when they fit
// in `cache_budget_bytes`, so a step (and a rejected step's re-solve) costs no Jacobian
// evaluation; above the budget nothing per frame is stored and the Jacobian is re-evaluated in
// each pass, so memory stays O(frames x frame_dim). Frames are processed in parallel with
// per-thread accumulators.
#pragma once

#include <Eigen/Cholesky>
#include <Eigen/Core>
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include "solver/arrow_problem.h"
#include "solver/levenberg_marquardt.h"

namespace mocap::solver {

class ArrowSchurProblem : public LmProblem {
 public:
  // Holds 60,000 frames of the full body (24 KB a frame, 1.44 GB; peak RSS of the benchmark's
  // whole 60,000-frame fit 1.82 GB, within the 2 GB). Without the cache every pass
  // re-evaluates the Jacobian: the back-substitution then costs 30 us a frame instead of 3.5.
  static constexpr double kDefaultCacheBudgetBytes = 1.5 * (1 << 30);
  ArrowSchurProblem(ArrowProblem* problem, int num_threads,
                    double cache_budget_bytes = kDefaultCacheBudgetBytes);
  bool caches_frames() const { return cached_; }
  // The threads its passes use (Cost sums the frames' costs in their chunks).
  int num_threads() const { return num_threads_; }
  // Passes SolveDamped made to form the reduced system (0 while Linearize anticipated them).
  int reduction_passes() const { return reduction_passes_; }
  // The symbolic structure: row groups in elimination order, how many shared columns each reaches.
  std::string DescribeStructure() const;
  ~ArrowSchurProblem() override;

  int num_parameters() const override;
  int num_residuals() const override;
  bool Cost(const Eigen::VectorXd& x, double* cost) override;
  bool Linearize(const Eigen::VectorXd& x, double* cost, Eigen::VectorXd* gradient,
                 Eigen::VectorXd* jtj_diagonal) override;
  bool SolveDamped(const Eigen::VectorXd& damping, Eigen::VectorXd* dx) override;
  double LastSharedStepMahalanobisSq() const override { return last_shared_step_sq_; }
  // Linearize then also forms the reduced system for this damping (one pass over the frames
  // fewer per iteration); SolveDamped uses it when asked for exactly that damping.
  void AnticipateDamping(double lambda, double min_diagonal, double max_diagonal) override {
    anticipated_lambda_ = lambda;
    anticipated_min_ = min_diagonal;
    anticipated_max_ = max_diagonal;
  }

  // Geodesic acceleration (LmProblem::SolveAcceleration): two passes over the frames, then the
  // reduced system's factor of the last SolveDamped once more. (1) Residuals at x + h v, with p + h
  // v_p set on the problem (SetShared is global, so this pass cannot be fused with the next).
  // (2) At x, with Jacobians: per residual block r_vv = (2 / h) ((r(x + h v) - r(x)) / h - J v)
  // (blocks matched by kind: a coordinate-limit block that exists at only one of the two points is
  // zero at the other), J_y^T r_vv and J_p^T r_vv, and while the frame is hot its share of the
  // reduced right-hand side W_f^T U_f^-1 (J_y^T r_vv) from the cached factor. Then dp from the kept
  // Cholesky of S and the frames' back-substitution as in SolveDamped. About a linearisation's
  // Jacobian evaluations and one back-substitution; no new factorisation. Needs the per-frame cache
  // (false without it) and `damping` equal to the last SolveDamped's since the last Linearize.
  bool SolveAcceleration(const Eigen::VectorXd& damping, const Eigen::VectorXd& velocity, double h,
                         Eigen::VectorXd* acceleration) override;

  // Covariance of the shared parameters at x, (S^{-1} with no damping on p), in the units of the
  // residuals. Frame blocks that the data leave singular get a ridge of `frame_ridge` relative
  // to their diagonal. False if S is not positive definite.
  bool SharedCovariance(const Eigen::VectorXd& x, Eigen::MatrixXd* covariance,
                        double frame_ridge = 1e-10);

  // Each frame's sum of squares (FrameSquaredNorm) at the x of the last Cost call, kept for a
  // per-frame pass that follows it (coarse_to_fine.h's inner iterations).
  const std::vector<double>& frame_costs() const { return frame_costs_; }

  // Options of the coarse-to-fine fine stage (CoarseToFineOptions::fine_secant_curvature and
  // fine_reduced_damping, measured there; on by default there); off here unless set.
  // A secant model of what Gauss-Newton drops from the reduced system (UpdateSecant): E, updated
  // at the first SolveDamped after each Linearize from how the reduced gradient changed over the
  // last step, is added to S before it is factored. The statistical stop's step length
  // (LastSharedStepMahalanobisSq) stays in S's metric without E. Turning it on forgets E and
  // restarts secant_updates(), the number of updates made since.
  void SetSecantCurvature(bool on) {
    secant_ = on;
    secant_e_.resize(0, 0);
    secant_have_last_ = false;
    if (on) secant_updates_ = 0;
  }
  int secant_updates() const { return secant_updates_; }
  // Marquardt's scaling on the reduced system: Linearize reports as the shared parameters'
  // diagonal that of S (at the anticipated damping of the frames, plus E's) instead of
  // J_p^T J_p's, so LM damps each shared parameter by what the data know about it once the poses
  // are eliminated. Needs the anticipated damping (AnticipateDamping), else J_p^T J_p's is kept.
  void SetReducedDamping(bool on) { reduced_damping_ = on; }

  // Per-frame squared residual sums at x (for per-marker statistics the problem computes itself).
  const std::vector<int>& elimination_order() const { return order_; }

 private:
  struct ThreadState;
  // A run of rows (elimination order) with one pattern of reached shared columns.
  struct RowGroup {
    int first_row, num_rows;
    std::vector<int> columns;   // shared columns reached, sorted
    bool full;                  // reaches every shared column (the root): columns == 0..np-1
    bool contiguous;            // columns == [columns.front(), columns.back()]
    int offset;                 // of its block (num_rows x columns.size(), row-major) in W_f, Y_f
    struct Run {
      int from, to, length;     // the child's columns from..from+length-1 are ours to..
    };
    struct Child {
      int group;
      std::vector<Run> runs;    // where the child's columns sit among ours (2-10 runs each)
    };
    std::vector<Child> children;  // earlier groups with a non-zero block of L_f in our rows
  };
  // One row r of a group against one earlier group h it is eliminated against: the row's
  // entries of L_f in h's rows (offsets into the column-major ny x ny factor), and the runs of
  // h's columns among ours. ReduceFrame runs these as a flat list: per row, each run's
  // elements get sum_q l_q Y_h(q, ·) subtracted in one pass, with no dense temporary over h's
  // columns and no per-row search for non-zeros (they are known from L_f's pattern).
  struct ChildRow {
    int group, child, row;     // row: within `group`
    int first_l, num_l;        // in child_l_: (L_f offset, child row) pairs
    int first_run, num_runs;   // in child_runs_
  };
  // Where one residual-block kind's products go.
  struct BlockKind {
    int num_y = 0;
    std::vector<int> y_order;     // block y columns, latest-eliminated first
    std::vector<int> y_position;  // their elimination positions (descending)
    std::vector<int> free_local;  // block columns with a free shared parameter
    std::vector<int> free_p;      // their shared indices
    std::vector<int> w_offset;    // num_y x free: offset in compact W (-1 none), row-major
  };
  void Analyse();
  bool AccumulateFrame(ThreadState& ts, bool linearizing) const;
  void BeginReduction(ThreadState& ts) const;
  void ReduceFrame(ThreadState& ts, int f);
  void EndReduction(ThreadState& ts) const;
  bool FinishReducedSystem(const Eigen::VectorXd& damping_p, Eigen::MatrixXd* s,
                           Eigen::VectorXd* rhs) const;
  void FlushV(ThreadState& ts, int kind) const;
  void FlushGroup(ThreadState& ts, int group) const;
  void AddFramePrior(int f, Eigen::MatrixXd* u) const;
  bool LoadFrame(ThreadState& ts, int f, const Eigen::VectorXd& damping);
  double* CachedU(int f) { return u_cache_->get() + static_cast<size_t>(f) * u_pattern_.size(); }
  double* CachedL(int f) { return l_cache_->get() + static_cast<size_t>(f) * u_pattern_.size(); }
  bool FactorInPlace(Eigen::MatrixXd* a) const;
  void SolveLower(const Eigen::MatrixXd& l, Eigen::VectorXd* v) const;
  void SolveLowerTransposed(const Eigen::MatrixXd& l, Eigen::VectorXd* v) const;
  double* CachedW(int f) { return w_cache_->get() + static_cast<size_t>(f) * w_size_; }
  // Accumulates S (lower triangle) and the reduced right-hand side over all frames.
  bool FormReducedSystem(const Eigen::VectorXd& damping, Eigen::MatrixXd* s, Eigen::VectorXd* rhs);
  // dx_f = -U_f^{-1} (b_f + W_f dp) for every frame, b = `gradient` (the frames' part), with the
  // factors of `damping` (cached, or re-formed without the cache); dx's tail is left as it is.
  bool BackSubstitute(const Eigen::VectorXd& damping, const Eigen::VectorXd& gradient, const Eigen::VectorXd& dp,
                      Eigen::VectorXd* dx);

  ArrowProblem* problem_;
  int num_threads_;
  int nf_, ny_, np_;
  int max_block_y_ = 1, max_block_p_ = 1;  // widest residual block (from BlockStructure)
  std::vector<int> order_;     // elimination order: position -> y index
  std::vector<int> position_;  // y index -> position
  std::vector<std::vector<int>> l_rows_;  // rows below the diagonal of each column of L_f
  std::vector<std::vector<int>> l_cols_;  // columns left of the diagonal of each row of L_f (ascending)
  std::vector<int> u_pattern_;            // offsets of L_f's pattern in a column-major ny x ny
  std::vector<RowGroup> groups_;
  std::vector<ChildRow> child_rows_;       // in group order, then child, then row
  std::vector<std::pair<int, int>> child_l_;
  std::vector<RowGroup::Run> child_runs_;
  std::vector<BlockKind> kinds_;
  int w_size_ = 0;             // doubles in a compact W_f
  std::vector<int> u_index_, w_index_;  // U_f's and compact W_f's offsets by (y, y) and (y, p)
  NormalLayout layout_;
  std::vector<std::unique_ptr<ThreadState>> threads_;
  Eigen::VectorXd x_, gradient_;
  bool cached_ = false;
  // Per frame: U_f and the last damped factor L_f (their pattern, packed), and compact W_f.
  // Left uninitialised (every frame's entries are written by Linearize before any read): zero-
  // filling 144 MB at 6,000 frames took 0.1 s of a 1 s fit, single-threaded. Anonymous mappings
  // whose pages each thread has the kernel populate for its own frames in one call
  // (MADV_POPULATE_WRITE, Linux >= 5.14; elsewhere the pages fault in on first write): faulted in
  // one at a time by the first linearisation, the 43,000 pages of 6,000 full-body frames cost
  // about 0.1 s of the solve's CPU in page faults (BENCHMARKS.md, "With gaps", twenty-fourth
  // session).
  struct CacheArray {
    double* data = nullptr;
    size_t bytes = 0;
    CacheArray() = default;
    explicit CacheArray(size_t doubles);
    CacheArray(const CacheArray&) = delete;
    CacheArray& operator=(const CacheArray&) = delete;
    ~CacheArray();
    double* get() const { return data; }
  };
  void PopulateCaches();
  std::unique_ptr<CacheArray> u_cache_, l_cache_, w_cache_;
  std::vector<double> frame_costs_;        // of the last Cost call
  Eigen::MatrixXd v_total_;                // sum of V_f (lower) at the linearisation point
  double anticipated_lambda_ = 0, anticipated_min_ = 0, anticipated_max_ = 0;
  bool anticipated_ready_ = false;
  int reduction_passes_ = 0;
  Eigen::VectorXd anticipated_damping_, anticipated_rhs_;
  Eigen::MatrixXd anticipated_s_;
  // The last SolveDamped's damping and Cholesky factor of S, for SolveAcceleration; valid until
  // the next Linearize. shifted_residuals_: per frame, (kind, r0, r1, r2) per block at x + h v.
  double last_shared_step_sq_ = std::numeric_limits<double>::quiet_NaN();  // dp^T S dp
  bool damped_solve_ready_ = false;
  Eigen::VectorXd solved_damping_;
  Eigen::LLT<Eigen::MatrixXd> s_factor_;
  std::vector<std::vector<double>> shifted_residuals_;
  bool fresh_linearization_ = false;
  bool reduced_damping_ = false;
  bool secant_ = false, secant_have_last_ = false;
  int secant_updates_ = 0;
  Eigen::MatrixXd secant_e_;
  Eigen::VectorXd secant_p_, secant_g_;
  void UpdateSecant(const Eigen::MatrixXd& s, const Eigen::VectorXd& rhs, const Eigen::VectorXd& damping_p);
};

}  // namespace mocap::solver
