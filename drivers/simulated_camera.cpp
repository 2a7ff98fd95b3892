#include "drivers/simulated_camera.h"

#include <time.h>

#include <algorithm>
#include <cmath>
#include <thread>

namespace mocap::drivers {
bool SimulatedCameraOptions::IsValid(std::string* error) const {
  if (width < 1 || height < 1) {
    if (error) *error = "simulated camera options: width and height must be >= 1";
    return false;
  }
  if (!(std::abs(clock_drift_ppm) <= 1e5) || !(timestamp_jitter_ns >= 0) || !(start_delay_ms >= 0)) {
    if (error) *error = "simulated camera options: clock_drift_ppm must be within +-1e5, "
                        "timestamp_jitter_ns and start_delay_ms >= 0";
    return false;
  }
  return true;
}

SimulatedCamera::SimulatedCamera(int camera_index, ImageGenerator generator,
                                 SimulatedCameraOptions options)
    : camera_(camera_index),
      id_("sim-" + std::to_string(camera_index)),
      generator_(std::move(generator)),
      options_(options) {}

Status SimulatedCamera::Open(const CameraSettings& settings) {
  std::string error;
  if (!settings.IsValid(&error)) return Status::Error(id_ + ": " + error);
  if (!options_.IsValid(&error)) return Status::Error(id_ + ": " + error);
  const int w = settings.roi_width > 0 ? settings.roi_width : options_.width - settings.roi_x;
  const int h = settings.roi_height > 0 ? settings.roi_height : options_.height - settings.roi_y;
  if (w <= 0 || h <= 0 || settings.roi_x + w > options_.width ||
      settings.roi_y + h > options_.height) {
    return Status::Error(id_ + ": ROI x=" + std::to_string(settings.roi_x) + " y=" +
                         std::to_string(settings.roi_y) + " " + std::to_string(w) + "x" +
                         std::to_string(h) + " does not fit the " +
                         std::to_string(options_.width) + "x" + std::to_string(options_.height) +
                         " sensor");
  }
  if (!generator_) return Status::Error(id_ + ": no image generator");
  std::lock_guard<std::mutex> lock(mutex_);
  if (std::any_of(slots_.begin(), slots_.end(), [](const Slot& s) { return s.held; })) {
    return Status::Error(id_ + ": Open() while frames are still held");
  }
  settings_ = settings;
  // Packing is a matter of the wire: in process the frames are what a source hands out, Mono12.
  if (settings_.pixel_format == PixelFormat::kMono12Packed) settings_.pixel_format = PixelFormat::kMono12;
  width_ = w;
  height_ = h;
  stride_ = static_cast<std::ptrdiff_t>(w) * BytesPerPixel(settings.pixel_format);
  slots_.clear();
  slots_.resize(settings.buffer_count);
  for (Slot& s : slots_) s.memory.reset(new std::uint8_t[static_cast<std::size_t>(stride_) * h]());
  first_sequence_ = options_.first_frame_id;
  if (options_.skip_zero_ids && first_sequence_ == 0) first_sequence_ = 1;
  opened_ = true;
  started_ = false;
  pending_triggers_ = 0;
  state_ = CameraState::kClosed;
  return Status::Ok();
}

Status SimulatedCamera::Start() {
  if (!opened_) return Status::Error(id_ + ": Start() before a successful Open()");
  start_time_ = std::chrono::steady_clock::now();
  // A late start: the first frame is the tick start_delay_ms after Start().
  next_sequence_ =
      first_sequence_ +
      static_cast<std::uint64_t>(std::ceil(options_.start_delay_ms * 1e-3 * settings_.frame_rate_hz));
  restart_sequence_ = next_sequence_;
  reconnect_.store(-1);
  jitter_rng_.seed(options_.jitter_seed + static_cast<std::uint64_t>(camera_));
  started_ = true;
  state_ = lose_.load() ? CameraState::kLost : CameraState::kStreaming;
  return Status::Ok();
}

void SimulatedCamera::Stop() {
  started_ = false;
  if (state_.load() == CameraState::kStreaming) state_ = CameraState::kClosed;
  cv_.notify_all();
}

Status SimulatedCamera::Trigger() {
  if (settings_.trigger != TriggerMode::kSoftware) {
    return Status::Error(id_ + ": Trigger() needs TriggerMode::kSoftware (configured: " +
                         std::string(ToString(settings_.trigger)) + ")");
  }
  {
    std::lock_guard<std::mutex> lock(mutex_);
    ++pending_triggers_;
  }
  cv_.notify_one();
  return Status::Ok();
}

void SimulatedCamera::FailFrames(int n, FrameStatus status) {
  fail_status_.store(status);
  fail_.fetch_add(n);
}

std::uint16_t SimulatedCamera::IdOf(std::uint64_t sequence) const {
  return static_cast<std::uint16_t>(sequence & 0xFFFFu);
}

void SimulatedCamera::Count(FrameStatus status) {
  switch (status) {
    case FrameStatus::kComplete: counters_.complete++; break;
    case FrameStatus::kMissingPackets: counters_.missing_packets++; break;
    case FrameStatus::kTimeout: counters_.timeouts++; break;
    case FrameStatus::kUnderrun: counters_.underruns++; break;
    case FrameStatus::kSizeMismatch: counters_.size_mismatches++; break;
    case FrameStatus::kWrongFormat: counters_.wrong_format++; break;
    case FrameStatus::kOther: counters_.other_errors++; break;
  }
}

GrabResult SimulatedCamera::Grab(Frame* frame) {
  using Clock = std::chrono::steady_clock;
  if (!opened_ || !started_) return GrabResult::kStopped;
  const auto timeout = std::chrono::microseconds(static_cast<long>(settings_.timeout_ms * 1000));
  const auto period = std::chrono::duration<double>(1.0 / settings_.frame_rate_hz);
  auto due_of = [&](std::uint64_t seq) {
    return start_time_ + std::chrono::duration_cast<Clock::duration>(
                             period * static_cast<double>(seq - first_sequence_));
  };
  if (const int missed = reconnect_.exchange(-1); missed >= 0) {
    // Unplugged: this grab finds it gone; it comes back at the next one, `missed` frames on, with
    // its ids and clock started again.
    state_ = CameraState::kLost;
    counters_.losses++;
    next_sequence_ += static_cast<std::uint64_t>(missed);
    restart_sequence_ = next_sequence_;
    count_slip_ = 0;
    return GrabResult::kLost;
  }
  if (lose_.load()) {
    if (state_.load() != CameraState::kLost) {
      state_ = CameraState::kLost;
      counters_.losses++;
    }
    std::this_thread::sleep_for(std::min<Clock::duration>(timeout, std::chrono::milliseconds(5)));
    return GrabResult::kLost;
  }
  if (state_.load() == CameraState::kLost) {  // restored: reopen, skip the time it was away
    state_ = CameraState::kStreaming;
    counters_.reopens++;
    if (!options_.unpaced && settings_.trigger == TriggerMode::kFreeRun) {
      const double elapsed = std::chrono::duration<double>(Clock::now() - start_time_).count();
      next_sequence_ = std::max<std::uint64_t>(
          next_sequence_, first_sequence_ + static_cast<std::uint64_t>(
                                                elapsed * settings_.frame_rate_hz) + 1);
    }
  }
  for (;;) {
    if (options_.skip_zero_ids && (next_sequence_ & 0xFFFFu) == 0) ++next_sequence_;  // no id 0
    const std::uint64_t seq = next_sequence_;
    if (settings_.trigger == TriggerMode::kSoftware) {
      std::unique_lock<std::mutex> lock(mutex_);
      if (!cv_.wait_for(lock, timeout, [&] { return pending_triggers_ > 0 || !started_; }) ||
          !started_) {
        if (!started_) return GrabResult::kStopped;
        counters_.timeouts++;
        return GrabResult::kTimeout;
      }
      --pending_triggers_;
    } else if (!options_.unpaced) {
      const auto now = Clock::now();
      const auto due = due_of(seq);
      if (due > now + timeout) {
        std::this_thread::sleep_for(timeout);
        counters_.timeouts++;
        return GrabResult::kTimeout;
      }
      if (due > now) {
        std::this_thread::sleep_until(due);
      } else {
        // A consumer this late has let the ring overflow on a real camera: the frames older
        // than the ring are gone (underruns); the newest ones are still there.
        const auto behind = static_cast<std::uint64_t>(
            std::chrono::duration<double>(now - due) / period);
        if (behind > static_cast<std::uint64_t>(settings_.buffer_count)) {
          const std::uint64_t skip = behind - settings_.buffer_count;
          counters_.underruns += skip;
          next_sequence_ += skip;
          continue;
        }
      }
    }
    ++next_sequence_;
    const bool unexposed = options_.unexposed_every > 0 && seq % options_.unexposed_every == 0;
    if (unexposed || drop_.load() > 0) {  // never arrives
      if (!unexposed) drop_.fetch_sub(1);
      if (settings_.trigger == TriggerMode::kSoftware) {
        counters_.timeouts++;
        return GrabResult::kTimeout;
      }
      continue;
    }
    if (fail_.load() > 0) {
      fail_.fetch_sub(1);
      Count(fail_status_.load());
      return GrabResult::kIncomplete;
    }
    Slot* slot = nullptr;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      for (Slot& s : slots_) {
        if (!s.held) {
          slot = &s;
          s.held = true;
          break;
        }
      }
    }
    if (slot == nullptr) {
      counters_.underruns++;
      return GrabResult::kIncomplete;
    }
    generator_(camera_, seq, slot->memory.get(), width_, height_, stride_, settings_.pixel_format);
    frame->camera = camera_;
    // Its own count and clock since the (re)start.
    count_slip_ += static_cast<std::uint64_t>(slip_.exchange(0));
    const std::uint64_t counted = first_sequence_ + (seq - restart_sequence_) + count_slip_;
    frame->frame_id = IdOf(counted);
    frame->sequence = counted;
    const double since_ns = static_cast<double>(seq - restart_sequence_) * 1e9 /
                            settings_.frame_rate_hz * (1.0 + options_.clock_drift_ppm * 1e-6);
    const double jitter = options_.timestamp_jitter_ns > 0
                              ? std::normal_distribution<double>(0, options_.timestamp_jitter_ns)(
                                    jitter_rng_)
                              : 0.0;
    frame->device_timestamp_ns = static_cast<std::uint64_t>(
        static_cast<double>(options_.device_clock_origin_ns) +
        static_cast<double>(options_.clock_offset_ns) + std::max(0.0, since_ns + jitter));
    frame->host_timestamp_ns = MonotonicNs();
    frame->status = FrameStatus::kComplete;
    frame->image.data = slot->memory.get();
    frame->image.width = width_;
    frame->image.height = height_;
    frame->image.stride = stride_;
    frame->image.format = settings_.pixel_format;
    frame->handle = slot;
    counters_.complete++;
    return GrabResult::kFrame;
  }
}

void SimulatedCamera::Release(const Frame& frame) {
  std::lock_guard<std::mutex> lock(mutex_);
  for (Slot& s : slots_) {
    if (&s == frame.handle) {
      s.held = false;
      return;
    }
  }
}

}  // namespace mocap::drivers
