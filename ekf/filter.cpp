#include "ekf/filter.h"

#include <cmath>

namespace mocap::ekf {

namespace {
// In-place lower Cholesky factor of a small SPD matrix (left-looking, column by column; the
// strict upper triangle is zeroed). False when not positive-definite.
bool CholeskyInPlace(Eigen::MatrixXd* a) {
  Eigen::MatrixXd& m = *a;
  const int n = static_cast<int>(m.rows());
  for (int j = 0; j < n; ++j) {
    if (j > 0)
      m.col(j).tail(n - j).noalias() -=
          m.block(j, 0, n - j, j) * m.row(j).head(j).transpose();
    const double d = m(j, j);
    if (!(d > 0) || !std::isfinite(d)) return false;
    const double r = std::sqrt(d);
    m(j, j) = r;
    m.col(j).tail(n - j - 1) /= r;
  }
  m.triangularView<Eigen::StrictlyUpper>().setZero();
  return true;
}

// V <- V L^-T for a lower-triangular L, i.e. the solution of V L^T = V, column by column
// (left-looking: column j takes the finished columns 0..j-1 in one matrix-vector product, so
// every operation runs down V's long contiguous columns). `reciprocal` holds 1 / L(j, j). At
// n_z = 38 this is 4 times faster than forming L^-1 and multiplying by it, and about as exact.
template <typename Matrix>
void SolveRightLowerTransposed(const Eigen::MatrixXd& L, const Eigen::VectorXd& reciprocal,
                               Matrix&& V) {
  const int n = static_cast<int>(L.rows());
  for (int j = 0; j < n; ++j) {
    if (j > 0) V.col(j).noalias() -= V.leftCols(j) * L.row(j).head(j).transpose();
    V.col(j) *= reciprocal[j];
  }
}
// P's strict upper triangle <- the transpose of its lower one, in 4 x 4 tiles: a tile is read as
// four contiguous column pieces and written as four, where the element-wise transposed copy
// reads every element from a different column (about half the time of
// P.triangularView<StrictlyUpper>() = P.transpose() at 114 x 114).
template <typename Matrix>
void MirrorLower(Matrix&& P) {
  const int n = static_cast<int>(P.rows()), tiled = n / 4 * 4;
  for (int j0 = 0; j0 < tiled; j0 += 4) {
    for (int i0 = 0; i0 < j0; i0 += 4)
      P.template block<4, 4>(i0, j0) = P.template block<4, 4>(j0, i0).transpose();
    for (int j = j0 + 1; j < j0 + 4; ++j)
      for (int i = j0; i < j; ++i) P(i, j) = P(j, i);
  }
  for (int j = tiled; j < n; ++j)
    for (int i = 0; i < j; ++i) P(i, j) = P(j, i);
}
}  // namespace

void MirrorLowerToUpper(Eigen::MatrixXd* P) { MirrorLower(*P); }

void PredictConstantAcceleration(double dt, const Eigen::VectorXd& jerk_psd, Eigen::VectorXd* x,
                                 Eigen::MatrixXd* Pp) {
  PredictConstantAcceleration(dt, jerk_psd, 1.0, 1.0, x, Pp);
}

void PredictConstantAcceleration(double dt, const Eigen::VectorXd& jerk_psd, double velocity_decay,
                                 double acceleration_decay, Eigen::VectorXd* x,
                                 Eigen::MatrixXd* Pp) {
  PredictConstantAccelerationLower(dt, jerk_psd, velocity_decay, acceleration_decay, x, Pp);
  MirrorLowerToUpper(Pp);
}

void PredictConstantAccelerationLower(double dt, const Eigen::VectorXd& jerk_psd,
                                      double velocity_decay, double acceleration_decay,
                                      Eigen::VectorXd* x, Eigen::MatrixXd* Pp) {
  const int nz = static_cast<int>(jerk_psd.size());
  Eigen::MatrixXd& P = *Pp;
  const double h = 0.5 * dt * dt, beta = velocity_decay, alpha = acceleration_decay;
  auto z = x->head(nz);
  auto v = x->segment(nz, nz);
  auto a = x->tail(nz);
  z += dt * v + h * a;
  v += dt * a;
  v *= beta;
  a *= alpha;
  // F = [1 dt h; 0 beta beta*dt; 0 0 alpha] on the 3 x 3 grid of n_z blocks (upper triangular),
  // so block (i, j) of F P F^T reads only the blocks (k >= i, l >= j) of P. The lower blocks are
  // formed in the order (0,0), (1,0), (2,0), (1,1), (2,1), (2,2), each from blocks not yet
  // written (the upper ones stay untouched until the mirror), in one pass each over contiguous
  // columns: about a third of the memory traffic of applying F's rows and then its columns.
  auto B = [&](int i, int j) { return P.block(i * nz, j * nz, nz, nz); };
  B(0, 0) += dt * (B(1, 0) + B(0, 1)) + h * (B(2, 0) + B(0, 2)) + (dt * dt) * B(1, 1) +
             (dt * h) * (B(2, 1) + B(1, 2)) + (h * h) * B(2, 2);
  B(1, 0) = beta * (B(1, 0) + dt * B(1, 1) + h * B(1, 2)) +
            (beta * dt) * (B(2, 0) + dt * B(2, 1) + h * B(2, 2));
  B(2, 0) = alpha * (B(2, 0) + dt * B(2, 1) + h * B(2, 2));
  B(1, 1) = (beta * beta) * (B(1, 1) + dt * (B(2, 1) + B(1, 2)) + (dt * dt) * B(2, 2));
  B(2, 1) = (alpha * beta) * (B(2, 1) + dt * B(2, 2));
  B(2, 2) *= alpha * alpha;
  const double d2 = dt * dt, d3 = d2 * dt, d4 = d3 * dt, d5 = d4 * dt;
  for (int i = 0; i < nz; ++i) {
    const double q = jerk_psd[i];
    const int i1 = nz + i, i2 = 2 * nz + i;
    P(i, i) += q * d5 / 20;
    P(i1, i1) += q * d3 / 3;
    P(i2, i2) += q * dt;
    P(i1, i) += q * d4 / 8;
    P(i2, i) += q * d3 / 6;
    P(i2, i1) += q * d2 / 2;
  }
  // The lower triangle is the result; the coordinates' block's upper one is its mirror, exactly
  // (the whole upper triangle: PredictConstantAcceleration).
  MirrorLower(P.topLeftCorner(nz, nz));
}

void CoordinateUpdate::Resize(int nz) {
  nz_ = nz;
  L_.resize(nz, nz);
  LB_.resize(nz, nz);
  X_.resize(nz, nz);
  tmp_.resize(nz, nz);
  V_.resize(2 * nz, nz);
  U_.resize(2 * nz, nz);
  c_.resize(nz);
  lb_.resize(nz);
  dx_.resize(3 * nz);
  reciprocal_l_.resize(nz);
  reciprocal_b_.resize(nz);
}

bool CoordinateUpdate::Apply(const Eigen::MatrixXd& A, const Eigen::VectorXd& b, double nu_r_nu,
                             Eigen::VectorXd* x, Eigen::MatrixXd* Pp, double* nis) {
  const int nz = nz_, nw = 2 * nz;
  Eigen::MatrixXd& P = *Pp;
  // P_zz = L L^T, B = I + L^T A L = L_B L_B^T (small dense Cholesky factors, own loops: Eigen's
  // blocked LLT and triangular solves cost more than the arithmetic at n_z = 38). Every
  // product with an inverse factor is a right-hand triangular solve on the rows it multiplies
  // (SolveRightLowerTransposed), never an explicit inverse.
  L_ = P.topLeftCorner(nz, nz);
  if (!CholeskyInPlace(&L_)) return false;
  tmp_.noalias() = A * L_.triangularView<Eigen::Lower>();
  LB_.noalias() = L_.transpose().triangularView<Eigen::Upper>() * tmp_;
  LB_.diagonal().array() += 1.0;
  if (!CholeskyInPlace(&LB_)) return false;
  reciprocal_l_ = L_.diagonal().cwiseInverse();
  reciprocal_b_ = LB_.diagonal().cwiseInverse();
  Eigen::MatrixXd& Vw = V_;  // V_w = P_wz L^-T
  Vw = P.bottomLeftCorner(nw, nz);
  SolveRightLowerTransposed(L_, reciprocal_l_, Vw);
  // dx = V B^-1 L^T b.
  lb_.noalias() = L_.transpose().triangularView<Eigen::Upper>() * b;
  c_ = lb_;
  LB_.triangularView<Eigen::Lower>().solveInPlace(c_);
  LB_.transpose().triangularView<Eigen::Upper>().solveInPlace(c_);  // B^-1 L^T b
  dx_.head(nz).noalias() = L_.triangularView<Eigen::Lower>() * c_;
  dx_.tail(nw).noalias() = Vw * c_;
  if (!dx_.allFinite()) return false;
  *nis = nu_r_nu - lb_.dot(c_);  // nu^T S^-1 nu by Woodbury
  // P+ = [0 0; 0 P_ww - V_w V_w^T] + U U^T with U = V L_B^-T, block by block:
  //   U_z = L L_B^-T (X), U_w = V_w L_B^-T,
  //   P_zz = X X^T, P_wz = U_w X^T, P_ww = P_ww - V_w V_w^T + U_w U_w^T.
  Eigen::MatrixXd& Uw = U_;
  Uw = Vw;
  SolveRightLowerTransposed(LB_, reciprocal_b_, Uw);
  X_ = L_;
  SolveRightLowerTransposed(LB_, reciprocal_b_, X_);
  auto Pww = P.bottomRightCorner(nw, nw);
  Pww.selfadjointView<Eigen::Lower>().rankUpdate(Vw, -1.0);
  Pww.selfadjointView<Eigen::Lower>().rankUpdate(Uw, 1.0);
  P.bottomLeftCorner(nw, nz).noalias() = Uw * X_.transpose();
  P.topLeftCorner(nz, nz).setZero();
  P.topLeftCorner(nz, nz).selfadjointView<Eigen::Lower>().rankUpdate(X_, 1.0);
  MirrorLowerToUpper(&P);
  *x += dx_;
  return true;
}

}  // namespace mocap::ekf
