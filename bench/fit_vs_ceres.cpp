// fit_vs_ceres: the global body-model fit (solver/global_fit.h) on simulated calibration-protocol
// data, solved by our Levenberg–Marquardt with per-frame Schur elimination (solver/schur_solver.h)
// and by Ceres Solver — the identical residuals from the identical starting point, timed in one
// process run.
//
//   fit_vs_ceres --frames N [--json] [--threads T] [--skip-ceres] [--ceres-solvers schur,normal,dense]
//                [--ceres-residuals marker|frame] [--ceres-shared split|single]
//                [--ceres-max-seconds S] [--repeat R] [--verbose] [--plain]
//                [--coarse-frames N] [--coarse-tolerance T] [--pose-iterations K]
//                [--pose-tolerance T] [--fine-lambda L] [--no-inner]
//                [--missing F] [--noise-mm S] [--seed N] [--frame-prior SIGMA] [--min-diagonal D]
//                [--fit-model] [--rescue-rounds N]
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
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <iostream>
#include <map>
#include <memory>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "formats/marker_data.h"
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
  int threads = 0;  // 0: every core
  bool skip_ceres = false;
  double ceres_max_seconds = 600;
  std::vector<std::string> ceres_solvers = {"schur", "normal", "dense"};
  std::string ceres_residuals = "marker";  // one cost function per (frame, marker) or per frame
  std::string ceres_shared = "split";      // shared p as one block per model object, or one block
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
};

[[noreturn]] void Usage(const std::string& error) {
  std::fprintf(stderr,
               "fit_vs_ceres: %s\n"
               "usage: fit_vs_ceres --frames N [--json] [--threads T] [--skip-ceres]\n"
               "         [--ceres-solvers schur,normal,dense] [--ceres-residuals marker|frame]\n"
               "         [--ceres-shared split|single] [--ceres-max-seconds S] [--repeat R] [--verbose]\n"
               "         [--plain] [--coarse-frames N] [--coarse-tolerance T] [--pose-iterations K]\n"
               "         [--pose-tolerance T] [--fine-lambda L] [--no-inner]\n"
               "         [--missing F] [--noise-mm S] [--seed N] [--frame-prior SIGMA]\n"
               "         [--min-diagonal D] [--fit-model] [--rescue-rounds N]\n",
               error.c_str());
  std::exit(2);
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
    else if (a == "--plain") args.plain = true;
    else if (a == "--coarse-frames") args.coarse.coarse_frames = static_cast<int>(number(1));
    else if (a == "--coarse-tolerance") args.coarse.coarse_function_tolerance = number(0);
    else if (a == "--pose-iterations") args.coarse.pose_iterations = static_cast<int>(number(0));
    else if (a == "--no-inner") args.coarse.inner_iterations = false;
    else if (a == "--pose-tolerance") args.coarse.pose_tolerance = number(0);
    else if (a == "--fine-lambda") args.coarse.fine_initial_lambda = number(1e-300);
    else if (a == "--missing") {
      args.missing = number(0);
      if (!(args.missing < 0.9)) Usage("--missing must be in [0, 0.9)");
    } else if (a == "--noise-mm") args.noise_mm = number(0);
    else if (a == "--fit-model") args.fit_model = true;
    else if (a == "--rescue-rounds") args.rescue_rounds = static_cast<int>(number(0));
    else if (a == "--min-diagonal") args.min_diagonal = number(1e-300);
    else if (a == "--frame-prior") args.frame_prior_sigma = number(1e-6);
    else if (a == "--seed") args.seed = static_cast<std::uint64_t>(number(0));
    else if (a == "--threads") args.threads = static_cast<int>(number(1));
    else if (a == "--skip-ceres") args.skip_ceres = true;
    else if (a == "--ceres-max-seconds") args.ceres_max_seconds = number(1e-3);
    else if (a == "--verbose") args.verbose = true;
    else if (a == "--repeat") args.repeat = static_cast<int>(number(1));
    else if (a == "--ceres-solvers") {
      args.ceres_solvers.clear();
      std::stringstream ss(value());
      for (std::string s; std::getline(ss, s, ',');) {
        if (s != "schur" && s != "normal" && s != "dense") Usage("unknown Ceres solver " + s);
        args.ceres_solvers.push_back(s);
      }
      if (args.ceres_solvers.empty()) Usage("--ceres-solvers is empty");
    } else if (a == "--ceres-residuals") {
      args.ceres_residuals = value();
      if (args.ceres_residuals != "marker" && args.ceres_residuals != "frame")
        Usage("--ceres-residuals is marker or frame");
    } else if (a == "--ceres-shared") {
      args.ceres_shared = value();
      if (args.ceres_shared != "split" && args.ceres_shared != "single")
        Usage("--ceres-shared is split or single");
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
  char buf[160];
  std::snprintf(buf, sizeof(buf),
                "default protocol, seed %llu, noise %g mm, missing %g, duration_scale %g, %zu trials",
                static_cast<unsigned long long>(options.seed), options.noise_mm, options.missing,
                options.duration_scale, d.trial_ranges.size());
  d.source = buf;
  return d;
}

// Per-frame IK with the nominal geometry, trials in parallel: FitModel's starting point.
Eigen::VectorXd InitialGuess(const BenchData& d, const solver::MarkerFitProblem& problem,
                             const solver::FitOptions& options, int threads) {
  const int nz = problem.frame_dim(), np = problem.shared_dim();
  Eigen::VectorXd x(static_cast<Eigen::Index>(problem.num_frames()) * nz + np);
  const int nt = static_cast<int>(d.trial_ranges.size());
  std::vector<Status> status(nt);
  solver::ParallelChunks(nt, threads, [&](int, int b, int e) {
    Geometry geometry(d.model);
    solver::InverseKinematics ik(d.model, geometry, options.ik);
    for (int t = b; t < e; ++t) {
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

// A Ceres parameter block of shared parameters: a contiguous range of the free vector.
struct SharedBlock {
  int begin = 0, size = 0;
};

// The parameter blocks and Jacobian columns of one kind of marker cost function.
struct MarkerLayout {
  std::vector<int> markers;  // model markers; marker i owns residual rows 3i..3i+2
  std::vector<int> blocks;   // shared blocks, Ceres parameter blocks 1.. (block 0 is z_f)
  // Per marker, per MarkerJacobian p column: (parameter block 1.., column), or block -1 if fixed.
  std::vector<std::vector<std::pair<int, int>>> columns;
};

struct CeresContext {
  const solver::MarkerFitProblem* problem = nullptr;
  std::vector<SharedBlock> blocks;
  std::vector<int> block_of_free;  // free index -> shared block
};

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
      : owner(&c), shared(c.problem->InitialShared()), full(c.problem->FullParameters(shared)),
        geometry(c.problem->model()), data(c.problem->model()), z(c.problem->frame_dim()),
        jz(3, c.problem->model().max_chain_coordinates()),
        jp(3, c.problem->model().max_chain_parameters()) {}

  const CeresContext* owner;
  Eigen::VectorXd shared, full;  // free and full parameter vectors behind `geometry`
  Geometry geometry;
  bool geometry_valid = false;
  ModelData data;
  Eigen::VectorXd z;  // the pose behind `data`
  bool fk_valid = false;
  Eigen::Matrix<double, 3, Eigen::Dynamic> jz, jp;
};

Workspace& ThreadWorkspace(const CeresContext& context) {
  thread_local std::unique_ptr<Workspace> ws;
  if (!ws || ws->owner != &context) ws = std::make_unique<Workspace>(context);
  return *ws;
}

// Marker residuals of one frame: all its markers, or one marker, per the layout.
class MarkerCost final : public ceres::CostFunction {
 public:
  MarkerCost(const CeresContext* context, const MarkerLayout* layout, int frame)
      : context_(context), layout_(layout), frame_(frame) {
    set_num_residuals(3 * static_cast<int>(layout->markers.size()));
    mutable_parameter_block_sizes()->push_back(context->problem->frame_dim());
    for (int b : layout->blocks) mutable_parameter_block_sizes()->push_back(context->blocks[b].size);
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
      double* cached = ws->shared.data() + b.begin;
      if (std::memcmp(cached, parameters[1 + i], b.size * sizeof(double)) == 0) continue;
      std::memcpy(cached, parameters[1 + i], b.size * sizeof(double));
      for (int k = b.begin; k < b.begin + b.size; ++k)
        ws->full[problem.free_parameters()[k]] = ws->shared[k];
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
    for (const SharedBlock& b : context->blocks) mutable_parameter_block_sizes()->push_back(b.size);
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
      for (int k = 0; k < blocks[b].size; ++k) delta[blocks[b].begin + k] = parameters[b][k];
    delta -= problem.prior_target();
    Eigen::Map<Eigen::VectorXd> r(residuals, num_residuals());
    r.head(np) = w.cwiseProduct(delta);
    r.tail(g.rows()) = g * delta;
    if (!r.allFinite()) return false;
    if (jacobians == nullptr) return true;
    for (size_t b = 0; b < blocks.size(); ++b) {
      if (!jacobians[b]) continue;
      const int begin = blocks[b].begin, size = blocks[b].size;
      Eigen::Map<Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>> j(
          jacobians[b], num_residuals(), size);
      j.setZero();
      for (int k = 0; k < size; ++k) j(begin + k, k) = w[begin + k];
      j.bottomRows(g.rows()) = g.middleCols(begin, size);
    }
    return true;
  }

 private:
  const CeresContext* context_;
};

// The Ceres problem over its own copy of x (Ceres's parameter blocks point into it).
class CeresFit {
 public:
  CeresFit(const solver::MarkerFitProblem& problem, const Eigen::VectorXd& x0, bool per_marker,
           bool split_shared)
      : x_(x0) {
    const int nf = problem.num_frames(), nz = problem.frame_dim(), np = problem.shared_dim();
    context_.problem = &problem;
    // Shared blocks: one per model object (segment scale, joint centre, axis element, marker
    // position), so a marker's cost touches only its chain's parameters and Ceres's Jacobian and
    // Schur complement stay sparse; or all of p as one block.
    const auto& info = problem.model().parameters();
    for (int k = 0; k < np; ++k) {
      const ParameterInfo& a = info[problem.free_parameters()[k]];
      if (k > 0 && split_shared) {
        const ParameterInfo& prev = info[problem.free_parameters()[k - 1]];
        if (a.group == prev.group && a.object == prev.object && a.element == prev.element) {
          ++context_.blocks.back().size;
          context_.block_of_free.push_back(static_cast<int>(context_.blocks.size()) - 1);
          continue;
        }
      }
      if (k == 0 || split_shared) context_.blocks.push_back({k, 0});
      ++context_.blocks.back().size;
      context_.block_of_free.push_back(static_cast<int>(context_.blocks.size()) - 1);
    }

    // Parameter blocks in x's order, so the Ceres gradient lines up with ours.
    ceres::Problem::Options options;
    options.cost_function_ownership = ceres::TAKE_OWNERSHIP;
    problem_ = std::make_unique<ceres::Problem>(options);
    for (int f = 0; f < nf; ++f) {
      parameter_blocks_.push_back(frame_block(f, nz));
      problem_->AddParameterBlock(parameter_blocks_.back(), nz);
    }
    for (const SharedBlock& b : context_.blocks) {
      parameter_blocks_.push_back(x_.data() + static_cast<Eigen::Index>(nf) * nz + b.begin);
      problem_->AddParameterBlock(parameter_blocks_.back(), b.size);
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
    for (int f = 0; f < nf; ++f) {
      const double* meas = problem.measurements().row(f).data();
      present.clear();
      for (int m = 0; m < nm; ++m)
        if (std::isfinite(meas[3 * m])) present.push_back(m);
      if (present.empty()) continue;
      if (per_marker) {
        for (int m : present) AddMarkerCost(layout_for({m}), f, nz, nf);
      } else {
        AddMarkerCost(layout_for(present), f, nz, nf);
      }
    }
    for (int f = 0; f < nf; ++f) {
      const double *w, *target;
      if (problem.FramePrior(f, &w, &target))
        problem_->AddResidualBlock(new FramePriorCost(w, target, nz), nullptr, frame_block(f, nz));
    }
    std::vector<double*> shared(parameter_blocks_.begin() + nf, parameter_blocks_.end());
    problem_->AddResidualBlock(new PriorCost(&context_), nullptr, shared);

    // Schur solvers eliminate the frames (group 0) and keep p (group 1).
    ordering_ = std::make_shared<ceres::ParameterBlockOrdering>();
    for (int f = 0; f < nf; ++f) ordering_->AddElementToGroup(parameter_blocks_[f], 0);
    for (double* b : shared) ordering_->AddElementToGroup(b, 1);
  }

  int num_shared_blocks() const { return static_cast<int>(context_.blocks.size()); }
  int num_residual_blocks() const { return problem_->NumResidualBlocks(); }
  Eigen::VectorXd& x() { return x_; }

  // Cost and gradient at the current x, gradient in x's order.
  void Evaluate(int threads, double* cost, Eigen::VectorXd* gradient) {
    ceres::Problem::EvaluateOptions options;
    options.parameter_blocks = parameter_blocks_;
    options.num_threads = threads;
    std::vector<double> g;
    problem_->Evaluate(options, cost, nullptr, &g, nullptr);
    *gradient = Eigen::Map<Eigen::VectorXd>(g.data(), static_cast<Eigen::Index>(g.size()));
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
  double* frame_block(int f, int nz) { return x_.data() + static_cast<Eigen::Index>(f) * nz; }

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
        const int block = context_.block_of_free[free];
        cols.emplace_back(slot[block], free - context_.blocks[block].begin);
      }
    }
    return layout;
  }

  void AddMarkerCost(const MarkerLayout* layout, int f, int nz, int nf) {
    std::vector<double*> blocks{frame_block(f, nz)};
    for (int b : layout->blocks)
      blocks.push_back(x_.data() + static_cast<Eigen::Index>(nf) * nz + context_.blocks[b].begin);
    problem_->AddResidualBlock(new MarkerCost(&context_, layout, f), nullptr, blocks);
  }

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

struct CeresRun {
  std::string name;
  double seconds = 0;
  double cpu_seconds = 0;  // of the fastest run
  double others_cpu = 0;  // of the fastest run
  ceres::Solver::Summary summary;
  bool capped = false;
  int iterations() const { return summary.num_successful_steps + summary.num_unsuccessful_steps; }
};

const char* CeresSolverName(const std::string& s) {
  return s == "schur" ? "SPARSE_SCHUR" : s == "normal" ? "SPARSE_NORMAL_CHOLESKY" : "DENSE_SCHUR";
}

std::string CeresJsonKey(const std::string& s) {
  return s == "schur" ? "ceres_schur_s" : s == "normal" ? "ceres_normal_s" : "ceres_dense_schur_s";
}

ceres::LinearSolverType CeresSolverType(const std::string& s) {
  return s == "schur" ? ceres::SPARSE_SCHUR
         : s == "normal" ? ceres::SPARSE_NORMAL_CHOLESKY
                         : ceres::DENSE_SCHUR;
}

double RelativeDifference(double a, double b) {
  return std::abs(a - b) / std::max({std::abs(a), std::abs(b), 1e-300});
}

}  // namespace

int main(int argc, char** argv) {
  const Args args = ParseArgs(argc, argv);
  solver::FitOptions fit_options;  // defaults: all four groups free, FitModel's LM settings
  if (args.min_diagonal > 0) fit_options.lm.min_diagonal = args.min_diagonal;
  if (args.frame_prior_sigma > 0) {
    fit_options.frame_prior_sigma_rad = args.frame_prior_sigma;
    fit_options.frame_prior_sigma_m = args.frame_prior_sigma;
  }

  const auto setup_start = Clock::now();
  const BenchData data = MakeData(args.frames, args);
  solver::MarkerFitProblem problem(data.model, data.measurements, fit_options);
  const int nf = problem.num_frames(), nz = problem.frame_dim(), np = problem.shared_dim();
  const double setup_seconds = Since(setup_start);

  const auto ik_start = Clock::now();
  const Eigen::VectorXd x0 = InitialGuess(data, problem, fit_options, args.threads);
  problem.SetFramePriorTargets(x0);  // as FitModel does: each frame weakly held at its start
  const double ik_seconds = Since(ik_start);

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

  // Ours first, and Ceres's problem built only afterwards, so that ours_peak_rss_mb is ours alone
  // (with the data, the problem and the IK, which Ceres's runs hold too).
  PeakMemory memory;
  solver::LmSummary ours;
  bool ours_cached = false;
  std::vector<double> ours_times;
  double ours_cpu = 0, ours_others_cpu = 0;
  solver::CoarseToFineSummary ours_coarse;
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
      ours_coarse = coarse;
      ours_cpu = timer.cpu();
      ours_others_cpu = timer.others();
    }
  }
  ours_cached = ours_coarse.frames_cached;
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
  if (args.verbose) std::fprintf(stderr, "--- ours ---\n%s\n", ours.FullReport().c_str());
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
                           {"inner_iterations_s", ours.inner_iteration_seconds}};
  out["ours_coarse"] = {{"used", ours_coarse.used},
                        {"fallback", ours_coarse.fallback},
                        {"frames", ours_coarse.coarse_frames},
                        {"iterations", ours_coarse.coarse.num_iterations()},
                        {"seconds", ours_coarse.coarse.total_seconds},
                        {"pose_seconds", ours_coarse.pose_seconds},
                        {"start_cost", ours_coarse.start_cost},
                        {"fine_start_cost", ours_coarse.fine_start_cost},
                        {"total_seconds", ours_coarse.total_seconds}};
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
  out["ours_caches_frames"] = ours_cached;  // U_f, W_f kept between passes (memory budget)
  out["ours_peak_rss_mb"] = ours_rss;

  std::vector<CeresRun> runs;
  if (!args.skip_ceres) {
    const auto build_start = Clock::now();
    CeresFit ceres_fit(problem, x0, args.ceres_residuals == "marker", args.ceres_shared == "split");
    out["ceres_build_s"] = Since(build_start);
    out["ceres_residuals"] = args.ceres_residuals;
    out["ceres_shared"] = args.ceres_shared;
    out["ceres_shared_blocks"] = ceres_fit.num_shared_blocks();
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
      out["check"] = {{"initial_cost_rel", cost_rel}, {"gradient_rel", gradient_rel}};
      if (!(cost_rel <= 1e-9))
        std::fprintf(stderr, "fit_vs_ceres: ERROR: initial costs differ: ours %.12e, Ceres %.12e (rel %.2e)\n",
                     our_cost, ceres_cost, cost_rel);
      if (!(gradient_rel <= 1e-9))
        std::fprintf(stderr, "fit_vs_ceres: ERROR: initial gradients differ (relative %.2e)\n",
                     gradient_rel);
    }

    for (const std::string& s : args.ceres_solvers) {
      const auto options =
          CeresOptions(fit_options.lm, CeresSolverType(s), args.threads, args.ceres_max_seconds);
      CeresRun run;
      run.name = s;
      run.seconds = std::numeric_limits<double>::infinity();
      std::vector<double> times;
      const bool own_peak = memory.Reset();
      for (int rep = 0; rep < args.repeat; ++rep) {
        ceres_fit.x() = x0;  // in place: Ceres's parameter blocks point into it
        const SolveTimer timer;
        ceres::Solver::Summary summary = ceres_fit.Solve(options);
        times.push_back(timer.wall());
        if (times.back() < run.seconds) {
          run.seconds = times.back();
          run.cpu_seconds = timer.cpu();
          run.others_cpu = timer.others();
          run.summary = std::move(summary);
        }
      }
      run.capped = run.summary.termination_type == ceres::NO_CONVERGENCE &&
                   run.summary.message.find("time") != std::string::npos;
      if (RelativeDifference(run.summary.initial_cost, ours.initial_cost) > 1e-9)
        std::fprintf(stderr,
                     "fit_vs_ceres: ERROR: %s initial cost %.12e differs from ours %.12e\n",
                     CeresSolverName(s), run.summary.initial_cost, ours.initial_cost);
      if (args.verbose)
        std::fprintf(stderr, "--- Ceres %s ---\n%s\n", CeresSolverName(s),
                     run.summary.FullReport().c_str());
      const auto& sm = run.summary;
      out[CeresJsonKey(s)] = run.seconds;
      out["ceres_runs"].push_back(
          {{"linear_solver", CeresSolverName(s)},
           {"seconds", run.seconds},
           {"seconds_all", times},
           {"cpu_s", run.cpu_seconds},
           {"others_cpu", run.others_cpu},
           {"cost", sm.final_cost},
           {"iterations", run.iterations()},
           {"successful_steps", sm.num_successful_steps},
           {"termination", ceres::TerminationTypeToString(sm.termination_type)},
           {"capped", run.capped},
           {"preprocessor_s", sm.preprocessor_time_in_seconds},
           {"residual_evaluation_s", sm.residual_evaluation_time_in_seconds},
           {"jacobian_evaluation_s", sm.jacobian_evaluation_time_in_seconds},
           {"linear_solver_s", sm.linear_solver_time_in_seconds},
           {"minimizer_s", sm.minimizer_time_in_seconds},
           {own_peak ? "peak_rss_mb" : "process_peak_rss_mb_so_far", PeakMemory::CurrentMarkMb()}});
      runs.push_back(std::move(run));
    }
  }
  if (!runs.empty()) {
    // Ceres at its best: the fastest of the linear solvers tried.
    const CeresRun& best = *std::min_element(
        runs.begin(), runs.end(), [](const CeresRun& a, const CeresRun& b) { return a.seconds < b.seconds; });
    out["ceres_s"] = best.seconds;
    out["ceres_linear_solver"] = CeresSolverName(best.name);
    out["ratio"] = best.seconds / ours_seconds;
    out["ceres_cost"] = best.summary.final_cost;
    out["ceres_iterations"] = best.iterations();
    out["ceres_capped"] = best.capped;
    out["ceres_cpu_s"] = best.cpu_seconds;
    out["ceres_others_cpu"] = best.others_cpu;
    out["cpu_ratio"] = best.cpu_seconds / ours_cpu;
  } else {
    for (const char* k : {"ceres_s", "ratio", "ceres_cost", "ceres_iterations"}) out[k] = nullptr;
  }
  out["peak_rss_mb"] = memory.ProcessPeakMb();
  out["blas"] = LoadedBlas();
  out["machine"] = {{"nproc", NumProcessors()}, {"cpu", CpuModel()}};

  if (args.json) {
    std::cout << out.dump() << std::endl;
    return 0;
  }
  std::printf("fit_vs_ceres: %d frames (%s), %lld unknowns (%d shared), %d residuals, %d threads\n",
              nf, data.source.c_str(), static_cast<long long>(nf) * nz + np, np,
              problem.num_residuals(), args.threads);
  std::printf("  setup %.2f s, IK %.2f s; initial cost %.6e\n", setup_seconds, ik_seconds,
              ours.initial_cost);
  // cpu: this process's CPU time over the solve; others: the share of the machine's CPU other
  // processes used meanwhile (both for the fastest of the repeats).
  std::printf("  %-30s %9s %9s %15s %5s %7s  %s\n", "solver", "seconds", "cpu s", "final cost",
              "iter", "others", "termination");
  std::printf("  %-30s %9.3f %9.3f %15.9e %5d %6.0f%%  %s\n", "ours (Schur LM)", ours_seconds,
              ours_cpu, ours.final_cost, ours.num_iterations(), 100 * ours_others_cpu,
              solver::ToString(ours.termination));
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
  for (const CeresRun& r : runs) {
    const std::string name = std::string("Ceres ") + CeresSolverName(r.name);
    std::printf("  %-30s %9.3f %9.3f %15.9e %5d %6.0f%%  %s%s\n", name.c_str(), r.seconds,
                r.cpu_seconds, r.summary.final_cost, r.iterations(), 100 * r.others_cpu,
                ceres::TerminationTypeToString(r.summary.termination_type),
                r.capped ? " (time cap)" : "");
  }
  if (!runs.empty())
    std::printf("  ratio (best Ceres / ours): wall %.2f, cpu %.2f\n", out["ratio"].get<double>(),
                out["cpu_ratio"].get<double>());
  if (out.contains("check"))
    std::printf("  check at x0: cost rel diff %.1e, gradient rel diff %.1e\n",
                out["check"]["initial_cost_rel"].get<double>(),
                out["check"]["gradient_rel"].get<double>());
  std::printf("  peak RSS: ours %.0f MB, total %.0f MB\n", ours_rss, out["peak_rss_mb"].get<double>());
  std::printf("  BLAS: %s\n  machine: %d x %s\n", out["blas"].get<std::string>().c_str(),
              NumProcessors(), CpuModel().c_str());
  return 0;
}
