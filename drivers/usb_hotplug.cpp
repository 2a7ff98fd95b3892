#include "drivers/usb_hotplug.h"

#include <libusb.h>

#include <cerrno>
#include <cmath>
#include <cstring>
#include <deque>
#include <fstream>
#include <map>
#include <sstream>

namespace mocap::drivers {

const char* ToString(UsbEvent e) { return e == UsbEvent::kArrived ? "arrived" : "left"; }

struct UsbHotplugMonitor::Impl {
  UsbHotplugMonitor* owner = nullptr;
  libusb_context* context = nullptr;
  libusb_hotplug_callback_handle handle = 0;
  bool registered = false;
  std::thread thread;
  std::atomic<bool> stop{false};
  std::mutex queue_mutex;
  std::deque<std::pair<UsbEvent, libusb_device*>> queue;  // each device referenced
  std::map<libusb_device*, UsbDeviceInfo> known;          // USB3 Vision devices seen arriving

  static int LIBUSB_CALL OnHotplug(libusb_context*, libusb_device* device,
                                   libusb_hotplug_event event, void* user_data) {
    // No I/O here (libusb forbids it in the callback): queue for the event thread.
    auto* self = static_cast<Impl*>(user_data);
    std::lock_guard<std::mutex> lock(self->queue_mutex);
    self->queue.emplace_back(event == LIBUSB_HOTPLUG_EVENT_DEVICE_ARRIVED ? UsbEvent::kArrived
                                                                          : UsbEvent::kLeft,
                             libusb_ref_device(device));
    return 0;  // stay registered
  }

  static bool IsUsb3Vision(libusb_device* device) {
    libusb_config_descriptor* config = nullptr;
    if (libusb_get_active_config_descriptor(device, &config) != 0 &&
        libusb_get_config_descriptor(device, 0, &config) != 0) {
      return false;
    }
    bool u3v = false;
    for (int i = 0; i < config->bNumInterfaces && !u3v; ++i) {
      const libusb_interface& itf = config->interface[i];
      for (int a = 0; a < itf.num_altsetting; ++a) {
        if (itf.altsetting[a].bInterfaceClass == kUsbClassMiscellaneous &&
            itf.altsetting[a].bInterfaceSubClass == kU3vInterfaceSubclass) {
          u3v = true;
        }
      }
    }
    libusb_free_config_descriptor(config);
    return u3v;
  }

  void Process() {
    std::deque<std::pair<UsbEvent, libusb_device*>> events;
    {
      std::lock_guard<std::mutex> lock(queue_mutex);
      events.swap(queue);
    }
    for (auto& [event, device] : events) {
      if (event == UsbEvent::kArrived) {
        if (known.count(device) == 0 && IsUsb3Vision(device)) {
          UsbDeviceInfo info;
          libusb_device_descriptor d;
          if (libusb_get_device_descriptor(device, &d) == 0) {
            info.vendor_id = d.idVendor;
            info.product_id = d.idProduct;
            libusb_device_handle* h = nullptr;
            if (d.iSerialNumber != 0 && libusb_open(device, &h) == 0) {
              unsigned char buf[256];
              const int n = libusb_get_string_descriptor_ascii(h, d.iSerialNumber, buf, sizeof buf);
              if (n > 0) info.serial.assign(reinterpret_cast<char*>(buf), n);
              libusb_close(h);
            }
          }
          info.bus = libusb_get_bus_number(device);
          info.address = libusb_get_device_address(device);
          known.emplace(libusb_ref_device(device), info);
          owner->Deliver(UsbEvent::kArrived, info);
        }
      } else {
        auto it = known.find(device);
        if (it != known.end()) {
          const UsbDeviceInfo info = it->second;
          libusb_unref_device(it->first);
          known.erase(it);
          owner->Deliver(UsbEvent::kLeft, info);
        }
      }
      libusb_unref_device(device);
    }
  }

  void Run() {
    while (!stop.load()) {
      timeval tv{0, 100000};
      libusb_handle_events_timeout_completed(context, &tv, nullptr);
      Process();
    }
  }

  void Shutdown() {
    stop = true;
    if (registered) {
      libusb_hotplug_deregister_callback(context, handle);  // also wakes the event thread
      registered = false;
    }
    if (thread.joinable()) thread.join();
    {
      std::lock_guard<std::mutex> lock(queue_mutex);
      for (auto& e : queue) libusb_unref_device(e.second);
      queue.clear();
    }
    for (auto& k : known) libusb_unref_device(k.first);
    known.clear();
    if (context != nullptr) libusb_exit(context);
    context = nullptr;
  }
};

UsbHotplugMonitor::UsbHotplugMonitor(UsbHotplugCallback callback)
    : callback_(std::move(callback)) {}

UsbHotplugMonitor::~UsbHotplugMonitor() { Stop(); }

Status UsbHotplugMonitor::Start() {
  if (running_.load()) return Status::Ok();
  auto impl = std::make_unique<Impl>();
  impl->owner = this;
  int rc = libusb_init(&impl->context);
  if (rc != 0) {
    impl->context = nullptr;
    return Status::Error(std::string("USB hot-plug: libusb_init failed: ") +
                         libusb_strerror(static_cast<libusb_error>(rc)) +
                         " (no USB support here: USB3 Vision cameras are reopened by polling)");
  }
  if (!libusb_has_capability(LIBUSB_CAP_HAS_HOTPLUG)) {
    impl->Shutdown();
    return Status::Error(
        "USB hot-plug: this libusb has no hot-plug support (LIBUSB_CAP_HAS_HOTPLUG is false); "
        "USB3 Vision cameras are reopened by polling instead");
  }
  rc = libusb_hotplug_register_callback(
      impl->context,
      static_cast<libusb_hotplug_event>(LIBUSB_HOTPLUG_EVENT_DEVICE_ARRIVED |
                                        LIBUSB_HOTPLUG_EVENT_DEVICE_LEFT),
      LIBUSB_HOTPLUG_ENUMERATE, LIBUSB_HOTPLUG_MATCH_ANY, LIBUSB_HOTPLUG_MATCH_ANY,
      LIBUSB_HOTPLUG_MATCH_ANY, &Impl::OnHotplug, impl.get(), &impl->handle);
  if (rc != LIBUSB_SUCCESS) {
    impl->Shutdown();
    return Status::Error(std::string("USB hot-plug: cannot register the callback: ") +
                         libusb_strerror(static_cast<libusb_error>(rc)));
  }
  impl->registered = true;
  Impl* raw = impl.get();
  impl->thread = std::thread([raw] { raw->Run(); });
  impl_ = std::move(impl);
  running_ = true;
  return Status::Ok();
}

void UsbHotplugMonitor::Stop() {
  if (impl_) impl_->Shutdown();
  impl_.reset();
  running_ = false;
}

void UsbHotplugMonitor::Inject(UsbEvent event, const UsbDeviceInfo& device) {
  Deliver(event, device);
}

void UsbHotplugMonitor::Deliver(UsbEvent event, const UsbDeviceInfo& device) {
  std::lock_guard<std::mutex> lock(callback_mutex_);
  if (callback_) callback_(event, device);
}

std::size_t UsbfsBytesNeeded(int cameras, const CameraSettings& settings, int width, int height) {
  const int w = settings.roi_width > 0 ? settings.roi_width : width;
  const int h = settings.roi_height > 0 ? settings.roi_height : height;
  return static_cast<std::size_t>(std::max(cameras, 0)) * std::max(settings.buffer_count, 0) *
         static_cast<std::size_t>(w) * h * BytesPerPixel(settings.pixel_format);
}

Status CheckUsbfsMemory(std::size_t needed_bytes, const std::string& path) {
  std::ifstream in(path);
  if (!in) {
    return Status::Error("usbfs memory: cannot read " + path + " (" + std::strerror(errno) +
                         "); is the usbcore module loaded?");
  }
  std::string text;
  std::getline(in, text);
  std::istringstream parse(text);
  long long mb = -1;
  if (!(parse >> mb) || mb < 0) {
    return Status::Error("usbfs memory: " + path + " holds '" + text + "', not a number of MB");
  }
  if (mb == 0) return Status::Ok();  // 0 = no limit
  const double needed_mb = static_cast<double>(needed_bytes) / (1024.0 * 1024.0);
  if (static_cast<double>(mb) >= needed_mb) return Status::Ok();
  // Suggest at least 1000 MB (the usual advice), or double what the rig needs.
  const long long suggest = std::max<long long>(1000, static_cast<long long>(std::ceil(needed_mb * 2 / 100.0)) * 100);
  const std::string s = std::to_string(suggest);
  char need[32];
  std::snprintf(need, sizeof need, "%.0f", std::ceil(needed_mb));
  return Status::Error("usbfs memory: the limit is " + std::to_string(mb) + " MB (" + path +
                       "), too small for the USB cameras' stream buffers (" + need +
                       " MB): frames will be lost. Raise it now with `echo " + s + " > " + path +
                       "` (as root), and at every boot with the kernel parameter "
                       "usbcore.usbfs_memory_mb=" + s);
}

}  // namespace mocap::drivers
