// mocapctl: the operator's client of mocapd. One subcommand per request of the control protocol
// (daemon/PROTOCOL.md); human-readable output by default, --json for scripts.
//
// Exit status: 0 success; 1 the daemon answered with an error (its code and message are
// printed); 2 a usage error; 3 the daemon is not reachable (not running, refused, gone, silent);
// 4 a recording that did not pass its coverage check (the advice says which movement to repeat);
// 5 `cameras --check` found the rig wanting (sync, lost frames, a link over budget: each printed).
//
// Long requests (calibration, recording, fit) show the daemon's progress: a bar with the ETA when
// the output is a terminal, one plain line per progress event otherwise (logs, CI). Ctrl-C during
// them asks the daemon to stop the work (record.stop, fit.cancel, rig.calibrate.cancel) and still
// prints what it kept; a second Ctrl-C quits at once.
#include <poll.h>
#include <sys/ioctl.h>
#include <unistd.h>

#include <CLI/CLI.hpp>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <functional>
#include <iostream>
#include <memory>
#include <string>
#include <vector>

#include "daemon/control_client.h"

namespace {

using json = nlohmann::json;
using mocap::Status;
using mocap::daemon::ControlClient;
using mocap::daemon::ControlClientOptions;
using mocap::daemon::ControlReply;

constexpr int kExitOk = 0;
constexpr int kExitDaemonError = 1;
constexpr int kExitUsage = 2;
constexpr int kExitUnreachable = 3;
constexpr int kExitCoverageFailed = 4;
constexpr int kExitRigCheckFailed = 5;

volatile std::sig_atomic_t g_interrupted = 0;
void OnInterrupt(int) { g_interrupted = 1; }

// Ctrl-C sets a flag (once: SA_RESETHAND, so a second one quits) while a long request runs.
class InterruptScope {
 public:
  InterruptScope() {
    g_interrupted = 0;
    struct sigaction action{};
    action.sa_handler = OnInterrupt;
    action.sa_flags = SA_RESETHAND;  // no SA_RESTART: poll() returns at once
    sigaction(SIGINT, &action, &previous_);
  }
  ~InterruptScope() { sigaction(SIGINT, &previous_, nullptr); }

 private:
  struct sigaction previous_{};
};

struct Globals {
  std::string socket;
  bool json = false;
  double timeout_s = 120;
};

// ---- Output ----------------------------------------------------------------------------------

std::string Text(const json& v) {
  if (v.is_string()) return v.get<std::string>();
  if (v.is_null()) return "-";
  if (v.is_number_float()) {
    char buf[32];
    std::snprintf(buf, sizeof buf, "%.4g", v.get<double>());
    return buf;
  }
  return v.dump();
}

// An array's items separated by commas (the streams subscribed, ...).
std::string Join(const json& v) {
  if (!v.is_array()) return Text(v);
  std::string out;
  for (const auto& item : v) out += (out.empty() ? "" : ", ") + Text(item);
  return out;
}

std::string Fixed(const json& v, int decimals) {
  if (!v.is_number()) return Text(v);
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.*f", decimals, v.get<double>());
  return buf;
}

// Any JSON value as indented "key: value" lines, for results without a layout of their own.
void PrintTree(const json& v, int indent = 0) {
  const std::string pad(indent, ' ');
  if (v.is_object()) {
    for (const auto& [key, value] : v.items()) {
      if (value.is_structured() && !value.empty()) {
        std::printf("%s%s:\n", pad.c_str(), key.c_str());
        PrintTree(value, indent + 2);
      } else {
        std::printf("%s%s: %s\n", pad.c_str(), key.c_str(), Text(value).c_str());
      }
    }
  } else if (v.is_array()) {
    bool scalars = true;
    for (const auto& item : v) scalars &= !item.is_structured();
    if (scalars) {
      std::printf("%s%s\n", pad.c_str(), Join(v).c_str());
      return;
    }
    for (const auto& item : v) {
      std::printf("%s-\n", pad.c_str());
      PrintTree(item, indent + 2);
    }
  } else {
    std::printf("%s%s\n", pad.c_str(), Text(v).c_str());
  }
}

// Rows of objects as an aligned table of the given columns.
void PrintTable(const json& rows, const std::vector<std::string>& columns) {
  if (!rows.is_array() || rows.empty()) {
    std::printf("(none)\n");
    return;
  }
  std::vector<std::vector<std::string>> cells{columns};
  for (const auto& row : rows) {
    std::vector<std::string> line;
    for (const auto& c : columns) line.push_back(row.contains(c) ? Text(row[c]) : "-");
    cells.push_back(line);
  }
  std::vector<std::size_t> width(columns.size(), 0);
  for (const auto& line : cells)
    for (std::size_t c = 0; c < line.size(); ++c) width[c] = std::max(width[c], line[c].size());
  for (const auto& line : cells) {
    std::string out;
    for (std::size_t c = 0; c < line.size(); ++c)
      out += line[c] + std::string(width[c] - line[c].size() + 2, ' ');
    while (!out.empty() && out.back() == ' ') out.pop_back();
    std::printf("%s\n", out.c_str());
  }
}

// The daemon's progress events: a bar with the ETA on a terminal, plain lines otherwise.
// In --json mode they go to stderr, so that stdout holds only the result.
class ProgressView {
 public:
  explicit ProgressView(bool json_mode)
      : out_(json_mode ? stderr : stdout), tty_(isatty(fileno(out_)) != 0) {}
  ~ProgressView() { Finish(); }

  void Show(const json& event) {
    if (event.value("event", json()) != "progress") return;
    const json text = event.value("message", json());
    const std::string message = text.is_string() ? text.get<std::string>() : std::string();
    if (!tty_) {
      std::fprintf(out_, "%s\n", message.empty() ? event.dump().c_str() : message.c_str());
      std::fflush(out_);
      return;
    }
    std::string line;
    const json fraction = event.value("fraction", json());
    if (fraction.is_number()) {
      constexpr int kBar = 30;
      const double f = std::clamp(fraction.get<double>(), 0.0, 1.0);
      const int filled = static_cast<int>(std::lround(f * kBar));
      char percent[16];
      std::snprintf(percent, sizeof percent, "%3d%%", static_cast<int>(std::lround(100 * f)));
      line = "[" + std::string(filled, '#') + std::string(kBar - filled, '.') + "] " + percent;
      const json eta = event.value("eta_s", json());
      if (eta.is_number()) {
        const int s = static_cast<int>(std::lround(eta.get<double>()));
        char text[32];
        std::snprintf(text, sizeof text, "  ETA %d:%02d", s / 60, s % 60);
        line += text;
      }
      line += "  ";
    }
    line += message;
    winsize ws{};
    const std::size_t columns =
        ioctl(fileno(out_), TIOCGWINSZ, &ws) == 0 && ws.ws_col > 0 ? ws.ws_col : 100;
    if (line.size() >= columns) line.resize(columns - 1);
    std::fprintf(out_, "\r\033[K%s", line.c_str());
    std::fflush(out_);
    open_line_ = true;
  }
  // Ends the bar's line before other output.
  void Finish() {
    if (open_line_) std::fprintf(out_, "\n");
    open_line_ = false;
  }

 private:
  FILE* out_;
  bool tty_;
  bool open_line_ = false;
};

// ---- Talking to the daemon -------------------------------------------------------------------

class Ctl {
 public:
  explicit Ctl(const Globals& g) : globals_(g) {}

  // Connects (once); false with the message printed when the daemon is not reachable.
  bool Connect() {
    if (client_) return true;
    ControlClientOptions options;
    options.socket_path = globals_.socket;
    options.reply_timeout_ms =
        globals_.timeout_s > 0 ? static_cast<int>(std::lround(globals_.timeout_s * 1000)) : 0;
    Status s = ControlClient::Connect(options, &client_);
    if (!s.ok()) std::fprintf(stderr, "mocapctl: %s\n", s.message().c_str());
    return s.ok();
  }

  // Sends `method` and waits for its reply, showing progress. Returns the exit status; on success
  // `result` holds the reply's result.
  int Call(const std::string& method, const json& params, json* result) {
    if (!Connect()) return kExitUnreachable;
    ProgressView progress(globals_.json);
    ControlReply reply;
    Status s = client_->Call(method, params, &reply, [&](const json& e) { progress.Show(e); });
    progress.Finish();
    return Finish(s, reply, result);
  }

  // As Call, for a long request that Ctrl-C should stop: then `stop_method` is sent (once) and
  // the reply to `method` still awaited (it says what the daemon kept).
  int CallInterruptible(const std::string& method, const json& params,
                        const std::string& stop_method, json* result) {
    if (!Connect()) return kExitUnreachable;
    InterruptScope interrupts;
    ProgressView progress(globals_.json);
    std::int64_t id = 0;
    Status s = client_->Send(method, params, &id);
    ControlReply reply;
    bool stop_sent = false;
    auto last_heard = std::chrono::steady_clock::now();
    while (s.ok()) {
      s = client_->Poll(200, [&](const json& e) {
        last_heard = std::chrono::steady_clock::now();
        progress.Show(e);
      });
      if (!s.ok()) s = Status::Error(s.message() + " before replying to " + method);
      if (!s.ok() || client_->TakeReply(id, &reply)) break;
      if (g_interrupted && !stop_sent) {
        progress.Finish();
        std::fprintf(stderr, "mocapctl: interrupted: asking mocapd to stop (%s)\n",
                     stop_method.c_str());
        std::int64_t stop_id = 0;
        s = client_->Send(stop_method, json::object(), &stop_id);
        stop_sent = true;
      }
      if (globals_.timeout_s > 0 && std::chrono::steady_clock::now() - last_heard >
                                        std::chrono::duration<double>(globals_.timeout_s))
        s = Status::Error("mocapd sent nothing for " + Text(globals_.timeout_s) + " s while " +
                          method + " waited for its reply");
    }
    progress.Finish();
    return Finish(s, reply, result);
  }

  ControlClient& client() { return *client_; }
  bool json_mode() const { return globals_.json; }

 private:
  int Finish(const Status& s, const ControlReply& reply, json* result) {
    if (!s.ok()) {
      std::fprintf(stderr, "mocapctl: %s\n", s.message().c_str());
      return kExitUnreachable;
    }
    if (!reply.ok()) {
      if (globals_.json)
        std::printf("%s\n",
                    json({{"error", {{"code", reply.error_code}, {"message", reply.error_message}}}})
                        .dump(2)
                        .c_str());
      std::fprintf(stderr, "mocapd: %s: %s\n", reply.error_code.c_str(),
                   reply.error_message.c_str());
      return kExitDaemonError;
    }
    *result = reply.result;
    return kExitOk;
  }

  const Globals& globals_;
  std::unique_ptr<ControlClient> client_;
};

using Printer = std::function<void(const json&)>;

// After a request: on success prints its result as JSON (--json) or with `print`; returns
// the exit status.
int Output(const Ctl& ctl, int status, const json& result, const Printer& print) {
  if (status != kExitOk) return status;
  if (ctl.json_mode())
    std::printf("%s\n", result.dump(2).c_str());
  else
    print(result);
  return kExitOk;
}

// Runs one request and prints its result.
int Simple(Ctl& ctl, const std::string& method, const json& params,
           const Printer& print = [](const json& r) { PrintTree(r); }) {
  json result;
  const int status = ctl.Call(method, params, &result);
  return Output(ctl, status, result, print);
}

std::string Absolute(const std::string& path) {
  return std::filesystem::absolute(path).lexically_normal().string();
}

// ---- Human layouts of the main results --------------------------------------------------------

// cameras.check (daemon/rig_check.h): per camera its sync and lost frames, per link its budget,
// then every problem.
void PrintRigCheck(const json& r) {
  const json sync = r.value("sync", json::object());
  const std::string mode = sync.value("mode", std::string("?"));
  std::printf("sync: %s", mode.c_str());
  if (mode == "ptp")
    std::printf(", %s, master %s", sync.value("locked", json()) == true ? "locked" : "NOT locked",
                Text(sync.value("master", json())).c_str());
  if (mode == "trigger") std::printf(", %s mismatched sets", Text(sync.value("mismatched_sets", json())).c_str());
  std::printf("\n");
  for (const json& c : r.value("cameras", json::array())) {
    const json cs = c.value("sync", json::object());
    const json f = c.value("frames", json::object());
    std::string line = Text(c.value("id", json())) + (c.value("ok", false) ? "  ok  " : "  FAIL");
    if (mode == "ptp")
      line += "  ptp " + Text(cs.value("status", json())) + " offset " +
              Text(cs.value("offset_from_master_ns", json())) + " ns, tick phase " +
              Fixed(cs.value("tick_phase", json()), 2) + " (" +
              Fixed(cs.value("phase_from_rig_us", json()), 0) + " us from the rig)";
    else if (mode == "free-run")
      line += "  offset " + Fixed(cs.value("offset_from_rig_ms", json()), 3) + " ms from the rig, drift " +
              Fixed(cs.value("clock_drift_ppm", json()), 1) + " ppm, residual " +
              Fixed(cs.value("clock_residual_us", json()), 0) + " us";
    else if (mode == "trigger")
      line += "  " + Text(cs.value("role", json())) + ", count/timestamp mismatches " +
              Text(cs.value("count_mismatches", json()));
    line += "  frames " + Text(f.value("complete", json())) + ", incomplete " +
            Text(f.value("incomplete", json())) + ", underruns " + Text(f.value("underruns", json())) +
            ", not received " + Text(f.value("not_received", json()));
    if (c.value("packets", json()).is_object())
      line += ", packets resent " + Text(c["packets"].value("resent", json())) + " missing " +
              Text(c["packets"].value("missing", json()));
    std::printf("%s\n", line.c_str());
  }
  for (const json& l : r.value("links", json::array()))
    std::printf("link %s (%s, %zu cameras): needs %s of %s MB/s, headroom %s MB/s%s\n",
                Text(l.value("link", json())).c_str(), Text(l.value("interface", json())).c_str(),
                l.value("cameras", json::array()).size(), Fixed(l.value("needed_mb_s", json()), 1).c_str(),
                Fixed(l.value("capacity_mb_s", json()), 1).c_str(),
                Fixed(l.value("headroom_mb_s", json()), 1).c_str(), l.value("ok", false) ? "" : "  OVER BUDGET");
  const json problems = r.value("problems", json::array());
  for (const json& p : problems) std::printf("problem: %s\n", Text(p).c_str());
  std::printf("rig check: %s\n", r.value("ok", false) ? "ok" : "FAILED");
}

void PrintStatus(const json& r) {
  std::printf("mocapd %s, %s, up %s s, %s clients\n", Text(r.value("version", json())).c_str(),
              Text(r.value("state", json())).c_str(), Fixed(r.value("uptime_s", json()), 0).c_str(),
              Text(r.value("clients", json())).c_str());
  if (const json rig = r.value("rig", json()); rig.is_object())
    std::printf("rig: %s cameras%s at %s Hz, calibration %s\n", Text(rig.value("cameras", json())).c_str(),
                rig.value("simulated", false) ? " (simulated)" : "",
                Text(rig.value("rate_hz", json())).c_str(),
                rig.value("calibration_version", json()).is_null()
                    ? "none"
                    : ("version " + Text(rig["calibration_version"])).c_str());
  if (const json sets = r.value("sets", json()); sets.is_object())
    std::printf("frame sets: %s, incomplete %s, dropped %s\n", Text(sets.value("total", json())).c_str(),
                Text(sets.value("incomplete", json())).c_str(),
                Text(sets.value("dropped", json())).c_str());
  if (const json t = r.value("tracker", json()); t.is_object())
    std::printf("tracker: %s, %s of %s markers labelled\n", Text(t.value("state", json())).c_str(),
                Text(t.value("labelled", json())).c_str(), Text(t.value("markers", json())).c_str());
  const json subject = r.value("subject", json());
  std::printf("subject: %s, model version %s (live %s)\n",
              subject.is_object() ? Text(subject.value("name", json())).c_str() : "none",
              Text(r.value("model_version", json())).c_str(),
              Text(r.value("live_model_version", json())).c_str());
  if (const json rec = r.value("recording", json()); rec.is_object())
    std::printf("recording %s: %s, %s frames, %s s\n", Text(rec.value("id", json())).c_str(),
                Text(rec.value("movement", json())).c_str(), Text(rec.value("frames", json())).c_str(),
                Fixed(rec.value("seconds", json()), 1).c_str());
  if (const json job = r.value("job", json()); job.is_object())
    std::printf("job: %s, %s%%\n", Text(job.value("kind", json())).c_str(),
                job.value("fraction", json()).is_number()
                    ? Fixed(100 * job["fraction"].get<double>(), 0).c_str()
                    : "-");
  if (const json l = r.value("latency_ms", json()); l.is_object())
    std::printf("latency: p50 %s ms, p99 %s ms\n", Fixed(l.value("p50", json()), 2).c_str(),
                Fixed(l.value("p99", json()), 2).c_str());
  if (const json st = r.value("storage", json()); st.is_object())
    std::printf("storage: %s, database %s MB, %s MB free\n", Text(st.value("dir", json())).c_str(),
                st.value("db_bytes", json()).is_number()
                    ? Fixed(st["db_bytes"].get<double>() / 1e6, 1).c_str()
                    : "-",
                st.value("free_bytes", json()).is_number()
                    ? Fixed(st["free_bytes"].get<double>() / 1e6, 0).c_str()
                    : "-");
  if (r.contains("cameras")) {
    PrintTable(r["cameras"], {"id", "connected", "fps", "frames", "incomplete", "dropped"});
    for (const json& c : r["cameras"])  // why a camera is not streaming (a degraded start, a loss)
      if (c.value("problem", json()).is_string())
        std::printf("camera %s: %s\n", Text(c.value("id", json())).c_str(), c["problem"].get<std::string>().c_str());
  }
}

void PrintCalibration(const json& r) {
  std::printf("rig calibration version %s: reprojection RMS %s px, wand length error %s mm, %s wand frames\n",
              Text(r.value("version", json())).c_str(),
              Fixed(r.value("reprojection_rms_px", json()), 3).c_str(),
              Fixed(r.value("wand_length_error_mm", json()), 2).c_str(),
              Text(r.value("wand_frames", json())).c_str());
  if (r.contains("cameras")) PrintTable(r["cameras"], {"id", "reprojection_rms_px", "wand_frames"});
  if (const json truth = r.value("truth", json()); truth.is_object())
    std::printf("against the simulated rig: position error %s mm, orientation error %s deg (max)\n",
                Fixed(truth.value("position_error_mm_max", json()), 2).c_str(),
                Fixed(truth.value("orientation_error_deg_max", json()), 3).c_str());
}

bool CoveragePassed(const json& recording) {
  const json coverage = recording.value("coverage", json());
  return coverage.is_object() && coverage.value("ok", false);
}

void PrintRecording(const json& r) {
  std::printf("recording %s (%s): %s frames, %s s, tracking %s%%\n", Text(r.value("recording", json())).c_str(),
              Text(r.value("movement", json())).c_str(), Text(r.value("frames", json())).c_str(),
              Fixed(r.value("seconds", json()), 2).c_str(),
              r.value("tracking_fraction", json()).is_number()
                  ? Fixed(100 * r["tracking_fraction"].get<double>(), 1).c_str()
                  : "-");
  const json coverage = r.value("coverage", json());
  if (coverage.is_object() && coverage.contains("excitations")) {
    json rows = json::array();
    for (const auto& e : coverage["excitations"]) {
      rows.push_back({{"coordinate", e.value("coordinate", json())},
                      {"required_deg", Fixed(e.value("min_deg", json()), 0) + " .. " +
                                           Fixed(e.value("max_deg", json()), 0)},
                      {"reached_deg", Fixed(e.value("reached_min_deg", json()), 1) + " .. " +
                                          Fixed(e.value("reached_max_deg", json()), 1)},
                      {"ok", e.value("ok", false) ? "ok" : (e.value("required", true) ? "TOO SMALL" : "small (optional)")}});
    }
    PrintTable(rows, {"coordinate", "required_deg", "reached_deg", "ok"});
  }
  std::printf("coverage: %s\n", CoveragePassed(r) ? "passed" : "NOT passed");
  // Frames missing from the take (daemon/PROTOCOL.md, record.start's `losses`): said, not hidden.
  if (const json losses = r.value("losses", json());
      losses.is_object() && losses.value("missing_frames", 0) > 0)
    std::printf("frames missing: %s (meanwhile %s sets not exposed by any camera, %s dropped by "
                "mocapd, %s refused by the recorder)\n",
                Text(losses["missing_frames"]).c_str(), Text(losses.value("sets_not_exposed", json())).c_str(),
                Text(losses.value("sets_dropped", json())).c_str(),
                Text(losses.value("recorder_dropped", json())).c_str());
  if (r.contains("advice") && r["advice"].is_string() && !r["advice"].get<std::string>().empty())
    std::printf("%s\n", r["advice"].get<std::string>().c_str());
}

// The fit's outcome in a dozen lines; the whole report is `mocapctl export report ID`.
void PrintFit(const json& r) {
  std::printf("fitted model version %s (stored, not applied: mocapctl apply)\n",
              Text(r.value("model_version", json())).c_str());
  if (r.contains("report")) {
    const json& rep = r["report"];
    std::printf("  %s after %s iterations (%s), %.1f s; %s frames of %s trials\n",
                rep.value("termination", "?").c_str(), Text(rep.value("iterations", json())).c_str(),
                rep.value("termination_message", "").c_str(), rep.value("wall_seconds", 0.0),
                Text(rep.value("frames", json())).c_str(), Text(rep.value("trials", json())).c_str());
    std::printf("  marker RMS %.3f mm (from %.3f mm)\n", rep.value("marker_rms_mm", 0.0),
                rep.value("initial_marker_rms_mm", 0.0));
    if (rep.contains("per_marker_rms_mm") && rep["per_marker_rms_mm"].is_object() &&
        !rep["per_marker_rms_mm"].empty()) {
      std::string worst;
      double w = -1;
      for (const auto& [name, v] : rep["per_marker_rms_mm"].items())
        if (v.is_number() && v.get<double>() > w) w = v.get<double>(), worst = name;
      std::printf("  largest marker RMS: %s %.3f mm\n", worst.c_str(), w);
    }
    if (rep.contains("undetermined") && rep["undetermined"].is_array()) {
      std::string names;
      int n = 0;
      for (const json& u : rep["undetermined"]) {
        if (n++ < 6) names += (names.empty() ? "" : ", ") + Text(u);
      }
      if (n > 6) names += ", ...";
      std::printf("  %d parameters the recordings did not determine%s%s\n", n, n ? ": " : "",
                  names.c_str());
    }
  }
  if (r.contains("report_id"))
    std::printf("  full report: mocapctl export report %s --format json --out FILE\n",
                Text(r["report_id"]).c_str());
  if (r.contains("diff") && r["diff"].contains("joint_centre_error_mm")) {
    const json& jc = r["diff"]["joint_centre_error_mm"];
    std::printf("  against the model it started from: joint centres moved %.2f mm RMS, %.2f mm max\n",
                jc.value("rms", 0.0), jc.value("max", 0.0));
  }
  if (r.contains("truth")) {
    const json& t = r["truth"];
    std::printf("  against the simulated subject's truth: joint centres %.3f mm RMS, %.3f mm max",
                t.value("joint_centre_error_mm_rms", 0.0), t.value("joint_centre_error_mm_max", 0.0));
    if (r.contains("truth_before"))
      std::printf(" (before the fit: %.1f mm max)",
                  r["truth_before"].value("joint_centre_error_mm_max", 0.0));
    std::printf("; segment lengths %.3f %% max; markers %.2f mm RMS\n",
                t.value("segment_length_error_pct_max", 0.0), t.value("marker_error_mm_rms", 0.0));
  }
}

void PrintReload(const json& r) {
  std::printf("configuration re-read\n");
  std::printf("applied: %s\n", r.value("applied", json::array()).empty()
                                    ? "nothing changed that applies live"
                                    : Join(r["applied"]).c_str());
  if (!r.value("needs_restart", json::array()).empty())
    std::printf("needs a restart of mocapd (not applied): %s\n", Join(r["needs_restart"]).c_str());
}

void PrintProtocol(const json& r) {
  const json movements = r.value("movements", json::array());
  std::printf("protocol %s: %zu movements\n", Text(r.value("name", json())).c_str(), movements.size());
  for (const auto& m : movements) {
    std::printf("%s (%s s): %s\n", Text(m.value("name", json())).c_str(),
                Fixed(m.value("duration_s", json()), 1).c_str(),
                Text(m.value("description", json(""))).c_str());
    for (const auto& e : m.value("excitations", json::array()))
      std::printf("  %s %s .. %s deg%s\n", Text(e.value("coordinate", json())).c_str(),
                  Fixed(e.value("min_deg", json()), 0).c_str(), Fixed(e.value("max_deg", json()), 0).c_str(),
                  e.value("required", json(true)) == false ? " (optional)" : "");
  }
}

void PrintSubject(const json& r) {
  std::printf("subject %s (id %s), model version %s\n", Text(r.value("name", json())).c_str(),
              Text(r.value("id", json())).c_str(), Text(r.value("model_version", json())).c_str());
}

void PrintApplied(const json& r) {
  std::printf("version %s is live from frame %s\n", Text(r.value("version", json())).c_str(),
              Text(r.value("from_frame", json())).c_str());
}

// ---- Subcommands that need more than one request ---------------------------------------------

// rig.calibrate.start, progress until --seconds passed or Enter, rig.calibrate.finish, [apply].
int Calibrate(Ctl& ctl, double seconds, bool apply) {
  json result;
  int status = ctl.Call("rig.calibrate.start", {{"seconds", seconds}}, &result);
  if (status != kExitOk) return status;
  const bool enter_ends = isatty(STDIN_FILENO) != 0;
  std::fprintf(ctl.json_mode() ? stderr : stdout, "collecting wand frames for %s s%s\n",
               Text(seconds).c_str(), enter_ends ? " (Enter: finish now, Ctrl-C: cancel)" : "");
  {
    InterruptScope interrupts;
    ProgressView progress(ctl.json_mode());
    const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(seconds);
    while (std::chrono::steady_clock::now() < end && !g_interrupted) {
      pollfd fds[2] = {{ctl.client().fd(), POLLIN, 0}, {STDIN_FILENO, POLLIN, 0}};
      poll(fds, enter_ends ? 2 : 1, 200);
      Status s = ctl.client().Poll(0, [&](const json& e) { progress.Show(e); });
      if (!s.ok()) {
        progress.Finish();
        std::fprintf(stderr, "mocapctl: %s\n", s.message().c_str());
        return kExitUnreachable;
      }
      if (enter_ends && (fds[1].revents & POLLIN)) {
        std::string line;
        std::getline(std::cin, line);
        break;
      }
    }
    progress.Finish();
    if (g_interrupted) {
      std::fprintf(stderr, "mocapctl: interrupted: cancelling the calibration\n");
      status = ctl.Call("rig.calibrate.cancel", json::object(), &result);
      return status == kExitOk ? kExitDaemonError : status;
    }
  }
  status = ctl.CallInterruptible("rig.calibrate.finish", json::object(), "rig.calibrate.cancel",
                                 &result);
  if (status != kExitOk) return status;
  json applied;
  if (apply) {
    status = ctl.Call("rig.calibrate.apply", {{"version", result.value("version", json())}}, &applied);
    if (status != kExitOk) return status;
  }
  if (ctl.json_mode()) {
    if (apply) result["applied"] = applied;
    std::printf("%s\n", result.dump(2).c_str());
  } else {
    PrintCalibration(result);
    if (apply)
      std::printf("applied: triangulation uses version %s from frame %s\n",
                  Text(applied.value("version", json())).c_str(),
                  Text(applied.value("from_frame", json())).c_str());
    else
      std::printf("stored, not applied (mocapctl calibrate apply --version %s)\n",
                  Text(result.value("version", json())).c_str());
  }
  return kExitOk;
}

int Record(Ctl& ctl, const json& params) {
  json result;
  const int status = ctl.CallInterruptible("record.start", params, "record.stop", &result);
  if (Output(ctl, status, result, PrintRecording) != kExitOk) return status;
  return CoveragePassed(result) ? kExitOk : kExitCoverageFailed;
}

int Watch(Ctl& ctl, const std::vector<std::string>& streams, int decimation, long count) {
  json result;
  int status = ctl.Call("subscribe", {{"streams", streams}, {"decimation", decimation}}, &result);
  if (status != kExitOk) return status;
  if (!ctl.json_mode())
    std::printf("watching %s (every %d. frame; Ctrl-C to stop)\n",
                Join(result.value("subscribed", json())).c_str(), decimation);
  InterruptScope interrupts;
  long frames = 0;
  while (!g_interrupted && (count <= 0 || frames < count)) {
    json event;
    bool got = false;
    Status s = ctl.client().NextEvent(&event, 500, &got);
    if (!s.ok()) {
      std::fprintf(stderr, "mocapctl: %s\n", s.message().c_str());
      return kExitUnreachable;
    }
    if (!got) continue;
    const std::string kind = event.value("event", "");
    if (kind == "frame") ++frames;
    if (ctl.json_mode()) {
      std::printf("%s\n", event.dump().c_str());
    } else if (kind == "dropped") {
      std::printf("(lost %s frames: this client read too slowly)\n", Text(event.value("count", json())).c_str());
    } else if (kind == "frame") {
      std::string line = "frame " + Text(event.value("frame", json())) + "  t " +
                         Fixed(event.value("t_mid", json()), 3) + " s";
      if (event.contains("markers") && event["markers"].is_array()) {
        int occluded = 0;
        for (const auto& m : event["markers"]) occluded += m.value("occluded", false) ? 1 : 0;
        line += "  markers " + std::to_string(event["markers"].size()) + " (" +
                std::to_string(occluded) + " occluded)";
      }
      if (event.contains("points") && event["points"].is_array())
        line += "  points " + std::to_string(event["points"].size());
      if (event.contains("pose") && event["pose"].is_object())
        line += "  tracker " + Text(event["pose"].value("tracker", json()));
      if (event.contains("health") && event["health"].is_object())
        line += "  cameras " + Text(event["health"].value("cameras_connected", json())) +
                "  incomplete " + Text(event["health"].value("sets_incomplete", json()));
      std::printf("%s\n", line.c_str());
    }
    std::fflush(stdout);
  }
  return kExitOk;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"mocapctl — the operator's client of mocapd (control socket, daemon/PROTOCOL.md)"};
  app.require_subcommand(1);
  app.fallthrough();  // --json, --socket also after the subcommand
  Globals globals;
  const char* env_socket = std::getenv("MOCAPD_SOCKET");
  globals.socket = env_socket && *env_socket ? env_socket : "/run/mocapd/control.sock";
  app.add_option("--socket", globals.socket, "mocapd's control socket (default $MOCAPD_SOCKET or "
                                             "/run/mocapd/control.sock)");
  app.add_flag("--json", globals.json, "print the reply's result as JSON (for scripts)");
  app.add_option("--timeout", globals.timeout_s,
                 "seconds mocapd may stay silent before mocapctl gives up (0: for ever)")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber);

  Ctl ctl(globals);
  std::function<int()> action;
  auto simple = [&](CLI::App* cmd, const std::string& method,
                    Printer print = [](const json& r) { PrintTree(r); }) {
    cmd->callback([&, method, print] { action = [&, method, print] { return Simple(ctl, method, json::object(), print); }; });
  };

  simple(app.add_subcommand("status", "the daemon, rig, tracker, subject, recording, job"), "status",
         PrintStatus);
  // cameras [--check]
  auto* cameras = app.add_subcommand("cameras", "each camera's state and counters; --check: the rig check");
  bool cameras_check = false;
  cameras->add_flag("--check", cameras_check,
                    "check the rig (sync lock or clock fits, lost frames and packets, link "
                    "bandwidth); exit status 5 when anything fails");
  cameras->callback([&] {
    action = [&]() -> int {
      if (!cameras_check)
        return Simple(ctl, "cameras", json::object(), [](const json& r) {
          PrintTable(r.value("cameras", json()),
                     {"id", "connected", "fps", "frames", "incomplete", "dropped", "width", "height"});
        });
      json result;
      const int status = Output(ctl, ctl.Call("cameras.check", json::object(), &result), result, PrintRigCheck);
      if (status != kExitOk) return status;
      return result.value("ok", false) ? kExitOk : kExitRigCheckFailed;
    };
  });
  simple(app.add_subcommand("reload", "re-read the config file (config.reload)"), "config.reload",
         PrintReload);
  simple(app.add_subcommand("protocol", "the protocol's movements and what each must excite"),
         "protocol.show", PrintProtocol);
  simple(app.add_subcommand("stop", "end the running recording early (record.stop)"), "record.stop");
  simple(app.add_subcommand("cancel", "stop the running fit, keeping its best result (fit.cancel)"),
         "fit.cancel");
  simple(app.add_subcommand("calibrations", "the stored rig calibrations (calibration.list)"),
         "calibration.list", [](const json& r) {
           PrintTable(r.value("calibrations", json()),
                      {"version", "created_at", "reprojection_rms_px", "wand_length_error_mm", "live"});
         });
  simple(app.add_subcommand("shutdown", "stop the daemon cleanly"), "shutdown");

  // calibrate [--seconds S] [--apply] | calibrate apply [--version V] | calibrate cancel
  auto* calibrate = app.add_subcommand("calibrate", "calibrate the rig with the wand (rig.calibrate.*)");
  calibrate->require_subcommand(0, 1);
  double calibrate_seconds = 20;
  bool calibrate_apply = false;
  calibrate->add_option("--seconds", calibrate_seconds, "wand collection time (Enter ends it earlier)")
      ->capture_default_str()
      ->check(CLI::Range(1.0, 600.0));
  calibrate->add_flag("--apply", calibrate_apply, "apply the new calibration at once");
  auto* calibrate_apply_cmd = calibrate->add_subcommand("apply", "switch triangulation to a stored calibration");
  std::optional<int> calibration_version;
  calibrate_apply_cmd->add_option("--version", calibration_version, "calibration version (default: the latest)");
  auto* calibrate_cancel_cmd = calibrate->add_subcommand("cancel", "stop collecting, discard the frames");
  calibrate->callback([&] {
    if (calibrate_apply_cmd->parsed()) {
      json params = json::object();
      if (calibration_version) params["version"] = *calibration_version;
      action = [&, params] { return Simple(ctl, "rig.calibrate.apply", params, PrintApplied); };
    } else if (calibrate_cancel_cmd->parsed()) {
      action = [&] { return Simple(ctl, "rig.calibrate.cancel", json::object()); };
    } else {
      action = [&] { return Calibrate(ctl, calibrate_seconds, calibrate_apply); };
    }
  });

  // subject create NAME --height H [--model PATH] | subject select NAME | subject list
  auto* subject = app.add_subcommand("subject", "create, select and list subjects");
  subject->require_subcommand(1);
  std::string subject_name, subject_model = "default";
  double subject_height = 0;
  auto* create = subject->add_subcommand("create", "a new subject (subject.create)");
  create->add_option("name", subject_name, "the subject's name")->required();
  create->add_option("--height", subject_height, "body height (m)")->required()->check(CLI::Range(0.5, 2.5));
  create->add_option("--model", subject_model, "\"default\", or an .osim / .json model file")
      ->capture_default_str();
  create->callback([&] {
    action = [&] {
      const std::string model = subject_model == "default" ? subject_model : Absolute(subject_model);
      return Simple(ctl, "subject.create",
                    {{"name", subject_name}, {"height_m", subject_height}, {"model", model}},
                    PrintSubject);
    };
  });
  auto* select = subject->add_subcommand("select", "track this subject (subject.select)");
  select->add_option("name", subject_name, "the subject's name")->required();
  select->callback([&] {
    action = [&] { return Simple(ctl, "subject.select", {{"name", subject_name}}, PrintSubject); };
  });
  simple(subject->add_subcommand("list", "the subjects (subject.list)"), "subject.list", [](const json& r) {
    PrintTable(r.value("subjects", json()),
               {"id", "name", "height_m", "model_versions", "recordings", "selected", "created_at"});
  });

  // record MOVEMENT [--duration S] [--sim-amplitude A] [--sim-duration-scale X]
  auto* record = app.add_subcommand("record", "record one movement of the protocol (record.start)");
  std::string movement;
  std::optional<double> record_duration, sim_amplitude, sim_duration_scale;
  record->add_option("movement", movement, "the movement's name in the protocol (mocapctl protocol)")->required();
  record->add_option("--duration", record_duration, "seconds (default: the protocol's + 1 s)")
      ->check(CLI::PositiveNumber);
  record->add_option("--sim-amplitude", sim_amplitude,
                     "simulated rig: the fraction of the ranges the virtual subject reaches")
      ->check(CLI::Range(0.0, 2.0));
  record->add_option("--sim-duration-scale", sim_duration_scale,
                     "simulated rig: the virtual subject's tempo (duration scale)")
      ->check(CLI::PositiveNumber);
  record->callback([&] {
    json params = {{"movement", movement}};
    if (record_duration) params["duration_s"] = *record_duration;
    if (sim_amplitude) params["sim_amplitude"] = *sim_amplitude;
    if (sim_duration_scale) params["sim_duration_scale"] = *sim_duration_scale;
    action = [&, params] { return Record(ctl, params); };
  });

  // fit [--max-iterations N] [--groups G] [--threads T]
  auto* fit = app.add_subcommand("fit", "fit the selected subject's model to its recordings (fit.start)");
  std::optional<int> fit_iterations, fit_threads;
  std::optional<std::string> fit_groups;
  fit->add_option("--max-iterations", fit_iterations, "iteration limit")->check(CLI::PositiveNumber);
  fit->add_option("--groups", fit_groups, "parameter groups: scales,centres,axes,markers (or all, none)");
  fit->add_option("--threads", fit_threads, "worker threads (0: all cores)")->check(CLI::NonNegativeNumber);
  fit->callback([&] {
    json params = json::object();
    if (fit_iterations) params["max_iterations"] = *fit_iterations;
    if (fit_groups) params["groups"] = *fit_groups;
    if (fit_threads) params["threads"] = *fit_threads;
    action = [&, params] {
      json result;
      const int status = ctl.CallInterruptible("fit.start", params, "fit.cancel", &result);
      return Output(ctl, status, result, PrintFit);
    };
  });

  // apply [--version V]
  auto* apply = app.add_subcommand("apply", "swap a fitted model into the live tracker (model.apply)");
  std::optional<int> model_version;
  apply->add_option("--version", model_version, "model version (default: the latest)");
  apply->callback([&] {
    json params = json::object();
    if (model_version) params["version"] = *model_version;
    action = [&, params] { return Simple(ctl, "model.apply", params, PrintApplied); };
  });

  // models / recordings [--subject S]
  std::optional<std::string> list_subject;
  auto* models = app.add_subcommand("models", "the subject's model versions (model.list)");
  auto* recordings = app.add_subcommand("recordings", "the recordings (recording.list)");
  for (auto* cmd : {models, recordings})
    cmd->add_option("--subject", list_subject, "a subject's name (default: the selected one)");
  models->callback([&] {
    json params = json::object();
    if (list_subject) params["subject"] = *list_subject;
    action = [&, params] {
      return Simple(ctl, "model.list", params, [](const json& r) {
        PrintTable(r.value("models", json()), {"version", "produced_by", "created_at", "live", "fit_report"});
      });
    };
  });
  recordings->callback([&] {
    json params = json::object();
    if (list_subject) params["subject"] = *list_subject;
    action = [&, params] {
      return Simple(ctl, "recording.list", params, [](const json& r) {
        PrintTable(r.value("recordings", json()),
                   {"id", "subject", "movement", "state", "frames", "rate_hz", "coverage_ok", "started_at"});
      });
    };
  });

  // export KIND ID --format F [--out PATH]
  auto* export_cmd = app.add_subcommand("export", "export a recording, model or report");
  std::string export_kind, export_format, export_out;
  std::int64_t export_id = 0;
  export_cmd->add_option("kind", export_kind, "recording, model or report")
      ->required()
      ->check(CLI::IsMember({"recording", "model", "report"}));
  export_cmd->add_option("id", export_id, "recording id, model version or report id")->required();
  export_cmd->add_option("--format", export_format, "c3d, trc, mot, json, osim or html (a report's page)")
      ->required()
      ->check(CLI::IsMember({"c3d", "trc", "mot", "json", "osim", "html"}));
  export_cmd->add_option("--out", export_out,
                         "file for the daemon to write (default: the content to stdout; not for c3d)");
  export_cmd->callback([&] {
    action = [&]() -> int {
      json params = {{"kind", export_kind}, {"id", export_id}, {"format", export_format}};
      if (export_out.empty() && export_format == "c3d") {
        std::fprintf(stderr, "mocapctl: export --format c3d is binary: give --out PATH\n");
        return kExitUsage;
      }
      if (export_out.empty())
        params["inline"] = true;
      else
        params["path"] = Absolute(export_out);
      json result;
      const int status = ctl.Call("export", params, &result);
      return Output(ctl, status, result, [](const json& r) {
        if (r.contains("content") && r["content"].is_string()) {
          const auto& content = r["content"].get_ref<const std::string&>();
          std::fwrite(content.data(), 1, content.size(), stdout);
        } else {
          std::printf("wrote %s (%s bytes)\n", Text(r.value("path", json())).c_str(),
                      Text(r.value("bytes", json())).c_str());
        }
      });
    };
  });

  // watch [--stream S]... [--decimate N] [--count N]
  auto* watch = app.add_subcommand("watch", "print the live stream (subscribe)");
  std::vector<std::string> streams;
  int decimation = 1;
  long watch_count = 0;
  watch->add_option("--stream", streams, "markers, points, pose, status (repeatable; default markers)")
      ->check(CLI::IsMember({"markers", "points", "pose", "status"}));
  watch->add_option("--decimate", decimation, "every n-th frame")->capture_default_str()->check(CLI::PositiveNumber);
  watch->add_option("--count", watch_count, "stop after this many frames (0: until Ctrl-C)")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber);
  watch->callback([&] {
    if (streams.empty()) streams = {"markers"};
    action = [&] { return Watch(ctl, streams, decimation, watch_count); };
  });

  // raw METHOD [PARAMS]
  auto* raw = app.add_subcommand("raw", "send any request; prints the result as JSON");
  std::string raw_method, raw_params = "{}";
  raw->add_option("method", raw_method, "the method (daemon/PROTOCOL.md)")->required();
  raw->add_option("params", raw_params, "its params, a JSON object")->capture_default_str();
  raw->callback([&] {
    action = [&]() -> int {
      const json params = json::parse(raw_params, nullptr, false);
      if (!params.is_object()) {
        std::fprintf(stderr, "mocapctl raw: params: expected a JSON object, got: %s\n", raw_params.c_str());
        return kExitUsage;
      }
      json result;
      const int status = ctl.Call(raw_method, params, &result);
      if (status == kExitOk) std::printf("%s\n", result.dump(2).c_str());
      return status;
    };
  });

  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    // --help exits 0; a usage error exits 2 (as getopt-style tools do).
    return app.exit(e) == 0 ? kExitOk : kExitUsage;
  }
  if (!action) return kExitUsage;
  try {
    return action();
  } catch (const json::exception& e) {
    // A reply of another shape than daemon/PROTOCOL.md says (a newer or broken daemon).
    std::fprintf(stderr, "mocapctl: unexpected reply from mocapd: %s\n", e.what());
    return kExitUnreachable;
  }
}
