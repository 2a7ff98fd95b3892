#include "daemon/export_path.h"

#include <fcntl.h>
#include <linux/openat2.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <cerrno>
#include <climits>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <utility>

namespace mocap::daemon {
namespace {

namespace fs = std::filesystem;

// `path` equals `dir` or lies beneath it (both normal and absolute).
bool Beneath(const fs::path& path, const fs::path& dir) {
  auto p = path.begin();
  for (auto d = dir.begin(); d != dir.end(); ++d, ++p) {
    if (d->empty()) continue;  // the trailing "" of "a/b/"
    if (p == path.end() || *p != *d) return false;
  }
  return true;
}

fs::path Normal(const std::string& path) {
  fs::path p = fs::path(path).lexically_normal();
  if (!p.empty() && !p.has_filename()) p = p.parent_path();  // "a/b/" -> "a/b"
  return p;
}

class Fd {
 public:
  explicit Fd(int fd) : fd_(fd) {}
  ~Fd() {
    if (fd_ >= 0) close(fd_);
  }
  Fd(const Fd&) = delete;
  Fd& operator=(const Fd&) = delete;
  int get() const { return fd_; }
  int release() { return std::exchange(fd_, -1); }

 private:
  int fd_;
};

constexpr int kOpenFlags = O_WRONLY | O_CREAT | O_CLOEXEC | O_NOCTTY;
constexpr mode_t kMode = 0640;

// openat2 beneath `dir_fd`; -1 with errno set (ENOSYS where the kernel lacks it).
int OpenBeneath(int dir_fd, const std::string& relative) {
  open_how how{};
  how.flags = kOpenFlags;
  how.mode = kMode;
  how.resolve = RESOLVE_BENEATH | RESOLVE_NO_SYMLINKS | RESOLVE_NO_MAGICLINKS;
  return static_cast<int>(syscall(SYS_openat2, dir_fd, relative.c_str(), &how, sizeof how));
}

}  // namespace

Status OpenExportFile(const std::string& requested, const std::vector<std::string>& allowed_dirs,
                      const std::string& state_dir, ExportFile* out) {
  *out = ExportFile();
  std::string allowed_list;
  for (const std::string& d : allowed_dirs) allowed_list += (allowed_list.empty() ? "" : ", ") + d;
  auto refuse = [&](const std::string& why) {
    out->forbidden = true;
    return Status::Error("export path '" + requested + "': " + why + " (exports go beneath " +
                         (allowed_list.empty() ? std::string("no directory") : allowed_list) +
                         ": [storage] export_dirs)");
  };
  if (requested.empty() || requested[0] != '/') return refuse("not an absolute path");
  if (requested.find('\0') != std::string::npos) return refuse("holds a NUL byte");
  const fs::path path = Normal(requested);
  out->path = path.string();
  const fs::path state = Normal(state_dir);
  if (!state.empty() && Beneath(path, state) && !Beneath(path, state / "exports"))
    return refuse("inside the daemon's storage " + state.string());

  for (const std::string& allowed : allowed_dirs) {
    const fs::path dir = Normal(allowed);
    if (dir.empty() || !dir.is_absolute() || !Beneath(path, dir)) continue;
    const fs::path relative = path.lexically_relative(dir);
    if (relative.empty() || relative == ".") return refuse("is the export directory itself");
    Fd dir_fd(open(dir.c_str(), O_PATH | O_DIRECTORY | O_CLOEXEC));
    if (dir_fd.get() < 0)
      return Status::Error("export path '" + requested + "': its export directory " +
                           dir.string() + ": " + std::strerror(errno));
    int fd = OpenBeneath(dir_fd.get(), relative.string());
    if (fd < 0 && errno == ENOSYS) {
      // No openat2: the directory resolved by the C library must still lie beneath, and the
      // file itself must not be a link.
      char resolved[PATH_MAX], resolved_dir[PATH_MAX];
      if (!realpath(path.parent_path().c_str(), resolved) || !realpath(dir.c_str(), resolved_dir))
        return Status::Error("export path '" + requested + "': " + std::strerror(errno));
      if (!Beneath(fs::path(resolved), fs::path(resolved_dir)))
        return refuse("its directory resolves to " + std::string(resolved));
      fd = open((fs::path(resolved) / path.filename()).c_str(), kOpenFlags | O_NOFOLLOW, kMode);
    }
    if (fd < 0) {
      const int e = errno;
      // ELOOP: a symlink on the way (or the file is one); EXDEV: ".." or an absolute link out.
      if (e == ELOOP || e == EXDEV) return refuse("goes through a symlink or out of its directory");
      return Status::Error("export path '" + requested + "': cannot create: " + std::strerror(e));
    }
    out->fd = fd;
    return Status::Ok();
  }
  return refuse("outside the allowed directories");
}

Status CopyIntoExportFile(const std::string& staged, int fd, const std::string& target) {
  Fd in(open(staged.c_str(), O_RDONLY | O_CLOEXEC));
  if (in.get() < 0) return Status::Error(staged + ": cannot read the staged export: " + std::strerror(errno));
  if (lseek(fd, 0, SEEK_SET) < 0) return Status::Error(target + ": " + std::strerror(errno));
  off_t copied = 0;
  char buffer[1 << 16];
  for (;;) {
    const ssize_t n = read(in.get(), buffer, sizeof buffer);
    if (n < 0 && errno == EINTR) continue;
    if (n < 0) return Status::Error(staged + ": " + std::strerror(errno));
    if (n == 0) break;
    for (ssize_t done = 0; done < n;) {
      const ssize_t w = write(fd, buffer + done, static_cast<std::size_t>(n - done));
      if (w < 0 && errno == EINTR) continue;
      if (w < 0) return Status::Error(target + ": write error: " + std::strerror(errno));
      done += w;
    }
    copied += n;
  }
  if (ftruncate(fd, copied) != 0) return Status::Error(target + ": " + std::strerror(errno));
  return Status::Ok();
}

}  // namespace mocap::daemon
