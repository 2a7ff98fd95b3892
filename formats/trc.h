// TRC (Motion Analysis "PathFileType 4") marker files, as written by OpenSim, Vicon, Qualisys
// and Cortex: tab-separated; header lines tolerate trailing tabs and space-padded numbers;
// an empty field (or a row cut short) is a missing sample; Units "mm" or "m".
#pragma once
#include <string>

#include "formats/marker_data.h"
#include "model/status.h"

namespace mocap::formats {

// Reads a TRC file into `trial` (positions converted to metres). Errors name the file and line
// ("PATH:LINE: ..."). trial.name is the file stem. A sample is missing (NaN in x, y and z) when
// any of its three fields is empty, "nan", or beyond the end of a short row. Rejected: a
// missing or garbled header, Units other than mm/cm/m, no markers, NumMarkers disagreeing with
// the marker-name line, duplicate marker names, a row with more fields than markers, a
// non-numeric or infinite field, and NumFrames disagreeing with the number of data rows.
// A trial with 0 frames loads. On error *trial is left unchanged.
Status ReadTrc(const std::string& path, MarkerTrial* trial);

struct TrcWriteOptions {
  std::string units = "mm";  // "mm" or "m"
  int decimals = 5;
};
// Writes `trial` (metres) as a TRC file in OpenSim's layout. Missing samples (any of x, y, z
// NaN) are written as three empty fields. Times are written in their shortest exact form; empty
// frame_numbers / times are written as 1..N and f / rate_hz. Rejects infinite values, marker
// names that are empty, duplicated or contain tabs/line breaks, and inconsistent sizes.
Status WriteTrc(const std::string& path, const MarkerTrial& trial,
                const TrcWriteOptions& options = TrcWriteOptions());

}  // namespace mocap::formats
