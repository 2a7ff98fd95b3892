// The body model: structure of the default model, analytic Jacobians against central finite
// differences, JSON round trip and validation errors, allocation-free evaluation.
#include <gtest/gtest.h>

#include <nlohmann/json.hpp>

#include <filesystem>
#include <fstream>
#include <random>

#include "model/default_model.h"
#include "model/kinematics.h"
#include "model/model_io.h"
#include "model_test_util.h"
#include "tests/model_test_util.h"

using namespace mocap;

using mocap::testutil::ExpectJacobiansMatchCentralDifferences;
using mocap::testutil::Positions;
using mocap::testutil::RandomParameters;
using mocap::testutil::RandomPose;

TEST(DefaultModel, HasTheDesignedStructure) {
  Model model = DefaultFullBodyModel();
  EXPECT_EQ(model.num_coordinates(), 38);
  EXPECT_EQ(model.num_segments(), 15);
  int required = 0;
  for (const auto& m : model.markers()) required += m.optional ? 0 : 1;
  EXPECT_EQ(required, 39);
  for (const char* n : {"LFHD", "RFHD", "LBHD", "RBHD", "C7", "T10", "CLAV", "STRN", "RBAK", "LSHO",
                        "RSHO", "LUPA", "RELB", "LFRM", "RWRA", "LWRB", "RFIN", "LASI", "RPSI",
                        "LTHI", "RKNE", "LTIB", "RANK", "LHEE", "RTOE", "LKNM", "RMMA"})
    EXPECT_GE(model.FindMarker(n), 0) << n;
  // Standing: the head above the pelvis above the feet, the left side at +y.
  Eigen::Matrix3Xd x = Positions(model, model.DefaultCoordinates(), model.InitialParameters());
  EXPECT_GT(x(2, model.FindMarker("LFHD")), 1.55);
  EXPECT_LT(x(2, model.FindMarker("LHEE")), 0.08);
  EXPECT_GT(x(2, model.FindMarker("LHEE")), 0.0);
  EXPECT_GT(x(2, model.FindMarker("RTOE")), 0.0);
  EXPECT_GT(x(1, model.FindMarker("LASI")), 0.0);
  EXPECT_LT(x(1, model.FindMarker("RASI")), 0.0);
}

TEST(DefaultModel, ScalesWithHeight) {
  Model a = DefaultFullBodyModel(1.75), b = DefaultFullBodyModel(1.60);
  Eigen::Matrix3Xd xa = Positions(a, Eigen::VectorXd::Zero(38), a.InitialParameters());
  Eigen::Matrix3Xd xb = Positions(b, Eigen::VectorXd::Zero(38), b.InitialParameters());
  EXPECT_NEAR((xb - xa * (1.60 / 1.75)).norm(), 0.0, 1e-12);
}

// Every block of dh/dz and dh/dp against central differences, to 1e-6 relative.
TEST(Kinematics, JacobiansMatchCentralDifferences) {
  Model model = DefaultFullBodyModel();
  std::mt19937 rng(7);
  for (int trial = 0; trial < 5; ++trial) {
    const Eigen::VectorXd z = RandomPose(model, rng);
    const Eigen::VectorXd p = RandomParameters(model, rng);
    EXPECT_LT(ExpectJacobiansMatchCentralDifferences(model, z, p), 1e-6);
  }
}

// The pass over a joint list (the tracker's limb search) places the listed joints' children exactly
// as the whole pass does, when only those joints' coordinates changed; and nothing else.
TEST(Kinematics, ForwardKinematicsOverAJointListMatchesTheWholePass) {
  Model model = DefaultFullBodyModel();
  const Geometry g(model);
  std::mt19937 rng(5);
  const Eigen::VectorXd z0 = RandomPose(model, rng);
  const int knee = model.FindJoint("knee_r");
  ASSERT_GE(knee, 0);
  // The knee's subtree: the knee and every joint below the shank.
  std::vector<int> joints;
  std::vector<char> moved(model.num_segments(), 0);
  for (int j = 0; j < model.num_joints(); ++j) {
    const Joint& jt = model.joints()[j];
    if (j != knee && !(jt.parent >= 0 && moved[jt.parent])) continue;
    moved[jt.child] = 1;
    joints.push_back(j);
  }
  ASSERT_GE(joints.size(), 2u);
  Eigen::VectorXd z1 = RandomPose(model, rng);
  Eigen::VectorXd z = z0;
  for (int j : joints)
    for (const JointElement& e : model.joints()[j].elements)
      if (e.coordinate >= 0) z[e.coordinate] = z1[e.coordinate];
  ModelData whole(model), listed(model);
  ForwardKinematics(model, g, z, &whole);
  ForwardKinematics(model, g, z0, &listed);
  ForwardKinematics(model, g, z, joints, &listed);
  for (int s = 0; s < model.num_segments(); ++s) {
    EXPECT_EQ(listed.segment_position[s], whole.segment_position[s]) << model.segments()[s].name;
    EXPECT_EQ(listed.segment_rotation[s], whole.segment_rotation[s]) << model.segments()[s].name;
  }
  // A joint left out keeps its place: the knee's child where z0 put it.
  ModelData before(model), partial(model);
  ForwardKinematics(model, g, z0, &before);
  ForwardKinematics(model, g, z0, &partial);
  ForwardKinematics(model, g, z, std::vector<int>(joints.begin() + 1, joints.end()), &partial);
  const int shank = model.joints()[knee].child;
  EXPECT_EQ(partial.segment_rotation[shank], before.segment_rotation[shank]);
  EXPECT_NE(partial.segment_rotation[shank], whole.segment_rotation[shank]);
}

TEST(Kinematics, WithParametersReproducesPositions) {
  Model model = DefaultFullBodyModel();
  std::mt19937 rng(3);
  const Eigen::VectorXd p = RandomParameters(model, rng);
  const Eigen::VectorXd z = RandomPose(model, rng);
  const Model baked = mocap::testutil::Baked(model, p);
  EXPECT_LT((Positions(model, z, p) - Positions(baked, z, baked.InitialParameters())).norm(), 1e-12);
  EXPECT_NEAR(baked.InitialParameters().segment(baked.axis_index(baked.FindJoint("knee_l"), 0), 2).norm(), 0.0, 0);
}

TEST(Model, WithParametersAndWithMarkersRefuseWhatIsNoModel) {
  const Model model = DefaultFullBodyModel();
  const int femur = model.FindSegment("femur_r");
  ASSERT_GE(femur, 0);
  Model out = DefaultFullBodyModel(1.5);  // what an error must leave alone
  const int kept_markers = out.num_markers();
  for (double bad_scale : {0.0, -0.5}) {
    Eigen::VectorXd p = model.InitialParameters();
    p[model.scale_index(femur)] = bad_scale;
    const Status s = model.WithParameters(p, &out);
    EXPECT_FALSE(s.ok()) << "scale " << bad_scale;
    EXPECT_NE(s.message().find("femur_r"), std::string::npos) << s.message();
    EXPECT_NE(s.message().find("scale must be > 0"), std::string::npos) << s.message();
  }
  Eigen::VectorXd nan_centre = model.InitialParameters();
  const int knee = model.FindJoint("knee_r");
  nan_centre[model.centre_index(knee) + 1] = std::nan("");
  Status s = model.WithParameters(nan_centre, &out);
  EXPECT_FALSE(s.ok());
  EXPECT_NE(s.message().find("knee_r.centre.y is not finite"), std::string::npos) << s.message();
  s = model.WithParameters(model.InitialParameters().head(5), &out);
  EXPECT_FALSE(s.ok());
  EXPECT_NE(s.message().find("5 parameters given"), std::string::npos) << s.message();
  EXPECT_EQ(out.num_markers(), kept_markers);

  s = model.WithMarkers({0, model.num_markers()}, &out);
  EXPECT_FALSE(s.ok());
  EXPECT_NE(s.message().find("out of range"), std::string::npos) << s.message();
  s = model.WithMarkers({2, 2}, &out);
  EXPECT_FALSE(s.ok());
  EXPECT_NE(s.message().find("kept twice"), std::string::npos) << s.message();
  EXPECT_EQ(out.num_markers(), kept_markers);

  s = model.WithMarkers({3, 1}, &out);
  ASSERT_TRUE(s.ok()) << s.message();
  ASSERT_EQ(out.num_markers(), 2);
  EXPECT_EQ(out.markers()[0].name, model.markers()[3].name);
}

TEST(Kinematics, EvaluationDoesNotAllocate) {
  Model model = DefaultFullBodyModel();
  Geometry g(model);
  ModelData d(model);
  const Eigen::VectorXd z = model.DefaultCoordinates();
  Eigen::Matrix3Xd x(3, model.num_markers());
  Eigen::Matrix<double, 3, Eigen::Dynamic> jz(3, model.max_chain_coordinates()),
      jp(3, model.max_chain_parameters());
  g.Set(model, model.InitialParameters());  // sizes already allocated: reuse
  Eigen::internal::set_is_malloc_allowed(false);
  g.Set(model, model.InitialParameters());
  ForwardKinematics(model, g, z, &d);
  for (int m = 0; m < model.num_markers(); ++m) {
    x.col(m) = MarkerPosition(model, g, d, m);
    auto bz = jz.leftCols(model.marker_coordinates(m).size());
    auto bp = jp.leftCols(model.marker_parameters(m).size());
    MarkerJacobian(model, g, d, m, &bz, &bp);
  }
  Eigen::internal::set_is_malloc_allowed(true);
  EXPECT_TRUE(x.allFinite());
}

TEST(ModelJson, RoundTripIsExact) {
  Model model = DefaultFullBodyModel(1.68);
  Model back;
  Status s = ParseModelJson(ModelToJsonString(model), "mem", &back);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(ModelToJsonString(back), ModelToJsonString(model));
  EXPECT_EQ((back.InitialParameters() - model.InitialParameters()).norm(), 0.0);
}

// OpenSim's <clamped> and <fixed> survive the model file (formats/osim.cpp reads them).
TEST(ModelJson, ClampedCoordinatesAndFixedMarkersRoundTrip) {
  const Model base = DefaultFullBodyModel();
  std::vector<Coordinate> coordinates = base.coordinates();
  std::vector<Marker> markers = base.markers();
  const int knee = base.FindCoordinate("knee_angle_r");
  ASSERT_GE(knee, 0);
  coordinates[knee].clamped = true;
  markers[3].fixed = true;
  Model model;
  ASSERT_TRUE(Model::Build(base.name(), base.segments(), base.joints(), coordinates, markers,
                           base.derived_coordinates(), &model).ok());
  Model back;
  Status s = ParseModelJson(ModelToJsonString(model), "mem", &back);
  ASSERT_TRUE(s.ok()) << s.message();
  for (int c = 0; c < back.num_coordinates(); ++c) EXPECT_EQ(back.coordinates()[c].clamped, c == knee);
  for (int m = 0; m < back.num_markers(); ++m) EXPECT_EQ(back.markers()[m].fixed, m == 3);
  // A clamped coordinate without a range is refused, by name.
  nlohmann::json doc = nlohmann::json::parse(ModelToJsonString(model));
  doc["coordinates"][knee].erase("range");
  Model bad;
  s = ParseModelJson(doc.dump(), "bad.json", &bad);
  EXPECT_FALSE(s.ok());
  EXPECT_NE(s.message().find("coordinates[" + std::to_string(knee) + "].clamped"), std::string::npos)
      << s.message();
}

TEST(ModelJson, ErrorsNameTheField) {
  const std::string good = ModelToJsonString(DefaultFullBodyModel());
  struct Case { std::string from, to, expect; };
  std::vector<Case> cases = {
      {"\"format\": \"mocap-model\"", "\"format\": \"other\"", ".format"},
      {"\"child\": \"femur_l\"", "\"child\": \"nothing\"", "joints[3].child: no segment named 'nothing'"},
      {"\"coordinate\": \"knee_angle_l\"", "\"coordinate\": \"nope\"", "joints[4].elements[0].coordinate"},
      {"\"segment\": \"head\"", "\"segment\": 5", "markers[11].segment: expected a string"},
      {"\"kind\": \"rotation\"", "\"kind\": \"twist\"", ".kind: expected"},
  };
  for (const auto& c : cases) {
    std::string text = good;
    const size_t at = text.find(c.from);
    ASSERT_NE(at, std::string::npos) << c.from;
    text.replace(at, c.from.size(), c.to);
    Model m;
    Status s = ParseModelJson(text, "bad.json", &m);
    EXPECT_FALSE(s.ok());
    EXPECT_NE(s.message().find("bad.json"), std::string::npos) << s.message();
    EXPECT_NE(s.message().find(c.expect), std::string::npos) << s.message();
  }
  Model m;
  Status s = ParseModelJson("{ \"format\": ", "trunc.json", &m);
  EXPECT_FALSE(s.ok());
  EXPECT_NE(s.message().find("trunc.json: not valid JSON"), std::string::npos) << s.message();
  s = LoadModelJson("/nonexistent/model.json", &m);
  EXPECT_FALSE(s.ok());
  EXPECT_NE(s.message().find("/nonexistent/model.json"), std::string::npos);
}

// --- coordinate functions (OpenSim's) and models that use them ---

namespace {

using Fn = CoordinateFunction;

double NumericDerivative(const Fn& f, double z) {
  const double h = 1e-6;
  return (f.Value(z + h) - f.Value(z - h)) / (2 * h);
}

Fn KneeSpline() {  // gait2354's knee_r translation2 (metres of knee_angle_r)
  return Fn::SimmSpline({-2.0944, -1.22173, -0.523599, -0.349066, -0.174533, 0.159149, 2.0944},
                        {-0.4226, -0.4082, -0.399, -0.3976, -0.3966, -0.395264, -0.396});
}

// A quintic GCV spline (half order 3, as SIMM's converter writes them) through a knee's
// translation-like values.
Fn GcvKneeSpline() {
  return Fn::GcvSpline(3, {-2.0944, -1.5, -1.0, -0.5, 0.0, 0.5, 2.0944},
                       {0.0035, 0.0028, 0.0017, 0.0009, -0.0002, -0.0005, -0.0031});
}

// A model exercising every function kind, coupled coordinates (one coordinate driving two
// joints), scaled translations of non-root joints, a fitted axis after translations.
Model FunctionModel() {
  std::vector<Segment> segments = {{"base", 1.0, -1}, {"thigh", 1.0, -1}, {"shank", 1.0, -1}};
  std::vector<Coordinate> coords;
  for (const char* n : {"tx", "ty", "tz", "r1", "r2", "r3", "a", "b"}) {
    Coordinate c;
    c.name = n;
    c.rotational = n[0] != 't';
    coords.push_back(c);
  }
  coords[1].default_value = 0.9;
  auto el = [](ElementKind k, Eigen::Vector3d axis, int c, Fn f, bool fitted = false) {
    JointElement e;
    e.kind = k;
    e.axis = axis.normalized();
    e.coordinate = c;
    e.function = std::move(f);
    e.fitted_axis = fitted;
    return e;
  };
  const auto R = ElementKind::kRotation, T = ElementKind::kTranslation;
  Joint root;
  root.name = "root";
  root.type = JointType::kFree;
  root.child = 0;
  for (int k = 0; k < 3; ++k) root.elements.push_back(el(T, Eigen::Vector3d::Unit(k), k, Fn::Identity()));
  for (int k = 0; k < 3; ++k) root.elements.push_back(el(R, Eigen::Vector3d::Unit(k), 3 + k, Fn::Identity()));
  Joint hip;
  hip.name = "hip";
  hip.parent = 0;
  hip.child = 1;
  hip.centre = {0.05, -0.1, 0.08};
  hip.orientation = Eigen::AngleAxisd(0.3, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  hip.elements = {el(T, {1, 0, 0}, 6, KneeSpline()),
                  el(T, {0, 1, 0.2}, 6, Fn::Polynomial({0.01, -0.02, 0.03, 0.005})),
                  el(T, {0, 0, 1}, -1, Fn::Constant(0.012)),
                  el(R, {0.1, 0.2, 1}, 6, Fn::Identity(), true),
                  el(R, {1, 0, 0}, 6, Fn::Linear(0.3, 0.1))};
  Joint knee;
  knee.name = "knee";
  knee.parent = 1;
  knee.child = 2;
  knee.centre = {0.0, -0.4, 0.0};
  knee.elements = {el(T, {0, 1, 0}, 7, Fn::Multiplier(1.3, KneeSpline())),
                   el(T, {1, 0, 0}, 7, GcvKneeSpline()),
                   el(T, {0, 0, 1}, 6, Fn::PiecewiseLinear({-1.5, 0.0, 1.2}, {0.01, -0.005, 0.02})),
                   el(R, {0, 0, 1}, 7, Fn::NaturalCubicSpline({-2, -1, 0, 0.5, 2}, {-1.9, -1.1, 0.1, 0.4, 2.2})),
                   el(R, {1, 0, 0}, 6, Fn::Compose(KneeSpline(), Fn::Polynomial({0.5, 0.1})))};
  std::vector<Marker> markers;
  const Eigen::Vector3d pos[] = {{0.1, 0.0, 0.1}, {0.0, -0.2, 0.05}, {0.02, -0.1, -0.03}, {0.05, -0.3, 0.0}};
  const int seg[] = {0, 1, 2, 2};
  for (int i = 0; i < 4; ++i) {
    Marker m;
    m.name = "M" + std::to_string(i);
    m.segment = seg[i];
    m.position = pos[i];
    markers.push_back(m);
  }
  DerivedCoordinate beta;
  beta.name = "a_beta";
  beta.source = 6;
  beta.function = Fn::Multiplier(0.5, KneeSpline());
  DerivedCoordinate locked;
  locked.name = "locked";
  locked.function = Fn::Constant(0.2);
  Model model;
  Status s = Model::Build("functions", segments, {root, hip, knee}, coords, markers, {beta, locked}, &model);
  EXPECT_TRUE(s.ok()) << s.message();
  return model;
}

}  // namespace

TEST(CoordinateFunction, SimmSplineInterpolatesAndIsC2) {
  const Fn f = KneeSpline();
  ASSERT_TRUE(f.Check("f").ok());
  for (size_t i = 0; i < f.x.size(); ++i) EXPECT_NEAR(f.Value(f.x[i]), f.y[i], 1e-14);
  for (size_t i = 1; i + 1 < f.x.size(); ++i) {
    // Slope and curvature continuous across every interior knot.
    const double e = 1e-9, xi = f.x[i];
    EXPECT_NEAR(f.Derivative(xi - e), f.Derivative(xi + e), 1e-7);
    const double left = (f.Derivative(xi - e) - f.Derivative(xi - 1e-4)) / (1e-4 - e);
    const double right = (f.Derivative(xi + 1e-4) - f.Derivative(xi + e)) / (1e-4 - e);
    EXPECT_NEAR(left, right, 1e-3 * std::max(1.0, std::abs(left)));
  }
  // Linear extrapolation with the end slopes.
  EXPECT_NEAR(f.Value(3.0), f.y.back() + (3.0 - f.x.back()) * f.Derivative(f.x.back()), 1e-12);
  EXPECT_NEAR(f.Derivative(-3.0), f.Derivative(f.x.front()), 1e-12);
}

// Forsythe-Malcolm-Moler end conditions match the third derivative of the cubic through the end
// knots, so a cubic is reproduced exactly (a natural spline would not); 3 knots give the parabola.
TEST(CoordinateFunction, SplineEndConditionsAreOpenSims) {
  auto cubic = [](double x) { return 0.3 - 0.7 * x + 0.25 * x * x + 0.4 * x * x * x; };
  std::vector<double> x = {-2.0, -1.3, -0.2, 0.1, 0.9, 1.7, 2.5}, y;
  for (double v : x) y.push_back(cubic(v));
  for (const Fn& f : {Fn::SimmSpline(x, y), Fn::NaturalCubicSpline(x, y)})
    for (double v = -2.0; v <= 2.5; v += 0.01) EXPECT_NEAR(f.Value(v), cubic(v), 1e-12) << v;
  auto parabola = [](double x) { return 1.0 - x + 0.5 * x * x; };
  const Fn p = Fn::SimmSpline({-1.0, 0.3, 2.0}, {parabola(-1.0), parabola(0.3), parabola(2.0)});
  for (double v = -1.0; v <= 2.0; v += 0.05) EXPECT_NEAR(p.Value(v), parabola(v), 1e-12) << v;
  const Fn line = Fn::SimmSpline({0.0, 2.0}, {1.0, 2.0});
  EXPECT_NEAR(line.Value(1.0), 1.5, 1e-15);
  EXPECT_NEAR(line.Derivative(5.0), 0.5, 1e-15);
}

TEST(CoordinateFunction, DerivativesMatchCentralDifferences) {
  const std::vector<Fn> fns = {
      Fn::Identity(), Fn::Linear(-0.4, 0.2), Fn::Constant(0.7), KneeSpline(),
      Fn::NaturalCubicSpline({0, 1, 2, 3}, {0, 0.5, 0.2, 1.0}), Fn::Polynomial({0.1, -0.2, 0.3, 0.5}),
      Fn::Multiplier(1.7, KneeSpline()), Fn::Compose(KneeSpline(), Fn::Polynomial({2.0, -0.1, 0.4})),
      GcvKneeSpline(), Fn::GcvSpline(1, {0, 1}, {0.2, 0.5}), Fn::GcvSpline(2, {-1, 0, 0.5, 2}, {1, 0, 0.3, -1}),
      Fn::PiecewiseLinear({-1.5, 0.0, 1.2}, {0.01, -0.005, 0.02})};
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> u(-3, 3);
  for (const Fn& f : fns) {
    ASSERT_TRUE(f.Check("f").ok()) << Fn::KindName(f.kind);
    for (int i = 0; i < 200; ++i) {
      const double z = u(rng);
      EXPECT_NEAR(f.Derivative(z), NumericDerivative(f, z), 1e-7) << Fn::KindName(f.kind) << " at " << z;
    }
  }
  // A heptic through oscillating points: its truncated-power sum cancels to ~1e-13 of the values
  // (weights of alternating sign), which a difference quotient over 1e-6 turns into ~1e-7.
  const Fn heptic = Fn::GcvSpline(4, {-3, -2, -1, 0, 0.5, 1, 2, 2.5}, {0, 1, 0, 2, 1, 0, 1, 3});
  for (int i = 0; i < 200; ++i) {
    const double z = u(rng);
    EXPECT_NEAR(heptic.Derivative(z), NumericDerivative(heptic, z), 1e-6) << "heptic at " << z;
  }
  EXPECT_DOUBLE_EQ(Fn::Polynomial({2.0, -3.0, 1.0}).Value(2.0), 3.0);  // 2 z^2 - 3 z + 1
  EXPECT_DOUBLE_EQ(Fn::Multiplier(2.0, Fn::Constant(0.5)).Value(9.0), 1.0);
  EXPECT_TRUE(Fn::Multiplier(2.0, Fn::Constant(0.5)).IsConstant());
  EXPECT_FALSE(Fn::SimmSpline({0, 1}, {0, 1}).IsIdentity());
  EXPECT_TRUE(Fn::Linear(1.0, 0.0).IsIdentity());
}

// OpenSim's GCVSpline with error variance 0 is the natural spline of degree 2m - 1 through the
// points. The conditions that define it uniquely: it interpolates, it is C^(2m-2) at the knots, and
// beyond the end knots it is a polynomial of degree m - 1 (with the continuity, the natural end
// conditions). Checked here by differences, independently of how the factory solves for it; and
// it reproduces any polynomial of degree below m.
TEST(CoordinateFunction, GcvSplineIsTheInterpolatingNaturalSpline) {
  for (int m : {1, 2, 3, 4}) {
    const std::vector<double> x = {-2.0944, -1.7, -1.0, -0.45, 0.0, 0.3, 0.9, 2.0944};
    std::vector<double> y;
    for (double v : x) y.push_back(0.01 * std::sin(3.0 * v) + 0.002 * v);
    const Fn f = Fn::GcvSpline(m, x, y);
    ASSERT_TRUE(f.Check("f").ok()) << m << ": " << f.Check("f").message();
    for (size_t i = 0; i < x.size(); ++i) EXPECT_NEAR(f.Value(x[i]), y[i], 1e-13) << m;
    // Beyond each end: the (m)-th difference of a degree m - 1 polynomial vanishes.
    for (double end : {x.front(), x.back()}) {
      const double h = end < 0 ? -0.1 : 0.1;
      double diff = 0.0, binom = 1.0;
      for (int k = 0; k <= m; ++k) {
        diff += ((m - k) % 2 == 0 ? 1.0 : -1.0) * binom * f.Value(end + k * h);
        binom = binom * (m - k) / (k + 1);
      }
      EXPECT_NEAR(diff, 0.0, 1e-12) << "m " << m << " beyond " << end;
    }
    // Slope continuous at every knot (m >= 2), with a kink only for the linear spline.
    if (m >= 2)
      for (double k : x) EXPECT_NEAR(f.Derivative(k - 1e-9), f.Derivative(k + 1e-9), 1e-6) << m << " at " << k;
  }
  // The natural cubic (m = 2): zero curvature at both ends.
  const std::vector<double> x = {-1.0, -0.2, 0.4, 1.1, 1.5};
  const Fn cubic = Fn::GcvSpline(2, x, {0.3, -0.1, 0.25, 0.05, 0.4});
  for (double end : {x.front(), x.back()}) {
    // A one-sided second-order difference from inside: exact on the end interval's cubic.
    const double h = end < 0 ? 1e-3 : -1e-3;
    const double curvature =
        (-3.0 * cubic.Derivative(end) + 4.0 * cubic.Derivative(end + h) - cubic.Derivative(end + 2 * h)) / (2 * h);
    EXPECT_NEAR(curvature, 0.0, 1e-9) << end;
  }
  // A parabola is reproduced by the quintic (m = 3) exactly, a cubic is not.
  auto parabola = [](double v) { return 0.2 - 0.3 * v + 0.05 * v * v; };
  std::vector<double> py;
  for (double v : x) py.push_back(parabola(v));
  const Fn quintic = Fn::GcvSpline(3, {-1.0, -0.2, 0.4, 1.1, 1.5, 2.0}, {parabola(-1.0), parabola(-0.2), parabola(0.4), parabola(1.1), parabola(1.5), parabola(2.0)});
  for (double v = -2.0; v <= 3.0; v += 0.05) EXPECT_NEAR(quintic.Value(v), parabola(v), 1e-12) << v;
  auto cube = [](double v) { return v * v * v; };
  const Fn not_cubic = Fn::GcvSpline(3, {-1.0, -0.2, 0.4, 1.1, 1.5, 2.0}, {cube(-1.0), cube(-0.2), cube(0.4), cube(1.1), cube(1.5), cube(2.0)});
  EXPECT_GT(std::abs(not_cubic.Value(-0.6) - cube(-0.6)), 1e-4);
}

TEST(CoordinateFunction, PiecewiseLinearIsOpenSims) {
  const Fn f = Fn::PiecewiseLinear({-1.0, 0.0, 2.0}, {1.0, -1.0, 3.0});
  ASSERT_TRUE(f.Check("f").ok());
  EXPECT_DOUBLE_EQ(f.Value(-0.5), 0.0);
  EXPECT_DOUBLE_EQ(f.Value(1.0), 1.0);
  EXPECT_DOUBLE_EQ(f.Value(-2.0), 3.0);  // the end slopes beyond the ends
  EXPECT_DOUBLE_EQ(f.Value(3.0), 5.0);
  EXPECT_DOUBLE_EQ(f.Derivative(0.5), 2.0);
}

TEST(CoordinateFunction, CheckRejectsBadSplines) {
  auto says = [](const Fn& f, const std::string& what) {
    const std::string m = f.Check("f").message();
    return m.find(what) != std::string::npos ? ::testing::AssertionSuccess() : ::testing::AssertionFailure() << m;
  };
  EXPECT_TRUE(says(Fn::GcvSpline(3, {0, 1, 2, 3, 4}, {0, 1, 2, 3, 4}), "GCV spline of half order 3 needs at least 6 points, has 5"));
  EXPECT_TRUE(says(Fn::GcvSpline(5, {0, 1, 2, 3, 4, 5, 6, 7, 8, 9}, {0, 1, 2, 3, 4, 5, 6, 7, 8, 9}), "half order 5 is not 1 to 4"));
  EXPECT_TRUE(says(Fn::GcvSpline(1, {0, 1, 1}, {0, 1, 2}), "x values must increase"));
  EXPECT_FALSE(Fn::PiecewiseLinear({0, 1}, {0}).Check("f").ok());
  EXPECT_FALSE(Fn::SimmSpline({0, 1, 1}, {0, 1, 2}).Check("f").ok());
  EXPECT_FALSE(Fn::SimmSpline({0, 1}, {0}).Check("f").ok());
  EXPECT_FALSE(Fn::SimmSpline({0}, {0}).Check("f").ok());
  EXPECT_FALSE(Fn::Polynomial({}).Check("f").ok());
  const Status s = Fn::SimmSpline({0, 2, 1}, {0, 1, 2}).Check("joints[1].elements[0].function");
  EXPECT_NE(s.message().find("joints[1].elements[0].function: spline x values must increase"), std::string::npos)
      << s.message();
}

TEST(Kinematics, FunctionModelJacobiansMatchCentralDifferences) {
  const Model model = FunctionModel();
  ASSERT_EQ(model.num_markers(), 4);
  // Coordinate a drives hip and knee; the knee markers list it.
  EXPECT_NE(std::find(model.marker_coordinates(3).begin(), model.marker_coordinates(3).end(), 6),
            model.marker_coordinates(3).end());
  std::mt19937 rng(5);
  for (int trial = 0; trial < 8; ++trial) {
    // Wide poses: outside the spline knots too (linear extrapolation).
    const Eigen::VectorXd z = RandomPose(model, rng, trial < 4 ? 0.8 : 2.5);
    const Eigen::VectorXd p = RandomParameters(model, rng);
    EXPECT_LT(ExpectJacobiansMatchCentralDifferences(model, z, p), 1e-6);
  }
}

// A non-identity translation of a non-root joint moves with the parent's scale; identity
// translations (degrees of freedom) do not.
TEST(Kinematics, TranslationFunctionsScaleWithTheParent) {
  const Model model = FunctionModel();
  Eigen::VectorXd z = Eigen::VectorXd::Zero(model.num_coordinates());
  z[6] = 0.4;
  z[0] = 0.3;
  Eigen::VectorXd p = model.InitialParameters();
  const Eigen::Matrix3Xd x1 = Positions(model, z, p);
  p[model.scale_index(0)] = 2.0;
  const Eigen::Matrix3Xd x2 = Positions(model, z, p);
  // The thigh's origin: root translation (not scaled) + 2 * (centre + hip translations).
  const Eigen::Vector3d root(0.3, 0.0, 0.0);
  Geometry g(model);
  ModelData d(model);
  ForwardKinematics(model, g, z, &d);
  const Eigen::Vector3d o1 = d.segment_position[1];
  g.Set(model, p);
  ForwardKinematics(model, g, z, &d);
  EXPECT_LT((d.segment_position[1] - (root + 2.0 * (o1 - root))).norm(), 1e-12);
  EXPECT_GT((x2 - x1).norm(), 0.01);
}

TEST(Kinematics, FunctionModelEvaluationDoesNotAllocate) {
  const Model model = FunctionModel();
  Geometry g(model);
  ModelData d(model);
  const Eigen::VectorXd z = Eigen::VectorXd::Constant(model.num_coordinates(), 0.3);
  Eigen::Matrix<double, 3, Eigen::Dynamic> jz(3, model.max_chain_coordinates()),
      jp(3, model.max_chain_parameters());
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  g.Set(model, model.InitialParameters());
  Eigen::internal::set_is_malloc_allowed(false);
  ForwardKinematics(model, g, z, &d);
  for (int m = 0; m < model.num_markers(); ++m) {
    sum += MarkerPosition(model, g, d, m);
    auto bz = jz.leftCols(model.marker_coordinates(m).size());
    auto bp = jp.leftCols(model.marker_parameters(m).size());
    MarkerJacobian(model, g, d, m, &bz, &bp);
  }
  double derived = 0;
  for (const auto& dc : model.derived_coordinates()) derived += dc.Value(z);
  Eigen::internal::set_is_malloc_allowed(true);
  EXPECT_TRUE(sum.allFinite());
  EXPECT_TRUE(std::isfinite(derived));
}

TEST(ModelJson, FunctionsAndDerivedCoordinatesRoundTripExactly) {
  const Model model = FunctionModel();
  const std::string text = ModelToJsonString(model);
  Model back;
  Status s = ParseModelJson(text, "mem", &back);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(ModelToJsonString(back), text);
  for (int j = 0; j < model.num_joints(); ++j)
    for (size_t e = 0; e < model.joints()[j].elements.size(); ++e)
      EXPECT_TRUE(back.joints()[j].elements[e].function == model.joints()[j].elements[e].function);
  ASSERT_EQ(back.derived_coordinates().size(), 2u);
  EXPECT_TRUE(back.derived_coordinates()[0].function == model.derived_coordinates()[0].function);
  EXPECT_EQ(back.derived_coordinates()[0].source, 6);
  EXPECT_EQ(back.derived_coordinates()[1].source, -1);
  std::mt19937 rng(2);
  const Eigen::VectorXd z = RandomPose(model, rng);
  EXPECT_EQ((Positions(back, z, back.InitialParameters()) - Positions(model, z, model.InitialParameters())).norm(), 0.0);
  // A bad spline names its place.
  std::string bad = text;
  const size_t at = bad.find("-1.22173", bad.find("\"joints\""));
  ASSERT_NE(at, std::string::npos);
  bad.replace(at, 8, "-3.0");
  s = ParseModelJson(bad, "bad.json", &back);
  EXPECT_FALSE(s.ok());
  EXPECT_NE(s.message().find("bad.json: joints[1].elements[0].function: spline x values must increase"), std::string::npos)
      << s.message();
}
