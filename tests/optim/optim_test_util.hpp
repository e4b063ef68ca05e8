#pragma once
#include <unistd.h>

#include <atomic>
#include <filesystem>
#include <string>

#include "flexsplat/decoder/model.hpp"
#include "flexsplat/geometry/config.hpp"
#include "flexsplat/io/safetensors.hpp"

namespace train_test {

inline std::string vggt_bundle_path() { return std::string(FLEXSPLAT_SHARED_DIR) + "/reference/vggt_tiny_1234.safetensors"; }

inline flexsplat::geometry::VggtConfig tiny_vggt_config() {
  return flexsplat::geometry::vggt_config_from_json(
      flexsplat::safetensors::File::open(vggt_bundle_path()).metadata("config"));
}

inline flexsplat::decoder::ModelConfig tiny_model_config() {
  flexsplat::decoder::ModelConfig cfg;
  cfg.unet = {3, 2, 1};
  cfg.fusion = {3, 2, 3};
  auto& d = cfg.decoder;
  d.dim = 8, d.ffn = 12, d.heads = 2, d.layers = 2, d.points = 2, d.max_views = 2, d.value_dim = 3, d.max_queries = 7;
  return cfg;
}

// A unique temporary path removed when the object goes out of scope.
struct TempPath {
  std::filesystem::path path;
  explicit TempPath(const std::string& stem) {
    static std::atomic<int> counter{0};
    path = std::filesystem::temp_directory_path() /
           (stem + "_" + std::to_string(::getpid()) + "_" + std::to_string(counter++) + ".safetensors");
  }
  ~TempPath() {
    std::error_code ec;
    std::filesystem::remove(path, ec);
  }
};

}  // namespace train_test
