// mocapctl (daemon/mocapctl_main.cpp) against a scripted fake mocapd (tests/fake_mocapd.h): the
// requests each subcommand sends, its output (human and --json), progress lines when the output
// is not a terminal, and its exit status on every kind of failure.
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <fcntl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <csignal>
#include <thread>

#include <array>
#include <cstdio>
#include <filesystem>
#include <string>
#include <vector>

#include "fake_mocapd.h"
#include "file_test_util.h"

namespace mocap {
namespace {

using json = nlohmann::json;
using ::testing::ElementsAre;
using ::testing::HasSubstr;
using testutil::ErrorLine;
using testutil::ResultLine;

struct CtlResult {
  int status;
  std::string out, err;
};

// Runs mocapctl with `args` (a shell command line) against the socket `socket`.
CtlResult RunCtl(const std::string& socket, const std::string& args) {
  const std::string err_path = testutil::TmpPath("mocapctl", ".stderr");
  const std::string cmd = std::string(MOCAPCTL_TOOL) + " --socket " + socket + " " + args +
                          " </dev/null 2>" + err_path;
  FILE* pipe = popen(cmd.c_str(), "r");
  std::string out;
  std::array<char, 4096> buf;
  while (pipe && fgets(buf.data(), buf.size(), pipe)) out += buf.data();
  const int rc = pipe ? pclose(pipe) : -1;
  return {WIFEXITED(rc) ? WEXITSTATUS(rc) : -1, out, testutil::ReadBytes(err_path)};
}

std::string SocketPath() { return testutil::ShortSocketPath(); }

std::string Progress(const json& request, double fraction, const std::string& message) {
  return json({{"event", "progress"}, {"id", request["id"]}, {"job", request["method"]},
               {"fraction", fraction}, {"eta_s", 3.0}, {"message", message}})
      .dump();
}

TEST(Mocapctl, NotRunningExits3WithTheReason) {
  const std::string socket = SocketPath();
  std::filesystem::remove(socket);
  CtlResult r = RunCtl(socket, "status");
  EXPECT_EQ(r.status, 3);
  EXPECT_EQ(r.err, "mocapctl: mocapd is not running (no socket at " + socket + ")\n");
  EXPECT_EQ(r.out, "");
}

TEST(Mocapctl, UsageErrorsExit2WithoutConnecting) {
  testutil::ScriptedMocapd daemon(SocketPath(), [](const json& r) {
    return std::vector<std::string>{ResultLine(r, json::object())};
  });
  EXPECT_EQ(RunCtl(SocketPath(), "record").status, 2);                         // no movement
  EXPECT_EQ(RunCtl(SocketPath(), "subject create S01").status, 2);              // no --height
  EXPECT_EQ(RunCtl(SocketPath(), "watch --stream video").status, 2);            // no such stream
  EXPECT_EQ(RunCtl(SocketPath(), "export recording 5 --format c3d").status, 2);  // binary inline
  CtlResult r = RunCtl(SocketPath(), "raw status '{not json'");
  EXPECT_EQ(r.status, 2);
  EXPECT_THAT(r.err, HasSubstr("params: expected a JSON object, got: {not json"));
  EXPECT_TRUE(daemon.requests().empty());
}

TEST(Mocapctl, StatusHumanAndJson) {
  const json status = {{"state", "running"}, {"version", "0.1.0"}, {"uptime_s", 12.6}, {"clients", 2},
                       {"rig", {{"simulated", true}, {"cameras", 8}, {"rate_hz", 200}, {"calibration_version", nullptr}}},
                       {"subject", nullptr}, {"model_version", nullptr}, {"live_model_version", nullptr},
                       {"recording", nullptr}, {"job", nullptr}};
  testutil::ScriptedMocapd daemon(SocketPath(), [&](const json& r) {
    return std::vector<std::string>{ResultLine(r, status)};
  });
  CtlResult human = RunCtl(SocketPath(), "status");
  EXPECT_EQ(human.status, 0) << human.err;
  EXPECT_THAT(human.out, HasSubstr("mocapd 0.1.0, running, up 13 s, 2 clients\n"));
  EXPECT_THAT(human.out, HasSubstr("rig: 8 cameras (simulated) at 200 Hz, calibration none\n"));
  EXPECT_THAT(human.out, HasSubstr("subject: none, model version - (live -)\n"));
  // --json after the subcommand too; stdout is exactly the result.
  CtlResult machine = RunCtl(SocketPath(), "status --json");
  EXPECT_EQ(machine.status, 0) << machine.err;
  EXPECT_EQ(json::parse(machine.out), status);
  EXPECT_THAT(daemon.methods(), ElementsAre("status", "status"));
}

// cameras --check: the rig check's report for people (each camera's sync and frames, each link's
// budget, every problem) and the exit status its verdict gives: 0 ok, 5 failed.
TEST(Mocapctl, CamerasCheckPrintsTheReportAndExits5WhenItFails) {
  json report = {
      {"ok", true}, {"problems", json::array()}, {"rate_hz", 200},
      {"sync", {{"mode", "free-run"}, {"median_offset_ms", 12.0}}},
      {"cameras", {{{"id", "cam0"}, {"ok", true}, {"problems", json::array()}, {"link", "nic0"},
                    {"sync", {{"mode", "free-run"}, {"offset_from_rig_ms", 3.0004}, {"clock_drift_ppm", 99.87},
                              {"clock_residual_us", 17.2}}},
                    {"frames", {{"complete", 2000}, {"incomplete", 1}, {"underruns", 0}, {"not_received", 3}}},
                    {"packets", {{"resent", 4}, {"missing", 5}}}}}},
      {"links", {{{"link", "nic0"}, {"interface", "gige"}, {"cameras", {"cam0"}}, {"capacity_mb_s", 125.0},
                  {"needed_mb_s", 110.25}, {"headroom_mb_s", 14.75}, {"ok", true}}}},
      {"sets", {{"total", 2000}}}};
  testutil::ScriptedMocapd daemon(SocketPath(), [&](const json& r) {
    return std::vector<std::string>{ResultLine(r, report)};
  });
  CtlResult ok = RunCtl(SocketPath(), "cameras --check");
  EXPECT_EQ(ok.status, 0) << ok.err;
  EXPECT_THAT(ok.out, HasSubstr("sync: free-run\n"));
  EXPECT_THAT(ok.out, HasSubstr("cam0  ok    offset 3.000 ms from the rig, drift 99.9 ppm, residual 17 us  "
                                "frames 2000, incomplete 1, underruns 0, not received 3, packets resent 4 missing 5\n"));
  EXPECT_THAT(ok.out, HasSubstr("link nic0 (gige, 1 cameras): needs 110.2 of 125.0 MB/s, headroom 14.8 MB/s\n"));
  EXPECT_THAT(ok.out, HasSubstr("rig check: ok\n"));
  report["ok"] = false;
  report["problems"] = {"link 'nic0' (gige): over"};
  report["links"][0]["ok"] = false;
  CtlResult failed = RunCtl(SocketPath(), "cameras --check");
  EXPECT_EQ(failed.status, 5) << failed.err;
  EXPECT_THAT(failed.out, HasSubstr("OVER BUDGET\n"));
  EXPECT_THAT(failed.out, HasSubstr("problem: link 'nic0' (gige): over\nrig check: FAILED\n"));
  CtlResult machine = RunCtl(SocketPath(), "--json cameras --check");
  EXPECT_EQ(machine.status, 5);
  EXPECT_EQ(json::parse(machine.out), report);
  EXPECT_THAT(daemon.methods(), ElementsAre("cameras.check", "cameras.check", "cameras.check"));
}

TEST(Mocapctl, ADaemonErrorExits1WithCodeAndMessage) {
  testutil::ScriptedMocapd daemon(SocketPath(), [](const json& r) {
    return std::vector<std::string>{ErrorLine(r, "forbidden", "subject.select needs group mocap")};
  });
  CtlResult r = RunCtl(SocketPath(), "subject select S01");
  EXPECT_EQ(r.status, 1);
  EXPECT_EQ(r.err, "mocapd: forbidden: subject.select needs group mocap\n");
  CtlResult j = RunCtl(SocketPath(), "--json subject select S01");
  EXPECT_EQ(j.status, 1);
  EXPECT_EQ(json::parse(j.out)["error"]["code"], "forbidden");
  ASSERT_EQ(daemon.requests().size(), 2u);
  EXPECT_EQ(daemon.requests()[0]["params"], json({{"name", "S01"}}));
}

TEST(Mocapctl, ASilentOrVanishedDaemonExits3) {
  testutil::ScriptedMocapd daemon(SocketPath(), [](const json& r) -> std::vector<std::string> {
    if (r["method"] == "fit.start") return {Progress(r, 0.5, "half way"), "sleep:1000"};
    return {Progress(r, 0.5, "half way"), "close"};
  });
  CtlResult r = RunCtl(SocketPath(), "--timeout 0.3 fit");
  EXPECT_EQ(r.status, 3);
  EXPECT_EQ(r.err, "mocapctl: mocapd sent nothing for 0.3 s while fit.start waited for its reply\n");
  EXPECT_EQ(r.out, "half way\n");
  r = RunCtl(SocketPath(), "record squats");
  EXPECT_EQ(r.status, 3);
  EXPECT_EQ(r.err, "mocapctl: mocapd closed the connection before replying to record.start\n");
  r = RunCtl(SocketPath(), "models");
  EXPECT_EQ(r.status, 3);
  EXPECT_EQ(r.err, "mocapctl: mocapd closed the connection before replying to request 1 (model.list)\n");
}

TEST(Mocapctl, RecordShowsProgressLinesAndExits4WhenTheCoverageFails) {
  const json result = {
      {"recording", 5}, {"movement", "squats"}, {"frames", 1400}, {"seconds", 7.0},
      {"tracking_fraction", 0.998},
      {"coverage", {{"ok", false},
                    {"excitations", {{{"coordinate", "hip_flexion_l"}, {"min_deg", 0}, {"max_deg", 90},
                                      {"reached_min_deg", 1.2}, {"reached_max_deg", 38.0},
                                      {"required", true}, {"ok", false}}}}}},
      {"losses", {{"missing_frames", 3}, {"sets_not_exposed", 3}, {"sets_dropped", 0},
                  {"recorder_dropped", 0}}},
      {"advice", "repeat squats: hip_flexion_l reached 38° of 90°"}};
  testutil::ScriptedMocapd daemon(SocketPath(), [&](const json& r) {
    return std::vector<std::string>{Progress(r, 0.5, "squats: 3.5 of 7.0 s"),
                                    Progress(r, 1.0, "squats: 7.0 of 7.0 s"), ResultLine(r, result)};
  });
  CtlResult r = RunCtl(SocketPath(), "record squats --duration 7 --sim-amplitude 0.4");
  EXPECT_EQ(r.status, 4) << r.err;
  // Not a terminal: one plain line per progress event, before the result.
  EXPECT_THAT(r.out, HasSubstr("squats: 3.5 of 7.0 s\nsquats: 7.0 of 7.0 s\nrecording 5 (squats): "
                               "1400 frames, 7.00 s, tracking 99.8%\n"));
  EXPECT_THAT(r.out, HasSubstr("hip_flexion_l  0 .. 90"));
  EXPECT_THAT(r.out, HasSubstr("1.2 .. 38.0"));
  // Frames missing from the take are said, with where they went.
  EXPECT_THAT(r.out, HasSubstr("coverage: NOT passed\nframes missing: 3 (meanwhile 3 sets not exposed "
                               "by any camera, 0 dropped by mocapd, 0 refused by the recorder)\n"
                               "repeat squats: hip_flexion_l reached 38° of 90°\n"));
  ASSERT_EQ(daemon.requests().size(), 1u);
  EXPECT_EQ(daemon.requests()[0]["method"], "record.start");
  EXPECT_EQ(daemon.requests()[0]["params"],
            json({{"movement", "squats"}, {"duration_s", 7.0}, {"sim_amplitude", 0.4}}));
  // --json: the result on stdout, the progress on stderr.
  CtlResult j = RunCtl(SocketPath(), "--json record squats");
  EXPECT_EQ(j.status, 4);
  EXPECT_EQ(json::parse(j.out), result);
  EXPECT_THAT(j.err, HasSubstr("squats: 3.5 of 7.0 s\n"));
}

TEST(Mocapctl, CtrlCDuringARecordingStopsItAndPrintsWhatWasKept) {
  const json kept = {{"recording", 5}, {"movement", "squats"}, {"frames", 300}, {"seconds", 1.5},
                     {"coverage", {{"ok", true}, {"excitations", json::array()}}}};
  testutil::ScriptedMocapd daemon(SocketPath(), [&](const json& r) -> std::vector<std::string> {
    if (r["method"] == "record.start") return {Progress(r, 0.2, "squats: 1.5 of 7.0 s")};
    // The stop's reply, then the recording's (request 1), as mocapd sends them.
    return {ResultLine(r, {{"stopped", 5}}), ResultLine(json({{"id", 1}}), kept)};
  });
  const std::string out_path = testutil::TmpPath("mocapctl", ".out");
  const std::string socket = SocketPath();
  const pid_t pid = fork();
  ASSERT_GE(pid, 0);
  if (pid == 0) {
    const int out = open(out_path.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    dup2(out, STDOUT_FILENO);
    dup2(out, STDERR_FILENO);
    execl(MOCAPCTL_TOOL, MOCAPCTL_TOOL, "--socket", socket.c_str(), "record", "squats", nullptr);
    _exit(127);
  }
  // Once the recording runs, the operator presses Ctrl-C (mocapctl catches it from before it
  // sends the request).
  for (int i = 0; i < 500 && daemon.requests().empty(); ++i)
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  ASSERT_FALSE(daemon.requests().empty());
  kill(pid, SIGINT);
  int status = 0;
  ASSERT_EQ(waitpid(pid, &status, 0), pid);
  const std::string out = testutil::ReadBytes(out_path);
  ASSERT_TRUE(WIFEXITED(status)) << out;
  EXPECT_EQ(WEXITSTATUS(status), 0) << out;
  EXPECT_THAT(daemon.methods(), ElementsAre("record.start", "record.stop"));
  EXPECT_THAT(out, HasSubstr("mocapctl: interrupted: asking mocapd to stop (record.stop)\n"));
  EXPECT_THAT(out, HasSubstr("recording 5 (squats): 300 frames, 1.50 s"));
  EXPECT_THAT(out, HasSubstr("coverage: passed\n"));
}

TEST(Mocapctl, CalibrateCollectsFinishesAndApplies) {
  testutil::ScriptedMocapd daemon(SocketPath(), [&](const json& r) -> std::vector<std::string> {
    const std::string method = r["method"];
    if (method == "rig.calibrate.start")
      return {ResultLine(r, {{"collecting", true}, {"seconds", 1}}),
              Progress(r, 0.5, "collect: 100 frames")};
    if (method == "rig.calibrate.finish")
      return {Progress(r, 0.3, "iteration 1: cost 12.5"), Progress(r, 0.9, "iteration 2: cost 3.1"),
              ResultLine(r, {{"version", 3}, {"reprojection_rms_px", 0.1234}, {"wand_length_error_mm", 0.21},
                             {"wand_frames", 900}, {"cameras", json::array()}})};
    if (method == "rig.calibrate.apply") return {ResultLine(r, {{"version", 3}, {"from_frame", 4242}})};
    return {ErrorLine(r, "unknown_method", method)};
  });
  CtlResult r = RunCtl(SocketPath(), "calibrate --seconds 1 --apply");
  EXPECT_EQ(r.status, 0) << r.err;
  EXPECT_THAT(daemon.methods(), ElementsAre("rig.calibrate.start", "rig.calibrate.finish", "rig.calibrate.apply"));
  EXPECT_EQ(daemon.requests()[0]["params"], json({{"seconds", 1.0}}));
  EXPECT_EQ(daemon.requests()[2]["params"], json({{"version", 3}}));
  EXPECT_THAT(r.out, HasSubstr("collecting wand frames for 1 s\ncollect: 100 frames\n"
                               "iteration 1: cost 12.5\niteration 2: cost 3.1\n"
                               "rig calibration version 3: reprojection RMS 0.123 px, wand length "
                               "error 0.21 mm, 900 wand frames\n"));
  EXPECT_THAT(r.out, HasSubstr("applied: triangulation uses version 3 from frame 4242\n"));

  CtlResult apply = RunCtl(SocketPath(), "calibrate apply --version 2");
  EXPECT_EQ(apply.status, 0) << apply.err;
  EXPECT_EQ(daemon.requests().back()["params"], json({{"version", 2}}));
}

TEST(Mocapctl, RequestsCarryTheirParams) {
  testutil::ScriptedMocapd daemon(SocketPath(), [](const json& r) {
    if (r["method"] == "export")
      return std::vector<std::string>{ResultLine(r, {{"content", "PathFileType\t4\n"}, {"bytes", 15}})};
    return std::vector<std::string>{ResultLine(r, json::object())};
  });
  const std::string cwd = std::filesystem::current_path().string();
  EXPECT_EQ(RunCtl(SocketPath(), "subject create S01 --height 1.8 --model models/s01.osim").status, 0);
  EXPECT_EQ(RunCtl(SocketPath(), "fit --max-iterations 30 --groups scales,centres").status, 0);
  EXPECT_EQ(RunCtl(SocketPath(), "apply --version 4").status, 0);
  CtlResult exported = RunCtl(SocketPath(), "export recording 5 --format trc");
  EXPECT_EQ(exported.status, 0);
  EXPECT_EQ(exported.out, "PathFileType\t4\n");
  EXPECT_EQ(RunCtl(SocketPath(), "export model 2 --format json --out out/m.json").status, 0);
  EXPECT_EQ(RunCtl(SocketPath(), "raw model.list '{\"subject\":\"S01\"}'").status, 0);
  const auto requests = daemon.requests();
  ASSERT_EQ(requests.size(), 6u);
  EXPECT_EQ(requests[0]["method"], "subject.create");
  EXPECT_EQ(requests[0]["params"],
            json({{"name", "S01"}, {"height_m", 1.8}, {"model", cwd + "/models/s01.osim"}}));
  EXPECT_EQ(requests[1]["params"], json({{"max_iterations", 30}, {"groups", "scales,centres"}}));
  EXPECT_EQ(requests[2]["method"], "model.apply");
  EXPECT_EQ(requests[2]["params"], json({{"version", 4}}));
  EXPECT_EQ(requests[3]["params"],
            json({{"kind", "recording"}, {"id", 5}, {"format", "trc"}, {"inline", true}}));
  EXPECT_EQ(requests[4]["params"],
            json({{"kind", "model"}, {"id", 2}, {"format", "json"}, {"path", cwd + "/out/m.json"}}));
  EXPECT_EQ(requests[5]["method"], "model.list");
  EXPECT_EQ(requests[5]["params"], json({{"subject", "S01"}}));
}

TEST(Mocapctl, HumanLayoutsOfReloadProtocolAndApply) {
  testutil::ScriptedMocapd daemon(SocketPath(), [](const json& r) -> std::vector<std::string> {
    const std::string method = r["method"];
    if (method == "config.reload")
      return {ResultLine(r, {{"reloaded", true}, {"applied", {"control.max_clients", "control.group"}},
                             {"needs_restart", {"rig.rate"}}})};
    if (method == "protocol.show")
      return {ResultLine(r, {{"name", "full body"},
                             {"movements", {{{"name", "squats"}, {"description", "three slow squats"},
                                             {"duration_s", 6},
                                             {"excitations", {{{"coordinate", "knee_angle_r"}, {"min_deg", 0},
                                                               {"max_deg", 90}, {"required", true}},
                                                              {{"coordinate", "lumbar_bending"}, {"min_deg", -5},
                                                               {"max_deg", 5}, {"required", false}}}}}}}})};
    return {ResultLine(r, {{"version", 3}, {"from_frame", 123456}})};
  });
  CtlResult reload = RunCtl(SocketPath(), "reload");
  EXPECT_EQ(reload.status, 0) << reload.err;
  EXPECT_EQ(reload.out, "configuration re-read\napplied: control.max_clients, control.group\n"
                        "needs a restart of mocapd (not applied): rig.rate\n");
  CtlResult protocol = RunCtl(SocketPath(), "protocol");
  EXPECT_EQ(protocol.status, 0) << protocol.err;
  EXPECT_EQ(protocol.out, "protocol full body: 1 movements\nsquats (6.0 s): three slow squats\n"
                          "  knee_angle_r 0 .. 90 deg\n  lumbar_bending -5 .. 5 deg (optional)\n");
  CtlResult apply = RunCtl(SocketPath(), "apply");
  EXPECT_EQ(apply.status, 0) << apply.err;
  EXPECT_EQ(apply.out, "version 3 is live from frame 123456\n");
  EXPECT_THAT(daemon.methods(), ElementsAre("config.reload", "protocol.show", "model.apply"));
  EXPECT_EQ(daemon.requests()[2]["params"], json::object());
}

TEST(Mocapctl, WatchPrintsFramesAndStopsAfterCount) {
  testutil::ScriptedMocapd daemon(SocketPath(), [](const json& r) {
    std::vector<std::string> lines = {ResultLine(r, {{"subscribed", {"markers"}}, {"decimation", 2}})};
    for (int f = 0; f < 5; ++f) {
      lines.push_back(json({{"event", "frame"}, {"frame", 10 + 2 * f}, {"t_mid", 0.05 + 0.01 * f},
                            {"markers", {{{"name", "LASI"}, {"occluded", f == 1}}, {{"name", "RASI"}}}}})
                          .dump());
      if (f == 0) lines.push_back(R"({"event":"dropped","count":17})");
    }
    return lines;
  });
  CtlResult r = RunCtl(SocketPath(), "watch --decimate 2 --count 2");
  EXPECT_EQ(r.status, 0) << r.err;
  EXPECT_EQ(r.out,
            "watching markers (every 2. frame; Ctrl-C to stop)\n"
            "frame 10  t 0.050 s  markers 2 (0 occluded)\n"
            "(lost 17 frames: this client read too slowly)\n"
            "frame 12  t 0.060 s  markers 2 (1 occluded)\n");
  EXPECT_EQ(daemon.requests()[0]["params"], json({{"streams", {"markers"}}, {"decimation", 2}}));
}

}  // namespace
}  // namespace mocap
