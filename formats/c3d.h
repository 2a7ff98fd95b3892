// C3D (www.c3d.org) marker trajectories in and out, written here: Debian 12 packages no C3D
// library (no ezc3d, no BTK), and the part mocapd needs — labelled 3D points — is small.
//
// The file: 512-byte blocks. Block 1 is the header (16-bit words: parameter block, point count,
// analog values per frame, first/last frame, scale, data start block, analog samples per frame,
// rate). The parameter section starts at the block named by the header's first byte; its 4th byte
// is the processor type, which fixes the byte order and float format of the WHOLE file (header
// included): 84 Intel (little-endian IEEE), 85 DEC (little-endian integers, VAX F floats: words
// swapped, exponent bias 128, i.e. IEEE of the swapped words / 4), 86 MIPS (big-endian IEEE).
// The parameters form a forward-linked list of groups and parameters; each parameter is a typed
// (char, byte, int16, float) array of up to 7 dimensions. The data blocks hold, per frame, every
// point as X Y Z + a 4th "residual/camera" word, then that frame's analog samples.
//
// Pitfalls handled by the reader:
// - POINT:SCALE's sign selects the storage: negative = floats, positive = int16 counts times the
//   scale. Analog samples use the same storage and are skipped: ANALOG:USED x the header's analog
//   samples per frame (the header's total analog count, word 3, only where ANALOG:USED is absent).
// - The 4th word: a negative residual marks an invalid (missing) sample. In float files it is a
//   float whose integer part holds the camera mask and residual; the sign is what matters. Some
//   writers (ezc3d, as in shared/data's biobuddy files) mark gaps with NaN coordinates and
//   residual 0 instead: a non-finite coordinate is missing too.
// - POINT:LABELS holds at most 255 labels; LABELS2, LABELS3, ... continue it. Labels are padded
//   with spaces; Cortex and Vicon prefix them with the subject ("FullBody_static:r_knee"), which
//   `strip_label_prefix` drops so the names match the model's markers.
// - POINT:USED is read as unsigned 16-bit (the int16 overflows past 32767). The header's 16-bit
//   last frame saturates on long trials: then TRIAL:ACTUAL_START_FIELD/END_FIELD (two words
//   forming a 32-bit number) or a larger POINT:FRAMES give the real count.
// - POINT:UNITS mm, cm or m (absent: mm, the standard's default) -> metres.
// - Not every point is a marker: Vicon Nexus (Plug-in Gait), Visual3D and others store their
//   model's outputs as points too -- joint angles in degrees, forces, moments, powers -- and list
//   their labels in POINT:ANGLES, FORCES, MOMENTS, POWERS, SCALARS and REACTIONS (the C3D
//   manual's convention, as BTK and ezc3d read it). Read as markers they would be "markers" a few
//   centimetres from the lab's origin: ghosts to the tracker, noise to the fit's attachment of
//   unknown markers. They are skipped (C3dReadOptions::skip_model_outputs) and named in
//   MarkerTrial::skipped_points. Virtual points a model places in the lab (Plug-in Gait's joint
//   centres, segment origins) are not listed there and stay: they are positions.
// - Every count and offset read from the file is checked against the file size before it is
//   used (no out-of-bounds read, no allocation larger than the file justifies), so corrupt or
//   truncated files give an error naming the file and the place, never a crash.
#pragma once
#include <string>
#include <string_view>
#include <vector>

#include "formats/marker_data.h"
#include "model/status.h"

namespace mocap::formats {

struct C3dReadOptions {
  // Drop everything up to and including the last ':' of each label ("FullBody_static:r_knee" ->
  // "r_knee"), as the TRC conversions in shared/data did. Set false to keep the labels as stored
  // (only trailing spaces are removed either way).
  bool strip_label_prefix = true;
  // Leave out the points listed as model outputs (see above); false reads every point.
  bool skip_model_outputs = true;
};

// Reads the 3D points of a C3D file into `trial` (metres; NaN where the residual marks a sample
// invalid, or a float coordinate is not finite). trial.name is the file stem; frame_numbers run
// from the header's first frame; times[f] = (frame_numbers[f] - 1) / rate (0 at frame 1).
// An empty label becomes "P<n>" (n = 1-based point number); a label repeated (after prefix
// stripping) gets "_2", "_3", ... appended, since marker names must be unique.
// Errors name the file and the place: "PATH: header: ...", "PATH: parameter section, group POINT,
// parameter LABELS: ...", "PATH: data block 12 (byte 6144): truncated ...". On error *trial is
// left unchanged.
Status ReadC3d(const std::string& path, MarkerTrial* trial,
               const C3dReadOptions& options = C3dReadOptions());
// The same on bytes already in memory; `path` only names the file in messages (tests, fuzzing).
Status ParseC3d(std::string_view bytes, const std::string& path, MarkerTrial* trial,
                const C3dReadOptions& options = C3dReadOptions());

enum class C3dProcessor { kIntel = 84, kDec = 85, kMips = 86 };

struct C3dWriteOptions {
  // The defaults write what every reader reads: Intel, floats, mm.
  C3dProcessor processor = C3dProcessor::kIntel;
  // Scaled 16-bit integers instead of floats: each coordinate is rounded to a multiple of the
  // scale, chosen so the largest |coordinate| maps to 30000 counts (at most 0.5 scale of error).
  bool integer_points = false;
  // Trial markers that are a model's joint angles, listed in POINT:ANGLES as Vicon Nexus lists
  // Plug-in Gait's outputs (see the reader's pitfalls): files such as a lab's exports, for tests.
  std::vector<std::string> angle_points;
};

// Writes `trial` (metres) as a C3D file: POINT:USED, LABELS (+ LABELS2, ... past 255 markers),
// UNITS "mm", RATE, SCALE, FRAMES, DATA_START; the header's first frame is frame_numbers[0] (1
// when empty); a missing sample (any of x, y, z NaN) is written as zeros with residual -1.
// Reading the file back gives the trial again: names, rate and frame numbers exactly, positions
// to float precision (integer_points: to half the scale). Times are not stored in C3D: they read
// back as (frame - 1) / rate. Rejected: no markers, inconsistent sizes, a non-positive rate,
// infinite values, frame numbers that are not consecutive or start below 0, and marker names that
// are empty, duplicated or longer than 255 characters.
Status WriteC3d(const std::string& path, const MarkerTrial& trial,
                const C3dWriteOptions& options = C3dWriteOptions());

}  // namespace mocap::formats
