#pragma once
// The per-Gaussian passes of the rasterizer (raster/render.hpp): render_forward's projection pass (value checks,
// EWA projection, SH colour, channels, tiles, kernel record; scalar and batched paths) and render_backward's adjoint
// of it (colour through SH and the view direction, then the projection, camera contributions in fixed blocks).
#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <vector>

#include "flexsplat/core/camera.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/core/gaussians.hpp"
#include "flexsplat/core/inline.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/simd.hpp"
#include "flexsplat/core/simd_dispatch.hpp"  // its lane overloads must be visible where the lane templates are defined
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/raster/constants.hpp"
#include "flexsplat/raster/intersect.hpp"
#include "flexsplat/raster/project.hpp"
#include "flexsplat/raster/rasterize.hpp"
#include "flexsplat/raster/render_types.hpp"
#include "flexsplat/raster/sh.hpp"

namespace flexsplat {
inline namespace v0 {
namespace raster {

namespace detail {

template <class T>
ViewParams<T> view_params(const View<T>& cam) {
  ViewParams<T> p;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) p.R[i * 3 + j] = cam.world_to_camera[i * 4 + j];
    p.t[i] = cam.world_to_camera[i * 4 + 3];
  }
  p.fx = cam.fx, p.fy = cam.fy, p.cx = cam.cx, p.cy = cam.cy;
  p.width = T(cam.width), p.height = T(cam.height);
  return p;
}

template <class T>
ProjectSettings<T> project_settings(const RenderOptions& opt) {
  ProjectSettings<T> set;
  set.eps2d = T(opt.eps2d), set.near_plane = T(opt.near_plane), set.far_plane = T(opt.far_plane);
  set.antialiased = opt.antialiased;
  return set;
}

// Camera centre in world coordinates, -R^T t: SH colours are evaluated in the direction mean - centre.
template <class T>
std::array<T, 3> camera_centre(const ViewParams<T>& cam) {
  std::array<T, 3> c;
  for (int i = 0; i < 3; ++i) c[i] = -(cam.R[i] * cam.t[0] + cam.R[3 + i] * cam.t[1] + cam.R[6 + i] * cam.t[2]);
  return c;
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
int validate_inputs(const GaussianSet<T>& in, const View<T>& cam, const RenderOptions& opt) {
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
  const index_t k = in.sh.shape(1);
  int degree = opt.sh_degree;
  if (degree < 0) {
    degree = 0;
    while (degree < max_sh_degree && sh_coefficients(degree + 1) <= k) ++degree;
    require(sh_coefficients(degree) == k, "render: sh has K = ", k,
            " coefficients, not (degree+1)^2 for a degree 0..3; pass RenderOptions::sh_degree");
  }
  require(degree <= max_sh_degree, "render: sh_degree ", degree, " is above the supported ", max_sh_degree);
  require(sh_coefficients(degree) <= k, "render: sh_degree ", degree, " needs ", sh_coefficients(degree),
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
void validate_values(const GaussianSet<T>& in) {
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
bool gaussian_values_ok(const GaussianSet<T>& in, index_t g) {
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

// Everything the per-Gaussian pass of render_forward reads, shared by its scalar and batched paths.
template <class T>
struct GaussianPass {
  const GaussianSet<T>* in = nullptr;
  RenderWorkspace<T>* ws = nullptr;
  ViewParams<T> cam;
  ProjectSettings<T> set;
  TileGrid grid;
  RasterSkips skips;
  int degree = 0, F = 0, C = 0;
  index_t n = 0, K = 0;
  std::array<T, 3> campos{};
  T* records = nullptr;
  int record_stride = 0;
};

// Scalar path, one Gaussian: value checks, projection, colour, channels, tiles, kernel record; false if a value is bad.
template <class T>
bool gaussian_one(const GaussianPass<T>& pass, index_t g) {
  const GaussianSet<T>& in = *pass.in;
  RenderWorkspace<T>& ws = *pass.ws;
  if (!gaussian_values_ok(in, g)) return false;
  const T* m = in.means.data() + g * 3;
  Projection<T>& p = ws.projections[g];
  if (!project_forward_one(m, in.quats.data() + g * 4, in.scales.data() + g * 3, in.opacities.data()[g], pass.cam,
                           pass.set, p))
    return true;
  ws.visible[g] = 1;
  const int C = pass.C, F = pass.F;
  T* ch = &ws.channels[g * C];
  const T dir[3] = {m[0] - pass.campos[0], m[1] - pass.campos[1], m[2] - pass.campos[2]};
  T rgb[3];
  sh_forward(pass.degree, 3, in.sh.data() + g * pass.K * 3, dir, rgb);
  for (int c = 0; c < 3; ++c) {
    const T value = rgb[c] + T(sh_color_offset);
    ws.color_positive[g * 3 + c] = value > T(0);
    ch[c] = value > T(0) ? value : T(0);
  }
  ch[3] = p.z;
  for (int f = 0; f < F; ++f) ch[4 + f] = in.features.data()[g * F + f];
  const std::int64_t tiles = count_gaussian_tiles(p, pass.grid, pass.skips, ws.tiles.gaussian_tiles[g]);
  ws.tiles.gaussian_counts[g] = tiles;
  if (tiles > 0) write_splat_record(p, ch, C, pass.grid, pass.records + g * pass.record_stride);
  return true;
}

// Whether every value of data[0, count) is finite: x - x is 0 for a finite x and NaN otherwise, and NaN survives sums.
template <class V, class T>
FLEXSPLAT_ALWAYS_INLINE bool all_finite_lanes(const T* data, index_t count) {
  constexpr index_t L = index_t(simd::lane_count<V>::value);
  V acc = V(T(0));
  index_t i = 0;
  for (; i + L <= count; i += L) {
    const V x = simd::lane_load<V>(data + i);
    acc = acc + (x - x);
  }
  T tail = T(0);
  for (; i < count; ++i) tail += data[i] - data[i];
  return simd::lane_all(acc == V(T(0))) && tail == T(0);
}

// Batched path: Gaussians [g0, g0 + L) (L = lanes of V; padding lanes past n repeat the last Gaussian and write
// nothing) give the same projections, colours and channels as gaussian_one (same arithmetic per lane) and
// conservative tiles and records computed in double lanes with one shared log. A block with a suspicious value runs
// gaussian_one per Gaussian, so errors are found exactly as on the scalar path.
// Long (about 180 lines): one lane body that mirrors gaussian_one step by step, so that the two paths read side by side.
template <class V, class T>
bool gaussian_block(const GaussianPass<T>& pass, index_t g0) {
  using VD = typename simd::double_lanes<V>::type;
  constexpr int L = int(simd::lane_count<V>::value), LD = int(simd::lane_count<VD>::value);
  static_assert(L % LD == 0, "a block splits into whole double batches");
  const GaussianSet<T>& in = *pass.in;
  RenderWorkspace<T>& ws = *pass.ws;
  const int live = int(std::min<index_t>(L, pass.n - g0));
  const index_t K3 = pass.K * 3, F = pass.F;
  auto per_gaussian = [&] {
    bool ok = true;
    for (int l = 0; l < live; ++l) ok &= gaussian_one(pass, g0 + l);
    return ok;
  };
  // Inputs of the block `ahead` blocks on: a block is a lot of work per cache line, so the hardware prefetchers fall
  // behind the streams (the inputs of a block are contiguous ranges).
  constexpr index_t ahead = 2;
  if (const index_t gp = g0 + ahead * L; gp + L <= pass.n) {
    auto prefetch = [](const T* p, index_t count) {
      for (index_t i = 0; i < count; i += index_t(64 / sizeof(T))) __builtin_prefetch(p + i);
    };
    prefetch(in.means.data() + gp * 3, L * 3);
    prefetch(in.quats.data() + gp * 4, L * 4);
    prefetch(in.scales.data() + gp * 3, L * 3);
    prefetch(in.opacities.data() + gp, L);
    prefetch(in.sh.data() + gp * K3, L * K3);
    if (F > 0) prefetch(in.features.data() + gp * F, L * F);
  }
  // Inputs of a block are contiguous ranges: one finiteness scan each.
  if (!(all_finite_lanes<V>(in.means.data() + g0 * 3, live * 3) &&
        all_finite_lanes<V>(in.quats.data() + g0 * 4, live * 4) &&
        all_finite_lanes<V>(in.scales.data() + g0 * 3, live * 3) &&
        all_finite_lanes<V>(in.opacities.data() + g0, live) && all_finite_lanes<V>(in.sh.data() + g0 * K3, live * K3) &&
        (F == 0 || all_finite_lanes<V>(in.features.data() + g0 * F, live * F))))
    return per_gaussian();
  // Structure of arrays of the block (transposed through the stack).
  alignas(64) T a_m[3][L], a_q[4][L], a_s[3][L], a_o[L];
  for (int l = 0; l < L; ++l) {
    const index_t g = g0 + std::min(l, live - 1);
    for (int i = 0; i < 3; ++i) a_m[i][l] = in.means.data()[g * 3 + i];
    for (int i = 0; i < 4; ++i) a_q[i][l] = in.quats.data()[g * 4 + i];
    for (int i = 0; i < 3; ++i) a_s[i][l] = in.scales.data()[g * 3 + i];
    a_o[l] = in.opacities.data()[g];
  }
  V m[3], q[4], sc[3];
  for (int i = 0; i < 3; ++i) m[i] = simd::lane_load<V>(a_m[i]), sc[i] = simd::lane_load<V>(a_s[i]);
  for (int i = 0; i < 4; ++i) q[i] = simd::lane_load<V>(a_q[i]);
  const V o = simd::lane_load<V>(a_o);
  // Quaternion length and opacity range. gaussian_values_ok rounds |q|^2 its own way: far from 0 and overflow every
  // rounding agrees, so only a block with a length in doubt takes the per-Gaussian checks.
  const V len2 = simd::lane_mul_add(q[3], q[3], simd::lane_mul_add(q[2], q[2], simd::lane_mul_add(q[1], q[1], q[0] * q[0])));
  if (!simd::lane_all((len2 > V(T(1e-30))) & (len2 < V(T(1e30))) & (o >= V(T(0))) & (o <= V(T(1)))))
    return per_gaussian();
  ProjectionLanes<V> p;
  const auto visible = project_forward_lanes<V, T>(m, q, sc, o, pass.cam, pass.set, p);
  // Colour from SH: coefficient (k, c) of every lane in one batch.
  const T* sh_rows[L];
  for (int l = 0; l < L; ++l) sh_rows[l] = in.sh.data() + (g0 + std::min(l, live - 1)) * K3;
  V coeffs[16 * 3];
  simd::load_columns<V, T>(sh_rows, sh_coefficients(pass.degree) * 3, coeffs);
  const V dir[3] = {m[0] - V(pass.campos[0]), m[1] - V(pass.campos[1]), m[2] - V(pass.campos[2])};
  V rgb[3];
  sh_forward_lanes<V>(pass.degree, 3, coeffs, dir, rgb);
  // Lane values back to arrays: projection, clamped colour and its sign, visibility.
  alignas(64) T a_p[10][L], a_rgb[3][L], a_pos[3][L], a_vis[L];
  const V* fields[10] = {&p.u, &p.v, &p.z, &p.cov[0], &p.cov[1], &p.cov[2], &p.conic[0], &p.conic[1], &p.conic[2],
                         &p.opacity};
  for (int i = 0; i < 10; ++i) simd::lane_store(a_p[i], *fields[i]);
  for (int c = 0; c < 3; ++c) {
    const V value = rgb[c] + V(T(sh_color_offset));
    const auto positive = value > V(T(0));
    simd::lane_store(a_rgb[c], simd::lane_select(positive, value, V(T(0))));
    simd::lane_store(a_pos[c], simd::lane_select(positive, V(T(1)), V(T(0))));
  }
  simd::lane_store(a_vis, simd::lane_select(visible, V(T(1)), V(T(0))));
  const int C = pass.C;
  for (int l = 0; l < live; ++l) {
    if (a_vis[l] == T(0)) continue;
    const index_t g = g0 + l;
    ws.visible[g] = 1;
    Projection<T>& pr = ws.projections[g];
    pr.u = a_p[0][l], pr.v = a_p[1][l], pr.z = a_p[2][l];
    for (int i = 0; i < 3; ++i) pr.cov[i] = a_p[3 + i][l], pr.conic[i] = a_p[6 + i][l];
    pr.opacity = a_p[9][l];
    T* ch = &ws.channels[g * C];
    for (int c = 0; c < 3; ++c) ch[c] = a_rgb[c][l], ws.color_positive[g * 3 + c] = a_pos[c][l] != T(0);
    ch[3] = a_p[2][l];
    for (int f = 0; f < F; ++f) ch[4 + f] = in.features.data()[g * F + f];
  }
  // Tiles and kernel records in double lanes (conservative extents, as count_gaussian_tiles and splat_params).
  alignas(64) double d_p[10][L], d_vis[L];
  for (int i = 0; i < 10; ++i)
    for (int l = 0; l < L; ++l) d_p[i][l] = double(a_p[i][l]);
  for (int l = 0; l < L; ++l) d_vis[l] = double(a_vis[l]);
  const TileGrid& grid = pass.grid;
  const bool aware = pass.skips.opacity_aware_extent, row_test = pass.skips.exact_tile_test;
  const VD r2_opaque = VD(cull_radius2(1.0, false));
  constexpr int stored = GaussianTiles::stored_rows;
  for (int base = 0; base < L; base += LD) {
    auto load = [&](const double* a) { return simd::lane_load<VD>(a + base); };
    const VD u = load(d_p[0]), v = load(d_p[1]), qa = load(d_p[6]), qb = load(d_p[7]), qc = load(d_p[8]);
    const VD opacity = load(d_p[9]);
    // One log for the tile extent and the kernel's sigma_max: log(o / alpha_threshold).
    const VD lg = simd::lane_log(opacity / VD(alpha_threshold));
    const VD r2 = aware ? VD(2.0) * lg * VD(1.0 + cull_slack_relative) + VD(cull_slack_absolute) : r2_opaque;
    TileRectLanes<VD> rect;
    const auto hit = tile_rect_lanes(u, v, load(d_p[3]), load(d_p[5]), r2, grid, rect) & (load(d_vis) != VD(0.0));
    if (!simd::lane_any(hit)) continue;
    const VD zero = VD(0.0), one = VD(1.0);
    const auto no_lane = zero != zero;
    const auto exact = row_test ? hit & (rect.x1 > rect.x0) & (rect.y1 > rect.y0) : no_lane;  // uses_row_test
    // Tiles of the stored rows (later rows are counted per Gaussian below, as for_each_gaussian_tile_row emits them).
    const VD stored_rows = simd::lane_min(rect.y1 - rect.y0 + one, VD(double(stored)));
    VD count = simd::lane_select(hit & simd::lane_not(exact), stored_rows * (rect.x1 - rect.x0 + one), zero);
    VD first[stored], last[stored];
    for (int i = 0; i < stored; ++i) first[i] = rect.x0, last[i] = rect.x1;
    if (simd::lane_any(exact)) {
      const EllipseRowsLanes<VD> e = ellipse_rows_lanes(u, v, qa, qb, qc, r2);
      for (int i = 0; i < stored; ++i) {
        const VD ty = rect.y0 + VD(double(i));
        const auto active = exact & (ty <= rect.y1);
        if (!simd::lane_any(active)) break;
        VD f, l;
        const auto reached = tile_row_span_lanes(e, grid, rect, ty, f, l);
        first[i] = simd::lane_select(exact, f, first[i]), last[i] = simd::lane_select(exact, l, last[i]);
        count += simd::lane_select(active & reached, l - f + one, zero);
      }
    }
    // Kernel extent (splat_params): sigma_max rounded to T first, as the kernels compare against that value.
    alignas(64) double sigma_max[LD];
    simd::lane_store(sigma_max, lg * VD(1.0 + cull_slack_relative) + VD(cull_slack_absolute));
    for (int l = 0; l < LD; ++l) sigma_max[l] = double(T(sigma_max[l]));
    const VD sm = simd::lane_load<VD>(sigma_max);
    const VD r2s = VD(2.0) * simd::lane_select(sm < zero, zero, sm);
    const VD det = qa * qc - qb * qb, trace = qa + qc;
    const VD margin = VD(1.0 + cull_slack_relative) + VD(cull_slack_conditioning) * trace * trace / det;
    VD rx = simd::lane_sqrt(r2s * qc / det) * margin + VD(cull_slack_absolute);
    VD ry = simd::lane_sqrt(r2s * qa / det) * margin + VD(cull_slack_absolute);
    const auto sane = (det > zero) & (qa > zero) & (qc > zero) & simd::lane_isfinite(rx) & simd::lane_isfinite(ry);
    // Widened so that T(rx) >= rx after rounding to nearest: conservative in T (as splat_params' round-up).
    const VD widen = VD(sizeof(T) < sizeof(double) ? 1.0 + 0x1p-22 : 1.0);
    rx = simd::lane_select(sane, rx * widen, VD(INFINITY)), ry = simd::lane_select(sane, ry * widen, VD(INFINITY));
    // Back to lanes: rectangle, stored rows, counts, extents.
    alignas(64) double a_rect[4][LD], a_first[stored][LD], a_last[stored][LD], a_count[LD], a_hit[LD], a_rx[LD], a_ry[LD];
    simd::lane_store(a_rect[0], simd::lane_select(hit, rect.x0, zero));
    simd::lane_store(a_rect[1], simd::lane_select(hit, rect.y0, zero));
    simd::lane_store(a_rect[2], simd::lane_select(hit, rect.x1, zero));
    simd::lane_store(a_rect[3], simd::lane_select(hit, rect.y1, zero));
    for (int i = 0; i < stored; ++i) {
      simd::lane_store(a_first[i], simd::lane_select(hit, first[i], zero));
      simd::lane_store(a_last[i], simd::lane_select(hit, last[i], zero));
    }
    simd::lane_store(a_count, simd::lane_select(hit, count, zero));
    simd::lane_store(a_hit, simd::lane_select(hit, one, zero));
    simd::lane_store(a_rx, rx), simd::lane_store(a_ry, ry);
    for (int l = 0; l < LD && base + l < live; ++l) {
      if (a_hit[l] == 0.0) continue;
      const int lane = base + l;
      const index_t g = g0 + lane;
      GaussianTiles& t = ws.tiles.gaussian_tiles[g];
      t.rect = TileRect{int(a_rect[0][l]), int(a_rect[1][l]), int(a_rect[2][l]), int(a_rect[3][l])};
      for (int i = 0; i < stored; ++i) t.first[i] = std::int16_t(a_first[i][l]), t.last[i] = std::int16_t(a_last[i][l]);
      std::int64_t tiles = std::int64_t(a_count[l]);
      for_each_later_tile_row(ws.projections[g], t, grid, pass.skips,
                              [&](int, int tx0, int tx1) { tiles += tx1 - tx0 + 1; });
      ws.tiles.gaussian_counts[g] = tiles;
      if (tiles == 0) continue;
      T* record = pass.records + g * pass.record_stride;
      record[0] = a_p[0][lane], record[1] = a_p[1][lane];
      record[2] = a_p[6][lane], record[3] = a_p[7][lane], record[4] = a_p[8][lane];
      record[5] = a_p[9][lane], record[6] = T(sigma_max[l]);
      write_record_pixels(double(a_p[0][lane]), double(a_p[1][lane]), double(T(a_rx[l])), double(T(a_ry[l])), grid,
                          record);
      const T* ch = &ws.channels[g * C];
      for (int c = 0; c < C; ++c) record[splat_fields + c] = ch[c];
    }
  }
  return true;
}

// Everything the per-Gaussian pass of render_backward reads, shared by its scalar and batched paths.
template <class T>
struct GaussianBackwardPass {
  const GaussianSet<T>* in = nullptr;
  const RenderWorkspace<T>* ws = nullptr;
  GaussianSetGrad<T>* grads = nullptr;
  ViewParams<T> cam;
  ProjectSettings<T> set;
  std::array<T, 3> campos{};
  int degree = 0, F = 0, stride = 0;
  index_t n = 0, K = 0;
};

// Gradient record of a Gaussian as the per-Gaussian adjoint reads it: d(u, v, conic a, b, c, opacity), d(colour) of
// the channels whose SH value was not clamped (others pass nothing), d(depth).
inline constexpr int backward_record_fields = 10;
inline constexpr int max_record_size = entry_grad_fixed + 4 + 48;  // 6 + C with C = 4 + F, F <= 48

// The adjoint of one Gaussian per lane of V (V = T: one Gaussian): colour through SH and the view direction, then the
// projection. dm, dq, ds, dopacity and dcam (this Gaussian's camera contribution) are set from zero; d_coeffs gets
// b_k d_rgb where colour_live (some colour cotangent is non-zero). The scalar and batched paths share this body, so
// their lanes are bit-identical.
template <class V, class T>
FLEXSPLAT_ALWAYS_INLINE void gaussian_backward_lanes(const GaussianBackwardPass<T>& pass, const V m[3], const V q[4],
                                                     const V s[3], V opacity, const V* coeffs,
                                                     const V gg[backward_record_fields],
                                                     simd::lane_mask<V>& colour_live, V* d_coeffs, V dm[3], V dq[4],
                                                     V ds[3], V& dopacity, ViewGradParams<V>& dcam) {
  const V zero = V(T(0));
  for (int i = 0; i < 3; ++i) dm[i] = zero, ds[i] = zero, dcam.t[i] = zero;
  for (int i = 0; i < 4; ++i) dq[i] = zero;
  for (int i = 0; i < 9; ++i) dcam.R[i] = zero;
  dcam.fx = zero, dcam.fy = zero, dcam.cx = zero, dcam.cy = zero;
  dopacity = zero;
  const V d_rgb[3] = {gg[6], gg[7], gg[8]};
  colour_live = (d_rgb[0] != zero) | (d_rgb[1] != zero) | (d_rgb[2] != zero);
  if (simd::lane_any(colour_live)) {
    const V dir[3] = {m[0] - V(pass.campos[0]), m[1] - V(pass.campos[1]), m[2] - V(pass.campos[2])};
    V d_dir[3] = {zero, zero, zero};
    sh_backward_lanes<V>(pass.degree, 3, coeffs, dir, d_rgb, d_coeffs, d_dir);
    for (int i = 0; i < 3; ++i) d_dir[i] = simd::lane_select(colour_live, d_dir[i], zero);
    // dir = m - campos, campos = -R^T t
    for (int i = 0; i < 3; ++i) {
      dm[i] = dm[i] + d_dir[i];
      for (int j = 0; j < 3; ++j) dcam.R[j * 3 + i] = simd::lane_mul_add(d_dir[i], V(pass.cam.t[j]), dcam.R[j * 3 + i]);
      dcam.t[i] = dcam.t[i] + detail::dot3_lanes(V(pass.cam.R[i * 3]), d_dir[0], V(pass.cam.R[i * 3 + 1]), d_dir[1],
                                                 V(pass.cam.R[i * 3 + 2]), d_dir[2]);
    }
  }
  ProjectionGrad<V> pg;
  pg.u = gg[0], pg.v = gg[1];
  pg.conic[0] = gg[2], pg.conic[1] = gg[3], pg.conic[2] = gg[4];
  pg.opacity = gg[5];
  pg.z = gg[9];
  project_backward_lanes<V, T>(m, q, s, opacity, pass.cam, pass.set, pg, dm, dq, ds, dopacity, dcam);
}

// Whether Gaussian g has a gradient record (visible with tile entries).
template <class T>
bool has_backward(const RenderWorkspace<T>& ws, index_t g) {
  return ws.visible[g] && ws.tiles.gaussian_counts[g] != 0;
}

// The record of Gaussian g: the sum of its entries' records (row, 6 + C values), and the values
// gaussian_backward_lanes reads (gg).
template <class T>
void backward_record(const GaussianBackwardPass<T>& pass, index_t g, T* row, T gg[backward_record_fields]) {
  sum_entry_grads(pass.ws->tiles, pass.ws->raster, pass.ws->channel_count, g, row);
  for (int i = 0; i < 6; ++i) gg[i] = row[i];
  for (int c = 0; c < 3; ++c) gg[6 + c] = pass.ws->color_positive[g * 3 + c] ? row[entry_grad_fixed + c] : T(0);
  gg[9] = row[entry_grad_fixed + 3];
}

// Adds one Gaussian's results into the gradient tensors (empty ones are skipped); d_coeffs null: no SH gradient,
// else coefficient j at d_coeffs[j * coeff_stride].
template <class T>
void add_gaussian_grads(const GaussianBackwardPass<T>& pass, index_t g, const T* row, const T dm[3], const T dq[4],
                        const T ds[3], T dopacity, const T* d_coeffs, int coeff_stride) {
  GaussianSetGrad<T>& grads = *pass.grads;
  if (!grads.means.empty())
    for (int i = 0; i < 3; ++i) grads.means.data()[g * 3 + i] += dm[i];
  if (!grads.quats.empty())
    for (int i = 0; i < 4; ++i) grads.quats.data()[g * 4 + i] += dq[i];
  if (!grads.scales.empty())
    for (int i = 0; i < 3; ++i) grads.scales.data()[g * 3 + i] += ds[i];
  if (!grads.opacities.empty()) grads.opacities.data()[g] += dopacity;
  if (d_coeffs && !grads.sh.empty()) {
    T* dsh = grads.sh.data() + g * pass.K * 3;
    for (int j = 0; j < sh_coefficients(pass.degree) * 3; ++j) dsh[j] += d_coeffs[j * coeff_stride];
  }
  if (!grads.features.empty()) {
    for (int f = 0; f < pass.F; ++f) grads.features.data()[g * pass.F + f] += row[entry_grad_fixed + 4 + f];
  }
}

// Scalar path, one Gaussian with a gradient record: adds its gradients and its camera contribution to dcam.
template <class T>
void gaussian_backward_one(const GaussianBackwardPass<T>& pass, index_t g, ViewGradParams<T>& dcam) {
  const GaussianSet<T>& in = *pass.in;
  T row[max_record_size], gg[backward_record_fields];
  backward_record(pass, g, row, gg);
  T dm[3], dq[4], ds[3], dopacity, d_coeffs[16 * 3];
  bool colour_live = false;
  ViewGradParams<T> mine;
  gaussian_backward_lanes<T, T>(pass, in.means.data() + g * 3, in.quats.data() + g * 4, in.scales.data() + g * 3,
                                in.opacities.data()[g], in.sh.data() + g * pass.K * 3, gg, colour_live, d_coeffs, dm,
                                dq, ds, dopacity, mine);
  add_gaussian_grads(pass, g, row, dm, dq, ds, dopacity, colour_live ? d_coeffs : nullptr, 1);
  dcam.add(mine);
}

// Batched path: Gaussians [g0, g0 + L) (padding lanes past n repeat the last Gaussian and write nothing; lanes
// without a record compute unused values). Adds the same gradients as gaussian_backward_one, Gaussian by Gaussian in
// index order, camera contributions included.
template <class V, class T>
void gaussian_backward_block(const GaussianBackwardPass<T>& pass, index_t g0, ViewGradParams<T>& dcam) {
  constexpr int L = int(simd::lane_count<V>::value);
  const GaussianSet<T>& in = *pass.in;
  const RenderWorkspace<T>& ws = *pass.ws;
  const int live = int(std::min<index_t>(L, pass.n - g0));
  bool any = false;
  for (int l = 0; l < live; ++l) any = any || has_backward(ws, g0 + l);
  if (!any) return;
  const index_t K3 = pass.K * 3;
  // Inputs of the block `ahead` blocks on (contiguous ranges), as in the forward's per-Gaussian pass.
  constexpr index_t ahead = 2;
  if (const index_t gp = g0 + ahead * L; gp + L <= pass.n) {
    auto prefetch = [](const T* p, index_t count) {
      for (index_t i = 0; i < count; i += index_t(64 / sizeof(T))) __builtin_prefetch(p + i);
    };
    prefetch(in.means.data() + gp * 3, L * 3);
    prefetch(in.quats.data() + gp * 4, L * 4);
    prefetch(in.scales.data() + gp * 3, L * 3);
    prefetch(in.opacities.data() + gp, L);
    prefetch(in.sh.data() + gp * K3, L * K3);
    const std::int64_t e0 = ws.tiles.gaussian_offsets[gp], e1 = ws.tiles.gaussian_offsets[gp + L - 1];
    prefetch(ws.raster.entry_grads.data() + e0 * pass.stride, index_t(e1 - e0 + 1) * pass.stride);
    // The SH gradients are read and written back (192 bytes per Gaussian at degree 3): the largest stream.
    if (!pass.grads->sh.empty())
      for (index_t i = 0; i < L * K3; i += index_t(64 / sizeof(T))) __builtin_prefetch(pass.grads->sh.data() + gp * K3 + i, 1);
  }
  // Structure of arrays of the block (transposed through the stack).
  alignas(64) T a_m[3][L], a_q[4][L], a_s[3][L], a_o[L], a_g[backward_record_fields][L];
  T rows[L][max_record_size];
  for (int l = 0; l < L; ++l) {
    const index_t g = g0 + std::min(l, live - 1);
    for (int i = 0; i < 3; ++i) a_m[i][l] = in.means.data()[g * 3 + i];
    for (int i = 0; i < 4; ++i) a_q[i][l] = in.quats.data()[g * 4 + i];
    for (int i = 0; i < 3; ++i) a_s[i][l] = in.scales.data()[g * 3 + i];
    a_o[l] = in.opacities.data()[g];
    T gg[backward_record_fields];
    backward_record(pass, g, rows[l], gg);
    for (int i = 0; i < backward_record_fields; ++i) a_g[i][l] = gg[i];
  }
  V m[3], q[4], sc[3], gv[backward_record_fields];
  for (int i = 0; i < 3; ++i) m[i] = simd::lane_load<V>(a_m[i]), sc[i] = simd::lane_load<V>(a_s[i]);
  for (int i = 0; i < 4; ++i) q[i] = simd::lane_load<V>(a_q[i]);
  for (int i = 0; i < backward_record_fields; ++i) gv[i] = simd::lane_load<V>(a_g[i]);
  const T* sh_rows[L];
  for (int l = 0; l < L; ++l) sh_rows[l] = in.sh.data() + (g0 + std::min(l, live - 1)) * K3;
  const int coeff_count = sh_coefficients(pass.degree) * 3;
  V coeffs[16 * 3], d_coeffs[16 * 3];
  simd::load_columns<V, T>(sh_rows, coeff_count, coeffs);
  V dm[3], dq[4], ds[3], dopacity;
  simd::lane_mask<V> colour_live;
  ViewGradParams<V> cam;
  gaussian_backward_lanes<V, T>(pass, m, q, sc, simd::lane_load<V>(a_o), coeffs, gv, colour_live, d_coeffs, dm, dq,
                                ds, dopacity, cam);
  // Lane values back to arrays, then added Gaussian by Gaussian.
  alignas(64) T a_dm[3][L], a_dq[4][L], a_ds[3][L], a_dop[L], a_live[L], a_cam[16][L];
  alignas(64) T a_dsh[16 * 3][L];
  for (int i = 0; i < 3; ++i) simd::lane_store(a_dm[i], dm[i]), simd::lane_store(a_ds[i], ds[i]);
  for (int i = 0; i < 4; ++i) simd::lane_store(a_dq[i], dq[i]);
  simd::lane_store(a_dop, dopacity);
  simd::lane_store(a_live, simd::lane_select(colour_live, V(T(1)), V(T(0))));
  const bool sh_wanted = !pass.grads->sh.empty() && simd::lane_any(colour_live);
  if (sh_wanted)
    for (int j = 0; j < coeff_count; ++j) simd::lane_store(a_dsh[j], d_coeffs[j]);
  for (int i = 0; i < 9; ++i) simd::lane_store(a_cam[i], cam.R[i]);
  for (int i = 0; i < 3; ++i) simd::lane_store(a_cam[9 + i], cam.t[i]);
  simd::lane_store(a_cam[12], cam.fx), simd::lane_store(a_cam[13], cam.fy);
  simd::lane_store(a_cam[14], cam.cx), simd::lane_store(a_cam[15], cam.cy);
  for (int l = 0; l < live; ++l) {
    const index_t g = g0 + l;
    if (!has_backward(ws, g)) continue;
    const T dml[3] = {a_dm[0][l], a_dm[1][l], a_dm[2][l]}, dsl[3] = {a_ds[0][l], a_ds[1][l], a_ds[2][l]};
    const T dql[4] = {a_dq[0][l], a_dq[1][l], a_dq[2][l], a_dq[3][l]};
    add_gaussian_grads(pass, g, rows[l], dml, dql, dsl, a_dop[l], sh_wanted && a_live[l] != T(0) ? &a_dsh[0][l] : nullptr,
                       L);
    ViewGradParams<T> mine;
    for (int i = 0; i < 9; ++i) mine.R[i] = a_cam[i][l];
    for (int i = 0; i < 3; ++i) mine.t[i] = a_cam[9 + i][l];
    mine.fx = a_cam[12][l], mine.fy = a_cam[13][l], mine.cx = a_cam[14][l], mine.cy = a_cam[15][l];
    dcam.add(mine);
  }
}

template <class T>
GaussianBackwardPass<T> backward_pass(const GaussianSet<T>& in, const View<T>& camera, const RenderOptions& opt,
                                      const RenderWorkspace<T>& ws, GaussianSetGrad<T>& grads) {
  GaussianBackwardPass<T> pass;
  pass.in = &in, pass.ws = &ws, pass.grads = &grads;
  pass.cam = view_params(camera), pass.set = project_settings<T>(opt);
  pass.campos = camera_centre(pass.cam);
  pass.degree = ws.sh_degree, pass.F = ws.channel_count - 4, pass.stride = entry_grad_fixed + ws.channel_count;
  pass.n = in.means.shape(0), pass.K = in.sh.shape(1);
  return pass;
}

// The per-Gaussian adjoints of render_backward for every Gaussian with a gradient record, on the scalar path or in
// the lanes of `kernel`. Camera contributions: partial sums over fixed blocks of Gaussians, each Gaussian's added in
// index order (the same for any thread count and on every path), into partials (one per block, to be summed in
// block order).
template <class T>
void gaussians_backward(const GaussianBackwardPass<T>& pass, BlendKernel kernel,
                        std::vector<ViewGradParams<T>>& partials, ThreadPool& pool) {
  constexpr index_t block = 256;
  const index_t n = pass.n, blocks = (n + block - 1) / block;
  const RenderWorkspace<T>& ws = *pass.ws;
  partials.assign(std::size_t(blocks), ViewGradParams<T>{});
  parallel_for(blocks, [&](index_t bb, index_t be, int) {
    if (kernel == BlendKernel::scalar) {
      for (index_t b = bb; b < be; ++b)
        for (index_t g = b * block; g < std::min(n, (b + 1) * block); ++g)
          if (has_backward(ws, g)) gaussian_backward_one(pass, g, partials[b]);
      return;
    }
    with_exact_lanes<T>(kernel, [&](auto* lanes) {
      using V = std::remove_pointer_t<decltype(lanes)>;
      constexpr index_t L = index_t(simd::lane_count<V>::value);
      static_assert(block % L == 0, "lane blocks never straddle a camera block");
      for (index_t b = bb; b < be; ++b)
        for (index_t g0 = b * block; g0 < std::min(n, (b + 1) * block); g0 += L)
          gaussian_backward_block<V, T>(pass, g0, partials[b]);
    });
  }, pool);
}

}  // namespace detail
}  // namespace raster
}  // namespace v0
}  // namespace flexsplat
