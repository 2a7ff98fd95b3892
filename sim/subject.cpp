#include "sim/subject.h"

#include <cmath>

#include "model/default_model.h"
#include "sim/random.h"

namespace mocap::sim {

bool SubjectOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& message) {
    if (error) *error = message;
    return false;
  };
  if (!(std::isfinite(min_height_m) && min_height_m > 0.5))
    return fail("min_height_m must be a height in metres above 0.5");
  if (!(std::isfinite(max_height_m) && max_height_m >= min_height_m && max_height_m < 3.0))
    return fail("max_height_m must be >= min_height_m and below 3 m");
  if (!(scale_spread >= 0.0 && scale_spread < 0.5))
    return fail("scale_spread must be in [0, 0.5)");
  if (!(centre_mm >= 0.0 && centre_mm <= 100.0)) return fail("centre_mm must be in [0, 100]");
  if (!(axis_deg >= 0.0 && axis_deg <= 45.0)) return fail("axis_deg must be in [0, 45]");
  if (!(marker_mm >= 0.0 && marker_mm <= 100.0)) return fail("marker_mm must be in [0, 100]");
  return true;
}

Eigen::VectorXd PerturbedParameters(const Model& model, std::uint64_t seed, const SubjectOptions& options) {
  Eigen::VectorXd p = model.InitialParameters();
  Random scale_rng(seed, Stream::kScale);
  for (int s = 0; s < model.num_segments(); ++s)
    p[model.scale_index(s)] *= scale_rng.Uniform(1.0 - options.scale_spread,
                                                 1.0 + options.scale_spread);

  // Displacements are drawn in metres of the true (scaled) frame, then stored unscaled.
  Random centre_rng(seed, Stream::kCentre);
  for (int j = 0; j < model.num_joints(); ++j) {
    const int ci = model.centre_index(j);
    if (ci < 0) continue;
    const double s_parent = p[model.scale_index(model.joints()[j].parent)];
    p.segment<3>(ci) += centre_rng.InBall(options.centre_mm * 1e-3) / s_parent;
  }
  Random axis_rng(seed, Stream::kAxis);
  const double max_tilt = options.axis_deg * M_PI / 180.0;
  for (int j = 0; j < model.num_joints(); ++j)
    for (size_t e = 0; e < model.joints()[j].elements.size(); ++e) {
      const int ai = model.axis_index(j, static_cast<int>(e));
      if (ai < 0) continue;
      p.segment<2>(ai) = axis_rng.InDisc(max_tilt);
    }
  Random marker_rng(seed, Stream::kMarker);
  for (int m = 0; m < model.num_markers(); ++m) {
    const double s_segment = p[model.scale_index(model.markers()[m].segment)];
    p.segment<3>(model.marker_index(m)) += marker_rng.InBall(options.marker_mm * 1e-3) / s_segment;
  }
  return p;
}

Status MakeVirtualSubject(std::uint64_t seed, const SubjectOptions& options, VirtualSubject* out) {
  std::string error;
  if (!options.IsValid(&error)) return Status::Error("subject options: " + error);
  VirtualSubject subject;
  subject.seed = seed;
  Random height_rng(seed, Stream::kHeight);
  subject.height_m = height_rng.Uniform(options.min_height_m, options.max_height_m);
  subject.nominal = DefaultFullBodyModel(subject.height_m);
  const Model& model = subject.nominal;

  const Eigen::VectorXd p = PerturbedParameters(model, seed, options);
  subject.truth_parameters = p;
  MOCAP_RETURN_IF_ERROR(model.WithParameters(p, &subject.truth));
  *out = std::move(subject);
  return Status::Ok();
}

}  // namespace mocap::sim
