// v = f(z): how a coordinate drives a joint element, with its exact first derivative f'(z).
//
// The kinds are those an OpenSim CustomJoint's TransformAxis uses (OpenSim API docs,
// "Function" and its subclasses), plus composition for coupled coordinates:
//   identity            v = z
//   linear              v = slope z + offset                 (OpenSim LinearFunction "slope intercept")
//   constant            v = offset, no coordinate needed     (OpenSim Constant)
//   simm_spline         SIMM's interpolating cubic spline    (OpenSim SimmSpline)
//   natural_cubic_spline                                     (OpenSim NaturalCubicSpline)
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
// OpenSim's kinematics.
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
    kComposed
  };
  Kind kind = Kind::kIdentity;
  double slope = 1.0;   // kLinear: slope; kMultiplier: the scale
  double offset = 0.0;  // kLinear: intercept; kConstant: the value
  std::vector<double> x, y;                // splines: knots (strictly increasing) and values
  std::vector<double> coefficients;        // kPolynomial: highest power first
  std::vector<CoordinateFunction> inner;   // kMultiplier: {f}; kComposed: {outer, inner}
  std::vector<double> b, c, d;             // splines: derived from x, y by the factories

  static CoordinateFunction Identity() { return {}; }
  static CoordinateFunction Linear(double slope, double offset);
  static CoordinateFunction Constant(double value);
  static CoordinateFunction SimmSpline(std::vector<double> x, std::vector<double> y);
  static CoordinateFunction NaturalCubicSpline(std::vector<double> x, std::vector<double> y);
  static CoordinateFunction Polynomial(std::vector<double> coefficients);
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
