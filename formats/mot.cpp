#include "formats/mot.h"

#include <cmath>
#include <string_view>
#include <utility>
#include <vector>

#include "formats/text_util.h"

namespace mocap::formats {

using detail::At;
using detail::DropTrailingEmpty;
using detail::EqualsIgnoreCase;
using detail::IsBlank;
using detail::Line;
using detail::NumberKind;
using detail::ParseDouble;
using detail::ParseInt;
using detail::Quote;
using detail::SplitFields;
using detail::Trim;

namespace {

constexpr int kMotDecimals = 8;

// Splits "key=value" (OpenSim) or "key value" (SIMM: "datacolumns 24") into key and value.
bool SplitKeyValue(std::string_view line, std::string_view* key, std::string_view* value) {
  line = Trim(line);
  size_t sep = line.find('=');
  if (sep == std::string_view::npos) sep = line.find_first_of(" \t");
  if (sep == std::string_view::npos) return false;
  *key = Trim(line.substr(0, sep));
  *value = Trim(line.substr(sep + 1));
  return !key->empty();
}

bool ParseYesNo(std::string_view v, bool* out) {
  if (EqualsIgnoreCase(v, "yes") || EqualsIgnoreCase(v, "true") || v == "1") {
    *out = true;
    return true;
  }
  if (EqualsIgnoreCase(v, "no") || EqualsIgnoreCase(v, "false") || v == "0") {
    *out = false;
    return true;
  }
  return false;
}

}  // namespace

Status WriteMot(const std::string& path, const CoordinateTable& table) {
  const int nf = table.num_frames();
  const int nc = static_cast<int>(table.column_names.size());
  if (table.values.cols() != nc) {
    return Status::Error(path + ": cannot write MOT: values has " +
                         std::to_string(table.values.cols()) + " columns but there are " +
                         std::to_string(nc) + " column names");
  }
  if (static_cast<int>(table.times.size()) != nf) {
    return Status::Error(path + ": cannot write MOT: " + std::to_string(table.times.size()) +
                         " times for " + std::to_string(nf) + " rows");
  }
  for (const std::string& name : table.column_names) {
    if (name.empty() || name.find_first_of("\t\r\n ") != std::string::npos ||
        EqualsIgnoreCase(name, "time")) {
      return Status::Error(path + ": cannot write MOT: column name " + Quote(name) +
                           " is empty, contains white space or is 'time'");
    }
  }
  const std::string name = table.name.empty() ? detail::FileStem(path) : table.name;
  if (name.find_first_of("\r\n=") != std::string::npos || Trim(name) == "endheader") {
    return Status::Error(path + ": cannot write MOT: table name " + Quote(name) +
                         " contains a line break or '=', or is 'endheader'");
  }
  for (int r = 0; r < nf; ++r) {
    if (!std::isfinite(table.times[r])) {
      return Status::Error(path + ": cannot write MOT: time of row " + std::to_string(r) +
                           " is not finite");
    }
    for (int c = 0; c < nc; ++c) {
      if (std::isinf(table.values(r, c))) {
        return Status::Error(path + ": cannot write MOT: row " + std::to_string(r) + " column " +
                             table.column_names[c] + " is infinite");
      }
    }
  }

  std::string out;
  out.reserve(static_cast<size_t>(nf + 8) * (nc + 1) * 16);
  out += name + "\n";
  out += "version=1\n";
  out += "nRows=" + std::to_string(nf) + "\n";
  out += "nColumns=" + std::to_string(nc + 1) + "\n";
  out += std::string("inDegrees=") + (table.in_degrees ? "yes" : "no") + "\n";
  out += "endheader\n";
  out += "time";
  for (const std::string& c : table.column_names) out += '\t' + c;
  out += '\n';
  for (int r = 0; r < nf; ++r) {
    detail::AppendFixed(&out, table.times[r], kMotDecimals);
    for (int c = 0; c < nc; ++c) {
      out += '\t';
      const double v = table.values(r, c);
      if (std::isnan(v)) {
        out += "NaN";
      } else {
        detail::AppendFixed(&out, v, kMotDecimals);
      }
    }
    out += '\n';
  }
  return detail::WriteWholeFile(path, out);
}

Status ReadMot(const std::string& path, CoordinateTable* table) {
  if (table == nullptr) return Status::Error(path + ": ReadMot called with a null table");
  std::string text;
  if (Status s = detail::ReadWholeFile(path, &text); !s.ok()) return s;
  const std::vector<Line> lines = detail::SplitLines(text);
  const int eof_line = lines.empty() ? 1 : lines.back().number + 1;

  // Header: everything up to "endheader".
  std::string name;
  bool have_version = false;
  int n_rows = -1, n_columns = -1, n_rows_line = 0, n_columns_line = 0;
  int in_degrees = -1;  // -1: not stated
  size_t i = 0;
  bool first_nonblank = true;
  bool ended = false;
  for (; i < lines.size(); ++i) {
    const Line& line = lines[i];
    const std::string_view t = Trim(line.text);
    if (t.empty()) continue;
    if (t == "endheader") {
      ended = true;
      ++i;
      break;
    }
    std::string_view key, value;
    const bool has_equals = t.find('=') != std::string_view::npos;
    const bool kv = SplitKeyValue(t, &key, &value);
    // The first line is the table name unless it is a key=value line (SIMM: "name xyz").
    if (first_nonblank) {
      first_nonblank = false;
      if (!has_equals) {
        if (kv && EqualsIgnoreCase(key, "name")) {
          name = std::string(value);
        } else {
          name = std::string(t);
        }
        continue;
      }
    }
    if (!kv) continue;  // free text (descriptions) is allowed in the header
    if (EqualsIgnoreCase(key, "version")) {
      int v = 0;
      if (!ParseInt(value, &v)) {
        return Status::Error(At(path, line.number, "version " + Quote(value) + " is not an integer"));
      }
      have_version = true;
    } else if (EqualsIgnoreCase(key, "nRows") || EqualsIgnoreCase(key, "datarows")) {
      if (!ParseInt(value, &n_rows) || n_rows < 0) {
        return Status::Error(At(path, line.number, std::string(key) + " " + Quote(value) +
                                                       " is not a non-negative integer"));
      }
      n_rows_line = line.number;
    } else if (EqualsIgnoreCase(key, "nColumns") || EqualsIgnoreCase(key, "datacolumns")) {
      if (!ParseInt(value, &n_columns) || n_columns < 1) {
        return Status::Error(At(path, line.number, std::string(key) + " " + Quote(value) +
                                                       " is not a positive integer"));
      }
      n_columns_line = line.number;
    } else if (EqualsIgnoreCase(key, "inDegrees")) {
      bool b = false;
      if (!ParseYesNo(value, &b)) {
        return Status::Error(At(path, line.number,
                                "inDegrees " + Quote(value) + " is not yes or no"));
      }
      in_degrees = b ? 1 : 0;
    } else if (EqualsIgnoreCase(key, "name") && has_equals == false && name.empty()) {
      name = std::string(value);
    }
    // Other keys (DataType, OpenSimVersion, range, units, ...) are ignored.
  }
  if (!ended) {
    return Status::Error(At(path, eof_line, "no 'endheader' line: not an OpenSim .mot/.sto file"));
  }

  // Column labels.
  while (i < lines.size() && IsBlank(lines[i].text)) ++i;
  if (i >= lines.size()) {
    return Status::Error(At(path, eof_line, "file ends before the column-label line (time ...)"));
  }
  const Line labels_line = lines[i++];
  std::vector<std::string_view> labels = SplitFields(labels_line.text);
  DropTrailingEmpty(&labels);
  if (labels.empty() || !EqualsIgnoreCase(labels[0], "time")) {
    return Status::Error(At(path, labels_line.number,
                            "expected the column-label line to start with 'time', found " +
                                Quote(labels_line.text)));
  }
  for (size_t j = 1; j < labels.size(); ++j) {
    if (labels[j].empty()) {
      return Status::Error(At(path, labels_line.number,
                              "column " + std::to_string(j + 1) + " has an empty label"));
    }
  }
  const int width = static_cast<int>(labels.size());
  if (n_columns >= 0 && n_columns != width) {
    return Status::Error(At(path, n_columns_line,
                            "nColumns is " + std::to_string(n_columns) +
                                " but the column-label line (line " +
                                std::to_string(labels_line.number) + ") has " +
                                std::to_string(width) + " columns"));
  }

  // Data.
  std::vector<double> data;
  std::vector<double> times;
  if (n_rows > 0) {
    data.reserve(static_cast<size_t>(n_rows) * (width - 1));
    times.reserve(n_rows);
  }
  for (; i < lines.size(); ++i) {
    const Line& line = lines[i];
    if (IsBlank(line.text)) continue;
    auto f = SplitFields(line.text);
    DropTrailingEmpty(&f);
    if (static_cast<int>(f.size()) != width) {
      return Status::Error(At(path, line.number,
                              "row has " + std::to_string(f.size()) + " fields but there are " +
                                  std::to_string(width) + " columns"));
    }
    for (int c = 0; c < width; ++c) {
      double v = 0.0;
      const std::string col = std::string(labels[c]);
      switch (f[c].empty() ? NumberKind::kInvalid : ParseDouble(f[c], &v)) {
        case NumberKind::kNumber:
          break;
        case NumberKind::kNaN:
          if (c == 0) {
            return Status::Error(At(path, line.number, "time is NaN"));
          }
          break;
        case NumberKind::kInf:
          return Status::Error(At(path, line.number,
                                  "column " + col + " is infinite: " + Quote(f[c])));
        case NumberKind::kInvalid:
          return Status::Error(At(path, line.number,
                                  "column " + col + " is not a number: " + Quote(f[c])));
      }
      if (c == 0) {
        times.push_back(v);
      } else {
        data.push_back(v);
      }
    }
  }
  const int rows = static_cast<int>(times.size());
  if (n_rows >= 0 && n_rows != rows) {
    return Status::Error(At(path, n_rows_line,
                            "nRows is " + std::to_string(n_rows) + " but the file has " +
                                std::to_string(rows) + " data rows"));
  }

  CoordinateTable out;
  out.name = name.empty() ? detail::FileStem(path) : name;
  for (int c = 1; c < width; ++c) out.column_names.emplace_back(labels[c]);
  out.times = std::move(times);
  out.values = Eigen::Map<const RowMatrix>(data.data(), rows, width - 1);
  // As OpenSim's Storage: a stated inDegrees wins; a versioned file without it is in radians;
  // an unversioned (SIMM-era) motion file is in degrees.
  out.in_degrees = in_degrees >= 0 ? in_degrees == 1 : !have_version;
  *table = std::move(out);
  return Status::Ok();
}

namespace {
constexpr double kPi = 3.14159265358979323846;
}  // namespace

Status PosesFromTable(const Model& model, const CoordinateTable& table, const std::string& source,
                      Eigen::MatrixXd* z) {
  if (table.values.cols() != static_cast<Eigen::Index>(table.column_names.size()))
    return Status::Error(source + ": the table's columns do not match its labels");
  std::vector<int> column(model.num_coordinates(), -1);
  for (size_t k = 0; k < table.column_names.size(); ++k) {
    const std::string& name = table.column_names[k];
    const int c = model.FindCoordinate(name);
    if (c >= 0) {
      if (column[c] >= 0) return Status::Error(source + ": column '" + name + "' appears twice");
      column[c] = static_cast<int>(k);
      continue;
    }
    bool derived = false;
    for (const DerivedCoordinate& d : model.derived_coordinates()) derived |= d.name == name;
    if (!derived)
      return Status::Error(source + ": column '" + name + "' is not a coordinate of model '" +
                           model.name() + "' (angles of another model?)");
  }
  std::string absent;
  int n_absent = 0;
  for (int c = 0; c < model.num_coordinates(); ++c)
    if (column[c] < 0) {
      if (n_absent < 5) absent += (absent.empty() ? "" : ", ") + model.coordinates()[c].name;
      ++n_absent;
    }
  if (n_absent > 0)
    return Status::Error(source + ": no column for " + std::to_string(n_absent) +
                         " coordinate(s) of model '" + model.name() + "': " + absent +
                         (n_absent > 5 ? ", ..." : ""));
  z->resize(table.num_frames(), model.num_coordinates());
  for (int c = 0; c < model.num_coordinates(); ++c) {
    const double k = model.coordinates()[c].rotational && table.in_degrees ? kPi / 180.0 : 1.0;
    z->col(c) = table.values.col(column[c]) * k;
  }
  return Status::Ok();
}

}  // namespace mocap::formats
