#include "reconstruction/triangulation.h"

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <Eigen/LU>
#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <string>

namespace mocap::reconstruction {
namespace {

constexpr std::uint8_t kFree = 0, kTaken = 1, kUnusable = 2;

std::string Fmt(const char* format, auto... args) {
  char buffer[512];
  std::snprintf(buffer, sizeof buffer, format, args...);
  return buffer;
}

// Rows of the inhomogeneous DLT (H&Z §12.2 with X = (X, 1)) for one view with normalised
// coordinates (x, y) and camera [R | t]:  (x r3 - r1) . X = t1 - x t3,  (y r3 - r2) . X = t2 - y
// t3. Each row is z_c times the normalised-coordinate error, so weighting by focal / sigma makes
// the rows roughly pixel errors in sigmas at similar depths. Accumulated as 3x3 normal equations.
inline void AddDltView(const Eigen::Matrix3d& R, const Eigen::Vector3d& t,
                       const Eigen::Vector2d& xy, double weight, Eigen::Matrix3d* A,
                       Eigen::Vector3d* b) {
  const Eigen::Vector3d r1 = xy.x() * R.row(2).transpose() - R.row(0).transpose();
  const Eigen::Vector3d r2 = xy.y() * R.row(2).transpose() - R.row(1).transpose();
  const double b1 = t.x() - xy.x() * t.z();
  const double b2 = t.y() - xy.y() * t.z();
  const double w2 = weight * weight;
  A->noalias() += w2 * (r1 * r1.transpose() + r2 * r2.transpose());
  b->noalias() += w2 * (r1 * b1 + r2 * b2);
}

// Solves the DLT normal equations; false when (near) rank-deficient: parallel rays.
inline bool SolveDlt(const Eigen::Matrix3d& A, const Eigen::Vector3d& b, Eigen::Vector3d* x) {
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig;
  eig.computeDirect(A);
  const Eigen::Vector3d& l = eig.eigenvalues();  // ascending
  if (!(l(0) > 1e-12 * l(2))) return false;
  *x = eig.eigenvectors() * ((eig.eigenvectors().transpose() * b).cwiseQuotient(l));
  return x->allFinite();
}

inline bool InVolume(const TriangulationOptions& o, const Eigen::Vector3d& x) {
  return (x.array() >= o.volume_min.array()).all() && (x.array() <= o.volume_max.array()).all();
}

// Sum of squared whitened residuals, with the Gauss–Newton normal equations and each view's
// squared pixel error if asked; +inf when a view is closer than min_depth to (or behind) its
// camera.
double Evaluate(const std::vector<CameraModel>& rig, std::span<const PointObservation> obs,
                const Eigen::Vector3d& x, double min_depth, Eigen::Matrix3d* H, Eigen::Vector3d* g,
                double* view_e2) {
  double cost = 0;
  if (H) {
    H->setZero();
    g->setZero();
  }
  for (size_t v = 0; v < obs.size(); ++v) {
    const PointObservation& o = obs[v];
    const CameraModel& cam = rig[o.camera];
    const Eigen::Vector3d pc = cam.R * x + cam.t;
    if (!(pc.z() >= min_depth)) return std::numeric_limits<double>::infinity();
    const double inv_sigma = 1.0 / o.sigma_px;
    Eigen::Matrix<double, 2, 3> jc;
    const Eigen::Vector2d e = cam.ProjectCameraPoint(pc, H ? &jc : nullptr) - o.pixel;
    if (view_e2) view_e2[v] = e.squaredNorm();
    const Eigen::Vector2d r = e * inv_sigma;
    cost += r.squaredNorm();
    if (H) {
      const Eigen::Matrix<double, 2, 3> j = inv_sigma * jc * cam.R;
      H->noalias() += j.transpose() * j;
      g->noalias() += j.transpose() * r;
    }
  }
  return cost;
}

// Levenberg–Marquardt on 3 unknowns: the damped normal equations (H + lambda diag(H)) dx = -g,
// lambda divided by 10 after a step that lowers the cost and multiplied by 10 otherwise. From the
// DLT it is Gauss–Newton in all but name: the residuals are tiny next to the projection's scale,
// so it converges in 2-3 steps; it stops after a step below kStepTolerance (0.1 um, far below
// any centroid noise: the next step would be smaller still by the convergence rate). Writes each
// view's squared pixel error at the solution into view_e2 (obs.size() entries) if given.
constexpr double kStepTolerance = 1e-7;  // metres

bool Refine(const std::vector<CameraModel>& rig, std::span<const PointObservation> obs,
            int max_iterations, double min_depth, Eigen::Vector3d* x, double* view_e2) {
  std::array<double, kMaxPointViews> trial_e2;
  double* trial = view_e2 && obs.size() <= trial_e2.size() ? trial_e2.data() : nullptr;
  Eigen::Matrix3d H, Hn;
  Eigen::Vector3d g, gn;
  double cost = Evaluate(rig, obs, *x, min_depth, &H, &g, trial);
  if (!std::isfinite(cost)) return false;
  if (trial) std::copy(trial, trial + obs.size(), view_e2);
  double lambda = 1e-6;
  for (int it = 0; it < max_iterations; ++it) {
    Eigen::Matrix3d damped = H;
    damped.diagonal() *= 1.0 + lambda;
    Eigen::LDLT<Eigen::Matrix3d> ldlt(damped);
    if (ldlt.info() != Eigen::Success || !ldlt.isPositive()) return false;
    const Eigen::Vector3d dx = ldlt.solve(-g);
    if (!dx.allFinite()) return false;
    const Eigen::Vector3d xn = *x + dx;
    const double cn = Evaluate(rig, obs, xn, min_depth, &Hn, &gn, trial);
    if (cn <= cost) {
      *x = xn;
      cost = cn;
      H = Hn;
      g = gn;
      if (trial) std::copy(trial, trial + obs.size(), view_e2);
      lambda = std::max(lambda * 0.1, 1e-12);
      if (dx.norm() < kStepTolerance) break;
    } else {
      lambda *= 10;
      if (lambda > 1e8) break;
    }
  }
  return true;
}

// RMS of the pixel reprojection error's norm over the views.
double RmsPixelResidual(const std::vector<CameraModel>& rig, std::span<const PointObservation> obs,
                        const Eigen::Vector3d& x) {
  double sum = 0;
  for (const PointObservation& o : obs) {
    const CameraModel& cam = rig[o.camera];
    sum += (cam.ProjectCameraPoint(cam.R * x + cam.t) - o.pixel).squaredNorm();
  }
  return std::sqrt(sum / static_cast<double>(obs.size()));
}

}  // namespace

bool TriangulationOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& what) {
    if (error) *error = "triangulation options: " + what;
    return false;
  };
  auto positive = [](double v) { return std::isfinite(v) && v > 0; };
  if (!(std::isfinite(calibration_sigma_px) && calibration_sigma_px >= 0)) {
    return fail("calibration_sigma_px must be finite and >= 0");
  }
  if (!positive(epipolar_gate_sigmas)) return fail("epipolar_gate_sigmas must be > 0");
  if (!positive(two_view_gate_sigmas)) return fail("two_view_gate_sigmas must be > 0");
  if (!positive(support_gate_sigmas)) return fail("support_gate_sigmas must be > 0");
  if (!positive(outlier_gate_sigmas)) return fail("outlier_gate_sigmas must be > 0");
  if (!positive(max_residual_px)) return fail("max_residual_px must be > 0");
  if (min_views < 2 || min_views > kMaxPointViews) {
    return fail(Fmt("min_views must be in [2, %d]", kMaxPointViews));
  }
  if (!(min_two_view_angle_deg >= 0 && min_two_view_angle_deg < 90)) {
    return fail("min_two_view_angle_deg must be in [0, 90)");
  }
  if (!positive(min_depth_m)) return fail("min_depth_m must be > 0");
  if (volume_min.hasNaN() || volume_max.hasNaN() ||
      !(volume_min.array() < volume_max.array()).all()) {
    return fail("volume_min must be below volume_max on every axis (and not NaN)");
  }
  if (max_iterations < 1) return fail("max_iterations must be >= 1");
  if (max_centroids_per_camera < 1) return fail("max_centroids_per_camera must be >= 1");
  if (!(std::isfinite(min_separation_m) && min_separation_m >= 0)) {
    return fail("min_separation_m must be finite and >= 0");
  }
  return true;
}

bool TriangulateLinear(const std::vector<CameraModel>& rig,
                       std::span<const PointObservation> observations, Eigen::Vector3d* position) {
  if (observations.size() < 2) return false;
  Eigen::Matrix3d A = Eigen::Matrix3d::Zero();
  Eigen::Vector3d b = Eigen::Vector3d::Zero();
  for (const PointObservation& o : observations) {
    if (o.camera < 0 || o.camera >= static_cast<int>(rig.size()) || !(o.sigma_px > 0)) {
      return false;
    }
    const CameraModel& cam = rig[o.camera];
    const double focal = std::sqrt(cam.intrinsics.fx * cam.intrinsics.fy);
    AddDltView(cam.R, cam.t, cam.Undistort(o.pixel), focal / o.sigma_px, &A, &b);
  }
  return SolveDlt(A, b, position);
}

Eigen::Vector2d WhitenedReprojectionResidual(const CameraModel& camera,
                                             const PointObservation& observation,
                                             const Eigen::Vector3d& position,
                                             Eigen::Matrix<double, 2, 3>* jacobian) {
  const double inv_sigma = 1.0 / observation.sigma_px;
  Eigen::Matrix<double, 2, 3> jc;
  const Eigen::Vector2d uv =
      camera.ProjectCameraPoint(camera.R * position + camera.t, jacobian ? &jc : nullptr);
  if (jacobian) *jacobian = inv_sigma * jc * camera.R;
  return (uv - observation.pixel) * inv_sigma;
}

bool RefinePosition(const std::vector<CameraModel>& rig,
                    std::span<const PointObservation> observations, int max_iterations,
                    Eigen::Vector3d* position, double* residual_px) {
  if (observations.empty()) return false;
  for (const PointObservation& o : observations) {
    if (o.camera < 0 || o.camera >= static_cast<int>(rig.size()) || !(o.sigma_px > 0)) {
      return false;
    }
  }
  constexpr double kMinDepth = 1e-9;
  const bool ok = Refine(rig, observations, max_iterations, kMinDepth, position, nullptr);
  if (residual_px) *residual_px = RmsPixelResidual(rig, observations, *position);
  return ok;
}

Status Triangulator::Create(std::vector<CameraModel> rig, const TriangulationOptions& options,
                            std::unique_ptr<Triangulator>* triangulator) {
  std::string error;
  if (!options.IsValid(&error)) return Status::Error(error);
  if (rig.size() < 2) {
    return Status::Error(
        Fmt("triangulation: the rig has %zu cameras; at least 2 are needed", rig.size()));
  }
  for (size_t c = 0; c < rig.size(); ++c) {
    const CameraModel& cam = rig[c];
    const std::string name = Fmt("triangulation: rig camera %zu (%s): ", c, cam.id.c_str());
    if (!cam.intrinsics.IsValid(&error)) return Status::Error(name + error);
    if (!cam.R.allFinite() || !cam.t.allFinite()) {
      return Status::Error(name + "R or t is not finite");
    }
    const double orthogonality = (cam.R.transpose() * cam.R - Eigen::Matrix3d::Identity()).norm();
    if (orthogonality > 1e-6 || cam.R.determinant() < 0) {
      return Status::Error(name + Fmt("R is not a rotation (|R^T R - I| = %.3g, det = %.3g)",
                                      orthogonality, cam.R.determinant()));
    }
  }

  std::unique_ptr<Triangulator> t(new Triangulator);
  t->options_ = options;
  t->rig_ = std::move(rig);
  const int n = static_cast<int>(t->rig_.size());
  t->focal_.resize(n);
  for (int c = 0; c < n; ++c) {
    t->focal_[c] = std::sqrt(t->rig_[c].intrinsics.fx * t->rig_[c].intrinsics.fy);
  }
  t->cos_min_two_view_angle_ = std::cos(options.min_two_view_angle_deg * M_PI / 180.0);
  t->calibration_sigma2_ = options.calibration_sigma_px * options.calibration_sigma_px;

  // The rig's focus: the point closest (least squares) to every optical axis.
  Eigen::Matrix3d M = Eigen::Matrix3d::Zero();
  Eigen::Vector3d v = Eigen::Vector3d::Zero();
  Eigen::Vector3d mean_ahead = Eigen::Vector3d::Zero();
  for (const CameraModel& cam : t->rig_) {
    const Eigen::Vector3d d = cam.R.row(2).transpose();  // optical axis in the world
    const Eigen::Matrix3d P = Eigen::Matrix3d::Identity() - d * d.transpose();
    M += P;
    v += P * cam.centre();
    mean_ahead += (cam.centre() + d) / n;
  }
  Eigen::FullPivLU<Eigen::Matrix3d> lu(M);
  const Eigen::Vector3d focus = lu.rank() == 3 ? Eigen::Vector3d(lu.solve(v)) : mean_ahead;

  for (int a = 0; a < n; ++a) {
    for (int b = a + 1; b < n; ++b) {
      const CameraModel& ca = t->rig_[a];
      const CameraModel& cb = t->rig_[b];
      const Eigen::Matrix3d R_ab = cb.R * ca.R.transpose();
      const Eigen::Vector3d t_ab = cb.t - R_ab * ca.t;
      if (t_ab.norm() < 1e-9) continue;  // coincident centres: no epipolar geometry
      Eigen::Matrix3d tx;
      tx << 0, -t_ab.z(), t_ab.y(), t_ab.z(), 0, -t_ab.x(), -t_ab.y(), t_ab.x(), 0;
      CameraPair pair;
      pair.a = a;
      pair.b = b;
      pair.essential = tx * R_ab;
      const Eigen::Vector3d da = ca.centre() - focus, db = cb.centre() - focus;
      pair.score = da.cross(db).norm() / std::max(da.norm() * db.norm(), 1e-300);
      t->pairs_.push_back(pair);
    }
  }
  std::stable_sort(t->pairs_.begin(), t->pairs_.end(),
                   [](const CameraPair& x, const CameraPair& y) { return x.score > y.score; });
  *triangulator = std::move(t);
  return Status::Ok();
}

Status Triangulator::Validate(const DetectionSet& set) const {
  const size_t n = rig_.size();
  if (set.cameras.size() != n) {
    return Status::Error(Fmt("triangulation: the detection set has %zu cameras but the rig has %zu",
                             set.cameras.size(), n));
  }
  if (set.present.size() != n) {
    return Status::Error(
        Fmt("triangulation: the detection set has %zu present flags for %zu cameras",
            set.present.size(), n));
  }
  for (size_t c = 0; c < n; ++c) {
    if (!set.present[c]) continue;
    const CameraDetections& d = set.cameras[c];
    if (d.camera != -1 && d.camera != static_cast<int>(c)) {
      return Status::Error(
          Fmt("triangulation: detection set cameras[%zu] holds camera %d's "
              "detections (out of rig order)",
              c, d.camera));
    }
    for (size_t i = 0; i < d.centroids.size(); ++i) {
      const Centroid& k = d.centroids[i];
      if (!k.pixel.allFinite()) {
        return Status::Error(
            Fmt("triangulation: camera %zu centroid %zu: pixel (%g, %g) is not "
                "finite",
                c, i, k.pixel.x(), k.pixel.y()));
      }
      if (!(std::isfinite(k.sigma_px) && k.sigma_px > 0)) {
        return Status::Error(
            Fmt("triangulation: camera %zu centroid %zu: sigma_px %g must be "
                "finite and > 0",
                c, i, k.sigma_px));
      }
    }
  }
  return Status::Ok();
}

int Triangulator::FindSupport(const TriangulationWorkspace& ws, int camera,
                              const Eigen::Vector3d& x) const {
  const CameraModel& cam = rig_[camera];
  const Eigen::Vector3d pc = cam.R * x + cam.t;
  if (!(pc.z() >= options_.min_depth_m)) return -1;
  const Eigen::Vector2d xy = pc.head<2>() / pc.z();
  const TriangulationWorkspace::CameraScratch& cs = ws.cameras_[camera];
  const double k2 = options_.support_gate_sigmas * options_.support_gate_sigmas;
  int best = -1;
  double best_d2 = std::numeric_limits<double>::infinity();
  const int n = static_cast<int>(cs.xy.size());
  for (int j = 0; j < n; ++j) {
    if (cs.state[j] != kFree) continue;
    const double d2 = (cs.xy[j] - xy).squaredNorm();
    if (d2 <= k2 * cs.gate[j] * cs.gate[j] && d2 < best_d2) {
      best_d2 = d2;
      best = j;
    }
  }
  return best;
}

bool Triangulator::Solve(const DetectionSet& set, int min_views, internal::Hypothesis* h,
                         TriangulationWorkspace* ws, TriangulatedPoint* point) const {
  const TriangulationOptions& o = options_;
  std::vector<PointObservation>& obs = ws->observations_;
  auto load = [&]() {
    obs.clear();
    for (int v = 0; v < h->view_count; ++v) {
      const Centroid& k = set.cameras[h->views[v].camera].centroids[h->views[v].centroid];
      obs.push_back({h->views[v].camera, k.pixel, k.sigma_px});
    }
  };

  // Multi-view DLT from the undistorted coordinates already in the workspace.
  Eigen::Matrix3d A = Eigen::Matrix3d::Zero();
  Eigen::Vector3d b = Eigen::Vector3d::Zero();
  for (int v = 0; v < h->view_count; ++v) {
    const PointView pv = h->views[v];
    const TriangulationWorkspace::CameraScratch& cs = ws->cameras_[pv.camera];
    const double sigma = set.cameras[pv.camera].centroids[pv.centroid].sigma_px;
    AddDltView(rig_[pv.camera].R, rig_[pv.camera].t, cs.xy[pv.centroid], focal_[pv.camera] / sigma,
               &A, &b);
  }
  Eigen::Vector3d x;
  if (!SolveDlt(A, b, &x)) return false;

  // Refine, drop the worst view while it is an outlier, then look for views the hypothesis
  // missed (once) and check again.
  std::array<double, kMaxPointViews> view_e2;  // squared pixel error per view at x
  for (int sweep = 0; sweep < 2; ++sweep) {
    load();
    if (!Refine(rig_, obs, o.max_iterations, o.min_depth_m, &x, view_e2.data())) return false;
    for (;;) {
      int worst = -1;
      double worst_e2 = o.outlier_gate_sigmas * o.outlier_gate_sigmas;
      for (int v = 0; v < h->view_count; ++v) {
        const double e2 = view_e2[v] / (obs[v].sigma_px * obs[v].sigma_px + calibration_sigma2_);
        if (e2 > worst_e2) {
          worst_e2 = e2;
          worst = v;
        }
      }
      if (worst < 0) break;
      for (int v = worst; v + 1 < h->view_count; ++v) h->views[v] = h->views[v + 1];
      --h->view_count;
      if (h->view_count < min_views) return false;
      load();
      if (!Refine(rig_, obs, o.max_iterations, o.min_depth_m, &x, view_e2.data())) return false;
    }
    if (sweep == 1) break;
    int added = 0;
    for (int c = 0; c < static_cast<int>(rig_.size()) && h->view_count < kMaxPointViews; ++c) {
      if (!ws->cameras_[c].active) continue;
      bool has = false;
      for (int v = 0; v < h->view_count; ++v) has |= h->views[v].camera == c;
      if (has) continue;
      const int j = FindSupport(*ws, c, x);
      if (j < 0) continue;
      h->views[h->view_count++] = {c, j};
      ++added;
    }
    if (added == 0) break;
  }

  if (h->view_count < min_views || !InVolume(o, x)) return false;
  if (h->view_count == 2) {
    const Eigen::Vector3d ra = (x - rig_[h->views[0].camera].centre()).normalized();
    const Eigen::Vector3d rb = (x - rig_[h->views[1].camera].centre()).normalized();
    // Near-parallel or near-opposite rays (cameras facing each other) leave the point free along
    // the rays.
    if (std::abs(ra.dot(rb)) > cos_min_two_view_angle_) return false;
  }
  double sum_e2 = 0;
  for (int v = 0; v < h->view_count; ++v) sum_e2 += view_e2[v];
  const double rms = std::sqrt(sum_e2 / h->view_count);
  if (!(rms <= o.max_residual_px)) return false;

  point->position = x;
  point->residual_px = rms;
  point->camera_count = h->view_count;
  std::copy(h->views.begin(), h->views.begin() + h->view_count, point->views.begin());
  std::sort(point->views.begin(), point->views.begin() + h->view_count,
            [](const PointView& p, const PointView& q) { return p.camera < q.camera; });
  return true;
}

void Triangulator::RunPass(const DetectionSet& set, int min_views, TriangulationWorkspace* ws,
                           std::vector<TriangulatedPoint>* points,
                           TriangulationSummary* summary) const {
  const TriangulationOptions& o = options_;
  const int n_cameras = static_cast<int>(rig_.size());
  const double gate = min_views == 2 ? o.two_view_gate_sigmas : o.epipolar_gate_sigmas;
  const double k2 = gate * gate;
  ws->hypotheses_.clear();
  for (const CameraPair& pair : pairs_) {
    TriangulationWorkspace::CameraScratch& sa = ws->cameras_[pair.a];
    TriangulationWorkspace::CameraScratch& sb = ws->cameras_[pair.b];
    if (!sa.active || !sb.active) continue;
    ws->unused_a_.clear();
    ws->unused_b_.clear();
    ws->lines_b_.clear();
    for (int i = 0; i < static_cast<int>(sa.xy.size()); ++i) {
      if (sa.state[i] == kFree) ws->unused_a_.push_back(i);
    }
    for (int j = 0; j < static_cast<int>(sb.xy.size()); ++j) {
      if (sb.state[j] != kFree) continue;
      ws->unused_b_.push_back(j);
      ws->lines_b_.push_back(pair.essential.transpose() * sb.xy[j].homogeneous());
    }
    if (ws->unused_a_.empty() || ws->unused_b_.empty()) continue;

    const int nb = static_cast<int>(ws->unused_b_.size());
    for (int i : ws->unused_a_) {
      const Eigen::Vector3d la = pair.essential * sa.xy[i].homogeneous();  // epipolar line in b
      const double na2 = la.head<2>().squaredNorm();
      const double ga2 = sa.gate[i] * sa.gate[i];
      for (int jb = 0; jb < nb; ++jb) {
        const int j = ws->unused_b_[jb];
        // Sampson's first-order distance to the epipolar constraint, with each image's own
        // sigma: e^2 / (s_b^2 |l_a|^2 + s_a^2 |l_b|^2).
        const double e = la.dot(sb.xy[j].homogeneous());
        const double denom =
            sb.gate[j] * sb.gate[j] * na2 + ga2 * ws->lines_b_[jb].head<2>().squaredNorm();
        if (e * e > k2 * denom) continue;

        Eigen::Matrix3d A = Eigen::Matrix3d::Zero();
        Eigen::Vector3d b = Eigen::Vector3d::Zero();
        AddDltView(rig_[pair.a].R, rig_[pair.a].t, sa.xy[i], 1.0 / sa.gate[i], &A, &b);
        AddDltView(rig_[pair.b].R, rig_[pair.b].t, sb.xy[j], 1.0 / sb.gate[j], &A, &b);
        Eigen::Vector3d x;
        if (!SolveDlt(A, b, &x)) continue;
        if (!((rig_[pair.a].R.row(2).dot(x) + rig_[pair.a].t.z()) >= o.min_depth_m) ||
            !((rig_[pair.b].R.row(2).dot(x) + rig_[pair.b].t.z()) >= o.min_depth_m) ||
            !InVolume(o, x)) {
          continue;
        }
        ++summary->candidates;
        internal::Hypothesis h;
        h.position = x;
        h.epipolar_cost = e * e / std::max(denom, 1e-300);
        h.views[0] = {pair.a, i};
        h.views[1] = {pair.b, j};
        h.view_count = 2;
        for (int c = 0; c < n_cameras && h.view_count < kMaxPointViews; ++c) {
          if (c == pair.a || c == pair.b || !ws->cameras_[c].active) continue;
          const int support = FindSupport(*ws, c, x);
          if (support >= 0) h.views[h.view_count++] = {c, support};
        }
        if (h.view_count >= min_views) ws->hypotheses_.push_back(h);
      }
    }
    // With three or more views, accept this pair's hypotheses before the next pair is visited:
    // the points accepted take their centroids out of every later pair's matching, which keeps
    // the search small. Two-view hypotheses have no third camera to tell a true match from a
    // coincidence, so they are all collected first and accepted best (smallest epipolar
    // distance) first over the whole set: a centroid goes to its most consistent partner, not to
    // whichever pair happened to be visited first.
    if (min_views >= 3) AcceptHypotheses(set, min_views, ws, points, summary);
  }
  if (min_views < 3) AcceptHypotheses(set, min_views, ws, points, summary);
}

void Triangulator::AcceptHypotheses(const DetectionSet& set, int min_views,
                                    TriangulationWorkspace* ws,
                                    std::vector<TriangulatedPoint>* points,
                                    TriangulationSummary* summary) const {
  ws->order_.resize(ws->hypotheses_.size());
  for (int k = 0; k < static_cast<int>(ws->order_.size()); ++k) ws->order_[k] = k;
  const auto& hyps = ws->hypotheses_;
  std::sort(ws->order_.begin(), ws->order_.end(), [&](int p, int q) {
    if (hyps[p].view_count != hyps[q].view_count) return hyps[p].view_count > hyps[q].view_count;
    return hyps[p].epipolar_cost < hyps[q].epipolar_cost;
  });
  auto is_free = [&](const PointView& v) {
    return ws->cameras_[v.camera].state[v.centroid] == kFree;
  };
  for (int k : ws->order_) {
    internal::Hypothesis& h = ws->hypotheses_[k];
    if (!is_free(h.views[0]) || !is_free(h.views[1])) {
      ++summary->superseded;
      continue;
    }
    int kept = 2;
    for (int v = 2; v < h.view_count; ++v) {
      if (is_free(h.views[v])) h.views[kept++] = h.views[v];
    }
    h.view_count = kept;
    if (h.view_count < min_views) {
      ++summary->superseded;
      continue;
    }
    TriangulatedPoint point;
    if (!Solve(set, min_views, &h, ws, &point)) {
      ++summary->rejected_ghosts;
      continue;
    }
    for (int v = 0; v < point.camera_count; ++v) {
      ws->cameras_[point.views[v].camera].state[point.views[v].centroid] = kTaken;
    }
    points->push_back(point);
  }
  ws->hypotheses_.clear();
}

void Triangulator::MergeClosePoints(const DetectionSet& set, TriangulationWorkspace* ws,
                                    std::vector<TriangulatedPoint>* points,
                                    TriangulationSummary* summary) const {
  const double d2 = options_.min_separation_m * options_.min_separation_m;
  auto mark = [&](const TriangulatedPoint& p, std::uint8_t state) {
    for (int v = 0; v < p.camera_count; ++v) {
      ws->cameras_[p.views[v].camera].state[p.views[v].centroid] = state;
    }
  };
  for (size_t i = 0; i < points->size(); ++i) {
    for (size_t j = i + 1; j < points->size(); ++j) {
      TriangulatedPoint& p = (*points)[i];
      TriangulatedPoint& q = (*points)[j];
      if ((p.position - q.position).squaredNorm() >= d2) continue;
      // Pool the views, one per camera, the better-supported point's first.
      const TriangulatedPoint& major = p.camera_count >= q.camera_count ? p : q;
      const TriangulatedPoint& minor = p.camera_count >= q.camera_count ? q : p;
      internal::Hypothesis h;
      for (int v = 0; v < major.camera_count; ++v) h.views[h.view_count++] = major.views[v];
      for (int v = 0; v < minor.camera_count && h.view_count < kMaxPointViews; ++v) {
        bool has = false;
        for (int w = 0; w < major.camera_count; ++w) {
          has |= major.views[w].camera == minor.views[v].camera;
        }
        if (!has) h.views[h.view_count++] = minor.views[v];
      }
      mark(p, kFree);
      mark(q, kFree);
      TriangulatedPoint merged;
      if (!Solve(set, options_.min_views, &h, ws, &merged)) merged = major;
      mark(merged, kTaken);
      p = merged;
      points->erase(points->begin() + static_cast<std::ptrdiff_t>(j));
      ++summary->merged;
      j = i;  // the merged point may now be close to another one
    }
  }
}

Status Triangulator::Triangulate(const DetectionSet& set, TriangulationWorkspace* ws,
                                 std::vector<TriangulatedPoint>* points,
                                 TriangulationSummary* summary) const {
  if (ws == nullptr || points == nullptr) {
    return Status::Error("triangulation: workspace and points must not be null");
  }
  points->clear();  // a failed call leaves no stale points behind
  MOCAP_RETURN_IF_ERROR(Validate(set));
  TriangulationSummary local;
  TriangulationSummary& s = summary ? *summary : local;
  s = TriangulationSummary{};

  const int n = static_cast<int>(rig_.size());
  ws->cameras_.resize(n);
  for (int c = 0; c < n; ++c) {
    TriangulationWorkspace::CameraScratch& cs = ws->cameras_[c];
    cs.active = false;
    cs.xy.clear();
    cs.gate.clear();
    cs.state.clear();
    if (!set.present[c]) continue;
    const std::vector<Centroid>& centroids = set.cameras[c].centroids;
    const int m = static_cast<int>(centroids.size());
    if (m > options_.max_centroids_per_camera) {
      ++s.cameras_overfull;
      continue;
    }
    cs.active = true;
    ++s.cameras_used;
    s.centroids += m;
    cs.xy.resize(m);
    cs.gate.resize(m);
    cs.state.assign(m, kFree);
    for (int i = 0; i < m; ++i) {
      cs.xy[i] = rig_[c].Undistort(centroids[i].pixel);
      if (!cs.xy[i].allFinite()) cs.state[i] = kUnusable;
      cs.gate[i] = std::sqrt(centroids[i].sigma_px * centroids[i].sigma_px + calibration_sigma2_) /
                   focal_[c];
    }
  }

  const int first = std::max(3, options_.min_views);
  RunPass(set, first, ws, points, &s);
  if (options_.min_views < first) RunPass(set, options_.min_views, ws, points, &s);
  if (options_.min_separation_m > 0) MergeClosePoints(set, ws, points, &s);

  s.accepted = static_cast<int>(points->size());
  for (int c = 0; c < n; ++c) {
    for (std::uint8_t st : ws->cameras_[c].state) s.unmatched_centroids += st != kTaken;
  }
  return Status::Ok();
}

Status Triangulate(const DetectionSet& set, const std::vector<CameraModel>& rig,
                   const TriangulationOptions& options, std::vector<TriangulatedPoint>* points,
                   TriangulationSummary* summary) {
  std::unique_ptr<Triangulator> triangulator;
  MOCAP_RETURN_IF_ERROR(Triangulator::Create(rig, options, &triangulator));
  TriangulationWorkspace workspace;
  return triangulator->Triangulate(set, &workspace, points, summary);
}

}  // namespace mocap::reconstruction
