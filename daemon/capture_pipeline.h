// The capture pipeline: camera frames in, unlabelled 3D points out, in real time.
//
//   grab (one thread per camera) --frames--> detection (a pool of workers) --detections-->
//   sync + triangulation (one thread) --point frames--> the caller (PopPoints)
//
// Each camera's frames always go to the same detection worker (camera c to worker c mod W, each
// worker with its own queue), so that a camera's detections reach the sync in the order its frames
// were taken. The sync relies on that order: when a newer set completes it emits the older pending
// ones incomplete, which is right only if no camera's older frame is still being detected. With
// one shared queue a worker descheduled in the middle of camera c's frame n lets the other
// workers finish every camera's frame n+1 first; set n then left without camera c and its frame
// arrived late (on a loaded machine: tens of sets in a few seconds).
//
// Stages are joined by BoundedQueues (daemon/bounded_queue.h). Nothing waits for a slow stage:
// when a queue is full the frame (or point frame) is dropped and counted, the camera's buffer
// goes straight back to its pool, and the frame set it belonged to goes on incomplete or is
// counted as dropped. A camera that is lost stops contributing; its sets are emitted incomplete
// by the sync's timeout while the other cameras go on (the source reopens it: drivers/).
//
// Stages start in dependency order (consumers first: output, triangulation, detection, then the
// cameras) and stop in reverse (cameras first, then each queue is closed and drained), so no
// frame is left in a queue and no buffer is lost at Stop().
//
// Start-up. Cameras do not begin streaming at one instant: for the first tenths of a second after
// Start() the sets hold whichever cameras are already running (on a loaded machine, two of eight).
// Those are not a recording: triangulated from a couple of neighbouring cameras their points are
// several times less precise, and a recording that starts with them starts with a transient. Nor
// is the first complete set the end of it: the cameras' first frames also fill their buffer pools
// for the first time, and on a loaded machine the sets go on arriving incomplete for a while. So
// the recording begins once the rig has been live for `start_complete_sets` consecutive COMPLETE
// sets (what Vicon and Qualisys call the rig being live); the sets before are counted as warm-up
// and never handed out. A camera that does not
// stream cannot hold the rig hostage: `start_timeout_ms` after the first set, the recording
// begins with the cameras it has, and Stats() names the ones missing at the start.
//
// Latency is measured from the host time the first image of a set was received by the transport
// (Frame::received_ns, Aravis's system timestamp, so the wait in the driver's queue counts; else
// Frame::host_timestamp_ns, when it was handed over), CLOCK_MONOTONIC, to the moment its points
// are ready.
#pragma once
#include <atomic>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include <Eigen/Core>

#include "daemon/bounded_queue.h"
#include "drivers/camera_source.h"
#include "model/status.h"
#include "reconstruction/centroid.h"
#include "reconstruction/clock_fit.h"
#include "reconstruction/detection.h"
#include "reconstruction/frame_sync.h"

namespace mocap::daemon {

// Names the calling thread (at most 15 characters are kept): `top -H` and the daemon's CPU-per-stage
// figures (bench/daemon_latency.cpp reads /proc/PID/task/*/comm) tell the stages apart.
void NameThisThread(const std::string& name);

// The p-th percentile (0..100) of `values` (nearest rank); 0 when empty. Reorders `values`.
double Percentile(std::vector<double>* values, double p);

// The most recent `capacity` samples of a timing, in a ring allocated once: a daemon runs for
// hours at thousands of frames a second, so keeping every sample would grow without bound.
class RecentSamples {
 public:
  explicit RecentSamples(std::size_t capacity) : ring_(capacity ? capacity : 1) {}
  void Add(double v) {
    ring_[next_] = v;
    next_ = (next_ + 1) % ring_.size();
    if (size_ < ring_.size()) ++size_;
  }
  // The p-th percentile of the samples held.
  double Percentile(double p) const {
    std::vector<double> v(ring_.begin(), ring_.begin() + size_);
    return daemon::Percentile(&v, p);
  }

 private:
  std::vector<double> ring_;
  std::size_t next_ = 0, size_ = 0;
};


// Per camera, seconds since `last_frame_ns[c]` (CLOCK_MONOTONIC) where camera c delivered nothing
// for more than `silence_s` while another camera delivered within it, else 0. A time after
// `now_ns` counts as delivering (a camera still in its start-up's grace).
std::vector<double> SilentCameraSeconds(const std::vector<std::uint64_t>& last_frame_ns,
                                        std::uint64_t now_ns, double silence_s);

// The points of one frame set.
struct PointFrame {
  std::uint64_t sequence = 0;
  std::uint64_t timestamp_ns = 0;         // the set's time (reconstruction/frame_sync.h)
  std::uint64_t device_timestamp_ns = 0;  // raw device time of its first present camera
  int cameras_present = 0;
  std::uint64_t present_mask = 0;         // bit c: camera c's image is in the set (c < 64)
  std::vector<Eigen::Vector3d> points;
  std::vector<float> residual_px;
  std::vector<std::uint8_t> camera_count;
  double latency_ms = 0;
  // CLOCK_MONOTONIC host times at which the first and the last image of the set were received
  // (see the header), and at which its points were ready (the live latency's stages).
  std::uint64_t first_host_ns = 0, last_host_ns = 0, ready_host_ns = 0;
  // The 2D detections the points came from (CapturePipelineOptions::keep_detections), per camera
  // of the rig; empty otherwise.
  std::vector<reconstruction::CameraDetections> detections;
};

// Turns one set of detections into 3D points (reconstruction/triangulation.h, wired by the
// caller). Called from the one triangulation thread only, so it may keep its workspace.
using TriangulateFn = std::function<Status(const reconstruction::DetectionSet&, PointFrame*)>;

struct CapturePipelineOptions {
  int detection_threads = 2;
  // Frames waiting for detection, all cameras and workers (each worker's queue holds its share):
  // 128 is 80 ms of 8 cameras at 200 Hz behind one worker that the machine descheduled. A camera
  // needs at least its share of buffers in its pool (drivers/: 32 by default).
  int frame_queue_capacity = 128;
  int detection_queue_capacity = 64;  // detections waiting for sync
  int point_queue_capacity = 256;     // point frames waiting for the caller
  // How the rig's cameras are synchronised, which decides what "the same instant" is:
  //  kTrigger      one trigger pulse (a master camera's strobe into the others' trigger line, or
  //                a trigger generator) exposes every camera: sets by trigger count (the frame
  //                ids, reconstruction/frame_sync.h kSequence), checked by timestamps (each
  //                camera's clock fitted against the host: a set whose members' mapped times
  //                spread beyond `trigger_check_tolerance` of a period
  //                is counted, Stats().
  //                mismatched_sets). A camera that comes back after a loss restarts its ids,
  //                and one that starts after the others counts from 1: its ids are put on the
  //                rig's count from its arrival times against the rig's (the trigger whose
  //                arrival time its least-delayed frame of the first ten is nearest), which
  //                holds while that frame's wait stays under half a period (the timestamp check
  //                counts the sets when not).
  //  kSharedClock  the cameras' clocks are one clock (PTP, IEEE 1588, locked; Aravis's fakes
  //                share the host's) and they expose on its ticks at rate_hz: a frame's sequence
  //                is its tick, floor(device timestamp x rate), the same for every camera at one
  //                instant whatever each camera's own count, also after a reconnect.
  //  kFreeRun      no common clock, no trigger: each camera's clock offset and drift against the
  //                host are fitted from its frames' arrival times (reconstruction/clock_fit.h)
  //                and frames are grouped by their time on the host clock, within
  //                `free_run_tolerance` of a period. Sets are only as good as that estimate
  //                (cameras on like links: tens of microseconds) and free-running cameras are
  //                not exposed together at all: an instant's images are up to the tolerance
  //                apart, which a moving marker turns into error. A set's sequence is the rig's
  //                count from the set's time (the previous set's + round(dt x rate)). A camera
  //                back from a loss has its clock fitted afresh (FrameSync::ResyncCamera).
  enum class RigSync : std::uint8_t { kTrigger, kSharedClock, kFreeRun };
  RigSync rig_sync = RigSync::kTrigger;
  // The rig's frame rate: needed by kSharedClock and kFreeRun; kTrigger needs it to place a
  // camera back after a loss and to check sets by timestamps (0: neither).
  double rate_hz = 0;
  // kTrigger with rate_hz, of a frame period (0: no check): a camera one trigger off is a whole
  // period off, and the fits of clocks from arrival times on a loaded host scatter by a
  // millisecond or two (a check at 0.5 ms counted a third of a 100 Hz rig's correct sets).
  double trigger_check_tolerance = 0.25;
  double free_run_tolerance = 0.45;         // kFreeRun: of a frame period, < 0.5
  bool keep_detections = false;  // hand each set's 2D detections out with its points (see also
                                 // CapturePipeline::KeepDetections, switched while running)
  // The recording starts once `start_complete_sets` consecutive sets had every camera (it starts
  // with the last of them), or `start_timeout_ms` after the first set, whichever comes first.
  // false: at the first set.
  bool start_on_complete_set = true;
  int start_complete_sets = 20;
  int start_timeout_ms = 2000;
  // A camera that delivers no frame for this long while another camera delivers is silent
  // (Stats().camera_silent_s; the daemon's status, STATUS= and journal say so). Seconds; 0:
  // max(0.5 s, 20 frame periods at rate_hz). Why not wait for the driver: a GigE Vision camera
  // whose cable is pulled is declared lost by Aravis's control-channel heartbeat only after
  // ~6 s, and its sets are missing from the first period on. The rig knows the frame rate, so
  // the others' frames say when one is overdue: 20 periods is more than the few ticks a camera
  // (or a fake's thread on a loaded host) skips when descheduled, and 0.5 s more than a
  // grab or stream thread waits for the CPU on a loaded 2-core capture PC. Requiring another
  // camera to deliver keeps a rig that stops as a whole (trigger off, every cable) from
  // reading as each camera being silent: that is the watchdog's and the cameras' state.
  double camera_silence_s = 0;
  reconstruction::DetectionOptions detection;
  reconstruction::FrameSyncOptions sync;  // num_cameras is set from the sources
  // Test hook: called by each grab thread before each grab (stage "grab") and by each detection
  // worker before each frame (stage "detection"), and by the live pipeline's tracking thread
  // before each point frame (stage "track"); a test holds a stage by blocking in it (the
  // daemon's watchdog must then stop its pings). Empty: not called. mocapd sets it only when
  // built with MOCAP_TEST_HOOKS (daemon/mocapd_main.cpp).
  std::function<void(const char* stage)> test_hold;

  bool IsValid(std::string* error) const;
};

// Per-stage figures. Timings in milliseconds; percentiles over the last kTimingSamples samples
// of each (about 40 s of detection at 8 cameras x 200 Hz).
struct CapturePipelineStats {
  std::uint64_t frames_grabbed = 0;
  std::uint64_t frames_incomplete = 0;   // buffers the cameras counted as incomplete
  std::uint64_t frames_dropped = 0;      // the detection queue was full
  std::uint64_t frames_detected = 0;     // images through detection (errors included)
  std::uint64_t detection_errors = 0;
  std::uint64_t sync_errors = 0;         // detections the sync refused (camera index, ...)
  std::uint64_t detections_dropped = 0;  // the sync queue was full
  std::uint64_t frame_sets = 0;          // point frames handed to the caller
  std::uint64_t incomplete_sets = 0;     // ... of which with a camera missing
  // Sets that never came out although a camera delivered a frame of theirs to the daemon (it
  // was dropped at a full queue, arrived too late for its set), or whose point frame found the
  // output queue full: the daemon's losses. kFreeRun (no common numbering): every sequence gap.
  std::uint64_t dropped_frame_sets = 0;
  // Sequence gaps that no camera delivered any frame of, and during which no camera's buffers
  // underran (a frame lost in the driver for want of a buffer the daemon held is the daemon's:
  // such gaps count as dropped): not exposed, or lost in transport. A simulated camera running in the
  // daemon's own process skips the ticks during which the host did not schedule it, as hardware,
  // exposing on its own clock, would not. kTrigger and kSharedClock.
  std::uint64_t undelivered_frame_sets = 0;
  std::uint64_t late_frames = 0;
  std::uint64_t triangulation_errors = 0;
  // Start-up (see the header): sets before the recording began, not handed out; whether it has
  // begun, how long after the first set, and which cameras were missing from its first set.
  std::uint64_t warmup_sets = 0;
  bool recording = false;
  double warmup_ms = 0;
  std::vector<int> cameras_missing_at_start;
  std::vector<std::uint64_t> camera_losses;  // per camera
  // Synchronisation (CapturePipelineOptions::rig_sync). Per camera: returns after a loss that
  // the sync re-synchronised, and the clock's offset against the rig's common time (ms) and its
  // drift against the host clock (ppm; 0 where not fitted: kSharedClock, or kTrigger without a
  // check). mismatched_sets: kTrigger sets whose timestamps disagreed.
  std::vector<std::uint64_t> camera_resyncs;
  std::vector<double> camera_clock_offset_ms, camera_clock_drift_ppm;
  // ... the clock fit's residual (reconstruction/clock_fit.h residual_ns, in us) and whether its
  // drift is fitted yet (the rig check judges a fit only once it is).
  std::vector<double> camera_clock_residual_us;
  std::vector<bool> camera_clock_fitted;
  // Per camera, its frame count against its own timestamps: frames whose id advanced by another
  // number of frames than their timestamp did (round(dt x rate_hz)) since the camera's previous
  // frame. With a hardware trigger that is a trigger the camera counted and did not expose, or
  // exposed and did not count: its frames are then on the wrong sets (the rig check fails it).
  // Frames lost in transport advance both alike and are not counted here.
  std::vector<std::uint64_t> camera_count_mismatches;
  // kSharedClock, per camera: where within the common clock's tick its recent frames are
  // stamped, in periods [0, 1) (the circular mean of frac(timestamp x rate_hz), each frame
  // weighing 1/50, so about the last 50 frames count); -1 before its first frame. The cameras of
  // a rig exposing on the ticks agree (PTP-scheduled: 0.5, drivers/aravis_camera.h); one that
  // does not free-runs at its own phase, and its images join sets of another instant's
  // (daemon/rig_check.h judges it).
  std::vector<double> camera_tick_phase;
  // Per camera, seconds since its last frame while it is silent (CapturePipelineOptions::
  // camera_silence_s: no frame for that long while another camera delivered within it); 0 while
  // it is not. Measured at the Stats() call.
  std::vector<double> camera_silent_s;
  std::uint64_t mismatched_sets = 0;
  // The queues between the stages (daemon/bounded_queue.h): frames waiting for detection (the
  // fullest worker's queue; capacity per worker), detections waiting for the sync, point frames
  // waiting for the caller.
  QueueDepth frame_queue, detection_queue, point_queue;
  double detect_ms_p50 = 0, detect_ms_p99 = 0;
  double triangulate_ms_p50 = 0, triangulate_ms_p99 = 0;
  double latency_ms_p50 = 0, latency_ms_p99 = 0;
};

class CapturePipeline {
 public:
  CapturePipeline(std::vector<std::unique_ptr<drivers::CameraSource>> cameras,
                  TriangulateFn triangulate, CapturePipelineOptions options = {});
  ~CapturePipeline();
  CapturePipeline(const CapturePipeline&) = delete;
  CapturePipeline& operator=(const CapturePipeline&) = delete;

  // Starts the stages and the cameras (which must be open). Fails, with nothing left running,
  // on invalid options or a camera that does not start.
  Status Start();
  // Stops the cameras, drains every queue, joins every thread. Idempotent.
  void Stop();
  // The next point frame, waiting up to timeout_ms. False on timeout or once stopped and empty.
  bool PopPoints(PointFrame* out, int timeout_ms);
  // Point frames waiting for the caller now.
  std::size_t PointsWaiting() const { return points_.Depth().depth; }
  // Figures so far (timing percentiles over the recent samples). The percentiles sort up to
  // 65,536 samples each (milliseconds of CPU): callers that poll often pass timings = false.
  CapturePipelineStats Stats(bool timings = true) const;
  // Hands the 2D detections out from the next set on, or stops (as options.keep_detections, but
  // while running: the daemon needs them only while it collects wand frames, and copying every
  // camera's centroids for every set otherwise is per-frame work for nothing).
  void KeepDetections(bool keep) { keep_detections_.store(keep); }
  drivers::CameraSource& camera(int c) { return *cameras_[c]; }
  int num_cameras() const { return static_cast<int>(cameras_.size()); }

 private:
  void GrabLoop(int camera);
  void DetectLoop(int worker);
  // camera_tick_phase's update by one frame of `camera` (under stats_mutex_).
  void AddTickPhase(std::size_t camera, const drivers::Frame& frame);
  void SyncLoop();
  void EmitSet(reconstruction::DetectionSet& set);
  // kFreeRun: the set's sequence from its time (see RigSync).
  void NumberByTime(reconstruction::DetectionSet* set);
  // Whether `set` belongs to the recording (start-up, see the header); counts warm-up sets.
  bool Recording(const reconstruction::DetectionSet& set);

  std::vector<std::unique_ptr<drivers::CameraSource>> cameras_;
  TriangulateFn triangulate_;
  CapturePipelineOptions options_;

  // One per detection worker; camera c's frames go to frames_[c % workers].
  std::vector<std::unique_ptr<BoundedQueue<drivers::Frame>>> frames_;
  BoundedQueue<reconstruction::CameraDetections> detections_;
  BoundedQueue<PointFrame> points_;

  std::atomic<bool> grabbing_{false};
  std::atomic<bool> keep_detections_{false};
  std::vector<std::thread> grab_threads_, detect_threads_;
  std::thread sync_thread_;
  bool started_ = false;

  reconstruction::FrameSync sync_;  // the sync thread's

  mutable std::mutex stats_mutex_;
  CapturePipelineStats stats_;
  // kTrigger, under stats_mutex_: the rig's trigger count against the host clock (a ClockFit of
  // the arrival times of every placed camera's frames against sequence x period) and its newest
  // trigger, where a camera that returns or starts late finds the count.
  static constexpr int kPlacementFrames = 10;
  reconstruction::ClockFit rig_clock_;
  std::uint64_t rig_newest_sequence_ = 0;
  static constexpr std::size_t kTimingSamples = 1 << 16;
  RecentSamples detect_ms_{kTimingSamples}, triangulate_ms_{kTimingSamples},
      latency_ms_{kTimingSamples};
  bool any_emitted_ = false;
  std::uint64_t last_emitted_sequence_ = 0;
  // The sync's sequence of every frame a camera delivered (grab threads write, the sync reads),
  // slot = sequence modulo the ring: a sequence gap at the sync is the daemon's loss only if some
  // camera delivered that sequence (dropped_frame_sets / undelivered_frame_sets). 4096 frames
  // (20 s at 200 Hz) is far beyond the sync's window; a divisor of 2^16, so 16-bit ids agree.
  static constexpr std::size_t kDeliveredRing = 4096;
  std::unique_ptr<std::atomic<std::uint64_t>[]> delivered_;
  // Per slot, the cameras' buffer underruns (summed) when that sequence was delivered: a gap
  // between two delivered sequences with underruns between them may be the daemon's doing.
  std::unique_ptr<std::atomic<std::uint64_t>[]> delivered_underruns_;
  std::uint64_t CameraUnderruns() const;
  std::uint64_t SyncSequence(const drivers::Frame& frame) const;
  bool Delivered(std::uint64_t sequence) const;
  // The sync thread's: the stream epoch each camera's detections last had; kFreeRun numbering.
  std::vector<std::uint32_t> sync_epoch_;
  std::vector<double> tick_phase_cos_, tick_phase_sin_;  // camera_tick_phase's running means
  // Under stats_mutex_: per camera, when its last frame was handed over, or when it was last
  // seen lost (Stats() too: hence mutable), from Start() plus the start-up's timeout.
  mutable std::vector<std::uint64_t> last_frame_ns_;
  bool numbered_any_ = false;
  std::uint64_t numbered_sequence_ = 0, numbered_time_ns_ = 0;
  std::uint64_t first_set_host_ns_ = 0;  // the sync thread's: when the first set came out
  int complete_run_ = 0;                  // consecutive complete sets before the recording
};

}  // namespace mocap::daemon
