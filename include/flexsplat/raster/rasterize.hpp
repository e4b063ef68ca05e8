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

// What the blending kernels read of one Gaussian, computed once per render instead of once per tile.
template <class T>
struct SplatParams {
  T u, v, ca, cb, cc, opacity, sigma_max;
  T rx, ry;  // half-extents (pixels) of the region where sigma <= sigma_max can hold in float arithmetic
};

// Per-worker tile scratch: tile-local copies of the Gaussians (structure of arrays), the rows and batch columns
// each entry's extent reaches, one front-to-back entry list per pixel row, and per-entry gradient accumulators
// (one lane group per value).
template <class T>
struct TileScratch {
  std::vector<T> u, v, ca, cb, cc, opacity, sigma_max, rx, ry, channels, lane_grads;
  std::vector<std::int32_t> row_first, row_last;  // [count] tile-local rows reached (first > last: none)
  std::vector<std::int16_t> column_first, column_last;  // [count] batch columns reached
  std::int64_t row_stride = 0;                    // capacity of one row list (count + SIMD slack)
  std::vector<std::int32_t> row_size, row_list;   // row r's list: row_list[r * row_stride, + row_size[r])
  void reserve(std::int64_t n, int channel_count) {
    for (auto* a : {&u, &v, &ca, &cb, &cc, &opacity, &sigma_max, &rx, &ry})
      if (a->size() < std::size_t(n)) a->resize(std::size_t(n));
    if (channels.size() < std::size_t(n * channel_count)) channels.resize(std::size_t(n * channel_count));
    for (auto* a : {&row_first, &row_last})
      if (a->size() < std::size_t(n)) a->resize(std::size_t(n));
    for (auto* a : {&column_first, &column_last})
      if (a->size() < std::size_t(n)) a->resize(std::size_t(n));
    row_size.resize(tile_size);
  }
  bool covered(std::int64_t k) const { return row_first[std::size_t(k)] <= row_last[std::size_t(k)]; }
};

template <class T>
struct RasterWorkspace {
  std::vector<TileScratch<T>> scratch;  // one per worker
  // Per-Gaussian records (SplatParams fields, then the C channels), one or more whole cache lines each so a tile
  // gather misses once per entry; filled by rasterize_forward, reused by rasterize_backward.
  std::vector<T> splat_storage;
  std::size_t splat_offset = 0;  // first record, 64-byte aligned
  int splat_stride = 0, splat_channels = 0;
  index_t splat_count = -1;
  const T* splat_records() const { return splat_storage.data() + splat_offset; }
  std::vector<T> entry_grads;           // [E, 6 + C]
};

inline constexpr int splat_fields = 9;  // u, v, ca, cb, cc, opacity, sigma_max, rx, ry; then the channels

// Kernel parameters of one projected Gaussian. The extent is conservative for the float evaluation of sigma: its
// rounding error grows with the conic's condition number, so the margin does too.
template <class T>
void splat_params(const Projection<T>& p, SplatParams<T>& s) {
  s.u = p.u, s.v = p.v;
  s.ca = p.conic[0], s.cb = p.conic[1], s.cc = p.conic[2];
  s.opacity = p.opacity;
  // sigma above this gives alpha < alpha_threshold for certain (slack covers float rounding of exp)
  const double sigma_max = std::log(double(p.opacity) / alpha_threshold) * (1.0 + cull_slack_relative) + cull_slack_absolute;
  s.sigma_max = T(sigma_max);
  const double a = double(s.ca), b = double(s.cb), c = double(s.cc);
  const double det = a * c - b * b, trace = a + c;
  const double margin = 1.0 + cull_slack_relative + cull_slack_conditioning * trace * trace / det;
  const double r2 = 2.0 * std::max(double(s.sigma_max), 0.0);
  double rx = std::sqrt(r2 * c / det) * margin + cull_slack_absolute;
  double ry = std::sqrt(r2 * a / det) * margin + cull_slack_absolute;
  if (!(det > 0) || !(a > 0) || !(c > 0) || !std::isfinite(rx) || !std::isfinite(ry)) rx = ry = INFINITY;
  // rounded up so that the narrower type stays conservative
  auto round_up = [](double x) {
    const T narrow = T(x);
    return double(narrow) < x ? std::nextafter(narrow, T(INFINITY)) : narrow;
  };
  s.rx = round_up(rx), s.ry = round_up(ry);
}

namespace detail {

// Copies the Gaussians of one tile into s and builds, for each pixel row, the front-to-back list of the entries
// whose extent reaches it (and records the batch columns each entry reaches); lane_grad_stride > 0 also clears the
// backward accumulators of covered entries.
template <class V, class T>
void gather_tile(const TileIntersections& ti, index_t tile, const T* records, int stride, int C, TileScratch<T>& s,
                 int lane_grad_stride) {
  constexpr int L = int(simd::lane_count<V>::value);
  const TileGrid& grid = ti.grid;
  const int x_base = int(tile % grid.tiles_x) * tile_size, y_base = int(tile / grid.tiles_x) * tile_size;
  const int width_here = std::min(tile_size, grid.width - x_base), rows_here = std::min(tile_size, grid.height - y_base);
  const std::int64_t begin = ti.tile_offsets[tile], count = ti.tile_offsets[tile + 1] - begin;
  s.row_stride = count + simd::append_indices_slack;
  if (s.row_list.size() < std::size_t(s.row_stride * tile_size)) s.row_list.resize(std::size_t(s.row_stride * tile_size));
  if (lane_grad_stride > 0 && s.lane_grads.size() < std::size_t(count * lane_grad_stride * L))
    s.lane_grads.resize(std::size_t(count * lane_grad_stride * L));
  const std::int32_t* gaussians = ti.tile_gaussian.data() + begin;
  // Tile-local pixel ranges: values are clamped to +-(tile_size + 8) first (beyond that the range misses the tile),
  // so floor reduces to truncation of a positive value (exact, and cheap without SSE4.1 rounding instructions).
  auto floor_local = [](double x) {
    constexpr int reach = tile_size + 8;
    return int(std::min(std::max(x, -double(reach)), double(reach)) + 2 * reach) - 2 * reach;
  };
  // Records are read in tile order (prefetched a few entries ahead: each is a likely cache miss).
  constexpr std::int64_t prefetch_distance = 24;
  for (std::int64_t k = 0; k < count; ++k) {
    if (k + prefetch_distance < count) __builtin_prefetch(records + std::int64_t(gaussians[k + prefetch_distance]) * stride);
    const T* p = records + std::int64_t(gaussians[k]) * stride;
    s.u[k] = p[0], s.v[k] = p[1];
    s.ca[k] = p[2], s.cb[k] = p[3], s.cc[k] = p[4];
    s.opacity[k] = p[5];
    s.sigma_max[k] = p[6];
    s.rx[k] = p[7], s.ry[k] = p[8];
    for (int c = 0; c < C; ++c) s.channels[k * C + c] = p[splat_fields + c];
    // Pixel x is in range when |x + 0.5 - u| <= rx.
    const double u = double(p[0]) - pixel_centre_offset - x_base, rx = double(p[7]);
    const double v = double(p[1]) - pixel_centre_offset - y_base, ry = double(p[8]);
    const int x0 = std::max(0, -floor_local(rx - u)), x1 = std::min(width_here - 1, floor_local(u + rx));
    const int y0 = std::max(0, -floor_local(ry - v)), y1 = std::min(rows_here - 1, floor_local(v + ry));
    const bool reached = x0 <= x1 && y0 <= y1;
    s.row_first[k] = reached ? y0 : 1;
    s.row_last[k] = reached ? y1 : 0;
    s.column_first[k] = std::int16_t(x0 / L), s.column_last[k] = std::int16_t(x1 / L);
    if (lane_grad_stride > 0 && reached)
      std::fill_n(&s.lane_grads[std::size_t(k * lane_grad_stride * L)], lane_grad_stride * L, T(0));
  }
  for (int r = 0; r < rows_here; ++r)
    s.row_size[r] = std::int32_t(simd::append_indices_in_range(s.row_first.data(), s.row_last.data(), count, r,
                                                               s.row_list.data() + r * s.row_stride));
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
  const V iota = lane_offsets<V, T>();
  constexpr int max_channels = 64;
  V acc[max_channels];
  alignas(64) T lanes_T[L], lanes_n[L], lanes_last[L], lanes_acc[max_channels][L];
  const int y_end = std::min(grid.height, (ty + 1) * tile_size);
  const int x_end = std::min(grid.width, (tx + 1) * tile_size);
  for (int py = ty * tile_size; py < y_end; ++py) {
    const V pyc = V(T(py) + T(pixel_centre_offset));
    for (int bx = tx * tile_size; bx < x_end; bx += L) {
      const int row = py - ty * tile_size, column = (bx - tx * tile_size) / L;
      const std::int32_t* list = s.row_list.data() + row * s.row_stride;
      const std::int32_t list_size = s.row_size[row];
      const V px = iota + V(T(bx));
      const V pxc = px + V(T(pixel_centre_offset));
      auto done = px >= V(T(grid.width));
      V trans = V(T(1)), n_contrib = V(T(0)), last = V(T(0));
      for (int c = 0; c < C; ++c) acc[c] = V(T(0));
      for (std::int32_t i = 0; i < list_size; ++i) {
        const std::int32_t k = list[i];
        if (L < tile_size && (column < s.column_first[k] || column > s.column_last[k])) continue;
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
        const T* ch = &s.channels[std::size_t(k) * C];
        for (int c = 0; c < C; ++c) acc[c] = acc[c] + w * V(ch[c]);
        trans = simd::lane_select(valid, next_T, trans);
        n_contrib = simd::lane_select(valid, n_contrib + V(T(1)), n_contrib);
        last = simd::lane_select(valid, V(T(k + 1)), last);
        if (simd::lane_any(stop)) {
          done = done | stop;
          if (skips.early_exit && simd::lane_all(done)) break;
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

// Adds into the per-entry lane accumulators of s (stride 6 + C values of L lanes per entry).
template <class V, class T>
void blend_tile_backward(const TileIntersections& ti, index_t tile, TileScratch<T>& s, int C, const T* background,
                         const BlendState<T>& state, const T* d_out_channels, const T* d_alpha) {
  constexpr int L = int(simd::lane_count<V>::value);
  const TileGrid& grid = ti.grid;
  const int tx = int(tile % grid.tiles_x), ty = int(tile / grid.tiles_x);
  const int stride = entry_grad_fixed + C;
  const V iota = lane_offsets<V, T>();
  constexpr int max_channels = 64;
  V d_out[max_channels], behind[max_channels];
  alignas(64) T lanes_T[L], lanes_last[L], lanes_dA[L], lanes_d[max_channels][L];
  const int y_end = std::min(grid.height, (ty + 1) * tile_size);
  const int x_end = std::min(grid.width, (tx + 1) * tile_size);
  auto add_lanes = [](T* dst, const V& value) { simd::lane_store(dst, simd::lane_load<V>(dst) + value); };
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
      const int row = py - ty * tile_size, column = (bx - tx * tile_size) / L;
      const std::int32_t* list = s.row_list.data() + row * s.row_stride;
      std::int32_t list_end = s.row_size[row];
      while (list_end > 0 && list[list_end - 1] >= max_last) --list_end;  // behind every lane's last contributor
      const V pxc = iota + V(T(bx) + T(pixel_centre_offset));
      const V T_final = simd::lane_load<V>(lanes_T), last = simd::lane_load<V>(lanes_last);
      const V dA = simd::lane_load<V>(lanes_dA);
      V trans = T_final;
      for (int c = 0; c < C; ++c) {
        d_out[c] = simd::lane_load<V>(lanes_d[c]);
        behind[c] = T_final * V(background[c]);
      }
      for (std::int32_t i = list_end - 1; i >= 0; --i) {
        const std::int32_t k = list[i];
        if (L < tile_size && (column < s.column_first[k] || column > s.column_last[k])) continue;
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
        const T* ch = &s.channels[std::size_t(k) * C];
        T* gk = &s.lane_grads[std::size_t(k) * stride * L];
        V v_alpha = dA * T_final * ra;
        for (int c = 0; c < C; ++c) {
          add_lanes(gk + (entry_grad_fixed + c) * L, simd::lane_select(valid, vis * d_out[c], V(T(0))));
          v_alpha = v_alpha + (V(ch[c]) * trans - behind[c] * ra) * d_out[c];
          behind[c] = simd::lane_select(valid, behind[c] + V(ch[c]) * vis, behind[c]);
        }
        const auto unclamped = valid & (raw < V(T(max_alpha)));
        const V v_sigma = simd::lane_select(unclamped, -alpha * v_alpha, V(T(0)));
        const V v_opacity = simd::lane_select(unclamped, raw / V(s.opacity[k]) * v_alpha, V(T(0)));
        add_lanes(gk + 0 * L, v_sigma * (V(s.ca[k]) * dx + V(s.cb[k]) * dy));
        add_lanes(gk + 1 * L, v_sigma * (V(s.cb[k]) * dx + V(s.cc[k]) * dy));
        add_lanes(gk + 2 * L, T(0.5) * v_sigma * dx * dx);
        add_lanes(gk + 3 * L, v_sigma * dx * dy);
        add_lanes(gk + 4 * L, T(0.5) * v_sigma * dy * dy);
        add_lanes(gk + 5 * L, v_opacity);
      }
    }
  }
}

// Runs body(tile, worker) over all tiles; tiles are handed out dynamically (results do not depend on the order).
template <class Body>
void for_each_tile(index_t tiles, ThreadPool& pool, Body&& body) {
  std::atomic<index_t> next{0};
  const index_t workers = std::min<index_t>(pool.size(), std::max<index_t>(tiles, 1));
  parallel_for(workers, [&](index_t begin, index_t end, int worker) {
    for (index_t t; (t = next.fetch_add(1, std::memory_order_relaxed)) < tiles;) body(t, worker);
  }, pool);
}

}  // namespace detail

// Sizes the per-Gaussian record store of ws for n Gaussians of C channels (records are then written by
// write_splat_record at splat_records() + g * splat_stride).
template <class T>
void begin_splats(index_t n, int C, RasterWorkspace<T>& ws) {
  constexpr int line = int(64 / sizeof(T));
  const int stride = (splat_fields + C + line - 1) / line * line;
  ws.splat_storage.resize(std::size_t(n * stride + line));
  const auto address = reinterpret_cast<std::uintptr_t>(ws.splat_storage.data());
  ws.splat_offset = ((64 - address % 64) % 64) / sizeof(T);
  ws.splat_stride = stride, ws.splat_channels = C, ws.splat_count = n;
}

template <class T>
void write_splat_record(const Projection<T>& p, const T* channels, int C, T* record) {
  SplatParams<T> sp;
  splat_params(p, sp);
  record[0] = sp.u, record[1] = sp.v, record[2] = sp.ca, record[3] = sp.cb, record[4] = sp.cc;
  record[5] = sp.opacity, record[6] = sp.sigma_max, record[7] = sp.rx, record[8] = sp.ry;
  for (int c = 0; c < C; ++c) record[splat_fields + c] = channels[c];
}

// Kernel parameters of every Gaussian that has tile entries (the others are never read).
template <class T>
void prepare_splats(const TileIntersections& ti, const Projection<T>* proj, const T* channels, int C,
                    RasterWorkspace<T>& ws, ThreadPool& pool) {
  const index_t n = index_t(ti.gaussian_counts.size());
  begin_splats(n, C, ws);
  T* records = ws.splat_storage.data() + ws.splat_offset;
  parallel_for(n, [&](index_t begin, index_t end, int) {
    for (index_t g = begin; g < end; ++g)
      if (ti.gaussian_counts[g] != 0) write_splat_record(proj[g], channels + g * C, C, records + g * ws.splat_stride);
  }, pool);
}

// rasterize_forward for a workspace whose records (begin_splats, write_splat_record) already hold every Gaussian
// that has tile entries.
template <class T>
void rasterize_forward_prepared(const TileIntersections& ti, int C, const T* background, const RasterSkips& skips,
                                RasterWorkspace<T>& ws, T* out_channels, BlendState<T>& state,
                                ThreadPool& pool = global_pool()) {
  require(C >= 1 && C <= 64, "raster: ", C, " channels; between 1 and 64 are supported");
  require(ti.max_tile_entries < (std::int64_t(1) << 24), "raster: a tile holds ", ti.max_tile_entries,
          " Gaussians, above the 2^24 limit");
  require(ws.splat_count == index_t(ti.gaussian_counts.size()) && ws.splat_channels == C,
          "raster: the workspace's Gaussian records do not match these intersections");
  const std::size_t pixels = std::size_t(ti.grid.width) * std::size_t(ti.grid.height);
  state.final_transmittance.resize(pixels);
  state.last_entry.resize(pixels);
  state.n_contrib.resize(pixels);
  ws.scratch.resize(std::size_t(pool.size()));
  for (auto& s : ws.scratch) s.reserve(ti.max_tile_entries, C);
  const bool use_simd = simd::enabled() && !skips.force_scalar;
  detail::for_each_tile(ti.grid.count(), pool, [&](index_t tile, int worker) {
    TileScratch<T>& s = ws.scratch[std::size_t(worker)];
    if (use_simd) {
      detail::gather_tile<simd::batch<T>, T>(ti, tile, ws.splat_records(), ws.splat_stride, C, s, 0);
      detail::blend_tile_forward<simd::batch<T>, T>(ti, tile, s, C, background, skips, out_channels, state);
    } else {
      detail::gather_tile<T, T>(ti, tile, ws.splat_records(), ws.splat_stride, C, s, 0);
      detail::blend_tile_forward<T, T>(ti, tile, s, C, background, skips, out_channels, state);
    }
  });
}

// Blends C channels of the visible Gaussians into out_channels [H*W*C] (background included) and fills state.
template <class T>
void rasterize_forward(const TileIntersections& ti, const Projection<T>* proj, const T* channels, int C,
                       const T* background, const RasterSkips& skips, RasterWorkspace<T>& ws, T* out_channels,
                       BlendState<T>& state, ThreadPool& pool = global_pool()) {
  require(C >= 1 && C <= 64, "raster: ", C, " channels; between 1 and 64 are supported");
  prepare_splats(ti, proj, channels, C, ws, pool);
  rasterize_forward_prepared(ti, C, background, skips, ws, out_channels, state, pool);
}

// Adds into the per-Gaussian cotangents (grads [N, 6 + C], same record layout as an entry) from d_out_channels
// [H*W*C] and d_alpha [H*W] (may be null). Zero the caller's buffer once; this accumulates.
template <class T>
void rasterize_backward(const TileIntersections& ti, const Projection<T>* proj, const T* channels, int C,
                        const T* background, const BlendState<T>& state, const T* d_out_channels, const T* d_alpha,
                        const RasterSkips& skips, RasterWorkspace<T>& ws, index_t n, T* gaussian_grads,
                        ThreadPool& pool = global_pool()) {
  const int stride = entry_grad_fixed + C;
  ws.entry_grads.resize(std::size_t(ti.total_entries) * std::size_t(stride));
  ws.scratch.resize(std::size_t(pool.size()));
  for (auto& s : ws.scratch) s.reserve(ti.max_tile_entries, C);
  if (ws.splat_count != index_t(ti.gaussian_counts.size()) || ws.splat_channels != C)
    prepare_splats(ti, proj, channels, C, ws, pool);
  const bool use_simd = simd::enabled() && !skips.force_scalar;
  auto run_tile = [&](auto lanes_tag, index_t tile, TileScratch<T>& s) {
    using V = decltype(lanes_tag);
    constexpr int L = int(simd::lane_count<V>::value);
    const std::int64_t begin = ti.tile_offsets[tile], count = ti.tile_offsets[tile + 1] - begin;
    detail::gather_tile<V, T>(ti, tile, ws.splat_records(), ws.splat_stride, C, s, stride);
    detail::blend_tile_backward<V, T>(ti, tile, s, C, background, state, d_out_channels, d_alpha);
    for (std::int64_t k = 0; k < count; ++k) {
      T* record = &ws.entry_grads[std::size_t(ti.tile_entries[begin + k]) * std::size_t(stride)];
      if (!s.covered(k)) {
        std::fill_n(record, stride, T(0));
        continue;
      }
      const T* lanes = &s.lane_grads[std::size_t(k * stride * L)];
      for (int j = 0; j < stride; ++j) record[j] = simd::lane_sum(simd::lane_load<V>(lanes + j * L));
    }
  };
  detail::for_each_tile(ti.grid.count(), pool, [&](index_t tile, int worker) {
    TileScratch<T>& s = ws.scratch[std::size_t(worker)];
    if (ti.tile_offsets[tile + 1] == ti.tile_offsets[tile]) return;
    if (use_simd) run_tile(simd::batch<T>{}, tile, s);
    else run_tile(T{}, tile, s);
  });
  // A Gaussian's entries are contiguous and in tile order: a fixed summation order for any thread count.
  parallel_for(n, [&](index_t gb, index_t ge, int) {
    for (index_t g = gb; g < ge; ++g) {
      const std::int64_t first = ti.gaussian_offsets[g], cnt = ti.gaussian_counts[g];
      T* out = gaussian_grads + g * stride;
      for (std::int64_t e = first; e < first + cnt; ++e)
        for (int j = 0; j < stride; ++j) out[j] += ws.entry_grads[e * stride + j];
    }
  }, pool);
}

}  // namespace raster
}  // namespace v0
}  // namespace flexsplat
