// What mocapd's memory is made of, and giving back what a finished job freed.
//
// RSS alone cannot tell a leak from the allocator keeping freed memory: glibc's malloc gives
// each thread that allocates an arena of its own (up to 8 per core, then threads share them)
// and returns a freed page to the kernel only from the top of a heap, and only once the free
// space there exceeds M_TRIM_THRESHOLD. A fit (daemon.cpp FitStart) runs on a thread of its
// own, allocates hundreds of MB in an arena that the pipeline's long-lived threads may share,
// and frees it when it ends: a page that a live allocation of another thread pins stays, and so
// do the pages below it. The soak (BENCHMARKS.md "Soak") saw RSS flat between fits and a step
// after some fits. So `status` reports the heap in use (allocated and not freed, every arena,
// mallinfo2) beside RSS: a leak grows the first, the allocator's retention only the second.
#pragma once
#include <cstdint>

#include "model/status.h"

namespace mocap::daemon {

struct ProcessMemory {
  std::uint64_t rss_bytes = 0;          // resident (VmRSS of /proc/self/status)
  std::uint64_t heap_in_use_bytes = 0;  // malloc'd and not yet freed, all arenas and mmapped chunks
  std::uint64_t heap_free_bytes = 0;    // freed but kept by malloc in its arenas (resident or not)
};

// This process's memory now. mallinfo2 walks every arena's free lists under its lock: callers
// on a hot path cache it (the daemon reads it at most once a second).
Status ReadProcessMemory(ProcessMemory* out);

// Gives the kernel back the free pages of every arena (malloc_trim(0): glibc >= 2.8 releases
// free pages in the middle of a heap too, with MADV_DONTNEED, not only its top). For after a job
// that allocated and freed much on a thread of its own; it takes each arena's lock in turn, so
// not per frame. Returns how much RSS dropped (0 when it grew meanwhile).
std::uint64_t ReleaseFreeHeapMemory();

}  // namespace mocap::daemon
