// libFuzzer target for the control protocol's server side (daemon/control_server.h): the input is
// what one client sends on the socket. The server, on its own sd-event loop, frames the lines,
// parses the JSON, checks the envelope and hands each request to a stand-in handler that answers
// at once (tests/control_server_test_util.h). Whatever the bytes, the server must not crash, leak
// or hit undefined behaviour (ASan/UBSan), and it must answer EVERY request line exactly once --
// with the handler's result or a structured error -- in valid JSON, or refuse an over-long line
// with `line_too_long` as its last word; else the target aborts.
//
// The daemon's methods behind the handler: fuzz/fuzz_daemon.cpp.
#include <cstddef>
#include <cstdint>
#include <set>
#include <string>
#include <string_view>

#include "fuzz/control_replies.h"
#include "tests/control_server_test_util.h"

namespace {
constexpr std::size_t kMaxLineBytes = 4096;  // small, so that the fuzzer reaches the limit
}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using mocap::fuzz::Check;
  static const std::set<std::string> kCodes = {"parse_error", "invalid_request", "line_too_long",
                                               "busy"};
  mocap::daemon::ControlServerOptions options;
  options.max_line_bytes = kMaxLineBytes;
  static mocap::testing::ControlServerHarness* harness = [&] {
    auto* h = new mocap::testing::ControlServerHarness(options);
    Check(h->ok(), "the server did not listen");
    return h;
  }();
  const std::string_view input(reinterpret_cast<const char*>(data), size);
  const int before = harness->requests();
  const std::string output = harness->Exchange(input);
  const mocap::fuzz::Replies got = mocap::fuzz::ParseReplies(output, kCodes, /*events=*/false);
  const mocap::fuzz::ExpectedReplies expected = mocap::fuzz::Expected(input, kMaxLineBytes);
  Check(got.answers == expected.answers, "not every request line answered exactly once");
  Check(got.ended_too_long == expected.too_long, "line_too_long where no line was too long, or none where one was");
  // Every request the handler saw was answered.
  Check(harness->requests() - before == got.results, "a request handed over and not answered");
  return 0;
}
