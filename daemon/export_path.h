// Where the daemon's `export` may write: a file beneath one of the directories the config allows
// (`[storage] export_dirs`), never through a symlink, never into the daemon's own storage.
//
// Why this is needed: mocapd writes exports as its own user, which owns the database and may
// write where a member of the control group may not (the state directory, whatever else the
// unit grants). Without a bound, `export --out /var/lib/mocapd/mocapd.sqlite` would let a
// client destroy the sessions a lab cannot repeat, and `../` or a symlink planted in a shared
// export directory would send the daemon's write anywhere its user can reach.
//
// How the bound is kept, in two layers:
//   1. lexically: the requested path, made normal ("a/./b/../c" -> "a/c"), must lie beneath an
//      allowed directory (itself normal and absolute), and not in the state directory unless
//      beneath its `exports/` folder. This refuses absolute paths elsewhere and `..` that climb
//      out, and names the allowed directories in the error.
//   2. by the kernel, at open: openat2(2) from the allowed directory with RESOLVE_BENEATH |
//      RESOLVE_NO_SYMLINKS | RESOLVE_NO_MAGICLINKS, so no component of what lies below the
//      allowed directory may be a symlink (a planted link refuses with ELOOP) and no `..` may
//      leave it, checked atomically with the open -- no window between a check and the write
//      for someone to swap a directory for a link. (The allowed directory itself is the admin's
//      and may be a symlink.) Kernels before 5.6 lack openat2: there the file is opened with
//      O_NOFOLLOW after realpath(3) of its directory is checked to stay beneath the allowed
//      one, which refuses the same inputs but leaves that window open.
//
// The file is opened without truncating it: the export is written to a staging file in the
// state directory first and copied in only when it succeeded (CopyIntoExportFile), so a failed
// export leaves an existing file as it was.
#pragma once
#include <string>
#include <vector>

#include "model/status.h"

namespace mocap::daemon {

struct ExportFile {
  int fd = -1;       // open for writing (not truncated); the caller closes it
  std::string path;  // the requested path, made normal
  // The request was refused because the path leaves the allowed directories (or goes through a
  // symlink, or into the storage): the protocol's `forbidden`. False with an error: the path is
  // allowed but could not be opened (no such directory, permissions): `failed`.
  bool forbidden = false;
};

// Opens `requested` (absolute) for writing if it lies beneath one of `allowed_dirs` (absolute)
// and outside `state_dir` (except `state_dir`/exports). The error names the path and what was
// wrong with it; `out->forbidden` says which kind of error it is.
Status OpenExportFile(const std::string& requested, const std::vector<std::string>& allowed_dirs,
                      const std::string& state_dir, ExportFile* out);

// Copies the file at `staged` into `fd` (from its start) and cuts `fd` at the copied length.
// Errors name `target` (the path the client asked for).
Status CopyIntoExportFile(const std::string& staged, int fd, const std::string& target);

}  // namespace mocap::daemon
