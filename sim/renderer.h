// The image renderer: what an IR motion-capture camera would see of the simulated subject —
// dark images with one bright blob per visible retro-reflective marker — drawn into the buffers
// of the simulated and Aravis fake cameras (drivers/simulated_camera.h, drivers/aravis_fake.h),
// with the TRUTH of every image (which markers, at which pixel) for tests of detection.
//
// The blob. A sphere marker of diameter D at depth z images as a disc of radius
// R = f (D/2) / z pixels (f the focal length; the small tilt of the disc off-axis is ignored),
// blurred by the lens/sensor point-spread function, a Gaussian of sigma s: the pixel at
// distance r from the centre gets  I * P(r; R, s)  with
//     P(r; R, s) = integral over the disc of the Gaussian = int_0^R (rho/s^2) exp(-(r^2+rho^2)/2s^2)
//                  I0(r rho / s^2) d rho,
// tabulated once in (R/s, r/s) and interpolated bilinearly (P = 1 - exp(-R^2/2s^2) at the
// centre, a soft edge of width ~s at r = R). Noise: sigma^2 = read^2 + shot^2 * signal (fractions
// of full scale); values are clipped at full scale (saturation) and quantised to Mono8/12/16.
// `centroid_noise_px` moves each drawn blob's centre by N(0, sigma) per axis per frame, so the
// pipeline's centroid error is about that sigma even with a perfect detector; the truth keeps
// both the projected and the drawn centre.
//
// Why it is cheap enough for 8 cameras x 1280x1024 x 200 Hz on a shared core: it never touches
// every pixel. The background is a constant dark level, noise is drawn only in a margin around
// each blob, and for every destination buffer (keyed by its data pointer) the renderer keeps the
// rectangles it drew last time and resets only those to the background before drawing the new
// blobs. A buffer it has not seen (or whose geometry changed) is cleared once in full. All random
// draws are hashes of (seed, stream, camera, frame, pixel/marker), so an image is a pure function
// of (camera, sequence): rendering order and threads do not matter, and Truth() recomputes what
// Render() drew without storing it.
//
// Buffers smaller than the camera's sensor show its top-left corner (an ROI at offset 0).
// Rendering of one camera is serialised (a mutex per camera); different cameras render in
// parallel from their own threads.
//
// Usage:
//   sim::SimulatedSession session;  sim::SimulateSession(opts /* noise_mm = 0 */, &session);
//   auto rig = sim::MakeCameraRig({});
//   sim::Renderer renderer(rig, sim::MakeSessionScene(session), {});
//   drivers::ImageGenerator gen = renderer.Generator();   // to SimulatedCamera / AravisFakeRig
//   sim::FrameTruth truth;  renderer.Truth(camera, frame.sequence, &truth);
#pragma once
#include <Eigen/Core>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <unordered_map>
#include <vector>

#include "drivers/camera_source.h"
#include "reconstruction/camera_model.h"

namespace mocap::sim {

struct SimulatedSession;

// Marker world positions (metres) as a function of time; a NaN position is an absent marker.
class Scene {
 public:
  virtual ~Scene() = default;
  virtual int marker_count() const = 0;
  // Writes marker_count() positions; must not allocate (it runs per camera per frame).
  virtual void Positions(double time_s, Eigen::Vector3d* positions) const = 0;
  // The scene repeats with this period (0: it does not).
  virtual double duration_s() const { return 0.0; }
};

// The session's trials one after the other (each at its own rate), linearly interpolated between
// samples, looping. Noise-free positions need a session simulated with noise_mm = 0, missing = 0.
std::shared_ptr<const Scene> MakeSessionScene(const SimulatedSession& session);
// Fixed points.
std::shared_ptr<const Scene> MakeStaticScene(std::vector<Eigen::Vector3d> points);
// Any callback (it must not allocate if used at full rate).
std::shared_ptr<const Scene> MakeCallbackScene(
    int markers, std::function<void(double, Eigen::Vector3d*)> positions, double duration_s = 0);

struct RendererOptions {
  double frame_rate_hz = 200.0;        // time of frame `sequence` = (sequence - origin) / rate
  std::uint64_t sequence_origin = 0;
  double marker_diameter_m = 0.014;
  double psf_sigma_px = 0.6;
  double marker_intensity = 0.9;       // disc radiance, fraction of full scale (> 1 saturates)
  double background = 0.03;            // dark level, fraction of full scale
  double read_noise = 0.004;           // sigma, fraction of full scale
  double shot_noise = 0.01;            // sigma at full-scale signal
  double noise_margin_px = 2.0;        // noise is drawn this far beyond each blob's support
  double centroid_noise_px = 0.1;      // per axis, per blob, per frame
  double min_depth_m = 0.2;            // markers closer to a camera than this are not drawn
  // Static reflections (shiny fixtures): spots fixed per camera, in every frame.
  int reflections_per_camera = 0;
  double reflection_radius_px = 2.0;
  double reflection_intensity = 0.8;
  // Occlusions: a marker is hidden from a camera for blocks of `occlusion_block_frames` frames,
  // each block with this probability.
  double occlusion_probability = 0.0;
  int occlusion_block_frames = 20;
  // Timing jitter: each camera's image is taken at frame time + N(0, sigma).
  double timing_jitter_s = 0.0;
  std::uint64_t seed = 1;

  bool IsValid(std::string* error) const;
};

struct BlobTruth {
  int marker = -1;                  // index into the scene's markers; -1 for a reflection
  Eigen::Vector2d projected{0, 0};  // the true projection of the marker centre (sensor pixels)
  Eigen::Vector2d drawn{0, 0};      // where the blob was drawn (projected + centroid noise)
  double radius_px = 0;
};

struct FrameTruth {
  int camera = -1;
  std::uint64_t sequence = 0;
  double time_s = 0;                // the scene time of this camera's image (with jitter)
  std::vector<BlobTruth> blobs;     // visible markers: centre inside the image, not occluded
  std::vector<BlobTruth> reflections;
};

class Renderer {
 public:
  Renderer(std::vector<reconstruction::CameraModel> cameras, std::shared_ptr<const Scene> scene,
           RendererOptions options = {});
  ~Renderer();

  // Checks the options and the rig; the Renderer draws nothing (blank images) when not ok.
  const Status& status() const { return status_; }
  int camera_count() const { return static_cast<int>(cameras_.size()); }
  const RendererOptions& options() const { return options_; }
  const std::vector<reconstruction::CameraModel>& cameras() const { return cameras_; }

  void Render(int camera, std::uint64_t sequence, std::uint8_t* data, int width, int height,
              std::ptrdiff_t stride, drivers::PixelFormat format);
  // Render bound to this renderer (which must outlive the generator's users).
  drivers::ImageGenerator Generator();
  // What Render() draws for (camera, sequence), in sensor pixels, for an image of the full
  // sensor (a smaller buffer drops the blobs outside it).
  void Truth(int camera, std::uint64_t sequence, FrameTruth* truth) const;
  // Forgets the remembered buffers (call when buffers are freed and may be reallocated).
  void ForgetBuffers();

 private:
  struct Rect {
    int x0, y0, x1, y1;  // inclusive-exclusive
  };
  struct BufferRecord {
    int width = 0, height = 0;
    std::ptrdiff_t stride = 0;
    drivers::PixelFormat format = drivers::PixelFormat::kMono8;
    std::vector<Rect> rects;
  };
  struct Blob {
    double x, y, radius, intensity;
    int marker;
    double px, py;  // projected (truth)
  };
  struct CameraState {
    std::mutex mutex;
    std::unordered_map<const std::uint8_t*, BufferRecord> buffers;
    std::vector<Blob> blobs;
    std::vector<Eigen::Vector3d> positions;
    std::vector<Blob> reflections;
  };

  void ComputeBlobs(int camera, std::uint64_t sequence, std::vector<Eigen::Vector3d>* positions,
                    std::vector<Blob>* blobs, double* time_s) const;

  std::vector<reconstruction::CameraModel> cameras_;
  std::shared_ptr<const Scene> scene_;
  RendererOptions options_;
  Status status_;
  std::vector<std::unique_ptr<CameraState>> states_;
  const std::vector<float>* noise_ = nullptr;  // standard normal variates, shared per seed
  // The dark pixels (no blob's light) quantised once per format (Mono8, Mono12, Mono16), entry i
  // for the noise variate (*noise_)[i]: most of a blob's rectangle is the noise margin, and a
  // table lookup there instead of the noise model and the rounding halves the renderer's time,
  // which the simulated cameras spend on the capture pipeline's cores.
  std::vector<std::uint16_t> dark_[3];
};

}  // namespace mocap::sim
