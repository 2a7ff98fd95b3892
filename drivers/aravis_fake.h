// Simulated cameras behind the REAL Aravis API, so tests and `mocap capture --sim` run the
// Aravis backend (drivers/aravis_camera.h) unchanged:
//   - AravisFakeRig: N in-process fake cameras (arv_fake_device_new + arv_camera_new_with_device),
//     each drawing its images with our ImageGenerator through the fake camera's fill-pattern
//     hook. No network, any number of cameras. A camera can be made absent (SetPresent(i,
//     false)): its device is refused until it is present again, which is how a USB removal is
//     simulated together with the hot-plug test hook (drivers/usb_hotplug.h).
//   - GvFakeCamera: Aravis's GigE Vision fake (arv_gv_fake_camera_new) on 127.0.0.1, opened as
//     "Aravis-<serial>" over real GVCP/GVSP sockets: software trigger, packet loss
//     (SetPacketLossRatio, the `gvsp-lost-ratio` property) and device loss (Destroy(): the
//     heartbeat fails and Aravis emits control-lost; Create() again brings it back). One per IP
//     address, so one per process on loopback.
//
// The fill hook gets the buffer's geometry and pixel format; Aravis's fake reports a data size of
// 0 there, so the image size is width x height x bytes per pixel. The generator's `sequence` is
// the fake's 16-bit frame id unwrapped as AravisCamera does (the fakes count 65401, ..., 65535,
// 1, ...: they wrap within the first 135 frames, and the sequence goes 65535 -> 65537), continued across a re-created device: for the rig's cameras at
// the sequence the AravisCamera resumes with (AravisCamera::ResumeSequence), so the renderer's
// truth for (camera, frame.sequence) stays the image the caller got, also after a reopen.
//
// Usage (the lead's `mocap capture`, with the renderer of sim/renderer.h):
//   render_options.sequence_origin = drivers::kAravisFakeFirstFrameId;  // scene time 0 first
//   sim::Renderer renderer(rig, scene, render_options);
//   drivers::FakeRigOptions fo;  fo.cameras = rig.size();  fo.width = 1280;  fo.height = 1024;
//   drivers::AravisFakeRig fakes(fo, renderer.Generator());
//   std::vector<std::unique_ptr<drivers::AravisCamera>> cams;
//   for (int i = 0; i < fakes.size(); ++i) cams.push_back(fakes.MakeCamera(i));
//   for (auto& c : cams) { c->Open(settings); c->Start(); }   // then Grab() per camera thread
#pragma once
#include <atomic>
#include <cstdint>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "drivers/aravis_camera.h"
#include "drivers/camera_source.h"

typedef struct _ArvFakeCamera ArvFakeCamera;
typedef struct _ArvGvFakeCamera ArvGvFakeCamera;

namespace mocap::drivers {

// The first frame id (and so the first sequence) of Aravis 0.8's fake cameras: they start near
// the end of the 16-bit range so that every test sees the wrap. A renderer that should start at
// the beginning of its scene uses it as RendererOptions::sequence_origin.
constexpr std::uint64_t kAravisFakeFirstFrameId = 65401;

struct FakeRigOptions {
  int cameras = 8;
  std::string serial_prefix = "MOCAPSIM";  // serials <prefix><index>, e.g. MOCAPSIM0
  int width = 1280;                          // the sensor (the fake's default is 2048 x 2048)
  int height = 1024;
  // > 0: the generator's `sequence` is the index of the frame-period tick the image was taken
  // at, floor(device timestamp x rate), instead of the camera's own frame count. Aravis's fakes
  // wake on the same ticks of the host's real-time clock (a multiple of the frame period), so
  // this makes N fakes behave as a hardware-synchronised rig: images with the same tick show the
  // same instant, whenever each camera was started. Sync the rig by timestamp in that mode, and
  // find an image's tick from Frame::device_timestamp_ns (SequenceOfTimestamp). Set it to the
  // cameras' frame rate.
  double clock_sequence_rate_hz = 0;
  // PTP cameras: the fakes' GenICam gains SFNC's PtpEnable, PtpStatus, PtpOffsetFromMaster,
  // PtpDataSetLatch and Basler's Synchronous Free Run (SyncFreeRunTimerTriggerRateAbs,
  // SyncFreeRunTimerStartTimeLow/High, SyncFreeRunTimerUpdate, SyncFreeRunTimerEnable), backed
  // by registers of the fake (Aravis's own XML, extended; without this they are absent). With
  // clock_sequence_rate_hz > 0, a fake then exposes as a PTP camera does, by what was written to
  // those registers, on tick k (the period its image is drawn for):
  //   - scheduled (PtpEnable and SyncFreeRunTimerEnable on, SyncFreeRunTimerUpdate executed with
  //     the frame rate): at k x period + the start time (ns) modulo the period: on the master's
  //     ticks, whatever its own clock;
  //   - not: at k x period + its own clock's offset (clock_offsets_ns) modulo the period, the
  //     phase its own timer runs at;
  // stamped with that instant on the master's clock (the host's) while PtpEnable is on, else on
  // its own clock (+ its offset). PtpStatus reads "Disabled" while PtpEnable is off, else the
  // state SetPtpState gave (initially "Slave").
  bool ptp_features = false;
  std::vector<std::int64_t> clock_offsets_ns;  // per camera; missing: 0
  std::vector<int> without_sync_free_run;      // cameras whose fakes lack SyncFreeRunTimer*

  bool IsValid(std::string* error) const;
};

// What the fill hook needs for one camera; lives as long as the rig (or GvFakeCamera).
struct FakeFillContext {
  int camera = 0;
  ImageGenerator generator;
  std::mutex mutex;
  FrameIdUnwrapper unwrapper;
  bool restart = true;              // a new device: re-anchor the sequence
  std::uint64_t resume = 0;         // ... at this sequence if non-zero, else after the last one
  std::int64_t offset = 0;
  std::uint64_t last_sequence = 0;
  bool any = false;
  std::atomic<std::uint64_t> drawn{0};
  double clock_sequence_rate_hz = 0;  // FakeRigOptions
  // FakeRigOptions::ptp_features: the camera's current device, its own clock, the PTP state its
  // PtpStatus reads, and (under `mutex`) the Synchronous Free Run timer as last latched by
  // SyncFreeRunTimerUpdate.
  bool ptp_features = false;
  bool sync_free_run_available = true;
  std::atomic<ArvFakeCamera*> fake{nullptr};
  std::int64_t own_offset_ns = 0;
  std::atomic<std::uint32_t> ptp_state{8};  // PtpStatus's value: 8 = "Slave"
  std::atomic<std::int32_t> ptp_offset_ns{0};
  bool sync_free_run_latched = false;
  double sync_free_run_rate_hz = 0;
  std::uint64_t sync_free_run_start_ns = 0;
};

class AravisFakeRig {
 public:
  AravisFakeRig(const FakeRigOptions& options, ImageGenerator generator);
  ~AravisFakeRig();
  AravisFakeRig(const AravisFakeRig&) = delete;
  AravisFakeRig& operator=(const AravisFakeRig&) = delete;

  int size() const { return options_.cameras; }
  std::string serial(int camera) const;
  // An AravisCamera whose factory builds a fresh fake device for camera `camera` (the first open
  // and every reopen). options.camera_index is set to `camera`.
  std::unique_ptr<AravisCamera> MakeCamera(int camera, AravisCameraOptions options = {});
  // Simulated unplug / replug: while absent, the factory fails ("device not found").
  void SetPresent(int camera, bool present);
  bool Present(int camera) const;
  // The fake camera behind the most recent device of `camera` (for tests that tamper with its
  // registers behind the backend's back), or nullptr.
  ArvFakeCamera* FakeCamera(int camera);
  std::uint64_t FramesDrawn(int camera) const;
  // ptp_features: the state camera `camera`'s PtpStatus reads while PtpEnable is on (SFNC's:
  // "Slave", "Master", "Listening", "Uncalibrated", "Faulty", ...) and its PtpOffsetFromMaster,
  // for its current device and the ones made after. Error naming an unknown state or camera.
  Status SetPtpState(int camera, const std::string& status, std::int64_t offset_from_master_ns = 0);

 private:
  ArvCamera* NewDevice(int camera, std::uint64_t resume_sequence, std::string* error);

  FakeRigOptions options_;
  std::vector<std::unique_ptr<FakeFillContext>> contexts_;
  std::unique_ptr<std::atomic<bool>[]> present_;
  mutable std::mutex mutex_;
  std::vector<ArvFakeCamera*> latest_;  // not owned
};

// Aravis's GigE Vision fake camera on 127.0.0.1 (real sockets, real GVCP/GVSP).
class GvFakeCamera {
 public:
  GvFakeCamera(std::string serial, int camera_index, ImageGenerator generator, int width = 1280,
               int height = 1024);
  ~GvFakeCamera();
  GvFakeCamera(const GvFakeCamera&) = delete;
  GvFakeCamera& operator=(const GvFakeCamera&) = delete;

  // Starts the fake (again). Only one GigE fake may run on an address (two would both answer
  // GVCP on port 3956): the first Create() takes an exclusive lock on
  // /tmp/mocap-gv-fake-127.0.0.1.lock, kept until destruction (so a Destroy()/Create() cycle
  // keeps the address), waiting up to `wait_s` seconds for another process to release it.
  Status Create(double wait_s = 0.0);
  void Destroy();     // the camera vanishes: no more answers on GVCP, no more packets
  bool running() const { return gv_ != nullptr; }
  std::string device_id() const { return "Aravis-" + serial_; }
  // Fraction of GVSP packets the fake drops (0 = none).
  void SetPacketLossRatio(double ratio);
  std::uint64_t FramesDrawn() const { return context_.drawn.load(); }

 private:
  std::string serial_;
  int width_, height_;
  double loss_ratio_ = 0.0;
  FakeFillContext context_;
  ArvGvFakeCamera* gv_ = nullptr;
  int lock_fd_ = -1;
};

}  // namespace mocap::drivers
