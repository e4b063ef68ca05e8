#pragma once
// Renders a Gaussian set from a camera with the CPU rasterizer (PNG output: image::write_png).
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <vector>

#include "flexsplat/core/camera.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/export/gaussian_set.hpp"
#include "flexsplat/raster/render.hpp"

namespace flexsplat {
inline namespace v0 {
namespace gaussians {

template <class T>
void render_set(const GaussianSet<T>& set, const Camera& cam, const raster::RenderOptions& options,
                raster::RenderWorkspace<T>& workspace, raster::RenderOutputs<T>& out) {
  raster::render_forward(set, raster::camera_view<T>(cam), options, workspace, out);
}

}  // namespace gaussians
}  // namespace v0
}  // namespace flexsplat
