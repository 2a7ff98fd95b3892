#include "solver/functional_joints.h"

#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <Eigen/SVD>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <random>

namespace mocap::solver {
namespace {

constexpr double kRadToDeg = 180.0 / M_PI;
using Matrix6d = Eigen::Matrix<double, 6, 6>;
using Vector6d = Eigen::Matrix<double, 6, 1>;

// The cluster's markers of frame f as columns; `seen` marks the finite ones.
int ClusterFrame(const formats::MarkerTrial& trial, const std::vector<int>& columns, int f,
                 Eigen::Matrix3Xd* points, std::vector<char>* seen) {
  const int n = static_cast<int>(columns.size());
  points->resize(3, n);
  seen->assign(n, 0);
  int count = 0;
  for (int k = 0; k < n; ++k) {
    if (!trial.Has(f, columns[k])) continue;
    points->col(k) = trial.At(f, columns[k]);
    (*seen)[k] = 1;
    ++count;
  }
  return count;
}

Eigen::Matrix3Xd Select(const Eigen::Matrix3Xd& points, const std::vector<char>& seen) {
  Eigen::Matrix3Xd out(3, std::count(seen.begin(), seen.end(), 1));
  for (int k = 0, c = 0; k < points.cols(); ++k)
    if (seen[k]) out.col(c++) = points.col(k);
  return out;
}

// The frames in which both clusters have a pose.
std::vector<int> CommonFrames(const ClusterTrack& parent, const ClusterTrack& child) {
  std::vector<int> frames;
  for (size_t f = 0; f < parent.valid.size(); ++f)
    if (parent.valid[f] && child.valid[f]) frames.push_back(static_cast<int>(f));
  return frames;
}

// Per-frame terms of the normal equations, summed over blocks of consecutive used frames, and
// the eigen-decomposition of their sum.
struct NormalTerms {
  std::vector<int> frames;  // used: both clusters have a pose
  Eigen::SelfAdjointEigenSolver<Matrix6d> eig;
  std::vector<Matrix6d> block_n;
  std::vector<Vector6d> block_g;
  Matrix6d n = Matrix6d::Zero();
  Vector6d g = Vector6d::Zero();
};

void FrameSystem(const ClusterTrack& parent, const ClusterTrack& child, int f,
                 Eigen::Matrix<double, 3, 6>* a, Eigen::Vector3d* b) {
  a->leftCols<3>() = parent.pose[f].rotation;
  a->rightCols<3>() = -child.pose[f].rotation;
  *b = child.pose[f].translation - parent.pose[f].translation;
}

NormalTerms Accumulate(const ClusterTrack& parent, const ClusterTrack& child,
                       const std::vector<int>& frames, int block) {
  NormalTerms t;
  Eigen::Matrix<double, 3, 6> a;
  Eigen::Vector3d b;
  for (size_t i = 0; i < frames.size(); ++i) {
    if (i % block == 0) {
      t.block_n.push_back(Matrix6d::Zero());
      t.block_g.push_back(Vector6d::Zero());
    }
    FrameSystem(parent, child, frames[i], &a, &b);
    t.block_n.back().noalias() += a.transpose() * a;
    t.block_g.back().noalias() += a.transpose() * b;
  }
  for (size_t k = 0; k < t.block_n.size(); ++k) {
    t.n += t.block_n[k];
    t.g += t.block_g[k];
  }
  return t;
}

// Least squares of N x = g in the eigenvectors of N from `first` on (0: SCoRE, every direction;
// 1: SARA, all but the null direction of a hinge). Eigenvalues ascending.
Vector6d SolveFrom(const Eigen::SelfAdjointEigenSolver<Matrix6d>& eig, const Vector6d& g, int first) {
  Vector6d x = Vector6d::Zero();
  const double floor = 1e-12 * eig.eigenvalues()[5];
  for (int i = first; i < 6; ++i) {
    const double l = eig.eigenvalues()[i];
    if (l > floor) x += (eig.eigenvectors().col(i).dot(g) / l) * eig.eigenvectors().col(i);
  }
  return x;
}

// Residual RMS (mm), condition, rotation spread; the excitation test is the caller's.
FunctionalFit Describe(const ClusterTrack& parent, const ClusterTrack& child,
                       const std::vector<int>& frames, const Matrix6d& n, const Vector6d& x) {
  FunctionalFit fit;
  fit.frames_used = static_cast<int>(frames.size());
  Eigen::Matrix<double, 3, 6> a;
  Eigen::Vector3d b;
  double sq = 0;
  Eigen::Matrix3d sum_rel = Eigen::Matrix3d::Zero();
  for (int f : frames) {
    FrameSystem(parent, child, f, &a, &b);
    sq += (a * x - b).squaredNorm();
    sum_rel += parent.pose[f].rotation.transpose() * child.pose[f].rotation;
  }
  fit.residual_rms_mm = 1000.0 * std::sqrt(sq / std::max<size_t>(1, frames.size()));
  const Eigen::SelfAdjointEigenSolver<Matrix6d> eig(n);
  const double lo = std::max(eig.eigenvalues()[0], 0.0), hi = eig.eigenvalues()[5];
  fit.condition = lo > 0 ? std::sqrt(hi / lo) : std::numeric_limits<double>::infinity();
  // Chordal mean of the relative rotations, then the spread of each about it.
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(sum_rel, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d d = Eigen::Matrix3d::Identity();
  d(2, 2) = (svd.matrixU() * svd.matrixV().transpose()).determinant() < 0 ? -1.0 : 1.0;
  const Eigen::Matrix3d mean = svd.matrixU() * d * svd.matrixV().transpose();
  Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
  for (int f : frames) {
    const Eigen::AngleAxisd aa(mean.transpose() * parent.pose[f].rotation.transpose() *
                               child.pose[f].rotation);
    const Eigen::Vector3d w = aa.angle() * aa.axis();
    cov += w * w.transpose();
  }
  cov /= std::max<size_t>(1, frames.size());
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> spread(cov);
  for (int k = 0; k < 3; ++k)
    fit.rotation_spread_deg[k] = kRadToDeg * std::sqrt(std::max(0.0, spread.eigenvalues()[2 - k]));
  return fit;
}

// Excited when the rotation spread about principal axis `axis` (0: main, 1: second) reaches
// `min_deg`; otherwise a note that says so.
void MarkExcitation(int axis, double min_deg, FunctionalFit* fit) {
  fit->excited = fit->rotation_spread_deg[axis] >= min_deg;
  if (fit->excited) return;
  char buf[240];
  std::snprintf(buf, sizeof(buf), "the joint turned %.1f deg RMS about its %s axis (at least %.1f "
                "needed)%s", fit->rotation_spread_deg[axis], axis == 0 ? "main" : "second", min_deg,
                axis == 0 ? "" : ": a centre needs rotation about two axes");
  fit->note = buf;
}

// Calls `estimate(n, g)` on `samples` moving-block resamples of the terms.
template <typename Estimate>
void Bootstrap(const NormalTerms& t, const FunctionalJointOptions& options, Estimate estimate) {
  std::mt19937_64 rng(options.seed);
  const int blocks = static_cast<int>(t.block_n.size());
  std::uniform_int_distribution<int> pick(0, blocks - 1);
  for (int s = 0; s < options.bootstrap_samples; ++s) {
    Matrix6d n = Matrix6d::Zero();
    Vector6d g = Vector6d::Zero();
    for (int k = 0; k < blocks; ++k) {
      const int b = pick(rng);
      n += t.block_n[b];
      g += t.block_g[b];
    }
    estimate(n, g);
  }
}

Status Prepare(const ClusterTrack& parent, const ClusterTrack& child, double rate_hz,
               const FunctionalJointOptions& options, NormalTerms* t) {
  std::string why;
  if (!options.IsValid(&why)) return Status::Error("functional joint options: " + why);
  if (parent.valid.size() != child.valid.size())
    return Status::Error("functional joint: the clusters are tracked over " +
                         std::to_string(parent.valid.size()) + " and " +
                         std::to_string(child.valid.size()) + " frames (not the same trial?)");
  if (!(rate_hz > 0)) return Status::Error("functional joint: the trial's rate must be > 0");
  const std::vector<int> frames = CommonFrames(parent, child);
  if (static_cast<int>(frames.size()) < options.min_frames)
    return Status::Error("functional joint: only " + std::to_string(frames.size()) +
                         " frames in which both segments' markers are seen (at least " +
                         std::to_string(options.min_frames) + " needed)");
  const int block = std::max(1, static_cast<int>(std::lround(options.bootstrap_block_s * rate_hz)));
  *t = Accumulate(parent, child, frames, block);
  t->frames = frames;
  t->eig.compute(t->n);
  return Status::Ok();
}

}  // namespace

bool FunctionalJointOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& what) {
    if (error) *error = what;
    return false;
  };
  if (min_frames < 3) return fail("min_frames must be >= 3");
  if (!(min_rotation_deg >= 0) || !std::isfinite(min_rotation_deg))
    return fail("min_rotation_deg must be >= 0");
  if (bootstrap_samples < 0) return fail("bootstrap_samples must be >= 0");
  if (!(bootstrap_block_s > 0) || !std::isfinite(bootstrap_block_s))
    return fail("bootstrap_block_s must be > 0");
  return true;
}

Status TrackCluster(const formats::MarkerTrial& trial, const std::vector<int>& columns,
                    ClusterTrack* track) {
  const int n = static_cast<int>(columns.size());
  const std::string name = "trial '" + trial.name + "'";
  if (n < 3)
    return Status::Error(name + ": a cluster needs at least 3 markers, " + std::to_string(n) +
                         " given");
  for (int c : columns)
    if (c < 0 || c >= trial.num_markers())
      return Status::Error(name + ": marker index " + std::to_string(c) + " is out of range");
  const int nf = trial.num_frames();
  Eigen::Matrix3Xd points;
  std::vector<char> seen;
  // Mean shape by generalised Procrustes over the complete frames.
  std::vector<int> complete;
  for (int f = 0; f < nf; ++f)
    if (ClusterFrame(trial, columns, f, &points, &seen) == n) complete.push_back(f);
  if (complete.empty())
    return Status::Error(name + ": no frame in which all " + std::to_string(n) +
                         " markers of the cluster are seen");
  ClusterFrame(trial, columns, complete.front(), &points, &seen);
  Eigen::Matrix3Xd shape = points.colwise() - points.rowwise().mean();
  if (!SpansPlane(shape))
    return Status::Error(name + ": the cluster's markers lie on one line");
  for (int iteration = 0; iteration < 3; ++iteration) {
    Eigen::Matrix3Xd sum = Eigen::Matrix3Xd::Zero(3, n);
    for (int f : complete) {
      ClusterFrame(trial, columns, f, &points, &seen);
      const std::optional<RigidTransform> pose = RigidAlign(shape, points);
      if (!pose) continue;
      sum += pose->rotation.transpose() * (points.colwise() - pose->translation);
    }
    shape = sum / static_cast<double>(complete.size());
    shape = shape.colwise() - shape.rowwise().mean();
  }
  ClusterTrack out;
  out.columns = columns;
  out.shape = shape;
  out.pose.resize(nf);
  out.valid.assign(nf, 0);
  double sq = 0;
  long samples = 0;
  for (int f = 0; f < nf; ++f) {
    if (ClusterFrame(trial, columns, f, &points, &seen) < 3) continue;
    const Eigen::Matrix3Xd src = Select(shape, seen), dst = Select(points, seen);
    const std::optional<RigidTransform> pose = RigidAlign(src, dst);
    if (!pose) continue;
    out.pose[f] = *pose;
    out.valid[f] = 1;
    sq += ((pose->rotation * src).colwise() + pose->translation - dst).squaredNorm();
    samples += src.cols();
  }
  out.rms_mm = 1000.0 * std::sqrt(sq / std::max(1L, samples));
  *track = std::move(out);
  return Status::Ok();
}

Status EstimateCentre(const ClusterTrack& parent, const ClusterTrack& child, double rate_hz,
                      const FunctionalJointOptions& options, CentreEstimate* centre) {
  NormalTerms t;
  MOCAP_RETURN_IF_ERROR(Prepare(parent, child, rate_hz, options, &t));
  CentreEstimate out;
  const Vector6d x = SolveFrom(t.eig, t.g, 0);
  out.in_parent = x.head<3>();
  out.in_child = x.tail<3>();
  out.fit = Describe(parent, child, t.frames, t.n, x);
  // A centre is fixed by rotation about two axes; about one it slides along that axis.
  MarkExcitation(1, options.min_rotation_deg, &out.fit);
  std::vector<Eigen::Vector3d> draws;
  Bootstrap(t, options, [&](const Matrix6d& n, const Vector6d& g) {
    const Eigen::SelfAdjointEigenSolver<Matrix6d> e(n);
    draws.push_back(SolveFrom(e, g, 0).head<3>());
  });
  for (const Eigen::Vector3d& d : draws)
    out.covariance_parent += (d - out.in_parent) * (d - out.in_parent).transpose();
  if (!draws.empty()) out.covariance_parent /= static_cast<double>(draws.size());
  out.std_mm = 1000.0 * std::sqrt(out.covariance_parent.trace());
  *centre = out;
  return Status::Ok();
}

Status EstimateAxis(const ClusterTrack& parent, const ClusterTrack& child, double rate_hz,
                    const FunctionalJointOptions& options, AxisEstimate* axis) {
  NormalTerms t;
  MOCAP_RETURN_IF_ERROR(Prepare(parent, child, rate_hz, options, &t));
  AxisEstimate out;
  const Vector6d null = t.eig.eigenvectors().col(0);
  const Vector6d x = SolveFrom(t.eig, t.g, 1);
  out.direction_parent = null.head<3>().normalized();
  out.direction_child = null.tail<3>().normalized();
  out.point_parent = x.head<3>();
  out.point_child = x.tail<3>();
  out.fit = Describe(parent, child, t.frames, t.n, x);
  MarkExcitation(0, options.min_rotation_deg, &out.fit);
  double angle_sq = 0, point_sq = 0;
  int draws = 0;
  Bootstrap(t, options, [&](const Matrix6d& n, const Vector6d& g) {
    const Eigen::SelfAdjointEigenSolver<Matrix6d> e(n);
    const Eigen::Vector3d d = e.eigenvectors().col(0).head<3>().normalized();
    const double c = std::min(1.0, std::abs(d.dot(out.direction_parent)));  // sign-free
    angle_sq += std::pow(std::acos(c), 2);
    const Eigen::Vector3d dp = SolveFrom(e, g, 1).head<3>() - out.point_parent;
    point_sq += (dp - dp.dot(out.direction_parent) * out.direction_parent).squaredNorm();
    ++draws;
  });
  if (draws > 0) {
    out.direction_std_deg = kRadToDeg * std::sqrt(angle_sq / draws);
    out.point_std_mm = 1000.0 * std::sqrt(point_sq / draws);
  }
  *axis = out;
  return Status::Ok();
}

Eigen::Vector3d FunctionalJoint::CentreInLab(int f) const {
  if (!parent.valid[f] || !child.valid[f])
    return Eigen::Vector3d::Constant(std::numeric_limits<double>::quiet_NaN());
  return 0.5 * (parent.pose[f].Point(centre.in_parent) + child.pose[f].Point(centre.in_child));
}

Eigen::Vector3d FunctionalJoint::AxisInLab(int f) const {
  if (!parent.valid[f] || !child.valid[f])
    return Eigen::Vector3d::Constant(std::numeric_limits<double>::quiet_NaN());
  return (parent.pose[f].Direction(axis.direction_parent) +
          child.pose[f].Direction(axis.direction_child)).normalized();
}

Eigen::Vector3d FunctionalJoint::AxisPointInLab(int f) const {
  if (!parent.valid[f] || !child.valid[f])
    return Eigen::Vector3d::Constant(std::numeric_limits<double>::quiet_NaN());
  return 0.5 * (parent.pose[f].Point(axis.point_parent) + child.pose[f].Point(axis.point_child));
}

bool DescribedByAxis(const Joint& joint) {
  if (joint.type == JointType::kHinge || joint.type == JointType::kUniversal) return true;
  if (joint.type != JointType::kCustom) return false;
  std::vector<int> coordinates;
  for (const JointElement& el : joint.elements)
    if (el.kind == ElementKind::kRotation && el.coordinate >= 0 && !el.function.IsConstant() &&
        std::find(coordinates.begin(), coordinates.end(), el.coordinate) == coordinates.end())
      coordinates.push_back(el.coordinate);
  return coordinates.size() == 1 || coordinates.size() == 2;
}

Status EstimateFunctionalJoint(const Model& model, const formats::MarkerTrial& trial,
                               const std::string& joint, const FunctionalJointOptions& options,
                               FunctionalJoint* result) {
  const int j = model.FindJoint(joint);
  if (j < 0) {
    std::string names;
    for (const Joint& jt : model.joints())
      if (jt.parent >= 0) names += (names.empty() ? "" : ", ") + jt.name;
    return Status::Error("model '" + model.name() + "' has no joint '" + joint +
                         "' (its joints: " + names + ")");
  }
  const Joint& jt = model.joints()[j];
  if (jt.parent < 0)
    return Status::Error("joint '" + joint + "' joins '" + model.segments()[jt.child].name +
                         "' to the lab, which has no markers: no functional estimate");
  FunctionalJoint out;
  out.joint = joint;
  out.type = jt.type;
  out.axis_joint = DescribedByAxis(jt);
  out.parent_segment = model.segments()[jt.parent].name;
  out.child_segment = model.segments()[jt.child].name;
  // The trial's columns of the model's markers on `segment`.
  auto cluster = [&](int segment, std::vector<std::string>* names, std::vector<int>* columns) {
    std::string absent;
    for (const Marker& m : model.markers()) {
      if (m.segment != segment) continue;
      const int c = trial.FindMarker(m.name);
      if (c < 0) {
        absent += (absent.empty() ? "" : ", ") + m.name;
        continue;
      }
      names->push_back(m.name);
      columns->push_back(c);
    }
    if (columns->size() >= 3) return Status::Ok();
    std::string have;
    for (const std::string& n : *names) have += (have.empty() ? "" : ", ") + n;
    return Status::Error("segment '" + model.segments()[segment].name + "' has " +
                         std::to_string(columns->size()) + " marker(s) in trial '" + trial.name +
                         "'" + (have.empty() ? "" : " (" + have + ")") +
                         (absent.empty() ? "" : "; the model's not in the trial: " + absent) +
                         "; a functional estimate needs at least 3 on each segment");
  };
  std::vector<int> parent_columns, child_columns;
  MOCAP_RETURN_IF_ERROR(cluster(jt.parent, &out.parent_markers, &parent_columns));
  MOCAP_RETURN_IF_ERROR(cluster(jt.child, &out.child_markers, &child_columns));
  MOCAP_RETURN_IF_ERROR(TrackCluster(trial, parent_columns, &out.parent));
  MOCAP_RETURN_IF_ERROR(TrackCluster(trial, child_columns, &out.child));
  MOCAP_RETURN_IF_ERROR(EstimateCentre(out.parent, out.child, trial.rate_hz, options, &out.centre));
  MOCAP_RETURN_IF_ERROR(EstimateAxis(out.parent, out.child, trial.rate_hz, options, &out.axis));
  *result = std::move(out);
  return Status::Ok();
}

Status AddFunctionalCentres(const std::vector<std::string>& joints,
                            const FunctionalJointOptions& options, double weight, Model* model,
                            std::vector<formats::MarkerTrial>* trials,
                            std::vector<std::string>* virtual_markers,
                            std::vector<std::string>* notes) {
  if (!(weight > 0) || !std::isfinite(weight))
    return Status::Error("functional centres: the weight must be > 0");
  std::vector<Marker> markers = model->markers();
  std::vector<formats::MarkerTrial> out_trials = *trials;  // *trials untouched on error
  std::vector<std::string> added;
  for (const std::string& joint : joints) {
    const std::string name = joint + "@functional";
    if (model->FindMarker(name) >= 0 || std::find(added.begin(), added.end(), name) != added.end())
      return Status::Error("functional centres: joint '" + joint + "' given twice");
    int excited = 0;
    std::vector<Eigen::MatrixXd> centres(trials->size());
    for (size_t t = 0; t < trials->size(); ++t) {
      const formats::MarkerTrial& trial = (*trials)[t];
      FunctionalJoint fj;
      if (Status s = EstimateFunctionalJoint(*model, trial, joint, options, &fj); !s) {
        if (model->FindJoint(joint) < 0 || model->joints()[model->FindJoint(joint)].parent < 0)
          return s;  // a joint the model does not have (or the root) is the caller's error
        notes->push_back(joint + ": trial '" + trial.name + "' not used: " + s.message());
        continue;
      }
      if (!fj.centre.fit.excited) {
        notes->push_back(joint + ": trial '" + trial.name + "' not used: " + fj.centre.fit.note);
        continue;
      }
      char buf[200];
      std::snprintf(buf, sizeof(buf),
                    "%s: trial '%s': SCoRE centre over %d frames, std %.2f mm, residual %.2f mm",
                    joint.c_str(), trial.name.c_str(), fj.centre.fit.frames_used, fj.centre.std_mm,
                    fj.centre.fit.residual_rms_mm);
      notes->push_back(buf);
      centres[t].resize(trial.num_frames(), 3);
      for (int f = 0; f < trial.num_frames(); ++f) centres[t].row(f) = fj.CentreInLab(f).transpose();
      ++excited;
    }
    if (excited == 0)
      return Status::Error("functional centres: no trial excites joint '" + joint +
                           "' (each needs rotation about two axes and 3 markers on each segment)");
    for (size_t t = 0; t < out_trials.size(); ++t) {
      formats::MarkerTrial& trial = out_trials[t];
      const Eigen::Index cols = trial.positions.cols();
      trial.positions.conservativeResize(Eigen::NoChange, cols + 3);
      if (centres[t].size() > 0) {
        trial.positions.rightCols<3>() = centres[t];
      } else {
        trial.positions.rightCols<3>().setConstant(std::numeric_limits<double>::quiet_NaN());
      }
      trial.marker_names.push_back(name);
    }
    Marker m;
    m.name = name;
    m.segment = model->joints()[model->FindJoint(joint)].child;
    m.position = Eigen::Vector3d::Zero();
    m.weight = weight;
    markers.push_back(m);
    added.push_back(name);
  }
  std::vector<Segment> segments = model->segments();
  std::vector<Joint> model_joints = model->joints();
  std::vector<Coordinate> coordinates = model->coordinates();
  std::vector<DerivedCoordinate> derived = model->derived_coordinates();
  Model out;
  MOCAP_RETURN_IF_ERROR(Model::Build(model->name(), segments, model_joints, coordinates, markers,
                                     derived, &out));
  *model = std::move(out);
  *trials = std::move(out_trials);
  virtual_markers->insert(virtual_markers->end(), added.begin(), added.end());
  return Status::Ok();
}

}  // namespace mocap::solver
