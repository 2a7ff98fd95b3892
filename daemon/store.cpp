#include "daemon/store.h"

#include <sqlite3.h>

#include <bit>
#include <cmath>
#include <filesystem>
#include <limits>
#include <nlohmann/json.hpp>
#include <set>
#include <system_error>
#include <utility>

#include "model/model.h"
#include "model/model_io.h"

namespace mocap::daemon {
namespace {

// ---------------------------------------------------------------------------------------------
// Small RAII wrappers over the SQLite C API. Every error names the database path, the SQL step
// (its statement) and sqlite3_errmsg.

Status SqlError(sqlite3* db, const std::string& db_path, const std::string& step) {
  return Status::Error(db_path + ": " + step + ": " + sqlite3_errmsg(db) + " (SQLite code " +
                       std::to_string(sqlite3_extended_errcode(db)) + ")");
}

// Prefixes the message of a failed status with what was being done.
Status In(const std::string& what, Status s) {
  return s.ok() ? s : Status::Error(what + ": " + s.message());
}

Status ExecSql(sqlite3* db, const std::string& db_path, const std::string& sql,
               const std::string& what) {
  if (sqlite3_exec(db, sql.c_str(), nullptr, nullptr, nullptr) != SQLITE_OK) {
    return SqlError(db, db_path, what);
  }
  return Status::Ok();
}

// One prepared statement. Parameters are bound in order (Bind returns *this, so binds chain); a
// failed prepare or bind is remembered and returned by the next Step/Run, so call sites stay flat.
class Statement {
 public:
  Statement(sqlite3* db, const std::string& db_path, std::string sql)
      : db_(db), db_path_(db_path), sql_(std::move(sql)) {
    if (sqlite3_prepare_v2(db, sql_.c_str(), -1, &stmt_, nullptr) != SQLITE_OK) {
      status_ = SqlError(db_, db_path_, "preparing `" + sql_ + "`");
    }
  }
  ~Statement() { sqlite3_finalize(stmt_); }
  Statement(const Statement&) = delete;
  Statement& operator=(const Statement&) = delete;

  Statement& Bind(std::int64_t v) {
    return Check(stmt_ ? sqlite3_bind_int64(stmt_, ++index_, v) : SQLITE_OK);
  }
  Statement& Bind(int v) { return Bind(static_cast<std::int64_t>(v)); }
  Statement& Bind(double v) {
    return Check(stmt_ ? sqlite3_bind_double(stmt_, ++index_, v) : SQLITE_OK);
  }
  Statement& Bind(const std::string& v) {
    return Check(stmt_ ? sqlite3_bind_text(stmt_, ++index_, v.data(), static_cast<int>(v.size()),
                                           SQLITE_TRANSIENT)
                       : SQLITE_OK);
  }
  Statement& BindBlob(const std::string& v) {
    return Check(stmt_ ? sqlite3_bind_blob64(stmt_, ++index_, v.data(), v.size(), SQLITE_STATIC)
                       : SQLITE_OK);
  }
  Statement& BindNull() { return Check(stmt_ ? sqlite3_bind_null(stmt_, ++index_) : SQLITE_OK); }
  Statement& Bind(const std::optional<std::int64_t>& v) { return v ? Bind(*v) : BindNull(); }

  // One step: *row is true when a result row is ready to read.
  Status Step(bool* row) {
    if (!status_.ok()) return status_;
    const int rc = sqlite3_step(stmt_);
    if (rc == SQLITE_ROW) {
      *row = true;
      return Status::Ok();
    }
    *row = false;
    if (rc == SQLITE_DONE) return Status::Ok();
    return SqlError(db_, db_path_, "running `" + sql_ + "`");
  }
  // Steps to the end, ignoring rows (INSERT / UPDATE).
  Status Run() {
    bool row = true;
    while (row) MOCAP_RETURN_IF_ERROR(Step(&row));
    return Status::Ok();
  }

  std::int64_t Int(int col) const { return sqlite3_column_int64(stmt_, col); }
  double Double(int col) const { return sqlite3_column_double(stmt_, col); }
  bool IsNull(int col) const { return sqlite3_column_type(stmt_, col) == SQLITE_NULL; }
  std::string Text(int col) const {
    const auto* p = reinterpret_cast<const char*>(sqlite3_column_text(stmt_, col));
    return p ? std::string(p, sqlite3_column_bytes(stmt_, col)) : std::string();
  }
  std::string Blob(int col) const {
    const auto* p = static_cast<const char*>(sqlite3_column_blob(stmt_, col));
    return p ? std::string(p, sqlite3_column_bytes(stmt_, col)) : std::string();
  }

 private:
  Statement& Check(int rc) {
    if (rc != SQLITE_OK && status_.ok()) {
      status_ = SqlError(db_, db_path_,
                         "binding parameter " + std::to_string(index_) + " of `" + sql_ + "`");
    }
    return *this;
  }

  sqlite3* db_;
  const std::string& db_path_;
  std::string sql_;
  sqlite3_stmt* stmt_ = nullptr;
  int index_ = 0;
  Status status_;
};

// A transaction rolled back unless committed. Writers use BEGIN IMMEDIATE: the write lock is
// taken at BEGIN (waiting up to busy_timeout), so a read-then-write transaction cannot fail
// half-way with SQLITE_BUSY when another connection wrote in between. Readers use a deferred
// BEGIN: one consistent snapshot across several SELECTs.
class Transaction {
 public:
  enum class Kind { kRead, kWrite };
  Transaction(sqlite3* db, const std::string& db_path) : db_(db), db_path_(db_path) {}
  ~Transaction() {
    if (open_) sqlite3_exec(db_, "ROLLBACK", nullptr, nullptr, nullptr);
  }
  Status Begin(Kind kind) {
    MOCAP_RETURN_IF_ERROR(ExecSql(db_, db_path_, kind == Kind::kWrite ? "BEGIN IMMEDIATE" : "BEGIN",
                                  "beginning a transaction"));
    open_ = true;
    return Status::Ok();
  }
  Status Commit() {
    MOCAP_RETURN_IF_ERROR(ExecSql(db_, db_path_, "COMMIT", "committing a transaction"));
    open_ = false;
    return Status::Ok();
  }

 private:
  sqlite3* db_;
  const std::string& db_path_;
  bool open_ = false;
};

// ---------------------------------------------------------------------------------------------
// Schema. kMigrations[v] takes a database from user_version v to v + 1.

#define MOCAP_NOW "(strftime('%Y-%m-%dT%H:%M:%fZ', 'now'))"

// clang-format off
const char* const kMigrations[] = {
    // 0 -> 1: the first schema.
    "CREATE TABLE subjects ("
    "  id INTEGER PRIMARY KEY,"
    "  name TEXT NOT NULL UNIQUE CHECK (length(name) > 0),"
    "  height_m REAL NOT NULL,"
    "  model_source TEXT NOT NULL,"
    "  osim_text TEXT NOT NULL DEFAULT '',"
    "  created_at TEXT NOT NULL DEFAULT " MOCAP_NOW ","
    "  produced_by TEXT NOT NULL);"
    "CREATE TABLE fit_reports ("
    "  id INTEGER PRIMARY KEY,"
    "  subject_id INTEGER NOT NULL REFERENCES subjects(id),"
    "  report_json TEXT NOT NULL,"
    "  created_at TEXT NOT NULL DEFAULT " MOCAP_NOW ","
    "  produced_by TEXT NOT NULL);"
    "CREATE TABLE models ("
    "  id INTEGER PRIMARY KEY,"
    "  subject_id INTEGER NOT NULL REFERENCES subjects(id),"
    "  version INTEGER NOT NULL CHECK (version >= 1),"
    "  model_json TEXT NOT NULL,"
    "  fit_report_id INTEGER REFERENCES fit_reports(id),"
    "  created_at TEXT NOT NULL DEFAULT " MOCAP_NOW ","
    "  produced_by TEXT NOT NULL,"
    "  UNIQUE (subject_id, version));"
    "CREATE TABLE calibrations ("
    "  version INTEGER PRIMARY KEY,"
    "  calibration_json TEXT NOT NULL,"
    "  reprojection_rms_px REAL NOT NULL,"
    "  wand_length_error_mm REAL NOT NULL,"
    "  created_at TEXT NOT NULL DEFAULT " MOCAP_NOW ","
    "  produced_by TEXT NOT NULL);"
    "CREATE TABLE recordings ("
    "  id INTEGER PRIMARY KEY,"
    "  subject_id INTEGER NOT NULL REFERENCES subjects(id),"
    "  movement TEXT NOT NULL,"
    "  state TEXT NOT NULL CHECK (state IN ('recording', 'complete', 'interrupted', 'failed')),"
    "  rate_hz REAL NOT NULL,"
    "  marker_names TEXT NOT NULL,"
    "  coordinate_names TEXT NOT NULL,"
    "  model_version INTEGER NOT NULL,"
    "  started_at TEXT NOT NULL DEFAULT " MOCAP_NOW ","
    "  stopped_at TEXT NOT NULL DEFAULT '',"
    "  frame_count INTEGER NOT NULL DEFAULT 0,"
    "  coverage_json TEXT NOT NULL DEFAULT '',"
    "  note TEXT NOT NULL DEFAULT '',"
    "  created_at TEXT NOT NULL DEFAULT " MOCAP_NOW ","
    "  produced_by TEXT NOT NULL);"
    "CREATE INDEX recordings_by_subject ON recordings(subject_id);"
    "CREATE INDEX recordings_by_state ON recordings(state);"
    "CREATE TABLE recording_chunks ("
    "  recording_id INTEGER NOT NULL REFERENCES recordings(id),"
    "  chunk_index INTEGER NOT NULL,"
    "  first_frame INTEGER NOT NULL,"
    "  last_frame INTEGER NOT NULL,"
    "  frame_count INTEGER NOT NULL,"
    "  frames BLOB NOT NULL,"
    "  created_at TEXT NOT NULL DEFAULT " MOCAP_NOW ","
    "  produced_by TEXT NOT NULL,"
    "  PRIMARY KEY (recording_id, chunk_index));",
    // 1 -> 2: what the daemon had live (the selected subject, its live model, the live rig
    // calibration), so a restart (a crash, the watchdog) resumes it.
    "CREATE TABLE daemon_state ("
    "  key TEXT PRIMARY KEY,"
    "  value TEXT NOT NULL,"
    "  updated_at TEXT NOT NULL DEFAULT " MOCAP_NOW ");",
};
// clang-format on
static_assert(std::size(kMigrations) == Store::kSchemaVersion, "one migration per schema version");

// Reads PRAGMA user_version.
Status ReadSchemaVersion(sqlite3* db, const std::string& db_path, int* version) {
  Statement q(db, db_path, "PRAGMA user_version");
  bool row = false;
  MOCAP_RETURN_IF_ERROR(q.Step(&row));
  *version = row ? static_cast<int>(q.Int(0)) : 0;
  return Status::Ok();
}

// ---------------------------------------------------------------------------------------------
// Rows.

const char* const kSubjectColumns =
    "id, name, height_m, model_source, osim_text,"
    " (SELECT COALESCE(MAX(version), 0) FROM models m WHERE m.subject_id = subjects.id),"
    " created_at, produced_by FROM subjects";
Status ReadSubject(const Statement& q, SubjectRecord* s) {
  s->id = q.Int(0);
  s->name = q.Text(1);
  s->height_m = q.Double(2);
  s->model_source = q.Text(3);
  s->osim_text = q.Text(4);
  s->latest_model_version = static_cast<int>(q.Int(5));
  s->created_at = q.Text(6);
  s->produced_by = q.Text(7);
  return Status::Ok();
}

const char* const kModelColumns =
    "id, subject_id, version, model_json, fit_report_id, created_at, produced_by FROM models";
Status ReadModel(const Statement& q, ModelRecord* m) {
  m->id = q.Int(0);
  m->subject_id = q.Int(1);
  m->version = static_cast<int>(q.Int(2));
  m->model_json = q.Text(3);
  m->fit_report_id = q.IsNull(4) ? std::nullopt : std::optional<std::int64_t>(q.Int(4));
  m->created_at = q.Text(5);
  m->produced_by = q.Text(6);
  return Status::Ok();
}

const char* const kCalibrationColumns =
    "version, calibration_json, reprojection_rms_px, wand_length_error_mm, created_at,"
    " produced_by FROM calibrations";
Status ReadCalibration(const Statement& q, CalibrationRecord* c) {
  c->version = q.Int(0);
  c->calibration_json = q.Text(1);
  c->reprojection_rms_px = q.Double(2);
  c->wand_length_error_mm = q.Double(3);
  c->created_at = q.Text(4);
  c->produced_by = q.Text(5);
  return Status::Ok();
}

const char* const kRecordingColumns =
    "id, subject_id, movement, state, rate_hz, marker_names, coordinate_names, model_version,"
    " started_at, stopped_at, frame_count,"
    " (SELECT COUNT(*) FROM recording_chunks c WHERE c.recording_id = recordings.id),"
    " coverage_json, note, created_at, produced_by FROM recordings";

// A JSON array of strings, as stored in recordings.marker_names / coordinate_names.
Status ParseNameArray(const std::string& text, const std::string& where,
                      std::vector<std::string>* names) {
  const nlohmann::json j = nlohmann::json::parse(text, nullptr, /*allow_exceptions=*/false);
  if (!j.is_array()) return Status::Error(where + ": not a JSON array of names: " + text);
  names->clear();
  for (const auto& e : j) {
    if (!e.is_string()) return Status::Error(where + ": not a JSON array of names: " + text);
    names->push_back(e.get<std::string>());
  }
  return Status::Ok();
}

Status ReadRecording(const Statement& q, const std::string& db_path, RecordingInfo* r) {
  r->id = q.Int(0);
  const std::string where = db_path + ": recording " + std::to_string(r->id);
  r->subject_id = q.Int(1);
  r->movement = q.Text(2);
  if (!ParseRecordingState(q.Text(3), &r->state)) {
    return Status::Error(where + ": unknown state '" + q.Text(3) + "'");
  }
  r->rate_hz = q.Double(4);
  MOCAP_RETURN_IF_ERROR(ParseNameArray(q.Text(5), where + ": marker_names", &r->marker_names));
  MOCAP_RETURN_IF_ERROR(
      ParseNameArray(q.Text(6), where + ": coordinate_names", &r->coordinate_names));
  r->model_version = static_cast<int>(q.Int(7));
  r->started_at = q.Text(8);
  r->stopped_at = q.Text(9);
  r->frame_count = q.Int(10);
  r->chunk_count = q.Int(11);
  r->coverage_json = q.Text(12);
  r->note = q.Text(13);
  r->created_at = q.Text(14);
  r->produced_by = q.Text(15);
  return Status::Ok();
}

// Runs a SELECT expected to return one row, read by `read`; `missing` is the error without one.
template <typename ReadRow>
Status SelectOne(Statement& q, const std::string& missing, ReadRow read) {
  bool row = false;
  MOCAP_RETURN_IF_ERROR(q.Step(&row));
  if (!row) return Status::Error(missing);
  return read(q);
}

// Runs a SELECT, calling `read` on every row.
template <typename ReadRow>
Status SelectAll(Statement& q, ReadRow read) {
  for (bool row = true;;) {
    MOCAP_RETURN_IF_ERROR(q.Step(&row));
    if (!row) return Status::Ok();
    MOCAP_RETURN_IF_ERROR(read(q));
  }
}

// Runs a SELECT and reads every row into a new element of *out (replaced only on success) with
// read_row(statement, Record*).
template <typename Record, typename ReadRow>
Status SelectList(Statement& q, ReadRow read_row, std::vector<Record>* out) {
  std::vector<Record> list;
  MOCAP_RETURN_IF_ERROR(
      SelectAll(q, [&](const Statement& s) { return read_row(s, &list.emplace_back()); }));
  *out = std::move(list);
  return Status::Ok();
}

// "SELECT <columns ... FROM table> <rest>".
std::string Select(const char* columns, const char* rest) {
  return std::string("SELECT ") + columns + " " + rest;
}

Status CheckJson(const std::string& text, const std::string& what) {
  if (!nlohmann::json::accept(text)) return Status::Error(what + " is not valid JSON");
  return Status::Ok();
}

Status CheckModelJson(const std::string& json, const std::string& what) {
  Model model;
  return In(what, ParseModelJson(json, what, &model));
}

Status CheckNames(const std::vector<std::string>& names, const std::string& what) {
  std::set<std::string> seen;
  for (const auto& n : names) {
    if (n.empty()) return Status::Error(what + ": an empty name");
    if (!seen.insert(n).second) return Status::Error(what + ": '" + n + "' appears twice");
  }
  return Status::Ok();
}

// ---------------------------------------------------------------------------------------------
// The frame blob (layout in store.h).

constexpr char kFrameMagic[4] = {'M', 'C', 'F', 'R'};
constexpr std::uint16_t kFrameLayoutVersion = 1;
constexpr std::size_t kFrameHeaderBytes = 24;

class BlobWriter {
 public:
  explicit BlobWriter(std::string* out) : out_(out) {}
  void U8(std::uint8_t v) { out_->push_back(static_cast<char>(v)); }
  void Uint(std::uint64_t v, int bytes) {
    for (int i = 0; i < bytes; ++i) U8(static_cast<std::uint8_t>(v >> (8 * i)));
  }
  void F64(double v) { Uint(std::bit_cast<std::uint64_t>(v), 8); }

 private:
  std::string* out_;
};

// Bounds-checked little-endian reads; each returns false past the end.
class BlobReader {
 public:
  explicit BlobReader(const std::string& in) : in_(in) {}
  std::size_t remaining() const { return in_.size() - pos_; }
  std::size_t position() const { return pos_; }
  bool Uint(int bytes, std::uint64_t* v) {
    if (remaining() < static_cast<std::size_t>(bytes)) return false;
    *v = 0;
    for (int i = 0; i < bytes; ++i) {
      *v |= static_cast<std::uint64_t>(static_cast<unsigned char>(in_[pos_ + i])) << (8 * i);
    }
    pos_ += bytes;
    return true;
  }
  bool F64(double* v) {
    std::uint64_t bits = 0;
    if (!Uint(8, &bits)) return false;
    *v = std::bit_cast<double>(bits);
    return true;
  }

 private:
  const std::string& in_;
  std::size_t pos_ = 0;
};

// The bytes of one frame apart from its points.
std::size_t FixedFrameBytes(std::size_t num_markers, std::size_t num_coordinates) {
  return 8 + 8 + 1 + 4 + num_markers * 25 + num_coordinates * 8;
}

}  // namespace

// =============================================================================================

const char* ToString(RecordingState state) {
  switch (state) {
    case RecordingState::kRecording:
      return "recording";
    case RecordingState::kComplete:
      return "complete";
    case RecordingState::kInterrupted:
      return "interrupted";
    case RecordingState::kFailed:
      return "failed";
  }
  return "unknown";
}

bool ParseRecordingState(const std::string& text, RecordingState* state) {
  for (RecordingState s : {RecordingState::kRecording, RecordingState::kComplete,
                           RecordingState::kInterrupted, RecordingState::kFailed}) {
    if (text == ToString(s)) {
      *state = s;
      return true;
    }
  }
  return false;
}

std::string EncodeFrames(const std::vector<RecordedFrame>& frames, int num_markers,
                         int num_coordinates) {
  std::string out;
  std::size_t total = kFrameHeaderBytes;
  for (const auto& f : frames)
    total += FixedFrameBytes(num_markers, num_coordinates) + 24 * f.points.size();
  out.reserve(total);
  BlobWriter w(&out);
  out.append(kFrameMagic, 4);
  w.Uint(kFrameLayoutVersion, 2);
  w.Uint(0, 2);
  w.Uint(frames.size(), 4);
  w.Uint(num_markers, 4);
  w.Uint(num_coordinates, 4);
  w.Uint(0, 4);
  for (const auto& f : frames) {
    w.Uint(f.frame, 8);
    w.F64(f.time_s);
    w.U8(static_cast<std::uint8_t>(f.tracker_state));
    w.Uint(f.points.size(), 4);
    for (const auto& p : f.points) {
      for (int k = 0; k < 3; ++k) w.F64(p[k]);
    }
    for (int m = 0; m < num_markers; ++m) {
      for (int k = 0; k < 3; ++k) w.F64(f.markers(k, m));
    }
    for (int m = 0; m < num_markers; ++m) w.U8(f.marker_flags[m]);
    for (int c = 0; c < num_coordinates; ++c) w.F64(f.coordinates[c]);
  }
  return out;
}

Status DecodeFrames(const std::string& blob, int num_markers, int num_coordinates,
                    const std::string& where, std::vector<RecordedFrame>* frames) {
  auto corrupt = [&](const std::string& what, std::size_t at) {
    return Status::Error(where + ": corrupt frame data (" + std::to_string(blob.size()) +
                         " bytes): " + what + " at byte " + std::to_string(at));
  };
  if (blob.size() < kFrameHeaderBytes) return corrupt("shorter than the 24-byte header", 0);
  if (blob.compare(0, 4, kFrameMagic, 4) != 0) return corrupt("no 'MCFR' magic", 0);
  BlobReader r(blob);
  std::uint64_t magic = 0, version = 0, reserved = 0, n = 0, m = 0, c = 0, reserved2 = 0;
  r.Uint(4, &magic);
  r.Uint(2, &version);
  r.Uint(2, &reserved);
  r.Uint(4, &n);
  r.Uint(4, &m);
  r.Uint(4, &c);
  r.Uint(4, &reserved2);
  if (version != kFrameLayoutVersion) {
    return corrupt("layout version " + std::to_string(version) + " (this mocapd reads " +
                       std::to_string(kFrameLayoutVersion) + ")",
                   4);
  }
  if (m != static_cast<std::uint64_t>(num_markers) ||
      c != static_cast<std::uint64_t>(num_coordinates)) {
    return corrupt("the header says " + std::to_string(m) + " markers and " + std::to_string(c) +
                       " coordinates, the recording " + std::to_string(num_markers) + " and " +
                       std::to_string(num_coordinates),
                   12);
  }
  const std::size_t fixed = FixedFrameBytes(m, c);
  if (n > r.remaining() / fixed) {
    return corrupt("the header's " + std::to_string(n) + " frames do not fit in the blob", 8);
  }
  std::vector<RecordedFrame> decoded(n);
  for (auto& f : decoded) {
    const std::size_t frame_start = r.position();
    if (r.remaining() < fixed) return corrupt("frame cut short", frame_start);
    std::uint64_t state = 0, num_points = 0;
    r.Uint(8, &f.frame);
    r.F64(&f.time_s);
    r.Uint(1, &state);
    f.tracker_state = static_cast<std::int8_t>(static_cast<std::uint8_t>(state));
    if (f.tracker_state < 0 || f.tracker_state > 2) {
      return corrupt("tracker state " + std::to_string(f.tracker_state), frame_start + 16);
    }
    r.Uint(4, &num_points);
    if (num_points > (r.remaining() - (fixed - 21)) / 24) {
      return corrupt(std::to_string(num_points) + " points do not fit in the blob",
                     frame_start + 17);
    }
    f.points.resize(num_points);
    for (auto& p : f.points) {
      for (int k = 0; k < 3; ++k) r.F64(&p[k]);
    }
    f.markers.resize(3, static_cast<Eigen::Index>(m));
    for (std::uint64_t j = 0; j < m; ++j) {
      for (int k = 0; k < 3; ++k) r.F64(&f.markers(k, j));
    }
    f.marker_flags.resize(m);
    for (auto& flag : f.marker_flags) {
      std::uint64_t v = 0;
      r.Uint(1, &v);
      flag = static_cast<std::uint8_t>(v);
    }
    f.coordinates.resize(static_cast<Eigen::Index>(c));
    for (std::uint64_t j = 0; j < c; ++j) r.F64(&f.coordinates[j]);
  }
  if (r.remaining() != 0) {
    return corrupt(std::to_string(r.remaining()) + " bytes after the last frame", r.position());
  }
  frames->insert(frames->end(), std::make_move_iterator(decoded.begin()),
                 std::make_move_iterator(decoded.end()));
  return Status::Ok();
}

bool StoreOptions::IsValid(std::string* error) const {
  if (busy_timeout_ms < 0) {
    if (error) *error = "busy_timeout_ms must be >= 0, not " + std::to_string(busy_timeout_ms);
    return false;
  }
  if (wal_autocheckpoint_pages < 0) {
    if (error) {
      *error = "wal_autocheckpoint_pages must be >= 0, not " +
               std::to_string(wal_autocheckpoint_pages);
    }
    return false;
  }
  return true;
}

void Store::DbCloser::operator()(sqlite3* db) const { sqlite3_close_v2(db); }

Store::Store(std::string path, sqlite3* db) : path_(std::move(path)), db_(db) {}
Store::~Store() = default;

Status Store::Exec(const std::string& sql, const std::string& what) {
  return ExecSql(db_.get(), path_, sql, what);
}

Status Store::Open(const std::string& state_dir, std::unique_ptr<Store>* out,
                   const StoreOptions& options) {
  if (std::string error; !options.IsValid(&error)) return Status::Error("StoreOptions: " + error);
  std::error_code ec;
  std::filesystem::create_directories(state_dir, ec);
  if (ec) {
    return Status::Error("cannot create the state directory " + state_dir + ": " + ec.message());
  }
  const std::string path = (std::filesystem::path(state_dir) / kFileName).string();
  sqlite3* raw = nullptr;
  const int rc =
      sqlite3_open_v2(path.c_str(), &raw,
                      SQLITE_OPEN_READWRITE | SQLITE_OPEN_CREATE | SQLITE_OPEN_NOMUTEX, nullptr);
  std::unique_ptr<Store> store(new Store(path, raw));  // owns `raw` even when the open failed
  if (rc != SQLITE_OK) {
    return Status::Error(
        path + ": cannot open the database: " + (raw ? sqlite3_errmsg(raw) : sqlite3_errstr(rc)));
  }
  sqlite3* db = store->db_.get();
  sqlite3_extended_result_codes(db, 1);
  sqlite3_busy_timeout(db, options.busy_timeout_ms);

  {
    // WAL: readers and one writer side by side (a Store per thread), and a commit appends to the
    // log instead of rewriting pages. The mode is persistent in the file; SQLite answers the mode
    // it ended in, which is not "wal" where WAL cannot work (e.g. no shared memory).
    Statement q(db, path, "PRAGMA journal_mode=WAL");
    bool row = false;
    MOCAP_RETURN_IF_ERROR(q.Step(&row));
    if (!row || q.Text(0) != "wal") {
      return Status::Error(path + ": could not switch the database to WAL mode (journal mode is '" +
                           (row ? q.Text(0) : std::string()) + "')");
    }
  }
  // NORMAL: a commit reaches the OS, so a crash of the process loses nothing committed; the
  // recorder makes each commit durable against a power cut by syncing the WAL from its own
  // thread, so the writer never waits for the disk (store.h, "Crashes and power cuts").
  const char* synchronous = options.sync_every_commit ? "PRAGMA synchronous=FULL"
                                                      : "PRAGMA synchronous=NORMAL";
  MOCAP_RETURN_IF_ERROR(store->Exec(synchronous, std::string("setting ") + (synchronous + 7)));
  MOCAP_RETURN_IF_ERROR(store->Exec("PRAGMA foreign_keys=ON", "enabling foreign keys"));
  if (sqlite3_wal_autocheckpoint(db, options.wal_autocheckpoint_pages) != SQLITE_OK) {
    return SqlError(db, path, "setting wal_autocheckpoint");
  }
  MOCAP_RETURN_IF_ERROR(store->Migrate());
  if (options.mark_interrupted_recordings) MOCAP_RETURN_IF_ERROR(store->MarkInterrupted());
  *out = std::move(store);
  return Status::Ok();
}

Status Store::Migrate() {
  int version = 0;
  MOCAP_RETURN_IF_ERROR(ReadSchemaVersion(db_.get(), path_, &version));
  if (version > kSchemaVersion) {
    return Status::Error(path_ + ": the database has schema version " + std::to_string(version) +
                         ", newer than this mocapd's " + std::to_string(kSchemaVersion) +
                         " (written by a newer mocapd)");
  }
  while (version < kSchemaVersion) {
    Transaction t(db_.get(), path_);
    MOCAP_RETURN_IF_ERROR(t.Begin(Transaction::Kind::kWrite));
    // Another Store may have migrated while this one waited for the write lock.
    MOCAP_RETURN_IF_ERROR(ReadSchemaVersion(db_.get(), path_, &version));
    if (version >= kSchemaVersion) break;
    const std::string step = "migrating the schema from version " + std::to_string(version) +
                             " to " + std::to_string(version + 1);
    MOCAP_RETURN_IF_ERROR(Exec(kMigrations[version], step));
    MOCAP_RETURN_IF_ERROR(
        Exec("PRAGMA user_version=" + std::to_string(version + 1), step + " (user_version)"));
    MOCAP_RETURN_IF_ERROR(t.Commit());
    ++version;
  }
  return Status::Ok();
}

Status Store::CheckSubjectExists(std::int64_t subject_id) {
  Statement q(db_.get(), path_, "SELECT 1 FROM subjects WHERE id = ?");
  q.Bind(subject_id);
  return SelectOne(q, path_ + ": no subject with id " + std::to_string(subject_id),
                   [](const Statement&) { return Status::Ok(); });
}

// --- subjects ---------------------------------------------------------------------------------

Status Store::CreateSubject(const std::string& name, double height_m,
                            const std::string& model_source, const std::string& osim_text,
                            const std::string& initial_model_json, const std::string& produced_by,
                            SubjectRecord* out) {
  const std::string what = path_ + ": creating subject '" + name + "'";
  if (name.empty()) return Status::Error(path_ + ": creating a subject: the name is empty");
  if (!(height_m > 0 && height_m <= 3)) {
    return Status::Error(what + ": height " + std::to_string(height_m) + " m is not in (0, 3] m");
  }
  if (model_source.empty()) return Status::Error(what + ": the model source is empty");
  MOCAP_RETURN_IF_ERROR(In(what, CheckModelJson(initial_model_json, "the initial model")));

  Transaction t(db_.get(), path_);
  MOCAP_RETURN_IF_ERROR(t.Begin(Transaction::Kind::kWrite));
  {
    Statement q(db_.get(), path_, "SELECT id FROM subjects WHERE name = ?");
    q.Bind(name);
    bool row = false;
    MOCAP_RETURN_IF_ERROR(q.Step(&row));
    if (row) {
      return Status::Error(what + ": the name '" + name + "' is already taken (subject id " +
                           std::to_string(q.Int(0)) + ")");
    }
  }
  Statement insert(db_.get(), path_,
                   "INSERT INTO subjects (name, height_m, model_source, osim_text, produced_by)"
                   " VALUES (?, ?, ?, ?, ?)");
  insert.Bind(name).Bind(height_m).Bind(model_source).Bind(osim_text).Bind(produced_by);
  MOCAP_RETURN_IF_ERROR(insert.Run());
  const std::int64_t id = sqlite3_last_insert_rowid(db_.get());
  Statement model(db_.get(), path_,
                  "INSERT INTO models (subject_id, version, model_json, produced_by)"
                  " VALUES (?, 1, ?, ?)");
  model.Bind(id).Bind(initial_model_json).Bind(produced_by);
  MOCAP_RETURN_IF_ERROR(model.Run());
  MOCAP_RETURN_IF_ERROR(t.Commit());
  return GetSubject(id, out);
}

Status Store::ListSubjects(std::vector<SubjectRecord>* out) {
  Statement q(db_.get(), path_, Select(kSubjectColumns, "ORDER BY id"));
  return SelectList(q, ReadSubject, out);
}

Status Store::FindSubject(const std::string& name, SubjectRecord* out) {
  Statement q(db_.get(), path_, Select(kSubjectColumns, "WHERE name = ?"));
  q.Bind(name);
  return SelectOne(q, path_ + ": no subject named '" + name + "'",
                   [&](const Statement& s) { return ReadSubject(s, out); });
}

Status Store::GetSubject(std::int64_t id, SubjectRecord* out) {
  Statement q(db_.get(), path_, Select(kSubjectColumns, "WHERE id = ?"));
  q.Bind(id);
  return SelectOne(q, path_ + ": no subject with id " + std::to_string(id),
                   [&](const Statement& s) { return ReadSubject(s, out); });
}

// --- models -----------------------------------------------------------------------------------

Status Store::AddModel(std::int64_t subject_id, const std::string& model_json,
                       const std::string& produced_by, std::optional<std::int64_t> fit_report_id,
                       ModelRecord* out) {
  const std::string what = path_ + ": adding a model to subject " + std::to_string(subject_id);
  MOCAP_RETURN_IF_ERROR(In(what, CheckModelJson(model_json, "the model")));
  Transaction t(db_.get(), path_);
  MOCAP_RETURN_IF_ERROR(t.Begin(Transaction::Kind::kWrite));
  MOCAP_RETURN_IF_ERROR(CheckSubjectExists(subject_id));
  if (fit_report_id) {
    Statement q(db_.get(), path_, "SELECT subject_id FROM fit_reports WHERE id = ?");
    q.Bind(*fit_report_id);
    MOCAP_RETURN_IF_ERROR(
        SelectOne(q, what + ": no fit report with id " + std::to_string(*fit_report_id),
                  [&](const Statement& s) {
                    if (s.Int(0) == subject_id) return Status::Ok();
                    return Status::Error(what + ": fit report " + std::to_string(*fit_report_id) +
                                         " belongs to subject " + std::to_string(s.Int(0)));
                  }));
  }
  Statement insert(
      db_.get(), path_,
      "INSERT INTO models (subject_id, version, model_json, fit_report_id, produced_by)"
      " VALUES (?1, (SELECT COALESCE(MAX(version), 0) + 1 FROM models"
      " WHERE subject_id = ?1), ?2, ?3, ?4)");
  insert.Bind(subject_id).Bind(model_json).Bind(fit_report_id).Bind(produced_by);
  MOCAP_RETURN_IF_ERROR(insert.Run());
  const std::int64_t id = sqlite3_last_insert_rowid(db_.get());
  MOCAP_RETURN_IF_ERROR(t.Commit());
  Statement q(db_.get(), path_, Select(kModelColumns, "WHERE id = ?"));
  q.Bind(id);
  return SelectOne(q, what + ": the new model " + std::to_string(id) + " is gone",
                   [&](const Statement& s) { return ReadModel(s, out); });
}

Status Store::ListModels(std::int64_t subject_id, std::vector<ModelRecord>* out) {
  MOCAP_RETURN_IF_ERROR(CheckSubjectExists(subject_id));
  Statement q(db_.get(), path_, Select(kModelColumns, "WHERE subject_id = ? ORDER BY version"));
  q.Bind(subject_id);
  return SelectList(q, ReadModel, out);
}

Status Store::GetModel(std::int64_t subject_id, int version, ModelRecord* out) {
  MOCAP_RETURN_IF_ERROR(CheckSubjectExists(subject_id));
  Statement q(
      db_.get(), path_,
      Select(kModelColumns,
             "WHERE subject_id = ?1 AND (version = ?2 OR ?2 = 0) ORDER BY version DESC LIMIT 1"));
  q.Bind(subject_id).Bind(version);
  const std::string missing =
      version == 0 ? path_ + ": subject " + std::to_string(subject_id) + " has no model"
                   : path_ + ": subject " + std::to_string(subject_id) + " has no model version " +
                         std::to_string(version);
  return SelectOne(q, missing, [&](const Statement& s) { return ReadModel(s, out); });
}

// --- fit reports ------------------------------------------------------------------------------

Status Store::AddFitReport(std::int64_t subject_id, const std::string& report_json,
                           const std::string& produced_by, std::int64_t* id) {
  const std::string what = path_ + ": adding a fit report to subject " + std::to_string(subject_id);
  MOCAP_RETURN_IF_ERROR(In(what, CheckJson(report_json, "the report")));
  MOCAP_RETURN_IF_ERROR(CheckSubjectExists(subject_id));
  Statement insert(
      db_.get(), path_,
      "INSERT INTO fit_reports (subject_id, report_json, produced_by) VALUES (?, ?, ?)");
  insert.Bind(subject_id).Bind(report_json).Bind(produced_by);
  MOCAP_RETURN_IF_ERROR(In(what, insert.Run()));
  *id = sqlite3_last_insert_rowid(db_.get());
  return Status::Ok();
}

Status Store::GetFitReport(std::int64_t id, FitReportRecord* out) {
  Statement q(db_.get(), path_,
              "SELECT id, subject_id, report_json, created_at, produced_by FROM fit_reports"
              " WHERE id = ?");
  q.Bind(id);
  return SelectOne(q, path_ + ": no fit report with id " + std::to_string(id),
                   [&](const Statement& s) {
                     out->id = s.Int(0);
                     out->subject_id = s.Int(1);
                     out->report_json = s.Text(2);
                     out->created_at = s.Text(3);
                     out->produced_by = s.Text(4);
                     return Status::Ok();
                   });
}

// --- the daemon's live state ----------------------------------------------------------------

Status Store::SetState(const std::string& key, const std::string& value) {
  Statement upsert(db_.get(), path_,
                   "INSERT INTO daemon_state (key, value) VALUES (?, ?) ON CONFLICT(key) DO UPDATE"
                   " SET value = excluded.value, updated_at = " MOCAP_NOW);
  upsert.Bind(key).Bind(value);
  return In(path_ + ": setting the daemon's " + key, upsert.Run());
}

Status Store::GetState(const std::string& key, std::string* value) {
  Statement q(db_.get(), path_, "SELECT value FROM daemon_state WHERE key = ?");
  q.Bind(key);
  return SelectOne(q, path_ + ": no daemon state '" + key + "'", [&](const Statement& s) {
    *value = s.Text(0);
    return Status::Ok();
  });
}

// --- calibrations -----------------------------------------------------------------------------

Status Store::AddCalibration(const std::string& calibration_json, double reprojection_rms_px,
                             double wand_length_error_mm, const std::string& produced_by,
                             std::int64_t* version) {
  const std::string what = path_ + ": adding a rig calibration";
  MOCAP_RETURN_IF_ERROR(In(what, CheckJson(calibration_json, "the calibration")));
  if (!std::isfinite(reprojection_rms_px) || !std::isfinite(wand_length_error_mm)) {
    return Status::Error(what + ": reprojection RMS " + std::to_string(reprojection_rms_px) +
                         " px / wand length error " + std::to_string(wand_length_error_mm) +
                         " mm must be finite");
  }
  Statement insert(db_.get(), path_,
                   "INSERT INTO calibrations (calibration_json, reprojection_rms_px,"
                   " wand_length_error_mm, produced_by) VALUES (?, ?, ?, ?)");
  insert.Bind(calibration_json)
      .Bind(reprojection_rms_px)
      .Bind(wand_length_error_mm)
      .Bind(produced_by);
  MOCAP_RETURN_IF_ERROR(In(what, insert.Run()));
  *version = sqlite3_last_insert_rowid(db_.get());
  return Status::Ok();
}

Status Store::GetCalibration(std::int64_t version, CalibrationRecord* out) {
  Statement q(
      db_.get(), path_,
      Select(kCalibrationColumns, "WHERE version = ?1 OR ?1 = 0 ORDER BY version DESC LIMIT 1"));
  q.Bind(version);
  const std::string missing =
      version == 0 ? path_ + ": no rig calibration stored yet"
                   : path_ + ": no rig calibration version " + std::to_string(version);
  return SelectOne(q, missing, [&](const Statement& s) { return ReadCalibration(s, out); });
}

Status Store::ListCalibrations(std::vector<CalibrationRecord>* out) {
  Statement q(db_.get(), path_, Select(kCalibrationColumns, "ORDER BY version"));
  return SelectList(q, ReadCalibration, out);
}

// --- recordings -------------------------------------------------------------------------------

Status Store::BeginRecording(std::int64_t subject_id, const std::string& movement, double rate_hz,
                             const std::vector<std::string>& marker_names,
                             const std::vector<std::string>& coordinate_names, int model_version,
                             const std::string& produced_by, std::int64_t* id) {
  const std::string what = path_ + ": starting a recording of '" + movement + "' for subject " +
                           std::to_string(subject_id);
  if (movement.empty()) return Status::Error(what + ": the movement name is empty");
  if (!(rate_hz > 0 && std::isfinite(rate_hz))) {
    return Status::Error(what + ": rate " + std::to_string(rate_hz) + " Hz is not > 0");
  }
  if (model_version < 0) {
    return Status::Error(what + ": model version " + std::to_string(model_version) + " < 0");
  }
  MOCAP_RETURN_IF_ERROR(CheckNames(marker_names, what + ": marker names"));
  MOCAP_RETURN_IF_ERROR(CheckNames(coordinate_names, what + ": coordinate names"));
  Transaction t(db_.get(), path_);
  MOCAP_RETURN_IF_ERROR(t.Begin(Transaction::Kind::kWrite));
  MOCAP_RETURN_IF_ERROR(CheckSubjectExists(subject_id));
  if (model_version > 0) {
    ModelRecord model;
    MOCAP_RETURN_IF_ERROR(In(what, GetModel(subject_id, model_version, &model)));
  }
  Statement insert(db_.get(), path_,
                   "INSERT INTO recordings (subject_id, movement, state, rate_hz, marker_names,"
                   " coordinate_names, model_version, produced_by)"
                   " VALUES (?, ?, 'recording', ?, ?, ?, ?, ?)");
  insert.Bind(subject_id)
      .Bind(movement)
      .Bind(rate_hz)
      .Bind(nlohmann::json(marker_names).dump())
      .Bind(nlohmann::json(coordinate_names).dump())
      .Bind(model_version)
      .Bind(produced_by);
  MOCAP_RETURN_IF_ERROR(insert.Run());
  const std::int64_t new_id = sqlite3_last_insert_rowid(db_.get());
  MOCAP_RETURN_IF_ERROR(t.Commit());
  *id = new_id;
  return Status::Ok();
}

Status Store::AppendFrames(std::int64_t recording_id, const std::vector<RecordedFrame>& frames) {
  if (frames.empty()) return Status::Ok();
  const std::string what = path_ + ": recording " + std::to_string(recording_id);
  RecordingInfo info;
  MOCAP_RETURN_IF_ERROR(GetRecording(recording_id, &info));
  const int num_markers = static_cast<int>(info.marker_names.size());
  const int num_coordinates = static_cast<int>(info.coordinate_names.size());
  constexpr std::uint64_t kMaxFrame = std::numeric_limits<std::int64_t>::max();
  for (std::size_t i = 0; i < frames.size(); ++i) {
    const RecordedFrame& f = frames[i];
    const std::string at = what + ": appending frame " + std::to_string(f.frame) + " (entry " +
                           std::to_string(i) + ")";
    if (f.markers.cols() != num_markers ||
        f.marker_flags.size() != static_cast<std::size_t>(num_markers)) {
      return Status::Error(at + ": " + std::to_string(f.markers.cols()) + " marker columns and " +
                           std::to_string(f.marker_flags.size()) + " flags; the recording has " +
                           std::to_string(num_markers) + " markers");
    }
    if (f.coordinates.size() != num_coordinates) {
      return Status::Error(at + ": " + std::to_string(f.coordinates.size()) +
                           " coordinates; the recording has " + std::to_string(num_coordinates));
    }
    if (f.tracker_state < 0 || f.tracker_state > 2) {
      return Status::Error(at + ": tracker state " + std::to_string(f.tracker_state) +
                           " is not 0, 1 or 2");
    }
    if (f.frame > kMaxFrame) return Status::Error(at + ": frame number is >= 2^63");
    if (i > 0 && f.frame <= frames[i - 1].frame) {
      return Status::Error(at + ": frame numbers must increase (previous entry is frame " +
                           std::to_string(frames[i - 1].frame) + ")");
    }
  }
  const std::string blob = EncodeFrames(frames, num_markers, num_coordinates);

  Transaction t(db_.get(), path_);
  MOCAP_RETURN_IF_ERROR(t.Begin(Transaction::Kind::kWrite));
  std::int64_t next_chunk = 0;
  {
    Statement q(db_.get(), path_,
                "SELECT r.state, (SELECT COALESCE(MAX(chunk_index) + 1, 0) FROM recording_chunks"
                " WHERE recording_id = r.id), (SELECT MAX(last_frame) FROM recording_chunks"
                " WHERE recording_id = r.id) FROM recordings r WHERE r.id = ?");
    q.Bind(recording_id);
    MOCAP_RETURN_IF_ERROR(SelectOne(
        q, path_ + ": no recording with id " + std::to_string(recording_id),
        [&](const Statement& s) {
          if (s.Text(0) != ToString(RecordingState::kRecording)) {
            return Status::Error(what + ": cannot append frames: the recording is " + s.Text(0));
          }
          next_chunk = s.Int(1);
          if (!s.IsNull(2) && static_cast<std::uint64_t>(s.Int(2)) >= frames.front().frame) {
            return Status::Error(what + ": appending frame " +
                                 std::to_string(frames.front().frame) +
                                 ": not after the last stored frame " + std::to_string(s.Int(2)));
          }
          return Status::Ok();
        }));
  }
  Statement insert(db_.get(), path_,
                   "INSERT INTO recording_chunks (recording_id, chunk_index, first_frame,"
                   " last_frame, frame_count, frames, produced_by) VALUES (?, ?, ?, ?, ?, ?, ?)");
  insert.Bind(recording_id)
      .Bind(next_chunk)
      .Bind(static_cast<std::int64_t>(frames.front().frame))
      .Bind(static_cast<std::int64_t>(frames.back().frame))
      .Bind(static_cast<std::int64_t>(frames.size()))
      .BindBlob(blob)
      .Bind(info.produced_by);
  MOCAP_RETURN_IF_ERROR(In(what + ": storing chunk " + std::to_string(next_chunk), insert.Run()));
  Statement update(db_.get(), path_,
                   "UPDATE recordings SET frame_count = frame_count + ? WHERE id = ?");
  update.Bind(static_cast<std::int64_t>(frames.size())).Bind(recording_id);
  MOCAP_RETURN_IF_ERROR(update.Run());
  return t.Commit();
}

Status Store::FinishRecording(std::int64_t recording_id, RecordingState state,
                              const std::string& coverage_json, const std::string& note) {
  const std::string what = path_ + ": finishing recording " + std::to_string(recording_id);
  if (state == RecordingState::kRecording) {
    return Status::Error(what + ": the final state cannot be 'recording'");
  }
  if (!coverage_json.empty())
    MOCAP_RETURN_IF_ERROR(In(what, CheckJson(coverage_json, "the coverage")));
  Transaction t(db_.get(), path_);
  MOCAP_RETURN_IF_ERROR(t.Begin(Transaction::Kind::kWrite));
  RecordingInfo info;
  MOCAP_RETURN_IF_ERROR(GetRecording(recording_id, &info));
  if (info.state != RecordingState::kRecording) {
    return Status::Error(what + " as " + ToString(state) + ": it is already " +
                         ToString(info.state));
  }
  Statement update(db_.get(), path_,
                   "UPDATE recordings SET state = ?, coverage_json = ?, note = ?,"
                   " stopped_at = " MOCAP_NOW " WHERE id = ?");
  update.Bind(std::string(ToString(state))).Bind(coverage_json).Bind(note).Bind(recording_id);
  MOCAP_RETURN_IF_ERROR(update.Run());
  return t.Commit();
}

Status Store::ListRecordings(std::int64_t subject_id, std::vector<RecordingInfo>* out) {
  if (subject_id != 0) MOCAP_RETURN_IF_ERROR(CheckSubjectExists(subject_id));
  Statement q(db_.get(), path_,
              Select(kRecordingColumns, "WHERE subject_id = ?1 OR ?1 = 0 ORDER BY id"));
  q.Bind(subject_id);
  return SelectList(
      q, [&](const Statement& s, RecordingInfo* r) { return ReadRecording(s, path_, r); }, out);
}

Status Store::GetRecording(std::int64_t recording_id, RecordingInfo* out) {
  Statement q(db_.get(), path_, Select(kRecordingColumns, "WHERE id = ?"));
  q.Bind(recording_id);
  return SelectOne(q, path_ + ": no recording with id " + std::to_string(recording_id),
                   [&](const Statement& s) { return ReadRecording(s, path_, out); });
}

Status Store::ReadFrames(std::int64_t recording_id, std::vector<RecordedFrame>* frames) {
  // One read transaction: the chunks and the frame count from the same snapshot while the
  // recorder may be appending through another Store.
  Transaction t(db_.get(), path_);
  MOCAP_RETURN_IF_ERROR(t.Begin(Transaction::Kind::kRead));
  RecordingInfo info;
  MOCAP_RETURN_IF_ERROR(GetRecording(recording_id, &info));
  const int num_markers = static_cast<int>(info.marker_names.size());
  const int num_coordinates = static_cast<int>(info.coordinate_names.size());
  Statement q(
      db_.get(), path_,
      "SELECT chunk_index, first_frame, last_frame, frame_count, frames FROM recording_chunks"
      " WHERE recording_id = ? ORDER BY chunk_index");
  q.Bind(recording_id);
  std::vector<RecordedFrame> read;
  MOCAP_RETURN_IF_ERROR(SelectAll(q, [&](const Statement& s) {
    const std::string where = path_ + ": recording " + std::to_string(recording_id) + " chunk " +
                              std::to_string(s.Int(0));
    const std::size_t before = read.size();
    MOCAP_RETURN_IF_ERROR(DecodeFrames(s.Blob(4), num_markers, num_coordinates, where, &read));
    const std::size_t n = read.size() - before;
    if (n == 0 || static_cast<std::int64_t>(n) != s.Int(3) ||
        read[before].frame != static_cast<std::uint64_t>(s.Int(1)) ||
        read.back().frame != static_cast<std::uint64_t>(s.Int(2))) {
      return Status::Error(where + ": corrupt chunk: its blob holds " + std::to_string(n) +
                           " frames, the row says " + std::to_string(s.Int(3)) + " frames " +
                           std::to_string(s.Int(1)) + ".." + std::to_string(s.Int(2)));
    }
    for (std::size_t i = std::max<std::size_t>(before, 1); i < read.size(); ++i) {
      if (read[i].frame <= read[i - 1].frame) {
        return Status::Error(where + ": corrupt chunk: frame " + std::to_string(read[i].frame) +
                             " follows frame " + std::to_string(read[i - 1].frame));
      }
    }
    return Status::Ok();
  }));
  if (static_cast<std::int64_t>(read.size()) != info.frame_count) {
    return Status::Error(path_ + ": recording " + std::to_string(recording_id) +
                         ": its chunks hold " + std::to_string(read.size()) +
                         " frames, the recording says " + std::to_string(info.frame_count));
  }
  MOCAP_RETURN_IF_ERROR(t.Commit());
  *frames = std::move(read);
  return Status::Ok();
}

Status Store::MarkInterrupted(int* count) {
  Statement update(db_.get(), path_,
                   "UPDATE recordings SET state = 'interrupted',"
                   " stopped_at = COALESCE((SELECT MAX(created_at) FROM recording_chunks c"
                   " WHERE c.recording_id = recordings.id), started_at),"
                   " note = CASE WHEN note = '' THEN 'still recording when the store was opened"
                   " again (the daemon stopped without finishing it)' ELSE note END"
                   " WHERE state = 'recording'");
  MOCAP_RETURN_IF_ERROR(In(path_ + ": marking interrupted recordings", update.Run()));
  if (count) *count = sqlite3_changes(db_.get());
  return Status::Ok();
}

Status Store::Checkpoint(int* wal_pages, int* checkpointed_pages) {
  int log = 0, done = 0;
  if (sqlite3_wal_checkpoint_v2(db_.get(), nullptr, SQLITE_CHECKPOINT_PASSIVE, &log, &done) !=
      SQLITE_OK) {
    return SqlError(db_.get(), path_, "checkpointing the WAL");
  }
  if (wal_pages) *wal_pages = log;
  if (checkpointed_pages) *checkpointed_pages = done;
  return Status::Ok();
}

Status Store::Usage(std::uint64_t* db_bytes) {
  std::uint64_t total = 0;
  for (const char* suffix : {"", "-wal"}) {
    std::error_code ec;
    const auto size = std::filesystem::file_size(path_ + suffix, ec);
    if (!ec) {
      total += size;
    } else if (*suffix == '\0') {
      return Status::Error(path_ + ": cannot read the database file's size: " + ec.message());
    }
  }
  *db_bytes = total;
  return Status::Ok();
}

}  // namespace mocap::daemon
#undef MOCAP_NOW
