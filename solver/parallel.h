// Minimal parallel loops. The fit's frames are independent and of equal cost, so contiguous
// chunks per thread are balanced and keep each thread's data in its own cache (ParallelChunks);
// whole trials are not of equal cost (ParallelQueue).
#pragma once
#include <algorithm>
#include <atomic>
#include <numeric>
#include <thread>
#include <utility>
#include <vector>

namespace mocap::solver {

inline int ResolveThreads(int requested) {
  if (requested > 0) return requested;
  const unsigned hw = std::thread::hardware_concurrency();
  return hw == 0 ? 1 : static_cast<int>(hw);
}

// The threads ParallelChunks uses for n items, and chunk t's [begin, end).
inline int ChunkThreads(int n, int num_threads) { return std::max(1, std::min(num_threads, n)); }
inline std::pair<int, int> ChunkRange(int n, int threads, int t) {
  const int chunk = (n + threads - 1) / threads;
  return {std::min(n, t * chunk), std::min(n, (t + 1) * chunk)};
}

// Calls fn(thread_index, begin, end) on num_threads contiguous chunks of [0, n).
template <typename Fn>
void ParallelChunks(int n, int num_threads, Fn&& fn) {
  num_threads = ChunkThreads(n, num_threads);
  if (num_threads == 1) {
    fn(0, 0, n);
    return;
  }
  std::vector<std::thread> threads;
  threads.reserve(num_threads - 1);
  for (int t = 1; t < num_threads; ++t) {
    // Not a structured binding: clang before 16 cannot capture one.
    const std::pair<int, int> range = ChunkRange(n, num_threads, t);
    threads.emplace_back([&fn, t, range] { fn(t, range.first, range.second); });
  }
  const auto [b0, e0] = ChunkRange(n, num_threads, 0);
  fn(0, b0, e0);
  for (auto& th : threads) th.join();
}

// The sum of v as a pass over ParallelChunks(v.size(), num_threads) forms it -- each chunk's in
// order, then the chunks' in order -- so a sum taken after the pass keeps the pass's bits.
inline double ChunkedSum(const std::vector<double>& v, int num_threads) {
  const int n = static_cast<int>(v.size());
  const int threads = ChunkThreads(n, num_threads);
  double sum = 0;
  for (int t = 0; t < threads; ++t) {
    const auto [b, e] = ChunkRange(n, threads, t);
    double part = 0;
    for (int f = b; f < e; ++f) part += v[f];
    sum += part;
  }
  return sum;
}

// Tasks of unequal cost (a session's trials: 150 to 1,500 frames each), where contiguous chunks
// leave a thread idle while another works through the long ones: fn(thread_index, next) on each
// thread, where next() hands out the task indices in `order` one at a time (-1 when none is left)
// and fn may set up its own workspace before it asks. Longest first (`order`) keeps the last task
// short. Each task's result must not depend on the thread that runs it.
template <typename Fn>
void ParallelQueue(const std::vector<int>& order, int num_threads, Fn&& fn) {
  const int n = static_cast<int>(order.size());
  std::atomic<int> taken{0};
  auto next = [&]() -> int {
    const int k = taken.fetch_add(1, std::memory_order_relaxed);
    return k < n ? order[k] : -1;
  };
  num_threads = std::max(1, std::min(num_threads, n));
  std::vector<std::thread> threads;
  threads.reserve(num_threads - 1);
  for (int t = 1; t < num_threads; ++t) threads.emplace_back([&fn, &next, t] { fn(t, next); });
  fn(0, next);
  for (auto& th : threads) th.join();
}

// The indices 0..n-1 by decreasing size[i] (ties in index order): ParallelQueue's order.
template <typename Size>
std::vector<int> LongestFirst(int n, Size&& size) {
  std::vector<int> order(n);
  std::iota(order.begin(), order.end(), 0);
  std::stable_sort(order.begin(), order.end(), [&](int a, int b) { return size(a) > size(b); });
  return order;
}

}  // namespace mocap::solver
