// The Aravis backend: one GenICam camera (GigE Vision, USB3 Vision, or one of Aravis's own fake
// devices) as a CameraSource.
//
// Why it is shaped this way:
//   - Pool. Open() allocates `buffer_count` image buffers once, in memory this object owns, and
//     wraps each in an ArvBuffer pushed to the stream. Grab() pops a filled buffer, Release()
//     pushes it back: no allocation per frame. The memory outlives streams, so a reopen after a
//     loss re-wraps the same blocks (a buffer the caller still holds is re-wrapped only when it
//     is released, so its pixels are never overwritten under the reader).
//   - Only complete frames reach the caller. Every buffer whose Aravis status is not SUCCESS, or
//     whose geometry or pixel format differs from what was configured, is counted in
//     CameraCounters and pushed straight back (GrabResult::kIncomplete); its pixels are never
//     read. Aravis's fake path reports a data size of 0, so the expected size is
//     width x height x bytes per pixel, and a non-zero reported size must cover it.
//   - Frame ids. GigE Vision 1.x block ids are 16 bit; USB3 Vision ids are 64 bit, of which the
//     low 16 bits are kept: Frame::frame_id is always 16 bit and Frame::sequence its unwrapped,
//     monotonic extension (FrameIdUnwrapper), whose low 16 bits ARE the id — frame sync
//     (reconstruction/frame_sync.h) relies on that to line up cameras that started on either
//     side of a wrap. GigE Vision 1.x never uses id 0 (nor do the fakes: 65535 is followed by 1),
//     so there the sequence skips one value per wrap (65535 -> 65537). After a reopen the device
//     restarts its ids; the sequence continues from the last one delivered (sync must then
//     re-align this camera, e.g. FrameSync::ResyncCamera on timestamps).
//   - Loss. Aravis emits `control-lost` from its heartbeat thread (GigE: some seconds after the
//     camera stops answering). The handler only sets a flag; the acquisition thread, in Grab(),
//     marks the camera lost (State() == kLost, counters.losses), drops the stream and the device
//     without talking to them, and from then on tries to reopen every `reopen_interval_ms`
//     (GigE has no arrival event) or at once after NotifyArrived() (USB hot-plug,
//     drivers/usb_hotplug.h). NotifyRemoved() is the same loss, reported by hot-plug. A loss
//     touches only this camera: the other cameras' threads go on.
//   - Exposure schedule (sync = "ptp"). PTP makes the cameras' clocks one clock; it does not
//     make them expose together: a free-running camera exposes at the phase its acquisition
//     started at, anywhere within a period of the others. The pipeline groups frames by the
//     common clock's tick, floor(timestamp x rate) (daemon/capture_pipeline.h kSharedClock), so
//     the exposures must be put on the ticks. Two GenICam ways exist: Basler's Synchronous Free
//     Run (a timer on the PTP clock that fires at SyncFreeRunTimerStartTime + n /
//     SyncFreeRunTimerTriggerRateAbs) and SFNC's scheduled action commands (a host sends
//     "expose at time t" to every camera). Aravis 0.8 has no action-command API (its pull request
//     #468 was never merged), so the backend uses Synchronous Free Run: rate = the frame rate,
//     start time = HALF a period (in ticks of the camera's timestamp clock,
//     GevTimestampTickFrequency, 1 GHz where the camera has no such feature), then
//     SyncFreeRunTimerUpdate, then SyncFreeRunTimerEnable, each read back. Why half a period:
//     cameras exposing exactly on the tick would stamp times a few nanoseconds either side of
//     it, and floor() would split one instant over two sets; mid-tick, the grouping has half a
//     period of margin on both sides. A camera without these features (or refusing one) is an
//     error naming camera and feature unless SyncFreeRunTimerEnable (or the refused feature) is
//     optional; such a camera free-runs at its own phase and the rig check names it
//     (daemon/rig_check.h, "tick phase"). A camera that joins late or comes back after a loss
//     is scheduled by the same Open/Reopen path, on the same ticks.
//   - Devices are made by a factory, so a reopen makes a fresh one: by default
//     arv_camera_new(id); the fake rig (drivers/aravis_fake.h) passes one that builds an
//     ArvFakeDevice with our image generator.
//
// Threading: Open/Start/Stop/Grab/Reopen from the camera's acquisition thread; Release may come
// from another thread (it takes a short lock); Counters/State/NotifyRemoved/NotifyArrived from
// any thread.
//
// Usage:
//   drivers::AravisCamera cam("Basler-acA1300-21812345");   // or AravisCamera::FromSerial(...)
//   drivers::CameraSettings s;  s.frame_rate_hz = 200;  s.exposure_us = 400;
//   if (Status st = cam.Open(s); !st.ok()) ...;             // names the setting and its bounds
//   cam.Start();
//   drivers::Frame f;
//   while (running) {
//     if (cam.Grab(&f) == drivers::GrabResult::kFrame) { Detect(f.image); cam.Release(f); }
//   }
#pragma once
#include <atomic>
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "drivers/camera_source.h"

typedef struct _ArvCamera ArvCamera;
typedef struct _ArvStream ArvStream;
typedef struct _ArvBuffer ArvBuffer;
typedef struct _ArvDevice ArvDevice;

namespace mocap::drivers {

struct AravisCameraOptions {
  int camera_index = -1;            // Frame::camera
  // GigE Vision: receive with ordinary sockets instead of Aravis's packet socket (needed without
  // CAP_NET_RAW; a device on the loopback interface, the GigE fake, always gets them).
  bool disable_packet_socket = false;
  // GigE Vision: size the socket receive buffer to one payload (Aravis's "auto"), which avoids
  // most missing-packet frames on a busy host.
  bool auto_socket_buffer = true;
  bool auto_reopen = true;          // Grab() retries a lost camera by itself
  int reopen_interval_ms = 500;

  bool IsValid(std::string* error) const;
};

// Builds a fresh ArvCamera (for the first open and every reopen). Returns nullptr and sets
// *error (a message naming the device) when the device is not there.
using ArvCameraFactory = std::function<ArvCamera*(std::string* error)>;

// What the device accepted after Open(), read back from it.
struct AppliedSettings {
  double exposure_us = 0, gain_db = 0, frame_rate_hz = 0;
  int roi_x = 0, roi_y = 0, width = 0, height = 0;
  PixelFormat pixel_format = PixelFormat::kMono8;
  std::string trigger_source;  // "" for free run, else "Software" / "Line<n>"
  std::size_t payload_bytes = 0;
  // "Off" as read back, or "" where the camera has no such feature (manual anyway).
  std::string exposure_auto, gain_auto;
  std::string strobe_source;   // LineSource read back for Line<strobe_line>, "" without strobe
  bool ptp_enabled = false;
  // The exposure schedule on the PTP clock (CameraSettings::ptp_schedule), read back:
  // "sync-free-run" once SyncFreeRunTimerEnable reads true, "" where none was applied; its rate
  // and its start time in ticks of the camera's timestamp clock.
  std::string ptp_schedule;
  double schedule_rate_hz = 0;
  std::int64_t schedule_start_ticks = 0;
  // GigE Vision, read back (0 / false elsewhere).
  int packet_size = 0;
  std::int64_t packet_delay_ns = 0;
  bool packet_resend = false;
  int socket_buffer_bytes = 0;
  // USB3 Vision, as applied (applied.applied false elsewhere).
  AppliedUsbTransfer usb;
  // Optional features the camera refused: "feature: why".
  std::vector<std::string> refused_optional;
};

// A camera's IEEE 1588 state as it reports it.
struct PtpState {
  std::string status;          // PtpStatus / GevIEEE1588Status: "Master", "Slave", "Listening"...
  bool has_offset = false;
  std::int64_t offset_from_master_ns = 0;
};
// Whether a rig's cameras are locked to one clock: every camera "Slave" (to one master outside
// the rig or on it) and at most one "Master". Otherwise false and *why names the cameras that
// are not (ids[i] is states[i]'s camera).
bool PtpLocked(const std::vector<std::string>& ids, const std::vector<PtpState>& states,
               std::string* why);

class AravisCamera final : public CameraSource {
 public:
  // By Aravis device id (arv_camera_new's name: "<vendor>-<model>-<serial>", "Aravis-<serial>"
  // for the GigE fake, or an IP address).
  explicit AravisCamera(std::string device_id, AravisCameraOptions options = {});
  // With a factory (fake devices); `id` names the camera in messages.
  AravisCamera(std::string id, ArvCameraFactory factory, AravisCameraOptions options = {});
  // Adopts an already created camera (a reference is taken); it is used for the first Open().
  // Without a factory a lost camera cannot be reopened.
  AravisCamera(std::string id, ArvCamera* camera, ArvCameraFactory factory = nullptr,
               AravisCameraOptions options = {});
  ~AravisCamera() override;
  AravisCamera(const AravisCamera&) = delete;
  AravisCamera& operator=(const AravisCamera&) = delete;

  // Looks the serial number up among the connected devices (arv_update_device_list).
  static Status FromSerial(const std::string& serial, AravisCameraOptions options,
                           std::unique_ptr<AravisCamera>* camera);

  const std::string& id() const override { return id_; }
  Status Open(const CameraSettings& settings) override;
  Status Start() override;
  void Stop() override;
  GrabResult Grab(Frame* frame) override;
  void Release(const Frame& frame) override;
  Status Trigger() override;
  CameraState State() const override { return state_.load(); }
  const CameraCounters& Counters() const override { return counters_; }

  const AppliedSettings& Applied() const { return applied_; }
  // IEEE 1588 state (latched, then read: PtpDataSetLatch / GevIEEE1588DataSetLatch where the
  // camera has it). Error if PTP is not on (CameraSettings::ptp) or the camera is not open (or
  // lost). Any thread: the rig's PTP monitor (daemon/ptp_monitor.h) reads it while streaming.
  Status Ptp(PtpState* state);
  // GigE Vision stream statistics: packets Aravis found missing and asked to be resent. Any
  // thread. PacketStatistics: false (and nothing set) where the stream is not GigE Vision's
  // (USB3 Vision, the in-process fakes) or there is none (lost).
  std::uint64_t MissingPackets() const;
  std::uint64_t ResentPackets() const;
  bool PacketStatistics(std::uint64_t* resent, std::uint64_t* missing) const;
  // Hot-plug: the device left (same as control-lost) / arrived (reopen at the next Grab).
  void NotifyRemoved() { lost_flag_.store(true); }
  void NotifyArrived() { arrived_flag_.store(true); }
  // Tries once to reopen a lost camera with the settings of the last Open(); Ok if streaming.
  Status Reopen();
  // A configured camera that Open() could not open at start (its device absent, or it refused a
  // setting): it is kept as a lost camera with these settings, so Start() arms it and Grab()
  // opens it when it can, every reopen_interval_ms or at NotifyArrived(), as after a loss. A
  // rig therefore starts degraded instead of refusing to start (daemon/rig_setup.h
  // OpenRigCameras). `why` (Open()'s error) is LastError() until it opens.
  void AwaitDevice(const CameraSettings& settings, std::string why);
  // After a failed Open(): whether the device answered (and refused a setting or the stream)
  // rather than being absent.
  bool DeviceFoundAtOpen() const { return device_found_at_open_; }
  // Still awaiting its device after AwaitDevice() (never opened since). Any thread.
  bool AwaitingDevice() const { return awaiting_device_.load(); }
  // Why the camera is not streaming: the last failed open or reopen ("" if none failed).
  std::string LastError() const override;
  // The sequence the next delivered frame gets after a reopen (last delivered + 1), or 0 if
  // none was delivered yet. The fake rig's factory reads it (from the reopening thread) so the
  // images it draws are numbered like the frames the caller receives.
  std::uint64_t ResumeSequence() const { return delivered_any_ ? last_sequence_ + 1 : 0; }

 private:
  struct Slot {
    std::unique_ptr<std::uint8_t[]> memory;
    ArvBuffer* buffer = nullptr;  // wraps memory for the current stream generation
    int generation = -1;
    bool outstanding = false;     // held by the caller
    std::unique_ptr<std::uint16_t[]> unpacked;  // Mono12Packed: the frame handed out
  };
  static void OnControlLost(ArvDevice* device, void* self);

  Status Connect();              // factory -> camera_, apply settings
  Status ApplySettings();
  Status ApplyCameraFeatures();  // auto off, strobe, PTP, GigE packet size and delay
  Status ApplySyncFreeRun();     // the exposure schedule on the PTP clock (see the header)
  // A feature the camera refused: an error naming camera and feature, unless it is optional.
  Status Refused(const std::string& feature, const std::string& why);
  Status CreateStreamAndPool();  // stream_, slots wrapped and pushed
  void TearDown(bool device_gone);
  void MarkLost();
  // After Open() or AwaitDevice(): configured, not acquiring, a new frame-id sequence; kLost
  // (opened when the device appears) when awaiting it, else kClosed.
  void StartFreshStream(bool awaiting_device);
  GrabResult Classify(ArvBuffer* buffer, Frame* frame, Slot** slot);
  std::uint64_t StreamUnderruns() const;

  std::string id_;
  ArvCameraFactory factory_;
  AravisCameraOptions options_;
  CameraSettings settings_;
  AppliedSettings applied_;
  mutable std::mutex error_mutex_;  // last_error_: set by the grab thread, read by any
  std::string last_error_;

  ArvCamera* camera_ = nullptr;
  ArvStream* stream_ = nullptr;
  unsigned long control_lost_handler_ = 0;
  // Written by Start/Stop (the pipeline's thread) and read by Grab on the grab thread, which
  // holds no lock there: atomic (TSan, scripts/tsan_daemon.sh, saw Stop race with Grab).
  std::atomic<bool> acquiring_{false};
  bool opened_ = false;
  std::atomic<bool> awaiting_device_{false};  // AwaitDevice(): never opened yet
  bool device_found_at_open_ = false;

  // camera_ (and talking to it) between the acquisition thread (Open, Reopen, Start, Stop) and
  // Ptp() from a monitoring thread: GenICam access to one device is not thread-safe.
  mutable std::mutex device_mutex_;
  mutable std::mutex pool_mutex_;  // slots_ and stream_ against Release from another thread
  std::vector<Slot> slots_;
  std::size_t slot_bytes_ = 0;
  int generation_ = 0;

  FrameIdUnwrapper unwrapper_;
  std::uint64_t sequence_offset_ = 0;
  std::uint64_t last_sequence_ = 0;
  bool delivered_any_ = false;
  bool resume_sequence_ = false;
  // CameraCounters::not_received: the frame ids skipped between two delivered frames of one
  // stream, less those of the buffers in between that did arrive (incomplete, underruns).
  // Aravis counts none of these (0.8.26: its n_missing_frames stayed 0 while a GigE fake's
  // receive buffer lost half the frames whole).
  bool id_gap_reference_ = false;  // a delivered frame of this stream to measure from
  std::uint64_t id_gap_last_raw_ = 0;
  std::uint64_t undelivered_since_ = 0;  // buffers popped and not delivered since it
  std::uint64_t underruns_at_ = 0;       // counters_.underruns at it

  std::atomic<CameraState> state_{CameraState::kClosed};
  std::atomic<bool> lost_flag_{false};
  std::atomic<bool> arrived_flag_{false};
  std::chrono::steady_clock::time_point last_reopen_attempt_{};
  std::uint64_t underrun_base_ = 0;  // Aravis's underruns of the streams before this one
  CameraCounters counters_;
};

// The pixel format as Aravis names it (ARV_PIXEL_FORMAT_MONO_8, ...), and back (false for
// formats the pipeline does not take).
std::uint32_t ToArvPixelFormat(PixelFormat format);
bool FromArvPixelFormat(std::uint32_t arv_format, PixelFormat* format);

}  // namespace mocap::drivers
