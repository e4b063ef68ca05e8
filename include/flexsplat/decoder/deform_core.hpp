#pragma once
// The sampling core of multi-view deformable attention, with Deformable DETR's ms_deform_attn_core semantics (views in
// the role of levels): for every (batch, query, head), a weighted sum over views x points of bilinear samples of the
// value map, grid_sample style (zero padding, align_corners=False: normalised 0 and 1 are the outer image edges).
// Backward gives the gradients of value, sampling locations and attention weights.
#include <cmath>
#include <span>
#include <vector>

#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/profile.hpp"
#include "flexsplat/core/simd.hpp"
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {
namespace decoder {

// value [batch, value_len, heads, head_dim] (views concatenated, each row-major H then W);
// locations [batch, n_queries, heads, views, points, 2] as normalised (x, y); weights [batch, n_queries, heads, views, points];
// out [batch, n_queries, heads * head_dim].
struct DeformCoreLayout {
  index_t batch = 1, n_queries = 0, heads = 1, head_dim = 0, points = 1;
  std::vector<index_t> height, width, start;  // per view
  index_t views() const { return static_cast<index_t>(height.size()); }
  index_t value_len() const { return start.empty() ? 0 : start.back() + height.back() * width.back(); }
  index_t location_count() const { return batch * n_queries * heads * views() * points; }
};

// Builds and validates a layout in place (reusing its vectors' capacity): `views` views of feat_h x feat_w each.
inline void set_deform_core_layout(DeformCoreLayout& L, index_t batch, index_t n_queries, index_t heads, index_t head_dim,
                                   index_t points, index_t views, index_t feat_h, index_t feat_w) {
  require(batch >= 1 && n_queries >= 0 && heads >= 1 && head_dim >= 1 && points >= 1,
          "deform_core: batch ", batch, ", queries ", n_queries, ", heads ", heads, ", head_dim ", head_dim, ", points ",
          points, " must be positive");
  require(views >= 1 && feat_h >= 1 && feat_w >= 1, "deform_core: ", views, " views of ", feat_h, "x", feat_w,
          " (zero-size)");
  L.batch = batch;
  L.n_queries = n_queries;
  L.heads = heads;
  L.head_dim = head_dim;
  L.points = points;
  L.height.assign(static_cast<std::size_t>(views), feat_h);
  L.width.assign(static_cast<std::size_t>(views), feat_w);
  L.start.resize(static_cast<std::size_t>(views));
  for (index_t v = 0; v < views; ++v) L.start[static_cast<std::size_t>(v)] = v * feat_h * feat_w;
}

// Builds and validates a layout; view_hw lists (H, W) per view.
inline DeformCoreLayout make_deform_core_layout(index_t batch, index_t n_queries, index_t heads, index_t head_dim,
                                                index_t points, std::span<const index_t> view_hw) {
  require(batch >= 1 && n_queries >= 0 && heads >= 1 && head_dim >= 1 && points >= 1,
          "deform_core: batch ", batch, ", queries ", n_queries, ", heads ", heads, ", head_dim ", head_dim, ", points ",
          points, " must be positive");
  require(!view_hw.empty() && view_hw.size() % 2 == 0, "deform_core: view shapes must be (H, W) pairs, got ",
          view_hw.size(), " numbers");
  DeformCoreLayout L;
  L.batch = batch;
  L.n_queries = n_queries;
  L.heads = heads;
  L.head_dim = head_dim;
  L.points = points;
  index_t start = 0;
  for (std::size_t v = 0; v < view_hw.size() / 2; ++v) {
    const index_t h = view_hw[2 * v], w = view_hw[2 * v + 1];
    require(h >= 1 && w >= 1, "deform_core: feature map of view ", v, " is ", h, "x", w, " (zero-size)");
    L.height.push_back(h);
    L.width.push_back(w);
    L.start.push_back(start);
    start += h * w;
  }
  return L;
}

// The four bilinear taps of one normalised location in an H x W map; taps outside the map have valid = false.
template <class T>
struct BilinearTaps {
  index_t pixel[4] = {0, 0, 0, 0};  // y * W + x
  T weight[4] = {0, 0, 0, 0};
  T d_weight_dx[4] = {0, 0, 0, 0};  // derivative with respect to the normalised x
  T d_weight_dy[4] = {0, 0, 0, 0};
  bool valid[4] = {false, false, false, false};
  bool any = false;
};

// grid_sample's unnormalisation for align_corners=False is px = x * W - 0.5; locations beyond one pixel of the edge
// (or not finite) touch nothing, which also keeps the integer conversion in range.
template <class T>
BilinearTaps<T> bilinear_taps(T x, T y, index_t h, index_t w) {
  BilinearTaps<T> t;
  const T px = x * static_cast<T>(w) - T(0.5), py = y * static_cast<T>(h) - T(0.5);
  if (!(px >= T(-1) && px <= static_cast<T>(w) && py >= T(-1) && py <= static_cast<T>(h))) return t;
  const T fx0 = std::floor(px), fy0 = std::floor(py);
  const index_t x0 = static_cast<index_t>(fx0), y0 = static_cast<index_t>(fy0);
  const T ax = px - fx0, ay = py - fy0;
  const T W = static_cast<T>(w), H = static_cast<T>(h);
  const index_t xs[4] = {x0, x0 + 1, x0, x0 + 1}, ys[4] = {y0, y0, y0 + 1, y0 + 1};
  const T wx[4] = {T(1) - ax, ax, T(1) - ax, ax}, wy[4] = {T(1) - ay, T(1) - ay, ay, ay};
  const T dwx[4] = {T(-1), T(1), T(-1), T(1)}, dwy[4] = {T(-1), T(-1), T(1), T(1)};
  for (int c = 0; c < 4; ++c) {
    t.valid[c] = xs[c] >= 0 && xs[c] < w && ys[c] >= 0 && ys[c] < h;
    if (!t.valid[c]) continue;
    t.any = true;
    t.pixel[c] = ys[c] * w + xs[c];
    t.weight[c] = wx[c] * wy[c];
    t.d_weight_dx[c] = dwx[c] * wy[c] * W;
    t.d_weight_dy[c] = wx[c] * dwy[c] * H;
  }
  return t;
}

namespace detail {
// y += a * x over n elements.
template <class T, bool Simd>
void axpy(index_t n, T a, const T* x, T* y) {
  index_t i = 0;
  if constexpr (Simd) {
    using B = simd::batch<T>;
    constexpr index_t step = static_cast<index_t>(B::size);
    const B av(a);
    for (; i + step <= n; i += step) xsimd::fma(av, B::load_unaligned(x + i), B::load_unaligned(y + i)).store_unaligned(y + i);
  }
  for (; i < n; ++i) y[i] += a * x[i];
}

template <class T, bool Simd>
T dot(index_t n, const T* x, const T* y) {
  index_t i = 0;
  T s = 0;
  if constexpr (Simd) {
    using B = simd::batch<T>;
    constexpr index_t step = static_cast<index_t>(B::size);
    B acc(T(0));
    for (; i + step <= n; i += step) acc = xsimd::fma(B::load_unaligned(x + i), B::load_unaligned(y + i), acc);
    s = xsimd::hadd(acc);
  }
  for (; i < n; ++i) s += x[i] * y[i];
  return s;
}
}  // namespace detail

// out is overwritten. Parallel over (batch, head, query): each worker sweeps one head at a time, so its working set is
// one head's slice of the value maps. query_order (may be null: 0..n-1) is a permutation of the queries to visit them in,
// e.g. along a space-filling curve so that consecutive queries read nearby pixels; the result does not depend on it.
// Simd selects the batch or the scalar inner loops.
template <class T, bool Simd>
void deform_core_forward_impl(T* out, const T* value, const T* locations, const T* weights, const DeformCoreLayout& L,
                              ThreadPool& pool = global_pool(), const index_t* query_order = nullptr) {
  const index_t V = L.views(), P = L.points, D = L.head_dim, H = L.heads, S = L.value_len(), nq = L.n_queries;
  parallel_for(L.batch * H * nq, [&](index_t t0, index_t t1, int) {
    for (index_t t = t0; t < t1; ++t) {
      const index_t bh = t / nq, i = t % nq, b = bh / H, h = bh % H;
      const index_t r = b * nq + (query_order ? query_order[i] : i);
      T* o = out + (r * H + h) * D;
      std::fill(o, o + D, T(0));
      const index_t base = (r * H + h) * V * P;
      for (index_t v = 0; v < V; ++v)
        for (index_t p = 0; p < P; ++p) {
          const index_t s = base + v * P + p;
          const T a = weights[s];
          if (a == T(0)) continue;
          const BilinearTaps<T> tap = bilinear_taps(locations[2 * s], locations[2 * s + 1], L.height[v], L.width[v]);
          for (int c = 0; c < 4; ++c)
            if (tap.valid[c])
              detail::axpy<T, Simd>(D, a * tap.weight[c], value + ((b * S + L.start[v] + tap.pixel[c]) * H + h) * D, o);
        }
    }
  }, pool);
}

// Adds into d_value, d_locations, d_weights (each may be null). Parallel over (batch, head): each task owns its slice
// of every gradient, so the sums are race-free and do not depend on the thread count. Queries are visited in
// query_order (null: 0..n-1), which fixes the summation order into d_value.
template <class T, bool Simd>
void deform_core_backward_impl(T* d_value, T* d_locations, T* d_weights, const T* d_out, const T* value, const T* locations,
                               const T* weights, const DeformCoreLayout& L, ThreadPool& pool = global_pool(),
                               const index_t* query_order = nullptr) {
  const index_t V = L.views(), P = L.points, D = L.head_dim, H = L.heads, S = L.value_len();
  parallel_for(L.batch * H, [&](index_t t0, index_t t1, int) {
    for (index_t task = t0; task < t1; ++task) {
      const index_t b = task / H, h = task % H;
      for (index_t i = 0; i < L.n_queries; ++i) {
        const index_t r = b * L.n_queries + (query_order ? query_order[i] : i);
        const T* g = d_out + (r * H + h) * D;
        const index_t base = (r * H + h) * V * P;
        for (index_t v = 0; v < V; ++v)
          for (index_t p = 0; p < P; ++p) {
            const index_t s = base + v * P + p;
            const T a = weights[s];
            const BilinearTaps<T> t = bilinear_taps(locations[2 * s], locations[2 * s + 1], L.height[v], L.width[v]);
            if (!t.any) continue;
            T d_a = 0, d_x = 0, d_y = 0;
            for (int c = 0; c < 4; ++c) {
              if (!t.valid[c]) continue;
              const index_t row = ((b * S + L.start[v] + t.pixel[c]) * H + h) * D;
              const T gv = detail::dot<T, Simd>(D, g, value + row);
              d_a += t.weight[c] * gv;
              d_x += t.d_weight_dx[c] * gv;
              d_y += t.d_weight_dy[c] * gv;
              if (d_value) detail::axpy<T, Simd>(D, a * t.weight[c], g, d_value + row);
            }
            if (d_weights) d_weights[s] += d_a;
            if (d_locations) {
              d_locations[2 * s] += a * d_x;
              d_locations[2 * s + 1] += a * d_y;
            }
          }
      }
    }
  }, pool);
}

template <class T>
void deform_core_forward(T* out, const T* value, const T* locations, const T* weights, const DeformCoreLayout& L,
                         ThreadPool& pool = global_pool(), const index_t* query_order = nullptr) {
  const profile::Scope timed(profile::Op::deformable_forward);
  if (simd::enabled()) deform_core_forward_impl<T, true>(out, value, locations, weights, L, pool, query_order);
  else deform_core_forward_impl<T, false>(out, value, locations, weights, L, pool, query_order);
}

template <class T>
void deform_core_backward(T* d_value, T* d_locations, T* d_weights, const T* d_out, const T* value, const T* locations,
                          const T* weights, const DeformCoreLayout& L, ThreadPool& pool = global_pool(),
                          const index_t* query_order = nullptr) {
  const profile::Scope timed(profile::Op::deformable_backward);
  if (simd::enabled())
    deform_core_backward_impl<T, true>(d_value, d_locations, d_weights, d_out, value, locations, weights, L, pool, query_order);
  else
    deform_core_backward_impl<T, false>(d_value, d_locations, d_weights, d_out, value, locations, weights, L, pool, query_order);
}

}  // namespace decoder
}  // namespace v0
}  // namespace flexsplat
