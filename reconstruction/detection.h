// 2D marker detection: the bright blobs of one infrared image, as subpixel centroids.
//
// Algorithm (one pass over the image, top to bottom):
//
//  1. Row scan. A pixel is bright when value >= threshold. Infrared images of a capture volume are
//     almost entirely dark (a few dozen markers of a few pixels each on a 1.3-megapixel frame), so
//     the scan is built to reject dark pixels as fast as memory delivers them: 64 pixels at a time
//     it takes the maximum of the block with SIMD and compares that once against the threshold
//     (AVX2 when the compiler targets it, else GCC/Clang vector extensions, which lower to SSE2 or
//     NEON). Only a block that holds a bright pixel is turned into a bit mask, whose set bits are
//     walked with count-trailing-zeros to give the RUNS of bright pixels [x0, x1) of the row. Each
//     dark pixel is read exactly once; bright pixels are read a second time to weigh them.
//  2. Connected components over runs, not pixels. A run joins every run of the previous row that
//     it touches with 8-connectivity (x ranges overlapping once widened by one pixel, as OpenCV's
//     default), found by a two-pointer merge of the two sorted run lists; runs that join two
//     blobs unite them (union-find over blob labels, path compression). Each blob carries running
//     sums (count, first and second moments, weighted and unweighted), so no pixel list is kept
//     and nothing is revisited: the sums of a united blob are added into its root.
//  3. A blob is finished on the first row with no run touching it: it is then filtered (size,
//     shape, border, reflection mask) and given its thresholded centre and uncertainty from its
//     sums. The windowed refinement below runs as soon as the scan has passed the last row of
//     the blob's window, while those rows are still in cache (a frame arrives by DMA; coming
//     back to it after the scan would fetch every window from memory again). Centroids are
//     returned in order of each blob's first pixel.
//
// Two centres are computed; DetectionOptions::centroid says which one is reported.
//
// kThresholdWeighted: weights w = value - (threshold - 1), the signal above the threshold (plus
// one count so that a blob lying entirely at the threshold still has a defined centre). Why not
// the raw or background-subtracted value: with those, a pixel that noise pushes across the
// threshold enters or leaves the blob with a weight equal to the threshold, a jump that drags
// the centroid towards the pixel grid ("pixel locking"). With w = value - threshold the weight
// of a pixel goes to zero continuously at the edge of the blob, so which edge pixels happen to be
// above the threshold hardly matters, and the background (below the threshold) is removed with
// it. It costs nothing beyond the scan (running sums) but it still cuts the spot's profile at the
// threshold, and the sampled centroid of a cut profile is biased: up to 0.05 px for a spot of
// sigma 1 px peaking at 3-5x the threshold, 0.1 px at sigma 0.8 px (bench/detect_vs_opencv).
//
// kGaussianWindowed (default): refines that centre with an iteratively re-centred Gaussian window
// over the background-subtracted values (value - background_dn) of a window around the blob that
// reaches below the threshold into the spot's tails. It solves
//     sum_i (x_i - c) (value_i - b) G(x_i - c) = 0,   G = exp(-|x - c|^2 / (2 s^2))
// by Newton's method (two steps from the thresholded centre, typically). Nothing is cut: the window goes to
// zero smoothly, and because G is centred on c, a symmetric spot's own samples balance each other
// whatever its sampling phase, so the pixel-locking bias falls below 0.01 px; for the same
// reason an error in the background level b cancels to first order. s = 1.3 x the blob's
// thresholded second-moment radius (the cut moments understate the spot's width; 1.3 matches
// the spot, which also minimises the noise of the estimate). Bright pixels of the window outside
// the blob's bounding box belong to other blobs and are left out. Cost: (blob width + 5 s)^2
// pixels x 3 passes (two Newton steps, one for the uncertainty), 4-wide, on rows still in cache:
// about 2.5 us per marker, i.e. 40 markers cost about 2/3 of the scan of a 1.3 MP frame. A saturated
// spot (peak at DetectionOptions::saturation_level) is a plateau with a sharp rim, which no sampled centroid
// handles exactly: its window is 3x the moment radius, averaging over more of the rim; still,
// 0.03 px holds for sigma >= 1.2 px up to 5x saturation; smaller or harder-saturated spots
// (nearly binary discs) keep errors of 0.03-0.07 px (tests/test_detection.cpp). A blob whose
// refinement moves by more than a pixel (a neighbour inside the window) keeps the thresholded
// centre.
//
// Shape: the weighted second moments of the blob, each pixel counted as a unit square (adding
// 1/12 px^2 to both variances, so that a 1- or 2-pixel blob has a finite, honest shape).
// roundness = sqrt(minor eigenvalue / major eigenvalue) = minor / major axis, in (0, 1].
// Two markers whose images touch merge into one elongated blob. On a moving subject those are
// most of the detector's error (simulated protocol, 8 cameras: 0.6 % of the centroids had a
// neighbour within 5 px, erred by 0.43 px RMS and made 98 % of the detector's squared error; the
// rest err by 0.006 px) and 4.5 % of the markers' views. Three answers, in order:
//
// Splitting. An elongated blob (roundness below overlap_roundness, down to split_min_roundness,
// so also pairs a spot diameter apart that the roundness filter would drop) is fitted by
// Levenberg-Marquardt with two round Gaussian spots of one common width (x1, y1, x2, y2, A1, A2,
// log s^2: 7 unknowns) over its bounding box and a one-pixel ring, started at the centre
// +- sqrt(major - minor) along the major axis; saturated pixels and other blobs' pixels are left
// out. The alternative is one elliptical spot (a marker smeared by motion or the lens, or a
// flat-topped disc, which two Gaussians would also fit), fitted the same way. When the two spots
// leave at most split_min_gain of the ellipse's squared residual, are of comparable brightness
// (the fainter at least a fifth of the brighter), at least split_min_separation_px apart and
// inside the blob, both are reported, each with sigma_px^2 from the fit's covariance (residual
// variance x (J^T J)^-1, which carries the profile's mismatch: a marker's image is a blurred
// disc, not a Gaussian) plus the floor^2. Gaussian-windowed centres only.
//
// Otherwise, rejection: below min_roundness (about a spot diameter apart: < 0.6) the blob is
// dropped rather than reported as a centre between two markers.
//
// Otherwise, an honest sigma: a pair closer than that looks like one slightly oval marker and
// passes, its centre pulled along the major axis. A blob less round than `overlap_roundness`
// (single spots score above 0.9 but for 1 in 300) adds its elongation, major - minor, to
// sigma_px^2: for two equal spots s apart that is (s / 2)^2, the distance from either marker to
// the blob's centre. Triangulation then leans on the other cameras' views of that marker, and
// the rare single spot so flagged merely loses weight.
//
// Uncertainty sigma_px: first-order propagation of independent pixel noise through the centre,
// var_i = read_noise^2 + 1/12 + gain * value_i (read noise, quantisation, shot noise, in the
// image's units). Thresholded: x_c = sum(w_i x_i) / W, d x_c / d value_i = (x_i - x_c) / W, so
//     var(x_c) = sum_i var_i (x_i - x_c)^2 / W^2,
// from the blob's running sums with no second pass (w is continuous at the threshold, so pixels
// crossing it add no further first-order term). Gaussian-windowed: by implicit differentiation
// of the equation above, d c / d value_i = (x_i - c) G_i / D with D = sum_i (value_i - b) G_i
// (1 - (x_i - c)^2 / s^2), so var(c) = sum_i var_i (x_i - c)^2 G_i^2 / D^2, summed in a last
// pass at the converged centre. Likewise along y. sigma_px = sqrt(max(var_x, var_y) + floor^2); the floor stands
// for what pixel noise does not model (residual sampling bias, lens blur, marker shape).
//
// Threads: the options and the reflection mask are read-only and may be shared; every thread
// owns its DetectionWorkspace. After the first frames have sized it (or after Reserve), a frame
// with no more runs per row and blobs than seen before allocates nothing, provided the output
// vector keeps its capacity (it is cleared, not freed).
#pragma once
#include <cstdint>
#include <string>
#include <vector>

#include "drivers/frame.h"
#include "model/status.h"
#include "reconstruction/centroid.h"

namespace mocap::reconstruction {

class ReflectionMask;

struct DetectionOptions {
  // In the image's own units (0..255 for Mono8, 0..4095 for Mono12, 0..65535 for Mono16); a
  // pixel is bright when value >= threshold. Must be >= 1 and within the image's bit depth.
  int threshold = 64;
  // Blob size, in bright pixels. A marker 3-10 px across covers about 7-80 px.
  int min_area_px = 3;
  int max_area_px = 500;
  // minor / major axis of the blob (see above). A round marker scores about 0.8-1 even at 3 px;
  // two merged markers a spot diameter apart score below 0.6.
  double min_roundness = 0.6;
  // Blobs less round than this may hold two overlapping spots: their sigma_px grows with the
  // elongation (see above). 0: no such term.
  double overlap_roundness = 0.9;
  // Such blobs (down to split_min_roundness, below min_roundness too) are fitted with two spots;
  // when the fit finds two of comparable brightness at least split_min_separation_px apart, both
  // are reported (see above). Gaussian-windowed centres only.
  bool split_overlapping = true;
  double split_min_roundness = 0.3;
  double split_min_separation_px = 2.0;
  // ... and only when two round spots leave at most this fraction of the squared residual that
  // one elliptical spot leaves (a marker smeared by motion is one oval spot, not two).
  double split_min_gain = 0.5;
  // A blob that touches the first or last row or column is cut by the edge of the sensor and its
  // centroid is pulled inwards: dropped when true.
  bool drop_border_blobs = true;
  // Which centre is reported (see above): the thresholded one costs about half as much and is
  // biased by up to 0.05-0.1 px on spots of sigma <= 1 px.
  enum class CentroidMethod { kThresholdWeighted, kGaussianWindowed };
  CentroidMethod centroid = CentroidMethod::kGaussianWindowed;
  // The image's level where there is no light (black level), for kGaussianWindowed. An error in
  // it cancels to first order (tests: 15 DN off moves centres by < 0.005 px).
  double background_dn = 0;
  // The value at which the sensor clips, in the image's units; 0: the pixel format's largest
  // value. Set it where the data does not fill the format (12-bit data shifted into Mono16
  // clips at 65520; a camera with a digital gain may clip lower). Saturated blobs get a wider
  // window (above).
  int saturation_level = 0;
  // Pixel noise model for sigma_px, in the image's units (DN): read noise (standard deviation)
  // and the shot-noise gain (variance per DN of signal; 0 leaves shot noise out).
  double read_noise_dn = 1.0;
  double shot_noise_gain = 0.0;
  double sigma_floor_px = 0.01;
  // More blobs than this passing the filters is an error (the threshold is at the background, the
  // room lights are on): the frame is not worth triangulating.
  int max_centroids = 1000;
  // Use the portable scan even where AVX2 is available (tests compare the two; benchmarks).
  bool force_portable_scan = false;

  bool IsValid(std::string* error) const;
};

// What happened to the blobs of one frame (for tests, diagnostics and the daemon's counters).
struct DetectionStats {
  int runs = 0;         // bright runs found by the row scan
  int blobs = 0;        // connected components
  int accepted = 0;     // centroids returned
  int too_small = 0;    // area < min_area_px
  int too_large = 0;    // area > max_area_px
  int not_round = 0;    // roundness < min_roundness
  int at_border = 0;    // touching the image edge (drop_border_blobs)
  int masked = 0;       // centre inside the reflection mask
  int split_attempts = 0;  // elongated blobs fitted with two spots
  int split = 0;           // ... reported as two spots
};

// Per-thread scratch memory of DetectMarkers. Its buffers grow to the largest frame seen and
// are then reused.
class DetectionWorkspace {
 public:
  // Sizes the buffers for rows of up to `max_runs_per_row` runs and `max_blobs` blobs per frame,
  // so that even the first frame allocates nothing.
  void Reserve(int max_runs_per_row, int max_blobs);
  // Bytes held (capacity, not size): constant across frames once warm.
  std::size_t CapacityBytes() const;

 private:
  friend class DetectionScanner;
  struct Run {
    int x0, x1;  // [x0, x1)
    int label;
  };
  struct Blob {
    // Unweighted sums (exact): pixel count, sum x, sum y, sum x^2, sum y^2.
    std::int64_t n, sx, sy, sxx, syy;
    // Weighted sums, w = value - threshold + 1.
    double w, wx, wy, wxx, wyy, wxy;
    int peak;
    bool border;
    int x_min, x_max, y_min, y_max;  // bounding box, inclusive
    bool closed;                     // no later row can touch it; filtered
  };
  struct Candidate {
    int blob = 0;       // index into blobs_
    double s = 0;       // Gaussian window sigma
    double overlap_var = 0;  // px^2 added to sigma_px^2 for a possible second spot (see above)
    bool try_split = false;  // elongated: fit two spots first
    bool keep_single = true;  // when the split fails: one centroid (else dropped, not round)
    bool dropped = false;
    double split_dx = 0, split_dy = 0, split_s2 = 1;  // starting offset of the two spots, width^2
    double split_mxx = 1, split_myy = 1, split_mxy = 0;  // the blob's second moments
    int ready_row = 0;  // the last row of its window
    Centroid centroid;
  };

  std::vector<Run> previous_, current_;
  std::vector<int> parent_;
  std::vector<Blob> blobs_;
  std::vector<Candidate> candidates_;  // blobs that passed the filters
  std::vector<int> queue_;             // candidates waiting for the scan to pass their window
  // Gaussian-window refinement: weights along x (and times d, d^2), along y; the window's pixels.
  std::vector<double> gx_, gy_, gxd_, gxdd_, gxd2_, window_;
  // Two-spot fit: the window's usable pixels (x, y, value) and their model derivatives.
  std::vector<double> split_x_, split_y_, split_v_;
};

// Finds the markers of `image` (Mono8, Mono12 or Mono16). `centroids` is cleared and filled in
// order of each blob's first row. `mask` (may be null) drops blobs whose centre lies in it; it
// must have the image's size. `stats` is optional. Errors (no centroid returned): an invalid
// image (null data, non-positive size, stride too small for the width, unknown pixel format),
// invalid options, a threshold beyond the bit depth, a mask of another size, too many blobs.
Status DetectMarkers(const drivers::ImageView& image, const DetectionOptions& options,
                     const ReflectionMask* mask, DetectionWorkspace* workspace,
                     std::vector<Centroid>* centroids, DetectionStats* stats = nullptr);

// Checks an image view (shared by detection and the reflection mask).
Status CheckImage(const drivers::ImageView& image);

}  // namespace mocap::reconstruction
