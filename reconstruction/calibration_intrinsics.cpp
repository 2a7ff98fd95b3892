#include "reconstruction/calibration_intrinsics.h"

#include <cstdio>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

namespace mocap::reconstruction {

bool CheckerboardOptions::IsValid(std::string* error) const {
  auto fail = [&](const char* what) {
    if (error) *error = std::string("checkerboard: ") + what;
    return false;
  };
  if (inner_corners_x < 3 || inner_corners_y < 3) return fail("needs at least 3 x 3 inner corners");
  if (inner_corners_x == inner_corners_y)
    return fail("inner corners must differ along x and y (a square board has no orientation)");
  if (!(square_m > 0)) return fail("square_m must be > 0");
  if (subpixel_window < 2) return fail("subpixel_window must be >= 2");
  if (min_images < 3) return fail("min_images must be >= 3");
  return true;
}

std::string IntrinsicsSummary::BriefReport() const {
  char buf[256];
  std::snprintf(buf, sizeof(buf), "Checkerboard intrinsics: %d of %d images used, RMS %.4f px",
                images_used, images, rms_px);
  return buf;
}

Status CalibrateIntrinsics(const std::vector<GrayImage>& images, const CheckerboardOptions& options,
                           CameraIntrinsics* intrinsics, IntrinsicsSummary* summary) {
  *summary = IntrinsicsSummary{};
  std::string error;
  if (!options.IsValid(&error)) return Status::Error(error);
  if (images.empty()) return Status::Error("checkerboard intrinsics: no images");
  const int w = images[0].width, h = images[0].height;
  const cv::Size board(options.inner_corners_x, options.inner_corners_y);
  std::vector<cv::Point3f> object;
  for (int y = 0; y < options.inner_corners_y; ++y)
    for (int x = 0; x < options.inner_corners_x; ++x)
      object.emplace_back(static_cast<float>(x * options.square_m),
                          static_cast<float>(y * options.square_m), 0.0f);
  std::vector<std::vector<cv::Point3f>> objects;
  std::vector<std::vector<cv::Point2f>> corners;
  summary->images = static_cast<int>(images.size());
  for (size_t i = 0; i < images.size(); ++i) {
    const GrayImage& im = images[i];
    if (im.width != w || im.height != h)
      return Status::Error("checkerboard intrinsics: image " + std::to_string(i) + " is " +
                           std::to_string(im.width) + " x " + std::to_string(im.height) +
                           ", image 0 is " + std::to_string(w) + " x " + std::to_string(h));
    if (im.width <= 0 || im.height <= 0 ||
        im.pixels.size() != static_cast<size_t>(im.width) * im.height)
      return Status::Error("checkerboard intrinsics: image " + std::to_string(i) +
                           " has a pixel buffer that does not match its size");
    const cv::Mat mat(im.height, im.width, CV_8UC1, const_cast<std::uint8_t*>(im.pixels.data()));
    std::vector<cv::Point2f> found;
    if (!cv::findChessboardCorners(mat, board, found,
                                   cv::CALIB_CB_ADAPTIVE_THRESH | cv::CALIB_CB_NORMALIZE_IMAGE)) {
      summary->rejected.push_back(static_cast<int>(i));
      continue;
    }
    const int win = options.subpixel_window;
    cv::cornerSubPix(mat, found, cv::Size(win, win), cv::Size(-1, -1),
                     cv::TermCriteria(cv::TermCriteria::EPS + cv::TermCriteria::COUNT, 100, 1e-4));
    corners.push_back(found);
    objects.push_back(object);
  }
  summary->images_used = static_cast<int>(corners.size());
  if (summary->images_used < options.min_images)
    return Status::Error("checkerboard intrinsics: the " + std::to_string(options.inner_corners_x) +
                         " x " + std::to_string(options.inner_corners_y) + " board was found in " +
                         std::to_string(summary->images_used) + " of " +
                         std::to_string(images.size()) + " images, need " +
                         std::to_string(options.min_images));
  int flags = 0;
  if (options.fix_k3) flags |= cv::CALIB_FIX_K3;
  if (options.fix_tangential) flags |= cv::CALIB_ZERO_TANGENT_DIST;
  cv::Mat k, dist;
  std::vector<cv::Mat> rvecs, tvecs;
  summary->rms_px =
      cv::calibrateCamera(objects, corners, cv::Size(w, h), k, dist, rvecs, tvecs, flags);
  CameraIntrinsics out;
  out.width = w;
  out.height = h;
  out.fx = k.at<double>(0, 0);
  out.fy = k.at<double>(1, 1);
  out.cx = k.at<double>(0, 2);
  out.cy = k.at<double>(1, 2);
  const double* d = dist.ptr<double>();
  out.k1 = d[0];
  out.k2 = d[1];
  out.p1 = d[2];
  out.p2 = d[3];
  out.k3 = dist.total() > 4 ? d[4] : 0.0;
  if (!out.IsValid(&error))
    return Status::Error("checkerboard intrinsics: result invalid: " + error);
  *intrinsics = out;
  return Status::Ok();
}

Status CalibrateIntrinsicsFromFiles(const std::vector<std::string>& paths,
                                    const CheckerboardOptions& options,
                                    CameraIntrinsics* intrinsics, IntrinsicsSummary* summary) {
  std::vector<GrayImage> images;
  for (const std::string& p : paths) {
    const cv::Mat m = cv::imread(p, cv::IMREAD_GRAYSCALE);
    if (m.empty()) return Status::Error(p + ": cannot read the image");
    GrayImage g;
    g.width = m.cols;
    g.height = m.rows;
    g.pixels.resize(static_cast<size_t>(m.cols) * m.rows);
    for (int y = 0; y < m.rows; ++y)
      std::copy(m.ptr<std::uint8_t>(y), m.ptr<std::uint8_t>(y) + m.cols,
                g.pixels.begin() + static_cast<size_t>(y) * m.cols);
    images.push_back(std::move(g));
  }
  return CalibrateIntrinsics(images, options, intrinsics, summary);
}

}  // namespace mocap::reconstruction
