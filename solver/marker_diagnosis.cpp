#include "solver/marker_diagnosis.h"

#include <algorithm>
#include <cmath>
#include <cstdio>

#include "model/kinematics.h"
#include "solver/attach_markers.h"
#include "solver/inverse_kinematics.h"

namespace mocap::solver {

bool MarkerDiagnosisOptions::IsValid(std::string* error) const {
  auto fail = [&](const char* what) {
    if (error) *error = what;
    return false;
  };
  if (!(bad_ratio > 1) || !(bad_min_mm >= 0)) return fail("bad_ratio must be > 1, bad_min_mm >= 0");
  if (min_stretch_frames < 2 || stretch_gap_frames < 0)
    return fail("min_stretch_frames must be >= 2, stretch_gap_frames >= 0");
  if (!(max_stretch_fraction > 0 && max_stretch_fraction < 1))
    return fail("max_stretch_fraction must be in (0, 1)");
  if (!(swap_ratio > 0 && swap_ratio < 1) || !(swap_max_mm > 0))
    return fail("swap_ratio must be in (0, 1), swap_max_mm > 0");
  if (!(wrong_body_max_spread_mm > 0) || !(wrong_body_ratio > 1))
    return fail("wrong_body_max_spread_mm must be > 0, wrong_body_ratio > 1");
  if (!(jump_ratio > 1) || !(jump_min_mm > 0)) return fail("jump_ratio must be > 1, jump_min_mm > 0");
  return true;
}

const char* ToString(MarkerDiagnosis::Kind kind) {
  switch (kind) {
    case MarkerDiagnosis::Kind::kStretch: return "mislabelled stretch";
    case MarkerDiagnosis::Kind::kSwap: return "swapped";
    case MarkerDiagnosis::Kind::kWrongBody: return "wrong body";
    case MarkerDiagnosis::Kind::kMoves: return "moves";
  }
  return "?";
}

namespace {

// One frame where the marker is seen: its distance from its own fitted place and from every
// marker's (m), in metres.
struct Sample {
  int trial = 0, frame = 0;
  double own = 0;
  Eigen::Vector3d x = Eigen::Vector3d::Zero();  // the measurement
};

double Median(std::vector<double> v) {
  if (v.empty()) return 0;
  std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
  return v[v.size() / 2];
}

// The marker (other than `self`) whose fitted place the samples `rows` of `dist` (samples x
// markers, m) lie closest to, and that RMS distance; -1 if none.
int ClosestOther(const Eigen::MatrixXd& dist, const std::vector<int>& rows, int self, double* rms) {
  int best = -1;
  *rms = 0;
  if (rows.empty()) return -1;
  for (int k = 0; k < dist.cols(); ++k) {
    if (k == self) continue;
    double sum = 0;
    for (int r : rows) sum += dist(r, k) * dist(r, k);
    const double v = std::sqrt(sum / rows.size());
    if (best < 0 || v < *rms) best = k, *rms = v;
  }
  return best;
}

// The fit's poses, re-solved per frame without the markers far off in that frame. A least-squares
// fit spreads a bad marker's error over its neighbours' poses (a swapped thigh marker turns the
// thigh), so measured against the fit's own poses every marker of the limb looks a little bad
// and the bad one less bad than it is. With the frame's worst markers left out (those above
// `ratio` x the frame's median residual and median + `min_m`, twice), the pose is the other
// markers', and the left-out marker's residual is its own.
Status TrimmedPoses(const Model& model, const std::vector<formats::MarkerTrial>& trials,
                    const std::vector<Eigen::MatrixXd>& poses, double ratio, double min_m,
                    std::vector<Eigen::MatrixXd>* out) {
  const int nm = static_cast<int>(model.markers().size());
  const Geometry geometry(model);
  ModelData data(model);
  InverseKinematics ik(model, geometry);
  Eigen::Matrix3Xd measured(3, nm), places;
  std::vector<double> r(nm), seen;
  out->resize(trials.size());
  for (size_t t = 0; t < trials.size(); ++t) {
    const formats::MarkerTrial& trial = trials[t];
    std::vector<int> column(nm);
    for (int m = 0; m < nm; ++m) column[m] = trial.FindMarker(model.markers()[m].name);
    Eigen::MatrixXd& z_out = (*out)[t];
    z_out = poses[t];
    for (int f = 0; f < trial.num_frames(); ++f) {
      if (!poses[t].row(f).allFinite()) continue;
      for (int m = 0; m < nm; ++m) {
        if (column[m] >= 0) measured.col(m) = trial.positions.row(f).segment<3>(3 * column[m]).transpose();
        else measured.col(m).setConstant(std::nan(""));
      }
      Eigen::VectorXd z = poses[t].row(f).transpose();
      for (int round = 0; round < 2; ++round) {
        ForwardKinematics(model, geometry, z, &data);
        MarkerPositions(model, geometry, data, &places);
        seen.clear();
        for (int m = 0; m < nm; ++m) {
          r[m] = measured.col(m).allFinite() ? (measured.col(m) - places.col(m)).norm() : -1;
          if (r[m] >= 0) seen.push_back(r[m]);
        }
        if (seen.size() < 4) break;
        const double median = Median(seen);
        const double limit = std::max(ratio * median, median + min_m);
        int dropped = 0;
        for (int m = 0; m < nm; ++m)
          if (r[m] > limit) measured.col(m).setConstant(std::nan("")), ++dropped;
        if (dropped == 0 || static_cast<int>(seen.size()) - dropped < 4) break;
        Eigen::VectorXd trial_z = z;
        ik.Solve(measured, &trial_z);
        if (!trial_z.allFinite()) break;
        z = trial_z;
      }
      z_out.row(f) = z.transpose();
    }
  }
  return Status::Ok();
}

// The samples [*begin, *end] of a stretch the marker's data jump into and out of (a step between
// consecutive frames above options.jump_ratio x the median step and options.jump_min_mm):
// between two jumps, the piece with the highest residual RMS; failing that, between a jump and
// its trial's start or end, the shorter side (the mislabelled part is the exception). Not the
// residual alone: a least-squares fit bent towards the wrong data can leave the right frames the
// worse-fitting ones. Pieces outside [min_stretch_frames, max_stretch_fraction x samples] are
// not stretches.
bool JumpStretch(const std::vector<Sample>& S, const std::vector<double>& own,
                 const MarkerDiagnosisOptions& options, int* begin, int* end) {
  const int n = static_cast<int>(S.size());
  std::vector<double> steps;
  for (int i = 1; i < n; ++i)
    if (S[i].trial == S[i - 1].trial && S[i].frame == S[i - 1].frame + 1)
      steps.push_back((S[i].x - S[i - 1].x).norm());
  if (steps.size() < 10) return false;
  const double limit = std::max(options.jump_ratio * Median(steps), 1e-3 * options.jump_min_mm);
  // Pieces: [start, next start); each start is the first sample, a new trial, or a jump.
  std::vector<int> starts{0};
  std::vector<char> after_jump{0};
  for (int i = 1; i < n; ++i) {
    const bool new_trial = S[i].trial != S[i - 1].trial;
    const bool jump = !new_trial && S[i].frame == S[i - 1].frame + 1 &&
                      (S[i].x - S[i - 1].x).norm() > limit;
    if (new_trial || jump) starts.push_back(i), after_jump.push_back(jump);
  }
  starts.push_back(n);
  after_jump.push_back(0);
  double best_rms = -1;
  int best_end_len = n + 1;
  bool interior = false;
  for (std::size_t p = 0; p + 1 < starts.size(); ++p) {
    const bool in_jump = after_jump[p], out_jump = after_jump[p + 1];
    if (!in_jump && !out_jump) continue;
    const int b = starts[p], e = starts[p + 1] - 1, len = e - b + 1;
    if (len < options.min_stretch_frames || len > options.max_stretch_fraction * n) continue;
    if (in_jump && out_jump) {
      double sq = 0;
      for (int i = b; i <= e; ++i) sq += own[i] * own[i];
      const double rms = std::sqrt(sq / len);
      if (!interior || rms > best_rms) best_rms = rms, *begin = b, *end = e;
      interior = true;
    } else if (!interior && len < best_end_len) {
      best_end_len = len, *begin = b, *end = e;
    }
  }
  return interior || best_end_len <= n;
}

}  // namespace

Status DiagnoseMarkers(const Model& model, const std::vector<formats::MarkerTrial>& trials,
                       const std::vector<Eigen::MatrixXd>& poses,
                       const std::vector<std::pair<std::string, double>>& outliers,
                       const MarkerDiagnosisOptions& options, std::vector<MarkerDiagnosis>* out) {
  out->clear();
  std::string why;
  if (!options.IsValid(&why)) return Status::Error("marker diagnosis: " + why);
  if (poses.size() != trials.size())
    return Status::Error("marker diagnosis: " + std::to_string(poses.size()) + " pose tables for " +
                         std::to_string(trials.size()) + " trials");
  std::vector<int> markers;
  std::vector<double> rms;
  std::vector<std::string> names;
  for (const auto& [name, r] : outliers)
    if (const int m = model.FindMarker(name); m >= 0) {
      markers.push_back(m);
      rms.push_back(r);
      names.push_back(name);
    }
  if (markers.empty()) return Status::Ok();
  for (size_t t = 0; t < trials.size(); ++t)
    if (poses[t].rows() != trials[t].num_frames() || poses[t].cols() != model.num_coordinates())
      return Status::Error("marker diagnosis: trial '" + trials[t].name + "': poses are " +
                           std::to_string(poses[t].rows()) + "x" + std::to_string(poses[t].cols()));
  std::vector<Eigen::MatrixXd> trimmed;
  MOCAP_RETURN_IF_ERROR(TrimmedPoses(model, trials, poses, options.bad_ratio,
                                     1e-3 * options.bad_min_mm, &trimmed));
  const int nm = static_cast<int>(model.markers().size());
  const int no = static_cast<int>(markers.size());

  // Every frame's fitted marker places, once for all the outliers.
  std::vector<std::vector<Sample>> samples(no);
  std::vector<std::vector<double>> distances(no);  // per outlier: samples x nm, row-major
  const Geometry geometry(model);
  ModelData data(model);
  Eigen::Matrix3Xd places;
  for (size_t t = 0; t < trials.size(); ++t) {
    const formats::MarkerTrial& trial = trials[t];
    std::vector<int> column(no);
    bool any = false;
    for (int o = 0; o < no; ++o) any |= (column[o] = trial.FindMarker(names[o])) >= 0;
    if (!any) continue;
    for (int f = 0; f < trial.num_frames(); ++f) {
      if (!trimmed[t].row(f).allFinite()) continue;
      bool seen = false;
      for (int o = 0; o < no; ++o)
        seen |= column[o] >= 0 && trial.positions.row(f).segment<3>(3 * column[o]).allFinite();
      if (!seen) continue;
      ForwardKinematics(model, geometry, trimmed[t].row(f).transpose(), &data);
      MarkerPositions(model, geometry, data, &places);
      for (int o = 0; o < no; ++o) {
        if (column[o] < 0) continue;
        const Eigen::Vector3d x = trial.positions.row(f).segment<3>(3 * column[o]).transpose();
        if (!x.allFinite()) continue;
        Sample s;
        s.trial = static_cast<int>(t);
        s.frame = f;
        s.own = (x - places.col(markers[o])).norm();
        s.x = x;
        samples[o].push_back(s);
        for (int k = 0; k < nm; ++k) distances[o].push_back((x - places.col(k)).norm());
      }
    }
  }

  std::vector<MarkerOnSegments> spreads;
  MOCAP_RETURN_IF_ERROR(MarkerSpreadOnSegments(model, trials, trimmed, names, &spreads));

  for (int o = 0; o < no; ++o) {
    const std::vector<Sample>& S = samples[o];
    if (S.empty()) continue;
    const int m = markers[o];
    const int n = static_cast<int>(S.size());
    const Eigen::Map<const Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>> dist(
        distances[o].data(), n, nm);
    MarkerDiagnosis d;
    d.marker = names[o];
    d.rms_mm = rms[o];
    const int seg = model.markers()[m].segment;
    d.segment = model.segments()[seg].name;
    const MarkerOnSegments& sp = spreads[o];
    int best = seg;
    for (int k = 0; k < static_cast<int>(sp.spread_mm.size()); ++k)
      if (sp.spread_mm[k] < sp.spread_mm[best]) best = k;
    d.rides_on = model.segments()[best].name;
    d.spread_on_segment_mm = sp.spread_mm.empty() ? 0 : sp.spread_mm[seg];
    d.spread_on_best_mm = sp.spread_mm.empty() ? 0 : sp.spread_mm[best];
    char text[400];
    // Steadier on another segment, though not steady enough to call it the wrong body: said with
    // whatever the diagnosis is (a least-squares fit bends the joint towards a marker on the wrong
    // body, which then also passes for a stretch).
    const bool steadier_elsewhere =
        best != seg && d.spread_on_segment_mm > options.wrong_body_ratio * d.spread_on_best_mm;
    auto finish = [&] {
      d.text = text;
      if (steadier_elsewhere && d.kind != MarkerDiagnosis::Kind::kWrongBody) {
        char more[200];
        std::snprintf(more, sizeof more, "; it rides on %s (%.1f mm) better than on %s (%.1f mm), "
                      "where the model attaches it", d.rides_on.c_str(), d.spread_on_best_mm,
                      d.segment.c_str(), d.spread_on_segment_mm);
        d.text += more;
      }
      out->push_back(d);
    };

    // The wrong body first: its error grows with the joint angle between the two segments, so on
    // a trial with a few large flexions it also looks like a stretch.
    if (best != seg && d.spread_on_best_mm < options.wrong_body_max_spread_mm &&
        d.spread_on_segment_mm > options.wrong_body_ratio * d.spread_on_best_mm) {
      d.kind = MarkerDiagnosis::Kind::kWrongBody;
      std::snprintf(text, sizeof text,
                    "%s %.1f mm: rides on %s (%.1f mm RMS in its frame), not on %s (%.1f mm), "
                    "where the model attaches it: attached to the wrong body?",
                    d.marker.c_str(), d.rms_mm, d.rides_on.c_str(), d.spread_on_best_mm,
                    d.segment.c_str(), d.spread_on_segment_mm);
      finish();
      continue;
    }

    // 1. A stretch of bad frames (runs within one trial, in frame order; short gaps bridged).
    std::vector<double> own(n);
    for (int i = 0; i < n; ++i) own[i] = S[i].own;
    const double median = Median(own);
    const double limit = std::max(options.bad_ratio * median, median + 1e-3 * options.bad_min_mm);
    int total_bad = 0;
    int run_begin = -1, run_end = -1, run_bad = 0;      // the current run: samples [begin, end]
    int best_begin = -1, best_end = -1, best_bad = 0;  // the longest run
    auto close_run = [&] {
      if (run_begin >= 0 && run_bad >= options.min_stretch_frames) {
        total_bad += run_bad;
        if (run_bad > best_bad) best_begin = run_begin, best_end = run_end, best_bad = run_bad;
      }
      run_begin = -1, run_bad = 0;
    };
    for (int i = 0; i < n; ++i) {
      if (run_begin >= 0 && (S[i].trial != S[run_end].trial ||
                             S[i].frame - S[run_end].frame > options.stretch_gap_frames + 1))
        close_run();
      if (own[i] <= limit) continue;
      if (run_begin < 0) run_begin = i;
      run_end = i;
      ++run_bad;
    }
    close_run();
    // A label that moved to another marker and back jumps in the data itself, whatever the fit
    // made of it: a least-squares fit bent towards the wrong data has its worst frames elsewhere
    // (where the bend shows), so when the marker's trajectory has jumps, the stretch is the
    // stretch between two of them (or a trial's end) whose residual is the highest.
    if (int jb = -1, je = -1; JumpStretch(S, own, options, &jb, &je)) {
      best_begin = jb, best_end = je;
      best_bad = total_bad = je - jb + 1;
    }
    if (best_bad > 0 && total_bad <= options.max_stretch_fraction * n) {
      d.kind = MarkerDiagnosis::Kind::kStretch;
      d.trial = trials[S[best_begin].trial].name;
      d.first_frame = S[best_begin].frame;
      d.last_frame = S[best_end].frame;
      std::vector<int> inside;
      double in_sq = 0, out_sq = 0;
      for (int i = 0; i < n; ++i) {
        if (i >= best_begin && i <= best_end) inside.push_back(i), in_sq += own[i] * own[i];
        else out_sq += own[i] * own[i];
      }
      d.stretch_rms_mm = 1000.0 * std::sqrt(in_sq / inside.size());
      d.elsewhere_rms_mm = 1000.0 * std::sqrt(out_sq / std::max<std::size_t>(1, n - inside.size()));
      double other_rms = 0;
      const int other = ClosestOther(dist, inside, m, &other_rms);
      if (other >= 0 && 1000.0 * other_rms < options.swap_ratio * d.stretch_rms_mm &&
          1000.0 * other_rms < options.swap_max_mm)
        d.other_marker = model.markers()[other].name;
      // The whole of one trial: the marker was moved (re-applied) between trials, or that trial's
      // label is another marker's.
      int trial_first = -1, trial_last = -1;
      for (int i = 0; i < n; ++i)
        if (S[i].trial == S[best_begin].trial) {
          if (trial_first < 0) trial_first = S[i].frame;
          trial_last = S[i].frame;
        }
      const bool whole_trial = trial_first == d.first_frame && trial_last == d.last_frame;
      if (whole_trial)
        std::snprintf(text, sizeof text,
                      "%s %.1f mm: off in trial '%s' alone, all its frames (%.1f mm there, %.1f mm "
                      "elsewhere): moved between trials, or another marker's label there?%s%s%s",
                      d.marker.c_str(), d.rms_mm, d.trial.c_str(), d.stretch_rms_mm, d.elsewhere_rms_mm,
                      d.other_marker.empty() ? "" : " It lies at ", d.other_marker.c_str(),
                      d.other_marker.empty() ? "" : "'s place");
      else
      std::snprintf(text, sizeof text,
                    "%s %.1f mm: mislabelled in trial '%s', frames %d-%d (%.1f mm there, %.1f mm "
                    "elsewhere)%s%s%s",
                    d.marker.c_str(), d.rms_mm, d.trial.c_str(), d.first_frame, d.last_frame,
                    d.stretch_rms_mm, d.elsewhere_rms_mm,
                    d.other_marker.empty() ? "" : "; there it lies at ", d.other_marker.c_str(),
                    d.other_marker.empty() ? "" : "'s place");
      finish();
      continue;
    }

    // 2. A swap: throughout, at another marker's place.
    std::vector<int> all(n);
    for (int i = 0; i < n; ++i) all[i] = i;
    double own_sq = 0;
    for (double v : own) own_sq += v * v;
    const double own_rms_mm = 1000.0 * std::sqrt(own_sq / n);
    double other_rms = 0;
    const int other = ClosestOther(dist, all, m, &other_rms);
    if (other >= 0 && 1000.0 * other_rms < options.swap_ratio * own_rms_mm &&
        1000.0 * other_rms < options.swap_max_mm) {
      d.kind = MarkerDiagnosis::Kind::kSwap;
      d.other_marker = model.markers()[other].name;
      std::snprintf(text, sizeof text,
                    "%s %.1f mm: follows %s's place throughout (%.1f mm from it, %.1f mm from its "
                    "own): swapped with %s?",
                    d.marker.c_str(), d.rms_mm, d.other_marker.c_str(), 1000.0 * other_rms,
                    own_rms_mm, d.other_marker.c_str());
      finish();
      continue;
    }

    // 4. It moves.
    d.kind = MarkerDiagnosis::Kind::kMoves;
    std::snprintf(text, sizeof text,
                  "%s %.1f mm: moves %.1f mm RMS on %s, its segment: slipping, loose, or soft "
                  "tissue (weight it by its spread, or leave it out)?",
                  d.marker.c_str(), d.rms_mm, d.spread_on_segment_mm, d.segment.c_str());
    finish();
  }
  return Status::Ok();
}

}  // namespace mocap::solver
