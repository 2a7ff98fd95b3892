#include "sim/osim_subject.h"

#include <cmath>

#include "formats/mot.h"
#include "model/kinematics.h"
#include "sim/random.h"

namespace mocap::sim {

bool OsimSubjectOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& message) {
    if (error) *error = message;
    return false;
  };
  std::string why;
  if (!geometry.IsValid(&why)) return fail("geometry: " + why);
  if (!(std::isfinite(noise_mm) && noise_mm >= 0.0))
    return fail("noise_mm must be a finite number >= 0 (got " + std::to_string(noise_mm) + ")");
  if (!(missing >= 0.0 && missing < 0.9))
    return fail("missing must be a fraction in [0, 0.9) (got " + std::to_string(missing) + ")");
  return true;
}

Status HoldPose(const Model& model, const formats::CoordinateTable& table, int row, int frames,
                double rate_hz, formats::CoordinateTable* out) {
  const std::string what = "motion '" + table.name + "'";
  if (row < 0 || row >= table.num_frames())
    return Status::Error(what + ": no row " + std::to_string(row) + " (it has " +
                         std::to_string(table.num_frames()) + ")");
  if (frames < 1) return Status::Error(what + ": frames must be >= 1 (got " + std::to_string(frames) + ")");
  if (!(std::isfinite(rate_hz) && rate_hz > 0))
    return Status::Error(what + ": rate_hz must be > 0 (got " + std::to_string(rate_hz) + ")");
  formats::CoordinateTable held;
  held.name = table.name;
  held.in_degrees = table.in_degrees;
  held.values.resize(frames, model.num_coordinates());
  for (int c = 0; c < model.num_coordinates(); ++c) {
    const std::string& name = model.coordinates()[c].name;
    const int k = table.FindColumn(name);
    if (k < 0) return Status::Error(what + ": no column for coordinate '" + name + "' of model '" + model.name() + "'");
    held.column_names.push_back(name);
    held.values.col(c).setConstant(table.values(row, k));
  }
  held.times.resize(frames);
  for (int f = 0; f < frames; ++f) held.times[f] = f / rate_hz;
  *out = std::move(held);
  return Status::Ok();
}

Status SimulateOsimSubject(const Model& generic, const std::vector<PrescribedMotion>& motions,
                           const OsimSubjectOptions& options, OsimSubject* out) {
  std::string error;
  if (!options.IsValid(&error)) return Status::Error("osim subject options: " + error);
  if (generic.num_markers() == 0)
    return Status::Error("model '" + generic.name() + "' has no markers to simulate (load a marker set)");
  OsimSubject subject;
  subject.generic = generic;
  subject.truth_parameters = PerturbedParameters(generic, options.seed, options.geometry);
  MOCAP_RETURN_IF_ERROR(generic.WithParameters(subject.truth_parameters, &subject.truth));
  const Model& truth = subject.truth;
  const Geometry geometry(truth);
  ModelData data(truth);
  const int nc = truth.num_coordinates();
  std::vector<std::string> coordinate_names;
  for (const Coordinate& c : truth.coordinates()) coordinate_names.push_back(c.name);

  for (size_t i = 0; i < motions.size(); ++i) {
    const formats::CoordinateTable& table = motions[i].table;
    const std::string source = motions[i].source.empty() ? "motion '" + table.name + "'" : motions[i].source;
    const int nf = table.num_frames();
    if (nf == 0) return Status::Error(source + ": no rows");
    if (static_cast<int>(table.times.size()) != nf)
      return Status::Error(source + ": " + std::to_string(table.times.size()) + " times for " +
                           std::to_string(nf) + " rows");
    for (int f = 1; f < nf; ++f)
      if (!(table.times[f] > table.times[f - 1]))
        return Status::Error(source + ": time " + std::to_string(table.times[f]) + " (row " +
                             std::to_string(f + 1) + ") does not increase");
    Eigen::MatrixXd z;
    MOCAP_RETURN_IF_ERROR(formats::PosesFromTable(truth, table, source, &z));
    if (!z.allFinite()) return Status::Error(source + ": a coordinate is NaN or infinite");
    std::vector<char> recorded(truth.num_markers(), motions[i].markers.empty() ? 1 : 0);
    for (const std::string& name : motions[i].markers) {
      const int m = truth.FindMarker(name);
      if (m < 0) return Status::Error(source + ": recorded marker '" + name + "' is not in model '" + truth.name() + "'");
      recorded[m] = 1;
    }
    std::vector<int> markers;
    std::vector<std::string> marker_names;
    for (int m = 0; m < truth.num_markers(); ++m)
      if (recorded[m]) {
        markers.push_back(m);
        marker_names.push_back(truth.markers()[m].name);
      }
    const int nm = static_cast<int>(markers.size());

    formats::RowMatrix positions(nf, 3 * nm);
    for (int f = 0; f < nf; ++f) {
      ForwardKinematics(truth, geometry, z.row(f).transpose(), &data);
      for (int k = 0; k < nm; ++k)
        positions.row(f).segment<3>(3 * k) = MarkerPosition(truth, geometry, data, markers[k]).transpose();
    }
    // Each motion draws from its own streams, as `mocap sim`'s movements do.
    if (options.noise_mm > 0.0) {
      Random rng(options.seed, Stream::kNoise, i);
      AddMarkerNoise(options.noise_mm * 1e-3, rng, &positions);
    }
    if (options.missing > 0.0) {
      Random rng(options.seed, Stream::kMissing, i);
      RemoveMarkerSamples(options.missing, rng, &positions);
    }

    SimulatedTrial trial;
    trial.markers.name = table.name;
    trial.markers.rate_hz = nf > 1 ? (nf - 1) / (table.times.back() - table.times.front()) : 100.0;
    trial.markers.marker_names = marker_names;
    trial.markers.times = table.times;
    for (int f = 0; f < nf; ++f) trial.markers.frame_numbers.push_back(f + 1);
    trial.markers.positions = std::move(positions);
    trial.coordinates.name = table.name;
    trial.coordinates.column_names = coordinate_names;
    trial.coordinates.times = table.times;
    trial.coordinates.in_degrees = true;
    trial.coordinates.values = z;
    for (int c = 0; c < nc; ++c)
      if (truth.coordinates()[c].rotational) trial.coordinates.values.col(c) *= 180.0 / M_PI;
    subject.trials.push_back(std::move(trial));
  }
  *out = std::move(subject);
  return Status::Ok();
}

}  // namespace mocap::sim
