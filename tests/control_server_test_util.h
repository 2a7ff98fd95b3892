// The control socket's server (daemon/control_server.h) on its own sd-event loop, driven in one
// thread by a client that writes bytes and reads what comes back: for fuzz/fuzz_control.cpp and
// tests/test_control_server.cpp. No GoogleTest here (the fuzzer uses it).
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
#include <memory>
#include <string>
#include <string_view>

#include <nlohmann/json.hpp>

#include "daemon/control_server.h"

namespace mocap::testing {

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
    std::string got;
    const int fd = socket(AF_UNIX, SOCK_STREAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
    if (fd < 0) return got;
    sockaddr_un addr{};
    addr.sun_family = AF_UNIX;
    path_.copy(addr.sun_path, sizeof addr.sun_path - 1);
    if (connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0) {
      close(fd);
      return got;
    }
    std::size_t sent = 0;
    bool shut = false;
    int quiet = 0;
    bool closed = false;
    char buf[65536];
    while (!closed && quiet < 4) {
      bool moved = false;
      if (sent < bytes.size()) {
        const ssize_t n = send(fd, bytes.data() + sent, bytes.size() - sent, MSG_NOSIGNAL);
        if (n > 0) sent += static_cast<std::size_t>(n), moved = true;
        else if (n < 0 && errno != EAGAIN) sent = bytes.size();  // the server closed on us
      } else if (!shut && !keep_open) {
        shutdown(fd, SHUT_WR);
        shut = moved = true;
      }
      while (sd_event_run(loop_, 0) > 0) moved = true;
      for (;;) {
        const ssize_t n = recv(fd, buf, sizeof buf, 0);
        if (n > 0) {
          got.append(buf, static_cast<std::size_t>(n));
          moved = true;
          continue;
        }
        closed = n == 0;  // closed by the server: all it will say has been read
        break;
      }
      quiet = moved ? 0 : quiet + 1;
    }
    close(fd);
    while (sd_event_run(loop_, 0) > 0) {
    }  // let the server see the close
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
