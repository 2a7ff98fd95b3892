#include "solver/marker_fit_problem.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "model/compare.h"
#include "solver/global_fit.h"
#include "solver/inverse_kinematics.h"
#include "solver/parallel.h"

namespace mocap::solver {
namespace {

// Whether joint `j` can follow a rotation u (in its parent's frame) of its parent segment's
// frame, so that turning the parent's frame, with its markers and child centres turned back, is
// a convention the data cannot see: a joint that turns about three coordinates re-poses; one
// whose moving rotations are all about fitted axes turns its axes with it; a joint without a
// moving rotation carries its child's geometry along; one whose moving rotations are about fixed
// axes follows only a rotation about the one axis they all share (a change of its coordinate).
bool ChildFollowsRotation(const Model& model, int j, const Eigen::Vector3d& u) {
  const Joint& joint = model.joints()[j];
  std::vector<int> coordinates;
  bool all_fitted = true, parallel = true;
  for (size_t e = 0; e < joint.elements.size(); ++e) {
    const JointElement& el = joint.elements[e];
    if (el.kind != ElementKind::kRotation || el.coordinate < 0 || el.function.IsConstant()) continue;
    if (std::find(coordinates.begin(), coordinates.end(), el.coordinate) == coordinates.end())
      coordinates.push_back(el.coordinate);
    all_fitted = all_fitted && model.axis_index(j, static_cast<int>(e)) >= 0;
    parallel = parallel && (joint.orientation * el.axis).normalized().cross(u.normalized()).norm() < 1e-6;
  }
  return coordinates.empty() || coordinates.size() >= 3 || all_fitted || parallel;
}

}  // namespace

class MarkerFrameEvaluator : public FrameEvaluator {
  using Vector6 = Eigen::Matrix<double, 6, 1>;
  // PoseNormalEquations' and AddNormalEquations' structure.
  struct PosePair {
    int a, b;       // pose elements, b's joint on a's chain
    int offset;     // of U's lower-triangle entry (column-major, ny x ny)
    double factor;  // 2 for two elements of one coordinate
  };
  struct SegmentSums {
    double mass;
    Eigen::Vector3d first, error, moment;
    double second[6];  // xx, yy, zz, xy, xz, yz
    void SetZero() {
      mass = 0;
      first.setZero();
      error.setZero();
      moment.setZero();
      std::fill(second, second + 6, 0.0);
    }
    void Add(const SegmentSums& o) {
      mass += o.mass;
      first += o.first;
      error += o.error;
      moment += o.moment;
      for (int k = 0; k < 6; ++k) second[k] += o.second[k];
    }
  };
  struct ParamTwist {
    int joint;
    enum Type { kScale, kCentre, kAlpha, kBeta } type;
    int index;  // the centre's column, or the axis's element
    int k;      // the axis's flattened element
    int free;   // shared index
  };
  struct ParamPair {
    int t, a;          // shared twist, pose element on one chain
    bool twist_force;  // a at or above the twist's joint: I of the twist's subtree, else of a's
  };

 public:
  explicit MarkerFrameEvaluator(const MarkerFitProblem& problem)
      : problem_(problem), data_(problem.model()) {
    const Model& model = problem.model();
    const int nm = model.num_markers();
    const int nl = static_cast<int>(problem.coordinate_limits().size());
    blocks_.resize(nm + nl);
    residual_.resize(3 * (nm + nl));
    jy_.resize(nm + nl, Eigen::Matrix<double, 3, Eigen::Dynamic>(3, model.max_chain_coordinates()));
    jp_.resize(nm, Eigen::Matrix<double, 3, Eigen::Dynamic>(3, model.max_chain_parameters()));
    z_.resize(model.num_coordinates());
    // Flattened (joint, element) indices, and each marker's dh/dz terms in MarkerJacobian's order.
    element_offset_.resize(model.num_joints() + 1, 0);
    for (int j = 0; j < model.num_joints(); ++j)
      element_offset_[j + 1] = element_offset_[j] + static_cast<int>(model.joints()[j].elements.size());
    const int ne = element_offset_.back();
    world_axis_.resize(ne);
    translation_column_.resize(ne);
    omega_alpha_.resize(ne);
    omega_beta_.resize(ne);
    centre_column_.resize(model.num_joints());
    scaled_rotation_.resize(model.num_segments());
    z_terms_.resize(nm);
    for (int m = 0; m < nm; ++m)
      ForEachDrivenElement(model, m, [&](int j, int e, int c) {
        z_terms_[m].push_back({j, e, element_offset_[j] + e, c,
                               model.joints()[j].elements[e].kind == ElementKind::kRotation});
      });
    // PoseNormalEquations: every driven element, and the pairs of them on one chain (the second
    // at or above the first: the markers moved by both are those below the first).
    for (int j = 0; j < model.num_joints(); ++j) {
      const Joint& jt = model.joints()[j];
      for (size_t e = 0; e < jt.elements.size(); ++e) {
        const JointElement& el = jt.elements[e];
        if (el.coordinate < 0 || el.function.IsConstant()) continue;
        pose_elements_.push_back({j, static_cast<int>(e), element_offset_[j] + static_cast<int>(e), el.coordinate,
                                  el.kind == ElementKind::kRotation});
      }
    }
    const int ne_pose = static_cast<int>(pose_elements_.size());
    for (int a = 0; a < ne_pose; ++a) {
      const std::vector<int>& chain = model.chain(model.joints()[pose_elements_[a].joint].child);
      for (int b = 0; b <= a; ++b) {
        const int jb = pose_elements_[b].joint;
        if (std::find(chain.begin(), chain.end(), jb) == chain.end()) continue;
        const int ca = pose_elements_[a].column, cb = pose_elements_[b].column;
        // Two elements of one coordinate meet twice in U_cc (J_c is their sum).
        pose_pairs_.push_back({a, b, std::max(ca, cb) + std::min(ca, cb) * model.num_coordinates(),
                               ca == cb && a != b ? 2.0 : 1.0});
      }
    }
    block_marker_.resize(nm);
    block_scale_.resize(nm);
    block_position_.resize(nm);
    // AddNormalEquations: the shared columns every marker below a joint shares (its parent's
    // scale, its centre, its axes), as twists, and the pose elements on the same chain.
    const std::vector<int>& free = problem.free_index();
    for (int j = 0; j < model.num_joints(); ++j) {
      const Joint& jt = model.joints()[j];
      if (jt.parent >= 0 && free[model.scale_index(jt.parent)] >= 0)
        param_twists_.push_back({j, ParamTwist::kScale, 0, 0, free[model.scale_index(jt.parent)]});
      if (model.centre_index(j) >= 0)
        for (int k = 0; k < 3; ++k)
          if (free[model.centre_index(j) + k] >= 0)
            param_twists_.push_back({j, ParamTwist::kCentre, k, 0, free[model.centre_index(j) + k]});
      for (size_t e = 0; e < jt.elements.size(); ++e) {
        const int ai = model.axis_index(j, static_cast<int>(e));
        if (ai < 0) continue;
        const int k = element_offset_[j] + static_cast<int>(e);
        if (free[ai] >= 0) param_twists_.push_back({j, ParamTwist::kAlpha, static_cast<int>(e), k, free[ai]});
        if (free[ai + 1] >= 0) param_twists_.push_back({j, ParamTwist::kBeta, static_cast<int>(e), k, free[ai + 1]});
      }
    }
    for (int t = 0; t < static_cast<int>(param_twists_.size()); ++t) {
      const int jt = param_twists_[t].joint;
      const std::vector<int>& chain = model.chain(model.joints()[jt].child);
      for (int a = 0; a < ne_pose; ++a) {
        const int ja = pose_elements_[a].joint;
        const std::vector<int>& chain_a = model.chain(model.joints()[ja].child);
        if (std::find(chain.begin(), chain.end(), ja) != chain.end())  // a at or above the twist's joint
          param_pairs_.push_back({t, a, true});
        else if (std::find(chain_a.begin(), chain_a.end(), jt) != chain_a.end())  // a below it
          param_pairs_.push_back({t, a, false});
      }
    }
    param_twist_.resize(param_twists_.size());
    param_force_.resize(param_twists_.size());
    sums_.resize(model.num_segments());
    twist_.resize(ne_pose);
    force_.resize(ne_pose);
  }

  // J_y^T J_y and J_y^T r from per-segment sums, as the composite-rigid-body algorithm forms a
  // tree's mass matrix (Featherstone, "Rigid Body Dynamics Algorithms", 2008, ch. 6). Each
  // element's column of a marker's dh/dz is a twist evaluated at the marker, xi(x) = w x y + v
  // (y = x - a reference point; w = 0 for a translation), and the same twist for every marker
  // below its joint. So sum_m w_m xi_a(x_m) . xi_b(x_m) over the markers below both is
  // xi_a . I xi_b with I the weighted markers' "spatial inertia" below the deeper joint: their
  // sum of weights M, first moment h = sum w y and second moment Q = sum w y y^T,
  //     I (w', v') = (K w' + h x v', M v' + w' x h),  K = tr(Q) 1 - Q,
  // and J_y^T r from sum w e and sum w y x e (e = x - measurement). Per frame that is one pass
  // over the markers and a handful of multiply-adds per U entry, against three per marker per
  // entry summed marker by marker (AddBlockNormalEquations): the per-frame solves' main work.
  // Moments are taken about the root segment's origin, so they do not grow with the distance
  // walked from the lab's origin.
  bool PoseNormalEquations(int frame, const double* y, int ny, double* u, double* g) override {
    const Model& model = problem_.model();
    const Geometry& geometry = problem_.geometry();
    z_ = Eigen::Map<const Eigen::VectorXd>(y, model.num_coordinates());
    ForwardKinematics(model, geometry, z_, &data_);
    PrepareJacobians(false);
    shared_ready_ = false;  // the blocks no longer match the pose
    const Eigen::Vector3d origin = data_.segment_position[model.joints()[0].child];
    for (SegmentSums& s : sums_) s.SetZero();
    const double* meas = problem_.measurements().row(frame).data();
    // The residuals also go to the blocks, as Evaluate leaves them (their Jacobians stale): the
    // frame's cost at y then needs no second evaluation (EvaluatedFrameSquaredNorm).
    num_blocks_ = 0;
    for (int m = 0; m < model.num_markers(); ++m) {
      if (!std::isfinite(meas[3 * m])) continue;
      const double scale = problem_.residual_scale(m) * std::sqrt(problem_.sample_weight(frame, m));
      const Eigen::Vector3d x = MarkerPosition(model, geometry, data_, m);
      Eigen::Vector3d r;
      for (int k = 0; k < 3; ++k) r[k] = scale * (x[k] - meas[3 * m + k]);
      if (!std::isfinite(r[0] + r[1] + r[2])) return false;
      const std::vector<int>& ycols = model.marker_coordinates(m);
      const std::vector<int>& pcols = problem_.marker_free_columns(m);
      SetBlock(num_blocks_++, problem_.block_kind(m), 3, r.data(), static_cast<int>(ycols.size()), ycols.data(),
               static_cast<int>(pcols.size()), pcols.data());
      AddMarker(scale * scale, x - origin, scale * r, &sums_[model.markers()[m].segment]);
    }
    num_marker_blocks_ = num_blocks_;
    PoseTwists(origin, g);
    for (const PosePair& pp : pose_pairs_) u[pp.offset] += pp.factor * twist_[pp.b].dot(force_[pp.a]);
    // Coordinate limits: a one-row block where the frame is beyond a range, as Evaluate has it.
    const auto& limits = problem_.coordinate_limits();
    for (size_t i = 0; i < limits.size(); ++i) {
      const auto& lim = limits[i];
      const double excess = RangeExcess(model.coordinates()[lim.coordinate], y[lim.coordinate]);
      if (excess == 0.0) continue;
      const double r = lim.weight * excess;
      if (!std::isfinite(r)) return false;
      SetBlock(num_blocks_++, problem_.limit_kind(static_cast<int>(i)), 1, &r, 1, &lim.coordinate, 0, nullptr);
      u[static_cast<size_t>(lim.coordinate) * (ny + 1)] += lim.weight * lim.weight;
      g[lim.coordinate] += lim.weight * r;
    }
    return true;
  }

  // The whole frame's normal equations from the same sums (see PoseNormalEquations), after
  // Evaluate with Jacobians: U and J_y^T r as there; J_y^T J_p and J_p^T r for the shared
  // columns that every marker below a joint shares (its parent's scale, its centre and its axes:
  // each a twist, a constant one for the first two) from the subtree's sums; only a marker's own
  // columns (its position, its segment's scale) from its own Jacobians, one marker at a time.
  bool AddNormalEquations(const NormalLayout& layout, double* u, double* w, double* gy, double* gp) override {
    if (!shared_ready_) return false;
    const Model& model = problem_.model();
    if (layout.u_offset != layout_u_ || layout.w_offset != layout_w_) SetLayout(layout);
    const Eigen::Vector3d origin = data_.segment_position[model.joints()[0].child];
    for (SegmentSums& s : sums_) s.SetZero();
    for (int b = 0; b < num_marker_blocks_; ++b) {
      const int m = block_marker_[b];
      const double scale = block_scale_[b];
      const ResidualBlock& blk = blocks_[b];
      const Eigen::Vector3d p = block_position_[b] - origin;
      const Eigen::Vector3d r(blk.residual[0], blk.residual[1], blk.residual[2]);
      AddMarker(scale * scale, p, scale * r, &sums_[model.markers()[m].segment]);
      // The marker's own columns: its position (the first three) and its segment's scale (the last).
      const int* offset = own_offset_[m].data();
      for (int c : {0, 1, 2, blk.num_p - 1}) {
        const int q = blk.p_index[c];
        if (q < 0) continue;
        const double* jp = blk.jp + c * kMaxBlockRows;
        if (gp) gp[q] += jp[0] * r[0] + jp[1] * r[1] + jp[2] * r[2];
        for (int a = 0; a < blk.num_y; ++a) {
          const double* jy = blk.jy + a * kMaxBlockRows;
          w[*offset++] += jy[0] * jp[0] + jy[1] * jp[1] + jy[2] * jp[2];
        }
      }
    }
    PoseTwists(origin, gy);
    for (size_t i = 0; i < pose_pairs_.size(); ++i) {
      const PosePair& pp = pose_pairs_[i];
      u[pose_pair_offset_[i]] += pp.factor * twist_[pp.b].dot(force_[pp.a]);
    }
    for (size_t t = 0; t < param_twists_.size(); ++t) {
      const ParamTwist& pt = param_twists_[t];
      const Joint& jt = model.joints()[pt.joint];
      Vector6& tw = param_twist_[t];
      switch (pt.type) {
        case ParamTwist::kScale:
          tw << Eigen::Vector3d::Zero(), centre_column_[pt.joint];
          break;
        case ParamTwist::kCentre:
          tw.head<3>().setZero();
          if (jt.parent >= 0) tw.tail<3>() = scaled_rotation_[jt.parent].col(pt.index);
          else tw.tail<3>() = Eigen::Vector3d::Unit(pt.index);
          break;
        case ParamTwist::kAlpha:
        case ParamTwist::kBeta: {
          const Eigen::Vector3d& omega = pt.type == ParamTwist::kAlpha ? omega_alpha_[pt.k] : omega_beta_[pt.k];
          tw << omega, omega.cross(origin - data_.element_origin[pt.joint][pt.index]);
          break;
        }
      }
      const SegmentSums& s = sums_[jt.child];
      Force(s, tw, &param_force_[t]);
      if (gp) gp[pt.free] += tw.head<3>().dot(s.moment) + tw.tail<3>().dot(s.error);
    }
    // W's shared columns: I of the deeper joint's subtree times one twist, dotted with the other.
    for (const WPair& wp : w_twist_force_) w[wp.offset] += twist_[wp.a].dot(param_force_[wp.t]);
    for (const WPair& wp : w_force_twist_) w[wp.offset] += param_twist_[wp.t].dot(force_[wp.a]);
    for (int b = num_marker_blocks_; b < num_blocks_; ++b) {  // coordinate limits: one row on one y
      const ResidualBlock& blk = blocks_[b];
      const int c = blk.y_index[0];
      u[layout.u_offset[c * layout.ny + c]] += blk.jy[0] * blk.jy[0];
      if (gy) gy[c] += blk.jy[0] * blk.residual[0];
    }
    return true;
  }

 private:
  // Where AddNormalEquations' entries go in `layout` (kept until another layout is given).
  void SetLayout(const NormalLayout& layout) {
    const Model& model = problem_.model();
    layout_u_ = layout.u_offset;
    layout_w_ = layout.w_offset;
    pose_pair_offset_.clear();
    for (const PosePair& pp : pose_pairs_)
      pose_pair_offset_.push_back(
          layout.u_offset[pose_elements_[pp.a].column * layout.ny + pose_elements_[pp.b].column]);
    w_twist_force_.clear();
    w_force_twist_.clear();
    for (const ParamPair& pp : param_pairs_) {
      const int offset =
          layout.w_offset[pose_elements_[pp.a].column * layout.np + param_twists_[pp.t].free];
      if (offset < 0) continue;  // no marker has both: no marker below moves with both
      (pp.twist_force ? w_twist_force_ : w_force_twist_).push_back({offset, pp.a, pp.t});
    }
    own_offset_.assign(model.num_markers(), {});
    for (int m = 0; m < model.num_markers(); ++m) {
      const std::vector<int>& ys = model.marker_coordinates(m);
      const std::vector<int>& ps = problem_.marker_free_columns(m);
      if (!problem_.observed(m) || ps.size() < 4) continue;
      for (int c : {0, 1, 2, static_cast<int>(ps.size()) - 1}) {
        if (ps[c] < 0) continue;
        for (int y : ys) own_offset_[m].push_back(layout.w_offset[y * layout.np + ps[c]]);
      }
    }
  }

  // Block b's residuals and columns as Evaluate sets them; its Jacobians left as they were.
  void SetBlock(int b, int kind, int rows, const double* r, int num_y, const int* y_index, int num_p,
                const int* p_index) {
    double* out = residual_.data() + 3 * b;
    for (int k = 0; k < rows; ++k) out[k] = r[k];
    ResidualBlock& blk = blocks_[b];
    blk.kind = kind;
    blk.rows = rows;
    blk.residual = out;
    blk.num_y = num_y;
    blk.y_index = y_index;
    blk.num_p = num_p;
    blk.p_index = p_index;
    blk.jy = jy_[b].data();
    blk.jp = num_p > 0 ? jp_[b].data() : nullptr;
  }
  static void AddMarker(double w, const Eigen::Vector3d& p, const Eigen::Vector3d& wr, SegmentSums* s) {
    const Eigen::Vector3d wp = w * p;
    s->mass += w;
    s->first += wp;
    s->second[0] += wp[0] * p[0];
    s->second[1] += wp[1] * p[1];
    s->second[2] += wp[2] * p[2];
    s->second[3] += wp[0] * p[1];
    s->second[4] += wp[0] * p[2];
    s->second[5] += wp[1] * p[2];
    s->error += wr;
    s->moment += p.cross(wr);
  }
  // I (w, v) for the sums' spatial inertia (see PoseNormalEquations).
  static void Force(const SegmentSums& s, const Vector6& twist, Vector6* force) {
    const Eigen::Vector3d w = twist.head<3>(), v = twist.tail<3>();
    if (w.isZero()) {  // a translation or a constant column: the same figures, a third of the work
      force->head<3>() = s.first.cross(v);
      force->tail<3>() = s.mass * v;
      return;
    }
    const Eigen::Vector3d qw(s.second[0] * w[0] + s.second[3] * w[1] + s.second[4] * w[2],
                             s.second[3] * w[0] + s.second[1] * w[1] + s.second[5] * w[2],
                             s.second[4] * w[0] + s.second[5] * w[1] + s.second[2] * w[2]);
    force->head<3>() = (s.second[0] + s.second[1] + s.second[2]) * w - qw + s.first.cross(v);
    force->tail<3>() = s.mass * v + w.cross(s.first);
  }
  // From the segments' own sums: the composite sums, each pose element's twist and I times it,
  // and J_y^T r into g (unless null).
  void PoseTwists(const Eigen::Vector3d& origin, double* g) {
    const Model& model = problem_.model();
    // Composite sums: each segment's plus everything below it (joints come parents first).
    for (int j = model.num_joints() - 1; j >= 0; --j) {
      const Joint& jt = model.joints()[j];
      if (jt.parent >= 0) sums_[jt.parent].Add(sums_[jt.child]);
    }
    const int ne_pose = static_cast<int>(pose_elements_.size());
    for (int a = 0; a < ne_pose; ++a) {
      const ZTerm& pe = pose_elements_[a];
      const SegmentSums& s = sums_[model.joints()[pe.joint].child];
      Vector6& twist = twist_[a];
      if (pe.rotation) {
        const Eigen::Vector3d w = data_.element_derivative[pe.joint][pe.element] * world_axis_[pe.k];
        twist << w, w.cross(origin - data_.element_origin[pe.joint][pe.element]);
      } else {
        twist << Eigen::Vector3d::Zero(), translation_column_[pe.k];
      }
      Force(s, twist, &force_[a]);
      if (g) g[pe.column] += twist.head<3>().dot(s.moment) + twist.tail<3>().dot(s.error);
    }
  }

 public:

  bool Evaluate(int frame, const double* y, bool with_jacobians) override {
    return Evaluate(frame, y, with_jacobians, with_jacobians);
  }
  bool EvaluatePoseJacobians(int frame, const double* y) override { return Evaluate(frame, y, true, false); }

 private:
  bool Evaluate(int frame, const double* y, bool with_jacobians, bool with_shared_jacobians) {
    const Model& model = problem_.model();
    const Geometry& g = problem_.geometry();
    z_ = Eigen::Map<const Eigen::VectorXd>(y, model.num_coordinates());
    ForwardKinematics(model, g, z_, &data_);
    if (with_jacobians) PrepareJacobians(with_shared_jacobians);
    const double* meas = problem_.measurements().row(frame).data();
    num_blocks_ = 0;
    num_marker_blocks_ = 0;
    shared_ready_ = false;
    for (int m = 0; m < model.num_markers(); ++m) {
      if (!std::isfinite(meas[3 * m])) continue;
      const double scale = problem_.residual_scale(m) * std::sqrt(problem_.sample_weight(frame, m));
      const Eigen::Vector3d x = MarkerPosition(model, g, data_, m);
      block_marker_[num_blocks_] = m;
      block_position_[num_blocks_] = x;
      block_scale_[num_blocks_] = scale;
      double* r = residual_.data() + 3 * num_blocks_;
      for (int k = 0; k < 3; ++k) r[k] = scale * (x[k] - meas[3 * m + k]);
      if (!std::isfinite(r[0] + r[1] + r[2])) return false;
      ResidualBlock& blk = blocks_[num_blocks_];
      blk.kind = problem_.block_kind(m);
      blk.rows = 3;
      blk.residual = r;
      const auto& ycols = model.marker_coordinates(m);
      const auto& pcols = problem_.marker_free_columns(m);
      blk.num_y = static_cast<int>(ycols.size());
      blk.y_index = ycols.data();
      blk.num_p = static_cast<int>(pcols.size());
      blk.p_index = pcols.data();
      if (with_jacobians) {
        auto jy = jy_[num_blocks_].leftCols(blk.num_y);
        PoseJacobian(m, x, &jy);
        jy *= scale;
        blk.jy = jy_[num_blocks_].data();
        if (with_shared_jacobians) {
          auto jp = jp_[num_blocks_].leftCols(blk.num_p);
          SharedJacobian(m, x, &jp);
          jp *= scale;
        }
        blk.jp = jp_[num_blocks_].data();
      }
      ++num_blocks_;
    }
    num_marker_blocks_ = num_blocks_;
    shared_ready_ = with_jacobians && with_shared_jacobians;
    // Coordinate limits: a block only where the frame is beyond a range (zero residual inside).
    const auto& limits = problem_.coordinate_limits();
    for (size_t i = 0; i < limits.size(); ++i) {
      const auto& lim = limits[i];
      const double excess = RangeExcess(problem_.model().coordinates()[lim.coordinate], y[lim.coordinate]);
      if (excess == 0.0) continue;
      double* r = residual_.data() + 3 * num_blocks_;
      r[0] = lim.weight * excess;
      ResidualBlock& blk = blocks_[num_blocks_];
      blk.kind = problem_.limit_kind(static_cast<int>(i));
      blk.rows = 1;
      blk.residual = r;
      blk.num_y = 1;
      blk.y_index = &lim.coordinate;  // its one y column
      blk.num_p = 0;
      blk.p_index = nullptr;
      if (with_jacobians) {
        jy_[num_blocks_](0, 0) = lim.weight;
        blk.jy = jy_[num_blocks_].data();
        blk.jp = nullptr;
      }
      ++num_blocks_;
    }
    return true;
  }

 public:
  int num_blocks() const override { return num_blocks_; }
  const ResidualBlock& block(int i) const override { return blocks_[i]; }

 private:
  // What MarkerJacobian computes per marker but depends only on the pose: world axes, the
  // axis-angle derivatives' rotation vectors (and their sines and cosines), each chain joint's
  // scale column and each segment's s R. Formed once per frame instead of once per marker on
  // the chain (the full body's 39 markers share 15 joints); the per-marker products below are
  // MarkerJacobian's own expressions in its order, so the Jacobians are the same to rounding
  // (tests/test_fit.cpp checks it).
  void PrepareJacobians(bool shared) {
    const Model& model = problem_.model();
    const Geometry& g = problem_.geometry();
    const ModelData& d = data_;
    for (int j = 0; j < model.num_joints(); ++j) {
      const Joint& jt = model.joints()[j];
      for (size_t e = 0; e < jt.elements.size(); ++e) {
        const JointElement& el = jt.elements[e];
        const int k = element_offset_[j] + static_cast<int>(e);
        if (el.coordinate >= 0 && !el.function.IsConstant()) {
          world_axis_[k] = d.element_rotation[j][e] * g.axis[j][e];
          if (el.kind != ElementKind::kRotation)
            translation_column_[k] = (TranslationScale(jt, el, g) * d.element_derivative[j][e]) * world_axis_[k];
        }
        if (!shared || model.axis_index(j, static_cast<int>(e)) < 0) continue;
        const double v = d.element_value[j][e];
        const Eigen::Vector3d& a = g.axis[j][e];
        const Eigen::Matrix3d& rb = d.element_rotation[j][e];
        const double sv = std::sin(v), cv1 = 1.0 - std::cos(v);
        const Eigen::Vector3d& da = g.axis_d_alpha[j][e];
        const Eigen::Vector3d& db = g.axis_d_beta[j][e];
        omega_alpha_[k] = rb * (sv * da + cv1 * a.cross(da));
        omega_beta_[k] = rb * (sv * db + cv1 * a.cross(db));
      }
      if (!shared || jt.parent < 0) continue;
      Eigen::Vector3d& col = centre_column_[j];
      col = d.segment_rotation[jt.parent] * g.centre[j];
      for (size_t e = 0; e < jt.elements.size(); ++e)
        if (ScalesWithParent(jt, jt.elements[e]))
          col += d.element_rotation[j][e] * (g.axis[j][e] * d.element_value[j][e]);
    }
    if (!shared) return;
    for (int s = 0; s < model.num_segments(); ++s) scaled_rotation_[s] = g.scale[s] * d.segment_rotation[s];
  }

  // MarkerJacobian(model, g, data_, m, jz, jp) from the prepared terms: its dh/dz part ...
  template <typename DerivedZ>
  void PoseJacobian(int m, const Eigen::Vector3d& x, Eigen::MatrixBase<DerivedZ>* jz) const {
    const ModelData& d = data_;
    jz->setZero();
    for (const ZTerm& t : z_terms_[m]) {
      if (t.rotation)
        jz->col(t.column) += d.element_derivative[t.joint][t.element] *
                             world_axis_[t.k].cross(x - d.element_origin[t.joint][t.element]);
      else
        jz->col(t.column) += translation_column_[t.k];
    }
  }
  // ... and its dh/dp part.
  template <typename DerivedP>
  void SharedJacobian(int m, const Eigen::Vector3d& x, Eigen::MatrixBase<DerivedP>* jp) const {
    const Model& model = problem_.model();
    const Geometry& g = problem_.geometry();
    const ModelData& d = data_;
    const int s = model.markers()[m].segment;
    int c = 0;
    jp->template middleCols<3>(c) = scaled_rotation_[s];
    c += 3;
    for (int j : model.chain(s)) {
      const Joint& jt = model.joints()[j];
      const int parent = jt.parent;
      if (parent >= 0) jp->col(c++) = centre_column_[j];
      if (model.centre_index(j) >= 0) {
        if (parent >= 0)
          jp->template middleCols<3>(c) = scaled_rotation_[parent];
        else
          jp->template middleCols<3>(c).setIdentity();
        c += 3;
      }
      for (size_t e = 0; e < jt.elements.size(); ++e) {
        if (model.axis_index(j, static_cast<int>(e)) < 0) continue;
        const int k = element_offset_[j] + static_cast<int>(e);
        const Eigen::Vector3d r = x - d.element_origin[j][e];
        jp->col(c++) = omega_alpha_[k].cross(r);
        jp->col(c++) = omega_beta_[k].cross(r);
      }
    }
    jp->col(c) = d.segment_rotation[s] * g.marker[m];
  }

  struct ZTerm {
    int joint, element, k, column;
    bool rotation;
  };
  std::vector<ParamTwist> param_twists_;
  std::vector<ParamPair> param_pairs_;
  struct WPair {
    int offset, a, t;  // compact W, pose element, shared twist
  };
  std::vector<Vector6> param_twist_, param_force_;
  std::vector<WPair> w_twist_force_, w_force_twist_;
  std::vector<std::vector<int>> own_offset_;  // per marker: W offsets of its own columns, by y
  std::vector<Eigen::Vector3d> block_position_;
  const int* layout_u_ = nullptr;
  const int* layout_w_ = nullptr;
  std::vector<int> pose_pair_offset_;
  std::vector<int> block_marker_;
  std::vector<double> block_scale_;
  int num_marker_blocks_ = 0;
  bool shared_ready_ = false;
  std::vector<ZTerm> pose_elements_;  // every driven element (ZTerm's column: its coordinate)
  std::vector<PosePair> pose_pairs_;
  std::vector<SegmentSums> sums_;
  std::vector<Vector6> twist_, force_;  // per pose element: (w, v) and I (w, v)
  std::vector<int> element_offset_;
  std::vector<Eigen::Vector3d> world_axis_, translation_column_, omega_alpha_, omega_beta_;
  std::vector<Eigen::Vector3d> centre_column_;
  std::vector<Eigen::Matrix3d> scaled_rotation_;
  std::vector<std::vector<ZTerm>> z_terms_;

  const MarkerFitProblem& problem_;
  ModelData data_;
  Eigen::VectorXd z_;
  std::vector<ResidualBlock> blocks_;
  std::vector<double> residual_;
  std::vector<Eigen::Matrix<double, 3, Eigen::Dynamic>> jy_, jp_;
  int num_blocks_ = 0;
};

MarkerFitProblem::MarkerFitProblem(const Model& model, formats::RowMatrix measurements,
                                   const FitOptions& options, bool relax_holds)
    : model_(model), measurements_(std::move(measurements)), geometry_(model) {
  const bool free_groups[4] = {options.fit_scales, options.fit_centres, options.fit_axes,
                               options.fit_markers};
  const double marker_sigma_m = options.marker_sigma_m;
  const double prior_sigma_scale = options.prior_sigma_scale;
  const double prior_sigma_position_m = options.prior_sigma_position_m;
  const double prior_sigma_axis_rad = options.prior_sigma_axis_rad;
  const int nm = model.num_markers();
  p0_ = model.InitialParameters();
  observed_.assign(nm, 0);
  for (int f = 0; f < measurements_.rows(); ++f)
    for (int m = 0; m < nm; ++m)
      if (std::isfinite(measurements_(f, 3 * m))) {
        observed_[m] = 1;
        ++samples_;
      }
  block_kind_.assign(nm, -1);
  int kinds = 0;
  for (int m = 0; m < nm; ++m)
    if (observed_[m]) block_kind_[m] = kinds++;
  first_limit_kind_ = kinds;
  for (int c : LimitedCoordinates(model)) {
    const Coordinate& co = model.coordinates()[c];
    const double sigma = co.rotational ? options.coordinate_limit_sigma_rad : options.coordinate_limit_sigma_m;
    if (!(sigma > 0)) continue;
    limits_.push_back({c, 1.0 / sigma});
  }
  free_index_.assign(model.num_parameters(), -1);
  std::vector<double> weights;
  for (int i = 0; i < model.num_parameters(); ++i) {
    const ParameterInfo& info = model.parameters()[i];
    if (!free_groups[static_cast<int>(info.group)]) continue;
    if (std::find(options.fixed_parameters.begin(), options.fixed_parameters.end(), info.name) !=
        options.fixed_parameters.end())
      continue;
    const bool held = std::find(options.held_parameters.begin(), options.held_parameters.end(), info.name) !=
                      options.held_parameters.end();
    const double held_sigma =
        info.group == ParameterGroup::kAxis ? options.held_axis_sigma_rad : options.held_centre_sigma_m;
    if (held) has_holds_ = has_holds_ || held_sigma > 0;
    if (held && !(relax_holds && held_sigma > 0)) continue;
    if (info.group == ParameterGroup::kMarker &&
        (!observed_[info.object] ||
         std::find(options.fixed_markers.begin(), options.fixed_markers.end(),
                   model.markers()[info.object].name) != options.fixed_markers.end()))
      continue;
    free_index_[i] = static_cast<int>(free_parameters_.size());
    free_parameters_.push_back(i);
    double sigma = prior_sigma_position_m;
    if (info.group == ParameterGroup::kScale) sigma = prior_sigma_scale;
    if (info.group == ParameterGroup::kAxis) sigma = prior_sigma_axis_rad;
    if (info.group == ParameterGroup::kMarker && model.markers()[info.object].fixed)
      sigma = options.prior_sigma_fixed_marker_m;
    if (held) sigma = held_sigma;
    weights.push_back(1.0 / sigma);
  }
  prior_weight_ = Eigen::Map<Eigen::VectorXd>(weights.data(), weights.size());
  prior_target_ = InitialShared();
  marker_free_columns_.resize(nm);
  residual_scale_.resize(nm);
  marker_sigma_.resize(nm);
  for (int m = 0; m < nm; ++m) {
    for (int p : model.marker_parameters(m)) marker_free_columns_[m].push_back(free_index_[p]);
    SetMarkerSigma(m, marker_sigma_m);
  }
  hold_hinge_centres_ = options.hold_hinge_centres_along_axis;
  held_centre_.assign(model.num_joints(), 0);
  for (int j = 0; j < model.num_joints(); ++j) {
    const int base = model.centre_index(j);
    if (base < 0) continue;
    for (int k = 0; k < 3; ++k)
      for (const std::vector<std::string>* held : {&options.fixed_parameters, &options.held_parameters})
        if (std::find(held->begin(), held->end(), model.parameters()[base + k].name) != held->end())
          held_centre_[j] = 1;
  }
  BuildGaugeRows(options.gauge_sigma_m,
                 relax_holds && options.held_centre_sigma_m > 0 ? options.held_centre_sigma_m : options.gauge_sigma_m,
                 options.held_centre_sigma_m > 0);
  periodic_ = PeriodicCoordinates(model);
  frame_prior_weight_.resize(model.num_coordinates());
  for (int c = 0; c < model.num_coordinates(); ++c)
    frame_prior_weight_[c] = 1.0 / (model.coordinates()[c].rotational ? options.frame_prior_sigma_rad
                                                                        : options.frame_prior_sigma_m);
}

void MarkerFitProblem::SetMarkerSigma(int m, double sigma_m) {
  marker_sigma_[m] = sigma_m;
  residual_scale_[m] = std::sqrt(model_.markers()[m].weight) / sigma_m;
}

void MarkerFitProblem::SetFramePriorTargets(const Eigen::VectorXd& x) {
  const int nz = model_.num_coordinates();
  frame_prior_target_ = Eigen::Map<const formats::RowMatrix>(x.data(), num_frames(), nz);
}

bool MarkerFitProblem::WrapFramePose(int frame, double* y) const {
  if (frame_prior_target_.rows() != num_frames()) return false;
  const double* target = frame_prior_target_.row(frame).data();
  bool moved = false;
  for (int c = 0; c < model_.num_coordinates(); ++c) {
    if (!periodic_[c]) continue;
    const double wrapped = target[c] + std::remainder(y[c] - target[c], 2.0 * M_PI);
    if (std::abs(wrapped - y[c]) < M_PI) continue;  // already the nearest turn (rounding aside)
    y[c] = wrapped;
    moved = true;
  }
  return moved;
}

bool MarkerFitProblem::FramePrior(int frame, const double** weight, const double** target) const {
  if (frame_prior_target_.rows() != num_frames()) return false;
  *weight = frame_prior_weights_.rows() == num_frames() ? frame_prior_weights_.row(frame).data()
                                                         : frame_prior_weight_.data();
  *target = frame_prior_target_.row(frame).data();
  return true;
}

void MarkerFitProblem::BuildGaugeRows(double gauge_sigma_m, double hold_sigma_m, bool relaxable) {
  const int np = shared_dim();
  std::vector<Eigen::VectorXd> rows;
  auto free3 = [&](int base) {
    return free_index_[base] >= 0 && free_index_[base + 1] >= 0 && free_index_[base + 2] >= 0;
  };
  for (int s = 0; s < model_.num_segments(); ++s) {
    // The segment's local geometry: observed markers on it and centres of joints hanging from it.
    // The gauge exists only if all of it is free. The rows are written on the markers alone:
    // a child joint centre may itself have an unobservable component (a hinge centre along its
    // axis), and a row through it would tie that weak direction to the segment's orientation and
    // so to every axis expressed in the segment. Centres are used only without markers.
    std::vector<std::pair<int, Eigen::Vector3d>> markers, centres;  // (first parameter, position)
    bool all_free = true;
    for (int m = 0; m < model_.num_markers(); ++m) {
      if (model_.markers()[m].segment != s || !observed_[m]) continue;
      const int base = model_.marker_index(m);
      // A fixed marker at the segment's origin (a joint centre: FitOptions::fixed_markers) moves
      // with none of its gauges: rotations and growth are about the origin.
      if (!free3(base) && p0_.segment<3>(base).isZero()) continue;
      all_free = all_free && free3(base);
      markers.emplace_back(base, p0_.segment<3>(base));
    }
    for (int j = 0; j < model_.num_joints(); ++j) {
      if (model_.joints()[j].parent != s) continue;
      const int base = model_.centre_index(j);
      // A centre held because its joint does not move in the trials (FitModel's schedule) does
      // not break the gauge: the data cannot see it move with the frame either, and without the
      // rows the frame would float against its markers along with it.
      if (held_centre_[j]) continue;
      all_free = all_free && free3(base);
      centres.emplace_back(base, p0_.segment<3>(base));
    }
    const auto& local = markers.empty() ? centres : markers;
    if (local.empty() || !all_free) continue;
    const int j = model_.segments()[s].joint;
    const Joint& joint = model_.joints()[j];
    const std::string& name = model_.segments()[s].name;
    auto add_row = [&](auto&& entry, const std::string& what, double sigma_m) {
      Eigen::VectorXd row = Eigen::VectorXd::Zero(np);
      for (const auto& [base, v] : local) {
        const Eigen::Vector3d e = entry(v);
        for (int k = 0; k < 3; ++k) row[free_index_[base + k]] = e[k];
      }
      const double norm = row.norm();
      if (norm < 1e-9) return;
      rows.push_back(row / (norm * sigma_m));
      gauge_names_.push_back(name + "." + what);
    };
    std::vector<Eigen::Vector3d> rotations;
    switch (joint.type) {
      case JointType::kFree:
        for (int k = 0; k < 3; ++k) {
          const Eigen::Vector3d d = Eigen::Vector3d::Unit(k);
          add_row([&](const Eigen::Vector3d&) { return d; }, std::string("translation") + "xyz"[k], gauge_sigma_m);
        }
        [[fallthrough]];
      case JointType::kSpherical:
        for (int k = 0; k < 3; ++k) rotations.push_back(Eigen::Vector3d::Unit(k));
        break;
      case JointType::kHinge:
        if (!joint.elements.empty()) rotations.push_back(joint.elements[0].axis);
        break;
      case JointType::kUniversal:
        if (joint.elements.size() == 2) {
          rotations.push_back(joint.elements[1].axis);
          const int a2 = model_.axis_index(j, 1);
          if (a2 >= 0 && free_index_[a2] >= 0 && free_index_[a2 + 1] >= 0)
            rotations.push_back(joint.elements[0].axis);
        }
        break;
      case JointType::kCustom:
        break;
    }
    for (size_t r = 0; r < rotations.size(); ++r) {
      const Eigen::Vector3d u = rotations[r].normalized();
      // A rotation of the frame is a convention only if every joint hanging from the segment can
      // follow it. Otherwise it turns that joint's axes against the segment's markers, which the
      // data see (welk007's walker knee, whose axes are no parameters, below the femur): the row
      // then holds an orientation the data determine at the starting model's -- a hold, not a
      // gauge. The solve keeps it: released, welk007's right knee slid with the thigh's skin
      // motion from 13 to 26 mm from its epicondyles (BENCHMARKS.md). The report's uncertainty
      // counts it as what it is (relax_holds).
      bool gauge = true;
      for (int c = 0; c < model_.num_joints(); ++c)
        if (model_.joints()[c].parent == s && !ChildFollowsRotation(model_, c, u)) gauge = false;
      if (!gauge && relaxable) has_holds_ = true;
      add_row([&](const Eigen::Vector3d& v) { return Eigen::Vector3d(u.cross(v)); },
              "rotation" + std::to_string(r), gauge ? gauge_sigma_m : hold_sigma_m);
    }
    if (free_index_[model_.scale_index(s)] >= 0)
      add_row([](const Eigen::Vector3d& v) { return v; }, "scale", gauge_sigma_m);
  }
  // A hinge's centre along its axis: moving it there and the child's whole geometry back leaves
  // every marker where it was, for a pure hinge exactly, for a knee whose coupled translations
  // ride on its flexion nearly, so no data can place it; left to the weak prior it drifts with
  // the skin motion's faint preferences (55 mm along the knee axis on gait2354). It is held at
  // the model's. One rotational coordinate makes a hinge here, whatever the joint's type. For a
  // joint with one moving rotation it is a gauge (model/compare.h, AlongAxisGaugeElement); a
  // knee whose one coordinate also turns it about other axes (OpenSim's walker knee: ad/abduction
  // and axial rotation on splines of the flexion) moves the tibia's markers when its centre moves
  // along the flexion axis, so the row is a hold there (see the rotations above): kept in the
  // solve (freed, welk007's right knee went 34 mm from its epicondyles), relaxed for the report.
  for (int j = 0; j < model_.num_joints(); ++j) {
    const int base = model_.centre_index(j);
    if (base < 0 || !free3(base)) continue;
    const Joint& joint = model_.joints()[j];
    int coordinate = -1;
    bool one = true;
    Eigen::Vector3d axis = Eigen::Vector3d::Zero();
    for (const JointElement& el : joint.elements) {
      if (el.kind != ElementKind::kRotation || el.coordinate < 0) continue;
      if (coordinate >= 0 && el.coordinate != coordinate) one = false;
      if (coordinate < 0) axis = joint.orientation * el.axis;
      coordinate = el.coordinate;
    }
    if (coordinate < 0 || !one || !hold_hinge_centres_) continue;
    const bool gauge = AlongAxisGaugeElement(joint) >= 0;
    if (!gauge && relaxable) has_holds_ = true;
    Eigen::VectorXd row = Eigen::VectorXd::Zero(np);
    for (int k = 0; k < 3; ++k) row[free_index_[base + k]] = axis.normalized()[k];
    rows.push_back(row / (gauge ? gauge_sigma_m : hold_sigma_m));
    gauge_names_.push_back(joint.name + ".centre_along_axis");
  }
  gauge_rows_.resize(static_cast<Eigen::Index>(rows.size()), np);
  for (size_t r = 0; r < rows.size(); ++r) gauge_rows_.row(r) = rows[r].transpose();
}

Eigen::VectorXd MarkerFitProblem::InitialShared() const {
  Eigen::VectorXd s(free_parameters_.size());
  for (size_t k = 0; k < free_parameters_.size(); ++k) s[k] = p0_[free_parameters_[k]];
  return s;
}

Eigen::VectorXd MarkerFitProblem::FullParameters(const Eigen::VectorXd& shared) const {
  Eigen::VectorXd p = p0_;
  for (size_t k = 0; k < free_parameters_.size(); ++k) p[free_parameters_[k]] = shared[k];
  return p;
}

bool MarkerFitProblem::SetShared(const Eigen::VectorXd& shared) {
  if (!shared.allFinite()) return false;
  const Eigen::VectorXd p = FullParameters(shared);
  for (int s = 0; s < model_.num_segments(); ++s)
    if (!(p[model_.scale_index(s)] > 0)) return false;  // a non-positive scale is no body
  geometry_.Set(model_, p);
  return true;
}

std::unique_ptr<FrameEvaluator> MarkerFitProblem::NewEvaluator() const {
  return std::make_unique<MarkerFrameEvaluator>(*this);
}

void MarkerFitProblem::BlockStructure(std::vector<std::vector<int>>* y_columns,
                                      std::vector<std::vector<int>>* p_columns) const {
  y_columns->clear();
  p_columns->clear();
  for (int m = 0; m < model_.num_markers(); ++m) {
    if (!observed_[m]) continue;  // block_kind(m) counts the same way
    y_columns->push_back(model_.marker_coordinates(m));
    p_columns->push_back(marker_free_columns_[m]);
  }
  for (const CoordinateLimit& limit : limits_) {
    y_columns->push_back({limit.coordinate});
    p_columns->push_back({});
  }
}

bool MarkerFitProblem::MarkerErrors(const Eigen::VectorXd& x, int num_threads,
                                    Eigen::VectorXd* sum_squared, Eigen::VectorXi* count) {
  Eigen::MatrixXd squared;
  if (!SampleErrors(x, num_threads, &squared)) return false;
  const int nm = model_.num_markers();
  sum_squared->setZero(nm);
  count->setZero(nm);
  for (int m = 0; m < nm; ++m)
    for (int f = 0; f < num_frames(); ++f)
      if (std::isfinite(squared(f, m))) {
        (*sum_squared)[m] += squared(f, m);
        (*count)[m] += 1;
      }
  return true;
}

bool MarkerFitProblem::SampleErrors(const Eigen::VectorXd& x, int num_threads, Eigen::MatrixXd* squared) {
  const int nm = model_.num_markers(), nz = model_.num_coordinates(), nf = num_frames();
  if (!SetShared(x.tail(shared_dim()))) return false;
  squared->setConstant(nf, nm, std::numeric_limits<double>::quiet_NaN());
  ParallelChunks(nf, ResolveThreads(num_threads), [&](int, int b, int e) {
    ModelData data(model_);
    Eigen::VectorXd z(nz);
    for (int f = b; f < e; ++f) {
      z = x.segment(static_cast<Eigen::Index>(f) * nz, nz);
      ForwardKinematics(model_, geometry_, z, &data);
      for (int m = 0; m < nm; ++m) {
        const double* meas = measurements_.row(f).data() + 3 * m;
        if (!std::isfinite(meas[0])) continue;
        (*squared)(f, m) = (MarkerPosition(model_, geometry_, data, m) -
                            Eigen::Map<const Eigen::Vector3d>(meas)).squaredNorm();
      }
    }
  });
  return true;
}

}  // namespace mocap::solver
