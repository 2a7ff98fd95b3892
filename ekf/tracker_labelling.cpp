// The tracker's labelling: which of this frame's unlabelled points is which model marker
// (ekf/tracker.h, "Labelling", has the design). What it decides, in order:
//   1. Labels follow point tracks (FollowLabelledTracks): a point that continues the point a marker
//      held in the last frame is that marker's or nobody's -- nobody's when an unlabelled marker
//      of another segment explains it better (LeaveHandedOffPointsEmpty: a marker hidden by
//      another that appears beside it hands its track over); a label the segment registration
//      moved to another point outside the gate keeps its point to its second frame.
//   2. Gating (LabelByGating): a marker can take a point inside its Mahalanobis gate, at its
//      rigid-body distance from its segment's joint centre (OnSegmentSphere), whose past does not
//      rule it out (NonRigidTrack, SeenBeside) and which a lasting reflection does not explain as
//      well (LastingClutterExplains); the optimal assignment decides contested points,
//      except a point that two markers of different segments, neither labelled, could each take
//      afresh: that is left empty (the assignment would decide it by the joint angle between
//      them, the very thing in doubt); and a point taken afresh that its segment's rigid geometry
//      fits better as an unlabelled mate (one wrist marker's point, the other's mirror image) is
//      left empty too (DropLabelsAMateFitsBetter).
//   2b. Rigid groups (LabelLooseSegments): where a segment's prediction is looser than the
//      spacing of its markers (a low frame rate against the motion: 12 Hz), its markers are
//      labelled as one rigid body about its joint centre, placed by its parent's fitted pose,
//      the prediction only a prior.
//   3. Segment registration (RegisterSegments): the markers the gates left unlabelled are looked
//      for as a group, where their segment's rigid geometry (its labelled markers, its joint
//      centre) puts them, and labelled when one choice of points fits clearly best; beside a
//      marker stuck for 20 frames, the labels of its segment are re-checked with it (a swap or
//      shift within the segment is one more hypothesis of the same fit).
//   4. The provisional window (ReviewProvisionalLabels): for kProvisionalFrames after a label is
//      taken afresh, its point is compared over the frames with the best unclaimed rival that
//      came after it, by the segment's rigid distances and by where the marker last was while
//      committed; a rival clearly better over several frames takes the label (a marker that took
//      a reflection while hidden, or that the limb search put on one, back beside it).
//   5. Probation (ChooseMeasurements): a returning marker's label enters the update from its
//      second consecutive frame.
//   6. The records the next frames judge points by (PushHistory): the last frames' points, and
//      which markers each unclaimed point has been seen beside.
// Why: the frame-by-frame assignment alone let a marker whose gate had grown take a neighbour's
// point and the filter settle in that wrong pose; each step removes one way for that to happen
// with evidence that does not depend on the pose being right (point continuity, rigid-body
// distances, a point's past). A marker the evidence does not place stays unlabelled.
#include <Eigen/SVD>
#include <algorithm>
#include <cmath>
#include <limits>

#include "ekf/tracker_impl.h"
#include "model/rigid_align.h"

namespace mocap::ekf {

using namespace internal;

// Mahalanobis gating with S_m = J_m P_zz J_m^T + R_m and the optimal assignment.
void Tracker::Impl::ComputeGates() {
  const double gate = options.gate_chi2;
  for (int m = 0; m < nm; ++m) {
    const std::vector<int>& cols = model->marker_coordinates(m);
    const int k = static_cast<int>(cols.size());
    const auto& J = jac[m];
    auto JP = jp.leftCols(k);
    // Summed in a register, not into JP: accumulating in memory made every term wait for the
    // previous one's store (this loop was most of the labelling's time).
    for (int bcol = 0; bcol < k; ++bcol) {
      const double* p_col = &P(0, cols[bcol]);
      Eigen::Vector3d sum = Eigen::Vector3d::Zero();
      for (int a = 0; a < k; ++a) sum += J.col(a) * p_col[cols[a]];
      JP.col(bcol) = sum;
    }
    Eigen::Matrix3d S = JP.lazyProduct(J.transpose());  // 3 x k x 3: no GEMM machinery
    prediction_trace[m] = S.trace();
    const double scale = labelled_run[m] == 0 ? HiddenScale(m) : 1.0;
    hidden_gated[m] = scale < 1.0;
    if (hidden_gated[m])
      s_inv_hidden[m] =
          (scale * S + (MeasurementVariance(m) + model_error[m]) * Eigen::Matrix3d::Identity()).inverse();
    S.diagonal().array() += MeasurementVariance(m) + (labelled_run[m] > 0 ? model_error[m] : 0.0);
    s_inv[m] = S.inverse();
    // d^2 >= |e|^2 / lambda_max(S) >= |e|^2 / trace(S): a cheap test before the quadratic form.
    reject_sq[m] = gate * S.trace();
  }
}

void Tracker::Impl::LabelByGating(int np) {
  const double gate = options.gate_chi2;
  ComputeGates();
  auto C = cost.topLeftCorner(nm, np + nm);
  std::fill(gated_by.begin(), gated_by.begin() + np, 0);
  std::fill(pred_cache.begin(), pred_cache.begin() + np, -2);
  bool contested = false;
  MatchDeferrals(np);
  FollowLabelledTracks(np);
  for (int m = 0; m < nm; ++m) {
    const Eigen::Vector3d p = predicted.col(m);
    double best = gate;
    int best_k = np + m;  // its own "missing" column
    // A label the registration's re-check moved last frame from one point to another outside the
    // gate (the pose was wrong: that is why the marker held the wrong point) keeps the point that
    // continues it to its second frame, when the probation passes it and the limb search places
    // its limb anew (Reacquire); the gate, still about the wrong pose, would give it back to the
    // wrong point (simulated seed 34 at 8 ghosts: the crossed wrist pair found and set right,
    // crossed again next frame). Not a label the registration gave an unlabelled marker: kept so,
    // a wrong one (a wrist marker on a reflection, seed 93 at 8 ghosts with the true model) moved
    // the limb onto it (72 -> 1,236 wrong labels); such a label is given again by the registration
    // if the next frame bears it out.
    const bool follow_registered = registered[m] && labelled_run[m] == 1;
    registered[m] = 0;
    if (!seen[m]) {
      C.row(m).head(np).setConstant(kForbidden);
      row_to_col[m] = best_k;
      continue;
    }
    for (int k = 0; k < np; ++k) {
      const Eigen::Vector3d e = points.col(k) - p;
      double d2 = kForbidden;
      if (follow_registered && track_owner[k] == m && OnSegmentSphere(m, points.col(k))) {
        d2 = 0;
        contested |= ++gated_by[k] > 1;
        best = -1;
        best_k = k;
      } else if (e.squaredNorm() < reject_sq[m] && (track_owner[k] < 0 || track_owner[k] == m) &&
                 !DeferralExcludes(m, k)) {
        const double q = e.dot(s_inv[m] * e);
        if (q < gate && (!hidden_gated[m] || e.dot(s_inv_hidden[m] * e) < gate) &&
            OnSegmentSphere(m, points.col(k)) &&
            (labelled_run[m] > 0 ||
             (!NonRigidTrack(m, points.col(k)) && !LastingClutterExplains(m, k, np))) &&
            !SeenBeside(m, k, np)) {
          d2 = q;
          contested |= ++gated_by[k] > 1;
          if (q < best) {
            best = q;
            best_k = k;
          }
        }
      }
      C(m, k) = d2;
    }
    row_to_col[m] = best_k;
  }
  LeaveHandedOffPointsEmpty(np);
  // When no point lies in two gates, each marker's nearest gated point is the optimum; only
  // contested frames (markers crossing, a ghost between two markers) need the assignment.
  if (contested) AssignContested(np);
  DropLabelsAMateFitsBetter(np);
}

// A point track is one marker's while its point is the same one; where a marker vanishes in the
// frame another appears beside it (a hand passing over a hip marker that the hand hides), the
// track continues onto the other marker's point, and the label with it (simulated seed 22, the
// swap traps: RASI hidden under the right hand, RWRB's point 9 mm from where RASI's would be,
// RASI on it for 12 frames while it moved off with the hand, in every scene of the sweep). The
// track says nothing there that the gates do not: a continuing point that an unlabelled marker of
// another segment explains better (a higher density under its prediction than under the
// holder's) is left empty, for the gates and the assignment to decide in the next frames.
void Tracker::Impl::LeaveHandedOffPointsEmpty(int np) {
  // The rivals first: most frames have few unlabelled markers, and the holders' densities are
  // needed only where one of them gates the point.
  int nrivals = 0;
  for (int b = 0; b < nm; ++b)
    if (labelled_run[b] == 0 && seen[b]) handoff_rivals[nrivals++] = b;
  if (nrivals == 0) return;
  const double gate = options.gate_chi2;
  auto C = cost.topLeftCorner(nm, np + nm);
  for (int a = 0; a < nm; ++a) {
    const int k = row_to_col[a];
    if (k < 0 || k >= np || track_owner[k] != a) continue;
    const Eigen::Vector3d p = points.col(k);
    const int segment = model->markers()[a].segment;
    double ga = -1;  // the holder's density, once needed
    for (int i = 0; i < nrivals; ++i) {
      const int b = handoff_rivals[i];
      if (b == a || model->markers()[b].segment == segment) continue;
      const Eigen::Vector3d e = p - predicted.col(b);
      if (e.squaredNorm() >= reject_sq[b] || e.dot(s_inv[b] * e) >= gate || !OnSegmentSphere(b, p)) continue;
      if (ga < 0) ga = PredictionDensity(a, p - predicted.col(a));
      if (PredictionDensity(b, e) <= ga) continue;
      C(a, k) = kForbidden;
      row_to_col[a] = np + a;
      break;
    }
  }
}

void Tracker::Impl::AssignContested(int np) {
  const double gate = options.gate_chi2;
  auto C = cost.topLeftCorner(nm, np + nm);
  for (int m = 0; m < nm; ++m) {
    C.row(m).tail(nm).setConstant(kForbidden);
    C(m, np + m) = gate;
  }
  lap.Solve(C, row_to_col.data());
  // A label the frame cannot decide is left empty. A marker taking a point afresh (not labelled
  // in the last frame) whose point also lies in the gate of a marker of ANOTHER segment that is
  // not labelled either has a rival the assignment out-scored only by where the pose puts the
  // two, that is by the joint angle between their segments: with the pose estimate wrong there
  // (a shank the start placed 8 cm off, a first-second gate as wide as the offset prior), the
  // cheaper pairing is a guess, and once given, labels follow point tracks and keep it (seed 6,
  // 8 ghosts: RHEE on RANK's point from frame 1 for the whole trial, RANK unlabelled). Left
  // empty, both wait for the frame that tells them apart, or for the segment registration and
  // the limb search, which fit the segment as a whole. Two markers of one segment are paired by
  // that segment's rigid geometry (the vector between them), which no joint angle changes: left
  // empty too, a forearm's two wrist markers waited for a fresh track's limb search, which placed
  // the forearm mirrored (true model, 8 ghosts, seed 23: 0.9996 -> 0.948).
  std::copy(row_to_col.begin(), row_to_col.begin() + nm, assigned.begin());
  for (int m = 0; m < nm; ++m) {
    const int k = assigned[m];
    if (k >= np || labelled_run[m] > 0) continue;
    for (int o = 0; o < nm; ++o)
      if (o != m && labelled_run[o] == 0 && assigned[o] >= np && C(o, k) < gate &&
          model->markers()[o].segment != model->markers()[m].segment) {
        row_to_col[m] = np + m;
        break;
      }
  }
}

// A label its segment's rigid geometry gives to a mate rather than to it is left empty. A marker
// taking a point afresh has only its prediction to say which of its segment's markers the point
// is, and the prediction of a marker back from an occlusion is where the segment's pose went
// while it was hidden, which the filter's covariance does not bound: a forearm held by its elbow
// centre and its forearm marker alone turns about the line between them unseen (seed 13, 8
// ghosts: the subject pronating, the wrist markers' predictions 7 cm off after 35 hidden frames,
// each 1-3 cm from the other's point and 50-60 Mahalanobis units from its own). The segment's
// rigid geometry does not drift: its joint centre, its labelled markers and the point, fitted as
// a rigid body (SegmentFitCost) with the point as this marker and as each unlabelled mate in
// turn. One wrist point with the elbow centre and the forearm marker is a triangle congruent with
// the other wrist marker's, a mirror image about the plane of the three, so the fits differ only
// by the model's asymmetries and the learnt offsets; where the mate's is better by
// kMateFitMargin the label is left empty, to wait for a frame whose points do tell (both wrist
// points: the mirror is not a rotation) or for the segment registration. Given, the label was
// followed as a point track for seconds and the finger marker took the freed wrist point (seeds
// 13 and 50: 0.972 and 0.980 of the labels). The verdict goes with the point: it is entered in
// the point's seen-beside record for the marker (PushHistory), which keeps the point out of the
// marker's gate while its track lasts (kBesideSeconds), through frames with too few anchors to
// give it again (the forearm marker hidden too: the centre and one point say only a distance,
// alike for both wrist markers, and the difference is the predicted centre's error -- judged on
// that alone, seed 27's wrist marker was kept from its own point, 0.97 of the labels).
// Where the marker's own fit is as good, or better, the prediction decides as before: leaving
// every such label empty (the first version, within init_ambiguity_margin) left wrist markers
// unlabelled for 20-60 frames 1-3 mm from their predictions while the other was hidden (seed 1,
// 5 ghosts: 0.99985 -> 0.99938). Not in a fresh track: its offsets are not yet learnt, and one
// learnt on a ghost makes the geometry itself wrong (seed 10: a wrist marker on a lasting ghost
// for its first 135 frames, its offset 43 mm; held back from its own point afterwards, 0.9979 ->
// 0.93 at 5 ghosts). Two markers of a segment taking points afresh together are judged as a
// pair, exchanged.
void Tracker::Impl::DropLabelsAMateFitsBetter(int np) {
  doubted_count = 0;
  if (FreshTrack()) return;
  for (int m = 0; m < nm; ++m) {
    const int k = row_to_col[m];
    if (k >= np || labelled_run[m] > 0) continue;
    const int segment = model->markers()[m].segment;
    const std::vector<int>& ms = segment_markers[segment];
    const int nms = static_cast<int>(ms.size());
    if (nms < 2 || nms > kMaxSegmentMarkers) continue;
    int labelling[kMaxSegmentMarkers];
    int im = -1;
    for (int i = 0; i < nms; ++i) {
      labelling[i] = row_to_col[ms[i]] < np ? row_to_col[ms[i]] : -1;
      if (ms[i] == m) im = i;
    }
    // With fewer than three anchors there is no fit: the prediction decides, and an earlier
    // verdict on the point's track (its seen-beside record, in the gating).
    int anchors = marker_depth[m] > 0 ? 1 : 0;
    for (int i = 0; i < nms; ++i) anchors += labelling[i] >= 0;
    if (anchors < 3) continue;
    double as_given = 0;
    const bool fits = SegmentFitCost(segment, labelling, &as_given);
    for (int io = 0; io < nms; ++io) {
      const int o = ms[io];
      if (io == im || labelled_run[o] > 0) continue;
      std::swap(labelling[im], labelling[io]);
      double exchanged = 0;
      const bool undecided =
          SegmentFitCost(segment, labelling, &exchanged) &&
          (!fits || exchanged < as_given - kMateFitMargin);
      std::swap(labelling[im], labelling[io]);
      if (!undecided) continue;
      if (doubted_count < nm) doubted[doubted_count++] = {k, m};
      row_to_col[m] = np + m;
      if (row_to_col[o] < np) row_to_col[o] = np + o;
      break;
    }
  }
}

// Labels follow point tracks. A point that continues the point a marker was labelled on in the
// last frame (mutual nearest neighbours between the two frames, after moving the last point as the
// marker's prediction moved, within a frame's motion kTrackStep) is that marker's or nobody's: no
// other marker's gate takes it. Markers are centimetres apart and a frame is 5 ms, so a point
// track does not jump from one marker to another; what the frame-by-frame assignment alone did
// was let a marker back from an occlusion, with a wide gate, take its neighbour's point (a wrist
// marker on the other wrist marker's point, the neighbour left unlabelled) and the filter then
// settle in the shifted pose for seconds.
void Tracker::Impl::FollowLabelledTracks(int np) {
  std::fill(track_owner.begin(), track_owner.begin() + np, -1);
  if (prev_np == 0) return;
  const double step2 = kTrackStep * kTrackStep;
  for (int a = 0; a < nm; ++a) {
    if (labelled_run[a] <= 0) continue;
    const Eigen::Vector3d shift = predicted.col(a) - last_predicted.col(a);
    const Eigen::Vector3d q = last_point.col(a) + shift;
    int nearest = -1;
    double best = step2;
    for (int k = 0; k < np; ++k) {
      const double d2 = (points.col(k) - q).squaredNorm();
      if (d2 < best) {
        best = d2;
        nearest = k;
      }
    }
    if (nearest < 0) continue;
    // Mutual: no other point of the last frame is nearer to it.
    const Eigen::Vector3d back = points.col(nearest) - shift;
    bool mutual = true;
    for (int j = 0; j < prev_np && mutual; ++j)
      mutual = (prev_points.col(j) - back).squaredNorm() >= best ||
               (prev_points.col(j) - last_point.col(a)).squaredNorm() < 1e-18;
    if (mutual) track_owner[nearest] = track_owner[nearest] < 0 ? a : nm;  // two claims: nobody's
  }
}

// Segment registration (ekf/tracker.h, "Labelling"): the markers the gates left unlabelled are
// looked for as a group, under their segment's rigid geometry, where the pose cannot mislead. A
// segment's markers and its joint centre (the origin of its frame, where its parent's pose puts
// it; the root has none) form a rigid body whatever the joint angles. Each unlabelled marker is
// given, in turn, each of the few unclaimed points at its distance from the joint centre
// (OnSegmentSphere) that its past does not rule out, or none; each such choice, with the
// segment's labelled markers on their points, is fitted as a rigid body (SegmentFitCost) and is
// possible when every anchor lies within its tolerance. The choice that labels the most markers at
// the least cost is taken when no different choice labelling as many comes within
// init_ambiguity_margin, and when no other segment's unlabelled marker could be one of its points.
// Pinned (three or more labelled mates: the fit places the marker, not only its distances) a
// point is judged as the gating judges one (NonRigidTrack, SeenBeside); unpinned, only a marker
// stuck for kStuckFrames is looked for, at points that moved rigidly with the segment
// (RigidWithSegment). Why: a marker leaves its gate when its segment's pose estimate is wrong or
// carries a nominal model's pose-dependent error, and its point then sits where its segment's
// rigid geometry puts it, and there only. For a segment with a stuck marker that has candidates,
// its labelled markers whose points the stuck marker could be are re-opened too, one or two at a
// time (EnumerateSegment): a labelled marker on a mate's point (a wrist marker on the other's,
// after a forearm turned about its axis while hidden) keeps every distance right and fits as
// well as the truth until the stuck marker's own point is tried with it. The same labelling
// reached with different markers re-opened is not its own rival. The labels go through probation
// (ChooseMeasurements); FilterUpdate does not measure a label outside its gate, whose limb the
// limb search places anew. Not in a fresh track (FreshTrack), whose joint centres may be wrong
// with a limb; the limb search relabels there.
void Tracker::Impl::RegisterSegments(int np) {
  for (int m = 0; m < nm; ++m)
    if (row_to_col[m] >= np) row_to_col[m] = -1;
  if (FreshTrack()) return;
  seg.fits = 0;
  bool claims_known = false;
  for (int segment : segment_order) {
    const std::vector<int>& ms = segment_markers[segment];
    const int nms = static_cast<int>(ms.size());
    if (nms > kMaxSegmentMarkers) continue;
    const bool has_centre = marker_depth[ms[0]] > 0;
    seg.nunl = 0;
    int labelled = 0;
    for (int m : ms) {
      if (row_to_col[m] >= 0)
        ++labelled;
      else if (seg.nunl < kSegmentMaxOpen)
        seg.unl[seg.nunl++] = m;
    }
    if (seg.nunl == 0 || (has_centre ? 1 : 0) + labelled + seg.nunl < 3) continue;
    if (!claims_known) {
      std::fill(ltaken.begin(), ltaken.begin() + np, 0);
      for (int a = 0; a < nm; ++a)
        if (row_to_col[a] >= 0) ltaken[row_to_col[a]] = 1;
      claims_known = true;
    }
    // Candidates: the unclaimed points on each unlabelled marker's sphere, nearest its prediction
    // first. With three or more of the segment's markers labelled the fit pins the marker's place
    // in this frame (not only its distances), and a point there is judged as the gating judges
    // one; with fewer, the point must also have moved rigidly with the segment (RigidWithSegment).
    const bool pinned = labelled >= kPinningMates;
    int with_candidates = 0, stuck_with_candidates = 0;
    for (int o = 0; o < seg.nunl; ++o) {
      const int m = seg.unl[o];
      double dist[kSegmentCandidates];
      int& n = seg.unl_n[o];
      n = 0;
      // Unpinned, only a marker missing from its point for kStuckFrames: one just back from an
      // occlusion is the gate's (a reflection riding with the segment can sit at its place).
      if (!pinned && unlabelled_run[m] < kStuckFrames) continue;
      for (int k = 0; k < np; ++k) {
        if (ltaken[k] || DeferralExcludes(m, k) || !OnSegmentSphere(m, points.col(k))) continue;
        const double d = (points.col(k) - predicted.col(m)).squaredNorm();
        if (n == kSegmentCandidates && d >= dist[n - 1]) continue;
        if ((pinned ? NonRigidTrack(m, points.col(k)) : !RigidWithSegment(m, k)) ||
            SeenBeside(m, k, np))
          continue;
        int i = n < kSegmentCandidates ? n++ : n - 1;
        for (; i > 0 && dist[i - 1] > d; --i) {
          dist[i] = dist[i - 1];
          seg.unl_cand[o][i] = seg.unl_cand[o][i - 1];
        }
        dist[i] = d;
        seg.unl_cand[o][i] = k;
      }
      with_candidates += n > 0;
      stuck_with_candidates += n > 0 && ReCheckDue(m);
    }
    if (with_candidates == 0 || (has_centre ? 1 : 0) + labelled + with_candidates < 3) continue;
    // Hypotheses: the segment's labels as they are, with points for its unlabelled markers; and,
    // for a marker stuck beside its candidate point, also with one or two labelled markers
    // re-opened (a swap or shift within the segment: a wrist marker on the other wrist marker's
    // point and that one's own point left over). The labelling with the most labels at the least
    // cost wins when no different one with as many comes within the margin.
    seg.best_labels = 0;
    seg.best_cost = seg.runner_up = std::numeric_limits<double>::infinity();
    seg.fit_limit = kSegmentFitBudget;
    bool complete = EnumerateSegment(segment, nullptr, 0);
    if (stuck_with_candidates > 0 && has_centre && complete) {
      // A re-check cut short by its budget leaves the registration's own decision standing.
      const int labels_alone = seg.best_labels;
      const double cost_alone = seg.best_cost, runner_up_alone = seg.runner_up;
      int point_alone[kMaxSegmentMarkers];
      std::copy(seg.best_point, seg.best_point + nms, point_alone);
      seg.fit_limit = std::min(kSegmentFitBudget, seg.fits + kReCheckFitBudget);
      // Re-opened: a labelled marker whose point a stuck marker could be (at that marker's
      // distance from the joint centre). The root has no centre to tell them by.
      auto could_be_stuck = [&](int i) {
        if (row_to_col[ms[i]] < 0) return false;
        for (int o = 0; o < seg.nunl; ++o)
          if (seg.unl_n[o] > 0 && ReCheckDue(seg.unl[o]) &&
              OnSegmentSphere(seg.unl[o], points.col(row_to_col[ms[i]])))
            return true;
        return false;
      };
      int freed[kSegmentMaxFreed];
      for (int i = 0; i < nms && complete; ++i) {
        if (!could_be_stuck(i)) continue;
        freed[0] = i;
        complete = EnumerateSegment(segment, freed, 1);
        for (int j = 0; j < nms && complete; ++j) {
          if (j == i || row_to_col[ms[j]] < 0 || (j < i && could_be_stuck(j))) continue;
          freed[0] = std::min(i, j);
          freed[1] = std::max(i, j);
          complete = EnumerateSegment(segment, freed, 2);
        }
      }
      if (!complete) {
        seg.best_labels = labels_alone;
        seg.best_cost = cost_alone;
        seg.runner_up = runner_up_alone;
        std::copy(point_alone, point_alone + nms, seg.best_point);
        complete = true;
      }
    }
    if (!complete || seg.best_labels == 0 ||
        seg.runner_up - seg.best_cost < options.init_ambiguity_margin)
      continue;
    bool changes = false;
    for (int i = 0; i < nms; ++i) changes |= seg.best_point[i] != row_to_col[ms[i]];
    if (!changes) continue;
    // A point another segment's unlabelled marker could also be (in its gate and on its own
    // segment's sphere) is not decided here: the heel marker's point fits the ankle
    // marker's place on the shank within a nominal model's error.
    bool contested = false;
    for (int i = 0; i < nms && !contested; ++i) {
      const int k = seg.best_point[i];
      if (k < 0 || k == row_to_col[ms[i]]) continue;
      for (int a = 0; a < nm && !contested; ++a) {
        if (row_to_col[a] >= 0 || !seen[a] || model->markers()[a].segment == segment) continue;
        const Eigen::Vector3d e = points.col(k) - predicted.col(a);
        contested = e.dot(s_inv[a] * e) < options.gate_chi2 && OnSegmentSphere(a, points.col(k));
      }
    }
    if (contested) continue;
    for (int i = 0; i < nms; ++i) {
      const int m = ms[i], k = seg.best_point[i];
      if (k == row_to_col[m]) continue;
      // A labelled marker moved to another point held the wrong one: what it was seen beside
      // was recorded under the wrong label, and its new label starts on probation.
      registered[m] = row_to_col[m] >= 0 && k >= 0;
      if (row_to_col[m] >= 0) {
        ForgetRecords(m);
        labelled_run[m] = 0;
      }
      row_to_col[m] = k;
      if (k >= 0) ltaken[k] = 1;
    }
  }
}

bool Tracker::Impl::EnumerateSegment(int segment, const int* freed, int nfreed) {
  const std::vector<int>& ms = segment_markers[segment];
  const int nms = static_cast<int>(ms.size());
  // The open markers in the segment's order: its unlabelled markers with their candidates, and
  // the freed labelled ones with their own points.
  seg.nopen = 0;
  int kept = 0, u = 0, f = 0;
  for (int i = 0; i < nms; ++i) {
    const int m = ms[i];
    if (u < seg.nunl && seg.unl[u] == m) {
      if (seg.nopen == kSegmentMaxOpen) return true;
      const int o = seg.nopen++;
      seg.open[o] = m;
      seg.ncand[o] = 0;
      for (int c = 0; c < seg.unl_n[u]; ++c) seg.cand[o][seg.ncand[o]++] = seg.unl_cand[u][c];
      ++u;
    } else if (f < nfreed && freed[f] == i) {
      if (seg.nopen == kSegmentMaxOpen) return true;
      const int o = seg.nopen++;
      seg.open[o] = m;
      seg.ncand[o] = 0;
      ++f;
    } else if (row_to_col[m] >= 0) {
      ++kept;
    }
  }
  // The freed markers' points are candidates of every open marker at their sphere (a freed
  // marker's own point always).
  for (int g = 0; g < nfreed; ++g) {
    const int k = row_to_col[ms[freed[g]]];
    for (int o = 0; o < seg.nopen; ++o)
      if (seg.ncand[o] < kSegmentMaxChoices &&
          (seg.open[o] == ms[freed[g]] || OnSegmentSphere(seg.open[o], points.col(k))))
        seg.cand[o][seg.ncand[o]++] = k;
  }
  // A freed marker may also take an unlabelled marker's candidate at its own sphere.
  for (int o = 0; o < seg.nopen; ++o) {
    if (row_to_col[seg.open[o]] < 0) continue;
    for (int v = 0; v < seg.nunl; ++v)
      for (int c = 0; c < seg.unl_n[v] && seg.ncand[o] < kSegmentMaxChoices; ++c) {
        const int k = seg.unl_cand[v][c];
        bool have = false;
        for (int i = 0; i < seg.ncand[o]; ++i) have |= seg.cand[o][i] == k;
        if (!have && OnSegmentSphere(seg.open[o], points.col(k))) seg.cand[o][seg.ncand[o]++] = k;
      }
  }
  // Every choice (odometer over candidates and none, distinct points).
  for (int o = 0; o < seg.nopen; ++o) seg.choice[o] = -1;
  int labelling[kMaxSegmentMarkers];
  for (;;) {
    int o = 0;
    for (; o < seg.nopen; ++o) {  // next choice
      int& c = seg.choice[o];
      c = c + 1 < seg.ncand[o] ? c + 1 : -1;
      if (c >= 0) break;
    }
    if (o == seg.nopen) return true;  // wrapped: all seen
    int labels = kept;
    bool distinct = true;
    for (int i = 0; i < seg.nopen && distinct; ++i) {
      if (seg.choice[i] < 0) continue;
      ++labels;
      for (int j = 0; j < i; ++j)
        distinct &= seg.choice[j] < 0 || seg.cand[j][seg.choice[j]] != seg.cand[i][seg.choice[i]];
    }
    if (!distinct || labels < seg.best_labels) continue;
    // The labelling of the whole segment; the same labelling reached with other markers freed
    // is not a rival of itself.
    for (int i = 0, op = 0; i < nms; ++i) {
      if (op < seg.nopen && seg.open[op] == ms[i]) {
        labelling[i] = seg.choice[op] >= 0 ? seg.cand[op][seg.choice[op]] : -1;
        ++op;
      } else {
        labelling[i] = row_to_col[ms[i]];
      }
    }
    const bool same = labels == seg.best_labels &&
                      std::equal(labelling, labelling + nms, seg.best_point);
    if (same) continue;
    if (++seg.fits > seg.fit_limit) return false;
    double cost = 0;
    if (!SegmentFitCost(segment, labelling, &cost)) continue;
    if (labels > seg.best_labels || cost < seg.best_cost) {
      // The previous best is the runner-up when it labels as many.
      seg.runner_up = labels == seg.best_labels ? std::min(seg.runner_up, seg.best_cost)
                                                : std::numeric_limits<double>::infinity();
      seg.best_labels = labels;
      seg.best_cost = cost;
      std::copy(labelling, labelling + nms, seg.best_point);
    } else {
      seg.runner_up = std::min(seg.runner_up, cost);
    }
  }
}

bool Tracker::Impl::RigidWithSegment(int m, int k) const {
  return SegmentPast(m, k) == PastWithSegment::kRigid;
}

Tracker::Impl::PastWithSegment Tracker::Impl::SegmentPast(int m, int k) const {
  const int segment = model->markers()[m].segment;
  const std::vector<int>& ms = segment_markers[segment];
  const bool has_centre = marker_depth[m] > 0;
  // Per anchor (the centre, then the segment's markers labelled now): the least and largest
  // distance of the followed point.
  constexpr int kMaxAnchors = 16;
  double lo[kMaxAnchors], hi[kMaxAnchors];
  const Eigen::Vector3d p = points.col(k);
  auto anchor_now = [&](int i) -> Eigen::Vector3d {
    return i == 0 ? centre_now[segment] : Eigen::Vector3d(points.col(row_to_col[ms[i - 1]]));
  };
  const int na = std::min<int>(kMaxAnchors, static_cast<int>(ms.size()) + 1);
  for (int i = 0; i < na; ++i) {
    if (i > 0 && row_to_col[ms[i - 1]] < 0) continue;
    lo[i] = hi[i] = (p - anchor_now(i)).norm();
  }
  Eigen::Vector3d q = p;
  int length = 1;
  double travel2 = 0;
  for (int h = 1; h <= hist_size; ++h) {
    const int slot = (hist_head - h + kHistory) % kHistory;
    const Eigen::Matrix3Xd& pts = hist_points[slot];
    // m's own past labels continue its track.
    const int nearest = PastPoint(slot, q, hist_marker_point[slot][m]);
    if (nearest < 0) break;
    q = pts.col(nearest);
    ++length;
    travel2 = std::max(travel2, (q - p).squaredNorm());
    for (int i = 0; i < na; ++i) {
      if (i > 0 && row_to_col[ms[i - 1]] < 0) continue;
      double r;
      if (i == 0) {
        r = (q - hist_centre[slot][segment]).norm();
      } else {
        const int then = hist_marker_point[slot][ms[i - 1]];
        if (then < 0) continue;
        r = (q - pts.col(then)).norm();
      }
      lo[i] = std::min(lo[i], r);
      hi[i] = std::max(hi[i], r);
    }
  }
  // Rigid while it stood still says nothing: a reflection fixed in the lab is rigid with a
  // segment at rest (the static pose).
  if (length < kMinTrackFrames) return PastWithSegment::kShort;
  for (int i = has_centre ? 0 : 1; i < na; ++i) {
    if (i > 0 && row_to_col[ms[i - 1]] < 0) continue;
    if (hi[i] - lo[i] > kRigidTolerance) return PastWithSegment::kNotRigid;
  }
  return travel2 < kRegistrationTravel * kRegistrationTravel ? PastWithSegment::kStill
                                                               : PastWithSegment::kRigid;
}

bool Tracker::Impl::SegmentFitCost(int segment, const int* labelling, double* cost) const {
  const std::vector<int>& ms = segment_markers[segment];
  // Anchors: local (segment frame, origin at the joint centre: where the predicted pose puts each
  // marker, its learnt offset included) and world positions, each with its variance and tolerance.
  constexpr int kMaxAnchors = 16;
  Eigen::Matrix<double, 3, kMaxAnchors> local, world;
  double var[kMaxAnchors], tol[kMaxAnchors];
  int n = 0;
  bool fresh[kMaxAnchors];  // the anchor is a label this labelling gives anew
  const Eigen::Matrix3d& R0 = data.segment_rotation[segment];
  if (marker_depth[ms[0]] > 0) {
    fresh[n] = false;
    local.col(n).setZero();
    world.col(n) = centre_now[segment];
    var[n] = 0.25 * kJointCentreTolerance * kJointCentreTolerance;
    tol[n++] = std::sqrt(options.gate_chi2) * options.sigma_m + kJointCentreTolerance;
  }
  auto add = [&](int m, int k) {
    if (n == kMaxAnchors) return;
    fresh[n] = k != row_to_col[m];
    local.col(n) = R0.transpose() * (predicted.col(m) - centre_now[segment]);
    world.col(n) = points.col(k);
    var[n] = MeasurementVariance(m) + model_error[m];
    tol[n] = std::sqrt(options.gate_chi2 * var[n]);
    ++n;
  };
  for (size_t i = 0; i < ms.size(); ++i)
    if (labelling[i] >= 0) add(ms[i], labelling[i]);
  if (n < 3) return false;
  // A rigid motion keeps distances, so whatever rotation the fit finds, residuals e_i, e_j obey
  // |e_i| + |e_j| >= | |l_i - l_j| - |w_i - w_j| |: a pair of anchors whose distance changed by
  // more than their two tolerances fails the per-anchor test below, and the SVD is not needed to
  // say so (the registration's enumeration tries mostly such choices: 94 % of its fits at 8
  // ghosts, where the SVD was most of a slow frame). The 1 nm keeps the shortcut to cases the
  // fit's rounding cannot decide otherwise, so the answer is the fit's own.
  for (int i = 1; i < n; ++i)
    for (int j = 0; j < i; ++j)
      if (std::abs((local.col(i) - local.col(j)).norm() - (world.col(i) - world.col(j)).norm()) >
          tol[i] + tol[j] + 1e-9)
        return false;
  const Eigen::Vector3d cl = local.leftCols(n).rowwise().mean();
  const Eigen::Vector3d cw = world.leftCols(n).rowwise().mean();
  Eigen::Matrix3d H = Eigen::Matrix3d::Zero();
  for (int i = 0; i < n; ++i) H += (local.col(i) - cl) * (world.col(i) - cw).transpose();
  const Eigen::Matrix3d R = KabschRotation(H);
  double c = 0;
  for (int i = 0; i < n; ++i) {
    const double e2 = (R * (local.col(i) - cl) + cw - world.col(i)).squaredNorm();
    if (e2 > tol[i] * tol[i]) return false;
    c += e2 / var[i];
  }
  // And the whole fit within the same tail (3n - 6 degrees of freedom): the rigid fit spreads
  // one wrong point's error over every anchor (simulated seed 11 at 8 ghosts: a reflection 88 mm
  // from the hidden LASI's prediction, the pelvis fitted to it and its three labelled mates with
  // residuals of 18, 14, 13 and 13 mm, each within its 18 mm tolerance: a chi-square of 41 on 6).
  if (c > segment_fit_chi2[3 * n - 6]) return false;
  // Each label given anew judged by where the segment's other anchors alone put it (its deleted
  // residual, as robust regression judges an outlier): the fit that includes the point pulls
  // towards it, and with four anchors it spreads the point's error within every tolerance and
  // the whole fit's (simulated seed 35 at 8 ghosts: LFHD hidden, the head held by its three other
  // markers, a reflection 33-38 mm from LFHD's place labelled for 13 frames). The others' fit is weighted by their variances, and the
  // place it predicts carries that fit's covariance (linearised: a translation and a small
  // rotation about the others' centroid) besides the point's own variance: anchors bunched on
  // one side of a segment pin its turn about the line through them loosely, and the place of a
  // marker on the far side with it (welk007's right foot at 12.5 Hz: the heel marker 49-63 mm
  // from where the ankle centre and the three forefoot markers put it, and rightly labelled).
  if (n < 4) {
    *cost = c;
    return true;
  }
  for (int i = 0; i < n; ++i) {
    if (!fresh[i]) continue;
    Eigen::Vector3d ml = Eigen::Vector3d::Zero(), mw = Eigen::Vector3d::Zero();
    double wsum = 0;
    for (int j = 0; j < n; ++j)
      if (j != i) {
        ml += local.col(j) / var[j];
        mw += world.col(j) / var[j];
        wsum += 1.0 / var[j];
      }
    ml /= wsum;
    mw /= wsum;
    Eigen::Matrix3d Hd = Eigen::Matrix3d::Zero();
    for (int j = 0; j < n; ++j)
      if (j != i) Hd += (local.col(j) - ml) * (world.col(j) - mw).transpose() / var[j];
    const Eigen::Matrix3d Rd = KabschRotation(Hd);
    // The others' information on (translation, rotation): J_j = [I, -[a_j]x], a_j the anchor's
    // lever from their centroid.
    Eigen::Matrix<double, 6, 6> info = Eigen::Matrix<double, 6, 6>::Zero();
    for (int j = 0; j < n; ++j) {
      if (j == i) continue;
      const Eigen::Vector3d a = Rd * (local.col(j) - ml);
      Eigen::Matrix<double, 3, 6> J;
      J << Eigen::Matrix3d::Identity(), -Skew(a);
      info.noalias() += J.transpose() * J / var[j];
    }
    const Eigen::Vector3d a = Rd * (local.col(i) - ml);
    Eigen::Matrix<double, 3, 6> Ji;
    Ji << Eigen::Matrix3d::Identity(), -Skew(a);
    const Eigen::LDLT<Eigen::Matrix<double, 6, 6>> ldlt(info);
    Eigen::Matrix3d S = Ji * ldlt.solve(Ji.transpose());
    S.diagonal().array() += var[i];
    const Eigen::Vector3d e = a + mw - world.col(i);
    if (e.dot(S.ldlt().solve(e)) > options.gate_chi2) return false;
  }
  *cost = c;
  return true;
}

// Turns row_to_col (columns < np are points) into the output labels; returns the count.
int Tracker::Impl::ApplyLabels(int np) {
  int labelled = 0;
  for (int m = 0; m < nm; ++m) {
    const int col = row_to_col[m];
    if (col < 0 || col >= np) {
      row_to_col[m] = -1;
      continue;
    }
    const int input = valid[col];
    out.point_of_marker[m] = input;
    out.marker_of_point[input] = m;
    ++labelled;
  }
  out.labelled = labelled;
  return labelled;
}

void Tracker::Impl::PushHistory(int np) {
  JudgeDeferrals();
  hist_points[hist_head].leftCols(np) = points.leftCols(np);
  hist_count[hist_head] = np;
  std::vector<char>& claimed = hist_claimed[hist_head];
  std::fill(claimed.begin(), claimed.begin() + np, 0);
  for (int m = 0; m < nm; ++m) {
    if (row_to_col[m] >= 0) claimed[row_to_col[m]] = 1;
    hist_marker_point[hist_head][m] = row_to_col[m];
  }
  for (size_t i = 0; i < centre_now.size(); ++i) hist_centre[hist_head][i] = centre_now[i];
  hist_head = (hist_head + 1) % kHistory;
  hist_size = std::min(hist_size + 1, kHistory);

  // A marker that lost its label this frame while another marker now holds its last point (one
  // marker is one point) held the wrong one: what it was seen beside was recorded under that
  // label (a head initialised turned about, its front markers on the back markers' points, their
  // own points unclaimed beside them), so it is forgotten, and the label no longer counts as held.
  for (int m = 0; m < nm; ++m) {
    if (row_to_col[m] >= 0 || unlabelled_run[m] != 1) continue;
    for (int a = 0; a < nm; ++a)
      if (a != m && row_to_col[a] >= 0 &&
          (points.col(row_to_col[a]) - last_point.col(m)).squaredNorm() < kTrackStep * kTrackStep) {
        ForgetRecords(m);
        break;
      }
  }
  // Each unclaimed point inherits its predecessor's record and adds the markers measured now.
  ++frame_index;
  for (int k = 0; k < np; ++k) {
    int* now = beside_now.data() + static_cast<size_t>(k) * nm;
    if (claimed[k]) continue;
    const int pred = Predecessor(k, np);
    const int* before = pred >= 0 ? beside_prev.data() + static_cast<size_t>(pred) * nm : nullptr;
    for (int a = 0; a < nm; ++a)
      now[a] = row_to_col[a] >= 0 && row_to_col[a] != k && measured[a] ? frame_index
               : before ? before[a]
                        : kNever;
  }
  for (int i = 0; i < doubted_count; ++i) {
    const auto [k, m] = doubted[i];
    if (!claimed[k]) beside_now[static_cast<size_t>(k) * nm + m] = frame_index;
  }
  beside_prev.swap(beside_now);
  // A limb re-check moved these markers' labels (ReacquireLimb): the points beside them were
  // recorded against the wrong labels, this frame's too.
  for (int m = 0; m < nm; ++m)
    if (relabelled[m]) {
      ForgetRecords(m);
      relabelled[m] = 0;
    }
  prev_points.leftCols(np) = points.leftCols(np);
  prev_free_count = 0;
  for (int k = 0; k < np; ++k) {
    prev_free[k] = !claimed[k];
    if (!claimed[k]) prev_free_list[prev_free_count++] = k;
  }
  prev_np = np;
}

// The last good frame's unclaimed point that point k continues: its nearest point of that frame
// within a frame's motion (kTrackStep), when k is also that point's nearest of this frame (mutual
// nearest neighbours: a reflection riding 15 mm from its marker is not confused with it) and
// it was not a marker's (k then continues that marker); -1 otherwise.
int Tracker::Impl::Predecessor(int k, int np) const {
  if (pred_cache[k] != -2) return pred_cache[k];
  const Eigen::Vector3d p = points.col(k);
  int pred = -1;
  double best = kTrackStep * kTrackStep;
  // The few unclaimed points first: most points (the markers') have none near and stop here.
  for (int f = 0; f < prev_free_count; ++f) {
    const int j = prev_free_list[f];
    const double d2 = (prev_points.col(j) - p).squaredNorm();
    if (d2 < best) {
      best = d2;
      pred = j;
    }
  }
  for (int j = 0; j < prev_np && pred >= 0; ++j)
    if (!prev_free[j] && (prev_points.col(j) - p).squaredNorm() < best) pred = -1;
  for (int i = 0; i < np && pred >= 0; ++i)
    if (i != k && (points.col(i) - prev_points.col(pred)).squaredNorm() < best) pred = -1;
  pred_cache[k] = pred;
  return pred;
}

// Whether point p has been seen beside marker m: followed back frame by frame, it was there, as
// another point, while m was measured, within the last kBesideSeconds. One marker is one point,
// so p is not m: it is a reflection that came with m (riding along with it, or fixed near where
// it passed) and outlived m's occlusion. Such a ghost keeps its distances to m's segment (it
// moves with the marker), so NonRigidTrack passes it, and its history ring (kHistory frames) is
// shorter than an occlusion; this record is carried for as long as the point is followed. The
// evidence expires, so that a point the track wrongly left unclaimed beside a wrong label is not
// kept from its marker for good.
bool Tracker::Impl::SeenBeside(int m, int k, int np) const {
  // A fresh track's labels may be wrong (see FreshTrack): there only a marker labelled in the last
  // frame, or one that held its point for kHeldSeconds, is kept from the reflection beside the
  // point it loses (an ankle marker hidden in the static pose, a lab-fixed ghost 8 cm away in its
  // still wide gate); a marker without either may be the one whose point was measured as
  // another's. A held label that proves wrong loses its records (PushHistory).
  if (prev_np == 0 || (FreshTrack() && labelled_run[m] == 0 && held_run[m] < HeldFrames()))
    return false;
  const int pred = Predecessor(k, np);
  if (pred < 0) return false;
  return frame_index - beside_prev[static_cast<size_t>(pred) * nm + m] <=
         kBesideSeconds * options.rate_hz;
}

// Whether point p, followed back through the last frames (the nearest unclaimed point within a
// frame's motion), changed its distance to marker m's joint centre: a marker keeps it (rigid
// body), a ghost does not -- a reflection fixed in the lab or riding along with another marker,
// which can live for seconds near the body. Only a point seen for kMinTrackFrames can be judged;
// a marker coming back from an occlusion has no past and passes (the labelled points it may
// pass near, a hand sliding over the thigh marker, are other markers' past, not its own).
bool Tracker::Impl::NonRigidTrack(int m, const Eigen::Vector3d& p) const {
  // A fresh track's limb may be wrongly placed, its joint centres with it (see FreshTrack).
  if (FreshTrack()) return false;
  double spread = 0;
  return TrackBack(m, p, &spread) >= kMinTrackFrames && spread > kRigidTolerance;
}

int Tracker::Impl::PastPoint(int slot, const Eigen::Vector3d& q, int own) const {
  const Eigen::Matrix3Xd& pts = hist_points[slot];
  const std::vector<char>& claimed = hist_claimed[slot];
  int nearest = -1;
  double best = kTrackStep * kTrackStep;
  for (int k = 0; k < hist_count[slot]; ++k) {
    if (claimed[k] && k != own) continue;
    const double d2 = (pts.col(k) - q).squaredNorm();
    if (d2 < best) {
      best = d2;
      nearest = k;
    }
  }
  return nearest;
}

int Tracker::Impl::TrackBack(int m, const Eigen::Vector3d& p, double* spread) const {
  const int segment = model->markers()[m].segment;
  Eigen::Vector3d q = p;
  const double r0 = (p - centre_now[segment]).norm();
  double lo = r0, hi = r0;
  int length = 1;
  for (int h = 1; h <= hist_size; ++h) {
    const int slot = (hist_head - h + kHistory) % kHistory;
    const Eigen::Matrix3Xd& pts = hist_points[slot];
    const int nearest = PastPoint(slot, q, -1);
    if (nearest < 0) break;
    q = pts.col(nearest);
    const double r = (q - hist_centre[slot][segment]).norm();
    lo = std::min(lo, r);
    hi = std::max(hi, r);
    ++length;
  }
  *spread = hi - lo;
  return length;
}

// A marker coming back after frames without a label is labelled at once but enters the update
// only from its second consecutive frame, and only if its point moved from the first frame's
// as its prediction did. Half of the ghosts near a body are single-frame reflections: one in the
// gate of a hidden marker whose segment is loosely held (a toe with only the heel seen: the gate
// is several centimetres long) would otherwise be trusted at the marker's full precision, move
// the segment by as much, shrink its covariance there, and leave the true marker outside the
// gate when it reappears (a limb lost for the 20 frames before its search). The next frame's
// point of a ghost is another one or none. A true marker costs one frame of information.
void Tracker::Impl::ChooseMeasurements() {
  measured_count = 0;
  int nmoved = 0;
  // Whether the subject stands still is asked only by the offsets' prior (LearnOffsets).
  const bool judge_stillness = options.marker_offset_prior_frames > 0;
  for (int m = 0; m < nm; ++m) {
    const int col = row_to_col[m];
    if (col < 0) {
      measured[m] = 0;
      labelled_run[m] = 0;
      continue;
    }
    const Eigen::Vector3d p = points.col(col), q = predicted.col(m);
    if (judge_stillness && labelled_run[m] > 1 && measured[m]) moved_buf[nmoved++] = (p - last_point.col(m)).norm();
    if (labelled_run[m] == 1) {
      const Eigen::Vector3d moved = (p - last_point.col(m)) - (q - last_predicted.col(m));
      measured[m] = moved.squaredNorm() <= kProbationDistance * kProbationDistance;
      if (!measured[m]) labelled_run[m] = 0;  // a different point: this is its first frame
    } else {
      measured[m] = labelled_run[m] > 1;
    }
    ++labelled_run[m];
    held_run[m] = std::max(held_run[m], labelled_run[m]);
    if (const int parent = ParentSegment(m); parent >= 0) {
      if (labelled_run[m] == 1) {
        window_rel.col(m) = committed_rel.col(m);
        has_window_rel[m] = has_committed_rel[m];
      } else if (labelled_run[m] > kProvisionalFrames) {
        committed_rel.col(m) = data.segment_rotation[parent].transpose() *
                               (p - data.segment_position[model->markers()[m].segment]);
        has_committed_rel[m] = 1;
      }
    }
    last_point.col(m) = p;
    last_predicted.col(m) = q;
    measured_count += measured[m];
  }
  subject_still = false;
  if (nmoved >= 3) {
    std::nth_element(moved_buf.begin(), moved_buf.begin() + nmoved / 2, moved_buf.begin() + nmoved);
    subject_still = moved_buf[nmoved / 2] <= kStillDisplacement + kStillSpeed * frame_dt;
  }
}

// TrackerOptions::min_return_probability. The clutter near the body: the points no marker
// claimed, new in this frame (no Predecessor), inside the labelled points' box grown by
// kClutterMargin (the simulated ghosts fill the body's box grown by 10 cm; a reflection far from
// the body is in no marker's gate), per m^3, averaged over the last clutter_time_constant_s. A single-frame ghost that took a returning
// marker's label is claimed, so the average over frames, not this frame's count, is the density.
// Withholding only clears the output: the label itself stays, so its probation (the next frame's
// point, moved as the prediction did) runs and reports it from its second frame, and the track
// is the same as without it.
void Tracker::Impl::WithholdDoubtfulReturns(int np, double dt) {
  if (options.min_return_probability <= 0) return;
  constexpr double kClutterMargin = 0.1;
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(std::numeric_limits<double>::infinity());
  Eigen::Vector3d hi = -lo;
  std::fill(claimed_now.begin(), claimed_now.begin() + np, 0);
  for (int m = 0; m < nm; ++m) {
    const int col = row_to_col[m];
    if (col < 0 || col >= np) continue;
    claimed_now[col] = 1;
    lo = lo.cwiseMin(points.col(col));
    hi = hi.cwiseMax(points.col(col));
  }
  if (!(hi.x() >= lo.x())) return;  // nothing labelled
  lo.array() -= kClutterMargin;
  hi.array() += kClutterMargin;
  int unclaimed = 0, lasting = 0;
  for (int k = 0; k < np; ++k)
    if (!claimed_now[k] && (points.col(k).array() >= lo.array()).all() &&
        (points.col(k).array() <= hi.array()).all())
      ++(Predecessor(k, np) < 0 ? unclaimed : lasting);
  const double volume = (hi - lo).prod();
  const double density = unclaimed / volume, lasting_density = lasting / volume;
  const double w = 1.0 - std::exp(-dt / options.clutter_time_constant_s);
  clutter_density = clutter_density < 0 ? density : clutter_density + w * (density - clutter_density);
  // Without a last tracking frame no point continues one (the start leaves the unclaimed points
  // without a past): that frame says nothing about lasting points.
  if (hist_size > 0)
    lasting_clutter_density = lasting_clutter_density < 0
                                  ? lasting_density
                                  : lasting_clutter_density + w * (lasting_density - lasting_clutter_density);
  if (clutter_density <= 0) return;
  // g / (g + lambda) < p  <=>  g < lambda p / (1 - p).
  const double p = options.min_return_probability;
  const double min_density = clutter_density * p / (1 - p);
  for (int m = 0; m < nm; ++m) {
    const int col = row_to_col[m];
    // A point that continues an unclaimed point of the last frame is no single-frame ghost (a
    // marker the start or the gates left unlabelled while in view; a lasting reflection is
    // judged by its past, NonRigidTrack and SeenBeside).
    if (col < 0 || col >= np || labelled_run[m] != 1 || Predecessor(col, np) >= 0) continue;
    if (PredictionDensity(m, points.col(col) - predicted.col(m)) >= min_density) continue;
    out.point_of_marker[m] = -1;
    out.marker_of_point[valid[col]] = -1;
    --out.labelled;
  }
}

// A hidden marker's gate grows with the process noise of the coordinates only it measured (a
// foot with its toe marker hidden turns freely about the line from the ankle centre to the
// heel): 90 ms after its toe marker was hidden a foot's gate took a reflection 57 mm off, and
// the label followed the reflection for 389 frames (simulated seed 42 at 8 ghosts; seed 69: after
// 60 ms of the static pose the toe's prediction had a 32 mm standard deviation and its gate took
// a reflection 104 mm off). A point that continues an unclaimed track is a
// lasting reflection or a marker the gates left; against the lasting reflections' density the
// point's density under the prediction tells which is likelier, as for a single-frame ghost
// (WithholdDoubtfulReturns). Unlike a single-frame ghost, a lasting reflection keeps the label
// it is given (labels follow point tracks): the label is not given; the registration and the
// limb search, which judge the point by its rigid past, may still give it. Only for a marker the
// track has held (its offset learnt, so its prediction errs as S says): one not yet labelled
// carries the model's own error, which S does not hold (gait2354's generic model: R.Acromium's
// point 110 mm from its prediction, 5 standard deviations, and its own). And only for a marker
// missing for kMinTrackFrames, the frames that make a point's track: before that its gate is
// the prediction of a few frames, not grown by an occlusion (at 12.5 Hz, where the learnt
// process noise leaves gates metres wide from one frame to the next, the test refused 12 right
// returns of EkfTracker.LearntProcessNoiseLabelsALowFrameRate and no wrong one).

bool Tracker::Impl::LastingClutterExplains(int m, int k, int np) const {
  if (options.min_return_probability <= 0 || lasting_clutter_density <= 0 ||
      held_run[m] < kHeldFrames || unlabelled_run[m] < kMinTrackFrames || Predecessor(k, np) < 0)
    return false;
  const double p = options.min_return_probability;
  return PredictionDensity(m, points.col(k) - predicted.col(m)) < lasting_clutter_density * p / (1 - p);
}

// The provisional window (ekf/tracker.h, "Labelling"). A label taken afresh was decided on one
// frame, by a prediction that drifted while the marker was hidden; labels then follow point
// tracks, so a wrong one lasts as long as its point. For kProvisionalFrames after a label is
// taken (outside the fresh track, whose labels the limb search still revises), its point and the
// best unclaimed rival within kRivalRadius are scored every frame, and the scores summed while the
// rival's point track lasts, on two pieces of evidence that the placement which gave the label
// cannot have bent: RigidResidual (their distances to the segment's joint centre and committed
// markers against the marker's own) and their distances to where the marker's point was when its
// label was last committed, carried with its parent segment (window_rel: a limb search that
// moved a hidden foot by decimetres to put its toe marker on a reflection moved the prediction,
// not that). After kRivalFrames frames, a rival that fits the marker's distances within kRivalFit
// takes the label when it fits them clearly better (mean square under kRivalRatio of the label's,
// the label's over kRivalFloor^2) or lies clearly nearer where the marker was (likewise, the
// label's over kPriorFloor): the marker held the wrong point (its records go, ForgetRecords; the
// verdict follows the old point, as DropLabelsAMateFitsBetter's does), and the new label starts
// on probation. Only a rival that came after the label was given is one (one there before was
// judged then), and only committed mates (held kProvisionalFrames) are anchors: a mate on a wrong
// point made a right label look wrong (seed 10's start, its forearm mirrored: the finger marker
// moved to a wrist marker's unclaimed point). Why a window and not the frame: the rival appears
// when the marker's own point comes back, frames after the wrong label was given (seed 47 at 5
// ghosts: RFIN took a reflection riding 30 mm from its hidden point; its own point came back 26
// frames later, 4 mm off its distance to the wrist, the reflection 12 mm, and was then left
// unlabelled for the rest of the take, 0.981 of the labels; seeds 4, 34, 42 at 8 ghosts: a toe
// marker placed on a reflection by the limb search, its own point back 5-12 cm away).
void Tracker::Impl::ReviewProvisionalLabels(int np) {
  std::fill(claimed_now.begin(), claimed_now.begin() + np, 0);
  for (int m = 0; m < nm; ++m)
    if (row_to_col[m] >= 0) claimed_now[row_to_col[m]] = 1;
  for (int m = 0; m < nm; ++m) {
    const int k = row_to_col[m];
    if (k < 0 || labelled_run[m] == 0 || labelled_run[m] >= kProvisionalFrames || FreshTrack()) {
      rival_frames[m] = 0;
      continue;
    }
    const Eigen::Vector3d p = points.col(k);
    const double own = RigidResidual(m, p);
    if (!std::isfinite(own)) {
      rival_frames[m] = 0;
      continue;
    }
    int best = -1;
    double best_r = std::numeric_limits<double>::infinity();
    for (int j = 0; j < np; ++j) {
      if (claimed_now[j] || (points.col(j) - p).squaredNorm() > kRivalRadius * kRivalRadius ||
          DeferralExcludes(m, j))
        continue;
      const double r = RigidResidual(m, points.col(j));
      if (r < best_r) {
        best_r = r;
        best = j;
      }
    }
    if (best < 0) {
      rival_frames[m] = 0;
      continue;
    }
    if (rival_frames[m] > 0 &&
        (points.col(best) - rival_last.col(m)).squaredNorm() > kTrackStep * kTrackStep)
      rival_frames[m] = 0;
    if (rival_frames[m] == 0)
      own_residual[m] = rival_residual[m] = own_prior[m] = rival_prior[m] = 0;
    own_residual[m] += own;
    rival_residual[m] += best_r;
    const int parent = ParentSegment(m);
    if (has_window_rel[m] && parent >= 0) {
      const Eigen::Vector3d was = data.segment_position[model->markers()[m].segment] +
                                  data.segment_rotation[parent] * window_rel.col(m);
      own_prior[m] += (p - was).squaredNorm();
      rival_prior[m] += (points.col(best) - was).squaredNorm();
    }
    rival_last.col(m) = points.col(best);
    const int n = ++rival_frames[m];
    const bool fits_better = rival_residual[m] < kRivalRatio * own_residual[m] &&
                             own_residual[m] >= n * kRivalFloor * kRivalFloor;
    const bool where_it_was = has_window_rel[m] && rival_prior[m] < kRivalRatio * own_prior[m] &&
                              own_prior[m] >= n * kPriorFloor * kPriorFloor;
    if (n < kRivalFrames || rival_residual[m] > n * kRivalFit * kRivalFit ||
        !(fits_better || where_it_was))
      continue;
    // A rival that was already there when the label was given was judged then.
    double spread = 0;
    if (TrackBack(m, points.col(best), &spread) > std::min(labelled_run[m], kHistory)) continue;
    // Nor one an unlabelled mate could be: which of a segment's markers a point is, the rigid
    // distances and the past place cannot tell where both fit (DropLabelsAMateFitsBetter).
    bool a_mates = false;
    for (const int o : segment_markers[model->markers()[m].segment])
      a_mates = a_mates || (o != m && row_to_col[o] < 0 && OnSegmentSphere(o, points.col(best)));
    if (a_mates) continue;
    if (doubted_count < nm) doubted[doubted_count++] = {k, m};
    ForgetRecords(m);
    row_to_col[m] = best;
    labelled_run[m] = 0;
    rival_frames[m] = 0;
    claimed_now[k] = 0;
    claimed_now[best] = 1;
  }
}

double Tracker::Impl::RigidResidual(int m, const Eigen::Vector3d& p) const {
  const int segment = model->markers()[m].segment;
  double sum = 0;
  int n = 0;
  if (marker_depth[m] > 0) {
    const Eigen::Vector3d& c = centre_now[segment];
    const double r = (p - c).norm() - (predicted.col(m) - c).norm();
    sum += r * r;
    ++n;
  }
  for (const int o : segment_markers[segment]) {
    if (o == m || row_to_col[o] < 0 || labelled_run[o] < kProvisionalFrames) continue;
    const double r = (p - points.col(row_to_col[o])).norm() -
                     (predicted.col(m) - predicted.col(o)).norm();
    sum += r * r;
    ++n;
  }
  return n > 0 ? sum / n : kNaN;
}

// Whether point p lies at marker m's distance from its segment's joint centre (within the
// marker's noise and the predicted centre's error): a segment turns about its joint, so that
// distance is the one thing about a marker that no error in the segment's angles changes. The
// Mahalanobis gate is long along the directions an uncertain joint angle moves the marker; a
// point of the neighbouring segment can sit inside it (a finger marker's gate, its hand held by
// that marker alone, over a wrist marker's point 4-5 cm nearer the wrist) and the filter then
// bends the limb to keep it. The root's origin is as uncertain as the root itself: not tested.
bool Tracker::Impl::OnSegmentSphere(int m, const Eigen::Vector3d& p) const {
  const int segment = model->markers()[m].segment;
  if (marker_depth[m] == 0) return true;
  const Eigen::Vector3d centre = centre_now[segment];
  const double radius = (predicted.col(m) - centre).norm();
  return std::abs((p - centre).norm() - radius) <= SegmentTolerance(m);
}

bool Tracker::Impl::LooseSegment(int segment) const {
  const std::vector<int>& ms = segment_markers[segment];
  // Three or more markers: with its joint centre, two markers fix only three distances, which a
  // point of the neighbouring segment or a ghost fits as well (a simulated foot's heel and toe).
  // The root has no joint centre to anchor it (and moves least).
  if (ms.size() < 3 || marker_depth[ms[0]] == 0) return false;
  // Only a segment the track holds: one with a marker labelled in the last kGroupRecentSeconds.
  // A limb never labelled, or lost for longer, has no pose its prediction could be a prior of
  // (welk007's forearms at the start, 30-44 cm off): the limb search places it.
  bool held = false;
  for (int m : ms)
    held |= labelled_run[m] > 0 ||
            (held_run[m] > 0 && unlabelled_run[m] < kGroupRecentSeconds * options.rate_hz);
  if (!held) return false;
  // The segment's best-held marker: where even its prediction is uncertain over more than half
  // the way to its nearest neighbour, the prediction cannot say which point is which. So every
  // marker's predicted spread (the gate's radius on the prediction alone) must reach past half
  // the distance to some other seen marker; the first that does not settles it (most frames, at
  // the first marker: this runs every frame).
  for (int m : ms) {
    const double reach = 2.0 * std::sqrt(options.gate_chi2 * prediction_trace[m] / 3.0);
    bool near = false;
    for (int o = 0; o < nm && !near; ++o)
      near = o != m && seen[o] && (predicted.col(o) - predicted.col(m)).squaredNorm() < reach * reach;
    if (!near) return false;
  }
  return true;
}

int Tracker::Impl::PlacingSegment(int segment) const {
  int p = model->joints()[model->segments()[segment].joint].parent;
  while (p >= 0 && segment_markers[p].empty()) p = model->joints()[model->segments()[p].joint].parent;
  return p;
}

bool Tracker::Impl::FitSegmentPose(int segment, Eigen::Matrix3d* R, Eigen::Vector3d* t,
                                   FitPrecision* fit) const {
  const std::vector<int>& ms = segment_markers[segment];
  constexpr int kMaxAnchors = kMaxSegmentMarkers + 1;
  Eigen::Matrix<double, 3, kMaxAnchors> local, world;
  double w[kMaxAnchors];
  int n = 0;
  const Eigen::Matrix3d& R0 = data.segment_rotation[segment];
  if (marker_depth[ms[0]] > 0) {
    local.col(n).setZero();
    world.col(n) = centre_now[segment];
    w[n++] = 1.0 / std::max(centre_variance[segment], 1e-8);
  }
  for (int m : ms) {
    if (row_to_col[m] < 0 || n == kMaxAnchors) continue;
    local.col(n) = R0.transpose() * (predicted.col(m) - centre_predicted[segment]);
    world.col(n) = points.col(row_to_col[m]);
    w[n++] = 1.0 / (MeasurementVariance(m) + model_error[m]);
  }
  if (n < 3) return false;
  double sw = 0;
  Eigen::Vector3d cl = Eigen::Vector3d::Zero(), cw = Eigen::Vector3d::Zero();
  for (int i = 0; i < n; ++i) {
    sw += w[i];
    cl += w[i] * local.col(i);
    cw += w[i] * world.col(i);
  }
  cl /= sw;
  cw /= sw;
  Eigen::Matrix3d H = Eigen::Matrix3d::Zero();
  // The fit's precision: its rotation's information sum w |r|^2 I - r r^T about the weighted
  // centroid (PlacedVariance).
  Eigen::Matrix3d info = Eigen::Matrix3d::Zero();
  for (int i = 0; i < n; ++i) {
    const Eigen::Vector3d r = world.col(i) - cw;
    H += w[i] * (local.col(i) - cl) * r.transpose();
    info += w[i] * (r.squaredNorm() * Eigen::Matrix3d::Identity() - r * r.transpose());
  }
  *R = KabschRotation(H);
  *t = cw - *R * cl;
  fit->centroid = cw;
  fit->weight = sw;
  bool invertible = false;
  info.computeInverseWithCheck(fit->rotation_covariance, invertible, 1e-12 * std::max(info.trace(), 1e-300));
  if (!invertible) fit->rotation_covariance.setConstant(kNaN);
  return true;
}

double Tracker::Impl::PlacedVariance(int segment, const Eigen::Vector3d& q) const {
  const FitPrecision& fit = fit_precision[segment];
  const Eigen::Vector3d d = q - fit.centroid;
  Eigen::Matrix3d cross;
  cross << 0, -d.z(), d.y(), d.z(), 0, -d.x(), -d.y(), d.x(), 0;
  return 1.0 / fit.weight + (cross * fit.rotation_covariance * cross.transpose()).trace() / 3.0;
}

// Rigid-group labelling (ekf/tracker.h, "Rigid groups"). Where the frame rate is low against the
// motion (12 Hz: a swinging foot 4-11 cm off its constant-acceleration prediction, its markers
// 5-6 cm apart), a marker's prediction cannot say which of the points near it is its own, and
// the gating's labels are guesses that the point tracks then keep (a lateral ankle marker on the
// medial one's point for 60 frames). What does not depend on the frame rate is the segment's
// rigid geometry: its markers and its joint centre keep their distances in every frame. So a
// loose segment (LooseSegment) has its markers labelled as one rigid body: every pair of its
// markers on a pair of candidate points at their distance (each candidate within the marker's
// gate, the prediction then only a prior, and at the marker's distance from the joint centre)
// gives, with the joint centre, a pose; each pose places the segment's other markers, which take
// the candidate points there; the labelling is refitted and scored -- the rigid residuals over
// their variances, the prediction's Mahalanobis distances as the prior, the gate for each marker
// left without a point, as the assignment prices it; a labelling must label kMinGroupLabels
// markers (an over-determined fit). The best labelling is taken when every different one costs
// kGroupMargin more; where one comes nearer, the markers the two label alike take the group's
// points and the others keep the gating's labels (left empty instead, the labels lost took the
// track with them: welk007 at 12.5 Hz 0.956 of the labels, biobuddy's right knee 0.961).
// Segments are labelled root first, and each fitted segment's pose places its loose children's
// joint centres (their own prediction is as loose as theirs: the knee of a swinging leg), and the
// children's gates move with their centres: the prediction's error at a swinging foot is mostly
// the shank's, which the shank's fit has measured (tracker.h: why moved, not turned). The
// points of a segment that is not loose are its gating's. At 100-200 Hz a segment is loose only
// where its markers' predictions have grown (a forearm turned about its axis while its wrist
// markers were hidden), a few frames in a take.
void Tracker::Impl::LabelLooseSegments(int np) {
  const int ns = model->num_segments();
  std::fill(segment_loose.begin(), segment_loose.end(), 0);
  std::fill(segment_fitted.begin(), segment_fitted.end(), 0);
  for (int m = 0; m < nm; ++m)
    if (row_to_col[m] >= np) row_to_col[m] = -1;
  bool any = false;
  for (int s : segment_order) any |= (segment_loose[s] = LooseSegment(s)) != 0;
  if (!any) return;
  // Which segments' poses are fitted: the loose ones and the segments that place their joint
  // centres (PlacingSegment).
  for (int s = 0; s < ns; ++s) {
    centre_predicted[s] = data.segment_position[s];
    centre_variance[s] = 0.25 * kJointCentreTolerance * kJointCentreTolerance;
    segment_wants_fit[s] = segment_loose[s];
  }
  for (int s = 0; s < ns; ++s)
    if (segment_loose[s]) {
      const int placing = PlacingSegment(s);
      if (placing >= 0) segment_wants_fit[placing] = 1;
    }
  // Point ownership: per point, the marker labelled on it.
  std::fill(lcand.begin(), lcand.begin() + np, -1);
  for (int m = 0; m < nm; ++m)
    if (row_to_col[m] >= 0) lcand[row_to_col[m]] = m;
  // Points claimed for good: by a marker of a segment that is not loose, or of a group decided.
  std::fill(ltaken.begin(), ltaken.begin() + np, 0);
  for (int m = 0; m < nm; ++m)
    if (row_to_col[m] >= 0 && !segment_loose[model->markers()[m].segment]) ltaken[row_to_col[m]] = 1;

  const double gate = options.gate_chi2;
  for (int s : segment_order) {
    const int parent = model->joints()[model->segments()[s].joint].parent;
    const std::vector<int>& ms = segment_markers[s];
    const int nms = static_cast<int>(ms.size());
    const int placing = segment_loose[s] ? PlacingSegment(s) : -1;
    if (placing >= 0 && segment_fitted[placing]) {
      // Where the placing segment's fitted pose puts this segment's joint centre. The parent's
      // joint with its child lies among its markers (a knee, an ankle), where their fit places
      // it well. Carried across a segment without markers (the talus: welk007's shank to its
      // foot), the centre can lie beyond them, where the fit's rotation error, times that
      // distance, can exceed the unfitted centre's tolerance (gait2354's walk, whose shank has
      // three markers below the knee and none at the ankle: carried 35 cm down to the feet, they
      // took each other's points, 1.000 -> 0.765 of the labels): carried only where the fit
      // places it within that tolerance, and held as loosely as unfitted, since it also moves
      // with the talus's own angle as predicted, which no fit has measured.
      const Eigen::Vector3d rel = data.segment_rotation[placing].transpose() *
                                  (centre_predicted[s] - centre_predicted[placing]);
      const Eigen::Vector3d placed = fit_rotation[placing] * rel + fit_translation[placing];
      if (placing == parent) {
        centre_now[s] = placed;
        centre_variance[s] = options.sigma_m * options.sigma_m;
      } else if (PlacedVariance(placing, placed) <= centre_variance[s]) {
        centre_now[s] = placed;
      }
    }
    if (segment_loose[s] && nms <= kMaxSegmentMarkers) {
      const Eigen::Matrix3d& R0 = data.segment_rotation[s];
      const Eigen::Vector3d c = centre_now[s];
      const double tol_c = std::sqrt(gate * centre_variance[s]);
      Eigen::Matrix<double, 3, kMaxSegmentMarkers> local;
      double var[kMaxSegmentMarkers], tol[kMaxSegmentMarkers];
      int cand[kMaxSegmentMarkers][kGroupCandidates], ncand[kMaxSegmentMarkers];
      double cd2[kMaxSegmentMarkers][kGroupCandidates];
      int with = 0;
      // The gates (and the prior) are centred where the joint centre went: each prediction moved
      // with the centre (zero when the parent was not fitted), the segment's own angles as
      // predicted. The gate keeps its size, S_m, which also holds the parent chain's uncertainty
      // the fit has taken out: no tighter than before, only where the evidence puts it.
      const Eigen::Vector3d centre_moved = c - centre_predicted[s];
      for (int i = 0; i < nms; ++i) {
        const int m = ms[i];
        local.col(i) = R0.transpose() * (predicted.col(m) - centre_predicted[s]);
        var[i] = MeasurementVariance(m) + model_error[m];
        tol[i] = std::sqrt(gate * var[i]);
        ncand[i] = 0;
        const double radius = local.col(i).norm();
        const Eigen::Vector3d expected = predicted.col(m) + centre_moved;
        for (int k = 0; k < np; ++k) {
          if (ltaken[k] || DeferralExcludes(m, k)) continue;
          const Eigen::Vector3d e = points.col(k) - expected;
          if (e.squaredNorm() >= reject_sq[m]) continue;
          const double d2 = e.dot(s_inv[m] * e);
          if (d2 >= gate) continue;
          if (std::abs((points.col(k) - c).norm() - radius) > tol[i] + tol_c) continue;
          int& n = ncand[i];
          if (n == kGroupCandidates && d2 >= cd2[i][n - 1]) continue;
          int j = n < kGroupCandidates ? n++ : n - 1;
          for (; j > 0 && cd2[i][j - 1] > d2; --j) {
            cd2[i][j] = cd2[i][j - 1];
            cand[i][j] = cand[i][j - 1];
          }
          cd2[i][j] = d2;
          cand[i][j] = k;
        }
        with += ncand[i] > 0;
      }
      int best_label[kMaxSegmentMarkers], label[kMaxSegmentMarkers];
      double best_cost = std::numeric_limits<double>::infinity(), runner_up = best_cost;
      int second_label[kMaxSegmentMarkers];
      bool have_second = false;
      // A pose from the centre and two markers' points, or from the whole labelling.
      auto fit = [&](const int* lab, Eigen::Matrix3d* R, Eigen::Vector3d* t) {
        const double wc = 1.0 / centre_variance[s];
        double sw = wc;
        Eigen::Vector3d cl = Eigen::Vector3d::Zero(), cw = wc * c;
        for (int i = 0; i < nms; ++i) {
          if (lab[i] < 0) continue;
          sw += 1.0 / var[i];
          cl += local.col(i) / var[i];
          cw += points.col(lab[i]) / var[i];
        }
        cl /= sw;
        cw /= sw;
        Eigen::Matrix3d H = wc * (-cl) * (c - cw).transpose();
        for (int i = 0; i < nms; ++i)
          if (lab[i] >= 0) H += (local.col(i) - cl) * (points.col(lab[i]) - cw).transpose() / var[i];
        *R = KabschRotation(H);
        *t = cw - *R * cl;
      };
      auto score = [&](int a, int ka, int b, int kb) {
        for (int i = 0; i < nms; ++i) label[i] = -1;
        label[a] = ka;
        label[b] = kb;
        Eigen::Matrix3d R;
        Eigen::Vector3d t;
        fit(label, &R, &t);
        // The pose places the other markers: each takes its nearest candidate within tolerance.
        for (int i = 0; i < nms; ++i) {
          if (i == a || i == b) continue;
          const Eigen::Vector3d w = R * local.col(i) + t;
          double bd = tol[i] * tol[i];
          for (int j = 0; j < ncand[i]; ++j) {
            const int k = cand[i][j];
            bool used = false;
            for (int o = 0; o < nms; ++o) used |= label[o] == k;
            const double d = (points.col(k) - w).squaredNorm();
            if (!used && d < bd) {
              bd = d;
              label[i] = k;
            }
          }
        }
        fit(label, &R, &t);
        double cost = (t - c).squaredNorm() / centre_variance[s];  // the centre: local origin
        if (cost > gate) return;
        int labels = 0;
        for (int i = 0; i < nms; ++i) {
          if (label[i] < 0) {
            cost += gate;
            continue;
          }
          const double e2 = (R * local.col(i) + t - points.col(label[i])).squaredNorm();
          if (e2 > tol[i] * tol[i]) {
            label[i] = -1;
            cost += gate;
            continue;
          }
          ++labels;
          double d2 = 0;
          for (int j = 0; j < ncand[i]; ++j)
            if (cand[i][j] == label[i]) d2 = cd2[i][j];
          cost += e2 / var[i] + d2;
        }
        if (labels < kMinGroupLabels) return;
        if (cost < best_cost) {
          if (std::isfinite(best_cost) && !std::equal(label, label + nms, best_label)) {
            runner_up = best_cost;
            std::copy(best_label, best_label + nms, second_label);
            have_second = true;
          }
          best_cost = cost;
          std::copy(label, label + nms, best_label);
        } else if (cost < runner_up && !std::equal(label, label + nms, best_label)) {
          runner_up = cost;
          std::copy(label, label + nms, second_label);
          have_second = true;
        }
      };
      if (with >= 2) {
        for (int a = 0; a < nms; ++a)
          for (int b = a + 1; b < nms; ++b) {
            const double dab = (local.col(a) - local.col(b)).norm();
            for (int i = 0; i < ncand[a]; ++i)
              for (int j = 0; j < ncand[b]; ++j) {
                const int ka = cand[a][i], kb = cand[b][j];
                if (ka == kb) continue;
                if (std::abs((points.col(ka) - points.col(kb)).norm() - dab) > tol[a] + tol[b]) continue;
                score(a, ka, b, kb);
              }
          }
      }
      if (std::isfinite(best_cost)) {
        const bool decided = !have_second || runner_up - best_cost >= kGroupMargin;
        // Undecided: the markers the two label alike take the group's points; the others keep
        // the gating's, where no marker of the group took it.
        int keep[kMaxSegmentMarkers];
        for (int i = 0; i < nms; ++i) {
          keep[i] = -1;
          if (decided || second_label[i] == best_label[i]) continue;
          const int old = row_to_col[ms[i]];
          bool taken = false;
          for (int j = 0; j < nms; ++j)
            taken |= (decided || second_label[j] == best_label[j]) && best_label[j] == old && old >= 0;
          keep[i] = taken ? -1 : old;
        }
        for (int i = 0; i < nms; ++i) {
          const int m = ms[i];
          int k = best_label[i];
          if (!decided && second_label[i] != k) k = keep[i];
          const int old = row_to_col[m];
          if (old == k) continue;
          if (old >= 0 && lcand[old] == m) lcand[old] = -1;
          if (k >= 0) {
            const int o = lcand[k];
            if (o >= 0 && o != m) row_to_col[o] = -1;
            lcand[k] = m;
          }
          row_to_col[m] = k;
        }
        for (int i = 0; i < nms; ++i)
          if (row_to_col[ms[i]] >= 0) ltaken[row_to_col[ms[i]]] = 1;
      }
    }
    if (segment_wants_fit[s])
      segment_fitted[s] = FitSegmentPose(s, &fit_rotation[s], &fit_translation[s], &fit_precision[s]);
  }
}

// Deferred labels (ekf/tracker.h, "Deferred labels"). Each candidate is followed as a point
// track (its nearest point within a frame's motion). A candidate lost for kDeferGoneSeconds (an
// occlusion's length: the marker's own point may come back) or after a single frame (a
// reflection of one frame: most are) is gone; one whose distance to an anchor changed is ruled
// out, by a centimetre in a frame or by a millimetre in its mean over kStillBlockSeconds (a
// standing subject's sway; JudgeDeferrals). The one candidate left when every other is ruled
// out or gone is the marker's: the gates may then give it; until then no stage gives the marker
// any of them (a new point, one that came after the deferral, is the gates' as ever, except while
// the decided candidate is hidden: the marker waits for it). A candidate ruled out is kept from
// the marker while it lives.
void Tracker::Impl::MatchDeferrals(int np) {
  const int gone_frames = std::max(2, static_cast<int>(std::lround(kDeferGoneSeconds * options.rate_hz)));
  for (int m = 0; m < nm; ++m) {
    Deferral& d = deferral[m];
    if (d.n == 0) continue;
    // Lost for less than kDeferGoneSeconds: its marker's point may be coming back.
    auto hidden_briefly = [&](int c) { return !d.alive[c] && d.frames - d.died[c] < gone_frames; };
    int open = 0, last = -1, undecided = 0, excluded = 0;
    for (int c = 0; c < d.n; ++c) {
      d.point[c] = -1;
      // The decided candidate hidden for less than kDeferGoneSeconds is looked for where it was
      // last seen: its marker's point coming back.
      const bool returning = c == d.decided && hidden_briefly(c);
      if (d.alive[c] || returning) {
        double best = kTrackStep * kTrackStep;
        for (int k = 0; k < np; ++k) {
          const double d2 = (points.col(k) - d.at[c]).squaredNorm();
          if (d2 < best) {
            best = d2;
            d.point[c] = k;
          }
        }
        if (d.point[c] >= 0) {
          d.alive[c] = 1;
        } else if (d.alive[c]) {
          d.alive[c] = 0;
          d.died[c] = d.frames;
        }
      }
      if (d.ruled_out[c]) {
        excluded += d.alive[c];
        continue;
      }
      if (d.alive[c]) {
        ++open;
        last = c;
      } else if (d.lived[c] > 1 && d.frames - d.died[c] < gone_frames) {
        ++undecided;  // hidden, perhaps: its marker may come back
      }
    }
    if (open == 0 && undecided == 0 && excluded == 0) {
      d.n = 0;
      continue;
    }
    // A decided candidate hidden (the one undecided, none open) stays decided: until it comes
    // back or is gone, its marker takes no other point.
    const bool hidden = open == 0 && undecided == 1 && d.decided >= 0 && hidden_briefly(d.decided);
    d.decided = open == 1 && undecided == 0 ? last : hidden ? d.decided : -1;
  }
}

void Tracker::Impl::JudgeDeferrals() {
  const int longest = static_cast<int>(std::lround(kBesideSeconds * options.rate_hz));
  const int block = std::max(3, static_cast<int>(std::lround(kStillBlockSeconds * options.rate_hz)));
  for (int m = 0; m < nm; ++m) {
    Deferral& d = deferral[m];
    if (d.n == 0) continue;
    bool rival = false;  // a candidate ruled out is kept from the marker while it lives
    for (int c = 0; c < d.n; ++c) rival |= c != d.decided && d.alive[c];
    if ((row_to_col[m] >= 0 && labelled_run[m] >= kHeldFrames && !rival) || ++d.frames > longest) {
      d.n = 0;
      continue;
    }
    for (int c = 0; c < d.n; ++c) {
      if (!d.alive[c] || d.point[c] < 0) continue;
      const Eigen::Vector3d p = points.col(d.point[c]);
      d.at[c] = p;
      ++d.lived[c];
      for (int a = 0; a < d.nanchors; ++a) {
        const int k = row_to_col[d.anchor[a]];
        if (k < 0) continue;
        const double distance = (p - points.col(k)).norm();
        if (std::abs(distance - d.d0[c][a]) > kRigidTolerance) d.ruled_out[c] = 1;
        d.sum[c][a] += distance;
        if (++d.count[c][a] < block) continue;
        const double mean = d.sum[c][a] / d.count[c][a];
        if (d.blocks[c][a]++ == 0)
          d.mean0[c][a] = mean;
        else if (std::abs(mean - d.mean0[c][a]) > kStillTolerance)
          d.ruled_out[c] = 1;
        d.sum[c][a] = 0;
        d.count[c][a] = 0;
      }
    }
  }
}

}  // namespace mocap::ekf
