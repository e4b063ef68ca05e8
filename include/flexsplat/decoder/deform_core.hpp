#pragma once
// The sampling core of multi-view deformable attention, with Deformable DETR's ms_deform_attn_core semantics (views in
// the role of levels): for every (batch, query, head), a weighted sum over views x points of bilinear samples of the
// value map, grid_sample style (zero padding, align_corners=False: normalised 0 and 1 are the outer image edges).
// Backward gives the gradients of value, sampling locations and attention weights.
#include <algorithm>
#include <span>
#include <type_traits>
#include <vector>

#include "flexsplat/core/inline.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/profile.hpp"
#include "flexsplat/core/simd.hpp"
#include "flexsplat/core/simd_dispatch.hpp"
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
// (or not finite) touch nothing, which also keeps the integer conversion in range. The floor goes through the integer
// conversion (exact for |px| < 2^31): SSE2 has no rounding instruction, and a call per tap costs more than the tap.
template <class T>
FLEXSPLAT_ALWAYS_INLINE BilinearTaps<T> bilinear_taps(T x, T y, index_t h, index_t w) {
  BilinearTaps<T> t;
  const T px = x * static_cast<T>(w) - T(0.5), py = y * static_cast<T>(h) - T(0.5);
  if (!(px >= T(-1) && px <= static_cast<T>(w) && py >= T(-1) && py <= static_cast<T>(h))) return t;
  const index_t tx = static_cast<index_t>(px), ty = static_cast<index_t>(py);  // toward zero
  const index_t x0 = tx - (px < static_cast<T>(tx)), y0 = ty - (py < static_cast<T>(ty));
  const T ax = px - static_cast<T>(x0), ay = py - static_cast<T>(y0);
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
// Row operations over one head's D values. Dc > 0 fixes D at compile time (a multiple of 4: the small model's heads
// are 8-16 wide), run in 16-byte vectors whatever the target; 0 takes the run-time d in scalar loops.
template <class T>
using Row16 = simd::wide<T, 16 / static_cast<int>(sizeof(T))>;

template <index_t Dc, class T>
FLEXSPLAT_ALWAYS_INLINE void row_axpy(index_t d, T a, const T* x, T* y) {
  if constexpr (Dc > 0) {
    using R = Row16<T>;
    constexpr index_t lanes = simd::lane_count<R>::value;
    static_assert(Dc % lanes == 0);
    for (index_t i = 0; i < Dc; i += lanes)
      simd::lane_store(y + i, simd::lane_load<R>(y + i) + a * simd::lane_load<R>(x + i));
  } else {
    for (index_t i = 0; i < d; ++i) y[i] += a * x[i];
  }
}

// sum_i x[i] y[i]: with Dc > 0 in vector partial sums, then across the lanes in order.
template <index_t Dc, class T>
FLEXSPLAT_ALWAYS_INLINE T row_dot(index_t d, const T* x, const T* y) {
  if constexpr (Dc > 0) {
    using R = Row16<T>;
    constexpr index_t lanes = simd::lane_count<R>::value;
    R acc = simd::lane_load<R>(x) * simd::lane_load<R>(y);
    for (index_t i = lanes; i < Dc; i += lanes) acc += simd::lane_load<R>(x + i) * simd::lane_load<R>(y + i);
    return simd::lane_sum(acc);
  } else {
    T s = 0;
    for (index_t i = 0; i < d; ++i) s += x[i] * y[i];
    return s;
  }
}

// One (query, head) of the forward: o[D] = sum over views x points x taps of weight * tap * value row.
template <index_t Dc, class T>
FLEXSPLAT_ALWAYS_INLINE void deform_sample_forward(T* o, const T* value, const T* locations, const T* weights,
                                                   const DeformCoreLayout& L, index_t b, index_t r, index_t h) {
  const index_t V = L.views(), P = L.points, D = Dc > 0 ? Dc : L.head_dim, H = L.heads, S = L.value_len();
  std::fill(o, o + D, T(0));
  const index_t base = (r * H + h) * V * P;
  for (index_t v = 0; v < V; ++v) {
    const T* value_v = value + (b * S + L.start[v]) * H * D + h * D;
    for (index_t p = 0; p < P; ++p) {
      const index_t s = base + v * P + p;
      const T a = weights[s];
      if (a == T(0)) continue;
      const BilinearTaps<T> tap = bilinear_taps(locations[2 * s], locations[2 * s + 1], L.height[v], L.width[v]);
      for (int c = 0; c < 4; ++c)
        if (tap.valid[c]) row_axpy<Dc>(D, a * tap.weight[c], value_v + tap.pixel[c] * H * D, o);
    }
  }
}

// One (query, head) of the backward: the weight's and location's gradients of every sample, d_value rows += a w g.
template <index_t Dc, class T>
FLEXSPLAT_ALWAYS_INLINE void deform_sample_backward(T* d_value, T* d_locations, T* d_weights, const T* g,
                                                    const T* value, const T* locations, const T* weights,
                                                    const DeformCoreLayout& L, index_t b, index_t r, index_t h) {
  const index_t V = L.views(), P = L.points, D = Dc > 0 ? Dc : L.head_dim, H = L.heads, S = L.value_len();
  const index_t base = (r * H + h) * V * P;
  for (index_t v = 0; v < V; ++v) {
    const index_t offset = (b * S + L.start[v]) * H * D + h * D;
    for (index_t p = 0; p < P; ++p) {
      const index_t s = base + v * P + p;
      const T a = weights[s];
      const BilinearTaps<T> t = bilinear_taps(locations[2 * s], locations[2 * s + 1], L.height[v], L.width[v]);
      if (!t.any) continue;
      T d_a = 0, d_x = 0, d_y = 0;
      for (int c = 0; c < 4; ++c) {
        if (!t.valid[c]) continue;
        const index_t row = offset + t.pixel[c] * H * D;
        const T gv = row_dot<Dc>(D, g, value + row);
        d_a += t.weight[c] * gv;
        d_x += t.d_weight_dx[c] * gv;
        d_y += t.d_weight_dy[c] * gv;
        if (d_value) row_axpy<Dc>(D, a * t.weight[c], g, d_value + row);
      }
      if (d_weights) d_weights[s] += d_a;
      if (d_locations) {
        d_locations[2 * s] += a * d_x;
        d_locations[2 * s + 1] += a * d_y;
      }
    }
  }
}

// Calls f.template operator()<Dc>() with the compile-time head width of D where the kernels have one, else 0; the
// scalar lane type (the reference path) always takes 0.
template <class T, class V, class F>
FLEXSPLAT_ALWAYS_INLINE void with_head_width(index_t D, V*, F&& f) {
  if constexpr (std::is_same_v<V, T>) return f.template operator()<0>();
  switch (D) {
    case 4: return f.template operator()<4>();
    case 8: return f.template operator()<8>();
    case 12: return f.template operator()<12>();
    case 16: return f.template operator()<16>();
    case 32: return f.template operator()<32>();
    default: return f.template operator()<0>();
  }
}
}  // namespace detail

// out is overwritten. Parallel over (batch, head, query): each worker sweeps one head at a time, so its working set is
// one head's slice of the value maps. query_order (may be null: 0..n-1) is a permutation of the queries to visit them in,
// e.g. along a space-filling curve so that consecutive queries read nearby pixels; the result does not depend on it.
// `lanes`: scalar runs plain loops (the reference); the others run heads 4-32 wide (multiples of 4) in 16-byte vectors,
// compiled for the build's target (compiled) or the run-time dispatched one (avx2 / avx512, which also fuse
// multiply-adds), and other widths in plain loops.
template <class T>
void deform_core_forward_impl(T* out, const T* value, const T* locations, const T* weights, const DeformCoreLayout& L,
                              simd::Lanes lanes, ThreadPool& pool = global_pool(), const index_t* query_order = nullptr) {
  const index_t D = L.head_dim, H = L.heads, nq = L.n_queries;
  parallel_for(L.batch * H * nq, [&](index_t t0, index_t t1, int) {
    simd::with_lanes<T>(lanes, [&](auto* lane_type) {
      detail::with_head_width<T>(D, lane_type, [&]<index_t Dc>() {
        for (index_t t = t0; t < t1; ++t) {
          const index_t bh = t / nq, i = t % nq, b = bh / H, h = bh % H;
          const index_t r = b * nq + (query_order ? query_order[i] : i);
          detail::deform_sample_forward<Dc>(out + (r * H + h) * D, value, locations, weights, L, b, r, h);
        }
      });
    });
  }, pool);
}

// Adds into d_value, d_locations, d_weights (each may be null). Parallel over (batch, head): each task owns its slice
// of every gradient, so the sums are race-free and do not depend on the thread count. Queries are visited in
// query_order (null: 0..n-1), which fixes the summation order into d_value.
template <class T>
void deform_core_backward_impl(T* d_value, T* d_locations, T* d_weights, const T* d_out, const T* value, const T* locations,
                               const T* weights, const DeformCoreLayout& L, simd::Lanes lanes,
                               ThreadPool& pool = global_pool(), const index_t* query_order = nullptr) {
  const index_t D = L.head_dim, H = L.heads;
  parallel_for(L.batch * H, [&](index_t t0, index_t t1, int) {
    simd::with_lanes<T>(lanes, [&](auto* lane_type) {
      detail::with_head_width<T>(D, lane_type, [&]<index_t Dc>() {
        for (index_t task = t0; task < t1; ++task) {
          const index_t b = task / H, h = task % H;
          for (index_t i = 0; i < L.n_queries; ++i) {
            const index_t r = b * L.n_queries + (query_order ? query_order[i] : i);
            detail::deform_sample_backward<Dc>(d_value, d_locations, d_weights, d_out + (r * H + h) * D, value,
                                               locations, weights, L, b, r, h);
          }
        }
      });
    });
  }, pool);
}

template <class T>
void deform_core_forward(T* out, const T* value, const T* locations, const T* weights, const DeformCoreLayout& L,
                         ThreadPool& pool = global_pool(), const index_t* query_order = nullptr) {
  const profile::Scope timed(profile::Op::deformable_forward);
  deform_core_forward_impl<T>(out, value, locations, weights, L, simd::best_lanes<T>(), pool, query_order);
}

template <class T>
void deform_core_backward(T* d_value, T* d_locations, T* d_weights, const T* d_out, const T* value, const T* locations,
                          const T* weights, const DeformCoreLayout& L, ThreadPool& pool = global_pool(),
                          const index_t* query_order = nullptr) {
  const profile::Scope timed(profile::Op::deformable_backward);
  deform_core_backward_impl<T>(d_value, d_locations, d_weights, d_out, value, locations, weights, L,
                               simd::best_lanes<T>(), pool, query_order);
}

}  // namespace decoder
}  // namespace v0
}  // namespace flexsplat
