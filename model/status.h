// Status: what every library function of mocapd returns instead of logging or exiting.
// A failed Status carries a message that names what is wrong (file, line, field).
#pragma once
#include <string>
#include <utility>

namespace mocap {

class Status {
 public:
  Status() = default;
  static Status Ok() { return Status(); }
  static Status Error(std::string message) { return Status(std::move(message), false); }

  bool ok() const { return ok_; }
  const std::string& message() const { return message_; }
  explicit operator bool() const { return ok_; }

 private:
  Status(std::string message, bool ok) : ok_(ok), message_(std::move(message)) {}
  bool ok_ = true;
  std::string message_;
};

}  // namespace mocap

// Returns the Status of `expr` from the enclosing function if it failed.
#define MOCAP_RETURN_IF_ERROR(expr) \
  do {                              \
    ::mocap::Status _s = (expr);    \
    if (!_s.ok()) return _s;        \
  } while (0)
