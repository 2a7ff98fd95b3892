// The real-time skeleton tracker: an Extended Kalman Filter on the body model's coordinates that
// labels the unlabelled 3D points of every camera frame, after Cuadrado, Michaud, Lugrís & Soto,
// "Using accelerometer data to tune the parameters of an Extended Kalman Filter for optical motion
// capture", Sensors 21:427 (2021), the filter whose output starts the global fit of Lugrís et al.
// (2024).
//
// State. x = [z; z'; z''] (3 n_z: coordinates, velocities, accelerations), each coordinate an
// independent constant-acceleration (white-jerk) process, as in Cuadrado et al.: without a
// dynamic model of the body (no masses, no muscles) the only prior on motion is smoothness, and
// carrying the acceleration lets the prediction follow the curved paths of limbs swinging at
// 200 Hz with a process noise small enough to keep ghosts out of the gates; a constant-velocity
// model needs a noise large enough for the accelerations, which widens the gates. The
// discretisation over dt is exact for white jerk of spectral density q per coordinate:
//     F = [1 dt dt^2/2; 0 1 dt; 0 0 1],
//     Q = q [dt^5/20 dt^4/8 dt^3/6; dt^4/8 dt^3/3 dt^2/2; dt^3/6 dt^2/2 dt]    (per coordinate)
// so the covariance prediction F P F^T + Q is done on the 3 x 3 grid of n_z x n_z blocks in
// O(n_z^2) instead of a dense (3 n_z)^3 product.
//
// Measurement. The labelled markers' positions y_m = h_m(z, p) + v_m, v_m ~ N(0, sigma_m^2 I /
// w_m) (w_m the marker's weight), through the SAME forward kinematics and analytic Jacobian dh/dz
// as the global fit (model/kinematics.h). H = [J 0 0]: only the coordinates are observed.
//
// Update (information form on the observed block). With P_zz = L L^T, A = J^T R^-1 J and
// b = J^T R^-1 nu (both accumulated marker by marker over the few coordinates of each marker's
// chain), B = I + L^T A L (eigenvalues >= 1, well conditioned for any marker precision),
// V = P_{:,z} L^-T:
//     dx  = V B^-1 L^T b                          (= K nu)
//     P+  = [0 0; 0 P_ww - V_w V_w^T] + (V L_B^-T)(V L_B^-T)^T
//     NIS = nu^T R^-1 nu - (L^T b)^T B^-1 (L^T b)   (= nu^T S^-1 nu, Woodbury)
// The first term of P+ is the covariance of the velocities and accelerations given the
// coordinates (a Schur complement the measurement does not change), the second the posterior of
// the coordinates carried to all states; both are positive semi-definite by construction, so P
// stays symmetric positive-definite where the textbook P - K S K^T can lose definiteness when the
// markers are much more precise than the prediction (tests/test_ekf.cpp checks both claims). It
// costs O(n_z^2 (3 n_z)) whatever the number of markers: the innovation covariance S, up to
// 117 x 117, is never formed or factored, and the sequential per-marker alternative (39 rank-3
// updates of the 114 x 114 P) is about three times the arithmetic. At n_z = 38 the factorisations
// are small hand loops and the products plain GEMMs (ekf/filter.cpp); bench/track_vs_ik.cpp
// measures it.
//
// Labelling. Each predicted marker m gates the points by its Mahalanobis distance with the 3 x 3
// innovation covariance S_m = J_m P_zz J_m^T + R_m; a globally optimal assignment (ekf/assignment.h)
// of markers to gated points, where each marker may also stay unassigned at the price of the gate,
// so two labels never take one point and a marker takes a point only when it is the best use of
// that point. Unassigned points are ghosts or strays (label -1). A marker missing for a while has a
// growing S_m and is picked up again when it reappears inside its gate. A label the frame cannot
// decide is left empty: a point that two markers of different segments, neither labelled in the
// last frame, could each take afresh is given to neither, since the assignment would decide it by
// the joint angle between their segments, which is what is in doubt where both markers are lost
// (a shank the start placed 8 cm off: RHEE on RANK's point from frame 1 for a whole trial, seed 6
// at 8 ghosts). They wait for a frame that tells them apart, or for the segment registration and
// the limb search, which fit the segment as a whole. Two markers of one segment are paired by its
// rigid geometry, which no angle changes, and a marker continuing its label is not held back.
// Within a segment the same holds where its rigid geometry, not its pose, says whose a point is:
// a point taken afresh that the segment's joint centre and labelled markers fit clearly better
// as an unlabelled mate is left empty, and the verdict follows the point's track (a forearm
// turned about the line from its elbow centre to its forearm marker while both wrist markers were
// hidden: one wrist point back is the other's mirror image, and the drifted prediction took it
// for the wrong one, seed 13 at 8 ghosts). Not in the first second, whose offsets are not learnt.
// A label taken afresh is provisional for a window of 40 frames (0.2 s) -- one frame's decision,
// made by a prediction that drifted while the marker was hidden, or by a limb search's placement
// -- and within it the point it holds is compared, frame after frame, with the best unclaimed
// rival that came after it, on what the decision cannot have bent: the segment's rigid distances
// (to its joint centre and its committed markers) and where the marker's point last was while
// committed, carried with its parent segment. A rival that fits the distances and is clearly
// better on either over 5 frames of its track takes the label; one an unlabelled mate could be is
// left to the mate rule above (distances do not tell mirror images apart). A hidden marker whose
// gate took a reflection riding beside it, or a toe marker the limb search put on a reflection,
// is then given its own point when that comes back (seed 47 at 5 ghosts: the finger marker on a
// reflection, then without a label for the rest of the take, 0.981 -> 0.9993 of the labels).
// The start's labels are the last frame's for the first tracking frame (at 12 Hz its 83 ms of
// the start's velocity uncertainty made an unlabelled forearm marker's gate 30 cm wide, and it
// took an elbow marker's point, the elbow markers shifted along the arm for the whole trial).
// Two rigid-body facts hold
// whatever the pose estimate, and the gate keeps to them. Labels follow point tracks: a point that
// continues the point a marker held in the last frame (mutual nearest neighbours, moved as the
// marker's prediction moved, within a frame's motion) is that marker's or nobody's, so a marker
// back from an occlusion with a grown gate cannot take its neighbour's point (a wrist marker on the
// other wrist marker's, the neighbour left unlabelled, the forearm then turned to fit for seconds).
// Nobody's, too, where an unlabelled marker of another segment explains the continuing point
// better than the holder does: a marker hidden under another that appears beside it in the same
// frame hands its track over (RASI under the right hand, seed 22). A label the segment
// registration's re-check moved to another point, outside its gate because the pose was wrong,
// keeps the point that continues it to its second frame, when its limb is placed anew (the gate,
// about the wrong pose, would give the points back: a crossed wrist pair, seed 34 at 8 ghosts).
// And a marker held before, missing for 5 frames, does not take afresh a point that continues an
// unclaimed track unless its prediction explains the point better than the density of lasting
// reflections does (its gate grows over the coordinates only it measured: a toe's gate took a
// reflection 57 mm off, seed 42 at 8 ghosts).
// And a point can be a marker only at the marker's distance from its segment's joint centre
// (within the marker's gate on its own variance plus 2 cm for the predicted centre; not for the
// root): a segment turns about its joint, so that distance does not depend on the angles the gate
// is long along (a finger marker's gate, its hand held by that marker alone, over a wrist marker).
// Rigid groups, where the frame rate is low against the motion. At 12 Hz a swinging foot or shank
// is 4-11 cm from its prediction, more than its markers' 5-6 cm spacing, and the gates' labels are
// guesses (biobuddy's hip trials: an ankle marker on the unmodelled medial one's point for 60
// frames). So a segment whose best-held marker's predicted spread (the gate's radius on the
// prediction alone) is over half the distance to its nearest neighbouring marker, with three or
// more markers and one labelled in the last 0.5 s, has its markers labelled as one rigid body
// (LabelLooseSegments): poses from its joint centre and each pair of its markers on candidate
// points (in their gates, at their distances), each pose labelling the rest; the rigid residuals
// plus the prediction's Mahalanobis distances (the prior) plus the gate for each marker left out
// decide, three labels at least, by a margin. Segments go root first and a fitted segment places
// its loose children's joint centres; a child's gates (and its prior) are then centred on its
// markers' predictions moved as its joint centre moved. At 12 Hz most of a foot's prediction
// error is the swinging shank's, which the shank's fit has just measured: gated about the
// predictions alone, the left hip trial's foot came 8-10 cm off, at the edge of its gates, its
// markers were missed or took their neighbours' points, and one such label drove the ankle to its
// range for a second (0.994 of the labels; moved with the centre, 0.99996). Moved, not turned
// with the parent's fitted rotation: the joint centre lies among the parent's markers, where
// their fit places it well, but the rotation, carried out to the child's markers, is as good as
// the parent's spread of labels (the pelvis fitted on RASI, RPSI and S3 with its left markers
// hidden turned the left thigh's expected places 7-9 cm the wrong way: 0.9976). A segment
// without markers between the two (an OpenSim model's talus, between shank and foot) has no fit
// of its own: the foot's centre is carried by the shank's fit, where that fit places it within
// the unfitted centre's tolerance (its rotation's error times the distance beyond the shank's
// markers; gait2354's walk has none at the ankle). Left where the prediction put it, welk007's
// swinging foot at 12.5 Hz kept its sphere 12 cm off and lost its labels for 1-4 frames in each
// fast swing (0.987 -> 0.994 of the labels, 13 -> 2 wrong). Not done:
// candidates beyond the gates (the sphere about a fitted joint centre alone, the prediction's
// prior capped): the fits then chose rotations of a shank about its long axis, on the medial
// markers no model has (left hip trial 0.995 -> 0.978).
// The code is in three files, one question each: ekf/tracker.cpp (the filter and a frame's
// sequence), ekf/tracker_labelling.cpp (which point is which marker), and
// ekf/tracker_initialisation.cpp (finding the subject, or a limb, without labels).
// On probation: a marker coming back is labelled at once, but its measurement enters the update
// only from its second consecutive labelled frame, when its point moved from the first one as its
// prediction did (within 1 cm). Half the ghosts near a body are single-frame reflections; one
// inside the long gate of a hidden marker on a loosely held segment (a toe with only the heel seen)
// would otherwise move the segment by centimetres at the marker's full precision and leave the true
// marker outside its gate when it reappears. Lasting ghosts (reflections fixed in the lab or riding
// along with a marker, alive for up to seconds) are told by their past: the tracker keeps the last
// 20 frames' points, and a point that a marker without a label in the last frame would take is
// followed back through the unclaimed points (nearest within 2.5 cm a frame); seen for 5 frames or
// more with its distance to the marker's joint centre varying by over 1 cm, it is not on that
// segment and stays out of the marker's gate. A marker back from an occlusion has no past and is
// not judged. A reflection that rides along with a marker (or sits where it passed) keeps its
// distances to the segment and outlives that 20-frame ring, and in the frame its marker is occluded
// it is the nearest point in the gate: so each unclaimed point carries, for as long as it is
// followed (mutual nearest neighbours between frames), which markers were measured on other points
// beside it in the last 2 s, and stays out of those markers' gates -- one marker is one point. In
// the first second of a track, whose labels may be wrong, this holds only for a marker labelled in
// the last frame or that has held its point for 0.1 s; a marker that loses its label while
// another marker takes its last point held the wrong one, and its records go. The gate of a marker
// labelled in the last frame also holds its own model error: the mean square of its residuals after
// the update (an average over the offsets' time constant), which with a nominal model grows with
// the pose (joint centres 15 mm off) and would otherwise push a tracked marker out of its gate in a
// deep squat or trunk bend; the same variance weighs its measurement. A marker coming back is gated
// without it (a wide gate at a hidden marker takes ghosts). Segment registration: the
// markers the gates leave unlabelled are looked for as a group under their segment's rigid
// geometry, which no error of the pose estimate changes. A segment's markers and its joint centre
// (where its parent's pose puts it) are a rigid body; each choice of unclaimed points for its
// unlabelled markers, with its labelled markers' points, is fitted as a rigid body (Kabsch), every
// anchor within its gate on its own variance and the whole fit's chi-square within the gate's tail
// on its 3n - 6 degrees of freedom (the fit spreads one wrong point's error over every anchor: a
// reflection 88 mm from a hidden pelvis marker passed each anchor's 18 mm gate with 13-18 mm
// residuals, a chi-square of 41 on 6), and each label the choice gives anew within its gate of
// where the other anchors alone put it (its deleted residual, with the others' fit's covariance:
// with four anchors a reflection 33-38 mm from a hidden head marker's place passed both tests
// above); the choice labelling the most markers at the least
// cost is taken only when no different choice comes within the initialisation's log-likelihood
// margin, and only for points no other segment's unlabelled marker could also be (in its gate and
// at its distance from its joint centre). With three or more of the segment's markers labelled
// the fit pins a marker's place and a point there is judged as the gating judges one (a pelvis
// marker back 2-5 cm from a nominal model's prediction among its labelled mates). With fewer, the
// fit checks only distances, so it looks only for a marker missing for 20 frames (stuck: its
// segment's pose is wrong -- a foot turned over while its markers were hidden, an upper arm turned
// about its long axis, a nominal model's knee marker 25-40 mm off in a deep squat -- with its
// point 5-25 cm from the prediction for seconds), and only at points followed back 5 frames or
// more at constant distances (1 cm) from the joint centre and the segment's labelled markers while
// moving 2 cm or more (a reflection fixed in the lab is rigid with a segment at rest); a marker
// just back from an occlusion is the gate's (a reflection riding with the segment can sit at its
// place). Such a label goes through probation; a label outside its gate is not measured (one
// linearised step of decimetres threw whole legs off the body, and one scaled down to the gate
// left the limb a velocity that ran on): its limb is placed anew by the limb search (below).
// Labels already given are re-checked the same way. A swap within a segment (a forearm turned
// about its axis while hidden, one wrist marker back on the other's point, that one's own point
// left over) keeps every label on a point and every distance right, so no gate sees it; but the
// segment then has a marker stuck beside a point that its labelled mates could be. So for a
// segment with a marker stuck for 20 frames, the labelled markers whose points it could be (at
// its distance from the joint centre) are re-opened, one or two at a time, and enumerated with it:
// a swap or a shift is one more hypothesis of the same rigid fit, taken only when no other
// labelling comes within the margin (two wrist markers and the elbow centre alone are mirror
// images and cannot tell; with the forearm marker the fit can). A marker so relabelled held a
// wrong point: its seen-beside records go and its new label starts on probation. The re-check
// runs on every frame of a marker's first 20 stuck frames (before another marker takes the point
// a swap left over), then on every 20th. The rigid fits are bounded: 100 a re-check (one cut
// short leaves the registration's own decision), 600 a frame (a search cut short decides nothing).
//
// Initialisation and recovery. Without any labels, the subject is searched for around the
// cloud's centroid at several headings about the vertical (the points turned so that the lab's
// vertical, options.up, is the model's, options.model_up), from the static pose (and,
// after a loss, from the last good pose). Each hypothesis is refined ICP-like (assign markers to
// points by distance with the optimal assignment, one damped Gauss-Newton step on the pose with a
// weak prior towards the start and the model's joint ranges, reassign), placing the body from the
// root outwards: stage d frees the joints at depth <= d of the tree and pairs only the markers
// they carry, so a distal marker is paired once its parents are in place. Then a few restarts
// from the best placement (the static pose bent towards the middle of the joint ranges, and
// random perturbations). Then the best placement's labels are exchanged pair by pair (two
// markers on points within 10 cm), each exchange held while the pose follows it and then
// released: every search assigns by distance from where its pose puts the markers, so all settle
// in the same minimum where two neighbours are each nearer the other's point, when only a large
// turn of the pose makes the right pairing the nearer one (welk007's wrist markers on radius and
// ulna, at the end of the 90 degree pronation range the static pose starts at the other end of).
// An exchange that labels as many markers at a lower score replaces the best; exchanges are tried
// only on a best placement that passes the acceptance tests on its own (they decide between
// labellings of a subject found, and do not find one on ghosts). The best score wins
// when its residual is small, enough markers are labelled, and every differently labelled
// hypothesis is worse by a log-likelihood margin (markers exchanged pairwise do not count: each
// pair was its own decision). Tracker::initialisation() says what the last search did and why it
// refused. A label that alone turns its limb is then left empty where a second configuration is
// at hand: the search's prior (0.5 rad) is a pin for what no marker holds, and it prices half a
// radian of a joint at about a centimetre of residual against the final radius (5 cm) for a
// marker left unlabelled, so a limb whose turn one marker decides (a foot's subtalar angle by its
// toe marker, a hand by its finger marker) turns for any point that marker can reach -- a
// reflection beside the foot won over the toe's own point, 41 mm from where the rest of the body
// put it, and stayed 339 frames (simulated seed 37 at 5 ghosts, the sweep's worst seed). So each
// labelled marker's deleted residual is taken (the pose refitted without its label, the prior at
// the static pose), and its label is left empty when that exceeds the final radius, an unclaimed
// point lies within the radius of where the rest of the body puts the marker, and the label takes
// the marker's chain farther from the static pose than the rest does; the limb starts where its
// other markers and the prior put it, and the gates decide from the next frame. A label the rest
// of the body cannot place but no other point competes for (a generic model's acromion marker 55
// mm off) keeps it, as does one that holds its chain nearer the static pose than its mates' model
// error would (LeaveSelfDecidedLabelsEmpty).
// Deferred labels. The search labels each marker with the point nearest where its placement
// puts it, and the placement is fitted to those labels, so with a nominal model (distances 1 cm
// off the subject's) a reflection near a marker's place can win over the marker's own point by
// the placement's pull alone. What the placement cannot bend is the segment's rigid geometry --
// the point's distances to its joint centre and to its labelled mates -- and that the model knows
// only to its own error: the start's residual variance per coordinate for each marker (7-9 mm RMS
// for a scaled nominal model, 2-3 mm for the true one) and 2 cm more for a predicted joint centre.
// A label whose point an unclaimed point within the search's radius fits better by those
// distances is the placement's guess: it is left empty and the pose refitted without it, and
// the candidates (its point and each such rival) are followed as point tracks.
// Their motion decides, not the model: a candidate whose distance to a mate changes by over 1 cm
// is not on the segment (a reflection fixed in the lab or riding elsewhere; the marker moves with
// its segment); one lost for 0.2 s (longer than an occlusion) or after its first frame (a
// single-frame reflection) is gone; the one left is the marker's, and the gates may give it.
// A standing subject moves no point a centimetre, but sways a few millimetres, and a point not on
// the segment moves against its mates by some of that: a distance's mean over 0.1 s (0.16 mm of
// noise in simulation against one frame's 0.7 mm) that differs from its first 0.1 s's by over
// 1 mm rules the candidate out too. Simulated seed 127 at 8 ghosts: RKNE labelled right, a
// reflection 40 mm off fitting the thigh's distances better (chi-square 0.9 against 1.7); the
// reflection's distance to RTHI drifted 1-1.6 mm, its own point's 0.4 mm at most, and RKNE waited
// unlabelled 368 frames, to the end of both tracks; now 100. A candidate ruled out is kept from
// the marker while it lives, and the one decided, while hidden, is looked for where it was seen
// for 0.2 s and the marker given no other point (seed 120: RWRB, decided at frame 40, took a
// ghost 78 mm off in the frame its point hid).
// Until then no stage (gates, registration, limb search, provisional window) gives the marker
// any candidate; a point that comes later is the gates' as ever. A deferral ends when its marker
// has held a label 20 frames, or after 2 s (about a stray reflection's longest life). Simulated
// seed 120 with the nominal model: RWRB placed 11 mm from a reflection and 25 mm from its own
// point, both fitting the forearm's distances within a centimetre (the own point better: a
// chi-square of 2.9 against 11.9); it held the reflection 71 frames. Only a rival that fits
// better: deferred also where a rival fitted worse within a log-likelihood margin of 6,
// welk007's L_toe (its hip trial, the scaled OpenSim model: chi-square 2.9 on its own point, 7.9
// on a point 40 mm off) was left empty and the trial lost 241 labels (0.99970 -> 0.97796).
// Scaled to the subject (TrackerOptions::init_scale_to_subject): a lab calibrates a generic
// model to its subject, and so does the tracker, at every start by default. A generic model
// (OpenSim's gait2354, whose femurs are 15 % short of its example subject's) can put markers
// farther from their points than the search's 5 cm, and no heading or restart mends a matter of
// size; a nominal model that does start leaves its markers 15-25 mm RMS from their points, and
// markers that its predictions miss by 3-20 cm unlabelled. So each segment's scale factor (its
// markers and its child joints' centres scale with it, model/model.h) is fitted with the pose to
// the best placement's points, from the root outwards and reassigned at each step, with a prior
// at the model's own scale; then the whole search runs again on the scaled model. Where the
// model's own size gave a labelling too and the scaled one differs, each is fitted with the scales
// free to its labels alone, and the scaled one is taken only when it fits clearly better (the
// search's log-likelihood margin) and every label it adds or changes lies within its gate of the
// noise the model's own labels leave; else the model's own labels start, at the scales fitted to
// them. The track keeps the scales (InitialisationSummary::segment_scales), and the offsets'
// prior is then what the scaled placement left unexplained (its RMS, 7-9 mm on the simulated
// subjects, and no less than 1 cm: with the true model's 2-3 mm the gates lost markers) instead
// of the nominal model's marker_offset_sigma: a first-second gate ~4 cm wide, not ~10 cm, in
// which a hidden wrist marker no longer takes a ghost. Told to, only before the first
// track and when the model's own size cannot start (too few labels, too large a residual; not a
// start refused as ambiguous), or never. A model fitted to the subject (ModelOrigin: the global
// fit's result, given by SwapModel) is scaled only when its own size cannot start.
// Markers the model cannot place -- stacked with another marker of their segment on one point, a
// generic model's placeholders for a lab's cluster markers (solver/attach_markers.h,
// StackedMarkers) -- are treated as unseen: never searched for nor labelled (picking them up by
// their rigid motion with their segment is not done).
// The track is declared lost when too few markers are labelled, or the NIS per measured
// coordinate is too high, for `divergence_frames` consecutive frames; the tracker then
// re-initialises automatically from the incoming frames.
//
// Limb re-acquisition. While the rest of the body tracks, one limb can settle in a wrong but
// self-consistent pose (a foot left with its heel marker only; a thigh turned about its long axis
// or a head turned after a re-initialisation) from which its other markers' gates never meet
// their points again. A marker unlabelled for 0.1 s of tracking frames (re-tried every 0.1 s; at
// least every frame at low rates) has the
// subtree of the joint that moves it (the nearest one whose subtree carries another marker, so a
// hand with one finger marker goes with its forearm; up to 12 coordinates; the root and the
// trunk are the global search's) searched again ICP-like among the points no other marker took,
// from its current pose and four restarts (the limb at the static pose -- the prior's mode, for a
// limb lost far from its pose --, its joint angles halfway to the middle of their ranges, fixed
// pseudo-random perturbations). The search runs only when an unclaimed point could
// be the marker: within 25 cm of its prediction and at the marker's rigid-body distances from
// its segment's other labelled points and from the segment's joint centre -- ghosts near the
// body are nearly always within 25 cm, rarely on those spheres. The limb's labelled markers keep
// their points; only its unlabelled ones are placed. The best placement replaces the limb's
// coordinates (velocities and accelerations zeroed, their covariance reset to the
// initialisation's) only when it labels more of the limb's markers than the track does (or as
// many, when it is placing a limb for a label outside its gate: see "Labelling"), their RMS
// distance is within 3 cm, EVERY label the placement gives lies within its gate on its measurement
// noise alone (gate_chi2 x the marker's variance: an RMS bound alone passes a marker put on a
// ghost 3 cm away; a label it keeps is not so held -- while the limb sat in the wrong pose, the
// marker that held it there learnt the pose's error as its offset, and gated it refused the
// placement that mends the limb), no differently labelling restart comes within the init_ambiguity_margin
// log-likelihood margin, and no new label is on a point whose past is not rigid with the
// marker's segment (as in the gating above: a lone finger marker's two wrist angles fit any point
// at the right distance from the wrist); and a placement whose one new label its segment does not
// pin -- fewer than three of the segment's other markers labelled (a hand's finger marker; a toe
// marker with the heel hidden, or with the heel alone, the foot free to turn about it) -- needs
// that point to have moved rigidly with the segment (the segment registration's standard for an
// unpinned marker: a reflection beside a hidden finger marker has no such past). And every label
// the placement gives must be on a point the last frame had, where the marker moves slowly
// enough for its point to be followed (at 12.5 Hz a swinging foot's point is new in every
// frame): the placement replaces the limb's coordinates at once, so it takes no single-frame
// point, as the gates' probation takes none into the update (seed 10 at 8 ghosts: in the fresh
// track a forearm placed on a reflection born in that frame, RWRB on RWRA's point for 51 frames).
// In the first second after a (re)initialisation the
// labels themselves are suspect (a search over one frame can label a limb wrongly but
// consistently), so there the search may also relabel the limb's markers and runs whenever any
// unclaimed point lies within 25 cm, and no point's past is judged, here or in the gating (the
// joint centres may be wrong with the limb) -- but one: a lone unpinned new label on a point
// that has stood still for 5 frames is refused there too. The subject stands still in the
// static start, a reflection fixed in the lab is as still as the marker's own point, and the
// placement that turns a foot onto it is the prior's guess, not evidence (seeds 93 and 101 at 8
// ghosts, true model: 65 and 378 frames of a toe marker on such a reflection).
// After the first second a limb's labels are re-checked where the evidence says they are wrong
// (LimbLabelsInDoubt): a marker stuck for 20 frames whose point, by the rigid geometry, is one a
// marker of its own limb holds (within 25 cm of its prediction, at its distances from its joint
// centre and its segment's other labelled markers, the holder left out), while a point no marker
// holds has moved rigidly (within 1 cm) with one of the limb's segments, followed 5 frames or
// more over 2 cm or more. A limb labelled one marker round: every label on a point, every
// distance the gates check right, so no gate sees it and the limb search, which keeps the
// labels it finds, cannot mend it (simulated seed 13 at 50 Hz, the true model: in the elbow's
// flexion-pronation RWRA on RWRB's point, RFIN on RWRA's, RWRB unlabelled beside its own point,
// 1,938 wrong labels for the rest of the take; re-checked, 52, the longest run 496 -> 43
// frames; at 200 Hz a wrist marker on its mate's point, seed 144 at 8 ghosts 36 -> 22 wrong,
// seed 98 at 5 ghosts 60 -> 49; seeds 1-50 unchanged). Stuck means without a label that lasted
// past its first frame (one the next frame took back was a guess), and the test is made every 5
// frames of the run, the span over which a spare point's past is judged (seed 159 at 8 ghosts:
// LWRB on LWRA's point, the spare points back but still for 8 frames, then rigid and moving; a
// one-frame label had restarted LWRA's run and the next check was 20 frames off: 46 -> 38 frames
// wrong at a stretch). The limb is then searched as a fresh
// track's is, its labels free, and the placement is taken on the search's own terms: MORE of
// the limb labelled than now (the spare point explained), every label it gives within its
// gate -- a moved label's allowing for its learnt offset, which was learnt on the wrong point
// and is cleared when the placement is taken --, no differently labelling start within the
// margin, no new label on a point whose past rules
// it out (judged from the limb's own joint centre only: the centres below it were placed by the
// labels in doubt). The moved markers' seen-beside records go (made under the wrong labels). A
// re-check takes turns with another limb's search due in the same frame (the one-search budget).
// Not done: a labelling as full as the present one but crossed (a wrist pair on each other's
// points, all labelled), which the search's count cannot tell; that needs the rigid fits'
// evidence over frames (no such run of 6 frames or more in the sweeps' seeds 1-50 and 111-160:
// their wrist runs on a mate's point have the mate unlabelled).
// Allocation-free; a hidden marker with no plausible point near costs nothing. At most one limb
// search a frame (the one nearest the root): with the segment registration's fit budget, that
// bounds a tracking frame's work (the search's five starts of ten damped Gauss-Newton steps are
// the largest item, about 1 ms on the 2-core VM).
// A limb none of whose markers is labelled (welk007's forearms in its hip trial: flexed 90
// degrees and pronated, where the start's search, from arms hanging, left all six unlabelled)
// has no pose to search near, and its parent's pose is only as good as the markers that hold
// it. So its search takes the smallest subtree above it that holds a labelled marker (the whole
// arm: the forearm's markers also turn the upper arm about its long axis), the angles of its
// joints with no label below them start (after the current and the static pose) at a quarter,
// half and three quarters of their ranges and may pass the ranges by 1 rad (a generic model's
// range is not the subject's: Rajagopal's pronation stops at 90 degrees, welk007's wrist
// markers fit right only at 147; the filter brings the angle back and the offsets learn the
// rest), it runs for any unclaimed point at the marker's distance from its joint centre however
// far from the prediction, and, for a marker the start did not label, from the first tracking
// frame (it has no gate to come back through). Only there: across and past their ranges, the
// wrist angles of a hand whose finger marker was hidden settled on ghosts (simulated seed 10 at
// 8 ghosts). And a placement about to be taken has its new labels exchanged pair by pair, as at
// the start ("Initialisation and recovery"): every start settled with the wrist markers crossed.
//
// Model error. A nominal model (before the global fit) misplaces markers by 1-4 cm; each marker
// carries a learnt offset in its segment's frame, and its measurement variance is inflated by
// what is not yet known of it (TrackerOptions::marker_offset_*). SwapModel clears them. Told to
// (marker_offset_prior_frames > 0, off by default), while the subject stands still the offset is
// the mean of the marker's residuals (the static start, where they measure its place on the
// segment), so a marker seen in the static is gated where it was seen, not within the prior's
// 10 cm of the nominal place, which took ghosts there (issue 15); off because it also locks in a
// label the first frames gave wrong (BENCHMARKS.md, seventeenth session). The
// error of a nominal model depends on the pose, so a marker back from an occlusion can find its
// learnt offset stale by 25-40 mm (a knee marker in a deep squat); the segment registration
// (above) finds its point where its segment's rigid geometry puts it, and its offset learns the
// new error from its measurements. (Moving the offset onto such a point at once, as an earlier
// rule did, could move it onto a reflection riding with the segment and leave it 5-9 cm wrong for
// good.)
//
// Unobserved coordinates. Velocities and accelerations decay between frames (time constants in
// the options), and coordinates are kept in the model's ranges. A coordinate that no measurement
// has observed for 10 frames stops within 50 ms: its last velocity is no evidence of where it went
// (a knee whose shank and foot markers were all hidden ran on a velocity that one surprising
// measurement had given it, to 40 cm from the markers when they came back); a shorter gap keeps
// the extrapolation that picks a marker up again. Observed means pinned by the evidence: the
// frame's measurements alone (their information on the coordinate, the diagonal of J^T R^-1 J)
// hold it within twice its initialisation sigma (0.1 rad, 2 cm), not merely that a measured
// marker hangs below it. A foot whose toe marker is hidden keeps its heel marker, 5 mm from the
// subtalar axis: in that angle's chain, but bounding it only to about 0.6 rad. Counted as observed,
// the angle ran on the velocity each heel residual gave it, the toe came back 10-20 cm from its
// prediction (the commonest missed label of the sweep, 13,300 of 5 ghosts' 39,000), and the heel's
// offset learnt the turned pose as its own error (66 mm on seed 44, whose heel then stayed
// unlabelled for most of the trial).
//
// Process noise. The jerk spectral densities (options) are an upper bound: what the simulated
// 200 Hz scenes' fast limb motion needs to keep the filter's velocities and accelerations agile.
// A subject's motion can be far smoother, which at 100-200 Hz hides under the measurement noise
// (welk007's hip trial labels the same with the bound or a hundredth of it) but at 12 Hz decides
// every gate: one 83 ms step adds q dt (56 rad/s^2 at the bound) to an acceleration's standard
// deviation, and a swinging foot's gate was a metre wide while its points came 4-15 cm from
// their predictions; the gate then said nothing and the assignment paired the foot's markers
// with their neighbours' points (welk007's hip trial with every 8th frame kept: 0.80 of the
// labels). So each coordinate's noise is learnt below the bound by covariance matching (Mehra
// 1972): each measured marker's squared innovation against its predicted spread (J P_zz J^T plus
// its measurement variance), shared among its chain's coordinates as they make its prediction's
// covariance, moves the coordinate's factor by (ratio - 1) over process_noise_time_constant_s --
// an arithmetic average, so the bursts of fast motion count at their size. A marker counts only
// as far as the prediction makes most of its spread (weight 2 f - 1 for a fraction f over a
// half): where the measurement noise makes the gate (200 Hz), the innovations say little about
// q, and a factor learnt from them anyway made the simulated sweep's labels worse (worst seed
// 0.93 at 5 ghosts, from 0.996), as did following the factor in the logarithm (a geometric mean,
// which the bursts hardly move). The predicted covariance is close to proportional to q where the noise makes
// it, so the factor that matches is the present one times the ratio.
// That weight leaves the estimate biased low: the measurement variance is an upper bound (it
// holds the model's error), so the innovations are smaller than the spread made with it at any q,
// and at 40-100 Hz, where the prediction makes about half the spread, they pulled a quiet limb's
// factors to the floor (1/256) while the innovations that said the motion had started were
// weighed as little (the scene at 50 Hz: a hand lost for 10-160 frames in the wrist
// circles). At 40 Hz and up each innovation is matched against the prediction's part plus the
// marker's learnt model error (its residuals' mean square: the noise as seen, not its bound), and
// one beyond its whole spread with the bound, which the bound's slack cannot have made, counts in
// full -- as the hidden gates' factor is learnt. Below 40 Hz the prediction makes the gates, the
// innovations count nearly in full already, and this widened them (test_ekf's 12.5 Hz run). The
// model error in the weight too (the textbook form with R known) sends every factor to the floor:
// the filter's prediction spread is itself made with the bound (its posterior) and stays above
// the innovations (ekf/tracker.cpp, LearnProcessNoise; BENCHMARKS.md, "Frame rates").
//
// Hidden markers' gates. While a marker is hidden its prediction's covariance grows with the
// process noise of the coordinates only it measured, and at 200 Hz that noise stays at its bound
// (the fastest motion's: a frame's innovation there is the measurement noise's, which the learnt
// process noise weighs out): a still hand's hidden finger marker had a gate 18 mm in standard
// deviation about a prediction 1 mm from its point after 20 frames, and took a reflection born
// 30-40 mm away that then rode with the hand (simulated seed 47 at 5 ghosts, 30 frames; seed 24 at
// 8 ghosts with the true model, 35). The marker's own returns say the gate is ~30 times too wide
// there, but returns are the wrong evidence: one outside its gate is never seen, so a factor
// learnt from them can only narrow the gates, and one learnt while a limb stood still left a toe
// refused 23 mm from its prediction for 2,366 frames once the foot moved (BENCHMARKS.md,
// twenty-third session). So every update forecasts each marker 0.25 s ahead as its prediction
// would run were it hidden from then on (the state open-loop, each coordinate stopping after 10
// frames as an unobserved one does), in the frame of its nearest ancestor segment with markers
// (they stay in view and hold that segment while it is hidden), with the spread that prediction
// has over the coordinates below that segment; a horizon later, each measured marker compares its
// point with the forecast. Covariance matching on those comparisons (the squared error over the
// spread, averaged over 0.5 s, weighted as the process noise's frames are, counted in full where
// the error passes the whole spread) gives each marker a factor in [1/16, 1] on its prediction's
// covariance in the gate of a frame it is not labelled in (its measurement variance and its learnt
// model error unscaled: a nominal model's elbow marker comes back 19-30 mm from its prediction, its
// pose-dependent error, and without that term it was refused for 191 frames, seed 34 at 8 ghosts)
// -- the gate test only: the update, the
// filter's own noise and the densities the other tests weigh a point by are as before (the process
// noise learnt so, tried first, left the filter too stiff: it lagged when a limb started moving,
// and tracked markers left their gates, a pelvis lost in the squats; the densities scaled too, two
// forearm markers crossed for 6 frames in seed 38's swap traps at 8 ghosts). The forecasts are
// judged in every phase, whatever their error, so a factor learnt while a limb stood still rises
// as soon as it moves. Past the horizon the forecasts say nothing (a limb that stood still may
// have started moving while its marker was hidden): the factor goes back to 1 over as long again.
// Not below 40 Hz, where the horizon is shorter than those 10 frames and the learnt process noise
// sees the prediction in each frame.
//
// Weakly observed coordinates. A heel marker lies 5-9 mm from the subtalar axis, so with the toe
// hidden it tells the subtalar angle about 0.8 rad in standard deviation a frame -- less than the
// joint's range does (a uniform distribution over 120 degrees: 0.6 rad). The update still moved
// the angle by all of it: each heel residual the nominal model leaves (a millimetre) turned the
// foot by 0.05 rad, and with the foot still the angle ran to its range in 0.2-0.3 s; the toe came
// back 59-175 mm from its prediction, outside its gate, and was left unlabelled for thousands of
// frames (simulated seeds 96 and 122 at 5 ghosts). The residuals are the
// measurements' systematic error, which does not average out, seen through a lever too short to
// resolve it. So an update whose measurements tell a coordinate less than its range does (the
// diagonal of J^T R^-1 J, an upper bound on what they tell it with the others free, under
// 12 / width^2) leaves that coordinate, its velocity and its acceleration where the prediction
// put them, as a consider state of a Schmidt-Kalman filter is; its covariance is left as the
// update makes it (a Schmidt filter would leave that at the prediction's too: not tried). Only a
// coordinate the measurements see (A_ii > 0): one none of them sees is moved only through its
// covariance with those they pin, the filter's knowledge of coupled motion, not a short lever
// (frozen too, seed 60's stuck left leg at 5 ghosts went 0.985 -> 0.977 of the labels). Not below
// 40 Hz, the rates the hidden-marker forecasts skip: there a frame's motion is a large part of a
// joint's range, and the weak measurement is still the best evidence of it (12.5 Hz, the scaled
// start: 0.9606 -> 0.9510 of the labels, 109 -> 233 wrong). Nor the stricter test of Predict's
// "observed" (2 initialisation sigmas): a forearm whose wrist markers are hidden is told its
// pronation to 0.12 rad a frame by its forearm and finger markers, and frozen it lost its labels
// (seed 34 at 8 ghosts, 4 -> 55 wrong; the protocol's angles 0.3 -> 3.2 degrees RMS).
//
// Angles. A coordinate that only drives identity rotations and whose range covers a full turn
// (the pelvis heading of the default model) is kept in (-pi, pi]: h is 2 pi-periodic in it, the
// innovations are in marker space, so wrapping it changes nothing but keeps z bounded.
//
// Shape (after Pinocchio): the Model is immutable and shared; the Tracker owns its workspace,
// sized at construction, so Update allocates nothing while tracking (tests/test_ekf.cpp checks it
// with EIGEN_RUNTIME_NO_MALLOC). Initialisation frames (searching for the subject) may allocate.
// A Tracker is not thread-safe; use one per stream.
#pragma once

#include <Eigen/Core>
#include <memory>
#include <string>
#include <vector>

#include "model/kinematics.h"
#include "model/model.h"
#include "model/status.h"

namespace mocap::ekf {

struct TrackerOptions {
  // Nominal frame rate: the time step when a frame's time does not advance.
  double rate_hz = 200.0;
  // Process noise: spectral density of the white jerk of each coordinate
  // (rad^2/s^5 for rotations, m^2/s^5 for translations).
  double jerk_psd_rotational = 4.0e4;
  double jerk_psd_translational = 4.0e2;
  // Learnt process noise: the jerk PSDs above are an upper bound, each coordinate's scaled down
  // (to no less than min_process_noise_scale of it) while the measured markers' innovations are
  // smaller than their predicted covariance says, where the prediction makes most of that
  // covariance (covariance matching over process_noise_time_constant_s; "Process noise" above).
  // At 100-200 Hz the measurement noise makes most of a gate and the factor moves little; at
  // 12 Hz the prediction's uncertainty is all of it. 0: the PSDs as given.
  double process_noise_time_constant_s = 0.5;
  double min_process_noise_scale = 1.0 / 256;
  // Decay of the velocities and accelerations between frames (exp(-dt / tau)): a coordinate that
  // the markers stop observing (a foot whose toe marker is hidden, so that only the heel marker
  // holds its two angles) coasts to a stop instead of running away on its last acceleration and
  // leaving the toe marker's gate. Long against a frame (5 ms), so observed motion is not lagged.
  double velocity_time_constant_s = 0.5;
  double acceleration_time_constant_s = 0.1;
  // Measurement noise: standard deviation of a marker coordinate (metres). It covers the
  // triangulation noise AND the model's own error (skin motion, a nominal model before the fit),
  // which is why it is larger than the cameras' noise.
  double sigma_m = 0.004;
  // Online marker offsets. A model before the global fit (the nominal model scaled to the
  // subject's height) puts markers 1-4 cm from where the subject wears them; a gate wide enough
  // for that would also take ghosts. So each marker carries an offset in its segment's frame,
  // learnt from its residuals after each update (an exponential average with this time
  // constant), and its measurement variance is inflated by what is not yet known of it:
  // sigma^2 = sigma_m^2 / w_m + marker_offset_sigma^2 (1 - g)^(frames seen) + marker_offset_floor^2,
  // g = 1 / (time constant x rate) (the floor: model errors that change with the pose, skin
  // motion); after a start on a model scaled to the subject, a marker the start labelled has the
  // scaled placement's RMS in place of marker_offset_sigma ("Initialisation and recovery").
  // The offsets are a filter-side stand-in for the marker parameters that the global fit
  // identifies properly; they are cleared at every initialisation and by SwapModel.
  // While the subject stands still (the median marker moved under 2 mm + 0.1 m/s x dt since the
  // last frame) the offsets may be learnt as the mean of the residuals, the prior
  // (marker_offset_sigma) counting as marker_offset_prior_frames frames of them; (1 - g)^n above
  // is then 1 / (1 + n / marker_offset_prior_frames) until the exponential average's gain is the
  // larger (ekf/tracker.cpp, LearnOffsets). A static start is where a marker's residual measures
  // its place on its segment, and a marker seen there is then gated where it was seen, not within
  // 4 x 25 mm of the nominal place (issue 15: markers hidden for a frame of the static took
  // ghosts 7-10 cm away; 1 removes that class on seeds 1-50). 0 (the default): the exponential
  // average always -- with 1, a label the first frames gave wrong is learnt as fast and kept (on
  // seeds 51-80 the static's long swaps went 10 -> 15, and one test's start got worse;
  // BENCHMARKS.md, seventeenth session).
  double marker_offset_sigma = 0.025;
  double marker_offset_floor = 0.002;
  double marker_offset_time_constant_s = 0.5;
  double marker_offset_prior_frames = 0.0;
  int swap_offset_count = 400;  // SwapModel: as if the new positions had been seen this many frames
  // Gate: chi-square (3 degrees of freedom) of a marker-to-point Mahalanobis distance beyond which
  // a point cannot be that marker. 16.27 is the 99.9 % quantile.
  double gate_chi2 = 16.27;
  // A marker back from an occlusion is labelled on its first frame (its label goes through
  // probation before it is measured, see "On probation" above), but that label is REPORTED only
  // when the point is at least this likely to be the marker rather than clutter:
  //   P = g / (g + lambda), g = N(e; 0, S) the point's density under the marker's prediction,
  //   lambda the density of new unclaimed points near the body (points per m^3 with no
  //   predecessor in the last frame, averaged over the last clutter_time_constant_s).
  // Only a point new in this frame is judged (one that continues an unclaimed point of the last
  // frame is no single-frame reflection: a marker in view that the start or the gates left
  // unlabelled). Inside the 99.9 % gate of a marker whose prediction is still loose (a nominal
  // model's offsets not yet learnt, a limb coasting through the occlusion: S several centimetres
  // wide), a single-frame reflection is as likely as the marker itself; from its second frame the
  // label is judged by the point's motion (probation) and reported. Without clutter (lambda 0)
  // every label is reported. 0.95 is the decision that counts a wrong label as costly as 19
  // missed ones (a wrong one goes into the recording and the fit; a missed one is a gap). Measured
  // on EkfTracker.TracksThroughOcclusions (5 ghosts a frame, 5 % occluded): of 1,376 first frames
  // back, the 63 on a ghost had d^2 (Mahalanobis) 1-222, median 11, the 1,313 on the marker
  // median 0.1, 90 % under 0.8; wrong labels 69 -> 34 (0.99: 24, but TrackCli's undecided start
  // then lost 19 right labels for 13 ghosts; BENCHMARKS.md). 0 reports every label.
  double min_return_probability = 0.95;
  double clutter_time_constant_s = 1.0;
  // Largest number of input points per frame: the workspace is sized for it; points beyond it are
  // left unlabelled (and a frame with more columns than this grows the output vectors once).
  int max_points = 256;

  // Divergence: the track is lost after `divergence_frames` consecutive frames in which fewer
  // than `min_labelled_fraction` of the markers seen in the last good frames are labelled, or the
  // NIS per measured coordinate exceeds `max_nis_per_dof`.
  int divergence_frames = 10;
  double min_labelled_fraction = 0.5;
  double max_nis_per_dof = 10.0;

  // Initialisation: number of headings tried about `up`; acceptance thresholds.
  // `up` is the lab's vertical (Z in our simulations and in most C3D labs, Y in OpenSim's TRC
  // files, -Z in a data set turned upside down); `model_up` the model's own vertical in its
  // default pose (Z for the default model, Y for an OpenSim model: its ground's gravity is -Y).
  // The tracker turns every input point by the rotation that takes up onto model_up (the
  // shortest one) and works in that frame: a Y-up OpenSim model in a Z-up lab would otherwise be
  // searched for lying down, and a subject in a -Z-up lab needs root angles outside the model's
  // ranges. TrackOutput::z and predicted_markers() are in that turned frame (the lab's when
  // up == model_up, the default).
  Eigen::Vector3d up = Eigen::Vector3d::UnitZ();
  Eigen::Vector3d model_up = Eigen::Vector3d::UnitZ();
  // Model markers the data never shows, by name: virtual markers (joint centres such as R_HJC,
  // midASIS, projections) and markers the lab's set lacks. They are never labelled (a joint
  // centre would otherwise take a ghost or a neighbour's point), never searched for, and not
  // counted in the fractions (init_min_fraction, min_labelled_fraction): counted, a model with 72
  // markers of which 54 are worn can never label 80 % of its markers. Names the model lacks are
  // ignored (one list serves several models of a lab). Markers stacked on one point of their
  // segment are unseen too, unlisted ("Initialisation and recovery").
  std::vector<std::string> unseen_markers;
  int init_headings = 12;
  // Then restarts from the best placement: the static pose blended 10, 20 and 30 % towards the
  // middle of each joint's range, and init_variants more with the joint angles perturbed by up
  // to init_variant_rad (a fixed pseudo-random sequence: deterministic). 0: no restarts.
  int init_variants = 3;
  double init_variant_rad = 0.3;
  int init_iterations = 30;          // ICP iterations per hypothesis
  double init_max_rms_m = 0.03;      // RMS distance of the labelled markers (nominal model: ~2 cm)
  double init_min_fraction = 0.8;    // of the model's markers labelled (those it can see)
  // Unambiguous: every hypothesis that labels 3 or more markers differently must cost at least
  // init_ambiguity_ratio x the best one's score, and more than the best by init_ambiguity_margin
  // times the best one's residual variance per coordinate (a log-likelihood-ratio test: with a
  // nominal model the residuals are model error, ~2 cm, and a plain ratio of scores would call a
  // clear winner ambiguous).
  double init_ambiguity_ratio = 1.0;
  double init_ambiguity_margin = 20.0;
  // Final matching radius of the search (markers farther from every point stay unlabelled).
  double init_radius_m = 0.05;
  // Scaling the model to the subject at a (re)initialisation ("Initialisation and recovery"
  // above): always (the default: on the simulated sweep's seeds 1-80 every scene's worst seed and
  // median are better, BENCHMARKS.md "Many seeds"); only when the model's own size cannot start
  // (the search labels too few markers, or leaves too large a residual: a generic OpenSim
  // model); or never. The scales' prior: the model's own, with this standard deviation.
  enum class ScaleToSubject { kNever, kWhenTheModelDoesNotFit, kAlways };
  ScaleToSubject init_scale_to_subject = ScaleToSubject::kAlways;
  double init_scale_sigma = 0.05;
  // kWhenTheModelDoesNotFit judges the model's size on this much of the recording (seconds at
  // rate_hz): it scales once every search over that span failed for too few labels or too large
  // a residual. A start refused for a few frames is the scene (gait2354's walk: refused at frames
  // 0-4, started right at frame 5 at the model's own size; scaled at frame 4, the acromion markers
  // crossed for the whole trial); a model that does not fit fails on.
  double init_scale_after_s = 0.25;
  // Starting pose of the search (empty: the model's default pose).
  Eigen::VectorXd static_pose;
  // Standard deviations of the state right after an initialisation.
  double init_sigma_rotational = 0.05;          // rad
  double init_sigma_translational = 0.01;       // m
  double init_sigma_velocity_rotational = 1.0;  // rad/s
  double init_sigma_velocity_translational = 0.3;   // m/s
  double init_sigma_acceleration_rotational = 20.0; // rad/s^2
  double init_sigma_acceleration_translational = 5.0;  // m/s^2

  // SwapModel: added to the coordinates' variance (rad^2 / m^2) when the model changes, since the
  // old pose is only approximately the new model's pose.
  double swap_inflation_rotational = 0.02 * 0.02;
  double swap_inflation_translational = 0.01 * 0.01;

  bool IsValid(std::string* error) const;
};

enum class TrackState { kInitialising, kTracking, kLost };
const char* ToString(TrackState state);
// TrackerOptions::ScaleToSubject by the name the tools take: "never", "when-needed", "always".
// False for any other name (*mode untouched).
bool ParseScaleToSubject(const std::string& name, TrackerOptions::ScaleToSubject* mode);

struct TrackOutput {             // valid until the next Update
  TrackState state = TrackState::kInitialising;
  Eigen::VectorXd z;             // model coordinates (radians/metres); never NaN (last good pose when lost)
  std::vector<int> marker_of_point;  // per input point: model marker index, or -1 (ghost/stray/NaN)
  std::vector<int> point_of_marker;  // per model marker: input point index, or -1 (not seen)
  int labelled = 0;
  bool reinitialised = false;    // this frame started a new track
  double nis = 0;                // normalised innovation squared of this update
  int nis_dof = 0;               // its degrees of freedom (3 x labelled markers)
};

// What the last attempt to find the subject without labels did (Tracker::initialisation()).
struct InitialisationSummary {
  int attempts = 0;             // frames searched since the last track started or was lost
  int hypotheses = 0;           // starting placements refined in the last attempt
  double best_score = 0;        // truncated sum of squared distances (m^2) of the best one
  double runner_up_score = 0;   // best differently labelled hypothesis (0: none)
  double rms_m = 0;             // RMS distance of the best one's labelled markers
  int labelled = 0;             // markers the best one labelled
  // Markers the close hypotheses labelled differently, left empty at the start (the gates pick
  // them up from the next frames).
  int undecided = 0;
  bool accepted = false;
  std::string reason;           // why it was refused (empty when accepted)
  // Per segment, the scale factors the search fitted when the model did not fit the subject
  // (TrackerOptions::init_scale_to_subject); the tracker then tracks with them. Empty: the
  // model's own.
  std::vector<double> segment_scales;
};

// Where a tracker's model comes from. A generic or nominal model is scaled to the subject at a
// start as TrackerOptions::init_scale_to_subject says. One fitted to this subject (the global
// fit's result, a model calibrated on the subject's static trial) is the subject's size already:
// scaled again at every start, the labels were worse (welk007 at 12.5 Hz with its calibrated
// model: 0.987 -> 0.940; biobuddy's left hip 0.994 -> 0.984), so it is scaled only when its own
// size cannot start (kAlways acts as kWhenTheModelDoesNotFit).
enum class ModelOrigin { kGeneric, kFittedToSubject };

class Tracker {
 public:
  // `options` must be valid (TrackerOptions::IsValid); the model must have at least one joint.
  Tracker(std::shared_ptr<const Model> model, TrackerOptions options = {},
          ModelOrigin origin = ModelOrigin::kGeneric);
  ~Tracker();
  Tracker(const Tracker&) = delete;
  Tracker& operator=(const Tracker&) = delete;

  // One camera frame: predict, label, update. `points` are unlabelled 3D points in metres,
  // columns; NaN columns are ignored. Allocation-free while tracking (for up to
  // options.max_points points).
  const TrackOutput& Update(double time_s, const Eigen::Ref<const Eigen::Matrix3Xd>& points);

  // Replace the model (e.g. the global fit's result) between two frames without losing the
  // track: z and its velocities are kept, the coordinates' covariance is inflated. The new model
  // must have the same coordinates and markers (names, order). `origin`: the global fit's result
  // is the subject's own (ModelOrigin), and a later re-initialisation scales it accordingly.
  Status SwapModel(std::shared_ptr<const Model> model,
                   ModelOrigin origin = ModelOrigin::kFittedToSubject);

  TrackState state() const;
  void Reset();

  const Model& model() const;
  const TrackerOptions& options() const;
  const TrackOutput& output() const;
  const InitialisationSummary& initialisation() const;
  // The full state covariance (3 n_z x 3 n_z: coordinates, velocities, accelerations).
  const Eigen::MatrixXd& covariance() const;
  // Where the last Update predicted each model marker (3 x n_markers, before its update; the
  // learnt offsets included).
  const Eigen::Matrix3Xd& predicted_markers() const;
  // Velocities and accelerations of the coordinates.
  Eigen::VectorXd velocities() const;
  Eigen::VectorXd accelerations() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace mocap::ekf
