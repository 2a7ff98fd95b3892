#include "daemon/ptp_monitor.h"

#include <chrono>
#include <cmath>
#include <sstream>

namespace mocap::daemon {

bool PtpMonitorOptions::IsValid(std::string* error) const {
  if (!(interval_s >= 0.01 && interval_s <= 3600)) {
    if (error) *error = "ptp monitor: interval_s " + std::to_string(interval_s) + " is outside [0.01, 3600]";
    return false;
  }
  return true;
}

PtpMonitor::PtpMonitor(std::vector<PtpStatusSource*> sources, PtpMonitorOptions options,
                       std::function<void()> on_change)
    : sources_(std::move(sources)), options_(options), on_change_(std::move(on_change)) {}

PtpMonitor::~PtpMonitor() { Stop(); }

Status PtpMonitor::Start() {
  std::string error;
  if (!options_.IsValid(&error)) return Status::Error(error);
  if (thread_.joinable()) return Status::Error("ptp monitor: already started");
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stop_ = false;
  }
  thread_ = std::thread(&PtpMonitor::Loop, this);
  return Status::Ok();
}

void PtpMonitor::Stop() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stop_ = true;
  }
  wake_.notify_all();
  if (thread_.joinable()) thread_.join();
}

PtpRigState PtpMonitor::Round() {
  std::lock_guard<std::mutex> round_lock(round_mutex_);
  PtpRigState next;
  next.states.resize(sources_.size());
  next.errors.resize(sources_.size());
  std::vector<std::string> ids;
  std::vector<drivers::PtpState> judged;
  std::string unread;
  for (std::size_t i = 0; i < sources_.size(); ++i) {
    if (sources_[i]->Awaited()) {
      next.awaited_cameras.push_back(sources_[i]->camera_id());
      continue;
    }
    ids.push_back(sources_[i]->camera_id());
    if (Status s = sources_[i]->Read(&next.states[i]); !s) {
      next.errors[i] = s.message();
      next.states[i] = {};
      unread += (unread.empty() ? "" : ", ") + ids.back() + " (" + s.message() + ")";
    }
    const std::string& st = next.states[i].status;
    if (st != "Slave" && st != "Master") next.unlocked_cameras.push_back(ids.back());
    judged.push_back(next.states[i]);
  }
  std::string why;
  next.locked = drivers::PtpLocked(ids, judged, &why) && unread.empty();
  if (!unread.empty()) why += (why.empty() ? "" : "; ") + std::string("not read: ") + unread;
  next.why = next.locked ? "" : why;
  next.checked = true;
  bool changed = false;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    next.rounds = state_.rounds + 1;
    next.lock_losses = state_.lock_losses + (state_.checked && state_.locked && !next.locked ? 1 : 0);
    changed = !state_.checked || state_.locked != next.locked;
    state_ = next;
  }
  if (changed && on_change_) on_change_();
  return next;
}

PtpRigState PtpMonitor::CheckNow() { return Round(); }

PtpRigState PtpMonitor::Snapshot() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return state_;
}

void PtpMonitor::Loop() {
  for (;;) {
    Round();
    std::unique_lock<std::mutex> lock(mutex_);
    if (wake_.wait_for(lock, std::chrono::duration<double>(options_.interval_s),
                       [this] { return stop_; }))
      return;
  }
}

Status WaitForPtpLock(const std::vector<PtpStatusSource*>& sources, double timeout_s,
                      PtpRigState* state) {
  PtpMonitor monitor(sources, {});
  const auto start = std::chrono::steady_clock::now();
  for (;;) {
    *state = monitor.CheckNow();
    if (state->locked) return Status::Ok();
    const double waited =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    if (waited >= timeout_s) {
      std::ostringstream m;
      m << "[rig] sync = \"ptp\": the cameras did not lock to one clock within " << timeout_s
        << " s (rig.ptp_lock_timeout_s): " << state->why;
      return Status::Error(m.str());
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
  }
}

}  // namespace mocap::daemon
