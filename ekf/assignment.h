// Globally optimal linear assignment (rectangular, rows <= columns): each row gets a distinct
// column so that the sum of the chosen costs is least. The tracker's rows are the model's markers
// and its columns the frame's points plus one "missing" column per marker (priced at the gate),
// so a marker is left unlabelled exactly when every point it could take is better used by
// another marker or is too far, and two labels never share a point.
//
// Algorithm: shortest augmenting paths with dual variables (Jonker & Volgenant, "A shortest
// augmenting path algorithm for dense and sparse linear assignment problems", Computing 38:325,
// 1987), in the rectangular form of Crouse ("On implementing 2D rectangular assignment
// algorithms", IEEE TAES 52:1679, 2016): one Dijkstra-like search per row over reduced costs,
// O(rows^2 cols), exact, no iteration count to tune (unlike an auction with its epsilon). With
// 39 markers and ~80 columns it is a few microseconds. Not a library because Debian's candidates
// do not fit the per-frame path: dlib's max_cost_assignment takes integer costs on a square
// matrix and allocates per call, OR-Tools is not packaged; this one keeps its workspace between
// frames and allocates nothing after Reserve.
#pragma once

#include <Eigen/Core>
#include <vector>

namespace mocap::ekf {

class LinearAssignment {
 public:
  // Sizes the workspace; Solve allocates nothing for problems up to this size.
  void Reserve(int max_rows, int max_cols);

  // cost: rows x cols, rows <= cols, finite (use a large value, not infinity, for a forbidden
  // pair, and make sure each row has some affordable column). Writes each row's column to
  // row_to_col[0..rows) and returns the total cost.
  double Solve(const Eigen::Ref<const Eigen::MatrixXd>& cost, int* row_to_col);

 private:
  std::vector<double> u_, v_, shortest_;
  std::vector<int> path_, col4row_, row4col_, remaining_;
  std::vector<char> visited_row_, visited_col_;
};

}  // namespace mocap::ekf
