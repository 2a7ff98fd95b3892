// The global fit as an ArrowProblem: frames of measured markers, y_f = z_f, shared = the free
// geometric parameters. Exposed so the benchmark can hand the identical residuals, weights,
// priors and starting point to another solver (Ceres) for comparison.
//
// Gauge. Some changes of p leave every marker trajectory unchanged once the per-frame poses
// adjust: rotating a segment's frame against its markers and child joint centres (3 directions
// behind a spherical or free joint, the axis direction behind a hinge, both axes behind a
// universal joint), translating the root segment's frame, and trading a segment's scale against
// the size of its local geometry. These are conventions, not properties of the subject; a weak
// prior alone would leave them as long, curved, almost flat valleys in which Levenberg–Marquardt
// crawls. Each one that is exact for the free parameters gets a stiff linear row that keeps the
// segment's free local geometry from rotating / translating / growing as a whole relative to the
// initial model (the row is the gauge's own tangent, so it fixes exactly that direction and
// biases nothing observable). A gauge that free parameters cannot realise (e.g. a fixed marker
// on the segment) does not exist and gets no row.
#pragma once

#include <Eigen/Core>
#include <memory>
#include <vector>

#include "formats/marker_data.h"
#include "model/kinematics.h"
#include "model/model.h"
#include "solver/arrow_problem.h"

namespace mocap::solver {

struct FitOptions;

class MarkerFitProblem : public ArrowProblem {
 public:
  // measurements: frames x 3 n_markers in MODEL marker order, metres, NaN = missing.
  // options: which groups are fitted, sigmas of residuals, priors and gauge rows. Markers with
  // no sample stay fixed.
  // relax_holds: what the fit holds at the starting model without the data being unable to see
  // it -- FitOptions::held_parameters, and the rows that hold an observable direction (a
  // segment's orientation against a joint below it whose axes are no parameters, a coupled
  // knee's centre along its flexion axis: BuildGaugeRows) -- is free instead, against a prior of
  // FitOptions::held_centre_sigma_m / held_axis_sigma_rad (nothing changes where those are 0).
  // Not for solving: the fit's uncertainty counts the holds' own (FitStage).
  MarkerFitProblem(const Model& model, formats::RowMatrix measurements, const FitOptions& options,
                   bool relax_holds = false);

  int num_frames() const override { return static_cast<int>(measurements_.rows()); }
  int frame_dim() const override { return model_.num_coordinates(); }
  int shared_dim() const override { return static_cast<int>(free_parameters_.size()); }
  int num_residuals() const override {
    return 3 * samples_ + shared_dim() + static_cast<int>(gauge_rows_.rows()) +
           static_cast<int>(frame_prior_target_.size());
  }
  // Refuses (false) non-finite parameters and a scale <= 0: Levenberg–Marquardt then costs the
  // candidate step as infinite and rejects it, so scales stay positive through the whole fit
  // (a bound, not a change of variable: the minimum and the priors are those of p itself).
  bool SetShared(const Eigen::VectorXd& shared) override;
  std::unique_ptr<FrameEvaluator> NewEvaluator() const override;
  const Eigen::VectorXd& prior_weight() const override { return prior_weight_; }
  const Eigen::VectorXd& prior_target() const override { return prior_target_; }
  const Eigen::MatrixXd& shared_rows() const override { return gauge_rows_; }
  bool FramePrior(int frame, const double** weight, const double** target) const override;
  // Each periodic coordinate (solver/inverse_kinematics.h, PeriodicCoordinates: a rotation driven
  // by its own value, which the markers cannot tell from the same angle a whole turn on) moved by
  // whole turns to within half a turn of its frame prior's target.
  bool WrapFramePose(int frame, double* y) const override;
  // The frame prior's targets: the starting poses, x = [z_1 ... z_F, shared].
  void SetFramePriorTargets(const Eigen::VectorXd& x);
  // Per-frame weights (frames x coordinates) instead of the options' uniform ones, e.g. from
  // solver::UnobservedCoordinateWeights; an empty matrix restores the uniform ones.
  void SetFramePriorWeights(formats::RowMatrix weights) { frame_prior_weights_ = std::move(weights); }
  const Eigen::VectorXd& uniform_frame_prior_weight() const { return frame_prior_weight_; }
  const std::vector<std::string>& gauge_names() const { return gauge_names_; }
  // Whether relax_holds would change the problem (see the constructor).
  bool has_holds() const { return has_holds_; }
  void BlockStructure(std::vector<std::vector<int>>* y_columns,
                      std::vector<std::vector<int>>* p_columns) const override;

  const Model& model() const { return model_; }
  const Geometry& geometry() const { return geometry_; }
  const formats::RowMatrix& measurements() const { return measurements_; }
  // Model parameter index of each free shared parameter, and the reverse map (-1 = fixed).
  const std::vector<int>& free_parameters() const { return free_parameters_; }
  const std::vector<int>& free_index() const { return free_index_; }
  // Free index of each column of marker_parameters(m) (-1 = fixed).
  const std::vector<int>& marker_free_columns(int m) const { return marker_free_columns_[m]; }
  double residual_scale(int m) const { return residual_scale_[m]; }
  // Marker m's residual sigma (metres), the residual scale then being sqrt(weight_m) / sigma
  // (FitOptions::marker_sigma_rounds re-estimates it; the constructor sets marker_sigma_m).
  void SetMarkerSigma(int m, double sigma_m);
  double marker_sigma(int m) const { return marker_sigma_[m]; }
  // Per-sample weights (FitOptions::robust_loss, solver/robust_loss.h): frames x markers, each in
  // (0, 1], multiplying sample (f, m)'s squared residual; its residual block and Jacobians are
  // scaled by the square root. Empty (the constructor's): every weight 1.
  void SetSampleWeights(Eigen::MatrixXd weights) { sample_weight_ = std::move(weights); }
  double sample_weight(int frame, int m) const {
    return sample_weight_.size() == 0 ? 1.0 : sample_weight_(frame, m);
  }
  bool observed(int m) const { return observed_[m]; }
  // Index of marker m's residual block in BlockStructure (-1 if never observed).
  int block_kind(int m) const { return block_kind_[m]; }
  // The coordinates held to their range (Coordinate::clamped, FitOptions::coordinate_limit_sigma_*):
  // a frame whose coordinate c lies beyond [min, max] gets a one-row block (excess / sigma) on
  // y = {c}, of kind limit_kind(i), after the markers' kinds.
  struct CoordinateLimit {
    int coordinate;  // one of solver::LimitedCoordinates (inverse_kinematics.h)
    double weight;   // 1 / sigma
  };
  const std::vector<CoordinateLimit>& coordinate_limits() const { return limits_; }
  int limit_kind(int i) const { return first_limit_kind_ + i; }
  int num_samples() const { return samples_; }
  Eigen::VectorXd InitialShared() const;
  Eigen::VectorXd FullParameters(const Eigen::VectorXd& shared) const;
  double prior_sigma(int free) const { return 1.0 / prior_weight_[free]; }

  // Sum of squared marker distances (m^2) and sample count per marker at x = [z..., shared].
  // False (and nothing written) when the shared parameters are no body (SetShared refuses them).
  bool MarkerErrors(const Eigen::VectorXd& x, int num_threads, Eigen::VectorXd* sum_squared,
                    Eigen::VectorXi* count);
  // Each sample's squared marker distance (m^2) at x, frames x markers, NaN where missing.
  // False (and nothing written) like MarkerErrors.
  bool SampleErrors(const Eigen::VectorXd& x, int num_threads, Eigen::MatrixXd* squared);

 private:
  friend class MarkerFrameEvaluator;
  const Model& model_;
  formats::RowMatrix measurements_;
  Geometry geometry_;
  Eigen::VectorXd p0_;
  std::vector<int> free_parameters_, free_index_;
  std::vector<std::vector<int>> marker_free_columns_;
  std::vector<double> residual_scale_, marker_sigma_;
  Eigen::MatrixXd sample_weight_;
  std::vector<char> observed_;
  std::vector<int> block_kind_;
  std::vector<CoordinateLimit> limits_;
  int first_limit_kind_ = 0;
  Eigen::VectorXd prior_weight_, prior_target_;
  Eigen::MatrixXd gauge_rows_;
  Eigen::VectorXd frame_prior_weight_;
  formats::RowMatrix frame_prior_target_;
  formats::RowMatrix frame_prior_weights_;  // empty: frame_prior_weight_ for every frame
  std::vector<std::string> gauge_names_;
  std::vector<char> periodic_;
  // Rows that hold an observable direction get 1 / hold_sigma_m; `relaxable`: has_holds_ counts them.
  void BuildGaugeRows(double gauge_sigma_m, double hold_sigma_m, bool relaxable);
  bool has_holds_ = false;
  bool hold_hinge_centres_ = true;
  std::vector<char> held_centre_;  // per joint: centre in FitOptions::fixed_ or held_parameters
  int samples_ = 0;
};

}  // namespace mocap::solver
