// `mocap track`: the real-time tracker (ekf/tracker.h) run offline over unlabelled 3D points —
// a simulated scene with known truth (sim/tracking_scene.h), or a file of unlabelled points as
// `mocap capture` writes them (TRC or C3D, generic names such as P1..Pn, NaN for empty slots).
//
// Writes, in --out DIR:
//   labelled.trc     the model's markers: the point the tracker gave each marker, per frame
//                    (empty where none). It is a labelled trial: `mocap fit` reads it.
//   coordinates.mot  the tracked coordinates (rotations in degrees), NaN in frames where the
//                    tracker was not tracking; `mocap fit --initial` takes it as its start.
//   stats.json       frames, state counts, (re)initialisations, update time percentiles (wall
//                    clock, and the thread's CPU time: on a shared machine the wall clock's tail
//                    is other processes' time slices, the CPU time's the tracker's work), and with
//                    --simulate the scores against the truth: label_accuracy, wrong_labels,
//                    swaps_longer_than_5_frames, marker_rms_mm, joint_angle_rms_deg, ...
//   truth.mot, nominal.model.json, truth.model.json, points.trc
//                    with --simulate: the true coordinates, the subject's nominal and true models
//                    (as `mocap sim` writes them), and (--write-points) the unlabelled points as a
//                    --points file.
//
// A labelled points file (a real recording, its names the model's after --marker-map): the model's
// markers it never shows are the tracker's unseen markers (virtual ones such as R_HJC); with
// --unlabel its labels are removed, each frame's points shuffled and --ghosts added, and
// stats.json scores the tracker's labels against the file's (label_accuracy, wrong_labels,
// swaps_longer_than_5_frames, per_marker_accuracy). --up names the lab's vertical (auto, the
// default: found, sim::FindLabVertical); an OpenSim model's own is Y, ours Z (TrackerOptions::up,
// model_up). A file's frames before the first start are labelled backward from it
// (sim::BackfillBeforeStart; --no-backfill: as live). The model is scaled to the subject at every
// start (--scale-to-subject always, the default; with --calibrate when-needed: the calibrated model
// is the subject's size; TrackerOptions::init_scale_to_subject); stats.json gives the scales
// (segment_scales). --calibrate STATIC first fits the model to a labelled static
// trial of the subject (solver/subject_calibration.h: scales, marker places, the lab's markers the
// model lacks attached) and tracks with that subject model, as a lab labels with a skeleton
// calibrated on a static trial; stats.json's "calibration" says what the fit did.
//
// The model: --model FILE (.json or .osim). With --simulate, also `nominal` (the default: the
// default model scaled to the subject's height, what `mocap sim` writes as nominal.model.json)
// or `truth` (the subject's true model, truth.model.json). With --points the default is the
// default full-body model scaled to --height.
#include <spdlog/spdlog.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <memory>
#include <nlohmann/json.hpp>
#include <sstream>

#include "daemon/capture_pipeline.h"
#include "ekf/tracker.h"
#include "formats/marker_file.h"
#include "formats/mot.h"
#include "formats/trc.h"
#include "model/default_model.h"
#include "model/kinematics.h"
#include "model/model_io.h"
#include "sim/track_run.h"
#include "solver/subject_calibration.h"
#include "sim/tracking_scene.h"
#include "tools/command.h"
#include "tools/trial_inputs.h"

namespace mocap::tools {
namespace {

namespace fs = std::filesystem;

struct TrackArgs {
  std::string model;
  bool simulate = false;
  sim::TrackingSceneOptions scene;
  std::string movements;  // comma-separated
  std::string fault = "none";
  std::string points;
  std::string marker_set, marker_map;
  std::string up = "auto";
  std::string scale_to_subject;  // empty: always, when-needed with --calibrate
  std::string calibrate;  // a labelled static trial: the model is fitted to it first
  int threads = 0;        // the calibration's fit
  bool unlabel = false;
  double height_m = 1.75;
  std::string out;
  bool write_points = false;
  bool no_backfill = false;
};

std::vector<std::string> SplitList(const std::string& list) {
  std::vector<std::string> out;
  std::stringstream ss(list);
  std::string item;
  while (std::getline(ss, item, ','))
    if (!item.empty()) out.push_back(item);
  return out;
}

// TrackingSceneOptions::IsValid names the field; the user typed the flag.
std::string FlagOf(const std::string& message) {
  static const std::pair<const char*, const char*> flags[] = {
      {"rate_hz", "--rate"},         {"noise_mm", "--noise-mm"}, {"duration_scale", "--duration-scale"},
      {"ghosts", "--ghosts"},        {"occlusion", "--occlusion"}, {"fault_time_s", "--fault-time"}};
  for (const auto& [field, flag] : flags)
    if (message.rfind(field, 0) == 0) return std::string(flag) + ": ";
  return "";
}

double WrapAngle(double a) { return std::remainder(a, 2.0 * M_PI); }

const std::pair<const char*, Eigen::Vector3d> kAxes[] = {
    {"x", Eigen::Vector3d::UnitX()},  {"y", Eigen::Vector3d::UnitY()},  {"z", Eigen::Vector3d::UnitZ()},
    {"-x", -Eigen::Vector3d::UnitX()}, {"-y", -Eigen::Vector3d::UnitY()}, {"-z", -Eigen::Vector3d::UnitZ()}};

// "x", "-y", ... as a unit vector.
bool ParseAxis(const std::string& text, Eigen::Vector3d* axis) {
  for (const auto& [name, a] : kAxes)
    if (text == name) {
      *axis = a;
      return true;
    }
  return false;
}
// The other way round.
std::string AxisName(const Eigen::Vector3d& axis) {
  for (const auto& [name, a] : kAxes)
    if (a == axis) return name;
  return "?";
}

int RunTrack(const TrackArgs& args) {
  if (args.simulate == !args.points.empty()) {
    spdlog::error("mocap track: give either --simulate or --points FILE");
    return 2;
  }
  // --- the input: a scene with truth, or a file of points ---
  sim::TrackingScene scene;
  formats::MarkerTrial file;
  if (args.simulate) {
    sim::TrackingSceneOptions o = args.scene;
    o.movements = SplitList(args.movements);
    if (!sim::ParseSceneFault(args.fault, &o.fault)) {
      spdlog::error("mocap track: --fault {}: expected none, all_occluded, leave_reenter, "
                    "second_person or nan_frame", args.fault);
      return 2;
    }
    std::string why;
    if (!o.IsValid(&why)) {
      spdlog::error("mocap track: {}{}", FlagOf(why), why);
      return 2;
    }
    spdlog::info("simulating: seed {}, {} Hz, {} ghosts per frame, occlusion {}, swap traps {}, "
                 "fault {}", o.seed, o.rate_hz, o.ghosts, o.occlusion, o.swap_traps ? "on" : "off",
                 sim::ToString(o.fault));
    if (Status s = sim::MakeTrackingScene(o, &scene); !s) {
      spdlog::error("mocap track: {}", s.message());
      return 2;
    }
  } else if (Status s = formats::ReadMarkerFile(args.points, &file); !s) {
    // Read here for its errors first; read again with the model's names below (LoadTrials).
    spdlog::error("mocap track: {}", s.message());
    return 2;
  } else {
    LogSkippedPoints(args.points, file);
  }

  // --- the model ---
  ModelInput input;
  if (args.model.empty() || args.model == "nominal" || args.model == "truth") {
    if (args.simulate) {
      input.path = args.model.empty() ? "nominal" : args.model;
      input.model = args.model == "truth" ? scene.truth : scene.nominal;
    } else if (args.model.empty()) {
      input.path = "default";
      input.model = DefaultFullBodyModel(args.height_m);
    } else {
      spdlog::error("mocap track: --model {}: only with --simulate (give a model file)", args.model);
      return 2;
    }
  } else if (Status s = LoadModelInput(args.model, args.marker_set, &input); !s) {
    spdlog::error("mocap track: {}", s.message());
    return 2;
  }
  if (!input.osim && !args.marker_set.empty()) {
    spdlog::error("mocap track: --marker-set {}: only with an OpenSim model (--model FILE.osim)",
                  args.marker_set);
    return 2;
  }
  if (args.simulate && !args.marker_map.empty()) {
    spdlog::error("mocap track: --marker-map {}: only with --points", args.marker_map);
    return 2;
  }
  // --- the subject model: the generic one calibrated on a labelled static trial (--calibrate) ---
  nlohmann::ordered_json calibration;  // stats.json's
  if (!args.calibrate.empty()) {
    if (args.simulate) {
      spdlog::error("mocap track: --calibrate {}: only with --points", args.calibrate);
      return 2;
    }
    std::vector<formats::MarkerTrial> statics;
    MarkerMatch static_match;
    if (Status s = LoadTrials({args.calibrate}, args.marker_map, input.model, &statics, &static_match); !s) {
      spdlog::error("mocap track: --calibrate: {}", s.message());
      return 2;
    }
    LogSkippedPoints(args.calibrate, statics[0]);
    spdlog::info("calibrating {} to the subject on {} ({} frames, {} markers)", input.path, args.calibrate,
                 statics[0].num_frames(), statics[0].num_markers());
    solver::SubjectCalibrationOptions co;
    co.fit.num_threads = args.threads;
    Model subject;
    solver::SubjectCalibrationSummary cs;
    if (Status s = solver::CalibrateSubject(input.model, statics[0], co, &subject, &cs); !s) {
      spdlog::error("mocap track: --calibrate {}: {}", args.calibrate, s.message());
      return 1;
    }
    for (const solver::CentreMarker& c : cs.centre_markers)
      spdlog::info("calibration: {} is on {}'s centre in the model ({:.1f} mm): fitted as a point of the centre",
                   c.marker, c.joint, c.from_centre_mm);
    for (const solver::PlacedMarker& p : cs.fit.placed_markers)
      if (p.why_not.empty())
        spdlog::info("calibration: {} (a placeholder stacked with others in the model) placed on {}, {:.0f} mm from "
                     "the model's point", p.name, p.segment, p.from_model_mm);
      else
        spdlog::warn("calibration: {} (a placeholder) not placed: {}", p.name, p.why_not);
    for (const solver::AttachedMarker& a : cs.fit.attached_markers)
      if (!a.segment.empty())
        spdlog::info("calibration: {} (not in the model) attached to {} by its motion ({:.1f} mm RMS there, {:.1f} "
                     "on the next best segment)", a.name, a.segment, a.spread_mm, a.runner_up_mm);
    for (const solver::AttachedMarker& a : cs.attached_by_proximity)
      if (!a.segment.empty())
        spdlog::info("calibration: {} (not in the model) attached to {}: its markers the nearest ({:.0f} mm; another "
                     "segment's {:.0f} mm)", a.name, a.segment, a.spread_mm, a.runner_up_mm);
    for (const std::string& n : cs.NotAttached())
      spdlog::warn("calibration: not attached (its points are nobody's to the tracker): {}", n);
    spdlog::info("{}", cs.BriefReport());
    // The subject model, as `mocap fit --out` would write it: track more trials with it.
    std::error_code dir_ec;
    fs::create_directories(args.out, dir_ec);
    const std::string written =
        (fs::path(args.out) / (input.osim ? "calibrated.osim" : "calibrated.model.json")).string();
    if (Status w = input.osim ? formats::ExportOsim(subject, input.import, written) : SaveModelJson(written, subject);
        !w) {
      spdlog::error("mocap track: {}", w.message());
      return 1;
    }
    spdlog::info("wrote the subject model {}", written);
    calibration = {{"trial", args.calibrate},
                   {"model", written},
                   {"initial_marker_rms_mm", cs.fit.initial_marker_rms_mm},
                   {"marker_rms_mm", cs.fit.marker_rms_mm},
                   {"iterations", cs.fit.solver.num_iterations()},
                   {"converged", cs.fit.converged()},
                   {"attached", nlohmann::json::object()},
                   {"placed", nlohmann::json::object()},
                   {"not_attached", cs.NotAttached()}};
    for (const auto* list : {&cs.fit.attached_markers, &cs.attached_by_proximity})
      for (const solver::AttachedMarker& a : *list)
        if (!a.segment.empty()) calibration["attached"][a.name] = a.segment;
    for (const solver::PlacedMarker& p : cs.fit.placed_markers)
      if (p.why_not.empty()) calibration["placed"][p.name] = p.segment;
    input.model = std::move(subject);
  }
  const Model& model = input.model;
  if (model.num_markers() < 4) {
    spdlog::error("mocap track: model '{}' ({}) has {} markers: the tracker needs at least 4",
                  model.name(), input.path, model.num_markers());
    return 2;
  }
  // --- the points file, its marker names mapped to the model's (--marker-map) ---
  MarkerMatch match;
  bool labelled_file = false;  // its names are the model's: the labels can be scored
  if (!args.simulate) {
    std::vector<formats::MarkerTrial> trials;
    if (Status s = LoadTrials({args.points}, args.marker_map, model, &trials, &match); !s) {
      spdlog::error("mocap track: {}", s.message());
      return 2;
    }
    file = std::move(trials[0]);
    if (!(file.rate_hz > 0.0) && file.times.size() < 2) {
      spdlog::error("mocap track: {}: no frame rate and no times", args.points);
      return 2;
    }
    if (file.times.size() != static_cast<size_t>(file.num_frames())) {
      file.times.resize(file.num_frames());
      for (int f = 0; f < file.num_frames(); ++f) file.times[f] = f / file.rate_hz;
    }
    for (int f = 1; f < file.num_frames(); ++f)
      if (!(file.times[f] > file.times[f - 1])) {
        spdlog::error("mocap track: {}: frame {} does not come after frame {} in time ({} s, {} s)",
                      args.points, f + 1, f, file.times[f], file.times[f - 1]);
        return 2;
      }
    labelled_file = static_cast<int>(match.unobserved_model_markers.size()) < model.num_markers();
    if (labelled_file) LogMarkerMatch(match);
    if (args.unlabel && !labelled_file) {
      spdlog::error("mocap track: --unlabel: {} has none of the model's marker names (after "
                    "--marker-map): there are no labels to score", args.points);
      return 2;
    }
  }

  std::vector<int> scene_marker;  // per model marker
  if (args.simulate) {
    scene_marker = sim::SceneMarkerOf(model, scene);
    const int matched = static_cast<int>(std::count_if(scene_marker.begin(), scene_marker.end(),
                                                       [](int k) { return k >= 0; }));
    if (matched == 0) {
      spdlog::error("mocap track: model '{}' ({}) has none of the simulated subject's {} markers "
                    "({}, {}, ...): its labels cannot be scored", model.name(), input.path,
                    scene.num_markers(), scene.marker_names[0], scene.marker_names[1]);
      return 2;
    }
    if (matched < model.num_markers() || matched < scene.num_markers())
      spdlog::warn("model '{}' shares {} marker names with the simulated subject's {} ({} in the "
                   "model)", model.name(), matched, scene.num_markers(), model.num_markers());
  }

  ekf::TrackerOptions topt;
  topt.rate_hz = args.simulate ? scene.options.rate_hz
                               : (file.rate_hz > 0 ? file.rate_hz
                                                   : 1.0 / (file.times[1] - file.times[0]));
  const bool find_up = args.up == "auto";
  if (find_up) {
    topt.up = Eigen::Vector3d::UnitZ();  // a simulated lab's; a file's is found below
  } else if (!ParseAxis(args.up, &topt.up)) {
    spdlog::error("mocap track: --up {}: expected auto, x, y, z, -x, -y or -z", args.up);
    return 2;
  }
  // A model calibrated on the subject's static trial is the subject's size already: scaled again
  // at the start, on one frame of real skin, the offsets' prior narrowed to that frame's residual
  // lost labels at low rates (welk007's hip trial at 12.5 Hz, 5 ghosts: 0.987 -> 0.940; biobuddy's
  // left hip 0.994 -> 0.984; BENCHMARKS.md, eighteenth session). So with --calibrate only when its
  // size cannot start.
  const std::string scale_to_subject =
      !args.scale_to_subject.empty() ? args.scale_to_subject : args.calibrate.empty() ? "always" : "when-needed";
  if (!ekf::ParseScaleToSubject(scale_to_subject, &topt.init_scale_to_subject)) {
    spdlog::error("mocap track: --scale-to-subject {}: expected never, when-needed or always", scale_to_subject);
    return 2;
  }
  // OpenSim's ground is Y up (gravity -Y); our models are Z up.
  topt.model_up = input.osim ? Eigen::Vector3d::UnitY() : Eigen::Vector3d::UnitZ();
  // The model's markers the file never shows (virtual ones such as R_HJC, markers the lab's set
  // lacks): known only when the file's names are the model's.
  if (labelled_file) topt.unseen_markers = match.unobserved_model_markers;
  std::string why;
  if (!topt.IsValid(&why)) {
    spdlog::error("mocap track: tracker options: {}", why);
    return 2;
  }
  std::error_code ec;
  fs::create_directories(args.out, ec);
  if (ec || !fs::is_directory(args.out)) {
    spdlog::error("mocap track: cannot create output directory '{}': {}", args.out,
                  ec ? ec.message() : "not a directory");
    return 1;
  }
  const fs::path dir(args.out);

  // --- tracking ---
  const int nf = args.simulate ? scene.num_frames() : file.num_frames();
  const int nm = model.num_markers(), nz = model.num_coordinates();
  auto shared = std::make_shared<const Model>(model);
  // A points file as frames of points (NaN columns dropped); with --unlabel its labels are
  // removed, each frame's points shuffled and --ghosts added, and the tracker scored against them.
  sim::UnlabelledTrial file_frames;
  if (!args.simulate) {
    sim::UnlabelOptions uo;
    uo.shuffle_seed = args.unlabel ? 1 : 0;
    uo.ghosts = args.unlabel ? args.scene.ghosts : 0;
    file_frames = sim::Unlabel(file, model, uo);
    if (find_up) {  // --up auto: the axis on which the tracker starts first (sim::FindLabVertical)
      int started = -1, labelled = 0;
      const int tried = std::min(nf, 10);
      topt.up = sim::FindLabVertical(file_frames.Input(nm), shared, topt, tried, &started, &labelled);
      const std::string axis = AxisName(topt.up);
      if (started >= 0)
        spdlog::info("the lab's vertical: {} (the tracker starts there at frame {} with {} markers; --up to set it)",
                     axis, started + 1, labelled);
      else
        spdlog::warn("the lab's vertical: the tracker starts on no axis in the first {} frames; taking {} (--up to "
                     "set it)",
                     tried, axis);
    }
  }
  ekf::Tracker tracker(shared, topt);
  const int progress_every = std::max(1, nf / 10);
  const auto progress = [&](int f, const ekf::TrackOutput& o) {
    if ((f + 1) % progress_every == 0 || f + 1 == nf)
      spdlog::info("frame {}/{} ({:.0f}%): {}, {}/{} markers labelled", f + 1, nf,
                   100.0 * (f + 1) / nf, ekf::ToString(o.state), o.labelled, nm);
  };
  sim::TrackRun run;
  if (args.simulate) {
    run = sim::TrackScene(scene, &tracker, progress);
  } else {
    sim::TrackInput in = file_frames.Input(nm);
    if (!args.unlabel) in.labels = nullptr;
    run = sim::RunTracker(in, &tracker, progress);
    // A file is offline: the frames before the first start are labelled backward from it.
    if (!args.no_backfill && run.first_tracking > 0) {
      const int start = run.first_tracking;
      const int filled = sim::BackfillBeforeStart(in, shared, topt, &run);
      spdlog::info("the tracker first started at frame {}; tracked backward from there, {} of the {} frames before "
                   "it labelled (--no-backfill: the live tracker's view)",
                   start + 1, filled, start);
    }
  }
  const std::vector<double>& times = args.simulate ? scene.times : file_frames.times;
  const std::vector<Eigen::Matrix3Xd>& frames = args.simulate ? scene.points : file_frames.points;
  formats::MarkerTrial labelled;
  labelled.name = "labelled";
  labelled.rate_hz = topt.rate_hz;
  for (const Marker& m : model.markers()) labelled.marker_names.push_back(m.name);
  labelled.positions.setConstant(nf, 3 * nm, std::nan(""));
  labelled.times = times;
  labelled.frame_numbers.resize(nf);
  for (int f = 0; f < nf; ++f) {
    labelled.frame_numbers[f] = f + 1;
    for (int m = 0; m < nm; ++m)
      if (const int i = run.point_of_marker(f, m); i >= 0)
        labelled.positions.row(f).segment<3>(3 * m) = frames[f].col(i).transpose();
  }
  const Eigen::MatrixXd& z_out = run.z;
  const std::vector<ekf::TrackState>& states = run.states;

  // --- outputs ---
  if (Status s = formats::WriteTrc((dir / "labelled.trc").string(), labelled); !s) {
    spdlog::error("mocap track: {}", s.message());
    return 1;
  }
  if (Status s = WriteAngles((dir / "coordinates.mot").string(), input, model, labelled, z_out); !s) {
    spdlog::error("mocap track: {}", s.message());
    return 1;
  }
  nlohmann::ordered_json j;
  j["frames"] = nf;
  j["model"] = input.path;
  j["model_markers"] = nm;
  j["rate_hz"] = topt.rate_hz;
  j["backfilled_frames"] = run.backfilled_frames;
  j["backfilled_labels"] = run.backfilled_labels;  // in the frames after the start (sim::BackfillBeforeStart)
  j["points_per_frame_mean"] = run.points_per_frame_mean;
  j["points_per_frame_max"] = run.points_per_frame_max;
  j["frames_tracking"] = run.frames_tracking();
  j["frames_initialising"] = run.state_count[static_cast<int>(ekf::TrackState::kInitialising)];
  j["frames_lost"] = run.state_count[static_cast<int>(ekf::TrackState::kLost)];
  j["first_tracking_frame"] = run.first_tracking;
  j["initialisations"] = run.initialisations;
  j["reinitialisations"] = run.reinitialisations();
  j["nan_poses"] = run.nan_poses;
  std::vector<double> update_us = run.update_us, update_cpu_us = run.update_cpu_us;
  j["update_us_p50"] = daemon::Percentile(&update_us, 50);
  j["update_us_p99"] = daemon::Percentile(&update_us, 99);
  j["update_us_max"] = update_us.empty() ? 0.0 : *std::max_element(update_us.begin(), update_us.end());
  j["update_cpu_us_p50"] = daemon::Percentile(&update_cpu_us, 50);
  j["update_cpu_us_p99"] = daemon::Percentile(&update_cpu_us, 99);

  if (args.simulate) {
    const sim::LabelScore& score = run.score;
    j["seed"] = scene.options.seed;
    j["scene"] = {{"ghosts", scene.options.ghosts},
                  {"occlusion", scene.options.occlusion},
                  {"swap_traps", scene.options.swap_traps},
                  {"fault", sim::ToString(scene.options.fault)},
                  {"fault_begin_frame", scene.fault_begin},
                  {"fault_end_frame", scene.fault_end},
                  {"movements", nlohmann::json::array()}};
    for (const sim::SceneSegment& s : scene.segments)
      j["scene"]["movements"].push_back({{"name", s.name}, {"begin", s.begin}, {"end", s.end}});
    j["marker_samples"] = score.samples;
    j["label_accuracy"] = score.accuracy();
    j["labelled_correctly"] = score.correct;
    j["wrong_labels"] = score.wrong;
    j["wrong_label_fraction"] = score.samples > 0 ? static_cast<double>(score.wrong) / score.samples : 0.0;
    j["wrong_labels_on_ghosts"] = score.wrong_on_ghosts;
    j["wrong_labels_on_second_person"] = score.wrong_on_second_person;
    j["swaps_longer_than_5_frames"] = score.swaps_longer_than_5_frames;
    j["longest_wrong_run_frames"] = score.longest_wrong_run;
    j["trap_moments"] = scene.traps.size();
    j["per_marker_accuracy"] = nlohmann::json::object();
    for (int k = 0; k < scene.num_markers(); ++k)
      if (run.marker_samples[k] > 0)
        j["per_marker_accuracy"][scene.marker_names[k]] =
            static_cast<double>(run.marker_correct[k]) / run.marker_samples[k];

    // Against the true poses, in the frames the tracker was tracking: the model's markers (forward
    // kinematics of the tracked z with the tracker's model) against the true markers, and the
    // joint angles (rotational coordinates of non-root joints, by name) against the true ones.
    const Geometry geometry(model);
    ModelData data(model);
    std::vector<int> truth_coordinate(nz, -1);
    for (int c = 0; c < nz; ++c) {
      const Coordinate& coord = model.coordinates()[c];
      const bool root = coord.joint >= 0 && model.joints()[coord.joint].parent < 0;
      if (coord.rotational && !root) truth_coordinate[c] = scene.truth.FindCoordinate(coord.name);
    }
    double marker_sq = 0, angle_sq = 0;
    long marker_n = 0, angle_n = 0;
    nlohmann::ordered_json per_coordinate = nlohmann::json::object();
    std::vector<double> coord_sq(nz, 0.0);
    std::vector<long> coord_n(nz, 0);
    for (int f = 0; f < nf; ++f) {
      if (states[f] != ekf::TrackState::kTracking || !z_out.row(f).allFinite()) continue;
      const Eigen::VectorXd z = z_out.row(f).transpose();
      ForwardKinematics(model, geometry, z, &data);
      for (int m = 0; m < nm; ++m) {
        if (scene_marker[m] < 0) continue;
        const Eigen::Vector3d truth = scene.true_markers.row(f).segment<3>(3 * scene_marker[m]).transpose();
        marker_sq += (MarkerPosition(model, geometry, data, m) - truth).squaredNorm();
        ++marker_n;
      }
      for (int c = 0; c < nz; ++c) {
        if (truth_coordinate[c] < 0) continue;
        const double e = WrapAngle(z[c] - scene.true_coordinates(f, truth_coordinate[c]));
        angle_sq += e * e;
        ++angle_n;
        coord_sq[c] += e * e;
        ++coord_n[c];
      }
    }
    for (int c = 0; c < nz; ++c)
      if (coord_n[c] > 0)
        per_coordinate[model.coordinates()[c].name] = std::sqrt(coord_sq[c] / coord_n[c]) * 180.0 / M_PI;
    // null when the tracker never tracked (nothing to compare).
    j["marker_rms_mm"] = nullptr;
    j["joint_angle_rms_deg"] = nullptr;
    if (marker_n > 0) j["marker_rms_mm"] = 1000.0 * std::sqrt(marker_sq / marker_n);
    if (angle_n > 0) j["joint_angle_rms_deg"] = std::sqrt(angle_sq / angle_n) * 180.0 / M_PI;
    j["per_coordinate_rms_deg"] = per_coordinate;
    // Recovery after a fault: frames from the fault's end until the tracker tracks again with
    // 90 % of the visible markers correctly labelled and no wrong label.
    if (scene.fault_end > 0 && scene.fault_end < nf) {
      j["recovery_frames"] = nullptr;
      for (int f = scene.fault_end; f < nf; ++f) {
        const sim::LabelScore& fs = run.frame_scores[f];
        if (states[f] == ekf::TrackState::kTracking && fs.wrong == 0 &&
            fs.correct >= 0.9 * static_cast<double>(fs.samples)) {
          j["recovery_frames"] = f - scene.fault_end;
          break;
        }
      }
    }
    if (Status s = SaveModelJson((dir / "nominal.model.json").string(), scene.nominal); !s) {
      spdlog::error("mocap track: {}", s.message());
      return 1;
    }
    if (Status s = SaveModelJson((dir / "truth.model.json").string(), scene.truth); !s) {
      spdlog::error("mocap track: {}", s.message());
      return 1;
    }
    if (Status s = formats::WriteMot((dir / "truth.mot").string(), scene.TrueCoordinateTable()); !s) {
      spdlog::error("mocap track: {}", s.message());
      return 1;
    }
    if (args.write_points)
      if (Status s = formats::WriteTrc((dir / "points.trc").string(), scene.PointsTrial()); !s) {
        spdlog::error("mocap track: {}", s.message());
        return 1;
      }
    std::printf("mocap track: %d frames, label accuracy %.6f, %ld wrong labels (%.4f%%), %d swaps > 5 "
                "frames, %d reinitialisations, marker RMS %.2f mm, joint angles RMS %.3f deg, update "
                "p50 %.0f us p99 %.0f us -> %s\n",
                nf, score.accuracy(), score.wrong,
                100.0 * j["wrong_label_fraction"].get<double>(), score.swaps_longer_than_5_frames,
                j["reinitialisations"].get<int>(),
                j["marker_rms_mm"].is_number() ? j["marker_rms_mm"].get<double>() : std::nan(""),
                j["joint_angle_rms_deg"].is_number() ? j["joint_angle_rms_deg"].get<double>() : std::nan(""),
                j["update_us_p50"].get<double>(), j["update_us_p99"].get<double>(), args.out.c_str());
  } else {
    if (run.scored) {
      j["unlabelled"] = {{"shuffled", true}, {"ghosts", args.scene.ghosts}};
      j["marker_samples"] = run.score.samples;
      j["label_accuracy"] = run.score.accuracy();
      j["wrong_labels"] = run.score.wrong;
      j["wrong_labels_on_ghosts"] = run.score.wrong_on_ghosts;
      j["swaps_longer_than_5_frames"] = run.score.swaps_longer_than_5_frames;
      j["longest_wrong_run_frames"] = run.score.longest_wrong_run;
      j["per_marker_accuracy"] = nlohmann::json::object();
      for (int k = 0; k < nm; ++k)
        if (run.marker_samples[k] > 0)
          j["per_marker_accuracy"][model.markers()[k].name] =
              static_cast<double>(run.marker_correct[k]) / run.marker_samples[k];
    }
    j["unseen_markers"] = topt.unseen_markers;
    if (!calibration.is_null()) j["calibration"] = calibration;
    j["scale_to_subject"] = scale_to_subject;
    const std::vector<double>& scales = tracker.initialisation().segment_scales;
    j["segment_scales"] = nlohmann::json::object();  // empty: the model's own
    for (size_t k = 0; k < scales.size(); ++k) j["segment_scales"][model.segments()[k].name] = scales[k];
    std::printf("mocap track: %d frames, %d tracking, %d reinitialisations, update p50 %.0f us p99 "
                "%.0f us", nf, j["frames_tracking"].get<int>(),
                j["reinitialisations"].get<int>(), j["update_us_p50"].get<double>(),
                j["update_us_p99"].get<double>());
    if (run.scored)
      std::printf(", label accuracy %.6f, %ld wrong labels, %d swaps > 5 frames (longest %d)",
                  run.score.accuracy(), run.score.wrong, run.score.swaps_longer_than_5_frames,
                  run.score.longest_wrong_run);
    std::printf(" -> %s\n", args.out.c_str());
  }
  {
    std::ofstream f(dir / "stats.json");
    f << j.dump(2) << "\n";
    if (!f) {
      spdlog::error("mocap track: cannot write {}", (dir / "stats.json").string());
      return 1;
    }
  }
  return 0;
}

const CommandRegistrar kRegisterTrack("track", [](CLI::App& app, int* exit_code) {
  auto args = std::make_shared<TrackArgs>();
  CLI::App* cmd = app.add_subcommand(
      "track", "run the real-time tracker (EKF) over unlabelled 3D points: a simulated scene with "
               "truth, or a points file; labelled markers, coordinates and stats out");
  cmd->add_option("--model", args->model,
                  "model (.json/.osim); with --simulate also 'nominal' (default) or 'truth'; with "
                  "--points the default is the default model scaled to --height");
  cmd->add_flag("--simulate", args->simulate, "track a simulated scene (sim/tracking_scene.h)");
  cmd->add_option("--seed", args->scene.seed, "simulation: the subject and movements of `mocap sim --seed N`")
      ->check(CLI::NonNegativeNumber);
  cmd->add_option("--ghosts", args->scene.ghosts, "simulation, or --points with --unlabel: ghost points per frame")
      ->check(CLI::NonNegativeNumber);
  cmd->add_option("--occlusion", args->scene.occlusion,
                  "simulation: fraction of marker samples occluded (gaps of 5..30 frames)");
  cmd->add_flag("--swap-traps", args->scene.swap_traps,
                "simulation: append a movement where markers pass within 15 mm of each other");
  cmd->add_option("--movements", args->movements,
                  "simulation: protocol movements, comma-separated (default: all, from 'static')");
  cmd->add_option("--duration-scale", args->scene.duration_scale, "simulation: scales each movement's duration");
  cmd->add_option("--noise-mm", args->scene.noise_mm, "simulation: marker noise per coordinate (mm)");
  cmd->add_option("--rate", args->scene.rate_hz, "simulation: frame rate (Hz)");
  cmd->add_option("--fault", args->fault,
                  "simulation: none, all_occluded, leave_reenter, second_person, nan_frame");
  cmd->add_option("--fault-time", args->scene.fault_time_s, "simulation: when the fault starts (s; default 40 % in)");
  cmd->add_flag("--write-points", args->write_points, "simulation: also write the points as DIR/points.trc");
  cmd->add_option("--points", args->points, "unlabelled points (.trc or .c3d, NaN for empty slots)");
  cmd->add_flag("--no-backfill", args->no_backfill,
                "with --points: leave the frames before the first start unlabelled (as live), instead of "
                "tracking backward from it");
  cmd->add_option("--marker-set", args->marker_set, "OpenSim marker set (.xml) added to an .osim model");
  cmd->add_option("--marker-map", args->marker_map,
                  "with --points: marker-name map, lines 'model_name = file_name' (# comments)");
  cmd->add_option("--up", args->up,
                  "the lab's vertical: x, y, z, -x, -y or -z; auto (default): z in a simulation, with --points "
                  "the axis on which the tracker starts in the first 10 frames");
  cmd->add_option("--scale-to-subject", args->scale_to_subject,
                  "scale the model segment by segment to the subject at the start: never, when-needed "
                  "(when the model's own size cannot start; the default with --calibrate) or always (the "
                  "default)")
      ->check(CLI::IsMember({"never", "when-needed", "always"}));
  cmd->add_option("--calibrate", args->calibrate,
                  "with --points: a labelled static trial of the subject (.c3d/.trc, --marker-map applies): the "
                  "model is first fitted to it -- scaled, its markers placed, the trial's markers it lacks "
                  "attached -- and the points tracked with that subject model (written as DIR/calibrated.osim "
                  "or DIR/calibrated.model.json), as a lab labels with a skeleton calibrated on a static trial");
  cmd->add_option("--threads", args->threads, "the calibration's fit: worker threads (0: all cores)")
      ->check(CLI::NonNegativeNumber);
  cmd->add_flag("--unlabel", args->unlabel,
                "with a labelled --points file: remove its labels, shuffle each frame's points, add "
                "--ghosts, and score the tracker's labels against the file's");
  cmd->add_option("--height", args->height_m, "with --points and no --model: subject height (m)")
      ->check(CLI::Range(0.5, 3.0));
  cmd->add_option("--out", args->out, "output directory (created)")->required();
  cmd->callback([args, exit_code] { *exit_code = RunTrack(*args); });
});

}  // namespace
}  // namespace mocap::tools
