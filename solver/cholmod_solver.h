// Levenberg–Marquardt linear algebra for arrow-structured problems (solver/arrow_problem.h) by a
// sparse Cholesky factorisation of the WHOLE damped normal matrix with CHOLMOD:
//
//     (J^T J + diag(damping)) dx = -J^T r,   x = [y_1 ... y_F, p],
//
// J = all frames' residual blocks, the prior rows diag(prior_weight) and the dense gauge rows
// shared_rows() (the same rows, in the same units, as ArrowSchurProblem). It solves the same
// equations as the per-frame Schur elimination of solver/schur_solver.h, by the general-purpose
// route: a supernodal sparse Cholesky (Y. Chen, T. A. Davis, W. W. Hager, S. Rajamanickam,
// "Algorithm 887: CHOLMOD, Supernodal Sparse Cholesky Factorization and Update/Downdate",
// ACM Trans. Math. Softw. 35(3), 2008), whose supernodes are dense blocks factored with BLAS.
// Why have it: it is the reference implementation of the step (no hand-written elimination
// order, fill or update pattern to trust) and the baseline the Schur solver is measured against
// (bench/schur_vs_cholmod.cpp).
//
// Fixed pattern, one symbolic analysis. Frames with missing markers have fewer residual blocks,
// so the pattern is built once:
//  * kNormalMatrix: the pattern of J^T J from ArrowProblem::BlockStructure (every block kind in
//    every frame; entries a frame does not have stay zero), so the analysis runs in the
//    constructor. Each linearisation assembles J^T J itself, frames in parallel, each frame
//    writing only its own entries; V = J_p^T J_p + A^T A + G^T G is reduced over threads. A solve
//    writes J^T J's diagonal plus the damping into the matrix's diagonal entries and factors.
//  * kJacobian / kJacobianProduct: J^T as a sparse matrix, pattern from the blocks each frame
//    actually has at the first linearisation (checked at every later one; a frame whose blocks
//    change triggers a new analysis). kJacobian appends one column sqrt(damping_i) e_i per
//    unknown and hands J^T to cholmod_factorize_p, which forms J^T J + D inside every
//    factorisation; kJacobianProduct forms J^T J once per linearisation with cholmod_aat.
// Every SolveDamped is then only cholmod_factorize_p (numeric) and cholmod_solve.
//
// Orderings (cholmod_analyze / cholmod_analyze_p, once per problem):
//  * kFramesFirst: every frame's unknowns in one order (CAMD on one frame's pattern with the
//    frame's unknowns constrained before p, then CHOLMOD's postorder), frames one after another,
//    p last: each frame's tree-structured block factors without fill and only its rows reach p,
//    exactly the Schur elimination's order. The matrix is STORED in that order (lower triangle),
//    so CHOLMOD factors it with its natural ordering and copies nothing.
//  * kFramesFirstGiven: the same order as a user permutation (cholmod_analyze_p) on the matrix
//    stored in variable order (upper triangle); each factorisation first permutes a copy.
//  * kCholmod: CHOLMOD's own choice (AMD, METIS if AMD fills badly), postordered.
//
// Measured (bench/schur_vs_cholmod: default protocol, 38 coordinates per frame, 202 shared
// parameters; 2 cores shared with other jobs, so wall times vary by +-30 %):
//  * Choices, 6000 frames, per factorisation: kNormalMatrix + kFramesFirst 0.63 s (the
//    defaults); the same order through cholmod_analyze_p 1.17 s (a permuted copy of A per
//    factorisation); CHOLMOD's own choice (AMD) 1.14 s, with 1.5x nnz(L) and 1.9x the flops;
//    kJacobian 2.2 s (J^T J formed inside every factorisation); kJacobianProduct factors like the
//    default but spends 4 s per linearisation in cholmod_aat.
//  * Against ArrowSchurProblem: the same iterations and final cost (13 digits). With one core
//    about equally fast: both eliminate the frames in the same order with about the same flops
//    (3.5 GFlop per step at 6000 frames); CHOLMOD's supernodes skip the shared columns a subtree
//    does not reach, which the Schur solver's dense L_f^-1 W_f does not, but it pays a rank-6
//    update and scatter into the shared block per frame where the Schur solver batches 64 frames.
//    When it gets both cores the Schur solver is ~1.6x faster (1000 frames 2.0 vs 3.2 s, 6000
//    frames 6.3 vs 9.8 s): CHOLMOD 3's numeric factorisation (over half of the time) is
//    sequential — its BLAS calls are too small to split — while the Schur elimination and the
//    assembly run frame-parallel. At 60,000 frames: Schur 108 s and
//    230 MB (no frame cache), CHOLMOD 192 s and 5.4 GB.
// Threads: frames are evaluated and assembled on `num_threads` threads; the factorisation runs
// on the calling thread with `Options::blas_threads` OpenBLAS threads (1: the supernodes are far
// too small for threaded BLAS, 2 threads measured 40 % slower) and CHOLMOD's OpenMP loops
// disabled (see cholmod_solver.cpp); both settings are restored after each factorisation.
// Memory: J^T J (each frame's ~2,900 entries) plus the factor (~4,150 entries per frame), about
// 90 MB per 1000 frames — against the Schur solver's 73 MB per 1000 frames of optional cache.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "solver/arrow_problem.h"
#include "solver/levenberg_marquardt.h"

namespace mocap::solver {

class SparseNormalCholeskyProblem : public LmProblem {
 public:
  enum class Assembly { kNormalMatrix, kJacobian, kJacobianProduct };
  enum class Ordering { kFramesFirst, kFramesFirstGiven, kCholmod };
  struct Options {
    Assembly assembly = Assembly::kNormalMatrix;
    Ordering ordering = Ordering::kFramesFirst;
    int blas_threads = 1;  // OpenBLAS threads in the factorisation; 0: num_threads
  };
  struct Statistics {
    int analyses = 0;
    int factorizations = 0;
    double analyse_seconds = 0;     // ordering + symbolic factorisation
    double assemble_seconds = 0;    // Linearize: evaluation, matrix values (and cholmod_aat)
    double factorize_seconds = 0;   // cholmod_factorize_p
    double solve_seconds = 0;       // cholmod_solve
    std::int64_t matrix_nonzeros = 0;  // stored entries of J^T J (triangle) or of J^T
    double factor_nonzeros = 0;        // nnz(L), from the analysis
    double factor_flops = 0;           // flops of one numeric factorisation, from the analysis
    std::string ordering_used;         // natural / given / amd / metis / nesdis / ...
  };

  static const char* ToString(Assembly assembly);
  static const char* ToString(Ordering ordering);
  static bool Parse(const std::string& name, Assembly* assembly);
  static bool Parse(const std::string& name, Ordering* ordering);

  SparseNormalCholeskyProblem(ArrowProblem* problem, int num_threads, Options options);
  SparseNormalCholeskyProblem(ArrowProblem* problem, int num_threads)
      : SparseNormalCholeskyProblem(problem, num_threads, Options()) {}
  ~SparseNormalCholeskyProblem() override;
  SparseNormalCholeskyProblem(const SparseNormalCholeskyProblem&) = delete;
  SparseNormalCholeskyProblem& operator=(const SparseNormalCholeskyProblem&) = delete;

  int num_parameters() const override;
  int num_residuals() const override;
  bool Cost(const Eigen::VectorXd& x, double* cost) override;
  bool Linearize(const Eigen::VectorXd& x, double* cost, Eigen::VectorXd* gradient,
                 Eigen::VectorXd* jtj_diagonal) override;
  bool SolveDamped(const Eigen::VectorXd& damping, Eigen::VectorXd* dx) override;

  const Options& options() const { return options_; }
  const Statistics& statistics() const { return stats_; }
  // False with a message if CHOLMOD could not analyse the problem (e.g. out of memory); every
  // Linearize then fails.
  bool ok() const { return error_.empty(); }
  const std::string& error() const { return error_; }

 private:
  struct Impl;
  struct ThreadState;
  struct BlockKind;
  void ComputeFrameOrder();
  void BuildNormalPattern();
  bool BuildJacobianPattern(const Eigen::VectorXd& x);
  bool Analyse(void* matrix);
  bool LinearizeNormal(const Eigen::VectorXd& x, double* cost, Eigen::VectorXd* gradient,
                       Eigen::VectorXd* diagonal);
  bool LinearizeJacobian(const Eigen::VectorXd& x, double* cost, Eigen::VectorXd* gradient,
                         Eigen::VectorXd* diagonal, bool* mismatch);
  void AddSharedRows(const Eigen::VectorXd& p, Eigen::VectorXd* gradient) const;
  double SharedRowsSquaredNorm(const Eigen::VectorXd& p) const;
  bool StoreLower() const;

  ArrowProblem* problem_;
  int num_threads_;
  Options options_;
  int nf_, ny_, np_;
  std::int64_t n_;
  std::unique_ptr<Impl> impl_;
  std::vector<std::unique_ptr<ThreadState>> threads_;
  Statistics stats_;
  std::string error_;

  // Frames-first elimination order of one frame's y and of p (position -> index).
  std::vector<int> y_elimination_, p_elimination_;
  // Storage order of the matrix rows/columns: frame f's unknown y sits at f * ny + local_[y],
  // shared p at F * ny + ppos_[p]; y_order_ / p_order_ are the inverse maps. The elimination
  // order with kFramesFirst, the identity otherwise.
  std::vector<int> local_, ppos_, y_order_, p_order_;
  int max_block_y_ = 1, max_block_p_ = 1;

  // kNormalMatrix: positions of the entries in the values array. U entry (storage positions
  // hi >= lo of one frame) at f * ustride_ + ulut_[hi * ny + lo]; W entry (local k, shared q) at
  // wbase_[q] + f * wstride_[q] + wlut_[k * np + q]; V entry (hi >= lo) at vlut_[hi * np + lo].
  std::int64_t ustride_ = 0;
  std::vector<std::int64_t> ulut_, wlut_, wbase_, wstride_, vlut_;

  // kJacobian*: block kinds (distinct index patterns) and, per frame, its blocks' kinds.
  std::vector<BlockKind> kinds_;
  std::vector<std::int64_t> frame_kind_begin_;  // nf + 1 offsets into frame_kinds_
  std::vector<int> frame_kinds_;
  std::vector<std::int64_t> frame_entry_begin_;  // first entry of each frame's columns in J^T
  std::int64_t prior_column_ = 0, damping_column_ = 0;  // first prior / damping column of J^T
  bool jacobian_pattern_ = false;

  std::vector<std::int64_t> diagonal_position_;  // per storage index, into the factored matrix
  Eigen::VectorXd undamped_diagonal_;            // J^T J's diagonal, storage order
  Eigen::VectorXd gradient_;  // original order
};

}  // namespace mocap::solver
