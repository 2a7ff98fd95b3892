#include "solver/inverse_kinematics.h"

#include <Eigen/Cholesky>
#include <cmath>
#include <limits>

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
  return true;
}

InverseKinematics::InverseKinematics(const Model& model, const Geometry& geometry, IkOptions options)
    : model_(model), geometry_(geometry), options_(options), data_(model) {
  const int nz = model.num_coordinates();
  jtj_.resize(nz, nz);
  damped_.resize(nz, nz);
  llt_ = Eigen::LLT<Eigen::MatrixXd>(nz);
  jtr_.resize(nz);
  jz_.resize(3, model.max_chain_coordinates());
}

namespace {
double SquaredError(const Model& model, const Geometry& g, const ModelData& d,
                    const Eigen::Matrix3Xd& measured, int* count) {
  double sum = 0;
  int n = 0;
  for (int m = 0; m < model.num_markers(); ++m) {
    if (!std::isfinite(measured(0, m))) continue;
    sum += (MarkerPosition(model, g, d, m) - measured.col(m)).squaredNorm();
    ++n;
  }
  if (count) *count = n;
  return sum;
}
}  // namespace

IkFrameResult InverseKinematics::Solve(const Eigen::Matrix3Xd& measured, Eigen::VectorXd* z,
                                       const std::vector<char>& free) {
  const int nz = model_.num_coordinates();
  IkFrameResult result;
  ForwardKinematics(model_, geometry_, *z, &data_);
  double cost = SquaredError(model_, geometry_, data_, measured, &result.markers);
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
      const Eigen::Vector3d r = MarkerPosition(model_, geometry_, data_, m) - measured.col(m);
      for (size_t a = 0; a < cols.size(); ++a) {
        jtr_[cols[a]] += jz.col(a).dot(r);
        for (size_t b = 0; b <= a; ++b) jtj_(cols[a], cols[b]) += jz.col(a).dot(jz.col(b));
      }
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
      const double new_cost = SquaredError(model_, geometry_, data_, measured, nullptr);
      if (new_cost < cost) {
        decrease = cost - new_cost;
        cost = new_cost;
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
  ForwardKinematics(model_, geometry_, *z, &data_);
  result.rms_m = result.markers > 0 ? std::sqrt(cost / result.markers) : 0.0;
  return result;
}

IkFrameResult InverseKinematics::Initialise(const Eigen::Matrix3Xd& measured, Eigen::VectorXd* z) {
  // The root joint (first in parents-first order) carries the subject's place and heading.
  const Joint& root = model_.joints()[0];
  std::vector<char> root_free(model_.num_coordinates(), 0);
  int heading = -1;
  for (const auto& el : root.elements) {
    if (el.coordinate < 0) continue;
    root_free[el.coordinate] = 1;
    if (heading < 0 && el.kind == ElementKind::kRotation) heading = el.coordinate;
  }
  // Start every try at the measured centroid so the translation is close from the outset.
  Eigen::Vector3d centroid = Eigen::Vector3d::Zero();
  int n = 0;
  for (int m = 0; m < model_.num_markers(); ++m)
    if (std::isfinite(measured(0, m))) {
      centroid += measured.col(m);
      ++n;
    }
  IkFrameResult best;
  best.rms_m = std::numeric_limits<double>::infinity();
  Eigen::VectorXd best_z = model_.DefaultCoordinates();
  if (n == 0) return best;
  centroid /= n;
  const int tries = heading >= 0 ? 4 : 1;
  for (int k = 0; k < tries; ++k) {
    Eigen::VectorXd trial = model_.DefaultCoordinates();
    if (heading >= 0) trial[heading] += k * M_PI / 2;
    // Shift the root's translations so the model's marker centroid lands on the data's.
    ForwardKinematics(model_, geometry_, trial, &data_);
    Eigen::Vector3d model_centroid = Eigen::Vector3d::Zero();
    for (int m = 0; m < model_.num_markers(); ++m)
      if (std::isfinite(measured(0, m))) model_centroid += MarkerPosition(model_, geometry_, data_, m);
    model_centroid /= n;
    const Eigen::Vector3d shift = centroid - model_centroid;
    for (const auto& el : root.elements)
      if (el.kind == ElementKind::kTranslation && el.coordinate >= 0 &&
          el.function.kind == CoordinateFunction::Kind::kIdentity)
        trial[el.coordinate] += el.axis.dot(shift);  // root translations are along lab axes
    Solve(measured, &trial, root_free);
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
  Eigen::VectorXd z = model_.DefaultCoordinates();
  Eigen::Matrix3Xd frame(3, nm);
  int first_valid = -1;
  for (int f = 0; f < nf; ++f) {
    frame = Eigen::Map<const Eigen::Matrix3Xd>(measured.row(f).data(), 3, nm);
    int present = 0;
    for (int m = 0; m < nm; ++m) present += std::isfinite(frame(0, m)) ? 1 : 0;
    IkFrameResult r;
    if (present >= 3) {
      if (first_valid < 0) {
        r = Initialise(frame, &z);
        first_valid = f;
      } else {
        Eigen::VectorXd warm = z;
        r = Solve(frame, &warm);
        if (r.rms_m > options_.restart_rms_m) {
          Eigen::VectorXd fresh;
          IkFrameResult r2 = Initialise(frame, &fresh);
          if (r2.rms_m < r.rms_m) {
            r = r2;
            warm = fresh;
          }
        }
        z = warm;
      }
    }
    coordinates->row(f) = z.transpose();
    if (rms_m) (*rms_m)[f] = r.rms_m;
  }
  if (first_valid < 0)
    return Status::Error("inverse kinematics: no frame has 3 or more of the model's markers");
  for (int f = 0; f < first_valid; ++f) coordinates->row(f) = coordinates->row(first_valid);
  return Status::Ok();
}

}  // namespace mocap::solver
