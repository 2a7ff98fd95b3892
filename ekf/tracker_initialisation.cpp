// The tracker's (re)initialisation: finding the subject in a cloud of unlabelled points with no
// labels to go on (TryInitialise and Search: headings about the vertical, ICP-like placement from
// the root outwards, restarts, exchanges of neighbouring labels, an ambiguity test; the model
// scaled to the subject when its own size cannot start, ScaleToSubject), and finding one limb
// again while the rest of the body tracks (Reacquire, ReacquireLimb). ekf/tracker.h
// ("Initialisation and recovery", "Limb re-acquisition") has the design. What it decides: whether
// a placement is good and unambiguous enough to start (or restart a limb of) the track, with which
// labels and at which size; a search that cannot tell two labellings apart refuses rather than
// guesses.
#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <random>

#include "ekf/tracker_impl.h"

namespace mocap::ekf {

using namespace internal;

namespace {
// One damped Gauss-Newton (Levenberg-Marquardt) step on the normal equations N step = -g of a
// search (the subject's, ICP-like, or one limb's): the damping grows tenfold until the step,
// made into a trial pose and costed by trial_cost() (which reads *step), lowers the cost, and
// shrinks after a success. Returns whether a step was accepted (the trial pose is then the
// caller's new pose). Allocation-free for fixed-capacity N (the limb search's).
template <class Matrix, class Vector, class Solver, class TrialCost>
bool DampedGaussNewtonStep(const Matrix& N, const Vector& g, double current_cost, double* lambda,
                           Matrix* damped, Solver* solver, Vector* step, TrialCost&& trial_cost) {
  for (int tries = 0; tries < 6; ++tries) {
    *damped = N;
    damped->diagonal() += *lambda * N.diagonal();
    solver->compute(*damped);
    if (solver->info() != Eigen::Success) {
      *lambda *= 10;
      continue;
    }
    *step = -solver->solve(g);
    if (trial_cost() < current_cost) {
      *lambda = std::max(1e-7, *lambda * 0.3);
      return true;
    }
    *lambda *= 10;
  }
  return false;
}
}  // namespace

// ---------------------------------------------------------------------------------------------
// Initialisation

// z = start with the root turned by `turn` (world, about the root's origin) and shifted so that
// the model's marker centroid lands on `centroid`.
bool Tracker::Impl::PlaceRoot(const Eigen::VectorXd& start, const Eigen::Matrix3d& turn,
                              const Eigen::Vector3d& centroid, Eigen::VectorXd* z) {
  *z = start;
  const Joint& root = model->joints()[0];
  if (!turn.isIdentity(1e-12)) {
    if (!root_euler) return false;
    ForwardKinematics(*model, geometry, *z, &data);
    const Eigen::Matrix3d target = turn * data.segment_rotation[root.child];
    // The root's rotation elements compose root.orientation * R(a0) R(a1) R(a2); earlier
    // translations do not rotate.
    const Eigen::Vector3d angles = (root.orientation.transpose() * target)
                                       .eulerAngles(root_rot_axis[0], root_rot_axis[1],
                                                    root_rot_axis[2]);
    // Two angle triples give the same rotation, (a0, a1, a2) and (a0 + pi, pi - a1, a2 + pi)
    // ((a0 + pi, -a1, a2 + pi) for a proper Euler sequence); Eigen returns a0 in [0, pi]. Take
    // the one nearer the start, or a subject facing the other half of the room would be tracked
    // upside down in its root angles (same markers, tilt and list near pi).
    const bool proper = root_rot_axis[0] == root_rot_axis[2];
    Eigen::Vector3d other(angles[0] + M_PI, proper ? -angles[1] : M_PI - angles[1],
                          angles[2] + M_PI);
    double da = 0, db = 0;
    for (int i = 0; i < 3; ++i) {
      const double s0 = start[root_rot_coord[i]] * root_rot_sign[i];
      da += std::pow(std::remainder(angles[i] - s0, 2 * M_PI), 2);
      db += std::pow(std::remainder(other[i] - s0, 2 * M_PI), 2);
    }
    const Eigen::Vector3d& chosen = db < da ? other : angles;
    for (int i = 0; i < 3; ++i)
      (*z)[root_rot_coord[i]] =
          root_rot_sign[i] * std::remainder(chosen[i], 2 * M_PI);
  }
  ForwardKinematics(*model, geometry, *z, &data);
  Eigen::Vector3d mc = Eigen::Vector3d::Zero();
  for (int m = 0; m < nm; ++m)
    if (seen[m]) mc += MarkerPosition(*model, geometry, data, m);
  const Eigen::Vector3d shift = centroid - mc / std::max(1, nm_seen);
  for (const auto& [coord, axis] : root_translations) (*z)[coord] += axis.dot(shift);
  return true;
}

double Tracker::Impl::AssignWithin(int np, double radius, int depth, std::vector<int>* assign) {
  auto C = cost.topLeftCorner(nm, np + nm);
  const double r2 = radius * radius;
  for (int m = 0; m < nm; ++m) {
    const bool active = seen[m] && marker_depth[m] <= depth;
    for (int k = 0; k < np; ++k) {
      const double d2 = (points.col(k) - predicted.col(m)).squaredNorm();
      C(m, k) = active && d2 < r2 ? d2 : kForbidden;
    }
    C.row(m).tail(nm).setConstant(kForbidden);
    C(m, np + m) = r2;
  }
  const double total = lap.Solve(C, row_to_col.data());
  for (int m = 0; m < nm; ++m) (*assign)[m] = row_to_col[m] < np ? row_to_col[m] : -1;
  return total;
}

void Tracker::Impl::LabelNormalEquations(const std::vector<int>& assign, const Eigen::VectorXd& z,
                                         const Eigen::VectorXd& centre, double prior_weight,
                                         Eigen::MatrixXd* Np, Eigen::VectorXd* gp) const {
  Eigen::MatrixXd& N = *Np;
  Eigen::VectorXd& g = *gp;
  N.setZero();
  g.setZero();
  for (int m = 0; m < nm; ++m) {
    if (assign[m] < 0) continue;
    const Eigen::Vector3d r = predicted.col(m) - points.col(assign[m]);
    const std::vector<int>& cols = model->marker_coordinates(m);
    const auto& J = jac[m];
    for (size_t a = 0; a < cols.size(); ++a) {
      g[cols[a]] += J.col(a).dot(r);
      for (size_t k = 0; k < cols.size(); ++k) N(cols[a], cols[k]) += J.col(a).dot(J.col(k));
    }
  }
  for (int i = 0; i < nz; ++i) {
    const double w = prior_weight * SearchPrior(i);
    N(i, i) += w;
    g[i] += w * (z[i] - centre[i]);
  }
}

double Tracker::Impl::LabelCost(const std::vector<int>& assign, const Eigen::VectorXd& z,
                                const Eigen::VectorXd& centre, double prior_weight,
                                const std::vector<char>* free) {
  ForwardKinematics(*model, geometry, z, &data);
  double s = 0;
  for (int m = 0; m < nm; ++m)
    if (assign[m] >= 0) s += (MarkerPosition(*model, geometry, data, m) - points.col(assign[m])).squaredNorm();
  for (int i = 0; i < nz; ++i)
    if (!free || (*free)[i]) s += prior_weight * SearchPrior(i) * (z[i] - centre[i]) * (z[i] - centre[i]);
  return s;
}

// ICP-like search from z: assign markers to points by distance (optimal assignment), one damped
// Gauss-Newton step on the pose, reassign. The body is placed from the root outwards: stage d
// frees the joints at depth <= d of the tree and assigns only the markers they carry, so a
// distal marker is paired only once its parent segments are in place (the two wrist markers,
// 7 cm apart, would otherwise cross while the arm is still beside the body, and the forearm turn
// half a revolution into a mirrored local minimum). A final stage refines everything with a
// radius shrinking to 4 cm.
//
// With `held` (an exchange: see ExchangeLabels), the search starts at the final stage and holds
// that assignment for its first kHeldIterations steps before it reassigns freely: the pose moves
// to where the held labels put it (a forearm turned half a revolution), which a search that
// reassigns by distance from the start never reaches.
Tracker::Impl::Hypothesis Tracker::Impl::Icp(Eigen::VectorXd z, int np, const std::vector<int>* held) {
  Eigen::VectorXd start = z;
  const int stages = max_depth + 1, per_stage = 3;
  // An exchange holds its labels first, then runs the final stage in full.
  const int hold = held ? kHeldIterations : 0;
  const int iters = hold + stages * per_stage + options.init_iterations;
  // While the labels are held, the prior barely pulls: the held pose may lie half a joint range
  // from the start (it is still there to pin what no marker moves). Released, the search starts
  // afresh from the held pose, its prior centred there.
  double prior_weight = held ? 0.01 : 1.0;
  Eigen::MatrixXd N(nz, nz), Nd(nz, nz);
  Eigen::VectorXd g(nz), step(nz), trial(nz);
  Eigen::LLT<Eigen::MatrixXd> llt(nz);
  std::vector<int> assign(nm, -1), previous(nm, -2);
  std::vector<char> free(nz, 1);
  Eigen::VectorXd lower(nz), upper(nz);
  for (int i = 0; i < nz; ++i) {
    // The start itself may be outside (a user's static pose): never clamp it back.
    lower[i] = std::min(model->coordinates()[i].min_value, z[i]);
    upper[i] = std::max(model->coordinates()[i].max_value, z[i]);
  }
  auto Cost = [&](const Eigen::VectorXd& zz) { return LabelCost(assign, zz, start, prior_weight, &free); };
  double radius = 0.25;
  double lambda = 1e-3;
  for (int iteration = held ? stages * per_stage : 0; iteration < iters; ++iteration) {
    const bool holding = held && iteration < stages * per_stage + hold;
    if (held && !holding && prior_weight < 1.0) {
      prior_weight = 1.0;
      start = z;
    }
    // The stage schedule; an exchange's release starts the final stage afresh.
    const int it = holding ? stages * per_stage : iteration - hold;
    const int stage = it / per_stage;  // >= stages: the final stage
    const bool final_stage = stage >= stages;
    const int depth = final_stage ? max_depth : stage;
    for (int i = 0; i < nz; ++i) free[i] = coordinate_depth[i] <= depth;
    radius = stage == 0 ? 0.25
             : !final_stage ? 0.15
                            : std::max(options.init_radius_m,
                                       0.12 - 0.02 * (it - stages * per_stage));
    Linearise(z);
    if (holding)
      assign = *held;
    else
      AssignWithin(np, radius, depth, &assign);
    const bool same = assign == previous;
    previous = assign;

    // Normal equations of the assigned markers + prior.
    LabelNormalEquations(assign, z, start, prior_weight, &N, &g);
    for (int i = 0; i < nz; ++i) {
      if (!free[i]) {
        N.row(i).setZero();
        N.col(i).setZero();
        N(i, i) = 1;
        g[i] = 0;
      }
    }
    const bool accepted = DampedGaussNewtonStep(
        N, g, Cost(z), &lambda, &Nd, &llt, &step,
        [&] {
          trial = z + step;
          // Within the model's joint ranges: a foot turned 120 degrees can match heel and toe
          // markers to each other's points, a pose no subject takes.
          for (int i = 0; i < nz; ++i)
            if (!wraps[i]) trial[i] = std::clamp(trial[i], lower[i], upper[i]);
          return Cost(trial);
        });
    if (accepted) z = trial;
    if (final_stage && !holding && same && (!accepted || step.norm() < 1e-6) &&
        radius <= options.init_radius_m)
      break;
  }
  // Final assignment at the final pose and its score.
  Hypothesis h;
  Linearise(z);
  h.assignment.assign(nm, -1);
  h.score = AssignWithin(np, radius, max_depth, &h.assignment);
  CountLabels(&h);
  Wrap(&z);
  h.z = z;
  return h;
}

// Exchanges. Every search above assigns by distance from where its pose puts the markers, so
// all of them settle in the same local minimum where two neighbouring markers' points are each
// nearer the other's prediction than to its own, and only a large turn of the pose makes the
// right pairing the nearer one: welk007's wrist markers on the radius and the ulna, at the ends
// of the forearm's 90 degree pronation range -- the static pose holds it at 0, the subject at 90,
// and every search labelled the two points crossed (a labelled fit of that model leaves 15.4 mm
// RMS, crossed 16.9 mm). So the best placement's labels are exchanged pair by pair (two markers
// whose points lie within kExchangeRadius of each other: neighbours the assignment could
// confuse), each exchange held while the pose follows it and then released (Icp with `held`),
// and an exchange that labels as many markers at a lower score replaces the best (scored as every
// other hypothesis, so its pose must fit all markers, not the pair alone; "as many": the truncated
// score alone would take a crossed pair that leaves two markers unlabelled for smaller
// residuals, simulated seed 9's left wrist). Greedy, two passes at most. The replaced placement
// stays among the hypotheses; it differs from the new best by exchanged pairs, which the
// ambiguity test leaves to this decision. An exchange that loses is not added: as a runner-up of
// the search's own making it delayed starts the search alone accepted (seed 19: frame 14 instead
// of 10, then RHEE and RANK crossed for 1,121 frames).
int Tracker::Impl::ExchangeLabels(std::vector<Hypothesis>* hyps, int best, int np) {
  std::vector<int> held;
  for (int pass = 0; pass < 2; ++pass) {
    bool improved = false;
    for (int a = 0; a < nm; ++a) {
      for (int b = a + 1; b < nm; ++b) {
        const Hypothesis& h = (*hyps)[best];
        const int pa = h.assignment[a], pb = h.assignment[b];
        if (pa < 0 || pb < 0 ||
            (points.col(pa) - points.col(pb)).squaredNorm() > kExchangeRadius * kExchangeRadius)
          continue;
        held = h.assignment;
        std::swap(held[a], held[b]);
        Hypothesis e = Icp(h.z, np, &held);
        // Better: as many labels at a lower score (the truncated score alone would trade a
        // label for smaller residuals: a crossed wrist pair leaving two markers unlabelled). A
        // refinement back at the same labels is no exchange.
        if (e.labelled >= h.labelled && e.score < h.score && e.assignment != h.assignment) {
          hyps->push_back(std::move(e));
          best = static_cast<int>(hyps->size()) - 1;
          improved = true;
        }
      }
    }
    if (!improved) break;
  }
  return best;
}

// Scaling to the subject. A generic model (OpenSim's gait2354 for a subject whose femurs are 15 %
// longer, welk007's Rajagopal model, 84 mm RMS off that subject with its labels) puts markers
// farther from their points than the search's 5 cm: its best placement labels too few, or too
// far, and no heading or restart mends what is a matter of size. So, as OpenSim's scaling does
// with labels, each segment's scale factor (model/model.h: its markers and its child joints'
// centres scale with it) is fitted together with the pose to the best placement's points, from
// the root outwards as the search places the body, reassigned at each step (within 15 cm, then a
// radius shrinking from 12 cm to the search's) so that markers the model put too far are taken up
// as their segments grow, with a prior at the model's own scale (init_scale_sigma; a segment no
// marker sizes keeps it), within 1/kScaleLimit..kScaleLimit of it. Then the whole search runs
// again on the scaled model; when that happens and which result is kept: TryInitialise.
double Tracker::Impl::ScaleToSubject(const Hypothesis& h, int np, const std::vector<int>* held,
                                     Hypothesis* fitted, std::vector<double>* distance) {
  const int ns = model->num_segments(), n = nz + ns;
  const Eigen::VectorXd p0 = model->InitialParameters();
  Eigen::VectorXd p = geometry_params, ptrial = p;
  Eigen::VectorXd z = h.z, trial(nz);
  const Eigen::VectorXd start = z;
  const double prior_scale = 0.01 * 0.01 / (options.init_scale_sigma * options.init_scale_sigma);
  Eigen::MatrixXd N(n, n), Nd(n, n);
  Eigen::VectorXd g(n), step(n);
  Eigen::LLT<Eigen::MatrixXd> llt(n);
  Eigen::Matrix3Xd jpm(3, std::max(1, model->max_chain_parameters()));
  std::vector<int> assign(nm, -1);
  auto Cost = [&](const Eigen::VectorXd& zz, const Eigen::VectorXd& pp) {
    SetGeometry(pp);
    double c = LabelCost(assign, zz, start, 1.0, nullptr);
    for (int k = 0; k < ns; ++k) c += prior_scale * (pp[k] - p0[k]) * (pp[k] - p0[k]);
    return c;
  };
  double lambda = 1e-3;
  // From the root outwards, as the search places the body (Icp): stage d sizes the segments at
  // depth <= d with the markers they carry, so a shank is sized once its thigh is.
  const int stages = max_depth + 1, per_stage = 3;
  std::vector<char> free_scale(ns, 1);
  // Held: a labelling placed already, every segment sized at once.
  for (int it = held ? stages * per_stage : 0; it < stages * per_stage + kScaleIterations; ++it) {
    const int stage = it / per_stage;
    const bool final_stage = stage >= stages;
    const int depth = final_stage ? max_depth : stage;
    for (int k = 0; k < ns; ++k) free_scale[k] = segment_depth[k] <= depth;
    const double radius =
        !final_stage ? 0.15
                     : std::max(options.init_radius_m, 0.12 - 0.01 * (it - stages * per_stage));
    SetGeometry(p);
    Linearise(z);
    if (held)
      assign = *held;
    else
      AssignWithin(np, radius, depth, &assign);
    N.setZero();
    g.setZero();
    for (int m = 0; m < nm; ++m) {
      if (assign[m] < 0) continue;
      const Eigen::Vector3d r = predicted.col(m) - points.col(assign[m]);
      // Columns: the marker's coordinates, then the scales among its parameters.
      const std::vector<int>& cz = model->marker_coordinates(m);
      const std::vector<int>& cp = model->marker_parameters(m);
      auto J = jpm.leftCols(cp.size());
      MarkerJacobian(*model, geometry, data, m, static_cast<Eigen::Matrix3Xd*>(nullptr), &J);
      const int nzc = static_cast<int>(cz.size());
      auto column = [&](int a) -> Eigen::Vector3d {
        return a < nzc ? Eigen::Vector3d(jac[m].col(a)) : Eigen::Vector3d(J.col(a - nzc));
      };
      auto index = [&](int a) { return a < nzc ? cz[a] : nz + cp[a - nzc]; };
      const int na = nzc + static_cast<int>(cp.size());
      for (int a = 0; a < na; ++a) {
        if (a >= nzc && cp[a - nzc] >= ns) continue;  // not a scale
        const Eigen::Vector3d ja = column(a);
        g[index(a)] += ja.dot(r);
        for (int k = 0; k < na; ++k) {
          if (k >= nzc && cp[k - nzc] >= ns) continue;
          N(index(a), index(k)) += ja.dot(column(k));
        }
      }
    }
    for (int i = 0; i < nz; ++i) {
      const double w = SearchPrior(i);
      N(i, i) += w;
      g[i] += w * (z[i] - start[i]);
    }
    for (int k = 0; k < ns; ++k) {
      N(nz + k, nz + k) += prior_scale;
      g[nz + k] += prior_scale * (p[k] - p0[k]);
    }
    for (int i = 0; i < n; ++i) {
      if (i < nz ? coordinate_depth[i] <= depth : free_scale[i - nz]) continue;
      N.row(i).setZero();
      N.col(i).setZero();
      N(i, i) = 1;
      g[i] = 0;
    }
    const bool accepted = DampedGaussNewtonStep(N, g, Cost(z, p), &lambda, &Nd, &llt, &step, [&] {
      trial = z + step.head(nz);
      for (int i = 0; i < nz; ++i)
        if (!wraps[i])
          trial[i] = std::clamp(trial[i], std::min(model->coordinates()[i].min_value, start[i]),
                                std::max(model->coordinates()[i].max_value, start[i]));
      ptrial = p;
      for (int k = 0; k < ns; ++k)
        ptrial[k] = std::clamp(p[k] + step[nz + k], p0[k] / kScaleLimit, p0[k] * kScaleLimit);
      return Cost(trial, ptrial);
    });
    if (accepted) {
      z = trial;
      p = ptrial;
    }
  }
  double cost = Cost(z, p);
  for (int m = 0; m < nm; ++m)
    if (seen[m] && assign[m] < 0) cost += options.init_radius_m * options.init_radius_m;
  if (fitted) {
    // Cost() left the geometry and the kinematics at (z, p).
    double sum = 0;
    int labelled = 0;
    if (distance) distance->assign(nm, 0.0);
    for (int m = 0; m < nm; ++m)
      if (assign[m] >= 0) {
        const double d2 = (MarkerPosition(*model, geometry, data, m) - points.col(assign[m])).squaredNorm();
        if (distance) (*distance)[m] = std::sqrt(d2);
        sum += d2;
        ++labelled;
      }
    fitted->z = z;
    fitted->rms = labelled > 0 ? std::sqrt(sum / labelled) : std::numeric_limits<double>::infinity();
  }
  SetGeometry(p);
  return cost;
}

// The whole search at the present geometry: every start and heading, the restarts from the
// best, the exchanges; then the acceptance tests. Returns the best hypothesis' index, or -1 when
// the search refuses (init.reason says why).
int Tracker::Impl::Search(int np, std::vector<Hypothesis>* out) {
  std::vector<Hypothesis>& hyps = *out;
  hyps.clear();
  const Eigen::Vector3d centroid = points.leftCols(np).rowwise().mean();
  std::vector<Eigen::VectorXd> starts;
  starts.push_back(options.static_pose.size() == nz ? options.static_pose
                                                    : model->DefaultCoordinates());
  if (had_track) starts.push_back(z_good);
  // The points are turned so that the lab's vertical is the model's (lab_to_model).
  const Eigen::Vector3d up = options.model_up.normalized();
  for (const Eigen::VectorXd& s : starts) {
    const int headings = root_euler ? options.init_headings : 1;
    for (int k = 0; k < headings; ++k) {
      const Eigen::Matrix3d turn =
          Eigen::AngleAxisd(2 * M_PI * k / headings, up).toRotationMatrix();
      Eigen::VectorXd z;
      if (!PlaceRoot(s, turn, centroid, &z)) continue;
      hyps.push_back(Icp(z, np));
    }
  }
  if (hyps.empty()) {
    init.reason = "the root cannot be placed";
    return -1;
  }
  auto Best = [&] {
    int b = 0;
    for (size_t i = 1; i < hyps.size(); ++i)
      if (hyps[i].score < hyps[b].score) b = static_cast<int>(i);
    return b;
  };
  // Variants: the best placement with the joints of the static pose perturbed. A few limbs can
  // settle in a wrong but self-consistent configuration (a ghost standing in for a wrist
  // marker); starting them elsewhere lets the right configuration win on its score.
  {
    const Eigen::VectorXd base = hyps[Best()].z;
    const Eigen::VectorXd& pose = starts[0];
    // First the static pose blended towards the middle of each joint's range (bent elbows and
    // knees: the wrist markers of a straight arm sit, 7 cm apart, along the very direction in
    // which a 15 degree elbow flexion moves them, so a straight start pairs each with the
    // other's point), then random perturbations.
    std::mt19937 rng(12345);
    std::uniform_real_distribution<double> u(-1.0, 1.0);
    const double blends[] = {0.1, 0.2, 0.3};
    const int blend_count = options.init_variants > 0 ? 3 : 0;
    for (int v = 0; v < blend_count + options.init_variants; ++v) {
      Eigen::VectorXd z = pose;
      for (int i = 0; i < nz; ++i) {
        const Coordinate& co = model->coordinates()[i];
        if (root_free[i]) {
          z[i] = base[i];
        } else if (!rotational[i]) {
          continue;
        } else if (v < blend_count) {
          if (co.max_value - co.min_value < 2 * M_PI)
            z[i] += blends[v] * (0.5 * (co.min_value + co.max_value) - z[i]);
        } else {
          z[i] += options.init_variant_rad * u(rng);
        }
      }
      hyps.push_back(Icp(z, np));
    }
  }
  // Exchanges decide between labellings of a subject found, they do not find one: only a best
  // placement that passes the tests below on its own is tried (in a second of ghosts alone, a
  // placement on ghosts one label short gained it in an exchange's refinement and started).
  int best = Best();
  if (hyps[best].labelled >= options.init_min_fraction * nm_seen && hyps[best].rms <= options.init_max_rms_m)
    best = ExchangeLabels(&hyps, best, np);
  init.hypotheses = static_cast<int>(hyps.size());
  const Hypothesis& h = hyps[best];
  init.best_score = h.score;
  init.rms_m = h.rms;
  init.labelled = h.labelled;
  // Ambiguity: a hypothesis that labels >= 3 markers differently and comes close (within
  // init_ambiguity_ratio of the best's score, or less than init_ambiguity_margin times its
  // residual variance per coordinate above it). Markers whose labels are exchanged pairwise (a's
  // point b's and b's a's) do not count: each such pair is decided by its own exchange
  // (ExchangeLabels), the wrist pairs of both arms are two decisions, not one ambiguity of four
  // labels.
  //
  // What the close hypotheses all agree on is decided; the markers they label differently are
  // not, and are left empty (the pose refitted without them: LeaveLabelsEmpty) rather than
  // guessed -- as long as the labels decided are enough to start (init_min_fraction). Refusing
  // the whole start for one limb's doubt cost more than the limb: simulated seed 81 at 5 ghosts,
  // the right hand's three markers and a standing reflection beside them, two placements 6e-4
  // m^2 apart (RWRA on its point or on RWRB's), refused for seven frames, then started when RFIN
  // was hidden on a third placement with the hand turned (RWRA on RWRB's point, RWRB on the
  // reflection, RFIN on RWRA's point), kept for the whole session (0.955 of the labels). The
  // gates pick an undecided marker up from the next frames, where its limb's other markers and
  // the prior put it. A doubt over too many markers (a subject placed facing two ways) still
  // refuses.
  const double variance = std::max(h.rms * h.rms / 3.0, 1e-6);
  auto close = [&](double score) {
    return score < options.init_ambiguity_ratio * h.score ||
           score - h.score < options.init_ambiguity_margin * variance;
  };
  double runner_up = std::numeric_limits<double>::infinity();
  std::vector<char> undecided(nm, 0);
  std::vector<char> differs(nm);
  for (const Hypothesis& o : hyps) {
    int differ = 0;
    for (int m = 0; m < nm; ++m) {
      differs[m] = 0;
      if (o.assignment[m] == h.assignment[m]) continue;
      bool exchanged = false;
      for (int k = 0; k < nm && !exchanged; ++k)
        exchanged = k != m && o.assignment[m] >= 0 && o.assignment[m] == h.assignment[k] &&
                    o.assignment[k] == h.assignment[m];
      differs[m] = !exchanged;
      differ += !exchanged;
    }
    if (differ < 3) continue;
    runner_up = std::min(runner_up, o.score);
    if (close(o.score))
      for (int m = 0; m < nm; ++m) undecided[m] |= differs[m];
  }
  init.runner_up_score = std::isfinite(runner_up) ? runner_up : 0.0;
  if (h.labelled < options.init_min_fraction * nm_seen) {
    init.reason = kTooFewLabelled;
    return -1;
  }
  if (!(h.rms <= options.init_max_rms_m)) {
    init.reason = kResidualTooLarge;
    return -1;
  }
  if (std::isfinite(runner_up) && close(runner_up)) {
    int decided = 0;
    for (int m = 0; m < nm; ++m) decided += h.assignment[m] >= 0 && !undecided[m];
    if (decided < options.init_min_fraction * nm_seen) {
      init.reason = "ambiguous";
      return -1;
    }
    init.undecided = LeaveLabelsEmpty(&hyps[best], undecided, StaticPoseAt(hyps[best].z));
    init.labelled = hyps[best].labelled;
    init.rms_m = hyps[best].rms;
  }
  return best;
}

// A label that alone turns its limb. The search prices a joint's departure from the static pose
// with a prior of 0.5 rad (a pin for what no marker holds, not a belief about the subject), and a
// marker it leaves unlabelled at the final radius squared: so a limb whose turn one marker alone
// decides (a foot's subtalar angle by its toe marker, a hand by its finger marker) turns by half
// a radian for any point that marker can reach, and a reflection there wins over the marker's own
// point where the pose without the turn puts it (simulated seed 37 at 5 ghosts: the right ankle
// turned 0.46 rad and the subtalar -0.42 rad to put RTOE on a reflection 10 mm away; its own
// point 41 mm from where the rest of the body puts it; the reflection stayed 339 frames, RTOE
// on it all that time). Which of the two configurations is right, one frame cannot say: the
// label is a guess, and is left empty (issue 15: "a label the window cannot decide left empty
// rather than guessed"); the gates decide from the next frame, with the limb where its other
// markers and the prior put it.
//
// Per labelled marker m, the pose is refitted without it (HeldFit, its labels held, the prior at
// the static pose with the root where the search put it): the deleted residual, m's point from
// where the rest of the body puts m. m's label is left empty when all three hold:
//  - the deleted residual exceeds the search's final radius (init_radius_m): without its own
//    label the search would not have matched m to that point;
//  - an unclaimed point lies nearer than m's labelled point to where the rest of the body puts
//    m: there is a second configuration, not one label or none (a generic model's acromion
//    marker 55 mm from where gait2354's torso puts it, with no other point near, keeps its label;
//    so do welk007's wrist markers, pronated past the static pose's range by the two together:
//    the point near one's deleted prediction is the other's). Nearer, not within the radius: the
//    marker's own point may be as far as the reflection it lost to (simulated seed 69 at 5
//    ghosts: LTOE on a reflection 85 mm from where the rest of the body puts it, its own point
//    63 mm from there, the label turning the foot by 4.6 times the prior's departure without it,
//    kept for 311 frames);
//  - the label takes m's chain farther from the static pose than the rest of the body does
//    (the search's prior, summed over the chain's joint angles): it buys a turn. Where it holds
//    the chain nearer (at the nominal model's own size seed 37's start in the static alone has
//    RTOE on its own point with the foot near the static pose, the heel's model error turning
//    the ankle 0.4 rad without it, and a reflection 45 mm from there), it is no guess of the
//    search's prior's making.
// Cheap: a Gauss-Newton step per marker on the normal equations at the search's pose (one
// linearisation; 38 x 38 factorisations) screens every label, and only a deleted residual of
// over half the radius there is refitted (the linearisation over half a radian errs by up to a
// centimetre); 1-4 ms against the search's 60-100 ms.
double Tracker::Impl::HeldFit(Eigen::VectorXd* zp, const Eigen::VectorXd& centre,
                              const std::vector<int>& assign, int iterations) {
  Eigen::VectorXd& z = *zp;
  Eigen::MatrixXd N(nz, nz), Nd(nz, nz);
  Eigen::VectorXd g(nz), step(nz), trial(nz);
  Eigen::LLT<Eigen::MatrixXd> llt(nz);
  auto Cost = [&](const Eigen::VectorXd& zz) { return LabelCost(assign, zz, centre, 1.0, nullptr); };
  double lambda = 1e-3;
  for (int it = 0; it < iterations; ++it) {
    Linearise(z);
    LabelNormalEquations(assign, z, centre, 1.0, &N, &g);
    const bool accepted = DampedGaussNewtonStep(N, g, Cost(z), &lambda, &Nd, &llt, &step, [&] {
      trial = z + step;
      for (int i = 0; i < nz; ++i)
        if (!wraps[i])
          trial[i] = std::clamp(trial[i], std::min(model->coordinates()[i].min_value, z[i]),
                                std::max(model->coordinates()[i].max_value, z[i]));
      return Cost(trial);
    });
    if (!accepted) break;
    const double moved = step.norm();
    z = trial;
    if (moved < 1e-6) break;
  }
  return Cost(z);
}

int Tracker::Impl::LeaveSelfDecidedLabelsEmpty(Hypothesis* h, int np) {
  const double radius = options.init_radius_m;
  const Eigen::VectorXd centre = StaticPoseAt(h->z);
  // The screen: at the search's pose, N = sum J^T J + W and g = sum J^T r + W (z - centre) over
  // the labels; without m's, one Gauss-Newton step moves m's residual r_m to r_m + J_m dz.
  Linearise(h->z);
  Eigen::MatrixXd N(nz, nz), Nm(nz, nz);
  Eigen::VectorXd g(nz), gm(nz), dz(nz);
  LabelNormalEquations(h->assignment, h->z, centre, 1.0, &N, &g);
  Eigen::LLT<Eigen::MatrixXd> llt(nz);
  std::vector<int> screened;
  for (int m = 0; m < nm; ++m) {
    if (h->assignment[m] < 0) continue;
    const Eigen::Vector3d r = predicted.col(m) - points.col(h->assignment[m]);
    const std::vector<int>& cols = model->marker_coordinates(m);
    const auto& J = jac[m];
    Nm = N;
    gm = g;
    for (size_t a = 0; a < cols.size(); ++a) {
      gm[cols[a]] -= J.col(a).dot(r);
      for (size_t b = 0; b < cols.size(); ++b) Nm(cols[a], cols[b]) -= J.col(a).dot(J.col(b));
    }
    llt.compute(Nm);
    if (llt.info() != Eigen::Success) continue;
    dz = -llt.solve(gm);
    Eigen::Vector3d e = r;
    for (size_t a = 0; a < cols.size(); ++a) e += J.col(a) * dz[cols[a]];
    if (e.norm() > 0.5 * radius) screened.push_back(m);
  }
  if (screened.empty()) return 0;
  // The screened labels, refitted. The reference: the fit of every label with the same prior.
  std::vector<int> held = h->assignment, dropped;
  Eigen::VectorXd full = h->z, z;
  HeldFit(&full, centre, held, kHeldFitIterations);
  std::vector<char> claimed(np, 0);
  for (int m = 0; m < nm; ++m)
    if (h->assignment[m] >= 0) claimed[h->assignment[m]] = 1;
  // How far marker m's chain is from the static pose, in the prior's terms (m^2).
  auto departure = [&](int m, const Eigen::VectorXd& zz) {
    double d = 0;
    for (int i : model->marker_coordinates(m))
      if (!root_free[i])
        d += SearchPrior(i) * (zz[i] - centre[i]) * (zz[i] - centre[i]);
    return d;
  };
  for (int m : screened) {
    const int k = h->assignment[m];
    held[m] = -1;
    z = full;
    HeldFit(&z, centre, held, kHeldFitIterations);
    held[m] = k;
    ForwardKinematics(*model, geometry, z, &data);
    const Eigen::Vector3d at = MarkerPosition(*model, geometry, data, m);
    const double deleted = (at - points.col(k)).norm();
    if (deleted <= radius) continue;
    bool second = false;
    for (int q = 0; q < np && !second; ++q) second = !claimed[q] && (at - points.col(q)).norm() < deleted;
    if (second && departure(m, full) > departure(m, z)) dropped.push_back(m);
  }
  if (dropped.empty()) return 0;
  std::vector<char> empty(nm, 0);
  for (int m : dropped) empty[m] = 1;
  h->z = full;
  return LeaveLabelsEmpty(h, empty, centre);
}

// Deferred start labels (ekf/tracker.h, "Deferred labels"). The search places the body on one
// frame's points and labels each marker with the point nearest where that placement puts it; a
// placement fitted to a label is pulled towards it, so the nearest point is the search's own
// choice, not evidence. What the placement cannot bend is the segment's rigid geometry: the
// point's distances to the segment's joint centre and to its labelled mates, each expected as the
// model says within the model's error -- the per-coordinate variance of the start's residuals
// (the placement's RMS over 3; a scaled nominal model leaves 7-9 mm RMS, the true model 2-3 mm)
// for each marker of a pair, and kJointCentreTolerance more for a predicted joint centre. A
// labelled marker with two anchors or more, and an unclaimed point within the search's final
// radius of its place that fits those distances better than its labelled point, is undecided
// (the placement, not the geometry, chose the label): the label is left empty, the pose refitted
// without it, and the candidates (the labelled point and every such rival) are followed over the
// next frames until their motion decides (MatchDeferrals, JudgeDeferrals). Simulated seed 120
// with the nominal model: RWRB placed 11 mm from a reflection (distances off by 6.6/10.5/11.8 mm,
// a chi-square of 11.9) and 25 mm from its own point (20.7/4.2/5.3 mm, 2.9), held the reflection
// 71 frames.
int Tracker::Impl::DeferAmbiguousStartLabels(Hypothesis* h, int np) {
  for (Deferral& d : deferral) d.n = 0;
  Linearise(h->z);
  const double noise = std::max(h->rms * h->rms / 3.0, 1e-6);
  const double centre_var = noise + kJointCentreTolerance * kJointCentreTolerance;
  const double radius = options.init_radius_m;
  std::vector<char> claimed(np, 0), empty(nm, 0);
  for (int m = 0; m < nm; ++m)
    if (h->assignment[m] >= 0) claimed[h->assignment[m]] = 1;
  int deferred = 0;
  for (int m = 0; m < nm; ++m) {
    const int k = h->assignment[m];
    if (k < 0 || !seen[m]) continue;
    const int segment = model->markers()[m].segment;
    const bool has_centre = marker_depth[m] > 0;
    const Eigen::Vector3d centre = data.segment_position[segment];
    int anchors = has_centre ? 1 : 0;
    for (int o : segment_markers[segment]) anchors += o != m && h->assignment[o] >= 0;
    if (anchors < 2) continue;
    auto cost = [&](const Eigen::Vector3d& p) {
      double c = 0;
      if (has_centre) {
        const double r = (p - centre).norm() - (predicted.col(m) - centre).norm();
        c += r * r / centre_var;
      }
      for (int o : segment_markers[segment]) {
        if (o == m || h->assignment[o] < 0) continue;
        const double r = (p - points.col(h->assignment[o])).norm() - (predicted.col(m) - predicted.col(o)).norm();
        c += r * r / (2 * noise);
      }
      return c;
    };
    const double own = cost(points.col(k));
    Deferral& d = deferral[m];
    d = Deferral();
    d.at[0] = points.col(k);
    d.n = 1;
    for (int q = 0; q < np && d.n < kDeferCandidates; ++q) {
      if (claimed[q] || (points.col(q) - predicted.col(m)).norm() > radius) continue;
      if (cost(points.col(q)) < own) d.at[d.n++] = points.col(q);
    }
    if (d.n == 1) {
      d.n = 0;
      continue;
    }
    for (int o : segment_markers[segment])
      if (o != m && h->assignment[o] >= 0 && d.nanchors < kDeferAnchors) d.anchor[d.nanchors++] = o;
    for (int c = 0; c < d.n; ++c) {
      d.alive[c] = 1;
      d.ruled_out[c] = 0;
      d.lived[c] = 0;
      d.died[c] = 0;
      d.point[c] = -1;
      for (int a = 0; a < d.nanchors; ++a) {
        d.d0[c][a] = (d.at[c] - points.col(h->assignment[d.anchor[a]])).norm();
        d.mean0[c][a] = d.sum[c][a] = 0;
        d.blocks[c][a] = d.count[c][a] = 0;
      }
    }
    empty[m] = 1;
    ++deferred;
  }
  if (deferred == 0) return 0;
  LeaveLabelsEmpty(h, empty, StaticPoseAt(h->z));
  return deferred;
}

Eigen::VectorXd Tracker::Impl::StaticPoseAt(const Eigen::VectorXd& z) const {
  Eigen::VectorXd centre = z_static;
  for (int i = 0; i < nz; ++i)
    if (root_free[i]) centre[i] = z[i];
  return centre;
}

int Tracker::Impl::LeaveLabelsEmpty(Hypothesis* h, const std::vector<char>& empty,
                                    const Eigen::VectorXd& centre) {
  int emptied = 0;
  for (int m = 0; m < nm; ++m)
    if (empty[m] && h->assignment[m] >= 0) {
      h->assignment[m] = -1;
      ++emptied;
    }
  if (emptied == 0) return 0;
  // The pose without them: where their limbs' other markers and the prior put the limbs.
  HeldFit(&h->z, centre, h->assignment, kHeldFitIterations);
  Linearise(h->z);
  CountLabels(h);
  return emptied;
}

void Tracker::Impl::CountLabels(Hypothesis* h) const {
  double sum = 0;
  h->labelled = 0;
  for (int m = 0; m < nm; ++m)
    if (h->assignment[m] >= 0) {
      sum += (points.col(h->assignment[m]) - predicted.col(m)).squaredNorm();
      ++h->labelled;
    }
  h->rms = h->labelled > 0 ? std::sqrt(sum / h->labelled) : std::numeric_limits<double>::infinity();
}

bool Tracker::Impl::TryInitialise(int np) {
  ++init.attempts;
  init.accepted = false;
  init.hypotheses = 0;
  init.best_score = init.runner_up_score = init.rms_m = 0;
  init.labelled = init.undecided = 0;
  if (np < options.init_min_fraction * nm_seen) {
    init.reason = "too few points";
    return false;
  }
  ClearOffsets(0);
  std::vector<Hypothesis> hyps;
  int best = Search(np, &hyps);
  // A model that does not fit the subject (the search's labels too few or too far, in every
  // search over init_scale_after_s) -- or any, scaling always (the default) -- is scaled to the
  // subject from the best placement (ScaleToSubject) and searched for again. A start refused as
  // ambiguous is not: a tie between labellings is no matter of size (scaled, simulated seed 19's
  // start shifted an arm's labels one marker along the arm). Nor, when scaling only a model that
  // does not fit, is a model that has tracked the subject: a later refusal is the scene's, not
  // the model's size (in a second of ghosts alone, TrackFaults' AllMarkersOccludedForASecond, 41
  // ghosts where the body was, a search labelling 27-31 of 39 markers on ghosts scaled itself to
  // label 32). Which labelling then starts, and at which scales: below.
  using Scale = TrackerOptions::ScaleToSubject;
  const bool unfit = !had_track && best < 0 && (init.reason == kTooFewLabelled || init.reason == kResidualTooLarge);
  unfit_searches = unfit ? unfit_searches + 1 : 0;
  const int judged = std::max(1, static_cast<int>(std::lround(options.init_scale_after_s * options.rate_hz)));
  const bool does_not_fit = unfit && unfit_searches >= judged;
  const Scale scale_mode = origin == ModelOrigin::kFittedToSubject && options.init_scale_to_subject == Scale::kAlways
                               ? Scale::kWhenTheModelDoesNotFit
                               : options.init_scale_to_subject;
  if (!hyps.empty() && ((scale_mode == Scale::kAlways && best >= 0) ||
                        (scale_mode != Scale::kNever && does_not_fit))) {
    const Eigen::VectorXd before = geometry_params;
    const InitialisationSummary summary = init;
    std::vector<Hypothesis> as_given = hyps;
    const int best_as_given = best;
    int b = 0;
    for (size_t i = 1; i < hyps.size(); ++i)
      if (hyps[i].score < hyps[b].score) b = static_cast<int>(i);
    ScaleToSubject(hyps[b], np);
    best = Search(np, &hyps);
    // Which labelling starts, and at which size. The scaled search's when the model's own size
    // gave none. Where both gave one and they differ (the scaled search may add labels, change
    // them, or shift an arm's along it), each labelling is fitted with the scales free to it
    // alone -- no reassignment, so no ghost within the scaling's wide radius takes part -- and
    // the scaled labelling is taken only when it fits clearly better (by the search's
    // log-likelihood margin; a marker left unlabelled costs the search's radius squared). Else
    // the model's own labels are kept, at the scales fitted to them: labels the search was sure
    // of at the model's own size. (Taken only when it kept every label the model's own size
    // gave, a wrong one stayed: RTOE on a ghost, simulated seed 10 at 8 ghosts, the static pose
    // alone. Taken whenever it only added labels, seed 74's at 5 ghosts, 21.7 mm RMS against
    // 15.0 at the model's size, put RTOE on a ghost 42 mm off.)
    const bool scaled_found = best >= 0;
    bool differ = false;
    if (scaled_found && best_as_given >= 0)
      for (int m = 0; m < nm; ++m)
        differ |= as_given[best_as_given].assignment[m] != hyps[best].assignment[m];
    if (!scaled_found && best_as_given < 0) {
      SetGeometry(before);
      best = -1;
    } else if (!scaled_found || differ) {
      double fit_scaled = std::numeric_limits<double>::infinity();
      Hypothesis found;
      std::vector<double> distance;
      if (scaled_found) {
        found = hyps[best];
        fit_scaled = ScaleToSubject(found, np, &found.assignment, &found, &distance);
      }
      const Eigen::VectorXd scaled_fitted = geometry_params;
      SetGeometry(before);
      Hypothesis given = as_given[best_as_given];
      const double fit_given = ScaleToSubject(given, np, &given.assignment, &given);
      const double variance = scaled_found ? std::max(hyps[best].rms * hyps[best].rms / 3.0, 1e-6) : 0.0;
      // Every label the scaled labelling gives that the model's own did not within its gate
      // (gate_chi2) of the noise the own labels leave at their fitted scales: the truncated cost
      // alone takes a ghost 42 mm off (seed 74's RTOE, the foot scaled to it: its heel and toe
      // markers unlabelled for the whole session).
      bool new_labels_fit = scaled_found;
      const double noise = given.rms * given.rms / 3.0;
      for (int m = 0; m < nm && new_labels_fit; ++m)
        if (found.assignment[m] >= 0 && found.assignment[m] != as_given[best_as_given].assignment[m])
          new_labels_fit = distance[m] * distance[m] <= options.gate_chi2 * noise;
      if (new_labels_fit && fit_scaled < fit_given - options.init_ambiguity_margin * variance) {
        SetGeometry(scaled_fitted);
        hyps[best].z = found.z;
        hyps[best].rms = found.rms;
        init.rms_m = found.rms;
      } else {
        // The geometry is the scales fitted to the model's own labels (the last fit's).
        hyps = std::move(as_given);
        best = best_as_given;
        init = summary;
        hyps[best].z = given.z;
        hyps[best].rms = given.rms;
        init.rms_m = given.rms;
      }
    }
  }
  const Eigen::VectorXd own = model->InitialParameters();
  if (geometry_params.head(model->num_segments()) == own.head(model->num_segments()))
    init.segment_scales.clear();
  else
    init.segment_scales.assign(geometry_params.data(), geometry_params.data() + model->num_segments());
  if (best < 0) return false;
  // A label that alone turns its limb, where the pose the rest of the body supports has a second
  // point for it, is the search's guess: left empty, the limb placed without it.
  if (LeaveSelfDecidedLabelsEmpty(&hyps[best], np) > 0) {
    init.labelled = hyps[best].labelled;
    init.rms_m = hyps[best].rms;
  }
  // A label its segment's rigid distances cannot tell from an unclaimed point's within the
  // model's error is deferred: left empty, decided by the points' motion.
  if (const int deferred = DeferAmbiguousStartLabels(&hyps[best], np); deferred > 0) {
    init.labelled = hyps[best].labelled;
    init.rms_m = hyps[best].rms;
    init.undecided += deferred;
  }
  const Hypothesis& h = hyps[best];
  // On a model scaled to the subject, what is not known of the offset of a marker the start
  // labelled is what the scaled placement left unexplained, not the nominal model's 1-4 cm
  // (marker_offset_sigma): with that prior a first-second gate is ~10 cm wide, and a wrist marker
  // hidden in the static took a ghost 96-106 mm away there, its mate later put on its point by the
  // limb search (simulated seeds 10 and 24 at 8 ghosts, at the model's own size and scaled
  // alike). A marker the start did not label keeps the nominal prior: nothing sized its segment
  // or measured its place (a forearm the start left, the limb search's placement of it refused
  // for its new labels' narrowed gates: TrackLab.AForearmTheStartLeavesIsPlacedAtOnce).
  //
  // No tighter than kScaledOffsetSigmaFloor, however well the start's one frame fits: with the
  // TRUE model the scaled placement leaves 2-3 mm, and gates that narrow from the first frame lost
  // a pelvis marker at 1 mm from its prediction (the rigid group left it undecided) and an upper
  // arm 10 cm off for thousands of frames (simulated seeds 63 and 78 at 8 ghosts, true model:
  // 0.9999 of the labels at the model's own size, 0.940 scaled with a 2 mm floor, 0.9997 / 0.9999
  // with 1 cm; 5 mm mended only 78). The nominal model's placements leave 7-9 mm.
  if (!init.segment_scales.empty()) {
    const double known = std::min(options.marker_offset_sigma, std::max(h.rms, kScaledOffsetSigmaFloor));
    for (int m = 0; m < nm; ++m)
      if (h.assignment[m] >= 0) offset_sigma[m] = known;
  }

  // Start the filter at the found pose, at rest, and update it with the found labels.
  x.setZero();
  x.head(nz) = h.z;
  P.setZero();
  for (int i = 0; i < nz; ++i) {
    const bool r = rotational[i];
    const double s0 = r ? options.init_sigma_rotational : options.init_sigma_translational;
    const double s1 =
        r ? options.init_sigma_velocity_rotational : options.init_sigma_velocity_translational;
    const double s2 = r ? options.init_sigma_acceleration_rotational
                        : options.init_sigma_acceleration_translational;
    P(i, i) = s0 * s0;
    P(nz + i, nz + i) = s1 * s1;
    P(2 * nz + i, 2 * nz + i) = s2 * s2;
  }
  zbuf = x.head(nz);
  Linearise(zbuf);
  for (int m = 0; m < nm; ++m) row_to_col[m] = h.assignment[m];
  ApplyLabels(np);
  // The search's labels are all measured at once (they were chosen together, not one by one).
  for (int m = 0; m < nm; ++m) {
    measured[m] = row_to_col[m] >= 0;
    labelled_run[m] = measured[m] ? 2 : 0;
    if (measured[m]) {
      last_point.col(m) = points.col(row_to_col[m]);
      last_predicted.col(m) = predicted.col(m);
    }
  }
  // No gate yet: every label of the search is measured at its full weight.
  subject_still = false;  // no last frame to tell
  std::fill(s_inv.begin(), s_inv.end(), Eigen::Matrix3d::Zero());
  double nis = 0;
  if (!FilterUpdate(&nis, 0.0)) {
    init.reason = "the first update failed";
    return false;
  }
  zbuf = x.head(nz);
  Wrap(&zbuf);
  x.head(nz) = zbuf;
  out.nis = nis;
  out.nis_dof = 3 * out.labelled;
  std::fill(unlabelled_run.begin(), unlabelled_run.end(), 0);
  std::fill(stuck_run.begin(), stuck_run.end(), 0);
  tracked_frames = 0;
  hist_size = 0;
  // The search's labels are this frame's: the next frame's labels follow their points
  // (FollowLabelledTracks). At 200 Hz the first prediction is tight enough to keep them anyway;
  // at 12 Hz it is not (83 ms of the start's velocity and acceleration uncertainty): an arm's
  // unlabelled forearm marker, its gate 30 cm wide, took an elbow marker's point and the elbow
  // markers shifted along to the next points (welk007's hip trial, every 8th frame). The
  // unclaimed points have no past yet (no predecessor, no record).
  prev_points.leftCols(np) = points.leftCols(np);
  std::fill(prev_free.begin(), prev_free.begin() + np, 0);
  prev_free_count = 0;
  prev_np = np;
  std::fill(held_run.begin(), held_run.end(), 0);
  init.accepted = true;
  init.reason.clear();
  return true;
}


// ---------------------------------------------------------------------------------------------
// Local re-acquisition of a limb. While the rest of the body tracks, a limb can settle in a wrong
// but self-consistent pose (a foot left with its heel marker only, a thigh turned about its long
// axis after a re-initialisation) from which its other markers' gates never meet their points
// again. When a marker has been unlabelled for kLimbSeconds of tracking frames, the subtree of the
// joint that moves it is searched again ICP-like among the points the rest of the body did not
// take, from its current pose and a few restarts; a clearly better, unambiguous placement that
// keeps the limb's present labels replaces the limb's coordinates, with their velocities and
// accelerations zeroed and their covariance reset to the initialisation's. Allocation-free.
namespace {
// A limb search's period: 20 frames at 200 Hz. In seconds, not frames: at 12 Hz 20 frames are 1.7 s,
// and a leg the filter lost in a fast swing ran on unlabelled for that long (biobuddy's knee trials).
constexpr double kLimbSeconds = 0.1;
constexpr int kLimbIterations = 10;
constexpr double kLimbFinalRadius = 0.05;
constexpr double kLimbMaxRms = 0.03;
constexpr double kLimbNearRadius = 0.25;  // an unclaimed point this near a due marker
constexpr double kLimbCentreTolerance = 0.02;
// How far (rad) the search for a limb with no label may take its unheld angles past the model's
// ranges. A generic model's range is not the subject's: Rajagopal's forearm pronates 0-90
// degrees from supination, and welk007, hands held in front in the hip trial, fits its wrist
// markers on radius and ulna the right way round only past it (the right arm's 6 markers: 18.0
// mm RMS crossed; right, 22.6 mm with the pronation held at 90 degrees, 15.2 mm at 147; tried with
// the slack in the filter too, 0.3 rad left both arms crossed and 0.6 one).
constexpr double kLimbRangeSlack = 1.0;
}  // namespace

// Assigns the limb's markers among the candidate points by distance at z (within radius);
// lassign receives compact point indices (or -1); returns the truncated cost.
// Predictions and Jacobians of the limb's markers only.
void Tracker::Impl::LineariseLimb(int joint, const Eigen::VectorXd& z) {
  ForwardKinematics(*model, geometry, z, limb_joint_list[joint], &data);
  for (int m : limb_markers[joint]) {
    predicted.col(m) = MarkerPosition(*model, geometry, data, m) +
                       data.segment_rotation[model->markers()[m].segment] * offset[m];
    MarkerJacobian(*model, geometry, data, m, &jac[m], static_cast<Eigen::Matrix3Xd*>(nullptr));
  }
}

double Tracker::Impl::LimbAssign(int joint, const Eigen::VectorXd& z, int nc, double radius) {
  LineariseLimb(joint, z);
  const double r2 = radius * radius;
  // The limb's labelled markers keep their points: only its unlabelled ones are assigned.
  double total = 0;
  int ns = 0;
  for (int m : limb_markers[joint]) {
    if (row_to_col[m] >= 0 && !LimbRelabels()) {
      lassign[m] = row_to_col[m];
      total += std::min(r2, (points.col(row_to_col[m]) - predicted.col(m)).squaredNorm());
    } else {
      lfree[ns++] = m;
    }
  }
  if (ns == 0) return total;
  auto C = cost.topLeftCorner(ns, nc + ns);
  for (int r = 0; r < ns; ++r) {
    const int m = lfree[r];
    for (int c = 0; c < nc; ++c) {
      const double d2 = (points.col(lcand[c]) - predicted.col(m)).squaredNorm();
      C(r, c) = d2 < r2 && !DeferralExcludes(m, lcand[c]) ? d2 : kForbidden;
    }
    C.row(r).tail(ns).setConstant(kForbidden);
    C(r, nc + r) = r2;
  }
  total += lap.Solve(C, lrow_to_col.data());
  for (int r = 0; r < ns; ++r)
    lassign[lfree[r]] = lrow_to_col[r] < nc ? lcand[lrow_to_col[r]] : -1;
  return total;
}

bool Tracker::Impl::ReacquireLimb(int joint, int np, bool place, bool unheld, bool relabel) {
  const std::vector<int>& rows = limb_markers[joint];
  const std::vector<char>& freec = limb_coord[joint];
  const int ns = static_cast<int>(rows.size());
  const std::vector<int>& lcoords = limb_coord_list[joint];
  const int nl = static_cast<int>(lcoords.size());
  if (ns < 2 || nl < 1 || nl > kMaxLimbCoords) return false;
  for (int l = 0; l < nl; ++l) llocal[lcoords[l]] = l;
  lsaved = predicted;
  struct Restore {  // llocal back to all -1 and the predictions back, on every return
    Impl& s;
    const std::vector<int>& c;
    ~Restore() {
      for (int i : c) s.llocal[i] = -1;
      s.predicted = s.lsaved;
      s.lrelabel = false;
    }
  } restore{*this, lcoords};
  lrelabel = relabel;  // LimbAssign's; cleared on every return (Restore)
  // Candidates: the points no marker took (the limb's labelled markers keep theirs).
  std::fill(ltaken.begin(), ltaken.begin() + np, 0);
  for (int m = 0; m < nm; ++m)
    if (row_to_col[m] >= 0) ltaken[row_to_col[m]] = 1;
  int current = 0;
  for (int m : rows) current += row_to_col[m] >= 0;
  if (LimbRelabels())
    for (int m : rows)
      if (row_to_col[m] >= 0) ltaken[row_to_col[m]] = 0;
  int nc = 0;
  for (int k = 0; k < np; ++k)
    if (!ltaken[k]) lcand[nc++] = k;
  if ((nc == 0 || current == ns) && !place) return false;

  // The unheld angles (below) may pass the model's ranges by kLimbRangeSlack (see there); the
  // filter brings them back (Wrap) and the markers' offsets learn the difference.
  // Only the limb's coordinates: the others are lz0's, which the filter has wrapped already.
  auto WrapLimb = [&](Eigen::VectorXd* zz) {
    const auto& co = model->coordinates();
    for (int i : lcoords) {
      if (wraps[i]) {
        (*zz)[i] = std::remainder((*zz)[i], 2 * M_PI);
      } else {
        const double slack = freec[i] && lunanchored[i] ? kLimbRangeSlack : 0.0;
        (*zz)[i] = std::clamp((*zz)[i], co[i].min_value - slack, co[i].max_value + slack);
      }
    }
  };
  double prior_scale = 1.0;  // the prior's weight (Refine)
  auto Cost = [&](const Eigen::VectorXd& zz) {
    ForwardKinematics(*model, geometry, zz, limb_joint_list[joint], &data);
    double c = 0;
    for (int m : rows)
      if (lassign[m] >= 0)
        c += (MarkerPosition(*model, geometry, data, m) +
              data.segment_rotation[model->markers()[m].segment] * offset[m] -
              points.col(lassign[m]))
                 .squaredNorm();
    for (int i : lcoords)
      c += prior_scale * SearchPrior(i) * (zz[i] - lstart[i]) * (zz[i] - lstart[i]);
    return c;
  };
  // Cost at the pose the last LineariseLimb placed (lz): from its predictions, without placing
  // the limb again.
  auto CostAtLinearisation = [&]() {
    double c = 0;
    for (int m : rows)
      if (lassign[m] >= 0) c += (predicted.col(m) - points.col(lassign[m])).squaredNorm();
    for (int i : lcoords)
      c += prior_scale * SearchPrior(i) * (lz[i] - lstart[i]) * (lz[i] - lstart[i]);
    return c;
  };
  // Damped Gauss-Newton from lz with the prior centred at lstart: kLimbIterations steps
  // reassigning by distance (the radius shrinking to kLimbFinalRadius); or, holding lheld (an
  // exchange, below), kLimbIterations steps on those labels with the prior barely pulling, then
  // as many reassigning at the final radius with the prior centred at the held pose.
  auto Refine = [&](bool holding_pair) {
    double lambda = 1e-3;
    prior_scale = holding_pair ? 0.01 : 1.0;
    for (int it = 0; it < (holding_pair ? 2 : 1) * kLimbIterations; ++it) {
      const bool holding = holding_pair && it < kLimbIterations;
      if (holding_pair && it == kLimbIterations) {
        lstart = lz;
        prior_scale = 1.0;
        lambda = 1e-3;
      }
      if (holding) {
        LineariseLimb(joint, lz);
        for (int m : rows) lassign[m] = lheld[m];
      } else {
        LimbAssign(joint, lz, nc,
                   holding_pair ? kLimbFinalRadius : std::max(kLimbFinalRadius, 0.15 - 0.01 * it));
      }
      lN.setZero(nl, nl);
      lg.setZero(nl);
      for (int m : rows) {
        if (lassign[m] < 0) continue;
        const Eigen::Vector3d r = predicted.col(m) - points.col(lassign[m]);
        const std::vector<int>& cols = model->marker_coordinates(m);
        const auto& J = jac[m];
        for (size_t a = 0; a < cols.size(); ++a) {
          const int la = llocal[cols[a]];
          if (la < 0) continue;
          lg[la] += J.col(a).dot(r);
          for (size_t k = 0; k < cols.size(); ++k)
            if (llocal[cols[k]] >= 0) lN(la, llocal[cols[k]]) += J.col(a).dot(J.col(k));
        }
      }
      for (int l = 0; l < nl; ++l) {
        const int i = lcoords[l];
        const double w = prior_scale * SearchPrior(i);
        lN(l, l) += w;
        lg[l] += w * (lz[i] - lstart[i]);
      }
      const bool accepted = DampedGaussNewtonStep(lN, lg, CostAtLinearisation(), &lambda, &lNd, &lllt, &lstep, [&] {
        ltrial = lz;
        for (int l = 0; l < nl; ++l) ltrial[lcoords[l]] += lstep[l];
        WrapLimb(&ltrial);
        return Cost(ltrial);
      });
      if (accepted) lz = ltrial;
    }
  };
  // The final assignment at lz: its truncated score, labels and sum of squared distances.
  auto Score = [&](int* labelled, double* sum) {
    const double score = LimbAssign(joint, lz, nc, kLimbFinalRadius);
    *labelled = 0;
    *sum = 0;
    for (int m : rows)
      if (lassign[m] >= 0) {
        ++*labelled;
        *sum += (points.col(lassign[m]) - predicted.col(m)).squaredNorm();
      }
    return score;
  };
  lz0 = x.head(nz);
  // The rest of the body, placed once: the search moves only the limb's coordinates, and places
  // only what they move (limb_joint_list).
  ForwardKinematics(*model, geometry, lz0, &data);
  std::mt19937 rng(777);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  const int starts = 5;
  // In a limb searched for a marker whose own limb has no label (`unheld`: AnchoredLimb), a
  // joint whose subtree has no labelled marker has no angle to start near: its prediction is
  // the prior's. Its angles' later starts then span their ranges (a quarter, half and three
  // quarters): an elbow flexed 90 degrees puts the wrist markers 35 cm from where the hanging arm
  // of the static pose predicts them, beyond what a search from the near poses can pull in.
  // Not for a limb some of whose markers are labelled (a hand whose finger marker is hidden:
  // started across their ranges, and past them, the wrist angles of simulated seed 10 at 8
  // ghosts settled on ghosts, 0.990 -> 0.939).
  for (int l = 0; l < nl; ++l) {
    const int i = lcoords[l];
    bool held = false;
    for (int a : limb_markers[model->coordinates()[i].joint]) held |= row_to_col[a] >= 0;
    lunanchored[i] = unheld && !held;
  }
  double best = std::numeric_limits<double>::infinity(), runner_up = best;
  int best_labelled = 0;
  double best_sum = 0;
  for (int v = 0; v < starts; ++v) {
    lstart = lz0;
    for (int i = 0; i < nz; ++i) {
      if (!freec[i] || !rotational[i]) continue;
      const Coordinate& co = model->coordinates()[i];
      if (v == 1) {
        lstart[i] = z_static[i];  // the prior's mode: a limb lost far from its pose
      } else if (lunanchored[i] && v >= 2) {
        if (co.max_value - co.min_value < 2 * M_PI)
          lstart[i] = co.min_value + 0.25 * (v - 1) * (co.max_value - co.min_value);
      } else if (v == 2) {
        if (co.max_value - co.min_value < 2 * M_PI)
          lstart[i] += 0.5 * (0.5 * (co.min_value + co.max_value) - lstart[i]);
      } else if (v > 2) {
        lstart[i] += options.init_variant_rad * u(rng);
      }
    }
    Wrap(&lstart);
    lz = lstart;
    Refine(false);
    int labelled = 0;
    double sum = 0;
    const double score = Score(&labelled, &sum);
    int differ = 0;
    if (std::isfinite(best))
      for (int m : rows) differ += lassign[m] != lbest_assign[m];
    if (score < best) {
      if (differ >= 2) runner_up = best;
      best = score;
      best_labelled = labelled;
      best_sum = sum;
      lbest = lz;
      for (int m : rows) lbest_assign[m] = lassign[m];
    } else if (differ >= 2) {
      runner_up = std::min(runner_up, score);
    }
  }
  if (best_labelled < current || (best_labelled == current && !place)) return false;
  if (!(best_sum <= kLimbMaxRms * kLimbMaxRms * best_labelled)) return false;
  // Exchanges, as the initialisation's (ExchangeLabels): every start assigns by distance from
  // where its pose puts the markers, so all can settle with two neighbours each on the other's
  // point when only a large turn makes the right pairing the nearer one (welk007's wrist markers
  // on radius and ulna, the forearm pronated past the end of its range). Each pair of the
  // placement's new labels (a label it keeps is not its decision) on points within
  // kExchangeRadius is exchanged, held while the limb follows, released; one that labels as many
  // at a lower score is the placement. Only for a placement that would be taken otherwise: each
  // exchange costs about what two starts do.
  for (int pass = 0; pass < 2; ++pass) {
    bool improved = false;
    for (int ia = 0; ia < ns; ++ia)
      for (int ib = ia + 1; ib < ns; ++ib) {
        const int a = rows[ia], b = rows[ib], pa = lbest_assign[a], pb = lbest_assign[b];
        if (pa < 0 || pb < 0 || pa == row_to_col[a] || pb == row_to_col[b] ||
            (points.col(pa) - points.col(pb)).squaredNorm() > kExchangeRadius * kExchangeRadius)
          continue;
        for (int m : rows) lheld[m] = lbest_assign[m];
        std::swap(lheld[a], lheld[b]);
        lstart = lbest;
        lz = lbest;
        Refine(true);
        int labelled = 0;
        double sum = 0;
        const double score = Score(&labelled, &sum);
        bool differs = false;
        for (int m : rows) differs |= lassign[m] != lbest_assign[m];
        if (labelled >= best_labelled && score < best && differs) {
          best = score;
          best_labelled = labelled;
          best_sum = sum;
          lbest = lz;
          for (int m : rows) lbest_assign[m] = lassign[m];
          improved = true;
        }
      }
    if (!improved) break;
  }
  const double rms = std::sqrt(best_sum / best_labelled);
  if (!(rms <= kLimbMaxRms)) return false;
  // Every label the placement gives (a marker on a point it did not hold) within its own gate on
  // the measurement noise alone (what it would be gated with once the limb's covariance has
  // shrunk again): an RMS within kLimbMaxRms also passes a placement that puts one marker on a
  // ghost 3 cm away. A label the placement keeps is not its decision, and is not held to that
  // gate: while a limb sat in a wrong pose, the marker that kept it there learnt the pose's error
  // as its offset (a heel marker holding a turned foot alone, 49.5 mm of offset), so its predicted
  // place in the right pose is that far from its own point; gated, it refused the very placement
  // that mends the limb (seed 24: 50 of its 63 refused searches, the toe left unlabelled for
  // seconds). Kept labels count in the RMS above.
  LineariseLimb(joint, lbest);
  // A re-check's moved label is allowed its learnt offset besides: that was learnt on the wrong
  // point (seed 13 at 50 Hz: RWRA's 12 mm, on RWRB's point; gated without it, 20-22 mm from its
  // place, the placement that mended the forearm was refused for 50 frames).
  for (int m : rows) {
    if (lbest_assign[m] < 0 || lbest_assign[m] == row_to_col[m]) continue;
    const double tol = std::sqrt(options.gate_chi2 * MeasurementVariance(m)) +
                       (relabel && row_to_col[m] >= 0 ? offset[m].norm() : 0.0);
    if ((points.col(lbest_assign[m]) - predicted.col(m)).squaredNorm() > tol * tol)
      return false;
  }
  // Probation, as for a label the gates give: the placement replaces the limb's coordinates at
  // once, so a new label on a point that appeared in this frame would move the limb onto a
  // single-frame reflection at full trust, which the gates' labels never do (a label on a point
  // new this frame is measured only from its second frame). So every label the placement gives
  // (a hidden marker's, or one moved to another point) must be on a point the last frame had:
  // the search runs again when it is due (simulated seed 10 at 8 ghosts, true model: in the fresh
  // track the search moved RWRA to a reflection born in that frame, 63 mm from it, and RWRB
  // onto RWRA's point; the forearm turned 7 cm and RWRB held RWRA's point for 51 frames). Only
  // where the marker moves slowly enough for its point to be followed from frame to frame (as in
  // UnpinnedMarkerWithoutPast): at 12.5 Hz a swinging foot's point is new in every frame, and
  // refused so, EkfTracker.LearntProcessNoiseLabelsALowFrameRate went 276 -> 302 wrong labels.
  for (int m : rows)
    if (lbest_assign[m] >= 0 && lbest_assign[m] != row_to_col[m] && Followable(m) &&
        NewThisFrame(lbest_assign[m]))
      return false;
  // A new label on a point that has been around without keeping its distance to the marker's
  // joint centre is a lasting ghost (a lone finger marker's two angles fit any point at the right
  // distance from the wrist).
  // The labels the placement gives: new ones, and in a fresh track (which may relabel) moved ones.
  int given = 0;
  for (int m : rows) given += lbest_assign[m] >= 0 && lbest_assign[m] != row_to_col[m];
  // In a re-check the joint centres below the limb's own were placed by the labels in doubt (a
  // hand's wrist centre by a forearm turned one marker round), so a past measured from them
  // says nothing (as in a fresh track, whose centres may all be wrong).
  auto centre_in_doubt = [&](int m) {
    return relabel && model->segments()[model->markers()[m].segment].joint != joint;
  };
  for (int m : rows)
    if (lbest_assign[m] >= 0 && row_to_col[m] < 0 &&
        ((!centre_in_doubt(m) && NonRigidTrack(m, points.col(lbest_assign[m]))) ||
         SeenBeside(m, lbest_assign[m], np) ||
         (given == 1 && UnpinnedMarkerWithoutPast(m, lbest_assign[m], lbest_assign))))
      return false;
  // A re-check's moved label on a point no marker held is judged by that point's past as a new
  // one is (its seen-beside record is the wrong label's: the point was seen beside the marker
  // measured on another point, the very label in doubt).
  if (relabel)
    for (int m : rows) {
      const int k = lbest_assign[m];
      if (k < 0 || row_to_col[m] < 0 || k == row_to_col[m]) continue;
      bool held = false;
      for (int a : rows) held |= row_to_col[a] == k;
      if (!held && !centre_in_doubt(m) && NonRigidTrack(m, points.col(k))) return false;
    }
  const double variance = std::max(rms * rms / 3.0, 1e-6);
  if (std::isfinite(runner_up) && runner_up - best < options.init_ambiguity_margin * variance)
    return false;
  // Accept: the limb's coordinates at rest at the found pose, their covariance reset. A
  // re-check's moved markers held wrong points: their records go (PushHistory).
  if (relabel)
    for (int m : rows) {
      relabelled[m] = row_to_col[m] >= 0 && lbest_assign[m] != row_to_col[m];
      if (relabelled[m]) offset[m].setZero();
    }
  for (int i = 0; i < nz; ++i) {
    if (!freec[i]) continue;
    const bool r = rotational[i];
    const double s[3] = {
        r ? options.init_sigma_rotational : options.init_sigma_translational,
        r ? options.init_sigma_velocity_rotational : options.init_sigma_velocity_translational,
        r ? options.init_sigma_acceleration_rotational
          : options.init_sigma_acceleration_translational};
    x[i] = lbest[i];
    x[nz + i] = 0;
    x[2 * nz + i] = 0;
    for (int blk = 0; blk < 3; ++blk) {
      const int idx = blk * nz + i;
      P.row(idx).setZero();
      P.col(idx).setZero();
      P(idx, idx) = s[blk] * s[blk];
    }
  }
  return true;
}

// Whether point k has no point of the last tracking frame within a frame's motion (kTrackStep):
// a point that appeared in this frame. Without a last frame (the first after a start or a bad
// frame) nothing is known to be new.
bool Tracker::Impl::NewThisFrame(int k) const {
  if (prev_np == 0) return false;
  for (int j = 0; j < prev_np; ++j)
    if ((prev_points.col(j) - points.col(k)).squaredNorm() < kTrackStep * kTrackStep) return false;
  return true;
}

// Whether the limb search's one new label, marker m on point k, is one its segment does not pin
// -- fewer than three of its mates labelled by the placement, the segment registration's standard
// (RegisterSegments) -- and point k has no past that moved rigidly with the segment
// (RigidWithSegment). Such a segment (a hand with its finger marker; a foot whose heel marker is
// hidden; a foot whose heel marker is labelled, turning about the line from the ankle centre to
// the heel) turns to put its marker on any point at the marker's distances from the centre and
// the mates, so the placement is no evidence that the point is the marker: a reflection that
// appeared beside the hidden finger marker at its 20th hidden frame was taken for it (seed 50, 8
// ghosts: 103 frames; seeds 15 and 47 likewise); with the heel marker hidden, the foot was turned
// to put RTOE on a reflection 55 mm from its prediction, 62 mm from its own point, for 69 frames
// (seed 21, 8 ghosts; seed 4's LTOE likewise, 8 frames); with the heel marker labelled, the foot
// was turned about it to put LTOE on a reflection riding with the shank, 71 mm from its
// prediction, for 106 frames (seed 33, 8 ghosts, the true model; only the marker alone on its
// segment was held to this before the twenty-second session). Where the placement also gives its
// parent limb new labels (a forearm placed anew), the past's joint centres were the wrong pose's
// and say nothing; so too where it moves another of the limb's labels (in a fresh track, which
// may relabel): two labels placed together are held by their mutual distance.
// In a fresh track, whose joint centres may be wrong with the limb, only a STILL past counts
// against the point: followed for 5 frames and moved less than 2 cm. There the subject stands
// still (the static start), and a reflection fixed in the lab is as still as the marker's own
// point would be, so the placement's one new label on it is a guess between the two, made by
// the prior on the limb's angles: left empty, it waits for a point that moves with the segment
// or comes back inside its gate (simulated seeds 93 and 101 at 8 ghosts, the true model: a
// toe marker hidden in the static, the foot turned onto a reflection 145-163 mm off, 65 and
// 378 frames). A past too short or not rigid is not judged there (the centres may be wrong).
// With one or two mates, a past too short to judge counts against the point only where the
// marker moves slowly enough for its point to be followed at all (at 12.5 Hz none is, and the
// mates' distances are some evidence); alone on its segment, the placement has no other
// evidence, and a point without a rigid past is refused at any rate.
// Its cost: a finger marker whose own offset or forearm is wrong is not placed again until its
// point moves 2 cm rigidly with the predicted wrist (seed 47 at 5 ghosts, its offset learnt on a
// reflection: 0.9926 -> 0.9815; seed 10 at 8 ghosts, its forearm mirrored from its start: 0.990
// -> 0.969). A limb search whose evidence is over frames, not one, would need neither.

bool Tracker::Impl::UnpinnedMarkerWithoutPast(int m, int k, const std::vector<int>& placement) const {
  int mates = 0;
  for (int a : segment_markers[model->markers()[m].segment]) mates += a != m && placement[a] >= 0;
  if (mates >= kPinningMates) return false;
  const PastWithSegment past = SegmentPast(m, k);
  if (FreshTrack()) return past == PastWithSegment::kStill;
  if (mates == 0) return past != PastWithSegment::kRigid;
  return Followable(m) ? past != PastWithSegment::kRigid
                       : past == PastWithSegment::kNotRigid || past == PastWithSegment::kStill;
}

// Whether marker m's predicted speed moves it less than PastPoint's kTrackStep a frame, so that
// its point can be followed from frame to frame (jac is the placement's, LineariseLimb).
bool Tracker::Impl::Followable(int m) const {
  Eigen::Vector3d velocity = Eigen::Vector3d::Zero();
  const std::vector<int>& cols = model->marker_coordinates(m);
  for (size_t a = 0; a < cols.size(); ++a) velocity += jac[m].col(a) * x[nz + cols[a]];
  return velocity.norm() * frame_dt < kTrackStep;
}

// Whether point k could be marker m with m's segment anywhere: within kLimbNearRadius of its
// prediction, and at m's distance from the segment's other labelled markers and from its joint
// centre (rigid-body distances, whatever the pose). Ghosts near the body are nearly always within
// the radius; few also sit on these spheres, so a hidden marker rarely sets off a search.
bool Tracker::Impl::RigidlyPlausible(int m, int k, bool anywhere, int except) const {
  const Eigen::Vector3d p = points.col(k), pm = predicted.col(m);
  if (!anywhere && (p - pm).squaredNorm() >= kLimbNearRadius * kLimbNearRadius) return false;
  const int segment = model->markers()[m].segment;
  const double var_m = MeasurementVariance(m);
  // The joint centre is predicted, not measured: allow for the parent's pose and for a nominal
  // model's joint centres.
  const Eigen::Vector3d centre = data.segment_position[segment];
  if (std::abs((p - centre).norm() - (pm - centre).norm()) >
      std::sqrt(options.gate_chi2 * var_m) + kLimbCentreTolerance)
    return false;
  for (int a = 0; a < nm; ++a) {
    if (a == m || a == except || row_to_col[a] < 0 || model->markers()[a].segment != segment)
      continue;
    const double tol = std::sqrt(options.gate_chi2 * (var_m + MeasurementVariance(a)));
    if (std::abs((p - points.col(row_to_col[a])).norm() - (pm - predicted.col(a)).norm()) > tol)
      return false;
  }
  return true;
}

int Tracker::Impl::AnchoredLimb(int m) const {
  int j = marker_limb[m];
  if (j <= 0) return j;
  for (;;) {
    bool anchored = false;
    for (int a : limb_markers[j]) anchored |= row_to_col[a] >= 0;
    if (anchored) return j;
    const int parent = model->joints()[j].parent;
    const int up = parent >= 0 ? model->segments()[parent].joint : -1;
    if (up <= 0 || static_cast<int>(limb_coord_list[up].size()) > kMaxLimbCoords) return j;
    j = up;
  }
}

void Tracker::Impl::Reacquire(int np) {
  ++tracked_frames;
  const int limb_frames = std::max(2, static_cast<int>(std::lround(kLimbSeconds * options.rate_hz)));
  for (int m = 0; m < nm; ++m) {
    unlabelled_run[m] = row_to_col[m] < 0 ? unlabelled_run[m] + 1 : 0;
    if (row_to_col[m] < 0)
      ++stuck_run[m];
    else if (labelled_run[m] >= 2)
      stuck_run[m] = 0;
  }
  // One search per frame: the largest limb (nearest the root) among those due, and only when an
  // unclaimed point lies near the marker's prediction -- or, for a marker whose limb has no
  // label (no prediction to be near), anywhere at its distance from its joint centre (a hidden
  // marker costs nothing).
  int joint = -1;
  bool unheld = false;  // the limb searched is one with no label (AnchoredLimb)
  bool claimed_known = false;
  for (int m = 0; m < nm; ++m) {
    const int run = unlabelled_run[m];
    // Every limb_frames of a run; and every frame for a marker the start did not label (run ==
    // tracked_frames), until it is limb_frames old: it has no gate that could bring it back, so
    // waiting for one only leaves it unlabelled (welk007's forearms, flexed away from the static
    // pose, 20 frames of 6 markers).
    const bool due = run >= limb_frames ? run % limb_frames == 0 : run == tracked_frames;
    if (!due || marker_limb[m] < 0) continue;
    if (!claimed_known) {
      std::fill(ltaken.begin(), ltaken.begin() + np, 0);
      for (int k = 0; k < nm; ++k)
        if (row_to_col[k] >= 0) ltaken[row_to_col[k]] = 1;
      claimed_known = true;
    }
    const int limb = AnchoredLimb(m);
    bool unanchored = true;
    for (int a : limb_markers[marker_limb[m]]) unanchored &= row_to_col[a] < 0;
    bool near = false;
    for (int k = 0; k < np && !near; ++k)
      near = !ltaken[k] && ((FreshTrack() && (points.col(k) - predicted.col(m)).squaredNorm() <
                                                 kLimbNearRadius * kLimbNearRadius) ||
                            RigidlyPlausible(m, k, unanchored));
    if (!near) continue;
    if (joint < 0 || limb < joint) {  // parents come first
      joint = limb;
      unheld = unanchored;
    } else if (limb == joint) {
      unheld |= unanchored;
    }
  }
  // A label outside its gate (the segment registration's) is not measured: its limb is placed
  // anew once the label is out of probation (its second frame: a point that moved as the segment
  // did, not a one-frame reflection) and every limb_frames after, until it is inside.
  bool place = false;
  for (int m = 0; m < nm; ++m) {
    if (!beyond_gate[m] || marker_limb[m] < 0 || labelled_run[m] < 2 || (labelled_run[m] - 2) % limb_frames != 0)
      continue;
    place = true;
    if (joint < 0 || marker_limb[m] < joint) {  // parents come first
      joint = marker_limb[m];
      unheld = false;
    }
  }
  // A re-check searches its limb with the labels free, which places its unlabelled markers too:
  // it goes before a search of the same limb or one below it (the finger marker the shifted
  // labels left without a point is due for its own search every limb_frames), and takes turns
  // with a search of another limb (on a cadence that can coincide with the re-check's, it would
  // wait for good: seed 13 at 50 Hz, the left hand's).
  if (!place) {
    const int doubt = LimbLabelsInDoubt(np);
    bool within = joint < 0 || recheck_waited;
    if (doubt >= 0)
      for (int j : limb_joint_list[doubt]) within |= j == joint;
    if (doubt >= 0) recheck_waited = !within;
    if (doubt >= 0 && within) {
      ReacquireLimb(doubt, np, false, false, true);
      return;
    }
  }
  if (joint >= 0) ReacquireLimb(joint, np, place, unheld);
}

// The evidence that a limb is labelled wrongly but consistently: a marker stuck for kStuckFrames
// whose point, by the rigid geometry, is one that another marker of its limb holds -- within
// kLimbNearRadius of its prediction, at its distance from its joint centre and from its
// segment's other labelled markers (the holder left out). Stuck counts the frames since the
// marker last held a label past its first frame (stuck_run): a label the next frame takes back
// was a guess, not the marker found. Looked at every kMinTrackFrames of the run (every
// limb_frames where that is fewer, at 50 Hz and below), not every limb_frames: the spare point
// below is judged by a 5-frame past, and a check 20 frames apart let a crossed pair stand up to
// 20 frames after that past said so. Simulated seed 159 at 8 ghosts: LWRB on LWRA's point from
// frame 9427, the spare points back at 9451-9453 but standing still (no evidence) until ~9460;
// a one-frame label at 9459 had restarted LWRA's run, the next check was due at 9479, and LWRB
// let the point go on its own at 9473 (46 frames); now the placement is taken at 9464 (38).
// The limb is then searched as a fresh track's is, its labels free (ReacquireLimb, relabel), and
// the placement is taken only on the search's own terms: more of the limb labelled, every label
// it gives within its gate on the measurement noise, no differently labelling start within the
// margin. A hidden marker whose segment-mates hold their own points meets the test only where
// they stand at its distances, which a right labelling's mates do not.
int Tracker::Impl::LimbLabelsInDoubt(int np) const {
  if (FreshTrack()) return -1;
  const int limb_frames = std::max(2, static_cast<int>(std::lround(kLimbSeconds * options.rate_hz)));
  const int cadence = std::min(limb_frames, kMinTrackFrames);
  int joint = -1;
  for (int m = 0; m < nm; ++m) {
    const int run = stuck_run[m], limb = marker_limb[m];
    if (run < kStuckFrames || run % cadence != 0 || limb < 0 || !seen[m]) continue;
    if (joint >= 0 && limb >= joint) continue;  // parents first
    bool doubt = false;
    for (int a : limb_markers[limb]) {
      const int k = row_to_col[a];
      if (a == m || k < 0 || k >= np) continue;
      if (RigidlyPlausible(m, k, false, a)) {
        doubt = true;
        break;
      }
    }
    if (!doubt) continue;
    // And a point no marker holds that has moved rigidly with one of the limb's segments: the
    // marker the shifted labels left without its own point (the finger marker's, its label on a
    // wrist point). Without it the re-check cannot label more of the limb than the track does.
    bool spare = false;
    for (int k = 0; k < np && !spare; ++k) {
      bool claimed = false;
      for (int a = 0; a < nm && !claimed; ++a) claimed = row_to_col[a] == k;
      if (claimed) continue;
      for (int a : limb_markers[limb])
        if ((points.col(k) - predicted.col(a)).squaredNorm() < kLimbNearRadius * kLimbNearRadius &&
            SegmentPast(a, k) == PastWithSegment::kRigid) {
          spare = true;
          break;
        }
    }
    if (spare) joint = limb;
  }
  return joint;
}

}  // namespace mocap::ekf
