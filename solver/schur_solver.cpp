#include "solver/schur_solver.h"

#include <Eigen/Cholesky>
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <new>
#include <sys/mman.h>
#include <unistd.h>
#if defined(__AVX512F__)
#include <immintrin.h>
#endif

#include "solver/parallel.h"

namespace mocap::solver {
namespace {
// Frames whose rows are stacked into one rank update: enough rows for the matrix product to run
// near peak speed, few enough that each group's stack stays in cache.
constexpr int kStackFrames = 16;

// d[e] -= c0 b0[e] + c1 b1[e] + c2 b2[e], e < n: the reduction's short runs (2-10 entries, on
// average 8 for the full body). With AVX-512 a run is one or two 8-wide operations, its tail
// masked; the compiler's own vectorisation of the plain loop left most of such a run to its
// scalar epilogue. The products are summed as the compiler had contracted that loop (c1 b1
// first, then fused c0 b0 and c2 b2): the fit's iteration count with gaps answers last-bit
// changes like chance (BENCHMARKS.md, "With gaps"), and this order keeps the iterates.
inline void SubtractCombination(double* d, const double* b0, const double* b1, const double* b2, double c0,
                                double c1, double c2, int n) {
  int e = 0;
#if defined(__AVX512F__)
  const __m512d v0 = _mm512_set1_pd(c0), v1 = _mm512_set1_pd(c1), v2 = _mm512_set1_pd(c2);
  for (; e + 8 <= n; e += 8) {
    __m512d sum = _mm512_mul_pd(v1, _mm512_loadu_pd(b1 + e));
    sum = _mm512_fmadd_pd(v0, _mm512_loadu_pd(b0 + e), sum);
    sum = _mm512_fmadd_pd(v2, _mm512_loadu_pd(b2 + e), sum);
    _mm512_storeu_pd(d + e, _mm512_sub_pd(_mm512_loadu_pd(d + e), sum));
  }
  if (e < n) {
    const __mmask8 m = static_cast<__mmask8>((1u << (n - e)) - 1);
    __m512d sum = _mm512_mul_pd(v1, _mm512_maskz_loadu_pd(m, b1 + e));
    sum = _mm512_fmadd_pd(v0, _mm512_maskz_loadu_pd(m, b0 + e), sum);
    sum = _mm512_fmadd_pd(v2, _mm512_maskz_loadu_pd(m, b2 + e), sum);
    _mm512_mask_storeu_pd(d + e, m, _mm512_sub_pd(_mm512_maskz_loadu_pd(m, d + e), sum));
  }
#else
  for (; e < n; ++e) d[e] -= (c1 * b1[e] + c0 * b0[e]) + c2 * b2[e];
#endif
}

}  // namespace

// Cache-line aligned: each thread's accumulators are written for every residual block, and two
// states sharing a line would make the threads invalidate each other's cache.
struct alignas(64) ArrowSchurProblem::ThreadState {
  std::unique_ptr<FrameEvaluator> evaluator;
  Eigen::MatrixXd u, s;  // u: U_f, then its factor L_f, in the lower triangle (pattern only)
  Eigen::MatrixXd s_v;   // this thread's share of V (lower)
  bool reduced = false;  // Linearize also reduced this thread's frames
  std::vector<double> w;       // compact W_f (when not cached)
  std::vector<double*> y_base; // where each row group's rows of Y_f are (in its stack), this frame
  const double* w_frame = nullptr;  // the current frame's compact W (cache or w)
  Eigen::VectorXd gy, gyi, v, rhs, gp, wdp;
  std::vector<double> panel_y, panel_p;  // one block's Jacobians, 3 rows, zero-padded
  std::vector<double> w_row;              // one row of the block's J_y^T J_p
  // Stacked columns awaiting a rank update, and what they have been applied to: per block kind
  // (J_p^T, for V) and per row group (Y_g^T, for S).
  std::vector<Eigen::MatrixXd> v_stack, v_acc, g_stack, g_acc;
  std::vector<Eigen::VectorXd> g_rhs;  // per row group: Y_g^T v_g over its own columns
  std::vector<int> v_count, g_count;
  std::vector<int> kind_slot;  // SolveAcceleration: where a block kind's shifted residuals are, -1 none
  Eigen::VectorXd by;          // SolveAcceleration: the frame's J_y^T r_vv, by y index
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
  const double cache_bytes = 8.0 * nf_ * (2.0 * u_pattern_.size() + w_size_);
  cached_ = cache_bytes <= cache_budget_bytes;
  if (cached_) {
    u_cache_ = std::make_unique<CacheArray>(static_cast<size_t>(nf_) * u_pattern_.size());
    l_cache_ = std::make_unique<CacheArray>(static_cast<size_t>(nf_) * u_pattern_.size());
    w_cache_ = std::make_unique<CacheArray>(static_cast<size_t>(nf_) * w_size_);
  }
  if (cached_) PopulateCaches();
  for (int t = 0; t < num_threads_; ++t) {
    auto ts = std::make_unique<ThreadState>();
    ts->evaluator = problem_->NewEvaluator();
    ts->u.setZero(ny_, ny_);
    ts->s.resize(np_, np_);
    ts->s_v.resize(np_, np_);
    ts->w.resize(w_size_);
    ts->y_base.assign(groups_.size(), nullptr);
    ts->gy.resize(ny_);
    ts->gyi.resize(ny_);
    ts->panel_y.resize(3 * max_block_y_);
    ts->panel_p.resize(3 * max_block_p_);
    ts->w_row.resize(max_block_p_);
    ts->v.resize(ny_);
    ts->rhs.resize(np_);
    ts->gp.resize(np_);
    ts->wdp.resize(ny_);
    for (const BlockKind& k : kinds_) {
      const int n = static_cast<int>(k.free_p.size());
      ts->v_stack.emplace_back(n, kMaxBlockRows * kStackFrames);
      ts->v_acc.emplace_back(n, n);
    }
    ts->v_count.assign(kinds_.size(), 0);
    for (const RowGroup& g : groups_) {
      const int n = static_cast<int>(g.columns.size());
      ts->g_stack.emplace_back(n, g.num_rows * kStackFrames);
      ts->g_acc.emplace_back(g.full ? 0 : n, g.full ? 0 : n);
      ts->g_rhs.emplace_back(n);
    }
    ts->g_count.assign(groups_.size(), 0);
    ts->kind_slot.assign(kinds_.size(), -1);
    ts->by.resize(ny_);
    threads_.push_back(std::move(ts));
  }
}

ArrowSchurProblem::~ArrowSchurProblem() = default;

ArrowSchurProblem::CacheArray::CacheArray(size_t doubles) : bytes(std::max<size_t>(1, doubles) * sizeof(double)) {
  void* p = mmap(nullptr, bytes, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
  if (p == MAP_FAILED) throw std::bad_alloc();
  data = static_cast<double*>(p);
}

ArrowSchurProblem::CacheArray::~CacheArray() {
  if (data) munmap(data, bytes);
}

void ArrowSchurProblem::PopulateCaches() {
#if defined(MADV_POPULATE_WRITE)
  const size_t page = static_cast<size_t>(sysconf(_SC_PAGESIZE));
  ParallelChunks(nf_, num_threads_, [&](int, int b, int e) {
    for (const auto& [cache, stride] : {std::pair<CacheArray*, size_t>{u_cache_.get(), u_pattern_.size()},
                                        {l_cache_.get(), u_pattern_.size()}, {w_cache_.get(), static_cast<size_t>(w_size_)}}) {
      const uintptr_t base = reinterpret_cast<uintptr_t>(cache->data);
      const uintptr_t from = (base + b * stride * sizeof(double)) / page * page;
      const uintptr_t to = std::min(base + cache->bytes, (base + e * stride * sizeof(double) + page - 1) / page * page);
      if (to > from) madvise(reinterpret_cast<void*>(from), to - from, MADV_POPULATE_WRITE);
    }
  });
#endif
}

int ArrowSchurProblem::num_parameters() const { return nf_ * ny_ + np_; }
int ArrowSchurProblem::num_residuals() const { return problem_->num_residuals(); }

void ArrowSchurProblem::Analyse() {
  std::vector<std::vector<int>> ycols, pcols;
  problem_->BlockStructure(&ycols, &pcols);
  WidestBlock(ycols, pcols, &max_block_y_, &max_block_p_);
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
  // L's pattern by columns (positions), and its lower-triangle offsets in a column-major ny x ny.
  l_rows_.assign(ny_, {});
  u_pattern_.clear();
  for (int j = 0; j < ny_; ++j) {
    u_pattern_.push_back(j + j * ny_);
    for (int i = j + 1; i < ny_; ++i)
      if (lpat[order_[i]][order_[j]]) {
        l_rows_[j].push_back(i);
        u_pattern_.push_back(i + j * ny_);
      }
  }
  l_cols_.assign(ny_, {});
  for (int j = 0; j < ny_; ++j)
    for (int i : l_rows_[j]) l_cols_[i].push_back(j);
  // Y row patterns in elimination order: a row reaches what its own W row and every row it is
  // eliminated against reach.
  std::vector<std::vector<char>> ypat(ny_);
  for (int k = 0; k < ny_; ++k) {
    const int i = order_[k];
    ypat[k] = wpat[i];
    for (int kj = 0; kj < k; ++kj)
      if (lpat[i][order_[kj]])
        for (int p = 0; p < np_; ++p) ypat[k][p] |= ypat[kj][p];
  }
  groups_.clear();
  std::vector<int> row_group(ny_, -1);
  w_size_ = 0;
  for (int k = 0; k < ny_;) {
    int e = k + 1;
    while (e < ny_ && ypat[e] == ypat[k]) ++e;
    RowGroup g;
    g.first_row = k;
    g.num_rows = e - k;
    for (int p = 0; p < np_; ++p)
      if (ypat[k][p]) g.columns.push_back(p);
    const int n = static_cast<int>(g.columns.size());
    g.full = n == np_;
    g.contiguous = n == 0 || g.columns.back() - g.columns.front() + 1 == n;
    g.offset = w_size_;
    if (n > 0) {
      for (int r = k; r < e; ++r) row_group[r] = static_cast<int>(groups_.size());
      w_size_ += g.num_rows * n;
      groups_.push_back(std::move(g));
    }
    k = e;
  }
  // Which earlier groups each group is eliminated against, and where their columns sit in ours
  // (a descendant reaches a subset of what its ancestor reaches).
  for (size_t gi = 0; gi < groups_.size(); ++gi) {
    RowGroup& g = groups_[gi];
    for (size_t hi = 0; hi < gi; ++hi) {
      const RowGroup& h = groups_[hi];
      bool coupled = false;
      for (int r = 0; r < g.num_rows && !coupled; ++r)
        for (int q = 0; q < h.num_rows && !coupled; ++q)
          coupled = lpat[order_[g.first_row + r]][order_[h.first_row + q]];
      if (!coupled) continue;
      RowGroup::Child child;
      child.group = static_cast<int>(hi);
      // Where each of the child's columns sits among ours, as runs of consecutive columns.
      int last = -2;
      for (int c = 0; c < static_cast<int>(h.columns.size()); ++c) {
        auto it = std::lower_bound(g.columns.begin(), g.columns.end(), h.columns[c]);
        const int at = static_cast<int>(it - g.columns.begin());  // present by construction
        if (at == last + 1) ++child.runs.back().length;
        else child.runs.push_back({c, at, 1});
        last = at;
      }
      g.children.push_back(std::move(child));
    }
  }
  child_rows_.clear();
  child_l_.clear();
  child_runs_.clear();
  for (size_t gi = 0; gi < groups_.size(); ++gi) {
    const RowGroup& g = groups_[gi];
    for (const RowGroup::Child& child : g.children) {
      const RowGroup& h = groups_[child.group];
      for (int r = 0; r < g.num_rows; ++r) {
        ChildRow cr;
        cr.group = static_cast<int>(gi);
        cr.child = child.group;
        cr.row = r;
        cr.first_l = static_cast<int>(child_l_.size());
        for (int q = 0; q < h.num_rows; ++q) {
          const int i = g.first_row + r, j = h.first_row + q;  // positions, j < i
          if (lpat[order_[i]][order_[j]]) child_l_.push_back({i + j * ny_, q});
        }
        cr.num_l = static_cast<int>(child_l_.size()) - cr.first_l;
        if (cr.num_l == 0) continue;
        cr.first_run = static_cast<int>(child_runs_.size());
        cr.num_runs = static_cast<int>(child.runs.size());
        child_runs_.insert(child_runs_.end(), child.runs.begin(), child.runs.end());
        child_rows_.push_back(cr);
      }
    }
  }
  // Scatter maps of each residual-block kind into U (positions) and compact W (offsets).
  kinds_.assign(ycols.size(), BlockKind());
  for (size_t b = 0; b < ycols.size(); ++b) {
    BlockKind& kind = kinds_[b];
    kind.num_y = static_cast<int>(ycols[b].size());
    // Columns latest-eliminated first: a column's U entries in the lower triangle are then those
    // of the columns after it (a contiguous range, no test per pair).
    for (int a = 0; a < kind.num_y; ++a) kind.y_order.push_back(a);
    std::sort(kind.y_order.begin(), kind.y_order.end(),
              [&](int a, int c) { return position_[ycols[b][a]] > position_[ycols[b][c]]; });
    for (int a : kind.y_order) kind.y_position.push_back(position_[ycols[b][a]]);
    for (size_t c = 0; c < pcols[b].size(); ++c)
      if (pcols[b][c] >= 0) {
        kind.free_local.push_back(static_cast<int>(c));
        kind.free_p.push_back(pcols[b][c]);
      }
    for (int k : kind.y_position)
      for (int p : kind.free_p) {
        const RowGroup& g = groups_[row_group[k]];  // the row reaches p, so it has a group
        const int col = static_cast<int>(std::lower_bound(g.columns.begin(), g.columns.end(), p) -
                                         g.columns.begin());
        kind.w_offset.push_back(g.offset + (k - g.first_row) * static_cast<int>(g.columns.size()) + col);
      }
  }
  // The same maps by (y, p) for a problem that assembles its frames itself (NormalLayout).
  u_index_.resize(static_cast<size_t>(ny_) * ny_);
  for (int i = 0; i < ny_; ++i)
    for (int j = 0; j < ny_; ++j)
      u_index_[static_cast<size_t>(i) * ny_ + j] =
          std::max(position_[i], position_[j]) + std::min(position_[i], position_[j]) * ny_;
  w_index_.assign(static_cast<size_t>(ny_) * np_, -1);
  for (size_t b = 0; b < kinds_.size(); ++b) {
    const BlockKind& kind = kinds_[b];
    const int n = static_cast<int>(kind.free_p.size());
    for (int a = 0; a < kind.num_y; ++a)
      for (int c = 0; c < n; ++c)
        w_index_[static_cast<size_t>(ycols[b][kind.y_order[a]]) * np_ + kind.free_p[c]] = kind.w_offset[a * n + c];
  }
  layout_ = {ny_, np_, u_index_.data(), w_index_.data()};
}

// Cholesky in place, skipping what is outside L_f's pattern: column j is updated only by the
// columns with a non-zero in row j (the rest of its chain). Eigen's blocked dense LLT costs four
// times as much at 38 x 38, most of it on zeros. Left-looking, each column's tail gets all its
// updates in registers, eight rows at a time, before one store; each entry gets the same fused
// multiply-subtracts in the same order (ascending k) as the right-looking loop that came before
// it, so the same bits (the fit's iterations with gaps answer last-bit changes like chance:
// BENCHMARKS.md, "With gaps"); that loop read back each update's masked store in the next one.
bool ArrowSchurProblem::FactorInPlace(Eigen::MatrixXd* a) const {
  const int n = ny_;
  double* data = a->data();
  for (int j = 0; j < n; ++j) {
    double* col = data + static_cast<size_t>(j) * n;
    const std::vector<int>& ks = l_cols_[j];
#if defined(__AVX512F__)
    for (int e = j; e < n; e += 8) {
      const __mmask8 m = n - e >= 8 ? static_cast<__mmask8>(0xff) : static_cast<__mmask8>((1u << (n - e)) - 1);
      __m512d acc = _mm512_maskz_loadu_pd(m, col + e);
      for (int k : ks) {
        const double* ck = data + static_cast<size_t>(k) * n;
        acc = _mm512_fnmadd_pd(_mm512_set1_pd(ck[j]), _mm512_maskz_loadu_pd(m, ck + e), acc);
      }
      _mm512_mask_storeu_pd(col + e, m, acc);
    }
#else
    for (int k : ks) {
      const double* ck = data + static_cast<size_t>(k) * n;
      const double lx = ck[j];
      for (int i = j; i < n; ++i) col[i] -= lx * ck[i];
    }
#endif
    if (!(col[j] > 0.0)) return false;
    const double d = std::sqrt(col[j]);
    col[j] = d;
    const double inv = 1.0 / d;  // one division a column instead of one an entry
    for (int i : l_rows_[j]) col[i] *= inv;
  }
  return true;
}

void ArrowSchurProblem::SolveLower(const Eigen::MatrixXd& l, Eigen::VectorXd* v) const {
  const int n = ny_;
  for (int j = 0; j < n; ++j) {
    const double vj = ((*v)[j] /= l(j, j));
    if (!l_rows_[j].empty()) v->tail(n - j - 1) -= vj * l.col(j).tail(n - j - 1);
  }
}

void ArrowSchurProblem::SolveLowerTransposed(const Eigen::MatrixXd& l, Eigen::VectorXd* v) const {
  const int n = ny_;
  for (int i = n - 1; i >= 0; --i) {
    double sum = (*v)[i];
    if (!l_rows_[i].empty()) sum -= l.col(i).tail(n - i - 1).dot(v->tail(n - i - 1));
    (*v)[i] = sum / l(i, i);
  }
}

std::string ArrowSchurProblem::DescribeStructure() const {
  std::string out = "elimination order:";
  for (int i : order_) out += " " + std::to_string(i);
  out += "\nL_f non-zeros below the diagonal: " + std::to_string(u_pattern_.size() - ny_) + " (dense " +
         std::to_string(ny_ * (ny_ - 1) / 2) + "); compact W_f: " + std::to_string(w_size_) +
         " values (dense " + std::to_string(ny_ * np_) + ")\n";
  for (const RowGroup& g : groups_) {
    out += "  rows " + std::to_string(g.first_row) + "+" + std::to_string(g.num_rows) + ": " +
           std::to_string(g.columns.size()) + " columns in [" + std::to_string(g.columns.front()) +
           ", " + std::to_string(g.columns.back()) + "]" + (g.contiguous ? " contiguous" : "") + "\n";
  }
  return out;
}

bool ArrowSchurProblem::Cost(const Eigen::VectorXd& x, double* cost) {
  if (!problem_->SetShared(x.tail(np_))) return false;
  frame_costs_.resize(nf_);
  ParallelChunks(nf_, num_threads_, [&](int t, int b, int e) {
    ThreadState& ts = *threads_[t];
    ts.cost = 0;
    ts.ok = true;
    for (int f = b; f < e && ts.ok; ++f) {
      ts.ok = FrameSquaredNorm(*problem_, ts.evaluator.get(), f, x.data() + static_cast<size_t>(f) * ny_,
                               &frame_costs_[f]);
      ts.cost += frame_costs_[f];
    }
  });
  double sum = 0;
  for (int t = 0; t < std::max(1, std::min(num_threads_, nf_)); ++t) {
    if (!threads_[t]->ok) return false;
    sum += threads_[t]->cost;
  }
  *cost = 0.5 * (sum + SharedRowsSquaredNorm(*problem_, x.tail(np_)));
  return std::isfinite(*cost);
}

bool ArrowSchurProblem::Linearize(const Eigen::VectorXd& x, double* cost, Eigen::VectorXd* gradient,
                                  Eigen::VectorXd* diagonal) {
  x_ = x;
  damped_solve_ready_ = false;
  fresh_linearization_ = true;
  const int n = num_parameters();
  gradient->setZero(n);
  diagonal->setZero(n);
  anticipated_ready_ = false;
  if (!problem_->SetShared(x.tail(np_))) return false;
  // With an anticipated damping, each frame is also reduced while its U_f and W_f are hot (the
  // pass SolveDamped would otherwise make), at the damping LM will ask for next.
  const bool reduce = anticipated_lambda_ > 0;
  if (reduce) anticipated_damping_.resize(n);
  ParallelChunks(nf_, num_threads_, [&](int t, int b, int e) {
    ThreadState& ts = *threads_[t];
    ts.cost = 0;
    ts.ok = true;
    ts.reduced = reduce;
    ts.gp.setZero();
    ts.s_v.setZero();
    for (Eigen::MatrixXd& acc : ts.v_acc) acc.setZero();
    if (reduce) BeginReduction(ts);
    for (int f = b; f < e; ++f) {
      if (!ts.evaluator->Evaluate(f, x.data() + static_cast<size_t>(f) * ny_, true) ||
          !AccumulateFrame(ts, /*linearizing=*/true)) {
        ts.ok = false;
        return;
      }
      if (cached_) {
        double* packed = CachedU(f);
        for (size_t k = 0; k < u_pattern_.size(); ++k) packed[k] = ts.u.data()[u_pattern_[k]];
        std::copy(ts.w.begin(), ts.w.end(), CachedW(f));
      }
      double* gy = gradient->data() + static_cast<size_t>(f) * ny_;
      double* dg = diagonal->data() + static_cast<size_t>(f) * ny_;
      for (int i = 0; i < ny_; ++i) {
        gy[i] = ts.gyi[i];
        dg[i] = ts.u(position_[i], position_[i]);
      }
      const double *w, *target;
      if (problem_->FramePrior(f, &w, &target)) {
        const double* y = x.data() + static_cast<size_t>(f) * ny_;
        for (int i = 0; i < ny_; ++i) {
          const double r = w[i] * (y[i] - target[i]);
          ts.cost += r * r;
          gy[i] += w[i] * r;
          dg[i] += w[i] * w[i];
        }
      }
      if (!ts.reduced) continue;
      // The damped U_f exactly as LevenbergMarquardt will form it from `diagonal`.
      double* dmp = anticipated_damping_.data() + static_cast<size_t>(f) * ny_;
      AddFramePrior(f, &ts.u);
      for (int i = 0; i < ny_; ++i) {
        dmp[i] = anticipated_lambda_ * std::min(std::max(dg[i], anticipated_min_), anticipated_max_);
        ts.u(position_[i], position_[i]) += dmp[i];
        ts.gy[position_[i]] = gy[i];
      }
      ts.w_frame = ts.w.data();
      if (!FactorInPlace(&ts.u)) {
        ts.reduced = false;  // SolveDamped will say so with its own pass
        continue;
      }
      ReduceFrame(ts, f);
    }
    // V of this thread's frames: the last stacks, then each kind's accumulator into its lower
    // triangle (a kind's columns need not be sorted).
    for (size_t k = 0; k < kinds_.size(); ++k) {
      FlushV(ts, static_cast<int>(k));
      const std::vector<int>& cols = kinds_[k].free_p;
      const Eigen::MatrixXd& acc = ts.v_acc[k];
      for (size_t c = 0; c < cols.size(); ++c)
        for (size_t d = 0; d <= c; ++d)
          ts.s_v(std::max(cols[c], cols[d]), std::min(cols[c], cols[d])) += acc(c, d);
    }
    if (ts.reduced) EndReduction(ts);
  });
  double sum = 0;
  bool all_reduced = reduce;
  v_total_.setZero(np_, np_);
  for (int t = 0; t < std::max(1, std::min(num_threads_, nf_)); ++t) {
    const ThreadState& ts = *threads_[t];
    if (!ts.ok) return false;
    sum += ts.cost;
    gradient->tail(np_) += ts.gp;
    v_total_ += ts.s_v;
    all_reduced = all_reduced && ts.reduced;
  }
  diagonal->tail(np_) = v_total_.diagonal();
  const Eigen::VectorXd& w = problem_->prior_weight();
  const Eigen::VectorXd delta = x.tail(np_) - problem_->prior_target();
  gradient->tail(np_) += w.cwiseProduct(w.cwiseProduct(delta));
  diagonal->tail(np_) += w.cwiseProduct(w);
  const Eigen::MatrixXd& g = problem_->shared_rows();
  if (g.rows() > 0) {
    gradient->tail(np_) += g.transpose() * (g * delta);
    diagonal->tail(np_) += g.colwise().squaredNorm().transpose();
  }
  *cost = 0.5 * (sum + SharedRowsSquaredNorm(*problem_, x.tail(np_)));
  gradient_ = *gradient;
  if (all_reduced) {
    auto dmp_p = anticipated_damping_.tail(np_);
    if (reduced_damping_) {
      // Marquardt's scaling on the reduced system: the shared parameters damped by the diagonal
      // of S (at the frames' anticipated damping) instead of J_p^T J_p's; S is reduced undamped
      // first, to read that diagonal, and damped after.
      dmp_p.setZero();
      anticipated_ready_ = FinishReducedSystem(dmp_p, &anticipated_s_, &anticipated_rhs_);
      if (anticipated_ready_) {
        Eigen::VectorXd d = anticipated_s_.diagonal();
        if (secant_ && secant_e_.size() > 0) d += secant_e_.diagonal();
        for (int i = 0; i < np_; ++i) (*diagonal)[nf_ * ny_ + i] = std::max(d[i], 0.0);
      }
    }
    for (int i = 0; i < np_; ++i)
      dmp_p[i] = anticipated_lambda_ *
                 std::min(std::max((*diagonal)[nf_ * ny_ + i], anticipated_min_), anticipated_max_);
    if (!reduced_damping_)
      anticipated_ready_ = FinishReducedSystem(dmp_p, &anticipated_s_, &anticipated_rhs_);
    else if (anticipated_ready_)
      anticipated_s_.diagonal() += dmp_p;
  }
  return std::isfinite(*cost) && gradient->allFinite();
}

// U (lower, elimination order) and compact W of one evaluated frame, from the problem's own
// assembly where it has one, else from the blocks as follows. When `linearizing`, also
// the frame's cost, its gradient (by y index, in ts.gyi) and its part of the shared gradient, and
// its J_p^T columns stacked for V. Blocks are copied into zero-padded 3-row panels so every
// product is an unrolled 3-term dot product, scattered through the block kind's precomputed
// maps (Eigen's general small products cost three times as much here: their sizes are only
// known at run time). False if a block's kind is unknown.
bool ArrowSchurProblem::AccumulateFrame(ThreadState& ts, bool linearizing) const {
  static_assert(kMaxBlockRows == 3, "the panels below are unrolled for 3 rows");
  for (int k : u_pattern_) ts.u.data()[k] = 0.0;  // the rest of ts.u stays zero
  std::fill(ts.w.begin(), ts.w.end(), 0.0);
  if (linearizing) ts.gyi.setZero();
  double* w = ts.w.data();
  double* u = ts.u.data();
  double* jy = ts.panel_y.data();
  double* jp = ts.panel_p.data();
  // The problem's own assembly where it has one (MarkerFitProblem: from per-segment sums); the
  // blocks then give only the cost and V's stacks.
  const bool assembled = ts.evaluator->AddNormalEquations(
      layout_, u, w, linearizing ? ts.gyi.data() : nullptr, linearizing ? ts.gp.data() : nullptr);
  for (int k = 0; k < ts.evaluator->num_blocks(); ++k) {
    const ResidualBlock& blk = ts.evaluator->block(k);
    if (blk.kind < 0 || blk.kind >= static_cast<int>(kinds_.size()) ||
        kinds_[blk.kind].num_y != blk.num_y || blk.rows < 1 || blk.rows > kMaxBlockRows)
      return false;
    const BlockKind& kind = kinds_[blk.kind];
    const int rows = blk.rows, nyb = blk.num_y, np = static_cast<int>(kind.free_p.size());
    const int* yorder = kind.y_order.data();
    if (assembled && !linearizing) continue;
    if (assembled) {
      // Only the cost and V's stack need the block: its J_p rows go straight into the stack (the
      // panel below, then a copy of it, cost a memmove call per marker).
      double res[3] = {0, 0, 0};
      for (int r = 0; r < rows; ++r) res[r] = blk.residual[r];
      ts.cost += res[0] * res[0] + res[1] * res[1] + res[2] * res[2];
      if (np == 0) continue;
      int& count = ts.v_count[blk.kind];
      double* stack = ts.v_stack[blk.kind].data() + static_cast<size_t>(count) * np;
      for (int c = 0; c < np; ++c)
        for (int r = 0; r < rows; ++r) stack[r * np + c] = blk.jp[kind.free_local[c] * kMaxBlockRows + r];
      count += rows;
      if (count + kMaxBlockRows > ts.v_stack[blk.kind].cols()) FlushV(ts, blk.kind);
      continue;
    }
    // jp as three rows of np values (row r at jp + r * np), so a W row is three axpys.
    for (int c = 0; c < np; ++c)
      for (int r = 0; r < 3; ++r)
        jp[r * np + c] = r < rows ? blk.jp[kind.free_local[c] * kMaxBlockRows + r] : 0.0;
    const double* jp0 = jp;
    const double* jp1 = jp + np;
    const double* jp2 = jp + 2 * np;
    for (int a = 0; a < nyb; ++a)
      for (int r = 0; r < 3; ++r) jy[3 * a + r] = r < rows ? blk.jy[yorder[a] * kMaxBlockRows + r] : 0.0;
    double* wrow = ts.w_row.data();
    const int* ypos = kind.y_position.data();
    const int* woff = kind.w_offset.data();
    for (int a = 0; a < nyb; ++a) {
      const double a0 = jy[3 * a], a1 = jy[3 * a + 1], a2 = jy[3 * a + 2];
      double* ucol = u + ypos[a];  // row ypos[a], columns ypos[c] <= ypos[a] (c >= a)
      for (int c = a; c < nyb; ++c)
        ucol[static_cast<size_t>(ypos[c]) * ny_] += a0 * jy[3 * c] + a1 * jy[3 * c + 1] + a2 * jy[3 * c + 2];
      for (int c = 0; c < np; ++c) wrow[c] = a0 * jp0[c] + a1 * jp1[c] + a2 * jp2[c];
      const int* wo = woff + a * np;
      for (int c = 0; c < np; ++c) w[wo[c]] += wrow[c];
    }
    if (!linearizing) continue;
    double res[3] = {0, 0, 0};
    for (int r = 0; r < rows; ++r) res[r] = blk.residual[r];
    ts.cost += res[0] * res[0] + res[1] * res[1] + res[2] * res[2];
    for (int a = 0; a < nyb; ++a)
      ts.gyi[blk.y_index[yorder[a]]] += jy[3 * a] * res[0] + jy[3 * a + 1] * res[1] + jy[3 * a + 2] * res[2];
    for (int c = 0; c < np; ++c)
      ts.gp[kind.free_p[c]] += jp0[c] * res[0] + jp1[c] * res[1] + jp2[c] * res[2];
    if (np > 0) {
      int& count = ts.v_count[blk.kind];
      double* stack = ts.v_stack[blk.kind].data() + static_cast<size_t>(count) * np;
      std::copy(jp, jp + rows * np, stack);
      count += rows;
      if (count + kMaxBlockRows > ts.v_stack[blk.kind].cols()) FlushV(ts, blk.kind);
    }
  }
  return true;
}

void ArrowSchurProblem::FlushV(ThreadState& ts, int kind) const {
  int& count = ts.v_count[kind];
  if (count == 0) return;
  ts.v_acc[kind].selfadjointView<Eigen::Lower>().rankUpdate(ts.v_stack[kind].leftCols(count), 1.0);
  count = 0;
}

void ArrowSchurProblem::FlushGroup(ThreadState& ts, int group) const {
  int& count = ts.g_count[group];
  if (count == 0) return;
  Eigen::MatrixXd& target = groups_[group].full ? ts.s : ts.g_acc[group];
  target.selfadjointView<Eigen::Lower>().rankUpdate(ts.g_stack[group].leftCols(count), -1.0);
  count = 0;
}

void ArrowSchurProblem::AddFramePrior(int f, Eigen::MatrixXd* u) const {
  const double *w, *target;
  if (!problem_->FramePrior(f, &w, &target)) return;
  for (int i = 0; i < ny_; ++i) (*u)(position_[i], position_[i]) += w[i] * w[i];
}

// U_f + damping factored in place into ts.u, W_f at ts.w_frame, the frame's gradient in ts.gy (both in
// elimination order): from the cache, or from a fresh evaluation at the linearisation point.
bool ArrowSchurProblem::LoadFrame(ThreadState& ts, int f, const Eigen::VectorXd& damping) {
  if (cached_) {
    const double* packed = CachedU(f);
    for (size_t k = 0; k < u_pattern_.size(); ++k) ts.u.data()[u_pattern_[k]] = packed[k];
    ts.w_frame = CachedW(f);
  } else {
    if (!ts.evaluator->Evaluate(f, x_.data() + static_cast<size_t>(f) * ny_, true) ||
        !AccumulateFrame(ts, /*linearizing=*/false))
      return false;
    ts.w_frame = ts.w.data();
  }
  const double* g = gradient_.data() + static_cast<size_t>(f) * ny_;
  const double* dmp = damping.data() + static_cast<size_t>(f) * ny_;
  AddFramePrior(f, &ts.u);
  for (int i = 0; i < ny_; ++i) {
    ts.u(position_[i], position_[i]) += dmp[i];
    ts.gy[position_[i]] = g[i];
  }
  return FactorInPlace(&ts.u);
}

// Begin / ReduceFrame / EndReduction: one thread's share of S - V and of the reduced
// right-hand side; ReduceFrame takes a frame whose U_f + damping is factored in ts.u, with W_f at
// ts.w_frame and its gradient in ts.gy.
void ArrowSchurProblem::BeginReduction(ThreadState& ts) const {
  ts.s.setZero();
  ts.rhs.setZero();
  for (Eigen::MatrixXd& acc : ts.g_acc) acc.setZero();
  for (Eigen::VectorXd& rhs : ts.g_rhs) rhs.setZero();
  std::fill(ts.g_count.begin(), ts.g_count.end(), 0);
}

void ArrowSchurProblem::ReduceFrame(ThreadState& ts, int f) {
  if (cached_) {  // the back-substitution reuses the factor
    double* packed = CachedL(f);
    for (size_t k = 0; k < u_pattern_.size(); ++k) packed[k] = ts.u.data()[u_pattern_[k]];
  }
  if (np_ == 0) return;
  const Eigen::MatrixXd& l = ts.u;
  ts.v = ts.gy;
  SolveLower(l, &ts.v);
  // Y = L^{-1} W, group by group in elimination order, each group's rows written straight into
  // the next free columns of its stack for S's rank update (the stack holds them row after row,
  // as the compact layout does): W's rows, minus what the rows eliminated earlier contribute
  // (through the columns they reach), then the group's own triangle. A group's rows stay where
  // they are until the next frame, so a flush after them leaves them readable by its ancestors.
  double** base = ts.y_base.data();
  const double* ld = l.data();
  const ChildRow* cr = child_rows_.data();
  const ChildRow* const cr_end = cr + child_rows_.size();
  for (size_t gi = 0; gi < groups_.size(); ++gi) {
    const RowGroup& g = groups_[gi];
    const int n = static_cast<int>(g.columns.size());
    int& count = ts.g_count[gi];
    double* yg = ts.g_stack[gi].col(count).data();
    base[gi] = yg;
    std::copy(ts.w_frame + g.offset, ts.w_frame + g.offset + g.num_rows * n, yg);
    for (; cr != cr_end && cr->group == static_cast<int>(gi); ++cr) {
      const int hn = static_cast<int>(groups_[cr->child].columns.size());
      const double* yh = base[cr->child];
      double* dst = yg + cr->row * n;
      const std::pair<int, int>* lq = child_l_.data() + cr->first_l;
      const RowGroup::Run* runs = child_runs_.data() + cr->first_run;
      // Three of the child's rows at a time (all of them for a body's joints), zero weights for
      // the missing ones (adding 0 * y changes nothing).
      for (int q0 = 0; q0 < cr->num_l; q0 += 3) {
        const int nq = std::min(3, cr->num_l - q0);
        const double c0 = ld[lq[q0].first];
        const double c1 = nq > 1 ? ld[lq[q0 + 1].first] : 0.0;
        const double c2 = nq > 2 ? ld[lq[q0 + 2].first] : 0.0;
        const double* a0 = yh + lq[q0].second * hn;
        const double* a1 = nq > 1 ? yh + lq[q0 + 1].second * hn : a0;
        const double* a2 = nq > 2 ? yh + lq[q0 + 2].second * hn : a0;
        for (int k = 0; k < cr->num_runs; ++k) {
          const RowGroup::Run& run = runs[k];
          SubtractCombination(dst + run.to, a0 + run.from, a1 + run.from, a2 + run.from, c0, c1, c2, run.length);
        }
      }
    }
    for (int r = 0; r < g.num_rows; ++r) {
      Eigen::Map<Eigen::VectorXd> row(yg + r * n, n);
      for (int q = 0; q < r; ++q)
        row -= l(g.first_row + r, g.first_row + q) * Eigen::Map<const Eigen::VectorXd>(yg + q * n, n);
      // A product with the reciprocal: a vector division costs a dozen products on this CPU
      // (it was the largest single cost of the reduction once the rest was flat).
      row *= 1.0 / l(g.first_row + r, g.first_row + r);
      ts.g_rhs[gi] += ts.v[g.first_row + r] * row;
    }
    count += g.num_rows;
    if (count + g.num_rows > ts.g_stack[gi].cols()) FlushGroup(ts, static_cast<int>(gi));
  }
}

void ArrowSchurProblem::EndReduction(ThreadState& ts) const {
  for (size_t gi = 0; gi < groups_.size(); ++gi) {
    FlushGroup(ts, static_cast<int>(gi));
    const RowGroup& g = groups_[gi];
    for (size_t c = 0; c < g.columns.size(); ++c) ts.rhs[g.columns[c]] += ts.g_rhs[gi][c];
    if (g.full) continue;
    const Eigen::MatrixXd& acc = ts.g_acc[gi];
    const int n = static_cast<int>(g.columns.size());
    for (int c = 0; c < n; ++c)
      for (int d = 0; d <= c; ++d) ts.s(g.columns[c], g.columns[d]) += acc(c, d);
  }
}

// The threads' shares summed, plus V, the priors, the damping of p and the dense rows.
bool ArrowSchurProblem::FinishReducedSystem(const Eigen::VectorXd& damping_p, Eigen::MatrixXd* s_out,
                                            Eigen::VectorXd* rhs_out) const {
  s_out->setZero(np_, np_);
  rhs_out->setZero(np_);
  for (int t = 0; t < std::max(1, std::min(num_threads_, nf_)); ++t) {
    if (!threads_[t]->ok) return false;
    *s_out += threads_[t]->s;
    *rhs_out += threads_[t]->rhs;
  }
  *s_out += v_total_;
  *rhs_out -= gradient_.tail(np_);
  const Eigen::VectorXd& w = problem_->prior_weight();
  s_out->diagonal() += w.cwiseProduct(w) + damping_p;
  const Eigen::MatrixXd& g = problem_->shared_rows();
  if (g.rows() > 0) s_out->selfadjointView<Eigen::Lower>().rankUpdate(g.transpose(), 1.0);
  return true;
}

bool ArrowSchurProblem::FormReducedSystem(const Eigen::VectorXd& damping, Eigen::MatrixXd* s_out,
                                          Eigen::VectorXd* rhs_out) {
  if (!cached_ && !problem_->SetShared(x_.tail(np_))) return false;
  ++reduction_passes_;
  ParallelChunks(nf_, num_threads_, [&](int t, int b, int e) {
    ThreadState& ts = *threads_[t];
    ts.ok = true;
    BeginReduction(ts);
    for (int f = b; f < e; ++f) {
      if (!LoadFrame(ts, f, damping)) {
        ts.ok = false;
        return;
      }
      ReduceFrame(ts, f);
    }
    EndReduction(ts);
  });
  return FinishReducedSystem(damping.tail(np_), s_out, rhs_out);
}

bool ArrowSchurProblem::SolveDamped(const Eigen::VectorXd& damping, Eigen::VectorXd* dx) {
  damped_solve_ready_ = false;
  last_shared_step_sq_ = std::numeric_limits<double>::quiet_NaN();
  Eigen::MatrixXd s;
  Eigen::VectorXd rhs;
  if (anticipated_ready_ && damping.size() == anticipated_damping_.size() &&
      (damping.array() == anticipated_damping_.array()).all()) {
    s.swap(anticipated_s_);
    rhs.swap(anticipated_rhs_);
  } else if (!FormReducedSystem(damping, &s, &rhs)) {
    anticipated_ready_ = false;
    return false;
  }
  anticipated_ready_ = false;
  dx->resize(num_parameters());
  Eigen::VectorXd dp = Eigen::VectorXd::Zero(np_);
  if (secant_ && np_ > 0 && fresh_linearization_) UpdateSecant(s, rhs, damping.tail(np_));
  fresh_linearization_ = false;
  if (np_ > 0) {
    if (secant_ && secant_e_.size() > 0) {
      Eigen::MatrixXd corrected = s;
      corrected.triangularView<Eigen::Lower>() += secant_e_;
      s_factor_.compute(corrected);
      if (s_factor_.info() != Eigen::Success) {
        secant_e_.setZero();
        s_factor_.compute(s);
      }
    } else {
      s_factor_.compute(s);  // reads the lower triangle only
    }
    if (s_factor_.info() != Eigen::Success) return false;
    dp = s_factor_.solve(rhs);
    dx->tail(np_) = dp;
    last_shared_step_sq_ = rhs.dot(dp);
    // In the Gauss-Newton metric (without the secant's correction, which flattens exactly the
    // directions still crawling and would stop the solve on a short step along them).
    if (secant_ && secant_e_.size() > 0) last_shared_step_sq_ -= dp.dot(secant_e_ * dp);
  }
  if (!BackSubstitute(damping, gradient_, dp, dx)) return false;
  damped_solve_ready_ = true;
  solved_damping_ = damping;
  return true;
}

// The reduced problem phi(p) = min_y F(y, p) has the gradient G = -rhs (the frames' remaining
// gradients folded in by their factors) and, near its minimum, a Hessian that is S (its
// Gauss-Newton model) plus the second-order terms sum r_i grad^2 r_i that Gauss-Newton drops.
// These are learnt from the steps as in NL2SOL (Dennis, Gay and Welsch, ACM TOMS 7, 1981): with
// s = p_{k+1} - p_k and y = G_{k+1} - G_k, E_{k+1} s = y - S_{k+1} s =: y#, by the sized
// DFP-like update E_{k+1} = tau E + (z y^T + y z^T) / y^T s - (z^T s) y y^T / (y^T s)^2,
// z = y# - tau E s, tau = min(1, |s^T y#| / |s^T E s|).
void ArrowSchurProblem::UpdateSecant(const Eigen::MatrixXd& s, const Eigen::VectorXd& rhs,
                                     const Eigen::VectorXd& damping_p) {
  const Eigen::VectorXd p = x_.tail(np_);
  const Eigen::VectorXd g = -rhs;
  if (secant_e_.size() == 0) secant_e_.setZero(np_, np_);
  if (secant_have_last_) {
    const Eigen::VectorXd step = p - secant_p_;
    const Eigen::VectorXd y = g - secant_g_;
    Eigen::VectorXd s_step = s.selfadjointView<Eigen::Lower>() * step;
    s_step -= damping_p.cwiseProduct(step);
    const Eigen::VectorXd ysharp = y - s_step;
    const double ys = y.dot(step);
    if (ys > 0 && step.squaredNorm() > 0) {
      const Eigen::VectorXd es = secant_e_ * step;
      const double ses = step.dot(es);
      const double tau = ses != 0 ? std::min(1.0, std::abs(step.dot(ysharp)) / std::abs(ses)) : 1.0;
      const Eigen::VectorXd z = ysharp - tau * es;
      secant_e_ = tau * secant_e_ + (z * y.transpose() + y * z.transpose()) / ys -
                  (z.dot(step) / (ys * ys)) * (y * y.transpose());
      ++secant_updates_;
    }
  }
  secant_p_ = p;
  secant_g_ = g;
  secant_have_last_ = true;
}

bool ArrowSchurProblem::BackSubstitute(const Eigen::VectorXd& damping, const Eigen::VectorXd& gradient,
                                       const Eigen::VectorXd& dp, Eigen::VectorXd* dx) {
  // Back-substitution, frame by frame: dy_f = -U_f^{-1} (g_yf + W_f dp).
  if (!cached_ && !problem_->SetShared(x_.tail(np_))) return false;
  ParallelChunks(nf_, num_threads_, [&](int t, int b, int e) {
    ThreadState& ts = *threads_[t];
    ts.ok = true;
    for (int f = b; f < e; ++f) {
      if (cached_) {  // the factor FormReducedSystem kept, at this damping
        const double* packed = CachedL(f);
        for (size_t k = 0; k < u_pattern_.size(); ++k) ts.u.data()[u_pattern_[k]] = packed[k];
        ts.w_frame = CachedW(f);
      } else if (!LoadFrame(ts, f, damping)) {
        ts.ok = false;
        return;
      }
      const double* g = gradient.data() + static_cast<size_t>(f) * ny_;
      for (int i = 0; i < ny_; ++i) ts.gy[position_[i]] = g[i];
      ts.wdp = ts.gy;
      for (const RowGroup& g : groups_) {
        const int n = static_cast<int>(g.columns.size());
        const double* wg = ts.w_frame + g.offset;
        for (int r = 0; r < g.num_rows; ++r) {
          double sum = 0;
          if (g.contiguous) {
            sum = Eigen::Map<const Eigen::VectorXd>(wg + r * n, n).dot(dp.segment(g.columns.front(), n));
          } else {
            for (int c = 0; c < n; ++c) sum += wg[r * n + c] * dp[g.columns[c]];
          }
          ts.wdp[g.first_row + r] += sum;
        }
      }
      SolveLower(ts.u, &ts.wdp);
      SolveLowerTransposed(ts.u, &ts.wdp);
      double* out = dx->data() + static_cast<size_t>(f) * ny_;
      for (int i = 0; i < ny_; ++i) out[i] = -ts.wdp[position_[i]];
    }
  });
  for (int t = 0; t < std::max(1, std::min(num_threads_, nf_)); ++t)
    if (!threads_[t]->ok) return false;
  return dx->allFinite();
}

bool ArrowSchurProblem::SolveAcceleration(const Eigen::VectorXd& damping, const Eigen::VectorXd& velocity, double h,
                                          Eigen::VectorXd* acceleration) {
  const int n = num_parameters();
  const int threads = std::max(1, std::min(num_threads_, nf_));
  if (!cached_ || !damped_solve_ready_ || !(h > 0) || velocity.size() != n || damping.size() != n ||
      !(damping.array() == solved_damping_.array()).all())
    return false;
  // (1) Residuals at x + h v, by frame and block: (kind, r0, r1, r2).
  const Eigen::VectorXd shifted = x_ + h * velocity;
  if (!problem_->SetShared(shifted.tail(np_))) {
    problem_->SetShared(x_.tail(np_));
    return false;
  }
  shifted_residuals_.resize(nf_);
  ParallelChunks(nf_, num_threads_, [&](int t, int b, int e) {
    ThreadState& ts = *threads_[t];
    ts.ok = true;
    for (int f = b; f < e; ++f) {
      if (!ts.evaluator->Evaluate(f, shifted.data() + static_cast<size_t>(f) * ny_, false)) {
        ts.ok = false;
        return;
      }
      std::vector<double>& out = shifted_residuals_[f];
      out.clear();
      for (int k = 0; k < ts.evaluator->num_blocks(); ++k) {
        const ResidualBlock& blk = ts.evaluator->block(k);
        out.push_back(blk.kind);
        for (int r = 0; r < kMaxBlockRows; ++r) out.push_back(r < blk.rows ? blk.residual[r] : 0.0);
      }
    }
  });
  bool ok = problem_->SetShared(x_.tail(np_));
  for (int t = 0; t < threads; ++t) ok = ok && threads_[t]->ok;
  if (!ok) return false;
  // (2) At x: b = J^T r_vv; each frame's share of the reduced right-hand side from its cached
  // factor while it is hot. The priors' rows are linear in x: their r_vv is zero.
  Eigen::VectorXd b = Eigen::VectorXd::Zero(n);
  const double* vp = velocity.data() + static_cast<size_t>(nf_) * ny_;
  ParallelChunks(nf_, num_threads_, [&](int t, int bf, int ef) {
    ThreadState& ts = *threads_[t];
    ts.ok = true;
    ts.gp.setZero();
    ts.rhs.setZero();
    for (int f = bf; f < ef; ++f) {
      const double* vy = velocity.data() + static_cast<size_t>(f) * ny_;
      const std::vector<double>& stored = shifted_residuals_[f];
      bool unique = true;
      for (size_t s = 0; s < stored.size(); s += 1 + kMaxBlockRows) {
        const int kind = static_cast<int>(stored[s]);
        if (kind < 0 || kind >= static_cast<int>(kinds_.size()) || ts.kind_slot[kind] >= 0) unique = false;
        else ts.kind_slot[kind] = static_cast<int>(s);
      }
      const bool evaluated = unique && ts.evaluator->Evaluate(f, x_.data() + static_cast<size_t>(f) * ny_, true);
      ts.by.setZero();
      for (int k = 0; evaluated && k < ts.evaluator->num_blocks(); ++k) {
        const ResidualBlock& blk = ts.evaluator->block(k);
        const int slot = blk.kind >= 0 && blk.kind < static_cast<int>(kinds_.size()) ? ts.kind_slot[blk.kind] : -1;
        double rvv[kMaxBlockRows] = {0, 0, 0};
        for (int r = 0; r < blk.rows; ++r) {
          double jv = 0;
          for (int a = 0; a < blk.num_y; ++a) jv += blk.jy[a * kMaxBlockRows + r] * vy[blk.y_index[a]];
          for (int c = 0; c < blk.num_p; ++c)
            if (blk.p_index[c] >= 0) jv += blk.jp[c * kMaxBlockRows + r] * vp[blk.p_index[c]];
          const double shifted_r = slot >= 0 ? stored[slot + 1 + r] : 0.0;
          rvv[r] = (2.0 / h) * ((shifted_r - blk.residual[r]) / h - jv);
        }
        for (int a = 0; a < blk.num_y; ++a) {
          double sum = 0;
          for (int r = 0; r < blk.rows; ++r) sum += blk.jy[a * kMaxBlockRows + r] * rvv[r];
          ts.by[blk.y_index[a]] += sum;
        }
        for (int c = 0; c < blk.num_p; ++c) {
          if (blk.p_index[c] < 0) continue;
          double sum = 0;
          for (int r = 0; r < blk.rows; ++r) sum += blk.jp[c * kMaxBlockRows + r] * rvv[r];
          ts.gp[blk.p_index[c]] += sum;
        }
      }
      for (size_t s = 0; s < stored.size(); s += 1 + kMaxBlockRows) {
        const int kind = static_cast<int>(stored[s]);
        if (kind >= 0 && kind < static_cast<int>(kinds_.size())) ts.kind_slot[kind] = -1;
      }
      if (!evaluated) {
        ts.ok = false;
        return;
      }
      b.segment(static_cast<Eigen::Index>(f) * ny_, ny_) = ts.by;
      if (np_ == 0) continue;
      // W_f^T U_f^{-1} b_f, U_f's damped factor from the cache (the last SolveDamped's).
      const double* packed = CachedL(f);
      for (size_t k = 0; k < u_pattern_.size(); ++k) ts.u.data()[u_pattern_[k]] = packed[k];
      for (int i = 0; i < ny_; ++i) ts.v[position_[i]] = ts.by[i];
      SolveLower(ts.u, &ts.v);
      SolveLowerTransposed(ts.u, &ts.v);
      const double* w = CachedW(f);
      for (const RowGroup& g : groups_) {
        const int gn = static_cast<int>(g.columns.size());
        for (int r = 0; r < g.num_rows; ++r) {
          const double z = ts.v[g.first_row + r];
          if (z == 0.0) continue;
          const double* wr = w + g.offset + r * gn;
          if (g.contiguous) {
            ts.rhs.segment(g.columns.front(), gn) += z * Eigen::Map<const Eigen::VectorXd>(wr, gn);
          } else {
            for (int c = 0; c < gn; ++c) ts.rhs[g.columns[c]] += z * wr[c];
          }
        }
      }
    }
  });
  Eigen::VectorXd rhs = Eigen::VectorXd::Zero(np_);
  for (int t = 0; t < threads; ++t) {
    if (!threads_[t]->ok) return false;
    b.tail(np_) += threads_[t]->gp;
    rhs += threads_[t]->rhs;
  }
  acceleration->resize(n);
  Eigen::VectorXd dp = Eigen::VectorXd::Zero(np_);
  if (np_ > 0) {
    // (S) dp = -b_p + sum_f W_f^T U_f^{-1} b_f, as SolveDamped's reduced system with b for g.
    dp = s_factor_.solve(rhs - b.tail(np_));
    acceleration->tail(np_) = dp;
  }
  return BackSubstitute(damping, b, dp, acceleration);
}

bool ArrowSchurProblem::SharedCovariance(const Eigen::VectorXd& x, Eigen::MatrixXd* covariance,
                                         double frame_ridge) {
  // Damping: a relative ridge on the frame blocks only (their diagonal from the gradient pass).
  Eigen::VectorXd gradient, diagonal;
  double cost;
  const double lambda = anticipated_lambda_;
  anticipated_lambda_ = 0;  // no step follows
  const bool linearized = Linearize(x, &cost, &gradient, &diagonal);
  anticipated_lambda_ = lambda;
  if (!linearized) return false;
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
