// A minimal static-partition parallel loop. The fit's frames are independent and of equal cost,
// so contiguous chunks per thread are balanced and keep each thread's data in its own cache.
#pragma once
#include <algorithm>
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

}  // namespace mocap::solver
