#include "formats/text_util.h"

#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <system_error>

namespace mocap::formats::detail {

Status ReadWholeFile(const std::string& path, std::string* text) {
  std::error_code ec;
  if (std::filesystem::is_directory(path, ec)) {
    return Status::Error(path + ": cannot open file (it is a directory)");
  }
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    return Status::Error(path + ": cannot open file (" + std::strerror(errno) + ")");
  }
  text->assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  if (in.bad()) return Status::Error(path + ": read error");
  return Status::Ok();
}

Status WriteWholeFile(const std::string& path, const std::string& text) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  if (!out) {
    return Status::Error(path + ": cannot create file (" + std::strerror(errno) + ")");
  }
  out.write(text.data(), static_cast<std::streamsize>(text.size()));
  out.close();
  if (!out) return Status::Error(path + ": write error");
  return Status::Ok();
}

std::vector<Line> SplitLines(std::string_view text) {
  std::vector<Line> lines;
  size_t start = 0;
  int number = 1;
  const size_t n = text.size();
  for (size_t i = 0; i < n; ++i) {
    const char c = text[i];
    if (c != '\n' && c != '\r') continue;
    lines.push_back({number++, text.substr(start, i - start)});
    if (c == '\r' && i + 1 < n && text[i + 1] == '\n') ++i;
    start = i + 1;
  }
  if (start < n) lines.push_back({number, text.substr(start)});
  return lines;
}

std::string_view Trim(std::string_view s) {
  size_t b = 0, e = s.size();
  while (b < e && (s[b] == ' ' || s[b] == '\t')) ++b;
  while (e > b && (s[e - 1] == ' ' || s[e - 1] == '\t')) --e;
  return s.substr(b, e - b);
}

bool IsBlank(std::string_view s) { return Trim(s).empty(); }

std::vector<std::string_view> SplitFields(std::string_view line) {
  std::vector<std::string_view> fields;
  if (line.find('\t') != std::string_view::npos) {
    size_t start = 0;
    while (true) {
      const size_t tab = line.find('\t', start);
      if (tab == std::string_view::npos) {
        fields.push_back(Trim(line.substr(start)));
        break;
      }
      fields.push_back(Trim(line.substr(start, tab - start)));
      start = tab + 1;
    }
    return fields;
  }
  return SplitWords(line);  // no tab: the words between runs of spaces
}

std::vector<std::string_view> SplitWords(std::string_view line) {
  std::vector<std::string_view> words;
  size_t i = 0;
  while (i < line.size()) {
    while (i < line.size() && (line[i] == ' ' || line[i] == '\t')) ++i;
    if (i >= line.size()) break;
    const size_t b = i;
    while (i < line.size() && line[i] != ' ' && line[i] != '\t') ++i;
    words.push_back(line.substr(b, i - b));
  }
  return words;
}

void DropTrailingEmpty(std::vector<std::string_view>* fields) {
  while (!fields->empty() && fields->back().empty()) fields->pop_back();
}

bool EqualsIgnoreCase(std::string_view a, std::string_view b) {
  if (a.size() != b.size()) return false;
  for (size_t i = 0; i < a.size(); ++i) {
    char x = a[i], y = b[i];
    if (x >= 'A' && x <= 'Z') x = static_cast<char>(x - 'A' + 'a');
    if (y >= 'A' && y <= 'Z') y = static_cast<char>(y - 'A' + 'a');
    if (x != y) return false;
  }
  return true;
}

double UnitsPerMetre(std::string_view units) {
  for (const char* mm : {"mm", "millimeters", "millimetres", "millimeter", "millimetre"}) {
    if (EqualsIgnoreCase(units, mm)) return 1000.0;
  }
  for (const char* cm : {"cm", "centimeters", "centimetres", "centimeter", "centimetre"}) {
    if (EqualsIgnoreCase(units, cm)) return 100.0;
  }
  for (const char* m : {"m", "meters", "metres", "meter", "metre"}) {
    if (EqualsIgnoreCase(units, m)) return 1.0;
  }
  return 0.0;
}

NumberKind ParseDouble(std::string_view field, double* value) {
  std::string_view s = Trim(field);
  if (s.empty()) return NumberKind::kInvalid;
  std::string_view body = s;
  if (body[0] == '+' || body[0] == '-') body.remove_prefix(1);
  // nan, NaN, -nan, nan(ind), -nan(ind)
  if (body.size() >= 3 && EqualsIgnoreCase(body.substr(0, 3), "nan")) {
    std::string_view rest = body.substr(3);
    if (rest.empty() || (rest.front() == '(' && rest.back() == ')')) {
      *value = std::nan("");
      return NumberKind::kNaN;
    }
    return NumberKind::kInvalid;
  }
  if (EqualsIgnoreCase(body, "inf") || EqualsIgnoreCase(body, "infinity")) {
    return NumberKind::kInf;
  }
  // from_chars rejects a leading '+'; the sign of the number is kept by passing '-' through.
  const char* first = s.data();
  if (*first == '+') {
    ++first;
    if (first == s.data() + s.size() || *first == '-' || *first == '+') return NumberKind::kInvalid;
  }
  const char* last = s.data() + s.size();
  double v = 0.0;
  const auto res = std::from_chars(first, last, v, std::chars_format::general);
  if (res.ec == std::errc::result_out_of_range) {
    // Overflow is an infinite value; underflow is a (denormal or zero) number.
    const double approx = std::strtod(std::string(first, last).c_str(), nullptr);
    if (std::isinf(approx)) return NumberKind::kInf;
    *value = approx;
    return NumberKind::kNumber;
  }
  if (res.ec != std::errc() || res.ptr != last) return NumberKind::kInvalid;
  if (std::isnan(v)) return NumberKind::kNaN;
  if (std::isinf(v)) return NumberKind::kInf;
  *value = v;
  return NumberKind::kNumber;
}

bool ParseInt(std::string_view field, int* value) {
  std::string_view s = Trim(field);
  if (s.empty()) return false;
  const char* first = s.data();
  const char* last = s.data() + s.size();
  if (*first == '+') ++first;
  int v = 0;
  auto res = std::from_chars(first, last, v);
  if (res.ec == std::errc() && res.ptr == last) {
    *value = v;
    return true;
  }
  double d = 0.0;
  if (ParseDouble(s, &d) != NumberKind::kNumber) return false;
  if (d != std::floor(d) || d < -2147483648.0 || d > 2147483647.0) return false;
  *value = static_cast<int>(d);
  return true;
}

void AppendFixed(std::string* out, double value, int decimals) {
  char buf[512];
  const auto res = std::to_chars(buf, buf + sizeof(buf), value, std::chars_format::fixed, decimals);
  if (res.ec == std::errc()) {
    out->append(buf, res.ptr);
  } else {  // absurdly large value: fall back to the shortest form
    AppendShortest(out, value);
  }
}

void AppendShortest(std::string* out, double value) {
  char buf[64];
  const auto res = std::to_chars(buf, buf + sizeof(buf), value);
  out->append(buf, res.ptr);
}

std::string At(const std::string& path, int line, const std::string& message) {
  return path + ":" + std::to_string(line) + ": " + message;
}

std::string FileStem(const std::string& path) {
  return std::filesystem::path(path).stem().string();
}

std::string FileName(const std::string& path) {
  return std::filesystem::path(path).filename().string();
}

std::string Quote(std::string_view field) {
  constexpr size_t kMax = 40;
  if (field.size() > kMax) return "'" + std::string(field.substr(0, kMax)) + "...'";
  return "'" + std::string(field) + "'";
}

}  // namespace mocap::formats::detail
