// libFuzzer target for the control protocol's server side (daemon/control_server.h): the input is
// what one client sends on the socket. The server, on its own sd-event loop, frames the lines,
// parses the JSON, checks the envelope and hands each request to a stand-in handler that answers
// at once (tests/control_server_test_util.h). Whatever the bytes, the server must not crash, leak
// or hit undefined behaviour (ASan/UBSan), and it must answer EVERY request line exactly once --
// with the handler's result or a structured error -- in valid JSON, or refuse an over-long line
// with `line_too_long` as its last word; else the target aborts.
//
// What it does not cover: the daemon's methods behind the handler (they need the whole daemon
// with its store and rig); tests/test_daemon_faults.cpp sends random requests to the real mocapd.
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <set>
#include <sstream>
#include <string>
#include <string_view>

#include "tests/control_server_test_util.h"

namespace {

constexpr std::size_t kMaxLineBytes = 4096;  // small, so that the fuzzer reaches the limit

void Check(bool ok) {
  if (!ok) std::abort();
}

// What the server must say to `input`: the number of request lines it answers, and whether it
// ends with line_too_long. A line is what precedes a '\n'; blank ones (spaces, tabs, one '\r')
// are no-ops; a line longer than the limit, complete or not, ends the connection.
void Expected(std::string_view input, int* answers, bool* too_long) {
  *answers = 0;
  *too_long = false;
  std::size_t start = 0;
  for (;;) {
    const std::size_t end = input.find('\n', start);
    std::string_view line = input.substr(start, end == std::string_view::npos ? input.size() - start
                                                                              : end - start);
    if (line.size() > kMaxLineBytes) {
      *too_long = true;
      return;
    }
    if (end == std::string_view::npos) return;  // an unfinished line: never a request
    if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
    if (line.find_first_not_of(" \t") != std::string_view::npos) ++*answers;
    start = end + 1;
  }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  static const std::set<std::string> kCodes = {"parse_error", "invalid_request", "line_too_long",
                                               "busy"};
  mocap::daemon::ControlServerOptions options;
  options.max_line_bytes = kMaxLineBytes;
  static mocap::testing::ControlServerHarness* harness = [&] {
    auto* h = new mocap::testing::ControlServerHarness(options);
    Check(h->ok());
    return h;
  }();
  const std::string_view input(reinterpret_cast<const char*>(data), size);
  const int before = harness->requests();
  const std::string output = harness->Exchange(input);

  int answers = 0, results = 0;
  bool ended_too_long = false;
  std::istringstream lines(output);
  std::string line;
  Check(static_cast<bool>(std::getline(lines, line)));
  Check(nlohmann::json::parse(line).value("event", "") == "hello");
  while (std::getline(lines, line)) {
    Check(!ended_too_long);  // nothing after line_too_long
    const nlohmann::json reply = nlohmann::json::parse(line);  // throws (a crash) if not JSON
    Check(reply.is_object() && reply.contains("id"));
    if (reply.contains("result")) {
      ++results;
    } else {
      const nlohmann::json& error = reply.at("error");
      const std::string code = error.at("code");
      Check(kCodes.count(code) && !error.at("message").get<std::string>().empty());
      ended_too_long = code == "line_too_long";
      if (ended_too_long) continue;
    }
    ++answers;
  }
  int expected = 0;
  bool too_long = false;
  Expected(input, &expected, &too_long);
  Check(answers == expected);
  Check(ended_too_long == too_long);
  Check(harness->requests() - before == results);  // every request the handler saw was answered
  return 0;
}
