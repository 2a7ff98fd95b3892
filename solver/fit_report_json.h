// The fit's report as JSON: `mocap fit --report`, the daemon's fit.start reply and its stored
// fit reports are this one object, so a lab's scripts read one format wherever the fit ran.
#pragma once
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "solver/global_fit.h"

namespace mocap::solver {

// Besides the totals it carries what the report page (report/fit_report_html.h) draws: each
// trial's rate and per-frame marker RMS, and the solve's iteration history.
// `trial_sources` names each trial's source (a file, a recording), in the order of `trials`.
nlohmann::json FitReportJson(const FitReport& report, const std::vector<FitTrial>& trials,
                             const std::vector<std::string>& trial_sources);

}  // namespace mocap::solver
