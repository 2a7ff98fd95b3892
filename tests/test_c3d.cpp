// Tests of formats/c3d: the real C3D files of ../shared/data against their TRC conversions and
// their READMEs; round trips through the writer in every processor format and storage; byte
// patterns fixed by the standard (so reader and writer cannot agree on a shared mistake);
// corrupt and truncated files; and `mocap convert` end to end.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <limits>
#include <map>
#include <random>
#include <string>
#include <vector>

#include "formats/c3d.h"
#include "formats/marker_data.h"
#include "formats/trc.h"
#include "tests/file_test_util.h"

namespace fs = std::filesystem;
using mocap::Status;
using mocap::formats::C3dProcessor;
using mocap::formats::C3dReadOptions;
using mocap::formats::C3dWriteOptions;
using mocap::formats::MarkerTrial;
using mocap::formats::ParseC3d;
using mocap::formats::ReadC3d;
using mocap::formats::ReadTrc;
using mocap::formats::WriteC3d;
using mocap::formats::WriteTrc;
using ::testing::HasSubstr;

namespace {

const double kNaN = std::numeric_limits<double>::quiet_NaN();

using mocap::testutil::CommandResult;
using mocap::testutil::Mocap;
using mocap::testutil::ReadBytes;
using mocap::testutil::SharedData;
using mocap::testutil::WriteBytes;

std::string TmpPath(const std::string& suffix) { return mocap::testutil::TmpPath("c3d", suffix); }

int CountMissing(const MarkerTrial& t) {
  int n = 0;
  for (int f = 0; f < t.num_frames(); ++f) {
    for (int m = 0; m < t.num_markers(); ++m) n += !t.Has(f, m);
  }
  return n;
}

// A trial with `markers` markers over `frames` frames starting at frame `first`: smooth motion of a
// few hundred mm with some negative coordinates, and a gap in marker 1.
MarkerTrial MakeTrial(int markers, int frames, int first = 1, double rate = 100.0) {
  MarkerTrial t;
  t.name = "synthetic";
  t.rate_hz = rate;
  for (int m = 0; m < markers; ++m) t.marker_names.push_back("M" + std::to_string(m));
  t.positions.resize(frames, 3 * markers);
  for (int f = 0; f < frames; ++f) {
    t.frame_numbers.push_back(first + f);
    t.times.push_back((first + f - 1) / rate);
    for (int m = 0; m < markers; ++m) {
      for (int c = 0; c < 3; ++c) {
        t.positions(f, 3 * m + c) = 0.9 * std::sin(0.05 * f + 0.7 * m + 2.1 * c) - 0.1 * c;
      }
    }
  }
  if (markers > 1) {
    for (int f = frames / 3; f < frames / 2; ++f) t.positions.block(f, 3, 1, 3).setConstant(kNaN);
  }
  return t;
}

// `b` equals `a`: names, rate and frame numbers exactly; times as (frame - 1) / rate; missing
// samples in the same places; coordinates within `tol_m` metres.
void ExpectSameTrial(const MarkerTrial& a, const MarkerTrial& b, double tol_m) {
  EXPECT_EQ(b.marker_names, a.marker_names);
  EXPECT_EQ(b.rate_hz, a.rate_hz);
  EXPECT_EQ(b.frame_numbers, a.frame_numbers);
  ASSERT_EQ(b.times.size(), a.times.size());
  for (size_t f = 0; f < a.times.size(); ++f) EXPECT_NEAR(b.times[f], a.times[f], 1e-12);
  ASSERT_EQ(b.positions.rows(), a.positions.rows());
  ASSERT_EQ(b.positions.cols(), a.positions.cols());
  for (int f = 0; f < a.num_frames(); ++f) {
    for (int k = 0; k < a.positions.cols(); ++k) {
      const double x = a.positions(f, k), y = b.positions(f, k);
      ASSERT_EQ(std::isnan(x), std::isnan(y)) << "frame " << f << " column " << k;
      if (!std::isnan(x)) {
        ASSERT_NEAR(y, x, tol_m) << "frame " << f << " column " << k;
      }
    }
  }
}

// Offset of the first occurrence of `what` in `bytes` (the test fails if absent).
size_t Find(const std::string& bytes, const std::string& what) {
  const size_t at = bytes.find(what);
  EXPECT_NE(at, std::string::npos) << what << " not found";
  return at;
}

std::string Hex(const std::string& bytes, size_t at, size_t n) {
  std::string s;
  char buf[4];
  for (size_t i = 0; i < n; ++i) {
    std::snprintf(buf, sizeof buf, "%02X", static_cast<unsigned char>(bytes.at(at + i)));
    s += buf;
  }
  return s;
}

// ---------------------------------------------------------------- real files

// Every C3D with a TRC conversion in derived_trc/ agrees with it to 0.001 mm on every sample,
// with the same missing samples, names, frame numbers and times.
TEST(C3dReal, AgreesWithDerivedTrcToAMicrometre) {
  SKIP_WITHOUT_SHARED_DATA();
  int compared = 0;
  double worst_mm = 0.0;
  for (const auto& folder : fs::directory_iterator(SharedData())) {
    const fs::path derived = folder.path() / "derived_trc";
    if (!fs::is_directory(derived)) continue;
    for (const auto& entry : fs::directory_iterator(derived)) {
      if (entry.path().extension() != ".trc") continue;
      const fs::path c3d = folder.path() / (entry.path().stem().string() + ".c3d");
      SCOPED_TRACE(c3d.string());
      ASSERT_TRUE(fs::exists(c3d)) << "derived TRC without its C3D";
      MarkerTrial from_c3d, from_trc;
      const Status sc = ReadC3d(c3d.string(), &from_c3d);
      ASSERT_TRUE(sc.ok()) << sc.message();
      const Status st = ReadTrc(entry.path().string(), &from_trc);
      ASSERT_TRUE(st.ok()) << st.message();
      EXPECT_EQ(from_c3d.name, c3d.stem().string());
      EXPECT_EQ(from_c3d.marker_names, from_trc.marker_names);
      EXPECT_EQ(from_c3d.rate_hz, from_trc.rate_hz);
      EXPECT_EQ(from_c3d.frame_numbers, from_trc.frame_numbers);
      ASSERT_EQ(from_c3d.num_frames(), from_trc.num_frames());
      ASSERT_EQ(from_c3d.positions.cols(), from_trc.positions.cols());
      for (int f = 0; f < from_c3d.num_frames(); ++f) {
        ASSERT_NEAR(from_c3d.times[f], from_trc.times[f], 0.5e-6) << "frame " << f;  // 6 decimals
      }
      double file_worst = 0.0;
      int missing = 0;
      for (int f = 0; f < from_c3d.num_frames(); ++f) {
        for (int k = 0; k < from_c3d.positions.cols(); ++k) {
          const double x = from_c3d.positions(f, k), y = from_trc.positions(f, k);
          ASSERT_EQ(std::isnan(x), std::isnan(y))
              << "frame " << f << " marker " << from_c3d.marker_names[k / 3];
          if (std::isnan(x)) {
            ++missing;
            continue;
          }
          file_worst = std::max(file_worst, std::fabs(x - y) * 1000.0);
        }
      }
      EXPECT_LE(file_worst, 0.001) << "mm";
      worst_mm = std::max(worst_mm, file_worst);
      ++compared;
      std::printf("  %s: %d frames, %d markers, %d missing coordinates, max |C3D - TRC| = %.4f mm\n",
                  c3d.filename().c_str(), from_c3d.num_frames(), from_c3d.num_markers(), missing,
                  file_worst);
    }
  }
  EXPECT_GE(compared, 7) << "shared/data has 7 derived TRC files";
  std::printf("  %d files, worst difference %.4f mm\n", compared, worst_mm);
}

struct RealC3d {
  std::string rel;
  int frames;
  int min_markers, max_markers;
  double rate;
  int missing_samples;  // -1: not stated in the README
};

// Every C3D in shared/data loads with the counts its folder's README.txt states.
TEST(C3dReal, EveryFileLoadsWithItsReadmeCounts) {
  SKIP_WITHOUT_SHARED_DATA();
  const std::vector<RealC3d> files = {
      {"welk007_hipfunc/c3d_Trimmed_static1.c3d", 297, 54, 54, 100.0, 0},
      {"welk007_hipfunc/c3d_Trimmed_RHJC1.c3d", 1224, 48, 48, 100.0, 0},
      {"biobuddy_p01_lowerlimb/anatomical_posture.c3d", 122, 59, 60, 12.0, 1},
      {"biobuddy_p01_lowerlimb/Test_func_anat.c3d", 131, 59, 60, 12.0, -1},
      {"biobuddy_p01_lowerlimb/Test_func_lhip.c3d", 489, 59, 60, 12.0, 5},
      {"biobuddy_p01_lowerlimb/Test_func_rhip.c3d", 525, 59, 60, 12.0, 8},
      {"biobuddy_p01_lowerlimb/Test_func_lknee.c3d", 216, 59, 60, 12.0, -1},
      {"biobuddy_p01_lowerlimb/Test_func_rknee.c3d", 217, 59, 60, 12.0, -1},
      {"biobuddy_p01_lowerlimb/Test_func_lankle.c3d", 491, 59, 60, 12.0, -1},
      {"biobuddy_p01_lowerlimb/Test_func_rankle.c3d", 486, 59, 60, 12.0, -1},
      {"biobuddy_p01_lowerlimb/Test_func_trunk.c3d", 1047, 59, 60, 12.0, -1},
  };
  std::map<std::string, const RealC3d*> expected;
  for (const RealC3d& f : files) expected[f.rel] = &f;
  int seen = 0;
  for (const auto& entry : fs::recursive_directory_iterator(SharedData())) {
    if (entry.path().extension() != ".c3d") continue;
    const std::string rel = fs::relative(entry.path(), SharedData()).string();
    SCOPED_TRACE(rel);
    ASSERT_TRUE(expected.count(rel)) << "a C3D file this test does not know: add its README counts";
    const RealC3d& e = *expected[rel];
    MarkerTrial t;
    const Status s = ReadC3d(entry.path().string(), &t);
    ASSERT_TRUE(s.ok()) << s.message();
    EXPECT_EQ(t.num_frames(), e.frames);
    EXPECT_GE(t.num_markers(), e.min_markers);
    EXPECT_LE(t.num_markers(), e.max_markers);
    EXPECT_EQ(t.rate_hz, e.rate);
    ASSERT_FALSE(t.frame_numbers.empty());
    EXPECT_EQ(t.frame_numbers.front(), 1);
    EXPECT_EQ(t.frame_numbers.back(), e.frames);
    if (e.missing_samples >= 0) {
      EXPECT_EQ(CountMissing(t), e.missing_samples);
    }
    // Positions are metres: a person in a lab, not millimetres.
    double largest = 0.0;
    for (int f = 0; f < t.num_frames(); ++f) {
      for (int m = 0; m < t.num_markers(); ++m) {
        if (t.Has(f, m)) largest = std::max(largest, t.At(f, m).cwiseAbs().maxCoeff());
      }
    }
    EXPECT_GT(largest, 0.2);
    EXPECT_LT(largest, 5.0);
    ++seen;
  }
  EXPECT_EQ(seen, static_cast<int>(files.size()));
}

// The README's stated gaps are where it says: LBHD 5 frames in lhip, RKNEM 8 in rhip.
TEST(C3dReal, GapsAreOnTheMarkersTheReadmeNames) {
  SKIP_WITHOUT_SHARED_DATA();
  for (const auto& [file, marker, n] :
       {std::tuple{"Test_func_lhip.c3d", "LBHD", 5}, std::tuple{"Test_func_rhip.c3d", "RKNEM", 8}}) {
    MarkerTrial t;
    ASSERT_TRUE(ReadC3d(SharedData() + "/biobuddy_p01_lowerlimb/" + file, &t).ok());
    const int m = t.FindMarker(marker);
    ASSERT_GE(m, 0) << marker;
    int missing = 0;
    for (int f = 0; f < t.num_frames(); ++f) missing += !t.Has(f, m);
    EXPECT_EQ(missing, n) << file << " " << marker;
  }
}

// Cortex stores "FullBody_static:r_knee"; the default strips the subject prefix, the option keeps it.
TEST(C3dReal, LabelPrefixIsStrippedUnlessAskedToKeepIt) {
  SKIP_WITHOUT_SHARED_DATA();
  const std::string path = SharedData() + "/welk007_hipfunc/c3d_Trimmed_static1.c3d";
  MarkerTrial stripped, kept;
  ASSERT_TRUE(ReadC3d(path, &stripped).ok());
  C3dReadOptions keep;
  keep.strip_label_prefix = false;
  ASSERT_TRUE(ReadC3d(path, &kept, keep).ok());
  EXPECT_EQ(stripped.marker_names.front(), "r_knee");
  EXPECT_EQ(kept.marker_names.front(), "FullBody_static:r_knee");
  EXPECT_EQ(kept.marker_names.back(), "FullBody_static:L_wrist_ulna");  // trailing spaces gone
  EXPECT_GE(stripped.FindMarker("r.ASIS"), 0);
  ExpectSameTrial(stripped, [&] {
    MarkerTrial t = kept;
    t.marker_names = stripped.marker_names;
    return t;
  }(), 0.0);
}

// ---------------------------------------------------------------- round trips

TEST(C3dRoundTrip, IntelFloatGivesBackTheTrialToFloatPrecision) {
  const MarkerTrial t = MakeTrial(4, 120, 7, 150.0);
  const std::string path = TmpPath(".c3d");
  ASSERT_TRUE(WriteC3d(path, t).ok());
  MarkerTrial back;
  const Status s = ReadC3d(path, &back);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(back.name, fs::path(path).stem().string());
  EXPECT_EQ(CountMissing(back), CountMissing(t));
  EXPECT_GT(CountMissing(t), 0);
  // |x| < 2048 mm stored as float: the spacing of floats below 2048 is at most 2^-13 mm.
  ExpectSameTrial(t, back, 0.5 * std::ldexp(1.0, -13) * 1e-3);
  // The file is whole 512-byte blocks: header, one parameter block, the data.
  const std::string bytes = ReadBytes(path);
  EXPECT_EQ(bytes.size() % 512, 0u);
  EXPECT_EQ(bytes.size(), 512u * 2 + (120 * 4 * 16 + 511) / 512 * 512);
}

// Writing the file again from what was read gives the same bytes: nothing drifts.
TEST(C3dRoundTrip, RewritingWhatWasReadIsByteIdentical) {
  const MarkerTrial t = MakeTrial(3, 50);
  const std::string a = TmpPath("_a.c3d"), b = TmpPath("_b.c3d");
  ASSERT_TRUE(WriteC3d(a, t).ok());
  MarkerTrial back;
  ASSERT_TRUE(ReadC3d(a, &back).ok());
  ASSERT_TRUE(WriteC3d(b, back).ok());
  EXPECT_EQ(ReadBytes(a), ReadBytes(b));
}

// Every processor format in float and scaled-integer storage reads back to the same values.
TEST(C3dRoundTrip, EveryProcessorAndStorageReadsBack) {
  const MarkerTrial t = MakeTrial(3, 80, 1, 60.0);
  for (C3dProcessor p : {C3dProcessor::kIntel, C3dProcessor::kDec, C3dProcessor::kMips}) {
    for (bool integer : {false, true}) {
      SCOPED_TRACE("processor " + std::to_string(static_cast<int>(p)) +
                   (integer ? " integer" : " float"));
      C3dWriteOptions o;
      o.processor = p;
      o.integer_points = integer;
      const std::string path = TmpPath("_" + std::to_string(static_cast<int>(p)) +
                                       (integer ? "_int" : "_float") + ".c3d");
      ASSERT_TRUE(WriteC3d(path, t, o).ok());
      const std::string bytes = ReadBytes(path);
      EXPECT_EQ(static_cast<unsigned char>(bytes.at(512 + 3)), static_cast<int>(p));
      MarkerTrial back;
      const Status s = ReadC3d(path, &back);
      ASSERT_TRUE(s.ok()) << s.message();
      // Integers: the largest |coordinate| is 30000 counts, so the error is at most half a count;
      // floats: half a float spacing below 2048 mm.
      const double largest_m = t.positions.array().isNaN().select(0.0, t.positions).cwiseAbs().maxCoeff();
      ASSERT_GT(largest_m, 1.024);
      ASSERT_LT(largest_m, 2.048);
      const double tol_m = integer ? 0.5 * (largest_m / 30000.0) * (1 + 1e-6)
                                   : 0.5 * std::ldexp(1.0, -13) * 1e-3;
      ExpectSameTrial(t, back, tol_m);
      if (integer) {  // not merely float precision: the integer path really quantises
        double worst = 0.0;
        for (int f = 0; f < t.num_frames(); ++f) {
          if (t.Has(f, 0)) worst = std::max(worst, std::fabs(back.positions(f, 0) - t.positions(f, 0)));
        }
        EXPECT_GT(worst, 1e-7);
      }
    }
  }
}

// The bytes the standard fixes, so a reader and writer sharing a mistake would still fail here:
// 100 Hz in the header (words 11-12) and 1.0 mm as the first coordinate of the data.
TEST(C3dRoundTrip, ProcessorFormatsHaveTheStandardsBytePatterns) {
  MarkerTrial t;
  t.rate_hz = 100.0;
  t.marker_names = {"A"};
  t.positions.resize(1, 3);
  t.positions << 0.001, -0.002, 0.0;  // 1 mm, -2 mm, 0
  t.frame_numbers = {1};
  struct Case {
    C3dProcessor p;
    const char* rate;      // 100.0
    const char* one_mm;    // 1.0
    const char* minus_two; // -2.0
    const char* minus_one; // residual -1.0
  };
  const Case cases[] = {
      {C3dProcessor::kIntel, "0000C842", "0000803F", "000000C0", "000080BF"},
      {C3dProcessor::kMips, "42C80000", "3F800000", "C0000000", "BF800000"},
      // VAX F: 100 = 0.78125 x 2^7 -> exponent 135; words (sign|exp|high mantissa), (low mantissa)
      {C3dProcessor::kDec, "C8430000", "80400000", "00C10000", "80C00000"},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(static_cast<int>(c.p));
    C3dWriteOptions o;
    o.processor = c.p;
    const std::string path = TmpPath("_" + std::to_string(static_cast<int>(c.p)) + ".c3d");
    ASSERT_TRUE(WriteC3d(path, t, o).ok());
    const std::string bytes = ReadBytes(path);
    EXPECT_EQ(Hex(bytes, 20, 4), c.rate);
    const size_t data = 512 * 2;  // header + one parameter block
    EXPECT_EQ(Hex(bytes, data, 4), c.one_mm);
    EXPECT_EQ(Hex(bytes, data + 4, 4), c.minus_two);
    EXPECT_EQ(Hex(bytes, data + 8, 4), "00000000");
    // A missing sample is marked by residual -1.
    MarkerTrial gap = t;
    gap.positions(0, 0) = kNaN;
    ASSERT_TRUE(WriteC3d(path, gap, o).ok());
    EXPECT_EQ(Hex(ReadBytes(path), data + 12, 4), c.minus_one);
  }
}

// Integer storage: 16-bit counts times POINT:SCALE; a missing sample's 4th word is -1.
TEST(C3dRoundTrip, IntegerStorageWritesCountsAndResidualMinusOne) {
  MarkerTrial t;
  t.rate_hz = 50.0;
  t.marker_names = {"A", "B"};
  t.positions.resize(1, 6);
  t.positions << 0.3, -0.15, 0.0, kNaN, kNaN, kNaN;
  C3dWriteOptions o;
  o.integer_points = true;
  const std::string path = TmpPath(".c3d");
  ASSERT_TRUE(WriteC3d(path, t, o).ok());
  const std::string bytes = ReadBytes(path);
  float scale;
  std::memcpy(&scale, bytes.data() + 12, 4);  // header words 7-8, Intel
  EXPECT_FLOAT_EQ(scale, 300.0f / 30000.0f);   // positive: integers
  auto i16 = [&](size_t at) {
    return static_cast<int16_t>(static_cast<unsigned char>(bytes[at]) |
                                static_cast<unsigned char>(bytes[at + 1]) << 8);
  };
  const size_t data = 1024;
  EXPECT_EQ(i16(data), 30000);
  EXPECT_EQ(i16(data + 2), -15000);
  EXPECT_EQ(i16(data + 4), 0);
  EXPECT_EQ(i16(data + 6), 0);    // valid
  EXPECT_EQ(i16(data + 14), -1);  // B missing
}

// More than 255 markers continue in POINT:LABELS2; long labels survive.
TEST(C3dRoundTrip, ManyMarkersUseLabels2) {
  MarkerTrial t = MakeTrial(300, 3);
  t.marker_names[299] = "a_rather_long_marker_name_for_the_last_one";
  const std::string path = TmpPath(".c3d");
  ASSERT_TRUE(WriteC3d(path, t).ok());
  const std::string bytes = ReadBytes(path);
  EXPECT_NE(bytes.find("LABELS2"), std::string::npos);
  EXPECT_EQ(bytes.find("LABELS3"), std::string::npos);
  MarkerTrial back;
  const Status s = ReadC3d(path, &back);
  ASSERT_TRUE(s.ok()) << s.message();
  ExpectSameTrial(t, back, 1e-6);
}

// Past 65535 frames the header's last frame saturates; TRIAL:ACTUAL_*_FIELD carries the count.
TEST(C3dRoundTrip, MoreThan65535FramesUseTheTrialFields) {
  const MarkerTrial t = MakeTrial(1, 70000, 3, 1000.0);
  const std::string path = TmpPath(".c3d");
  ASSERT_TRUE(WriteC3d(path, t).ok());
  MarkerTrial back;
  const Status s = ReadC3d(path, &back);
  ASSERT_TRUE(s.ok()) << s.message();
  ASSERT_EQ(back.num_frames(), 70000);
  EXPECT_EQ(back.frame_numbers.back(), 70002);
  ExpectSameTrial(t, back, 1e-6);
}

TEST(C3dRoundTrip, ZeroFramesLoad) {
  const MarkerTrial t = MakeTrial(2, 0);
  const std::string path = TmpPath(".c3d");
  ASSERT_TRUE(WriteC3d(path, t).ok());
  MarkerTrial back;
  const Status s = ReadC3d(path, &back);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(back.num_frames(), 0);
  EXPECT_EQ(back.marker_names, t.marker_names);
}

// Prefixes: the part after the last ':' by default; repeats get _2; empty labels get P<n>.
TEST(C3dRoundTrip, LabelPrefixesRepeatsAndEmptyLabels) {
  MarkerTrial t = MakeTrial(4, 2);
  t.marker_names = {"Subj:Sess:LASI", "Other:LASI", "RASI", "P4x"};
  const std::string path = TmpPath(".c3d");
  ASSERT_TRUE(WriteC3d(path, t).ok());
  MarkerTrial stripped, kept;
  ASSERT_TRUE(ReadC3d(path, &stripped).ok());
  EXPECT_THAT(stripped.marker_names, ::testing::ElementsAre("LASI", "LASI_2", "RASI", "P4x"));
  C3dReadOptions keep;
  keep.strip_label_prefix = false;
  ASSERT_TRUE(ReadC3d(path, &kept, keep).ok());
  EXPECT_EQ(kept.marker_names, t.marker_names);

  // Blank the last label in the file: it reads as P4.
  std::string bytes = ReadBytes(path);
  const size_t at = Find(bytes, "P4x");
  bytes.replace(at, 3, "   ");
  WriteBytes(path, bytes);
  ASSERT_TRUE(ReadC3d(path, &stripped).ok());
  EXPECT_EQ(stripped.marker_names.back(), "P4");
}

// A lab's export holds its model's outputs as points too (Vicon Nexus: Plug-in Gait's joint
// angles, listed in POINT:ANGLES): they are not markers, so they are skipped and named, with or
// without the subject prefix, and the markers after them keep their own samples.
TEST(C3dRoundTrip, ModelOutputPointsAreNotReadAsMarkers) {
  MarkerTrial t = MakeTrial(4, 20);
  t.marker_names = {"Bob:RKNE", "Bob:LKneeAngles", "Bob:RANK", "LHipAngles"};
  C3dWriteOptions w;
  w.angle_points = {"Bob:LKneeAngles", "LHipAngles"};
  const std::string path = TmpPath("_angles.c3d");
  ASSERT_TRUE(WriteC3d(path, t, w).ok());
  MarkerTrial r;
  ASSERT_TRUE(ReadC3d(path, &r).ok());
  EXPECT_EQ(r.marker_names, (std::vector<std::string>{"RKNE", "RANK"}));
  EXPECT_EQ(r.skipped_points, (std::vector<std::string>{"Bob:LKneeAngles", "LHipAngles"}));
  ASSERT_EQ(r.positions.cols(), 6);
  for (int f = 0; f < t.num_frames(); ++f) {
    EXPECT_NEAR((r.At(f, 0) - t.At(f, 0)).norm(), 0.0, 1e-6) << f;
    if (t.Has(f, 2)) EXPECT_NEAR((r.At(f, 1) - t.At(f, 2)).norm(), 0.0, 1e-6) << f;
  }
  C3dReadOptions all;
  all.skip_model_outputs = false;
  ASSERT_TRUE(ReadC3d(path, &r, all).ok());
  EXPECT_EQ(r.marker_names, (std::vector<std::string>{"RKNE", "LKneeAngles", "RANK", "LHipAngles"}));
  EXPECT_TRUE(r.skipped_points.empty());
  // Nothing but model outputs: no markers, said so.
  w.angle_points = t.marker_names;
  ASSERT_TRUE(WriteC3d(path, t, w).ok());
  const Status none = ReadC3d(path, &r);
  ASSERT_FALSE(none.ok());
  EXPECT_THAT(none.message(), HasSubstr("every one of its 4 points is a model output"));
  w.angle_points = {"LKneeAngles"};  // not a label of the trial as written
  const Status bad = WriteC3d(path, t, w);
  ASSERT_FALSE(bad.ok());
  EXPECT_THAT(bad.message(), HasSubstr("angle point 'LKneeAngles' is not one of the trial's markers"));
}

TEST(C3dWrite, RejectsWhatC3dCannotHold) {
  const std::string path = TmpPath(".c3d");
  MarkerTrial t = MakeTrial(2, 5);
  t.frame_numbers[3] = 10;
  Status s = WriteC3d(path, t);
  EXPECT_THAT(s.message(), HasSubstr("consecutive"));
  t = MakeTrial(2, 5);
  t.marker_names[1] = "M0";
  EXPECT_THAT(WriteC3d(path, t).message(), HasSubstr("more than once"));
  t = MakeTrial(2, 5);
  t.positions(1, 1) = std::numeric_limits<double>::infinity();
  EXPECT_THAT(WriteC3d(path, t).message(), HasSubstr("infinite"));
  t = MakeTrial(2, 5);
  t.rate_hz = 0.0;
  EXPECT_THAT(WriteC3d(path, t).message(), HasSubstr("rate"));
  t = MakeTrial(2, 5);
  t.marker_names[0] = std::string(256, 'x');
  EXPECT_THAT(WriteC3d(path, t).message(), HasSubstr("255"));
  EXPECT_FALSE(WriteC3d(path, MarkerTrial()).ok());
  EXPECT_THAT(WriteC3d("/nonexistent-dir/x.c3d", MakeTrial(1, 1)).message(),
              HasSubstr("/nonexistent-dir/x.c3d"));
}

// ---------------------------------------------------------------- bad input

class C3dBad : public ::testing::Test {
 protected:
  void SetUp() override {
    good_ = TmpPath("_good.c3d");
    ASSERT_TRUE(WriteC3d(good_, MakeTrial(2, 100)).ok());
    bytes_ = ReadBytes(good_);
    ASSERT_EQ(bytes_.size(), 512u * 2 + 100 * 2 * 16 / 512 * 512 + 512);
  }
  // Writes `bytes` to a file, reads it, expects an error containing "PATH: " + each of `what`,
  // and that the trial was left unchanged.
  void ExpectError(const std::string& bytes, const std::vector<std::string>& what) {
    const std::string path = TmpPath("_bad.c3d");
    WriteBytes(path, bytes);
    MarkerTrial t;
    t.name = "untouched";
    const Status s = ReadC3d(path, &t);
    ASSERT_FALSE(s.ok());
    EXPECT_THAT(s.message(), HasSubstr(path + ": "));
    for (const std::string& w : what) EXPECT_THAT(s.message(), HasSubstr(w));
    EXPECT_EQ(t.name, "untouched");
  }
  std::string good_, bytes_;
};

TEST_F(C3dBad, TruncatedHeader) {
  ExpectError(bytes_.substr(0, 300), {"header: truncated", "300 bytes"});
  ExpectError("", {"header: truncated", "0 bytes"});
}

TEST_F(C3dBad, NotAC3dFile) {
  ExpectError("PathFileType\t4\t(X/Y/Z)\tt.trc\n" + std::string(600, 'x'),
              {"header (byte 1): not a C3D file", "0x61"});
}

TEST_F(C3dBad, TruncatedParameterSection) {
  ExpectError(bytes_.substr(0, 512 + 2), {"parameter section (block 2, byte 512): truncated"});
  ExpectError(bytes_.substr(0, 512 + 200),
              {"parameter section (block 2, byte 512): truncated", "1 blocks end at byte 1024",
               "only 712 bytes"});
}

TEST_F(C3dBad, UnknownProcessorType) {
  std::string b = bytes_;
  b[512 + 3] = 99;
  ExpectError(b, {"parameter section (block 2, byte 512)", "unknown processor type 99",
                  "84 Intel, 85 DEC or 86 MIPS"});
}

// The parameter section's block count points beyond the end of the file.
TEST_F(C3dBad, ParameterBlockCountBeyondTheFile) {
  std::string b = bytes_;
  b[512 + 2] = static_cast<char>(200);
  ExpectError(b, {"parameter section (block 2, byte 512): truncated", "200 blocks end at byte 102912",
                  "only " + std::to_string(bytes_.size()) + " bytes"});
  b = bytes_;
  b[0] = static_cast<char>(250);  // the header's parameter block beyond the file
  ExpectError(b, {"parameter section (block 250, byte 127488): truncated"});
}

// A parameter's dimensions claim more data than the section holds.
TEST_F(C3dBad, ParameterDataBeyondTheSection) {
  std::string b = bytes_;
  const size_t at = Find(b, "LABELS");  // name, offset (2), type, ndims, dims...
  ASSERT_EQ(b[at + 8], -1);
  ASSERT_EQ(b[at + 9], 2);
  b[at + 10] = static_cast<char>(255);
  b[at + 11] = static_cast<char>(255);
  ExpectError(b, {"parameter section, group POINT, parameter LABELS (byte " + std::to_string(at - 2) + ")",
                  "65025 bytes of data", "run past the end of the parameter section (byte 1024)"});
}

// A parameter's link to the next item points past the section.
TEST_F(C3dBad, ParameterOffsetBeyondTheSection) {
  std::string b = bytes_;
  const size_t at = Find(b, "SCALE");
  b[at + 5] = static_cast<char>(0xff);
  b[at + 6] = static_cast<char>(0x7f);
  ExpectError(b, {"group POINT, parameter SCALE", "the offset to the next item (32767)",
                  "past the end of the parameter section (byte 1024)"});
}

TEST_F(C3dBad, ParameterOfTheWrongTypeOrUnits) {
  std::string b = bytes_;
  size_t at = Find(b, "UNITS");
  ASSERT_EQ(b.substr(at + 10, 2), "mm");
  b.replace(at + 10, 2, "ft");
  ExpectError(b, {"parameter section, group POINT, parameter UNITS", "units 'ft' are not supported"});
  b = bytes_;
  at = Find(b, "USED");  // POINT:USED (int16) claimed to be text
  b[at + 6] = -1;
  ExpectError(b, {"group POINT, parameter USED", "is text, expected a number"});
  b = bytes_;
  b[at + 6] = 3;
  ExpectError(b, {"group POINT, parameter USED", "data type 3"});
}

TEST_F(C3dBad, TruncatedDataBlock) {
  // 2 markers x 16 bytes a frame from byte 1024: frame 41 starts at byte 2304, in block 5.
  ExpectError(bytes_.substr(0, 1024 + 40 * 32 + 7),
              {"data block 5 (byte 2304): truncated: frame 41 of 100", "needs 32 bytes",
               "ends at byte 2311"});
  // No data at all.
  ExpectError(bytes_.substr(0, 1024), {"data block 3 (byte 1024): truncated: frame 1 of 100"});
}

// A corrupt frame count cannot make the reader allocate more than the file holds.
TEST_F(C3dBad, AbsurdCountsAreBoundedByTheFileSize) {
  std::string b = bytes_;
  b[8] = static_cast<char>(0xfe);  // last frame 65534 (Intel: low byte first)
  b[9] = static_cast<char>(0xff);
  ExpectError(b, {"data block", "truncated", "of 65534"});
  b = bytes_;
  const size_t at = Find(b, "USED");  // POINT:USED = 65535 points
  b[at + 8] = static_cast<char>(0xff);
  b[at + 9] = static_cast<char>(0xff);
  ExpectError(b, {"data block 3 (byte 1024): truncated: frame 1 of 100", "needs 1048560 bytes"});
  b = bytes_;
  b[at + 8] = 0;
  b[at + 9] = 0;
  ExpectError(b, {"group POINT, parameter USED", "no 3D points"});
}

TEST_F(C3dBad, DataStartInsideTheHeader) {
  std::string b = bytes_;
  b[16] = 1;  // word 9
  b[17] = 0;
  ExpectError(b, {"header (word 9)", "data start block 1"});
}

TEST_F(C3dBad, MissingFile) {
  MarkerTrial t;
  const Status s = ReadC3d(TmpPath("_absent.c3d"), &t);
  EXPECT_THAT(s.message(), HasSubstr(TmpPath("_absent.c3d") + ": cannot open file"));
}

// Random corruption and truncation of a valid file: every outcome is a Status, never a crash
// (the libFuzzer target in fuzz/ explores this far more under AddressSanitizer).
TEST_F(C3dBad, RandomCorruptionNeverCrashes) {
  std::mt19937 rng(12345);
  int errors = 0;
  for (int trial = 0; trial < 3000; ++trial) {
    std::string b = bytes_;
    const int flips = 1 + static_cast<int>(rng() % 8);
    for (int k = 0; k < flips; ++k) {
      // Mostly the header and parameter section, where the structure is.
      const size_t limit = (rng() % 4 == 0) ? b.size() : 1024;
      b[rng() % limit] = static_cast<char>(rng());
    }
    if (rng() % 3 == 0) b.resize(rng() % b.size());
    MarkerTrial t;
    const Status s = ParseC3d(b, "mutant.c3d", &t);
    if (!s.ok()) {
      ++errors;
      EXPECT_EQ(s.message().rfind("mutant.c3d: ", 0), 0u) << s.message();
    } else {
      EXPECT_EQ(t.positions.cols(), 3 * t.num_markers());
      EXPECT_EQ(static_cast<int>(t.frame_numbers.size()), t.num_frames());
    }
  }
  EXPECT_GT(errors, 100);  // the corruption did reach the checks
}

// ---------------------------------------------------------------- mocap convert

// C3D -> TRC -> C3D -> TRC: the TRC has the C3D's values (to its 5 decimals of mm), and so has
// the TRC made from the C3D made from it.
TEST(C3dConvert, C3dToTrcAndBack) {
  const MarkerTrial t = MakeTrial(3, 40, 11, 120.0);
  const std::string c3d = TmpPath(".c3d"), trc = TmpPath(".trc"), c3d2 = TmpPath("_2.C3D"),
                    trc2 = TmpPath("_2.trc");
  ASSERT_TRUE(WriteC3d(c3d, t).ok());
  CommandResult r = Mocap("convert " + c3d + " " + trc);
  ASSERT_EQ(r.status, 0) << r.output;
  EXPECT_THAT(r.output, HasSubstr("40 frames, 3 markers at 120 Hz, " +
                                  std::to_string(CountMissing(t)) + " missing samples"));
  MarkerTrial from_c3d, from_trc;
  ASSERT_TRUE(ReadC3d(c3d, &from_c3d).ok());
  const Status s = ReadTrc(trc, &from_trc);
  ASSERT_TRUE(s.ok()) << s.message();
  ExpectSameTrial(from_c3d, from_trc, 0.6e-8);
  r = Mocap("convert " + trc + " " + c3d2);
  ASSERT_EQ(r.status, 0) << r.output;
  r = Mocap("convert " + c3d2 + " " + trc2);
  ASSERT_EQ(r.status, 0) << r.output;
  MarkerTrial again;
  ASSERT_TRUE(ReadTrc(trc2, &again).ok());
  ExpectSameTrial(from_trc, again, 1.1e-8);
}

TEST(C3dConvert, RealFileMatchesItsDerivedTrc) {
  SKIP_WITHOUT_SHARED_DATA();
  const std::string dir = SharedData() + "/welk007_hipfunc/";
  const std::string trc = TmpPath(".trc");
  const CommandResult r = Mocap("convert " + dir + "c3d_Trimmed_static1.c3d " + trc);
  ASSERT_EQ(r.status, 0) << r.output;
  MarkerTrial ours, derived;
  ASSERT_TRUE(ReadTrc(trc, &ours).ok());
  ASSERT_TRUE(ReadTrc(dir + "derived_trc/c3d_Trimmed_static1.trc", &derived).ok());
  ExpectSameTrial(derived, ours, 1e-6);  // 0.001 mm
  const CommandResult k = Mocap("convert --keep-label-prefix " + dir + "c3d_Trimmed_static1.c3d " + trc);
  ASSERT_EQ(k.status, 0) << k.output;
  ASSERT_TRUE(ReadTrc(trc, &ours).ok());
  EXPECT_EQ(ours.marker_names.front(), "FullBody_static:r_knee");
}

TEST(C3dConvert, ErrorsExitNonZeroAndNameTheFile) {
  const std::string c3d = TmpPath(".c3d"), trc = TmpPath(".trc");
  ASSERT_TRUE(WriteC3d(c3d, MakeTrial(2, 5)).ok());
  fs::remove(trc);
  // Usage errors: 2.
  CommandResult r = Mocap("convert " + c3d);
  EXPECT_EQ(r.status, 2) << r.output;
  r = Mocap("convert " + c3d + " " + TmpPath(".txt"));
  EXPECT_EQ(r.status, 2);
  EXPECT_THAT(r.output, HasSubstr(TmpPath(".txt") + ": unknown file type"));
  r = Mocap("convert " + c3d + " " + trc + " --units ft");
  EXPECT_EQ(r.status, 2) << r.output;
  r = Mocap("convert " + c3d + " " + c3d);
  EXPECT_EQ(r.status, 2);
  EXPECT_THAT(r.output, HasSubstr("both the input and the output"));
  // Input that cannot be read: 1, with the reader's message.
  r = Mocap("convert " + TmpPath("_absent.c3d") + " " + trc);
  EXPECT_EQ(r.status, 1);
  EXPECT_THAT(r.output, HasSubstr(TmpPath("_absent.c3d") + ": cannot open file"));
  std::string bytes = ReadBytes(c3d);
  bytes[512 + 3] = 80;
  const std::string corrupt = TmpPath("_corrupt.c3d");
  WriteBytes(corrupt, bytes);
  r = Mocap("convert " + corrupt + " " + trc);
  EXPECT_EQ(r.status, 1);
  EXPECT_THAT(r.output, HasSubstr(corrupt + ": parameter section (block 2, byte 512): unknown processor type 80"));
  EXPECT_FALSE(fs::exists(trc)) << "nothing written on error";
  r = Mocap("convert " + c3d + " /nonexistent-dir/out.trc");
  EXPECT_EQ(r.status, 1);
  EXPECT_THAT(r.output, HasSubstr("/nonexistent-dir/out.trc"));
}

}  // namespace
