#include "formats/osim.h"

#include <tinyxml2.h>

#include <algorithm>
#include <cmath>
#include <functional>
#include <map>
#include <set>
#include <sstream>

#include "formats/mot.h"
#include "formats/text_util.h"
#include "model/kinematics.h"

namespace mocap::formats {
namespace {

using tinyxml2::XMLDocument;
using tinyxml2::XMLElement;
using Iso = Eigen::Isometry3d;
using V3 = Eigen::Vector3d;
using M3 = Eigen::Matrix3d;

constexpr int kGround = -1;
constexpr double kDegPerRad = 180.0 / M_PI;

std::string Text(const XMLElement* e) {
  return e && e->GetText() ? std::string(detail::Trim(e->GetText())) : std::string();
}
std::string NameOf(const XMLElement* e) {
  const char* n = e ? e->Attribute("name") : nullptr;
  return n ? n : "";
}
XMLElement* Child(XMLElement* e, const char* tag) { return e ? e->FirstChildElement(tag) : nullptr; }
std::string LastComponent(const std::string& path) {
  std::string p = path;
  while (!p.empty() && p.back() == '/') p.pop_back();
  const size_t slash = p.rfind('/');
  return slash == std::string::npos ? p : p.substr(slash + 1);
}

// SimTK Rotation::setRotationToBodyFixedXYZ: R = Rx(a) Ry(b) Rz(c).
M3 BodyFixedXYZ(const V3& a) {
  return (Eigen::AngleAxisd(a.x(), V3::UnitX()) * Eigen::AngleAxisd(a.y(), V3::UnitY()) *
          Eigen::AngleAxisd(a.z(), V3::UnitZ()))
      .toRotationMatrix();
}
V3 ToBodyFixedXYZ(const M3& r) {
  const double sb = std::clamp(r(0, 2), -1.0, 1.0);
  const double b = std::asin(sb);
  if (std::abs(sb) < 1.0 - 1e-12) return {std::atan2(-r(1, 2), r(2, 2)), b, std::atan2(-r(0, 1), r(0, 0))};
  // Gimbal lock: only a + c (or a - c) is defined; put it all in a.
  return {std::atan2(r(2, 1), r(1, 1)), b, 0.0};
}
Iso MakeIso(const M3& r, const V3& t) {
  Iso x = Iso::Identity();
  x.linear() = r;
  x.translation() = t;
  return x;
}

std::string FormatNumbers(const double* v, int n) {
  std::string s;
  for (int i = 0; i < n; ++i) {
    if (i) s += ' ';
    detail::AppendShortest(&s, v[i] == 0.0 ? 0.0 : v[i]);  // no "-0"
  }
  return s;
}
std::string FormatVec3(const V3& v) { return FormatNumbers(v.data(), 3); }

class Reader {
 public:
  explicit Reader(std::string source) : source_(std::move(source)) {}
  const std::string& source() const { return source_; }

  // "SRC:LINE: Tag 'name': what"
  Status Fail(const XMLElement* e, const std::string& what) const {
    std::string who;
    if (e) {
      who = e->Name();
      if (!NameOf(e).empty()) who += " '" + NameOf(e) + "'";
      who += ": ";
    }
    return Status::Error(detail::At(source_, e ? e->GetLineNum() : 0, who + what));
  }
  Status Numbers(const XMLElement* e, std::vector<double>* out) const {
    out->clear();
    std::istringstream in(e && e->GetText() ? e->GetText() : "");
    std::string field;
    while (in >> field) {
      double v;
      if (detail::ParseDouble(field, &v) != detail::NumberKind::kNumber)
        return Fail(e, "expected numbers, got " + detail::Quote(field));
      out->push_back(v);
    }
    return Status::Ok();
  }
  Status Number(XMLElement* parent, const char* tag, double* out, bool required) const {
    XMLElement* e = Child(parent, tag);
    if (!e) return required ? Fail(parent, std::string("missing <") + tag + ">") : Status::Ok();
    std::vector<double> v;
    MOCAP_RETURN_IF_ERROR(Numbers(e, &v));
    if (v.size() != 1) return Fail(e, "expected one number");
    *out = v[0];
    return Status::Ok();
  }
  Status Vec3(XMLElement* parent, const char* tag, V3* out, bool required) const {
    XMLElement* e = Child(parent, tag);
    if (!e) return required ? Fail(parent, std::string("missing <") + tag + ">") : Status::Ok();
    std::vector<double> v;
    MOCAP_RETURN_IF_ERROR(Numbers(e, &v));
    if (v.size() != 3) return Fail(e, "expected 3 numbers");
    *out = V3(v[0], v[1], v[2]);
    return Status::Ok();
  }

 private:
  std::string source_;
};

Status ParseFunction(const Reader& rd, XMLElement* e, CoordinateFunction* f);

// The function held by `parent`: 4.x writes it as a child element (<SimmSpline name="function">),
// 3.x and MultiplierFunction wrap it in <function>; `skip` are the parent's other properties.
Status FindFunction(const Reader& rd, XMLElement* parent, const std::set<std::string>& skip,
                    XMLElement** out) {
  *out = nullptr;
  for (XMLElement* c = parent->FirstChildElement(); c; c = c->NextSiblingElement()) {
    const std::string tag = c->Name();
    if (skip.count(tag)) continue;
    if (tag == "function" || tag == "coupled_coordinates_function") {
      XMLElement* inner = c->FirstChildElement();
      if (!inner) return rd.Fail(c, "empty function");
      *out = inner;
      return Status::Ok();
    }
    *out = c;
    return Status::Ok();
  }
  return Status::Ok();
}

Status ParseFunction(const Reader& rd, XMLElement* e, CoordinateFunction* f) {
  const std::string tag = e->Name();
  std::vector<double> v;
  if (tag == "Constant") {
    double value = 0.0;
    MOCAP_RETURN_IF_ERROR(rd.Number(e, "value", &value, true));
    *f = CoordinateFunction::Constant(value);
  } else if (tag == "LinearFunction") {
    MOCAP_RETURN_IF_ERROR(rd.Numbers(Child(e, "coefficients"), &v));
    if (v.size() != 2) return rd.Fail(e, "<coefficients> must be 'slope intercept'");
    // OpenSim treats slope 1, intercept 0 as the coordinate itself (not scaled, not coupled).
    *f = v[0] == 1.0 && v[1] == 0.0 ? CoordinateFunction::Identity()
                                    : CoordinateFunction::Linear(v[0], v[1]);
  } else if (tag == "SimmSpline" || tag == "NaturalCubicSpline") {
    std::vector<double> x, y;
    MOCAP_RETURN_IF_ERROR(rd.Numbers(Child(e, "x"), &x));
    MOCAP_RETURN_IF_ERROR(rd.Numbers(Child(e, "y"), &y));
    *f = tag == "SimmSpline" ? CoordinateFunction::SimmSpline(x, y)
                             : CoordinateFunction::NaturalCubicSpline(x, y);
  } else if (tag == "PiecewiseLinearFunction") {
    std::vector<double> x, y;
    MOCAP_RETURN_IF_ERROR(rd.Numbers(Child(e, "x"), &x));
    MOCAP_RETURN_IF_ERROR(rd.Numbers(Child(e, "y"), &y));
    *f = CoordinateFunction::PiecewiseLinear(x, y);
  } else if (tag == "GCVSpline") {
    // OpenSim's own default half order is 0, which it cannot evaluate: a usable file says it.
    if (!Child(e, "half_order")) return rd.Fail(e, "missing <half_order> (3 for OpenSim's quintic)");
    double m = 0.0, error_variance = 0.0;
    MOCAP_RETURN_IF_ERROR(rd.Number(e, "half_order", &m, true));
    MOCAP_RETURN_IF_ERROR(rd.Number(e, "error_variance", &error_variance, false));
    // Checked before the cast: a huge number would not fit an int.
    if (!(m >= 1.0 && m <= 4.0) || m != std::floor(m))
      return rd.Fail(e, "<half_order> " + FormatNumbers(&m, 1) + " is not a whole number from 1 to 4 (degree 1 to 7)");
    // A non-zero error variance makes GCVSPL smooth instead of interpolate: another curve,
    // which we would have to compute as GCVSPL does to match OpenSim's kinematics.
    if (error_variance != 0.0)
      return rd.Fail(e, "<error_variance> " + FormatNumbers(&error_variance, 1) +
                            ": only interpolating GCV splines (error variance 0) are supported");
    std::vector<double> x, y;
    MOCAP_RETURN_IF_ERROR(rd.Numbers(Child(e, "x"), &x));
    MOCAP_RETURN_IF_ERROR(rd.Numbers(Child(e, "y"), &y));
    *f = CoordinateFunction::GcvSpline(static_cast<int>(m), x, y);
  } else if (tag == "PolynomialFunction") {
    MOCAP_RETURN_IF_ERROR(rd.Numbers(Child(e, "coefficients"), &v));
    *f = CoordinateFunction::Polynomial(v);
  } else if (tag == "MultiplierFunction") {
    double scale = 1.0;
    MOCAP_RETURN_IF_ERROR(rd.Number(e, "scale", &scale, false));
    XMLElement* inner = nullptr;
    MOCAP_RETURN_IF_ERROR(FindFunction(rd, e, {"scale"}, &inner));
    if (!inner) return rd.Fail(e, "missing <function>");
    CoordinateFunction g;
    MOCAP_RETURN_IF_ERROR(ParseFunction(rd, inner, &g));
    *f = CoordinateFunction::Multiplier(scale, g);
  } else {
    return rd.Fail(e, "unsupported function type '" + tag +
                          "' (supported: Constant, LinearFunction, SimmSpline, NaturalCubicSpline, "
                          "GCVSpline, PiecewiseLinearFunction, PolynomialFunction, MultiplierFunction)");
  }
  if (Status s = f->Check(tag); !s) return rd.Fail(e, s.message());
  return Status::Ok();
}

// outer(inner(z)), simplified where one side is trivial.
CoordinateFunction ComposeSimplified(const CoordinateFunction& outer, const CoordinateFunction& inner) {
  if (inner.IsIdentity()) return outer;
  if (outer.IsIdentity()) return inner;
  if (inner.IsConstant()) return CoordinateFunction::Constant(outer.Value(inner.Value(0.0)));
  if (outer.IsConstant()) return CoordinateFunction::Constant(outer.Value(0.0));
  return CoordinateFunction::Compose(outer, inner);
}

// One side of a joint: the joint frame F (or M) in an OpenSim body, and where it is written.
struct FrameSide {
  int body = kGround;
  Iso offset = Iso::Identity();         // X_B,F
  Iso frame_parent = Iso::Identity();   // X_B,(the offset frame's own parent frame)
  XMLElement* offset_xml = nullptr;     // 4.x PhysicalOffsetFrame holding the offset
  XMLElement* socket = nullptr;         // 4.x socket_parent_frame / socket_child_frame
  XMLElement* location3 = nullptr;      // 3.x: the joint element itself (fields by name)
};

struct RawCoordinate {
  std::string name;
  double default_value = 0.0, lo = -1e9, hi = 1e9;
  bool locked = false;
  bool clamped = false;  // <clamped>: the range is a limit (OpenSim IK bounds it)
  XMLElement* xml = nullptr;
};

struct RawElement {
  ElementKind kind = ElementKind::kRotation;
  V3 axis = V3::UnitX();
  std::string coordinate;  // empty: none
  CoordinateFunction function;
  int axis_index = -1;     // TransformAxis 0..5, or the joint's coordinate index
  XMLElement* xml = nullptr;  // TransformAxis (CustomJoint)
};

struct RawJoint {
  std::string name, type;
  XMLElement* xml = nullptr;
  int child = -1;
  FrameSide parent, child_side;
  std::vector<RawElement> elements;   // before coupler/lock resolution
  std::vector<std::string> coordinates;
  bool three = false;  // 3.x layout
};

struct Mapping {
  std::vector<RawJoint> joints;                  // file order
  std::vector<XMLElement*> bodies;               // per segment
  std::map<std::string, XMLElement*> markers;    // by name
  XMLElement* model = nullptr;
  std::string ground = "ground";
  std::vector<std::string> body_names;
  int version = 0;
};

struct Importer {
  Reader rd;
  Mapping* map;
  OsimImport* out;

  int FindBody(const std::string& n) const {
    for (size_t i = 0; i < map->body_names.size(); ++i)
      if (map->body_names[i] == n) return static_cast<int>(i);
    return -2;
  }
  // A body or the ground from a path's last component; -2 if neither.
  int BodyFromPath(const std::string& path) const {
    const std::string last = LastComponent(path);
    const int b = FindBody(last);
    if (b >= 0) return b;
    if (last == map->ground || last == "ground") return kGround;
    return -2;
  }

  Status ResolveFrame(XMLElement* joint, XMLElement* socket, const std::string& path,
                      FrameSide* side, int depth) {
    if (depth > 8) return rd.Fail(socket, "offset frames nest too deep at '" + path + "'");
    XMLElement* frames = Child(joint, "frames");
    if (path.find('/') == std::string::npos && frames) {
      for (XMLElement* f = frames->FirstChildElement(); f; f = f->NextSiblingElement()) {
        if (NameOf(f) != path) continue;
        if (std::string(f->Name()) != "PhysicalOffsetFrame")
          return rd.Fail(f, "unsupported frame type (only PhysicalOffsetFrame)");
        XMLElement* parent_socket = Child(f, "socket_parent");
        if (!parent_socket) return rd.Fail(f, "missing <socket_parent>");
        FrameSide base;
        MOCAP_RETURN_IF_ERROR(ResolveFrame(joint, parent_socket, Text(parent_socket), &base, depth + 1));
        V3 t = V3::Zero(), o = V3::Zero();
        MOCAP_RETURN_IF_ERROR(rd.Vec3(f, "translation", &t, false));
        MOCAP_RETURN_IF_ERROR(rd.Vec3(f, "orientation", &o, false));
        side->body = base.body;
        side->frame_parent = base.offset;
        side->offset = base.offset * MakeIso(BodyFixedXYZ(o), t);
        side->offset_xml = f;
        return Status::Ok();
      }
    }
    const int b = BodyFromPath(path);
    if (b == -2)
      return rd.Fail(socket, "no body, ground or frame of this joint named '" + path + "'");
    side->body = b;
    side->offset = Iso::Identity();
    return Status::Ok();
  }

  Status ParseCoordinates(XMLElement* list, RawJoint* j, std::vector<RawCoordinate>* coords) {
    if (!list) return Status::Ok();
    for (XMLElement* c = list->FirstChildElement("Coordinate"); c; c = c->NextSiblingElement("Coordinate")) {
      RawCoordinate rc;
      rc.name = NameOf(c);
      rc.xml = c;
      if (rc.name.empty()) return rd.Fail(c, "coordinate without a name");
      MOCAP_RETURN_IF_ERROR(rd.Number(c, "default_value", &rc.default_value, false));
      if (XMLElement* r = Child(c, "range")) {
        std::vector<double> v;
        MOCAP_RETURN_IF_ERROR(rd.Numbers(r, &v));
        if (v.size() != 2 || !(v[0] <= v[1])) return rd.Fail(r, "expected 'min max'");
        rc.lo = v[0];
        rc.hi = v[1];
      }
      rc.locked = Text(Child(c, "locked")) == "true";
      rc.clamped = Text(Child(c, "clamped")) == "true";
      for (const auto& other : *coords)
        if (other.name == rc.name) return rd.Fail(c, "duplicate coordinate name");
      j->coordinates.push_back(rc.name);
      coords->push_back(rc);
    }
    return Status::Ok();
  }

  Status ParseCustom(XMLElement* jx, RawJoint* j) {
    XMLElement* st = Child(jx, "SpatialTransform");
    if (!st) return rd.Fail(jx, "missing <SpatialTransform>");
    const char* names[6] = {"rotation1", "rotation2", "rotation3", "translation1", "translation2", "translation3"};
    std::vector<RawElement> rotations, translations;
    int found = 0;
    for (XMLElement* ta = st->FirstChildElement("TransformAxis"); ta; ta = ta->NextSiblingElement("TransformAxis")) {
      int k = -1;
      for (int i = 0; i < 6; ++i)
        if (NameOf(ta) == names[i]) k = i;
      if (k < 0) return rd.Fail(ta, "expected a name rotation1..3 or translation1..3");
      ++found;
      RawElement el;
      el.kind = k < 3 ? ElementKind::kRotation : ElementKind::kTranslation;
      el.axis_index = k;
      el.xml = ta;
      MOCAP_RETURN_IF_ERROR(rd.Vec3(ta, "axis", &el.axis, true));
      if (!(el.axis.norm() > 1e-12)) return rd.Fail(Child(ta, "axis"), "zero axis");
      el.axis.normalize();
      std::istringstream names_in(Text(Child(ta, "coordinates")));
      std::vector<std::string> cn;
      for (std::string n; names_in >> n;) cn.push_back(n);
      if (cn.size() > 1)
        return rd.Fail(ta, "functions of several coordinates are unsupported");
      if (!cn.empty()) el.coordinate = cn[0];
      XMLElement* fx = nullptr;
      MOCAP_RETURN_IF_ERROR(FindFunction(rd, ta, {"coordinates", "axis"}, &fx));
      if (fx) {
        MOCAP_RETURN_IF_ERROR(ParseFunction(rd, fx, &el.function));
      } else {
        // OpenSim's default (SpatialTransform::connectToJoint).
        el.function = cn.empty() ? CoordinateFunction::Constant(0.0) : CoordinateFunction::Identity();
      }
      if (el.coordinate.empty() && !el.function.IsConstant())
        return rd.Fail(ta, "a function of no coordinate must be constant");
      (k < 3 ? rotations : translations).push_back(el);
    }
    if (found != 6) return rd.Fail(st, "expected 6 TransformAxis, found " + std::to_string(found));
    // X_FM = [R1 R2 R3, translations in F]: translations first as elements.
    for (auto& e : translations) j->elements.push_back(e);
    for (auto& e : rotations) j->elements.push_back(e);
    return Status::Ok();
  }

  Status ParseBuiltIn(XMLElement* jx, RawJoint* j) {
    struct Axis { ElementKind kind; int axis; int coordinate; };
    const auto R = ElementKind::kRotation;
    const auto T = ElementKind::kTranslation;
    std::vector<Axis> layout;
    const std::string& t = j->type;
    if (t == "PinJoint") layout = {{R, 2, 0}};
    else if (t == "UniversalJoint") layout = {{R, 0, 0}, {R, 1, 1}};
    else if (t == "BallJoint" || t == "GimbalJoint") layout = {{R, 0, 0}, {R, 1, 1}, {R, 2, 2}};
    else if (t == "FreeJoint") layout = {{T, 0, 3}, {T, 1, 4}, {T, 2, 5}, {R, 0, 0}, {R, 1, 1}, {R, 2, 2}};
    else if (t == "SliderJoint") layout = {{T, 0, 0}};
    else if (t == "PlanarJoint") layout = {{T, 0, 1}, {T, 1, 2}, {R, 2, 0}};
    else if (t == "WeldJoint") layout = {};
    else
      return rd.Fail(jx, "unsupported joint type '" + t +
                             "' (supported: CustomJoint, PinJoint, UniversalJoint, BallJoint, "
                             "GimbalJoint, FreeJoint, SliderJoint, PlanarJoint, WeldJoint)");
    const size_t needed = layout.empty() ? 0 : static_cast<size_t>(std::max_element(layout.begin(), layout.end(), [](const Axis& a, const Axis& b) { return a.coordinate < b.coordinate; })->coordinate + 1);
    if (j->coordinates.size() != needed)
      return rd.Fail(jx, "expected " + std::to_string(needed) + " coordinates, found " +
                             std::to_string(j->coordinates.size()));
    for (const Axis& a : layout) {
      RawElement el;
      el.kind = a.kind;
      el.axis = V3::Unit(a.axis);
      el.coordinate = j->coordinates[a.coordinate];
      el.axis_index = a.coordinate;
      j->elements.push_back(el);
    }
    return Status::Ok();
  }

  Status ParseJoint(XMLElement* jx, int child_of_body, std::vector<RawCoordinate>* coords) {
    RawJoint j;
    j.name = NameOf(jx);
    j.type = jx->Name();
    j.xml = jx;
    if (j.name.empty()) return rd.Fail(jx, "joint without a name");
    if (Text(Child(jx, "reverse")) == "true") return rd.Fail(jx, "reversed joints are unsupported");
    if (child_of_body >= -1) {  // 3.x: inside the child body
      j.three = true;
      j.child = child_of_body;
      const std::string parent = Text(Child(jx, "parent_body"));
      const int p = BodyFromPath(parent);
      if (p == -2) return rd.Fail(Child(jx, "parent_body") ? Child(jx, "parent_body") : jx, "no body named '" + parent + "'");
      V3 lp = V3::Zero(), op = V3::Zero(), lc = V3::Zero(), oc = V3::Zero();
      MOCAP_RETURN_IF_ERROR(rd.Vec3(jx, "location_in_parent", &lp, false));
      MOCAP_RETURN_IF_ERROR(rd.Vec3(jx, "orientation_in_parent", &op, false));
      MOCAP_RETURN_IF_ERROR(rd.Vec3(jx, "location", &lc, false));
      MOCAP_RETURN_IF_ERROR(rd.Vec3(jx, "orientation", &oc, false));
      j.parent.body = p;
      j.parent.offset = MakeIso(BodyFixedXYZ(op), lp);
      j.parent.location3 = jx;
      j.child_side.body = child_of_body;
      j.child_side.offset = MakeIso(BodyFixedXYZ(oc), lc);
      j.child_side.location3 = jx;
      MOCAP_RETURN_IF_ERROR(ParseCoordinates(Child(Child(jx, "CoordinateSet"), "objects"), &j, coords));
    } else {
      for (int side = 0; side < 2; ++side) {
        const char* tag = side == 0 ? "socket_parent_frame" : "socket_child_frame";
        XMLElement* sock = Child(jx, tag);
        if (!sock) return rd.Fail(jx, std::string("missing <") + tag + ">");
        FrameSide* fs = side == 0 ? &j.parent : &j.child_side;
        MOCAP_RETURN_IF_ERROR(ResolveFrame(jx, sock, Text(sock), fs, 0));
        fs->socket = sock;
      }
      if (j.child_side.body == kGround)
        return rd.Fail(Child(jx, "socket_child_frame"), "the ground cannot be a joint's child");
      j.child = j.child_side.body;
      MOCAP_RETURN_IF_ERROR(ParseCoordinates(Child(jx, "coordinates"), &j, coords));
    }
    if (j.type == "CustomJoint")
      MOCAP_RETURN_IF_ERROR(ParseCustom(jx, &j));
    else
      MOCAP_RETURN_IF_ERROR(ParseBuiltIn(jx, &j));
    for (const RawElement& el : j.elements)
      if (!el.coordinate.empty() &&
          std::find(j.coordinates.begin(), j.coordinates.end(), el.coordinate) == j.coordinates.end())
        return rd.Fail(el.xml ? el.xml : jx, "coordinate '" + el.coordinate + "' is not one of this joint's coordinates");
    for (const RawJoint& other : map->joints)
      if (other.name == j.name) return rd.Fail(jx, "duplicate joint name");
    map->joints.push_back(std::move(j));
    return Status::Ok();
  }

  Status Run(XMLDocument& doc) {
    XMLElement* root = doc.RootElement();
    if (!root || std::string(root->Name()) != "OpenSimDocument")
      return rd.Fail(root, "expected an <OpenSimDocument> root element");
    map->version = root->IntAttribute("Version", 0);
    out->version = map->version;
    XMLElement* mx = Child(root, "Model");
    if (!mx) return rd.Fail(root, "missing <Model>");
    map->model = mx;
    if (XMLElement* g = Child(mx, "Ground"); g && !NameOf(g).empty()) map->ground = NameOf(g);

    // Bodies (3.x: the body named "ground" is the ground).
    XMLElement* body_objects = Child(Child(mx, "BodySet"), "objects");
    if (!body_objects) return rd.Fail(mx, "missing <BodySet><objects>");
    std::vector<XMLElement*> three_joint_bodies;
    for (XMLElement* b = body_objects->FirstChildElement(); b; b = b->NextSiblingElement()) {
      if (std::string(b->Name()) != "Body") return rd.Fail(b, "unsupported body type");
      const std::string n = NameOf(b);
      if (n.empty()) return rd.Fail(b, "body without a name");
      if (n == "ground" && map->version < 40000) {
        map->ground = n;
        continue;
      }
      if (FindBody(n) >= 0) return rd.Fail(b, "duplicate body name");
      map->body_names.push_back(n);
      map->bodies.push_back(b);
    }
    std::vector<RawCoordinate> coords;
    for (size_t i = 0; i < map->bodies.size(); ++i)
      if (XMLElement* jw = Child(map->bodies[i], "Joint"))
        if (XMLElement* jx = jw->FirstChildElement())
          MOCAP_RETURN_IF_ERROR(ParseJoint(jx, static_cast<int>(i), &coords));
    if (XMLElement* jo = Child(Child(mx, "JointSet"), "objects"))
      for (XMLElement* jx = jo->FirstChildElement(); jx; jx = jx->NextSiblingElement())
        MOCAP_RETURN_IF_ERROR(ParseJoint(jx, -2, &coords));

    // Every body is the child of exactly one joint.
    std::vector<int> joint_of(map->bodies.size(), -1);
    for (size_t k = 0; k < map->joints.size(); ++k) {
      const RawJoint& j = map->joints[k];
      if (joint_of[j.child] >= 0)
        return rd.Fail(j.xml, "body '" + map->body_names[j.child] + "' is already the child of joint '" +
                                  map->joints[joint_of[j.child]].name + "' (closed loops are unsupported)");
      joint_of[j.child] = static_cast<int>(k);
    }
    for (size_t b = 0; b < map->bodies.size(); ++b)
      if (joint_of[b] < 0) return rd.Fail(map->bodies[b], "body is not the child of any joint");

    // Couplers and locks: every coordinate is either free (a model coordinate), or a function of
    // a free one, or constant.
    auto find_coord = [&](const std::string& n) {
      for (size_t i = 0; i < coords.size(); ++i)
        if (coords[i].name == n) return static_cast<int>(i);
      return -1;
    };
    struct Coupler { int independent; CoordinateFunction f; XMLElement* xml; };
    std::map<int, Coupler> couplers;
    if (XMLElement* co = Child(Child(mx, "ConstraintSet"), "objects")) {
      for (XMLElement* c = co->FirstChildElement(); c; c = c->NextSiblingElement()) {
        const std::string tag = c->Name();
        const std::string what = "ConstraintSet: " + tag + " '" + NameOf(c) + "' (line " + std::to_string(c->GetLineNum()) + ")";
        if (tag != "CoordinateCouplerConstraint") {
          out->ignored.push_back(what + ": constraint type not supported, ignored");
          continue;
        }
        // 4.x: isEnforced (default true); 3.x: isDisabled (default false).
        const bool enforced = Child(c, "isEnforced") ? Text(Child(c, "isEnforced")) != "false"
                                                     : Text(Child(c, "isDisabled")) != "true";
        if (!enforced) {
          out->ignored.push_back(what + ": not enforced, ignored");
          continue;
        }
        std::istringstream in(Text(Child(c, "independent_coordinate_names")));
        std::vector<std::string> ind;
        for (std::string n; in >> n;) ind.push_back(n);
        if (ind.size() != 1)
          return rd.Fail(c, "couplers with " + std::to_string(ind.size()) +
                                " independent coordinates are unsupported (exactly one is)");
        const std::string dep = Text(Child(c, "dependent_coordinate_name"));
        const int ii = find_coord(ind[0]), di = find_coord(dep);
        if (ii < 0) return rd.Fail(c, "unknown independent coordinate '" + ind[0] + "'");
        if (di < 0) return rd.Fail(c, "unknown dependent coordinate '" + dep + "'");
        if (ii == di) return rd.Fail(c, "a coordinate coupled to itself");
        if (couplers.count(di)) return rd.Fail(c, "coordinate '" + dep + "' is already coupled");
        XMLElement* fx = nullptr;
        MOCAP_RETURN_IF_ERROR(FindFunction(rd, c, {"isEnforced", "isDisabled", "independent_coordinate_names",
                                                   "dependent_coordinate_name", "scale_factor"}, &fx));
        if (!Child(c, "coupled_coordinates_function") || !fx) return rd.Fail(c, "missing <coupled_coordinates_function>");
        CoordinateFunction f;
        MOCAP_RETURN_IF_ERROR(ParseFunction(rd, fx, &f));
        double scale = 1.0;
        MOCAP_RETURN_IF_ERROR(rd.Number(c, "scale_factor", &scale, false));
        if (scale != 1.0) f = CoordinateFunction::Multiplier(scale, f);
        couplers[di] = {ii, f, c};
      }
    }
    struct Source { int coord; CoordinateFunction f; };
    std::vector<int> state(coords.size(), 0);
    std::vector<Source> resolved(coords.size(), {-1, {}});
    std::function<Status(int)> resolve = [&](int i) -> Status {
      if (state[i] == 2) return Status::Ok();
      if (state[i] == 1) return rd.Fail(couplers.at(i).xml, "coupled coordinates form a cycle");
      state[i] = 1;
      if (auto it = couplers.find(i); it != couplers.end()) {
        MOCAP_RETURN_IF_ERROR(resolve(it->second.independent));
        const Source& s = resolved[it->second.independent];
        resolved[i] = {s.coord, ComposeSimplified(it->second.f, s.f)};
        if (resolved[i].f.IsConstant()) resolved[i].coord = -1;
      } else if (coords[i].locked) {
        resolved[i] = {-1, CoordinateFunction::Constant(coords[i].default_value)};
      } else {
        resolved[i] = {i, CoordinateFunction::Identity()};
      }
      state[i] = 2;
      return Status::Ok();
    };
    for (size_t i = 0; i < coords.size(); ++i) MOCAP_RETURN_IF_ERROR(resolve(static_cast<int>(i)));

    // Motion types (CustomJoint::constructCoordinates): rotational if it is a rotation axis's
    // value with slope 1, translational likewise, else coupled.
    std::vector<OsimMotion> motion(coords.size(), OsimMotion::kCoupled);
    for (const RawJoint& j : map->joints)
      for (const RawElement& el : j.elements) {
        const int c = find_coord(el.coordinate);
        if (c < 0 || motion[c] != OsimMotion::kCoupled) continue;
        const bool unit = el.function.IsIdentity() ||
                          (el.function.kind == CoordinateFunction::Kind::kLinear && el.function.slope == 1.0);
        if (unit) motion[c] = el.kind == ElementKind::kRotation ? OsimMotion::kRotational : OsimMotion::kTranslational;
      }
    std::vector<int> model_index(coords.size(), -1);
    std::vector<Coordinate> coordinates;
    for (size_t i = 0; i < coords.size(); ++i) {
      out->motion[coords[i].name] = motion[i];
      if (resolved[i].coord != static_cast<int>(i)) continue;
      Coordinate c;
      c.name = coords[i].name;
      c.rotational = motion[i] != OsimMotion::kTranslational;
      c.default_value = coords[i].default_value;
      c.min_value = coords[i].lo;
      c.max_value = coords[i].hi;
      c.clamped = coords[i].clamped && coords[i].lo > -1e9 && coords[i].hi < 1e9;
      model_index[i] = static_cast<int>(coordinates.size());
      coordinates.push_back(c);
    }
    std::vector<DerivedCoordinate> derived;
    for (size_t i = 0; i < coords.size(); ++i) {
      if (model_index[i] >= 0) continue;
      DerivedCoordinate dc;
      dc.name = coords[i].name;
      dc.rotational = motion[i] != OsimMotion::kTranslational;
      dc.source = resolved[i].coord >= 0 ? model_index[resolved[i].coord] : -1;
      dc.function = resolved[i].f;
      derived.push_back(dc);
    }

    // Segments, and the joints re-expressed in segment frames (= joint child frames M).
    std::vector<Segment> segments;
    for (const auto& n : map->body_names) segments.push_back({n, 1.0, -1});
    std::vector<Iso> body_to_m(map->bodies.size());  // X_B,M of each body
    for (const RawJoint& j : map->joints) body_to_m[j.child] = j.child_side.offset;
    std::vector<Joint> joints;
    for (const RawJoint& rj : map->joints) {
      Joint j;
      j.name = rj.name;
      j.parent = rj.parent.body;
      j.child = rj.child;
      const Iso m_f = rj.parent.body == kGround ? rj.parent.offset : body_to_m[rj.parent.body].inverse() * rj.parent.offset;
      j.centre = m_f.translation();
      j.orientation = m_f.linear();
      OsimJointInfo info;
      info.type = rj.type;
      info.line = rj.xml->GetLineNum();
      info.parent_offset = rj.parent.offset;
      info.child_offset = rj.child_side.offset;
      for (const RawElement& re : rj.elements) {
        JointElement el;
        el.kind = re.kind;
        el.axis = re.axis;
        if (re.coordinate.empty()) {
          el.function = re.function;
        } else {
          const Source& s = resolved[find_coord(re.coordinate)];
          el.function = ComposeSimplified(re.function, s.f);
          el.coordinate = s.coord >= 0 && !el.function.IsConstant() ? model_index[s.coord] : -1;
        }
        if (el.coordinate < 0 && !el.function.IsConstant())
          return rd.Fail(re.xml ? re.xml : rj.xml, "element depends on no free coordinate but is not constant");
        if (el.coordinate < 0 && el.function.Value(0.0) == 0.0) continue;  // no motion at all
        if (el.coordinate < 0) el.function = CoordinateFunction::Constant(el.function.Value(0.0));
        j.elements.push_back(el);
        info.element_axis.push_back(re.axis_index);
      }
      Classify(rj.type, &j);
      joints.push_back(j);
      out->joints.push_back(info);
    }

    // Markers.
    std::vector<Marker> markers;
    if (XMLElement* mo = Child(Child(mx, "MarkerSet"), "objects")) {
      for (XMLElement* m = mo->FirstChildElement("Marker"); m; m = m->NextSiblingElement("Marker")) {
        Marker mk;
        std::string skip;
        MOCAP_RETURN_IF_ERROR(ParseMarker(m, &mk, body_to_m, &skip));
        if (!skip.empty()) {
          out->ignored.push_back(SkippedMarker(m, skip));
          continue;
        }
        map->markers[mk.name] = m;
        markers.push_back(mk);
      }
    }
    Model model;
    Status s = Model::Build(NameOf(mx).empty() ? "opensim" : NameOf(mx), segments, joints, coordinates, markers, derived, &model);
    if (!s) return Status::Error(rd.source() + ": " + s.message());
    // Model::Build orders joints parents first: keep the info in the same order.
    std::vector<OsimJointInfo> ordered;
    for (const Joint& j : model.joints())
      for (size_t k = 0; k < map->joints.size(); ++k)
        if (map->joints[k].name == j.name) ordered.push_back(out->joints[k]);
    out->joints = ordered;
    out->model = std::move(model);
    return Status::Ok();
  }

  // A marker the fit cannot use -- fixed to the ground, or on a frame that is no body and no
  // joint's offset frame -- is left out with the reason in *skip (empty otherwise), not an error:
  // one such marker in a generic model should not refuse the model's other markers.
  Status ParseMarker(XMLElement* m, Marker* mk, const std::vector<Iso>& body_to_m, std::string* skip) {
    skip->clear();
    mk->name = NameOf(m);
    if (mk->name.empty()) return rd.Fail(m, "marker without a name");
    XMLElement* where = Child(m, "socket_parent_frame");
    if (!where) where = Child(m, "body");
    if (!where) return rd.Fail(m, "missing <socket_parent_frame> (or 3.x <body>)");
    V3 p = V3::Zero();
    MOCAP_RETURN_IF_ERROR(rd.Vec3(m, "location", &p, false));
    // The frame it is on: a body, or (4.x) a PhysicalOffsetFrame of a joint, resolved to its body.
    int b = BodyFromPath(Text(where));
    Iso frame_in_body = Iso::Identity();
    if (b == -2) {
      const std::string name = LastComponent(Text(where));
      for (const RawJoint& rj : map->joints) {
        XMLElement* frames = rj.xml ? Child(rj.xml, "frames") : nullptr;
        bool found = false;
        for (XMLElement* f = frames ? frames->FirstChildElement() : nullptr; f && !found; f = f->NextSiblingElement())
          found = NameOf(f) == name;
        if (!found) continue;
        FrameSide side;
        MOCAP_RETURN_IF_ERROR(ResolveFrame(rj.xml, where, name, &side, 0));
        b = side.body;
        frame_in_body = side.offset;
        break;
      }
    }
    if (b == kGround) {
      *skip = "fixed to the ground: nothing to fit";
      return Status::Ok();
    }
    if (b < 0) {
      *skip = "on '" + Text(where) + "', which is no body and no offset frame of a joint";
      return Status::Ok();
    }
    mk->segment = b;
    mk->position = body_to_m[b].inverse() * (frame_in_body * p);
    mk->fixed = Text(Child(m, "fixed")) == "true";
    return Status::Ok();
  }
  static std::string SkippedMarker(XMLElement* m, const std::string& why) {
    return "MarkerSet: Marker '" + NameOf(m) + "' (line " + std::to_string(m->GetLineNum()) + "): " + why +
           ", left out";
  }

  static void Classify(const std::string& type, Joint* j) {
    int moving_rot = 0, moving_trans = 0, unit = 0;
    for (const JointElement& el : j->elements) {
      if (el.function.IsConstant()) continue;
      (el.kind == ElementKind::kRotation ? moving_rot : moving_trans) += 1;
      if (el.function.IsIdentity()) ++unit;
    }
    const int n = static_cast<int>(j->elements.size());
    const bool all_unit = unit == n;
    j->type = JointType::kCustom;
    (void)type;
    if (moving_rot == 1 && n == 1) j->type = JointType::kHinge;
    else if (moving_rot == 2 && n == 2) j->type = JointType::kUniversal;
    else if (all_unit && moving_rot == 3 && n == 3) j->type = JointType::kSpherical;
    else if (all_unit && moving_rot == 3 && moving_trans == 3 && n == 6 &&
             j->elements[0].kind == ElementKind::kTranslation)
      j->type = JointType::kFree;
    // Fitted axes: a hinge's or universal joint's rotations, and the single moving rotation of
    // a custom joint (e.g. a knee with spline translations).
    const bool fit = j->type == JointType::kHinge || j->type == JointType::kUniversal ||
                     (j->type == JointType::kCustom && moving_rot == 1);
    if (!fit) return;
    for (JointElement& el : j->elements)
      if (el.kind == ElementKind::kRotation && !el.function.IsConstant()) el.fitted_axis = true;
  }
};

Status ParseDocument(XMLDocument* doc, const std::string& text, const std::string& source) {
  doc->Parse(text.data(), text.size());
  if (doc->Error())
    return Status::Error(detail::At(source, doc->ErrorLineNum(),
                                    std::string("not a valid XML document: ") + doc->ErrorName()));
  // tinyxml2 accepts text and further elements beside the root, which export would then write
  // out in a form it does not read back: refuse them.
  int elements = 0;
  for (const tinyxml2::XMLNode* n = doc->FirstChild(); n; n = n->NextSibling()) {
    if (n->ToText())
      return Status::Error(detail::At(source, n->GetLineNum(),
                                      "not a valid XML document: text outside the root element"));
    if (n->ToElement() && ++elements > 1)
      return Status::Error(detail::At(source, n->GetLineNum(),
                                      std::string("not a valid XML document: a second root element <") +
                                          n->Value() + ">"));
  }
  return Status::Ok();
}

// The components the importer finds by path (bodies, joints, frames, coordinates, markers) may
// not have a '/' in their names: it is OpenSim's path separator (OpenSim refuses such a name,
// Component::setName), and a joint named "kn/ee" gave an offset frame "kn/ee_parent_offset" that
// export wrote and import could not find again (found by the fuzzer).
Status CheckComponentNames(const XMLElement* e, const Reader& rd) {
  for (const XMLElement* c = e ? e->FirstChildElement() : nullptr; c; c = c->NextSiblingElement()) {
    const std::string tag = c->Name();
    const bool by_path = tag == "Body" || tag == "PhysicalOffsetFrame" || tag == "Coordinate" || tag == "Marker" ||
                         (tag.size() > 5 && tag.compare(tag.size() - 5, 5, "Joint") == 0);
    if (by_path && NameOf(c).find('/') != std::string::npos)
      return rd.Fail(c, "the name contains '/', OpenSim's path separator, which a component's name may not");
    MOCAP_RETURN_IF_ERROR(CheckComponentNames(c, rd));
  }
  return Status::Ok();
}

Status ImportDocument(XMLDocument* doc, const std::string& source, OsimImport* out, Mapping* map) {
  Importer im{Reader(source), map, out};
  MOCAP_RETURN_IF_ERROR(CheckComponentNames(doc->RootElement(), Reader(source)));
  return im.Run(*doc);
}

std::string Print(XMLDocument* doc) {
  tinyxml2::XMLPrinter printer;
  doc->Print(&printer);
  return std::string(printer.CStr(), printer.CStrSize() > 0 ? printer.CStrSize() - 1 : 0);
}

XMLElement* SetChildText(XMLElement* parent, const char* tag, const std::string& text) {
  XMLElement* e = parent->FirstChildElement(tag);
  if (!e) e = parent->InsertNewChildElement(tag);
  e->SetText(text.c_str());
  return e;
}

void ScaleNumbers(XMLElement* e, double s) {
  if (!e) return;
  std::vector<double> v;
  if (!Reader("").Numbers(e, &v) || v.empty()) return;
  for (double& x : v) x *= s;
  e->SetText(FormatNumbers(v.data(), static_cast<int>(v.size())).c_str());
}

// Writes X_B,F into a joint side: its offset frame, a new offset frame, or the 3.x fields.
void WriteFrame(const RawJoint& rj, bool parent_side, const Mapping& map, const Iso& offset) {
  const FrameSide& fs = parent_side ? rj.parent : rj.child_side;
  if (fs.location3) {
    SetChildText(rj.xml, parent_side ? "location_in_parent" : "location", FormatVec3(offset.translation()));
    SetChildText(rj.xml, parent_side ? "orientation_in_parent" : "orientation",
                 FormatVec3(ToBodyFixedXYZ(offset.linear())));
    return;
  }
  XMLElement* f = fs.offset_xml;
  Iso local = fs.frame_parent.inverse() * offset;
  if (!f) {
    if (offset.isApprox(Iso::Identity(), 0.0)) return;
    XMLElement* frames = rj.xml->FirstChildElement("frames");
    if (!frames) frames = rj.xml->InsertNewChildElement("frames");
    const std::string name = rj.name + (parent_side ? "_parent_offset" : "_child_offset");
    f = frames->InsertNewChildElement("PhysicalOffsetFrame");
    f->SetAttribute("name", name.c_str());
    const std::string body = fs.body == kGround ? "/" + map.ground : "/bodyset/" + map.body_names[fs.body];
    SetChildText(f, "socket_parent", body);
    fs.socket->SetText(name.c_str());
    local = offset;
  }
  SetChildText(f, "translation", FormatVec3(local.translation()));
  SetChildText(f, "orientation", FormatVec3(ToBodyFixedXYZ(local.linear())));
}

// Replaces the function of a TransformAxis by scale * function (a MultiplierFunction, or its
// scale updated), as OpenSim's Scale tool does.
Status ScaleAxisFunction(XMLDocument* doc, const Reader& rd, XMLElement* ta, double s) {
  XMLElement* fx = nullptr;
  MOCAP_RETURN_IF_ERROR(FindFunction(rd, ta, {"coordinates", "axis"}, &fx));
  if (!fx) {  // OpenSim's default function: a LinearFunction or a Constant 0
    fx = ta->InsertNewChildElement("LinearFunction");
    fx->SetAttribute("name", "function");
    SetChildText(fx, "coefficients", "1 0");
  }
  if (std::string(fx->Name()) == "MultiplierFunction") {
    double old = 1.0;
    MOCAP_RETURN_IF_ERROR(rd.Number(fx, "scale", &old, false));
    std::string v;
    detail::AppendShortest(&v, old * s);
    SetChildText(fx, "scale", v);
    return Status::Ok();
  }
  XMLElement* holder = fx->Parent()->ToElement();
  XMLElement* mf = doc->NewElement("MultiplierFunction");
  if (const char* n = fx->Attribute("name")) mf->SetAttribute("name", n);
  holder->InsertAfterChild(fx, mf);
  XMLElement* wrap = mf->InsertNewChildElement("function");
  XMLElement* copy = fx->DeepClone(doc)->ToElement();
  copy->DeleteAttribute("name");
  wrap->InsertEndChild(copy);
  std::string v;
  detail::AppendShortest(&v, s);
  SetChildText(mf, "scale", v);
  holder->DeleteChild(fx);
  return Status::Ok();
}

void ScaleBody(XMLElement* b, double s) {
  ScaleNumbers(b->FirstChildElement("mass_center"), s);
  for (const char* tag : {"inertia", "inertia_xx", "inertia_yy", "inertia_zz", "inertia_xy", "inertia_xz", "inertia_yz"})
    ScaleNumbers(b->FirstChildElement(tag), s * s);
  // Display geometry: every scale_factors below the body except its axes' FrameGeometry.
  std::function<void(XMLElement*)> walk = [&](XMLElement* e) {
    for (XMLElement* c = e->FirstChildElement(); c; c = c->NextSiblingElement()) {
      const std::string tag = c->Name();
      if (tag == "FrameGeometry" || tag == "Joint") continue;
      if (tag == "scale_factors") ScaleNumbers(c, s);
      else if (tag == "translation" && e->Name() && std::string(e->Name()).find("Wrap") != std::string::npos) ScaleNumbers(c, s);
      else walk(c);
    }
  };
  walk(b);
}

}  // namespace

Status ImportOsimText(const std::string& text, const std::string& source, OsimImport* out) {
  XMLDocument doc;
  MOCAP_RETURN_IF_ERROR(ParseDocument(&doc, text, source));
  OsimImport result;
  result.source = source;
  Mapping map;
  MOCAP_RETURN_IF_ERROR(ImportDocument(&doc, source, &result, &map));
  result.xml = text;
  *out = std::move(result);
  return Status::Ok();
}

Status ImportOsim(const std::string& path, OsimImport* out) {
  std::string text;
  MOCAP_RETURN_IF_ERROR(detail::ReadWholeFile(path, &text));
  return ImportOsimText(text, path, out);
}

Status LoadOsimMarkerSet(const std::string& path, OsimImport* import) {
  std::string text;
  MOCAP_RETURN_IF_ERROR(detail::ReadWholeFile(path, &text));
  XMLDocument mdoc;
  MOCAP_RETURN_IF_ERROR(ParseDocument(&mdoc, text, path));
  const Reader rd(path);
  XMLElement* root = mdoc.RootElement();
  XMLElement* set = root && std::string(root->Name()) == "MarkerSet" ? root : Child(root, "MarkerSet");
  if (!set) set = Child(Child(root, "Model"), "MarkerSet");
  XMLElement* objects = Child(set, "objects");
  if (!objects) return rd.Fail(root, "no <MarkerSet><objects> in this file");

  XMLDocument doc;
  MOCAP_RETURN_IF_ERROR(ParseDocument(&doc, import->xml, import->source));
  OsimImport check;
  Mapping map;
  MOCAP_RETURN_IF_ERROR(ImportDocument(&doc, import->source, &check, &map));
  XMLElement* model_set = Child(map.model, "MarkerSet");
  if (!model_set) {
    model_set = map.model->InsertNewChildElement("MarkerSet");
    model_set->SetAttribute("name", "markerset");
  }
  XMLElement* model_objects = Child(model_set, "objects");
  if (!model_objects) model_objects = model_set->InsertNewChildElement("objects");
  // Validate in the marker file's own terms (its name and lines in errors), then merge.
  Importer im{rd, &map, &check};
  std::vector<Iso> identity(map.bodies.size(), Iso::Identity());
  std::vector<std::string> skipped;  // markers left out, kept past the re-import below
  for (XMLElement* m = objects->FirstChildElement("Marker"); m; m = m->NextSiblingElement("Marker")) {
    Marker mk;
    std::string skip;
    MOCAP_RETURN_IF_ERROR(im.ParseMarker(m, &mk, identity, &skip));
    if (!skip.empty()) {
      skipped.push_back(path + ": " + Importer::SkippedMarker(m, skip));
      continue;
    }
    if (auto it = map.markers.find(mk.name); it != map.markers.end()) model_objects->DeleteChild(it->second);
    XMLElement* copy = m->DeepClone(&doc)->ToElement();
    if (XMLElement* body = copy->FirstChildElement("body"); body && map.version >= 40000) {
      // A 4.x document names the marker's frame by path.
      XMLElement* sock = doc.NewElement("socket_parent_frame");
      sock->SetText(("/bodyset/" + Text(body)).c_str());
      copy->InsertAfterChild(body, sock);
      copy->DeleteChild(body);
    }
    model_objects->InsertEndChild(copy);
    map.markers[mk.name] = copy;
  }
  MOCAP_RETURN_IF_ERROR(ImportOsimText(Print(&doc), import->source, import));
  import->ignored.insert(import->ignored.end(), skipped.begin(), skipped.end());
  return Status::Ok();
}

Status ExportOsimText(const Model& fitted, const OsimImport& import, std::string* xml) {
  XMLDocument doc;
  MOCAP_RETURN_IF_ERROR(ParseDocument(&doc, import.xml, import.source));
  OsimImport again;
  Mapping map;
  MOCAP_RETURN_IF_ERROR(ImportDocument(&doc, import.source, &again, &map));
  const Model& base = again.model;
  const std::string who = "cannot export to " + import.source + ": ";
  if (fitted.num_segments() != base.num_segments() || fitted.num_joints() != base.num_joints())
    return Status::Error(who + "the model's segments and joints differ from the imported ones");
  for (int s = 0; s < base.num_segments(); ++s)
    if (fitted.segments()[s].name != base.segments()[s].name)
      return Status::Error(who + "segment " + std::to_string(s) + " is '" + fitted.segments()[s].name +
                           "', the import has '" + base.segments()[s].name + "'");
  for (int j = 0; j < base.num_joints(); ++j) {
    const Joint& a = base.joints()[j];
    const Joint& b = fitted.joints()[j];
    if (a.name != b.name || a.parent != b.parent || a.child != b.child || a.elements.size() != b.elements.size())
      return Status::Error(who + "joint '" + b.name + "' differs from the imported joint '" + a.name + "'");
  }
  const Reader rd(import.source);
  auto raw_of = [&](const std::string& n) -> const RawJoint& {
    for (const RawJoint& r : map.joints)
      if (r.name == n) return r;
    return map.joints.front();  // names were checked above
  };
  auto scale_of = [&](int s) { return s < 0 ? 1.0 : fitted.segments()[s].scale; };
  // X_B,M of each body after scaling (the body keeps its place relative to scaled geometry).
  std::vector<Iso> body_to_m(base.num_segments());
  for (const Joint& j : base.joints()) {
    const RawJoint& rj = raw_of(j.name);
    body_to_m[j.child] = MakeIso(rj.child_side.offset.linear(), scale_of(j.child) * rj.child_side.offset.translation());
  }
  for (int k = 0; k < fitted.num_joints(); ++k) {
    const Joint& j = fitted.joints()[k];
    const RawJoint& rj = raw_of(j.name);
    const double sp = scale_of(j.parent);
    Iso m_f = MakeIso(j.orientation, sp * j.centre);
    Iso parent = j.parent < 0 ? m_f : body_to_m[j.parent] * m_f;
    Iso child = body_to_m[j.child];
    // Fitted axes of the built-in joints, by the joint's own axis index (a locked coordinate
    // leaves its element out or constant).
    V3 builtin_axis[2] = {V3::UnitX(), V3::UnitY()};
    bool moved = false;
    if (rj.type == "PinJoint" || rj.type == "UniversalJoint") {
      const OsimJointInfo& info = again.joints[k];
      for (size_t e = 0; e < j.elements.size(); ++e) {
        if (!j.elements[e].fitted_axis) continue;
        const int axis = info.element_axis[e];
        const V3 original = rj.type == "PinJoint" ? V3::UnitZ() : V3::Unit(axis);
        if (axis < 2) builtin_axis[axis] = j.elements[e].axis.normalized();
        moved = moved || !j.elements[e].axis.isApprox(original, 1e-15);
      }
    }
    if (rj.type == "PinJoint" && moved) {
      // Turn both frames so that their z is the fitted axis: Q Rz(q) Q^T is the rotation about Qz.
      const M3 q = Eigen::Quaterniond::FromTwoVectors(V3::UnitZ(), builtin_axis[0]).toRotationMatrix();
      parent.linear() = parent.linear() * q;
      child.linear() = child.linear() * q;
    }
    WriteFrame(rj, true, map, parent);
    WriteFrame(rj, false, map, child);
    if (rj.type == "UniversalJoint" && moved) {
      // Two arbitrary axes are not a UniversalJoint any more: write the same motion as a
      // CustomJoint (same coordinates, frames and names).
      rj.xml->SetName("CustomJoint");
      XMLElement* st = rj.xml->InsertNewChildElement("SpatialTransform");
      const V3 axes[6] = {builtin_axis[0], builtin_axis[1], builtin_axis[0].cross(builtin_axis[1]).normalized(),
                          V3::UnitX(), V3::UnitY(), V3::UnitZ()};
      const char* names[6] = {"rotation1", "rotation2", "rotation3", "translation1", "translation2", "translation3"};
      for (int i = 0; i < 6; ++i) {
        XMLElement* ta = st->InsertNewChildElement("TransformAxis");
        ta->SetAttribute("name", names[i]);
        SetChildText(ta, "coordinates", i < 2 ? rj.coordinates[i] : "");
        SetChildText(ta, "axis", FormatVec3(axes[i]));
        XMLElement* f = ta->InsertNewChildElement(i < 2 ? "LinearFunction" : "Constant");
        f->SetAttribute("name", "function");
        SetChildText(f, i < 2 ? "coefficients" : "value", i < 2 ? "1 0" : "0");
      }
    }
    if (rj.type == "CustomJoint") {
      const OsimJointInfo& info = again.joints[k];
      for (size_t e = 0; e < j.elements.size(); ++e) {
        const int axis = info.element_axis[e];
        const RawElement* re = nullptr;
        for (const RawElement& r : rj.elements)
          if (r.axis_index == axis) re = &r;
        if (!re || !re->xml) continue;
        const JointElement& el = j.elements[e];
        if (el.fitted_axis) SetChildText(re->xml, "axis", FormatVec3(el.axis.normalized()));
        if (ScalesWithParent(j, el) && sp != 1.0)
          MOCAP_RETURN_IF_ERROR(ScaleAxisFunction(&doc, rd, re->xml, sp));
      }
    }
  }
  // Bodies, and path points fixed on them.
  for (int s = 0; s < base.num_segments(); ++s)
    if (scale_of(s) != 1.0) ScaleBody(map.bodies[s], scale_of(s));
  std::function<void(XMLElement*)> walk = [&](XMLElement* e) {
    for (XMLElement* c = e->FirstChildElement(); c; c = c->NextSiblingElement()) {
      const std::string tag = c->Name();
      if (tag == "PathPoint" || tag == "ConditionalPathPoint") {
        XMLElement* where = c->FirstChildElement("socket_parent_frame");
        if (!where) where = c->FirstChildElement("body");
        const int b = where ? base.FindSegment(LastComponent(Text(where))) : -1;
        if (b >= 0 && scale_of(b) != 1.0) ScaleNumbers(c->FirstChildElement("location"), scale_of(b));
      } else if (tag != "BodySet" && tag != "JointSet" && tag != "MarkerSet") {
        walk(c);
      }
    }
  };
  walk(map.model);
  // Markers: p_B = X_B,M (s m).
  for (const Marker& mk : fitted.markers()) {
    auto it = map.markers.find(mk.name);
    XMLElement* m = it == map.markers.end() ? nullptr : it->second;
    const std::string body = fitted.segments()[mk.segment].name;
    if (!m) {
      XMLElement* set = Child(map.model, "MarkerSet");
      if (!set) {
        set = map.model->InsertNewChildElement("MarkerSet");
        set->SetAttribute("name", "markerset");
      }
      XMLElement* objects = Child(set, "objects");
      if (!objects) objects = set->InsertNewChildElement("objects");
      m = objects->InsertNewChildElement("Marker");
      m->SetAttribute("name", mk.name.c_str());
      SetChildText(m, map.version >= 40000 ? "socket_parent_frame" : "body",
                   map.version >= 40000 ? "/bodyset/" + body : body);
      SetChildText(m, "fixed", "false");
    } else if (XMLElement* sock = m->FirstChildElement("socket_parent_frame")) {
      sock->SetText(("/bodyset/" + body).c_str());
    } else if (XMLElement* b = m->FirstChildElement("body")) {
      b->SetText(body.c_str());
    }
    const V3 p = body_to_m[mk.segment] * (scale_of(mk.segment) * mk.position);
    SetChildText(m, "location", FormatVec3(p));
  }
  *xml = Print(&doc);
  return Status::Ok();
}

Status ExportOsim(const Model& fitted, const OsimImport& import, const std::string& path) {
  std::string xml;
  MOCAP_RETURN_IF_ERROR(ExportOsimText(fitted, import, &xml));
  return detail::WriteWholeFile(path, xml);
}

Status WriteOsimMot(const std::string& path, const OsimImport& import, const Model& model,
                    const std::vector<double>& times, const Eigen::MatrixXd& poses) {
  if (poses.cols() != model.num_coordinates() || static_cast<Eigen::Index>(times.size()) != poses.rows())
    return Status::Error(path + ": cannot write MOT: " + std::to_string(poses.rows()) + " poses of " +
                         std::to_string(poses.cols()) + " coordinates for " + std::to_string(times.size()) +
                         " times and a model of " + std::to_string(model.num_coordinates()) + " coordinates");
  CoordinateTable table;
  table.in_degrees = true;
  table.times = times;
  std::vector<double> unit;
  auto add = [&](const std::string& name, bool rotational) {
    table.column_names.push_back(name);
    auto it = import.motion.find(name);
    const bool degrees = it != import.motion.end() ? it->second == OsimMotion::kRotational : rotational;
    unit.push_back(degrees ? kDegPerRad : 1.0);
  };
  for (const Coordinate& c : model.coordinates()) add(c.name, c.rotational);
  for (const DerivedCoordinate& d : model.derived_coordinates()) add(d.name, d.rotational);
  table.values.resize(poses.rows(), static_cast<Eigen::Index>(unit.size()));
  for (Eigen::Index f = 0; f < poses.rows(); ++f) {
    const Eigen::VectorXd z = poses.row(f).transpose();
    for (int c = 0; c < model.num_coordinates(); ++c) table.values(f, c) = z[c] * unit[c];
    for (size_t d = 0; d < model.derived_coordinates().size(); ++d) {
      const size_t col = model.num_coordinates() + d;
      table.values(f, col) = model.derived_coordinates()[d].Value(z) * unit[col];
    }
  }
  return WriteMot(path, table);
}

}  // namespace mocap::formats
