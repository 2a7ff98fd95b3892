#include "reconstruction/calibration_file.h"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <fstream>
#include <nlohmann/json.hpp>
#include <set>
#include <sstream>

#include "model/json_fields.h"

namespace mocap::reconstruction {

namespace {
using json = nlohmann::json;

template <typename Json>
void PutIfKnown(Json* j, const char* key, double v) {
  if (std::isfinite(v)) (*j)[key] = v;
}
}  // namespace

std::vector<CameraModel> CalibrationFile::Models() const {
  std::vector<CameraModel> out;
  for (const CalibratedCamera& c : cameras) out.push_back(c.camera);
  return out;
}

CalibrationFile CalibrationFileOf(const std::vector<CameraModel>& calibrated,
                                  const WandCalibrationSummary& summary, const Wand& wand) {
  CalibrationFile file;
  file.lab_frame = summary.lab_frame_from_lframe ? "L-frame" : "camera 0";
  file.reprojection_rms_px = summary.reprojection_rms_px;
  file.wand_length_error_mm_rms = summary.wand_length_error_mm_rms;
  file.wand_length_error_mm_mean = summary.wand_length_error_mm_mean;
  file.wand_markers_m = wand.marker_positions_m;
  for (std::size_t c = 0; c < calibrated.size(); ++c) {
    CalibratedCamera cc;
    cc.camera = calibrated[c];
    if (c < summary.cameras.size()) {
      cc.reprojection_rms_px = summary.cameras[c].reprojection_rms_px;
      cc.wand_frames = summary.cameras[c].wand_frames;
    }
    file.cameras.push_back(cc);
  }
  return file;
}

Status WriteCalibrationJson(const std::string& path, const CalibrationFile& file) {
  std::ofstream f(path, std::ios::binary);
  if (!f) return Status::Error(path + ": cannot open for writing");
  f << CalibrationJsonString(file);
  if (!f) return Status::Error(path + ": write failed");
  return Status::Ok();
}

std::string CalibrationJsonString(const CalibrationFile& file) {
  using json = nlohmann::ordered_json;  // fields in the order written, as the header shows
  json doc = {{"format", "mocap-calibration"}, {"version", 1}, {"lab_frame", file.lab_frame}};
  PutIfKnown(&doc, "reprojection_rms_px", file.reprojection_rms_px);
  PutIfKnown(&doc, "wand_length_error_mm_rms", file.wand_length_error_mm_rms);
  PutIfKnown(&doc, "wand_length_error_mm_mean", file.wand_length_error_mm_mean);
  if (!file.wand_markers_m.empty()) doc["wand_markers_m"] = file.wand_markers_m;
  json cams = json::array();
  for (const CalibratedCamera& cc : file.cameras) {
    const CameraModel& c = cc.camera;
    const CameraIntrinsics& k = c.intrinsics;
    json j = {{"id", c.id}, {"width", k.width}, {"height", k.height}, {"fx", k.fx},
              {"fy", k.fy}, {"cx", k.cx},       {"cy", k.cy},         {"k1", k.k1},
              {"k2", k.k2}, {"p1", k.p1},       {"p2", k.p2},         {"k3", k.k3}};
    json r = json::array();
    for (int i = 0; i < 3; ++i) r.push_back({c.R(i, 0), c.R(i, 1), c.R(i, 2)});
    j["R"] = r;
    j["t"] = {c.t.x(), c.t.y(), c.t.z()};
    PutIfKnown(&j, "reprojection_rms_px", cc.reprojection_rms_px);
    if (cc.wand_frames > 0) j["wand_frames"] = cc.wand_frames;
    PutIfKnown(&j, "position_error_mm", cc.position_error_mm);
    PutIfKnown(&j, "orientation_error_deg", cc.orientation_error_deg);
    cams.push_back(j);
  }
  doc["cameras"] = cams;
  return doc.dump(2) + "\n";
}

Status ReadCalibrationJson(const std::string& path, CalibrationFile* file) {
  std::ifstream f(path, std::ios::binary);
  if (!f) return Status::Error(path + ": cannot open");
  std::stringstream ss;
  ss << f.rdbuf();
  return ParseCalibrationJson(ss.str(), path, file);
}

Status ParseCalibrationJson(const std::string& text, const std::string& name,
                            CalibrationFile* out) {
  json doc;
  try {
    doc = json::parse(text);
  } catch (const json::parse_error& e) {
    return Status::Error(name + ": not valid JSON: " + e.what());
  }
  const JsonFields r(name);
  if (!doc.is_object()) return r.Fail("", "expected a JSON object");
  std::string format;
  MOCAP_RETURN_IF_ERROR(r.String(doc, "", "format", &format));
  if (format != "mocap-calibration")
    return r.Fail("format", "expected \"mocap-calibration\", got \"" + format + "\"");
  double version = 0;
  MOCAP_RETURN_IF_ERROR(r.Number(doc, "", "version", &version));
  if (version != 1) return r.Fail("version", "unsupported version (this reader knows 1)");
  CalibrationFile file;
  MOCAP_RETURN_IF_ERROR(r.String(doc, "", "lab_frame", &file.lab_frame, false));
  MOCAP_RETURN_IF_ERROR(r.Number(doc, "", "reprojection_rms_px", &file.reprojection_rms_px, false));
  MOCAP_RETURN_IF_ERROR(
      r.Number(doc, "", "wand_length_error_mm_rms", &file.wand_length_error_mm_rms, false));
  MOCAP_RETURN_IF_ERROR(
      r.Number(doc, "", "wand_length_error_mm_mean", &file.wand_length_error_mm_mean, false));
  if (doc.contains("wand_markers_m")) {
    const json& w = doc["wand_markers_m"];
    if (!w.is_array()) return r.Fail("wand_markers_m", "expected an array of numbers");
    for (const json& v : w) {
      if (!v.is_number() || !std::isfinite(v.get<double>()))
        return r.Fail("wand_markers_m", "expected an array of numbers");
      file.wand_markers_m.push_back(v.get<double>());
    }
  }
  MOCAP_RETURN_IF_ERROR(r.Array(doc, "", "cameras"));
  const json& cams = doc["cameras"];
  if (cams.empty()) return r.Fail("cameras", "no cameras");
  std::set<std::string> ids;
  for (size_t i = 0; i < cams.size(); ++i) {
    const std::string path = "cameras[" + std::to_string(i) + "]";
    const json& j = cams[i];
    if (!j.is_object()) return r.Fail(path, "expected an object");
    CalibratedCamera cc;
    CameraModel& c = cc.camera;
    MOCAP_RETURN_IF_ERROR(r.String(j, path, "id", &c.id));
    if (c.id.empty()) return r.Fail(path + ".id", "empty");
    if (!ids.insert(c.id).second) return r.Fail(path + ".id", "duplicate camera id '" + c.id + "'");
    CameraIntrinsics& k = c.intrinsics;
    double w = 0, h = 0;
    MOCAP_RETURN_IF_ERROR(r.Number(j, path, "width", &w));
    MOCAP_RETURN_IF_ERROR(r.Number(j, path, "height", &h));
    if (w != std::floor(w) || h != std::floor(h) || w < 1 || h < 1 || w > 65535 || h > 65535)
      return r.Fail(path, "width and height must be whole numbers of pixels in [1, 65535]");
    k.width = static_cast<int>(w);
    k.height = static_cast<int>(h);
    const std::pair<const char*, double*> fields[] = {{"fx", &k.fx}, {"fy", &k.fy}, {"cx", &k.cx},
                                                      {"cy", &k.cy}, {"k1", &k.k1}, {"k2", &k.k2},
                                                      {"p1", &k.p1}, {"p2", &k.p2}, {"k3", &k.k3}};
    for (const auto& [key, dst] : fields) MOCAP_RETURN_IF_ERROR(r.Number(j, path, key, dst));
    if (!(k.fx > 0) || !(k.fy > 0)) return r.Fail(path, "fx and fy must be positive");
    if (!j.contains("R")) return r.Fail(path + ".R", "missing");
    const json& jr = j["R"];
    bool shape = jr.is_array() && jr.size() == 3;
    for (size_t a = 0; shape && a < 3; ++a) {
      shape = jr[a].is_array() && jr[a].size() == 3;
      for (size_t b = 0; shape && b < 3; ++b) {
        shape = jr[a][b].is_number();
        if (shape) c.R(a, b) = jr[a][b].get<double>();
      }
    }
    if (!shape) return r.Fail(path + ".R", "expected 3 rows of 3 numbers");
    if (!c.R.allFinite()) return r.Fail(path + ".R", "not finite");
    const double orth = (c.R.transpose() * c.R - Eigen::Matrix3d::Identity()).norm();
    if (orth > 1e-6 || c.R.determinant() < 0) {
      char buf[128];
      std::snprintf(buf, sizeof(buf), "not a rotation matrix (|R^T R - I| = %.3g, det = %.6f)",
                    orth, c.R.determinant());
      return r.Fail(path + ".R", buf);
    }
    MOCAP_RETURN_IF_ERROR(r.Vec3(j, path, "t", &c.t));
    MOCAP_RETURN_IF_ERROR(r.Number(j, path, "reprojection_rms_px", &cc.reprojection_rms_px, false));
    double frames = 0;
    MOCAP_RETURN_IF_ERROR(r.Number(j, path, "wand_frames", &frames, false));
    cc.wand_frames = static_cast<int>(frames);
    MOCAP_RETURN_IF_ERROR(r.Number(j, path, "position_error_mm", &cc.position_error_mm, false));
    MOCAP_RETURN_IF_ERROR(
        r.Number(j, path, "orientation_error_deg", &cc.orientation_error_deg, false));
    std::string error;
    if (!k.IsValid(&error)) return r.Fail(path, error);
    file.cameras.push_back(cc);
  }
  *out = std::move(file);
  return Status::Ok();
}

Status MatchCalibrationToRig(const CalibrationFile& file, const std::vector<std::string>& rig_ids,
                             std::vector<CameraModel>* ordered) {
  std::string unknown, missing;
  for (const CalibratedCamera& c : file.cameras)
    if (std::find(rig_ids.begin(), rig_ids.end(), c.camera.id) == rig_ids.end())
      unknown += (unknown.empty() ? "'" : ", '") + c.camera.id + "'";
  std::vector<CameraModel> out;
  for (const std::string& id : rig_ids) {
    const CalibratedCamera* found = nullptr;
    for (const CalibratedCamera& c : file.cameras)
      if (c.camera.id == id) found = &c;
    if (!found) {
      missing += (missing.empty() ? "'" : ", '") + id + "'";
      continue;
    }
    out.push_back(found->camera);
  }
  if (!unknown.empty() || !missing.empty() || file.cameras.size() != rig_ids.size()) {
    std::string msg = "calibration does not match the cameras: it has " +
                      std::to_string(file.cameras.size()) + " cameras, the rig " +
                      std::to_string(rig_ids.size());
    if (!missing.empty()) msg += "; not calibrated: " + missing;
    if (!unknown.empty()) msg += "; unknown to the rig: " + unknown;
    return Status::Error(msg);
  }
  *ordered = std::move(out);
  return Status::Ok();
}

namespace {

json FramesToJson(const std::vector<DetectionSet>& frames) {
  json out = json::array();
  for (const DetectionSet& set : frames) {
    json cams = json::array();
    for (size_t c = 0; c < set.cameras.size(); ++c) {
      if (!set.present[c]) {
        cams.push_back(nullptr);
        continue;
      }
      json pts = json::array();
      for (const Centroid& ct : set.cameras[c].centroids)
        pts.push_back({ct.pixel.x(), ct.pixel.y()});
      cams.push_back(pts);
    }
    out.push_back(cams);
  }
  return out;
}

Status FramesFromJson(const JsonFields& r, const json& doc, const char* key, int cameras,
                      std::vector<DetectionSet>* frames) {
  if (!doc.contains(key)) return Status::Ok();
  if (!doc[key].is_array()) return r.Fail(key, "expected an array of frames");
  const json& arr = doc[key];
  for (size_t f = 0; f < arr.size(); ++f) {
    const std::string path = std::string(key) + "[" + std::to_string(f) + "]";
    const json& jf = arr[f];
    if (!jf.is_array() || jf.size() != static_cast<size_t>(cameras))
      return r.Fail(path, "expected one entry per camera (" + std::to_string(cameras) + ")");
    DetectionSet set;
    set.sequence = f;
    set.cameras.resize(cameras);
    set.present.assign(cameras, true);
    for (int c = 0; c < cameras; ++c) {
      set.cameras[c].camera = c;
      set.cameras[c].sequence = f;
      if (jf[c].is_null()) {
        set.present[c] = false;
        continue;
      }
      const std::string cpath = path + "[" + std::to_string(c) + "]";
      if (!jf[c].is_array()) return r.Fail(cpath, "expected an array of [u, v] or null");
      for (const json& p : jf[c]) {
        if (!p.is_array() || p.size() != 2 || !p[0].is_number() || !p[1].is_number())
          return r.Fail(cpath, "expected [u, v] pairs of numbers");
        Centroid ct;
        ct.pixel = {p[0].get<double>(), p[1].get<double>()};
        if (!ct.pixel.allFinite()) return r.Fail(cpath, "not finite");
        set.cameras[c].centroids.push_back(ct);
      }
    }
    frames->push_back(std::move(set));
  }
  return Status::Ok();
}

}  // namespace

Status WriteWandObservationsJson(const std::string& path, const WandObservations& obs) {
  json doc = {{"format", "mocap-wand-observations"},
              {"version", 1},
              {"cameras", obs.camera_ids},
              {"wand_markers_m", obs.wand.marker_positions_m}};
  json lf = json::array();
  for (const Eigen::Vector3d& m : obs.lframe.markers_m) lf.push_back({m.x(), m.y(), m.z()});
  doc["lframe_markers_m"] = lf;
  doc["wand_frames"] = FramesToJson(obs.wand_frames);
  doc["lframe_frames"] = FramesToJson(obs.lframe_frames);
  std::ofstream f(path, std::ios::binary);
  if (!f) return Status::Error(path + ": cannot open for writing");
  f << doc.dump() << "\n";
  if (!f) return Status::Error(path + ": write failed");
  return Status::Ok();
}

Status ReadWandObservationsJson(const std::string& path, WandObservations* out) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return Status::Error(path + ": cannot open");
  std::stringstream ss;
  ss << in.rdbuf();
  json doc;
  try {
    doc = json::parse(ss.str());
  } catch (const json::parse_error& e) {
    return Status::Error(path + ": not valid JSON: " + e.what());
  }
  const JsonFields r(path);
  if (!doc.is_object()) return r.Fail("", "expected a JSON object");
  std::string format;
  MOCAP_RETURN_IF_ERROR(r.String(doc, "", "format", &format));
  if (format != "mocap-wand-observations")
    return r.Fail("format", "expected \"mocap-wand-observations\", got \"" + format + "\"");
  WandObservations obs;
  MOCAP_RETURN_IF_ERROR(r.Array(doc, "", "cameras"));
  for (const json& id : doc["cameras"]) {
    if (!id.is_string() || id.get<std::string>().empty())
      return r.Fail("cameras", "expected non-empty camera id strings");
    obs.camera_ids.push_back(id.get<std::string>());
  }
  if (obs.camera_ids.size() < 2) return r.Fail("cameras", "needs at least 2 cameras");
  if (doc.contains("wand_markers_m")) {
    obs.wand.marker_positions_m.clear();
    const json& w = doc["wand_markers_m"];
    if (!w.is_array()) return r.Fail("wand_markers_m", "expected 3 numbers");
    for (const json& v : w) {
      if (!v.is_number()) return r.Fail("wand_markers_m", "expected 3 numbers");
      obs.wand.marker_positions_m.push_back(v.get<double>());
    }
  }
  std::string error;
  if (!obs.wand.IsValid(&error)) return r.Fail("wand_markers_m", error);
  if (doc.contains("lframe_markers_m")) {
    obs.lframe.markers_m.clear();
    const json& l = doc["lframe_markers_m"];
    if (!l.is_array()) return r.Fail("lframe_markers_m", "expected an array of [x, y, z]");
    for (size_t i = 0; i < l.size(); ++i) {
      Eigen::Vector3d m;
      bool ok = l[i].is_array() && l[i].size() == 3;
      for (int k = 0; ok && k < 3; ++k) {
        ok = l[i][k].is_number();
        if (ok) m[k] = l[i][k].get<double>();
      }
      if (!ok) return r.Fail("lframe_markers_m[" + std::to_string(i) + "]", "expected 3 numbers");
      obs.lframe.markers_m.push_back(m);
    }
  }
  if (!obs.lframe.IsValid(&error)) return r.Fail("lframe_markers_m", error);
  const int nc = static_cast<int>(obs.camera_ids.size());
  MOCAP_RETURN_IF_ERROR(FramesFromJson(r, doc, "wand_frames", nc, &obs.wand_frames));
  MOCAP_RETURN_IF_ERROR(FramesFromJson(r, doc, "lframe_frames", nc, &obs.lframe_frames));
  if (obs.wand_frames.empty()) return r.Fail("wand_frames", "no wand frames");
  *out = std::move(obs);
  return Status::Ok();
}

}  // namespace mocap::reconstruction
