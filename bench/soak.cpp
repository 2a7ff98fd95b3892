// soak: the real mocapd on the simulated rig for hours, as a lab runs it, sampling what would
// show a leak or a stage falling behind (issue 17, "Load"). Not a test: the soak is two
// hours; the shortened runs on the shared machine are in BENCHMARKS.md with their flags.
//
// What runs: mocapd on a simulated rig of --cameras Aravis fake cameras at 200 Hz (the renderer
// drawing them runs inside the daemon), the rig calibrated through the socket, a subject created
// and selected, every movement of the protocol recorded once (what a session does before its
// first fit); then for --duration minutes:
//   - --subscribers clients subscribed to the live stream, each to other streams (markers;
//     points; pose; all four), reading as fast as they can;
//   - the operator records a movement every --record-every minutes (the protocol's movements in
//     turn) and fits the subject's model every --fit-every minutes, applying the result;
//   - every --sample seconds a row: the daemon's RSS, open file descriptors and threads (from
//     /proc), its heap in use and free (`status` memory: a leak grows the first, the allocator
//     keeping freed memory only RSS), its queues (`status` queues: the largest depth seen by a poll each second in the
//     interval, and the high-water mark since start), the end-to-end latency p50/p99 seen by the
//     first subscriber in the interval (last image of a set handed over -> frame read from the
//     socket, CLOCK_MONOTONIC), and the frame sets the daemon dropped so far (sets.dropped,
//     tracker.loop_dropped, tracker.recorder_dropped), the sets no camera delivered
//     (sets.undelivered: ticks the fake cameras, threads of the daemon's process, skipped while
//     the host did not run them) and the cameras' buffer underruns, the frames the subscribers
//     missed.
// At the end: the slope of RSS (least squares over the rows after the first, and over those after
// the first fit, whose working set may stay with the process as a step), the range of the
// descriptors, the latency p99 range, the daemon's memory before and after each fit, and the
// totals; --json writes every row.
//
//   soak [--duration MIN] [--sample S] [--record-every MIN] [--fit-every MIN] [--cameras N]
//        [--subscribers N] [--json PATH] [--mocapd PATH]
// (--mocapd: run that executable instead of this build's; the environment, e.g. MALLOC_ARENA_MAX,
// is mocapd's too)
#include <dirent.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <iterator>
#include <memory>
#include <mutex>
#include <set>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <nlohmann/json.hpp>

#include "drivers/frame.h"
#include "tests/daemon_test_util.h"

namespace {

using mocap::daemon::ControlClient;
using mocap::daemon::ControlReply;
using nlohmann::json;
using Clock = std::chrono::steady_clock;

struct Args {
  double duration_min = 120, sample_s = 60, record_every_min = 5, fit_every_min = 20;
  int cameras = 8, subscribers = 4;
  std::string json_path;
  std::string mocapd = MOCAPD_PATH;  // another build's, to compare (e.g. its memory after fits)
};

double Pct(std::vector<double> v, double p) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  return v[std::min(v.size() - 1, static_cast<std::size_t>(p / 100.0 * v.size()))];
}

long ProcStatusKb(pid_t pid, const std::string& key) {
  std::ifstream f("/proc/" + std::to_string(pid) + "/status");
  for (std::string line; std::getline(f, line);)
    if (line.rfind(key + ":", 0) == 0) return std::atol(line.c_str() + key.size() + 1);
  return -1;
}

// The nice value of `pid` (field 19 of /proc/PID/stat, after the parenthesised command name).
int ProcNice(pid_t pid) {
  std::ifstream f("/proc/" + std::to_string(pid) + "/stat");
  std::string stat((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  const std::size_t close = stat.rfind(')');
  if (close == std::string::npos) return 0;
  std::istringstream fields(stat.substr(close + 2));
  std::string field;
  for (int k = 3; k <= 19 && fields >> field; ++k) {
  }
  return std::atoi(field.c_str());
}

int CountEntries(const std::string& dir) {
  DIR* d = opendir(dir.c_str());
  if (!d) return -1;
  int n = 0;
  while (dirent* e = readdir(d)) n += e->d_name[0] != '.';
  closedir(d);
  return n;
}

// What each open descriptor of `pid` refers to (a file, socket:[inode], anon_inode:[eventfd], ...).
std::multiset<std::string> FdTargets(pid_t pid) {
  std::multiset<std::string> out;
  const std::string dir = "/proc/" + std::to_string(pid) + "/fd";
  DIR* d = opendir(dir.c_str());
  if (!d) return out;
  while (dirent* e = readdir(d)) {
    if (e->d_name[0] == '.') continue;
    char target[512];
    const ssize_t n = readlink((dir + "/" + e->d_name).c_str(), target, sizeof target - 1);
    if (n <= 0) continue;
    std::string t(target, static_cast<std::size_t>(n));
    // Sockets and pipes differ by inode from one connection to the next: the kind is what counts.
    if (auto bracket = t.find(":["); bracket != std::string::npos) t = t.substr(0, bracket);
    out.insert(t);
  }
  closedir(d);
  return out;
}

double Minutes(Clock::time_point since) {
  return std::chrono::duration<double>(Clock::now() - since).count() / 60.0;
}

// One subscriber: reads every event, counts frames, the frames missing from the sequence and the
// losses the daemon told; the first one keeps the interval's latencies.
struct Subscriber {
  std::unique_ptr<ControlClient> client;
  json streams;
  std::thread thread;
  std::atomic<std::uint64_t> frames{0}, missing{0}, told_dropped{0};
  std::string error;
  std::mutex mutex;
  std::vector<double> latency_ms;  // since the last Take
  bool keep_latency = false;

  void Run(const std::atomic<bool>& done) {
    ControlReply r;
    if (!client->Call("subscribe", {{"streams", streams}}, &r).ok() || !r.ok()) {
      error = "subscribe: " + r.error_code + " " + r.error_message;
      return;
    }
    std::uint64_t last = 0;
    while (!done) {
      json ev;
      bool got = false;
      if (mocap::Status s = client->NextEvent(&ev, 1000, &got); !s) {
        error = s.message();
        return;
      }
      const std::uint64_t now = mocap::drivers::MonotonicNs();
      if (!got) continue;
      const std::string kind = ev.value("event", "");
      if (kind == "dropped") told_dropped += ev["count"].get<std::uint64_t>();
      if (kind != "frame") continue;
      const std::uint64_t f = ev["frame"];
      if (frames > 0 && f > last + 1) missing += f - last - 1;
      last = f;
      ++frames;
      if (keep_latency && ev.contains("host_last_ns")) {
        std::lock_guard<std::mutex> lock(mutex);
        latency_ms.push_back((static_cast<double>(now) - ev["host_last_ns"].get<double>()) * 1e-6);
      }
    }
  }
  std::vector<double> TakeLatencies() {
    std::lock_guard<std::mutex> lock(mutex);
    std::vector<double> out;
    out.swap(latency_ms);
    return out;
  }
};

bool Call(ControlClient* c, const std::string& method, const json& params, json* result,
          std::string* error = nullptr) {
  ControlReply r;
  const mocap::Status s = c->Call(method, params, &r);
  if (!s.ok() || !r.ok()) {
    const std::string e = method + ": " + (s.ok() ? r.error_code + " " + r.error_message : s.message());
    if (error) *error = e;
    else std::fprintf(stderr, "soak: %s\n", e.c_str());
    return false;
  }
  if (result) *result = r.result;
  return true;
}

// The daemon's frame-set losses so far: the sync's, the loop queue's, the recorder queue's.
std::uint64_t DaemonDropped(const json& status, std::uint64_t* sets, std::uint64_t* loop,
                            std::uint64_t* recorder) {
  *sets = status["sets"]["dropped"];  // undelivered sets are not the daemon's (UndeliveredSets)
  *loop = status["tracker"]["loop_dropped"];
  *recorder = status["tracker"]["recorder_dropped"];
  return *sets + *loop + *recorder;
}

// Frame sets no camera delivered (`sets.undelivered`: the fakes, threads of the daemon's process,
// skip the ticks the host did not schedule them for) and the cameras' buffer underruns (frames
// lost in the driver for want of a buffer the daemon had not returned: the daemon's, if any).
void UndeliveredSets(const json& status, std::uint64_t* undelivered, std::uint64_t* underruns) {
  *undelivered = status["sets"].value("undelivered", std::uint64_t{0});
  *underruns = 0;
  for (const json& c : status["cameras"]) *underruns += c.value("dropped", std::uint64_t{0});
}

// The daemon's memory from `status` (daemon/process_memory.h), in MB: RSS, heap in use, heap
// free (kept by malloc). RSS alone cannot tell a leak from the allocator keeping a fit's memory.
struct MemoryMb {
  double rss = 0, heap_in_use = 0, heap_free = 0;
};
MemoryMb DaemonMemory(const json& status) {
  const json& m = status["memory"];
  return {m["rss_bytes"].get<double>() / 1048576.0, m["heap_in_use_bytes"].get<double>() / 1048576.0,
          m["heap_free_bytes"].get<double>() / 1048576.0};
}

}  // namespace

int main(int argc, char** argv) {
  Args a;
  for (int i = 1; i < argc; ++i) {
    const std::string k = argv[i];
    const bool v = i + 1 < argc;
    if (k == "--duration" && v) a.duration_min = std::stod(argv[++i]);
    else if (k == "--sample" && v) a.sample_s = std::stod(argv[++i]);
    else if (k == "--record-every" && v) a.record_every_min = std::stod(argv[++i]);
    else if (k == "--fit-every" && v) a.fit_every_min = std::stod(argv[++i]);
    else if (k == "--cameras" && v) a.cameras = std::stoi(argv[++i]);
    else if (k == "--subscribers" && v) a.subscribers = std::stoi(argv[++i]);
    else if (k == "--json" && v) a.json_path = argv[++i];
    else if (k == "--mocapd" && v) a.mocapd = argv[++i];
    else {
      std::fprintf(stderr, "usage: soak [--duration MIN] [--sample S] [--record-every MIN] "
                           "[--fit-every MIN] [--cameras N] [--subscribers N] [--json PATH] "
                           "[--mocapd PATH]\n");
      return 2;
    }
  }
  const std::string dir = mocap::testing::MakeTempDir("mocapd-soak");
  // The fit runs inside the daemon beside the live pipeline: on the 2-core capture PC its
  // default (threads = 0, every core) would take both cores from the pipeline for the whole fit;
  // one worker leaves a core to the cameras and the tracker (a lab's mocapd.toml does the same).
  mocap::testing::DaemonProcess d(dir, mocap::testing::SimulatedRigToml(a.cameras, 1,
                                                                        "[fit]\nthreads = 1\n"),
                                  a.mocapd);
  std::unique_ptr<ControlClient> op, poller;
  if (mocap::Status s = mocap::testing::StartCalibratedSession(&d, &op, "soak", "soak", 3600 * 1000);
      !s || !(s = d.Connect(&poller)).ok()) {
    std::fprintf(stderr, "soak: %s\n", s.message().c_str());
    return 1;
  }
  json protocol;
  if (!Call(op.get(), "protocol.show", json::object(), &protocol)) return 1;
  const json& movements = protocol["movements"];
  // The session's first pass: every movement once (at half its duration), so that a fit has
  // data from the first one on.
  auto record = [&](std::size_t k, std::string* outcome) {
    const std::string m = movements[k % movements.size()]["name"];
    json r;
    std::string error;
    const auto t0 = Clock::now();
    const bool ok = Call(op.get(), "record.start", {{"movement", m}, {"sim_duration_scale", 0.5}},
                         &r, &error);
    char buf[256];
    std::snprintf(buf, sizeof buf, "record %s: %s (%.1f s)", m.c_str(),
                  ok ? ("recording " + std::to_string(r.value("recording", 0)) + ", " +
                        std::to_string(r.value("frames", 0)) + " frames")
                           .c_str()
                     : error.c_str(),
                  std::chrono::duration<double>(Clock::now() - t0).count());
    *outcome = buf;
    return ok;
  };
  for (std::size_t k = 0; k < movements.size(); ++k) {
    std::string outcome;
    record(k, &outcome);
    std::fprintf(stderr, "soak: %s\n", outcome.c_str());
  }

  std::atomic<bool> done{false};
  std::vector<std::unique_ptr<Subscriber>> subs;
  const std::vector<json> stream_sets = {{"markers"}, {"points"}, {"pose"},
                                         {"markers", "points", "pose", "status"}};
  for (int i = 0; i < a.subscribers; ++i) {
    auto s = std::make_unique<Subscriber>();
    if (!d.Connect(&s->client).ok()) return 1;
    s->streams = stream_sets[i % stream_sets.size()];
    s->keep_latency = i == 0;
    subs.push_back(std::move(s));
  }
  for (auto& s : subs) s->thread = std::thread([&s, &done] { s->Run(done); });

  json status0;
  if (!Call(poller.get(), "status", json::object(), &status0)) return 1;
  std::uint64_t sets0, loop0, rec0;
  DaemonDropped(status0, &sets0, &loop0, &rec0);
  std::uint64_t undelivered0, underruns0;
  UndeliveredSets(status0, &undelivered0, &underruns0);

  // The operator: a recording every record_every, a fit (then model.apply) every fit_every.
  const std::multiset<std::string> fds0 = FdTargets(d.pid());
  const auto start = Clock::now();
  const auto end = start + std::chrono::duration<double>(a.duration_min * 60);
  std::mutex events_mutex;
  json events = json::array();
  json fits = json::array();  // the daemon's memory before and after each fit
  std::thread operator_thread([&] {
    auto next_record = start + std::chrono::duration<double>(a.record_every_min * 60);
    auto next_fit = start + std::chrono::duration<double>(a.fit_every_min * 60);
    std::size_t k = 0;
    while (!done) {
      const auto now = Clock::now();
      std::string outcome;
      if (now >= next_fit) {
        next_fit += std::chrono::duration<double>(a.fit_every_min * 60);
        json r, st;
        std::string error;
        const MemoryMb before =
            Call(op.get(), "status", json::object(), &st) ? DaemonMemory(st) : MemoryMb();
        const auto t0 = Clock::now();
        const bool ok = Call(op.get(), "fit.start", json::object(), &r, &error);
        const double fit_s = std::chrono::duration<double>(Clock::now() - t0).count();
        json applied;
        const bool apply_ok = ok && Call(op.get(), "model.apply", json::object(), &applied, &error);
        char buf[256];
        std::snprintf(buf, sizeof buf, "fit: %s in %.1f s%s", ok ? ("model version " +
                      std::to_string(r.value("model_version", 0))).c_str() : error.c_str(), fit_s,
                      apply_ok ? (", applied from frame " +
                                  std::to_string(applied.value("from_frame", 0ull))).c_str()
                               : "");
        outcome = buf;
        // The memory once the fit is over and applied (status reads it at most once a second).
        std::this_thread::sleep_for(std::chrono::milliseconds(1500));
        const MemoryMb after =
            Call(op.get(), "status", json::object(), &st) ? DaemonMemory(st) : MemoryMb();
        std::lock_guard<std::mutex> lock(events_mutex);
        fits.push_back({{"minute", Minutes(start)}, {"seconds", fit_s},
                        {"rss_mb_before", before.rss}, {"rss_mb_after", after.rss},
                        {"heap_in_use_mb_before", before.heap_in_use},
                        {"heap_in_use_mb_after", after.heap_in_use},
                        {"heap_free_mb_after", after.heap_free}});
      } else if (now >= next_record) {
        next_record += std::chrono::duration<double>(a.record_every_min * 60);
        record(k++, &outcome);
      } else {
        std::this_thread::sleep_for(std::chrono::milliseconds(200));
        continue;
      }
      std::lock_guard<std::mutex> lock(events_mutex);
      events.push_back({{"minute", Minutes(start)}, {"what", outcome}});
      std::fprintf(stderr, "soak: %5.1f min: %s\n", Minutes(start), outcome.c_str());
    }
  });

  std::printf("mocapd soak: %d simulated cameras x 200 Hz, %d subscribers, a recording every "
              "%g min, a fit every %g min ([fit] threads = 1), %g min, a row every %g s, "
              "mocapd at nice %d, %ld cores\n",
              a.cameras, a.subscribers, a.record_every_min, a.fit_every_min, a.duration_min,
              a.sample_s, ProcNice(d.pid()), sysconf(_SC_NPROCESSORS_ONLN));
  std::printf("| min | RSS MB | heap in use / free MB | fds | threads | queue depth max in the interval (high-water since start): frames / detections / points / loop / recorder | latency p50 / p99 ms | daemon dropped: sets / loop / recorder | no camera delivered: sets / buffer underruns | subscribers: frames missing / told dropped | load |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|---|---|\n");
  std::fflush(stdout);
  json rows = json::array();
  const std::vector<std::string> queues = {"frames", "detections", "points", "loop", "recorder"};
  std::vector<std::size_t> window_max(queues.size(), 0);
  auto next_sample = start + std::chrono::duration<double>(a.sample_s);
  bool failed = false;
  while (Clock::now() < end && !failed) {
    std::this_thread::sleep_for(std::chrono::seconds(1));
    json st;
    if (!d.running() || !Call(poller.get(), "status", json::object(), &st)) {
      std::fprintf(stderr, "soak: the daemon stopped answering; log:\n%s\n", d.Log().c_str());
      failed = true;
      break;
    }
    for (std::size_t q = 0; q < queues.size(); ++q)
      window_max[q] = std::max(window_max[q], st["queues"][queues[q]]["depth"].get<std::size_t>());
    if (Clock::now() < next_sample) continue;
    next_sample += std::chrono::duration<double>(a.sample_s);
    json row;
    row["minute"] = Minutes(start);
    row["rss_mb"] = ProcStatusKb(d.pid(), "VmRSS") / 1024.0;
    const MemoryMb memory = DaemonMemory(st);
    row["heap_in_use_mb"] = memory.heap_in_use;
    row["heap_free_mb"] = memory.heap_free;
    row["fds"] = CountEntries("/proc/" + std::to_string(d.pid()) + "/fd");
    row["threads"] = CountEntries("/proc/" + std::to_string(d.pid()) + "/task");
    std::string qtext, qhigh;
    for (std::size_t q = 0; q < queues.size(); ++q) {
      const std::size_t high = st["queues"][queues[q]]["max"];
      row["queue_depth_max"][queues[q]] = window_max[q];
      row["queue_high_water"][queues[q]] = high;
      qtext += (q ? " / " : "") + std::to_string(window_max[q]);
      qhigh += (q ? " / " : "") + std::to_string(high);
      window_max[q] = 0;
    }
    const std::vector<double> lat = subs.empty() ? std::vector<double>{} : subs[0]->TakeLatencies();
    row["latency_ms"] = {{"p50", Pct(lat, 50)}, {"p99", Pct(lat, 99)}, {"samples", lat.size()}};
    std::uint64_t sets, loop, rec;
    DaemonDropped(st, &sets, &loop, &rec);
    row["daemon_dropped"] = {{"sets", sets - sets0}, {"loop", loop - loop0}, {"recorder", rec - rec0}};
    std::uint64_t undelivered, underruns;
    UndeliveredSets(st, &undelivered, &underruns);
    row["cameras_undelivered"] = {{"sets", undelivered - undelivered0}, {"underruns", underruns - underruns0}};
    std::uint64_t missing = 0, told = 0;
    for (auto& s : subs) missing += s->missing, told += s->told_dropped;
    row["subscribers"] = {{"missing", missing}, {"told_dropped", told}};
    double load = 0;
    std::ifstream("/proc/loadavg") >> load;
    row["load"] = load;
    std::printf("| %.1f | %.1f | %.1f / %.1f | %d | %d | %s (%s) | %.2f / %.2f | %llu / %llu / %llu | %llu / %llu | %llu / %llu | %.1f |\n",
                row["minute"].get<double>(), row["rss_mb"].get<double>(), memory.heap_in_use,
                memory.heap_free, row["fds"].get<int>(),
                row["threads"].get<int>(), qtext.c_str(), qhigh.c_str(), Pct(lat, 50),
                Pct(lat, 99), static_cast<unsigned long long>(sets - sets0),
                static_cast<unsigned long long>(loop - loop0),
                static_cast<unsigned long long>(rec - rec0),
                static_cast<unsigned long long>(undelivered - undelivered0),
                static_cast<unsigned long long>(underruns - underruns0),
                static_cast<unsigned long long>(missing), static_cast<unsigned long long>(told),
                load);
    std::fflush(stdout);
    rows.push_back(row);
  }
  // Descriptors open at the end that were not at minute 0 (and the reverse), by what they are.
  const std::multiset<std::string> fds1 = FdTargets(d.pid());
  std::vector<std::string> fds_added, fds_gone;
  std::set_difference(fds1.begin(), fds1.end(), fds0.begin(), fds0.end(),
                      std::back_inserter(fds_added));
  std::set_difference(fds0.begin(), fds0.end(), fds1.begin(), fds1.end(),
                      std::back_inserter(fds_gone));
  done = true;
  {  // ends a running recording (the operator's connection is the operator thread's)
    std::unique_ptr<ControlClient> stopper;
    ControlReply rr;
    if (d.Connect(&stopper).ok()) stopper->Call("record.stop", json::object(), &rr);
  }
  operator_thread.join();
  for (auto& s : subs) s->thread.join();
  for (std::size_t i = 0; i < subs.size(); ++i)
    if (!subs[i]->error.empty())
      std::fprintf(stderr, "soak: subscriber %zu: %s\n", i, subs[i]->error.c_str()), failed = true;
  const int exit_status = d.Stop();

  // RSS slope (MB/hour), least squares over the rows after `from_min`: all but the first (the
  // first minute still warms up), and those after the first fit (the fit's working set, hundreds
  // of MB, may stay with the process: a step, not a leak; a leak keeps the slope after it).
  auto rss_slope = [&rows](double from_min) {
    double n = 0, sx = 0, sy = 0, sxx = 0, sxy = 0;
    for (const json& r : rows) {
      if (r["minute"].get<double>() <= from_min) continue;
      const double x = r["minute"].get<double>() / 60.0, y = r["rss_mb"];
      n += 1, sx += x, sy += y, sxx += x * x, sxy += x * y;
    }
    return n >= 3 ? (n * sxy - sx * sy) / (n * sxx - sx * sx) : 0.0;
  };
  const double slope_mb_per_h = rows.empty() ? 0.0 : rss_slope(rows[0]["minute"].get<double>());
  double first_fit_min = -1;
  for (const json& e : events)
    if (first_fit_min < 0 && e["what"].get<std::string>().rfind("fit", 0) == 0)
      first_fit_min = e["minute"];
  const double slope_after_fit = first_fit_min >= 0 ? rss_slope(first_fit_min) : 0.0;
  int fd_min = 1 << 30, fd_max = 0;
  double p99_min = 1e300, p99_max = 0, rss_min = 1e300, rss_max = 0;
  for (const json& r : rows) {
    fd_min = std::min(fd_min, r["fds"].get<int>());
    fd_max = std::max(fd_max, r["fds"].get<int>());
    p99_min = std::min(p99_min, r["latency_ms"]["p99"].get<double>());
    p99_max = std::max(p99_max, r["latency_ms"]["p99"].get<double>());
    rss_min = std::min(rss_min, r["rss_mb"].get<double>());
    rss_max = std::max(rss_max, r["rss_mb"].get<double>());
  }
  std::printf("\nRSS %.1f-%.1f MB, slope %+.2f MB/hour (rows 2-%zu); fds %d-%d; latency p99 "
              "%.2f-%.2f ms; daemon exit status %d\n",
              rss_min, rss_max, slope_mb_per_h, rows.size(), fd_min, fd_max, p99_min, p99_max,
              exit_status);
  std::printf("descriptors opened since minute 0 and still open:");
  for (const std::string& f : fds_added) std::printf(" %s", f.c_str());
  std::printf("%s; closed:", fds_added.empty() ? " none" : "");
  for (const std::string& f : fds_gone) std::printf(" %s", f.c_str());
  std::printf("%s\n", fds_gone.empty() ? " none" : "");
  if (first_fit_min >= 0)
    std::printf("RSS slope after the first fit (%.1f min): %+.2f MB/hour\n", first_fit_min,
                slope_after_fit);
  for (std::size_t i = 0; i < subs.size(); ++i)
    std::printf("subscriber %zu (%s): %llu frames, %llu missing, %llu told dropped\n", i,
                subs[i]->streams.dump().c_str(),
                static_cast<unsigned long long>(subs[i]->frames.load()),
                static_cast<unsigned long long>(subs[i]->missing.load()),
                static_cast<unsigned long long>(subs[i]->told_dropped.load()));
  for (const json& e : events)
    std::printf("%5.1f min: %s\n", e["minute"].get<double>(), e["what"].get<std::string>().c_str());
  if (!fits.empty()) {
    std::printf("\n| fit | at min | seconds | RSS MB before -> after | heap in use MB before -> after | heap free MB after |\n|---|---|---|---|---|---|\n");
    for (std::size_t i = 0; i < fits.size(); ++i) {
      const json& f = fits[i];
      std::printf("| %zu | %.1f | %.1f | %.1f -> %.1f | %.1f -> %.1f | %.1f |\n", i + 1,
                  f["minute"].get<double>(), f["seconds"].get<double>(),
                  f["rss_mb_before"].get<double>(), f["rss_mb_after"].get<double>(),
                  f["heap_in_use_mb_before"].get<double>(), f["heap_in_use_mb_after"].get<double>(),
                  f["heap_free_mb_after"].get<double>());
    }
  }
  if (!a.json_path.empty()) {
    std::ofstream(a.json_path) << json{{"rows", rows},
                                       {"events", events},
                                       {"fits", fits},
                                       {"rss_slope_mb_per_hour", slope_mb_per_h},
                                       {"rss_slope_after_first_fit_mb_per_hour", slope_after_fit},
                                       {"daemon_exit_status", exit_status}}
                                      .dump(2);
  }
  return failed ? 1 : 0;
}
