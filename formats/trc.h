// TRC (Motion Analysis "PathFileType 4") marker files, as written by OpenSim, Vicon, Qualisys
// and Cortex: tab-separated; header lines tolerate trailing tabs and space-padded numbers;
// an empty field (or a row cut short) is a missing sample; Units "mm" or "m".
#pragma once
#include <string>

#include "formats/marker_data.h"
#include "model/status.h"

namespace mocap::formats {

// Reads a TRC file into `trial` (positions converted to metres). Errors name the file and line.
Status ReadTrc(const std::string& path, MarkerTrial* trial);

struct TrcWriteOptions {
  std::string units = "mm";  // "mm" or "m"
  int decimals = 5;
};
// Writes `trial` (metres) as a TRC file. Missing samples are written as empty fields.
Status WriteTrc(const std::string& path, const MarkerTrial& trial,
                const TrcWriteOptions& options = TrcWriteOptions());

}  // namespace mocap::formats
