// Model comparison (model/compare.h): zero against itself, blind to gauge choices (a hinge centre
// sliding along its axis, a segment's markers re-expressed in a rotated frame, the zero of a
// universal joint's coordinate), sensitive to known perturbations; topology errors; and the
// `mocap model diff/show` command.
#include <gtest/gtest.h>
#include <sys/wait.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <nlohmann/json.hpp>
#include <random>

#include "model/compare.h"
#include "model/default_model.h"
#include "model/kinematics.h"
#include "model/model_io.h"
#include "model_test_util.h"
#include "tests/model_test_util.h"

using namespace mocap;

namespace {

constexpr double kDeg = M_PI / 180.0;

using Edit = std::function<void(std::vector<Segment>*, std::vector<Joint>*, std::vector<Marker>*)>;

Model Rebuild(const Model& m, const Edit& edit) {
  std::vector<Segment> segments = m.segments();
  std::vector<Joint> joints = m.joints();
  std::vector<Marker> markers = m.markers();
  edit(&segments, &joints, &markers);
  Model out;
  Status s = Model::Build(m.name(), segments, joints, m.coordinates(), markers, &out);
  EXPECT_TRUE(s.ok()) << s.message();
  return out;
}

template <typename T>
T& Named(std::vector<T>* items, const std::string& name) {
  for (auto& item : *items)
    if (item.name == name) return item;
  ADD_FAILURE() << "no " << name;
  return items->front();
}

int SegmentIndex(const std::vector<Segment>& segments, const std::string& name) {
  for (size_t i = 0; i < segments.size(); ++i)
    if (segments[i].name == name) return static_cast<int>(i);
  ADD_FAILURE() << "no segment " << name;
  return -1;
}

const JointDifference& J(const ModelComparison& c, const std::string& name) {
  for (const auto& j : c.joints)
    if (j.joint == name) return j;
  ADD_FAILURE() << "no joint " << name;
  return c.joints.front();
}
const SegmentDifference& L(const ModelComparison& c, const std::string& name) {
  for (const auto& s : c.segments)
    if (s.name == name) return s;
  ADD_FAILURE() << "no length " << name;
  return c.segments.front();
}
const MarkerDifference& M(const ModelComparison& c, const std::string& name) {
  for (const auto& m : c.markers)
    if (m.marker == name) return m;
  ADD_FAILURE() << "no marker " << name;
  return c.markers.front();
}

ModelComparison Compare(const Model& a, const Model& b) {
  ModelComparison c;
  Status s = CompareModels(a, b, &c);
  EXPECT_TRUE(s.ok()) << s.message();
  return c;
}

Eigen::Matrix3Xd WorldMarkers(const Model& model, const Eigen::VectorXd& z) {
  Geometry g(model);
  ModelData d(model);
  ForwardKinematics(model, g, z, &d);
  Eigen::Matrix3Xd x;
  MarkerPositions(model, g, d, &x);
  return x;
}

Eigen::VectorXd RandomPose(const Model& model, std::mt19937& rng) {
  std::uniform_real_distribution<double> u(-0.8, 0.8);
  Eigen::VectorXd z = model.DefaultCoordinates();
  for (int c = 0; c < model.num_coordinates(); ++c) z[c] += u(rng);
  return z;
}

// The default model with every parameter nudged, so that no axis or offset is special.
Model Perturbed(unsigned seed) {
  Model base = DefaultFullBodyModel();
  std::mt19937 rng(seed);
  return mocap::testutil::Baked(base, mocap::testutil::RandomParameters(base, rng));
}

void ExpectAllZero(const ModelComparison& c, double tol) {
  for (const auto& j : c.joints) {
    EXPECT_LE(j.centre_error_mm, tol) << j.joint;
    for (const auto& a : j.axes) EXPECT_LE(a.error_deg, tol) << j.joint << " axis " << a.element;
  }
  for (const auto& s : c.segments)
    EXPECT_LE(std::abs(s.length_b_mm - s.length_a_mm), tol) << s.name;
  for (const auto& m : c.markers) EXPECT_LE(m.error_mm, tol) << m.marker;
}

}  // namespace

TEST(CompareModels, ModelAgainstItselfIsZero) {
  for (const Model& a : {DefaultFullBodyModel(), Perturbed(1)}) {
    const ModelComparison c = Compare(a, a);
    EXPECT_EQ(c.joints.size(), 14u);  // every joint but the root
    EXPECT_EQ(c.markers.size(), static_cast<size_t>(a.num_markers()));
    EXPECT_TRUE(c.markers_only_in_a.empty());
    EXPECT_TRUE(c.markers_only_in_b.empty());
    for (const ErrorStats* s : {&c.joint_centre_error_mm, &c.axis_error_deg,
                                &c.segment_length_error_pct, &c.marker_error_mm}) {
      EXPECT_GT(s->count, 0);
      EXPECT_LE(s->max, 1e-9);
      EXPECT_LE(s->rms, 1e-9);
    }
    EXPECT_EQ(c.axis_error_deg.count, 2 + 2 * (2 + 2 + 2));  // knees; ankles, elbows, wrists
    ExpectAllZero(c, 1e-9);
    EXPECT_TRUE(J(c, "knee_l").hinge);
    EXPECT_FALSE(J(c, "ankle_l").hinge);
    EXPECT_TRUE(std::isnan(J(c, "hip_l").axis_error_deg));  // no fitted axes
    EXPECT_EQ(J(c, "knee_l").basis, "femur_l+tibia_l");
  }
}

TEST(CompareModels, LengthsAreNamedPerChildAndRootPairs) {
  const Model a = DefaultFullBodyModel();
  const ModelComparison c = Compare(a, a);
  // femur_l: hip point to the knee axis line = 0.43 m; torso has three children.
  EXPECT_NEAR(L(c, "femur_l->knee_l").length_a_mm, 430.0, 1e-9);
  for (const char* n : {"torso->neck", "torso->shoulder_l", "torso->shoulder_r",
                        "pelvis:hip_l-hip_r", "pelvis:lumbar-hip_l", "tibia_l->ankle_l",
                        "forearm_r->wrist_r"})
    EXPECT_GT(L(c, n).length_a_mm, 0.0) << n;
  EXPECT_NEAR(L(c, "pelvis:hip_l-hip_r").length_a_mm, 2 * 86.0, 1e-9);
  for (const auto& s : c.segments) EXPECT_NE(s.segment, "hand_l");  // no child joint
}

// Sliding a hinge's centre along its axis, with the child's markers and its child joint centres
// moved back by as much in the child's frame, changes no marker anywhere: not an error.
TEST(CompareModels, HingeCentreAlongItsAxisIsAGauge) {
  const Model a = Perturbed(2);
  const int knee = a.FindJoint("knee_l");
  const Joint& kj = a.joints()[knee];
  ASSERT_TRUE(kj.orientation.isIdentity(0));
  const Eigen::Vector3d axis = kj.elements[0].axis;  // same in the femur and the tibia frame
  const double slide = 0.03;                          // m, in the femur's unscaled frame
  const double s_femur = a.segments()[kj.parent].scale, s_tibia = a.segments()[kj.child].scale;
  const Eigen::Vector3d back = -(s_femur * slide / s_tibia) * axis;  // tibia's unscaled frame
  const Model b = Rebuild(a, [&](auto* segments, auto* joints, auto* markers) {
    const int tibia = SegmentIndex(*segments, "tibia_l");
    Named(joints, "knee_l").centre += slide * axis;
    Named(joints, "ankle_l").centre += back;
    for (auto& m : *markers)
      if (m.segment == tibia) m.position += back;
  });
  std::mt19937 rng(3);
  for (int k = 0; k < 3; ++k) {
    const Eigen::VectorXd z = RandomPose(a, rng);
    ASSERT_LE((WorldMarkers(a, z) - WorldMarkers(b, z)).cwiseAbs().maxCoeff(), 1e-12);
  }
  const ModelComparison c = Compare(a, b);
  ExpectAllZero(c, 1e-9);
  EXPECT_LE(c.joint_centre_error_mm.max, 1e-9);
  EXPECT_LE(c.segment_length_error_pct.max, 1e-9);
  // The knee centre did move, 30 mm along the axis.
  EXPECT_NEAR((b.joints()[knee].centre - a.joints()[knee].centre).norm(), slide, 1e-12);
}

// A segment's markers re-expressed in a rotated and shifted frame: the marker errors do not
// change, and neither does the centre of the joint at that frame's origin.
TEST(CompareModels, MarkersInARotatedFrameAreAGauge) {
  const Model a = Perturbed(4);
  const Eigen::Matrix3d r = Eigen::AngleAxisd(25 * kDeg, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  const Model b1 = Rebuild(a, [&](auto*, auto*, auto* markers) {
    Named(markers, "LFHD").position += Eigen::Vector3d(0.004, -0.003, 0.002);
  });
  const Model b2 = Rebuild(b1, [&](auto* segments, auto*, auto* markers) {
    const int head = SegmentIndex(*segments, "head");
    for (auto& m : *markers)
      if (m.segment == head) m.position = r * m.position;
  });
  const ModelComparison c1 = Compare(a, b1), c2 = Compare(a, b2);
  ASSERT_EQ(c1.markers.size(), c2.markers.size());
  for (size_t i = 0; i < c1.markers.size(); ++i)
    EXPECT_NEAR(c1.markers[i].error_mm, c2.markers[i].error_mm, 1e-9) << c1.markers[i].marker;
  EXPECT_GT(M(c1, "LFHD").error_mm, 1.0);
  EXPECT_TRUE(M(c1, "LFHD").aligned);
  // Rotating the head frame about its origin (the neck centre) is absorbed by the spherical neck.
  const ModelComparison c3 = Compare(a, Rebuild(a, [&](auto* segments, auto*, auto* markers) {
    const int head = SegmentIndex(*segments, "head");
    for (auto& m : *markers)
      if (m.segment == head) m.position = r * m.position;
  }));
  ExpectAllZero(c3, 1e-9);
}

// The zero of a universal joint's second coordinate: rotating the child's frame (and everything
// expressed in it) about the second axis is undone by a coordinate offset. The first axis is
// fixed only in the parent, the second only in the child, so neither reads the offset as error.
TEST(CompareModels, UniversalJointCoordinateZeroIsAGauge) {
  const Model base = Rebuild(Perturbed(5), [](auto* segments, auto*, auto* markers) {
    Marker m;  // a third humerus marker, so that the elbow's first axis has an aligned segment
    m.name = "LHUM";
    m.segment = SegmentIndex(*segments, "humerus_l");
    m.position = Eigen::Vector3d(0.04, 0.03, -0.22);
    markers->push_back(m);
  });
  const Joint& elbow = base.joints()[base.FindJoint("elbow_l")];
  ASSERT_TRUE(elbow.orientation.isIdentity(0));
  ASSERT_TRUE(base.joints()[base.FindJoint("wrist_l")].orientation.isIdentity(0));
  const double theta = 20 * kDeg;
  const Eigen::Matrix3d g = Eigen::AngleAxisd(theta, elbow.elements[1].axis).toRotationMatrix();
  const Model b = Rebuild(base, [&](auto* segments, auto* joints, auto* markers) {
    const int forearm = SegmentIndex(*segments, "forearm_l"), hand = SegmentIndex(*segments, "hand_l");
    Joint& wrist = Named(joints, "wrist_l");
    wrist.centre = g * wrist.centre;
    for (auto& el : wrist.elements) el.axis = g * el.axis;
    for (auto& m : *markers)
      if (m.segment == forearm || m.segment == hand) m.position = g * m.position;
  });
  const int pro_sup = base.FindCoordinate("pro_sup_l");
  std::mt19937 rng(6);
  for (int k = 0; k < 3; ++k) {
    const Eigen::VectorXd z = RandomPose(base, rng);
    Eigen::VectorXd zb = z;
    zb[pro_sup] -= theta;
    ASSERT_LE((WorldMarkers(base, z) - WorldMarkers(b, zb)).cwiseAbs().maxCoeff(), 1e-12);
  }
  const ModelComparison c = Compare(base, b);
  for (const char* j : {"elbow_l", "wrist_l"}) {
    EXPECT_LE(J(c, j).centre_error_mm, 1e-9) << j;
    EXPECT_LE(J(c, j).axis_error_deg, 1e-7) << j;
  }
  EXPECT_EQ(J(c, "elbow_l").axes[0].basis, "humerus_l");
  EXPECT_EQ(J(c, "elbow_l").axes[1].basis, "forearm_l");
  for (const char* m : {"LFRM", "LWRA", "LWRB"}) EXPECT_LE(M(c, m).error_mm, 1e-9) << m;
  // LFIN is alone on the hand: compared in the hand's frame, which this gauge rotates.
  EXPECT_FALSE(M(c, "LFIN").aligned);
}

TEST(CompareModels, MeasuresAKneeCentreMovedAcrossItsAxis) {
  const Model a = Perturbed(7);
  const Joint& knee = a.joints()[a.FindJoint("knee_l")];
  const Eigen::Vector3d u = knee.elements[0].axis;
  const Eigen::Vector3d across = u.unitOrthogonal();
  const double s_femur = a.segments()[knee.parent].scale;
  const Model b = Rebuild(a, [&](auto*, auto* joints, auto*) {
    Named(joints, "knee_l").centre += (0.010 / s_femur) * across + 0.02 * u;  // along: ignored
  });
  const ModelComparison c = Compare(a, b);
  EXPECT_NEAR(J(c, "knee_l").centre_error_mm, 10.0, 1e-9);
  EXPECT_NEAR(c.joint_centre_error_mm.max, 10.0, 1e-9);
  EXPECT_EQ(c.joint_centre_error_mm.count, 14);
  EXPECT_NEAR(c.joint_centre_error_mm.rms, 10.0 / std::sqrt(14.0), 1e-9);
  EXPECT_LE(J(c, "ankle_l").centre_error_mm, 1e-9);
  EXPECT_LE(J(c, "hip_l").centre_error_mm, 1e-9);
  EXPECT_LE(c.marker_error_mm.max, 1e-9);
}

TEST(CompareModels, MeasuresAScaledFemur) {
  const Model a = Perturbed(8);
  Eigen::VectorXd p = a.InitialParameters();
  p[a.scale_index(a.FindSegment("femur_l"))] *= 1.05;
  const ModelComparison c = Compare(a, mocap::testutil::Baked(a, p));
  EXPECT_NEAR(L(c, "femur_l->knee_l").error_pct, 5.0, 1e-9);
  EXPECT_NEAR(c.segment_length_error_pct.max, 5.0, 1e-9);
  EXPECT_NEAR(L(c, "femur_r->knee_r").error_pct, 0.0, 1e-9);
  EXPECT_NEAR(L(c, "tibia_l->ankle_l").error_pct, 0.0, 1e-9);
}

TEST(CompareModels, MeasuresATiltedHingeAxis) {
  const Model a = Perturbed(9);
  const int knee = a.FindJoint("knee_l");
  for (int component : {0, 1}) {  // alpha, beta
    Eigen::VectorXd p = a.InitialParameters();
    p[a.axis_index(knee, 0) + component] = 3 * kDeg;
    const ModelComparison c = Compare(a, mocap::testutil::Baked(a, p));
    EXPECT_NEAR(J(c, "knee_l").axis_error_deg, 3.0, 1e-9);
    EXPECT_NEAR(c.axis_error_deg.max, 3.0, 1e-9);
    EXPECT_LE(J(c, "knee_r").axis_error_deg, 1e-9);
    EXPECT_LE(J(c, "ankle_l").axis_error_deg, 1e-9);
    EXPECT_LE(c.joint_centre_error_mm.max, 1e-9);
  }
}

TEST(CompareModels, MeasuresAMovedMarker) {
  const Model a = Perturbed(10);
  const int c7 = a.FindMarker("C7");
  const Eigen::Vector3d shift = Eigen::Vector3d(0.2, -0.3, 1.0).normalized() * 0.007;
  const double s = a.segments()[a.markers()[c7].segment].scale;
  const Model b = Rebuild(a, [&](auto*, auto*, auto* markers) {
    Named(markers, "C7").position += shift / s;
  });
  const ModelComparison c = Compare(a, b);
  const double e = M(c, "C7").error_mm;
  // Torso has 7 markers: the alignment absorbs some of the 7 mm, at most a share ~ 1/n of it.
  EXPECT_GT(e, 7.0 * (1 - 2.0 / 7));
  EXPECT_LE(e, 7.0 + 1e-9);
  EXPECT_EQ(c.marker_error_mm.max, e);
  for (const auto& m : c.markers) {
    if (m.marker == "C7") continue;
    EXPECT_LT(m.error_mm, e) << m.marker;
    if (m.segment != "torso") {
      EXPECT_LE(m.error_mm, 1e-9) << m.marker;
    }
  }
}

TEST(CompareModels, MarkersInOneModelOnlyAreListedAndIgnored) {
  const Model a = DefaultFullBodyModel();
  std::vector<int> keep;
  for (int m = 0; m < a.num_markers(); ++m)
    if (!a.markers()[m].optional) keep.push_back(m);
  const Model b = mocap::testutil::Keeping(a, keep);
  const ModelComparison c = Compare(a, b);
  EXPECT_EQ(c.markers_only_in_a, (std::vector<std::string>{"LKNM", "LMMA", "RKNM", "RMMA"}));
  EXPECT_TRUE(c.markers_only_in_b.empty());
  EXPECT_EQ(c.markers.size(), 39u);
  ExpectAllZero(c, 1e-9);
  // Femur and tibia keep 2 markers each: they are aligned with their determined joint centres
  // (hip, ankle) and, for the tibia, the knee's axis line, never at the zero pose.
  EXPECT_EQ(J(c, "knee_l").basis, "femur_l+centres+tibia_l+centres");
  const ModelComparison reverse = Compare(b, a);
  EXPECT_EQ(reverse.markers_only_in_b.size(), 4u);
}

TEST(CompareModels, TopologyMismatchNamesTheFirstDifference) {
  const Model a = DefaultFullBodyModel();
  ModelComparison c;
  {
    std::string text = ModelToJsonString(a);
    for (size_t at; (at = text.find("\"tibia_l\"")) != std::string::npos;)
      text.replace(at, 9, "\"shank_l\"");
    Model b;
    ASSERT_TRUE(ParseModelJson(text, "b.json", &b).ok());
    const Status s = CompareModels(a, b, &c);
    ASSERT_FALSE(s.ok());
    EXPECT_NE(s.message().find("tibia_l"), std::string::npos) << s.message();
  }
  {
    const Model b = Rebuild(a, [](auto*, auto* joints, auto*) {
      Named(joints, "knee_r").type = JointType::kUniversal;
    });
    const Status s = CompareModels(a, b, &c);
    ASSERT_FALSE(s.ok());
    EXPECT_NE(s.message().find("knee_r"), std::string::npos) << s.message();
  }
  {
    const Model b = Rebuild(a, [](auto* segments, auto*, auto* markers) {
      Named(markers, "LTHI").segment = SegmentIndex(*segments, "tibia_l");
    });
    const Status s = CompareModels(a, b, &c);
    ASSERT_FALSE(s.ok());
    EXPECT_NE(s.message().find("LTHI"), std::string::npos) << s.message();
  }
  {
    const Model b = Rebuild(a, [](auto*, auto* joints, auto*) {
      Named(joints, "elbow_l").elements[1].fitted_axis = false;
    });
    const Status s = CompareModels(a, b, &c);
    ASSERT_FALSE(s.ok());
    EXPECT_NE(s.message().find("elbow_l"), std::string::npos) << s.message();
  }
}

// --- the command ---

namespace {

int RunTool(const std::string& args, std::string* out, bool with_stderr) {
  const std::string cmd = std::string(MOCAP_TOOL) + " " + args + (with_stderr ? " 2>&1" : "");
  FILE* pipe = popen(cmd.c_str(), "r");
  if (!pipe) return -1;
  out->clear();
  char buf[4096];
  for (size_t n; (n = fread(buf, 1, sizeof buf, pipe)) > 0;) out->append(buf, n);
  const int status = pclose(pipe);
  return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
}

std::string TmpFile(const std::string& name) {
  std::filesystem::create_directories(MOCAP_TEST_TMP);
  return std::string(MOCAP_TEST_TMP) + "/" + name;
}

}  // namespace

TEST(ModelCommand, DiffPrintsJsonWithNumericSummaries) {
  const Model a = DefaultFullBodyModel();
  Eigen::VectorXd p = a.InitialParameters();
  p[a.scale_index(a.FindSegment("femur_l"))] = 1.05;
  const std::string pa = TmpFile("compare_a.json"), pb = TmpFile("compare_b.json");
  ASSERT_TRUE(SaveModelJson(pa, a).ok());
  ASSERT_TRUE(SaveModelJson(pb, mocap::testutil::Baked(a, p)).ok());

  std::string out;
  ASSERT_EQ(RunTool("model diff " + pa + " " + pb + " --json", &out, false), 0) << out;
  const nlohmann::json doc = nlohmann::json::parse(out);
  for (const char* key : {"joint_centre_error_mm", "axis_error_deg", "segment_length_error_pct",
                          "marker_error_mm"}) {
    ASSERT_TRUE(doc.contains(key)) << key;
    EXPECT_TRUE(doc[key]["max"].is_number()) << key;
    EXPECT_TRUE(doc[key]["rms"].is_number()) << key;
  }
  EXPECT_NEAR(doc["segment_length_error_pct"]["max"].get<double>(), 5.0, 1e-6);
  ASSERT_EQ(doc["joints"].size(), 14u);
  for (const auto& j : doc["joints"]) {
    EXPECT_TRUE(j["joint"].is_string());
    EXPECT_TRUE(j["centre_error_mm"].is_number());
    EXPECT_EQ(j.contains("axis_error_deg"), j["joint"] == "knee_l" || j["joint"] == "knee_r" ||
                                               j["joint"].get<std::string>().find("ankle") == 0 ||
                                               j["joint"].get<std::string>().find("elbow") == 0 ||
                                               j["joint"].get<std::string>().find("wrist") == 0);
  }
  EXPECT_TRUE(doc["segments"].is_array());
  EXPECT_TRUE(doc["markers"].is_array());
  EXPECT_TRUE(doc["markers_only_in_a"].is_array());
  EXPECT_TRUE(doc["markers_only_in_b"].is_array());

  // The human tables.
  ASSERT_EQ(RunTool("model diff " + pa + " " + pb, &out, true), 0) << out;
  EXPECT_NE(out.find("femur_l->knee_l"), std::string::npos) << out;
  EXPECT_NE(out.find("joint centre error"), std::string::npos) << out;
  EXPECT_NE(out.find("unaligned"), std::string::npos) << out;
}

TEST(ModelCommand, ErrorsNameTheFileAndUsageExitsTwo) {
  const std::string pa = TmpFile("compare_present.json");
  ASSERT_TRUE(SaveModelJson(pa, DefaultFullBodyModel()).ok());
  const std::string missing = TmpFile("no_such_model.json");
  std::string out;
  int code = RunTool("model diff " + pa + " " + missing + " --json", &out, true);
  EXPECT_EQ(code, 1);
  EXPECT_NE(out.find(missing), std::string::npos) << out;
  code = RunTool("model show " + missing, &out, true);
  EXPECT_EQ(code, 1);
  EXPECT_NE(out.find(missing), std::string::npos) << out;

  EXPECT_EQ(RunTool("model diff " + pa, &out, true), 2) << out;
  EXPECT_EQ(RunTool("model diff " + pa + " " + pa + " --bogus", &out, true), 2) << out;
  EXPECT_EQ(RunTool("model", &out, true), 2) << out;

  // Different topology: exit 1, both files named.
  std::string text = ModelToJsonString(DefaultFullBodyModel());
  text.replace(text.find("\"knee_l\""), 8, "\"knee_x\"");
  const std::string pb = TmpFile("compare_renamed.json");
  {
    std::ofstream f(pb);
    f << text;
  }
  code = RunTool("model diff " + pa + " " + pb, &out, true);
  EXPECT_EQ(code, 1);
  EXPECT_NE(out.find("knee_l"), std::string::npos) << out;
  EXPECT_NE(out.find(pb), std::string::npos) << out;
}

TEST(ModelCommand, ShowSummarisesTheModel) {
  const std::string pa = TmpFile("show_model.json");
  ASSERT_TRUE(SaveModelJson(pa, DefaultFullBodyModel()).ok());
  std::string out;
  ASSERT_EQ(RunTool("model show " + pa, &out, true), 0) << out;
  for (const char* s : {"15 segments", "38 coordinates", "scales 15", "centres 42", "axes 28",
                        "markers 129", "knee_l", "hinge", "femur_l -> tibia_l", "knee_angle_l",
                        "fitted", "LKNM*"})
    EXPECT_NE(out.find(s), std::string::npos) << s << "\n" << out;
}
