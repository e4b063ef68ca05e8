#pragma once
// CPU tile rasterizer for 3D Gaussians: public entry points.
//
//   GaussianSet<T> set;           // core/gaussians.hpp: means [N,3], quats [N,4] (w,x,y,z, normalised inside),
//                                 // scales [N,3] (linear), opacities [N] in [0,1], sh [N,K,3], features [N,F] (optional)
//   View<T> cam{world_to_camera (4x4 row-major, OpenCV axes, bottom row 0 0 0 1), fx, fy, cx, cy, width, height};
//   RenderOptions opt;            // sh_degree (-1: from K), eps2d 0.3, near 0.01, far, antialiased, background
//   RenderWorkspace<T> ws;        // reuse across calls: buffers only grow
//   RenderOutputs<T> out;         // image [H,W,3], alpha [H,W], depth [H,W], n_contrib [H,W], features [H,W,F]
//   render_forward(set, cam, opt, ws, out);
//   GaussianSetGrad<T> grads = make_gaussian_grad(set);   // empty fields are skipped
//   ViewGrad<T> d_cam;            // optional
//   render_backward(set, cam, opt, ws, RenderOutputGrads<T>{d_image, d_alpha, d_depth, d_features}, grads, &d_cam);
//
// Semantics follow gsplat: pixel centres at +0.5, EWA projection with the 1.3x field-of-view clamp in the Jacobian,
// blur eps2d (antialiased mode multiplies opacity by sqrt(det(cov)/det(cov + eps2d I))), alpha = min(0.99,
// o exp(-sigma)) skipped below 1/255, front to back by camera depth of the mean, a pixel stops before the Gaussian
// that would bring its transmittance to 1e-4 or below, colour = SH + 0.5 clamped at 0, depth = sum w_i z_i
// (expected_depth divides by alpha), features blended with a zero background. render_backward ADDS gradients with
// respect to means, quats, scales, opacities, sh, features and the camera (world_to_camera and intrinsics); the
// workspace must still hold the state of the matching render_forward call.
#include <array>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <vector>

#include "flexsplat/core/camera.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/core/gaussians.hpp"
#include "flexsplat/core/inline.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/profile.hpp"
#include "flexsplat/core/simd.hpp"
#include "flexsplat/core/simd_dispatch.hpp"  // its lane overloads must be visible where the lane templates are defined
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/raster/constants.hpp"
#include "flexsplat/raster/intersect.hpp"
#include "flexsplat/raster/project.hpp"
#include "flexsplat/raster/projection_pass.hpp"
#include "flexsplat/raster/rasterize.hpp"
#include "flexsplat/raster/render_types.hpp"
#include "flexsplat/raster/sh.hpp"

namespace flexsplat {
inline namespace v0 {
namespace raster {

namespace detail {

template <class T, class Tensor_, std::size_t R>
void ensure_shape(Tensor_& t, const Shape<R>& shape) {
  if (t.shape() != shape) t.resize(shape);
}

}  // namespace detail

template <class T>
void render_forward(const GaussianSet<T>& in, const View<T>& camera, const RenderOptions& opt,
                    RenderWorkspace<T>& ws, RenderOutputs<T>& out) {
  const profile::Scope timed(profile::Op::raster_forward);
  using clock = std::chrono::steady_clock;
  auto stage_end = [last = clock::now()](double& ms) mutable {
    const auto now = clock::now();
    ms = std::chrono::duration<double, std::milli>(now - last).count();
    last = now;
  };
  const int degree = detail::validate_inputs(in, camera, opt);
  stage_end(ws.forward_times.validate);
  ThreadPool& pool = opt.pool ? *opt.pool : global_pool();
  const index_t n = in.means.shape(0);
  const int F = in.features.empty() ? 0 : int(in.features.shape(1));
  const int C = 4 + F;
  const index_t K = in.sh.shape(1);
  ws.n = n;
  ws.sh_degree = degree;
  ws.channel_count = C;
  ws.visible.assign(std::size_t(n), 0);
  ws.projections.resize(std::size_t(n));
  ws.channels.resize(std::size_t(n * C));
  ws.color_positive.resize(std::size_t(n * 3));
  ws.background.assign(std::size_t(C), T(0));
  for (int c = 0; c < 3; ++c) ws.background[c] = T(opt.background[c]);
  const ViewParams<T> cam = detail::view_params(camera);
  const ProjectSettings<T> set = detail::project_settings<T>(opt);
  const std::array<T, 3> campos = detail::camera_centre(cam);
  // One pass per Gaussian while its data is in cache: value checks, projection, colour, tiles, kernel record.
  const TileGrid grid(camera.width, camera.height);
  begin_intersections(n, grid, ws.tiles);
  begin_splats(n, C, ws.raster);
  T* records = ws.raster.splat_storage.data() + ws.raster.splat_offset;
  std::atomic<bool> value_failed{false};
  detail::GaussianPass<T> pass;
  pass.in = &in, pass.ws = &ws, pass.cam = cam, pass.set = set, pass.grid = grid, pass.skips = opt.skips;
  pass.degree = degree, pass.F = F, pass.C = C, pass.n = n, pass.K = K;
  pass.campos = campos;
  pass.records = records, pass.record_stride = ws.raster.splat_stride;
  const detail::BlendKernel kernel = detail::choose_blend_kernel<T>(opt.skips);
  if (kernel != detail::BlendKernel::scalar) {
    // Blocks of L Gaussians at fixed positions: the same lanes for any number of threads.
    const index_t L = detail::blend_lane_count<T>(kernel);
    parallel_for((n + L - 1) / L, [&](index_t begin, index_t end, int) {
      detail::with_exact_lanes<T>(kernel, [&](auto* lanes) {
        using V = std::remove_pointer_t<decltype(lanes)>;
        for (index_t b = begin; b < end; ++b)
          if (!detail::gaussian_block<V, T>(pass, b * L)) value_failed.store(true, std::memory_order_relaxed);
      });
    }, pool);
  } else {
    parallel_for(n, [&](index_t begin, index_t end, int) {
      for (index_t g = begin; g < end; ++g)
        if (!detail::gaussian_one(pass, g)) value_failed.store(true, std::memory_order_relaxed);
    }, pool);
  }
  if (value_failed.load()) {
    detail::validate_values(in);
    throw Error("render: an input value failed validation");  // validate_values names it first; not reached
  }
  stage_end(ws.forward_times.project);
  bin_tiles(n, ws.projections.data(), opt.skips, ws.tiles, pool);
  stage_end(ws.forward_times.intersect);
  const index_t pixels = index_t(camera.width) * camera.height;
  const index_t H = camera.height, W = camera.width;
  detail::ensure_shape<T>(out.image, Shape<3>{H, W, 3});
  detail::ensure_shape<T>(out.alpha, Shape<2>{H, W});
  detail::ensure_shape<T>(out.depth, Shape<2>{H, W});
  detail::ensure_shape<T>(out.n_contrib, Shape<2>{H, W});
  detail::ensure_shape<T>(out.features, Shape<3>{H, W, F});
  ws.blend_depth.resize(std::size_t(pixels));
  // The outputs are written as each tile row finishes, while it is in cache.
  T* const image = out.image.data();
  T* const alpha = out.alpha.data();
  T* const depth = out.depth.data();
  std::int32_t* const n_contrib = out.n_contrib.data();
  T* const features = out.features.data();
  T* const blend_depth = ws.blend_depth.data();
  const bool expected_depth = opt.expected_depth;
  rasterize_forward_rows(ws.tiles, C, ws.background.data(), opt.skips, ws.raster, ws.blend,
                         [&](std::int64_t p0, int count, const T* ch, int plane, const T* trans, const T* contributors) {
    // One simple loop per output so that each vectorizes.
    const T* red = ch;
    const T* green = ch + plane;
    const T* blue = ch + 2 * plane;
    const T* sum_depth = ch + 3 * plane;
    T* rgb = image + p0 * 3;
    for (int x = 0; x < count; ++x) rgb[3 * x] = red[x], rgb[3 * x + 1] = green[x], rgb[3 * x + 2] = blue[x];
    for (int x = 0; x < count; ++x) alpha[p0 + x] = T(1) - trans[x];
    std::copy_n(sum_depth, count, blend_depth + p0);
    if (expected_depth) {
      for (int x = 0; x < count; ++x) {
        const T a = T(1) - trans[x];
        depth[p0 + x] = a > T(0) ? sum_depth[x] / a : T(0);
      }
    } else {
      std::copy_n(sum_depth, count, depth + p0);
    }
    for (int x = 0; x < count; ++x) n_contrib[p0 + x] = std::int32_t(contributors[x]);
    for (int x = 0; x < count; ++x)
      for (int f = 0; f < F; ++f) features[(p0 + x) * F + f] = ch[(4 + f) * plane + x];
  }, pool);
  stage_end(ws.forward_times.rasterize);
}

template <class T>
void render_backward(const GaussianSet<T>& in, const View<T>& camera, const RenderOptions& opt,
                     RenderWorkspace<T>& ws, const RenderOutputGrads<T>& d_out, GaussianSetGrad<T>& grads,
                     ViewGrad<T>* d_camera = nullptr) {
  const profile::Scope timed(profile::Op::raster_backward);
  using clock = std::chrono::steady_clock;
  auto stage_end = [last = clock::now()](double& ms) mutable {
    const auto now = clock::now();
    ms = std::chrono::duration<double, std::milli>(now - last).count();
    last = now;
  };
  const index_t n = in.means.shape(0);
  const int C = ws.channel_count, F = C - 4;
  ThreadPool& pool = opt.pool ? *opt.pool : global_pool();
  require(ws.n == n && index_t(ws.blend.final_transmittance.size()) == index_t(camera.width) * camera.height,
          "render_backward: the workspace does not hold the forward pass of these inputs");
  const index_t H = camera.height, W = camera.width;
  auto check = [&](auto view, auto shape, const char* what) {
    require(view.empty() || (view.shape() == shape && view.is_contiguous()), "render_backward: ", what, " must be ",
            shape_string(shape), ", got ", shape_string(view.shape()));
  };
  check(d_out.image, Shape<3>{H, W, 3}, "d_image");
  check(d_out.alpha, Shape<2>{H, W}, "d_alpha");
  check(d_out.depth, Shape<2>{H, W}, "d_depth");
  check(d_out.features, Shape<3>{H, W, F}, "d_features");
  auto check_grad = [&](const auto& t, auto shape, const char* what) {
    require(t.empty() || t.shape() == shape, "render_backward: ", what, " must be ", shape_string(shape), " or empty, got ",
            shape_string(t.shape()));
  };
  check_grad(grads.means, Shape<2>{n, 3}, "grad means");
  check_grad(grads.quats, Shape<2>{n, 4}, "grad quats");
  check_grad(grads.scales, Shape<2>{n, 3}, "grad scales");
  check_grad(grads.opacities, Shape<1>{n}, "grad opacities");
  check_grad(grads.sh, in.sh.shape(), "grad sh");
  check_grad(grads.features, Shape<2>{n, F}, "grad features");
  stage_end(ws.backward_times.validate);
  // The blend reads the output cotangents per image row as it sets a tile up (no planar copy of them).
  const T* const final_transmittance = ws.blend.final_transmittance.data();
  const T* const blend_depth = ws.blend_depth.data();
  const bool expected_depth = opt.expected_depth;
  auto cotangent_rows = [&](std::int64_t p0, int count, T* planes, int plane, T* d_alpha) {
    for (int x = 0; x < count; ++x) {
      const std::int64_t p = p0 + x;
      for (int c = 0; c < C; ++c) planes[c * plane + x] = T(0);
      d_alpha[x] = d_out.alpha.empty() ? T(0) : d_out.alpha.data()[p];
      if (!d_out.image.empty())
        for (int c = 0; c < 3; ++c) planes[c * plane + x] = d_out.image.data()[p * 3 + c];
      if (!d_out.depth.empty()) {
        const T dd = d_out.depth.data()[p];
        if (expected_depth) {
          const T a = T(1) - final_transmittance[p];
          if (a > T(0)) {
            planes[3 * plane + x] = dd / a;
            d_alpha[x] -= dd * blend_depth[p] / (a * a);
          }
        } else {
          planes[3 * plane + x] = dd;
        }
      }
      if (!d_out.features.empty())
        for (int f = 0; f < F; ++f) planes[(4 + f) * plane + x] = d_out.features.data()[p * F + f];
    }
  };
  // The per-Gaussian pass sums each Gaussian's entry records as it reads them.
  rasterize_backward_rows(ws.tiles, ws.projections.data(), ws.channels.data(), C, ws.background.data(), ws.blend,
                          cotangent_rows, opt.skips, ws.raster, pool);
  stage_end(ws.backward_times.blend);
  const detail::GaussianBackwardPass<T> pass = detail::backward_pass(in, camera, opt, ws, grads);
  detail::gaussians_backward(pass, detail::choose_blend_kernel<T>(opt.skips), ws.camera_partials, pool);
  stage_end(ws.backward_times.gaussians);
  if (d_camera) {
    ViewGradParams<T> total;
    for (const auto& part : ws.camera_partials) total.add(part);
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) d_camera->world_to_camera[i * 4 + j] += total.R[i * 3 + j];
      d_camera->world_to_camera[i * 4 + 3] += total.t[i];
    }
    d_camera->fx += total.fx, d_camera->fy += total.fy;
    d_camera->cx += total.cx, d_camera->cy += total.cy;
  }
}

}  // namespace raster
}  // namespace v0
}  // namespace flexsplat
