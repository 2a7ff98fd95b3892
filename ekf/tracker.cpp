#include "ekf/tracker.h"

namespace mocap::ekf {

bool TrackerOptions::IsValid(std::string* error) const { return true; }

const char* ToString(TrackState state) {
  switch (state) {
    case TrackState::kInitialising: return "initialising";
    case TrackState::kTracking: return "tracking";
    case TrackState::kLost: return "lost";
  }
  return "?";
}

struct Tracker::Impl {
  std::shared_ptr<const Model> model;
  TrackerOptions options;
  TrackOutput out;
  Eigen::MatrixXd P;
};

Tracker::Tracker(std::shared_ptr<const Model> model, TrackerOptions options) : impl_(new Impl) {
  impl_->model = std::move(model);
  impl_->options = std::move(options);
  impl_->out.z = impl_->model->DefaultCoordinates();
}
Tracker::~Tracker() = default;
const TrackOutput& Tracker::Update(double, const Eigen::Ref<const Eigen::Matrix3Xd>& points) {
  impl_->out.marker_of_point.assign(points.cols(), -1);
  impl_->out.point_of_marker.assign(impl_->model->num_markers(), -1);
  return impl_->out;
}
Status Tracker::SwapModel(std::shared_ptr<const Model> model) { return Status::Error("not implemented"); }
TrackState Tracker::state() const { return impl_->out.state; }
void Tracker::Reset() {}
const Model& Tracker::model() const { return *impl_->model; }
const TrackerOptions& Tracker::options() const { return impl_->options; }
const TrackOutput& Tracker::output() const { return impl_->out; }
const Eigen::MatrixXd& Tracker::covariance() const { return impl_->P; }
Eigen::VectorXd Tracker::velocities() const { return {}; }
Eigen::VectorXd Tracker::accelerations() const { return {}; }

}  // namespace mocap::ekf
