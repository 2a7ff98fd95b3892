#include "reconstruction/clock_fit.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace mocap::reconstruction {
bool ClockFitOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& what) {
    if (error) *error = "clock fit options: " + what;
    return false;
  };
  if (window < 4 || window > (1 << 20))
    return fail("window " + std::to_string(window) + " is outside [4, 1048576]");
  if (segments < 2 || segments > window / 2)
    return fail("segments " + std::to_string(segments) + " is outside [2, window / 2 = " +
                std::to_string(window / 2) + "]");
  if (min_samples_for_drift < 2 * segments || min_samples_for_drift > window)
    return fail("min_samples_for_drift " + std::to_string(min_samples_for_drift) +
                " is outside [2 x segments, window]");
  if (refit_every < 1) return fail("refit_every must be >= 1");
  if (!(near_line_ns >= 0)) return fail("near_line_ns must be >= 0");
  if (!(max_drift_ppm >= 0 && max_drift_ppm <= 1e5))
    return fail("max_drift_ppm must be in [0, 100000]");
  return true;
}

ClockFit::ClockFit(ClockFitOptions options) : options_(options) { Reset(); }

void ClockFit::Reset() {
  const std::size_t w = static_cast<std::size_t>(std::max(options_.window, 4));
  x_.assign(w, 0.0);
  y_.assign(w, 0.0);
  next_ = size_ = count_ = 0;
  device0_ = y0_ = last_device_ = 0;
  intercept_ = slope_ = 0;
  drift_fitted_ = false;
  residual_ns_ = 0;
}

void ClockFit::Add(std::uint64_t device_ns, std::uint64_t host_ns) {
  const auto device = static_cast<std::int64_t>(device_ns);
  const std::int64_t raw = static_cast<std::int64_t>(host_ns) - device;
  if (count_ == 0) {
    device0_ = device;
    y0_ = raw;
  }
  const double x = static_cast<double>(device - device0_);
  const double y = static_cast<double>(raw - y0_);
  x_[next_] = x;
  y_[next_] = y;
  next_ = (next_ + 1) % x_.size();
  size_ = std::min(size_ + 1, x_.size());
  ++count_;
  last_device_ = device;
  if (size_ < static_cast<std::size_t>(options_.min_samples_for_drift)) {
    // The offset alone: the earliest arrival so far.
    intercept_ = count_ == 1 ? y : std::min(intercept_, y);
    return;
  }
  if (!drift_fitted_ || count_ % options_.refit_every == 0) Refit();
}

void ClockFit::Refit() {
  // The ring in time order starts at next_ once full, at 0 before.
  const std::size_t start = size_ == x_.size() ? next_ : 0;
  const int s = options_.segments;
  mx_.clear();
  my_.clear();
  for (int k = 0; k < s; ++k) {
    const std::size_t from = size_ * k / s, to = size_ * (k + 1) / s;
    std::size_t best = from;
    for (std::size_t i = from; i < to; ++i) {
      if (y_[(start + i) % x_.size()] < y_[(start + best) % x_.size()]) best = i;
    }
    mx_.push_back(x_[(start + best) % x_.size()]);
    my_.push_back(y_[(start + best) % x_.size()]);
  }
  // The lower support line of the minima: of the lines through two of them that no minimum lies
  // below, the one closest to all of them (the hull edge under their centre). Minima of runs
  // that waited lie above it and do not move it.
  const double limit = options_.max_drift_ppm * 1e-6;
  double sum_x = 0, sum_y = 0;
  for (int i = 0; i < s; ++i) sum_x += mx_[i], sum_y += my_[i];
  double best_cost = 0, best_a = 0, best_b = 0;
  bool found = false;
  for (int i = 0; i < s; ++i) {
    for (int j = i + 1; j < s; ++j) {
      if (mx_[j] == mx_[i]) continue;
      const double b = (my_[j] - my_[i]) / (mx_[j] - mx_[i]);
      if (std::abs(b) > limit) continue;
      const double a = my_[i] - b * mx_[i];
      bool below = false;
      for (int k = 0; k < s && !below; ++k) below = my_[k] < a + b * mx_[k] - 1.0;  // 1 ns
      if (below) continue;
      const double cost = sum_y - s * a - b * sum_x;
      if (!found || cost < best_cost) best_cost = cost, best_a = a, best_b = b, found = true;
    }
  }
  if (!found) {  // every support line is steeper than the limit: the offset alone
    best_b = 0;
    best_a = *std::min_element(my_.begin(), my_.end());
  }
  // The support line rests on two minima only, and a camera's own timestamps jitter: the minima
  // scatter on both sides of the true line by about that jitter, and a support line through two
  // neighbouring runs tilts by their difference over the runs' spacing (10 us over 0.17 s is 60
  // ppm). So its slope is then refitted by least squares through the minima within
  // `near_line_ns` of it (the scatter; the runs that waited lie far above and are left out
  // however many they are), which averages the jitter over all of them; and the line is lowered
  // onto the lowest of them, so that it stays the lower edge of the arrivals.
  if (found) {
    double n = 0, sx = 0, sy = 0, sxx = 0, sxy = 0;
    for (int k = 0; k < s; ++k) {
      if (my_[k] - (best_a + best_b * mx_[k]) > options_.near_line_ns) continue;
      n += 1, sx += mx_[k], sy += my_[k], sxx += mx_[k] * mx_[k], sxy += mx_[k] * my_[k];
    }
    const double det = n * sxx - sx * sx;
    const double b = det > 0 ? (n * sxy - sx * sy) / det : best_b;
    if (n >= 3 && det > 0 && std::abs(b) <= limit) {
      double a = std::numeric_limits<double>::infinity();
      for (int k = 0; k < s; ++k)
        if (my_[k] - (best_a + best_b * mx_[k]) <= options_.near_line_ns) a = std::min(a, my_[k] - b * mx_[k]);
      best_a = a;
      best_b = b;
    }
  }
  slope_ = best_b;
  intercept_ = best_a;
  drift_fitted_ = true;
  residual_ns_ = 0;
  for (int k = 0; k < s; ++k) residual_ns_ = std::max(residual_ns_, my_[k] - (best_a + best_b * mx_[k]));
}

std::int64_t ClockFit::ToHost(std::uint64_t device_ns) const {
  const auto device = static_cast<std::int64_t>(device_ns);
  if (count_ == 0) return device;
  const double x = static_cast<double>(device - device0_);
  return device + y0_ + static_cast<std::int64_t>(std::llround(intercept_ + slope_ * x));
}

std::int64_t ClockFit::offset_ns() const {
  return ToHost(static_cast<std::uint64_t>(last_device_)) - last_device_;
}

}  // namespace mocap::reconstruction
