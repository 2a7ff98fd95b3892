// A small synthetic subject for solver tests that do not need the full protocol of sim/:
// a perturbed default model performing smooth random motions of every joint.
#pragma once
#include <random>

#include "formats/marker_data.h"
#include "model/default_model.h"
#include "model/kinematics.h"
#include "tests/model_test_util.h"

namespace mocap::testutil {

// The default full-body model without its optional markers (the Plug-in Gait set).
inline Model NominalWithoutOptional() {
  Model m = DefaultFullBodyModel();
  std::vector<int> keep;
  for (int i = 0; i < m.num_markers(); ++i)
    if (!m.markers()[i].optional) keep.push_back(i);
  return mocap::testutil::Keeping(m, keep);
}

inline Eigen::VectorXd PerturbedParameters(const Model& model, std::mt19937_64& rng) {
  std::uniform_real_distribution<double> u(-1, 1);
  Eigen::VectorXd p = model.InitialParameters();
  auto random_vector = [&](double max_len) {
    Eigen::Vector3d v(u(rng), u(rng), u(rng));
    return Eigen::Vector3d(v.normalized() * max_len * std::abs(u(rng)));
  };
  for (int i = 0; i < model.num_parameters(); ++i) {
    const ParameterInfo& info = model.parameters()[i];
    if (info.component != 0) continue;
    switch (info.group) {
      case ParameterGroup::kScale: p[i] *= 1 + 0.1 * u(rng); break;
      case ParameterGroup::kCentre: {
        const int parent = model.joints()[info.object].parent;
        p.segment<3>(i) += random_vector(0.015) / p[model.scale_index(parent)];
        break;
      }
      case ParameterGroup::kAxis: {
        const double tilt = 5.0 * M_PI / 180 * std::abs(u(rng)), dir = M_PI * u(rng);
        p[i] = tilt * std::cos(dir);
        p[i + 1] = tilt * std::sin(dir);
        break;
      }
      case ParameterGroup::kMarker:
        p.segment<3>(i) += random_vector(0.010) / p[model.scale_index(model.markers()[info.object].segment)];
        break;
    }
  }
  return p;
}

// Frames of every joint moving smoothly through about +-0.6 rad, the pelvis wandering.
inline formats::MarkerTrial SimulateRandomMotion(const Model& truth, int frames, double noise_m,
                                                 std::mt19937_64& rng, Eigen::MatrixXd* z_out = nullptr) {
  std::uniform_real_distribution<double> u(-1, 1);
  const int nz = truth.num_coordinates(), nm = truth.num_markers();
  std::vector<Eigen::Vector3d> waves(nz);  // amplitude, frequency, phase
  for (int c = 0; c < nz; ++c) {
    const bool rot = truth.coordinates()[c].rotational;
    waves[c] = Eigen::Vector3d((rot ? 0.6 : 0.2) * (0.5 + 0.5 * std::abs(u(rng))),
                               0.2 + 0.5 * std::abs(u(rng)), M_PI * u(rng));
  }
  formats::MarkerTrial trial;
  trial.name = "random_motion";
  trial.rate_hz = 100;
  for (const auto& m : truth.markers()) trial.marker_names.push_back(m.name);
  trial.positions.resize(frames, 3 * nm);
  Geometry g(truth);
  ModelData d(truth);
  std::normal_distribution<double> noise(0.0, noise_m);
  Eigen::VectorXd z(nz);
  if (z_out) z_out->resize(frames, nz);
  for (int f = 0; f < frames; ++f) {
    const double t = f / 100.0;
    z = truth.DefaultCoordinates();
    for (int c = 0; c < nz; ++c) z[c] += waves[c][0] * std::sin(2 * M_PI * waves[c][1] * t + waves[c][2]);
    if (z_out) z_out->row(f) = z.transpose();
    ForwardKinematics(truth, g, z, &d);
    for (int m = 0; m < nm; ++m)
      for (int k = 0; k < 3; ++k) trial.positions(f, 3 * m + k) = MarkerPosition(truth, g, d, m)[k] + noise(rng);
    trial.frame_numbers.push_back(f + 1);
    trial.times.push_back(t);
  }
  return trial;
}

}  // namespace mocap::testutil
