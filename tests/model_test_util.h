// Shared by the model tests: random poses and parameters, marker positions, and the check of
// every analytic Jacobian column against central finite differences.
#pragma once

#include <gtest/gtest.h>

#include <algorithm>
#include <random>
#include <vector>

#include "model/kinematics.h"
#include "model/model.h"

namespace mocap::testutil {

inline Eigen::VectorXd RandomPose(const Model& model, std::mt19937& rng, double range = 0.8) {
  std::uniform_real_distribution<double> u(-range, range);
  Eigen::VectorXd z = model.DefaultCoordinates();
  for (int c = 0; c < model.num_coordinates(); ++c)
    z[c] += model.coordinates()[c].rotational ? u(rng) : 0.3 * u(rng);
  return z;
}

// m.WithParameters(p) / m.WithMarkers(keep) for tests: a refusal fails the test (with the
// message) instead of passing an empty model on.
inline Model Baked(const Model& m, const Eigen::VectorXd& p) {
  Model out;
  const Status s = m.WithParameters(p, &out);
  EXPECT_TRUE(s.ok()) << s.message();
  return out;
}
inline Model Keeping(const Model& m, const std::vector<int>& keep) {
  Model out;
  const Status s = m.WithMarkers(keep, &out);
  EXPECT_TRUE(s.ok()) << s.message();
  return out;
}

// Perturbs every parameter so that the Jacobian test does not run at a special point.
inline Eigen::VectorXd RandomParameters(const Model& model, std::mt19937& rng) {
  std::uniform_real_distribution<double> u(-1, 1);
  Eigen::VectorXd p = model.InitialParameters();
  for (int i = 0; i < model.num_parameters(); ++i) {
    switch (model.parameters()[i].group) {
      case ParameterGroup::kScale: p[i] *= 1 + 0.1 * u(rng); break;
      case ParameterGroup::kCentre: p[i] += 0.02 * u(rng); break;
      case ParameterGroup::kAxis: p[i] += 0.1 * u(rng); break;
      case ParameterGroup::kMarker: p[i] += 0.01 * u(rng); break;
    }
  }
  return p;
}

inline Eigen::Matrix3Xd Positions(const Model& model, const Eigen::VectorXd& z, const Eigen::VectorXd& p) {
  Geometry g(model);
  g.Set(model, p);
  ModelData d(model);
  ForwardKinematics(model, g, z, &d);
  Eigen::Matrix3Xd x;
  MarkerPositions(model, g, d, &x);
  return x;
}

// Every column of dh/dz and dh/dp of every marker against central differences, to 1e-6
// relative; columns not listed by the model must have a zero derivative. Returns the worst error.
inline double ExpectJacobiansMatchCentralDifferences(const Model& model, const Eigen::VectorXd& z,
                                                     const Eigen::VectorXd& p) {
  Geometry g(model);
  g.Set(model, p);
  ModelData d(model);
  ForwardKinematics(model, g, z, &d);
  const double h = 1e-6;
  // Differences of all markers at once: one FK per perturbed coordinate or parameter.
  std::vector<Eigen::Matrix3Xd> dz(model.num_coordinates()), dp(model.num_parameters());
  for (int c = 0; c < model.num_coordinates(); ++c) {
    Eigen::VectorXd zp = z, zm = z;
    zp[c] += h;
    zm[c] -= h;
    dz[c] = (Positions(model, zp, p) - Positions(model, zm, p)) / (2 * h);
  }
  for (int i = 0; i < model.num_parameters(); ++i) {
    Eigen::VectorXd pp = p, pm = p;
    pp[i] += h;
    pm[i] -= h;
    dp[i] = (Positions(model, z, pp) - Positions(model, z, pm)) / (2 * h);
  }
  double worst = 0;
  for (int m = 0; m < model.num_markers(); ++m) {
    const auto& zc = model.marker_coordinates(m);
    const auto& pc = model.marker_parameters(m);
    Eigen::MatrixXd jz(3, zc.size()), jp(3, pc.size());
    MarkerJacobian(model, g, d, m, &jz, &jp);
    for (int c = 0; c < model.num_coordinates(); ++c) {
      auto it = std::find(zc.begin(), zc.end(), c);
      const Eigen::Vector3d an = it == zc.end() ? Eigen::Vector3d::Zero() : Eigen::Vector3d(jz.col(it - zc.begin()));
      const double err = (dz[c].col(m) - an).norm() / std::max(1.0, an.norm());
      worst = std::max(worst, err);
      EXPECT_LT(err, 1e-6) << model.markers()[m].name << " d/d " << model.coordinates()[c].name;
    }
    for (int i = 0; i < model.num_parameters(); ++i) {
      auto it = std::find(pc.begin(), pc.end(), i);
      const Eigen::Vector3d an = it == pc.end() ? Eigen::Vector3d::Zero() : Eigen::Vector3d(jp.col(it - pc.begin()));
      const double err = (dp[i].col(m) - an).norm() / std::max(1.0, an.norm());
      worst = std::max(worst, err);
      EXPECT_LT(err, 1e-6) << model.markers()[m].name << " d/d " << model.parameters()[i].name;
    }
  }
  return worst;
}

}  // namespace mocap::testutil
