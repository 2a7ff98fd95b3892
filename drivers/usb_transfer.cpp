#include "drivers/usb_transfer.h"

#include <algorithm>
#include <cmath>
#include <cstdio>

namespace mocap::drivers {
namespace {

constexpr const char* kLimit = "DeviceLinkThroughputLimit";
constexpr const char* kLimitMode = "DeviceLinkThroughputLimitMode";

std::string Mb(double mb_s) {
  char b[32];
  std::snprintf(b, sizeof b, "%g", mb_s);
  return b;
}

}  // namespace

const char* ToString(UsbMode mode) {
  switch (mode) {
    case UsbMode::kDefault: return "default";
    case UsbMode::kSync: return "sync";
    case UsbMode::kAsync: return "async";
  }
  return "?";
}

bool ParseUsbMode(const std::string& text, UsbMode* mode) {
  for (UsbMode m : {UsbMode::kDefault, UsbMode::kSync, UsbMode::kAsync}) {
    if (text == ToString(m)) {
      *mode = m;
      return true;
    }
  }
  return false;
}

bool UsbTransferSettings::IsValid(std::string* error) const {
  if (!(throughput_limit_mb_s >= 0 && throughput_limit_mb_s <= 1e5)) {
    if (error) *error = "usb transfer: throughput_limit_mb_s " + Mb(throughput_limit_mb_s) + " is outside [0, 100000]";
    return false;
  }
  return true;
}

Status RefusedFeature(const std::string& camera_id, const std::string& feature,
                      const std::string& why, const std::vector<std::string>& optional,
                      std::vector<std::string>* refused_optional) {
  if (std::find(optional.begin(), optional.end(), feature) != optional.end()) {
    if (refused_optional) refused_optional->push_back(feature + ": " + why);
    return Status::Ok();
  }
  return Status::Error(camera_id + ": " + feature + ": " + why +
                       " (list it among the camera's optional features if the rig does without)");
}

Status ApplyUsbTransfer(const std::string& camera_id, const UsbTransferSettings& settings,
                        const std::vector<std::string>& optional, UsbTransferDevice* device,
                        AppliedUsbTransfer* applied, std::vector<std::string>* refused_optional) {
  std::string error;
  if (!settings.IsValid(&error)) return Status::Error(camera_id + ": " + error);
  *applied = AppliedUsbTransfer{};
  applied->applied = true;
  device->SetUsbMode(settings.mode);
  applied->mode = ToString(settings.mode);
  auto refused = [&](const char* feature, const std::string& why) {
    return RefusedFeature(camera_id, feature, why, optional, refused_optional);
  };
  auto set_mode = [&](const std::string& value) -> Status {
    if (Status s = device->SetString(kLimitMode, value); !s)
      return refused(kLimitMode, "refused " + value + " (" + s.message() + ")");
    std::string back;
    if (Status s = device->GetString(kLimitMode, &back); !s)
      return refused(kLimitMode, "cannot be read back (" + s.message() + ")");
    applied->throughput_limit_mode = back;
    if (back != value) return refused(kLimitMode, "set to " + value + ", reads back " + back);
    return Status::Ok();
  };

  if (settings.throughput_limit_mb_s <= 0) {
    // Off, so that a limit left on by another program does not throttle the rig unseen.
    if (device->HasFeature(kLimitMode)) MOCAP_RETURN_IF_ERROR(set_mode("Off"));
    return Status::Ok();
  }
  const std::string wanted = Mb(settings.throughput_limit_mb_s) + " MB/s";
  if (!device->HasFeature(kLimit))
    return refused(kLimit, "the camera has no " + std::string(kLimit) + " to hold it to " + wanted);
  const auto bytes = static_cast<std::int64_t>(std::llround(settings.throughput_limit_mb_s * 1e6));
  std::int64_t lo = 0, hi = 0;
  if (Status s = device->IntegerBounds(kLimit, &lo, &hi); !s)
    return refused(kLimit, "cannot read its bounds (" + s.message() + ")");
  if (bytes < lo || bytes > hi)
    return refused(kLimit, wanted + " outside the camera's range " + Mb(lo * 1e-6) + ".." +
                               Mb(hi * 1e-6) + " MB/s");
  if (device->HasFeature(kLimitMode)) MOCAP_RETURN_IF_ERROR(set_mode("On"));
  if (Status s = device->SetInteger(kLimit, bytes); !s)
    return refused(kLimit, "refused " + wanted + " (" + s.message() + ")");
  std::int64_t back = 0;
  if (Status s = device->GetInteger(kLimit, &back); !s)
    return refused(kLimit, "cannot be read back (" + s.message() + ")");
  applied->throughput_limit_mb_s = back * 1e-6;
  if (std::llabs(back - bytes) > bytes / 100)
    return refused(kLimit, "set to " + wanted + ", reads back " + Mb(back * 1e-6) + " MB/s");
  return Status::Ok();
}

}  // namespace mocap::drivers
