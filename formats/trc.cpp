#include "formats/trc.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <string_view>
#include <unordered_set>
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
using detail::SplitWords;
using detail::UnitsPerMetre;

namespace {

const char* const kAxis[3] = {"X", "Y", "Z"};

// "X12" / "x12": the coordinate-label line's first label.
bool IsCoordinateLabel(std::string_view f) {
  if (f.size() < 2 || (f[0] != 'X' && f[0] != 'x')) return false;
  for (size_t i = 1; i < f.size(); ++i) {
    if (f[i] < '0' || f[i] > '9') return false;
  }
  return true;
}

struct Header {
  double rate = 0.0;
  int num_frames = -1;   // -1: not given
  int num_markers = -1;  // -1: not given (the marker-name line decides)
  std::string units;
  int values_line = 0;  // line number of the header values line
};

// The values of the header values line, one per key. OpenSim drops empty fields from both lines
// and pairs what is left; writers differ in how they pad (tabs, runs of spaces, both). A value
// left empty between two tabs is kept in its place when the tabs line up with the keys, so that
// "60<TAB><TAB>300..." is read as a CameraRate without a value, not as CameraRate 300.
std::vector<std::string_view> HeaderValues(std::string_view line, size_t num_keys) {
  if (line.find('\t') != std::string_view::npos) {
    std::vector<std::string_view> by_tab = SplitFields(line);
    DropTrailingEmpty(&by_tab);
    if (by_tab.size() <= num_keys) {
      bool words_inside = false;  // "60 60" in one tab field: padded with spaces, not tabs
      for (auto v : by_tab) words_inside |= SplitWords(v).size() > 1;
      if (!words_inside) return by_tab;
    }
  }
  return SplitWords(line);
}

// Parses the keys line and the values line below it. Keys never contain spaces, so the keys are
// the words of their line whatever separates them.
Status ParseHeader(const std::string& path, const Line& keys_line, const Line& values_line,
                   Header* header) {
  const std::vector<std::string_view> keys = SplitWords(keys_line.text);
  const std::vector<std::string_view> values = HeaderValues(values_line.text, keys.size());
  header->values_line = values_line.number;

  bool has_rate_key = false;
  for (auto k : keys) has_rate_key |= EqualsIgnoreCase(k, "DataRate");
  if (!has_rate_key) {
    return Status::Error(At(path, keys_line.number,
                            "expected the header keys line (DataRate CameraRate NumFrames "
                            "NumMarkers Units ...), found " + Quote(keys_line.text)));
  }
  if (values.size() > keys.size()) {
    return Status::Error(At(path, values_line.number,
                            "header values line has " + std::to_string(values.size()) +
                                " fields but the keys line (line " +
                                std::to_string(keys_line.number) + ") has only " +
                                std::to_string(keys.size())));
  }

  bool seen_rate = false, seen_units = false;
  for (size_t j = 0; j < keys.size(); ++j) {
    const std::string key(keys[j]);
    const std::string_view value = j < values.size() ? values[j] : std::string_view();
    auto is = [&](const char* name) { return EqualsIgnoreCase(key, name); };
    if (value.empty()) {
      // Only what the reader cannot do without must have a value: the rate (times, filters) and
      // the units (a guess would scale the subject by 10 or 1000 silently). The counts are
      // checked against the file itself, as OpenSim does.
      if (is("DataRate") || is("Units")) {
        return Status::Error(At(path, values_line.number, "header field " + key + " has no value"));
      }
      continue;
    }
    if (is("Units")) {
      if (UnitsPerMetre(value) == 0.0) {
        return Status::Error(At(path, values_line.number,
                                "Units " + Quote(value) + " is not supported (expected mm, cm or m)"));
      }
      header->units = std::string(value);
      seen_units = true;
    } else if (is("NumFrames") || is("NumMarkers") || is("OrigDataStartFrame") ||
               is("OrigNumFrames")) {
      int n = 0;
      if (!ParseInt(value, &n) || n < 0) {
        return Status::Error(At(path, values_line.number,
                                "header field " + key + " = " + Quote(value) +
                                    " is not a non-negative integer"));
      }
      if (is("NumFrames")) header->num_frames = n;
      if (is("NumMarkers")) header->num_markers = n;
    } else if (is("DataRate") || is("CameraRate") || is("OrigDataRate")) {
      double r = 0.0;
      if (ParseDouble(value, &r) != NumberKind::kNumber || !(r > 0.0)) {
        return Status::Error(At(path, values_line.number,
                                "header field " + key + " = " + Quote(value) +
                                    " is not a positive number"));
      }
      if (is("DataRate")) { header->rate = r; seen_rate = true; }
    }
    // Other keys are kept for forward compatibility and ignored.
  }
  const char* missing = !seen_rate ? "DataRate" : !seen_units ? "Units" : nullptr;
  if (missing) {
    return Status::Error(At(path, keys_line.number,
                            std::string("header has no ") + missing + " field"));
  }
  return Status::Ok();
}

}  // namespace

Status ReadTrc(const std::string& path, MarkerTrial* trial) {
  if (trial == nullptr) return Status::Error(path + ": ReadTrc called with a null trial");
  std::string text;
  if (Status s = detail::ReadWholeFile(path, &text); !s.ok()) return s;
  // A UTF-8 byte order mark (Windows editors) is not part of the first line.
  const std::string_view bom = "\xEF\xBB\xBF";
  const std::string_view body =
      std::string_view(text).substr(std::string_view(text).starts_with(bom) ? bom.size() : 0);
  const std::vector<Line> lines = detail::SplitLines(body);

  size_t i = 0;
  auto skip_blank = [&]() {
    while (i < lines.size() && IsBlank(lines[i].text)) ++i;
    return i < lines.size();
  };
  const int eof_line = lines.empty() ? 1 : lines.back().number + 1;
  auto ends_early = [&](const std::string& what) {
    return Status::Error(At(path, eof_line, "file ends before " + what));
  };

  // 1: PathFileType 4 (X/Y/Z) name
  if (!skip_blank()) {
    return Status::Error(At(path, 1, "empty file (expected a TRC header line 'PathFileType 4 ...')"));
  }
  {
    // Any spaces and tabs after the key: "PathFileType  4<TAB>(X/Y/Z) C:\\..." is OpenCap's.
    auto f = SplitWords(lines[i].text);
    if (f.empty() || !EqualsIgnoreCase(f[0], "PathFileType")) {
      return Status::Error(At(path, lines[i].number,
                              "not a TRC file: expected the header line 'PathFileType 4 (X/Y/Z) "
                              "...', found " + Quote(lines[i].text)));
    }
    ++i;
  }
  // 2-3: keys and values
  if (!skip_blank()) return ends_early("the header keys line (DataRate CameraRate ...)");
  const Line keys_line = lines[i++];
  if (!skip_blank()) return ends_early("the header values line");
  const Line values_line = lines[i++];
  Header header;
  if (Status s = ParseHeader(path, keys_line, values_line, &header); !s.ok()) return s;

  // 4: Frame# Time name1 <tab><tab> name2 ...
  if (!skip_blank()) return ends_early("the marker-name line (Frame# Time ...)");
  const Line names_line = lines[i++];
  std::vector<std::string> names;
  {
    auto f = SplitFields(names_line.text);
    // "Frame# Time<TAB>A<TAB><TAB><TAB>B...": the two column labels padded with spaces.
    if (!f.empty() && SplitWords(f[0]).size() > 1) {
      std::vector<std::string_view> first = SplitWords(f[0]);
      f.erase(f.begin());
      f.insert(f.begin(), first.begin(), first.end());
    }
    if (f.size() < 2 || !EqualsIgnoreCase(f[0], "Frame#") || !EqualsIgnoreCase(f[1], "Time")) {
      return Status::Error(At(path, names_line.number,
                              "expected the marker-name line 'Frame# Time name1 ...', found " +
                                  Quote(names_line.text)));
    }
    std::unordered_set<std::string_view> seen;
    for (size_t j = 2; j < f.size(); ++j) {
      if (f[j].empty()) continue;
      if (!seen.insert(f[j]).second) {
        return Status::Error(At(path, names_line.number,
                                "marker name " + Quote(f[j]) + " appears more than once"));
      }
      names.emplace_back(f[j]);
    }
  }
  if (names.empty()) {
    return Status::Error(At(path, names_line.number, "the file names no markers"));
  }
  if (header.num_markers >= 0 && static_cast<int>(names.size()) != header.num_markers) {
    return Status::Error(At(path, names_line.number,
                            "the marker-name line lists " + std::to_string(names.size()) +
                                " markers but NumMarkers (line " +
                                std::to_string(header.values_line) + ") is " +
                                std::to_string(header.num_markers)));
  }
  const int num_markers = static_cast<int>(names.size());

  // 5: X1 Y1 Z1 X2 ... (optional: some writers leave it out)
  if (skip_blank()) {
    auto f = SplitFields(lines[i].text);
    size_t first = 0;
    while (first < f.size() && f[first].empty()) ++first;
    if (first < f.size() && IsCoordinateLabel(f[first])) {
      ++i;
    } else {
      double dummy;
      if (f.empty() || ParseDouble(f[0], &dummy) != NumberKind::kNumber) {
        return Status::Error(At(path, lines[i].number,
                                "expected the coordinate-label line 'X1 Y1 Z1 ...' or a data row, "
                                "found " + Quote(lines[i].text)));
      }
    }
  }

  // Data rows.
  const double per_metre = UnitsPerMetre(header.units);
  const size_t width = 3 * static_cast<size_t>(num_markers);
  const double nan = std::numeric_limits<double>::quiet_NaN();
  std::vector<double> data;
  std::vector<int> frames;
  std::vector<double> times;
  // NumFrames only sizes the buffers, and no more than the lines left can hold.
  const size_t expected_rows =
      std::min(static_cast<size_t>(std::max(header.num_frames, 0)), lines.size() - i);
  data.reserve(expected_rows * width);
  frames.reserve(expected_rows);
  times.reserve(expected_rows);
  for (; i < lines.size(); ++i) {
    const Line& line = lines[i];
    if (IsBlank(line.text)) continue;
    auto f = SplitFields(line.text);
    DropTrailingEmpty(&f);
    if (f.size() > 2 + width) {
      return Status::Error(At(path, line.number,
                              "data row has " + std::to_string(f.size() - 2) +
                                  " coordinate fields, more than 3 x " +
                                  std::to_string(num_markers) + " markers = " +
                                  std::to_string(width)));
    }
    int frame = 0;
    if (!ParseInt(f[0], &frame)) {
      return Status::Error(At(path, line.number,
                              "Frame# " + Quote(f[0]) + " is not an integer"));
    }
    double time = 0.0;
    if (f.size() < 2 || ParseDouble(f[1], &time) != NumberKind::kNumber) {
      return Status::Error(At(path, line.number,
                              "Time " + Quote(f.size() < 2 ? std::string_view() : f[1]) +
                                  " is not a number"));
    }
    frames.push_back(frame);
    times.push_back(time);
    for (int m = 0; m < num_markers; ++m) {
      double xyz[3];
      bool missing = false;
      for (int c = 0; c < 3; ++c) {
        const size_t idx = 2 + 3 * static_cast<size_t>(m) + c;
        if (idx >= f.size() || f[idx].empty()) {
          missing = true;
          continue;
        }
        switch (ParseDouble(f[idx], &xyz[c])) {
          case NumberKind::kNumber:
            break;
          case NumberKind::kNaN:
            missing = true;
            break;
          case NumberKind::kInf:
            return Status::Error(At(path, line.number,
                                    "marker " + names[m] + " " + kAxis[c] + " (column " +
                                        std::to_string(idx + 1) + ") is infinite: " +
                                        Quote(f[idx])));
          case NumberKind::kInvalid:
            return Status::Error(At(path, line.number,
                                    "marker " + names[m] + " " + kAxis[c] + " (column " +
                                        std::to_string(idx + 1) + ") is not a number: " +
                                        Quote(f[idx])));
        }
      }
      for (int c = 0; c < 3; ++c) data.push_back(missing ? nan : xyz[c] / per_metre);
    }
  }
  // NumFrames is not checked against the rows: OpenSim reads the rows that are there, and
  // writers (Pose2Sim, trimmed exports) leave it stale.
  const int rows = static_cast<int>(frames.size());

  MarkerTrial out;
  out.name = detail::FileStem(path);
  out.rate_hz = header.rate;
  out.marker_names = std::move(names);
  out.frame_numbers = std::move(frames);
  out.times = std::move(times);
  out.positions = Eigen::Map<const RowMatrix>(data.data(), rows, static_cast<Eigen::Index>(width));
  *trial = std::move(out);
  return Status::Ok();
}

Status WriteTrc(const std::string& path, const MarkerTrial& trial, const TrcWriteOptions& options) {
  const std::string& units = options.units;
  if (units != "mm" && units != "m") {
    return Status::Error(path + ": cannot write TRC: units " + Quote(units) +
                         " is not supported (use \"mm\" or \"m\")");
  }
  if (options.decimals < 0 || options.decimals > 15) {
    return Status::Error(path + ": cannot write TRC: decimals " + std::to_string(options.decimals) +
                         " is outside 0..15");
  }
  const int nm = trial.num_markers();
  const int nf = trial.num_frames();
  if (nm == 0) return Status::Error(path + ": cannot write TRC: the trial has no markers");
  if (trial.positions.cols() != 3 * static_cast<Eigen::Index>(nm)) {
    return Status::Error(path + ": cannot write TRC: positions has " +
                         std::to_string(trial.positions.cols()) + " columns but " +
                         std::to_string(nm) + " markers need " + std::to_string(3 * nm));
  }
  if (!trial.frame_numbers.empty() && static_cast<int>(trial.frame_numbers.size()) != nf) {
    return Status::Error(path + ": cannot write TRC: " + std::to_string(trial.frame_numbers.size()) +
                         " frame numbers for " + std::to_string(nf) + " frames");
  }
  if (!trial.times.empty() && static_cast<int>(trial.times.size()) != nf) {
    return Status::Error(path + ": cannot write TRC: " + std::to_string(trial.times.size()) +
                         " times for " + std::to_string(nf) + " frames");
  }
  if (!(trial.rate_hz > 0.0) || !std::isfinite(trial.rate_hz)) {
    return Status::Error(path + ": cannot write TRC: rate_hz must be a positive number");
  }
  std::unordered_set<std::string_view> seen;
  for (const std::string& name : trial.marker_names) {
    if (name.empty() || name.find_first_of("\t\r\n") != std::string::npos ||
        detail::Trim(name) != name) {
      return Status::Error(path + ": cannot write TRC: marker name " + Quote(name) +
                           " is empty or contains tabs, line breaks or edge spaces");
    }
    if (!seen.insert(name).second) {
      return Status::Error(path + ": cannot write TRC: marker name " + Quote(name) +
                           " appears more than once");
    }
  }
  for (int f = 0; f < nf; ++f) {
    if (!trial.times.empty() && !std::isfinite(trial.times[f])) {
      return Status::Error(path + ": cannot write TRC: time of frame " + std::to_string(f) +
                           " is not finite");
    }
    for (int k = 0; k < 3 * nm; ++k) {
      if (std::isinf(trial.positions(f, k))) {
        return Status::Error(path + ": cannot write TRC: frame " + std::to_string(f) + " marker " +
                             trial.marker_names[k / 3] + " " + kAxis[k % 3] + " is infinite");
      }
    }
  }

  const double scale = UnitsPerMetre(units);
  const int first_frame = trial.frame_numbers.empty() ? 1 : trial.frame_numbers.front();
  std::string out;
  out.reserve(static_cast<size_t>(nf + 8) * (24 + 3 * nm * (options.decimals + 8)));
  out += "PathFileType\t4\t(X/Y/Z)\t" + detail::FileName(path) + "\n";
  out += "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\t"
         "OrigNumFrames\n";
  detail::AppendShortest(&out, trial.rate_hz);
  out += '\t';
  detail::AppendShortest(&out, trial.rate_hz);
  out += '\t' + std::to_string(nf) + '\t' + std::to_string(nm) + '\t' + units + '\t';
  detail::AppendShortest(&out, trial.rate_hz);
  out += '\t' + std::to_string(first_frame) + '\t' + std::to_string(nf) + '\n';
  out += "Frame#\tTime";
  for (int m = 0; m < nm; ++m) out += '\t' + trial.marker_names[m] + "\t\t";
  out += "\n\t";
  for (int m = 1; m <= nm; ++m) {
    const std::string k = std::to_string(m);
    out += "\tX" + k + "\tY" + k + "\tZ" + k;
  }
  out += "\n\n";
  for (int f = 0; f < nf; ++f) {
    out += std::to_string(trial.frame_numbers.empty() ? f + 1 : trial.frame_numbers[f]);
    out += '\t';
    detail::AppendShortest(&out, trial.times.empty() ? f / trial.rate_hz : trial.times[f]);
    for (int m = 0; m < nm; ++m) {
      if (!trial.Has(f, m)) {
        out += "\t\t\t";
        continue;
      }
      for (int c = 0; c < 3; ++c) {
        out += '\t';
        detail::AppendFixed(&out, trial.positions(f, 3 * m + c) * scale, options.decimals);
      }
    }
    out += '\n';
  }
  return detail::WriteWholeFile(path, out);
}

}  // namespace mocap::formats
