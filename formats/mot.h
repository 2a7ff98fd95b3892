// OpenSim storage/motion (.mot / .sto) files: a header ending in "endheader", then a
// tab-separated table whose first column is time.
#pragma once
#include <Eigen/Core>
#include <string>

#include "formats/marker_data.h"
#include "model/model.h"
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

// The rows of a coordinate table (a .mot of OpenSim's IK or Scale tool, `mocap ik`, the
// simulator's truth) as poses of `model`: frames x model.num_coordinates(), in the model's
// coordinate order, radians and metres (rotational columns converted from degrees when
// table.in_degrees). Checked, with errors naming `source`: every coordinate of the model has a
// column; every column is a coordinate or a derived coordinate of the model (another model's
// angles are refused rather than half used). NaN entries are kept.
Status PosesFromTable(const Model& model, const CoordinateTable& table, const std::string& source,
                      Eigen::MatrixXd* z);

}  // namespace mocap::formats
