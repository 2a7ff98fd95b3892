// Reproducible random numbers for the simulator. Every random choice draws from its own stream,
// seeded from (session seed, stream, index) — e.g. (seed, kNoise, movement 3) — so a stream
// never depends on how many numbers another one drew: changing one movement, or the noise level,
// leaves every other draw unchanged. Uniform and normal variates are computed here from the raw
// 64-bit engine output (not with std::*_distribution, whose algorithms differ between standard
// libraries), so a seed gives bit-identical sessions everywhere.
#pragma once
#include <Eigen/Core>
#include <cmath>
#include <cstdint>
#include <random>

namespace mocap::sim {

enum class Stream : std::uint64_t {
  kHeight = 1, kScale, kCentre, kAxis, kMarker,  // the virtual subject
  kMotion, kSta, kNoise, kMissing,               // the recordings
  kRig, kImageNoise, kReflections, kJitter,      // the simulated cameras (sim/camera_rig.h, renderer)
  kWand,                                         // the simulated wand calibration
  kGhosts, kOcclusion, kSwapTraps, kSecondPerson,  // unlabelled points for the tracker
};

// SplitMix64's finaliser: a bijective 64-bit mix (Steele, Lea, Flood 2014).
inline std::uint64_t Mix64(std::uint64_t x) {
  x += 0x9e3779b97f4a7c15ULL;
  x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ULL;
  x = (x ^ (x >> 27)) * 0x94d049bb133111ebULL;
  return x ^ (x >> 31);
}

inline std::uint64_t SubSeed(std::uint64_t seed, Stream stream, std::uint64_t index = 0) {
  return Mix64(Mix64(Mix64(seed) ^ static_cast<std::uint64_t>(stream)) ^ index);
}

class Random {
 public:
  explicit Random(std::uint64_t seed) : engine_(seed) {}
  Random(std::uint64_t seed, Stream stream, std::uint64_t index = 0)
      : engine_(SubSeed(seed, stream, index)) {}

  // Uniform in [0, 1), 53 random bits.
  double Uniform() { return static_cast<double>(engine_() >> 11) * 0x1.0p-53; }
  double Uniform(double lo, double hi) { return lo + (hi - lo) * Uniform(); }
  // Integer in [lo, hi] (hi - lo small: the modulo bias is below 2^-50).
  int UniformInt(int lo, int hi) {
    return lo + static_cast<int>(engine_() % static_cast<std::uint64_t>(hi - lo + 1));
  }
  // Standard normal (Box–Muller; the second value of each pair is kept for the next call).
  double Normal() {
    if (has_spare_) {
      has_spare_ = false;
      return spare_;
    }
    const double u1 = 1.0 - Uniform();  // (0, 1]: log is finite
    const double u2 = Uniform();
    const double r = std::sqrt(-2.0 * std::log(u1));
    spare_ = r * std::sin(2.0 * M_PI * u2);
    has_spare_ = true;
    return r * std::cos(2.0 * M_PI * u2);
  }
  // Uniformly distributed in the ball / disc of the given radius.
  Eigen::Vector3d InBall(double radius) {
    Eigen::Vector3d d(Normal(), Normal(), Normal());
    const double n = d.norm();
    if (n == 0.0) return Eigen::Vector3d::Zero();
    return d / n * radius * std::cbrt(Uniform());
  }
  Eigen::Vector2d InDisc(double radius) {
    const double r = radius * std::sqrt(Uniform()), a = 2.0 * M_PI * Uniform();
    return {r * std::cos(a), r * std::sin(a)};
  }

 private:
  std::mt19937_64 engine_;
  bool has_spare_ = false;
  double spare_ = 0.0;
};

}  // namespace mocap::sim
