#include "solver/levenberg_marquardt.h"

#include <chrono>
#include <cmath>
#include <cstdio>
#include <sstream>

namespace mocap::solver {
namespace {
using Clock = std::chrono::steady_clock;
double Since(Clock::time_point t) {
  return std::chrono::duration<double>(Clock::now() - t).count();
}
// The damping at which the quadratic model's minimiser along the step v (taken at `lambda`, with
// damping = lambda x the scaling S) is v / 2: v^T J^T J v / v^T S v + 2 lambda, from what LM
// already has (predicted = (lambda v^T S v - v^T g) / 2 and v^T J^T J v = -v^T g - lambda v^T S v);
// 0 when the step says nothing (halve_rejected_steps, raise_lambda_below_gain_ratio).
double HalvingLambda(const Eigen::VectorXd& v, const Eigen::VectorXd& damping, double lambda, double predicted) {
  const double vsv = v.dot(damping.cwiseProduct(v)) / lambda;
  const double vjjv = 2.0 * predicted - 2.0 * lambda * vsv;
  return vsv > 0 && vjjv > 0 ? vjjv / vsv + 2.0 * lambda : 0.0;
}
}  // namespace

const char* ToString(TerminationType type) {
  switch (type) {
    case TerminationType::kConvergence: return "CONVERGENCE";
    case TerminationType::kNoConvergence: return "NO_CONVERGENCE";
    case TerminationType::kUserCancelled: return "USER_CANCELLED";
    case TerminationType::kFailure: return "FAILURE";
  }
  return "?";
}

bool LmOptions::IsValid(std::string* error) const {
  auto fail = [&](const char* what) {
    if (error) *error = what;
    return false;
  };
  if (max_iterations < 0) return fail("max_iterations must be >= 0");
  if (!(max_seconds > 0)) return fail("max_seconds must be > 0");
  if (!(function_tolerance >= 0)) return fail("function_tolerance must be >= 0");
  if (!(shared_step_tolerance >= 0)) return fail("shared_step_tolerance must be >= 0");
  if (!(gradient_tolerance >= 0)) return fail("gradient_tolerance must be >= 0");
  if (!(parameter_tolerance >= 0)) return fail("parameter_tolerance must be >= 0");
  if (!(initial_lambda > 0)) return fail("initial_lambda must be > 0");
  if (!(min_lambda > 0 && min_lambda <= initial_lambda && initial_lambda <= max_lambda))
    return fail("need 0 < min_lambda <= initial_lambda <= max_lambda");
  if (!(min_diagonal > 0 && min_diagonal <= max_diagonal))
    return fail("need 0 < min_diagonal <= max_diagonal");
  if (!(min_gain_ratio >= 0 && min_gain_ratio < 1)) return fail("min_gain_ratio must be in [0, 1)");
  if (max_consecutive_rejections < 1) return fail("max_consecutive_rejections must be >= 1");
  if (!(acceleration_step > 0 && acceleration_step <= 1)) return fail("acceleration_step must be in (0, 1]");
  if (!(function_tolerance_min_gain_ratio >= 0 && function_tolerance_min_gain_ratio < 1))
    return fail("function_tolerance_min_gain_ratio must be in [0, 1)");
  if (!(raise_lambda_below_gain_ratio >= 0 && raise_lambda_below_gain_ratio < 1))
    return fail("raise_lambda_below_gain_ratio must be in [0, 1)");
  if (!(max_acceleration_ratio > 0)) return fail("max_acceleration_ratio must be > 0");
  return true;
}

std::string LmSummary::BriefReport() const {
  char buf[512];
  std::snprintf(buf, sizeof(buf),
                "Levenberg-Marquardt: %s, initial cost %.6e, final cost %.6e, %d iterations, "
                "%d linear solves, %.3f s (%s)",
                ToString(termination), initial_cost, final_cost, num_iterations(),
                num_linear_solves, total_seconds, message.c_str());
  std::string out = buf;
  if (num_accelerated_steps + num_acceleration_rejections + num_acceleration_failures > 0) {
    std::snprintf(buf, sizeof(buf),
                  "; geodesic acceleration: %d steps accelerated, %d refused (2|a|/|v| too large), "
                  "%d acceleration solves failed",
                  num_accelerated_steps, num_acceleration_rejections, num_acceleration_failures);
    out += buf;
  }
  return out;
}

std::string LmSummary::FullReport() const {
  std::ostringstream os;
  char buf[256];
  os << "Levenberg-Marquardt solver summary\n";
  std::snprintf(buf, sizeof(buf), "  parameters %d, residuals %d\n", num_parameters, num_residuals);
  os << buf;
  os << "  iter        cost      change   |gradient|       |step|       lambda   gain  accept  time(s)\n";
  for (const auto& it : iterations) {
    std::snprintf(buf, sizeof(buf), "  %4d %11.5e %11.4e %11.4e %11.4e %11.4e %6.3f %6s %8.3f\n",
                  it.iteration, it.cost, it.cost_change, it.gradient_max_norm, it.step_norm,
                  it.lambda, it.gain_ratio, it.step_accepted ? "yes" : "no", it.total_seconds);
    os << buf;
  }
  std::snprintf(buf, sizeof(buf),
                "  initial cost %.8e\n  final cost   %.8e\n  time: linearize %.3f s, linear "
                "solver %.3f s, cost %.3f s, inner iterations %.3f s, total %.3f s\n",
                initial_cost, final_cost, linearize_seconds, linear_solver_seconds,
                cost_evaluation_seconds, inner_iteration_seconds, total_seconds);
  os << buf;
  if (num_accelerated_steps + num_acceleration_rejections + num_acceleration_failures > 0) {
    std::snprintf(buf, sizeof(buf),
                  "  geodesic acceleration: %d steps accelerated, %d refused (2|a|/|v| too large), %d solves "
                  "failed, %.3f s\n",
                  num_accelerated_steps, num_acceleration_rejections, num_acceleration_failures,
                  acceleration_seconds);
    os << buf;
  }
  os << "  termination: " << ToString(termination) << " (" << message << ")\n";
  return os.str();
}

LmSummary Solve(const LmOptions& options, LmProblem* problem, Eigen::VectorXd* x) {
  LmSummary summary;
  const auto start = Clock::now();
  summary.num_parameters = problem->num_parameters();
  summary.num_residuals = problem->num_residuals();
  std::string why;
  if (!options.IsValid(&why)) {
    summary.message = "invalid options: " + why;
    return summary;
  }
  if (x->size() != problem->num_parameters() || !x->allFinite()) {
    summary.message = "initial parameters have the wrong size or are not finite";
    return summary;
  }

  Eigen::VectorXd gradient, diagonal, damping, dx, x_new, acceleration;
  double cost = 0;
  auto t = Clock::now();
  problem->AnticipateDamping(options.initial_lambda, options.min_diagonal, options.max_diagonal);
  if (!problem->Linearize(*x, &cost, &gradient, &diagonal)) {
    summary.message = "residuals or Jacobian not finite at the initial parameters";
    summary.total_seconds = Since(start);
    return summary;
  }
  summary.linearize_seconds += Since(t);
  summary.initial_cost = summary.final_cost = cost;
  double lambda = options.initial_lambda, nu = 2.0;
  int rejections = 0;

  auto finish = [&](TerminationType type, std::string message) {
    summary.termination = type;
    summary.message = std::move(message);
    summary.final_cost = cost;
    summary.total_seconds = Since(start);
    return summary;
  };

  if (gradient.lpNorm<Eigen::Infinity>() <= options.gradient_tolerance)
    return finish(TerminationType::kConvergence, "gradient tolerance reached at the start");

  for (int iteration = 1;; ++iteration) {
    if (iteration > options.max_iterations)
      return finish(TerminationType::kNoConvergence, "maximum number of iterations reached");
    if (Since(start) > options.max_seconds)
      return finish(TerminationType::kNoConvergence, "maximum time reached");
    const auto iteration_start = Clock::now();
    IterationSummary it;
    it.iteration = iteration;

    // Inner loop: raise lambda until a step is accepted or we give up.
    for (;;) {
      if (options.cancel && options.cancel->load(std::memory_order_relaxed))
        return finish(TerminationType::kUserCancelled, "cancelled");
      damping = lambda * diagonal.cwiseMax(options.min_diagonal).cwiseMin(options.max_diagonal);
      t = Clock::now();
      const bool solved = problem->SolveDamped(damping, &dx);
      summary.linear_solver_seconds += Since(t);
      ++it.linear_solves;
      ++summary.num_linear_solves;
      double new_cost = std::numeric_limits<double>::infinity();
      double predicted = 0;
      double acceleration_ratio = 0;
      bool refused = false, accelerated = false;
      if (solved && dx.allFinite()) {
        // The quadratic model's decrease for the velocity dx, with or without an acceleration.
        predicted = 0.5 * (dx.dot(damping.cwiseProduct(dx)) - dx.dot(gradient));
        x_new = *x + dx;
        if (options.geodesic_acceleration) {
          t = Clock::now();
          if (problem->SolveAcceleration(damping, dx, options.acceleration_step, &acceleration) &&
              acceleration.allFinite()) {
            // The damping is lambda times the scaling: the ratio does not depend on lambda.
            const double v_norm = std::sqrt(dx.dot(damping.cwiseProduct(dx)));
            acceleration_ratio = 2.0 * std::sqrt(acceleration.dot(damping.cwiseProduct(acceleration))) /
                                 std::max(v_norm, std::numeric_limits<double>::min());
            if (acceleration_ratio > options.max_acceleration_ratio) {
              refused = true;
              ++summary.num_acceleration_rejections;
            } else {
              x_new += 0.5 * acceleration;
              accelerated = true;
              ++summary.num_accelerated_steps;
            }
          } else {
            ++summary.num_acceleration_failures;
          }
          summary.acceleration_seconds += Since(t);
        }
        if (!refused) {
          t = Clock::now();
          if (!problem->Cost(x_new, &new_cost)) new_cost = std::numeric_limits<double>::infinity();
          summary.cost_evaluation_seconds += Since(t);
        }
      }
      const double actual = cost - new_cost;
      const double rho = predicted > 0 ? actual / predicted : -1.0;
      it.step_norm = !solved || refused ? 0.0 : accelerated ? (dx + 0.5 * acceleration).norm() : dx.norm();
      it.acceleration_ratio = refused ? 0.0 : acceleration_ratio;
      it.gain_ratio = std::isfinite(rho) ? rho : -1.0;
      if (std::isfinite(new_cost) && rho > options.min_gain_ratio) {
        // Accept.
        const double step_lambda = lambda;
        const double parameter_norm = x->norm();
        x->swap(x_new);
        problem->StepAccepted(x);
        const double old_cost = cost;
        lambda = std::max(options.min_lambda,
                          lambda * std::max(1.0 / 3.0, 1.0 - std::pow(2.0 * rho - 1.0, 3)));
        if (rho < options.raise_lambda_below_gain_ratio)
          lambda = std::max(lambda, HalvingLambda(dx, damping, step_lambda, predicted));
        nu = 2.0;
        rejections = 0;
        it.step_accepted = true;
        it.lambda = lambda;
        // The function and parameter tolerances need no Jacobian: when one is met the solve ends
        // here and the final point is not linearised (one pass over all the data saved; Ceres
        // does the same). The gradient reported is then the previous iterate's.
        const char* converged = nullptr;
        if (old_cost - new_cost <= options.function_tolerance * old_cost &&
            rho > options.function_tolerance_min_gain_ratio)
          converged = "function tolerance reached";
        else if (it.step_norm <= options.parameter_tolerance * (parameter_norm + options.parameter_tolerance))
          converged = "parameter tolerance reached";
        else if (options.shared_step_tolerance > 0 && it.linear_solves == 1 && step_lambda <= 0.1 && !accelerated) {
          const double mahalanobis_sq = problem->LastSharedStepMahalanobisSq();
          if (mahalanobis_sq < options.shared_step_tolerance * options.shared_step_tolerance)
            converged = "the shared parameters' step is below their tolerance in standard deviations";
        }
        if (converged == nullptr) {
          t = Clock::now();
          problem->InnerIteration(x);
          summary.inner_iteration_seconds += Since(t);
          problem->AnticipateDamping(lambda, options.min_diagonal, options.max_diagonal);
          t = Clock::now();
          if (!problem->Linearize(*x, &cost, &gradient, &diagonal)) {
            // Cannot happen for a finite cost in exact arithmetic; step back to the last good x.
            x->swap(x_new);  // x_new holds the last good x since the swap above
            cost = old_cost;
            return finish(TerminationType::kNoConvergence, "Jacobian not finite after a step");
          }
          summary.linearize_seconds += Since(t);
        } else {
          cost = new_cost;
        }
        it.cost_change = old_cost - cost;
        it.cost = cost;
        if (options.data_rms) it.data_rms = options.data_rms(*x);
        it.gradient_max_norm = gradient.lpNorm<Eigen::Infinity>();
        it.iteration_seconds = Since(iteration_start);
        it.total_seconds = Since(start);
        summary.iterations.push_back(it);
        for (const auto& cb : options.callbacks)
          if (!cb(it)) return finish(TerminationType::kUserCancelled, "cancelled by the callback");
        if (converged != nullptr) return finish(TerminationType::kConvergence, converged);
        if (it.gradient_max_norm <= options.gradient_tolerance)
          return finish(TerminationType::kConvergence, "gradient tolerance reached");
        break;
      }
      // Reject.
      double halving = 0;
      if (options.halve_rejected_steps && solved && dx.allFinite())
        halving = HalvingLambda(dx, damping, lambda, predicted);
      lambda = std::max(lambda * nu, halving);
      nu *= 2.0;
      ++rejections;
      if (lambda > options.max_lambda || rejections >= options.max_consecutive_rejections) {
        it.cost = cost;
        if (!summary.iterations.empty()) it.data_rms = summary.iterations.back().data_rms;
        it.lambda = lambda;
        it.gradient_max_norm = gradient.lpNorm<Eigen::Infinity>();
        it.iteration_seconds = Since(iteration_start);
        it.total_seconds = Since(start);
        summary.iterations.push_back(it);
        // No step decreases the cost any more: at the floating-point floor of a minimum.
        return finish(TerminationType::kConvergence,
                      "no further decrease possible (damping at its limit)");
      }
    }
  }
}

}  // namespace mocap::solver
