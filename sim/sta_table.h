// The soft-tissue artefact class of each marker, as DATA: how far a marker moves relative to its
// bone depends on what lies under it, not on the simulator. Skin over a subcutaneous bony
// landmark (malleolus, epicondyle, styloid, calcaneus, ASIS) moves a few millimetres; a wand or
// cluster over muscle and fat (thigh, shank, upper arm, forearm, the scapula) moves one to three
// centimetres (Leardini et al. 2005, Gait & Posture 21:212; Peters et al. 2010, Gait & Posture
// 31:1; Camomilla et al. 2017, J Biomech 62:1). Giving every marker the same amplitude would make
// the distal segments, whose one or two markers are bony landmarks next to the joint, carry an
// artefact that is to first order a shifted joint centre (issue 2), and would not be a body.
//
// The simulator (sim/simulate.h) gives marker m the RMS artefact sta_mm x ratio(m), where the
// ratio is that of m's class. The default table (sim/default_sta_table.json, embedded at build
// time) classes every marker of DefaultFullBodyModel; its thigh class has ratio 1, so sta_mm is
// the artefact of a thigh marker, and bony landmarks get a quarter of it. A marker the table does
// not name (an imported model's) gets ratio `unknown_ratio`, 1 by default: treating an unknown
// marker as soft tissue is the pessimistic choice.
//
// File format (JSON):
//   {"format": "mocap-sta-table", "version": 1, "name": "...", "description": "...",
//    "references": ["...", ...],
//    "classes": {"bony_landmark": {"ratio": 0.25, "basis": "why, with its source"}, ...},
//    "markers": {"LASI": "bony_landmark", "LTHI": "thigh", ...}}
#pragma once
#include <map>
#include <string>
#include <vector>

#include "model/status.h"

namespace mocap::sim {

struct StaClass {
  double ratio = 1.0;  // of the table's reference amplitude (sta_mm), >= 0
  std::string basis;   // what the figure rests on, with its source
};

struct StaTable {
  std::string name;
  std::string description;
  std::vector<std::string> references;
  std::map<std::string, StaClass> classes;
  std::map<std::string, std::string> marker_class;  // marker name -> class name
  double unknown_ratio = 1.0;  // markers the table does not name: soft tissue

  // The class name of `marker`, or empty when the table does not name it.
  std::string ClassOf(const std::string& marker) const;
  // The amplitude ratio of `marker`: its class's, or unknown_ratio.
  double RatioOf(const std::string& marker) const;
};

// sim/default_sta_table.json, parsed once.
const StaTable& DefaultStaTable();
const std::string& DefaultStaTableJson();

// Parse and validation: format and version, every class's ratio a finite number >= 0, every
// marker's class one of the classes. Errors name the source and the field
// ("t.json: markers.LTHI: class 'thig' is not in classes").
Status ParseStaTableJson(const std::string& text, const std::string& source_name, StaTable* table);

}  // namespace mocap::sim
