// Typed reads of JSON object fields whose errors name the source and the field's path
// ("m.json: joints[3].elements[1].axis: expected 3 numbers"). Used by every JSON file mocapd
// reads (model files, protocols).
#pragma once

#include <Eigen/Core>
#include <cmath>
#include <nlohmann/json.hpp>
#include <string>

#include "model/status.h"

namespace mocap {

class JsonFields {
 public:
  using json = nlohmann::json;
  explicit JsonFields(std::string source) : source_(std::move(source)) {}

  // "a.b" from ("a", "b") or ("a.", "b"); "b" from ("", "b").
  static std::string Join(const std::string& path, const std::string& key) {
    if (path.empty() || path.back() == '.') return path + key;
    return path + "." + key;
  }
  Status Fail(const std::string& path, const std::string& what) const {
    return Status::Error(source_ + ": " + (path.empty() ? "(top level)" : path) + ": " + what);
  }
  Status String(const json& obj, const std::string& path, const char* key, std::string* out,
                bool required = true) const {
    if (!obj.contains(key)) return required ? Fail(Join(path, key), "missing") : Status::Ok();
    if (!obj[key].is_string()) return Fail(Join(path, key), "expected a string");
    *out = obj[key].get<std::string>();
    return Status::Ok();
  }
  Status Number(const json& obj, const std::string& path, const char* key, double* out,
                bool required = true) const {
    if (!obj.contains(key)) return required ? Fail(Join(path, key), "missing") : Status::Ok();
    if (!obj[key].is_number()) return Fail(Join(path, key), "expected a number");
    *out = obj[key].get<double>();
    if (!std::isfinite(*out)) return Fail(Join(path, key), "not finite");
    return Status::Ok();
  }
  Status Bool(const json& obj, const std::string& path, const char* key, bool* out) const {
    if (!obj.contains(key)) return Status::Ok();
    if (!obj[key].is_boolean()) return Fail(Join(path, key), "expected true or false");
    *out = obj[key].get<bool>();
    return Status::Ok();
  }
  Status Vec3(const json& obj, const std::string& path, const char* key, Eigen::Vector3d* out,
              bool required = true) const {
    if (!obj.contains(key)) return required ? Fail(Join(path, key), "missing") : Status::Ok();
    const json& v = obj[key];
    if (!v.is_array() || v.size() != 3) return Fail(Join(path, key), "expected 3 numbers");
    for (int i = 0; i < 3; ++i) {
      if (!v[i].is_number()) return Fail(Join(path, key), "expected 3 numbers");
      (*out)[i] = v[i].get<double>();
    }
    if (!out->allFinite()) return Fail(Join(path, key), "not finite");
    return Status::Ok();
  }
  // Parses `text` as a JSON object whose "format" is `format` and whose "version" is `version`:
  // the opening every versioned file of the project shares.
  Status Document(const std::string& text, const std::string& format, double version,
                  json* doc) const {
    try {
      *doc = json::parse(text);
    } catch (const json::parse_error& e) {
      return Status::Error(source_ + ": not valid JSON (byte " + std::to_string(e.byte) +
                           "): " + e.what());
    }
    if (!doc->is_object()) return Fail("", "expected an object");
    std::string found;
    MOCAP_RETURN_IF_ERROR(String(*doc, "", "format", &found, true));
    if (found != format)
      return Fail("format", "expected \"" + format + "\", found \"" + found + "\"");
    double found_version = 0;
    MOCAP_RETURN_IF_ERROR(Number(*doc, "", "version", &found_version, true));
    if (found_version != version)
      return Fail("version", "unsupported version " + (*doc)["version"].dump());
    return Status::Ok();
  }
  Status Array(const json& obj, const std::string& path, const char* key) const {
    if (!obj.contains(key)) return Fail(Join(path, key), "missing");
    if (!obj[key].is_array()) return Fail(Join(path, key), "expected an array");
    return Status::Ok();
  }

 private:
  std::string source_;
};

}  // namespace mocap
