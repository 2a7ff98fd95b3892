// The control socket's server (daemon/control_server.h) on its own sd-event loop, driven in one
// thread by a client that writes bytes and reads what comes back: for fuzz/fuzz_control.cpp and
// tests/test_control_server.cpp. That client (LoopClient) serves any loop run on the client's
// thread: fuzz/fuzz_daemon.cpp drives the whole daemon's loop with it. No GoogleTest here (the
// fuzzers use it).
//
// The request handler stands in for the daemon: it answers each request at once with its method
// and params (so every line the server hands over comes back, params serialised again), or, with
// `answer = false`, holds every request unanswered (a daemon busy with long jobs). With
// `stream_method`, a request {"method":"stream","params":{"frames":N,"bytes":B}} is a pipeline
// publishing N stream frames of B bytes (JSON strings "fff...") to that client at once
// (ControlServer::SendStream), and
// its reply says how many were accepted: {"accepted":K}.
#pragma once
#include <sys/socket.h>
#include <sys/un.h>
#include <systemd/sd-event.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdlib>
#include <filesystem>
#include <functional>
#include <memory>
#include <string>
#include <string_view>

#include <nlohmann/json.hpp>

#include "daemon/control_server.h"

namespace mocap::testing {

// A client of a server whose event loop runs on the client's own thread (so it cannot block on
// the socket): a non-blocking connection that each Step() feeds what is left to send, then lets
// the loop take a turn (`turn`, true when the loop did something), then reads what came back.
class LoopClient {
 public:
  explicit LoopClient(const std::string& socket_path) {
    fd_ = socket(AF_UNIX, SOCK_STREAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
    if (fd_ < 0) return;
    sockaddr_un addr{};
    addr.sun_family = AF_UNIX;
    socket_path.copy(addr.sun_path, sizeof addr.sun_path - 1);
    if (connect(fd_, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0) Close();
  }
  ~LoopClient() { Close(); }
  LoopClient(const LoopClient&) = delete;
  LoopClient& operator=(const LoopClient&) = delete;

  bool connected() const { return fd_ >= 0; }
  void Send(std::string_view bytes) { to_send_.append(bytes); }
  bool all_sent() const { return sent_ == to_send_.size(); }
  void ShutdownWrite() {
    if (fd_ >= 0) shutdown(fd_, SHUT_WR);
    write_shut_ = true;
  }
  bool write_shut() const { return write_shut_; }
  // The server closed the connection: all it will say has been read.
  bool closed() const { return closed_ || fd_ < 0; }
  const std::string& received() const { return received_; }
  void Close() {
    if (fd_ >= 0) close(fd_);
    fd_ = -1;
  }

  // Sends, turns the loop, reads; true when anything moved.
  bool Step(const std::function<bool()>& turn) {
    bool moved = false;
    if (fd_ >= 0 && sent_ < to_send_.size()) {
      const ssize_t n = send(fd_, to_send_.data() + sent_, to_send_.size() - sent_, MSG_NOSIGNAL);
      if (n > 0) sent_ += static_cast<std::size_t>(n), moved = true;
      else if (n < 0 && errno != EAGAIN) sent_ = to_send_.size();  // the server closed on us
    }
    if (turn()) moved = true;
    char buf[65536];
    while (fd_ >= 0 && !closed_) {
      const ssize_t n = recv(fd_, buf, sizeof buf, 0);
      if (n <= 0) {
        closed_ = n == 0;
        break;
      }
      received_.append(buf, static_cast<std::size_t>(n));
      moved = true;
    }
    return moved;
  }

 private:
  int fd_ = -1;
  std::string to_send_, received_;
  std::size_t sent_ = 0;
  bool write_shut_ = false, closed_ = false;
};

class ControlServerHarness {
 public:
  // Listens on a socket in a fresh temporary directory; ok() says whether that worked.
  ControlServerHarness(daemon::ControlServerOptions options, bool answer = true,
                       bool stream_method = false)
      : answer_(answer), stream_method_(stream_method) {
    std::string pattern = (std::filesystem::temp_directory_path() / "mocap-control-XXXXXX").string();
    if (!mkdtemp(pattern.data())) return;
    dir_ = pattern;
    options.socket_path = dir_ + "/control.sock";
    options.control_group = "root";
    path_ = options.socket_path;
    if (sd_event_new(&loop_) < 0) return;
    server_ = std::make_unique<daemon::ControlServer>(
        loop_, options,
        [this](const daemon::ClientInfo& client, const nlohmann::json& id, const std::string& method,
               const nlohmann::json& params) {
          ++requests_;
          if (stream_method_ && method == "stream") {
            const int frames = params.value("frames", 0);
            // A JSON string of B bytes with its newline.
            const std::string line =
                "\"" + std::string(std::max(3, params.value("bytes", 3)) - 3, 'f') + "\"";
            int accepted = 0;
            for (int i = 0; i < frames; ++i) accepted += server_->SendStream(client.id, line + "\n");
            server_->Reply(client.id, id, {{"accepted", accepted}});
            return;
          }
          if (answer_) server_->Reply(client.id, id, {{"method", method}, {"params", params}});
        },
        nullptr, nullptr);
    ok_ = server_->Listen().ok();
  }
  ~ControlServerHarness() {
    if (server_) server_->Close();
    server_.reset();
    if (loop_) sd_event_unref(loop_);
    if (!dir_.empty()) std::filesystem::remove_all(dir_);
  }
  ControlServerHarness(const ControlServerHarness&) = delete;
  ControlServerHarness& operator=(const ControlServerHarness&) = delete;

  bool ok() const { return ok_; }
  // Requests handed to the handler so far.
  int requests() const { return requests_; }

  // A new client sends `bytes`, then ends its side of the connection (unless `keep_open`);
  // returns all the client read until the server closed the connection or stayed quiet for a
  // few turns of the loop with nothing left to send.
  std::string Exchange(std::string_view bytes, bool keep_open = false) {
    LoopClient client(path_);
    if (!client.connected()) return {};
    client.Send(bytes);
    const auto turn = [this] {
      bool moved = false;
      while (sd_event_run(loop_, 0) > 0) moved = true;
      return moved;
    };
    for (int quiet = 0; !client.closed() && quiet < 4;) {
      bool moved = client.Step(turn);
      if (client.all_sent() && !keep_open && !client.write_shut()) client.ShutdownWrite(), moved = true;
      quiet = moved ? 0 : quiet + 1;
    }
    std::string got = client.received();
    client.Close();
    turn();  // let the server see the close
    return got;
  }

 private:
  bool answer_;
  bool stream_method_;
  bool ok_ = false;
  int requests_ = 0;
  std::string dir_, path_;
  sd_event* loop_ = nullptr;
  std::unique_ptr<daemon::ControlServer> server_;
};

}  // namespace mocap::testing
