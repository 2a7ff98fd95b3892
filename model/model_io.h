// The mocapd model file: JSON, {"format": "mocap-model", "version": 1, ...}. Segments, coordinates,
// joints (with their elementary motions) and markers by name; see docs in README.md.
// Errors name the file and the offending field, e.g. "m.json: joints[3].elements[1].axis: ...".
#pragma once
#include <string>

#include "model/model.h"

namespace mocap {

Status LoadModelJson(const std::string& path, Model* model);
Status ParseModelJson(const std::string& text, const std::string& source_name, Model* model);
Status SaveModelJson(const std::string& path, const Model& model);
std::string ModelToJsonString(const Model& model);

}  // namespace mocap
