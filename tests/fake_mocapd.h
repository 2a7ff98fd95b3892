// A fake mocapd for the tests of the control client and of mocapctl: the daemon's end of a
// connection (blocking line I/O), and a scripted daemon on a real Unix socket that answers each
// request with the lines a test gives (events, then the reply) and records what it was sent.
#pragma once
#include <gtest/gtest.h>
#include <poll.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <cstring>
#include <filesystem>
#include <functional>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include <nlohmann/json.hpp>

namespace mocap::testutil {

inline const std::string kFakeHello =
    R"({"event":"hello","protocol":1,"daemon":"mocapd 0.1.0","may_control":false,"uid":1000})";

// The daemon's end of one connection.
class FakeDaemonEnd {
 public:
  explicit FakeDaemonEnd(int fd) : fd_(fd) {}
  ~FakeDaemonEnd() { Close(); }
  FakeDaemonEnd(const FakeDaemonEnd&) = delete;
  FakeDaemonEnd& operator=(const FakeDaemonEnd&) = delete;

  void Write(const std::string& bytes) {
    std::size_t sent = 0;
    while (sent < bytes.size()) {
      const ssize_t n = send(fd_, bytes.data() + sent, bytes.size() - sent, MSG_NOSIGNAL);
      if (n <= 0) return;  // the client went away: the test's assertions say what matters
      sent += static_cast<std::size_t>(n);
    }
  }
  void WriteLine(const std::string& line) { Write(line + "\n"); }
  // The next request line, parsed; null when the client closed (or `stop` was set).
  nlohmann::json ReadRequest(const std::atomic<bool>* stop = nullptr) {
    for (;;) {
      if (auto nl = buffer_.find('\n'); nl != std::string::npos) {
        nlohmann::json request = nlohmann::json::parse(buffer_.substr(0, nl), nullptr, false);
        buffer_.erase(0, nl + 1);
        return request;
      }
      if (stop) {  // wake up now and then to see whether the test is over
        pollfd p{fd_, POLLIN, 0};
        if (poll(&p, 1, 50) == 0) {
          if (stop->load()) return nlohmann::json();
          continue;
        }
      }
      char chunk[4096];
      const ssize_t n = read(fd_, chunk, sizeof chunk);
      if (n < 0 && errno == EINTR) continue;
      if (n <= 0) return nlohmann::json();
      buffer_.append(chunk, static_cast<std::size_t>(n));
    }
  }
  void Close() {
    if (fd_ >= 0) close(fd_);
    fd_ = -1;
  }

 private:
  int fd_;
  std::string buffer_;
};

// Listens on `path`; each connection gets the hello, then for each request the lines
// `respond(request)` returns (a line "sleep:MS" waits that long instead of being sent, and a line
// "close" closes the connection).
// Connections are served one after the other, until the object is destroyed.
class ScriptedMocapd {
 public:
  using Responder = std::function<std::vector<std::string>(const nlohmann::json& request)>;

  ScriptedMocapd(const std::string& path, Responder respond)
      : path_(path), respond_(std::move(respond)) {
    std::filesystem::remove(path_);
    listener_ = socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0);
    sockaddr_un addr{};
    addr.sun_family = AF_UNIX;
    std::strncpy(addr.sun_path, path_.c_str(), sizeof addr.sun_path - 1);
    EXPECT_EQ(bind(listener_, reinterpret_cast<sockaddr*>(&addr), sizeof addr), 0)
        << path_ << ": " << std::strerror(errno);
    EXPECT_EQ(listen(listener_, 8), 0);
    thread_ = std::thread([this] { Serve(); });
  }
  ~ScriptedMocapd() {
    stop_ = true;
    thread_.join();
    close(listener_);
    std::filesystem::remove(path_);
  }
  // Every request received so far, in order.
  std::vector<nlohmann::json> requests() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return requests_;
  }
  std::vector<std::string> methods() const {
    std::vector<std::string> m;
    for (const auto& r : requests()) m.push_back(r.value("method", ""));
    return m;
  }

 private:
  void Serve() {
    while (!stop_) {
      pollfd p{listener_, POLLIN, 0};
      if (poll(&p, 1, 50) <= 0) continue;
      FakeDaemonEnd end(accept(listener_, nullptr, nullptr));
      end.WriteLine(kFakeHello);
      for (bool open = true; open;) {
        const nlohmann::json request = end.ReadRequest(&stop_);
        if (request.is_null()) break;
        {
          std::lock_guard<std::mutex> lock(mutex_);
          requests_.push_back(request);
        }
        for (const std::string& line : respond_(request)) {
          if (line.rfind("sleep:", 0) == 0) {
            std::this_thread::sleep_for(std::chrono::milliseconds(std::stoi(line.substr(6))));
          } else if (line == "close") {
            end.Close();
            open = false;
            break;
          } else {
            end.WriteLine(line);
          }
        }
      }
    }
  }

  std::string path_;
  Responder respond_;
  int listener_ = -1;
  std::atomic<bool> stop_{false};
  mutable std::mutex mutex_;
  std::vector<nlohmann::json> requests_;
  std::thread thread_;
};

// A socket path short enough for sun_path (107 bytes; the build tree may be deep), unique to the
// test process (ctest runs tests in parallel processes).
inline std::string ShortSocketPath() {
  return "/tmp/mocap-test-" + std::to_string(getpid()) + ".sock";
}

// The reply line to `request` with `result`.
inline std::string ResultLine(const nlohmann::json& request, const nlohmann::json& result) {
  return nlohmann::json({{"id", request["id"]}, {"result", result}}).dump();
}
inline std::string ErrorLine(const nlohmann::json& request, const std::string& code,
                             const std::string& message) {
  return nlohmann::json({{"id", request["id"]}, {"error", {{"code", code}, {"message", message}}}})
      .dump();
}

}  // namespace mocap::testutil
