#pragma once
// Renders a Gaussian set from a camera with the CPU rasterizer (PNG output: image::write_png).
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <vector>

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

}  // namespace gaussians
}  // namespace v0
}  // namespace flexsplat
