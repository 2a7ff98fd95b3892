#include "daemon/capture_pipeline.h"

#include <pthread.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <ctime>
#include <limits>
#include <numbers>

namespace mocap::daemon {

using drivers::MonotonicNs;

void NameThisThread(const std::string& name) {
  pthread_setname_np(pthread_self(), name.substr(0, 15).c_str());
}

double Percentile(std::vector<double>* values, double p) {
  if (values->empty()) return 0.0;
  const std::size_t n = values->size();
  std::size_t k = static_cast<std::size_t>(std::ceil(p / 100.0 * n));
  k = std::clamp<std::size_t>(k, 1, n) - 1;
  std::nth_element(values->begin(), values->begin() + k, values->end());
  return (*values)[k];
}

std::vector<double> SilentCameraSeconds(const std::vector<std::uint64_t>& last_frame_ns,
                                        std::uint64_t now_ns, double silence_s) {
  std::vector<double> since(last_frame_ns.size()), out(last_frame_ns.size(), 0.0);
  for (std::size_t c = 0; c < since.size(); ++c)
    since[c] = now_ns > last_frame_ns[c] ? static_cast<double>(now_ns - last_frame_ns[c]) * 1e-9 : 0.0;
  for (std::size_t c = 0; c < since.size(); ++c) {
    if (since[c] <= silence_s) continue;
    for (std::size_t o = 0; o < since.size(); ++o) {
      if (o != c && since[o] <= silence_s) {
        out[c] = since[c];
        break;
      }
    }
  }
  return out;
}

bool CapturePipelineOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& what) {
    if (error) *error = "capture pipeline: " + what;
    return false;
  };
  if (detection_threads < 1 || detection_threads > 64) {
    return fail("detection_threads must be in [1, 64]");
  }
  if (!(rate_hz >= 0) || rate_hz > 100000) return fail("rate_hz must be in [0, 100000]");
  if (rig_sync != RigSync::kTrigger && rate_hz <= 0)
    return fail(std::string(rig_sync == RigSync::kFreeRun ? "free-run" : "shared-clock") +
                " sync needs rate_hz > 0 (the rig's frame rate)");
  if (!(free_run_tolerance > 0 && free_run_tolerance < 0.5))
    return fail("free_run_tolerance must be in (0, 0.5) of a frame period");
  if (!(trigger_check_tolerance >= 0 && trigger_check_tolerance < 0.5))
    return fail("trigger_check_tolerance must be in [0, 0.5) of a frame period");
  if (frame_queue_capacity < 1 || detection_queue_capacity < 1 || point_queue_capacity < 1) {
    return fail("queue capacities must be >= 1");
  }
  if (start_complete_sets < 1 || start_complete_sets > 100000) {
    return fail("start_complete_sets must be in [1, 100000]");
  }
  if (start_timeout_ms < 0 || start_timeout_ms > 600000) {
    return fail("start_timeout_ms must be in [0, 600000]");
  }
  if (!(camera_silence_s >= 0 && camera_silence_s <= 3600))
    return fail("camera_silence_s must be in [0, 3600] seconds");
  std::string sub;
  if (!detection.IsValid(&sub)) return fail(sub);
  return true;
}

CapturePipeline::CapturePipeline(std::vector<std::unique_ptr<drivers::CameraSource>> cameras,
                                 TriangulateFn triangulate, CapturePipelineOptions options)
    : cameras_(std::move(cameras)),
      triangulate_(std::move(triangulate)),
      options_(std::move(options)),
      detections_(options_.detection_queue_capacity),
      points_(options_.point_queue_capacity) {
  stats_.camera_losses.assign(cameras_.size(), 0);
  // Slot i starts with a value whose low bits never equal those of a sequence of slot i.
  delivered_ = std::make_unique<std::atomic<std::uint64_t>[]>(kDeliveredRing);
  delivered_underruns_ = std::make_unique<std::atomic<std::uint64_t>[]>(kDeliveredRing);
  for (std::size_t i = 0; i < kDeliveredRing; ++i) {
    delivered_[i].store((i + 1) % kDeliveredRing);
    delivered_underruns_[i].store(0);
  }
}

std::uint64_t CapturePipeline::CameraUnderruns() const {
  std::uint64_t sum = 0;
  for (const auto& cam : cameras_) sum += cam->Counters().underruns.load(std::memory_order_relaxed);
  return sum;
}

// The sequence the sync groups a frame by (DetectLoop gives it to the sync).
std::uint64_t CapturePipeline::SyncSequence(const drivers::Frame& frame) const {
  return options_.rig_sync == CapturePipelineOptions::RigSync::kSharedClock
             ? drivers::SequenceOfTimestamp(frame.device_timestamp_ns, options_.rate_hz)
             : frame.sequence;
}

// Whether a camera delivered a frame of the sync's sequence `sequence`, compared on the bits the
// sync keeps (kTrigger unwraps 16-bit ids itself).
bool CapturePipeline::Delivered(std::uint64_t sequence) const {
  const int bits = options_.sync.sequence_bits;
  const std::uint64_t mask = bits >= 64 ? ~std::uint64_t{0} : (std::uint64_t{1} << bits) - 1;
  return ((delivered_[sequence % kDeliveredRing].load(std::memory_order_acquire) ^ sequence) & mask) == 0;
}

CapturePipeline::~CapturePipeline() { Stop(); }

Status CapturePipeline::Start() {
  if (started_) return Status::Error("capture pipeline: already started");
  std::string error;
  if (!options_.IsValid(&error)) return Status::Error(error);
  if (cameras_.empty()) return Status::Error("capture pipeline: no cameras");
  if (!triangulate_) return Status::Error("capture pipeline: no triangulation stage");
  options_.sync.num_cameras = static_cast<int>(cameras_.size());
  const double rate = options_.rate_hz;
  using Mode = reconstruction::FrameSyncOptions::Mode;
  switch (options_.rig_sync) {
    case CapturePipelineOptions::RigSync::kSharedClock:
      options_.sync.mode = Mode::kSequence;
      options_.sync.sequence_bits = 64;  // ticks of the one clock, the same on every camera
      options_.sync.check_tolerance_ns = 0;
      break;
    case CapturePipelineOptions::RigSync::kTrigger:
      options_.sync.mode = Mode::kSequence;
      options_.sync.check_tolerance_ns =
          rate > 0 ? static_cast<std::uint64_t>(options_.trigger_check_tolerance * 1e9 / rate) : 0;
      break;
    case CapturePipelineOptions::RigSync::kFreeRun:
      options_.sync.mode = Mode::kTimestamp;
      options_.sync.estimate_offsets = true;
      options_.sync.tolerance_ns = static_cast<std::uint64_t>(options_.free_run_tolerance * 1e9 / rate);
      break;
  }
  if (options_.camera_silence_s == 0)
    options_.camera_silence_s = std::max(0.5, rate > 0 ? 20 / rate : 0.0);
  if (rate > 0) {
    // The sync waits up to its timeout for a camera that is behind; its window must hold that
    // many sets, or a camera 40 ms behind (8 sets at 200 Hz: a detection worker descheduled on a
    // loaded machine) loses its frames as late although the timeout would have waited.
    const double timeout_sets = std::ceil(options_.sync.timeout_ns * 1e-9 * rate);
    options_.sync.max_pending_sets = std::max(
        options_.sync.max_pending_sets, std::min(static_cast<int>(timeout_sets), 4096));
  }
  MOCAP_RETURN_IF_ERROR(sync_.Reset(options_.sync));
  sync_epoch_.assign(cameras_.size(), 0);
  numbered_any_ = false;
  rig_clock_.Reset();
  rig_newest_sequence_ = 0;
  {
    std::lock_guard<std::mutex> lock(stats_mutex_);
    stats_.camera_resyncs.assign(cameras_.size(), 0);
    stats_.camera_clock_offset_ms.assign(cameras_.size(), 0.0);
    stats_.camera_clock_drift_ppm.assign(cameras_.size(), 0.0);
    stats_.camera_clock_residual_us.assign(cameras_.size(), 0.0);
    stats_.camera_clock_fitted.assign(cameras_.size(), false);
    stats_.camera_count_mismatches.assign(cameras_.size(), 0);
    stats_.camera_tick_phase.assign(cameras_.size(), -1.0);
    stats_.camera_silent_s.assign(cameras_.size(), 0.0);
    // A camera's first frame may come up to the start-up's timeout after the others' (see the
    // header): its silence counts from there.
    last_frame_ns_.assign(cameras_.size(),
                          MonotonicNs() + static_cast<std::uint64_t>(options_.start_timeout_ms) * 1000000u);
    tick_phase_cos_.assign(cameras_.size(), 0.0);
    tick_phase_sin_.assign(cameras_.size(), 0.0);
  }
  frames_.clear();
  const int per_worker =
      std::max(1, options_.frame_queue_capacity / options_.detection_threads);
  for (int w = 0; w < options_.detection_threads; ++w) {
    frames_.push_back(std::make_unique<BoundedQueue<drivers::Frame>>(per_worker));
  }

  // Consumers first, so that nothing a producer emits waits for a stage that does not exist.
  sync_thread_ = std::thread(&CapturePipeline::SyncLoop, this);
  for (int w = 0; w < options_.detection_threads; ++w) {
    detect_threads_.emplace_back(&CapturePipeline::DetectLoop, this, w);
  }
  started_ = true;
  grabbing_ = true;
  for (std::size_t c = 0; c < cameras_.size(); ++c) {
    if (Status s = cameras_[c]->Start(); !s) {
      Stop();
      return Status::Error("camera " + cameras_[c]->id() + ": " + s.message());
    }
  }
  for (std::size_t c = 0; c < cameras_.size(); ++c) {
    grab_threads_.emplace_back(&CapturePipeline::GrabLoop, this, static_cast<int>(c));
  }
  return Status::Ok();
}

void CapturePipeline::Stop() {
  if (!started_) return;
  started_ = false;
  // Reverse order: cameras, then each queue closed after its producers are gone.
  grabbing_ = false;
  for (auto& cam : cameras_) cam->Stop();
  for (auto& t : grab_threads_) t.join();
  grab_threads_.clear();
  for (auto& q : frames_) q->Close();
  for (auto& t : detect_threads_) t.join();
  detect_threads_.clear();
  detections_.Close();
  if (sync_thread_.joinable()) sync_thread_.join();
  points_.Close();
}

void CapturePipeline::GrabLoop(int c) {
  NameThisThread("grab-" + std::to_string(c));
  drivers::CameraSource& cam = *cameras_[c];
  bool was_lost = false;
  // The camera's stream: its generation (+1 after each loss), the correction that puts its ids
  // on the rig's trigger count after a loss or a late start, and its last delivered frame.
  std::uint32_t epoch = 0;
  std::uint64_t sequence_shift = 0;  // modular
  std::uint64_t reopens_seen = cam.Counters().reopens.load();
  bool delivered = false;
  int placing = 0;  // frames left to place it on the rig's trigger count
  double best_excess_ns = 0;
  bool force_shift = false;
  // Its previous frame of this epoch (own count and timestamp): the count-vs-timestamp check.
  bool have_previous = false;
  std::uint64_t previous_sequence = 0, previous_device_ns = 0;
  while (grabbing_) {
    if (options_.test_hold) options_.test_hold("grab");
    drivers::Frame frame;
    const drivers::GrabResult r = cam.Grab(&frame);
    if (r == drivers::GrabResult::kFrame) {
      const std::uint64_t reopens = cam.Counters().reopens.load();
      const bool returned = was_lost || reopens != reopens_seen;
      if (returned) {
        ++epoch;
        reopens_seen = reopens;
      }
      was_lost = false;
      if (returned) have_previous = false;
      bool count_mismatch = false;
      if (have_previous && options_.rate_hz > 0 && frame.device_timestamp_ns > previous_device_ns) {
        const double periods =
            static_cast<double>(frame.device_timestamp_ns - previous_device_ns) * options_.rate_hz * 1e-9;
        count_mismatch = static_cast<long long>(frame.sequence - previous_sequence) != std::llround(periods);
      }
      have_previous = true;
      previous_sequence = frame.sequence;
      previous_device_ns = frame.device_timestamp_ns;
      const bool trigger_count =
          options_.rig_sync == CapturePipelineOptions::RigSync::kTrigger && options_.rate_hz > 0;
      if (trigger_count && (returned || !delivered)) {
        // Its ids restarted (a return) or began while the rig may already have been running (a
        // start): over its next frames it is placed on the rig's count.
        placing = kPlacementFrames;
        best_excess_ns = std::numeric_limits<double>::infinity();
        force_shift = returned;
      }
      const std::uint64_t arrived =
          frame.received_ns != 0 ? frame.received_ns : frame.host_timestamp_ns;
      if (placing > 0) {
        // The trigger it is: the rig's clock (the lower envelope of the arrivals of the rig's
        // triggers, below) says when trigger n reached the host; the frame that arrived
        // closest to a trigger's time, over the first kPlacementFrames, waited least and says
        // which trigger it was.
        --placing;
        std::lock_guard<std::mutex> lock(stats_mutex_);
        if (rig_clock_.samples() > 0) {
          const double period_ns = 1e9 / options_.rate_hz;
          const std::uint64_t r = rig_newest_sequence_;
          const double since = static_cast<double>(arrived) -
                               static_cast<double>(rig_clock_.ToHost(
                                   static_cast<std::uint64_t>(r * period_ns)));
          const long long steps = std::llround(since / period_ns);
          const double excess = std::abs(since - steps * period_ns);
          if (excess < best_excess_ns) {
            best_excess_ns = excess;
            const std::uint64_t expected = r + static_cast<std::uint64_t>(steps);
            const std::uint64_t own = frame.sequence;  // its own count, not yet shifted
            // At start-up the cameras' first frames are the same triggers, numbered alike: only
            // a camera whose own count is two or more triggers off the rig's (it started after
            // the triggers had begun) is renumbered. A returning camera always is.
            const auto off = static_cast<std::int64_t>(expected - own);
            if (force_shift || off >= 2 || off <= -2) sequence_shift = expected - own;
          }
        }
      }
      frame.sequence += sequence_shift;
      frame.stream_epoch = epoch;
      delivered = true;
      frame.camera = c;
      std::lock_guard<std::mutex> lock(stats_mutex_);
      if (trigger_count && placing == 0) {
        rig_clock_.Add(static_cast<std::uint64_t>(frame.sequence * (1e9 / options_.rate_hz)),
                       arrived);
        rig_newest_sequence_ = std::max(rig_newest_sequence_, frame.sequence);
      }
      ++stats_.frames_grabbed;
      last_frame_ns_[c] = MonotonicNs();
      if (count_mismatch) ++stats_.camera_count_mismatches[c];
      if (options_.rig_sync == CapturePipelineOptions::RigSync::kSharedClock) AddTickPhase(c, frame);
      if (options_.rig_sync != CapturePipelineOptions::RigSync::kFreeRun) {
        const std::uint64_t sequence = SyncSequence(frame);
        delivered_underruns_[sequence % kDeliveredRing].store(CameraUnderruns(), std::memory_order_relaxed);
        delivered_[sequence % kDeliveredRing].store(sequence, std::memory_order_release);
      }
      BoundedQueue<drivers::Frame>& queue = *frames_[c % frames_.size()];
      if (!queue.TryPush(std::move(frame))) {  // full: the frame is left to us
        ++stats_.frames_dropped;
        cam.Release(frame);
      }
    } else if (r == drivers::GrabResult::kIncomplete) {
      std::lock_guard<std::mutex> lock(stats_mutex_);
      ++stats_.frames_incomplete;
    } else if (r == drivers::GrabResult::kLost) {
      {
        std::lock_guard<std::mutex> lock(stats_mutex_);
        if (!was_lost) ++stats_.camera_losses[c];
        // Lost is the driver's word, not silence; once reopened its silence counts from here.
        last_frame_ns_[c] = MonotonicNs();
      }
      was_lost = true;
      // The source reopens a lost camera by itself; poll it without spinning.
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    } else if (r == drivers::GrabResult::kStopped) {
      break;
    }
  }
}

void CapturePipeline::AddTickPhase(std::size_t camera, const drivers::Frame& frame) {
  constexpr double kWeight = 1.0 / 50;
  const long double period_ns = 1e9L / options_.rate_hz;
  const double phase = static_cast<double>(
      std::fmod(static_cast<long double>(frame.device_timestamp_ns), period_ns) / period_ns);
  const double angle = 2 * std::numbers::pi * phase;
  double& x = tick_phase_cos_[camera];
  double& y = tick_phase_sin_[camera];
  const bool first = stats_.camera_tick_phase[camera] < 0;
  x = first ? std::cos(angle) : x + kWeight * (std::cos(angle) - x);
  y = first ? std::sin(angle) : y + kWeight * (std::sin(angle) - y);
  const double mean = std::atan2(y, x) / (2 * std::numbers::pi);
  stats_.camera_tick_phase[camera] = mean < 0 ? mean + 1 : mean;
}

void CapturePipeline::DetectLoop(int worker) {
  NameThisThread("detect-" + std::to_string(worker));
  reconstruction::DetectionWorkspace workspace;
  drivers::Frame frame;
  BoundedQueue<drivers::Frame>& queue = *frames_[worker];
  for (;;) {
    if (!queue.Pop(&frame, std::chrono::milliseconds(50))) {
      if (queue.closed()) break;  // closed and drained
      continue;
    }
    if (options_.test_hold) options_.test_hold("detection");
    reconstruction::CameraDetections d;
    d.camera = frame.camera;
    d.sequence = SyncSequence(frame);
    d.stream_epoch = frame.stream_epoch;
    d.device_timestamp_ns = frame.device_timestamp_ns;
    d.host_timestamp_ns = frame.host_timestamp_ns;
    d.received_ns = frame.received_ns;
    const auto t0 = std::chrono::steady_clock::now();
    const Status s = reconstruction::DetectMarkers(frame.image, options_.detection, nullptr,
                                                   &workspace, &d.centroids);
    const double ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    cameras_[frame.camera]->Release(frame);
    std::lock_guard<std::mutex> lock(stats_mutex_);
    detect_ms_.Add(ms);
    ++stats_.frames_detected;
    if (!s) {
      ++stats_.detection_errors;
      d.centroids.clear();  // the set still learns that this camera saw nothing usable
    }
    if (!detections_.TryPush(std::move(d))) ++stats_.detections_dropped;
  }
}

bool CapturePipeline::Recording(const reconstruction::DetectionSet& set) {
  std::lock_guard<std::mutex> lock(stats_mutex_);
  if (stats_.recording) return true;
  const std::uint64_t now = MonotonicNs();
  if (first_set_host_ns_ == 0) first_set_host_ns_ = now;
  const bool complete = set.present_count() == static_cast<int>(set.present.size());
  const bool timed_out =
      now - first_set_host_ns_ >= static_cast<std::uint64_t>(options_.start_timeout_ms) * 1000000u;
  complete_run_ = complete ? complete_run_ + 1 : 0;
  if (options_.start_on_complete_set && complete_run_ < options_.start_complete_sets &&
      !timed_out) {
    ++stats_.warmup_sets;
    return false;
  }
  stats_.recording = true;
  stats_.warmup_ms = (now - first_set_host_ns_) * 1e-6;
  for (std::size_t c = 0; c < set.present.size(); ++c) {
    if (!set.present[c]) stats_.cameras_missing_at_start.push_back(static_cast<int>(c));
  }
  return true;
}

void CapturePipeline::NumberByTime(reconstruction::DetectionSet* set) {
  // A phase-locked count: the expected time of the next set runs on by whole periods and is
  // pulled a tenth of the way towards each set's time, so that which cameras a set holds (its
  // median time moves within the tolerance) does not change its number, while the cameras' rate
  // error against the nominal rate (ppm) is followed.
  const double period_ns = 1e9 / options_.rate_hz;
  if (!numbered_any_) {
    numbered_any_ = true;
    numbered_sequence_ = set->sequence;
    numbered_time_ns_ = set->timestamp_ns;
    return;
  }
  const double dt = static_cast<double>(static_cast<std::int64_t>(set->timestamp_ns -
                                                                  numbered_time_ns_));
  const long long steps = std::max<long long>(1, std::llround(dt / period_ns));
  const double expected = static_cast<double>(numbered_time_ns_) + steps * period_ns;
  numbered_time_ns_ = static_cast<std::uint64_t>(
      expected + 0.1 * (static_cast<double>(set->timestamp_ns) - expected));
  numbered_sequence_ += static_cast<std::uint64_t>(steps);
  set->sequence = numbered_sequence_;
}

void CapturePipeline::EmitSet(reconstruction::DetectionSet& set) {
  if (options_.rig_sync == CapturePipelineOptions::RigSync::kFreeRun) NumberByTime(&set);
  if (!Recording(set)) return;
  PointFrame out;
  out.sequence = set.sequence;
  out.timestamp_ns = set.timestamp_ns;
  out.cameras_present = set.present_count();
  const auto t0 = std::chrono::steady_clock::now();
  const Status s = triangulate_(set, &out);
  const auto t1 = std::chrono::steady_clock::now();
  std::uint64_t first = UINT64_MAX, last = 0;
  for (std::size_t c = 0; c < set.cameras.size(); ++c) {
    if (!set.present[c]) continue;
    if (c < 64) out.present_mask |= std::uint64_t{1} << c;
    if (out.device_timestamp_ns == 0) out.device_timestamp_ns = set.cameras[c].device_timestamp_ns;
    const auto& cam = set.cameras[c];
    const std::uint64_t received = cam.received_ns != 0 ? cam.received_ns : cam.host_timestamp_ns;
    first = std::min(first, received);
    last = std::max(last, received);
  }
  if (options_.keep_detections || keep_detections_.load(std::memory_order_relaxed))
    out.detections = set.cameras;
  const std::uint64_t now = MonotonicNs();
  out.latency_ms = first <= now ? (now - first) * 1e-6 : 0.0;
  out.first_host_ns = first == UINT64_MAX ? now : first;
  out.last_host_ns = last == 0 ? now : last;
  out.ready_host_ns = now;

  std::lock_guard<std::mutex> lock(stats_mutex_);
  for (std::size_t c = 0; c < cameras_.size(); ++c) {
    stats_.camera_clock_offset_ms[c] = sync_.offset_ns(static_cast<int>(c)) * 1e-6;
    stats_.camera_clock_drift_ppm[c] = sync_.drift_ppm(static_cast<int>(c));
    stats_.camera_clock_residual_us[c] = sync_.clock_residual_ns(static_cast<int>(c)) * 1e-3;
    stats_.camera_clock_fitted[c] = sync_.clock_fitted(static_cast<int>(c));
  }
  stats_.mismatched_sets = sync_.counters().mismatched;
  triangulate_ms_.Add(std::chrono::duration<double, std::milli>(t1 - t0).count());
  if (!s) ++stats_.triangulation_errors;
  if (any_emitted_ && set.sequence > last_emitted_sequence_ + 1) {
    const std::uint64_t gap = set.sequence - last_emitted_sequence_ - 1;
    // Whether a camera's ring underran between the deliveries of the sets on either side of the
    // gap (which sequences an underrun lost is not known): the gap may then be the daemon's doing
    // and is counted as such, as it is when either side's record is gone.
    const bool recorded = Delivered(last_emitted_sequence_) && Delivered(set.sequence);
    const bool underran =
        !recorded || delivered_underruns_[set.sequence % kDeliveredRing].load(std::memory_order_relaxed) !=
                         delivered_underruns_[last_emitted_sequence_ % kDeliveredRing].load(std::memory_order_relaxed);
    std::uint64_t undelivered = 0;
    // A gap longer than the ring cannot be told apart: all of it is counted as the daemon's.
    if (options_.rig_sync != CapturePipelineOptions::RigSync::kFreeRun && gap <= kDeliveredRing && !underran)
      for (std::uint64_t q = last_emitted_sequence_ + 1; q < set.sequence; ++q) undelivered += Delivered(q) ? 0 : 1;
    stats_.undelivered_frame_sets += undelivered;
    stats_.dropped_frame_sets += gap - undelivered;
  }
  if (!any_emitted_ || set.sequence > last_emitted_sequence_) last_emitted_sequence_ = set.sequence;
  any_emitted_ = true;
  latency_ms_.Add(out.latency_ms);
  if (out.cameras_present < static_cast<int>(cameras_.size())) ++stats_.incomplete_sets;
  if (points_.TryPush(std::move(out))) {
    ++stats_.frame_sets;
  } else {
    ++stats_.dropped_frame_sets;
  }
}

void CapturePipeline::SyncLoop() {
  NameThisThread("sync");
  std::vector<reconstruction::DetectionSet> ready;
  reconstruction::CameraDetections d;
  for (;;) {
    const bool got = detections_.Pop(&d, std::chrono::milliseconds(5));
    ready.clear();
    if (got) {
      const int c = d.camera;
      if (c >= 0 && c < static_cast<int>(sync_epoch_.size()) && d.stream_epoch != sync_epoch_[c]) {
        // The camera came back from a loss: its clock restarted (a no-op error where the sync
        // fits no clocks: shared clock, or a trigger count without a check).
        sync_epoch_[c] = d.stream_epoch;
        if (sync_.ResyncCamera(c).ok()) {
          std::lock_guard<std::mutex> lock(stats_mutex_);
          ++stats_.camera_resyncs[c];
        }
      }
      if (!sync_.Add(std::move(d), &ready)) {
        std::lock_guard<std::mutex> lock(stats_mutex_);
        ++stats_.sync_errors;
      }
    }
    sync_.Poll(MonotonicNs(), &ready);
    for (auto& set : ready) EmitSet(set);
    if (!got && detections_.closed() && detections_.size() == 0) break;
  }
  ready.clear();
  sync_.Flush(&ready);
  for (auto& set : ready) EmitSet(set);
  std::lock_guard<std::mutex> lock(stats_mutex_);
  stats_.late_frames = sync_.counters().late;
}

bool CapturePipeline::PopPoints(PointFrame* out, int timeout_ms) {
  return points_.Pop(out, std::chrono::milliseconds(timeout_ms));
}

CapturePipelineStats CapturePipeline::Stats(bool timings) const {
  std::lock_guard<std::mutex> lock(stats_mutex_);
  CapturePipelineStats s = stats_;
  for (const auto& q : frames_) {
    const QueueDepth d = q->Depth();
    s.frame_queue.depth = std::max(s.frame_queue.depth, d.depth);
    s.frame_queue.max_depth = std::max(s.frame_queue.max_depth, d.max_depth);
    s.frame_queue.capacity = d.capacity;
  }
  s.detection_queue = detections_.Depth();
  s.point_queue = points_.Depth();
  if (!last_frame_ns_.empty()) {  // since Start()
    // A camera its driver does not call streaming (lost, being reopened, awaited) is missing,
    // not silent; once it streams again its silence counts from then (to within the callers'
    // polling: the daemon's 100 ms tick), not from its last frame before the loss.
    const std::uint64_t now = MonotonicNs();
    for (std::size_t c = 0; c < cameras_.size(); ++c)
      if (cameras_[c]->State() != drivers::CameraState::kStreaming)
        last_frame_ns_[c] = std::max(last_frame_ns_[c], now);
    s.camera_silent_s = SilentCameraSeconds(last_frame_ns_, now, options_.camera_silence_s);
  }
  if (!timings) return s;
  s.detect_ms_p50 = detect_ms_.Percentile(50);
  s.detect_ms_p99 = detect_ms_.Percentile(99);
  s.triangulate_ms_p50 = triangulate_ms_.Percentile(50);
  s.triangulate_ms_p99 = triangulate_ms_.Percentile(99);
  s.latency_ms_p50 = latency_ms_.Percentile(50);
  s.latency_ms_p99 = latency_ms_.Percentile(99);
  return s;
}

}  // namespace mocap::daemon
