// Intrinsics from images of a checkerboard, by OpenCV: inner corners found
// (cv::findChessboardCorners) and refined to subpixel accuracy (cv::cornerSubPix, the saddle point
// of the image gradient), then Zhang's method — a closed-form start from the homographies of the
// planar board, refined by Levenberg–Marquardt over intrinsics, distortion and every board pose
// (Z. Zhang, "A flexible new technique for camera calibration", IEEE PAMI 22(11), 2000; through
// cv::calibrateCamera). The result is in OpenCV's parameters, which camera_model.h uses as they
// are.
//
// The board must fill much of the image in some views and be tilted in others: a fronto-parallel
// board leaves the focal length and the board's distance interchangeable (Zhang's degenerate
// configurations).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "model/status.h"
#include "reconstruction/camera_model.h"

namespace mocap::reconstruction {

// An 8-bit grey image, row-major, no padding.
struct GrayImage {
  int width = 0, height = 0;
  std::vector<std::uint8_t> pixels;
};

struct CheckerboardOptions {
  int inner_corners_x = 9;  // inner corners along a row (squares - 1)
  int inner_corners_y = 6;
  double square_m = 0.03;
  int subpixel_window = 5;      // half size of cornerSubPix's window, pixels
  bool fix_k3 = true;           // k3 is rarely determined by a board and then absorbs noise
  bool fix_tangential = false;  // p1 = p2 = 0
  int min_images = 5;

  bool IsValid(std::string* error) const;
};

struct IntrinsicsSummary {
  int images = 0;
  int images_used = 0;
  std::vector<int> rejected;  // images in which the board was not found
  double rms_px = 0;          // OpenCV's reprojection RMS over all corners
  std::string BriefReport() const;
};

// All images come from one camera (same size).
Status CalibrateIntrinsics(const std::vector<GrayImage>& images, const CheckerboardOptions& options,
                           CameraIntrinsics* intrinsics, IntrinsicsSummary* summary);
// Reads the images (PNG, PGM, JPEG, ... through cv::imread) and calibrates.
Status CalibrateIntrinsicsFromFiles(const std::vector<std::string>& paths,
                                    const CheckerboardOptions& options,
                                    CameraIntrinsics* intrinsics, IntrinsicsSummary* summary);

}  // namespace mocap::reconstruction
