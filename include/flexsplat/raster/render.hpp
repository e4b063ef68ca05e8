#pragma once
// CPU tile rasterizer for 3D Gaussians: public entry points.
//
//   GaussianInputs<T> in{means [N,3], quats [N,4] (w,x,y,z, normalised inside), scales [N,3] (linear),
//                        opacities [N] in [0,1], sh [N,K,3] (K >= (degree+1)^2), features [N,F] (optional)};
//   Camera<T> cam{world_to_camera (4x4 row-major, OpenCV axes, bottom row 0 0 0 1), fx, fy, cx, cy, width, height};
//   RenderOptions opt;            // sh_degree (-1: from K), eps2d 0.3, near 0.01, far, antialiased, background
//   RenderWorkspace<T> ws;        // reuse across calls: buffers only grow
//   RenderOutputs<T> out;         // image [H,W,3], alpha [H,W], depth [H,W], n_contrib [H,W], features [H,W,F]
//   render_forward(in, cam, opt, ws, out);
//   GaussianGrads<T> grads{...views of the caller's gradient buffers (may be empty)..., &camera_grad};
//   render_backward(in, cam, opt, ws, RenderOutputGrads<T>{d_image, d_alpha, d_depth, d_features}, grads);
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

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/raster/constants.hpp"
#include "flexsplat/raster/intersect.hpp"
#include "flexsplat/raster/project.hpp"
#include "flexsplat/raster/rasterize.hpp"
#include "flexsplat/raster/sh.hpp"

namespace flexsplat {
inline namespace v0 {
namespace raster {

template <class T>
struct Camera {
  std::array<T, 16> world_to_camera{1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};
  T fx = 1, fy = 1, cx = 0, cy = 0;
  int width = 0, height = 0;
};

template <class T>
struct CameraGrad {
  std::array<T, 16> world_to_camera{};  // bottom row stays zero
  T fx = 0, fy = 0, cx = 0, cy = 0;
};

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
struct GaussianInputs {
  TensorView<const T, 2> means, quats, scales;
  TensorView<const T, 1> opacities;
  TensorView<const T, 3> sh;
  TensorView<const T, 2> features;  // optional [N, F]
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

// Where render_backward adds gradients; empty views and a null camera are skipped.
template <class T>
struct GaussianGrads {
  TensorView<T, 2> means, quats, scales;
  TensorView<T, 1> opacities;
  TensorView<T, 3> sh;
  TensorView<T, 2> features;
  CameraGrad<T>* camera = nullptr;
};

// Wall time of each stage of the last render_forward (milliseconds), for benchmarks and profiling.
struct ForwardStageTimes {
  double validate = 0, project = 0, intersect = 0, rasterize = 0, output = 0;
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
  std::vector<T> out_channels, d_out_channels, d_alpha, gaussian_grads;
  std::vector<CameraGradParams<T>> camera_partials;
  std::vector<T> background;
  int sh_degree = 0, channel_count = 0;
  index_t n = 0;
  ForwardStageTimes forward_times;
};

namespace detail {

template <class T>
CameraParams<T> camera_params(const Camera<T>& cam) {
  CameraParams<T> p;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) p.R[i * 3 + j] = cam.world_to_camera[i * 4 + j];
    p.t[i] = cam.world_to_camera[i * 4 + 3];
  }
  p.fx = cam.fx, p.fy = cam.fy, p.cx = cam.cx, p.cy = cam.cy;
  p.width = T(cam.width), p.height = T(cam.height);
  return p;
}

template <class T>
void require_finite(const T* data, index_t count, const char* what) {
  // Branch-free scan first (vectorises); the index is looked up only when something is wrong.
  bool all_finite = true;
  for (index_t i = 0; i < count; ++i) all_finite &= std::isfinite(data[i]);
  if (all_finite) return;
  for (index_t i = 0; i < count; ++i)
    require(std::isfinite(data[i]), "render: ", what, " has a non-finite value ", data[i], " at flat index ", i);
}

template <class T>
int validate_inputs(const GaussianInputs<T>& in, const Camera<T>& cam, const RenderOptions& opt) {
  const index_t n = in.means.shape(0);
  require(in.means.shape(1) == 3, "render: means must be [N, 3], got ", shape_string(in.means.shape()));
  require(in.quats.shape(0) == n && in.quats.shape(1) == 4, "render: quats must be [", n, ", 4], got ",
          shape_string(in.quats.shape()));
  require(in.scales.shape(0) == n && in.scales.shape(1) == 3, "render: scales must be [", n, ", 3], got ",
          shape_string(in.scales.shape()));
  require(in.opacities.shape(0) == n, "render: opacities must be [", n, "], got ", shape_string(in.opacities.shape()));
  require(in.sh.shape(0) == n && in.sh.shape(2) == 3 && in.sh.shape(1) >= 1, "render: sh must be [", n,
          ", K, 3] with K >= 1, got ", shape_string(in.sh.shape()));
  require(n < (index_t(1) << 31), "render: ", n, " Gaussians exceed the 2^31 limit");
  require(in.features.empty() || in.features.shape(0) == n, "render: features must be [", n, ", F], got ",
          shape_string(in.features.shape()));
  require(in.features.empty() || in.features.shape(1) <= 48, "render: at most 48 feature channels, got ",
          in.features.shape(1));
  for (auto* v : {&in.means, &in.quats, &in.scales})
    require(v->is_contiguous(), "render: Gaussian tensors must be contiguous");
  require(in.opacities.is_contiguous() && in.sh.is_contiguous() && (in.features.empty() || in.features.is_contiguous()),
          "render: Gaussian tensors must be contiguous");
  const index_t k = in.sh.shape(1);
  int degree = opt.sh_degree;
  if (degree < 0) {
    degree = 0;
    while (degree < max_sh_degree && sh_coeff_count(degree + 1) <= k) ++degree;
    require(sh_coeff_count(degree) == k, "render: sh has K = ", k,
            " coefficients, not (degree+1)^2 for a degree 0..3; pass RenderOptions::sh_degree");
  }
  require(degree <= max_sh_degree, "render: sh_degree ", degree, " is above the supported ", max_sh_degree);
  require(sh_coeff_count(degree) <= k, "render: sh_degree ", degree, " needs ", sh_coeff_count(degree),
          " coefficients but sh has K = ", k);
  require(cam.width > 0 && cam.height > 0 && cam.width <= 65536 && cam.height <= 65536, "render: image size ",
          cam.width, "x", cam.height, " is not in [1, 65536]");
  require_finite(cam.world_to_camera.data(), 16, "camera world_to_camera");
  const T intr[4] = {cam.fx, cam.fy, cam.cx, cam.cy};
  require_finite(intr, 4, "camera intrinsics (fx, fy, cx, cy)");
  require(cam.fx > T(0) && cam.fy > T(0), "render: focal lengths must be positive, got fx ", cam.fx, " fy ", cam.fy);
  const auto& w = cam.world_to_camera;
  require(w[12] == T(0) && w[13] == T(0) && w[14] == T(0) && w[15] == T(1),
          "render: world_to_camera bottom row must be (0, 0, 0, 1), got (", w[12], ", ", w[13], ", ", w[14], ", ",
          w[15], ")");
  require(opt.eps2d >= 0 && std::isfinite(opt.eps2d), "render: eps2d ", opt.eps2d, " must be finite and >= 0");
  require(opt.near_plane > 0 && opt.far_plane > opt.near_plane, "render: near ", opt.near_plane, " and far ",
          opt.far_plane, " must satisfy 0 < near < far");
  for (double b : opt.background) require(std::isfinite(b), "render: background has a non-finite value ", b);
  return degree;
}

// The per-value checks (finite inputs, quaternion directions, opacity range), throwing at the first bad value.
template <class T>
void validate_values(const GaussianInputs<T>& in) {
  const index_t n = in.means.shape(0);
  require_finite(in.means.data(), n * 3, "means");
  require_finite(in.quats.data(), n * 4, "quats");
  require_finite(in.scales.data(), n * 3, "scales");
  require_finite(in.opacities.data(), n, "opacities");
  require_finite(in.sh.data(), in.sh.size(), "sh");
  if (!in.features.empty()) require_finite(in.features.data(), in.features.size(), "features");
  for (index_t g = 0; g < n; ++g) {
    const T* q = in.quats.data() + g * 4;
    const T len2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3];
    require(len2 > T(0) && std::isfinite(len2), "render: quaternion ", g, " (", q[0], ", ", q[1], ", ", q[2], ", ",
            q[3], ") has no direction (zero or out of range length)");
    const T o = in.opacities.data()[g];
    require(o >= T(0) && o <= T(1), "render: opacity ", g, " is ", o, ", outside [0, 1]");
  }
}

// The same verdict as validate_values for Gaussian g alone, without a message (run inside the projection pass).
template <class T>
bool gaussian_values_ok(const GaussianInputs<T>& in, index_t g) {
  const index_t k = in.sh.shape(1), f = in.features.empty() ? 0 : in.features.shape(1);
  bool ok = true;
  auto scan = [&ok](const T* data, index_t count) {
    for (index_t i = 0; i < count; ++i) ok &= std::isfinite(data[i]);
  };
  scan(in.means.data() + g * 3, 3);
  scan(in.quats.data() + g * 4, 4);
  scan(in.scales.data() + g * 3, 3);
  scan(in.opacities.data() + g, 1);
  scan(in.sh.data() + g * k * 3, k * 3);
  if (f > 0) scan(in.features.data() + g * f, f);
  const T* q = in.quats.data() + g * 4;
  const T len2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3];
  const T o = in.opacities.data()[g];
  return ok && len2 > T(0) && std::isfinite(len2) && o >= T(0) && o <= T(1);
}

template <class T, class Tensor_, std::size_t R>
void ensure_shape(Tensor_& t, const Shape<R>& shape) {
  if (t.shape() != shape) t.resize(shape);
}

}  // namespace detail

template <class T>
void render_forward(const GaussianInputs<T>& in, const Camera<T>& camera, const RenderOptions& opt,
                    RenderWorkspace<T>& ws, RenderOutputs<T>& out) {
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
  const CameraParams<T> cam = detail::camera_params(camera);
  ProjectSettings<T> set;
  set.eps2d = T(opt.eps2d), set.near_plane = T(opt.near_plane), set.far_plane = T(opt.far_plane);
  set.antialiased = opt.antialiased;
  T campos[3];
  for (int i = 0; i < 3; ++i) campos[i] = -(cam.R[i] * cam.t[0] + cam.R[3 + i] * cam.t[1] + cam.R[6 + i] * cam.t[2]);
  // One pass per Gaussian while its data is in cache: value checks, projection, colour, tiles, kernel record.
  const TileGrid grid(camera.width, camera.height);
  begin_intersections(n, grid, ws.tiles);
  begin_splats(n, C, ws.raster);
  T* records = ws.raster.splat_storage.data() + ws.raster.splat_offset;
  std::atomic<bool> value_failed{false};
  parallel_for(n, [&](index_t begin, index_t end, int) {
    for (index_t g = begin; g < end; ++g) {
      if (!detail::gaussian_values_ok(in, g)) {
        value_failed.store(true, std::memory_order_relaxed);
        continue;
      }
      const T* m = in.means.data() + g * 3;
      Projection<T>& p = ws.projections[g];
      if (!project_forward_one(m, in.quats.data() + g * 4, in.scales.data() + g * 3, in.opacities.data()[g], cam, set, p))
        continue;
      ws.visible[g] = 1;
      T* ch = &ws.channels[g * C];
      const T dir[3] = {m[0] - campos[0], m[1] - campos[1], m[2] - campos[2]};
      T rgb[3];
      sh_forward(degree, 3, in.sh.data() + g * K * 3, dir, rgb);
      for (int c = 0; c < 3; ++c) {
        const T value = rgb[c] + T(sh_color_offset);
        ws.color_positive[g * 3 + c] = value > T(0);
        ch[c] = value > T(0) ? value : T(0);
      }
      ch[3] = p.z;
      for (int f = 0; f < F; ++f) ch[4 + f] = in.features.data()[g * F + f];
      const std::int64_t tiles = count_gaussian_tiles(p, grid, opt.skips, ws.tiles.gaussian_tiles[g]);
      ws.tiles.gaussian_counts[g] = tiles;
      if (tiles > 0) write_splat_record(p, ch, C, grid, records + g * ws.raster.splat_stride);
    }
  }, pool);
  if (value_failed.load()) {
    detail::validate_values(in);
    throw Error("render: an input value failed validation");  // validate_values names it first; not reached
  }
  stage_end(ws.forward_times.project);
  bin_tiles(n, ws.projections.data(), opt.skips, ws.tiles, pool);
  stage_end(ws.forward_times.intersect);
  const index_t pixels = index_t(camera.width) * camera.height;
  ws.out_channels.resize(std::size_t(pixels * C));
  rasterize_forward_prepared(ws.tiles, C, ws.background.data(), opt.skips, ws.raster, ws.out_channels.data(), ws.blend,
                             pool);
  stage_end(ws.forward_times.rasterize);
  const index_t H = camera.height, W = camera.width;
  detail::ensure_shape<T>(out.image, Shape<3>{H, W, 3});
  detail::ensure_shape<T>(out.alpha, Shape<2>{H, W});
  detail::ensure_shape<T>(out.depth, Shape<2>{H, W});
  detail::ensure_shape<T>(out.n_contrib, Shape<2>{H, W});
  detail::ensure_shape<T>(out.features, Shape<3>{H, W, F});
  parallel_for(pixels, [&](index_t begin, index_t end, int) {
    for (index_t p = begin; p < end; ++p) {
      const T* src = &ws.out_channels[p * C];
      for (int c = 0; c < 3; ++c) out.image.data()[p * 3 + c] = src[c];
      const T a = T(1) - ws.blend.final_transmittance[p];
      out.alpha.data()[p] = a;
      out.depth.data()[p] = opt.expected_depth ? (a > T(0) ? src[3] / a : T(0)) : src[3];
      out.n_contrib.data()[p] = ws.blend.n_contrib[p];
      for (int f = 0; f < F; ++f) out.features.data()[p * F + f] = src[4 + f];
    }
  }, pool);
  stage_end(ws.forward_times.output);
}

template <class T>
void render_backward(const GaussianInputs<T>& in, const Camera<T>& camera, const RenderOptions& opt,
                     RenderWorkspace<T>& ws, const RenderOutputGrads<T>& d_out, GaussianGrads<T>& grads) {
  const index_t n = in.means.shape(0);
  const int C = ws.channel_count, F = C - 4;
  ThreadPool& pool = opt.pool ? *opt.pool : global_pool();
  require(ws.n == n && index_t(ws.blend.final_transmittance.size()) == index_t(camera.width) * camera.height,
          "render_backward: the workspace does not hold the forward pass of these inputs");
  const index_t H = camera.height, W = camera.width, pixels = H * W;
  auto check = [&](auto view, auto shape, const char* what) {
    require(view.empty() || (view.shape() == shape && view.is_contiguous()), "render_backward: ", what, " must be ",
            shape_string(shape), ", got ", shape_string(view.shape()));
  };
  check(d_out.image, Shape<3>{H, W, 3}, "d_image");
  check(d_out.alpha, Shape<2>{H, W}, "d_alpha");
  check(d_out.depth, Shape<2>{H, W}, "d_depth");
  check(d_out.features, Shape<3>{H, W, F}, "d_features");
  check(grads.means, Shape<2>{n, 3}, "grad means");
  check(grads.quats, Shape<2>{n, 4}, "grad quats");
  check(grads.scales, Shape<2>{n, 3}, "grad scales");
  check(grads.opacities, Shape<1>{n}, "grad opacities");
  check(grads.sh, in.sh.shape(), "grad sh");
  check(grads.features, Shape<2>{n, F}, "grad features");
  ws.d_out_channels.resize(std::size_t(pixels * C));
  ws.d_alpha.resize(std::size_t(pixels));
  parallel_for(pixels, [&](index_t begin, index_t end, int) {
    for (index_t p = begin; p < end; ++p) {
      T* d = &ws.d_out_channels[p * C];
      std::fill_n(d, C, T(0));
      ws.d_alpha[p] = T(0);
      if (!d_out.image.empty())
        for (int c = 0; c < 3; ++c) d[c] = d_out.image.data()[p * 3 + c];
      if (!d_out.alpha.empty()) ws.d_alpha[p] = d_out.alpha.data()[p];
      if (!d_out.depth.empty()) {
        const T dd = d_out.depth.data()[p];
        if (opt.expected_depth) {
          const T a = T(1) - ws.blend.final_transmittance[p];
          if (a > T(0)) {
            d[3] = dd / a;
            ws.d_alpha[p] -= dd * ws.out_channels[p * C + 3] / (a * a);
          }
        } else {
          d[3] = dd;
        }
      }
      if (!d_out.features.empty())
        for (int f = 0; f < F; ++f) d[4 + f] = d_out.features.data()[p * F + f];
    }
  }, pool);
  const int stride = entry_grad_fixed + C;
  ws.gaussian_grads.assign(std::size_t(n * stride), T(0));
  rasterize_backward(ws.tiles, ws.projections.data(), ws.channels.data(), C, ws.background.data(), ws.blend,
                     ws.d_out_channels.data(), ws.d_alpha.data(), opt.skips, ws.raster, n, ws.gaussian_grads.data(), pool);
  const CameraParams<T> cam = detail::camera_params(camera);
  ProjectSettings<T> set;
  set.eps2d = T(opt.eps2d), set.near_plane = T(opt.near_plane), set.far_plane = T(opt.far_plane);
  set.antialiased = opt.antialiased;
  T campos[3];
  for (int i = 0; i < 3; ++i) campos[i] = -(cam.R[i] * cam.t[0] + cam.R[3 + i] * cam.t[1] + cam.R[6 + i] * cam.t[2]);
  const index_t K = in.sh.shape(1);
  // Camera gradients: partial sums over fixed blocks of Gaussians, then summed in block order (thread-independent).
  constexpr index_t block = 256;
  const index_t blocks = (n + block - 1) / block;
  ws.camera_partials.assign(std::size_t(blocks), CameraGradParams<T>{});
  parallel_for(blocks, [&](index_t bb, index_t be, int) {
    for (index_t b = bb; b < be; ++b) {
      CameraGradParams<T>& dcam = ws.camera_partials[b];
      for (index_t g = b * block; g < std::min(n, (b + 1) * block); ++g) {
        if (!ws.visible[g] || ws.tiles.gaussian_counts[g] == 0) continue;
        const T* gg = &ws.gaussian_grads[g * stride];
        const T* m = in.means.data() + g * 3;
        T dm[3] = {0, 0, 0}, dq[4] = {0, 0, 0, 0}, ds[3] = {0, 0, 0}, dopacity = 0;
        // Colour from SH (clamped channels pass no gradient).
        T d_rgb[3];
        bool any = false;
        for (int c = 0; c < 3; ++c) {
          d_rgb[c] = ws.color_positive[g * 3 + c] ? gg[entry_grad_fixed + c] : T(0);
          any = any || d_rgb[c] != T(0);
        }
        if (any) {
          const T dir[3] = {m[0] - campos[0], m[1] - campos[1], m[2] - campos[2]};
          T d_dir[3] = {0, 0, 0};
          T* dsh = grads.sh.empty() ? nullptr : grads.sh.data() + g * K * 3;
          T dsh_local[16 * 3] = {};
          if (!dsh) dsh = dsh_local;
          sh_backward(ws.sh_degree, 3, in.sh.data() + g * K * 3, dir, d_rgb, dsh, d_dir);
          // dir = m - campos, campos = -R^T t
          for (int i = 0; i < 3; ++i) {
            dm[i] += d_dir[i];
            for (int j = 0; j < 3; ++j) dcam.R[j * 3 + i] += d_dir[i] * cam.t[j];
            dcam.t[i] += cam.R[i * 3] * d_dir[0] + cam.R[i * 3 + 1] * d_dir[1] + cam.R[i * 3 + 2] * d_dir[2];
          }
        }
        ProjectionGrad<T> pg;
        pg.u = gg[0], pg.v = gg[1];
        pg.conic[0] = gg[2], pg.conic[1] = gg[3], pg.conic[2] = gg[4];
        pg.opacity = gg[5];
        pg.z = gg[entry_grad_fixed + 3];
        project_backward_one(m, in.quats.data() + g * 4, in.scales.data() + g * 3, in.opacities.data()[g], cam, set, pg,
                             dm, dq, ds, dopacity, dcam);
        if (!grads.means.empty())
          for (int i = 0; i < 3; ++i) grads.means.data()[g * 3 + i] += dm[i];
        if (!grads.quats.empty())
          for (int i = 0; i < 4; ++i) grads.quats.data()[g * 4 + i] += dq[i];
        if (!grads.scales.empty())
          for (int i = 0; i < 3; ++i) grads.scales.data()[g * 3 + i] += ds[i];
        if (!grads.opacities.empty()) grads.opacities.data()[g] += dopacity;
        if (!grads.features.empty())
          for (int f = 0; f < F; ++f) grads.features.data()[g * F + f] += gg[entry_grad_fixed + 4 + f];
      }
    }
  }, pool);
  if (grads.camera) {
    CameraGradParams<T> total;
    for (const auto& part : ws.camera_partials) total.add(part);
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) grads.camera->world_to_camera[i * 4 + j] += total.R[i * 3 + j];
      grads.camera->world_to_camera[i * 4 + 3] += total.t[i];
    }
    grads.camera->fx += total.fx, grads.camera->fy += total.fy;
    grads.camera->cx += total.cx, grads.camera->cy += total.cy;
  }
}

}  // namespace raster
}  // namespace v0
}  // namespace flexsplat
