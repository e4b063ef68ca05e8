#pragma once
// The rasterizer's public types (raster/render.hpp): the view, its gradient, the options, the outputs and their
// cotangents, the stage timings and the workspace render_forward and render_backward share.
#include <array>
#include <cstdint>
#include <vector>

#include "flexsplat/core/camera.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/raster/constants.hpp"
#include "flexsplat/raster/intersect.hpp"
#include "flexsplat/raster/project.hpp"
#include "flexsplat/raster/rasterize.hpp"

namespace flexsplat {
inline namespace v0 {
namespace raster {

template <class T>
struct View {
  std::array<T, 16> world_to_camera{1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};
  T fx = 1, fy = 1, cx = 0, cy = 0;
  int width = 0, height = 0;
};

template <class T>
struct ViewGrad {
  std::array<T, 16> world_to_camera{};  // bottom row stays zero
  T fx = 0, fy = 0, cx = 0, cy = 0;
};

// The view of row-major K [3, 3] and world-to-camera [3, 4] (core/camera.hpp's arrays, pixel-centre convention).
template <class T>
View<T> view_from_arrays(const T* K, const T* world_to_camera, int width, int height) {
  require(width >= 1 && height >= 1, "render view: image size ", width, " x ", height, " is empty");
  View<T> c;
  for (int i = 0; i < 12; ++i) c.world_to_camera[static_cast<std::size_t>(i)] = world_to_camera[i];
  c.world_to_camera[12] = 0, c.world_to_camera[13] = 0, c.world_to_camera[14] = 0, c.world_to_camera[15] = 1;
  c.fx = K[0], c.fy = K[4], c.cx = K[2], c.cy = K[5];
  c.width = width, c.height = height;
  return c;
}

// Adds a view's gradient into dK [3, 3] (fx, fy, cx, cy entries) and d_world_to_camera [3, 4]; either may be null.
template <class T>
void view_from_arrays_backward(T* dK, T* d_world_to_camera, const ViewGrad<T>& g) {
  if (d_world_to_camera)
    for (int i = 0; i < 12; ++i) d_world_to_camera[i] += g.world_to_camera[static_cast<std::size_t>(i)];
  if (dK) dK[0] += g.fx, dK[4] += g.fy, dK[2] += g.cx, dK[5] += g.cy;
}

// The view of a camera, its entries rounded to T.
template <class T>
View<T> camera_view(const Camera& cam) {
  T K[9], w2c[12];
  camera_arrays(cam, K, w2c);
  return view_from_arrays(K, w2c, cam.width, cam.height);
}

struct RenderOptions {
  int sh_degree = -1;  // -1: the degree that K = sh.shape(1) holds
  double eps2d = default_eps2d;
  double near_plane = default_near;
  double far_plane = default_far;
  bool antialiased = false;
  bool expected_depth = false;  // depth output = sum(w z) / alpha (0 where alpha is 0)
  std::array<double, 3> background{0, 0, 0};
  RasterSkips skips;
  ThreadPool* pool = nullptr;  // null: the global pool
};

template <class T>
struct RenderOutputs {
  Tensor<T, 3> image;
  Tensor<T, 2> alpha, depth;
  Tensor<std::int32_t, 2> n_contrib;
  Tensor<T, 3> features;
};

// Cotangents of the outputs; empty views count as zero.
template <class T>
struct RenderOutputGrads {
  TensorView<const T, 3> image;
  TensorView<const T, 2> alpha, depth;
  TensorView<const T, 3> features;
};

// Wall time of each stage of the last render_forward (milliseconds), for benchmarks and profiling; rasterize
// includes writing the outputs (the blend hands them each finished tile row).
struct ForwardStageTimes {
  double validate = 0, project = 0, intersect = 0, rasterize = 0;
};

// Wall time of each stage of the last render_backward (milliseconds): the checks, the blend's adjoint (reading the
// output cotangents and writing every entry's gradient record), and the per-Gaussian adjoints (summing each
// Gaussian's entry records; SH, projection).
struct BackwardStageTimes {
  double validate = 0, blend = 0, gaussians = 0;
};

template <class T>
struct RenderWorkspace {
  std::vector<std::uint8_t> visible;
  std::vector<Projection<T>> projections;
  std::vector<T> channels;            // [N, C]: r, g, b, z, features
  std::vector<std::uint8_t> color_positive;  // [N, 3]: SH + 0.5 > 0 (else clamped)
  TileIntersections tiles;
  BlendState<T> blend;
  RasterWorkspace<T> raster;
  std::vector<T> blend_depth;  // channel 3 per pixel
  std::vector<ViewGradParams<T>> camera_partials;
  std::vector<T> background;
  int sh_degree = 0, channel_count = 0;
  index_t n = 0;
  ForwardStageTimes forward_times;
  BackwardStageTimes backward_times;
};

}  // namespace raster
}  // namespace v0
}  // namespace flexsplat
