// Frame-set sync: groups the per-camera detections of one instant into a DetectionSet.
//
// Two ways to say "the same instant":
//
//  * kSequence: by frame id. With a hardware trigger and acquisition started together, every
//    camera numbers the same trigger pulse alike. Device ids wrap (16 bit on GigE Vision), and each
//    source unwraps its own ids, so two sources that started on either side of a wrap disagree on
//    the unwrapped value by 65,536. The sync therefore keeps only the low `sequence_bits` bits of
//    CameraDetections::sequence and unwraps them itself, once for the whole rig, against the
//    newest id seen: id = newest + (low - newest) taken modulo 2^bits into [-2^(bits-1), 2^(bits-1)).
//    Cameras whose counters were NOT reset together are not handled by this mode (use kTimestamp).
//
//  * kTimestamp: by device timestamp. Camera clocks are not one clock: each camera c has its
//    own epoch and rate (free-running cameras: offsets of seconds, drifts of tens of ppm), and
//    both are estimated, not assumed: a ClockFit per camera (reconstruction/clock_fit.h) fits
//    the lower envelope of its frames' host arrival times against their device timestamps (the
//    host clock is common to all cameras and the transport only ever adds latency), and a
//    frame's corrected time is its device time mapped onto the host clock,
//    t = ToHost(device). The cameras' corrected times agree to within the difference of their
//    best latencies (which must stay below the tolerance: cameras on like links). A frame joins
//    the pending set whose reference time (the running mean of its members' t) is within
//    `tolerance_ns` of its own t. With PTP-synchronised cameras (GigE Vision 2.0), set
//    estimate_offsets = false and give the known offsets (or none: zeros). A set's sequence is
//    then the sequence of its lowest-numbered present camera, and its timestamp_ns the median
//    of its members' corrected times (the rig's common timeline: the host clock, offset by the
//    fastest delivery latency).
//
//  * Timestamp check in kSequence mode (check_tolerance_ns > 0): a hardware-triggered rig groups
//    by trigger count, and a camera that missed a trigger without noticing (or came back from a
//    reconnect on the wrong count) would be silently one frame off. The same per-camera clock
//    fits map each frame onto the host clock, and a set whose members' corrected times spread
//    beyond the tolerance is counted (counters.mismatched). Cameras whose fit has no drift yet
//    (the first frames after a start or a ResyncCamera) are not checked.
//
// Emission, in order of sequence (or time): a set is emitted as soon as every camera has
// contributed (complete). A pending set older than one that completes is emitted first, as
// INCOMPLETE (cameras deliver their own frames in order, so a camera that already delivered a
// later frame will not deliver this one). A set is also emitted incomplete when it is the oldest
// and the window holds more than `max_pending_sets`, or when `timeout_ns` of host time passed
// since its first image arrived (checked on every Add, with the arriving frame's host time, and
// on Poll). An incomplete set has present[c] = false and an empty CameraDetections for each
// missing camera. A frame for a set already emitted (or older) is LATE: counted and dropped. A
// second frame of the same camera for the same pending set is a DUPLICATE: counted and dropped
// (the first is kept).
//
// Memory is bounded: at most max_pending_sets sets are held. Threading: NOT thread-safe; the
// pipeline funnels every camera's detections through one queue into one sync thread.
#pragma once
#include <cstdint>
#include <string>
#include <vector>

#include "model/status.h"
#include "reconstruction/centroid.h"
#include "reconstruction/clock_fit.h"

namespace mocap::reconstruction {

struct FrameSyncOptions {
  enum class Mode { kSequence, kTimestamp };

  int num_cameras = 0;
  Mode mode = Mode::kSequence;
  // kSequence: how many low bits of the frame sequence are meaningful (16 for GigE Vision block
  // ids; 64 when the sources' sequences are already consistent across the rig).
  int sequence_bits = 16;
  // Window: pending (not yet emitted) sets held at most.
  int max_pending_sets = 8;
  // Host time after the first image of a set arrived at which it is emitted incomplete
  // (0: never; the window and later complete sets still emit it).
  std::uint64_t timeout_ns = 100'000'000;

  // kTimestamp: frames of one set lie within this of the set's reference time; keep it below half
  // the frame period.
  std::uint64_t tolerance_ns = 1'000'000;
  bool estimate_offsets = true;
  ClockFitOptions clock;  // the per-camera fits (kTimestamp estimating; kSequence checking)
  // Known per-camera clock offsets (device - common time), used as given when estimate_offsets is
  // false; empty means zeros. Ignored when estimating.
  std::vector<std::int64_t> camera_offsets_ns;
  // kSequence: > 0 checks each set's corrected times against this spread (see above).
  std::uint64_t check_tolerance_ns = 0;

  bool IsValid(std::string* error) const;
};

struct FrameSyncCounters {
  std::uint64_t frames = 0;      // detections offered to Add
  std::uint64_t complete = 0;    // sets emitted with every camera
  std::uint64_t incomplete = 0;  // sets emitted with a camera missing
  std::uint64_t late = 0;        // frames for a set already emitted, dropped
  std::uint64_t duplicate = 0;   // second frame of a camera for the same set, dropped
  std::uint64_t mismatched = 0;  // kSequence with a check: sets whose times spread too far
  std::vector<std::uint64_t> missing;  // per camera: emitted sets without it
};

class FrameSync {
 public:
  FrameSync() = default;
  // Validates the options and starts empty (counters zeroed). Must succeed before Add.
  Status Reset(const FrameSyncOptions& options);

  // Takes one camera's detections; appends to `ready` every set this completes or releases, in
  // order. Errors: not Reset, camera index outside the rig, null `ready`.
  Status Add(CameraDetections detections, std::vector<DetectionSet>* ready);
  // Emits the sets whose timeout has passed at host time `host_now_ns`.
  void Poll(std::uint64_t host_now_ns, std::vector<DetectionSet>* ready);
  // Emits every pending set (at the end of a recording).
  void Flush(std::vector<DetectionSet>* ready);
  // A camera came back (unplugged and reconnected, restarted): its clock and its frame ids
  // started again. kTimestamp: its clock is fitted afresh from its next frames. kSequence with
  // a timestamp check: the check's fit is restarted (the caller must have put the camera's new
  // ids back on the rig's count, as CapturePipeline does from the time it was away). kSequence
  // without a check: an error, as the new ids cannot be placed against the rig's here.
  Status ResyncCamera(int camera);

  const FrameSyncCounters& counters() const { return counters_; }
  int pending() const { return static_cast<int>(pending_.size()); }
  // The current clock offset of camera c (device - common time), in ns, and its drift against
  // the host clock (ppm; 0 until fitted): kTimestamp, or kSequence with a check.
  std::int64_t offset_ns(int camera) const;
  double drift_ppm(int camera) const;
  // Camera c's clock fit: its residual (ClockFit::residual_ns, 0 until fitted) and whether its
  // drift is fitted yet (false where no clocks are fitted).
  double clock_residual_ns(int camera) const;
  bool clock_fitted(int camera) const;

 private:
  struct Pending {
    std::int64_t key = 0;  // kSequence: rig-unwrapped id; kTimestamp: reference time (running mean)
    int count = 0;
    std::vector<std::int64_t> times;  // corrected (kTimestamp) or device time per camera
    DetectionSet set;
  };

  std::int64_t UnwrapSequence(std::uint64_t sequence);
  void EmitFront(std::vector<DetectionSet>* ready);
  void EmitTimedOut(std::uint64_t host_now_ns, std::vector<DetectionSet>* ready);

  bool initialised_ = false;
  FrameSyncOptions options_;
  FrameSyncCounters counters_;
  std::vector<Pending> pending_;  // sorted by key, oldest first
  bool emitted_any_ = false;
  std::int64_t last_emitted_key_ = 0;
  bool seen_any_ = false;
  std::int64_t newest_key_ = 0;
  bool Fitting() const;
  std::vector<std::int64_t> offsets_;  // given offsets (estimate_offsets = false)
  std::vector<ClockFit> fits_;
  std::vector<std::int64_t> scratch_;
};

}  // namespace mocap::reconstruction
