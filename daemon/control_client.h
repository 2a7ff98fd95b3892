// The client side of mocapd's control protocol (daemon/PROTOCOL.md): newline-delimited JSON over
// a Unix stream socket. Used by mocapctl and by the daemon's tests.
//
// One connection, one thread. On connect the daemon sends a hello; each request gets the next id
// (1, 2, ...) and its reply repeats that id. Between a request and its reply the daemon may send
// events: progress of a long job (with the request's id), stream frames (after `subscribe`, no
// id), `dropped` counts. Those go to the caller's handler in the order they arrived, so a progress
// bar sees every iteration before the result. A long request (record.start, fit.start) may be
// followed by another one on the same connection before it replies (record.stop on Ctrl-C):
// replies that arrive while the client waits for a different id are kept until asked for.
//
// Two kinds of failure, kept apart because an operator acts differently on them:
//  - the connection: mocapd not running, the socket refused, the daemon gone mid-reply, silent
//    for too long, a line longer than the bound. A failed Status; the connection is then closed
//    and every later call fails at once (a half-read line cannot be resynchronised).
//  - the daemon's answer: an error reply {"code", "message"} is a Reply with `error_code` set,
//    and the connection goes on.
//
// Bounded: a line from the daemon longer than max_line_bytes is refused without being held (the
// buffer never grows past the bound); nothing waits longer than reply_timeout_ms of silence.
#pragma once
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <string>

#include <nlohmann/json.hpp>

#include "model/status.h"

namespace mocap::daemon {

// The version of daemon/PROTOCOL.md this client speaks; a hello with another is refused.
constexpr int kControlProtocolVersion = 1;

struct ControlClientOptions {
  std::string socket_path = "/run/mocapd/control.sock";
  // The longest the daemon may stay silent while the client waits for the hello or a reply (no
  // reply, no event). Long jobs send progress at least every iteration or 0.5 s, so a silent
  // daemon is a stuck one. <= 0: wait for ever.
  int reply_timeout_ms = 120000;
  // Longest line accepted from the daemon. Inline exports are up to 4 MiB of content (base64:
  // about 5.4 MiB) inside a JSON reply.
  std::size_t max_line_bytes = 16u << 20;
  bool IsValid(std::string* error) const;
};

// The daemon's first line.
struct Hello {
  int protocol = 0;
  std::string daemon;        // "mocapd 0.1.0"
  bool may_control = false;  // false: this user may only read (status, subscribe, lists)
  std::int64_t uid = -1;     // the uid the daemon saw (SO_PEERCRED)
};

struct ControlReply {
  nlohmann::json result;    // when ok()
  std::string error_code;   // the daemon's stable code ("forbidden", "not_found", ...); "" when ok
  std::string error_message;
  bool ok() const { return error_code.empty(); }
};

// Why connecting to `path` failed with `error_number` (errno), in the operator's words:
// "mocapd is not running (no socket at PATH)", "permission denied on PATH: you need to be in
// group G" (the socket's group), ...
std::string DescribeConnectError(const std::string& path, int error_number);

class ControlClient {
 public:
  using EventHandler = std::function<void(const nlohmann::json& event)>;

  // Connects to options.socket_path and reads the hello.
  static Status Connect(const ControlClientOptions& options, std::unique_ptr<ControlClient>* out);
  // Takes `fd`, a connected stream socket (tests: one end of a socketpair), and reads the hello.
  // The fd is closed on failure too.
  static Status Adopt(int fd, const ControlClientOptions& options,
                      std::unique_ptr<ControlClient>* out);
  ~ControlClient();
  ControlClient(const ControlClient&) = delete;
  ControlClient& operator=(const ControlClient&) = delete;

  const Hello& hello() const { return hello_; }
  // For poll() beside other descriptors (mocapctl waits on stdin and the daemon at once). Data
  // may already be buffered: call Poll(0) when it is readable, and after every call.
  int fd() const { return fd_; }
  bool connected() const { return fd_ >= 0; }

  // Sends a request; `id` receives the id its reply will carry.
  Status Send(const std::string& method, const nlohmann::json& params, std::int64_t* id);
  // Reads until the reply to `id` arrives (or was kept earlier), handing every event to
  // `on_event` (may be empty: events dropped).
  Status Wait(std::int64_t id, ControlReply* reply, const EventHandler& on_event = {});
  // Send, then Wait.
  Status Call(const std::string& method, const nlohmann::json& params, ControlReply* reply,
              const EventHandler& on_event = {});
  // Handles the messages that arrive within timeout_ms (0: those already readable), events to
  // `on_event`, replies kept for TakeReply. Not arriving is not an error here.
  Status Poll(int timeout_ms, const EventHandler& on_event);
  // The reply to `id` if it has arrived (it is then forgotten).
  bool TakeReply(std::int64_t id, ControlReply* reply);
  // The next event (a message that is not a reply), waiting up to timeout_ms (< 0: for ever);
  // *got is false when none came in time. Replies arriving meanwhile are kept.
  Status NextEvent(nlohmann::json* event, int timeout_ms, bool* got);

 private:
  ControlClient(int fd, ControlClientOptions options) : fd_(fd), options_(std::move(options)) {}
  Status ReadHello();
  // The next complete line; *got false when `timeout_ms` (< 0: for ever) passed first.
  Status ReadLine(std::string* line, int timeout_ms, bool* got);
  // The next message, parsed; replies to pending requests are stored, events returned.
  // *got false on timeout; *is_event false when the message was a reply (stored).
  Status ReadMessage(int timeout_ms, bool* got, nlohmann::json* event, bool* is_event);
  Status Fail(std::string message);  // closes the connection
  std::string Describe(std::int64_t id) const;

  int fd_ = -1;
  ControlClientOptions options_;
  Hello hello_;
  std::string buffer_;  // bytes read and not yet handed out (at most max_line_bytes + one read)
  std::size_t scanned_ = 0;  // buffer_[0, scanned_) holds no newline
  std::int64_t next_id_ = 1;
  std::map<std::int64_t, std::string> pending_;  // id -> method, sent and not yet replied
  std::map<std::int64_t, ControlReply> replies_;  // arrived, not yet taken
  std::int64_t waiting_for_ = 0;  // the id Wait is on: an id-less error reply is its
  std::string closed_because_;    // why the connection was closed (Fail)
};

}  // namespace mocap::daemon
