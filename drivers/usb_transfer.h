// USB3 Vision transfer settings: what of a USB3 camera's stream Aravis 0.8 lets a rig set, how
// it is applied and read back, and what a camera's refusal means.
//
// What Aravis 0.8 (0.8.17 and later) offers, and what it does not:
//   - the libusb I/O mode of the stream (arv_uv_device_set_usb_mode / arv_camera_uv_set_usb_mode,
//     ArvUvUsbMode): "sync" (the default: one bulk transfer at a time, a thread waiting on each)
//     or "async" (libusb's asynchronous API: every buffer's transfers submitted ahead, which
//     keeps a fast camera's endpoint busy and is what high frame rates need). It applies to the
//     streams created after it, so it is set before the stream; Aravis has no getter for it (the
//     stream's "usb-mode" property is construct-only and write-only), so it is reported as set.
//   - the transfer geometry is NOT configurable in 0.8: arvuvstream.c fixes the payload transfer
//     size at 1 MiB (ARV_UV_STREAM_MAXIMUM_TRANSFER_SIZE, aligned to the camera's SIRM
//     alignment) and, in async mode, at most 8 MiB submitted at once
//     (ARV_UV_STREAM_MAXIMUM_SUBMIT_TOTAL); the number of transfers per buffer follows from the
//     payload (payload / 1 MiB, plus leader and trailer). AppliedUsbTransfer reports them, and
//     the usbfs budget (drivers/usb_hotplug.h CheckUsbfsMemory) is what a rig sizes instead.
//   - the camera's own link limit, SFNC's DeviceLinkThroughputLimit (bytes per second) with
//     DeviceLinkThroughputLimitMode On/Off: a camera sharing a host controller with others can be
//     held to its share instead of bursting. Aravis's arv_camera_uv_set_bandwidth only enables it
//     on XIMEA cameras, so the SFNC features are set directly, and read back.
// A feature the camera refuses (absent, out of range, reads back otherwise) is an error naming
// the camera and the feature, unless the camera's optional features list it
// (CameraSettings::optional_features), as every other camera feature (drivers/aravis_camera.h).
//
// The device calls are an interface (UsbTransferDevice), so that the application logic runs in
// tests without a USB3 camera: AravisCamera implements it over Aravis, tests over a fake.
#pragma once
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "model/status.h"

namespace mocap::drivers {

enum class UsbMode : std::uint8_t { kDefault, kSync, kAsync };
const char* ToString(UsbMode mode);            // "default" | "sync" | "async"
bool ParseUsbMode(const std::string& text, UsbMode* mode);

struct UsbTransferSettings {
  UsbMode mode = UsbMode::kDefault;  // kDefault: Aravis's (sync)
  // DeviceLinkThroughputLimit in MB/s (1e6 bytes); 0: the limit switched off.
  double throughput_limit_mb_s = 0;

  bool IsValid(std::string* error) const;
};

// Aravis 0.8's fixed USB3 stream geometry (arvuvstream.c), reported with what was applied.
constexpr std::size_t kAravisUsbMaximumTransferBytes = 1 << 20;
constexpr std::size_t kAravisUsbMaximumSubmitBytes = 8 << 20;

struct AppliedUsbTransfer {
  bool applied = false;  // a USB3 Vision camera (else nothing below was set)
  std::string mode;      // as set before the stream (Aravis 0.8 cannot read it back)
  // Read back: DeviceLinkThroughputLimitMode ("On" / "Off", "" when the camera has none) and the
  // limit in MB/s (0 when off).
  std::string throughput_limit_mode;
  double throughput_limit_mb_s = 0;
  std::size_t maximum_transfer_bytes = kAravisUsbMaximumTransferBytes;
  std::size_t maximum_submit_bytes = kAravisUsbMaximumSubmitBytes;
};

// The GenICam and Aravis calls the settings need, on one camera.
class UsbTransferDevice {
 public:
  virtual ~UsbTransferDevice() = default;
  virtual void SetUsbMode(UsbMode mode) = 0;
  virtual bool HasFeature(const std::string& feature) = 0;
  // Errors carry the device's own words; ApplyUsbTransfer names camera and feature around them.
  virtual Status SetInteger(const std::string& feature, std::int64_t value) = 0;
  virtual Status GetInteger(const std::string& feature, std::int64_t* value) = 0;
  virtual Status IntegerBounds(const std::string& feature, std::int64_t* min, std::int64_t* max) = 0;
  virtual Status SetString(const std::string& feature, const std::string& value) = 0;
  virtual Status GetString(const std::string& feature, std::string* value) = 0;
};

// A feature the camera refused: Ok (and "feature: why" appended to *refused_optional) when
// `optional` lists it, else an error naming the camera and the feature. Every camera feature
// of the Aravis backend goes through it.
Status RefusedFeature(const std::string& camera_id, const std::string& feature,
                      const std::string& why, const std::vector<std::string>& optional,
                      std::vector<std::string>* refused_optional);

// Sets the mode, then the throughput limit (on, with the limit, or off), reading each back.
// A limit that reads back more than 1 % away from the one set is refused (cameras round it to
// their increment; more than that is another limit than the rig was sized for).
Status ApplyUsbTransfer(const std::string& camera_id, const UsbTransferSettings& settings,
                        const std::vector<std::string>& optional, UsbTransferDevice* device,
                        AppliedUsbTransfer* applied, std::vector<std::string>* refused_optional);

}  // namespace mocap::drivers
