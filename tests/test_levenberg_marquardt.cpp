// solver::Solve's geodesic acceleration (LmOptions::geodesic_acceleration) on small dense problems
// with a known minimum: Rosenbrock's valley, the curved canyon Transtrum and Sethna's method is for.
#include <gtest/gtest.h>

#include <Eigen/Cholesky>
#include <Eigen/Core>
#include <cstdio>
#include <functional>
#include <string>

#include "solver/levenberg_marquardt.h"

using namespace mocap;

namespace {

// r(x) dense, with its Jacobian; the damped solves by dense Cholesky. `accelerate` false: the
// problem offers no acceleration (LmProblem's default), as a problem without the per-frame cache.
class DenseProblem : public solver::LmProblem {
 public:
  using Residuals = std::function<Eigen::VectorXd(const Eigen::VectorXd&)>;
  using Jacobian = std::function<Eigen::MatrixXd(const Eigen::VectorXd&)>;
  DenseProblem(int n, int m, Residuals r, Jacobian j, bool accelerate)
      : n_(n), m_(m), r_(std::move(r)), j_(std::move(j)), accelerate_(accelerate) {}
  int num_parameters() const override { return n_; }
  int num_residuals() const override { return m_; }
  bool Cost(const Eigen::VectorXd& x, double* cost) override {
    *cost = 0.5 * r_(x).squaredNorm();
    return std::isfinite(*cost);
  }
  bool Linearize(const Eigen::VectorXd& x, double* cost, Eigen::VectorXd* gradient,
                 Eigen::VectorXd* diagonal) override {
    x_ = x;
    res_ = r_(x);
    jac_ = j_(x);
    *cost = 0.5 * res_.squaredNorm();
    *gradient = jac_.transpose() * res_;
    *diagonal = jac_.colwise().squaredNorm().transpose();
    return std::isfinite(*cost);
  }
  bool SolveDamped(const Eigen::VectorXd& damping, Eigen::VectorXd* dx) override {
    *dx = Factor(damping).solve(-(jac_.transpose() * res_));
    // Every parameter counts as shared (LmOptions::shared_step_tolerance): dx^T (J^T J + D) dx.
    step_sq_ = -dx->dot(jac_.transpose() * res_);
    return dx->allFinite();
  }
  double LastSharedStepMahalanobisSq() const override { return step_sq_; }
  bool SolveAcceleration(const Eigen::VectorXd& damping, const Eigen::VectorXd& v, double h,
                         Eigen::VectorXd* a) override {
    if (!accelerate_) return false;
    const Eigen::VectorXd rvv = (2.0 / h) * ((r_(x_ + h * v) - res_) / h - jac_ * v);
    *a = Factor(damping).solve(-(jac_.transpose() * rvv));
    return a->allFinite();
  }

 private:
  Eigen::LLT<Eigen::MatrixXd> Factor(const Eigen::VectorXd& damping) const {
    Eigen::MatrixXd m = jac_.transpose() * jac_;
    m.diagonal() += damping;
    return Eigen::LLT<Eigen::MatrixXd>(m);
  }
  int n_, m_;
  Residuals r_;
  Jacobian j_;
  bool accelerate_;
  Eigen::VectorXd x_, res_;
  Eigen::MatrixXd jac_;
  double step_sq_ = 0;
};

// Rosenbrock as least squares: r = (k (x2 - x1^2), 1 - x1), minimum 0 at (1, 1); k sets how
// narrow the curved valley is.
DenseProblem Rosenbrock(double k, bool accelerate) {
  return DenseProblem(
      2, 2,
      [k](const Eigen::VectorXd& x) { return Eigen::Vector2d(k * (x[1] - x[0] * x[0]), 1.0 - x[0]).eval(); },
      [k](const Eigen::VectorXd& x) {
        Eigen::Matrix2d j;
        j << -2.0 * k * x[0], k, -1.0, 0.0;
        return Eigen::MatrixXd(j);
      },
      accelerate);
}

solver::LmOptions Options(bool geodesic) {
  solver::LmOptions o;
  o.geodesic_acceleration = geodesic;
  o.max_iterations = 500;
  o.function_tolerance = 0;  // run to the gradient or parameter tolerance
  o.gradient_tolerance = 1e-12;
  o.parameter_tolerance = 1e-14;
  return o;
}

}  // namespace

TEST(LevenbergMarquardt, GeodesicAccelerationFollowsTheCurvedValleyInFewerIterations) {
  for (double k : {10.0, 100.0, 1000.0}) {
    SCOPED_TRACE("valley steepness " + std::to_string(k));
    Eigen::VectorXd plain_x = Eigen::Vector2d(-1.2, 1.0), accel_x = plain_x;
    DenseProblem plain_problem = Rosenbrock(k, true), accel_problem = Rosenbrock(k, true);
    const solver::LmSummary plain = solver::Solve(Options(false), &plain_problem, &plain_x);
    const solver::LmSummary accel = solver::Solve(Options(true), &accel_problem, &accel_x);
    ASSERT_EQ(accel.termination, solver::TerminationType::kConvergence) << accel.FullReport();
    EXPECT_NEAR(accel_x[0], 1.0, 1e-6);
    EXPECT_NEAR(accel_x[1], 1.0, 1e-6);
    EXPECT_LT(accel.final_cost, 1e-12);
    EXPECT_GT(accel.num_accelerated_steps, 0);
    EXPECT_EQ(accel.num_acceleration_failures, 0);
    // Measured (these options): k = 10, 100, 1000: plain 24, 68, 245 iterations; accelerated 23,
    // 39, 70 (20, 24, 29 steps refused by the ratio test). The narrower the valley, the more it gains.
    EXPECT_LT(accel.num_iterations(), plain.num_iterations()) << plain.FullReport() << accel.FullReport();
    EXPECT_EQ(plain.num_accelerated_steps + plain.num_acceleration_rejections, 0);
    EXPECT_NE(accel.BriefReport().find("geodesic acceleration"), std::string::npos);
  }
}

TEST(LevenbergMarquardt, WithoutAnAccelerationSolveTheStepsArePlain) {
  Eigen::VectorXd plain_x = Eigen::Vector2d(-1.2, 1.0), x = plain_x;
  DenseProblem plain_problem = Rosenbrock(100, false), problem = Rosenbrock(100, false);
  const solver::LmSummary plain = solver::Solve(Options(false), &plain_problem, &plain_x);
  const solver::LmSummary s = solver::Solve(Options(true), &problem, &x);
  EXPECT_EQ(s.num_iterations(), plain.num_iterations());
  EXPECT_EQ(s.num_accelerated_steps, 0);
  EXPECT_GT(s.num_acceleration_failures, 0);
  EXPECT_EQ(x, plain_x);  // bit for bit: the same steps
}

TEST(LevenbergMarquardt, AccelerationOptionsAreValidated) {
  std::string why;
  solver::LmOptions o;
  EXPECT_TRUE(o.IsValid(&why));
  o.acceleration_step = 0;
  EXPECT_FALSE(o.IsValid(&why));
  EXPECT_NE(why.find("acceleration_step"), std::string::npos);
  o.acceleration_step = 0.02;
  o.max_acceleration_ratio = -1;
  EXPECT_FALSE(o.IsValid(&why));
  EXPECT_NE(why.find("max_acceleration_ratio"), std::string::npos);
  // Invalid options fail the solve with the reason, before any evaluation.
  Eigen::VectorXd x = Eigen::Vector2d(-1.2, 1.0);
  DenseProblem problem = Rosenbrock(10, true);
  const solver::LmSummary s = solver::Solve(o, &problem, &x);
  EXPECT_EQ(s.termination, solver::TerminationType::kFailure);
  EXPECT_NE(s.message.find("max_acceleration_ratio"), std::string::npos);
}

// LmOptions::halve_rejected_steps: from a Gauss–Newton-like start (lambda 1e-8) a rejected step
// raises lambda at once to where the model's minimiser along it is half as long, instead of
// doubling lambda through re-solves that give nearly the same step: the first accepted step
// costs far fewer solves (measured, k = 10, 100, 1000: 7, 6, 4 doubling, 2, 2, 2 halving), and
// the minimum is the same. (Over a whole Rosenbrock solve it is no
// better than Nielsen's rule: measured, k = 10, 100, 1000: 39, 84, 248 solves doubling, 29, 83,
// 270 halving. It is for the coarse-to-fine fine stage's start, coarse_to_fine.h.)
TEST(LevenbergMarquardt, HalvingARejectedStepSavesTheResolvesOfNielsensDoubling) {
  for (double k : {10.0, 100.0, 1000.0}) {
    SCOPED_TRACE("valley steepness " + std::to_string(k));
    solver::LmOptions doubling = Options(false), halving = Options(false);
    doubling.initial_lambda = halving.initial_lambda = 1e-8;
    halving.halve_rejected_steps = true;
    Eigen::VectorXd x_doubling = Eigen::Vector2d(-1.2, 1.0), x_halving = x_doubling;
    DenseProblem p_doubling = Rosenbrock(k, false), p_halving = Rosenbrock(k, false);
    const solver::LmSummary d = solver::Solve(doubling, &p_doubling, &x_doubling);
    const solver::LmSummary h = solver::Solve(halving, &p_halving, &x_halving);
    ASSERT_EQ(h.termination, solver::TerminationType::kConvergence) << h.FullReport();
    EXPECT_NEAR(x_halving[0], 1.0, 1e-6);
    EXPECT_NEAR(x_halving[1], 1.0, 1e-6);
    ASSERT_FALSE(d.iterations.empty());
    ASSERT_FALSE(h.iterations.empty());
    EXPECT_LT(h.iterations[0].linear_solves, d.iterations[0].linear_solves) << d.FullReport() << h.FullReport();
  }
}

// LmOptions::shared_step_tolerance: with the residuals in units of their standard deviations,
// the solve ends once a step is shorter than a tenth of a standard deviation (dx^T (J^T J + D) dx
// below 0.01), in fewer iterations than the function tolerance's. What that promises is local: in
// Rosenbrock's curved valley (k = 100) LM crawls along the floor in steps of that size, and the
// solve stops with 0.024 of cost left (the minimum's is 0): within a quarter of a standard
// deviation by the likelihood (cost excess below 1/2 0.25^2), though 4.3 standard deviations away
// in the metric of the linearisation at the minimum, which does not follow the valley's bend.
// And a step kept short by a large damping is no evidence: from lambda 1e6 the first steps are
// 1e-6 standard deviations long, and the solve still reaches the minimum.
TEST(LevenbergMarquardt, AStepBelowATenthOfAStandardDeviationEndsTheSolve) {
  for (double k : {10.0, 100.0}) {
    SCOPED_TRACE("valley steepness " + std::to_string(k));
    solver::LmOptions tight = Options(false), statistical = Options(false);
    tight.function_tolerance = 1e-12;
    statistical.function_tolerance = 1e-12;
    statistical.shared_step_tolerance = 0.1;
    Eigen::VectorXd x_tight = Eigen::Vector2d(-1.2, 1.0), x_statistical = x_tight;
    DenseProblem p_tight = Rosenbrock(k, false), p_statistical = Rosenbrock(k, false);
    const solver::LmSummary t = solver::Solve(tight, &p_tight, &x_tight);
    const solver::LmSummary s = solver::Solve(statistical, &p_statistical, &x_statistical);
    ASSERT_EQ(s.termination, solver::TerminationType::kConvergence) << s.FullReport();
    EXPECT_NE(s.message.find("standard deviations"), std::string::npos) << s.message;
    EXPECT_LT(s.num_iterations(), t.num_iterations());
    EXPECT_LT(s.final_cost, 0.5 * 0.25 * 0.25) << x_statistical.transpose() << s.FullReport();
    std::printf("k %.0f: stopped after %d iterations (function tolerance: %d) at cost %.4f, (%.4f, %.4f)\n", k,
                s.num_iterations(), t.num_iterations(), s.final_cost, x_statistical[0], x_statistical[1]);
  }
  solver::LmOptions damped = Options(false);
  damped.shared_step_tolerance = 0.1;
  damped.initial_lambda = 1e6;
  Eigen::VectorXd x = Eigen::Vector2d(-1.2, 1.0);
  DenseProblem p = Rosenbrock(10.0, false);
  const solver::LmSummary d = solver::Solve(damped, &p, &x);
  ASSERT_EQ(d.termination, solver::TerminationType::kConvergence) << d.FullReport();
  EXPECT_GT(d.num_iterations(), 3);
  EXPECT_NEAR(x[0], 1.0, 0.05);
  EXPECT_NEAR(x[1], 1.0, 0.1);
  std::string error;
  damped.shared_step_tolerance = -1;
  EXPECT_FALSE(damped.IsValid(&error));
  EXPECT_NE(error.find("shared_step_tolerance"), std::string::npos) << error;
}

// LmOptions::function_tolerance_min_gain_ratio: a small decrease from a step the quadratic model
// predicted badly (gain ratio below the bound) does not end the solve; the solve then stops only
// on a step the model predicted well, and at least as low.
TEST(LevenbergMarquardt, APoorlyPredictedStepDoesNotEndTheSolveOnTheFunctionTolerance) {
  int differed = 0;
  for (double k : {10.0, 100.0, 1000.0}) {
    for (double tolerance : {1e-2, 1e-3}) {
      SCOPED_TRACE("valley steepness " + std::to_string(k) + ", tolerance " + std::to_string(tolerance));
      solver::LmOptions plain = Options(false), judged = Options(false);
      plain.function_tolerance = judged.function_tolerance = tolerance;
      judged.function_tolerance_min_gain_ratio = 0.25;
      Eigen::VectorXd x_plain = Eigen::Vector2d(-1.2, 1.0), x_judged = x_plain;
      DenseProblem p_plain = Rosenbrock(k, false), p_judged = Rosenbrock(k, false);
      const solver::LmSummary a = solver::Solve(plain, &p_plain, &x_plain);
      const solver::LmSummary b = solver::Solve(judged, &p_judged, &x_judged);
      ASSERT_EQ(b.termination, solver::TerminationType::kConvergence) << b.FullReport();
      ASSERT_FALSE(b.iterations.empty());
      if (b.message == "function tolerance reached") EXPECT_GT(b.iterations.back().gain_ratio, 0.25) << b.FullReport();
      EXPECT_LE(b.final_cost, a.final_cost) << a.FullReport() << b.FullReport();
      if (!a.iterations.empty() && a.message == "function tolerance reached" && a.iterations.back().gain_ratio <= 0.25)
        ++differed;
    }
  }
  // The bound must have mattered somewhere, or this test shows nothing.
  EXPECT_GT(differed, 0);
}

// LmOptions::raise_lambda_below_gain_ratio: after an accepted step the model predicted badly,
// lambda rises at least to twice the step's (the halving rule's lambda' = v^T J^T J v / v^T S v +
// 2 lambda), instead of Nielsen's at most 1.5x; the minimum is the same.
TEST(LevenbergMarquardt, APoorlyPredictedAcceptedStepRaisesTheDamping) {
  int raised = 0;
  for (double k : {10.0, 100.0, 1000.0}) {
    SCOPED_TRACE("valley steepness " + std::to_string(k));
    solver::LmOptions o = Options(false);
    o.raise_lambda_below_gain_ratio = 0.25;
    Eigen::VectorXd x = Eigen::Vector2d(-1.2, 1.0);
    DenseProblem p = Rosenbrock(k, false);
    const solver::LmSummary s = solver::Solve(o, &p, &x);
    ASSERT_EQ(s.termination, solver::TerminationType::kConvergence) << s.FullReport();
    EXPECT_NEAR(x[0], 1.0, 1e-6);
    EXPECT_NEAR(x[1], 1.0, 1e-6);
    for (size_t i = 1; i < s.iterations.size(); ++i) {
      const solver::IterationSummary& it = s.iterations[i];
      // The step's lambda is the previous iteration's when this one solved once.
      if (!it.step_accepted || it.linear_solves != 1 || !(it.gain_ratio < 0.25)) continue;
      EXPECT_GE(it.lambda, 2.0 * s.iterations[i - 1].lambda) << "iteration " << it.iteration << s.FullReport();
      ++raised;
    }
  }
  EXPECT_GT(raised, 0);
  std::string error;
  solver::LmOptions bad;
  bad.raise_lambda_below_gain_ratio = 1.5;
  EXPECT_FALSE(bad.IsValid(&error));
  EXPECT_NE(error.find("raise_lambda_below_gain_ratio"), std::string::npos) << error;
  bad = solver::LmOptions();
  bad.function_tolerance_min_gain_ratio = -0.5;
  EXPECT_FALSE(bad.IsValid(&error));
  EXPECT_NE(error.find("function_tolerance_min_gain_ratio"), std::string::npos) << error;
}
