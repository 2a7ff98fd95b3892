// Where the daemon's `export` may write (daemon/export_path.h): beneath the allowed directories
// only, never through a symlink, never into the daemon's storage; what is refused creates nothing.
#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <string>

#include <gtest/gtest.h>

#include "daemon/export_path.h"
#include "tests/daemon_test_util.h"

namespace mocap {
namespace {

namespace fs = std::filesystem;
using daemon::ExportFile;
using daemon::OpenExportFile;

std::string Read(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  return std::string((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
}

class ExportPath : public ::testing::Test {
 protected:
  void SetUp() override {
    root_ = testing::MakeTempDir("mocap-export-path");
    ASSERT_FALSE(root_.empty());
    allowed_ = root_ + "/allowed";
    outside_ = root_ + "/outside";
    state_ = root_ + "/state";
    for (const std::string& d : {allowed_, outside_, state_, allowed_ + "/sub"}) fs::create_directories(d);
    std::ofstream(outside_ + "/target") << "precious";
  }
  void TearDown() override { fs::remove_all(root_); }

  // Opens `path` for export; the error code the daemon would answer ("" when it opened).
  std::string Open(const std::string& path, std::vector<std::string> allowed = {}) {
    if (allowed.empty()) allowed = {allowed_};
    ExportFile f;
    const Status s = OpenExportFile(path, allowed, state_, &f);
    if (s) {
      EXPECT_GE(f.fd, 0);
      close(f.fd);
      return "";
    }
    EXPECT_LT(f.fd, 0);
    EXPECT_NE(s.message().find(path), std::string::npos) << s.message();  // names the path
    return f.forbidden ? "forbidden" : "failed";
  }

  std::string root_, allowed_, outside_, state_;
};

TEST_F(ExportPath, AllowedDirectoryAndItsSubdirectoriesOpen) {
  EXPECT_EQ(Open(allowed_ + "/a.c3d"), "");
  EXPECT_TRUE(fs::is_regular_file(allowed_ + "/a.c3d"));
  EXPECT_EQ(Open(allowed_ + "/sub/b.trc"), "");
  EXPECT_EQ(Open(allowed_ + "/sub/../c.json"), "");  // stays beneath
  EXPECT_TRUE(fs::is_regular_file(allowed_ + "/c.json"));
  EXPECT_EQ(Open(allowed_ + "/./sub//d.json"), "");
  // The second of two allowed directories.
  EXPECT_EQ(Open(outside_ + "/e.json", {allowed_, outside_}), "");
}

TEST_F(ExportPath, DotDotAbsoluteAndRelativePathsOutsideAreForbidden) {
  EXPECT_EQ(Open(allowed_ + "/../outside/x.json"), "forbidden");
  EXPECT_EQ(Open(allowed_ + "/sub/../../outside/x.json"), "forbidden");
  EXPECT_EQ(Open(outside_ + "/x.json"), "forbidden");
  EXPECT_FALSE(fs::exists(outside_ + "/x.json"));
  EXPECT_EQ(Open("/etc/mocap-export-test.json"), "forbidden");
  EXPECT_FALSE(fs::exists("/etc/mocap-export-test.json"));
  EXPECT_EQ(Open("allowed/x.json"), "forbidden");  // relative
  EXPECT_EQ(Open(""), "forbidden");
  EXPECT_EQ(Open(allowed_), "forbidden");  // the directory itself
  // A sibling whose name starts with the allowed one's is not beneath it.
  fs::create_directories(allowed_ + "-evil");
  EXPECT_EQ(Open(allowed_ + "-evil/x.json"), "forbidden");
  EXPECT_FALSE(fs::exists(allowed_ + "-evil/x.json"));
}

TEST_F(ExportPath, SymlinksAreNeverFollowed) {
  // A directory link planted in the export directory, pointing out of it.
  fs::create_directory_symlink(outside_, allowed_ + "/link");
  EXPECT_EQ(Open(allowed_ + "/link/x.json"), "forbidden");
  EXPECT_FALSE(fs::exists(outside_ + "/x.json"));
  // A file link to a file outside: the file keeps its content.
  fs::create_symlink(outside_ + "/target", allowed_ + "/f.json");
  EXPECT_EQ(Open(allowed_ + "/f.json"), "forbidden");
  EXPECT_EQ(Read(outside_ + "/target"), "precious");
  // Even a link that stays inside is refused (no component may be a link).
  fs::create_directory_symlink(allowed_ + "/sub", allowed_ + "/inner");
  EXPECT_EQ(Open(allowed_ + "/inner/x.json"), "forbidden");
  // An absolute link to /.
  fs::create_directory_symlink("/", allowed_ + "/root");
  EXPECT_EQ(Open(allowed_ + "/root/etc/mocap-export-test.json"), "forbidden");
  EXPECT_FALSE(fs::exists("/etc/mocap-export-test.json"));
}

TEST_F(ExportPath, TheDaemonsStorageIsForbiddenButItsExportsFolder) {
  // An admin who allows a directory that holds the state directory.
  std::ofstream(state_ + "/mocapd.sqlite") << "database";
  EXPECT_EQ(Open(state_ + "/mocapd.sqlite", {root_}), "forbidden");
  EXPECT_EQ(Open(state_ + "/sub/../mocapd.sqlite-wal", {root_}), "forbidden");
  EXPECT_EQ(Read(state_ + "/mocapd.sqlite"), "database");
  fs::create_directories(state_ + "/exports");
  EXPECT_EQ(Open(state_ + "/exports/a.json", {state_ + "/exports"}), "");
}

TEST_F(ExportPath, MissingDirectoryFailsWithoutBeingForbidden) {
  EXPECT_EQ(Open(allowed_ + "/nowhere/x.json"), "failed");
  EXPECT_EQ(Open(root_ + "/gone/x.json", {root_ + "/gone"}), "failed");
}

TEST_F(ExportPath, CopyReplacesTheContentOnlyWhenAsked) {
  std::ofstream(allowed_ + "/old.json") << "a much longer content than the new one";
  ExportFile f;
  ASSERT_TRUE(OpenExportFile(allowed_ + "/old.json", {allowed_}, state_, &f).ok());
  // Opening did not truncate: a failed export leaves the file as it was.
  EXPECT_EQ(Read(allowed_ + "/old.json"), "a much longer content than the new one");
  std::ofstream(state_ + "/staged") << "new";
  ASSERT_TRUE(daemon::CopyIntoExportFile(state_ + "/staged", f.fd, f.path).ok());
  close(f.fd);
  EXPECT_EQ(Read(allowed_ + "/old.json"), "new");
  const Status missing = daemon::CopyIntoExportFile(state_ + "/absent", -1, "x");
  EXPECT_FALSE(missing.ok());
  EXPECT_NE(missing.message().find(state_ + "/absent"), std::string::npos);
}

}  // namespace
}  // namespace mocap
