// The daemon tier: the real mocapd executable on a simulated rig (8 Aravis fake cameras drawn by
// the renderer from a virtual subject who does what the operator asks), driven through its
// control socket with the real client, as an operator would drive it with mocapctl.
#include <sys/socket.h>
#include <sys/un.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <fstream>
#include <map>
#include <regex>
#include <set>
#include <string>
#include <chrono>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

#include "daemon/store.h"
#include "formats/c3d.h"
#include "formats/trc.h"
#include "tests/daemon_test_util.h"

namespace mocap {
namespace {

using daemon::ControlClient;
using daemon::ControlReply;
using nlohmann::json;
using testing::DaemonProcess;

#define ASSERT_DAEMON_STARTS(d)            \
  do {                                     \
    const Status started = (d).Start();    \
    ASSERT_TRUE(started.ok()) << started.message(); \
  } while (0)

// Call that must succeed; the reply's result.
json MustCall(ControlClient* c, const std::string& method, const json& params = json::object(),
              const ControlClient::EventHandler& on_event = {}) {
  ControlReply reply;
  Status s = c->Call(method, params, &reply, on_event);
  EXPECT_TRUE(s.ok()) << method << ": " << s.message();
  EXPECT_TRUE(reply.ok()) << method << ": " << reply.error_code << ": " << reply.error_message;
  return reply.result;
}

// Call that must fail with `code`; the message.
std::string MustFail(ControlClient* c, const std::string& method, const json& params,
                     const std::string& code) {
  ControlReply reply;
  Status s = c->Call(method, params, &reply);
  EXPECT_TRUE(s.ok()) << method << ": " << s.message();
  EXPECT_EQ(reply.error_code, code) << method << " " << params.dump() << ": "
                                    << reply.error_message;
  return reply.error_message;
}

bool WaitTracking(ControlClient* c, double seconds) {
  const auto until = std::chrono::steady_clock::now() + std::chrono::duration<double>(seconds);
  while (std::chrono::steady_clock::now() < until) {
    ControlReply r;
    if (!c->Call("status", json::object(), &r) || !r.ok()) return false;
    if (r.result["tracker"]["state"] == "tracking") return true;
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
  }
  return false;
}

// The session: rig calibration, subject, every movement (one under-performed and repeated), fit,
// apply, export, and a restart on the same storage.
TEST(Daemon, WholeSessionOnTheSimulatedRig) {
  const std::string dir = testing::MakeTempDir("mocapd-session");
  ASSERT_FALSE(dir.empty());
  DaemonProcess d(dir, testing::SimulatedRigToml(8, 3));
  ASSERT_DAEMON_STARTS(d);
  std::unique_ptr<ControlClient> c;
  ASSERT_TRUE(d.Connect(&c).ok());
  EXPECT_TRUE(c->hello().may_control);  // root

  // Rig calibration: the virtual operator waves the wand, then lays the L-frame.
  json start = MustCall(c.get(), "rig.calibrate.start", {{"seconds", 12}});
  EXPECT_EQ(start["collecting"], true);
  int collect_events = 0;
  double last_coverage = 0;
  const auto collect_until = std::chrono::steady_clock::now() + std::chrono::seconds(13);
  while (std::chrono::steady_clock::now() < collect_until) {
    json ev;
    bool got = false;
    ASSERT_TRUE(c->NextEvent(&ev, 500, &got).ok());
    if (got && ev.value("job", "") == "rig.calibrate" && ev.contains("coverage_per_camera")) {
      ++collect_events;
      last_coverage = *std::min_element(ev["coverage_per_camera"].begin(),
                                        ev["coverage_per_camera"].end());
    }
  }
  EXPECT_GE(collect_events, 10);
  EXPECT_GT(last_coverage, 0.1) << "every camera saw the wand over a tenth of its 8 x 8 grid";
  int ba_iterations = 0;
  json cal = MustCall(c.get(), "rig.calibrate.finish", json::object(), [&](const json& ev) {
    if (ev.value("phase", "") == "solve") ++ba_iterations;
  });
  EXPECT_GT(ba_iterations, 0);
  // `mocap calibrate --simulate`'s bounds (tests/test_calibration.cpp).
  EXPECT_LE(cal.value("reprojection_rms_px", 1e9), 0.15);
  EXPECT_LE(cal.value("wand_length_error_mm", 1e9), 0.3);
  ASSERT_TRUE(cal.contains("truth")) << cal.dump();
  EXPECT_LT(cal["truth"]["position_error_mm_max"].get<double>(), 1.5);
  EXPECT_LT(cal["truth"]["orientation_error_deg_max"].get<double>(), 0.02);
  json applied = MustCall(c.get(), "rig.calibrate.apply", json::object());
  EXPECT_EQ(applied["version"], cal["version"]);

  // The subject, measured (the virtual subject's height), created and selected.
  json status = MustCall(c.get(), "status");
  const double height = status["rig"]["virtual_subject"]["height_m"].get<double>();
  const int dropped_before_tracking = status["sets"]["dropped"].get<int>();
  EXPECT_GT(height, 1.4);
  MustCall(c.get(), "subject.create", {{"name", "S01"}, {"height_m", height}});
  MustFail(c.get(), "subject.create", {{"name", "S01"}, {"height_m", height}}, "conflict");
  MustCall(c.get(), "subject.select", {{"name", "S01"}});
  ASSERT_TRUE(WaitTracking(c.get(), 15)) << d.LogTail();
  // The tracker's start is its slowest frame (a search among unlabelled points, tens of ms, far
  // over the 5 ms frame period): the frames that arrive meanwhile wait in the point queue, none is
  // dropped, and the stage catches up. (The timings in the status are at most 1 s old.)
  std::this_thread::sleep_for(std::chrono::milliseconds(1100));
  status = MustCall(c.get(), "status");
  std::printf("tracking started: the tracking stage's slowest frame %.1f ms, p99 %.2f ms; at most "
              "%d of %d point frames waited; %d frame sets dropped since the subject was selected\n",
              status["latency_ms"]["track_max"].get<double>(),
              status["latency_ms"]["track_p99"].get<double>(),
              status["queues"]["points"]["max"].get<int>(),
              status["queues"]["points"]["capacity"].get<int>(),
              status["sets"]["dropped"].get<int>() - dropped_before_tracking);
  EXPECT_GT(status["latency_ms"]["track_max"].get<double>(), 0.0);
  // At most half the queue: the start leaves as much again for a slower moment (37 ms on a quiet
  // machine, 120 ms with two other agents' benchmarks running: 7 and 23 of the 256 frames).
  EXPECT_LT(status["queues"]["points"]["max"].get<int>(), status["queues"]["points"]["capacity"].get<int>() / 2);
  EXPECT_EQ(status["sets"]["dropped"].get<int>(), dropped_before_tracking);

  // Every movement of the protocol; squats first under-performed (40 % of the range).
  json protocol = MustCall(c.get(), "protocol.show");
  ASSERT_GT(protocol["movements"].size(), 3u);
  json weak = MustCall(c.get(), "record.start",
                       {{"movement", "squats"}, {"sim_amplitude", 0.4}, {"sim_duration_scale", 0.5}});
  EXPECT_EQ(weak["coverage"]["ok"], false) << weak.dump();
  ASSERT_TRUE(weak["advice"].is_string());
  const std::string advice = weak["advice"];
  EXPECT_NE(advice.find("squats"), std::string::npos) << advice;
  EXPECT_TRUE(advice.find("hip_flexion") != std::string::npos ||
              advice.find("knee_angle") != std::string::npos)
      << advice;
  // A subscriber watches the first recording: what is stored must be what was streamed.
  std::unique_ptr<ControlClient> streamer;
  ASSERT_TRUE(d.Connect(&streamer).ok());
  MustCall(streamer.get(), "subscribe", {{"streams", {"markers"}}});
  std::map<std::uint64_t, json> streamed;
  std::atomic<bool> streaming{true};
  std::thread stream_thread([&] {
    while (streaming) {
      json ev;
      bool got = false;
      if (!streamer->NextEvent(&ev, 100, &got).ok()) break;
      if (got && ev.value("event", "") == "frame") streamed[ev["frame"].get<std::uint64_t>()] = ev["markers"];
    }
  });
  std::int64_t static_recording = 0;
  json static_losses;
  int repeats = 0;
  for (const json& m : protocol["movements"]) {
    const std::string name = m["name"];
    int progress = 0;
    json rec;
    // As the operator is told: a movement whose check fails is repeated (a one-marker hand the
    // tracker on the nominal model took the wrong way round, once in a few sessions).
    for (int attempt = 0; attempt < 3; ++attempt) {
      rec = MustCall(c.get(), "record.start", {{"movement", name}, {"sim_duration_scale", 0.5}},
                     [&](const json& ev) { progress += ev.value("job", "") == "record"; });
      if (rec["coverage"]["ok"] == true) break;
      ++repeats;
      std::printf("%s repeated: %s\n", name.c_str(), rec["advice"].dump().c_str());
    }
    EXPECT_EQ(rec["coverage"]["ok"], true) << name << ": " << rec.dump();
    EXPECT_GT(rec["tracking_fraction"].get<double>(), 0.95) << name;
    EXPECT_GT(progress, 0) << name;
    if (static_recording == 0) {
      static_recording = rec["recording"];
      static_losses = rec["losses"];
      streaming = false;
      stream_thread.join();
    }
  }
  EXPECT_LE(repeats, 2) << "more than a rare repeat: the live labelling is not robust";
  {
    std::unique_ptr<daemon::Store> store;
    daemon::StoreOptions so;
    so.mark_interrupted_recordings = false;
    ASSERT_TRUE(daemon::Store::Open(d.state_dir(), &store, so).ok());
    std::vector<daemon::RecordedFrame> stored;
    ASSERT_TRUE(store->ReadFrames(static_recording, &stored).ok());
    ASSERT_GT(stored.size(), 300u);
    // The daemon loses no frame and hides no loss: every frame missing from the stored sequence
    // is one the reply counts, and a set that no camera exposed (the simulated cameras run in
    // mocapd's process and skip the ticks a loaded host does not schedule them, as cameras on
    // their own clocks would not: CI's 2-core hosts, 28 Nov 2026, 6 frames in one run); none
    // was dropped by the daemon or its recorder.
    std::uint64_t missing = 0;
    for (std::size_t f = 1; f < stored.size(); ++f) {
      ASSERT_GT(stored[f].frame, stored[f - 1].frame) << "recorded frames out of order";
      missing += stored[f].frame - stored[f - 1].frame - 1;
    }
    std::printf("static recording: %zu frames stored, %llu missing; losses %s\n", stored.size(),
                static_cast<unsigned long long>(missing), static_losses.dump().c_str());
    ASSERT_TRUE(static_losses.is_object()) << "the record.start reply has no losses";
    EXPECT_EQ(missing, static_losses["missing_frames"].get<std::uint64_t>())
        << "the reply does not count the frames missing from the recording";
    EXPECT_EQ(static_losses["sets_dropped"], 0) << "the daemon dropped sets while it recorded";
    EXPECT_EQ(static_losses["recorder_dropped"], 0) << "the recorder dropped frames";
    EXPECT_LE(missing, static_losses["sets_not_exposed"].get<std::uint64_t>())
        << "a recorded frame is missing that a camera exposed";
    int compared = 0;
    for (const auto& fr : stored) {
      auto it = streamed.find(fr.frame);
      ASSERT_NE(it, streamed.end()) << "frame " << fr.frame << " was recorded, never streamed";
      ASSERT_EQ(it->second.size(), static_cast<std::size_t>(fr.markers.cols()));
      for (Eigen::Index m = 0; m < fr.markers.cols(); ++m) {
        const json& sm = it->second[m];
        EXPECT_EQ(sm["occluded"].get<bool>(), !fr.markers.col(m).allFinite());
        if (!fr.markers.col(m).allFinite()) continue;
        // The stream's JSON numbers round-trip doubles exactly.
        EXPECT_EQ(sm["x"].get<double>(), fr.markers(0, m));
        EXPECT_EQ(sm["y"].get<double>(), fr.markers(1, m));
        EXPECT_EQ(sm["z"].get<double>(), fr.markers(2, m));
        ++compared;
      }
    }
    EXPECT_GT(compared, 10000);
  }

  // A fit cancelled at once keeps the best it reached, stored as a version; while it runs the
  // socket answers status from another client.
  {
    std::int64_t id = 0;
    ASSERT_TRUE(c->Send("fit.start", json::object(), &id).ok());
    std::unique_ptr<ControlClient> other;
    ASSERT_TRUE(d.Connect(&other).ok());
    json during = MustCall(other.get(), "status");
    EXPECT_EQ(during["job"]["kind"], "fit") << during.dump();
    ControlReply cancel, cancelled;
    ASSERT_TRUE(other->Call("fit.cancel", json::object(), &cancel).ok());
    EXPECT_TRUE(cancel.ok()) << cancel.error_message;
    ASSERT_TRUE(c->Wait(id, &cancelled).ok());
    EXPECT_EQ(cancelled.error_code, "cancelled") << cancelled.error_message;
    EXPECT_NE(cancelled.error_message.find("model v2"), std::string::npos) << cancelled.error_message;
  }
  // Fit, then apply between two frames while a subscriber watches.
  int fit_events = 0;
  json fit = MustCall(c.get(), "fit.start", json::object(),
                      [&](const json& ev) { fit_events += ev.value("job", "") == "fit"; });
  EXPECT_GT(fit_events, 0);
  ASSERT_TRUE(fit.contains("truth")) << fit.dump().substr(0, 2000);
  EXPECT_LE(fit["truth"]["joint_centre_error_mm_max"].get<double>(), 1.0) << fit["truth"].dump();
  EXPECT_GT(fit["truth_before"]["joint_centre_error_mm_max"].get<double>(), 5.0);
  EXPECT_EQ(fit["report"]["converged"], true);
  const int fitted_version = fit["model_version"];
  EXPECT_EQ(fitted_version, 3);  // v2 is the cancelled fit's

  std::unique_ptr<ControlClient> watcher;
  ASSERT_TRUE(d.Connect(&watcher).ok());
  MustCall(watcher.get(), "subscribe", {{"streams", {"markers", "pose", "status"}}});
  json apply = MustCall(c.get(), "model.apply", json::object());
  EXPECT_EQ(apply["version"], fitted_version);
  const std::uint64_t from_frame = apply["from_frame"];
  std::vector<std::uint64_t> frames;
  std::vector<int> versions;
  std::vector<int> labelled, cameras_present;
  // A frame the daemon itself drops (a queue full on a loaded host, a set the cameras did not
  // deliver, a subscriber that read too slowly) is counted and told; only a silent loss fails.
  auto counted_losses = [&](std::uint64_t told) {
    const json st = MustCall(c.get(), "status");
    return st["sets"]["dropped"].get<std::uint64_t>() + st["sets"]["undelivered"].get<std::uint64_t>() +
           st["tracker"]["loop_dropped"].get<std::uint64_t>() + told;
  };
  std::uint64_t told_dropped = 0;
  const std::uint64_t losses_before = counted_losses(0);
  const auto watch_until = std::chrono::steady_clock::now() + std::chrono::seconds(2);
  while (std::chrono::steady_clock::now() < watch_until) {
    json ev;
    bool got = false;
    ASSERT_TRUE(watcher->NextEvent(&ev, 200, &got).ok());
    if (got && ev.value("event", "") == "dropped") told_dropped += ev["count"].get<std::uint64_t>();
    if (!got || ev.value("event", "") != "frame") continue;
    frames.push_back(ev["frame"]);
    versions.push_back(ev["pose"]["model_version"]);
    int n = 0;
    for (const json& m : ev["markers"]) n += !m["occluded"].get<bool>();
    labelled.push_back(n);
    cameras_present.push_back(ev["health"]["cameras_present"]);
  }
  ASSERT_GT(frames.size(), 100u);
  const std::uint64_t counted = counted_losses(told_dropped) - losses_before;
  std::uint64_t missing = 0;
  for (std::size_t i = 1; i < frames.size(); ++i) {
    EXPECT_GT(frames[i], frames[i - 1]) << "frames out of order";
    if (frames[i] > frames[i - 1]) missing += frames[i] - frames[i - 1] - 1;
  }
  EXPECT_LE(missing, counted) << missing << " frames missing from the stream, " << counted
                              << " dropped and counted by the daemon: a frame was lost silently";
  for (std::size_t i = 0; i < frames.size(); ++i) {
    if (frames[i] >= from_frame) EXPECT_EQ(versions[i], fitted_version) << frames[i];
    // A set the overloaded machine delivered with cameras missing has fewer points; the swap
    // must not cost a complete set its labels.
    if (cameras_present[i] == 8)
      EXPECT_GT(labelled[i], 30) << "frame " << frames[i] << " (the swap at " << from_frame
                                 << ") lost its labels";
  }

  // Exports read back identically: the static recording as C3D and TRC against the store.
  const std::string c3d = dir + "/static.c3d", trc = dir + "/static.trc";
  MustCall(c.get(), "export", {{"kind", "recording"}, {"id", static_recording}, {"format", "c3d"}, {"path", c3d}});
  MustCall(c.get(), "export", {{"kind", "recording"}, {"id", static_recording}, {"format", "trc"}, {"path", trc}});
  json model_inline = MustCall(c.get(), "export", {{"kind", "model"}, {"id", fitted_version}, {"format", "json"}, {"inline", true}});
  EXPECT_GT(model_inline["content"].get<std::string>().size(), 1000u);
  // The fit's report page (report/fit_report_html.h), built from the stored report and the two
  // model versions: the same page as `mocap fit --html`, with this fit's RMS and iterations.
  json page = MustCall(c.get(), "export", {{"kind", "report"}, {"id", fit["report_id"]}, {"format", "html"}, {"inline", true}});
  const std::string html = page["content"];
  EXPECT_EQ(html.rfind("<!DOCTYPE html>", 0), 0u);
  for (const char* view : {"front", "side", "top"})
    EXPECT_NE(html.find(std::string("data-view=\"") + view + "\""), std::string::npos) << view;
  char rms[64];
  std::snprintf(rms, sizeof rms, "<div class=\"v\">%.2f mm</div>", fit["report"]["marker_rms_mm"].get<double>());
  EXPECT_NE(html.find(rms), std::string::npos) << rms;
  EXPECT_NE(html.find("after " + std::to_string(fit["report"]["iterations"].get<int>()) + " iterations"),
            std::string::npos);
  // Each joint checked against its functional estimate per recording (solver/fit_trust.h), in
  // the stored report and on its page, as `mocap fit` does.
  ASSERT_TRUE(fit["report"].contains("joint_checks"));
  EXPECT_FALSE(fit["report"]["joint_checks"].empty());
  EXPECT_NE(html.find("fitted − functional estimate"), std::string::npos);
  {
    std::unique_ptr<daemon::Store> store;
    daemon::StoreOptions so;
    so.mark_interrupted_recordings = false;
    ASSERT_TRUE(daemon::Store::Open(d.state_dir(), &store, so).ok());
    std::vector<daemon::RecordedFrame> stored;
    daemon::RecordingInfo info;
    ASSERT_TRUE(store->GetRecording(static_recording, &info).ok());
    ASSERT_TRUE(store->ReadFrames(static_recording, &stored).ok());
    formats::MarkerTrial from_trc;
    ASSERT_TRUE(formats::ReadTrc(trc, &from_trc).ok());
    ASSERT_EQ(from_trc.num_frames(), static_cast<int>(stored.size()));
    for (std::size_t m = 0; m < info.marker_names.size(); ++m) {
      const int k = from_trc.FindMarker(info.marker_names[m]);
      ASSERT_GE(k, 0) << info.marker_names[m];
      for (std::size_t f = 0; f < stored.size(); f += 37) {
        const Eigen::Vector3d want = stored[f].markers.col(m);
        if (!want.allFinite()) {
          EXPECT_FALSE(from_trc.Has(static_cast<int>(f), k));
          continue;
        }
        EXPECT_LT((from_trc.At(static_cast<int>(f), k) - want).norm(), 1e-5);  // TRC's precision
      }
    }
    formats::MarkerTrial from_c3d;
    ASSERT_TRUE(formats::ReadC3d(c3d, &from_c3d).ok());
    EXPECT_GE(from_c3d.num_frames(), static_cast<int>(stored.size()));
    EXPECT_GE(from_c3d.FindMarker(info.marker_names[0]), 0);
  }

  // A restart on the same storage lists the same subjects, recordings and models.
  json subjects = MustCall(c.get(), "subject.list");
  json recordings = MustCall(c.get(), "recording.list");
  json models = MustCall(c.get(), "model.list", {{"subject", "S01"}});
  c.reset();
  watcher.reset();
  EXPECT_EQ(d.Stop(), 0) << d.LogTail();
  ASSERT_DAEMON_STARTS(d);
  ASSERT_TRUE(d.Connect(&c).ok());
  json subjects2 = MustCall(c.get(), "subject.list");
  ASSERT_EQ(subjects2["subjects"].size(), subjects["subjects"].size());
  EXPECT_EQ(subjects2["subjects"][0]["name"], "S01");
  EXPECT_EQ(MustCall(c.get(), "recording.list")["recordings"], recordings["recordings"]);
  json models2 = MustCall(c.get(), "model.list", {{"subject", "S01"}});
  ASSERT_EQ(models2["models"].size(), models["models"].size());
  for (std::size_t i = 0; i < models["models"].size(); ++i)
    EXPECT_EQ(models2["models"][i]["version"], models["models"][i]["version"]);
  // What was live survived the restart: the rig comes back calibrated, tracking the subject with
  // the model that was applied.
  const json resumed = MustCall(c.get(), "status");
  EXPECT_EQ(resumed["rig"]["calibrated"], true);
  EXPECT_EQ(resumed["rig"]["calibration_version"], cal["version"]);
  EXPECT_EQ(resumed["subject"]["name"], "S01");
  EXPECT_EQ(resumed["live_model_version"], fitted_version);
  EXPECT_EQ(d.Stop(), 0) << d.LogTail();
}

// Raw bytes on the socket (the client library would refuse to send most of these).
class RawConnection {
 public:
  explicit RawConnection(const std::string& path) {
    fd_ = socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0);
    sockaddr_un addr{};
    addr.sun_family = AF_UNIX;
    std::snprintf(addr.sun_path, sizeof addr.sun_path, "%s", path.c_str());
    if (connect(fd_, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0) {
      close(fd_);
      fd_ = -1;
    }
    timeval tv{5, 0};
    if (fd_ >= 0) setsockopt(fd_, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
  }
  ~RawConnection() {
    if (fd_ >= 0) close(fd_);
  }
  bool ok() const { return fd_ >= 0; }
  bool Send(const std::string& bytes) {
    std::size_t off = 0;
    while (off < bytes.size()) {
      const ssize_t n = ::send(fd_, bytes.data() + off, bytes.size() - off, MSG_NOSIGNAL);
      if (n <= 0) return false;
      off += static_cast<std::size_t>(n);
    }
    return true;
  }
  // The next line as JSON (null on EOF or timeout).
  json Next() {
    for (;;) {
      const auto nl = buffer_.find('\n');
      if (nl != std::string::npos) {
        std::string line = buffer_.substr(0, nl);
        buffer_.erase(0, nl + 1);
        return json::parse(line, nullptr, false);
      }
      char buf[4096];
      const ssize_t n = ::recv(fd_, buf, sizeof buf, 0);
      if (n <= 0) return nullptr;
      buffer_.append(buf, static_cast<std::size_t>(n));
    }
  }

 private:
  int fd_ = -1;
  std::string buffer_;
};

// Every documented request and error code (daemon/PROTOCOL.md), and every kind of bad input.
TEST(Daemon, ProtocolEveryRequestAndEveryError) {
  const std::string dir = testing::MakeTempDir("mocapd-protocol");
  DaemonProcess d(dir, testing::SimulatedRigToml(2, 1) + "[control]\nmax_line_bytes = 65536\n");
  ASSERT_DAEMON_STARTS(d);
  std::unique_ptr<ControlClient> c;
  ASSERT_TRUE(d.Connect(&c).ok());
  std::set<std::string> sent, codes;
  auto call = [&](const std::string& method, const json& params) {
    sent.insert(method);
    ControlReply r;
    EXPECT_TRUE(c->Call(method, params, &r).ok()) << method;
    if (!r.ok()) {
      codes.insert(r.error_code);
      EXPECT_FALSE(r.error_message.empty()) << method;
    }
    return r;
  };
  // In a state where most need something first: each answers with the error that says what.
  EXPECT_TRUE(call("status", {}).ok());
  EXPECT_TRUE(call("cameras", {}).ok());
  EXPECT_EQ(call("cameras", {}).result["cameras"].size(), 2u);
  // The rig check, a moment after the start: its cameras have too few frames to judge yet.
  const json check = call("cameras.check", {}).result;
  EXPECT_EQ(check["cameras"].size(), 2u);
  EXPECT_EQ(check["sync"]["mode"], "shared-clock");
  EXPECT_TRUE(call("protocol.show", {}).ok());
  EXPECT_EQ(call("config.reload", {}).result["reloaded"], true);
  EXPECT_EQ(call("rig.calibrate.finish", {}).error_code, "conflict");
  EXPECT_EQ(call("rig.calibrate.cancel", {}).error_code, "conflict");
  EXPECT_EQ(call("rig.calibrate.apply", {}).error_code, "not_found");
  EXPECT_EQ(call("rig.calibrate.start", {{"seconds", "long"}}).error_code, "invalid_params");
  EXPECT_TRUE(call("rig.calibrate.start", {{"seconds", 5}}).ok());
  EXPECT_EQ(call("rig.calibrate.start", {{"seconds", 5}}).error_code, "conflict");
  EXPECT_EQ(call("record.start", {{"movement", "squats"}}).error_code, "conflict");  // no subject
  EXPECT_TRUE(call("rig.calibrate.cancel", {}).ok());
  EXPECT_TRUE(call("calibration.list", {}).ok());
  EXPECT_EQ(call("subject.create", {{"name", "A"}}).error_code, "invalid_params");
  EXPECT_EQ(call("subject.create", {{"name", "A"}, {"height_m", 9}}).error_code, "invalid_params");
  EXPECT_EQ(call("subject.create", {{"name", "A"}, {"height_m", 1.7}, {"model", "/nonexistent.osim"}}).error_code, "failed");
  EXPECT_TRUE(call("subject.create", {{"name", "A"}, {"height_m", 1.7}}).ok());
  EXPECT_EQ(call("subject.select", {{"name", "B"}}).error_code, "not_found");
  EXPECT_TRUE(call("subject.select", {{"name", "A"}}).ok());
  // Its model applied at once (the select's tracker starts at the next frame: the apply must not
  // find "no subject is being tracked"; tests/test_capture_pipeline.cpp holds the frames back).
  const ControlReply applied = call("model.apply", {});
  EXPECT_TRUE(applied.ok()) << applied.error_message;
  EXPECT_EQ(applied.result["version"], 1);
  EXPECT_EQ(call("subject.list", {}).result["subjects"].size(), 1u);
  EXPECT_EQ(call("record.start", {{"movement", "moonwalk"}}).error_code, "not_found");
  EXPECT_EQ(call("record.start", {{"movement", "squats"}}).error_code, "unavailable");  // uncalibrated
  EXPECT_EQ(call("record.stop", {}).error_code, "conflict");
  EXPECT_TRUE(call("recording.list", {}).ok());
  EXPECT_EQ(call("fit.start", {}).error_code, "conflict");  // nothing recorded
  EXPECT_EQ(call("fit.start", {{"max_iterations", -3}}).error_code, "invalid_params");
  EXPECT_EQ(call("fit.cancel", {}).error_code, "conflict");
  EXPECT_EQ(call("model.list", {}).result["models"].size(), 1u);
  EXPECT_EQ(call("model.apply", {{"version", 7}}).error_code, "not_found");
  EXPECT_EQ(call("export", {{"kind", "model"}, {"id", 1}, {"format", "osim"}, {"path", dir + "/m.osim"}}).error_code, "unavailable");
  EXPECT_EQ(call("export", {{"kind", "model"}, {"id", 1}, {"format", "json"}, {"path", "relative.json"}}).error_code, "invalid_params");
  EXPECT_TRUE(call("export", {{"kind", "model"}, {"id", 1}, {"format", "json"}, {"inline", true}}).ok());
  EXPECT_EQ(call("subscribe", {{"streams", {"gossip"}}}).error_code, "invalid_params");
  EXPECT_TRUE(call("subscribe", {{"streams", {"status"}}, {"decimation", 50}}).ok());
  EXPECT_TRUE(call("unsubscribe", {}).ok());
  EXPECT_EQ(call("no.such.method", {}).error_code, "unknown_method");
  EXPECT_EQ(call("sim.camera", {{"camera", 5}, {"present", false}}).error_code, "invalid_params");
  EXPECT_EQ(call("sim.camera", {{"camera", 1}}).error_code, "invalid_params");
  EXPECT_TRUE(call("sim.camera", {{"camera", 1}, {"present", false}}).ok());
  EXPECT_TRUE(call("sim.camera", {{"camera", 1}, {"present", true}}).ok());
  EXPECT_EQ(call("sim.camera", {{"camera", 1}, {"ptp", "Slave"}}).error_code, "unavailable");  // not ptp
  EXPECT_EQ(call("sim.camera", {{"camera", 1}, {"ptp", 3}}).error_code, "invalid_params");

  // Envelopes the client library never sends, on a raw connection.
  RawConnection raw(d.socket());
  ASSERT_TRUE(raw.ok());
  json hello = raw.Next();
  EXPECT_EQ(hello["event"], "hello");
  EXPECT_EQ(hello["protocol"], 1);
  auto raw_error = [&](const std::string& bytes) {
    EXPECT_TRUE(raw.Send(bytes));
    json r = raw.Next();
    EXPECT_TRUE(r.contains("error")) << bytes.substr(0, 80) << " -> " << r.dump();
    if (r.contains("error")) codes.insert(r["error"]["code"].get<std::string>());
    return r.contains("error") ? r["error"]["code"].get<std::string>() : std::string();
  };
  EXPECT_EQ(raw_error("{not json\n"), "parse_error");
  EXPECT_EQ(raw_error(std::string("{\"id\":1,\"method\":\"st\xff\xfe\"}\n")), "parse_error");
  EXPECT_EQ(raw_error("[1,2,3]\n"), "invalid_request");
  EXPECT_EQ(raw_error("{\"method\":\"status\"}\n"), "invalid_request");
  EXPECT_EQ(raw_error("{\"id\":{},\"method\":\"status\"}\n"), "invalid_request");
  EXPECT_EQ(raw_error("{\"id\":2,\"method\":5}\n"), "invalid_request");
  EXPECT_EQ(raw_error("{\"id\":3,\"method\":\"status\",\"params\":[]}\n"), "invalid_request");
  EXPECT_TRUE(raw.Send("{\"id\":\"x\",\"method\":\"status\"}\n"));
  EXPECT_EQ(raw.Next()["id"], "x");
  // An over-long line: the error, then the connection closes; the others go on.
  EXPECT_EQ(raw_error(std::string(100000, 'a') + "\n"), "line_too_long");
  EXPECT_TRUE(raw.Next().is_null());
  {
    ControlReply r;
    EXPECT_TRUE(c->Call("status", json::object(), &r).ok() && r.ok());
  }

  // A user outside the control group may read, not change state.
  chmod(dir.c_str(), 0755);  // mkdtemp's 0700 would keep `nobody` from the socket's directory
  chmod(d.socket().c_str(), 0666);
  const std::string got = testing::RunAsUser("nobody", [&] {
    std::unique_ptr<ControlClient> u;
    daemon::ControlClientOptions o;
    o.socket_path = d.socket();
    if (!ControlClient::Connect(o, &u).ok()) return std::string("connect");
    ControlReply a, b;
    const bool ok1 = u->Call("status", json::object(), &a).ok();
    const bool ok2 = u->Call("subject.create", {{"name", "Z"}, {"height_m", 1.7}}, &b).ok();
    return std::string(u->hello().may_control ? "control" : "read") + "|" +
           (ok1 && a.ok() ? "status-ok" : "status-bad") + "|" + (ok2 ? b.error_code : "io") + "|" +
           b.error_message;
  });
  EXPECT_EQ(got.substr(0, got.find("|forbidden") + 10), "read|status-ok|forbidden") << got;
  EXPECT_NE(got.find("group"), std::string::npos) << got;
  codes.insert("forbidden");

  // Every method and every error code of PROTOCOL.md was exercised.
  std::ifstream doc(MOCAP_SOURCE_DIR "/daemon/PROTOCOL.md");
  std::string line;
  const std::regex method_re("^### ([a-z.]+)"), code_re("^\\| `([a-z_]+)` \\|");
  std::set<std::string> documented_methods, documented_codes;
  while (std::getline(doc, line)) {
    std::smatch m;
    if (std::regex_search(line, m, method_re)) documented_methods.insert(m[1]);
    if (std::regex_search(line, m, code_re)) documented_codes.insert(m[1]);
  }
  EXPECT_GT(documented_methods.size(), 20u);
  sent.insert("shutdown");  // below
  for (const std::string& m : documented_methods) EXPECT_TRUE(sent.count(m)) << "not exercised: " << m;
  // busy, cancelled and internal need load, a running job or a bug: the session and fault tests.
  for (const std::string& code : documented_codes)
    if (code != "busy" && code != "cancelled" && code != "internal")
      EXPECT_TRUE(codes.count(code)) << "error code not exercised: " << code;
  for (const std::string& code : codes) EXPECT_TRUE(documented_codes.count(code)) << "undocumented: " << code;

  {
    ControlReply r;
    EXPECT_TRUE(c->Call("shutdown", json::object(), &r).ok() && r.ok());
  }
  EXPECT_EQ(d.Stop(), 0) << d.LogTail();
}

TEST(Daemon, RefusesABadConfigNamingFileLineAndKey) {
  const std::string dir = testing::MakeTempDir("mocapd-badconfig");
  DaemonProcess d(dir, "[rig]\nsimulated = 2\nrate = \"fast\"\n");
  EXPECT_FALSE(d.Start(10).ok());
  const std::string log = d.Log();
  EXPECT_NE(log.find("mocapd.toml:3"), std::string::npos) << log;
  EXPECT_NE(log.find("rig.rate"), std::string::npos) << log;
}

}  // namespace
}  // namespace mocap
