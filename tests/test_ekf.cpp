// The real-time tracker (ekf/): its linear algebra against the dense textbook formulas, the
// optimal assignment against brute force, and tracking of the simulated protocol (sim/) against
// the truth: each frame's true marker positions are shuffled into unlabelled points (plus ghosts
// and NaNs) and the permutation is the label truth.
#include <gtest/gtest.h>

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <algorithm>
#include <atomic>
#include <cstdlib>
#include <new>
#include <cmath>
#include <cstdio>
#include <functional>
#include <memory>
#include <numeric>
#include <random>

#include "ekf/assignment.h"
#include "ekf/filter.h"
#include "ekf/tracker.h"
#include "ekf/tracker_impl.h"
#include "model/kinematics.h"
#include "sim/simulate.h"
#include "tests/allocation_test_util.h"
#include "tests/model_test_util.h"

using namespace mocap;

namespace {

constexpr double kDeg = M_PI / 180.0;

Eigen::MatrixXd RandomSpd(int n, std::mt19937& rng, double scale = 1.0) {
  std::normal_distribution<double> g(0, 1);
  Eigen::MatrixXd a(n, n);
  for (int i = 0; i < a.size(); ++i) a.data()[i] = g(rng);
  return scale * (a * a.transpose() + 0.1 * Eigen::MatrixXd::Identity(n, n));
}

double MinEigenvalue(const Eigen::MatrixXd& p) {
  return Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd>(p, Eigen::EigenvaluesOnly).eigenvalues()[0];
}

// The simulated protocol at 200 Hz with 0.5 mm noise, built once.
const sim::SimulatedSession& Session() {
  static const sim::SimulatedSession* session = [] {
    auto* s = new sim::SimulatedSession;
    sim::SimulationOptions o;
    o.rate_hz = 200;
    o.noise_mm = 0.5;
    o.seed = 11;
    const Status st = sim::SimulateSession(o, s);
    if (!st.ok()) std::fprintf(stderr, "SimulateSession: %s\n", st.message().c_str());
    return s;
  }();
  return *session;
}

int TrialIndex(const std::string& name) {
  const auto& trials = Session().trials;
  for (size_t i = 0; i < trials.size(); ++i)
    if (trials[i].markers.name == name) return static_cast<int>(i);
  ADD_FAILURE() << "no trial " << name;
  return 0;
}

// One frame of unlabelled points and its label truth (per point: model marker or -1).
struct Frame {
  Eigen::Matrix3Xd points;
  std::vector<int> truth;
};

// A scene built from a trial: the markers present at frame f, optionally transformed, shuffled,
// with `ghosts` points inside the body's bounding box (grown by 10 cm) but at least
// `ghost_clearance` from every true marker, and `nans` NaN columns.
struct SceneOptions {
  int ghosts = 0;
  double ghost_clearance = 0.04;
  int nans = 0;
  std::function<bool(int frame, int marker)> drop;  // true: marker not seen
  // Extra points that are no marker (a lasting reflection), per frame: (frame, that frame's
  // marker positions) -> points.
  std::function<std::vector<Eigen::Vector3d>(int frame, const std::vector<Eigen::Vector3d>&)>
      reflections;
  std::function<Eigen::Vector3d(int frame, const Eigen::Vector3d&)> transform;
};

Frame MakeFrame(const formats::MarkerTrial& trial, int f, const SceneOptions& o, std::mt19937& rng) {
  const int nm = trial.num_markers();
  std::vector<Eigen::Vector3d> pts;
  std::vector<int> truth;
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(1e9), hi = -lo;
  std::vector<Eigen::Vector3d> all;
  for (int m = 0; m < nm; ++m) {
    if (!trial.Has(f, m)) continue;
    Eigen::Vector3d p = trial.At(f, m);
    if (o.transform) p = o.transform(f, p);
    all.push_back(p);
    lo = lo.cwiseMin(p);
    hi = hi.cwiseMax(p);
    if (o.drop && o.drop(f, m)) continue;
    pts.push_back(p);
    truth.push_back(m);
  }
  if (o.reflections) {
    std::vector<Eigen::Vector3d> markers(nm, Eigen::Vector3d::Constant(std::nan("")));
    for (int m = 0; m < nm; ++m)
      if (trial.Has(f, m)) markers[m] = trial.At(f, m);
    for (const Eigen::Vector3d& p : o.reflections(f, markers)) {
      pts.push_back(p);
      truth.push_back(-1);
    }
  }
  lo.array() -= 0.1;
  hi.array() += 0.1;
  std::uniform_real_distribution<double> u(0, 1);
  for (int g = 0; g < o.ghosts; ++g) {
    for (int tries = 0; tries < 1000; ++tries) {
      const Eigen::Vector3d p = lo + (hi - lo).cwiseProduct(Eigen::Vector3d(u(rng), u(rng), u(rng)));
      bool clear = true;
      for (const auto& q : all) clear = clear && (p - q).norm() >= o.ghost_clearance;
      if (!clear) continue;
      pts.push_back(p);
      truth.push_back(-1);
      break;
    }
  }
  for (int k = 0; k < o.nans; ++k) {
    pts.push_back(Eigen::Vector3d::Constant(std::numeric_limits<double>::quiet_NaN()));
    truth.push_back(-1);
  }
  std::vector<int> order(pts.size());
  std::iota(order.begin(), order.end(), 0);
  std::shuffle(order.begin(), order.end(), rng);
  Frame fr;
  fr.points.resize(3, pts.size());
  fr.truth.resize(pts.size());
  for (size_t k = 0; k < order.size(); ++k) {
    fr.points.col(k) = pts[order[k]];
    fr.truth[k] = truth[order[k]];
  }
  return fr;
}

// Label and angle statistics of a tracked run.
struct RunStats {
  long marker_points = 0;   // true marker points seen while tracking
  long correct = 0;         // of those, labelled with their marker
  long wrong = 0;           // points given a wrong marker (including ghosts given one)
  long ghosts = 0, ghosts_labelled = 0;
  long tracked_frames = 0, frames = 0;
  int reinitialisations = 0;
  int first_tracked = -1;
  double angle_sq = 0;
  long angle_n = 0;
  double max_asymmetry = 0;
  double min_eigenvalue = 1e300;
  double accuracy() const { return marker_points ? double(correct) / marker_points : 0.0; }
  double angle_rms_deg() const { return angle_n ? std::sqrt(angle_sq / angle_n) / kDeg : 1e9; }
};

void Score(const Frame& fr, const ekf::TrackOutput& out, RunStats* s) {
  for (size_t k = 0; k < fr.truth.size(); ++k) {
    const int t = fr.truth[k], l = out.marker_of_point[k];
    if (t >= 0) {
      ++s->marker_points;
      s->correct += l == t;
    } else if (std::isfinite(fr.points(0, k))) {
      ++s->ghosts;
      s->ghosts_labelled += l >= 0;
    }
    if (l >= 0 && l != t) ++s->wrong;
  }
}

// Rotational coordinates' error against the truth, wrapped.
void ScoreAngles(const Model& model, const Eigen::VectorXd& z, const Eigen::VectorXd& truth,
                 RunStats* s) {
  for (int c = 0; c < model.num_coordinates(); ++c) {
    if (!model.coordinates()[c].rotational) continue;
    const double e = std::remainder(z[c] - truth[c], 2 * M_PI);
    s->angle_sq += e * e;
    ++s->angle_n;
  }
}

// Tracks frames [begin, end) of a trial with a fresh tracker.
RunStats TrackRun(ekf::Tracker* tracker, const sim::SimulatedTrial& trial, const SceneOptions& scene,
             int begin, int end, unsigned seed, int settle_frames = 20,
             const std::function<void(int, ekf::Tracker*)>& hook = {}) {
  std::mt19937 rng(seed);
  RunStats s;
  const Model& model = tracker->model();
  for (int f = begin; f < end; ++f) {
    if (hook) hook(f, tracker);
    const Frame fr = MakeFrame(trial.markers, f, scene, rng);
    const ekf::TrackOutput& out = tracker->Update(trial.markers.times[f], fr.points);
    ++s.frames;
    s.reinitialisations += out.reinitialised;
    if (out.state != ekf::TrackState::kTracking) continue;
    if (s.first_tracked < 0) s.first_tracked = f;
    ++s.tracked_frames;
    Score(fr, out, &s);
    if (f >= s.first_tracked + settle_frames && !scene.transform)
      ScoreAngles(model, out.z, sim::TrueCoordinates(model, trial.coordinates, f), &s);
  }
  const Eigen::MatrixXd& P = tracker->covariance();
  s.max_asymmetry = (P - P.transpose()).cwiseAbs().maxCoeff();
  s.min_eigenvalue = MinEigenvalue(P);
  return s;
}

std::shared_ptr<const Model> Share(const Model& m) { return std::make_shared<const Model>(m); }

}  // namespace

// ---------------------------------------------------------------------------------------------
// Linear algebra

TEST(EkfAssignment, MatchesBruteForce) {
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> u(0, 10);
  std::bernoulli_distribution forbid(0.3);
  ekf::LinearAssignment lap;
  lap.Reserve(5, 8);
  for (int trial = 0; trial < 300; ++trial) {
    const int rows = 1 + trial % 5, cols = rows + trial % 4;
    Eigen::MatrixXd c(rows, cols);
    for (int i = 0; i < c.size(); ++i) c.data()[i] = forbid(rng) ? 1e9 : u(rng);
    // Brute force over injective maps rows -> cols.
    std::vector<int> perm(cols);
    std::iota(perm.begin(), perm.end(), 0);
    double best = 1e300;
    do {
      double s = 0;
      for (int r = 0; r < rows; ++r) s += c(r, perm[r]);
      best = std::min(best, s);
    } while (std::next_permutation(perm.begin(), perm.end()));
    std::vector<int> got(rows);
    const double total = lap.Solve(c, got.data());
    EXPECT_NEAR(total, best, 1e-9 * std::max(1.0, best)) << "case " << trial;
    std::vector<int> sorted = got;
    std::sort(sorted.begin(), sorted.end());
    EXPECT_EQ(std::unique(sorted.begin(), sorted.end()), sorted.end()) << "a column taken twice";
    double s = 0;
    for (int r = 0; r < rows; ++r) s += c(r, got[r]);
    EXPECT_NEAR(s, total, 1e-9 * std::max(1.0, total));
  }
}

TEST(EkfFilter, PredictionMatchesDenseConstantAccelerationModel) {
  std::mt19937 rng(4);
  const int nz = 4, n = 3 * nz;
  const double dt = 0.005;
  Eigen::VectorXd q(nz);
  q << 1e4, 2e3, 5e2, 1.0;
  Eigen::MatrixXd P = RandomSpd(n, rng);
  Eigen::VectorXd x = Eigen::VectorXd::Random(n);
  Eigen::MatrixXd F = Eigen::MatrixXd::Identity(n, n), Q = Eigen::MatrixXd::Zero(n, n);
  F.block(0, nz, nz, nz).diagonal().setConstant(dt);
  F.block(nz, 2 * nz, nz, nz).diagonal().setConstant(dt);
  F.block(0, 2 * nz, nz, nz).diagonal().setConstant(dt * dt / 2);
  Eigen::Matrix3d q1;
  q1 << std::pow(dt, 5) / 20, std::pow(dt, 4) / 8, std::pow(dt, 3) / 6,  //
      std::pow(dt, 4) / 8, std::pow(dt, 3) / 3, dt * dt / 2,               //
      std::pow(dt, 3) / 6, dt * dt / 2, dt;
  for (int i = 0; i < nz; ++i)
    for (int a = 0; a < 3; ++a)
      for (int b = 0; b < 3; ++b) Q(a * nz + i, b * nz + i) = q[i] * q1(a, b);
  const Eigen::VectorXd x_ref = F * x;
  const Eigen::MatrixXd P_ref = F * P * F.transpose() + Q;
  const Eigen::VectorXd x0 = x;
  const Eigen::MatrixXd P0 = P;
  ekf::PredictConstantAcceleration(dt, q, &x, &P);
  EXPECT_LT((x - x_ref).cwiseAbs().maxCoeff(), 1e-14);
  EXPECT_LT((P - P_ref).cwiseAbs().maxCoeff(), 1e-12 * P_ref.cwiseAbs().maxCoeff());
  // With decays: F = diag(1, beta, alpha) F.
  const double beta = 0.99, alpha = 0.95;
  Eigen::VectorXd d(n);
  d << Eigen::VectorXd::Ones(nz), Eigen::VectorXd::Constant(nz, beta), Eigen::VectorXd::Constant(nz, alpha);
  const Eigen::MatrixXd Fd = d.asDiagonal() * F;
  const Eigen::MatrixXd Pd_ref = Fd * P0 * Fd.transpose() + Q;
  x = x0;
  P = P0;
  ekf::PredictConstantAcceleration(dt, q, beta, alpha, &x, &P);
  EXPECT_LT((x - Fd * x0).cwiseAbs().maxCoeff(), 1e-14);
  EXPECT_LT((P - Pd_ref).cwiseAbs().maxCoeff(), 1e-12 * Pd_ref.cwiseAbs().maxCoeff());
}

// The information-form update equals the textbook Kalman update K = P H^T S^-1 with
// H = [J 0 0], and stays positive-definite where the textbook form does not.
TEST(EkfFilter, UpdateMatchesTextbookKalmanUpdate) {
  std::mt19937 rng(5);
  std::normal_distribution<double> g(0, 1);
  const int nz = 5, n = 3 * nz, nmeas = 9;
  for (int trial = 0; trial < 20; ++trial) {
    Eigen::MatrixXd P = RandomSpd(n, rng, 0.1);
    Eigen::VectorXd x = Eigen::VectorXd::Random(n);
    Eigen::MatrixXd J(nmeas, nz);
    for (int i = 0; i < J.size(); ++i) J.data()[i] = g(rng);
    if (trial % 2) J.col(trial % nz).setZero();  // a coordinate no measurement sees
    Eigen::VectorXd rinv(nmeas);
    for (int i = 0; i < nmeas; ++i) rinv[i] = 1.0 / (0.01 + 0.1 * std::abs(g(rng)));
    Eigen::VectorXd nu(nmeas);
    for (int i = 0; i < nmeas; ++i) nu[i] = g(rng);

    Eigen::MatrixXd H = Eigen::MatrixXd::Zero(nmeas, n);
    H.leftCols(nz) = J;
    const Eigen::MatrixXd S = H * P * H.transpose() + Eigen::MatrixXd(rinv.cwiseInverse().asDiagonal());
    const Eigen::MatrixXd K = P * H.transpose() * S.inverse();
    const Eigen::VectorXd x_ref = x + K * nu;
    const Eigen::MatrixXd P_ref = P - K * S * K.transpose();
    const double nis_ref = nu.dot(S.ldlt().solve(nu));

    const Eigen::MatrixXd A = J.transpose() * rinv.asDiagonal() * J;
    const Eigen::VectorXd b = J.transpose() * rinv.asDiagonal() * nu;
    const double nrn = nu.dot(rinv.asDiagonal() * nu);
    ekf::CoordinateUpdate update;
    update.Resize(nz);
    double nis = 0;
    ASSERT_TRUE(update.Apply(A, b, nrn, &x, &P, &nis));
    EXPECT_LT((x - x_ref).cwiseAbs().maxCoeff(), 1e-10) << trial;
    EXPECT_LT((P - P_ref).cwiseAbs().maxCoeff(), 1e-10) << trial;
    EXPECT_NEAR(nis, nis_ref, 1e-9 * nis_ref) << trial;
    EXPECT_EQ((P - P.transpose()).cwiseAbs().maxCoeff(), 0.0);
  }
  // Markers a million times more precise than the prediction, repeatedly: P stays symmetric
  // positive-definite.
  Eigen::MatrixXd P = RandomSpd(n, rng, 1.0);
  Eigen::VectorXd x = Eigen::VectorXd::Zero(n), q = Eigen::VectorXd::Constant(nz, 1e-6);
  ekf::CoordinateUpdate update;
  update.Resize(nz);
  for (int k = 0; k < 1000; ++k) {
    Eigen::MatrixXd J(nmeas, nz);
    for (int i = 0; i < J.size(); ++i) J.data()[i] = g(rng);
    const Eigen::MatrixXd A = 1e12 * J.transpose() * J;
    double nis;
    ASSERT_TRUE(update.Apply(A, Eigen::VectorXd::Zero(nz), 0.0, &x, &P, &nis)) << k;
    ekf::PredictConstantAcceleration(0.005, q, &x, &P);
  }
  EXPECT_EQ((P - P.transpose()).cwiseAbs().maxCoeff(), 0.0);
  EXPECT_GT(MinEigenvalue(P), 0.0);
}

TEST(EkfOptions, InvalidOptionsAreNamed) {
  ekf::TrackerOptions o;
  std::string error;
  EXPECT_TRUE(o.IsValid(&error));
  o.sigma_m = 0;
  EXPECT_FALSE(o.IsValid(&error));
  EXPECT_NE(error.find("sigma_m"), std::string::npos);
  o = ekf::TrackerOptions();
  o.gate_chi2 = -1;
  EXPECT_FALSE(o.IsValid(&error));
  EXPECT_NE(error.find("gate_chi2"), std::string::npos);
  o = ekf::TrackerOptions();
  o.min_process_noise_scale = 0;
  EXPECT_FALSE(o.IsValid(&error));
  EXPECT_NE(error.find("min_process_noise_scale"), std::string::npos);
  EXPECT_STREQ(ekf::ToString(ekf::TrackState::kLost), "lost");
}

// ---------------------------------------------------------------------------------------------
// Tracking the simulated protocol

TEST(EkfTracker, TracksTheProtocolWithTheTrueModel) {
  const auto& session = Session();
  ASSERT_FALSE(session.trials.empty());
  auto truth = Share(session.truth);
  RunStats total;
  SceneOptions scene;
  scene.ghosts = 5;
  scene.nans = 1;
  for (size_t t = 0; t < session.trials.size(); ++t) {
    const auto& trial = session.trials[t];
    ekf::Tracker tracker(truth);
    const RunStats s = TrackRun(&tracker, trial, scene, 0, trial.markers.num_frames(), 100 + t);
    std::printf("%-28s frames %5ld tracked from %3d  labels %.6f wrong %ld ghosts labelled %ld  "
                "angle RMS %.3f deg  reinit %d\n",
                trial.markers.name.c_str(), s.frames, s.first_tracked, s.accuracy(), s.wrong,
                s.ghosts_labelled, s.angle_rms_deg(), s.reinitialisations);
    EXPECT_EQ(s.first_tracked, 0) << trial.markers.name << ": not initialised on the first frame";
    EXPECT_EQ(s.reinitialisations, 1) << trial.markers.name;
    EXPECT_EQ(s.max_asymmetry, 0.0);
    EXPECT_GT(s.min_eigenvalue, 0.0);
    total.marker_points += s.marker_points;
    total.correct += s.correct;
    total.wrong += s.wrong;
    total.ghosts += s.ghosts;
    total.ghosts_labelled += s.ghosts_labelled;
    total.angle_sq += s.angle_sq;
    total.angle_n += s.angle_n;
  }
  std::printf("TRUE model: label accuracy %.6f (%ld/%ld), wrong %ld, ghosts labelled %ld/%ld, "
              "angle RMS %.3f deg\n",
              total.accuracy(), total.correct, total.marker_points, total.wrong,
              total.ghosts_labelled, total.ghosts, total.angle_rms_deg());
  EXPECT_GE(total.accuracy(), 0.9995);
  EXPECT_LE(total.angle_rms_deg(), 1.0);
  EXPECT_EQ(total.ghosts_labelled, 0);
}

TEST(EkfTracker, TracksTheProtocolWithTheNominalModel) {
  const auto& session = Session();
  auto nominal = Share(session.nominal);
  RunStats total;
  SceneOptions scene;
  scene.ghosts = 5;
  for (size_t t = 0; t < session.trials.size(); ++t) {
    const auto& trial = session.trials[t];
    ekf::Tracker tracker(nominal);
    const RunStats s = TrackRun(&tracker, trial, scene, 0, trial.markers.num_frames(), 200 + t);
    std::printf("%-28s tracked from %3d  labels %.6f wrong %ld ghosts labelled %ld  angle RMS "
                "%.3f deg  reinit %d\n",
                trial.markers.name.c_str(), s.first_tracked, s.accuracy(), s.wrong,
                s.ghosts_labelled, s.angle_rms_deg(), s.reinitialisations);
    EXPECT_EQ(s.first_tracked, 0) << trial.markers.name;
    EXPECT_EQ(s.reinitialisations, 1) << trial.markers.name;
    total.marker_points += s.marker_points;
    total.correct += s.correct;
    total.wrong += s.wrong;
    total.ghosts += s.ghosts;
    total.ghosts_labelled += s.ghosts_labelled;
    total.angle_sq += s.angle_sq;
    total.angle_n += s.angle_n;
  }
  std::printf("NOMINAL model: label accuracy %.6f (%ld/%ld), wrong %ld, ghosts labelled %ld/%ld, "
              "angle RMS %.3f deg\n",
              total.accuracy(), total.correct, total.marker_points, total.wrong,
              total.ghosts_labelled, total.ghosts, total.angle_rms_deg());
  EXPECT_GE(total.accuracy(), 0.9995);
  EXPECT_EQ(total.ghosts_labelled, 0);
}

// The simulator's own occlusions (5 % of the samples lost in gaps of 5-30 frames at random
// markers and times) with the nominal model: markers come and go, the labels stay right.
// Measured: 0.999993 of the labels, 34 wrong (all on ghosts) against at most 44. Disabled from
// when it was written until the sixteenth session: 69-73 ghosts labelled, 56 of them in the first
// second of a trial, where a fresh tracker's nominal-model gates are ~10 cm wide until the marker
// offsets are learnt and this scene's ghosts, new every frame anywhere in the body's box, fall
// into a returning marker's gate now and then. Of 1,376 first frames back, the 63 labels on a
// ghost had Mahalanobis d^2 1-222 (median 11), the 1,313 on the marker median 0.1: a returning
// marker's first-frame label on a point new in that frame is now reported only when the point is
// 95 % likely the marker rather than clutter (TrackerOptions::min_return_probability), and from
// its second frame otherwise.
TEST(EkfTracker, TracksThroughOcclusions) {
  sim::SimulatedSession session;
  sim::SimulationOptions o;
  o.rate_hz = 200;
  o.noise_mm = 0.5;
  o.missing = 0.05;
  o.seed = 13;
  ASSERT_TRUE(sim::SimulateSession(o, &session).ok());
  auto nominal = Share(session.nominal);
  RunStats total;
  SceneOptions scene;
  scene.ghosts = 5;
  for (size_t t = 0; t < session.trials.size(); ++t) {
    const auto& trial = session.trials[t];
    ekf::Tracker tracker(nominal);
    const RunStats s = TrackRun(&tracker, trial, scene, 0, trial.markers.num_frames(), 400 + t);
    std::printf("%-28s tracked from %3d  labels %.6f wrong %ld ghosts labelled %ld reinit %d\n",
                trial.markers.name.c_str(), s.first_tracked, s.accuracy(), s.wrong,
                s.ghosts_labelled, s.reinitialisations);
    EXPECT_LE(s.first_tracked, 2) << trial.markers.name;
    EXPECT_EQ(s.reinitialisations, 1) << trial.markers.name;
    total.marker_points += s.marker_points;
    total.correct += s.correct;
    total.wrong += s.wrong;
    total.ghosts_labelled += s.ghosts_labelled;
  }
  std::printf("occlusions, NOMINAL model: label accuracy %.6f (%ld/%ld), wrong %ld, ghosts "
              "labelled %ld\n",
              total.accuracy(), total.correct, total.marker_points, total.wrong,
              total.ghosts_labelled);
  EXPECT_GE(total.accuracy(), 0.9995);
  EXPECT_LE(total.wrong, total.marker_points / 10000);
}

// The simulated protocol at 12.5 Hz (the frame rate of biobuddy's functional trials), true
// model, 5 ghosts: the process noise learnt from the innovations (TrackerOptions::
// process_noise_time_constant_s) against the jerk PSDs as given, whose 83 ms steps make every
// limb's gate decimetres wide (tracker.h, "Process noise"). Measured: 0.898796 of the labels
// (1,149 wrong) with the bound's, 0.937666 (850 wrong) learnt. Seventeenth session, the loose
// segments labelled as rigid groups (tracker.h, "Rigid groups"): 0.910460 (496 wrong) with the
// bound's, 0.958580 (528 wrong) learnt. The bound's gates make every limb loose, and its groups
// leave what they cannot decide unlabelled rather than wrong: it now has fewer wrong labels than
// the learnt noise (which it had not before), and fewer right ones by 0.048 of the labels. So
// the learnt noise's wrong labels are held to what is reached, not to the bound's. With the limb
// search's period in seconds (0.1 s, at least 2 frames, instead of 20 frames: 1.6 s here) the
// learnt noise reaches 0.962355 (496 wrong); the bound's is unchanged. Eighteenth, a loose
// segment's gates centred where its fitted parent moved its joint centre: learnt 0.963375 (276
// wrong), the bound's 0.947936 (432 wrong) -- every limb of the bound's is loose, and it gained
// the most. The learnt noise is again the better on both counts, by 0.015 of the labels (0.03
// before: the bound's moved up) and 156 wrong labels.
TEST(EkfTracker, LearntProcessNoiseLabelsALowFrameRate) {
  sim::SimulatedSession session;
  sim::SimulationOptions o;
  o.rate_hz = 12.5;
  o.noise_mm = 0.5;
  o.seed = 11;
  ASSERT_TRUE(sim::SimulateSession(o, &session).ok());
  auto truth = Share(session.truth);
  SceneOptions scene;
  scene.ghosts = 5;
  RunStats total[3];
  // 0, 1: the bound's and the learnt noise at the model's own size (as measured above); 2: the
  // learnt noise scaled to the subject at the start (the default since the eighteenth session):
  // 0.963613 (185 wrong); the bound's is 0.938992 (397 wrong) so. With the loose segments' gates
  // moved with their parent's centre too (the same session): 0.963749, 186 wrong; with the scaled
  // start's offsets' prior no tighter than 1 cm (TryInitialise: the true model's 8-ghost seeds 63
  // and 78 lost 6 % of their labels at 2 mm) 0.959974, 145 wrong: fewer wrong, more left empty.
  for (int learnt : {0, 1, 2}) {
    ekf::TrackerOptions to;
    to.rate_hz = 12.5;
    if (!learnt) to.process_noise_time_constant_s = 0;
    if (learnt < 2) to.init_scale_to_subject = ekf::TrackerOptions::ScaleToSubject::kWhenTheModelDoesNotFit;
    for (size_t t = 0; t < session.trials.size(); ++t) {
      const auto& trial = session.trials[t];
      ekf::Tracker tracker(truth, to);
      const RunStats s = TrackRun(&tracker, trial, scene, 0, trial.markers.num_frames(), 500 + t, 2);
      total[learnt].marker_points += s.marker_points;
      total[learnt].correct += s.correct;
      total[learnt].wrong += s.wrong;
    }
    std::printf("12.5 Hz, %s: label accuracy %.6f (%ld/%ld), wrong %ld\n",
                learnt == 2 ? "learnt process noise, scaled" : learnt ? "learnt process noise" : "the bound's",
                total[learnt].accuracy(),
                total[learnt].correct, total[learnt].marker_points, total[learnt].wrong);
  }
  EXPECT_GE(total[1].accuracy(), 0.963);
  EXPECT_GT(total[1].accuracy(), total[0].accuracy() + 0.015);
  EXPECT_LE(total[1].wrong, 276);
  EXPECT_LT(total[1].wrong, total[0].wrong);
  EXPECT_GE(total[2].accuracy(), 0.9599);
  EXPECT_LE(total[2].wrong, 145);
}

// The subject in the static pose, turned to random headings and placed anywhere in the volume:
// the first frame finds the labels and the pose without any help.
TEST(EkfTracker, InitialisesFromTheStaticPoseFacingAnyDirection) {
  const auto& session = Session();
  const auto& trial = session.trials[TrialIndex("static")];
  std::mt19937 rng(21);
  std::uniform_real_distribution<double> heading(-M_PI, M_PI), place(-2.0, 2.0);
  for (const Model* model : {&session.nominal, &session.truth}) {
    auto shared = Share(*model);
    for (int k = 0; k < 8; ++k) {
      const Eigen::Matrix3d turn =
          Eigen::AngleAxisd(heading(rng), Eigen::Vector3d::UnitZ()).toRotationMatrix();
      const Eigen::Vector3d shift(place(rng), place(rng), 0.0);
      const Eigen::Vector3d pivot = trial.markers.At(0, 0);
      SceneOptions scene;
      scene.ghosts = 3;
      scene.transform = [&](int, const Eigen::Vector3d& p) { return turn * (p - pivot) + pivot + shift; };
      ekf::Tracker tracker(shared);
      const RunStats s = TrackRun(&tracker, trial, scene, 0, 100, 300 + k);
      EXPECT_EQ(s.first_tracked, 0) << (model == &session.nominal ? "nominal" : "truth") << " " << k;
      EXPECT_EQ(s.correct, s.marker_points) << k;
      EXPECT_EQ(s.wrong, 0) << k;
    }
  }
}

// A marker hidden for 20 frames (100 ms) is picked up again on its first frame back, and while it
// is away a ghost at 5 cm from where it would be is not given its label.
TEST(EkfTracker, PicksUpAMarkerAfterAGap) {
  const auto& session = Session();
  const auto& trial = session.trials[TrialIndex("shoulder_circles_l")];
  const Model& model = session.nominal;
  for (const char* name : {"LWRA", "LELB", "RKNE", "LFHD"}) {
    const int m = model.FindMarker(name);
    ASSERT_GE(m, 0) << name;
    const int gap_begin = 300, gap_end = 320;
    SceneOptions scene;
    scene.ghosts = 2;
    scene.drop = [&](int f, int marker) { return marker == m && f >= gap_begin && f < gap_end; };
    ekf::Tracker tracker(Share(model));
    std::mt19937 rng(4);
    for (int f = 0; f < 400; ++f) {
      const Frame fr = MakeFrame(trial.markers, f, scene, rng);
      const ekf::TrackOutput& out = tracker.Update(trial.markers.times[f], fr.points);
      ASSERT_EQ(out.state, ekf::TrackState::kTracking) << name << " frame " << f;
      if (f >= gap_begin && f < gap_end) {
        EXPECT_EQ(out.point_of_marker[m], -1) << name << " frame " << f;
      } else if (f >= gap_end) {
        ASSERT_GE(out.point_of_marker[m], 0) << name << " not picked up at frame " << f;
        EXPECT_EQ(fr.truth[out.point_of_marker[m]], m) << name << " frame " << f;
      }
    }
  }
}

TEST(EkfTracker, IgnoresNaNPointsAndLeavesGhostsNearTheBodyUnlabelled) {
  const auto& session = Session();
  const auto& trial = session.trials[TrialIndex("squats")];
  SceneOptions scene;
  scene.ghosts = 20;
  scene.ghost_clearance = 0.05;
  scene.nans = 6;
  ekf::Tracker tracker(Share(session.nominal));
  const RunStats s = TrackRun(&tracker, trial, scene, 0, trial.markers.num_frames(), 9);
  EXPECT_EQ(s.first_tracked, 0);
  EXPECT_EQ(s.tracked_frames, trial.markers.num_frames());
  EXPECT_EQ(s.ghosts, 20L * s.tracked_frames);  // every ghost was placed and scored
  EXPECT_EQ(s.ghosts_labelled, 0);
  EXPECT_GE(s.accuracy(), 0.9995);
  // Only NaNs, or nothing at all: no labels, no NaN in z.
  Eigen::Matrix3Xd nan(3, 4);
  nan.setConstant(std::numeric_limits<double>::quiet_NaN());
  const ekf::TrackOutput& out = tracker.Update(1000.0, nan);
  EXPECT_EQ(out.labelled, 0);
  EXPECT_TRUE(out.z.allFinite());
  EXPECT_EQ(out.marker_of_point, std::vector<int>(4, -1));
  EXPECT_TRUE(tracker.Update(1000.005, Eigen::Matrix3Xd(3, 0)).z.allFinite());
}

// The subject jumps 1.5 m and turns 90 degrees between two frames: the innovation tests declare
// the track lost within the divergence window and the tracker re-initialises on its own.
TEST(EkfTracker, DetectsDivergenceAndReinitialisesAfterATeleport) {
  const auto& session = Session();
  const auto& trial = session.trials[TrialIndex("knee_flexion_l")];
  const int jump = 250;
  const Eigen::Matrix3d turn = Eigen::AngleAxisd(M_PI / 2, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  const Eigen::Vector3d pivot = trial.markers.At(0, 0);
  SceneOptions scene;
  scene.ghosts = 3;
  scene.transform = [&](int f, const Eigen::Vector3d& p) -> Eigen::Vector3d {
    if (f < jump) return p;
    return turn * (p - pivot) + pivot + Eigen::Vector3d(1.5, 0.5, 0);
  };
  ekf::TrackerOptions options;
  ekf::Tracker tracker(Share(session.nominal), options);
  std::mt19937 rng(5);
  int lost_at = -1, back_at = -1;
  long correct_after = 0, points_after = 0;
  for (int f = 0; f < 500; ++f) {
    const Frame fr = MakeFrame(trial.markers, f, scene, rng);
    const ekf::TrackOutput& out = tracker.Update(trial.markers.times[f], fr.points);
    EXPECT_TRUE(out.z.allFinite());
    if (f < jump) ASSERT_EQ(out.state, ekf::TrackState::kTracking) << f;
    if (f >= jump && lost_at < 0 && out.state == ekf::TrackState::kLost) lost_at = f;
    if (f >= jump && back_at < 0 && out.reinitialised) back_at = f;
    if (back_at >= 0) {
      for (size_t k = 0; k < fr.truth.size(); ++k)
        if (fr.truth[k] >= 0) {
          ++points_after;
          correct_after += out.marker_of_point[k] == fr.truth[k];
        }
    }
  }
  std::printf("teleport at %d: re-initialised at %d\n", jump, back_at);
  // Lost, or re-initialised in the very frame it was declared lost, within the window.
  ASSERT_GE(back_at, jump);
  EXPECT_LE(back_at, jump + options.divergence_frames);
  EXPECT_GE(double(correct_after) / points_after, 0.9995);
  (void)lost_at;
}

// The whole-fit gate of the segment registration: the chi-square at the 3-dof gate's tail, for
// other degrees of freedom, against the exact quantiles at the 0.999 level (tables; the default
// gate_chi2 16.27 is chi-square(3) at 0.999).
TEST(EkfTracker, ChiSquareAtTheGatesTailMatchesTheTables) {
  using mocap::ekf::internal::ChiSquareAtGateTail;
  const double gate = mocap::ekf::TrackerOptions{}.gate_chi2;
  EXPECT_NEAR(ChiSquareAtGateTail(gate, 3), gate, 1e-9);
  const std::pair<int, double> table[] = {{6, 22.458}, {9, 27.877}, {12, 32.909}, {30, 59.703}, {42, 76.084}};
  for (const auto& [dof, exact] : table) EXPECT_NEAR(ChiSquareAtGateTail(gate, dof), exact, 0.02 * exact) << dof;
  // Monotone in the degrees of freedom.
  for (int dof = 3; dof < 48; ++dof) EXPECT_LT(ChiSquareAtGateTail(gate, dof), ChiSquareAtGateTail(gate, dof + 1));
}

// A model fitted to the subject (the global fit's, given by SwapModel, or a tracker built on it)
// is not scaled again at a re-initialisation; a generic one is (TrackerOptions::
// init_scale_to_subject kAlways, the default). The subject teleports mid-trial to force a start.
TEST(EkfTracker, ModelFittedToTheSubjectIsNotScaledAgainAtARestart) {
  const auto& session = Session();
  const auto& trial = session.trials[TrialIndex("knee_flexion_l")];
  const int swap = 150, jump = 250, n = 500;
  SceneOptions scene;
  scene.ghosts = 3;
  scene.transform = [&](int f, const Eigen::Vector3d& p) -> Eigen::Vector3d {
    return f < jump ? p : Eigen::Vector3d(p + Eigen::Vector3d(1.5, 0.5, 0));
  };
  struct Restart {
    int back_at = -1;
    std::vector<double> scales;  // the re-initialisation's
    double accuracy = 0;
  };
  auto run = [&](ekf::Tracker* tracker, bool swap_in_truth) {
    std::mt19937 rng(5);
    Restart r;
    long correct = 0, points = 0;
    for (int f = 0; f < n; ++f) {
      if (swap_in_truth && f == swap) EXPECT_TRUE(tracker->SwapModel(Share(session.truth)).ok());
      const Frame fr = MakeFrame(trial.markers, f, scene, rng);
      const ekf::TrackOutput& out = tracker->Update(trial.markers.times[f], fr.points);
      if (f >= jump && r.back_at < 0 && out.reinitialised) {
        r.back_at = f;
        r.scales = tracker->initialisation().segment_scales;
      }
      if (r.back_at >= 0)
        for (size_t k = 0; k < fr.truth.size(); ++k)
          if (fr.truth[k] >= 0) {
            ++points;
            correct += out.marker_of_point[k] == fr.truth[k];
          }
    }
    r.accuracy = points ? double(correct) / points : 0.0;
    return r;
  };
  ekf::Tracker generic(Share(session.truth));
  const Restart g = run(&generic, false);
  ekf::Tracker fitted(Share(session.truth), {}, ekf::ModelOrigin::kFittedToSubject);
  const Restart f = run(&fitted, false);
  ekf::Tracker swapped(Share(session.nominal));
  const Restart s = run(&swapped, true);
  std::printf("restart at %d / %d / %d: scaled segments %zu / %zu / %zu, labels %.6f / %.6f / %.6f\n",
              g.back_at, f.back_at, s.back_at, g.scales.size(), f.scales.size(), s.scales.size(),
              g.accuracy, f.accuracy, s.accuracy);
  ASSERT_GE(g.back_at, jump);
  ASSERT_GE(f.back_at, jump);
  ASSERT_GE(s.back_at, jump);
  EXPECT_FALSE(g.scales.empty()) << "a generic model is scaled at every start";
  EXPECT_TRUE(f.scales.empty()) << "the subject's fitted model was scaled again";
  EXPECT_TRUE(s.scales.empty()) << "the model given by SwapModel was scaled again";
  EXPECT_GE(f.accuracy, 0.9995);
  EXPECT_GE(s.accuracy, 0.9995);
}

// SwapModel mid-trial, nominal -> true: the labels stay right and the joint angles improve.
TEST(EkfTracker, SwapModelKeepsTheTrackAndImprovesTheAngles) {
  const auto& session = Session();
  const auto& trial = session.trials[TrialIndex("hip_star_arc_l")];
  const int swap = trial.markers.num_frames() / 3, n = trial.markers.num_frames();
  SceneOptions scene;
  scene.ghosts = 3;
  auto nominal = Share(session.nominal), truth = Share(session.truth);
  // Reference: the nominal model throughout.
  ekf::Tracker stay(nominal);
  RunStats before;
  TrackRun(&stay, trial, scene, 0, swap, 7);
  const RunStats nominal_after = TrackRun(&stay, trial, scene, swap, n, 8, 40);
  // Swapped.
  ekf::Tracker swapped(nominal);
  TrackRun(&swapped, trial, scene, 0, swap, 7);
  ASSERT_EQ(swapped.state(), ekf::TrackState::kTracking);
  ASSERT_TRUE(swapped.SwapModel(truth).ok());
  EXPECT_EQ(&swapped.model(), truth.get());
  const RunStats swapped_after = TrackRun(&swapped, trial, scene, swap, n, 8, 40);
  std::printf("after the swap: angle RMS %.3f deg (nominal kept: %.3f deg), labels %.6f\n",
              swapped_after.angle_rms_deg(), nominal_after.angle_rms_deg(), swapped_after.accuracy());
  EXPECT_EQ(swapped_after.reinitialisations, 0);
  EXPECT_EQ(swapped_after.tracked_frames, n - swap);
  EXPECT_GE(swapped_after.accuracy(), 0.9995);
  EXPECT_LT(swapped_after.angle_rms_deg(), 0.8 * nominal_after.angle_rms_deg());
  EXPECT_LE(swapped_after.angle_rms_deg(), 1.0);
  // A model with other markers is refused, the track kept.
  const Model fewer = mocap::testutil::Keeping(session.nominal, {0, 1, 2, 3});
  const Status bad = swapped.SwapModel(Share(fewer));
  EXPECT_FALSE(bad.ok());
  EXPECT_NE(bad.message().find("markers"), std::string::npos);
  EXPECT_EQ(&swapped.model(), truth.get());
}

// The frame after a swap (model.apply in the daemon) is measured like the one before it: the swap
// keeps the labelling's state (probation runs, history, seen-beside records); it used to wipe it,
// and the next frame's markers were all back on probation, with no measurement at all.
TEST(EkfTracker, SwapModelLosesNoMeasurement) {
  const auto& session = Session();
  const auto& trial = session.trials[TrialIndex("hip_star_arc_l")];
  const int swap = trial.markers.num_frames() / 3;
  SceneOptions scene;
  scene.ghosts = 3;
  ekf::Tracker tracker(Share(session.nominal));
  TrackRun(&tracker, trial, scene, 0, swap, 7);
  ASSERT_EQ(tracker.state(), ekf::TrackState::kTracking);
  const int labelled_before = tracker.output().labelled;
  const int dof_before = tracker.output().nis_dof;
  ASSERT_GT(dof_before, 60);
  ASSERT_TRUE(tracker.SwapModel(Share(session.truth)).ok());
  TrackRun(&tracker, trial, scene, swap, swap + 1, 7);
  EXPECT_EQ(tracker.state(), ekf::TrackState::kTracking);
  EXPECT_GE(tracker.output().labelled, labelled_before - 1);
  EXPECT_GE(tracker.output().nis_dof, dof_before - 3) << "the frame after the swap was not measured";
}

// A subject turning on the spot (1.5 rad/s about the vertical) through +-pi: the heading stays in
// (-pi, pi] and the labels stay right.
TEST(EkfTracker, WrapsTheHeading) {
  const auto& session = Session();
  const auto& trial = session.trials[TrialIndex("static")];
  const Eigen::Vector3d pivot = trial.markers.At(0, session.nominal.FindMarker("LASI"));
  SceneOptions scene;
  scene.transform = [&](int f, const Eigen::Vector3d& p) -> Eigen::Vector3d {
    const double a = 1.5 * trial.markers.times[f];
    return Eigen::AngleAxisd(a, Eigen::Vector3d::UnitZ()) * (p - pivot) + pivot;
  };
  ekf::Tracker tracker(Share(session.nominal));
  std::mt19937 rng(6);
  const int heading = session.nominal.FindCoordinate("pelvis_rotation");
  double lo = 10, hi = -10;
  long correct = 0, total = 0;
  for (int f = 0; f < trial.markers.num_frames(); ++f) {
    const Frame fr = MakeFrame(trial.markers, f, scene, rng);
    const ekf::TrackOutput& out = tracker.Update(trial.markers.times[f], fr.points);
    ASSERT_EQ(out.state, ekf::TrackState::kTracking) << f;
    lo = std::min(lo, out.z[heading]);
    hi = std::max(hi, out.z[heading]);
    for (size_t k = 0; k < fr.truth.size(); ++k) {
      total += fr.truth[k] >= 0;
      correct += fr.truth[k] >= 0 && out.marker_of_point[k] == fr.truth[k];
    }
  }
  EXPECT_GE(lo, -M_PI);
  EXPECT_LE(hi, M_PI);
  EXPECT_GT(hi - lo, 6.0);  // it did go all the way round (1.5 rad/s x 3 s)
  EXPECT_EQ(correct, total);
}

// ---------------------------------------------------------------------------------------------
// No heap allocation per frame (tests/allocation_test_util.h).

TEST(EkfTracker, UpdateAllocatesNothingWhileTracking) {
  const auto& session = Session();
  const auto& trial = session.trials[TrialIndex("shoulder_circles_l")];
  SceneOptions scene;
  scene.ghosts = 5;
  scene.nans = 2;
  // Gaps, so the frames have different point counts.
  scene.drop = [](int f, int m) { return (f / 15 + m) % 11 == 0; };
  std::mt19937 rng(8);
  std::vector<Frame> frames;
  for (int f = 0; f < 600; ++f) frames.push_back(MakeFrame(trial.markers, f, scene, rng));
  // At the model's own size, every label right. Scaled to the subject (the default since the
  // eighteenth session), 21,264 of 21,265: LELB, hidden at the start, comes back at frame 15
  // 72 mm from its prediction and is withheld one frame as a doubtful return
  // (min_return_probability). The scaled start allocates too, but before the measured frames.
  ekf::TrackerOptions to;
  to.init_scale_to_subject = ekf::TrackerOptions::ScaleToSubject::kWhenTheModelDoesNotFit;
  ekf::Tracker tracker(Share(session.nominal), to);
  ASSERT_EQ(tracker.Update(trial.markers.times[0], frames[0].points).state,
            ekf::TrackState::kTracking);
  long correct = 0, total = 0;
  mocap::testing::g_allocations = 0;
  for (int f = 1; f < 600; ++f) {
    mocap::testing::BeginNoAllocation();
    const ekf::TrackOutput& out = tracker.Update(trial.markers.times[f], frames[f].points);
    mocap::testing::EndNoAllocation();
    ASSERT_EQ(out.state, ekf::TrackState::kTracking) << f;
    for (size_t k = 0; k < frames[f].truth.size(); ++k) {
      total += frames[f].truth[k] >= 0;
      correct += frames[f].truth[k] >= 0 && out.marker_of_point[k] == frames[f].truth[k];
    }
  }
  EXPECT_EQ(mocap::testing::g_allocations.load(), 0);
  EXPECT_EQ(correct, total);
}


// Both wrist markers and the finger marker of the left arm hidden for 60 frames while the subject
// flexes and pronates, then one wrist marker back 40 frames before the other: with only the elbow
// centre and the forearm marker, the forearm turns unseen about the line between them, and the
// drifted prediction put the returning wrist point within the other wrist marker's gate -- a
// mirror image its segment's rigid geometry tells by the fit (DropLabelsAMateFitsBetter). Before
// that rule: 147 wrong labels (LWRA on LWRB's point, the finger marker on LWRA's). Other timings
// of the same scene (hidden at frame 330 for 30 frames; at 250 for 90) still go wrong with and
// without it: there the fit prefers the wrong marker (BENCHMARKS.md, fourteenth session).
TEST(EkfTracker, AWristPointBackAloneIsNotTakenForItsMirrorImage) {
  const auto& session = Session();
  const auto& trial = session.trials[TrialIndex("elbow_flexion_pronation_l")];
  const Model& model = session.nominal;
  const int wra = model.FindMarker("LWRA"), wrb = model.FindMarker("LWRB"),
            fin = model.FindMarker("LFIN");
  ASSERT_TRUE(wra >= 0 && wrb >= 0 && fin >= 0);
  const int hidden_from = 250, both_back = 310, wra_back = 350;
  SceneOptions scene;
  scene.drop = [&](int f, int m) {
    if (f < hidden_from) return false;
    if ((m == wrb || m == fin) && f < both_back) return true;
    return m == wra && f < wra_back;
  };
  ekf::Tracker tracker(Share(model));
  const RunStats s = TrackRun(&tracker, trial, scene, 0, wra_back + 110, 5);
  EXPECT_EQ(s.first_tracked, 0);
  EXPECT_EQ(s.wrong, 0);
  EXPECT_GE(s.accuracy(), 0.999);
}

// A lone marker (the hand's finger marker, its segment's only one) hidden while a reflection
// riding along 30 mm from it appears, and back beside the reflection 25 frames later: the
// marker's gate, grown while it was hidden, took the reflection, and labels follow point tracks,
// so its own point was left unlabelled for seconds (simulated seed 47 at 5 ghosts: RFIN on a
// reflection for 338 frames, then 80-200 mm from its own point for the rest of the take). Within
// the label's provisional window its point and the rival are compared by their distances to the
// hand's joint centre and to where the marker was before (ReviewProvisionalLabels), and the label
// goes to its own point.
TEST(EkfTracker, ALoneMarkerBackBesideAReflectionItTookIsGivenItsOwnPoint) {
  const auto& session = Session();
  const auto& trial = session.trials[TrialIndex("ankle_circles")];
  const Model& model = session.nominal;
  const int fin = model.FindMarker("RFIN");
  ASSERT_GE(fin, 0);
  const int hidden_from = 400, reflection_from = 420, back = 445, end = 600;
  SceneOptions scene;
  scene.drop = [&](int f, int m) { return m == fin && f >= hidden_from && f < back; };
  scene.reflections = [&](int f, const std::vector<Eigen::Vector3d>& markers) {
    std::vector<Eigen::Vector3d> r;
    if (f >= reflection_from) r.push_back(markers[fin] + Eigen::Vector3d(0.03, 0, 0));
    return r;
  };
  ekf::Tracker tracker(Share(model));
  std::mt19937 rng(5);
  int on_reflection = 0, own = 0, late_frames = 0;
  for (int f = 0; f < end; ++f) {
    const Frame fr = MakeFrame(trial.markers, f, scene, rng);
    const ekf::TrackOutput& out = tracker.Update(trial.markers.times[f], fr.points);
    ASSERT_EQ(out.state, ekf::TrackState::kTracking) << "frame " << f;
    if (f < back) continue;
    const int k = out.point_of_marker[fin];
    on_reflection += k >= 0 && fr.truth[k] < 0;
    if (f < back + 20) continue;
    ++late_frames;
    own += k >= 0 && fr.truth[k] == fin;
  }
  // Before: on the reflection for all 155 frames, its own point never labelled.
  EXPECT_LE(on_reflection, 10);
  EXPECT_EQ(own, late_frames);
}
