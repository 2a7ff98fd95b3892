// The daemon's store: everything mocapd has done, in one SQLite database (`mocapd.sqlite` in the
// state directory). Subjects, rig calibrations, models, fit reports and recordings, each row with
// the UTC time it was written (`created_at`, ISO-8601 "2026-11-25T21:26:18.123Z") and what wrote
// it (`produced_by`, free text: "mocapd 0.1.0 fit", "import default", ...). Nothing is updated in
// place except a recording's progress (state, frame count, coverage, note): a new model or
// calibration is a new version, so every result can be traced to what produced it.
//
// Why SQLite, and how it is used:
// - WAL journal: readers never block the writer and the writer never blocks readers, so a Store
//   per thread (the event loop's, a fit worker's, an export worker's) can work side by side; a
//   write waits up to `busy_timeout_ms` for another writer instead of failing at once.
// - synchronous=NORMAL, and the recorder's own WAL syncs ("Crashes and power cuts" below): a
//   crash of the process or a power cut loses at most the last 100 ms of a recording on a disk
//   whose fsync keeps up (daemon/recorder.h).
// - Frames are stored in chunks (one BLOB per AppendFrames call, one transaction each) rather than
//   one row per frame: at 200 Hz a row per frame would be 200 transactions or index entries a
//   second; a chunk is one, and reading a recording back is a scan of a few hundred blobs.
// - The schema is versioned with `PRAGMA user_version`; Open migrates an older database step by
//   step and refuses a newer one (written by a newer mocapd) rather than guess at it.
//
// Checkpoints. SQLite moves the WAL's pages into the database file (a checkpoint, with an fsync)
// by default at the commit that takes the WAL past 1000 pages (~4 MB, every ~8 s of recording):
// that commit then takes tens of ms, once hundreds. The recorder's commits are on the live path, so
// the daemon opens the recorder's Store with `wal_autocheckpoint_pages = 0` and calls Checkpoint()
// every few seconds from another thread's Store (a passive checkpoint never blocks the writer).
// bench/store_append (BENCHMARKS.md; the default
// model's 43 markers and 38 coordinates, 48 points a frame, 60 s at 200 Hz, 20-frame chunks at
// the rig's pace), AppendFrames per chunk:
//   automatic checkpoints          p50 0.55 ms  p99 10-23 ms  max 22-449 ms (5 runs)
//   Checkpoint() every 5 s         p50 0.58 ms  p99 4.6 ms    max 8-9 ms (2 runs)
//   Checkpoint() every 1 s         p50 0.54 ms  p99 8.1 ms    max 12 ms
//   Checkpoint() every 100 ms      p50 1.9-2.4  p99 7-11 ms   max 11-14 ms (an fsync in each gap)
// 2.7 kB a frame (32 MB a minute); ReadFrames of the 12,000 frames 47-132 ms.
//
// Crashes and power cuts. In WAL mode a commit appends its pages and a commit record to the WAL
// file; SQLite recovers, after a crash or a power cut, every transaction whose commit record
// reached the disk intact, in order (the WAL's frames are checksummed in a chain, so a torn tail
// is ignored, never half-applied).
//   - synchronous=NORMAL writes the WAL at each commit but fsyncs it only at checkpoints: a
//     crash of the PROCESS loses nothing committed (the OS has the pages and writes them), a
//     power cut everything since the last fsync of the WAL.
//   - synchronous=FULL fsyncs the WAL inside every commit: durable against a power cut when
//     COMMIT returns, but the writer waits for the disk. bench/store_append on this project's
//     machine (ext4 on a virtual disk, loaded by other agents; BENCHMARKS.md "The store"),
//     50 ms chunks at 200 Hz: FULL commit p50 8 ms, p99 38 ms, max 55 ms (NORMAL p50 0.5 ms);
//     and single fsyncs of 400 ms under load.
// The daemon takes NORMAL and has the recorder fdatasync the WAL file from a thread of its own
// after each commit (daemon/recorder.h): the same durability as FULL once that sync returns,
// without a slow disk holding the writer -- so a crash never loses more than the 100 ms the
// recorder's commit deadline allows, and a power cut loses at most that on a disk whose fsync
// keeps up (the deadline keeps the slowest recent syncs in reserve). Syncing a file that SQLite
// writes is safe: an fsync only makes durable what SQLite already wrote, in any order the OS
// could have chosen itself. A disk that lies about fsync (a write cache without power-loss
// protection) can lose more: no setting of SQLite's helps there.
//
// A recording that was still "recording" when the daemon stopped (crash, power cut, kill) becomes
// "interrupted" at the next Open: its committed chunks stay readable and exportable.
//
// Frame blob layout (version 1), all integers and doubles LITTLE-ENDIAN whatever the host, doubles
// as their IEEE-754 bit patterns (so NaN payloads and -0 survive bit for bit):
//   header  (24 bytes)
//     [0..4)   magic "MCFR"
//     u16      layout version (1)
//     u16      reserved, 0
//     u32      frame count N
//     u32      marker count M   (= the recording's marker_names.size())
//     u32      coordinate count C (= the recording's coordinate_names.size())
//     u32      reserved, 0
//   then N frames, each:
//     u64      frame (the rig's frame-set sequence number)
//     f64      time_s
//     i8       tracker_state
//     u32      point count P
//     P x 3 f64   points (x y z)
//     M x 3 f64   markers (x y z; NaN where not labelled)
//     M x u8      marker flags
//     C x f64     coordinates
// A reader checks every count against the bytes left before it allocates, so a corrupt blob is an
// error naming its recording and chunk, never a crash or an unbounded allocation.
//
// Not thread-safe: one Store has one owner thread. Open another Store (on the same directory) for
// another thread.
#pragma once
#include <Eigen/Core>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "model/status.h"

struct sqlite3;

namespace mocap::daemon {

// One frame set as the recorder saw it.
struct RecordedFrame {
  std::uint64_t frame = 0;                 // the rig's frame-set sequence number
  double time_s = 0;                       // mid-exposure time of the set (seconds, daemon clock)
  std::vector<Eigen::Vector3d> points;     // unlabelled 3D points (metres)
  Eigen::Matrix3Xd markers;                // per model marker, NaN columns where not labelled
  std::vector<std::uint8_t> marker_flags;  // per marker: bit0 occluded, bit1 filled
  Eigen::VectorXd coordinates;             // the tracker's z (radians/metres)
  std::int8_t tracker_state = 0;           // 0 initialising, 1 tracking, 2 lost
};
constexpr std::uint8_t kMarkerOccluded = 1u << 0;
constexpr std::uint8_t kMarkerFilled = 1u << 1;

// The frame blob of the layout above (exposed for tests and tools; the Store uses them).
// EncodeFrames expects every frame to have `num_markers` marker columns and flags and
// `num_coordinates` coordinates (AppendFrames checks that first).
std::string EncodeFrames(const std::vector<RecordedFrame>& frames, int num_markers,
                         int num_coordinates);
// Appends the blob's frames to *frames. `where` names the blob in errors ("recording 3 chunk 2").
// On error *frames is unchanged.
Status DecodeFrames(const std::string& blob, int num_markers, int num_coordinates,
                    const std::string& where, std::vector<RecordedFrame>* frames);

struct SubjectRecord {
  std::int64_t id = 0;
  std::string name;
  double height_m = 0;
  std::string model_source;  // "default" or the path of the uploaded .osim / .json
  std::string osim_text;     // the original .osim document when the model came from one, else ""
  int latest_model_version = 0;
  std::string created_at, produced_by;
};

struct ModelRecord {
  std::int64_t id = 0;
  std::int64_t subject_id = 0;
  int version = 0;                            // 1, 2, ... per subject
  std::string model_json;                     // model/model_io.h ModelToJsonString
  std::optional<std::int64_t> fit_report_id;  // the fit that produced it, if any
  std::string created_at, produced_by;
};

struct FitReportRecord {
  std::int64_t id = 0;
  std::int64_t subject_id = 0;
  std::string report_json;
  std::string created_at, produced_by;
};

struct CalibrationRecord {
  std::int64_t version = 0;
  std::string calibration_json;  // reconstruction/calibration_file.h's format, as text
  double reprojection_rms_px = 0;
  double wand_length_error_mm = 0;
  std::string created_at, produced_by;
};

enum class RecordingState { kRecording, kComplete, kInterrupted, kFailed };
const char* ToString(RecordingState state);  // "recording", "complete", "interrupted", "failed"
// Parses the names above; false for anything else.
bool ParseRecordingState(const std::string& text, RecordingState* state);

struct RecordingInfo {
  std::int64_t id = 0;
  std::int64_t subject_id = 0;
  std::string movement;
  RecordingState state = RecordingState::kRecording;
  double rate_hz = 0;
  std::vector<std::string> marker_names;      // the columns of RecordedFrame::markers
  std::vector<std::string> coordinate_names;  // the entries of RecordedFrame::coordinates
  int model_version = 0;                      // the subject's model the tracker ran
  std::string started_at, stopped_at;         // stopped_at "" while recording
  std::int64_t frame_count = 0;
  std::int64_t chunk_count = 0;
  std::string coverage_json;  // set by FinishRecording; "" before
  std::string note;
  std::string created_at, produced_by;
};

struct StoreOptions {
  // How long a write waits for another connection's write transaction before failing.
  int busy_timeout_ms = 5000;
  // At Open, turn recordings left in "recording" into "interrupted". The daemon's first Store does
  // this once at start-up; a Store opened later by a worker thread of the SAME daemon must not
  // (it would mark the recording in progress as interrupted), so it passes false.
  bool mark_interrupted_recordings = true;
  // Checkpoint the WAL automatically at the commit that takes it past this many pages (SQLite's
  // default, 1000). 0: never on this connection's commits; then some Store must call Checkpoint()
  // regularly, or the WAL grows without bound (see "Checkpoints" above).
  int wal_autocheckpoint_pages = 1000;
  // true: synchronous=FULL, every commit fsyncs the WAL before it returns. false (the daemon's):
  // NORMAL, the recorder syncs the WAL from its own thread ("Crashes and power cuts" above).
  bool sync_every_commit = false;

  bool IsValid(std::string* error) const;
};

class Store {
 public:
  static constexpr const char* kFileName = "mocapd.sqlite";
  static constexpr int kSchemaVersion = 2;

  // Opens (creating it, and the state directory with its parents, if missing) the database
  // `state_dir`/mocapd.sqlite, migrates its schema and, if the options say so, marks interrupted
  // recordings. Errors name the path.
  static Status Open(const std::string& state_dir, std::unique_ptr<Store>* out,
                     const StoreOptions& options = StoreOptions());
  ~Store();
  Store(const Store&) = delete;
  Store& operator=(const Store&) = delete;

  const std::string& path() const { return path_; }

  // --- subjects ---
  // Creates the subject and its model version 1 (`initial_model_json`, validated by parsing it)
  // in one transaction. Errors: empty name, a name already taken (named), height not in
  // (0, 3] m, an empty model_source, a model that does not parse.
  Status CreateSubject(const std::string& name, double height_m, const std::string& model_source,
                       const std::string& osim_text, const std::string& initial_model_json,
                       const std::string& produced_by, SubjectRecord* out);
  Status ListSubjects(std::vector<SubjectRecord>* out);             // by id
  Status FindSubject(const std::string& name, SubjectRecord* out);  // error: no subject named
  Status GetSubject(std::int64_t id, SubjectRecord* out);

  // --- models ---
  // Adds the subject's next model version (validated by parsing it). fit_report_id, when given,
  // must be a fit report of the same subject.
  Status AddModel(std::int64_t subject_id, const std::string& model_json,
                  const std::string& produced_by, std::optional<std::int64_t> fit_report_id,
                  ModelRecord* out);
  Status ListModels(std::int64_t subject_id, std::vector<ModelRecord>* out);  // by version
  // version 0 = the subject's latest.
  Status GetModel(std::int64_t subject_id, int version, ModelRecord* out);

  // --- fit reports --- (report_json must be JSON)
  Status AddFitReport(std::int64_t subject_id, const std::string& report_json,
                      const std::string& produced_by, std::int64_t* id);
  Status GetFitReport(std::int64_t id, FitReportRecord* out);

  // --- the daemon's live state --- (schema 2) What the daemon had live, by key
  // ("subject", "live_model_version"), so that a restart resumes it. GetState: an error when the
  // key was never set.
  Status SetState(const std::string& key, const std::string& value);
  Status GetState(const std::string& key, std::string* value);
  // --- rig calibrations --- (calibration_json must be JSON; version = id, increasing)
  Status AddCalibration(const std::string& calibration_json, double reprojection_rms_px,
                        double wand_length_error_mm, const std::string& produced_by,
                        std::int64_t* version);
  // version 0 = the latest; an error when there is none.
  Status GetCalibration(std::int64_t version, CalibrationRecord* out);
  Status ListCalibrations(std::vector<CalibrationRecord>* out);  // by version

  // --- recordings ---
  // Starts a recording in state "recording". model_version must be one of the subject's models
  // (0 = none: the tracker had no model, e.g. a points-only recording); names must be unique and
  // non-empty; rate_hz > 0.
  Status BeginRecording(std::int64_t subject_id, const std::string& movement, double rate_hz,
                        const std::vector<std::string>& marker_names,
                        const std::vector<std::string>& coordinate_names, int model_version,
                        const std::string& produced_by, std::int64_t* id);
  // Stores `frames` as ONE chunk in ONE transaction (the recorder calls it with <= 100 ms of
  // frames). The recording must be "recording"; every frame must have as many marker columns and
  // flags as marker_names and as many coordinates as coordinate_names; frame numbers must
  // increase strictly, past the last frame already stored, and stay below 2^63. Empty: no-op.
  Status AppendFrames(std::int64_t recording_id, const std::vector<RecordedFrame>& frames);
  // Ends a recording that is "recording" with state complete, interrupted or failed.
  // coverage_json ("" = none) must be JSON.
  Status FinishRecording(std::int64_t recording_id, RecordingState state,
                         const std::string& coverage_json, const std::string& note);
  // subject_id 0 = every subject's; by id.
  Status ListRecordings(std::int64_t subject_id, std::vector<RecordingInfo>* out);
  Status GetRecording(std::int64_t recording_id, RecordingInfo* out);
  // Every stored frame of the recording, in order. A corrupt chunk is an error naming the
  // recording and chunk index; *frames is then unchanged.
  Status ReadFrames(std::int64_t recording_id, std::vector<RecordedFrame>* frames);
  // Turns every recording still "recording" into "interrupted" (stopped_at = its last chunk's time,
  // or its start). Open does this when the options say so. *count (optional): how many.
  Status MarkInterrupted(int* count = nullptr);

  // A passive checkpoint: moves what it can of the WAL into the database file without waiting
  // for (or blocking) readers and the writer; the writer then starts the WAL over at its next
  // commit once every page is in. *wal_pages / *checkpointed_pages (optional): the WAL's size and
  // how much of it is now in the database.
  Status Checkpoint(int* wal_pages = nullptr, int* checkpointed_pages = nullptr);

  // Bytes on disk: the database file plus its WAL.
  Status Usage(std::uint64_t* db_bytes);

 private:
  struct DbCloser {
    void operator()(sqlite3* db) const;
  };
  Store(std::string path, sqlite3* db);
  // Runs `sql` (no results) and names `what` in the error.
  Status Exec(const std::string& sql, const std::string& what);
  Status Migrate();
  Status CheckSubjectExists(std::int64_t subject_id);

  std::string path_;
  std::unique_ptr<sqlite3, DbCloser> db_;
};

}  // namespace mocap::daemon
