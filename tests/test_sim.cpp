// The simulator: the protocol file, the virtual subject's perturbation bounds, and the simulated
// recordings — determinism, reached ranges, noise, soft-tissue artefact, occlusions, smoothness,
// grounding and speed, in memory — and the `mocap sim` command end to end.
#include <gtest/gtest.h>

#include <sys/wait.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>

#include "formats/mot.h"
#include "formats/trc.h"
#include "model/default_model.h"
#include "model/kinematics.h"
#include "model/model_io.h"
#include "sim/protocol.h"
#include "sim/random.h"
#include "sim/simulate.h"
#include "sim/sta_table.h"
#include "sim/subject.h"
#include "tests/cpu_time_test_util.h"
#include "tests/sim_test_util.h"

using namespace mocap;
using namespace mocap::sim;

namespace {

constexpr double kDeg = M_PI / 180.0;

SimulatedSession Simulate(const SimulationOptions& options) {
  SimulatedSession session;
  Status s = SimulateSession(options, &session);
  EXPECT_TRUE(s.ok()) << s.message();
  return session;
}

SimulationOptions NoiseFree() {
  SimulationOptions o;
  o.noise_mm = 0.0;
  return o;
}

int Column(const formats::CoordinateTable& t, const std::string& name) {
  for (size_t i = 0; i < t.column_names.size(); ++i)
    if (t.column_names[i] == name) return static_cast<int>(i);
  return -1;
}

int MarkerColumn(const formats::MarkerTrial& t, const std::string& name) {
  for (size_t i = 0; i < t.marker_names.size(); ++i)
    if (t.marker_names[i] == name) return static_cast<int>(i);
  return -1;
}

const SimulatedTrial& Trial(const SimulatedSession& s, const std::string& name) {
  for (const SimulatedTrial& t : s.trials)
    if (t.markers.name == name) return t;
  ADD_FAILURE() << "no trial " << name;
  return s.trials.front();
}

// Angle between two unit vectors, degrees.
double AngleDeg(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  return std::atan2(a.cross(b).norm(), a.dot(b)) / kDeg;
}

const char* kMinimalProtocol = R"({
  "format": "mocap-protocol", "version": 1, "name": "p",
  "movements": [{"name": "m", "duration_s": 2,
                 "excitations": [{"coordinate": "knee_angle_l", "min_deg": 0, "max_deg": 90}]}]})";

// kMinimalProtocol with `from` replaced by `to`.
std::string Edited(const std::string& from, const std::string& to) {
  std::string text = kMinimalProtocol;
  const size_t at = text.find(from);
  EXPECT_NE(at, std::string::npos) << from;
  return text.replace(at, from.size(), to);
}

}  // namespace

// ---------------------------------------------------------------------------------------------
// Protocol

TEST(Protocol, DefaultProtocolHasTheDesignedMovements) {
  const Protocol& p = DefaultProtocol();
  const std::vector<std::string> expected = {
      "static",          "hip_star_arc_l",     "hip_star_arc_r",           "knee_flexion_l",
      "knee_flexion_r",  "ankle_circles",      "squats",                   "shoulder_circles_l",
      "shoulder_circles_r", "elbow_flexion_pronation_l", "elbow_flexion_pronation_r",
      "wrist_circles_l", "wrist_circles_r",    "trunk_rom",                "neck_rom"};
  ASSERT_EQ(p.movements.size(), expected.size());
  for (size_t i = 0; i < expected.size(); ++i) EXPECT_EQ(p.movements[i].name, expected[i]);
  EXPECT_NEAR(p.TotalDuration(), 60.0, 3.0);
  Status s = ValidateProtocol(p, DefaultFullBodyModel());
  EXPECT_TRUE(s.ok()) << s.message();
  for (const Movement& m : p.movements) {
    EXPECT_FALSE(m.description.empty()) << m.name;
    if (m.name == "static") continue;
    int required = 0;
    for (const Excitation& e : m.excitations) required += e.required;
    EXPECT_GE(required, 1) << m.name;
    // arm_add is the middle angle of the shoulder's Euler sequence: keep it far from 90 deg.
    for (const char* c : {"arm_add_l", "arm_add_r"}) {
      if (const Excitation* e = m.Find(c)) {
        EXPECT_LT(std::max(-e->min_deg, e->max_deg), 50) << m.name;
      }
    }
  }
  const Excitation* hip = p.Find("hip_star_arc_l")->Find("hip_flexion_l");
  ASSERT_NE(hip, nullptr);
  EXPECT_EQ(hip->min_deg, -20);
  EXPECT_EQ(hip->max_deg, 60);
  EXPECT_EQ(p.Find("squats")->Find("knee_angle_r")->follow, "hip_flexion_l");
}

TEST(Protocol, JsonRoundTrip) {
  const Protocol& p = DefaultProtocol();
  Protocol q;
  Status s = ParseProtocolJson(ProtocolToJsonString(p), "round trip", &q);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(q.name, p.name);
  ASSERT_EQ(q.movements.size(), p.movements.size());
  for (size_t i = 0; i < p.movements.size(); ++i) {
    const Movement &a = p.movements[i], &b = q.movements[i];
    EXPECT_EQ(a.name, b.name);
    EXPECT_EQ(a.description, b.description);
    EXPECT_EQ(a.duration_s, b.duration_s);
    EXPECT_EQ(a.period_s, b.period_s);
    EXPECT_EQ(a.background, b.background);
    ASSERT_EQ(a.excitations.size(), b.excitations.size());
    for (size_t k = 0; k < a.excitations.size(); ++k) {
      const Excitation &x = a.excitations[k], &y = b.excitations[k];
      EXPECT_EQ(x.coordinate, y.coordinate);
      EXPECT_EQ(x.min_deg, y.min_deg);
      EXPECT_EQ(x.max_deg, y.max_deg);
      EXPECT_EQ(x.required, y.required);
      EXPECT_EQ(x.follow, y.follow);
      EXPECT_EQ(x.anti_phase, y.anti_phase);
      EXPECT_EQ(x.window_begin, y.window_begin);
      EXPECT_EQ(x.window_end, y.window_end);
    }
  }
}

TEST(Protocol, ParseErrorsNameTheField) {
  Protocol p;
  ASSERT_TRUE(ParseProtocolJson(kMinimalProtocol, "p.json", &p).ok());
  struct Case {
    std::string text, expected;
  };
  const std::vector<Case> cases = {
      {"{not json", "p.json: not valid JSON"},
      {Edited("\"mocap-protocol\"", "\"mocap-model\""), "p.json: format"},
      {Edited("\"version\": 1", "\"version\": 2"), "p.json: version"},
      {Edited("\"duration_s\": 2", "\"duration_s\": \"2\""), "movements[0].duration_s: expected a number"},
      {Edited("\"duration_s\": 2", "\"duration_s\": -1"), "movements[0].duration_s: must be > 0"},
      {Edited("\"name\": \"m\", \"duration_s\": 2,", ""), "movements[0].name: missing"},
      {Edited("\"name\": \"m\"", "\"name\": \"a b\""), "movements[0].name"},
      {Edited("\"min_deg\": 0", "\"min_deg\": 100"), "movements[0].excitations[0].min_deg: greater than max_deg"},
      {Edited("\"max_deg\": 90", "\"max_deg\": 90, \"window\": [0.5, 0.2]"), "movements[0].excitations[0].window"},
      {Edited("\"max_deg\": 90", "\"max_deg\": 90, \"follow\": \"hip_flexion_l\""), "movements[0].excitations[0].follow"},
      {Edited("\"max_deg\": 90", "\"max_deg\": 90, \"required\": 1"), "movements[0].excitations[0].required"},
      {Edited("\"max_deg\": 90", "\"max_deg\": 90, \"maxdeg\": 1"), "movements[0].excitations[0].maxdeg: unknown field"},
      {Edited("\"coordinate\": \"knee_angle_l\", ", ""), "movements[0].excitations[0].coordinate: missing"},
      {Edited("\"movements\": [", "\"movements\": 3, \"x\": ["), "p.json: movements: expected an array"},
  };
  for (const Case& c : cases) {
    Status s = ParseProtocolJson(c.text, "p.json", &p);
    EXPECT_FALSE(s.ok()) << c.text;
    EXPECT_NE(s.message().find(c.expected), std::string::npos)
        << "message: " << s.message() << "\nexpected to contain: " << c.expected;
  }
  Status s = LoadProtocolJson("/nonexistent/protocol.json", &p);
  EXPECT_FALSE(s.ok());
  EXPECT_NE(s.message().find("/nonexistent/protocol.json"), std::string::npos);
}

// ---------------------------------------------------------------------------------------------
// Soft-tissue artefact table

// The embedded table classes every marker of the default model (optional ones too), cites its
// sources, and gives bony landmarks a quarter of the thigh's amplitude.
TEST(StaTable, DefaultTableClassesEveryDefaultMarker) {
  StaTable parsed;
  const Status s = ParseStaTableJson(DefaultStaTableJson(), "default_sta_table.json", &parsed);
  ASSERT_TRUE(s.ok()) << s.message();
  const StaTable& t = DefaultStaTable();
  EXPECT_EQ(t.marker_class, parsed.marker_class);
  EXPECT_GE(t.references.size(), 3u);
  const Model model = DefaultFullBodyModel(1.75);
  for (const Marker& m : model.markers()) EXPECT_FALSE(t.ClassOf(m.name).empty()) << m.name;
  EXPECT_EQ(t.marker_class.size(), static_cast<size_t>(model.num_markers()));
  EXPECT_DOUBLE_EQ(t.RatioOf("LTHI"), 1.0);
  EXPECT_DOUBLE_EQ(t.RatioOf("RTHI"), 1.0);
  for (const char* bony : {"LANK", "RHEE", "LTOE", "RKNE", "LELB", "RWRA", "LWRB", "RFIN", "LASI", "C7"}) {
    EXPECT_EQ(t.ClassOf(bony), "bony_landmark") << bony;
    EXPECT_DOUBLE_EQ(t.RatioOf(bony), 0.25) << bony;
  }
  for (const char* soft : {"LTIB", "RUPA", "LFRM", "RBAK"}) {
    EXPECT_GT(t.RatioOf(soft), 0.5) << soft;
    EXPECT_LE(t.RatioOf(soft), 1.0) << soft;
  }
  for (const auto& [name, c] : t.classes) EXPECT_FALSE(c.basis.empty()) << name;
  // A marker of an imported model that the table does not know: soft tissue, the pessimistic
  // choice.
  EXPECT_EQ(t.ClassOf("L_FLE_cluster3"), "");
  EXPECT_DOUBLE_EQ(t.RatioOf("L_FLE_cluster3"), 1.0);
}

TEST(StaTable, ParseErrorsNameTheField) {
  const std::string minimal =
      R"({"format": "mocap-sta-table", "version": 1,
          "classes": {"bony": {"ratio": 0.25}, "thigh": {"ratio": 1}},
          "markers": {"LANK": "bony", "LTHI": "thigh"}})";
  StaTable t;
  ASSERT_TRUE(ParseStaTableJson(minimal, "t.json", &t).ok());
  EXPECT_DOUBLE_EQ(t.RatioOf("LANK"), 0.25);
  auto edited = [&](const std::string& from, const std::string& to) {
    std::string text = minimal;
    text.replace(text.find(from), from.size(), to);
    return text;
  };
  const std::vector<std::pair<std::string, std::string>> cases = {
      {"{not json", "t.json: not valid JSON"},
      {edited("mocap-sta-table", "mocap-protocol"), "t.json: format"},
      {edited("\"version\": 1", "\"version\": 2"), "t.json: version"},
      {edited("\"ratio\": 0.25", "\"ratio\": -0.25"), "t.json: classes.bony.ratio: must be >= 0"},
      {edited("\"ratio\": 0.25", "\"ratio\": \"a quarter\""), "t.json: classes.bony.ratio: expected a number"},
      {edited("{\"ratio\": 1}", "{}"), "t.json: classes.thigh.ratio: missing"},
      {edited("{\"ratio\": 1}", "{\"ratio\": 1, \"rato\": 2}"), "t.json: classes.thigh.rato: unknown field"},
      {edited("\"LTHI\": \"thigh\"", "\"LTHI\": \"thig\""), "t.json: markers.LTHI: class 'thig' is not in classes"},
      {edited("\"LTHI\": \"thigh\"", "\"LTHI\": 1"), "t.json: markers.LTHI: expected a class name"},
      {edited("\"markers\"", "\"marker\""), "t.json: marker: unknown field"},
  };
  for (const auto& [text, expected] : cases) {
    const Status s = ParseStaTableJson(text, "t.json", &t);
    EXPECT_FALSE(s.ok()) << text;
    EXPECT_NE(s.message().find(expected), std::string::npos)
        << "message: " << s.message() << "\nexpected to contain: " << expected;
  }
}

TEST(Protocol, ValidateAgainstTheModel) {
  const Model model = DefaultFullBodyModel();
  Protocol p;
  ASSERT_TRUE(ParseProtocolJson(Edited("knee_angle_l", "knee_angle_x"), "p", &p).ok());
  Status s = ValidateProtocol(p, model);
  EXPECT_FALSE(s.ok());
  EXPECT_NE(s.message().find("'knee_angle_x' is not in model"), std::string::npos) << s.message();
  ASSERT_TRUE(ParseProtocolJson(Edited("knee_angle_l", "pelvis_tx"), "p", &p).ok());
  EXPECT_NE(ValidateProtocol(p, model).message().find("translation"), std::string::npos);
  ASSERT_TRUE(ParseProtocolJson(Edited("\"max_deg\": 90", "\"max_deg\": 170"), "p", &p).ok());
  EXPECT_NE(ValidateProtocol(p, model).message().find("limits"), std::string::npos);
}

TEST(Protocol, CheckExcitationsReportsWhatWasReached) {
  Protocol p;
  ASSERT_TRUE(ParseProtocolJson(kMinimalProtocol, "p", &p).ok());
  formats::CoordinateTable t;
  t.column_names = {"knee_angle_l"};
  t.values.resize(3, 1);
  t.values << 5, 92, std::nan("");
  auto checks = CheckExcitations(p.movements[0], t);
  ASSERT_EQ(checks.size(), 1u);
  EXPECT_FALSE(checks[0].ok);  // min 0 not reached
  EXPECT_DOUBLE_EQ(checks[0].reached_min_deg, 5);
  EXPECT_DOUBLE_EQ(checks[0].reached_max_deg, 92);
  EXPECT_TRUE(CheckExcitations(p.movements[0], t, 5.0)[0].ok);
  t.in_degrees = false;  // radians: 92 rad is beyond, 5 rad is not below 0
  EXPECT_FALSE(CheckExcitations(p.movements[0], t)[0].ok);
  t.column_names = {"hip_flexion_l"};
  EXPECT_TRUE(std::isnan(CheckExcitations(p.movements[0], t)[0].reached_min_deg));
}

// The live check (a tracker on a model before its fit): the span must be reached, the range may
// sit up to max_offset_deg from the protocol's.
TEST(Protocol, CheckExcitationsBySpanAllowsAnOffsetZero) {
  Protocol p;
  ASSERT_TRUE(ParseProtocolJson(kMinimalProtocol, "p", &p).ok());
  const Excitation& e = p.movements[0].excitations[0];
  const double span = e.max_deg - e.min_deg;
  formats::CoordinateTable t;
  t.column_names = {e.coordinate};
  t.values.resize(2, 1);
  ExcitationCheckOptions o;
  o.tolerance_deg = 3;
  o.max_offset_deg = 20;
  t.values << e.min_deg - 15, e.max_deg - 15;  // the whole span, 15 deg off
  EXPECT_TRUE(CheckExcitations(p.movements[0], t, o)[0].ok);
  EXPECT_FALSE(CheckExcitations(p.movements[0], t)[0].ok);  // absolute ranges: not reached
  t.values << e.min_deg - 25, e.max_deg - 25;  // too far off
  EXPECT_FALSE(CheckExcitations(p.movements[0], t, o)[0].ok);
  t.values << e.min_deg, e.min_deg + span - 4;  // 4 deg short of the span
  EXPECT_FALSE(CheckExcitations(p.movements[0], t, o)[0].ok);
  t.values << e.min_deg + 2, e.min_deg + span;  // 2 deg short: within the tolerance
  EXPECT_TRUE(CheckExcitations(p.movements[0], t, o)[0].ok);
  t.values << e.min_deg, e.min_deg + 0.4 * span;  // 40 % of the range
  EXPECT_FALSE(CheckExcitations(p.movements[0], t, o)[0].ok);
  o.tolerance_fraction = 0.15;  // 15 % of the span: 13.5 deg of knee_angle_l's 90
  t.values << e.min_deg + 13, e.min_deg + span;
  EXPECT_TRUE(CheckExcitations(p.movements[0], t, o)[0].ok);
  t.values << e.min_deg + 14, e.min_deg + span;
  EXPECT_FALSE(CheckExcitations(p.movements[0], t, o)[0].ok);
}

// ---------------------------------------------------------------------------------------------
// Virtual subject

TEST(Subject, PerturbationsStayWithinTheirBounds) {
  const SubjectOptions o;
  for (std::uint64_t seed : {1, 2, 3, 17, 12345}) {
    VirtualSubject v;
    ASSERT_TRUE(MakeVirtualSubject(seed, o, &v).ok());
    SCOPED_TRACE("seed " + std::to_string(seed));
    EXPECT_GE(v.height_m, 1.55);
    EXPECT_LE(v.height_m, 1.95);
    const Model &n = v.nominal, &t = v.truth;
    ASSERT_EQ(n.num_markers(), 43);
    ASSERT_EQ(t.num_markers(), 43);
    double max_scale = 0, max_centre = 0, max_axis = 0, max_marker = 0;
    for (int s = 0; s < n.num_segments(); ++s) {
      const double r = t.segments()[s].scale / n.segments()[s].scale;
      EXPECT_GE(r, 0.9);
      EXPECT_LE(r, 1.1);
      max_scale = std::max(max_scale, std::abs(r - 1));
    }
    for (int j = 0; j < n.num_joints(); ++j) {
      const Joint &jn = n.joints()[j], &jt = t.joints()[j];
      ASSERT_EQ(jn.name, jt.name);
      if (jn.parent >= 0) {
        // The actual centre in the true parent, against the nominal one in the same parent.
        const double d = t.segments()[jt.parent].scale * (jt.centre - jn.centre).norm();
        EXPECT_LE(d, 0.015 + 1e-12) << jn.name;
        max_centre = std::max(max_centre, d);
      }
      for (size_t e = 0; e < jn.elements.size(); ++e) {
        const double a = AngleDeg(jn.elements[e].axis, jt.elements[e].axis);
        if (!jn.elements[e].fitted_axis) {
          EXPECT_LT(a, 1e-9) << jn.name;
          continue;
        }
        EXPECT_LE(a, 5.0 + 1e-9) << jn.name << " element " << e;
        max_axis = std::max(max_axis, a);
      }
    }
    for (int m = 0; m < n.num_markers(); ++m) {
      const int s = t.markers()[m].segment;
      const double d = t.segments()[s].scale * (t.markers()[m].position - n.markers()[m].position).norm();
      EXPECT_LE(d, 0.010 + 1e-12) << n.markers()[m].name;
      max_marker = std::max(max_marker, d);
    }
    // Perturbed, and across the range (uniform draws over ~15-40 objects come near the bound).
    EXPECT_GT(max_scale, 0.05);
    EXPECT_GT(max_centre, 0.009);
    EXPECT_GT(max_axis, 3.0);
    EXPECT_GT(max_marker, 0.007);
    // truth_parameters reproduce the truth.
    const Eigen::VectorXd p = v.truth_parameters;
    EXPECT_TRUE(t.InitialParameters().head(n.num_segments()).isApprox(p.head(n.num_segments())));
  }
}

TEST(Subject, DeterministicPerSeed) {
  VirtualSubject a, b, c;
  ASSERT_TRUE(MakeVirtualSubject(7, {}, &a).ok());
  ASSERT_TRUE(MakeVirtualSubject(7, {}, &b).ok());
  ASSERT_TRUE(MakeVirtualSubject(8, {}, &c).ok());
  EXPECT_EQ(a.height_m, b.height_m);
  EXPECT_TRUE(a.truth_parameters == b.truth_parameters);
  EXPECT_NE(a.height_m, c.height_m);
  EXPECT_NE(a.truth_parameters.size(), 0);
}

TEST(Random, StreamsAreIndependentAndNormalIsStandard) {
  Random a(1, Stream::kNoise, 0), b(1, Stream::kNoise, 1), c(1, Stream::kNoise, 0);
  EXPECT_NE(a.Uniform(), b.Uniform());
  Random d(1, Stream::kNoise, 0);
  EXPECT_EQ(c.Uniform(), d.Uniform());
  double sum = 0, sum2 = 0;
  const int n = 200000;
  for (int i = 0; i < n; ++i) {
    const double x = a.Normal();
    sum += x;
    sum2 += x * x;
  }
  EXPECT_NEAR(sum / n, 0.0, 0.01);
  EXPECT_NEAR(std::sqrt(sum2 / n), 1.0, 0.01);
}

// ---------------------------------------------------------------------------------------------
// Simulation

TEST(Simulation, OptionsAreValidated) {
  std::string error;
  EXPECT_TRUE(SimulationOptions().IsValid(&error)) << error;
  struct Case {
    void (*edit)(SimulationOptions*);
    const char* name;
  };
  const Case cases[] = {
      {[](SimulationOptions* o) { o->noise_mm = -0.1; }, "noise_mm"},
      {[](SimulationOptions* o) { o->noise_mm = NAN; }, "noise_mm"},
      {[](SimulationOptions* o) { o->sta_mm = -1; }, "sta_mm"},
      {[](SimulationOptions* o) { o->missing = -0.01; }, "missing"},
      {[](SimulationOptions* o) { o->missing = 0.9; }, "missing"},
      {[](SimulationOptions* o) { o->rate_hz = 0; }, "rate_hz"},
      {[](SimulationOptions* o) { o->rate_hz = -100; }, "rate_hz"},
      {[](SimulationOptions* o) { o->duration_scale = 0; }, "duration_scale"},
      {[](SimulationOptions* o) { o->duration_scale = INFINITY; }, "duration_scale"},
      {[](SimulationOptions* o) { o->subject.axis_deg = -1; }, "subject.axis_deg"},
      {[](SimulationOptions* o) { o->subject.max_height_m = 1.0; }, "subject.max_height_m"},
  };
  for (const Case& c : cases) {
    SimulationOptions o;
    c.edit(&o);
    error.clear();
    EXPECT_FALSE(o.IsValid(&error)) << c.name;
    EXPECT_NE(error.find(c.name), std::string::npos) << error;
    SimulatedSession s;
    Status st = SimulateSession(o, &s);
    EXPECT_FALSE(st.ok());
    EXPECT_NE(st.message().find(c.name), std::string::npos) << st.message();
  }
}

TEST(Simulation, SameSeedSameSessionOtherSeedOther) {
  SimulationOptions o;
  o.sta_mm = 5;
  o.missing = 0.05;
  const SimulatedSession a = Simulate(o), b = Simulate(o);
  ASSERT_EQ(a.trials.size(), b.trials.size());
  for (size_t i = 0; i < a.trials.size(); ++i) {
    const auto &pa = a.trials[i].markers.positions, &pb = b.trials[i].markers.positions;
    ASSERT_EQ(pa.rows(), pb.rows());
    // Bit-identical, NaNs at the same places.
    EXPECT_EQ(0, std::memcmp(pa.data(), pb.data(), sizeof(double) * pa.size())) << i;
    EXPECT_TRUE(a.trials[i].coordinates.values == b.trials[i].coordinates.values);
  }
  o.seed = 2;
  const SimulatedSession c = Simulate(o);
  EXPECT_NE(a.height_m, c.height_m);
  const auto &pa = a.trials[0].markers.positions, &pc = c.trials[0].markers.positions;
  EXPECT_NE(0, std::memcmp(pa.data(), pc.data(), sizeof(double) * std::min(pa.size(), pc.size())));
}

TEST(Simulation, NoiseDoesNotChangeTheMotion) {
  SimulationOptions o = NoiseFree();
  const SimulatedSession a = Simulate(o);
  o.noise_mm = 2.0;
  o.missing = 0.2;
  o.sta_mm = 8;
  const SimulatedSession b = Simulate(o);
  for (size_t i = 0; i < a.trials.size(); ++i)
    EXPECT_TRUE(a.trials[i].coordinates.values == b.trials[i].coordinates.values);
  EXPECT_TRUE(a.truth_parameters == b.truth_parameters);
}

TEST(Simulation, FrameCountsTimesAndNames) {
  const SimulatedSession s = Simulate(SimulationOptions());
  EXPECT_NEAR(s.total_frames(), 6000, 10);
  ASSERT_EQ(s.trials.size(), s.protocol.movements.size());
  for (size_t i = 0; i < s.trials.size(); ++i) {
    const SimulatedTrial& t = s.trials[i];
    EXPECT_EQ(t.markers.name, s.protocol.movements[i].name);
    EXPECT_EQ(t.coordinates.name, t.markers.name);
    EXPECT_EQ(t.markers.rate_hz, 100.0);
    EXPECT_EQ(t.markers.num_frames(), std::lround(s.protocol.movements[i].duration_s * 100));
    ASSERT_EQ(static_cast<int>(t.markers.frame_numbers.size()), t.markers.num_frames());
    EXPECT_EQ(t.markers.frame_numbers.front(), 1);
    EXPECT_EQ(t.markers.frame_numbers.back(), t.markers.num_frames());
    EXPECT_EQ(t.markers.times.front(), 0.0);
    EXPECT_NEAR(t.markers.times[1], 0.01, 1e-15);
    EXPECT_EQ(t.coordinates.times, t.markers.times);
    EXPECT_EQ(t.coordinates.values.rows(), t.markers.num_frames());
    EXPECT_EQ(t.coordinates.values.cols(), 38);
    EXPECT_TRUE(t.coordinates.in_degrees);
    EXPECT_EQ(t.markers.num_markers(), 39);
    EXPECT_EQ(t.markers.positions.cols(), 3 * 39);
  }
  // The models carry exactly the recorded markers (an unrecorded marker cannot be fitted).
  EXPECT_EQ(s.nominal.num_markers(), 39);
  EXPECT_EQ(s.truth.num_markers(), 39);
  for (int m = 0; m < 39; ++m) {
    EXPECT_EQ(s.nominal.markers()[m].name, s.trials[0].markers.marker_names[m]);
    EXPECT_EQ(s.truth.markers()[m].name, s.trials[0].markers.marker_names[m]);
  }

  SimulationOptions o;
  o.duration_scale = 2.5;
  EXPECT_NEAR(Simulate(o).total_frames(), 15000, 10);
  o.duration_scale = 1;
  o.rate_hz = 250;
  EXPECT_NEAR(Simulate(o).total_frames(), 15000, 10);
}

TEST(Simulation, MedialMarkersOnRequest) {
  SimulationOptions o;
  o.medial_markers = true;
  o.duration_scale = 0.2;
  const SimulatedSession s = Simulate(o);
  const formats::MarkerTrial& t = s.trials[0].markers;
  EXPECT_EQ(t.num_markers(), 43);
  for (const char* m : {"LKNM", "RKNM", "LMMA", "RMMA"}) EXPECT_GE(MarkerColumn(t, m), 0) << m;
  o.medial_markers = false;
  const formats::MarkerTrial& u = Simulate(o).trials[0].markers;
  EXPECT_EQ(MarkerColumn(u, "LKNM"), -1);
  EXPECT_GE(MarkerColumn(u, "LKNE"), 0);
}

TEST(Simulation, EveryMovementReachesItsExcitations) {
  for (double scale : {1.0, 0.5, 3.0}) {
    SimulationOptions o;
    o.duration_scale = scale;
    o.seed = scale == 1.0 ? 1 : 5;
    const SimulatedSession s = Simulate(o);
    for (size_t i = 0; i < s.trials.size(); ++i)
      ExpectExcitationsReached(s.protocol.movements[i], s.trials[i].coordinates,
                               "scale " + std::to_string(scale));
  }
}

TEST(Simulation, NeutralPoseWanderAndArmsAwayFromTheBody) {
  const SimulatedSession s = Simulate(NoiseFree());
  for (const SimulatedTrial& t : s.trials) {
    const auto& v = t.coordinates.values;
    const int last = static_cast<int>(v.rows()) - 1;
    // Start and end near the neutral pose: every joint angle (not the pelvis) within a few
    // degrees of the static trial's mean.
    const Eigen::RowVectorXd neutral = Trial(s, "static").coordinates.values.colwise().mean();
    for (int c = 6; c < v.cols(); ++c) {
      EXPECT_NEAR(v(0, c), neutral[c], 8) << t.markers.name << " " << t.coordinates.column_names[c];
      EXPECT_NEAR(v(last, c), neutral[c], 8) << t.markers.name << " " << t.coordinates.column_names[c];
    }
    // Joints that are not the target still move a little.
    for (const char* c : {"lumbar_bending", "elbow_flex_r", "hip_rotation_l"}) {
      const Movement* m = s.protocol.Find(t.markers.name);
      if (m->Find(c)) continue;
      const int col = Column(t.coordinates, c);
      const double range = v.col(col).maxCoeff() - v.col(col).minCoeff();
      EXPECT_GT(range, 0.05) << t.markers.name << " " << c;
      EXPECT_LT(range, 12.0) << t.markers.name << " " << c;
    }
    // Arms away from the body except in the shoulder movements.
    for (const char* c : {"arm_add_l", "arm_add_r"}) {
      if (s.protocol.Find(t.markers.name)->Find(c)) continue;
      const int col = Column(t.coordinates, c);
      EXPECT_LE(v.col(col).maxCoeff(), -15.0 + 1e-9) << t.markers.name;
      EXPECT_GE(v.col(col).minCoeff(), -25.0 - 1e-9) << t.markers.name;
    }
  }
}

TEST(Simulation, MotionIsSmooth) {
  // C2 motion has a bounded third derivative, so the largest third difference / dt^3 converges
  // as the rate grows; a jump in acceleration would make it grow like 1 / dt.
  auto max_jerk = [](double rate) {
    SimulationOptions o = NoiseFree();
    o.rate_hz = rate;
    const SimulatedSession s = Simulate(o);
    std::vector<Eigen::ArrayXd> out;
    for (const SimulatedTrial& t : s.trials) {
      const auto& v = t.coordinates.values;
      Eigen::ArrayXd jerk = Eigen::ArrayXd::Zero(v.cols());
      for (int c = 0; c < v.cols(); ++c)
        for (int f = 3; f < v.rows(); ++f)
          jerk[c] = std::max(jerk[c], std::abs(v(f, c) - 3 * v(f - 1, c) + 3 * v(f - 2, c) - v(f - 3, c)) * rate * rate * rate);
      out.push_back(jerk);
    }
    return std::make_pair(s.protocol, out);
  };
  const auto [protocol, low] = max_jerk(500);
  const auto high = max_jerk(2000).second;
  for (size_t i = 0; i < low.size(); ++i)
    for (int c = 0; c < low[i].size(); ++c)
      EXPECT_LT(high[i][c], 1.3 * low[i][c] + 1e-6)
          << protocol.movements[i].name << " coordinate " << c << ": " << low[i][c] << " -> " << high[i][c];
}

TEST(Simulation, MarkersAreTheTrueModelsForwardKinematics) {
  const SimulatedSession s = Simulate(NoiseFree());
  const Model& truth = s.truth;
  const std::vector<int> markers = SimulatedMarkers(truth, false);
  Geometry g(truth);
  ModelData d(truth);
  for (const SimulatedTrial& t : s.trials) {
    for (int f : {0, t.markers.num_frames() / 3, t.markers.num_frames() - 1}) {
      const Eigen::VectorXd z = TrueCoordinates(truth, t.coordinates, f);
      ForwardKinematics(truth, g, z, &d);
      for (size_t i = 0; i < markers.size(); ++i) {
        ASSERT_EQ(t.markers.marker_names[i], truth.markers()[markers[i]].name);
        EXPECT_LT((t.markers.At(f, static_cast<int>(i)) - MarkerPosition(truth, g, d, markers[i])).norm(),
                  1e-9);
      }
    }
  }
}

TEST(Simulation, StaticTrialStandsOnTheFloor) {
  const SimulatedSession s = Simulate(SimulationOptions());
  const formats::MarkerTrial& t = Trial(s, "static").markers;
  ASSERT_TRUE(t.positions.allFinite());
  for (int f = 0; f < t.num_frames(); ++f)
    for (int m = 0; m < t.num_markers(); ++m) {
      EXPECT_GE(t.At(f, m).z(), -0.05) << t.marker_names[m];
      EXPECT_LE(t.At(f, m).z(), s.height_m + 0.05) << t.marker_names[m];
    }
  for (const char* m : {"LHEE", "RHEE", "LTOE", "RTOE"}) {
    const int c = MarkerColumn(t, m);
    EXPECT_LT(t.positions.col(3 * c + 2).maxCoeff(), 0.10) << m;
  }
  // The head near the top, the pelvis at about half the height.
  EXPECT_GT(t.positions.col(3 * MarkerColumn(t, "LFHD") + 2).mean(), 0.85 * s.height_m);
  EXPECT_NEAR(t.positions.col(3 * MarkerColumn(t, "LASI") + 2).mean(), 0.55 * s.height_m, 0.1);
  for (const SimulatedTrial& trial : s.trials) EXPECT_TRUE(trial.markers.positions.allFinite());
}

TEST(Simulation, SquatsLowerThePelvisAndTheStanceFootStays) {
  const SimulatedSession s = Simulate(NoiseFree());
  const int tz = Column(s.trials[0].coordinates, "pelvis_tz");
  const double standing = Trial(s, "static").coordinates.values.col(tz).mean();
  const double squat_low = Trial(s, "squats").coordinates.values.col(tz).minCoeff();
  EXPECT_LT(squat_low, standing - 0.2 * s.height_m / 1.75);
  // During the left hip arc the right heel carries the weight: it barely moves horizontally,
  // apart from the planned sway of the whole body (a few cm).
  const formats::MarkerTrial& arc = Trial(s, "hip_star_arc_l").markers;
  const int heel = MarkerColumn(arc, "RHEE"), swing = MarkerColumn(arc, "LTOE");
  auto horizontal_range = [&](int m) {
    const Eigen::MatrixXd xy = arc.positions.middleCols(3 * m, 2);
    return (xy.colwise().maxCoeff() - xy.colwise().minCoeff()).norm();
  };
  EXPECT_LT(horizontal_range(heel), 0.08);
  EXPECT_GT(horizontal_range(swing), 0.3);
  // Feet stay on or above the floor in every movement.
  for (const SimulatedTrial& t : s.trials)
    for (const char* m : {"LHEE", "RHEE", "LTOE", "RTOE"})
      EXPECT_GT(t.markers.positions.col(3 * MarkerColumn(t.markers, m) + 2).minCoeff(), -0.02)
          << t.markers.name << " " << m;
}

TEST(Simulation, SubjectFacesDifferentDirections) {
  const SimulatedSession s = Simulate(NoiseFree());
  const int yaw = Column(s.trials[0].coordinates, "pelvis_rotation");
  double lo = 1e9, hi = -1e9;
  for (const SimulatedTrial& t : s.trials) {
    const auto col = t.coordinates.values.col(yaw);
    EXPECT_LT(col.maxCoeff() - col.minCoeff(), 10.0) << t.markers.name;  // a few degrees within
    lo = std::min(lo, col.mean());
    hi = std::max(hi, col.mean());
  }
  EXPECT_GT(hi - lo, 90.0);
}

TEST(Simulation, NoiseHasTheRequestedStandardDeviation) {
  SimulationOptions o = NoiseFree();
  const SimulatedSession clean = Simulate(o);
  o.noise_mm = 0.5;
  const SimulatedSession noisy = Simulate(o);
  double sum = 0, sum2 = 0;
  long n = 0;
  for (size_t i = 0; i < clean.trials.size(); ++i) {
    const Eigen::ArrayXXd d = noisy.trials[i].markers.positions - clean.trials[i].markers.positions;
    sum += d.sum();
    sum2 += d.square().sum();
    n += d.size();
  }
  const double mean = sum / n, sd = std::sqrt(sum2 / n - mean * mean);
  EXPECT_NEAR(sd, 0.5e-3, 0.05 * 0.5e-3);
  EXPECT_NEAR(mean, 0.0, 0.01e-3);
}

TEST(Simulation, MissingSamplesComeInGaps) {
  for (double fraction : {0.05, 0.2}) {
    SimulationOptions o;
    o.missing = fraction;
    const SimulatedSession s = Simulate(o);
    long missing = 0, total = 0;
    int shortest = 1 << 30;
    for (const SimulatedTrial& t : s.trials) {
      const formats::MarkerTrial& m = t.markers;
      long trial_missing = 0;
      for (int k = 0; k < m.num_markers(); ++k) {
        int run = 0;
        for (int f = 0; f <= m.num_frames(); ++f) {
          const bool gone = f < m.num_frames() && std::isnan(m.positions(f, 3 * k));
          if (f < m.num_frames()) {
            const auto xyz = m.positions.row(f).segment<3>(3 * k);
            EXPECT_EQ(xyz.array().isNaN().count(), gone ? 3 : 0);  // all three or none
          }
          if (gone) {
            ++run;
            ++trial_missing;
          } else if (run > 0) {
            shortest = std::min(shortest, run);
            run = 0;
          }
        }
      }
      EXPECT_NEAR(static_cast<double>(trial_missing) / (m.num_frames() * m.num_markers()), fraction, 0.02)
          << m.name;
      missing += trial_missing;
      total += static_cast<long>(m.num_frames()) * m.num_markers();
    }
    EXPECT_NEAR(static_cast<double>(missing) / total, fraction, 0.01);
    EXPECT_GE(shortest, 5);
  }
}

TEST(Simulation, SoftTissueArtefactHasTheRequestedRmsAndIsSmooth) {
  SimulationOptions o = NoiseFree();
  const SimulatedSession rigid = Simulate(o);
  o.sta_mm = 10;
  const SimulatedSession soft = Simulate(o);
  const int nm = rigid.trials[0].markers.num_markers();
  // Per marker, the RMS in the movement that moves it most is the requested amplitude, and no
  // movement exceeds it.
  Eigen::ArrayXd worst = Eigen::ArrayXd::Zero(nm);
  double max_step = 0, max_step2 = 0;
  for (size_t i = 0; i < rigid.trials.size(); ++i) {
    const formats::RowMatrix d = soft.trials[i].markers.positions - rigid.trials[i].markers.positions;
    for (int m = 0; m < nm; ++m)
      worst[m] = std::max(worst[m], std::sqrt(d.middleCols(3 * m, 3).rowwise().squaredNorm().mean()));
    for (int f = 1; f < d.rows(); ++f)
      max_step = std::max(max_step, (d.row(f) - d.row(f - 1)).cwiseAbs().maxCoeff());
    for (int f = 2; f < d.rows(); ++f)
      max_step2 = std::max(max_step2, (d.row(f) - 2 * d.row(f - 1) + d.row(f - 2)).cwiseAbs().maxCoeff());
  }
  // Each marker's amplitude is 10 mm times its class's ratio in the STA table: a thigh wand
  // 10 mm, a malleolus 2.5 mm.
  ASSERT_EQ(static_cast<int>(soft.sta_rms_mm.size()), nm);
  const auto& names = rigid.trials[0].markers.marker_names;
  for (int m = 0; m < nm; ++m) {
    const double expected = 0.010 * DefaultStaTable().RatioOf(names[m]);
    EXPECT_DOUBLE_EQ(soft.sta_rms_mm[m], 1e3 * expected) << names[m];
    EXPECT_NEAR(worst[m], expected, 0.2 * expected) << names[m];
  }
  EXPECT_NEAR(worst[std::find(names.begin(), names.end(), "LTHI") - names.begin()], 0.010, 0.002);
  EXPECT_NEAR(worst[std::find(names.begin(), names.end(), "LANK") - names.begin()], 0.0025, 0.0005);
  // Smooth: it follows the joint angles, so it changes little between frames (unlike noise, whose
  // second difference would be about 2.4 x its RMS).
  std::printf("STA 10 mm RMS: largest change between frames %.2f mm, largest second difference %.3f mm\n",
              1e3 * max_step, 1e3 * max_step2);
  EXPECT_LT(max_step2, 0.001);
}

TEST(Simulation, SixtyThousandFramesInAFewSeconds) {
  SimulationOptions o;
  o.duration_scale = 10;
  o.sta_mm = 5;
  o.missing = 0.05;
  // CPU time (every thread's): a wall-clock bound would measure the tests beside it.
  const double start = testutil::ProcessCpuSeconds();
  const SimulatedSession s = Simulate(o);
  const double seconds = testutil::ProcessCpuSeconds() - start;
  EXPECT_NEAR(s.total_frames(), 60000, 20);
  std::printf("60,000-frame session simulated in %.2f CPU s\n", seconds);
  EXPECT_LT(seconds, 10.0);
}

TEST(Simulation, SummaryJsonDescribesTheSession) {
  SimulationOptions o;
  o.seed = 42;
  o.duration_scale = 0.5;
  const SimulatedSession s = Simulate(o);
  const nlohmann::json j = nlohmann::json::parse(SessionSummaryJson(s));
  EXPECT_EQ(j["seed"], 42);
  EXPECT_DOUBLE_EQ(j["height_m"].get<double>(), s.height_m);
  EXPECT_EQ(j["options"]["duration_scale"], 0.5);
  EXPECT_EQ(j["markers"].size(), 39u);
  EXPECT_EQ(j["sta_rms_mm"].size(), 39u);  // every marker's artefact amplitude
  ASSERT_EQ(j["movements"].size(), s.trials.size());
  int frames = 0;
  for (size_t i = 0; i < s.trials.size(); ++i) {
    EXPECT_EQ(j["movements"][i]["name"], s.trials[i].markers.name);
    EXPECT_EQ(j["movements"][i]["trc"], s.trials[i].markers.name + ".trc");
    frames += j["movements"][i]["frames"].get<int>();
  }
  EXPECT_EQ(frames, s.total_frames());
}

TEST(Simulation, CustomProtocol) {
  Protocol p;
  ASSERT_TRUE(ParseProtocolJson(kMinimalProtocol, "p", &p).ok());
  SimulatedSession s;
  Status st = SimulateSession(SimulationOptions(), p, &s);
  ASSERT_TRUE(st.ok()) << st.message();
  ASSERT_EQ(s.trials.size(), 1u);
  EXPECT_EQ(s.trials[0].markers.num_frames(), 200);
  EXPECT_TRUE(CheckExcitations(p.movements[0], s.trials[0].coordinates)[0].ok);
  ASSERT_TRUE(ParseProtocolJson(Edited("knee_angle_l", "knee_bend"), "p", &p).ok());
  st = SimulateSession(SimulationOptions(), p, &s);
  EXPECT_FALSE(st.ok());
  EXPECT_NE(st.message().find("knee_bend"), std::string::npos);
}

// ---------------------------------------------------------------------------------------------
// The command

namespace {

int RunTool(const std::string& args, std::string* out) {
  const std::string cmd = std::string(MOCAP_TOOL) + " " + args + " 2>&1";
  FILE* pipe = popen(cmd.c_str(), "r");
  if (!pipe) return -1;
  out->clear();
  char buf[4096];
  for (size_t n; (n = fread(buf, 1, sizeof buf, pipe)) > 0;) out->append(buf, n);
  const int status = pclose(pipe);
  return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
}

}  // namespace

TEST(SimCommand, WritesModelsTrialsAndSummaryThatReadBack) {
  if (!std::filesystem::exists(MOCAP_TOOL)) GTEST_SKIP() << "the mocap tool is not built";
  const std::string dir = std::string(MOCAP_TEST_TMP) + "/sim_command";
  std::filesystem::remove_all(dir);
  std::string out;
  ASSERT_EQ(RunTool("sim --out " + dir + " --seed 9 --duration-scale 0.3 --missing 0.05 --medial", &out), 0)
      << out;
  EXPECT_NE(out.find("43 markers"), std::string::npos) << out;

  SimulationOptions o;
  o.seed = 9;
  o.duration_scale = 0.3;
  o.missing = 0.05;
  o.medial_markers = true;
  const SimulatedSession s = Simulate(o);

  Model nominal, truth;
  ASSERT_TRUE(LoadModelJson(dir + "/nominal.model.json", &nominal).ok());
  ASSERT_TRUE(LoadModelJson(dir + "/truth.model.json", &truth).ok());
  EXPECT_EQ(truth.num_markers(), 43);
  EXPECT_TRUE(truth.InitialParameters().isApprox(s.truth.InitialParameters(), 1e-12));
  EXPECT_TRUE(nominal.InitialParameters().isApprox(s.nominal.InitialParameters(), 1e-12));

  for (const SimulatedTrial& t : s.trials) {
    SCOPED_TRACE(t.markers.name);
    formats::MarkerTrial trc;
    Status st = formats::ReadTrc(dir + "/" + t.markers.name + ".trc", &trc);
    ASSERT_TRUE(st.ok()) << st.message();
    ASSERT_EQ(trc.num_frames(), t.markers.num_frames());
    ASSERT_EQ(trc.marker_names, t.markers.marker_names);
    EXPECT_EQ(trc.rate_hz, 100.0);
    EXPECT_EQ(trc.frame_numbers.front(), 1);
    for (int f = 0; f < trc.num_frames(); ++f)
      for (int c = 0; c < trc.positions.cols(); ++c) {
        const double a = trc.positions(f, c), b = t.markers.positions(f, c);
        ASSERT_EQ(std::isnan(a), std::isnan(b)) << f << " " << c;
        if (!std::isnan(a)) ASSERT_NEAR(a, b, 1e-7);  // written in mm with 5 decimals
      }
    formats::CoordinateTable mot;
    st = formats::ReadMot(dir + "/" + t.markers.name + ".mot", &mot);
    ASSERT_TRUE(st.ok()) << st.message();
    EXPECT_TRUE(mot.in_degrees);
    ASSERT_EQ(mot.column_names, t.coordinates.column_names);
    EXPECT_TRUE(mot.values.isApprox(t.coordinates.values, 1e-7));
  }
  const nlohmann::json j = nlohmann::json::parse(std::ifstream(dir + "/subject.json"));
  EXPECT_EQ(j["seed"], 9);
  EXPECT_EQ(j["movements"].size(), 15u);
  EXPECT_EQ(j["total_frames"], s.total_frames());
}

TEST(SimCommand, BadOptionsExitWithStatus2AndNameTheOption) {
  if (!std::filesystem::exists(MOCAP_TOOL)) GTEST_SKIP() << "the mocap tool is not built";
  const std::string dir = std::string(MOCAP_TEST_TMP) + "/sim_command_bad";
  const std::pair<const char*, const char*> cases[] = {
      {"--noise-mm -1", "--noise-mm"},       {"--missing 0.95", "--missing"},
      {"--rate 0", "--rate"},                {"--duration-scale 0", "--duration-scale"},
      {"--sta-mm -3", "--sta-mm"},           {"--rate fast", "--rate"},
      {"--seed -1", "--seed"},               {"--protocol /nonexistent.json", "/nonexistent.json"},
  };
  for (const auto& [args, expected] : cases) {
    std::string out;
    EXPECT_EQ(RunTool(std::string("sim --out ") + dir + " " + args, &out), 2) << args << "\n" << out;
    EXPECT_NE(out.find(expected), std::string::npos) << args << "\n" << out;
  }
  std::string out;
  EXPECT_EQ(RunTool("sim", &out), 2) << out;  // --out is required
  EXPECT_NE(out.find("--out"), std::string::npos) << out;
}

// A movement's phases are its required excitations' windows: the ankle circles' left half and
// right half; a movement without windows is one phase; optional excitations make none.
TEST(Protocol, MovementPhasesAreTheWindowsOfTheRequiredExcitations) {
  const Movement* ankles = DefaultProtocol().Find("ankle_circles");
  ASSERT_NE(ankles, nullptr);
  const std::vector<MovementPhase> phases = MovementPhases(*ankles);
  ASSERT_EQ(phases.size(), 2u);
  EXPECT_EQ(phases[0].begin, 0.0);
  EXPECT_EQ(phases[0].end, 0.5);
  EXPECT_EQ(phases[0].coordinates, (std::vector<std::string>{"ankle_angle_l", "subtalar_angle_l"}));
  EXPECT_EQ(phases[1].begin, 0.5);
  EXPECT_EQ(phases[1].end, 1.0);
  EXPECT_EQ(phases[1].coordinates, (std::vector<std::string>{"ankle_angle_r", "subtalar_angle_r"}));
  const std::vector<MovementPhase> squats = MovementPhases(*DefaultProtocol().Find("squats"));
  ASSERT_EQ(squats.size(), 1u);
  EXPECT_EQ(squats[0].begin, 0.0);
  EXPECT_EQ(squats[0].end, 1.0);
  // Listed out of order, and an optional excitation with its own window: sorted, and no phase.
  Movement m;
  m.excitations = {{"b", 0, 10, true, "", false, 0.6, 1.0}, {"a", 0, 10, true, "", false, 0.0, 0.6},
                   {"c", 0, 10, false, "", false, 0.2, 0.3}};
  const std::vector<MovementPhase> sorted = MovementPhases(m);
  ASSERT_EQ(sorted.size(), 2u);
  EXPECT_EQ(sorted[0].coordinates, std::vector<std::string>{"a"});
  EXPECT_EQ(sorted[1].coordinates, std::vector<std::string>{"b"});
  EXPECT_EQ(MovementPhases(Movement()).size(), 1u);
}
