#include "daemon/control_client.h"

#include <fcntl.h>
#include <grp.h>
#include <poll.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/un.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstring>
#include <filesystem>
#include <optional>
#include <vector>

namespace mocap::daemon {
namespace {

using Clock = std::chrono::steady_clock;

// Milliseconds left until `deadline` (>= 0), or -1 (for ever) when there is none.
int RemainingMs(const std::optional<Clock::time_point>& deadline) {
  if (!deadline) return -1;
  const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(*deadline - Clock::now());
  return static_cast<int>(std::max<std::int64_t>(0, left.count()));
}

std::optional<Clock::time_point> DeadlineIn(int timeout_ms) {
  if (timeout_ms < 0) return std::nullopt;
  return Clock::now() + std::chrono::milliseconds(timeout_ms);
}

std::string GroupName(gid_t gid) {
  std::vector<char> buf(16384);
  group g{};
  group* found = nullptr;
  if (getgrgid_r(gid, &g, buf.data(), buf.size(), &found) == 0 && found) return g.gr_name;
  return std::to_string(gid);
}

// The start of a line the daemon sent, for an error message.
std::string Excerpt(const std::string& line) {
  constexpr std::size_t kShown = 80;
  return line.size() <= kShown ? line : line.substr(0, kShown) + "...";
}

// reply_timeout_ms as a wait: <= 0 is "for ever" (-1 to poll()).
int SilenceLimitMs(const ControlClientOptions& options) {
  return options.reply_timeout_ms > 0 ? options.reply_timeout_ms : -1;
}

std::string Seconds(int ms) {
  return ms % 1000 == 0 ? std::to_string(ms / 1000) + " s" : std::to_string(ms) + " ms";
}

}  // namespace

bool ControlClientOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& m) {
    if (error) *error = m;
    return false;
  };
  if (socket_path.empty()) return fail("socket_path: must not be empty");
  if (socket_path.size() >= sizeof(sockaddr_un{}.sun_path))
    return fail("socket_path: \"" + socket_path + "\" is " + std::to_string(socket_path.size()) +
                " bytes long; a Unix socket path holds at most " +
                std::to_string(sizeof(sockaddr_un{}.sun_path) - 1));
  if (max_line_bytes < 1024)
    return fail("max_line_bytes: " + std::to_string(max_line_bytes) + " is below 1024");
  return true;
}

std::string DescribeConnectError(const std::string& path, int error_number) {
  struct stat st{};
  switch (error_number) {
    case ENOENT:
      return "mocapd is not running (no socket at " + path + ")";
    case ECONNREFUSED:
      if (stat(path.c_str(), &st) == 0 && !S_ISSOCK(st.st_mode))
        return path + " is not a socket (is --socket right?)";
      return "mocapd is not running (" + path +
             " exists but nobody listens on it: the socket of a daemon that stopped)";
    case EACCES:
    case EPERM: {
      // The socket (0660) or its directory refused us: name the group that owns whichever it is.
      std::string denied = path;
      if (stat(path.c_str(), &st) != 0) {
        denied = std::filesystem::path(path).parent_path().string();
        if (stat(denied.c_str(), &st) != 0)
          return "permission denied on " + path + ": " + std::strerror(error_number);
      }
      return "permission denied on " + denied + ": you need to be in group " +
             GroupName(st.st_gid);
    }
    case EAGAIN:
      return "mocapd at " + path + " is not accepting connections (its queue is full)";
    case ENOTDIR:
      return "mocapd is not running (no socket at " + path + ": a component is not a directory)";
    default:
      return "cannot connect to mocapd at " + path + ": " + std::strerror(error_number);
  }
}

Status ControlClient::Connect(const ControlClientOptions& options,
                              std::unique_ptr<ControlClient>* out) {
  std::string error;
  if (!options.IsValid(&error)) return Status::Error(error);
  const int fd = socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0);
  if (fd < 0) return Status::Error(std::string("cannot create a Unix socket: ") + strerror(errno));
  sockaddr_un addr{};
  addr.sun_family = AF_UNIX;
  std::memcpy(addr.sun_path, options.socket_path.data(), options.socket_path.size());
  if (connect(fd, reinterpret_cast<const sockaddr*>(&addr), sizeof addr) != 0) {
    const int e = errno;
    close(fd);
    return Status::Error(DescribeConnectError(options.socket_path, e));
  }
  return Adopt(fd, options, out);
}

Status ControlClient::Adopt(int fd, const ControlClientOptions& options,
                            std::unique_ptr<ControlClient>* out) {
  std::string error;
  if (!options.IsValid(&error)) {
    close(fd);
    return Status::Error(error);
  }
  const int flags = fcntl(fd, F_GETFL);
  if (flags < 0 || fcntl(fd, F_SETFL, flags | O_NONBLOCK) != 0) {
    close(fd);
    return Status::Error(std::string("cannot make the control socket non-blocking: ") +
                         strerror(errno));
  }
  std::unique_ptr<ControlClient> client(new ControlClient(fd, options));
  MOCAP_RETURN_IF_ERROR(client->ReadHello());
  *out = std::move(client);
  return Status::Ok();
}

ControlClient::~ControlClient() {
  if (fd_ >= 0) close(fd_);
}

Status ControlClient::Fail(std::string message) {
  if (fd_ >= 0) close(fd_);
  fd_ = -1;
  closed_because_ = message;
  return Status::Error(std::move(message));
}

std::string ControlClient::Describe(std::int64_t id) const {
  auto it = pending_.find(id);
  return "request " + std::to_string(id) + (it == pending_.end() ? "" : " (" + it->second + ")");
}

Status ControlClient::ReadHello() {
  std::string line;
  bool got = false;
  if (Status s = ReadLine(&line, SilenceLimitMs(options_), &got); !s)
    return Status::Error(s.message() + " before its hello (on " + options_.socket_path + ")");
  if (!got)
    return Fail("no hello from mocapd on " + options_.socket_path + " within " +
                Seconds(options_.reply_timeout_ms));
  const nlohmann::json hello = nlohmann::json::parse(line, nullptr, false);
  if (!hello.is_object() || hello.value("event", nlohmann::json()) != "hello" ||
      !hello.contains("protocol") || !hello["protocol"].is_number_integer())
    return Fail(options_.socket_path + ": expected mocapd's hello, got: " + Excerpt(line));
  hello_.protocol = hello["protocol"].get<int>();
  if (hello_.protocol != kControlProtocolVersion)
    return Fail("mocapd on " + options_.socket_path + " speaks control protocol " +
                std::to_string(hello_.protocol) + "; this client speaks " +
                std::to_string(kControlProtocolVersion));
  if (auto it = hello.find("daemon"); it != hello.end() && it->is_string()) hello_.daemon = *it;
  if (auto it = hello.find("may_control"); it != hello.end() && it->is_boolean())
    hello_.may_control = *it;
  if (auto it = hello.find("uid"); it != hello.end() && it->is_number_integer()) hello_.uid = *it;
  return Status::Ok();
}

Status ControlClient::ReadLine(std::string* line, int timeout_ms, bool* got) {
  *got = false;
  const auto deadline = DeadlineIn(timeout_ms);
  for (;;) {
    if (fd_ < 0) return Status::Error("not connected to mocapd (" + closed_because_ + ")");
    // Only the bytes not yet searched: a long line arrives in many reads.
    const std::size_t newline = buffer_.find('\n', scanned_);
    if (newline != std::string::npos && newline <= options_.max_line_bytes) {
      line->assign(buffer_, 0, newline);
      buffer_.erase(0, newline + 1);
      scanned_ = 0;
      *got = true;
      return Status::Ok();
    }
    scanned_ = buffer_.size();
    if (buffer_.size() > options_.max_line_bytes)
      return Fail("mocapd sent a line longer than " + std::to_string(options_.max_line_bytes) +
                  " bytes (the client's limit)");
    pollfd p{fd_, POLLIN, 0};
    const int ready = poll(&p, 1, RemainingMs(deadline));
    if (ready < 0 && errno != EINTR)
      return Fail(std::string("waiting for mocapd: ") + strerror(errno));
    // A signal (EINTR) ends the wait too: the caller decides whether to go on.
    if (ready <= 0) return Status::Ok();
    char chunk[65536];
    const ssize_t n = read(fd_, chunk, sizeof chunk);
    if (n == 0)
      return Fail(buffer_.empty() ? "mocapd closed the connection"
                                  : "mocapd closed the connection in the middle of a message");
    if (n < 0) {
      if (errno == EINTR || errno == EAGAIN) continue;
      return Fail(std::string("reading from mocapd: ") + strerror(errno));
    }
    buffer_.append(chunk, static_cast<std::size_t>(n));
  }
}

Status ControlClient::ReadMessage(int timeout_ms, bool* got, nlohmann::json* event,
                                  bool* is_event) {
  std::string line;
  MOCAP_RETURN_IF_ERROR(ReadLine(&line, timeout_ms, got));
  *is_event = false;
  if (!*got) return Status::Ok();
  nlohmann::json message = nlohmann::json::parse(line, nullptr, false);
  if (!message.is_object())
    return Fail("mocapd sent a line that is not a JSON object: " + Excerpt(line));
  const bool reply = !message.contains("event") && message.contains("id") &&
                     (message.contains("result") || message.contains("error"));
  if (!reply) {
    *event = std::move(message);
    *is_event = true;
    return Status::Ok();
  }
  ControlReply r;
  if (auto it = message.find("error"); it != message.end()) {
    const nlohmann::json& e = *it;
    r.error_code = e.is_object() && e.value("code", nlohmann::json()).is_string()
                       ? e["code"].get<std::string>()
                       : "";
    if (r.error_code.empty()) r.error_code = "internal";  // a reply that failed without a code
    if (e.is_object() && e.value("message", nlohmann::json()).is_string())
      r.error_message = e["message"].get<std::string>();
    else
      r.error_message = "mocapd's error reply has no message: " + Excerpt(line);
  } else {
    r.result = std::move(message["result"]);
  }
  std::int64_t id = 0;
  const nlohmann::json& id_value = message["id"];
  if (id_value.is_number_integer()) {
    id = id_value.get<std::int64_t>();
  } else if (id_value.is_null() && !r.ok()) {
    // The daemon could not read a request of ours (e.g. line_too_long): the one waited for, or
    // else the oldest still pending.
    id = waiting_for_ ? waiting_for_ : (pending_.empty() ? 0 : pending_.begin()->first);
  }
  if (pending_.erase(id)) replies_[id] = std::move(r);
  // A reply to no request of ours is dropped: nothing waits for it.
  return Status::Ok();
}

Status ControlClient::Send(const std::string& method, const nlohmann::json& params,
                           std::int64_t* id) {
  if (fd_ < 0) return Status::Error("not connected to mocapd (" + closed_because_ + ")");
  const std::int64_t request_id = next_id_++;
  nlohmann::json request = {{"id", request_id}, {"method", method}};
  if (!params.is_null()) request["params"] = params;
  const std::string line = request.dump() + "\n";
  std::size_t sent = 0;
  const auto deadline = DeadlineIn(SilenceLimitMs(options_));
  while (sent < line.size()) {
    const ssize_t n = send(fd_, line.data() + sent, line.size() - sent, MSG_NOSIGNAL);
    if (n > 0) {
      sent += static_cast<std::size_t>(n);
      continue;
    }
    if (n < 0 && errno == EINTR) continue;
    if (n < 0 && errno == EAGAIN) {
      pollfd p{fd_, POLLOUT, 0};
      const int ready = poll(&p, 1, RemainingMs(deadline));
      if (ready == 0)
        return Fail("mocapd did not take request " + std::to_string(request_id) + " (" + method +
                    ") within " + Seconds(options_.reply_timeout_ms));
      continue;
    }
    return Fail(errno == EPIPE || errno == ECONNRESET
                    ? "mocapd closed the connection (sending request " +
                          std::to_string(request_id) + ", " + method + ")"
                    : std::string("sending to mocapd: ") + strerror(errno));
  }
  pending_[request_id] = method;
  *id = request_id;
  return Status::Ok();
}

bool ControlClient::TakeReply(std::int64_t id, ControlReply* reply) {
  auto it = replies_.find(id);
  if (it == replies_.end()) return false;
  *reply = std::move(it->second);
  replies_.erase(it);
  return true;
}

Status ControlClient::Wait(std::int64_t id, ControlReply* reply, const EventHandler& on_event) {
  if (TakeReply(id, reply)) return Status::Ok();
  if (!pending_.count(id))
    return Status::Error("request " + std::to_string(id) + " is not waiting for a reply");
  const std::string what = Describe(id);
  waiting_for_ = id;
  auto last_heard = Clock::now();
  for (;;) {
    bool got = false, is_event = false;
    nlohmann::json event;
    int timeout = -1;
    if (options_.reply_timeout_ms > 0) {
      const auto silent = std::chrono::duration_cast<std::chrono::milliseconds>(
          Clock::now() - last_heard);
      timeout = std::max<int>(0, options_.reply_timeout_ms - static_cast<int>(silent.count()));
    }
    Status s = ReadMessage(timeout, &got, &event, &is_event);
    if (!s.ok()) {
      waiting_for_ = 0;
      return Status::Error(s.message() + " before replying to " + what);
    }
    if (got) {
      last_heard = Clock::now();
      if (is_event && on_event) on_event(event);
      if (TakeReply(id, reply)) {
        waiting_for_ = 0;
        return Status::Ok();
      }
    } else if (options_.reply_timeout_ms > 0 &&
               Clock::now() - last_heard >= std::chrono::milliseconds(options_.reply_timeout_ms)) {
      waiting_for_ = 0;
      return Fail("mocapd sent nothing for " + Seconds(options_.reply_timeout_ms) +
                  " while " + what + " waited for its reply");
    }
  }
}

Status ControlClient::Call(const std::string& method, const nlohmann::json& params,
                           ControlReply* reply, const EventHandler& on_event) {
  std::int64_t id = 0;
  MOCAP_RETURN_IF_ERROR(Send(method, params, &id));
  return Wait(id, reply, on_event);
}

Status ControlClient::Poll(int timeout_ms, const EventHandler& on_event) {
  int timeout = timeout_ms;
  for (;;) {
    bool got = false, is_event = false;
    nlohmann::json event;
    MOCAP_RETURN_IF_ERROR(ReadMessage(timeout, &got, &event, &is_event));
    if (!got) return Status::Ok();
    if (is_event && on_event) on_event(event);
    timeout = 0;  // then only what is already there
  }
}

Status ControlClient::NextEvent(nlohmann::json* event, int timeout_ms, bool* got) {
  *got = false;
  const auto deadline = DeadlineIn(timeout_ms);
  for (;;) {
    bool got_message = false, is_event = false;
    MOCAP_RETURN_IF_ERROR(ReadMessage(RemainingMs(deadline), &got_message, event, &is_event));
    if (got_message && is_event) {
      *got = true;
      return Status::Ok();
    }
    if (deadline && Clock::now() >= *deadline) return Status::Ok();
  }
}

}  // namespace mocap::daemon
