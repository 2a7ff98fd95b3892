// A coarse-to-fine start for arrow problems (solver/arrow_problem.h) with many similar frames:
// the global body-model fit over thousands of frames of a few repeated movements.
//
// Levenberg–Marquardt from per-frame IK with the nominal geometry takes 6-7 linearisations of
// the whole problem to reach the minimum, though the shared parameters p are determined by far
// fewer frames than are given: a tenth of them, evenly spread over every trial, covers every
// movement's range and fixes p to well within its final uncertainty's scale. So:
//
//  1. Coarse. The same problem restricted to `coarse_frames` evenly spaced frames (the same
//     residuals, weights, frame priors, p priors and gauge rows; only the frame set differs) is
//     solved by LM to a loose tolerance: p moves most of the way at a tenth of the cost.
//  2. Poses. Every frame's pose is re-solved for that p with p held fixed: a few damped
//     Gauss–Newton steps per frame on the frame's own residuals and prior (a step is kept only
//     if it lowers the frame's cost), so poses and geometry agree before the full problem is
//     linearised. Cheap: no shared columns, a 38 x 38 solve per frame.
//  3. Fine. LM on the whole problem from there with the caller's tolerances: the same minimum
//     and stopping rule as a plain solve (the coarse stage only moves the start). Two changes,
//     both because it starts near the minimum: the initial damping is Gauss–Newton-like
//     (fine_initial_lambda), and after each accepted step every pose is re-solved for the new
//     geometry (LmProblem::InnerIteration, as Ceres's inner iterations), which takes the step's
//     shortfall in the weakly seen coordinates. Measured on the default protocol: 2 whole-problem
//     linearisations instead of 6 at 6,000 frames and 7 at 60,000 (BENCHMARKS.md).
//
// This is the multi-resolution idea of bundle adjustment over keyframes first (e.g. Mouragnon et
// al., "Real time localization and 3D reconstruction", CVPR 2006) applied to frames of motion:
// the subset is a statistical sample of the same problem, not a different model.
//
// Problems with fewer than `min_frames` frames are solved directly (their plain solve is cheap
// and a sample of them would not determine p), and so is a problem whose subset LM does not
// converge within its budget: that happened when frames in long marker gaps, held only by their
// weak priors, made LM crawl (10 % missing samples in gaps of 5-30 frames, before
// UnobservedCoordinateWeights and the rescue below: now 24 subset iterations). The subset's
// geometry is then no good start; measured, starting from it cost 30 % more time and ended
// higher than the plain solve, so the plain solve runs from the caller's x (the subset's
// iterations, about 5 % of the plain solve, are lost).
#pragma once

#include <Eigen/Core>
#include <limits>
#include <string>
#include <vector>

#include "solver/arrow_problem.h"
#include "solver/levenberg_marquardt.h"
#include "solver/schur_solver.h"

namespace mocap::solver {

struct CoarseToFineOptions {
  bool enabled = true;
  int min_frames = 3000;          // fewer frames: a plain solve
  // Frames of the coarse stage, evenly spaced. Stage 3 ends after two linearisations when its
  // second step gains less than the function tolerance (0.059 at 6,000 frames); that step's gain
  // is second order in what the subset got wrong. Measured at 6,000 frames: 300 -> 0.080 and
  // 500 -> 0.125 (a third linearisation), 400 -> 0.029, 600 -> 0.049, 700 -> 0.032,
  // 800 -> 0.022, 1,000 -> 0.026; at 60,000 frames 800 -> 0.24 of 0.59. 800 keeps a margin
  // for 0.05 s more than 600.
  int coarse_frames = 800;
  double coarse_function_tolerance = 1e-5;
  int coarse_max_iterations = 50;
  // Stage 2: each frame starts from its predecessor's correction (consecutive frames need nearly
  // the same one: the geometry changed, the motion hardly) and takes one damped Gauss–Newton
  // step; what that leaves, stage 3's inner iterations take. A frame the correction does not
  // suit (the first of a thread's run, a trial boundary) starts from its given pose and takes
  // up to pose_iterations steps, stopping once a step gains less than pose_tolerance of its cost
  // (with quadratic convergence the next would gain about nothing).
  int pose_iterations = 8;
  double pose_tolerance = 0.5;
  bool pose_from_predecessor = true;
  // Stage 3: after each accepted step every pose is re-solved for the new geometry
  // (LmProblem::InnerIteration): Gauss–Newton steps until one gains no more than the fine LM's
  // function tolerance times the cost, at most inner_pose_iterations. One step a frame (the
  // earlier rule) left frames whose cost is far from quadratic in a weakly seen coordinate
  // (marker gaps) far from their own minimum, and the whole problem crawled after them
  // (BENCHMARKS.md, "With gaps").
  bool inner_iterations = true;
  int inner_pose_iterations = 10;
  double pose_damping = 1e-6;     // relative to diag(J_y^T J_y), for steps in badly seen frames
  // Every per-frame pose step above (stages 2 and 3, the rescue) is Gauss–Newton and stops at the
  // first step that does not lower the frame's cost. A frame whose cost is far from quadratic in
  // a weakly seen angle (a forearm's pro-supination with its markers hidden) then stays away from
  // its own minimum, and the next whole-problem step, which linearises it there, turns it by up
  // to 1 rad and is rejected (BENCHMARKS.md, "With gaps", eleventh and twelfth sessions). With
  // pose_step_retries > 0 a failed step is retried with a damping 100 times higher (at least
  // 1e-3), and every step is shortened to pose_step_cap (rad or m) in its largest component, so
  // such a frame creeps towards its own minimum instead of leaping into another branch. Off by
  // default, measured at 6,000 frames, 0.8 mm noise (twelfth session; retries 2, cap 0.1): whole-
  // problem iterations at 5 % / 10 % missing, seeds 1-3: 7, 2, 5 / 7, 10, 15 -> 5, 4, 5 / 7, 5, 4
  // (CPU 31.7 -> 24.4 s in all), centres within +-0.02 mm of the default's, but the end costs
  // differ by -143 to +30 (other branches in some frames) and 5 % seed 2 takes 4 iterations
  // instead of 2; in FitModel's staged fit at 10 % (test_sim_fit) 25 iterations instead of 47,
  // but the weakest axes further from the truth (wrist_r 11.9 -> 15.2 deg); test_real_fit's
  // figures unchanged. Without the cap (retries alone) frames walk into other branches (10 %
  // seed 2: 0.592 mm from the truth); the cap is a narrow optimum (0.05 and 0.2 are worse).
  int pose_step_retries = 0;
  double pose_step_cap = std::numeric_limits<double>::infinity();
  // Stage 3 starts near the minimum, where Ceres's initial damping (LmOptions::initial_lambda,
  // 1e-4) only slows the weakly determined directions (a parameter held mostly by its prior has
  // a curvature far below 1e-4 of its data diagonal): each LM step would close only part of their
  // gap. Gauss–Newton-like steps from the start; Nielsen's rule raises it if a step fails.
  double fine_initial_lambda = 1e-8;
  // Stage 3 with LmOptions::halve_rejected_steps: a step rejected at that Gauss–Newton-like
  // damping (frames in marker gaps whose cost is far from quadratic, e.g. a hidden forearm's
  // pro-supination) raised lambda 2x, 4x, 8x, 16x, 32x: five re-solves of the whole problem, each
  // a pass over every frame, to reach ~3e-4. Measured at 6,000 frames, 0.8 mm noise, seeds 1-3
  // (BENCHMARKS.md, "With gaps", fifteenth session): whole-problem linear solves at 5 % / 10 %
  // missing 15, 2, 5 / 15, 18, 22 -> 8, 2, 5 / 6, 14, 15 (iterations 7, 2, 5 / 7, 10, 15 ->
  // 6, 2, 5 / 5, 10, 14), CPU 30.0 -> 23.5 s in all, the same centres (+-0.001 mm), end costs
  // within +1.1 of Nielsen's alone; without gaps nothing changes (no step is rejected). Not in
  // stage 1: there (a far start) Nielsen's gentle rise suits, and with the halving there 5 % seed
  // 2 took 4 whole-problem iterations instead of 2.
  bool fine_halve_rejected_steps = true;
  // Stage 3 as variable projection with a secant model of the reduced problem; five options,
  // measured together (nineteenth session; BENCHMARKS.md, "With gaps"). What the crawl with gaps
  // is, traced at 10 % missing, seed 3: along the last steps the reduced problem phi(p) =
  // min_y F(y, p) is 3-35x flatter than the Gauss-Newton Schur complement S that LM's step uses
  // (s^T y against s^T S s, y the change of the reduced gradient over the step s): the frames'
  // damping makes S see the poses absorb less of an axis's change than they do. And LM's gain
  // ratio (0.1-0.6 at lambda ~1e-3) judges the poses' linear extrapolation, which the inner
  // iteration replaces anyway.
  //  * fine_variable_projection: each candidate step's poses re-solved (the inner iteration)
  //    before its cost is taken, so the gain ratio judges phi (Golub and Pereyra 1973); the
  //    accepted step keeps those poses. Alone (seventeenth session) lambda then stays at 1e-9
  //    for steps of gain ratio 0.02-0.1.
  //  * fine_secant_curvature: S corrected by a secant model of phi's curvature
  //    (ArrowSchurProblem::SetSecantCurvature; NL2SOL's structured update).
  //  * fine_reduced_damping: the shared parameters damped by S's diagonal
  //    (ArrowSchurProblem::SetReducedDamping), not J_p^T J_p's, far larger for an axis.
  //  * fine_raise_lambda_below_gain (LmOptions::raise_lambda_below_gain_ratio) and
  //    fine_converge_min_gain_ratio (LmOptions::function_tolerance_min_gain_ratio, with the
  //    projection only): after a poorly predicted step lambda rises as after a rejection, and such
  //    a step's small gain does not end the solve (with the projection a step of gain ratio 0.04
  //    ended 5 % seed 1 1.6 above the fine stage's end without it).
  // On by default since the twentieth session; measured at 6,000 frames, 0.8 mm noise, 0 / 5 / 10 %
  // missing, seeds 1-3 (all five, 0.25 for both ratios; BENCHMARKS.md, "With gaps"): whole-problem
  // iterations 2, 2, 2 / 6, 2, 5 / 5, 10, 14 -> 2, 2, 2 / 7, 5, 4 / 7, 6, 7, every end cost at or
  // below the earlier default's, centres within +-0.04 mm. The earlier default's fewer iterations
  // at 5 % seed 2 (2 instead of 5) and 10 % seed 1 (5 instead of 7) were not a speed: it stopped
  // with cost left to gain (5 % seed 2 ended 12.7 higher). Each iteration costs more (every trial,
  // rejected ones too, re-solves the poses), yet on a quiet machine (nineteenth session) the six
  // gap runs took 11.1 s of wall instead of 13.6, the slowest 2.19 s instead of 3.64; in
  // FitModel's staged fit at 10 % (test_sim_fit) 28 iterations instead of 31 (8 on every frame
  // instead of 11), the same bounds; real recordings under 3,000 frames (welk007, gait2354) never
  // reach stage 3. All five off is the earlier fine stage (bench/fit_vs_ceres: --no-vp
  // --no-secant --no-reduced-damping --raise-gain 0 --converge-gain 0).
  bool fine_variable_projection = true;
  bool fine_secant_curvature = true;
  bool fine_reduced_damping = true;
  double fine_converge_min_gain_ratio = 0.25;
  double fine_raise_lambda_below_gain = 0.25;
  // After stage 2, a frame whose cost is above `rescue_ratio` times the median frame's (a pose
  // in a wrong branch: a two-marker foot turned round during a gap) is re-solved, up to
  // `rescue_iterations` Gauss–Newton steps, from its neighbour's pose, sweeping each run of such
  // frames from the well-fitted frame on either side; the lower cost wins
  // (RescueFramesFromNeighbours). 0 or below 1: off.
  double rescue_ratio = 4.0;
  int rescue_iterations = 10;
  // Stage 2's rescue also sweeps, from their neighbours, the frames with fewer marker rows than
  // the fullest frame (a marker in a gap), whatever their cost. A foot whose toe marker is hidden
  // has two valleys of its subtalar angle 1.3-1.8 rad apart (a forearm's rotations too), whose
  // costs differ by a few units, far below rescue_ratio: which one each such frame starts stage 3
  // in decided the last 10-150 units of the final cost and, as they hopped, the fine stage's
  // iterations. Measured at 6,000 frames, 0.8 mm noise, 5 / 10 % missing, seeds 1-6 (BENCHMARKS.md,
  // "With gaps", twenty-sixth session): fine iterations 75 -> 58 over the twelve runs, final costs
  // lower on eleven (by up to 147), about 0.4 CPU s more in stage 2 per run; without gaps nothing
  // changes (no frame is swept).
  bool rescue_gap_frames = true;
  // Before stage 2, in every inner iteration and for every rescue start, each frame's angles that
  // the markers cannot tell from a whole turn on are moved to their frame prior's turn
  // (ArrowProblem::WrapFramePose). Off by default, measured (BENCHMARKS.md, "With gaps",
  // eleventh session): at 10 % missing, seed 2, 346 frames ended a whole turn from their targets
  // (pro_sup_r at -348 deg, truth +4 deg), paying the frame prior; wrapped, the fit ends 68 lower
  // (1.35925e5) in the same 10 iterations, but at 5 % it takes 3 instead of 2 and ends 45 higher;
  // seeds 1 and 3 unchanged. It moves the end point, not the crawl.
  bool wrap_frame_turns = false;

  bool IsValid(std::string* error) const;
};

struct CoarseToFineSummary {
  bool used = false;              // false: a plain solve (too few frames, disabled, or fallback)
  bool fallback = false;          // stage 1 did not converge: the whole problem was solved plainly
  int coarse_frames = 0;
  LmSummary coarse;               // stage 1, on the subset
  double pose_seconds = 0;        // stage 2
  int poses_improved = 0;         // frames whose pose stage 2 moved
  int poses_rescued = 0;          // frames re-solved from a neighbour's pose (all stages)
  double start_cost = 0;          // the whole problem's cost at the caller's x
  double fine_start_cost = 0;     // ... after stages 1 and 2
  double total_seconds = 0;
  // From the call to stage 3's start (stages 1 and 2 and the start's cost), wall and this
  // process's CPU (every thread of it, not only the solve's): with gaps the coarse start took
  // 18-40 % of the solve's CPU (BENCHMARKS.md, "With gaps", twenty-third session), and the CPU
  // share is what a loaded machine still measures.
  double fine_start_seconds = 0;
  double fine_start_cpu_seconds = 0;
  bool frames_cached = false;     // the whole problem's per-frame cache fit its memory budget
  std::string BriefReport() const;
};

// The frames of a problem restricted to a subset: frame i of the view is frame frames[i] of
// `full`. Everything else (shared parameters, priors, gauge rows, block kinds) is `full`'s.
class FrameSubsetProblem : public ArrowProblem {
 public:
  FrameSubsetProblem(ArrowProblem* full, std::vector<int> frames);
  int num_frames() const override { return static_cast<int>(frames_.size()); }
  int frame_dim() const override { return full_->frame_dim(); }
  int shared_dim() const override { return full_->shared_dim(); }
  // ArrowProblem has no per-frame row count: the full problem's rows pro rata (for reports).
  int num_residuals() const override;
  bool SetShared(const Eigen::VectorXd& p) override { return full_->SetShared(p); }
  std::unique_ptr<FrameEvaluator> NewEvaluator() const override;
  const Eigen::VectorXd& prior_weight() const override { return full_->prior_weight(); }
  const Eigen::VectorXd& prior_target() const override { return full_->prior_target(); }
  bool FramePrior(int frame, const double** weight, const double** target) const override {
    return full_->FramePrior(frames_[frame], weight, target);
  }
  bool WrapFramePose(int frame, double* y) const override { return full_->WrapFramePose(frames_[frame], y); }
  const Eigen::MatrixXd& shared_rows() const override { return full_->shared_rows(); }
  void BlockStructure(std::vector<std::vector<int>>* y_columns,
                      std::vector<std::vector<int>>* p_columns) const override {
    full_->BlockStructure(y_columns, p_columns);
  }
  const std::vector<int>& frames() const { return frames_; }

 private:
  ArrowProblem* full_;
  std::vector<int> frames_;
};

// Stage 2 alone: re-solves every frame's pose in x = [y_1 ... y_F, p] for x's p, p fixed. A
// Gauss–Newton step is kept only if it lowers the frame's cost. A frame starts from its given
// pose, or from its predecessor's correction when that is better (pose_from_predecessor); when
// the corrected start is within 4x of the cost the previous frame ended with, the given pose is
// not evaluated (it belongs to another geometry and is far worse). Returns the number of frames
// whose pose changed and, in *cost if given, the whole problem's cost at the result; false in
// *ok if p is refused or a frame's residuals are not finite at its given pose. `frame_costs`,
// if given, holds each frame's sum of squares (residuals and frame prior) at x's poses.
// `min_gain` > 0: a frame stops once a step lowers its sum of squares by at most min_gain
// (instead of options.pose_tolerance of it), after at most options.pose_iterations steps.
// `final_frame_costs`, if given, receives each frame's sum of squares at its result (what
// FrameSquaredNorm gives there), for a pass that follows (RescueFramesFromNeighbours).
int RefineFramePoses(ArrowProblem* problem, const CoarseToFineOptions& options, int num_threads,
                     Eigen::VectorXd* x, bool* ok, double* cost = nullptr,
                     const double* frame_costs = nullptr, double min_gain = 0,
                     std::vector<double>* final_frame_costs = nullptr);

// Frames in marker gaps (issue 14): a frame whose markers leave some coordinates nearly
// unobserved (a two-marker foot with its toe marker hidden: the rotation about the line from
// the ankle to the heel marker; a hand whose only marker is hidden: both wrist angles) has a
// per-frame block U_f that is near-singular in them, held only by the frame prior, which is
// deliberately negligible (FitOptions::frame_prior_sigma_rad = 10 rad). LM's Marquardt damping
// is proportional to that tiny curvature, so raising lambda does not restrain those
// coordinates: measured at 5 % missing on the default protocol, each step moved them by up to
// 0.2-0.6 rad in some frames, the gain ratio stayed at 0.4-0.6 and lambda at 5e-3 for 100
// iterations, the shared parameters crawling. A stronger prior on every coordinate converges
// but biases the well-seen frames (BENCHMARKS.md: --frame-prior 0.1); so only the coordinates
// a frame leaves unobserved are held:
//   * a frame is examined only if it has fewer residual blocks than the fullest frame (a hidden
//     marker), so a problem without gaps is left exactly as it was;
//   * coordinate c of such a frame is unobserved when its marginal information from the frame's
//     own rows, 1 / (U_f^-1)_cc, is below `weak_ratio` times the median of the same over all
//     frames (what a frame typically knows about c);
//   * it then gets a prior of information `hold_ratio` times that median (a standard deviation
//     1/sqrt(hold_ratio) = 32 times a typical frame's) towards its starting value, which
//     InverseKinematics::SolveTrial interpolates across the gap (IkOptions::bridge_gaps).
// The prior is weak against data (a frame that sees c outweighs it by 1/hold_ratio) and sits
// only where the data are silent. Its strength is a trade (its targets come from IK with the
// nominal geometry), measured at 6,000 frames, seed 2 (BENCHMARKS.md, tenth session): hold_ratio
// 1e-2 biases the fit (joint centres 1.15 mm max from the truth at 5 % missing, 5.94 mm at 10 %);
// 1e-3, 2 and 10 iterations, 0.49 mm (0.48 mm on the same data without gaps); 1e-4 crawls at
// 10 % (100 iterations, not converged); none ends in a wrong minimum at 10 %.
struct UnobservedHoldOptions {
  bool enabled = true;
  double weak_ratio = 1e-2;
  double hold_ratio = 1e-3;
  bool IsValid(std::string* error) const;
};

// The frame prior weights (frames x frame_dim, row-major) for `problem` at x: `base` (the
// uniform weights) everywhere, raised as above where a frame leaves a coordinate unobserved.
// Returns how many (frame, coordinate) pairs were raised; 0 and `weights` left empty when no
// frame has a hidden residual block, or options.enabled is false. x's p is set on the problem.
int UnobservedCoordinateWeights(ArrowProblem* problem, const Eigen::VectorXd& x, const Eigen::VectorXd& base,
                                const UnobservedHoldOptions& options, int num_threads,
                                Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>* weights);

// Re-solves the frames of x whose cost is far above the median frame's from their neighbours'
// poses (p fixed), as CoarseToFineOptions::rescue_ratio describes. Each run of consecutive such
// frames is swept forwards from the well-fitted frame before it and backwards from the one after
// it, each frame starting from its neighbour's pose as the sweep left it: a stretch of hundreds of
// frames in a wrong branch (a foot turned round through a long gap, 10 % missing) is carried back
// in one pass. Starting only from the nearest well-fitted frame within 60 frames (the earlier
// rule) reached ~50 frames of such a stretch per call, one more band per LM iteration.
// Returns how many poses were replaced (each only if that lowered its frame's cost).
// `frame_costs`, if given: each frame's sum of squares at x (computed if its size is not the
// frame count), updated to the result's.
// `also`, if given (one entry per frame): frames swept whatever their cost.
int RescueFramesFromNeighbours(ArrowProblem* problem, const CoarseToFineOptions& options, int num_threads,
                               Eigen::VectorXd* x, std::vector<double>* frame_costs,
                               const std::vector<char>* also = nullptr);

// Variable projection's judge of a candidate x (CoarseToFineOptions::fine_variable_projection):
// the whole problem's cost at x, then every pose re-solved for x's geometry, in one pass over the
// frames fewer than ArrowSchurProblem::Cost followed by RescueFramesFromNeighbours and
// RefineFramePoses(..., min_gain = 2 function_tolerance cost): each frame's cost at x is read
// from its first pose step's evaluation, which the re-solve's pass repeated (about 3 % of a
// fine-stage iteration with gaps). The results are theirs to the bit: *cost summed as Cost sums it
// with `cost_threads` threads (its frames in its chunks), the rescue judged by those costs
// before any pose moves (a rescued frame's first step is taken again from its new pose), the
// steps after the first only once that cost gives min_gain, *projected_cost summed as
// RefineFramePoses sums it. `options.pose_iterations` steps a frame at most, from the given
// poses (no predecessor's correction); options.wrap_frame_turns must be off. False if p is
// refused or x's cost is not finite (*cost then undefined); *projected_cost is +inf if the
// re-solve fails. *rescued: the frames the rescue replaced.
bool ProjectedCost(ArrowProblem* problem, const CoarseToFineOptions& options, int num_threads, int cost_threads,
                   const Eigen::VectorXd& x, double function_tolerance, double* cost, Eigen::VectorXd* projected,
                   double* projected_cost, int* rescued);

// Minimises `problem` from *x: stages 1-3 when it has enough frames, else LM directly. `whole`
// is the caller's Schur solver of `problem` (it holds the per-frame cache, so the caller keeps
// it for the covariance afterwards); stage 1 makes its own for the subset. The returned summary
// is stage 3's (the whole problem) with initial_cost the cost at the caller's x; the options'
// callbacks see stage 1's iterations too (IterationSummary::coarse) and may cancel in either
// stage.
LmSummary SolveCoarseToFine(ArrowProblem* problem, ArrowSchurProblem* whole, const LmOptions& options,
                            const CoarseToFineOptions& coarse, int num_threads, Eigen::VectorXd* x,
                            CoarseToFineSummary* summary = nullptr);

}  // namespace mocap::solver
