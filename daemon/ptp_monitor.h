// The rig's IEEE 1588 lock, checked while it streams (sync = "ptp").
//
// Why after start-up too: PTP locks once and can lose it (a switch rebooted, a cable moved, a
// grandmaster gone, a camera that fell back to "Listening" after a reconnect). Frame sets are
// grouped by the tick of the one clock (capture_pipeline.h kSharedClock); with a camera off that
// clock, its images join sets of another instant, and nothing in the images says so. So the
// daemon keeps reading each camera's PTP state (PtpStatus / GevIEEE1588Status) on a thread of its
// own (a GenICam read is a network round trip, and a lost camera's is a timeout: never on the
// event loop), and the loop reads the latest snapshot: `status` and STATUS= say the rig is
// unlocked and which cameras, record.start is refused naming them, and a recording running when
// the lock goes is marked (daemon.cpp).
//
// Where a camera's state comes from is an interface, PtpStatusSource: AravisPtpSource reads the
// camera (drivers::AravisCamera::Ptp), real or simulated (the simulated rig's Aravis fakes have
// the PTP features, drivers/aravis_fake.h FakeRigOptions::ptp_features); tests script others.
//
// Every configured camera has a source, also one the rig started without (rig_setup.h
// OpenRigCameras): while it is awaited (never opened) it is not judged — the rig is degraded,
// not unlocked, and start-up does not wait for it — and once it opens, with PTP enabled and its
// exposures scheduled by the same Open path as the others, the next round reads it: it holds
// the rig unlocked (record.start refused, a recording marked) until it locks like the others.
#pragma once
#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "drivers/aravis_camera.h"
#include "model/status.h"

namespace mocap::daemon {

// One camera's IEEE 1588 state. Read() may be called from any one thread at a time.
class PtpStatusSource {
 public:
  virtual ~PtpStatusSource() = default;
  virtual const std::string& camera_id() const = 0;
  // Error when the state cannot be read (camera lost, PTP not enabled); the message names it.
  virtual Status Read(drivers::PtpState* state) = 0;
  // A camera the rig started without and still awaits: not read, not judged.
  virtual bool Awaited() const { return false; }
};

// An Aravis camera's state (AravisCamera::Ptp, which serialises with the acquisition thread).
class AravisPtpSource final : public PtpStatusSource {
 public:
  explicit AravisPtpSource(drivers::AravisCamera* camera) : camera_(camera) {}
  const std::string& camera_id() const override { return camera_->id(); }
  Status Read(drivers::PtpState* state) override { return camera_->Ptp(state); }
  bool Awaited() const override { return camera_->AwaitingDevice(); }

 private:
  drivers::AravisCamera* camera_;
};

struct PtpMonitorOptions {
  double interval_s = 0.5;  // between two readings of every camera

  bool IsValid(std::string* error) const;
};

// What the last round of readings said.
struct PtpRigState {
  bool checked = false;  // at least one round done
  bool locked = false;   // drivers::PtpLocked over the round, and every camera read
  std::string why;       // when not locked: the cameras and their states (or read errors)
  std::vector<std::string> unlocked_cameras;  // ids of the cameras that are not "Slave"/"Master"
  std::vector<drivers::PtpState> states;      // per camera, as read (empty status: not read)
  std::vector<std::string> errors;            // per camera, "" or why it could not be read
  std::vector<std::string> awaited_cameras;   // ids of the cameras not judged: awaited
  std::uint64_t rounds = 0;
  std::uint64_t lock_losses = 0;  // rounds that found the rig unlocked after a locked one
};

// Reads every camera's state in a round, a round every interval_s, on its own thread.
class PtpMonitor {
 public:
  // The sources must outlive the monitor. `on_change` (may be empty) is called from the
  // monitor's thread when the lock changes (locked <-> not), e.g. to wake the event loop.
  PtpMonitor(std::vector<PtpStatusSource*> sources, PtpMonitorOptions options,
             std::function<void()> on_change = {});
  ~PtpMonitor();
  PtpMonitor(const PtpMonitor&) = delete;
  PtpMonitor& operator=(const PtpMonitor&) = delete;

  Status Start();
  void Stop();  // idempotent
  // One round now, on the caller's thread (tests; the start-up wait).
  PtpRigState CheckNow();
  PtpRigState Snapshot() const;

 private:
  void Loop();
  PtpRigState Round();

  std::vector<PtpStatusSource*> sources_;
  PtpMonitorOptions options_;
  std::function<void()> on_change_;
  mutable std::mutex mutex_;  // state_, stop_
  std::condition_variable wake_;
  PtpRigState state_;
  bool stop_ = false;
  std::thread thread_;
  std::mutex round_mutex_;  // one round at a time (the thread's and CheckNow's)
};

// Reads the rig until it is locked (drivers::PtpLocked) or `timeout_s` passes; the last round is
// left in *state. The error names the cameras that are not locked and how long it waited.
Status WaitForPtpLock(const std::vector<PtpStatusSource*>& sources, double timeout_s,
                      PtpRigState* state);

}  // namespace mocap::daemon
