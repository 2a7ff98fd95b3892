// Evaluating an OpenSim model and a .mot of its coordinates against measured markers, the one way
// both OpenSim's results and ours are scored in the tests: per frame, the pose from the .mot row
// (OpenSim's coordinate names; rotational coordinates in degrees when inDegrees), the TRC frame
// nearest in time, and every model marker the trial has; RMS of the 3D distances over all those
// samples (OpenSim's convention, no marker weights).
#pragma once
#include <gtest/gtest.h>

#include <cmath>
#include <string>
#include <vector>

#include "formats/marker_data.h"
#include "formats/osim.h"
#include "model/kinematics.h"

namespace mocap::testutil {

// Index of the time in `times` nearest to t.
inline int NearestTime(const std::vector<double>& times, double t) {
  int best = 0;
  for (int k = 1; k < static_cast<int>(times.size()); ++k)
    if (std::abs(times[k] - t) < std::abs(times[best] - t)) best = k;
  return best;
}

// Column of every model coordinate in `table` (-1 where absent).
inline std::vector<int> CoordinateColumns(const Model& m, const formats::CoordinateTable& table) {
  std::vector<int> column(m.num_coordinates());
  for (int c = 0; c < m.num_coordinates(); ++c) column[c] = table.FindColumn(m.coordinates()[c].name);
  return column;
}

// The pose z of row `row` of an OpenSim .mot for an imported model (radians and metres).
inline Eigen::VectorXd OsimPose(const formats::OsimImport& im, const formats::CoordinateTable& table,
                                const std::vector<int>& column, int row) {
  const Model& m = im.model;
  Eigen::VectorXd z = m.DefaultCoordinates();
  for (int c = 0; c < m.num_coordinates(); ++c) {
    if (column[c] < 0) continue;
    const double v = table.values(row, column[c]);
    z[c] = table.in_degrees && im.motion.at(m.coordinates()[c].name) == formats::OsimMotion::kRotational
               ? v * M_PI / 180
               : v;
  }
  return z;
}

struct MotionRms {
  double rms_mm = 0;
  int frames = 0;
  int samples = 0;
};

// Marker RMS of (model, motion) against `trial` at each time of `at` (the .mot row and the TRC
// frame nearest to it, each within half a frame).
inline MotionRms MarkerRmsOfMotion(const formats::OsimImport& im, const formats::CoordinateTable& motion,
                                   const formats::MarkerTrial& trial, const std::vector<double>& at) {
  const Model& m = im.model;
  const std::vector<int> column = CoordinateColumns(m, motion);
  for (int c = 0; c < m.num_coordinates(); ++c)
    EXPECT_GE(column[c], 0) << "no column for " << m.coordinates()[c].name;
  std::vector<int> in_trial(m.num_markers());
  for (int k = 0; k < m.num_markers(); ++k) in_trial[k] = trial.FindMarker(m.markers()[k].name);
  const Geometry g(m);
  ModelData d(m);
  double sum_sq = 0;
  MotionRms out;
  for (double t : at) {
    const int row = NearestTime(motion.times, t), tf = NearestTime(trial.times, t);
    EXPECT_LT(std::abs(motion.times[row] - t), 0.5 / trial.rate_hz);
    EXPECT_LT(std::abs(trial.times[tf] - t), 0.5 / trial.rate_hz);
    ForwardKinematics(m, g, OsimPose(im, motion, column, row), &d);
    for (int k = 0; k < m.num_markers(); ++k) {
      if (in_trial[k] < 0 || !trial.Has(tf, in_trial[k])) continue;
      sum_sq += (MarkerPosition(m, g, d, k) - trial.At(tf, in_trial[k])).squaredNorm();
      ++out.samples;
    }
    ++out.frames;
  }
  out.rms_mm = 1000 * std::sqrt(sum_sq / std::max(1, out.samples));
  return out;
}

}  // namespace mocap::testutil
