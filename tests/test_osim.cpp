// OpenSim models in and out: the real models of shared/data import; OpenSim's own scaled model
// and IK angles reproduce the measured markers of a walk through our kinematics; Jacobians of
// imported models against finite differences; export/import round trips to 1e-9 m; .mot out;
// bad input.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <map>
#include <random>
#include <regex>
#include <sstream>

#include "formats/mot.h"
#include "formats/osim.h"
#include "formats/trc.h"
#include "model/kinematics.h"
#include "model/model_io.h"
#include "model_test_util.h"
#include "tests/osim_test_util.h"
#include "tests/file_test_util.h"
#include "tests/model_test_util.h"

namespace fs = std::filesystem;
using namespace mocap;
using namespace mocap::formats;
using mocap::testutil::CoordinateColumns;
using mocap::testutil::ExpectJacobiansMatchCentralDifferences;
using mocap::testutil::NearestTime;
using mocap::testutil::OsimPose;
using mocap::testutil::Positions;
using mocap::testutil::RandomParameters;
using mocap::testutil::RandomPose;
using ::testing::HasSubstr;

namespace {

using mocap::testutil::SharedData;
std::string Gait(const std::string& f) { return SharedData() + "/opensim_gait2354_subject01/" + f; }
std::string Welk(const std::string& f) { return SharedData() + "/welk007_hipfunc/" + f; }


std::string TmpPath(const std::string& suffix) {
  const fs::path dir = fs::path(MOCAP_TEST_TMP) / "osim";
  fs::create_directories(dir);
  const auto* info = ::testing::UnitTest::GetInstance()->current_test_info();
  return (dir / (std::string(info->test_suite_name()) + "_" + info->name() + suffix)).string();
}

OsimImport MustImport(const std::string& path) {
  OsimImport im;
  Status s = ImportOsim(path, &im);
  EXPECT_TRUE(s.ok()) << s.message();
  return im;
}

// Marker positions of `b` for the pose z of `a`, matched by coordinate and marker name.
Eigen::Matrix3Xd PositionsByName(const Model& a, const Eigen::VectorXd& za, const Model& b) {
  Eigen::VectorXd zb = b.DefaultCoordinates();
  for (int c = 0; c < b.num_coordinates(); ++c) {
    const int k = a.FindCoordinate(b.coordinates()[c].name);
    EXPECT_GE(k, 0) << b.coordinates()[c].name;
    if (k >= 0) zb[c] = za[k];
  }
  const Eigen::Matrix3Xd xb = Positions(b, zb, b.InitialParameters());
  Eigen::Matrix3Xd out(3, a.num_markers());
  for (int m = 0; m < a.num_markers(); ++m) {
    const int k = b.FindMarker(a.markers()[m].name);
    EXPECT_GE(k, 0) << a.markers()[m].name;
    out.col(m) = k >= 0 ? Eigen::Vector3d(xb.col(k)) : Eigen::Vector3d::Constant(NAN);
  }
  return out;
}

// Exports `fitted` into `import`'s document, imports that, and compares marker positions over
// random poses. Returns the largest distance (m).
double RoundTripError(const OsimImport& import, const Model& fitted, std::mt19937& rng) {
  std::string xml;
  Status s = ExportOsimText(fitted, import, &xml);
  EXPECT_TRUE(s.ok()) << s.message();
  OsimImport back;
  s = ImportOsimText(xml, "exported.osim", &back);
  EXPECT_TRUE(s.ok()) << s.message();
  if (!s.ok()) return INFINITY;
  EXPECT_EQ(back.model.num_coordinates(), fitted.num_coordinates());
  EXPECT_EQ(back.model.num_markers(), fitted.num_markers());
  double worst = 0;
  for (int trial = 0; trial < 20; ++trial) {
    const Eigen::VectorXd z = RandomPose(fitted, rng, 1.0);
    const Eigen::Matrix3Xd xa = Positions(fitted, z, fitted.InitialParameters());
    const Eigen::Matrix3Xd xb = PositionsByName(fitted, z, back.model);
    worst = std::max(worst, (xa - xb).colwise().norm().maxCoeff());
  }
  return worst;
}

// A small OpenSim 4 model to break in the bad-input tests: pelvis on a free custom joint,
// femur on a pin, tibia on a knee with a spline, patella coupled to the knee.
const char* kSmallModel = R"(<?xml version="1.0" encoding="UTF-8" ?>
<OpenSimDocument Version="40000">
  <Model name="small">
    <Ground name="ground" />
    <BodySet name="bodyset">
      <objects>
        <Body name="pelvis"><mass>10</mass><mass_center>0 0 0</mass_center><inertia>1 1 1 0 0 0</inertia></Body>
        <Body name="femur"><mass>5</mass><mass_center>0 -0.2 0</mass_center><inertia>1 1 1 0 0 0</inertia></Body>
        <Body name="tibia"><mass>3</mass><mass_center>0 -0.2 0</mass_center><inertia>1 1 1 0 0 0</inertia></Body>
      </objects>
    </BodySet>
    <JointSet name="jointset">
      <objects>
        <FreeJoint name="ground_pelvis">
          <socket_parent_frame>/ground</socket_parent_frame>
          <socket_child_frame>/bodyset/pelvis</socket_child_frame>
          <coordinates>
            <Coordinate name="rx" /><Coordinate name="ry" /><Coordinate name="rz" />
            <Coordinate name="tx" /><Coordinate name="ty"><default_value>0.9</default_value></Coordinate><Coordinate name="tz" />
          </coordinates>
        </FreeJoint>
        <PinJoint name="hip">
          <socket_parent_frame>pelvis_offset</socket_parent_frame>
          <socket_child_frame>femur_offset</socket_child_frame>
          <coordinates><Coordinate name="hip_flexion"><range>-1 1</range><clamped>true</clamped></Coordinate></coordinates>
          <frames>
            <PhysicalOffsetFrame name="pelvis_offset">
              <socket_parent>/bodyset/pelvis</socket_parent>
              <translation>-0.07 -0.06 0.08</translation>
              <orientation>0.1 -0.2 0.3</orientation>
            </PhysicalOffsetFrame>
            <PhysicalOffsetFrame name="femur_offset">
              <socket_parent>/bodyset/femur</socket_parent>
              <translation>0.01 0.02 0</translation>
              <orientation>0 0 0.2</orientation>
            </PhysicalOffsetFrame>
          </frames>
        </PinJoint>
        <CustomJoint name="knee">
          <socket_parent_frame>/bodyset/femur</socket_parent_frame>
          <socket_child_frame>/bodyset/tibia</socket_child_frame>
          <coordinates>
            <Coordinate name="knee_angle"><default_value>0</default_value></Coordinate>
            <Coordinate name="knee_beta" />
          </coordinates>
          <SpatialTransform>
            <TransformAxis name="rotation1"><coordinates>knee_angle</coordinates><axis>0 0 1</axis><LinearFunction name="function"><coefficients>1 0</coefficients></LinearFunction></TransformAxis>
            <TransformAxis name="rotation2"><coordinates>knee_beta</coordinates><axis>1 0 0</axis><PolynomialFunction name="function"><coefficients>0.1 0.05 0</coefficients></PolynomialFunction></TransformAxis>
            <TransformAxis name="rotation3"><coordinates></coordinates><axis>0 1 0</axis><Constant name="function"><value>0</value></Constant></TransformAxis>
            <TransformAxis name="translation1"><coordinates>knee_angle</coordinates><axis>1 0 0</axis><SimmSpline name="function"><x>-2 -1 0 1 2</x><y>-0.003 0.002 0.004 0.001 -0.002</y></SimmSpline></TransformAxis>
            <TransformAxis name="translation2"><coordinates>knee_angle</coordinates><axis>0 1 0</axis><NaturalCubicSpline name="function"><x>-2 -1 0 2</x><y>-0.42 -0.41 -0.40 -0.396</y></NaturalCubicSpline></TransformAxis>
            <TransformAxis name="translation3"><coordinates></coordinates><axis>0 0 1</axis><Constant name="function"><value>0.003</value></Constant></TransformAxis>
          </SpatialTransform>
        </CustomJoint>
      </objects>
    </JointSet>
    <ConstraintSet name="constraintset">
      <objects>
        <CoordinateCouplerConstraint name="knee_coupler">
          <isEnforced>true</isEnforced>
          <coupled_coordinates_function><SimmSpline><x>-2 0 2</x><y>-1 0 1.5</y></SimmSpline></coupled_coordinates_function>
          <independent_coordinate_names>knee_angle</independent_coordinate_names>
          <dependent_coordinate_name>knee_beta</dependent_coordinate_name>
          <scale_factor>0.8</scale_factor>
        </CoordinateCouplerConstraint>
        <PointConstraint name="some_point" />
      </objects>
    </ConstraintSet>
    <MarkerSet name="markerset">
      <objects>
        <Marker name="ASIS"><socket_parent_frame>/bodyset/pelvis</socket_parent_frame><location>0.02 0.03 0.12</location><fixed>false</fixed></Marker>
        <Marker name="THIGH"><socket_parent_frame>/bodyset/femur</socket_parent_frame><location>0.03 -0.2 0.05</location><fixed>true</fixed></Marker>
        <Marker name="KNEE"><socket_parent_frame>/bodyset/femur</socket_parent_frame><location>0.0 -0.4 0.05</location></Marker>
        <Marker name="SHANK"><socket_parent_frame>/bodyset/tibia</socket_parent_frame><location>0.02 -0.2 0.04</location></Marker>
        <Marker name="ANKLE"><socket_parent_frame>/bodyset/tibia</socket_parent_frame><location>0.0 -0.4 0.04</location></Marker>
      </objects>
    </MarkerSet>
  </Model>
</OpenSimDocument>
)";

int LineOf(const std::string& text, const std::string& needle) {
  const size_t at = text.find(needle);
  EXPECT_NE(at, std::string::npos) << needle;
  return 1 + static_cast<int>(std::count(text.begin(), text.begin() + at, '\n'));
}

}  // namespace

TEST(Osim, SmallModelImportsWithCouplerAndIgnoredConstraint) {
  OsimImport im;
  Status s = ImportOsimText(kSmallModel, "small.osim", &im);
  ASSERT_TRUE(s.ok()) << s.message();
  const Model& m = im.model;
  EXPECT_EQ(m.num_segments(), 3);
  EXPECT_EQ(m.num_coordinates(), 8);  // knee_beta is derived
  ASSERT_EQ(m.derived_coordinates().size(), 1u);
  EXPECT_EQ(m.derived_coordinates()[0].name, "knee_beta");
  EXPECT_EQ(m.derived_coordinates()[0].source, m.FindCoordinate("knee_angle"));
  ASSERT_EQ(im.ignored.size(), 1u);
  EXPECT_THAT(im.ignored[0], HasSubstr("PointConstraint 'some_point'"));
  EXPECT_EQ(m.joints()[m.FindJoint("hip")].type, JointType::kHinge);
  EXPECT_EQ(m.joints()[m.FindJoint("ground_pelvis")].type, JointType::kFree);
  EXPECT_EQ(m.num_markers(), 5);
  for (const Marker& mk : m.markers()) EXPECT_FALSE(mk.optional);
  // OpenSim's <fixed> (a landmark the marker placer does not move) and <clamped> (a range IK keeps).
  EXPECT_FALSE(m.markers()[m.FindMarker("ASIS")].fixed);
  EXPECT_TRUE(m.markers()[m.FindMarker("THIGH")].fixed);
  EXPECT_FALSE(m.markers()[m.FindMarker("KNEE")].fixed);
  const Coordinate& hip = m.coordinates()[m.FindCoordinate("hip_flexion")];
  EXPECT_TRUE(hip.clamped);
  EXPECT_DOUBLE_EQ(hip.min_value, -1.0);
  EXPECT_DOUBLE_EQ(hip.max_value, 1.0);
  EXPECT_FALSE(m.coordinates()[m.FindCoordinate("knee_angle")].clamped);
  EXPECT_EQ(im.motion.at("knee_beta"), OsimMotion::kCoupled);
  EXPECT_EQ(im.motion.at("tx"), OsimMotion::kTranslational);
  EXPECT_EQ(im.motion.at("knee_angle"), OsimMotion::kRotational);
  std::mt19937 rng(1);
  for (int trial = 0; trial < 6; ++trial)
    EXPECT_LT(ExpectJacobiansMatchCentralDifferences(m, RandomPose(m, rng, 1.5), RandomParameters(m, rng)), 1e-6);
}

// The pelvis sits where the free joint puts it, the hip offset frame's orientation is body-fixed
// XYZ, and markers keep their OpenSim body positions (checked against a hand computation).
TEST(Osim, FramesFollowOpenSimsConventions) {
  OsimImport im;
  ASSERT_TRUE(ImportOsimText(kSmallModel, "small.osim", &im).ok());
  const Model& m = im.model;
  Eigen::VectorXd z = m.DefaultCoordinates();
  z[m.FindCoordinate("hip_flexion")] = 0.4;
  const Eigen::Matrix3Xd x = Positions(m, z, m.InitialParameters());
  // Pelvis at (0, 0.9, 0), unrotated: ASIS at its body location.
  EXPECT_LT((x.col(m.FindMarker("ASIS")) - Eigen::Vector3d(0.02, 0.93, 0.12)).norm(), 1e-15);
  auto rot = [](double a, double b, double c) {
    return (Eigen::AngleAxisd(a, Eigen::Vector3d::UnitX()) * Eigen::AngleAxisd(b, Eigen::Vector3d::UnitY()) *
            Eigen::AngleAxisd(c, Eigen::Vector3d::UnitZ())).toRotationMatrix();
  };
  // femur body frame: X_G,pelvis * X_pelvis,F * Rz(q) * X_femur,M^-1.
  const Eigen::Matrix3d rf = rot(0.1, -0.2, 0.3) * Eigen::AngleAxisd(0.4, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  const Eigen::Matrix3d rm = rot(0, 0, 0.2);
  const Eigen::Vector3d f_origin = Eigen::Vector3d(0, 0.9, 0) + Eigen::Vector3d(-0.07, -0.06, 0.08);
  const Eigen::Vector3d thigh = f_origin + rf * (rm.transpose() * (Eigen::Vector3d(0.03, -0.2, 0.05) - Eigen::Vector3d(0.01, 0.02, 0)));
  EXPECT_LT((x.col(m.FindMarker("THIGH")) - thigh).norm(), 1e-14);
}

TEST(Osim, Gait2354ImportsWithItsMarkerSet) {
  SKIP_WITHOUT_SHARED_DATA();
  OsimImport im = MustImport(Gait("gait2354_simbody.osim"));
  EXPECT_EQ(im.model.num_markers(), 0);
  EXPECT_EQ(im.model.num_coordinates(), 23);
  EXPECT_EQ(im.model.num_segments(), 12);
  Status s = LoadOsimMarkerSet(Gait("gait2354_Scale_MarkerSet.xml"), &im);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(im.model.num_markers(), 39);
  const Model& m = im.model;
  const int asis = m.FindMarker("R.ASIS");
  ASSERT_GE(asis, 0);
  EXPECT_EQ(m.segments()[m.markers()[asis].segment].name, "pelvis");
  EXPECT_LT((m.markers()[asis].position - Eigen::Vector3d(0.02, 0.03, 0.128)).norm(), 1e-12);
  // The knee: a custom joint with spline translations and a fitted flexion axis.
  const Joint& knee = m.joints()[m.FindJoint("knee_r")];
  EXPECT_EQ(knee.type, JointType::kCustom);
  int splines = 0, fitted = 0;
  for (const auto& el : knee.elements) {
    splines += el.function.kind == CoordinateFunction::Kind::kSimmSpline;
    fitted += el.fitted_axis;
  }
  EXPECT_EQ(splines, 2);
  EXPECT_EQ(fitted, 1);
  EXPECT_EQ(m.joints()[m.FindJoint("ground_pelvis")].type, JointType::kFree);
  EXPECT_EQ(m.joints()[m.FindJoint("hip_r")].type, JointType::kSpherical);
  std::mt19937 rng(3);
  for (int trial = 0; trial < 3; ++trial)
    EXPECT_LT(ExpectJacobiansMatchCentralDifferences(m, RandomPose(m, rng), RandomParameters(m, rng)), 1e-6);
}

// OpenSim's scaled model and its IK angles, evaluated by our kinematics, against the measured
// markers of the walk: the RMS is OpenSim's IK residual, a few mm to ~2 cm if (and only if) our
// kinematics reproduce OpenSim's (frames, Euler conventions, the knee's splines and scaling).
TEST(Osim, OpenSimsScaledModelAndIkReproduceTheWalk) {
  SKIP_WITHOUT_SHARED_DATA();
  OsimImport im = MustImport(Gait("reference_outputs/subject01_simbody.osim"));
  const Model& m = im.model;
  ASSERT_EQ(m.num_markers(), 39);
  CoordinateTable ik;
  Status s = ReadMot(Gait("reference_outputs/subject01_walk1_ik.mot"), &ik);
  ASSERT_TRUE(s.ok()) << s.message();
  MarkerTrial trial;
  s = ReadTrc(Gait("subject01_walk1.trc"), &trial);
  ASSERT_TRUE(s.ok()) << s.message();
  const std::vector<int> column = CoordinateColumns(m, ik);
  for (int c = 0; c < m.num_coordinates(); ++c) ASSERT_GE(column[c], 0) << m.coordinates()[c].name;
  std::vector<int> in_trial(m.num_markers());
  for (int k = 0; k < m.num_markers(); ++k) in_trial[k] = trial.FindMarker(m.markers()[k].name);
  Geometry g(m);
  ModelData d(m);
  double sum_sq = 0;
  int count = 0;
  std::vector<double> frame_rms;
  std::vector<double> marker_sq(m.num_markers(), 0.0);
  // OpenSim's IK minimises sum_k w_k |x_k - r_k|^2 with the weights of its setup (and coordinate
  // tasks on the subtalar and mtp angles): at its solution the gradient along every other
  // coordinate vanishes -- if our kinematics are OpenSim's.
  std::vector<double> weight(m.num_markers(), 0.0);
  {
    std::ifstream in(Gait("subject01_Setup_IK.xml"));
    std::stringstream ss;
    ss << in.rdbuf();
    const std::string setup = ss.str();
    const std::regex task(R"re(<IKMarkerTask name="([^"]+)">[\s\S]*?<apply>\s*true\s*</apply>[\s\S]*?<weight>\s*([0-9.eE+-]+)\s*</weight>)re");
    for (auto it = std::sregex_iterator(setup.begin(), setup.end(), task); it != std::sregex_iterator(); ++it) {
      const int k = m.FindMarker((*it)[1]);
      if (k >= 0) weight[k] = std::stod((*it)[2]);
    }
  }
  double worst_stationarity = 0;
  std::string worst_coordinate;
  std::vector<int> marker_n(m.num_markers(), 0);
  for (int f = 0; f < ik.num_frames(); ++f) {
    ForwardKinematics(m, g, OsimPose(im, ik, column, f), &d);
    // The TRC frame at the same time (its times are rounded to the ms).
    const int tf = NearestTime(trial.times, ik.times[f]);
    ASSERT_LT(std::abs(trial.times[tf] - ik.times[f]), 0.5 / trial.rate_hz);
    double fs = 0;
    int fn = 0;
    for (int k = 0; k < m.num_markers(); ++k) {
      if (in_trial[k] < 0 || !trial.Has(tf, in_trial[k])) continue;
      const double e2 = (MarkerPosition(m, g, d, k) - trial.At(tf, in_trial[k])).squaredNorm();
      fs += e2;
      ++fn;
      marker_sq[k] += e2;
      ++marker_n[k];
    }
    ASSERT_GT(fn, 20);
    // Relative gradient per coordinate: |sum w J^T e| / sum w |J| |e|.
    Eigen::VectorXd grad = Eigen::VectorXd::Zero(m.num_coordinates()), size = grad;
    for (int k = 0; k < m.num_markers(); ++k) {
      if (in_trial[k] < 0 || !trial.Has(tf, in_trial[k]) || weight[k] == 0) continue;
      const auto& cols = m.marker_coordinates(k);
      Eigen::MatrixXd jz(3, cols.size());
      MarkerJacobian(m, g, d, k, &jz, static_cast<Eigen::MatrixXd*>(nullptr));
      const Eigen::Vector3d e = MarkerPosition(m, g, d, k) - trial.At(tf, in_trial[k]);
      for (size_t i = 0; i < cols.size(); ++i) {
        grad[cols[i]] += weight[k] * jz.col(i).dot(e);
        size[cols[i]] += weight[k] * jz.col(i).norm() * e.norm();
      }
    }
    for (int c = 0; c < m.num_coordinates(); ++c) {
      const std::string& n = m.coordinates()[c].name;
      if (n.rfind("subtalar", 0) == 0 || n.rfind("mtp", 0) == 0 || size[c] == 0) continue;
      const double r = std::abs(grad[c]) / size[c];
      if (r > worst_stationarity) {
        worst_stationarity = r;
        worst_coordinate = n + " at t=" + std::to_string(ik.times[f]);
      }
    }
    sum_sq += fs;
    count += fn;
    frame_rms.push_back(std::sqrt(fs / fn));
  }
  const double rms_mm = 1000 * std::sqrt(sum_sq / count);
  double max_jump_mm = 0, max_frame_mm = 0;
  for (size_t f = 0; f < frame_rms.size(); ++f) {
    max_frame_mm = std::max(max_frame_mm, 1000 * frame_rms[f]);
    if (f > 0) max_jump_mm = std::max(max_jump_mm, 1000 * std::abs(frame_rms[f] - frame_rms[f - 1]));
  }
  std::printf("OpenSim's scale + IK of subject01_walk1 through our kinematics: marker RMS %.2f mm over "
              "%d frames (%d marker samples), worst frame %.2f mm, largest frame-to-frame change %.2f mm\n",
              rms_mm, ik.num_frames(), count, max_frame_mm, max_jump_mm);
  for (int k = 0; k < m.num_markers(); ++k)
    if (marker_n[k] > 0)
      std::printf("  %-16s %.2f mm\n", m.markers()[k].name.c_str(), 1000 * std::sqrt(marker_sq[k] / marker_n[k]));
  std::printf("  stationarity of OpenSim's weighted IK objective in our kinematics: worst relative "
              "gradient %.2e (%s)\n", worst_stationarity, worst_coordinate.c_str());
  EXPECT_LT(worst_stationarity, 0.02);
  EXPECT_GT(rms_mm, 1.0);   // a perfect fit of real data would be suspicious
  EXPECT_LT(rms_mm, 25.0);
  EXPECT_LT(max_frame_mm, 35.0);
  EXPECT_LT(max_jump_mm, 3.0);  // continuous: no frame where our kinematics jump away
}

TEST(Osim, Welk007ModelsImportWithCouplersAndJacobians) {
  SKIP_WITHOUT_SHARED_DATA();
  for (const char* name : {"unscaled_generic.osim", "manually_scaled.osim"}) {
    SCOPED_TRACE(name);
    OsimImport im = MustImport(Welk(name));
    const Model& m = im.model;
    EXPECT_EQ(m.num_markers(), 68);  // the file lists 72, four of them commented out
    for (const char* mk : {"R_HJC", "L_HJC", "midASIS", "r.ASIS", "r_knee"}) EXPECT_GE(m.FindMarker(mk), 0) << mk;
    for (const Marker& mk : m.markers()) EXPECT_FALSE(mk.optional);
    // The patellae follow the knees: knee_angle_r drives both joints.
    const int knee = m.FindCoordinate("knee_angle_r");
    ASSERT_GE(knee, 0);
    EXPECT_LT(m.FindCoordinate("knee_angle_r_beta"), 0);
    bool drives_patella = false;
    for (const auto& el : m.joints()[m.FindJoint("patellofemoral_r")].elements) drives_patella |= el.coordinate == knee;
    EXPECT_TRUE(drives_patella);
    bool derived = false;
    for (const auto& dc : m.derived_coordinates()) derived |= dc.name == "knee_angle_r_beta" && dc.source == knee;
    EXPECT_TRUE(derived);
    EXPECT_EQ(m.joints()[m.FindJoint("ankle_r")].type, JointType::kHinge);
    // Both wrist coordinates are locked: constants, kept as derived coordinates for a .mot.
    for (const char* n : {"wrist_flex_r", "wrist_dev_r"}) {
      EXPECT_LT(m.FindCoordinate(n), 0) << n;
      bool constant = false;
      for (const auto& dc : m.derived_coordinates()) constant |= dc.name == n && dc.source == -1;
      EXPECT_TRUE(constant) << n;
    }
    for (const auto& el : m.joints()[m.FindJoint("radius_hand_r")].elements) EXPECT_TRUE(el.function.IsConstant());
    std::mt19937 rng(17);
    for (int trial = 0; trial < 3; ++trial)
      EXPECT_LT(ExpectJacobiansMatchCentralDifferences(m, RandomPose(m, rng), RandomParameters(m, rng)), 1e-6);
  }
}

TEST(Osim, ExportImportRoundTripKeepsKinematics) {
  std::vector<OsimImport> imports;
  OsimImport small;
  ASSERT_TRUE(ImportOsimText(kSmallModel, "small.osim", &small).ok());
  imports.push_back(small);
  if (fs::is_directory(SharedData())) {
    OsimImport gait = MustImport(Gait("gait2354_simbody.osim"));
    ASSERT_TRUE(LoadOsimMarkerSet(Gait("gait2354_Scale_MarkerSet.xml"), &gait).ok());
    imports.push_back(gait);
    imports.push_back(MustImport(Gait("reference_outputs/subject01_simbody.osim")));
    imports.push_back(MustImport(Welk("unscaled_generic.osim")));
    imports.push_back(MustImport(Welk("manually_scaled.osim")));
  } else {
    std::printf("shared data folder %s is absent: round trip of the small model only\n", SharedData().c_str());
  }
  std::mt19937 rng(23);
  for (const OsimImport& im : imports) {
    SCOPED_TRACE(im.source);
    const double same = RoundTripError(im, im.model, rng);
    EXPECT_LT(same, 1e-9);
    double worst = 0;
    for (int k = 0; k < 3; ++k) {
      const Model fitted = mocap::testutil::Baked(im.model, RandomParameters(im.model, rng));
      worst = std::max(worst, RoundTripError(im, fitted, rng));
    }
    std::printf("%s: round trip %.3g m unchanged, %.3g m after random scales, centres, axes, markers\n",
                im.source.c_str(), same, worst);
    EXPECT_LT(worst, 1e-9);
  }
}

TEST(Osim, ExportWritesOpenSimsScaling) {
  OsimImport im;
  ASSERT_TRUE(ImportOsimText(kSmallModel, "small.osim", &im).ok());
  Eigen::VectorXd p = im.model.InitialParameters();
  p[im.model.scale_index(im.model.FindSegment("femur"))] = 1.2;
  std::string xml;
  ASSERT_TRUE(ExportOsimText(mocap::testutil::Baked(im.model, p), im, &xml).ok());
  // The knee's translations are functions of the femur: wrapped in a MultiplierFunction; its
  // mass properties scaled (mass kept).
  EXPECT_THAT(xml, HasSubstr("<MultiplierFunction name=\"function\">"));
  EXPECT_THAT(xml, HasSubstr("<scale>1.2</scale>"));
  EXPECT_THAT(xml, HasSubstr("<mass_center>0 -0.24 0</mass_center>"));
  EXPECT_THAT(xml, HasSubstr("<mass>5</mass>"));
  // The exported document imports again (and says which constraint it ignores).
  OsimImport back;
  Status s = ImportOsimText(xml, "back.osim", &back);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(back.ignored.size(), 1u);
}

TEST(Osim, MotHasOpenSimsNamesAndUnits) {
  OsimImport im;
  ASSERT_TRUE(ImportOsimText(kSmallModel, "small.osim", &im).ok());
  const Model& m = im.model;
  std::mt19937 rng(4);
  Eigen::MatrixXd poses(3, m.num_coordinates());
  for (int f = 0; f < 3; ++f) poses.row(f) = RandomPose(m, rng).transpose();
  const std::string path = TmpPath(".mot");
  Status s = WriteOsimMot(path, im, m, {0.0, 0.01, 0.02}, poses);
  ASSERT_TRUE(s.ok()) << s.message();
  CoordinateTable t;
  ASSERT_TRUE(ReadMot(path, &t).ok());
  EXPECT_TRUE(t.in_degrees);
  ASSERT_EQ(t.column_names.size(), 9u);
  const int hip = t.FindColumn("hip_flexion"), tx = t.FindColumn("tx"), beta = t.FindColumn("knee_beta");
  ASSERT_GE(hip, 0);
  ASSERT_GE(tx, 0);
  ASSERT_GE(beta, 0);
  for (int f = 0; f < 3; ++f) {
    EXPECT_NEAR(t.values(f, hip), poses(f, m.FindCoordinate("hip_flexion")) * 180 / M_PI, 1e-6);
    EXPECT_NEAR(t.values(f, tx), poses(f, m.FindCoordinate("tx")), 1e-8);
    // Coupled: radians, as OpenSim writes it, = 0.8 * spline(knee_angle).
    EXPECT_NEAR(t.values(f, beta), m.derived_coordinates()[0].Value(poses.row(f).transpose()), 1e-8);
  }
}

// OpenSim 3.x: joints inside bodies, CoordinateSet, markers with <body>, ground as a body.
TEST(Osim, OpenSim3LayoutMatchesThe4Layout) {
  const char* v3 = R"(<?xml version="1.0" encoding="UTF-8"?>
<OpenSimDocument Version="30000">
  <Model name="small3">
    <BodySet><objects>
      <Body name="ground"><mass>0</mass></Body>
      <Body name="pelvis"><mass>10</mass>
        <Joint><FreeJoint name="ground_pelvis"><parent_body>ground</parent_body>
          <location_in_parent>0 0 0</location_in_parent><orientation_in_parent>0 0 0</orientation_in_parent>
          <location>0 0 0</location><orientation>0 0 0</orientation>
          <CoordinateSet><objects>
            <Coordinate name="rx" /><Coordinate name="ry" /><Coordinate name="rz" />
            <Coordinate name="tx" /><Coordinate name="ty"><default_value>0.9</default_value></Coordinate><Coordinate name="tz" />
          </objects></CoordinateSet></FreeJoint></Joint></Body>
      <Body name="femur"><mass>5</mass>
        <Joint><PinJoint name="hip"><parent_body>pelvis</parent_body>
          <location_in_parent>-0.07 -0.06 0.08</location_in_parent><orientation_in_parent>0.1 -0.2 0.3</orientation_in_parent>
          <location>0.01 0.02 0</location><orientation>0 0 0.2</orientation>
          <CoordinateSet><objects><Coordinate name="hip_flexion" /></objects></CoordinateSet></PinJoint></Joint></Body>
      <Body name="tibia"><mass>3</mass>
        <Joint><CustomJoint name="knee"><parent_body>femur</parent_body>
          <location_in_parent>0 0 0</location_in_parent><orientation_in_parent>0 0 0</orientation_in_parent>
          <location>0 0 0</location><orientation>0 0 0</orientation>
          <CoordinateSet><objects><Coordinate name="knee_angle" /></objects></CoordinateSet>
          <SpatialTransform>
            <TransformAxis name="rotation1"><coordinates>knee_angle</coordinates><axis>0 0 1</axis><function><LinearFunction><coefficients>1 0</coefficients></LinearFunction></function></TransformAxis>
            <TransformAxis name="rotation2"><coordinates></coordinates><axis>1 0 0</axis><function><Constant><value>0</value></Constant></function></TransformAxis>
            <TransformAxis name="rotation3"><coordinates></coordinates><axis>0 1 0</axis><function><Constant><value>0</value></Constant></function></TransformAxis>
            <TransformAxis name="translation1"><coordinates>knee_angle</coordinates><axis>1 0 0</axis><function><SimmSpline><x>-2 -1 0 1 2</x><y>-0.003 0.002 0.004 0.001 -0.002</y></SimmSpline></function></TransformAxis>
            <TransformAxis name="translation2"><coordinates>knee_angle</coordinates><axis>0 1 0</axis><function><NaturalCubicSpline><x>-2 -1 0 2</x><y>-0.42 -0.41 -0.40 -0.396</y></NaturalCubicSpline></function></TransformAxis>
            <TransformAxis name="translation3"><coordinates></coordinates><axis>0 0 1</axis><function><Constant><value>0.003</value></Constant></function></TransformAxis>
          </SpatialTransform></CustomJoint></Joint></Body>
    </objects></BodySet>
    <MarkerSet><objects>
      <Marker name="ASIS"><body>pelvis</body><location>0.02 0.03 0.12</location></Marker>
      <Marker name="THIGH"><body>femur</body><location>0.03 -0.2 0.05</location></Marker>
      <Marker name="SHANK"><body>tibia</body><location>0.02 -0.2 0.04</location></Marker>
    </objects></MarkerSet>
  </Model>
</OpenSimDocument>)";
  OsimImport a, b;
  Status s = ImportOsimText(v3, "small3.osim", &a);
  ASSERT_TRUE(s.ok()) << s.message();
  ASSERT_TRUE(ImportOsimText(kSmallModel, "small.osim", &b).ok());
  EXPECT_EQ(a.version, 30000);
  EXPECT_EQ(a.model.num_segments(), 3);
  std::mt19937 rng(8);
  for (int k = 0; k < 5; ++k) {
    Eigen::VectorXd z = RandomPose(a.model, rng);
    const Eigen::Matrix3Xd xa = Positions(a.model, z, a.model.InitialParameters());
    Eigen::VectorXd zb = b.model.DefaultCoordinates();
    for (int c = 0; c < a.model.num_coordinates(); ++c) zb[b.model.FindCoordinate(a.model.coordinates()[c].name)] = z[c];
    zb[b.model.FindCoordinate("knee_angle")] = z[a.model.FindCoordinate("knee_angle")];
    const Eigen::Matrix3Xd xb = Positions(b.model, zb, b.model.InitialParameters());
    for (const char* mk : {"ASIS", "THIGH"})
      EXPECT_LT((xa.col(a.model.FindMarker(mk)) - xb.col(b.model.FindMarker(mk))).norm(), 1e-14) << mk;
  }
  // Round trip of the 3.x document too.
  std::mt19937 rng2(9);
  EXPECT_LT(RoundTripError(a, mocap::testutil::Baked(a.model, RandomParameters(a.model, rng2)), rng2), 1e-9);
}

// GCVSpline (as SIMM's converter and older models write joint functions) and
// PiecewiseLinearFunction read as the functions OpenSim evaluates (model/coordinate_function.h),
// and a fitted model written back keeps them.
TEST(Osim, GcvSplineAndPiecewiseLinearJointFunctions) {
  std::string text = kSmallModel;
  const std::string simm =
      "<SimmSpline name=\"function\"><x>-2 -1 0 1 2</x><y>-0.003 0.002 0.004 0.001 -0.002</y></SimmSpline>";
  const std::string natural =
      "<NaturalCubicSpline name=\"function\"><x>-2 -1 0 2</x><y>-0.42 -0.41 -0.40 -0.396</y></NaturalCubicSpline>";
  ASSERT_NE(text.find(simm), std::string::npos);
  ASSERT_NE(text.find(natural), std::string::npos);
  text.replace(text.find(simm), simm.size(),
               "<GCVSpline name=\"function\"> <half_order> 3 </half_order>\n"
               "<x> -2 -1 -0.5 0 1 2 </x>\n<y> -0.003 0.002 0.003 0.004 0.001 -0.002 </y></GCVSpline>");
  text.replace(text.find(natural), natural.size(),
               "<PiecewiseLinearFunction name=\"function\"><x>-2 -1 0 2</x><y>-0.42 -0.41 -0.40 -0.396</y></PiecewiseLinearFunction>");
  OsimImport im;
  const Status s = ImportOsimText(text, "gcv.osim", &im);
  ASSERT_TRUE(s.ok()) << s.message();
  const int knee = im.model.FindJoint("knee");
  ASSERT_GE(knee, 0);
  const CoordinateFunction gcv = CoordinateFunction::GcvSpline(3, {-2, -1, -0.5, 0, 1, 2}, {-0.003, 0.002, 0.003, 0.004, 0.001, -0.002});
  const CoordinateFunction linear = CoordinateFunction::PiecewiseLinear({-2, -1, 0, 2}, {-0.42, -0.41, -0.40, -0.396});
  int found = 0;
  for (const JointElement& el : im.model.joints()[knee].elements) {
    if (el.function.kind == CoordinateFunction::Kind::kGcvSpline) {
      EXPECT_EQ(el.function, gcv);
      for (double z = -2.5; z <= 2.5; z += 0.25) EXPECT_DOUBLE_EQ(el.function.Value(z), gcv.Value(z)) << z;
      ++found;
    }
    if (el.function.kind == CoordinateFunction::Kind::kPiecewiseLinear) {
      EXPECT_EQ(el.function, linear);
      EXPECT_NEAR(el.function.Value(-0.5), -0.405, 1e-15);
      ++found;
    }
  }
  EXPECT_EQ(found, 2);
  std::mt19937 rng(12);
  EXPECT_LT(RoundTripError(im, mocap::testutil::Baked(im.model, RandomParameters(im.model, rng)), rng), 1e-9);
}

TEST(Osim, BadInputIsAClearErrorWithElementAndLine) {
  const std::string good = kSmallModel;
  OsimImport im;
  Status s = ImportOsimText("this is not XML <", "junk.osim", &im);
  EXPECT_FALSE(s.ok());
  EXPECT_THAT(s.message(), HasSubstr("junk.osim:1: not a valid XML document"));
  s = ImportOsimText("<a><b></a>", "bad.osim", &im);
  EXPECT_FALSE(s.ok());
  EXPECT_THAT(s.message(), HasSubstr("bad.osim:"));
  s = ImportOsimText("<Model/>", "nodoc.osim", &im);
  EXPECT_THAT(s.message(), HasSubstr("expected an <OpenSimDocument>"));
  // Found by the fuzzer: tinyxml2 takes text and elements beside the root, which export wrote
  // back in a form that did not read back.
  const std::string tail = good + "\nstray words\n</objects>\n";
  s = ImportOsimText(tail, "tail.osim", &im);
  EXPECT_THAT(s.message(), HasSubstr("tail.osim:" + std::to_string(LineOf(tail, "stray words")) +
                                     ": not a valid XML document: text outside the root element"));
  s = ImportOsimText(good + "<More/>", "two.osim", &im);
  EXPECT_THAT(s.message(), HasSubstr("not a valid XML document: a second root element <More>"));
  struct Case { std::string from, to, line_of, expect; };
  const std::vector<Case> cases = {
      {"<PinJoint name=\"hip\">", "<EllipsoidJoint name=\"hip\">", "<PinJoint name=\"hip\">",
       "EllipsoidJoint 'hip': unsupported joint type 'EllipsoidJoint'"},
      {"</PinJoint>", "</EllipsoidJoint>", "", ""},  // (paired with the case above)
      {"<SimmSpline name=\"function\"><x>-2 -1 0 1 2</x><y>-0.003 0.002 0.004 0.001 -0.002</y></SimmSpline>",
       "<StepFunction name=\"function\"><start_time>0</start_time><end_time>1</end_time></StepFunction>",
       "<SimmSpline name=\"function\"><x>-2", "StepFunction 'function': unsupported function type 'StepFunction'"},
      {"<SimmSpline name=\"function\"><x>-2 -1 0 1 2</x><y>-0.003 0.002 0.004 0.001 -0.002</y></SimmSpline>",
       "<GCVSpline name=\"function\"><x>-2 -1 0 1 2 3</x><y>-0.003 0.002 0.004 0.001 -0.002 0</y></GCVSpline>",
       "<SimmSpline name=\"function\"><x>-2", "GCVSpline 'function': missing <half_order>"},
      {"<SimmSpline name=\"function\"><x>-2 -1 0 1 2</x><y>-0.003 0.002 0.004 0.001 -0.002</y></SimmSpline>",
       "<GCVSpline name=\"function\"><half_order>3</half_order><error_variance>0.001</error_variance><x>-2 -1 0 1 2 3</x><y>-0.003 0.002 0.004 0.001 -0.002 0</y></GCVSpline>",
       "<SimmSpline name=\"function\"><x>-2", "only interpolating GCV splines (error variance 0) are supported"},
      {"<SimmSpline name=\"function\"><x>-2 -1 0 1 2</x><y>-0.003 0.002 0.004 0.001 -0.002</y></SimmSpline>",
       "<GCVSpline name=\"function\"><half_order>3</half_order><x>-2 -1 0 1 2</x><y>-0.003 0.002 0.004 0.001 -0.002</y></GCVSpline>",
       "<SimmSpline name=\"function\"><x>-2", "GCV spline of half order 3 needs at least 6 points, has 5"},
      {"<independent_coordinate_names>knee_angle</independent_coordinate_names>",
       "<independent_coordinate_names>knee_angel</independent_coordinate_names>",
       "<CoordinateCouplerConstraint name=\"knee_coupler\">",
       "CoordinateCouplerConstraint 'knee_coupler': unknown independent coordinate 'knee_angel'"},
      {"<independent_coordinate_names>knee_angle</independent_coordinate_names>",
       "<independent_coordinate_names>knee_angle hip_flexion</independent_coordinate_names>",
       "<CoordinateCouplerConstraint name=\"knee_coupler\">",
       "couplers with 2 independent coordinates are unsupported"},
      {"<socket_child_frame>/bodyset/tibia</socket_child_frame>", "<socket_child_frame>/bodyset/fibula</socket_child_frame>",
       "<socket_child_frame>/bodyset/tibia</socket_child_frame>", "socket_child_frame: no body, ground or frame of this joint named '/bodyset/fibula'"},
      {"<socket_parent>/bodyset/femur</socket_parent>", "<socket_parent>/bodyset/thigh</socket_parent>",
       "<socket_parent>/bodyset/femur</socket_parent>", "no body, ground or frame of this joint named '/bodyset/thigh'"},
      {"<x>-2 -1 0 1 2</x>", "<x>-2 -1 0 0 2</x>", "<SimmSpline name=\"function\"><x>-2", "spline x values must increase"},
      {"<translation>-0.07 -0.06 0.08</translation>", "<translation>-0.07 oops 0.08</translation>",
       "<translation>-0.07 -0.06 0.08</translation>", "translation: expected numbers, got 'oops'"},
      // Found by the fuzzer: a '/' in a joint's name made an offset frame's path that export wrote
      // and import could not find again.
      {"<PinJoint name=\"hip\">", "<PinJoint name=\"h/ip\">", "<PinJoint name=\"hip\">",
       "PinJoint 'h/ip': the name contains '/', OpenSim's path separator"},
  };
  for (size_t i = 0; i < cases.size(); ++i) {
    const Case& c = cases[i];
    if (c.expect.empty()) continue;
    std::string text = good;
    const int line = LineOf(text, c.line_of);
    text.replace(text.find(c.from), c.from.size(), c.to);
    if (i == 0) text.replace(text.find(cases[1].from), cases[1].from.size(), cases[1].to);
    s = ImportOsimText(text, "broken.osim", &im);
    EXPECT_FALSE(s.ok()) << c.expect;
    EXPECT_THAT(s.message(), HasSubstr("broken.osim:" + std::to_string(line) + ": ")) << c.expect;
    EXPECT_THAT(s.message(), HasSubstr(c.expect));
  }
  // A body that no joint holds.
  std::string text = good;
  const std::string extra = "<Body name=\"orphan\"><mass>1</mass></Body>\n";
  text.insert(text.find("      </objects>\n    </BodySet>"), "        " + extra);
  s = ImportOsimText(text, "orphan.osim", &im);
  EXPECT_FALSE(s.ok());
  EXPECT_THAT(s.message(), HasSubstr("orphan.osim:" + std::to_string(LineOf(text, extra)) + ": Body 'orphan': body is not the child of any joint"));
  s = ImportOsim("/nonexistent/model.osim", &im);
  EXPECT_FALSE(s.ok());
  EXPECT_THAT(s.message(), HasSubstr("/nonexistent/model.osim"));
}

// A marker on a joint's PhysicalOffsetFrame is on that frame's body, where the offset puts it (the
// same world place as the offset's own origin plus the location turned by its orientation); a
// marker fixed to the ground, or on a frame that is nothing of the model, is left out with the
// reason in `ignored`: one such marker must not refuse a generic model's others.
TEST(Osim, MarkersOnOffsetFramesResolveAndUnusableOnesAreLeftOut) {
  std::string text = kSmallModel;
  const std::string anchor = "<Marker name=\"ANKLE\">";
  const std::string extra =
      "<Marker name=\"ON_OFFSET\"><socket_parent_frame>/jointset/hip/femur_offset</socket_parent_frame>"
      "<location>0.1 0 0</location></Marker>\n"
      "<Marker name=\"ON_ORIGIN\"><socket_parent_frame>/bodyset/femur</socket_parent_frame>"
      "<location>0.01 0.02 0</location></Marker>\n"
      "<Marker name=\"ON_GROUND\"><socket_parent_frame>/ground</socket_parent_frame><location>1 0 0</location></Marker>\n"
      "<Marker name=\"ON_NOTHING\"><socket_parent_frame>/bodyset/fibula</socket_parent_frame><location>0 0 0</location></Marker>\n";
  text.insert(text.find(anchor), extra);
  OsimImport im;
  const Status s = ImportOsimText(text, "extra.osim", &im);
  ASSERT_TRUE(s.ok()) << s.message();
  const Model& m = im.model;
  EXPECT_EQ(m.FindMarker("ON_GROUND"), -1);
  EXPECT_EQ(m.FindMarker("ON_NOTHING"), -1);
  const int on_offset = m.FindMarker("ON_OFFSET"), origin = m.FindMarker("ON_ORIGIN");
  ASSERT_GE(on_offset, 0);
  ASSERT_GE(origin, 0);
  EXPECT_EQ(m.markers()[on_offset].segment, m.markers()[origin].segment);
  // femur_offset: translation (0.01, 0.02, 0), orientation 0.2 rad about z: the location (0.1, 0, 0)
  // lies at (0.01 + 0.1 cos 0.2, 0.02 + 0.1 sin 0.2, 0) in the femur, 0.1 m from the offset's origin.
  Eigen::VectorXd z = m.DefaultCoordinates();
  const Eigen::Matrix3Xd x = testutil::Positions(m, z, m.InitialParameters());
  const Eigen::Vector3d from_origin = x.col(on_offset) - x.col(origin);
  EXPECT_NEAR(from_origin.norm(), 0.1, 1e-12);
  // In the femur's frame that vector is (0.1 cos 0.2, 0.1 sin 0.2, 0): compare against a marker
  // placed there directly on the femur.
  std::ostringstream location;
  location.precision(17);
  location << 0.01 + 0.1 * std::cos(0.2) << " " << 0.02 + 0.1 * std::sin(0.2) << " 0";
  std::string direct = kSmallModel;
  direct.insert(direct.find(anchor), "<Marker name=\"DIRECT\"><socket_parent_frame>/bodyset/femur</socket_parent_frame>"
                                     "<location>" + location.str() + "</location></Marker>\n");
  OsimImport d;
  ASSERT_TRUE(ImportOsimText(direct, "direct.osim", &d).ok());
  const Eigen::Matrix3Xd xd = testutil::Positions(d.model, d.model.DefaultCoordinates(), d.model.InitialParameters());
  EXPECT_LT((x.col(on_offset) - xd.col(d.model.FindMarker("DIRECT"))).norm(), 1e-12);
  std::string ignored;
  for (const std::string& i : im.ignored) ignored += i + "\n";
  EXPECT_THAT(ignored, HasSubstr("Marker 'ON_GROUND' (line " + std::to_string(LineOf(text, "ON_GROUND")) +
                                 "): fixed to the ground: nothing to fit, left out"));
  EXPECT_THAT(ignored, HasSubstr("Marker 'ON_NOTHING'"));
  EXPECT_THAT(ignored, HasSubstr("'/bodyset/fibula', which is no body and no offset frame of a joint"));
}

namespace {
std::string TestData(const std::string& f) { return std::string(MOCAP_SOURCE_DIR) + "/tests/data/" + f; }

// OpenCap's LaiUhlrich2022 (its skeleton, tests/data) with the augmenter's marker set, as OpenCap
// puts them together before scaling.
OsimImport LaiUhlrich2022() {
  OsimImport im = MustImport(TestData("laiuhlrich2022_skeleton.osim"));
  const Status s = LoadOsimMarkerSet(TestData("laiuhlrich2022_markers_augmenter.xml"), &im);
  EXPECT_TRUE(s.ok()) << s.message();
  return im;
}

// OpenSim's PolynomialFunction: coefficients from the highest order down.
double Polynomial(const std::vector<double>& c, double x) {
  double v = 0;
  for (double k : c) v = v * x + k;
  return v;
}
}  // namespace

// OpenCap's generic model, never seen before this session: every joint built as OpenSim defines
// it. The markers of the right leg are computed here by hand from the file's own transforms --
// X_G,B = X_G,P X_P,F X_F,M(q) X_B,M^-1 with body-fixed X-Y-Z offset orientations, a CustomJoint's
// rotations about successive body-fixed axes and translations along F's axes, the walker knee's
// PolynomialFunctions -- at a straight and a 90 deg knee, and must match our kinematics.
TEST(Osim, LaiUhlrich2022IsBuiltAsOpenSimDefinesIt) {
  const OsimImport im = LaiUhlrich2022();
  const Model& m = im.model;
  EXPECT_EQ(m.num_segments(), 22);
  EXPECT_EQ(m.num_joints(), 22);
  EXPECT_EQ(m.num_markers(), 43);
  EXPECT_EQ(m.num_coordinates(), 33);  // 35 in the file; the patellae's follow the knees
  for (const char* side : {"r", "l"}) {
    const std::string beta = std::string("knee_angle_") + side + "_beta";
    EXPECT_LT(m.FindCoordinate(beta), 0);
    bool derived = false;
    for (const auto& dc : m.derived_coordinates())
      derived |= dc.name == beta && dc.source == m.FindCoordinate(std::string("knee_angle_") + side);
    EXPECT_TRUE(derived) << beta;
  }
  EXPECT_EQ(m.joints()[m.FindJoint("hip_r")].type, JointType::kSpherical);
  EXPECT_EQ(m.joints()[m.FindJoint("ankle_r")].type, JointType::kHinge);
  EXPECT_EQ(m.joints()[m.FindJoint("radius_hand_r")].elements.size(), 0u);  // a WeldJoint

  auto rot = [](double a, double b, double c) {
    return Eigen::Matrix3d((Eigen::AngleAxisd(a, Eigen::Vector3d::UnitX()) *
                            Eigen::AngleAxisd(b, Eigen::Vector3d::UnitY()) *
                            Eigen::AngleAxisd(c, Eigen::Vector3d::UnitZ())).toRotationMatrix());
  };
  auto about = [](double a, const Eigen::Vector3d& axis) {
    return Eigen::Matrix3d(Eigen::AngleAxisd(a, axis).toRotationMatrix());
  };
  const Eigen::Vector3d x = Eigen::Vector3d::UnitX(), y = Eigen::Vector3d::UnitY(), z = Eigen::Vector3d::UnitZ();
  for (const double knee : {0.0, 1.5708}) {  // knots of the patella's splines: 0 and 90 deg
    SCOPED_TRACE("knee_angle_r " + std::to_string(knee));
    Eigen::VectorXd q = m.DefaultCoordinates();
    const std::map<std::string, double> set = {
        {"pelvis_tilt", 0.1}, {"pelvis_list", -0.05}, {"pelvis_rotation", 0.2}, {"pelvis_tx", 0.1},
        {"pelvis_ty", 0.9},   {"pelvis_tz", -0.05},   {"hip_flexion_r", 0.5},   {"hip_adduction_r", -0.1},
        {"hip_rotation_r", 0.15}, {"knee_angle_r", knee}, {"ankle_angle_r", 0.2}, {"subtalar_angle_r", -0.1}};
    for (const auto& [name, v] : set) {
      ASSERT_GE(m.FindCoordinate(name), 0) << name;
      q[m.FindCoordinate(name)] = v;
    }
    const Eigen::Matrix3Xd at = Positions(m, q, m.InitialParameters());
    // ground_pelvis: rotation1 pelvis_tilt about z, rotation2 list about x, rotation3 rotation
    // about y, translations along ground's axes; both offset frames are the identity.
    const Eigen::Matrix3d rp = about(0.1, z) * about(-0.05, x) * about(0.2, y);
    const Eigen::Vector3d pp(0.1, 0.9, -0.05);
    // hip_r: parent frame at (-0.056276, -0.07849, 0.07726) on the pelvis, child frame the femur's origin.
    const Eigen::Matrix3d rf = rp * about(0.5, z) * about(-0.1, x) * about(0.15, y);
    const Eigen::Vector3d pf = pp + rp * Eigen::Vector3d(-0.056276, -0.078490000000000004, 0.077259999999999995);
    // walker_knee_r: both offset frames oriented (-1.64157, 1.44618, 1.5708); rotation1 q about x,
    // rotation2 about z and rotation3 about y by polynomials of q, translations by polynomials.
    const Eigen::Matrix3d ro = rot(-1.64157, 1.44618, 1.5708);
    const Eigen::Matrix3d rF = rf * ro;
    const Eigen::Vector3d pF = pf + rf * Eigen::Vector3d(-0.0044999999999999997, -0.40960000000000002, -0.00175);
    const double r2 = Polynomial({0.010832094539863, -0.025218325501241, -0.032847810398852, 0.079100011967027,
                                  -1.473252350900463e-08}, knee);
    const double r3 = Polynomial({0.025165762727423, -0.169480051390540, 0.369499348688249, -4.430358308836305e-08}, knee);
    const Eigen::Vector3d t(
        Polynomial({1.590447878850381e-04, -0.001015149915669, 0.001817510974968, 2.641426645199230e-05,
                    -7.746563532471892e-07}, knee),
        Polynomial({-5.796878052338684e-04, 0.005079765745626, -0.011442375726364, 0.003936908668844,
                    -2.516350383213525e-05}, knee),
        Polynomial({0.001208086889206, -0.004453611224706, 6.116494072981739e-04, 0.006265429606387,
                    -1.461912533723326e-05}, knee));
    const Eigen::Matrix3d rM = rF * about(knee, x) * about(r2, z) * about(r3, y);
    const Eigen::Vector3d pM = pF + rF * t;
    // The tibia's body frame from its child offset frame M: X_G,B = X_G,M X_B,M^-1.
    const Eigen::Matrix3d rt = rM * ro.transpose();
    const Eigen::Vector3d pt = pM - rt * Eigen::Vector3d(-0.0080895399999999992, -0.0035347999999999998, -0.00148474);
    // ankle_r (PinJoint about z of its frames, oriented (0.175895, -0.105208, 0.0186622)).
    const Eigen::Matrix3d ra = rot(0.175895, -0.105208, 0.0186622);
    const Eigen::Matrix3d rtalus = rt * ra * about(0.2, z) * ra.transpose();
    const Eigen::Vector3d ptalus = pt + rt * Eigen::Vector3d(-0.01, -0.40000000000000002, 0);
    // subtalar_r: frames oriented (-1.76819, 0.906223, 1.8196), at (-0.04877, -0.04195, 0.00792) on the talus.
    const Eigen::Matrix3d rs = rot(-1.7681899999999999, 0.906223, 1.8196000000000001);
    const Eigen::Matrix3d rc = rtalus * rs * about(-0.1, z) * rs.transpose();
    const Eigen::Vector3d pc = ptalus + rtalus * Eigen::Vector3d(-0.048770000000000001, -0.041950000000000001, 0.00792);
    const std::vector<std::pair<const char*, Eigen::Vector3d>> expected = {
        {"r.ASIS_study", pp + rp * Eigen::Vector3d(0.028000000000000001, 0.01, 0.128)},
        {"RHJC_study", pf},
        {"r_knee_study", pf + rf * Eigen::Vector3d(0.0080000000000000002, -0.40400000000000003, 0.055)},
        {"r_thigh2_study", pf + rf * Eigen::Vector3d(0.055, -0.25, 0.085)},
        {"r_ankle_study", pt + rt * Eigen::Vector3d(-0.02, -0.38500000000000001, 0.052999999999999999)},
        {"r_sh1_study", pt + rt * Eigen::Vector3d(0.0, -0.115, 0.07)},
        {"r_toe_study", pc + rc * Eigen::Vector3d(0.18684400000000001, 0.0083665300000000005, 0.0052662100000000003)},
        {"r_calc_study", pc + rc * Eigen::Vector3d(-0.032161500000000003, 0.032569300000000002, -0.011169500000000001)}};
    for (const auto& [name, p] : expected) {
      ASSERT_GE(m.FindMarker(name), 0) << name;
      EXPECT_LT((at.col(m.FindMarker(name)) - p).norm(), 1e-12) << name;
    }
    // The patella (no marker) on its SimmSplines of knee_angle_r_beta = knee_angle_r (the
    // coupler's slope 1): at its knots a spline is the knot's value. rotation1
    // about z, translations along x, y and a constant 0.00275 along z of the frame at
    // (-0.00809, -0.40796, -0.00275) on the femur; the patella's own frame is its body's.
    const bool straight = knee == 0.0;
    const Eigen::Matrix3d rpat = rf * about(straight ? 0.00113686 : -1.26379, z);
    const Eigen::Vector3d ppat = pf + rf * (Eigen::Vector3d(-0.00809, -0.40795999999999999, -0.0027499999999999998) +
                                            Eigen::Vector3d(straight ? 0.0524 : -0.0088, straight ? -0.0108 : -0.0349,
                                                            0.0027499999999999998));
    const Geometry g(m);
    ModelData d(m);
    ForwardKinematics(m, g, q, &d);
    const int patella = m.FindSegment("patella_r");
    ASSERT_GE(patella, 0);
    EXPECT_LT((d.segment_position[patella] - ppat).norm(), 1e-12);
    EXPECT_LT((d.segment_rotation[patella] - rpat).norm(), 1e-12);
  }
  std::mt19937 rng(29);
  for (int trial = 0; trial < 3; ++trial)
    EXPECT_LT(ExpectJacobiansMatchCentralDifferences(m, RandomPose(m, rng), RandomParameters(m, rng)), 1e-6);
  const double same = RoundTripError(im, im.model, rng);
  EXPECT_LT(same, 1e-9);
  const double fitted = RoundTripError(im, mocap::testutil::Baked(im.model, RandomParameters(im.model, rng)), rng);
  EXPECT_LT(fitted, 1e-9);
}
