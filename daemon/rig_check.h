// The rig check: what a lab engineer asks of a running rig before a session, in one report
// (`mocapctl cameras --check`, the control method `cameras.check`, daemon/PROTOCOL.md):
//   - synchronisation, per camera, by the rig's mode:
//       ptp        its PTP status (Slave / Master / Listening ...), its offset from the master,
//                  and whether the rig is locked to one clock (daemon/ptp_monitor.h); and where
//                  within the clock's tick it exposes (its tick phase, CapturePipelineStats::
//                  camera_tick_phase) against the rig's median camera: a locked camera whose
//                  exposures are not scheduled on the ticks (drivers/aravis_camera.h "Exposure
//                  schedule") free-runs at a phase of its own, and its images join sets of
//                  another instant while the lock looks perfect;
//       free-run   its clock fitted against the host (reconstruction/clock_fit.h): offset (also
//                  against the rig's median camera, which is what grouping depends on), drift,
//                  and the fit's residual, set against a frame period;
//       trigger    its frame count against its own timestamps (a trigger counted and not
//                  exposed, or the reverse: CapturePipelineStats::camera_count_mismatches) and
//                  the rig's sets whose timestamps disagreed (mismatched_sets);
//   - what did not become a frame: incomplete buffers (missing packets, size mismatches),
//     underruns, timeouts, losses, and GigE Vision's resent / missing packet counts where Aravis
//     gives them;
//   - per link, the bandwidth its cameras need against what it carries, and the headroom
//     (daemon/startup_checks.h RigLinkLoads).
// Anything that fails is a line in `problems` naming the camera or link and the figure; the
// report's `ok` is false then and mocapctl exits non-zero.
//
// Why a report of its own and not `cameras`: `cameras` is what the operator watches; the check
// is a verdict with thresholds (RigCheckOptions), so that a lab can run it from a script after
// moving a camera, changing a switch, or upgrading firmware, and trust its exit status.
#pragma once
#include <cstdint>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "daemon/startup_checks.h"
#include "drivers/aravis_camera.h"

namespace mocap::daemon {

struct RigCheckOptions {
  // free-run: a camera whose clock fit's residual exceeds this fraction of a frame period fails
  // (the sets gather frames within 0.45 of a period of each other: a fit uncertain by a quarter
  // of one leaves the grouping no margin).
  double max_clock_residual_periods = 0.25;
  // Per camera: frames that did not arrive whole (incomplete buffers, underruns, frames not
  // received at all) beyond this
  // fraction of its complete frames fail it.
  double max_lost_frame_fraction = 0.01;
  // trigger: sets whose members' timestamps disagreed, beyond this fraction of the sets, fail the
  // rig; any frame whose count disagreed with its own timestamp fails its camera.
  double max_mismatched_set_fraction = 0.001;
  // ptp: a slave further than this from its master fails: it has not converged (locked slaves
  // with hardware timestamps sit within a microsecond or so); at 200 Hz it is 2 % of a period.
  double max_ptp_offset_us = 100;
  // ptp: a camera whose tick phase is further than this fraction of a period from the rig's
  // median camera's fails (at 200 Hz, 0.5 ms: an exposure of the usual 0.3-1 ms overlaps the
  // others' by half or less; scheduled cameras agree within microseconds).
  double max_tick_phase_periods = 0.1;
  // A camera with fewer complete frames than this many seconds at the rate is not judged on its
  // fractions (its first buffers, a start-up underrun, would be percent of nothing): it fails
  // with "too few frames so far" instead.
  double min_seconds_of_frames = 1.0;

  bool IsValid(std::string* error) const;
};

// One camera's figures, as the daemon gathers them.
struct CameraCheckInput {
  std::string id;
  std::string link;  // its link in the rig check ("" where none is checked)
  bool streaming = false;
  std::uint64_t complete = 0, missing_packets = 0, size_mismatches = 0, other_errors = 0;
  std::uint64_t underruns = 0, timeouts = 0, losses = 0, reopens = 0;
  std::uint64_t not_received = 0;  // whole frames (drivers::CameraCounters::not_received)
  // GigE Vision stream statistics (AravisCamera::PacketStatistics); absent elsewhere.
  bool has_packet_statistics = false;
  std::uint64_t resent_packets = 0, missing_stream_packets = 0;
  // Clock fit (free-run; trigger with its timestamp check).
  bool clock_fitted = false;
  double clock_offset_ms = 0, clock_drift_ppm = 0, clock_residual_us = 0;
  // trigger
  bool trigger_master = false;
  std::uint64_t count_mismatches = 0;
  // ptp: the monitor's last reading ("" status: not read; ptp_error says why).
  drivers::PtpState ptp;
  std::string ptp_error;
  double tick_phase = -1;  // ptp: CapturePipelineStats::camera_tick_phase (-1: no frames)
};

struct RigCheckInput {
  // "trigger" | "ptp" | "free-run" | "shared-clock" (a simulated rig whose fakes share a clock)
  std::string sync;
  double rate_hz = 0;
  std::vector<CameraCheckInput> cameras;
  std::vector<LinkLoad> links;
  std::uint64_t sets = 0, incomplete_sets = 0, dropped_sets = 0, mismatched_sets = 0;
  // ptp: the monitor's verdict over the rig (daemon/ptp_monitor.h PtpRigState).
  bool ptp_checked = false, ptp_locked = false;
  std::string ptp_why;
};

// The report (its layout: daemon/PROTOCOL.md, cameras.check):
//   {"ok":bool, "problems":[..], "sync":{"mode":..,..}, "cameras":[{"id","ok","problems",
//    "sync":{..},"frames":{..},"packets":{..}|null,"link"}], "links":[{"link","interface",
//    "cameras","capacity_mb_s","needed_mb_s","headroom_mb_s","ok"}], "sets":{..}}
nlohmann::json RigCheckReport(const RigCheckInput& input, const RigCheckOptions& options = {});

}  // namespace mocap::daemon
