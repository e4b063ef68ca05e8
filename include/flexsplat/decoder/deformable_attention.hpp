#pragma once
// Multi-view deformable cross-attention (FlexSplat eq. 3). Each query's current centre is projected into every view;
// around that reference point a linear layer of the query places `points` sampling offsets per head and view (in
// feature-map pixels, as Deformable DETR), another gives attention logits with one softmax per head over all views x
// points. Views that see the centre behind the camera are masked before the softmax; a query no view sees gets a zero
// update. Value and output projections as in Deformable DETR.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <random>
#include <vector>

#include "flexsplat/core/tensor.hpp"
#include "flexsplat/decoder/deform_core.hpp"
#include "flexsplat/decoder/gaussians.hpp"
#include "flexsplat/decoder/init.hpp"
#include "flexsplat/decoder/morton.hpp"
#include "flexsplat/nn/linear.hpp"

namespace flexsplat {
inline namespace v0 {
namespace decoder {

struct MVDeformConfig {
  index_t dim = 256;        // query width C
  index_t value_dim = 128;  // fused feature channels C_f
  index_t heads = 8;
  index_t points = 4;
  index_t max_views = 4;   // views a run may have
  index_t view_slots = 0;  // parameter slots; view v uses slot min(v, slots - 1). 0: max_views (slot v per view)

  index_t slot_count() const { return view_slots > 0 ? view_slots : max_views; }
  index_t slot(index_t view) const { return std::min(view, slot_count() - 1); }
  // Slots a run with `views` views uses: the first min(views, slot_count()).
  index_t used_slots(index_t views) const { return std::min(views, slot_count()); }
};

// Offsets of every tensor in the module's flat parameter block. Offset/logit rows are ordered (slot, head, point[, xy])
// so a run with V views uses the first rows only. With fewer slots than views (VGGT's two token sets: the reference
// view, then one set every other view shares), views 2..V are interchangeable: the input order carries no pose.
struct MVDeformParamLayout {
  index_t value_w, value_b, offset_w, offset_b, logit_w, logit_b, out_w, out_b, size;
  explicit MVDeformParamLayout(const MVDeformConfig& c) {
    const index_t slots = c.slot_count() * c.heads * c.points;
    index_t at = 0;
    auto take = [&](index_t n) { const index_t o = at; at += n; return o; };
    value_w = take(c.dim * c.value_dim);
    value_b = take(c.dim);
    offset_w = take(2 * slots * c.dim);
    offset_b = take(2 * slots);
    logit_w = take(slots * c.dim);
    logit_b = take(slots);
    out_w = take(c.dim * c.dim);
    out_b = take(c.dim);
    size = at;
  }
};

// Deformable DETR's initialisation: zero offset weights with biases on a ring of directions per head (growing with
// the point index), zero logit weights and biases, Xavier-uniform value/output projections with zero biases.
template <class T>
void mv_deform_init(T* params, const MVDeformConfig& c, std::mt19937_64& rng) {
  const MVDeformParamLayout L(c);
  std::fill(params, params + L.size, T(0));
  xavier_uniform(params + L.value_w, c.dim, c.value_dim, rng);
  xavier_uniform(params + L.out_w, c.dim, c.dim, rng);
  for (index_t v = 0; v < c.slot_count(); ++v)
    for (index_t h = 0; h < c.heads; ++h) {
      const double angle = 2.0 * 3.14159265358979323846 * static_cast<double>(h) / static_cast<double>(c.heads);
      const double cx = std::cos(angle), cy = std::sin(angle), m = std::max(std::abs(cx), std::abs(cy));
      for (index_t p = 0; p < c.points; ++p) {
        const index_t row = ((v * c.heads + h) * c.points + p) * 2;
        params[L.offset_b + row] = static_cast<T>(cx / m * static_cast<double>(p + 1));
        params[L.offset_b + row + 1] = static_cast<T>(cy / m * static_cast<double>(p + 1));
      }
    }
}

// Fused per-view features, NCHW [V, value_dim, feat_h, feat_w].
template <class T>
struct FeatureMaps {
  index_t views = 0, channels = 0, h = 0, w = 0;
  const T* data = nullptr;
};

// Everything backward needs; buffers are sized by resize() (called by mv_deform_forward) and never shrink, so a cache
// reserved once does not allocate again.
template <class T>
struct MVDeformCache {
  index_t n = 0, views = 0;
  AlignedVector<T> value;      // [V*h*w, dim] = [1, S, heads, head_dim]: one bilinear tap reads head_dim in a row
  AlignedVector<T> offsets;    // [N, U*heads*points*2] (linear output, slot-major; U = used_slots(V))
  AlignedVector<T> logits;     // [N, U*heads*points]
  AlignedVector<T> reference;  // [N, V, 2] normalised reference points
  std::vector<unsigned char> visible;  // [N, V]
  std::vector<unsigned char> any_visible;  // [N]
  AlignedVector<T> locations;  // [N, heads, V, points, 2]
  AlignedVector<T> weights;    // [N, heads, V, points]
  AlignedVector<T> sampled;    // [N, dim]
  std::vector<index_t> order;                    // [N] queries along a Morton curve of their centres (cache locality)
  std::vector<MortonKey> morton_keys, morton_scratch;  // [N] sort items
  DeformCoreLayout core;
  void resize(index_t n_queries, index_t n_views, index_t feat_h, index_t feat_w, const MVDeformConfig& c) {
    n = n_queries;
    views = n_views;
    const auto z = static_cast<std::size_t>(n_queries);
    const auto slots = static_cast<std::size_t>(n_views * c.heads * c.points);
    const auto lin = static_cast<std::size_t>(c.used_slots(n_views) * c.heads * c.points);
    value.resize(static_cast<std::size_t>(n_views * feat_h * feat_w * c.dim));
    offsets.resize(z * 2 * lin);
    logits.resize(z * lin);
    reference.resize(z * static_cast<std::size_t>(n_views) * 2);
    visible.resize(z * static_cast<std::size_t>(n_views));
    any_visible.resize(z);
    locations.resize(z * 2 * slots);
    weights.resize(z * slots);
    sampled.resize(z * static_cast<std::size_t>(c.dim));
    order.resize(z), morton_keys.resize(z), morton_scratch.resize(z);
    core.height.reserve(static_cast<std::size_t>(c.max_views));
    core.width.reserve(static_cast<std::size_t>(c.max_views));
    core.start.reserve(static_cast<std::size_t>(c.max_views));
  }
  std::size_t capacity_bytes() const {
    return (value.capacity() + offsets.capacity() + logits.capacity() + reference.capacity() + locations.capacity() +
            weights.capacity() + sampled.capacity()) * sizeof(T) + visible.capacity() + any_visible.capacity() +
           order.capacity() * sizeof(index_t) + (morton_keys.capacity() + morton_scratch.capacity()) * sizeof(MortonKey) +
           (core.height.capacity() + core.width.capacity() + core.start.capacity()) * sizeof(index_t);
  }
};

// Backward temporaries; one instance can serve every layer.
template <class T>
struct MVDeformGradScratch {
  AlignedVector<T> g_out, d_sampled, d_value, d_loc, d_w, d_logits, d_offsets, d_ref;
  void resize(index_t n, index_t views, index_t feat_h, index_t feat_w, const MVDeformConfig& c) {
    const auto z = static_cast<std::size_t>(n), slots = static_cast<std::size_t>(views * c.heads * c.points);
    const auto lin = static_cast<std::size_t>(c.used_slots(views) * c.heads * c.points);
    g_out.resize(z * static_cast<std::size_t>(c.dim));
    d_sampled.resize(z * static_cast<std::size_t>(c.dim));
    d_value.resize(static_cast<std::size_t>(views * feat_h * feat_w * c.dim));
    d_loc.resize(z * 2 * slots);
    d_w.resize(z * slots);
    d_logits.resize(z * lin);
    d_offsets.resize(z * 2 * lin);
    d_ref.resize(z * static_cast<std::size_t>(views) * 2);
  }
  std::size_t capacity_bytes() const {
    return (g_out.capacity() + d_sampled.capacity() + d_value.capacity() + d_loc.capacity() + d_w.capacity() +
            d_logits.capacity() + d_offsets.capacity() + d_ref.capacity()) * sizeof(T);
  }
};

template <class T>
void validate_features(const FeatureMaps<T>& f, const MVDeformConfig& c, index_t views) {
  require(f.data != nullptr, "deformable attention: null feature maps");
  require(f.h >= 1 && f.w >= 1, "deformable attention: feature maps are ", f.h, "x", f.w, " (zero-size)");
  require(f.views == views, "deformable attention: ", f.views, " feature maps for ", views, " views");
  require(f.channels == c.value_dim, "deformable attention: feature maps have ", f.channels, " channels, the module expects ",
          c.value_dim);
  require(views >= 1 && views <= c.max_views, "deformable attention: ", views, " views, the module takes 1 to ",
          c.max_views);
  require(c.dim % c.heads == 0, "deformable attention: dim ", c.dim, " is not divisible by ", c.heads, " heads");
}

// Projection of a world point into a view: normalised (x, y) with 0 and 1 at the image edges; false when behind.
template <class T>
bool project_normalised(const T* K, const T* E, const T* X, index_t image_w, index_t image_h, T* xy) {
  const T c0 = E[0] * X[0] + E[1] * X[1] + E[2] * X[2] + E[3];
  const T c1 = E[4] * X[0] + E[5] * X[1] + E[6] * X[2] + E[7];
  const T z = E[8] * X[0] + E[9] * X[1] + E[10] * X[2] + E[11];
  if (!(z > static_cast<T>(near_depth))) return false;
  xy[0] = (K[0] * c0 / z + K[2]) / static_cast<T>(image_w);
  xy[1] = (K[4] * c1 / z + K[5]) / static_cast<T>(image_h);
  return std::isfinite(xy[0]) && std::isfinite(xy[1]);
}

// out [N, dim] = the attention update for queries x [N, dim] at centres [N, 3].
template <class T>
void mv_deform_forward(T* out, MVDeformCache<T>& cache, const T* x, const T* centres, index_t n, const T* params,
                       const MVDeformConfig& c, const FeatureMaps<T>& f, const ViewGeometry<T>& g) {
  validate_features(f, c, g.views);
  const MVDeformParamLayout P(c);
  const index_t V = g.views, H = c.heads, Pn = c.points, hw = f.h * f.w, S = V * hw;
  const index_t slots = c.used_slots(V) * H * Pn;  // offset / logit rows in use
  cache.resize(n, V, f.h, f.w, c);
  // value projection straight from NCHW: value_v [hw, dim] = features_v^T [hw, C_f] W^T + b
  parallel_for(S, [&](index_t r0, index_t r1, int) {
    for (index_t r = r0; r < r1; ++r) std::copy(params + P.value_b, params + P.value_b + c.dim, cache.value.data() + r * c.dim);
  });
  for (index_t v = 0; v < V; ++v)
    gemm(Trans::yes, Trans::yes, hw, c.dim, c.value_dim, T(1), f.data + v * c.value_dim * hw, hw, params + P.value_w,
         c.value_dim, T(1), cache.value.data() + v * hw * c.dim, c.dim);
  // offsets and logits for the views in use
  nn::linear_forward(cache.offsets.data(), x, params + P.offset_w, params + P.offset_b, n, c.dim, 2 * slots);
  nn::linear_forward(cache.logits.data(), x, params + P.logit_w, params + P.logit_b, n, c.dim, slots);
  std::fill(cache.reference.begin(), cache.reference.end(), T(0));
  std::fill(cache.visible.begin(), cache.visible.end(), 0);
  std::fill(cache.any_visible.begin(), cache.any_visible.end(), 0);
  std::fill(cache.locations.begin(), cache.locations.end(), T(0));
  std::fill(cache.weights.begin(), cache.weights.end(), T(0));
  parallel_for(n, [&](index_t q0, index_t q1, int) {
    for (index_t q = q0; q < q1; ++q) {
      for (index_t v = 0; v < V; ++v) {
        T* ref = &cache.reference[(q * V + v) * 2];
        const bool vis = project_normalised(g.K + 9 * v, g.world_to_camera + 12 * v, centres + 3 * q, g.image_w, g.image_h, ref);
        cache.visible[q * V + v] = vis;
        if (!vis) ref[0] = ref[1] = T(0);
        cache.any_visible[q] |= vis;
      }
      for (index_t h = 0; h < H; ++h) {
        T max_logit = -std::numeric_limits<T>::infinity();
        for (index_t v = 0; v < V; ++v)
          if (cache.visible[q * V + v])
            for (index_t p = 0; p < Pn; ++p)
              max_logit = std::max(max_logit, cache.logits[q * slots + (c.slot(v) * H + h) * Pn + p]);
        T sum = 0;
        for (index_t v = 0; v < V; ++v)
          for (index_t p = 0; p < Pn; ++p) {
            const index_t core = ((q * H + h) * V + v) * Pn + p;  // [N, heads, V, points]
            const index_t lin = (c.slot(v) * H + h) * Pn + p;     // [U, heads, points]
            const T* ref = &cache.reference[(q * V + v) * 2];
            cache.locations[2 * core] = ref[0] + cache.offsets[q * 2 * slots + 2 * lin] / static_cast<T>(f.w);
            cache.locations[2 * core + 1] = ref[1] + cache.offsets[q * 2 * slots + 2 * lin + 1] / static_cast<T>(f.h);
            if (!cache.visible[q * V + v]) continue;
            const T e = std::exp(cache.logits[q * slots + lin] - max_logit);
            cache.weights[core] = e;
            sum += e;
          }
        if (sum > T(0))
          for (index_t s = 0; s < V * Pn; ++s) cache.weights[(q * H + h) * V * Pn + s] /= sum;
      }
    }
  });
  set_deform_core_layout(cache.core, 1, n, H, c.dim / H, Pn, V, f.h, f.w);
  morton_order(cache.order.data(), centres, n, cache.morton_keys.data(), cache.morton_scratch.data());
  deform_core_forward(cache.sampled.data(), cache.value.data(), cache.locations.data(), cache.weights.data(), cache.core,
                      global_pool(), cache.order.data());
  nn::linear_forward(out, cache.sampled.data(), params + P.out_w, params + P.out_b, n, c.dim, c.dim);
  for (index_t q = 0; q < n; ++q)
    if (!cache.any_visible[q]) std::fill(out + q * c.dim, out + (q + 1) * c.dim, T(0));
}

// Adds into d_x [N, dim], d_centres [N, 3], d_params, d_features (NCHW like the input) and the camera gradients
// (any may be null except d_params). Temporaries live in gs (sized here, reused across calls).
template <class T>
void mv_deform_backward(T* d_x, T* d_centres, T* d_params, T* d_features, const ViewGeometryGrad<T>& d_geometry,
                        const T* d_out, const MVDeformCache<T>& cache, const T* x, const T* centres, const T* params,
                        const MVDeformConfig& c, const FeatureMaps<T>& f, const ViewGeometry<T>& g,
                        MVDeformGradScratch<T>& gs) {
  const MVDeformParamLayout P(c);
  const index_t n = cache.n, V = cache.views, H = c.heads, Pn = c.points, hw = f.h * f.w;
  const index_t slots = c.used_slots(V) * H * Pn;
  gs.resize(n, V, f.h, f.w, c);
  std::copy(d_out, d_out + n * c.dim, gs.g_out.begin());
  for (index_t q = 0; q < n; ++q)
    if (!cache.any_visible[q]) std::fill(gs.g_out.begin() + q * c.dim, gs.g_out.begin() + (q + 1) * c.dim, T(0));
  for (auto* buf : {&gs.d_sampled, &gs.d_value, &gs.d_loc, &gs.d_w, &gs.d_logits, &gs.d_offsets, &gs.d_ref})
    std::fill(buf->begin(), buf->end(), T(0));
  nn::linear_backward(gs.d_sampled.data(), d_params + P.out_w, d_params + P.out_b, gs.g_out.data(), cache.sampled.data(),
                      params + P.out_w, n, c.dim, c.dim);
  T* const d_value = gs.d_value.data();
  T* const d_loc = gs.d_loc.data();
  T* const d_w = gs.d_w.data();
  T* const d_logits = gs.d_logits.data();
  T* const d_offsets = gs.d_offsets.data();
  T* const d_ref = gs.d_ref.data();
  deform_core_backward(d_value, d_loc, d_w, gs.d_sampled.data(), cache.value.data(), cache.locations.data(),
                       cache.weights.data(), cache.core, global_pool(), cache.order.data());
  // softmax, offsets and reference points
  parallel_for(n, [&](index_t q0, index_t q1, int) {
    for (index_t q = q0; q < q1; ++q)
      for (index_t h = 0; h < H; ++h) {
        const index_t base = (q * H + h) * V * Pn;
        T dot = 0;
        for (index_t s = 0; s < V * Pn; ++s) dot += cache.weights[base + s] * d_w[base + s];
        for (index_t v = 0; v < V; ++v)
          for (index_t p = 0; p < Pn; ++p) {
            const index_t core = base + v * Pn + p, lin = (c.slot(v) * H + h) * Pn + p;  // views may share a slot
            d_logits[q * slots + lin] += cache.weights[core] * (d_w[core] - dot);
            d_offsets[q * 2 * slots + 2 * lin] += d_loc[2 * core] / static_cast<T>(f.w);
            d_offsets[q * 2 * slots + 2 * lin + 1] += d_loc[2 * core + 1] / static_cast<T>(f.h);
            if (cache.visible[q * V + v]) {
              d_ref[(q * V + v) * 2] += d_loc[2 * core];
              d_ref[(q * V + v) * 2 + 1] += d_loc[2 * core + 1];
            }
          }
      }
  });
  nn::linear_backward(d_x, d_params + P.offset_w, d_params + P.offset_b, d_offsets, x, params + P.offset_w, n,
                      c.dim, 2 * slots);
  nn::linear_backward(d_x, d_params + P.logit_w, d_params + P.logit_b, d_logits, x, params + P.logit_w, n, c.dim,
                      slots);
  // projection: serial so the shared camera gradients are summed in a fixed order
  for (index_t q = 0; q < n; ++q)
    for (index_t v = 0; v < V; ++v) {
      if (!cache.visible[q * V + v]) continue;
      const T* K = g.K + 9 * v;
      const T* E = g.world_to_camera + 12 * v;
      const T* X = centres + 3 * q;
      const T cam[3] = {E[0] * X[0] + E[1] * X[1] + E[2] * X[2] + E[3], E[4] * X[0] + E[5] * X[1] + E[6] * X[2] + E[7],
                        E[8] * X[0] + E[9] * X[1] + E[10] * X[2] + E[11]};
      const T gx = d_ref[(q * V + v) * 2] / static_cast<T>(g.image_w), gy = d_ref[(q * V + v) * 2 + 1] / static_cast<T>(g.image_h);
      const T iz = T(1) / cam[2];
      if (d_geometry.K) {
        T* dK = d_geometry.K + 9 * v;
        dK[0] += gx * cam[0] * iz;
        dK[2] += gx;
        dK[4] += gy * cam[1] * iz;
        dK[5] += gy;
      }
      const T d_cam[3] = {gx * K[0] * iz, gy * K[4] * iz, -(gx * K[0] * cam[0] + gy * K[4] * cam[1]) * iz * iz};
      if (d_geometry.world_to_camera) {
        T* dE = d_geometry.world_to_camera + 12 * v;
        for (int r = 0; r < 3; ++r) {
          for (int j = 0; j < 3; ++j) dE[4 * r + j] += d_cam[r] * X[j];
          dE[4 * r + 3] += d_cam[r];
        }
      }
      if (d_centres)
        for (int j = 0; j < 3; ++j) d_centres[3 * q + j] += E[j] * d_cam[0] + E[4 + j] * d_cam[1] + E[8 + j] * d_cam[2];
    }
  // value projection, straight back to NCHW: d_features_v [C_f, hw] += W^T d_value_v^T, d_W += d_value_v^T features_v^T
  for (index_t v = 0; v < V; ++v) {
    const T* dv = d_value + v * hw * c.dim;
    const T* fv = f.data + v * c.value_dim * hw;
    if (d_features)
      gemm(Trans::yes, Trans::yes, c.value_dim, hw, c.dim, T(1), params + P.value_w, c.value_dim, dv, c.dim, T(1),
           d_features + v * c.value_dim * hw, hw);
    gemm(Trans::yes, Trans::yes, c.dim, c.value_dim, hw, T(1), dv, c.dim, fv, hw, T(1), d_params + P.value_w, c.value_dim);
  }
  T* db = d_params + P.value_b;
  for (index_t r = 0; r < V * hw; ++r)
    for (index_t k = 0; k < c.dim; ++k) db[k] += d_value[r * c.dim + k];
}

// Convenience form with its own (allocated) temporaries.
template <class T>
void mv_deform_backward(T* d_x, T* d_centres, T* d_params, T* d_features, const ViewGeometryGrad<T>& d_geometry,
                        const T* d_out, const MVDeformCache<T>& cache, const T* x, const T* centres, const T* params,
                        const MVDeformConfig& c, const FeatureMaps<T>& f, const ViewGeometry<T>& g) {
  MVDeformGradScratch<T> gs;
  mv_deform_backward(d_x, d_centres, d_params, d_features, d_geometry, d_out, cache, x, centres, params, c, f, g, gs);
}

}  // namespace decoder
}  // namespace v0
}  // namespace flexsplat
