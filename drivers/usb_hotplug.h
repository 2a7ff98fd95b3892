// USB3 Vision cameras arriving and leaving, and the usbfs memory limit they need.
//
// Hot-plug. A USB camera that is unplugged does not always fail its stream at once (Aravis may
// sit in a transfer timeout), and one plugged back in says nothing at all: nobody would reopen
// it. UsbHotplugMonitor registers a libusb hot-plug callback (libusb_hotplug_register_callback)
// and reports USB3 Vision devices only: those with an interface of class 0xEF (miscellaneous),
// subclass 0x05 (USB3 Vision; protocol 0 control, 1 event, 2 streaming), identified by serial
// number (the string descriptor iSerialNumber, which is also Aravis's serial). libusb calls its
// callback from the monitor's event thread, where it may not do I/O; the monitor only queues
// there, and opens the arriving device to read its serial after libusb_handle_events returns.
// Departing devices are reported with the serial read at arrival (a gone device has none).
// The owner routes an event to the AravisCamera of that serial: kLeft -> NotifyRemoved(),
// kArrived -> NotifyArrived() (drivers/aravis_camera.h), which reopens it.
//
// Where libusb has no hot-plug (no usbfs/udev in a container, other platforms) Start() says so
// in its Status and the cameras still come back by the backend's periodic reopen attempts.
// Inject() delivers an event as if libusb had reported it: the test hook for a simulated USB
// removal (with AravisFakeRig::SetPresent, drivers/aravis_fake.h).
//
// usbfs memory. Linux caps the memory all usbfs users may pin for USB transfers at
// /sys/module/usbcore/parameters/usbfs_memory_mb (16 MB by default): far less than the stream
// buffers of a rig of USB3 cameras (8 x 1280x1024 x 16 buffers = 168 MB), and the symptom
// (failed transfers, lost frames) does not name the cause. CheckUsbfsMemory() does, at start-up.
//
// Usage:
//   drivers::UsbHotplugMonitor monitor([&](drivers::UsbEvent e, const drivers::UsbDeviceInfo& d) {
//     if (auto* cam = FindBySerial(d.serial))
//       e == drivers::UsbEvent::kLeft ? cam->NotifyRemoved() : cam->NotifyArrived();
//   });
//   if (Status s = monitor.Start(); !s.ok()) log.warn(s.message());
//   if (Status s = drivers::CheckUsbfsMemory(drivers::UsbfsBytesNeeded(cams, settings)); !s.ok())
//     log.error(s.message());
#pragma once
#include <atomic>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "drivers/camera_source.h"

namespace mocap::drivers {

enum class UsbEvent : std::uint8_t { kArrived, kLeft };
const char* ToString(UsbEvent e);

struct UsbDeviceInfo {
  std::uint16_t vendor_id = 0;
  std::uint16_t product_id = 0;
  int bus = 0;
  int address = 0;
  std::string serial;  // "" if it could not be read (permissions)
};

using UsbHotplugCallback = std::function<void(UsbEvent, const UsbDeviceInfo&)>;

// USB3 Vision interface class codes (USB3 Vision standard, section on the device descriptors).
constexpr std::uint8_t kUsbClassMiscellaneous = 0xEF;
constexpr std::uint8_t kU3vInterfaceSubclass = 0x05;

class UsbHotplugMonitor {
 public:
  explicit UsbHotplugMonitor(UsbHotplugCallback callback);
  ~UsbHotplugMonitor();
  UsbHotplugMonitor(const UsbHotplugMonitor&) = delete;
  UsbHotplugMonitor& operator=(const UsbHotplugMonitor&) = delete;

  // libusb_init, hot-plug capability, callback registration (devices already present are
  // reported as arrived), event thread. An error Status names what is missing; the monitor is
  // then stopped and Stop() is harmless.
  Status Start();
  void Stop();
  bool running() const { return running_.load(); }
  // Delivers an event as if libusb had reported it (from the caller's thread).
  void Inject(UsbEvent event, const UsbDeviceInfo& device);

  struct Impl;  // libusb state (public only for the C callback)

 private:
  void Deliver(UsbEvent event, const UsbDeviceInfo& device);

  UsbHotplugCallback callback_;
  std::mutex callback_mutex_;
  std::atomic<bool> running_{false};
  std::unique_ptr<Impl> impl_;
};

// Bytes of stream buffers a set of cameras pins in usbfs: cameras x buffers x payload.
std::size_t UsbfsBytesNeeded(int cameras, const CameraSettings& settings, int width, int height);

// Ok if the usbfs limit in `path` (MB; 0 = unlimited) covers `needed_bytes`; otherwise an error
// saying it is too small and how to raise it (now, and at every boot).
Status CheckUsbfsMemory(std::size_t needed_bytes,
                        const std::string& path = "/sys/module/usbcore/parameters/usbfs_memory_mb");

}  // namespace mocap::drivers
