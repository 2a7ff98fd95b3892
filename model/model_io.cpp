#include "model/model_io.h"

#include <fstream>
#include <cmath>
#include <map>
#include <nlohmann/json.hpp>

#include "model/json_fields.h"
#include <sstream>

namespace mocap {
namespace {

using json = nlohmann::json;

using Reader = JsonFields;
#define MOCAP_TRY MOCAP_RETURN_IF_ERROR

json V(const Eigen::Vector3d& v) { return json::array({v.x(), v.y(), v.z()}); }

Status NumberArray(const Reader& r, const json& obj, const std::string& path, const char* key,
                   std::vector<double>* out) {
  MOCAP_TRY(r.Array(obj, path, key));
  out->clear();
  for (const json& v : obj[key]) {
    if (!v.is_number()) return r.Fail(Reader::Join(path, key), "expected numbers");
    out->push_back(v.get<double>());
  }
  return Status::Ok();
}

// {"kind": ..., kind-specific fields}; splines keep only their points (the coefficients follow).
Status ParseFunction(const Reader& r, const json& jf, const std::string& path,
                     CoordinateFunction* f) {
  using Kind = CoordinateFunction::Kind;
  if (!jf.is_object()) return r.Fail(path, "expected an object");
  std::string name;
  MOCAP_TRY(r.String(jf, path, "kind", &name));
  Kind kind;
  if (!CoordinateFunction::KindFromName(name, &kind))
    return r.Fail(Reader::Join(path, "kind"),
                  "unknown function '" + name +
                      "' (identity, linear, constant, simm_spline, natural_cubic_spline, "
                      "piecewise_linear, gcv_spline, polynomial, multiplier, composed)");
  switch (kind) {
    case Kind::kIdentity:
      *f = CoordinateFunction::Identity();
      break;
    case Kind::kLinear:
    case Kind::kConstant: {
      double slope = 1.0, offset = 0.0;
      MOCAP_TRY(r.Number(jf, path, "slope", &slope, false));
      MOCAP_TRY(r.Number(jf, path, "offset", &offset, false));
      *f = kind == Kind::kLinear ? CoordinateFunction::Linear(slope, offset)
                                 : CoordinateFunction::Constant(offset);
      if (kind == Kind::kConstant) f->slope = slope;  // kept as written (unused)
      break;
    }
    case Kind::kSimmSpline:
    case Kind::kNaturalCubicSpline: {
      std::vector<double> x, y;
      MOCAP_TRY(NumberArray(r, jf, path, "x", &x));
      MOCAP_TRY(NumberArray(r, jf, path, "y", &y));
      *f = kind == Kind::kSimmSpline ? CoordinateFunction::SimmSpline(x, y)
                                     : CoordinateFunction::NaturalCubicSpline(x, y);
      break;
    }
    case Kind::kPiecewiseLinear:
    case Kind::kGcvSpline: {
      std::vector<double> x, y;
      MOCAP_TRY(NumberArray(r, jf, path, "x", &x));
      MOCAP_TRY(NumberArray(r, jf, path, "y", &y));
      if (kind == Kind::kPiecewiseLinear) {
        *f = CoordinateFunction::PiecewiseLinear(x, y);
        break;
      }
      double m = 0.0;
      MOCAP_TRY(r.Number(jf, path, "half_order", &m));
      // Checked before the cast: a huge number would not fit an int.
      if (!(m >= 1.0 && m <= 4.0) || m != std::floor(m))
        return r.Fail(Reader::Join(path, "half_order"), "must be a whole number from 1 to 4 (degree 1 to 7)");
      *f = CoordinateFunction::GcvSpline(static_cast<int>(m), x, y);
      break;
    }
    case Kind::kPolynomial: {
      std::vector<double> c;
      MOCAP_TRY(NumberArray(r, jf, path, "coefficients", &c));
      *f = CoordinateFunction::Polynomial(c);
      break;
    }
    case Kind::kMultiplier: {
      double scale = 1.0;
      MOCAP_TRY(r.Number(jf, path, "scale", &scale));
      if (!jf.contains("function")) return r.Fail(Reader::Join(path, "function"), "missing");
      CoordinateFunction inner;
      MOCAP_TRY(ParseFunction(r, jf["function"], Reader::Join(path, "function"), &inner));
      *f = CoordinateFunction::Multiplier(scale, inner);
      break;
    }
    case Kind::kComposed: {
      CoordinateFunction outer, inner;
      for (const char* key : {"outer", "inner"})
        if (!jf.contains(key)) return r.Fail(Reader::Join(path, key), "missing");
      MOCAP_TRY(ParseFunction(r, jf["outer"], Reader::Join(path, "outer"), &outer));
      MOCAP_TRY(ParseFunction(r, jf["inner"], Reader::Join(path, "inner"), &inner));
      *f = CoordinateFunction::Compose(outer, inner);
      break;
    }
  }
  if (Status s = f->Check(path); !s) return r.Fail(path, s.message().substr(path.size() + 2));
  return Status::Ok();
}

json FunctionToJson(const CoordinateFunction& f) {
  using Kind = CoordinateFunction::Kind;
  json j = {{"kind", CoordinateFunction::KindName(f.kind)}};
  switch (f.kind) {
    case Kind::kIdentity: break;
    case Kind::kLinear:
    case Kind::kConstant:
      j["slope"] = f.slope;
      j["offset"] = f.offset;
      break;
    case Kind::kSimmSpline:
    case Kind::kNaturalCubicSpline:
    case Kind::kPiecewiseLinear:
      j["x"] = f.x;
      j["y"] = f.y;
      break;
    case Kind::kGcvSpline:
      j["half_order"] = f.half_order;
      j["x"] = f.x;
      j["y"] = f.y;
      break;
    case Kind::kPolynomial: j["coefficients"] = f.coefficients; break;
    case Kind::kMultiplier:
      j["scale"] = f.slope;
      j["function"] = FunctionToJson(f.inner[0]);
      break;
    case Kind::kComposed:
      j["outer"] = FunctionToJson(f.inner[0]);
      j["inner"] = FunctionToJson(f.inner[1]);
      break;
  }
  return j;
}

}  // namespace

Status ParseModelJson(const std::string& text, const std::string& source, Model* model) {
  Reader r(source);
  json doc;
  try {
    doc = json::parse(text);
  } catch (const json::parse_error& e) {
    return Status::Error(source + ": not valid JSON (byte " + std::to_string(e.byte) +
                         "): " + e.what());
  }
  if (!doc.is_object()) return r.Fail("(top level)", "expected an object");
  std::string format;
  MOCAP_TRY(r.String(doc, "", "format", &format));
  if (format != "mocap-model") return r.Fail(".format", "expected \"mocap-model\", got \"" + format + "\"");
  double version = 0;
  MOCAP_TRY(r.Number(doc, "", "version", &version));
  if (version != 1) return r.Fail(".version", "unsupported version " + std::to_string(version));
  std::string name = "model";
  MOCAP_TRY(r.String(doc, "", "name", &name, false));
  for (const char* key : {"segments", "coordinates", "joints", "markers"})
    MOCAP_TRY(r.Array(doc, "", key));

  std::vector<Segment> segments;
  std::map<std::string, int> segment_index;
  for (size_t i = 0; i < doc["segments"].size(); ++i) {
    const json& js = doc["segments"][i];
    const std::string path = "segments[" + std::to_string(i) + "]";
    if (!js.is_object()) return r.Fail(path, "expected an object");
    Segment s;
    MOCAP_TRY(r.String(js, path, "name", &s.name));
    MOCAP_TRY(r.Number(js, path, "scale", &s.scale, false));
    if (!(s.scale > 0)) return r.Fail(path + ".scale", "must be > 0");
    if (!segment_index.emplace(s.name, static_cast<int>(i)).second)
      return r.Fail(path + ".name", "duplicate segment '" + s.name + "'");
    segments.push_back(s);
  }
  std::vector<Coordinate> coordinates;
  std::map<std::string, int> coordinate_index;
  for (size_t i = 0; i < doc["coordinates"].size(); ++i) {
    const json& jc = doc["coordinates"][i];
    const std::string path = "coordinates[" + std::to_string(i) + "]";
    if (!jc.is_object()) return r.Fail(path, "expected an object");
    Coordinate c;
    MOCAP_TRY(r.String(jc, path, "name", &c.name));
    MOCAP_TRY(r.Bool(jc, path, "rotational", &c.rotational));
    MOCAP_TRY(r.Number(jc, path, "default", &c.default_value, false));
    if (jc.contains("range")) {
      const json& rg = jc["range"];
      if (!rg.is_array() || rg.size() != 2 || !rg[0].is_number() || !rg[1].is_number())
        return r.Fail(path + ".range", "expected [min, max]");
      c.min_value = rg[0].get<double>();
      c.max_value = rg[1].get<double>();
      if (!(c.min_value <= c.max_value)) return r.Fail(path + ".range", "min > max");
    }
    if (jc.contains("clamped")) {
      if (!jc.contains("range")) return r.Fail(path + ".clamped", "a clamped coordinate needs a range");
      MOCAP_TRY(r.Bool(jc, path, "clamped", &c.clamped));
    }
    if (!coordinate_index.emplace(c.name, static_cast<int>(i)).second)
      return r.Fail(path + ".name", "duplicate coordinate '" + c.name + "'");
    coordinates.push_back(c);
  }
  std::vector<Joint> joints;
  for (size_t i = 0; i < doc["joints"].size(); ++i) {
    const json& jj = doc["joints"][i];
    const std::string path = "joints[" + std::to_string(i) + "]";
    if (!jj.is_object()) return r.Fail(path, "expected an object");
    Joint j;
    MOCAP_TRY(r.String(jj, path, "name", &j.name));
    std::string type = "custom", parent, child;
    MOCAP_TRY(r.String(jj, path, "type", &type, false));
    if (type == "free") j.type = JointType::kFree;
    else if (type == "spherical") j.type = JointType::kSpherical;
    else if (type == "universal") j.type = JointType::kUniversal;
    else if (type == "hinge") j.type = JointType::kHinge;
    else if (type == "custom") j.type = JointType::kCustom;
    else return r.Fail(path + ".type", "unknown joint type '" + type + "' (free, spherical, universal, hinge, custom)");
    MOCAP_TRY(r.String(jj, path, "parent", &parent));
    MOCAP_TRY(r.String(jj, path, "child", &child));
    if (parent == "ground") j.parent = -1;
    else if (auto it = segment_index.find(parent); it != segment_index.end()) j.parent = it->second;
    else return r.Fail(path + ".parent", "no segment named '" + parent + "'");
    if (auto it = segment_index.find(child); it != segment_index.end()) j.child = it->second;
    else return r.Fail(path + ".child", "no segment named '" + child + "'");
    MOCAP_TRY(r.Vec3(jj, path, "centre", &j.centre, false));
    if (jj.contains("orientation")) {
      const json& o = jj["orientation"];
      if (!o.is_array() || o.size() != 3) return r.Fail(path + ".orientation", "expected 3 rows of 3 numbers");
      for (int a = 0; a < 3; ++a) {
        if (!o[a].is_array() || o[a].size() != 3) return r.Fail(path + ".orientation", "expected 3 rows of 3 numbers");
        for (int b = 0; b < 3; ++b) {
          if (!o[a][b].is_number()) return r.Fail(path + ".orientation", "expected numbers");
          j.orientation(a, b) = o[a][b].get<double>();
        }
      }
      if (!(j.orientation.transpose() * j.orientation).isIdentity(1e-6))
        return r.Fail(path + ".orientation", "not a rotation matrix");
    }
    MOCAP_TRY(r.Array(jj, path + ".", "elements"));
    for (size_t e = 0; e < jj["elements"].size(); ++e) {
      const json& je = jj["elements"][e];
      const std::string ep = path + ".elements[" + std::to_string(e) + "]";
      if (!je.is_object()) return r.Fail(ep, "expected an object");
      JointElement el;
      std::string kind;
      MOCAP_TRY(r.String(je, ep, "kind", &kind));
      if (kind == "rotation") el.kind = ElementKind::kRotation;
      else if (kind == "translation") el.kind = ElementKind::kTranslation;
      else return r.Fail(ep + ".kind", "expected \"rotation\" or \"translation\", got \"" + kind + "\"");
      MOCAP_TRY(r.Vec3(je, ep, "axis", &el.axis));
      if (el.axis.norm() < 1e-9) return r.Fail(ep + ".axis", "zero vector");
      // Saved axes are unit already: renormalising them would change their last bits.
      if (std::abs(el.axis.norm() - 1.0) > 1e-12) el.axis.normalize();
      MOCAP_TRY(r.Bool(je, ep, "fitted_axis", &el.fitted_axis));
      if (je.contains("function"))
        MOCAP_TRY(ParseFunction(r, je["function"], ep + ".function", &el.function));
      std::string coord;
      const bool constant = el.function.IsConstant();
      MOCAP_TRY(r.String(je, ep, "coordinate", &coord, !constant));
      if (!coord.empty()) {
        auto it = coordinate_index.find(coord);
        if (it == coordinate_index.end()) return r.Fail(ep + ".coordinate", "no coordinate named '" + coord + "'");
        el.coordinate = it->second;
      }
      j.elements.push_back(el);
    }
    joints.push_back(j);
  }
  std::vector<Marker> markers;
  for (size_t i = 0; i < doc["markers"].size(); ++i) {
    const json& jm = doc["markers"][i];
    const std::string path = "markers[" + std::to_string(i) + "]";
    if (!jm.is_object()) return r.Fail(path, "expected an object");
    Marker m;
    std::string seg;
    MOCAP_TRY(r.String(jm, path, "name", &m.name));
    MOCAP_TRY(r.String(jm, path, "segment", &seg));
    auto it = segment_index.find(seg);
    if (it == segment_index.end()) return r.Fail(path + ".segment", "no segment named '" + seg + "'");
    m.segment = it->second;
    MOCAP_TRY(r.Vec3(jm, path, "position", &m.position));
    MOCAP_TRY(r.Bool(jm, path, "optional", &m.optional));
    MOCAP_TRY(r.Bool(jm, path, "fixed", &m.fixed));
    MOCAP_TRY(r.Number(jm, path, "weight", &m.weight, false));
    if (!(m.weight > 0)) return r.Fail(path + ".weight", "must be > 0");
    markers.push_back(m);
  }
  std::vector<DerivedCoordinate> derived;
  if (doc.contains("derived_coordinates")) {
    MOCAP_TRY(r.Array(doc, "", "derived_coordinates"));
    for (size_t i = 0; i < doc["derived_coordinates"].size(); ++i) {
      const json& jd = doc["derived_coordinates"][i];
      const std::string path = "derived_coordinates[" + std::to_string(i) + "]";
      if (!jd.is_object()) return r.Fail(path, "expected an object");
      DerivedCoordinate dc;
      MOCAP_TRY(r.String(jd, path, "name", &dc.name));
      MOCAP_TRY(r.Bool(jd, path, "rotational", &dc.rotational));
      std::string source;
      MOCAP_TRY(r.String(jd, path, "source", &source, false));
      if (!source.empty()) {
        auto it = coordinate_index.find(source);
        if (it == coordinate_index.end())
          return r.Fail(path + ".source", "no coordinate named '" + source + "'");
        dc.source = it->second;
      }
      if (!jd.contains("function")) return r.Fail(path + ".function", "missing");
      MOCAP_TRY(ParseFunction(r, jd["function"], path + ".function", &dc.function));
      derived.push_back(dc);
    }
  }
  Status s = Model::Build(name, segments, joints, coordinates, markers, derived, model);
  if (!s.ok()) return Status::Error(source + ": " + s.message());
  return Status::Ok();
}

Status LoadModelJson(const std::string& path, Model* model) {
  std::ifstream in(path);
  if (!in) return Status::Error(path + ": cannot open model file");
  std::stringstream ss;
  ss << in.rdbuf();
  return ParseModelJson(ss.str(), path, model);
}

std::string ModelToJsonString(const Model& model) {
  json doc;
  doc["format"] = "mocap-model";
  doc["version"] = 1;
  doc["name"] = model.name();
  doc["segments"] = json::array();
  for (const auto& s : model.segments()) doc["segments"].push_back({{"name", s.name}, {"scale", s.scale}});
  doc["coordinates"] = json::array();
  for (const auto& c : model.coordinates())
  {
    json jc = {{"name", c.name}, {"rotational", c.rotational}, {"default", c.default_value},
               {"range", json::array({c.min_value, c.max_value})}};
    if (c.clamped) jc["clamped"] = true;
    doc["coordinates"].push_back(std::move(jc));
  }
  doc["joints"] = json::array();
  for (const auto& j : model.joints()) {
    json jj = {{"name", j.name}, {"type", ToString(j.type)},
               {"parent", j.parent < 0 ? "ground" : model.segments()[j.parent].name},
               {"child", model.segments()[j.child].name}, {"centre", V(j.centre)}};
    if (!j.orientation.isIdentity(0)) {
      json o = json::array();
      for (int a = 0; a < 3; ++a)
        o.push_back(json::array({j.orientation(a, 0), j.orientation(a, 1), j.orientation(a, 2)}));
      jj["orientation"] = o;
    }
    jj["elements"] = json::array();
    for (const auto& el : j.elements) {
      json je = {{"kind", el.kind == ElementKind::kRotation ? "rotation" : "translation"},
                 {"axis", V(el.axis)}};
      if (el.coordinate >= 0) je["coordinate"] = model.coordinates()[el.coordinate].name;
      if (el.fitted_axis) je["fitted_axis"] = true;
      if (el.function.kind != CoordinateFunction::Kind::kIdentity)
        je["function"] = FunctionToJson(el.function);
      jj["elements"].push_back(je);
    }
    doc["joints"].push_back(jj);
  }
  doc["markers"] = json::array();
  for (const auto& m : model.markers()) {
    json jm = {{"name", m.name}, {"segment", model.segments()[m.segment].name}, {"position", V(m.position)}};
    if (m.optional) jm["optional"] = true;
    if (m.fixed) jm["fixed"] = true;
    if (m.weight != 1.0) jm["weight"] = m.weight;
    doc["markers"].push_back(jm);
  }
  if (!model.derived_coordinates().empty()) {
    doc["derived_coordinates"] = json::array();
    for (const auto& dc : model.derived_coordinates()) {
      json jd = {{"name", dc.name}, {"rotational", dc.rotational},
                 {"function", FunctionToJson(dc.function)}};
      if (dc.source >= 0) jd["source"] = model.coordinates()[dc.source].name;
      doc["derived_coordinates"].push_back(jd);
    }
  }
  return doc.dump(1);
}

Status SaveModelJson(const std::string& path, const Model& model) {
  std::ofstream out(path);
  if (!out) return Status::Error(path + ": cannot write model file");
  out << ModelToJsonString(model) << "\n";
  out.close();
  if (!out) return Status::Error(path + ": write failed");
  return Status::Ok();
}

}  // namespace mocap
