#include "model/model.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <set>

namespace mocap {

const char* ToString(JointType type) {
  switch (type) {
    case JointType::kFree: return "free";
    case JointType::kSpherical: return "spherical";
    case JointType::kUniversal: return "universal";
    case JointType::kHinge: return "hinge";
    case JointType::kCustom: return "custom";
  }
  return "?";
}

const char* ToString(ParameterGroup group) {
  switch (group) {
    case ParameterGroup::kScale: return "scales";
    case ParameterGroup::kCentre: return "centres";
    case ParameterGroup::kAxis: return "axes";
    case ParameterGroup::kMarker: return "markers";
  }
  return "?";
}

Eigen::Matrix<double, 3, 2> TangentBasis(const Eigen::Vector3d& axis) {
  // Cross with the world axis least aligned with `axis`, so the basis is well conditioned.
  Eigen::Vector3d a = axis.normalized();
  Eigen::Index k;
  a.cwiseAbs().minCoeff(&k);
  Eigen::Vector3d e2 = a.cross(Eigen::Vector3d::Unit(k)).normalized();
  Eigen::Vector3d e3 = a.cross(e2);
  Eigen::Matrix<double, 3, 2> basis;
  basis << e2, e3;
  return basis;
}

void AxisFromAngles(const Eigen::Vector3d& e1, const Eigen::Matrix<double, 3, 2>& basis,
                    double alpha, double beta, Eigen::Vector3d* axis, Eigen::Vector3d* d_alpha,
                    Eigen::Vector3d* d_beta) {
  const double ca = std::cos(alpha), sa = std::sin(alpha), cb = std::cos(beta),
               sb = std::sin(beta);
  const Eigen::Vector3d in_plane = ca * e1 + sa * basis.col(0);
  *axis = cb * in_plane + sb * basis.col(1);
  if (d_alpha) *d_alpha = cb * (-sa * e1 + ca * basis.col(0));
  if (d_beta) *d_beta = -sb * in_plane + cb * basis.col(1);
}

namespace {
template <typename T>
int FindByName(const std::vector<T>& items, const std::string& n) {
  for (size_t i = 0; i < items.size(); ++i)
    if (items[i].name == n) return static_cast<int>(i);
  return -1;
}
template <typename T>
Status CheckUniqueNames(const std::vector<T>& items, const char* what) {
  std::set<std::string> seen;
  for (size_t i = 0; i < items.size(); ++i) {
    if (items[i].name.empty())
      return Status::Error(std::string(what) + "[" + std::to_string(i) + "]: empty name");
    if (!seen.insert(items[i].name).second)
      return Status::Error(std::string(what) + ": duplicate name '" + items[i].name + "'");
  }
  return Status::Ok();
}
}  // namespace

int Model::FindSegment(const std::string& n) const { return FindByName(segments_, n); }
int Model::FindJoint(const std::string& n) const { return FindByName(joints_, n); }
int Model::FindCoordinate(const std::string& n) const { return FindByName(coordinates_, n); }
int Model::FindMarker(const std::string& n) const { return FindByName(markers_, n); }
int Model::FindParameter(const std::string& n) const { return FindByName(parameters_, n); }

int Model::axis_index(int joint, int element) const { return axis_index_[joint][element]; }

Status Model::Build(std::string name, std::vector<Segment> segments, std::vector<Joint> joints,
                    std::vector<Coordinate> coordinates, std::vector<Marker> markers,
                    Model* out) {
  return Build(std::move(name), std::move(segments), std::move(joints), std::move(coordinates),
               std::move(markers), {}, out);
}

Status Model::Build(std::string name, std::vector<Segment> segments, std::vector<Joint> joints,
                    std::vector<Coordinate> coordinates, std::vector<Marker> markers,
                    std::vector<DerivedCoordinate> derived, Model* out) {
  if (segments.empty()) return Status::Error("model has no segments");
  if (Status s = CheckUniqueNames(segments, "segments"); !s) return s;
  if (Status s = CheckUniqueNames(joints, "joints"); !s) return s;
  if (Status s = CheckUniqueNames(coordinates, "coordinates"); !s) return s;
  if (Status s = CheckUniqueNames(markers, "markers"); !s) return s;
  const int ns = static_cast<int>(segments.size());
  const int nc = static_cast<int>(coordinates.size());
  if (joints.size() != segments.size())
    return Status::Error("model has " + std::to_string(segments.size()) + " segments but " +
                         std::to_string(joints.size()) +
                         " joints: every segment needs exactly one joint to its parent");

  // Every segment is the child of exactly one joint; exactly one joint hangs from the ground.
  std::vector<int> joint_of(ns, -1);
  int roots = 0;
  for (size_t j = 0; j < joints.size(); ++j) {
    const Joint& jt = joints[j];
    const std::string where = "joints[" + std::to_string(j) + "] '" + jt.name + "'";
    if (jt.child < 0 || jt.child >= ns) return Status::Error(where + ": child segment out of range");
    if (jt.parent < -1 || jt.parent >= ns) return Status::Error(where + ": parent out of range");
    if (jt.parent == jt.child) return Status::Error(where + ": parent and child are the same");
    if (joint_of[jt.child] >= 0)
      return Status::Error(where + ": segment '" + segments[jt.child].name +
                           "' is already the child of joint '" + joints[joint_of[jt.child]].name + "'");
    joint_of[jt.child] = static_cast<int>(j);
    if (jt.parent == -1) ++roots;
    if (!jt.centre.allFinite()) return Status::Error(where + ".centre: not finite");
    if (!jt.orientation.allFinite() ||
        !(jt.orientation.transpose() * jt.orientation).isIdentity(1e-6) ||
        jt.orientation.determinant() < 0)
      return Status::Error(where + ".orientation: not a rotation matrix");
    for (size_t e = 0; e < jt.elements.size(); ++e) {
      const JointElement& el = jt.elements[e];
      const std::string ew = where + ".elements[" + std::to_string(e) + "]";
      if (!el.axis.allFinite() || std::abs(el.axis.norm() - 1.0) > 1e-6)
        return Status::Error(ew + ".axis: not a unit vector");
      if (Status s = el.function.Check(ew + ".function"); !s) return s;
      if (el.function.IsConstant()) {
        if (el.coordinate != -1 && (el.coordinate < 0 || el.coordinate >= nc))
          return Status::Error(ew + ".coordinate: out of range");
      } else if (el.coordinate < 0 || el.coordinate >= nc) {
        return Status::Error(ew + ".coordinate: out of range");
      }
      if (el.fitted_axis && el.kind != ElementKind::kRotation)
        return Status::Error(ew + ": only rotation axes can be fitted");
    }
  }
  {
    std::set<std::string> names;
    for (const auto& c : coordinates) names.insert(c.name);
    for (size_t i = 0; i < derived.size(); ++i) {
      const DerivedCoordinate& dc = derived[i];
      const std::string where = "derived_coordinates[" + std::to_string(i) + "] '" + dc.name + "'";
      if (dc.name.empty()) return Status::Error(where + ": empty name");
      if (!names.insert(dc.name).second)
        return Status::Error(where + ": name already used by another coordinate");
      if (dc.source < -1 || dc.source >= nc) return Status::Error(where + ".source: out of range");
      if (Status s = dc.function.Check(where + ".function"); !s) return s;
      if (dc.source < 0 && !dc.function.IsConstant())
        return Status::Error(where + ": no source coordinate but the function is not constant");
    }
  }
  if (roots != 1)
    return Status::Error("model must have exactly one joint whose parent is the ground, found " +
                         std::to_string(roots));

  // Order joints parents first (breadth-first from the ground).
  std::vector<int> order;
  std::vector<char> placed(ns, 0);
  while (static_cast<int>(order.size()) < ns) {
    bool progress = false;
    for (int j = 0; j < ns; ++j) {
      const Joint& jt = joints[j];
      if (placed[jt.child]) continue;
      if (jt.parent == -1 || placed[jt.parent]) {
        order.push_back(j);
        placed[jt.child] = 1;
        progress = true;
      }
    }
    if (!progress) return Status::Error("model's joints do not form a tree rooted at the ground");
  }
  std::vector<Joint> sorted;
  for (int j : order) sorted.push_back(joints[j]);

  Model m;
  m.name_ = std::move(name);
  m.segments_ = std::move(segments);
  m.joints_ = std::move(sorted);
  m.coordinates_ = std::move(coordinates);
  m.markers_ = std::move(markers);
  m.derived_ = std::move(derived);
  for (int j = 0; j < ns; ++j) m.segments_[m.joints_[j].child].joint = j;
  for (auto& c : m.coordinates_) c.joint = -1;
  for (int j = 0; j < ns; ++j)
    for (const auto& el : m.joints_[j].elements)
      if (el.coordinate >= 0) {
        Coordinate& c = m.coordinates_[el.coordinate];
        if (c.joint < 0) c.joint = j;
      }
  for (const auto& c : m.coordinates_)
    if (c.joint < 0) return Status::Error("coordinate '" + c.name + "' drives no joint");
  for (size_t i = 0; i < m.markers_.size(); ++i) {
    const Marker& mk = m.markers_[i];
    if (mk.segment < 0 || mk.segment >= ns)
      return Status::Error("markers[" + std::to_string(i) + "] '" + mk.name + "': segment out of range");
    if (!mk.position.allFinite())
      return Status::Error("markers[" + std::to_string(i) + "] '" + mk.name + "': position not finite");
    if (!(mk.weight > 0) || !std::isfinite(mk.weight))
      return Status::Error("markers[" + std::to_string(i) + "] '" + mk.name + "': weight must be > 0");
  }
  for (int s = 0; s < ns; ++s)
    if (!(m.segments_[s].scale > 0) || !std::isfinite(m.segments_[s].scale))
      return Status::Error("segments[" + std::to_string(s) + "] '" + m.segments_[s].name +
                           "': scale must be > 0");

  // Parameter layout: scales, centres, axes, markers.
  for (int s = 0; s < ns; ++s)
    m.parameters_.push_back({ParameterGroup::kScale, s, -1, 0, m.segments_[s].name + ".scale"});
  m.centre_index_.assign(ns, -1);
  const char* xyz[] = {"x", "y", "z"};
  for (int j = 0; j < ns; ++j) {
    if (m.joints_[j].parent < 0) continue;  // the root's centre trades with its translation
    m.centre_index_[j] = m.num_parameters();
    for (int k = 0; k < 3; ++k)
      m.parameters_.push_back({ParameterGroup::kCentre, j, -1, k,
                               m.joints_[j].name + ".centre." + xyz[k]});
  }
  m.axis_index_.resize(ns);
  m.axis_basis_.resize(ns);
  for (int j = 0; j < ns; ++j) {
    const auto& els = m.joints_[j].elements;
    m.axis_index_[j].assign(els.size(), -1);
    m.axis_basis_[j].resize(els.size());
    int fitted = 0;
    for (size_t e = 0; e < els.size(); ++e) {
      m.axis_basis_[j][e] = TangentBasis(els[e].axis);
      if (!els[e].fitted_axis) continue;
      m.axis_index_[j][e] = m.num_parameters();
      const std::string base = m.joints_[j].name + ".axis" + std::to_string(fitted++);
      m.parameters_.push_back({ParameterGroup::kAxis, j, static_cast<int>(e), 0, base + ".alpha"});
      m.parameters_.push_back({ParameterGroup::kAxis, j, static_cast<int>(e), 1, base + ".beta"});
    }
  }
  m.marker_index_.assign(m.markers_.size(), -1);
  for (size_t i = 0; i < m.markers_.size(); ++i) {
    m.marker_index_[i] = m.num_parameters();
    for (int k = 0; k < 3; ++k)
      m.parameters_.push_back({ParameterGroup::kMarker, static_cast<int>(i), -1, k,
                               m.markers_[i].name + "." + xyz[k]});
  }

  // Chains, and per-marker coordinate and parameter lists. The parameter order here is the
  // column order of MarkerJacobian (model/kinematics.cpp): marker xyz; then for each chain joint,
  // root first: parent scale, centre xyz, fitted axes (alpha, beta); finally the segment's scale.
  m.chains_.resize(ns);
  for (int s = 0; s < ns; ++s) {
    std::vector<int> chain;
    for (int j = m.segments_[s].joint; j >= 0;) {
      chain.push_back(j);
      const int p = m.joints_[j].parent;
      j = p < 0 ? -1 : m.segments_[p].joint;
    }
    std::reverse(chain.begin(), chain.end());
    m.chains_[s] = chain;
  }
  m.marker_coords_.resize(m.markers_.size());
  m.marker_params_.resize(m.markers_.size());
  for (size_t i = 0; i < m.markers_.size(); ++i) {
    const int s = m.markers_[i].segment;
    std::set<int> coords;
    std::vector<int> params;
    for (int k = 0; k < 3; ++k) params.push_back(m.marker_index_[i] + k);
    for (int j : m.chains_[s]) {
      const Joint& jt = m.joints_[j];
      for (const auto& el : jt.elements)
        if (el.coordinate >= 0 && !el.function.IsConstant())
          coords.insert(el.coordinate);
      if (jt.parent >= 0) params.push_back(m.scale_index(jt.parent));
      if (m.centre_index_[j] >= 0)
        for (int k = 0; k < 3; ++k) params.push_back(m.centre_index_[j] + k);
      for (size_t e = 0; e < jt.elements.size(); ++e)
        if (m.axis_index_[j][e] >= 0) {
          params.push_back(m.axis_index_[j][e]);
          params.push_back(m.axis_index_[j][e] + 1);
        }
    }
    params.push_back(m.scale_index(s));
    m.marker_coords_[i].assign(coords.begin(), coords.end());
    m.marker_params_[i] = params;
    m.max_chain_coords_ = std::max<int>(m.max_chain_coords_, coords.size());
    m.max_chain_params_ = std::max<int>(m.max_chain_params_, params.size());
  }
  *out = std::move(m);
  return Status::Ok();
}

Eigen::VectorXd Model::InitialParameters() const {
  Eigen::VectorXd p = Eigen::VectorXd::Zero(num_parameters());
  for (int s = 0; s < num_segments(); ++s) p[s] = segments_[s].scale;
  for (int j = 0; j < num_joints(); ++j)
    if (centre_index_[j] >= 0) p.segment<3>(centre_index_[j]) = joints_[j].centre;
  for (int i = 0; i < num_markers(); ++i) p.segment<3>(marker_index_[i]) = markers_[i].position;
  return p;
}

Eigen::VectorXd Model::DefaultCoordinates() const {
  Eigen::VectorXd z(num_coordinates());
  for (int c = 0; c < num_coordinates(); ++c) z[c] = coordinates_[c].default_value;
  return z;
}

Status Model::WithParameters(const Eigen::VectorXd& p, Model* out) const {
  if (out == nullptr) return Status::Error("model '" + name_ + "': WithParameters given no output");
  if (p.size() != num_parameters())
    return Status::Error("model '" + name_ + "': " + std::to_string(p.size()) +
                         " parameters given, the model has " + std::to_string(num_parameters()));
  for (int i = 0; i < num_parameters(); ++i) {
    if (!std::isfinite(p[i]))
      return Status::Error("model '" + name_ + "': parameter " + parameters_[i].name +
                           " is not finite");
  }
  std::vector<Segment> segments = segments_;
  std::vector<Joint> joints = joints_;
  std::vector<Marker> markers = markers_;
  for (int s = 0; s < num_segments(); ++s) segments[s].scale = p[scale_index(s)];
  for (int j = 0; j < num_joints(); ++j) {
    if (centre_index_[j] >= 0) joints[j].centre = p.segment<3>(centre_index_[j]);
    for (size_t e = 0; e < joints[j].elements.size(); ++e) {
      const int a = axis_index_[j][e];
      if (a < 0) continue;
      Eigen::Vector3d axis;
      AxisFromAngles(joints_[j].elements[e].axis, axis_basis_[j][e], p[a], p[a + 1], &axis,
                     nullptr, nullptr);
      joints[j].elements[e].axis = axis.normalized();
    }
  }
  for (int i = 0; i < num_markers(); ++i) markers[i].position = p.segment<3>(marker_index_[i]);
  Model built;
  if (Status s = Build(name_, segments, joints, coordinates_, markers, derived_, &built); !s)
    return Status::Error("model '" + name_ + "' with new parameters: " + s.message());
  *out = std::move(built);
  return Status::Ok();
}

Status Model::WithMarkers(const std::vector<int>& keep, Model* out) const {
  if (out == nullptr) return Status::Error("model '" + name_ + "': WithMarkers given no output");
  std::vector<Marker> markers;
  std::vector<char> taken(markers_.size(), 0);
  for (int i : keep) {
    if (i < 0 || i >= num_markers())
      return Status::Error("model '" + name_ + "': marker index " + std::to_string(i) +
                           " is out of range (the model has " + std::to_string(num_markers()) +
                           " markers)");
    if (taken[i]++)
      return Status::Error("model '" + name_ + "': marker '" + markers_[i].name +
                           "' is kept twice");
    markers.push_back(markers_[i]);
  }
  Model built;
  if (Status s = Build(name_, segments_, joints_, coordinates_, markers, derived_, &built); !s)
    return Status::Error("model '" + name_ + "' with " + std::to_string(keep.size()) +
                         " markers: " + s.message());
  *out = std::move(built);
  return Status::Ok();
}

Status Model::WithMarkerWeights(const std::vector<double>& weights, Model* out) const {
  if (out == nullptr) return Status::Error("model '" + name_ + "': WithMarkerWeights given no output");
  if (weights.size() != markers_.size())
    return Status::Error("model '" + name_ + "': " + std::to_string(weights.size()) + " marker weights for " +
                         std::to_string(markers_.size()) + " markers");
  std::vector<Marker> markers = markers_;
  for (size_t m = 0; m < markers.size(); ++m) markers[m].weight = weights[m];
  Model built;
  if (Status s = Build(name_, segments_, joints_, coordinates_, markers, derived_, &built); !s)
    return Status::Error("model '" + name_ + "' with new marker weights: " + s.message());
  *out = std::move(built);
  return Status::Ok();
}

std::vector<char> StackedOnOnePoint(const Model& model, const std::vector<char>& among, double tolerance_m) {
  const int nm = model.num_markers();
  std::vector<char> stacked(nm, 0);
  for (int a = 0; a < nm; ++a)
    for (int b = a + 1; b < nm; ++b) {
      const Marker& ma = model.markers()[a];
      const Marker& mb = model.markers()[b];
      if (among[a] && among[b] && ma.segment == mb.segment && (ma.position - mb.position).norm() <= tolerance_m)
        stacked[a] = stacked[b] = 1;
    }
  return stacked;
}

}  // namespace mocap
