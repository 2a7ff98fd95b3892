// Marker trajectories and marker-name maps from files, whatever the format: the reader is chosen
// by the file's extension (.c3d or .trc, any case). Shared by `mocap convert`, `mocap fit` and
// `mocap ik`.
#pragma once
#include <string>
#include <utility>
#include <vector>

#include "formats/c3d.h"
#include "formats/marker_data.h"
#include "model/status.h"

namespace mocap::formats {

enum class MarkerFileKind { kUnknown, kC3d, kTrc };

// By extension, any case: ".c3d" -> kC3d, ".trc" -> kTrc, anything else kUnknown.
MarkerFileKind MarkerFileKindOf(const std::string& path);

// Reads a .c3d (ReadC3d with `c3d_options`) or .trc (ReadTrc) file into `trial` (metres, NaN
// where missing). An unknown extension is an error naming the file.
Status ReadMarkerFile(const std::string& path, MarkerTrial* trial,
                      const C3dReadOptions& c3d_options = C3dReadOptions());

// A marker-name map: one pair a line, `our_name = file_name` (the model's marker name, then the
// name in the trial files); `#` starts a comment; blank lines are skipped. Errors name the file
// and line ("map.txt:3: expected 'model_name = file_name'"), as do a model name or a file name
// given twice.
struct MarkerMapEntry {
  std::string model_name;
  std::string file_name;
  int line = 0;
};
struct MarkerMap {
  std::string source;  // file the map came from (for messages)
  std::vector<MarkerMapEntry> entries;
};
Status ReadMarkerMap(const std::string& path, MarkerMap* map);
Status ParseMarkerMap(const std::string& text, const std::string& source, MarkerMap* map);

// Renames the markers of `trial` from file names to model names by `map`. A file name the trial
// does not have is left alone (several trials share one map); a renamed marker that would collide
// with another marker of the trial is an error naming the map's line.
Status ApplyMarkerMap(const MarkerMap& map, MarkerTrial* trial);

}  // namespace mocap::formats
