// 2D marker detection (reconstruction/detection.h) and the static-reflection mask
// (reconstruction/reflection_mask.h) against known truth: synthetic blobs whose pixels are the
// exact integral of a Gaussian profile over each pixel square, so the true centre is exact.
#include <gtest/gtest.h>

#include <atomic>
#include <cmath>
#include <cstdlib>
#include <new>
#include <random>
#include <vector>

#include "reconstruction/detection.h"
#include "reconstruction/reflection_mask.h"

// Counts heap allocations while a test enables it: Eigen's malloc check does not see std::vector.
namespace {
std::atomic<long> g_allocations{0};
std::atomic<bool> g_counting{false};
}  // namespace

// GCC cannot see that this operator new pairs with the free() below.
#pragma GCC diagnostic ignored "-Wmismatched-new-delete"
void* operator new(std::size_t size) {
  if (g_counting.load(std::memory_order_relaxed)) g_allocations.fetch_add(1);
  if (void* p = std::malloc(size == 0 ? 1 : size)) return p;
  throw std::bad_alloc();
}
void operator delete(void* p) noexcept { std::free(p); }
void operator delete(void* p, std::size_t) noexcept { std::free(p); }

namespace mocap::reconstruction {
namespace {

using drivers::ImageView;
using drivers::PixelFormat;

// A test image with its own storage; stride may exceed the row.
struct TestImage {
  int width = 0, height = 0;
  PixelFormat format = PixelFormat::kMono8;
  std::ptrdiff_t stride = 0;
  std::vector<std::uint8_t> bytes;

  TestImage(int w, int h, PixelFormat f, int padding_bytes = 0)
      : width(w), height(h), format(f),
        stride(static_cast<std::ptrdiff_t>(w) * drivers::BytesPerPixel(f) + padding_bytes),
        bytes(static_cast<std::size_t>(stride) * h, 0) {}
  int max_value() const { return (1 << drivers::BitDepth(format)) - 1; }
  void Set(int x, int y, int v) {
    v = std::clamp(v, 0, max_value());
    if (format == PixelFormat::kMono8) {
      bytes[y * stride + x] = static_cast<std::uint8_t>(v);
    } else {
      const auto u = static_cast<std::uint16_t>(v);
      std::memcpy(&bytes[y * stride + 2 * x], &u, 2);
    }
  }
  int Get(int x, int y) const {
    if (format == PixelFormat::kMono8) return bytes[y * stride + x];
    std::uint16_t u;
    std::memcpy(&u, &bytes[y * stride + 2 * x], 2);
    return u;
  }
  ImageView view() const { return ImageView{bytes.data(), width, height, stride, format}; }
};

// Radiance in double, quantised into a TestImage (rounded, clipped at the format's maximum).
struct Scene {
  int width, height;
  std::vector<double> v;
  Scene(int w, int h, double background = 0) : width(w), height(h), v(std::size_t(w) * h, background) {}

  // A Gaussian spot of standard deviation sigma centred at (cx, cy), integrated over each pixel
  // square [x - 0.5, x + 0.5] x [y - 0.5, y + 0.5]; `peak` is the value of a pixel centred on it.
  void AddGaussian(double cx, double cy, double sigma, double peak) {
    auto cdf = [](double t) { return 0.5 * std::erfc(-t / std::sqrt(2.0)); };
    auto cell = [&](int i, double c) { return cdf((i + 0.5 - c) / sigma) - cdf((i - 0.5 - c) / sigma); };
    const double norm = std::pow(cdf(0.5 / sigma) - cdf(-0.5 / sigma), 2);
    const int r = static_cast<int>(std::ceil(6 * sigma)) + 1;
    for (int y = std::max(0, int(cy) - r); y <= std::min(height - 1, int(cy) + r); ++y) {
      const double gy = cell(y, cy);
      for (int x = std::max(0, int(cx) - r); x <= std::min(width - 1, int(cx) + r); ++x)
        v[std::size_t(y) * width + x] += peak * cell(x, cx) * gy / norm;
    }
  }
  void AddRect(int x0, int y0, int w, int h, double value) {
    for (int y = y0; y < y0 + h; ++y)
      for (int x = x0; x < x0 + w; ++x) v[std::size_t(y) * width + x] += value;
  }
  void AddNoise(double sigma, std::mt19937& rng) {
    std::normal_distribution<double> n(0, sigma);
    for (double& p : v) p += n(rng);
  }
  TestImage Render(PixelFormat f = PixelFormat::kMono8, double scale = 1, int padding = 0) const {
    TestImage img(width, height, f, padding);
    for (int y = 0; y < height; ++y)
      for (int x = 0; x < width; ++x)
        img.Set(x, y, static_cast<int>(std::lround(scale * v[std::size_t(y) * width + x])));
    return img;
  }
};

struct Truth {
  double x, y, sigma, peak;
};

// Finds the detection nearest to (x, y); returns its distance.
double Nearest(const std::vector<Centroid>& cs, double x, double y, const Centroid** hit = nullptr) {
  double best = 1e9;
  for (const Centroid& c : cs) {
    const double d = std::hypot(c.pixel.x() - x, c.pixel.y() - y);
    if (d < best) {
      best = d;
      if (hit) *hit = &c;
    }
  }
  return best;
}

// Non-overlapping blobs on a grid with random subpixel centres, sizes and brightness.
std::vector<Truth> MakeBlobs(Scene* scene, int count, std::mt19937& rng, double smin = 0.9,
                             double smax = 2.8, double pmin = 120, double pmax = 250) {
  std::uniform_real_distribution<double> u(0, 1);
  std::vector<Truth> truth;
  const int cell = 32;
  const int cols = (scene->width - 2 * cell) / cell;
  for (int i = 0; i < count; ++i) {
    const double x = cell + (i % cols) * cell + 8 + 16 * u(rng);
    const double y = cell + (i / cols) * cell + 8 + 16 * u(rng);
    const double s = smin + (smax - smin) * u(rng);
    const double p = pmin + (pmax - pmin) * u(rng);
    scene->AddGaussian(x, y, s, p);
    truth.push_back({x, y, s, p});
  }
  return truth;
}

DetectionOptions Permissive(int threshold) {
  DetectionOptions o;
  o.threshold = threshold;
  o.min_area_px = 1;
  o.max_area_px = 1 << 30;
  o.min_roundness = 0;
  o.drop_border_blobs = false;
  o.max_centroids = 1 << 30;
  o.centroid = DetectionOptions::CentroidMethod::kThresholdWeighted;
  return o;
}

TEST(Detection, NoiseFreeCentresWithin003PxMono8) {
  std::mt19937 rng(7);
  Scene scene(1280, 1024);
  const std::vector<Truth> truth = MakeBlobs(&scene, 300, rng);
  const TestImage img = scene.Render();
  DetectionOptions o;
  o.threshold = 40;
  DetectionWorkspace ws;
  std::vector<Centroid> cs;
  DetectionStats st;
  ASSERT_TRUE(DetectMarkers(img.view(), o, nullptr, &ws, &cs, &st).ok());
  ASSERT_EQ(cs.size(), truth.size());
  double worst = 0;
  for (const Truth& t : truth) worst = std::max(worst, Nearest(cs, t.x, t.y));
  EXPECT_LE(worst, 0.03);
  EXPECT_EQ(st.blobs, 300);
  EXPECT_EQ(st.accepted, 300);
  // Roundness of a round spot stays high even for the smallest ones.
  for (const Centroid& c : cs) EXPECT_GT(c.roundness, 0.8f);
}

TEST(Detection, WindowedCentreHardlyDependsOnTheBackgroundLevel) {
  std::mt19937 rng(17);
  Scene scene(640, 320, 15);  // a black level of 15 DN
  const std::vector<Truth> truth = MakeBlobs(&scene, 50, rng);
  const TestImage img = scene.Render();
  DetectionOptions right, wrong;
  right.threshold = wrong.threshold = 60;
  right.background_dn = 15;
  wrong.background_dn = 0;
  DetectionWorkspace ws;
  std::vector<Centroid> a, b;
  ASSERT_TRUE(DetectMarkers(img.view(), right, nullptr, &ws, &a).ok());
  ASSERT_TRUE(DetectMarkers(img.view(), wrong, nullptr, &ws, &b).ok());
  ASSERT_EQ(a.size(), truth.size());
  ASSERT_EQ(b.size(), truth.size());
  double worst_right = 0, worst_shift = 0;
  for (std::size_t i = 0; i < a.size(); ++i) {
    worst_shift = std::max(worst_shift, (a[i].pixel - b[i].pixel).norm());
    worst_right = std::max(worst_right, Nearest(a, truth[i].x, truth[i].y));
  }
  EXPECT_LE(worst_right, 0.03);
  EXPECT_LT(worst_shift, 0.005);
}

TEST(Detection, Mono16AndMono12GiveTheSameCentres) {
  std::mt19937 rng(8);
  Scene scene(700, 300);
  const std::vector<Truth> truth = MakeBlobs(&scene, 60, rng);
  DetectionWorkspace ws;
  std::vector<Centroid> c8, c12, c16;
  DetectionOptions o;
  o.threshold = 40;
  ASSERT_TRUE(DetectMarkers(scene.Render().view(), o, nullptr, &ws, &c8).ok());
  o.threshold = 40 * 16;
  ASSERT_TRUE(DetectMarkers(scene.Render(PixelFormat::kMono12, 16).view(), o, nullptr, &ws, &c12).ok());
  o.threshold = 40 * 256;
  ASSERT_TRUE(DetectMarkers(scene.Render(PixelFormat::kMono16, 256, 6).view(), o, nullptr, &ws, &c16).ok());
  ASSERT_EQ(c8.size(), truth.size());
  ASSERT_EQ(c12.size(), truth.size());
  ASSERT_EQ(c16.size(), truth.size());
  double worst12 = 0, worst16 = 0;
  for (const Truth& t : truth) {
    worst12 = std::max(worst12, Nearest(c12, t.x, t.y));
    worst16 = std::max(worst16, Nearest(c16, t.x, t.y));
  }
  EXPECT_LE(worst12, 0.03);
  EXPECT_LE(worst16, 0.03);
  for (std::size_t i = 0; i < c16.size(); ++i) EXPECT_GT(c16[i].peak, 100 * 256);
}

TEST(Detection, NoiseErrorIsConsistentWithSigma) {
  // The error that noise adds (noisy centre - noise-free centre of the same blob) divided by
  // sigma_px must have unit RMS per axis; the floor is off so sigma_px is the noise model alone.
  // Both centre estimates, each with its own propagation (detection.h).
  for (auto method : {DetectionOptions::CentroidMethod::kGaussianWindowed,
                      DetectionOptions::CentroidMethod::kThresholdWeighted}) {
    SCOPED_TRACE(method == DetectionOptions::CentroidMethod::kGaussianWindowed ? "windowed"
                                                                               : "thresholded");
    std::mt19937 rng(9);
    const double noise = 6, background = 20;
    DetectionOptions o;
    o.centroid = method;
    o.threshold = 70;  // background + 8 sigma: noise alone never crosses it
    o.background_dn = background;
    o.read_noise_dn = noise;
    o.sigma_floor_px = 0;
    DetectionWorkspace ws;
    double sum_sq = 0;
    int samples = 0;
    double mean_sigma = 0;
    for (int frame = 0; frame < 6; ++frame) {
      Scene scene(800, 400, background);
      const std::vector<Truth> truth = MakeBlobs(&scene, 80, rng, 1.2, 2.5, 150, 230);
      std::vector<Centroid> clean, noisy;
      ASSERT_TRUE(DetectMarkers(scene.Render().view(), o, nullptr, &ws, &clean).ok());
      scene.AddNoise(noise, rng);
      ASSERT_TRUE(DetectMarkers(scene.Render().view(), o, nullptr, &ws, &noisy).ok());
      ASSERT_EQ(clean.size(), truth.size());
      ASSERT_EQ(noisy.size(), truth.size());
      for (const Centroid& c : clean) {
        const Centroid* n = nullptr;
        ASSERT_LT(Nearest(noisy, c.pixel.x(), c.pixel.y(), &n), 0.5);
        const Eigen::Vector2d d = (n->pixel - c.pixel) / n->sigma_px;
        sum_sq += d.squaredNorm();
        samples += 2;
        mean_sigma += n->sigma_px;
      }
    }
    const double rms = std::sqrt(sum_sq / samples);
    mean_sigma /= samples / 2;
    EXPECT_GT(rms, 0.8) << "sigma_px overstates the noise; mean sigma " << mean_sigma;
    EXPECT_LT(rms, 1.25) << "sigma_px understates the noise; mean sigma " << mean_sigma;
    EXPECT_GT(mean_sigma, 0.01);  // the test is not trivial: noise moves centres measurably
  }
}

TEST(Detection, SizeAndRoundnessFiltersRejectWhatTheyShould) {
  Scene scene(400, 200);
  scene.AddGaussian(50.3, 50.6, 1.5, 200);  // a marker: kept
  scene.AddRect(100, 50, 1, 1, 200);         // 1 px hot pixel: too small
  scene.AddRect(150, 50, 2, 1, 200);         // 2 px: too small
  scene.AddRect(200, 30, 30, 30, 200);       // 900 px lamp: too large
  scene.AddRect(260, 50, 12, 2, 200);        // a 12 x 2 streak: not round
  scene.AddGaussian(320.0, 50.0, 1.5, 200);  // a blob stretched by a second one 1.5 px away
  scene.AddGaussian(321.5, 50.0, 1.5, 200);
  const TestImage img = scene.Render();
  DetectionOptions o;
  o.threshold = 50;
  DetectionWorkspace ws;
  std::vector<Centroid> cs;
  DetectionStats st;
  ASSERT_TRUE(DetectMarkers(img.view(), o, nullptr, &ws, &cs, &st).ok());
  ASSERT_EQ(cs.size(), 2u);  // the marker and the merged pair (roundness ~0.75 passes 0.6)
  EXPECT_LT(Nearest(cs, 50.3, 50.6), 0.03);
  EXPECT_EQ(st.blobs, 6);
  EXPECT_EQ(st.too_small, 2);
  EXPECT_EQ(st.too_large, 1);
  EXPECT_EQ(st.not_round, 1);
  // A stricter roundness drops the stretched pair too.
  o.min_roundness = 0.9;
  ASSERT_TRUE(DetectMarkers(img.view(), o, nullptr, &ws, &cs, &st).ok());
  ASSERT_EQ(cs.size(), 1u);
  EXPECT_EQ(st.not_round, 2);
  // Area and roundness as measured: the marker's area is its bright pixel count.
  int bright = 0;
  for (int y = 40; y < 62; ++y)
    for (int x = 40; x < 62; ++x) bright += img.Get(x, y) >= 50;
  EXPECT_EQ(cs[0].area_px, bright);
}

TEST(Detection, TouchingBlobsAreSplitIntoTheirSpotsOrRejectedNeverMisreported) {
  Scene scene(300, 120);
  // Touching: 4 px apart, sigma 1.5 (bright regions overlap) -> one elongated blob.
  scene.AddGaussian(60.2, 60.0, 1.5, 200);
  scene.AddGaussian(64.2, 60.0, 1.5, 200);
  // Apart: 9 px apart with dark pixels between -> two blobs, each accurate.
  scene.AddGaussian(150.4, 60.3, 1.5, 200);
  scene.AddGaussian(159.4, 60.3, 1.5, 200);
  // Touching only diagonally: one pixel each, corner to corner -> one blob (8-connectivity).
  scene.AddRect(240, 60, 2, 2, 200);
  scene.AddRect(242, 62, 2, 2, 200);
  const TestImage img = scene.Render();
  DetectionOptions o;
  o.threshold = 50;
  o.min_area_px = 4;
  DetectionWorkspace ws;
  std::vector<Centroid> cs;
  DetectionStats st;
  // By default the two elongated blobs are fitted with two spots each, and each spot is found.
  ASSERT_TRUE(DetectMarkers(img.view(), o, nullptr, &ws, &cs, &st).ok());
  EXPECT_EQ(st.blobs, 4);
  EXPECT_EQ(st.split_attempts, 2);
  EXPECT_EQ(st.split, 2);
  EXPECT_EQ(st.not_round, 0);
  ASSERT_EQ(cs.size(), 6u);
  const std::vector<Eigen::Vector2d> spots = {{60.2, 60.0}, {64.2, 60.0}, {240.5, 60.5}, {242.5, 62.5}};
  for (const Eigen::Vector2d& t : spots) EXPECT_LT(Nearest(cs, t.x(), t.y()), 0.02) << t.transpose();
  EXPECT_LT(Nearest(cs, 150.4, 60.3), 0.03);
  EXPECT_LT(Nearest(cs, 159.4, 60.3), 0.03);

  // Without the split, as before it: the merged pair is dropped rather than misreported.
  o.split_overlapping = false;
  ASSERT_TRUE(DetectMarkers(img.view(), o, nullptr, &ws, &cs, &st).ok());
  EXPECT_EQ(st.blobs, 4);
  EXPECT_EQ(st.not_round, 2);  // the merged pair and the diagonal pair
  ASSERT_EQ(cs.size(), 2u);
  EXPECT_LT(Nearest(cs, 150.4, 60.3), 0.03);
  EXPECT_LT(Nearest(cs, 159.4, 60.3), 0.03);
  // Without the roundness filter the merged pair is one centroid halfway between.
  o.min_roundness = 0;
  ASSERT_TRUE(DetectMarkers(img.view(), o, nullptr, &ws, &cs, &st).ok());
  ASSERT_EQ(cs.size(), 4u);
  EXPECT_LT(Nearest(cs, 62.2, 60.0), 0.03);
  EXPECT_LT(Nearest(cs, 241.5, 61.5), 1e-9);
  const Centroid* merged = nullptr;
  Nearest(cs, 62.2, 60.0, &merged);
  EXPECT_LT(merged->roundness, 0.6f);
}

TEST(Detection, OverlappingSpotsCarryTheirOffsetInSigma) {
  // Two equal spots s apart that pass the roundness filter as one blob (not split): its centre
  // lies between them, s / 2 from either marker, and sigma_px must say about that much; a lone
  // spot's must not.
  for (const double sep : {2.0, 2.5, 3.0}) {
    SCOPED_TRACE(sep);
    Scene scene(200, 100);
    scene.AddGaussian(50.3, 50.2, 1.5, 200);
    scene.AddGaussian(50.3 + sep * 0.8, 50.2 + sep * 0.6, 1.5, 200);
    scene.AddGaussian(150.6, 50.4, 1.5, 200);  // alone
    const TestImage img = scene.Render();
    DetectionOptions o;
    o.threshold = 50;
    o.split_overlapping = false;
    DetectionWorkspace ws;
    std::vector<Centroid> cs;
    ASSERT_TRUE(DetectMarkers(img.view(), o, nullptr, &ws, &cs).ok());
    ASSERT_EQ(cs.size(), 2u);
    const Centroid *pair = nullptr, *lone = nullptr;
    const double offset = Nearest(cs, 50.3, 50.2, &pair);
    EXPECT_LT(Nearest(cs, 150.6, 50.4, &lone), 0.03);
    EXPECT_GT(offset, 0.3 * sep);  // the merged centre is well off either marker
    EXPECT_LT(pair->roundness, o.overlap_roundness);
    EXPECT_GT(pair->sigma_px, 0.5 * offset) << "offset " << offset;
    EXPECT_LT(pair->sigma_px, 2.0 * offset) << "offset " << offset;
    EXPECT_LT(lone->sigma_px, 0.05);
    // The term is what says it: without it the pair claims a lone spot's precision.
    o.overlap_roundness = 0;
    ASSERT_TRUE(DetectMarkers(img.view(), o, nullptr, &ws, &cs).ok());
    Nearest(cs, 50.3, 50.2, &pair);
    EXPECT_LT(pair->sigma_px, 0.05);
  }
  DetectionOptions bad;
  bad.overlap_roundness = 1.5;
  std::string error;
  EXPECT_FALSE(bad.IsValid(&error));
  EXPECT_NE(error.find("overlap_roundness"), std::string::npos) << error;
}

TEST(Detection, SplitSpotsAreAccurateAndTheirSigmaHonest) {
  // Pairs of overlapping markers (2.5-5 px apart, the fainter 50-100 % of the brighter, noise
  // 3 DN) at random angles; each blob is split and each spot found, its error explained by
  // sigma_px. A lone elongated spot (motion smear: an elliptical Gaussian) is never split.
  std::mt19937 rng(21);
  std::uniform_real_distribution<double> u(0, 1);
  DetectionOptions o;
  o.threshold = 50;
  o.background_dn = 10;
  o.read_noise_dn = 3;
  o.sigma_floor_px = 0;
  DetectionWorkspace ws;
  std::vector<Centroid> cs;
  DetectionStats st;
  int found = 0, pairs = 0, splits = 0;
  double sum_sq = 0, sum_sq_norm = 0;
  for (int trial = 0; trial < 200; ++trial) {
    Scene scene(64, 64, 10);
    const double sep = 2.5 + 2.5 * u(rng), angle = 2 * M_PI * u(rng), ratio = 0.5 + 0.5 * u(rng);
    const Eigen::Vector2d a(30 + u(rng), 30 + u(rng));
    const Eigen::Vector2d b = a + sep * Eigen::Vector2d(std::cos(angle), std::sin(angle));
    scene.AddGaussian(a.x(), a.y(), 1.3, 200);
    scene.AddGaussian(b.x(), b.y(), 1.3, 200 * ratio);
    scene.AddNoise(3, rng);
    ASSERT_TRUE(DetectMarkers(scene.Render().view(), o, nullptr, &ws, &cs, &st).ok());
    ++pairs;
    splits += st.split;
    if (cs.size() != 2) continue;
    for (const Eigen::Vector2d& t : {a, b}) {
      const Centroid* c = nullptr;
      const double e = Nearest(cs, t.x(), t.y(), &c);
      if (e > 1.0) continue;
      ++found;
      sum_sq += e * e;
      sum_sq_norm += e * e / (c->sigma_px * c->sigma_px);
    }
  }
  const double rms = std::sqrt(sum_sq / (2.0 * found));            // per axis
  const double norm_rms = std::sqrt(sum_sq_norm / (2.0 * found));  // per axis, in sigmas
  std::printf("%d of %d pairs split, %d spots found; error %.4f px RMS per axis, %.2f sigma\n",
              splits, pairs, found, rms, norm_rms);
  EXPECT_GE(splits, pairs * 95 / 100);
  EXPECT_GE(found, 2 * pairs * 95 / 100);
  EXPECT_LT(rms, 0.04);
  EXPECT_GT(norm_rms, 0.5);  // sigma_px neither overstates...
  EXPECT_LT(norm_rms, 2.0);  // ... nor understates the error much

  // One spot smeared along a direction (an elliptical Gaussian, roundness about 0.6): one centroid.
  for (int trial = 0; trial < 20; ++trial) {
    Scene scene(64, 64, 10);
    const double angle = M_PI * u(rng);
    const double ca = std::cos(angle), sa = std::sin(angle);
    for (int k = -6; k <= 6; ++k) {  // a streak of 13 sub-spots = a smooth oval
      scene.AddGaussian(30.3 + 0.25 * k * ca, 30.6 + 0.25 * k * sa, 1.3, 40);
    }
    scene.AddNoise(3, rng);
    ASSERT_TRUE(DetectMarkers(scene.Render().view(), o, nullptr, &ws, &cs, &st).ok());
    EXPECT_EQ(st.split_attempts, 1) << "angle " << angle;  // elongated enough to be tried
    EXPECT_EQ(st.split, 0) << "angle " << angle;
    ASSERT_EQ(cs.size(), 1u);
    EXPECT_LT(Nearest(cs, 30.3, 30.6), 0.1);
  }
}

TEST(Detection, BlobsAtTheImageBorders) {
  // Width 1000 + 37: rows end in a partial 64-pixel block.
  Scene scene(1037, 203);
  scene.AddGaussian(0.7, 100.2, 1.5, 200);     // cut by the left edge
  scene.AddGaussian(1036.0, 50.5, 1.5, 200);   // cut by the right edge
  scene.AddGaussian(500.5, 0.2, 1.5, 200);     // cut by the top edge
  scene.AddGaussian(300.5, 202.4, 1.5, 200);   // cut by the bottom edge
  scene.AddGaussian(5.3, 5.6, 1.2, 200);       // near the corner but whole
  scene.AddGaussian(1030.6, 196.3, 1.2, 200);  // in the last partial block, whole
  scene.AddGaussian(1023.7, 120.1, 1.5, 200);  // across the last full 64-block boundary (1024)
  DetectionWorkspace ws;
  std::vector<Centroid> cs;
  DetectionStats st;
  DetectionOptions o;
  o.threshold = 50;
  for (int padding : {0, 5}) {
    const TestImage img = scene.Render(PixelFormat::kMono8, 1, padding);
    ASSERT_TRUE(DetectMarkers(img.view(), o, nullptr, &ws, &cs, &st).ok());
    EXPECT_EQ(st.at_border, 4);
    ASSERT_EQ(cs.size(), 3u);
    EXPECT_LT(Nearest(cs, 5.3, 5.6), 0.03);
    EXPECT_LT(Nearest(cs, 1030.6, 196.3), 0.03);
    EXPECT_LT(Nearest(cs, 1023.7, 120.1), 0.03);
  }
  // Kept when asked: the cut blobs' centres are pulled inwards.
  o.drop_border_blobs = false;
  o.min_roundness = 0;
  const TestImage img = scene.Render();
  ASSERT_TRUE(DetectMarkers(img.view(), o, nullptr, &ws, &cs, &st).ok());
  ASSERT_EQ(cs.size(), 7u);
  const Centroid* left = nullptr;
  ASSERT_LT(Nearest(cs, 0.7, 100.2, &left), 1.0);
  EXPECT_GT(left->pixel.x(), 0.7);
}

TEST(Detection, LargeAndThinBlobsGiveFiniteCentresWhenTheFiltersAllowThem) {
  Scene scene(1000, 400);
  scene.AddRect(100, 100, 120, 120, 255);  // a lamp, saturated: centre (159.5, 159.5)
  scene.AddRect(300, 50, 600, 1, 200);     // a one-pixel line: centre (599.5, 50)
  scene.AddRect(300, 300, 1, 90, 200);     // a vertical one: centre (300, 344.5)
  DetectionOptions o = Permissive(50);
  o.centroid = DetectionOptions::CentroidMethod::kGaussianWindowed;
  DetectionWorkspace ws;
  std::vector<Centroid> cs;
  ASSERT_TRUE(DetectMarkers(scene.Render().view(), o, nullptr, &ws, &cs).ok());
  ASSERT_EQ(cs.size(), 3u);
  for (const Centroid& c : cs) {
    EXPECT_TRUE(std::isfinite(c.pixel.x()) && std::isfinite(c.pixel.y()) &&
                std::isfinite(c.sigma_px));
  }
  EXPECT_LT(Nearest(cs, 159.5, 159.5), 1e-6);
  EXPECT_LT(Nearest(cs, 599.5, 50), 1e-6);
  EXPECT_LT(Nearest(cs, 300, 344.5), 1e-6);
}

TEST(Detection, SaturatedBlobsKeepAccurateCentres) {
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> u(0, 1);
  Scene scene(640, 200);
  std::vector<Truth> truth;
  for (int i = 0; i < 15; ++i) {
    const Truth t{30 + 40.0 * i + u(rng), 100 + u(rng), 1.0 + 1.5 * u(rng), 600 + 1500 * u(rng)};
    scene.AddGaussian(t.x, t.y, t.sigma, t.peak);
    truth.push_back(t);
  }
  const TestImage img = scene.Render();
  DetectionOptions o;
  o.threshold = 60;
  DetectionWorkspace ws;
  std::vector<Centroid> cs;
  ASSERT_TRUE(DetectMarkers(img.view(), o, nullptr, &ws, &cs).ok());
  ASSERT_EQ(cs.size(), truth.size());
  for (const Truth& t : truth) {
    const Centroid* c = nullptr;
    // A plateau with a sharp rim: 0.03 px holds from sigma 1.2 px up to 5x saturation; smaller
    // or harder-saturated spots are nearly binary discs, 0.03-0.07 px (detection.h).
    const bool mild = t.sigma >= 1.2 && t.peak <= 5 * 255;
    EXPECT_LT(Nearest(cs, t.x, t.y, &c), mild ? 0.03 : 0.07)
        << "sigma " << t.sigma << " peak " << t.peak;
    EXPECT_EQ(c->peak, 255.0f);
  }
  // 12-bit data shifted into Mono16 clips at 4095 x 16 = 65520, not 65535: with
  // saturation_level set to it, the same bounds hold.
  Scene scene12 = scene;
  for (double& v : scene12.v) v = std::min(std::round(v * 4095.0 / 255.0), 4095.0) * 16;
  const TestImage img16 = scene12.Render(PixelFormat::kMono16);
  DetectionOptions o16 = o;
  o16.threshold = 60 * 4095 / 255 * 16;
  o16.saturation_level = 65520;
  std::vector<Centroid> cs16;
  ASSERT_TRUE(DetectMarkers(img16.view(), o16, nullptr, &ws, &cs16).ok());
  ASSERT_EQ(cs16.size(), truth.size());
  for (const Truth& t : truth) {
    const Centroid* c = nullptr;
    const bool mild = t.sigma >= 1.2 && t.peak <= 5 * 255;
    EXPECT_LT(Nearest(cs16, t.x, t.y, &c), mild ? 0.03 : 0.07)
        << "Mono16: sigma " << t.sigma << " peak " << t.peak;
    EXPECT_EQ(c->peak, 65520.0f);
  }
  o16.saturation_level = 70000;
  EXPECT_FALSE(DetectMarkers(img16.view(), o16, nullptr, &ws, &cs16).ok());
}

// Reference labelling: flood fill with 8-connectivity, weights value - threshold + 1.
struct RefBlob {
  long n = 0;
  double w = 0, wx = 0, wy = 0;
};
std::vector<RefBlob> FloodFill(const TestImage& img, int t) {
  std::vector<int> seen(std::size_t(img.width) * img.height, 0);
  std::vector<RefBlob> out;
  std::vector<std::pair<int, int>> stack;
  for (int y = 0; y < img.height; ++y)
    for (int x = 0; x < img.width; ++x) {
      if (seen[y * img.width + x] || img.Get(x, y) < t) continue;
      RefBlob b;
      stack.push_back({x, y});
      seen[y * img.width + x] = 1;
      while (!stack.empty()) {
        auto [px, py] = stack.back();
        stack.pop_back();
        const double w = img.Get(px, py) - t + 1;
        b.n++;
        b.w += w;
        b.wx += w * px;
        b.wy += w * py;
        for (int dy = -1; dy <= 1; ++dy)
          for (int dx = -1; dx <= 1; ++dx) {
            const int qx = px + dx, qy = py + dy;
            if (qx < 0 || qy < 0 || qx >= img.width || qy >= img.height) continue;
            if (seen[qy * img.width + qx] || img.Get(qx, qy) < t) continue;
            seen[qy * img.width + qx] = 1;
            stack.push_back({qx, qy});
          }
      }
      out.push_back(b);
    }
  return out;
}

TEST(Detection, RunLabellingMatchesFloodFillOnRandomImages) {
  // Random images with clustered bright pixels: shapes that wrap around, merge late (U shapes),
  // long runs across many 64-pixel blocks, odd widths and padded strides; both scan kernels and
  // both pixel sizes.
  std::mt19937 rng(11);
  for (int trial = 0; trial < 12; ++trial) {
    const int w = 64 + static_cast<int>(rng() % 300), h = 20 + static_cast<int>(rng() % 60);
    const PixelFormat f = trial % 3 == 0 ? PixelFormat::kMono16 : PixelFormat::kMono8;
    TestImage img(w, h, f, static_cast<int>(rng() % 3) * 2);
    const double p = 0.2 + 0.05 * (trial % 6);
    std::uniform_real_distribution<double> u(0, 1);
    for (int y = 0; y < h; ++y)
      for (int x = 0; x < w; ++x) {
        const bool long_run = (y % 17 == 3) && x > 10 && x < w - 10;
        const int v = (u(rng) < p || long_run) ? 100 + static_cast<int>(rng() % 150) : static_cast<int>(rng() % 100);
        img.Set(x, y, f == PixelFormat::kMono8 ? v : v * 200);
      }
    const int t = f == PixelFormat::kMono8 ? 100 : 100 * 200;
    const std::vector<RefBlob> ref = FloodFill(img, t);
    for (bool portable : {false, true}) {
      DetectionOptions o = Permissive(t);
      o.force_portable_scan = portable;
      DetectionWorkspace ws;
      std::vector<Centroid> cs;
      DetectionStats st;
      ASSERT_TRUE(DetectMarkers(img.view(), o, nullptr, &ws, &cs, &st).ok());
      ASSERT_EQ(cs.size(), ref.size()) << "trial " << trial << " portable " << portable;
      for (std::size_t i = 0; i < ref.size(); ++i) {
        EXPECT_EQ(cs[i].area_px, ref[i].n);
        EXPECT_NEAR(cs[i].pixel.x(), ref[i].wx / ref[i].w, 1e-9);
        EXPECT_NEAR(cs[i].pixel.y(), ref[i].wy / ref[i].w, 1e-9);
      }
    }
  }
}

TEST(Detection, ReflectionMaskRemovesReflectionsButNotAMarkerBesideThem) {
  std::mt19937 rng(5);
  const int w = 640, h = 480;
  auto empty_scene = [&] {
    Scene s(w, h, 10);
    s.AddGaussian(100.4, 100.7, 1.8, 230);   // a strobe of another camera
    s.AddRect(300, 200, 4, 3, 180);          // a shiny screw
    s.AddGaussian(500.0, 400.0, 1.2, 95);    // a dim reflection, a few pixels above the threshold
    return s;
  };
  ReflectionMaskOptions mo;
  mo.threshold = 60;
  mo.margin_px = 3;
  ReflectionMaskBuilder builder(mo);
  for (int i = 0; i < 10; ++i) {
    Scene s = empty_scene();
    s.AddNoise(5, rng);
    ASSERT_TRUE(builder.Add(s.Render().view()).ok());
  }
  ReflectionMask mask;
  ASSERT_TRUE(builder.Build(&mask).ok());
  EXPECT_TRUE(mask.Contains(100, 100));
  EXPECT_TRUE(mask.Contains(303, 201));
  EXPECT_TRUE(mask.Contains(500, 400));
  EXPECT_FALSE(mask.Contains(200, 200));
  EXPECT_LT(mask.masked_pixels(), 400);  // three small patches, not the image

  // A capture: the reflections, a marker 9 px beside the strobe (its own blob), one elsewhere.
  Scene s = empty_scene();
  s.AddGaussian(109.6, 100.2, 1.5, 200);
  s.AddGaussian(400.3, 300.8, 1.5, 200);
  s.AddNoise(5, rng);
  const TestImage img = s.Render();
  DetectionOptions o;
  o.threshold = 60;
  o.min_area_px = 2;
  DetectionWorkspace ws;
  std::vector<Centroid> cs;
  DetectionStats st;
  ASSERT_TRUE(DetectMarkers(img.view(), o, nullptr, &ws, &cs, &st).ok());
  EXPECT_EQ(cs.size(), 5u);  // without the mask, all five are found
  ASSERT_TRUE(DetectMarkers(img.view(), o, &mask, &ws, &cs, &st).ok());
  EXPECT_EQ(st.masked, 3);
  ASSERT_EQ(cs.size(), 2u);
  EXPECT_LT(Nearest(cs, 109.6, 100.2), 0.05);
  EXPECT_LT(Nearest(cs, 400.3, 300.8), 0.05);

  // A mask of another size is an error, not a silent mismatch.
  ReflectionMask other(320, 240);
  const Status s2 = DetectMarkers(img.view(), o, &other, &ws, &cs);
  ASSERT_FALSE(s2.ok());
  EXPECT_NE(s2.message().find("reflection mask is 320 x 240"), std::string::npos) << s2.message();
}

TEST(Detection, ReflectionMaskBuilderRejectsBadInput) {
  ReflectionMaskBuilder b;
  ReflectionMask m;
  Status s = b.Build(&m);
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.message().find("no frame"), std::string::npos);
  TestImage a(64, 32, PixelFormat::kMono8), c(32, 32, PixelFormat::kMono8);
  ASSERT_TRUE(b.Add(a.view()).ok());
  s = b.Add(c.view());
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.message().find("32 x 32"), std::string::npos) << s.message();
  ReflectionMaskOptions bad;
  bad.min_fraction = 0;
  ReflectionMaskBuilder b2(bad);
  s = b2.Add(a.view());
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.message().find("min_fraction"), std::string::npos) << s.message();
}

TEST(Detection, BadInputGivesAClearStatus) {
  TestImage img(64, 32, PixelFormat::kMono8);
  DetectionOptions o;
  DetectionWorkspace ws;
  std::vector<Centroid> cs;
  auto expect_error = [&](ImageView v, const DetectionOptions& opt, const char* words) {
    const Status s = DetectMarkers(v, opt, nullptr, &ws, &cs);
    ASSERT_FALSE(s.ok()) << words;
    EXPECT_NE(s.message().find(words), std::string::npos) << s.message();
    EXPECT_TRUE(cs.empty());
  };
  ImageView v = img.view();
  v.data = nullptr;
  expect_error(v, o, "null pixel data");
  v = img.view();
  v.width = 0;
  expect_error(v, o, "not positive");
  v = img.view();
  v.height = -3;
  expect_error(v, o, "not positive");
  v = img.view();
  v.stride = 63;
  expect_error(v, o, "stride 63 bytes is below width 64");
  v = img.view();
  v.format = PixelFormat::kMono16;  // 64 px of 2 bytes do not fit a 64-byte stride
  expect_error(v, o, "stride 64 bytes is below width 64 x 2");
  v = img.view();
  v.format = PixelFormat::kMono16;
  v.width = 32;
  v.data += 1;  // 16-bit pixels at an odd address
  expect_error(v, o, "2-byte boundaries");
  v = img.view();
  v.format = static_cast<PixelFormat>(7);
  expect_error(v, o, "unknown pixel format 7");
  DetectionOptions high;
  high.threshold = 300;
  expect_error(img.view(), high, "threshold 300 is above the largest Mono8 value 255");
  DetectionOptions zero;
  zero.threshold = 0;
  expect_error(img.view(), zero, "threshold 0");
  DetectionOptions sizes;
  sizes.max_area_px = 2;
  expect_error(img.view(), sizes, "max_area_px");
  // Too many blobs: a threshold at the background of a noisy image.
  Scene noisy(256, 64, 50);
  std::mt19937 rng(1);
  noisy.AddNoise(20, rng);
  DetectionOptions low = Permissive(90);  // 2 sigma above the background: specks everywhere
  low.max_centroids = 100;
  expect_error(noisy.Render().view(), low, "more than 100 blobs");
  EXPECT_FALSE(DetectMarkers(img.view(), o, nullptr, nullptr, &cs).ok());
}

TEST(Detection, WarmWorkspaceAllocatesNothing) {
  std::mt19937 rng(21);
  Scene scene(1280, 1024, 8);
  MakeBlobs(&scene, 40, rng, 0.9, 2.8, 120, 400);
  scene.AddNoise(4, rng);
  const TestImage busy = scene.Render();
  Scene quiet_scene(1280, 1024, 8);
  MakeBlobs(&quiet_scene, 10, rng);
  const TestImage quiet = quiet_scene.Render();
  DetectionOptions o;
  o.threshold = 50;
  DetectionWorkspace ws;
  std::vector<Centroid> cs;
  ASSERT_TRUE(DetectMarkers(busy.view(), o, nullptr, &ws, &cs).ok());  // warm-up
  const std::size_t capacity = ws.CapacityBytes();
  ASSERT_GT(cs.size(), 30u);
  g_allocations = 0;
  g_counting = true;
  Status s1 = DetectMarkers(busy.view(), o, nullptr, &ws, &cs);
  Status s2 = DetectMarkers(quiet.view(), o, nullptr, &ws, &cs);
  Status s3 = DetectMarkers(busy.view(), o, nullptr, &ws, &cs);
  g_counting = false;
  ASSERT_TRUE(s1.ok() && s2.ok() && s3.ok());
  EXPECT_EQ(g_allocations.load(), 0);
  EXPECT_EQ(ws.CapacityBytes(), capacity);
  // Reserve makes even the first frame allocation-free.
  DetectionWorkspace fresh;
  fresh.Reserve(64, 256);
  std::vector<Centroid> out;
  out.reserve(64);
  g_allocations = 0;
  g_counting = true;
  Status s4 = DetectMarkers(busy.view(), o, nullptr, &fresh, &out);
  g_counting = false;
  ASSERT_TRUE(s4.ok());
  EXPECT_EQ(g_allocations.load(), 0);
  // And the counter does count (the test can fail).
  g_allocations = 0;
  g_counting = true;
  std::vector<int>* probe = new std::vector<int>(10);
  g_counting = false;
  delete probe;
  EXPECT_GE(g_allocations.load(), 2);
}

}  // namespace
}  // namespace mocap::reconstruction
