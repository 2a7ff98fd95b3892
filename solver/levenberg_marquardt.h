// Levenberg–Marquardt for sparse nonlinear least squares, min_x 1/2 ||r(x)||^2.
//
// The minimiser is independent of how the damped normal equations
//     (J^T J + D) dx = -J^T r,   D = lambda * clamp(diag(J^T J), min_diagonal, max_diagonal)
// are solved: an LmProblem owns its Jacobian and its linear solver (the global fit uses a
// per-frame Schur elimination, solver/schur_solver.h, or CHOLMOD, solver/cholmod_solver.h).
// Damping follows Marquardt's diagonal scaling and Nielsen's update rule (H. B. Nielsen, "Damping
// parameter in Marquardt's method", IMM-REP-1999-05): after a step with gain ratio rho > eta,
// lambda *= max(1/3, 1 - (2 rho - 1)^3); otherwise lambda *= nu, nu *= 2. The predicted decrease
// uses the identity dx^T J^T J dx = -dx^T g - dx^T D dx, so no extra product with J is needed.
// Options, Summary and termination types follow Ceres Solver's shape.
//
// Optional geodesic acceleration (M. K. Transtrum and J. P. Sethna, "Improvements to the
// Levenberg-Marquardt algorithm for nonlinear least-squares minimization", arXiv:1201.5885, 2012;
// GSL's gsl_multifit_nlinear "lmaccel"): in a narrow curved valley the LM step v (the velocity)
// leaves the valley floor and is rejected or cut short by the damping. The second-order term of
// the geodesic through x along v adds an acceleration a, solving the same damped system
// (J^T J + D) a = -J^T r_vv, with r_vv the residuals' second directional derivative along v
// (a finite difference: one more residual evaluation at x + h v, LmProblem::SolveAcceleration).
// The step is v + a / 2; it is refused (as a failed step: lambda rises) when 2 |a| / |v| > alpha
// in the damping's scaled norm, where the second-order model cannot be trusted. The gain ratio
// is measured against v's predicted decrease (the quadratic model's, as GSL does).
#pragma once
#include <atomic>

#include <Eigen/Core>
#include <functional>
#include <limits>
#include <string>
#include <vector>

namespace mocap::solver {

enum class TerminationType {
  kConvergence,        // a tolerance was met: the solution is a local minimum
  kNoConvergence,      // max_iterations or max_seconds reached: usable, not converged
  kUserCancelled,      // the iteration callback asked to stop: usable, not converged
  kFailure,            // the problem could not be evaluated or solved at the start
};
const char* ToString(TerminationType type);

struct IterationSummary {
  int iteration = 0;
  double cost = 0;              // after this iteration
  double cost_change = 0;       // decrease achieved (0 if the step was rejected)
  double gradient_max_norm = 0;  // at the new iterate; at the previous one when the solve ends
                                 // on the function or parameter tolerance (not re-linearised)
  double step_norm = 0;
  double lambda = 0;
  double gain_ratio = 0;
  bool step_accepted = false;
  int linear_solves = 0;        // in this iteration (rejected steps re-solve)
  double iteration_seconds = 0;
  double total_seconds = 0;
  bool coarse = false;          // of a coarse stage on a subset of the frames (coarse_to_fine.h)
  // Geodesic acceleration (LmOptions::geodesic_acceleration) of the accepted step: 2 |a| / |v| in
  // the damping's scaled norm; 0 when the step had none.
  double acceleration_ratio = 0;
  // LmOptions::data_rms at the iterate this iteration ended on; NaN without one.
  double data_rms = std::numeric_limits<double>::quiet_NaN();
};

// Return false to stop the solve (the summary then says kUserCancelled).
using IterationCallback = std::function<bool(const IterationSummary&)>;

struct LmOptions {
  int max_iterations = 100;
  double max_seconds = 1e9;
  double function_tolerance = 1e-8;   // stop when |cost change| / cost < this
  double gradient_tolerance = 1e-10;  // stop when max |g_i| < this
  double parameter_tolerance = 1e-10; // stop when |dx| < this * (|x| + this)
  double initial_lambda = 1e-4;
  double min_lambda = 1e-16;
  double max_lambda = 1e16;
  double min_diagonal = 1e-6;         // floor for diag(J^T J) in the damping
  double max_diagonal = 1e32;
  double min_gain_ratio = 1e-3;       // eta: accept steps whose gain ratio exceeds this
  int max_consecutive_rejections = 10;
  // After a rejected step v, lambda rises at least to the damping at which the quadratic model's
  // minimiser along v is v / 2: lambda' = v^T J^T J v / v^T S v + 2 lambda (S = the damping's
  // scaling, clamp(diag(J^T J)); v^T J^T J v from the identity above, no product with J), not
  // only by Nielsen's nu (2, 4, 8, ...). Nielsen's doubling assumes the damping is already of the
  // scale that shapes the step; from a Gauss–Newton-like start (lambda 1e-8, coarse_to_fine.h's
  // fine stage) a rejected step is nearly the undamped one, and doubling re-solves the same step
  // four or five times (each a pass over every frame) before lambda reaches that scale. Off by
  // default here; on in the coarse-to-fine fine stage (CoarseToFineOptions::fine_halve_rejected_steps).
  bool halve_rejected_steps = false;
  // Geodesic acceleration (see the top of this file). Needs LmProblem::SolveAcceleration; a problem
  // without it (or whose acceleration solve fails) gets the plain step. acceleration_step is h of
  // the finite difference r_vv ~ (2 / h) ((r(x + h v) - r(x)) / h - J v), relative to v (GSL's
  // h_fvv, 0.02); max_acceleration_ratio is alpha of the test 2 |a| / |v| <= alpha (0.75 in
  // Transtrum and Sethna and in GSL). Off: measured on the global fit with marker gaps (6,000
  // frames, 5 and 10 % missing, seeds 1-3; BENCHMARKS.md, "With gaps", fifteenth session) it turns
  // the crawl's gain ratios from 0.2-0.7 to 0.9-1.0, but the first Gauss–Newton-like step is
  // refused (2|a|/|v| = 11.5) up to a higher damping than plain LM's, and each trial costs about
  // 40 % of a linearisation more: CPU +56 % over the six runs. On Rosenbrock's narrow valley
  // (k = 1000) it takes 70 iterations instead of 245 (test_levenberg_marquardt).
  // Statistical convergence of the shared parameters (problems that can measure it, i.e.
  // LmProblem::LastSharedStepMahalanobisSq; 0: off). With the cost 1/2 chi^2 (residuals in units
  // of their standard deviations), the shared part dp of a step measured in the metric of the
  // reduced system it solved, dp^T S dp, is its length in the shared parameters' own standard
  // deviations (S is their inverse covariance, the poses eliminated). A step shorter than
  // `shared_step_tolerance` of a standard deviation ends the solve, converged: what is left to
  // gain moves the estimate by less than the data can tell. Why: on real recordings (biobuddy,
  // 3,724 frames at 12 Hz) the last iterations gain 0.005-0.1 of a cost of 3,292 each, the poses
  // of a few frames still moving while the body model moves by 0.05-0.07 standard deviations a
  // step; the function tolerance (1e-6 of the cost) let that run on for up to 8 iterations, and
  // how many depended on the rounding (27-31 on one machine with 1 or 2 threads). Only a step
  // taken without a rejection in its iteration and at lambda <= 0.1 counts: the damping
  // shortens a step (S here includes it), and a step cut short by a large lambda is no evidence
  // of convergence. Like the function tolerance, it judges the step, not the way left along a
  // curved valley: on Rosenbrock's (k = 100) it stops with 0.024 of cost above the minimum, within
  // a quarter of a standard deviation by the likelihood (test_levenberg_marquardt). The global fit
  // uses it in its final stage only (FitOptions), whose residuals are weighted by the data's own
  // spread; a stage that assumes a sigma has no standard deviations to measure a step in. Only a
  // problem that eliminates the frames measures it (ArrowSchurProblem): a whole-system solve
  // (CholmodProblem) goes on to the function tolerance, so the two may stop at different points
  // within that tenth.
  double shared_step_tolerance = 0;
  // The function tolerance stops the solve only after a step whose gain ratio exceeds this: a
  // small decrease from a step the model predicted badly says nothing about how near the minimum
  // is. 0: every accepted step may stop it. In [0, 1).
  double function_tolerance_min_gain_ratio = 0;
  // After an accepted step whose gain ratio is below this, lambda rises as after a rejected step
  // with halve_rejected_steps (at least to where the model's minimiser along the step is half of
  // it, so at least 2x), not by Nielsen's at most 1.5x. 0: off. In [0, 1). Both are used by the
  // coarse-to-fine fine stage's variable projection (coarse_to_fine.h), on by default there.
  double raise_lambda_below_gain_ratio = 0;
  bool geodesic_acceleration = false;
  double acceleration_step = 0.02;
  double max_acceleration_ratio = 0.75;
  std::vector<IterationCallback> callbacks;
  // Optional: how well x fits the data alone, in the problem's own unit (the body fit: marker
  // RMS in mm, without the priors' rows that the cost also holds), evaluated after each
  // accepted step, before the callbacks, into IterationSummary::data_rms. The cost mixes data and
  // priors in units of sigma; a lab reads millimetres. It costs the problem one pass over its data
  // per iteration. x has the size of the problem being solved: a caller that solves a smaller
  // problem with these options (a coarse subset) must clear it.
  std::function<double(const Eigen::VectorXd& x)> data_rms;
  // Set by another thread (a daemon's fit.cancel): the solve stops before its next linear solve,
  // accepted or not, with x at the last accepted step (kUserCancelled). A callback's `false` is
  // only seen after an accepted step; a solve stuck rejecting steps would not see it for a while.
  const std::atomic<bool>* cancel = nullptr;

  bool IsValid(std::string* error) const;
};

struct LmSummary {
  TerminationType termination = TerminationType::kFailure;
  std::string message;
  double initial_cost = 0;
  double final_cost = 0;
  int num_parameters = 0;
  int num_residuals = 0;
  std::vector<IterationSummary> iterations;
  int num_linear_solves = 0;
  double total_seconds = 0;
  double linearize_seconds = 0;
  double linear_solver_seconds = 0;
  double cost_evaluation_seconds = 0;
  double inner_iteration_seconds = 0;
  // Geodesic acceleration: steps taken with an acceleration (accepted or not by the gain ratio),
  // steps refused by the test 2 |a| / |v| > alpha, acceleration solves that failed (plain step
  // taken), and their time (the residual pass at x + h v, J^T r_vv and the extra back-substitution).
  int num_accelerated_steps = 0;
  int num_acceleration_rejections = 0;
  int num_acceleration_failures = 0;
  double acceleration_seconds = 0;

  int num_iterations() const { return static_cast<int>(iterations.size()); }
  bool IsSolutionUsable() const { return termination != TerminationType::kFailure; }
  std::string BriefReport() const;
  std::string FullReport() const;
};

class LmProblem {
 public:
  virtual ~LmProblem() = default;
  virtual int num_parameters() const = 0;
  virtual int num_residuals() const = 0;
  // 1/2 ||r(x)||^2; false if r is not finite.
  virtual bool Cost(const Eigen::VectorXd& x, double* cost) = 0;
  // Linearises at x: cost, gradient J^T r and diag(J^T J). False if not finite.
  virtual bool Linearize(const Eigen::VectorXd& x, double* cost, Eigen::VectorXd* gradient,
                         Eigen::VectorXd* jtj_diagonal) = 0;
  // Solves (J^T J + diag(damping)) dx = -gradient at the last linearisation point.
  virtual bool SolveDamped(const Eigen::VectorXd& damping, Eigen::VectorXd* dx) = 0;
  // A hint before each Linearize: the next SolveDamped will most likely ask for damping =
  // lambda * clamp(jtj_diagonal, min_diagonal, max_diagonal), so a problem may prepare that
  // solve during the linearisation pass. Ignoring it is correct.
  virtual void AnticipateDamping(double lambda, double min_diagonal, double max_diagonal) {}
  // After an accepted step that did not end the solve, before x is linearised: the problem may
  // move *x to a point of no higher cost by a cheap partial minimisation (Ceres Solver's "inner
  // iterations": each frame's own block re-solved with the shared parameters fixed). The next
  // iteration's cost change includes what it gained. Doing nothing is correct.
  virtual void InnerIteration(Eigen::VectorXd* x) {}
  // Right after a step is accepted, before anything else: a problem whose Cost judged the
  // candidate at a point of its own (variable projection: the candidate's poses re-solved, at
  // the cost Cost returned) moves *x there, so that x always has the cost LM reports. Doing
  // nothing is correct for a problem whose Cost is the cost at the x it is given.
  virtual void StepAccepted(Eigen::VectorXd* x) {}
  // LmOptions::shared_step_tolerance: dp^T S dp of the last SolveDamped's step, S the damped
  // reduced system of the shared parameters it solved; NaN when the problem has no such split.
  virtual double LastSharedStepMahalanobisSq() const { return std::numeric_limits<double>::quiet_NaN(); }
  // Geodesic acceleration (LmOptions::geodesic_acceleration): solves (J^T J + damping) a = -J^T r_vv
  // at the last linearisation point, with `damping` that of the last SolveDamped (whose
  // factorisation it may reuse) and r_vv = (2 / h) ((r(x + h v) - r(x)) / h - J v). False: not
  // available (LM then takes the plain step v).
  virtual bool SolveAcceleration(const Eigen::VectorXd& damping, const Eigen::VectorXd& velocity, double h,
                                 Eigen::VectorXd* acceleration) {
    return false;
  }
};

// Minimises from *x in place. Never leaves a non-finite value in *x.
LmSummary Solve(const LmOptions& options, LmProblem* problem, Eigen::VectorXd* x);

}  // namespace mocap::solver
