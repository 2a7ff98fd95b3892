// schur_vs_cholmod: the global fit's Levenberg–Marquardt solve with the per-frame Schur
// elimination (solver/schur_solver.h) and with CHOLMOD's sparse Cholesky of the whole normal
// matrix (solver/cholmod_solver.h), on the same problem from the same starting point.
//
//   schur_vs_cholmod --frames N [--threads T] [--json]
//                    [--assembly normal|jacobian|aat] [--ordering frames_first|frames_first_given|cholmod]
//                    [--solver both|schur|cholmod] [--blas-threads B]
//
// Problem: the first N frames of the default calibration protocol simulated by
// sim::SimulateSession (seed 1, 0.5 mm noise; duration_scale = ceil(N / 6000) for N > 6000),
// the initial guess from per-trial inverse kinematics with the nominal model (as
// solver::FitModel builds it), one MarkerFitProblem with FitOptions()'s weights and priors, and
// FitOptions().lm for both solves. Peak RSS per solver is measured by resetting the kernel's
// high-water mark (/proc/self/clear_refs) before each; it includes the problem's own memory.
#include <sys/resource.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <nlohmann/json.hpp>
#include <string>

#include "model/kinematics.h"
#include "sim/simulate.h"
#include "solver/cholmod_solver.h"
#include "solver/global_fit.h"
#include "solver/inverse_kinematics.h"
#include "solver/marker_fit_problem.h"
#include "solver/parallel.h"
#include "solver/schur_solver.h"

using namespace mocap;
using Clock = std::chrono::steady_clock;
using Sparse = solver::SparseNormalCholeskyProblem;

namespace {
double Since(Clock::time_point t) { return std::chrono::duration<double>(Clock::now() - t).count(); }

// User + system CPU time of the whole process (all threads), in seconds.
double CpuSeconds() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return usage.ru_utime.tv_sec + usage.ru_stime.tv_sec +
         1e-6 * (usage.ru_utime.tv_usec + usage.ru_stime.tv_usec);
}

double PeakRssMb() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return usage.ru_maxrss / 1024.0;
}

// VmHWM / VmRSS from /proc/self/status, in MB (-1 if unavailable).
double ProcStatusMb(const std::string& field) {
  std::ifstream in("/proc/self/status");
  std::string line;
  while (std::getline(in, line))
    if (line.rfind(field + ":", 0) == 0) return std::atof(line.c_str() + field.size() + 1) / 1024.0;
  return -1;
}

// Resets the peak-RSS mark to the current RSS (Linux >= 4.0). False if not possible.
bool ResetPeakRss() {
  std::ofstream out("/proc/self/clear_refs");
  if (!out) return false;
  out << "5";
  out.flush();
  return static_cast<bool>(out);
}

int Usage(const char* message) {
  std::fprintf(stderr,
               "%s\nusage: schur_vs_cholmod --frames N [--threads T] [--json] "
               "[--assembly normal|jacobian|aat] [--ordering frames_first|frames_first_given|cholmod] "
               "[--solver both|schur|cholmod] [--blas-threads B]\n",
               message);
  return 2;
}

struct Run {
  solver::LmSummary summary;
  double seconds = 0;       // construction (analysis) + solve
  double setup_seconds = 0; // construction
  double cpu_seconds = 0;   // CPU time of all threads over construction + solve
  double peak_rss_mb = -1;
};

void Put(nlohmann::json& j, const std::string& prefix, const Run& run) {
  j[prefix + "_s"] = run.seconds;
  j[prefix + "_setup_s"] = run.setup_seconds;
  j[prefix + "_cpu_s"] = run.cpu_seconds;
  j[prefix + "_cost"] = run.summary.final_cost;
  j[prefix + "_initial_cost"] = run.summary.initial_cost;
  j[prefix + "_iterations"] = run.summary.num_iterations();
  j[prefix + "_linear_solves"] = run.summary.num_linear_solves;
  j[prefix + "_termination"] = solver::ToString(run.summary.termination);
  j[prefix + "_linearize_s"] = run.summary.linearize_seconds;
  j[prefix + "_linear_solver_s"] = run.summary.linear_solver_seconds;
  j[prefix + "_cost_evaluation_s"] = run.summary.cost_evaluation_seconds;
  j[prefix + "_peak_rss_mb"] = run.peak_rss_mb;
}
}  // namespace

int main(int argc, char** argv) {
  int frames = 0, threads = 0;
  bool json = false;
  std::string which = "both";
  Sparse::Options sparse_options;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    auto value = [&]() -> const char* { return i + 1 < argc ? argv[++i] : nullptr; };
    if (arg == "--frames") {
      const char* v = value();
      if (!v || (frames = std::atoi(v)) <= 0) return Usage("--frames: expected a positive integer");
    } else if (arg == "--threads") {
      const char* v = value();
      if (!v || (threads = std::atoi(v)) < 0) return Usage("--threads: expected an integer >= 0");
    } else if (arg == "--blas-threads") {
      const char* v = value();
      if (!v || (sparse_options.blas_threads = std::atoi(v)) < 0)
        return Usage("--blas-threads: expected an integer >= 0");
    } else if (arg == "--json") {
      json = true;
    } else if (arg == "--assembly") {
      const char* v = value();
      if (!v || !Sparse::Parse(v, &sparse_options.assembly)) return Usage("--assembly: unknown value");
    } else if (arg == "--ordering") {
      const char* v = value();
      if (!v || !Sparse::Parse(v, &sparse_options.ordering)) return Usage("--ordering: unknown value");
    } else if (arg == "--solver") {
      const char* v = value();
      if (!v || (std::string(v) != "both" && std::string(v) != "schur" && std::string(v) != "cholmod"))
        return Usage("--solver: expected both, schur or cholmod");
      which = v;
    } else {
      return Usage(("unknown argument " + arg).c_str());
    }
  }
  if (frames <= 0) return Usage("--frames is required");
  threads = solver::ResolveThreads(threads);

  // The session.
  const auto sim_start = Clock::now();
  sim::SimulationOptions sim_options;
  sim_options.seed = 1;
  sim_options.noise_mm = 0.5;
  sim_options.duration_scale = frames > 6000 ? std::ceil(frames / 6000.0) : 1.0;
  sim::SimulatedSession session;
  if (Status s = sim::SimulateSession(sim_options, &session); !s) {
    std::fprintf(stderr, "simulation failed: %s\n", s.message().c_str());
    return 1;
  }
  if (session.total_frames() < frames) {
    std::fprintf(stderr, "the session has only %d frames\n", session.total_frames());
    return 1;
  }
  const Model& model = session.nominal;
  const int nm = model.num_markers(), nz = model.num_coordinates();
  // The first `frames` frames, trial by trial, in model marker order.
  formats::RowMatrix measurements(frames, 3 * nm);
  measurements.setConstant(std::numeric_limits<double>::quiet_NaN());
  std::vector<std::pair<int, int>> pieces;  // (first frame, frames) per (truncated) trial
  for (const sim::SimulatedTrial& trial : session.trials) {
    const int first = pieces.empty() ? 0 : pieces.back().first + pieces.back().second;
    if (first >= frames) break;
    const formats::MarkerTrial& m = trial.markers;
    const int count = std::min(m.num_frames(), frames - first);
    for (int c = 0; c < m.num_markers(); ++c) {
      const int k = model.FindMarker(m.marker_names[c]);
      if (k >= 0) measurements.block(first, 3 * k, count, 3) = m.positions.block(0, 3 * c, count, 3);
    }
    pieces.emplace_back(first, count);
  }
  session.trials.clear();
  const double sim_seconds = Since(sim_start);

  // Initial guess: per-trial IK with the nominal model, trials in parallel (as FitModel does).
  const auto ik_start = Clock::now();
  solver::FitOptions fit_options;
  Eigen::MatrixXd z0(frames, nz);
  std::vector<Status> ik_status(pieces.size());
  solver::ParallelChunks(static_cast<int>(pieces.size()), threads, [&](int, int b, int e) {
    Geometry geometry(model);
    solver::InverseKinematics ik(model, geometry, fit_options.ik);
    for (int t = b; t < e; ++t) {
      Eigen::MatrixXd z;
      ik_status[t] = ik.SolveTrial(measurements.middleRows(pieces[t].first, pieces[t].second), &z);
      if (ik_status[t].ok()) z0.middleRows(pieces[t].first, pieces[t].second) = z;
    }
  });
  for (const Status& s : ik_status)
    if (!s.ok()) {
      std::fprintf(stderr, "IK failed: %s\n", s.message().c_str());
      return 1;
    }
  const double ik_seconds = Since(ik_start);

  solver::MarkerFitProblem problem(model, std::move(measurements), fit_options);
  const int np = problem.shared_dim();
  Eigen::VectorXd x0(static_cast<Eigen::Index>(frames) * nz + np);
  for (int f = 0; f < frames; ++f) x0.segment(static_cast<Eigen::Index>(f) * nz, nz) = z0.row(f).transpose();
  x0.tail(np) = problem.InitialShared();
  z0.resize(0, 0);
  const double baseline_rss_mb = ProcStatusMb("VmRSS");
  const solver::LmOptions& lm = fit_options.lm;

  nlohmann::json out;
  out["frames"] = frames;
  out["unknowns"] = x0.size();
  out["frame_dim"] = nz;
  out["shared_dim"] = np;
  out["residuals"] = problem.num_residuals();
  out["threads"] = threads;
  out["sim_s"] = sim_seconds;
  out["ik_s"] = ik_seconds;
  out["baseline_rss_mb"] = baseline_rss_mb;

  if (which != "cholmod") {
    Run run;
    const bool reset = ResetPeakRss();
    Eigen::VectorXd x = x0;
    const double cpu = CpuSeconds();
    const auto start = Clock::now();
    solver::ArrowSchurProblem schur(&problem, threads);
    run.setup_seconds = Since(start);
    run.summary = solver::Solve(lm, &schur, &x);
    run.seconds = Since(start);
    run.cpu_seconds = CpuSeconds() - cpu;
    run.peak_rss_mb = reset ? ProcStatusMb("VmHWM") : -1;
    Put(out, "schur", run);
    out["schur_caches_frames"] = schur.caches_frames();
  }
  if (which != "schur") {
    Run run;
    const bool reset = ResetPeakRss();
    Eigen::VectorXd x = x0;
    const double cpu = CpuSeconds();
    const auto start = Clock::now();
    Sparse cholmod(&problem, threads, sparse_options);
    run.setup_seconds = Since(start);
    if (!cholmod.ok()) {
      std::fprintf(stderr, "%s\n", cholmod.error().c_str());
      return 1;
    }
    run.summary = solver::Solve(lm, &cholmod, &x);
    run.seconds = Since(start);
    run.cpu_seconds = CpuSeconds() - cpu;
    run.peak_rss_mb = reset ? ProcStatusMb("VmHWM") : -1;
    Put(out, "cholmod", run);
    const Sparse::Statistics& s = cholmod.statistics();
    out["cholmod_assembly"] = Sparse::ToString(sparse_options.assembly);
    out["cholmod_ordering"] = Sparse::ToString(sparse_options.ordering);
    out["cholmod_ordering_used"] = s.ordering_used;
    out["cholmod_blas_threads"] = sparse_options.blas_threads > 0 ? sparse_options.blas_threads : threads;
    out["cholmod_analyses"] = s.analyses;
    out["cholmod_analyse_s"] = s.analyse_seconds;
    out["cholmod_assemble_s"] = s.assemble_seconds;
    out["cholmod_factorize_s"] = s.factorize_seconds;
    out["cholmod_solve_s"] = s.solve_seconds;
    out["cholmod_factorizations"] = s.factorizations;
    out["cholmod_matrix_nnz"] = s.matrix_nonzeros;
    out["cholmod_factor_nnz"] = s.factor_nonzeros;
    out["cholmod_factor_gflop"] = s.factor_flops * 1e-9;
  }
  out["peak_rss_mb"] = PeakRssMb();

  if (json) {
    std::printf("%s\n", out.dump(2).c_str());
    return 0;
  }
  std::printf("%d frames, %lld unknowns (%d x %d + %d shared), %d threads; IK %.2f s\n", frames,
              static_cast<long long>(x0.size()), frames, nz, np, threads, ik_seconds);
  for (const char* name : {"schur", "cholmod"}) {
    const std::string p = name;
    if (!out.contains(p + "_s")) continue;
    std::printf("%-8s %8.2f s (CPU %.2f s)  cost %.9e  %d iterations (%d solves)  linearize %.2f s, linear solver "
                "%.2f s, cost %.2f s  peak RSS %.0f MB\n",
                name, out[p + "_s"].get<double>(), out[p + "_cpu_s"].get<double>(),
                out[p + "_cost"].get<double>(),
                out[p + "_iterations"].get<int>(), out[p + "_linear_solves"].get<int>(),
                out[p + "_linearize_s"].get<double>(), out[p + "_linear_solver_s"].get<double>(),
                out[p + "_cost_evaluation_s"].get<double>(), out[p + "_peak_rss_mb"].get<double>());
  }
  if (out.contains("cholmod_s"))
    std::printf("cholmod: %s/%s (%s), analyse %.2f s, %d factorisations %.2f s, solves %.2f s, "
                "nnz(A or J^T) %lld, nnz(L) %.3g, %.2f GFlop per factorisation\n",
                out["cholmod_assembly"].get<std::string>().c_str(),
                out["cholmod_ordering"].get<std::string>().c_str(),
                out["cholmod_ordering_used"].get<std::string>().c_str(),
                out["cholmod_analyse_s"].get<double>(), out["cholmod_factorizations"].get<int>(),
                out["cholmod_factorize_s"].get<double>(), out["cholmod_solve_s"].get<double>(),
                out["cholmod_matrix_nnz"].get<long long>(), out["cholmod_factor_nnz"].get<double>(),
                out["cholmod_factor_gflop"].get<double>());
  std::printf("peak RSS %.0f MB (baseline %.0f MB)\n", out["peak_rss_mb"].get<double>(), baseline_rss_mb);
  return 0;
}
