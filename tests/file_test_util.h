// What the tests that read and write files share: the real data folder (and the skip where it
// is absent), scratch paths unique to the running test, whole-file bytes, and running `mocap`.
#pragma once
#include <gtest/gtest.h>
#include <sys/wait.h>

#include <array>
#include <cstdio>
#include <filesystem>
#include <unistd.h>
#include <fstream>
#include <sstream>
#include <string>

namespace mocap::testutil {

inline std::string SharedData() { return MOCAP_SHARED_DATA; }

#define SKIP_WITHOUT_SHARED_DATA()                                                          \
  do {                                                                                       \
    if (!std::filesystem::is_directory(::mocap::testutil::SharedData())) {                   \
      GTEST_SKIP() << "shared data folder " << ::mocap::testutil::SharedData()               \
                   << " is absent (CI puts shared/ beside the checkout); skipping real-data test"; \
    }                                                                                        \
  } while (0)

// A scratch file path in MOCAP_TEST_TMP/<subdir>/ unique to the running test (ctest runs tests
// in parallel processes).
inline std::string TmpPath(const std::string& subdir, const std::string& suffix) {
  const std::filesystem::path dir = std::filesystem::path(MOCAP_TEST_TMP) / subdir;
  std::filesystem::create_directories(dir);
  const auto* info = ::testing::UnitTest::GetInstance()->current_test_info();
  return (dir / (std::string(info->test_suite_name()) + "_" + info->name() + suffix)).string();
}

inline std::string ReadBytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

// An empty scratch directory MOCAP_TEST_TMP/group/name (emptied if it exists).
// Per process: ctest runs each test of a binary as its own process, in parallel, and two of them
// emptying and writing one directory read each other's half-written files (RealFit's gait2354
// tests: an empty report.json once).
inline std::filesystem::path FreshDir(const std::string& group, const std::string& name) {
  const std::filesystem::path dir =
      std::filesystem::path(MOCAP_TEST_TMP) / group / (name + "-" + std::to_string(::getpid()));
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  return dir;
}

inline void WriteBytes(const std::string& path, const std::string& bytes) {
  std::ofstream(path, std::ios::binary | std::ios::trunc) << bytes;
}

struct CommandResult {
  int status;
  std::string output;  // stdout and stderr
};

// Runs the `mocap` tool with `args` (a shell command line).
inline CommandResult Mocap(const std::string& args) {
  const std::string cmd = std::string(MOCAP_TOOL) + " " + args + " 2>&1";
  FILE* pipe = popen(cmd.c_str(), "r");
  std::string out;
  std::array<char, 4096> buf;
  while (pipe && fgets(buf.data(), buf.size(), pipe)) out += buf.data();
  const int rc = pipe ? pclose(pipe) : -1;
  return {WIFEXITED(rc) ? WEXITSTATUS(rc) : -1, out};
}

}  // namespace mocap::testutil
