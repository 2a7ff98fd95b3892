// The control socket's server alone (daemon/control_server.h), with a stand-in handler: every
// request line answered once and in order, blank lines ignored, the pending-request bound kept
// under a flood, an over-long line refused and the connection closed, a stream that is not read
// held to its bound.
#include <sstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "tests/control_server_test_util.h"

namespace mocap {
namespace {

using nlohmann::json;

std::vector<json> Lines(const std::string& text) {
  std::vector<json> out;
  std::istringstream in(text);
  for (std::string line; std::getline(in, line);) out.push_back(json::parse(line));
  return out;
}

TEST(ControlServer, EveryRequestLineIsAnsweredOnceInOrder) {
  testing::ControlServerHarness h({});
  ASSERT_TRUE(h.ok());
  const std::vector<json> got = Lines(h.Exchange(
      "{\"id\":1,\"method\":\"a\"}\n"
      "\n  \t\r\n"                                       // blank lines: no-ops
      "{\"id\":\"two\",\"method\":\"b\",\"params\":{\"x\":[1,2]}}\r\n"
      "garbage\n"
      "{\"id\":3}\n"
      "{\"id\":4,\"method\":\"c\",\"params\":5}\n"
      "{\"id\":5,\"method\":\"d\",\"params\":null}\n"
      "{\"id\":6,\"method\":\"partial\"}"));           // no newline: never a request
  ASSERT_EQ(got.size(), 7u);
  EXPECT_EQ(got[0]["event"], "hello");
  EXPECT_EQ(got[1]["id"], 1);
  EXPECT_EQ(got[1]["result"]["method"], "a");
  EXPECT_EQ(got[2]["id"], "two");
  EXPECT_EQ(got[2]["result"]["params"], (json{{"x", {1, 2}}}));
  EXPECT_EQ(got[3]["error"]["code"], "parse_error");
  EXPECT_EQ(got[4]["id"], 3);
  EXPECT_EQ(got[4]["error"]["code"], "invalid_request");
  EXPECT_EQ(got[5]["error"]["code"], "invalid_request");
  EXPECT_EQ(got[6]["id"], 5);
  EXPECT_EQ(got[6]["result"]["params"], json::object());
  EXPECT_EQ(h.requests(), 3);
}

// A number beyond a double makes nlohmann::json throw out_of_range, not parse_error: the fuzzer
// found that one such line ended the daemon.
TEST(ControlServer, ANumberBeyondADoubleIsAParseErrorNotACrash) {
  testing::ControlServerHarness h({});
  ASSERT_TRUE(h.ok());
  const std::vector<json> got = Lines(h.Exchange(
      "{\"id\":1,\"method\":\"a\",\"params\":{\"x\":1.75e7502}}\n"
      "{\"id\":2,\"method\":\"b\"}\n"));
  ASSERT_EQ(got.size(), 3u);
  EXPECT_EQ(got[1]["error"]["code"], "parse_error");
  EXPECT_NE(got[1]["error"]["message"].get<std::string>().find("not JSON"), std::string::npos);
  EXPECT_EQ(got[2]["id"], 2);
  EXPECT_EQ(h.requests(), 1);
}

TEST(ControlServer, BusyRepliesDoNotFreePendingSlots) {
  // A handler that never answers: the first max_pending requests wait, every later one is
  // `busy`, however many come (a busy reply is not one of the pending requests finishing).
  daemon::ControlServerOptions o;
  o.max_pending = 8;
  testing::ControlServerHarness h(o, /*answer=*/false);
  ASSERT_TRUE(h.ok());
  std::string flood;
  for (int i = 0; i < 40; ++i) flood += "{\"id\":" + std::to_string(i) + ",\"method\":\"slow\"}\n";
  // Envelope errors between them must not free slots either.
  flood += "{\"id\":99,\"method\":7}\n{\"id\":100,\"method\":\"slow\"}\n";
  const std::vector<json> got = Lines(h.Exchange(flood, /*keep_open=*/true));
  EXPECT_EQ(h.requests(), 8);
  int busy = 0;
  for (const json& j : got) busy += j.contains("error") && j["error"]["code"] == "busy";
  EXPECT_EQ(busy, 33);  // 32 of the first 40, and id 100
}

TEST(ControlServer, OverLongLineIsRefusedAndTheConnectionClosed) {
  daemon::ControlServerOptions o;
  o.max_line_bytes = 1024;
  testing::ControlServerHarness h(o);
  ASSERT_TRUE(h.ok());
  const std::vector<json> got = Lines(h.Exchange("{\"id\":1,\"method\":\"a\"}\n" + std::string(5000, 'x') +
                                                 "\n{\"id\":2,\"method\":\"b\"}\n", true));
  ASSERT_EQ(got.size(), 3u);
  EXPECT_EQ(got[1]["id"], 1);
  EXPECT_EQ(got[2]["error"]["code"], "line_too_long");
  EXPECT_EQ(h.requests(), 1);  // nothing after it
}

// A subscriber that does not read: the kernel's socket buffer takes what it can, then the server
// keeps at most stream_queue_frames frames (or stream_output_bytes) for it and drops the rest
// (counted and told with the next frame it takes: tests/test_daemon_faults.cpp, the subscriber
// that never reads). The kernel's share is the same for the same lines, so two bounds accept
// exactly their difference.
TEST(ControlServer, AStreamThatIsNotReadIsHeldToItsBoundOfFrames) {
  auto run = [](int queue_frames, std::size_t queue_bytes) {
    daemon::ControlServerOptions o;
    o.stream_queue_frames = queue_frames;
    o.stream_output_bytes = queue_bytes;
    testing::ControlServerHarness h(o, true, /*stream_method=*/true);
    EXPECT_TRUE(h.ok());
    const std::vector<json> got = Lines(h.Exchange(
        "{\"id\":1,\"method\":\"stream\",\"params\":{\"frames\":3000,\"bytes\":1000}}\n",
        /*keep_open=*/true));
    int accepted = -1, frames = 0;
    for (const json& j : got) {
      if (j.is_string()) ++frames;  // a stream frame
      else if (j.contains("id") && j["id"] == 1) accepted = j["result"]["accepted"];
    }
    EXPECT_EQ(frames, accepted) << "every frame accepted arrives once read";
    return accepted;
  };
  const int a10 = run(10, 2u << 20), a50 = run(50, 2u << 20);
  const int a_bytes = run(100000, 20000);  // the bytes' bound: 20 frames of 1000 bytes
  EXPECT_GT(a10, 10);
  EXPECT_LT(a10, 3000);
  EXPECT_EQ(a50 - a10, 40);
  // 20 whole frames of 1000 bytes beside the one the kernel may have taken in part (counted by the
  // frames' bound, and by the bytes' only for its rest).
  EXPECT_GE(a_bytes - a10, 10);
  EXPECT_LE(a_bytes - a10, 11);
}

}  // namespace
}  // namespace mocap
