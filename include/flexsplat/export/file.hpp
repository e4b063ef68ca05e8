#pragma once
// Reading and writing Gaussian sets by file extension (.glb or .ply).
#include <algorithm>
#include <cctype>
#include <filesystem>
#include <string>
#include <vector>

#include "flexsplat/core/camera.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/export/gaussian_set.hpp"
#include "flexsplat/export/gltf.hpp"
#include "flexsplat/export/ply.hpp"

namespace flexsplat {
inline namespace v0 {
namespace gaussians {

enum class FileFormat { Glb, Ply };

inline FileFormat format_of(const std::filesystem::path& path) {
  std::string ext = path.extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return char(std::tolower(c)); });
  if (ext == ".glb") return FileFormat::Glb;
  if (ext == ".ply") return FileFormat::Ply;
  fail("'", path.string(), "': unknown Gaussian file extension '", ext, "' (expected .glb or .ply)");
}

// A .glb's cameras go to *cameras when it is given (a .ply has none: *cameras is cleared).
inline GaussianSet<float> read_gaussians(const std::filesystem::path& path, std::vector<Camera>* cameras = nullptr) {
  if (format_of(path) == FileFormat::Glb) return gltf::read_glb(path, cameras);
  if (cameras) cameras->clear();
  return ply::read_ply(path);
}

// Returns what export repaired (clamped opacities, renormalised quaternions) and the file size. options.cameras are
// written to a .glb; a .ply cannot hold cameras, so asking for them there is an error.
template <class T>
gltf::WriteReport write_gaussians(const GaussianSet<T>& set, const std::filesystem::path& path,
                                  const gltf::WriteOptions& options = {}) {
  if (format_of(path) == FileFormat::Glb) return gltf::write_glb(set, path, options);
  require(options.cameras.empty(), "'", path.string(), "': a .ply file cannot store the ", options.cameras.size(),
          " cameras given (write a .glb)");
  const ply::WriteReport r = ply::write_ply(set, path);
  return gltf::WriteReport{r.repairs, r.bytes};
}

}  // namespace gaussians
}  // namespace v0
}  // namespace flexsplat
