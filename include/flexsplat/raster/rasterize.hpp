#pragma once
// Front-to-back alpha blending of C channels per pixel over the per-tile lists, and its adjoint (back to front,
// transmittance recovered by division). Threads take whole tiles; SIMD lanes are neighbouring pixels of a row.
// Backward writes one gradient record per (tile, Gaussian) entry, reduced per Gaussian in a fixed order, so results
// do not depend on the number of threads.
#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <vector>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/simd.hpp"
#include "flexsplat/raster/constants.hpp"
#include "flexsplat/raster/intersect.hpp"
#include "flexsplat/raster/project.hpp"

namespace flexsplat {
inline namespace v0 {
namespace raster {

// Per-entry gradient record: d(u), d(v), d(conic a, b, c), d(opacity), then d(channel 0..C-1).
inline constexpr int entry_grad_fixed = 6;

// Per-pixel blending state kept from the forward pass for the backward pass.
template <class T>
struct BlendState {
  std::vector<T> final_transmittance;     // [H*W]
  std::vector<std::int32_t> last_entry;   // [H*W] 1 + tile-list position of the last contributor (0: none)
  std::vector<std::int32_t> n_contrib;    // [H*W]
};

// Tile-local copies of the Gaussians of one tile (structure of arrays) plus per-entry gradient accumulators.
template <class T>
struct TileScratch {
  std::vector<T> u, v, ca, cb, cc, opacity, sigma_max, channels, grads;
  void reserve(std::int64_t n, int channel_count) {
    for (auto* a : {&u, &v, &ca, &cb, &cc, &opacity, &sigma_max}) a->resize(std::size_t(n));
    channels.resize(std::size_t(n * channel_count));
    grads.resize(std::size_t(n * (entry_grad_fixed + channel_count)));
  }
};

template <class T>
struct RasterWorkspace {
  std::vector<TileScratch<T>> scratch;  // one per worker
  std::vector<T> entry_grads;           // [E, 6 + C]
};

namespace detail {

template <class T>
void gather_tile(const TileIntersections& ti, index_t tile, const Projection<T>* proj, const T* channels, int C,
                 TileScratch<T>& s) {
  const std::int64_t begin = ti.tile_offsets[tile], end = ti.tile_offsets[tile + 1];
  for (std::int64_t k = 0; k < end - begin; ++k) {
    const std::int32_t g = ti.isect_gaussian[ti.tile_entries[begin + k]];
    const Projection<T>& p = proj[g];
    s.u[k] = p.u, s.v[k] = p.v;
    s.ca[k] = p.conic[0], s.cb[k] = p.conic[1], s.cc[k] = p.conic[2];
    s.opacity[k] = p.opacity;
    // sigma above this gives alpha < alpha_threshold for certain (slack covers float rounding of exp)
    s.sigma_max[k] = T(std::log(double(p.opacity) / alpha_threshold) * (1.0 + cull_slack_relative) + cull_slack_absolute);
    for (int c = 0; c < C; ++c) s.channels[k * C + c] = channels[std::int64_t(g) * C + c];
  }
}

template <class V, class T>
V lane_offsets() {
  alignas(64) T idx[simd::lane_count<V>::value];
  for (std::size_t i = 0; i < simd::lane_count<V>::value; ++i) idx[i] = T(i);
  return simd::lane_load<V>(idx);
}

// Blends one tile; V is T (scalar path) or simd::batch<T>.
template <class V, class T>
void blend_tile_forward(const TileIntersections& ti, index_t tile, const TileScratch<T>& s, int C, const T* background,
                        const RasterSkips& skips, T* out_channels, BlendState<T>& state) {
  constexpr int L = int(simd::lane_count<V>::value);
  static_assert(tile_size % L == 0, "tile rows must split into whole batches");
  const TileGrid& grid = ti.grid;
  const int tx = int(tile % grid.tiles_x), ty = int(tile / grid.tiles_x);
  const std::int64_t count = ti.tile_offsets[tile + 1] - ti.tile_offsets[tile];
  const V iota = lane_offsets<V, T>();
  constexpr int max_channels = 64;
  V acc[max_channels];
  alignas(64) T lanes_T[L], lanes_n[L], lanes_last[L], lanes_acc[max_channels][L];
  const int y_end = std::min(grid.height, (ty + 1) * tile_size);
  const int x_end = std::min(grid.width, (tx + 1) * tile_size);
  for (int py = ty * tile_size; py < y_end; ++py) {
    const V pyc = V(T(py) + T(pixel_centre_offset));
    for (int bx = tx * tile_size; bx < x_end; bx += L) {
      const V px = iota + V(T(bx));
      const V pxc = px + V(T(pixel_centre_offset));
      auto done = px >= V(T(grid.width));
      V trans = V(T(1)), n_contrib = V(T(0)), last = V(T(0));
      for (int c = 0; c < C; ++c) acc[c] = V(T(0));
      if (!simd::lane_all(done)) {
        for (std::int64_t k = 0; k < count; ++k) {
          const V dx = V(s.u[k]) - pxc, dy = V(s.v[k]) - pyc;
          const V sigma = T(0.5) * (V(s.ca[k]) * dx * dx + V(s.cc[k]) * dy * dy) + V(s.cb[k]) * dx * dy;
          auto maybe = (sigma <= V(s.sigma_max[k])) & simd::lane_not(done);
          if (!simd::lane_any(maybe)) continue;
          const V alpha = simd::lane_min(V(T(max_alpha)), V(s.opacity[k]) * simd::lane_exp(-sigma));
          auto valid = maybe & (sigma >= V(T(0))) & (alpha >= V(T(alpha_threshold)));
          if (!simd::lane_any(valid)) continue;
          const V next_T = trans * (V(T(1)) - alpha);
          const auto stop = valid & (next_T <= V(T(transmittance_stop)));
          valid = valid & simd::lane_not(stop);
          const V w = simd::lane_select(valid, alpha * trans, V(T(0)));
          const T* ch = &s.channels[k * C];
          for (int c = 0; c < C; ++c) acc[c] = acc[c] + w * V(ch[c]);
          trans = simd::lane_select(valid, next_T, trans);
          n_contrib = simd::lane_select(valid, n_contrib + V(T(1)), n_contrib);
          last = simd::lane_select(valid, V(T(k + 1)), last);
          if (simd::lane_any(stop)) {
            done = done | stop;
            if (skips.early_exit && simd::lane_all(done)) break;
          }
        }
      }
      simd::lane_store(lanes_T, trans);
      simd::lane_store(lanes_n, n_contrib);
      simd::lane_store(lanes_last, last);
      for (int c = 0; c < C; ++c) simd::lane_store(lanes_acc[c], acc[c]);
      for (int l = 0; l < L && bx + l < x_end; ++l) {
        const std::int64_t pix = std::int64_t(py) * grid.width + bx + l;
        state.final_transmittance[pix] = lanes_T[l];
        state.n_contrib[pix] = std::int32_t(lanes_n[l]);
        state.last_entry[pix] = std::int32_t(lanes_last[l]);
        for (int c = 0; c < C; ++c) out_channels[pix * C + c] = lanes_acc[c][l] + lanes_T[l] * background[c];
      }
    }
  }
}

template <class V, class T>
void blend_tile_backward(const TileIntersections& ti, index_t tile, TileScratch<T>& s, int C, const T* background,
                         const BlendState<T>& state, const T* d_out_channels, const T* d_alpha) {
  constexpr int L = int(simd::lane_count<V>::value);
  const TileGrid& grid = ti.grid;
  const int tx = int(tile % grid.tiles_x), ty = int(tile / grid.tiles_x);
  const std::int64_t count = ti.tile_offsets[tile + 1] - ti.tile_offsets[tile];
  const int stride = entry_grad_fixed + C;
  std::fill(s.grads.begin(), s.grads.begin() + count * stride, T(0));
  const V iota = lane_offsets<V, T>();
  constexpr int max_channels = 64;
  V d_out[max_channels], behind[max_channels];
  alignas(64) T lanes_T[L], lanes_last[L], lanes_dA[L], lanes_d[max_channels][L];
  const int y_end = std::min(grid.height, (ty + 1) * tile_size);
  const int x_end = std::min(grid.width, (tx + 1) * tile_size);
  for (int py = ty * tile_size; py < y_end; ++py) {
    const V pyc = V(T(py) + T(pixel_centre_offset));
    for (int bx = tx * tile_size; bx < x_end; bx += L) {
      std::int32_t max_last = 0;
      for (int l = 0; l < L; ++l) {
        const bool inside = bx + l < x_end;
        const std::int64_t pix = std::int64_t(py) * grid.width + bx + l;
        lanes_T[l] = inside ? state.final_transmittance[pix] : T(1);
        lanes_last[l] = inside ? T(state.last_entry[pix]) : T(0);
        lanes_dA[l] = inside && d_alpha ? d_alpha[pix] : T(0);
        for (int c = 0; c < C; ++c) lanes_d[c][l] = inside ? d_out_channels[pix * C + c] : T(0);
        if (inside) max_last = std::max(max_last, state.last_entry[pix]);
      }
      if (max_last == 0) continue;
      const V pxc = iota + V(T(bx) + T(pixel_centre_offset));
      const V T_final = simd::lane_load<V>(lanes_T), last = simd::lane_load<V>(lanes_last);
      const V dA = simd::lane_load<V>(lanes_dA);
      V trans = T_final;
      for (int c = 0; c < C; ++c) {
        d_out[c] = simd::lane_load<V>(lanes_d[c]);
        behind[c] = T_final * V(background[c]);
      }
      for (std::int64_t k = max_last - 1; k >= 0; --k) {
        const V dx = V(s.u[k]) - pxc, dy = V(s.v[k]) - pyc;
        const V sigma = T(0.5) * (V(s.ca[k]) * dx * dx + V(s.cc[k]) * dy * dy) + V(s.cb[k]) * dx * dy;
        auto maybe = (sigma <= V(s.sigma_max[k])) & (V(T(k)) < last);
        if (!simd::lane_any(maybe)) continue;
        const V raw = V(s.opacity[k]) * simd::lane_exp(-sigma);
        const V alpha = simd::lane_min(V(T(max_alpha)), raw);
        const auto valid = maybe & (sigma >= V(T(0))) & (alpha >= V(T(alpha_threshold)));
        if (!simd::lane_any(valid)) continue;
        const V ra = V(T(1)) / (V(T(1)) - alpha);
        trans = simd::lane_select(valid, trans * ra, trans);
        const V vis = alpha * trans;
        const T* ch = &s.channels[k * C];
        T* gk = &s.grads[k * stride];
        V v_alpha = dA * T_final * ra;
        for (int c = 0; c < C; ++c) {
          gk[entry_grad_fixed + c] += simd::lane_sum(simd::lane_select(valid, vis * d_out[c], V(T(0))));
          v_alpha = v_alpha + (V(ch[c]) * trans - behind[c] * ra) * d_out[c];
          behind[c] = simd::lane_select(valid, behind[c] + V(ch[c]) * vis, behind[c]);
        }
        const auto unclamped = valid & (raw < V(T(max_alpha)));
        const V v_sigma = simd::lane_select(unclamped, -alpha * v_alpha, V(T(0)));
        const V v_opacity = simd::lane_select(unclamped, raw / V(s.opacity[k]) * v_alpha, V(T(0)));
        gk[0] += simd::lane_sum(v_sigma * (V(s.ca[k]) * dx + V(s.cb[k]) * dy));
        gk[1] += simd::lane_sum(v_sigma * (V(s.cb[k]) * dx + V(s.cc[k]) * dy));
        gk[2] += simd::lane_sum(T(0.5) * v_sigma * dx * dx);
        gk[3] += simd::lane_sum(v_sigma * dx * dy);
        gk[4] += simd::lane_sum(T(0.5) * v_sigma * dy * dy);
        gk[5] += simd::lane_sum(v_opacity);
      }
    }
  }
}

// Runs body(tile, worker) over all tiles; tiles are handed out dynamically (results do not depend on the order).
template <class Body>
void for_each_tile(index_t tiles, Body&& body) {
  std::atomic<index_t> next{0};
  const index_t workers = std::min<index_t>(global_pool().size(), std::max<index_t>(tiles, 1));
  parallel_for(workers, [&](index_t begin, index_t end, int worker) {
    for (index_t t; (t = next.fetch_add(1, std::memory_order_relaxed)) < tiles;) body(t, worker);
  });
}

}  // namespace detail

// Blends C channels of the visible Gaussians into out_channels [H*W*C] (background included) and fills state.
template <class T>
void rasterize_forward(const TileIntersections& ti, const Projection<T>* proj, const T* channels, int C,
                       const T* background, const RasterSkips& skips, RasterWorkspace<T>& ws, T* out_channels,
                       BlendState<T>& state) {
  require(C >= 1 && C <= 64, "raster: ", C, " channels; between 1 and 64 are supported");
  require(ti.max_tile_entries < (std::int64_t(1) << 24), "raster: a tile holds ", ti.max_tile_entries,
          " Gaussians, above the 2^24 limit");
  const std::size_t pixels = std::size_t(ti.grid.width) * std::size_t(ti.grid.height);
  state.final_transmittance.resize(pixels);
  state.last_entry.resize(pixels);
  state.n_contrib.resize(pixels);
  ws.scratch.resize(std::size_t(global_pool().size()));
  for (auto& s : ws.scratch) s.reserve(ti.max_tile_entries, C);
  const bool use_simd = simd::enabled();
  detail::for_each_tile(ti.grid.count(), [&](index_t tile, int worker) {
    TileScratch<T>& s = ws.scratch[std::size_t(worker)];
    detail::gather_tile(ti, tile, proj, channels, C, s);
    if (use_simd) detail::blend_tile_forward<simd::batch<T>, T>(ti, tile, s, C, background, skips, out_channels, state);
    else detail::blend_tile_forward<T, T>(ti, tile, s, C, background, skips, out_channels, state);
  });
}

// Adds into the per-Gaussian cotangents (grads [N, 6 + C], same record layout as an entry) from d_out_channels
// [H*W*C] and d_alpha [H*W] (may be null). Zero the caller's buffer once; this accumulates.
template <class T>
void rasterize_backward(const TileIntersections& ti, const Projection<T>* proj, const T* channels, int C,
                        const T* background, const BlendState<T>& state, const T* d_out_channels, const T* d_alpha,
                        RasterWorkspace<T>& ws, index_t n, T* gaussian_grads) {
  const int stride = entry_grad_fixed + C;
  ws.entry_grads.resize(ti.isect_gaussian.size() * std::size_t(stride));
  ws.scratch.resize(std::size_t(global_pool().size()));
  for (auto& s : ws.scratch) s.reserve(ti.max_tile_entries, C);
  const bool use_simd = simd::enabled();
  detail::for_each_tile(ti.grid.count(), [&](index_t tile, int worker) {
    TileScratch<T>& s = ws.scratch[std::size_t(worker)];
    const std::int64_t begin = ti.tile_offsets[tile], count = ti.tile_offsets[tile + 1] - begin;
    if (count == 0) return;
    detail::gather_tile(ti, tile, proj, channels, C, s);
    if (use_simd) detail::blend_tile_backward<simd::batch<T>, T>(ti, tile, s, C, background, state, d_out_channels, d_alpha);
    else detail::blend_tile_backward<T, T>(ti, tile, s, C, background, state, d_out_channels, d_alpha);
    for (std::int64_t k = 0; k < count; ++k) {
      const std::int64_t e = ti.tile_entries[begin + k];
      std::copy(&s.grads[k * stride], &s.grads[k * stride] + stride, &ws.entry_grads[e * stride]);
    }
  });
  // A Gaussian's entries are contiguous and in tile order: a fixed summation order for any thread count.
  parallel_for(n, [&](index_t gb, index_t ge, int) {
    for (index_t g = gb; g < ge; ++g) {
      const std::int64_t first = ti.gaussian_offsets[g], cnt = ti.gaussian_counts[g];
      T* out = gaussian_grads + g * stride;
      for (std::int64_t e = first; e < first + cnt; ++e)
        for (int j = 0; j < stride; ++j) out[j] += ws.entry_grads[e * stride + j];
    }
  });
}

}  // namespace raster
}  // namespace v0
}  // namespace flexsplat
