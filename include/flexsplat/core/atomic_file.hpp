#pragma once
// The one way the library writes a file: into a temporary sibling "<name>.tmp<pid>_<n>", flushed to disk (fsync),
// then renamed over the name, whose folder entry is synced too. After a crash, kill or power loss the name holds the
// old file or the complete new one, never a partial one; remove_stale_temp_files clears the temporaries of writers
// that died. Usage:
//   write_file_atomic(path, "glb writer", bytes);                                     // a buffer
//   write_file_atomic(path, "safetensors writer", [&](std::ostream& out) { ... });    // streamed
#include <atomic>
#include <cerrno>
#include <concepts>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <ostream>
#include <string>
#include <string_view>

#include <fcntl.h>
#include <signal.h>
#include <unistd.h>

#include "flexsplat/core/error.hpp"

namespace flexsplat {
inline namespace v0 {

// "<path>.tmp<pid>_<n>": unique within and across processes; the pid lets remove_stale_temp_files find dead writers.
inline std::filesystem::path temp_sibling(const std::filesystem::path& path) {
  static std::atomic<unsigned> counter{0};
  return path.string() + ".tmp" + std::to_string(::getpid()) + "_" + std::to_string(counter.fetch_add(1));
}

// fill(std::ostream&) writes the content; `who` starts every error message, which names the file and the reason.
template <class Fill>
  requires std::invocable<Fill&, std::ostream&>
void write_file_atomic(const std::filesystem::path& path, const char* who, Fill&& fill) {
  const std::filesystem::path tmp = temp_sibling(path);
  auto discard = [&] {
    std::error_code ignored;
    std::filesystem::remove(tmp, ignored);
  };
  {
    std::ofstream out(tmp, std::ios::binary | std::ios::trunc);
    require(static_cast<bool>(out), who, ": cannot create '", tmp.string(), "' next to '", path.string(), "'");
    try {
      fill(static_cast<std::ostream&>(out));
    } catch (...) {
      out.close();
      discard();
      throw;
    }
    out.flush();
    if (!out) {
      const int err = errno;  // the failed write()'s reason (no space, file too large, I/O error)
      out.close();
      discard();
      fail(who, ": writing '", tmp.string(), "' failed: ", std::strerror(err));
    }
  }
  // The data reaches the disk before the rename publishes it (and a write error the kernel reports late surfaces here).
  {
    const int fd = ::open(tmp.c_str(), O_RDONLY | O_CLOEXEC);
    const int synced = fd >= 0 ? ::fsync(fd) : -1;
    const int err = errno;
    if (fd >= 0) ::close(fd);
    if (synced != 0) {
      discard();
      fail(who, ": cannot flush '", tmp.string(), "' to disk: ", std::strerror(err));
    }
  }
  std::error_code ec;
  std::filesystem::rename(tmp, path, ec);
  if (ec) {
    discard();
    fail(who, ": cannot rename '", tmp.string(), "' to '", path.string(), "': ", ec.message());
  }
  // The rename is durable once the folder's entry is (best effort: some file systems refuse fsync on a folder).
  const std::filesystem::path parent = path.has_parent_path() ? path.parent_path() : std::filesystem::path(".");
  if (const int dir = ::open(parent.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC); dir >= 0) {
    (void)::fsync(dir);
    ::close(dir);
  }
}

inline void write_file_atomic(const std::filesystem::path& path, const char* who, std::string_view bytes) {
  write_file_atomic(path, who, [&](std::ostream& out) { out.write(bytes.data(), static_cast<std::streamsize>(bytes.size())); });
}

// Removes "<file>.tmp<pid>_<n>" next to `path` left by a writer that died mid-write (SIGKILL, power loss): only when
// process <pid> no longer exists, so a concurrent writer's file is never touched. Without this, a run killed during
// checkpoint writes keeps one model-sized file per kill.
inline void remove_stale_temp_files(const std::filesystem::path& path) {
  namespace fs = std::filesystem;
  const fs::path dir = path.has_parent_path() ? path.parent_path() : fs::path(".");
  const std::string prefix = path.filename().string() + ".tmp";
  std::error_code ec;
  for (fs::directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec)) {
    const std::string name = it->path().filename().string();
    if (name.size() <= prefix.size() || name.compare(0, prefix.size(), prefix) != 0) continue;
    const std::string rest = name.substr(prefix.size());
    const std::size_t sep = rest.find('_');
    if (sep == 0 || sep == std::string::npos || rest.find_first_not_of("0123456789_") != std::string::npos) continue;
    const long pid = std::strtol(rest.substr(0, sep).c_str(), nullptr, 10);
    if (pid <= 0 || pid == static_cast<long>(::getpid())) continue;
    if (::kill(static_cast<pid_t>(pid), 0) == 0 || errno != ESRCH) continue;
    std::error_code ignored;
    fs::remove(it->path(), ignored);
  }
}

}  // namespace v0
}  // namespace flexsplat
