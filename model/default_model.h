// The default full-body model: pelvis free joint; lumbar, neck, hips and shoulders spherical;
// knees hinges; elbows flexion + pronation; ankles and wrists two hinges (universal); 38
// coordinates. Lab frame Z up; segment frames x anterior, y left, z up in the standing pose.
// Markers: the Plug-in Gait full-body set (39) and, marked optional, medial knee (LKNM/RKNM) and
// medial ankle (LMMA/RMMA) markers. Dimensions follow Winter's segment-length fractions of
// stature for a 1.75 m adult; `height_m` scales every segment uniformly.
#pragma once
#include "model/model.h"

namespace mocap {

Model DefaultFullBodyModel(double height_m = 1.75);

}  // namespace mocap
