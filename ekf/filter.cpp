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

// inverse = L^-1 for a lower-triangular L (forward substitution, column by column). The
// diagonal's reciprocals are taken once (`reciprocal`, n entries): n divisions, not n^2 / 2.
void LowerInverse(const Eigen::MatrixXd& L, Eigen::VectorXd* reciprocal, Eigen::MatrixXd* inverse) {
  Eigen::MatrixXd& x = *inverse;
  const int n = static_cast<int>(L.rows());
  *reciprocal = L.diagonal().cwiseInverse();
  const double* r = reciprocal->data();
  x.setZero();
  for (int j = 0; j < n; ++j) {
    double* xj = &x(0, j);
    xj[j] = 1.0;
    for (int i = j; i < n; ++i) {
      const double xi = xj[i] * r[i];
      xj[i] = xi;
      const double* li = &L(0, i);
      for (int k = i + 1; k < n; ++k) xj[k] -= li[k] * xi;
    }
  }
}
}  // namespace

void PredictConstantAcceleration(double dt, const Eigen::VectorXd& jerk_psd, Eigen::VectorXd* x,
                                 Eigen::MatrixXd* Pp) {
  PredictConstantAcceleration(dt, jerk_psd, 1.0, 1.0, x, Pp);
}

void PredictConstantAcceleration(double dt, const Eigen::VectorXd& jerk_psd, double velocity_decay,
                                 double acceleration_decay, Eigen::VectorXd* x,
                                 Eigen::MatrixXd* Pp) {
  const int nz = static_cast<int>(jerk_psd.size());
  Eigen::MatrixXd& P = *Pp;
  const double h = 0.5 * dt * dt;
  auto z = x->head(nz);
  auto v = x->segment(nz, nz);
  auto a = x->tail(nz);
  z += dt * v + h * a;
  v += dt * a;
  v *= velocity_decay;
  a *= acceleration_decay;
  // F P F^T on the 3 x 3 grid of n_z blocks: block rows first, then block columns, in place
  // (each update reads only blocks not yet written).
  P.topRows(nz) += dt * P.middleRows(nz, nz) + h * P.bottomRows(nz);
  P.middleRows(nz, nz) += dt * P.bottomRows(nz);
  P.leftCols(nz) += dt * P.middleCols(nz, nz) + h * P.rightCols(nz);
  P.middleCols(nz, nz) += dt * P.rightCols(nz);
  if (velocity_decay != 1.0) {
    P.middleRows(nz, nz) *= velocity_decay;
    P.middleCols(nz, nz) *= velocity_decay;
  }
  if (acceleration_decay != 1.0) {
    P.bottomRows(nz) *= acceleration_decay;
    P.rightCols(nz) *= acceleration_decay;
  }
  const double d2 = dt * dt, d3 = d2 * dt, d4 = d3 * dt, d5 = d4 * dt;
  for (int i = 0; i < nz; ++i) {
    const double q = jerk_psd[i];
    const int i1 = nz + i, i2 = 2 * nz + i;
    P(i, i) += q * d5 / 20;
    P(i1, i1) += q * d3 / 3;
    P(i2, i2) += q * dt;
    P(i, i1) += q * d4 / 8;
    P(i1, i) += q * d4 / 8;
    P(i, i2) += q * d3 / 6;
    P(i2, i) += q * d3 / 6;
    P(i1, i2) += q * d2 / 2;
    P(i2, i1) += q * d2 / 2;
  }
  // Row-then-column rounding differs between (i,j) and (j,i): keep P exactly symmetric.
  P.triangularView<Eigen::StrictlyUpper>() = P.transpose();
}

void CoordinateUpdate::Resize(int nz) {
  nz_ = nz;
  L_.resize(nz, nz);
  B_.resize(nz, nz);
  tmp_.resize(nz, nz);
  Linv_.resize(nz, nz);
  LBinv_.resize(nz, nz);
  V_.resize(3 * nz, nz);
  U_.resize(3 * nz, nz);
  c_.resize(nz);
  lb_.resize(nz);
  dx_.resize(3 * nz);
  LB_.resize(nz, nz);
  lbb_.resize(nz);
  reciprocal_.resize(nz);
}

bool CoordinateUpdate::Apply(const Eigen::MatrixXd& A, const Eigen::VectorXd& b, double nu_r_nu,
                             Eigen::VectorXd* x, Eigen::MatrixXd* Pp, double* nis) {
  const int nz = nz_, nw = 2 * nz;
  Eigen::MatrixXd& P = *Pp;
  // P_zz = L L^T, B = I + L^T A L = L_B L_B^T (small dense Cholesky factors, own loops: Eigen's
  // blocked LLT and triangular solves cost more than the arithmetic at n_z = 38). The
  // triangular inverses are formed explicitly (n_z^3 / 6 each) so that the products with the
  // 2 n_z rows of velocities and accelerations run as plain matrix products.
  L_ = P.topLeftCorner(nz, nz);
  if (!CholeskyInPlace(&L_)) return false;
  tmp_.noalias() = A * L_.triangularView<Eigen::Lower>();
  B_.noalias() = L_.transpose().triangularView<Eigen::Upper>() * tmp_;
  B_.diagonal().array() += 1.0;
  LB_ = B_;
  if (!CholeskyInPlace(&LB_)) return false;
  LowerInverse(L_, &reciprocal_, &Linv_);
  LowerInverse(LB_, &reciprocal_, &LBinv_);
  auto Vw = V_.topRows(nw);
  Vw.noalias() = P.bottomLeftCorner(nw, nz) * Linv_.transpose().triangularView<Eigen::Upper>();
  // dx = V B^-1 L^T b.
  lb_.noalias() = L_.transpose().triangularView<Eigen::Upper>() * b;
  lbb_.noalias() = LBinv_.triangularView<Eigen::Lower>() * lb_;
  c_.noalias() = LBinv_.transpose().triangularView<Eigen::Upper>() * lbb_;  // B^-1 L^T b
  dx_.head(nz).noalias() = L_.triangularView<Eigen::Lower>() * c_;
  dx_.tail(nw).noalias() = Vw * c_;
  if (!dx_.allFinite()) return false;
  *nis = nu_r_nu - lb_.dot(c_);  // nu^T S^-1 nu by Woodbury
  // P+ = [0 0; 0 P_ww - V_w V_w^T] + U U^T with U = V L_B^-T, block by block:
  //   U_z = L L_B^-T (X), U_w = V_w L_B^-T,
  //   P_zz = X X^T, P_wz = U_w X^T, P_ww = P_ww - V_w V_w^T + U_w U_w^T.
  Eigen::MatrixXd& X = tmp_;  // reused
  X.noalias() = L_.triangularView<Eigen::Lower>() * LBinv_.transpose();
  auto Uw = U_.topRows(nw);
  Uw.noalias() = Vw * LBinv_.transpose().triangularView<Eigen::Upper>();
  auto Pww = P.bottomRightCorner(nw, nw);
  Pww.selfadjointView<Eigen::Lower>().rankUpdate(Vw, -1.0);
  Pww.selfadjointView<Eigen::Lower>().rankUpdate(Uw, 1.0);
  P.bottomLeftCorner(nw, nz).noalias() = Uw * X.transpose();
  P.topLeftCorner(nz, nz).setZero();
  P.topLeftCorner(nz, nz).selfadjointView<Eigen::Lower>().rankUpdate(X, 1.0);
  P.triangularView<Eigen::StrictlyUpper>() = P.transpose();
  *x += dx_;
  return true;
}

}  // namespace mocap::ekf
