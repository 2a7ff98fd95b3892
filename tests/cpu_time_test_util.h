// CPU time, for the few tests that bound how much work something takes. CI runs the tests two
// at a time beside a sanitizer build on 2 cores, the batch tests at nice 10 (tests/CMakeLists.txt):
// a wall-clock bound there measures the neighbours, CPU time measures the code.
#pragma once

#include <time.h>

namespace mocap::testutil {

// The calling thread's CPU time in milliseconds.
inline double ThreadCpuMs() {
  timespec ts{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return ts.tv_sec * 1e3 + ts.tv_nsec / 1e6;
}

// The whole process's CPU time (every thread's) in seconds.
inline double ProcessCpuSeconds() {
  timespec ts{};
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return ts.tv_sec + ts.tv_nsec / 1e9;
}

}  // namespace mocap::testutil
