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

void PutIfKnown(json* j, const char* key, double v) {
  if (std::isfinite(v)) (*j)[key] = v;
}
}  // namespace

std::vector<CameraModel> CalibrationFile::Models() const {
  std::vector<CameraModel> out;
  for (const CalibratedCamera& c : cameras) out.push_back(c.camera);
  return out;
}

Status WriteCalibrationJson(const std::string& path, const CalibrationFile& file) {
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
              {"fy", k.fy}, {"cx", k.cx},         {"cy", k.cy},         {"k1", k.k1},
              {"k2", k.k2}, {"p1", k.p1},         {"p2", k.p2},         {"k3", k.k3}};
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
  std::ofstream f(path, std::ios::binary);
  if (!f) return Status::Error(path + ": cannot open for writing");
  f << doc.dump(2) << "\n";
  if (!f) return Status::Error(path + ": write failed");
  return Status::Ok();
}

Status ReadCalibrationJson(const std::string& path, CalibrationFile* file) {
  std::ifstream f(path, std::ios::binary);
  if (!f) return Status::Error(path + ": cannot open");
  std::stringstream ss;
  ss << f.rdbuf();
  return ParseCalibrationJson(ss.str(), path, file);
}

Status ParseCalibrationJson(const std::string& text, const std::string& name, CalibrationFile* out) {
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
      std::snprintf(buf, sizeof(buf),
                    "not a rotation matrix (|R^T R - I| = %.3g, det = %.6f)", orth,
                    c.R.determinant());
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

}  // namespace mocap::reconstruction
