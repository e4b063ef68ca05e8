#pragma once
// Cameras at the boundary between VGGT and the rest of the library. VGGT puts pixel u at the integer coordinate u,
// the decoder and rasterizer at u + 0.5 (docs/conventions.md), so the predicted principal point moves by half a
// pixel: the ray through depth sample u stays the same. Both directions have their adjoints.
#include "flexsplat/core/error.hpp"
#include "flexsplat/raster/render.hpp"

namespace flexsplat {
inline namespace v0 {
namespace model {

// K [V, 3, 3] in VGGT's integer-pixel convention -> the library's pixel-centre convention.
template <class T>
void intrinsics_from_vggt(T* K, const T* K_vggt, index_t views) {
  for (index_t v = 0; v < views; ++v) {
    for (int i = 0; i < 9; ++i) K[9 * v + i] = K_vggt[9 * v + i];
    K[9 * v + 2] += T(0.5);
    K[9 * v + 5] += T(0.5);
  }
}

// The shift is constant: the gradient passes through unchanged (added into dK_vggt).
template <class T>
void intrinsics_from_vggt_backward(T* dK_vggt, const T* dK, index_t views) {
  for (index_t i = 0; i < 9 * views; ++i) dK_vggt[i] += dK[i];
}

// A rasterizer camera from row-major K [3, 3] and world-to-camera [3, 4] (pixel-centre convention).
template <class T>
raster::Camera<T> render_camera(const T* K, const T* world_to_camera, int width, int height) {
  require(width >= 1 && height >= 1, "render camera: image size ", width, " x ", height, " is empty");
  raster::Camera<T> c;
  for (int i = 0; i < 12; ++i) c.world_to_camera[static_cast<std::size_t>(i)] = world_to_camera[i];
  c.world_to_camera[12] = 0, c.world_to_camera[13] = 0, c.world_to_camera[14] = 0, c.world_to_camera[15] = 1;
  c.fx = K[0], c.fy = K[4], c.cx = K[2], c.cy = K[5];
  c.width = width, c.height = height;
  return c;
}

// Adds the rasterizer's camera gradient into dK [3, 3] (fx, fy, cx, cy entries) and d_world_to_camera [3, 4]; either
// may be null.
template <class T>
void render_camera_backward(T* dK, T* d_world_to_camera, const raster::CameraGrad<T>& g) {
  if (d_world_to_camera)
    for (int i = 0; i < 12; ++i) d_world_to_camera[i] += g.world_to_camera[static_cast<std::size_t>(i)];
  if (dK) dK[0] += g.fx, dK[4] += g.fy, dK[2] += g.cx, dK[5] += g.cy;
}

}  // namespace model
}  // namespace v0
}  // namespace flexsplat
