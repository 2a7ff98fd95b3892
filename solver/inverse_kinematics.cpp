#include "solver/inverse_kinematics.h"

#include <Eigen/Cholesky>
#include <algorithm>
#include <cmath>
#include <limits>
#include <optional>

#include "model/rigid_align.h"

namespace mocap::solver {

bool IkOptions::IsValid(std::string* error) const {
  if (max_iterations < 1) {
    if (error) *error = "max_iterations must be >= 1";
    return false;
  }
  if (!(step_tolerance > 0) || !(restart_rms_m > 0)) {
    if (error) *error = "step_tolerance and restart_rms_m must be > 0";
    return false;
  }
  if (!(coordinate_limit_stiffness >= 0)) {
    if (error) *error = "coordinate_limit_stiffness must be >= 0 (0: ranges not enforced)";
    return false;
  }
  return true;
}

std::vector<char> PeriodicCoordinates(const Model& model) {
  const int nz = model.num_coordinates();
  std::vector<char> periodic(nz, 0), drives(nz, 0);
  std::vector<char> other(nz, 0);
  for (const Joint& joint : model.joints())
    for (const JointElement& el : joint.elements) {
      if (el.coordinate < 0) continue;
      drives[el.coordinate] = 1;
      const bool whole_turn = el.kind == ElementKind::kRotation &&
                              (el.function.kind == CoordinateFunction::Kind::kIdentity ||
                               (el.function.kind == CoordinateFunction::Kind::kLinear &&
                                std::abs(el.function.slope) == 1.0));
      if (!whole_turn) other[el.coordinate] = 1;
    }
  for (int c = 0; c < nz; ++c) periodic[c] = drives[c] && !other[c];
  return periodic;
}

void WrapPeriodicCoordinates(const Model& model, const std::vector<char>& periodic, const Eigen::VectorXd& reference,
                             Eigen::VectorXd* z) {
  for (int c = 0; c < model.num_coordinates(); ++c) {
    if (!periodic[c]) continue;
    const Coordinate& coordinate = model.coordinates()[c];
    // A joint that cannot turn round (range narrower than a turn) is referred to its range's
    // centre; one that can, and the joint to the lab (whose angles depend on the lab's axes: an
    // upside-down lab puts a pelvis tilt near pi, outside any range), to `reference`, so that they
    // stay continuous.
    const bool to_lab = coordinate.joint >= 0 && model.joints()[coordinate.joint].parent < 0;
    const double centre = !to_lab && coordinate.max_value - coordinate.min_value < 2.0 * M_PI
                              ? 0.5 * (coordinate.max_value + coordinate.min_value)
                              : reference[c];
    (*z)[c] = centre + std::remainder((*z)[c] - centre, 2.0 * M_PI);
  }
}

InverseKinematics::InverseKinematics(const Model& model, const Geometry& geometry, IkOptions options)
    : model_(model), geometry_(geometry), options_(options), data_(model), periodic_(PeriodicCoordinates(model)) {
  const int nz = model.num_coordinates();
  jtj_.resize(nz, nz);
  damped_.resize(nz, nz);
  llt_ = Eigen::LLT<Eigen::MatrixXd>(nz);
  jtr_.resize(nz);
  jz_.resize(3, model.max_chain_coordinates());
  if (options_.coordinate_limit_stiffness > 0) limited_ = LimitedCoordinates(model);
}

std::vector<int> LimitedCoordinates(const Model& model) {
  std::vector<int> out;
  for (int c = 0; c < model.num_coordinates(); ++c) {
    const Coordinate& co = model.coordinates()[c];
    const bool root = co.joint >= 0 && model.joints()[co.joint].parent < 0;
    if (co.clamped && !root && co.max_value - co.min_value < 1e8) out.push_back(c);
  }
  return out;
}

double InverseKinematics::LimitCost(const Eigen::VectorXd& z) const {
  double sum = 0;
  for (int c : limited_) {
    const double e = options_.coordinate_limit_stiffness * RangeExcess(model_.coordinates()[c], z[c]);
    sum += e * e;
  }
  return sum;
}

namespace {
// Sum over the present markers of weight * squared distance (Marker::weight, as in the global
// fit: a marker the fit weighs less bends the pose less), the count of markers and the sum of
// their weights.
double SquaredError(const Model& model, const Geometry& g, const ModelData& d,
                    const Eigen::Matrix3Xd& measured, int* count, double* weight_sum = nullptr) {
  double sum = 0, weights = 0;
  int n = 0;
  for (int m = 0; m < model.num_markers(); ++m) {
    if (!std::isfinite(measured(0, m))) continue;
    const double w = model.markers()[m].weight;
    sum += w * (MarkerPosition(model, g, d, m) - measured.col(m)).squaredNorm();
    weights += w;
    ++n;
  }
  if (count) *count = n;
  if (weight_sum) *weight_sum = weights;
  return sum;
}
}  // namespace

IkFrameResult InverseKinematics::Solve(const Eigen::Matrix3Xd& measured, Eigen::VectorXd* z,
                                       const std::vector<char>& free) {
  const int nz = model_.num_coordinates();
  IkFrameResult result;
  const Eigen::VectorXd start = *z;
  ForwardKinematics(model_, geometry_, *z, &data_);
  double weight_sum = 0;
  double marker_cost = SquaredError(model_, geometry_, data_, measured, &result.markers, &weight_sum);
  double cost = marker_cost + LimitCost(*z);
  double lambda = 1e-3;
  Eigen::VectorXd dz(nz), z_new(nz);
  for (int it = 0; it < options_.max_iterations; ++it) {
    result.iterations = it + 1;
    jtj_.setZero();
    jtr_.setZero();
    for (int m = 0; m < model_.num_markers(); ++m) {
      if (!std::isfinite(measured(0, m))) continue;
      const auto& cols = model_.marker_coordinates(m);
      auto jz = jz_.leftCols(cols.size());
      MarkerJacobian(model_, geometry_, data_, m, &jz, static_cast<Eigen::Matrix3Xd*>(nullptr));
      const double w = model_.markers()[m].weight;
      const Eigen::Vector3d r = MarkerPosition(model_, geometry_, data_, m) - measured.col(m);
      for (size_t a = 0; a < cols.size(); ++a) {
        jtr_[cols[a]] += w * jz.col(a).dot(r);
        for (size_t b = 0; b <= a; ++b) jtj_(cols[a], cols[b]) += w * jz.col(a).dot(jz.col(b));
      }
    }
    for (int c : limited_) {
      const double k = options_.coordinate_limit_stiffness;
      const double e = RangeExcess(model_.coordinates()[c], (*z)[c]);
      if (e == 0.0) continue;
      jtr_[c] += k * k * e;
      jtj_(c, c) += k * k;
    }
    for (int c = 0; c < nz; ++c)
      if (!free.empty() && !free[c]) {
        jtj_.row(c).setZero();
        jtj_.col(c).setZero();
        jtj_(c, c) = 1.0;
        jtr_[c] = 0.0;
      }
    bool accepted = false;
    double decrease = 0;
    for (int tries = 0; tries < 12 && !accepted; ++tries) {
      damped_ = jtj_;
      damped_.diagonal() += lambda * jtj_.diagonal().cwiseMax(1e-9) + Eigen::VectorXd::Constant(nz, 1e-12);
      llt_.compute(damped_);  // reads the lower triangle, which is all jtj_ holds
      if (llt_.info() != Eigen::Success) {
        lambda *= 10;
        continue;
      }
      dz = -llt_.solve(jtr_);
      if (!dz.allFinite()) {
        lambda *= 10;
        continue;
      }
      z_new = *z + dz;
      ForwardKinematics(model_, geometry_, z_new, &data_);
      const double new_marker_cost = SquaredError(model_, geometry_, data_, measured, nullptr);
      const double new_cost = new_marker_cost + LimitCost(z_new);
      if (new_cost < cost) {
        decrease = cost - new_cost;
        cost = new_cost;
        marker_cost = new_marker_cost;
        z->swap(z_new);
        lambda = std::max(1e-9, lambda * 0.3);
        accepted = true;
      } else {
        lambda *= 10;
      }
    }
    // Converged when the step is tiny or the cost no longer moves (1e-12 m^2: a nanometre-level
    // change of a marker), which is far below any marker noise.
    if (accepted && decrease < 1e-12 * std::max(1.0, double(result.markers))) break;
    if (!accepted || dz.norm() < options_.step_tolerance) break;
  }
  WrapPeriodicCoordinates(model_, periodic_, start, z);
  ForwardKinematics(model_, geometry_, *z, &data_);
  // Weighted RMS: with every weight 1 (the usual case) the plain RMS.
  result.rms_m = weight_sum > 0 ? std::sqrt(marker_cost / weight_sum) : 0.0;
  return result;
}

namespace {
// Sets the root joint's rotation coordinates so that its child segment's orientation becomes
// `target` (world). Possible when the root's moving rotations are three identity-driven
// rotations about signed coordinate axes (x, y or z, consecutive ones different), with no
// constant rotation among them, as in OpenSim's and our free joints; false otherwise.
bool SetRootRotation(const Joint& root, const Eigen::Matrix3d& target, Eigen::VectorXd* z) {
  std::vector<const JointElement*> rot;
  for (const auto& el : root.elements) {
    if (el.kind != ElementKind::kRotation) continue;
    if (el.coordinate < 0 || el.function.kind != CoordinateFunction::Kind::kIdentity) return false;
    rot.push_back(&el);
  }
  if (rot.size() != 3) return false;
  int index[3];
  double sign[3];
  for (int i = 0; i < 3; ++i) {
    Eigen::Index k;
    const double largest = rot[i]->axis.cwiseAbs().maxCoeff(&k);
    if (std::abs(largest - 1.0) > 1e-12) return false;  // not a coordinate axis
    index[i] = static_cast<int>(k);
    sign[i] = rot[i]->axis[k] > 0 ? 1.0 : -1.0;
  }
  if (index[0] == index[1] || index[1] == index[2]) return false;
  const Eigen::Vector3d angles =
      (root.orientation.transpose() * target).eulerAngles(index[0], index[1], index[2]);
  for (int i = 0; i < 3; ++i) (*z)[rot[i]->coordinate] = sign[i] * angles[i];
  return true;
}
}  // namespace

IkFrameResult InverseKinematics::Initialise(const Eigen::Matrix3Xd& measured, Eigen::VectorXd* z) {
  // The root joint (first in parents-first order) carries the subject's place and orientation.
  const Joint& root = model_.joints()[0];
  std::vector<char> root_free(model_.num_coordinates(), 0);
  int heading = -1;
  for (const auto& el : root.elements) {
    if (el.coordinate < 0) continue;
    root_free[el.coordinate] = 1;
    if (heading < 0 && el.kind == ElementKind::kRotation) heading = el.coordinate;
  }
  std::vector<int> present;
  for (int m = 0; m < model_.num_markers(); ++m)
    if (std::isfinite(measured(0, m))) present.push_back(m);
  IkFrameResult best;
  best.rms_m = std::numeric_limits<double>::infinity();
  Eigen::VectorXd best_z = model_.DefaultCoordinates();
  if (present.empty()) {
    *z = best_z;
    return best;
  }
  const int n = static_cast<int>(present.size());
  Eigen::Matrix3Xd dst(3, n);
  for (int i = 0; i < n; ++i) dst.col(i) = measured.col(present[i]);
  const Eigen::Vector3d centroid = dst.rowwise().mean();

  // Starting orientations of the root. The lab's vertical may be any axis (Y in OpenSim data, Z
  // or -Z elsewhere) and the subject may face anywhere, so besides the default pose turned to four
  // headings, the default pose is rigidly aligned (Kabsch) onto the measured markers: all of them,
  // and those of the root segment alone (the pelvis, whose shape does not change with the pose).
  std::vector<Eigen::VectorXd> starts;
  const Eigen::VectorXd z_default = model_.DefaultCoordinates();
  const int tries = heading >= 0 ? 4 : 1;
  for (int k = 0; k < tries; ++k) {
    starts.push_back(z_default);
    if (heading >= 0) starts.back()[heading] += k * M_PI / 2;
  }
  ForwardKinematics(model_, geometry_, z_default, &data_);
  const Eigen::Matrix3d root_rotation = data_.segment_rotation[root.child];
  Eigen::Matrix3Xd src(3, n);
  for (int i = 0; i < n; ++i) src.col(i) = MarkerPosition(model_, geometry_, data_, present[i]);
  std::vector<int> on_root;
  for (int i = 0; i < n; ++i)
    if (model_.markers()[present[i]].segment == root.child) on_root.push_back(i);
  std::vector<std::optional<RigidTransform>> alignments = {RigidAlign(src, dst)};
  if (on_root.size() >= 3) alignments.push_back(RigidAlign(src(Eigen::all, on_root), dst(Eigen::all, on_root)));
  for (const auto& a : alignments) {
    Eigen::VectorXd start = z_default;
    if (a && SetRootRotation(root, a->rotation * root_rotation, &start)) starts.push_back(start);
  }

  // Each start: its root alone solved first (6 unknowns: cheap); the full solve only from the
  // two best of those.
  std::vector<std::pair<double, int>> root_rms;
  for (size_t k = 0; k < starts.size(); ++k) {
    Eigen::VectorXd& trial = starts[k];
    // Shift the root's translations so the model's marker centroid lands on the data's.
    ForwardKinematics(model_, geometry_, trial, &data_);
    Eigen::Vector3d model_centroid = Eigen::Vector3d::Zero();
    for (int m : present) model_centroid += MarkerPosition(model_, geometry_, data_, m);
    model_centroid /= n;
    const Eigen::Vector3d shift = centroid - model_centroid;
    // Translations before any rotation move along the joint's fixed frame.
    for (const auto& el : root.elements) {
      if (el.kind == ElementKind::kRotation) break;
      if (el.coordinate >= 0 && el.function.kind == CoordinateFunction::Kind::kIdentity)
        trial[el.coordinate] += (root.orientation * el.axis).dot(shift);
    }
    root_rms.emplace_back(Solve(measured, &trial, root_free).rms_m, static_cast<int>(k));
  }
  std::sort(root_rms.begin(), root_rms.end());
  for (size_t i = 0; i < std::min<size_t>(2, root_rms.size()); ++i) {
    Eigen::VectorXd trial = starts[root_rms[i].second];
    IkFrameResult r = Solve(measured, &trial);
    if (r.rms_m < best.rms_m) {
      best = r;
      best_z = trial;
    }
  }
  *z = best_z;
  ForwardKinematics(model_, geometry_, *z, &data_);
  return best;
}

Status InverseKinematics::SolveTrial(
    const Eigen::Ref<const Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>>& measured,
    Eigen::MatrixXd* coordinates, std::vector<double>* rms_m) {
  const int nf = static_cast<int>(measured.rows());
  const int nm = model_.num_markers();
  if (measured.cols() != 3 * nm)
    return Status::Error("inverse kinematics: measurements have " + std::to_string(measured.cols()) +
                         " columns, the model needs " + std::to_string(3 * nm));
  coordinates->resize(nf, model_.num_coordinates());
  if (rms_m) rms_m->assign(nf, 0.0);
  Eigen::Matrix3Xd frame(3, nm);
  auto load = [&](int f) {
    frame = Eigen::Map<const Eigen::Matrix3Xd>(measured.row(f).data(), 3, nm);
    int present = 0;
    for (int m = 0; m < nm; ++m) present += std::isfinite(frame(0, m)) ? 1 : 0;
    return present;
  };
  // Start where the most markers are seen: a pose found from a frame with gaps can sit on a
  // wrong branch (a two-marker segment with one marker missing), and warm starts would carry it
  // through the trial. Then sweep forwards and backwards from there.
  int start = -1, best = 2;
  for (int f = 0; f < nf; ++f) {
    const int present = load(f);
    if (present > best) {
      best = present;
      start = f;
    }
  }
  if (start < 0)
    return Status::Error("inverse kinematics: no frame has 3 or more of the model's markers");
  load(start);
  Eigen::VectorXd z_start;
  std::vector<double> frame_rms(nf, 0.0);
  IkFrameResult r0 = Initialise(frame, &z_start);
  frame_rms[start] = r0.rms_m;
  coordinates->row(start) = z_start.transpose();
  if (rms_m) (*rms_m)[start] = r0.rms_m;
  for (int direction : {+1, -1}) {
    Eigen::VectorXd z = z_start;
    // The trial's typical error so far: with an approximate model (before the fit) it is
    // several millimetres, so a fixed threshold would miss a pose that slid into a wrong valley
    // during a gap and stayed there. A jump well above the running level re-initialises.
    double level = r0.rms_m;
    for (int f = start + direction; f >= 0 && f < nf; f += direction) {
      IkFrameResult r;
      if (load(f) >= 3) {
        Eigen::VectorXd warm = z;
        r = Solve(frame, &warm);
        if (r.rms_m > std::min(options_.restart_rms_m, 1.25 * level + 0.002)) {
          Eigen::VectorXd fresh;
          IkFrameResult r2 = Initialise(frame, &fresh);
          if (r2.rms_m < r.rms_m) {
            r = r2;
            warm = fresh;
          }
        }
        z = warm;
        level = 0.9 * level + 0.1 * r.rms_m;
      }
      coordinates->row(f) = z.transpose();  // a frame with < 3 markers keeps its neighbour's pose
      if (rms_m) (*rms_m)[f] = r.rms_m;
      frame_rms[f] = r.rms_m;
    }
  }
  if (options_.bridge_gaps) BridgeGaps(measured, frame_rms, coordinates, rms_m);
  return Status::Ok();
}

void InverseKinematics::BridgeGaps(
    const Eigen::Ref<const Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>>& measured,
    const std::vector<double>& frame_rms, Eigen::MatrixXd* coordinates, std::vector<double>* rms_m) {
  const int nf = static_cast<int>(measured.rows()), nm = model_.num_markers(), nz = model_.num_coordinates();
  auto seen = [&](int f, int m) { return std::isfinite(measured(f, 3 * m)); };
  // Markers the trial records at all: one it never sees is no gap.
  std::vector<char> recorded(nm, 0);
  for (int f = 0; f < nf; ++f)
    for (int m = 0; m < nm; ++m) recorded[m] |= seen(f, m) ? 1 : 0;
  // Anchors are read from the sweep's poses, before any frame is bridged.
  const Eigen::MatrixXd swept = *coordinates;
  Eigen::Matrix3Xd frame(3, nm);
  Eigen::VectorXd z(nz);
  std::vector<int> hidden;
  for (int f = 0; f < nf; ++f) {
    hidden.clear();
    int present = 0;
    for (int m = 0; m < nm; ++m) {
      if (seen(f, m)) ++present;
      else if (recorded[m]) hidden.push_back(m);
    }
    if (hidden.empty() || present < 3) continue;
    auto sees_all_hidden = [&](int g) {
      for (int m : hidden)
        if (!seen(g, m)) return false;
      return true;
    };
    int before = f - 1, after = f + 1;
    while (before >= 0 && !sees_all_hidden(before)) --before;
    while (after < nf && !sees_all_hidden(after)) ++after;
    if (before < 0 && after >= nf) continue;
    // Linear in time between the anchors, rotations along the shorter way round (an anchor
    // re-initialised from scratch may sit a turn away from the other).
    if (before < 0) {
      z = swept.row(after).transpose();
    } else if (after >= nf) {
      z = swept.row(before).transpose();
    } else {
      const double t = double(f - before) / double(after - before);
      for (int c = 0; c < nz; ++c) {
        double d = swept(after, c) - swept(before, c);
        if (model_.coordinates()[c].rotational) d = std::remainder(d, 2.0 * M_PI);
        z[c] = swept(before, c) + t * d;
      }
    }
    frame = Eigen::Map<const Eigen::Matrix3Xd>(measured.row(f).data(), 3, nm);
    const IkFrameResult r = Solve(frame, &z);
    // Both branches fit the seen markers alike; the bridged one is kept unless clearly worse.
    if (!(r.rms_m <= 1.1 * frame_rms[f] + 0.0005)) continue;
    coordinates->row(f) = z.transpose();
    if (rms_m) (*rms_m)[f] = r.rms_m;
  }
}

}  // namespace mocap::solver
