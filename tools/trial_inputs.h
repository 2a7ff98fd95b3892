// What `mocap fit` and `mocap ik` share: the model from .osim (with an optional OpenSim marker-set
// file) or .json, the trials from .c3d or .trc with an optional marker-name map, the lists of
// markers that match nothing, and joint angles out as .mot.
#pragma once
#include <CLI/CLI.hpp>
#include <Eigen/Core>
#include <string>
#include <vector>

#include "formats/marker_data.h"
#include "formats/osim.h"
#include "model/model.h"
#include "model/status.h"

namespace mocap::tools {

struct ModelInput {
  std::string path;
  bool osim = false;              // read from an OpenSim .osim (then `import` is filled)
  formats::OsimImport import;
  Model model;
};

// `path` ending in .osim (any case) is imported with formats::ImportOsim, plus `marker_set`
// (an OpenSim MarkerSet .xml) when not empty; anything else is a JSON model, with which a marker
// set is an error.
Status LoadModelInput(const std::string& path, const std::string& marker_set, ModelInput* out);

// Markers of the trials against the model's: trial markers no model marker has (ignored), and
// model markers with no sample in any trial (left out of the fit, e.g. virtual markers such as
// R_HJC or midASIS).
struct MarkerMatch {
  std::vector<std::string> unmatched_trial_markers;
  std::vector<std::string> unobserved_model_markers;
};

// Reads every trial (by extension: .c3d, .trc) and renames its markers by the marker map
// `marker_map` (a file, formats/marker_file.h; empty: none). A map line naming a model marker the
// model lacks, or a file marker that no trial has, is an error naming the map file and line.
// A trial with no frames is an error naming it.
Status LoadTrials(const std::vector<std::string>& paths, const std::string& marker_map, const Model& model,
                  std::vector<formats::MarkerTrial>* trials, MarkerMatch* match);

// Logs (spdlog warn) the two lists of `match`, when not empty.
void LogMarkerMatch(const MarkerMatch& match);
// Logs the points a file held that are not markers (formats::MarkerTrial::skipped_points), if any.
void LogSkippedPoints(const std::string& path, const formats::MarkerTrial& trial);

// The inputs of `mocap fit` and `mocap ik`: --model, --marker-set, --marker-map and the trials.
struct InputArgs {
  std::string model_path;
  std::string marker_set;
  std::string marker_map;
  std::vector<std::string> trials;
};
void AddInputOptions(CLI::App* cmd, InputArgs* args);

struct Inputs {
  ModelInput model;
  std::vector<formats::MarkerTrial> trials;
  MarkerMatch match;
};
// LoadModelInput + LoadTrials; logs each trial's size and the marker lists (LogMarkerMatch), or
// the error and returns false.
bool LoadInputs(const InputArgs& args, Inputs* out);

// Joint angles of one trial (rows of `z`: frames) as a .mot: OpenSim's coordinate names and units
// (formats::WriteOsimMot) for an OpenSim model, our coordinate names in degrees / metres otherwise.
Status WriteAngles(const std::string& path, const ModelInput& input, const Model& model,
                   const formats::MarkerTrial& trial, const Eigen::MatrixXd& z);

// True when `path` ends in `ext` (".osim", ...), any case.
bool HasExtension(const std::string& path, const std::string& ext);

}  // namespace mocap::tools
