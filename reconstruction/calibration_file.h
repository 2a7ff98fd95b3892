// The calibration file: every camera's id, intrinsics (OpenCV's parameters, camera_model.h) and
// pose (R, t: world/lab -> camera, metres), with the quality figures of the calibration that made
// it. JSON:
//
//   {"format": "mocap-calibration", "version": 1, "lab_frame": "L-frame" | "camera 0",
//    "reprojection_rms_px": 0.13, "wand_length_error_mm_rms": 0.26, "wand_length_error_mm_mean":
//    0.0, "wand_markers_m": [0, 0.2, 0.5], "cameras": [{"id": "sim-0", "width": 1280, "height":
//    1024, "fx": .., "fy": .., "cx": ..,
//                 "cy": .., "k1": .., "k2": .., "p1": .., "p2": .., "k3": ..,
//                 "R": [[..], [..], [..]], "t": [.., .., ..],
//                 "reprojection_rms_px": .., "wand_frames": ..,
//                 "position_error_mm": .., "orientation_error_deg": ..}]}   // last two: simulation
//
// The reader validates everything a wrong file could carry — not JSON, a missing or mistyped
// field, a non-finite number, a matrix that is not a rotation, a duplicated id — and names the
// file and the field. MatchCalibrationToRig then checks it against the cameras actually present.
#pragma once

#include <limits>
#include <string>
#include <vector>

#include "model/status.h"
#include "reconstruction/calibration.h"
#include "reconstruction/camera_model.h"
#include "reconstruction/centroid.h"

namespace mocap::reconstruction {

struct CalibratedCamera {
  CameraModel camera;
  static constexpr double kNone = std::numeric_limits<double>::quiet_NaN();
  double reprojection_rms_px = kNone;  // NaN: not known (not written)
  int wand_frames = 0;
  double position_error_mm = kNone;  // against the truth, simulations only
  double orientation_error_deg = kNone;
};

struct CalibrationFile {
  std::vector<CalibratedCamera> cameras;
  std::string lab_frame = "camera 0";
  double reprojection_rms_px = CalibratedCamera::kNone;
  double wand_length_error_mm_rms = CalibratedCamera::kNone;
  double wand_length_error_mm_mean = CalibratedCamera::kNone;
  std::vector<double> wand_markers_m;

  std::vector<CameraModel> Models() const;
};

// The file of a wand calibration's result: `calibrated` (CalibrateWand's cameras, in order), its
// summary's figures per camera and for the rig, and the wand it used.
CalibrationFile CalibrationFileOf(const std::vector<CameraModel>& calibrated,
                                  const WandCalibrationSummary& summary, const Wand& wand);

Status WriteCalibrationJson(const std::string& path, const CalibrationFile& file);
// The JSON document WriteCalibrationJson writes.
std::string CalibrationJsonString(const CalibrationFile& file);
Status ReadCalibrationJson(const std::string& path, CalibrationFile* file);
// Parses a document already in memory; `name` stands for the file in error messages.
Status ParseCalibrationJson(const std::string& text, const std::string& name,
                            CalibrationFile* file);

// Orders the calibrated cameras as `rig_ids` (the cameras present). Errors name the cameras the
// calibration lacks or does not know, and a wrong count.
Status MatchCalibrationToRig(const CalibrationFile& file, const std::vector<std::string>& rig_ids,
                             std::vector<CameraModel>* ordered);

// Wand-calibration input recorded as 2D centroids, so calibration can run from a file:
//
//   {"format": "mocap-wand-observations", "version": 1, "cameras": ["id0", "id1", ...],
//    "wand_markers_m": [0, 0.2, 0.5], "lframe_markers_m": [[x, y, z], ...],
//    "wand_frames": [[[[u, v], ...] or null, ...one entry per camera], ...],
//    "lframe_frames": [...same...]}
//
// Each frame lists, per camera in "cameras" order, its unlabelled centroids (pixels), or null
// when that camera's image is missing.
struct WandObservations {
  std::vector<std::string> camera_ids;
  Wand wand;
  LFrame lframe;
  std::vector<DetectionSet> wand_frames, lframe_frames;
};
Status WriteWandObservationsJson(const std::string& path, const WandObservations& obs);
Status ReadWandObservationsJson(const std::string& path, WandObservations* obs);

}  // namespace mocap::reconstruction
