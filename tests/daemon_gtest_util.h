// GoogleTest helpers of the daemon tier's tests (tests/daemon_test_util.h stays free of
// GoogleTest: the benchmarks use it too).
#pragma once
#include <string>

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "daemon/control_client.h"
#include "model/status.h"

// Fails the test (and returns) when `expr`, a Status, is not ok; its message is the failure's.
#define ASSERT_OK(expr)                              \
  do {                                               \
    const ::mocap::Status status_ = (expr);          \
    ASSERT_TRUE(status_.ok()) << status_.message();  \
  } while (0)

namespace mocap::testing {

// A request that must succeed: its result (a failed call or an error reply fails the test).
inline nlohmann::json Call(daemon::ControlClient* c, const std::string& method,
                           const nlohmann::json& params = nlohmann::json::object()) {
  daemon::ControlReply r;
  const Status s = c->Call(method, params, &r);
  EXPECT_TRUE(s.ok()) << method << ": " << s.message();
  EXPECT_TRUE(r.ok()) << method << ": " << r.error_code << " " << r.error_message;
  return r.result;
}

}  // namespace mocap::testing
