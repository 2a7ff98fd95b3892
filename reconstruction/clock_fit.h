// A camera's clock against the host's: a robust online linear fit of the host arrival times of
// its frames against their device timestamps, for rigs whose cameras share no clock (free run).
//
// Why a lower envelope, not a least-squares line: a frame reaches the host some latency after
// its exposure (transport, the driver's queue, the scheduler), and latency only ever ADDS: the
// arrival line host = device + offset + drift x device is the lower edge of the points, and the
// points far above it are the frames that waited. A least-squares line through all of them would
// sit at the mean latency and tilt whenever the load changes. So the window of recent samples is
// cut into `segments` runs, the earliest-arriving frame of each run (the one that waited least)
// is kept, and the line fitted is the lower support line of those minima (of the lines through
// two of them with none below, the one nearest to all: the convex-hull estimator of network
// clock sync): runs whose best frame still waited (a loaded second, or several) lie above it
// and move neither the slope nor the intercept, however many of them there are. That line rests on
// two minima, and a camera's own timestamps jitter by microseconds to tens of them, so its slope
// is then refitted by least squares through every minimum near it (ClockFitOptions::near_line_ns)
// and the line lowered onto the lowest of them: the jitter averaged over all the runs that did not
// wait, not taken from two (over 2.7 s at 100 Hz with 20 us of jitter, the drift's RMS error 17
// -> 12 ppm: tests/test_frame_sync.cpp). The fitted drift is the camera clock's rate error
// against the host (tens of ppm for crystal oscillators), which over a recording of minutes is
// milliseconds: more than a frame period at 200 Hz. Until `min_samples_for_drift` samples are
// in, the fit is the offset alone (the minimum of host - device), the best a few frames say.
//
// The mapped time ToHost(device) is the exposure on the host's clock, late by the camera's
// smallest latency: cameras on like links agree on it to within the difference of their best
// latencies (microseconds), which is what frame sync (reconstruction/frame_sync.h) needs to put
// the images of one instant into one set. It is only as good as that assumption: a camera on a
// slower link is consistently late by the difference.
//
// After the camera restarts (its clock starts again) the old line is meaningless: Reset().
// Not thread-safe; one per camera, fed in the order of its frames.
#pragma once
#include <cstdint>
#include <string>
#include <vector>

namespace mocap::reconstruction {

struct ClockFitOptions {
  int window = 1024;                // recent samples fitted (5 s at 200 Hz)
  int segments = 16;                // runs of the window whose earliest arrivals are fitted
  int min_samples_for_drift = 128;  // before: the offset only (8 frames a run at least)
  int refit_every = 16;             // samples between two fits (a fit reads the whole window)
  // A fitted drift beyond this is clamped to it: a clock that far off is broken, not drifting,
  // and a wild slope would throw the camera's frames out of every set.
  double max_drift_ppm = 1000;
  // The runs' earliest arrivals within this of the lower support line are the timestamps'
  // scatter, through which the slope is refitted by least squares (see Refit); those above it
  // waited. Above a camera's timestamp jitter (GigE Vision and USB3 Vision stamps: microseconds
  // to tens of them), below a loaded host's waits (hundreds of microseconds and more).
  double near_line_ns = 100'000;

  bool IsValid(std::string* error) const;
};

class ClockFit {
 public:
  explicit ClockFit(ClockFitOptions options = {});
  // Forgets every sample (the camera's clock restarted).
  void Reset();
  void Add(std::uint64_t device_ns, std::uint64_t host_ns);
  // The host time of device time `device_ns` (the lower envelope of the arrivals). Before the
  // first sample: device_ns itself.
  std::int64_t ToHost(std::uint64_t device_ns) const;
  // The camera clock's rate error against the host's (ppm; > 0: the camera's clock runs fast).
  double drift_ppm() const { return -slope_ * 1e6; }
  // host - device at the newest sample's device time, ns.
  std::int64_t offset_ns() const;
  int samples() const { return static_cast<int>(count_); }
  bool drift_fitted() const { return drift_fitted_; }
  // How well the line is known, ns: the largest height of the runs' earliest arrivals above the
  // fitted line at the last fit (0 until the drift is fitted). Each run's best frame should lie
  // ON the line; one that lies above it waited even at its best, so the mapped time of that
  // stretch is uncertain by as much. A rig check (daemon/rig_check.h) sets it against the set
  // tolerance: a residual of a sizeable fraction of a period means the sets are guesses.
  double residual_ns() const { return residual_ns_; }

 private:
  void Refit();

  ClockFitOptions options_;
  // Samples relative to the first one: x = device - device0, y = (host - device) - y0, so that
  // the doubles of the fit hold small numbers whatever the camera's epoch.
  std::vector<double> x_, y_;  // rings of `window`
  std::size_t next_ = 0, size_ = 0, count_ = 0;
  std::int64_t device0_ = 0, y0_ = 0;
  std::int64_t last_device_ = 0;
  double intercept_ = 0, slope_ = 0;  // y = intercept + slope x
  bool drift_fitted_ = false;
  double residual_ns_ = 0;
  std::vector<double> mx_, my_;
};

}  // namespace mocap::reconstruction
