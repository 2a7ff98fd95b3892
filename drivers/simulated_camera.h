// A pure in-process CameraSource (no Aravis): frames drawn by an ImageGenerator into a ring of
// pre-allocated images, for fast unit tests and the daemon's simulation tier.
//
// It behaves like a camera where it matters to the pipeline:
//   - pacing: frame n is due at start + n / frame rate (steady clock) and Grab() waits for it;
//     `unpaced` hands frames out as fast as they are asked for (tests). In software-trigger mode
//     a frame is made per Trigger(); a Grab() without one times out.
//   - ids: 16-bit frame ids that wrap, starting at `first_frame_id` so a test sees the wrap after
//     a few frames; the sequence is their unwrapped extension (its low 16 bits are the id, as
//     FrameIdUnwrapper gives on Aravis) and time = sequence / frame rate for the generator. With
//     `skip_zero_ids` (GigE Vision 1.x never uses block id 0) the sequences whose id would be 0
//     are never made: 65535 is followed by 1, the sequence by +2.
//   - the ring: Grab() needs a free image; when the caller holds them all the frame is lost and
//     counted as an underrun, as a real stream would.
//   - faults, injectable from any thread: DropFrames(n) (frames that never arrive: the sequence
//     jumps), FailFrames(n, status) (incomplete frames, counted, not delivered), Lose() (the
//     camera vanishes: Grab() returns kLost, counters.losses) and Restore() (it comes back; the
//     next Grab() reopens it, counters.reopens, and the sequence continues with the time that
//     passed), Reconnect(n) (unplugged and back, as a real camera: it misses the next n frames,
//     then its frame ids and its clock start again from the beginning), SlipCount(n) (its frame
//     counter runs n ahead of its exposures from the next frame on: a trigger pulse counted and
//     not exposed, as a glitch on a trigger line gives; its clock does not slip).
//   - a clock of its own, for the sync of rigs without a shared clock (free run, trigger checks):
//     device time = origin + clock_offset_ns + (1 + clock_drift_ppm) x (time since its first
//     frame), with gaussian jitter of timestamp_jitter_ns on each stamp; and a late start
//     (start_delay_ms: its first frame is the tick that long after Start()). Whatever its clock
//     says, frame n is exposed (drawn) at tick n of the host's steady clock, so the renderer's
//     truth for a frame is its tick: Frame::sequence until a Reconnect() restarts the ids.
//
// Usage:
//   drivers::SimulatedCamera cam(0, renderer.Generator(), {.width = 1280, .height = 1024});
//   cam.Open(settings);  cam.Start();
//   drivers::Frame f;
//   if (cam.Grab(&f) == drivers::GrabResult::kFrame) { ...; cam.Release(f); }
#pragma once
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <memory>
#include <mutex>
#include <random>
#include <string>
#include <vector>

#include "drivers/camera_source.h"

namespace mocap::drivers {

struct SimulatedCameraOptions {
  int width = 1280;  // the sensor
  int height = 1024;
  bool unpaced = false;                 // frames as fast as Grab() asks (tests)
  std::uint16_t first_frame_id = 1;
  bool skip_zero_ids = true;            // ids 1..65535 (GigE Vision 1.x); false: 0..65535
  std::uint64_t device_clock_origin_ns = 0;
  std::int64_t clock_offset_ns = 0;
  double clock_drift_ppm = 0;       // > 0: the device clock runs fast
  double timestamp_jitter_ns = 0;   // standard deviation
  std::uint64_t jitter_seed = 1;
  double start_delay_ms = 0;        // the first frame comes this late after Start()
  // > 0: the frames whose sequence is a multiple of this are never delivered (their ids are
  // used): ticks the camera did not expose, as a fake camera in a descheduled process skips.
  std::uint64_t unexposed_every = 0;

  bool IsValid(std::string* error) const;
};

class SimulatedCamera final : public CameraSource {
 public:
  SimulatedCamera(int camera_index, ImageGenerator generator, SimulatedCameraOptions options = {});
  ~SimulatedCamera() override = default;

  const std::string& id() const override { return id_; }
  Status Open(const CameraSettings& settings) override;
  Status Start() override;
  void Stop() override;
  GrabResult Grab(Frame* frame) override;
  void Release(const Frame& frame) override;
  Status Trigger() override;
  CameraState State() const override { return state_.load(); }
  const CameraCounters& Counters() const override { return counters_; }

  // Fault injection (any thread).
  void DropFrames(int n) { drop_.fetch_add(n); }
  void FailFrames(int n, FrameStatus status);
  void Lose() { lose_.store(true); }
  void Restore() { lose_.store(false); }
  void Reconnect(int missed_frames) { reconnect_.store(missed_frames); }
  void SlipCount(int n) { slip_.fetch_add(n); }

 private:
  struct Slot {
    std::unique_ptr<std::uint8_t[]> memory;
    bool held = false;
  };
  std::uint16_t IdOf(std::uint64_t sequence) const;
  void Count(FrameStatus status);

  int camera_;
  std::string id_;
  ImageGenerator generator_;
  SimulatedCameraOptions options_;
  CameraSettings settings_;
  int width_ = 0, height_ = 0;
  std::ptrdiff_t stride_ = 0;

  std::mutex mutex_;  // slots_ (Release from another thread) and triggers
  std::condition_variable cv_;
  std::vector<Slot> slots_;
  int pending_triggers_ = 0;

  bool opened_ = false;
  bool started_ = false;
  std::chrono::steady_clock::time_point start_time_;
  std::uint64_t first_sequence_ = 0;
  std::uint64_t next_sequence_ = 0;  // of the next frame to be made

  std::atomic<int> drop_{0};
  std::atomic<int> fail_{0};
  std::atomic<FrameStatus> fail_status_{FrameStatus::kMissingPackets};
  std::atomic<bool> lose_{false};
  std::atomic<int> reconnect_{-1};  // missed frames of a pending Reconnect(), -1: none
  std::atomic<int> slip_{0};        // pending SlipCount()
  std::uint64_t count_slip_ = 0;    // how far its count runs ahead since the (re)start
  // Where the ids and the clock (re)started: the tick of the first frame after Start() or the
  // last Reconnect().
  std::uint64_t restart_sequence_ = 0;
  std::mt19937_64 jitter_rng_;
  std::atomic<CameraState> state_{CameraState::kClosed};
  CameraCounters counters_;
};

}  // namespace mocap::drivers
