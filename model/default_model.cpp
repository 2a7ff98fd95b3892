#include "model/default_model.h"

#include <cmath>

namespace mocap {
namespace {

using V3 = Eigen::Vector3d;

// The right side mirrors the left through the sagittal plane (y -> -y). A rotation axis is a
// pseudo-vector, so it mirrors as (x, y, z) -> (-x, y, -z).
V3 MirrorPoint(const V3& p) { return {p.x(), -p.y(), p.z()}; }
V3 MirrorAxis(const V3& a) { return {-a.x(), a.y(), -a.z()}; }

struct Builder {
  std::vector<Segment> segments;
  std::vector<Joint> joints;
  std::vector<Coordinate> coordinates;
  std::vector<Marker> markers;

  int AddSegment(const std::string& name) {
    segments.push_back({name, 1.0, -1});
    return static_cast<int>(segments.size()) - 1;
  }
  int AddCoordinate(const std::string& name, bool rotational, double lo, double hi) {
    Coordinate c;
    c.name = name;
    c.rotational = rotational;
    c.min_value = lo;
    c.max_value = hi;
    coordinates.push_back(c);
    return static_cast<int>(coordinates.size()) - 1;
  }
  void AddElement(Joint* j, ElementKind kind, const V3& axis, const std::string& coord,
                  bool fitted, double lo, double hi) {
    JointElement el;
    el.kind = kind;
    el.axis = axis.normalized();
    el.coordinate = AddCoordinate(coord, kind == ElementKind::kRotation, lo, hi);
    el.fitted_axis = fitted;
    j->elements.push_back(el);
  }
  void AddMarker(const std::string& name, int segment, const V3& p, bool optional = false) {
    Marker m;
    m.name = name;
    m.segment = segment;
    m.position = p;
    m.optional = optional;
    markers.push_back(m);
  }
};

constexpr double kDeg = M_PI / 180.0;

}  // namespace

Model DefaultFullBodyModel(double height_m) {
  const double k = height_m / 1.75;  // every length below is for a 1.75 m adult
  Builder b;
  const auto rot = ElementKind::kRotation;
  const auto tra = ElementKind::kTranslation;

  // Pelvis: origin between the hip joint centres' level and the ASIS, free joint to the lab.
  const int pelvis = b.AddSegment("pelvis");
  {
    Joint j;
    j.name = "ground_pelvis";
    j.type = JointType::kFree;
    j.parent = -1;
    j.child = pelvis;
    b.AddElement(&j, tra, V3::UnitX(), "pelvis_tx", false, -10, 10);
    b.AddElement(&j, tra, V3::UnitY(), "pelvis_ty", false, -10, 10);
    b.AddElement(&j, tra, V3::UnitZ(), "pelvis_tz", false, -10, 10);
    b.AddElement(&j, rot, V3::UnitZ(), "pelvis_rotation", false, -2 * M_PI, 2 * M_PI);
    b.AddElement(&j, rot, -V3::UnitY(), "pelvis_tilt", false, -M_PI / 2, M_PI / 2);
    b.AddElement(&j, rot, V3::UnitX(), "pelvis_list", false, -M_PI / 2, M_PI / 2);
    // Standing: ankle centres about 9 cm above the floor, heel markers just above it.
    b.coordinates[j.elements[2].coordinate].default_value = 1.02 * k;
    b.joints.push_back(j);
  }
  b.AddMarker("LASI", pelvis, V3(0.070, 0.120, 0.000) * k);
  b.AddMarker("RASI", pelvis, V3(0.070, -0.120, 0.000) * k);
  b.AddMarker("LPSI", pelvis, V3(-0.100, 0.045, 0.020) * k);
  b.AddMarker("RPSI", pelvis, V3(-0.100, -0.045, 0.020) * k);

  // Torso (abdomen + thorax), lumbar spherical joint at L5/S1.
  const int torso = b.AddSegment("torso");
  {
    Joint j;
    j.name = "lumbar";
    j.type = JointType::kSpherical;
    j.parent = pelvis;
    j.child = torso;
    j.centre = V3(-0.040, 0.0, 0.060) * k;
    b.AddElement(&j, rot, -V3::UnitY(), "lumbar_extension", false, -90 * kDeg, 90 * kDeg);
    b.AddElement(&j, rot, V3::UnitX(), "lumbar_bending", false, -90 * kDeg, 90 * kDeg);
    b.AddElement(&j, rot, V3::UnitZ(), "lumbar_rotation", false, -90 * kDeg, 90 * kDeg);
    b.joints.push_back(j);
  }
  b.AddMarker("C7", torso, V3(-0.060, 0.000, 0.470) * k);
  b.AddMarker("T10", torso, V3(-0.090, 0.000, 0.220) * k);
  b.AddMarker("CLAV", torso, V3(0.090, 0.000, 0.410) * k);
  b.AddMarker("STRN", torso, V3(0.130, 0.000, 0.260) * k);
  b.AddMarker("RBAK", torso, V3(-0.100, -0.080, 0.330) * k);
  b.AddMarker("LSHO", torso, V3(-0.010, 0.190, 0.455) * k);
  b.AddMarker("RSHO", torso, V3(-0.010, -0.190, 0.455) * k);

  const int head = b.AddSegment("head");
  {
    Joint j;
    j.name = "neck";
    j.type = JointType::kSpherical;
    j.parent = torso;
    j.child = head;
    j.centre = V3(0.000, 0.0, 0.500) * k;
    b.AddElement(&j, rot, -V3::UnitY(), "neck_extension", false, -90 * kDeg, 90 * kDeg);
    b.AddElement(&j, rot, V3::UnitX(), "neck_bending", false, -90 * kDeg, 90 * kDeg);
    b.AddElement(&j, rot, V3::UnitZ(), "neck_rotation", false, -90 * kDeg, 90 * kDeg);
    b.joints.push_back(j);
  }
  b.AddMarker("LFHD", head, V3(0.090, 0.065, 0.130) * k);
  b.AddMarker("RFHD", head, V3(0.090, -0.065, 0.130) * k);
  b.AddMarker("LBHD", head, V3(-0.080, 0.065, 0.110) * k);
  b.AddMarker("RBHD", head, V3(-0.080, -0.065, 0.110) * k);

  for (int side = 0; side < 2; ++side) {
    const bool left = side == 0;
    const std::string s = left ? "l" : "r";
    const std::string P = left ? "L" : "R";
    auto pt = [&](const V3& p) { return left ? V3(p * k) : MirrorPoint(p * k); };
    auto ax = [&](const V3& a) { return left ? a : MirrorAxis(a); };

    // Leg.
    const int femur = b.AddSegment("femur_" + s);
    {
      Joint j;
      j.name = "hip_" + s;
      j.type = JointType::kSpherical;
      j.parent = pelvis;
      j.child = femur;
      j.centre = pt(V3(0.024, 0.086, -0.072));
      b.AddElement(&j, rot, ax(-V3::UnitY()), "hip_flexion_" + s, false, -120 * kDeg, 120 * kDeg);
      b.AddElement(&j, rot, ax(-V3::UnitX()), "hip_adduction_" + s, false, -90 * kDeg, 90 * kDeg);
      b.AddElement(&j, rot, ax(-V3::UnitZ()), "hip_rotation_" + s, false, -90 * kDeg, 90 * kDeg);
      b.joints.push_back(j);
    }
    b.AddMarker(P + "THI", femur, pt(V3(0.030, 0.070, -0.220)));
    b.AddMarker(P + "KNE", femur, pt(V3(0.000, 0.050, -0.430)));
    b.AddMarker(P + "KNM", femur, pt(V3(0.000, -0.050, -0.430)), true);

    const int tibia = b.AddSegment("tibia_" + s);
    {
      Joint j;
      j.name = "knee_" + s;
      j.type = JointType::kHinge;
      j.parent = femur;
      j.child = tibia;
      j.centre = pt(V3(0.000, 0.000, -0.430));
      b.AddElement(&j, rot, ax(V3::UnitY()), "knee_angle_" + s, true, -10 * kDeg, 160 * kDeg);
      b.joints.push_back(j);
    }
    b.AddMarker(P + "TIB", tibia, pt(V3(0.030, 0.055, -0.220)));
    b.AddMarker(P + "ANK", tibia, pt(V3(0.000, 0.040, -0.430)));
    b.AddMarker(P + "MMA", tibia, pt(V3(0.005, -0.035, -0.420)), true);

    const int foot = b.AddSegment("foot_" + s);
    {
      Joint j;
      j.name = "ankle_" + s;
      j.type = JointType::kUniversal;
      j.parent = tibia;
      j.child = foot;
      j.centre = pt(V3(0.000, 0.000, -0.430));
      b.AddElement(&j, rot, ax(-V3::UnitY()), "ankle_angle_" + s, true, -60 * kDeg, 60 * kDeg);
      b.AddElement(&j, rot, ax(V3(0.78, 0.0, 0.62)), "subtalar_angle_" + s, true, -60 * kDeg,
                   60 * kDeg);
      b.joints.push_back(j);
    }
    b.AddMarker(P + "HEE", foot, pt(V3(-0.065, 0.000, -0.045)));
    b.AddMarker(P + "TOE", foot, pt(V3(0.140, 0.010, -0.055)));

    // Arm.
    const int humerus = b.AddSegment("humerus_" + s);
    {
      Joint j;
      j.name = "shoulder_" + s;
      j.type = JointType::kSpherical;
      j.parent = torso;
      j.child = humerus;
      j.centre = pt(V3(-0.010, 0.175, 0.420));
      b.AddElement(&j, rot, ax(-V3::UnitY()), "arm_flex_" + s, false, -180 * kDeg, 180 * kDeg);
      b.AddElement(&j, rot, ax(-V3::UnitX()), "arm_add_" + s, false, -180 * kDeg, 180 * kDeg);
      b.AddElement(&j, rot, ax(-V3::UnitZ()), "arm_rot_" + s, false, -180 * kDeg, 180 * kDeg);
      b.joints.push_back(j);
    }
    b.AddMarker(P + "UPA", humerus, pt(V3(-0.030, 0.045, -0.160)));
    b.AddMarker(P + "ELB", humerus, pt(V3(0.000, 0.040, -0.300)));

    const int forearm = b.AddSegment("forearm_" + s);
    {
      Joint j;
      j.name = "elbow_" + s;
      j.type = JointType::kUniversal;
      j.parent = humerus;
      j.child = forearm;
      j.centre = pt(V3(0.000, 0.000, -0.300));
      b.AddElement(&j, rot, ax(-V3::UnitY()), "elbow_flex_" + s, true, -10 * kDeg, 160 * kDeg);
      b.AddElement(&j, rot, ax(-V3::UnitZ()), "pro_sup_" + s, true, -100 * kDeg, 100 * kDeg);
      b.joints.push_back(j);
    }
    b.AddMarker(P + "FRM", forearm, pt(V3(0.000, 0.040, -0.120)));
    b.AddMarker(P + "WRA", forearm, pt(V3(0.035, 0.005, -0.250)));
    b.AddMarker(P + "WRB", forearm, pt(V3(-0.035, 0.005, -0.250)));

    const int hand = b.AddSegment("hand_" + s);
    {
      Joint j;
      j.name = "wrist_" + s;
      j.type = JointType::kUniversal;
      j.parent = forearm;
      j.child = hand;
      j.centre = pt(V3(0.000, 0.000, -0.255));
      b.AddElement(&j, rot, ax(-V3::UnitY()), "wrist_flex_" + s, true, -90 * kDeg, 90 * kDeg);
      b.AddElement(&j, rot, ax(-V3::UnitX()), "wrist_dev_" + s, true, -60 * kDeg, 60 * kDeg);
      b.joints.push_back(j);
    }
    b.AddMarker(P + "FIN", hand, pt(V3(0.020, 0.010, -0.080)));
  }

  Model model;
  Status status = Model::Build("default_full_body", b.segments, b.joints, b.coordinates,
                               b.markers, &model);
  (void)status;  // a fixed, known-valid description; tests/test_model.cpp checks it builds
  return model;
}

}  // namespace mocap
