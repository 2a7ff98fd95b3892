#include "solver/schur_solver.h"

#include <Eigen/Cholesky>
#include <algorithm>
#include <cmath>

#include "solver/parallel.h"

namespace mocap::solver {

struct ArrowSchurProblem::ThreadState {
  std::unique_ptr<FrameEvaluator> evaluator;
  Eigen::MatrixXd u, w, y, s, gather, outer;
  Eigen::VectorXd gy, v, rhs, gp, diag_p, wdp, dy;
  Eigen::LLT<Eigen::MatrixXd> llt;
  Eigen::MatrixXd block_jp, block_u, block_w, block_v;  // one residual block's products
  std::vector<int> ycol, pcol, plocal;
  double cost = 0;
  bool ok = true;
};

ArrowSchurProblem::ArrowSchurProblem(ArrowProblem* problem, int num_threads,
                                     double cache_budget_bytes)
    : problem_(problem),
      num_threads_(ResolveThreads(num_threads)),
      nf_(problem->num_frames()),
      ny_(problem->frame_dim()),
      np_(problem->shared_dim()) {
  Analyse();
  const double cache_bytes = 8.0 * nf_ * (static_cast<double>(ny_) * ny_ + static_cast<double>(ny_) * np_);
  cached_ = cache_bytes <= cache_budget_bytes;
  if (cached_) {
    u_cache_.resize(static_cast<size_t>(nf_) * ny_ * ny_);
    w_cache_.resize(static_cast<size_t>(nf_) * ny_ * np_);
  }
  for (int t = 0; t < num_threads_; ++t) {
    auto ts = std::make_unique<ThreadState>();
    ts->evaluator = problem_->NewEvaluator();
    ts->u.resize(ny_, ny_);
    ts->w.resize(ny_, np_);
    ts->y.resize(ny_, np_);
    ts->s.resize(np_, np_);
    ts->gather.resize(np_, ny_);
    ts->outer.resize(np_, np_);
    ts->gy.resize(ny_);
    ts->v.resize(ny_);
    ts->rhs.resize(np_);
    ts->gp.resize(np_);
    ts->diag_p.resize(np_);
    ts->wdp.resize(ny_);
    ts->dy.resize(ny_);
    ts->llt = Eigen::LLT<Eigen::MatrixXd>(ny_);
    ts->block_jp.resize(kMaxBlockRows, max_block_p_);
    ts->block_u.resize(max_block_y_, max_block_y_);
    ts->block_w.resize(max_block_y_, max_block_p_);
    ts->block_v.resize(max_block_p_, max_block_p_);
    ts->ycol.resize(max_block_y_);
    ts->pcol.resize(max_block_p_);
    ts->plocal.resize(max_block_p_);
    threads_.push_back(std::move(ts));
  }
}

ArrowSchurProblem::~ArrowSchurProblem() = default;

int ArrowSchurProblem::num_parameters() const { return nf_ * ny_ + np_; }
int ArrowSchurProblem::num_residuals() const { return problem_->num_residuals(); }

void ArrowSchurProblem::Analyse() {
  std::vector<std::vector<int>> ycols, pcols;
  problem_->BlockStructure(&ycols, &pcols);
  max_block_y_ = max_block_p_ = 1;
  for (size_t b = 0; b < ycols.size(); ++b) {
    max_block_y_ = std::max<int>(max_block_y_, ycols[b].size());
    max_block_p_ = std::max<int>(max_block_p_, pcols[b].size());
  }
  // Graph of U and pattern of W.
  std::vector<std::vector<char>> adj(ny_, std::vector<char>(ny_, 0));
  std::vector<std::vector<char>> wpat(ny_, std::vector<char>(np_, 0));
  for (size_t b = 0; b < ycols.size(); ++b)
    for (int a : ycols[b]) {
      for (int c : ycols[b]) adj[a][c] = 1;
      for (int p : pcols[b])
        if (p >= 0) wpat[a][p] = 1;
    }
  // Greedy minimum degree with fill; ties go to the later coordinate, which in a parents-first
  // model is the deeper one, so chains are eliminated from their leaves.
  std::vector<char> done(ny_, 0);
  std::vector<std::vector<char>> lpat(ny_, std::vector<char>(ny_, 0));  // by y index
  order_.clear();
  for (int step = 0; step < ny_; ++step) {
    int best = -1, best_degree = 1 << 30;
    for (int i = 0; i < ny_; ++i) {
      if (done[i]) continue;
      int degree = 0;
      for (int j = 0; j < ny_; ++j) degree += (j != i && !done[j] && adj[i][j]);
      if (degree <= best_degree) {
        best_degree = degree;
        best = i;
      }
    }
    done[best] = 1;
    order_.push_back(best);
    std::vector<int> nbrs;
    for (int j = 0; j < ny_; ++j)
      if (!done[j] && adj[best][j]) nbrs.push_back(j);
    for (int a : nbrs) {
      lpat[a][best] = 1;
      for (int c : nbrs) adj[a][c] = 1;
    }
  }
  position_.assign(ny_, 0);
  for (int k = 0; k < ny_; ++k) position_[order_[k]] = k;
  // Y row patterns in elimination order.
  std::vector<std::vector<char>> ypat(ny_);
  for (int k = 0; k < ny_; ++k) {
    const int i = order_[k];
    ypat[k] = wpat[i];
    for (int kj = 0; kj < k; ++kj)
      if (lpat[i][order_[kj]])
        for (int p = 0; p < np_; ++p) ypat[k][p] |= ypat[kj][p];
  }
  groups_.clear();
  for (int k = 0; k < ny_;) {
    int e = k + 1;
    while (e < ny_ && ypat[e] == ypat[k]) ++e;
    RowGroup g;
    g.first_row = k;
    g.num_rows = e - k;
    for (int p = 0; p < np_; ++p)
      if (ypat[k][p]) g.columns.push_back(p);
    g.contiguous = g.columns.empty() ||
                   g.columns.back() - g.columns.front() + 1 == static_cast<int>(g.columns.size());
    if (!g.columns.empty()) groups_.push_back(std::move(g));
    k = e;
  }
}

double ArrowSchurProblem::SharedRowsSquaredNorm(const Eigen::VectorXd& p) const {
  const Eigen::VectorXd delta = p - problem_->prior_target();
  double sum = problem_->prior_weight().cwiseProduct(delta).squaredNorm();
  const Eigen::MatrixXd& g = problem_->shared_rows();
  if (g.rows() > 0) sum += (g * delta).squaredNorm();
  return sum;
}

bool ArrowSchurProblem::Cost(const Eigen::VectorXd& x, double* cost) {
  if (!problem_->SetShared(x.tail(np_))) return false;
  ParallelChunks(nf_, num_threads_, [&](int t, int b, int e) {
    ThreadState& ts = *threads_[t];
    ts.cost = 0;
    ts.ok = true;
    for (int f = b; f < e && ts.ok; ++f) {
      if (!ts.evaluator->Evaluate(f, x.data() + static_cast<size_t>(f) * ny_, false)) {
        ts.ok = false;
        break;
      }
      for (int k = 0; k < ts.evaluator->num_blocks(); ++k) {
        const ResidualBlock& blk = ts.evaluator->block(k);
        for (int r = 0; r < blk.rows; ++r) ts.cost += blk.residual[r] * blk.residual[r];
      }
    }
  });
  double sum = 0;
  for (int t = 0; t < std::max(1, std::min(num_threads_, nf_)); ++t) {
    if (!threads_[t]->ok) return false;
    sum += threads_[t]->cost;
  }
  *cost = 0.5 * (sum + SharedRowsSquaredNorm(x.tail(np_)));
  return std::isfinite(*cost);
}

bool ArrowSchurProblem::Linearize(const Eigen::VectorXd& x, double* cost, Eigen::VectorXd* gradient,
                                  Eigen::VectorXd* diagonal) {
  x_ = x;
  const int n = num_parameters();
  gradient->setZero(n);
  diagonal->setZero(n);
  if (!problem_->SetShared(x.tail(np_))) return false;
  ParallelChunks(nf_, num_threads_, [&](int t, int b, int e) {
    ThreadState& ts = *threads_[t];
    ts.cost = 0;
    ts.ok = true;
    ts.gp.setZero();
    ts.diag_p.setZero();
    if (cached_) ts.s.setZero();
    for (int f = b; f < e; ++f) {
      if (!ts.evaluator->Evaluate(f, x.data() + static_cast<size_t>(f) * ny_, true)) {
        ts.ok = false;
        return;
      }
      if (cached_) {
        AccumulateFrame(ts);
        CachedU(f) = ts.u;
        CachedW(f) = ts.w;
      }
      double* gy = gradient->data() + static_cast<size_t>(f) * ny_;
      double* dg = diagonal->data() + static_cast<size_t>(f) * ny_;
      for (int k = 0; k < ts.evaluator->num_blocks(); ++k) {
        const ResidualBlock& blk = ts.evaluator->block(k);
        for (int r = 0; r < blk.rows; ++r) ts.cost += blk.residual[r] * blk.residual[r];
        for (int a = 0; a < blk.num_y; ++a)
          for (int r = 0; r < blk.rows; ++r) {
            const double j = blk.jy[a * kMaxBlockRows + r];
            gy[blk.y_index[a]] += j * blk.residual[r];
            dg[blk.y_index[a]] += j * j;
          }
        for (int c = 0; c < blk.num_p; ++c) {
          const int p = blk.p_index[c];
          if (p < 0) continue;
          for (int r = 0; r < blk.rows; ++r) {
            const double j = blk.jp[c * kMaxBlockRows + r];
            ts.gp[p] += j * blk.residual[r];
            ts.diag_p[p] += j * j;
          }
        }
      }
    }
  });
  double sum = 0;
  if (cached_) v_total_.setZero(np_, np_);
  for (int t = 0; t < std::max(1, std::min(num_threads_, nf_)); ++t) {
    const ThreadState& ts = *threads_[t];
    if (!ts.ok) return false;
    sum += ts.cost;
    gradient->tail(np_) += ts.gp;
    diagonal->tail(np_) += ts.diag_p;
    if (cached_) v_total_ += ts.s;
  }
  const Eigen::VectorXd& w = problem_->prior_weight();
  const Eigen::VectorXd delta = x.tail(np_) - problem_->prior_target();
  gradient->tail(np_) += w.cwiseProduct(w.cwiseProduct(delta));
  diagonal->tail(np_) += w.cwiseProduct(w);
  const Eigen::MatrixXd& g = problem_->shared_rows();
  if (g.rows() > 0) {
    gradient->tail(np_) += g.transpose() * (g * delta);
    diagonal->tail(np_) += g.colwise().squaredNorm().transpose();
  }
  *cost = 0.5 * (sum + SharedRowsSquaredNorm(x.tail(np_)));
  gradient_ = *gradient;
  return std::isfinite(*cost) && gradient->allFinite();
}

// U (lower, elimination order), W and V (lower, into ts.s) of one evaluated frame. Each block's
// three small products are formed densely (vectorised), then scattered by index.
void ArrowSchurProblem::AccumulateFrame(ThreadState& ts) const {
  ts.u.setZero();
  ts.w.setZero();
  int* ycol = ts.ycol.data();
  int* pcol = ts.pcol.data();
  int* plocal = ts.plocal.data();
  for (int k = 0; k < ts.evaluator->num_blocks(); ++k) {
    const ResidualBlock& blk = ts.evaluator->block(k);
    using Strided = Eigen::Map<const Eigen::MatrixXd, 0, Eigen::OuterStride<>>;
    const Strided jy(blk.jy, blk.rows, blk.num_y, Eigen::OuterStride<>(kMaxBlockRows));
    const Strided jp_all(blk.jp, blk.rows, blk.num_p, Eigen::OuterStride<>(kMaxBlockRows));
    int np = 0;
    for (int c = 0; c < blk.num_p; ++c)
      if (blk.p_index[c] >= 0) {
        plocal[np] = c;
        pcol[np++] = blk.p_index[c];
      }
    for (int a = 0; a < blk.num_y; ++a) ycol[a] = position_[blk.y_index[a]];
    auto& jp = ts.block_jp;
    for (int c = 0; c < np; ++c) jp.col(c).head(blk.rows) = jp_all.col(plocal[c]);
    auto jpc = jp.topLeftCorner(blk.rows, np);
    auto uy = ts.block_u.topLeftCorner(blk.num_y, blk.num_y);
    auto wy = ts.block_w.topLeftCorner(blk.num_y, np);
    auto vp = ts.block_v.topLeftCorner(np, np);
    uy.noalias() = jy.transpose() * jy;
    wy.noalias() = jy.transpose() * jpc;
    vp.noalias() = jpc.transpose() * jpc;
    for (int a = 0; a < blk.num_y; ++a) {
      for (int c = 0; c < blk.num_y; ++c)
        if (ycol[c] <= ycol[a]) ts.u(ycol[a], ycol[c]) += uy(a, c);
      for (int c = 0; c < np; ++c) ts.w(ycol[a], pcol[c]) += wy(a, c);
    }
    for (int d = 0; d < np; ++d)
      for (int c = 0; c < np; ++c)
        if (pcol[d] <= pcol[c]) ts.s(pcol[c], pcol[d]) += vp(c, d);
  }
}

bool ArrowSchurProblem::FormReducedSystem(const Eigen::VectorXd& damping, Eigen::MatrixXd* s_out,
                                          Eigen::VectorXd* rhs_out) {
  if (!problem_->SetShared(x_.tail(np_))) return false;
  const int used_threads = std::max(1, std::min(num_threads_, nf_));
  ParallelChunks(nf_, num_threads_, [&](int t, int b, int e) {
    ThreadState& ts = *threads_[t];
    ts.ok = true;
    ts.s.setZero();
    ts.rhs.setZero();
    for (int f = b; f < e; ++f) {
      if (cached_) {
        ts.u = CachedU(f);
        ts.w = CachedW(f);
      } else {
        if (!ts.evaluator->Evaluate(f, x_.data() + static_cast<size_t>(f) * ny_, true)) {
          ts.ok = false;
          return;
        }
        AccumulateFrame(ts);  // V of the frame goes into ts.s
      }
      const double* g = gradient_.data() + static_cast<size_t>(f) * ny_;
      const double* dmp = damping.data() + static_cast<size_t>(f) * ny_;
      for (int i = 0; i < ny_; ++i) {
        ts.u(position_[i], position_[i]) += dmp[i];
        ts.gy[position_[i]] = g[i];
      }
      ts.llt.compute(ts.u);
      if (ts.llt.info() != Eigen::Success) {
        ts.ok = false;
        return;
      }
      if (np_ == 0) continue;
      ts.y = ts.w;
      ts.llt.matrixL().solveInPlace(ts.y);
      ts.v = ts.gy;
      ts.llt.matrixL().solveInPlace(ts.v);
      ts.rhs.noalias() += ts.y.transpose() * ts.v;
      for (const RowGroup& grp : groups_) {
        const int n = static_cast<int>(grp.columns.size());
        if (grp.contiguous) {
          const int a = grp.columns.front();
          ts.s.block(a, a, n, n).selfadjointView<Eigen::Lower>().rankUpdate(
              ts.y.block(grp.first_row, a, grp.num_rows, n).transpose(), -1.0);
        } else {
          for (int c = 0; c < n; ++c)
            for (int r = 0; r < grp.num_rows; ++r)
              ts.gather(c, r) = ts.y(grp.first_row + r, grp.columns[c]);
          auto g2 = ts.gather.topLeftCorner(n, grp.num_rows);
          auto o = ts.outer.topLeftCorner(n, n);
          o.triangularView<Eigen::Lower>().setZero();
          o.selfadjointView<Eigen::Lower>().rankUpdate(g2, 1.0);
          for (int c = 0; c < n; ++c)
            for (int d = 0; d <= c; ++d) ts.s(grp.columns[c], grp.columns[d]) -= o(c, d);
        }
      }
    }
  });
  s_out->setZero(np_, np_);
  rhs_out->setZero(np_);
  for (int t = 0; t < used_threads; ++t) {
    if (!threads_[t]->ok) return false;
    *s_out += threads_[t]->s;
    *rhs_out += threads_[t]->rhs;
  }
  if (cached_) *s_out += v_total_;
  *rhs_out -= gradient_.tail(np_);
  const Eigen::VectorXd& w = problem_->prior_weight();
  s_out->diagonal() += w.cwiseProduct(w) + damping.tail(np_);
  const Eigen::MatrixXd& g = problem_->shared_rows();
  if (g.rows() > 0) s_out->selfadjointView<Eigen::Lower>().rankUpdate(g.transpose(), 1.0);
  return true;
}

bool ArrowSchurProblem::SolveDamped(const Eigen::VectorXd& damping, Eigen::VectorXd* dx) {
  Eigen::MatrixXd s;
  Eigen::VectorXd rhs;
  if (!FormReducedSystem(damping, &s, &rhs)) return false;
  dx->resize(num_parameters());
  Eigen::VectorXd dp = Eigen::VectorXd::Zero(np_);
  if (np_ > 0) {
    Eigen::LLT<Eigen::MatrixXd> llt(s);  // reads the lower triangle only
    if (llt.info() != Eigen::Success) return false;
    dp = llt.solve(rhs);
    dx->tail(np_) = dp;
  }
  // Back-substitution, frame by frame: dy_f = -U_f^{-1} (g_yf + W_f dp).
  if (!cached_ && !problem_->SetShared(x_.tail(np_))) return false;
  ParallelChunks(nf_, num_threads_, [&](int t, int b, int e) {
    ThreadState& ts = *threads_[t];
    ts.ok = true;
    for (int f = b; f < e; ++f) {
      if (cached_) {
        ts.u = CachedU(f);
        ts.wdp.noalias() = CachedW(f) * dp;
      } else if (!BackSubstitutionTerms(ts, f, dp)) {
        ts.ok = false;
        return;
      }
      const double* g = gradient_.data() + static_cast<size_t>(f) * ny_;
      const double* dmp = damping.data() + static_cast<size_t>(f) * ny_;
      for (int i = 0; i < ny_; ++i) {
        ts.u(position_[i], position_[i]) += dmp[i];
        ts.wdp[position_[i]] += g[i];
      }
      ts.llt.compute(ts.u);
      if (ts.llt.info() != Eigen::Success) {
        ts.ok = false;
        return;
      }
      ts.dy = ts.llt.solve(ts.wdp);
      double* out = dx->data() + static_cast<size_t>(f) * ny_;
      for (int i = 0; i < ny_; ++i) out[i] = -ts.dy[position_[i]];
    }
  });
  for (int t = 0; t < std::max(1, std::min(num_threads_, nf_)); ++t)
    if (!threads_[t]->ok) return false;
  return dx->allFinite();
}

// Without the cache: U_f and W_f dp of frame f from a fresh evaluation of its Jacobian.
bool ArrowSchurProblem::BackSubstitutionTerms(ThreadState& ts, int f, const Eigen::VectorXd& dp) {
  if (!ts.evaluator->Evaluate(f, x_.data() + static_cast<size_t>(f) * ny_, true)) return false;
  ts.u.setZero();
  ts.wdp.setZero();
  for (int k = 0; k < ts.evaluator->num_blocks(); ++k) {
    const ResidualBlock& blk = ts.evaluator->block(k);
    double jdp[kMaxBlockRows] = {0, 0, 0};
    for (int c = 0; c < blk.num_p; ++c) {
      const int p = blk.p_index[c];
      if (p < 0) continue;
      for (int r = 0; r < blk.rows; ++r) jdp[r] += blk.jp[c * kMaxBlockRows + r] * dp[p];
    }
    for (int a = 0; a < blk.num_y; ++a) {
      const int pa = position_[blk.y_index[a]];
      const double* ja = blk.jy + a * kMaxBlockRows;
      double sum = 0;
      for (int r = 0; r < blk.rows; ++r) sum += ja[r] * jdp[r];
      ts.wdp[pa] += sum;
      for (int c = 0; c < blk.num_y; ++c) {
        const int pc = position_[blk.y_index[c]];
        if (pc > pa) continue;
        const double* jc = blk.jy + c * kMaxBlockRows;
        double s2 = 0;
        for (int r = 0; r < blk.rows; ++r) s2 += ja[r] * jc[r];
        ts.u(pa, pc) += s2;
      }
    }
  }
  return true;
}

bool ArrowSchurProblem::SharedCovariance(Eigen::MatrixXd* covariance, double frame_ridge) {
  // Damping: a relative ridge on the frame blocks only (their diagonal from the gradient pass).
  Eigen::VectorXd gradient, diagonal;
  double cost;
  if (!Linearize(x_, &cost, &gradient, &diagonal)) return false;
  Eigen::VectorXd damping = frame_ridge * diagonal.cwiseMax(1e-12);
  damping.tail(np_).setZero();
  Eigen::MatrixXd s;
  Eigen::VectorXd rhs;
  if (!FormReducedSystem(damping, &s, &rhs)) return false;
  Eigen::MatrixXd full = s.selfadjointView<Eigen::Lower>();
  Eigen::LLT<Eigen::MatrixXd> llt(full);
  if (llt.info() != Eigen::Success) return false;
  *covariance = llt.solve(Eigen::MatrixXd::Identity(np_, np_));
  return covariance->allFinite();
}

}  // namespace mocap::solver
