// The control socket of mocapd: a Unix stream socket speaking newline-delimited JSON
// (daemon/PROTOCOL.md), served from the daemon's sd-event loop.
//
// The server owns the transport only: the listening socket (created by itself, or handed over by
// systemd's socket activation), the clients, their SO_PEERCRED credentials, line framing, JSON
// parsing and the request envelope (id, method, params). What a method does is the handler's
// (daemon/daemon.h). Everything here runs on the loop's thread and never blocks:
//   - reads are non-blocking; a client's partial line is kept up to `max_line_bytes`, beyond
//     which it gets `line_too_long` and is disconnected (a 100 MB line costs 1 MB of memory);
//   - writes are non-blocking into a per-client output buffer drained when the socket is
//     writable. Replies and progress events always go in (a client that lets more than
//     `max_output_bytes` of them pile up is disconnected, with a logged reason); stream frames go
//     in only while fewer than `stream_queue_frames` of them wait (the config's
//     `subscriber_queue_frames`: 400, 2 s at 200 Hz) and the buffer holds less than
//     `stream_output_bytes`, otherwise they are dropped and counted, and the client is told how
//     many it lost once it catches up. So a subscriber may pause for up to that long (a viewer's
//     window dragged, a logger's disk stalling) without losing a frame, one that never reads
//     holds at most `stream_output_bytes`, and neither costs the pipeline anything
//     (bench/daemon_latency --slow-subscriber measures where the loss begins).
//   - a client with more than `max_pending` requests whose replies have not gone out is answered
//     `busy` (a request flood cannot queue work without bound).
#pragma once
#include <sys/types.h>
#include <systemd/sd-event.h>

#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <string>

#include <nlohmann/json.hpp>

#include "model/status.h"

namespace mocap::daemon {

struct ControlServerOptions {
  std::string socket_path = "/run/mocapd/control.sock";
  unsigned socket_mode = 0660;
  std::string control_group = "mocap";  // may change state (and root); others read only
  int max_clients = 64;
  std::size_t max_line_bytes = 1 << 20;
  // Replies + events + stream frames waiting: beyond, disconnect. 9 MiB holds the largest reply
  // (an inline export of 4 MiB, base64: 5.4 MiB) beside a full stream backlog, and bounds what
  // 64 clients that never read can cost (576 MiB).
  std::size_t max_output_bytes = 9u << 20;
  // Stream frames waiting per client, and their bytes: beyond either, frames are dropped. 3 MiB
  // holds 400 frames of the `markers` stream (6.3 kB each with the default model's 43 markers,
  // bench/daemon_latency --slow-subscriber); a subscriber to every stream holds fewer.
  int stream_queue_frames = 400;
  std::size_t stream_output_bytes = 3u << 20;
  int max_pending = 64;
  bool IsValid(std::string* error) const;
};

struct ClientInfo {
  std::uint64_t id = 0;
  uid_t uid = 0;
  gid_t gid = 0;
  pid_t pid = 0;
  bool may_control = false;
};

// Stable error codes of the protocol (daemon/PROTOCOL.md).
namespace error_code {
inline constexpr const char* kParseError = "parse_error";
inline constexpr const char* kInvalidRequest = "invalid_request";
inline constexpr const char* kLineTooLong = "line_too_long";
inline constexpr const char* kUnknownMethod = "unknown_method";
inline constexpr const char* kInvalidParams = "invalid_params";
inline constexpr const char* kForbidden = "forbidden";
inline constexpr const char* kNotFound = "not_found";
inline constexpr const char* kConflict = "conflict";
inline constexpr const char* kBusy = "busy";
inline constexpr const char* kUnavailable = "unavailable";
inline constexpr const char* kFailed = "failed";
inline constexpr const char* kCancelled = "cancelled";
inline constexpr const char* kInternal = "internal";
}  // namespace error_code

class ControlServer {
 public:
  // A request, already checked for its envelope. The handler answers with Reply/ReplyError now or
  // later (long methods); the client may be gone by then (Reply is then a no-op).
  using RequestHandler = std::function<void(const ClientInfo& client, const nlohmann::json& id,
                                            const std::string& method,
                                            const nlohmann::json& params)>;
  using DisconnectHandler = std::function<void(std::uint64_t client)>;
  // Logging is the daemon's: the server reports what happened to clients through this.
  using LogFn = std::function<void(int priority, const std::string& message)>;

  ControlServer(sd_event* loop, ControlServerOptions options, RequestHandler on_request,
                DisconnectHandler on_disconnect, LogFn log);
  ~ControlServer();
  ControlServer(const ControlServer&) = delete;
  ControlServer& operator=(const ControlServer&) = delete;

  // Listens on `fd` when >= 0 (socket activation: already bound and listening), otherwise creates
  // the socket at options.socket_path (its directory too), with its mode and group. A stale socket
  // file (no one listening) is replaced; a live one is an error (another mocapd runs there).
  Status Listen(int fd = -1);
  // Stops accepting and closes every client (after trying to flush what they were sent).
  void Close();
  // New limits (config.reload); they apply to new lines and new clients.
  void SetLimits(int max_clients, std::size_t max_line_bytes, int max_pending,
                 int stream_queue_frames);
  // Who may change state, from the next client on (clients keep what their hello said).
  void SetControlGroup(const std::string& group) { options_.control_group = group; }

  std::string hello_daemon = "mocapd";  // the hello's "daemon" field

  void Reply(std::uint64_t client, const nlohmann::json& id, nlohmann::json result);
  void ReplyError(std::uint64_t client, const nlohmann::json& id, const std::string& code,
                  const std::string& message);
  // A progress (or other) event: always queued.
  void SendEvent(std::uint64_t client, const nlohmann::json& event);
  // A stream line (already serialised, with its '\n'): queued only if the client keeps up.
  // Returns false when dropped.
  bool SendStream(std::uint64_t client, const std::string& line);
  bool HasClient(std::uint64_t client) const { return clients_.count(client) > 0; }
  int client_count() const { return static_cast<int>(clients_.size()); }
  std::uint64_t clients_refused() const { return clients_refused_; }

 private:
  struct Client {
    std::uint64_t id = 0;
    int fd = -1;
    sd_event_source* source = nullptr;
    ClientInfo info;
    std::string in;
    std::string out;
    std::size_t out_offset = 0;
    int pending = 0;  // requests handed to the handler and not yet answered
    std::uint64_t stream_dropped = 0;  // not yet told
    // Bytes ever queued and ever sent, and the end (in bytes ever queued) of each stream frame
    // not yet sent: the frames waiting are the ends beyond sent_bytes.
    std::uint64_t queued_bytes = 0, sent_bytes = 0;
    std::deque<std::uint64_t> stream_ends;
    bool closing = false;  // flush, then close
  };
  static int OnAccept(sd_event_source* s, int fd, uint32_t revents, void* self);
  static int OnClient(sd_event_source* s, int fd, uint32_t revents, void* self);
  void Accept();
  void ReadFrom(Client* c);
  void HandleLine(Client* c, std::string_view line);
  // An error answered by the server itself (parse, envelope, busy): the request never reached the
  // handler, so it is not one of the client's pending ones.
  void EnvelopeError(Client* c, const nlohmann::json& id, const std::string& code,
                     const std::string& message);
  void LineTooLong(Client* c);  // error, then close once it is sent
  void Queue(Client* c, const std::string& line);
  void Flush(Client* c);
  void UpdateEvents(Client* c);
  void Drop(Client* c, const std::string& reason);
  bool MayControl(uid_t uid, gid_t gid) const;

  sd_event* loop_;
  ControlServerOptions options_;
  RequestHandler on_request_;
  DisconnectHandler on_disconnect_;
  LogFn log_;
  int listen_fd_ = -1;
  bool own_socket_file_ = false;
  sd_event_source* listen_source_ = nullptr;
  std::map<std::uint64_t, std::unique_ptr<Client>> clients_;
  std::uint64_t next_id_ = 1;
  std::uint64_t clients_refused_ = 0;
};

}  // namespace mocap::daemon
