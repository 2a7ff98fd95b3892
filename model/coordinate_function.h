// v = f(z): how a coordinate drives a joint element, with its exact first derivative f'(z).
//
// The kinds are those an OpenSim CustomJoint's TransformAxis uses (OpenSim API docs,
// "Function" and its subclasses), plus composition for coupled coordinates:
//   identity            v = z
//   linear              v = slope z + offset                 (OpenSim LinearFunction "slope intercept")
//   constant            v = offset, no coordinate needed     (OpenSim Constant)
//   simm_spline         SIMM's interpolating cubic spline    (OpenSim SimmSpline)
//   natural_cubic_spline                                     (OpenSim NaturalCubicSpline)
//   piecewise_linear    straight lines between the points    (OpenSim PiecewiseLinearFunction)
//   gcv_spline          the interpolating natural spline of degree 2m - 1 (OpenSim GCVSpline,
//                       half order m, error variance 0: OpenSim's default and what SIMM's
//                       converter writes)
//   polynomial          sum c_i z^(n-i), highest power first (OpenSim PolynomialFunction, as
//                       SimTK::Function::Polynomial)
//   multiplier          v = slope * inner(z)                 (OpenSim MultiplierFunction; what
//                       OpenSim's Scale tool wraps a scaled translation function in)
//   composed            v = outer(inner(z))                  (a CoordinateCouplerConstraint: the
//                       element's own function of the dependent coordinate, which is itself a
//                       function of the independent one)
//
// Splines. OpenSim evaluates SimmSpline and, despite its name, NaturalCubicSpline with the same
// algorithm (SimmSpline.cpp, NaturalCubicSpline.cpp): the interpolating cubic spline of Forsythe,
// Malcolm and Moler, "Computer Methods for Mathematical Computations" (1977), routine SPLINE,
// whose end conditions make the third derivative at each end equal to that of the cubic through
// the four nearest knots (with 3 knots: a parabola; with 2: the straight line). Outside
// [x_0, x_{n-1}] both extrapolate linearly with the end slope. We compute the same piecewise
// cubic y_k + b_k dx + c_k dx^2 + d_k dx^3 (our own code), so a model imported from OpenSim has
// OpenSim's kinematics. PiecewiseLinearFunction is the same with c = d = 0 (OpenSim's
// PiecewiseLinearFunction.cpp also extrapolates with the end slopes).
//
// GCVSpline. OpenSim evaluates it through SimTK::SplineFitter::fitFromErrorVariance(degree, x, y,
// error_variance), Woltring's GCVSPL (Adv. Eng. Software 8(2), 1986). With the error variance 0
// GCVSPL's smoothing parameter is 0 and the spline interpolates the points: the natural spline of
// degree 2m - 1 through them, the unique interpolant that minimises the integral of its m-th
// derivative squared. We compute that spline in its truncated-power form
//   s(u) = sum_{k<m} a_k u^k + sum_i w_i |u - u_i|^(2m-1),  sum_i w_i u_i^k = 0 for k < m
// (Wahba, "Spline Models for Observational Data", 1990, ch. 1), on u = (z - centre) / half-width
// for conditioning: (n + m) linear equations solved once by the factory. The moment conditions
// make s a polynomial of degree m - 1 outside the knots -- the natural extension. (SimTK asserts
// that z lies within the knots and does not define the outside; a model's coordinate ranges
// normally keep it there.) A non-zero error variance (a smoothing fit) is refused by the reader.
//
// The coefficients are computed once by the factories and kept here, in the immutable Model:
// Value and Derivative only read (no allocation).
#pragma once

#include <string>
#include <vector>

#include "model/status.h"

namespace mocap {

struct CoordinateFunction {
  enum class Kind {
    kIdentity,
    kLinear,
    kConstant,
    kSimmSpline,
    kNaturalCubicSpline,
    kPolynomial,
    kMultiplier,
    kComposed,
    kPiecewiseLinear,
    kGcvSpline
  };
  Kind kind = Kind::kIdentity;
  double slope = 1.0;   // kLinear: slope; kMultiplier: the scale
  double offset = 0.0;  // kLinear: intercept; kConstant: the value
  std::vector<double> x, y;                // splines: knots (strictly increasing) and values
  std::vector<double> coefficients;        // kPolynomial: highest power first
  std::vector<CoordinateFunction> inner;   // kMultiplier: {f}; kComposed: {outer, inner}
  int half_order = 0;                      // kGcvSpline: m (degree 2m - 1)
  // Derived from x, y by the factories. Cubic splines and kPiecewiseLinear: the piecewise
  // polynomial's coefficients per knot. kGcvSpline: b the weights w_i, c the polynomial's a_k
  // (lowest power first), d {centre, half-width} of the scaled abscissa u, then the knots' u_i.
  std::vector<double> b, c, d;

  static CoordinateFunction Identity() { return {}; }
  static CoordinateFunction Linear(double slope, double offset);
  static CoordinateFunction Constant(double value);
  static CoordinateFunction SimmSpline(std::vector<double> x, std::vector<double> y);
  static CoordinateFunction NaturalCubicSpline(std::vector<double> x, std::vector<double> y);
  static CoordinateFunction Polynomial(std::vector<double> coefficients);
  static CoordinateFunction PiecewiseLinear(std::vector<double> x, std::vector<double> y);
  // Needs at least 2m points (as OpenSim); m in 1..4 (OpenSim clamps the degree to 1..7).
  static CoordinateFunction GcvSpline(int half_order, std::vector<double> x, std::vector<double> y);
  static CoordinateFunction Multiplier(double scale, CoordinateFunction f);
  static CoordinateFunction Compose(CoordinateFunction outer, CoordinateFunction inner);

  double Value(double z) const;
  double Derivative(double z) const;
  // Both at once (what the kinematics needs).
  void Evaluate(double z, double* value, double* derivative) const;

  // v does not depend on z (a Constant, possibly scaled or composed).
  bool IsConstant() const;
  // v = z exactly: OpenSim treats such a translation as a degree of freedom and does not scale
  // it with the parent body (SpatialTransform::scale).
  bool IsIdentity() const;
  // Sizes, knot order, finiteness. `where` prefixes the message.
  Status Check(const std::string& where) const;

  // Kind names as in the JSON model file ("identity", "simm_spline", ...).
  static const char* KindName(Kind kind);
  static bool KindFromName(const std::string& name, Kind* kind);

  bool operator==(const CoordinateFunction& o) const;
  bool operator!=(const CoordinateFunction& o) const { return !(*this == o); }
};

}  // namespace mocap
