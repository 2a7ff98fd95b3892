// The subject model a lab labels its trials with. A generic model is not the subject: its segments
// are another body's size, its marker places a template's (a generic OpenSim model stacks a lab's
// thigh cluster on one placeholder point), and it lacks the markers the lab adds beside its
// marker set (biobuddy's THID and TIBD beside Plug-in Gait's THI and TIB, at the heights where
// the template puts those). Labelled with it, the tracker puts a marker on its neighbour's point
// wherever the neighbour sits where the template puts the marker -- nothing else tells two points
// rigid with one segment apart. Vicon Nexus and QTM do not label with a template either: the
// labelling skeleton (Nexus) or AIM model (QTM) is first calibrated to the subject on one
// labelled static trial, and every other trial of the session is labelled with that subject
// model, which knows every marker the lab wears.
//
// CalibrateSubject does that with the global fit (solver/global_fit.h) of the generic model to
// the static trial: segments scaled, marker places fitted, placeholder markers placed where the
// trial puts them, and the trial's markers the model lacks attached -- by their motion where the
// trial moves the joints (AttachTrialMarkers), else, in a static posture, by the model markers
// they sit beside (AttachMarkersByProximity). Markers the model puts on a joint centre are tied
// to it during the fit and put back after, as `mocap fit` does (TieCentreMarkers).
#pragma once

#include <string>
#include <vector>

#include "formats/marker_data.h"
#include "model/model.h"
#include "model/status.h"
#include "solver/attach_markers.h"
#include "solver/global_fit.h"

namespace mocap::solver {

struct SubjectCalibrationOptions {
  FitOptions fit;
  // TieCentreMarkers' tolerance (as `mocap fit`'s).
  double centre_marker_tolerance_m = 0.002;
  // AttachMarkersByProximity's: the nearest model marker of any other segment at least this many
  // times as far as the nearest one. At 1.5 a marker beside its own segment's markers (biobuddy's
  // THID 67-76 mm from THI, TIBD 55-57 mm from TIB, the other segments' beyond 170 mm) is
  // attached, one between two segments (S1: 129 / 135 mm) is not.
  double proximity_ratio = 1.5;
  // And the nearest within this (mm): biobuddy's attached ones are 45-117 mm from theirs (T6 from
  // T10 the farthest); gait2354's arm and head markers are 175-537 mm from its torso's (its arms
  // ride on no segment of that model).
  double proximity_max_mm = 150.0;
  bool IsValid(std::string* error) const;
};

struct SubjectCalibrationSummary {
  FitReport fit;                                // the fit's (its attached and placed markers too)
  std::vector<CentreMarker> centre_markers;     // tied to their joint centres during the fit
  // The fit's attached markers that it could not place by their motion, judged by proximity.
  std::vector<AttachedMarker> attached_by_proximity;
  int model_markers = 0;                        // in the subject model
  // Every trial marker the generic model lacks: attached (by motion or proximity) or not.
  int Attached() const;
  std::vector<std::string> NotAttached() const;  // "NAME: why"
  std::string BriefReport() const;
};

// `generic` fitted to the labelled static trial `trial` (a lab's calibration trial): *subject is
// the fitted model with the attached markers. Errors: the fit's (a trial with none of the
// model's markers, ...), invalid options.
Status CalibrateSubject(const Model& generic, const formats::MarkerTrial& trial,
                        const SubjectCalibrationOptions& options, Model* subject,
                        SubjectCalibrationSummary* summary);

}  // namespace mocap::solver
