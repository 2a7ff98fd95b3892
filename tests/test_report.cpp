// The fit's HTML report (report/fit_report_html.h), on real fits of a `mocap sim` subject:
// - the three orthographic views draw every joint centre (fitted and nominal) where the model's
//   forward kinematics puts it (the SVG parsed, the centres projected here independently);
// - the highlights: a fit stopped by its iteration limit says it did not converge, a marker
//   displaced by 4 cm in one trial is flagged and named (and only the outliers are), undetermined parameters are greyed — and
//   a good fit shows none of the alarms;
// - headless Chromium (Debian's `chromium`) opens the page: no console error, a screenshot of
//   the right size that is not blank, and the rendered text holds the JSON report's figures.
#include <gtest/gtest.h>
#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <map>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/core.hpp>
#include <regex>
#include <set>

#include "formats/trc.h"
#include "model/kinematics.h"
#include "model/model_io.h"
#include "report/fit_report_html.h"
#include "sim/protocol.h"
#include "tests/file_test_util.h"

namespace mocap {
namespace {

namespace fs = std::filesystem;
using testutil::Mocap;
using testutil::ReadBytes;

// Per process: ctest runs each test in its own process, side by side, and each one's
// SetUpTestSuite rebuilds the directory (a shared one raced: the tests were skipped).
fs::path Dir() { return fs::path(MOCAP_TEST_TMP) / ("report-" + std::to_string(::getpid())); }
std::string P(const std::string& rel) { return (Dir() / rel).string(); }

// The sim subject and two fits, shared by the tests (each fit takes seconds).
class Report : public ::testing::Test {
 protected:
  static void TearDownTestSuite() { fs::remove_all(Dir()); }
  static void SetUpTestSuite() {
    fs::remove_all(Dir());
    fs::create_directories(Dir());
    CommandResult r = Mocap("sim --out " + P("sim") + " --seed 3 --duration-scale 0.5");
    ASSERT_EQ(r.status, 0) << r.output;
    const std::string trials = " " + P("sim/static.trc") + " " + P("sim/hip_star_arc_l.trc") + " " +
                               P("sim/knee_flexion_l.trc");
    r = Mocap("fit --model " + P("sim/nominal.model.json") + trials + " --threads 2 --out " +
              P("good/fitted.json") + " --report " + P("good/report.json") + " --html " + P("good/report.html"));
    ASSERT_EQ(r.status, 0) << r.output;
    // A fit stopped by its iteration limit, on the same trials.
    r = Mocap("fit --model " + P("sim/nominal.model.json") + trials + " --threads 2 --max-iterations 2 --out " +
              P("short/fitted.json") + " --report " + P("short/report.json") + " --html " + P("short/report.html"));
    ASSERT_EQ(r.status, 0) << r.output;
    // A fit with an outlying marker: RASI 4 cm off in the knee trial (a marker that slipped; the pelvis
    // cluster's other three markers keep the pose from absorbing it).
    formats::MarkerTrial knee;
    ASSERT_TRUE(formats::ReadTrc(P("sim/knee_flexion_l.trc"), &knee));
    int m = -1;
    for (int i = 0; i < knee.num_markers(); ++i)
      if (knee.marker_names[i] == "RASI") m = i;
    ASSERT_GE(m, 0);
    for (int f = 0; f < knee.num_frames(); ++f) knee.positions(f, 3 * m + 0) += 0.04;
    fs::create_directories(Dir() / "outlier");
    ASSERT_TRUE(formats::WriteTrc(P("outlier/knee_flexion_l.trc"), knee));
    r = Mocap("fit --model " + P("sim/nominal.model.json") + " " + P("sim/static.trc") + " " +
              P("sim/hip_star_arc_l.trc") + " " + P("outlier/knee_flexion_l.trc") + " --threads 2 --out " +
              P("outlier/fitted.json") + " --report " + P("outlier/report.json") + " --html " +
              P("outlier/report.html"));
    ASSERT_EQ(r.status, 0) << r.output;
  }
  using CommandResult = testutil::CommandResult;

  static nlohmann::json Json(const std::string& rel) { return nlohmann::json::parse(ReadBytes(P(rel))); }
  static Model LoadModel(const std::string& rel) {
    Model m;
    EXPECT_TRUE(LoadModelJson(P(rel), &m));
    return m;
  }
};

std::map<std::string, std::string> AttributesOf(const std::string& element) {
  std::map<std::string, std::string> out;
  static const std::regex kAttr(R"re(([\w-]+)="([^"]*)")re");
  for (std::sregex_iterator it(element.begin(), element.end(), kAttr), end; it != end; ++it)
    out[(*it)[1]] = (*it)[2];
  return out;
}

TEST_F(Report, ThreeViewsPlaceEveryJointCentreWhereTheModelPutsIt) {
  const std::string html = ReadBytes(P("good/report.html"));
  // Lab frame Z up, X anterior, Y left (model/default_model.h): front (Y, Z), side (X, Z), top (Y, -X).
  const std::map<std::string, std::pair<Eigen::Vector3d, Eigen::Vector3d>> views = {
      {"front", {Eigen::Vector3d::UnitY(), Eigen::Vector3d::UnitZ()}},
      {"side", {Eigen::Vector3d::UnitX(), Eigen::Vector3d::UnitZ()}},
      {"top", {Eigen::Vector3d::UnitY(), -Eigen::Vector3d::UnitX()}}};
  std::map<std::string, Model> models = {{"fitted", LoadModel("good/fitted.json")},
                                         {"nominal", LoadModel("sim/nominal.model.json")}};
  int checked = 0;
  std::set<std::string> seen_views;
  static const std::regex kGroup(R"re(<g class="view"[^>]*>)re");
  for (std::sregex_iterator g(html.begin(), html.end(), kGroup), end; g != end; ++g) {
    auto a = AttributesOf(g->str());
    const std::string view = a["data-view"];
    ASSERT_TRUE(views.count(view)) << view;
    seen_views.insert(view);
    const double scale = std::stod(a["data-scale"]), ox = std::stod(a["data-ox"]), oy = std::stod(a["data-oy"]);
    EXPECT_GT(scale, 50.0) << "a 1.8 m subject drawn in a few pixels?";
    const size_t from = g->position() + g->length(), to = html.find("</g>", from);
    const std::string body = html.substr(from, to - from);
    for (auto& [kind, model] : models) {
      const Geometry geometry(model);
      ModelData data(model);
      ForwardKinematics(model, geometry, model.DefaultCoordinates(), &data);
      const std::regex circle("<circle[^>]*class=\"joint " + kind + "\"[^>]*>");
      std::set<std::string> drawn;
      for (std::sregex_iterator c(body.begin(), body.end(), circle), cend; c != cend; ++c) {
        auto ca = AttributesOf(c->str());
        const int j = model.FindJoint(ca["data-joint"]);
        ASSERT_GE(j, 0) << ca["data-joint"];
        const Eigen::Vector3d centre = JointCentre(model, data, j);
        const auto& [h, v] = views.at(view);
        EXPECT_NEAR(std::stod(ca["cx"]), ox + scale * centre.dot(h), 2e-3) << view << " " << kind << " " << ca["data-joint"];
        EXPECT_NEAR(std::stod(ca["cy"]), oy - scale * centre.dot(v), 2e-3) << view << " " << kind << " " << ca["data-joint"];
        drawn.insert(ca["data-joint"]);
        ++checked;
      }
      EXPECT_EQ(static_cast<int>(drawn.size()), model.num_joints()) << view << " " << kind;
    }
  }
  EXPECT_EQ(seen_views, (std::set<std::string>{"front", "side", "top"}));
  EXPECT_EQ(checked, 3 * (models["fitted"].num_joints() + models["nominal"].num_joints()));
}

TEST_F(Report, GoodFitShowsNoAlarmAndIsSelfContained) {
  const std::string html = ReadBytes(P("good/report.html"));
  const auto report = Json("good/report.json");
  ASSERT_TRUE(report["converged"].get<bool>());
  ASSERT_TRUE(report["outlier_markers"].empty());
  EXPECT_EQ(html.find("id=\"not-converged\""), std::string::npos);
  EXPECT_EQ(html.find("id=\"outliers\""), std::string::npos);
  EXPECT_EQ(html.find("bar outlier"), std::string::npos);
  // Per-frame RMS in the JSON: one value per frame of each trial.
  for (const auto& t : report["per_trial"]) EXPECT_EQ(t["per_frame_rms_mm"].size(), t["frames"].get<size_t>());
  EXPECT_EQ(report["iteration_history"].size(), report["iterations"].get<size_t>());
  // The convergence plot's marker RMS is the solver's, measured after each iteration (not derived
  // from the cost, which holds the priors): it ends at the solver's figure, over the frames as
  // fitted (the static trial as its mean posture). The report's marker RMS is over the frames as
  // measured: the trials' own figures combined by their samples.
  ASSERT_FALSE(report["iteration_history"].empty());
  for (const auto& it : report["iteration_history"]) {
    ASSERT_TRUE(it["marker_rms_mm"].is_number()) << it.dump();
    EXPECT_LT(it["marker_rms_mm"].get<double>(), report["initial_marker_rms_mm"].get<double>());
  }
  EXPECT_NEAR(report["iteration_history"].back()["marker_rms_mm"].get<double>(),
              report["fitted_marker_rms_mm"].get<double>(), 1e-9);
  double sum_sq = 0, samples = 0;
  for (const auto& t : report["per_trial"]) {
    sum_sq += std::pow(t["marker_rms_mm"].get<double>(), 2) * t["marker_samples"].get<double>();
    samples += t["marker_samples"].get<double>();
  }
  ASSERT_GT(samples, 0);
  EXPECT_NEAR(report["marker_rms_mm"].get<double>(), std::sqrt(sum_sq / samples), 1e-9);
  // This fit has a static trial, so the two differ and the page says why its plot ends lower.
  ASSERT_FALSE(report["static_trials"].empty());
  EXPECT_GT(report["marker_rms_mm"].get<double>() - report["fitted_marker_rms_mm"].get<double>(), 0.01);
  EXPECT_NE(html.find("over the frames as fitted"), std::string::npos);
  EXPECT_NE(html.find("marker RMS (mm, log scale)"), std::string::npos);
  EXPECT_EQ(html.find("√(2 cost / residuals)"), std::string::npos);
  // Nothing fetched: no script, stylesheet link, import, url() or remote address (the SVG
  // namespace is an identifier, not fetched).
  std::string stripped = std::regex_replace(html, std::regex("xmlns=\"http://www.w3.org/2000/svg\""), "");
  for (const char* s : {"<script", "<link", "@import", "url(", "http:", "https:", "<img", "@font-face"})
    EXPECT_EQ(stripped.find(s), std::string::npos) << s;
  EXPECT_NE(html.find("@media print"), std::string::npos);
  EXPECT_NE(html.find("size: A4"), std::string::npos);
}

TEST_F(Report, UndeterminedParametersAreGreyedAndListed) {
  const auto report = Json("good/report.json");
  const std::string html = ReadBytes(P("good/report.html"));
  // Only the left hip and knee moved: the right side's centres cannot be determined.
  ASSERT_FALSE(report["undetermined"].empty());
  EXPECT_NE(html.find("id=\"undetermined\""), std::string::npos);
  for (const auto& u : report["undetermined"])
    EXPECT_NE(html.find("<li class=\"undetermined\">" + u.get<std::string>()), std::string::npos) << u;
  // A joint row is greyed exactly when one of its centre coordinates is undetermined.
  std::set<std::string> undetermined_joints;
  for (const auto& u : report["undetermined"]) {
    const std::string n = u.get<std::string>();
    const size_t at = n.find(".centre.");
    if (at != std::string::npos) undetermined_joints.insert(n.substr(0, at));
  }
  ASSERT_FALSE(undetermined_joints.empty()) << report["undetermined"];
  const Model fitted = LoadModel("good/fitted.json");
  for (const Joint& j : fitted.joints()) {
    if (j.parent < 0) continue;
    const bool greyed = html.find("<tr class=\"undetermined\" data-joint=\"" + j.name + "\"") != std::string::npos;
    EXPECT_EQ(greyed, undetermined_joints.count(j.name) > 0) << j.name;
  }
}

TEST_F(Report, FitStoppedByTheIterationLimitSaysItDidNotConverge) {
  const auto report = Json("short/report.json");
  ASSERT_FALSE(report["converged"].get<bool>());
  const std::string html = ReadBytes(P("short/report.html"));
  const size_t at = html.find("id=\"not-converged\"");
  ASSERT_NE(at, std::string::npos);
  EXPECT_NE(html.find(report["termination"].get<std::string>(), at), std::string::npos);
  EXPECT_NE(html.find("after 2 iterations"), std::string::npos);
}

TEST_F(Report, DisplacedMarkerIsFlaggedAndNamed) {
  const auto report = Json("outlier/report.json");
  ASSERT_TRUE(report["outlier_markers"].contains("RASI")) << report["outlier_markers"];
  const std::string html = ReadBytes(P("outlier/report.html"));
  const size_t at = html.find("id=\"outliers\"");
  ASSERT_NE(at, std::string::npos);
  const size_t end = html.find("</div>", at);
  for (const auto& [name, rms] : report["outlier_markers"].items())
    EXPECT_NE(html.substr(at, end - at).find("<b>" + name + "</b>"), std::string::npos) << name;
  // Its bar is red, and only the outliers' bars are.
  int red_bars = 0;
  static const std::regex kBar(R"re(<rect[^>]*class="bar outlier"[^>]*>)re");
  for (std::sregex_iterator b(html.begin(), html.end(), kBar), e; b != e; ++b) {
    ++red_bars;
    EXPECT_TRUE(report["outlier_markers"].contains(AttributesOf(b->str())["data-marker"])) << b->str();
  }
  EXPECT_EQ(red_bars, static_cast<int>(report["outlier_markers"].size()));
  EXPECT_NE(html.find("class=\"marker outlier\" data-marker=\"RASI\""), std::string::npos);
  // Why: off in the one trial where it was displaced (solver/marker_diagnosis.h), on the page too.
  nlohmann::json rasi;
  for (const auto& d : report["marker_diagnoses"])
    if (d["marker"] == "RASI") rasi = d;
  ASSERT_TRUE(rasi.is_object()) << report["marker_diagnoses"];
  EXPECT_EQ(rasi["kind"], "mislabelled stretch") << rasi;
  EXPECT_NE(rasi["trial"].get<std::string>().find("knee_flexion_l"), std::string::npos) << rasi;
  EXPECT_NE(rasi["text"].get<std::string>().find("alone, all its frames"), std::string::npos) << rasi;
  // Least squares parks the marker between its two places, nearer the trial with more frames:
  // more than half the 4 cm displacement shows in the displaced trial.
  EXPECT_GT(rasi["stretch_rms_mm"].get<double>(), 20.0) << rasi;
  EXPECT_LT(rasi["elsewhere_rms_mm"].get<double>(), 10.0) << rasi;
  EXPECT_NE(html.find("<li data-marker=\"RASI\" data-kind=\"mislabelled stretch\">", at), std::string::npos);
}

TEST_F(Report, RejectsAReportThatIsNotAFitReport) {
  report::FitReportPage page;
  ASSERT_TRUE(report::FitReportPageFromJson(ReadBytes(P("good/report.json")),
                                            ReadBytes(P("sim/nominal.model.json")),
                                            ReadBytes(P("good/fitted.json")), &page));
  std::string html = "untouched";
  page.report.erase("per_marker_rms_mm");
  const Status s = report::WriteFitReportHtml(page, &html);
  ASSERT_FALSE(s);
  EXPECT_NE(s.message().find("per_marker_rms_mm"), std::string::npos) << s.message();
  EXPECT_EQ(html, "untouched");
  EXPECT_FALSE(report::FitReportPageFromJson("{not json", ReadBytes(P("sim/nominal.model.json")),
                                             ReadBytes(P("good/fitted.json")), &page));
}

// The CLI's optional inputs: the functional estimate beside each fitted centre (the distance is
// the report's RMS of the joint's virtual marker, solver/functional_joints.h) and the protocol's
// coverage by the trials named after its movements, checked on the fitted poses.
TEST_F(Report, FunctionalEstimatesAndProtocolCoverageWhenGiven) {
  CommandResult r = Mocap("sim --out " + P("medial") + " --seed 3 --duration-scale 0.5 --medial");
  ASSERT_EQ(r.status, 0) << r.output;
  r = Mocap("fit --model " + P("medial/nominal.model.json") + " " + P("medial/static.trc") + " " +
            P("medial/hip_star_arc_l.trc") + " " + P("medial/knee_flexion_l.trc") + " " + P("medial/ankle_circles.trc") +
            " --threads 2 --functional hip_l --protocol default --out " + P("functional/fitted.json") +
            " --report " + P("functional/report.json") + " --html " + P("functional/report.html"));
  ASSERT_EQ(r.status, 0) << r.output;
  const auto report = Json("functional/report.json");
  const std::string html = ReadBytes(P("functional/report.html"));
  ASSERT_TRUE(report["per_marker_rms_mm"].contains("hip_l@functional"));
  char cell[64];
  std::snprintf(cell, sizeof cell, "<td>%.1f</td><td></td></tr>",
                report["per_marker_rms_mm"]["hip_l@functional"].get<double>());
  const size_t row = html.find("<tr data-joint=\"hip_l\">");
  ASSERT_NE(row, std::string::npos);
  EXPECT_EQ(html.find(cell, row), html.find("</tr>", row) - std::strlen(cell) + 5) << cell;
  EXPECT_EQ(html.find("data-marker=\"hip_l@functional\""), std::string::npos) << "a virtual marker drawn as a marker";
  // The joint checks (solver/fit_trust.h): hip_l against SCoRE on its star arc, knee_l against
  // SARA on its flexion, in their rows; a joint without 3 markers a segment says so.
  ASSERT_TRUE(report.contains("joint_checks"));
  for (const auto& [joint, trial, unit] : {std::tuple{"hip_l", "hip_star_arc_l", "centre_distance_mm"},
                                           std::tuple{"knee_l", "knee_flexion_l", "axis_angle_deg"}}) {
    SCOPED_TRACE(joint);
    const nlohmann::json* check = nullptr;
    for (const auto& jc : report["joint_checks"])
      for (const auto& t : jc["trials"])
        if (jc["joint"] == joint && t["trial"] == trial) check = &t;
    ASSERT_NE(check, nullptr);
    ASSERT_TRUE((*check)["excited"].get<bool>()) << check->dump();
    const double figure = (*check)[unit];
    EXPECT_LT(figure, std::string(unit) == "axis_angle_deg" ? 2.0 : 3.0);
    std::snprintf(cell, sizeof cell, std::string(unit) == "axis_angle_deg" ? "%.1f° axis</span>" : "%.1f mm</span> on ",
                  figure);
    const size_t at = html.find("data-joint=\"" + std::string(joint) + "\"><td>");
    ASSERT_NE(at, std::string::npos);
    const size_t found = html.find(cell, at);
    EXPECT_LT(found, html.find("</tr>", at)) << cell;
  }
  const size_t elbow = html.find("data-joint=\"elbow_l\"><td>");
  ASSERT_NE(elbow, std::string::npos);
  EXPECT_LT(html.find("no reference: fewer than 3 markers", elbow), html.find("</tr>", elbow));
  EXPECT_EQ(html.find("id=\"functional-far\""), std::string::npos);
  // Every excitation of the two movements has its row.
  int rows = 0;
  for (const char* name : {"hip_star_arc_l", "knee_flexion_l"}) {
    const sim::Movement* m = sim::DefaultProtocol().Find(name);
    ASSERT_NE(m, nullptr) << name;
    for (const sim::Excitation& e : m->excitations) {
      EXPECT_NE(html.find(std::string(">") + name + ": " + e.coordinate), std::string::npos) << name << " " << e.coordinate;
      ++rows;
    }
  }
  ASSERT_GT(rows, 2);
  // The ankle circles move the left side, then the right (the protocol's windows): two bands in
  // its strip, where the frames put them; the one-phase movements get none.
  int ankle_frames = 0;
  for (const auto& t : report["per_trial"])
    if (t["name"] == "ankle_circles") ankle_frames = t["frames"];
  ASSERT_GT(ankle_frames, 100);
  static const std::regex kBand(R"re(<rect[^>]*class="phase[^"]*"[^>]*>)re");
  std::vector<std::map<std::string, std::string>> bands;
  for (std::sregex_iterator b(html.begin(), html.end(), kBand), e; b != e; ++b) bands.push_back(AttributesOf(b->str()));
  ASSERT_EQ(bands.size(), 2u);
  EXPECT_EQ(bands[0]["data-band"], "ankle_angle_l, subtalar_angle_l");
  EXPECT_EQ(bands[1]["data-band"], "ankle_angle_r, subtalar_angle_r");
  const double plot_left = 46, plot_width = 1000 - 46 - 10;  // RmsStripsHtml's strip geometry
  const int middle = static_cast<int>(std::lround(0.5 * (ankle_frames - 1)));
  EXPECT_NEAR(std::stod(bands[0]["x"]), plot_left, 0.01);
  EXPECT_NEAR(std::stod(bands[1]["x"]), plot_left + plot_width * middle / (ankle_frames - 1), 0.01);
  EXPECT_NEAR(std::stod(bands[1]["x"]) + std::stod(bands[1]["width"]), plot_left + plot_width, 0.01);
  EXPECT_EQ(ReadBytes(P("good/report.html")).find("class=\"phase"), std::string::npos);
  EXPECT_EQ(html.find("No protocol coverage"), std::string::npos);
  EXPECT_NE(ReadBytes(P("good/report.html")).find("No protocol coverage"), std::string::npos);
}

// A check far from its functional estimate raises an alert naming the joint, its figure and
// trial, and its cell is red (the page reads the report's `far`, it does not re-judge).
TEST_F(Report, JointFarFromItsFunctionalEstimateIsFlagged) {
  report::FitReportPage page;
  ASSERT_TRUE(report::FitReportPageFromJson(ReadBytes(P("good/report.json")),
                                            ReadBytes(P("sim/nominal.model.json")),
                                            ReadBytes(P("good/fitted.json")), &page));
  page.report["joint_checks"] = nlohmann::json::array(
      {{{"joint", "hip_l"}, {"axis_joint", false}, {"best_trial", "hip_star_arc_l"},
        {"trials", {{{"trial", "hip_star_arc_l"}, {"estimated", true}, {"excited", true}, {"far", true},
                     {"frames", 250}, {"centre_distance_mm", 23.44}, {"centre_spread_mm", 4.0},
                     {"functional_std_mm", 1.5}}}},
        {"regression", {{{"method", "Harrington 2007"}, {"trial", "static"}, {"frames", 300},
                         {"pelvis_width_mm", 231.2}, {"pelvis_depth_mm", 180.0},
                         {"centre_from_regression_mm", 14.26}, {"generic_from_regression_mm", 15.0},
                         {"far", false}}}},
        {"profile", {{{"trial", "hip_star_arc_l"}, {"centre_distance_mm", 23.44}, {"delta_chi2", 3.21},
                      {"told_apart", false}}}}},
       {{"joint", "knee_l"}, {"axis_joint", true}, {"best_trial", nullptr},
        {"trials", {{{"trial", "static"}, {"estimated", true}, {"excited", false}, {"note", "too still"}}}}}});
  std::string html;
  ASSERT_TRUE(report::WriteFitReportHtml(page, &html));
  const size_t at = html.find("id=\"functional-far\"");
  ASSERT_NE(at, std::string::npos);
  EXPECT_NE(html.substr(at, html.find("</div>", at) - at).find("<b>hip_l</b> 23.4 mm on hip_star_arc_l"),
            std::string::npos);
  EXPECT_NE(html.find("<span class=\"bad\">23.4 mm</span> on hip_star_arc_l"), std::string::npos);
  // The hip's regression reference in the same cell (fit_trust.h).
  const size_t hip = html.find("data-joint=\"hip_l\"><td>");
  ASSERT_NE(hip, std::string::npos);
  EXPECT_LT(html.find("<span class=\"fd\">14.3 mm</span> from Harrington 2007's regression on static", hip),
            html.find("</tr>", hip));
  // The profile check: held at SCoRE's centre the chi-square rose by less than the data allow.
  EXPECT_LT(html.find("held at its functional centre on hip_star_arc_l: chi-square +3.2, <span class=\"bad\">the "
                      "data cannot tell the two apart</span>",
                      hip),
            html.find("</tr>", hip));
  // Without a second trial that excites the hip, no line on what the reference is worth.
  EXPECT_EQ(html.find("apart</small>", hip), std::string::npos);
  const size_t knee = html.find("data-joint=\"knee_l\"><td>");
  ASSERT_NE(knee, std::string::npos);
  EXPECT_LT(html.find("title=\"static: too still\">not excited by any trial", knee), html.find("</tr>", knee));
  // A worse minimum released and adopted (fit_trust.h, CheckFitTrustAndAdopt) says so.
  page.report["joint_checks"][0]["profile"].push_back({{"trial", "hip_star_arc_l"}, {"centre_distance_mm", 23.44},
                                                       {"delta_chi2", -19.7}, {"held_fits_better", true},
                                                       {"released", true}, {"released_delta_chi2", -31.3},
                                                       {"adopted", true}});
  ASSERT_TRUE(report::WriteFitReportHtml(page, &html));
  const size_t adopted = html.find("data-joint=\"hip_l\"><td>");
  EXPECT_LT(html.find("the fit ended in a worse minimum</span>; released from there, chi-square -31.3: <b>adopted</b>",
                      adopted),
            html.find("</tr>", adopted));
  // Two trials that excite the hip: how far apart their functional centres are (fit_trust.h).
  page.report["joint_checks"][0]["second_trial"] = "hip_star_arc_r";
  page.report["joint_checks"][0]["functional_between_trials_mm"] = 22.94;
  ASSERT_TRUE(report::WriteFitReportHtml(page, &html));
  const size_t two = html.find("data-joint=\"hip_l\"><td>");
  EXPECT_LT(html.find("the functional centres on hip_star_arc_l and hip_star_arc_r are 22.9 mm apart", two),
            html.find("</tr>", two));
  page.report["joint_checks"][0]["trials"][0]["far"] = false;
  ASSERT_TRUE(report::WriteFitReportHtml(page, &html));
  EXPECT_EQ(html.find("id=\"functional-far\""), std::string::npos);
}

struct ShellRun {
  int status;
  std::string output;
};
ShellRun Shell(const std::string& cmd) {
  FILE* pipe = popen(cmd.c_str(), "r");
  std::string out;
  char buf[4096];
  while (pipe && fgets(buf, sizeof buf, pipe)) out += buf;
  const int rc = pipe ? pclose(pipe) : -1;
  return {WIFEXITED(rc) ? WEXITSTATUS(rc) : -1, out};
}

TEST_F(Report, ChromiumRendersThePageWithTheReportsFigures) {
  if (Shell("command -v chromium").status != 0)
    GTEST_SKIP() << "chromium is not installed (scripts/deps.sh installs it): the browser check is skipped";
  const std::string page = "file://" + fs::absolute(P("good/report.html")).string();
  const std::string flags = "timeout 120 chromium --headless --no-sandbox --disable-gpu --disable-quic "
                            "--no-first-run --disable-background-networking --disable-component-update "
                            "--disable-sync --user-data-dir=" + P("chromium-profile") +
                            " --window-size=1280,2000 --enable-logging=stderr --v=0 ";
  const std::string png = P("good/report.png");
  fs::remove(png);
  const ShellRun shot = Shell(flags + "--screenshot=" + png + " " + page + " 2>&1");
  ASSERT_EQ(shot.status, 0) << shot.output;
  const ShellRun dom = Shell(flags + "--dump-dom " + page + " 2>" + P("good/dom.stderr"));
  ASSERT_EQ(dom.status, 0) << ReadBytes(P("good/dom.stderr"));
  for (const std::string& log : {shot.output, ReadBytes(P("good/dom.stderr"))}) {
    EXPECT_EQ(log.find("Uncaught"), std::string::npos) << log;
    EXPECT_EQ(log.find("CONSOLE"), std::string::npos) << log;
  }
  // The screenshot: the window's size, and a drawn page (not white, not one colour), with the
  // fitted skeleton's blue in it.
  const cv::Mat image = cv::imread(png, cv::IMREAD_COLOR);
  ASSERT_FALSE(image.empty()) << png;
  EXPECT_EQ(image.cols, 1280);
  EXPECT_EQ(image.rows, 2000);
  int non_white = 0, blue = 0;
  for (int y = 0; y < image.rows; ++y)
    for (int x = 0; x < image.cols; ++x) {
      const cv::Vec3b p = image.at<cv::Vec3b>(y, x);  // B, G, R
      non_white += (p[0] < 235 || p[1] < 235 || p[2] < 235) ? 1 : 0;
      blue += (p[0] > 150 && p[2] < 90 && p[1] > 60 && p[1] < 130) ? 1 : 0;
    }
  const double fraction = static_cast<double>(non_white) / (image.rows * image.cols);
  EXPECT_GT(fraction, 0.03) << "a blank page?";
  EXPECT_LT(fraction, 0.6) << "a page filled with one colour?";
  EXPECT_GT(blue, 500) << "no fitted skeleton or bars drawn?";
  cv::Scalar mean, sd;
  cv::meanStdDev(image, mean, sd);
  EXPECT_GT(sd[0] + sd[1] + sd[2], 30.0);

  // The rendered text holds the JSON report's figures.
  const auto report = Json("good/report.json");
  char rms[32];
  std::snprintf(rms, sizeof rms, "%.2f mm", report["marker_rms_mm"].get<double>());
  EXPECT_NE(dom.output.find(rms), std::string::npos) << rms;
  std::snprintf(rms, sizeof rms, "%.2f mm", report["initial_marker_rms_mm"].get<double>());
  EXPECT_NE(dom.output.find(rms), std::string::npos) << rms;
  const std::string iterations = "after " + std::to_string(report["iterations"].get<int>()) + " iterations";
  EXPECT_NE(dom.output.find(iterations), std::string::npos) << iterations;
  EXPECT_NE(dom.output.find(report["termination"].get<std::string>()), std::string::npos);
  for (const Joint& j : LoadModel("good/fitted.json").joints())
    EXPECT_NE(dom.output.find("<td>" + j.name + "</td>"), std::string::npos) << j.name;
  for (const auto& t : report["per_trial"])
    EXPECT_NE(dom.output.find(t["name"].get<std::string>() + " — " + std::to_string(t["frames"].get<int>()) + " frames"),
              std::string::npos)
        << t["name"];
}

}  // namespace
}  // namespace mocap
