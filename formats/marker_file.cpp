#include "formats/marker_file.h"

#include <map>

#include "formats/text_util.h"
#include "formats/trc.h"

namespace mocap::formats {

MarkerFileKind MarkerFileKindOf(const std::string& path) {
  const size_t dot = path.find_last_of('.');
  const size_t slash = path.find_last_of('/');
  if (dot == std::string::npos || (slash != std::string::npos && dot < slash))
    return MarkerFileKind::kUnknown;
  const std::string_view ext = std::string_view(path).substr(dot);
  if (detail::EqualsIgnoreCase(ext, ".c3d")) return MarkerFileKind::kC3d;
  if (detail::EqualsIgnoreCase(ext, ".trc")) return MarkerFileKind::kTrc;
  return MarkerFileKind::kUnknown;
}

Status ReadMarkerFile(const std::string& path, MarkerTrial* trial, const C3dReadOptions& c3d_options) {
  switch (MarkerFileKindOf(path)) {
    case MarkerFileKind::kC3d:
      return ReadC3d(path, trial, c3d_options);
    case MarkerFileKind::kTrc:
      return ReadTrc(path, trial);
    case MarkerFileKind::kUnknown:
      break;
  }
  return Status::Error(path + ": unknown marker file type (expected a .c3d or .trc extension)");
}

Status ReadMarkerMap(const std::string& path, MarkerMap* map) {
  std::string text;
  MOCAP_RETURN_IF_ERROR(detail::ReadWholeFile(path, &text));
  return ParseMarkerMap(text, path, map);
}

Status ParseMarkerMap(const std::string& text, const std::string& source, MarkerMap* map) {
  MarkerMap out;
  out.source = source;
  std::map<std::string, int> model_line, file_line;
  for (const detail::Line& line : detail::SplitLines(text)) {
    std::string_view s = line.text;
    if (const size_t hash = s.find('#'); hash != std::string_view::npos) s = s.substr(0, hash);
    s = detail::Trim(s);
    if (s.empty()) continue;
    const size_t eq = s.find('=');
    if (eq == std::string_view::npos || s.find('=', eq + 1) != std::string_view::npos)
      return Status::Error(detail::At(source, line.number, "expected 'model_name = file_name', got " +
                                                               detail::Quote(s)));
    MarkerMapEntry e;
    e.model_name = std::string(detail::Trim(s.substr(0, eq)));
    e.file_name = std::string(detail::Trim(s.substr(eq + 1)));
    e.line = line.number;
    if (e.model_name.empty() || e.file_name.empty())
      return Status::Error(detail::At(source, line.number, "expected 'model_name = file_name', got " +
                                                               detail::Quote(s) + " (a name is empty)"));
    for (const std::string* n : {&e.model_name, &e.file_name})
      if (n->find_first_of(" \t") != std::string::npos)
        return Status::Error(detail::At(source, line.number, "marker name " + detail::Quote(*n) +
                                                                 " contains a space or tab"));
    if (auto [it, fresh] = model_line.emplace(e.model_name, e.line); !fresh)
      return Status::Error(detail::At(source, line.number, "model marker '" + e.model_name +
                                                               "' is already mapped on line " +
                                                               std::to_string(it->second)));
    if (auto [it, fresh] = file_line.emplace(e.file_name, e.line); !fresh)
      return Status::Error(detail::At(source, line.number, "file marker '" + e.file_name +
                                                               "' is already mapped on line " +
                                                               std::to_string(it->second)));
    out.entries.push_back(std::move(e));
  }
  *map = std::move(out);
  return Status::Ok();
}

Status ApplyMarkerMap(const MarkerMap& map, MarkerTrial* trial) {
  std::vector<std::string> names = trial->marker_names;
  std::map<std::string, int> renamed;  // new name -> map line
  for (const MarkerMapEntry& e : map.entries) {
    const int c = trial->FindMarker(e.file_name);
    if (c < 0) continue;
    names[c] = e.model_name;
    renamed[e.model_name] = e.line;
  }
  std::map<std::string, int> seen;
  for (int c = 0; c < static_cast<int>(names.size()); ++c) {
    if (auto [it, fresh] = seen.emplace(names[c], c); !fresh) {
      const int line = renamed.count(names[c]) ? renamed[names[c]] : 0;
      return Status::Error(detail::At(map.source, line, "renaming gives trial '" + trial->name +
                                                            "' two markers named '" + names[c] + "'"));
    }
  }
  trial->marker_names = std::move(names);
  return Status::Ok();
}

}  // namespace mocap::formats
