// From the configuration's [rig] to what the cameras and the capture pipeline are given: one
// place, so that mocapd (daemon.cpp) and its tests read the configuration alike.
//
// Synchronisation ([rig] sync, README "Cameras"):
//   trigger   every camera on its trigger input (Line<trigger_line>), except the trigger master
//             ([rig] trigger_master), which free-runs at the rate and drives the others through
//             its strobe line; without a master an external generator drives them all. The
//             pipeline groups sets by trigger count, checked by timestamps (RigSync::kTrigger).
//   ptp       every camera free-runs with IEEE 1588 enabled and its exposures scheduled on the
//             common clock's ticks ([rig] ptp_schedule, by default Synchronous Free Run:
//             drivers/aravis_camera.h "Exposure schedule"); start-up waits until the rig is
//             locked to one clock (PtpLocked) for ptp_lock_timeout_s and refuses to start (so to
//             record) otherwise; sets by the tick of the common clock (kSharedClock).
//   free-run  every camera free-runs on its own clock; sets by each camera's clock fitted against
//             the host (kFreeRun): only as good as that estimate, which mocapd says at start.
// A simulated rig's fakes share the host's clock: kSharedClock, except with sync = "free-run",
// whose clocks are fitted as a real free-running rig's (the fakes' clocks skewed by
// [[rig.camera]] sim_clock_offset_ms / sim_clock_drift_ppm, drivers/skewed_clock_camera.h).
// With sync = "ptp" the fakes are PTP cameras, configured as real ones are
// (drivers/aravis_fake.h FakeRigOptions::ptp_features; sim_clock_offset_ms: their own clocks).
// The PTP wait and the lock's monitoring while streaming: daemon/ptp_monitor.h.
#pragma once
#include <string>
#include <vector>

#include "daemon/capture_pipeline.h"
#include "daemon/config.h"
#include "drivers/aravis_camera.h"
#include "drivers/camera_source.h"
#include "model/status.h"

namespace mocap::daemon {

// The settings camera `camera` (an index of config.cameras) is opened with.
drivers::CameraSettings CameraSettingsOf(const DaemonConfig& config, int camera);
// How the pipeline groups frames into sets for this configuration.
CapturePipelineOptions::RigSync RigSyncOf(const DaemonConfig& config);

// A configured camera that did not open at start, and why (AravisCamera::Open's error).
struct MissingCamera {
  int index = 0;         // in the rig's order
  std::string id;
  std::string why;
  bool device_found = false;  // the device answered and refused a setting (vs absent)
};

// Opens the rig's cameras, camera i with settings[i]. Why a rig starts degraded rather than not
// at all: a lab PC booted before a PoE switch, or with one camera's cable pulled, must still
// come up — its socket serves stored recordings, exports and fits, and the camera joins the
// rig when it appears, without a restart (systemd restarting a daemon whose camera is away is
// a crash loop that also drops every client). So a camera that does not open is kept awaiting
// its device (AravisCamera::AwaitDevice: opened when it appears, as after a loss) and listed in
// *missing. Only when fewer than `min_cameras` open (clamped to the number configured; a rig
// of fewer than two cannot triangulate) does start-up fail: the error lists every missing
// camera and why, and *exit_code is kExitConfig if each of them answered and refused a
// setting (no restart cures a configuration: RestartPreventExitStatus=), else kExitUnavailable
// (a camera may come back: systemd retries).
Status OpenRigCameras(const std::vector<drivers::AravisCamera*>& cameras,
                      const std::vector<drivers::CameraSettings>& settings, int min_cameras,
                      std::vector<MissingCamera>* missing, int* exit_code);

}  // namespace mocap::daemon
