// The virtual subject's motion generator, shared by the recorded session (sim/simulate.h: every
// movement of the protocol one after the other, sampled at the trial rate) and the live subject
// (sim/live_scene.h: one movement at a time, when the operator asks, evaluated at whatever time a
// camera takes its image). The model of the motion is described in sim/simulate.h; here it is
// split so that a movement's coordinates are a function of time (MovementPlan::Coordinates) and
// the feet's contact with the floor a function of one pose (SoleContact), which is what the live
// subject needs: SimulateSession could integrate frame after frame, a camera thread cannot.
//
// Units inside a plan are those of the protocol: rotational channels in DEGREES, translations in
// metres; Coordinates() converts to the model's z (radians, metres).
#pragma once
#include <Eigen/Core>
#include <cmath>
#include <vector>

#include "model/kinematics.h"
#include "model/model.h"
#include "model/status.h"
#include "sim/protocol.h"

namespace mocap::sim {

struct SimulationOptions;

// Two sinusoids of random phase: a slow one and a faster one; |value| <= amplitude.
struct Wander {
  double a1 = 0, w1 = 0, p1 = 0, a2 = 0, w2 = 0, p2 = 0;
  double At(double t) const { return a1 * std::sin(w1 * t + p1) + a2 * std::sin(w2 * t + p2); }
};

// C2 ramp from 0 (x <= 0) to 1 (x >= 1): the quintic 6x^5 - 15x^4 + 10x^3.
double Smootherstep(double x);

// One coordinate's motion during a movement (angles in degrees, translations in metres).
struct Channel {
  double neutral = 0.0;
  Wander wander;
  bool excited = false;
  double centre = 0.0, amplitude = 0.0, sign = 1.0;  // of the excitation
  double omega = 0.0, phase = 0.0;                   // of s(t), shared with the leader
  double t0 = 0.0, t1 = 0.0, ramp = 1.0;             // window and its ramps, seconds
  // How far the excursion from neutral goes: 1 reaches the protocol's range (with its margin),
  // 0.4 is a subject who does 40 % of what was asked.
  double gain = 1.0;

  double Envelope(double t) const {
    if (!excited || t <= t0 || t >= t1) return 0.0;
    return Smootherstep((t - t0) / ramp) * Smootherstep((t1 - t) / ramp);
  }
  double At(double t) const {
    const double w = wander.At(t);
    if (!excited) return neutral + w;
    const double env = Envelope(t);
    const double s = std::sin(omega * (t - t0) + phase);
    return neutral + (1.0 - env) * w + env * gain * (centre - neutral + sign * amplitude * s);
  }
};

// Where the simulator finds the pelvis in the model: the root joint must start with translations
// along the lab's x, y, z (so a world offset of the body is a change of those three coordinates).
struct RootLayout {
  int tx = -1, ty = -1, tz = -1;
  int yaw = -1;  // the root's rotation about z, if any: the direction the subject faces
  std::vector<int> feet;  // segments whose name starts with "foot": the floor contact
};

Status FindRootLayout(const Model& model, RootLayout* layout);

// One movement's motion. Local time t = 0 is the movement's first frame, span_s its last.
struct MovementPlan {
  int frames = 0;
  double span_s = 0.0;            // (frames - 1) / rate
  std::vector<Channel> channels;  // per model coordinate; the root translations are not used
  double base_x = 0.0, base_y = 0.0;
  Wander sway_x, sway_y;

  // The model's z at local time t (radians, metres), the root translations set to 0 (the floor
  // contact places them); any t, also outside [0, span_s] (the subject then stands in the neutral
  // pose with its wander). Writes into *z, which must have the model's size: no allocation.
  void Coordinates(const Model& model, double t, Eigen::VectorXd* z) const;
  // The planned horizontal position of the pelvis (base + sway) at local time t.
  Eigen::Vector2d Sway(double t) const {
    return {base_x + sway_x.At(t), base_y + sway_y.At(t)};
  }
};

// Plans movement `index` of a protocol: the same options and index give the same plan (its own
// random stream). `amplitude` multiplies every excited coordinate's excursion from neutral.
// Requires a movement validated against the model (ValidateProtocol).
MovementPlan PlanMovement(const Model& model, const RootLayout& root, const Movement& movement,
                          const SimulationOptions& options, int index, double amplitude = 1.0);

// The soles' heel and toe points, and where each stands in the neutral pose. The independent
// segment scales give the virtual subject a leg-length difference of several centimetres, so in
// the neutral pose one foot is higher than the other; each point's height is measured from its
// own neutral height (its baseline), so "the foot that carries the weight" means the one raised
// least from where it stands, not simply the one on the longer leg.
struct FootContacts {
  std::vector<Eigen::Vector3d> point;  // in the foot frame, scaled
  std::vector<int> segment;
  std::vector<double> baseline;  // neutral-pose height above the lowest neutral point
  int size() const { return static_cast<int>(point.size()); }
};

FootContacts MakeFootContacts(const Model& truth, const Geometry& geometry, const RootLayout& root,
                              double height_m);

// The floor contact of a pose posed with zero root translation (`data` after ForwardKinematics):
// writes each sole point's world position to point[i] and its share of the weight to weight[i]
// (a soft minimum over the heights above the baselines, summing to 1), and returns the soft
// lowest height: the pelvis height that puts the feet on the floor is minus that. No allocation.
double SoleContact(const FootContacts& feet, const ModelData& data, Eigen::Vector3d* point,
                   double* weight);

// How far the feet's weighted contact point has moved since the first frame, accumulated frame by
// frame (the trapezoidal sum of the sole points' displacements weighted by their share of the
// weight): the pelvis moves back by that much, so the foot that carries the weight does not
// skate when the other leg swings or the knees bend.
class StanceDrift {
 public:
  explicit StanceDrift(int points) : point_(points), weight_(points) {}
  // Feeds the next frame's SoleContact output; returns the drift so far. No allocation.
  Eigen::Vector2d Add(const Eigen::Vector3d* point, const double* weight);

 private:
  std::vector<Eigen::Vector3d> point_;  // the previous frame's
  std::vector<double> weight_;
  Eigen::Vector2d anchor_ = Eigen::Vector2d::Zero(), anchor0_ = Eigen::Vector2d::Zero();
  bool first_ = true;
};

}  // namespace mocap::sim
