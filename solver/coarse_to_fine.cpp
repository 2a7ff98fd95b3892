#include "solver/coarse_to_fine.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <limits>
#include <vector>
#if defined(__AVX512F__)
#include <immintrin.h>
#endif

#include <Eigen/Cholesky>

#include "solver/parallel.h"

namespace mocap::solver {
namespace {
using Clock = std::chrono::steady_clock;
double Since(Clock::time_point t) { return std::chrono::duration<double>(Clock::now() - t).count(); }
double ProcessCpuSeconds() {
  timespec t{};
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &t);
  return t.tv_sec + 1e-9 * t.tv_nsec;
}

class SubsetEvaluator : public FrameEvaluator {
 public:
  SubsetEvaluator(std::unique_ptr<FrameEvaluator> inner, const std::vector<int>* frames)
      : inner_(std::move(inner)), frames_(frames) {}
  bool Evaluate(int frame, const double* y, bool with_jacobians) override {
    return inner_->Evaluate((*frames_)[frame], y, with_jacobians);
  }
  bool EvaluatePoseJacobians(int frame, const double* y) override {
    return inner_->EvaluatePoseJacobians((*frames_)[frame], y);
  }
  // The problem's own assemblies (MarkerFitProblem: from per-segment sums), as on every frame.
  bool PoseNormalEquations(int frame, const double* y, int ny, double* u, double* g) override {
    return inner_->PoseNormalEquations((*frames_)[frame], y, ny, u, g);
  }
  bool AddNormalEquations(const NormalLayout& layout, double* u, double* w, double* gy, double* gp) override {
    return inner_->AddNormalEquations(layout, u, w, gy, gp);
  }
  int num_blocks() const override { return inner_->num_blocks(); }
  const ResidualBlock& block(int i) const override { return inner_->block(i); }

 private:
  std::unique_ptr<FrameEvaluator> inner_;
  const std::vector<int>* frames_;
};

// ArrowProblem::WrapFramePose on every frame of x; how many moved.
int WrapFramePoses(const ArrowProblem& problem, int num_threads, Eigen::VectorXd* x) {
  const int nf = problem.num_frames(), ny = problem.frame_dim();
  const int threads = std::max(1, std::min(num_threads, nf));
  std::vector<int> moved(threads, 0);
  ParallelChunks(nf, threads, [&](int t, int b, int e) {
    for (int f = b; f < e; ++f) moved[t] += problem.WrapFramePose(f, x->data() + static_cast<size_t>(f) * ny) ? 1 : 0;
  });
  int total = 0;
  for (int m : moved) total += m;
  return total;
}

// Stage 3's problem: the whole problem's Schur solver, with every frame's pose re-solved for the
// new geometry after each accepted step (LmProblem::InnerIteration). Near the minimum, LM's
// step leaves most of its shortfall in the weakly seen coordinates (a wrist's deviation, a
// subtalar angle) that follow the weakly determined axes nonlinearly. Each frame takes
// Gauss–Newton steps (each kept only if it lowers the frame's cost) until a step gains no more
// than the whole problem's function tolerance would let LM stop on (function_tolerance times
// the cost), at most inner_pose_iterations: a well-seen frame stops after one step, for about a
// third of a linearisation's cost in all, while a frame far from its own minimum (a weakly seen
// subtalar angle in a marker gap, its cost far from quadratic) is taken there now instead of by
// one whole-problem linearisation after another (measured: BENCHMARKS.md, "With gaps").
class WithInnerIterations : public LmProblem {
 public:
  WithInnerIterations(ArrowSchurProblem* whole, ArrowProblem* problem, const CoarseToFineOptions& options,
                      int num_threads, bool refine_poses, double function_tolerance)
      : whole_(whole), problem_(problem), options_(options), num_threads_(num_threads),
        refine_poses_(refine_poses), function_tolerance_(function_tolerance) {
    options_.pose_iterations = options.inner_pose_iterations;
    options_.pose_from_predecessor = false;
  }
  int num_parameters() const override { return whole_->num_parameters(); }
  int num_residuals() const override { return whole_->num_residuals(); }
  // The Schur solver's cost pass keeps each frame's share: the inner iteration that follows an
  // accepted step starts from them instead of re-evaluating.
  bool Cost(const Eigen::VectorXd& x, double* cost) override {
    if (project_ && refine_poses_ && !options_.wrap_frame_turns && options_.pose_iterations >= 1) {
      // The cost pass fused with the re-solve's first steps (ProjectedCost): the same figures.
      double refined = std::numeric_limits<double>::infinity();
      int rescued = 0;
      if (!ProjectedCost(problem_, options_, num_threads_, whole_->num_threads(), x, function_tolerance_, cost,
                         &projected_, &refined, &rescued))
        return false;
      rescued_ += rescued;
      last_cost_ = *cost;
      projected_at_ = Fingerprint(x);
      costs_at_ = 0;
      if (refined < *cost) *cost = refined;
      else projected_ = x;
      return true;
    }
    if (!whole_->Cost(x, cost)) return false;
    costs_at_ = Fingerprint(x);
    last_cost_ = *cost;
    if (project_ && refine_poses_) {
      // The candidate judged with every pose re-solved for its geometry (variable projection).
      projected_ = x;
      double refined = std::numeric_limits<double>::infinity();
      Refine(&projected_, *cost, &refined);
      projected_at_ = costs_at_;
      if (refined < *cost) *cost = refined;
      else projected_ = x;
      costs_at_ = 0;
    }
    return true;
  }
  void SetProject(bool on) { project_ = on; }
  bool Linearize(const Eigen::VectorXd& x, double* cost, Eigen::VectorXd* gradient,
                 Eigen::VectorXd* jtj_diagonal) override {
    return whole_->Linearize(x, cost, gradient, jtj_diagonal);
  }
  bool SolveDamped(const Eigen::VectorXd& damping, Eigen::VectorXd* dx) override {
    return whole_->SolveDamped(damping, dx);
  }
  void AnticipateDamping(double lambda, double min_diagonal, double max_diagonal) override {
    whole_->AnticipateDamping(lambda, min_diagonal, max_diagonal);
  }
  // Without it the base class's NaN reached LM, and the final stage's statistical stop
  // (LmOptions::shared_step_tolerance) never fired in this, its usual, path.
  double LastSharedStepMahalanobisSq() const override { return whole_->LastSharedStepMahalanobisSq(); }
  bool SolveAcceleration(const Eigen::VectorXd& damping, const Eigen::VectorXd& velocity, double h,
                         Eigen::VectorXd* acceleration) override {
    return whole_->SolveAcceleration(damping, velocity, h, acceleration);
  }
  // The accepted candidate's projected poses (Cost) replace its extrapolated ones, also when the
  // step ends the solve: x then has the cost LM reports.
  void StepAccepted(Eigen::VectorXd* x) override {
    if (!(project_ && refine_poses_)) return;
    if (projected_at_ == Fingerprint(*x)) x->swap(projected_);
    projected_at_ = 0;
  }
  void InnerIteration(Eigen::VectorXd* x) override {
    if (project_ && refine_poses_) return;  // StepAccepted did it
    Refine(x, last_cost_);
  }
  void Refine(Eigen::VectorXd* x, double cost_at_x, double* refined_cost = nullptr) {
    candidate_ = *x;
    bool ok = false;
    // LM has just evaluated the cost at this very x (the accepted step).
    costs_.clear();
    if (costs_at_ == Fingerprint(*x)) costs_ = whole_->frame_costs();
    // Angles a whole turn from their targets back to the target's turn (ArrowProblem::
    // WrapFramePose): the data do not change, the frame prior falls.
    if (options_.wrap_frame_turns && WrapFramePoses(*problem_, num_threads_, &candidate_) > 0) costs_.clear();
    // Frames that the step left in a wrong branch first (their cost far above the others'),
    // then Gauss–Newton steps for every pose; each frame's cost only falls, p is unchanged.
    rescued_ += RescueFramesFromNeighbours(problem_, options_, num_threads_, &candidate_, &costs_);
    if (!refine_poses_) {
      x->swap(candidate_);
      return;
    }
    // Frame costs are sums of squares: twice the cost's share.
    const double min_gain = 2.0 * function_tolerance_ * cost_at_x;
    RefineFramePoses(problem_, options_, num_threads_, &candidate_, &ok, refined_cost,
                     static_cast<int>(costs_.size()) == problem_->num_frames() ? costs_.data() : nullptr, min_gain);
    if (ok) x->swap(candidate_);
    else if (refined_cost) *refined_cost = std::numeric_limits<double>::infinity();
  }
  int rescued() const { return rescued_; }

 private:
  ArrowSchurProblem* whole_;
  ArrowProblem* problem_;
  CoarseToFineOptions options_;
  // Which x the frame costs belong to: a 64-bit FNV-1a hash of its bits and its size (a copy of
  // x would cost 18 MB at 60,000 frames).
  static std::uint64_t Fingerprint(const Eigen::VectorXd& x) {
    std::uint64_t h = 1469598103934665603ull ^ static_cast<std::uint64_t>(x.size());
    for (Eigen::Index i = 0; i < x.size(); ++i) {
      std::uint64_t bits;
      std::memcpy(&bits, x.data() + i, sizeof bits);
      h = (h ^ bits) * 1099511628211ull;
    }
    return h;
  }
  int num_threads_;
  bool refine_poses_;
  double function_tolerance_;
  double last_cost_ = 0;
  int rescued_ = 0;
  std::vector<double> costs_;
  Eigen::VectorXd candidate_;
  std::uint64_t costs_at_ = 0;
  bool project_ = false;
  Eigen::VectorXd projected_;
  std::uint64_t projected_at_ = 0;
};

// y[i] -= a x[i], i < n: each entry one fused multiply-subtract, as the plain loop's scalar code
// has it, so the vectorised loop gives the same bits (the fit's iterations with gaps answer
// last-bit changes like chance: BENCHMARKS.md, "With gaps"). The compiler leaves the plain loop
// scalar (y and x may overlap, for all it knows): a frame's factorisation ran at one entry a cycle.
inline void SubtractScaled(double* y, const double* x, double a, int n) {
  int i = 0;
#if defined(__AVX512F__)
  const __m512d va = _mm512_set1_pd(a);
  for (; i + 8 <= n; i += 8)
    _mm512_storeu_pd(y + i, _mm512_fnmadd_pd(va, _mm512_loadu_pd(x + i), _mm512_loadu_pd(y + i)));
  if (i < n) {
    const __mmask8 m = static_cast<__mmask8>((1u << (n - i)) - 1);
    _mm512_mask_storeu_pd(y + i, m,
                          _mm512_fnmadd_pd(va, _mm512_maskz_loadu_pd(m, x + i), _mm512_maskz_loadu_pd(m, y + i)));
  }
#else
  for (; i < n; ++i) y[i] -= a * x[i];
#endif
}

// In-place Cholesky of a small dense SPD matrix (lower triangle, column-major, n x n), then
// the solve with it. Written out rather than Eigen's LLT because at the frame's size (38) Eigen
// takes its blocked path (panels of 16, packed GEMM updates) and spends more in the packing than
// in the 9,000 multiply-adds; this left-looking loop runs down contiguous columns. It also lists
// each column's non-zero rows below the diagonal (ascending, column k's at rows[k * n], count[k]
// of them), for the back-substitution (CholeskySolveInPlace).
bool CholeskyInPlace(double* a, int n, int* rows, int* count, int* row_nonzeros) {
  std::fill(count, count + n, 0);
  for (int j = 0; j < n; ++j) {
    double* cj = a + static_cast<size_t>(j) * n;
    // Row j's non-zeros: the columns that update this one (no coupling: skipping it changes no figure).
    int nk = 0;
    for (int k = 0; k < j; ++k)
      if (a[static_cast<size_t>(k) * n + j] != 0.0) {
        row_nonzeros[nk++] = k;
        rows[static_cast<size_t>(k) * n + count[k]++] = j;
      }
#if defined(__AVX512F__)
    // Eight rows at a time, every update applied in a register before one store: each entry gets
    // the same fused multiply-subtracts in the same order as the plain loop over k (the same
    // bits), without a masked store's result read back by the next update (no store forwarding).
    for (int e = j; e < n; e += 8) {
      const __mmask8 m = n - e >= 8 ? static_cast<__mmask8>(0xff) : static_cast<__mmask8>((1u << (n - e)) - 1);
      __m512d acc = _mm512_maskz_loadu_pd(m, cj + e);
      for (int t = 0; t < nk; ++t) {
        const double* ck = a + static_cast<size_t>(row_nonzeros[t]) * n;
        acc = _mm512_fnmadd_pd(_mm512_set1_pd(ck[j]), _mm512_maskz_loadu_pd(m, ck + e), acc);
      }
      _mm512_mask_storeu_pd(cj + e, m, acc);
    }
#else
    for (int t = 0; t < nk; ++t) {
      const double* ck = a + static_cast<size_t>(row_nonzeros[t]) * n;
      SubtractScaled(cj + j, ck + j, ck[j], n - j);
    }
#endif
    if (!(cj[j] > 0)) return false;
    const double d = std::sqrt(cj[j]);
    cj[j] = d;
    const double inv = 1.0 / d;
    for (int i = j + 1; i < n; ++i) cj[i] *= inv;
  }
  return true;
}

// Solves L L^T x = b in place, L, rows and count from CholeskyInPlace. The back-substitution's
// sums skip L's zeros (a kinematic tree's factor, leaves first, is half zeros): each is a chain
// of dependent multiply-adds, so its length is its time; a zero term changes no sum.
void CholeskySolveInPlace(const double* l, int n, const int* rows, const int* count, double* b) {
  for (int j = 0; j < n; ++j) {
    const double* cj = l + static_cast<size_t>(j) * n;
    b[j] /= cj[j];
    SubtractScaled(b + j + 1, cj + j + 1, b[j], n - j - 1);
  }
  for (int j = n - 1; j >= 0; --j) {
    const double* cj = l + static_cast<size_t>(j) * n;
    const int* r = rows + static_cast<size_t>(j) * n;
    double sum = b[j];
    for (int t = 0; t < count[j]; ++t) sum -= cj[r[t]] * b[r[t]];
    b[j] = sum / cj[j];
  }
}

// A thread's scratch for FramePoseSteps, allocated once: the hot loop allocates nothing.
struct PoseStepWorkspace {
  explicit PoseStepWorkspace(int ny)
      : u(ny, ny), factor(ny, ny), g(ny), step(ny), rows(static_cast<size_t>(ny) * ny), count(ny), row_nonzeros(ny) {}
  Eigen::MatrixXd u, factor;  // the normal equations; their damped, reversed factor
  Eigen::VectorXd g, step;
  std::vector<int> rows, count, row_nonzeros;  // the factor's non-zeros (CholeskyInPlace)
};

// Up to `iterations` damped Gauss–Newton steps on frame f's own rows and prior (p fixed) from
// y, each kept only if it lowers *cost (y's sum of squares on entry); stops once a step gains
// at most `tolerance` of the cost, or at most `min_gain`. A step that does not lower the cost is
// retried up to options.pose_step_retries times with a damping 100 times higher (at least 1e-3
// of the diagonal), each step shortened to options.pose_step_cap in its largest component
// (CoarseToFineOptions). Returns whether y moved. `trial` is scratch of frame_dim. With
// `given_cost`, *cost on entry is not needed: y's sum of squares is read from the first step's
// evaluation (PoseNormalEquations leaves the residuals in the blocks) into *given_cost and
// *cost, as FrameSquaredNorm would give it (NaN in *given_cost if y's residuals are not finite).
bool FramePoseSteps(const ArrowProblem& problem, const CoarseToFineOptions& options, FrameEvaluator* evaluator,
                    int f, int iterations, double tolerance, double min_gain, PoseStepWorkspace* ws,
                    Eigen::VectorXd* trial, double* yf, double* cost, double* given_cost = nullptr) {
  const int ny = problem.frame_dim();
  Eigen::MatrixXd* u = &ws->u;
  Eigen::VectorXd* g = &ws->g;
  Eigen::VectorXd* step = &ws->step;
  bool moved = false;
  if (given_cost) *given_cost = std::numeric_limits<double>::quiet_NaN();
  for (int it = 0; it < iterations; ++it) {
    // Normal equations of the frame's own rows: U = J_y^T J_y + B^T B, g = J_y^T r + B^T B (y - y0).
    u->setZero();
    g->setZero();
    if (!evaluator->PoseNormalEquations(f, yf, ny, u->data(), g->data())) break;
    if (it == 0 && given_cost) {
      if (!EvaluatedFrameSquaredNorm(problem, *evaluator, f, yf, cost)) return false;
      *given_cost = *cost;
    }
    const double *w, *target;
    if (problem.FramePrior(f, &w, &target))
      for (int i = 0; i < ny; ++i) {
        (*u)(i, i) += w[i] * w[i];
        (*g)[i] += w[i] * w[i] * (yf[i] - target[i]);
      }
    double trial_cost = 0;
    bool lower = false;
    double damping = options.pose_damping;
    const double* uu = u->data();
    double* l = ws->factor.data();
    double* s = step->data();
    for (int attempt = 0; attempt <= options.pose_step_retries; ++attempt) {
      if (attempt > 0) damping = std::max(100.0 * damping, 1e-3);
      // U's lower triangle damped and reversed into the factor, entry (i, j) to (n-1-j, n-1-i)
      // (a frame's coordinates come parents first, so reversed they come leaves first, and
      // eliminated in that order a kinematic tree's normal equations factor without fill:
      // CholeskyInPlace then skips every column that does not couple; a full-body frame: about a
      // third of the dense factorisation's multiply-adds); U itself is kept for a retry.
      for (int j = 0; j < ny; ++j)
        for (int i = j; i < ny; ++i) l[static_cast<size_t>(ny - 1 - i) * ny + (ny - 1 - j)] = uu[static_cast<size_t>(j) * ny + i];
      for (int i = 0; i < ny; ++i) {
        double& d = l[static_cast<size_t>(ny - 1 - i) * (ny + 1)];
        d += damping * std::max(d, 1e-12);
      }
      if (!CholeskyInPlace(l, ny, ws->rows.data(), ws->count.data(), ws->row_nonzeros.data())) break;
      for (int i = 0; i < ny; ++i) s[ny - 1 - i] = (*g)[i];
      CholeskySolveInPlace(l, ny, ws->rows.data(), ws->count.data(), s);
      const double largest = step->lpNorm<Eigen::Infinity>();
      if (largest > options.pose_step_cap) *step *= options.pose_step_cap / largest;
      for (int i = 0; i < ny; ++i) (*trial)[i] = yf[i] - s[ny - 1 - i];
      lower = trial->allFinite() && FrameSquaredNorm(problem, evaluator, f, trial->data(), &trial_cost) &&
              trial_cost < *cost;
      if (lower) break;
    }
    if (!lower) break;
    Eigen::Map<Eigen::VectorXd>(yf, ny) = *trial;
    const double decrease = *cost - trial_cost;
    *cost = trial_cost;
    moved = true;
    if (decrease <= tolerance * *cost || decrease <= min_gain) break;
  }
  return moved;
}
}  // namespace

bool CoarseToFineOptions::IsValid(std::string* error) const {
  auto fail = [&](const char* what) {
    if (error) *error = what;
    return false;
  };
  if (coarse_frames < 1) return fail("coarse_frames must be >= 1");
  if (min_frames < 2 * coarse_frames) return fail("min_frames must be >= 2 coarse_frames");
  if (!(coarse_function_tolerance > 0)) return fail("coarse_function_tolerance must be > 0");
  if (coarse_max_iterations < 1) return fail("coarse_max_iterations must be >= 1");
  if (pose_iterations < 0) return fail("pose_iterations must be >= 0");
  if (!(pose_damping >= 0)) return fail("pose_damping must be >= 0");
  if (!(pose_tolerance > 0 && pose_tolerance < 1)) return fail("pose_tolerance must be in (0, 1)");
  if (!(fine_initial_lambda > 0)) return fail("fine_initial_lambda must be > 0");
  if (!(rescue_ratio >= 0)) return fail("rescue_ratio must be >= 0 (below 1: off)");
  if (rescue_iterations < 1) return fail("rescue_iterations must be >= 1");
  if (inner_pose_iterations < 1) return fail("inner_pose_iterations must be >= 1");
  if (pose_step_retries < 0) return fail("pose_step_retries must be >= 0");
  if (!(pose_step_cap > 0)) return fail("pose_step_cap must be > 0 (infinity: none)");
  if (!(fine_converge_min_gain_ratio >= 0 && fine_converge_min_gain_ratio < 1))
    return fail("fine_converge_min_gain_ratio must be in [0, 1)");
  if (!(fine_raise_lambda_below_gain >= 0 && fine_raise_lambda_below_gain < 1))
    return fail("fine_raise_lambda_below_gain must be in [0, 1)");
  return true;
}

std::string CoarseToFineSummary::BriefReport() const {
  if (fallback)
    return "coarse-to-fine: " + std::to_string(coarse.num_iterations()) + " iterations on " +
           std::to_string(coarse_frames) + " frames did not converge; all frames solved from the start";
  if (!used) return "coarse-to-fine: not used (plain solve)";
  char buf[400];
  std::snprintf(buf, sizeof(buf),
                "coarse-to-fine: %d coarse frames, %d iterations (%.3f s); %d poses re-solved "
                "(%.3f s); whole problem from cost %.6e (start %.6e) after %.3f s (CPU %.3f s); %.3f s",
                coarse_frames, coarse.num_iterations(), coarse.total_seconds, poses_improved,
                pose_seconds, fine_start_cost, start_cost, fine_start_seconds, fine_start_cpu_seconds, total_seconds);
  return buf;
}

FrameSubsetProblem::FrameSubsetProblem(ArrowProblem* full, std::vector<int> frames)
    : full_(full), frames_(std::move(frames)) {}

int FrameSubsetProblem::num_residuals() const {
  return static_cast<int>(std::llround(double(full_->num_residuals()) * num_frames() /
                                       std::max(1, full_->num_frames())));
}

std::unique_ptr<FrameEvaluator> FrameSubsetProblem::NewEvaluator() const {
  return std::make_unique<SubsetEvaluator>(full_->NewEvaluator(), &frames_);
}

bool UnobservedHoldOptions::IsValid(std::string* error) const {
  if (!(weak_ratio > 0) || !(hold_ratio > 0)) {
    if (error) *error = "weak_ratio and hold_ratio must be > 0";
    return false;
  }
  return true;
}

int UnobservedCoordinateWeights(ArrowProblem* problem, const Eigen::VectorXd& x, const Eigen::VectorXd& base,
                                const UnobservedHoldOptions& options, int num_threads,
                                Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>* weights) {
  weights->resize(0, 0);
  const int nf = problem->num_frames(), ny = problem->frame_dim(), np = problem->shared_dim();
  if (!options.enabled || nf == 0 || base.size() != ny || !problem->SetShared(x.tail(np))) return 0;
  const int threads = std::max(1, std::min(num_threads, nf));
  // Per frame: its residual block count and each coordinate's marginal information.
  std::vector<int> blocks(nf, 0);
  Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> info(nf, ny);
  ParallelChunks(nf, threads, [&](int, int b, int e) {
    std::unique_ptr<FrameEvaluator> evaluator = problem->NewEvaluator();
    for (int f = b; f < e; ++f)
      if (evaluator->Evaluate(f, x.data() + static_cast<size_t>(f) * ny, false)) blocks[f] = evaluator->num_blocks();
  });
  const int fullest = *std::max_element(blocks.begin(), blocks.end());
  if (std::count(blocks.begin(), blocks.end(), fullest) == nf) return 0;
  ParallelChunks(nf, threads, [&](int, int b, int e) {
    std::unique_ptr<FrameEvaluator> evaluator = problem->NewEvaluator();
    Eigen::MatrixXd u(ny, ny);
    Eigen::VectorXd g(ny);
    for (int f = b; f < e; ++f) {
      info.row(f).setZero();
      if (!evaluator->EvaluatePoseJacobians(f, x.data() + static_cast<size_t>(f) * ny)) continue;
      u.setZero();
      g.setZero();
      for (int k = 0; k < evaluator->num_blocks(); ++k) AddBlockNormalEquations(evaluator->block(k), ny, u.data(), g.data());
      // The uniform prior keeps U_f invertible where no marker reaches a coordinate.
      for (int i = 0; i < ny; ++i) u(i, i) += base[i] * base[i] + 1e-12;
      Eigen::LLT<Eigen::MatrixXd, Eigen::Lower> llt(u);
      if (llt.info() != Eigen::Success) continue;
      const Eigen::MatrixXd inverse = llt.solve(Eigen::MatrixXd::Identity(ny, ny));
      for (int i = 0; i < ny; ++i) info(f, i) = 1.0 / inverse(i, i);
    }
  });
  std::vector<double> median(ny), column(nf);
  for (int i = 0; i < ny; ++i) {
    for (int f = 0; f < nf; ++f) column[f] = info(f, i);
    std::nth_element(column.begin(), column.begin() + nf / 2, column.end());
    median[i] = column[nf / 2];
  }
  weights->resize(nf, ny);
  int raised = 0;
  for (int f = 0; f < nf; ++f)
    for (int i = 0; i < ny; ++i) {
      (*weights)(f, i) = base[i];
      if (blocks[f] == fullest || !(info(f, i) < options.weak_ratio * median[i])) continue;
      (*weights)(f, i) = std::sqrt(base[i] * base[i] + options.hold_ratio * median[i]);
      ++raised;
    }
  return raised;
}

int RefineFramePoses(ArrowProblem* problem, const CoarseToFineOptions& options, int num_threads,
                     Eigen::VectorXd* x, bool* ok, double* cost, const double* frame_costs, double min_gain,
                     std::vector<double>* final_frame_costs) {
  const int nf = problem->num_frames(), ny = problem->frame_dim(), np = problem->shared_dim();
  if (final_frame_costs) final_frame_costs->clear();
  *ok = problem->SetShared(x->tail(np));
  if (!*ok) return 0;
  if (final_frame_costs) final_frame_costs->assign(nf, std::numeric_limits<double>::infinity());
  const int threads = std::max(1, std::min(num_threads, nf));
  std::vector<int> improved(threads, 0);
  std::vector<double> frames_cost(threads, 0.0);
  std::vector<char> fine(threads, 1);
  ParallelChunks(nf, threads, [&](int t, int b, int e) {
    // Per thread, allocated once: the hot loop allocates nothing.
    std::unique_ptr<FrameEvaluator> evaluator = problem->NewEvaluator();
    PoseStepWorkspace ws(ny);
    Eigen::VectorXd trial(ny), given(ny), correction = Eigen::VectorXd::Zero(ny);
    bool have_correction = false;
    double previous_cost = 0;
    for (int f = b; f < e; ++f) {
      double* yf = x->data() + static_cast<size_t>(f) * ny;
      given = Eigen::Map<const Eigen::VectorXd>(yf, ny);
      double cost = 0;
      bool have_cost = false, moved = false;
      int max_iterations = options.pose_iterations;
      if (frame_costs) {
        cost = frame_costs[f];
        have_cost = true;
      }
      // Start from the previous frame's correction. When that start is about as good as the
      // previous frame ended, the given pose (made for another geometry) is not even evaluated.
      double corrected_cost = std::numeric_limits<double>::infinity();
      if (!have_cost && have_correction && options.pose_from_predecessor) {
        trial = given + correction;
        if (!FrameSquaredNorm(*problem, evaluator.get(), f, trial.data(), &corrected_cost))
          corrected_cost = std::numeric_limits<double>::infinity();
        if (corrected_cost <= 4.0 * previous_cost) {
          Eigen::Map<Eigen::VectorXd>(yf, ny) = trial;
          cost = corrected_cost;
          have_cost = moved = true;
          max_iterations = 1;  // close already; stage 3 takes what one step leaves
        }
      }
      if (!have_cost) {
        if (!FrameSquaredNorm(*problem, evaluator.get(), f, yf, &cost)) {
          fine[t] = 0;
          return;
        }
        if (corrected_cost < cost) {
          Eigen::Map<Eigen::VectorXd>(yf, ny) = trial;
          cost = corrected_cost;
          moved = true;
        }
      }
      moved |= FramePoseSteps(*problem, options, evaluator.get(), f, max_iterations,
                              min_gain > 0 ? 0.0 : options.pose_tolerance, min_gain, &ws, &trial, yf, &cost);
      correction = Eigen::Map<const Eigen::VectorXd>(yf, ny) - given;
      have_correction = true;
      previous_cost = cost;
      improved[t] += moved ? 1 : 0;
      frames_cost[t] += cost;
      if (final_frame_costs) (*final_frame_costs)[f] = cost;
    }
  });
  int total = 0;
  double sum = 0;
  for (int t = 0; t < threads; ++t) {
    *ok = *ok && fine[t];
    total += improved[t];
    sum += frames_cost[t];
  }
  if (cost) *cost = 0.5 * (sum + SharedRowsSquaredNorm(*problem, x->tail(np)));
  if (final_frame_costs && !*ok) final_frame_costs->clear();
  return total;
}

int RescueFramesFromNeighbours(ArrowProblem* problem, const CoarseToFineOptions& options, int num_threads,
                               Eigen::VectorXd* x, std::vector<double>* frame_costs, const std::vector<char>* also) {
  const int nf = problem->num_frames(), ny = problem->frame_dim(), np = problem->shared_dim();
  if (!(options.rescue_ratio > 1) || nf < 3 || !problem->SetShared(x->tail(np))) return 0;
  const int threads = std::max(1, std::min(num_threads, nf));
  std::vector<double> own;
  std::vector<double>& cost = frame_costs ? *frame_costs : own;
  if (static_cast<int>(cost.size()) != nf) {
    cost.assign(nf, std::numeric_limits<double>::infinity());
    ParallelChunks(nf, threads, [&](int, int b, int e) {
      std::unique_ptr<FrameEvaluator> evaluator = problem->NewEvaluator();
      for (int f = b; f < e; ++f)
        if (!FrameSquaredNorm(*problem, evaluator.get(), f, x->data() + static_cast<size_t>(f) * ny, &cost[f]))
          cost[f] = std::numeric_limits<double>::infinity();
    });
  }
  std::vector<double> sorted = cost;
  std::nth_element(sorted.begin(), sorted.begin() + nf / 2, sorted.end());
  const double limit = options.rescue_ratio * sorted[nf / 2];
  if (!std::isfinite(limit)) return 0;
  std::vector<char> suspect(nf);
  for (int f = 0; f < nf; ++f) suspect[f] = !(cost[f] <= limit) || (also && (*also)[f]);
  // Runs of consecutive suspect frames, each swept from both ends.
  std::vector<std::pair<int, int>> runs;
  for (int f = 0; f < nf; ++f) {
    if (!suspect[f]) continue;
    if (runs.empty() || runs.back().second != f) runs.emplace_back(f, f + 1);
    else runs.back().second = f + 1;
  }
  if (runs.empty()) return 0;
  std::vector<int> rescued(threads, 0);
  const std::vector<double> given_cost = cost;
  ParallelChunks(static_cast<int>(runs.size()), threads, [&](int t, int rb, int re) {
    std::unique_ptr<FrameEvaluator> evaluator = problem->NewEvaluator();
    PoseStepWorkspace ws(ny);
    Eigen::VectorXd trial(ny), start(ny);
    for (int r = rb; r < re; ++r) {
      const auto [first, end] = runs[r];
      // Forwards from the well-fitted frame before the run, then backwards from the one after
      // it: each frame starts from its neighbour's pose as it stands after the sweep (rescued or
      // not), so a long stretch in a wrong branch (a foot turned round for hundreds of frames)
      // is carried back in one pass, as the IK's own sweep carries a trial.
      for (int direction : {+1, -1}) {
        const int from = direction > 0 ? first - 1 : end;
        if (from < 0 || from >= nf) continue;
        for (int f = direction > 0 ? first : end - 1; f >= first && f < end; f += direction) {
          start = x->segment(static_cast<Eigen::Index>(f - direction) * ny, ny);
          if (options.wrap_frame_turns) problem->WrapFramePose(f, start.data());
          double c = 0;
          if (!FrameSquaredNorm(*problem, evaluator.get(), f, start.data(), &c)) continue;
          FramePoseSteps(*problem, options, evaluator.get(), f, options.rescue_iterations, 1e-3, 0.0, &ws, &trial,
                         start.data(), &c);
          if (c < cost[f]) {
            cost[f] = c;
            x->segment(static_cast<Eigen::Index>(f) * ny, ny) = start;
          }
        }
      }
      for (int f = first; f < end; ++f) rescued[t] += cost[f] < given_cost[f] ? 1 : 0;
    }
  });
  int total = 0;
  for (int r : rescued) total += r;
  return total;
}

bool ProjectedCost(ArrowProblem* problem, const CoarseToFineOptions& options, int num_threads, int cost_threads,
                   const Eigen::VectorXd& x, double function_tolerance, double* cost, Eigen::VectorXd* projected,
                   double* projected_cost, int* rescued) {
  const int nf = problem->num_frames(), ny = problem->frame_dim(), np = problem->shared_dim();
  *rescued = 0;
  *projected_cost = std::numeric_limits<double>::infinity();
  if (options.pose_iterations < 1 || options.wrap_frame_turns || !problem->SetShared(x.tail(np))) return false;
  const int threads = std::max(1, std::min(num_threads, nf));
  // Pass 1: each frame's cost at x and its first pose step, the stepped poses kept apart (the
  // rescue judges, and starts from, x's poses).
  Eigen::VectorXd stepped = x;
  std::vector<double> given(nf), first(nf);
  std::vector<char> moved(nf, 0), fine(threads, 1);
  ParallelChunks(nf, threads, [&](int t, int b, int e) {
    std::unique_ptr<FrameEvaluator> evaluator = problem->NewEvaluator();
    PoseStepWorkspace ws(ny);
    Eigen::VectorXd trial(ny);
    for (int f = b; f < e; ++f) {
      double c = 0;
      moved[f] = FramePoseSteps(*problem, options, evaluator.get(), f, 1, 0.0, 0.0, &ws, &trial,
                                stepped.data() + static_cast<size_t>(f) * ny, &c, &given[f]);
      first[f] = c;
      if (!std::isfinite(given[f])) {
        fine[t] = 0;
        return;
      }
    }
  });
  for (char ok : fine)
    if (!ok) return false;
  *cost = 0.5 * (ChunkedSum(given, cost_threads) + SharedRowsSquaredNorm(*problem, x.tail(np)));
  if (!std::isfinite(*cost)) return false;
  // Frame costs are sums of squares: twice the cost's share.
  const double min_gain = 2.0 * function_tolerance * *cost;
  const double tolerance = min_gain > 0 ? 0.0 : options.pose_tolerance;
  *projected = x;
  std::vector<double> costs = given;
  *rescued = RescueFramesFromNeighbours(problem, options, num_threads, projected, &costs);
  // Pass 2: the steps after the first; a rescued frame (its cost lowered) from its new pose.
  std::vector<double> final_cost(nf);
  ParallelChunks(nf, threads, [&](int, int b, int e) {
    std::unique_ptr<FrameEvaluator> evaluator = problem->NewEvaluator();
    PoseStepWorkspace ws(ny);
    Eigen::VectorXd trial(ny);
    for (int f = b; f < e; ++f) {
      double* yf = projected->data() + static_cast<size_t>(f) * ny;
      double c = costs[f];
      int iterations = options.pose_iterations;
      if (!(costs[f] < given[f])) {
        // x's pose: after a refused first step FramePoseSteps stops; after a kept one it goes on
        // unless that step's gain already stops it.
        iterations = 0;
        if (moved[f]) {
          c = first[f];
          const double decrease = given[f] - c;
          Eigen::Map<Eigen::VectorXd>(yf, ny) = stepped.segment(static_cast<Eigen::Index>(f) * ny, ny);
          if (!(decrease <= tolerance * c || decrease <= min_gain)) iterations = options.pose_iterations - 1;
        }
      }
      if (iterations > 0)
        FramePoseSteps(*problem, options, evaluator.get(), f, iterations, tolerance, min_gain, &ws, &trial, yf, &c);
      final_cost[f] = c;
    }
  });
  *projected_cost = 0.5 * (ChunkedSum(final_cost, threads) + SharedRowsSquaredNorm(*problem, x.tail(np)));
  return true;
}

LmSummary SolveCoarseToFine(ArrowProblem* problem, ArrowSchurProblem* whole, const LmOptions& options,
                            const CoarseToFineOptions& coarse, int num_threads, Eigen::VectorXd* x,
                            CoarseToFineSummary* summary) {
  const auto start = Clock::now();
  const double start_cpu = ProcessCpuSeconds();
  CoarseToFineSummary local;
  CoarseToFineSummary& s = summary ? *summary : local;
  s = CoarseToFineSummary();
  std::string why;
  if (!coarse.IsValid(&why)) {
    LmSummary failed;
    failed.message = "invalid coarse-to-fine options: " + why;
    return failed;
  }
  const int nf = problem->num_frames(), ny = problem->frame_dim(), np = problem->shared_dim();
  ArrowSchurProblem& fine = *whole;
  s.frames_cached = fine.caches_frames();
  if (!coarse.enabled || nf < coarse.min_frames || np == 0 ||
      x->size() != static_cast<Eigen::Index>(nf) * ny + np || !x->allFinite()) {
    LmSummary plain = Solve(options, &fine, x);
    s.total_seconds = Since(start);
    return plain;
  }
  s.used = true;
  if (!fine.Cost(*x, &s.start_cost)) {
    LmSummary failed;
    failed.message = "residuals not finite at the initial parameters";
    return failed;
  }

  // Stage 1: every (nf / coarse_frames)-th frame, centred in its stretch.
  std::vector<int> frames(coarse.coarse_frames);
  for (int i = 0; i < coarse.coarse_frames; ++i)
    frames[i] = static_cast<int>((i + 0.5) * nf / coarse.coarse_frames);
  s.coarse_frames = coarse.coarse_frames;
  FrameSubsetProblem subset(problem, frames);
  Eigen::VectorXd xs(static_cast<Eigen::Index>(frames.size()) * ny + np);
  for (size_t i = 0; i < frames.size(); ++i)
    xs.segment(static_cast<Eigen::Index>(i) * ny, ny) = x->segment(static_cast<Eigen::Index>(frames[i]) * ny, ny);
  xs.tail(np) = x->tail(np);
  LmOptions coarse_lm = options;
  coarse_lm.function_tolerance = std::max(options.function_tolerance, coarse.coarse_function_tolerance);
  coarse_lm.max_iterations = std::min(options.max_iterations, coarse.coarse_max_iterations);
  // The subset's standard deviations are the subset's (sqrt(F / n) times the whole problem's):
  // its own statistical convergence is not the start the fine stage is tuned for.
  coarse_lm.shared_step_tolerance = 0;
  coarse_lm.callbacks.clear();
  coarse_lm.data_rms = nullptr;  // of the whole problem's x, not the subset's
  for (const IterationCallback& cb : options.callbacks)
    coarse_lm.callbacks.push_back([cb](const IterationSummary& it) {
      IterationSummary tagged = it;
      tagged.coarse = true;
      return cb(tagged);
    });
  {
    ArrowSchurProblem schur(&subset, num_threads);
    WithInnerIterations with_rescue(&schur, &subset, coarse, num_threads, /*refine_poses=*/false,
                                   coarse_lm.function_tolerance);
    s.coarse = Solve(coarse_lm, &with_rescue, &xs);
    s.poses_rescued += with_rescue.rescued();
  }
  if (s.coarse.termination == TerminationType::kUserCancelled) {
    // Cancelled on the subset: keep its geometry and its frames' poses when that lowers the whole
    // problem's cost (the best result reached), else x as the caller gave it.
    LmSummary out;
    out.termination = TerminationType::kUserCancelled;
    out.message = "cancelled (coarse stage)";
    out.initial_cost = out.final_cost = s.start_cost;
    Eigen::VectorXd kept = *x;
    for (size_t i = 0; i < frames.size(); ++i)
      kept.segment(static_cast<Eigen::Index>(frames[i]) * ny, ny) = xs.segment(static_cast<Eigen::Index>(i) * ny, ny);
    kept.tail(np) = xs.tail(np);
    double kept_cost = 0;
    if (fine.Cost(kept, &kept_cost) && kept_cost < s.start_cost) {
      x->swap(kept);
      out.final_cost = kept_cost;
    }
    out.num_parameters = fine.num_parameters();
    out.num_residuals = fine.num_residuals();
    out.total_seconds = s.total_seconds = Since(start);
    return out;
  }
  if (s.coarse.termination != TerminationType::kConvergence) {
    // The subset could not be solved, or LM was still crawling on it at its budget (frames in
    // long marker gaps, held only by their weak priors: the 10 %-missing simulation). Its
    // geometry is then no good start, and the whole problem goes plainly from the caller's x.
    s.used = false;
    s.fallback = true;
    LmSummary plain = Solve(options, &fine, x);
    plain.initial_cost = s.start_cost;
    s.total_seconds = Since(start);
    return plain;
  }

  // Stage 2: the coarse geometry, every pose re-solved for it (the subset's frames too, from
  // the caller's poses like the others: each frame starts from its predecessor's correction, so
  // the corrections must all be measured from the same starting poses).
  const auto pose_start = Clock::now();
  Eigen::VectorXd candidate = *x;
  candidate.tail(np) = xs.tail(np);
  if (coarse.wrap_frame_turns) WrapFramePoses(*problem, num_threads, &candidate);
  bool ok = false;
  double candidate_cost = 0;
  // Each frame's cost at its re-solved pose goes on to the rescue, and the candidate's cost is
  // summed from what the rescue leaves: two passes over the frames fewer (the rescue's cost pass
  // and a whole-problem cost), the same poses. The sum's order differs from
  // ArrowSchurProblem::Cost's, but it only decides whether the candidate beats the caller's
  // start and is reported; stage 3's first linearisation computes its own cost.
  std::vector<double> frame_costs;
  s.poses_improved =
      RefineFramePoses(problem, coarse, num_threads, &candidate, &ok, &candidate_cost, nullptr, 0, &frame_costs);
  if (ok) {
    // Frames in gaps (CoarseToFineOptions::rescue_gap_frames): fewer marker rows, i.e. blocks
    // reaching the shared parameters (a coordinate limit's block reaches none), than the fullest.
    std::vector<char> gap;
    if (coarse.rescue_gap_frames) {
      std::vector<int> rows(nf, 0);
      ParallelChunks(nf, std::max(1, std::min(num_threads, nf)), [&](int, int b, int e) {
        std::unique_ptr<FrameEvaluator> evaluator = problem->NewEvaluator();
        for (int f = b; f < e; ++f) {
          if (!evaluator->Evaluate(f, candidate.data() + static_cast<size_t>(f) * ny, false)) continue;
          for (int k = 0; k < evaluator->num_blocks(); ++k)
            if (evaluator->block(k).num_p > 0) rows[f] += evaluator->block(k).rows;
        }
      });
      const int fullest = *std::max_element(rows.begin(), rows.end());
      gap.resize(nf);
      for (int f = 0; f < nf; ++f) gap[f] = rows[f] < fullest;
    }
    s.poses_rescued = RescueFramesFromNeighbours(problem, coarse, num_threads, &candidate, &frame_costs,
                                                 coarse.rescue_gap_frames ? &gap : nullptr);
    if (s.poses_rescued > 0) {
      double sum = 0;
      for (double c : frame_costs) sum += c;
      candidate_cost = 0.5 * (sum + SharedRowsSquaredNorm(*problem, candidate.tail(np)));
    }
  }
  s.pose_seconds = Since(pose_start);
  if (ok && std::isfinite(candidate_cost) && candidate_cost < s.start_cost) {
    *x = candidate;
    s.fine_start_cost = candidate_cost;
  } else {
    // Never start the whole problem from a worse point than the caller's.
    s.fine_start_cost = s.start_cost;
  }

  // Stage 3.
  s.fine_start_seconds = Since(start);
  s.fine_start_cpu_seconds = ProcessCpuSeconds() - start_cpu;
  LmOptions fine_lm = options;
  fine_lm.initial_lambda = std::clamp(coarse.fine_initial_lambda, options.min_lambda, options.max_lambda);
  fine_lm.halve_rejected_steps = options.halve_rejected_steps || coarse.fine_halve_rejected_steps;
  if (coarse.fine_variable_projection)
    fine_lm.function_tolerance_min_gain_ratio =
        std::max(fine_lm.function_tolerance_min_gain_ratio, coarse.fine_converge_min_gain_ratio);
  fine_lm.raise_lambda_below_gain_ratio = std::max(fine_lm.raise_lambda_below_gain_ratio, coarse.fine_raise_lambda_below_gain);
  LmSummary result;
  if (coarse.fine_secant_curvature) fine.SetSecantCurvature(true);
  fine.SetReducedDamping(coarse.fine_reduced_damping);
  if (coarse.inner_iterations) {
    WithInnerIterations with_inner(&fine, problem, coarse, num_threads, /*refine_poses=*/true,
                                   fine_lm.function_tolerance);
    with_inner.SetProject(coarse.fine_variable_projection);
    result = Solve(fine_lm, &with_inner, x);
    s.poses_rescued += with_inner.rescued();
  } else {
    result = Solve(fine_lm, &fine, x);
  }
  if (coarse.fine_secant_curvature) fine.SetSecantCurvature(false);
  fine.SetReducedDamping(false);
  result.initial_cost = s.start_cost;
  result.total_seconds = s.total_seconds = Since(start);
  return result;
}

}  // namespace mocap::solver
