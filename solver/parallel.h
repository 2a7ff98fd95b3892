// Minimal parallel loops. The fit's frames are independent and of equal cost, so contiguous
// chunks per thread are balanced and keep each thread's data in its own cache (ParallelChunks);
// whole trials are not of equal cost (ParallelQueue).
#pragma once
#include <algorithm>
#include <atomic>
#include <numeric>
#include <thread>
#include <vector>

namespace mocap::solver {

inline int ResolveThreads(int requested) {
  if (requested > 0) return requested;
  const unsigned hw = std::thread::hardware_concurrency();
  return hw == 0 ? 1 : static_cast<int>(hw);
}

// Calls fn(thread_index, begin, end) on num_threads contiguous chunks of [0, n).
template <typename Fn>
void ParallelChunks(int n, int num_threads, Fn&& fn) {
  num_threads = std::max(1, std::min(num_threads, n));
  if (num_threads == 1) {
    fn(0, 0, n);
    return;
  }
  std::vector<std::thread> threads;
  threads.reserve(num_threads - 1);
  const int chunk = (n + num_threads - 1) / num_threads;
  for (int t = 1; t < num_threads; ++t) {
    const int b = std::min(n, t * chunk), e = std::min(n, (t + 1) * chunk);
    threads.emplace_back([&fn, t, b, e] { fn(t, b, e); });
  }
  fn(0, 0, std::min(n, chunk));
  for (auto& th : threads) th.join();
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
