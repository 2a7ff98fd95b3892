// OpenSim storage/motion (.mot / .sto) files: a header ending in "endheader", then a
// tab-separated table whose first column is time.
#pragma once
#include <string>

#include "formats/marker_data.h"
#include "model/status.h"

namespace mocap::formats {

// Writes the OpenSim header (name, version=1, nRows, nColumns incl. time, inDegrees, endheader),
// the "time ..." label line and rows with 8 decimals; NaN is written as "NaN". An empty
// table.name is replaced by the file stem.
Status WriteMot(const std::string& path, const CoordinateTable& table);
// Reads a .mot/.sto (version 1 header with nRows/nColumns/inDegrees, or OpenSim 4 header; also
// OpenSim 3 headers without "version" and SIMM's "datacolumns N"/"datarows N"). The first header
// line is the table name. inDegrees, when absent, follows OpenSim: unversioned files are in
// degrees, versioned ones in radians. "nan" fields load as NaN; errors ("PATH:LINE: ...") for a
// missing endheader, a first label other than time, nRows/nColumns disagreeing with the table,
// rows of the wrong width, and non-numeric or infinite fields. On error *table is unchanged.
Status ReadMot(const std::string& path, CoordinateTable* table);

}  // namespace mocap::formats
