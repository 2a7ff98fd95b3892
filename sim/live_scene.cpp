#include "sim/live_scene.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>

#include "sim/simulate.h"

namespace mocap::sim {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
// The schedule keeps this many phases (the past ones for the truth of recent frames); older
// phases are forgotten (the volume was empty before the oldest one kept).
constexpr std::size_t kMaxPhases = 64;
// Blends nest when commands come faster than blend_s; deeper ones start from the older phase's
// own motion (a small step, only for commands less than blend_s / kMaxBlendDepth apart).
constexpr int kMaxBlendDepth = 4;
constexpr double kMaxCommandDuration = 3600.0;
// A subject standing still steps back onto the mark in this time.
constexpr double kReturnToMarkS = 1.5;

std::string Show(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%g", v);
  return buf;
}

bool IsSubject(LiveActivity a) { return a == LiveActivity::kStatic || a == LiveActivity::kMovement; }

}  // namespace

// One subject phase's motion: the plan in local time (0 at `begin`), and the pelvis's horizontal
// correction (minus the stance drift, continuing the previous phase's) at the frame rate from
// `begin`, held after its last sample.
struct LiveScene::SubjectTrack {
  MovementPlan plan;
  double begin = 0.0;
  double blend_s = 0.0;  // the previous phase fades out over this time
  double rate_hz = 1.0;
  std::vector<Eigen::Vector2d> correction;

  Eigen::Vector2d CorrectionAt(double t) const {
    if (correction.empty()) return Eigen::Vector2d::Zero();
    const double x = std::max(0.0, (t - begin) * rate_hz);
    const std::size_t last = correction.size() - 1;
    if (x >= static_cast<double>(last)) return correction[last];
    const std::size_t i = static_cast<std::size_t>(x);
    const double w = x - static_cast<double>(i);
    return correction[i] + w * (correction[i + 1] - correction[i]);
  }
};

struct LiveScene::Phase {
  LiveActivity activity = LiveActivity::kEmpty;
  double begin = -std::numeric_limits<double>::infinity();
  int movement = -1;        // kMovement: index in the protocol
  double wand_time = 0.0;   // kWand: the path's time at `begin`
  std::shared_ptr<const SubjectTrack> track;  // kStatic, kMovement
};

struct LiveScene::Workspace {
  explicit Workspace(const Model& model, int sole_points)
      : data(model), z(model.num_coordinates()), point(sole_points), weight(sole_points) {
    for (Eigen::VectorXd& v : own) v.resize(model.num_coordinates());
  }
  ModelData data;
  Eigen::VectorXd z;
  Eigen::Vector3d offset = Eigen::Vector3d::Zero();
  Eigen::VectorXd own[kMaxBlendDepth + 1];
  std::vector<Eigen::Vector3d> point;
  std::vector<double> weight;
};

const char* ToString(LiveActivity activity) {
  switch (activity) {
    case LiveActivity::kEmpty: return "empty";
    case LiveActivity::kWand: return "wand";
    case LiveActivity::kLFrame: return "lframe";
    case LiveActivity::kStatic: return "static";
    case LiveActivity::kMovement: return "movement";
  }
  return "?";
}

bool LiveSceneOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& what) {
    if (error) *error = "live scene options: " + what;
    return false;
  };
  std::string e;
  if (!subject.IsValid(&e)) return fail("subject." + e);
  if (!(std::isfinite(rate_hz) && rate_hz > 0 && rate_hz <= 10000))
    return fail("rate_hz must be in (0, 10000] (got " + Show(rate_hz) + ")");
  if (!(command_lead_s >= 0 && command_lead_s <= 10))
    return fail("command_lead_s must be in [0, 10] (got " + Show(command_lead_s) + ")");
  if (!(blend_s > 0 && blend_s <= 10))
    return fail("blend_s must be in (0, 10] (got " + Show(blend_s) + ")");
  if (!wand.IsValid(&e)) return fail("wand: " + e);
  if (!lframe.IsValid(&e)) return fail("lframe: " + e);
  if (!wand_volume_centre_m.allFinite() || !wand_volume_half_size_m.allFinite() ||
      !(wand_volume_half_size_m.minCoeff() > 0))
    return fail("the wand's volume must be finite with positive half sizes");
  return true;
}

Status LiveScene::Create(const LiveSceneOptions& options, std::shared_ptr<LiveScene>* scene) {
  std::string error;
  if (!options.IsValid(&error)) return Status::Error(error);
  std::shared_ptr<LiveScene> s(new LiveScene());
  s->options_ = options;
  s->protocol_ = options.protocol ? *options.protocol : DefaultProtocol();
  VirtualSubject subject;
  MOCAP_RETURN_IF_ERROR(MakeVirtualSubject(options.seed, options.subject, &subject));
  if (Status st = ValidateProtocol(s->protocol_, subject.truth); !st) return st;
  const std::vector<int> markers = SimulatedMarkers(subject.truth, options.medial_markers);
  SessionModels models;
  MOCAP_RETURN_IF_ERROR(MakeSessionModels(subject, markers, &models));
  s->truth_ = std::move(models.truth);
  s->nominal_ = std::move(models.nominal);
  s->truth_parameters_ = std::move(models.truth_parameters);
  s->height_m_ = subject.height_m;
  if (Status st = FindRootLayout(s->truth_, &s->root_); !st) return st;
  s->geometry_ = Geometry(s->truth_);
  s->feet_ = MakeFootContacts(s->truth_, s->geometry_, s->root_, s->height_m_);
  s->wand_path_ = std::make_unique<WandPath>(options.seed, options.wand_volume_centre_m,
                                             options.wand_volume_half_size_m, options.wand);
  s->lframe_begin_ = s->truth_.num_markers() + 3;

  // The static pose: the protocol's movement without excitations (planned as SimulateSession
  // plans it), or the neutral pose with a little wander.
  SimulationOptions plan_options;
  plan_options.seed = options.seed;
  plan_options.rate_hz = options.rate_hz;
  int static_index = -1;
  for (std::size_t i = 0; i < s->protocol_.movements.size() && static_index < 0; ++i)
    if (s->protocol_.movements[i].excitations.empty()) static_index = static_cast<int>(i);
  Movement neutral;
  neutral.name = "static";
  neutral.duration_s = 3.0;
  neutral.background = 0.3;
  const int plan_index =
      static_index >= 0 ? static_index : static_cast<int>(s->protocol_.movements.size());
  s->static_plan_ = PlanMovement(s->truth_, s->root_,
                                 static_index >= 0 ? s->protocol_.movements[static_index] : neutral,
                                 plan_options, plan_index);
  s->static_plan_.base_x = s->static_plan_.base_y = 0.0;
  if (s->root_.yaw >= 0) s->static_plan_.channels[s->root_.yaw].neutral = 0.0;

  s->schedule_ = std::make_unique<Schedule>();
  s->schedule_->reserve(kMaxPhases + 4);
  s->schedule_->push_back(Phase());  // empty since the beginning of time
  s->workspace_ = std::make_unique<Workspace>(s->truth_, s->feet_.size());
  s->cache_.assign(s->marker_count(), Eigen::Vector3d::Zero());
  *scene = std::move(s);
  return Status::Ok();
}

LiveScene::~LiveScene() = default;

// ---- The clock ----

double LiveScene::SceneTimeNow() const {
  const std::uint64_t ns =
      options_.clock_ns ? options_.clock_ns()
                        : static_cast<std::uint64_t>(
                              std::chrono::duration_cast<std::chrono::nanoseconds>(
                                  std::chrono::system_clock::now().time_since_epoch())
                                  .count());
  // In frames first (as drivers::SequenceOfTimestamp): the origin is a frame count.
  const long double frames = static_cast<long double>(ns) * options_.rate_hz / 1e9L -
                             static_cast<long double>(options_.sequence_origin);
  return static_cast<double>(frames / options_.rate_hz);
}

double LiveScene::SceneTimeOf(std::uint64_t sequence) const {
  return static_cast<double>(static_cast<std::int64_t>(sequence - options_.sequence_origin)) /
         options_.rate_hz;
}

// ---- Evaluation ----

int LiveScene::PhaseAt(const Schedule& schedule, double t) {
  for (int k = static_cast<int>(schedule.size()) - 1; k >= 0; --k)
    if (schedule[k].begin <= t) return k;
  return -1;  // before the oldest phase kept: empty
}

Eigen::Vector2d LiveScene::BlendedPose(const Schedule& schedule, int k, double t, int depth,
                                       Workspace* ws) const {
  const Phase& phase = schedule[k];
  const MovementPlan& plan = phase.track->plan;
  const double local = t - phase.begin;
  Eigen::VectorXd& own = ws->own[depth];
  plan.Coordinates(truth_, local, &own);
  Eigen::Vector2d sway = plan.Sway(local);
  if (depth < kMaxBlendDepth && k > 0 && IsSubject(schedule[k - 1].activity) &&
      local < phase.track->blend_s) {
    const Eigen::Vector2d before = BlendedPose(schedule, k - 1, t, depth + 1, ws);
    const Eigen::VectorXd& previous = ws->own[depth + 1];
    const double b = Smootherstep(local / phase.track->blend_s);
    own = previous + b * (own - previous);  // coefficient-wise: no aliasing, no temporary
    sway = before + b * (sway - before);
  }
  return sway;
}

void LiveScene::EvaluateSubject(const Schedule& schedule, int k, double t, Workspace* ws) const {
  const Eigen::Vector2d sway = BlendedPose(schedule, k, t, 0, ws);
  Eigen::VectorXd& z = ws->z;
  z = ws->own[0];
  z[root_.tx] = z[root_.ty] = z[root_.tz] = 0.0;
  ForwardKinematics(truth_, geometry_, z, &ws->data);
  const Eigen::Vector2d horizontal = sway + schedule[k].track->CorrectionAt(t);
  double height = truth_.coordinates()[root_.tz].default_value;
  if (feet_.size() > 0) height = -SoleContact(feet_, ws->data, ws->point.data(), ws->weight.data());
  ws->offset = Eigen::Vector3d(horizontal.x(), horizontal.y(), height);
  z[root_.tx] = ws->offset.x();
  z[root_.ty] = ws->offset.y();
  z[root_.tz] = ws->offset.z();
}

void LiveScene::WriteSubjectMarkers(const Workspace& ws, Eigen::Vector3d* out) const {
  // The root translations come first and act along the lab axes (FindRootLayout): adding the
  // offset to the untranslated pose's markers is posing with it.
  for (int m = 0; m < truth_.num_markers(); ++m)
    out[m] = MarkerPosition(truth_, geometry_, ws.data, m) + ws.offset;
}

void LiveScene::Positions(double t, Eigen::Vector3d* out) const {
  const int n = marker_count();
  std::lock_guard<std::mutex> lock(mutex_);
  if (cache_valid_ && cache_time_ == t) {
    std::copy(cache_.begin(), cache_.end(), out);
    return;
  }
  Eigen::Vector3d* p = cache_.data();
  for (int m = 0; m < n; ++m) p[m].setConstant(kNaN);
  const Schedule& schedule = *schedule_;
  const int k = PhaseAt(schedule, t);
  const Phase* phase = k >= 0 ? &schedule[k] : nullptr;
  const LiveActivity activity = phase ? phase->activity : LiveActivity::kEmpty;
  if (IsSubject(activity)) {
    EvaluateSubject(schedule, k, t, workspace_.get());
    WriteSubjectMarkers(*workspace_, p);
  } else if (activity == LiveActivity::kWand) {
    wand_path_->Markers(phase->wand_time + (t - phase->begin), p + wand_marker_begin());
  } else if (activity == LiveActivity::kLFrame) {
    std::copy(options_.lframe.markers_m.begin(), options_.lframe.markers_m.end(),
              p + lframe_begin_);
  }
  cache_valid_ = true;
  cache_time_ = t;
  std::copy(cache_.begin(), cache_.end(), out);
}

LiveActivity LiveScene::ActivityAt(double t) const {
  std::lock_guard<std::mutex> lock(mutex_);
  const int k = PhaseAt(*schedule_, t);
  return k >= 0 ? (*schedule_)[k].activity : LiveActivity::kEmpty;
}

bool LiveScene::TrueCoordinates(double t, Eigen::VectorXd* z) const {
  std::lock_guard<std::mutex> lock(mutex_);
  const int k = PhaseAt(*schedule_, t);
  if (k < 0 || !IsSubject((*schedule_)[k].activity)) return false;
  EvaluateSubject(*schedule_, k, t, workspace_.get());
  *z = workspace_->z;
  return true;
}

bool LiveScene::TrueWandMarkers(double t, std::vector<Eigen::Vector3d>* markers) const {
  std::lock_guard<std::mutex> lock(mutex_);
  const int k = PhaseAt(*schedule_, t);
  if (k < 0 || (*schedule_)[k].activity != LiveActivity::kWand) return false;
  const Phase& phase = (*schedule_)[k];
  markers->resize(3);
  wand_path_->Markers(phase.wand_time + (t - phase.begin), markers->data());
  return true;
}

// ---- Commands ----

void LiveScene::AppendSubject(Schedule* schedule, const MovementPlan& plan, LiveActivity activity,
                              int movement, double begin, int samples, int return_samples) const {
  auto track = std::make_shared<SubjectTrack>();
  track->plan = plan;
  track->begin = begin;
  track->rate_hz = options_.rate_hz;
  // A movement's excitations reach their range after their ramp: the blend ends by then, so it
  // never takes anything from the range a short movement reaches.
  track->blend_s = options_.blend_s;
  for (const Channel& ch : plan.channels)
    if (ch.excited && ch.t0 < track->blend_s) track->blend_s = std::min(track->blend_s, ch.t0 + ch.ramp);
  track->blend_s = std::max(track->blend_s, 1.0 / options_.rate_hz);
  // The correction continues the previous subject phase's (0 when the subject steps in).
  Eigen::Vector2d start = Eigen::Vector2d::Zero();
  if (!schedule->empty() && IsSubject(schedule->back().activity))
    start = schedule->back().track->CorrectionAt(begin);
  Phase phase;
  phase.activity = activity;
  phase.begin = begin;
  phase.movement = movement;
  phase.track = track;
  schedule->push_back(phase);
  // The stance drift over the phase's frames, as SimulateSession integrates it.
  Workspace ws(truth_, feet_.size());
  StanceDrift drift(feet_.size());
  const int k = static_cast<int>(schedule->size()) - 1;
  track->correction.assign(samples + return_samples, start);
  if (feet_.size() == 0) return;
  for (int f = 0; f < samples; ++f) {
    BlendedPose(*schedule, k, begin + f / options_.rate_hz, 0, &ws);
    ws.z = ws.own[0];
    ws.z[root_.tx] = ws.z[root_.ty] = ws.z[root_.tz] = 0.0;
    ForwardKinematics(truth_, geometry_, ws.z, &ws.data);
    SoleContact(feet_, ws.data, ws.point.data(), ws.weight.data());
    track->correction[f] = start - drift.Add(ws.point.data(), ws.weight.data());
  }
  // Back onto the mark: the drifts of the movements add up (a hip arc moves the pelvis by up to
  // 25 cm), and a subject told to stand still returns to where they were asked to stand.
  const Eigen::Vector2d off_mark = samples > 0 ? track->correction[samples - 1] : start;
  for (int f = 0; f < return_samples; ++f)
    track->correction[samples + f] =
        (1.0 - Smootherstep((f + 1.0) / return_samples)) * off_mark;
}

void LiveScene::AppendStatic(Schedule* schedule, double begin) const {
  // The drift is integrated while the pose blends into the static one; after that the subject
  // stands (the static wander moves the feet by a fraction of a millimetre) and steps back onto
  // the mark.
  const int samples = static_cast<int>(std::ceil(options_.blend_s * options_.rate_hz)) + 1;
  const int return_samples = std::max(1, static_cast<int>(std::ceil(kReturnToMarkS * options_.rate_hz)));
  AppendSubject(schedule, static_plan_, LiveActivity::kStatic, -1, begin, samples, return_samples);
}

double LiveScene::Command(const std::function<void(double, Schedule*)>& build) {
  double lead = options_.command_lead_s;
  for (int attempt = 0;; ++attempt) {
    const double ts = SceneTimeNow() + lead;
    auto next = std::make_unique<Schedule>();
    next->reserve(kMaxPhases + 4);
    // Only commands change the schedule, and they hold command_mutex_: reading it here races
    // with nothing but the cameras' reads.
    for (const Phase& p : *schedule_)
      if (p.begin < ts) next->push_back(p);
    build(ts, next.get());
    if (next->size() > kMaxPhases) next->erase(next->begin(), next->end() - kMaxPhases);
    {
      std::lock_guard<std::mutex> lock(mutex_);
      // Building took longer than the lead: a camera may have drawn a frame after ts already.
      if (attempt < 3 && SceneTimeNow() >= ts) {
        lead *= 4.0;
        continue;
      }
      std::swap(schedule_, next);
      cache_valid_ = false;
    }
    return ts;  // the old schedule is freed here, outside the lock
  }
}

double LiveScene::ShowEmpty() {
  std::lock_guard<std::mutex> command(command_mutex_);
  return Command([](double ts, Schedule* s) {
    Phase p;
    p.activity = LiveActivity::kEmpty;
    p.begin = ts;
    s->push_back(p);
  });
}

Status LiveScene::WaveWand(double duration_s, double* start_time_s) {
  if (!(duration_s > 0 && duration_s <= kMaxCommandDuration))
    return Status::Error("WaveWand: duration_s must be in (0, 3600] s (got " + Show(duration_s) +
                         ")");
  std::lock_guard<std::mutex> command(command_mutex_);
  const double wand_time = next_wand_time_;
  const double ts = Command([&](double ts, Schedule* s) {
    Phase wand;
    wand.activity = LiveActivity::kWand;
    wand.begin = ts;
    wand.wand_time = wand_time;
    s->push_back(wand);
    Phase empty;
    empty.begin = ts + duration_s;
    s->push_back(empty);
  });
  next_wand_time_ += duration_s;
  if (start_time_s) *start_time_s = ts;
  return Status::Ok();
}

Status LiveScene::ShowLFrame(double duration_s, double* start_time_s) {
  if (!(duration_s > 0 && duration_s <= kMaxCommandDuration))
    return Status::Error("ShowLFrame: duration_s must be in (0, 3600] s (got " +
                         Show(duration_s) + ")");
  std::lock_guard<std::mutex> command(command_mutex_);
  const double ts = Command([&](double ts, Schedule* s) {
    Phase lframe;
    lframe.activity = LiveActivity::kLFrame;
    lframe.begin = ts;
    s->push_back(lframe);
    Phase empty;
    empty.begin = ts + duration_s;
    s->push_back(empty);
  });
  if (start_time_s) *start_time_s = ts;
  return Status::Ok();
}

double LiveScene::StandStatic() {
  std::lock_guard<std::mutex> command(command_mutex_);
  // The drift is integrated while the pose blends into the static one; after that the subject
  // stands (the static wander moves the feet by a fraction of a millimetre).
  return Command([&](double ts, Schedule* s) { AppendStatic(s, ts); });
}

Status LiveScene::Perform(const std::string& movement, double amplitude, double duration_scale,
                          double* start_time_s, double* end_time_s) {
  const Movement* m = protocol_.Find(movement);
  if (m == nullptr) {
    std::string names;
    for (const Movement& mv : protocol_.movements) names += (names.empty() ? "" : ", ") + mv.name;
    return Status::Error("Perform: unknown movement '" + movement + "'; protocol '" +
                         protocol_.name + "' has: " + names);
  }
  if (!(amplitude >= 0 && amplitude <= 1.5))
    return Status::Error("Perform '" + movement + "': amplitude must be in [0, 1.5] (got " +
                         Show(amplitude) + ")");
  if (!(duration_scale > 0 && duration_scale <= 100))
    return Status::Error("Perform '" + movement + "': duration_scale must be in (0, 100] (got " +
                         Show(duration_scale) + ")");
  const int index = static_cast<int>(m - protocol_.movements.data());
  SimulationOptions plan_options;
  plan_options.seed = options_.seed;
  plan_options.rate_hz = options_.rate_hz;
  plan_options.duration_scale = duration_scale;
  MovementPlan plan = PlanMovement(truth_, root_, *m, plan_options, index, amplitude);
  // The live subject stays on its mark, facing +x.
  plan.base_x = plan.base_y = 0.0;
  if (root_.yaw >= 0) plan.channels[root_.yaw].neutral = 0.0;

  std::lock_guard<std::mutex> command(command_mutex_);
  const double ts = Command([&](double ts, Schedule* s) {
    AppendSubject(s, plan, LiveActivity::kMovement, index, ts, plan.frames, 0);
    AppendStatic(s, ts + plan.span_s);
  });
  if (start_time_s) *start_time_s = ts;
  if (end_time_s) *end_time_s = ts + plan.span_s;
  return Status::Ok();
}

}  // namespace mocap::sim
