#include "sim/protocol.h"

#include <algorithm>

#include <cmath>
#include <cstdio>
#include <fstream>
#include <limits>
#include <nlohmann/json.hpp>

#include "model/json_fields.h"
#include <set>
#include <sstream>

namespace mocap::sim {
namespace detail {
extern const char kDefaultProtocolJson[];  // generated from sim/default_protocol.json
}

namespace {

using json = nlohmann::json;
constexpr double kRadToDeg = 180.0 / M_PI;

std::string Show(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%g", v);
  return buf;
}

using Reader = JsonFields;
#define MOCAP_TRY MOCAP_RETURN_IF_ERROR

Status ParseExcitation(const Reader& r, const json& e, const std::string& path, Excitation* out) {
  if (!e.is_object()) return r.Fail(path, "expected an object");
  MOCAP_TRY(r.String(e, path, "coordinate", &out->coordinate, true));
  if (out->coordinate.empty()) return r.Fail(path + "coordinate", "empty");
  MOCAP_TRY(r.Number(e, path, "min_deg", &out->min_deg, true));
  MOCAP_TRY(r.Number(e, path, "max_deg", &out->max_deg, true));
  if (out->min_deg > out->max_deg)
    return r.Fail(path + "min_deg", "greater than max_deg (" + Show(out->min_deg) +
                                        " > " + Show(out->max_deg) + ")");
  MOCAP_TRY(r.Bool(e, path, "required", &out->required));
  MOCAP_TRY(r.String(e, path, "follow", &out->follow, false));
  MOCAP_TRY(r.Bool(e, path, "anti_phase", &out->anti_phase));
  if (out->anti_phase && out->follow.empty())
    return r.Fail(path + "anti_phase", "only meaningful with \"follow\"");
  if (e.contains("window")) {
    const json& w = e["window"];
    if (!w.is_array() || w.size() != 2 || !w[0].is_number() || !w[1].is_number())
      return r.Fail(path + "window", "expected [begin, end] as fractions of the duration");
    out->window_begin = w[0].get<double>();
    out->window_end = w[1].get<double>();
    if (!(out->window_begin >= 0.0 && out->window_begin < out->window_end &&
          out->window_end <= 1.0))
      return r.Fail(path + "window", "expected 0 <= begin < end <= 1");
  }
  for (const auto& [key, value] : e.items()) {
    static const std::set<std::string> known = {"coordinate", "min_deg",    "max_deg", "required",
                                                "follow",     "anti_phase", "window"};
    if (!known.count(key)) return r.Fail(path + key, "unknown field");
  }
  return Status::Ok();
}

Status ParseMovement(const Reader& r, const json& m, const std::string& path, Movement* out) {
  if (!m.is_object()) return r.Fail(path, "expected an object");
  MOCAP_TRY(r.String(m, path + ".", "name", &out->name, true));
  if (out->name.empty() || out->name.find_first_of("/\\ \t\r\n") != std::string::npos)
    return r.Fail(path + ".name", "must be non-empty, without spaces or slashes (it names files)");
  MOCAP_TRY(r.String(m, path + ".", "description", &out->description, false));
  MOCAP_TRY(r.Number(m, path + ".", "duration_s", &out->duration_s, true));
  if (!(out->duration_s > 0.0)) return r.Fail(path + ".duration_s", "must be > 0");
  MOCAP_TRY(r.Number(m, path + ".", "period_s", &out->period_s, false));
  if (!(out->period_s > 0.0)) return r.Fail(path + ".period_s", "must be > 0");
  MOCAP_TRY(r.Number(m, path + ".", "background", &out->background, false));
  if (!(out->background >= 0.0)) return r.Fail(path + ".background", "must be >= 0");
  if (!m.contains("excitations")) return r.Fail(path + ".excitations", "missing");
  const json& ex = m["excitations"];
  if (!ex.is_array()) return r.Fail(path + ".excitations", "expected an array");
  for (size_t i = 0; i < ex.size(); ++i) {
    Excitation e;
    MOCAP_TRY(ParseExcitation(r, ex[i], path + ".excitations[" + std::to_string(i) + "].", &e));
    out->excitations.push_back(std::move(e));
  }
  // Cross-field rules: one entry per coordinate; a follower's leader is in the same movement and
  // is not itself a follower (so the motion generator needs no ordering).
  for (size_t i = 0; i < out->excitations.size(); ++i) {
    const Excitation& e = out->excitations[i];
    const std::string at = path + ".excitations[" + std::to_string(i) + "].";
    for (size_t k = 0; k < i; ++k)
      if (out->excitations[k].coordinate == e.coordinate)
        return r.Fail(at + "coordinate", "'" + e.coordinate + "' is listed twice");
    if (e.follow.empty()) continue;
    const Excitation* leader = out->Find(e.follow);
    if (!leader) return r.Fail(at + "follow", "'" + e.follow + "' is not excited in this movement");
    if (leader == &e) return r.Fail(at + "follow", "a coordinate cannot follow itself");
    if (!leader->follow.empty())
      return r.Fail(at + "follow", "'" + e.follow + "' itself follows '" + leader->follow + "'");
    if (e.window_begin != leader->window_begin || e.window_end != leader->window_end)
      return r.Fail(at + "window", "a follower has the window of its leader '" + e.follow + "'");
  }
  return Status::Ok();
}

}  // namespace

const Excitation* Movement::Find(const std::string& coordinate) const {
  for (const Excitation& e : excitations)
    if (e.coordinate == coordinate) return &e;
  return nullptr;
}

std::vector<MovementPhase> MovementPhases(const Movement& movement) {
  std::vector<MovementPhase> phases;
  for (const Excitation& e : movement.excitations) {
    if (!e.required) continue;
    auto it = std::find_if(phases.begin(), phases.end(), [&](const MovementPhase& p) {
      return p.begin == e.window_begin && p.end == e.window_end;
    });
    if (it == phases.end()) it = phases.insert(phases.end(), {e.window_begin, e.window_end, {}});
    it->coordinates.push_back(e.coordinate);
  }
  std::stable_sort(phases.begin(), phases.end(), [](const MovementPhase& a, const MovementPhase& b) {
    return a.begin != b.begin ? a.begin < b.begin : a.end < b.end;
  });
  if (phases.empty()) phases.push_back({});
  return phases;
}

double Protocol::TotalDuration() const {
  double t = 0.0;
  for (const Movement& m : movements) t += m.duration_s;
  return t;
}

const Movement* Protocol::Find(const std::string& movement) const {
  for (const Movement& m : movements)
    if (m.name == movement) return &m;
  return nullptr;
}

const std::string& DefaultProtocolJson() {
  static const std::string text(detail::kDefaultProtocolJson);
  return text;
}

const Protocol& DefaultProtocol() {
  static const Protocol protocol = [] {
    Protocol p;
    Status s = ParseProtocolJson(DefaultProtocolJson(), "default_protocol.json", &p);
    (void)s;  // the embedded file is checked by tests/test_sim.cpp
    return p;
  }();
  return protocol;
}

Status ParseProtocolJson(const std::string& text, const std::string& source_name,
                         Protocol* protocol) {
  Reader r{source_name};
  json doc;
  MOCAP_TRY(r.Document(text, "mocap-protocol", 1, &doc));
  Protocol p;
  MOCAP_TRY(r.String(doc, "", "name", &p.name, false));
  if (!doc.contains("movements")) return r.Fail("movements", "missing");
  const json& ms = doc["movements"];
  if (!ms.is_array()) return r.Fail("movements", "expected an array");
  if (ms.empty()) return r.Fail("movements", "empty");
  for (size_t i = 0; i < ms.size(); ++i) {
    Movement m;
    const std::string path = "movements[" + std::to_string(i) + "]";
    MOCAP_TRY(ParseMovement(r, ms[i], path, &m));
    if (p.Find(m.name)) return r.Fail(path + ".name", "'" + m.name + "' is listed twice");
    p.movements.push_back(std::move(m));
  }
  *protocol = std::move(p);
  return Status::Ok();
}

Status LoadProtocolJson(const std::string& path, Protocol* protocol) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return Status::Error(path + ": cannot open for reading");
  std::stringstream buffer;
  buffer << in.rdbuf();
  return ParseProtocolJson(buffer.str(), path, protocol);
}

std::string ProtocolToJsonString(const Protocol& protocol) {
  using json = nlohmann::ordered_json;  // the file's order: format, version, name, movements
  json doc;
  doc["format"] = "mocap-protocol";
  doc["version"] = 1;
  doc["name"] = protocol.name;
  json ms = json::array();
  for (const Movement& m : protocol.movements) {
    json jm;
    jm["name"] = m.name;
    jm["description"] = m.description;
    jm["duration_s"] = m.duration_s;
    jm["period_s"] = m.period_s;
    jm["background"] = m.background;
    json ex = json::array();
    for (const Excitation& e : m.excitations) {
      json je;
      je["coordinate"] = e.coordinate;
      je["min_deg"] = e.min_deg;
      je["max_deg"] = e.max_deg;
      if (!e.required) je["required"] = false;
      if (!e.follow.empty()) je["follow"] = e.follow;
      if (e.anti_phase) je["anti_phase"] = true;
      if (e.window_begin != 0.0 || e.window_end != 1.0)
        je["window"] = json::array({e.window_begin, e.window_end});
      ex.push_back(je);
    }
    jm["excitations"] = ex;
    ms.push_back(jm);
  }
  doc["movements"] = ms;
  return doc.dump(2) + "\n";
}

Status ValidateProtocol(const Protocol& protocol, const Model& model) {
  for (size_t i = 0; i < protocol.movements.size(); ++i) {
    const Movement& m = protocol.movements[i];
    for (size_t k = 0; k < m.excitations.size(); ++k) {
      const Excitation& e = m.excitations[k];
      const std::string where = "protocol '" + protocol.name + "': movements[" +
                                std::to_string(i) + "] '" + m.name + "': excitations[" +
                                std::to_string(k) + "]: coordinate '" + e.coordinate + "'";
      const int c = model.FindCoordinate(e.coordinate);
      if (c < 0) return Status::Error(where + " is not in model '" + model.name() + "'");
      const Coordinate& coord = model.coordinates()[c];
      if (!coord.rotational)
        return Status::Error(where + " is a translation; excitations are angles in degrees");
      const double lo = coord.min_value * kRadToDeg, hi = coord.max_value * kRadToDeg;
      if (e.min_deg < lo || e.max_deg > hi)
        return Status::Error(where + ": range [" + Show(e.min_deg) + ", " +
                             Show(e.max_deg) + "] deg leaves the coordinate's limits [" +
                             Show(lo) + ", " + Show(hi) + "] deg");
    }
  }
  return Status::Ok();
}

std::vector<ExcitationCheck> CheckExcitations(const Movement& movement,
                                              const formats::CoordinateTable& table,
                                              double tolerance_deg) {
  ExcitationCheckOptions options;
  options.tolerance_deg = tolerance_deg;
  return CheckExcitations(movement, table, options);
}

std::vector<ExcitationCheck> CheckExcitations(const Movement& movement,
                                              const formats::CoordinateTable& table,
                                              const ExcitationCheckOptions& options) {
  const double nan = std::numeric_limits<double>::quiet_NaN();
  const double to_deg = table.in_degrees ? 1.0 : kRadToDeg;
  std::vector<ExcitationCheck> out;
  for (const Excitation& e : movement.excitations) {
    const double tolerance_deg =
        std::max(options.tolerance_deg, options.tolerance_fraction * (e.max_deg - e.min_deg));
    ExcitationCheck c;
    c.coordinate = e.coordinate;
    c.min_deg = e.min_deg;
    c.max_deg = e.max_deg;
    c.required = e.required;
    c.reached_min_deg = nan;
    c.reached_max_deg = nan;
    int col = -1;
    for (size_t k = 0; k < table.column_names.size(); ++k)
      if (table.column_names[k] == e.coordinate) col = static_cast<int>(k);
    if (col >= 0) {
      double lo = std::numeric_limits<double>::infinity(), hi = -lo;
      for (int f = 0; f < table.num_frames(); ++f) {
        const double v = table.values(f, col) * to_deg;
        if (std::isnan(v)) continue;
        lo = std::min(lo, v);
        hi = std::max(hi, v);
      }
      if (lo <= hi) {
        c.reached_min_deg = lo;
        c.reached_max_deg = hi;
      }
    }
    if (options.max_offset_deg < 0) {
      c.ok = c.reached_min_deg <= e.min_deg + tolerance_deg &&
             c.reached_max_deg >= e.max_deg - tolerance_deg;
    } else {
      const double offset = 0.5 * ((c.reached_min_deg + c.reached_max_deg) - (e.min_deg + e.max_deg));
      c.ok = c.reached_max_deg - c.reached_min_deg >= e.max_deg - e.min_deg - tolerance_deg &&
             std::abs(offset) <= options.max_offset_deg;
    }
    out.push_back(c);
  }
  return out;
}

}  // namespace mocap::sim
