// detect_vs_opencv: 2D marker detection (reconstruction/detection.h) against OpenCV's
// cv::threshold + cv::connectedComponentsWithStats (+ the stats' centroids, what OpenCV users
// take), on the same frames, side by side in one process, one thread each.
//
//   detect_vs_opencv [--frames N] [--repeats R] [--threshold T] [--seed S]
//
// Frames: 1280 x 1024 Mono8, about 40 markers 3-10 px across (Gaussian spots, sigma 0.8-2.6 px,
// peaks 120-250 DN, each pixel the exact integral of the spot over its square, so the true centre
// is exact), 4 saturated markers (peaks 600-1500 DN clipped at 255), 3 static reflections (the
// same in every frame), background 8 DN with Gaussian sensor noise of 3 DN (never reaching the
// threshold of 50). Timing: R rounds; in each, ours over all N frames then OpenCV over the same
// frames; the median round of each is reported, and their ratio. Accuracy: the same markers
// rendered without noise; error = distance from each true centre to the nearest detection.
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
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
  std::vector<Spot> markers;  // not the reflections
};

const Spot kReflections[3] = {{211.3, 140.6, 2.0, 230}, {905.0, 610.2, 1.2, 200}, {640.5, 980.4, 2.5, 255}};

Frame MakeFrame(std::mt19937& rng) {
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
    s.sigma = 0.8 + 1.8 * u(rng);
    s.peak = i < 40 ? 120 + 130 * u(rng) : 600 + 900 * u(rng);
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
  return f;
}

struct OpenCvWorkspace {
  cv::Mat binary, labels, stats, centroids;
};

// What an OpenCV user writes: binary threshold, labelled components with statistics, area filter,
// the stats' centroid of each component.
void DetectOpenCv(const cv::Mat& img, int threshold, int min_area, int max_area, OpenCvWorkspace* ws,
                  std::vector<cv::Point2d>* out) {
  cv::threshold(img, ws->binary, threshold - 1, 255, cv::THRESH_BINARY);  // > T - 1 <=> >= T
  const int n = cv::connectedComponentsWithStats(ws->binary, ws->labels, ws->stats, ws->centroids, 8,
                                                 CV_32S);
  out->clear();
  for (int i = 1; i < n; ++i) {
    const int area = ws->stats.at<int>(i, cv::CC_STAT_AREA);
    if (area < min_area || area > max_area) continue;
    out->emplace_back(ws->centroids.at<double>(i, 0), ws->centroids.at<double>(i, 1));
  }
}

double Median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

struct ErrorStats {
  double rms = 0, max = 0;
  int missed = 0;
};

template <class Points>
ErrorStats Errors(const std::vector<Spot>& truth, const Points& found) {
  ErrorStats e;
  double sum = 0;
  int n = 0;
  for (const Spot& s : truth) {
    double best = 1e9;
    for (const auto& p : found) best = std::min(best, std::hypot(p.x - s.x, p.y - s.y));
    if (best > 1.0) {
      ++e.missed;
      continue;
    }
    sum += best * best;
    ++n;
    e.max = std::max(e.max, best);
  }
  e.rms = n ? std::sqrt(sum / n) : 0;
  return e;
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
  int frames = 8, repeats = 15, threshold = 50;
  unsigned seed = 1;
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string a = argv[i];
    if (a == "--frames") frames = std::atoi(argv[i + 1]);
    else if (a == "--repeats") repeats = std::atoi(argv[i + 1]);
    else if (a == "--threshold") threshold = std::atoi(argv[i + 1]);
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
  for (int i = 0; i < frames; ++i) set.push_back(MakeFrame(rng));

  DetectionOptions options;
  options.threshold = threshold;
  options.read_noise_dn = 3;
  DetectionWorkspace ws;
  std::vector<Centroid> ours;
  OpenCvWorkspace cvws;
  std::vector<cv::Point2d> theirs;

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

  // Warm-up (sizes the workspaces) and a check that both find the same blobs.
  int ours_found = 0, cv_found = 0, ours_masked_found = 0;
  for (const Frame& f : set) {
    if (Status s = DetectMarkers(View(f.noisy), options, nullptr, &ws, &ours); !s.ok()) {
      std::fprintf(stderr, "%s\n", s.message().c_str());
      return 1;
    }
    ours_found += static_cast<int>(ours.size());
    DetectMarkers(View(f.noisy), options, &mask, &ws, &ours);
    ours_masked_found += static_cast<int>(ours.size());
    DetectOpenCv(f.noisy, threshold, options.min_area_px, options.max_area_px, &cvws, &theirs);
    cv_found += static_cast<int>(theirs.size());
  }

  std::vector<double> t_ours, t_mask, t_portable, t_cv;
  DetectionOptions portable = options;
  portable.force_portable_scan = true;
  for (int r = 0; r < repeats; ++r) {
    auto t0 = Clock::now();
    for (const Frame& f : set) DetectMarkers(View(f.noisy), options, nullptr, &ws, &ours);
    auto t1 = Clock::now();
    for (const Frame& f : set) DetectMarkers(View(f.noisy), options, &mask, &ws, &ours);
    auto t2 = Clock::now();
    for (const Frame& f : set) DetectMarkers(View(f.noisy), portable, nullptr, &ws, &ours);
    auto t3 = Clock::now();
    for (const Frame& f : set)
      DetectOpenCv(f.noisy, threshold, options.min_area_px, options.max_area_px, &cvws, &theirs);
    auto t4 = Clock::now();
    auto per_frame = [&](auto a, auto b) {
      return std::chrono::duration<double>(b - a).count() / frames;
    };
    t_ours.push_back(per_frame(t0, t1));
    t_mask.push_back(per_frame(t1, t2));
    t_portable.push_back(per_frame(t2, t3));
    t_cv.push_back(per_frame(t3, t4));
  }

  // Accuracy on noise-free frames (markers only: the reflections are not in the truth).
  std::vector<Spot> truth_all;
  std::vector<cv::Point2d> ours_pts, cv_pts;
  ErrorStats e_ours_noisy, e_cv_noisy;
  std::vector<Spot> truth_sat;
  std::vector<cv::Point2d> ours_sat;
  double ours_sum = 0, cv_sum = 0, ours_max = 0, cv_max = 0, noisy_ours_sum = 0, noisy_cv_sum = 0;
  int n_ok = 0, ours_missed = 0, cv_missed = 0;
  for (const Frame& f : set) {
    for (int pass = 0; pass < 2; ++pass) {
      const cv::Mat& img = pass == 0 ? f.clean : f.noisy;
      DetectMarkers(View(img), options, &mask, &ws, &ours);
      ours_pts.clear();
      for (const Centroid& c : ours) ours_pts.emplace_back(c.pixel.x(), c.pixel.y());
      DetectOpenCv(img, threshold, options.min_area_px, options.max_area_px, &cvws, &cv_pts);
      const ErrorStats eo = Errors(f.markers, ours_pts), ec = Errors(f.markers, cv_pts);
      const int n = static_cast<int>(f.markers.size());
      if (pass == 0) {
        ours_sum += eo.rms * eo.rms * (n - eo.missed);
        cv_sum += ec.rms * ec.rms * (n - ec.missed);
        ours_max = std::max(ours_max, eo.max);
        cv_max = std::max(cv_max, ec.max);
        ours_missed += eo.missed;
        cv_missed += ec.missed;
        n_ok += n;
      } else {
        noisy_ours_sum += eo.rms * eo.rms * (n - eo.missed);
        noisy_cv_sum += ec.rms * ec.rms * (n - ec.missed);
      }
    }
  }
  // Per sigma class (noise-free): where the residual bias of the thresholded centroid lives.
  double cls_max[3] = {0, 0, 0};
  for (const Frame& f : set) {
    DetectMarkers(View(f.clean), options, &mask, &ws, &ours);
    for (const Spot& s : f.markers) {
      double best = 1e9;
      for (const Centroid& c : ours) best = std::min(best, std::hypot(c.pixel.x() - s.x, c.pixel.y() - s.y));
      if (best > 1) continue;
      const int k = s.sigma < 1.2 ? 0 : (s.sigma < 1.8 ? 1 : 2);
      cls_max[k] = std::max(cls_max[k], best);
    }
  }

  const double bytes = double(kWidth) * kHeight;
  const double mo = Median(t_ours), mm = Median(t_mask), mp = Median(t_portable), mc = Median(t_cv);
  double load[3] = {0, 0, 0};
  if (FILE* la = std::fopen("/proc/loadavg", "r")) {
    if (std::fscanf(la, "%lf %lf %lf", &load[0], &load[1], &load[2]) != 3) load[0] = -1;
    std::fclose(la);
  }
  std::printf("detect_vs_opencv: %d frames %dx%d Mono8, %d rounds, threshold %d, one thread; CPU %s; "
              "load average %.2f; OpenCV %s\n",
              frames, kWidth, kHeight, repeats, threshold, CpuModel().c_str(), load[0], CV_VERSION);
  std::printf("blobs found per frame: ours %.1f (with reflection mask %.1f), OpenCV %.1f "
              "(44 markers + 3 reflections)\n",
              double(ours_found) / frames, double(ours_masked_found) / frames, double(cv_found) / frames);
  std::printf("\n| method | ms / frame | GB/s | vs OpenCV | noise-free error RMS / max px | noisy RMS px | missed |\n");
  std::printf("|---|---:|---:|---:|---:|---:|---:|\n");
  auto row = [&](const char* name, double t, bool acc) {
    if (acc)
      std::printf("| %s | %.3f | %.2f | %.1fx | %.4f / %.4f | %.4f | %d |\n", name, t * 1e3,
                  bytes / t / 1e9, mc / t, std::sqrt(ours_sum / (n_ok - ours_missed)), ours_max,
                  std::sqrt(noisy_ours_sum / (n_ok - ours_missed)), ours_missed);
    else
      std::printf("| %s | %.3f | %.2f | %.1fx | | | |\n", name, t * 1e3, bytes / t / 1e9, mc / t);
  };
  row("ours (AVX2 scan, mask)", mm, true);
  row("ours (AVX2 scan, no mask)", mo, false);
  row("ours (portable scan)", mp, false);
  std::printf("| OpenCV threshold + connectedComponentsWithStats | %.3f | %.2f | 1.0x | %.4f / %.4f | %.4f | %d |\n",
              mc * 1e3, bytes / mc / 1e9, std::sqrt(cv_sum / (n_ok - cv_missed)), cv_max,
              std::sqrt(noisy_cv_sum / (n_ok - cv_missed)), cv_missed);
  std::printf("\nours, noise-free max error by spot sigma: <1.2 px %.4f, 1.2-1.8 px %.4f, >=1.8 px %.4f\n",
              cls_max[0], cls_max[1], cls_max[2]);
#if !defined(__AVX2__)
  std::printf("(built without AVX2: both 'ours' rows use the portable scan)\n");
#endif
  return 0;
}
