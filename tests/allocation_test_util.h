// No heap allocation on a real-time path: every call of malloc and of the global operator new is
// counted while counting is on. Eigen's own check (EIGEN_RUNTIME_NO_MALLOC, set for the whole
// build) is switched on too, but it is an eigen_assert, which a Release build (NDEBUG) compiles
// out; Eigen allocates with malloc, so the malloc count is what catches a matrix that allocates.
// malloc is interposed (glibc: the executable's definition wins, also for the calls from the
// shared libraries) and forwards to glibc's __libc_malloc, so free, realloc and the rest stay
// glibc's and agree with it.
//
// This header REPLACES malloc and the global operator new and delete: include it in exactly one
// translation unit of a test executable (each tests/test_*.cpp is its own executable).
#pragma once
#include <Eigen/Core>
#include <atomic>
#include <cstdlib>
#include <new>

namespace mocap::testing {

inline std::atomic<bool> g_count_allocations{false};
inline std::atomic<long> g_allocations{0};

// Between the two, operator new is counted and an Eigen heap allocation asserts.
inline void BeginNoAllocation() {
  g_count_allocations = true;
  Eigen::internal::set_is_malloc_allowed(false);
}
inline void EndNoAllocation() {
  Eigen::internal::set_is_malloc_allowed(true);
  g_count_allocations = false;
}

}  // namespace mocap::testing

extern "C" void* __libc_malloc(std::size_t n);
extern "C" void* malloc(std::size_t n) {
  if (mocap::testing::g_count_allocations.load(std::memory_order_relaxed))
    mocap::testing::g_allocations.fetch_add(1);
  return __libc_malloc(n);
}

void* operator new(std::size_t n) {
  if (mocap::testing::g_count_allocations.load(std::memory_order_relaxed))
    mocap::testing::g_allocations.fetch_add(1);
  if (void* p = std::malloc(n ? n : 1)) return p;
  throw std::bad_alloc();
}
void* operator new[](std::size_t n) {
  if (mocap::testing::g_count_allocations.load(std::memory_order_relaxed))
    mocap::testing::g_allocations.fetch_add(1);
  if (void* p = std::malloc(n ? n : 1)) return p;
  throw std::bad_alloc();
}
void operator delete(void* p) noexcept { std::free(p); }
void operator delete[](void* p) noexcept { std::free(p); }
void operator delete(void* p, std::size_t) noexcept { std::free(p); }
void operator delete[](void* p, std::size_t) noexcept { std::free(p); }
