// gige_packet_loss: what GVSP packet loss costs a camera on the Aravis backend
// (drivers/aravis_camera.h), on Aravis's GigE Vision fake camera over real sockets on 127.0.0.1
// (drivers/aravis_fake.h: GvFakeCamera, its `gvsp-lost-ratio`). For each loss ratio the camera
// streams for --seconds; every delivered frame is checked pixel for pixel against the image that
// was drawn (tests/aravis_test_util.h), so a frame with a missing packet that slipped through as
// complete would count as `corrupt`. Then the loss stops and the time to the next complete frame
// is the recovery.
//
//   gige_packet_loss [--seconds S] [--rate HZ] [--width W] [--height H] [--ratios 0,0.01,0.1]
//
// Prints per ratio: frames drawn by the fake, delivered complete, counted incomplete (missing
// packets; never delivered), timeouts, corrupt (must be 0), and the recovery time.
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <sstream>
#include <string>
#include <vector>

#include "drivers/aravis_camera.h"
#include "drivers/aravis_fake.h"
#include "tests/aravis_test_util.h"

using namespace mocap::drivers;

int main(int argc, char** argv) {
  double seconds = 5, rate = 100;
  int width = 1280, height = 1024;
  std::vector<double> ratios = {0, 0.01, 0.1};
  for (int i = 1; i + 1 < argc; i += 2) {
    if (!std::strcmp(argv[i], "--seconds")) seconds = std::atof(argv[i + 1]);
    else if (!std::strcmp(argv[i], "--rate")) rate = std::atof(argv[i + 1]);
    else if (!std::strcmp(argv[i], "--width")) width = std::atoi(argv[i + 1]);
    else if (!std::strcmp(argv[i], "--height")) height = std::atoi(argv[i + 1]);
    else if (!std::strcmp(argv[i], "--ratios")) {
      ratios.clear();
      std::stringstream in(argv[i + 1]);
      for (std::string r; std::getline(in, r, ',');) ratios.push_back(std::atof(r.c_str()));
    } else {
      std::fprintf(stderr, "usage: gige_packet_loss [--seconds S] [--rate HZ] [--width W] "
                           "[--height H] [--ratios 0,0.01,0.1]\n");
      return 2;
    }
  }
  std::printf("GigE Vision fake on 127.0.0.1, %dx%d Mono8 at %.0f Hz, %.0f s per ratio\n", width,
              height, rate, seconds);
  std::printf("| gvsp-lost-ratio | drawn | complete | incomplete (counted, not delivered) | timeouts | corrupt delivered | recovery to the next complete frame |\n");
  std::printf("|---|---|---|---|---|---|---|\n");
  for (double ratio : ratios) {
    GvFakeCamera fake("MOCAPGVB", 0, testing::DrawPattern, width, height);
    if (mocap::Status s = fake.Create(60); !s.ok()) {
      std::fprintf(stderr, "gige_packet_loss: %s\n", s.message().c_str());
      return 1;
    }
    fake.SetPacketLossRatio(ratio);
    AravisCameraOptions o;
    o.camera_index = 0;  // the generator's camera: what CheckPattern compares against
    o.disable_packet_socket = true;
    AravisCamera cam(fake.device_id(), o);
    CameraSettings settings;
    settings.frame_rate_hz = rate;
    settings.timeout_ms = 300;
    if (mocap::Status s = cam.Open(settings); !s.ok() || !(s = cam.Start()).ok()) {
      std::fprintf(stderr, "gige_packet_loss: %s\n", s.message().c_str());
      return 1;
    }
    const std::uint64_t drawn0 = fake.FramesDrawn();
    int complete = 0, incomplete = 0, timeouts = 0, corrupt = 0;
    const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(seconds);
    while (std::chrono::steady_clock::now() < end) {
      Frame f;
      const GrabResult r = cam.Grab(&f);
      if (r == GrabResult::kIncomplete) ++incomplete;
      if (r == GrabResult::kTimeout) ++timeouts;
      if (r != GrabResult::kFrame) continue;
      std::uint64_t stamped = 0;
      if (!testing::CheckPattern(f, &stamped)) ++corrupt;
      ++complete;
      cam.Release(f);
    }
    const std::uint64_t drawn = fake.FramesDrawn() - drawn0;
    // Recovery: the loss stops; how long until a complete frame arrives.
    fake.SetPacketLossRatio(0);
    const auto t0 = std::chrono::steady_clock::now();
    double recovery_ms = -1;
    while (std::chrono::steady_clock::now() - t0 < std::chrono::seconds(5)) {
      Frame f;
      if (cam.Grab(&f) == GrabResult::kFrame) {
        recovery_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
        cam.Release(f);
        break;
      }
    }
    cam.Stop();
    std::printf("| %.0f %% | %llu | %d (%.1f %%) | %d (missing packets %llu) | %d | %d | %.0f ms |\n",
                ratio * 100, static_cast<unsigned long long>(drawn), complete,
                drawn ? 100.0 * complete / static_cast<double>(drawn) : 0.0, incomplete,
                static_cast<unsigned long long>(cam.Counters().missing_packets.load()), timeouts,
                corrupt, recovery_ms);
    std::fflush(stdout);
  }
  return 0;
}
