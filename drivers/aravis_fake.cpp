#include "drivers/aravis_fake.h"

#include <arv.h>

#include <fcntl.h>
#include <sys/file.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <climits>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <iterator>
#include <mutex>
#include <thread>

namespace mocap::drivers {
namespace {

// FakeRigOptions::ptp_features: the registers behind the features added to Aravis's fake XML
// (free addresses of its 64 KiB register space; the bootstrap and Aravis's own end below 0x1000).
constexpr guint32 kPtpAvailableReg = 0x9000;        // written by the rig: 1 = the features exist
constexpr guint32 kPtpEnableReg = 0x9004;
constexpr guint32 kPtpStateReg = 0x9008;            // PtpStatus's value while enabled
constexpr guint32 kPtpOffsetReg = 0x900c;
constexpr guint32 kSyncFreeRunAvailableReg = 0x9014;
constexpr guint32 kSyncFreeRunEnableReg = 0x9018;
constexpr guint32 kSyncFreeRunStartLowReg = 0x901c;
constexpr guint32 kSyncFreeRunStartHighReg = 0x9020;
constexpr guint32 kSyncFreeRunUpdateReg = 0x9024;   // the command's register: 1 once executed
constexpr guint32 kSyncFreeRunRateReg = 0x9028;     // a big-endian double
constexpr const char* kPtpStates[] = {"Initializing", "Faulty",  "Disabled",     "Listening", "PreMaster",
                                      "Master",       "Passive", "Uncalibrated", "Slave"};

// Spliced into Aravis's fake GenICam XML before </RegisterDescription>. Every feature is
// available only where the rig wrote 1 to its availability register, so a rig without
// ptp_features (and cameras listed in without_sync_free_run) lack them as before.
constexpr const char* kPtpFeaturesXml = R"XML(	<!-- mocap: IEEE 1588 (SFNC Ptp*) and Basler's Synchronous Free Run (SyncFreeRunTimer*),
	     drivers/aravis_fake.h. -->
	<IntReg Name="MocapPtpAvailableReg"><Address>0x9000</Address><Length>4</Length><AccessMode>RO</AccessMode><pPort>Device</pPort><Sign>Unsigned</Sign><Endianess>BigEndian</Endianess></IntReg>
	<IntReg Name="MocapSyncFreeRunAvailableReg"><Address>0x9014</Address><Length>4</Length><AccessMode>RO</AccessMode><pPort>Device</pPort><Sign>Unsigned</Sign><Endianess>BigEndian</Endianess></IntReg>
	<Boolean Name="PtpEnable" NameSpace="Standard"><pIsAvailable>MocapPtpAvailableReg</pIsAvailable><pValue>MocapPtpEnableReg</pValue><OnValue>1</OnValue><OffValue>0</OffValue></Boolean>
	<IntReg Name="MocapPtpEnableReg"><Address>0x9004</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort><Sign>Unsigned</Sign><Endianess>BigEndian</Endianess></IntReg>
	<IntReg Name="MocapPtpStateReg"><Address>0x9008</Address><Length>4</Length><AccessMode>RO</AccessMode><pPort>Device</pPort><Sign>Unsigned</Sign><Endianess>BigEndian</Endianess></IntReg>
	<IntSwissKnife Name="MocapPtpStatusValue"><pVariable Name="EN">MocapPtpEnableReg</pVariable><pVariable Name="ST">MocapPtpStateReg</pVariable><Formula>EN ? ST : 2</Formula></IntSwissKnife>
	<Enumeration Name="PtpStatus" NameSpace="Standard">
		<pIsAvailable>MocapPtpAvailableReg</pIsAvailable>
		<EnumEntry Name="Initializing"><Value>0</Value></EnumEntry>
		<EnumEntry Name="Faulty"><Value>1</Value></EnumEntry>
		<EnumEntry Name="Disabled"><Value>2</Value></EnumEntry>
		<EnumEntry Name="Listening"><Value>3</Value></EnumEntry>
		<EnumEntry Name="PreMaster"><Value>4</Value></EnumEntry>
		<EnumEntry Name="Master"><Value>5</Value></EnumEntry>
		<EnumEntry Name="Passive"><Value>6</Value></EnumEntry>
		<EnumEntry Name="Uncalibrated"><Value>7</Value></EnumEntry>
		<EnumEntry Name="Slave"><Value>8</Value></EnumEntry>
		<pValue>MocapPtpStatusValue</pValue>
	</Enumeration>
	<Integer Name="PtpOffsetFromMaster" NameSpace="Standard"><pIsAvailable>MocapPtpAvailableReg</pIsAvailable><pValue>MocapPtpOffsetReg</pValue></Integer>
	<IntReg Name="MocapPtpOffsetReg"><Address>0x900c</Address><Length>4</Length><AccessMode>RO</AccessMode><pPort>Device</pPort><Sign>Signed</Sign><Endianess>BigEndian</Endianess></IntReg>
	<Command Name="PtpDataSetLatch" NameSpace="Standard"><pIsAvailable>MocapPtpAvailableReg</pIsAvailable><pValue>MocapPtpLatchReg</pValue><CommandValue>1</CommandValue></Command>
	<IntReg Name="MocapPtpLatchReg"><Address>0x9010</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort><Sign>Unsigned</Sign><Endianess>BigEndian</Endianess></IntReg>
	<Boolean Name="SyncFreeRunTimerEnable"><pIsAvailable>MocapSyncFreeRunAvailableReg</pIsAvailable><pValue>MocapSfrEnableReg</pValue><OnValue>1</OnValue><OffValue>0</OffValue></Boolean>
	<IntReg Name="MocapSfrEnableReg"><Address>0x9018</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort><Sign>Unsigned</Sign><Endianess>BigEndian</Endianess></IntReg>
	<Integer Name="SyncFreeRunTimerStartTimeLow"><pIsAvailable>MocapSyncFreeRunAvailableReg</pIsAvailable><pValue>MocapSfrStartLowReg</pValue></Integer>
	<IntReg Name="MocapSfrStartLowReg"><Address>0x901c</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort><Sign>Unsigned</Sign><Endianess>BigEndian</Endianess></IntReg>
	<Integer Name="SyncFreeRunTimerStartTimeHigh"><pIsAvailable>MocapSyncFreeRunAvailableReg</pIsAvailable><pValue>MocapSfrStartHighReg</pValue></Integer>
	<IntReg Name="MocapSfrStartHighReg"><Address>0x9020</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort><Sign>Unsigned</Sign><Endianess>BigEndian</Endianess></IntReg>
	<Command Name="SyncFreeRunTimerUpdate"><pIsAvailable>MocapSyncFreeRunAvailableReg</pIsAvailable><pValue>MocapSfrUpdateReg</pValue><CommandValue>1</CommandValue></Command>
	<IntReg Name="MocapSfrUpdateReg"><Address>0x9024</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort><Sign>Unsigned</Sign><Endianess>BigEndian</Endianess></IntReg>
	<Float Name="SyncFreeRunTimerTriggerRateAbs"><pIsAvailable>MocapSyncFreeRunAvailableReg</pIsAvailable><pValue>MocapSfrRateReg</pValue><Min>0.001</Min><Max>10000</Max><Unit>Hz</Unit></Float>
	<FloatReg Name="MocapSfrRateReg"><Address>0x9028</Address><Length>8</Length><AccessMode>RW</AccessMode><pPort>Device</pPort><Endianess>BigEndian</Endianess></FloatReg>
)XML";

// The extended XML, written once per process to a file Aravis reads at every new fake device
// (arv_set_fake_camera_genicam_filename: a process-wide setting; absent features are harmless).
void InstallPtpFeatures() {
  static std::once_flag once;
  static std::string path;
  std::call_once(once, [] {
    ArvFakeCamera* probe = arv_fake_camera_new("MOCAPXMLPROBE");
    size_t size = 0;
    const char* text = arv_fake_camera_get_genicam_xml(probe, &size);
    std::string xml(text ? text : "", text ? size : 0);
    g_object_unref(probe);
    const std::size_t at = xml.rfind("</RegisterDescription>");
    if (at == std::string::npos) return;  // an Aravis whose fake XML we do not know: left as is
    xml.insert(at, kPtpFeaturesXml);
    path = std::string(g_get_tmp_dir()) + "/mocap-fake-genicam-" +
           std::to_string(std::hash<std::string>{}(xml)) + ".xml";
    const std::string tmp = path + "." + std::to_string(::getpid());
    if (FILE* f = std::fopen(tmp.c_str(), "wb")) {
      const bool written = std::fwrite(xml.data(), 1, xml.size(), f) == xml.size();
      if (std::fclose(f) == 0 && written && std::rename(tmp.c_str(), path.c_str()) == 0)
        arv_set_fake_camera_genicam_filename(path.c_str());
    }
  });
}

guint32 Register(ArvFakeCamera* fake, guint32 address) {
  guint32 v = 0;
  arv_fake_camera_read_register(fake, address, &v);
  return v;
}

// The PTP camera's exposure (FakeRigOptions::ptp_features): the buffer's timestamp moved from
// the fake's wake-up on tick `tick` to the instant the camera exposes at, on its clock.
void ExposeAsPtpCamera(FakeFillContext* ctx, ArvFakeCamera* fake, std::uint64_t tick,
                       ArvBuffer* buffer) {
  const double period_ns = 1e9 / ctx->clock_sequence_rate_hz;
  const bool ptp = Register(fake, kPtpEnableReg) != 0;
  bool scheduled = false;
  std::uint64_t start_ns = 0;
  {
    std::lock_guard<std::mutex> lock(ctx->mutex);
    if (Register(fake, kSyncFreeRunUpdateReg) != 0) {  // executed: latch, and clear the command
      std::uint8_t be[8];
      arv_fake_camera_read_memory(fake, kSyncFreeRunRateReg, 8, be);
      std::uint64_t bits = 0;
      for (std::uint8_t b : be) bits = bits << 8 | b;
      std::memcpy(&ctx->sync_free_run_rate_hz, &bits, sizeof bits);
      ctx->sync_free_run_start_ns = static_cast<std::uint64_t>(Register(fake, kSyncFreeRunStartHighReg)) << 32 |
                                    Register(fake, kSyncFreeRunStartLowReg);
      ctx->sync_free_run_latched = true;
      arv_fake_camera_write_register(fake, kSyncFreeRunUpdateReg, 0);
    }
    scheduled = ptp && Register(fake, kSyncFreeRunEnableReg) != 0 && ctx->sync_free_run_latched &&
                std::abs(ctx->sync_free_run_rate_hz - ctx->clock_sequence_rate_hz) <=
                    1e-9 * ctx->clock_sequence_rate_hz;
    start_ns = ctx->sync_free_run_start_ns;
  }
  const double phase_ns =
      scheduled ? std::fmod(static_cast<double>(start_ns), period_ns)
                : std::fmod(std::fmod(static_cast<double>(ctx->own_offset_ns), period_ns) + period_ns, period_ns);
  const long double exposed = static_cast<long double>(tick) * period_ns + phase_ns;
  std::uint64_t stamp = static_cast<std::uint64_t>(std::ceil(exposed));
  if (!ptp) stamp += static_cast<std::uint64_t>(ctx->own_offset_ns);
  arv_buffer_set_timestamp(buffer, stamp);
}

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
  if (ctx->clock_sequence_rate_hz > 0) {
    sequence = SequenceOfTimestamp(arv_buffer_get_timestamp(buffer), ctx->clock_sequence_rate_hz);
    if (ArvFakeCamera* fake = ctx->fake.load(); ctx->ptp_features && fake != nullptr)
      ExposeAsPtpCamera(ctx, fake, sequence, buffer);
  } else {
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
  if (!(clock_sequence_rate_hz >= 0) || clock_sequence_rate_hz > 10000) {
    return fail("clock_sequence_rate_hz must be in [0, 10000]");
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
    ctx->clock_sequence_rate_hz = options_.clock_sequence_rate_hz;
    ctx->ptp_features = options_.ptp_features;
    ctx->sync_free_run_available =
        std::find(options_.without_sync_free_run.begin(), options_.without_sync_free_run.end(), i) ==
        options_.without_sync_free_run.end();
    if (i < static_cast<int>(options_.clock_offsets_ns.size())) ctx->own_offset_ns = options_.clock_offsets_ns[i];
    contexts_.push_back(std::move(ctx));
  }
  if (options_.ptp_features) InstallPtpFeatures();
}

Status AravisFakeRig::SetPtpState(int camera, const std::string& status,
                                  std::int64_t offset_from_master_ns) {
  if (camera < 0 || camera >= options_.cameras)
    return Status::Error("fake rig: no camera " + std::to_string(camera));
  const auto* at = std::find(std::begin(kPtpStates), std::end(kPtpStates), status);
  if (at == std::end(kPtpStates)) {
    std::string known;
    for (const char* k : kPtpStates) known += std::string(known.empty() ? "" : ", ") + k;
    return Status::Error("fake rig: PTP state '" + status + "' is none of " + known);
  }
  if (offset_from_master_ns < INT32_MIN || offset_from_master_ns > INT32_MAX)
    return Status::Error("fake rig: PTP offset " + std::to_string(offset_from_master_ns) +
                         " ns is outside the fake's 32-bit PtpOffsetFromMaster");
  FakeFillContext& ctx = *contexts_[camera];
  ctx.ptp_state = static_cast<std::uint32_t>(at - std::begin(kPtpStates));
  ctx.ptp_offset_ns = static_cast<std::int32_t>(offset_from_master_ns);
  std::lock_guard<std::mutex> lock(mutex_);
  if (ArvFakeCamera* fake = latest_[camera]) {
    arv_fake_camera_write_register(fake, kPtpStateReg, ctx.ptp_state);
    arv_fake_camera_write_register(fake, kPtpOffsetReg, static_cast<guint32>(ctx.ptp_offset_ns.load()));
  }
  return Status::Ok();
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
  FakeFillContext& ctx = *contexts_[camera];
  if (ctx.ptp_features) {
    arv_fake_camera_write_register(fake, kPtpAvailableReg, 1);
    arv_fake_camera_write_register(fake, kSyncFreeRunAvailableReg, ctx.sync_free_run_available ? 1 : 0);
    arv_fake_camera_write_register(fake, kPtpStateReg, ctx.ptp_state);
    arv_fake_camera_write_register(fake, kPtpOffsetReg, static_cast<guint32>(ctx.ptp_offset_ns.load()));
    std::lock_guard<std::mutex> lock(ctx.mutex);
    ctx.sync_free_run_latched = false;  // a new device: its timer is not set
  }
  ctx.fake = fake;
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
