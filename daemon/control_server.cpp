#include "daemon/control_server.h"

#include <fcntl.h>
#include <grp.h>
#include <pwd.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/un.h>
#include <syslog.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <filesystem>
#include <vector>

namespace mocap::daemon {

namespace {

std::string Errno(const std::string& what) { return what + ": " + std::strerror(errno); }

// The id as the reply should repeat it: numbers and strings as given, anything else null.
nlohmann::json UsableId(const nlohmann::json& request) {
  if (!request.is_object()) return nullptr;
  auto it = request.find("id");
  if (it == request.end()) return nullptr;
  if (it->is_number_integer() || it->is_number_unsigned() || it->is_string()) return *it;
  return nullptr;
}

std::string Dump(const nlohmann::json& j) {
  // Strings a client sent may hold anything; never throw on output.
  return j.dump(-1, ' ', false, nlohmann::json::error_handler_t::replace) + "\n";
}

}  // namespace

bool ControlServerOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& m) {
    if (error) *error = m;
    return false;
  };
  if (socket_path.empty()) return fail("socket path is empty");
  if (socket_path.size() >= sizeof(sockaddr_un{}.sun_path))
    return fail("socket path '" + socket_path + "' is longer than " +
                std::to_string(sizeof(sockaddr_un{}.sun_path) - 1) + " bytes");
  if (max_clients < 1) return fail("max_clients must be >= 1");
  if (max_line_bytes < 1024) return fail("max_line_bytes must be >= 1024");
  if (max_pending < 1) return fail("max_pending must be >= 1");
  if (stream_queue_frames < 1) return fail("stream_queue_frames must be >= 1");
  if (stream_output_bytes < 4096 || max_output_bytes < stream_output_bytes)
    return fail("output limits: stream_output_bytes >= 4096 and <= max_output_bytes");
  return true;
}

ControlServer::ControlServer(sd_event* loop, ControlServerOptions options,
                             RequestHandler on_request, DisconnectHandler on_disconnect, LogFn log)
    : loop_(loop),
      options_(std::move(options)),
      on_request_(std::move(on_request)),
      on_disconnect_(std::move(on_disconnect)),
      log_(std::move(log)) {}

ControlServer::~ControlServer() { Close(); }

Status ControlServer::Listen(int fd) {
  std::string error;
  if (!options_.IsValid(&error)) return Status::Error("control socket: " + error);
  if (fd >= 0) {
    listen_fd_ = fd;
    own_socket_file_ = false;
    const int flags = fcntl(fd, F_GETFL);
    if (flags < 0 || fcntl(fd, F_SETFL, flags | O_NONBLOCK) < 0)
      return Status::Error(Errno("control socket (from systemd): fcntl"));
  } else {
    namespace fs = std::filesystem;
    const fs::path path(options_.socket_path);
    std::error_code ec;
    if (path.has_parent_path()) fs::create_directories(path.parent_path(), ec);
    if (ec)
      return Status::Error("control socket: cannot create directory '" +
                           path.parent_path().string() + "': " + ec.message());
    sockaddr_un addr{};
    addr.sun_family = AF_UNIX;
    std::strncpy(addr.sun_path, options_.socket_path.c_str(), sizeof addr.sun_path - 1);
    listen_fd_ = socket(AF_UNIX, SOCK_STREAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
    if (listen_fd_ < 0) return Status::Error(Errno("control socket: socket"));
    if (fs::exists(fs::symlink_status(path, ec))) {
      // Someone listening there is another daemon; a file no one answers on is stale.
      const int probe = socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0);
      const bool live =
          probe >= 0 && connect(probe, reinterpret_cast<sockaddr*>(&addr), sizeof addr) == 0;
      if (probe >= 0) ::close(probe);
      if (live) {
        ::close(listen_fd_);
        listen_fd_ = -1;
        return Status::Error("control socket '" + options_.socket_path +
                             "': another daemon is listening there");
      }
      if (!fs::is_socket(fs::symlink_status(path, ec))) {
        ::close(listen_fd_);
        listen_fd_ = -1;
        return Status::Error("control socket '" + options_.socket_path +
                             "' exists and is not a socket");
      }
      ::unlink(options_.socket_path.c_str());
    }
    // Created with no access for anyone, then opened up to the mode: no window in which a
    // client outside the group could connect.
    const mode_t old = umask(0777);
    const int rc = bind(listen_fd_, reinterpret_cast<sockaddr*>(&addr), sizeof addr);
    umask(old);
    if (rc < 0) {
      const std::string e = Errno("control socket '" + options_.socket_path + "': bind");
      ::close(listen_fd_);
      listen_fd_ = -1;
      return Status::Error(e);
    }
    own_socket_file_ = true;
    if (!options_.control_group.empty()) {
      if (const group* g = getgrnam(options_.control_group.c_str())) {
        if (chown(options_.socket_path.c_str(), static_cast<uid_t>(-1), g->gr_gid) < 0 && log_)
          log_(LOG_WARNING, Errno("control socket: chown to group '" + options_.control_group + "'"));
      } else if (log_) {
        log_(LOG_WARNING, "control group '" + options_.control_group +
                              "' does not exist: only root may change state");
      }
    }
    if (chmod(options_.socket_path.c_str(), options_.socket_mode) < 0) {
      return Status::Error(Errno("control socket '" + options_.socket_path + "': chmod"));
    }
    if (listen(listen_fd_, 128) < 0) return Status::Error(Errno("control socket: listen"));
  }
  const int r = sd_event_add_io(loop_, &listen_source_, listen_fd_, EPOLLIN, &OnAccept, this);
  if (r < 0) return Status::Error(std::string("control socket: sd_event_add_io: ") + std::strerror(-r));
  return Status::Ok();
}

void ControlServer::Close() {
  if (listen_source_) listen_source_ = sd_event_source_disable_unref(listen_source_);
  if (listen_fd_ >= 0) {
    ::close(listen_fd_);
    listen_fd_ = -1;
    if (own_socket_file_) ::unlink(options_.socket_path.c_str());
  }
  std::vector<std::uint64_t> ids;
  for (auto& [id, c] : clients_) ids.push_back(id);
  for (std::uint64_t id : ids) {
    auto it = clients_.find(id);
    if (it == clients_.end()) continue;
    Flush(it->second.get());
    Drop(it->second.get(), "");
  }
}

void ControlServer::SetLimits(int max_clients, std::size_t max_line_bytes, int max_pending,
                              int stream_queue_frames) {
  options_.max_clients = max_clients;
  options_.max_line_bytes = max_line_bytes;
  options_.max_pending = max_pending;
  options_.stream_queue_frames = stream_queue_frames;
}

int ControlServer::OnAccept(sd_event_source*, int, uint32_t, void* self) {
  static_cast<ControlServer*>(self)->Accept();
  return 0;
}

bool ControlServer::MayControl(uid_t uid, gid_t gid) const {
  if (uid == 0) return true;
  if (options_.control_group.empty()) return false;
  const group* g = getgrnam(options_.control_group.c_str());
  if (!g) return false;
  if (gid == g->gr_gid) return true;
  // Supplementary groups: those of the user's account (SO_PEERCRED carries only the primary).
  if (const passwd* pw = getpwuid(uid)) {
    int n = 64;
    std::vector<gid_t> groups(n);
    if (getgrouplist(pw->pw_name, pw->pw_gid, groups.data(), &n) < 0) {
      groups.resize(n);
      getgrouplist(pw->pw_name, pw->pw_gid, groups.data(), &n);
    }
    groups.resize(std::max(0, n));
    return std::find(groups.begin(), groups.end(), g->gr_gid) != groups.end();
  }
  return false;
}

void ControlServer::Accept() {
  for (;;) {
    const int fd = accept4(listen_fd_, nullptr, nullptr, SOCK_NONBLOCK | SOCK_CLOEXEC);
    if (fd < 0) {
      if (errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR && log_)
        log_(LOG_WARNING, Errno("control socket: accept"));
      return;
    }
    ucred cred{};
    socklen_t len = sizeof cred;
    if (getsockopt(fd, SOL_SOCKET, SO_PEERCRED, &cred, &len) < 0) {
      if (log_) log_(LOG_WARNING, Errno("control socket: SO_PEERCRED"));
      ::close(fd);
      continue;
    }
    if (static_cast<int>(clients_.size()) >= options_.max_clients) {
      ++clients_refused_;
      const std::string line = Dump({{"event", "error"},
                                     {"error",
                                      {{"code", error_code::kBusy},
                                       {"message", "too many clients (" +
                                                       std::to_string(options_.max_clients) +
                                                       "); try again later"}}}});
      [[maybe_unused]] ssize_t n = ::send(fd, line.data(), line.size(), MSG_NOSIGNAL | MSG_DONTWAIT);
      ::close(fd);
      if (log_ && (clients_refused_ < 10 || clients_refused_ % 1000 == 0))
        log_(LOG_WARNING, "control socket: refused a client of uid " + std::to_string(cred.uid) +
                              ": " + std::to_string(options_.max_clients) + " clients already (" +
                              std::to_string(clients_refused_) + " refused so far)");
      continue;
    }
    auto c = std::make_unique<Client>();
    c->id = next_id_++;
    c->fd = fd;
    c->info.id = c->id;
    c->info.uid = cred.uid;
    c->info.gid = cred.gid;
    c->info.pid = cred.pid;
    c->info.may_control = MayControl(cred.uid, cred.gid);
    if (sd_event_add_io(loop_, &c->source, fd, EPOLLIN, &OnClient, this) < 0) {
      ::close(fd);
      continue;
    }
    Client* raw = c.get();
    clients_[c->id] = std::move(c);
    // OnClient finds the client by its fd: a Client may be gone by the time an event queued for
    // it is dispatched, so the source never carries a pointer to it.
    sd_event_source_set_description(raw->source, "control-client");
    Queue(raw, Dump({{"event", "hello"},
                     {"protocol", 1},
                     {"daemon", hello_daemon},
                     {"uid", cred.uid},
                     {"may_control", raw->info.may_control}}));
  }
}

int ControlServer::OnClient(sd_event_source* s, int fd, uint32_t revents, void* self) {
  auto* server = static_cast<ControlServer*>(self);
  Client* c = nullptr;
  for (auto& [id, cl] : server->clients_)
    if (cl->fd == fd) {
      c = cl.get();
      break;
    }
  if (!c) return 0;
  const std::uint64_t id = c->id;
  if (revents & EPOLLOUT) server->Flush(c);
  if (!server->HasClient(id)) return 0;
  if (revents & (EPOLLIN | EPOLLHUP | EPOLLERR)) server->ReadFrom(c);
  return 0;
}

void ControlServer::ReadFrom(Client* c) {
  const std::uint64_t id = c->id;
  // Fairness: one 2 KB read per wake-up (a hundred short requests at most, ~30 ms of status
  // replies), then the loop serves the frames and the other clients; epoll wakes it again for
  // the rest. A 16 KB read was ~550 status requests, ~165 ms of work, stretched past the loop's
  // 320 ms frame queue when other processes took half the CPU (CI, 28 Nov 2026). A longer line
  // gathers in `in` over several wake-ups, up to max_line_bytes.
  char buf[2048];
  for (int rounds = 0; rounds < 1; ++rounds) {
    const ssize_t n = ::recv(c->fd, buf, sizeof buf, 0);
    if (n == 0) {
      Drop(c, "");
      return;
    }
    if (n < 0) {
      if (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR) return;
      Drop(c, Errno("recv"));
      return;
    }
    if (c->closing) continue;  // discard what arrives after a fatal error
    std::size_t start = 0;
    for (ssize_t i = 0; i < n; ++i) {
      if (buf[i] != '\n') continue;
      if (c->in.size() + (i - start) > options_.max_line_bytes) {
        c->in.clear();
        LineTooLong(c);
        return;
      }
      if (c->in.empty()) {
        HandleLine(c, std::string_view(buf + start, i - start));
      } else {
        c->in.append(buf + start, i - start);
        std::string line;
        line.swap(c->in);
        HandleLine(c, line);
      }
      if (!HasClient(id) || c->closing) return;
      start = i + 1;
    }
    c->in.append(buf + start, n - start);
    if (c->in.size() > options_.max_line_bytes) {
      c->in.clear();
      c->in.shrink_to_fit();
      LineTooLong(c);
      return;
    }
  }
}

void ControlServer::LineTooLong(Client* c) {
  Queue(c, Dump({{"id", nullptr},
                 {"error",
                  {{"code", error_code::kLineTooLong},
                   {"message", "request line longer than " +
                                   std::to_string(options_.max_line_bytes) +
                                   " bytes; closing the connection"}}}}));
  if (!HasClient(c->id)) return;
  if (log_)
    log_(LOG_WARNING, "client " + std::to_string(c->id) + " (uid " + std::to_string(c->info.uid) +
                          ") disconnected: line longer than " +
                          std::to_string(options_.max_line_bytes) + " bytes");
  c->closing = true;
  Flush(c);
}

void ControlServer::HandleLine(Client* c, std::string_view line) {
  if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
  if (line.find_first_not_of(" \t") == std::string_view::npos) return;  // blank lines are no-ops
  nlohmann::json request;
  try {
    request = nlohmann::json::parse(line.begin(), line.end());
  } catch (const nlohmann::json::exception& e) {
    // parse_error, and out_of_range for a number beyond a double ("1e9999"): the fuzzer's find,
    // which ended the daemon when only parse_error was caught.
    EnvelopeError(c, nullptr, error_code::kParseError, std::string("not JSON: ") + e.what());
    return;
  }
  const nlohmann::json id = UsableId(request);
  if (!request.is_object()) {
    EnvelopeError(c, nullptr, error_code::kInvalidRequest, "a request is a JSON object");
    return;
  }
  if (!request.contains("id")) {
    EnvelopeError(c, nullptr, error_code::kInvalidRequest, "id: missing");
    return;
  }
  if (id.is_null()) {
    EnvelopeError(c, nullptr, error_code::kInvalidRequest, "id: expected a number or a string");
    return;
  }
  auto m = request.find("method");
  if (m == request.end() || !m->is_string()) {
    EnvelopeError(c, id, error_code::kInvalidRequest,
               m == request.end() ? "method: missing" : "method: expected a string");
    return;
  }
  nlohmann::json params = nlohmann::json::object();
  if (auto p = request.find("params"); p != request.end()) {
    if (p->is_null()) {
    } else if (!p->is_object()) {
      EnvelopeError(c, id, error_code::kInvalidRequest, "params: expected an object");
      return;
    } else {
      params = *p;
    }
  }
  if (c->pending >= options_.max_pending) {
    EnvelopeError(c, id, error_code::kBusy,
               "too many requests pending on this connection (" +
                   std::to_string(options_.max_pending) + "); wait for their replies");
    return;
  }
  ++c->pending;
  const ClientInfo info = c->info;
  on_request_(info, id, m->get<std::string>(), params);
}

void ControlServer::Reply(std::uint64_t client, const nlohmann::json& id, nlohmann::json result) {
  auto it = clients_.find(client);
  if (it == clients_.end()) return;
  Client* c = it->second.get();
  if (c->pending > 0) --c->pending;
  Queue(c, Dump({{"id", id}, {"result", std::move(result)}}));
}

void ControlServer::ReplyError(std::uint64_t client, const nlohmann::json& id,
                               const std::string& code, const std::string& message) {
  auto it = clients_.find(client);
  if (it == clients_.end()) return;
  Client* c = it->second.get();
  if (c->pending > 0) --c->pending;
  Queue(c, Dump({{"id", id}, {"error", {{"code", code}, {"message", message}}}}));
}

void ControlServer::EnvelopeError(Client* c, const nlohmann::json& id, const std::string& code,
                                  const std::string& message) {
  // Not counted as pending, so not uncounted: a `busy` (or a bad envelope) must not free a slot
  // of the requests still running, or a flood would get past max_pending.
  Queue(c, Dump({{"id", id}, {"error", {{"code", code}, {"message", message}}}}));
}

void ControlServer::SendEvent(std::uint64_t client, const nlohmann::json& event) {
  auto it = clients_.find(client);
  if (it == clients_.end()) return;
  Queue(it->second.get(), Dump(event));
}

bool ControlServer::SendStream(std::uint64_t client, const std::string& line) {
  auto it = clients_.find(client);
  if (it == clients_.end()) return false;
  Client* c = it->second.get();
  while (!c->stream_ends.empty() && c->stream_ends.front() <= c->sent_bytes)
    c->stream_ends.pop_front();
  if (c->closing || c->out.size() - c->out_offset >= options_.stream_output_bytes ||
      c->stream_ends.size() >= static_cast<std::size_t>(options_.stream_queue_frames)) {
    ++c->stream_dropped;
    return false;
  }
  if (c->stream_dropped > 0) {
    const std::uint64_t lost = c->stream_dropped;
    c->stream_dropped = 0;
    Queue(c, Dump({{"event", "dropped"}, {"count", lost}}));
    if (!HasClient(client)) return false;
  }
  Queue(c, line);
  if (!HasClient(client)) return false;
  if (c->queued_bytes > c->sent_bytes) c->stream_ends.push_back(c->queued_bytes);
  return true;
}

void ControlServer::Queue(Client* c, const std::string& line) {
  if (c->out.size() - c->out_offset + line.size() > options_.max_output_bytes) {
    if (log_)
      log_(LOG_WARNING, "client " + std::to_string(c->id) + " (uid " + std::to_string(c->info.uid) +
                            ") disconnected: it has not read " +
                            std::to_string(c->out.size() - c->out_offset) + " bytes of replies");
    Drop(c, "");
    return;
  }
  c->out += line;
  c->queued_bytes += line.size();
  Flush(c);
}

void ControlServer::Flush(Client* c) {
  const std::uint64_t id = c->id;
  while (c->out_offset < c->out.size()) {
    const ssize_t n = ::send(c->fd, c->out.data() + c->out_offset, c->out.size() - c->out_offset,
                             MSG_NOSIGNAL | MSG_DONTWAIT);
    if (n < 0) {
      if (errno == EAGAIN || errno == EWOULDBLOCK) break;
      if (errno == EINTR) continue;
      Drop(c, "");  // the peer went away mid-reply: nothing to tell it
      return;
    }
    c->out_offset += static_cast<std::size_t>(n);
    c->sent_bytes += static_cast<std::uint64_t>(n);
  }
  if (!HasClient(id)) return;
  if (c->out_offset == c->out.size()) {
    c->out.clear();
    c->out_offset = 0;
    if (c->closing) {
      Drop(c, "");
      return;
    }
  } else if (c->out_offset > (1u << 20)) {
    c->out.erase(0, c->out_offset);
    c->out_offset = 0;
  }
  UpdateEvents(c);
}

void ControlServer::UpdateEvents(Client* c) {
  const bool want_out = c->out_offset < c->out.size();
  sd_event_source_set_io_events(c->source, want_out ? (EPOLLIN | EPOLLOUT) : EPOLLIN);
}

void ControlServer::Drop(Client* c, const std::string& reason) {
  const std::uint64_t id = c->id;
  if (!reason.empty() && log_)
    log_(LOG_INFO, "client " + std::to_string(id) + " disconnected: " + reason);
  if (c->source) c->source = sd_event_source_disable_unref(c->source);
  if (c->fd >= 0) ::close(c->fd);
  clients_.erase(id);
  if (on_disconnect_) on_disconnect_(id);
}

}  // namespace mocap::daemon
