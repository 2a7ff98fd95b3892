// The global fit on the simulated subject performing the default protocol: accuracy against the
// true model (shared/DESIGN.md targets), with noise, soft-tissue artefact and gaps.
#include <gtest/gtest.h>

#include "model/compare.h"
#include "sim/simulate.h"
#include "solver/global_fit.h"

using namespace mocap;

namespace {

struct Outcome {
  solver::FitResult fit;
  ModelComparison cmp;
};

Outcome FitSession(const sim::SimulationOptions& options, bool start_from_truth_poses = false) {
  sim::SimulatedSession session;
  Status s = sim::SimulateSession(options, &session);
  EXPECT_TRUE(s.ok()) << s.message();
  std::vector<solver::FitTrial> trials;
  for (const auto& t : session.trials) {
    solver::FitTrial ft;
    ft.markers = t.markers;
    if (start_from_truth_poses) {
      ft.initial_coordinates.resize(t.markers.num_frames(), session.nominal.num_coordinates());
      for (int f = 0; f < t.markers.num_frames(); ++f)
        ft.initial_coordinates.row(f) = sim::TrueCoordinates(session.nominal, t.coordinates, f).transpose();
    }
    trials.push_back(std::move(ft));
  }
  Outcome out;
  s = solver::FitModel(session.nominal, trials, solver::FitOptions(), &out.fit);
  EXPECT_TRUE(s.ok()) << s.message();
  EXPECT_TRUE(CompareModels(session.truth, out.fit.model, &out.cmp).ok());
  std::printf("%s\n", out.fit.report.BriefReport().c_str());
  for (const auto& jd : out.cmp.joints)
    std::printf("  %-12s centre %7.3f mm  axis %7.3f deg  (%s)\n", jd.joint.c_str(), jd.centre_error_mm,
                jd.axis_error_deg, jd.basis.c_str());
  return out;
}

}  // namespace

TEST(SimFit, DISABLED_FromTruePoses) {
  sim::SimulationOptions options;
  FitSession(options, true);
}
