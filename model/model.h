// The body model: a kinematic tree of rigid segments joined by joints, with markers fixed on the
// segments, and its geometric parameters p.
//
// Shape (after Pinocchio): a `Model` is immutable once built and shared by every thread; each
// thread evaluates it with its own `ModelData` workspace (model/kinematics.h), so the fit's and
// the filter's hot loops allocate nothing.
//
// Frames. Every segment has a frame whose origin is its proximal joint centre. A joint J between
// parent segment P and child segment C places C's frame at
//
//     T_C = T_P * Trans(s_P * c_J) * Rot(R_J) * E_1(v_1) * ... * E_k(v_k)
//
// where s_P is P's scale factor, c_J the joint centre in P's unscaled frame, R_J a fixed
// orientation, and E_i an ELEMENTARY motion: a rotation about, or a translation along, a unit axis
// fixed in the frame reached after E_1..E_{i-1}. Each element's value v_i = f_i(z_k) is a function
// of one coordinate (model/coordinate_function.h: identity, linear, constant, OpenSim's splines,
// polynomials, multipliers and compositions), which is how an OpenSim CustomJoint's
// SpatialTransform maps onto a joint (formats/osim.h). A translation element of a non-root joint
// whose function is not the identity moves by s_P f(z) (OpenSim scales such a translation with the
// parent body). A coordinate may drive elements of several joints (a coupled coordinate, e.g. a
// patella driven by the knee angle). A marker on segment C sits at T_C * (s_C * m).
//
// Geometric parameters p (Lugrís et al. 2024, eq. 1), in switchable groups, in this order:
//   scales   one uniform scale factor per segment                       [n_segments]
//   centres  each non-root joint's centre c_J in its parent (unscaled)   [3 per joint]
//   axes     each fitted axis (hinge and universal joints) as two angles
//            (alpha, beta) about the axis stored in the model:
//            a = cos(b)(cos(a) e1 + sin(a) e2) + sin(b) e3, e1 = stored axis [2 per axis]
//   markers  each marker's position on its segment (unscaled)            [3 per marker]
// Axis angles are relative to the model's stored axes, so Model::InitialParameters() has zeros
// there; Model::WithParameters bakes a p into a new Model (axes re-based, angles back to 0).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <string>
#include <vector>

#include "model/coordinate_function.h"
#include "model/status.h"

namespace mocap {

enum class JointType { kFree, kSpherical, kUniversal, kHinge, kCustom };
enum class ElementKind { kRotation, kTranslation };
enum class ParameterGroup { kScale = 0, kCentre = 1, kAxis = 2, kMarker = 3 };
constexpr int kNumParameterGroups = 4;

const char* ToString(JointType type);
const char* ToString(ParameterGroup group);

struct JointElement {
  ElementKind kind = ElementKind::kRotation;
  Eigen::Vector3d axis = Eigen::Vector3d::UnitX();  // unit, in the frame after earlier elements
  int coordinate = -1;  // model coordinate index; -1 when the function is constant
  // v = f(z). A translation element of a non-root joint whose function is not the identity is
  // scaled by the parent segment's scale factor, as OpenSim scales a CustomJoint's translation
  // functions with the parent body (SpatialTransform::scale); an identity translation is a
  // degree of freedom and is not scaled.
  CoordinateFunction function;
  bool fitted_axis = false;  // the axis is a geometric parameter (hinge/universal axes)
};

struct Coordinate {
  std::string name;
  bool rotational = true;
  double default_value = 0.0;  // radians or metres
  double min_value = -1e9;
  double max_value = 1e9;
  // The range is a limit the pose must keep (OpenSim's Coordinate `clamped`), not only the span a
  // motion is expected in: the fit and IK then penalise a pose beyond it (FitOptions::
  // coordinate_limit_sigma), as OpenSim's IK bounds a clamped coordinate.
  bool clamped = false;
  int joint = -1;  // filled by Model::Build: the first joint (parents first) it drives
};

// A coordinate that is not an independent degree of freedom but a function of one (OpenSim's
// CoordinateCouplerConstraint: dependent = f(independent)) or a constant (a locked coordinate).
// It is not in z; the elements it drove are driven by `source` through the composed function.
// Kept so that joint angles can be written out under every OpenSim coordinate name.
struct DerivedCoordinate {
  std::string name;
  bool rotational = true;
  int source = -1;  // model coordinate index; -1: constant
  CoordinateFunction function;
  double Value(const Eigen::VectorXd& z) const {
    return function.Value(source >= 0 ? z[source] : 0.0);
  }
};

struct Joint {
  std::string name;
  JointType type = JointType::kCustom;
  int parent = -1;  // segment index; -1 = ground (the lab)
  int child = -1;   // segment index
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();            // in parent, unscaled
  Eigen::Matrix3d orientation = Eigen::Matrix3d::Identity();   // fixed, not fitted
  std::vector<JointElement> elements;
};

struct Segment {
  std::string name;
  double scale = 1.0;
  int joint = -1;  // the joint whose child this segment is (filled by Model::Build)
};

struct Marker {
  std::string name;
  int segment = -1;
  Eigen::Vector3d position = Eigen::Vector3d::Zero();  // on the segment, unscaled
  bool optional = false;  // not in every lab's marker set (medial knee/ankle, ...)
  double weight = 1.0;    // relative weight in the fit
  // Placed by the model's author on a bony landmark (OpenSim's Marker <fixed>true</fixed>, which
  // OpenSim's marker placer does not move): the fit moves it only against a tight prior
  // (FitOptions::prior_sigma_fixed_marker_m), so the bones stay where the landmarks say.
  bool fixed = false;
};

// One entry of p: which group, which object (segment, joint, axis element or marker), which
// component. Used for names in reports and by the fit to pick groups.
struct ParameterInfo {
  ParameterGroup group;
  int object = -1;     // segment / joint / marker index
  int element = -1;    // for axes: element index within the joint
  int component = 0;   // x,y,z or alpha,beta
  std::string name;    // e.g. "knee_r.centre.x", "RKNE.y", "femur_r.scale", "knee_r.axis0.alpha"
};

class Model {
 public:
  // Builds the index structures (topological order, chains, parameter layout) after the
  // description fields are filled in; validates (names unique, tree connected, parents before
  // children, unit axes, a single root). Segments and joints may be given in any order; Build
  // reorders joints so that every parent comes before its children.
  static Status Build(std::string name, std::vector<Segment> segments, std::vector<Joint> joints,
                      std::vector<Coordinate> coordinates, std::vector<Marker> markers, Model* out);
  static Status Build(std::string name, std::vector<Segment> segments, std::vector<Joint> joints,
                      std::vector<Coordinate> coordinates, std::vector<Marker> markers,
                      std::vector<DerivedCoordinate> derived, Model* out);

  const std::string& name() const { return name_; }
  const std::vector<Segment>& segments() const { return segments_; }
  const std::vector<Joint>& joints() const { return joints_; }          // parents first
  const std::vector<Coordinate>& coordinates() const { return coordinates_; }
  const std::vector<Marker>& markers() const { return markers_; }
  const std::vector<DerivedCoordinate>& derived_coordinates() const { return derived_; }
  int num_segments() const { return static_cast<int>(segments_.size()); }
  int num_joints() const { return static_cast<int>(joints_.size()); }
  int num_coordinates() const { return static_cast<int>(coordinates_.size()); }
  int num_markers() const { return static_cast<int>(markers_.size()); }
  int num_parameters() const { return static_cast<int>(parameters_.size()); }
  const std::vector<ParameterInfo>& parameters() const { return parameters_; }

  int FindSegment(const std::string& n) const;
  int FindJoint(const std::string& n) const;
  int FindCoordinate(const std::string& n) const;
  int FindMarker(const std::string& n) const;
  int FindParameter(const std::string& n) const;

  // First index of each group in p, and of each object's block.
  int scale_index(int segment) const { return segment; }
  int centre_index(int joint) const { return centre_index_[joint]; }  // -1 for the root joint
  int axis_index(int joint, int element) const;                       // -1 if not fitted
  int marker_index(int marker) const { return marker_index_[marker]; }

  // p of this model as stored (axis angles zero) and the default pose z.
  Eigen::VectorXd InitialParameters() const;
  Eigen::VectorXd DefaultCoordinates() const;
  // A new model with geometry p baked in (scales, centres, re-based axes, markers). An error,
  // naming the entry, when p has the wrong size, a non-finite entry or a non-positive scale (a
  // segment scaled to nothing is no body); *out is then left unchanged.
  Status WithParameters(const Eigen::VectorXd& p, Model* out) const;
  // The same model with only the markers `keep` (indices, in the order given), for data that
  // lacks the others. An error for an index out of range or given twice.
  Status WithMarkers(const std::vector<int>& keep, Model* out) const;
  // The same model with marker m weighted weights[m] (Marker::weight). An error for a count that
  // is not num_markers() or a weight that is not a finite number > 0.
  Status WithMarkerWeights(const std::vector<double>& weights, Model* out) const;

  // --- precomputed structure used by the kinematics (read-only) ---
  // Joints on the path from the root to segment s, root first.
  const std::vector<int>& chain(int segment) const { return chains_[segment]; }
  // Coordinates that move marker m, ascending, and the p entries it depends on (in the order
  // MarkerJacobian writes its columns).
  const std::vector<int>& marker_coordinates(int m) const { return marker_coords_[m]; }
  const std::vector<int>& marker_parameters(int m) const { return marker_params_[m]; }
  int max_chain_coordinates() const { return max_chain_coords_; }
  int max_chain_parameters() const { return max_chain_params_; }
  // Axis basis (e2, e3) of a fitted element, fixed at build time.
  const Eigen::Matrix<double, 3, 2>& axis_basis(int joint, int element) const {
    return axis_basis_[joint][element];
  }

 private:
  std::string name_;
  std::vector<Segment> segments_;
  std::vector<Joint> joints_;
  std::vector<Coordinate> coordinates_;
  std::vector<Marker> markers_;
  std::vector<DerivedCoordinate> derived_;
  std::vector<ParameterInfo> parameters_;
  std::vector<int> centre_index_, marker_index_;
  std::vector<std::vector<int>> axis_index_;
  std::vector<std::vector<Eigen::Matrix<double, 3, 2>>> axis_basis_;
  std::vector<std::vector<int>> chains_;
  std::vector<std::vector<int>> marker_coords_, marker_params_;
  int max_chain_coords_ = 0, max_chain_params_ = 0;
};

// A unit vector's two tangent directions, chosen deterministically (for axis parameters).
Eigen::Matrix<double, 3, 2> TangentBasis(const Eigen::Vector3d& axis);
// The fitted axis for angles (alpha, beta) about e1 with tangent basis (e2, e3), and its
// derivatives with respect to alpha and beta.
void AxisFromAngles(const Eigen::Vector3d& e1, const Eigen::Matrix<double, 3, 2>& basis,
                    double alpha, double beta, Eigen::Vector3d* axis, Eigen::Vector3d* d_alpha,
                    Eigen::Vector3d* d_beta);

// Per marker of `model`: 1 when it and another marker of its segment, both flagged in `among`
// (one flag per marker), sit within tolerance_m of each other (unscaled): placeholders a generic
// model gives a lab's cluster markers without knowing where they are. The fit places them from
// the trials (solver/attach_markers.h, StackedMarkers); the tracker leaves them unseen.
std::vector<char> StackedOnOnePoint(const Model& model, const std::vector<char>& among, double tolerance_m);

}  // namespace mocap
