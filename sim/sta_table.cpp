#include "sim/sta_table.h"

#include <nlohmann/json.hpp>
#include <set>

#include "model/json_fields.h"

namespace mocap::sim {
namespace detail {
extern const char kDefaultStaTableJson[];  // generated from sim/default_sta_table.json
}

std::string StaTable::ClassOf(const std::string& marker) const {
  const auto it = marker_class.find(marker);
  return it == marker_class.end() ? std::string() : it->second;
}

double StaTable::RatioOf(const std::string& marker) const {
  const auto it = marker_class.find(marker);
  if (it == marker_class.end()) return unknown_ratio;
  return classes.at(it->second).ratio;  // ParseStaTableJson checked the class exists
}

const std::string& DefaultStaTableJson() {
  static const std::string text(detail::kDefaultStaTableJson);
  return text;
}

const StaTable& DefaultStaTable() {
  static const StaTable table = [] {
    StaTable t;
    Status s = ParseStaTableJson(DefaultStaTableJson(), "default_sta_table.json", &t);
    (void)s;  // the embedded file is checked by tests/test_sim.cpp
    return t;
  }();
  return table;
}

Status ParseStaTableJson(const std::string& text, const std::string& source_name, StaTable* table) {
  using json = nlohmann::json;
  const JsonFields r{source_name};
  json doc;
  MOCAP_RETURN_IF_ERROR(r.Document(text, "mocap-sta-table", 1, &doc));
  for (const auto& [key, value] : doc.items()) {
    static const std::set<std::string> known = {"format",     "version", "name",   "description",
                                                "references", "classes", "markers"};
    if (!known.count(key)) return r.Fail(key, "unknown field");
  }
  StaTable t;
  MOCAP_RETURN_IF_ERROR(r.String(doc, "", "name", &t.name, false));
  MOCAP_RETURN_IF_ERROR(r.String(doc, "", "description", &t.description, false));
  if (doc.contains("references")) {
    const json& refs = doc["references"];
    if (!refs.is_array()) return r.Fail("references", "expected an array of strings");
    for (size_t i = 0; i < refs.size(); ++i) {
      if (!refs[i].is_string())
        return r.Fail("references[" + std::to_string(i) + "]", "expected a string");
      t.references.push_back(refs[i].get<std::string>());
    }
  }
  if (!doc.contains("classes") || !doc["classes"].is_object())
    return r.Fail("classes", doc.contains("classes") ? "expected an object" : "missing");
  for (const auto& [name, c] : doc["classes"].items()) {
    const std::string path = "classes." + name;
    if (!c.is_object()) return r.Fail(path, "expected an object");
    for (const auto& [key, value] : c.items())
      if (key != "ratio" && key != "basis") return r.Fail(path + "." + key, "unknown field");
    StaClass k;
    MOCAP_RETURN_IF_ERROR(r.Number(c, path, "ratio", &k.ratio, true));
    if (!(k.ratio >= 0.0)) return r.Fail(path + ".ratio", "must be >= 0");
    MOCAP_RETURN_IF_ERROR(r.String(c, path, "basis", &k.basis, false));
    t.classes[name] = std::move(k);
  }
  if (!doc.contains("markers") || !doc["markers"].is_object())
    return r.Fail("markers", doc.contains("markers") ? "expected an object" : "missing");
  for (const auto& [marker, c] : doc["markers"].items()) {
    const std::string path = "markers." + marker;
    if (!c.is_string()) return r.Fail(path, "expected a class name");
    const std::string name = c.get<std::string>();
    if (!t.classes.count(name)) return r.Fail(path, "class '" + name + "' is not in classes");
    t.marker_class[marker] = name;
  }
  *table = std::move(t);
  return Status::Ok();
}

}  // namespace mocap::sim
