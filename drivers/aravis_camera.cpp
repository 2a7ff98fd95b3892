#include "drivers/aravis_camera.h"

#include <arv.h>
#include <time.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <thread>
#include <utility>

namespace mocap::drivers {
namespace {

// Takes the message out of a GError (and frees it).
std::string Take(GError** e) {
  if (*e == nullptr) return {};
  std::string m = (*e)->message ? (*e)->message : "unknown Aravis error";
  g_clear_error(e);
  return m;
}

std::string Num(double v) {
  char b[64];
  std::snprintf(b, sizeof b, "%g", v);
  return b;
}

}  // namespace

std::uint32_t ToArvPixelFormat(PixelFormat format) {
  switch (format) {
    case PixelFormat::kMono8: return ARV_PIXEL_FORMAT_MONO_8;
    case PixelFormat::kMono12: return ARV_PIXEL_FORMAT_MONO_12;
    case PixelFormat::kMono16: return ARV_PIXEL_FORMAT_MONO_16;
    case PixelFormat::kMono12Packed: return ARV_PIXEL_FORMAT_MONO_12_PACKED;
  }
  return 0;
}

bool FromArvPixelFormat(std::uint32_t arv_format, PixelFormat* format) {
  switch (arv_format) {
    case ARV_PIXEL_FORMAT_MONO_8: *format = PixelFormat::kMono8; return true;
    case ARV_PIXEL_FORMAT_MONO_12: *format = PixelFormat::kMono12; return true;
    case ARV_PIXEL_FORMAT_MONO_16: *format = PixelFormat::kMono16; return true;
    case ARV_PIXEL_FORMAT_MONO_12_PACKED: *format = PixelFormat::kMono12Packed; return true;
    default: return false;
  }
}

bool AravisCameraOptions::IsValid(std::string* error) const {
  if (reopen_interval_ms < 0) {
    if (error) *error = "aravis camera options: reopen_interval_ms must be >= 0";
    return false;
  }
  return true;
}

AravisCamera::AravisCamera(std::string device_id, AravisCameraOptions options)
    : id_(std::move(device_id)), options_(options) {
  const std::string name = id_;
  factory_ = [name](std::string* error) -> ArvCamera* {
    GError* e = nullptr;
    ArvCamera* cam = arv_camera_new(name.c_str(), &e);
    if (cam == nullptr) {
      const std::string why = Take(&e);
      *error = "cannot open camera '" + name + "'" + (why.empty() ? "" : ": " + why);
    }
    return cam;
  };
}

AravisCamera::AravisCamera(std::string id, ArvCameraFactory factory, AravisCameraOptions options)
    : id_(std::move(id)), factory_(std::move(factory)), options_(options) {}

AravisCamera::AravisCamera(std::string id, ArvCamera* camera, ArvCameraFactory factory,
                           AravisCameraOptions options)
    : id_(std::move(id)), factory_(std::move(factory)), options_(options) {
  if (camera != nullptr) camera_ = ARV_CAMERA(g_object_ref(camera));
}

AravisCamera::~AravisCamera() {
  TearDown(state_.load() == CameraState::kLost);
  for (Slot& s : slots_) {
    // Buffers the caller still holds (or any left by a torn-down stream) are ours to free.
    if (s.outstanding && s.buffer != nullptr) g_object_unref(s.buffer);
    s.buffer = nullptr;
  }
}

Status AravisCamera::FromSerial(const std::string& serial, AravisCameraOptions options,
                                std::unique_ptr<AravisCamera>* camera) {
  arv_update_device_list();
  const unsigned n = arv_get_n_devices();
  std::string seen;
  for (unsigned i = 0; i < n; ++i) {
    const char* s = arv_get_device_serial_nbr(i);
    const char* id = arv_get_device_id(i);
    if (s != nullptr && serial == s && id != nullptr) {
      *camera = std::make_unique<AravisCamera>(id, options);
      return Status::Ok();
    }
    if (s != nullptr) seen += std::string(seen.empty() ? "" : ", ") + s;
  }
  return Status::Error("no camera with serial number '" + serial + "' (found: " +
                       (seen.empty() ? "none" : seen) + ")");
}

void AravisCamera::OnControlLost(ArvDevice*, void* self) {
  static_cast<AravisCamera*>(self)->lost_flag_.store(true);
}

Status AravisCamera::Open(const CameraSettings& settings) {
  std::string error;
  if (!settings.IsValid(&error)) return Status::Error(id_ + ": " + error);
  if (!options_.IsValid(&error)) return Status::Error(id_ + ": " + error);
  if (opened_) TearDown(state_.load() == CameraState::kLost);
  settings_ = settings;
  lost_flag_ = false;
  arrived_flag_ = false;
  Status s = Connect();
  device_found_at_open_ = camera_ != nullptr;
  if (s.ok()) s = CreateStreamAndPool();
  if (!s.ok()) {
    TearDown(false);
    state_ = CameraState::kClosed;
    return s;
  }
  StartFreshStream(/*awaiting_device=*/false);
  return Status::Ok();
}

void AravisCamera::StartFreshStream(bool awaiting_device) {
  opened_ = true;  // configured: Reopen() has the settings
  awaiting_device_ = awaiting_device;
  acquiring_ = false;
  state_ = awaiting_device ? CameraState::kLost : CameraState::kClosed;
  unwrapper_ = FrameIdUnwrapper();
  id_gap_reference_ = false;
  delivered_any_ = false;
  resume_sequence_ = false;
  sequence_offset_ = 0;
}

namespace {
// Opening a device parses its GenICam description (libxml2 into Aravis's node registry). Aravis
// allows different objects in different threads, yet a grab thread reopening its camera crashed
// in that parse while the rig's other grab threads ran (fuzz_daemon, 27 Nov 2026: FPE in
// g_hash_table_remove under arv_gc_register_feature_node, from AravisFakeRig::NewDevice, on an
// empty input: a race, not the input). Every camera's reopen runs on its own grab thread, so
// several can parse at once; an open is rare and slow anyway: the process opens one device at a
// time. (Whether the parse is the whole race is not shown: the crash was seen once.)
std::mutex& DeviceOpenMutex() {
  static std::mutex m;
  return m;
}
}  // namespace

Status AravisCamera::Connect() {
  std::lock_guard<std::mutex> device_lock(device_mutex_);
  if (camera_ == nullptr) {
    if (!factory_) return Status::Error(id_ + ": no camera and no way to open one");
    std::string error;
    {
      std::lock_guard<std::mutex> open_lock(DeviceOpenMutex());
      camera_ = factory_(&error);
    }
    if (camera_ == nullptr) return Status::Error(error.empty() ? id_ + ": cannot open" : error);
  }
  ArvDevice* device = arv_camera_get_device(camera_);
  control_lost_handler_ =
      g_signal_connect(device, "control-lost", G_CALLBACK(&AravisCamera::OnControlLost), this);
  return ApplySettings();
}

Status AravisCamera::ApplySettings() {
  GError* e = nullptr;
  auto fail = [&](const std::string& what) {
    const std::string why = Take(&e);
    return Status::Error(id_ + ": " + what + (why.empty() ? "" : " (" + why + ")"));
  };
  const CameraSettings& s = settings_;

  arv_camera_set_acquisition_mode(camera_, ARV_ACQUISITION_MODE_CONTINUOUS, &e);
  if (e) return fail("cannot set continuous acquisition");

  // Pixel format.
  const ArvPixelFormat want_format = ToArvPixelFormat(s.pixel_format);
  guint n_formats = 0;
  gint64* formats = arv_camera_dup_available_pixel_formats(camera_, &n_formats, &e);
  if (e) return fail("cannot list pixel formats");
  bool available = false;
  for (guint i = 0; i < n_formats; ++i) available |= formats[i] == want_format;
  g_free(formats);
  if (!available) {
    const char** names = arv_camera_dup_available_pixel_formats_as_strings(camera_, &n_formats, &e);
    std::string list;
    for (guint i = 0; names && i < n_formats; ++i) {
      list += std::string(list.empty() ? "" : ", ") + names[i];
    }
    g_free(names);
    g_clear_error(&e);
    return Status::Error(id_ + ": pixel format " + ToString(s.pixel_format) +
                         " not supported by the camera (it offers: " + list + ")");
  }
  arv_camera_set_pixel_format(camera_, want_format, &e);
  if (e) return fail(std::string("cannot set pixel format ") + ToString(s.pixel_format));

  // Region of interest (width/height 0 = the rest of the sensor from the offset).
  gint sensor_w = 0, sensor_h = 0;
  arv_camera_get_sensor_size(camera_, &sensor_w, &sensor_h, &e);
  if (e) return fail("cannot read the sensor size");
  const int w = s.roi_width > 0 ? s.roi_width : sensor_w - s.roi_x;
  const int h = s.roi_height > 0 ? s.roi_height : sensor_h - s.roi_y;
  if (w <= 0 || h <= 0 || s.roi_x + w > sensor_w || s.roi_y + h > sensor_h) {
    return Status::Error(id_ + ": ROI x=" + std::to_string(s.roi_x) + " y=" +
                         std::to_string(s.roi_y) + " " + std::to_string(w) + "x" +
                         std::to_string(h) + " does not fit the " + std::to_string(sensor_w) +
                         "x" + std::to_string(sensor_h) + " sensor");
  }
  gint wmin = 0, wmax = 0, hmin = 0, hmax = 0;
  arv_camera_get_width_bounds(camera_, &wmin, &wmax, &e);
  g_clear_error(&e);
  arv_camera_get_height_bounds(camera_, &hmin, &hmax, &e);
  g_clear_error(&e);
  if ((wmax > 0 && (w < wmin || w > wmax)) || (hmax > 0 && (h < hmin || h > hmax))) {
    return Status::Error(id_ + ": ROI " + std::to_string(w) + "x" + std::to_string(h) +
                         " outside the camera's width " + std::to_string(wmin) + ".." +
                         std::to_string(wmax) + " / height " + std::to_string(hmin) + ".." +
                         std::to_string(hmax));
  }
  const gint winc = std::max<gint>(1, arv_camera_get_width_increment(camera_, &e));
  g_clear_error(&e);
  const gint hinc = std::max<gint>(1, arv_camera_get_height_increment(camera_, &e));
  g_clear_error(&e);
  if (w % winc != 0 || h % hinc != 0) {
    return Status::Error(id_ + ": ROI " + std::to_string(w) + "x" + std::to_string(h) +
                         " is not a multiple of the camera's increments " +
                         std::to_string(winc) + "x" + std::to_string(hinc));
  }
  arv_camera_set_region(camera_, s.roi_x, s.roi_y, w, h, &e);
  if (e) return fail("cannot set the ROI");
  gint rx = 0, ry = 0, rw = 0, rh = 0;
  arv_camera_get_region(camera_, &rx, &ry, &rw, &rh, &e);
  if (e) return fail("cannot read the ROI back");
  if (rx != s.roi_x || ry != s.roi_y || rw != w || rh != h) {
    return Status::Error(id_ + ": the camera changed the ROI to x=" + std::to_string(rx) +
                         " y=" + std::to_string(ry) + " " + std::to_string(rw) + "x" +
                         std::to_string(rh));
  }

  // Exposure and gain, checked against the device's bounds for a message naming both.
  auto set_float = [&](const char* name, double value, const char* unit,
                       void (*bounds)(ArvCamera*, double*, double*, GError**),
                       void (*set)(ArvCamera*, double, GError**),
                       double (*get)(ArvCamera*, GError**), double* readback) -> Status {
    double lo = 0, hi = 0;
    bounds(camera_, &lo, &hi, &e);
    if (e) return fail(std::string("cannot read the ") + name + " bounds");
    if (value < lo || value > hi) {
      return Status::Error(id_ + ": " + name + " " + Num(value) + " " + unit +
                           " outside the camera's range " + Num(lo) + ".." + Num(hi));
    }
    set(camera_, value, &e);
    if (e) return fail(std::string("cannot set ") + name);
    *readback = get(camera_, &e);
    if (e) return fail(std::string("cannot read ") + name + " back");
    return Status::Ok();
  };
  // Real cameras bound the exposure by the frame period and the frame rate by the exposure:
  // lengthening the exposure beyond the CURRENT period must wait for the new frame rate, and
  // the new frame rate may need the new (shorter) exposure first.
  auto set_exposure = [&]() -> Status {
    if (arv_camera_is_exposure_time_available(camera_, &e)) {
      MOCAP_RETURN_IF_ERROR(set_float("exposure", s.exposure_us, "us",
                                      arv_camera_get_exposure_time_bounds,
                                      arv_camera_set_exposure_time, arv_camera_get_exposure_time,
                                      &applied_.exposure_us));
    }
    g_clear_error(&e);
    return Status::Ok();
  };
  bool exposure_first = true;
  if (s.trigger == TriggerMode::kFreeRun && arv_camera_is_frame_rate_available(camera_, &e)) {
    const double current_hz = arv_camera_get_frame_rate(camera_, &e);
    if (current_hz > 0 && s.exposure_us > 1e6 / current_hz) exposure_first = false;
  }
  g_clear_error(&e);
  if (exposure_first) MOCAP_RETURN_IF_ERROR(set_exposure());
  if (arv_camera_is_gain_available(camera_, &e)) {
    MOCAP_RETURN_IF_ERROR(set_float("gain", s.gain_db, "dB", arv_camera_get_gain_bounds,
                                    arv_camera_set_gain, arv_camera_get_gain,
                                    &applied_.gain_db));
  }
  g_clear_error(&e);

  // Trigger, then (free run) the frame rate.
  applied_.trigger_source.clear();
  if (s.trigger == TriggerMode::kFreeRun) {
    arv_camera_clear_triggers(camera_, &e);
    g_clear_error(&e);  // cameras without trigger features are free running anyway
    if (arv_camera_is_frame_rate_available(camera_, &e)) {
      MOCAP_RETURN_IF_ERROR(set_float("frame rate", s.frame_rate_hz, "Hz",
                                      arv_camera_get_frame_rate_bounds,
                                      arv_camera_set_frame_rate, arv_camera_get_frame_rate,
                                      &applied_.frame_rate_hz));
    } else {
      g_clear_error(&e);
      return Status::Error(id_ + ": the camera has no frame rate control for free run");
    }
  } else {
    const std::string source = s.trigger == TriggerMode::kSoftware
                                   ? std::string("Software")
                                   : "Line" + std::to_string(s.trigger_line);
    guint n_sources = 0;
    const char** sources = arv_camera_dup_available_trigger_sources(camera_, &n_sources, &e);
    bool found = false;
    std::string list;
    for (guint i = 0; sources && i < n_sources; ++i) {
      found |= source == sources[i];
      list += std::string(list.empty() ? "" : ", ") + sources[i];
    }
    g_free(sources);
    g_clear_error(&e);
    if (!found) {
      return Status::Error(id_ + ": trigger source " + source +
                           " not offered by the camera (it offers: " +
                           (list.empty() ? "none" : list) + ")");
    }
    arv_camera_set_trigger(camera_, source.c_str(), &e);
    if (e) return fail("cannot set trigger source " + source);
    applied_.trigger_source = source;
    applied_.frame_rate_hz = s.frame_rate_hz;
  }
  if (!exposure_first) MOCAP_RETURN_IF_ERROR(set_exposure());

  ArvPixelFormat got_format = arv_camera_get_pixel_format(camera_, &e);
  if (e) return fail("cannot read the pixel format back");
  if (!FromArvPixelFormat(got_format, &applied_.pixel_format) ||
      applied_.pixel_format != s.pixel_format) {
    return Status::Error(id_ + ": the camera did not take pixel format " +
                         ToString(s.pixel_format));
  }
  applied_.roi_x = rx;
  applied_.roi_y = ry;
  applied_.width = rw;
  applied_.height = rh;
  MOCAP_RETURN_IF_ERROR(ApplyCameraFeatures());
  applied_.payload_bytes = arv_camera_get_payload(camera_, &e);
  if (e) return fail("cannot read the payload size");
  return Status::Ok();
}

Status AravisCamera::Refused(const std::string& feature, const std::string& why) {
  return RefusedFeature(id_, feature, why, settings_.optional_features, &applied_.refused_optional);
}

namespace {

// USB3 Vision transfer settings' device calls (drivers/usb_transfer.h) on an ArvCamera.
class AravisUsbDevice final : public UsbTransferDevice {
 public:
  explicit AravisUsbDevice(ArvCamera* camera) : camera_(camera) {}
  void SetUsbMode(UsbMode mode) override {
    arv_camera_uv_set_usb_mode(camera_, mode == UsbMode::kAsync ? ARV_UV_USB_MODE_ASYNC
                                                                 : ARV_UV_USB_MODE_SYNC);
  }
  bool HasFeature(const std::string& feature) override {
    GError* e = nullptr;
    const bool yes = arv_camera_is_feature_available(camera_, feature.c_str(), &e);
    g_clear_error(&e);
    return yes;
  }
  Status SetInteger(const std::string& feature, std::int64_t value) override {
    GError* e = nullptr;
    arv_camera_set_integer(camera_, feature.c_str(), value, &e);
    return Result(&e);
  }
  Status GetInteger(const std::string& feature, std::int64_t* value) override {
    GError* e = nullptr;
    *value = arv_camera_get_integer(camera_, feature.c_str(), &e);
    return Result(&e);
  }
  Status IntegerBounds(const std::string& feature, std::int64_t* min, std::int64_t* max) override {
    GError* e = nullptr;
    gint64 lo = 0, hi = 0;
    arv_camera_get_integer_bounds(camera_, feature.c_str(), &lo, &hi, &e);
    *min = lo;
    *max = hi;
    return Result(&e);
  }
  Status SetString(const std::string& feature, const std::string& value) override {
    GError* e = nullptr;
    arv_camera_set_string(camera_, feature.c_str(), value.c_str(), &e);
    return Result(&e);
  }
  Status GetString(const std::string& feature, std::string* value) override {
    GError* e = nullptr;
    const char* got = arv_camera_get_string(camera_, feature.c_str(), &e);
    *value = got ? got : "";
    return Result(&e);
  }

 private:
  static Status Result(GError** e) {
    if (*e == nullptr) return Status::Ok();
    return Status::Error(Take(e));
  }
  ArvCamera* camera_;
};

}  // namespace

Status AravisCamera::ApplyCameraFeatures() {
  GError* e = nullptr;
  const CameraSettings& s = settings_;
  applied_.refused_optional.clear();
  auto available = [&](const char* feature) {
    const bool yes = arv_camera_is_feature_available(camera_, feature, &e);
    g_clear_error(&e);
    return yes;
  };
  auto set_string = [&](const char* feature, const std::string& value) -> Status {
    arv_camera_set_string(camera_, feature, value.c_str(), &e);
    if (e) return Refused(feature, "refused " + value + " (" + Take(&e) + ")");
    const char* got = arv_camera_get_string(camera_, feature, &e);
    const std::string back = got ? got : "";
    if (e) return Refused(feature, "cannot be read back (" + Take(&e) + ")");
    if (back != value) return Refused(feature, "set to " + value + ", reads back " + back);
    return Status::Ok();
  };

  // Auto exposure and gain off: a camera that brightens a dark scene moves every marker's
  // pixels across the detector's threshold.
  applied_.exposure_auto.clear();
  applied_.gain_auto.clear();
  for (const char* feature : {"ExposureAuto", "GainAuto"}) {
    if (!available(feature)) continue;
    const Status st = set_string(feature, "Off");
    MOCAP_RETURN_IF_ERROR(st);
    const char* got = arv_camera_get_string(camera_, feature, &e);
    g_clear_error(&e);
    (std::string(feature) == "ExposureAuto" ? applied_.exposure_auto : applied_.gain_auto) =
        got ? got : "";
  }

  // Strobe: Line<n> an output of ExposureActive.
  applied_.strobe_source.clear();
  if (s.strobe_line >= 0) {
    const std::string line = "Line" + std::to_string(s.strobe_line);
    if (!available("LineSelector") || !available("LineSource")) {
      MOCAP_RETURN_IF_ERROR(Refused("LineSource", "the camera has no LineSelector/LineSource "
                                                  "to drive " + line + " with ExposureActive"));
    } else {
      Status st = set_string("LineSelector", line);
      if (st.ok() && available("LineMode")) st = set_string("LineMode", "Output");
      if (st.ok()) st = set_string("LineSource", "ExposureActive");
      MOCAP_RETURN_IF_ERROR(st);
      const char* got = arv_camera_get_string(camera_, "LineSource", &e);
      g_clear_error(&e);
      applied_.strobe_source = got ? got : "";
    }
  }

  // IEEE 1588: SFNC's PtpEnable, or GigE Vision 1.x's GevIEEE1588.
  applied_.ptp_enabled = false;
  if (s.ptp) {
    const char* feature = available("PtpEnable")     ? "PtpEnable"
                          : available("GevIEEE1588") ? "GevIEEE1588"
                                                     : nullptr;
    if (feature == nullptr) {
      MOCAP_RETURN_IF_ERROR(Refused("PtpEnable", "the camera has neither PtpEnable nor "
                                                 "GevIEEE1588 (no IEEE 1588 support)"));
    } else {
      arv_camera_set_boolean(camera_, feature, TRUE, &e);
      if (e) MOCAP_RETURN_IF_ERROR(Refused(feature, "refused true (" + Take(&e) + ")"));
      applied_.ptp_enabled = arv_camera_get_boolean(camera_, feature, &e);
      g_clear_error(&e);
      if (!applied_.ptp_enabled) MOCAP_RETURN_IF_ERROR(Refused(feature, "reads back false"));
    }
  }
  applied_.ptp_schedule.clear();
  applied_.schedule_rate_hz = 0;
  applied_.schedule_start_ticks = 0;
  if (applied_.ptp_enabled && s.ptp_schedule == PtpSchedule::kSyncFreeRun &&
      s.trigger == TriggerMode::kFreeRun)
    MOCAP_RETURN_IF_ERROR(ApplySyncFreeRun());

  // USB3 Vision transfer: the I/O mode (before the stream is created) and the link limit.
  applied_.usb = AppliedUsbTransfer{};
  if (arv_camera_is_uv_device(camera_)) {
    AravisUsbDevice usb(camera_);
    MOCAP_RETURN_IF_ERROR(ApplyUsbTransfer(id_, s.usb, s.optional_features, &usb, &applied_.usb,
                                           &applied_.refused_optional));
  }

  // GigE Vision packets: size (configured, or the largest the path carries) and delay. The
  // stream is created after this, with this packet size.
  applied_.packet_size = 0;
  applied_.packet_delay_ns = 0;
  if (arv_camera_is_gv_device(camera_)) {
    if (s.packet_size > 0) {
      arv_camera_gv_set_packet_size(camera_, s.packet_size, &e);
      if (e) MOCAP_RETURN_IF_ERROR(Refused("GevSCPSPacketSize", "refused " +
                                           std::to_string(s.packet_size) + " (" + Take(&e) + ")"));
    } else {
      arv_camera_gv_auto_packet_size(camera_, &e);
      if (e) MOCAP_RETURN_IF_ERROR(Refused("GevSCPSPacketSize",
                                           "cannot negotiate the packet size (" + Take(&e) + ")"));
    }
    applied_.packet_size = static_cast<int>(arv_camera_gv_get_packet_size(camera_, &e));
    g_clear_error(&e);
    if (s.packet_size > 0 && applied_.packet_size != s.packet_size)
      MOCAP_RETURN_IF_ERROR(Refused("GevSCPSPacketSize",
                                    "set to " + std::to_string(s.packet_size) +
                                        ", reads back " + std::to_string(applied_.packet_size)));
    if (s.packet_delay_ns > 0 || available("GevSCPD")) {
      arv_camera_gv_set_packet_delay(camera_, s.packet_delay_ns, &e);
      if (e) MOCAP_RETURN_IF_ERROR(Refused("GevSCPD", "refused " + std::to_string(s.packet_delay_ns) +
                                                      " ns (" + Take(&e) + ")"));
      applied_.packet_delay_ns = arv_camera_gv_get_packet_delay(camera_, &e);
      g_clear_error(&e);
      // GevSCPD counts ticks of the camera's timestamp clock: the delay reads back rounded to
      // one tick, not more.
      if (std::llabs(applied_.packet_delay_ns - s.packet_delay_ns) > 1000)
        MOCAP_RETURN_IF_ERROR(Refused("GevSCPD", "set to " + std::to_string(s.packet_delay_ns) +
                                                     " ns, reads back " +
                                                     std::to_string(applied_.packet_delay_ns) +
                                                     " ns"));
    }
  }
  return Status::Ok();
}

Status AravisCamera::ApplySyncFreeRun() {
  GError* e = nullptr;
  auto available = [&](const char* feature) {
    const bool yes = arv_camera_is_feature_available(camera_, feature, &e);
    g_clear_error(&e);
    return yes;
  };
  for (const char* feature : {"SyncFreeRunTimerTriggerRateAbs", "SyncFreeRunTimerStartTimeLow",
                              "SyncFreeRunTimerStartTimeHigh", "SyncFreeRunTimerUpdate",
                              "SyncFreeRunTimerEnable"}) {
    if (!available(feature))
      return Refused("SyncFreeRunTimerEnable",
                     std::string("the camera has no ") + feature +
                         " (no Synchronous Free Run): it would free-run at its own phase, off "
                         "the rig's PTP ticks");
  }
  const double rate = settings_.frame_rate_hz;
  arv_camera_set_float(camera_, "SyncFreeRunTimerTriggerRateAbs", rate, &e);
  if (e) return Refused("SyncFreeRunTimerTriggerRateAbs", "refused " + Num(rate) + " Hz (" + Take(&e) + ")");
  const double rate_back = arv_camera_get_float(camera_, "SyncFreeRunTimerTriggerRateAbs", &e);
  if (e) return Refused("SyncFreeRunTimerTriggerRateAbs", "cannot be read back (" + Take(&e) + ")");
  // A float register holds the rate to its last bits; a camera that rounds it to its own timer's
  // resolution drifts off the others' ticks by the difference every period.
  if (std::abs(rate_back - rate) > 1e-9 * rate)
    return Refused("SyncFreeRunTimerTriggerRateAbs",
                   "set to " + Num(rate) + " Hz, reads back " + Num(rate_back) + " Hz");
  double tick_hz = 1e9;
  if (available("GevTimestampTickFrequency")) {
    const gint64 f = arv_camera_get_integer(camera_, "GevTimestampTickFrequency", &e);
    if (!e && f > 0) tick_hz = static_cast<double>(f);
    g_clear_error(&e);
  }
  const auto start = static_cast<std::int64_t>(std::llround(0.5 * tick_hz / rate));
  const std::pair<const char*, std::int64_t> words[] = {
      {"SyncFreeRunTimerStartTimeHigh", start >> 32}, {"SyncFreeRunTimerStartTimeLow", start & 0xFFFFFFFF}};
  for (const auto& [feature, value] : words) {
    arv_camera_set_integer(camera_, feature, value, &e);
    if (e) return Refused(feature, "refused " + std::to_string(value) + " (" + Take(&e) + ")");
    const gint64 back = arv_camera_get_integer(camera_, feature, &e);
    if (e) return Refused(feature, "cannot be read back (" + Take(&e) + ")");
    if (back != value)
      return Refused(feature, "set to " + std::to_string(value) + ", reads back " + std::to_string(back));
  }
  arv_camera_execute_command(camera_, "SyncFreeRunTimerUpdate", &e);
  if (e) return Refused("SyncFreeRunTimerUpdate", "refused (" + Take(&e) + ")");
  arv_camera_set_boolean(camera_, "SyncFreeRunTimerEnable", TRUE, &e);
  if (e) return Refused("SyncFreeRunTimerEnable", "refused true (" + Take(&e) + ")");
  const bool enabled = arv_camera_get_boolean(camera_, "SyncFreeRunTimerEnable", &e);
  if (e) return Refused("SyncFreeRunTimerEnable", "cannot be read back (" + Take(&e) + ")");
  if (!enabled) return Refused("SyncFreeRunTimerEnable", "set to true, reads back false");
  applied_.ptp_schedule = ToString(PtpSchedule::kSyncFreeRun);
  applied_.schedule_rate_hz = rate_back;
  applied_.schedule_start_ticks = start;
  return Status::Ok();
}

bool PtpLocked(const std::vector<std::string>& ids, const std::vector<PtpState>& states,
               std::string* why) {
  std::string not_locked;
  int masters = 0;
  std::string master_ids;
  for (std::size_t i = 0; i < states.size(); ++i) {
    const std::string id = i < ids.size() ? ids[i] : "camera " + std::to_string(i);
    if (states[i].status == "Master") {
      ++masters;
      master_ids += (master_ids.empty() ? "" : ", ") + id;
    } else if (states[i].status != "Slave") {
      not_locked += (not_locked.empty() ? "" : ", ") + id + " (" +
                    (states[i].status.empty() ? "no status" : states[i].status) + ")";
    }
  }
  std::string problem;
  if (!not_locked.empty()) problem = "not locked: " + not_locked;
  if (masters > 1)
    problem += std::string(problem.empty() ? "" : "; ") + std::to_string(masters) +
               " cameras are PTP masters (" + master_ids + "): the rig has more than one clock";
  if (why) *why = problem;
  return problem.empty();
}

Status AravisCamera::Ptp(PtpState* state) {
  std::lock_guard<std::mutex> device_lock(device_mutex_);
  if (camera_ == nullptr) return Status::Error(id_ + ": Ptp() while the camera is not open");
  if (!applied_.ptp_enabled) return Status::Error(id_ + ": PTP is not enabled on this camera");
  GError* e = nullptr;
  const bool sfnc = arv_camera_is_feature_available(camera_, "PtpStatus", &e);
  g_clear_error(&e);
  const char* latch = sfnc ? "PtpDataSetLatch" : "GevIEEE1588DataSetLatch";
  if (arv_camera_is_feature_available(camera_, latch, &e)) arv_camera_execute_command(camera_, latch, &e);
  g_clear_error(&e);
  const char* status = arv_camera_get_string(camera_, sfnc ? "PtpStatus" : "GevIEEE1588Status", &e);
  if (e) return Status::Error(id_ + ": cannot read " + (sfnc ? "PtpStatus" : "GevIEEE1588Status") +
                              " (" + Take(&e) + ")");
  state->status = status ? status : "";
  const char* offset = sfnc ? "PtpOffsetFromMaster" : "GevIEEE1588OffsetFromMaster";
  state->has_offset = arv_camera_is_feature_available(camera_, offset, &e);
  g_clear_error(&e);
  if (state->has_offset) {
    state->offset_from_master_ns = arv_camera_get_integer(camera_, offset, &e);
    if (e) state->has_offset = false;
    g_clear_error(&e);
  }
  return Status::Ok();
}

bool AravisCamera::PacketStatistics(std::uint64_t* resent, std::uint64_t* missing) const {
  std::lock_guard<std::mutex> lock(pool_mutex_);
  if (stream_ == nullptr || !ARV_IS_GV_STREAM(stream_)) return false;
  guint64 r = 0, m = 0;
  arv_gv_stream_get_statistics(ARV_GV_STREAM(stream_), &r, &m);
  *resent = r;
  *missing = m;
  return true;
}

std::uint64_t AravisCamera::MissingPackets() const {
  std::uint64_t resent = 0, missing = 0;
  PacketStatistics(&resent, &missing);
  return missing;
}

std::uint64_t AravisCamera::ResentPackets() const {
  std::uint64_t resent = 0, missing = 0;
  PacketStatistics(&resent, &missing);
  return resent;
}

namespace {

// A GigE Vision device reached over the loopback interface: Aravis's GigE fake on 127.0.0.1, which
// a test runs beside mocapd. Aravis's packet socket (AF_PACKET) does not receive its stream there
// (the tests saw no frame), ordinary sockets do; a real camera is never on loopback.
bool OnLoopback(ArvDevice* device) {
  if (!ARV_IS_GV_DEVICE(device)) return false;
  GSocketAddress* address = arv_gv_device_get_device_address(ARV_GV_DEVICE(device));
  return address != nullptr && G_IS_INET_SOCKET_ADDRESS(address) &&
         g_inet_address_get_is_loopback(
             g_inet_socket_address_get_address(G_INET_SOCKET_ADDRESS(address)));
}

}  // namespace

Status AravisCamera::CreateStreamAndPool() {
  GError* e = nullptr;
  ArvDevice* device = arv_camera_get_device(camera_);
  if (ARV_IS_GV_DEVICE(device) && (options_.disable_packet_socket || OnLoopback(device))) {
    arv_gv_device_set_stream_options(ARV_GV_DEVICE(device),
                                     ARV_GV_STREAM_OPTION_PACKET_SOCKET_DISABLED);
  }
  ArvStream* stream = arv_camera_create_stream(camera_, nullptr, nullptr, &e);
  if (stream == nullptr) {
    return Status::Error(id_ + ": cannot create the stream: " + Take(&e));
  }
  applied_.packet_resend = false;
  applied_.socket_buffer_bytes = 0;
  if (ARV_IS_GV_STREAM(stream)) {
    if (settings_.socket_buffer_bytes > 0) {
      g_object_set(stream, "socket-buffer", ARV_GV_STREAM_SOCKET_BUFFER_FIXED,
                   "socket-buffer-size", settings_.socket_buffer_bytes, nullptr);
    } else if (options_.auto_socket_buffer) {
      g_object_set(stream, "socket-buffer", ARV_GV_STREAM_SOCKET_BUFFER_AUTO, nullptr);
    }
    g_object_set(stream, "packet-resend",
                 settings_.packet_resend ? ARV_GV_STREAM_PACKET_RESEND_ALWAYS
                                         : ARV_GV_STREAM_PACKET_RESEND_NEVER,
                 nullptr);
    gint resend = 0, buffer_size = 0;
    g_object_get(stream, "packet-resend", &resend, "socket-buffer-size", &buffer_size, nullptr);
    applied_.packet_resend = resend == ARV_GV_STREAM_PACKET_RESEND_ALWAYS;
    applied_.socket_buffer_bytes = buffer_size;
    if (applied_.packet_resend != settings_.packet_resend) {
      g_object_unref(stream);
      return Status::Error(id_ + ": the stream's packet-resend reads back " +
                           (applied_.packet_resend ? "always" : "never"));
    }
  }
  const std::size_t image_bytes =
      WireRowBytes(applied_.pixel_format, applied_.width) * applied_.height;
  const std::size_t needed = std::max(image_bytes, applied_.payload_bytes);

  std::lock_guard<std::mutex> lock(pool_mutex_);
  stream_ = stream;
  const bool any_outstanding =
      std::any_of(slots_.begin(), slots_.end(), [](const Slot& s) { return s.outstanding; });
  if (!any_outstanding &&
      (slots_.size() != static_cast<std::size_t>(settings_.buffer_count) || slot_bytes_ < needed)) {
    slots_.clear();
    slots_.resize(settings_.buffer_count);
    for (Slot& s : slots_) {
      s.memory.reset(new std::uint8_t[needed]);
      if (applied_.pixel_format == PixelFormat::kMono12Packed)
        s.unpacked.reset(new std::uint16_t[static_cast<std::size_t>(applied_.width) * applied_.height]);
    }
    slot_bytes_ = needed;
  } else if (slot_bytes_ < needed) {
    return Status::Error(id_ + ": the payload grew while frames are still held");
  }
  if (applied_.pixel_format == PixelFormat::kMono12Packed) {
    for (Slot& s : slots_)
      if (!s.outstanding)
        s.unpacked.reset(new std::uint16_t[static_cast<std::size_t>(applied_.width) * applied_.height]);
  }
  ++generation_;
  for (Slot& s : slots_) {
    if (s.outstanding) continue;  // re-wrapped on Release
    s.buffer = arv_buffer_new_full(slot_bytes_, s.memory.get(), &s, nullptr);
    s.generation = generation_;
    arv_stream_push_buffer(stream_, s.buffer);  // the stream owns it until popped
  }
  return Status::Ok();
}

std::uint64_t AravisCamera::StreamUnderruns() const {
  if (stream_ == nullptr) return 0;
  guint64 completed = 0, failures = 0, underruns = 0;
  arv_stream_get_statistics(stream_, &completed, &failures, &underruns);
  return underruns;
}


void AravisCamera::TearDown(bool device_gone) {
  std::lock_guard<std::mutex> device_lock(device_mutex_);
  GError* e = nullptr;
  underrun_base_ += StreamUnderruns();
  counters_.underruns = underrun_base_;
  if (camera_ != nullptr && acquiring_ && !device_gone) {
    arv_camera_stop_acquisition(camera_, &e);
    g_clear_error(&e);
  }
  {
    std::lock_guard<std::mutex> lock(pool_mutex_);
    if (stream_ != nullptr) {
      g_object_unref(stream_);  // joins its thread, frees the buffers in its queues
      stream_ = nullptr;
    }
    for (Slot& s : slots_) {
      if (!s.outstanding) s.buffer = nullptr;
    }
  }
  if (camera_ != nullptr) {
    if (control_lost_handler_ != 0) {
      g_signal_handler_disconnect(arv_camera_get_device(camera_), control_lost_handler_);
      control_lost_handler_ = 0;
    }
    g_object_unref(camera_);
    camera_ = nullptr;
  }
}

void AravisCamera::AwaitDevice(const CameraSettings& settings, std::string why) {
  if (opened_) TearDown(state_.load() == CameraState::kLost);
  settings_ = settings;
  lost_flag_ = false;
  arrived_flag_ = false;
  StartFreshStream(/*awaiting_device=*/true);
  last_reopen_attempt_ = std::chrono::steady_clock::now();
  std::lock_guard<std::mutex> lock(error_mutex_);
  last_error_ = std::move(why);
}

std::string AravisCamera::LastError() const {
  std::lock_guard<std::mutex> lock(error_mutex_);
  return last_error_;
}

Status AravisCamera::Start() {
  if (!opened_) return Status::Error(id_ + ": Start() before a successful Open()");
  if (state_.load() == CameraState::kLost && awaiting_device_) {
    acquiring_ = true;  // streams from its first successful open (Grab -> Reopen)
    return Status::Ok();
  }
  if (state_.load() == CameraState::kLost) return Status::Error(id_ + ": camera lost");
  std::lock_guard<std::mutex> device_lock(device_mutex_);
  GError* e = nullptr;
  arv_camera_start_acquisition(camera_, &e);
  if (e) return Status::Error(id_ + ": cannot start acquisition: " + Take(&e));
  acquiring_ = true;
  state_ = CameraState::kStreaming;
  return Status::Ok();
}

void AravisCamera::Stop() {
  std::lock_guard<std::mutex> device_lock(device_mutex_);
  if (camera_ != nullptr && acquiring_ && state_.load() != CameraState::kLost) {
    GError* e = nullptr;
    arv_camera_stop_acquisition(camera_, &e);
    g_clear_error(&e);
  }
  acquiring_ = false;
  if (state_.load() == CameraState::kStreaming) state_ = CameraState::kClosed;
}

Status AravisCamera::Trigger() {
  if (settings_.trigger != TriggerMode::kSoftware) {
    return Status::Error(id_ + ": Trigger() needs TriggerMode::kSoftware (configured: " +
                         ToString(settings_.trigger) + ")");
  }
  if (camera_ == nullptr || state_.load() != CameraState::kStreaming) {
    return Status::Error(id_ + ": Trigger() while not streaming");
  }
  GError* e = nullptr;
  arv_camera_software_trigger(camera_, &e);
  if (e) return Status::Error(id_ + ": software trigger failed: " + Take(&e));
  return Status::Ok();
}

void AravisCamera::MarkLost() {
  if (state_.load() == CameraState::kLost) return;
  state_ = CameraState::kLost;
  counters_.losses++;
  TearDown(/*device_gone=*/true);
  last_reopen_attempt_ = std::chrono::steady_clock::now();
}

Status AravisCamera::Reopen() {
  if (!opened_) return Status::Error(id_ + ": Reopen() before Open()");
  if (!factory_) return Status::Error(id_ + ": cannot reopen a camera adopted without a factory");
  last_reopen_attempt_ = std::chrono::steady_clock::now();
  TearDown(/*device_gone=*/true);
  lost_flag_ = false;
  Status s = Connect();
  if (s.ok()) s = CreateStreamAndPool();
  if (s.ok() && acquiring_) {
    std::lock_guard<std::mutex> device_lock(device_mutex_);
    GError* e = nullptr;
    arv_camera_start_acquisition(camera_, &e);
    if (e) s = Status::Error(id_ + ": cannot restart acquisition: " + Take(&e));
  }
  if (!s.ok()) {
    {
      std::lock_guard<std::mutex> lock(error_mutex_);
      last_error_ = s.message();
    }
    TearDown(true);
    state_ = CameraState::kLost;
    return s;
  }
  unwrapper_ = FrameIdUnwrapper();
  id_gap_reference_ = false;  // a new stream counts its ids afresh
  resume_sequence_ = delivered_any_;
  awaiting_device_ = false;
  {
    std::lock_guard<std::mutex> lock(error_mutex_);
    last_error_.clear();
  }
  counters_.reopens++;
  state_ = acquiring_ ? CameraState::kStreaming : CameraState::kClosed;
  return Status::Ok();
}

GrabResult AravisCamera::Grab(Frame* frame) {
  if (!opened_) return GrabResult::kStopped;
  if (lost_flag_.load()) MarkLost();
  if (state_.load() == CameraState::kLost) {
    if (!factory_) return GrabResult::kLost;
    const auto now = std::chrono::steady_clock::now();
    const bool arrived = arrived_flag_.exchange(false);
    const bool due = options_.auto_reopen &&
                     now - last_reopen_attempt_ >=
                         std::chrono::milliseconds(options_.reopen_interval_ms);
    if (arrived || due) Reopen();
    if (state_.load() == CameraState::kLost) {
      // Not back yet: wait a little so the caller's loop does not spin.
      std::this_thread::sleep_for(std::chrono::milliseconds(
          std::min<int>(20, std::max(1, options_.reopen_interval_ms / 4))));
      return GrabResult::kLost;
    }
  }
  if (!acquiring_ || stream_ == nullptr) return GrabResult::kStopped;

  ArvBuffer* buffer = arv_stream_timeout_pop_buffer(
      stream_, static_cast<guint64>(settings_.timeout_ms * 1000.0));
  if (buffer == nullptr) {
    if (lost_flag_.load()) {
      MarkLost();
      return GrabResult::kLost;
    }
    counters_.timeouts++;
    return GrabResult::kTimeout;
  }
  // Images that found no free buffer in the stream are Aravis's to count: mirror them.
  counters_.underruns = underrun_base_ + StreamUnderruns();
  Slot* slot = nullptr;
  const GrabResult r = Classify(buffer, frame, &slot);
  if (r != GrabResult::kFrame) {
    ++undelivered_since_;
    arv_stream_push_buffer(stream_, buffer);
    return r;
  }
  std::lock_guard<std::mutex> lock(pool_mutex_);
  slot->outstanding = true;
  return GrabResult::kFrame;
}

GrabResult AravisCamera::Classify(ArvBuffer* buffer, Frame* frame, Slot** slot) {
  switch (arv_buffer_get_status(buffer)) {
    case ARV_BUFFER_STATUS_SUCCESS: break;
    case ARV_BUFFER_STATUS_MISSING_PACKETS:
    case ARV_BUFFER_STATUS_WRONG_PACKET_ID:
      counters_.missing_packets++;
      return GrabResult::kIncomplete;
    case ARV_BUFFER_STATUS_TIMEOUT:
      counters_.timeouts++;
      return GrabResult::kIncomplete;
    case ARV_BUFFER_STATUS_SIZE_MISMATCH:
      counters_.size_mismatches++;
      return GrabResult::kIncomplete;
    default:
      counters_.other_errors++;
      return GrabResult::kIncomplete;
  }
  const ArvBufferPayloadType type = arv_buffer_get_payload_type(buffer);
  if (type != ARV_BUFFER_PAYLOAD_TYPE_IMAGE && type != ARV_BUFFER_PAYLOAD_TYPE_EXTENDED_CHUNK_DATA) {
    counters_.other_errors++;
    return GrabResult::kIncomplete;
  }
  PixelFormat format;
  if (!FromArvPixelFormat(arv_buffer_get_image_pixel_format(buffer), &format) ||
      format != applied_.pixel_format) {
    counters_.wrong_format++;
    return GrabResult::kIncomplete;
  }
  const int w = arv_buffer_get_image_width(buffer);
  const int h = arv_buffer_get_image_height(buffer);
  size_t reported = 0;
  const void* data = arv_buffer_get_image_data(buffer, &reported);
  const std::size_t expected = WireRowBytes(format, applied_.width) * applied_.height;
  // The fake path reports 0: the size is then width x height x bytes per pixel.
  if (w != applied_.width || h != applied_.height || data == nullptr ||
      (reported != 0 && reported < expected) || expected > slot_bytes_) {
    counters_.size_mismatches++;
    return GrabResult::kIncomplete;
  }
  *slot = static_cast<Slot*>(const_cast<void*>(arv_buffer_get_user_data(buffer)));

  const std::uint16_t id = static_cast<std::uint16_t>(arv_buffer_get_frame_id(buffer) & 0xFFFFu);
  const std::uint64_t raw = unwrapper_.Next(id);
  const std::uint64_t underruns = counters_.underruns.load();
  if (id_gap_reference_ && raw > id_gap_last_raw_ + 1) {
    // Each wrap of the 16-bit id passes an id 0 that GigE Vision 1.x cameras never send (the
    // fakes go 65535 -> 1): not a frame lost. (A camera that does send 0 loses one per 65536
    // from this count.)
    const std::uint64_t wraps = (raw >> 16) - (id_gap_last_raw_ >> 16);
    const std::uint64_t skipped = raw - id_gap_last_raw_ - 1 - std::min(wraps, raw - id_gap_last_raw_ - 1);
    const std::uint64_t arrived = undelivered_since_ + (underruns - underruns_at_);
    if (skipped > arrived) counters_.not_received += skipped - arrived;
  }
  id_gap_reference_ = true;
  id_gap_last_raw_ = raw;
  undelivered_since_ = 0;
  underruns_at_ = underruns;
  if (resume_sequence_) {
    sequence_offset_ = last_sequence_ + 1 - raw;  // modular: continues after a reopen
    resume_sequence_ = false;
  }
  const std::uint64_t sequence = raw + sequence_offset_;
  last_sequence_ = sequence;
  delivered_any_ = true;

  frame->camera = options_.camera_index;
  frame->frame_id = id;
  frame->sequence = sequence;
  frame->device_timestamp_ns = arv_buffer_get_timestamp(buffer);
  // When Aravis began receiving the image (its system timestamp, real time) besides when we
  // popped it: the wait in Aravis's output queue belongs in every latency figure.
  const std::uint64_t now = MonotonicNs();
  const std::uint64_t system_ns = arv_buffer_get_system_timestamp(buffer);
  std::uint64_t host = now;
  if (system_ns != 0) {
    timespec rt;
    clock_gettime(CLOCK_REALTIME, &rt);
    const std::int64_t realtime_now = static_cast<std::int64_t>(rt.tv_sec) * 1000000000LL + rt.tv_nsec;
    const std::int64_t waited = realtime_now - static_cast<std::int64_t>(system_ns);
    // A clock step (NTP) between the two readings would give nonsense: keep the pop time then.
    if (waited >= 0 && waited < 10'000'000'000LL) host = now - static_cast<std::uint64_t>(waited);
  }
  frame->host_timestamp_ns = now;
  frame->received_ns = host;
  frame->status = FrameStatus::kComplete;
  frame->image.width = w;
  frame->image.height = h;
  if (format == PixelFormat::kMono12Packed) {
    // Unpacked into the slot's own words: one pass over the image, the only copy on this path.
    UnpackMono12Packed(static_cast<const std::uint8_t*>(data), WireRowBytes(format, w), w, h,
                       (*slot)->unpacked.get(), static_cast<std::size_t>(w) * 2);
    frame->image.data = reinterpret_cast<const std::uint8_t*>((*slot)->unpacked.get());
    frame->image.stride = static_cast<std::ptrdiff_t>(w) * 2;
    frame->image.format = PixelFormat::kMono12;
  } else {
    frame->image.data = static_cast<const std::uint8_t*>(data);
    frame->image.stride = static_cast<std::ptrdiff_t>(w) * BytesPerPixel(format);
    frame->image.format = format;
  }
  frame->handle = buffer;
  counters_.complete++;
  return GrabResult::kFrame;
}

void AravisCamera::Release(const Frame& frame) {
  ArvBuffer* buffer = static_cast<ArvBuffer*>(const_cast<void*>(frame.handle));
  if (buffer == nullptr) return;
  std::lock_guard<std::mutex> lock(pool_mutex_);
  Slot* slot = static_cast<Slot*>(const_cast<void*>(arv_buffer_get_user_data(buffer)));
  if (slot == nullptr || !slot->outstanding || slot->buffer != buffer) return;  // stale handle
  slot->outstanding = false;
  if (slot->generation == generation_ && stream_ != nullptr) {
    arv_stream_push_buffer(stream_, buffer);
    return;
  }
  // Its stream is gone (a reopen): free the old wrapper, give the memory to the new stream.
  g_object_unref(buffer);
  slot->buffer = nullptr;
  if (stream_ != nullptr) {
    slot->buffer = arv_buffer_new_full(slot_bytes_, slot->memory.get(), slot, nullptr);
    slot->generation = generation_;
    arv_stream_push_buffer(stream_, slot->buffer);
  }
}

}  // namespace mocap::drivers
