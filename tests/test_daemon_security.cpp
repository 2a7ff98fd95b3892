// mocapd's security bounds (issue 17, "Security"), against the real executable on a small
// simulated rig:
//  - a client outside the control group may read but cannot change state through ANY method:
//    every method PROTOCOL.md documents is sent by `nobody`, each state-changing one must be
//    refused `forbidden`, and afterwards root sees the state exactly as before (subjects, the
//    selected subject, models, calibrations, recordings, cameras, the config, the daemon alive);
//  - `export` writes only beneath the directories the config allows: `..`, symlinks, absolute
//    paths elsewhere and the daemon's own database are refused `forbidden` and nothing is written;
//  - random requests (every method, random params of random types) dispatched into the real
//    daemon: each is answered with a result or a documented error, never `internal` (a type the
//    method's checks missed), and the daemon stays up (fuzz/fuzz_control.cpp fuzzes the framing).
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <map>
#include <random>
#include <regex>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "daemon/store.h"
#include "tests/daemon_test_util.h"

namespace mocap {
namespace {

namespace fs = std::filesystem;
using daemon::ControlClient;
using daemon::ControlReply;
using nlohmann::json;
using testing::DaemonProcess;

ControlReply Send(ControlClient* c, const std::string& method, const json& params) {
  ControlReply r;
  const Status s = c->Call(method, params, &r);
  EXPECT_TRUE(s.ok()) << method << ": " << s.message();
  return r;
}

json MustCall(ControlClient* c, const std::string& method, const json& params = json::object()) {
  ControlReply r = Send(c, method, params);
  EXPECT_TRUE(r.ok()) << method << ": " << r.error_code << " " << r.error_message;
  return r.result;
}

// Every method of PROTOCOL.md ("### name").
std::set<std::string> DocumentedMethods() {
  std::ifstream doc(MOCAP_SOURCE_DIR "/daemon/PROTOCOL.md");
  std::set<std::string> methods;
  const std::regex method_re("^### ([a-z.]+)");
  for (std::string line; std::getline(doc, line);) {
    std::smatch m;
    if (std::regex_search(line, m, method_re)) methods.insert(m[1]);
  }
  return methods;
}

// What root sees of the daemon's state: everything a state-changing method could alter.
json StateSnapshot(ControlClient* c) {
  json status = MustCall(c, "status");
  json cameras = MustCall(c, "cameras")["cameras"];
  json connected = json::array();
  for (const json& cam : cameras) connected.push_back(cam["connected"]);
  return {{"subjects", MustCall(c, "subject.list")["subjects"]},
          {"models", MustCall(c, "model.list")["models"]},
          {"calibrations", MustCall(c, "calibration.list")["calibrations"]},
          {"recordings", MustCall(c, "recording.list")["recordings"]},
          {"selected", status["subject"]},
          {"state", status["state"]},
          {"connected", connected}};
}

class DaemonSecurity : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = testing::MakeTempDir("mocapd-security");
    ASSERT_FALSE(dir_.empty());
    // mkdtemp's 0700 would keep `nobody` from the socket's directory.
    chmod(dir_.c_str(), 0755);
    allowed_ = dir_ + "/exports";
    outside_ = dir_ + "/outside";
    fs::create_directories(allowed_);
    fs::create_directories(outside_);
    // A small rig: this test needs the daemon's methods, not its cameras' load.
    toml_ = "[rig]\nsimulated = 2\nwidth = 640\nheight = 512\nrate = 100\n";
    daemon_ = std::make_unique<DaemonProcess>(dir_, toml_);
    daemon_->SetExportDirs({allowed_});
    const Status started = daemon_->Start();
    ASSERT_TRUE(started.ok()) << started.message();
    chmod(daemon_->socket().c_str(), 0666);
    ASSERT_TRUE(daemon_->Connect(&root_).ok());
    ASSERT_TRUE(root_->hello().may_control);  // the test runs as root
    MustCall(root_.get(), "subject.create", {{"name", "A"}, {"height_m", 1.7}});
    MustCall(root_.get(), "subject.create", {{"name", "B"}, {"height_m", 1.8}});
    MustCall(root_.get(), "subject.select", {{"name", "A"}});
  }
  void TearDown() override {
    root_.reset();
    if (daemon_) daemon_->Stop();
    fs::remove_all(dir_);
  }

  std::string dir_, allowed_, outside_, toml_;
  std::unique_ptr<DaemonProcess> daemon_;
  std::unique_ptr<ControlClient> root_;
};

TEST_F(DaemonSecurity, OutsideTheControlGroupNoMethodChangesState) {
  // Requests root could make: valid params, so that only the client's rights stop them.
  const std::map<std::string, json> params = {
      {"status", json::object()},
      {"cameras", json::object()},
      {"cameras.check", json::object()},
      {"config.reload", json::object()},
      {"rig.calibrate.start", {{"seconds", 5}}},
      {"rig.calibrate.finish", json::object()},
      {"rig.calibrate.cancel", json::object()},
      {"rig.calibrate.apply", json::object()},
      {"calibration.list", json::object()},
      {"subject.create", {{"name", "Intruder"}, {"height_m", 1.7}}},
      {"subject.select", {{"name", "B"}}},
      {"subject.list", json::object()},
      {"protocol.show", json::object()},
      {"record.start", {{"movement", "static"}}},
      {"record.stop", json::object()},
      {"recording.list", json::object()},
      {"fit.start", json::object()},
      {"fit.cancel", json::object()},
      {"model.list", json::object()},
      {"model.apply", {{"version", 1}}},
      {"export", {{"kind", "model"}, {"id", 1}, {"format", "json"}, {"path", allowed_ + "/by-nobody.json"}}},
      {"subscribe", {{"streams", {"status"}}, {"decimation", 100}}},
      {"unsubscribe", json::object()},
      {"sim.camera", {{"camera", 0}, {"present", false}}},
      {"shutdown", json::object()},
  };
  // PROTOCOL.md's list of what anyone connected may do; everything else needs control.
  const std::set<std::string> read_only = {"status",         "cameras",        "cameras.check",
                                           "protocol.show",
                                           "subject.list",   "model.list",     "recording.list",
                                           "calibration.list", "subscribe",    "unsubscribe"};
  const std::set<std::string> documented = DocumentedMethods();
  ASSERT_GT(documented.size(), 20u);
  for (const std::string& m : documented) ASSERT_TRUE(params.count(m)) << "a method this test does not send: " << m;

  // A changed config file on disk: a reload by `nobody` must not apply it (root's reload below does).
  std::ofstream(dir_ + "/mocapd.toml") << toml_ << "[control]\nmax_clients = 32\n";
  const json before = StateSnapshot(root_.get());

  // `nobody` sends every method, then an inline export (read-only); each reply as "method code".
  const std::string got = testing::RunAsUser("nobody", [&] {
    std::unique_ptr<ControlClient> u;
    daemon::ControlClientOptions o;
    o.socket_path = daemon_->socket();
    o.reply_timeout_ms = 20000;
    if (!ControlClient::Connect(o, &u).ok()) return std::string("connect failed\n");
    std::string out = std::string("hello ") + (u->hello().may_control ? "control" : "read") + "\n";
    auto send = [&](const std::string& name, const std::string& method, const json& p) {
      ControlReply r;
      const Status s = u->Call(method, p, &r);
      out += name + " " + (!s ? "io" : r.ok() ? "ok" : r.error_code) + "\n";
    };
    for (const auto& [method, p] : params) send(method, method, p);
    send("export.inline", "export", {{"kind", "model"}, {"id", 1}, {"format", "json"}, {"inline", true}});
    return out;
  });

  std::map<std::string, std::string> code;
  std::istringstream lines(got);
  for (std::string name, c; lines >> name >> c;) code[name] = c;
  ASSERT_EQ(code["hello"], "read") << got;
  for (const auto& [method, p] : params) {
    if (read_only.count(method))
      EXPECT_EQ(code[method], "ok") << method << " is read-only; " << got;
    else
      EXPECT_EQ(code[method], "forbidden") << method << " changes state; " << got;
  }
  EXPECT_EQ(code["export.inline"], "ok") << got;  // exporting back over the socket only reads

  // Nothing changed: the same state, no file written, the camera still there, the daemon alive.
  ASSERT_TRUE(daemon_->running());
  EXPECT_EQ(StateSnapshot(root_.get()), before);
  EXPECT_FALSE(fs::exists(allowed_ + "/by-nobody.json"));
  EXPECT_EQ(Send(root_.get(), "rig.calibrate.cancel", json::object()).error_code, "conflict");  // not collecting
  // The reload `nobody` asked for was not applied: root's is the one that applies the change.
  EXPECT_EQ(MustCall(root_.get(), "config.reload")["applied"], json::array({"control.max_clients"}));
}

TEST_F(DaemonSecurity, ExportPathsCannotEscapeTheAllowedDirectories) {
  const json model = {{"kind", "model"}, {"id", 1}, {"format", "json"}};
  auto export_to = [&](const std::string& path) {
    json p = model;
    p["path"] = path;
    return Send(root_.get(), "export", p);
  };
  // Allowed: written, the path in the reply.
  ControlReply ok = export_to(allowed_ + "/a.model.json");
  ASSERT_TRUE(ok.ok()) << ok.error_code << " " << ok.error_message;
  EXPECT_EQ(ok.result["path"], allowed_ + "/a.model.json");
  EXPECT_GT(fs::file_size(allowed_ + "/a.model.json"), 100u);

  const std::string db = daemon_->state_dir() + "/" + daemon::Store::kFileName;
  const auto db_size = fs::file_size(db);
  fs::create_directory_symlink(outside_, allowed_ + "/link");
  std::ofstream(outside_ + "/precious") << "precious";
  fs::create_symlink(outside_ + "/precious", allowed_ + "/precious.json");
  for (const std::string& path : std::vector<std::string>{
        allowed_ + "/../outside/x.json",       // .. out of the allowed directory
        outside_ + "/x.json",                   // absolute, elsewhere
        std::string("/etc/mocapd-security-test.json"),  // absolute, the system's
        allowed_ + "/link/x.json",              // a directory symlink planted inside
        allowed_ + "/precious.json",            // a file symlink to a file outside
        db,                                     // the daemon's own database
        allowed_ + "/../state/mocapd.sqlite-wal"}) {
    ControlReply r = export_to(path);
    EXPECT_EQ(r.error_code, "forbidden") << path << ": " << r.error_message;
    EXPECT_NE(r.error_message.find(allowed_), std::string::npos) << r.error_message;  // says where
  }
  EXPECT_FALSE(fs::exists(outside_ + "/x.json"));
  EXPECT_FALSE(fs::exists("/etc/mocapd-security-test.json"));
  std::ifstream precious(outside_ + "/precious");
  EXPECT_EQ(std::string(std::istreambuf_iterator<char>(precious), {}), "precious");
  EXPECT_EQ(fs::file_size(db), db_size);
  // Bad formats never reach the staging file's name.
  json bad = model;
  bad["format"] = "json/../../x";
  bad["inline"] = true;
  EXPECT_EQ(Send(root_.get(), "export", bad).error_code, "invalid_params");
  // The daemon is intact and its store readable.
  EXPECT_EQ(MustCall(root_.get(), "model.list")["models"].size(), 1u);
}

// A random JSON value of a random type, biased to the edges a parameter check must handle.
json RandomValue(std::mt19937& rng, int depth = 0) {
  static const std::vector<std::string> kStrings = {
      "", "S01", "A", "default", "squats", "static", "c3d", "json", "html", "osim", "recording",
      "model", "report", "markers", "points", "pose", "status", "../../etc/passwd", "/etc/passwd",
      "/nonexistent.osim", "\u00e9\u4e2d", std::string(5000, 'x'), "scales,centres", "null", "1e999"};
  switch (std::uniform_int_distribution<int>(0, depth > 1 ? 6 : 8)(rng)) {
    case 0: return nullptr;
    case 1: return std::uniform_int_distribution<int>(0, 1)(rng) == 1;
    case 2: {
      static const std::vector<std::int64_t> kInts = {0, 1, 2, 3, 5, -1, -3, 7, 600, 601, 100000,
                                                      INT32_MAX, INT64_MAX, INT64_MIN};
      return kInts[std::uniform_int_distribution<std::size_t>(0, kInts.size() - 1)(rng)];
    }
    case 3: {
      static const std::vector<double> kReals = {0.0, -0.0, 0.5, 1.7, 2.6, 1e-300, 1e308, -1e308,
                                                 0.1, 100.5};
      return kReals[std::uniform_int_distribution<std::size_t>(0, kReals.size() - 1)(rng)];
    }
    case 4:
    case 5:
    case 6: return kStrings[std::uniform_int_distribution<std::size_t>(0, kStrings.size() - 1)(rng)];
    case 7: {
      json a = json::array();
      for (int i = std::uniform_int_distribution<int>(0, 3)(rng); i > 0; --i) a.push_back(RandomValue(rng, depth + 1));
      return a;
    }
    default: {
      json o = json::object();
      for (int i = std::uniform_int_distribution<int>(0, 2)(rng); i > 0; --i) o["k" + std::to_string(i)] = RandomValue(rng, depth + 1);
      return o;
    }
  }
}

TEST_F(DaemonSecurity, RandomRequestsAreEachAnsweredAndNeverAnInternalError) {
  // Every documented method but shutdown, and some that do not exist; params with the keys the
  // methods read (and others), each a random value.
  std::vector<std::string> methods;
  for (const std::string& m : DocumentedMethods())
    if (m != "shutdown") methods.push_back(m);
  methods.push_back("no.such");
  methods.push_back("");
  const std::vector<std::string> keys = {
      "name", "height_m", "model", "version", "id", "kind", "format", "path", "inline", "subject",
      "movement", "duration_s", "sim_amplitude", "sim_duration_scale", "seconds", "streams",
      "decimation", "camera", "present", "max_iterations", "groups", "threads", "other"};
  std::set<std::string> codes = {"parse_error", "invalid_request", "unknown_method", "invalid_params",
                                 "forbidden", "not_found", "conflict", "busy", "unavailable",
                                 "failed", "cancelled"};  // PROTOCOL.md's, but `internal`
  std::mt19937 rng(17);
  std::map<std::string, int> seen;
  const int requests = 4000;
  for (int i = 0; i < requests; ++i) {
    const std::string method = methods[std::uniform_int_distribution<std::size_t>(0, methods.size() - 1)(rng)];
    json params = json::object();
    for (int k = std::uniform_int_distribution<int>(0, 4)(rng); k > 0; --k)
      params[keys[std::uniform_int_distribution<std::size_t>(0, keys.size() - 1)(rng)]] = RandomValue(rng);
    ControlReply r;
    const Status s = root_->Call(method, params, &r);
    ASSERT_TRUE(s.ok()) << "request " << i << " " << method << " " << params.dump().substr(0, 300)
                        << ": no reply: " << s.message();
    if (!r.ok()) {
      EXPECT_TRUE(codes.count(r.error_code)) << method << " " << params.dump().substr(0, 300) << " -> "
                                             << r.error_code << ": " << r.error_message;
      EXPECT_FALSE(r.error_message.empty());
    }
    ++seen[r.ok() ? "ok" : r.error_code];
    // A recording or a collection a random request started ends, so the next ones see the rig.
    if (method == "record.start" || method == "rig.calibrate.start") {
      ControlReply ignored;
      (void)root_->Call("record.stop", json::object(), &ignored);
      (void)root_->Call("rig.calibrate.cancel", json::object(), &ignored);
    }
  }
  std::string summary;
  for (const auto& [code, n] : seen) summary += code + " " + std::to_string(n) + ", ";
  std::printf("%d random requests: %s\n", requests, summary.c_str());
  EXPECT_GT(seen["ok"], 50);               // the generator reaches the methods' work...
  EXPECT_GT(seen["invalid_params"], 200);  // ... and their checks
  ASSERT_TRUE(daemon_->running());
  EXPECT_EQ(MustCall(root_.get(), "status")["state"], "running");
}

}  // namespace
}  // namespace mocap
