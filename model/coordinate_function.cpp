#include "model/coordinate_function.h"

#include <algorithm>
#include <cmath>

#include <Eigen/Dense>

namespace mocap {
namespace {

using Kind = CoordinateFunction::Kind;

// Kinds defined by points (x, y).
bool HasPoints(Kind k) {
  return k == Kind::kSimmSpline || k == Kind::kNaturalCubicSpline || k == Kind::kPiecewiseLinear ||
         k == Kind::kGcvSpline;
}

// Forsythe-Malcolm-Moler coefficients (see the header). sigma_i (= s''(x_i) / 6) solve a
// symmetric tridiagonal system: interior rows are the usual C2 continuity conditions, the two end
// rows match the third derivative of the cubic through the four end knots.
void SplineCoefficients(CoordinateFunction* f) {
  const std::vector<double>& x = f->x;
  const std::vector<double>& y = f->y;
  const size_t n = x.size();
  f->b.assign(n, 0.0);
  f->c.assign(n, 0.0);
  f->d.assign(n, 0.0);
  if (n < 2) return;
  if (n == 2) {
    f->b[0] = f->b[1] = (y[1] - y[0]) / (x[1] - x[0]);
    return;
  }
  std::vector<double> h(n - 1), slope(n - 1);
  for (size_t i = 0; i + 1 < n; ++i) {
    h[i] = x[i + 1] - x[i];
    slope[i] = (y[i + 1] - y[i]) / h[i];
  }
  std::vector<double> diag(n), rhs(n, 0.0);  // off-diagonal of rows i, i+1 is h[i]
  diag[0] = -h[0];
  diag[n - 1] = -h[n - 2];
  for (size_t i = 1; i + 1 < n; ++i) {
    diag[i] = 2.0 * (h[i - 1] + h[i]);
    rhs[i] = slope[i] - slope[i - 1];
  }
  if (n > 3) {
    const double first = ((slope[2] - slope[1]) / (x[3] - x[1]) - (slope[1] - slope[0]) / (x[2] - x[0])) /
                         (x[3] - x[0]);
    const double last = ((slope[n - 2] - slope[n - 3]) / (x[n - 1] - x[n - 3]) -
                         (slope[n - 3] - slope[n - 4]) / (x[n - 2] - x[n - 4])) /
                        (x[n - 1] - x[n - 4]);
    rhs[0] = h[0] * h[0] * first;
    rhs[n - 1] = -h[n - 2] * h[n - 2] * last;
  }
  for (size_t i = 1; i < n; ++i) {  // elimination without pivoting, as the reference does
    const double t = h[i - 1] / diag[i - 1];
    diag[i] -= t * h[i - 1];
    rhs[i] -= t * rhs[i - 1];
  }
  std::vector<double> sigma(n);
  sigma[n - 1] = rhs[n - 1] / diag[n - 1];
  for (size_t i = n - 1; i-- > 0;) sigma[i] = (rhs[i] - h[i] * sigma[i + 1]) / diag[i];
  for (size_t i = 0; i + 1 < n; ++i) {
    f->b[i] = slope[i] - h[i] * (sigma[i + 1] + 2.0 * sigma[i]);
    f->c[i] = 3.0 * sigma[i];
    f->d[i] = (sigma[i + 1] - sigma[i]) / h[i];
  }
  f->b[n - 1] = slope[n - 2] + h[n - 2] * (sigma[n - 2] + 2.0 * sigma[n - 1]);
  f->c[n - 1] = 3.0 * sigma[n - 1];
  f->d[n - 1] = f->d[n - 2];
}

void SplineEvaluate(const CoordinateFunction& f, double z, double* v, double* dv) {
  const std::vector<double>& x = f.x;
  const size_t n = x.size();
  if (z < x.front()) {
    *v = f.y.front() + (z - x.front()) * f.b.front();
    *dv = f.b.front();
    return;
  }
  if (z > x.back()) {
    *v = f.y.back() + (z - x.back()) * f.b.back();
    *dv = f.b.back();
    return;
  }
  // The interval [x_k, x_k+1] holding z.
  size_t k = static_cast<size_t>(std::upper_bound(x.begin(), x.end(), z) - x.begin());
  k = k == 0 ? 0 : std::min(k - 1, n - 2);
  const double dx = z - x[k];
  *v = f.y[k] + dx * (f.b[k] + dx * (f.c[k] + dx * f.d[k]));
  *dv = f.b[k] + dx * (2.0 * f.c[k] + 3.0 * dx * f.d[k]);
}


// Straight lines between the points, the end slopes beyond them (OpenSim's
// PiecewiseLinearFunction); evaluated by SplineEvaluate with c = d = 0.
void PiecewiseLinearCoefficients(CoordinateFunction* f) {
  const size_t n = f->x.size();
  f->b.assign(n, 0.0);
  f->c.assign(n, 0.0);
  f->d.assign(n, 0.0);
  if (n < 2) return;
  for (size_t i = 0; i + 1 < n; ++i) f->b[i] = (f->y[i + 1] - f->y[i]) / (f->x[i + 1] - f->x[i]);
  f->b[n - 1] = f->b[n - 2];
}

// The dense solve is cubic in the points and each evaluation linear: a joint's GCV spline has a
// few dozen at most, and a file with thousands is refused rather than left to stall the reader.
constexpr int kMaxGcvPoints = 200;

// |t|^p and its derivative; p is odd and >= 1.
void OddPower(double t, int p, double* v, double* dv) {
  const double a = std::abs(t);
  double a1 = 1.0;  // |t|^(p-1)
  for (int k = 1; k < p; ++k) a1 *= a;
  *v = a1 * a;
  *dv = t == 0.0 ? 0.0 : (t > 0.0 ? p * a1 : -p * a1);
}

// The interpolating natural spline in truncated-power form (see the header). Leaves b empty when
// the points do not define it (too few, not increasing, not finite), for Check to name.
void GcvCoefficients(CoordinateFunction* f) {
  f->b.clear();
  f->c.clear();
  f->d.clear();
  const std::vector<double>& x = f->x;
  const int n = static_cast<int>(x.size()), m = f->half_order;
  if (m < 1 || m > 4 || n < 2 * m || n > kMaxGcvPoints || f->y.size() != x.size()) return;
  for (int i = 0; i < n; ++i)
    if (!std::isfinite(x[i]) || !std::isfinite(f->y[i]) || (i > 0 && !(x[i] > x[i - 1]))) return;
  const double centre = 0.5 * (x.front() + x.back()), half = 0.5 * (x.back() - x.front());
  const int p = 2 * m - 1;
  std::vector<double> u(n);
  for (int i = 0; i < n; ++i) u[i] = (x[i] - centre) / half;
  Eigen::MatrixXd a = Eigen::MatrixXd::Zero(n + m, n + m);
  Eigen::VectorXd rhs = Eigen::VectorXd::Zero(n + m);
  for (int i = 0; i < n; ++i) {
    for (int j = 0; j < n; ++j) {
      double v, dv;
      OddPower(u[i] - u[j], p, &v, &dv);
      a(i, j) = v;
    }
    double power = 1.0;
    for (int k = 0; k < m; ++k, power *= u[i]) a(i, n + k) = a(n + k, i) = power;
    rhs[i] = f->y[i];
  }
  const Eigen::VectorXd sol = a.fullPivLu().solve(rhs);
  if (!sol.allFinite()) return;
  f->b.assign(sol.data(), sol.data() + n);
  f->c.assign(sol.data() + n, sol.data() + n + m);
  f->d = {centre, half};
  f->d.insert(f->d.end(), u.begin(), u.end());
}

void GcvEvaluate(const CoordinateFunction& f, double z, double* v, double* dv) {
  const double u = (z - f.d[0]) / f.d[1];
  const int p = 2 * f.half_order - 1;
  double s = 0.0, ds = 0.0;
  for (size_t k = f.c.size(); k-- > 0;) {  // Horner, highest power first
    ds = ds * u + s;
    s = s * u + f.c[k];
  }
  for (size_t i = 0; i < f.x.size(); ++i) {
    double t, dt;
    OddPower(u - f.d[2 + i], p, &t, &dt);
    s += f.b[i] * t;
    ds += f.b[i] * dt;
  }
  *v = s;
  *dv = ds / f.d[1];
}

// A function defined by points, before its coefficients.
CoordinateFunction WithPoints(Kind kind, std::vector<double> x, std::vector<double> y) {
  CoordinateFunction f;
  f.kind = kind;
  f.x = std::move(x);
  f.y = std::move(y);
  return f;
}

}  // namespace

CoordinateFunction CoordinateFunction::Linear(double slope, double offset) {
  CoordinateFunction f;
  f.kind = Kind::kLinear;
  f.slope = slope;
  f.offset = offset;
  return f;
}

CoordinateFunction CoordinateFunction::Constant(double value) {
  CoordinateFunction f;
  f.kind = Kind::kConstant;
  f.offset = value;
  return f;
}

CoordinateFunction CoordinateFunction::SimmSpline(std::vector<double> x, std::vector<double> y) {
  CoordinateFunction f = WithPoints(Kind::kSimmSpline, std::move(x), std::move(y));
  if (f.x.size() == f.y.size()) SplineCoefficients(&f);
  return f;
}

CoordinateFunction CoordinateFunction::NaturalCubicSpline(std::vector<double> x,
                                                          std::vector<double> y) {
  CoordinateFunction f = SimmSpline(std::move(x), std::move(y));
  f.kind = Kind::kNaturalCubicSpline;
  return f;
}

CoordinateFunction CoordinateFunction::PiecewiseLinear(std::vector<double> x, std::vector<double> y) {
  CoordinateFunction f = WithPoints(Kind::kPiecewiseLinear, std::move(x), std::move(y));
  if (f.x.size() == f.y.size()) PiecewiseLinearCoefficients(&f);
  return f;
}

CoordinateFunction CoordinateFunction::GcvSpline(int half_order, std::vector<double> x,
                                                 std::vector<double> y) {
  CoordinateFunction f = WithPoints(Kind::kGcvSpline, std::move(x), std::move(y));
  f.half_order = half_order;
  GcvCoefficients(&f);
  return f;
}

CoordinateFunction CoordinateFunction::Polynomial(std::vector<double> coefficients) {
  CoordinateFunction f;
  f.kind = Kind::kPolynomial;
  f.coefficients = std::move(coefficients);
  return f;
}

CoordinateFunction CoordinateFunction::Multiplier(double scale, CoordinateFunction inner) {
  CoordinateFunction f;
  f.kind = Kind::kMultiplier;
  f.slope = scale;
  f.inner.push_back(std::move(inner));
  return f;
}

CoordinateFunction CoordinateFunction::Compose(CoordinateFunction outer, CoordinateFunction inner) {
  CoordinateFunction f;
  f.kind = Kind::kComposed;
  f.inner.push_back(std::move(outer));
  f.inner.push_back(std::move(inner));
  return f;
}

void CoordinateFunction::Evaluate(double z, double* v, double* dv) const {
  switch (kind) {
    case Kind::kIdentity:
      *v = z;
      *dv = 1.0;
      return;
    case Kind::kLinear:
      *v = slope * z + offset;
      *dv = slope;
      return;
    case Kind::kConstant:
      *v = offset;
      *dv = 0.0;
      return;
    case Kind::kSimmSpline:
    case Kind::kNaturalCubicSpline:
    case Kind::kPiecewiseLinear:
      SplineEvaluate(*this, z, v, dv);
      return;
    case Kind::kGcvSpline:
      GcvEvaluate(*this, z, v, dv);
      return;
    case Kind::kPolynomial: {
      double p = 0.0, dp = 0.0;  // Horner for the value and its derivative together
      for (double a : coefficients) {
        dp = dp * z + p;
        p = p * z + a;
      }
      *v = p;
      *dv = dp;
      return;
    }
    case Kind::kMultiplier:
      inner[0].Evaluate(z, v, dv);
      *v *= slope;
      *dv *= slope;
      return;
    case Kind::kComposed: {
      double u, du, w, dw;
      inner[1].Evaluate(z, &u, &du);
      inner[0].Evaluate(u, &w, &dw);
      *v = w;
      *dv = dw * du;
      return;
    }
  }
  *v = z;
  *dv = 1.0;
}

double CoordinateFunction::Value(double z) const {
  double v, dv;
  Evaluate(z, &v, &dv);
  return v;
}

double CoordinateFunction::Derivative(double z) const {
  double v, dv;
  Evaluate(z, &v, &dv);
  return dv;
}

bool CoordinateFunction::IsConstant() const {
  switch (kind) {
    case Kind::kConstant: return true;
    case Kind::kLinear: return slope == 0.0;
    case Kind::kMultiplier: return slope == 0.0 || (!inner.empty() && inner[0].IsConstant());
    case Kind::kComposed:
      return inner.size() == 2 && (inner[0].IsConstant() || inner[1].IsConstant());
    case Kind::kPolynomial: return coefficients.size() <= 1;
    default: return false;
  }
}

bool CoordinateFunction::IsIdentity() const {
  return kind == Kind::kIdentity || (kind == Kind::kLinear && slope == 1.0 && offset == 0.0);
}

Status CoordinateFunction::Check(const std::string& where) const {
  auto fail = [&](const std::string& what) { return Status::Error(where + ": " + what); };
  if (!std::isfinite(slope) || !std::isfinite(offset)) return fail("not finite");
  if (HasPoints(kind)) {
    if (x.size() != y.size())
      return fail("spline has " + std::to_string(x.size()) + " x but " + std::to_string(y.size()) +
                  " y values");
    if (x.size() < 2) return fail("spline needs at least 2 points");
    for (size_t i = 0; i < x.size(); ++i) {
      if (!std::isfinite(x[i]) || !std::isfinite(y[i])) return fail("spline point not finite");
      if (i > 0 && !(x[i] > x[i - 1]))
        return fail("spline x values must increase strictly (x[" + std::to_string(i) + "])");
    }
    if (kind == Kind::kGcvSpline) {
      if (half_order < 1 || half_order > 4)
        return fail("GCV spline half order " + std::to_string(half_order) + " is not 1 to 4 (degree 1 to 7)");
      if (x.size() < 2 * static_cast<size_t>(half_order))
        return fail("GCV spline of half order " + std::to_string(half_order) + " needs at least " +
                    std::to_string(2 * half_order) + " points, has " + std::to_string(x.size()));
      if (x.size() > static_cast<size_t>(kMaxGcvPoints))
        return fail("GCV spline with " + std::to_string(x.size()) + " points (at most " +
                    std::to_string(kMaxGcvPoints) + " are supported)");
      if (b.size() != x.size() || c.size() != static_cast<size_t>(half_order) || d.size() != x.size() + 2)
        return fail("GCV spline coefficients missing (use the factory)");
    } else if (b.size() != x.size()) {
      return fail("spline coefficients missing (use the factory)");
    }
  }
  if (kind == Kind::kPolynomial) {
    if (coefficients.empty()) return fail("polynomial has no coefficients");
    for (double a : coefficients)
      if (!std::isfinite(a)) return fail("polynomial coefficient not finite");
  }
  if (kind == Kind::kMultiplier) {
    if (inner.size() != 1) return fail("multiplier needs exactly one inner function");
    return inner[0].Check(where + ".function");
  }
  if (kind == Kind::kComposed) {
    if (inner.size() != 2) return fail("composition needs an outer and an inner function");
    if (Status s = inner[0].Check(where + ".outer"); !s) return s;
    return inner[1].Check(where + ".inner");
  }
  return Status::Ok();
}

const char* CoordinateFunction::KindName(Kind k) {
  switch (k) {
    case Kind::kIdentity: return "identity";
    case Kind::kLinear: return "linear";
    case Kind::kConstant: return "constant";
    case Kind::kSimmSpline: return "simm_spline";
    case Kind::kNaturalCubicSpline: return "natural_cubic_spline";
    case Kind::kPolynomial: return "polynomial";
    case Kind::kMultiplier: return "multiplier";
    case Kind::kComposed: return "composed";
    case Kind::kPiecewiseLinear: return "piecewise_linear";
    case Kind::kGcvSpline: return "gcv_spline";
  }
  return "?";
}

bool CoordinateFunction::KindFromName(const std::string& name, Kind* k) {
  for (Kind c : {Kind::kIdentity, Kind::kLinear, Kind::kConstant, Kind::kSimmSpline,
                 Kind::kNaturalCubicSpline, Kind::kPolynomial, Kind::kMultiplier, Kind::kComposed,
                 Kind::kPiecewiseLinear, Kind::kGcvSpline})
    if (name == KindName(c)) {
      *k = c;
      return true;
    }
  return false;
}

bool CoordinateFunction::operator==(const CoordinateFunction& o) const {
  // b, c, d follow from x and y.
  return kind == o.kind && slope == o.slope && offset == o.offset && half_order == o.half_order && x == o.x && y == o.y &&
         coefficients == o.coefficients && inner == o.inner;
}

}  // namespace mocap
