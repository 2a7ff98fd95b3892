// The fit's report as ONE self-contained HTML page: what a lab looks at after a calibration
// session to decide whether the model can be trusted (issue 20), the way Vicon Nexus and
// OpenSim's GUI show the skeleton and the residuals.
//
// Design:
// - The page is built from the fit's report JSON (solver/fit_report_json.h) and the two models
//   (the nominal/initial one and the fitted one), never from the solver's internals: `mocap fit
//   --html` and the daemon's `export {kind: "report", format: "html"}` (which only has the stored
//   report JSON and model versions, daemon/store.h) call the same WriteFitReportHtml, so the two
//   pages cannot drift apart. The figures shown are the report's; the page computes only
//   geometry to draw (projections, distances between the two models' joint centres).
// - Self-contained: inline CSS and inline SVG (report/svg_writer.h), no script, no web font, no
//   image or style fetched: it opens from a USB stick on a lab PC without a network, and prints
//   to A4 (@media print: page size, margins, no section split across pages).
// - Highlights are CSS classes and element ids the tests search: `#not-converged` (the solve
//   stopped for another reason than convergence), `#outliers` with each outlying marker named and
//   its bar of class `bar outlier`, rows and list items of class `undetermined` (greyed) for the
//   parameters the data did not determine.
// - The three orthographic views assume the lab frame of model/default_model.h (Z up, X
//   anterior, Y left); each view's <g class="view"> carries its projection (data-scale,
//   data-ox, data-oy, data-h, data-v: screen = (ox + scale * p.h, oy - scale * p.v)) and each
//   joint centre's <circle> its joint (data-joint) and model (class fitted or nominal), so a
//   test can check that every centre is drawn where the model puts it.
#pragma once

#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "model/model.h"
#include "model/status.h"

namespace mocap::report {

// One protocol excitation checked on a recording (sim/protocol.h CheckExcitations; the daemon
// stores them as a recording's coverage): the range required against the range reached.
struct CoverageRow {
  std::string movement;
  std::string coordinate;
  double required_min_deg = 0, required_max_deg = 0;
  double reached_min_deg = 0, reached_max_deg = 0;  // NaN when never reached
  bool required = true;
  bool ok = false;
};

// A part of a trial drawn as a band inside its RMS strip: a protocol movement's phase
// (sim/protocol.h MovementPhases), frames [first_frame, last_frame] of the trial named `trial`
// (the report's per_trial name).
struct TrialBand {
  std::string trial;
  std::string label;
  int first_frame = 0, last_frame = 0;
};

struct FitReportPage {
  nlohmann::json report;   // solver/fit_report_json.h FitReportJson
  Model initial;           // the nominal model the fit started from
  Model fitted;            // the fitted model (without the fit's virtual markers)
  std::string title = "Model fit report";
  std::string model_file;  // where the initial model came from
  nlohmann::json options = nlohmann::json::object();  // the fit's options, shown as given
  std::vector<CoverageRow> coverage;                  // empty: none given
  std::vector<TrialBand> bands;                       // empty: none drawn
  std::string software_version;
  std::string date;        // shown as given (the caller's clock or the store's created_at)
  // How much the standard-deviation ellipses are magnified in the views (a 2 mm sd is a
  // fraction of a pixel at body scale).
  double ellipse_magnification = 10.0;

  // An error naming what is missing: the report's fields the page reads, models that do not
  // have the same joints and segments.
  bool IsValid(std::string* error) const;
};

// The page for `inputs`; *html untouched on error.
Status WriteFitReportHtml(const FitReportPage& inputs, std::string* html);

// The page's inputs from what the daemon stores: the report JSON and the two model versions'
// JSON (model/model_io.h). Errors name which text does not parse.
Status FitReportPageFromJson(const std::string& report_json, const std::string& initial_model_json,
                             const std::string& fitted_model_json, FitReportPage* page);

// Appends a recording's coverage as the daemon stores it (daemon.cpp: {"ok", "excitations":
// [{coordinate, min_deg, max_deg, reached_min_deg, reached_max_deg (null: never reached),
// required, ok}]}) as rows of `movement`. An error names the field that is missing or mistyped.
Status AppendCoverageRows(const std::string& movement, const std::string& coverage_json,
                          std::vector<CoverageRow>* rows);

// The three orthographic views, shared with the tests: horizontal and vertical screen
// directions in the lab frame (Z up, X anterior, Y left).
struct OrthographicView {
  const char* name;  // "front", "side", "top"
  double h[3];
  double v[3];
};
const std::vector<OrthographicView>& SkeletonViews();

}  // namespace mocap::report
