#include "model/compare.h"

#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <Eigen/SVD>
#include <algorithm>
#include <cmath>
#include <functional>
#include <nlohmann/json.hpp>
#include <optional>

#include "model/kinematics.h"
#include "model/rigid_align.h"

namespace mocap {
namespace {

constexpr double kMm = 1000.0;
constexpr double kDeg = 180.0 / M_PI;

using Eigen::Vector3d;

bool Varying(const JointElement& el) {
  return el.coordinate >= 0 && !el.function.IsConstant();
}

bool HasTranslation(const Joint& j) {
  for (const auto& el : j.elements)
    if (el.kind == ElementKind::kTranslation) return true;
  return false;
}

// The element of j's one moving rotation, or -1 if it has none or several.
int SingleMovingRotation(const Joint& j) {
  int found = -1;
  for (size_t e = 0; e < j.elements.size(); ++e) {
    if (j.elements[e].kind != ElementKind::kRotation || !Varying(j.elements[e])) continue;
    if (found >= 0) return -1;
    found = static_cast<int>(e);
  }
  return found;
}

// The element a hinge turns about, or -1 if j is not a hinge (one moving rotation, no
// translation: then its centre may slide along the axis without changing any marker).
int HingeElement(const Joint& j) {
  if (j.type != JointType::kHinge || HasTranslation(j)) return -1;
  return SingleMovingRotation(j);
}

// An element's axis is fixed in the parent if no moving rotation comes before it, and in the
// child if none comes after it. Elsewhere its direction depends on a coordinate.
bool AxisFixedInParent(const Joint& j, int e) {
  for (int i = 0; i < e; ++i)
    if (j.elements[i].kind == ElementKind::kRotation && Varying(j.elements[i])) return false;
  return true;
}
bool AxisFixedInChild(const Joint& j, int e) {
  for (size_t i = e + 1; i < j.elements.size(); ++i)
    if (j.elements[i].kind == ElementKind::kRotation && Varying(j.elements[i])) return false;
  return true;
}

// x -> R x + t, taking B's coordinates to A's.
using Rigid = RigidTransform;
std::optional<Rigid> Align(const Eigen::Matrix3Xd& src, const Eigen::Matrix3Xd& dst) {
  return RigidAlign(src, dst);
}

// One model at the zero pose.
struct Posed {
  explicit Posed(const Model& m) : model(m), geometry(m), data(m) {
    ForwardKinematics(m, geometry, Eigen::VectorXd::Zero(m.num_coordinates()), &data);
  }
  Vector3d ToFrame(int s, const Vector3d& world) const {
    return data.segment_rotation[s].transpose() * (world - data.segment_position[s]);
  }
  Vector3d CentreWorld(int j) const {
    const Joint& jt = model.joints()[j];
    if (jt.parent < 0) return geometry.centre_scaled[j];
    return data.segment_position[jt.parent] +
           data.segment_rotation[jt.parent] * geometry.centre_scaled[j];
  }
  // Joint j's centre in segment s's frame (s = -1: the world).
  Vector3d Centre(int j, int s) const {
    if (s < 0) return CentreWorld(j);
    if (s == model.joints()[j].parent) return geometry.centre_scaled[j];
    return ToFrame(s, CentreWorld(j));
  }
  Vector3d Axis(int j, int e, int s) const {
    const Vector3d w = (data.element_rotation[j][e] * geometry.axis[j][e]).normalized();
    return s < 0 ? w : Vector3d(data.segment_rotation[s].transpose() * w);
  }
  Vector3d Marker(int m, int s) const {
    if (s < 0) return MarkerPosition(model, geometry, data, m);
    return geometry.marker_scaled[m];  // s is the marker's own segment
  }

  const Model& model;
  Geometry geometry;
  ModelData data;
};

// How B's quantities are brought to A's: through a segment's alignment, the union alignment of
// two segments in the world, or as they are in a segment's frame.
struct Basis {
  std::string name;
  int segment_a = -1, segment_b = -1;  // -1: the world at the zero pose
  Rigid map;
};

// A joint end as seen in one segment's frame: its centre, or a hinge's axis line.
struct Feature {
  Vector3d point;
  Vector3d direction = Vector3d::Zero();
  bool line = false;
};

double PointLine(const Vector3d& p, const Vector3d& q, const Vector3d& u) {
  const Vector3d w = p - q;
  return (w - w.dot(u) * u).norm();
}

double Distance(const Feature& f, const Feature& g) {
  if (!f.line && !g.line) return (f.point - g.point).norm();
  if (!f.line) return PointLine(f.point, g.point, g.direction);
  if (!g.line) return PointLine(g.point, f.point, f.direction);
  const Vector3d n = f.direction.cross(g.direction);
  if (n.norm() < 1e-9) return PointLine(f.point, g.point, g.direction);  // parallel
  return std::abs((f.point - g.point).dot(n)) / n.norm();
}

Feature JointFeature(const Posed& posed, int j, int s) {
  Feature f;
  f.point = posed.Centre(j, s);
  const int he = HingeElement(posed.model.joints()[j]);
  if (he >= 0) {
    f.line = true;
    f.direction = posed.Axis(j, he, s);
  }
  return f;
}

double AngleDeg(const Vector3d& a, const Vector3d& b) {
  const Vector3d u = a.normalized(), v = b.normalized();
  return std::atan2(u.cross(v).norm(), u.dot(v)) * kDeg;
}

ErrorStats Stats(const std::vector<double>& values) {
  ErrorStats s;
  double sum_sq = 0;
  for (double v : values) {
    if (!std::isfinite(v)) continue;
    s.max = std::max(s.max, std::abs(v));
    sum_sq += v * v;
    ++s.count;
  }
  if (s.count > 0) s.rms = std::sqrt(sum_sq / s.count);
  return s;
}

std::string SegmentName(const Model& m, int s) { return s < 0 ? "ground" : m.segments()[s].name; }

std::string ElementText(const Model& m, const JointElement& el) {
  std::string t = el.kind == ElementKind::kRotation ? "rotation" : "translation";
  t += el.coordinate >= 0 ? " of '" + m.coordinates()[el.coordinate].name + "'" : " (no coordinate)";
  if (el.fitted_axis) t += ", fitted axis";
  if (el.function.kind != CoordinateFunction::Kind::kIdentity)
    t += std::string(", ") + CoordinateFunction::KindName(el.function.kind);
  return t;
}

template <typename T, typename Find>
Status MatchNames(const std::vector<T>& in_a, const std::vector<T>& in_b, const char* what,
                  Find find_in_b, Find find_in_a, std::vector<int>* b_of_a) {
  b_of_a->assign(in_a.size(), -1);
  for (size_t i = 0; i < in_a.size(); ++i) {
    (*b_of_a)[i] = find_in_b(in_a[i].name);
    if ((*b_of_a)[i] < 0)
      return Status::Error(std::string(what) + " '" + in_a[i].name + "' is in A but not in B");
  }
  for (const auto& item : in_b)
    if (find_in_a(item.name) < 0)
      return Status::Error(std::string(what) + " '" + item.name + "' is in B but not in A");
  return Status::Ok();
}

Status CheckTopology(const Model& a, const Model& b, std::vector<int>* segment_b,
                     std::vector<int>* joint_b) {
  using FindFn = std::function<int(const std::string&)>;
  FindFn seg_b = [&](const std::string& n) { return b.FindSegment(n); };
  FindFn seg_a = [&](const std::string& n) { return a.FindSegment(n); };
  if (Status s = MatchNames(a.segments(), b.segments(), "segment", seg_b, seg_a, segment_b); !s)
    return s;
  std::vector<int> coordinate_b;
  FindFn crd_b = [&](const std::string& n) { return b.FindCoordinate(n); };
  FindFn crd_a = [&](const std::string& n) { return a.FindCoordinate(n); };
  if (Status s = MatchNames(a.coordinates(), b.coordinates(), "coordinate", crd_b, crd_a,
                            &coordinate_b);
      !s)
    return s;
  FindFn jnt_b = [&](const std::string& n) { return b.FindJoint(n); };
  FindFn jnt_a = [&](const std::string& n) { return a.FindJoint(n); };
  if (Status s = MatchNames(a.joints(), b.joints(), "joint", jnt_b, jnt_a, joint_b); !s) return s;

  for (int ja = 0; ja < a.num_joints(); ++ja) {
    const Joint& x = a.joints()[ja];
    const Joint& y = b.joints()[(*joint_b)[ja]];
    const std::string where = "joint '" + x.name + "': ";
    auto differ = [&](const std::string& what, const std::string& in_a, const std::string& in_b) {
      return Status::Error(where + what + " is " + in_a + " in A but " + in_b + " in B");
    };
    if (SegmentName(a, x.parent) != SegmentName(b, y.parent))
      return differ("parent", "'" + SegmentName(a, x.parent) + "'", "'" + SegmentName(b, y.parent) + "'");
    if (SegmentName(a, x.child) != SegmentName(b, y.child))
      return differ("child", "'" + SegmentName(a, x.child) + "'", "'" + SegmentName(b, y.child) + "'");
    if (x.type != y.type) return differ("type", ToString(x.type), ToString(y.type));
    if (x.elements.size() != y.elements.size())
      return differ("the number of elements", std::to_string(x.elements.size()),
                    std::to_string(y.elements.size()));
    for (size_t e = 0; e < x.elements.size(); ++e) {
      const std::string ta = ElementText(a, x.elements[e]), tb = ElementText(b, y.elements[e]);
      if (ta != tb) return differ("element " + std::to_string(e), ta, tb);
    }
  }
  return Status::Ok();
}

}  // namespace

int AlongAxisGaugeElement(const Joint& j) { return j.parent < 0 ? -1 : SingleMovingRotation(j); }

Status CompareModels(const Model& a, const Model& b, ModelComparison* out) {
  std::vector<int> segment_b, joint_b;
  if (Status s = CheckTopology(a, b, &segment_b, &joint_b); !s) return s;

  ModelComparison result;
  // Markers by name; per A segment, the (A, B) marker pairs on it.
  const int ns = a.num_segments();
  std::vector<std::vector<std::pair<int, int>>> pairs(ns);
  std::vector<std::pair<int, int>> matched;
  for (int ma = 0; ma < a.num_markers(); ++ma) {
    const Marker& mk = a.markers()[ma];
    const int mb = b.FindMarker(mk.name);
    if (mb < 0) {
      result.markers_only_in_a.push_back(mk.name);
      continue;
    }
    const int sb = b.markers()[mb].segment;
    if (sb != segment_b[mk.segment])
      return Status::Error("marker '" + mk.name + "' is on segment '" +
                           a.segments()[mk.segment].name + "' in A but on '" +
                           b.segments()[sb].name + "' in B");
    pairs[mk.segment].emplace_back(ma, mb);
    matched.emplace_back(ma, mb);
  }
  for (const Marker& mk : b.markers())
    if (a.FindMarker(mk.name) < 0) result.markers_only_in_b.push_back(mk.name);

  const Posed pa(a), pb(b);

  // Markers of segments (A indices; -1 skipped) in frame s (s = -1: the world), B then A.
  auto collect = [&](std::initializer_list<int> segments, bool world, Eigen::Matrix3Xd* src,
                     Eigen::Matrix3Xd* dst) {
    int n = 0;
    for (int s : segments) n += static_cast<int>(pairs[s].size());
    src->resize(3, n);
    dst->resize(3, n);
    int c = 0;
    for (int s : segments)
      for (auto [ma, mb] : pairs[s]) {
        src->col(c) = pb.Marker(mb, world ? -1 : segment_b[s]);
        dst->col(c) = pa.Marker(ma, world ? -1 : s);
        ++c;
      }
  };

  // Each segment's own alignment.
  std::vector<std::optional<Rigid>> align(ns);
  for (int s = 0; s < ns; ++s) {
    Eigen::Matrix3Xd src, dst;
    collect({s}, false, &src, &dst);
    align[s] = Align(src, dst);
  }
  auto segment_basis = [&](int s) {
    return Basis{a.segments()[s].name, s, segment_b[s], align[s] ? *align[s] : Rigid{}};
  };
  // A segment's alignment for measuring joint `exclude`: its markers plus the centres of its
  // other joints that marker data determine (not the root's, not a hinge's, whose point along
  // the axis is free). Thighs and shanks carry two markers in the Plug-in Gait set; with the
  // hip or ankle centre they are aligned without falling back to the zero pose, where a hinge's
  // zero angle (a convention) would count as error.
  std::vector<std::vector<std::optional<Rigid>>> align_without(ns);
  auto aligned_without = [&](int s, int exclude) -> const std::optional<Rigid>& {
    auto& cache = align_without[s];
    if (cache.empty()) cache.resize(a.num_joints() + 1);
    auto& slot = cache[exclude + 1];
    if (slot) return slot;
    Eigen::Matrix3Xd src, dst;
    collect({s}, false, &src, &dst);
    std::vector<std::pair<Vector3d, Vector3d>> extra;
    const Vector3d centroid_b = src.cols() > 0 ? Vector3d(src.rowwise().mean()) : Vector3d::Zero();
    const Vector3d centroid_a = dst.cols() > 0 ? Vector3d(dst.rowwise().mean()) : Vector3d::Zero();
    for (int j = 0; j < a.num_joints(); ++j) {
      const Joint& jt = a.joints()[j];
      if (j == exclude || (jt.parent != s && jt.child != s)) continue;
      if (jt.parent < 0 || HasTranslation(jt)) continue;
      const int he = HingeElement(jt);
      if (he < 0) {
        extra.emplace_back(pb.Centre(joint_b[j], segment_b[s]), pa.Centre(j, s));
        continue;
      }
      // A hinge fixes a line: use its point nearest the markers' centroid, and one 10 cm along it.
      auto on_axis = [](const Vector3d& q, const Vector3d& u, const Vector3d& c) {
        return Vector3d(q + (c - q).dot(u) * u);
      };
      const Vector3d ub = pb.Axis(joint_b[j], he, segment_b[s]), ua = pa.Axis(j, he, s);
      const Vector3d qb = on_axis(pb.Centre(joint_b[j], segment_b[s]), ub, centroid_b);
      const Vector3d qa = on_axis(pa.Centre(j, s), ua, centroid_a);
      extra.emplace_back(qb, qa);
      extra.emplace_back(qb + 0.1 * ub, qa + 0.1 * ua);
    }
    const Eigen::Index n = src.cols();
    src.conservativeResize(3, n + extra.size());
    dst.conservativeResize(3, n + extra.size());
    for (size_t k = 0; k < extra.size(); ++k) {
      src.col(n + k) = extra[k].first;
      dst.col(n + k) = extra[k].second;
    }
    slot = Align(src, dst);
    return slot;
  };
  auto segment_basis_without = [&](int s, int exclude) {
    const auto& r = aligned_without(s, exclude);
    const bool markers_only = align[s].has_value();
    return Basis{a.segments()[s].name + (markers_only ? "" : "+centres"), s, segment_b[s],
                 markers_only ? *align[s] : (r ? *r : Rigid{})};
  };
  // The fallback when none of the wanted segments can be aligned.
  auto fallback_basis = [&](int p, int c, int frame) {
    Eigen::Matrix3Xd src, dst;
    collect({p, c}, true, &src, &dst);
    if (auto r = Align(src, dst))
      return Basis{"union(" + a.segments()[p].name + "," + a.segments()[c].name + ")", -1, -1, *r};
    Basis basis = segment_basis(frame);
    basis.name = "unaligned(" + basis.name + ")";
    basis.map = Rigid{};
    return basis;
  };
  auto join = [](const std::vector<Basis>& bases) {
    std::string n;
    for (const auto& basis : bases) n += (n.empty() ? "" : "+") + basis.name;
    return n;
  };

  // Joints.
  std::vector<double> centre_errors, axis_errors;
  for (int ja = 0; ja < a.num_joints(); ++ja) {
    const Joint& jt = a.joints()[ja];
    if (jt.parent < 0) continue;  // the root's centre trades with the root translation: a gauge
    const int jb = joint_b[ja];
    const int p = jt.parent, c = jt.child;
    const int he = AlongAxisGaugeElement(jt);
    JointDifference jd;
    jd.joint = jt.name;
    jd.type = jt.type;
    jd.hinge = he >= 0;

    std::vector<Basis> bases;
    if (aligned_without(p, ja)) bases.push_back(segment_basis_without(p, ja));
    if (aligned_without(c, ja) && !HasTranslation(jt)) bases.push_back(segment_basis_without(c, ja));
    if (bases.empty()) bases.push_back(fallback_basis(p, c, p));
    double worst = 0;
    for (const Basis& basis : bases) {
      Vector3d d = basis.map.Point(pb.Centre(jb, basis.segment_b)) - pa.Centre(ja, basis.segment_a);
      if (he >= 0) {
        const Vector3d u = pa.Axis(ja, he, basis.segment_a);
        d -= d.dot(u) * u;
      }
      worst = std::max(worst, d.norm() * kMm);
    }
    jd.centre_error_mm = worst;
    jd.basis = join(bases);
    centre_errors.push_back(worst);

    for (size_t e = 0; e < jt.elements.size(); ++e) {
      if (!jt.elements[e].fitted_axis) continue;
      const int ei = static_cast<int>(e);
      AxisDifference ad;
      ad.element = ei;
      ad.coordinate = jt.elements[e].coordinate >= 0 ? a.coordinates()[jt.elements[e].coordinate].name : "";
      const bool in_p = AxisFixedInParent(jt, ei), in_c = AxisFixedInChild(jt, ei);
      std::vector<Basis> axis_bases;
      if (in_p && aligned_without(p, -1)) axis_bases.push_back(segment_basis_without(p, -1));
      if (in_c && aligned_without(c, -1)) axis_bases.push_back(segment_basis_without(c, -1));
      if (axis_bases.empty()) axis_bases.push_back(fallback_basis(p, c, in_p || !in_c ? p : c));
      double angle = 0;
      for (const Basis& basis : axis_bases)
        angle = std::max(angle, AngleDeg(pa.Axis(ja, ei, basis.segment_a),
                                         basis.map.Direction(pb.Axis(jb, ei, basis.segment_b))));
      ad.error_deg = angle;
      ad.basis = join(axis_bases);
      axis_errors.push_back(angle);
      jd.axis_error_deg = std::isnan(jd.axis_error_deg) ? angle : std::max(jd.axis_error_deg, angle);
      jd.axes.push_back(ad);
    }
    result.joints.push_back(std::move(jd));
  }

  // Segment lengths, in each segment's own frame (distances need no alignment).
  std::vector<double> length_errors;
  for (int s = 0; s < ns; ++s) {
    std::vector<int> children;
    for (int ja = 0; ja < a.num_joints(); ++ja)
      if (a.joints()[ja].parent == s) children.push_back(ja);
    const int proximal = a.segments()[s].joint;
    auto add = [&](int from, int to, const std::string& name) {
      SegmentDifference sd;
      sd.name = name;
      sd.segment = a.segments()[s].name;
      sd.from = a.joints()[from].name;
      sd.to = a.joints()[to].name;
      const int sb = segment_b[s];
      sd.length_a_mm = Distance(JointFeature(pa, from, s), JointFeature(pa, to, s)) * kMm;
      sd.length_b_mm =
          Distance(JointFeature(pb, joint_b[from], sb), JointFeature(pb, joint_b[to], sb)) * kMm;
      if (sd.length_a_mm > 1e-6)
        sd.error_pct = 100.0 * (sd.length_b_mm - sd.length_a_mm) / sd.length_a_mm;
      length_errors.push_back(sd.error_pct);
      result.segments.push_back(sd);
    };
    if (a.joints()[proximal].parent >= 0) {
      for (int k : children) add(proximal, k, a.segments()[s].name + "->" + a.joints()[k].name);
    } else {
      // The root segment's origin is a gauge: lengths between its child joints instead.
      for (size_t i = 0; i < children.size(); ++i)
        for (size_t k = i + 1; k < children.size(); ++k)
          add(children[i], children[k], a.segments()[s].name + ":" + a.joints()[children[i]].name +
                                            "-" + a.joints()[children[k]].name);
    }
  }

  // Markers.
  std::vector<double> marker_errors;
  for (auto [ma, mb] : matched) {
    const int s = a.markers()[ma].segment;
    MarkerDifference md;
    md.marker = a.markers()[ma].name;
    md.segment = a.segments()[s].name;
    // Segments with fewer than 3 markers borrow their determined joint centres (see above).
    const std::optional<Rigid>& r = align[s] ? align[s] : aligned_without(s, -1);
    md.aligned = r.has_value();
    const Rigid map = md.aligned ? *r : Rigid{};
    md.error_mm = (map.Point(pb.Marker(mb, segment_b[s])) - pa.Marker(ma, s)).norm() * kMm;
    marker_errors.push_back(md.error_mm);
    result.markers.push_back(md);
  }

  result.joint_centre_error_mm = Stats(centre_errors);
  result.axis_error_deg = Stats(axis_errors);
  result.segment_length_error_pct = Stats(length_errors);
  result.marker_error_mm = Stats(marker_errors);
  *out = std::move(result);
  return Status::Ok();
}

std::string ComparisonToJsonString(const ModelComparison& c) {
  using json = nlohmann::ordered_json;
  auto stats = [](const ErrorStats& s) {
    return json{{"max", s.max}, {"rms", s.rms}, {"count", s.count}};
  };
  auto number = [](json* j, const char* key, double v) {
    if (std::isfinite(v)) (*j)[key] = v;
  };
  json doc;
  doc["joint_centre_error_mm"] = stats(c.joint_centre_error_mm);
  doc["axis_error_deg"] = stats(c.axis_error_deg);
  doc["segment_length_error_pct"] = stats(c.segment_length_error_pct);
  doc["marker_error_mm"] = stats(c.marker_error_mm);
  doc["joints"] = json::array();
  for (const auto& jd : c.joints) {
    json j = {{"joint", jd.joint}, {"type", ToString(jd.type)}, {"hinge", jd.hinge}};
    number(&j, "centre_error_mm", jd.centre_error_mm);
    number(&j, "axis_error_deg", jd.axis_error_deg);
    j["basis"] = jd.basis;
    if (!jd.axes.empty()) {
      j["axes"] = json::array();
      for (const auto& ad : jd.axes) {
        json x = {{"element", ad.element}, {"coordinate", ad.coordinate}};
        number(&x, "error_deg", ad.error_deg);
        x["basis"] = ad.basis;
        j["axes"].push_back(x);
      }
    }
    doc["joints"].push_back(j);
  }
  doc["segments"] = json::array();
  for (const auto& sd : c.segments) {
    json j = {{"name", sd.name}, {"segment", sd.segment}, {"from", sd.from}, {"to", sd.to},
              {"length_a_mm", sd.length_a_mm}, {"length_b_mm", sd.length_b_mm}};
    number(&j, "error_pct", sd.error_pct);
    doc["segments"].push_back(j);
  }
  doc["markers"] = json::array();
  for (const auto& md : c.markers)
    doc["markers"].push_back({{"marker", md.marker}, {"segment", md.segment},
                              {"error_mm", md.error_mm}, {"aligned", md.aligned}});
  doc["markers_only_in_a"] = c.markers_only_in_a;
  doc["markers_only_in_b"] = c.markers_only_in_b;
  return doc.dump(1);
}

}  // namespace mocap
