// The two linear-algebra halves of the tracker's Kalman filter (the model-specific parts, the
// marker predictions and Jacobians, are in tracker.cpp). See ekf/tracker.h for the equations and
// why they are arranged this way; tests/test_ekf.cpp checks both against the dense textbook
// formulas.
//
// The state is x = [z; z'; z''] with n_z coordinates each, the covariance P is 3 n_z x 3 n_z.
#pragma once

#include <Eigen/Cholesky>
#include <Eigen/Core>

namespace mocap::ekf {

// x <- F x, P <- F P F^T + Q for independent constant-acceleration (white-jerk) coordinates,
// jerk_psd[i] the jerk spectral density of coordinate i. F's block structure makes this O(n_z^2)
// and in place; allocation-free.
void PredictConstantAcceleration(double dt, const Eigen::VectorXd& jerk_psd, Eigen::VectorXd* x,
                                 Eigen::MatrixXd* P);
// The same, followed by a decay of the velocities and accelerations, v *= velocity_decay,
// a *= acceleration_decay (F becomes diag(1, velocity_decay, acceleration_decay) F): a coordinate
// the markers stop observing (a foot whose toe marker is hidden) coasts to a stop instead of
// running away on its last acceleration. Decays of 1 give the plain model.
void PredictConstantAcceleration(double dt, const Eigen::VectorXd& jerk_psd, double velocity_decay,
                                 double acceleration_decay, Eigen::VectorXd* x, Eigen::MatrixXd* P);
// The same, with only P's lower triangle and its coordinates' block P_zz whole afterwards: the
// strict upper triangle outside P_zz is left as it was. For a caller whose next use of the rest of
// P is CoordinateUpdate::Apply, which reads the lower triangle only and writes the whole matrix
// (the tracker: one 114 x 114 mirror a frame saved); any other reader first calls
// MirrorLowerToUpper.
void PredictConstantAccelerationLower(double dt, const Eigen::VectorXd& jerk_psd,
                                      double velocity_decay, double acceleration_decay,
                                      Eigen::VectorXd* x, Eigen::MatrixXd* P);
// P's strict upper triangle <- the transpose of its lower one.
void MirrorLowerToUpper(Eigen::MatrixXd* P);

// The measurement update for measurements of the coordinates only (H = [J 0 0]), in information
// form on the observed block, from the accumulated A = J^T R^-1 J (n_z x n_z, full symmetric),
// b = J^T R^-1 nu and nu^T R^-1 nu. Keeps its workspace: allocation-free after Resize.
class CoordinateUpdate {
 public:
  void Resize(int nz);
  // Updates x and P; returns false (x and P untouched) when P_zz is not positive-definite or
  // the step is not finite. *nis receives nu^T S^-1 nu. Reads P's lower triangle only; the P it
  // writes is whole (symmetric).
  bool Apply(const Eigen::MatrixXd& A, const Eigen::VectorXd& b, double nu_r_nu,
             Eigen::VectorXd* x, Eigen::MatrixXd* P, double* nis);

 private:
  int nz_ = 0;
  Eigen::MatrixXd L_, LB_, X_, V_, U_, tmp_;
  Eigen::VectorXd c_, lb_, dx_, reciprocal_l_, reciprocal_b_;
};

}  // namespace mocap::ekf
