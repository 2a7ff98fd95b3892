#include "daemon/recording_export.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <numbers>

#include "formats/c3d.h"
#include "formats/mot.h"

namespace mocap::daemon {
namespace {

// Where each recorded frame goes, and the frame numbers and times of the rows (see the header).
struct RowLayout {
  std::vector<int> frame_numbers;  // per row, 1-based
  std::vector<double> times;       // per row
  std::vector<int> row_of_frame;   // per recorded frame
};

Status MakeRowLayout(const RecordingInfo& info, const std::vector<RecordedFrame>& frames,
                     bool fill_gaps, RowLayout* layout) {
  const std::string what = "recording " + std::to_string(info.id);
  if (!(info.rate_hz > 0)) {
    return Status::Error(what + ": rate " + std::to_string(info.rate_hz) + " Hz is not > 0");
  }
  const auto num_markers = static_cast<Eigen::Index>(info.marker_names.size());
  const auto num_coordinates = static_cast<Eigen::Index>(info.coordinate_names.size());
  layout->frame_numbers.clear();
  layout->times.clear();
  layout->row_of_frame.clear();
  constexpr std::uint64_t kMaxRows = std::numeric_limits<int>::max();
  for (std::size_t i = 0; i < frames.size(); ++i) {
    const RecordedFrame& f = frames[i];
    const std::string at = what + ": frame " + std::to_string(f.frame);
    if (f.markers.cols() != num_markers || f.coordinates.size() != num_coordinates) {
      return Status::Error(at + ": " + std::to_string(f.markers.cols()) + " markers and " +
                           std::to_string(f.coordinates.size()) +
                           " coordinates; the recording has " + std::to_string(num_markers) +
                           " and " + std::to_string(num_coordinates));
    }
    if (i > 0 && f.frame <= frames[i - 1].frame) {
      return Status::Error(at + " follows frame " + std::to_string(frames[i - 1].frame) +
                           ": frame numbers must increase");
    }
    const std::uint64_t offset = f.frame - frames.front().frame;
    if (offset >= kMaxRows) return Status::Error(at + ": too far from the first frame for a table");
    if (fill_gaps) {
      while (layout->frame_numbers.size() <= offset) {
        layout->frame_numbers.push_back(static_cast<int>(layout->frame_numbers.size()) + 1);
      }
      layout->row_of_frame.push_back(static_cast<int>(offset));
    } else {
      layout->row_of_frame.push_back(static_cast<int>(layout->frame_numbers.size()));
      layout->frame_numbers.push_back(static_cast<int>(offset) + 1);
    }
  }
  for (int n : layout->frame_numbers) layout->times.push_back((n - 1) / info.rate_hz);
  return Status::Ok();
}

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

// A table of the layout's rows x `columns`, NaN except recorded frame i's row, whose column k is
// value(frames[i], k).
template <typename Value>
formats::RowMatrix ScatterRows(const RowLayout& layout, const std::vector<RecordedFrame>& frames,
                               int columns, Value value) {
  formats::RowMatrix out = formats::RowMatrix::Constant(
      static_cast<Eigen::Index>(layout.frame_numbers.size()), columns, kNaN);
  for (std::size_t i = 0; i < frames.size(); ++i) {
    for (int k = 0; k < columns; ++k) out(layout.row_of_frame[i], k) = value(frames[i], k);
  }
  return out;
}

}  // namespace

Status RecordingToMarkerTrial(const RecordingInfo& info, const std::vector<RecordedFrame>& frames,
                              const RecordingTableOptions& options, formats::MarkerTrial* trial) {
  RowLayout layout;
  MOCAP_RETURN_IF_ERROR(MakeRowLayout(info, frames, options.fill_gaps, &layout));
  const int num_markers = static_cast<int>(info.marker_names.size());
  formats::MarkerTrial out;
  out.name = info.movement;
  out.rate_hz = info.rate_hz;
  out.marker_names = info.marker_names;
  // markers is 3 x M column-major: entry k of its data is coordinate k % 3 of marker k / 3, the
  // order of a MarkerTrial row.
  out.positions = ScatterRows(layout, frames, 3 * num_markers,
                              [](const RecordedFrame& f, int k) { return f.markers.data()[k]; });
  out.frame_numbers = std::move(layout.frame_numbers);
  out.times = std::move(layout.times);
  *trial = std::move(out);
  return Status::Ok();
}

Status RecordingToCoordinateTable(const RecordingInfo& info,
                                  const std::vector<RecordedFrame>& frames,
                                  const std::vector<bool>& rotational, bool in_degrees,
                                  const RecordingTableOptions& options,
                                  formats::CoordinateTable* table) {
  if (rotational.size() != info.coordinate_names.size()) {
    return Status::Error("recording " + std::to_string(info.id) + ": " +
                         std::to_string(rotational.size()) + " rotational flags for " +
                         std::to_string(info.coordinate_names.size()) + " coordinates");
  }
  RowLayout layout;
  MOCAP_RETURN_IF_ERROR(MakeRowLayout(info, frames, options.fill_gaps, &layout));
  const int num_coordinates = static_cast<int>(info.coordinate_names.size());
  formats::CoordinateTable out;
  out.name = info.movement;
  out.column_names = info.coordinate_names;
  out.in_degrees = in_degrees;
  out.values = ScatterRows(layout, frames, num_coordinates, [&](const RecordedFrame& f, int c) {
    return (in_degrees && rotational[c] ? 180.0 / std::numbers::pi : 1.0) * f.coordinates[c];
  });
  out.times = std::move(layout.times);
  *table = std::move(out);
  return Status::Ok();
}

Status RotationalCoordinates(const Model& model, const std::vector<std::string>& coordinate_names,
                             std::vector<bool>* rotational) {
  std::vector<bool> out;
  for (const auto& name : coordinate_names) {
    const int c = model.FindCoordinate(name);
    if (c < 0) {
      return Status::Error("model '" + model.name() + "' has no coordinate '" + name + "'");
    }
    out.push_back(model.coordinates()[c].rotational);
  }
  *rotational = std::move(out);
  return Status::Ok();
}

Status ExportRecordingC3d(const RecordingInfo& info, const std::vector<RecordedFrame>& frames,
                          const std::string& path) {
  formats::MarkerTrial trial;
  RecordingTableOptions options;
  options.fill_gaps = true;
  MOCAP_RETURN_IF_ERROR(RecordingToMarkerTrial(info, frames, options, &trial));
  std::size_t slots = 0;
  for (const auto& f : frames) slots = std::max(slots, f.points.size());
  const int num_markers = trial.num_markers();
  for (std::size_t k = 1; k <= slots; ++k) {
    char name[16];
    std::snprintf(name, sizeof(name), "P%03zu", k);
    trial.marker_names.push_back(name);
  }
  // Recorded frames sit at their fill_gaps rows: frame i at (sequence - first sequence).
  formats::RowMatrix all = formats::RowMatrix::Constant(
      trial.positions.rows(), 3 * static_cast<Eigen::Index>(trial.marker_names.size()), kNaN);
  all.leftCols(trial.positions.cols()) = trial.positions;
  for (const auto& f : frames) {
    const auto row = static_cast<Eigen::Index>(f.frame - frames.front().frame);
    for (std::size_t k = 0; k < f.points.size(); ++k) {
      all.row(row).segment<3>(3 * (num_markers + static_cast<Eigen::Index>(k))) =
          f.points[k].transpose();
    }
  }
  trial.positions = std::move(all);
  return formats::WriteC3d(path, trial);
}

Status ExportRecordingTrc(const RecordingInfo& info, const std::vector<RecordedFrame>& frames,
                          const std::string& path, const formats::TrcWriteOptions& options) {
  formats::MarkerTrial trial;
  MOCAP_RETURN_IF_ERROR(RecordingToMarkerTrial(info, frames, RecordingTableOptions(), &trial));
  return formats::WriteTrc(path, trial, options);
}

Status ExportRecordingMot(const RecordingInfo& info, const std::vector<RecordedFrame>& frames,
                          const std::vector<bool>& rotational, const std::string& path) {
  formats::CoordinateTable table;
  MOCAP_RETURN_IF_ERROR(RecordingToCoordinateTable(info, frames, rotational, /*in_degrees=*/true,
                                                   RecordingTableOptions(), &table));
  return formats::WriteMot(path, table);
}

}  // namespace mocap::daemon
