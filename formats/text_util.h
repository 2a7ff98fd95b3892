// Internal helpers shared by the TRC, C3D and MOT readers/writers: whole-file I/O, line splitting
// that tolerates LF / CRLF / CR endings, field splitting, strict locale-independent number
// parsing and formatting. Not part of the public formats API.
#pragma once
#include <string>
#include <string_view>
#include <vector>

#include "model/status.h"

namespace mocap::formats::detail {

// Reads the whole file into *text. Error message: "PATH: cannot open file (reason)".
Status ReadWholeFile(const std::string& path, std::string* text);
// Writes text to path (truncating). Error message names the path.
Status WriteWholeFile(const std::string& path, const std::string& text);

// One physical line of a file, without its line terminator; number is 1-based.
struct Line {
  int number = 0;
  std::string_view text;
};
// Splits text into lines; "\r\n", "\n" and a lone "\r" all end a line. A final line without
// terminator is kept; a trailing terminator does not produce an extra empty line.
std::vector<Line> SplitLines(std::string_view text);

// Removes leading and trailing spaces and tabs.
std::string_view Trim(std::string_view s);
bool IsBlank(std::string_view s);

// Splits a line into fields. If the line contains a tab, fields are separated by single tabs
// (so an empty field between two tabs is kept, which is how TRC marks a missing sample);
// otherwise fields are separated by runs of spaces. Each field is trimmed of spaces.
std::vector<std::string_view> SplitFields(std::string_view line);
// Splits a line into the words between runs of spaces and tabs (no empty words). For header
// lines whose words never contain spaces, written with any mix of tabs and spaces.
std::vector<std::string_view> SplitWords(std::string_view line);
// Drops empty fields from the end of `fields`.
void DropTrailingEmpty(std::vector<std::string_view>* fields);

enum class NumberKind { kNumber, kNaN, kInf, kInvalid };
// Parses a whole field as a double (decimal or exponent form, optional leading '+' or '-').
// "nan" (any case, optional sign, optional "(...)" suffix as in "-nan(ind)") -> kNaN;
// "inf"/"infinity" (any case, optional sign) or a literal overflowing a double -> kInf;
// anything else not fully numeric -> kInvalid.
NumberKind ParseDouble(std::string_view field, double* value);
// Parses a whole field as an int (optional sign). Also accepts a double with an integral value
// such as "12.0". Returns false on anything else.
bool ParseInt(std::string_view field, int* value);

bool EqualsIgnoreCase(std::string_view a, std::string_view b);

// File units per metre for a length unit name (any case): mm 1000, cm 100, m 1 (also spelled out:
// millimeters/millimetres, centimeters/centimetres, meters/metres); 0 when the unit is not
// supported. Exact integers, so dividing a value in file units by them rounds correctly.
double UnitsPerMetre(std::string_view units);

// Appends `value` in fixed notation with `decimals` digits after the point (locale-independent).
void AppendFixed(std::string* out, double value, int decimals);
// Appends the shortest decimal form that reads back to exactly `value` (locale-independent).
void AppendShortest(std::string* out, double value);

// "PATH:LINE: message"
std::string At(const std::string& path, int line, const std::string& message);
// The file name without directories and last extension.
std::string FileStem(const std::string& path);
// The file name without directories.
std::string FileName(const std::string& path);
// Quotes a field for an error message, shortened if very long.
std::string Quote(std::string_view field);

}  // namespace mocap::formats::detail
