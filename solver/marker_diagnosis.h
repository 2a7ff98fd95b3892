// Why a marker's residual stays high after the fit: the report must say more than "RKNE 48 mm".
// A lab can act on "RKNE follows RTIB's place throughout: swapped with RTIB?" or "RKNE rides on
// tibia_r, not femur_r: attached to the wrong body?" or "LASI mislabelled in trial 'walk',
// frames 812-1040"; it cannot act on a number. Vicon Nexus and QTM leave this to the operator,
// who scrubs through the trial looking for the jump.
//
// Each outlying marker (FitReport::outlier_markers) is tested against the explanations a lab
// meets, from the fitted model and poses alone (no refit). The poses are first re-solved per
// frame without the markers far off in that frame: a least-squares fit spreads a bad marker's
// error over its limb's pose, and against the fit's own poses every marker of the limb looks a
// little bad and the bad one less bad than it is. Then, in this order:
//   1. The wrong body. In the frame of the segment the model attaches it to, it moves; in the
//      frame of another segment it stays put (solver/attach_markers.h MarkerSpreadOnSegments):
//      the model attaches it to the wrong segment (or the lab put it somewhere else). First,
//      because its error grows with the joint angle between the two segments, so on a trial with
//      a few large flexions it would also pass for a stretch.
//   2. A stretch of frames. A label that moves to another marker and back makes the data jump:
//      the stretch between two jumps (the worst-fitting such piece), else between a jump and a
//      trial's end (the shorter side). Without jumps, its per-frame residual (distance from where
//      the fitted model puts it) is split into frames far above the marker's own median and the
//      rest; a run of bad frames covering less than `max_stretch_fraction` of the frames where
//      it is seen is a labelling error over that stretch (a label that jumped to a neighbour when two markers
//      crossed, a gap filled with the wrong marker). If over the stretch the data lie at another
//      marker's fitted place, that marker is named.
//   3. A swap. Its data, over every frame, lie close to where the fitted model puts another
//      marker (much closer than to its own place): the two labels are exchanged.
//   4. Otherwise it moves on its own segment about as much as it moves anywhere: a marker that
//      slipped, a wand that wobbles, or soft tissue — weight it by its own spread
//      (FitOptions::marker_sigma_rounds) or leave it out.
// The fit is not changed by the diagnosis; a robust loss or leaving the marker out is the
// caller's decision, and the report says which marker to look at first.
#pragma once

#include <Eigen/Core>
#include <string>
#include <vector>

#include "formats/marker_data.h"
#include "model/model.h"
#include "model/status.h"

namespace mocap::solver {

struct MarkerDiagnosisOptions {
  // A frame is bad when its residual exceeds both `bad_ratio` x the marker's median residual and
  // the median + `bad_min_mm`.
  double bad_ratio = 3.0;
  double bad_min_mm = 15.0;
  int min_stretch_frames = 10;         // shorter runs of bad frames are noise, not a label
  int stretch_gap_frames = 5;          // good frames inside a stretch that do not end it
  double max_stretch_fraction = 0.6;   // a longer "stretch" is the whole trial: see 2-4
  // A jump in the data (a label moving to another marker): a step between consecutive frames
  // above jump_ratio x the marker's median step and above jump_min_mm. Stretches are looked
  // for between jumps first, then as runs of bad frames.
  double jump_ratio = 8.0;
  double jump_min_mm = 30.0;
  // A swap (or the marker a stretch takes the place of): the data's RMS distance from the other
  // marker's fitted place is below `swap_ratio` x its distance from its own and below swap_max_mm.
  double swap_ratio = 0.5;
  double swap_max_mm = 20.0;
  // The wrong body: the best segment's spread is below wrong_body_max_spread_mm and the attached
  // segment's is above `wrong_body_ratio` x the best one's.
  double wrong_body_max_spread_mm = 15.0;
  double wrong_body_ratio = 1.5;
  bool IsValid(std::string* error) const;
};

struct MarkerDiagnosis {
  enum class Kind { kStretch, kSwap, kWrongBody, kMoves };
  std::string marker;
  double rms_mm = 0;          // over the fit (FitReport::per_marker_rms_mm)
  Kind kind = Kind::kMoves;
  std::string segment;        // the segment the model attaches it to
  std::string other_marker;   // kSwap; kStretch when its data take another marker's place there
  std::string rides_on;       // the segment its trajectory is most rigid on
  double spread_on_segment_mm = 0, spread_on_best_mm = 0;
  std::string trial;          // kStretch: where, frames [first_frame, last_frame]
  int first_frame = -1, last_frame = -1;
  double stretch_rms_mm = 0, elsewhere_rms_mm = 0;  // kStretch: residual RMS inside / outside
  std::string text;           // one line for the log and the report
};
const char* ToString(MarkerDiagnosis::Kind kind);

// `model` and `poses` are the fit's result (FitResult::model, ::coordinates); `outliers` the
// report's outlying markers (name, RMS mm). A name the model lacks is skipped.
Status DiagnoseMarkers(const Model& model, const std::vector<formats::MarkerTrial>& trials,
                       const std::vector<Eigen::MatrixXd>& poses,
                       const std::vector<std::pair<std::string, double>>& outliers,
                       const MarkerDiagnosisOptions& options, std::vector<MarkerDiagnosis>* out);

}  // namespace mocap::solver
