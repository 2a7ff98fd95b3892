#include "reconstruction/frame_sync.h"

#include <algorithm>
#include <cmath>
#include <utility>

namespace mocap::reconstruction {

bool FrameSyncOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& what) {
    if (error) *error = "frame sync options: " + what;
    return false;
  };
  if (num_cameras < 1 || num_cameras > 1024)
    return fail("num_cameras " + std::to_string(num_cameras) + " is outside [1, 1024]");
  if (mode != Mode::kSequence && mode != Mode::kTimestamp) return fail("unknown mode");
  if (sequence_bits < 2 || sequence_bits > 64)
    return fail("sequence_bits " + std::to_string(sequence_bits) + " is outside [2, 64]");
  if (max_pending_sets < 1 || max_pending_sets > 4096)
    return fail("max_pending_sets " + std::to_string(max_pending_sets) +
                " is outside [1, 4096]");
  if (mode == Mode::kTimestamp) {
    if (tolerance_ns == 0 || tolerance_ns > (1ull << 62)) return fail("tolerance_ns must be > 0");
    if (!estimate_offsets && !camera_offsets_ns.empty() &&
        static_cast<int>(camera_offsets_ns.size()) != num_cameras)
      return fail("camera_offsets_ns has " + std::to_string(camera_offsets_ns.size()) +
                  " entries for " + std::to_string(num_cameras) + " cameras");
  }
  if (mode == Mode::kTimestamp ? estimate_offsets : check_tolerance_ns > 0) {
    std::string sub;
    if (!clock.IsValid(&sub)) return fail(sub);
  }
  return true;
}

bool FrameSync::Fitting() const {
  return options_.mode == FrameSyncOptions::Mode::kTimestamp ? options_.estimate_offsets
                                                            : options_.check_tolerance_ns > 0;
}

Status FrameSync::Reset(const FrameSyncOptions& options) {
  std::string error;
  if (!options.IsValid(&error)) {
    initialised_ = false;
    return Status::Error(error);
  }
  options_ = options;
  counters_ = FrameSyncCounters{};
  counters_.missing.assign(options.num_cameras, 0);
  pending_.clear();
  pending_.reserve(options.max_pending_sets + 1);
  emitted_any_ = false;
  last_emitted_key_ = 0;
  seen_any_ = false;
  newest_key_ = 0;
  offsets_.assign(options.num_cameras, 0);
  if (!options.estimate_offsets && !options.camera_offsets_ns.empty())
    offsets_ = options.camera_offsets_ns;
  fits_.assign(Fitting() ? options.num_cameras : 0, ClockFit(options.clock));
  scratch_.reserve(options.num_cameras);
  initialised_ = true;
  return Status::Ok();
}

std::int64_t FrameSync::offset_ns(int camera) const {
  if (camera < 0 || camera >= static_cast<int>(offsets_.size())) return 0;
  if (camera < static_cast<int>(fits_.size())) return -fits_[camera].offset_ns();
  return offsets_[camera];
}

double FrameSync::drift_ppm(int camera) const {
  if (camera < 0 || camera >= static_cast<int>(fits_.size())) return 0;
  return fits_[camera].drift_ppm();
}

double FrameSync::clock_residual_ns(int camera) const {
  if (camera < 0 || camera >= static_cast<int>(fits_.size())) return 0;
  return fits_[camera].residual_ns();
}

bool FrameSync::clock_fitted(int camera) const {
  if (camera < 0 || camera >= static_cast<int>(fits_.size())) return false;
  return fits_[camera].drift_fitted();
}

std::int64_t FrameSync::UnwrapSequence(std::uint64_t sequence) {
  if (options_.sequence_bits >= 63) return static_cast<std::int64_t>(sequence);
  const std::uint64_t modulus = 1ull << options_.sequence_bits;
  const std::uint64_t low = sequence & (modulus - 1);
  if (!seen_any_) {
    seen_any_ = true;
    newest_key_ = static_cast<std::int64_t>(low);
    return newest_key_;
  }
  std::int64_t delta =
      static_cast<std::int64_t>((low - static_cast<std::uint64_t>(newest_key_)) & (modulus - 1));
  if (delta >= static_cast<std::int64_t>(modulus / 2)) delta -= static_cast<std::int64_t>(modulus);
  const std::int64_t key = newest_key_ + delta;
  newest_key_ = std::max(newest_key_, key);
  return key;
}

Status FrameSync::Add(CameraDetections detections, std::vector<DetectionSet>* ready) {
  if (!initialised_) return Status::Error("frame sync: Reset with valid options first");
  if (ready == nullptr) return Status::Error("frame sync: output list is null");
  const int n = options_.num_cameras;
  const int c = detections.camera;
  if (c < 0 || c >= n)
    return Status::Error("frame sync: camera " + std::to_string(c) + " is outside the rig's " +
                         std::to_string(n) + " cameras");
  ++counters_.frames;
  const bool by_time = options_.mode == FrameSyncOptions::Mode::kTimestamp;
  const std::uint64_t host_now = detections.host_timestamp_ns;

  // The frame's key and, for kTimestamp, the pending set it belongs to.
  std::int64_t key = 0;
  std::int64_t time = static_cast<std::int64_t>(detections.device_timestamp_ns);
  if (!fits_.empty()) {
    fits_[c].Add(detections.device_timestamp_ns,
                 detections.received_ns != 0 ? detections.received_ns : host_now);
    time = fits_[c].ToHost(detections.device_timestamp_ns);
  } else if (by_time) {
    time -= offsets_[c];
  }
  int slot = -1;
  if (!by_time) {
    key = UnwrapSequence(detections.sequence);
    if (emitted_any_ && key <= last_emitted_key_) {
      ++counters_.late;
      EmitTimedOut(host_now, ready);
      return Status::Ok();
    }
    for (int i = 0; i < static_cast<int>(pending_.size()); ++i)
      if (pending_[i].key == key) slot = i;
  } else {
    const auto tol = static_cast<std::int64_t>(options_.tolerance_ns);
    std::int64_t best = tol + 1;
    for (int i = 0; i < static_cast<int>(pending_.size()); ++i) {
      const std::int64_t d = std::llabs(pending_[i].key - time);
      if (d <= tol && d < best) {
        best = d;
        slot = i;
      }
    }
    if (slot < 0 && emitted_any_ && time <= last_emitted_key_ + tol) {
      ++counters_.late;
      EmitTimedOut(host_now, ready);
      return Status::Ok();
    }
    key = time;
  }

  if (slot >= 0 && pending_[slot].set.present[c]) {
    ++counters_.duplicate;
    EmitTimedOut(host_now, ready);
    return Status::Ok();
  }
  if (slot < 0) {
    // A new set, inserted in key order.
    Pending p;
    p.key = key;
    p.times.assign(n, 0);
    p.set.cameras.resize(n);
    p.set.present.assign(n, false);
    p.set.first_arrival_ns = host_now;
    auto it = std::upper_bound(pending_.begin(), pending_.end(), key,
                               [](std::int64_t k, const Pending& q) { return k < q.key; });
    slot = static_cast<int>(it - pending_.begin());
    pending_.insert(it, std::move(p));
  }
  Pending& p = pending_[slot];
  p.times[c] = time;
  p.set.present[c] = true;
  p.set.first_arrival_ns = std::min(p.set.first_arrival_ns, host_now);
  if (!by_time && p.count == 0) p.set.sequence = static_cast<std::uint64_t>(key);
  ++p.count;
  if (by_time) {
    p.key += (time - p.key) / p.count;  // running mean of the members' corrected times
    int lowest = 0;
    while (!p.set.present[lowest]) ++lowest;
    if (lowest == c) p.set.sequence = detections.sequence;
  }
  p.set.cameras[c] = std::move(detections);

  if (p.count == n) {
    // Complete: everything older goes first, incomplete.
    const int complete_slot = slot;
    for (int i = 0; i <= complete_slot; ++i) EmitFront(ready);
  }
  while (static_cast<int>(pending_.size()) > options_.max_pending_sets) EmitFront(ready);
  EmitTimedOut(host_now, ready);
  return Status::Ok();
}

void FrameSync::Poll(std::uint64_t host_now_ns, std::vector<DetectionSet>* ready) {
  if (!initialised_ || ready == nullptr) return;
  EmitTimedOut(host_now_ns, ready);
}

void FrameSync::Flush(std::vector<DetectionSet>* ready) {
  if (!initialised_ || ready == nullptr) return;
  while (!pending_.empty()) EmitFront(ready);
}

Status FrameSync::ResyncCamera(int camera) {
  if (!initialised_) return Status::Error("frame sync: Reset with valid options first");
  if (camera < 0 || camera >= options_.num_cameras)
    return Status::Error("frame sync: camera " + std::to_string(camera) +
                         " is outside the rig's " + std::to_string(options_.num_cameras) +
                         " cameras");
  if (options_.mode != FrameSyncOptions::Mode::kTimestamp && fits_.empty())
    return Status::Error("frame sync: camera " + std::to_string(camera) +
                         " cannot be re-synchronised in sequence mode without a timestamp check "
                         "(its frame ids restarted); use timestamp mode, or put its ids back on "
                         "the rig's count and set check_tolerance_ns");
  if (fits_.empty())
    return Status::Error("frame sync: offsets are given (estimate_offsets = false); set camera " +
                         std::to_string(camera) + "'s new offset with Reset");
  fits_[camera].Reset();
  return Status::Ok();
}

void FrameSync::EmitTimedOut(std::uint64_t host_now_ns, std::vector<DetectionSet>* ready) {
  if (options_.timeout_ns == 0) return;
  // Sets are emitted oldest first, so a timed-out set releases every older one too.
  int last = -1;
  for (int i = 0; i < static_cast<int>(pending_.size()); ++i) {
    const std::uint64_t first = pending_[i].set.first_arrival_ns;
    if (host_now_ns >= first && host_now_ns - first >= options_.timeout_ns) last = i;
  }
  for (int i = 0; i <= last; ++i) EmitFront(ready);
}

void FrameSync::EmitFront(std::vector<DetectionSet>* ready) {
  Pending& p = pending_.front();
  const int n = options_.num_cameras;
  const bool by_time = options_.mode == FrameSyncOptions::Mode::kTimestamp;
  DetectionSet& set = p.set;
  scratch_.clear();
  for (int c = 0; c < n; ++c) {
    if (set.present[c]) {
      scratch_.push_back(p.times[c]);
    } else {
      ++counters_.missing[c];
      set.cameras[c].camera = c;
      set.cameras[c].sequence = set.sequence;
    }
  }
  std::sort(scratch_.begin(), scratch_.end());
  const std::size_t m = scratch_.size();
  const std::int64_t median =
      m % 2 == 1 ? scratch_[m / 2] : scratch_[m / 2 - 1] + (scratch_[m / 2] - scratch_[m / 2 - 1]) / 2;
  set.timestamp_ns = static_cast<std::uint64_t>(median);
  if (p.count == n)
    ++counters_.complete;
  else
    ++counters_.incomplete;
  // The trigger-count check: the members' corrected times, of the cameras whose clock is fitted.
  if (!by_time && !fits_.empty()) {
    std::int64_t lo = 0, hi = 0;
    int checked = 0;
    for (int c = 0; c < n; ++c) {
      if (!set.present[c] || !fits_[c].drift_fitted()) continue;
      lo = checked == 0 ? p.times[c] : std::min(lo, p.times[c]);
      hi = checked == 0 ? p.times[c] : std::max(hi, p.times[c]);
      ++checked;
    }
    if (checked >= 2 && static_cast<std::uint64_t>(hi - lo) > options_.check_tolerance_ns)
      ++counters_.mismatched;
  }
  if (!emitted_any_ || p.key > last_emitted_key_) last_emitted_key_ = p.key;
  emitted_any_ = true;
  ready->push_back(std::move(set));
  pending_.erase(pending_.begin());
}

}  // namespace mocap::reconstruction
