// Forward kinematics h(z, p) of the markers and its analytic Jacobians dh/dz and dh/dp.
//
// Evaluation is split in two, because the fit evaluates thousands of frames with one p:
//   Geometry  — what depends on p only (scaled centres and markers, axes and their derivatives
//               with respect to the axis angles); computed once per p, shared read-only.
//   ModelData — the per-thread workspace of one pose (segment and element frames).
// Neither allocates after construction, so the per-frame paths of the fit and the filter are
// allocation-free (checked by a test under EIGEN_RUNTIME_NO_MALLOC).
//
// Derivatives (x = world marker position, element i with world axis w and frame origin o):
//   rotation element, value v = f(z):   dx/dz = f'(z) w x (x - o)
//   translation element:                dx/dz = k f'(z) w, k = s_P if the element scales with
//                                       its joint's parent P (model/model.h), else 1
//   (f'(z) at the pose's z: ForwardKinematics keeps it per element)
//   fitted rotation axis a(alpha,beta): the rotation's left perturbation for a tangent change
//     da of its unit axis at fixed angle v is  omega = sin(v) da + (1 - cos(v)) a x da
//     (from the left Jacobian of SO(3)), so dx/dalpha = (R_before omega) x (x - o)
//   joint centre c (in parent P):       dx/dc = s_P R_P
//   marker position m (on segment S):   dx/dm = s_S R_S
//   scale s_P of a chain segment:       dx/ds_P = R_P c_child_joint + sum over the child joint's
//                                       scaled translation elements of R_before,i a_i f_i(z)
//                                       (or R_S m for the marker's own segment)
#pragma once

#include <Eigen/Core>
#include <vector>

#include "model/model.h"

namespace mocap {

struct Geometry {
  Geometry() = default;
  explicit Geometry(const Model& model) { Set(model, model.InitialParameters()); }
  // Recomputes everything from p. Allocates only the first time (sizes come from the model).
  void Set(const Model& model, const Eigen::VectorXd& p);

  std::vector<double> scale;                  // per segment
  std::vector<Eigen::Vector3d> centre;        // per joint: unscaled c_J
  std::vector<Eigen::Vector3d> centre_scaled; // per joint: s_P c_J
  std::vector<std::vector<Eigen::Vector3d>> axis, axis_d_alpha, axis_d_beta;  // per joint, element
  std::vector<Eigen::Vector3d> marker;        // per marker: unscaled m
  std::vector<Eigen::Vector3d> marker_scaled; // per marker: s_S m
};

struct ModelData {
  ModelData() = default;
  explicit ModelData(const Model& model);

  std::vector<Eigen::Matrix3d> segment_rotation;   // world, per segment
  std::vector<Eigen::Vector3d> segment_position;   // world, per segment (origin = joint centre)
  // Per joint, per element: the world frame just before the element (its axis is
  // element_rotation * axis, its origin element_origin) and the element's value v.
  std::vector<std::vector<Eigen::Matrix3d>> element_rotation;
  std::vector<std::vector<Eigen::Vector3d>> element_origin;
  std::vector<std::vector<double>> element_value;       // f(z), before any scaling
  std::vector<std::vector<double>> element_derivative;  // f'(z)
};

// A non-identity translation of a non-root joint moves by s_P f(z) (OpenSim's CustomJoint
// scaling, model/model.h); TranslationScale is that factor (1 for every other element).
inline bool ScalesWithParent(const Joint& joint, const JointElement& element) {
  return joint.parent >= 0 && element.kind == ElementKind::kTranslation &&
         !element.function.IsIdentity();
}
inline double TranslationScale(const Joint& joint, const JointElement& element,
                               const Geometry& geometry) {
  return ScalesWithParent(joint, element) ? geometry.scale[joint.parent] : 1.0;
}

// Places every segment for coordinates z.
void ForwardKinematics(const Model& model, const Geometry& geometry, const Eigen::VectorXd& z,
                       ModelData* data);
// Places the child segments of `joints` only (indices in the model's joint order, parents first),
// each from its parent's place in *data: the same figures as the whole pass when every other
// joint's parent and coordinates are as *data was placed. For a search that moves one limb's
// coordinates many times (the tracker's limb search): the rest of the body is placed once.
void ForwardKinematics(const Model& model, const Geometry& geometry, const Eigen::VectorXd& z,
                       const std::vector<int>& joints, ModelData* data);

// World position of marker m (after ForwardKinematics).
inline Eigen::Vector3d MarkerPosition(const Model& model, const Geometry& geometry,
                                      const ModelData& data, int m) {
  const int s = model.markers()[m].segment;
  return data.segment_position[s] + data.segment_rotation[s] * geometry.marker_scaled[m];
}

// All marker positions, as a 3 x n_markers matrix.
void MarkerPositions(const Model& model, const Geometry& geometry, const ModelData& data,
                     Eigen::Matrix3Xd* positions);

// Jacobians of marker m's world position: jz (3 x model.marker_coordinates(m).size()) with the
// columns of marker_coordinates(m), jp (3 x model.marker_parameters(m).size()) with the columns
// of marker_parameters(m). Either may be null. The outputs must already have those sizes
// (a fixed-capacity block of a larger matrix is fine).
template <typename DerivedZ, typename DerivedP>
void MarkerJacobian(const Model& model, const Geometry& geometry, const ModelData& data, int m,
                    Eigen::MatrixBase<DerivedZ>* jz, Eigen::MatrixBase<DerivedP>* jp);

// Joint centre of joint j in the world (the child segment's origin).
inline Eigen::Vector3d JointCentre(const Model& model, const ModelData& data, int j) {
  return data.segment_position[model.joints()[j].child];
}

}  // namespace mocap

#include "model/kinematics_impl.h"
