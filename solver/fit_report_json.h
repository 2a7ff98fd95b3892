// The fit's report as JSON: `mocap fit --report`, the daemon's fit.start reply and its stored
// fit reports are this one object, so a lab's scripts read one format wherever the fit ran.
#pragma once
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "solver/fit_trust.h"
#include "solver/global_fit.h"

namespace mocap::solver {

// Besides the totals it carries what the report page (report/fit_report_html.h) draws: each
// trial's rate and per-frame marker RMS, and the solve's iteration history.
// `trial_sources` names each trial's source (a file, a recording), in the order of `trials`.
nlohmann::json FitReportJson(const FitReport& report, const std::vector<FitTrial>& trials,
                             const std::vector<std::string>& trial_sources);

// The per-joint trust table (solver/fit_trust.h) as the report's "joint_checks" array: one object
// per joint {joint, type, axis_joint, from_generic_mm, axis_from_generic_deg, fitted_std_mm
// (null: centre not fitted), undetermined, best_trial (null: no trial excites it), trials:
// [{trial, estimated, excited, note, frames, and when excited: far, and centre_distance_mm,
// centre_spread_mm, functional_std_mm (centre joints) or axis_angle_deg, axis_spread_deg,
// functional_axis_std_deg, axis_line_distance_mm (axis joints)}]}. The page (report/fit_report_html.h) reads it
// from the report, so `mocap fit` adds it with report["joint_checks"] = FitTrustJson(trust).
nlohmann::json FitTrustJson(const FitTrust& trust);

}  // namespace mocap::solver
