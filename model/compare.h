// Comparing two body models with the same topology, e.g. a fitted model (B) against the truth it
// was simulated from (A), by what marker data can determine only, so that a gauge choice (where
// a segment's frame sits relative to its markers, the point along a hinge axis, the zero of a
// coordinate, the root segment's origin) is never counted as an error.
//
// Geometry is taken in each segment's own frame, scaled (s_S m for markers, s_P c_J for centres),
// at the zero pose (z = 0). For every segment with >= 3 non-collinear markers present in both
// models, B's markers are rigidly aligned onto A's (Umeyama, no scale): that alignment, not the
// segment frame, relates B's geometry on the segment to A's.
//
//   joint centre  J (parent P, child C): B's centre mapped through P's and through C's alignment,
//                 distance to A's centre; the larger of the two. If neither segment can be
//                 aligned: the union of P's and C's markers in the world at the zero pose is
//                 aligned instead ("union"); if even that is impossible, P's frame as is
//                 ("unaligned"). Joints with one moving rotation (hinges, and CustomJoints such
//                 as OpenSim's knee whose translations follow the angle): only the component
//                 perpendicular to A's axis, the other is a gauge. The root
//                 joint is skipped (its centre is a gauge).
//   axis          each fitted axis, mapped through the alignment of the segments it is FIXED in
//                 (no moving rotation of its joint between it and the segment: a hinge axis is
//                 fixed in both, a universal joint's first axis in the parent only, its second in
//                 the child only -- in the other segment its direction depends on a coordinate's
//                 zero, a gauge); the larger angle. Fallbacks as for centres.
//   length        segment S: distance from its proximal joint centre to each child joint's centre
//                 in S's frame; a hinge end is its axis line (closest point). No alignment needed.
//                 The root segment's origin is a gauge: there the lengths are between pairs of
//                 its child joints ("pelvis:hip_l-hip_r").
//   marker        after its segment's alignment; segments with 1-2 markers are compared in their
//                 own frame (MarkerDifference::aligned = false), which is not gauge-free.
#pragma once

#include <limits>
#include <string>
#include <vector>

#include "model/model.h"

namespace mocap {

struct ErrorStats {
  double max = 0.0;
  double rms = 0.0;
  int count = 0;  // values that went into max and rms
};

struct AxisDifference {
  int element = -1;        // element index within the joint
  std::string coordinate;  // the coordinate that drives it
  double error_deg = std::numeric_limits<double>::quiet_NaN();
  std::string basis;       // how it was aligned, as JointDifference::basis
};

struct JointDifference {
  std::string joint;
  JointType type = JointType::kCustom;
  // One moving rotation (a hinge, or a knee whose translations follow its angle): along-axis
  // centre offsets ignored, a gauge.
  bool hinge = false;
  double centre_error_mm = std::numeric_limits<double>::quiet_NaN();
  // Largest over the joint's fitted axes; NaN for joints without fitted axes.
  double axis_error_deg = std::numeric_limits<double>::quiet_NaN();
  std::vector<AxisDifference> axes;  // one per fitted axis
  // The alignments the centre was measured through: "femur_l+tibia_l", "femur_l",
  // "union(humerus_l,forearm_l)" or "unaligned(humerus_l)".
  std::string basis;
};

struct SegmentDifference {
  std::string name;     // "femur_l->knee_l", or "pelvis:hip_l-hip_r" on the root segment
  std::string segment;
  std::string from;     // proximal joint (or first child joint on the root segment)
  std::string to;       // distal child joint
  double length_a_mm = 0.0;
  double length_b_mm = 0.0;
  double error_pct = std::numeric_limits<double>::quiet_NaN();  // 100 (B - A) / A, signed
};

struct MarkerDifference {
  std::string marker;
  std::string segment;
  double error_mm = 0.0;
  bool aligned = false;  // false: the segment has < 3 usable markers, compared in its own frame
};

struct ModelComparison {
  // Over all joints / fitted axes / lengths (|error_pct|) / markers.
  ErrorStats joint_centre_error_mm, axis_error_deg, segment_length_error_pct, marker_error_mm;
  std::vector<JointDifference> joints;      // in A's joint order, root skipped
  std::vector<SegmentDifference> segments;  // in A's segment order
  std::vector<MarkerDifference> markers;    // markers in both models, in A's order
  std::vector<std::string> markers_only_in_a, markers_only_in_b;  // ignored by the comparison
};

// The element of a joint with exactly one moving rotation (a hinge, or OpenSim's knee whose
// translations follow its angle), or -1 (also for the root). Its centre's offset along that axis
// is a gauge for marker data even with translations: shifting the centre by d along the axis a
// and the child's markers and child joints by -d (a is fixed in both frames, R(q) a = a) leaves
// every marker where it was.
int AlongAxisGaugeElement(const Joint& joint);

// A is the reference (e.g. the truth). Fails, naming the first mismatch, unless both models have
// the same segments, coordinates and joints (by name; same parent, child, type and elements) and
// every marker in both models sits on the same segment in both.
Status CompareModels(const Model& a, const Model& b, ModelComparison* out);

// The comparison as one JSON object: the four ErrorStats as {"max", "rms", "count"}, "joints",
// "segments", "markers", "markers_only_in_a", "markers_only_in_b". NaN fields are omitted.
std::string ComparisonToJsonString(const ModelComparison& comparison);

}  // namespace mocap
