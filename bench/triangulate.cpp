// triangulate: reconstruction::Triangulator on the simulated rig and subject, per frame set, single
// thread, side by side in one run with two peers:
//   - brute force: every centroid pair of every camera pair within the same epipolar gate is
//     triangulated and scored by its support in all other cameras, then accepted greedily by
//     support over the whole set (no pruning of used centroids while hypothesising), positions
//     by the multi-view DLT of its views (no refinement);
//   - OpenCV: cv::undistortPoints + cv::triangulatePoints (two-view DLT) on the TRUE
//     correspondences (no matching at all), from the widest pair of cameras that saw the marker:
//     the cost and accuracy of the linear part alone.
//
//   triangulate [--reps R] [--strays K] [--stride S] [--no-peers]
//
// Scene: the default 8-camera rig (sim/camera_rig.h, 1280 x 1024), the default subject's 39
// markers (sim::SimulateSession, seed 1, noise-free, duration_scale 0.5), one frame set every S
// (default 7) frames of the whole protocol; each marker projected through the true cameras
// (dropped behind a camera or outside the image), N(0, 0.1 px) added to each coordinate, K
// (default 3) stray reflections per camera uniform over the image, centroids shuffled; once with
// every observation and once with 20% of them hidden at random. Times are per frame set, over R
// (default 5) passes of all frame sets with a warm workspace, as this thread's CPU time and as
// wall-clock time (which includes preemption on a shared machine); the accuracy columns use the
// first pass: 3D RMS error of points within 5 mm of a marker (and the Cramer-Rao bound of those
// markers from all their centroids), recall of markers seen by >= 2 cameras, ghosts (points
// more than 5 mm from every marker) over all points.
#include <time.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "daemon/capture_pipeline.h"
#include "reconstruction/triangulation.h"
#include "sim/camera_rig.h"
#include "sim/centroid_scene.h"
#include "sim/random.h"
#include "sim/simulate.h"

using namespace mocap;
using reconstruction::CameraModel;
using reconstruction::Centroid;
using reconstruction::DetectionSet;
using reconstruction::PointObservation;
using reconstruction::TriangulatedPoint;
using Clock = std::chrono::steady_clock;

namespace {

using Scene = sim::CentroidScene;

// The triangulation test's scene (sim/centroid_scene.h): 0.1 px noise, seed 1.
Scene MakeScene(const std::vector<CameraModel>& rig, const std::vector<Eigen::Vector3d>& markers,
                double hide, int strays, std::uint64_t frame) {
  sim::CentroidSceneOptions o;
  o.hide = hide;
  o.strays = strays;
  return sim::MakeCentroidScene(rig, markers, o, frame);
}

struct Score {
  long eligible = 0, found = 0, points = 0, ghosts = 0, true_points = 0;
  double sum_sq = 0, sum_crlb = 0;
  void Add(const std::vector<CameraModel>& rig, const std::vector<Eigen::Vector3d>& markers,
           const Scene& scene, const std::vector<Eigen::Vector3d>& positions) {
    std::vector<bool> found_marker(markers.size(), false);
    for (const Eigen::Vector3d& p : positions) {
      ++points;
      int best = -1;
      double best_d = 5e-3;
      for (size_t m = 0; m < markers.size(); ++m) {
        const double d = (p - markers[m]).norm();
        if (d < best_d) best_d = d, best = static_cast<int>(m);
      }
      if (best < 0) {
        ++ghosts;
        continue;
      }
      found_marker[best] = true;
      ++true_points;
      sum_sq += best_d * best_d;
      Eigen::Matrix3d info = Eigen::Matrix3d::Zero();
      for (const auto& [c, i] : scene.observed[best]) {
        const PointObservation o{c, scene.set.cameras[c].centroids[i].pixel, 0.1};
        Eigen::Matrix<double, 2, 3> j;
        reconstruction::WhitenedReprojectionResidual(rig[c], o, markers[best], &j);
        info += j.transpose() * j;
      }
      sum_crlb += info.inverse().trace();
    }
    for (size_t m = 0; m < markers.size(); ++m) {
      if (scene.observed[m].size() >= 2) ++eligible, found += found_marker[m];
    }
  }
};

// The brute-force peer (see the top of the file).
class BruteForce {
 public:
  BruteForce(const std::vector<CameraModel>& rig, const reconstruction::Triangulator& t)
      : rig_(rig), pairs_(t.pairs()) {}

  void Run(const DetectionSet& set, std::vector<Eigen::Vector3d>* out) {
    const int nc = static_cast<int>(rig_.size());
    xy_.resize(nc);
    gate_.resize(nc);
    used_.resize(nc);
    for (int c = 0; c < nc; ++c) {
      const auto& cs = set.cameras[c].centroids;
      xy_[c].resize(cs.size());
      gate_[c].resize(cs.size());
      used_[c].assign(cs.size(), 0);
      const double f = std::sqrt(rig_[c].intrinsics.fx * rig_[c].intrinsics.fy);
      for (size_t i = 0; i < cs.size(); ++i) {
        xy_[c][i] = rig_[c].Undistort(cs[i].pixel);
        gate_[c][i] = std::hypot(cs[i].sigma_px, 0.05) / f;
      }
    }
    hyps_.clear();
    for (const auto& pair : pairs_) {
      for (size_t i = 0; i < xy_[pair.a].size(); ++i) {
        const Eigen::Vector3d la = pair.essential * xy_[pair.a][i].homogeneous();
        for (size_t j = 0; j < xy_[pair.b].size(); ++j) {
          const Eigen::Vector3d lb = pair.essential.transpose() * xy_[pair.b][j].homogeneous();
          const double e = la.dot(xy_[pair.b][j].homogeneous());
          const double denom = gate_[pair.b][j] * gate_[pair.b][j] * la.head<2>().squaredNorm() +
                               gate_[pair.a][i] * gate_[pair.a][i] * lb.head<2>().squaredNorm();
          if (e * e > 16.0 * denom) continue;
          Hyp h;
          h.views.push_back({pair.a, static_cast<int>(i)});
          h.views.push_back({pair.b, static_cast<int>(j)});
          Eigen::Vector3d x;
          if (!Linear(h.views, &x)) continue;
          if ((rig_[pair.a].R * x + rig_[pair.a].t).z() <= 0.05 ||
              (rig_[pair.b].R * x + rig_[pair.b].t).z() <= 0.05) {
            continue;
          }
          for (int c = 0; c < nc; ++c) {
            if (c == pair.a || c == pair.b) continue;
            const Eigen::Vector3d pc = rig_[c].R * x + rig_[c].t;
            if (pc.z() <= 0.05) continue;
            const Eigen::Vector2d p = pc.head<2>() / pc.z();
            int best = -1;
            double best_d2 = 1e300;
            for (size_t k = 0; k < xy_[c].size(); ++k) {
              const double d2 = (xy_[c][k] - p).squaredNorm();
              if (d2 <= 25.0 * gate_[c][k] * gate_[c][k] && d2 < best_d2)
                best_d2 = d2, best = static_cast<int>(k);
            }
            if (best >= 0) h.views.push_back({c, best});
          }
          hyps_.push_back(std::move(h));
        }
      }
    }
    std::stable_sort(hyps_.begin(), hyps_.end(),
                     [](const Hyp& p, const Hyp& q) { return p.views.size() > q.views.size(); });
    out->clear();
    for (Hyp& h : hyps_) {
      std::vector<std::pair<int, int>> free_views;
      for (const auto& v : h.views) {
        if (!used_[v.first][v.second]) free_views.push_back(v);
      }
      if (free_views.size() < 2 || used_[h.views[0].first][h.views[0].second] ||
          used_[h.views[1].first][h.views[1].second]) {
        continue;
      }
      Eigen::Vector3d x;
      if (!Linear(free_views, &x)) continue;
      for (const auto& v : free_views) used_[v.first][v.second] = 1;
      out->push_back(x);
    }
  }

 private:
  struct Hyp {
    std::vector<std::pair<int, int>> views;
  };
  bool Linear(const std::vector<std::pair<int, int>>& views, Eigen::Vector3d* x) const {
    Eigen::Matrix3d A = Eigen::Matrix3d::Zero();
    Eigen::Vector3d b = Eigen::Vector3d::Zero();
    for (const auto& [c, i] : views) {
      const Eigen::Vector2d& p = xy_[c][i];
      const Eigen::Matrix3d& R = rig_[c].R;
      const Eigen::Vector3d& t = rig_[c].t;
      const Eigen::Vector3d r1 = p.x() * R.row(2).transpose() - R.row(0).transpose();
      const Eigen::Vector3d r2 = p.y() * R.row(2).transpose() - R.row(1).transpose();
      A += r1 * r1.transpose() + r2 * r2.transpose();
      b += r1 * (t.x() - p.x() * t.z()) + r2 * (t.y() - p.y() * t.z());
    }
    Eigen::LDLT<Eigen::Matrix3d> ldlt(A);
    if (ldlt.info() != Eigen::Success) return false;
    *x = ldlt.solve(b);
    return x->allFinite();
  }

  const std::vector<CameraModel>& rig_;
  std::vector<reconstruction::Triangulator::CameraPair> pairs_;
  std::vector<std::vector<Eigen::Vector2d>> xy_;
  std::vector<std::vector<double>> gate_;
  std::vector<std::vector<std::uint8_t>> used_;
  std::vector<Hyp> hyps_;
};

// The OpenCV peer: two-view DLT of the true correspondences, widest pair (the Triangulator's
// pair order) of the cameras that saw each marker.
class OpenCvTrueCorrespondences {
 public:
  OpenCvTrueCorrespondences(const std::vector<CameraModel>& rig,
                            const reconstruction::Triangulator& t)
      : rig_(rig) {
    const int nc = static_cast<int>(rig.size());
    rank_.assign(nc * nc, 1 << 30);
    for (size_t k = 0; k < t.pairs().size(); ++k) {
      rank_[t.pairs()[k].a * nc + t.pairs()[k].b] = static_cast<int>(k);
    }
    for (const CameraModel& c : rig) {
      const auto& k = c.intrinsics;
      K_.push_back((cv::Mat_<double>(3, 3) << k.fx, 0, k.cx, 0, k.fy, k.cy, 0, 0, 1));
      dist_.push_back((cv::Mat_<double>(1, 5) << k.k1, k.k2, k.p1, k.p2, k.k3));
      cv::Mat P(3, 4, CV_64F);
      for (int r = 0; r < 3; ++r) {
        for (int q = 0; q < 3; ++q) P.at<double>(r, q) = c.R(r, q);
        P.at<double>(r, 3) = c.t(r);
      }
      P_.push_back(P);
    }
  }

  void Run(const Scene& scene, std::vector<Eigen::Vector3d>* out) {
    const int nc = static_cast<int>(rig_.size());
    // Undistort every centroid of every camera (normalised coordinates).
    undistorted_.resize(nc);
    for (int c = 0; c < nc; ++c) {
      pixels_.clear();
      for (const Centroid& k : scene.set.cameras[c].centroids) {
        pixels_.emplace_back(static_cast<float>(k.pixel.x()), static_cast<float>(k.pixel.y()));
      }
      undistorted_[c].clear();
      if (!pixels_.empty()) cv::undistortPoints(pixels_, undistorted_[c], K_[c], dist_[c]);
    }
    // Group the markers by their widest pair, one triangulatePoints call per pair.
    for (auto& g : groups_) g.clear();
    groups_.resize(nc * nc);
    for (size_t m = 0; m < scene.observed.size(); ++m) {
      const auto& obs = scene.observed[m];
      if (obs.size() < 2) continue;
      int best = -1, best_rank = 1 << 30;
      for (size_t i = 0; i < obs.size(); ++i) {
        for (size_t j = i + 1; j < obs.size(); ++j) {
          const int r = rank_[obs[i].first * nc + obs[j].first];
          if (r < best_rank) best_rank = r, best = static_cast<int>(i * 64 + j);
        }
      }
      const auto& va = obs[best / 64];
      const auto& vb = obs[best % 64];
      groups_[va.first * nc + vb.first].push_back({va.second, vb.second});
    }
    out->clear();
    for (int a = 0; a < nc; ++a) {
      for (int b = 0; b < nc; ++b) {
        const auto& g = groups_[a * nc + b];
        if (g.empty()) continue;
        pa_.clear();
        pb_.clear();
        for (const auto& [i, j] : g) {
          pa_.push_back(undistorted_[a][i]);
          pb_.push_back(undistorted_[b][j]);
        }
        cv::Mat X;
        cv::triangulatePoints(P_[a], P_[b], pa_, pb_, X);
        X.convertTo(X, CV_64F);
        for (int k = 0; k < X.cols; ++k) {
          const double w = X.at<double>(3, k);
          out->emplace_back(X.at<double>(0, k) / w, X.at<double>(1, k) / w, X.at<double>(2, k) / w);
        }
      }
    }
  }

 private:
  const std::vector<CameraModel>& rig_;
  std::vector<int> rank_;
  std::vector<cv::Mat> K_, dist_, P_;
  std::vector<cv::Point2f> pixels_, pa_, pb_;
  std::vector<std::vector<cv::Point2f>> undistorted_;
  std::vector<std::vector<std::pair<int, int>>> groups_;
};

// This thread's CPU time, microseconds: what a frame set costs without the time the scheduler
// gave other processes (the machine is shared; wall-clock percentiles include preemption).
double ThreadCpuMicros() {
  timespec ts{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return 1e6 * ts.tv_sec + 1e-3 * ts.tv_nsec;
}

struct Timing {
  std::vector<double> wall_us, cpu_us;
  Clock::time_point wall0;
  double cpu0 = 0;
  void Start() {
    cpu0 = ThreadCpuMicros();
    wall0 = Clock::now();
  }
  void Stop() {
    wall_us.push_back(std::chrono::duration<double, std::micro>(Clock::now() - wall0).count());
    cpu_us.push_back(ThreadCpuMicros() - cpu0);
  }
  // The capture pipeline's percentile (nearest rank), so that the figures here and the live
  // pipeline's are the same statistic.
  static double Percentile(std::vector<double>& v, double p) { return daemon::Percentile(&v, 100 * p); }
};

void Report(const char* name, Timing& t, const Score& s) {
  std::printf(
      "  %-34s cpu p50 %6.1f p99 %6.1f us | wall p50 %6.1f p99 %7.1f us | rms %.4f mm "
      "(bound %.4f)  recall %.5f  ghosts %ld / %ld = %.5f\n",
      name, Timing::Percentile(t.cpu_us, 0.5), Timing::Percentile(t.cpu_us, 0.99),
      Timing::Percentile(t.wall_us, 0.5), Timing::Percentile(t.wall_us, 0.99),
      1e3 * std::sqrt(s.sum_sq / std::max(1L, s.true_points)),
      1e3 * std::sqrt(s.sum_crlb / std::max(1L, s.true_points)),
      static_cast<double>(s.found) / std::max(1L, s.eligible), s.ghosts, s.points,
      static_cast<double>(s.ghosts) / std::max(1L, s.points));
}

}  // namespace

int main(int argc, char** argv) {
  int reps = 5, strays = 3, stride = 7;
  bool peers = true;
  for (int i = 1; i < argc; ++i) {
    auto next = [&]() {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "triangulate: %s needs a value\n", argv[i]);
        std::exit(2);
      }
      return std::atoi(argv[++i]);
    };
    if (!std::strcmp(argv[i], "--reps"))
      reps = next();
    else if (!std::strcmp(argv[i], "--strays"))
      strays = next();
    else if (!std::strcmp(argv[i], "--stride"))
      stride = next();
    else if (!std::strcmp(argv[i], "--no-peers"))
      peers = false;
    else {
      std::fprintf(stderr,
                   "usage: triangulate [--reps R] [--strays K] [--stride S] [--no-peers]\n");
      return 2;
    }
  }
  if (reps < 1 || strays < 0 || stride < 1) {
    std::fprintf(stderr, "triangulate: --reps and --stride must be >= 1, --strays >= 0\n");
    return 2;
  }

  cv::setNumThreads(1);  // every contender single-threaded
  const auto rig = sim::MakeCameraRig(sim::CameraRigOptions{});
  sim::SimulationOptions so;
  so.noise_mm = 0.0;
  so.duration_scale = 0.5;
  sim::SimulatedSession session;
  if (Status s = sim::SimulateSession(so, &session); !s.ok()) {
    std::fprintf(stderr, "triangulate: %s\n", s.message().c_str());
    return 1;
  }
  std::vector<std::vector<Eigen::Vector3d>> frames;
  for (const sim::SimulatedTrial& t : session.trials) {
    for (int f = 0; f < t.markers.num_frames(); f += stride) {
      std::vector<Eigen::Vector3d> m;
      for (int k = 0; k < t.markers.num_markers(); ++k) {
        if (t.markers.Has(f, k)) m.push_back(t.markers.At(f, k));
      }
      frames.push_back(std::move(m));
    }
  }

  reconstruction::TriangulationOptions lab;
  lab.volume_min = Eigen::Vector3d(-2.5, -2.5, -0.1);
  lab.volume_max = Eigen::Vector3d(2.5, 2.5, 2.5);
  std::unique_ptr<reconstruction::Triangulator> with_volume, unbounded;
  if (Status s = reconstruction::Triangulator::Create(rig, lab, &with_volume);
      !s.ok() || !reconstruction::Triangulator::Create(rig, {}, &unbounded).ok()) {
    std::fprintf(stderr, "triangulate: %s\n", s.message().c_str());
    return 1;
  }

  std::printf(
      "triangulate: %zu cameras, %zu frame sets of %zu markers, %d strays per camera, "
      "%d passes\n",
      rig.size(), frames.size(), frames[0].size(), strays, reps);
  for (double hide : {0.0, 0.2}) {
    std::vector<Scene> scenes;
    for (size_t f = 0; f < frames.size(); ++f) {
      scenes.push_back(MakeScene(rig, frames[f], hide, strays, f));
    }
    std::printf("%s:\n", hide == 0 ? "every observation" : "20% of the observations hidden");

    for (auto* t : {with_volume.get(), unbounded.get()}) {
      reconstruction::TriangulationWorkspace ws;
      std::vector<TriangulatedPoint> points;
      std::vector<Eigen::Vector3d> positions;
      Timing timing;
      Score score;
      for (const Scene& s : scenes) t->Triangulate(s.set, &ws, &points);  // warm-up
      for (int r = 0; r < reps; ++r) {
        for (size_t f = 0; f < scenes.size(); ++f) {
          timing.Start();
          t->Triangulate(scenes[f].set, &ws, &points);
          timing.Stop();
          if (r == 0) {
            positions.clear();
            for (const TriangulatedPoint& p : points) positions.push_back(p.position);
            score.Add(rig, frames[f], scenes[f], positions);
          }
        }
      }
      Report(t == with_volume.get() ? "Triangulator (lab volume)" : "Triangulator (unbounded)",
             timing, score);
    }
    if (!peers) continue;
    {
      BruteForce brute(rig, *unbounded);
      std::vector<Eigen::Vector3d> positions;
      Timing timing;
      Score score;
      for (const Scene& s : scenes) brute.Run(s.set, &positions);
      for (int r = 0; r < reps; ++r) {
        for (size_t f = 0; f < scenes.size(); ++f) {
          timing.Start();
          brute.Run(scenes[f].set, &positions);
          timing.Stop();
          if (r == 0) score.Add(rig, frames[f], scenes[f], positions);
        }
      }
      Report("brute force all pairs (unbounded)", timing, score);
    }
    {
      OpenCvTrueCorrespondences ocv(rig, *unbounded);
      std::vector<Eigen::Vector3d> positions;
      Timing timing;
      Score score;
      for (const Scene& s : scenes) ocv.Run(s, &positions);
      for (int r = 0; r < reps; ++r) {
        for (size_t f = 0; f < scenes.size(); ++f) {
          timing.Start();
          ocv.Run(scenes[f], &positions);
          timing.Stop();
          if (r == 0) score.Add(rig, frames[f], scenes[f], positions);
        }
      }
      Report("OpenCV 2-view DLT, true matches", timing, score);
    }
  }
  return 0;
}
