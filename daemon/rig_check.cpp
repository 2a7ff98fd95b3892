#include "daemon/rig_check.h"

#include <cmath>
#include <cstdio>

#include "daemon/capture_pipeline.h"  // Percentile

namespace mocap::daemon {
namespace {

using Json = nlohmann::json;

std::string Fixed(double v, int digits) {
  char b[64];
  std::snprintf(b, sizeof b, "%.*f", digits, v);
  return b;
}

}  // namespace

bool RigCheckOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& what) {
    if (error) *error = "rig check options: " + what;
    return false;
  };
  if (!(max_clock_residual_periods > 0 && max_clock_residual_periods <= 0.5))
    return fail("max_clock_residual_periods must be in (0, 0.5]");
  if (!(max_lost_frame_fraction >= 0 && max_lost_frame_fraction <= 1))
    return fail("max_lost_frame_fraction must be in [0, 1]");
  if (!(max_mismatched_set_fraction >= 0 && max_mismatched_set_fraction <= 1))
    return fail("max_mismatched_set_fraction must be in [0, 1]");
  if (!(max_ptp_offset_us > 0)) return fail("max_ptp_offset_us must be > 0");
  if (!(max_tick_phase_periods > 0 && max_tick_phase_periods <= 0.5))
    return fail("max_tick_phase_periods must be in (0, 0.5]");
  if (!(min_seconds_of_frames >= 0 && min_seconds_of_frames <= 3600))
    return fail("min_seconds_of_frames must be in [0, 3600]");
  return true;
}

Json RigCheckReport(const RigCheckInput& in, const RigCheckOptions& options) {
  Json problems = Json::array();
  Json report;
  std::string error;
  if (!options.IsValid(&error)) {
    report["ok"] = false;
    report["problems"] = Json::array({error});
    return report;
  }
  const double period_us = in.rate_hz > 0 ? 1e6 / in.rate_hz : 0;

  // Free-run offsets against the rig's median camera: the epochs of free-running clocks are
  // arbitrary, their differences are what the sets are grouped by.
  std::vector<double> fitted_offsets;
  for (const CameraCheckInput& c : in.cameras)
    if (c.clock_fitted) fitted_offsets.push_back(c.clock_offset_ms);
  const double median_offset_ms = Percentile(&fitted_offsets, 50);
  // PTP: the tick phase of the rig's median camera, which the others must share (a schedule's
  // phase is the same on every camera; where the timestamp is taken within the exposure is the
  // vendor's, and alike on like cameras).
  std::vector<double> phases;
  for (const CameraCheckInput& c : in.cameras)
    if (c.tick_phase >= 0) phases.push_back(c.tick_phase);
  const bool have_phase = !phases.empty();
  const double rig_phase = Percentile(&phases, 50);
  const double min_frames = options.min_seconds_of_frames * in.rate_hz;

  Json cameras = Json::array();
  for (const CameraCheckInput& c : in.cameras) {
    Json cp = Json::array();
    auto fail = [&](const std::string& what) {
      cp.push_back(what);
      problems.push_back("camera '" + c.id + "': " + what);
    };
    if (!c.streaming) fail("not streaming (" + std::to_string(c.losses) + " losses)");

    Json sync = {{"mode", in.sync}};
    if (in.sync == "ptp") {
      sync["status"] = c.ptp.status.empty() ? Json() : Json(c.ptp.status);
      sync["master"] = c.ptp.status == "Master";
      sync["offset_from_master_ns"] = c.ptp.has_offset ? Json(c.ptp.offset_from_master_ns) : Json();
      const bool locked = c.ptp.status == "Slave" || c.ptp.status == "Master";
      sync["locked"] = locked;
      // A camera the rig awaits (never opened) is not read: "not streaming" says it.
      if (!c.streaming && c.ptp.status.empty() && c.ptp_error.empty()) {
      } else if (!c.ptp_error.empty()) fail("PTP state not read: " + c.ptp_error);
      else if (c.ptp.status.empty())
        fail("PTP state not read yet (the monitor reads every camera twice a second)");
      else if (!locked)
        fail("PTP not locked (status " + c.ptp.status + ")");
      else if (c.ptp.status == "Slave" && c.ptp.has_offset &&
               std::abs(static_cast<double>(c.ptp.offset_from_master_ns)) > options.max_ptp_offset_us * 1e3)
        fail("PTP offset from the master " + std::to_string(c.ptp.offset_from_master_ns) +
             " ns exceeds " + Fixed(options.max_ptp_offset_us, 0) + " us (not converged)");
      // Off the rig's phase by d periods (wrapped to [-0.5, 0.5)).
      const double d = c.tick_phase >= 0 && have_phase
                           ? c.tick_phase - rig_phase - std::floor(c.tick_phase - rig_phase + 0.5)
                           : 0;
      sync["tick_phase"] = c.tick_phase >= 0 ? Json(c.tick_phase) : Json();
      sync["phase_from_rig_us"] = c.tick_phase >= 0 && have_phase ? Json(d * period_us) : Json();
      if (c.streaming && c.tick_phase >= 0 && static_cast<double>(c.complete) >= min_frames &&
          std::abs(d) > options.max_tick_phase_periods)
        fail("exposes " + Fixed(d * period_us, 0) + " us off the rig's other cameras within the tick (" +
             Fixed(d, 2) + " of a period; tick phase " + Fixed(c.tick_phase, 2) + ", the rig's " +
             Fixed(rig_phase, 2) + "): not exposing on the PTP clock's ticks (its exposure schedule, "
             "SyncFreeRunTimer*, is off or was refused), so its images join sets of another instant");
    } else if (in.sync == "free-run" || in.sync == "trigger") {
      sync["clock_fitted"] = c.clock_fitted;
      sync["clock_offset_ms"] = c.clock_offset_ms;
      sync["clock_drift_ppm"] = c.clock_drift_ppm;
      sync["clock_residual_us"] = c.clock_residual_us;
      if (in.sync == "free-run") {
        sync["offset_from_rig_ms"] = c.clock_fitted ? Json(c.clock_offset_ms - median_offset_ms) : Json();
        if (!c.clock_fitted) {
          fail("clock not fitted yet (" + std::to_string(c.complete) +
               " frames; the fit's drift needs a few hundred)");
        } else if (period_us > 0 && c.clock_residual_us > options.max_clock_residual_periods * period_us) {
          fail("clock fit residual " + Fixed(c.clock_residual_us, 0) + " us exceeds " +
               Fixed(options.max_clock_residual_periods * period_us, 0) + " us (" +
               Fixed(options.max_clock_residual_periods, 2) +
               " of a period): its frames' arrival times scatter too much to place them in sets");
        }
      } else {
        sync["role"] = c.trigger_master ? "master" : "triggered";
        sync["count_mismatches"] = c.count_mismatches;
        if (c.count_mismatches > 0)
          fail(std::to_string(c.count_mismatches) +
               " frames whose count disagreed with their timestamps (a trigger counted and not "
               "exposed, or exposed and not counted)");
      }
    }

    const std::uint64_t incomplete = c.missing_packets + c.size_mismatches + c.other_errors;
    const std::uint64_t lost = incomplete + c.underruns + c.not_received;
    Json frames = {{"complete", c.complete},       {"incomplete", incomplete},
                   {"missing_packets", c.missing_packets}, {"size_mismatches", c.size_mismatches},
                   {"underruns", c.underruns},     {"not_received", c.not_received},
                   {"timeouts", c.timeouts},
                   {"losses", c.losses},           {"reopens", c.reopens}};
    const double lost_fraction = c.complete > 0 ? static_cast<double>(lost) / c.complete : (lost > 0 ? 1.0 : 0.0);
    frames["lost_fraction"] = lost_fraction;
    if (static_cast<double>(c.complete) < min_frames)
      fail("too few frames so far to judge (" + std::to_string(c.complete) + " of the " +
           Fixed(min_frames, 0) + " of " + Fixed(options.min_seconds_of_frames, 1) +
           " s): check again once the rig has streamed");
    else if (lost_fraction > options.max_lost_frame_fraction)
      fail(std::to_string(lost) + " frames lost (" + std::to_string(incomplete) + " incomplete, " +
           std::to_string(c.underruns) + " underruns, " + std::to_string(c.not_received) +
           " not received) of " + std::to_string(c.complete) + ": " +
           Fixed(100 * lost_fraction, 2) + " %, above " +
           Fixed(100 * options.max_lost_frame_fraction, 2) + " %");
    Json packets = c.has_packet_statistics
                       ? Json{{"resent", c.resent_packets}, {"missing", c.missing_stream_packets}}
                       : Json();
    cameras.push_back({{"id", c.id},
                       {"ok", cp.empty()},
                       {"problems", cp},
                       {"sync", sync},
                       {"frames", frames},
                       {"packets", packets},
                       {"link", c.link.empty() ? Json() : Json(c.link)}});
  }

  Json links = Json::array();
  for (const LinkLoad& l : in.links) {
    const double headroom = l.capacity_mb_s - l.needed_mb_s;
    links.push_back({{"link", l.link},
                     {"interface", l.interface},
                     {"cameras", l.cameras},
                     {"capacity_mb_s", l.capacity_mb_s},
                     {"needed_mb_s", l.needed_mb_s},
                     {"headroom_mb_s", headroom},
                     {"ok", headroom >= 0}});
    if (headroom < 0)
      problems.push_back("link '" + l.link + "' (" + l.interface + "): its " +
                         std::to_string(l.cameras.size()) + " camera(s) need " +
                         Fixed(l.needed_mb_s, 1) + " MB/s of its " + Fixed(l.capacity_mb_s, 1) +
                         " MB/s (headroom " + Fixed(headroom, 1) + " MB/s; mocapd --check-config says what fits)");
  }

  Json rig_sync = {{"mode", in.sync}};
  if (in.sync == "ptp") {
    rig_sync["checked"] = in.ptp_checked;
    rig_sync["locked"] = in.ptp_checked ? Json(in.ptp_locked) : Json();
    std::string masters;
    for (const CameraCheckInput& c : in.cameras)
      if (c.ptp.status == "Master") masters += (masters.empty() ? "" : ", ") + c.id;
    rig_sync["master"] = masters.empty() ? Json("outside the rig") : Json(masters);
    rig_sync["tick_phase"] = have_phase ? Json(rig_phase) : Json();
    if (!in.ptp_checked) problems.push_back("PTP: not checked yet");
    else if (!in.ptp_locked && !in.ptp_why.empty()) problems.push_back("PTP: " + in.ptp_why);
  } else if (in.sync == "trigger") {
    const double fraction = in.sets > 0 ? static_cast<double>(in.mismatched_sets) / in.sets : 0;
    rig_sync["mismatched_sets"] = in.mismatched_sets;
    if (fraction > options.max_mismatched_set_fraction)
      problems.push_back(std::to_string(in.mismatched_sets) + " of " + std::to_string(in.sets) +
                         " sets had timestamps that disagree with their trigger count (" +
                         Fixed(100 * fraction, 2) + " %)");
  } else if (in.sync == "free-run") {
    rig_sync["median_offset_ms"] = median_offset_ms;
  }
  report["ok"] = problems.empty();
  report["problems"] = problems;
  report["sync"] = rig_sync;
  report["rate_hz"] = in.rate_hz;
  report["cameras"] = cameras;
  report["links"] = links;
  report["sets"] = {{"total", in.sets},
                    {"incomplete", in.incomplete_sets},
                    {"dropped", in.dropped_sets},
                    {"mismatched", in.mismatched_sets}};
  return report;
}

}  // namespace mocap::daemon
