// Robust losses for the global fit (FitOptions::robust_loss): one mislabelled or slipping marker
// must not drag a segment (issue 14). Least squares gives a sample 50 mm off 2,500 times the pull
// of a sample 1 mm off; a robust loss rho caps (Huber) or fades out (Cauchy) that pull.
//
// The loss acts on one marker sample, all three coordinates together: a mislabelled marker is
// wrong as a point, not per axis. With u = |x_fm - r_fm| / sigma the sample's residual in units
// of the marker sigma, s = u^2 and c the loss's scale (same unit), the sample costs rho(s):
//     none    rho(s) = s
//     Huber   rho(s) = s                    for s <= c^2,   2 c sqrt(s) - c^2   beyond
//     Cauchy  rho(s) = c^2 log(1 + s / c^2)
// (the forms of Ceres Solver's HuberLoss and CauchyLoss, so the two are comparable).
//
// How it is minimised: iteratively reweighted least squares (Holland & Welsch 1977, "Robust
// regression using iteratively reweighted least-squares", Comm. Statist. A6:813; Huber 1981,
// "Robust Statistics", ch. 7), not the Triggs correction inside Levenberg–Marquardt (Triggs,
// McLauchlan, Hartley & Fitzgibbon 2000, "Bundle adjustment — a modern synthesis", sec. 6.8, as
// Ceres does). Each round fixes the weight w_fm = rho'(s_fm) of every sample at the current
// solution and solves the weighted least-squares problem sum w_fm |r_fm|^2 / sigma^2 to
// convergence; a fixed point of the rounds is a stationary point of sum rho(s_fm), because the
// gradients of the two objectives agree there (d rho / dx = rho'(s) ds/dx). Why IRLS here:
//   - the solver stays what it is: LevenbergMarquardt, the Schur elimination and the
//     coarse-to-fine start (solver/levenberg_marquardt.h, coarse_to_fine.h) solve an ordinary
//     weighted least-squares problem, the same one the Ceres comparison hands to Ceres; the loss
//     is only the weights the problem applies to its residual blocks (MarkerFitProblem's sample
//     weights), so nothing in the solver's inner loop changes and its convergence proofs hold;
//   - the weights are per sample and at hand: the report says how many samples and of which
//     markers the loss down-weighted, which is what a lab needs to find a mislabelled marker;
//   - the Triggs correction rescales each residual block and its Jacobian by rho' and rho''
//     inside every iteration; for Cauchy beyond the scale (rho'' < 0) its Gauss–Newton model is
//     no longer positive semidefinite per block and needs Triggs's clamping. IRLS needs neither.
// Its cost: each round is a solve, warm-started at the previous one's minimum (a few iterations).
// Huber is convex in the residual, so its minimum does not depend on where the rounds start;
// Cauchy is not, and it starts from the least-squares fit: a gross error that has already
// dragged the geometry far is still seen, but a fit that is wrong everywhere is not repaired.
#pragma once

#include <string>

#include "model/status.h"

namespace mocap::solver {

enum class RobustLoss { kNone, kHuber, kCauchy };

const char* ToString(RobustLoss loss);  // "none", "huber", "cauchy"
// Parses "none", "huber" or "cauchy"; the error names the text.
Status ParseRobustLoss(const std::string& text, RobustLoss* loss);

// rho(s) above, s the squared residual in units of the scale's sigma, c > 0 the scale.
double RobustCost(RobustLoss loss, double s, double c);
// rho'(s): the IRLS weight of a sample, in (0, 1]; 1 within the scale for Huber, always for none.
double RobustWeight(RobustLoss loss, double s, double c);

}  // namespace mocap::solver
