#pragma once
// The Gaussian decoder: N_G learnable queries, an initial splat head, then L layers of
// [multi-view deformable attention -> self-attention -> FFN] (each with a residual and LayerNorm) whose splat heads
// refine the running 24-value estimate. Every layer's Gaussians are returned. Parameters live in one flat block
// (DecoderParamLayout gives the offsets); backward adds into a parallel gradient block and reaches the fused features,
// depth maps and cameras.
#include <algorithm>
#include <random>
#include <vector>

#include "flexsplat/decoder/deformable_attention.hpp"
#include "flexsplat/decoder/gaussians.hpp"
#include "flexsplat/decoder/init.hpp"
#include "flexsplat/decoder/self_attention.hpp"
#include "flexsplat/decoder/splat_head.hpp"
#include "flexsplat/nn/activations.hpp"
#include "flexsplat/nn/layernorm.hpp"

namespace flexsplat {
inline namespace v0 {
namespace decoder {

struct DecoderConfig {
  index_t dim = 256, ffn = 1024, heads = 8, layers = 3, points = 4, max_views = 4, value_dim = 128;
  index_t max_queries = 20480;  // rows of the query embedding table; a run uses the first N_G
  bool local_attention = false;
  index_t window = 512;
  MVDeformConfig deform() const { return {dim, value_dim, heads, points, max_views}; }
  SelfAttentionConfig self_attention() const { return {dim, heads, local_attention, window}; }
};

// Default budget per view count (paper: 10K / 15K / 20K for 1 / 2 / 4 views).
inline index_t default_gaussian_budget(index_t views) { return views <= 1 ? 10000 : views <= 2 ? 15000 : 20000; }

struct DecoderLayerOffsets {
  index_t deform, ln1_g, ln1_b, attn, ln2_g, ln2_b, ffn_w1, ffn_b1, ffn_w2, ffn_b2, ln3_g, ln3_b, head_w, head_b;
};

struct DecoderParamLayout {
  index_t embeddings, init_head_w, init_head_b, size;
  std::vector<DecoderLayerOffsets> layer;
  explicit DecoderParamLayout(const DecoderConfig& c) {
    index_t at = 0;
    auto take = [&](index_t n) { const index_t o = at; at += n; return o; };
    embeddings = take(c.max_queries * c.dim);
    init_head_w = take(splat_values * c.dim);
    init_head_b = take(splat_values);
    for (index_t l = 0; l < c.layers; ++l) {
      DecoderLayerOffsets o;
      o.deform = take(MVDeformParamLayout(c.deform()).size);
      o.ln1_g = take(c.dim);
      o.ln1_b = take(c.dim);
      o.attn = take(SelfAttentionParamLayout(c.self_attention()).size);
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
      layer.push_back(o);
    }
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

template <class T>
struct DecoderLayerCache {
  std::vector<T> x_in, mv_out, r1, mean1, rstd1, x1, sa_out, r2, mean2, rstd2, x2, hidden_pre, hidden, ffn_out, r3,
      mean3, rstd3, x3, delta;
  MVDeformCache<T> deform;
  SelfAttentionCache<T> attention;
};

// Forward results and everything backward needs. gaussians[0] is the initial estimate, gaussians[l + 1] layer l's.
template <class T>
struct DecoderState {
  index_t n = 0;
  Anchors anchors;
  SceneCentre scene_centre;
  std::vector<T> base_depth;
  std::vector<unsigned char> depth_used;
  std::vector<std::vector<T>> states;  // [layers + 1][N, 24]
  std::vector<GaussianSet<T>> gaussians;
  std::vector<DecoderLayerCache<T>> layers;
};

namespace detail {
template <class T>
void gelu_parallel_forward(T* out, const T* in, index_t n) {
  parallel_for((n + 4095) / 4096, [&](index_t b0, index_t b1, int) {
    const index_t i0 = b0 * 4096, i1 = std::min(n, b1 * 4096);
    nn::gelu_forward(out + i0, in + i0, i1 - i0);
  });
}
template <class T>
void gelu_parallel_backward(T* d_in, const T* d_out, const T* in, index_t n) {
  parallel_for((n + 4095) / 4096, [&](index_t b0, index_t b1, int) {
    const index_t i0 = b0 * 4096, i1 = std::min(n, b1 * 4096);
    nn::gelu_backward(d_in + i0, d_out + i0, in + i0, i1 - i0);
  });
}
template <class T>
void add(T* out, const T* a, const T* b, index_t n) {
  for (index_t i = 0; i < n; ++i) out[i] = a[i] + b[i];
}
}  // namespace detail

// Runs the decoder for n_queries Gaussians on fused features [V, value_dim, h, w] and the views' geometry.
template <class T>
void decoder_forward(DecoderState<T>& st, index_t n_queries, const T* params, const DecoderConfig& c,
                     const FeatureMaps<T>& features, const ViewGeometry<T>& g) {
  validate_geometry(g);
  validate_features(features, c.deform(), g.views);
  require(n_queries >= 1 && n_queries <= c.max_queries, "decoder: Gaussian budget ", n_queries, " is outside [1, ",
          c.max_queries, "]");
  const DecoderParamLayout L(c);
  const index_t n = n_queries, C = c.dim;
  st.n = n;
  st.anchors = make_anchors(n, g.views, g.image_w, g.image_h);
  st.scene_centre = scene_centre_from_axes(g);
  const T centre[3] = {static_cast<T>(st.scene_centre.centre[0]), static_cast<T>(st.scene_centre.centre[1]),
                       static_cast<T>(st.scene_centre.centre[2])};
  st.base_depth.resize(static_cast<std::size_t>(n));
  st.depth_used.resize(static_cast<std::size_t>(n));
  anchor_depths(st.base_depth.data(), st.depth_used.data(), g, st.anchors, centre);
  st.states.assign(static_cast<std::size_t>(c.layers + 1), std::vector<T>(static_cast<std::size_t>(n * splat_values)));
  st.gaussians.resize(static_cast<std::size_t>(c.layers + 1));
  st.layers.resize(static_cast<std::size_t>(c.layers));
  const T* x = params + L.embeddings;
  splat_head_forward(st.states[0].data(), x, params + L.init_head_w, params + L.init_head_b, n, C, true);
  gaussians_forward(st.gaussians[0], st.states[0].data(), st.base_depth.data(), st.anchors, g);
  const std::size_t nc = static_cast<std::size_t>(n * C);
  for (index_t l = 0; l < c.layers; ++l) {
    const auto& o = L.layer[l];
    auto& k = st.layers[l];
    const T* centres = st.gaussians[l].means.data();
    k.x_in.assign(x, x + n * C);
    for (auto* v : {&k.mv_out, &k.r1, &k.x1, &k.sa_out, &k.r2, &k.x2, &k.ffn_out, &k.r3, &k.x3}) v->resize(nc);
    for (auto* v : {&k.mean1, &k.rstd1, &k.mean2, &k.rstd2, &k.mean3, &k.rstd3}) v->resize(static_cast<std::size_t>(n));
    k.hidden_pre.resize(static_cast<std::size_t>(n * c.ffn));
    k.hidden.resize(static_cast<std::size_t>(n * c.ffn));
    k.delta.resize(static_cast<std::size_t>(n * splat_values));
    mv_deform_forward(k.mv_out.data(), k.deform, k.x_in.data(), centres, n, params + o.deform, c.deform(), features, g);
    detail::add(k.r1.data(), k.x_in.data(), k.mv_out.data(), n * C);
    nn::layernorm_forward(k.x1.data(), k.r1.data(), params + o.ln1_g, params + o.ln1_b, n, C, static_cast<T>(layernorm_eps),
                          {k.mean1.data(), k.rstd1.data()});
    self_attention_forward(k.sa_out.data(), k.attention, k.x1.data(), centres, n, params + o.attn, c.self_attention());
    detail::add(k.r2.data(), k.x1.data(), k.sa_out.data(), n * C);
    nn::layernorm_forward(k.x2.data(), k.r2.data(), params + o.ln2_g, params + o.ln2_b, n, C, static_cast<T>(layernorm_eps),
                          {k.mean2.data(), k.rstd2.data()});
    nn::linear_forward(k.hidden_pre.data(), k.x2.data(), params + o.ffn_w1, params + o.ffn_b1, n, C, c.ffn);
    detail::gelu_parallel_forward(k.hidden.data(), k.hidden_pre.data(), n * c.ffn);
    nn::linear_forward(k.ffn_out.data(), k.hidden.data(), params + o.ffn_w2, params + o.ffn_b2, n, c.ffn, C);
    detail::add(k.r3.data(), k.x2.data(), k.ffn_out.data(), n * C);
    nn::layernorm_forward(k.x3.data(), k.r3.data(), params + o.ln3_g, params + o.ln3_b, n, C, static_cast<T>(layernorm_eps),
                          {k.mean3.data(), k.rstd3.data()});
    splat_head_forward(k.delta.data(), k.x3.data(), params + o.head_w, params + o.head_b, n, C, false);
    compose_forward(st.states[l + 1].data(), st.states[l].data(), k.delta.data(), n);
    gaussians_forward(st.gaussians[l + 1], st.states[l + 1].data(), st.base_depth.data(), st.anchors, g);
    x = k.x3.data();
  }
}

// d_gaussians[l] is the loss gradient of gaussians[l] (null members: no gradient). Adds into d_params, d_features
// (NCHW like the input, may be null) and d_geometry (K, world_to_camera, depth; null members skipped).
template <class T>
void decoder_backward(T* d_params, T* d_features, const ViewGeometryGrad<T>& d_geometry,
                      const std::vector<GaussianSetGrad<T>>& d_gaussians, DecoderState<T>& st, const T* params,
                      const DecoderConfig& c, const FeatureMaps<T>& features, const ViewGeometry<T>& g) {
  require(static_cast<index_t>(d_gaussians.size()) == c.layers + 1, "decoder_backward: ", d_gaussians.size(),
          " gradient sets for ", c.layers + 1, " Gaussian sets");
  const DecoderParamLayout L(c);
  const index_t n = st.n, C = c.dim;
  const std::size_t nc = static_cast<std::size_t>(n * C);
  std::vector<T> d_state(static_cast<std::size_t>(n * splat_values), T(0)), d_prev_state(d_state.size());
  std::vector<T> d_centres(static_cast<std::size_t>(3 * n), T(0)), d_means(d_centres.size());
  std::vector<T> d_x(nc, T(0));  // gradient of the current layer's output features
  // Loss gradient plus the gradient that later layers' attention sent into these centres.
  auto gaussians_grad = [&](index_t set, std::vector<T>& d_st) {
    GaussianSetGrad<T> d = d_gaussians[set];
    if (d.means) std::transform(d.means, d.means + 3 * n, d_centres.begin(), d_means.begin(), std::plus<T>());
    else d_means = d_centres;
    d.means = d_means.data();
    gaussians_backward(d_st.data(), {d_geometry.K, d_geometry.world_to_camera, d_geometry.depth}, d,
                       st.states[set].data(), st.base_depth.data(), st.depth_used.data(), st.anchors, g);
    std::fill(d_centres.begin(), d_centres.end(), T(0));
  };
  std::vector<T> d_delta(d_state.size()), d_r(nc), d_tmp(nc), d_hidden(static_cast<std::size_t>(n * c.ffn)),
      d_hidden_pre(d_hidden.size());
  for (index_t l = c.layers - 1; l >= 0; --l) {
    const auto& o = L.layer[l];
    auto& k = st.layers[l];
    gaussians_grad(l + 1, d_state);
    std::fill(d_prev_state.begin(), d_prev_state.end(), T(0));
    std::fill(d_delta.begin(), d_delta.end(), T(0));
    compose_backward(d_prev_state.data(), d_delta.data(), d_state.data(), st.states[l].data(), k.delta.data(), n);
    splat_head_backward(d_x.data(), d_params + o.head_w, d_params + o.head_b, d_delta.data(), k.x3.data(), params + o.head_w,
                        n, C);
    // x3 = LN3(x2 + FFN(x2))
    std::fill(d_r.begin(), d_r.end(), T(0));
    nn::layernorm_backward(d_r.data(), d_params + o.ln3_g, d_params + o.ln3_b, d_x.data(), k.r3.data(), params + o.ln3_g,
                           n, C, {k.mean3.data(), k.rstd3.data()});
    d_tmp = d_r;  // into x2 through the residual
    std::fill(d_hidden.begin(), d_hidden.end(), T(0));
    nn::linear_backward(d_hidden.data(), d_params + o.ffn_w2, d_params + o.ffn_b2, d_r.data(), k.hidden.data(),
                        params + o.ffn_w2, n, c.ffn, C);
    std::fill(d_hidden_pre.begin(), d_hidden_pre.end(), T(0));
    detail::gelu_parallel_backward(d_hidden_pre.data(), d_hidden.data(), k.hidden_pre.data(), n * c.ffn);
    nn::linear_backward(d_tmp.data(), d_params + o.ffn_w1, d_params + o.ffn_b1, d_hidden_pre.data(), k.x2.data(),
                        params + o.ffn_w1, n, C, c.ffn);
    // x2 = LN2(x1 + SA(x1))
    std::fill(d_r.begin(), d_r.end(), T(0));
    nn::layernorm_backward(d_r.data(), d_params + o.ln2_g, d_params + o.ln2_b, d_tmp.data(), k.r2.data(), params + o.ln2_g,
                           n, C, {k.mean2.data(), k.rstd2.data()});
    d_tmp = d_r;
    self_attention_backward(d_tmp.data(), d_params + o.attn, d_r.data(), k.attention, k.x1.data(), params + o.attn,
                            c.self_attention());
    // x1 = LN1(x + MVDA(x, centres))
    std::fill(d_r.begin(), d_r.end(), T(0));
    nn::layernorm_backward(d_r.data(), d_params + o.ln1_g, d_params + o.ln1_b, d_tmp.data(), k.r1.data(), params + o.ln1_g,
                           n, C, {k.mean1.data(), k.rstd1.data()});
    d_x = d_r;
    mv_deform_backward(d_x.data(), d_centres.data(), d_params + o.deform, d_features,
                       ViewGeometryGrad<T>{d_geometry.K, d_geometry.world_to_camera, nullptr}, d_r.data(), k.deform,
                       k.x_in.data(), st.gaussians[l].means.data(), params + o.deform, c.deform(), features, g);
    d_state.swap(d_prev_state);
  }
  // The initial estimate: its own loss gradient, the first layer's centre gradient and the composed-state gradient.
  gaussians_grad(0, d_state);
  splat_head_backward(d_x.data(), d_params + L.init_head_w, d_params + L.init_head_b, d_state.data(), params + L.embeddings,
                      params + L.init_head_w, n, C);
  for (std::size_t i = 0; i < nc; ++i) d_params[L.embeddings + static_cast<index_t>(i)] += d_x[i];
}

}  // namespace decoder
}  // namespace v0
}  // namespace flexsplat
