#include "formats/c3d.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdint>
#include <cstring>
#include <limits>
#include <initializer_list>
#include <map>
#include <set>
#include <tuple>
#include <utility>
#include <vector>

#include "formats/text_util.h"

namespace mocap::formats {

using detail::Quote;

namespace {

constexpr size_t kBlock = 512;
constexpr unsigned char kKey = 0x50;  // second byte of the header and of the parameter section

// ------------------------------------------------------------------ byte order and float formats

// VAX F float (DEC processor type): the 32 bits are two little-endian 16-bit words, the first
// holding sign, 8-bit exponent (bias 128) and the high mantissa bits; the value is 0.1m x 2^(e-128),
// i.e. 1.m x 2^(e-129). Exponent 0 is zero (sign 0) or the reserved operand (sign 1, here NaN).
double DecodeVax(const unsigned char* p) {
  const uint32_t bits = (static_cast<uint32_t>(p[0] | p[1] << 8) << 16) |
                        static_cast<uint32_t>(p[2] | p[3] << 8);
  const int exponent = static_cast<int>((bits >> 23) & 0xff);
  const bool negative = (bits >> 31) != 0;
  if (exponent == 0) return negative ? std::numeric_limits<double>::quiet_NaN() : 0.0;
  const double value = std::ldexp(1.0 + (bits & 0x7fffff) / 8388608.0, exponent - 129);
  return negative ? -value : value;
}

// Reads 16-bit integers and floats in the file's processor format. All offsets are checked by
// the caller.
struct Decoder {
  C3dProcessor processor = C3dProcessor::kIntel;

  uint16_t U16(const unsigned char* p) const {
    return processor == C3dProcessor::kMips ? static_cast<uint16_t>(p[0] << 8 | p[1])
                                            : static_cast<uint16_t>(p[0] | p[1] << 8);
  }
  int16_t I16(const unsigned char* p) const { return static_cast<int16_t>(U16(p)); }
  double F32(const unsigned char* p) const {
    uint32_t bits = 0;
    switch (processor) {
      case C3dProcessor::kDec:
        return DecodeVax(p);
      case C3dProcessor::kMips:
        bits = static_cast<uint32_t>(p[0]) << 24 | static_cast<uint32_t>(p[1]) << 16 |
               static_cast<uint32_t>(p[2]) << 8 | p[3];
        break;
      case C3dProcessor::kIntel:
        bits = static_cast<uint32_t>(p[3]) << 24 | static_cast<uint32_t>(p[2]) << 16 |
               static_cast<uint32_t>(p[1]) << 8 | p[0];
        break;
    }
    float f;
    std::memcpy(&f, &bits, sizeof f);
    return f;
  }
};

// Writes 16-bit integers and floats in a processor format (the inverse of Decoder).
struct Encoder {
  C3dProcessor processor = C3dProcessor::kIntel;
  std::string* out = nullptr;

  void U16(uint16_t v) const {
    if (processor == C3dProcessor::kMips) {
      out->push_back(static_cast<char>(v >> 8));
      out->push_back(static_cast<char>(v & 0xff));
    } else {
      out->push_back(static_cast<char>(v & 0xff));
      out->push_back(static_cast<char>(v >> 8));
    }
  }
  void I16(int v) const { U16(static_cast<uint16_t>(static_cast<int16_t>(v))); }
  void F32(float v) const {
    uint32_t bits;
    if (processor == C3dProcessor::kDec) {
      // The VAX value of the word-swapped IEEE bits is a quarter of the IEEE value; a zero (or
      // an IEEE denormal, below VAX's range) is stored as VAX zero.
      const float q = v * 4.0f;
      std::memcpy(&bits, &q, sizeof bits);
      if (((bits >> 23) & 0xff) == 0) bits = 0;
      U16(static_cast<uint16_t>(bits >> 16));
      U16(static_cast<uint16_t>(bits & 0xffff));
      return;
    }
    std::memcpy(&bits, &v, sizeof bits);
    if (processor == C3dProcessor::kMips) {
      U16(static_cast<uint16_t>(bits >> 16));
      U16(static_cast<uint16_t>(bits & 0xffff));
    } else {
      U16(static_cast<uint16_t>(bits & 0xffff));
      U16(static_cast<uint16_t>(bits >> 16));
    }
  }
};

std::string Upper(std::string_view s) {
  std::string u(s);
  for (char& c : u) {
    if (c >= 'a' && c <= 'z') c = static_cast<char>(c - 'a' + 'A');
  }
  return u;
}

// Removes trailing spaces and NULs (C3D pads character arrays with spaces; some writers use 0).
std::string_view TrimRight(std::string_view s) {
  while (!s.empty() && (s.back() == ' ' || s.back() == '\0')) s.remove_suffix(1);
  return s;
}

// ------------------------------------------------------------------ the reader

enum ParamType { kChar = -1, kByte = 1, kInt16 = 2, kFloat = 4 };

struct Param {
  int group_id = 0;
  std::string name;        // upper case
  int type = 0;
  std::vector<int> dims;
  size_t data = 0;         // byte offset of the values in the file
  size_t count = 0;        // number of elements (product of dims; 1 for a scalar)
};

class Reader {
 public:
  Reader(std::string_view bytes, const std::string& path)
      : b_(reinterpret_cast<const unsigned char*>(bytes.data())), size_(bytes.size()), path_(path) {}

  Status Read(const C3dReadOptions& options, MarkerTrial* trial);

 private:
  Status Error(const std::string& where, const std::string& message) const {
    return Status::Error(path_ + ": " + where + ": " + message);
  }
  std::string GroupName(int id) const {
    auto it = groups_.find(id);
    return it != groups_.end() ? it->second : "#" + std::to_string(id);
  }
  std::string ParamWhere(const Param& p) const {
    return "parameter section, group " + GroupName(p.group_id) + ", parameter " + p.name;
  }
  const Param* Find(const std::string& group, const std::string& name) const {
    for (const Param& p : params_) {
      if (p.name == name && GroupName(p.group_id) == group) return &p;
    }
    return nullptr;
  }

  Status ParseParameters();
  // Element `i` of a numeric parameter as an unsigned count (int16 read as uint16: counts past
  // 32767 are stored that way) or as a real number.
  Status HasValue(const Param& p, size_t i) const;
  Status Unsigned(const Param& p, size_t i, uint32_t* value) const;
  Status Real(const Param& p, size_t i, double* value) const;
  // The strings of a character parameter: the first dimension is the length.
  Status Strings(const Param& p, std::vector<std::string>* out) const;
  Status Labels(size_t points, std::vector<std::string>* labels) const;

  const unsigned char* b_;
  size_t size_;
  const std::string& path_;
  Decoder dec_;
  size_t param_begin_ = 0, param_end_ = 0;
  std::map<int, std::string> groups_;
  std::vector<Param> params_;
};

Status Reader::ParseParameters() {
  size_t pos = param_begin_ + 4;
  while (pos + 2 <= param_end_) {
    const int name_len = static_cast<int8_t>(b_[pos]);  // negative: locked
    const int id = static_cast<int8_t>(b_[pos + 1]);     // negative: group; positive: its parameter
    if (name_len == 0 || id == 0) break;                 // end of the list
    const std::string at = " (byte " + std::to_string(pos) + ")";
    const size_t n = static_cast<size_t>(std::abs(name_len));
    const size_t offset_at = pos + 2 + n;
    if (offset_at + 2 > param_end_) {
      return Error("parameter section" + at,
                   "item name runs past the end of the parameter section (byte " +
                       std::to_string(param_end_) + ")");
    }
    const std::string name =
        Upper(std::string_view(reinterpret_cast<const char*>(b_ + pos + 2), n));
    const std::string where = id < 0 ? "parameter section, group " + name + at
                                     : "parameter section, group " + GroupName(id) +
                                           ", parameter " + name + at;
    const uint16_t step = dec_.U16(b_ + offset_at);
    const size_t next = offset_at + step;
    if (step != 0 && next > param_end_) {
      return Error(where, "the offset to the next item (" + std::to_string(step) +
                              ") points to byte " + std::to_string(next) +
                              ", past the end of the parameter section (byte " +
                              std::to_string(param_end_) + ")");
    }
    const size_t q = offset_at + 2;
    if (id < 0) {
      groups_.emplace(-id, name);  // the first definition wins
    } else {
      if (q + 2 > param_end_) {
        return Error(where, "type and dimensions run past the end of the parameter section");
      }
      Param p;
      p.group_id = id;
      p.name = name;
      p.type = static_cast<int8_t>(b_[q]);
      const size_t ndims = b_[q + 1];
      if (p.type != kChar && p.type != kByte && p.type != kInt16 && p.type != kFloat) {
        return Error(where, "data type " + std::to_string(p.type) +
                                " is not -1 (char), 1 (byte), 2 (int16) or 4 (float)");
      }
      if (ndims > 7) {
        return Error(where, std::to_string(ndims) + " dimensions (at most 7 are allowed)");
      }
      if (q + 2 + ndims > param_end_) {
        return Error(where, "dimensions run past the end of the parameter section");
      }
      uint64_t count = 1;  // at most 255^7 = 7e16: no overflow in 64 bits
      for (size_t d = 0; d < ndims; ++d) {
        p.dims.push_back(b_[q + 2 + d]);
        count *= b_[q + 2 + d];
      }
      p.data = q + 2 + ndims;
      const uint64_t data_bytes = count * static_cast<uint64_t>(std::abs(p.type));
      if (data_bytes > param_end_ - p.data) {
        return Error(where, "its " + std::to_string(data_bytes) + " bytes of data (from byte " +
                                std::to_string(p.data) +
                                ") run past the end of the parameter section (byte " +
                                std::to_string(param_end_) + ")");
      }
      p.count = static_cast<size_t>(count);
      params_.push_back(std::move(p));
    }
    if (step == 0) break;  // the last item
    pos = next;            // always forward: the walk ends
  }
  return Status::Ok();
}

Status Reader::HasValue(const Param& p, size_t i) const {
  if (i < p.count) return Status::Ok();
  return Error(ParamWhere(p), "has " + std::to_string(p.count) + " values, expected at least " +
                                  std::to_string(i + 1));
}

Status Reader::Unsigned(const Param& p, size_t i, uint32_t* value) const {
  if (Status s = HasValue(p, i); !s.ok()) return s;
  switch (p.type) {
    case kByte: *value = b_[p.data + i]; return Status::Ok();
    case kInt16: *value = dec_.U16(b_ + p.data + 2 * i); return Status::Ok();
    case kFloat: {
      const double v = dec_.F32(b_ + p.data + 4 * i);
      if (!(v >= 0.0 && v <= 4294967295.0) || v != std::floor(v)) {
        return Error(ParamWhere(p), "value " + std::to_string(v) + " is not a count");
      }
      *value = static_cast<uint32_t>(v);
      return Status::Ok();
    }
    default: return Error(ParamWhere(p), "is text, expected a number");
  }
}

Status Reader::Real(const Param& p, size_t i, double* value) const {
  if (Status s = HasValue(p, i); !s.ok()) return s;
  switch (p.type) {
    case kByte: *value = b_[p.data + i]; return Status::Ok();
    case kInt16: *value = dec_.I16(b_ + p.data + 2 * i); return Status::Ok();
    case kFloat: *value = dec_.F32(b_ + p.data + 4 * i); return Status::Ok();
    default: return Error(ParamWhere(p), "is text, expected a number");
  }
}

Status Reader::Strings(const Param& p, std::vector<std::string>* out) const {
  if (p.type != kChar) return Error(ParamWhere(p), "is a number, expected text");
  out->clear();
  const size_t len = p.dims.empty() ? 1 : static_cast<size_t>(p.dims[0]);
  if (len == 0) return Status::Ok();
  for (size_t k = 0; k < p.count / len; ++k) {
    out->emplace_back(TrimRight(
        std::string_view(reinterpret_cast<const char*>(b_ + p.data + k * len), len)));
  }
  return Status::Ok();
}

// POINT:LABELS, then LABELS2, LABELS3, ... until `points` labels are found or one is absent.
Status Reader::Labels(size_t points, std::vector<std::string>* labels) const {
  labels->clear();
  for (int k = 1; labels->size() < points; ++k) {
    const Param* p = Find("POINT", k == 1 ? "LABELS" : "LABELS" + std::to_string(k));
    if (p == nullptr) break;
    std::vector<std::string> more;
    if (Status s = Strings(*p, &more); !s.ok()) return s;
    for (std::string& m : more) {
      if (labels->size() < points) labels->push_back(std::move(m));
    }
  }
  return Status::Ok();
}

Status Reader::Read(const C3dReadOptions& options, MarkerTrial* trial) {
  // ---- header block and parameter section bounds
  if (size_ < kBlock) {
    return Error("header", "truncated: the file has " + std::to_string(size_) +
                               " bytes, a C3D header alone has 512");
  }
  if (b_[1] != kKey) {
    char hex[8];
    std::snprintf(hex, sizeof hex, "0x%02X", b_[1]);
    return Error("header (byte 1)", std::string("not a C3D file: the key byte is ") + hex +
                                        ", expected 0x50");
  }
  const size_t param_block = b_[0];
  if (param_block < 2) {
    return Error("header (byte 0)", "the parameter section's first block is " +
                                        std::to_string(param_block) + " (expected 2 or more)");
  }
  param_begin_ = (param_block - 1) * kBlock;
  const std::string section_at =
      "parameter section (block " + std::to_string(param_block) + ", byte " +
      std::to_string(param_begin_) + ")";
  if (param_begin_ + 4 > size_) {
    return Error(section_at, "truncated: the file ends at byte " + std::to_string(size_));
  }
  const int processor = b_[param_begin_ + 3];
  if (processor < 84 || processor > 86) {
    return Error(section_at, "unknown processor type " + std::to_string(processor) +
                                 " (expected 84 Intel, 85 DEC or 86 MIPS)");
  }
  dec_.processor = static_cast<C3dProcessor>(processor);
  const size_t param_blocks = b_[param_begin_ + 2];
  if (param_blocks == 0) return Error(section_at, "its block count is 0");
  param_end_ = param_begin_ + param_blocks * kBlock;
  if (param_end_ > size_) {
    return Error(section_at, "truncated: its " + std::to_string(param_blocks) +
                                 " blocks end at byte " + std::to_string(param_end_) +
                                 " but the file has only " + std::to_string(size_) + " bytes");
  }
  if (Status s = ParseParameters(); !s.ok()) return s;

  // ---- header words, overridden by parameters where those are the better source
  auto word = [&](int w) { return dec_.U16(b_ + 2 * (w - 1)); };  // 1-based as in the standard
  const Param* p_used = Find("POINT", "USED");
  uint32_t points = word(2);
  if (p_used != nullptr) {
    if (Status s = Unsigned(*p_used, 0, &points); !s.ok()) return s;
  }
  if (points == 0) {
    return Error(p_used ? ParamWhere(*p_used) : "header (word 2)",
                 "the file has no 3D points (the number of points is 0)");
  }

  double scale = dec_.F32(b_ + 12);  // words 7-8
  std::string scale_where = "header (words 7-8)";
  if (const Param* p = Find("POINT", "SCALE")) {
    if (Status s = Real(*p, 0, &scale); !s.ok()) return s;
    scale_where = ParamWhere(*p);
  }
  if (!std::isfinite(scale) || scale == 0.0) {
    return Error(scale_where, "point scale " + std::to_string(scale) +
                                  " is not a non-zero number (its sign tells floats from "
                                  "integers)");
  }
  const bool floats = scale < 0.0;

  double rate = dec_.F32(b_ + 20);  // words 11-12
  std::string rate_where = "header (words 11-12)";
  if (const Param* p = Find("POINT", "RATE")) {
    if (Status s = Real(*p, 0, &rate); !s.ok()) return s;
    rate_where = ParamWhere(*p);
  }
  if (!std::isfinite(rate) || !(rate > 0.0)) {
    return Error(rate_where, "frame rate " + std::to_string(rate) + " is not a positive number");
  }

  double units_per_metre = 1000.0;  // the standard's default unit is mm
  if (const Param* p = Find("POINT", "UNITS")) {
    std::vector<std::string> units;
    if (Status s = Strings(*p, &units); !s.ok()) return s;
    const std::string_view u = units.empty() ? std::string_view() : detail::Trim(units[0]);
    units_per_metre = detail::UnitsPerMetre(u);
    if (units_per_metre == 0.0) {
      return Error(ParamWhere(*p), "units " + Quote(u) + " are not supported (expected mm, cm or m)");
    }
  }

  // Analog samples share the data blocks: skip ANALOG:USED x samples-per-frame values per frame.
  uint32_t analog = word(3);
  if (const Param* p = Find("ANALOG", "USED")) {
    uint32_t channels = 0;
    if (Status s = Unsigned(*p, 0, &channels); !s.ok()) return s;
    const uint32_t per_frame = word(10);
    if (per_frame != 0 || channels == 0) analog = channels * per_frame;  // both < 2^16
  }

  size_t data_block = word(9);
  if (data_block == 0) {
    if (const Param* p = Find("POINT", "DATA_START")) {
      uint32_t v = 0;
      if (Status s = Unsigned(*p, 0, &v); !s.ok()) return s;
      data_block = v;
    }
  }
  if (data_block <= param_block) {
    return Error("header (word 9)", "the data start block " + std::to_string(data_block) +
                                        " is not after the parameter section's first block " +
                                        std::to_string(param_block));
  }

  // Frames: the header's first and last frame; its 16-bit last frame saturates (or wraps) on long
  // trials, where TRIAL:ACTUAL_START/END_FIELD or POINT:FRAMES hold the real numbers.
  uint64_t first = word(4);
  const uint64_t last = word(5);
  const bool header_valid = last + 1 >= first;
  uint64_t frames = header_valid ? last + 1 - first : 0;
  if (last == 0xffff || !header_valid) {
    const Param* ps = Find("TRIAL", "ACTUAL_START_FIELD");
    const Param* pe = Find("TRIAL", "ACTUAL_END_FIELD");
    const Param* pf = Find("POINT", "FRAMES");
    if (ps != nullptr && pe != nullptr) {
      uint32_t s0 = 0, s1 = 0, e0 = 0, e1 = 0;
      for (auto [p, i, v] : {std::tuple{ps, 0, &s0}, std::tuple{ps, 1, &s1},
                             std::tuple{pe, 0, &e0}, std::tuple{pe, 1, &e1}}) {
        if (Status s = Unsigned(*p, i, v); !s.ok()) return s;
      }
      const uint64_t start = s0 | static_cast<uint64_t>(s1) << 16;
      const uint64_t end = e0 | static_cast<uint64_t>(e1) << 16;
      if (end + 1 < start) {
        return Error(ParamWhere(*pe), "the last frame " + std::to_string(end) +
                                          " is before the first frame " + std::to_string(start));
      }
      first = start;
      frames = end + 1 - start;
    } else if (pf != nullptr) {
      uint32_t n = 0;
      if (Status s = Unsigned(*pf, 0, &n); !s.ok()) return s;
      if (n > frames || !header_valid) frames = n;
    } else if (!header_valid) {
      return Error("header (words 4-5)", "the last frame " + std::to_string(last) +
                                             " is before the first frame " + std::to_string(first));
    }
  }
  if (first + frames > static_cast<uint64_t>(std::numeric_limits<int>::max())) {
    return Error("header", "frame numbers " + std::to_string(first) + " + " +
                               std::to_string(frames) + " frames do not fit in an int");
  }

  // ---- data blocks: every frame must lie inside the file before anything is allocated
  const uint64_t word_bytes = floats ? 4 : 2;
  const uint64_t frame_bytes = (4 * static_cast<uint64_t>(points) + analog) * word_bytes;
  const uint64_t data_begin = (data_block - 1) * kBlock;
  const uint64_t available = size_ > data_begin ? size_ - data_begin : 0;
  if (frames > 0 && available / frame_bytes < frames) {
    const uint64_t f = available / frame_bytes;  // first frame that does not fit
    const uint64_t at = data_begin + f * frame_bytes;
    return Error("data block " + std::to_string(at / kBlock + 1) + " (byte " + std::to_string(at) + ")",
                 "truncated: frame " + std::to_string(f + 1) + " of " + std::to_string(frames) +
                     " needs " + std::to_string(frame_bytes) + " bytes but the file ends at byte " +
                     std::to_string(size_));
  }

  std::vector<std::string> labels;
  if (Status s = Labels(points, &labels); !s.ok()) return s;
  labels.resize(points);
  // C3dReadOptions::skip_model_outputs: the labels the model-output groups list, as stored.
  std::set<std::string> outputs;
  if (options.skip_model_outputs)
    for (const char* kind : {"ANGLES", "FORCES", "MOMENTS", "POWERS", "SCALARS", "REACTIONS"}) {
      const Param* p = Find("POINT", kind);
      if (p == nullptr || p->type != kChar) continue;
      std::vector<std::string> listed;
      if (Status s = Strings(*p, &listed); !s.ok()) return s;
      for (const std::string& l : listed)
        if (!l.empty()) outputs.insert(l.substr(l.rfind(':') + 1));  // with or without a subject prefix
    }
  std::vector<uint32_t> kept;  // the points read, file order
  std::vector<std::string> skipped;
  for (uint32_t m = 0; m < points; ++m) {
    if (outputs.count(labels[m].substr(labels[m].rfind(':') + 1)))
      skipped.push_back(labels[m]);
    else
      kept.push_back(m);
  }
  if (kept.empty())
    return Error("parameter section, group POINT",
                 "every one of its " + std::to_string(points) +
                     " points is a model output (listed in ANGLES, FORCES, MOMENTS, POWERS, SCALARS or "
                     "REACTIONS): the file has no markers");
  std::set<std::string> taken;
  for (size_t m = 0; m < points; ++m) {
    std::string name = labels[m];
    if (options.strip_label_prefix) {
      const size_t colon = name.rfind(':');
      if (colon != std::string::npos) name.erase(0, colon + 1);
    }
    if (name.empty()) name = "P" + std::to_string(m + 1);
    if (taken.count(name)) {
      int k = 2;
      while (taken.count(name + "_" + std::to_string(k))) ++k;
      name += "_" + std::to_string(k);
    }
    taken.insert(name);
    labels[m] = std::move(name);
  }

  // Integer coordinates are counts of `scale` file units; floats are file units already.
  const double nan = std::numeric_limits<double>::quiet_NaN();
  const double per_metre = units_per_metre;
  const double unit = floats ? 1.0 : scale;
  MarkerTrial out;
  out.name = detail::FileStem(path_);
  out.rate_hz = rate;
  for (uint32_t k = 0; k < kept.size(); ++k) out.marker_names.push_back(std::move(labels[kept[k]]));
  out.skipped_points = std::move(skipped);
  out.positions.resize(static_cast<Eigen::Index>(frames), 3 * static_cast<Eigen::Index>(kept.size()));
  out.frame_numbers.resize(frames);
  out.times.resize(frames);
  for (uint64_t f = 0; f < frames; ++f) {
    const unsigned char* row = b_ + data_begin + f * frame_bytes;
    out.frame_numbers[f] = static_cast<int>(first + f);
    out.times[f] = (static_cast<double>(first + f) - 1.0) / rate;
    for (uint32_t k = 0; k < kept.size(); ++k) {
      const uint32_t m = kept[k];
      const unsigned char* q = row + 4 * word_bytes * m;
      double xyz[3];
      bool missing;
      if (floats) {
        for (int c = 0; c < 3; ++c) xyz[c] = dec_.F32(q + 4 * c);
        const double residual = dec_.F32(q + 12);
        // The residual word as a signed integer is negative iff the float is <= -1; a NaN
        // (no integer value) counts as invalid too.
        missing = !(residual > -1.0);
        missing |= !std::isfinite(xyz[0]) || !std::isfinite(xyz[1]) || !std::isfinite(xyz[2]);
      } else {
        for (int c = 0; c < 3; ++c) xyz[c] = dec_.I16(q + 2 * c);
        missing = dec_.I16(q + 6) < 0;
      }
      for (int c = 0; c < 3; ++c) {
        out.positions(static_cast<Eigen::Index>(f), 3 * k + c) =
            missing ? nan : xyz[c] * unit / per_metre;
      }
    }
  }
  *trial = std::move(out);
  return Status::Ok();
}

}  // namespace

Status ParseC3d(std::string_view bytes, const std::string& path, MarkerTrial* trial,
                const C3dReadOptions& options) {
  if (trial == nullptr) return Status::Error(path + ": ParseC3d called with a null trial");
  Reader reader(bytes, path);
  return reader.Read(options, trial);
}

Status ReadC3d(const std::string& path, MarkerTrial* trial, const C3dReadOptions& options) {
  if (trial == nullptr) return Status::Error(path + ": ReadC3d called with a null trial");
  std::string bytes;
  if (Status s = detail::ReadWholeFile(path, &bytes); !s.ok()) return s;
  return ParseC3d(bytes, path, trial, options);
}

// ------------------------------------------------------------------ the writer

namespace {

// Builds the linked list of groups and parameters of the parameter section.
class ParamWriter {
 public:
  explicit ParamWriter(C3dProcessor processor) : processor_(processor) {}

  void Group(int id, const std::string& name) {
    Begin(name, -id);
    End();
  }
  void Int16(int group, const std::string& name, int value) {
    BeginParam(name, group, kInt16, {});
    Enc().I16(value);
    End();
  }
  void Float(int group, const std::string& name, float value) {
    BeginParam(name, group, kFloat, {});
    Enc().F32(value);
    End();
  }
  // Two int16 words forming an unsigned 32-bit number, low word first (TRIAL:ACTUAL_*_FIELD).
  void Word32(int group, const std::string& name, uint32_t value) {
    BeginParam(name, group, kInt16, {2});
    Enc().U16(static_cast<uint16_t>(value & 0xffff));
    Enc().U16(static_cast<uint16_t>(value >> 16));
    End();
  }
  // A char array of `strings`, each padded with spaces to the longest (at least 1 character).
  void Strings(int group, const std::string& name, const std::vector<std::string>& strings,
               bool as_array) {
    size_t len = 1;
    for (const std::string& s : strings) len = std::max(len, s.size());
    if (as_array) {
      BeginParam(name, group, kChar, {len, strings.size()});
    } else {
      BeginParam(name, group, kChar, {len});
    }
    for (const std::string& s : strings) body_ += s + std::string(len - s.size(), ' ');
    End();
  }
  // The section: 4-byte header, the items (the last one's offset is 0), zero padding.
  std::string Section(size_t* blocks) const {
    *blocks = (4 + body_.size() + kBlock - 1) / kBlock;
    std::string s;
    s.push_back(1);
    s.push_back(static_cast<char>(kKey));
    s.push_back(static_cast<char>(*blocks & 0xff));
    s.push_back(static_cast<char>(static_cast<int>(processor_)));
    const size_t items = s.size();
    s += body_;
    if (last_offset_ != std::string::npos) {
      s[items + last_offset_] = 0;
      s[items + last_offset_ + 1] = 0;
    }
    s.resize(*blocks * kBlock, '\0');
    return s;
  }

 private:
  void Begin(const std::string& name, int id) {
    body_.push_back(static_cast<char>(name.size()));
    body_.push_back(static_cast<char>(static_cast<int8_t>(id)));
    body_ += name;
    offset_at_ = body_.size();
    body_ += "..";  // offset, filled in by End
  }
  void BeginParam(const std::string& name, int group, ParamType type,
                  std::initializer_list<size_t> dims) {
    Begin(name, group);
    body_.push_back(static_cast<char>(type));
    body_.push_back(static_cast<char>(dims.size()));
    for (size_t d : dims) body_.push_back(static_cast<char>(d));
  }
  Encoder Enc() { return Encoder{processor_, &body_}; }
  // Ends the item with an empty description; its offset points just past it.
  void End() {
    body_.push_back(0);  // description length
    const size_t step = body_.size() - offset_at_;
    std::string fixed;
    Encoder{processor_, &fixed}.U16(static_cast<uint16_t>(step));
    body_[offset_at_] = fixed[0];
    body_[offset_at_ + 1] = fixed[1];
    last_offset_ = offset_at_;
  }

  C3dProcessor processor_;
  std::string body_;
  size_t offset_at_ = 0;
  size_t last_offset_ = std::string::npos;
};

}  // namespace

Status WriteC3d(const std::string& path, const MarkerTrial& trial, const C3dWriteOptions& options) {
  const std::string cannot = path + ": cannot write C3D: ";
  const int nm = trial.num_markers();
  const int nf = trial.num_frames();
  if (nm == 0) return Status::Error(cannot + "the trial has no markers");
  if (nm > 0xffff) return Status::Error(cannot + std::to_string(nm) + " markers (at most 65535)");
  if (trial.positions.cols() != 3 * static_cast<Eigen::Index>(nm)) {
    return Status::Error(cannot + "positions has " + std::to_string(trial.positions.cols()) +
                         " columns but " + std::to_string(nm) + " markers need " +
                         std::to_string(3 * nm));
  }
  if (!trial.frame_numbers.empty() && static_cast<int>(trial.frame_numbers.size()) != nf) {
    return Status::Error(cannot + std::to_string(trial.frame_numbers.size()) +
                         " frame numbers for " + std::to_string(nf) + " frames");
  }
  if (!(trial.rate_hz > 0.0) || !std::isfinite(trial.rate_hz) ||
      !std::isfinite(static_cast<float>(trial.rate_hz))) {
    return Status::Error(cannot + "rate_hz must be a positive number");
  }
  const int first = trial.frame_numbers.empty() ? 1 : trial.frame_numbers.front();
  if (first < 0 || first > 0xffff) {
    return Status::Error(cannot + "the first frame number " + std::to_string(first) +
                         " is outside 0..65535");
  }
  for (int f = 1; f < static_cast<int>(trial.frame_numbers.size()); ++f) {
    if (trial.frame_numbers[f] != trial.frame_numbers[f - 1] + 1) {
      return Status::Error(cannot + "frame numbers must be consecutive (C3D stores only the "
                           "first): frame " + std::to_string(trial.frame_numbers[f - 1]) +
                           " is followed by " + std::to_string(trial.frame_numbers[f]));
    }
  }
  for (const std::string& name : options.angle_points)
    if (trial.FindMarker(name) < 0)
      return Status::Error(cannot + "angle point " + Quote(name) + " is not one of the trial's markers");
  std::set<std::string> seen;
  for (const std::string& name : trial.marker_names) {
    if (name.empty() || name.size() > 255 || TrimRight(name).size() != name.size()) {
      return Status::Error(cannot + "marker name " + Quote(name) +
                           " is empty, longer than 255 characters or ends in a space");
    }
    if (!seen.insert(name).second) {
      return Status::Error(cannot + "marker name " + Quote(name) + " appears more than once");
    }
  }
  double max_mm = 0.0;
  for (int f = 0; f < nf; ++f) {
    for (int m = 0; m < nm; ++m) {
      for (int c = 0; c < 3; ++c) {
        const double v = trial.positions(f, 3 * m + c);
        if (std::isinf(v) || std::fabs(v * 1000.0) > 1e30) {
          return Status::Error(cannot + "frame " + std::to_string(f) + " marker " +
                               trial.marker_names[m] + " has an infinite or huge coordinate");
        }
        // Of the float that is stored, so that rewriting a file read back gives the same scale.
        if (trial.Has(f, m)) max_mm = std::max(max_mm, std::fabs(double{static_cast<float>(v * 1000.0)}));
      }
    }
  }
  // Floats: the scale only serves residuals; integers: 30000 counts for the largest coordinate.
  float scale = static_cast<float>(max_mm > 0.0 ? max_mm / 30000.0 : 0.01);
  if (!(scale > 0.0f)) scale = std::numeric_limits<float>::min();
  if (!options.integer_points) scale = -scale;

  const uint32_t frames = static_cast<uint32_t>(nf);
  ParamWriter params(options.processor);
  enum { kPoint = 1, kAnalog = 2, kTrial = 3 };
  params.Group(kPoint, "POINT");
  params.Int16(kPoint, "USED", nm);
  if (frames <= 0xffff) {
    params.Int16(kPoint, "FRAMES", static_cast<int>(frames));
  } else {
    params.Float(kPoint, "FRAMES", static_cast<float>(frames));
  }
  params.Float(kPoint, "SCALE", scale);
  params.Float(kPoint, "RATE", static_cast<float>(trial.rate_hz));
  params.Strings(kPoint, "UNITS", {"mm"}, false);
  for (int k = 0; 255 * k < nm; ++k) {
    const auto begin = trial.marker_names.begin() + 255 * k;
    const std::vector<std::string> chunk(begin, begin + std::min(255, nm - 255 * k));
    params.Strings(kPoint, k == 0 ? "LABELS" : "LABELS" + std::to_string(k + 1), chunk, true);
  }
  if (!options.angle_points.empty()) params.Strings(kPoint, "ANGLES", options.angle_points, true);
  params.Group(kAnalog, "ANALOG");
  params.Int16(kAnalog, "USED", 0);
  params.Float(kAnalog, "RATE", static_cast<float>(trial.rate_hz));
  if (frames > 0) {  // the 32-bit frame range, for readers of trials past 65535 frames
    params.Group(kTrial, "TRIAL");
    params.Word32(kTrial, "ACTUAL_START_FIELD", static_cast<uint32_t>(first));
    params.Word32(kTrial, "ACTUAL_END_FIELD", static_cast<uint32_t>(first) + frames - 1);
  }
  // DATA_START goes last: its value depends on the section's size, which the parameter's own
  // (fixed) size is part of, so size a copy that has it first.
  size_t blocks = 0;
  {
    ParamWriter probe = params;
    probe.Int16(kPoint, "DATA_START", 0);
    probe.Section(&blocks);
  }
  const size_t data_block = 2 + blocks;
  if (blocks > 255 || data_block > 0xffff) {
    return Status::Error(cannot + "the parameter section needs " + std::to_string(blocks) +
                         " blocks (at most 255): too many or too long marker names");
  }
  params.Int16(kPoint, "DATA_START", static_cast<int>(data_block));
  const std::string section = params.Section(&blocks);

  std::string out;
  Encoder h{options.processor, &out};
  out.reserve((data_block - 1) * kBlock + static_cast<size_t>(nf) * nm * 16 + kBlock);
  out.push_back(2);  // parameter section at block 2
  out.push_back(static_cast<char>(kKey));
  h.U16(static_cast<uint16_t>(nm));
  h.U16(0);  // analog values per frame
  h.U16(static_cast<uint16_t>(first));
  const uint64_t last = static_cast<uint64_t>(first) + frames - 1;
  // 0 frames: last = first - 1 (first is 1 then); past 65535 the word saturates (TRIAL has it).
  h.U16(static_cast<uint16_t>(frames == 0 ? first - 1 : std::min<uint64_t>(last, 0xffff)));
  h.U16(0);  // maximum interpolation gap
  h.F32(scale);
  h.U16(static_cast<uint16_t>(data_block));
  h.U16(0);  // analog samples per frame
  h.F32(static_cast<float>(trial.rate_hz));
  out.resize(kBlock, '\0');
  out += section;

  for (int f = 0; f < nf; ++f) {
    for (int m = 0; m < nm; ++m) {
      const bool has = trial.Has(f, m);
      for (int c = 0; c < 3; ++c) {
        const double mm = has ? trial.positions(f, 3 * m + c) * 1000.0 : 0.0;
        if (options.integer_points) {
          h.I16(static_cast<int>(std::lround(mm / scale)));
        } else {
          h.F32(static_cast<float>(mm));
        }
      }
      if (options.integer_points) {
        h.I16(has ? 0 : -1);
      } else {
        h.F32(has ? 0.0f : -1.0f);
      }
    }
  }
  out.resize((out.size() + kBlock - 1) / kBlock * kBlock, '\0');
  return detail::WriteWholeFile(path, out);
}

}  // namespace mocap::formats
