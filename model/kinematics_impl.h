// Template bodies of model/kinematics.h.
#pragma once
#include <cmath>

namespace mocap {

// Calls f(joint, element, column) for every element on marker m's chain that a coordinate drives,
// `column` being that coordinate's place in model.marker_coordinates(m): the terms of dh_m/dz in
// MarkerJacobian's order, which the global fit's evaluator (solver/marker_fit_problem.cpp)
// precomputes and must visit identically.
template <typename F>
void ForEachDrivenElement(const Model& model, int m, F&& f) {
  const std::vector<int>& cols = model.marker_coordinates(m);
  for (int j : model.chain(model.markers()[m].segment)) {
    const Joint& jt = model.joints()[j];
    for (size_t e = 0; e < jt.elements.size(); ++e) {
      const JointElement& el = jt.elements[e];
      if (el.coordinate < 0 || el.function.IsConstant()) continue;
      // cols is short and sorted: a linear scan beats a lookup table here.
      int c = 0;
      while (cols[c] != el.coordinate) ++c;
      f(j, static_cast<int>(e), c);
    }
  }
}

template <typename DerivedZ, typename DerivedP>
void MarkerJacobian(const Model& model, const Geometry& g, const ModelData& d, int m,
                    Eigen::MatrixBase<DerivedZ>* jz, Eigen::MatrixBase<DerivedP>* jp) {
  const Marker& mk = model.markers()[m];
  const int s = mk.segment;
  const Eigen::Vector3d x = MarkerPosition(model, g, d, m);
  const std::vector<int>& chain = model.chain(s);

  if (jz) {
    jz->setZero();
    ForEachDrivenElement(model, m, [&](int j, int e, int c) {
      const Joint& jt = model.joints()[j];
      const JointElement& el = jt.elements[e];
      const Eigen::Vector3d w = d.element_rotation[j][e] * g.axis[j][e];
      const double dv = d.element_derivative[j][e];
      if (el.kind == ElementKind::kRotation)
        jz->col(c) += dv * w.cross(x - d.element_origin[j][e]);
      else
        jz->col(c) += (TranslationScale(jt, el, g) * dv) * w;
    });
  }
  if (jp) {
    int c = 0;
    jp->template middleCols<3>(c) = g.scale[s] * d.segment_rotation[s];
    c += 3;
    for (int j : chain) {
      const Joint& jt = model.joints()[j];
      const int parent = jt.parent;
      if (parent >= 0) {
        auto col = jp->col(c++);
        col = d.segment_rotation[parent] * g.centre[j];
        for (size_t e = 0; e < jt.elements.size(); ++e)
          if (ScalesWithParent(jt, jt.elements[e]))
            col += d.element_rotation[j][e] * (g.axis[j][e] * d.element_value[j][e]);
      }
      if (model.centre_index(j) >= 0) {
        if (parent >= 0)
          jp->template middleCols<3>(c) = g.scale[parent] * d.segment_rotation[parent];
        else
          jp->template middleCols<3>(c).setIdentity();
        c += 3;
      }
      for (size_t e = 0; e < jt.elements.size(); ++e) {
        if (model.axis_index(j, static_cast<int>(e)) < 0) continue;
        const double v = d.element_value[j][e];
        const Eigen::Vector3d& a = g.axis[j][e];
        const Eigen::Matrix3d& rb = d.element_rotation[j][e];
        const Eigen::Vector3d r = x - d.element_origin[j][e];
        const double sv = std::sin(v), cv1 = 1.0 - std::cos(v);
        const Eigen::Vector3d& da = g.axis_d_alpha[j][e];
        const Eigen::Vector3d& db = g.axis_d_beta[j][e];
        jp->col(c++) = (rb * (sv * da + cv1 * a.cross(da))).cross(r);
        jp->col(c++) = (rb * (sv * db + cv1 * a.cross(db))).cross(r);
      }
    }
    jp->col(c) = d.segment_rotation[s] * g.marker[m];
  }
}

}  // namespace mocap
