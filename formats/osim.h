// OpenSim models (.osim) in and out.
//
// Import reads an OpenSim 4.x document (and 3.x where the differences are small: joints inside
// bodies with location_in_parent / orientation_in_parent / location / orientation, coordinates in
// a CoordinateSet, markers with <body>) into our Model (model/model.h):
//
//   BodySet       one segment per Body (3.x: the Body named "ground" is the ground).
//   JointSet      one joint per OpenSim joint. OpenSim places a child body B_C at
//                   X_G,B_C = X_G,B_P  X_B_P,F  X_F,M(q)  X_B_C,M^-1
//                 where F is the joint's parent frame (a PhysicalOffsetFrame on the parent body:
//                 translation + orientation as body-fixed X-Y-Z Euler angles, OpenSim's
//                 OffsetFrame / SimTK Rotation::setRotationToBodyFixedXYZ) and M its child frame on
//                 the child body. Our segment frame is M (its origin is the joint centre), so
//                 everything fixed on an OpenSim body (its markers, the parent frames of its child
//                 joints) is re-expressed in M: p_M = R_BM^T (p_B - t_BM). OpenSim scales a body
//                 by multiplying every location on it (markers, t_BM, child joint offsets) by s;
//                 with a uniform s the re-expression is linear in those locations, so
//                 R^T (s p - s t) = s R^T (p - t): scaling in our frame M is the same scaling.
//   X_F,M(q)      CustomJoint: Simbody's FunctionBased mobilizer (what CustomJoint builds) is
//                 X_FM = [R1(v1) R2(v2) R3(v3), sum_i v_{3+i} a_{3+i}]: three rotations about
//                 body-fixed axes (each in the frame after the previous rotations), translations
//                 along axes fixed in F. As elements: translation1..3, then rotation1..3.
//                 Elements whose function is the constant 0 are left out.
//                 PinJoint: rotation about z. UniversalJoint: x then y. BallJoint and GimbalJoint:
//                 body-fixed x, y, z. FreeJoint: translation x, y, z in F, then rotation x, y, z.
//                 SliderJoint: translation along x. PlanarJoint: translation x, y, rotation z.
//                 WeldJoint: no element.
//   functions     Constant, LinearFunction, SimmSpline, NaturalCubicSpline, PolynomialFunction,
//                 MultiplierFunction, PiecewiseLinearFunction, GCVSpline with error variance 0
//                 (model/coordinate_function.h). Others (StepFunction, Sine, a smoothing
//                 GCVSpline) are refused with the element and line.
//   Coordinates   default_value and range; a locked coordinate becomes a constant (its value
//                 kept as a derived coordinate). CoordinateCouplerConstraint (dependent =
//                 scale_factor * f(independent)): the dependent coordinate's elements are driven
//                 by the independent coordinate through the composed function; the dependent one
//                 is a DerivedCoordinate. Couplers with several independent coordinates are
//                 refused. Other constraints are listed in `ignored`.
//   MarkerSet     every marker (fixed or not, virtual ones such as *_HJC included), none optional.
//   Everything else (geometry, wrap objects, forces, muscles, controllers) is read past and kept
//   in the document for export.
//
// Joint types: PinJoint -> hinge, UniversalJoint -> universal (their axes are fitted parameters);
// BallJoint/GimbalJoint -> spherical; FreeJoint -> free; CustomJoint by what its elements are
// (three rotations: spherical; three translations and three rotations: free; one moving rotation
// and nothing else: hinge; two moving rotations and nothing else: universal; otherwise custom).
// A CustomJoint's single moving rotation, and a universal-like CustomJoint's two rotations, are
// fitted axes too (the knee of gait2354 keeps its spline translations).
//
// Export writes a fitted Model (same segments and joints as the import, e.g. after
// Model::WithParameters) into the imported document: body scales baked into every location
// (OpenSim's convention: the body frame keeps its place relative to the scaled geometry, so
// X_B,M becomes (R_BM, s t_BM)), joint frames (offset translations and orientations), fitted
// axes (a CustomJoint's TransformAxis <axis>; a PinJoint by turning both its frames by Q with
// Q z = axis; a UniversalJoint whose axes moved becomes a CustomJoint), translation functions
// scaled with the parent as MultiplierFunction (as OpenSim's Scale tool does), marker locations,
// and body mass properties (mass kept, mass_center * s, inertia * s^2), attached geometry
// scale_factors and path point locations * s. Importing the export gives the same kinematics.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <map>
#include <string>
#include <vector>

#include "model/model.h"
#include "model/status.h"

namespace mocap::formats {

enum class OsimMotion { kRotational, kTranslational, kCoupled };

// Per model joint: where it came from.
struct OsimJointInfo {
  std::string type;  // "CustomJoint", "PinJoint", ...
  int line = 0;      // of the joint element in the document
  // X_B,F and X_B,M of the parent and child frames in their (unscaled) OpenSim bodies.
  Eigen::Isometry3d parent_offset = Eigen::Isometry3d::Identity();
  Eigen::Isometry3d child_offset = Eigen::Isometry3d::Identity();
  // Per model element: CustomJoint TransformAxis 0..5 (rotation1..3, translation1..3); for the
  // other joint types the index of the joint's own coordinate that drives it.
  std::vector<int> element_axis;
};

struct OsimImport {
  Model model;
  std::string source;  // file name used in messages
  int version = 0;     // OpenSimDocument Version (30000 for 3.0, 40000 for 4.0)
  std::string xml;     // the document (with any marker sets merged in), what export edits
  std::vector<OsimJointInfo> joints;  // per model joint, model order
  // OpenSim's motion type of every coordinate (model and derived), by name: rotational ones are
  // written in degrees in a .mot.
  std::map<std::string, OsimMotion> motion;
  // Elements read but not used, e.g. "ConstraintSet: WeldConstraint 'w' (line 812)".
  std::vector<std::string> ignored;
};

// Errors name the file, the element and its line: "m.osim:123: CustomJoint 'knee_r': ...".
Status ImportOsim(const std::string& path, OsimImport* out);
Status ImportOsimText(const std::string& text, const std::string& source, OsimImport* out);

// Adds the markers of a MarkerSet file (OpenSim 3.x or 4.x; a marker already in the model is
// replaced) to an imported model, and to its document for export.
Status LoadOsimMarkerSet(const std::string& path, OsimImport* import);

// The fitted model written into the imported document (see the header comment). `fitted` must
// have the import's segments and joints (names, order, elements); its markers may be a subset.
Status ExportOsimText(const Model& fitted, const OsimImport& import, std::string* xml);
Status ExportOsim(const Model& fitted, const OsimImport& import, const std::string& path);

// Every OpenSim coordinate (model coordinates, then derived ones) for each pose: row f of
// `poses` is z at times[f]. Rotational coordinates (OpenSim's motion type) in degrees, others as
// they are (metres, or radians for coupled ones), inDegrees=yes, as OpenSim's IK writes.
Status WriteOsimMot(const std::string& path, const OsimImport& import, const Model& model,
                    const std::vector<double>& times, const Eigen::MatrixXd& poses);

}  // namespace mocap::formats
