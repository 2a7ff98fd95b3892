#include "drivers/aravis_fake.h"

#include <arv.h>

#include <fcntl.h>
#include <sys/file.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstring>
#include <thread>

namespace mocap::drivers {
namespace {

// Aravis's fake camera calls this from its stream thread (ArvFakeDevice) or its GVSP thread
// (GigE fake) with the buffer to fill.
void FillHook(ArvBuffer* buffer, void* data, guint32 /*exposure_us*/, guint32 /*gain*/,
              ArvPixelFormat arv_format) {
  auto* ctx = static_cast<FakeFillContext*>(data);
  if (buffer == nullptr || ctx == nullptr || !ctx->generator) return;
  PixelFormat format;
  if (!FromArvPixelFormat(arv_format, &format)) return;  // e.g. a Bayer format: left as it is
  const int w = arv_buffer_get_image_width(buffer);
  const int h = arv_buffer_get_image_height(buffer);
  size_t reported = 0;  // 0 on this path: the size is w x h x bytes per pixel
  auto* pixels = static_cast<std::uint8_t*>(const_cast<void*>(arv_buffer_get_data(buffer, &reported)));
  if (pixels == nullptr || w <= 0 || h <= 0) return;
  const auto id = static_cast<std::uint16_t>(arv_buffer_get_frame_id(buffer) & 0xFFFFu);
  std::uint64_t sequence;
  {
    std::lock_guard<std::mutex> lock(ctx->mutex);
    const std::uint64_t raw = ctx->unwrapper.Next(id);
    if (ctx->restart) {
      if (ctx->resume != 0) {
        ctx->offset = static_cast<std::int64_t>(ctx->resume - raw);
      } else {
        ctx->offset = ctx->any ? static_cast<std::int64_t>(ctx->last_sequence + 1 - raw) : 0;
      }
      ctx->restart = false;
    }
    sequence = raw + static_cast<std::uint64_t>(ctx->offset);
    ctx->last_sequence = sequence;
    ctx->any = true;
  }
  ctx->generator(ctx->camera, sequence, pixels, w, h,
                 static_cast<std::ptrdiff_t>(w) * BytesPerPixel(format), format);
  ctx->drawn++;
}

void SetSensor(ArvFakeCamera* fake, int width, int height) {
  arv_fake_camera_write_register(fake, ARV_FAKE_CAMERA_REGISTER_SENSOR_WIDTH, width);
  arv_fake_camera_write_register(fake, ARV_FAKE_CAMERA_REGISTER_SENSOR_HEIGHT, height);
  arv_fake_camera_write_register(fake, ARV_FAKE_CAMERA_REGISTER_WIDTH, width);
  arv_fake_camera_write_register(fake, ARV_FAKE_CAMERA_REGISTER_HEIGHT, height);
}

void Restart(FakeFillContext* ctx, std::uint64_t resume = 0) {
  std::lock_guard<std::mutex> lock(ctx->mutex);
  ctx->unwrapper = FrameIdUnwrapper();
  ctx->restart = true;
  ctx->resume = resume;
}

}  // namespace

bool FakeRigOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& what) {
    if (error) *error = "fake rig options: " + what;
    return false;
  };
  if (cameras < 1) return fail("cameras must be >= 1");
  if (width < 1 || height < 1 || width > 2048 || height > 2048) {
    return fail("width and height must be in 1..2048 (the fake's sensor limit)");
  }
  if (serial_prefix.empty() || serial_prefix.size() > 20) {
    return fail("serial_prefix must have 1..20 characters");
  }
  return true;
}

AravisFakeRig::AravisFakeRig(const FakeRigOptions& options, ImageGenerator generator)
    : options_(options) {
  options_.cameras = std::max(1, options_.cameras);
  present_.reset(new std::atomic<bool>[options_.cameras]);
  latest_.assign(options_.cameras, nullptr);
  for (int i = 0; i < options_.cameras; ++i) {
    present_[i] = true;
    auto ctx = std::make_unique<FakeFillContext>();
    ctx->camera = i;
    ctx->generator = generator;
    contexts_.push_back(std::move(ctx));
  }
}

AravisFakeRig::~AravisFakeRig() = default;

std::string AravisFakeRig::serial(int camera) const {
  return options_.serial_prefix + std::to_string(camera);
}

void AravisFakeRig::SetPresent(int camera, bool present) {
  if (camera >= 0 && camera < options_.cameras) present_[camera] = present;
}

bool AravisFakeRig::Present(int camera) const {
  return camera >= 0 && camera < options_.cameras && present_[camera].load();
}

ArvFakeCamera* AravisFakeRig::FakeCamera(int camera) {
  std::lock_guard<std::mutex> lock(mutex_);
  return camera >= 0 && camera < options_.cameras ? latest_[camera] : nullptr;
}

std::uint64_t AravisFakeRig::FramesDrawn(int camera) const {
  return camera >= 0 && camera < options_.cameras ? contexts_[camera]->drawn.load() : 0;
}

ArvCamera* AravisFakeRig::NewDevice(int camera, std::uint64_t resume_sequence,
                                    std::string* error) {
  const std::string sn = serial(camera);
  if (!present_[camera].load()) {
    *error = "fake camera " + sn + ": device not found (unplugged)";
    return nullptr;
  }
  GError* e = nullptr;
  ArvDevice* device = arv_fake_device_new(sn.c_str(), &e);
  if (device == nullptr) {
    *error = "fake camera " + sn + ": " + (e ? e->message : "arv_fake_device_new failed");
    g_clear_error(&e);
    return nullptr;
  }
  ArvFakeCamera* fake = arv_fake_device_get_fake_camera(ARV_FAKE_DEVICE(device));
  SetSensor(fake, options_.width, options_.height);
  Restart(contexts_[camera].get(), resume_sequence);
  arv_fake_camera_set_fill_pattern(fake, FillHook, contexts_[camera].get());
  ArvCamera* cam = arv_camera_new_with_device(device, &e);
  g_object_unref(device);  // the camera holds its own reference
  if (cam == nullptr) {
    *error = "fake camera " + sn + ": " + (e ? e->message : "arv_camera_new_with_device failed");
    g_clear_error(&e);
    return nullptr;
  }
  std::lock_guard<std::mutex> lock(mutex_);
  latest_[camera] = fake;
  return cam;
}

std::unique_ptr<AravisCamera> AravisFakeRig::MakeCamera(int camera, AravisCameraOptions options) {
  if (camera < 0 || camera >= options_.cameras) return nullptr;
  options.camera_index = camera;
  // The factory runs in the camera's own Open()/Reopen(): it may ask the camera where its
  // sequence resumes.
  auto owner = std::make_shared<AravisCamera*>(nullptr);
  auto cam = std::make_unique<AravisCamera>(
      serial(camera),
      [this, camera, owner](std::string* error) {
        return NewDevice(camera, *owner ? (*owner)->ResumeSequence() : 0, error);
      },
      options);
  *owner = cam.get();
  return cam;
}

GvFakeCamera::GvFakeCamera(std::string serial, int camera_index, ImageGenerator generator,
                           int width, int height)
    : serial_(std::move(serial)), width_(width), height_(height) {
  context_.camera = camera_index;
  context_.generator = std::move(generator);
}

GvFakeCamera::~GvFakeCamera() {
  Destroy();
  if (lock_fd_ >= 0) ::close(lock_fd_);  // releases the flock
}

Status GvFakeCamera::Create(double wait_s) {
  if (gv_ != nullptr) return Status::Ok();
  const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(wait_s);
  if (lock_fd_ < 0) {
    const char* path = "/tmp/mocap-gv-fake-127.0.0.1.lock";
    lock_fd_ = ::open(path, O_RDWR | O_CREAT | O_CLOEXEC, 0666);
    if (lock_fd_ < 0) {
      return Status::Error("GigE fake camera " + serial_ + ": cannot open " + path + ": " +
                           std::strerror(errno));
    }
    while (::flock(lock_fd_, LOCK_EX | LOCK_NB) != 0) {
      if (std::chrono::steady_clock::now() >= end) {
        ::close(lock_fd_);
        lock_fd_ = -1;
        return Status::Error("GigE fake camera " + serial_ +
                             ": another GigE fake holds 127.0.0.1 (" + path + ")");
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
  }
  for (;;) {
    gv_ = arv_gv_fake_camera_new("127.0.0.1", serial_.c_str());
    if (gv_ != nullptr && arv_gv_fake_camera_is_running(gv_)) break;
    if (gv_ != nullptr) g_object_unref(gv_);
    gv_ = nullptr;
    if (std::chrono::steady_clock::now() >= end) {
      return Status::Error("GigE fake camera " + serial_ +
                           ": cannot start on 127.0.0.1 (another GigE fake running there?)");
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  ArvFakeCamera* fake = arv_gv_fake_camera_get_fake_camera(gv_);
  SetSensor(fake, width_, height_);
  Restart(&context_);
  arv_fake_camera_set_fill_pattern(fake, FillHook, &context_);
  g_object_set(gv_, "gvsp-lost-ratio", loss_ratio_, nullptr);
  return Status::Ok();
}

void GvFakeCamera::Destroy() {
  if (gv_ == nullptr) return;
  g_object_unref(gv_);  // stops its GVCP and GVSP threads
  gv_ = nullptr;
}

void GvFakeCamera::SetPacketLossRatio(double ratio) {
  loss_ratio_ = ratio;
  if (gv_ != nullptr) g_object_set(gv_, "gvsp-lost-ratio", ratio, nullptr);
}

}  // namespace mocap::drivers
