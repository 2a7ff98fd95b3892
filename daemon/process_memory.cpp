#include "daemon/process_memory.h"

#include <malloc.h>

#include <cstdlib>
#include <fstream>
#include <string>

namespace mocap::daemon {

namespace {

Status ReadRss(std::uint64_t* bytes) {
  const char* path = "/proc/self/status";
  std::ifstream f(path);
  if (!f) return Status::Error(std::string(path) + ": cannot open");
  for (std::string line; std::getline(f, line);) {
    if (line.rfind("VmRSS:", 0) != 0) continue;
    *bytes = std::strtoull(line.c_str() + 6, nullptr, 10) * 1024;  // "VmRSS:   12345 kB"
    return Status::Ok();
  }
  return Status::Error(std::string(path) + ": no VmRSS line");
}

}  // namespace

Status ReadProcessMemory(ProcessMemory* out) {
  *out = ProcessMemory();
  MOCAP_RETURN_IF_ERROR(ReadRss(&out->rss_bytes));
  const struct mallinfo2 mi = mallinfo2();
  out->heap_in_use_bytes = mi.uordblks + mi.hblkhd;  // chunks in arenas + mmapped chunks
  out->heap_free_bytes = mi.fordblks;
  return Status::Ok();
}

std::uint64_t ReleaseFreeHeapMemory() {
  std::uint64_t before = 0, after = 0;
  const bool measured = ReadRss(&before).ok();
  malloc_trim(0);
  if (!measured || !ReadRss(&after).ok() || after > before) return 0;
  return before - after;
}

}  // namespace mocap::daemon
