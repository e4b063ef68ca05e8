#pragma once
// Renders a Gaussian set from one of its cameras with the CPU rasterizer, and writes 8-bit PNGs.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <vector>

#include <stb_image_write.h>

#include "flexsplat/core/error.hpp"
#include "flexsplat/export/gaussian_set.hpp"
#include "flexsplat/raster/render.hpp"

namespace flexsplat {
inline namespace v0 {
namespace gaussians {

template <class T>
raster::Camera<T> raster_camera(const Camera& cam) {
  raster::Camera<T> rc;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 4; ++c) rc.world_to_camera[r * 4 + c] = T(cam.w2c[r * 4 + c]);
  rc.world_to_camera[12] = rc.world_to_camera[13] = rc.world_to_camera[14] = T(0);
  rc.world_to_camera[15] = T(1);
  rc.fx = T(cam.K[0]);
  rc.fy = T(cam.K[4]);
  rc.cx = T(cam.K[2]);
  rc.cy = T(cam.K[5]);
  rc.width = cam.width;
  rc.height = cam.height;
  return rc;
}

template <class T>
void render_set(const GaussianSet<T>& set, const Camera& cam, const raster::RenderOptions& options,
                raster::RenderWorkspace<T>& workspace, raster::RenderOutputs<T>& out) {
  raster::render_forward(set, raster_camera<T>(cam), options, workspace, out);
}

// Quantises an [H, W, 3] image in [0, 1] to 8 bits (round to nearest, clamped); with alpha [H, W], writes RGBA.
template <class T>
void write_png(const std::filesystem::path& path, const Tensor<T, 3>& image, const Tensor<T, 2>* alpha = nullptr) {
  const index_t h = image.shape(0), w = image.shape(1);
  require(image.shape(2) == 3, "write_png: image must be [H, W, 3], got ", shape_string(image.shape()));
  require(!alpha || alpha->shape() == Shape<2>{h, w}, "write_png: alpha must be [", h, ", ", w, "]");
  const int channels = alpha ? 4 : 3;
  std::vector<std::uint8_t> pixels(static_cast<std::size_t>(h * w * channels));
  auto to8 = [](double v) { return static_cast<std::uint8_t>(std::lround(std::clamp(v, 0.0, 1.0) * 255.0)); };
  for (index_t y = 0; y < h; ++y)
    for (index_t x = 0; x < w; ++x) {
      std::uint8_t* p = pixels.data() + (y * w + x) * channels;
      for (int c = 0; c < 3; ++c) p[c] = to8(double(image(y, x, c)));
      if (alpha) p[3] = to8(double((*alpha)(y, x)));
    }
  const int ok = stbi_write_png(path.string().c_str(), int(w), int(h), channels, pixels.data(), int(w * channels));
  require(ok != 0, "write_png: cannot write '", path.string(), "'");
}

}  // namespace gaussians
}  // namespace v0
}  // namespace flexsplat
