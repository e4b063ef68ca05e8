#pragma once
// The Gaussian decoder: N_G learnable queries, an initial splat head, then L layers of
// [multi-view deformable attention -> self-attention -> FFN] (each with a residual and LayerNorm) whose splat heads
// refine the running 24-value estimate. Every layer's Gaussians are returned. Parameters live in one flat block
// (DecoderParamLayout gives the offsets); backward adds into a parallel gradient block and reaches the fused features,
// depth maps and cameras.
#include <algorithm>
#include <random>
#include <string>
#include <vector>

#include "flexsplat/core/profile.hpp"
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/decoder/deformable_attention.hpp"
#include "flexsplat/decoder/gaussians.hpp"
#include "flexsplat/decoder/init.hpp"
#include "flexsplat/decoder/kernels.hpp"
#include "flexsplat/decoder/self_attention.hpp"
#include "flexsplat/decoder/splat_head.hpp"
#include "flexsplat/nn/activations.hpp"
#include "flexsplat/nn/layernorm.hpp"

namespace flexsplat {
inline namespace v0 {
namespace decoder {

struct DecoderConfig {
  index_t dim = 256, ffn = 1024, heads = 8, layers = 3, points = 4, max_views = 4, value_dim = 128;
  index_t view_slots = 0;       // deformable attention's parameter slots (MVDeformConfig); 0: one per view
  index_t max_queries = 20480;  // rows of the query embedding table; a run uses the first N_G
  bool local_attention = false;
  index_t window = 512;
  MVDeformConfig deform() const { return {dim, value_dim, heads, points, max_views, view_slots}; }
  // The query embedding row of query i of a run with `views` views. Query i is anchored in view i % views at grid
  // cell i / views (make_anchors). One slot per view: row i. With view_slots S: row (i / views) * S + slot, so the
  // queries of views 2..V at the same cell share a row and the input order carries no pose.
  index_t query_row(index_t i, index_t views) const {
    return view_slots > 0 ? (i / views) * view_slots + std::min(i % views, view_slots - 1) : i;
  }
  // Rows of the embedding table a run of n queries over `views` views reads.
  index_t query_rows_used(index_t n, index_t views) const {
    return view_slots > 0 ? (n + views - 1) / views * view_slots : n;
  }
  SelfAttentionConfig self_attention() const { return {dim, heads, local_attention, window}; }
};

// Default budget per view count (paper: 10K / 15K / 20K for 1 / 2 / 4 views).
inline index_t default_gaussian_budget(index_t views) { return views <= 1 ? 10000 : views <= 2 ? 15000 : 20000; }

struct DecoderLayerOffsets {
  index_t deform, ln1_g, ln1_b, attn, ln2_g, ln2_b, ffn_w1, ffn_b1, ffn_w2, ffn_b2, ln3_g, ln3_b, head_w, head_b;
};

namespace detail {
// The order of one layer's parameters, shared by the direct computation and the sequential layout walk.
template <class Take>
DecoderLayerOffsets take_layer_offsets(Take&& take, const DecoderConfig& c, index_t deform, index_t attn) {
  DecoderLayerOffsets o;
  o.deform = take(deform);
  o.ln1_g = take(c.dim);
  o.ln1_b = take(c.dim);
  o.attn = take(attn);
  o.ln2_g = take(c.dim);
  o.ln2_b = take(c.dim);
  o.ffn_w1 = take(c.ffn * c.dim);
  o.ffn_b1 = take(c.ffn);
  o.ffn_w2 = take(c.dim * c.ffn);
  o.ffn_b2 = take(c.dim);
  o.ln3_g = take(c.dim);
  o.ln3_b = take(c.dim);
  o.head_w = take(splat_values * c.dim);
  o.head_b = take(splat_values);
  return o;
}
}  // namespace detail

// Offsets of layer l computed directly (no allocation): the layers follow the initial head, all of equal size.
inline DecoderLayerOffsets decoder_layer_offsets(const DecoderConfig& c, index_t l) {
  const index_t deform = MVDeformParamLayout(c.deform()).size, attn = SelfAttentionParamLayout(c.self_attention()).size;
  const index_t layer_size = deform + attn + 6 * c.dim + 2 * c.ffn * c.dim + c.ffn + c.dim + splat_values * c.dim + splat_values;
  index_t at = c.max_queries * c.dim + splat_values * c.dim + splat_values + l * layer_size;
  return detail::take_layer_offsets([&](index_t n) { const index_t o = at; at += n; return o; }, c, deform, attn);
}

struct DecoderParamLayout {
  index_t embeddings, init_head_w, init_head_b, size;
  std::vector<DecoderLayerOffsets> layer;
  explicit DecoderParamLayout(const DecoderConfig& c) {
    index_t at = 0;
    auto take = [&](index_t n) { const index_t o = at; at += n; return o; };
    embeddings = take(c.max_queries * c.dim);
    init_head_w = take(splat_values * c.dim);
    init_head_b = take(splat_values);
    const index_t deform = MVDeformParamLayout(c.deform()).size, attn = SelfAttentionParamLayout(c.self_attention()).size;
    for (index_t l = 0; l < c.layers; ++l) layer.push_back(detail::take_layer_offsets(take, c, deform, attn));
    size = at;
  }
};

// Embeddings N(0, 0.02); initial head Xavier-uniform with zero learnable bias (the Splatter Image biases are fixed);
// per-layer heads Xavier-uniform with gain 0.01 so the first refinements are small; LayerNorm gamma 1, beta 0; FFN
// Xavier-uniform, zero biases; attention blocks as their own init functions.
template <class T>
void decoder_init(T* params, const DecoderConfig& c, std::uint64_t seed) {
  const DecoderParamLayout L(c);
  std::mt19937_64 rng(seed);
  std::fill(params, params + L.size, T(0));
  normal_init(params + L.embeddings, c.max_queries * c.dim, rng, 0.02);
  xavier_uniform(params + L.init_head_w, splat_values, c.dim, rng);
  for (const auto& o : L.layer) {
    mv_deform_init(params + o.deform, c.deform(), rng);
    self_attention_init(params + o.attn, c.self_attention(), rng);
    xavier_uniform(params + o.ffn_w1, c.ffn, c.dim, rng);
    xavier_uniform(params + o.ffn_w2, c.dim, c.ffn, rng);
    xavier_uniform(params + o.head_w, splat_values, c.dim, rng, 0.01);
    for (index_t k : {o.ln1_g, o.ln2_g, o.ln3_g}) std::fill(params + k, params + k + c.dim, T(1));
  }
}

namespace detail {
template <class T, class A>
std::size_t capacity_bytes_of(const std::vector<T, A>& v) {
  return v.capacity() * sizeof(T);
}
}  // namespace detail

// One layer's forward cache. The layer input is the previous layer's x3 (or the query embeddings).
template <class T>
struct DecoderLayerCache {
  AlignedVector<T> r1, mean1, rstd1, x1, r2, mean2, rstd2, x2, hidden_pre, hidden, r3, mean3, rstd3, x3, delta;
  MVDeformCache<T> deform;
  SelfAttentionCache<T> attention;
  // keep = false (forward only): the FFN's GELU runs in place in `hidden`, hidden_pre stays empty.
  void resize(const DecoderConfig& c, index_t n, index_t views, index_t feat_h, index_t feat_w, int workers,
              bool keep = true) {
    const auto nc = static_cast<std::size_t>(n * c.dim), z = static_cast<std::size_t>(n);
    for (auto* v : {&r1, &x1, &r2, &x2, &r3, &x3}) v->resize(nc);
    for (auto* v : {&mean1, &rstd1, &mean2, &rstd2, &mean3, &rstd3}) v->resize(z);
    hidden_pre.resize(keep ? static_cast<std::size_t>(n * c.ffn) : 0);
    hidden.resize(static_cast<std::size_t>(n * c.ffn));
    delta.resize(static_cast<std::size_t>(n * splat_values));
    deform.resize(n, views, feat_h, feat_w, c.deform());
    attention.resize(n, c.self_attention(), workers);
  }
  std::size_t capacity_bytes() const {
    std::size_t b = deform.capacity_bytes() + attention.capacity_bytes();
    for (auto* v : {&r1, &mean1, &rstd1, &x1, &r2, &mean2, &rstd2, &x2, &hidden_pre, &hidden, &r3, &mean3, &rstd3, &x3, &delta})
      b += detail::capacity_bytes_of(*v);
    return b;
  }
};

// Backward temporaries shared by all layers.
template <class T>
struct DecoderGradScratch {
  AlignedVector<T> d_state, d_prev_state, d_centres, d_means, d_x, d_delta, d_r, d_tmp, d_hidden, d_hidden_pre;
  MVDeformGradScratch<T> deform;
  SelfAttentionGradScratch<T> attention;
  void resize(const DecoderConfig& c, index_t n, index_t views, index_t feat_h, index_t feat_w) {
    const auto z = static_cast<std::size_t>(n), nc = static_cast<std::size_t>(n * c.dim);
    for (auto* v : {&d_state, &d_prev_state, &d_delta}) v->resize(z * splat_values);
    for (auto* v : {&d_centres, &d_means}) v->resize(3 * z);
    for (auto* v : {&d_x, &d_r, &d_tmp}) v->resize(nc);
    for (auto* v : {&d_hidden, &d_hidden_pre}) v->resize(static_cast<std::size_t>(n * c.ffn));
    deform.resize(n, views, feat_h, feat_w, c.deform());
    attention.resize(n, c.self_attention());
  }
  std::size_t capacity_bytes() const {
    std::size_t b = deform.capacity_bytes() + attention.capacity_bytes();
    for (auto* v : {&d_state, &d_prev_state, &d_centres, &d_means, &d_x, &d_delta, &d_r, &d_tmp, &d_hidden, &d_hidden_pre})
      b += detail::capacity_bytes_of(*v);
    return b;
  }
};

// Every buffer of decoder_forward / decoder_backward: the forward results (gaussians[0] is the initial estimate,
// gaussians[l + 1] layer l's), the per-layer caches backward needs, and the backward temporaries. reserve() sizes it
// once for a budget, view count and feature-map size; later calls with sizes up to those do not allocate.
template <class T>
struct DecoderWorkspace {
  index_t n = 0;
  Anchors anchors;
  SceneCentre scene_centre;
  AlignedVector<T> base_depth;
  AlignedVector<T> queries;  // [N, dim] the gathered query embeddings when view_slots > 0
  std::vector<unsigned char> depth_used;
  std::vector<double> median_scratch;
  std::vector<AlignedVector<T>> states;  // [layers + 1][N, 24]
  std::vector<GaussianSet<T>> gaussians;
  std::vector<DecoderLayerCache<T>> layers;
  DecoderGradScratch<T> grad;
  // false: forward only (predict); every layer runs in layers[0], so decoder_backward cannot follow.
  bool keep_for_backward = true;
  // Non-empty: decoder_forward runs only these queries of its budget (ascending indices: their anchors and embedding
  // rows, as the whole budget would have them), forward only. Empty: every query.
  std::vector<index_t> subset;
  Anchors budget_anchors;  // the whole budget's anchors when a subset runs

  void resize_forward(const DecoderConfig& c, index_t n_queries, index_t views, index_t feat_h, index_t feat_w,
                      index_t depth_pixels) {
    n = n_queries;
    const auto z = static_cast<std::size_t>(n_queries), sets = static_cast<std::size_t>(c.layers + 1);
    anchors.view.resize(z);
    anchors.pixel.resize(2 * z);
    base_depth.resize(z);
    if (c.view_slots > 0 || !subset.empty()) queries.resize(z * static_cast<std::size_t>(c.dim));
    depth_used.resize(z);
    if (median_scratch.capacity() < static_cast<std::size_t>(depth_pixels))
      median_scratch.reserve(static_cast<std::size_t>(depth_pixels));
    states.resize(sets);
    for (auto& st : states) st.resize(z * splat_values);
    gaussians.resize(sets);
    for (auto& g : gaussians) resize_gaussian_set(g, n_queries, 1);
    const auto used = static_cast<std::size_t>(keep_for_backward ? c.layers : 1);  // forward only: layers[0]
    if (layers.size() < used) layers.resize(used);
    for (std::size_t l = 0; l < used; ++l)
      layers[l].resize(c, n_queries, views, feat_h, feat_w, global_pool().size(), keep_for_backward);
  }
  // Sizes everything (forward and backward) for up to n_queries Gaussians.
  void reserve(const DecoderConfig& c, index_t n_queries, index_t views, index_t feat_h, index_t feat_w,
               index_t depth_pixels = 0) {
    resize_forward(c, n_queries, views, feat_h, feat_w, depth_pixels);
    grad.resize(c, n_queries, views, feat_h, feat_w);
  }
  std::size_t capacity_bytes() const {
    std::size_t b = anchors.view.capacity() * sizeof(index_t) + anchors.pixel.capacity() * sizeof(double) +
                    detail::capacity_bytes_of(base_depth) + detail::capacity_bytes_of(queries) + depth_used.capacity() +
                    detail::capacity_bytes_of(median_scratch) + grad.capacity_bytes();
    for (const auto& st : states) b += detail::capacity_bytes_of(st);
    for (const auto& g : gaussians)
      b += sizeof(T) * static_cast<std::size_t>(g.means.size() + g.quats.size() + g.scales.size() + g.opacities.size() +
                                                g.sh.size());
    for (const auto& k : layers) b += k.capacity_bytes();
    return b;
  }
};

namespace detail {
// out = a + b elementwise, parallel.
template <class T>
void add(T* out, const T* a, const T* b, index_t n) {
  parallel_for((n + 16383) / 16384, [&](index_t b0, index_t b1, int) {
    const index_t i1 = std::min(n, b1 * 16384);
    for (index_t i = b0 * 16384; i < i1; ++i) out[i] = a[i] + b[i];
  });
}
template <class T>
void add_inplace(T* out, const T* a, index_t n) {
  add(out, out, a, n);
}
}  // namespace detail

// Runs the decoder for n_queries Gaussians on fused features [V, value_dim, h, w] and the views' geometry.
// ws: a workspace (reserve() it to avoid the first call's allocations); results are in ws.gaussians.
template <class T>
void decoder_forward(DecoderWorkspace<T>& ws, index_t n_queries, const T* params, const DecoderConfig& c,
                     const FeatureMaps<T>& features, const ViewGeometry<T>& g) {
  validate_geometry(g);
  validate_features(features, c.deform(), g.views);
  require(n_queries >= 1 && n_queries <= c.max_queries, "decoder: Gaussian budget ", n_queries, " is outside [1, ",
          c.max_queries, "]");
  require(c.query_rows_used(n_queries, g.views) <= c.max_queries, "decoder: Gaussian budget ", n_queries, " over ",
          g.views, " views reads ", c.query_rows_used(n_queries, g.views), " query embeddings, the table has ",
          c.max_queries, " (max_queries)");
  const bool subset = !ws.subset.empty();
  require(!subset || !ws.keep_for_backward, "decoder: a query subset runs forward only (keep_for_backward false)");
  for (std::size_t i = 0; i < ws.subset.size(); ++i)
    require(ws.subset[i] >= 0 && ws.subset[i] < n_queries && (i == 0 || ws.subset[i] > ws.subset[i - 1]),
            "decoder: query subset entry ", i, " (", ws.subset[i], ") is not an ascending index below the budget ",
            n_queries);
  const index_t n = subset ? static_cast<index_t>(ws.subset.size()) : n_queries, C = c.dim;
  auto query = [&](index_t i) { return subset ? ws.subset[static_cast<std::size_t>(i)] : i; };
  const T eps = static_cast<T>(layernorm_eps);
  const T* embeddings = params;  // the query table starts the block
  {
    const profile::Stage stage("setup");
    ws.resize_forward(c, n, g.views, features.h, features.w, g.depth_w * g.depth_h);
    if (c.view_slots > 0 || subset) {
      for (index_t i = 0; i < n; ++i) {
        const T* row = params + c.query_row(query(i), g.views) * C;
        std::copy(row, row + C, ws.queries.data() + i * C);
      }
      embeddings = ws.queries.data();
    }
    if (subset) {
      make_anchors(ws.budget_anchors, n_queries, g.views, g.image_w, g.image_h);
      for (index_t i = 0; i < n; ++i) {
        const auto q = static_cast<std::size_t>(query(i));
        ws.anchors.view[static_cast<std::size_t>(i)] = ws.budget_anchors.view[q];
        for (int a = 0; a < 2; ++a) ws.anchors.pixel[2 * static_cast<std::size_t>(i) + a] = ws.budget_anchors.pixel[2 * q + a];
      }
    } else {
      make_anchors(ws.anchors, n, g.views, g.image_w, g.image_h);
    }
    ws.scene_centre = scene_centre_from_axes(g, static_cast<const T*>(nullptr), &ws.median_scratch);
    const T centre[3] = {static_cast<T>(ws.scene_centre.centre[0]), static_cast<T>(ws.scene_centre.centre[1]),
                         static_cast<T>(ws.scene_centre.centre[2])};
    anchor_depths(ws.base_depth.data(), ws.depth_used.data(), g, ws.anchors, centre);
    const index_t init_w = c.max_queries * c.dim;
    splat_head_forward(ws.states[0].data(), embeddings, params + init_w, params + init_w + splat_values * c.dim, n, C, true);
    gaussians_forward(ws.gaussians[0], ws.states[0].data(), ws.base_depth.data(), ws.anchors, g);
  }
  const T* x = embeddings;
  for (index_t l = 0; l < c.layers; ++l) {
    const DecoderLayerOffsets o = decoder_layer_offsets(c, l);
    // One cache serves every layer when none is kept: layer l reads x (layers[0].x3) only before it rewrites x3.
    auto& k = ws.layers[ws.keep_for_backward ? static_cast<std::size_t>(l) : 0];
    const T* centres = ws.gaussians[static_cast<std::size_t>(l)].means.data();
    const profile::Stage layer("layer " + std::to_string(l + 1));
    {
      const profile::Stage stage("deformable attention");
      mv_deform_forward(k.r1.data(), k.deform, x, centres, n, params + o.deform, c.deform(), features, g);
    }
    {
      const profile::Stage stage("norm+residual");
      detail::add_inplace(k.r1.data(), x, n * C);
      nn::layernorm_forward(k.x1.data(), k.r1.data(), params + o.ln1_g, params + o.ln1_b, n, C, eps,
                            {k.mean1.data(), k.rstd1.data()});
    }
    {
      const profile::Stage stage("self-attention");
      self_attention_forward(k.r2.data(), k.attention, k.x1.data(), centres, n, params + o.attn, c.self_attention());
    }
    {
      const profile::Stage stage("norm+residual");
      detail::add_inplace(k.r2.data(), k.x1.data(), n * C);
      nn::layernorm_forward(k.x2.data(), k.r2.data(), params + o.ln2_g, params + o.ln2_b, n, C, eps,
                            {k.mean2.data(), k.rstd2.data()});
    }
    {
      const profile::Stage stage("FFN");
      T* pre = ws.keep_for_backward ? k.hidden_pre.data() : k.hidden.data();
      nn::linear_forward(pre, k.x2.data(), params + o.ffn_w1, params + o.ffn_b1, n, C, c.ffn);
      nn::gelu_forward(k.hidden.data(), pre, n * c.ffn);
      nn::linear_forward(k.r3.data(), k.hidden.data(), params + o.ffn_w2, params + o.ffn_b2, n, c.ffn, C);
    }
    {
      const profile::Stage stage("norm+residual");
      detail::add_inplace(k.r3.data(), k.x2.data(), n * C);
      nn::layernorm_forward(k.x3.data(), k.r3.data(), params + o.ln3_g, params + o.ln3_b, n, C, eps,
                            {k.mean3.data(), k.rstd3.data()});
    }
    {
      const profile::Stage stage("splat head");
      splat_head_forward(k.delta.data(), k.x3.data(), params + o.head_w, params + o.head_b, n, C, false);
      compose_forward(ws.states[l + 1].data(), ws.states[l].data(), k.delta.data(), n);
      gaussians_forward(ws.gaussians[l + 1], ws.states[l + 1].data(), ws.base_depth.data(), ws.anchors, g);
    }
    x = k.x3.data();
  }
}

// d_gaussians[l] is the loss gradient of gaussians[l] (empty fields: no gradient). Adds into d_params, d_features
// (NCHW like the input, may be null) and d_geometry (K, world_to_camera, depth; null members skipped). Temporaries
// live in ws.grad.
template <class T>
void decoder_backward(T* d_params, T* d_features, const ViewGeometryGrad<T>& d_geometry,
                      const std::vector<GaussianSetGrad<T>>& d_gaussians, DecoderWorkspace<T>& ws, const T* params,
                      const DecoderConfig& c, const FeatureMaps<T>& features, const ViewGeometry<T>& g) {
  require(static_cast<index_t>(d_gaussians.size()) == c.layers + 1, "decoder_backward: ", d_gaussians.size(),
          " gradient sets for ", c.layers + 1, " Gaussian sets");
  require(ws.keep_for_backward && ws.layers.size() >= static_cast<std::size_t>(c.layers),
          "decoder_backward: the forward kept no per-layer caches (DecoderWorkspace::keep_for_backward is false)");
  const index_t n = ws.n, C = c.dim;
  auto& s = ws.grad;
  s.resize(c, n, g.views, features.h, features.w);
  for (auto* v : {&s.d_state, &s.d_centres, &s.d_x}) std::fill(v->begin(), v->end(), T(0));
  auto zero = [](AlignedVector<T>& v) { std::fill(v.begin(), v.end(), T(0)); };
  // Loss gradient plus the gradient that later layers' attention sent into these centres.
  auto gaussians_grad = [&](index_t set, AlignedVector<T>& d_st) {
    detail::GaussianGradPointers<T> d = detail::grad_pointers(d_gaussians[static_cast<std::size_t>(set)], n);
    if (d.means) std::transform(d.means, d.means + 3 * n, s.d_centres.begin(), s.d_means.begin(), std::plus<T>());
    else std::copy(s.d_centres.begin(), s.d_centres.end(), s.d_means.begin());
    d.means = s.d_means.data();
    detail::gaussians_backward(d_st.data(), {d_geometry.K, d_geometry.world_to_camera, d_geometry.depth}, d,
                       ws.states[static_cast<std::size_t>(set)].data(), ws.base_depth.data(), ws.depth_used.data(),
                       ws.anchors, g);
    zero(s.d_centres);
  };
  const T* embeddings = c.view_slots > 0 ? ws.queries.data() : params;  // as decoder_forward gathered them
  for (index_t l = c.layers - 1; l >= 0; --l) {
    const DecoderLayerOffsets o = decoder_layer_offsets(c, l);
    auto& k = ws.layers[static_cast<std::size_t>(l)];
    const T* x_in = l == 0 ? embeddings : ws.layers[static_cast<std::size_t>(l - 1)].x3.data();
    gaussians_grad(l + 1, s.d_state);
    zero(s.d_prev_state);
    zero(s.d_delta);
    compose_backward(s.d_prev_state.data(), s.d_delta.data(), s.d_state.data(), ws.states[l].data(), k.delta.data(), n);
    splat_head_backward(s.d_x.data(), d_params + o.head_w, d_params + o.head_b, s.d_delta.data(), k.x3.data(),
                        params + o.head_w, n, C);
    // x3 = LN3(x2 + FFN(x2))
    zero(s.d_r);
    nn::layernorm_backward(s.d_r.data(), d_params + o.ln3_g, d_params + o.ln3_b, s.d_x.data(), k.r3.data(),
                           params + o.ln3_g, n, C, {k.mean3.data(), k.rstd3.data()});
    std::copy(s.d_r.begin(), s.d_r.end(), s.d_tmp.begin());  // into x2 through the residual
    zero(s.d_hidden);
    nn::linear_backward(s.d_hidden.data(), d_params + o.ffn_w2, d_params + o.ffn_b2, s.d_r.data(), k.hidden.data(),
                        params + o.ffn_w2, n, c.ffn, C);
    zero(s.d_hidden_pre);
    nn::gelu_backward(s.d_hidden_pre.data(), s.d_hidden.data(), k.hidden_pre.data(), n * c.ffn);
    nn::linear_backward(s.d_tmp.data(), d_params + o.ffn_w1, d_params + o.ffn_b1, s.d_hidden_pre.data(), k.x2.data(),
                        params + o.ffn_w1, n, C, c.ffn);
    // x2 = LN2(x1 + SA(x1))
    zero(s.d_r);
    nn::layernorm_backward(s.d_r.data(), d_params + o.ln2_g, d_params + o.ln2_b, s.d_tmp.data(), k.r2.data(),
                           params + o.ln2_g, n, C, {k.mean2.data(), k.rstd2.data()});
    std::copy(s.d_r.begin(), s.d_r.end(), s.d_tmp.begin());
    self_attention_backward(s.d_tmp.data(), d_params + o.attn, s.d_r.data(), k.attention, k.x1.data(), params + o.attn,
                            c.self_attention(), s.attention);
    // x1 = LN1(x + MVDA(x, centres))
    zero(s.d_r);
    nn::layernorm_backward(s.d_r.data(), d_params + o.ln1_g, d_params + o.ln1_b, s.d_tmp.data(), k.r1.data(),
                           params + o.ln1_g, n, C, {k.mean1.data(), k.rstd1.data()});
    std::copy(s.d_r.begin(), s.d_r.end(), s.d_x.begin());
    mv_deform_backward(s.d_x.data(), s.d_centres.data(), d_params + o.deform, d_features,
                       ViewGeometryGrad<T>{d_geometry.K, d_geometry.world_to_camera, nullptr}, s.d_r.data(), k.deform,
                       x_in, ws.gaussians[l].means.data(), params + o.deform, c.deform(), features, g, s.deform);
    s.d_state.swap(s.d_prev_state);
  }
  // The initial estimate: its own loss gradient, the first layer's centre gradient and the composed-state gradient.
  gaussians_grad(0, s.d_state);
  const index_t init_w = c.max_queries * c.dim;
  splat_head_backward(s.d_x.data(), d_params + init_w, d_params + init_w + splat_values * c.dim, s.d_state.data(),
                      embeddings, params + init_w, n, C);
  if (c.view_slots > 0) {
    for (index_t i = 0; i < n; ++i) {
      T* row = d_params + c.query_row(i, g.views) * C;
      for (index_t k = 0; k < C; ++k) row[k] += s.d_x[static_cast<std::size_t>(i * C + k)];
    }
  } else {
    for (index_t i = 0; i < n * C; ++i) d_params[i] += s.d_x[static_cast<std::size_t>(i)];
  }
}

}  // namespace decoder
}  // namespace v0
}  // namespace flexsplat
