// Bad data at the triangulation stage (daemon/detection_health.h): NaN and infinite centroids
// from a broken camera, a camera with ten times the usual blobs, a camera whose calibration is
// 5 cm off. Synthetic frame sets of the simulated rig's cameras (sim/camera_rig.h): markers
// projected exactly, 0.1 px of noise.
#include <time.h>

#include <cmath>
#include <cstdio>
#include <limits>
#include <memory>
#include <random>
#include <vector>

#include <gtest/gtest.h>

#include "daemon/detection_health.h"
#include "reconstruction/triangulation.h"
#include "sim/camera_rig.h"
#include "tests/cpu_time_test_util.h"

namespace mocap {
namespace {

using daemon::CameraHealth;
using daemon::DetectionHealth;
using reconstruction::CameraModel;
using reconstruction::DetectionSet;
using reconstruction::TriangulatedPoint;

constexpr int kCameras = 8;
constexpr int kMarkers = 40;

using testutil::ThreadCpuMs;

class SyntheticRig {
 public:
  SyntheticRig() : truth_(sim::MakeCameraRig(sim::CameraRigOptions())) {}
  const std::vector<CameraModel>& truth() const { return truth_; }

  // `kMarkers` markers somewhere in the volume, seen by every camera that has them in its image.
  DetectionSet Set(std::uint64_t sequence) {
    std::uniform_real_distribution<double> xy(-0.8, 0.8), z(0.2, 1.8);
    std::normal_distribution<double> noise(0, 0.1);
    DetectionSet set;
    set.sequence = sequence;
    set.present.assign(kCameras, true);
    set.cameras.resize(kCameras);
    std::vector<Eigen::Vector3d> markers;
    for (int m = 0; m < kMarkers; ++m) markers.emplace_back(xy(rng_), xy(rng_), z(rng_));
    for (int c = 0; c < kCameras; ++c) {
      set.cameras[c].camera = c;
      set.cameras[c].sequence = sequence;
      const auto& k = truth_[c].intrinsics;
      for (const Eigen::Vector3d& m : markers) {
        Eigen::Vector2d px;
        if (!truth_[c].Project(m, &px) || px.x() < 0 || px.y() < 0 || px.x() > k.width - 1 ||
            px.y() > k.height - 1)
          continue;
        reconstruction::Centroid cen;
        cen.pixel = px + Eigen::Vector2d(noise(rng_), noise(rng_));
        set.cameras[c].centroids.push_back(cen);
      }
    }
    return set;
  }
  // `n` blobs anywhere in camera c's image (sunlight, a reflective watch).
  void AddBlobs(DetectionSet* set, int c, int n) {
    std::uniform_real_distribution<double> u(0, 1);
    const auto& k = truth_[c].intrinsics;
    for (int i = 0; i < n; ++i) {
      reconstruction::Centroid cen;
      cen.pixel = Eigen::Vector2d(u(rng_) * (k.width - 1), u(rng_) * (k.height - 1));
      set->cameras[c].centroids.push_back(cen);
    }
  }

 private:
  std::vector<CameraModel> truth_;
  std::mt19937 rng_{7};
};

std::unique_ptr<reconstruction::Triangulator> MakeTriangulator(std::vector<CameraModel> cameras) {
  std::unique_ptr<reconstruction::Triangulator> t;
  EXPECT_TRUE(reconstruction::Triangulator::Create(std::move(cameras), {}, &t).ok());
  return t;
}

TEST(DetectionHealth, NonFiniteCentroidsAreDroppedAndCounted) {
  SyntheticRig rig;
  auto triangulator = MakeTriangulator(rig.truth());
  DetectionHealth health(kCameras);
  reconstruction::TriangulationWorkspace ws;
  DetectionSet scratch;
  const DetectionSet clean = rig.Set(1);
  // A clean set goes through as it is (no copy).
  EXPECT_EQ(&health.Sanitize(clean, &scratch), &clean);
  std::vector<TriangulatedPoint> expected, got;
  ASSERT_TRUE(triangulator->Triangulate(clean, &ws, &expected).ok());
  ASSERT_GE(expected.size(), 35u);

  DetectionSet broken = clean;
  const double nan = std::numeric_limits<double>::quiet_NaN(), inf = std::numeric_limits<double>::infinity();
  for (const Eigen::Vector2d& bad : {Eigen::Vector2d(nan, 100), Eigen::Vector2d(200, nan),
                                     Eigen::Vector2d(inf, 5), Eigen::Vector2d(-inf, -inf)}) {
    reconstruction::Centroid cen;
    cen.pixel = bad;
    broken.cameras[2].centroids.insert(broken.cameras[2].centroids.begin(), cen);
  }
  const DetectionSet& used = health.Sanitize(broken, &scratch);
  EXPECT_EQ(&used, &scratch);
  ASSERT_TRUE(triangulator->Triangulate(used, &ws, &got).ok());
  // The same points as without the broken centroids.
  ASSERT_EQ(got.size(), expected.size());
  for (std::size_t i = 0; i < got.size(); ++i) {
    EXPECT_TRUE(got[i].position.allFinite());
    EXPECT_LT((got[i].position - expected[i].position).norm(), 1e-9);
  }
  const std::vector<CameraHealth> h = health.Snapshot();
  EXPECT_EQ(h[2].nonfinite_centroids, 4u);
  for (int c = 0; c < kCameras; ++c)
    if (c != 2) EXPECT_EQ(h[c].nonfinite_centroids, 0u) << c;
}

TEST(DetectionHealth, TenTimesTheBlobsSitsTheCameraOutInBoundedTime) {
  SyntheticRig rig;
  auto triangulator = MakeTriangulator(rig.truth());
  DetectionHealth health(kCameras);
  reconstruction::TriangulationWorkspace ws;
  DetectionSet scratch;
  std::vector<TriangulatedPoint> points;
  double clean_ms = 0, flooded_ms = 0, unguarded_ms = 0;
  std::size_t clean_points = 0, flooded_points = 0;
  const int sets = 20;
  for (int i = 0; i < sets; ++i) {
    DetectionSet set = rig.Set(static_cast<std::uint64_t>(i));
    double t0 = ThreadCpuMs();
    ASSERT_TRUE(triangulator->Triangulate(health.Sanitize(set, &scratch), &ws, &points).ok());
    clean_ms += ThreadCpuMs() - t0;
    clean_points += points.size();
    // Cameras 5 and 6 see ten times the markers' number of blobs.
    rig.AddBlobs(&set, 5, 10 * kMarkers);
    rig.AddBlobs(&set, 6, 10 * kMarkers);
    t0 = ThreadCpuMs();
    ASSERT_TRUE(triangulator->Triangulate(health.Sanitize(set, &scratch), &ws, &points).ok());
    flooded_ms += ThreadCpuMs() - t0;
    flooded_points += points.size();
    t0 = ThreadCpuMs();
    ASSERT_TRUE(triangulator->Triangulate(set, &ws, &points).ok());
    unguarded_ms += ThreadCpuMs() - t0;
  }
  std::printf("CPU per set: clean %.3f ms, 10x blobs in 2 cameras %.3f ms (without the guard %.3f ms)\n",
              clean_ms / sets, flooded_ms / sets, unguarded_ms / sets);
  // The flooded cameras sat out: the set costs no more than a clean one (thread CPU time, so a
  // loaded machine does not change it), and still gives most markers from the six others.
  EXPECT_LT(flooded_ms, 1.5 * clean_ms + 1.0);
  EXPECT_GT(flooded_points, 0.9 * clean_points);
  const std::vector<CameraHealth> h = health.Snapshot();
  EXPECT_EQ(h[5].overfull_sets, static_cast<std::uint64_t>(sets));
  EXPECT_EQ(h[6].overfull_sets, static_cast<std::uint64_t>(sets));
  EXPECT_EQ(h[0].overfull_sets, 0u);
  // Every camera flooded: no points, no failure.
  DetectionSet all = rig.Set(99);
  for (int c = 0; c < kCameras; ++c) rig.AddBlobs(&all, c, 10 * kMarkers);
  ASSERT_TRUE(triangulator->Triangulate(health.Sanitize(all, &scratch), &ws, &points).ok());
  EXPECT_TRUE(points.empty());
}

TEST(DetectionHealth, ACameraCalibratedFiveCentimetresOffIsNamed) {
  SyntheticRig rig;
  std::vector<CameraModel> calibration = rig.truth();
  // Camera 3 was knocked: the calibration puts it 5 cm from where it is.
  const Eigen::Vector3d moved(0.03, -0.03, 0.028);  // |moved| = 5.0 cm
  calibration[3].t -= calibration[3].R * moved;
  for (bool off : {false, true}) {
    const std::vector<CameraModel>& used = off ? calibration : rig.truth();
    auto triangulator = MakeTriangulator(used);
    DetectionHealth health(kCameras);
    reconstruction::TriangulationWorkspace ws;
    DetectionSet scratch;
    std::vector<TriangulatedPoint> points;
    for (int i = 0; i < 600; ++i) {
      const DetectionSet set = rig.Set(static_cast<std::uint64_t>(i));
      const DetectionSet& clean = health.Sanitize(set, &scratch);
      ASSERT_TRUE(triangulator->Triangulate(clean, &ws, &points).ok());
      health.Observe(clean, points, used);
    }
    const std::vector<CameraHealth> h = health.Snapshot();
    for (int c = 0; c < kCameras; ++c) {
      std::printf("%s camera %d: reprojection %.2f px over %d samples\n", off ? "off" : "true", c,
                  h[c].reprojection_px, h[c].reprojection_samples);
      EXPECT_GE(h[c].reprojection_samples, 50) << c;
      const bool bad = off && c == 3;
      EXPECT_EQ(h[c].calibration_suspect, bad) << c;
      if (bad) EXPECT_GT(h[c].reprojection_px, 5.0);
      else EXPECT_LT(h[c].reprojection_px, 1.0) << c;
    }
  }
}

}  // namespace
}  // namespace mocap
