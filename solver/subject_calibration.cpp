#include "solver/subject_calibration.h"

#include <cstdio>

namespace mocap::solver {

bool SubjectCalibrationOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& what) {
    if (error) *error = what;
    return false;
  };
  std::string why;
  if (!fit.IsValid(&why)) return fail("fit: " + why);
  if (!(centre_marker_tolerance_m > 0)) return fail("centre_marker_tolerance_m must be > 0");
  if (!(proximity_ratio >= 1)) return fail("proximity_ratio must be >= 1");
  if (!(proximity_max_mm > 0)) return fail("proximity_max_mm must be > 0");
  return true;
}

int SubjectCalibrationSummary::Attached() const {
  int n = 0;
  for (const AttachedMarker& a : fit.attached_markers) n += a.segment.empty() ? 0 : 1;
  for (const AttachedMarker& a : attached_by_proximity) n += a.segment.empty() ? 0 : 1;
  return n;
}

std::vector<std::string> SubjectCalibrationSummary::NotAttached() const {
  std::vector<std::string> out;
  for (const AttachedMarker& a : fit.attached_markers) {
    if (!a.segment.empty()) continue;
    std::string why = a.why_not;
    for (const AttachedMarker& p : attached_by_proximity)
      if (p.name == a.name) why = p.segment.empty() ? p.why_not : "";
    if (!why.empty()) out.push_back(a.name + ": " + why);
  }
  return out;
}

std::string SubjectCalibrationSummary::BriefReport() const {
  int by_motion = 0, by_proximity = 0, placed = 0;
  for (const AttachedMarker& a : fit.attached_markers) by_motion += a.segment.empty() ? 0 : 1;
  for (const AttachedMarker& a : attached_by_proximity) by_proximity += a.segment.empty() ? 0 : 1;
  for (const PlacedMarker& p : fit.placed_markers) placed += p.why_not.empty() ? 1 : 0;
  char text[400];
  std::snprintf(text, sizeof text,
                "subject calibration: marker RMS %.2f -> %.2f mm (%d iterations, %s); %d placeholder markers "
                "placed, %d trial markers attached (%d by their motion, %d by the markers beside them), %zu not; "
                "%d markers in the subject model",
                fit.initial_marker_rms_mm, fit.marker_rms_mm, fit.solver.num_iterations(),
                fit.converged() ? "converged" : "not converged", placed, by_motion + by_proximity, by_motion,
                by_proximity, NotAttached().size(), model_markers);
  return text;
}

Status CalibrateSubject(const Model& generic, const formats::MarkerTrial& trial,
                        const SubjectCalibrationOptions& options, Model* subject,
                        SubjectCalibrationSummary* summary) {
  std::string why;
  if (!options.IsValid(&why)) return Status::Error("subject calibration: " + why);
  *summary = SubjectCalibrationSummary{};
  const std::vector<formats::MarkerTrial> trials = {trial};
  Model model = generic;
  MOCAP_RETURN_IF_ERROR(TieCentreMarkers(trials, options.centre_marker_tolerance_m, &model, &summary->centre_markers));
  FitOptions fit = options.fit;
  for (const CentreMarker& c : summary->centre_markers) fit.fixed_markers.push_back(c.marker);
  FitResult result;
  MOCAP_RETURN_IF_ERROR(FitModel(model, {FitTrial{trial, {}}}, fit, &result));
  summary->fit = result.report;
  // What the motion could not attach, because the trial does not move the joint between two
  // segments (a static posture: none), by the markers beside it; not a marker that moves on
  // every segment (no segment carries it) nor one seen too rarely.
  std::vector<std::string> undecided;
  for (const AttachedMarker& a : result.report.attached_markers)
    if (a.segment.empty() && a.samples >= fit.attach.min_samples && a.spread_mm <= fit.attach.max_spread_mm)
      undecided.push_back(a.name);
  Model with = result.model;
  if (!undecided.empty())
    MOCAP_RETURN_IF_ERROR(AttachMarkersByProximity(result.model, trials, result.coordinates, undecided,
                                                   options.proximity_ratio, options.proximity_max_mm,
                                                   fit.attach.min_samples, &with,
                                                   &summary->attached_by_proximity));
  MOCAP_RETURN_IF_ERROR(UntieCentreMarkers(summary->centre_markers, &with));
  summary->model_markers = with.num_markers();
  *subject = std::move(with);
  return Status::Ok();
}

}  // namespace mocap::solver
