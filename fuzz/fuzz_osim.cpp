// libFuzzer target for the OpenSim model importer: any bytes must give a Status, never a crash,
// an out-of-bounds read (AddressSanitizer) or undefined behaviour (UBSan); a model that imports
// must be consistent (its kinematics evaluate to finite marker positions at the default pose, and
// it exports and imports back), else the target aborts.
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <string>

#include "formats/osim.h"
#include "model/kinematics.h"

namespace {

void Check(bool ok) {
  if (!ok) std::abort();
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);
  mocap::formats::OsimImport import;
  const mocap::Status s = mocap::formats::ImportOsimText(text, "fuzz.osim", &import);
  if (!s.ok()) {
    Check(s.message().rfind("fuzz.osim", 0) == 0);  // every error names the file
    return 0;
  }
  const mocap::Model& m = import.model;
  Check(static_cast<int>(import.joints.size()) == m.num_joints());
  const mocap::Geometry g(m);
  mocap::ModelData d(m);
  const Eigen::VectorXd z = m.DefaultCoordinates();
  mocap::ForwardKinematics(m, g, z, &d);
  bool finite = z.allFinite();
  for (int k = 0; k < m.num_markers(); ++k) finite = finite && mocap::MarkerPosition(m, g, d, k).allFinite();
  if (!finite) return 0;  // huge or NaN numbers in the file: nothing more to check
  std::string xml;
  const mocap::Status e = mocap::formats::ExportOsimText(m, import, &xml);
  if (!e.ok()) return 0;
  mocap::formats::OsimImport again;
  Check(mocap::formats::ImportOsimText(xml, "fuzz.osim", &again).ok());
  Check(again.model.num_coordinates() == m.num_coordinates());
  Check(again.model.num_markers() == m.num_markers());
  return 0;
}
