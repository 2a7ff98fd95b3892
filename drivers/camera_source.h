// One interface for every camera backend, shaped after Aravis's own layers
// (system -> interface -> device -> stream -> buffer):
//   - CameraSource    one camera: settings, start/stop, a stream of Frames from a pooled buffer;
//   - backends        drivers/aravis_camera.h (GigE Vision + USB3 Vision, and Aravis's own fake
//                     devices, so tests run the Aravis code unchanged) and
//                     drivers/simulated_camera.h (in process, no Aravis, for fast unit tests).
// Images of the fake and simulated cameras come from an ImageGenerator the caller plugs in
// (sim/renderer.h draws the simulated subject's markers): drivers/ depends on nothing of ours.
//
// Threading: Grab() is called from one acquisition thread per camera; Counters() and State()
// may be read from any thread.
#pragma once
#include <atomic>
#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "drivers/frame.h"
#include "drivers/usb_transfer.h"
#include "model/status.h"

namespace mocap::drivers {

enum class TriggerMode : std::uint8_t { kFreeRun, kHardwareLine, kSoftware };
const char* ToString(TriggerMode m);

enum class PtpSchedule : std::uint8_t { kNone, kSyncFreeRun };
const char* ToString(PtpSchedule s);                       // "none" | "sync-free-run"
bool ParsePtpSchedule(const std::string& text, PtpSchedule* schedule);

struct CameraSettings {
  double exposure_us = 500.0;
  double gain_db = 0.0;
  double frame_rate_hz = 200.0;
  // Region of interest; width/height 0 = the whole sensor.
  int roi_x = 0, roi_y = 0, roi_width = 0, roi_height = 0;
  PixelFormat pixel_format = PixelFormat::kMono8;
  TriggerMode trigger = TriggerMode::kFreeRun;
  int trigger_line = 0;   // for kHardwareLine: Line<trigger_line>
  int buffer_count = 16;  // the pre-allocated pool
  double timeout_ms = 1000.0;
  // Exposure and gain are always manual: a camera's ExposureAuto / GainAuto (where it has them)
  // are switched Off and read back, so that the camera never changes the brightness the
  // detector's threshold was set for.
  // Line<strobe_line> becomes an output driven by ExposureActive (the IR ring's flash, and a
  // trigger master's pulse into the other cameras' trigger inputs); -1: none.
  int strobe_line = -1;
  // IEEE 1588: PtpEnable (SFNC) or GevIEEE1588 (GigE Vision 1.x naming) switched on; the lock
  // is read with AravisCamera::Ptp().
  bool ptp = false;
  // With ptp: how the camera's exposures are put on the common clock's ticks (a PTP lock alone
  // makes the clocks agree, not the instants the cameras expose at: each free-runs at the phase
  // its acquisition happened to start at). kSyncFreeRun: Basler's Synchronous Free Run
  // (SyncFreeRunTimer*, drivers/aravis_camera.h "Exposure schedule"); kNone: left to the camera
  // (the rig check then shows whether it exposes on the ticks).
  PtpSchedule ptp_schedule = PtpSchedule::kSyncFreeRun;
  // GigE Vision transport (other transports ignore these). packet_size 0: negotiated, the
  // largest the path carries (jumbo frames where every NIC and switch allow them).
  int packet_size = 0;
  int packet_delay_ns = 0;      // GevSCPD: spreads a frame's packets (cameras sharing a link)
  bool packet_resend = true;    // Aravis asks the camera again for a lost packet
  int socket_buffer_bytes = 0;  // the stream socket's receive buffer; 0: one payload
  // USB3 Vision transfer (other transports ignore it): drivers/usb_transfer.h.
  UsbTransferSettings usb;
  // GenICam features the camera may refuse (a camera without a strobe line, without PTP, ...):
  // refused, they are listed in AppliedSettings::refused_optional instead of failing Open().
  // Any other feature the camera refuses fails Open() with the camera and the feature named.
  std::vector<std::string> optional_features;

  bool IsValid(std::string* error) const;
};

enum class CameraState : std::uint8_t { kClosed, kStreaming, kLost };
const char* ToString(CameraState s);

// Per-camera counts of everything that did not become a frame, and of what did.
struct CameraCounters {
  std::atomic<std::uint64_t> complete{0};
  std::atomic<std::uint64_t> missing_packets{0};
  std::atomic<std::uint64_t> timeouts{0};
  std::atomic<std::uint64_t> underruns{0};
  // Whole frames that never arrived: frame ids skipped within a stream (GigE Vision: every
  // packet of the frame lost before the host took it, a receive buffer too small for a
  // descheduled stream thread, a link dropping them). No buffer was handed out for them, so no
  // other counter sees them. AravisCamera counts them; 0 for sources without frame ids.
  std::atomic<std::uint64_t> not_received{0};
  std::atomic<std::uint64_t> size_mismatches{0};
  std::atomic<std::uint64_t> wrong_format{0};
  std::atomic<std::uint64_t> other_errors{0};
  std::atomic<std::uint64_t> losses{0};   // control lost / device removed
  std::atomic<std::uint64_t> reopens{0};  // came back after a loss
};

enum class GrabResult : std::uint8_t { kFrame, kIncomplete, kTimeout, kLost, kStopped };

class CameraSource {
 public:
  virtual ~CameraSource() = default;
  virtual const std::string& id() const = 0;  // Aravis device id or serial; "sim-<n>" otherwise
  virtual Status Open(const CameraSettings& settings) = 0;
  virtual Status Start() = 0;
  virtual void Stop() = 0;
  // Waits up to the settings' timeout for the next buffer. kFrame: *frame is complete and must
  // be given back with Release(). kIncomplete: the buffer was counted and already recycled.
  virtual GrabResult Grab(Frame* frame) = 0;
  virtual void Release(const Frame& frame) = 0;
  // Software trigger (TriggerMode::kSoftware).
  virtual Status Trigger() = 0;
  virtual CameraState State() const = 0;
  virtual const CameraCounters& Counters() const = 0;
  // Why the camera is not streaming, when it is not (its last failed open); "" otherwise.
  virtual std::string LastError() const { return {}; }
};

// Draws the image of one camera for one frame: the fake and simulated backends call it to fill
// a buffer. `sequence` is the frame's unwrapped number (time = sequence / frame rate).
using ImageGenerator = std::function<void(int camera, std::uint64_t sequence, std::uint8_t* data,
                                          int width, int height, std::ptrdiff_t stride,
                                          PixelFormat format)>;

}  // namespace mocap::drivers
