// mocapd's configuration file (daemon/config.h): the shipped example, every key's type and range
// errors with file:line:key, typos, missing files, relative paths and what a reload may apply.
#include "daemon/config.h"
#include "daemon/startup_checks.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <sys/wait.h>

#include <cstdio>
#include <filesystem>
#include <string>
#include <vector>

#include "file_test_util.h"
#include "ekf/tracker.h"
#include "solver/coarse_to_fine.h"

namespace mocap::daemon {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;
using ::testing::StartsWith;

const std::string kSource = "/etc/mocapd/mocapd.toml";
// A valid simulated rig; the documents below add their key after it, from line 3 on.
const std::string kSimulatedRig = "[rig]\nsimulated = 8\n";

std::string ExamplePath() { return std::string(MOCAP_SOURCE_DIR) + "/daemon/examples/simulated-rig.toml"; }

Status Parse(const std::string& text, DaemonConfig* out) { return ParseConfig(text, kSource, out); }
std::string ParseError(const std::string& text) {
  DaemonConfig config;
  Status s = Parse(text, &config);
  return s.ok() ? "(parsed)" : s.message();
}

TEST(Config, ShippedExampleParsesAndHoldsTheDefaultsButTheSimulatedRig) {
  DaemonConfig config;
  Status s = LoadConfig(ExamplePath(), &config);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(config.source, fs::path(ExamplePath()).lexically_normal().string());
  EXPECT_EQ(config.simulated_cameras, 8);
  EXPECT_EQ(config.num_cameras(), 8);
  EXPECT_EQ(config.subject_seed, 1u);
  EXPECT_TRUE(config.cameras.empty());
  // The example says "the values are the defaults": every other key equals DaemonConfig's.
  EXPECT_EQ(DiffConfig(DaemonConfig(), config),
            (std::vector<ConfigChange>{{"rig.simulated", true}}));
  std::string error;
  EXPECT_TRUE(config.IsValid(&error)) << error;
}

TEST(Config, DefaultsAreTheLibrariesAndADefaultConfigNeedsARig) {
  EXPECT_EQ(DaemonConfig().fit_coarse_frames, solver::CoarseToFineOptions().coarse_frames);
  EXPECT_EQ(DaemonConfig().tracker_sigma_m, ekf::TrackerOptions().sigma_m);
  EXPECT_EQ(DaemonConfig().tracker_gate_chi2, ekf::TrackerOptions().gate_chi2);
  std::string error;
  EXPECT_FALSE(DaemonConfig().IsValid(&error));
  EXPECT_THAT(error, StartsWith("rig: a real rig needs at least one [[rig.camera]]"));
}

TEST(Config, TheErrorOfTheIssueWordForWord) {
  std::string text = "# mocapd\n";
  for (int line = 2; line < 11; ++line) text += "\n";
  text += "[rig]\nrate = \"fast\"\nsimulated = 8\n";  // rate on line 12
  EXPECT_EQ(ParseError(text),
            "/etc/mocapd/mocapd.toml:12: rig.rate: expected a number in [1, 2000], got \"fast\"");
}

struct BadValue {
  std::string table, key, value;  // `key = value` in [table]
  std::string expected;           // the message after "file:line: table.key: "
};

// For every key: a value of the wrong type and one out of range (or otherwise refused).
const std::vector<BadValue> kBadValues = {
    {"rig", "simulated", "\"8\"", "expected an integer in [0, 64], got \"8\""},
    {"rig", "simulated", "65", "expected an integer in [0, 64], got 65"},
    {"rig", "subject_seed", "1.5", "expected an integer in [0, 9200000000000000000], got 1.5"},
    {"rig", "subject_seed", "-1", "expected an integer in [0, 9200000000000000000], got -1"},
    {"rig", "rate", "true", "expected a number in [1, 2000], got true"},
    {"rig", "rate", "0.5", "expected a number in [1, 2000], got 0.5"},
    {"rig", "rate", "nan", "expected a number in [1, 2000], got nan"},
    {"rig", "rate", "inf", "expected a number in [1, 2000], got inf"},
    {"rig", "width", "1280.0", "expected an integer in [16, 16384], got 1280"},
    {"rig", "width", "8", "expected an integer in [16, 16384], got 8"},
    {"rig", "height", "[1024]", "expected an integer in [16, 16384], got an array"},
    {"rig", "height", "99999999999", "expected an integer in [16, 16384], got 99999999999"},
    {"rig", "exposure_us", "\"500us\"", "expected a number in [1, 1000000], got \"500us\""},
    {"rig", "exposure_us", "0", "expected a number in [1, 1000000], got 0"},
    {"rig", "exposure_us", "6000", "6000 us does not fit in the frame period of 5000 us (rig.rate 200 Hz)"},
    {"rig", "gain_db", "{ db = 3 }", "expected a number in [0, 48], got a table"},
    {"rig", "gain_db", "49", "expected a number in [0, 48], got 49"},
    {"rig", "detection_threshold", "60.5", "expected an integer in [1, 65535], got 60.5"},
    {"rig", "detection_threshold", "0", "expected an integer in [1, 65535], got 0"},
    {"rig", "centroid_noise_px", "\"low\"", "expected a number in [0, 10], got \"low\""},
    {"rig", "centroid_noise_px", "-0.1", "expected a number in [0, 10], got -0.1"},
    {"rig", "detection_threads", "\"two\"", "expected an integer in [1, 64], got \"two\""},
    {"rig", "detection_threads", "0", "expected an integer in [1, 64], got 0"},
    {"rig", "min_cameras", "0", "expected an integer in [1, 64], got 0"},
    {"rig", "calibration", "5", "expected a path (a string), got 5"},
    {"rig", "sync", "1", "expected a string, got 1"},
    {"rig", "sync", "\"genlock\"",
     "expected one of \"trigger\", \"ptp\", \"free-run\", got \"genlock\""},
    {"rig", "trigger_master", "3", "expected a string, got 3"},
    {"rig", "trigger_master", "\"cam-A\"",
     "\"cam-A\" on a simulated rig (its fake cameras share the host's clock; there is nothing to "
     "trigger)"},
    {"rig", "trigger_line", "\"Line1\"", "expected an integer in [0, 15], got \"Line1\""},
    {"rig", "trigger_line", "16", "expected an integer in [0, 15], got 16"},
    {"rig", "ptp_lock_timeout_s", "\"10s\"", "expected a number in [0.1, 600], got \"10s\""},
    {"rig", "ptp_lock_timeout_s", "0", "expected a number in [0.1, 600], got 0"},
    {"rig", "ptp_schedule", "\"action\"", "expected one of \"sync-free-run\", \"none\", got \"action\""},
    {"rig", "pixel_format", "8", "expected a string, got 8"},
    {"rig", "pixel_format", "\"Mono10\"",
     "expected one of \"Mono8\", \"Mono12\", \"Mono12Packed\", \"Mono16\", got \"Mono10\""},
    {"rig", "packet_size", "\"jumbo\"",
     "expected an integer in [576, 16384] or 0 (negotiated), got \"jumbo\""},
    {"rig", "packet_size", "100", "expected an integer in [576, 16384] or 0 (negotiated), got 100"},
    {"rig", "packet_delay_ns", "1.5", "expected an integer in [0, 100000000], got 1.5"},
    {"rig", "packet_delay_ns", "-1", "expected an integer in [0, 100000000], got -1"},
    {"rig", "packet_resend", "true", "expected a string, got true"},
    {"rig", "packet_resend", "\"sometimes\"",
     "expected one of \"always\", \"never\", got \"sometimes\""},
    {"rig", "socket_buffer_bytes", "\"auto\"", "expected an integer in [0, 1073741824], got \"auto\""},
    {"rig", "socket_buffer_bytes", "-1", "expected an integer in [0, 1073741824], got -1"},
    {"storage", "state_dir", "false", "expected a path (a string), got false"},
    {"storage", "state_dir", "\"\"", "must not be empty"},
    {"storage", "export_dirs", "\"/srv\"", "expected an array of paths, got \"/srv\""},
    {"control", "socket", "1", "expected a path (a string), got 1"},
    {"control", "socket", "\"/" + std::string(120, 's') + "\"",
     "\"/" + std::string(120, 's') + "\" is 121 bytes long; a Unix socket path holds at most 107"},
    {"control", "group", "100", "expected a string, got 100"},
    {"control", "group", "\"\"", "must not be empty"},
    {"control", "max_clients", "\"many\"", "expected an integer in [1, 4096], got \"many\""},
    {"control", "max_clients", "0", "expected an integer in [1, 4096], got 0"},
    {"control", "max_line_bytes", "1e6", "expected an integer in [1024, 67108864], got 1000000"},
    {"control", "max_line_bytes", "100", "expected an integer in [1024, 67108864], got 100"},
    {"control", "subscriber_queue_frames", "[]", "expected an integer in [1, 100000], got an array"},
    {"control", "subscriber_queue_frames", "0", "expected an integer in [1, 100000], got 0"},
    {"control", "max_pending_requests", "\"64\"", "expected an integer in [1, 4096], got \"64\""},
    {"control", "max_pending_requests", "5000", "expected an integer in [1, 4096], got 5000"},
    {"protocol", "file", "0", "expected a path (a string), got 0"},
    {"tracker", "sigma_m", "\"4 mm\"", "expected a number in [0.0001, 0.1], got \"4 mm\""},
    {"tracker", "sigma_m", "0", "expected a number in [0.0001, 0.1], got 0"},
    {"tracker", "gate_chi2", "true", "expected a number in [1, 100], got true"},
    {"tracker", "gate_chi2", "0.5", "expected a number in [1, 100], got 0.5"},
    {"fit", "threads", "\"all\"", "expected an integer in [0, 256], got \"all\""},
    {"fit", "threads", "-1", "expected an integer in [0, 256], got -1"},
    {"fit", "max_iterations", "2.5", "expected an integer in [1, 10000], got 2.5"},
    {"fit", "max_iterations", "0", "expected an integer in [1, 10000], got 0"},
    {"fit", "groups", "[\"scales\"]", "expected a string, got an array"},
    {"fit", "groups", "\"scales,bones\"",
     "unknown parameter group 'bones' (expected scales, centres, axes, markers, all or none)"},
    {"fit", "coarse_frames", "\"800\"", "expected an integer in [0, 1000000], got \"800\""},
    {"fit", "coarse_frames", "-800", "expected an integer in [0, 1000000], got -800"},
};

TEST(Config, EveryKeysBadTypeAndRangeNameFileLineAndKey) {
  for (const BadValue& bad : kBadValues) {
    // [table] on line 3 (or the rig's own table), the key on line 5 after a comment.
    // (`simulated` itself cannot be given twice: its own document starts with another key.)
    std::string text = bad.key == "simulated" ? "[rig]\nrate = 200\n" : kSimulatedRig;
    text += bad.table == "rig" ? "\n# the key\n" : "[" + bad.table + "]\n# the key\n";
    text += bad.key + " = " + bad.value + "\n";
    EXPECT_EQ(ParseError(text), kSource + ":5: " + bad.table + "." + bad.key + ": " + bad.expected)
        << text;
  }
}

TEST(Config, EveryDocumentedKeyIsTestedWithABadValue) {
  // The example documents every key (commented where it has no default value); each of them
  // must appear in kBadValues, so a key added to the parser without a test fails here.
  const std::string example = testutil::ReadBytes(ExamplePath());
  std::string table;
  int keys = 0;
  std::istringstream lines(example);
  for (std::string line; std::getline(lines, line);) {
    if (line.rfind("[", 0) == 0 && line.rfind("[[", 0) != 0) {
      table = line.substr(1, line.find(']') - 1);
      continue;
    }
    if (line.rfind("# ", 0) == 0 && line.find(" = ") != std::string::npos) line = line.substr(2);
    const std::size_t eq = line.find(" = ");
    if (eq == std::string::npos || line[0] == '#' || line[0] == ' ' || table.empty()) continue;
    const std::string key = line.substr(0, eq);
    if (table == "rig" && (key == "id" || key == "backend" || key == "masks" ||
                           key == "interface" || key == "link" || key == "strobe_line" ||
                           key == "optional" || key == "usb_mode" ||
                           key == "usb_throughput_limit_mb_s" || key == "sim_clock_offset_ms" ||
                           key == "sim_clock_drift_ppm" || key == "sim_arrival_wait_us" ||
                           line.find("the rig's") != std::string::npos))
      continue;  // [[rig.camera]]'s keys, tested below
    bool tested = false;
    for (const BadValue& bad : kBadValues) tested |= bad.table == table && bad.key == key;
    EXPECT_TRUE(tested) << table << "." << key << " has no bad-value test";
    ++keys;
  }
  EXPECT_EQ(keys, 37);
}

TEST(Config, CameraKeysAndMasksNameTheCameraAndLine) {
  const std::string real_rig = "[rig]\nwidth = 1280\nheight = 1024\n";
  const std::string camera = "[[rig.camera]]\nid = \"cam-A\"\n";  // lines 4-5
  const std::string second = "[[rig.camera]]\nid = \"cam-B\"\n";  // lines 6-7 after one camera
  DaemonConfig config;
  Status s = Parse(real_rig + camera + "backend = \"simulated\"\ngain_db = -1\nexposure_us = 0\n"
                   "masks = [ { x = 0, y = 960, width = 1280, height = 64 } ]\n" + second,
                   &config);
  ASSERT_TRUE(s.ok()) << s.message();
  ASSERT_EQ(config.cameras.size(), 2u);
  EXPECT_EQ(config.cameras[0].backend, "simulated");
  EXPECT_EQ(config.cameras[1].backend, "aravis");
  EXPECT_EQ(config.cameras[0].masks, (std::vector<MaskRect>{{0, 960, 1280, 64}}));
  EXPECT_EQ(config.num_cameras(), 2);

  // Each document after the first camera, and the error after "file:".
  const std::vector<std::pair<std::string, std::string>> bad = {
      {"gain_db = 60\n",
       "6: rig.camera[0].gain_db: expected a number in [0, 48] or -1 (the rig's), got 60"},
      {"detection_threshold = -3\n",
       "6: rig.camera[0].detection_threshold: expected an integer in [1, 65535] or 0 (the rig's), "
       "got -3"},
      {"exposure_us = 5000\n",
       "6: rig.camera[0].exposure_us: 5000 us does not fit in the frame period of 5000 us "
       "(rig.rate 200 Hz)"},
      {"backend = \"usb\"\n",
       "6: rig.camera[0].backend: expected one of \"aravis\", \"simulated\", got \"usb\""},
      {"interface = \"firewire\"\n",
       "6: rig.camera[0].interface: expected one of \"gige\", \"10gige\", \"usb3\", got \"firewire\""},
      {"link = 1\n", "6: rig.camera[0].link: expected a string, got 1"},
      {"strobe_line = -2\n",
       "6: rig.camera[0].strobe_line: expected an integer in [0, 15] or -1 (none), got -2"},
      {"optional = [\"GainAuto\"]\n", "6: rig.camera[0].optional: expected a string, got an array"},
      {"usb_mode = 3\n", "6: rig.camera[0].usb_mode: expected a string, got 3"},
      {"usb_throughput_limit_mb_s = -5\n",
       "6: rig.camera[0].usb_throughput_limit_mb_s: expected a number in [0, 100000], got -5"},
      {"sim_clock_offset_ms = \"3 ms\"\n",
       "6: rig.camera[0].sim_clock_offset_ms: expected a number in [-1000000, 1000000], got \"3 ms\""},
      {"sim_clock_drift_ppm = 2000\n",
       "6: rig.camera[0].sim_clock_drift_ppm: expected a number in [-1000, 1000], got 2000"},
      {"sim_arrival_wait_us = -1\n",
       "6: rig.camera[0].sim_arrival_wait_us: expected a number in [0, 100000], got -1"},
      {second + "id2 = 3\n",
       "8: rig.camera[1].id2: unknown key (the keys of [rig.camera] are id, backend, exposure_us, "
       "gain_db, detection_threshold, interface, link, strobe_line, optional, usb_mode, "
       "usb_throughput_limit_mb_s, sim_clock_offset_ms, sim_clock_drift_ppm, sim_arrival_wait_us, masks)"},
      {"[[rig.camera]]\nid = \"cam-A\"\n", "7: rig.camera[1].id: \"cam-A\" is also rig.camera[0]'s id"},
      {"[[rig.camera]]\nbackend = \"aravis\"\n",
       "6: rig.camera[1].id: missing: each camera needs its GenICam id or serial"},
      {"masks = [ { x = 0, y = 1000, width = 10, height = 25 } ]\n",
       "6: rig.camera[0].masks[0]: x 0, y 1000, width 10, height 25 is not a rectangle within the "
       "1280x1024 image"},
      {"masks = [ { x = 0, y = 0, w = 10, height = 25 } ]\n",
       "6: rig.camera[0].masks[0].w: unknown key (the keys of a mask are x, y, width, height)"},
      {"masks = [ { x = 0, y = 0, height = 25 } ]\n",
       "6: rig.camera[0].masks[0]: missing width (the keys of a mask are x, y, width, height)"},
      {"masks = [ { x = 0, y = 0, width = 0, height = 25 } ]\n",
       "6: rig.camera[0].masks[0].width: expected an integer in [1, 16384], got 0"},
      {"masks = \"top\"\n",
       "6: rig.camera[0].masks: expected rectangles [ { x = 0, y = 0, width = 10, height = 10 } ], "
       "got \"top\""},
  };
  for (const auto& [text, expected] : bad)
    EXPECT_EQ(ParseError(real_rig + camera + text), kSource + ":" + expected) << text;
  EXPECT_EQ(ParseError("[rig]\ncamera = \"cam-A\"\n"),
            kSource + ":2: rig.camera: expected camera tables ([[rig.camera]] sections), got \"cam-A\"");
}

TEST(Config, RigConsistency) {
  EXPECT_EQ(ParseError("[control]\ngroup = \"lab\"\n"),
            kSource + ": rig: a real rig needs at least one [[rig.camera]] (or simulated = N for a "
                      "simulated rig of N cameras)");
  EXPECT_EQ(ParseError("\n[rig]\nrate = 100\n"),
            kSource + ":2: rig: a real rig needs at least one [[rig.camera]] (or simulated = N for a "
                      "simulated rig of N cameras)");
  EXPECT_EQ(ParseError("[rig]\nsimulated = 2\n[[rig.camera]]\nid = \"a\"\n"),
            kSource + ":3: rig.camera: 1 cameras listed for a simulated rig of 2 (list none, or one "
                      "per simulated camera, then the real cameras that join it)");
  // Cameras after the fakes join the rig as real ones: Aravis cameras, not under a simulated PTP.
  EXPECT_EQ(ParseError("[rig]\nsimulated = 1\n[[rig.camera]]\nid = \"a\"\n[[rig.camera]]\nid = \"b\"\n"
                       "backend = \"simulated\"\n"),
            kSource + ":7: rig.camera[1].backend: 'b', after the 1 simulated cameras, joins the "
                      "simulated rig as a real camera: backend \"aravis\", got \"simulated\"");
  EXPECT_EQ(ParseError("[rig]\nsimulated = 1\nsync = \"ptp\"\n[[rig.camera]]\nid = \"a\"\n[[rig.camera]]\nid = \"b\"\n"),
            kSource + ":7: rig.camera[1].id: 'b', after the 1 simulated cameras, joins the simulated "
                      "rig as a real camera: rig.sync \"trigger\" or \"free-run\" (the fakes' PTP is "
                      "simulated), got \"ptp\"");
  // Exposure against the rate whichever comes first in the file.
  EXPECT_EQ(ParseError("[rig]\nexposure_us = 900\nsimulated = 8\nrate = 1200\n"),
            kSource + ":2: rig.exposure_us: 900 us does not fit in the frame period of 833.333 us "
                      "(rig.rate 1200 Hz)");
}

TEST(Config, UnknownKeysAndTablesAreErrorsNamingThem) {
  EXPECT_EQ(ParseError(kSimulatedRig + "rat = 200\n"),
            kSource + ":3: rig.rat: unknown key (the keys of [rig] are simulated, subject_seed, rate, "
                      "width, height, exposure_us, gain_db, detection_threshold, centroid_noise_px, "
                      "detection_threads, min_cameras, calibration, sync, trigger_master, trigger_line, "
                      "ptp_lock_timeout_s, ptp_schedule, pixel_format, packet_size, packet_delay_ns, "
                      "packet_resend, socket_buffer_bytes, camera ([[rig.camera]]))");
  EXPECT_EQ(ParseError(kSimulatedRig + "[control]\nmax_client = 8\n"),
            kSource + ":4: control.max_client: unknown key (the keys of [control] are socket, group, "
                      "max_clients, max_line_bytes, subscriber_queue_frames, max_pending_requests)");
  EXPECT_EQ(ParseError(kSimulatedRig + "[controls]\nmax_clients = 8\n"),
            kSource + ":3: controls: unknown table (the tables are [rig], [storage], [control], "
                      "[protocol], [tracker], [fit])");
  EXPECT_EQ(ParseError("socket = \"/tmp/s\"\n" + kSimulatedRig),
            kSource + ":1: socket: unknown key (keys belong in one of the tables [rig], [storage], "
                      "[control], [protocol], [tracker], [fit])");
  EXPECT_EQ(ParseError("rig = 8\n"), kSource + ":1: rig: expected a table [rig], got 8");
  EXPECT_THAT(ParseError(kSimulatedRig + "[fit.more]\nthreads = 1\n"),
              StartsWith(kSource + ":3: fit.more: unknown key (the keys of [fit] are threads,"));
}

TEST(Config, SyntaxErrorsNameTheLine) {
  EXPECT_THAT(ParseError(kSimulatedRig + "[control\ngroup = \"x\"\n"), StartsWith(kSource + ":3: "));
  EXPECT_THAT(ParseError(kSimulatedRig + "rate = 200\nrate = 100\n"), StartsWith(kSource + ":4: "));
}

TEST(Config, ARefusedFileLeavesTheConfigUntouched) {
  DaemonConfig config;
  ASSERT_TRUE(Parse(kSimulatedRig + "[control]\nmax_clients = 5\n", &config).ok());
  const DaemonConfig before = config;
  EXPECT_FALSE(Parse(kSimulatedRig + "[control]\nmax_clients = 6\nrate = 1\n", &config).ok());
  EXPECT_FALSE(Parse("[rig\n", &config).ok());
  EXPECT_TRUE(DiffConfig(before, config).empty());
  EXPECT_EQ(config.max_clients, 5);
}

TEST(Config, MissingFileNamesItAndWhy) {
  DaemonConfig config;
  Status s = LoadConfig("/nonexistent-dir/mocapd.toml", &config);
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.message(), "/nonexistent-dir/mocapd.toml: cannot read: No such file or directory");
}

TEST(Config, RelativePathsAreRelativeToTheFilesDirectory) {
  const fs::path dir = fs::path(testutil::TmpPath("config", "_dir")) / "etc";
  fs::create_directories(dir);
  const fs::path file = dir / "mocapd.toml";
  testutil::WriteBytes(file.string(), kSimulatedRig +
                                          "calibration = \"calib/./rig.json\"\n"
                                          "[storage]\nstate_dir = \"../state\"\n"
                                          "export_dirs = [\"out/../exports\", \"/srv/x/\"]\n"
                                          "[control]\nsocket = \"/run/x/control.sock\"\n"
                                          "[protocol]\nfile = \"protocol.json\"\n");
  DaemonConfig config;
  // Loaded through a path relative to the working directory: the paths come out absolute.
  const std::string relative = fs::relative(file).string();
  ASSERT_FALSE(fs::path(relative).is_absolute());
  Status s = LoadConfig(relative, &config);
  ASSERT_TRUE(s.ok()) << s.message();
  const fs::path abs_dir = fs::absolute(dir).lexically_normal();
  EXPECT_EQ(config.source, (abs_dir / "mocapd.toml").string());
  EXPECT_EQ(config.calibration_file, (abs_dir / "calib" / "rig.json").string());
  EXPECT_EQ(config.state_dir, (abs_dir.parent_path() / "state").string());
  EXPECT_EQ(config.socket_path, "/run/x/control.sock");
  EXPECT_EQ(config.protocol_file, (abs_dir / "protocol.json").string());
  EXPECT_EQ(config.export_dirs, (std::vector<std::string>{(abs_dir / "exports").string(), "/srv/x/"}));
  EXPECT_EQ(config.AllowedExportDirs(), config.export_dirs);
  // Without the key: the state directory's exports/ folder only.
  DaemonConfig defaults;
  ASSERT_TRUE(Parse(kSimulatedRig, &defaults).ok());
  EXPECT_EQ(defaults.AllowedExportDirs(), std::vector<std::string>{"/var/lib/mocapd/exports"});
  // Each item a non-empty path, named by its index and line.
  EXPECT_EQ(ParseError(kSimulatedRig + "[storage]\nexport_dirs = [\"/a\", 5]\n"),
            kSource + ":4: storage.export_dirs[1]: expected a path (a string), got 5");
  EXPECT_EQ(ParseError(kSimulatedRig + "[storage]\nexport_dirs = [\"\"]\n"),
            kSource + ":4: storage.export_dirs[0]: must not be empty");
  defaults.export_dirs = {"relative"};
  std::string error;
  EXPECT_FALSE(defaults.IsValid(&error));
  EXPECT_EQ(error, "storage.export_dirs[0]: expected an absolute path, got \"relative\"");
}

TEST(Config, IsValidNamesTheKeyWithoutALine) {
  DaemonConfig config;
  config.simulated_cameras = 8;
  std::string error;
  ASSERT_TRUE(config.IsValid(&error)) << error;
  config.max_clients = 0;
  EXPECT_FALSE(config.IsValid(&error));
  EXPECT_EQ(error, "control.max_clients: expected an integer in [1, 4096], got 0");
  config.max_clients = 8;
  config.cameras.resize(8);
  for (int c = 0; c < 8; ++c) config.cameras[c].id = "cam-" + std::to_string(c % 7);
  EXPECT_FALSE(config.IsValid(&error));
  EXPECT_EQ(error, "rig.camera[7].id: \"cam-0\" is also rig.camera[0]'s id");
}

TEST(Config, DiffSaysWhatChangedAndWhatNeedsARestart) {
  DaemonConfig a;
  ASSERT_TRUE(LoadConfig(ExamplePath(), &a).ok());
  DaemonConfig b = a;
  EXPECT_TRUE(DiffConfig(a, b).empty());
  b.source = "/elsewhere.toml";  // where it came from is not a change
  EXPECT_TRUE(DiffConfig(a, b).empty());

  b.rate_hz = 100;
  b.control_group = "lab";
  b.max_clients = 8;
  b.subscriber_queue_frames = 100;
  b.fit_max_iterations = 20;
  b.socket_path = "/tmp/other.sock";
  b.calibration_file = "/var/lib/mocapd/calibration.json";
  b.export_dirs = {"/srv/exports"};
  CameraConfig camera;
  camera.id = "cam-A";
  b.cameras.push_back(camera);
  EXPECT_EQ(DiffConfig(a, b), (std::vector<ConfigChange>{{"rig.rate", true},
                                                         {"rig.calibration", false},
                                                         {"control.socket", true},
                                                         {"control.group", false},
                                                         {"control.max_clients", false},
                                                         {"control.subscriber_queue_frames", false},
                                                         {"fit.max_iterations", false},
                                                         {"storage.export_dirs", false},
                                                         {"rig.camera", true}}));
  // A 64-bit seed is compared exactly, not as a double.
  DaemonConfig c = a, d = a;
  c.subject_seed = (1ull << 60);
  d.subject_seed = (1ull << 60) + 1;
  EXPECT_EQ(DiffConfig(c, d), (std::vector<ConfigChange>{{"rig.subject_seed", true}}));
  // A mask moved is a camera change.
  DaemonConfig e = b;
  e.cameras[0].masks.push_back({0, 0, 10, 10});
  EXPECT_EQ(DiffConfig(b, e), (std::vector<ConfigChange>{{"rig.camera", true}}));
}

}  // namespace
}  // namespace mocap::daemon

namespace mocap::daemon {
namespace {

// A real rig of `n` cameras (ids cam-0...) with `camera_keys` in each camera's table.
DaemonConfig RealRig(int n, const std::string& rig_keys, const std::string& camera_keys) {
  std::string text = "[rig]\n" + rig_keys;
  for (int c = 0; c < n; ++c)
    text += "[[rig.camera]]\nid = \"cam-" + std::to_string(c) + "\"\n" + camera_keys;
  DaemonConfig config;
  const Status s = ParseConfig(text, kSource, &config);
  EXPECT_TRUE(s.ok()) << s.message();
  return config;
}

// The issue's default rig: 1280x1024 Mono8 at 200 Hz is 262.1 MB/s of images a camera, which no
// GigE link carries (119 MB/s of images in 1500-byte packets): refused, naming the link, the
// camera, the figures and what would fit (90 Hz or 464 rows: 119.0 MB/s of images each).
TEST(RigBandwidth, TheDefaultRigDoesNotFitGigEAndTheMessageSaysWhatWould) {
  const StartupCheck c = CheckRigBandwidth(RealRig(2, "", ""));
  ASSERT_FALSE(c.ok());
  EXPECT_EQ(c.exit_code, kExitConfig);
  const std::string& m = c.status.message();
  EXPECT_THAT(m, StartsWith("[rig] bandwidth: link 'cam-0' (gige) carries 1 camera 'cam-0' needing "
                            "275.4 MB/s of its 125.0 MB/s (each camera 1280x1024 Mono8 at 200.0 Hz "
                            "is 262.1 MB/s of images). To fit: rig.rate <= 90 Hz, or a ROI of "
                            "1280 x <= 464 px (rig.height) at 200.0 Hz, or a 10gige link; jumbo "
                            "frames (packet_size = 9000) save a few %; link 'cam-1'"))
      << m;
  // What it says fits, fits: 90 Hz, or 464 rows, or 10GigE.
  EXPECT_TRUE(CheckRigBandwidth(RealRig(2, "rate = 90\n", "")).ok());
  EXPECT_FALSE(CheckRigBandwidth(RealRig(2, "rate = 91\n", "")).ok());
  EXPECT_TRUE(CheckRigBandwidth(RealRig(2, "height = 464\n", "")).ok());
  EXPECT_FALSE(CheckRigBandwidth(RealRig(2, "height = 466\n", "")).ok());
  EXPECT_TRUE(CheckRigBandwidth(RealRig(8, "", "interface = \"10gige\"\n")).ok());
}

TEST(RigBandwidth, ASharedLinkCountsEveryCameraOnItAndPackedFormatsAreSuggested) {
  // Five 10GigE cameras behind one uplink: 5 x 264.1 MB/s on the wire (packets of 1500 bytes).
  StartupCheck c = CheckRigBandwidth(RealRig(5, "", "interface = \"10gige\"\nlink = \"up\"\n"));
  ASSERT_FALSE(c.ok());
  EXPECT_THAT(c.status.message(),
              HasSubstr("link 'up' (10gige) carries 5 cameras 'cam-0', 'cam-1', 'cam-2', 'cam-3', "
                        "'cam-4' needing 1377.0 MB/s of its 1250.0 MB/s"));
  EXPECT_THAT(c.status.message(), HasSubstr("or fewer cameras on the link"));
  // Jumbo frames: 8964 of 9038 wire bytes are image, 1321.5 MB/s: still too much.
  EXPECT_THAT(CheckRigBandwidth(RealRig(5, "packet_size = 9000\n",
                                        "interface = \"10gige\"\nlink = \"up\"\n"))
                  .status.message(),
              HasSubstr("needing 1321.5 MB/s"));
  // Mono16 doubles it and the message offers the packed format.
  c = CheckRigBandwidth(RealRig(1, "pixel_format = \"Mono16\"\n", "interface = \"usb3\"\n"));
  ASSERT_FALSE(c.ok());
  EXPECT_THAT(c.status.message(), HasSubstr("needing 524.3 MB/s of its 400.0 MB/s"));
  EXPECT_THAT(c.status.message(), HasSubstr("pixel_format \"Mono12Packed\" (1.5 bytes/px)"));
  EXPECT_TRUE(CheckRigBandwidth(RealRig(1, "pixel_format = \"Mono12Packed\"\n",
                                        "interface = \"usb3\"\n")).ok());
  // One link, one interface.
  DaemonConfig mixed = RealRig(2, "rate = 50\n", "link = \"x\"\n");
  mixed.cameras[1].interface = "usb3";
  c = CheckRigBandwidth(mixed);
  ASSERT_FALSE(c.ok());
  EXPECT_THAT(c.status.message(), HasSubstr("share link 'x': one link has one interface"));
  // A simulated rig has no links.
  DaemonConfig simulated;
  simulated.simulated_cameras = 8;
  EXPECT_TRUE(CheckRigBandwidth(simulated).ok());
  EXPECT_TRUE(RigLinkLoads(simulated).empty());
}

TEST(RigBandwidth, TheReportNamesEachLinkAndTheUsbfsBudget) {
  const std::string usbfs = testutil::TmpPath("rig_bandwidth", ".usbfs");
  testutil::WriteBytes(usbfs, "16\n");  // the kernel's default, MB
  const DaemonConfig rig = RealRig(2, "rate = 100\n", "interface = \"usb3\"\n");
  std::string report = DescribeRigBandwidth(rig, usbfs);
  EXPECT_THAT(report, HasSubstr("link 'cam-0' (usb3): 1 camera need 131.1 of 400.0 MB/s (33 %)"));
  // 2 cameras x 32 buffers x 1.25 MiB = 80 MiB of usbfs memory.
  EXPECT_THAT(report, HasSubstr("warning: usbfs memory: the limit is 16 MB"));
  testutil::WriteBytes(usbfs, "0\n");  // unlimited
  EXPECT_THAT(DescribeRigBandwidth(rig, usbfs),
              HasSubstr("usbfs memory: enough for 2 USB3 cameras' buffers (80.0 MB)"));
}

// `mocapd --check-config` runs the check without a camera: exit 78 (EX_CONFIG) and the message.
TEST(RigBandwidth, MocapdCheckConfigRefusesAnOverBudgetRigWithoutCameras) {
  auto run = [](const std::string& toml, std::string* out) {
    const std::string path = testutil::TmpPath("rig_bandwidth", ".toml");
    testutil::WriteBytes(path, toml);
    const std::string cmd = std::string(MOCAPD_PATH) + " --check-config --config '" + path + "' 2>&1";
    FILE* pipe = popen(cmd.c_str(), "r");
    char buf[4096];
    out->clear();
    while (pipe && fgets(buf, sizeof buf, pipe)) *out += buf;
    const int rc = pipe ? pclose(pipe) : -1;
    return WIFEXITED(rc) ? WEXITSTATUS(rc) : -1;
  };
  std::string out;
  const std::string cameras = "[[rig.camera]]\nid = \"left\"\n[[rig.camera]]\nid = \"right\"\n";
  EXPECT_EQ(run("[rig]\nrate = 200\n" + cameras, &out), kExitConfig) << out;
  EXPECT_THAT(out, HasSubstr("[rig] bandwidth: link 'left' (gige) carries 1 camera 'left'"));
  EXPECT_EQ(run("[rig]\nrate = 60\n" + cameras, &out), 0) << out;
  EXPECT_THAT(out, HasSubstr("link 'right' (gige): 1 camera need 82.6 of 125.0 MB/s (66 %)"));
}

}  // namespace
}  // namespace mocap::daemon

#include "daemon/rig_setup.h"

namespace mocap::daemon {
namespace {

TEST(RigSetup, TriggerMasterFreeRunsAndStrobesTheOthersWaitOnTheirLine) {
  DaemonConfig c;
  ASSERT_TRUE(ParseConfig("[rig]\nrate = 100\nsync = \"trigger\"\ntrigger_master = \"m\"\n"
                          "trigger_line = 2\npixel_format = \"Mono12Packed\"\npacket_size = 9000\n"
                          "packet_resend = \"never\"\n"
                          "[[rig.camera]]\nid = \"m\"\nstrobe_line = 1\n"
                          "[[rig.camera]]\nid = \"s\"\noptional = \" LineSource , GevSCPD\"\n",
                          kSource, &c).ok());
  const drivers::CameraSettings master = CameraSettingsOf(c, 0), slave = CameraSettingsOf(c, 1);
  EXPECT_EQ(master.trigger, drivers::TriggerMode::kFreeRun);
  EXPECT_EQ(master.strobe_line, 1);
  EXPECT_EQ(slave.trigger, drivers::TriggerMode::kHardwareLine);
  EXPECT_EQ(slave.trigger_line, 2);
  EXPECT_EQ(slave.strobe_line, -1);
  EXPECT_EQ(slave.optional_features, (std::vector<std::string>{"LineSource", "GevSCPD"}));
  EXPECT_EQ(slave.pixel_format, drivers::PixelFormat::kMono12Packed);
  EXPECT_EQ(slave.packet_size, 9000);
  EXPECT_FALSE(slave.packet_resend);
  EXPECT_FALSE(slave.ptp);
  EXPECT_EQ(RigSyncOf(c), CapturePipelineOptions::RigSync::kTrigger);
  // The master must drive a line.
  EXPECT_THAT(ParseError("[rig]\ntrigger_master = \"m\"\n[[rig.camera]]\nid = \"m\"\n"),
              HasSubstr("rig.camera[0].strobe_line: -1 (none) on the trigger master \"m\""));
  c.sync = "ptp";
  EXPECT_TRUE(CameraSettingsOf(c, 1).ptp);
  EXPECT_EQ(CameraSettingsOf(c, 1).ptp_schedule, drivers::PtpSchedule::kSyncFreeRun);  // the default
  c.ptp_schedule = "none";
  EXPECT_EQ(CameraSettingsOf(c, 1).ptp_schedule, drivers::PtpSchedule::kNone);
  EXPECT_EQ(RigSyncOf(c), CapturePipelineOptions::RigSync::kSharedClock);
  c.sync = "free-run";
  EXPECT_EQ(RigSyncOf(c), CapturePipelineOptions::RigSync::kFreeRun);
  EXPECT_EQ(CameraSettingsOf(c, 1).trigger, drivers::TriggerMode::kFreeRun);
}

}  // namespace
}  // namespace mocap::daemon
