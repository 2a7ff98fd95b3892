#include "reconstruction/calibration.h"


#include <Eigen/Dense>
#include <algorithm>
#include <limits>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <functional>
#include <memory>
#include <numeric>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>
#include <sstream>

#include "model/rigid_align.h"
#include "reconstruction/calibration_problem.h"
#include "reconstruction/triangulation.h"
#include "solver/schur_solver.h"

namespace mocap::reconstruction {

namespace {

using Clock = std::chrono::steady_clock;

std::string Fmt(const char* format, double a) {
  char buf[64];
  std::snprintf(buf, sizeof(buf), format, a);
  return buf;
}

}  // namespace

bool Wand::IsValid(std::string* error) const {
  auto fail = [&](const std::string& what) {
    if (error) *error = "wand: " + what;
    return false;
  };
  if (marker_positions_m.size() != 3) return fail("needs exactly 3 markers");
  for (double v : marker_positions_m)
    if (!std::isfinite(v)) return fail("a marker position is not finite");
  if (!(marker_positions_m[0] < marker_positions_m[1] &&
        marker_positions_m[1] < marker_positions_m[2]))
    return fail("marker positions must increase along the wand");
  if (!(length_m() > 0.05 && length_m() < 5.0)) return fail("length must be in (0.05, 5) m");
  const double r = middle_ratio();
  if (std::abs(r - 0.5) < 0.05)
    return fail("the middle marker must be off-centre (spacing ratio " + Fmt("%.3f", r) +
                " is too close to 0.5: the wand would have no direction)");
  return true;
}

bool LFrame::IsValid(std::string* error) const {
  auto fail = [&](const std::string& what) {
    if (error) *error = "L-frame: " + what;
    return false;
  };
  if (markers_m.size() < 3 || markers_m.size() > 6) return fail("needs 3 to 6 markers");
  for (const auto& m : markers_m)
    if (!m.allFinite()) return fail("a marker position is not finite");
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  for (const auto& m : markers_m) mean += m;
  mean /= static_cast<double>(markers_m.size());
  Eigen::Matrix3d scatter = Eigen::Matrix3d::Zero();
  for (const auto& m : markers_m) scatter += (m - mean) * (m - mean).transpose();
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(scatter);
  if (!(es.eigenvalues()[1] > 1e-4)) return fail("markers are collinear: they define no plane");
  for (size_t i = 0; i < markers_m.size(); ++i)
    for (size_t j = i + 1; j < markers_m.size(); ++j)
      if ((markers_m[i] - markers_m[j]).norm() < 0.02)
        return fail("markers " + std::to_string(i) + " and " + std::to_string(j) +
                    " are closer than 20 mm");
  return true;
}

bool WandIdentificationOptions::IsValid(std::string* error) const {
  if (!(collinearity_px > 0) || !(ratio_tolerance > 0 && ratio_tolerance < 0.2) ||
      !(min_separation_px >= 0)) {
    if (error)
      *error =
          "wand identification: need collinearity_px > 0, ratio_tolerance in (0, 0.2), "
          "min_separation_px >= 0";
    return false;
  }
  return true;
}

bool WandCalibrationOptions::IsValid(std::string* error) const {
  if (!wand.IsValid(error) || !lframe.IsValid(error) || !identification.IsValid(error))
    return false;
  auto fail = [&](const char* what) {
    if (error) *error = std::string("wand calibration: ") + what;
    return false;
  };
  if (std::abs(wand.middle_ratio() - 0.5) <= identification.ratio_tolerance)
    return fail("ratio_tolerance must be below |middle ratio - 0.5| (the wand's direction)");
  if (min_shared_frames < 3) return fail("min_shared_frames must be >= 3");
  if (!(ransac_threshold_px > 0)) return fail("ransac_threshold_px must be > 0");
  if (!(outlier_min_px > 0) || !(outlier_sigmas > 0))
    return fail("outlier_min_px and outlier_sigmas must be > 0");
  std::string lm_error;
  if (!lm.IsValid(&lm_error)) {
    if (error) *error = "wand calibration: lm: " + lm_error;
    return false;
  }
  return true;
}

bool IdentifyWand(const std::vector<Centroid>& centroids, const Wand& wand,
                  const WandIdentificationOptions& options, std::vector<Eigen::Vector2d>* markers) {
  const int n = static_cast<int>(centroids.size());
  const double rho = wand.middle_ratio();
  int matches = 0;
  Eigen::Vector2d found[3];
  for (int i = 0; i < n; ++i) {
    for (int j = i + 1; j < n; ++j) {
      const Eigen::Vector2d a = centroids[i].pixel, b = centroids[j].pixel;
      const Eigen::Vector2d ab = b - a;
      const double len = ab.norm();
      if (!(len > 2 * options.min_separation_px)) continue;
      const Eigen::Vector2d u = ab / len;
      for (int k = 0; k < n; ++k) {
        if (k == i || k == j) continue;
        const Eigen::Vector2d ak = centroids[k].pixel - a;
        const double along = ak.dot(u);
        const double across = std::abs(u.x() * ak.y() - u.y() * ak.x());
        if (across > options.collinearity_px) continue;
        const double tau = along / len;
        if (along < options.min_separation_px || len - along < options.min_separation_px) continue;
        if (std::abs(tau - rho) < options.ratio_tolerance) {
          found[0] = a, found[1] = centroids[k].pixel, found[2] = b;
          ++matches;
        } else if (std::abs((1.0 - tau) - rho) < options.ratio_tolerance) {
          found[0] = b, found[1] = centroids[k].pixel, found[2] = a;
          ++matches;
        }
      }
    }
  }
  if (matches != 1) return false;
  markers->assign(found, found + 3);
  return true;
}

bool TriangulatePoint(const std::vector<const CameraModel*>& cameras,
                      const std::vector<Eigen::Vector2d>& pixels, Eigen::Vector3d* point) {
  const int n = static_cast<int>(cameras.size());
  if (n < 2 || pixels.size() != cameras.size()) return false;
  // The rig's triangulation (reconstruction/triangulation.h): linear, then refined on the pixel
  // reprojection error, every view weighted alike.
  std::vector<CameraModel> views;
  std::vector<PointObservation> observations;
  views.reserve(n);
  observations.reserve(n);
  for (int i = 0; i < n; ++i) {
    views.push_back(*cameras[i]);
    observations.push_back({i, pixels[i], 1.0});
  }
  Eigen::Vector3d x;
  double residual_px = 0;
  if (!TriangulateLinear(views, observations, &x) ||
      !RefinePosition(views, observations, 10, &x, &residual_px))
    return false;
  for (int i = 0; i < n; ++i)
    if (!(cameras[i]->ToCamera(x).z() > 0)) return false;
  *point = x;
  return x.allFinite();
}

void CameraPoseError(const CameraModel& estimated, const CameraModel& truth, double* position_m,
                     double* angle_rad) {
  *position_m = (estimated.centre() - truth.centre()).norm();
  const Eigen::AngleAxisd aa(Eigen::Matrix3d(estimated.R * truth.R.transpose()));
  *angle_rad = std::abs(aa.angle());
}

namespace {

// The rigid transform (Q, q) minimising sum |Q a_i + q - b_i|^2 (model/rigid_align.h) and its
// RMS residual; infinite when the points cannot fix it (fewer than 3, or collinear).
double RigidAlign(const std::vector<Eigen::Vector3d>& a, const std::vector<Eigen::Vector3d>& b,
                  Eigen::Matrix3d* q_rot, Eigen::Vector3d* q_trans) {
  const int n = static_cast<int>(a.size());
  Eigen::Matrix3Xd src(3, n), dst(3, n);
  for (int i = 0; i < n; ++i) src.col(i) = a[i], dst.col(i) = b[i];
  const std::optional<RigidTransform> fit = mocap::RigidAlign(src, dst);
  if (!fit) return std::numeric_limits<double>::infinity();
  *q_rot = fit->rotation;
  *q_trans = fit->translation;
  return std::sqrt(((fit->rotation * src).colwise() + fit->translation - dst).squaredNorm() / n);
}

// Relative pose of camera b to camera a (X_b = R X_a + t, |t| = baseline in metres) from the
// wand frames both saw. False with *why set if it cannot be determined.
bool PairPose(const CameraModel& ca, const CameraModel& cb,
              const std::vector<std::array<Eigen::Vector2d, 3>>& xa,
              const std::vector<std::array<Eigen::Vector2d, 3>>& xb, const Wand& wand,
              double ransac_threshold_px, Eigen::Matrix3d* r, Eigen::Vector3d* t,
              std::string* why) {
  std::vector<cv::Point2d> pa, pb;
  for (size_t f = 0; f < xa.size(); ++f)
    for (int k = 0; k < 3; ++k) {
      pa.emplace_back(xa[f][k].x(), xa[f][k].y());
      pb.emplace_back(xb[f][k].x(), xb[f][k].y());
    }
  const double focal =
      0.25 * (ca.intrinsics.fx + ca.intrinsics.fy + cb.intrinsics.fx + cb.intrinsics.fy);
  cv::Mat mask;
  cv::Mat e = cv::findEssentialMat(pa, pb, 1.0, cv::Point2d(0, 0), cv::RANSAC, 0.9999,
                                   ransac_threshold_px / focal, mask);
  if (e.rows < 3 || e.cols != 3) {
    *why = "no essential matrix";
    return false;
  }
  e = e.rowRange(0, 3).clone();
  cv::Mat rr, tt;
  const int inliers = cv::recoverPose(e, pa, pb, cv::Mat::eye(3, 3, CV_64F), rr, tt, mask);
  if (inliers < 8) {
    *why = "only " + std::to_string(inliers) + " correspondences in front of both cameras";
    return false;
  }
  Eigen::Matrix3d rot;
  Eigen::Vector3d tr;
  for (int i = 0; i < 3; ++i) {
    tr[i] = tt.at<double>(i);
    for (int j = 0; j < 3; ++j) rot(i, j) = rr.at<double>(i, j);
  }
  // Metric scale from the wand: triangulate its ends with a unit baseline.
  CameraModel ua, ub;  // ideal pinholes in normalised coordinates
  for (CameraModel* c : {&ua, &ub}) {
    c->intrinsics.width = c->intrinsics.height = 1;
    c->intrinsics.fx = c->intrinsics.fy = 1.0;
  }
  ub.R = rot;
  ub.t = tr;
  std::vector<double> lengths;
  for (size_t f = 0; f < xa.size(); ++f) {
    Eigen::Vector3d ends[2];
    bool ok = true;
    for (int e2 = 0; e2 < 2 && ok; ++e2) {
      const int k = e2 == 0 ? 0 : 2;
      ok = TriangulatePoint({&ua, &ub}, {xa[f][k], xb[f][k]}, &ends[e2]);
    }
    if (ok) lengths.push_back((ends[1] - ends[0]).norm());
  }
  if (lengths.size() < 3) {
    *why = "the wand could not be triangulated";
    return false;
  }
  std::nth_element(lengths.begin(), lengths.begin() + lengths.size() / 2, lengths.end());
  const double median = lengths[lengths.size() / 2];
  if (!(median > 0)) {
    *why = "degenerate wand triangulation";
    return false;
  }
  *r = rot;
  *t = tr * (wand.length_m() / median);
  return true;
}

// Averaged centroids of a static scene per camera: centroids of successive frames within
// `radius_px` of a cluster join it; clusters seen in at least half the frames are kept.
std::vector<Eigen::Vector2d> StaticCentroids(const std::vector<DetectionSet>& frames, int camera,
                                             double radius_px) {
  struct Cluster {
    Eigen::Vector2d sum = Eigen::Vector2d::Zero();
    int count = 0;
    Eigen::Vector2d mean() const { return sum / count; }
  };
  std::vector<Cluster> clusters;
  int present = 0;
  for (const DetectionSet& s : frames) {
    if (!s.present[camera]) continue;
    ++present;
    for (const Centroid& c : s.cameras[camera].centroids) {
      Cluster* best = nullptr;
      double best_d = radius_px;
      for (Cluster& cl : clusters) {
        const double d = (cl.mean() - c.pixel).norm();
        if (d < best_d) best_d = d, best = &cl;
      }
      if (!best) {
        clusters.emplace_back();
        best = &clusters.back();
      }
      best->sum += c.pixel;
      best->count += 1;
    }
  }
  std::vector<Eigen::Vector2d> out;
  for (const Cluster& cl : clusters)
    if (2 * cl.count >= present && present > 0) out.push_back(cl.mean());
  return out;
}

// Unlabelled 3D points of a static scene: every pair of centroids from two cameras is a
// candidate, supported by the other cameras' centroids that it reprojects onto; candidates seen
// by >= 3 cameras are kept, the best-supported one of any near-duplicates.
std::vector<Eigen::Vector3d> ReconstructStatic(const std::vector<CameraModel>& cams,
                                               const std::vector<std::vector<Eigen::Vector2d>>& pts,
                                               double tolerance_px) {
  struct Candidate {
    Eigen::Vector3d x;
    int support;
    double rms;
  };
  std::vector<Candidate> candidates;
  const int nc = static_cast<int>(cams.size());
  for (int a = 0; a < nc; ++a)
    for (int b = a + 1; b < nc; ++b)
      for (const Eigen::Vector2d& pa : pts[a])
        for (const Eigen::Vector2d& pb : pts[b]) {
          Eigen::Vector3d x;
          if (!TriangulatePoint({&cams[a], &cams[b]}, {pa, pb}, &x)) continue;
          std::vector<const CameraModel*> used;
          std::vector<Eigen::Vector2d> px;
          for (int c = 0; c < nc; ++c) {
            Eigen::Vector2d u;
            if (!cams[c].Project(x, &u)) continue;
            const Eigen::Vector2d* best = nullptr;
            double best_d = tolerance_px;
            for (const Eigen::Vector2d& p : pts[c]) {
              const double d = (p - u).norm();
              if (d < best_d) best_d = d, best = &p;
            }
            if (best) {
              used.push_back(&cams[c]);
              px.push_back(*best);
            }
          }
          if (used.size() < 3 || !TriangulatePoint(used, px, &x)) continue;
          double ss = 0;
          for (size_t i = 0; i < used.size(); ++i) {
            Eigen::Vector2d u;
            used[i]->Project(x, &u);
            ss += (u - px[i]).squaredNorm();
          }
          candidates.push_back({x, static_cast<int>(used.size()), std::sqrt(ss / used.size())});
        }
  std::sort(candidates.begin(), candidates.end(), [](const Candidate& l, const Candidate& r) {
    return l.support != r.support ? l.support > r.support : l.rms < r.rms;
  });
  std::vector<Eigen::Vector3d> points;
  for (const Candidate& c : candidates) {
    bool duplicate = false;
    for (const Eigen::Vector3d& p : points) duplicate = duplicate || (p - c.x).norm() < 0.01;
    if (!duplicate) points.push_back(c.x);
  }
  return points;
}

struct ObsStats {
  double sum_sq = 0;
  int markers = 0;
};

// Per-observation largest marker error and per-camera statistics at the problem's state x.
void ObservationErrors(WandBundleProblem& problem, const Eigen::VectorXd& x,
                       std::vector<std::vector<double>>* worst, std::vector<ObsStats>* per_camera) {
  const int nf = problem.num_frames();
  problem.SetShared(x.tail(problem.shared_dim()));
  per_camera->assign(problem.cameras().size(), ObsStats{});
  worst->assign(nf, {});
  for (int f = 0; f < nf; ++f) {
    const double* y = x.data() + 5 * f;
    const WandFrame& fr = problem.frames()[f];
    for (const WandObservation& o : fr.observations) {
      const CameraModel& cam = problem.cameras()[o.camera];
      double w = 0;
      for (int k = 0; k < 3; ++k) {
        Eigen::Vector2d u;
        cam.Project(problem.MarkerPosition(f, y, k), &u);
        const double e2 = (u - o.pixels[k]).squaredNorm();
        w = std::max(w, std::sqrt(e2));
        (*per_camera)[o.camera].sum_sq += e2;
        (*per_camera)[o.camera].markers += 1;
      }
      (*worst)[f].push_back(w);
    }
  }
}

double TotalRms(const std::vector<ObsStats>& s) {
  double ss = 0;
  int n = 0;
  for (const ObsStats& o : s) ss += o.sum_sq, n += o.markers;
  return n ? std::sqrt(ss / n) : 0.0;
}

}  // namespace

std::string WandCalibrationSummary::BriefReport() const {
  char buf[512];
  std::snprintf(
      buf, sizeof(buf),
      "Wand calibration: %s, %d cameras, %d/%d wand frames used, reprojection RMS %.4f px "
      "(initial %.2f px), wand length error RMS %.4f mm (mean %+.4f mm), lab frame: %s, "
      "%.2f s%s%s",
      termination == CalibrationTermination::kSuccess ? "SUCCESS" : "FAILURE",
      static_cast<int>(cameras.size()), wand_frames_used, wand_frames_total, reprojection_rms_px,
      initial_reprojection_rms_px, wand_length_error_mm_rms, wand_length_error_mm_mean,
      lab_frame_from_lframe ? "L-frame" : "camera 0", seconds, message.empty() ? "" : ": ",
      message.c_str());
  return buf;
}

std::string WandCalibrationSummary::FullReport() const {
  std::ostringstream os;
  os << BriefReport() << "\n";
  char buf[256];
  std::snprintf(buf, sizeof(buf),
                "  wand frames: %d given, %d identified in >= 2 cameras, %d used; %d observations, "
                "%d rejected as outliers\n",
                wand_frames_total, wand_frames_identified, wand_frames_used, observations,
                rejected_observations);
  os << buf;
  os << "  spanning tree (parent -> child: shared frames):";
  for (size_t e = 0; e < tree.size(); ++e)
    os << " " << tree[e].first << "->" << tree[e].second << ":" << tree_shared_frames[e];
  os << "\n  camera            frames  rejected  RMS(px)\n";
  for (const CameraCalibrationStats& c : cameras) {
    std::snprintf(buf, sizeof(buf), "  %-16s %7d %9d  %.4f\n", c.id.c_str(), c.wand_frames,
                  c.rejected, c.reprojection_rms_px);
    os << buf;
  }
  if (lab_frame_from_lframe) {
    std::snprintf(buf, sizeof(buf), "  L-frame residual after alignment: %.3f mm RMS\n",
                  lframe_residual_mm_rms);
    os << buf;
  }
  os << "  first solve: " << first_solve.BriefReport() << "\n";
  os << "  final solve: " << final_solve.BriefReport() << "\n";
  return os.str();
}

Status CalibrateWand(const std::vector<CameraModel>& cameras,
                     const std::vector<DetectionSet>& wand_frames,
                     const std::vector<DetectionSet>& lframe_frames,
                     const WandCalibrationOptions& options, std::vector<CameraModel>* calibrated,
                     WandCalibrationSummary* summary) {
  const auto start = Clock::now();
  *summary = WandCalibrationSummary{};
  auto fail = [&](const std::string& message) {
    summary->termination = CalibrationTermination::kFailure;
    summary->message = message;
    return Status::Error("wand calibration: " + message);
  };
  std::string error;
  if (!options.IsValid(&error)) return fail(error);
  const int nc = static_cast<int>(cameras.size());
  if (nc < 2) return fail("needs at least 2 cameras, got " + std::to_string(nc));
  for (int c = 0; c < nc; ++c) {
    if (!cameras[c].intrinsics.IsValid(&error))
      return fail("camera " + std::to_string(c) + " '" + cameras[c].id + "': " + error);
    for (int d = 0; d < c; ++d)
      if (cameras[d].id == cameras[c].id)
        return fail("cameras " + std::to_string(d) + " and " + std::to_string(c) +
                    " have the same id '" + cameras[c].id + "'");
  }
  auto check_sets = [&](const std::vector<DetectionSet>& sets, const char* what) -> std::string {
    for (size_t f = 0; f < sets.size(); ++f)
      if (sets[f].cameras.size() != static_cast<size_t>(nc) ||
          sets[f].present.size() != static_cast<size_t>(nc))
        return std::string(what) + " frame " + std::to_string(f) + " has " +
               std::to_string(sets[f].cameras.size()) + " camera entries, the rig has " +
               std::to_string(nc);
    return "";
  };
  if (std::string e = check_sets(wand_frames, "wand"); !e.empty()) return fail(e);
  if (std::string e = check_sets(lframe_frames, "L-frame"); !e.empty()) return fail(e);
  summary->wand_frames_total = static_cast<int>(wand_frames.size());

  // 1. Identify the wand in every image.
  const Wand& wand = options.wand;
  std::vector<WandFrame> frames;
  std::vector<int> seen_once(nc, 0);
  for (const DetectionSet& set : wand_frames) {
    WandFrame fr;
    for (int c = 0; c < nc; ++c) {
      if (!set.present[c]) continue;
      std::vector<Eigen::Vector2d> m;
      if (!IdentifyWand(set.cameras[c].centroids, wand, options.identification, &m)) continue;
      WandObservation o;
      o.camera = c;
      for (int k = 0; k < 3; ++k) o.pixels[k] = m[k];
      fr.observations.push_back(o);
    }
    if (fr.observations.size() == 1) seen_once[fr.observations[0].camera] += 1;
    if (fr.observations.size() >= 2) frames.push_back(std::move(fr));
  }
  summary->wand_frames_identified = static_cast<int>(frames.size());
  if (frames.empty()) {
    int once = 0;
    for (int v : seen_once) once += v;
    return fail("the wand was never seen by two cameras at once in " +
                std::to_string(wand_frames.size()) +
                " wand frames (identified by a single camera in " + std::to_string(once) +
                " frames): wave it where the cameras' views overlap");
  }

  // 2. Spanning tree of camera pairs with the most shared frames (Prim, from camera 0).
  Eigen::MatrixXi shared = Eigen::MatrixXi::Zero(nc, nc);
  for (const WandFrame& fr : frames)
    for (const WandObservation& a : fr.observations)
      for (const WandObservation& b : fr.observations)
        if (a.camera != b.camera) shared(a.camera, b.camera) += 1;
  std::vector<int> parent(nc, -1);
  std::vector<char> in_tree(nc, 0);
  in_tree[0] = 1;
  std::vector<int> order = {0};
  for (int added = 1; added < nc; ++added) {
    int best_a = -1, best_b = -1, best = options.min_shared_frames - 1;
    for (int a = 0; a < nc; ++a) {
      if (!in_tree[a]) continue;
      for (int b = 0; b < nc; ++b)
        if (!in_tree[b] && shared(a, b) > best) best = shared(a, b), best_a = a, best_b = b;
    }
    if (best_b < 0) {
      std::string missing;
      for (int c = 0; c < nc; ++c) {
        if (in_tree[c]) continue;
        int most = 0;
        for (int a = 0; a < nc; ++a)
          if (in_tree[a]) most = std::max(most, shared(a, c));
        missing += (missing.empty() ? "" : ", ") +
                   ("'" + cameras[c].id + "' (at most " + std::to_string(most) + " shared)");
      }
      return fail("camera(s) " + missing + " share too few wand frames with camera '" +
                  cameras[0].id + "' and the cameras linked to it (need " +
                  std::to_string(options.min_shared_frames) +
                  " with one of them): wave the wand where their views overlap");
    }
    in_tree[best_b] = 1;
    parent[best_b] = best_a;
    order.push_back(best_b);
    summary->tree.emplace_back(best_a, best_b);
    summary->tree_shared_frames.push_back(best);
  }

  // 3. Pairwise poses along the tree, chained from camera 0.
  std::vector<CameraModel> init = cameras;
  init[0].R.setIdentity();
  init[0].t.setZero();
  for (size_t i = 1; i < order.size(); ++i) {
    const int b = order[i], a = parent[b];
    std::vector<std::array<Eigen::Vector2d, 3>> xa, xb;
    for (const WandFrame& fr : frames) {
      const WandObservation *oa = nullptr, *ob = nullptr;
      for (const WandObservation& o : fr.observations) {
        if (o.camera == a) oa = &o;
        if (o.camera == b) ob = &o;
      }
      if (!oa || !ob) continue;
      std::array<Eigen::Vector2d, 3> pa, pb;
      for (int k = 0; k < 3; ++k) {
        pa[k] = cameras[a].Undistort(oa->pixels[k]);
        pb[k] = cameras[b].Undistort(ob->pixels[k]);
      }
      xa.push_back(pa);
      xb.push_back(pb);
    }
    Eigen::Matrix3d r;
    Eigen::Vector3d t;
    std::string why;
    if (!PairPose(cameras[a], cameras[b], xa, xb, wand, options.ransac_threshold_px, &r, &t, &why))
      return fail("relative pose of cameras '" + cameras[a].id + "' and '" + cameras[b].id +
                  "' from " + std::to_string(xa.size()) + " shared wand frames failed: " + why);
    init[b].R = r * init[a].R;
    init[b].t = r * init[a].t + t;
  }

  // 4. Starting wand poses: triangulate each marker; a camera that disagrees is left out.
  const std::vector<double>& s = wand.marker_positions_m;
  const double s_mean = (s[0] + s[1] + s[2]) / 3.0;
  const std::vector<double> offsets = {s[0] - s_mean, s[1] - s_mean, s[2] - s_mean};
  auto start_frame = [&](const std::vector<CameraModel>& cams, WandFrame* fr) {
    while (fr->observations.size() >= 2) {
      Eigen::Vector3d x[3];
      bool ok = true;
      for (int k = 0; k < 3 && ok; ++k) {
        std::vector<const CameraModel*> used;
        std::vector<Eigen::Vector2d> px;
        for (const WandObservation& o : fr->observations) {
          used.push_back(&cams[o.camera]);
          px.push_back(o.pixels[k]);
        }
        ok = TriangulatePoint(used, px, &x[k]);
      }
      if (!ok) return false;
      double worst = 0;
      size_t worst_i = 0;
      for (size_t i = 0; i < fr->observations.size(); ++i)
        for (int k = 0; k < 3; ++k) {
          Eigen::Vector2d u;
          cams[fr->observations[i].camera].Project(x[k], &u);
          const double e = (u - fr->observations[i].pixels[k]).norm();
          if (e > worst) worst = e, worst_i = i;
        }
      if (worst > 10.0) {  // px: a mis-identified wand, or a poor chained pose
        fr->observations.erase(fr->observations.begin() + worst_i);
        continue;
      }
      const double length = (x[2] - x[0]).norm();
      if (std::abs(length - wand.length_m()) > 0.2 * wand.length_m()) return false;
      fr->SetDirection(x[2] - x[0]);
      Eigen::Vector3d o = Eigen::Vector3d::Zero();
      for (int k = 0; k < 3; ++k) o += x[k] - offsets[k] * fr->d0;
      fr->centre = o / 3.0;
      return true;
    }
    return false;
  };
  std::vector<WandFrame> started;
  for (WandFrame& fr : frames)
    if (start_frame(init, &fr)) started.push_back(std::move(fr));
  if (started.size() < 10)
    return fail("only " + std::to_string(started.size()) +
                " wand frames could be triangulated with the chained pairwise poses");

  // 5. Bundle adjustment, outlier rejection, bundle adjustment again.
  std::vector<std::vector<double>> worst;
  std::vector<ObsStats> per_camera;
  std::vector<int> rejected(nc, 0);
  auto solve = [&](std::vector<CameraModel> start_cams, std::vector<WandFrame> fr,
                   solver::LmSummary* lm, Eigen::VectorXd* x_out,
                   std::unique_ptr<WandBundleProblem>* out) -> bool {
    auto problem = std::make_unique<WandBundleProblem>(
        std::move(start_cams), std::move(fr), offsets, options.refine_intrinsics, 0, cameras);
    Eigen::VectorXd x = problem->InitialState();
    solver::ArrowSchurProblem schur(problem.get(), options.num_threads);
    *lm = solver::Solve(options.lm, &schur, &x);
    problem->SetShared(x.tail(problem->shared_dim()));
    *x_out = x;
    *out = std::move(problem);
    return lm->IsSolutionUsable();
  };
  {
    WandBundleProblem probe(init, started, offsets, false, 0);
    ObservationErrors(probe, probe.InitialState(), &worst, &per_camera);
    summary->initial_reprojection_rms_px = TotalRms(per_camera);
  }
  std::unique_ptr<WandBundleProblem> problem;
  Eigen::VectorXd x;
  if (!solve(init, started, &summary->first_solve, &x, &problem))
    return fail("bundle adjustment failed: " + summary->first_solve.message);
  if (summary->first_solve.termination == solver::TerminationType::kUserCancelled)
    return fail("cancelled during the bundle adjustment");
  ObservationErrors(*problem, x, &worst, &per_camera);
  const double rms1 = TotalRms(per_camera);
  const double threshold = std::max(options.outlier_min_px, options.outlier_sigmas * rms1);
  std::vector<WandFrame> kept;
  for (int f = 0; f < problem->num_frames(); ++f) {
    WandFrame fr = problem->frames()[f];
    const double* y = x.data() + 5 * f;
    std::vector<WandObservation> obs;
    for (size_t i = 0; i < fr.observations.size(); ++i) {
      if (worst[f][i] > threshold) {
        rejected[fr.observations[i].camera] += 1;
        summary->rejected_observations += 1;
      } else {
        obs.push_back(fr.observations[i]);
      }
    }
    if (obs.size() < 2) continue;
    fr.observations = std::move(obs);
    // Restart from the solved pose (a new chart at the solved direction).
    fr.centre = Eigen::Vector3d(y[0], y[1], y[2]);
    fr.SetDirection(problem->Direction(f, y));
    kept.push_back(std::move(fr));
  }
  std::vector<CameraModel> solved = problem->cameras();
  if (!solve(solved, std::move(kept), &summary->final_solve, &x, &problem))
    return fail("bundle adjustment failed: " + summary->final_solve.message);
  if (summary->final_solve.termination == solver::TerminationType::kUserCancelled)
    return fail("cancelled during the bundle adjustment");
  ObservationErrors(*problem, x, &worst, &per_camera);
  std::vector<CameraModel> result = problem->cameras();

  summary->wand_frames_used = problem->num_frames();
  summary->reprojection_rms_px = TotalRms(per_camera);
  summary->cameras.resize(nc);
  for (int c = 0; c < nc; ++c) {
    CameraCalibrationStats& st = summary->cameras[c];
    st.id = cameras[c].id;
    st.wand_frames = per_camera[c].markers / 3;
    st.rejected = rejected[c];
    st.reprojection_rms_px =
        per_camera[c].markers ? std::sqrt(per_camera[c].sum_sq / per_camera[c].markers) : 0.0;
    summary->observations += st.wand_frames;
  }

  // 6. Wand-length error: each marker triangulated on its own, no wand model.
  double ss = 0, sum = 0;
  int n = 0;
  for (const WandFrame& fr : problem->frames()) {
    Eigen::Vector3d ends[2];
    bool ok = true;
    for (int e = 0; e < 2 && ok; ++e) {
      std::vector<const CameraModel*> used;
      std::vector<Eigen::Vector2d> px;
      for (const WandObservation& o : fr.observations) {
        used.push_back(&result[o.camera]);
        px.push_back(o.pixels[e == 0 ? 0 : 2]);
      }
      ok = TriangulatePoint(used, px, &ends[e]);
    }
    if (!ok) continue;
    const double err = (ends[1] - ends[0]).norm() - wand.length_m();
    ss += err * err;
    sum += err;
    ++n;
  }
  summary->wand_length_error_mm_rms = n ? 1000.0 * std::sqrt(ss / n) : 0.0;
  summary->wand_length_error_mm_mean = n ? 1000.0 * sum / n : 0.0;

  // 7. Lab frame from the L-frame.
  if (!lframe_frames.empty()) {
    std::vector<std::vector<Eigen::Vector2d>> pts(nc);
    for (int c = 0; c < nc; ++c) pts[c] = StaticCentroids(lframe_frames, c, 2.0);
    const std::vector<Eigen::Vector3d> points = ReconstructStatic(result, pts, 2.0);
    const std::vector<Eigen::Vector3d>& model = options.lframe.markers_m;
    const int m = static_cast<int>(model.size()), np = static_cast<int>(points.size());
    if (np < m)
      return fail("L-frame: " + std::to_string(np) +
                  " points reconstructed (seen by >= 3 cameras), "
                  "the L-frame has " +
                  std::to_string(m) + " markers");
    if (np > 10)
      return fail("L-frame: " + std::to_string(np) +
                  " points reconstructed, more than 10: the static frames must show the L-frame "
                  "alone");
    // Every assignment of reconstructed points to the L-frame's markers; the best rigid fit wins.
    std::vector<int> pick(m);
    std::vector<char> used(np, 0);
    double best = 1e30;
    Eigen::Matrix3d best_q;
    Eigen::Vector3d best_t;
    std::function<void(int)> recurse = [&](int i) {
      if (i == m) {
        std::vector<Eigen::Vector3d> a(m);
        for (int k = 0; k < m; ++k) a[k] = points[pick[k]];
        Eigen::Matrix3d q;
        Eigen::Vector3d t;
        const double rms = RigidAlign(a, model, &q, &t);
        if (rms < best) best = rms, best_q = q, best_t = t;
        return;
      }
      for (int p = 0; p < np; ++p) {
        if (used[p]) continue;
        used[p] = 1;
        pick[i] = p;
        recurse(i + 1);
        used[p] = 0;
      }
    };
    recurse(0);
    if (best > 0.005)
      return fail("L-frame: no " + std::to_string(m) + " of the " + std::to_string(np) +
                  " reconstructed points match its marker layout (best RMS " +
                  Fmt("%.1f", 1000 * best) + " mm)");
    summary->lframe_residual_mm_rms = 1000.0 * best;
    summary->lab_frame_from_lframe = true;
    // X_lab = Q X + q: R' = R Q^T, t' = t - R' q.
    for (CameraModel& cam : result) {
      cam.R = cam.R * best_q.transpose();
      cam.t = cam.t - cam.R * best_t;
    }
  }

  *calibrated = result;
  summary->termination = CalibrationTermination::kSuccess;
  summary->seconds = std::chrono::duration<double>(Clock::now() - start).count();
  return Status::Ok();
}

}  // namespace mocap::reconstruction
