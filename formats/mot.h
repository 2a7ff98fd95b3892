// OpenSim storage/motion (.mot / .sto) files: a header ending in "endheader", then a
// tab-separated table whose first column is time.
#pragma once
#include <string>

#include "formats/marker_data.h"
#include "model/status.h"

namespace mocap::formats {

Status WriteMot(const std::string& path, const CoordinateTable& table);
// Reads a .mot/.sto (version 1 header with nRows/nColumns/inDegrees, or OpenSim 4 header).
Status ReadMot(const std::string& path, CoordinateTable* table);

}  // namespace mocap::formats
