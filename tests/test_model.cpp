// The body model: structure of the default model, analytic Jacobians against central finite
// differences, JSON round trip and validation errors, allocation-free evaluation.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <random>

#include "model/default_model.h"
#include "model/kinematics.h"
#include "model/model_io.h"

using namespace mocap;

namespace {

Eigen::VectorXd RandomPose(const Model& model, std::mt19937& rng) {
  std::uniform_real_distribution<double> u(-0.8, 0.8);
  Eigen::VectorXd z = model.DefaultCoordinates();
  for (int c = 0; c < model.num_coordinates(); ++c) z[c] += model.coordinates()[c].rotational ? u(rng) : 0.3 * u(rng);
  return z;
}

// Perturbs every parameter so that the Jacobian test does not run at a special point.
Eigen::VectorXd RandomParameters(const Model& model, std::mt19937& rng) {
  std::uniform_real_distribution<double> u(-1, 1);
  Eigen::VectorXd p = model.InitialParameters();
  for (int i = 0; i < model.num_parameters(); ++i) {
    switch (model.parameters()[i].group) {
      case ParameterGroup::kScale: p[i] *= 1 + 0.1 * u(rng); break;
      case ParameterGroup::kCentre: p[i] += 0.02 * u(rng); break;
      case ParameterGroup::kAxis: p[i] += 0.1 * u(rng); break;
      case ParameterGroup::kMarker: p[i] += 0.01 * u(rng); break;
    }
  }
  return p;
}

Eigen::Matrix3Xd Positions(const Model& model, const Eigen::VectorXd& z, const Eigen::VectorXd& p) {
  Geometry g(model);
  g.Set(model, p);
  ModelData d(model);
  ForwardKinematics(model, g, z, &d);
  Eigen::Matrix3Xd x;
  MarkerPositions(model, g, d, &x);
  return x;
}

}  // namespace

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
    Geometry g(model);
    g.Set(model, p);
    ModelData d(model);
    ForwardKinematics(model, g, z, &d);
    double worst = 0;
    for (int m = 0; m < model.num_markers(); ++m) {
      const auto& zc = model.marker_coordinates(m);
      const auto& pc = model.marker_parameters(m);
      Eigen::MatrixXd jz(3, zc.size()), jp(3, pc.size());
      MarkerJacobian(model, g, d, m, &jz, &jp);
      // Columns of coordinates and parameters that are NOT listed must have zero derivative.
      const double h = 1e-6;
      for (int c = 0; c < model.num_coordinates(); ++c) {
        Eigen::VectorXd zp = z, zm = z;
        zp[c] += h;
        zm[c] -= h;
        const Eigen::Vector3d fd = (Positions(model, zp, p).col(m) - Positions(model, zm, p).col(m)) / (2 * h);
        auto it = std::find(zc.begin(), zc.end(), c);
        const Eigen::Vector3d an = it == zc.end() ? Eigen::Vector3d::Zero() : Eigen::Vector3d(jz.col(it - zc.begin()));
        const double err = (fd - an).norm() / std::max(1.0, an.norm());
        worst = std::max(worst, err);
        EXPECT_LT(err, 1e-6) << model.markers()[m].name << " d/d " << model.coordinates()[c].name;
      }
      for (int i = 0; i < model.num_parameters(); ++i) {
        Eigen::VectorXd pp = p, pm = p;
        pp[i] += h;
        pm[i] -= h;
        const Eigen::Vector3d fd = (Positions(model, z, pp).col(m) - Positions(model, z, pm).col(m)) / (2 * h);
        auto it = std::find(pc.begin(), pc.end(), i);
        const Eigen::Vector3d an = it == pc.end() ? Eigen::Vector3d::Zero() : Eigen::Vector3d(jp.col(it - pc.begin()));
        const double err = (fd - an).norm() / std::max(1.0, an.norm());
        EXPECT_LT(err, 1e-6) << model.markers()[m].name << " d/d " << model.parameters()[i].name;
      }
    }
    EXPECT_LT(worst, 1e-6);
  }
}

TEST(Kinematics, WithParametersReproducesPositions) {
  Model model = DefaultFullBodyModel();
  std::mt19937 rng(3);
  const Eigen::VectorXd p = RandomParameters(model, rng);
  const Eigen::VectorXd z = RandomPose(model, rng);
  const Model baked = model.WithParameters(p);
  EXPECT_LT((Positions(model, z, p) - Positions(baked, z, baked.InitialParameters())).norm(), 1e-12);
  EXPECT_NEAR(baked.InitialParameters().segment(baked.axis_index(baked.FindJoint("knee_l"), 0), 2).norm(), 0.0, 0);
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
