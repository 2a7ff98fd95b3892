// The virtual subject: a body whose TRUE geometry is known, so the fit can be scored against it.
//
// From a seed: a height in [min_height_m, max_height_m]; the NOMINAL model is
// DefaultFullBodyModel(height) — what the fit starts from, as a lab would; the TRUE model is the
// nominal one perturbed the way real bodies and marker placements differ from it:
//   - every segment's scale factor multiplied by U(1 - scale_spread, 1 + scale_spread);
//   - every non-root joint centre moved by a vector uniform in a ball of radius centre_mm,
//     in metres in the (true, scaled) parent frame: since centres are stored unscaled, the stored
//     centre moves by d / s_parent, and the actual centre lands |d| from where the nominal centre
//     would sit in the true-scaled parent;
//   - every fitted axis (hinge and universal elements) tilted by (alpha, beta) uniform in a disc
//     of radius axis_deg, i.e. by at most axis_deg;
//   - every marker moved by a vector uniform in a ball of radius marker_mm on its segment
//     (likewise d / s_segment in the stored, unscaled position).
// Each kind of perturbation draws from its own random stream (sim/random.h), so adding a marker to
// the model does not change the subject's scales.
#pragma once
#include <Eigen/Core>
#include <cstdint>
#include <string>

#include "model/model.h"

namespace mocap::sim {

struct SubjectOptions {
  double min_height_m = 1.55;
  double max_height_m = 1.95;
  double scale_spread = 0.10;  // scale factors in [1 - spread, 1 + spread]
  double centre_mm = 15.0;     // joint centre displacement, at most
  double axis_deg = 5.0;       // axis tilt, at most
  double marker_mm = 10.0;     // marker displacement on its segment, at most

  // False (with a message naming the field) for negative, non-finite or inconsistent values.
  bool IsValid(std::string* error) const;
};

struct VirtualSubject {
  std::uint64_t seed = 0;
  double height_m = 0.0;
  Model nominal;                 // DefaultFullBodyModel(height_m), all markers
  Model truth;                   // nominal.WithParameters(truth_parameters), all markers
  Eigen::VectorXd truth_parameters;  // p of the truth in the nominal model's layout
};

// The parameters of `model` (model.InitialParameters()) perturbed as described above, drawn from
// `seed`: works on any model (the default one, an imported OpenSim model); joints without a
// fitted centre or axis are left as they are. The height fields of `options` are not used here.
// `options` must be valid (IsValid).
Eigen::VectorXd PerturbedParameters(const Model& model, std::uint64_t seed, const SubjectOptions& options);

// A subject drawn from `seed`. An error when the options are not valid (IsValid's message).
Status MakeVirtualSubject(std::uint64_t seed, const SubjectOptions& options, VirtualSubject* out);

}  // namespace mocap::sim
