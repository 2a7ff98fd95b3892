#include "daemon/config.h"

#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <optional>
#include <sstream>
#include <type_traits>

#include <toml++/toml.h>

#include "solver/global_fit.h"

namespace mocap::daemon {
namespace {

namespace fs = std::filesystem;

// The longest path a Unix socket address holds (sun_path is 108 bytes with its terminating NUL).
constexpr std::size_t kMaxSocketPath = 107;

// The values a number key accepts: [lo, hi] (integers only when `integer`), and optionally one
// sentinel outside it that means "not set here" (a camera's -1 gain: the rig's gain).
struct Range {
  double lo = 0, hi = 0;
  bool integer = false;
  std::optional<double> sentinel = std::nullopt;
  const char* sentinel_meaning = "";
};

// Integers as integers (a seed's bound of 9.2e18 reads as the number it is), others as "%g".
std::string FormatNumber(double v) {
  char text[32];
  std::snprintf(text, sizeof text, v == std::floor(v) && std::fabs(v) < 1e19 ? "%.0f" : "%g", v);
  return text;
}

std::string Describe(const Range& r) {
  std::string d = std::string(r.integer ? "an integer" : "a number") + " in [" +
                  FormatNumber(r.lo) + ", " + FormatNumber(r.hi) + "]";
  if (r.sentinel) d += " or " + FormatNumber(*r.sentinel) + " (" + r.sentinel_meaning + ")";
  return d;
}

// "" when `v` is accepted, else what was expected and what was got.
std::string CheckRange(const Range& r, double v) {
  if (r.sentinel && v == *r.sentinel) return "";
  if (v >= r.lo && v <= r.hi && (!r.integer || v == std::floor(v))) return "";
  return "expected " + Describe(r) + ", got " + FormatNumber(v);
}

// One key of the file and the member it sets. One table of these drives parsing (which keys
// exist, their types and ranges), validation (IsValid) and DiffConfig, so that a key added to
// the table is parsed, checked and diffed alike.
template <class Config>
struct Field {
  enum class Kind { kNumber, kText, kPath };
  const char* table;  // "rig", "control", ...
  const char* key;
  Kind kind;
  bool live;  // a change can be applied without a restart (DiffConfig)
  // kNumber
  Range range{};
  double (*get)(const Config&) = nullptr;  // for range checks and messages
  bool (*equal)(const Config&, const Config&) = nullptr;  // exact (a 64-bit seed is not a double)
  void (*set)(Config*, std::int64_t as_integer, double as_real) = nullptr;
  // kText, kPath
  std::string Config::*text = nullptr;
  bool required = false;              // must not be empty
  std::vector<std::string> choices{};  // kText: the values accepted (empty: any)

  std::string Name() const { return std::string(table) + "." + key; }
};

template <class T>
struct MemberPointer;
template <class C, class V>
struct MemberPointer<V C::*> {
  using Class = C;
  using Value = V;
};

template <auto kMember>
auto Number(const char* table, const char* key, bool live, Range range) {
  using C = typename MemberPointer<decltype(kMember)>::Class;
  using V = typename MemberPointer<decltype(kMember)>::Value;
  range.integer = std::is_integral_v<V>;
  Field<C> f{table, key, Field<C>::Kind::kNumber, live, range};
  f.get = [](const C& c) { return static_cast<double>(c.*kMember); };
  f.equal = [](const C& a, const C& b) { return a.*kMember == b.*kMember; };
  f.set = [](C* c, std::int64_t i, double d) {
    if constexpr (std::is_integral_v<V>)
      c->*kMember = static_cast<V>(i);
    else
      c->*kMember = static_cast<V>(d);
  };
  return f;
}

template <class C>
Field<C> Text(const char* table, const char* key, bool live, std::string C::*member,
              bool required, std::vector<std::string> choices = {}) {
  Field<C> f{table, key, Field<C>::Kind::kText, live};
  f.text = member;
  f.required = required;
  f.choices = std::move(choices);
  return f;
}

template <class C>
Field<C> Path(const char* table, const char* key, bool live, std::string C::*member,
              bool required) {
  Field<C> f = Text(table, key, live, member, required);
  f.kind = Field<C>::Kind::kPath;
  return f;
}

using DaemonField = Field<DaemonConfig>;
using CameraField = Field<CameraConfig>;

// Every key of the file but [[rig.camera]], in the file's order.
const std::vector<DaemonField>& DaemonFields() {
  static const std::vector<DaemonField> fields = {
      Number<&DaemonConfig::simulated_cameras>("rig", "simulated", false, {0, 64}),
      Number<&DaemonConfig::subject_seed>("rig", "subject_seed", false, {0, 9.2e18}),
      Number<&DaemonConfig::rate_hz>("rig", "rate", false, {1, 2000}),
      Number<&DaemonConfig::width>("rig", "width", false, {16, 16384}),
      Number<&DaemonConfig::height>("rig", "height", false, {16, 16384}),
      Number<&DaemonConfig::exposure_us>("rig", "exposure_us", false, {1, 1e6}),
      Number<&DaemonConfig::gain_db>("rig", "gain_db", false, {0, 48}),
      Number<&DaemonConfig::detection_threshold>("rig", "detection_threshold", false, {1, 65535}),
      Number<&DaemonConfig::centroid_noise_px>("rig", "centroid_noise_px", false, {0, 10}),
      Number<&DaemonConfig::detection_threads>("rig", "detection_threads", false, {1, 64}),
      Number<&DaemonConfig::min_cameras>("rig", "min_cameras", false, {1, 64}),
      // The running triangulation can switch calibration between two frame sets (as
      // rig.calibrate.apply does), so a new file applies live.
      Path("rig", "calibration", true, &DaemonConfig::calibration_file, false),
      Text("rig", "sync", false, &DaemonConfig::sync, true, {"trigger", "ptp", "free-run"}),
      Text("rig", "trigger_master", false, &DaemonConfig::trigger_master, false),
      Number<&DaemonConfig::trigger_line>("rig", "trigger_line", false, {0, 15}),
      Number<&DaemonConfig::ptp_lock_timeout_s>("rig", "ptp_lock_timeout_s", false, {0.1, 600}),
      Text("rig", "ptp_schedule", false, &DaemonConfig::ptp_schedule, true, {"sync-free-run", "none"}),
      Text("rig", "pixel_format", false, &DaemonConfig::pixel_format, true,
           {"Mono8", "Mono12", "Mono12Packed", "Mono16"}),
      Number<&DaemonConfig::packet_size>("rig", "packet_size", false,
                                         {576, 16384, false, 0.0, "negotiated"}),
      Number<&DaemonConfig::packet_delay_ns>("rig", "packet_delay_ns", false, {0, 100000000}),
      Text("rig", "packet_resend", false, &DaemonConfig::packet_resend, true, {"always", "never"}),
      Number<&DaemonConfig::socket_buffer_bytes>("rig", "socket_buffer_bytes", false,
                                                 {0, 1 << 30}),
      Path("storage", "state_dir", false, &DaemonConfig::state_dir, true),
      Path("control", "socket", false, &DaemonConfig::socket_path, true),
      Text("control", "group", true, &DaemonConfig::control_group, true),
      Number<&DaemonConfig::max_clients>("control", "max_clients", true, {1, 4096}),
      Number<&DaemonConfig::max_line_bytes>("control", "max_line_bytes", true,
                                            {1024, 64 << 20}),
      Number<&DaemonConfig::subscriber_queue_frames>("control", "subscriber_queue_frames", true,
                                                     {1, 100000}),
      Number<&DaemonConfig::max_pending_requests>("control", "max_pending_requests", true,
                                                  {1, 4096}),
      Path("protocol", "file", true, &DaemonConfig::protocol_file, false),
      // The tracker is built with its options when the pipeline starts.
      Number<&DaemonConfig::tracker_sigma_m>("tracker", "sigma_m", false, {1e-4, 0.1}),
      Number<&DaemonConfig::tracker_gate_chi2>("tracker", "gate_chi2", false, {1, 100}),
      Number<&DaemonConfig::fit_threads>("fit", "threads", true, {0, 256}),
      Number<&DaemonConfig::fit_max_iterations>("fit", "max_iterations", true, {1, 10000}),
      Text("fit", "groups", true, &DaemonConfig::fit_groups, true),
      Number<&DaemonConfig::fit_coarse_frames>("fit", "coarse_frames", true, {0, 1000000}),
  };
  return fields;
}

const std::vector<CameraField>& CameraFields() {
  static const std::vector<CameraField> fields = {
      Text("rig.camera", "id", false, &CameraConfig::id, true),
      Text("rig.camera", "backend", false, &CameraConfig::backend, true, {"aravis", "simulated"}),
      Number<&CameraConfig::exposure_us>("rig.camera", "exposure_us", false,
                                         {1, 1e6, false, 0.0, "the rig's"}),
      Number<&CameraConfig::gain_db>("rig.camera", "gain_db", false,
                                     {0, 48, false, -1.0, "the rig's"}),
      Number<&CameraConfig::detection_threshold>("rig.camera", "detection_threshold", false,
                                                 {1, 65535, false, 0.0, "the rig's"}),
      Text("rig.camera", "interface", false, &CameraConfig::interface, true,
           {"gige", "10gige", "usb3"}),
      Text("rig.camera", "link", false, &CameraConfig::link, false),
      Number<&CameraConfig::strobe_line>("rig.camera", "strobe_line", false,
                                         {0, 15, false, -1.0, "none"}),
      Text("rig.camera", "optional", false, &CameraConfig::optional, false),
      Text("rig.camera", "usb_mode", false, &CameraConfig::usb_mode, true,
           {"default", "sync", "async"}),
      Number<&CameraConfig::usb_throughput_limit_mb_s>("rig.camera", "usb_throughput_limit_mb_s",
                                                       false, {0, 100000}),
      Number<&CameraConfig::sim_clock_offset_ms>("rig.camera", "sim_clock_offset_ms", false,
                                                 {-1e6, 1e6}),
      Number<&CameraConfig::sim_clock_drift_ppm>("rig.camera", "sim_clock_drift_ppm", false,
                                                 {-1000, 1000}),
      Number<&CameraConfig::sim_arrival_wait_us>("rig.camera", "sim_arrival_wait_us", false,
                                                 {0, 100000}),
  };
  return fields;
}

// The keys of one rectangle of rig.camera[i].masks (checked against the image in Validate).
const std::vector<Field<MaskRect>>& MaskFields() {
  static const std::vector<Field<MaskRect>> fields = {
      Number<&MaskRect::x>("mask", "x", false, {0, 16383}),
      Number<&MaskRect::y>("mask", "y", false, {0, 16383}),
      Number<&MaskRect::width>("mask", "width", false, {1, 16384}),
      Number<&MaskRect::height>("mask", "height", false, {1, 16384}),
  };
  return fields;
}

const char* const kTables[] = {"rig", "storage", "control", "protocol", "tracker", "fit"};

template <class C>
std::string KeysOf(const std::vector<Field<C>>& fields, const std::string& table,
                   const char* extra = nullptr) {
  std::string keys;
  for (const auto& f : fields) {
    if (table != f.table) continue;
    keys += (keys.empty() ? "" : ", ") + std::string(f.key);
  }
  if (extra) keys += std::string(", ") + extra;
  return keys;
}

// How errors name the table of `fields` whose `table` is this: a mask is an inline table, not a
// [section] of the file.
std::string Owner(const std::string& table) { return table == "mask" ? "a mask" : "[" + table + "]"; }

// Where each key was read from, so that validation after parsing still names the line.
using KeyLines = std::map<std::string, int>;

// Builds "file:line: key: message" (or "key: message" where no line is known).
class ErrorFormatter {
 public:
  ErrorFormatter(std::string source, const KeyLines* lines)
      : source_(std::move(source)), lines_(lines) {}
  std::string operator()(const std::string& key, const std::string& message) const {
    std::string where;
    if (lines_) {
      // The key's own line, else the nearest enclosing one it was read under.
      std::string k = key;
      while (!k.empty()) {
        if (auto it = lines_->find(k); it != lines_->end()) {
          where = source_ + ":" + std::to_string(it->second) + ": ";
          break;
        }
        const std::size_t cut = k.find_last_of(".[");
        k = cut == std::string::npos ? "" : k.substr(0, cut);
      }
      if (where.empty()) where = source_ + ": ";
    }
    return where + key + ": " + message;
  }

 private:
  std::string source_;
  const KeyLines* lines_;
};

// The checks of one value that do not depend on other values; "" when it passes.
template <class C>
std::string CheckField(const Field<C>& f, const C& config) {
  if (f.kind == Field<C>::Kind::kNumber) return CheckRange(f.range, f.get(config));
  const std::string& value = config.*(f.text);
  if (f.required && value.empty()) return "must not be empty";
  if (!f.choices.empty()) {
    bool known = false;
    std::string list;
    for (const auto& c : f.choices) {
      known |= value == c;
      list += (list.empty() ? "\"" : ", \"") + c + "\"";
    }
    if (!known) return "expected one of " + list + ", got \"" + value + "\"";
  }
  return "";
}

bool Validate(const DaemonConfig& c, const ErrorFormatter& fail, std::string* error) {
  auto set_error = [&](const std::string& key, const std::string& message) {
    if (error) *error = fail(key, message);
    return false;
  };
  for (const auto& f : DaemonFields())
    if (std::string m = CheckField(f, c); !m.empty()) return set_error(f.Name(), m);
  if (c.socket_path.size() > kMaxSocketPath)
    return set_error("control.socket", "\"" + c.socket_path + "\" is " +
                                           std::to_string(c.socket_path.size()) +
                                           " bytes long; a Unix socket path holds at most " +
                                           std::to_string(kMaxSocketPath));
  for (std::size_t i = 0; i < c.export_dirs.size(); ++i)
    if (c.export_dirs[i].empty() || c.export_dirs[i][0] != '/')
      return set_error("storage.export_dirs[" + std::to_string(i) + "]",
                       "expected an absolute path, got \"" + c.export_dirs[i] + "\"");
  if (Status s = solver::FitOptions().SetGroups(c.fit_groups); !s)
    return set_error("fit.groups", s.message());

  const double frame_period_us = 1e6 / c.rate_hz;
  auto check_exposure = [&](const std::string& key, double exposure_us) {
    if (exposure_us < frame_period_us) return true;
    return set_error(key, FormatNumber(exposure_us) + " us does not fit in the frame period of " +
                              FormatNumber(frame_period_us) + " us (rig.rate " +
                              FormatNumber(c.rate_hz) + " Hz)");
  };
  if (!check_exposure("rig.exposure_us", c.exposure_us)) return false;
  if (!c.trigger_master.empty()) {
    if (c.simulated_cameras > 0)
      return set_error("rig.trigger_master", "\"" + c.trigger_master +
                                                 "\" on a simulated rig (its fake cameras share "
                                                 "the host's clock; there is nothing to trigger)");
    if (c.sync != "trigger")
      return set_error("rig.trigger_master", "\"" + c.trigger_master +
                                                 "\" given with rig.sync \"" + c.sync +
                                                 "\" (a trigger master belongs to sync = \"trigger\")");
    bool listed = false;
    for (const CameraConfig& cam : c.cameras) listed |= cam.id == c.trigger_master;
    if (!listed)
      return set_error("rig.trigger_master", "\"" + c.trigger_master +
                                                 "\" is not the id of a [[rig.camera]]");
  }

  if (c.simulated_cameras == 0 && c.cameras.empty())
    return set_error("rig", "a real rig needs at least one [[rig.camera]] (or simulated = N for "
                            "a simulated rig of N cameras)");
  if (c.simulated_cameras > 0 && !c.cameras.empty() &&
      static_cast<int>(c.cameras.size()) < c.simulated_cameras)
    return set_error("rig.camera", std::to_string(c.cameras.size()) +
                                       " cameras listed for a simulated rig of " +
                                       std::to_string(c.simulated_cameras) +
                                       " (list none, or one per simulated camera, then the real "
                                       "cameras that join it)");
  if (c.cameras.size() > 64)
    return set_error("rig.camera", std::to_string(c.cameras.size()) +
                                       " cameras; a rig has at most 64 (frame sets hold a "
                                       "64-bit camera mask)");
  std::map<std::string, std::size_t> first_with_id;
  for (std::size_t i = 0; i < c.cameras.size(); ++i) {
    const CameraConfig& cam = c.cameras[i];
    const std::string prefix = "rig.camera[" + std::to_string(i) + "]";
    for (const auto& f : CameraFields())
      if (std::string m = CheckField(f, cam); !m.empty())
        return set_error(prefix + "." + f.key, m);
    if (auto [it, added] = first_with_id.emplace(cam.id, i); !added)
      return set_error(prefix + ".id", "\"" + cam.id + "\" is also rig.camera[" +
                                           std::to_string(it->second) + "]'s id");
    // After a simulated rig's fakes: a real camera joining it (config.h).
    if (c.simulated_cameras > 0 && static_cast<int>(i) >= c.simulated_cameras) {
      const std::string joins = "'" + cam.id + "', after the " + std::to_string(c.simulated_cameras) +
                                " simulated cameras, joins the simulated rig as a real camera";
      if (cam.backend != "aravis")
        return set_error(prefix + ".backend", joins + ": backend \"aravis\", got \"" + cam.backend + "\"");
      if (c.sync == "ptp")
        return set_error(prefix + ".id", joins + ": rig.sync \"trigger\" or \"free-run\" (the fakes' PTP "
                                                 "is simulated), got \"ptp\"");
    }
    if (cam.exposure_us != 0 && !check_exposure(prefix + ".exposure_us", cam.exposure_us))
      return false;
    if (cam.interface != "usb3" && cam.usb_mode != "default")
      return set_error(prefix + ".usb_mode", "\"" + cam.usb_mode + "\" on a " + cam.interface +
                                                 " camera (USB3 Vision transfer: interface = \"usb3\")");
    if (cam.interface != "usb3" && cam.usb_throughput_limit_mb_s > 0)
      return set_error(prefix + ".usb_throughput_limit_mb_s",
                       FormatNumber(cam.usb_throughput_limit_mb_s) + " on a " + cam.interface +
                           " camera (USB3 Vision transfer: interface = \"usb3\")");
    if (cam.usb_throughput_limit_mb_s > 0) {
      // What the camera sends: a limit below it drops frames every second or so, silently.
      const double need = CameraImageMbS(c);
      if (cam.usb_throughput_limit_mb_s < need)
        return set_error(prefix + ".usb_throughput_limit_mb_s",
                         FormatNumber(cam.usb_throughput_limit_mb_s) + " MB/s is below the " +
                             FormatNumber(std::round(need * 10) / 10) + " MB/s the camera sends (" +
                             std::to_string(c.width) + "x" + std::to_string(c.height) + " " +
                             c.pixel_format + " at " + FormatNumber(c.rate_hz) + " Hz)");
    }
    // sync = "ptp" takes an offset too: the fake's own clock, which PTP replaces by the master's
    // and whose phase an unscheduled fake free-runs at (drivers/aravis_fake.h ptp_features).
    if ((cam.sim_clock_offset_ms != 0 || cam.sim_clock_drift_ppm != 0 || cam.sim_arrival_wait_us != 0) &&
        (c.simulated_cameras == 0 ||
         (c.sync != "free-run" &&
          (c.sync != "ptp" || cam.sim_clock_drift_ppm != 0 || cam.sim_arrival_wait_us != 0))))
      return set_error(prefix + (cam.sim_clock_offset_ms != 0   ? ".sim_clock_offset_ms"
                                 : cam.sim_clock_drift_ppm != 0 ? ".sim_clock_drift_ppm"
                                                                : ".sim_arrival_wait_us"),
                       c.simulated_cameras == 0
                           ? "a simulated camera's clock on a real rig (its cameras have clocks of their own)"
                           : "needs rig.sync = \"free-run\" (got \"" + c.sync +
                                 "\": the fakes' one clock has no offsets to fit)");
    if (cam.id == c.trigger_master && cam.strobe_line < 0)
      return set_error(prefix + ".strobe_line",
                       "-1 (none) on the trigger master \"" + cam.id +
                           "\": its strobe output line triggers the other cameras");
    for (std::size_t m = 0; m < cam.masks.size(); ++m) {
      const MaskRect& r = cam.masks[m];
      if (r.x < 0 || r.y < 0 || r.width < 1 || r.height < 1 || r.x + r.width > c.width ||
          r.y + r.height > c.height)
        return set_error(prefix + ".masks[" + std::to_string(m) + "]",
                         "x " + std::to_string(r.x) + ", y " + std::to_string(r.y) + ", width " +
                             std::to_string(r.width) + ", height " + std::to_string(r.height) +
                             " is not a rectangle within the " + std::to_string(c.width) + "x" +
                             std::to_string(c.height) + " image");
    }
  }
  return true;
}

// ---------------------------------------------------------------------------------------------
// Reading the TOML tree.

int LineOf(const toml::node& node) { return static_cast<int>(node.source().begin.line); }

// How a value the file holds is shown in an error: strings quoted, as the file spells them.
std::string Shown(const toml::node& node) {
  if (const auto* s = node.as_string()) return "\"" + s->get() + "\"";
  if (const auto* i = node.as_integer()) return std::to_string(i->get());
  if (const auto* d = node.as_floating_point()) return FormatNumber(d->get());
  if (const auto* b = node.as_boolean()) return b->get() ? "true" : "false";
  if (node.is_table()) return "a table";
  if (node.is_array()) return "an array";
  return "a date or time";
}

class Reader {
 public:
  Reader(const std::string& source, KeyLines* lines)
      : source_(source), base_dir_(fs::path(source).parent_path()), lines_(lines) {}

  Status Error(const toml::node& node, const std::string& key, const std::string& message) const {
    return Status::Error(source_ + ":" + std::to_string(LineOf(node)) + ": " + key + ": " +
                         message);
  }

  Status Document(const toml::table& root, DaemonConfig* config) {
    for (const auto& [k, node] : root) {
      const std::string name(k.str());
      bool known = false;
      for (const char* t : kTables) known |= name == t;
      if (!known) {
        std::string tables;
        for (const char* t : kTables) tables += (tables.empty() ? "[" : ", [") + std::string(t) + "]";
        return Error(node, name,
                     node.is_table() ? "unknown table (the tables are " + tables + ")"
                                     : "unknown key (keys belong in one of the tables " +
                                           tables + ")");
      }
      const toml::table* table = node.as_table();
      if (!table) return Error(node, name, "expected a table [" + name + "], got " + Shown(node));
      (*lines_)[name] = LineOf(node);
      for (const auto& [key, value] : *table) {
        const std::string key_name(key.str());
        if (name == "rig" && key_name == "camera") {
          MOCAP_RETURN_IF_ERROR(Cameras(value, config));
          continue;
        }
        if (name == "storage" && key_name == "export_dirs") {
          MOCAP_RETURN_IF_ERROR(PathList(value, "storage.export_dirs", &config->export_dirs));
          continue;
        }
        MOCAP_RETURN_IF_ERROR(
            Value(DaemonFields(), name, name + "." + key_name, key_name, value, config,
                  name == "rig" ? "camera ([[rig.camera]])"
                                : name == "storage" ? "export_dirs" : nullptr));
      }
    }
    return Status::Ok();
  }

 private:
  // Sets the field `key` of [table] (named `full_key` in errors) from `node`.
  template <class C>
  Status Value(const std::vector<Field<C>>& fields, const std::string& table,
               const std::string& full_key, const std::string& key, const toml::node& node,
               C* config, const char* extra_keys) {
    const Field<C>* field = nullptr;
    for (const auto& f : fields)
      if (table == f.table && key == f.key) field = &f;
    if (!field)
      return Error(node, full_key,
                   "unknown key (the keys of " + Owner(table) + " are " +
                       KeysOf(fields, table, extra_keys) + ")");
    (*lines_)[full_key] = LineOf(node);
    if (field->kind == Field<C>::Kind::kNumber) {
      const auto* as_int = node.as_integer();
      const auto* as_real = node.as_floating_point();
      if (!as_int && !(as_real && !field->range.integer))
        return Error(node, full_key, "expected " + Describe(field->range) + ", got " + Shown(node));
      const double v = as_int ? static_cast<double>(as_int->get()) : as_real->get();
      // Checked before it is stored: an out-of-range integer would not survive the cast.
      if (std::string m = CheckRange(field->range, v); !m.empty())
        return Error(node, full_key, m);
      field->set(config, as_int ? as_int->get() : 0, v);
      return Status::Ok();
    }
    const auto* s = node.as_string();
    if (!s)
      return Error(node, full_key,
                   std::string(field->kind == Field<C>::Kind::kPath ? "expected a path (a string)"
                                                                    : "expected a string") +
                       ", got " + Shown(node));
    std::string value = s->get();
    if (field->kind == Field<C>::Kind::kPath && !value.empty())
      value = (base_dir_ / fs::path(value)).lexically_normal().string();
    config->*(field->text) = value;
    if (std::string m = CheckField(*field, *config); !m.empty()) return Error(node, full_key, m);
    return Status::Ok();
  }

  Status Cameras(const toml::node& node, DaemonConfig* config) {
    const toml::array* cameras = node.as_array();
    if (!cameras || !cameras->is_array_of_tables())
      return Error(node, "rig.camera",
                   "expected camera tables ([[rig.camera]] sections), got " + Shown(node));
    (*lines_)["rig.camera"] = LineOf(node);
    for (std::size_t i = 0; i < cameras->size(); ++i) {
      const toml::table& table = *(*cameras)[i].as_table();
      const std::string prefix = "rig.camera[" + std::to_string(i) + "]";
      (*lines_)[prefix] = LineOf(table);
      CameraConfig camera;
      for (const auto& [key, value] : table) {
        const std::string key_name(key.str());
        if (key_name == "masks") {
          MOCAP_RETURN_IF_ERROR(Masks(value, prefix + ".masks", &camera.masks));
          continue;
        }
        MOCAP_RETURN_IF_ERROR(Value(CameraFields(), "rig.camera", prefix + "." + key_name,
                                    key_name, value, &camera, "masks"));
      }
      if (camera.id.empty())
        return Error(table, prefix + ".id", "missing: each camera needs its GenICam id or serial");
      config->cameras.push_back(std::move(camera));
    }
    return Status::Ok();
  }

  // An array of paths, each resolved against the file's directory as a single path key is.
  Status PathList(const toml::node& node, const std::string& key, std::vector<std::string>* out) {
    const toml::array* array = node.as_array();
    if (!array) return Error(node, key, "expected an array of paths, got " + Shown(node));
    (*lines_)[key] = LineOf(node);
    out->clear();
    for (std::size_t i = 0; i < array->size(); ++i) {
      const toml::node& item = (*array)[i];
      const auto* s = item.as_string();
      const std::string item_key = key + "[" + std::to_string(i) + "]";
      if (!s) return Error(item, item_key, "expected a path (a string), got " + Shown(item));
      if (s->get().empty()) return Error(item, item_key, "must not be empty");
      out->push_back((base_dir_ / fs::path(s->get())).lexically_normal().string());
    }
    return Status::Ok();
  }

  Status Masks(const toml::node& node, const std::string& key, std::vector<MaskRect>* masks) {
    const std::string expected = "expected rectangles [ { x = 0, y = 0, width = 10, height = 10 } ]";
    const toml::array* array = node.as_array();
    if (!array) return Error(node, key, expected + ", got " + Shown(node));
    for (std::size_t m = 0; m < array->size(); ++m) {
      const toml::node& item = (*array)[m];
      const std::string item_key = key + "[" + std::to_string(m) + "]";
      const toml::table* rect = item.as_table();
      if (!rect) return Error(item, item_key, expected + ", got " + Shown(item));
      (*lines_)[item_key] = LineOf(item);
      MaskRect r;
      for (const auto& [name, value] : *rect)
        MOCAP_RETURN_IF_ERROR(Value(MaskFields(), "mask", item_key + "." + std::string(name.str()),
                                    std::string(name.str()), value, &r, nullptr));
      for (const auto& f : MaskFields())
        if (!rect->contains(f.key))
          return Error(item, item_key, std::string("missing ") + f.key + " (the keys of " +
                                           Owner("mask") + " are " + KeysOf(MaskFields(), "mask") + ")");
      masks->push_back(r);
    }
    return Status::Ok();
  }

  std::string source_;
  fs::path base_dir_;
  KeyLines* lines_;
};

}  // namespace

bool DaemonConfig::IsValid(std::string* error) const {
  return Validate(*this, ErrorFormatter(source, nullptr), error);
}

double ConfiguredBytesPerPixel(const std::string& pixel_format) {
  if (pixel_format == "Mono8") return 1.0;
  if (pixel_format == "Mono12Packed") return 1.5;
  if (pixel_format == "Mono12" || pixel_format == "Mono16") return 2.0;
  return 0.0;
}

double CameraImageMbS(const DaemonConfig& c) {
  return static_cast<double>(c.width) * c.height * ConfiguredBytesPerPixel(c.pixel_format) *
         c.rate_hz * 1e-6;
}

Status ParseConfig(const std::string& text, const std::string& source, DaemonConfig* out) {
  toml::table root;
  try {
    root = toml::parse(text, source);
  } catch (const toml::parse_error& e) {
    return Status::Error(source + ":" + std::to_string(e.source().begin.line) + ": " +
                         std::string(e.description()));
  }
  DaemonConfig config;
  config.source = source;
  KeyLines lines;
  Reader reader(source, &lines);
  MOCAP_RETURN_IF_ERROR(reader.Document(root, &config));
  std::string error;
  if (!Validate(config, ErrorFormatter(source, &lines), &error)) return Status::Error(error);
  *out = std::move(config);
  return Status::Ok();
}

Status LoadConfig(const std::string& path, DaemonConfig* out) {
  std::error_code ec;
  const fs::path absolute = fs::absolute(path, ec);
  const std::string source = ec ? path : absolute.lexically_normal().string();
  std::ifstream in(source, std::ios::binary);
  if (!in) return Status::Error(source + ": cannot read: " + std::strerror(errno));
  std::ostringstream text;
  text << in.rdbuf();
  if (in.bad()) return Status::Error(source + ": cannot read: " + std::strerror(errno));
  return ParseConfig(text.str(), source, out);
}

std::vector<ConfigChange> DiffConfig(const DaemonConfig& a, const DaemonConfig& b) {
  std::vector<ConfigChange> changes;
  for (const auto& f : DaemonFields()) {
    const bool differs = f.kind == DaemonField::Kind::kNumber ? !f.equal(a, b)
                                                              : a.*(f.text) != b.*(f.text);
    if (differs) changes.push_back({f.Name(), !f.live});
  }
  // The next export checks its path against them.
  if (a.export_dirs != b.export_dirs) changes.push_back({"storage.export_dirs", false});
  if (a.cameras != b.cameras) changes.push_back({"rig.camera", true});
  return changes;
}

}  // namespace mocap::daemon
