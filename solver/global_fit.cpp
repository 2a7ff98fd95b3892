#include "solver/global_fit.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <cstdio>
#include <map>
#include <set>
#include <sstream>

#include "formats/mot.h"
#include "solver/marker_fit_problem.h"
#include "solver/parallel.h"
#include "solver/schur_solver.h"

namespace mocap::solver {
namespace {
using Clock = std::chrono::steady_clock;
double Since(Clock::time_point t) { return std::chrono::duration<double>(Clock::now() - t).count(); }

// Rows of `z` that are all NaN (frames without a given pose) solved by IK, each warm-started from
// the previous frame's pose (the first given pose, backwards, for leading rows); a warm start
// worse than restart_rms_m re-initialises. A frame with fewer than 3 markers keeps the
// neighbour's pose. FitModel has checked that some row is given.
void FillMissingPoses(const Eigen::Ref<const formats::RowMatrix>& measured, const IkOptions& options,
                      InverseKinematics* ik, Eigen::MatrixXd* z) {
  const int nf = static_cast<int>(z->rows());
  const int nm = static_cast<int>(measured.cols() / 3);
  auto missing = [&](int f) { return z->row(f).array().isNaN().all(); };
  int first = 0;
  while (first < nf && missing(first)) ++first;
  if (first == nf) return;
  Eigen::Matrix3Xd frame(3, nm);
  auto solve = [&](int f, const Eigen::VectorXd& from) {
    frame = Eigen::Map<const Eigen::Matrix3Xd>(measured.row(f).data(), 3, nm);
    int present = 0;
    for (int m = 0; m < nm; ++m) present += std::isfinite(frame(0, m)) ? 1 : 0;
    Eigen::VectorXd pose = from;
    if (present >= 3) {
      const IkFrameResult r = ik->Solve(frame, &pose);
      if (r.rms_m > options.restart_rms_m) {
        Eigen::VectorXd fresh;
        if (ik->Initialise(frame, &fresh).rms_m < r.rms_m) pose = fresh;
      }
    }
    z->row(f) = pose.transpose();
  };
  for (int f = first - 1; f >= 0; --f) solve(f, z->row(f + 1).transpose());
  for (int f = first + 1; f < nf; ++f)
    if (missing(f)) solve(f, z->row(f - 1).transpose());
}

// FitOptions::rescue_ratio: frames of trials [first[t], first[t+1]) whose cost per marker sample
// is far above the median get their pose re-solved by IK (geometry `model`) from the nearest
// well-fitted frames of the same trial; the lowest of the frame's own cost (frame prior included)
// wins. `frame_costs` are the solver's at x. Returns how many poses were replaced.
int RescueFrames(const MarkerFitProblem& problem, const Model& model, const std::vector<int>& first,
                 const std::vector<double>& frame_costs, double ratio, const IkOptions& ik_options,
                 Eigen::VectorXd* x) {
  const int nf = problem.num_frames(), nz = problem.frame_dim(), nm = model.num_markers();
  if (static_cast<int>(frame_costs.size()) != nf) return 0;
  std::vector<double> per_sample(nf, 0.0);
  std::vector<double> sorted;
  for (int f = 0; f < nf; ++f) {
    int n = 0;
    for (int m = 0; m < nm; ++m) n += std::isfinite(problem.measurements()(f, 3 * m)) ? 1 : 0;
    if (n == 0) continue;
    per_sample[f] = frame_costs[f] / n;
    sorted.push_back(per_sample[f]);
  }
  if (sorted.empty()) return 0;
  std::nth_element(sorted.begin(), sorted.begin() + sorted.size() / 2, sorted.end());
  const double limit = ratio * sorted[sorted.size() / 2];
  std::vector<char> suspect(nf, 0);
  int suspects = 0;
  for (int f = 0; f < nf; ++f) suspects += suspect[f] = per_sample[f] > limit;
  if (suspects == 0) return 0;
  const Geometry geometry(model);
  InverseKinematics ik(model, geometry, ik_options);
  auto evaluator = problem.NewEvaluator();
  int replaced = 0;
  for (size_t t = 0; t + 1 < first.size(); ++t) {
    for (int f = first[t]; f < first[t + 1]; ++f) {
      if (!suspect[f]) continue;
      int before = f - 1, after = f + 1;
      while (before >= first[t] && suspect[before]) --before;
      while (after < first[t + 1] && suspect[after]) ++after;
      const Eigen::Map<const Eigen::Matrix3Xd> measured(problem.measurements().row(f).data(), 3, nm);
      double best = 0;
      Eigen::VectorXd best_z = x->segment(static_cast<Eigen::Index>(f) * nz, nz);
      if (!FrameSquaredNorm(problem, evaluator.get(), f, best_z.data(), &best)) continue;
      bool improved = false;
      for (int from : {before, after}) {
        if (from < first[t] || from >= first[t + 1]) continue;
        Eigen::VectorXd z = x->segment(static_cast<Eigen::Index>(from) * nz, nz);
        ik.Solve(measured, &z);
        double cost = 0;
        if (FrameSquaredNorm(problem, evaluator.get(), f, z.data(), &cost) && cost < best) {
          best = cost;
          best_z = z;
          improved = true;
        }
      }
      if (!improved) continue;
      x->segment(static_cast<Eigen::Index>(f) * nz, nz) = best_z;
      ++replaced;
    }
  }
  return replaced;
}
}  // namespace

Status InitialCoordinatesFromTable(const Model& model, const formats::CoordinateTable& table,
                                   int num_frames, const std::string& source, Eigen::MatrixXd* z) {
  if (table.num_frames() != num_frames)
    return Status::Error(source + ": has " + std::to_string(table.num_frames()) +
                         " frames, its trial has " + std::to_string(num_frames));
  return formats::PosesFromTable(model, table, source, z);
}

bool FitOptions::IsValid(std::string* error) const {
  std::string why;
  auto fail = [&](const std::string& what) {
    if (error) *error = what;
    return false;
  };
  if (!(marker_sigma_m > 0)) return fail("marker_sigma_m must be > 0");
  if (!(prior_sigma_scale > 0) || !(prior_sigma_position_m > 0) || !(prior_sigma_axis_rad > 0))
    return fail("prior sigmas must be > 0");
  if (!(undetermined_ratio > 0)) return fail("undetermined_ratio must be > 0");
  if (!(gauge_sigma_m > 0)) return fail("gauge_sigma_m must be > 0");
  if (repose_after_iterations < 1) return fail("repose_after_iterations must be >= 1");
  if (!(rescue_ratio > 1)) return fail("rescue_ratio must be > 1");
  if (!(outlier_marker_ratio > 1) || !(outlier_marker_min_mm >= 0))
    return fail("outlier_marker_ratio must be > 1 and outlier_marker_min_mm >= 0");
  if (rescue_rounds < 0) return fail("rescue_rounds must be >= 0");
  if (marker_sigma_rounds < 0) return fail("marker_sigma_rounds must be >= 0");
  if (!(marker_sigma_tolerance > 0)) return fail("marker_sigma_tolerance must be > 0");
  if (!(robust_scale > 0) || !std::isfinite(robust_scale))
    return fail("robust_scale must be a finite number > 0 (got " + std::to_string(robust_scale) + ")");
  if (robust_rounds < 0) return fail("robust_rounds must be >= 0");
  if (!(robust_tolerance > 0)) return fail("robust_tolerance must be > 0");
  if (rescue_iterations < 1) return fail("rescue_iterations must be >= 1");
  if (staged_iterations < 1) return fail("staged_iterations must be >= 1");
  if (stage_frames < 0) return fail("stage_frames must be >= 0 (0: every frame)");
  if (!(reweigh_markers_stage_ratio >= 1.0)) return fail("reweigh_markers_stage_ratio must be >= 1");
  if (!(markers_measure_tolerance > 0 && markers_measure_tolerance < 1))
    return fail("markers_measure_tolerance must be in (0, 1)");
  if (!(static_trial_motion_mm >= 0)) return fail("static_trial_motion_mm must be >= 0");
  if (!(far_moved_marker_sigmas > 0)) return fail("far_moved_marker_sigmas must be > 0");
  if (!(stacked_marker_tolerance_m >= 0)) return fail("stacked_marker_tolerance_m must be >= 0");
  if (!(stage_function_tolerance > 0 && stage_function_tolerance < 1))
    return fail("stage_function_tolerance must be in (0, 1)");
  if (!coarse.IsValid(&why)) return fail("coarse: " + why);
  if (!unobserved_hold.IsValid(&why)) return fail("unobserved_hold: " + why);
  if (!attach.IsValid(&why)) return fail("attach: " + why);
  if (!diagnosis.IsValid(&why)) return fail("diagnosis: " + why);
  if (!(frame_prior_sigma_rad > 0) || !(frame_prior_sigma_m > 0))
    return fail("frame prior sigmas must be > 0");
  if (!(prior_sigma_fixed_marker_m > 0)) return fail("prior_sigma_fixed_marker_m must be > 0");
  if (!(held_centre_sigma_m >= 0) || !(held_axis_sigma_rad >= 0))
    return fail("held_centre_sigma_m and held_axis_sigma_rad must be >= 0 (0: the holds count as exact)");
  if (!(coordinate_limit_sigma_rad >= 0) || !(coordinate_limit_sigma_m >= 0))
    return fail("coordinate_limit_sigma_rad and coordinate_limit_sigma_m must be >= 0 (0: ranges not enforced)");
  if (num_threads < 0) return fail("num_threads must be >= 0");
  if (!lm.IsValid(&why)) return fail("lm: " + why);
  if (!ik.IsValid(&why)) return fail("ik: " + why);
  return true;
}

Status FitOptions::SetGroups(const std::string& list) {
  bool groups[4] = {false, false, false, false};
  std::stringstream ss(list);
  std::string item;
  while (std::getline(ss, item, ',')) {
    if (item == "all") {
      for (bool& g : groups) g = true;
    } else if (item == "none" || item.empty()) {
    } else if (item == "scales") groups[0] = true;
    else if (item == "centres" || item == "centers") groups[1] = true;
    else if (item == "axes") groups[2] = true;
    else if (item == "markers") groups[3] = true;
    else
      return Status::Error("unknown parameter group '" + item +
                           "' (expected scales, centres, axes, markers, all or none)");
  }
  fit_scales = groups[0];
  fit_centres = groups[1];
  fit_axes = groups[2];
  fit_markers = groups[3];
  return Status::Ok();
}

namespace {
// FitOptions::robust_loss: each sample's weight rho'(s) at x (frames x markers, 1 where missing),
// the unit being the median marker's residual RMS per coordinate at x (*sigma_m, never below a
// micrometre: noise-free data would make it zero). *largest_change against the problem's current
// weights. False when x is no body.
bool RobustSampleWeights(MarkerFitProblem* problem, const Eigen::VectorXd& x, const FitOptions& options,
                         int threads, Eigen::MatrixXd* weights, double* sigma_m, double* largest_change) {
  Eigen::MatrixXd squared;
  if (!problem->SampleErrors(x, threads, &squared)) return false;
  const int nf = static_cast<int>(squared.rows()), nm = static_cast<int>(squared.cols());
  std::vector<double> rms;
  for (int m = 0; m < nm; ++m) {
    double sum = 0;
    int n = 0;
    for (int f = 0; f < nf; ++f)
      if (std::isfinite(squared(f, m))) sum += squared(f, m), ++n;
    if (n > 0) rms.push_back(std::sqrt(sum / (3.0 * n)));
  }
  if (rms.empty()) return false;
  std::nth_element(rms.begin(), rms.begin() + rms.size() / 2, rms.end());
  *sigma_m = std::max(1e-6, rms[rms.size() / 2]);
  const double inv_var = 1.0 / (*sigma_m * *sigma_m);
  weights->setOnes(nf, nm);
  *largest_change = 0;
  for (int f = 0; f < nf; ++f)
    for (int m = 0; m < nm; ++m) {
      if (!std::isfinite(squared(f, m))) continue;
      const double w = RobustWeight(options.robust_loss, squared(f, m) * inv_var, options.robust_scale);
      (*weights)(f, m) = w;
      *largest_change = std::max(*largest_change, std::abs(w - problem->sample_weight(f, m)));
    }
  return true;
}
}  // namespace

double MedianMarkerMotionMm(const formats::MarkerTrial& trial) {
  std::vector<double> motion;
  for (int c = 0; c < trial.num_markers(); ++c) {
    const auto xyz = trial.positions.middleCols(3 * c, 3);
    Eigen::Vector3d sum = Eigen::Vector3d::Zero();
    int n = 0;
    for (int f = 0; f < xyz.rows(); ++f)
      if (xyz.row(f).allFinite()) sum += xyz.row(f).transpose(), ++n;
    if (n < 2) continue;
    const Eigen::Vector3d mean = sum / n;
    double sq = 0;
    for (int f = 0; f < xyz.rows(); ++f)
      if (xyz.row(f).allFinite()) sq += (xyz.row(f).transpose() - mean).squaredNorm();
    motion.push_back(1000.0 * std::sqrt(sq / n));
  }
  if (motion.empty()) return std::numeric_limits<double>::quiet_NaN();
  std::nth_element(motion.begin(), motion.begin() + motion.size() / 2, motion.end());
  return motion[motion.size() / 2];
}

int FitReport::IterationsOnEveryFrame() const {
  if (stages.empty()) return solver.num_iterations();
  int n = 0;
  for (const FitStageSummary& st : stages) n += st.frames >= frames ? st.iterations : 0;
  return n;
}

int FitReport::IterationsSearchingBetterMinimum() const {
  int n = 0;
  for (const FitStageSummary& st : stages) n += st.better_minimum_search ? st.iterations : 0;
  return n;
}

std::string FitReport::BriefReport() const {
  const std::string coarse_note =
      coarse.used       ? " (after " + std::to_string(coarse.coarse.num_iterations()) + " on " +
                              std::to_string(coarse.coarse_frames) + " frames)"
      : coarse.fallback ? " (from the start: " + std::to_string(coarse.coarse.num_iterations()) +
                              " on " + std::to_string(coarse.coarse_frames) + " frames did not converge)"
                        : "";
  std::string outliers;
  for (size_t k = 0; k < outlier_markers.size() && k < 5; ++k) {
    char one[96];
    std::snprintf(one, sizeof(one), "%s%s %.1f mm", k == 0 ? "; outlying markers: " : ", ",
                  outlier_markers[k].first.c_str(), outlier_markers[k].second);
    outliers += one;
  }
  if (outlier_markers.size() > 5) outliers += ", ...";
  std::string robust;
  if (robust_loss != RobustLoss::kNone) {
    const RobustMarker* most = nullptr;
    for (const RobustMarker& m : robust_markers)
      if (m.downweighted > 0 && (!most || m.downweighted > most->downweighted)) most = &m;
    char one[160];
    std::snprintf(one, sizeof(one), "; %s loss: %d samples down-weighted in %d rounds%s%s%s", ToString(robust_loss),
                  robust_downweighted, robust_rounds, most ? " (most: " : "", most ? most->name.c_str() : "",
                  most ? (" " + std::to_string(most->downweighted) + ")").c_str() : "");
    robust = one;
  }
  std::string staging;
  if (IterationsOnEveryFrame() != solver.num_iterations())
    staging = ", " + std::to_string(IterationsOnEveryFrame()) + " of them on every frame";
  if (stages.size() > 1) {
    staging += " (";
    for (size_t k = 0; k < stages.size(); ++k)
      staging += (k ? " + " : "") + std::to_string(stages[k].iterations) + " " + stages[k].name +
                 (stages[k].frames > 0 && stages[k].frames < frames
                      ? " on " + std::to_string(stages[k].frames) + " frames"
                      : "");
    staging += ")";
  }
  char buf[1024];
  std::snprintf(buf, sizeof(buf),
                "fit: %d trials, %d frames, %d markers, %d unknowns; marker RMS %.3f -> %.3f mm; "
                "%d iterations%s%s, %s%s; %zu undetermined%s%s; %.2f s (IK %.2f s, solve %.2f s)",
                trials, frames, markers, unknowns, initial_marker_rms_mm, marker_rms_mm,
                solver.num_iterations(), staging.c_str(), coarse_note.c_str(), ToString(solver.termination),
                rescued_frames > 0 ? (", " + std::to_string(rescued_frames) +
                                      " frame poses rescued").c_str()
                                   : "",
                undetermined.size(), outliers.c_str(), robust.c_str(), wall_seconds, ik_seconds, solve_seconds);
  return buf;
}

namespace {
// One solve of the whole problem for the groups `options` frees (FitModel's stage).
// `measure_correlation`: the residuals' autocorrelation time (FitReport) is measured; it costs a
// pass over the residuals per lag, and after a stage with the model's markers it would measure
// their misplacement, not the data's error.
Status FitStage(const Model& initial, const std::vector<FitTrial>& trials, const FitOptions& options,
                bool measure_correlation, FitResult* result) {
  const auto start = Clock::now();
  const int nm = initial.num_markers(), nz = initial.num_coordinates();
  FitReport report;
  report.trials = static_cast<int>(trials.size());

  // Map each trial's markers onto the model's by name.
  std::set<std::string> unmatched;
  std::vector<std::vector<int>> column_of(trials.size(), std::vector<int>(nm, -1));
  int total_frames = 0;
  for (size_t t = 0; t < trials.size(); ++t) {
    const formats::MarkerTrial& trial = trials[t].markers;
    const std::string name = trial.name.empty() ? "trial " + std::to_string(t + 1) : "trial '" + trial.name + "'";
    if (trial.num_frames() == 0) return Status::Error(name + ": has no frames");
    if (trial.positions.cols() != 3 * trial.num_markers())
      return Status::Error(name + ": positions do not match the marker names");
    int matched = 0;
    for (int c = 0; c < trial.num_markers(); ++c) {
      const int m = initial.FindMarker(trial.marker_names[c]);
      if (m < 0) {
        unmatched.insert(trial.marker_names[c]);
        continue;
      }
      column_of[t][m] = c;
      ++matched;
    }
    if (matched == 0)
      return Status::Error(name + ": none of its " + std::to_string(trial.num_markers()) +
                           " markers is in the model");
    for (int f = 0; f < trial.num_frames(); ++f)
      for (int c = 0; c < trial.positions.cols(); ++c)
        if (std::isinf(trial.positions(f, c)))
          return Status::Error(name + ": frame " + std::to_string(f + 1) + ", marker '" +
                               trial.marker_names[c / 3] + "' has an infinite coordinate");
    const Eigen::MatrixXd& z0 = trials[t].initial_coordinates;
    if (z0.size() > 0 && (z0.rows() != trial.num_frames() || z0.cols() != nz))
      return Status::Error(name + ": starting coordinates are " + std::to_string(z0.rows()) + "x" +
                           std::to_string(z0.cols()) + ", expected " +
                           std::to_string(trial.num_frames()) + "x" + std::to_string(nz));
    if (z0.size() > 0) {
      int given = 0;
      for (int f = 0; f < z0.rows(); ++f) {
        const bool nan_row = z0.row(f).array().isNaN().all();
        if (!nan_row && !z0.row(f).allFinite())
          return Status::Error(name + ": starting coordinates of frame " + std::to_string(f + 1) +
                               " are partly missing or infinite (a frame's pose is all or nothing)");
        given += nan_row ? 0 : 1;
      }
      if (given == 0) return Status::Error(name + ": the starting coordinates have no frame with a pose");
    }
    total_frames += trial.num_frames();
  }
  report.unmatched_trial_markers.assign(unmatched.begin(), unmatched.end());

  // One measurement matrix over all frames, model marker order.
  formats::RowMatrix measurements(total_frames, 3 * nm);
  measurements.setConstant(std::numeric_limits<double>::quiet_NaN());
  std::vector<int> first_frame(trials.size() + 1, 0);
  for (size_t t = 0; t < trials.size(); ++t) {
    const formats::MarkerTrial& trial = trials[t].markers;
    first_frame[t + 1] = first_frame[t] + trial.num_frames();
    for (int m = 0; m < nm; ++m) {
      const int c = column_of[t][m];
      if (c < 0) continue;
      measurements.block(first_frame[t], 3 * m, trial.num_frames(), 3) =
          trial.positions.middleCols(3 * c, 3);
    }
  }
  // A sample is all three coordinates or nothing.
  for (int f = 0; f < total_frames; ++f)
    for (int m = 0; m < nm; ++m)
      if (!measurements.row(f).segment<3>(3 * m).allFinite())
        measurements.row(f).segment<3>(3 * m).setConstant(std::numeric_limits<double>::quiet_NaN());

  MarkerFitProblem problem(initial, std::move(measurements), options);
  for (int m = 0; m < nm; ++m) {
    if (problem.observed(m)) ++report.markers;
    else report.unobserved_model_markers.push_back(initial.markers()[m].name);
  }
  report.frames = total_frames;
  report.marker_samples = problem.num_samples();
  const int np = problem.shared_dim();
  report.unknowns = total_frames * nz + np;
  report.residuals = problem.num_residuals();

  // Starting point: given poses, else per-frame IK with the initial geometry (trials in parallel).
  const auto ik_start = Clock::now();
  Eigen::VectorXd x(static_cast<Eigen::Index>(total_frames) * nz + np);
  const int threads = ResolveThreads(options.num_threads);
  // Poses of every frame by IK for the geometry `p` (trials in parallel); given poses are kept
  // on the first call.
  auto solve_poses = [&](const Eigen::VectorXd& p, bool keep_given) -> Status {
    Model model;
    MOCAP_RETURN_IF_ERROR(initial.WithParameters(p, &model));
    std::vector<Status> status(trials.size());
    const std::vector<int> order = LongestFirst(static_cast<int>(trials.size()),
                                                [&](int t) { return trials[t].markers.num_frames(); });
    ParallelQueue(order, threads, [&](int, auto&& next) {
      Geometry geometry(model);
      InverseKinematics ik(model, geometry, options.ik);
      for (int t = next(); t >= 0; t = next()) {
        Eigen::MatrixXd z;
        if (keep_given && trials[t].initial_coordinates.size() > 0) {
          z = trials[t].initial_coordinates;
          FillMissingPoses(problem.measurements().middleRows(first_frame[t], trials[t].markers.num_frames()),
                           options.ik, &ik, &z);
        } else {
          status[t] = ik.SolveTrial(
              problem.measurements().middleRows(first_frame[t], trials[t].markers.num_frames()), &z);
          if (!status[t].ok()) continue;
        }
        for (int f = 0; f < z.rows(); ++f)
          x.segment(static_cast<Eigen::Index>(first_frame[t] + f) * nz, nz) = z.row(f).transpose();
      }
    });
    for (size_t t = 0; t < trials.size(); ++t)
      if (!status[t].ok()) return Status::Error("trial '" + trials[t].markers.name + "': " + status[t].message());
    return Status::Ok();
  };
  if (Status s = solve_poses(initial.InitialParameters(), true); !s) return s;
  x.tail(np) = problem.InitialShared();
  problem.SetFramePriorTargets(x);
  // What a frame in a gap leaves unobserved is held at its start (coarse_to_fine.h).
  auto hold_unobserved = [&] {
    formats::RowMatrix weights;
    UnobservedCoordinateWeights(&problem, x, problem.uniform_frame_prior_weight(), options.unobserved_hold,
                                threads, &weights);
    problem.SetFramePriorWeights(std::move(weights));
  };
  hold_unobserved();
  report.ik_seconds = Since(ik_start);

  Eigen::VectorXd sum_sq;
  Eigen::VectorXi counts;
  if (!problem.MarkerErrors(x, threads, &sum_sq, &counts))
    return Status::Error("fit: the initial model's parameters are no body (a scale <= 0?)");
  report.initial_marker_rms_mm = 1000.0 * std::sqrt(sum_sq.sum() / std::max(1, counts.sum()));

  const auto solve_start = Clock::now();
  ArrowSchurProblem schur(&problem, threads);
  LmOptions lm = options.lm;  // with the marker RMS per iteration (the report's convergence plot)
  lm.data_rms = [&problem, threads](const Eigen::VectorXd& at) {
    Eigen::VectorXd sum;
    Eigen::VectorXi count;
    if (!problem.MarkerErrors(at, threads, &sum, &count)) return std::numeric_limits<double>::quiet_NaN();
    return 1000.0 * std::sqrt(sum.sum() / std::max(1, count.sum()));
  };
  LmOptions first = lm;
  first.max_iterations = std::min(options.lm.max_iterations, options.repose_after_iterations);
  report.solver = SolveCoarseToFine(&problem, &schur, first, options.coarse, threads, &x, &report.coarse);
  // The solve continued from x for at most `max_iterations` more, appended to the report's.
  auto continue_solve = [&](int max_iterations) {
    LmOptions rest = lm;
    rest.max_iterations = max_iterations;
    LmSummary more = Solve(rest, &schur, &x);
    more.initial_cost = report.solver.initial_cost;
    more.iterations.insert(more.iterations.begin(), report.solver.iterations.begin(),
                           report.solver.iterations.end());
    more.num_linear_solves += report.solver.num_linear_solves;
    more.total_seconds += report.solver.total_seconds;
    report.solver = more;
  };
  int iterations_left = options.lm.max_iterations - first.max_iterations;
  int rescue_rounds = 0;
  // One rescue pass (FitOptions::rescue_ratio) at x; *replaced poses.
  auto rescue = [&](int* replaced) -> Status {
    *replaced = 0;
    if (rescue_rounds >= options.rescue_rounds || !report.solver.IsSolutionUsable()) return Status::Ok();
    ++rescue_rounds;
    double cost = 0;
    if (!schur.Cost(x, &cost)) return Status::Ok();  // also sets the problem's geometry to x's
    Model current;
    MOCAP_RETURN_IF_ERROR(initial.WithParameters(problem.FullParameters(x.tail(np)), &current));
    const auto rescue_start = Clock::now();
    *replaced = RescueFrames(problem, current, first_frame, schur.frame_costs(),
                             options.rescue_ratio, options.ik, &x);
    report.ik_seconds += Since(rescue_start);
    report.rescued_frames += *replaced;
    return Status::Ok();
  };
  // Wrong branches first: they are what makes a solve with gaps crawl.
  for (int replaced = 1; replaced > 0 && iterations_left > 0;) {
    MOCAP_RETURN_IF_ERROR(rescue(&replaced));
    if (replaced == 0) break;
    const int budget = std::min(iterations_left, options.rescue_iterations);
    continue_solve(budget);
    iterations_left -= budget;
  }
  if (report.solver.termination == TerminationType::kNoConvergence && iterations_left > 0) {
    // Still crawling: the poses found with the initial geometry hold the fit back (frames in
    // gaps sit where the first IK put them). Re-solve every pose with the geometry reached so
    // far and continue from there.
    const auto repose_start = Clock::now();
    if (Status s = solve_poses(problem.FullParameters(x.tail(np)), false); !s) return s;
    problem.SetFramePriorTargets(x);
    hold_unobserved();
    report.ik_seconds += Since(repose_start);
    report.reposed = true;
    continue_solve(iterations_left);
    iterations_left = 0;
    int replaced = 0;
    MOCAP_RETURN_IF_ERROR(rescue(&replaced));
    if (replaced > 0) continue_solve(options.rescue_iterations);
  }
  // FitOptions::robust_loss: iteratively reweighted least squares (solver/robust_loss.h), from
  // the least-squares solution reached so far.
  double robust_sigma_m = 0;
  while (options.robust_loss != RobustLoss::kNone && report.robust_rounds < options.robust_rounds &&
         report.solver.IsSolutionUsable()) {
    Eigen::MatrixXd weights;
    double change = 0;
    if (!RobustSampleWeights(&problem, x, options, threads, &weights, &robust_sigma_m, &change)) break;
    problem.SetSampleWeights(std::move(weights));
    if (change <= options.robust_tolerance) break;
    ++report.robust_rounds;
    continue_solve(options.lm.max_iterations);
  }
  // FitOptions::marker_sigma_rounds: each marker weighted by its own residual spread, measured
  // at a converged solve only (the residuals of a solve that stopped short are not the markers').
  while (report.marker_sigma_rounds < options.marker_sigma_rounds && report.converged() &&
         problem.MarkerErrors(x, threads, &sum_sq, &counts)) {
    double largest_change = 0;
    std::vector<double> sigma(nm);
    for (int m = 0; m < nm; ++m) {
      sigma[m] = problem.marker_sigma(m);
      if (counts[m] == 0) continue;
      sigma[m] = std::max(options.marker_sigma_m, std::sqrt(sum_sq[m] / (3.0 * counts[m])));
      largest_change = std::max(largest_change, std::abs(sigma[m] / problem.marker_sigma(m) - 1));
    }
    if (largest_change <= options.marker_sigma_tolerance) break;
    for (int m = 0; m < nm; ++m) problem.SetMarkerSigma(m, sigma[m]);
    ++report.marker_sigma_rounds;
    continue_solve(options.lm.max_iterations);
  }
  for (int m = 0; m < nm; ++m)
    if (problem.observed(m))
      report.marker_sigma_mm.emplace_back(initial.markers()[m].name, 1000.0 * problem.marker_sigma(m));
  if (options.robust_loss != RobustLoss::kNone) {
    report.robust_loss = options.robust_loss;
    report.robust_scale = options.robust_scale;
    report.robust_sigma_mm = 1000.0 * robust_sigma_m;
    // Down-weighted: a weight below the loss's own at the scale (Huber 1, Cauchy 1/2).
    const double at_scale = RobustWeight(options.robust_loss, options.robust_scale * options.robust_scale,
                                         options.robust_scale);
    for (int m = 0; m < nm; ++m) {
      if (!problem.observed(m)) continue;
      FitReport::RobustMarker rm;
      rm.name = initial.markers()[m].name;
      double sum = 0;
      for (int f = 0; f < total_frames; ++f) {
        if (!std::isfinite(problem.measurements()(f, 3 * m))) continue;
        const double w = problem.sample_weight(f, m);
        ++rm.samples;
        sum += w;
        rm.downweighted += w < at_scale * (1.0 - 1e-9) ? 1 : 0;
      }
      rm.mean_weight = rm.samples > 0 ? sum / rm.samples : 1.0;
      report.robust_downweighted += rm.downweighted;
      report.robust_markers.push_back(rm);
    }
  }
  report.solve_seconds = Since(solve_start);
  if (!report.solver.IsSolutionUsable())
    return Status::Error("fit: the solver failed: " + report.solver.message);

  if (!problem.MarkerErrors(x, threads, &sum_sq, &counts))
    return Status::Error("fit: the solver ended at parameters that are no body");
  report.marker_rms_mm = 1000.0 * std::sqrt(sum_sq.sum() / std::max(1, counts.sum()));
  for (int m = 0; m < nm; ++m)
    if (counts[m] > 0)
      report.per_marker_rms_mm.emplace_back(initial.markers()[m].name,
                                            1000.0 * std::sqrt(sum_sq[m] / counts[m]));

  if (!report.per_marker_rms_mm.empty()) {
    std::vector<double> rms;
    for (const auto& [name, v] : report.per_marker_rms_mm) rms.push_back(v);
    std::nth_element(rms.begin(), rms.begin() + rms.size() / 2, rms.end());
    report.median_marker_rms_mm = rms[rms.size() / 2];
    for (const auto& [name, v] : report.per_marker_rms_mm)
      if (v > options.outlier_marker_ratio * report.median_marker_rms_mm &&
          v > report.median_marker_rms_mm + options.outlier_marker_min_mm)
        report.outlier_markers.emplace_back(name, v);
    std::sort(report.outlier_markers.begin(), report.outlier_markers.end(),
              [](const auto& a, const auto& b) { return a.second > b.second; });
  }

  // Uncertainty: S^{-1} in residual units; scaled by the residual variance for the reported std.
  const auto cov_start = Clock::now();
  Eigen::MatrixXd covariance;
  const bool have_covariance = np > 0 && schur.SharedCovariance(x, &covariance);
  const int dof = std::max(1, report.residuals - report.unknowns);
  const double variance = 2.0 * report.solver.final_cost / dof;
  const Eigen::VectorXd p0 = initial.InitialParameters();
  const Eigen::VectorXd p = problem.FullParameters(x.tail(np));
  // FitOptions::held_parameters: the holds counted at what they are worth. The same problem at
  // the same point with the holds free against their priors (MarkerFitProblem, relax_holds); its
  // covariance gives the fitted parameters' standard deviations.
  std::vector<double> relaxed_variance(np, -1.0);
  if (have_covariance && problem.has_holds()) {
    MarkerFitProblem relaxed(initial, problem.measurements(), options, /*relax_holds=*/true);
    for (int m = 0; m < nm; ++m) relaxed.SetMarkerSigma(m, problem.marker_sigma(m));
    if (options.robust_loss != RobustLoss::kNone) {
      Eigen::MatrixXd weights(total_frames, nm);
      for (int f = 0; f < total_frames; ++f)
        for (int m = 0; m < nm; ++m) weights(f, m) = problem.sample_weight(f, m);
      relaxed.SetSampleWeights(std::move(weights));
    }
    const int nr = relaxed.shared_dim();
    Eigen::VectorXd xr(static_cast<Eigen::Index>(total_frames) * nz + nr);
    xr.head(static_cast<Eigen::Index>(total_frames) * nz) = x.head(static_cast<Eigen::Index>(total_frames) * nz);
    for (int k = 0; k < nr; ++k) xr[static_cast<Eigen::Index>(total_frames) * nz + k] = p[relaxed.free_parameters()[k]];
    relaxed.SetFramePriorTargets(xr);
    formats::RowMatrix frame_weights;
    UnobservedCoordinateWeights(&relaxed, xr, relaxed.uniform_frame_prior_weight(), options.unobserved_hold, threads,
                                &frame_weights);
    relaxed.SetFramePriorWeights(std::move(frame_weights));
    ArrowSchurProblem relaxed_schur(&relaxed, threads);
    Eigen::MatrixXd relaxed_covariance;
    if (relaxed_schur.SharedCovariance(xr, &relaxed_covariance))
      for (int k = 0; k < np; ++k) {
        const int r = relaxed.free_index()[problem.free_parameters()[k]];
        if (r >= 0) relaxed_variance[k] = std::max(0.0, relaxed_covariance(r, r));
      }
  }
  for (int k = 0; k < np; ++k) {
    const int i = problem.free_parameters()[k];
    ParameterEstimate e;
    e.name = initial.parameters()[i].name;
    e.group = initial.parameters()[i].group;
    e.initial = p0[i];
    e.value = p[i];
    e.fitted = true;
    if (have_covariance) {
      const double c = std::max({0.0, covariance(k, k), relaxed_variance[k]});
      e.std = std::sqrt(c * variance);
      e.determined = std::sqrt(c) <= options.undetermined_ratio * problem.prior_sigma(k);
    } else {
      e.std = problem.prior_sigma(k);
      e.determined = false;
    }
    if (!e.determined) report.undetermined.push_back(e.name);
    report.parameters.push_back(e);
  }
  report.covariance_seconds = Since(cov_start);

  MOCAP_RETURN_IF_ERROR(initial.WithParameters(p, &result->model));
  result->coordinates.resize(trials.size());
  const Geometry geometry(result->model);
  ModelData data(result->model);
  // Residuals' lag products for their integrated autocorrelation time (FitReport).
  double lag_sum = 0, samples = 0;
  for (size_t t = 0; t < trials.size(); ++t) {
    Eigen::MatrixXd& z = result->coordinates[t];
    z.resize(trials[t].markers.num_frames(), nz);
    formats::RowMatrix residual(measure_correlation ? z.rows() : 0, 3 * nm);
    residual.setConstant(std::numeric_limits<double>::quiet_NaN());
    double trial_sq = 0;
    int trial_n = 0;
    std::vector<double>& frame_rms = report.per_frame_rms_mm.emplace_back(z.rows());
    for (int f = 0; f < z.rows(); ++f) {
      double frame_sq = 0;
      int frame_n = 0;
      z.row(f) = x.segment(static_cast<Eigen::Index>(first_frame[t] + f) * nz, nz).transpose();
      ForwardKinematics(result->model, geometry, z.row(f).transpose(), &data);
      const auto row = problem.measurements().row(first_frame[t] + f);
      for (int m = 0; m < nm; ++m) {
        if (!std::isfinite(row[3 * m])) continue;
        const Eigen::Vector3d r =
            MarkerPosition(result->model, geometry, data, m) - row.segment<3>(3 * m).transpose();
        if (measure_correlation) residual.row(f).segment<3>(3 * m) = r.transpose();
        frame_sq += r.squaredNorm();
        ++frame_n;
      }
      frame_rms[f] = frame_n > 0 ? 1000.0 * std::sqrt(frame_sq / frame_n)
                                 : std::numeric_limits<double>::quiet_NaN();
      trial_sq += frame_sq;
      trial_n += frame_n;
    }
    report.per_trial_rms_mm.push_back(1000.0 * std::sqrt(trial_sq / std::max(1, trial_n)));
    report.per_trial_samples.push_back(trial_n);
    if (!measure_correlation) continue;
    // rho(k) pooled over the trial's markers and axes, summed while it stays above 0.05 (the
    // noise floor of the estimate), for at most a quarter of the trial.
    auto lag = [&](int k) {
      double sum = 0;
      for (int f = 0; f + k < residual.rows(); ++f)
        for (int c = 0; c < residual.cols(); ++c) {
          const double a = residual(f, c), b = residual(f + k, c);
          if (std::isfinite(a) && std::isfinite(b)) sum += a * b;
        }
      return sum;
    };
    const double c0 = lag(0);
    if (!(c0 > 0)) continue;
    double trial_lags = 0;
    for (int k = 1; k <= residual.rows() / 4; ++k) {
      const double rho = lag(k) / c0;
      if (rho < 0.05) break;
      trial_lags += rho;
    }
    lag_sum += trial_lags * trial_n;
    samples += trial_n;
  }
  // The median marker's RMS per coordinate: a few markers far off (a held joint's, a slipping
  // one) say nothing about the others' error.
  report.residual_sigma_mm = report.median_marker_rms_mm / std::sqrt(3.0);
  report.residual_correlation_frames = samples > 0 ? 1.0 + 2.0 * lag_sum / samples : 1.0;
  report.wall_seconds = Since(start);
  result->report = std::move(report);
  return Status::Ok();
}


// The joints whose centre the trials observe directly: a marker of FitOptions::fixed_markers at
// the origin of the joint's child segment -- a marker tied to the centre (OpenCap's RHJC_study,
// solver/attach_markers.h TieCentreMarkers) or a functional centre's virtual marker
// (AddFunctionalCentres) -- with a sample in some trial. Its samples are the centre in the lab, so
// however little the joint turns, the centre is placed by them, not by the rotation.
std::vector<bool> CentresObserved(const Model& model, const std::vector<FitTrial>& trials, const FitOptions& options) {
  std::vector<bool> observed(model.num_joints(), false);
  for (const std::string& name : options.fixed_markers) {
    const int m = model.FindMarker(name);
    if (m < 0 || model.markers()[m].position.norm() > 1e-12) continue;
    bool seen = false;
    for (const FitTrial& t : trials) {
      const int c = t.markers.FindMarker(name);
      for (int f = 0; c >= 0 && f < t.markers.num_frames() && !seen; ++f) seen = t.markers.Has(f, c);
    }
    if (!seen) continue;
    for (int j = 0; j < model.num_joints(); ++j)
      if (model.joints()[j].parent >= 0 && model.joints()[j].child == model.markers()[m].segment) observed[j] = true;
  }
  return observed;
}

// FitOptions::min_excitation_deg: the joints whose centre or axes are free but whose rotation
// the poses `z` (every trial's frames) hardly move, with the parameters to hold and why. The
// centre of a joint in `centre_observed` (CentresObserved) is not held: only its axes are.
void UnexcitedJoints(const Model& model, const std::vector<Eigen::MatrixXd>& z, const FitOptions& options,
                     const std::vector<bool>& centre_observed,
                     std::vector<std::pair<std::string, std::string>>* held,
                     std::vector<std::string>* parameters) {
  // Per trial (a joint moved in one trial and still in the others is excited: pooling the frames
  // would dilute its spread), the largest.
  const int nz = model.num_coordinates();
  Eigen::VectorXd spread = Eigen::VectorXd::Zero(nz);
  for (const Eigen::MatrixXd& t : z) {
    if (t.rows() < 2) continue;
    const Eigen::RowVectorXd mean = t.colwise().mean();
    const Eigen::VectorXd s =
        ((t.rowwise() - mean).colwise().squaredNorm().transpose() / t.rows()).cwiseSqrt();
    spread = spread.cwiseMax(s * (180.0 / M_PI));
  }
  for (int j = 0; j < model.num_joints(); ++j) {
    if (model.centre_index(j) < 0) continue;  // the root: its centre is no parameter
    const Joint& joint = model.joints()[j];
    std::vector<int> coordinates;
    std::vector<std::string> names;
    for (size_t e = 0; e < joint.elements.size(); ++e) {
      const JointElement& el = joint.elements[e];
      if (el.kind == ElementKind::kRotation && el.coordinate >= 0 &&
          std::find(coordinates.begin(), coordinates.end(), el.coordinate) == coordinates.end())
        coordinates.push_back(el.coordinate);
      const int a = model.axis_index(j, static_cast<int>(e));
      if (a >= 0) {
        names.push_back(model.parameters()[a].name);
        names.push_back(model.parameters()[a + 1].name);
      }
    }
    const bool centre_free = options.fit_centres && !centre_observed[j];
    const bool axes_free = options.fit_axes && !names.empty();
    if (!centre_free && !axes_free) continue;
    std::vector<double> s;
    for (int c : coordinates) s.push_back(spread[c]);
    std::sort(s.rbegin(), s.rend());
    const size_t needed = s.size() >= 2 ? 2 : 1;  // a centre needs two axes moved; a hinge its one
    const double moved = s.size() >= needed ? s[needed - 1] : 0.0;
    if (moved >= options.min_excitation_deg) continue;
    char why[160];
    std::snprintf(why, sizeof(why), "%s spread %.1f deg (%s), below %.0f deg",
                  s.empty() ? "no rotation:" : needed == 2 ? "second rotation" : "rotation", moved,
                  ToString(joint.type), options.min_excitation_deg);
    held->emplace_back(joint.name, centre_observed[j] ? std::string(why) + "; axes only: a marker on the centre places it"
                                                      : std::string(why));
    if (centre_free)
      for (int k = 0; k < 3; ++k) parameters->push_back(model.parameters()[model.centre_index(j) + k].name);
    if (axes_free) parameters->insert(parameters->end(), names.begin(), names.end());
  }
}

// FitOptions::effective_marker_sigma: the data's weight for the next stage from this stage's
// residuals, never below the nominal marker sigma.
double EffectiveMarkerSigma(const FitOptions& options, const FitReport& r) {
  if (!options.effective_marker_sigma) return options.marker_sigma_m;
  const double sigma = 1e-3 * r.residual_sigma_mm * std::sqrt(std::max(1.0, r.residual_correlation_frames));
  return std::isfinite(sigma) ? std::max(options.marker_sigma_m, sigma) : options.marker_sigma_m;
}

// A stage's iterations and times added to those of the stages before it.
void AppendIterations(const FitReport& r, LmSummary* before, FitReport* totals) {
  if (before->iterations.empty()) {
    *before = r.solver;
    totals->initial_marker_rms_mm = r.initial_marker_rms_mm;
  } else {
    before->iterations.insert(before->iterations.end(), r.solver.iterations.begin(), r.solver.iterations.end());
    before->num_linear_solves += r.solver.num_linear_solves;
    before->total_seconds += r.solver.total_seconds;
  }
  totals->ik_seconds += r.ik_seconds;
  totals->solve_seconds += r.solve_seconds;
  totals->rescued_frames += r.rescued_frames;
  totals->reposed = totals->reposed || r.reposed;
}

// FitOptions::stage_frames: the rows of a trial the stages before the last solve, every k-th
// frame from the middle of the first stretch of k.
std::vector<int> EveryKthFrame(int num_frames, int k) {
  std::vector<int> rows;
  if (num_frames <= 0) return rows;  // an empty trial stays empty: FitStage names it
  for (int f = std::min(k / 2, num_frames - 1); f < num_frames; f += k) rows.push_back(f);
  return rows;
}

FitTrial TrialRows(const FitTrial& trial, const std::vector<int>& rows) {
  FitTrial out;
  const formats::MarkerTrial& m = trial.markers;
  out.markers.name = m.name;
  out.markers.marker_names = m.marker_names;
  out.markers.rate_hz = rows.size() > 1 ? m.rate_hz / (rows[1] - rows[0]) : m.rate_hz;
  out.markers.positions.resize(static_cast<Eigen::Index>(rows.size()), m.positions.cols());
  if (trial.initial_coordinates.rows() > 0)
    out.initial_coordinates.resize(static_cast<Eigen::Index>(rows.size()), trial.initial_coordinates.cols());
  for (size_t i = 0; i < rows.size(); ++i) {
    const int f = rows[i];
    out.markers.positions.row(static_cast<Eigen::Index>(i)) = m.positions.row(f);
    if (static_cast<size_t>(f) < m.frame_numbers.size()) out.markers.frame_numbers.push_back(m.frame_numbers[f]);
    if (static_cast<size_t>(f) < m.times.size()) out.markers.times.push_back(m.times[f]);
    if (trial.initial_coordinates.rows() > 0)
      out.initial_coordinates.row(static_cast<Eigen::Index>(i)) = trial.initial_coordinates.row(f);
  }
  return out;
}

}  // namespace

namespace {
std::string GroupList(const FitOptions& o) {
  std::string list;
  auto add = [&](bool on, const char* name) {
    if (on) list += (list.empty() ? "" : ",") + std::string(name);
  };
  add(o.fit_scales, "scales");
  add(o.fit_centres, "centres");
  add(o.fit_axes, "axes");
  add(o.fit_markers, "markers");
  return list.empty() ? "none" : list;
}
}  // namespace

FitStageSummary StageSummary(const std::string& name, const FitOptions& o, const FitReport& r) {
  FitStageSummary s;
  s.name = name;
  s.groups = GroupList(o);
  s.iterations = r.solver.num_iterations();
  s.termination = r.solver.termination;
  s.initial_marker_rms_mm = r.initial_marker_rms_mm;
  s.marker_rms_mm = r.marker_rms_mm;
  s.seconds = r.wall_seconds;
  s.marker_sigma_mm = 1000.0 * o.marker_sigma_m;
  s.residual_correlation_frames = r.residual_correlation_frames;
  s.frames = r.frames;
  return s;
}

namespace {

// The report's outlying markers explained (solver/marker_diagnosis.h), from the fitted result.
Status DiagnoseOutliers(const std::vector<FitTrial>& trials, const FitOptions& options,
                        FitResult* result) {
  if (result->report.outlier_markers.empty()) return Status::Ok();
  std::vector<formats::MarkerTrial> markers;
  for (const FitTrial& t : trials) markers.push_back(t.markers);
  return DiagnoseMarkers(result->model, markers, result->coordinates, result->report.outlier_markers,
                         options.diagnosis, &result->report.marker_diagnoses);
}

}  // namespace

namespace {
// FitOptions::scaling_marker_rounds: the scales stage solved again with each marker weighted by
// how far the model's place for it is from where the data put it, until the weights settle; the
// result keeps the model's own marker weights.
// *name: the stage name of *out's solve.
Status ReweighScalingMarkers(const Model& model, const std::vector<FitTrial>& trials, const FitOptions& o,
                             const FitOptions& options, FitResult* out, int* iterations_left,
                             std::vector<FitStageSummary>* summaries, LmSummary* before, FitReport* totals,
                             std::string* name) {
  if (options.scaling_marker_rounds == 0) return Status::Ok();
  const int nm = model.num_markers();
  std::vector<double> base(nm), weight(nm);
  for (int m = 0; m < nm; ++m) base[m] = weight[m] = model.markers()[m].weight;
  for (int round = 0; round < options.scaling_marker_rounds && *iterations_left > 1; ++round) {
    std::vector<double> rms(nm, -1.0), observed;
    for (const auto& [name, v] : out->report.per_marker_rms_mm) {
      const int m = model.FindMarker(name);
      if (m >= 0 && std::isfinite(v)) rms[m] = v, observed.push_back(v);
    }
    if (observed.size() < 3) break;
    std::nth_element(observed.begin(), observed.begin() + observed.size() / 2, observed.end());
    const double scale_mm = std::max(1e-3, options.scaling_marker_robust_scale * observed[observed.size() / 2]);
    double largest_change = 0;
    std::vector<double> next(weight);
    for (int m = 0; m < nm; ++m) {
      if (rms[m] < 0) continue;
      const double u = rms[m] / scale_mm;
      next[m] = base[m] / (1.0 + u * u);  // Cauchy (solver/robust_loss.h), per marker
      largest_change = std::max(largest_change, std::abs(next[m] - weight[m]) / base[m]);
    }
    if (largest_change <= options.scaling_marker_tolerance) break;
    weight = next;
    Model weighted;
    MOCAP_RETURN_IF_ERROR(out->model.WithMarkerWeights(weight, &weighted));
    std::vector<FitTrial> from = trials;
    for (size_t t = 0; t < from.size(); ++t) from[t].initial_coordinates = out->coordinates[t];
    summaries->push_back(StageSummary(*name, o, out->report));
    *name = "scales, reweighted";
    AppendIterations(out->report, before, totals);
    FitOptions r = o;
    r.lm.max_iterations = std::min(options.staged_iterations, *iterations_left - 1);
    FitResult again;
    MOCAP_RETURN_IF_ERROR(FitStage(weighted, from, r, /*measure_correlation=*/false, &again));
    if (!again.report.solver.IsSolutionUsable())
      return Status::Error("fit, stage 'scales, reweighted': " + again.report.solver.message);
    *iterations_left -= again.report.solver.num_iterations();
    *out = std::move(again);
  }
  out->report.scaling_marker_weights.clear();
  for (int m = 0; m < nm; ++m)
    if (weight[m] < 0.5 * base[m]) out->report.scaling_marker_weights.emplace_back(model.markers()[m].name, weight[m] / base[m]);
  if (weight == base) return Status::Ok();
  Model restored;
  MOCAP_RETURN_IF_ERROR(out->model.WithMarkerWeights(base, &restored));
  out->model = std::move(restored);
  return Status::Ok();
}

// FitOptions::far_moved_marker_sigmas: the model's markers that the fit moved that far on their
// segment, farthest first.
void FlagFarMovedMarkers(const Model& initial, const FitOptions& options, FitResult* result) {
  std::map<std::string, Eigen::Vector3d> moved;
  for (const ParameterEstimate& e : result->report.parameters) {
    if (e.group != ParameterGroup::kMarker || e.name.size() < 3) continue;
    const std::string marker = e.name.substr(0, e.name.size() - 2);
    const char axis = e.name.back();
    if (initial.FindMarker(marker) < 0 || axis < 'x' || axis > 'z') continue;
    // A placeholder placed from the trials (FitOptions::place_stacked_markers) was never where
    // the model said: its move says nothing about the poses.
    const auto& placed = result->report.placed_markers;
    if (std::any_of(placed.begin(), placed.end(),
                    [&](const PlacedMarker& p) { return p.name == marker && p.why_not.empty(); }))
      continue;
    auto [it, fresh] = moved.try_emplace(marker, Eigen::Vector3d::Zero());
    it->second[axis - 'x'] = e.value - e.initial;
  }
  const double limit_m = options.far_moved_marker_sigmas * options.prior_sigma_position_m;
  auto& far = result->report.far_moved_markers;
  far.clear();
  for (const auto& [name, d] : moved) {
    const int m = result->model.FindMarker(name);
    if (m < 0) continue;
    const Segment& segment = result->model.segments()[result->model.markers()[m].segment];
    const double distance_m = segment.scale * d.norm();
    if (distance_m > limit_m) far.push_back({name, segment.name, 1000.0 * distance_m});
  }
  std::sort(far.begin(), far.end(), [](const auto& a, const auto& b) { return a.distance_mm > b.distance_mm; });
}

// FitModel for trials already reduced to their postures where static (options checked there).
Status FitSchedule(const Model& initial, const std::vector<FitTrial>& trials, const FitOptions& options,
                   FitResult* result) {
  const auto start = Clock::now();
  if (trials.empty()) return Status::Error("fit: no trials given");
  const bool staged = options.staged && (options.fit_centres || options.fit_axes) &&
                      (options.fit_scales || options.fit_markers);
  if (!staged) {
    MOCAP_RETURN_IF_ERROR(FitStage(initial, trials, options, true, result));
    result->report.stages = {StageSummary("all parameters", options, result->report)};
    return DiagnoseOutliers(trials, options, result);
  }

  // The schedule (see the header): scales with the model's markers, then the markers with those
  // scales, then everything; each stage starts from the previous one's geometry and poses.
  struct Stage {
    const char* name;
    bool scales, markers;
  };
  std::vector<Stage> stages;
  if (options.fit_scales) stages.push_back({"scales", true, false});
  if (options.fit_markers) stages.push_back({"markers", false, true});
  FitResult placed;
  const Model* model = &initial;
  // FitOptions::stage_frames: the stages before the last solve every k-th frame of each trial.
  int total_frames = 0;
  for (const FitTrial& t : trials) total_frames += t.markers.num_frames();
  const int stride = options.stage_frames > 0 && total_frames > 2 * options.stage_frames
                         ? (total_frames + options.stage_frames - 1) / options.stage_frames
                         : 1;
  std::vector<std::vector<int>> stage_rows(trials.size());
  std::vector<FitTrial> stage_trials;
  for (size_t t = 0; t < trials.size(); ++t) {
    stage_rows[t] = EveryKthFrame(trials[t].markers.num_frames(), stride);
    stage_trials.push_back(stride > 1 ? TrialRows(trials[t], stage_rows[t]) : trials[t]);
  }
  // FitOptions::place_stacked_markers: the first stage without them, placed after it.
  std::vector<Marker> stacked;
  Model unstacked;
  // Every trial's markers, for the steps that read them beside the poses (placement, attachment).
  std::vector<formats::MarkerTrial> trial_markers;
  for (const FitTrial& t : stage_trials) trial_markers.push_back(t.markers);
  if (options.place_stacked_markers) {
    const std::vector<int> stacked_index =
        StackedMarkers(initial, trial_markers, options.stacked_marker_tolerance_m);
    if (!stacked_index.empty()) {
      std::vector<int> keep;
      for (int m = 0; m < initial.num_markers(); ++m)
        if (std::find(stacked_index.begin(), stacked_index.end(), m) == stacked_index.end()) keep.push_back(m);
        else stacked.push_back(initial.markers()[m]);
      MOCAP_RETURN_IF_ERROR(initial.WithMarkers(keep, &unstacked));
      model = &unstacked;
    }
  }
  std::vector<PlacedMarker> placed_markers;
  std::vector<FitStageSummary> summaries;
  LmSummary before;
  FitReport totals;
  int iterations_left = options.lm.max_iterations;
  double effective_sigma_m = options.marker_sigma_m;
  std::vector<AttachedMarker> attached;
  std::vector<std::pair<std::string, double>> scaling_weights;
  for (const Stage& stage : stages) {
    FitOptions o = options;
    o.marker_sigma_m = effective_sigma_m;
    o.fit_scales = stage.scales;
    o.fit_markers = stage.markers;
    o.fit_centres = o.fit_axes = false;
    o.marker_sigma_rounds = 0;  // the markers' spread is the final stage's, not a start's
    // The robust loss judges the data's errors: with the model's markers, the residuals are
    // their misplacement.
    if (!stage.markers) o.robust_loss = RobustLoss::kNone;
    // The final stage keeps at least one of the caller's iterations; a stage left none is skipped.
    o.lm.max_iterations = std::min(options.staged_iterations, iterations_left - 1);
    o.lm.function_tolerance = std::max(options.lm.function_tolerance, options.stage_function_tolerance);
    // A stage before the last weighs the data by a sigma it assumed (the first, the nominal
    // marker_sigma_m), so its reduced system is no inverse covariance: the statistical stop
    // (LmOptions::shared_step_tolerance) is the final stage's.
    o.lm.shared_step_tolerance = 0;
    if (o.lm.max_iterations < 1) break;
    // The markers stage weighs its data before their error is known (nominal sigma), so it first
    // solves only until the residual level settles (the cost changes by less than
    // markers_measure_tolerance: the sigma, its square root, to half that), enough to place the
    // markers and measure what the residuals left say a sample is worth (EffectiveMarkerSigma).
    // Where that is far less than assumed (skin motion over a walk, repeated over hundreds of
    // frames), the stage is solved from the same start again with the measured weight; otherwise
    // it goes on from where it stopped.
    // Weighted as independent 1 mm samples, the frames of a walk outvote the priors that hold
    // each segment inside its markers: on gait2354 the left leg's bones slid 5-8 cm medially out
    // of its markers (ankle centre 96 mm from the malleoli, knee 52 mm from the epicondyles; at
    // the measured 20 mm: 46 and 26 mm) for a 0.003 mm better RMS.
    std::string stage_name = stage.name;
    const RobustLoss robust_loss = o.robust_loss;
    if (stage.markers) {
      o.lm.function_tolerance = std::max(o.lm.function_tolerance, options.markers_measure_tolerance);
      o.robust_loss = RobustLoss::kNone;
    }
    FitResult out;
    MOCAP_RETURN_IF_ERROR(FitStage(*model, stage_trials, o, /*measure_correlation=*/stage.markers, &out));
    if (!out.report.solver.IsSolutionUsable())
      return Status::Error(std::string("fit, stage '") + stage.name + "': " + out.report.solver.message);
    iterations_left -= out.report.solver.num_iterations();
    if (stage.scales) {
      MOCAP_RETURN_IF_ERROR(ReweighScalingMarkers(*model, stage_trials, o, options, &out, &iterations_left,
                                                  &summaries, &before, &totals, &stage_name));
      scaling_weights = out.report.scaling_marker_weights;
    }
    const double measured_sigma_m = stage.markers ? EffectiveMarkerSigma(options, out.report) : 0.0;
    const bool reweigh = stage.markers && measured_sigma_m > options.reweigh_markers_stage_ratio * o.marker_sigma_m;
    if (stage.markers && (reweigh || !out.report.converged() || robust_loss != RobustLoss::kNone) &&
        iterations_left > 1) {
      summaries.push_back(StageSummary(stage.name, o, out.report));
      AppendIterations(out.report, &before, &totals);
      o.robust_loss = robust_loss;
      o.lm.max_iterations = std::min(options.staged_iterations, iterations_left - 1);
      o.lm.function_tolerance = std::max(options.lm.function_tolerance, options.stage_function_tolerance);
      FitResult next;
      if (reweigh) {
        o.marker_sigma_m = measured_sigma_m;
        MOCAP_RETURN_IF_ERROR(FitStage(*model, stage_trials, o, /*measure_correlation=*/true, &next));
      } else {
        std::vector<FitTrial> from = stage_trials;
        for (size_t t = 0; t < from.size(); ++t) from[t].initial_coordinates = out.coordinates[t];
        MOCAP_RETURN_IF_ERROR(FitStage(out.model, from, o, /*measure_correlation=*/true, &next));
      }
      const std::string name = reweigh ? "markers, reweighted" : "markers, continued";
      if (!next.report.solver.IsSolutionUsable())
        return Status::Error("fit, stage '" + name + "': " + next.report.solver.message);
      iterations_left -= next.report.solver.num_iterations();
      out = std::move(next);
      summaries.push_back(StageSummary(name, o, out.report));
    } else {
      summaries.push_back(StageSummary(stage_name, o, out.report));
    }
    AppendIterations(out.report, &before, &totals);
    // Only residuals left with the markers placed measure the data's error; with the model's
    // markers they are its misplacement.
    if (stage.markers) effective_sigma_m = EffectiveMarkerSigma(options, out.report);
    placed = std::move(out);
    if (!stacked.empty()) {
      Model with_placed;
      MOCAP_RETURN_IF_ERROR(PlaceMarkersOnTheirSegments(placed.model, trial_markers, placed.coordinates, stacked,
                                                        options.attach, &with_placed, &placed_markers));
      placed.model = std::move(with_placed);
      stacked.clear();
    }
    if (stage.scales && options.attach_trial_markers) {
      Model with_extra;
      MOCAP_RETURN_IF_ERROR(AttachTrialMarkers(placed.model, trial_markers, placed.coordinates,
                                               options.attach, &with_extra, &attached));
      placed.model = std::move(with_extra);
    }
    model = &placed.model;
    for (size_t t = 0; t < trials.size(); ++t) stage_trials[t].initial_coordinates = placed.coordinates[t];
  }
  if (stride > 1 && !summaries.empty()) {
    // Every frame posed by the stages' model, from the poses of the frames they solved (IK
    // warm-started from the nearest of them, then the poses alone by LM), and the data's error
    // measured on every frame: the residuals' correlation time is in frames, and a subset's
    // would be the full trial's divided by the stride.
    const int nz = placed.model.num_coordinates();
    std::vector<FitTrial> every = trials;
    for (size_t t = 0; t < trials.size(); ++t) {
      every[t].initial_coordinates = Eigen::MatrixXd::Constant(trials[t].markers.num_frames(), nz,
                                                               std::numeric_limits<double>::quiet_NaN());
      for (size_t i = 0; i < stage_rows[t].size(); ++i)
        every[t].initial_coordinates.row(stage_rows[t][i]) = placed.coordinates[t].row(static_cast<Eigen::Index>(i));
    }
    FitOptions poses = options;
    poses.marker_sigma_m = effective_sigma_m;
    poses.fit_scales = poses.fit_centres = poses.fit_axes = poses.fit_markers = false;
    poses.robust_loss = RobustLoss::kNone;
    poses.marker_sigma_rounds = 0;
    poses.lm.max_iterations = std::max(1, std::min(options.staged_iterations, iterations_left - 1));
    poses.lm.function_tolerance = std::max(options.lm.function_tolerance, options.stage_function_tolerance);
    FitResult posed;
    MOCAP_RETURN_IF_ERROR(FitStage(placed.model, every, poses, /*measure_correlation=*/options.fit_markers, &posed));
    if (!posed.report.solver.IsSolutionUsable())
      return Status::Error("fit, stage 'poses': " + posed.report.solver.message);
    iterations_left -= posed.report.solver.num_iterations();
    summaries.push_back(StageSummary("poses", poses, posed.report));
    AppendIterations(posed.report, &before, &totals);
    if (options.fit_markers) effective_sigma_m = EffectiveMarkerSigma(options, posed.report);
    placed.coordinates = std::move(posed.coordinates);
    stage_trials = trials;
    for (size_t t = 0; t < trials.size(); ++t) stage_trials[t].initial_coordinates = placed.coordinates[t];
  }

  if (summaries.empty()) {  // no iteration to spare for a first stage: one stage, as asked
    MOCAP_RETURN_IF_ERROR(FitStage(initial, trials, options, true, result));
    result->report.stages = {StageSummary("all parameters", options, result->report)};
    return DiagnoseOutliers(trials, options, result);
  }
  // The whole problem from the last stage's geometry and poses.
  FitOptions last = options;
  last.marker_sigma_m = effective_sigma_m;
  // Scales stay as the first stage found them: with a segment's markers and centres free its
  // scale is a convention (the growth gauge, marker_fit_problem.h), and where a child centre is
  // held it is a back door through which the held centre moves after all.
  last.fit_scales = false;
  std::vector<std::pair<std::string, std::string>> held;
  UnexcitedJoints(placed.model, placed.coordinates, options, CentresObserved(placed.model, trials, options), &held,
                  &last.held_parameters);
  last.lm.max_iterations = std::max(1, iterations_left);
  const Model placed_model = placed.model;  // *result may be `placed`'s storage
  MOCAP_RETURN_IF_ERROR(FitStage(placed_model, stage_trials, last, true, result));

  FitReport& report = result->report;
  summaries.push_back(StageSummary("all parameters", last, report));
  report.stages = std::move(summaries);
  report.initial_marker_rms_mm = totals.initial_marker_rms_mm;
  report.solver.initial_cost = before.initial_cost;
  report.solver.iterations.insert(report.solver.iterations.begin(), before.iterations.begin(),
                                  before.iterations.end());
  report.solver.num_linear_solves += before.num_linear_solves;
  report.solver.total_seconds += before.total_seconds;
  report.ik_seconds += totals.ik_seconds;
  report.solve_seconds += totals.solve_seconds;
  report.rescued_frames += totals.rescued_frames;
  report.reposed = report.reposed || totals.reposed;
  // A held joint's centre and axes are parameters these trials do not determine: listed as such.
  for (const std::string& name : last.held_parameters)
    if (std::find(report.undetermined.begin(), report.undetermined.end(), name) == report.undetermined.end())
      report.undetermined.push_back(name);
  report.held_joints = std::move(held);
  report.attached_markers = std::move(attached);
  report.placed_markers = std::move(placed_markers);
  report.scaling_marker_weights = std::move(scaling_weights);
  // The caller's model is the parameters' starting point, not a stage's.
  const Eigen::VectorXd p0 = initial.InitialParameters();
  for (ParameterEstimate& e : report.parameters) {
    const int i = initial.FindParameter(e.name);
    if (i >= 0) e.initial = p0[i];
  }
  MOCAP_RETURN_IF_ERROR(DiagnoseOutliers(trials, options, result));
  report.wall_seconds = Since(start);
  return Status::Ok();
}

}  // namespace

Status FitModel(const Model& initial, const std::vector<FitTrial>& trials, const FitOptions& options,
                FitResult* result) {
  std::string why;
  if (!options.IsValid(&why)) return Status::Error("fit options: " + why);
  // FitOptions::static_trial_motion_mm: every frame of a static trial becomes its mean posture.
  std::vector<FitTrial> postures = trials;
  std::vector<size_t> static_index;
  for (size_t t = 0; t < postures.size(); ++t) {
    formats::MarkerTrial& m = postures[t].markers;
    if (options.static_trial_motion_mm <= 0 || m.num_frames() < 2 ||
        !(MedianMarkerMotionMm(m) < options.static_trial_motion_mm))
      continue;
    for (int c = 0; c < m.positions.cols(); ++c) {
      double sum = 0;
      int n = 0;
      for (int f = 0; f < m.num_frames(); ++f)
        if (std::isfinite(m.positions(f, c))) sum += m.positions(f, c), ++n;
      if (n > 0) m.positions.col(c).setConstant(sum / n);
    }
    static_index.push_back(t);
  }
  MOCAP_RETURN_IF_ERROR(FitSchedule(initial, postures, options, result));
  result->report.fitted_marker_rms_mm = result->report.marker_rms_mm;
  FlagFarMovedMarkers(initial, options, result);
  if (static_index.empty()) return Status::Ok();
  // The static trials' own frames, posed by the fitted model (its geometry fixed) from their
  // posture: their coordinates and residuals follow the sway the posture averaged out.
  FitOptions poses_only = options;
  poses_only.fit_scales = poses_only.fit_centres = poses_only.fit_axes = poses_only.fit_markers = false;
  poses_only.robust_loss = RobustLoss::kNone;
  poses_only.marker_sigma_rounds = 0;
  std::vector<FitTrial> measured;
  for (size_t t : static_index) measured.push_back({trials[t].markers, result->coordinates[t]});
  FitResult posed;
  MOCAP_RETURN_IF_ERROR(FitStage(result->model, measured, poses_only, /*measure_correlation=*/false, &posed));
  FitReport& report = result->report;
  for (size_t k = 0; k < static_index.size(); ++k) {
    const size_t t = static_index[k];
    result->coordinates[t] = posed.coordinates[k];
    if (t < report.per_trial_rms_mm.size()) report.per_trial_rms_mm[t] = posed.report.per_trial_rms_mm[k];
    if (t < report.per_trial_samples.size()) report.per_trial_samples[t] = posed.report.per_trial_samples[k];
    if (t < report.per_frame_rms_mm.size()) report.per_frame_rms_mm[t] = posed.report.per_frame_rms_mm[k];
    report.static_trials.push_back(trials[t].markers.name);
  }
  // The headline RMS is that of the frames as measured, as each trial's is: a static trial fitted
  // alone fits its one mean posture exactly (every marker free), and its 0 mm said nothing of the
  // sway and skin the frames show.
  if (report.per_trial_samples.size() == report.per_trial_rms_mm.size()) {
    double sum_sq = 0;
    int samples = 0;
    for (size_t t = 0; t < report.per_trial_rms_mm.size(); ++t) {
      sum_sq += report.per_trial_rms_mm[t] * report.per_trial_rms_mm[t] * report.per_trial_samples[t];
      samples += report.per_trial_samples[t];
    }
    if (samples > 0) report.marker_rms_mm = std::sqrt(sum_sq / samples);
    report.marker_samples = samples;
  }
  return Status::Ok();
}

}  // namespace mocap::solver
