#include "formats/marker_data.h"

#include <cmath>

namespace mocap::formats {

int MarkerTrial::FindMarker(const std::string& marker_name) const {
  for (size_t i = 0; i < marker_names.size(); ++i) {
    if (marker_names[i] == marker_name) return static_cast<int>(i);
  }
  return -1;
}

bool MarkerTrial::Has(int f, int m) const {
  if (f < 0 || f >= num_frames() || m < 0 || 3 * m + 2 >= positions.cols()) return false;
  const double* p = positions.row(f).data() + 3 * m;
  return std::isfinite(p[0]) && std::isfinite(p[1]) && std::isfinite(p[2]);
}

int CoordinateTable::FindColumn(const std::string& column_name) const {
  for (size_t i = 0; i < column_names.size(); ++i) {
    if (column_names[i] == column_name) return static_cast<int>(i);
  }
  return -1;
}

}  // namespace mocap::formats
