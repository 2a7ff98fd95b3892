#include "solver/cholmod_solver.h"

#include <cholmod.h>
#include <dlfcn.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <map>
#include <numeric>

#include "solver/parallel.h"

namespace mocap::solver {
namespace {
using Clock = std::chrono::steady_clock;
using Long = SuiteSparse_long;
static_assert(sizeof(Long) == sizeof(std::int64_t));

double Since(Clock::time_point t) { return std::chrono::duration<double>(Clock::now() - t).count(); }

struct SparseFree {
  cholmod_common* c;
  void operator()(cholmod_sparse* a) const { cholmod_l_free_sparse(&a, c); }
};
struct FactorFree {
  cholmod_common* c;
  void operator()(cholmod_factor* l) const { cholmod_l_free_factor(&l, c); }
};
struct DenseFree {
  cholmod_common* c;
  void operator()(cholmod_dense* d) const { cholmod_l_free_dense(&d, c); }
};
using SparsePtr = std::unique_ptr<cholmod_sparse, SparseFree>;
using FactorPtr = std::unique_ptr<cholmod_factor, FactorFree>;
using DensePtr = std::unique_ptr<cholmod_dense, DenseFree>;

// Threads of CHOLMOD's parallel kernels for one factorisation and solve, restored afterwards:
//  * OpenBLAS (the supernodes' dense kernels): `blas_threads`;
//  * OpenMP: CHOLMOD 3 zeroes and copies supernodes in `omp parallel for num_threads(4)` loops
//    (4 fixed when it was built). On fewer or busy cores these fork/joins, one per supernode, cost
//    far more than they save (300 frames, 50 factorisations on 2 busy cores: 16 s, mostly
//    futex/sched_yield system time, against 2.7 s), so they run on the calling thread:
//    max-active-levels 0 makes every parallel region inactive. In libgomp (GCC >= 11) that
//    setting belongs to the calling thread, so other threads' OpenMP is unaffected.
// Both are looked up at run time, so any BLAS / OpenMP runtime works (others keep their setting).
class KernelThreads {
 public:
  explicit KernelThreads(int blas_threads) {
    using SetInt = void (*)(int);
    using GetInt = int (*)();
    static const SetInt set_blas = reinterpret_cast<SetInt>(dlsym(RTLD_DEFAULT, "openblas_set_num_threads"));
    static const GetInt get_blas = reinterpret_cast<GetInt>(dlsym(RTLD_DEFAULT, "openblas_get_num_threads"));
    static const SetInt set_levels = reinterpret_cast<SetInt>(dlsym(RTLD_DEFAULT, "omp_set_max_active_levels"));
    static const GetInt get_levels = reinterpret_cast<GetInt>(dlsym(RTLD_DEFAULT, "omp_get_max_active_levels"));
    if (set_blas && get_blas) {
      blas_previous_ = get_blas();
      if (blas_previous_ != blas_threads) {
        set_blas(blas_threads);
        set_blas_ = set_blas;
      }
    }
    if (set_levels && get_levels) {
      levels_previous_ = get_levels();
      if (levels_previous_ != 0) {
        set_levels(0);
        set_levels_ = set_levels;
      }
    }
  }
  ~KernelThreads() {
    if (set_blas_) set_blas_(blas_previous_);
    if (set_levels_) set_levels_(levels_previous_);
  }
  KernelThreads(const KernelThreads&) = delete;
  KernelThreads& operator=(const KernelThreads&) = delete;

 private:
  void (*set_blas_)(int) = nullptr;
  void (*set_levels_)(int) = nullptr;
  int blas_previous_ = 0, levels_previous_ = 0;
};

const char* OrderingName(int ordering) {
  switch (ordering) {
    case CHOLMOD_NATURAL: return "natural";
    case CHOLMOD_GIVEN: return "given";
    case CHOLMOD_AMD: return "amd";
    case CHOLMOD_METIS: return "metis";
    case CHOLMOD_NESDIS: return "nesdis";
    case CHOLMOD_COLAMD: return "colamd";
    case CHOLMOD_POSTORDERED: return "postordered";
    default: return "unknown";
  }
}

// Identifies a residual block's index pattern: rows, then the y and p index lists.
std::vector<int> BlockKey(const ResidualBlock& blk) {
  std::vector<int> key;
  key.reserve(3 + blk.num_y + blk.num_p);
  key.push_back(blk.rows);
  key.push_back(blk.num_y);
  key.insert(key.end(), blk.y_index, blk.y_index + blk.num_y);
  key.push_back(blk.num_p);
  key.insert(key.end(), blk.p_index, blk.p_index + blk.num_p);
  return key;
}
}  // namespace

struct SparseNormalCholeskyProblem::Impl {
  cholmod_common c;
  SparsePtr a{nullptr, SparseFree{&c}};   // J^T J, one triangle (kNormalMatrix, kJacobianProduct)
  SparsePtr jt{nullptr, SparseFree{&c}};  // J^T (kJacobian, kJacobianProduct)
  FactorPtr l{nullptr, FactorFree{&c}};
  DensePtr b{nullptr, DenseFree{&c}};
  Impl() {
    cholmod_l_start(&c);
    Configure();
  }
  void Configure() {
    cholmod_l_defaults(&c);
    c.print = 0;
    c.supernodal = CHOLMOD_SUPERNODAL;
  }
  ~Impl() {
    b.reset();
    l.reset();
    jt.reset();
    a.reset();
    cholmod_l_finish(&c);
  }
};

struct SparseNormalCholeskyProblem::BlockKind {
  int rows = 0;
  std::vector<int> y_index, p_index;  // as the evaluator gives them
  // Each row of the block is one column of J^T with these rows (sorted, unique): a frame's
  // local storage position (add f * ny) for y, the absolute storage row for p.
  std::vector<Long> entry_row;
  std::vector<char> entry_is_y;
  std::vector<int> y_dest, p_dest;  // entry of each y / p index (-1: fixed p)
  bool Matches(const ResidualBlock& blk) const {
    return blk.rows == rows && blk.num_y == static_cast<int>(y_index.size()) &&
           blk.num_p == static_cast<int>(p_index.size()) &&
           std::equal(y_index.begin(), y_index.end(), blk.y_index) &&
           std::equal(p_index.begin(), p_index.end(), blk.p_index);
  }
};

struct SparseNormalCholeskyProblem::ThreadState {
  std::unique_ptr<FrameEvaluator> evaluator;
  Eigen::MatrixXd v;  // this thread's sum of J_p^T J_p (storage order, lower triangle)
  Eigen::VectorXd gp, dp;
  Eigen::MatrixXd block_jp, block_u, block_w, block_v;
  std::vector<int> ka, pq, plocal;
  double cost = 0;
  bool ok = true, mismatch = false;
  // Pattern pass: block kinds seen by this thread and, per frame of its chunk, its blocks' kinds.
  std::map<std::vector<int>, int> kind_ids;
  std::vector<std::vector<int>> kind_keys;
  std::vector<int> frame_kinds, frame_blocks;
};

const char* SparseNormalCholeskyProblem::ToString(Assembly assembly) {
  switch (assembly) {
    case Assembly::kNormalMatrix: return "normal";
    case Assembly::kJacobian: return "jacobian";
    case Assembly::kJacobianProduct: return "aat";
  }
  return "?";
}

const char* SparseNormalCholeskyProblem::ToString(Ordering ordering) {
  switch (ordering) {
    case Ordering::kFramesFirst: return "frames_first";
    case Ordering::kFramesFirstGiven: return "frames_first_given";
    case Ordering::kCholmod: return "cholmod";
  }
  return "?";
}

bool SparseNormalCholeskyProblem::Parse(const std::string& name, Assembly* assembly) {
  for (Assembly a : {Assembly::kNormalMatrix, Assembly::kJacobian, Assembly::kJacobianProduct})
    if (name == ToString(a)) {
      *assembly = a;
      return true;
    }
  return false;
}

bool SparseNormalCholeskyProblem::Parse(const std::string& name, Ordering* ordering) {
  for (Ordering o : {Ordering::kFramesFirst, Ordering::kFramesFirstGiven, Ordering::kCholmod})
    if (name == ToString(o)) {
      *ordering = o;
      return true;
    }
  return false;
}

SparseNormalCholeskyProblem::SparseNormalCholeskyProblem(ArrowProblem* problem, int num_threads,
                                                         Options options)
    : problem_(problem),
      num_threads_(ResolveThreads(num_threads)),
      options_(options),
      nf_(problem->num_frames()),
      ny_(problem->frame_dim()),
      np_(problem->shared_dim()),
      n_(static_cast<std::int64_t>(nf_) * ny_ + np_),
      impl_(std::make_unique<Impl>()) {
  ComputeFrameOrder();
  for (int t = 0; t < num_threads_; ++t) {
    auto ts = std::make_unique<ThreadState>();
    ts->evaluator = problem_->NewEvaluator();
    ts->gp.resize(np_);
    ts->dp.resize(np_);
    if (options_.assembly == Assembly::kNormalMatrix) {
      ts->v.resize(np_, np_);
      ts->block_jp.resize(kMaxBlockRows, max_block_p_);
      ts->block_u.resize(max_block_y_, max_block_y_);
      ts->block_w.resize(max_block_y_, max_block_p_);
      ts->block_v.resize(max_block_p_, max_block_p_);
    }
    ts->ka.resize(max_block_y_);
    ts->pq.resize(max_block_p_);
    ts->plocal.resize(max_block_p_);
    threads_.push_back(std::move(ts));
  }
  impl_->b.reset(cholmod_l_zeros(n_, 1, CHOLMOD_REAL, &impl_->c));
  if (!impl_->b) error_ = "CHOLMOD: out of memory";
  if (options_.assembly == Assembly::kNormalMatrix && error_.empty()) {
    BuildNormalPattern();
    if (error_.empty()) Analyse(impl_->a.get());
  }
}

SparseNormalCholeskyProblem::~SparseNormalCholeskyProblem() = default;

int SparseNormalCholeskyProblem::num_parameters() const { return static_cast<int>(n_); }
int SparseNormalCholeskyProblem::num_residuals() const { return problem_->num_residuals(); }

bool SparseNormalCholeskyProblem::StoreLower() const {
  // Lower and in elimination order: CHOLMOD's natural ordering factors it without a copy. Any
  // other ordering permutes a copy; from the upper triangle that is one transpose, not two.
  return options_.ordering == Ordering::kFramesFirst;
}

// One frame's elimination order: CAMD on the pattern of one frame's normal matrix [U W; W^T V]
// (from BlockStructure) with y constrained before p, then CHOLMOD's weighted postorder of the
// elimination tree, so that each supernode's columns are contiguous. The y part is used for
// every frame; p keeps its relative order after all frames.
void SparseNormalCholeskyProblem::ComputeFrameOrder() {
  std::vector<std::vector<int>> ycols, pcols;
  problem_->BlockStructure(&ycols, &pcols);
  WidestBlock(ycols, pcols, &max_block_y_, &max_block_p_);
  y_elimination_.resize(ny_);
  p_elimination_.resize(np_);
  std::iota(y_elimination_.begin(), y_elimination_.end(), 0);
  std::iota(p_elimination_.begin(), p_elimination_.end(), 0);
  if (options_.ordering != Ordering::kCholmod && ny_ > 0) {
    const int m = ny_ + np_;
    std::vector<char> adj(static_cast<size_t>(m) * m, 0);
    for (int i = 0; i < m; ++i) adj[static_cast<size_t>(i) * m + i] = 1;
    for (int i = ny_; i < m; ++i)
      for (int j = ny_; j < m; ++j) adj[static_cast<size_t>(i) * m + j] = 1;  // V: dense
    std::vector<int> vars;
    for (size_t b = 0; b < ycols.size(); ++b) {
      vars.assign(ycols[b].begin(), ycols[b].end());
      for (int p : pcols[b])
        if (p >= 0) vars.push_back(ny_ + p);
      for (int a : vars)
        for (int c : vars) adj[static_cast<size_t>(a) * m + c] = 1;
    }
    Long nnz = 0;
    for (int j = 0; j < m; ++j)
      for (int i = 0; i <= j; ++i) nnz += adj[static_cast<size_t>(i) * m + j];
    cholmod_common* c = &impl_->c;
    SparsePtr pattern(cholmod_l_allocate_sparse(m, m, nnz, 1, 1, 1, CHOLMOD_PATTERN, c),
                      SparseFree{c});
    std::vector<Long> cmember(m), perm(m);
    bool ok = pattern != nullptr;
    if (ok) {
      Long* ap = static_cast<Long*>(pattern->p);
      Long* ai = static_cast<Long*>(pattern->i);
      Long k = 0;
      for (int j = 0; j < m; ++j) {
        ap[j] = k;
        for (int i = 0; i <= j; ++i)
          if (adj[static_cast<size_t>(i) * m + j]) ai[k++] = i;
      }
      ap[m] = k;
      for (int i = 0; i < m; ++i) cmember[i] = i < ny_ ? 0 : 1;
      ok = cholmod_l_camd(pattern.get(), nullptr, 0, cmember.data(), perm.data(), c) != 0;
    }
    if (ok) {
      impl_->Configure();
      c->nmethods = 1;
      c->method[0].ordering = CHOLMOD_GIVEN;
      c->postorder = 1;
      FactorPtr symbolic(cholmod_l_analyze_p(pattern.get(), perm.data(), nullptr, 0, c),
                         FactorFree{c});
      ok = symbolic != nullptr;
      if (ok) {
        const Long* post = static_cast<const Long*>(symbolic->Perm);
        int ky = 0, kp = 0;
        for (int k = 0; k < m; ++k) {
          if (post[k] < ny_) y_elimination_[ky++] = static_cast<int>(post[k]);
          else p_elimination_[kp++] = static_cast<int>(post[k] - ny_);
        }
      }
    }
    impl_->Configure();
    // Without CAMD (cannot happen short of running out of memory) the natural order is valid.
    if (!ok) {
      std::iota(y_elimination_.begin(), y_elimination_.end(), 0);
      std::iota(p_elimination_.begin(), p_elimination_.end(), 0);
    }
  }
  // Storage order: the elimination order itself with kFramesFirst, else the variables' order.
  y_order_ = y_elimination_;
  p_order_ = p_elimination_;
  if (options_.ordering != Ordering::kFramesFirst) {
    std::iota(y_order_.begin(), y_order_.end(), 0);
    std::iota(p_order_.begin(), p_order_.end(), 0);
  }
  local_.resize(ny_);
  ppos_.resize(np_);
  for (int k = 0; k < ny_; ++k) local_[y_order_[k]] = k;
  for (int k = 0; k < np_; ++k) ppos_[p_order_[k]] = k;
}

// The pattern of J^T J (one triangle, storage order) from BlockStructure, and where each
// frame's entries go.
void SparseNormalCholeskyProblem::BuildNormalPattern() {
  std::vector<std::vector<int>> ycols, pcols;
  problem_->BlockStructure(&ycols, &pcols);
  const int ny = ny_, np = np_;
  const Long nf = nf_, yrows = nf * ny;
  std::vector<char> uadj(static_cast<size_t>(ny) * ny, 0), wpat(static_cast<size_t>(ny) * np, 0);
  for (int k = 0; k < ny; ++k) uadj[static_cast<size_t>(k) * ny + k] = 1;
  for (size_t b = 0; b < ycols.size(); ++b)
    for (int ya : ycols[b]) {
      const int ka = local_[ya];
      for (int yc : ycols[b]) uadj[static_cast<size_t>(ka) * ny + local_[yc]] = 1;
      for (int p : pcols[b])
        if (p >= 0) wpat[static_cast<size_t>(ka) * np + ppos_[p]] = 1;
    }
  const bool lower = StoreLower();
  ulut_.assign(static_cast<size_t>(ny) * ny, -1);
  wlut_.assign(static_cast<size_t>(ny) * np, -1);
  vlut_.assign(static_cast<size_t>(np) * np, -1);
  wbase_.assign(np, 0);
  wstride_.assign(np, 0);
  // Per frame column (local k): offset of its first entry in the frame's region, and its rows
  // (local y positions, then shared storage positions + yrows).
  std::vector<Long> coloff(ny + 1, 0);
  std::vector<std::vector<Long>> colrows(ny);
  std::vector<std::vector<int>> wcol(np);
  Long off = 0;
  for (int k = 0; k < ny; ++k) {
    coloff[k] = off;
    if (lower) {
      for (int h = k; h < ny; ++h)
        if (uadj[static_cast<size_t>(h) * ny + k]) {
          ulut_[static_cast<size_t>(h) * ny + k] = off++;
          colrows[k].push_back(h);
        }
      for (int q = 0; q < np; ++q)
        if (wpat[static_cast<size_t>(k) * np + q]) {
          wlut_[static_cast<size_t>(k) * np + q] = off++;
          colrows[k].push_back(yrows + q);
        }
    } else {
      for (int l = 0; l <= k; ++l)
        if (uadj[static_cast<size_t>(k) * ny + l]) {
          ulut_[static_cast<size_t>(k) * ny + l] = off++;
          colrows[k].push_back(l);
        }
      for (int q = 0; q < np; ++q)
        if (wpat[static_cast<size_t>(k) * np + q]) {
          wlut_[static_cast<size_t>(k) * np + q] = static_cast<Long>(wcol[q].size());
          wcol[q].push_back(k);
        }
    }
  }
  coloff[ny] = off;
  ustride_ = off;
  // Shared columns.
  std::vector<Long> pcol_begin(np + 1, 0);
  Long pos = nf * ustride_;
  for (int q = 0; q < np; ++q) {
    pcol_begin[q] = pos;
    if (lower) {
      wstride_[q] = ustride_;
      for (int h = q; h < np; ++h) vlut_[static_cast<size_t>(h) * np + q] = pos++;
    } else {
      wbase_[q] = pos;
      wstride_[q] = static_cast<Long>(wcol[q].size());
      pos += nf * wstride_[q];
      for (int l = 0; l <= q; ++l) vlut_[static_cast<size_t>(q) * np + l] = pos++;
    }
  }
  pcol_begin[np] = pos;
  const Long nnz = pos;
  stats_.matrix_nonzeros = nnz;
  cholmod_common* c = &impl_->c;
  impl_->a.reset(cholmod_l_allocate_sparse(n_, n_, nnz, 1, 1, lower ? -1 : 1, CHOLMOD_REAL, c));
  if (!impl_->a) {
    error_ = "CHOLMOD: out of memory for the normal matrix (" + std::to_string(nnz) + " entries)";
    return;
  }
  Long* ap = static_cast<Long*>(impl_->a->p);
  Long* ai = static_cast<Long*>(impl_->a->i);
  double* ax = static_cast<double*>(impl_->a->x);
  ParallelChunks(nf_, num_threads_, [&](int, int b, int e) {
    for (Long f = b; f < e; ++f) {
      for (int k = 0; k < ny; ++k) {
        Long* out = ai + f * ustride_ + coloff[k];
        ap[f * ny + k] = f * ustride_ + coloff[k];
        for (Long r : colrows[k]) *out++ = r < ny ? f * ny + r : r;
      }
      if (!lower)
        for (int q = 0; q < np; ++q) {
          Long* out = ai + wbase_[q] + f * wstride_[q];
          for (int k : wcol[q]) *out++ = f * ny + k;
        }
    }
    std::fill(ax + b * ustride_, ax + e * ustride_, 0.0);
  });
  for (int q = 0; q < np; ++q) {
    ap[yrows + q] = pcol_begin[q];
    Long* out = ai + pcol_begin[q] + (lower ? 0 : nf * wstride_[q]);
    if (lower)
      for (int h = q; h < np; ++h) *out++ = yrows + h;
    else
      for (int l = 0; l <= q; ++l) *out++ = yrows + l;
  }
  ap[n_] = nnz;
  std::fill(ax + nf * ustride_, ax + nnz, 0.0);
  diagonal_position_.resize(n_);
  for (Long f = 0; f < nf; ++f)
    for (int k = 0; k < ny; ++k)
      diagonal_position_[f * ny + k] = f * ustride_ + ulut_[static_cast<size_t>(k) * ny + k];
  for (int q = 0; q < np; ++q) diagonal_position_[yrows + q] = vlut_[static_cast<size_t>(q) * np + q];
  undamped_diagonal_.setZero(n_);
}

bool SparseNormalCholeskyProblem::Analyse(void* matrix) {
  cholmod_sparse* a = static_cast<cholmod_sparse*>(matrix);
  cholmod_common* c = &impl_->c;
  const auto start = Clock::now();
  impl_->l.reset();
  impl_->Configure();
  cholmod_factor* l = nullptr;
  switch (options_.ordering) {
    case Ordering::kFramesFirst:
      // The matrix is stored in the frames-first order already.
      c->nmethods = 1;
      c->method[0].ordering = CHOLMOD_NATURAL;
      c->postorder = 0;
      l = cholmod_l_analyze(a, c);
      break;
    case Ordering::kFramesFirstGiven: {
      std::vector<Long> perm(n_);
      for (Long f = 0; f < nf_; ++f)
        for (int k = 0; k < ny_; ++k) perm[f * ny_ + k] = f * ny_ + y_elimination_[k];
      for (int k = 0; k < np_; ++k)
        perm[static_cast<Long>(nf_) * ny_ + k] = static_cast<Long>(nf_) * ny_ + p_elimination_[k];
      c->nmethods = 1;
      c->method[0].ordering = CHOLMOD_GIVEN;
      c->postorder = 1;
      l = cholmod_l_analyze_p(a, perm.data(), nullptr, 0, c);
      break;
    }
    case Ordering::kCholmod:
      c->nmethods = 0;  // CHOLMOD's default strategy: AMD, then METIS if AMD fills badly
      c->postorder = 1;
      l = cholmod_l_analyze(a, c);
      break;
  }
  const double fl = c->fl, lnz = c->lnz;
  impl_->Configure();
  ++stats_.analyses;
  stats_.analyse_seconds += Since(start);
  if (l == nullptr) {
    error_ = "CHOLMOD: symbolic analysis failed (status " + std::to_string(c->status) + ")";
    return false;
  }
  impl_->l.reset(l);
  stats_.factor_flops = fl;
  stats_.factor_nonzeros = lnz;
  stats_.ordering_used = OrderingName(l->ordering);
  return true;
}

// J^T's pattern from the blocks each frame has at x: block kinds (distinct index patterns), each
// frame's list of kinds, then the columns: frames' rows, prior rows, gauge rows, one damping
// column per unknown.
bool SparseNormalCholeskyProblem::BuildJacobianPattern(const Eigen::VectorXd& x) {
  if (!problem_->SetShared(x.tail(np_))) return false;
  const int used = std::max(1, std::min(num_threads_, nf_));
  ParallelChunks(nf_, num_threads_, [&](int t, int b, int e) {
    ThreadState& ts = *threads_[t];
    ts.ok = true;
    ts.kind_ids.clear();
    ts.kind_keys.clear();
    ts.frame_kinds.clear();
    ts.frame_blocks.clear();
    for (int f = b; f < e; ++f) {
      if (!ts.evaluator->Evaluate(f, x.data() + static_cast<size_t>(f) * ny_, false)) {
        ts.ok = false;
        return;
      }
      ts.frame_blocks.push_back(ts.evaluator->num_blocks());
      for (int k = 0; k < ts.evaluator->num_blocks(); ++k) {
        std::vector<int> key = BlockKey(ts.evaluator->block(k));
        auto [it, inserted] = ts.kind_ids.emplace(key, static_cast<int>(ts.kind_keys.size()));
        if (inserted) ts.kind_keys.push_back(std::move(key));
        ts.frame_kinds.push_back(it->second);
      }
    }
  });
  for (int t = 0; t < used; ++t)
    if (!threads_[t]->ok) return false;
  // Merge the kinds; frames in order (the chunks are contiguous and ascending).
  std::map<std::vector<int>, int> ids;
  std::vector<const std::vector<int>*> keys;
  frame_kind_begin_.assign(1, 0);
  frame_kinds_.clear();
  for (int t = 0; t < used; ++t) {
    ThreadState& ts = *threads_[t];
    std::vector<int> remap(ts.kind_keys.size());
    for (size_t k = 0; k < ts.kind_keys.size(); ++k) {
      auto [it, inserted] = ids.emplace(ts.kind_keys[k], static_cast<int>(keys.size()));
      if (inserted) keys.push_back(&it->first);
      remap[k] = it->second;
    }
    size_t next = 0;
    for (int nb : ts.frame_blocks) {
      for (int k = 0; k < nb; ++k) frame_kinds_.push_back(remap[ts.frame_kinds[next++]]);
      frame_kind_begin_.push_back(static_cast<Long>(frame_kinds_.size()));
    }
  }
  for (int t = 0; t < used; ++t) {
    threads_[t]->kind_ids.clear();
    threads_[t]->kind_keys.clear();
    threads_[t]->frame_kinds.clear();
    threads_[t]->frame_blocks.clear();
  }
  const Long yrows = static_cast<Long>(nf_) * ny_;
  kinds_.assign(keys.size(), BlockKind());
  for (size_t id = 0; id < keys.size(); ++id) {
    const std::vector<int>& key = *keys[id];
    BlockKind& kind = kinds_[id];
    kind.rows = key[0];
    const int num_y = key[1], num_p = key[2 + num_y];
    kind.y_index.assign(key.begin() + 2, key.begin() + 2 + num_y);
    kind.p_index.assign(key.begin() + 3 + num_y, key.begin() + 3 + num_y + num_p);
    std::vector<Long> rows;
    for (int y : kind.y_index) rows.push_back(local_[y]);
    for (int p : kind.p_index)
      if (p >= 0) rows.push_back(yrows + ppos_[p]);
    std::sort(rows.begin(), rows.end());
    rows.erase(std::unique(rows.begin(), rows.end()), rows.end());
    kind.entry_row = rows;
    kind.entry_is_y.resize(rows.size());
    for (size_t e = 0; e < rows.size(); ++e) kind.entry_is_y[e] = rows[e] < yrows ? 1 : 0;
    auto dest = [&](Long r) {
      return static_cast<int>(std::lower_bound(rows.begin(), rows.end(), r) - rows.begin());
    };
    for (int y : kind.y_index) kind.y_dest.push_back(dest(local_[y]));
    for (int p : kind.p_index) kind.p_dest.push_back(p >= 0 ? dest(yrows + ppos_[p]) : -1);
  }
  // Column and entry offsets per frame.
  std::vector<Long> frame_col_begin(nf_ + 1, 0);
  frame_entry_begin_.assign(nf_ + 1, 0);
  for (int f = 0; f < nf_; ++f) {
    Long cols = 0, entries = 0;
    for (Long k = frame_kind_begin_[f]; k < frame_kind_begin_[f + 1]; ++k) {
      const BlockKind& kind = kinds_[frame_kinds_[k]];
      cols += kind.rows;
      entries += static_cast<Long>(kind.rows) * kind.entry_row.size();
    }
    frame_col_begin[f + 1] = frame_col_begin[f] + cols;
    frame_entry_begin_[f + 1] = frame_entry_begin_[f] + entries;
  }
  const Eigen::MatrixXd& g = problem_->shared_rows();
  const Long gauge = g.rows();
  prior_column_ = frame_col_begin[nf_];
  damping_column_ = prior_column_ + np_ + gauge;
  const Long ncol = damping_column_ + n_;
  const Long nnz = frame_entry_begin_[nf_] + np_ + gauge * np_ + n_;
  stats_.matrix_nonzeros = nnz;
  cholmod_common* c = &impl_->c;
  impl_->l.reset();
  impl_->a.reset();
  impl_->jt.reset(cholmod_l_allocate_sparse(n_, ncol, nnz, 1, 1, 0, CHOLMOD_REAL, c));
  if (!impl_->jt) {
    error_ = "CHOLMOD: out of memory for J^T (" + std::to_string(nnz) + " entries)";
    return false;
  }
  Long* ap = static_cast<Long*>(impl_->jt->p);
  Long* ai = static_cast<Long*>(impl_->jt->i);
  double* ax = static_cast<double*>(impl_->jt->x);
  ParallelChunks(nf_, num_threads_, [&](int, int b, int e) {
    for (int f = b; f < e; ++f) {
      Long col = frame_col_begin[f], pos = frame_entry_begin_[f];
      const Long ybase = static_cast<Long>(f) * ny_;
      for (Long k = frame_kind_begin_[f]; k < frame_kind_begin_[f + 1]; ++k) {
        const BlockKind& kind = kinds_[frame_kinds_[k]];
        for (int r = 0; r < kind.rows; ++r) {
          ap[col++] = pos;
          for (size_t e2 = 0; e2 < kind.entry_row.size(); ++e2)
            ai[pos++] = kind.entry_is_y[e2] ? ybase + kind.entry_row[e2] : kind.entry_row[e2];
        }
      }
    }
    std::fill(ax + frame_entry_begin_[b], ax + frame_entry_begin_[e], 0.0);
  });
  Long pos = frame_entry_begin_[nf_], col = prior_column_;
  for (int q = 0; q < np_; ++q) {  // prior rows, in storage order
    ap[col++] = pos;
    ai[pos] = yrows + q;
    ax[pos++] = problem_->prior_weight()[p_order_[q]];
  }
  for (Long r = 0; r < gauge; ++r) {  // gauge rows
    ap[col++] = pos;
    for (int q = 0; q < np_; ++q) {
      ai[pos] = yrows + q;
      ax[pos++] = g(r, p_order_[q]);
    }
  }
  for (Long s = 0; s < n_; ++s) {  // damping (set per solve)
    ap[col++] = pos;
    ai[pos] = s;
    ax[pos++] = 0.0;
  }
  ap[ncol] = pos;
  jacobian_pattern_ = true;
  undamped_diagonal_.setZero(n_);
  return Analyse(impl_->jt.get());
}

double SparseNormalCholeskyProblem::SharedRowsSquaredNorm(const Eigen::VectorXd& p) const {
  const Eigen::VectorXd delta = p - problem_->prior_target();
  double sum = problem_->prior_weight().cwiseProduct(delta).squaredNorm();
  const Eigen::MatrixXd& g = problem_->shared_rows();
  if (g.rows() > 0) sum += (g * delta).squaredNorm();
  return sum;
}

// Gradient of the prior and gauge rows (original order).
void SparseNormalCholeskyProblem::AddSharedRows(const Eigen::VectorXd& p,
                                                Eigen::VectorXd* gradient) const {
  const Eigen::VectorXd& w = problem_->prior_weight();
  const Eigen::VectorXd delta = p - problem_->prior_target();
  gradient->tail(np_) += w.cwiseProduct(w.cwiseProduct(delta));
  const Eigen::MatrixXd& g = problem_->shared_rows();
  if (g.rows() > 0) gradient->tail(np_) += g.transpose() * (g * delta);
}

bool SparseNormalCholeskyProblem::Cost(const Eigen::VectorXd& x, double* cost) {
  if (!problem_->SetShared(x.tail(np_))) return false;
  ParallelChunks(nf_, num_threads_, [&](int t, int b, int e) {
    ThreadState& ts = *threads_[t];
    ts.cost = 0;
    ts.ok = true;
    for (int f = b; f < e; ++f) {
      if (!ts.evaluator->Evaluate(f, x.data() + static_cast<size_t>(f) * ny_, false)) {
        ts.ok = false;
        return;
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

bool SparseNormalCholeskyProblem::Linearize(const Eigen::VectorXd& x, double* cost,
                                            Eigen::VectorXd* gradient, Eigen::VectorXd* diagonal) {
  if (!error_.empty()) return false;
  // Per-frame priors (ArrowProblem::FramePrior) came after this path was written and are not
  // assembled here yet: refuse rather than solve a different problem.
  const double *prior_weight, *prior_target;
  if (nf_ > 0 && problem_->FramePrior(0, &prior_weight, &prior_target)) {
    error_ = "the CHOLMOD path does not support per-frame priors yet (use ArrowSchurProblem)";
    return false;
  }
  const auto start = Clock::now();
  const double analyse_before = stats_.analyse_seconds;
  gradient_.resize(0);
  bool ok = false;
  if (options_.assembly == Assembly::kNormalMatrix) {
    ok = LinearizeNormal(x, cost, gradient, diagonal);
  } else {
    bool mismatch = false;
    if (!jacobian_pattern_ && !BuildJacobianPattern(x)) return false;
    ok = LinearizeJacobian(x, cost, gradient, diagonal, &mismatch);
    if (mismatch) {  // a frame's blocks changed since the pattern was built: build it again
      if (!BuildJacobianPattern(x)) return false;
      ok = LinearizeJacobian(x, cost, gradient, diagonal, &mismatch) && !mismatch;
    }
    if (ok && options_.assembly == Assembly::kJacobianProduct) {
      cholmod_common* c = &impl_->c;
      SparsePtr product(cholmod_l_aat(impl_->jt.get(), nullptr, 0, 1, c), SparseFree{c});
      if (!product) return false;
      impl_->a.reset(cholmod_l_copy(product.get(), StoreLower() ? -1 : 1, 1, c));
      if (!impl_->a) return false;
      product.reset();
      const Long* ap = static_cast<const Long*>(impl_->a->p);
      const Long* ai = static_cast<const Long*>(impl_->a->i);
      const double* ax = static_cast<const double*>(impl_->a->x);
      diagonal_position_.assign(n_, -1);
      for (Long j = 0; j < n_; ++j)
        for (Long k = ap[j]; k < ap[j + 1]; ++k)
          if (ai[k] == j) diagonal_position_[j] = k;
      for (Long j = 0; j < n_; ++j) {
        if (diagonal_position_[j] < 0) return false;  // cannot happen: J^T has damping columns
        undamped_diagonal_[j] = ax[diagonal_position_[j]];
      }
    }
  }
  stats_.assemble_seconds += Since(start) - (stats_.analyse_seconds - analyse_before);
  if (!ok) return false;
  gradient_ = *gradient;
  return std::isfinite(*cost) && gradient->allFinite() && diagonal->allFinite();
}

bool SparseNormalCholeskyProblem::LinearizeNormal(const Eigen::VectorXd& x, double* cost,
                                                  Eigen::VectorXd* gradient,
                                                  Eigen::VectorXd* diagonal) {
  gradient->setZero(n_);
  diagonal->resize(n_);
  if (!problem_->SetShared(x.tail(np_))) return false;
  double* ax = static_cast<double*>(impl_->a->x);
  const bool lower = StoreLower();
  const int ny = ny_, np = np_;
  ParallelChunks(nf_, num_threads_, [&](int t, int b, int e) {
    ThreadState& ts = *threads_[t];
    ts.cost = 0;
    ts.ok = true;
    ts.gp.setZero();
    ts.v.setZero();
    int* ka = ts.ka.data();
    int* pq = ts.pq.data();
    int* plocal = ts.plocal.data();
    for (int f = b; f < e; ++f) {
      if (!ts.evaluator->Evaluate(f, x.data() + static_cast<size_t>(f) * ny, true)) {
        ts.ok = false;
        return;
      }
      double* gy = gradient->data() + static_cast<size_t>(f) * ny;
      double* uf = ax + static_cast<Long>(f) * ustride_;
      // Zeroed just before it is accumulated, so the frame's entries stay in cache.
      std::fill(uf, uf + ustride_, 0.0);
      if (!lower)
        for (int q = 0; q < np; ++q)
          std::fill(ax + wbase_[q] + f * wstride_[q], ax + wbase_[q] + (f + 1) * wstride_[q], 0.0);
      for (int k = 0; k < ts.evaluator->num_blocks(); ++k) {
        const ResidualBlock& blk = ts.evaluator->block(k);
        for (int r = 0; r < blk.rows; ++r) ts.cost += blk.residual[r] * blk.residual[r];
        using Strided = Eigen::Map<const Eigen::MatrixXd, 0, Eigen::OuterStride<>>;
        const Strided jy(blk.jy, blk.rows, blk.num_y, Eigen::OuterStride<>(kMaxBlockRows));
        const Strided jp_all(blk.jp, blk.rows, blk.num_p, Eigen::OuterStride<>(kMaxBlockRows));
        const Eigen::Map<const Eigen::VectorXd> res(blk.residual, blk.rows);
        int nbp = 0;
        for (int c = 0; c < blk.num_p; ++c)
          if (blk.p_index[c] >= 0) {
            plocal[nbp] = c;
            pq[nbp++] = ppos_[blk.p_index[c]];
          }
        for (int a = 0; a < blk.num_y; ++a) {
          ka[a] = local_[blk.y_index[a]];
          gy[blk.y_index[a]] += jy.col(a).dot(res);
        }
        auto& jp = ts.block_jp;
        for (int c = 0; c < nbp; ++c) {
          jp.col(c).head(blk.rows) = jp_all.col(plocal[c]);
          ts.gp[blk.p_index[plocal[c]]] += jp_all.col(plocal[c]).dot(res);
        }
        auto jpc = jp.topLeftCorner(blk.rows, nbp);
        auto uy = ts.block_u.topLeftCorner(blk.num_y, blk.num_y);
        auto wy = ts.block_w.topLeftCorner(blk.num_y, nbp);
        auto vp = ts.block_v.topLeftCorner(nbp, nbp);
        uy.noalias() = jy.transpose() * jy;
        wy.noalias() = jy.transpose() * jpc;
        vp.noalias() = jpc.transpose() * jpc;
        // Scatter; an entry outside BlockStructure's pattern (lookup -1) fails the linearisation.
        bool inside = true;
        for (int c = 0; c < blk.num_y; ++c)
          for (int a = 0; a < blk.num_y; ++a) {
            if (ka[c] > ka[a]) continue;
            const Long at = ulut_[static_cast<size_t>(ka[a]) * ny + ka[c]];
            inside = inside && at >= 0;
            uf[inside ? at : 0] += uy(a, c);
          }
        for (int c = 0; c < nbp; ++c) {
          const int q = pq[c];
          double* wcol = ax + wbase_[q] + f * wstride_[q];
          const Long* lut = wlut_.data() + q;
          for (int a = 0; a < blk.num_y; ++a) {
            const Long at = lut[static_cast<size_t>(ka[a]) * np];
            inside = inside && at >= 0;
            wcol[inside ? at : 0] += wy(a, c);
          }
        }
        if (!inside) {
          ts.ok = false;
          return;
        }
        for (int d = 0; d < nbp; ++d)
          for (int c = 0; c < nbp; ++c)
            if (pq[c] >= pq[d]) ts.v(pq[c], pq[d]) += vp(c, d);  // lower triangle
      }
    }
  });
  double sum = 0;
  Eigen::MatrixXd v = Eigen::MatrixXd::Zero(np, np);
  for (int t = 0; t < std::max(1, std::min(num_threads_, nf_)); ++t) {
    const ThreadState& ts = *threads_[t];
    if (!ts.ok) return false;
    sum += ts.cost;
    gradient->tail(np) += ts.gp;
    v += ts.v;
  }
  // Prior and gauge rows, in storage order.
  const Eigen::VectorXd& w = problem_->prior_weight();
  for (int q = 0; q < np; ++q) v(q, q) += w[p_order_[q]] * w[p_order_[q]];
  const Eigen::MatrixXd& g = problem_->shared_rows();
  if (g.rows() > 0) {
    Eigen::MatrixXd gs(g.rows(), np);
    for (int q = 0; q < np; ++q) gs.col(q) = g.col(p_order_[q]);
    v.selfadjointView<Eigen::Lower>().rankUpdate(gs.transpose());
  }
  for (int h = 0; h < np; ++h)
    for (int l = 0; l <= h; ++l)
      ax[vlut_[static_cast<size_t>(h) * np + l]] = v(h, l);
  AddSharedRows(x.tail(np), gradient);
  *cost = 0.5 * (sum + SharedRowsSquaredNorm(x.tail(np)));
  // J^T J's diagonal, as stored.
  const Long yrows = static_cast<Long>(nf_) * ny;
  for (Long s = 0; s < n_; ++s) undamped_diagonal_[s] = ax[diagonal_position_[s]];
  for (Long f = 0; f < nf_; ++f)
    for (int k = 0; k < ny; ++k) (*diagonal)[f * ny + y_order_[k]] = undamped_diagonal_[f * ny + k];
  for (int q = 0; q < np; ++q) (*diagonal)[yrows + p_order_[q]] = undamped_diagonal_[yrows + q];
  return true;
}

bool SparseNormalCholeskyProblem::LinearizeJacobian(const Eigen::VectorXd& x, double* cost,
                                                    Eigen::VectorXd* gradient,
                                                    Eigen::VectorXd* diagonal, bool* mismatch) {
  *mismatch = false;
  gradient->setZero(n_);
  diagonal->setZero(n_);
  if (!problem_->SetShared(x.tail(np_))) return false;
  double* ax = static_cast<double*>(impl_->jt->x);
  const int ny = ny_;
  ParallelChunks(nf_, num_threads_, [&](int t, int b, int e) {
    ThreadState& ts = *threads_[t];
    ts.cost = 0;
    ts.ok = true;
    ts.mismatch = false;
    ts.gp.setZero();
    ts.dp.setZero();
    for (int f = b; f < e; ++f) {
      if (!ts.evaluator->Evaluate(f, x.data() + static_cast<size_t>(f) * ny, true)) {
        ts.ok = false;
        return;
      }
      const Long kb = frame_kind_begin_[f];
      if (ts.evaluator->num_blocks() != frame_kind_begin_[f + 1] - kb) {
        ts.mismatch = true;
        return;
      }
      double* gy = gradient->data() + static_cast<size_t>(f) * ny;
      double* dy = diagonal->data() + static_cast<size_t>(f) * ny;
      double* out = ax + frame_entry_begin_[f];
      for (int k = 0; k < ts.evaluator->num_blocks(); ++k) {
        const ResidualBlock& blk = ts.evaluator->block(k);
        const BlockKind& kind = kinds_[frame_kinds_[kb + k]];
        if (!kind.Matches(blk)) {
          ts.mismatch = true;
          return;
        }
        const int entries = static_cast<int>(kind.entry_row.size());
        for (int r = 0; r < blk.rows; ++r) {
          const double res = blk.residual[r];
          ts.cost += res * res;
          std::fill(out, out + entries, 0.0);
          for (int a = 0; a < blk.num_y; ++a) {
            const double j = blk.jy[a * kMaxBlockRows + r];
            out[kind.y_dest[a]] += j;
            gy[blk.y_index[a]] += j * res;
            dy[blk.y_index[a]] += j * j;
          }
          for (int c = 0; c < blk.num_p; ++c) {
            const int p = blk.p_index[c];
            if (p < 0) continue;
            const double j = blk.jp[c * kMaxBlockRows + r];
            out[kind.p_dest[c]] += j;
            ts.gp[p] += j * res;
            ts.dp[p] += j * j;
          }
          out += entries;
        }
      }
    }
  });
  double sum = 0;
  for (int t = 0; t < std::max(1, std::min(num_threads_, nf_)); ++t) {
    const ThreadState& ts = *threads_[t];
    if (ts.mismatch) *mismatch = true;
    if (!ts.ok) return false;
    sum += ts.cost;
    gradient->tail(np_) += ts.gp;
    diagonal->tail(np_) += ts.dp;
  }
  if (*mismatch) return false;
  // Duplicate y indices within a block would make diag(J^T J) differ from the sum of squares;
  // BlockKind merges them in J^T, and the diagonal below is only LM's damping scale.
  const Eigen::VectorXd& w = problem_->prior_weight();
  diagonal->tail(np_) += w.cwiseProduct(w);
  const Eigen::MatrixXd& g = problem_->shared_rows();
  if (g.rows() > 0) diagonal->tail(np_) += g.colwise().squaredNorm().transpose();
  AddSharedRows(x.tail(np_), gradient);
  *cost = 0.5 * (sum + SharedRowsSquaredNorm(x.tail(np_)));
  return true;
}

bool SparseNormalCholeskyProblem::SolveDamped(const Eigen::VectorXd& damping, Eigen::VectorXd* dx) {
  if (!error_.empty() || !impl_->l || gradient_.size() != n_ || damping.size() != n_) return false;
  cholmod_common* c = &impl_->c;
  const Long yrows = static_cast<Long>(nf_) * ny_;
  // Original index of storage position s.
  auto original = [&](Long s) {
    return s < yrows ? (s / ny_) * ny_ + y_order_[s % ny_] : yrows + p_order_[s - yrows];
  };
  cholmod_sparse* matrix = nullptr;
  if (options_.assembly == Assembly::kJacobian) {
    matrix = impl_->jt.get();
    const Long* ap = static_cast<const Long*>(matrix->p);
    double* ax = static_cast<double*>(matrix->x);
    for (Long s = 0; s < n_; ++s) {
      const double d = damping[original(s)];
      if (!(d >= 0)) return false;
      ax[ap[damping_column_ + s]] = std::sqrt(d);
    }
  } else {
    matrix = impl_->a.get();
    double* ax = static_cast<double*>(matrix->x);
    for (Long s = 0; s < n_; ++s)
      ax[diagonal_position_[s]] = undamped_diagonal_[s] + damping[original(s)];
  }
  KernelThreads kernel_threads(options_.blas_threads > 0 ? options_.blas_threads : num_threads_);
  auto t = Clock::now();
  double beta[2] = {0.0, 0.0};
  const int factored = cholmod_l_factorize_p(matrix, beta, nullptr, 0, impl_->l.get(), c);
  stats_.factorize_seconds += Since(t);
  ++stats_.factorizations;
  if (!factored || c->status != CHOLMOD_OK || impl_->l->minor < impl_->l->n) return false;
  double* bx = static_cast<double*>(impl_->b->x);
  for (Long s = 0; s < n_; ++s) bx[s] = -gradient_[original(s)];
  t = Clock::now();
  DensePtr solution(cholmod_l_solve(CHOLMOD_A, impl_->l.get(), impl_->b.get(), c), DenseFree{c});
  stats_.solve_seconds += Since(t);
  if (!solution) return false;
  const double* sx = static_cast<const double*>(solution->x);
  dx->resize(n_);
  for (Long s = 0; s < n_; ++s) (*dx)[original(s)] = sx[s];
  return dx->allFinite();
}

}  // namespace mocap::solver
