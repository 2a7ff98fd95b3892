#include "reconstruction/calibration_problem.h"

#include <cmath>

#include "model/rigid_align.h"

namespace mocap::reconstruction {

Eigen::Matrix3d ExpSO3(const Eigen::Vector3d& w) {
  const double theta = w.norm();
  if (theta < 1e-12) return Eigen::Matrix3d::Identity() + Skew(w);
  return Eigen::AngleAxisd(theta, w / theta).toRotationMatrix();
}

Eigen::Matrix3d LeftJacobianSO3(const Eigen::Vector3d& w) {
  const double t2 = w.squaredNorm();
  const Eigen::Matrix3d W = Skew(w);
  double a, b;  // (1 - cos t) / t^2, (t - sin t) / t^3
  if (t2 < 1e-8) {
    a = 0.5 - t2 / 24.0;
    b = 1.0 / 6.0 - t2 / 120.0;
  } else {
    const double t = std::sqrt(t2);
    a = (1.0 - std::cos(t)) / t2;
    b = (t - std::sin(t)) / (t2 * t);
  }
  return Eigen::Matrix3d::Identity() + a * W + b * W * W;
}

void WandFrame::SetDirection(const Eigen::Vector3d& direction) {
  d0 = direction.normalized();
  // e1: the axis least aligned with d0, made orthogonal.
  Eigen::Index k;
  d0.cwiseAbs().minCoeff(&k);
  e1 = (Eigen::Vector3d::Unit(k) - d0[k] * d0).normalized();
  e2 = d0.cross(e1);
}

WandBundleProblem::WandBundleProblem(std::vector<CameraModel> cameras,
                                     std::vector<WandFrame> frames,
                                     std::vector<double> marker_offsets_m, bool refine_intrinsics,
                                     int fixed_camera,
                                     const std::vector<CameraModel>& prior_intrinsics)
    : initial_(std::move(cameras)),
      current_(initial_),
      frames_(std::move(frames)),
      offsets_(std::move(marker_offsets_m)),
      refine_intrinsics_(refine_intrinsics) {
  for (const WandFrame& f : frames_) num_observations_ += static_cast<int>(f.observations.size());
  const int nc = static_cast<int>(initial_.size());
  index_.assign(nc, std::vector<int>(kPose + kIntrinsics, -1));
  std::vector<double> weights, targets, start;
  for (int c = 0; c < nc; ++c) {
    if (c != fixed_camera)
      for (int j = 0; j < kPose; ++j) {
        index_[c][j] = shared_dim_++;
        weights.push_back(0.0);
        targets.push_back(j < 3 ? 0.0 : initial_[c].t[j - 3]);
        start.push_back(targets.back());
      }
    if (refine_intrinsics_) {
      const CameraIntrinsics& k = initial_[c].intrinsics;
      const CameraIntrinsics& kp =
          prior_intrinsics.size() == initial_.size() ? prior_intrinsics[c].intrinsics : k;
      const double values[kIntrinsics] = {k.fx, k.fy, k.cx, k.cy, k.k1, k.k2};
      const double priors[kIntrinsics] = {kp.fx, kp.fy, kp.cx, kp.cy, kp.k1, kp.k2};
      // Weak priors: 5% of the focal length, 50 px, 0.2 on the distortion coefficients.
      const double sigmas[kIntrinsics] = {0.05 * kp.fx, 0.05 * kp.fy, 50, 50, 0.2, 0.2};
      for (int j = 0; j < kIntrinsics; ++j) {
        index_[c][kPose + j] = shared_dim_++;
        weights.push_back(1.0 / sigmas[j]);
        ++prior_rows_;
        targets.push_back(priors[j]);
        start.push_back(values[j]);
      }
    }
  }
  prior_weight_ = Eigen::Map<Eigen::VectorXd>(weights.data(), weights.size());
  prior_target_ = Eigen::Map<Eigen::VectorXd>(targets.data(), targets.size());
  start_ = Eigen::Map<Eigen::VectorXd>(start.data(), start.size());
  left_jacobian_.assign(nc, Eigen::Matrix3d::Identity());
}

Eigen::VectorXd WandBundleProblem::InitialState() const {
  const int nf = num_frames();
  Eigen::VectorXd x(5 * nf + shared_dim_);
  for (int f = 0; f < nf; ++f) {
    x.segment<3>(5 * f) = frames_[f].centre;
    x[5 * f + 3] = x[5 * f + 4] = 0.0;
  }
  x.tail(shared_dim_) = start_;
  return x;
}

bool WandBundleProblem::SetShared(const Eigen::VectorXd& p) {
  if (p.size() != shared_dim_ || !p.allFinite()) return false;
  for (size_t c = 0; c < initial_.size(); ++c) {
    CameraModel& cam = current_[c];
    cam = initial_[c];
    const std::vector<int>& idx = index_[c];
    left_jacobian_[c].setIdentity();
    if (idx[0] >= 0) {
      const Eigen::Vector3d w(p[idx[0]], p[idx[1]], p[idx[2]]);
      cam.R = ExpSO3(w) * initial_[c].R;
      left_jacobian_[c] = LeftJacobianSO3(w);
      cam.t = Eigen::Vector3d(p[idx[3]], p[idx[4]], p[idx[5]]);
    }
    if (idx[kPose] >= 0) {
      CameraIntrinsics& k = cam.intrinsics;
      k.fx = p[idx[kPose]];
      k.fy = p[idx[kPose + 1]];
      k.cx = p[idx[kPose + 2]];
      k.cy = p[idx[kPose + 3]];
      k.k1 = p[idx[kPose + 4]];
      k.k2 = p[idx[kPose + 5]];
      if (!(k.fx > 0 && k.fy > 0)) return false;
    }
  }
  return true;
}

Eigen::Vector3d WandBundleProblem::Direction(int f, const double* y) const {
  const WandFrame& fr = frames_[f];
  return (fr.d0 + y[3] * fr.e1 + y[4] * fr.e2).normalized();
}

Eigen::Vector3d WandBundleProblem::MarkerPosition(int f, const double* y, int k) const {
  return Eigen::Vector3d(y[0], y[1], y[2]) + offsets_[k] * Direction(f, y);
}

void WandBundleProblem::BlockStructure(std::vector<std::vector<int>>* y_columns,
                                       std::vector<std::vector<int>>* p_columns) const {
  y_columns->assign(initial_.size(), std::vector<int>{0, 1, 2, 3, 4});
  p_columns->assign(initial_.size(), {});
  for (size_t c = 0; c < initial_.size(); ++c) {
    (*p_columns)[c] = index_[c];
    if (!refine_intrinsics_) (*p_columns)[c].resize(kPose);
  }
}

class WandFrameEvaluator : public solver::FrameEvaluator {
 public:
  explicit WandFrameEvaluator(const WandBundleProblem& problem) : problem_(problem) {
    int most = 0;
    for (const WandFrame& f : problem.frames_)
      most = std::max(most, static_cast<int>(f.observations.size()));
    const int blocks = 3 * most;
    const int np = problem.refine_intrinsics_
                       ? WandBundleProblem::kPose + WandBundleProblem::kIntrinsics
                       : WandBundleProblem::kPose;
    np_ = np;
    blocks_.resize(blocks);
    residual_.resize(3 * blocks);
    jy_.resize(static_cast<size_t>(solver::kMaxBlockRows) * 5 * blocks);
    jp_.resize(static_cast<size_t>(solver::kMaxBlockRows) * np * blocks);
  }

  bool Evaluate(int f, const double* y, bool with_jacobians) override {
    const WandBundleProblem& pb = problem_;
    const WandFrame& frame = pb.frames_[f];
    const Eigen::Vector3d o(y[0], y[1], y[2]);
    const Eigen::Vector3d v = frame.d0 + y[3] * frame.e1 + y[4] * frame.e2;
    const double n = v.norm();
    const Eigen::Vector3d d = v / n;
    Eigen::Matrix<double, 3, 2> dd_dab;  // d(d)/d(a, b)
    if (with_jacobians) {
      const Eigen::Matrix3d proj = (Eigen::Matrix3d::Identity() - d * d.transpose()) / n;
      dd_dab.col(0) = proj * frame.e1;
      dd_dab.col(1) = proj * frame.e2;
    }
    num_blocks_ = 0;
    for (const WandObservation& obs : frame.observations) {
      const CameraModel& cam = pb.current_[obs.camera];
      const std::vector<int>& idx = pb.index_[obs.camera];
      for (int k = 0; k < 3; ++k) {
        const Eigen::Vector3d X = o + pb.offsets_[k] * d;
        const Eigen::Vector3d RX = cam.R * X;
        const Eigen::Vector3d Xc = RX + cam.t;
        Eigen::Matrix<double, 2, 3> J;
        const Eigen::Vector2d u = cam.ProjectCameraPoint(Xc, with_jacobians ? &J : nullptr);
        const int b = num_blocks_++;
        double* r = residual_.data() + 3 * b;
        r[0] = u.x() - obs.pixels[k].x();
        r[1] = u.y() - obs.pixels[k].y();
        r[2] = 0;
        if (!std::isfinite(r[0] + r[1]) || !(Xc.z() > 0)) return false;
        solver::ResidualBlock& blk = blocks_[b];
        blk.kind = obs.camera;
        blk.rows = 2;
        blk.residual = r;
        blk.num_y = 5;
        blk.y_index = kYIndex;
        blk.num_p = np_;
        blk.p_index = idx.data();
        blk.jy = blk.jp = nullptr;
        if (!with_jacobians) continue;
        const Eigen::Matrix<double, 2, 3> JR = J * cam.R;
        Eigen::Map<Eigen::Matrix<double, 3, 5>> jy(jy_.data() + 15 * b);
        jy.setZero();
        jy.topLeftCorner<2, 3>() = JR;
        jy.block<2, 2>(0, 3) = JR * (pb.offsets_[k] * dd_dab);
        Eigen::Map<Eigen::Matrix<double, 3, Eigen::Dynamic>> jp(jp_.data() + 3 * np_ * b, 3, np_);
        jp.setZero();
        // d Xc / d w = -[R X]_x J_l(w), J_l cached by SetShared.
        jp.block<2, 3>(0, 0) = J * (-Skew(RX) * pb.left_jacobian_[obs.camera]);
        jp.block<2, 3>(0, 3) = J;
        if (np_ > WandBundleProblem::kPose) {
          const CameraIntrinsics& ki = cam.intrinsics;
          const Eigen::Vector2d xy(Xc.x() / Xc.z(), Xc.y() / Xc.z());
          const Eigen::Vector2d dist = Distort(ki, xy);
          const double r2 = xy.squaredNorm();
          jp(0, 6) = dist.x();
          jp(1, 7) = dist.y();
          jp(0, 8) = 1.0;
          jp(1, 9) = 1.0;
          jp(0, 10) = ki.fx * xy.x() * r2;
          jp(1, 10) = ki.fy * xy.y() * r2;
          jp(0, 11) = ki.fx * xy.x() * r2 * r2;
          jp(1, 11) = ki.fy * xy.y() * r2 * r2;
        }
        blk.jy = jy_.data() + 15 * b;
        blk.jp = jp_.data() + 3 * np_ * b;
      }
    }
    return true;
  }
  int num_blocks() const override { return num_blocks_; }
  const solver::ResidualBlock& block(int i) const override { return blocks_[i]; }

 private:
  static constexpr int kYIndex[5] = {0, 1, 2, 3, 4};
  const WandBundleProblem& problem_;
  int np_ = 6;
  std::vector<solver::ResidualBlock> blocks_;
  std::vector<double> residual_, jy_, jp_;
  int num_blocks_ = 0;
};

std::unique_ptr<solver::FrameEvaluator> WandBundleProblem::NewEvaluator() const {
  return std::make_unique<WandFrameEvaluator>(*this);
}

}  // namespace mocap::reconstruction
