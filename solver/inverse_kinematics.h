// Per-frame inverse kinematics: the pose z that best fits one frame's measured markers for a
// fixed model geometry, by a small dense Levenberg–Marquardt (what OpenSim's IK tool does, with
// the model's marker weights: Marker::weight, 1 unless the fit sets it). It builds the global fit's initial guess when data come from a file
// instead of the live filter: the trial's most complete frame starts from the best of several
// placements of the default pose -- turned to four headings, and rigidly aligned (Kabsch) onto all
// measured markers and onto the root segment's markers -- so a subject facing any direction in a
// lab whose vertical is Y, Z or -Z is found without being told; the other
// frames are solved outwards from it, each warm-started from its neighbour (and re-initialised
// when the warm start fails).
#pragma once

#include <Eigen/Cholesky>
#include <Eigen/Core>
#include <vector>

#include "model/kinematics.h"
#include "model/model.h"
#include "model/status.h"

namespace mocap::solver {

struct IkOptions {
  int max_iterations = 50;
  double step_tolerance = 1e-8;       // stop when |dz| < this
  double restart_rms_m = 0.03;        // a warm start worse than this re-initialises
  // SolveTrial: a frame with hidden markers is re-solved from its pose interpolated between the
  // nearest frames that see those markers (InverseKinematics::BridgeGaps).
  bool bridge_gaps = true;
  // A clamped coordinate (Coordinate::clamped) beyond its range by d (rad or m) costs what a
  // marker d * stiffness metres off costs (the global fit's FitOptions::coordinate_limit_sigma_*
  // wall at its defaults: 1 m per radian). 0: ranges not enforced.
  double coordinate_limit_stiffness = 1.0;
  bool IsValid(std::string* error) const;
};

struct IkFrameResult {
  double rms_m = 0;        // RMS marker distance after the solve
  int iterations = 0;
  int markers = 0;         // markers present in the frame
};

// Which coordinates only turn rotations by their own value (identity or +-1-slope functions): a
// whole turn more or less leaves every marker where it was, so the data cannot tell z from
// z + 2 pi. Priors can: see WrapPeriodicCoordinates.
std::vector<char> PeriodicCoordinates(const Model& model);
// Moves each periodic coordinate of z by whole turns to its representative nearest the centre
// of its range (a joint whose range is narrower than a turn) or nearest reference[c] (one that
// may turn round, and every coordinate of the joint to the lab). Markers stay where they are.
void WrapPeriodicCoordinates(const Model& model, const std::vector<char>& periodic, const Eigen::VectorXd& reference,
                             Eigen::VectorXd* z);

// The coordinates whose range is a limit the pose must keep: clamped (Coordinate::clamped) with a
// finite range, and not of the root joint, which places the model in the lab, whose axes are
// the lab's, not the model's ground's (a Z-up lab puts pelvis_list near 90 deg). Shared by the
// IK's wall and the global fit's (MarkerFitProblem::coordinate_limits).
std::vector<int> LimitedCoordinates(const Model& model);
// How far q lies beyond coordinate co's range (signed; 0 inside).
inline double RangeExcess(const Coordinate& co, double q) {
  return q > co.max_value ? q - co.max_value : (q < co.min_value ? q - co.min_value : 0.0);
}

class InverseKinematics {
 public:
  InverseKinematics(const Model& model, const Geometry& geometry, IkOptions options = IkOptions());

  // measured: 3 x n_markers in model marker order (NaN = missing). z: in = start, out = solution.
  // free: coordinates to solve for (empty = all).
  IkFrameResult Solve(const Eigen::Matrix3Xd& measured, Eigen::VectorXd* z,
                      const std::vector<char>& free = {});
  // A pose from nothing: each placement of the default pose above with its root solved alone;
  // from the two best of those a full solve; the lower marker RMS wins.
  IkFrameResult Initialise(const Eigen::Matrix3Xd& measured, Eigen::VectorXd* z);

  // Solves every frame of a trial (rows of `measured`: frames x 3 n_markers, model order): the
  // frame with the most markers from scratch, then the others warm-started outwards from it. Fills `coordinates` (frames x n_coordinates) and the
  // per-frame RMS. A frame with fewer than 3 markers keeps its neighbour's pose; the trial fails
  // only when no frame has 3 markers.
  Status SolveTrial(const Eigen::Ref<const Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic,
                                                          Eigen::RowMajor>>& measured,
                    Eigen::MatrixXd* coordinates, std::vector<double>* rms_m = nullptr);

 private:
  // In a gap, what the hidden markers observed is lost: a hand whose only marker is hidden
  // leaves both wrist angles free, a two-marker foot with its toe marker hidden leaves the
  // rotation about the line from the ankle to the heel marker nearly free and may fit the heel
  // marker equally well in a second, turned branch. The sweep's warm start holds such
  // coordinates at the frame before the gap (or wherever a re-initialisation put them); the
  // global fit then has to move them over the whole gap while they are held by almost nothing
  // (solver/coarse_to_fine.h, UnobservedCoordinateWeights). So a frame with hidden markers is
  // re-solved from the pose interpolated in time between the nearest frames that see every one
  // of them (the motion is smooth over a gap of a few tens of frames), and the result kept
  // unless its RMS is clearly worse than the sweep's.
  void BridgeGaps(const Eigen::Ref<const Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic,
                                                       Eigen::RowMajor>>& measured,
                  const std::vector<double>& frame_rms, Eigen::MatrixXd* coordinates,
                  std::vector<double>* rms_m);

  const Model& model_;
  const Geometry& geometry_;
  IkOptions options_;
  ModelData data_;
  std::vector<char> periodic_;
  std::vector<int> limited_;  // clamped coordinates (enforced when coordinate_limit_stiffness > 0)
  // Sum of (stiffness * excess)^2 over the limited coordinates of z: the limits' share of the cost.
  double LimitCost(const Eigen::VectorXd& z) const;
  Eigen::MatrixXd jtj_, damped_;
  Eigen::LLT<Eigen::MatrixXd> llt_;
  Eigen::VectorXd jtr_;
  Eigen::Matrix<double, 3, Eigen::Dynamic> jz_;
};

}  // namespace mocap::solver
