// The control client (daemon/control_client.h) against a fake mocapd (tests/fake_mocapd.h): a
// thread on the other end of a socketpair (or of a real Unix socket) that plays a conversation.
#include "daemon/control_client.h"

#include <gmock/gmock.h>
#include <grp.h>
#include <gtest/gtest.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/un.h>
#include <unistd.h>

#include <chrono>
#include <cstring>
#include <filesystem>
#include <functional>
#include <string>
#include <thread>
#include <vector>

#include "fake_mocapd.h"
#include "file_test_util.h"

namespace mocap::daemon {
namespace {

using ::testing::HasSubstr;
using json = nlohmann::json;

using testutil::FakeDaemonEnd;
const std::string& kHello = testutil::kFakeHello;

// A client connected through a socketpair to `script`, which runs on its own thread.
class FakeDaemon {
 public:
  explicit FakeDaemon(std::function<void(FakeDaemonEnd&)> script) {
    int fds[2];
    EXPECT_EQ(socketpair(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0, fds), 0);
    client_fd_ = fds[0];
    thread_ = std::thread([fd = fds[1], script = std::move(script)] {
      FakeDaemonEnd end(fd);
      script(end);
    });
  }
  ~FakeDaemon() { thread_.join(); }
  Status Connect(std::unique_ptr<ControlClient>* client, ControlClientOptions options = {}) {
    return ControlClient::Adopt(client_fd_, options, client);
  }

 private:
  int client_fd_ = -1;
  std::thread thread_;
};

TEST(ControlClient, ReadsTheHello) {
  FakeDaemon daemon([](FakeDaemonEnd& d) { d.WriteLine(kHello); });
  std::unique_ptr<ControlClient> client;
  Status s = daemon.Connect(&client);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(client->hello().protocol, 1);
  EXPECT_EQ(client->hello().daemon, "mocapd 0.1.0");
  EXPECT_FALSE(client->hello().may_control);
  EXPECT_EQ(client->hello().uid, 1000);
}

TEST(ControlClient, RefusesAnotherProtocolOrSomethingElseThanAHello) {
  {
    FakeDaemon daemon([](FakeDaemonEnd& d) { d.WriteLine(R"({"event":"hello","protocol":2})"); });
    std::unique_ptr<ControlClient> client;
    Status s = daemon.Connect(&client);
    ASSERT_FALSE(s.ok());
    EXPECT_THAT(s.message(), HasSubstr("speaks control protocol 2; this client speaks 1"));
  }
  {
    FakeDaemon daemon([](FakeDaemonEnd& d) { d.WriteLine("SSH-2.0-OpenSSH_9.2"); });
    std::unique_ptr<ControlClient> client;
    Status s = daemon.Connect(&client);
    ASSERT_FALSE(s.ok());
    EXPECT_THAT(s.message(), HasSubstr("expected mocapd's hello, got: SSH-2.0-OpenSSH_9.2"));
  }
  {
    FakeDaemon daemon([](FakeDaemonEnd& d) { d.Close(); });
    std::unique_ptr<ControlClient> client;
    Status s = daemon.Connect(&client);
    ASSERT_FALSE(s.ok());
    EXPECT_THAT(s.message(), HasSubstr("mocapd closed the connection before its hello"));
  }
}

TEST(ControlClient, EventsBeforeTheReplyGoToTheHandlerInOrder) {
  FakeDaemon daemon([](FakeDaemonEnd& d) {
    d.WriteLine(kHello);
    json request = d.ReadRequest();
    EXPECT_EQ(request["id"], 1);
    EXPECT_EQ(request["method"], "fit.start");
    EXPECT_EQ(request["params"]["max_iterations"], 7);
    // Two progress events and a stream frame, then the reply, in one write and then split.
    d.Write(R"({"event":"progress","id":1,"job":"fit","iteration":1,"fraction":0.1})" "\n"
            R"({"event":"frame","frame":17})" "\n"
            R"({"event":"progress","id":1,"job":"fit","iter)");
    d.Write(R"(ation":2,"fraction":0.2})" "\n" R"({"id":1,"result":{"model_version":3}})" "\n");
    request = d.ReadRequest();
    EXPECT_EQ(request["id"], 2);
    EXPECT_EQ(request["method"], "status");
    EXPECT_FALSE(request.contains("params"));
    d.WriteLine(R"({"id":2,"result":{"state":"running"}})");
  });
  std::unique_ptr<ControlClient> client;
  ASSERT_TRUE(daemon.Connect(&client).ok());
  std::vector<json> events;
  ControlReply reply;
  Status s = client->Call("fit.start", {{"max_iterations", 7}}, &reply,
                          [&](const json& e) { events.push_back(e); });
  ASSERT_TRUE(s.ok()) << s.message();
  ASSERT_TRUE(reply.ok());
  EXPECT_EQ(reply.result["model_version"], 3);
  ASSERT_EQ(events.size(), 3u);
  EXPECT_EQ(events[0]["iteration"], 1);
  EXPECT_EQ(events[1]["frame"], 17);
  EXPECT_EQ(events[2]["iteration"], 2);
  s = client->Call("status", json(), &reply);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(reply.result["state"], "running");
}

TEST(ControlClient, RepliesAreMatchedByIdWhateverTheirOrder) {
  FakeDaemon daemon([](FakeDaemonEnd& d) {
    d.WriteLine(kHello);
    EXPECT_EQ(d.ReadRequest()["method"], "record.start");
    EXPECT_EQ(d.ReadRequest()["method"], "record.stop");
    d.WriteLine(R"({"id":2,"result":{"stopped":5}})");
    d.WriteLine(R"({"id":99,"result":{"not":"ours"}})");  // no such request: dropped
    d.WriteLine(R"({"id":1,"result":{"recording":5}})");
  });
  std::unique_ptr<ControlClient> client;
  ASSERT_TRUE(daemon.Connect(&client).ok());
  std::int64_t record = 0, stop = 0;
  ASSERT_TRUE(client->Send("record.start", {{"movement", "squats"}}, &record).ok());
  ASSERT_TRUE(client->Send("record.stop", json(), &stop).ok());
  EXPECT_EQ(record, 1);
  EXPECT_EQ(stop, 2);
  ControlReply reply;
  Status s = client->Wait(record, &reply);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(reply.result["recording"], 5);
  // The reply to the stop came first and was kept.
  ASSERT_TRUE(client->TakeReply(stop, &reply));
  EXPECT_EQ(reply.result["stopped"], 5);
  EXPECT_FALSE(client->TakeReply(99, &reply));
}

TEST(ControlClient, ErrorRepliesCarryTheCodeAndTheConnectionGoesOn) {
  FakeDaemon daemon([](FakeDaemonEnd& d) {
    d.WriteLine(kHello);
    d.ReadRequest();
    d.WriteLine(R"({"id":1,"error":{"code":"forbidden","message":"subject.create needs group mocap"}})");
    d.ReadRequest();
    // A reply to a request the daemon could not read has no id: it is the waiting request's.
    d.WriteLine(R"({"id":null,"error":{"code":"line_too_long","message":"line exceeds 1048576 bytes"}})");
  });
  std::unique_ptr<ControlClient> client;
  ASSERT_TRUE(daemon.Connect(&client).ok());
  ControlReply reply;
  ASSERT_TRUE(client->Call("subject.create", {{"name", "S01"}}, &reply).ok());
  EXPECT_FALSE(reply.ok());
  EXPECT_EQ(reply.error_code, "forbidden");
  EXPECT_EQ(reply.error_message, "subject.create needs group mocap");
  Status s = client->Call("raw", {{"blob", std::string(100, 'x')}}, &reply);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(reply.error_code, "line_too_long");
}

TEST(ControlClient, AnOverLongLineFromTheDaemonIsAClearErrorAndClosesTheConnection) {
  FakeDaemon daemon([](FakeDaemonEnd& d) {
    d.WriteLine(kHello);
    d.ReadRequest();
    d.Write(R"({"id":1,"result":")" + std::string(200000, 'x'));  // no end in sight
    d.ReadRequest();  // until the client closes
  });
  ControlClientOptions options;
  options.max_line_bytes = 4096;
  std::unique_ptr<ControlClient> client;
  ASSERT_TRUE(daemon.Connect(&client, options).ok());
  ControlReply reply;
  Status s = client->Call("export", {{"inline", true}}, &reply);
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.message(), "mocapd sent a line longer than 4096 bytes (the client's limit) before "
                         "replying to request 1 (export)");
  EXPECT_FALSE(client->connected());
  s = client->Call("status", json(), &reply);
  ASSERT_FALSE(s.ok());
  EXPECT_THAT(s.message(), HasSubstr("not connected to mocapd (mocapd sent a line longer than"));
  client.reset();  // closes: the fake daemon's read ends
}

TEST(ControlClient, ALineJustWithinTheBoundIsAccepted) {
  const std::string payload(4096 - std::string(R"({"id":1,"result":""})").size(), 'y');
  FakeDaemon daemon([&](FakeDaemonEnd& d) {
    d.WriteLine(kHello);
    d.ReadRequest();
    d.WriteLine(R"({"id":1,"result":")" + payload + "\"}");
  });
  ControlClientOptions options;
  options.max_line_bytes = 4096;
  std::unique_ptr<ControlClient> client;
  ASSERT_TRUE(daemon.Connect(&client, options).ok());
  ControlReply reply;
  Status s = client->Call("export", json::object(), &reply);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(reply.result.get<std::string>().size(), payload.size());
}

TEST(ControlClient, AMultiMegabyteReplyArrivesWholeAfterEventsInTheSameReads) {
  // An inline export: 5 MB of content in one line, read in many pieces, behind two events.
  std::string content(5 << 20, 'z');
  for (std::size_t i = 0; i < content.size(); i += 4099) content[i] = 'a' + (i / 4099) % 26;
  FakeDaemon daemon([&](FakeDaemonEnd& d) {
    d.WriteLine(kHello);
    d.ReadRequest();
    d.Write(R"({"event":"progress","id":1,"job":"export"})" "\n"
            R"({"event":"progress","id":1,"job":"export"})" "\n");
    d.WriteLine(json({{"id", 1}, {"result", {{"content", content}}}}).dump());
  });
  std::unique_ptr<ControlClient> client;
  ASSERT_TRUE(daemon.Connect(&client).ok());
  ControlReply reply;
  int events = 0;
  Status s = client->Call("export", {{"inline", true}}, &reply, [&](const json&) { ++events; });
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(events, 2);
  EXPECT_EQ(reply.result["content"], content);
}

TEST(ControlClient, DaemonGoneMidReplyIsAClearError) {
  FakeDaemon daemon([](FakeDaemonEnd& d) {
    d.WriteLine(kHello);
    d.ReadRequest();
    d.WriteLine(R"({"event":"progress","id":1,"job":"rig.calibrate","fraction":0.5})");
    d.Write(R"({"id":1,"resu)");
    d.Close();
  });
  std::unique_ptr<ControlClient> client;
  ASSERT_TRUE(daemon.Connect(&client).ok());
  int events = 0;
  ControlReply reply;
  Status s = client->Call("rig.calibrate.finish", json::object(), &reply,
                          [&](const json&) { ++events; });
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.message(), "mocapd closed the connection in the middle of a message before "
                         "replying to request 1 (rig.calibrate.finish)");
  EXPECT_EQ(events, 1);
}

TEST(ControlClient, SilenceLongerThanTheTimeoutFailsButProgressKeepsTheWaitAlive) {
  FakeDaemon daemon([](FakeDaemonEnd& d) {
    d.WriteLine(kHello);
    d.ReadRequest();
    // Progress every 100 ms for 0.6 s: longer than the 300 ms timeout in all, never silent for it.
    for (int i = 0; i < 6; ++i) {
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
      d.WriteLine(R"({"event":"progress","id":1,"job":"fit"})");
    }
    d.WriteLine(R"({"id":1,"result":{}})");
    d.ReadRequest();  // the status request, and then silence until the client gives up and closes
    d.ReadRequest();
  });
  ControlClientOptions options;
  options.reply_timeout_ms = 300;
  std::unique_ptr<ControlClient> client;
  ASSERT_TRUE(daemon.Connect(&client, options).ok());
  ControlReply reply;
  int events = 0;
  Status s = client->Call("fit.start", json::object(), &reply, [&](const json&) { ++events; });
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(events, 6);
  const auto start = std::chrono::steady_clock::now();
  s = client->Call("status", json(), &reply);
  const double waited_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.message(), "mocapd sent nothing for 300 ms while request 2 (status) waited for its reply");
  EXPECT_GE(waited_s, 0.3);
  EXPECT_LT(waited_s, 2.0);
  client.reset();
}

TEST(ControlClient, ATimeoutOfZeroWaitsForEver) {
  FakeDaemon daemon([](FakeDaemonEnd& d) {
    std::this_thread::sleep_for(std::chrono::milliseconds(300));
    d.WriteLine(kHello);
    d.ReadRequest();
    std::this_thread::sleep_for(std::chrono::milliseconds(300));
    d.WriteLine(R"({"id":1,"result":{"state":"running"}})");
  });
  ControlClientOptions options;
  options.reply_timeout_ms = 0;
  std::unique_ptr<ControlClient> client;
  Status s = daemon.Connect(&client, options);
  ASSERT_TRUE(s.ok()) << s.message();
  ControlReply reply;
  s = client->Call("status", json(), &reply);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(reply.result["state"], "running");
}

TEST(ControlClient, StreamEventsAfterTheReplyAreReadByNextEvent) {
  FakeDaemon daemon([](FakeDaemonEnd& d) {
    d.WriteLine(kHello);
    d.ReadRequest();
    // The reply and the first frames in one write: the frames stay buffered for NextEvent.
    d.Write(R"({"id":1,"result":{"subscribed":["markers"]}})" "\n"
            R"({"event":"frame","frame":1})" "\n" R"({"event":"dropped","count":4})" "\n");
    d.WriteLine(R"({"event":"frame","frame":6})");
    d.ReadRequest();
  });
  std::unique_ptr<ControlClient> client;
  ASSERT_TRUE(daemon.Connect(&client).ok());
  ControlReply reply;
  ASSERT_TRUE(client->Call("subscribe", {{"streams", {"markers"}}}, &reply).ok());
  std::vector<json> events;
  for (;;) {
    json event;
    bool got = false;
    ASSERT_TRUE(client->NextEvent(&event, 500, &got).ok());
    if (!got) break;
    events.push_back(event);
  }
  ASSERT_EQ(events.size(), 3u);
  EXPECT_EQ(events[0]["frame"], 1);
  EXPECT_EQ(events[1]["count"], 4);
  EXPECT_EQ(events[2]["frame"], 6);
  client.reset();
}

// --- A real Unix socket ------------------------------------------------------------------------

std::string SocketPath() {
  const std::string path = testutil::ShortSocketPath();
  std::filesystem::remove(path);
  return path;
}

int BoundSocket(const std::string& path) {
  const int fd = socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0);
  sockaddr_un addr{};
  addr.sun_family = AF_UNIX;
  std::strncpy(addr.sun_path, path.c_str(), sizeof addr.sun_path - 1);
  EXPECT_EQ(bind(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr), 0) << strerror(errno);
  return fd;
}

TEST(ControlClient, ConnectsThroughAUnixSocket) {
  const std::string path = SocketPath();
  testutil::ScriptedMocapd daemon(path, [](const json& request) {
    return std::vector<std::string>{testutil::ResultLine(request, {{"echo", request["method"]}})};
  });
  ControlClientOptions options;
  options.socket_path = path;
  std::unique_ptr<ControlClient> client;
  Status s = ControlClient::Connect(options, &client);
  ASSERT_TRUE(s.ok()) << s.message();
  ControlReply reply;
  s = client->Call("cameras", json(), &reply);
  ASSERT_TRUE(s.ok()) << s.message();
  EXPECT_EQ(reply.result["echo"], "cameras");
}

TEST(ControlClient, NotRunningSaysSo) {
  const std::string path = SocketPath();
  ControlClientOptions options;
  options.socket_path = path;
  std::unique_ptr<ControlClient> client;
  Status s = ControlClient::Connect(options, &client);
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.message(), "mocapd is not running (no socket at " + path + ")");

  // A socket left behind by a daemon that stopped: nobody listens.
  close(BoundSocket(path));
  s = ControlClient::Connect(options, &client);
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.message(), "mocapd is not running (" + path +
                             " exists but nobody listens on it: the socket of a daemon that stopped)");

  // A regular file where the socket should be.
  std::filesystem::remove(path);
  testutil::WriteBytes(path, "not a socket");
  s = ControlClient::Connect(options, &client);
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.message(), path + " is not a socket (is --socket right?)");
}

TEST(ControlClient, PermissionDeniedNamesTheSocketsGroup) {
  // Tests run as root here (no EACCES from connect): the message is built from the errno.
  const std::string path = SocketPath();
  close(BoundSocket(path));
  struct stat st{};
  ASSERT_EQ(stat(path.c_str(), &st), 0);
  const group* g = getgrgid(st.st_gid);
  const std::string name = g ? g->gr_name : std::to_string(st.st_gid);
  EXPECT_EQ(DescribeConnectError(path, EACCES),
            "permission denied on " + path + ": you need to be in group " + name);
  // The directory refused us (the socket cannot even be seen): its group is the one to join.
  const std::string hidden = path + ".d/control.sock";
  std::filesystem::create_directories(path + ".d");
  ASSERT_EQ(stat((path + ".d").c_str(), &st), 0);
  g = getgrgid(st.st_gid);
  EXPECT_EQ(DescribeConnectError(hidden, EACCES),
            "permission denied on " + path + ".d: you need to be in group " +
                (g ? g->gr_name : std::to_string(st.st_gid)));
}

TEST(ControlClient, OptionsAreChecked) {
  ControlClientOptions options;
  options.socket_path = "/" + std::string(200, 'x');
  std::unique_ptr<ControlClient> client;
  Status s = ControlClient::Connect(options, &client);
  ASSERT_FALSE(s.ok());
  EXPECT_THAT(s.message(), HasSubstr("is 201 bytes long; a Unix socket path holds at most 107"));
}

}  // namespace
}  // namespace mocap::daemon
