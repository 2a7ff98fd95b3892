// What a client's bytes must bring back on the control socket (daemon/PROTOCOL.md), for the fuzz
// targets of the control protocol: fuzz_control.cpp (the server alone) and fuzz_daemon.cpp (the
// daemon's dispatch behind it). One place for the rule "every request line is answered exactly
// once, with a result or a documented error, in valid JSON", so both targets hold the server and
// the daemon to the same one.
#pragma once
#include <cstddef>
#include <cstdio>
#include <cstdlib>
#include <set>
#include <string>
#include <string_view>
#include <vector>

#include <nlohmann/json.hpp>

namespace mocap::fuzz {

// A failed expectation: says which on stderr (the fuzzer keeps the input) and aborts.
inline void Check(bool ok, const char* what) {
  if (ok) return;
  std::fprintf(stderr, "fuzz check failed: %s\n", what);
  std::abort();
}

// What the server must do with `input`: answer `answers` request lines, and end the connection
// with line_too_long when `too_long`. A line is what precedes a '\n'; blank ones (spaces, tabs,
// one '\r') are no-ops; a line longer than `max_line_bytes`, complete or not, ends the
// connection (and nothing after it is read).
struct ExpectedReplies {
  int answers = 0;
  bool too_long = false;
};
inline ExpectedReplies Expected(std::string_view input, std::size_t max_line_bytes) {
  ExpectedReplies e;
  std::size_t start = 0;
  for (;;) {
    const std::size_t end = input.find('\n', start);
    std::string_view line = input.substr(start, end == std::string_view::npos ? input.size() - start
                                                                              : end - start);
    if (line.size() > max_line_bytes) {
      e.too_long = true;
      return e;
    }
    if (end == std::string_view::npos) return e;  // an unfinished line: never a request
    if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
    if (line.find_first_not_of(" \t") != std::string_view::npos) ++e.answers;
    start = end + 1;
  }
}

// What came back so far: the complete lines of `output` (a partial last line is left for later).
// The first line is the hello; then every line is a JSON object: a reply (an id and either a
// result or an error whose code is one of `codes`, with a message), or, when `events` is true,
// an event (progress with its request's id and job, a stream frame, a drop notice). After
// line_too_long nothing follows. Aborts on anything else.
struct Replies {
  int answers = 0;   // replies, but not the line_too_long that ends the connection
  int results = 0;   // of which results
  bool ended_too_long = false;
  std::set<std::string> codes;  // the error codes seen
  std::vector<nlohmann::json> results_seen;  // the results, in order
};
inline Replies ParseReplies(std::string_view output, const std::set<std::string>& codes,
                            bool events) {
  Replies r;
  std::size_t start = 0;
  bool hello = false;
  for (std::size_t end; (end = output.find('\n', start)) != std::string_view::npos; start = end + 1) {
    const nlohmann::json line = nlohmann::json::parse(output.substr(start, end - start), nullptr,
                                                      /*allow_exceptions=*/false);
    Check(line.is_object(), "a line from the server is not a JSON object");
    if (!hello) {
      Check(line.value("event", "") == "hello", "the first line is not the hello");
      hello = true;
      continue;
    }
    Check(!r.ended_too_long, "a line after line_too_long");
    if (line.contains("event")) {
      Check(events, "an event where none may come");
      Check(line.at("event").is_string(), "an event's name is not a string");
      if (line.at("event") == "progress")
        Check(line.contains("id") && line.contains("job") && line.at("message").is_string(),
              "a progress event without its request's id, job or message");
      continue;
    }
    Check(line.contains("id"), "a reply without an id");
    Check(line.contains("result") != line.contains("error"), "a reply with neither or both of result and error");
    if (line.contains("result")) {
      ++r.results;
      r.results_seen.push_back(line.at("result"));
      ++r.answers;
      continue;
    }
    const nlohmann::json& error = line.at("error");
    Check(error.is_object() && error.contains("code") && error.at("code").is_string(),
          "an error without a code");
    const std::string code = error.at("code");
    if (!codes.count(code)) std::fprintf(stderr, "error code '%s': %s\n", code.c_str(), line.dump().c_str());
    Check(codes.count(code) > 0, "an error code outside the allowed ones");
    Check(error.contains("message") && error.at("message").is_string() &&
              !error.at("message").get<std::string>().empty(),
          "an error without a message");
    r.codes.insert(code);
    r.ended_too_long = code == "line_too_long";
    if (!r.ended_too_long) ++r.answers;
  }
  return r;
}

}  // namespace mocap::fuzz
