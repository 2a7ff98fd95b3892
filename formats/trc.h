// TRC (Motion Analysis "PathFileType 4") marker files, as written by OpenSim, OpenCap, Pose2Sim,
// Vicon, Qualisys and Cortex. The reader accepts every file OpenSim's TRCFileAdapter accepts,
// because a lab's files have been checked with OpenSim, not with us: the header lines may be
// padded with any mix of tabs and spaces ("PathFileType  4<TAB>(X/Y/Z) C:\..." is OpenCap's),
// CRLF / CR line ends, trailing tabs, a UTF-8 byte order mark; Units m, mm or cm (or spelled
// out); NumFrames, NumMarkers, CameraRate and the Orig* fields optional; NumFrames may disagree
// with the data rows (OpenSim reads the rows that are there). An empty field (or a row cut short)
// is a missing sample.
#pragma once
#include <string>

#include "formats/marker_data.h"
#include "model/status.h"

namespace mocap::formats {

// Reads a TRC file into `trial` (positions converted to metres). Errors name the file and line
// ("PATH:LINE: ..."). trial.name is the file stem. A sample is missing (NaN in x, y and z) when
// any of its three fields is empty, "nan", or beyond the end of a short row. Rejected: a
// missing or garbled header, no DataRate or Units, Units other than mm/cm/m, no markers, a
// NumMarkers disagreeing with the marker-name line, duplicate marker names, a row with more
// fields than markers, a non-numeric or infinite field. A trial with 0 frames loads. On error
// *trial is left unchanged.
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
