// sta_accuracy: the global fit's accuracy against the simulated truth as the soft-tissue artefact
// grows (issue 19): the default protocol simulated at each --sta-mm (the thigh's RMS; every other
// marker per the STA table, sim/default_sta_table.json), fitted by solver::FitModel with its
// default options from per-frame IK, and held against the true model:
//   - joint centres in the lab: per joint, the RMS over every frame of the fitted centre's
//     distance from the true one (sim::JointCentreTrackRmsMm); the worst joint is printed;
//   - joint centres in their segments, axes and segment lengths (model/compare.h), the axes the
//     fit reports as determined only (the wrist axes behind one hand marker are not).
//
//   sta_accuracy [--sta 0,5,10,20] [--seed N] [--noise-mm S] [--threads T] [--joints]
//                [--sigma-rounds N] [--truth-start] [--single-stage] [--diagnose JOINT]
//                [--robust huber|cauchy[:SCALE]] [--drop M1,M2] [--hold P1,P2]
//
// Prints BENCHMARKS.md's accuracy table (markdown); --joints adds every joint's lab RMS and every
// marker's residual RMS and fitted sigma. --sigma-rounds sets FitOptions::marker_sigma_rounds
// (default: FitOptions' own; 0 is the fit with one sigma for all markers). --truth-start starts
// the fit from the true poses instead of IK: the same result means the errors are those of the
// least-squares minimum, not of a solve that stopped short. --single-stage turns FitModel's
// schedule off (FitOptions::staged). --diagnose JOINT splits that joint's lab error d(t) (fitted
// centre minus true centre) into its mean and the rest, each expressed in the true parent and
// child segment frames and along the joint's true axes: a constant offset is a geometry that
// trades against the markers; a time-varying one is artefact leaking into the poses. --robust sets
// FitOptions::robust_loss (and robust_scale); --drop leaves markers out of the trials; --hold
// holds parameters at the model's (FitOptions::fixed_parameters): experiments on what the
// artefact does, not fits a lab would run.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <sstream>
#include <string>
#include <vector>

#include "model/compare.h"
#include "sim/simulate.h"
#include "solver/global_fit.h"

using namespace mocap;

namespace {

struct Args {
  std::vector<double> sta_mm = {0, 5, 10, 20};
  std::uint64_t seed = 1;
  double noise_mm = 0.5;
  int threads = 0;
  bool joints = false;
  int sigma_rounds = -1;  // < 0: FitOptions' default
  bool truth_start = false;
  bool single_stage = false;
  solver::RobustLoss robust = solver::RobustLoss::kNone;
  double robust_scale = solver::FitOptions().robust_scale;
  std::string diagnose;  // joint name, or empty
  std::vector<std::string> drop;  // markers left out of the trials
  std::vector<std::string> hold;  // parameters held (FitOptions::fixed_parameters)
};

[[noreturn]] void Usage(const std::string& why) {
  std::fprintf(stderr,
               "sta_accuracy: %s\nusage: sta_accuracy [--sta 0,5,10,20] [--seed N] [--noise-mm S] "
               "[--threads T] [--joints] [--sigma-rounds N] [--truth-start] "
               "[--single-stage] [--diagnose JOINT] [--robust huber|cauchy[:SCALE]] [--drop M,..] [--hold P,..]\n",
               why.c_str());
  std::exit(2);
}

double Number(const std::string& flag, const std::string& text) {
  char* end = nullptr;
  const double v = std::strtod(text.c_str(), &end);
  if (text.empty() || *end != '\0' || !std::isfinite(v)) Usage(flag + ": not a number: '" + text + "'");
  return v;
}

Args ParseArgs(int argc, char** argv) {
  Args a;
  for (int i = 1; i < argc; ++i) {
    const std::string flag = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) Usage(flag + ": needs a value");
      return argv[++i];
    };
    if (flag == "--sta") {
      a.sta_mm.clear();
      std::stringstream list(value());
      for (std::string item; std::getline(list, item, ',');) a.sta_mm.push_back(Number(flag, item));
    } else if (flag == "--seed") {
      a.seed = static_cast<std::uint64_t>(Number(flag, value()));
    } else if (flag == "--noise-mm") {
      a.noise_mm = Number(flag, value());
    } else if (flag == "--threads") {
      a.threads = static_cast<int>(Number(flag, value()));
    } else if (flag == "--sigma-rounds") {
      a.sigma_rounds = static_cast<int>(Number(flag, value()));
    } else if (flag == "--truth-start") {
      a.truth_start = true;
    } else if (flag == "--robust") {
      const std::string v = value();
      const size_t colon = v.find(':');
      if (Status st = solver::ParseRobustLoss(v.substr(0, colon), &a.robust); !st) Usage(flag + ": " + st.message());
      if (colon != std::string::npos) a.robust_scale = Number(flag, v.substr(colon + 1));
    } else if (flag == "--single-stage") {
      a.single_stage = true;
    } else if (flag == "--drop" || flag == "--hold") {
      std::stringstream list(value());
      for (std::string item; std::getline(list, item, ',');) (flag == "--drop" ? a.drop : a.hold).push_back(item);
    } else if (flag == "--diagnose") {
      a.diagnose = value();
    } else if (flag == "--joints") {
      a.joints = true;
    } else {
      Usage("unknown argument '" + flag + "'");
    }
  }
  return a;
}

bool AxisDetermined(const solver::FitReport& r, const std::string& joint, size_t k) {
  const std::string base = joint + ".axis" + std::to_string(k) + ".";
  for (const std::string& u : r.undetermined)
    if (u.rfind(base, 0) == 0) return false;
  return true;
}

// --diagnose: joint j's lab error d(t) = fitted centre - true centre over every frame, as its
// mean and the RMS of d - mean, in the true parent's frame, the true child's frame and along the
// joint's true axes (in the lab at each frame).
std::string DiagnoseJoint(const sim::SimulatedSession& session, const Model& fitted,
                          const std::vector<Eigen::MatrixXd>& coordinates, int j) {
  const Model& truth = session.truth;
  const Joint& joint = truth.joints()[j];
  const Geometry gt(truth), gf(fitted);
  ModelData dt(truth), df(fitted);
  const size_t na = joint.elements.size();
  std::vector<Eigen::Vector3d> parent, child;
  std::vector<Eigen::VectorXd> along;
  for (size_t t = 0; t < session.trials.size() && t < coordinates.size(); ++t)
    for (int f = 0; f < session.trials[t].markers.num_frames(); ++f) {
      ForwardKinematics(truth, gt, sim::TrueCoordinates(truth, session.trials[t].coordinates, f), &dt);
      ForwardKinematics(fitted, gf, coordinates[t].row(f).transpose(), &df);
      const Eigen::Vector3d d = 1000.0 * (JointCentre(fitted, df, j) - JointCentre(truth, dt, j));
      parent.push_back(dt.segment_rotation[joint.parent].transpose() * d);
      child.push_back(dt.segment_rotation[joint.child].transpose() * d);
      Eigen::VectorXd a(na);
      for (size_t e = 0; e < na; ++e) a[e] = d.dot((dt.element_rotation[j][e] * gt.axis[j][e]).normalized());
      along.push_back(a);
    }
  auto split = [](const auto& v, auto* mean, double* rest) {
    *mean = v[0] * 0.0;
    for (const auto& x : v) *mean += x;
    *mean /= static_cast<double>(v.size());
    double sq = 0;
    for (const auto& x : v) sq += (x - *mean).squaredNorm();
    *rest = std::sqrt(sq / static_cast<double>(v.size()));
  };
  Eigen::Vector3d mp, mc;
  Eigen::VectorXd ma;
  double rp = 0, rc = 0, ra = 0;
  split(parent, &mp, &rp);
  split(child, &mc, &rc);
  split(along, &ma, &ra);
  char buf[512];
  std::snprintf(buf, sizeof(buf),
                "%s: lab error mean in %s frame (%.1f, %.1f, %.1f) |%.1f| mm, varying RMS %.1f mm; "
                "in %s frame (%.1f, %.1f, %.1f) |%.1f| mm, varying RMS %.1f mm; along the axes:",
                joint.name.c_str(), truth.segments()[joint.parent].name.c_str(), mp.x(), mp.y(), mp.z(),
                mp.norm(), rp, truth.segments()[joint.child].name.c_str(), mc.x(), mc.y(), mc.z(),
                mc.norm(), rc);
  std::string out = buf;
  for (size_t e = 0; e < na; ++e) {
    double sq = 0;
    for (const auto& a : along) sq += (a[e] - ma[e]) * (a[e] - ma[e]);
    std::snprintf(buf, sizeof(buf), " %s mean %.1f varying %.1f mm;",
                  joint.elements[e].coordinate >= 0
                      ? truth.coordinates()[joint.elements[e].coordinate].name.c_str()
                      : "fixed",
                  ma[e], std::sqrt(sq / static_cast<double>(along.size())));
    out += buf;
  }
  return out;
}

}  // namespace

int main(int argc, char** argv) {
  const Args args = ParseArgs(argc, argv);
  std::printf("| --sta-mm | joint centre in the lab, worst RMS (mm) | joint centre in its segment, "
              "worst (mm) | axis, worst determined (deg) | segment length, worst (%%) | marker RMS "
              "(mm) | fit (s) |\n|---|---|---|---|---|---|---|\n");
  std::vector<std::string> details;
  for (double sta : args.sta_mm) {
    sim::SimulationOptions options;
    options.seed = args.seed;
    options.noise_mm = args.noise_mm;
    options.sta_mm = sta;
    sim::SimulatedSession session;
    if (Status s = sim::SimulateSession(options, &session); !s) {
      std::fprintf(stderr, "sta_accuracy: --sta %g: %s\n", sta, s.message().c_str());
      return 1;
    }
    std::vector<solver::FitTrial> trials;
    for (const sim::SimulatedTrial& t : session.trials) {
      solver::FitTrial ft{t.markers, {}};
      for (const std::string& name : args.drop) {
        auto& names = ft.markers.marker_names;
        const auto it = std::find(names.begin(), names.end(), name);
        if (it == names.end()) continue;
        ft.markers.positions.middleCols(3 * (it - names.begin()), 3).setConstant(std::nan(""));
      }
      if (args.truth_start) {
        ft.initial_coordinates.resize(t.markers.num_frames(), session.nominal.num_coordinates());
        for (int f = 0; f < t.markers.num_frames(); ++f)
          ft.initial_coordinates.row(f) = sim::TrueCoordinates(session.nominal, t.coordinates, f).transpose();
      }
      trials.push_back(std::move(ft));
    }
    solver::FitOptions fit_options;
    fit_options.num_threads = args.threads;
    if (args.sigma_rounds >= 0) fit_options.marker_sigma_rounds = args.sigma_rounds;
    if (args.single_stage) fit_options.staged = false;
    fit_options.robust_loss = args.robust;
    fit_options.robust_scale = args.robust_scale;
    fit_options.fixed_parameters = args.hold;
    solver::FitResult fit;
    if (Status s = solver::FitModel(session.nominal, trials, fit_options, &fit); !s) {
      std::fprintf(stderr, "sta_accuracy: --sta %g: %s\n", sta, s.message().c_str());
      return 1;
    }
    ModelComparison cmp;
    if (Status s = CompareModels(session.truth, fit.model, &cmp); !s) {
      std::fprintf(stderr, "sta_accuracy: %s\n", s.message().c_str());
      return 1;
    }
    const std::vector<double> lab = sim::JointCentreTrackRmsMm(session, fit.model, fit.coordinates);
    int worst_lab = 1;
    for (int j = 1; j < static_cast<int>(lab.size()); ++j)
      if (lab[j] > lab[worst_lab]) worst_lab = j;
    std::string centre_joint, axis_joint, length_segment;
    double centre = 0, axis = 0, length = 0;
    for (const JointDifference& jd : cmp.joints) {
      if (jd.centre_error_mm > centre) centre = jd.centre_error_mm, centre_joint = jd.joint;
      for (size_t k = 0; k < jd.axes.size(); ++k)
        if (AxisDetermined(fit.report, jd.joint, k) && jd.axes[k].error_deg > axis)
          axis = jd.axes[k].error_deg, axis_joint = jd.joint;
    }
    for (const SegmentDifference& sd : cmp.segments)
      if (std::abs(sd.error_pct) > length) length = std::abs(sd.error_pct), length_segment = sd.name;
    std::printf("| %g | %.1f (%s) | %.1f (%s) | %.2f (%s) | %.2f (%s) | %.2f | %.0f |\n", sta,
                lab[worst_lab], session.truth.joints()[worst_lab].name.c_str(), centre,
                centre_joint.c_str(), axis, axis_joint.c_str(), length, length_segment.c_str(),
                fit.report.marker_rms_mm, fit.report.wall_seconds);
    std::fflush(stdout);
    if (!args.diagnose.empty()) {
      const int j = session.truth.FindJoint(args.diagnose);
      if (j <= 0) {
        std::fprintf(stderr, "sta_accuracy: --diagnose: no non-root joint '%s'\n", args.diagnose.c_str());
        return 2;
      }
      std::string stds = "; fitted centre std (mm):";
      for (const solver::ParameterEstimate& e : fit.report.parameters)
        if (e.name.rfind(args.diagnose + ".centre.", 0) == 0)
          stds += " " + e.name.substr(e.name.size() - 1) + " " + std::to_string(1000.0 * e.std);
      details.push_back("--sta-mm " + std::to_string(sta) + ", " +
                        DiagnoseJoint(session, fit.model, fit.coordinates, j) + stds);
    }
    if (args.joints) {
      std::string line = "--sta-mm " + std::to_string(sta) + ", lab RMS (mm):";
      char one[64];
      for (int j = 1; j < static_cast<int>(lab.size()); ++j) {
        std::snprintf(one, sizeof(one), " %s %.1f", session.truth.joints()[j].name.c_str(), lab[j]);
        line += one;
      }
      details.push_back(line);
      line = "--sta-mm " + std::to_string(sta) + ", marker residual RMS (mm) / sigma (mm):";
      for (size_t m = 0; m < fit.report.per_marker_rms_mm.size(); ++m) {
        std::snprintf(one, sizeof(one), " %s %.1f/%.1f", fit.report.per_marker_rms_mm[m].first.c_str(),
                      fit.report.per_marker_rms_mm[m].second, fit.report.marker_sigma_mm[m].second);
        line += one;
      }
      details.push_back(line);
    }
  }
  for (const std::string& d : details) std::printf("\n%s\n", d.c_str());
  return 0;
}
