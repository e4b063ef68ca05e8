#pragma once
// Front-to-back alpha blending of C channels per pixel over the per-tile lists, and its adjoint (back to front,
// transmittance recovered by division). Threads take whole tiles; a tile's pixel state lives in per-worker buffers
// and each entry of the tile list visits only the pixel batches its extent reaches (SIMD lanes = neighbouring pixels
// of a row). Backward writes one gradient record per (tile, Gaussian) entry, reduced per Gaussian in a fixed order,
// so results do not depend on the number of threads.
#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <type_traits>
#include <utility>
#include <vector>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/inline.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/simd.hpp"
#include "flexsplat/core/simd_dispatch.hpp"
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

// Per-worker state of the tile being blended: one slot of L lanes per pixel batch (row-major, tile_size / L batches
// per row); channel c of slot j at [c * tile_pixels + j * L].
template <class T>
struct TileState {
  static constexpr int tile_pixels = tile_size * tile_size;
  // Cache-line aligned: every lane batch is one whole line, so loads never split lines and stores forward to them.
  using Buffer = std::vector<T, AlignedAllocator<T>>;
  Buffer transmittance, n_contrib, last, done, final_transmittance, d_alpha, channels, d_channels, behind;
  Buffer pending;  // backward: lane vectors of the gradient records of up to 16 entries, reduced together
  std::vector<std::uint8_t> batch_done;
  void reserve(int channel_count) {
    for (auto* a : {&transmittance, &n_contrib, &last, &done, &final_transmittance, &d_alpha}) a->resize(tile_pixels);
    for (auto* a : {&channels, &d_channels, &behind}) a->resize(std::size_t(tile_pixels) * std::size_t(channel_count));
    pending.resize(std::size_t(6 + channel_count) * 16 * 16);
    batch_done.resize(tile_pixels);
  }
};

template <class T>
struct RasterWorkspace {
  std::vector<TileState<T>> scratch;  // one per worker
  // Per-Gaussian records (the splat_fields values, then the C channels), one or more whole cache lines each so a
  // tile entry misses once; filled by render_forward / rasterize_forward, reused by rasterize_backward.
  std::vector<T> splat_storage;
  std::size_t splat_offset = 0;  // first record, 64-byte aligned
  int splat_stride = 0, splat_channels = 0;
  index_t splat_count = -1;
  const T* splat_records() const { return splat_storage.data() + splat_offset; }
  std::vector<T> entry_grads;           // [E, 6 + C]
};

// u, v, ca, cb, cc, opacity, sigma_max, then the image pixels the extent reaches (first x, last x, first y, last y;
// first > last: none), then the channels
inline constexpr int splat_fields = 11;

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

// Tile-local pixel rectangle that an entry's conservative extent reaches (x1 < x0 or y1 < y0: none).
struct EntryPixels {
  int x0, x1, y0, y1;
  bool empty() const { return x1 < x0 || y1 < y0; }
};

template <class T>
FLEXSPLAT_ALWAYS_INLINE EntryPixels entry_pixels(const T* record, int x_base, int y_base, int width_here,
                                                 int rows_here) {
  return {std::max(0, int(record[7]) - x_base), std::min(width_here - 1, int(record[8]) - x_base),
          std::max(0, int(record[9]) - y_base), std::min(rows_here - 1, int(record[10]) - y_base)};
}

template <class V, class T>
V lane_offsets() {
  alignas(64) T idx[simd::lane_count<V>::value];
  for (std::size_t i = 0; i < simd::lane_count<V>::value; ++i) idx[i] = T(i);
  return simd::lane_load<V>(idx);
}

// Geometry of one tile: its pixel origin and the pixels inside the image.
struct TileFrame {
  int x_base, y_base, width_here, rows_here;
  TileFrame(const TileGrid& grid, index_t tile)
      : x_base(int(tile % grid.tiles_x) * tile_size), y_base(int(tile / grid.tiles_x) * tile_size),
        width_here(std::min(tile_size, grid.width - x_base)), rows_here(std::min(tile_size, grid.height - y_base)) {}
};

// sigma of one entry over a column of batches (lanes = pixels of a row): the x terms once per column, then one
// multiply-add per row. The forward and backward kernels both use it, so they see the same contributions.
template <class V, class T>
struct ColumnSigma {
  V sigma_x, cross;
  T v, half_cc;
  FLEXSPLAT_ALWAYS_INLINE ColumnSigma(const T* record, const V& dx)
      : sigma_x(T(0.5) * V(record[2]) * dx * dx), cross(V(record[3]) * dx), v(record[1]),
        half_cc(T(0.5) * record[4]) {}
  FLEXSPLAT_ALWAYS_INLINE T dy(int pixel_row) const { return v - (T(pixel_row) + T(pixel_centre_offset)); }
  FLEXSPLAT_ALWAYS_INLINE V sigma(T dy) const {
    return simd::lane_fma(cross, V(dy), sigma_x + V(half_cc * dy * dy));
  }
};

// Blends one tile front to back; V is T (scalar path) or simd::batch<T>. Entries visit the batches their extent
// reaches; a pixel sees the tile's entries in list order, so its result does not depend on the visiting order.
template <class V, class T, class RowSink>
void blend_tile_forward(const TileIntersections& ti, index_t tile, const T* records, int record_stride,
                        TileState<T>& st, int C, const T* background, const RasterSkips& skips, BlendState<T>& state,
                        RowSink& sink) {
  constexpr int L = int(simd::lane_count<V>::value), batches_per_row = tile_size / L;
  constexpr int P = TileState<T>::tile_pixels;
  static_assert(tile_size % L == 0, "tile rows must split into whole batches");
  const TileGrid& grid = ti.grid;
  const TileFrame f(grid, tile);
  const std::int64_t begin = ti.tile_offsets[tile], count = ti.tile_offsets[tile + 1] - begin;
  const std::int32_t* gaussians = ti.tile_gaussian.data() + begin;
  const V iota = lane_offsets<V, T>();
  const int used_batches = (f.width_here + L - 1) / L;
  int active_batches = used_batches * f.rows_here;
  for (int j = 0; j < P / L; ++j) {
    const int column = j % batches_per_row;
    const V inside = simd::lane_select(iota + V(T(column * L)) < V(T(f.width_here)), V(T(0)), V(T(1)));
    simd::lane_store(&st.done[j * L], inside);
    simd::lane_store(&st.transmittance[j * L], V(T(1)));
    simd::lane_store(&st.n_contrib[j * L], V(T(0)));
    simd::lane_store(&st.last[j * L], V(T(0)));
    for (int c = 0; c < C; ++c) simd::lane_store(&st.channels[c * P + j * L], V(T(0)));
    st.batch_done[j] = 0;
  }
  constexpr std::int64_t prefetch_distance = 8;
  // Raw pointers: through st the compiler reloads every buffer's address after each store.
  T* const trans_p = st.transmittance.data();
  T* const n_p = st.n_contrib.data();
  T* const last_p = st.last.data();
  T* const done_p = st.done.data();
  T* const chan_p = st.channels.data();
  std::uint8_t* const batch_done_p = st.batch_done.data();
  const bool early_exit = skips.early_exit;
  for (std::int64_t k = 0; k < count; ++k) {
    if (k + prefetch_distance < count)
      __builtin_prefetch(records + std::int64_t(gaussians[k + prefetch_distance]) * record_stride);
    const T* r = records + std::int64_t(gaussians[k]) * record_stride;
    const EntryPixels px = entry_pixels(r, f.x_base, f.y_base, f.width_here, f.rows_here);
    if (px.empty()) continue;
    const V u = V(r[0]), opacity = V(r[5]), smax = V(r[6]);
    const T* ch = r + splat_fields;
    const V entry_index = V(T(k + 1));
    for (int column = px.x0 / L; column <= px.x1 / L; ++column) {
      const ColumnSigma<V, T> column_sigma(r, u - (iota + V(T(f.x_base + column * L) + T(pixel_centre_offset))));
      for (int row = px.y0; row <= px.y1; ++row) {
        const int j = row * batches_per_row + column;
        if (early_exit && batch_done_p[j]) continue;
        const V sigma = column_sigma.sigma(column_sigma.dy(f.y_base + row));
        const auto done = simd::lane_load<V>(&done_p[j * L]) != V(T(0));
        auto maybe = (sigma <= smax) & simd::lane_not(done);
        if (!simd::lane_any(maybe)) continue;
        const V alpha = simd::lane_min(V(T(max_alpha)), opacity * simd::lane_exp_blend(-sigma));
        // No branch on "any lane valid": a lane that may reach the threshold almost always does.
        auto valid = maybe & (sigma >= V(T(0))) & (alpha >= V(T(alpha_threshold)));
        const V trans = simd::lane_load<V>(&trans_p[j * L]);
        const V next_T = trans * (V(T(1)) - alpha);
        const auto stop = valid & (next_T <= V(T(transmittance_stop)));
        valid = valid & simd::lane_not(stop);
        const V w = simd::lane_select(valid, alpha * trans, V(T(0)));
        for (int c = 0; c < C; ++c) {
          T* acc = &chan_p[c * P + j * L];
          simd::lane_store(acc, simd::lane_load<V>(acc) + w * V(ch[c]));
        }
        simd::lane_store(&trans_p[j * L], simd::lane_select(valid, next_T, trans));
        // Written as full stores (an add, and a max: entry indices grow along the list), not select-into-memory,
        // which compiles to masked stores that the next entry's loads cannot be forwarded from.
        const V one_if_valid = simd::lane_select(valid, V(T(1)), V(T(0)));
        simd::lane_store(&n_p[j * L], simd::lane_load<V>(&n_p[j * L]) + one_if_valid);
        simd::lane_store(&last_p[j * L], simd::lane_max(simd::lane_load<V>(&last_p[j * L]), entry_index * one_if_valid));
        // Stored every time: a branch on "any lane stopped" is taken at random and mispredicts (rasterize 9.2 ->
        // 8.5 ms without it); "every lane done" happens once per batch, so its branch predicts well.
        const auto now_done = done | stop;
        simd::lane_store(&done_p[j * L], simd::lane_select(now_done, V(T(1)), V(T(0))));
        if (simd::lane_all(now_done)) {
          batch_done_p[j] = 1;
          --active_batches;
        }
      }
    }
    if (skips.early_exit && active_batches == 0) break;
  }
  // Out: background added in place (whole batches as vectors, the image's right edge lane by lane), the state
  // backward needs, then each finished row to the sink.
  for (int row = 0; row < f.rows_here; ++row) {
    const std::int64_t pix0 = std::int64_t(f.y_base + row) * grid.width + f.x_base;
    for (int x = 0; x < f.width_here; x += L) {
      const int i = row * tile_size + x;
      if (x + L <= f.width_here) {
        const V trans = simd::lane_load<V>(&st.transmittance[i]);
        simd::lane_store(&state.final_transmittance[pix0 + x], trans);
        for (int c = 0; c < C; ++c) {
          T* acc = &st.channels[c * P + i];
          simd::lane_store(acc, simd::lane_load<V>(acc) + trans * V(background[c]));
        }
      } else {
        for (int l = x; l < f.width_here; ++l) {
          const T trans = st.transmittance[row * tile_size + l];
          state.final_transmittance[pix0 + l] = trans;
          for (int c = 0; c < C; ++c) st.channels[c * P + row * tile_size + l] += trans * background[c];
        }
      }
    }
    for (int x = 0; x < f.width_here; ++x) {
      state.n_contrib[pix0 + x] = std::int32_t(st.n_contrib[row * tile_size + x]);
      state.last_entry[pix0 + x] = std::int32_t(st.last[row * tile_size + x]);
    }
    sink(pix0, f.width_here, &st.channels[row * tile_size], P, &st.transmittance[row * tile_size],
         &st.n_contrib[row * tile_size]);
  }
}

// Writes the gradient record (6 + C values) of every entry of the tile into entry_grads at the entry's emission
// slot, visiting entries back to front.
// cotangents(p0, count, d_channels, plane, d_alpha) writes the output cotangents of pixels [p0, p0 + count) of one
// image row: channel c of pixel p0 + x at d_channels[c * plane + x], d(alpha) at d_alpha[x].
template <class V, class T, int FixedChannels = 0, class CotangentRows>
void blend_tile_backward(const TileIntersections& ti, index_t tile, const T* records, int record_stride,
                         TileState<T>& st, int channel_count, const T* background, const BlendState<T>& state,
                         const CotangentRows& cotangents, T* entry_grads) {
  // A compile-time channel count keeps the per-channel sums in registers.
  const int C = FixedChannels > 0 ? FixedChannels : channel_count;
  constexpr int L = int(simd::lane_count<V>::value), batches_per_row = tile_size / L;
  constexpr int P = TileState<T>::tile_pixels;
  constexpr int max_channels = 64;
  const TileGrid& grid = ti.grid;
  const TileFrame f(grid, tile);
  const std::int64_t begin = ti.tile_offsets[tile], count = ti.tile_offsets[tile + 1] - begin;
  const std::int32_t* gaussians = ti.tile_gaussian.data() + begin;
  const int stride = entry_grad_fixed + C;
  const V iota = lane_offsets<V, T>();
  std::int32_t max_last = 0;
  for (int row = 0; row < tile_size; ++row) {
    const std::int64_t pix0 = std::int64_t(f.y_base + row) * grid.width + f.x_base;
    const int width = row < f.rows_here ? f.width_here : 0;  // pixels of this tile row inside the image
    if (width > 0) cotangents(pix0, width, &st.d_channels[row * tile_size], P, &st.d_alpha[row * tile_size]);
    for (int x = width; x < tile_size; ++x) {
      st.d_alpha[row * tile_size + x] = T(0);
      for (int c = 0; c < C; ++c) st.d_channels[c * P + row * tile_size + x] = T(0);
    }
    for (int x0 = 0; x0 < tile_size; x0 += L) {
      const int i0 = row * tile_size + x0;
      if (x0 + L <= width) {  // whole batch inside the image
        const V t_final = simd::lane_load<V>(&state.final_transmittance[pix0 + x0]);
        simd::lane_store(&st.final_transmittance[i0], t_final);
        simd::lane_store(&st.transmittance[i0], t_final);
        for (int c = 0; c < C; ++c) simd::lane_store(&st.behind[c * P + i0], t_final * V(background[c]));
        continue;
      }
      for (int x = x0; x < x0 + L; ++x) {  // the image's right and bottom edges
        const int i = row * tile_size + x;
        const T t_final = x < width ? state.final_transmittance[pix0 + x] : T(1);
        st.final_transmittance[i] = st.transmittance[i] = t_final;
        for (int c = 0; c < C; ++c) st.behind[c * P + i] = t_final * background[c];
      }
    }
    for (int x = 0; x < tile_size; ++x) {
      st.last[row * tile_size + x] = x < width ? T(state.last_entry[pix0 + x]) : T(0);
      if (x < width) max_last = std::max(max_last, state.last_entry[pix0 + x]);
    }
  }
  constexpr std::int64_t prefetch_distance = 8;
  V grad[entry_grad_fixed + max_channels];
  // The lane sums of L entries' records are taken together: L x L transposes (simd::load_columns) and a pairwise
  // sum, instead of a chain of L - 1 dependent scalar adds per value.
  static_assert(L <= 16, "TileState::pending holds 16 x 16 values per record field");
  T* const pending = st.pending.data();
  T* pending_out[L];
  int n_pending = 0;
  auto flush = [&] {
    for (int j = 0; j < stride; ++j) {
      const T* rows[L];
      for (int e = 0; e < L; ++e) rows[e] = pending + (std::size_t(j) * L + std::size_t(std::min(e, n_pending - 1))) * L;
      V cols[L];
      simd::load_columns<V, T>(rows, L, cols);
      for (int w = L / 2; w >= 1; w /= 2)
        for (int i = 0; i < w; ++i) cols[i] = cols[i] + cols[i + w];
      alignas(64) T sums[L];
      simd::lane_store(sums, cols[0]);
      for (int e = 0; e < n_pending; ++e) pending_out[e][j] = sums[e];
    }
    n_pending = 0;
  };
  // Raw pointers: through st the compiler reloads every buffer's address after each store (as in the forward).
  T* const transmittance_p = st.transmittance.data();
  const T* const last_p = st.last.data();
  const T* const final_transmittance_p = st.final_transmittance.data();
  const T* const d_alpha_p = st.d_alpha.data();
  const T* const d_channels_p = st.d_channels.data();
  T* const behind_p = st.behind.data();
  // Entries behind every pixel's last contributor get a zero record without their splat record being read.
  const std::int64_t live = std::min<std::int64_t>(count, max_last);
  for (std::int64_t k = count - 1; k >= live; --k)
    std::fill_n(entry_grads + std::int64_t(ti.tile_entries[begin + k]) * stride, stride, T(0));
  for (std::int64_t k = live - 1; k >= 0; --k) {
    if (k - prefetch_distance >= 0)
      __builtin_prefetch(records + std::int64_t(gaussians[k - prefetch_distance]) * record_stride);
    T* record_out = entry_grads + std::int64_t(ti.tile_entries[begin + k]) * stride;
    const T* r = records + std::int64_t(gaussians[k]) * record_stride;
    const EntryPixels px = entry_pixels(r, f.x_base, f.y_base, f.width_here, f.rows_here);
    if (px.empty()) {  // reaches no pixel
      std::fill_n(record_out, stride, T(0));
      continue;
    }
    for (int j = 0; j < stride; ++j) grad[j] = V(T(0));
    const V u = V(r[0]), ca = V(r[2]), cb = V(r[3]), cc = V(r[4]), opacity = V(r[5]), smax = V(r[6]);
    const T* ch = r + splat_fields;
    const V entry_position = V(T(k));
    for (int column = px.x0 / L; column <= px.x1 / L; ++column) {
      const V dx = u - (iota + V(T(f.x_base + column * L) + T(pixel_centre_offset)));
      const ColumnSigma<V, T> column_sigma(r, dx);
      for (int row = px.y0; row <= px.y1; ++row) {
        const int j = row * batches_per_row + column;
        const T dy_row = column_sigma.dy(f.y_base + row);
        const V dy = V(dy_row);
        const V sigma = column_sigma.sigma(dy_row);
        auto maybe = (sigma <= smax) & (entry_position < simd::lane_load<V>(&last_p[j * L]));
        if (!simd::lane_any(maybe)) continue;
        const V e = simd::lane_exp_blend(-sigma), raw = opacity * e;
        const V alpha = simd::lane_min(V(T(max_alpha)), raw);
        // No branch on "any lane valid", as in the forward kernel.
        const auto valid = maybe & (sigma >= V(T(0))) & (alpha >= V(T(alpha_threshold)));
        const V ra = V(T(1)) / (V(T(1)) - alpha);
        const V trans = simd::lane_select(valid, simd::lane_load<V>(&transmittance_p[j * L]) * ra,
                                          simd::lane_load<V>(&transmittance_p[j * L]));
        simd::lane_store(&transmittance_p[j * L], trans);
        const V vis = alpha * trans;
        const V t_final = simd::lane_load<V>(&final_transmittance_p[j * L]);
        V v_alpha = simd::lane_load<V>(&d_alpha_p[j * L]) * t_final * ra;
        for (int c = 0; c < C; ++c) {
          const V d_out = simd::lane_load<V>(&d_channels_p[c * P + j * L]);
          T* behind_ptr = &behind_p[c * P + j * L];
          const V behind = simd::lane_load<V>(behind_ptr);
          grad[entry_grad_fixed + c] = grad[entry_grad_fixed + c] + simd::lane_select(valid, vis * d_out, V(T(0)));
          v_alpha = v_alpha + (V(ch[c]) * trans - behind * ra) * d_out;
          simd::lane_store(behind_ptr, simd::lane_select(valid, behind + V(ch[c]) * vis, behind));
        }
        const auto unclamped = valid & (raw < V(T(max_alpha)));
        const V v_sigma = simd::lane_select(unclamped, -alpha * v_alpha, V(T(0)));
        const V v_opacity = simd::lane_select(unclamped, e * v_alpha, V(T(0)));
        grad[0] = grad[0] + v_sigma * (ca * dx + cb * dy);
        grad[1] = grad[1] + v_sigma * (cb * dx + cc * dy);
        grad[2] = grad[2] + T(0.5) * v_sigma * dx * dx;
        grad[3] = grad[3] + v_sigma * dx * dy;
        grad[4] = grad[4] + T(0.5) * v_sigma * dy * dy;
        grad[5] = grad[5] + v_opacity;
      }
    }
    if constexpr (L == 1) {
      for (int j = 0; j < stride; ++j) record_out[j] = simd::lane_sum(grad[j]);
    } else {
      for (int j = 0; j < stride; ++j) simd::lane_store(pending + (std::size_t(j) * L + std::size_t(n_pending)) * L, grad[j]);
      pending_out[n_pending++] = record_out;
      if (n_pending == L) flush();
    }
  }
  if (n_pending > 0) flush();
}

// Which blend kernel a render uses: the compile-time SIMD batches, a run-time dispatched wider one, or scalar.
enum class BlendKernel { scalar, compiled, avx2, avx512 };

template <class T>
BlendKernel choose_blend_kernel(const RasterSkips& skips) {
  if (skips.force_scalar || !simd::enabled()) return BlendKernel::scalar;
#if FLEXSPLAT_SIMD_DISPATCH
  const simd::DispatchLevel level = std::min(simd::dispatch_level(), skips.dispatch_cap);
  const std::size_t compiled_bytes = simd::width<T> * sizeof(T);
  // Dispatch is for float renders (its exp is accurate to float precision); double keeps the compiled batches.
  if (sizeof(T) == 4 && level == simd::DispatchLevel::avx512 && compiled_bytes < 64) return BlendKernel::avx512;
  if (sizeof(T) == 4 && level != simd::DispatchLevel::none && compiled_bytes < 32) return BlendKernel::avx2;
#endif
  return BlendKernel::compiled;
}

// Lanes per vector of a (non-scalar) kernel's float lanes.
template <class T>
index_t blend_lane_count(BlendKernel kernel) {
  if (kernel == BlendKernel::avx512) return 16;
  if (kernel == BlendKernel::avx2) return 8;
  return index_t(simd::width<T>);
}

// with_blend_lanes for kernels that must match the scalar path bit for bit (simd::run_avx512_exact / run_avx2_exact).
template <class T, class Body>
void with_exact_lanes(BlendKernel kernel, Body&& body) {
#if FLEXSPLAT_SIMD_DISPATCH
  if constexpr (sizeof(T) == 4) {
    if (kernel == BlendKernel::avx512) return simd::run_avx512_exact(body);
    if (kernel == BlendKernel::avx2) return simd::run_avx2_exact(body);
  }
#endif
  body(static_cast<simd::batch<T>*>(nullptr));
}

// Calls body(V*) with the lane type V of the chosen kernel (the pointer only carries the type).
template <class T, class Body>
void with_blend_lanes(BlendKernel kernel, Body&& body) {
#if FLEXSPLAT_SIMD_DISPATCH
  if constexpr (sizeof(T) == 4) {
    if (kernel == BlendKernel::avx512) return simd::run_avx512(body);
    if (kernel == BlendKernel::avx2) return simd::run_avx2(body);
  }
#endif
  if (kernel == BlendKernel::compiled) body(static_cast<simd::batch<T>*>(nullptr));
  else body(static_cast<T*>(nullptr));
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

// Record fields 7-10: the image pixels within the half-extents rx, ry of (u, v) (pixel x is in range when
// |x + 0.5 - u| <= rx), computed once per Gaussian so tiles only clamp integers.
template <class T>
void write_record_pixels(double u, double v, double rx, double ry, const TileGrid& grid, T* record) {
  auto pixel_range = [](double centre, double half, int size, T* out) {
    const double first = std::ceil(centre - pixel_centre_offset - half);
    const double last = std::floor(centre - pixel_centre_offset + half);
    out[0] = T(std::clamp(first, 0.0, double(size)));
    out[1] = T(std::clamp(last, -1.0, double(size - 1)));
  };
  pixel_range(u, rx, grid.width, record + 7);
  pixel_range(v, ry, grid.height, record + 9);
}

template <class T>
void write_splat_record(const Projection<T>& p, const T* channels, int C, const TileGrid& grid, T* record) {
  SplatParams<T> sp;
  splat_params(p, sp);
  record[0] = sp.u, record[1] = sp.v, record[2] = sp.ca, record[3] = sp.cb, record[4] = sp.cc;
  record[5] = sp.opacity, record[6] = sp.sigma_max;
  write_record_pixels(double(sp.u), double(sp.v), double(sp.rx), double(sp.ry), grid, record);
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
      if (ti.gaussian_counts[g] != 0)
        write_splat_record(proj[g], channels + g * C, C, ti.grid, records + g * ws.splat_stride);
  }, pool);
}

// rasterize_forward for a workspace whose records (begin_splats, write_splat_record) already hold every Gaussian
// that has tile entries, handing every finished pixel row to sink(first pixel p0, count, channels, plane,
// transmittance, contributors): channel c of pixel p0 + x at channels[c * plane + x] (background included), its
// final transmittance at transmittance[x] and contributor count at contributors[x]. Rows of different tiles reach
// the sink from different threads.
template <class T, class RowSink>
void rasterize_forward_rows(const TileIntersections& ti, int C, const T* background, const RasterSkips& skips,
                            RasterWorkspace<T>& ws, BlendState<T>& state, RowSink&& sink,
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
  for (auto& s : ws.scratch) s.reserve(C);
  const detail::BlendKernel kernel = detail::choose_blend_kernel<T>(skips);
  detail::for_each_tile(ti.grid.count(), pool, [&](index_t tile, int worker) {
    TileState<T>& st = ws.scratch[std::size_t(worker)];
    const T* records = ws.splat_records();
    detail::with_blend_lanes<T>(kernel, [&](auto* lanes) {
      using V = std::remove_pointer_t<decltype(lanes)>;
      detail::blend_tile_forward<V, T>(ti, tile, records, ws.splat_stride, st, C, background, skips, state, sink);
    });
  });
}

// Blends C channels of the visible Gaussians into out_channels (planar: channel c of pixel p at [c * H * W + p],
// background included) and fills state.
template <class T>
void rasterize_forward(const TileIntersections& ti, const Projection<T>* proj, const T* channels, int C,
                       const T* background, const RasterSkips& skips, RasterWorkspace<T>& ws, T* out_channels,
                       BlendState<T>& state, ThreadPool& pool = global_pool()) {
  require(C >= 1 && C <= 64, "raster: ", C, " channels; between 1 and 64 are supported");
  prepare_splats(ti, proj, channels, C, ws, pool);
  const std::int64_t plane = std::int64_t(ti.grid.width) * ti.grid.height;
  rasterize_forward_rows(ti, C, background, skips, ws, state, [&](std::int64_t p0, int count, const T* row_channels,
                                                                  int stride, const T*, const T*) {
    for (int c = 0; c < C; ++c) std::copy_n(row_channels + c * stride, count, out_channels + c * plane + p0);
  }, pool);
}

// Sum of the gradient records of Gaussian g's entries (a Gaussian's entries are contiguous and in tile order: a fixed
// summation order for any thread count) into out[0, 6 + C).
template <class T>
FLEXSPLAT_ALWAYS_INLINE void sum_entry_grads(const TileIntersections& ti, const RasterWorkspace<T>& ws, int C, index_t g,
                                             T* out) {
  const int stride = entry_grad_fixed + C;
  for (int j = 0; j < stride; ++j) out[j] = T(0);
  const std::int64_t first = ti.gaussian_offsets[g], cnt = ti.gaussian_counts[g];
  for (std::int64_t e = first; e < first + cnt; ++e)
    for (int j = 0; j < stride; ++j) out[j] += ws.entry_grads[e * stride + j];
}

// Writes the gradient record of every tile entry into ws.entry_grads from the output cotangents, read per image row
// by cotangents(p0, count, d_channels, plane, d_alpha) (as blend_tile_backward; called from several threads).
template <class T, class CotangentRows>
void rasterize_backward_rows(const TileIntersections& ti, const Projection<T>* proj, const T* channels, int C,
                             const T* background, const BlendState<T>& state, const CotangentRows& cotangents,
                             const RasterSkips& skips, RasterWorkspace<T>& ws, ThreadPool& pool = global_pool()) {
  require(C >= 1 && C <= 64, "raster: ", C, " channels; between 1 and 64 are supported");
  const int stride = entry_grad_fixed + C;
  ws.entry_grads.resize(std::size_t(ti.tile_offsets.back()) * std::size_t(stride));
  ws.scratch.resize(std::size_t(pool.size()));
  for (auto& s : ws.scratch) s.reserve(C);
  if (ws.splat_count != index_t(ti.gaussian_counts.size()) || ws.splat_channels != C)
    prepare_splats(ti, proj, channels, C, ws, pool);
  const detail::BlendKernel kernel = detail::choose_blend_kernel<T>(skips);
  detail::for_each_tile(ti.grid.count(), pool, [&](index_t tile, int worker) {
    TileState<T>& st = ws.scratch[std::size_t(worker)];
    if (ti.tile_offsets[tile + 1] == ti.tile_offsets[tile]) return;
    const T* records = ws.splat_records();
    T* grads = ws.entry_grads.data();
    detail::with_blend_lanes<T>(kernel, [&](auto* lanes) {
      using V = std::remove_pointer_t<decltype(lanes)>;
      if (C == 4)  // image and depth, no features
        detail::blend_tile_backward<V, T, 4>(ti, tile, records, ws.splat_stride, st, C, background, state, cotangents,
                                             grads);
      else
        detail::blend_tile_backward<V, T>(ti, tile, records, ws.splat_stride, st, C, background, state, cotangents,
                                          grads);
    });
  });
}

// rasterize_backward_rows from planar cotangents d_out_channels (as out_channels) and d_alpha [H*W] (may be null),
// then, unless gaussian_grads is null, adds the per-Gaussian sums of the entry records (sum_entry_grads) into
// gaussian_grads [N, 6 + C] (same record layout as an entry). A caller that passes null reduces the records itself,
// e.g. while it reads them.
template <class T>
void rasterize_backward(const TileIntersections& ti, const Projection<T>* proj, const T* channels, int C,
                        const T* background, const BlendState<T>& state, const T* d_out_channels, const T* d_alpha,
                        const RasterSkips& skips, RasterWorkspace<T>& ws, index_t n, T* gaussian_grads,
                        ThreadPool& pool = global_pool()) {
  const std::int64_t plane = std::int64_t(ti.grid.width) * ti.grid.height;
  auto planar = [&](std::int64_t p0, int count, T* d_channels, int row_plane, T* d_alpha_row) {
    for (int c = 0; c < C; ++c) std::copy_n(d_out_channels + c * plane + p0, count, d_channels + c * row_plane);
    if (d_alpha) std::copy_n(d_alpha + p0, count, d_alpha_row);
    else std::fill_n(d_alpha_row, count, T(0));
  };
  rasterize_backward_rows(ti, proj, channels, C, background, state, planar, skips, ws, pool);
  if (!gaussian_grads) return;
  const int stride = entry_grad_fixed + C;
  parallel_for(n, [&](index_t gb, index_t ge, int) {
    T sum[entry_grad_fixed + 64];
    for (index_t g = gb; g < ge; ++g) {
      sum_entry_grads(ti, ws, C, g, sum);
      for (int j = 0; j < stride; ++j) gaussian_grads[g * stride + j] += sum[j];
    }
  }, pool);
}

}  // namespace raster
}  // namespace v0
}  // namespace flexsplat
