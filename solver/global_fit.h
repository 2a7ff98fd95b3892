// The global body-model fit of Lugrís, Beron, Michaud & Cuadrado (2024): every frame of every
// calibration trial and the geometric parameters in ONE least-squares problem
//
//     min_q  sum_f sum_m w_m ||h_m(z_f, p) - r_fm||^2 / sigma^2  +  sum_i ((p_i - p0_i) / s_i)^2
//     q = [z_1 ... z_F, p]
//
// solved by Levenberg–Marquardt with the analytic sparse Jacobian of model/kinematics.h and the
// per-frame Schur elimination of solver/schur_solver.h. Missing markers have no residual. The
// weak priors (s_i: FitOptions' prior sigmas) towards the initial model pin the directions the
// data cannot fix — a hinge centre along its axis, a marker offset that trades against a joint
// centre — and keep the normal matrix positive definite, so no NaN ever comes out. The report
// gives a standard deviation for every fitted parameter (the p-block of the inverse normal
// matrix, scaled by the residual variance) and names the parameters the data did not determine:
// those whose posterior standard deviation, with the data's nominal sigma, is more than
// `undetermined_ratio` of their prior sigma.
#pragma once

#include <Eigen/Core>
#include <string>
#include <vector>

#include "formats/marker_data.h"
#include "model/model.h"
#include "model/status.h"
#include "solver/attach_markers.h"
#include "solver/marker_diagnosis.h"
#include "solver/coarse_to_fine.h"
#include "solver/inverse_kinematics.h"
#include "solver/levenberg_marquardt.h"
#include "solver/robust_loss.h"

namespace mocap::solver {

struct FitOptions {
  // Parameter groups to fit (scales, centres, axes, markers); the others stay at the initial model.
  bool fit_scales = true;
  bool fit_centres = true;
  bool fit_axes = true;
  bool fit_markers = true;
  double marker_sigma_m = 0.001;        // residual unit: 1 mm of marker error
  double prior_sigma_scale = 0.1;       // 10 % of segment size
  double prior_sigma_position_m = 0.05; // joint centres and marker positions
  double prior_sigma_axis_rad = 0.17;   // about 10 degrees
  // A marker the model's author fixed on a landmark (Marker::fixed, OpenSim's <fixed>): its prior
  // is the precision of palpating a landmark, 1-2 cm (Della Croce, Cappozzo & Kerrigan 1999, Med
  // Biol Eng Comput 37:155), not the 5 cm of a marker whose place is unknown. The tighter prior
  // holds segments in their landmarks where every marker is free and only priors say where the
  // bones are. welk007 (generic model, static + hip trial), 20 / 10 / 50 mm: knees 13-14 / 9-15 /
  // 15-29 mm from their epicondyles' midpoint, right hip 9.3 / 12.7 / 4.9 mm from SCoRE and 25.9 /
  // 23.3 / 27.4 mm from the hand-scaled model's (which is itself ~28 mm from SCoRE).
  double prior_sigma_fixed_marker_m = 0.02;
  // Each frame's coordinates are pulled, very weakly, to their starting pose: a coordinate whose
  // markers are all missing in a frame (a gap) stays put instead of taking a wild step. 1 rad or
  // 1 m of deviation costs what 0.1 mm of one marker's error costs.
  double frame_prior_sigma_rad = 10.0;
  double frame_prior_sigma_m = 10.0;
  // A clamped coordinate (Coordinate::clamped, OpenSim's <clamped>true</clamped>) beyond its range
  // adds a residual (excess) / sigma in every frame: a stiff one-sided wall, zero inside the range.
  // OpenSim's IK bounds such coordinates hard; a wall keeps the solve smooth. At 1e-3, 1 degree
  // beyond costs what a 17 mm marker error costs at marker_sigma_m = 1 mm. Without it, a generic
  // model whose wand markers are far from the lab's (welk007) is posed standing with its ankles
  // 70 deg dorsiflexed and a knee 23 deg hyperextended, and its markers slide 20 cm to match.
  // 0: ranges are not enforced.
  double coordinate_limit_sigma_rad = 1e-3;
  double coordinate_limit_sigma_m = 1e-3;
  // Coordinates that a frame in a marker gap leaves unobserved are held at their start instead
  // (solver/coarse_to_fine.h, UnobservedCoordinateWeights): without it such frames make LM crawl.
  UnobservedHoldOptions unobserved_hold;
  double gauge_sigma_m = 1e-5;          // stiffness of the gauge rows (marker_fit_problem.h)
  // A hinge's centre along its axis is held at the model's by a stiff row (marker_fit_problem.cpp).
  bool hold_hinge_centres_along_axis = true;
  double undetermined_ratio = 0.1;
  // If the solve has not converged after this many iterations, every pose is re-solved by IK
  // with the geometry reached so far and the solve continues (see FitModel).
  int repose_after_iterations = 12;
  // After the solve, a frame whose cost per marker sample is more than `rescue_ratio` times the
  // median frame's (a limb left in a wrong branch of its pose, typically behind a marker gap:
  // with one of a two-marker segment's markers hidden its rotation is free, and the solve can
  // carry it round to a mirror pose it cannot leave) gets its pose re-solved by IK from the
  // nearest well-fitted frames before and after it; where that lowers the frame's cost the pose
  // is replaced and the solve continues, for at most `rescue_rounds` rounds. 0 rounds: off.
  // A marker whose residual RMS over the fit is more than `outlier_marker_ratio` times the median
  // marker's and at least `outlier_marker_min_mm` above it is named in the report: a mislabelled
  // marker, one placed on another body than the model says, or one that slipped. It is still
  // fitted (least squares: it pulls its segment); the report says so instead of staying silent.
  // Markers whose positions on their segments are not fitted (the virtual markers of
  // solver/functional_joints.h's AddFunctionalCentres, which sit at a joint centre by definition).
  std::vector<std::string> fixed_markers;
  // Parameters (by name, e.g. "knee_l.centre.z") held at the initial model's values whatever the
  // groups say: FitModel's schedule holds the centres and axes of joints the trials do not move.
  std::vector<std::string> fixed_parameters;
  // Parameters (by name) held at the initial model's values like fixed_parameters, but as a
  // judgement, not as a fact: FitModel's schedule puts here the centres and axes of the joints the
  // trials hardly move (min_excitation_deg). The solve keeps them fixed: as 10 mm priors instead
  // (and the rows that hold an observable direction dropped) they followed the skin
  // motion -- gait2354's hips 22 mm from OpenSim's, welk007's left knee 29 mm from its epicondyles
  // (BENCHMARKS.md). The report's standard deviations count them as what a scaled generic
  // model's centre and axis are worth -- free against a prior of held_centre_sigma_m (a centre's
  // coordinates, unscaled) and held_axis_sigma_rad (an axis' angles) -- and the rows that hold
  // an observable direction likewise (MarkerFitProblem, relax_holds), so that a parameter the
  // data place only through a held neighbour is not reported as precise as the hold makes it
  // look: welk007's right knee, 9 mm from the truth behind its held ankle and femur, was
  // reported to 0.3 mm, now 3.3 mm and undetermined. 0: the holds count as exact.
  std::vector<std::string> held_parameters;
  double held_centre_sigma_m = 0.01;
  double held_axis_sigma_rad = 0.087;  // 5 degrees
  double outlier_marker_ratio = 3.0;
  double outlier_marker_min_mm = 5.0;
  // Why each outlying marker is off (a stretch mislabelled, a swap, the wrong body, it moves):
  // FitReport::marker_diagnoses (solver/marker_diagnosis.h).
  MarkerDiagnosisOptions diagnosis;
  double rescue_ratio = 4.0;
  int rescue_rounds = 2;
  int rescue_iterations = 12;  // the solve's iterations after each rescue that replaced poses
  // Per-marker sigmas re-estimated from the residuals (iteratively reweighted least squares, one
  // weight per marker): after a converged solve, marker m's sigma becomes the RMS of its residual
  // per coordinate, never below marker_sigma_m (in the schedule, the final stage's effective
  // sigma, effective_marker_sigma), and the solve continues with the residual scale
  // sqrt(weight_m) / sigma_m; at most `marker_sigma_rounds` rounds, fewer once no sigma moves by
  // more than `marker_sigma_tolerance` (relative); each round's solve may take lm.max_iterations.
  // Why: markers are not equally reliable. Skin over muscle (a thigh or upper-arm wand) moves
  // 10-30 mm against the bone, skin over a malleolus or an epicondyle a few mm (sim/sta_table.h
  // and its sources); with one sigma for all, the wobbling markers pull on the geometry as hard
  // as the bony landmarks. One noise variance per marker, estimated from the fit, is the
  // maximum-likelihood weighting of such data, and it needs no marker classes: a slipping or
  // wobbling marker of a real session is weighted down the same way. The floor keeps a marker
  // that fits better than the stated measurement noise from counting more than that noise
  // allows, so a fit of clean data is unchanged (no round runs when every marker is within the
  // floor). What it cannot do: an artefact that the poses and the geometry absorb leaves no
  // residual, so it is not weighted down (BENCHMARKS.md, soft-tissue artefact: the elbow behind
  // one forearm wand). Off by default (0 rounds: one sigma for every marker), measured: on the
  // simulated subject at 10 mm of soft-tissue artefact 3 rounds lower the joint centres' RMS by
  // 2-16 % (seeds 1-4) but leave the worst joint where it was; on real recordings, whose models
  // misfit some markers by 10-30 mm, every round is a new solve (single-stage fits, before the
  // schedule: gait2354 202 -> 318 iterations; welk007's scaling 78 iterations, converged -> 178,
  // not converged within its 100 a round). In the schedule, the rounds run in its final stage,
  // whose floor is that stage's effective sigma (the median marker's residual RMS per coordinate
  // times sqrt(tau): 7.5 mm on the simulated subject at 10 mm of skin artefact), above every
  // marker's residual RMS per coordinate there (at most 1.7 mm): no round runs, and the figures
  // are those of the fit without (bench/sta_accuracy --sigma-rounds 3, BENCHMARKS.md).
  int marker_sigma_rounds = 0;
  double marker_sigma_tolerance = 0.05;
  // Robust loss (solver/robust_loss.h: why iteratively reweighted least squares, and the
  // sources): a marker sample whose residual is more than `robust_scale` marker sigmas is
  // down-weighted (Huber: its pull capped; Cauchy: faded out), so that a marker mislabelled or
  // slipping for a few hundred frames cannot drag its segment. The unit, the marker sigma, is one
  // sample's error per coordinate as the residuals show it: the median marker's residual RMS per
  // coordinate at the current solve (the one FitReport::residual_sigma_mm reports; robust to a
  // few bad markers, and without the effective sigma's sqrt(tau), which is about how much
  // correlated samples tell, not how large one is), re-estimated each round. The 3-D residual of
  // Gaussian noise of that sigma exceeds 3 sigmas in 2.9 % of samples (chi with 3 degrees of
  // freedom), hence the default scale. After the least-squares solve, at most `robust_rounds`
  // rounds, fewer once no weight moves by more than `robust_tolerance`; each round's solve may
  // take lm.max_iterations. In FitModel's schedule it acts from the markers stage on: before the
  // markers are placed their residuals are the generic model's misplacement, not the data's
  // errors. Cauchy fades a gross error out (weight ~ 1/u^2), Huber only caps its pull (~ 1/u):
  // with a marker 50 mm off for 300 frames Huber left the knee 1.4 mm off, Cauchy 0.6 mm
  // (tests/test_sim_fit.cpp). Off by default: every round is a solve (the simulated session at
  // 10 mm of skin artefact: 20 s -> 61 s with Cauchy, machine loaded), and on that artefact it
  // helps on average but not everywhere (seeds 1-4, Cauchy: RMS over the 14 joint centres
  // 6.8/5.7/6.6/7.8 -> 5.5/5.7/5.0/5.9 mm, but seed 2's left knee 9.2 -> 12.2 mm; BENCHMARKS.md).
  // The sigma rounds (marker_sigma_rounds), if any, run after the robust rounds and keep the
  // last round's weights.
  RobustLoss robust_loss = RobustLoss::kNone;
  double robust_scale = 3.0;
  int robust_rounds = 5;
  double robust_tolerance = 0.1;
  // The automatic schedule (FitModel): from a generic model, joint centres and axes are freed
  // only once scales and marker positions fit the subject. On for every fit that frees centres
  // or axes together with scales or markers; `staged_iterations` caps the first stage (it is a
  // start, not the answer: the final stage is the whole problem).
  bool staged = true;
  int staged_iterations = 40;
  // The stages before the last are starts, not answers: each stops once an iteration lowers the
  // cost by less than this fraction (lm.function_tolerance, if larger, still applies) instead of
  // crawling on at the same RMS (gait2354's markers stage: 7.55 mm from its 8th iteration to its
  // 19th). The final stage keeps lm's tolerances.
  double stage_function_tolerance = 1e-5;
  // The stages before the last are solved on every k-th frame of each trial, k chosen so that
  // they see at most this many frames in all, when the trials have more than twice as many;
  // every frame is then posed by their model and the final stage solves them all (0: every
  // stage on every frame). Why: those stages place the
  // markers and scale the segments, which a few hundred frames spread over every movement
  // determine as well as thousands (the coarse-to-fine start of solver/coarse_to_fine.h, for the
  // same reason), and on real recordings they took most of the iterations over every frame
  // (welk007: 55 of 82). The weights are unchanged in total: a subset's residuals are
  // correlated over tau / k of its frames, so each of its samples weighs k times one of the
  // whole trial's (FitOptions::effective_marker_sigma), and the data's error for the final
  // stage is measured on every frame. Measured (BENCHMARKS.md, fourteenth session): welk007 the
  // same right hip (9.3 mm from SCoRE) and RMS (5.407 mm), 29 iterations over every frame
  // instead of 82; biobuddy 38.9 -> 14.2 s of CPU, 28 iterations over every frame instead of 79.
  int stage_frames = 400;
  // In the schedule's final stage, a joint whose rotation the trials hardly move keeps its centre
  // and axes where stage 1 left them (the model's, scaled): a ball joint needs its second-largest
  // coordinate spread (RMS about the mean over every frame) at least this, a hinge its one.
  // SCoRE's own excitation rule (solver/functional_joints.h) with the same 5 degrees.
  // A joint whose centre a marker of fixed_markers observes (a model marker tied to the centre,
  // OpenCap's RHJC_study; a functional centre's virtual marker) keeps its centre free however
  // little it turns: those samples are the centre in the lab. OpenCap's squats turn the hips
  // 5-9.6 deg about their second axis: held, the hips sat 0.7-2.0 mm RMS from the truth in the
  // lab, fitted 0.3-0.5 mm (tests/test_osim_subject.cpp, OpenCapSquatsFromLaiUhlrich2022).
  double min_excitation_deg = 10.0;
  // From the second stage on, the data are weighted as what they are: a marker's error is not
  // the nominal marker_sigma_m of white noise but the residual RMS the previous stage left, and
  // its samples are not independent: skin moves with the movement, so neighbouring frames repeat
  // the same error (Leardini et al. 2005; Camomilla et al. 2017). N frames whose errors are
  // correlated over tau frames carry the information of N / tau independent ones (the effective
  // sample size of a correlated series), so the stage's marker sigma is
  //     sigma = RMS per coordinate * sqrt(tau),   tau = FitReport::residual_correlation_frames,
  // never below marker_sigma_m. Weighted with 1 mm and every frame as independent, thousands of
  // frames of skin motion outvote any prior: on gait2354 a hip centre the walk cannot place slid
  // 400 mm for a 0.01 mm better RMS. Clean simulated data (white noise, tau ~ 1) keep
  // marker_sigma_m.
  bool effective_marker_sigma = true;
  // A static trial is one posture, fitted as such: every frame of a trial whose markers hardly
  // move -- the median marker's RMS distance from its mean position below this (mm) -- is
  // replaced by the trial's mean marker positions, so all its frames share one pose (as
  // OpenSim's marker placer averages a static trial into one frame). What differs between a
  // standing subject's frames (sway, breathing) is not the rotation about joints that the model
  // can explain, yet counted as hundreds of frames it outvotes the priors that keep the
  // skeleton inside its markers: on gait2354's static trial alone, fitted with the markers
  // free, the whole skeleton slid 15 cm up out of its markers (knee centres 17 cm from the
  // epicondyle markers) for a 0.01 mm better RMS; as one posture they are 6-11 mm from them.
  // Standing trials measure 1-5 mm, functional ones and walks 80-110 mm (../shared/data).
  // A static trial's residuals are then those of its mean posture. 0: every frame as measured.
  double static_trial_motion_mm = 10.0;
  // A model marker the fit moved more than this many prior sigmas (prior_sigma_position_m) on
  // its segment is named in the report (far_moved_markers) and the log: a generic model's marker
  // is a few centimetres from where a lab puts it, and a move of 15 cm or more says rather that
  // the poses of its segment are wrong while the marker RMS looks fine (welk007's one-command fit:
  // L_calc and L_ankle moved 28-30 cm, the left ankle centre 23 cm from its malleoli, at 5.3 mm RMS).
  double far_moved_marker_sigmas = 3.0;
  // The scales stage fits the model's own marker places, and a generic model's places for
  // cluster markers (thigh and shank wands, plates) are guesses that may be 10-15 cm from where
  // a lab put them: weighed like the anatomical landmarks they bend the whole skeleton (welk007's
  // generic model on its static trial: marker RMS 73 mm after scaling, the hips flexed 30 deg and
  // the lumbar spine 69 deg, knee centres 70-100 mm from the epicondyle markers). So the stage is
  // solved again with each marker weighted by a Cauchy loss of its residual RMS, the unit being
  // scaling_marker_robust_scale times the median marker's, for at most scaling_marker_rounds
  // rounds, fewer once no weight moves by more than scaling_marker_tolerance: the markers that
  // agree with the model's anatomy scale it, as OpenSim users scale from chosen landmark pairs.
  // The weights serve the scaling only; the markers stage places every marker at full weight.
  // Off by default (`mocap fit --scaling-marker-rounds 5` turns it on), measured: on welk007's
  // static trial alone the left knee centre comes from 70 to 48 mm of its epicondyle markers
  // and the left ankle from 85 to 23 mm of its malleoli, but the right knee stays 105 mm off (the
  // right thigh's wand keeps its weight and the epicondyle markers lose theirs); over all three
  // real recordings' one-command fits it helps biobuddy's right knee axis (6.6 -> 5.5 deg from
  // SARA) and gait2354's knees (5.3/3.8 -> 3.7/2.9 mm from OpenSim's) but costs gait2354 7
  // iterations (29 -> 36, against the 30) and 0.24 mm of marker RMS.
  int scaling_marker_rounds = 0;
  double scaling_marker_robust_scale = 2.0;
  double scaling_marker_tolerance = 0.05;
  // The markers stage first runs until an iteration changes the cost by less than this fraction,
  // to measure the data's error; it is solved again from its start at the measured sigma when
  // that is more than reweigh_markers_stage_ratio times the sigma it assumed, and otherwise goes
  // on (global_fit.cpp, FitModel: why).
  double markers_measure_tolerance = 1e-2;
  double reweigh_markers_stage_ratio = 2.0;
  // After the schedule's first stage, trial markers the model lacks are attached to the segment
  // they ride on (solver/attach_markers.h) and fitted with the others.
  bool attach_trial_markers = true;
  AttachOptions attach;
  // Model markers the trials see that the model stacks on one point of a segment with another
  // (within stacked_marker_tolerance_m): placeholders of a generic model (solver/attach_markers.h,
  // StackedMarkers). They are left out of the schedule's first stage and then placed where the
  // trials put them on their segments, with the trial markers the model lacks.
  bool place_stacked_markers = true;
  double stacked_marker_tolerance_m = 1e-3;
  int num_threads = 0;                  // 0: all cores
  LmOptions lm;
  IkOptions ik;
  // Many frames: the geometry first from an evenly spaced subset, then the whole problem
  // (solver/coarse_to_fine.h). The same minimum and stopping rule, fewer passes over all frames.
  CoarseToFineOptions coarse;

  FitOptions() {
    lm.function_tolerance = 1e-6;  // Ceres's default; the benchmark compares final costs at 1e-6
    lm.parameter_tolerance = 1e-9;
    lm.max_iterations = 100;
    lm.shared_step_tolerance = 0.1;  // the body model within a tenth of its standard deviation
  }
  bool IsValid(std::string* error) const;
  // Parses "scales,centres,axes,markers" (any subset, or "all"/"none").
  Status SetGroups(const std::string& list);
};

// One trial: labelled markers (metres) and, optionally, a starting pose per frame (from the live
// filter, or a .mot); without it the fit runs per-frame inverse kinematics first. A row that is
// entirely NaN (a frame the filter was not tracking) is solved by IK, warm-started from the
// nearest given pose before it (after it, for leading rows); a row with only some NaN entries is
// an error, as is a trial with no given row at all.
struct FitTrial {
  formats::MarkerTrial markers;
  Eigen::MatrixXd initial_coordinates;  // frames x n_coordinates, or empty
};

// Starting poses of one trial from a table of coordinates (a .mot of `mocap track`, `mocap ik`,
// or the simulator's truth): formats::PosesFromTable (its checks, errors naming `source`), and
// the table has `num_frames` rows. NaN entries are kept (see FitTrial).
Status InitialCoordinatesFromTable(const Model& model, const formats::CoordinateTable& table,
                                   int num_frames, const std::string& source, Eigen::MatrixXd* z);

struct ParameterEstimate {
  std::string name;
  ParameterGroup group;
  double initial = 0;
  double value = 0;
  double std = 0;          // standard deviation (same unit as value); 0 when not fitted
  bool fitted = false;
  bool determined = true;
};

// One stage of FitModel's schedule.
struct FitStageSummary {
  std::string name;              // "scales and markers", "all parameters"
  std::string groups;            // e.g. "scales,markers"
  int iterations = 0;
  TerminationType termination = TerminationType::kFailure;
  double initial_marker_rms_mm = 0, marker_rms_mm = 0;
  double marker_sigma_mm = 0;               // the data's weight in this stage (1 / sigma^2)
  double residual_correlation_frames = 1;   // of its residuals (FitReport); 1: not measured (scales)
  double seconds = 0;
  int frames = 0;                           // the frames it solved (FitOptions::stage_frames)
  // One of the two solves that found a better minimum after the schedule (solver/fit_trust.h,
  // CheckFitTrustAndAdopt), not a stage of the schedule.
  bool better_minimum_search = false;
};

struct FitReport {
  // The final stage's solve, preceded by the iterations of the stages before it (`stages`):
  // num_iterations() counts every iteration of the fit, termination is the final stage's.
  LmSummary solver;
  std::vector<FitStageSummary> stages;
  // Joints whose centre and axes the final stage held (FitOptions::min_excitation_deg): name and
  // why, e.g. "knee_l: rotation spread 1.2 deg (hinge), below 5 deg"; "...; axes only: ..." where
  // a marker on the centre keeps the centre free.
  std::vector<std::pair<std::string, std::string>> held_joints;
  // Trial markers the model lacked: attached to a segment, or left out and why.
  std::vector<AttachedMarker> attached_markers;
  // Model markers stacked on one point (FitOptions::place_stacked_markers), placed from the trials.
  std::vector<PlacedMarker> placed_markers;
  int trials = 0;
  int frames = 0;
  int markers = 0;                 // model markers with data
  int marker_samples = 0;
  int unknowns = 0;
  int residuals = 0;
  double initial_marker_rms_mm = 0;
  double marker_rms_mm = 0;
  // The solver's own figure, over the frames as it fitted them (a static trial as its mean
  // posture): where the iteration history ends. marker_rms_mm is over the frames as measured
  // (FitModel); the two differ only when a trial is static.
  double fitted_marker_rms_mm = 0;
  std::vector<std::pair<std::string, double>> per_marker_rms_mm;
  double median_marker_rms_mm = 0;
  // Markers far above the median (FitOptions::outlier_marker_ratio), worst first: name, RMS mm.
  std::vector<std::pair<std::string, double>> outlier_markers;
  // Per outlying marker, the likeliest explanation, in the same order (FitModel only).
  std::vector<MarkerDiagnosis> marker_diagnoses;
  std::vector<double> per_trial_rms_mm;        // RMS over each trial's marker samples, trial order
  std::vector<int> per_trial_samples;          // the marker samples behind each trial's RMS
  // Per trial, per frame: the RMS over that frame's marker samples (NaN for a frame without
  // any), so a report can show where in a trial the model stops fitting (a slipping marker, a
  // movement outside the model's range) rather than one number per trial.
  std::vector<std::vector<double>> per_frame_rms_mm;
  std::vector<ParameterEstimate> parameters;   // every fitted parameter
  std::vector<std::string> undetermined;
  std::vector<std::string> unmatched_trial_markers;   // in a trial, not in the model (ignored)
  std::vector<std::string> unobserved_model_markers;  // in the model, in no trial (not fitted)
  double ik_seconds = 0;
  double solve_seconds = 0;
  double covariance_seconds = 0;
  double wall_seconds = 0;
  // The residuals at the end: the median marker's RMS per coordinate, and their integrated autocorrelation time in
  // frames, 1 + 2 sum_k rho(k) (rho pooled over markers and axes, per trial, summed while above
  // 0.05): white noise gives 1; skin motion, which follows the movement, tens.
  double residual_sigma_mm = 0;
  double residual_correlation_frames = 1;
  bool reposed = false;  // the poses were re-solved part-way (FitOptions::repose_after_iterations)
  int rescued_frames = 0;  // poses replaced by FitOptions' rescue pass (all rounds)
  std::vector<std::string> static_trials;  // weighed as one posture (FitOptions::static_trial_motion_mm)
  struct FarMovedMarker {
    std::string name, segment;
    double distance_mm = 0;  // from the caller's model's place, scaled
  };
  std::vector<FarMovedMarker> far_moved_markers;  // FitOptions::far_moved_marker_sigmas, farthest first
  // Markers the scales stage weighed at less than half (FitOptions::scaling_marker_rounds): their
  // place in the model is far from where the data put them. Name, relative weight.
  std::vector<std::pair<std::string, double>> scaling_marker_weights;
  // FitOptions::marker_sigma_rounds: the rounds run, and each observed marker's sigma of the
  // final solve (mm; marker_sigma_m for a marker within the floor), model order.
  int marker_sigma_rounds = 0;
  std::vector<std::pair<std::string, double>> marker_sigma_mm;
  // FitOptions::robust_loss of the final solve: the loss, its scale (marker sigmas) and unit (mm),
  // the reweighting rounds run, and the marker samples beyond the scale at the end (down-weighted:
  // Huber weight < 1, Cauchy < 1/2), in all and per marker with its mean weight, model order
  // (markers with none beyond the scale included, so a lab sees every marker's share).
  struct RobustMarker {
    std::string name;
    int samples = 0;
    int downweighted = 0;
    double mean_weight = 1;
  };
  RobustLoss robust_loss = RobustLoss::kNone;
  double robust_scale = 0;
  double robust_sigma_mm = 0;
  int robust_rounds = 0;
  int robust_downweighted = 0;
  std::vector<RobustMarker> robust_markers;
  CoarseToFineSummary coarse;  // the coarse-to-fine start of the (first) solve
  bool converged() const { return solver.termination == TerminationType::kConvergence; }
  // The iterations of the stages that solved every frame (FitOptions::stage_frames: the stages
  // before the last may solve a subset); all of them without stages.
  int IterationsOnEveryFrame() const;
  // The iterations of the stages that searched for a better minimum (better_minimum_search).
  int IterationsSearchingBetterMinimum() const;
  std::string BriefReport() const;
};

struct FitResult {
  Model model;                                // the fitted model (unobserved markers unchanged)
  std::vector<Eigen::MatrixXd> coordinates;   // per trial: frames x n_coordinates
  FitReport report;
};

// The median over a trial's markers of each one's RMS distance from its mean position (mm;
// NaN when no marker is seen twice): how much the trial moves (FitOptions::static_trial_motion_mm).
double MedianMarkerMotionMm(const formats::MarkerTrial& trial);

// Fits `initial` to the trials. Errors name the trial: no frames, none of the model's markers,
// non-finite coordinates, a starting pose of the wrong size.
//
// Schedule (FitOptions::staged). A generic model's marker positions are guesses, several
// centimetres from where a lab put the markers on this subject, while its joint centres are
// anatomical predictions good to a centimetre or two once the segments are scaled. Freed at once
// from the generic model, the solve has two ways to move a segment's markers as a group relative
// to its frame: move the markers, or move the joint centre that places the segment (and with it
// all of the segment's geometry). Where the data do not tell them apart — a joint that hardly
// rotates in the trials, e.g. the knee of the standing leg — the weak priors decide, and they
// favour moving the one centre over moving every marker: a knee centre 13 cm from its place, a
// right hip centre 40 mm from its functional (SCoRE) estimate on welk007 at a worse marker RMS
// than the staged fit's (5.4 against 4.5 mm). So the fit runs in two stages:
//   1. scales and marker positions (the requested ones), centres and axes held at the model's:
//      the markers move to where they are on the subject (scales first with the model's
//      markers, then the markers: solved until the residual level settles, and solved again
//      from that start weighted by the error the residuals show when it is far above the
//      assumed one — markers_measure_tolerance, reweigh_markers_stage_ratio);
//   2. the whole problem (every requested group, every frame: the paper's single global LM) from
//      stage 1's geometry and poses, the priors of scales and markers centred on stage 1's
//      values. What the data determine is unaffected (the priors are weak); what they do not
//      determine stays where stage 1 put it instead of sliding towards the generic guess.
// Stage 1 solves every k-th frame of each trial when the trials have more than twice
// stage_frames frames; every frame is then posed by its model (a poses-only solve, "poses", which
// also measures the data's error for stage 2) and stage 2 solves them all.
// Static trials are fitted as their mean posture, then their frames posed by the fitted model
// (static_trial_motion_mm). The report's parameters keep the caller's model as their `initial`
// values.
Status FitModel(const Model& initial, const std::vector<FitTrial>& trials, const FitOptions& options,
                FitResult* result);

// A stage of a schedule, from the options it was solved with and its report (FitModel's own, and
// the adoption of a better minimum's: solver/fit_trust.h).
FitStageSummary StageSummary(const std::string& name, const FitOptions& options, const FitReport& report);

}  // namespace mocap::solver
