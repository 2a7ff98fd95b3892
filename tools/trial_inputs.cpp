#include "tools/trial_inputs.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <cmath>
#include <set>

#include "formats/marker_file.h"
#include "formats/mot.h"
#include "model/model_io.h"

namespace mocap::tools {

bool HasExtension(const std::string& path, const std::string& ext) {
  if (path.size() < ext.size()) return false;
  return std::equal(ext.begin(), ext.end(), path.end() - static_cast<std::ptrdiff_t>(ext.size()),
                    [](char a, char b) { return std::tolower(a) == std::tolower(b); });
}

Status LoadModelInput(const std::string& path, const std::string& marker_set, ModelInput* out) {
  out->path = path;
  out->osim = HasExtension(path, ".osim");
  if (!out->osim) {
    if (!marker_set.empty())
      return Status::Error("--marker-set " + marker_set + ": a marker set goes with an OpenSim model (.osim), not " +
                           path);
    return LoadModelJson(path, &out->model);
  }
  MOCAP_RETURN_IF_ERROR(formats::ImportOsim(path, &out->import));
  if (!marker_set.empty()) MOCAP_RETURN_IF_ERROR(formats::LoadOsimMarkerSet(marker_set, &out->import));
  out->model = out->import.model;
  for (const std::string& what : out->import.ignored) spdlog::warn("{}: {}", path, what);
  if (out->model.num_markers() == 0)
    return Status::Error(path + ": the model has no markers (give its marker set with --marker-set MARKERS.xml)");
  return Status::Ok();
}

Status LoadTrials(const std::vector<std::string>& paths, const std::string& marker_map, const Model& model,
                  std::vector<formats::MarkerTrial>* trials, MarkerMatch* match) {
  formats::MarkerMap map;
  if (!marker_map.empty()) MOCAP_RETURN_IF_ERROR(formats::ReadMarkerMap(marker_map, &map));
  for (const auto& e : map.entries)
    if (model.FindMarker(e.model_name) < 0)
      return Status::Error(marker_map + ":" + std::to_string(e.line) + ": model marker '" + e.model_name +
                           "' is not in the model " + model.name());
  std::vector<formats::MarkerTrial> out;
  std::vector<char> map_used(map.entries.size(), 0);
  for (const auto& path : paths) {
    formats::MarkerTrial t;
    MOCAP_RETURN_IF_ERROR(formats::ReadMarkerFile(path, &t));
    if (t.num_frames() == 0) return Status::Error(path + ": the trial has no frames");
    for (size_t k = 0; k < map.entries.size(); ++k) map_used[k] |= t.FindMarker(map.entries[k].file_name) >= 0;
    MOCAP_RETURN_IF_ERROR(formats::ApplyMarkerMap(map, &t));
    out.push_back(std::move(t));
  }
  for (size_t k = 0; k < map.entries.size(); ++k)
    if (!map_used[k])
      return Status::Error(marker_map + ":" + std::to_string(map.entries[k].line) + ": trial marker '" +
                           map.entries[k].file_name + "' is in none of the trials");
  MarkerMatch m;
  std::set<std::string> unmatched;
  std::vector<char> observed(model.num_markers(), 0);
  for (const auto& t : out)
    for (int c = 0; c < t.num_markers(); ++c) {
      const int k = model.FindMarker(t.marker_names[c]);
      if (k < 0) {
        unmatched.insert(t.marker_names[c]);
        continue;
      }
      for (int f = 0; f < t.num_frames() && !observed[k]; ++f) observed[k] = t.Has(f, c);
    }
  m.unmatched_trial_markers.assign(unmatched.begin(), unmatched.end());
  for (int k = 0; k < model.num_markers(); ++k)
    if (!observed[k]) m.unobserved_model_markers.push_back(model.markers()[k].name);
  *trials = std::move(out);
  *match = std::move(m);
  return Status::Ok();
}

void LogMarkerMatch(const MarkerMatch& match) {
  auto join = [](const std::vector<std::string>& names) {
    std::string list;
    for (const auto& n : names) list += " " + n;
    return list;
  };
  if (!match.unmatched_trial_markers.empty())
    spdlog::warn("trial markers not in the model (ignored):{}", join(match.unmatched_trial_markers));
  if (!match.unobserved_model_markers.empty())
    spdlog::warn("model markers in no trial (left out of the fit, kept as they were):{}",
                 join(match.unobserved_model_markers));
}

void AddInputOptions(CLI::App* cmd, InputArgs* args) {
  cmd->add_option("--model", args->model_path, "model (.json, or OpenSim .osim)")->required();
  cmd->add_option("--marker-set", args->marker_set, "OpenSim marker set (.xml) added to an .osim model");
  cmd->add_option("--marker-map", args->marker_map, "marker-name map: lines 'model_name = file_name' (# comments)");
  cmd->add_option("trials", args->trials, "marker trials (.trc, .c3d)")->required();
}

void LogSkippedPoints(const std::string& path, const formats::MarkerTrial& trial) {
  if (trial.skipped_points.empty()) return;
  std::string list;
  for (size_t k = 0; k < trial.skipped_points.size() && k < 6; ++k) list += (k ? ", " : "") + trial.skipped_points[k];
  spdlog::info("{}: {} points are the file's model outputs (angles, forces, moments, powers), not markers: not "
               "read ({}{})",
               path, trial.skipped_points.size(), list, trial.skipped_points.size() > 6 ? ", ..." : "");
}

bool LoadInputs(const InputArgs& args, Inputs* out) {
  Status s = LoadModelInput(args.model_path, args.marker_set, &out->model);
  if (s) s = LoadTrials(args.trials, args.marker_map, out->model.model, &out->trials, &out->match);
  if (!s) {
    spdlog::error("{}", s.message());
    return false;
  }
  for (size_t t = 0; t < out->trials.size(); ++t)
    spdlog::info("{}: {} frames, {} markers at {} Hz", args.trials[t], out->trials[t].num_frames(),
                 out->trials[t].num_markers(), out->trials[t].rate_hz);
  for (size_t t = 0; t < out->trials.size(); ++t) LogSkippedPoints(args.trials[t], out->trials[t]);
  LogMarkerMatch(out->match);
  return true;
}

Status WriteAngles(const std::string& path, const ModelInput& input, const Model& model,
                   const formats::MarkerTrial& trial, const Eigen::MatrixXd& z) {
  if (input.osim) return formats::WriteOsimMot(path, input.import, model, trial.times, z);
  formats::CoordinateTable table;
  table.name = trial.name;
  table.in_degrees = true;
  for (const auto& c : model.coordinates()) table.column_names.push_back(c.name);
  table.times = trial.times;
  table.values.resize(z.rows(), z.cols());
  for (int c = 0; c < z.cols(); ++c) {
    const double k = model.coordinates()[c].rotational ? 180.0 / M_PI : 1.0;
    table.values.col(c) = z.col(c) * k;
  }
  return formats::WriteMot(path, table);
}

}  // namespace mocap::tools
