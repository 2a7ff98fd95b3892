#include "solver/robust_loss.h"

#include <cmath>

namespace mocap::solver {

const char* ToString(RobustLoss loss) {
  switch (loss) {
    case RobustLoss::kNone: return "none";
    case RobustLoss::kHuber: return "huber";
    case RobustLoss::kCauchy: return "cauchy";
  }
  return "unknown";
}

Status ParseRobustLoss(const std::string& text, RobustLoss* loss) {
  for (RobustLoss l : {RobustLoss::kNone, RobustLoss::kHuber, RobustLoss::kCauchy})
    if (text == ToString(l)) {
      *loss = l;
      return Status::Ok();
    }
  return Status::Error("unknown robust loss '" + text + "' (expected none, huber or cauchy)");
}

double RobustCost(RobustLoss loss, double s, double c) {
  const double c2 = c * c;
  switch (loss) {
    case RobustLoss::kNone: return s;
    case RobustLoss::kHuber: return s <= c2 ? s : 2.0 * c * std::sqrt(s) - c2;
    case RobustLoss::kCauchy: return c2 * std::log1p(s / c2);
  }
  return s;
}

double RobustWeight(RobustLoss loss, double s, double c) {
  const double c2 = c * c;
  switch (loss) {
    case RobustLoss::kNone: return 1.0;
    case RobustLoss::kHuber: return s <= c2 ? 1.0 : c / std::sqrt(s);
    case RobustLoss::kCauchy: return 1.0 / (1.0 + s / c2);
  }
  return 1.0;
}

}  // namespace mocap::solver
