// In-memory forms of the files mocapd reads and writes: labelled marker trajectories
// (TRC, later C3D) and tables of coordinates over time (MOT).
#pragma once
#include <Eigen/Core>
#include <string>
#include <vector>

namespace mocap::formats {

using RowMatrix = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;

// Marker trajectories of one trial. Positions are in METRES whatever the file's units;
// row f holds frame f as x0 y0 z0 x1 y1 z1 ...; a missing sample is NaN in all three.
struct MarkerTrial {
  std::string name;                      // trial name, normally the file stem
  double rate_hz = 0.0;                  // DataRate of the file
  std::vector<std::string> marker_names;
  std::vector<int> frame_numbers;        // as in the file
  std::vector<double> times;             // seconds, as in the file
  RowMatrix positions;                   // frames x (3 * markers)
  // Points the file held that are not markers and were not read (a C3D's model outputs, listed
  // in POINT:ANGLES, FORCES, MOMENTS, POWERS, SCALARS or REACTIONS: formats/c3d.h).
  std::vector<std::string> skipped_points;

  int num_frames() const { return static_cast<int>(positions.rows()); }
  int num_markers() const { return static_cast<int>(marker_names.size()); }
  // Index of a marker by exact name, or -1.
  int FindMarker(const std::string& marker_name) const;
  // True where frame f has a finite sample of marker m.
  bool Has(int f, int m) const;
  Eigen::Vector3d At(int f, int m) const { return positions.row(f).segment<3>(3 * m).transpose(); }
};

// Values of named columns over time (joint angles, coordinates). Rotational columns are
// kept in the unit of `in_degrees`.
struct CoordinateTable {
  std::string name;
  std::vector<std::string> column_names;  // not including "time"
  std::vector<double> times;
  RowMatrix values;                       // frames x columns
  bool in_degrees = true;

  int num_frames() const { return static_cast<int>(values.rows()); }
  int FindColumn(const std::string& column_name) const;
};

}  // namespace mocap::formats
