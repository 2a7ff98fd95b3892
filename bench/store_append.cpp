// store_append: what recording into the store (daemon/store.h) costs. A recording of the default
// model (its markers and coordinates, plus `markers + 5` unlabelled points a frame) is appended in
// chunks of --chunk-ms (default 80, the recorder's) at the rig's pace (in real time) as the
// recorder does, then read back whole; for each --synchronous setting (full: every commit fsynced,
// the daemon's; normal; both), twice in one process, side by side:
//   auto        SQLite's automatic WAL checkpoint on the recorder's commits (the default options);
//   background  the recorder's Store with wal_autocheckpoint_pages = 0, and a second Store on
//               another thread calling Checkpoint() every --checkpoint-ms (default 5000).
//
//   store_append [--dir DIR] [--seconds S] [--rate HZ] [--checkpoint-ms MS] [--chunk-ms MS]
//                [--synchronous full|normal|both]
//
// Prints, per mode, the AppendFrames time per chunk (p50 / p99 / max), how many took over 5 ms,
// the bytes per frame on disk (database + WAL), and the ReadFrames time. DIR (default
// /tmp/mocap_store_append) is emptied first.
#include <algorithm>
#include <atomic>
#include <cmath>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <string>
#include <thread>
#include <vector>

#include "daemon/store.h"
#include "model/default_model.h"
#include "model/model_io.h"

using mocap::Status;
using mocap::daemon::RecordedFrame;
using mocap::daemon::Store;
using mocap::daemon::StoreOptions;

namespace {

double MillisecondsSince(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
}

struct Result {
  std::vector<double> append_ms;  // sorted
  std::uint64_t bytes = 0;
  std::size_t frames = 0;
  double read_ms = 0;
};

Status Record(const std::string& dir, bool background_checkpoints, int checkpoint_ms,
              bool sync_every_commit, int chunk_ms, double seconds, double rate_hz,
              Result* result) {
  std::filesystem::remove_all(dir);
  StoreOptions options;
  options.sync_every_commit = sync_every_commit;
  if (background_checkpoints) options.wal_autocheckpoint_pages = 0;
  std::unique_ptr<Store> store;
  MOCAP_RETURN_IF_ERROR(Store::Open(dir, &store, options));
  const mocap::Model model = mocap::DefaultFullBodyModel();
  mocap::daemon::SubjectRecord subject;
  MOCAP_RETURN_IF_ERROR(store->CreateSubject("bench", 1.75, "default", "",
                                             mocap::ModelToJsonString(model), "bench", &subject));
  std::vector<std::string> markers, coordinates;
  for (const auto& m : model.markers()) markers.push_back(m.name);
  for (const auto& c : model.coordinates()) coordinates.push_back(c.name);
  std::int64_t id = 0;
  MOCAP_RETURN_IF_ERROR(
      store->BeginRecording(subject.id, "bench", rate_hz, markers, coordinates, 1, "bench", &id));

  std::atomic<bool> stop{false};
  Status checkpointer_status;
  std::thread checkpointer;
  if (background_checkpoints) {
    StoreOptions worker;
    worker.mark_interrupted_recordings = false;
    worker.sync_every_commit = sync_every_commit;
    std::unique_ptr<Store> other;
    MOCAP_RETURN_IF_ERROR(Store::Open(dir, &other, worker));
    checkpointer =
        std::thread([&stop, &checkpointer_status, checkpoint_ms, other = std::move(other)] {
          while (!stop && checkpointer_status.ok()) {
            checkpointer_status = other->Checkpoint();
            std::this_thread::sleep_for(std::chrono::milliseconds(checkpoint_ms));
          }
        });
  }
  const int chunk_frames = std::max(1, static_cast<int>(std::lround(rate_hz * chunk_ms / 1000)));
  const int chunks = static_cast<int>(seconds * rate_hz / chunk_frames);
  Status status;
  std::uint64_t frame = 1;
  const auto start = std::chrono::steady_clock::now();
  for (int c = 0; c < chunks && status.ok(); ++c) {
    // At the rig's pace: one chunk every chunk_ms, as the recorder receives them.
    std::this_thread::sleep_until(start + std::chrono::milliseconds(chunk_ms) * c);
    std::vector<RecordedFrame> frames(chunk_frames);
    for (auto& f : frames) {
      f.frame = frame++;
      f.time_s = f.frame / rate_hz;
      f.points.assign(markers.size() + 5, Eigen::Vector3d(0.1, 0.2, 0.3));
      f.markers = Eigen::Matrix3Xd::Constant(3, static_cast<Eigen::Index>(markers.size()), 0.5);
      f.marker_flags.assign(markers.size(), 0);
      f.coordinates = Eigen::VectorXd::Constant(static_cast<Eigen::Index>(coordinates.size()), 0.1);
    }
    const auto t0 = std::chrono::steady_clock::now();
    status = store->AppendFrames(id, frames);
    result->append_ms.push_back(MillisecondsSince(t0));
  }
  stop = true;
  if (checkpointer.joinable()) checkpointer.join();
  MOCAP_RETURN_IF_ERROR(status);
  MOCAP_RETURN_IF_ERROR(checkpointer_status);
  std::sort(result->append_ms.begin(), result->append_ms.end());
  MOCAP_RETURN_IF_ERROR(store->Usage(&result->bytes));
  std::vector<RecordedFrame> all;
  const auto t0 = std::chrono::steady_clock::now();
  MOCAP_RETURN_IF_ERROR(store->ReadFrames(id, &all));
  result->read_ms = MillisecondsSince(t0);
  result->frames = all.size();
  return Status::Ok();
}

}  // namespace

int main(int argc, char** argv) {
  std::string dir = "/tmp/mocap_store_append";
  double seconds = 60, rate_hz = 200;
  int checkpoint_ms = 5000, chunk_ms = 80;
  std::string synchronous = "full";
  for (int i = 1; i + 1 < argc; i += 2) {
    if (!std::strcmp(argv[i], "--dir")) {
      dir = argv[i + 1];
    } else if (!std::strcmp(argv[i], "--seconds")) {
      seconds = std::atof(argv[i + 1]);
    } else if (!std::strcmp(argv[i], "--checkpoint-ms")) {
      checkpoint_ms = std::atoi(argv[i + 1]);
    } else if (!std::strcmp(argv[i], "--rate")) {
      rate_hz = std::atof(argv[i + 1]);
    } else if (!std::strcmp(argv[i], "--chunk-ms") && std::atoi(argv[i + 1]) > 0) {
      chunk_ms = std::atoi(argv[i + 1]);
    } else if (!std::strcmp(argv[i], "--synchronous") &&
               (!std::strcmp(argv[i + 1], "full") || !std::strcmp(argv[i + 1], "normal") ||
                !std::strcmp(argv[i + 1], "both"))) {
      synchronous = argv[i + 1];
    } else {
      std::fprintf(
          stderr,
          "usage: store_append [--dir DIR] [--seconds S] [--rate HZ] [--checkpoint-ms MS]"
          " [--chunk-ms MS] [--synchronous full|normal|both]\n");
      return 2;
    }
  }
  std::printf("%.0f s at %.0f Hz in %d ms chunks; default model, 43 markers + 48 points a frame\n",
              seconds, rate_hz, chunk_ms);
  std::vector<bool> syncs;
  if (synchronous != "normal") syncs.push_back(true);
  if (synchronous != "full") syncs.push_back(false);
  for (bool sync : syncs)
  for (bool background : {false, true}) {
    Result r;
    if (Status s = Record(dir + (background ? "/background" : "/auto"), background, checkpoint_ms,
                          sync, chunk_ms, seconds, rate_hz, &r);
        !s.ok()) {
      std::fprintf(stderr, "store_append: %s\n", s.message().c_str());
      return 1;
    }
    const auto& ms = r.append_ms;
    const auto slow = std::count_if(ms.begin(), ms.end(), [](double t) { return t > 5; });
    std::printf(
        "%-6s %-10s AppendFrames p50 %.2f ms  p99 %.2f ms  max %.2f ms  (%td of %zu over 5 ms); "
        "%.0f bytes a frame; ReadFrames of %zu frames %.0f ms\n",
        sync ? "FULL" : "NORMAL", background ? "background" : "auto", ms[ms.size() / 2],
        ms[static_cast<std::size_t>(0.99 * (ms.size() - 1))], ms.back(), slow, ms.size(),
        static_cast<double>(r.bytes) / static_cast<double>(r.frames), r.frames, r.read_ms);
  }
  return 0;
}
