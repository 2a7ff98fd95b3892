// From the configuration's [rig] to what the cameras and the capture pipeline are given: one
// place, so that mocapd (daemon.cpp) and its tests read the configuration alike.
//
// Synchronisation ([rig] sync, README "Cameras"):
//   trigger   every camera on its trigger input (Line<trigger_line>), except the trigger master
//             ([rig] trigger_master), which free-runs at the rate and drives the others through
//             its strobe line; without a master an external generator drives them all. The
//             pipeline groups sets by trigger count, checked by timestamps (RigSync::kTrigger).
//   ptp       every camera free-runs with IEEE 1588 enabled; start-up waits until the rig is
//             locked to one clock (PtpLocked) for ptp_lock_timeout_s and refuses to start (so to
//             record) otherwise; sets by the tick of the common clock (kSharedClock).
//   free-run  every camera free-runs on its own clock; sets by each camera's clock fitted against
//             the host (kFreeRun): only as good as that estimate, which mocapd says at start.
// A simulated rig's fakes share the host's clock: kSharedClock, except with sync = "free-run",
// whose clocks are fitted as a real free-running rig's (the fakes' clocks skewed by
// [[rig.camera]] sim_clock_offset_ms / sim_clock_drift_ppm, drivers/skewed_clock_camera.h).
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

}  // namespace mocap::daemon
