// libFuzzer target for mocapd's configuration file (daemon/config.h): any bytes must give a
// Status, never a crash, a leak or undefined behaviour (ASan/UBSan); an error must name the file
// (every error starts with it), and a configuration that parses must be valid by its own
// IsValid and equal to itself under DiffConfig; else the target aborts.
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <string>

#include "daemon/config.h"

namespace {

void Check(bool ok) {
  if (!ok) std::abort();
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string source = "/etc/mocapd/mocapd.toml";
  const std::string text(reinterpret_cast<const char*>(data), size);
  mocap::daemon::DaemonConfig config;
  const mocap::Status s = mocap::daemon::ParseConfig(text, source, &config);
  if (!s.ok()) {
    Check(s.message().rfind(source, 0) == 0);
    Check(config.source.empty());  // a refused file leaves the output untouched
    return 0;
  }
  std::string error;
  Check(config.IsValid(&error));
  Check(mocap::daemon::DiffConfig(config, config).empty());
  Check(config.num_cameras() > 0);
  for (const std::string& d : config.AllowedExportDirs()) Check(!d.empty() && d[0] == '/');
  return 0;
}
