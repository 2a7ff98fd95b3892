// The `mocap` command line end to end: sim -> fit -> model diff, and every kind of bad input
// gets a clear error naming the file (and line or field) with a non-zero exit status.
#include <gtest/gtest.h>

#include <array>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <regex>
#include <sstream>
#include <unistd.h>

#include "tests/file_test_util.h"

namespace fs = std::filesystem;

namespace {

using mocap::testutil::CommandResult;
using mocap::testutil::Mocap;

class Cli : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    // One folder per process: ctest runs the tests of this suite as parallel processes, each of
    // which sets the suite up.
    dir_ = fs::path(MOCAP_TEST_TMP) / "cli" / std::to_string(::getpid());
    fs::remove_all(dir_);
    fs::create_directories(dir_);
    const CommandResult r = Mocap("sim --out " + (dir_ / "sim").string() + " --seed 3 --duration-scale 0.5");
    ASSERT_EQ(r.status, 0) << r.output;
  }
  static void TearDownTestSuite() { fs::remove_all(dir_); }
  static std::string P(const std::string& rel) { return (dir_ / rel).string(); }
  static void Write(const std::string& rel, const std::string& text) {
    fs::create_directories((dir_ / rel).parent_path());
    std::ofstream(dir_ / rel) << text;
  }
  static std::string Read(const std::string& rel) {
    std::ifstream in(dir_ / rel);
    std::stringstream ss;
    ss << in.rdbuf();
    return ss.str();
  }
  static inline fs::path dir_;
};

// The whole protocol (3,000 frames here) starts coarse to fine (solver/coarse_to_fine.h): the
// subset's iterations are printed and reported, and the result is the plain solve's minimum.
TEST_F(Cli, WholeProtocolFitStartsCoarseAndReachesThePlainMinimum) {
  std::string trials;
  for (const auto& entry : fs::directory_iterator(P("sim")))
    if (entry.path().extension() == ".trc") trials += " " + entry.path().string();
  // One stage: the schedule's later stages weight the data by the residuals the earlier ones
  // left (solver/global_fit.h), which differ in the last digits between the two paths, so only
  // the single-stage objective is the same function for both.
  const std::string fit = "fit --model " + P("sim/nominal.model.json") + trials + " --threads 2 --single-stage";
  const CommandResult a = Mocap(fit + " --out " + P("whole/a.json") + " --report " + P("whole/a_report.json"));
  ASSERT_EQ(a.status, 0) << a.output;
  EXPECT_NE(a.output.find("coarse iteration   1"), std::string::npos) << a.output;
  const CommandResult b = Mocap(fit + " --coarse-frames 0 --out " + P("whole/b.json") + " --report " +
                                P("whole/b_report.json"));
  ASSERT_EQ(b.status, 0) << b.output;
  EXPECT_EQ(b.output.find("coarse iteration"), std::string::npos) << b.output;
  const auto ra = nlohmann::json::parse(Read("whole/a_report.json"));
  const auto rb = nlohmann::json::parse(Read("whole/b_report.json"));
  ASSERT_EQ(ra["frames"].get<int>(), 3000);
  EXPECT_TRUE(ra["coarse"]["used"].get<bool>()) << ra["coarse"];
  EXPECT_FALSE(ra["coarse"]["fallback"].get<bool>());
  EXPECT_EQ(ra["coarse"]["frames"].get<int>(), 800);
  EXPECT_GT(ra["coarse"]["iterations"].get<int>(), 0);
  EXPECT_FALSE(rb["coarse"]["used"].get<bool>());
  EXPECT_TRUE(ra["converged"].get<bool>());
  EXPECT_TRUE(rb["converged"].get<bool>());
  // Both start at the same cost and stop on the same tolerance: the same minimum to 1e-6.
  EXPECT_NEAR(ra["initial_cost"].get<double>(), rb["initial_cost"].get<double>(),
              1e-12 * rb["initial_cost"].get<double>());
  EXPECT_LE(std::abs(ra["final_cost"].get<double>() - rb["final_cost"].get<double>()),
            1e-6 * rb["final_cost"].get<double>());
  EXPECT_LT(ra["iterations"].get<int>(), rb["iterations"].get<int>());
}

TEST_F(Cli, FitWritesModelReportAnglesAndJointCentres) {
  const CommandResult r = Mocap("fit --model " + P("sim/nominal.model.json") + " " + P("sim/static.trc") + " " +
                      P("sim/hip_star_arc_l.trc") + " " + P("sim/knee_flexion_l.trc") + " --out " +
                      P("fit/fitted.json") + " --report " + P("fit/report.json") + " --threads 2");
  ASSERT_EQ(r.status, 0) << r.output;
  EXPECT_NE(r.output.find("iteration   1"), std::string::npos) << "one progress line per iteration";
  EXPECT_NE(r.output.find("Levenberg-Marquardt: CONVERGENCE"), std::string::npos) << r.output;
  const auto report = nlohmann::json::parse(Read("fit/report.json"));
  for (const char* key : {"frames", "markers", "unknowns", "iterations", "initial_cost", "final_cost",
                          "marker_rms_mm", "per_marker_rms_mm", "wall_seconds", "converged",
                          "termination", "undetermined", "parameters"})
    EXPECT_TRUE(report.contains(key)) << key;
  EXPECT_TRUE(report["converged"].get<bool>());
  EXPECT_LT(report["marker_rms_mm"].get<double>(), 1.0);
  EXPECT_LT(report["final_cost"].get<double>(), report["initial_cost"].get<double>());
  EXPECT_EQ(report["per_marker_rms_mm"].size(), 39u);
  for (const auto& p : report["parameters"]) {
    EXPECT_TRUE(p["value"].is_number()) << p;
    EXPECT_TRUE(p["std"].is_number()) << p;
  }
  EXPECT_TRUE(fs::exists(P("fit/knee_flexion_l.fitted.mot")));
  const std::string centres = Read("fit/hip_star_arc_l.joint_centres.trc");
  EXPECT_NE(centres.find("hip_l"), std::string::npos);
  EXPECT_NE(centres.find("knee_r"), std::string::npos);
  const CommandResult diff = Mocap("model diff " + P("sim/truth.model.json") + " " + P("fit/fitted.json") + " --json");
  ASSERT_EQ(diff.status, 0) << diff.output;
  const auto cmp = nlohmann::json::parse(diff.output);
  EXPECT_TRUE(cmp["joint_centre_error_mm"]["max"].is_number());
}

// A static trial cannot locate joint centres: they come back as undetermined, finite, and
// close to where they started, never as garbage.
TEST_F(Cli, StaticTrialAloneReportsUndeterminedParameters) {
  const CommandResult r = Mocap("fit --model " + P("sim/nominal.model.json") + " " + P("sim/static.trc") +
                      " --out " + P("static/fitted.json") + " --report " + P("static/report.json"));
  ASSERT_EQ(r.status, 0) << r.output;
  const auto report = nlohmann::json::parse(Read("static/report.json"));
  std::set<std::string> undetermined;
  for (const auto& n : report["undetermined"]) undetermined.insert(n.get<std::string>());
  for (const char* name : {"hip_l.centre.x", "knee_r.axis0.alpha", "shoulder_l.centre.z"})
    EXPECT_TRUE(undetermined.count(name)) << name;
  // The headline RMS is the frames' as measured, as the trial's is; its one mean posture, with
  // every marker free, fits exactly (it printed 0.000 mm), while the simulated noise is there.
  ASSERT_EQ(report["static_trials"].size(), 1u);
  EXPECT_DOUBLE_EQ(report["marker_rms_mm"].get<double>(), report["per_trial"][0]["marker_rms_mm"].get<double>());
  EXPECT_GT(report["marker_rms_mm"].get<double>(), 0.2);
  EXPECT_EQ(report["marker_samples"].get<int>(), report["per_trial"][0]["marker_samples"].get<int>());
  for (const auto& p : report["parameters"]) {
    ASSERT_TRUE(p["value"].is_number()) << p;
    EXPECT_LT(std::abs(p["value"].get<double>() - p["initial"].get<double>()), 0.2) << p;
  }
}

TEST_F(Cli, UnknownTrialMarkersAreListedAndIgnored) {
  std::string trc = Read("sim/static.trc");
  const size_t at = trc.find("LFHD");
  ASSERT_NE(at, std::string::npos);
  trc.replace(at, 4, "XTRA");
  Write("extra.trc", trc);
  const CommandResult r = Mocap("fit --model " + P("sim/nominal.model.json") + " " + P("extra.trc") + " " +
                      P("sim/neck_rom.trc") + " --out " + P("extra/fitted.json") + " --max-iterations 3");
  EXPECT_NE(r.output.find("not in the model (ignored): XTRA"), std::string::npos) << r.output;
}

TEST_F(Cli, BadInputFailsWithAClearError) {
  const std::string model = P("sim/nominal.model.json");
  const std::string out = " --out " + P("bad/out.json");
  struct Case {
    std::string args, expect;
  };
  Write("broken.model.json", "{ \"format\": \"mocap-model\", ");
  std::string m = Read("sim/nominal.model.json");
  m.replace(m.find("\"femur_l\""), 9, "\"nothing\"");
  Write("wrongref.model.json", m);
  std::string trc = Read("sim/static.trc");
  // Cut short, as OpenSim reads it (the rows that are there: formats/trc.h), and then a field
  // that is no number: refused, naming the file.
  Write("rows.trc", trc.substr(0, trc.size() / 2) + "\tgarbage\n");
  // An infinite value in the first data row's first X field.
  std::string inf = trc;
  const size_t row = inf.find('\n', inf.find('\n', inf.find("Frame#")) + 1) + 1;
  const size_t x0 = inf.find('\t', inf.find('\t', row) + 1) + 1;
  inf.replace(x0, inf.find('\t', x0) - x0, "inf");
  Write("inf.trc", inf);
  // A well-formed trial with no frames at all.
  Write("noframes.trc",
        "PathFileType\t4\t(X/Y/Z)\tnoframes.trc\n"
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames\n"
        "100\t100\t0\t1\tmm\t100\t1\t0\n"
        "Frame#\tTime\tLASI\t\t\n"
        "\t\tX1\tY1\tZ1\n");
  std::string foreign = trc;
  for (const char* n : {"LASI", "RASI", "LPSI", "RPSI", "C7", "T10", "CLAV", "STRN", "RBAK", "LSHO",
                        "RSHO", "LFHD", "RFHD", "LBHD", "RBHD", "LUPA", "LELB", "LFRM", "LWRA", "LWRB",
                        "LFIN", "RUPA", "RELB", "RFRM", "RWRA", "RWRB", "RFIN", "LTHI", "LKNE", "LTIB",
                        "LANK", "LHEE", "LTOE", "RTHI", "RKNE", "RTIB", "RANK", "RHEE", "RTOE"}) {
    const size_t at = foreign.find(std::string("\t") + n + "\t");
    if (at != std::string::npos) foreign.replace(at + 1, std::string(n).size(), std::string("Q") + n);
  }
  Write("foreign.trc", foreign);
  const std::vector<Case> cases = {
      {"fit --model " + P("broken.model.json") + " " + P("sim/static.trc") + out, "broken.model.json: not valid JSON"},
      {"fit --model " + P("wrongref.model.json") + " " + P("sim/static.trc") + out, "no segment named 'nothing'"},
      {"fit --model " + P("missing.json") + " " + P("sim/static.trc") + out, "missing.json"},
      {"fit --model " + model + " " + P("nofile.trc") + out, "nofile.trc"},
      {"fit --model " + model + " " + P("rows.trc") + out, "rows.trc"},
      {"fit --model " + model + " " + P("inf.trc") + out, "inf.trc:7"},
      {"fit --model " + model + " " + P("noframes.trc") + out, "noframes.trc: the trial has no frames"},
      {"fit --model " + model + " " + P("foreign.trc") + out, "none of its"},
      {"fit --model " + model + " " + P("sim/static.trc") + out + " --fit scales,elbows", "unknown parameter group 'elbows'"},
  };
  for (const auto& c : cases) {
    const CommandResult r = Mocap(c.args);
    EXPECT_NE(r.status, 0) << c.args << "\n" << r.output;
    EXPECT_NE(r.output.find(c.expect), std::string::npos) << c.args << "\n" << r.output;
  }
  EXPECT_FALSE(fs::exists(P("bad/out.json"))) << "a failed fit writes no model";
}

// `mocap ik` with a JSON model, a C3D trial (read by its extension) and a marker map that renames
// a trial marker to the model's name.
TEST_F(Cli, IkReadsC3dAndAppliesTheMarkerMap) {
  fs::create_directories(P("ik"));
  const CommandResult conv = Mocap("convert " + P("sim/static.trc") + " " + P("ik/static_c3d.c3d"));
  ASSERT_EQ(conv.status, 0) << conv.output;
  std::string trc = Read("sim/static.trc");
  const size_t at = trc.find("\tLASI\t");
  ASSERT_NE(at, std::string::npos);
  trc.replace(at + 1, 4, "L.ASIS");
  Write("ik/renamed.trc", trc);
  Write("ik/map.txt", "# model = file\n\n  LASI = L.ASIS   # left ASIS\n");
  const std::string model = P("sim/nominal.model.json");
  const CommandResult plain = Mocap("ik --model " + model + " " + P("ik/renamed.trc") + " --out " + P("ik/plain.mot"));
  ASSERT_EQ(plain.status, 0) << plain.output;
  EXPECT_NE(plain.output.find("not in the model (ignored): L.ASIS"), std::string::npos) << plain.output;
  EXPECT_NE(plain.output.find("38 model markers"), std::string::npos) << plain.output;
  const CommandResult mapped = Mocap("ik --model " + model + " " + P("ik/renamed.trc") + " " + P("ik/static_c3d.c3d") +
                                     " --marker-map " + P("ik/map.txt") + " --out " + P("ik/angles.mot"));
  ASSERT_EQ(mapped.status, 0) << mapped.output;
  EXPECT_EQ(mapped.output.find("L.ASIS"), std::string::npos) << mapped.output;
  EXPECT_TRUE(std::regex_search(mapped.output, std::regex(R"(renamed.trc: \d+ frames, 39 model markers)")))
      << mapped.output;
  // One .mot per trial when there are several: <out stem>_<trial>.mot.
  EXPECT_TRUE(fs::exists(P("ik/angles_renamed.mot")));
  EXPECT_TRUE(fs::exists(P("ik/angles_static_c3d.mot")));
  // The C3D (floats, mm) gives the TRC's result.
  std::smatch m1;
  const std::regex rms(R"(renamed.trc: .* marker RMS ([0-9.]+) mm[\s\S]*static_c3d.c3d: .* marker RMS ([0-9.]+) mm)");
  ASSERT_TRUE(std::regex_search(mapped.output, m1, rms)) << mapped.output;
  EXPECT_NEAR(std::stod(m1[1]), std::stod(m1[2]), 0.01);
  EXPECT_LT(std::stod(m1[1]), 20.0);
}

// Marker maps and OpenSim models that are wrong: the message names the file and line.
TEST_F(Cli, BadMarkerMapsAndModelsNameFileAndLine) {
  const std::string model = P("sim/nominal.model.json"), trial = " " + P("sim/static.trc");
  Write("maps/unknown_model.txt", "LASI = LASI\nNOPE = RASI\n");
  Write("maps/unknown_trial.txt", "# ok\nLASI = XYZ\n");
  Write("maps/garbled.txt", "LASI = LASI\n\nRASI RASI\n");
  Write("maps/twice.txt", "LASI = A\nLASI = B\n");
  Write("maps/junk.osim", "this is not XML <");
  struct Case {
    std::string args, expect;
  };
  const std::vector<Case> cases = {
      {"fit --model " + model + trial + " --marker-map " + P("maps/unknown_model.txt") + " --out " + P("maps/o.json"),
       "unknown_model.txt:2: model marker 'NOPE' is not in the model"},
      {"ik --model " + model + trial + " --marker-map " + P("maps/unknown_trial.txt") + " --out " + P("maps/o.mot"),
       "unknown_trial.txt:2: trial marker 'XYZ' is in none of the trials"},
      {"fit --model " + model + trial + " --marker-map " + P("maps/garbled.txt") + " --out " + P("maps/o.json"),
       "garbled.txt:3: expected 'model_name = file_name'"},
      {"fit --model " + model + trial + " --marker-map " + P("maps/twice.txt") + " --out " + P("maps/o.json"),
       "twice.txt:2: model marker 'LASI' is already mapped on line 1"},
      {"fit --model " + model + trial + " --marker-map " + P("maps/none.txt") + " --out " + P("maps/o.json"), "none.txt"},
      {"fit --model " + P("maps/junk.osim") + trial + " --out " + P("maps/o.osim"), "junk.osim:1: not a valid XML document"},
      {"ik --model " + P("maps/junk.osim") + trial + " --out " + P("maps/o.mot"), "junk.osim:1: not a valid XML document"},
      {"fit --model " + model + trial + " --out " + P("maps/o.osim"), "is not one (write .json)"},
      {"fit --model " + model + trial + " --marker-set " + P("maps/x.xml") + " --out " + P("maps/o.json"),
       "a marker set goes with an OpenSim model"},
      {"ik --model " + model + " " + P("maps/garbled.txt") + " --out " + P("maps/o.mot"), "unknown marker file type"},
  };
  for (const auto& c : cases) {
    const CommandResult r = Mocap(c.args);
    EXPECT_NE(r.status, 0) << c.args << "\n" << r.output;
    EXPECT_NE(r.output.find(c.expect), std::string::npos) << c.args << "\n" << r.output;
  }
  EXPECT_FALSE(fs::exists(P("maps/o.json")));
  EXPECT_FALSE(fs::exists(P("maps/o.osim")));
  EXPECT_FALSE(fs::exists(P("maps/o.mot")));
}

}  // namespace
