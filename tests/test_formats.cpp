// Tests of formats/: TRC and MOT readers and writers, on the real files in ../shared/data and on
// small files written here (round trips, tolerated oddities, and every rejected input).
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <limits>
#include <string>
#include <vector>

#include "formats/marker_data.h"
#include "formats/mot.h"
#include "formats/trc.h"
#include "tests/file_test_util.h"

namespace fs = std::filesystem;
using mocap::Status;
using mocap::formats::CoordinateTable;
using mocap::formats::MarkerTrial;
using mocap::formats::ReadMot;
using mocap::formats::ReadTrc;
using mocap::formats::TrcWriteOptions;
using mocap::formats::WriteMot;
using mocap::formats::WriteTrc;
using ::testing::HasSubstr;

namespace {

const double kNaN = std::numeric_limits<double>::quiet_NaN();

using mocap::testutil::SharedData;

std::string TmpPath(const std::string& suffix) { return mocap::testutil::TmpPath("formats", suffix); }

std::string WriteText(const std::string& suffix, const std::string& text) {
  const std::string path = TmpPath(suffix);
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out << text;
  return path;
}

// The status failed and its message names the file and "FILE:LINE:" and contains `what`.
void ExpectErrorAt(const Status& s, const std::string& path, int line, const std::string& what) {
  EXPECT_FALSE(s.ok()) << "expected an error for " << path;
  EXPECT_THAT(s.message(), HasSubstr(path + ":" + std::to_string(line) + ":"));
  EXPECT_THAT(s.message(), HasSubstr(what));
}

// Header of a small valid TRC with markers A and B, mm, 100 Hz; rows are appended by the tests.
std::string TrcHead(int num_frames, int num_markers = 2, const std::string& units = "mm",
                    const std::string& names = "A\t\t\tB\t\t") {
  return "PathFileType\t4\t(X/Y/Z)\tt.trc\n"
         "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\t"
         "OrigNumFrames\n"
         "100\t100\t" + std::to_string(num_frames) + "\t" + std::to_string(num_markers) + "\t" +
         units + "\t100\t1\t" + std::to_string(num_frames) + "\n"
         "Frame#\tTime\t" + names + "\n"
         "\t\tX1\tY1\tZ1\tX2\tY2\tZ2\n"
         "\n";
}

int CountMissing(const MarkerTrial& t, int m) {
  int n = 0;
  for (int f = 0; f < t.num_frames(); ++f) n += !t.Has(f, m);
  return n;
}

// Same values, NaN where NaN, bit for bit otherwise.
void ExpectSamePositions(const MarkerTrial& a, const MarkerTrial& b) {
  ASSERT_EQ(a.positions.rows(), b.positions.rows());
  ASSERT_EQ(a.positions.cols(), b.positions.cols());
  for (int f = 0; f < a.positions.rows(); ++f) {
    for (int k = 0; k < a.positions.cols(); ++k) {
      const double x = a.positions(f, k), y = b.positions(f, k);
      if (std::isnan(x) || std::isnan(y)) {
        ASSERT_TRUE(std::isnan(x) && std::isnan(y)) << "frame " << f << " column " << k;
      } else {
        ASSERT_EQ(x, y) << "frame " << f << " column " << k;
      }
    }
  }
}

// ---------------------------------------------------------------- marker_data

TEST(MarkerData, FindMarkerHasAndFindColumn) {
  MarkerTrial t;
  t.marker_names = {"R.ASIS", "L.ASIS"};
  t.positions.resize(2, 6);
  t.positions << 1, 2, 3, 4, 5, 6,
                 7, 8, 9, kNaN, kNaN, kNaN;
  EXPECT_EQ(t.FindMarker("R.ASIS"), 0);
  EXPECT_EQ(t.FindMarker("L.ASIS"), 1);
  EXPECT_EQ(t.FindMarker("l.asis"), -1);  // exact names only
  EXPECT_EQ(t.FindMarker("V.Sacral"), -1);
  EXPECT_TRUE(t.Has(0, 1));
  EXPECT_FALSE(t.Has(1, 1));
  EXPECT_TRUE(t.Has(1, 0));
  EXPECT_FALSE(t.Has(2, 0));   // out of range frame
  EXPECT_FALSE(t.Has(0, 2));   // out of range marker
  EXPECT_FALSE(t.Has(-1, 0));
  t.positions(0, 1) = std::numeric_limits<double>::infinity();
  EXPECT_FALSE(t.Has(0, 0));
  EXPECT_EQ(t.At(0, 1), Eigen::Vector3d(4, 5, 6));

  CoordinateTable c;
  c.column_names = {"hip_flexion_r", "knee_angle_r"};
  EXPECT_EQ(c.FindColumn("knee_angle_r"), 1);
  EXPECT_EQ(c.FindColumn("time"), -1);
}

// ---------------------------------------------------------------- real TRC files

struct RealTrc {
  std::string rel;
  int markers;
  int frames;
  double rate;
  int missing_samples;  // marker-frames without a sample
};

TEST(TrcReal, EveryRealFileLoadsWithItsHeaderCounts) {
  SKIP_WITHOUT_SHARED_DATA();
  const std::vector<RealTrc> files = {
      {"opensim_gait2354_subject01/subject01_static.trc", 49, 300, 60.0, 0},
      {"opensim_gait2354_subject01/subject01_walk1.trc", 41, 151, 60.0, 0},
      {"welk007_hipfunc/derived_trc/c3d_Trimmed_static1.trc", 54, 297, 100.0, 0},
      {"welk007_hipfunc/derived_trc/c3d_Trimmed_RHJC1.trc", 48, 1224, 100.0, 0},
      {"biobuddy_p01_lowerlimb/derived_trc/anatomical_posture.trc", 60, 122, 12.0, 1},
      {"biobuddy_p01_lowerlimb/derived_trc/Test_func_lhip.trc", 60, 489, 12.0, 5},
      {"biobuddy_p01_lowerlimb/derived_trc/Test_func_rhip.trc", 60, 525, 12.0, 8},
      {"biobuddy_p01_lowerlimb/derived_trc/Test_func_lknee.trc", 60, 216, 12.0, 0},
      {"biobuddy_p01_lowerlimb/derived_trc/Test_func_rknee.trc", 60, 217, 12.0, 0},
  };
  for (const RealTrc& r : files) {
    SCOPED_TRACE(r.rel);
    MarkerTrial t;
    const Status s = ReadTrc(SharedData() + "/" + r.rel, &t);
    ASSERT_TRUE(s.ok()) << s.message();
    EXPECT_EQ(t.name, fs::path(r.rel).stem().string());
    EXPECT_EQ(t.num_markers(), r.markers);
    EXPECT_EQ(t.num_frames(), r.frames);
    EXPECT_EQ(t.positions.cols(), 3 * r.markers);
    EXPECT_EQ(t.rate_hz, r.rate);
    ASSERT_EQ(static_cast<int>(t.frame_numbers.size()), r.frames);
    ASSERT_EQ(static_cast<int>(t.times.size()), r.frames);
    EXPECT_EQ(t.frame_numbers.front(), 1);
    EXPECT_EQ(t.frame_numbers.back(), r.frames);
    EXPECT_EQ(t.times.front(), 0.0);
    int missing = 0;
    for (int m = 0; m < t.num_markers(); ++m) missing += CountMissing(t, m);
    EXPECT_EQ(missing, r.missing_samples);
    // Every present sample is within a 5 m cube: the mm -> m conversion happened.
    for (int f = 0; f < t.num_frames(); ++f) {
      for (int m = 0; m < t.num_markers(); ++m) {
        if (t.Has(f, m)) {
          ASSERT_LT(t.At(f, m).cwiseAbs().maxCoeff(), 5.0);
        }
      }
    }
  }
}

TEST(TrcReal, GaitStaticValues) {
  SKIP_WITHOUT_SHARED_DATA();
  MarkerTrial t;
  const Status s = ReadTrc(SharedData() + "/opensim_gait2354_subject01/subject01_static.trc", &t);
  ASSERT_TRUE(s.ok()) << s.message();
  ASSERT_EQ(t.num_markers(), 49);
  EXPECT_EQ(t.marker_names.front(), "R.ASIS");
  EXPECT_EQ(t.marker_names.back(), "Top.Head");
  const int rasis = t.FindMarker("R.ASIS");
  ASSERT_EQ(rasis, 0);
  // line 7: "1  0.000000  608.664310  1072.713130  157.442150 ..." (mm)
  EXPECT_DOUBLE_EQ(t.At(0, rasis).x(), 0.608664310);
  EXPECT_DOUBLE_EQ(t.At(0, rasis).y(), 1.072713130);
  EXPECT_DOUBLE_EQ(t.At(0, rasis).z(), 0.157442150);
  // line 8: L.ASIS z = -103.827290 mm
  EXPECT_DOUBLE_EQ(t.At(1, t.FindMarker("L.ASIS")).z(), -0.103827290);
  // last line: "300  4.983000  602.003660  1073.367190  157.648210"
  EXPECT_EQ(t.frame_numbers.back(), 300);
  EXPECT_DOUBLE_EQ(t.times.back(), 4.983);
  EXPECT_DOUBLE_EQ(t.At(299, rasis).x(), 0.602003660);
  EXPECT_DOUBLE_EQ(t.At(299, rasis).y(), 1.073367190);
  EXPECT_DOUBLE_EQ(t.At(299, rasis).z(), 0.157648210);
  // The static trial has the medial markers the walk lacks.
  EXPECT_GE(t.FindMarker("R.Knee.Med"), 0);
  EXPECT_GE(t.FindMarker("L.Ankle.Med"), 0);
}

TEST(TrcReal, GaitWalkValues) {
  SKIP_WITHOUT_SHARED_DATA();
  MarkerTrial t;
  const Status s = ReadTrc(SharedData() + "/opensim_gait2354_subject01/subject01_walk1.trc", &t);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(t.FindMarker("R.Knee.Med"), -1);
  EXPECT_EQ(t.FindMarker("R.Ankle.Med"), -1);
  const int rasis = t.FindMarker("R.ASIS");
  ASSERT_GE(rasis, 0);
  EXPECT_DOUBLE_EQ(t.At(0, rasis).x(), 0.617247620);
  EXPECT_DOUBLE_EQ(t.At(0, rasis).y(), 1.055275020);
  EXPECT_DOUBLE_EQ(t.At(0, rasis).z(), 0.170781980);
  EXPECT_DOUBLE_EQ(t.times[1], 0.017);  // the file's times are rounded to the millisecond
  EXPECT_DOUBLE_EQ(t.times.back(), 2.5);
  EXPECT_DOUBLE_EQ(t.At(150, rasis).x(), 0.597613650);
}

TEST(TrcReal, WelkValues) {
  SKIP_WITHOUT_SHARED_DATA();
  MarkerTrial st, rhjc;
  Status s = ReadTrc(SharedData() + "/welk007_hipfunc/derived_trc/c3d_Trimmed_static1.trc", &st);
  ASSERT_TRUE(s.ok()) << s.message();
  s = ReadTrc(SharedData() + "/welk007_hipfunc/derived_trc/c3d_Trimmed_RHJC1.trc", &rhjc);
  ASSERT_TRUE(s.ok()) << s.message();
  ASSERT_EQ(st.FindMarker("r_knee"), 0);
  EXPECT_DOUBLE_EQ(st.At(0, 0).x(), 0.930260);
  EXPECT_DOUBLE_EQ(st.At(0, 0).y(), 0.474909);
  EXPECT_DOUBLE_EQ(st.At(0, 0).z(), 0.494998);
  EXPECT_GE(st.FindMarker("r_mknee"), 0);
  EXPECT_EQ(rhjc.FindMarker("r_mknee"), -1);
  EXPECT_EQ(rhjc.FindMarker("r_band"), -1);
  ASSERT_EQ(rhjc.FindMarker("r_knee"), 0);
  EXPECT_DOUBLE_EQ(rhjc.At(0, 0).x(), 1.040920);
  EXPECT_DOUBLE_EQ(rhjc.At(1223, 0).x(), 1.028720);
  EXPECT_DOUBLE_EQ(rhjc.At(1223, 0).y(), 0.853020);
  EXPECT_DOUBLE_EQ(rhjc.At(1223, 0).z(), 0.484528);
  EXPECT_DOUBLE_EQ(rhjc.times.back(), 12.23);
}

TEST(TrcReal, BiobuddyMissingSamplesAreNaN) {
  SKIP_WITHOUT_SHARED_DATA();
  const std::string dir = SharedData() + "/biobuddy_p01_lowerlimb/derived_trc/";
  MarkerTrial lhip, rhip, anat;
  Status s = ReadTrc(dir + "Test_func_lhip.trc", &lhip);
  ASSERT_TRUE(s.ok()) << s.message();
  s = ReadTrc(dir + "Test_func_rhip.trc", &rhip);
  ASSERT_TRUE(s.ok()) << s.message();
  s = ReadTrc(dir + "anatomical_posture.trc", &anat);
  ASSERT_TRUE(s.ok()) << s.message();

  // lhip: LBHD is the last (60th) marker and has no sample in frames 1-5 (empty fields).
  EXPECT_DOUBLE_EQ(lhip.rate_hz, 12.0);
  const int lbhd = lhip.FindMarker("LBHD");
  ASSERT_EQ(lbhd, 59);
  for (int f = 0; f < 5; ++f) {
    EXPECT_FALSE(lhip.Has(f, lbhd)) << f;
    EXPECT_TRUE(std::isnan(lhip.positions(f, 3 * lbhd)));
    EXPECT_TRUE(std::isnan(lhip.positions(f, 3 * lbhd + 1)));
    EXPECT_TRUE(std::isnan(lhip.positions(f, 3 * lbhd + 2)));
  }
  EXPECT_EQ(CountMissing(lhip, lbhd), 5);
  // line 12 (frame 6): "... -495.207  -129.948  -1699.754"
  ASSERT_TRUE(lhip.Has(5, lbhd));
  EXPECT_DOUBLE_EQ(lhip.At(5, lbhd).x(), -0.495207);
  EXPECT_DOUBLE_EQ(lhip.At(5, lbhd).y(), -0.129948);
  EXPECT_DOUBLE_EQ(lhip.At(5, lbhd).z(), -1.699754);
  // First sample of the file: S3 = (-523.339, -56.695, -1109.246) mm; vertical is -Z.
  ASSERT_EQ(lhip.FindMarker("S3"), 0);
  EXPECT_DOUBLE_EQ(lhip.At(0, 0).x(), -0.523339);
  EXPECT_DOUBLE_EQ(lhip.At(0, 0).y(), -0.056695);
  EXPECT_DOUBLE_EQ(lhip.At(0, 0).z(), -1.109246);
  EXPECT_NEAR(lhip.times[1], 1.0 / 12.0, 1e-6);

  // rhip: RKNEM (16th marker) missing in frames 268 286 416 440 441 444 459 465.
  const int rkne = rhip.FindMarker("RKNEM");
  ASSERT_EQ(rkne, 15);
  EXPECT_EQ(CountMissing(rhip, rkne), 8);
  for (int frame : {268, 286, 416, 440, 441, 444, 459, 465}) {
    EXPECT_FALSE(rhip.Has(frame - 1, rkne)) << frame;
  }
  ASSERT_TRUE(rhip.Has(0, rkne));
  EXPECT_DOUBLE_EQ(rhip.At(0, rkne).x(), -0.496969);  // line 7 columns 48-50
  EXPECT_DOUBLE_EQ(rhip.At(0, rkne).z(), -0.501819);
  // Marker order differs between trials of this set: LBHD is 24th in rhip, last in lhip.
  EXPECT_EQ(rhip.FindMarker("LBHD"), 23);

  EXPECT_FALSE(anat.Has(0, anat.FindMarker("LBHD")));
  EXPECT_TRUE(anat.Has(1, anat.FindMarker("LBHD")));
}

TEST(TrcReal, RealFilesRoundTripExactly) {
  SKIP_WITHOUT_SHARED_DATA();
  // The gait files carry 6 decimals (mm), the others 3: writing with 6 decimals in mm
  // reproduces every value bit for bit.
  for (const char* rel : {"opensim_gait2354_subject01/subject01_walk1.trc",
                          "biobuddy_p01_lowerlimb/derived_trc/Test_func_lhip.trc"}) {
    SCOPED_TRACE(rel);
    MarkerTrial a, b;
    Status s = ReadTrc(SharedData() + "/" + rel, &a);
    ASSERT_TRUE(s.ok()) << s.message();
    const std::string out = TmpPath("_" + fs::path(rel).stem().string() + ".trc");
    TrcWriteOptions opt;
    opt.units = "mm";
    opt.decimals = 6;
    s = WriteTrc(out, a, opt);
    ASSERT_TRUE(s.ok()) << s.message();
    s = ReadTrc(out, &b);
    ASSERT_TRUE(s.ok()) << s.message();
    EXPECT_EQ(b.marker_names, a.marker_names);
    EXPECT_EQ(b.frame_numbers, a.frame_numbers);
    EXPECT_EQ(b.times, a.times);
    EXPECT_EQ(b.rate_hz, a.rate_hz);
    ExpectSamePositions(a, b);
  }
}

// ---------------------------------------------------------------- TRC round trips

MarkerTrial SyntheticTrial() {
  MarkerTrial t;
  t.name = "synthetic";
  t.rate_hz = 120.0;
  t.marker_names = {"LASI", "RASI", "Marker With Space", "LKNE"};
  const int nf = 7;
  t.positions.resize(nf, 12);
  for (int f = 0; f < nf; ++f) {
    t.frame_numbers.push_back(11 + f);
    t.times.push_back(f / 120.0 + 0.25);
    for (int k = 0; k < 12; ++k) {
      // values with at most 5 decimals in mm, some negative, some large
      t.positions(f, k) = std::round((std::sin(0.37 * f + 1.3 * k) * 1234.56789) * 1e5) / 1e5 / 1000.0;
    }
  }
  // missing samples: a whole marker-frame, the first and last frame, and a half-missing one
  for (int c = 0; c < 3; ++c) {
    t.positions(2, 3 * 1 + c) = kNaN;
    t.positions(0, 3 * 3 + c) = kNaN;
    t.positions(nf - 1, 3 * 0 + c) = kNaN;
  }
  t.positions(4, 3 * 2 + 1) = kNaN;  // only y missing: the whole sample is missing
  return t;
}

TEST(TrcRoundTrip, MissingSamplesInMillimetres) {
  const MarkerTrial t = SyntheticTrial();
  const std::string path = TmpPath(".trc");
  Status s = WriteTrc(path, t);  // default: mm, 5 decimals
  ASSERT_TRUE(s.ok()) << s.message();
  MarkerTrial r;
  s = ReadTrc(path, &r);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(r.name, fs::path(path).stem().string());
  EXPECT_EQ(r.rate_hz, 120.0);
  EXPECT_EQ(r.marker_names, t.marker_names);
  EXPECT_EQ(r.frame_numbers, t.frame_numbers);
  EXPECT_EQ(r.times, t.times);  // times are written in shortest exact form
  ASSERT_EQ(r.num_frames(), t.num_frames());
  for (int f = 0; f < t.num_frames(); ++f) {
    for (int m = 0; m < t.num_markers(); ++m) {
      ASSERT_EQ(r.Has(f, m), t.Has(f, m)) << "frame " << f << " marker " << m;
      if (!t.Has(f, m)) {
        EXPECT_TRUE(r.positions.row(f).segment<3>(3 * m).array().isNaN().all());
        continue;
      }
      for (int c = 0; c < 3; ++c) {
        // values had 5 decimals in mm: they come back within rounding of the double
        EXPECT_NEAR(r.positions(f, 3 * m + c), t.positions(f, 3 * m + c), 1e-12);
      }
    }
  }
  EXPECT_FALSE(r.Has(4, 2));
  EXPECT_EQ(CountMissing(r, 1), 1);
  // A second write of what was read is byte-identical: the format is a fixed point.
  const std::string path2 = TmpPath("_again.trc");
  ASSERT_TRUE(WriteTrc(path2, r).ok());
  MarkerTrial r2;
  ASSERT_TRUE(ReadTrc(path2, &r2).ok());
  ExpectSamePositions(r, r2);
  std::ifstream a(path), b(path2);
  std::string sa((std::istreambuf_iterator<char>(a)), {}), sb((std::istreambuf_iterator<char>(b)), {});
  // only the file name on line 1 differs
  EXPECT_EQ(sa.substr(sa.find('\n')), sb.substr(sb.find('\n')));
}

TEST(TrcRoundTrip, MetresAndLayout) {
  MarkerTrial t = SyntheticTrial();
  const std::string path = TmpPath(".trc");
  TrcWriteOptions opt;
  opt.units = "m";
  opt.decimals = 8;
  Status s = WriteTrc(path, t, opt);
  ASSERT_TRUE(s.ok()) << s.message();
  std::ifstream in(path);
  std::vector<std::string> lines;
  for (std::string l; std::getline(in, l);) lines.push_back(l);
  ASSERT_GE(lines.size(), 7u);
  EXPECT_EQ(lines[0], "PathFileType\t4\t(X/Y/Z)\t" + fs::path(path).filename().string());
  EXPECT_EQ(lines[1],
            "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\t"
            "OrigNumFrames");
  EXPECT_EQ(lines[2], "120\t120\t7\t4\tm\t120\t11\t7");
  EXPECT_EQ(lines[3], "Frame#\tTime\tLASI\t\t\tRASI\t\t\tMarker With Space\t\t\tLKNE\t\t");
  EXPECT_EQ(lines[4], "\t\tX1\tY1\tZ1\tX2\tY2\tZ2\tX3\tY3\tZ3\tX4\tY4\tZ4");
  EXPECT_EQ(lines[5], "");
  EXPECT_EQ(lines.size(), 6u + 7u);
  // frame 11: marker LKNE missing -> three empty fields at the end
  EXPECT_THAT(lines[6], ::testing::StartsWith("11\t0.25\t"));
  EXPECT_THAT(lines[6], ::testing::EndsWith("\t\t\t"));

  MarkerTrial r;
  s = ReadTrc(path, &r);
  ASSERT_TRUE(s.ok()) << s.message();
  for (int f = 0; f < t.num_frames(); ++f) {
    for (int k = 0; k < 12; ++k) {
      if (!t.Has(f, k / 3)) continue;
      EXPECT_NEAR(r.positions(f, k), t.positions(f, k), 0.5e-8 + 1e-15);
    }
  }
}

TEST(TrcRoundTrip, ZeroFramesLoads) {
  MarkerTrial t = SyntheticTrial();
  t.positions.resize(0, 12);
  t.frame_numbers.clear();
  t.times.clear();
  const std::string path = TmpPath(".trc");
  ASSERT_TRUE(WriteTrc(path, t).ok());
  MarkerTrial r;
  const Status s = ReadTrc(path, &r);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(r.num_frames(), 0);
  EXPECT_EQ(r.num_markers(), 4);
  EXPECT_EQ(r.positions.cols(), 12);
}

TEST(TrcRoundTrip, MissingFrameNumbersAndTimesAreMadeUp) {
  MarkerTrial t = SyntheticTrial();
  t.frame_numbers.clear();
  t.times.clear();
  const std::string path = TmpPath(".trc");
  ASSERT_TRUE(WriteTrc(path, t).ok());
  MarkerTrial r;
  ASSERT_TRUE(ReadTrc(path, &r).ok());
  ASSERT_EQ(r.num_frames(), 7);
  EXPECT_EQ(r.frame_numbers.front(), 1);
  EXPECT_EQ(r.frame_numbers.back(), 7);
  EXPECT_DOUBLE_EQ(r.times[3], 3.0 / 120.0);
}

TEST(TrcWrite, RejectsBadInput) {
  const std::string path = TmpPath(".trc");
  MarkerTrial t = SyntheticTrial();
  TrcWriteOptions opt;
  opt.units = "inch";
  Status s = WriteTrc(path, t, opt);
  EXPECT_FALSE(s.ok());
  EXPECT_THAT(s.message(), HasSubstr(path));
  EXPECT_THAT(s.message(), HasSubstr("inch"));

  MarkerTrial bad_cols = t;
  bad_cols.marker_names.pop_back();
  s = WriteTrc(path, bad_cols);
  EXPECT_FALSE(s.ok());
  EXPECT_THAT(s.message(), HasSubstr("columns"));

  MarkerTrial inf = t;
  inf.positions(3, 4) = std::numeric_limits<double>::infinity();
  s = WriteTrc(path, inf);
  EXPECT_FALSE(s.ok());
  EXPECT_THAT(s.message(), HasSubstr("RASI Y"));

  MarkerTrial tab = t;
  tab.marker_names[0] = "A\tB";
  EXPECT_FALSE(WriteTrc(path, tab).ok());

  MarkerTrial dup = t;
  dup.marker_names[1] = dup.marker_names[0];
  EXPECT_FALSE(WriteTrc(path, dup).ok());

  MarkerTrial none;
  none.rate_hz = 100;
  EXPECT_FALSE(WriteTrc(path, none).ok());

  EXPECT_FALSE(WriteTrc(TmpPath("_no_such_dir") + "/x.trc", t).ok());
}

// ---------------------------------------------------------------- TRC tolerance

TEST(TrcTolerance, CrlfPaddingTrailingTabsBlankLinesShortRowsNanAndMetres) {
  const std::string text =
      "PathFileType\t4\t(X/Y/Z)\tweird.trc\t\r\n"
      "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\t"
      "OrigNumFrames\t\r\n"
      " 200.00 \t 200.00\t       5\t  3 \tm\t200.00\t1\t       5\t\t\r\n"
      "\r\n"
      "Frame#\tTime\tA\t\t\tB\t\t\tC\t\t\t\r\n"
      "\t\tX1\tY1\tZ1\tX2\tY2\tZ2\tX3\tY3\tZ3\t\r\n"
      "\r\n"
      "1\t0.000\t0.1\t0.2\t0.3\t1.1\t1.2\t1.3\t2.1\t2.2\t2.3\t\r\n"
      "2\t0.005\t0.1\t\t0.3\t1.1\t1.2\t1.3\t 2.1 \t2.2\t+2.3\t\r\n"   // A half-empty -> missing
      "\r\n"                                                           // blank line in the data
      "3\t0.010\t0.1\t0.2\t0.3\tnan\tNaN\t-nan\t2.1\t2.2\t2.3\r\n"     // B nan -> missing
      "4\t0.015\t0.1\t0.2\t0.3\t1.1\r\n"                               // cut short: B, C missing
      "5\t0.020\t1e-1\t2E-1\t.3\t1.1\t1.2\t1.3\t\t\t\r\n";             // C empty
  const std::string path = WriteText(".trc", text);
  MarkerTrial t;
  const Status s = ReadTrc(path, &t);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(t.rate_hz, 200.0);
  EXPECT_EQ(t.marker_names, (std::vector<std::string>{"A", "B", "C"}));
  ASSERT_EQ(t.num_frames(), 5);
  EXPECT_EQ(t.frame_numbers, (std::vector<int>{1, 2, 3, 4, 5}));
  EXPECT_DOUBLE_EQ(t.times[4], 0.02);
  // units m: no conversion
  EXPECT_EQ(t.At(0, 0), Eigen::Vector3d(0.1, 0.2, 0.3));
  EXPECT_EQ(t.At(0, 2), Eigen::Vector3d(2.1, 2.2, 2.3));
  EXPECT_FALSE(t.Has(1, 0));
  EXPECT_TRUE(std::isnan(t.positions(1, 0)));  // x was present but the sample is incomplete
  EXPECT_EQ(t.At(1, 2), Eigen::Vector3d(2.1, 2.2, 2.3));
  EXPECT_FALSE(t.Has(2, 1));
  EXPECT_TRUE(t.Has(2, 2));
  EXPECT_TRUE(t.Has(3, 0));
  EXPECT_FALSE(t.Has(3, 1));
  EXPECT_FALSE(t.Has(3, 2));
  EXPECT_EQ(t.At(4, 0), Eigen::Vector3d(0.1, 0.2, 0.3));
  EXPECT_FALSE(t.Has(4, 2));
}

TEST(TrcTolerance, NoCoordinateLabelLineAndCentimetres) {
  const std::string text =
      "PathFileType\t4\t(X/Y/Z)\tx.trc\n"
      "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\n"
      "50\t50\t1\t1\tcm\n"
      "Frame#\tTime\tP\n"
      "1\t0\t10\t20\t-30\n";
  const std::string path = WriteText(".trc", text);
  MarkerTrial t;
  const Status s = ReadTrc(path, &t);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_DOUBLE_EQ(t.At(0, 0).x(), 0.1);
  EXPECT_DOUBLE_EQ(t.At(0, 0).z(), -0.3);
}

// ---------------------------------------------------------------- TRC as other tools write it
//
// Headers as each tool writes them (from the formats' documentation and the writers' published
// behaviour), each with 3 frames of markers A (or the tool's names) and B: B is missing in frame 2.
// What OpenSim's TRCFileAdapter reads, we read: its header line is split at spaces and tabs, the
// other lines at tabs with empty fields dropped, and NumFrames is not checked against the rows.

struct TrcVariant {
  std::string writer;
  std::string text;
  std::vector<std::string> names;
  double rate_hz;
  double metres_per_unit;  // the file's unit
  int first_frame;
};

// Rows of the three frames: A at (10, 20, 30) + f, B at (-5, 0.5, 1000) + f, B missing in frame 2.
std::string TrcVariantRows(int first_frame, double rate, const std::string& sep,
                           const std::string& eol, bool trailing_sep) {
  std::string rows;
  for (int f = 0; f < 3; ++f) {
    const std::string n = std::to_string(f);
    rows += std::to_string(first_frame + f) + sep + std::to_string(f / rate) + sep;
    rows += std::to_string(10 + f) + sep + std::to_string(20 + f) + sep + std::to_string(30 + f);
    if (f == 1) {
      rows += sep + sep + sep;
    } else {
      rows += sep + std::to_string(-5 + f) + sep + std::to_string(0.5 + f) + sep +
              std::to_string(1000 + f);
      if (trailing_sep) rows += sep;
    }
    rows += eol;
  }
  return rows;
}

std::vector<TrcVariant> TrcVariants() {
  std::vector<TrcVariant> v;
  // OpenSim 4 (TRCFileAdapter::extendWrite): tabs, a tab after every label and value, a blank line
  // before the data, OrigDataStartFrame 0 when the table has none.
  v.push_back({"OpenSim",
               "PathFileType\t4\t(X/Y/Z)\t/home/lab/walk.trc\n"
               "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\t"
               "OrigDataStartFrame\tOrigNumFrames\n"
               "100\t100\t3\t2\tmm\t100\t0\t3\n"
               "Frame#\tTime\tA\t\t\tB\t\t\t\n"
               "\t\tX1\tY1\tZ1\tX2\tY2\tZ2\t\n"
               "\n" + TrcVariantRows(1, 100, "\t", "\n", true),
               {"A", "B"}, 100, 0.001, 1});
  // OpenCap (its TRC writer, Windows): "PathFileType" then two spaces and a tab, a space before
  // the path, CRLF, rates written "%.1f", and a trailing tab after each coordinate label triple.
  v.push_back({"OpenCap",
               "PathFileType  4\t(X/Y/Z) C:\\Users\\lab\\OpenCapData\\squat.trc\r\n"
               "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\t"
               "OrigDataStartFrame\tOrigNumFrames\r\n"
               "60.0\t60.0\t3\t2\tmm\t60.0\t1\t3\r\n"
               "Frame#\tTime\tr.ASIS_study\t\t\tL.ASIS_study\t\t\t\r\n"
               "\t\tX1\tY1\tZ1\tX2\tY2\tZ2\t\r\n"
               "\r\n" + TrcVariantRows(1, 60, "\t", "\r\n", false),
               {"r.ASIS_study", "L.ASIS_study"}, 60, 0.001, 1});
  // Pose2Sim: metres, NumFrames from the frame range (one short of the rows), OrigDataStartFrame
  // the first frame index.
  v.push_back({"Pose2Sim",
               "PathFileType\t4\t(X/Y/Z)\tsquat_0-2.trc\n"
               "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\t"
               "OrigDataStartFrame\tOrigNumFrames\n"
               "30\t30\t2\t2\tm\t30\t0\t2\n"
               "Frame#\tTime\tHip\t\t\tKnee\t\t\n"
               "\t\tX1\tY1\tZ1\tX2\tY2\tZ2\n" + TrcVariantRows(0, 30, "\t", "\n", false),
               {"Hip", "Knee"}, 30, 1.0, 0});
  // Motion Analysis Cortex / EVaRT: CRLF, rates "60.00", counts right-aligned in spaces, a Windows
  // path, dotted names, a trailing tab on the data rows.
  v.push_back({"Cortex",
               "PathFileType\t4\t(X/Y/Z)\tC:\\Cortex\\Data\\walk1.trc\r\n"
               "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\t"
               "OrigDataStartFrame\tOrigNumFrames\r\n"
               "60.00\t60.00\t         3\t2\tmm\t60.00\t1\t         3\r\n"
               "Frame#\tTime\tR.ASIS\t\t\tL.ASIS\t\t\t\r\n"
               "\t\tX1\tY1\tZ1\tX2\tY2\tZ2\t\r\n"
               "\r\n" + TrcVariantRows(1, 60, "\t", "\r\n", true),
               {"R.ASIS", "L.ASIS"}, 60, 0.001, 1});
  // Vicon Nexus (TRC export of a trimmed trial): subject-prefixed labels, frames numbered from the
  // trimmed start, OrigDataStartFrame that start, NumFrames of the untrimmed trial, centimetres.
  v.push_back({"Vicon Nexus",
               "PathFileType\t4\t(X/Y/Z)\tD:\\Vicon\\Session 1\\Walk 03.trc\n"
               "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\t"
               "OrigDataStartFrame\tOrigNumFrames\n"
               "100.000000\t100.000000\t1250\t2\tcm\t100.000000\t57\t1250\n"
               "Frame#\tTime\tSubject01:LASI\t\t\tSubject01:RASI\t\t\t\n"
               "\t\tX1\tY1\tZ1\tX2\tY2\tZ2\t\n"
               "\n" + TrcVariantRows(57, 100, "\t", "\n", false),
               {"Subject01:LASI", "Subject01:RASI"}, 100, 0.01, 57});
  // Qualisys QTM: marker names with spaces, no blank line before the data, only the five keys
  // QTM fills (no Orig* fields), a UTF-8 byte order mark from a Windows editor.
  v.push_back({"Qualisys QTM",
               "\xEF\xBB\xBFPathFileType\t4\t(X/Y/Z)\tgait 0001.trc\n"
               "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\n"
               "150\t150\t3\t2\tmm\n"
               "Frame#\tTime\tL ASIS\t\t\tR ASIS\n"
               "\t\tX1\tY1\tZ1\tX2\tY2\tZ2\n" + TrcVariantRows(1, 150, "\t", "\n", false),
               {"L ASIS", "R ASIS"}, 150, 0.001, 1});
  // Hand-made: runs of spaces everywhere (no tab at all), "Frame# Time" labels, units spelled out,
  // no NumFrames / NumMarkers. Space-separated rows cannot mark a gap, so B has all its frames.
  std::string spaced =
      "PathFileType 4 (X/Y/Z) hand.trc\n"
      "DataRate   CameraRate   Units\n"
      "  50         50         millimeters\n"
      "Frame#  Time  A  B\n"
      "    X1  Y1  Z1  X2  Y2  Z2\n";
  for (int f = 0; f < 3; ++f) {
    spaced += std::to_string(1 + f) + "  " + std::to_string(f / 50.0) + "   " +
              std::to_string(10 + f) + " " + std::to_string(20 + f) + " " + std::to_string(30 + f) +
              "  " + std::to_string(-5 + f) + " " + std::to_string(0.5 + f) + " " +
              std::to_string(1000 + f) + "\n";
  }
  v.push_back({"spaces only", spaced, {"A", "B"}, 50, 0.001, 1});
  // Tabs and spaces mixed in the header lines, an extra tab inside the values line, "Frame# Time"
  // padded with a space, CR-only line ends (classic Mac).
  v.push_back({"mixed padding",
               "PathFileType \t 4 \t(X/Y/Z)\tmixed.trc\r"
               "DataRate \tCameraRate\t\tNumFrames\tNumMarkers\tUnits\r"
               "200 \t\t200\t3 \t2\t MM\r"
               "Frame# Time\tA\t\t\tB\t\t\t\r"
               "\t\tX1\tY1\tZ1\tX2\tY2\tZ2\r"
               "\r" + TrcVariantRows(1, 200, "\t", "\r", false),
               {"A", "B"}, 200, 0.001, 1});
  return v;
}

TEST(TrcVariants, EveryWriterVariantLoadsWithItsValues) {
  const std::vector<TrcVariant> variants = TrcVariants();
  for (size_t k = 0; k < variants.size(); ++k) {
    const TrcVariant& variant = variants[k];
    SCOPED_TRACE(variant.writer);
    const std::string path = WriteText("_" + std::to_string(k) + ".trc", variant.text);
    MarkerTrial t;
    const Status s = ReadTrc(path, &t);
    ASSERT_TRUE(s.ok()) << s.message();
    EXPECT_EQ(t.marker_names, variant.names);
    EXPECT_EQ(t.rate_hz, variant.rate_hz);
    ASSERT_EQ(t.num_frames(), 3);  // the rows, whatever NumFrames says
    EXPECT_EQ(t.frame_numbers,
              (std::vector<int>{variant.first_frame, variant.first_frame + 1,
                                variant.first_frame + 2}));
    EXPECT_NEAR(t.times[2], 2.0 / variant.rate_hz, 1e-6);
    const double u = variant.metres_per_unit;
    for (int f = 0; f < 3; ++f) {
      ASSERT_TRUE(t.Has(f, 0)) << "frame " << f;
      EXPECT_NEAR((t.At(f, 0) - u * Eigen::Vector3d(10 + f, 20 + f, 30 + f)).norm(), 0.0, 1e-12);
    }
    EXPECT_NEAR((t.At(2, 1) - u * Eigen::Vector3d(-3, 2.5, 1002)).norm(), 0.0, 1e-12);
    EXPECT_EQ(t.Has(1, 1), variant.writer == "spaces only");
  }
}

TEST(TrcVariants, NumFramesDisagreeingWithTheRowsReadsTheRows) {
  MarkerTrial t;
  const std::string more = WriteText("_more.trc", TrcHead(3) +
                                                      "1\t0\t1\t2\t3\t4\t5\t6\n"
                                                      "2\t0.01\t1\t2\t3\t4\t5\t6\n");
  Status s = ReadTrc(more, &t);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(t.num_frames(), 2);
  const std::string fewer = WriteText("_fewer.trc", TrcHead(1) +
                                                        "1\t0\t1\t2\t3\t4\t5\t6\n"
                                                        "2\t0.01\t1\t2\t3\t4\t5\t7\n");
  s = ReadTrc(fewer, &t);
  ASSERT_TRUE(s.ok()) << s.message();
  ASSERT_EQ(t.num_frames(), 2);
  EXPECT_DOUBLE_EQ(t.At(1, 1).z(), 0.007);
  // A NumFrames far beyond the file is no allocation of that size.
  std::string huge = TrcHead(1) + "1\t0\t1\t2\t3\t4\t5\t6\n";
  huge.replace(huge.find("100\t100\t1\t"), 10, "100\t100\t2000000000\t");
  const std::string huge_path = WriteText("_huge.trc", huge);
  s = ReadTrc(huge_path, &t);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(t.num_frames(), 1);
}

TEST(TrcVariants, AnEmptyValueBetweenTabsKeepsItsKey) {
  // CameraRate left empty: NumFrames is still 1 and NumMarkers 2 (positions by tab), not shifted.
  const std::string text =
      "PathFileType\t4\t(X/Y/Z)\tt.trc\n"
      "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\n"
      "100\t\t1\t2\tmm\n"
      "Frame#\tTime\tA\t\t\tB\n"
      "1\t0\t1\t2\t3\t4\t5\t6\n";
  const std::string path = WriteText(".trc", text);
  MarkerTrial t;
  const Status s = ReadTrc(path, &t);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(t.num_markers(), 2);
  EXPECT_DOUBLE_EQ(t.At(0, 1).z(), 0.006);
}

TEST(TrcVariants, StillRejectedWhatOpenSimRejectsAndNoUnits) {
  MarkerTrial t;
  // No Units at all: a guess would scale the subject by 1000 silently.
  const std::string no_units = WriteText("_no_units.trc",
                                         "PathFileType\t4\t(X/Y/Z)\tt.trc\n"
                                         "DataRate\tCameraRate\tNumFrames\tNumMarkers\n"
                                         "100\t100\t1\t1\n"
                                         "Frame#\tTime\tA\n1\t0\t1\t2\t3\n");
  ExpectErrorAt(ReadTrc(no_units, &t), no_units, 2, "header has no Units field");
  // "PathFileTypes" is not the key, whatever the padding.
  const std::string bad_key = WriteText("_bad_key.trc", "PathFileTypes  4\t(X/Y/Z)\tt.trc\n");
  ExpectErrorAt(ReadTrc(bad_key, &t), bad_key, 1, "not a TRC file");
  // Values beyond the keys.
  std::string extra = TrcHead(1);
  extra.replace(extra.find("\t1\t1\nFrame#"), 5, "\t1\t1\t7\t8\nFrame#");
  const std::string extra_path = WriteText("_extra.trc", extra + "1\t0\t1\t2\t3\t4\t5\t6\n");
  ExpectErrorAt(ReadTrc(extra_path, &t), extra_path, 3, "header values line has 10 fields");
}

// ---------------------------------------------------------------- TRC errors

TEST(TrcErrors, NonExistentFile) {
  const std::string path = TmpPath("_does_not_exist.trc");
  MarkerTrial t;
  const Status s = ReadTrc(path, &t);
  EXPECT_FALSE(s.ok());
  EXPECT_THAT(s.message(), HasSubstr(path));
  EXPECT_THAT(s.message(), HasSubstr("cannot open"));
}

TEST(TrcErrors, EmptyFile) {
  const std::string path = WriteText(".trc", "");
  MarkerTrial t;
  ExpectErrorAt(ReadTrc(path, &t), path, 1, "empty file");
}

TEST(TrcErrors, NotATrcFile) {
  const std::string path = WriteText(".trc", "time\tx\ty\n0\t1\t2\n");
  MarkerTrial t;
  ExpectErrorAt(ReadTrc(path, &t), path, 1, "PathFileType");
}

TEST(TrcErrors, HeaderCutShort) {
  const std::string path = WriteText(".trc", "PathFileType\t4\t(X/Y/Z)\tt.trc\n"
                                             "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\n");
  MarkerTrial t;
  ExpectErrorAt(ReadTrc(path, &t), path, 3, "header values line");
}

TEST(TrcErrors, GarbledHeaderKeys) {
  std::string text = TrcHead(1);
  text.replace(text.find("DataRate"), 8, "DataRat");
  const std::string path = WriteText(".trc", text + "1\t0\t1\t2\t3\t4\t5\t6\n");
  MarkerTrial t;
  ExpectErrorAt(ReadTrc(path, &t), path, 2, "header keys line");
}

TEST(TrcErrors, GarbledHeaderValue) {
  std::string text = TrcHead(1);
  text.replace(text.find("100\t100\t1\t"), 10, "100\t100\tone\t");
  const std::string path = WriteText(".trc", text + "1\t0\t1\t2\t3\t4\t5\t6\n");
  MarkerTrial t;
  ExpectErrorAt(ReadTrc(path, &t), path, 3, "NumFrames = 'one'");
}

TEST(TrcErrors, MissingRequiredHeaderValue) {
  const std::string text =
      "PathFileType\t4\t(X/Y/Z)\tt.trc\n"
      "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\n"
      "100\t100\t1\t1\n"
      "Frame#\tTime\tA\n\t\tX1\tY1\tZ1\n1\t0\t1\t2\t3\n";
  const std::string path = WriteText(".trc", text);
  MarkerTrial t;
  ExpectErrorAt(ReadTrc(path, &t), path, 3, "Units has no value");
}

TEST(TrcErrors, UnsupportedUnits) {
  const std::string path = WriteText(".trc", TrcHead(1, 2, "in") + "1\t0\t1\t2\t3\t4\t5\t6\n");
  MarkerTrial t;
  ExpectErrorAt(ReadTrc(path, &t), path, 3, "Units 'in'");
}

TEST(TrcErrors, NonPositiveRate) {
  std::string text = TrcHead(1);
  text.replace(text.find("100\t100\t1"), 3, "0");
  const std::string path = WriteText(".trc", text + "1\t0\t1\t2\t3\t4\t5\t6\n");
  MarkerTrial t;
  ExpectErrorAt(ReadTrc(path, &t), path, 3, "DataRate");
}

TEST(TrcErrors, NumMarkersDisagreesWithNames) {
  const std::string path = WriteText(".trc", TrcHead(1, 3) + "1\t0\t1\t2\t3\t4\t5\t6\n");
  MarkerTrial t;
  const Status s = ReadTrc(path, &t);
  ExpectErrorAt(s, path, 4, "lists 2 markers");
  EXPECT_THAT(s.message(), HasSubstr("NumMarkers (line 3) is 3"));
}

TEST(TrcErrors, MissingNamesLine) {
  const std::string text =
      "PathFileType\t4\t(X/Y/Z)\tt.trc\n"
      "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\n"
      "100\t100\t1\t1\tmm\n"
      "1\t0\t1\t2\t3\n";
  const std::string path = WriteText(".trc", text);
  MarkerTrial t;
  ExpectErrorAt(ReadTrc(path, &t), path, 4, "Frame# Time");
}

TEST(TrcErrors, NoMarkers) {
  const std::string text =
      "PathFileType\t4\t(X/Y/Z)\tt.trc\n"
      "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\n"
      "100\t100\t0\t0\tmm\n"
      "Frame#\tTime\t\t\n";
  const std::string path = WriteText(".trc", text);
  MarkerTrial t;
  ExpectErrorAt(ReadTrc(path, &t), path, 4, "no markers");
}

TEST(TrcErrors, DuplicateMarkerName) {
  const std::string path =
      WriteText(".trc", TrcHead(1, 2, "mm", "A\t\t\tA\t\t") + "1\t0\t1\t2\t3\t4\t5\t6\n");
  MarkerTrial t;
  ExpectErrorAt(ReadTrc(path, &t), path, 4, "'A' appears more than once");
}

TEST(TrcErrors, RowWithMoreColumnsThanMarkers) {
  const std::string path = WriteText(".trc", TrcHead(2) +
                                                 "1\t0\t1\t2\t3\t4\t5\t6\n"
                                                 "2\t0.01\t1\t2\t3\t4\t5\t6\t7\n");
  MarkerTrial t;
  ExpectErrorAt(ReadTrc(path, &t), path, 8, "7 coordinate fields, more than 3 x 2 markers = 6");
}

TEST(TrcErrors, NonNumericField) {
  const std::string path = WriteText(".trc", TrcHead(2) +
                                                 "1\t0\t1\t2\t3\t4\t5\t6\n"
                                                 "2\t0.01\t1\t2\t3\t4\t5x\t6\n");
  MarkerTrial t;
  ExpectErrorAt(ReadTrc(path, &t), path, 8, "marker B Y (column 7) is not a number: '5x'");
}

TEST(TrcErrors, NonNumericFrameAndTime) {
  MarkerTrial t;
  const std::string p1 = WriteText("_frame.trc", TrcHead(1) + "one\t0\t1\t2\t3\t4\t5\t6\n");
  ExpectErrorAt(ReadTrc(p1, &t), p1, 7, "Frame# 'one'");
  const std::string p2 = WriteText("_time.trc", TrcHead(1) + "1\tt0\t1\t2\t3\t4\t5\t6\n");
  ExpectErrorAt(ReadTrc(p2, &t), p2, 7, "Time 't0'");
}

TEST(TrcErrors, InfiniteValue) {
  const std::string path = WriteText(".trc", TrcHead(2) +
                                                 "1\t0\t1\t2\t3\t4\t5\t6\n"
                                                 "2\t0.01\t-inf\t2\t3\t4\t5\t6\n");
  MarkerTrial t;
  ExpectErrorAt(ReadTrc(path, &t), path, 8, "marker A X (column 3) is infinite");
  const std::string p2 = WriteText("_overflow.trc", TrcHead(1) + "1\t0\t1\t2\t3\t4\t1e999\t6\n");
  ExpectErrorAt(ReadTrc(p2, &t), p2, 7, "marker B Y (column 7) is infinite");
}

TEST(TrcErrors, FailedReadLeavesTrialUntouched) {
  MarkerTrial t;
  t.name = "keep";
  const std::string path = WriteText(".trc", TrcHead(1) + "1\t0\t1\t2\t3\t4\tbad\t6\n");
  EXPECT_FALSE(ReadTrc(path, &t).ok());
  EXPECT_EQ(t.name, "keep");
}

// ---------------------------------------------------------------- MOT

CoordinateTable SyntheticTable() {
  CoordinateTable c;
  c.name = "Coordinates";
  c.column_names = {"pelvis_tilt", "pelvis_tx", "knee_angle_r"};
  c.in_degrees = true;
  const int n = 9;
  c.values.resize(n, 3);
  for (int r = 0; r < n; ++r) {
    c.times.push_back(0.4 + r / 60.0);
    c.values(r, 0) = 4.84455933 + 0.1 * r;
    c.values(r, 1) = -0.60102028 * r;
    c.values(r, 2) = -54.91982332 + std::sin(r) * 10.0;
  }
  c.values(5, 1) = kNaN;
  return c;
}

TEST(MotRoundTrip, WriteThenRead) {
  const CoordinateTable c = SyntheticTable();
  const std::string path = TmpPath(".mot");
  Status s = WriteMot(path, c);
  ASSERT_TRUE(s.ok()) << s.message();
  {
    std::ifstream in(path);
    std::vector<std::string> lines;
    for (std::string l; std::getline(in, l);) lines.push_back(l);
    ASSERT_EQ(lines.size(), 7u + 9u);
    EXPECT_EQ(lines[0], "Coordinates");
    EXPECT_EQ(lines[1], "version=1");
    EXPECT_EQ(lines[2], "nRows=9");
    EXPECT_EQ(lines[3], "nColumns=4");
    EXPECT_EQ(lines[4], "inDegrees=yes");
    EXPECT_EQ(lines[5], "endheader");
    EXPECT_EQ(lines[6], "time\tpelvis_tilt\tpelvis_tx\tknee_angle_r");
    EXPECT_EQ(lines[7].substr(0, 22), "0.40000000\t4.84455933\t");
  }
  CoordinateTable r;
  s = ReadMot(path, &r);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(r.name, "Coordinates");
  EXPECT_EQ(r.column_names, c.column_names);
  EXPECT_TRUE(r.in_degrees);
  ASSERT_EQ(r.num_frames(), 9);
  ASSERT_EQ(r.values.cols(), 3);
  for (int i = 0; i < 9; ++i) {
    EXPECT_NEAR(r.times[i], c.times[i], 5e-9);
    for (int k = 0; k < 3; ++k) {
      if (std::isnan(c.values(i, k))) {
        EXPECT_TRUE(std::isnan(r.values(i, k)));
      } else {
        EXPECT_NEAR(r.values(i, k), c.values(i, k), 5e-9);
      }
    }
  }

  CoordinateTable rad = c;
  rad.in_degrees = false;
  rad.name.clear();
  const std::string p2 = TmpPath("_rad.mot");
  ASSERT_TRUE(WriteMot(p2, rad).ok());
  ASSERT_TRUE(ReadMot(p2, &r).ok());
  EXPECT_FALSE(r.in_degrees);
  EXPECT_EQ(r.name, fs::path(p2).stem().string());
}

TEST(MotRoundTrip, EmptyTable) {
  CoordinateTable c;
  c.name = "empty";
  c.column_names = {"a"};
  c.values.resize(0, 1);
  const std::string path = TmpPath(".mot");
  ASSERT_TRUE(WriteMot(path, c).ok());
  CoordinateTable r;
  const Status s = ReadMot(path, &r);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(r.num_frames(), 0);
  EXPECT_EQ(r.column_names, c.column_names);
}

TEST(MotWrite, RejectsBadInput) {
  const std::string path = TmpPath(".mot");
  CoordinateTable c = SyntheticTable();
  CoordinateTable bad = c;
  bad.times.pop_back();
  EXPECT_FALSE(WriteMot(path, bad).ok());
  bad = c;
  bad.column_names.pop_back();
  EXPECT_FALSE(WriteMot(path, bad).ok());
  bad = c;
  bad.column_names[0] = "has space";
  EXPECT_FALSE(WriteMot(path, bad).ok());
  bad = c;
  bad.values(1, 1) = -std::numeric_limits<double>::infinity();
  const Status s = WriteMot(path, bad);
  EXPECT_FALSE(s.ok());
  EXPECT_THAT(s.message(), HasSubstr(path));
  EXPECT_THAT(s.message(), HasSubstr("pelvis_tx"));
}

TEST(MotReal, OpenSimWalk1Ik) {
  SKIP_WITHOUT_SHARED_DATA();
  const std::string path =
      SharedData() + "/opensim_gait2354_subject01/reference_outputs/subject01_walk1_ik.mot";
  CoordinateTable c;
  const Status s = ReadMot(path, &c);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(c.name, "Coordinates");
  EXPECT_TRUE(c.in_degrees);
  ASSERT_EQ(c.column_names.size(), 23u);
  EXPECT_EQ(c.column_names.front(), "pelvis_tilt");
  EXPECT_EQ(c.column_names.back(), "lumbar_rotation");
  ASSERT_EQ(c.num_frames(), 73);
  ASSERT_EQ(c.values.cols(), 23);
  EXPECT_DOUBLE_EQ(c.times.front(), 0.4);
  EXPECT_DOUBLE_EQ(c.times.back(), 1.6);
  EXPECT_DOUBLE_EQ(c.times[1], 0.41666667);
  EXPECT_DOUBLE_EQ(c.values(0, c.FindColumn("pelvis_tilt")), 4.84455933);
  EXPECT_DOUBLE_EQ(c.values(0, c.FindColumn("pelvis_ty")), 1.04559875);
  EXPECT_DOUBLE_EQ(c.values(0, c.FindColumn("knee_angle_r")), -54.91982332);
  EXPECT_DOUBLE_EQ(c.values(2, c.FindColumn("lumbar_rotation")), -5.06961773);
  EXPECT_DOUBLE_EQ(c.values(72, c.FindColumn("hip_flexion_r")), 17.10246448);
  EXPECT_EQ(c.FindColumn("time"), -1);

  // Our writer's output reads back to the same table (to the 8 written decimals).
  const std::string out = TmpPath(".mot");
  ASSERT_TRUE(WriteMot(out, c).ok());
  CoordinateTable r;
  ASSERT_TRUE(ReadMot(out, &r).ok());
  EXPECT_EQ(r.column_names, c.column_names);
  EXPECT_EQ(r.times, c.times);
  EXPECT_TRUE(r.values == c.values);
}

TEST(MotReal, OpenSimStaticOutputInRadians) {
  SKIP_WITHOUT_SHARED_DATA();
  const std::string path =
      SharedData() + "/opensim_gait2354_subject01/reference_outputs/subject01_static_output.mot";
  CoordinateTable c;
  const Status s = ReadMot(path, &c);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(c.name, "static pose");
  EXPECT_FALSE(c.in_degrees);
  ASSERT_EQ(c.num_frames(), 1);
  ASSERT_EQ(c.column_names.size(), 301u);
  EXPECT_EQ(c.column_names[0], "R.ASIS_tx");
  EXPECT_DOUBLE_EQ(c.values(0, 0), 0.60623401);
  EXPECT_DOUBLE_EQ(c.values(0, 1), 1.07305817);
  EXPECT_GE(c.FindColumn("knee_angle_r"), 0);
}

TEST(MotTolerance, OpenSim3AndSimmHeaders) {
  // OpenSim 3 style: no version line -> degrees; CRLF; space-padded values; blank lines.
  const std::string p1 = WriteText("_os3.mot",
                                   "walk ik\r\nnRows=2\r\nnColumns=3\r\n\r\nSome free text.\r\n"
                                   "endheader\r\n\r\ntime\tq1\tq2\t\r\n"
                                   "   0.0\t  1.5\t -2\t\r\n\r\n   0.01\tnan\t3e1\r\n");
  CoordinateTable c;
  Status s = ReadMot(p1, &c);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(c.name, "walk ik");
  EXPECT_TRUE(c.in_degrees);
  ASSERT_EQ(c.num_frames(), 2);
  EXPECT_EQ(c.values(0, 1), -2.0);
  EXPECT_TRUE(std::isnan(c.values(1, 0)));
  EXPECT_EQ(c.values(1, 1), 30.0);
  // SIMM style: "name x", "datacolumns N", "datarows N", space-separated table.
  const std::string p2 = WriteText("_simm.mot",
                                   "name simm_motion\ndatacolumns 2\ndatarows 1\nrange 0 1\n"
                                   "endheader\ntime knee\n0.5 12.25\n");
  s = ReadMot(p2, &c);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(c.name, "simm_motion");
  EXPECT_TRUE(c.in_degrees);
  EXPECT_EQ(c.column_names, std::vector<std::string>{"knee"});
  EXPECT_EQ(c.values(0, 0), 12.25);
  // version=1 without inDegrees: radians, as OpenSim reads it.
  const std::string p3 = WriteText("_v1.mot", "x\nversion=1\nendheader\ntime\ta\n0\t1\n");
  s = ReadMot(p3, &c);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_FALSE(c.in_degrees);
}

TEST(MotErrors, BadInputs) {
  CoordinateTable c;
  {
    const std::string path = TmpPath("_does_not_exist.mot");
    const Status s = ReadMot(path, &c);
    EXPECT_FALSE(s.ok());
    EXPECT_THAT(s.message(), HasSubstr(path));
  }
  const std::string head = "Coordinates\nversion=1\nnRows=2\nnColumns=3\ninDegrees=yes\nendheader\n";
  {
    const std::string p = WriteText("_noend.mot", "Coordinates\nversion=1\nnRows=2\ntime\ta\n");
    ExpectErrorAt(ReadMot(p, &c), p, 5, "endheader");
  }
  {
    const std::string p = WriteText("_nolabels.mot", head);
    ExpectErrorAt(ReadMot(p, &c), p, 7, "column-label line");
  }
  {
    const std::string p = WriteText("_notime.mot", head + "t\ta\tb\n0\t1\t2\n0.1\t1\t2\n");
    ExpectErrorAt(ReadMot(p, &c), p, 7, "start with 'time'");
  }
  {
    const std::string p = WriteText("_ncols.mot", head + "time\ta\n0\t1\n0.1\t1\n");
    ExpectErrorAt(ReadMot(p, &c), p, 4, "nColumns is 3 but the column-label line (line 7) has 2");
  }
  {
    const std::string p = WriteText("_nrows.mot", head + "time\ta\tb\n0\t1\t2\n");
    ExpectErrorAt(ReadMot(p, &c), p, 3, "nRows is 2 but the file has 1 data rows");
  }
  {
    const std::string p = WriteText("_short.mot", head + "time\ta\tb\n0\t1\t2\n0.1\t1\n");
    ExpectErrorAt(ReadMot(p, &c), p, 9, "row has 2 fields but there are 3 columns");
  }
  {
    const std::string p = WriteText("_long.mot", head + "time\ta\tb\n0\t1\t2\t4\n0.1\t1\t2\n");
    ExpectErrorAt(ReadMot(p, &c), p, 8, "row has 4 fields but there are 3 columns");
  }
  {
    const std::string p = WriteText("_text.mot", head + "time\ta\tb\n0\t1\t2\n0.1\tabc\t2\n");
    ExpectErrorAt(ReadMot(p, &c), p, 9, "column a is not a number: 'abc'");
  }
  {
    const std::string p = WriteText("_empty_field.mot", head + "time\ta\tb\n0\t\t2\n0.1\t1\t2\n");
    ExpectErrorAt(ReadMot(p, &c), p, 8, "column a is not a number");
  }
  {
    const std::string p = WriteText("_inf.mot", head + "time\ta\tb\n0\t1\t2\n0.1\t1\tinf\n");
    ExpectErrorAt(ReadMot(p, &c), p, 9, "column b is infinite");
  }
  {
    const std::string p = WriteText("_badnum.mot",
                                    "Coordinates\nversion=1\nnRows=two\nendheader\ntime\ta\n0\t1\n");
    ExpectErrorAt(ReadMot(p, &c), p, 3, "nRows 'two'");
  }
  {
    const std::string p = WriteText("_baddeg.mot",
                                    "Coordinates\nversion=1\ninDegrees=maybe\nendheader\ntime\ta\n");
    ExpectErrorAt(ReadMot(p, &c), p, 3, "inDegrees 'maybe'");
  }
}

}  // namespace
