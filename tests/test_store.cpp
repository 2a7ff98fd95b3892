// Tests of daemon/store.h (SQLite store) and daemon/recording_export.h: every entity round trips,
// frames come back bit for bit across chunks and reopenings, a recording left open reads back
// "interrupted", bad input and unknown ids are errors naming what is wrong, corrupt frame blobs are
// errors (never crashes), and exports read back with formats/ equal what was stored.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <bit>
#include <cmath>
#include <filesystem>
#include <limits>
#include <numbers>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include "daemon/recorder.h"
#include "daemon/recording_export.h"
#include "daemon/store.h"
#include "formats/c3d.h"
#include "formats/mot.h"
#include "formats/trc.h"
#include "model/default_model.h"
#include "model/model_io.h"
#include "tests/file_test_util.h"
#include "tests/store_test_util.h"

namespace fs = std::filesystem;
using mocap::Status;
using mocap::daemon::CalibrationRecord;
using mocap::daemon::FitReportRecord;
using mocap::daemon::ModelRecord;
using mocap::daemon::RecordedFrame;
using mocap::daemon::RecordingInfo;
using mocap::daemon::RecordingState;
using mocap::daemon::Store;
using mocap::daemon::StoreOptions;
using mocap::daemon::SubjectRecord;
using ::testing::HasSubstr;
using ::testing::MatchesRegex;

namespace {
using mocap::testing::RawSql;

const double kNaN = std::numeric_limits<double>::quiet_NaN();

#define ASSERT_OK(expr)                                      \
  do {                                                       \
    const ::mocap::Status _st = (expr);                      \
    ASSERT_TRUE(_st.ok()) << #expr << ": " << _st.message(); \
  } while (0)

// The error's message contains every one of `parts`.
void ExpectError(const Status& s, std::initializer_list<std::string> parts) {
  ASSERT_FALSE(s.ok()) << "expected an error containing " << *parts.begin();
  for (const auto& p : parts) EXPECT_THAT(s.message(), HasSubstr(p));
}

// Runs one SQL statement on the database file directly (behind the Store's back) and returns the
// first column of its first row as text ("" when none).
// Each test gets an empty state directory (nested, so Open must create the parents); after each,
// SQLite's integrity check must pass on what the test left.
class StoreTest : public ::testing::Test {
 protected:
  void SetUp() override {
    const auto* info = ::testing::UnitTest::GetInstance()->current_test_info();
    root_ = fs::path(MOCAP_TEST_TMP) / "store" /
            (std::string(info->test_suite_name()) + "_" + info->name());
    fs::remove_all(root_);
    dir_ = (root_ / "var" / "lib" / "mocapd").string();
    ASSERT_OK(Store::Open(dir_, &store_));
    model_ = mocap::DefaultFullBodyModel(1.75);
    model_json_ = mocap::ModelToJsonString(model_);
    for (const auto& m : model_.markers()) marker_names_.push_back(m.name);
    for (const auto& c : model_.coordinates()) coordinate_names_.push_back(c.name);
  }
  void TearDown() override {
    store_.reset();
    if (fs::exists(db_path())) {
      EXPECT_EQ(RawSql(db_path(), "PRAGMA integrity_check"), "ok");
    }
  }
  std::string db_path() const { return (fs::path(dir_) / Store::kFileName).string(); }

  SubjectRecord MakeSubject(const std::string& name) {
    SubjectRecord s;
    EXPECT_TRUE(
        store_->CreateSubject(name, 1.75, "default", "", model_json_, "import default", &s).ok());
    return s;
  }
  std::int64_t BeginRecording(std::int64_t subject_id, const std::string& movement = "squats") {
    std::int64_t id = 0;
    EXPECT_TRUE(store_
                    ->BeginRecording(subject_id, movement, 200.0, marker_names_, coordinate_names_,
                                     1, "mocapd 0.1.0 record", &id)
                    .ok());
    return id;
  }

  // Frames first, first + step, ... with every oddity the blob must keep: no points, unlabelled
  // (NaN) markers, a NaN with a payload, -0.0, flags, each tracker state.
  std::vector<RecordedFrame> MakeFrames(std::uint64_t first, int n, int step = 1) {
    std::mt19937 rng(static_cast<unsigned>(first));
    std::uniform_real_distribution<double> u(-1.5, 1.5);
    std::vector<RecordedFrame> frames(n);
    for (int i = 0; i < n; ++i) {
      RecordedFrame& f = frames[i];
      f.frame = first + static_cast<std::uint64_t>(i) * step;
      f.time_s = 1000.0 + static_cast<double>(f.frame) / 200.0 + 1e-7 * u(rng);
      f.points.resize(i % 5);  // 0 points every fifth frame
      for (auto& p : f.points) p = Eigen::Vector3d(u(rng), u(rng), u(rng) + 1.5);
      f.markers.resize(3, static_cast<Eigen::Index>(marker_names_.size()));
      f.marker_flags.resize(marker_names_.size());
      for (Eigen::Index m = 0; m < f.markers.cols(); ++m) {
        f.markers.col(m) = Eigen::Vector3d(u(rng), u(rng), u(rng) + 1.0);
        f.marker_flags[m] = static_cast<std::uint8_t>((i + m) % 4);
        if ((i + m) % 7 == 0) f.markers.col(m).setConstant(kNaN);
      }
      f.markers(0, 0) = std::bit_cast<double>(0x7ff8000000000abcULL);  // NaN with a payload
      f.markers(1, 0) = -0.0;
      f.coordinates.resize(static_cast<Eigen::Index>(coordinate_names_.size()));
      for (auto& z : f.coordinates) z = 0.5 * u(rng);
      f.tracker_state = static_cast<std::int8_t>(i % 3);
    }
    return frames;
  }

  fs::path root_;
  std::string dir_;
  std::unique_ptr<Store> store_;
  mocap::Model model_;
  std::string model_json_;
  std::vector<std::string> marker_names_, coordinate_names_;
};

bool SameBits(double a, double b) {
  return std::bit_cast<std::uint64_t>(a) == std::bit_cast<std::uint64_t>(b);
}

void ExpectSameFrames(const std::vector<RecordedFrame>& a, const std::vector<RecordedFrame>& b) {
  ASSERT_EQ(a.size(), b.size());
  for (std::size_t i = 0; i < a.size(); ++i) {
    SCOPED_TRACE("frame entry " + std::to_string(i));
    ASSERT_EQ(a[i].frame, b[i].frame);
    ASSERT_TRUE(SameBits(a[i].time_s, b[i].time_s));
    ASSERT_EQ(a[i].points.size(), b[i].points.size());
    for (std::size_t k = 0; k < a[i].points.size(); ++k) {
      for (int c = 0; c < 3; ++c) ASSERT_TRUE(SameBits(a[i].points[k][c], b[i].points[k][c]));
    }
    ASSERT_EQ(a[i].markers.cols(), b[i].markers.cols());
    for (Eigen::Index k = 0; k < a[i].markers.size(); ++k) {
      ASSERT_TRUE(SameBits(a[i].markers.data()[k], b[i].markers.data()[k])) << "marker entry " << k;
    }
    ASSERT_EQ(a[i].marker_flags, b[i].marker_flags);
    ASSERT_EQ(a[i].coordinates.size(), b[i].coordinates.size());
    for (Eigen::Index k = 0; k < a[i].coordinates.size(); ++k) {
      ASSERT_TRUE(SameBits(a[i].coordinates[k], b[i].coordinates[k]));
    }
    ASSERT_EQ(a[i].tracker_state, b[i].tracker_state);
  }
}

const char* const kIsoUtc = "[0-9]{4}-[0-9]{2}-[0-9]{2}T[0-9]{2}:[0-9]{2}:[0-9]{2}\\.[0-9]{3}Z";

// --- opening ------------------------------------------------------------------------------------

TEST_F(StoreTest, OpenCreatesTheDatabaseInWalModeWithTheCurrentSchema) {
  EXPECT_TRUE(fs::exists(db_path()));
  EXPECT_EQ(store_->path(), db_path());
  EXPECT_EQ(RawSql(db_path(), "PRAGMA journal_mode"), "wal");
  EXPECT_EQ(RawSql(db_path(), "PRAGMA user_version"), std::to_string(Store::kSchemaVersion));
  std::uint64_t bytes = 0;
  ASSERT_OK(store_->Usage(&bytes));
  EXPECT_GT(bytes, 0u);
}

TEST_F(StoreTest, ADatabaseFromANewerMocapdIsRefusedNamingThePath) {
  store_.reset();
  RawSql(db_path(), "PRAGMA user_version=7");
  std::unique_ptr<Store> again;
  ExpectError(Store::Open(dir_, &again), {db_path(), "schema version 7", "newer"});
  EXPECT_EQ(again, nullptr);
  RawSql(db_path(), "PRAGMA user_version=1");  // leave it consistent for the integrity check
}

TEST_F(StoreTest, AFileThatIsNotADatabaseIsAnErrorNamingThePath) {
  const std::string other = (root_ / "garbage").string();
  fs::create_directories(other);
  mocap::testutil::WriteBytes((fs::path(other) / Store::kFileName).string(),
                              std::string(4096, 'x'));
  std::unique_ptr<Store> s;
  ExpectError(Store::Open(other, &s),
              {(fs::path(other) / Store::kFileName).string(), "not a database"});
}

TEST_F(StoreTest, AStateDirectoryThatCannotBeCreatedIsNamed) {
  const std::string file = (root_ / "a_file").string();
  mocap::testutil::WriteBytes(file, "x");
  std::unique_ptr<Store> s;
  ExpectError(Store::Open(file + "/state", &s), {file + "/state"});
}

TEST_F(StoreTest, InvalidOptionsAreRefused) {
  StoreOptions options;
  options.busy_timeout_ms = -1;
  std::string error;
  EXPECT_FALSE(options.IsValid(&error));
  EXPECT_THAT(error, HasSubstr("busy_timeout_ms"));
  std::unique_ptr<Store> s;
  ExpectError(Store::Open(dir_, &s, options), {"busy_timeout_ms"});
}

// --- subjects and models ------------------------------------------------------------------------

TEST_F(StoreTest, SubjectRoundTripsWithItsFirstModel) {
  SubjectRecord s;
  ASSERT_OK(store_->CreateSubject("alice", 1.68, "/tmp/alice.osim", "<OpenSimDocument/>",
                                  model_json_, "mocapd 0.1.0 subject.create", &s));
  EXPECT_GT(s.id, 0);
  EXPECT_EQ(s.name, "alice");
  EXPECT_EQ(s.height_m, 1.68);
  EXPECT_EQ(s.model_source, "/tmp/alice.osim");
  EXPECT_EQ(s.osim_text, "<OpenSimDocument/>");
  EXPECT_EQ(s.latest_model_version, 1);
  EXPECT_EQ(s.produced_by, "mocapd 0.1.0 subject.create");
  EXPECT_THAT(s.created_at, MatchesRegex(kIsoUtc));

  SubjectRecord by_name, by_id;
  ASSERT_OK(store_->FindSubject("alice", &by_name));
  ASSERT_OK(store_->GetSubject(s.id, &by_id));
  for (const SubjectRecord* r : {&by_name, &by_id}) {
    EXPECT_EQ(r->id, s.id);
    EXPECT_EQ(r->name, s.name);
    EXPECT_EQ(r->osim_text, s.osim_text);
    EXPECT_EQ(r->created_at, s.created_at);
  }
  ModelRecord m;
  ASSERT_OK(store_->GetModel(s.id, 1, &m));
  EXPECT_EQ(m.version, 1);
  EXPECT_EQ(m.subject_id, s.id);
  EXPECT_EQ(m.model_json, model_json_);
  EXPECT_EQ(m.produced_by, "mocapd 0.1.0 subject.create");
  EXPECT_FALSE(m.fit_report_id.has_value());
  mocap::Model parsed;
  ASSERT_OK(mocap::ParseModelJson(m.model_json, "stored", &parsed));
  EXPECT_EQ(parsed.num_markers(), model_.num_markers());

  MakeSubject("bob");
  std::vector<SubjectRecord> list;
  ASSERT_OK(store_->ListSubjects(&list));
  ASSERT_EQ(list.size(), 2u);
  EXPECT_EQ(list[0].name, "alice");
  EXPECT_EQ(list[1].name, "bob");
}

TEST_F(StoreTest, BadSubjectsAreRefusedAndNothingIsLeftBehind) {
  MakeSubject("alice");
  SubjectRecord s;
  ExpectError(store_->CreateSubject("alice", 1.7, "default", "", model_json_, "t", &s),
              {"'alice'", "already taken"});
  ExpectError(store_->CreateSubject("", 1.7, "default", "", model_json_, "t", &s),
              {"name is empty"});
  ExpectError(store_->CreateSubject("carol", 0.0, "default", "", model_json_, "t", &s),
              {"'carol'", "height"});
  ExpectError(store_->CreateSubject("carol", 1.7, "", "", model_json_, "t", &s),
              {"'carol'", "model source"});
  ExpectError(store_->CreateSubject("carol", 1.7, "default", "", "{\"format\": 3}", "t", &s),
              {"'carol'", "initial model"});
  std::vector<SubjectRecord> list;
  ASSERT_OK(store_->ListSubjects(&list));
  EXPECT_EQ(list.size(), 1u);
  ExpectError(store_->FindSubject("carol", &s), {"no subject named 'carol'"});
  ExpectError(store_->GetSubject(42, &s), {"no subject with id 42"});
}

TEST_F(StoreTest, ModelsAreVersionedPerSubjectAndLinkTheirFitReport) {
  const SubjectRecord a = MakeSubject("alice");
  const SubjectRecord b = MakeSubject("bob");
  std::int64_t report = 0;
  ASSERT_OK(store_->AddFitReport(a.id, R"({"marker_rms_mm": 3.2})", "mocapd 0.1.0 fit", &report));
  ModelRecord m2, m3, b2;
  ASSERT_OK(store_->AddModel(a.id, model_json_, "mocapd 0.1.0 fit", report, &m2));
  ASSERT_OK(store_->AddModel(a.id, model_json_, "manual", std::nullopt, &m3));
  ASSERT_OK(store_->AddModel(b.id, model_json_, "manual", std::nullopt, &b2));
  EXPECT_EQ(m2.version, 2);
  EXPECT_EQ(m3.version, 3);
  EXPECT_EQ(b2.version, 2);  // per subject
  ASSERT_TRUE(m2.fit_report_id.has_value());
  EXPECT_EQ(*m2.fit_report_id, report);
  EXPECT_EQ(m2.produced_by, "mocapd 0.1.0 fit");
  EXPECT_THAT(m2.created_at, MatchesRegex(kIsoUtc));

  ModelRecord latest, second;
  ASSERT_OK(store_->GetModel(a.id, 0, &latest));
  EXPECT_EQ(latest.version, 3);
  EXPECT_EQ(latest.id, m3.id);
  ASSERT_OK(store_->GetModel(a.id, 2, &second));
  EXPECT_EQ(second.id, m2.id);
  EXPECT_EQ(second.fit_report_id, m2.fit_report_id);
  std::vector<ModelRecord> list;
  ASSERT_OK(store_->ListModels(a.id, &list));
  ASSERT_EQ(list.size(), 3u);
  for (int v = 0; v < 3; ++v) EXPECT_EQ(list[v].version, v + 1);
  SubjectRecord again;
  ASSERT_OK(store_->GetSubject(a.id, &again));
  EXPECT_EQ(again.latest_model_version, 3);

  ModelRecord bad;
  ExpectError(store_->GetModel(a.id, 9, &bad),
              {"subject " + std::to_string(a.id), "no model version 9"});
  ExpectError(store_->GetModel(77, 0, &bad), {"no subject with id 77"});
  ExpectError(store_->ListModels(77, &list), {"no subject with id 77"});
  ExpectError(store_->AddModel(77, model_json_, "t", std::nullopt, &bad),
              {"no subject with id 77"});
  ExpectError(store_->AddModel(a.id, "not json", "t", std::nullopt, &bad), {"adding a model"});
  ExpectError(store_->AddModel(a.id, model_json_, "t", 555, &bad), {"no fit report with id 555"});
  ExpectError(
      store_->AddModel(b.id, model_json_, "t", report, &bad),
      {"fit report " + std::to_string(report), "belongs to subject " + std::to_string(a.id)});
  ASSERT_OK(store_->ListModels(a.id, &list));
  EXPECT_EQ(list.size(), 3u);  // the refused ones added nothing
}

TEST_F(StoreTest, FitReportsRoundTrip) {
  const SubjectRecord a = MakeSubject("alice");
  const std::string json = R"({"iterations": 12, "joint_centres_mm": [0.4, 0.7]})";
  std::int64_t id = 0;
  ASSERT_OK(store_->AddFitReport(a.id, json, "mocapd 0.1.0 fit", &id));
  FitReportRecord r;
  ASSERT_OK(store_->GetFitReport(id, &r));
  EXPECT_EQ(r.id, id);
  EXPECT_EQ(r.subject_id, a.id);
  EXPECT_EQ(r.report_json, json);
  EXPECT_EQ(r.produced_by, "mocapd 0.1.0 fit");
  EXPECT_THAT(r.created_at, MatchesRegex(kIsoUtc));
  ExpectError(store_->GetFitReport(id + 1, &r),
              {"no fit report with id " + std::to_string(id + 1)});
  ExpectError(store_->AddFitReport(a.id, "{oops", "t", &id), {"report is not valid JSON"});
  ExpectError(store_->AddFitReport(99, json, "t", &id), {"no subject with id 99"});
}

TEST_F(StoreTest, CalibrationsAreVersionedAndTheLatestIsVersionZero) {
  CalibrationRecord c;
  ExpectError(store_->GetCalibration(0, &c), {"no rig calibration stored yet"});
  std::int64_t v1 = 0, v2 = 0;
  ASSERT_OK(
      store_->AddCalibration(R"({"cameras": [1]})", 0.21, 0.4, "mocapd 0.1.0 rig.calibrate", &v1));
  ASSERT_OK(
      store_->AddCalibration(R"({"cameras": [2]})", 0.18, -0.3, "mocapd 0.1.0 rig.calibrate", &v2));
  EXPECT_GT(v2, v1);
  ASSERT_OK(store_->GetCalibration(0, &c));
  EXPECT_EQ(c.version, v2);
  EXPECT_EQ(c.calibration_json, R"({"cameras": [2]})");
  EXPECT_EQ(c.reprojection_rms_px, 0.18);
  EXPECT_EQ(c.wand_length_error_mm, -0.3);
  EXPECT_EQ(c.produced_by, "mocapd 0.1.0 rig.calibrate");
  EXPECT_THAT(c.created_at, MatchesRegex(kIsoUtc));
  ASSERT_OK(store_->GetCalibration(v1, &c));
  EXPECT_EQ(c.calibration_json, R"({"cameras": [1]})");
  EXPECT_EQ(c.reprojection_rms_px, 0.21);
  std::vector<CalibrationRecord> list;
  ASSERT_OK(store_->ListCalibrations(&list));
  ASSERT_EQ(list.size(), 2u);
  EXPECT_EQ(list[0].version, v1);
  EXPECT_EQ(list[1].version, v2);
  ExpectError(store_->GetCalibration(v2 + 5, &c),
              {"no rig calibration version " + std::to_string(v2 + 5)});
  ExpectError(store_->AddCalibration("[1,", 0.2, 0.1, "t", &v1), {"calibration is not valid JSON"});
  ExpectError(store_->AddCalibration("{}", kNaN, 0.1, "t", &v1), {"must be finite"});
}

// --- recordings ---------------------------------------------------------------------------------

TEST_F(StoreTest, FramesAppendedInChunksReadBackBitIdentical) {
  const SubjectRecord a = MakeSubject("alice");
  const std::int64_t id = BeginRecording(a.id);
  RecordingInfo info;
  ASSERT_OK(store_->GetRecording(id, &info));
  EXPECT_EQ(info.state, RecordingState::kRecording);
  EXPECT_EQ(info.movement, "squats");
  EXPECT_EQ(info.rate_hz, 200.0);
  EXPECT_EQ(info.marker_names, marker_names_);
  EXPECT_EQ(info.coordinate_names, coordinate_names_);
  EXPECT_EQ(info.model_version, 1);
  EXPECT_THAT(info.started_at, MatchesRegex(kIsoUtc));
  EXPECT_EQ(info.stopped_at, "");
  EXPECT_EQ(info.produced_by, "mocapd 0.1.0 record");

  std::vector<RecordedFrame> all;
  // Chunks of 20, 1 and 17 frames (100 ms, a lone frame, a chunk after a dropped set).
  for (auto chunk : {MakeFrames(5000, 20), MakeFrames(5020, 1), MakeFrames(5023, 17)}) {
    ASSERT_OK(store_->AppendFrames(id, chunk));
    all.insert(all.end(), chunk.begin(), chunk.end());
  }
  ASSERT_OK(store_->AppendFrames(id, {}));  // nothing to store is not an error
  std::vector<RecordedFrame> read;
  ASSERT_OK(store_->ReadFrames(id, &read));
  ExpectSameFrames(all, read);
  EXPECT_TRUE(read[0].points.empty());
  EXPECT_TRUE(std::isnan(read[0].markers(0, 0)));

  ASSERT_OK(store_->GetRecording(id, &info));
  EXPECT_EQ(info.frame_count, 38);
  EXPECT_EQ(info.chunk_count, 3);

  ASSERT_OK(store_->FinishRecording(id, RecordingState::kComplete, R"({"hip_flexion_r": [95, 90]})",
                                    "good"));
  ASSERT_OK(store_->GetRecording(id, &info));
  EXPECT_EQ(info.state, RecordingState::kComplete);
  EXPECT_EQ(info.coverage_json, R"({"hip_flexion_r": [95, 90]})");
  EXPECT_EQ(info.note, "good");
  EXPECT_THAT(info.stopped_at, MatchesRegex(kIsoUtc));
  EXPECT_GE(info.stopped_at, info.started_at);
  ExpectError(
      store_->AppendFrames(id, MakeFrames(6000, 2)),
      {"recording " + std::to_string(id), "cannot append frames: the recording is complete"});
  ExpectError(store_->FinishRecording(id, RecordingState::kFailed, "", ""),
              {"finishing recording " + std::to_string(id), "already complete"});
  ASSERT_OK(store_->ReadFrames(id, &read));
  EXPECT_EQ(read.size(), all.size());
}

TEST_F(StoreTest, ARecordingWithoutMarkersOrCoordinatesKeepsItsPoints) {
  const SubjectRecord a = MakeSubject("alice");
  std::int64_t id = 0;
  ASSERT_OK(store_->BeginRecording(a.id, "wand", 100.0, {}, {}, 0, "mocapd 0.1.0", &id));
  std::vector<RecordedFrame> frames(3);
  for (int i = 0; i < 3; ++i) {
    frames[i].frame = i;
    frames[i].points.assign(i, Eigen::Vector3d(1.0 * i, -1.0 * i, 0.5));
  }
  ASSERT_OK(store_->AppendFrames(id, frames));
  std::vector<RecordedFrame> read;
  ASSERT_OK(store_->ReadFrames(id, &read));
  ExpectSameFrames(frames, read);
}

// The recorder's frames (daemon/recorder.h ToRecordedFrame): a frame the tracker labelled with
// no model yet, or with the previous subject's, is stored untracked with its points; before,
// the store refused it and a record.start right after subject.select failed on its first frame
// (found by fuzz/fuzz_daemon.cpp's seed session).
TEST_F(StoreTest, AFrameLabelledWithAnotherModelIsRecordedUntracked) {
  const SubjectRecord a = MakeSubject("alice");
  const std::int64_t id = BeginRecording(a.id);
  const int markers = static_cast<int>(marker_names_.size());
  const int coordinates = static_cast<int>(coordinate_names_.size());
  mocap::daemon::LiveFrame none, other, own;
  none.frame = 10;
  none.points = {Eigen::Vector3d(0.1, 0.2, 1.0)};
  none.tracker_state = -1;  // no tracker: no markers, no coordinates
  other.frame = 11;
  other.tracker_state = static_cast<int>(mocap::ekf::TrackState::kTracking);
  other.markers.setConstant(3, markers + 4, 0.5);  // the previous subject's model
  other.coordinates.setConstant(coordinates + 1, 0.1);
  own = other;
  own.frame = 12;
  own.markers.setConstant(3, markers, 0.25);
  own.markers.col(2).setConstant(kNaN);
  own.coordinates.setConstant(coordinates, 0.2);
  std::vector<RecordedFrame> frames;
  for (const auto* f : {&none, &other, &own})
    frames.push_back(mocap::daemon::ToRecordedFrame(*f, markers, coordinates));
  ASSERT_OK(store_->AppendFrames(id, frames));
  std::vector<RecordedFrame> read;
  ASSERT_OK(store_->ReadFrames(id, &read));
  ASSERT_EQ(read.size(), 3u);
  for (int i : {0, 1}) {
    SCOPED_TRACE(i);
    EXPECT_TRUE(read[i].markers.array().isNaN().all());
    EXPECT_EQ(read[i].marker_flags, std::vector<std::uint8_t>(markers, 1));
    EXPECT_TRUE(read[i].coordinates.array().isNaN().all());
    EXPECT_EQ(read[i].tracker_state, static_cast<int>(mocap::ekf::TrackState::kInitialising));
  }
  ASSERT_EQ(read[0].points.size(), 1u);
  EXPECT_EQ(read[0].points[0], none.points[0]);
  // A frame of the recording's own model is kept as labelled.
  EXPECT_EQ(read[2].tracker_state, static_cast<int>(mocap::ekf::TrackState::kTracking));
  EXPECT_EQ(read[2].markers(0, 0), 0.25);
  EXPECT_EQ(read[2].marker_flags[2], 1);
  EXPECT_EQ(read[2].marker_flags[0], 0);
  EXPECT_EQ(read[2].coordinates[0], 0.2);
}

TEST_F(StoreTest, FramesThatDoNotFitTheRecordingAreRefusedNamingTheFrame) {
  const SubjectRecord a = MakeSubject("alice");
  const std::int64_t id = BeginRecording(a.id);
  ASSERT_OK(store_->AppendFrames(id, MakeFrames(100, 5)));

  auto frames = MakeFrames(200, 3);
  frames[1].markers.resize(3, 2);
  ExpectError(store_->AppendFrames(id, frames), {"frame 201", "2 marker columns"});
  frames = MakeFrames(200, 3);
  frames[2].marker_flags.pop_back();
  ExpectError(store_->AppendFrames(id, frames), {"frame 202", "flags"});
  frames = MakeFrames(200, 3);
  frames[0].coordinates.resize(2);
  ExpectError(store_->AppendFrames(id, frames), {"frame 200", "2 coordinates"});
  frames = MakeFrames(200, 3);
  frames[1].tracker_state = 3;
  ExpectError(store_->AppendFrames(id, frames), {"frame 201", "tracker state 3"});
  frames = MakeFrames(200, 3);
  frames[2].frame = 200;
  ExpectError(store_->AppendFrames(id, frames), {"frame 200", "must increase"});
  ExpectError(store_->AppendFrames(id, MakeFrames(104, 3)), {"frame 104", "last stored frame 104"});
  frames = MakeFrames(200, 1);
  frames[0].frame = std::uint64_t{1} << 63;
  ExpectError(store_->AppendFrames(id, frames), {"2^63"});
  ExpectError(store_->AppendFrames(id + 1, MakeFrames(1, 1)),
              {"no recording with id " + std::to_string(id + 1)});

  std::vector<RecordedFrame> read;
  ASSERT_OK(store_->ReadFrames(id, &read));
  EXPECT_EQ(read.size(), 5u);  // nothing refused was stored
}

TEST_F(StoreTest, BadRecordingsAndUnknownIdsAreErrors) {
  const SubjectRecord a = MakeSubject("alice");
  std::int64_t id = 0;
  ExpectError(store_->BeginRecording(99, "squats", 200, {}, {}, 0, "t", &id),
              {"no subject with id 99"});
  ExpectError(store_->BeginRecording(a.id, "squats", 200, {}, {}, 4, "t", &id),
              {"no model version 4"});
  ExpectError(store_->BeginRecording(a.id, "squats", 0, {}, {}, 1, "t", &id), {"rate 0"});
  ExpectError(store_->BeginRecording(a.id, "", 200, {}, {}, 1, "t", &id),
              {"movement name is empty"});
  ExpectError(store_->BeginRecording(a.id, "squats", 200, {"A", "B", "A"}, {}, 1, "t", &id),
              {"marker names", "'A' appears twice"});
  ExpectError(store_->BeginRecording(a.id, "squats", 200, {}, {"knee", ""}, 1, "t", &id),
              {"coordinate names", "empty name"});
  RecordingInfo info;
  std::vector<RecordedFrame> frames;
  std::vector<RecordingInfo> list;
  ExpectError(store_->GetRecording(31, &info), {"no recording with id 31"});
  ExpectError(store_->ReadFrames(31, &frames), {"no recording with id 31"});
  ExpectError(store_->FinishRecording(31, RecordingState::kComplete, "", ""),
              {"no recording with id 31"});
  ExpectError(store_->ListRecordings(31, &list), {"no subject with id 31"});
  id = BeginRecording(a.id);
  ExpectError(store_->FinishRecording(id, RecordingState::kRecording, "", ""),
              {"cannot be 'recording'"});
  ExpectError(store_->FinishRecording(id, RecordingState::kComplete, "{", ""),
              {"coverage is not valid JSON"});
  ASSERT_OK(store_->GetRecording(id, &info));
  EXPECT_EQ(info.state, RecordingState::kRecording);
}

TEST_F(StoreTest, RecordingsAreListedPerSubjectOrAll) {
  const SubjectRecord a = MakeSubject("alice");
  const SubjectRecord b = MakeSubject("bob");
  const std::int64_t r1 = BeginRecording(a.id, "static");
  const std::int64_t r2 = BeginRecording(b.id, "squats");
  const std::int64_t r3 = BeginRecording(a.id, "gait");
  std::vector<RecordingInfo> list;
  ASSERT_OK(store_->ListRecordings(0, &list));
  ASSERT_EQ(list.size(), 3u);
  EXPECT_EQ(list[0].id, r1);
  EXPECT_EQ(list[1].id, r2);
  EXPECT_EQ(list[2].id, r3);
  ASSERT_OK(store_->ListRecordings(a.id, &list));
  ASSERT_EQ(list.size(), 2u);
  EXPECT_EQ(list[0].movement, "static");
  EXPECT_EQ(list[1].movement, "gait");
}

TEST_F(StoreTest, AReopenedStoreListsTheSameSubjectsModelsAndRecordings) {
  const SubjectRecord a = MakeSubject("alice");
  const SubjectRecord b = MakeSubject("bob");
  ModelRecord m2;
  ASSERT_OK(store_->AddModel(a.id, model_json_, "mocapd 0.1.0 fit", std::nullopt, &m2));
  const std::int64_t r1 = BeginRecording(a.id);
  const auto frames = MakeFrames(1, 30);
  ASSERT_OK(store_->AppendFrames(r1, frames));
  ASSERT_OK(store_->FinishRecording(r1, RecordingState::kComplete, "{}", ""));
  std::int64_t cal = 0;
  ASSERT_OK(store_->AddCalibration("{}", 0.2, 0.1, "t", &cal));
  std::vector<SubjectRecord> subjects_before;
  std::vector<RecordingInfo> recordings_before;
  ASSERT_OK(store_->ListSubjects(&subjects_before));
  ASSERT_OK(store_->ListRecordings(0, &recordings_before));

  store_.reset();
  ASSERT_OK(Store::Open(dir_, &store_));
  std::vector<SubjectRecord> subjects;
  std::vector<RecordingInfo> recordings;
  std::vector<ModelRecord> models;
  ASSERT_OK(store_->ListSubjects(&subjects));
  ASSERT_OK(store_->ListRecordings(0, &recordings));
  ASSERT_OK(store_->ListModels(a.id, &models));
  ASSERT_EQ(subjects.size(), subjects_before.size());
  for (std::size_t i = 0; i < subjects.size(); ++i) {
    EXPECT_EQ(subjects[i].id, subjects_before[i].id);
    EXPECT_EQ(subjects[i].name, subjects_before[i].name);
    EXPECT_EQ(subjects[i].created_at, subjects_before[i].created_at);
    EXPECT_EQ(subjects[i].latest_model_version, subjects_before[i].latest_model_version);
  }
  ASSERT_EQ(recordings.size(), 1u);
  EXPECT_EQ(recordings[0].state, RecordingState::kComplete);
  EXPECT_EQ(recordings[0].stopped_at, recordings_before[0].stopped_at);
  EXPECT_EQ(recordings[0].frame_count, 30);
  ASSERT_EQ(models.size(), 2u);
  EXPECT_EQ(models[1].id, m2.id);
  CalibrationRecord c;
  ASSERT_OK(store_->GetCalibration(0, &c));
  EXPECT_EQ(c.version, cal);
  std::vector<RecordedFrame> read;
  ASSERT_OK(store_->ReadFrames(r1, &read));
  ExpectSameFrames(frames, read);
  SubjectRecord dup;
  ExpectError(store_->CreateSubject("bob", 1.8, "default", "", model_json_, "t", &dup),
              {"'bob'", "already taken", "subject id " + std::to_string(b.id)});
}

TEST_F(StoreTest, ARecordingLeftOpenReadsBackInterruptedWithItsFrames) {
  const SubjectRecord a = MakeSubject("alice");
  const std::int64_t done = BeginRecording(a.id, "static");
  ASSERT_OK(store_->FinishRecording(done, RecordingState::kComplete, "", ""));
  const std::int64_t open = BeginRecording(a.id, "squats");
  const auto frames = MakeFrames(10, 25);
  ASSERT_OK(store_->AppendFrames(open, {frames.begin(), frames.begin() + 20}));
  ASSERT_OK(store_->AppendFrames(open, {frames.begin() + 20, frames.end()}));

  // A worker's Store opened while the recording runs must not end it.
  StoreOptions worker;
  worker.mark_interrupted_recordings = false;
  std::unique_ptr<Store> second;
  ASSERT_OK(Store::Open(dir_, &second, worker));
  RecordingInfo info;
  ASSERT_OK(second->GetRecording(open, &info));
  EXPECT_EQ(info.state, RecordingState::kRecording);
  // ... and reads what the recorder committed, side by side (WAL).
  std::vector<RecordedFrame> read;
  ASSERT_OK(second->ReadFrames(open, &read));
  EXPECT_EQ(read.size(), 25u);
  second.reset();

  store_.reset();  // the daemon stops without FinishRecording
  ASSERT_OK(Store::Open(dir_, &store_));
  ASSERT_OK(store_->GetRecording(open, &info));
  EXPECT_EQ(info.state, RecordingState::kInterrupted);
  EXPECT_THAT(info.stopped_at, MatchesRegex(kIsoUtc));
  EXPECT_THAT(info.note, HasSubstr("still recording"));
  EXPECT_EQ(info.frame_count, 25);
  ASSERT_OK(store_->ReadFrames(open, &read));
  ExpectSameFrames(frames, read);
  ASSERT_OK(store_->GetRecording(done, &info));
  EXPECT_EQ(info.state, RecordingState::kComplete);  // untouched
  int count = -1;
  ASSERT_OK(store_->MarkInterrupted(&count));
  EXPECT_EQ(count, 0);
  ExpectError(store_->AppendFrames(open, MakeFrames(100, 1)), {"the recording is interrupted"});
}

// The daemon's shape: the recorder appends through its Store while other threads read and write
// through theirs. No call fails on a lock (busy_timeout, BEGIN IMMEDIATE), and every read sees a
// whole number of committed chunks, bit for bit.
TEST_F(StoreTest, AStorePerThreadWorkSideBySide) {
  const SubjectRecord a = MakeSubject("alice");
  const std::int64_t id = BeginRecording(a.id);
  constexpr int kChunks = 40, kChunkFrames = 20;
  std::vector<std::vector<RecordedFrame>> chunks;
  for (int c = 0; c < kChunks; ++c)
    chunks.push_back(MakeFrames(1 + kChunkFrames * c, kChunkFrames));
  StoreOptions worker;
  worker.mark_interrupted_recordings = false;
  std::unique_ptr<Store> reader, calibrator;
  ASSERT_OK(Store::Open(dir_, &reader, worker));
  ASSERT_OK(Store::Open(dir_, &calibrator, worker));

  std::atomic<bool> done{false};
  std::string writer_error, reader_error, calibrator_error;
  std::thread writer_thread([&] {
    for (const auto& chunk : chunks) {
      if (Status s = store_->AppendFrames(id, chunk); !s.ok()) {
        writer_error = s.message();
        break;
      }
    }
    done = true;
  });
  std::thread calibrator_thread([&] {
    for (int i = 0; i < 20 && calibrator_error.empty(); ++i) {
      std::int64_t v = 0;
      if (Status s = calibrator->AddCalibration("{}", 0.2, 0.1, "t", &v); !s.ok()) {
        calibrator_error = s.message();
      }
    }
  });
  int reads = 0;
  std::size_t last_size = 0;
  while (reader_error.empty()) {
    const bool finished = done;  // read once more after the writer is done
    std::vector<RecordedFrame> read;
    if (Status s = reader->ReadFrames(id, &read); !s.ok()) {
      reader_error = s.message();
      break;
    }
    ++reads;
    if (read.size() % kChunkFrames != 0 || read.size() < last_size) {
      reader_error =
          "read " + std::to_string(read.size()) + " frames after " + std::to_string(last_size);
      break;
    }
    last_size = read.size();
    for (std::size_t c = 0; c < read.size() / kChunkFrames; ++c) {
      ExpectSameFrames(chunks[c],
                       {read.begin() + c * kChunkFrames, read.begin() + (c + 1) * kChunkFrames});
    }
    if (finished) break;
  }
  writer_thread.join();
  calibrator_thread.join();
  EXPECT_EQ(writer_error, "");
  EXPECT_EQ(reader_error, "");
  EXPECT_EQ(calibrator_error, "");
  EXPECT_EQ(last_size, static_cast<std::size_t>(kChunks * kChunkFrames));
  EXPECT_GE(reads, 1);
  std::vector<CalibrationRecord> calibrations;
  ASSERT_OK(reader->ListCalibrations(&calibrations));
  EXPECT_EQ(calibrations.size(), 20u);
}

// Without automatic checkpoints the WAL grows with every chunk; a Checkpoint() from another Store
// lets the writer start the WAL over, so it stops growing.
TEST_F(StoreTest, ACheckpointFromAnotherStoreKeepsTheWalFromGrowing) {
  store_.reset();
  StoreOptions recorder;
  recorder.wal_autocheckpoint_pages = 0;
  ASSERT_OK(Store::Open(dir_, &store_, recorder));
  const SubjectRecord a = MakeSubject("alice");
  const std::int64_t id = BeginRecording(a.id);
  const std::string wal = db_path() + "-wal";
  std::uint64_t frame = 1;
  auto append = [&](int chunks) {
    for (int c = 0; c < chunks; ++c, frame += 20) {
      ASSERT_OK(store_->AppendFrames(id, MakeFrames(frame, 20)));
    }
  };
  append(100);  // ~4.7 MB: past SQLite's default 1000-page checkpoint, which must not run here
  const auto wal_after_100 = fs::file_size(wal);
  EXPECT_GT(wal_after_100, 1000u * 4096u);
  StoreOptions worker;
  worker.mark_interrupted_recordings = false;
  std::unique_ptr<Store> checkpointer;
  ASSERT_OK(Store::Open(dir_, &checkpointer, worker));
  int wal_pages = 0, checkpointed = 0;
  ASSERT_OK(checkpointer->Checkpoint(&wal_pages, &checkpointed));
  EXPECT_GT(wal_pages, 1000);
  EXPECT_EQ(checkpointed, wal_pages);  // nobody was reading: all of it
  append(50);  // written from the start of the WAL again
  EXPECT_EQ(fs::file_size(wal), wal_after_100);
  std::vector<RecordedFrame> read;
  ASSERT_OK(checkpointer->ReadFrames(id, &read));
  EXPECT_EQ(read.size(), 150u * 20u);
  StoreOptions bad;
  bad.wal_autocheckpoint_pages = -5;
  std::string error;
  EXPECT_FALSE(bad.IsValid(&error));
  EXPECT_THAT(error, HasSubstr("wal_autocheckpoint_pages must be >= 0, not -5"));
}

TEST_F(StoreTest, UsageGrowsWithTheFrames) {
  const SubjectRecord a = MakeSubject("alice");
  const std::int64_t id = BeginRecording(a.id);
  std::uint64_t before = 0, after = 0;
  ASSERT_OK(store_->Usage(&before));
  for (int c = 0; c < 10; ++c) ASSERT_OK(store_->AppendFrames(id, MakeFrames(1 + 20 * c, 20)));
  ASSERT_OK(store_->Usage(&after));
  // 200 frames of at least the markers (3 doubles each) and coordinates.
  EXPECT_GT(after, before + 200 * (24 * marker_names_.size() + 8 * coordinate_names_.size()));
}

// --- corrupt blobs ------------------------------------------------------------------------------

TEST_F(StoreTest, ACorruptedChunkIsAnErrorNamingRecordingAndChunk) {
  const SubjectRecord a = MakeSubject("alice");
  const std::int64_t id = BeginRecording(a.id);
  ASSERT_OK(store_->AppendFrames(id, MakeFrames(1, 10)));
  ASSERT_OK(store_->AppendFrames(id, MakeFrames(11, 10)));
  const std::string where = "recording " + std::to_string(id) + " chunk 1";
  const std::string set = "UPDATE recording_chunks SET frames = ";
  const std::string which = " WHERE recording_id = " + std::to_string(id) + " AND chunk_index = 1";
  struct Case {
    std::string value, message;
  };
  const std::vector<Case> cases = {
      {"x'00'", "shorter than the 24-byte header"},
      {"zeroblob(4000)", "no 'MCFR' magic"},
      // The last frame (4 points) loses 3 bytes.
      {"substr(frames, 1, length(frames) - 3)", "4 points do not fit"},
      {"frames || x'00'", "1 bytes after the last frame"},
      // The header claims 2^32 - 1 frames: refused before allocating.
      {"substr(frames, 1, 8) || x'ffffffff' || substr(frames, 13)", "do not fit in the blob"},
      {"substr(frames, 1, 4) || x'0900' || substr(frames, 7)", "layout version 9"},
      {"substr(frames, 1, 12) || x'03000000' || substr(frames, 17)", "says 3 markers"},
      // Frame 0's point count (after 24 + 17 bytes) set to 2^32 - 1.
      {"substr(frames, 1, 41) || x'ffffffff' || substr(frames, 46)", "points do not fit"},
      // Frame 0's tracker state (byte 24 + 16).
      {"substr(frames, 1, 40) || x'07' || substr(frames, 42)", "tracker state 7"},
      {"randomblob(length(frames))", "corrupt frame data"},
  };
  for (const auto& c : cases) {
    SCOPED_TRACE(c.value);
    RawSql(db_path(), set + c.value + which);
    std::vector<RecordedFrame> read(1);
    ExpectError(store_->ReadFrames(id, &read), {db_path(), where, c.message});
    EXPECT_EQ(read.size(), 1u);  // unchanged on error
    // Restore chunk 1 from a fresh copy for the next case.
    RawSql(db_path(), "DELETE FROM recording_chunks" + which);
    RawSql(db_path(), "UPDATE recordings SET frame_count = 10 WHERE id = " + std::to_string(id));
    ASSERT_OK(store_->AppendFrames(id, MakeFrames(11, 10)));
  }
  // A blob that decodes but disagrees with its row.
  RawSql(db_path(), "UPDATE recording_chunks SET frame_count = 9" + which);
  std::vector<RecordedFrame> read;
  ExpectError(store_->ReadFrames(id, &read), {where, "holds 10 frames, the row says 9"});
}

TEST(FrameBlob, EveryTruncationAndEveryByteFlipIsAnErrorOrDecodes) {
  std::vector<RecordedFrame> frames(3);
  for (int i = 0; i < 3; ++i) {
    frames[i].frame = 7 + i;
    frames[i].points.assign(i, Eigen::Vector3d(1, 2, 3));
    frames[i].markers = Eigen::Matrix3Xd::Constant(3, 2, 0.25 * i);
    frames[i].marker_flags = {1, 2};
    frames[i].coordinates = Eigen::VectorXd::Constant(4, -1.0);
  }
  const std::string blob = mocap::daemon::EncodeFrames(frames, 2, 4);
  std::vector<RecordedFrame> out;
  ASSERT_OK(mocap::daemon::DecodeFrames(blob, 2, 4, "b", &out));
  ExpectSameFrames(frames, out);
  for (std::size_t n = 0; n < blob.size(); ++n) {
    out.clear();
    const Status s = mocap::daemon::DecodeFrames(blob.substr(0, n), 2, 4, "blob x", &out);
    ASSERT_FALSE(s.ok()) << "truncated to " << n << " bytes";
    EXPECT_THAT(s.message(), HasSubstr("blob x: corrupt frame data"));
    EXPECT_TRUE(out.empty());
  }
  for (std::size_t i = 0; i < blob.size(); ++i) {
    std::string flipped = blob;
    flipped[i] = static_cast<char>(~flipped[i]);
    out.clear();
    const Status s = mocap::daemon::DecodeFrames(flipped, 2, 4, "blob x", &out);
    if (s.ok()) {
      EXPECT_EQ(out.size(), 3u);  // a flipped value, not a flipped structure
    } else {
      EXPECT_THAT(s.message(), HasSubstr("blob x: corrupt frame data"));
    }
  }
}

// --- exports ------------------------------------------------------------------------------------

class ExportTest : public StoreTest {
 protected:
  void SetUp() override {
    StoreTest::SetUp();
    const SubjectRecord a = MakeSubject("alice");
    id_ = BeginRecording(a.id);
    // Frames 1..20 and 23..40: sequence numbers 21 and 22 were dropped by the rig.
    frames_ = MakeFrames(1, 20);
    const auto more = MakeFrames(23, 18);
    frames_.insert(frames_.end(), more.begin(), more.end());
    for (auto& f : frames_) {
      f.markers(0, 0) = kNaN;  // a plain NaN: the formats' readers give back a plain NaN
      f.markers(1, 0) = kNaN;
      f.markers(2, 0) = kNaN;
    }
    ASSERT_OK(store_->AppendFrames(id_, {frames_.begin(), frames_.begin() + 20}));
    ASSERT_OK(store_->AppendFrames(id_, {frames_.begin() + 20, frames_.end()}));
    ASSERT_OK(store_->GetRecording(id_, &info_));
    ASSERT_OK(store_->ReadFrames(id_, &stored_));
  }
  std::string Path(const std::string& ext) const { return (root_ / ("export" + ext)).string(); }

  std::int64_t id_ = 0;
  RecordingInfo info_;
  std::vector<RecordedFrame> frames_, stored_;
};

// |read - stored| within `tol`, NaN where NaN.
void ExpectNear(double stored, double read, double tol, const std::string& what) {
  if (std::isnan(stored)) {
    EXPECT_TRUE(std::isnan(read)) << what;
  } else {
    EXPECT_NEAR(read, stored, tol) << what;
  }
}

TEST_F(ExportTest, C3dReadsBackTheLabelledMarkersAndTheUnlabelledPoints) {
  ASSERT_OK(mocap::daemon::ExportRecordingC3d(info_, stored_, Path(".c3d")));
  mocap::formats::MarkerTrial trial;
  ASSERT_OK(mocap::formats::ReadC3d(Path(".c3d"), &trial));
  EXPECT_EQ(trial.rate_hz, 200.0);
  ASSERT_EQ(trial.num_frames(), 40);  // every sequence number 1..40, the dropped two included
  EXPECT_EQ(trial.frame_numbers.front(), 1);
  EXPECT_EQ(trial.frame_numbers.back(), 40);
  const int num_markers = static_cast<int>(marker_names_.size());
  ASSERT_EQ(trial.num_markers(), num_markers + 4);  // at most 4 points in a frame: P001..P004
  for (int m = 0; m < num_markers; ++m) EXPECT_EQ(trial.marker_names[m], marker_names_[m]);
  EXPECT_EQ(trial.marker_names[num_markers], "P001");
  EXPECT_EQ(trial.marker_names[num_markers + 3], "P004");
  for (int row : {20, 21}) {  // the dropped sets
    for (int m = 0; m < trial.num_markers(); ++m) EXPECT_FALSE(trial.Has(row, m)) << row;
  }
  for (const auto& f : stored_) {
    const int row = static_cast<int>(f.frame - 1);
    EXPECT_DOUBLE_EQ(trial.times[row], row / 200.0);
    for (int m = 0; m < num_markers; ++m) {
      for (int k = 0; k < 3; ++k) {
        // Floats in mm: half an ulp of a float, relative.
        ExpectNear(f.markers(k, m), trial.At(row, m)[k], 6e-8 * std::abs(f.markers(k, m)) + 1e-12,
                   "frame " + std::to_string(f.frame) + " marker " + marker_names_[m]);
      }
    }
    for (int p = 0; p < 4; ++p) {
      const bool has = p < static_cast<int>(f.points.size());
      ASSERT_EQ(trial.Has(row, num_markers + p), has) << "frame " << f.frame << " point " << p;
      if (!has) continue;
      for (int k = 0; k < 3; ++k) {
        EXPECT_NEAR(trial.At(row, num_markers + p)[k], f.points[p][k],
                    6e-8 * std::abs(f.points[p][k]) + 1e-12);
      }
    }
  }
}

TEST_F(ExportTest, TrcReadsBackTheLabelledMarkers) {
  ASSERT_OK(mocap::daemon::ExportRecordingTrc(info_, stored_, Path(".trc")));
  mocap::formats::MarkerTrial trial;
  ASSERT_OK(mocap::formats::ReadTrc(Path(".trc"), &trial));
  ASSERT_EQ(trial.num_frames(), static_cast<int>(stored_.size()));  // one row per recorded frame
  EXPECT_EQ(trial.marker_names, marker_names_);
  for (int row = 0; row < trial.num_frames(); ++row) {
    const auto& f = stored_[row];
    EXPECT_EQ(trial.frame_numbers[row], static_cast<int>(f.frame));
    EXPECT_DOUBLE_EQ(trial.times[row], (f.frame - 1) / 200.0);
    for (int m = 0; m < trial.num_markers(); ++m) {
      for (int k = 0; k < 3; ++k) {
        // 5 decimals of mm.
        ExpectNear(f.markers(k, m), trial.At(row, m)[k], 5e-9 + 1e-12,
                   "marker " + marker_names_[m]);
      }
    }
  }
}

TEST_F(ExportTest, MotRoundTripsTheCoordinatesInDegrees) {
  std::vector<bool> rotational;
  ASSERT_OK(mocap::daemon::RotationalCoordinates(model_, info_.coordinate_names, &rotational));
  ASSERT_NE(std::count(rotational.begin(), rotational.end(), false), 0);  // the pelvis translations
  ASSERT_OK(mocap::daemon::ExportRecordingMot(info_, stored_, rotational, Path(".mot")));
  mocap::formats::CoordinateTable table;
  ASSERT_OK(mocap::formats::ReadMot(Path(".mot"), &table));
  EXPECT_TRUE(table.in_degrees);
  EXPECT_EQ(table.column_names, coordinate_names_);
  ASSERT_EQ(table.num_frames(), static_cast<int>(stored_.size()));
  for (int row = 0; row < table.num_frames(); ++row) {
    EXPECT_NEAR(table.times[row], (stored_[row].frame - 1) / 200.0, 5e-9);
    for (int c = 0; c < static_cast<int>(coordinate_names_.size()); ++c) {
      const double z = stored_[row].coordinates[c];
      const double expected = rotational[c] ? z * 180.0 / std::numbers::pi : z;
      EXPECT_NEAR(table.values(row, c), expected, 5e-9) << coordinate_names_[c];  // 8 decimals
    }
  }
  std::vector<bool> wrong(2, true);
  ExpectError(mocap::daemon::ExportRecordingMot(info_, stored_, wrong, Path("_bad.mot")),
              {"2 rotational flags"});
  ExpectError(mocap::daemon::RotationalCoordinates(model_, {"no_such_joint"}, &rotational),
              {"no coordinate 'no_such_joint'"});
}

TEST_F(ExportTest, TablesForTheFitAreInMetresAndRadians) {
  mocap::formats::MarkerTrial trial;
  ASSERT_OK(mocap::daemon::RecordingToMarkerTrial(info_, stored_, {}, &trial));
  EXPECT_EQ(trial.name, "squats");
  ASSERT_EQ(trial.num_frames(), 38);
  for (int row = 0; row < trial.num_frames(); ++row) {
    for (int m = 0; m < trial.num_markers(); ++m) {
      for (int k = 0; k < 3; ++k) {
        const double v = stored_[row].markers(k, m);
        ASSERT_TRUE(std::isnan(v) ? std::isnan(trial.At(row, m)[k]) : trial.At(row, m)[k] == v);
      }
    }
  }
  mocap::daemon::RecordingTableOptions fill;
  fill.fill_gaps = true;
  mocap::formats::CoordinateTable table;
  const std::vector<bool> rotational(coordinate_names_.size(), true);
  ASSERT_OK(
      mocap::daemon::RecordingToCoordinateTable(info_, stored_, rotational, false, fill, &table));
  EXPECT_FALSE(table.in_degrees);
  ASSERT_EQ(table.num_frames(), 40);
  EXPECT_TRUE(table.values.row(20).array().isNaN().all());
  EXPECT_EQ(table.values(22, 3), stored_[20].coordinates[3]);  // frame 23, radians as stored

  auto bad = stored_;
  bad[3].coordinates.resize(1);
  ExpectError(mocap::daemon::RecordingToMarkerTrial(info_, bad, {}, &trial),
              {"recording " + std::to_string(id_), "frame 4", "1 coordinates"});
  bad = stored_;
  std::swap(bad[1], bad[2]);
  ExpectError(mocap::daemon::RecordingToMarkerTrial(info_, bad, {}, &trial), {"must increase"});
}

// The daemon's live state: set, replaced, read back after a reopen; an unknown key is an error.
TEST_F(StoreTest, DaemonStateSurvivesAReopen) {
  ASSERT_TRUE(store_->SetState("subject", "3").ok());
  ASSERT_TRUE(store_->SetState("subject", "4").ok());
  std::string v;
  const Status missing = store_->GetState("live_model_version", &v);
  EXPECT_FALSE(missing.ok());
  EXPECT_THAT(missing.message(), HasSubstr("live_model_version"));
  store_.reset();
  ASSERT_TRUE(Store::Open(dir_, &store_).ok());
  ASSERT_TRUE(store_->GetState("subject", &v).ok());
  EXPECT_EQ(v, "4");
}

}  // namespace
