#include "daemon/rig_setup.h"

#include <algorithm>

#include <chrono>
#include <sstream>
#include <thread>

#include "daemon/startup_checks.h"

namespace mocap::daemon {

drivers::CameraSettings CameraSettingsOf(const DaemonConfig& config, int camera) {
  drivers::CameraSettings s;
  s.frame_rate_hz = config.rate_hz;
  s.exposure_us = config.exposure_us;
  s.gain_db = config.gain_db;
  s.pixel_format = config.pixel_format == "Mono12"         ? drivers::PixelFormat::kMono12
                   : config.pixel_format == "Mono16"       ? drivers::PixelFormat::kMono16
                   : config.pixel_format == "Mono12Packed" ? drivers::PixelFormat::kMono12Packed
                                                           : drivers::PixelFormat::kMono8;
  s.buffer_count = 32;
  s.packet_size = config.packet_size;
  s.packet_delay_ns = config.packet_delay_ns;
  s.packet_resend = config.packet_resend == "always";
  s.socket_buffer_bytes = config.socket_buffer_bytes;
  s.ptp = config.sync == "ptp";  // the simulated rig's fakes have the PTP features then
  drivers::ParsePtpSchedule(config.ptp_schedule, &s.ptp_schedule);  // validated by the config
  if (camera < 0 || camera >= static_cast<int>(config.cameras.size())) return s;
  const CameraConfig& c = config.cameras[camera];
  if (c.exposure_us > 0) s.exposure_us = c.exposure_us;
  if (c.gain_db >= 0) s.gain_db = c.gain_db;
  s.strobe_line = c.strobe_line;
  drivers::ParseUsbMode(c.usb_mode, &s.usb.mode);  // validated by the config
  s.usb.throughput_limit_mb_s = c.usb_throughput_limit_mb_s;
  // A simulated rig has no trigger line (its fakes expose on the host clock's ticks: "trigger"
  // runs as shared-clock); a real camera joining it (config.h), Aravis's GigE fake, does the same.
  if (config.sync == "trigger" && config.simulated_cameras == 0 && c.id != config.trigger_master) {
    s.trigger = drivers::TriggerMode::kHardwareLine;
    s.trigger_line = config.trigger_line;
  }
  std::stringstream features(c.optional);
  for (std::string f; std::getline(features, f, ',');) {
    const auto b = f.find_first_not_of(' '), e = f.find_last_not_of(' ');
    if (b != std::string::npos) s.optional_features.push_back(f.substr(b, e - b + 1));
  }
  return s;
}

CapturePipelineOptions::RigSync RigSyncOf(const DaemonConfig& config) {
  if (config.sync == "free-run") return CapturePipelineOptions::RigSync::kFreeRun;
  if (config.simulated_cameras > 0 || config.sync == "ptp")
    return CapturePipelineOptions::RigSync::kSharedClock;
  return CapturePipelineOptions::RigSync::kTrigger;
}

Status OpenRigCameras(const std::vector<drivers::AravisCamera*>& cameras,
                      const std::vector<drivers::CameraSettings>& settings, int min_cameras,
                      std::vector<MissingCamera>* missing, int* exit_code) {
  missing->clear();
  *exit_code = 0;
  if (settings.size() != cameras.size())
    return Status::Error("OpenRigCameras: " + std::to_string(settings.size()) + " settings for " +
                         std::to_string(cameras.size()) + " cameras");
  for (std::size_t i = 0; i < cameras.size(); ++i) {
    drivers::AravisCamera& cam = *cameras[i];
    const Status st = cam.Open(settings[i]);
    if (st.ok()) continue;
    missing->push_back({static_cast<int>(i), cam.id(), st.message(), cam.DeviceFoundAtOpen()});
    cam.AwaitDevice(settings[i], st.message());
  }
  const int configured = static_cast<int>(cameras.size());
  const int needed = std::clamp(min_cameras, 1, std::max(1, configured));
  const int opened = configured - static_cast<int>(missing->size());
  if (opened >= needed) return Status::Ok();
  std::string list;
  bool all_refused = true;
  for (const MissingCamera& m : *missing) {
    list += (list.empty() ? "" : "; ") + m.why;
    all_refused &= m.device_found;
  }
  *exit_code = all_refused ? kExitConfig : kExitUnavailable;
  return Status::Error(std::to_string(opened) + " of " + std::to_string(configured) +
                       " cameras opened, fewer than min_cameras = " + std::to_string(needed) + ": " +
                       list);
}

}  // namespace mocap::daemon
