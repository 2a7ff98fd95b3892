// libFuzzer target for the C3D reader: any bytes must give a Status, never a crash, an
// out-of-bounds read (AddressSanitizer) or undefined behaviour (UBSan); a trial that loads must
// be consistent (sizes agree, names unique and non-empty), else the target aborts.
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <set>
#include <string>
#include <string_view>

#include "formats/c3d.h"

namespace {

void Check(bool ok) {
  if (!ok) std::abort();
}

void CheckTrial(const mocap::formats::MarkerTrial& t) {
  Check(t.num_markers() > 0);
  Check(t.positions.cols() == 3 * static_cast<Eigen::Index>(t.num_markers()));
  Check(static_cast<int>(t.frame_numbers.size()) == t.num_frames());
  Check(static_cast<int>(t.times.size()) == t.num_frames());
  Check(t.rate_hz > 0.0);
  std::set<std::string> names;
  for (const std::string& n : t.marker_names) Check(!n.empty() && names.insert(n).second);
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string_view bytes(reinterpret_cast<const char*>(data), size);
  for (bool strip : {true, false}) {
    mocap::formats::C3dReadOptions options;
    options.strip_label_prefix = strip;
    mocap::formats::MarkerTrial trial;
    const mocap::Status s = mocap::formats::ParseC3d(bytes, "fuzz.c3d", &trial, options);
    if (s.ok()) {
      CheckTrial(trial);
    } else {
      Check(s.message().rfind("fuzz.c3d: ", 0) == 0);  // every error names the file
    }
  }
  return 0;
}
