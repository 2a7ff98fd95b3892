// fit_vs_ceres: the global body-model fit (solver/global_fit.h) on simulated calibration-protocol
// data, solved by our Levenberg–Marquardt with per-frame Schur elimination (solver/schur_solver.h)
// and by Ceres Solver — the identical residuals from the identical starting point, timed in one
// process run.
//
//   fit_vs_ceres --frames N [--json] [--json-out FILE] [--threads T] [--skip-ceres]
//                [--ceres-solvers schur,normal,dense] [--ceres-residuals marker|frame]
//                [--ceres-shared split,segment,single] [--ceres-start cold,same]
//                [--ceres-radius R1,R2,...] [--ceres-pose-tolerance T] [--ceres-pose-iterations K]
//                [--ceres-max-seconds S] [--repeat R] [--verbose] [--plain]
//                [--coarse-frames N] [--coarse-tolerance T] [--pose-iterations K]
//                [--pose-tolerance T] [--fine-lambda L] [--no-inner] [--wrap]
//                [--missing F] [--noise-mm S] [--seed N] [--frame-prior SIGMA] [--min-diagonal D]
//                [--max-iterations K] [--no-hold] [--hold-weak R] [--hold-ratio R] [--rescue-ratio R]
//                [--fit-model] [--rescue-rounds N] [--clamp-ranges] [--ik-limit-stiffness S]
//                [--limit-sigma SIGMA] [--pose-retries K] [--pose-cap R] [--time-iteration K]
//                [--save-x FILE] [--no-rescue-gaps]
//
// The accuracy against the simulation's truth is printed ("truth:", JSON ours_accuracy): joint
// centres, frames whose markers (hidden ones too) sit > 20 mm off, and joint rotations outside
// their ranges (frames x coordinates; the joint to the lab and joints that may turn round not
// counted). With FVC_DEBUG=1 in the
// environment it also prints each such frame's worst marker and the per-trial frame costs (how
// the gap diagnosis in BENCHMARKS.md was made). --no-hold / --hold-* / --rescue-ratio / --no-rescue-gaps
// set FitOptions::unobserved_hold and CoarseToFineOptions::rescue_ratio / rescue_gap_frames
// (solver/coarse_to_fine.h).
// --clamp-ranges marks those ranged joint rotations clamped (the default model declares none), so
// the IK start and the fit hold them inside their ranges by their walls (--ik-limit-stiffness,
// --limit-sigma: IkOptions::coordinate_limit_stiffness, FitOptions::coordinate_limit_sigma_rad);
// it prints how many (frame, rotation) pairs of the truth lie outside the ranges (none for the
// default protocol: clamping is consistent with the simulated motions). --pose-retries / --pose-cap
// set CoarseToFineOptions::pose_step_retries / pose_step_cap. --save-x FILE writes each frame's sum
// of squares at our result (frame order, doubles) and then our x, to tell two end points apart
// frame by frame (which frames a final cost's difference is in). --time-iteration K times the parts of
// one fine-stage iteration (linearisation, shared solve, cost, the inner iteration's pose re-solve)
// K times at our solution and prints each part's least CPU time (JSON ours_iteration_parts), and
// as a fifth part the cost and re-solve fused as the fine stage runs them (solver::ProjectedCost).
//
// --fit-model also runs solver::FitModel, what `mocap fit` runs, on the same trials with the same
// options: its IK start, the coarse-to-fine solve, the re-posing and the rescue of frames left in
// a wrong branch (FitOptions::rescue_ratio), timed whole (wall) and solve alone.
//
// The data: the default protocol simulated with seed N (1), noise S mm (0.5) and a fraction F (0)
// of the marker samples lost in gaps of 5-30 frames (sim/simulate.h), as real captures have.
//
// Sameness. Both solvers work on ONE solver::MarkerFitProblem (measurements, residual scales,
// free parameters, prior rows, gauge rows) from ONE x0 (per-frame IK with the nominal model, as
// FitModel does, and the problem's InitialShared()). Ceres's cost functions cannot call the
// problem's FrameEvaluator: it reads the one Geometry that ArrowProblem::SetShared sets, while
// Ceres evaluates residual blocks on many threads at whatever point it is trying. They evaluate
// the marker residuals with the same model/kinematics.h functions instead (ForwardKinematics,
// MarkerPosition, MarkerJacobian, the problem's residual scales) on a per-thread Geometry. Before
// either solve, Ceres's cost and gradient at x0 are compared with ours (ArrowSchurProblem's
// Linearize): a mismatch is printed as an error.
//
// Ceres's side is set up the way that was fastest for it (measured, see --ceres-residuals and
// --ceres-shared): one cost function per (frame, marker), 3 residuals, on the frame's block z_f
// and on one parameter block per model object (segment scale, joint centre, axis, marker
// position), so each marker's Jacobian touches only its own chain. One cost function per frame, or
// all of p in one block, makes Ceres store and eliminate dense 117 x 202 blocks and is 3-5x slower.
// The prior and gauge rows are one more cost function on all shared blocks. Jacobians are
// analytic. Ceres's LM gets our tolerances, initial damping and damping bounds; its iteration
// limit is 100, ours FitModel's 50: on a few poorly exciting frames (the first trial alone) both
// stop at their limit, and only the time per iteration compares.
//
// Ceres variants (issue 14 item 4: the ratio is against the best a Ceres user could write). Every
// combination of the listed starts, shared layouts, linear solvers and (cold start) radii is run:
//  * --ceres-start cold: Ceres's LM on the whole problem from x0 (earlier sessions' comparison);
//    same: ours's strategy in Ceres (RunCeresVariant): LM on the same coarse subset, a pose pass
//    with every shared block constant, then the whole problem at ours's small initial damping.
//  * --ceres-shared split: a block per model object; segment: a block per segment's geometry
//    (scale, its joint's centre and axes, its markers); single: all of p in one block.
//  * --ceres-radius: the cold start's initial_trust_region_radius (default 1 / our initial
//    lambda, 1e4, which is also Ceres's default); several values give several runs.
// Each run's Solver::Summary breakdown (preprocessor, linear solver, residual and Jacobian
// evaluation, the minimizer's other time, counts) is printed and written per stage to the JSON.
// The headline ratio is the fastest variant's time over ours; the cold plain-LM ratio (per-object
// blocks, default radius) and the same strategy's are printed beside it. Final costs are printed
// relative to ours: with gaps the solvers can end in different minima, and a ratio between
// different costs compares different work.
//
// Ours is what FitModel runs: solver::SolveCoarseToFine (solver/coarse_to_fine.h), LM on an
// evenly spaced subset of the frames, every pose re-solved for that geometry, then LM on the
// whole problem with the same tolerances. Its final cost is the whole problem's, so it compares
// with Ceres's like for like. --plain also times our LM on the whole problem from x0 alone.
//
// Timing: wall clock of the solve only, for ours ArrowSchurProblem's construction (its symbolic
// analysis) plus the solve, for Ceres ceres::Solve (which includes its preprocessing);
// simulation, IK and building the problems are not timed. With --repeat R each solver runs R
// times from x0 and the fastest run counts.
//
// The project compiles with -march=native and libceres does not, so Eigen's alignment may differ
// between the two: only Ceres interfaces free of Eigen types are used here (Problem, Solver,
// CostFunction with raw double arrays).
#include <ceres/ceres.h>
#include <sched.h>
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <functional>
#include <iostream>
#include <limits>
#include <map>
#include <memory>
#include <set>
#include <sstream>
#include <string>
#include <tuple>
#include <vector>

#include <nlohmann/json.hpp>

#include "formats/marker_data.h"
#include "model/compare.h"
#include "model/kinematics.h"
#include "model/model.h"
#include "sim/simulate.h"
#include "solver/coarse_to_fine.h"
#include "solver/global_fit.h"
#include "solver/inverse_kinematics.h"
#include "solver/marker_fit_problem.h"
#include "solver/parallel.h"
#include "solver/schur_solver.h"

namespace {

using namespace mocap;
using Clock = std::chrono::steady_clock;
using nlohmann::json;

double Since(Clock::time_point t) { return std::chrono::duration<double>(Clock::now() - t).count(); }

// Peak resident memory from getrusage's ru_maxrss, the process's high-water mark. To give each
// Ceres run its own peak the mark is reset before it (/proc/self/clear_refs, "5", which getrusage
// follows), so the process's overall peak is kept here as the largest mark seen before a reset.
class PeakMemory {
 public:
  double ProcessPeakMb() {
    total_mb_ = std::max(total_mb_, CurrentMarkMb());
    return total_mb_;
  }
  // The mark since the last Reset (or since the start).
  static double CurrentMarkMb() {
    rusage usage{};
    getrusage(RUSAGE_SELF, &usage);
    return usage.ru_maxrss / 1024.0;  // kilobytes on Linux
  }
  // Restarts the mark at the current resident size; false if the kernel refuses.
  bool Reset() {
    ProcessPeakMb();
    std::ofstream f("/proc/self/clear_refs");
    f << "5";
    f.close();
    return !f.fail();
  }

 private:
  double total_mb_ = 0;
};

// Wall clock of one timed solve, this process's CPU time over it, and the share of the machine's
// CPU that OTHER processes used meanwhile (/proc/stat's busy time minus our own). The cores are
// shared (builds and other benchmarks run alongside); wall time is what counts, but under
// contention CPU time is the steadier measure of work, and the share says how far to trust the
// wall time. A busy neighbour slows ours more than Ceres: our frames are split into equal static
// chunks per thread, so each pass waits for the thread whose core is taken.
class SolveTimer {
 public:
  SolveTimer() : machine_(MachineBusySeconds()), self_(SelfSeconds()), start_(Clock::now()) {}
  double wall() const { return Since(start_); }
  double cpu() const { return SelfSeconds() - self_; }
  double others() const {
    const double others = (MachineBusySeconds() - machine_) - cpu();
    return std::max(0.0, others / (wall() * NumCpus()));
  }

 private:
  static int NumCpus() { return std::max(1, static_cast<int>(sysconf(_SC_NPROCESSORS_ONLN))); }
  static double MachineBusySeconds() {
    std::ifstream in("/proc/stat");
    std::string cpu;
    double user = 0, nice = 0, system = 0, idle = 0, iowait = 0, irq = 0, softirq = 0, steal = 0;
    in >> cpu >> user >> nice >> system >> idle >> iowait >> irq >> softirq >> steal;
    return (user + nice + system + irq + softirq + steal) / sysconf(_SC_CLK_TCK);
  }
  static double SelfSeconds() {
    rusage usage{};
    getrusage(RUSAGE_SELF, &usage);
    auto seconds = [](const timeval& t) { return t.tv_sec + 1e-6 * t.tv_usec; };
    return seconds(usage.ru_utime) + seconds(usage.ru_stime);
  }
  double machine_, self_;
  Clock::time_point start_;
};

double LoadAverage() {
  std::ifstream in("/proc/loadavg");
  double one_minute = -1;
  in >> one_minute;
  return one_minute;
}

// ---------------------------------------------------------------------------------------------
// Command line

struct Args {
  int frames = 1000;
  bool json = false;
  std::string json_out;  // also write the JSON there (the text report still goes to stdout)
  std::string save_x;    // raw doubles: each frame's sum of squares at our result, then our x
  int threads = 0;  // 0: every core
  bool skip_ceres = false;
  double ceres_max_seconds = 600;
  std::vector<std::string> ceres_solvers = {"schur", "normal", "dense"};
  std::string ceres_residuals = "marker";  // one cost function per (frame, marker) or per frame
  // Shared p as one block per model object (split), per segment, or one block; each one run.
  std::vector<std::string> ceres_shared = {"split"};
  // Ceres's start: cold (LM on the whole problem from x0) and/or same (ours's strategy).
  std::vector<std::string> ceres_starts = {"cold"};
  // The cold start's initial_trust_region_radius, one run each; empty: 1 / LmOptions::initial_lambda.
  std::vector<double> ceres_radius;
  double ceres_pose_tolerance = 1e-3;  // the same start's pose pass (CeresSettings)
  int ceres_pose_iterations = -1;      // -1: CoarseToFineOptions::pose_iterations
  int repeat = 1;  // solves per solver; the fastest counts (the machine is shared and noisy)
  bool verbose = false;
  bool plain = false;  // also time our plain LM (no coarse-to-fine start) in the same run
  solver::CoarseToFineOptions coarse;  // FitOptions' defaults unless set
  double missing = 0.0;     // fraction of marker samples lost in gaps
  double noise_mm = 0.5;
  std::uint64_t seed = 1;
  double min_diagonal = 0;       // > 0: LmOptions::min_diagonal; 0: its default
  bool fit_model = false;        // also time solver::FitModel on the same trials
  int rescue_rounds = -1;        // >= 0: FitOptions::rescue_rounds (0: no rescue); -1: default
  double frame_prior_sigma = 0;  // > 0: FitOptions' frame prior sigma (rad and m); 0: its default
  int max_iterations = -1;       // >= 0: LmOptions::max_iterations (ours); -1: FitOptions' default
  bool hold = true;              // FitOptions::unobserved_hold.enabled
  double hold_weak = 0, hold_ratio = 0;  // > 0: UnobservedHoldOptions' weak_ratio, hold_ratio
  bool clamp_ranges = false;     // mark the model's ranged joint rotations clamped (ClampRangedRotations)
  double ik_limit_stiffness = -1;  // >= 0: IkOptions::coordinate_limit_stiffness; -1: its default
  double limit_sigma = 0;          // > 0: FitOptions::coordinate_limit_sigma_rad; 0: its default
  int geodesic = -1;               // 1 / 0: LmOptions::geodesic_acceleration on / off; -1: its default
  double geodesic_alpha = 0, geodesic_h = 0;  // > 0: max_acceleration_ratio, acceleration_step
  int time_iteration = 0;          // > 0: time one fine-stage iteration's parts this many times
};

[[noreturn]] void Usage(const std::string& error) {
  std::fprintf(stderr,
               "fit_vs_ceres: %s\n"
               "usage: fit_vs_ceres --frames N [--json] [--json-out FILE] [--threads T] [--skip-ceres]\n"
               "         [--ceres-solvers schur,normal,dense] [--ceres-residuals marker|frame]\n"
               "         [--ceres-shared split,segment,single] [--ceres-start cold,same]\n"
               "         [--ceres-radius R1,R2] [--ceres-pose-tolerance T] [--ceres-pose-iterations K]\n"
               "         [--ceres-max-seconds S] [--repeat R] [--verbose]\n"
               "         [--plain] [--coarse-frames N] [--coarse-tolerance T] [--pose-iterations K]\n"
               "         [--pose-tolerance T] [--fine-lambda L] [--no-inner] [--wrap] [--no-halve]\n"
               "         [--missing F] [--noise-mm S] [--seed N] [--frame-prior SIGMA]\n"
               "         [--min-diagonal D] [--fit-model] [--rescue-rounds N] [--max-iterations K]\n"
               "         [--no-hold] [--hold-weak R] [--hold-ratio R] [--rescue-ratio R]\n"
               "         [--clamp-ranges] [--ik-limit-stiffness S] [--limit-sigma SIGMA]\n"
               "         [--pose-retries K] [--pose-cap R]\n"
               "         [--geodesic | --no-geodesic] [--geodesic-alpha A] [--geodesic-h H]\n"
               "         [--vp | --no-vp] [--secant | --no-secant] [--reduced-damping | --no-reduced-damping]\n"
               "         [--raise-gain G] [--converge-gain G] (the five on by default; a gain of 0: off)\n"
               "         [--time-iteration K] [--save-x FILE] [--no-rescue-gaps]\n",
               error.c_str());
  std::exit(2);
}

// A comma-separated list of a flag's values, each one of `allowed` (any if empty).
std::vector<std::string> List(const std::string& text, const std::set<std::string>& allowed,
                              const std::string& flag) {
  std::vector<std::string> items;
  std::stringstream ss(text);
  for (std::string item; std::getline(ss, item, ',');) {
    if (!allowed.empty() && !allowed.count(item)) Usage("unknown value for " + flag + ": " + item);
    items.push_back(item);
  }
  if (items.empty()) Usage(flag + " is empty");
  return items;
}

Args ParseArgs(int argc, char** argv) {
  Args args;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) Usage(a + " needs a value");
      return argv[++i];
    };
    auto number = [&](double min) {
      const std::string v = value();
      char* end = nullptr;
      const double d = std::strtod(v.c_str(), &end);
      if (end == v.c_str() || *end != '\0' || !(d >= min)) Usage("bad value for " + a + ": " + v);
      return d;
    };
    if (a == "--frames") args.frames = static_cast<int>(number(1));
    else if (a == "--json") args.json = true;
    else if (a == "--json-out") args.json_out = value();
    else if (a == "--save-x") args.save_x = value();
    else if (a == "--plain") args.plain = true;
    else if (a == "--coarse-frames") args.coarse.coarse_frames = static_cast<int>(number(1));
    else if (a == "--coarse-tolerance") args.coarse.coarse_function_tolerance = number(0);
    else if (a == "--no-rescue-gaps") args.coarse.rescue_gap_frames = false;
    else if (a == "--pose-iterations") args.coarse.pose_iterations = static_cast<int>(number(0));
    else if (a == "--no-inner") args.coarse.inner_iterations = false;
    else if (a == "--wrap") args.coarse.wrap_frame_turns = true;
    else if (a == "--no-halve") args.coarse.fine_halve_rejected_steps = false;
    else if (a == "--secant") args.coarse.fine_secant_curvature = true;
    else if (a == "--no-secant") args.coarse.fine_secant_curvature = false;
    else if (a == "--reduced-damping") args.coarse.fine_reduced_damping = true;
    else if (a == "--no-reduced-damping") args.coarse.fine_reduced_damping = false;
    else if (a == "--vp") args.coarse.fine_variable_projection = true;
    else if (a == "--no-vp") args.coarse.fine_variable_projection = false;
    else if (a == "--raise-gain") args.coarse.fine_raise_lambda_below_gain = number(0);
    else if (a == "--converge-gain") args.coarse.fine_converge_min_gain_ratio = number(0);
    else if (a == "--pose-tolerance") args.coarse.pose_tolerance = number(0);
    else if (a == "--fine-lambda") args.coarse.fine_initial_lambda = number(1e-300);
    else if (a == "--missing") {
      args.missing = number(0);
      if (!(args.missing < 0.9)) Usage("--missing must be in [0, 0.9)");
    } else if (a == "--noise-mm") args.noise_mm = number(0);
    else if (a == "--fit-model") args.fit_model = true;
    else if (a == "--rescue-rounds") args.rescue_rounds = static_cast<int>(number(0));
    else if (a == "--min-diagonal") args.min_diagonal = number(1e-300);
    else if (a == "--no-hold") args.hold = false;
    else if (a == "--hold-weak") args.hold_weak = number(1e-300);
    else if (a == "--hold-ratio") args.hold_ratio = number(1e-300);
    else if (a == "--rescue-ratio") args.coarse.rescue_ratio = number(0);
    else if (a == "--clamp-ranges") args.clamp_ranges = true;
    else if (a == "--pose-retries") args.coarse.pose_step_retries = static_cast<int>(number(0));
    else if (a == "--pose-cap") args.coarse.pose_step_cap = number(1e-300);
    else if (a == "--ik-limit-stiffness") args.ik_limit_stiffness = number(0);
    else if (a == "--limit-sigma") args.limit_sigma = number(1e-300);
    else if (a == "--max-iterations") args.max_iterations = static_cast<int>(number(0));
    else if (a == "--geodesic") args.geodesic = 1;
    else if (a == "--no-geodesic") args.geodesic = 0;
    else if (a == "--geodesic-alpha") args.geodesic_alpha = number(1e-300);
    else if (a == "--geodesic-h") args.geodesic_h = number(1e-300);
    else if (a == "--frame-prior") args.frame_prior_sigma = number(1e-6);
    else if (a == "--seed") args.seed = static_cast<std::uint64_t>(number(0));
    else if (a == "--threads") args.threads = static_cast<int>(number(1));
    else if (a == "--skip-ceres") args.skip_ceres = true;
    else if (a == "--ceres-max-seconds") args.ceres_max_seconds = number(1e-3);
    else if (a == "--verbose") args.verbose = true;
    else if (a == "--repeat") args.repeat = static_cast<int>(number(1));
    else if (a == "--time-iteration") args.time_iteration = static_cast<int>(number(1));
    else if (a == "--ceres-solvers") {
      args.ceres_solvers = List(value(), {"schur", "normal", "dense"}, a);
    } else if (a == "--ceres-residuals") {
      args.ceres_residuals = value();
      if (args.ceres_residuals != "marker" && args.ceres_residuals != "frame")
        Usage("--ceres-residuals is marker or frame");
    } else if (a == "--ceres-shared") {
      args.ceres_shared = List(value(), {"split", "segment", "single"}, a);
    } else if (a == "--ceres-start") {
      args.ceres_starts = List(value(), {"cold", "same"}, a);
    } else if (a == "--ceres-radius") {
      args.ceres_radius.clear();
      for (const std::string& v : List(value(), {}, a)) {
        char* end = nullptr;
        const double r = std::strtod(v.c_str(), &end);
        if (end == v.c_str() || *end != '\0' || !(r > 0)) Usage("bad value for --ceres-radius: " + v);
        args.ceres_radius.push_back(r);
      }
    } else if (a == "--ceres-pose-tolerance") {
      args.ceres_pose_tolerance = number(0);
    } else if (a == "--ceres-pose-iterations") {
      args.ceres_pose_iterations = static_cast<int>(number(1));
    } else if (a == "--help" || a == "-h") Usage("help");
    else Usage("unknown argument " + a);
  }
  args.threads = solver::ResolveThreads(args.threads);
  return args;
}

// ---------------------------------------------------------------------------------------------
// The machine, for the record

int NumProcessors() {
  cpu_set_t set;
  CPU_ZERO(&set);
  if (sched_getaffinity(0, sizeof(set), &set) == 0) return CPU_COUNT(&set);  // what nproc says
  return static_cast<int>(std::thread::hardware_concurrency());
}

std::string CpuModel() {
  std::ifstream in("/proc/cpuinfo");
  for (std::string line; std::getline(in, line);)
    if (line.rfind("model name", 0) == 0) {
      const size_t colon = line.find(':');
      return colon == std::string::npos ? line : line.substr(line.find_first_not_of(" \t", colon + 1));
    }
  return "unknown";
}

// The BLAS actually mapped into this process (ours uses none; Ceres's CHOLMOD and LAPACK do), read
// from /proc/self/maps, which shows the file behind the libblas.so.3 alternatives symlink.
std::string LoadedBlas() {
  std::ifstream in("/proc/self/maps");
  std::set<std::string> found;
  for (std::string line; std::getline(in, line);) {
    const size_t slash = line.find('/');
    if (slash == std::string::npos) continue;
    const std::string path = line.substr(slash);
    const std::string file = path.substr(path.rfind('/') + 1);
    if (file.find("blas") != std::string::npos || file.find("mkl") != std::string::npos)
      found.insert(path);
  }
  std::string out;
  for (const auto& p : found) out += (out.empty() ? "" : ", ") + p;
  return out.empty() ? "none loaded" : out;
}

// ---------------------------------------------------------------------------------------------
// The data: N frames of the calibration protocol

struct BenchData {
  Model model;  // the nominal model, markers restricted to those in the data
  formats::RowMatrix measurements;                // frames x 3 markers, model order, NaN = missing
  std::vector<std::pair<int, int>> trial_ranges;  // first frame, frame count
  std::vector<formats::MarkerTrial> trials;       // the same frames as trials (--fit-model)
  std::string source;
  // The simulation's truth, for the accuracy figures: the true model (same joints as `model`)
  // and every frame's true z (rows: frames).
  Model truth;
  Eigen::MatrixXd true_coordinates;
};

// Copies `trials` (in order, the last truncated so the total is `frames`) into one measurement
// matrix in the order of `nominal`'s markers that occur in the data, as FitModel does.
BenchData Assemble(const Model& nominal, const std::vector<const formats::MarkerTrial*>& trials,
                   int frames) {
  BenchData d;
  std::set<std::string> names;
  int total = 0;
  std::vector<int> take;
  for (const formats::MarkerTrial* t : trials) {
    if (total >= frames) break;
    take.push_back(std::min(t->num_frames(), frames - total));
    total += take.back();
    names.insert(t->marker_names.begin(), t->marker_names.end());
  }
  std::vector<int> keep;
  for (int m = 0; m < nominal.num_markers(); ++m)
    if (names.count(nominal.markers()[m].name)) keep.push_back(m);
  if (mocap::Status s = nominal.WithMarkers(keep, &d.model); !s) {
    std::fprintf(stderr, "fit_vs_ceres: %s\n", s.message().c_str());
    std::exit(1);
  }
  const int nm = d.model.num_markers();
  d.measurements.setConstant(total, 3 * nm, std::numeric_limits<double>::quiet_NaN());
  int first = 0;
  for (size_t t = 0; t < take.size(); ++t) {
    const formats::MarkerTrial& trial = *trials[t];
    for (int c = 0; c < trial.num_markers(); ++c) {
      const int m = d.model.FindMarker(trial.marker_names[c]);
      if (m >= 0)
        d.measurements.block(first, 3 * m, take[t], 3) = trial.positions.block(0, 3 * c, take[t], 3);
    }
    d.trial_ranges.emplace_back(first, take[t]);
    first += take[t];
    formats::MarkerTrial copy = trial;
    copy.positions.conservativeResize(take[t], Eigen::NoChange);
    copy.frame_numbers.resize(std::min<size_t>(copy.frame_numbers.size(), take[t]));
    copy.times.resize(std::min<size_t>(copy.times.size(), take[t]));
    d.trials.push_back(std::move(copy));
  }
  // A sample is all three coordinates or nothing (as in FitModel).
  for (int f = 0; f < total; ++f)
    for (int m = 0; m < nm; ++m)
      if (!d.measurements.row(f).segment<3>(3 * m).allFinite())
        d.measurements.row(f).segment<3>(3 * m).setConstant(std::numeric_limits<double>::quiet_NaN());
  return d;
}

BenchData MakeData(int frames, const Args& args) {
  sim::SimulationOptions options;
  options.seed = args.seed;
  options.noise_mm = args.noise_mm;
  options.missing = args.missing;
  // The protocol is about 6000 frames at duration_scale 1; longer sessions repeat more cycles.
  options.duration_scale = std::max(1.0, std::ceil(frames / 6000.0));
  sim::SimulatedSession session;
  for (;;) {
    const Status s = sim::SimulateSession(options, &session);
    if (!s.ok()) {
      std::fprintf(stderr, "fit_vs_ceres: simulation failed: %s\n", s.message().c_str());
      std::exit(1);
    }
    if (session.total_frames() >= frames) break;
    options.duration_scale += 1;  // the protocol came out a little short of 6000 frames
  }
  std::vector<const formats::MarkerTrial*> trials;
  for (const auto& t : session.trials) trials.push_back(&t.markers);
  BenchData d = Assemble(session.nominal, trials, frames);
  d.truth = session.truth;
  d.true_coordinates.resize(d.measurements.rows(), d.model.num_coordinates());
  for (size_t t = 0, first = 0; t < d.trial_ranges.size(); ++t) {
    for (int f = 0; f < d.trial_ranges[t].second; ++f)
      d.true_coordinates.row(first + f) =
          sim::TrueCoordinates(d.truth, session.trials[t].coordinates, f).transpose();
    first += d.trial_ranges[t].second;
  }
  char buf[160];
  std::snprintf(buf, sizeof(buf),
                "default protocol, seed %llu, noise %g mm, missing %g, duration_scale %g, %zu trials",
                static_cast<unsigned long long>(options.seed), options.noise_mm, options.missing,
                options.duration_scale, d.trial_ranges.size());
  d.source = buf;
  return d;
}

// How far a solution x = [z_1 .. z_F, p] is from the simulation's truth: the fitted joint
// centres (model/compare.h, in the frames of the segments they join) and, per trial, the frames
// where some marker, seen or hidden, lies more than 20 mm from its true place (a wrong branch:
// a two-marker foot turned round while one marker was hidden).
struct Accuracy {
  double centre_max_mm = NAN, centre_rms_mm = NAN;
  int frames_off = 0;
  std::vector<int> frames_off_per_trial;
  int outside_range = 0;  // (frame, joint rotation) pairs outside the rotation's range
};

// A joint rotation whose range a pose should keep (the ones counted outside their ranges): not
// the joint to the lab, whose angles depend on the lab's axes, nor one that may turn round.
bool IsRangedRotation(const Model& model, int c) {
  const Coordinate& k = model.coordinates()[c];
  return k.rotational && k.joint >= 0 && model.joints()[k.joint].parent >= 0 &&
         k.max_value - k.min_value < 2.0 * M_PI;
}

// (frame, ranged rotation) pairs of z (rows: frames) outside the rotation's range.
int CountOutsideRange(const Model& model, const Eigen::MatrixXd& z) {
  int outside = 0;
  for (int c = 0; c < model.num_coordinates(); ++c) {
    if (!IsRangedRotation(model, c)) continue;
    const Coordinate& k = model.coordinates()[c];
    outside += static_cast<int>(((z.col(c).array() < k.min_value) || (z.col(c).array() > k.max_value)).count());
  }
  return outside;
}

// --clamp-ranges: every ranged rotation of the model marked clamped (Coordinate::clamped), so the
// IK start and the fit keep it inside its range by their one-sided walls
// (IkOptions::coordinate_limit_stiffness, FitOptions::coordinate_limit_sigma_rad). The default
// model declares none clamped; whether the simulated motions stay inside the ranges is printed
// with it (CountOutsideRange of the truth). Returns how many were marked.
int ClampRangedRotations(Model* model) {
  std::vector<Coordinate> coordinates = model->coordinates();
  int clamped = 0;
  for (int c = 0; c < model->num_coordinates(); ++c)
    if (IsRangedRotation(*model, c) && !coordinates[c].clamped) {
      coordinates[c].clamped = true;
      ++clamped;
    }
  Model out;
  if (const Status s = Model::Build(model->name(), model->segments(), model->joints(), coordinates,
                                    model->markers(), model->derived_coordinates(), &out);
      !s.ok()) {
    std::fprintf(stderr, "fit_vs_ceres: --clamp-ranges: %s\n", s.message().c_str());
    std::exit(1);
  }
  *model = std::move(out);
  return clamped;
}

Accuracy MeasureAccuracy(const BenchData& d, const solver::MarkerFitProblem& problem, const Eigen::VectorXd& x) {
  Accuracy a;
  const int nz = problem.frame_dim();
  Model fitted;
  ModelComparison cmp;
  if (!d.model.WithParameters(problem.FullParameters(x.tail(problem.shared_dim())), &fitted).ok() ||
      !CompareModels(d.truth, fitted, &cmp).ok())
    return a;
  a.centre_max_mm = cmp.joint_centre_error_mm.max;
  a.centre_rms_mm = cmp.joint_centre_error_mm.rms;
  if (std::getenv("FVC_DEBUG")) {
    // SetShared only moves the problem's current geometry, which every solve sets anew.
    solver::MarkerFitProblem& pr = const_cast<solver::MarkerFitProblem&>(problem);
    pr.SetShared(x.tail(problem.shared_dim()));
    auto ev = pr.NewEvaluator();
    std::vector<double> per(problem.num_frames());
    for (int f = 0; f < problem.num_frames(); ++f) {
      double c = 0;
      solver::FrameSquaredNorm(pr, ev.get(), f, x.data() + static_cast<size_t>(f) * problem.frame_dim(), &c);
      per[f] = c;
    }
    std::vector<double> sorted = per;
    std::nth_element(sorted.begin(), sorted.begin() + sorted.size() / 2, sorted.end());
    const double med = sorted[sorted.size() / 2];
    double excess = 0;
    int high = 0;
    for (double c : per) {
      if (c > 4 * med) ++high;
      excess += std::max(0.0, c - med);
    }
    std::fprintf(stderr, "cost: median frame %.2f, frames > 4x median %d, sum above median %.1f\n", med, high, excess);
    for (size_t t = 0; t < d.trial_ranges.size(); ++t) {
      double sum = 0;
      int h = 0;
      for (int f = d.trial_ranges[t].first; f < d.trial_ranges[t].first + d.trial_ranges[t].second; ++f) {
        sum += per[f];
        h += per[f] > 4 * med;
      }
      std::fprintf(stderr, "cost: trial %zu (%s) sum %.1f, per frame %.2f, frames > 4x median %d\n", t,
                   d.trials[t].name.c_str(), sum, sum / d.trial_ranges[t].second, h);
    }
  }
  for (int c = 0; c < nz; ++c) {
    if (!IsRangedRotation(d.model, c)) continue;
    const Coordinate& k = d.model.coordinates()[c];
    for (int f = 0; f < problem.num_frames(); ++f) {
      const double v = x[static_cast<Eigen::Index>(f) * nz + c];
      if (v >= k.min_value && v <= k.max_value) continue;
      ++a.outside_range;
      if (std::getenv("FVC_DEBUG"))
        std::fprintf(stderr, "range: frame %d %s %.1f deg (truth %.1f)\n", f, k.name.c_str(), v * 180 / M_PI,
                     d.true_coordinates(f, c) * 180 / M_PI);
    }
  }
  // Every marker where the fitted model and pose put it, seen or hidden, against where the truth
  // put it: convention-free (joint axes and segment frames differ between the two models), and
  // a segment turned round in a gap moves its hidden markers far off.
  const double limit = 0.02;
  const Geometry fitted_geometry(fitted), truth_geometry(d.truth);
  ModelData fitted_data(fitted), truth_data(d.truth);
  std::vector<int> truth_marker(fitted.num_markers());
  for (int m = 0; m < fitted.num_markers(); ++m) truth_marker[m] = d.truth.FindMarker(fitted.markers()[m].name);
  for (const auto& [first, count] : d.trial_ranges) {
    int off = 0;
    for (int f = first; f < first + count; ++f) {
      ForwardKinematics(fitted, fitted_geometry, x.segment(static_cast<Eigen::Index>(f) * nz, nz), &fitted_data);
      ForwardKinematics(d.truth, truth_geometry, d.true_coordinates.row(f).transpose(), &truth_data);
      for (int m = 0; m < fitted.num_markers(); ++m) {
        if (truth_marker[m] < 0) continue;
        const double e = (MarkerPosition(fitted, fitted_geometry, fitted_data, m) -
                          MarkerPosition(d.truth, truth_geometry, truth_data, truth_marker[m])).norm();
        if (e > limit) {
          ++off;
          if (std::getenv("FVC_DEBUG"))
            std::fprintf(stderr, "off: frame %d marker %s %.1f mm %s\n", f, fitted.markers()[m].name.c_str(),
                         1000 * e, std::isfinite(d.measurements(f, 3 * m)) ? "seen" : "hidden");
          break;
        }
      }
    }
    a.frames_off_per_trial.push_back(off);
    a.frames_off += off;
  }
  return a;
}

// Per-frame IK with the nominal geometry, trials in parallel: FitModel's starting point.
Eigen::VectorXd InitialGuess(const BenchData& d, const solver::MarkerFitProblem& problem,
                             const solver::FitOptions& options, int threads) {
  const int nz = problem.frame_dim(), np = problem.shared_dim();
  Eigen::VectorXd x(static_cast<Eigen::Index>(problem.num_frames()) * nz + np);
  const int nt = static_cast<int>(d.trial_ranges.size());
  std::vector<Status> status(nt);
  const std::vector<int> order = solver::LongestFirst(nt, [&](int t) { return d.trial_ranges[t].second; });
  solver::ParallelQueue(order, threads, [&](int, auto&& next) {
    Geometry geometry(d.model);
    solver::InverseKinematics ik(d.model, geometry, options.ik);
    for (int t = next(); t >= 0; t = next()) {
      const auto [first, count] = d.trial_ranges[t];
      Eigen::MatrixXd z;
      status[t] = ik.SolveTrial(problem.measurements().middleRows(first, count), &z);
      if (!status[t].ok()) continue;
      for (int f = 0; f < count; ++f)
        x.segment(static_cast<Eigen::Index>(first + f) * nz, nz) = z.row(f).transpose();
    }
  });
  for (int t = 0; t < nt; ++t)
    if (!status[t].ok()) {
      std::fprintf(stderr, "fit_vs_ceres: IK failed on trial %d: %s\n", t, status[t].message().c_str());
      std::exit(1);
    }
  x.tail(np) = problem.InitialShared();
  return x;
}

// ---------------------------------------------------------------------------------------------
// The problem as Ceres sees it

// How the shared parameters p are split into Ceres parameter blocks.
enum class SharedLayout {
  kObject,   // one block per model object: segment scale, joint centre, axis element, marker
  kSegment,  // one block per segment's geometry: its scale, its own joint's centre and axes, its
             // markers (fewer, larger blocks: less block bookkeeping, denser Jacobian blocks)
  kSingle,   // all of p in one block
};

SharedLayout ParseSharedLayout(const std::string& s) {
  return s == "split" ? SharedLayout::kObject : s == "segment" ? SharedLayout::kSegment : SharedLayout::kSingle;
}

std::uint64_t NextContextId() {
  static std::atomic<std::uint64_t> next{1};
  return next++;
}

// A Ceres parameter block of shared parameters: free indices (into p) in the block's order. Ceres
// stores the blocks one after another, so p is stored permuted (CeresFit::SetX / GetX).
struct SharedBlock {
  std::vector<int> free;
  int offset = 0;  // in the stored p
};

// The parameter blocks and Jacobian columns of one kind of marker cost function.
struct MarkerLayout {
  std::vector<int> markers;  // model markers; marker i owns residual rows 3i..3i+2
  std::vector<int> blocks;   // shared blocks, Ceres parameter blocks 1.. (block 0 is z_f)
  // Per marker, per MarkerJacobian p column: (parameter block 1.., column), or block -1 if fixed.
  std::vector<std::vector<std::pair<int, int>>> columns;
};

struct CeresContext {
  // Unique per context: a thread's Workspace belongs to one (ThreadWorkspace).
  const std::uint64_t id = NextContextId();
  const solver::MarkerFitProblem* problem = nullptr;
  std::vector<SharedBlock> blocks;
  std::vector<int> block_of_free;  // free index -> shared block
  std::vector<int> slot_of_free;   // free index -> position in its block
  std::vector<int> stored_of_free;  // free index -> position in the stored p
};

// The shared blocks of `layout`, in order of their first free parameter.
void MakeSharedBlocks(const solver::MarkerFitProblem& problem, SharedLayout layout, CeresContext* c) {
  const Model& model = problem.model();
  const auto& info = model.parameters();
  const int np = problem.shared_dim();
  std::map<std::tuple<int, int, int>, int> block_of_key;
  c->block_of_free.assign(np, -1);
  c->slot_of_free.assign(np, -1);
  c->stored_of_free.assign(np, -1);
  for (int k = 0; k < np; ++k) {
    const ParameterInfo& a = info[problem.free_parameters()[k]];
    std::tuple<int, int, int> key{0, 0, 0};
    if (layout == SharedLayout::kObject) {
      key = {static_cast<int>(a.group), a.object, a.element};
    } else if (layout == SharedLayout::kSegment) {
      int segment = -1;
      switch (a.group) {
        case ParameterGroup::kScale: segment = a.object; break;
        case ParameterGroup::kCentre:
        case ParameterGroup::kAxis: segment = model.joints()[a.object].child; break;
        case ParameterGroup::kMarker: segment = model.markers()[a.object].segment; break;
      }
      key = {segment, 0, 0};
    }
    auto [it, added] = block_of_key.emplace(key, static_cast<int>(c->blocks.size()));
    if (added) c->blocks.emplace_back();
    c->block_of_free[k] = it->second;
    c->slot_of_free[k] = static_cast<int>(c->blocks[it->second].free.size());
    c->blocks[it->second].free.push_back(k);
  }
  int offset = 0;
  for (SharedBlock& b : c->blocks) {
    b.offset = offset;
    for (size_t i = 0; i < b.free.size(); ++i) c->stored_of_free[b.free[i]] = offset + static_cast<int>(i);
    offset += static_cast<int>(b.free.size());
  }
}

// What one thread needs to evaluate marker residuals: a Geometry for the shared values it last saw
// and the forward kinematics of the pose it last saw. Ceres hands residual blocks to threads with
// pointers into its own (changing) state vectors, so both caches are keyed on VALUES. Ceres 2.1
// keeps a frame's residual blocks together and deals them to threads round-robin, so with one cost
// function per marker each thread still runs the frame's FK once, not once per marker; the
// Geometry is rebuilt only when Ceres moves to a new point.
//
// A cost function sees only its own shared blocks, so `full` can mix values of the current point
// (the blocks seen since it moved) and of an older one. That is safe: a marker's residual and
// Jacobian depend only on the parameters in its own chain (model.marker_parameters), which are
// exactly the blocks it passes in, and those are always current.
struct Workspace {
  explicit Workspace(const CeresContext& c)
      : owner(&c), owner_id(c.id), stored(c.problem->shared_dim()),
        full(c.problem->FullParameters(c.problem->InitialShared())), geometry(c.problem->model()), data(c.problem->model()), z(c.problem->frame_dim()),
        jz(3, c.problem->model().max_chain_coordinates()),
        jp(3, c.problem->model().max_chain_parameters()) {
    const Eigen::VectorXd p = c.problem->InitialShared();
    for (int k = 0; k < p.size(); ++k) stored[c.stored_of_free[k]] = p[k];
  }

  const CeresContext* owner;
  std::uint64_t owner_id;  // a later context may reuse the address, with another layout
  Eigen::VectorXd stored, full;  // stored (block-ordered) and full parameters behind `geometry`
  Geometry geometry;
  bool geometry_valid = false;
  ModelData data;
  Eigen::VectorXd z;  // the pose behind `data`
  bool fk_valid = false;
  Eigen::Matrix<double, 3, Eigen::Dynamic> jz, jp;
};

Workspace& ThreadWorkspace(const CeresContext& context) {
  thread_local std::unique_ptr<Workspace> ws;
  if (!ws || ws->owner != &context || ws->owner_id != context.id) ws = std::make_unique<Workspace>(context);
  return *ws;
}

// Marker residuals of one frame: all its markers, or one marker, per the layout.
class MarkerCost final : public ceres::CostFunction {
 public:
  MarkerCost(const CeresContext* context, const MarkerLayout* layout, int frame)
      : context_(context), layout_(layout), frame_(frame) {
    set_num_residuals(3 * static_cast<int>(layout->markers.size()));
    mutable_parameter_block_sizes()->push_back(context->problem->frame_dim());
    for (int b : layout->blocks)
      mutable_parameter_block_sizes()->push_back(static_cast<int>(context->blocks[b].free.size()));
  }

  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override {
    const solver::MarkerFitProblem& problem = *context_->problem;
    const Model& model = problem.model();
    const int nz = problem.frame_dim();
    Workspace& ws = ThreadWorkspace(*context_);
    if (!Prepare(parameters, &ws)) return false;
    const double* meas = problem.measurements().row(frame_).data();
    const auto& markers = layout_->markers;
    for (size_t i = 0; i < markers.size(); ++i) {
      const int m = markers[i];
      const double scale = problem.residual_scale(m);
      const Eigen::Vector3d x = MarkerPosition(model, ws.geometry, ws.data, m);
      double* r = residuals + 3 * i;
      for (int k = 0; k < 3; ++k) r[k] = scale * (x[k] - meas[3 * m + k]);
      if (!std::isfinite(r[0] + r[1] + r[2])) return false;
    }
    if (jacobians == nullptr) return true;
    const int rows = num_residuals();
    const int nb = static_cast<int>(parameter_block_sizes().size());
    for (int b = 0; b < nb; ++b)
      if (jacobians[b]) std::fill_n(jacobians[b], rows * parameter_block_sizes()[b], 0.0);
    for (size_t i = 0; i < markers.size(); ++i) {
      const int m = markers[i];
      const double scale = problem.residual_scale(m);
      const auto& zcols = model.marker_coordinates(m);
      auto jz = ws.jz.leftCols(static_cast<Eigen::Index>(zcols.size()));
      auto jp = ws.jp.leftCols(static_cast<Eigen::Index>(model.marker_parameters(m).size()));
      MarkerJacobian(model, ws.geometry, ws.data, m, &jz, &jp);
      // Ceres's Jacobians are row-major, rows x block size.
      if (jacobians[0])
        for (size_t a = 0; a < zcols.size(); ++a)
          for (int k = 0; k < 3; ++k) jacobians[0][(3 * i + k) * nz + zcols[a]] += scale * jz(k, a);
      const auto& cols = layout_->columns[i];
      for (size_t c = 0; c < cols.size(); ++c) {
        const auto [b, col] = cols[c];
        if (b < 0 || !jacobians[b]) continue;
        const int size = parameter_block_sizes()[b];
        for (int k = 0; k < 3; ++k) jacobians[b][(3 * i + k) * size + col] += scale * jp(k, c);
      }
    }
    return true;
  }

 private:
  // Brings the thread's Geometry and FK up to date with `parameters`. False for a non-positive
  // scale, which ours (MarkerFitProblem::SetShared) rejects too.
  bool Prepare(double const* const* parameters, Workspace* ws) const {
    const solver::MarkerFitProblem& problem = *context_->problem;
    const Model& model = problem.model();
    for (size_t i = 0; i < layout_->blocks.size(); ++i) {
      const SharedBlock& b = context_->blocks[layout_->blocks[i]];
      const size_t size = b.free.size();
      double* cached = ws->stored.data() + b.offset;
      if (std::memcmp(cached, parameters[1 + i], size * sizeof(double)) == 0) continue;
      std::memcpy(cached, parameters[1 + i], size * sizeof(double));
      for (size_t k = 0; k < size; ++k) ws->full[problem.free_parameters()[b.free[k]]] = cached[k];
      ws->geometry_valid = false;
    }
    if (!ws->geometry_valid) {
      for (int s = 0; s < model.num_segments(); ++s)
        if (!(ws->full[model.scale_index(s)] > 0)) return false;
      ws->geometry.Set(model, ws->full);
      ws->geometry_valid = true;
      ws->fk_valid = false;
    }
    const int nz = problem.frame_dim();
    if (!ws->fk_valid || std::memcmp(ws->z.data(), parameters[0], nz * sizeof(double)) != 0) {
      std::memcpy(ws->z.data(), parameters[0], nz * sizeof(double));
      ForwardKinematics(model, ws->geometry, ws->z, &ws->data);
      ws->fk_valid = true;
    }
    return true;
  }

  const CeresContext* context_;
  const MarkerLayout* layout_;
  int frame_;
};

// The per-frame prior rows w_i (z_i - target_i) on one frame block (ArrowProblem::FramePrior).
class FramePriorCost final : public ceres::CostFunction {
 public:
  FramePriorCost(const double* weight, const double* target, int nz) : weight_(weight), target_(target) {
    set_num_residuals(nz);
    mutable_parameter_block_sizes()->push_back(nz);
  }
  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override {
    const int nz = num_residuals();
    for (int i = 0; i < nz; ++i) residuals[i] = weight_[i] * (parameters[0][i] - target_[i]);
    if (jacobians && jacobians[0]) {
      std::fill(jacobians[0], jacobians[0] + nz * nz, 0.0);
      for (int i = 0; i < nz; ++i) jacobians[0][i * nz + i] = weight_[i];
    }
    return true;
  }

 private:
  const double* weight_;
  const double* target_;
};

// The prior rows w_i (p_i - target_i) and the gauge rows G (p - target), on every shared block.
class PriorCost final : public ceres::CostFunction {
 public:
  explicit PriorCost(const CeresContext* context) : context_(context) {
    const auto& problem = *context->problem;
    set_num_residuals(problem.shared_dim() + static_cast<int>(problem.shared_rows().rows()));
    for (const SharedBlock& b : context->blocks)
      mutable_parameter_block_sizes()->push_back(static_cast<int>(b.free.size()));
  }

  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override {
    const auto& problem = *context_->problem;
    const int np = problem.shared_dim();
    const Eigen::VectorXd& w = problem.prior_weight();
    const Eigen::MatrixXd& g = problem.shared_rows();
    const auto& blocks = context_->blocks;
    Eigen::VectorXd delta(np);
    for (size_t b = 0; b < blocks.size(); ++b)
      for (size_t k = 0; k < blocks[b].free.size(); ++k) delta[blocks[b].free[k]] = parameters[b][k];
    delta -= problem.prior_target();
    Eigen::Map<Eigen::VectorXd> r(residuals, num_residuals());
    r.head(np) = w.cwiseProduct(delta);
    r.tail(g.rows()) = g * delta;
    if (!r.allFinite()) return false;
    if (jacobians == nullptr) return true;
    for (size_t b = 0; b < blocks.size(); ++b) {
      if (!jacobians[b]) continue;
      const std::vector<int>& free = blocks[b].free;
      const int size = static_cast<int>(free.size());
      Eigen::Map<Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>> j(
          jacobians[b], num_residuals(), size);
      j.setZero();
      for (int k = 0; k < size; ++k) {
        j(free[k], k) = w[free[k]];
        j.col(k).tail(g.rows()) = g.col(free[k]);
      }
    }
    return true;
  }

 private:
  const CeresContext* context_;
};

// The Ceres problem over its own copy of x (Ceres's parameter blocks point into it): every frame
// of `problem`, or the frames listed (the coarse subset: the same residuals, frame priors, p
// priors and gauge rows; only the frame set differs, as solver::FrameSubsetProblem). x is stored
// as [z of each listed frame, p in the blocks' order]; SetX and GetX translate from and to the
// problem's x = [z_1 ... z_F, p].
class CeresFit {
 public:
  CeresFit(const solver::MarkerFitProblem& problem, std::vector<int> frames, bool per_marker,
           SharedLayout layout)
      : problem_ref_(&problem), frames_(std::move(frames)) {
    const int nz = problem.frame_dim(), np = problem.shared_dim();
    if (frames_.empty())
      for (int f = 0; f < problem.num_frames(); ++f) frames_.push_back(f);
    const int nf = static_cast<int>(frames_.size());
    x_.setZero(static_cast<Eigen::Index>(nf) * nz + np);
    context_.problem = &problem;
    MakeSharedBlocks(problem, layout, &context_);

    // Parameter blocks in x's order, so the Ceres gradient lines up with ours.
    ceres::Problem::Options options;
    options.cost_function_ownership = ceres::TAKE_OWNERSHIP;
    problem_ = std::make_unique<ceres::Problem>(options);
    for (int i = 0; i < nf; ++i) {
      parameter_blocks_.push_back(frame_block(i));
      problem_->AddParameterBlock(parameter_blocks_.back(), nz);
    }
    for (const SharedBlock& sb : context_.blocks) {
      parameter_blocks_.push_back(shared_block(sb));
      problem_->AddParameterBlock(parameter_blocks_.back(), static_cast<int>(sb.free.size()));
    }

    // Layouts depend only on which markers a cost function covers: per marker, or per frame's
    // set of present markers (one set unless data are missing).
    std::map<std::vector<int>, const MarkerLayout*> by_markers;
    auto layout_for = [&](const std::vector<int>& markers) {
      auto it = by_markers.find(markers);
      if (it != by_markers.end()) return it->second;
      layouts_.push_back(MakeLayout(problem, markers));
      return by_markers[markers] = layouts_.back().get();
    };
    const int nm = problem.model().num_markers();
    std::vector<int> present;
    for (int i = 0; i < nf; ++i) {
      const double* meas = problem.measurements().row(frames_[i]).data();
      present.clear();
      for (int m = 0; m < nm; ++m)
        if (std::isfinite(meas[3 * m])) present.push_back(m);
      if (present.empty()) continue;
      if (per_marker) {
        for (int m : present) AddMarkerCost(layout_for({m}), i);
      } else {
        AddMarkerCost(layout_for(present), i);
      }
    }
    for (int i = 0; i < nf; ++i) {
      const double *w, *target;
      if (problem.FramePrior(frames_[i], &w, &target))
        problem_->AddResidualBlock(new FramePriorCost(w, target, nz), nullptr, frame_block(i));
    }
    std::vector<double*> shared(parameter_blocks_.begin() + nf, parameter_blocks_.end());
    problem_->AddResidualBlock(new PriorCost(&context_), nullptr, shared);

    // Schur solvers eliminate the frames (group 0) and keep p (group 1).
    ordering_ = std::make_shared<ceres::ParameterBlockOrdering>();
    for (int i = 0; i < nf; ++i) ordering_->AddElementToGroup(parameter_blocks_[i], 0);
    for (double* sb : shared) ordering_->AddElementToGroup(sb, 1);
  }

  int num_frames() const { return static_cast<int>(frames_.size()); }
  int num_shared_blocks() const { return static_cast<int>(context_.blocks.size()); }
  int num_residual_blocks() const { return problem_->NumResidualBlocks(); }

  // The listed frames' poses and p from the problem's x (in place: Ceres points into x_).
  void SetX(const Eigen::VectorXd& x) {
    const int nz = problem_ref_->frame_dim(), np = problem_ref_->shared_dim();
    const Eigen::Index full_frames = static_cast<Eigen::Index>(problem_ref_->num_frames()) * nz;
    for (int i = 0; i < num_frames(); ++i)
      x_.segment(static_cast<Eigen::Index>(i) * nz, nz) =
          x.segment(static_cast<Eigen::Index>(frames_[i]) * nz, nz);
    for (int k = 0; k < np; ++k) x_[stored_begin() + context_.stored_of_free[k]] = x[full_frames + k];
  }
  // Writes the listed frames' poses and p into the problem's x (other frames untouched).
  void GetX(Eigen::VectorXd* x) const {
    const int nz = problem_ref_->frame_dim(), np = problem_ref_->shared_dim();
    const Eigen::Index full_frames = static_cast<Eigen::Index>(problem_ref_->num_frames()) * nz;
    for (int i = 0; i < num_frames(); ++i)
      x->segment(static_cast<Eigen::Index>(frames_[i]) * nz, nz) =
          x_.segment(static_cast<Eigen::Index>(i) * nz, nz);
    for (int k = 0; k < np; ++k) (*x)[full_frames + k] = x_[stored_begin() + context_.stored_of_free[k]];
  }

  // Holds p constant (SetParameterBlockConstant on every shared block) or frees it again.
  void SetSharedConstant(bool constant) {
    for (const SharedBlock& sb : context_.blocks) {
      if (constant) problem_->SetParameterBlockConstant(shared_block(sb));
      else problem_->SetParameterBlockVariable(shared_block(sb));
    }
  }

  // Cost and gradient at the current x, gradient in the problem's order (frames, then p).
  void Evaluate(int threads, double* cost, Eigen::VectorXd* gradient) {
    ceres::Problem::EvaluateOptions options;
    options.parameter_blocks = parameter_blocks_;
    options.num_threads = threads;
    std::vector<double> g;
    problem_->Evaluate(options, cost, nullptr, &g, nullptr);
    gradient->resize(static_cast<Eigen::Index>(g.size()));
    const Eigen::Index nfz = stored_begin();
    for (Eigen::Index i = 0; i < nfz; ++i) (*gradient)[i] = g[i];
    for (size_t k = 0; k < context_.stored_of_free.size(); ++k)
      (*gradient)[nfz + static_cast<Eigen::Index>(k)] = g[nfz + context_.stored_of_free[k]];
  }

  ceres::Solver::Summary Solve(ceres::Solver::Options options) {
    if (options.linear_solver_type == ceres::SPARSE_SCHUR ||
        options.linear_solver_type == ceres::DENSE_SCHUR)
      options.linear_solver_ordering = ordering_;
    ceres::Solver::Summary summary;
    ceres::Solve(options, problem_.get(), &summary);
    return summary;
  }

 private:
  Eigen::Index stored_begin() const {
    return static_cast<Eigen::Index>(num_frames()) * problem_ref_->frame_dim();
  }
  double* frame_block(int i) { return x_.data() + static_cast<Eigen::Index>(i) * problem_ref_->frame_dim(); }
  double* shared_block(const SharedBlock& sb) { return x_.data() + stored_begin() + sb.offset; }

  std::unique_ptr<MarkerLayout> MakeLayout(const solver::MarkerFitProblem& problem,
                                           const std::vector<int>& markers) {
    auto layout = std::make_unique<MarkerLayout>();
    layout->markers = markers;
    std::map<int, int> slot;  // shared block -> Ceres parameter block of the cost function
    for (int m : markers)
      for (int free : problem.marker_free_columns(m))
        if (free >= 0) slot.emplace(context_.block_of_free[free], 0);
    for (auto& [block, s] : slot) {
      layout->blocks.push_back(block);
      s = static_cast<int>(layout->blocks.size());  // parameter block 0 is z_f
    }
    for (int m : markers) {
      auto& cols = layout->columns.emplace_back();
      for (int free : problem.marker_free_columns(m)) {
        if (free < 0) {
          cols.emplace_back(-1, -1);
          continue;
        }
        cols.emplace_back(slot[context_.block_of_free[free]], context_.slot_of_free[free]);
      }
    }
    return layout;
  }

  void AddMarkerCost(const MarkerLayout* layout, int i) {
    std::vector<double*> blocks{frame_block(i)};
    for (int b : layout->blocks) blocks.push_back(shared_block(context_.blocks[b]));
    problem_->AddResidualBlock(new MarkerCost(&context_, layout, frames_[i]), nullptr, blocks);
  }

  const solver::MarkerFitProblem* problem_ref_;
  std::vector<int> frames_;  // problem frame of each Ceres frame block
  Eigen::VectorXd x_;
  CeresContext context_;
  std::vector<std::unique_ptr<MarkerLayout>> layouts_;
  std::unique_ptr<ceres::Problem> problem_;
  std::vector<double*> parameter_blocks_;
  std::shared_ptr<ceres::ParameterBlockOrdering> ordering_;
};

// Ceres's LM with our tolerances and damping bounds (Ceres's trust-region radius is 1 / lambda).
ceres::Solver::Options CeresOptions(const solver::LmOptions& lm, ceres::LinearSolverType type,
                                    int threads, double max_seconds) {
  ceres::Solver::Options o;
  o.minimizer_type = ceres::TRUST_REGION;
  o.trust_region_strategy_type = ceres::LEVENBERG_MARQUARDT;
  o.linear_solver_type = type;
  o.num_threads = threads;
  o.function_tolerance = lm.function_tolerance;
  o.gradient_tolerance = lm.gradient_tolerance;
  o.parameter_tolerance = lm.parameter_tolerance;
  o.max_num_iterations = 100;
  o.max_solver_time_in_seconds = max_seconds;
  o.initial_trust_region_radius = 1.0 / lm.initial_lambda;
  o.max_trust_region_radius = 1.0 / lm.min_lambda;
  o.min_lm_diagonal = lm.min_diagonal;
  o.max_lm_diagonal = lm.max_diagonal;
  o.min_relative_decrease = lm.min_gain_ratio;
  o.logging_type = ceres::SILENT;
  return o;
}

const char* CeresSolverName(const std::string& s) {
  return s == "schur" ? "SPARSE_SCHUR" : s == "normal" ? "SPARSE_NORMAL_CHOLESKY" : "DENSE_SCHUR";
}

// One ceres::Solve of a variant and what it cost.
struct CeresStage {
  std::string name;       // "whole", or the same strategy's "subset", "poses", "whole"
  double build_s = 0;     // building this stage's ceres::Problem (the subset's), inside the timing
  ceres::Solver::Summary summary;
};

// One Ceres variant: its start (cold: LM on the whole problem from x0; same: ours's strategy),
// shared-block layout, linear solver and initial trust-region radius; the fastest of its repeats.
struct CeresRun {
  std::string start, layout, solver;
  double radius = 0;  // the whole-problem stage's initial_trust_region_radius
  double seconds = 0;
  double cpu_seconds = 0;  // of the fastest run
  double others_cpu = 0;   // of the fastest run
  std::vector<CeresStage> stages;
  bool fallback = false;  // same: the subset did not converge; the whole problem solved cold
  bool capped = false;
  const ceres::Solver::Summary& whole() const { return stages.back().summary; }
  int iterations() const { return whole().num_successful_steps + whole().num_unsuccessful_steps; }
  std::string name() const {
    char radius_text[32];
    std::snprintf(radius_text, sizeof(radius_text), "%g", radius);
    return start + "/" + layout + "/" + CeresSolverName(solver) + "/r=" + radius_text;
  }
};

// Ceres's own time breakdown of one solve (Solver::Summary), in seconds and counts.
json CeresBreakdown(const ceres::Solver::Summary& sm) {
  const double evaluation = sm.residual_evaluation_time_in_seconds + sm.jacobian_evaluation_time_in_seconds;
  return {{"total_s", sm.total_time_in_seconds},
          {"preprocessor_s", sm.preprocessor_time_in_seconds},
          {"minimizer_s", sm.minimizer_time_in_seconds},
          {"postprocessor_s", sm.postprocessor_time_in_seconds},
          {"linear_solver_s", sm.linear_solver_time_in_seconds},
          {"residual_evaluation_s", sm.residual_evaluation_time_in_seconds},
          {"jacobian_evaluation_s", sm.jacobian_evaluation_time_in_seconds},
          {"inner_iteration_s", sm.inner_iteration_time_in_seconds},
          // the minimizer's time outside the linear solver and evaluations (step bookkeeping,
          // Jacobi scaling, trust-region logic)
          {"minimizer_other_s",
           sm.minimizer_time_in_seconds - sm.linear_solver_time_in_seconds - evaluation -
               std::max(0.0, sm.inner_iteration_time_in_seconds)},
          {"num_linear_solves", sm.num_linear_solves},
          {"num_residual_evaluations", sm.num_residual_evaluations},
          {"num_jacobian_evaluations", sm.num_jacobian_evaluations},
          {"successful_steps", sm.num_successful_steps},
          {"unsuccessful_steps", sm.num_unsuccessful_steps},
          {"initial_cost", sm.initial_cost},
          {"final_cost", sm.final_cost},
          {"termination", ceres::TerminationTypeToString(sm.termination_type)},
          {"message", sm.message},
          {"linear_solver_used", ceres::LinearSolverTypeToString(sm.linear_solver_type_used)},
          {"threads_used", sm.num_threads_used}};
}

ceres::LinearSolverType CeresSolverType(const std::string& s) {
  return s == "schur" ? ceres::SPARSE_SCHUR
         : s == "normal" ? ceres::SPARSE_NORMAL_CHOLESKY
                         : ceres::DENSE_SCHUR;
}

// The whole problem's coarse subset as solver::SolveCoarseToFine picks it: every
// (nf / coarse_frames)-th frame, centred in its stretch (solver/coarse_to_fine.cpp, stage 1).
std::vector<int> CoarseFrames(int nf, int coarse_frames) {
  std::vector<int> frames(coarse_frames);
  for (int i = 0; i < coarse_frames; ++i) frames[i] = static_cast<int>((i + 0.5) * nf / coarse_frames);
  return frames;
}

// What a variant's solves need besides the problem.
struct CeresSettings {
  solver::LmOptions lm;
  solver::CoarseToFineOptions coarse;
  int threads = 1;
  double max_seconds = 600;
  bool per_marker = true;
  SharedLayout layout = SharedLayout::kObject;
  double pose_tolerance = 1e-3;  // the same strategy's pose pass: Ceres's function_tolerance
  int pose_iterations = 8;       // ... and its max_num_iterations
};

// One run of a variant from x0 on `whole` (the whole problem's Ceres problem, built untimed as
// ours's problem is). Cold: Ceres's LM on the whole problem at `run->radius`. Same: ours's
// strategy step by step, each stage a ceres::Solve:
//  1. LM on the same coarse subset of frames (a Ceres problem of its own, built inside the timing),
//     to the same loose tolerance and iteration cap as ours (CoarseToFineOptions); if it does not
//     converge, the whole problem is solved cold from x0, as ours falls back;
//  2. every pose re-solved for the subset's p with p held constant (SetParameterBlockConstant on
//     every shared block): independent 38-unknown frames, so SPARSE_NORMAL_CHOLESKY (a Schur
//     solver with nothing left to keep would fall back to a dense one);
//  3. LM on the whole problem from there at ours's small initial damping (run->radius, which the
//     caller sets to 1 / CoarseToFineOptions::fine_initial_lambda; the pose pass uses it too).
// Ours's stage 3 also re-solves the poses after each step (inner iterations); Ceres's own
// use_inner_iterations cannot be restricted to the frames here (its groups must be independent
// sets and the prior couples every shared block), and with its automatic ordering it made the
// solve slower (issue 14: 53 s), so it is not used.
void RunCeresVariant(const solver::MarkerFitProblem& problem, CeresFit* whole, const Eigen::VectorXd& x0,
                     const CeresSettings& settings, CeresRun* run) {
  const auto start = Clock::now();
  auto options = [&](ceres::LinearSolverType type, double radius) {
    ceres::Solver::Options o = CeresOptions(settings.lm, type, settings.threads,
                                            std::max(1e-3, settings.max_seconds - Since(start)));
    o.initial_trust_region_radius = radius;
    return o;
  };
  const ceres::LinearSolverType type = CeresSolverType(run->solver);
  run->stages.clear();
  run->fallback = false;
  const int nf = problem.num_frames();
  const bool coarse = run->start == "same" && settings.coarse.enabled && nf >= settings.coarse.min_frames;
  // Below min_frames ours solves plainly, at the LM's own initial damping: so does "same".
  if (run->start == "same" && !coarse) run->radius = 1.0 / settings.lm.initial_lambda;
  if (coarse) {
    const auto build_start = Clock::now();
    CeresFit subset(problem, CoarseFrames(nf, settings.coarse.coarse_frames), settings.per_marker,
                    settings.layout);
    subset.SetX(x0);
    CeresStage stage{"subset", Since(build_start), {}};
    ceres::Solver::Options o = options(type, 1.0 / settings.lm.initial_lambda);
    o.function_tolerance = std::max(settings.lm.function_tolerance, settings.coarse.coarse_function_tolerance);
    o.max_num_iterations = std::min(settings.lm.max_iterations, settings.coarse.coarse_max_iterations);
    stage.summary = subset.Solve(o);
    const bool converged = stage.summary.termination_type == ceres::CONVERGENCE;
    run->stages.push_back(std::move(stage));
    if (converged) {
      // The subset's p with every pose from x0, as ours: the subset's frames are re-solved like
      // the others.
      Eigen::VectorXd from_subset = x0;
      subset.GetX(&from_subset);
      Eigen::VectorXd x = x0;
      x.tail(problem.shared_dim()) = from_subset.tail(problem.shared_dim());
      whole->SetX(x);
      whole->SetSharedConstant(true);
      ceres::Solver::Options po = options(ceres::SPARSE_NORMAL_CHOLESKY, run->radius);
      po.function_tolerance = settings.pose_tolerance;
      po.max_num_iterations = settings.pose_iterations;
      CeresStage poses{"poses", 0, whole->Solve(po)};
      whole->SetSharedConstant(false);
      run->stages.push_back(std::move(poses));
    } else {
      run->fallback = true;
      whole->SetX(x0);
    }
  } else {
    whole->SetX(x0);
  }
  // A fallback goes cold, at the LM's own initial damping, as ours's does.
  CeresStage last{"whole", 0, {}};
  last.summary = whole->Solve(options(type, run->fallback ? 1.0 / settings.lm.initial_lambda : run->radius));
  run->stages.push_back(std::move(last));
}

double RelativeDifference(double a, double b) {
  return std::abs(a - b) / std::max({std::abs(a), std::abs(b), 1e-300});
}

}  // namespace

int main(int argc, char** argv) {
  const Args args = ParseArgs(argc, argv);
  solver::FitOptions fit_options;  // defaults: all four groups free, FitModel's LM settings
  // One problem, solved by both from the same start: FitModel's schedule (generic models) would
  // change the problem between stages; Ceres gets the single problem, so ours does too.
  fit_options.staged = false;
  if (args.min_diagonal > 0) fit_options.lm.min_diagonal = args.min_diagonal;
  if (args.max_iterations >= 0) fit_options.lm.max_iterations = args.max_iterations;
  if (args.geodesic >= 0) fit_options.lm.geodesic_acceleration = args.geodesic == 1;
  if (args.geodesic_alpha > 0) fit_options.lm.max_acceleration_ratio = args.geodesic_alpha;
  if (args.geodesic_h > 0) fit_options.lm.acceleration_step = args.geodesic_h;
  fit_options.unobserved_hold.enabled = args.hold;
  if (args.hold_weak > 0) fit_options.unobserved_hold.weak_ratio = args.hold_weak;
  if (args.hold_ratio > 0) fit_options.unobserved_hold.hold_ratio = args.hold_ratio;
  if (args.ik_limit_stiffness >= 0) fit_options.ik.coordinate_limit_stiffness = args.ik_limit_stiffness;
  if (args.limit_sigma > 0) fit_options.coordinate_limit_sigma_rad = args.limit_sigma;
  if (args.frame_prior_sigma > 0) {
    fit_options.frame_prior_sigma_rad = args.frame_prior_sigma;
    fit_options.frame_prior_sigma_m = args.frame_prior_sigma;
  }

  const auto setup_start = Clock::now();
  BenchData data = MakeData(args.frames, args);
  if (args.clamp_ranges) {
    const int clamped = ClampRangedRotations(&data.model);
    std::printf("--clamp-ranges: %d joint rotations clamped to their ranges; the truth has %d (frame, rotation) "
                "pairs outside them\n", clamped, CountOutsideRange(data.model, data.true_coordinates));
  }
  solver::MarkerFitProblem problem(data.model, data.measurements, fit_options);
  const int nf = problem.num_frames(), nz = problem.frame_dim(), np = problem.shared_dim();
  const double setup_seconds = Since(setup_start);

  const SolveTimer ik_timer;
  const Eigen::VectorXd x0 = InitialGuess(data, problem, fit_options, args.threads);
  problem.SetFramePriorTargets(x0);  // as FitModel does: each frame weakly held at its start
  const double ik_seconds = ik_timer.wall(), ik_cpu = ik_timer.cpu(), ik_others = ik_timer.others();
  // As FitModel does: the coordinates a frame in a gap leaves unobserved held at their start
  // (solver::UnobservedCoordinateWeights); part of the problem both solvers get, so untimed.
  const auto hold_start = Clock::now();
  formats::RowMatrix hold_weights;
  const int held = solver::UnobservedCoordinateWeights(&problem, x0, problem.uniform_frame_prior_weight(),
                                                       fit_options.unobserved_hold, args.threads, &hold_weights);
  problem.SetFramePriorWeights(std::move(hold_weights));
  const double hold_seconds = Since(hold_start);

  json out;
  out["frames"] = nf;
  out["unknowns"] = static_cast<long long>(nf) * nz + np;
  out["shared"] = np;
  out["residuals"] = problem.num_residuals();
  out["threads"] = args.threads;
  out["repeat"] = args.repeat;
  out["loadavg_1m"] = LoadAverage();  // other work on the machine skews both timings
  out["data"] = data.source;
  out["setup_s"] = setup_seconds;
  out["ik_s"] = ik_seconds;
  out["ik_cpu_s"] = ik_cpu;
  out["ik_others_cpu"] = ik_others;
  out["held_coordinates"] = held;
  out["hold_s"] = hold_seconds;

  // Ours first, and Ceres's problem built only afterwards, so that ours_peak_rss_mb is ours alone
  // (with the data, the problem and the IK, which Ceres's runs hold too).
  PeakMemory memory;
  solver::LmSummary ours;
  bool ours_cached = false;
  std::vector<double> ours_times;
  double ours_cpu = 0, ours_others_cpu = 0;
  solver::CoarseToFineSummary ours_coarse;
  Eigen::VectorXd ours_x;
  for (int rep = 0; rep < args.repeat; ++rep) {
    Eigen::VectorXd x = x0;
    const SolveTimer timer;
    // FitModel's solve: the coarse-to-fine start, then LM on the whole problem (its memory budget).
    solver::CoarseToFineSummary coarse;
    solver::ArrowSchurProblem schur(&problem, args.threads);
    solver::LmSummary summary = solver::SolveCoarseToFine(&problem, &schur, fit_options.lm,
                                                          args.coarse, args.threads, &x, &coarse);
    ours_times.push_back(timer.wall());
    if (ours_times.back() <= *std::min_element(ours_times.begin(), ours_times.end())) {
      ours = summary;
      ours_x = x;
      ours_coarse = coarse;
      ours_cpu = timer.cpu();
      ours_others_cpu = timer.others();
    }
  }
  ours_cached = ours_coarse.frames_cached;
  if (!args.save_x.empty() && ours_x.size() > 0 && problem.SetShared(ours_x.tail(np))) {
    std::vector<double> frame_costs(nf, 0.0);
    auto evaluator = problem.NewEvaluator();
    for (int f = 0; f < nf; ++f)
      solver::FrameSquaredNorm(problem, evaluator.get(), f, ours_x.data() + static_cast<size_t>(f) * nz,
                               &frame_costs[f]);
    if (FILE* file = std::fopen(args.save_x.c_str(), "wb")) {
      std::fwrite(frame_costs.data(), sizeof(double), frame_costs.size(), file);
      std::fwrite(ours_x.data(), sizeof(double), ours_x.size(), file);
      std::fclose(file);
    }
  }
  // --time-iteration K: the parts of one whole-problem iteration of the fine stage, timed K times
  // at our solution (the same work every time): the linearisation with the reduction at an
  // anticipated damping, the shared solve and back-substitution, the candidate's cost, and the
  // inner iteration's pose re-solve, as SolveCoarseToFine runs them. Each part's CPU seconds are
  // the minimum over the K runs (the machine is shared: the least disturbed run is the work).
  if (args.time_iteration > 0) {
    const double lambda = 1e-3;  // the crawl's damping (BENCHMARKS.md, "With gaps")
    solver::ArrowSchurProblem schur(&problem, args.threads);
    solver::CoarseToFineOptions inner = args.coarse;
    inner.pose_iterations = inner.inner_pose_iterations;
    inner.pose_from_predecessor = false;
    // The last part is not one of the iteration's: the variable projection's cost and re-solve as
    // the fine stage runs them, in one pass fewer (solver::ProjectedCost, the rescue included),
    // against the two parts before it; its cost must be the "cost" part's to the bit.
    const char* names[5] = {"linearize", "solve", "cost", "inner_iteration", "projected_cost"};
    double wall_sum[5] = {0, 0, 0, 0, 0}, cpu_min[5];
    std::fill(cpu_min, cpu_min + 5, std::numeric_limits<double>::infinity());
    bool ok = true, same_cost = true;
    for (int k = 0; k < args.time_iteration && ok; ++k) {
      Eigen::VectorXd x = ours_x, gradient, diagonal, dx;
      double cost = 0, new_cost = 0;
      auto part = [&](int i, auto&& work) {
        const SolveTimer timer;
        ok = ok && work();
        wall_sum[i] += timer.wall();
        cpu_min[i] = std::min(cpu_min[i], timer.cpu());
      };
      part(0, [&] {
        schur.AnticipateDamping(lambda, fit_options.lm.min_diagonal, fit_options.lm.max_diagonal);
        return schur.Linearize(x, &cost, &gradient, &diagonal);
      });
      const Eigen::VectorXd damping =
          lambda * diagonal.cwiseMax(fit_options.lm.min_diagonal).cwiseMin(fit_options.lm.max_diagonal);
      part(1, [&] { return schur.SolveDamped(damping, &dx); });
      x += dx;
      const Eigen::VectorXd candidate = x;
      part(2, [&] { return schur.Cost(x, &new_cost); });
      part(3, [&] {
        bool refined = false;
        solver::RefineFramePoses(&problem, inner, args.threads, &x, &refined, nullptr, schur.frame_costs().data(),
                                 2.0 * fit_options.lm.function_tolerance * new_cost);
        return refined;
      });
      part(4, [&] {
        Eigen::VectorXd projected;
        double fused_cost = 0, projected_cost = 0;
        int rescued = 0;
        const bool done = solver::ProjectedCost(&problem, inner, args.threads, schur.num_threads(), candidate,
                                                fit_options.lm.function_tolerance, &fused_cost, &projected,
                                                &projected_cost, &rescued);
        same_cost = same_cost && fused_cost == new_cost;
        return done;
      });
    }
    json parts;
    std::string line;
    double total = 0;
    for (int i = 0; i < 5; ++i) {
      parts[names[i]] = {{"wall_s", wall_sum[i] / args.time_iteration}, {"cpu_s", cpu_min[i]}};
      if (i < 4) total += cpu_min[i];
      char part[64];
      std::snprintf(part, sizeof(part), "%s%s %.4f", i ? ", " : "", names[i], cpu_min[i]);
      line += part;
    }
    out["ours_iteration_parts"] = parts;
    std::fprintf(stderr, "  one fine-stage iteration (%d runs, %s): CPU s %s; total %.3f (without the last)%s\n",
                 args.time_iteration, ok ? "min CPU" : "FAILED", line.c_str(), total,
                 same_cost ? "" : "; projected_cost's cost DIFFERS from cost's");
  }
  // The plain LM on the whole problem from x0, for comparison (--plain).
  solver::LmSummary plain;
  std::vector<double> plain_times;
  double plain_cpu = 0;
  for (int rep = 0; args.plain && rep < args.repeat; ++rep) {
    Eigen::VectorXd x = x0;
    const SolveTimer timer;
    solver::ArrowSchurProblem schur(&problem, args.threads);
    solver::LmSummary summary = solver::Solve(fit_options.lm, &schur, &x);
    plain_times.push_back(timer.wall());
    if (plain_times.back() <= *std::min_element(plain_times.begin(), plain_times.end())) {
      plain = summary;
      plain_cpu = timer.cpu();
    }
  }
  const double ours_seconds = *std::min_element(ours_times.begin(), ours_times.end());
  const double ours_rss = memory.ProcessPeakMb();
  if (args.verbose)
    std::fprintf(stderr, "--- ours: coarse stage ---\n%s--- ours ---\n%s%s\n", ours_coarse.coarse.FullReport().c_str(),
                 ours.FullReport().c_str(), ours_coarse.BriefReport().c_str());
  out["ours_s"] = ours_seconds;
  out["ours_s_all"] = ours_times;
  out["ours_cpu_s"] = ours_cpu;
  out["ours_others_cpu"] = ours_others_cpu;
  out["ours_cost"] = ours.final_cost;
  out["initial_cost"] = ours.initial_cost;
  out["ours_iterations"] = ours.num_iterations();
  out["ours_linear_solves"] = ours.num_linear_solves;
  out["ours_termination"] = solver::ToString(ours.termination);
  out["ours_breakdown"] = {{"linearize_s", ours.linearize_seconds},
                           {"linear_solver_s", ours.linear_solver_seconds},
                           {"cost_s", ours.cost_evaluation_seconds},
                           {"inner_iterations_s", ours.inner_iteration_seconds},
                           {"acceleration_s", ours.acceleration_seconds}};
  out["ours_geodesic"] = {{"enabled", fit_options.lm.geodesic_acceleration},
                          {"accelerated_steps", ours.num_accelerated_steps},
                          {"refused_steps", ours.num_acceleration_rejections},
                          {"failed_solves", ours.num_acceleration_failures},
                          {"coarse_accelerated_steps", ours_coarse.coarse.num_accelerated_steps},
                          {"coarse_refused_steps", ours_coarse.coarse.num_acceleration_rejections}};
  out["ours_coarse"] = {{"used", ours_coarse.used},
                        {"fallback", ours_coarse.fallback},
                        {"frames", ours_coarse.coarse_frames},
                        {"iterations", ours_coarse.coarse.num_iterations()},
                        {"seconds", ours_coarse.coarse.total_seconds},
                        {"pose_seconds", ours_coarse.pose_seconds},
                        {"poses_rescued", ours_coarse.poses_rescued},
                        {"start_cost", ours_coarse.start_cost},
                        {"fine_start_cost", ours_coarse.fine_start_cost},
                        {"total_seconds", ours_coarse.total_seconds},
                        {"fine_start_s", ours_coarse.fine_start_seconds},
                        {"fine_start_cpu_s", ours_coarse.fine_start_cpu_seconds}};
  out["ours_fine_options"] = {{"variable_projection", args.coarse.fine_variable_projection},
                              {"secant_curvature", args.coarse.fine_secant_curvature},
                              {"reduced_damping", args.coarse.fine_reduced_damping},
                              {"raise_lambda_below_gain", args.coarse.fine_raise_lambda_below_gain},
                              {"converge_min_gain_ratio", args.coarse.fine_converge_min_gain_ratio}};
  if (args.plain) {
    out["plain_s"] = *std::min_element(plain_times.begin(), plain_times.end());
    out["plain_s_all"] = plain_times;
    out["plain_cpu_s"] = plain_cpu;
    out["plain_cost"] = plain.final_cost;
    out["plain_iterations"] = plain.num_iterations();
  }
  solver::FitResult fitted;
  if (args.fit_model) {
    std::vector<solver::FitTrial> fit_trials(data.trials.size());
    for (size_t t = 0; t < data.trials.size(); ++t) fit_trials[t].markers = data.trials[t];
    solver::FitOptions options = fit_options;
    options.num_threads = args.threads;
    if (args.rescue_rounds >= 0) options.rescue_rounds = args.rescue_rounds;
    if (Status s = solver::FitModel(data.model, fit_trials, options, &fitted); !s) {
      std::fprintf(stderr, "fit_vs_ceres: FitModel: %s\n", s.message().c_str());
      return 1;
    }
    const solver::FitReport& r = fitted.report;
    out["fitmodel_wall_s"] = r.wall_seconds;
    out["fitmodel_solve_s"] = r.solve_seconds;
    out["fitmodel_ik_s"] = r.ik_seconds;
    out["fitmodel_cost"] = r.solver.final_cost;
    out["fitmodel_iterations"] = r.solver.num_iterations();
    out["fitmodel_termination"] = solver::ToString(r.solver.termination);
    out["fitmodel_reposed"] = r.reposed;
    out["fitmodel_rescued_frames"] = r.rescued_frames;
    out["fitmodel_marker_rms_mm"] = r.marker_rms_mm;
    out["fitmodel_per_trial_rms_mm"] = r.per_trial_rms_mm;
  }
  const Accuracy start_accuracy = MeasureAccuracy(data, problem, x0);
  const Accuracy ours_accuracy = MeasureAccuracy(data, problem, ours_x);
  for (const auto& [key, a] : {std::pair{"start_accuracy", &start_accuracy}, std::pair{"ours_accuracy", &ours_accuracy}})
    out[key] = {{"centre_max_mm", a->centre_max_mm},
                {"centre_rms_mm", a->centre_rms_mm},
                {"frames_marker_off_20mm", a->frames_off},
                {"frames_marker_off_20mm_per_trial", a->frames_off_per_trial},
                {"coordinates_outside_range", a->outside_range}};
  out["ours_caches_frames"] = ours_cached;  // U_f, W_f kept between passes (memory budget)
  out["ours_peak_rss_mb"] = ours_rss;

  std::vector<CeresRun> runs;
  const double default_radius = 1.0 / fit_options.lm.initial_lambda;
  const std::vector<double> cold_radii =
      args.ceres_radius.empty() ? std::vector<double>{default_radius} : args.ceres_radius;
  // Ours's stage 3 damping as a radius; the same start's pose pass and whole problem use it.
  const double same_radius = 1.0 / std::clamp(args.coarse.fine_initial_lambda, fit_options.lm.min_lambda,
                                               fit_options.lm.max_lambda);
  for (const std::string& layout : args.skip_ceres ? std::vector<std::string>{} : args.ceres_shared) {
    // One Ceres problem per layout, built untimed (as ours's problem), freed before the next.
    const auto build_start = Clock::now();
    CeresFit ceres_fit(problem, {}, args.ceres_residuals == "marker", ParseSharedLayout(layout));
    ceres_fit.SetX(x0);
    out["ceres_build_s"][layout] = Since(build_start);
    out["ceres_residuals"] = args.ceres_residuals;
    out["ceres_shared_blocks"][layout] = ceres_fit.num_shared_blocks();
    out["ceres_residual_blocks"] = ceres_fit.num_residual_blocks();

    // Sanity check: the same cost and gradient at x0.
    {
      double ceres_cost = 0, our_cost = 0;
      Eigen::VectorXd ceres_gradient, our_gradient, diagonal;
      ceres_fit.Evaluate(args.threads, &ceres_cost, &ceres_gradient);
      solver::ArrowSchurProblem schur(&problem, args.threads);
      schur.Linearize(x0, &our_cost, &our_gradient, &diagonal);
      const double cost_rel = RelativeDifference(ceres_cost, our_cost);
      const double gradient_rel =
          (ceres_gradient - our_gradient).norm() / std::max(our_gradient.norm(), 1e-300);
      out["check"][layout] = {{"initial_cost_rel", cost_rel}, {"gradient_rel", gradient_rel}};
      if (!(cost_rel <= 1e-9))
        std::fprintf(stderr, "fit_vs_ceres: ERROR: %s layout: initial costs differ: ours %.12e, Ceres %.12e (rel %.2e)\n",
                     layout.c_str(), our_cost, ceres_cost, cost_rel);
      if (!(gradient_rel <= 1e-9))
        std::fprintf(stderr, "fit_vs_ceres: ERROR: %s layout: initial gradients differ (relative %.2e)\n",
                     layout.c_str(), gradient_rel);
    }

    CeresSettings settings;
    settings.lm = fit_options.lm;
    settings.coarse = args.coarse;
    settings.threads = args.threads;
    settings.max_seconds = args.ceres_max_seconds;
    settings.per_marker = args.ceres_residuals == "marker";
    settings.layout = ParseSharedLayout(layout);
    settings.pose_tolerance = args.ceres_pose_tolerance;
    settings.pose_iterations =
        args.ceres_pose_iterations > 0 ? args.ceres_pose_iterations : args.coarse.pose_iterations;
    for (const std::string& start : args.ceres_starts)
      for (const std::string& s : args.ceres_solvers)
        for (double radius : start == "same" ? std::vector<double>{same_radius} : cold_radii) {
          CeresRun run;
          run.start = start;
          run.layout = layout;
          run.solver = s;
          run.radius = radius;
          run.seconds = std::numeric_limits<double>::infinity();
          std::vector<double> times;
          const bool own_peak = memory.Reset();
          for (int rep = 0; rep < args.repeat; ++rep) {
            CeresRun attempt = run;
            const SolveTimer timer;
            RunCeresVariant(problem, &ceres_fit, x0, settings, &attempt);
            times.push_back(timer.wall());
            if (times.back() < run.seconds) {
              run = std::move(attempt);
              run.seconds = times.back();
              run.cpu_seconds = timer.cpu();
              run.others_cpu = timer.others();
            }
          }
          const ceres::Solver::Summary& sm = run.whole();
          run.capped = sm.termination_type == ceres::NO_CONVERGENCE &&
                       sm.message.find("time") != std::string::npos;
          const double initial = run.stages.front().summary.initial_cost;
          if (run.stages.front().name == "whole" && RelativeDifference(initial, ours.initial_cost) > 1e-9)
            std::fprintf(stderr, "fit_vs_ceres: ERROR: %s initial cost %.12e differs from ours %.12e\n",
                         run.name().c_str(), initial, ours.initial_cost);
          if (args.verbose)
            for (const CeresStage& st : run.stages)
              std::fprintf(stderr, "--- Ceres %s, %s ---\n%s\n", run.name().c_str(), st.name.c_str(),
                           st.summary.FullReport().c_str());
          json stages = json::array();
          for (const CeresStage& st : run.stages) {
            json j = CeresBreakdown(st.summary);
            j["stage"] = st.name;
            j["build_s"] = st.build_s;
            stages.push_back(std::move(j));
          }
          out["ceres_runs"].push_back(
              {{"variant", run.name()},
               {"start", run.start},
               {"shared_layout", run.layout},
               {"shared_blocks", ceres_fit.num_shared_blocks()},
               {"linear_solver", CeresSolverName(s)},
               {"initial_trust_region_radius", run.radius},
               {"seconds", run.seconds},
               {"seconds_all", times},
               {"cpu_s", run.cpu_seconds},
               {"others_cpu", run.others_cpu},
               {"cost", sm.final_cost},
               {"cost_rel_to_ours", (sm.final_cost - ours.final_cost) / ours.final_cost},
               {"iterations", run.iterations()},
               {"termination", ceres::TerminationTypeToString(sm.termination_type)},
               {"capped", run.capped},
               {"fallback", run.fallback},
               {"ratio", run.seconds / ours_seconds},
               {"stages", std::move(stages)},
               {own_peak ? "peak_rss_mb" : "process_peak_rss_mb_so_far", PeakMemory::CurrentMarkMb()}});
          // Progress on stderr as each run ends: a long sweep killed midway keeps what it did.
          std::fprintf(stderr, "fit_vs_ceres: %s: %.3f s (cpu %.3f, others %.0f%%), cost %.9e, %d "
                       "iterations, %s; ours %.3f s, cost %.9e\n",
                       run.name().c_str(), run.seconds, run.cpu_seconds, 100 * run.others_cpu,
                       sm.final_cost, run.iterations(), ceres::TerminationTypeToString(sm.termination_type),
                       ours_seconds, ours.final_cost);
          runs.push_back(std::move(run));
        }
  }
  // The headline: ours against the fastest Ceres variant. Beside it, the cold plain-LM Ceres of
  // earlier sessions (per-object blocks, Ceres's default radius) and the same strategy's best.
  auto best_of = [&](const std::function<bool(const CeresRun&)>& keep) -> const CeresRun* {
    const CeresRun* best = nullptr;
    for (const CeresRun& r : runs)
      if (keep(r) && (!best || r.seconds < best->seconds)) best = &r;
    return best;
  };
  const CeresRun* fastest = best_of([](const CeresRun&) { return true; });
  const CeresRun* cold_default = best_of([&](const CeresRun& r) {
    return r.start == "cold" && r.layout == "split" && r.radius == default_radius;
  });
  const CeresRun* same = best_of([](const CeresRun& r) { return r.start == "same"; });
  auto record = [&](const char* key, const CeresRun* r) {
    if (!r) {
      out[key] = nullptr;
      return;
    }
    out[key] = {{"variant", r->name()},
                {"seconds", r->seconds},
                {"ratio", r->seconds / ours_seconds},
                {"cpu_ratio", r->cpu_seconds / ours_cpu},
                {"cost", r->whole().final_cost},
                {"iterations", r->iterations()}};
  };
  record("ceres_fastest", fastest);
  record("ceres_cold_default", cold_default);
  record("ceres_same_best", same);
  if (fastest) {
    out["ceres_s"] = fastest->seconds;
    out["ceres_variant"] = fastest->name();
    out["ratio"] = fastest->seconds / ours_seconds;
    out["ceres_cost"] = fastest->whole().final_cost;
    out["ceres_iterations"] = fastest->iterations();
    out["ceres_capped"] = fastest->capped;
    out["ceres_cpu_s"] = fastest->cpu_seconds;
    out["ceres_others_cpu"] = fastest->others_cpu;
    out["cpu_ratio"] = fastest->cpu_seconds / ours_cpu;
  } else {
    for (const char* k : {"ceres_s", "ratio", "ceres_cost", "ceres_iterations"}) out[k] = nullptr;
  }
  out["peak_rss_mb"] = memory.ProcessPeakMb();
  out["blas"] = LoadedBlas();
  out["machine"] = {{"nproc", NumProcessors()}, {"cpu", CpuModel()}};

  if (!args.json_out.empty()) {
    std::ofstream file(args.json_out);
    file << out.dump(1) << std::endl;
    if (!file) std::fprintf(stderr, "fit_vs_ceres: cannot write %s\n", args.json_out.c_str());
  }
  if (args.json) {
    std::cout << out.dump() << std::endl;
    return 0;
  }
  std::printf("fit_vs_ceres: %d frames (%s), %lld unknowns (%d shared), %d residuals, %d threads\n",
              nf, data.source.c_str(), static_cast<long long>(nf) * nz + np, np,
              problem.num_residuals(), args.threads);
  std::printf("  held coordinates (frames in gaps) %d, %.3f s\n", held, hold_seconds);
  std::printf("  setup %.2f s, IK %.2f s (CPU %.2f s, others %.0f %%); initial cost %.6e\n", setup_seconds,
              ik_seconds, ik_cpu, 100 * ik_others, ours.initial_cost);
  // cpu: this process's CPU time over the solve; others: the share of the machine's CPU other
  // processes used meanwhile (both for the fastest of the repeats).
  std::printf("  %-30s %9s %9s %15s %5s %7s  %s\n", "solver", "seconds", "cpu s", "final cost",
              "iter", "others", "termination");
  std::printf("  %-30s %9.3f %9.3f %15.9e %5d %6.0f%%  %s\n", "ours (Schur LM)", ours_seconds,
              ours_cpu, ours.final_cost, ours.num_iterations(), 100 * ours_others_cpu,
              solver::ToString(ours.termination));
  if (ours_coarse.used)
    std::printf("    of it before the whole problem's first iteration (coarse stage %d iterations on %d frames, "
                "poses): %.3f s (CPU %.3f s)\n",
                ours_coarse.coarse.num_iterations(), ours_coarse.coarse_frames, ours_coarse.fine_start_seconds,
                ours_coarse.fine_start_cpu_seconds);
  if (args.fit_model) {
    const solver::FitReport& r = fitted.report;
    double worst_trial = 0;
    for (double v : r.per_trial_rms_mm) worst_trial = std::max(worst_trial, v);
    std::printf("  %-30s %9.3f %9s %15.9e %5d %7s  %s (solve %.3f s, IK %.3f s; %d frames "
                "rescued%s; marker RMS %.3f mm, worst trial %.3f mm)\n",
                "FitModel (whole, wall)", r.wall_seconds, "", r.solver.final_cost,
                r.solver.num_iterations(), "", solver::ToString(r.solver.termination),
                r.solve_seconds, r.ik_seconds, r.rescued_frames, r.reposed ? ", reposed" : "",
                r.marker_rms_mm, worst_trial);
  }
  // Each Ceres variant (start/layout/linear solver/initial radius), then Ceres's own breakdown of
  // each of its solves (Solver::Summary).
  for (const CeresRun& r : runs) {
    std::printf("  %-30s %9.3f %9.3f %15.9e %5d %6.0f%%  %s%s%s  (%.1fx ours, cost %+.1e rel)\n",
                ("Ceres " + r.name()).c_str(), r.seconds, r.cpu_seconds, r.whole().final_cost,
                r.iterations(), 100 * r.others_cpu,
                ceres::TerminationTypeToString(r.whole().termination_type), r.capped ? " (time cap)" : "",
                r.fallback ? " (subset not converged: cold)" : "", r.seconds / ours_seconds,
                (r.whole().final_cost - ours.final_cost) / ours.final_cost);
    for (const CeresStage& st : r.stages) {
      const auto& sm = st.summary;
      std::printf("      %-6s %7.3f s: build %.3f, preprocessor %.3f, linear solver %.3f, residuals %.3f, "
                  "Jacobians %.3f, minimizer other %.3f, postprocessor %.3f; %d+%d steps, %d linear "
                  "solves, %d Jacobians, cost %.6e -> %.9e, %s\n",
                  st.name.c_str(), st.build_s + sm.total_time_in_seconds, st.build_s,
                  sm.preprocessor_time_in_seconds, sm.linear_solver_time_in_seconds,
                  sm.residual_evaluation_time_in_seconds, sm.jacobian_evaluation_time_in_seconds,
                  CeresBreakdown(sm)["minimizer_other_s"].get<double>(), sm.postprocessor_time_in_seconds,
                  sm.num_successful_steps, sm.num_unsuccessful_steps, sm.num_linear_solves,
                  sm.num_jacobian_evaluations, sm.initial_cost, sm.final_cost,
                  ceres::LinearSolverTypeToString(sm.linear_solver_type_used));
    }
  }
  auto ratio_line = [&](const char* label, const char* key) {
    if (!out.contains(key) || out[key].is_null()) return;
    const json& j = out[key];
    std::printf("  %-44s %6.2f wall, %6.2f cpu  (%s, %.3f s, cost %.9e)\n", label,
                j["ratio"].get<double>(), j["cpu_ratio"].get<double>(),
                j["variant"].get<std::string>().c_str(), j["seconds"].get<double>(),
                j["cost"].get<double>());
  };
  ratio_line("ratio, fastest Ceres variant / ours:", "ceres_fastest");
  ratio_line("ratio, cold plain-LM Ceres (default radius):", "ceres_cold_default");
  ratio_line("ratio, Ceres with ours's strategy (same):", "ceres_same_best");
  if (out.contains("check"))
    for (const auto& [layout, c] : out["check"].items())
      std::printf("  check at x0 (%s blocks): cost rel diff %.1e, gradient rel diff %.1e\n",
                  layout.c_str(), c["initial_cost_rel"].get<double>(), c["gradient_rel"].get<double>());
  std::printf("  truth: joint centres max / RMS %.3f / %.3f mm at the start, %.3f / %.3f mm after ours; "
              "frames with a marker > 20 mm off %d at the start, %d after ours; coordinates outside "
              "their range %d at the start, %d after ours\n",
              start_accuracy.centre_max_mm, start_accuracy.centre_rms_mm, ours_accuracy.centre_max_mm,
              ours_accuracy.centre_rms_mm, start_accuracy.frames_off, ours_accuracy.frames_off,
              start_accuracy.outside_range, ours_accuracy.outside_range);
  std::printf("  peak RSS: ours %.0f MB, total %.0f MB\n", ours_rss, out["peak_rss_mb"].get<double>());
  std::printf("  BLAS: %s\n  machine: %d x %s\n", out["blas"].get<std::string>().c_str(),
              NumProcessors(), CpuModel().c_str());
  return 0;
}
