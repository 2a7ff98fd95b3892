#include "ekf/assignment.h"

#include <algorithm>
#include <limits>
#include <utility>

namespace mocap::ekf {

void LinearAssignment::Reserve(int max_rows, int max_cols) {
  u_.reserve(max_rows);
  col4row_.reserve(max_rows);
  visited_row_.reserve(max_rows);
  for (auto* v : {&v_, &shortest_}) v->reserve(max_cols);
  for (auto* v : {&path_, &row4col_, &remaining_}) v->reserve(max_cols);
  visited_col_.reserve(max_cols);
}

double LinearAssignment::Solve(const Eigen::Ref<const Eigen::MatrixXd>& cost, int* row_to_col) {
  const int nr = static_cast<int>(cost.rows()), nc = static_cast<int>(cost.cols());
  constexpr double kInf = std::numeric_limits<double>::infinity();
  u_.assign(nr, 0.0);
  v_.assign(nc, 0.0);
  col4row_.assign(nr, -1);
  row4col_.assign(nc, -1);
  path_.assign(nc, -1);
  shortest_.resize(nc);
  remaining_.resize(nc);
  visited_row_.resize(nr);
  visited_col_.resize(nc);

  for (int current = 0; current < nr; ++current) {
    // Dijkstra over reduced costs from `current` to the nearest free column.
    double min_value = 0;
    int i = current, sink = -1, remaining = nc;
    for (int j = 0; j < nc; ++j) remaining_[j] = nc - 1 - j;
    std::fill(visited_row_.begin(), visited_row_.end(), 0);
    std::fill(visited_col_.begin(), visited_col_.end(), 0);
    std::fill(shortest_.begin(), shortest_.end(), kInf);
    while (sink < 0) {
      int index = -1;
      double lowest = kInf;
      visited_row_[i] = 1;
      for (int it = 0; it < remaining; ++it) {
        const int j = remaining_[it];
        const double r = min_value + cost(i, j) - u_[i] - v_[j];
        if (r < shortest_[j]) {
          path_[j] = i;
          shortest_[j] = r;
        }
        if (shortest_[j] < lowest || (shortest_[j] == lowest && row4col_[j] < 0)) {
          lowest = shortest_[j];
          index = it;
        }
      }
      min_value = lowest;
      if (index < 0) return kInf;  // only with non-finite costs (documented as not allowed)
      const int j = remaining_[index];
      if (row4col_[j] < 0)
        sink = j;
      else
        i = row4col_[j];
      visited_col_[j] = 1;
      remaining_[index] = remaining_[--remaining];
    }
    // Dual update, then augment along the path.
    u_[current] += min_value;
    for (int r = 0; r < nr; ++r)
      if (visited_row_[r] && r != current) u_[r] += min_value - shortest_[col4row_[r]];
    for (int c = 0; c < nc; ++c)
      if (visited_col_[c]) v_[c] -= min_value - shortest_[c];
    int j = sink;
    while (true) {
      const int r = path_[j];
      row4col_[j] = r;
      std::swap(col4row_[r], j);
      if (r == current) break;
    }
  }
  double total = 0;
  for (int r = 0; r < nr; ++r) {
    row_to_col[r] = col4row_[r];
    total += cost(r, col4row_[r]);
  }
  return total;
}

}  // namespace mocap::ekf
