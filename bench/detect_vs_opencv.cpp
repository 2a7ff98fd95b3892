// detect_vs_opencv: 2D marker detection (reconstruction/detection.h) against OpenCV's
// cv::threshold + cv::connectedComponentsWithStats (+ the stats' centroids, what OpenCV users
// take), on the same frames, side by side in one process, one thread each.
//
//   detect_vs_opencv [--frames N] [--repeats R] [--threshold T] [--seed S] [--only K]
//
// --only K times method K alone (0-based, in the order of the table), e.g. under a profiler.
//
// Frames: 1280 x 1024 Mono8, 40 markers 3-10 px across above the threshold (Gaussian spots with
// peaks 120-250 DN, sigma 0.84-3.8 px to match; each pixel the exact integral of the spot over its
// square, so the true centre is exact), 4 saturated markers 3-10 px across (peaks 600-1500 DN
// clipped at 255, sigma 0.6-2.3 px), 3 static reflections (the
// same in every frame), background 8 DN with Gaussian sensor noise of 3 DN (never reaching the
// threshold of 50). Timing: R rounds; in each, every frame goes through every method in turn; the
// median round of each is reported (and its best), and its ratio to the faster of OpenCV's two labelling
// algorithms (CCL_DEFAULT = Spaghetti, and CCL_GRANA = BBDT, often faster on sparse images).
// Accuracy: the same markers rendered without noise, then with it; error = distance from each
// true centre to the nearest detection (a marker with none within 1 px is counted as missed).
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <functional>
#include <random>
#include <string>
#include <vector>

#include "reconstruction/detection.h"
#include "reconstruction/reflection_mask.h"

using namespace mocap;
using namespace mocap::reconstruction;
using Clock = std::chrono::steady_clock;

namespace {

constexpr int kWidth = 1280, kHeight = 1024;

struct Spot {
  double x, y, sigma, peak;
};

double Cdf(double t) { return 0.5 * std::erfc(-t / std::sqrt(2.0)); }

void AddSpot(std::vector<double>* img, const Spot& s) {
  const double norm = std::pow(Cdf(0.5 / s.sigma) - Cdf(-0.5 / s.sigma), 2);
  const int r = static_cast<int>(std::ceil(6 * s.sigma)) + 1;
  for (int y = std::max(0, int(s.y) - r); y <= std::min(kHeight - 1, int(s.y) + r); ++y) {
    const double gy = Cdf((y + 0.5 - s.y) / s.sigma) - Cdf((y - 0.5 - s.y) / s.sigma);
    for (int x = std::max(0, int(s.x) - r); x <= std::min(kWidth - 1, int(s.x) + r); ++x) {
      const double gx = Cdf((x + 0.5 - s.x) / s.sigma) - Cdf((x - 0.5 - s.x) / s.sigma);
      (*img)[std::size_t(y) * kWidth + x] += s.peak * gx * gy / norm;
    }
  }
}

cv::Mat Quantise(const std::vector<double>& v) {
  cv::Mat m(kHeight, kWidth, CV_8UC1);
  for (int y = 0; y < kHeight; ++y)
    for (int x = 0; x < kWidth; ++x)
      m.at<std::uint8_t>(y, x) =
          static_cast<std::uint8_t>(std::clamp(std::lround(v[std::size_t(y) * kWidth + x]), 0L, 255L));
  return m;
}

drivers::ImageView View(const cv::Mat& m) {
  return drivers::ImageView{m.data, m.cols, m.rows, static_cast<std::ptrdiff_t>(m.step),
                            drivers::PixelFormat::kMono8};
}

struct Frame {
  cv::Mat noisy, clean;
  cv::Mat noisy16, clean16;  // the same x 256, Mono16
  std::vector<Spot> markers;  // not the reflections
};

const Spot kReflections[3] = {{211.3, 140.6, 2.0, 230}, {905.0, 610.2, 1.2, 200}, {640.5, 980.4, 2.5, 255}};

Frame MakeFrame(std::mt19937& rng, int threshold) {
  std::uniform_real_distribution<double> u(0, 1);
  Frame f;
  // Markers on a jittered grid (no two touch), 40 normal + 4 saturated.
  std::vector<std::pair<int, int>> cells;
  for (int gy = 1; gy < 15; ++gy)
    for (int gx = 1; gx < 19; ++gx) cells.push_back({gx, gy});
  std::shuffle(cells.begin(), cells.end(), rng);
  for (int i = 0; i < 44; ++i) {
    Spot s;
    s.x = cells[i].first * 64 + 8 + 48 * u(rng);
    s.y = cells[i].second * 64 + 8 + 48 * u(rng);
    // Diameter D of the part above the threshold, 3-10 px: D = 2 sigma sqrt(2 ln(peak / T)).
    s.peak = i < 40 ? 120 + 130 * u(rng) : 600 + 900 * u(rng);
    const double diameter = 3 + 7 * u(rng);
    s.sigma = diameter / (2 * std::sqrt(2 * std::log(s.peak / threshold)));
    f.markers.push_back(s);
  }
  std::vector<double> clean(std::size_t(kWidth) * kHeight, 0.0);
  for (const Spot& s : f.markers) AddSpot(&clean, s);
  for (const Spot& s : kReflections) AddSpot(&clean, s);
  std::normal_distribution<double> noise(0, 3);
  std::vector<double> noisy = clean;
  for (double& p : noisy) p += 8 + noise(rng);
  f.clean = Quantise(clean);
  f.noisy = Quantise(noisy);
  f.clean.convertTo(f.clean16, CV_16U, 256);
  f.noisy.convertTo(f.noisy16, CV_16U, 256);
  return f;
}

struct OpenCvWorkspace {
  cv::Mat binary, labels, stats, centroids;
};

// What an OpenCV user writes: binary threshold, labelled components with statistics, area filter,
// the stats' centroid of each component.
void DetectOpenCv(const cv::Mat& img, int threshold, int min_area, int max_area, int algorithm,
                  OpenCvWorkspace* ws, std::vector<cv::Point2d>* out) {
  cv::threshold(img, ws->binary, threshold - 1, 255, cv::THRESH_BINARY);  // > T - 1 <=> >= T
  const int n = cv::connectedComponentsWithStats(ws->binary, ws->labels, ws->stats, ws->centroids, 8,
                                                 CV_32S, algorithm);
  out->clear();
  for (int i = 1; i < n; ++i) {
    const int area = ws->stats.at<int>(i, cv::CC_STAT_AREA);
    if (area < min_area || area > max_area) continue;
    out->emplace_back(ws->centroids.at<double>(i, 0), ws->centroids.at<double>(i, 1));
  }
}

// Reads a buffer larger than any CPU cache, so that the next frame comes from memory.
void EvictCaches() {
  static std::vector<std::uint64_t> junk(64 << 20 >> 3, 1);
  static volatile std::uint64_t sink = 0;
  std::uint64_t acc = 0;
  for (std::size_t i = 0; i < junk.size(); i += 8) acc += junk[i]++;
  sink = sink + acc;
}

double Median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

std::string CpuModel() {
  std::ifstream in("/proc/cpuinfo");
  std::string line;
  while (std::getline(in, line))
    if (line.rfind("model name", 0) == 0) return line.substr(line.find(':') + 2);
  return "unknown";
}

}  // namespace

int main(int argc, char** argv) {
  int frames = 8, repeats = 15, threshold = 50, only = -1;
  unsigned seed = 1;
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string a = argv[i];
    if (a == "--frames") frames = std::atoi(argv[i + 1]);
    else if (a == "--repeats") repeats = std::atoi(argv[i + 1]);
    else if (a == "--threshold") threshold = std::atoi(argv[i + 1]);
    else if (a == "--only") only = std::atoi(argv[i + 1]);
    else if (a == "--seed") seed = static_cast<unsigned>(std::atoi(argv[i + 1]));
    else {
      std::fprintf(stderr, "unknown option %s\n", argv[i]);
      return 2;
    }
  }
  if (frames < 1 || repeats < 1 || threshold < 1 || threshold > 255) {
    std::fprintf(stderr, "--frames and --repeats must be >= 1, --threshold in [1, 255]\n");
    return 2;
  }
  cv::setNumThreads(1);
  std::mt19937 rng(seed);
  std::vector<Frame> set;
  for (int i = 0; i < frames; ++i) set.push_back(MakeFrame(rng, threshold));

  DetectionOptions options;
  options.threshold = threshold;
  options.read_noise_dn = 3;
  DetectionWorkspace ws;
  std::vector<Centroid> ours;
  OpenCvWorkspace cvws;

  // The reflection mask from 20 frames of the empty volume (reflections + noise).
  ReflectionMaskOptions mask_options;
  mask_options.threshold = threshold;
  ReflectionMaskBuilder builder(mask_options);
  {
    std::vector<double> empty(std::size_t(kWidth) * kHeight, 0.0);
    for (const Spot& s : kReflections) AddSpot(&empty, s);
    std::normal_distribution<double> noise(0, 3);
    for (int i = 0; i < 20; ++i) {
      std::vector<double> v = empty;
      for (double& p : v) p += 8 + noise(rng);
      const cv::Mat m = Quantise(v);
      if (Status s = builder.Add(View(m)); !s.ok()) {
        std::fprintf(stderr, "%s\n", s.message().c_str());
        return 1;
      }
    }
  }
  ReflectionMask mask;
  if (Status s = builder.Build(&mask); !s.ok()) {
    std::fprintf(stderr, "%s\n", s.message().c_str());
    return 1;
  }

  // The contenders, each a function from a frame to centre points.
  struct Method {
    std::string name;
    std::function<void(const Frame&, bool clean, std::vector<cv::Point2d>*)> detect;
    std::vector<double> seconds;  // per frame: {median, best}
    int bytes_per_pixel = 1;
  };
  auto ours_with = [&](DetectionOptions o, const ReflectionMask* m) {
    return [&, o, m](const Frame& f, bool clean, std::vector<cv::Point2d>* pts) {
      const cv::Mat& img = clean ? f.clean : f.noisy;
      if (Status s = DetectMarkers(View(img), o, m, &ws, &ours); !s.ok()) {
        std::fprintf(stderr, "%s\n", s.message().c_str());
        std::exit(1);
      }
      pts->clear();
      for (const Centroid& c : ours) pts->emplace_back(c.pixel.x(), c.pixel.y());
    };
  };
  DetectionOptions thresholded = options;
  thresholded.centroid = DetectionOptions::CentroidMethod::kThresholdWeighted;
  DetectionOptions portable = options;
  portable.force_portable_scan = true;
  auto opencv_with = [&](int algorithm) {
    return [&, algorithm](const Frame& f, bool clean, std::vector<cv::Point2d>* pts) {
      const cv::Mat& img = clean ? f.clean : f.noisy;
      DetectOpenCv(img, threshold, options.min_area_px, options.max_area_px, algorithm, &cvws, pts);
    };
  };
  std::vector<Method> methods;
  methods.push_back({"ours: Gaussian-windowed centre, reflection mask", ours_with(options, &mask), {}});
  methods.push_back({"ours: Gaussian-windowed centre, no mask", ours_with(options, nullptr), {}});
  methods.push_back({"ours: thresholded centre (no refinement), no mask", ours_with(thresholded, nullptr), {}});
  methods.push_back({"ours: portable scan (no AVX2), Gaussian-windowed, no mask", ours_with(portable, nullptr), {}});
  DetectionOptions mono16 = options;
  mono16.threshold = threshold * 256;
  mono16.read_noise_dn = options.read_noise_dn * 256;
  mono16.saturation_level = 255 * 256;  // where these frames clip
  methods.push_back({"ours: Mono16 (the same frames x 256; 2 bytes a pixel), no mask",
                     [&, mono16](const Frame& f, bool clean, std::vector<cv::Point2d>* pts) {
                       const cv::Mat& img = clean ? f.clean16 : f.noisy16;
                       const drivers::ImageView v{img.data, img.cols, img.rows,
                                                  static_cast<std::ptrdiff_t>(img.step),
                                                  drivers::PixelFormat::kMono16};
                       if (Status s = DetectMarkers(v, mono16, nullptr, &ws, &ours); !s.ok()) {
                         std::fprintf(stderr, "%s\n", s.message().c_str());
                         std::exit(1);
                       }
                       pts->clear();
                       for (const Centroid& c : ours) pts->emplace_back(c.pixel.x(), c.pixel.y());
                     },
                     {},
                     2});
  methods.push_back({"OpenCV threshold + connectedComponentsWithStats (CCL_DEFAULT)", opencv_with(cv::CCL_DEFAULT), {}});
  methods.push_back({"OpenCV threshold + connectedComponentsWithStats (CCL_GRANA)", opencv_with(cv::CCL_GRANA), {}});
  const std::size_t first_opencv = 5;

  // Warm-up (sizes every workspace); blobs found per frame.
  std::vector<double> found(methods.size(), 0);
  std::vector<cv::Point2d> pts;
  for (std::size_t k = 0; k < methods.size(); ++k)
    for (const Frame& f : set) {
      methods[k].detect(f, false, &pts);
      found[k] += double(pts.size()) / frames;
    }
  // Timing, interleaved as finely as possible so that every method sees the same machine (this
  // one is shared and busy): in each round, each frame goes through every method, starting with
  // a different method each time (a preemption after a long OpenCV call must not always land on
  // the same method). Before every call the caches are flushed: a camera frame arrives by DMA
  // into memory, never in cache, and a method that ran after another on the same frame would
  // otherwise find it there. A method's time is the mean over frames of its median over rounds, which
  // ignores the odd time slice lost to another process; the best round is shown beside it.
  std::vector<std::vector<std::vector<double>>> calls(
      methods.size(), std::vector<std::vector<double>>(frames));
  int turn = 0;
  for (int r = 0; r < repeats; ++r)
    for (int f = 0; f < frames; ++f, ++turn)
      for (std::size_t i = 0; i < methods.size(); ++i) {
        const std::size_t k = (i + turn) % methods.size();
        if (only >= 0 && static_cast<int>(k) != only) continue;
        EvictCaches();
        const auto t0 = Clock::now();
        methods[k].detect(set[f], false, &pts);
        calls[k][f].push_back(std::chrono::duration<double>(Clock::now() - t0).count());
      }
  for (std::size_t k = 0; k < methods.size(); ++k) {
    double median = 0, best = 0;
    for (int f = 0; f < frames && !calls[k][f].empty(); ++f) {
      median += Median(calls[k][f]) / frames;
      best += *std::min_element(calls[k][f].begin(), calls[k][f].end()) / frames;
    }
    methods[k].seconds = {median, best};
  }
  // Accuracy: noise-free (unsaturated / saturated markers separately) and noisy frames.
  struct Accuracy {
    double sum2 = 0, max = 0;
    int n = 0, missed = 0;
    void Add(double e) {
      if (e > 1.0) {
        ++missed;
        return;
      }
      sum2 += e * e;
      max = std::max(max, e);
      ++n;
    }
    double rms() const { return n ? std::sqrt(sum2 / n) : 0; }
  };
  std::vector<Accuracy> clean(methods.size()), clean_sat(methods.size()), noisy(methods.size());
  for (std::size_t k = 0; k < methods.size(); ++k)
    for (const Frame& f : set)
      for (int pass = 0; pass < 2; ++pass) {
        methods[k].detect(f, pass == 0, &pts);
        for (const Spot& s : f.markers) {
          double best = 1e9;
          for (const cv::Point2d& p : pts) best = std::min(best, std::hypot(p.x - s.x, p.y - s.y));
          if (pass == 1)
            noisy[k].Add(best);
          else if (s.peak > 255)
            clean_sat[k].Add(best);
          else
            clean[k].Add(best);
        }
      }

  const double bytes = double(kWidth) * kHeight;  // per frame, Mono8
  double best_opencv = 1e9;
  for (std::size_t k = first_opencv; k < methods.size(); ++k)
    best_opencv = std::min(best_opencv, methods[k].seconds[0]);
  double load[3] = {0, 0, 0};
  if (FILE* la = std::fopen("/proc/loadavg", "r")) {
    if (std::fscanf(la, "%lf %lf %lf", &load[0], &load[1], &load[2]) != 3) load[0] = -1;
    std::fclose(la);
  }
  std::printf("detect_vs_opencv: %d frames %dx%d Mono8 (44 markers: 40 + 4 saturated, 3 static "
              "reflections, noise 3 DN on 8 DN), threshold %d, %d rounds, one thread each; CPU %s; "
              "load average %.2f; OpenCV %s%s\n\n",
              frames, kWidth, kHeight, threshold, repeats, CpuModel().c_str(), load[0], CV_VERSION,
#if defined(__AVX2__)
              ""
#else
              " (built WITHOUT AVX2: every 'ours' row uses the portable scan)"
#endif
  );
  std::printf("| method | ms / frame: median (best) | GB/s (median) | speed-up vs best OpenCV "
              "(median) | blobs / frame | noise-free error RMS / max px | saturated RMS / max px | "
              "noisy RMS px |\n");
  std::printf("|---|---:|---:|---:|---:|---:|---:|---:|\n");
  for (std::size_t k = 0; k < methods.size(); ++k) {
    const double t = methods[k].seconds[0];
    std::printf("| %s | %.3f (%.3f) | %.2f | %.1fx | %.1f | %.4f / %.4f | %.4f / %.4f | %.4f |\n",
                methods[k].name.c_str(), t * 1e3, methods[k].seconds[1] * 1e3,
                methods[k].bytes_per_pixel * bytes / t / 1e9,
                best_opencv / t, found[k],
                clean[k].rms(), clean[k].max, clean_sat[k].rms(), clean_sat[k].max, noisy[k].rms());
    if (clean[k].missed + clean_sat[k].missed + noisy[k].missed > 0)
      std::printf("|   (missed markers: %d noise-free, %d saturated, %d noisy) | | | | | | | |\n",
                  clean[k].missed, clean_sat[k].missed, noisy[k].missed);
  }
  return 0;
}
