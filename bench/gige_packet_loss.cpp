// gige_packet_loss: what GVSP packet loss costs a camera on the Aravis backend
// (drivers/aravis_camera.h), on Aravis's GigE Vision fake camera over real sockets on 127.0.0.1
// (drivers/aravis_fake.h: GvFakeCamera, its `gvsp-lost-ratio`).
//
// Frame counts (default). For each loss ratio the camera streams for --seconds; every delivered
// frame is checked pixel for pixel against the image that was drawn
// (tests/aravis_test_util.h), so a frame with a missing packet that slipped through as complete
// would count as `corrupt`. Then the loss stops and the time to the next complete frame is the
// recovery.
//
//   gige_packet_loss [--seconds S] [--rate HZ] [--width W] [--height H] [--ratios 0,0.01,0.1]
//
// Prints per ratio: frames drawn by the fake, delivered complete, counted incomplete (missing
// packets; never delivered), timeouts, corrupt (must be 0), and the recovery time.
//
// Accuracy (--accuracy): what the loss costs the 3D points. The default simulated rig (8 cameras,
// 1280x1024, sim/camera_rig.h) films the default subject performing the protocol
// (sim/simulate.h, noise-free; the renderer's 0.1 px centroid jitter); each camera's images are
// drawn by the renderer INTO the GigE fake and received over GVSP, one camera after the other
// (one GigE fake per address), the same frame ids each time, at each loss ratio. Every frame
// delivered goes through detection (reconstruction/detection.h, the capture settings of `mocap
// capture --simulate`) and the sets of the same frame id through triangulation with the true
// cameras; a camera whose frame was lost is absent from that set, as the capture pipeline's sync
// emits it. Scored against the renderer's truth over every frame id drawn: recall (markers
// found within 5 mm, of those the truth shows to >= 2 cameras of the whole rig), 3D RMS error of
// the points matched, ghosts (points > 5 mm from every marker) and sets triangulated (>= 2
// cameras). Two cases per ratio: the loss on one camera's link (camera 0), and on every camera.
//
//   gige_packet_loss --accuracy [--frames N] [--rate HZ] [--packet-size BYTES] [--ratios ...]
//
// --packet-size 0 (default): the size Aravis negotiates on the path (loopback: ~1.4 kB, ~940
// packets a 1280x1024 frame); 8000: jumbo frames as a GigE mocap rig is set up (164 packets).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <iterator>
#include <map>
#include <memory>
#include <mutex>
#include <set>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "drivers/aravis_camera.h"
#include "drivers/aravis_fake.h"
#include "reconstruction/detection.h"
#include "reconstruction/triangulation.h"
#include "sim/camera_rig.h"
#include "sim/renderer.h"
#include "sim/simulate.h"
#include "tests/aravis_test_util.h"

using namespace mocap::drivers;
using mocap::Status;
namespace rec = mocap::reconstruction;

namespace {

struct Args {
  double seconds = 5, rate = 100;
  int width = 1280, height = 1024;
  std::vector<double> ratios = {0, 0.01, 0.1};
  bool accuracy = false;
  int frames = 400;
  int packet_size = 0;
};

// The GigE fake camera `index` drawing with `generator`, loss `ratio`, opened through the Aravis
// backend and started. Only one fake per address: the previous one must be gone.
Status OpenGigE(const Args& a, int index, ImageGenerator generator, double ratio,
                std::unique_ptr<GvFakeCamera>* fake, std::unique_ptr<AravisCamera>* cam) {
  *fake = std::make_unique<GvFakeCamera>("MOCAPGVB", index, std::move(generator), a.width,
                                         a.height);
  MOCAP_RETURN_IF_ERROR((*fake)->Create(60));
  (*fake)->SetPacketLossRatio(ratio);
  AravisCameraOptions o;
  o.camera_index = index;
  o.disable_packet_socket = true;
  *cam = std::make_unique<AravisCamera>((*fake)->device_id(), o);
  CameraSettings settings;
  settings.frame_rate_hz = a.rate;
  settings.timeout_ms = 300;
  settings.packet_size = a.packet_size;
  // A jumbo packet on loopback takes about twice its size of the receive buffer: the default
  // (one payload) overflows at 0 % loss. 8 MiB, as tests/test_aravis_gige.cpp (the kernel caps
  // it at net.core.rmem_max).
  if (a.packet_size > 0) settings.socket_buffer_bytes = 8 << 20;
  MOCAP_RETURN_IF_ERROR((*cam)->Open(settings));
  return (*cam)->Start();
}

int FrameCounts(const Args& a) {
  const double seconds = a.seconds, rate = a.rate;
  const int width = a.width, height = a.height;
  std::printf("GigE Vision fake on 127.0.0.1, %dx%d Mono8 at %.0f Hz, %.0f s per ratio\n", width,
              height, rate, seconds);
  std::printf("| gvsp-lost-ratio | drawn | complete | incomplete (counted, not delivered) | timeouts | corrupt delivered | recovery to the next complete frame |\n");
  std::printf("|---|---|---|---|---|---|---|\n");
  for (double ratio : a.ratios) {
    std::unique_ptr<GvFakeCamera> fake_owner;
    std::unique_ptr<AravisCamera> cam_owner;
    // Camera 0: the generator's camera, what CheckPattern compares against.
    if (Status s = OpenGigE(a, 0, testing::DrawPattern, ratio, &fake_owner, &cam_owner); !s.ok()) {
      std::fprintf(stderr, "gige_packet_loss: %s\n", s.message().c_str());
      return 1;
    }
    GvFakeCamera& fake = *fake_owner;
    AravisCamera& cam = *cam_owner;
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

// --accuracy ---------------------------------------------------------------------------------

// What one camera delivered in one pass: the frame ids the fake drew, and the detections of the
// frames received complete.
struct Pass {
  std::set<std::uint64_t> drawn;
  std::map<std::uint64_t, std::vector<rec::Centroid>> delivered;
  int incomplete = 0, timeouts = 0;
};

// Streams camera `index`'s images of the scene through the GigE fake at `ratio` until the fake
// has drawn `frames` + 10 images (or 60 s), detecting every frame delivered. The last ones drawn
// may still be on their way: only the first `frames` are scored.
Status RunPass(const Args& a, mocap::sim::Renderer* renderer, int index, double ratio, Pass* out) {
  auto drawn = std::make_shared<std::pair<std::mutex, std::set<std::uint64_t>>>();
  ImageGenerator draw = [renderer, drawn](int camera, std::uint64_t sequence, std::uint8_t* data,
                                          int w, int h, std::ptrdiff_t stride, PixelFormat f) {
    renderer->Render(camera, sequence, data, w, h, stride, f);
    std::lock_guard<std::mutex> lock(drawn->first);
    drawn->second.insert(sequence);
  };
  std::unique_ptr<GvFakeCamera> fake;
  std::unique_ptr<AravisCamera> cam;
  MOCAP_RETURN_IF_ERROR(OpenGigE(a, index, draw, ratio, &fake, &cam));
  rec::DetectionOptions detection;  // as `mocap capture --simulate` (tools/cmd_capture.cpp)
  detection.threshold = 60;
  detection.sigma_floor_px = 0.1;
  rec::DetectionWorkspace workspace;
  const auto end = std::chrono::steady_clock::now() + std::chrono::seconds(60);
  while (fake->FramesDrawn() < static_cast<std::uint64_t>(a.frames) + 10 &&
         std::chrono::steady_clock::now() < end) {
    Frame f;
    const GrabResult r = cam->Grab(&f);
    if (r == GrabResult::kIncomplete) ++out->incomplete;
    if (r == GrabResult::kTimeout) ++out->timeouts;
    if (r != GrabResult::kFrame) continue;
    std::vector<rec::Centroid> centroids;
    const Status s = rec::DetectMarkers(f.image, detection, nullptr, &workspace, &centroids);
    const std::uint64_t sequence = f.sequence;
    cam->Release(f);
    MOCAP_RETURN_IF_ERROR(s);
    out->delivered[sequence] = std::move(centroids);
  }
  cam->Stop();
  cam.reset();
  fake.reset();  // no more drawing
  // The next pass's buffers may be allocated where these were: the renderer must not take them
  // for buffers it drew into.
  renderer->ForgetBuffers();
  out->drawn = drawn->second;
  return Status::Ok();
}

struct Score {
  long sets = 0, triangulated = 0, eligible = 0, found = 0, points = 0, ghosts = 0;
  double sum_sq = 0;
  long camera_frames = 0, camera_frames_delivered = 0;
  double recall() const { return eligible ? static_cast<double>(found) / eligible : 0; }
  double rms_mm() const { return found ? 1e3 * std::sqrt(sum_sq / found) : 0; }
};

// Triangulates the set of frame id `sequence` from the cameras whose pass delivered it and
// scores it against the truth.
Status ScoreSet(const rec::Triangulator& triangulator, const mocap::sim::Renderer& renderer,
                const mocap::sim::Scene& scene, const std::vector<const Pass*>& passes,
                std::uint64_t sequence, rec::TriangulationWorkspace* workspace, Score* score) {
  const int n = static_cast<int>(passes.size());
  rec::DetectionSet set;
  set.sequence = sequence;
  set.cameras.resize(n);
  set.present.assign(n, false);
  // Markers the truth shows to >= 2 cameras of the whole rig: what a lossless rig could find.
  std::vector<int> views(scene.marker_count(), 0);
  for (int c = 0; c < n; ++c) {
    mocap::sim::FrameTruth truth;
    renderer.Truth(c, sequence, &truth);
    for (const mocap::sim::BlobTruth& b : truth.blobs) ++views[b.marker];
    set.cameras[c].camera = c;
    set.cameras[c].sequence = sequence;
    ++score->camera_frames;
    if (auto it = passes[c]->delivered.find(sequence); it != passes[c]->delivered.end()) {
      set.present[c] = true;
      set.cameras[c].centroids = it->second;
      ++score->camera_frames_delivered;
    }
  }
  std::vector<Eigen::Vector3d> markers(scene.marker_count());
  scene.Positions((static_cast<double>(sequence) - renderer.options().sequence_origin) /
                      renderer.options().frame_rate_hz,
                  markers.data());
  std::vector<rec::TriangulatedPoint> points;
  if (set.present_count() >= 2)
    MOCAP_RETURN_IF_ERROR(triangulator.Triangulate(set, workspace, &points));
  ++score->sets;
  score->triangulated += set.present_count() >= 2;
  std::vector<bool> found(markers.size(), false);
  for (const rec::TriangulatedPoint& p : points) {
    ++score->points;
    int best = -1;
    double best_d = 5e-3;
    for (std::size_t m = 0; m < markers.size(); ++m) {
      const double d = (p.position - markers[m]).norm();
      if (markers[m].allFinite() && d < best_d) best_d = d, best = static_cast<int>(m);
    }
    if (best < 0 || found[best]) {
      ++score->ghosts;
      continue;
    }
    found[best] = true;
    if (views[best] >= 2) score->sum_sq += best_d * best_d;
  }
  for (std::size_t m = 0; m < markers.size(); ++m) {
    if (views[m] < 2) continue;
    ++score->eligible;
    score->found += found[m];
  }
  return Status::Ok();
}

int Accuracy(const Args& a) {
  namespace sim = mocap::sim;
  sim::CameraRigOptions rig_options;
  rig_options.width = a.width;
  rig_options.height = a.height;
  const std::vector<rec::CameraModel> rig = sim::MakeCameraRig(rig_options);
  sim::SimulationOptions sim_options;
  sim_options.noise_mm = 0;
  sim_options.rate_hz = 200;
  sim::SimulatedSession session;
  if (Status s = sim::SimulateSession(sim_options, &session); !s) {
    std::fprintf(stderr, "gige_packet_loss: %s\n", s.message().c_str());
    return 1;
  }
  std::shared_ptr<const sim::Scene> scene = sim::MakeSessionScene(session);
  sim::RendererOptions render_options;  // 200 Hz, 0.1 px centroid jitter
  // The fake's first frame id is scene time 0 (the protocol's static pose): start 10 s in,
  // where the subject moves.
  render_options.sequence_origin = kAravisFakeFirstFrameId - 2000;
  sim::Renderer renderer(rig, scene, render_options);
  std::unique_ptr<rec::Triangulator> triangulator;
  if (Status s = rec::Triangulator::Create(rig, {}, &triangulator); !s) {
    std::fprintf(stderr, "gige_packet_loss: %s\n", s.message().c_str());
    return 1;
  }
  const int n = static_cast<int>(rig.size());
  std::printf("8 simulated cameras %dx%d, each through the GigE Vision fake on 127.0.0.1 in "
              "turn (%s packets), %d frame ids each, streamed at %.0f Hz; the subject at 200 Hz\n",
              a.width, a.height,
              a.packet_size ? std::to_string(a.packet_size).c_str() : "negotiated", a.frames,
              a.rate);
  // passes[ratio][camera]
  std::map<double, std::vector<Pass>> passes;
  for (double ratio : a.ratios) {
    for (int c = 0; c < n; ++c) {
      Pass p;
      if (Status s = RunPass(a, &renderer, c, ratio, &p); !s) {
        std::fprintf(stderr, "gige_packet_loss: camera %d at %g: %s\n", c, ratio,
                     s.message().c_str());
        return 1;
      }
      std::fprintf(stderr, "  loss %4.1f %% camera %d: %zu drawn, %zu delivered, %d incomplete, "
                   "%d timeouts\n", ratio * 100, c, p.drawn.size(), p.delivered.size(),
                   p.incomplete, p.timeouts);
      passes[ratio].push_back(std::move(p));
    }
  }
  // The frame ids every pass drew: the sets scored.
  std::set<std::uint64_t> common = passes.begin()->second[0].drawn;
  for (const auto& [ratio, ps] : passes) {
    for (const Pass& p : ps) {
      std::set<std::uint64_t> both;
      std::set_intersection(common.begin(), common.end(), p.drawn.begin(), p.drawn.end(),
                            std::inserter(both, both.begin()));
      common.swap(both);
    }
  }
  while (common.size() > static_cast<std::size_t>(a.frames)) common.erase(std::prev(common.end()));
  if (common.empty() || !passes.count(0.0)) {
    std::fprintf(stderr, "gige_packet_loss: no frame id drawn in every pass (or no 0 %% ratio)\n");
    return 1;
  }
  std::printf("%zu frame sets (frame ids %llu-%llu)\n", common.size(),
              static_cast<unsigned long long>(*common.begin()),
              static_cast<unsigned long long>(*common.rbegin()));
  std::printf("| gvsp-lost-ratio | lossy link | camera frames delivered | frames counted incomplete (never parsed) | sets triangulated (>= 2 cameras) | recall | 3D RMS | ghosts |\n");
  std::printf("|---|---|---|---|---|---|---|---|\n");
  rec::TriangulationWorkspace workspace;
  for (const auto& [ratio, lossy] : passes) {
    for (const bool every_camera : {false, true}) {
      if (ratio == 0 && every_camera) continue;
      std::vector<const Pass*> used;
      for (int c = 0; c < n; ++c)
        used.push_back(every_camera || c == 0 ? &lossy[c] : &passes.at(0.0)[c]);
      Score score;
      int incomplete = 0;
      for (const Pass* p : used) incomplete += p->incomplete;
      for (std::uint64_t sequence : common) {
        if (Status s = ScoreSet(*triangulator, renderer, *scene, used, sequence, &workspace,
                                &score); !s) {
          std::fprintf(stderr, "gige_packet_loss: frame %llu: %s\n",
                       static_cast<unsigned long long>(sequence), s.message().c_str());
          return 1;
        }
      }
      std::printf("| %.0f %% | %s | %.1f %% | %d | %.1f %% | %.2f %% | %.3f mm | %ld of %ld points |\n",
                  ratio * 100, ratio == 0 ? "none" : every_camera ? "every camera" : "camera 0",
                  100.0 * score.camera_frames_delivered / score.camera_frames, incomplete,
                  100.0 * score.triangulated / score.sets, 100 * score.recall(), score.rms_mm(),
                  score.ghosts, score.points);
      std::fflush(stdout);
    }
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  Args a;
  for (int i = 1; i < argc; ++i) {
    const bool value = i + 1 < argc;
    if (!std::strcmp(argv[i], "--accuracy")) a.accuracy = true;
    else if (value && !std::strcmp(argv[i], "--seconds")) a.seconds = std::atof(argv[++i]);
    else if (value && !std::strcmp(argv[i], "--rate")) a.rate = std::atof(argv[++i]);
    else if (value && !std::strcmp(argv[i], "--width")) a.width = std::atoi(argv[++i]);
    else if (value && !std::strcmp(argv[i], "--height")) a.height = std::atoi(argv[++i]);
    else if (value && !std::strcmp(argv[i], "--frames")) a.frames = std::atoi(argv[++i]);
    else if (value && !std::strcmp(argv[i], "--packet-size")) a.packet_size = std::atoi(argv[++i]);
    else if (value && !std::strcmp(argv[i], "--ratios")) {
      a.ratios.clear();
      std::stringstream in(argv[++i]);
      for (std::string r; std::getline(in, r, ',');) a.ratios.push_back(std::atof(r.c_str()));
    } else {
      std::fprintf(stderr, "usage: gige_packet_loss [--seconds S] [--rate HZ] [--width W] "
                           "[--height H] [--ratios 0,0.01,0.1] [--packet-size BYTES]\n"
                           "       gige_packet_loss --accuracy [--frames N] [--rate HZ] "
                           "[--packet-size BYTES] [--ratios 0,0.01,0.1]\n");
      return 2;
    }
  }
  return a.accuracy ? Accuracy(a) : FrameCounts(a);
}
