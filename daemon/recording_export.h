// A stored recording (daemon/store.h) as the formats the rest of mocap reads: C3D (labelled markers
// and the unlabelled points), TRC (labelled markers), MOT (the tracker's coordinates), and the
// in-memory MarkerTrial / CoordinateTable the fit takes.
//
// Rows and time. A recording's frames carry the rig's frame-set sequence numbers, which run at
// the recording's rate but may skip a set the rig dropped. Row f is recorded frame f; its frame
// number is (sequence - first sequence + 1) and its time (frame number - 1) / rate_hz, i.e. the
// rig's nominal time from the first frame, which is also what a C3D file reads back (C3D stores no
// times). With `fill_gaps` every skipped sequence number gets a row too (all NaN): C3D needs
// consecutive frames, and a regular time base is what OpenSim-style tools expect.
//
// Unlabelled points in C3D. Their number changes from frame to frame and they have no identity, so
// they go into K numbered slots "P001".."PK" (K = the most points in any frame): frame f's points
// fill slots 1..n_f in the order stored, the rest are missing. (C3D readers give an empty label
// "P<n>", so this naming also matches what files from systems that leave points unlabelled read
// back as.)
#pragma once
#include <string>
#include <vector>

#include "daemon/store.h"
#include "formats/marker_data.h"
#include "formats/trc.h"
#include "model/model.h"
#include "model/status.h"

namespace mocap::daemon {

struct RecordingTableOptions {
  // One row per rig sequence number from the first to the last recorded frame (skipped ones NaN)
  // instead of one row per recorded frame.
  bool fill_gaps = false;
};

// The labelled markers (metres, NaN where not labelled) under the recording's marker names.
// trial.name is the movement. Errors: frames whose sizes disagree with the recording's names, frame
// numbers that do not increase, more rows than an int counts.
Status RecordingToMarkerTrial(const RecordingInfo& info, const std::vector<RecordedFrame>& frames,
                              const RecordingTableOptions& options, formats::MarkerTrial* trial);

// The tracker's coordinates under the recording's coordinate names. `rotational` has one entry
// per coordinate; with `in_degrees` the rotational ones are converted from radians (the table's
// in_degrees says which unit it holds).
Status RecordingToCoordinateTable(const RecordingInfo& info,
                                  const std::vector<RecordedFrame>& frames,
                                  const std::vector<bool>& rotational, bool in_degrees,
                                  const RecordingTableOptions& options,
                                  formats::CoordinateTable* table);

// Which of `coordinate_names` are rotational in `model` (for the two above). Error: a name the
// model does not have.
Status RotationalCoordinates(const Model& model, const std::vector<std::string>& coordinate_names,
                             std::vector<bool>* rotational);

// C3D with every sequence number a frame (fill_gaps): the labelled markers, then the unlabelled
// points as P001.. slots. formats/c3d.h's writer: floats, mm.
Status ExportRecordingC3d(const RecordingInfo& info, const std::vector<RecordedFrame>& frames,
                          const std::string& path);
// TRC of the labelled markers, one row per recorded frame.
Status ExportRecordingTrc(const RecordingInfo& info, const std::vector<RecordedFrame>& frames,
                          const std::string& path,
                          const formats::TrcWriteOptions& options = formats::TrcWriteOptions());
// MOT of the coordinates, rotational ones in degrees (OpenSim's convention), one row per frame.
Status ExportRecordingMot(const RecordingInfo& info, const std::vector<RecordedFrame>& frames,
                          const std::vector<bool>& rotational, const std::string& path);

}  // namespace mocap::daemon
