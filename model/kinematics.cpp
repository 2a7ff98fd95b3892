#include "model/kinematics.h"

#include <Eigen/Geometry>

namespace mocap {

void Geometry::Set(const Model& model, const Eigen::VectorXd& p) {
  const int ns = model.num_segments(), nj = model.num_joints(), nm = model.num_markers();
  scale.resize(ns);
  centre.resize(nj);
  centre_scaled.resize(nj);
  axis.resize(nj);
  axis_d_alpha.resize(nj);
  axis_d_beta.resize(nj);
  marker.resize(nm);
  marker_scaled.resize(nm);
  for (int s = 0; s < ns; ++s) scale[s] = p[model.scale_index(s)];
  for (int j = 0; j < nj; ++j) {
    const Joint& jt = model.joints()[j];
    const int ci = model.centre_index(j);
    centre[j] = ci >= 0 ? Eigen::Vector3d(p.segment<3>(ci)) : jt.centre;
    centre_scaled[j] = (jt.parent >= 0 ? scale[jt.parent] : 1.0) * centre[j];
    const size_t ne = jt.elements.size();
    axis[j].resize(ne);
    axis_d_alpha[j].resize(ne);
    axis_d_beta[j].resize(ne);
    for (size_t e = 0; e < ne; ++e) {
      const int ai = model.axis_index(j, static_cast<int>(e));
      if (ai < 0) {
        axis[j][e] = jt.elements[e].axis;
        axis_d_alpha[j][e].setZero();
        axis_d_beta[j][e].setZero();
      } else {
        AxisFromAngles(jt.elements[e].axis, model.axis_basis(j, static_cast<int>(e)), p[ai],
                       p[ai + 1], &axis[j][e], &axis_d_alpha[j][e], &axis_d_beta[j][e]);
      }
    }
  }
  for (int i = 0; i < nm; ++i) {
    marker[i] = p.segment<3>(model.marker_index(i));
    marker_scaled[i] = scale[model.markers()[i].segment] * marker[i];
  }
}

ModelData::ModelData(const Model& model) {
  const int ns = model.num_segments(), nj = model.num_joints();
  segment_rotation.assign(ns, Eigen::Matrix3d::Identity());
  segment_position.assign(ns, Eigen::Vector3d::Zero());
  element_rotation.resize(nj);
  element_origin.resize(nj);
  element_value.resize(nj);
  element_derivative.resize(nj);
  for (int j = 0; j < nj; ++j) {
    const size_t ne = model.joints()[j].elements.size();
    element_rotation[j].assign(ne, Eigen::Matrix3d::Identity());
    element_origin[j].assign(ne, Eigen::Vector3d::Zero());
    element_value[j].assign(ne, 0.0);
    element_derivative[j].assign(ne, 0.0);
  }
}

namespace {
// Joint j's child segment from its parent's place in *d.
void PlaceChild(const Model& model, const Geometry& g, const Eigen::VectorXd& z, int j, ModelData* d) {
  const Joint& jt = model.joints()[j];
  Eigen::Matrix3d r;
  Eigen::Vector3d t;
  if (jt.parent >= 0) {
    const Eigen::Matrix3d& rp = d->segment_rotation[jt.parent];
    t = d->segment_position[jt.parent] + rp * g.centre_scaled[j];
    r = rp * jt.orientation;
  } else {
    t = g.centre_scaled[j];
    r = jt.orientation;
  }
  for (size_t e = 0; e < jt.elements.size(); ++e) {
    const JointElement& el = jt.elements[e];
    d->element_rotation[j][e] = r;
    d->element_origin[j][e] = t;
    double v, dv;
    el.function.Evaluate(el.coordinate >= 0 ? z[el.coordinate] : 0.0, &v, &dv);
    d->element_value[j][e] = v;
    d->element_derivative[j][e] = dv;
    if (el.kind == ElementKind::kRotation)
      r = r * Eigen::AngleAxisd(v, g.axis[j][e]).toRotationMatrix();
    else
      t += r * (g.axis[j][e] * (TranslationScale(jt, el, g) * v));
  }
  d->segment_rotation[jt.child] = r;
  d->segment_position[jt.child] = t;
}
}  // namespace

void ForwardKinematics(const Model& model, const Geometry& g, const Eigen::VectorXd& z,
                       ModelData* d) {
  const int nj = model.num_joints();
  for (int j = 0; j < nj; ++j) PlaceChild(model, g, z, j, d);
}

void ForwardKinematics(const Model& model, const Geometry& g, const Eigen::VectorXd& z,
                       const std::vector<int>& joints, ModelData* d) {
  for (int j : joints) PlaceChild(model, g, z, j, d);
}

void MarkerPositions(const Model& model, const Geometry& g, const ModelData& d,
                     Eigen::Matrix3Xd* positions) {
  positions->resize(3, model.num_markers());
  for (int m = 0; m < model.num_markers(); ++m) positions->col(m) = MarkerPosition(model, g, d, m);
}

}  // namespace mocap
