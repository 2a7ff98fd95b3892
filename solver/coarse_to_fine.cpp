#include "solver/coarse_to_fine.h"

#include <Eigen/Cholesky>
#include <chrono>
#include <algorithm>
#include <cmath>
#include <cstdio>

#include "solver/parallel.h"

namespace mocap::solver {
namespace {
using Clock = std::chrono::steady_clock;
double Since(Clock::time_point t) { return std::chrono::duration<double>(Clock::now() - t).count(); }

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
  int num_blocks() const override { return inner_->num_blocks(); }
  const ResidualBlock& block(int i) const override { return inner_->block(i); }

 private:
  std::unique_ptr<FrameEvaluator> inner_;
  const std::vector<int>* frames_;
};

// One frame's cost with p fixed: its residuals and its frame prior (halved sum of squares
// left out: only compared with itself).
bool FrameCost(const ArrowProblem& problem, FrameEvaluator* evaluator, int f, const double* y,
               double* cost) {
  if (!evaluator->Evaluate(f, y, false)) return false;
  double sum = 0;
  for (int k = 0; k < evaluator->num_blocks(); ++k) {
    const ResidualBlock& b = evaluator->block(k);
    for (int r = 0; r < b.rows; ++r) sum += b.residual[r] * b.residual[r];
  }
  const double *w, *target;
  if (problem.FramePrior(f, &w, &target))
    for (int i = 0; i < problem.frame_dim(); ++i) sum += (w[i] * (y[i] - target[i])) * (w[i] * (y[i] - target[i]));
  *cost = sum;
  return std::isfinite(sum);
}
// Stage 3's problem: the whole problem's Schur solver, with every frame's pose re-solved for the
// new geometry after each accepted step (LmProblem::InnerIteration). Near the minimum, LM's
// step leaves most of its shortfall in the weakly seen coordinates (a wrist's deviation, a
// subtalar angle) that follow the weakly determined axes nonlinearly; one Gauss–Newton step per
// frame takes it, for about a third of a linearisation's cost, so the next step already meets the
// function tolerance.
class WithInnerIterations : public LmProblem {
 public:
  WithInnerIterations(ArrowSchurProblem* whole, ArrowProblem* problem, const CoarseToFineOptions& options,
                      int num_threads)
      : whole_(whole), problem_(problem), options_(options), num_threads_(num_threads) {
    options_.pose_iterations = 1;
    options_.pose_from_predecessor = false;
  }
  int num_parameters() const override { return whole_->num_parameters(); }
  int num_residuals() const override { return whole_->num_residuals(); }
  bool Cost(const Eigen::VectorXd& x, double* cost) override { return whole_->Cost(x, cost); }
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
  void InnerIteration(Eigen::VectorXd* x) override {
    candidate_ = *x;
    bool ok = false;
    RefineFramePoses(problem_, options_, num_threads_, &candidate_, &ok, nullptr);
    if (ok) x->swap(candidate_);  // every frame's cost only fell; p is unchanged
  }

 private:
  ArrowSchurProblem* whole_;
  ArrowProblem* problem_;
  CoarseToFineOptions options_;
  int num_threads_;
  Eigen::VectorXd candidate_;
};
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
  return true;
}

std::string CoarseToFineSummary::BriefReport() const {
  if (!used) return "coarse-to-fine: not used (plain solve)";
  char buf[320];
  std::snprintf(buf, sizeof(buf),
                "coarse-to-fine: %d coarse frames, %d iterations (%.3f s); %d poses re-solved "
                "(%.3f s); whole problem from cost %.6e (start %.6e); %.3f s",
                coarse_frames, coarse.num_iterations(), coarse.total_seconds, poses_improved,
                pose_seconds, fine_start_cost, start_cost, total_seconds);
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

int RefineFramePoses(ArrowProblem* problem, const CoarseToFineOptions& options, int num_threads,
                     Eigen::VectorXd* x, bool* ok, double* cost) {
  const int nf = problem->num_frames(), ny = problem->frame_dim(), np = problem->shared_dim();
  *ok = problem->SetShared(x->tail(np));
  if (!*ok) return 0;
  const int threads = std::max(1, std::min(num_threads, nf));
  std::vector<int> improved(threads, 0);
  std::vector<double> frames_cost(threads, 0.0);
  std::vector<char> fine(threads, 1);
  ParallelChunks(nf, threads, [&](int t, int b, int e) {
    // Per thread, allocated once: the hot loop allocates nothing.
    std::unique_ptr<FrameEvaluator> evaluator = problem->NewEvaluator();
    Eigen::MatrixXd u(ny, ny);
    Eigen::VectorXd g(ny), y(ny), trial(ny), given(ny), correction = Eigen::VectorXd::Zero(ny);
    Eigen::LLT<Eigen::MatrixXd> llt(ny);
    bool have_correction = false;
    for (int f = b; f < e; ++f) {
      double* yf = x->data() + static_cast<size_t>(f) * ny;
      given = Eigen::Map<const Eigen::VectorXd>(yf, ny);
      double cost = 0;
      if (!FrameCost(*problem, evaluator.get(), f, yf, &cost)) {
        fine[t] = 0;
        return;
      }
      bool moved = false;
      // Start from the previous frame's correction when that is better than the given pose.
      if (have_correction && options.pose_from_predecessor) {
        trial = given + correction;
        double trial_cost = 0;
        if (FrameCost(*problem, evaluator.get(), f, trial.data(), &trial_cost) && trial_cost < cost) {
          Eigen::Map<Eigen::VectorXd>(yf, ny) = trial;
          cost = trial_cost;
          moved = true;
        }
      }
      for (int it = 0; it < options.pose_iterations; ++it) {
        // Normal equations of the frame's own rows: U = J_y^T J_y + B^T B, g = J_y^T r + B^T B (y - y0).
        if (!evaluator->EvaluatePoseJacobians(f, yf)) break;
        u.setZero();
        g.setZero();
        for (int k = 0; k < evaluator->num_blocks(); ++k) {
          const ResidualBlock& blk = evaluator->block(k);
          for (int a = 0; a < blk.num_y; ++a) {
            const double* ja = blk.jy + a * kMaxBlockRows;
            const int ia = blk.y_index[a];
            double ga = 0;
            for (int r = 0; r < blk.rows; ++r) ga += ja[r] * blk.residual[r];
            g[ia] += ga;
            for (int c = 0; c <= a; ++c) {
              const double* jc = blk.jy + c * kMaxBlockRows;
              double s = 0;
              for (int r = 0; r < blk.rows; ++r) s += ja[r] * jc[r];
              const int ic = blk.y_index[c];
              // Lower triangle in any column order: (max, min).
              u(std::max(ia, ic), std::min(ia, ic)) += s;
            }
          }
        }
        const double *w, *target;
        if (problem->FramePrior(f, &w, &target))
          for (int i = 0; i < ny; ++i) {
            u(i, i) += w[i] * w[i];
            g[i] += w[i] * w[i] * (yf[i] - target[i]);
          }
        for (int i = 0; i < ny; ++i) u(i, i) += options.pose_damping * std::max(u(i, i), 1e-12);
        llt.compute(u.selfadjointView<Eigen::Lower>());
        if (llt.info() != Eigen::Success) break;
        y = Eigen::Map<const Eigen::VectorXd>(yf, ny);
        trial = y - llt.solve(g);
        double trial_cost = 0;
        if (!trial.allFinite() || !FrameCost(*problem, evaluator.get(), f, trial.data(), &trial_cost) ||
            !(trial_cost < cost))
          break;
        Eigen::Map<Eigen::VectorXd>(yf, ny) = trial;
        const double decrease = cost - trial_cost;
        cost = trial_cost;
        moved = true;
        if (decrease <= options.pose_tolerance * cost) break;
      }
      correction = Eigen::Map<const Eigen::VectorXd>(yf, ny) - given;
      have_correction = true;
      improved[t] += moved ? 1 : 0;
      frames_cost[t] += cost;
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
  return total;
}

LmSummary SolveCoarseToFine(ArrowProblem* problem, ArrowSchurProblem* whole, const LmOptions& options,
                            const CoarseToFineOptions& coarse, int num_threads, Eigen::VectorXd* x,
                            CoarseToFineSummary* summary) {
  const auto start = Clock::now();
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
  coarse_lm.callbacks.clear();
  for (const IterationCallback& cb : options.callbacks)
    coarse_lm.callbacks.push_back([cb](const IterationSummary& it) {
      IterationSummary tagged = it;
      tagged.coarse = true;
      return cb(tagged);
    });
  {
    ArrowSchurProblem schur(&subset, num_threads);
    s.coarse = Solve(coarse_lm, &schur, &xs);
  }
  auto stop_early = [&](TerminationType type, const std::string& message) {
    // x is left as the caller gave it: its cost is known, nothing half-updated.
    LmSummary out;
    out.termination = type;
    out.message = message;
    out.initial_cost = out.final_cost = s.start_cost;
    out.num_parameters = fine.num_parameters();
    out.num_residuals = fine.num_residuals();
    out.total_seconds = s.total_seconds = Since(start);
    return out;
  };
  if (s.coarse.termination == TerminationType::kUserCancelled)
    return stop_early(TerminationType::kUserCancelled, "cancelled by the callback (coarse stage)");
  if (!s.coarse.IsSolutionUsable()) {
    // The subset could not be solved (not finite there): the whole problem from the caller's x.
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
  bool ok = false;
  double candidate_cost = 0;
  s.poses_improved = RefineFramePoses(problem, coarse, num_threads, &candidate, &ok, &candidate_cost);
  s.pose_seconds = Since(pose_start);
  if (ok && std::isfinite(candidate_cost) && candidate_cost < s.start_cost) {
    *x = candidate;
    s.fine_start_cost = candidate_cost;
  } else {
    // Never start the whole problem from a worse point than the caller's.
    s.fine_start_cost = s.start_cost;
  }

  // Stage 3.
  LmOptions fine_lm = options;
  fine_lm.initial_lambda = std::clamp(coarse.fine_initial_lambda, options.min_lambda, options.max_lambda);
  LmSummary result;
  if (coarse.inner_iterations) {
    WithInnerIterations with_inner(&fine, problem, coarse, num_threads);
    result = Solve(fine_lm, &with_inner, x);
  } else {
    result = Solve(fine_lm, &fine, x);
  }
  result.initial_cost = s.start_cost;
  result.total_seconds = s.total_seconds = Since(start);
  return result;
}

}  // namespace mocap::solver
