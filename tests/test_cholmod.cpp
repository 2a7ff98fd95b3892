// The CHOLMOD sparse-normal-Cholesky LM step equals the dense solution of the damped normal
// equations and the Schur solver's step, for every assembly and ordering; a whole solve reaches
// the Schur solver's final cost.
#include <gtest/gtest.h>

#include "dense_reference.h"
#include "fit_test_util.h"
#include "solver/cholmod_solver.h"
#include "solver/global_fit.h"
#include "solver/marker_fit_problem.h"
#include "solver/schur_solver.h"
#include "tests/model_test_util.h"

using namespace mocap;
using Sparse = solver::SparseNormalCholeskyProblem;

namespace {
// Hides one marker of one frame while `hide` is set: a frame whose blocks change between
// linearisations (the Jacobian assemblies must notice and build their pattern again).
class HidingProblem : public solver::ArrowProblem {
 public:
  HidingProblem(solver::MarkerFitProblem* inner, int frame) : inner_(inner), frame_(frame) {}
  bool hide = false;
  int num_frames() const override { return inner_->num_frames(); }
  int frame_dim() const override { return inner_->frame_dim(); }
  int shared_dim() const override { return inner_->shared_dim(); }
  int num_residuals() const override { return inner_->num_residuals(); }
  bool SetShared(const Eigen::VectorXd& p) override { return inner_->SetShared(p); }
  const Eigen::VectorXd& prior_weight() const override { return inner_->prior_weight(); }
  const Eigen::VectorXd& prior_target() const override { return inner_->prior_target(); }
  const Eigen::MatrixXd& shared_rows() const override { return inner_->shared_rows(); }
  void BlockStructure(std::vector<std::vector<int>>* y, std::vector<std::vector<int>>* p) const override {
    inner_->BlockStructure(y, p);
  }
  std::unique_ptr<solver::FrameEvaluator> NewEvaluator() const override {
    return std::make_unique<Evaluator>(this, inner_->NewEvaluator());
  }

 private:
  class Evaluator : public solver::FrameEvaluator {
   public:
    Evaluator(const HidingProblem* owner, std::unique_ptr<solver::FrameEvaluator> inner)
        : owner_(owner), inner_(std::move(inner)) {}
    bool Evaluate(int frame, const double* y, bool jac) override {
      skip_ = owner_->hide && frame == owner_->frame_ ? 1 : 0;
      return inner_->Evaluate(frame, y, jac);
    }
    int num_blocks() const override { return inner_->num_blocks() - skip_; }
    const solver::ResidualBlock& block(int i) const override { return inner_->block(i + skip_); }

   private:
    const HidingProblem* owner_;
    std::unique_ptr<solver::FrameEvaluator> inner_;
    int skip_ = 0;
  };
  solver::MarkerFitProblem* inner_;
  int frame_;
};

struct SmallProblem {
  Model nominal = DefaultFullBodyModel();
  Eigen::MatrixXd z_true;
  formats::MarkerTrial trial;
  std::unique_ptr<solver::MarkerFitProblem> problem;
  Eigen::VectorXd x;
  explicit SmallProblem(int frames, unsigned seed = 5) {
    std::mt19937_64 rng(seed);
    const Model truth = mocap::testutil::Baked(nominal, testutil::PerturbedParameters(nominal, rng));
    trial = testutil::SimulateRandomMotion(truth, frames, 0.0005, rng, &z_true);
    // Missing samples, so frames differ in structure: two markers in frame 2, a whole frame,
    // and one marker in every third frame.
    trial.positions.block(2, 0, 1, 6).setConstant(NAN);
    if (frames > 4) trial.positions.row(4).setConstant(NAN);
    for (int f = 0; f < frames; f += 3) trial.positions.block(f, 3 * 7, 1, 3).setConstant(NAN);
    problem = std::make_unique<solver::MarkerFitProblem>(nominal, trial.positions, solver::FitOptions());
    const int ny = nominal.num_coordinates(), np = problem->shared_dim();
    x.resize(frames * ny + np);
    for (int f = 0; f < frames; ++f) x.segment(f * ny, ny) = z_true.row(f).transpose();
    x.tail(np) = problem->InitialShared() + 0.001 * Eigen::VectorXd::Random(np);
  }
};

double Relative(const Eigen::VectorXd& a, const Eigen::VectorXd& b) { return (a - b).norm() / b.norm(); }
}  // namespace

class CholmodStep : public ::testing::TestWithParam<std::tuple<Sparse::Assembly, Sparse::Ordering>> {};

TEST_P(CholmodStep, MatchesDenseNormalEquationsAndSchur) {
  SmallProblem sp(7);
  solver::MarkerFitProblem& problem = *sp.problem;
  const int n = static_cast<int>(sp.x.size());
  Sparse::Options options;
  options.assembly = std::get<0>(GetParam());
  options.ordering = std::get<1>(GetParam());
  Sparse cholmod(&problem, 2, options);
  ASSERT_TRUE(cholmod.ok()) << cholmod.error();
  EXPECT_EQ(cholmod.num_parameters(), n);
  solver::ArrowSchurProblem schur(&problem, 2);

  double cost, schur_cost;
  Eigen::VectorXd g, d, schur_g, schur_d;
  ASSERT_TRUE(cholmod.Linearize(sp.x, &cost, &g, &d));
  ASSERT_TRUE(schur.Linearize(sp.x, &schur_cost, &schur_g, &schur_d));
  Eigen::MatrixXd j;
  Eigen::VectorXd r;
  testutil::DenseJacobian(problem, sp.x, &j, &r);
  EXPECT_NEAR(cost, 0.5 * r.squaredNorm(), 1e-12 * cost);
  EXPECT_NEAR(cost, schur_cost, 1e-12 * cost);
  const Eigen::VectorXd g_dense = j.transpose() * r;
  EXPECT_LT(Relative(g, g_dense), 1e-12);
  const Eigen::MatrixXd jtj = j.transpose() * j;
  EXPECT_LT(Relative(d, jtj.diagonal()), 1e-12);
  double c2;
  ASSERT_TRUE(cholmod.Cost(sp.x, &c2));
  EXPECT_NEAR(c2, cost, 1e-12 * cost);

  for (double lambda : {1e-3, 1e-6}) {
    const Eigen::VectorXd damping = lambda * jtj.diagonal().cwiseMax(1e-6);
    Eigen::VectorXd dx, dx_schur;
    ASSERT_TRUE(cholmod.SolveDamped(damping, &dx));
    ASSERT_TRUE(schur.SolveDamped(damping, &dx_schur));
    Eigen::MatrixXd a = jtj;
    a.diagonal() += damping;
    const Eigen::VectorXd dx_dense = a.llt().solve(-g_dense);
    EXPECT_LT(Relative(dx, dx_dense), 1e-8) << "lambda " << lambda;
    EXPECT_LT(Relative(dx, dx_schur), 1e-8) << "lambda " << lambda;
    // The residual of the normal equations themselves, independent of any reference solver.
    EXPECT_LT((a * dx + g_dense).norm(), 1e-9 * g_dense.norm()) << "lambda " << lambda;
  }
  const Sparse::Statistics& s = cholmod.statistics();
  EXPECT_EQ(s.analyses, 1);
  EXPECT_EQ(s.factorizations, 2);
  EXPECT_GT(s.factor_nonzeros, 0);
  // Frames-first: stored in elimination order, so CHOLMOD's natural ordering (no copy per factor).
  if (options.ordering == Sparse::Ordering::kFramesFirst) {
    EXPECT_EQ(s.ordering_used, "natural");
  }
  if (options.ordering == Sparse::Ordering::kFramesFirstGiven) {
    EXPECT_EQ(s.ordering_used, "given");
  }
}

INSTANTIATE_TEST_SUITE_P(
    AllVariants, CholmodStep,
    ::testing::Combine(::testing::Values(Sparse::Assembly::kNormalMatrix, Sparse::Assembly::kJacobian,
                                         Sparse::Assembly::kJacobianProduct),
                       ::testing::Values(Sparse::Ordering::kFramesFirst,
                                         Sparse::Ordering::kFramesFirstGiven,
                                         Sparse::Ordering::kCholmod)),
    [](const auto& info) {
      return std::string(Sparse::ToString(std::get<0>(info.param))) + "_" +
             Sparse::ToString(std::get<1>(info.param));
    });

// A frame's blocks change between linearisations: the Jacobian assemblies rebuild their pattern
// (a second analysis) and the step still matches the dense one.
TEST(Cholmod, PatternRebuiltWhenBlocksChange) {
  SmallProblem sp(5);
  HidingProblem hiding(sp.problem.get(), 3);
  for (Sparse::Assembly assembly : {Sparse::Assembly::kJacobian, Sparse::Assembly::kJacobianProduct,
                                    Sparse::Assembly::kNormalMatrix}) {
    hiding.hide = false;
    Sparse::Options options;
    options.assembly = assembly;
    Sparse cholmod(&hiding, 1, options);
    double cost;
    Eigen::VectorXd g, d, dx;
    ASSERT_TRUE(cholmod.Linearize(sp.x, &cost, &g, &d));
    ASSERT_TRUE(cholmod.SolveDamped(1e-3 * d.cwiseMax(1e-6), &dx));
    hiding.hide = true;
    ASSERT_TRUE(cholmod.Linearize(sp.x, &cost, &g, &d));
    Eigen::MatrixXd j;
    Eigen::VectorXd r;
    testutil::DenseJacobian(hiding, sp.x, &j, &r);
    const Eigen::MatrixXd jtj = j.transpose() * j;
    const Eigen::VectorXd damping = 1e-3 * jtj.diagonal().cwiseMax(1e-6);
    ASSERT_TRUE(cholmod.SolveDamped(damping, &dx));
    Eigen::MatrixXd a = jtj;
    a.diagonal() += damping;
    EXPECT_LT(Relative(dx, a.llt().solve(-j.transpose() * r)), 1e-8) << Sparse::ToString(assembly);
    EXPECT_EQ(cholmod.statistics().analyses, assembly == Sparse::Assembly::kNormalMatrix ? 1 : 2);
  }
}

// A whole Levenberg–Marquardt solve from the same start reaches the Schur solver's final cost.
TEST(Cholmod, SolveReachesSchurCost) {
  SmallProblem sp(300, 11);
  solver::MarkerFitProblem& problem = *sp.problem;
  std::mt19937_64 rng(3);
  std::normal_distribution<double> noise(0.0, 0.02);
  const int ny = problem.frame_dim();
  for (int i = 0; i < problem.num_frames() * ny; ++i) sp.x[i] += noise(rng);
  sp.x.tail(problem.shared_dim()) = problem.InitialShared();
  solver::LmOptions lm = solver::FitOptions().lm;
  lm.function_tolerance = 1e-13;
  lm.parameter_tolerance = 1e-13;
  lm.max_iterations = 100;
  // The same minimum to 1e-9 from both linear solvers: no statistical stop (a Schur solve can
  // measure its shared step in standard deviations, CHOLMOD's whole-system solve cannot).
  lm.shared_step_tolerance = 0;
  Eigen::VectorXd x_schur = sp.x, x_cholmod = sp.x;
  solver::ArrowSchurProblem schur(&problem, 2);
  const solver::LmSummary s1 = solver::Solve(lm, &schur, &x_schur);
  Sparse cholmod(&problem, 2);
  const solver::LmSummary s2 = solver::Solve(lm, &cholmod, &x_cholmod);
  ASSERT_EQ(s1.termination, solver::TerminationType::kConvergence) << s1.message;
  ASSERT_EQ(s2.termination, solver::TerminationType::kConvergence) << s2.message;
  EXPECT_LT(s2.final_cost, 0.01 * s2.initial_cost);
  EXPECT_NEAR(s2.final_cost, s1.final_cost, 1e-9 * s1.final_cost)
      << "schur " << s1.BriefReport() << "\ncholmod " << s2.BriefReport();
  EXPECT_LT((x_cholmod - x_schur).lpNorm<Eigen::Infinity>(), 1e-5);
  EXPECT_EQ(cholmod.statistics().analyses, 1);
  std::printf("schur:   %s\ncholmod: %s\n", s1.BriefReport().c_str(), s2.BriefReport().c_str());
}

// Per-frame priors are not assembled by the CHOLMOD path yet: it must refuse, not ignore them.
TEST(SparseNormalCholesky, RefusesPerFramePriors) {
  std::mt19937_64 rng(9);
  Model nominal = DefaultFullBodyModel();
  formats::MarkerTrial trial = testutil::SimulateRandomMotion(nominal, 4, 0.0005, rng);
  solver::MarkerFitProblem problem(nominal, trial.positions, solver::FitOptions());
  Eigen::VectorXd x(4 * problem.frame_dim() + problem.shared_dim());
  x.setZero();
  x.tail(problem.shared_dim()) = problem.InitialShared();
  problem.SetFramePriorTargets(x);
  solver::SparseNormalCholeskyProblem cholmod(&problem, 1);
  double cost;
  Eigen::VectorXd g, d;
  EXPECT_FALSE(cholmod.Linearize(x, &cost, &g, &d));
  EXPECT_NE(cholmod.error().find("per-frame priors"), std::string::npos) << cholmod.error();
}
