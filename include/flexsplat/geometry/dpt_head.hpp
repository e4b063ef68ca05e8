#pragma once
// VGGT's DPT head as used for depth (vggt/heads/dpt_head.py at 44b3afb, feature_only = False), forward and backward.
// Per frame: four aggregator block outputs -> LayerNorm -> 1x1 "projects" (+ uv sin/cos embedding) -> resize layers
// (4x and 2x transposed convs, identity, stride-2 conv) -> 3x3 "layer_rn" convs -> four fusion blocks (refinenet4 ..
// refinenet1) -> output_conv1 -> bilinear (align_corners) upsampling to patch_h*patch x patch_w*patch (+ embedding)
// -> output_conv2 (3x3, ReLU, 1x1) -> activations (exp depth, 1 + exp confidence).
//
// Fusion blocks and residual conv units reproduce the official modules exactly, including one easy-to-miss detail:
// the units use nn.ReLU(inplace=True) on their input, so the skip connection adds relu(x), not x.
#include <algorithm>
#include <array>
#include <cmath>
#include <span>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/gemm.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/geometry/dpt_weights.hpp"
#include "flexsplat/io/param_check.hpp"
#include "flexsplat/io/param_source.hpp"
#include "flexsplat/nn/activations.hpp"
#include "flexsplat/nn/conv.hpp"
#include "flexsplat/nn/interpolate.hpp"
#include "flexsplat/nn/layernorm.hpp"

namespace flexsplat {
inline namespace v0 {
namespace geometry {

// Spatial sizes of one frame's maps for a patch grid of patch_h x patch_w.
struct DptGeometry {
  index_t patch_h = 0, patch_w = 0;
  std::array<index_t, 4> h{}, w{};  // pyramid levels after the resize layers (4x, 2x, 1x, 1/2x)
  index_t fused_h = 0, fused_w = 0;  // refinenet1 output (2x level 0)
  index_t out_h = 0, out_w = 0;      // final maps: patch grid times patch size

  DptGeometry(index_t ph, index_t pw, index_t patch) : patch_h(ph), patch_w(pw) {
    h = {4 * ph, 2 * ph, ph, (ph - 1) / 2 + 1};
    w = {4 * pw, 2 * pw, pw, (pw - 1) / 2 + 1};
    fused_h = 2 * h[0];
    fused_w = 2 * w[0];
    out_h = ph * patch;
    out_w = pw * patch;
  }
  index_t level_size(int i) const { return h[i] * w[i]; }
};

// Convolutions larger than this run over horizontal bands so their scratch (im2col columns, or the shifted path's
// padded rows) stays within it (elements).
inline constexpr index_t dpt_conv_scratch_budget = index_t(1) << 22;

namespace detail {
// k x k convolution, stride 1, zero padding (k-1)/2, one NCHW image; nn::conv2d runs bands of output rows when the
// scratch (dpt_band_scratch) is smaller than the whole column matrix.
inline nn::Conv2dShape same_conv_shape(index_t cin, index_t cout, index_t h, index_t w, index_t k) {
  return {1, cin, cout, h, w, k, k, 1, (k - 1) / 2};
}

// The whole column matrix, or the budget if that is smaller (but at least one output row's columns).
inline index_t dpt_band_scratch(index_t cin, index_t k, index_t h, index_t w) {
  const nn::Conv2dShape s = same_conv_shape(cin, 1, h, w, k);  // the column matrix does not depend on C_out
  return std::min(nn::conv2d_scratch_size(s), std::max(nn::conv2d_row_scratch_size(s), dpt_conv_scratch_budget));
}

// Offsets (in elements) of one frame's buffers inside the workspace.
struct DptWorkspaceLayout {
  index_t normed = 0, proj = 0, level[4]{}, rn[4]{}, a = 0, b = 0, c = 0, d = 0, fused = 0, head_in = 0, up = 0,
          image_a = 0, image_b = 0, hidden = 0, out = 0, pos_table = 0, scratch = 0, total = 0;
  index_t scratch_size = 0;
};

inline DptWorkspaceLayout dpt_workspace_layout(const DptHeadConfig& cfg, const DptGeometry& g) {
  DptWorkspaceLayout L;
  const index_t P = g.patch_h * g.patch_w, F = cfg.features, Fh = cfg.head_features();
  index_t cursor = 0;
  auto take = [&](index_t n) {
    const index_t at = cursor;
    cursor += (n + 15) / 16 * 16;  // 64-byte aligned sub-buffers for float
    return at;
  };
  const index_t max_oc = *std::max_element(cfg.out_channels.begin(), cfg.out_channels.end());
  L.normed = take(P * cfg.dim_in);
  L.proj = take(max_oc * P);
  for (int i = 0; i < 4; ++i) L.level[i] = take(cfg.out_channels[i] * g.level_size(i));
  for (int i = 0; i < 4; ++i) L.rn[i] = take(F * g.level_size(i));
  const index_t level_max = F * g.level_size(0);
  L.a = take(level_max);
  L.b = take(level_max);
  L.c = take(level_max);
  L.d = take(level_max);
  L.fused = take(F * g.fused_h * g.fused_w);
  L.head_in = take(Fh * g.fused_h * g.fused_w);
  const index_t full = g.out_h * g.out_w;
  L.up = take(cfg.conv2_in() * full);
  const index_t image_map = cfg.image_convs > 0 ? cfg.image_width * full : 0;
  L.image_a = take(image_map);
  L.image_b = take(image_map);
  L.hidden = take(DptHeadConfig::head_hidden * full);
  L.out = take(cfg.output_dim * full);
  L.pos_table = take(std::max({max_oc, Fh}) / 2 * (std::max(g.out_h, g.h[0]) + std::max(g.out_w, g.w[0])));
  index_t s = 0;
  s = std::max(s, nn::conv_transpose2d_scratch_size({1, cfg.out_channels[0], cfg.out_channels[0], g.h[2], g.w[2], 4, 4, 4, 0}));
  s = std::max(s, nn::conv_transpose2d_scratch_size({1, cfg.out_channels[1], cfg.out_channels[1], g.h[2], g.w[2], 2, 2, 2, 0}));
  s = std::max(s, nn::conv2d_scratch_size({1, cfg.out_channels[3], cfg.out_channels[3], g.h[2], g.w[2], 3, 3, 2, 1}));
  for (int i = 0; i < 4; ++i) s = std::max(s, dpt_band_scratch(cfg.out_channels[i], 3, g.h[i], g.w[i]));
  for (int i = 0; i < 4; ++i) s = std::max(s, dpt_band_scratch(F, 3, g.h[i], g.w[i]));
  s = std::max(s, dpt_band_scratch(F, 3, g.fused_h, g.fused_w));
  s = std::max(s, dpt_band_scratch(cfg.conv2_in(), 3, g.out_h, g.out_w));
  if (cfg.image_convs > 0)
    s = std::max(s, dpt_band_scratch(std::max(cfg.image_channels, cfg.image_width), 3, g.out_h, g.out_w));
  L.scratch = take(s);
  L.scratch_size = s;
  L.total = cursor;
  return L;
}

template <class T>
void conv2d_same(T* out, const T* in, const T* weight, const T* bias, index_t cin, index_t cout, index_t h, index_t w,
                 index_t k, std::span<T> scratch) {
  nn::conv2d_forward(out, in, weight, bias, same_conv_shape(cin, cout, h, w, k), scratch);
}

// Backward of conv2d_same: adds into d_in, d_weight, d_bias (each may be null).
template <class T>
void conv2d_same_backward(T* d_in, T* d_weight, T* d_bias, const T* d_out, const T* in, const T* weight, index_t cin,
                          index_t cout, index_t h, index_t w, index_t k, std::span<T> scratch) {
  nn::conv2d_backward(d_in, d_weight, d_bias, d_out, in, weight, same_conv_shape(cin, cout, h, w, k), scratch);
}

template <class T>
void relu_copy(T* out, const T* in, index_t n) {
  parallel_for((n + 8191) / 8192, [&](index_t c0, index_t c1, int) {
    for (index_t i = c0 * 8192, e = std::min(n, c1 * 8192); i < e; ++i) out[i] = in[i] > T(0) ? in[i] : T(0);
  });
}

template <class T>
void add_into(T* x, const T* y, index_t n) {
  parallel_for((n + 8191) / 8192, [&](index_t c0, index_t c1, int) {
    for (index_t i = c0 * 8192, e = std::min(n, c1 * 8192); i < e; ++i) x[i] += y[i];
  });
}

// Bilinear resize with align_corners = True of [planes, h, w] -> [planes, oh, ow], planes split over the pool.
template <class T>
void resize_align_corners(T* out, const T* in, index_t planes, index_t h, index_t w, index_t oh, index_t ow) {
  parallel_for(planes, [&](index_t p0, index_t p1, int) {
    nn::bilinear_resize_forward(out + p0 * oh * ow, in + p0 * h * w, p1 - p0, h, w, oh, ow, true);
  });
}

template <class T>
void resize_align_corners_backward(T* d_in, const T* d_out, index_t planes, index_t h, index_t w, index_t oh,
                                   index_t ow) {
  parallel_for(planes, [&](index_t p0, index_t p1, int) {
    nn::bilinear_resize_backward(d_in + p0 * h * w, d_out + p0 * oh * ow, p1 - p0, h, w, oh, ow, true);
  });
}

// ReLU backward in place: d is zeroed where `activated` = relu(pre) is not positive (exactly where pre <= 0).
template <class T>
void relu_mask(T* d, const T* activated, index_t n) {
  parallel_for((n + 8191) / 8192, [&](index_t c0, index_t c1, int) {
    for (index_t i = c0 * 8192, e = std::min(n, c1 * 8192); i < e; ++i)
      d[i] = activated[i] > T(0) ? d[i] : T(0);  // a select, not a branch: it vectorises
  });
}

// x [C, h, w] += ratio * sincos(uv grid) as VGGT's _apply_pos_embed: channels [0, C/2) encode the column's u,
// [C/2, C) the row's v, each half as [sin(p * omega_d), cos(p * omega_d)] with omega_d = omega0^(-d / (C/4)).
template <class T>
void add_uv_pos_embed(T* x, index_t C, index_t h, index_t w, double aspect, double ratio, double omega0, T* table) {
  const index_t quarter = C / 4;
  const double diag = std::sqrt(aspect * aspect + 1.0);
  const double span_x = aspect / diag, span_y = 1.0 / diag;
  auto coord = [](index_t i, index_t n, double span) {  // torch.linspace(-s (n-1)/n, s (n-1)/n, n)[i]
    const double lo = -span * static_cast<double>(n - 1) / static_cast<double>(n);
    return n == 1 ? lo : lo + 2.0 * -lo * static_cast<double>(i) / static_cast<double>(n - 1);
  };
  T* col_table = table;              // [C/2, w]
  T* row_table = table + (C / 2) * w;  // [C/2, h]
  for (index_t d = 0; d < quarter; ++d) {
    const double omega = std::pow(omega0, -static_cast<double>(d) / static_cast<double>(quarter));
    for (index_t i = 0; i < w; ++i) {
      const double a = coord(i, w, span_x) * omega;
      col_table[d * w + i] = static_cast<T>(ratio * std::sin(a));
      col_table[(d + quarter) * w + i] = static_cast<T>(ratio * std::cos(a));
    }
    for (index_t i = 0; i < h; ++i) {
      const double a = coord(i, h, span_y) * omega;
      row_table[d * h + i] = static_cast<T>(ratio * std::sin(a));
      row_table[(d + quarter) * h + i] = static_cast<T>(ratio * std::cos(a));
    }
  }
  parallel_for(C, [&](index_t c0, index_t c1, int) {
    for (index_t c = c0; c < c1; ++c) {
      T* plane = x + c * h * w;
      if (c < C / 2) {
        const T* t = col_table + c * w;
        for (index_t y = 0; y < h; ++y)
          for (index_t i = 0; i < w; ++i) plane[y * w + i] += t[i];
      } else {
        const T* t = row_table + (c - C / 2) * h;
        for (index_t y = 0; y < h; ++y)
          for (index_t i = 0; i < w; ++i) plane[y * w + i] += t[y];
      }
    }
  });
}

template <class T>
T dpt_activate(T v, DptActivation a) {
  switch (a) {
    case DptActivation::exp: return std::exp(v);
    case DptActivation::linear: return v;
    case DptActivation::relu: return v > T(0) ? v : T(0);
    case DptActivation::inv_log: return v < T(0) ? -std::expm1(-v) : std::expm1(v);
    case DptActivation::sigmoid: return nn::sigmoid(v);
  }
  return v;
}

// Derivatives of the activations with respect to their pre-activation input v.
template <class T>
T dpt_activate_grad(T v, DptActivation a) {
  switch (a) {
    case DptActivation::exp: return std::exp(v);
    case DptActivation::linear: return T(1);
    case DptActivation::relu: return v > T(0) ? T(1) : T(0);
    case DptActivation::inv_log: return std::exp(std::abs(v));
    case DptActivation::sigmoid: {
      return nn::sigmoid_vjp(v, T(1));
    }
  }
  return T(1);
}

template <class T>
T dpt_conf_activate_grad(T v, DptConfActivation a) {
  switch (a) {
    case DptConfActivation::expp1:
    case DptConfActivation::expp0: return std::exp(v);
    case DptConfActivation::sigmoid: {
      return nn::sigmoid_vjp(v, T(1));
    }
  }
  return T(1);
}

template <class T>
T dpt_conf_activate(T v, DptConfActivation a) {
  switch (a) {
    case DptConfActivation::expp1: return T(1) + std::exp(v);
    case DptConfActivation::expp0: return std::exp(v);
    case DptConfActivation::sigmoid: return nn::sigmoid(v);
  }
  return v;
}
}  // namespace detail

// Workspace elements dpt_head_forward needs for a patch grid of patch_h x patch_w (independent of the frame count).
inline index_t dpt_head_workspace_size(const DptHeadConfig& cfg, index_t patch_h, index_t patch_w) {
  return detail::dpt_workspace_layout(cfg, DptGeometry(patch_h, patch_w, cfg.patch_size)).total;
}

// Where the head writes; every pointer but `preds` and `conf` may be null. OH = patch_h * patch, OW = patch_w * patch.
template <class T>
struct DptHeadOutputs {
  T* preds = nullptr;          // [frames, OH, OW, output_dim - 1] activated predictions (depth for the depth head)
  T* conf = nullptr;           // [frames, OH, OW] activated confidence
  T* features = nullptr;       // [frames, features/2, OH, OW]: the full-resolution map entering output_conv2 (the
                               // depth features FlexSplat's decoder fusion consumes)
  T* fused_features = nullptr; // [frames, features/2, 8 patch_h, 8 patch_w]: output_conv1, before upsampling
};

// Gradients with respect to DptHeadOutputs for dpt_head_backward; every pointer may be null (no gradient).
template <class T>
struct DptHeadOutputGrads {
  const T* preds = nullptr;           // [frames, OH, OW, output_dim - 1]
  const T* conf = nullptr;            // [frames, OH, OW]
  const T* features = nullptr;        // [frames, features/2, OH, OW]
  const T* fused_features = nullptr;  // [frames, features/2, 8 patch_h, 8 patch_w]
};

// Gradient slots mirroring DptHeadWeights (null where the weight is absent or its gradient is not wanted).
template <class T>
struct ConvGrads {
  T* weight = nullptr;
  T* bias = nullptr;
};

template <class T>
struct ResidualConvUnitGrads {
  ConvGrads<T> conv1, conv2;
};

template <class T>
struct FusionBlockGrads {
  ResidualConvUnitGrads<T> unit1;  // null in refinenet4
  ResidualConvUnitGrads<T> unit2;
  ConvGrads<T> out_conv;
};

template <class T>
struct DptHeadGrads {
  T *norm_weight = nullptr, *norm_bias = nullptr;
  std::array<ConvGrads<T>, 4> projects;
  std::array<ConvGrads<T>, 4> resize;  // [2] stays null
  std::array<T*, 4> layer_rn{};
  std::array<FusionBlockGrads<T>, 4> refinenet;
  ConvGrads<T> output_conv1, output_conv2_0, output_conv2_2;
  std::array<ConvGrads<T>, 4> image_conv;
};

namespace detail {
template <class T>
ConvGrads<T> rebase_conv_grads(const ConvWeights<T>& c, const T* params_base, T* grads_base) {
  return {io::rebase_pointer(c.weight, params_base, grads_base), io::rebase_pointer(c.bias, params_base, grads_base)};
}
}  // namespace detail

// Each weight's gradient sits at the same offset in the flat gradient block `grads_base` as the weight in the flat
// parameter block `params_base` (every non-null weight must point into that block).
template <class T>
DptHeadGrads<T> dpt_head_grads(const DptHeadWeights<T>& w, const T* params_base, T* grads_base) {
  auto conv = [&](const ConvWeights<T>& c) { return detail::rebase_conv_grads(c, params_base, grads_base); };
  DptHeadGrads<T> g;
  g.norm_weight = io::rebase_pointer(w.norm_weight, params_base, grads_base);
  g.norm_bias = io::rebase_pointer(w.norm_bias, params_base, grads_base);
  for (int i = 0; i < 4; ++i) {
    g.projects[i] = conv(w.projects[i]);
    g.resize[i] = conv(w.resize[i]);
    g.layer_rn[i] = io::rebase_pointer(w.layer_rn[i], params_base, grads_base);
    g.image_conv[i] = conv(w.image_conv[i]);
    const auto& fb = w.refinenet[i];
    auto& gb = g.refinenet[i];
    gb.unit1 = {conv(fb.unit1.conv1), conv(fb.unit1.conv2)};
    gb.unit2 = {conv(fb.unit2.conv1), conv(fb.unit2.conv2)};
    gb.out_conv = conv(fb.out_conv);
  }
  g.output_conv1 = conv(w.output_conv1);
  g.output_conv2_0 = conv(w.output_conv2_0);
  g.output_conv2_2 = conv(w.output_conv2_2);
  return g;
}

// What dpt_head_forward_train keeps for dpt_head_backward (every vector holds all frames; sizes in
// docs/geometry_heads.md). The layers themselves are not copied: backward takes the same pointers again.
template <class T>
struct DptHeadCache {
  index_t frames = 0, tokens = 0, patch_start = 0, image_h = 0, image_w = 0;
  std::vector<T> ln_mean, ln_rstd;         // [frames, 4, P] statistics of `norm` on each level's patch tokens
  std::array<std::vector<T>, 4> proj;      // [frames, oc_i, P]: projection + embedding, the resize layer's input ([2] unused)
  std::array<std::vector<T>, 4> level;     // [frames, oc_i, h_i, w_i]: resize output, layer_rn's input
  std::array<std::vector<T>, 4> unit1_r, unit1_u, unit2_r, unit2_u;  // [frames, F, h_i, w_i]: relu(x), relu(conv1(relu(x)))
  std::array<std::vector<T>, 4> block_out;  // [frames, F, h_i, w_i]: unit2's output, out_conv's input
  std::vector<T> fused;                     // [frames, F, 8 ph, 8 pw]: output_conv1's input
  std::vector<T> up;                        // [frames, conv2_in, OH, OW]: output_conv2.0's input
  std::vector<T> image;                     // [frames, image_channels, OH, OW] when image_convs > 0
  std::vector<T> image_act;                 // [frames, image_convs, image_width, OH, OW]: each image conv after ReLU
  std::vector<T> hidden;                    // [frames, 32, OH, OW] after its ReLU
  std::vector<T> logits;                    // [frames, output_dim, OH, OW] before the activations
  std::vector<T> grad_ws;                   // dpt_head_backward's buffers
};

// Elements a DptHeadCache holds after dpt_head_forward_train on `frames` frames of a patch_h x patch_w grid (the
// activations kept for backward; grad_ws, sized on the first backward, is not included).
inline index_t dpt_head_cache_elements(const DptHeadConfig& cfg, index_t patch_h, index_t patch_w, index_t frames) {
  const DptGeometry g(patch_h, patch_w, cfg.patch_size);
  const index_t P = patch_h * patch_w, F = cfg.features, full = g.out_h * g.out_w;
  const auto& oc = cfg.out_channels;
  index_t n = 8 * P + (oc[0] + oc[1] + oc[3]) * P;
  for (int i = 0; i < 4; ++i) n += oc[i] * g.level_size(i) + (i == 3 ? 3 : 5) * F * g.level_size(i);
  n += F * g.fused_h * g.fused_w + (cfg.conv2_in() + DptHeadConfig::head_hidden + cfg.output_dim) * full;
  if (cfg.image_convs > 0) n += (cfg.image_channels + cfg.image_convs * cfg.image_width) * full;
  return frames * n;
}

namespace detail {
// The DPT fusion block's residual conv unit: result = relu(x) + conv2(relu(conv1(relu(x)))) over F channels of h x w;
// save_r / save_u (may be null) receive relu(x) and relu(conv1(relu(x))), what the backward reads.
template <class T>
void dpt_unit_forward(T* result, const T* x, const ResidualConvUnitWeights<T>& u, T* tmp1, T* tmp2, index_t F,
                      index_t h, index_t w, T* save_r, T* save_u, std::span<T> scratch) {
  const index_t n = F * h * w;
  relu_copy(result, x, n);
  if (save_r) std::copy(result, result + n, save_r);
  conv2d_same(tmp1, result, u.conv1.weight, u.conv1.bias, F, F, h, w, 3, scratch);
  relu_copy(tmp1, tmp1, n);
  if (save_u) std::copy(tmp1, tmp1 + n, save_u);
  conv2d_same(tmp2, tmp1, u.conv2.weight, u.conv2.bias, F, F, h, w, 3, scratch);
  add_into(result, tmp2, n);
}

// d_x += d(result) through result = r + conv2(u), u = relu(conv1(r)), r = relu(x) (r, u saved by the forward);
// d_r, d_u: scratch of F h w values each.
template <class T>
void dpt_unit_backward(T* d_x, const T* d_result, const ResidualConvUnitWeights<T>& u, const ResidualConvUnitGrads<T>& gu,
                       const T* r, const T* uu, index_t F, index_t h, index_t w, T* d_r, T* d_u, std::span<T> scratch) {
  const index_t n = F * h * w;
  std::copy(d_result, d_result + n, d_r);
  std::fill(d_u, d_u + n, T(0));
  conv2d_same_backward(d_u, gu.conv2.weight, gu.conv2.bias, d_result, uu, u.conv2.weight, F, F, h, w, 3, scratch);
  relu_mask(d_u, uu, n);
  conv2d_same_backward(d_r, gu.conv1.weight, gu.conv1.bias, d_u, r, u.conv1.weight, F, F, h, w, 3, scratch);
  relu_mask(d_r, r, n);
  add_into(d_x, d_r, n);
}

// The fusion of frame f, coarse to fine: each level's block [prev + unit1(rn)] -> unit2 -> out_conv, resized to the
// next level (prev) or, at level 0, to the fused grid (fused). A, B, C, Dbuf: scratch of F times level 0's size each
// (prev lives in Dbuf between levels); k (may be null): the cache the backward reads.
template <class T>
void dpt_fusion_forward(T* fused, T* const rn[4], const DptHeadWeights<T>& wt, const DptGeometry& g, index_t F, T* A,
                        T* B, T* C, T* Dbuf, std::span<T> scratch, DptHeadCache<T>* k, index_t f) {
  using Slots = std::array<std::vector<T>, 4> DptHeadCache<T>::*;
  auto slot = [&](Slots member, int level) {
    return k ? ((*k).*member)[level].data() + f * F * g.level_size(level) : static_cast<T*>(nullptr);
  };
  bool has_prev = false;
  for (int level = 3; level >= 0; --level) {
    const auto& fb = wt.refinenet[level];
    const index_t h = g.h[level], w = g.w[level], n = F * h * w;
    const T* x = rn[level];
    if (has_prev) {
      dpt_unit_forward(A, x, fb.unit1, B, C, F, h, w, slot(&DptHeadCache<T>::unit1_r, level),
                       slot(&DptHeadCache<T>::unit1_u, level), scratch);
      add_into(A, Dbuf, n);
      x = A;
    }
    dpt_unit_forward(B, x, fb.unit2, C, Dbuf, F, h, w, slot(&DptHeadCache<T>::unit2_r, level),
                     slot(&DptHeadCache<T>::unit2_u, level), scratch);
    if (k) std::copy(B, B + n, slot(&DptHeadCache<T>::block_out, level));
    // The 1x1 out_conv commutes with bilinear resizing (weights sum to one), so it runs at the smaller size.
    conv2d_same(C, B, fb.out_conv.weight, fb.out_conv.bias, F, F, h, w, 1, scratch);
    if (level > 0) resize_align_corners(Dbuf, C, F, h, w, g.h[level - 1], g.w[level - 1]);
    else resize_align_corners(fused, C, F, h, w, g.fused_h, g.fused_w);
    has_prev = true;
  }
}

// The adjoint of dpt_fusion_forward for frame f: sets d_rn[i] (F times level i's size) from d_fused. d_c, d_b, d_a,
// d_r, d_u: scratch of F times level 0's size each (d_c holds the gradient of the current level's out_conv output).
template <class T>
void dpt_fusion_backward(T* const d_rn[4], const T* d_fused, const DptHeadCache<T>& k, const DptHeadWeights<T>& wt,
                         const DptHeadGrads<T>& grads, const DptGeometry& g, index_t F, index_t f, T* d_c, T* d_b,
                         T* d_a, T* d_r, T* d_u, std::span<T> scratch) {
  auto zero = [](T* p, index_t n) { std::fill(p, p + n, T(0)); };
  zero(d_c, F * g.level_size(0));
  resize_align_corners_backward(d_c, d_fused, F, g.h[0], g.w[0], g.fused_h, g.fused_w);
  for (int i = 0; i < 4; ++i) zero(d_rn[i], F * g.level_size(i));
  for (int level = 0; level < 4; ++level) {
    const auto& fb = wt.refinenet[level];
    const auto& gb = grads.refinenet[level];
    const index_t h = g.h[level], w = g.w[level], n = F * h * w, at = f * n;
    zero(d_b, n);
    conv2d_same_backward(d_b, gb.out_conv.weight, gb.out_conv.bias, d_c, k.block_out[level].data() + at,
                         fb.out_conv.weight, F, F, h, w, 1, scratch);
    if (level == 3) {
      dpt_unit_backward(d_rn[3], d_b, fb.unit2, gb.unit2, k.unit2_r[3].data() + at, k.unit2_u[3].data() + at, F, h, w,
                        d_r, d_u, scratch);
      break;
    }
    zero(d_a, n);
    dpt_unit_backward(d_a, d_b, fb.unit2, gb.unit2, k.unit2_r[level].data() + at, k.unit2_u[level].data() + at, F, h,
                      w, d_r, d_u, scratch);
    // unit2's input is unit1(rn) + prev, prev the coarser level's out_conv output resized to this level.
    dpt_unit_backward(d_rn[level], d_a, fb.unit1, gb.unit1, k.unit1_r[level].data() + at,
                      k.unit1_u[level].data() + at, F, h, w, d_r, d_u, scratch);
    zero(d_c, F * g.level_size(level + 1));
    resize_align_corners_backward(d_c, d_a, F, g.h[level + 1], g.w[level + 1], h, w);
  }
}
}  // namespace detail

namespace detail {
template <class T>
void dpt_head_run(const DptHeadOutputs<T>& out, const DptHeadConfig& cfg, const DptHeadWeights<T>& wt,
                  std::span<const T* const> layers, index_t frames, index_t tokens, index_t patch_start,
                  index_t image_h, index_t image_w, std::span<T> workspace, DptHeadCache<T>* k, const T* image) {
  cfg.validate();
  require(out.preds && out.conf, "DPT head: the prediction and confidence outputs are required");

  require(image_h >= cfg.patch_size && image_w >= cfg.patch_size, "DPT head: image ", image_h, "x", image_w,
          " is smaller than one ", cfg.patch_size, "-pixel patch");
  const DptGeometry g(image_h / cfg.patch_size, image_w / cfg.patch_size, cfg.patch_size);
  const index_t P = g.patch_h * g.patch_w;
  require(cfg.image_channels == 0 || (image && g.out_h == image_h && g.out_w == image_w), "DPT head: image_channels ",
          cfg.image_channels, " needs the image, whole patches (", image_h, "x", image_w, " in ", cfg.patch_size,
          "-pixel patches)");
  require(patch_start >= 0 && tokens == patch_start + P, "DPT head: ", tokens, " tokens per frame, expected ",
          patch_start, " special + ", P, " patch tokens (", g.patch_h, "x", g.patch_w, " grid of a ", image_h, "x",
          image_w, " image)");
  for (index_t idx : cfg.intermediate_layer_idx)
    require(idx < static_cast<index_t>(layers.size()) && layers[idx] != nullptr, "DPT head: intermediate layer ", idx,
            " is not among the ", layers.size(), " aggregator outputs given");
  const auto L = dpt_workspace_layout(cfg, g);
  require(static_cast<index_t>(workspace.size()) >= L.total, "DPT head: workspace has ", workspace.size(),
          " elements, needs ", L.total);
  T* ws = workspace.data();
  std::span<T> scratch(ws + L.scratch, static_cast<std::size_t>(L.scratch_size));
  const index_t F = cfg.features, Fh = cfg.head_features(), D = cfg.dim_in;
  const double aspect = static_cast<double>(image_w) / static_cast<double>(image_h);
  const auto& oc = cfg.out_channels;
  const index_t full = g.out_h * g.out_w, fused_n = F * g.fused_h * g.fused_w;
  constexpr index_t Hh = DptHeadConfig::head_hidden;

  if (k) {
    k->frames = frames, k->tokens = tokens, k->patch_start = patch_start, k->image_h = image_h, k->image_w = image_w;
    auto fit = [&](std::vector<T>& v, index_t per_frame) { v.resize(static_cast<std::size_t>(frames * per_frame)); };
    fit(k->ln_mean, 4 * P);
    fit(k->ln_rstd, 4 * P);
    for (int i = 0; i < 4; ++i) {
      const index_t n = F * g.level_size(i);
      fit(k->proj[i], i == 2 ? 0 : oc[i] * P);
      fit(k->level[i], oc[i] * g.level_size(i));
      fit(k->unit1_r[i], i == 3 ? 0 : n);
      fit(k->unit1_u[i], i == 3 ? 0 : n);
      fit(k->unit2_r[i], n);
      fit(k->unit2_u[i], n);
      fit(k->block_out[i], n);
    }
    fit(k->fused, fused_n);
    fit(k->up, cfg.conv2_in() * full);
    fit(k->image, cfg.image_convs > 0 ? cfg.image_channels * full : 0);
    fit(k->image_act, cfg.image_convs * cfg.image_width * full);
    fit(k->hidden, Hh * full);
    fit(k->logits, cfg.output_dim * full);
  }
  auto save = [](std::vector<T>& dst, index_t f, const T* src, index_t n) {
    std::copy(src, src + n, dst.data() + f * n);
  };

  for (index_t f = 0; f < frames; ++f) {
    // Token pyramid: norm, 1x1 projection (straight from token-major rows), embedding, resize.
    for (int i = 0; i < 4; ++i) {
      const T* tok = layers[cfg.intermediate_layer_idx[i]] + (f * tokens + patch_start) * D;
      T* normed = ws + L.normed;
      nn::LayerNormCache<T> ln_cache;
      if (k) ln_cache = {k->ln_mean.data() + (f * 4 + i) * P, k->ln_rstd.data() + (f * 4 + i) * P};
      nn::layernorm_forward(normed, tok, wt.norm_weight, wt.norm_bias, P, D, static_cast<T>(cfg.norm_eps), ln_cache);
      T* proj = i == 2 ? ws + L.level[2] : ws + L.proj;
      for (index_t o = 0; o < oc[i]; ++o) std::fill(proj + o * P, proj + (o + 1) * P, wt.projects[i].bias[o]);
      gemm(Trans::no, Trans::yes, oc[i], P, D, T(1), wt.projects[i].weight, D, normed, D, T(1), proj, P);
      if (cfg.pos_embed)
        add_uv_pos_embed(proj, oc[i], g.patch_h, g.patch_w, aspect, cfg.pos_embed_ratio, cfg.pos_embed_omega,
                         ws + L.pos_table);
      if (k && i != 2) save(k->proj[i], f, proj, oc[i] * P);
      if (i == 0 || i == 1) {
        const index_t kk = i == 0 ? 4 : 2;
        nn::conv_transpose2d_forward(ws + L.level[i], proj, wt.resize[i].weight, wt.resize[i].bias,
                                     {1, oc[i], oc[i], g.patch_h, g.patch_w, kk, kk, kk, 0}, scratch);
      } else if (i == 3) {
        nn::conv2d_forward(ws + L.level[3], proj, wt.resize[3].weight, wt.resize[3].bias,
                           {1, oc[3], oc[3], g.patch_h, g.patch_w, 3, 3, 2, 1}, scratch);
      }
      if (k) save(k->level[i], f, ws + L.level[i], oc[i] * g.level_size(i));
      conv2d_same(ws + L.rn[i], ws + L.level[i], wt.layer_rn[i], static_cast<const T*>(nullptr), oc[i], F, g.h[i],
                  g.w[i], 3, scratch);
    }

    // Fusion, coarse to fine, into ws + L.fused.
    T* const rn[4] = {ws + L.rn[0], ws + L.rn[1], ws + L.rn[2], ws + L.rn[3]};
    dpt_fusion_forward(ws + L.fused, rn, wt, g, F, ws + L.a, ws + L.b, ws + L.c, ws + L.d, scratch, k, f);

    // Head: output_conv1, upsample to the image grid, embedding, output_conv2, activations.
    T* fused = ws + L.fused;
    if (k) save(k->fused, f, fused, fused_n);
    T* head_in = ws + L.head_in;
    conv2d_same(head_in, fused, wt.output_conv1.weight, wt.output_conv1.bias, F, Fh, g.fused_h, g.fused_w, 3, scratch);
    if (out.fused_features)
      std::copy(head_in, head_in + Fh * g.fused_h * g.fused_w, out.fused_features + f * Fh * g.fused_h * g.fused_w);
    T* up = ws + L.up;
    resize_align_corners(up, head_in, Fh, g.fused_h, g.fused_w, g.out_h, g.out_w);
    if (cfg.pos_embed)
      add_uv_pos_embed(up, Fh, g.out_h, g.out_w, aspect, cfg.pos_embed_ratio, cfg.pos_embed_omega, ws + L.pos_table);
    if (out.features) std::copy(up, up + Fh * full, out.features + f * Fh * full);
    const index_t Ci = cfg.image_channels, Cin = cfg.conv2_in(), Iw = cfg.image_width, In = cfg.image_convs;
    const T* pixels = image + f * Ci * full;
    if (Ci > 0 && In == 0) std::copy(pixels, pixels + Ci * full, up + Fh * full);
    if (In > 0 && k) save(k->image, f, pixels, Ci * full);
    for (index_t j = 0; j < In; ++j) {
      // The last image conv writes straight into the map entering output_conv2.
      T* y = j + 1 == In ? up + Fh * full : ws + (j % 2 == 0 ? L.image_a : L.image_b);
      const T* x = j == 0 ? pixels : ws + (j % 2 == 1 ? L.image_a : L.image_b);
      conv2d_same(y, x, wt.image_conv[j].weight, wt.image_conv[j].bias, j == 0 ? Ci : Iw, Iw, g.out_h, g.out_w, 3,
                  scratch);
      relu_copy(y, y, Iw * full);
      if (k) std::copy(y, y + Iw * full, k->image_act.data() + (f * In + j) * Iw * full);
    }
    if (k) save(k->up, f, up, Cin * full);
    T* hidden = ws + L.hidden;
    conv2d_same(hidden, up, wt.output_conv2_0.weight, wt.output_conv2_0.bias, Cin, Hh, g.out_h, g.out_w, 3, scratch);
    relu_copy(hidden, hidden, Hh * full);
    if (k) save(k->hidden, f, hidden, Hh * full);
    T* logits = ws + L.out;
    conv2d_same(logits, hidden, wt.output_conv2_2.weight, wt.output_conv2_2.bias, Hh, cfg.output_dim, g.out_h, g.out_w,
                1, scratch);
    if (k) save(k->logits, f, logits, cfg.output_dim * full);
    const index_t np = cfg.output_dim - 1;
    T* preds = out.preds + f * full * np;
    T* conf = out.conf + f * full;
    parallel_for(full, [&](index_t p0, index_t p1, int) {
      for (index_t p = p0; p < p1; ++p) {
        for (index_t c = 0; c < np; ++c) preds[p * np + c] = dpt_activate(logits[c * full + p], cfg.activation);
        conf[p] = dpt_conf_activate(logits[np * full + p], cfg.conf_activation);
      }
    });
  }
}
}  // namespace detail

// layers[i] points to aggregator block output i as [frames, tokens, dim_in] (one batch entry); tokens =
// patch_start + patch_h * patch_w with patch_h = image_h / patch, patch_w = image_w / patch (integer division).
// image: [frames, image_channels, OH, OW], read only when cfg.image_channels > 0.
template <class T>
void dpt_head_forward(const DptHeadOutputs<T>& out, const DptHeadConfig& cfg, const DptHeadWeights<T>& wt,
                      std::span<const T* const> layers, index_t frames, index_t tokens, index_t patch_start,
                      index_t image_h, index_t image_w, std::span<T> workspace, const T* image = nullptr) {
  detail::dpt_head_run<T>(out, cfg, wt, layers, frames, tokens, patch_start, image_h, image_w, workspace, nullptr,
                          image);
}

// dpt_head_forward (same arguments, same results bit for bit) that also fills `cache` for dpt_head_backward.
template <class T>
void dpt_head_forward_train(const DptHeadOutputs<T>& out, DptHeadCache<T>& cache, const DptHeadConfig& cfg,
                            const DptHeadWeights<T>& wt, std::span<const T* const> layers, index_t frames,
                            index_t tokens, index_t patch_start, index_t image_h, index_t image_w,
                            std::span<T> workspace, const T* image = nullptr) {
  detail::dpt_head_run<T>(out, cfg, wt, layers, frames, tokens, patch_start, image_h, image_w, workspace, &cache, image);
}

namespace detail {
// Where dpt_head_backward's buffers sit in DptHeadCache::grad_ws (64-byte aligned sub-buffers for float).
struct DptBackwardLayout {
  index_t logits, hidden, up, head_in, fused, c, b, a, r, u, rn[4], level, proj, normed, dnormed, scratch, image_a,
      image_b, d_image, total;
};

inline DptBackwardLayout dpt_backward_layout(const DptHeadConfig& cfg, const DptGeometry& g, index_t scratch_size) {
  const auto& oc = cfg.out_channels;
  const index_t P = g.patch_h * g.patch_w, F = cfg.features, Fh = cfg.head_features(), D = cfg.dim_in;
  const index_t Ci = cfg.image_channels, Cin = cfg.conv2_in(), Iw = cfg.image_width, In = cfg.image_convs;
  const index_t full = g.out_h * g.out_w, fused_hw = g.fused_h * g.fused_w, l0 = F * g.level_size(0);
  const index_t od = cfg.output_dim;
  constexpr index_t Hh = DptHeadConfig::head_hidden;
  index_t max_level = 0;
  for (int i = 0; i < 4; ++i) max_level = std::max(max_level, oc[i] * g.level_size(i));
  const index_t max_oc = *std::max_element(oc.begin(), oc.end());
  index_t cursor = 0;
  auto take = [&](index_t n) {
    const index_t at = cursor;
    cursor += (n + 15) / 16 * 16;
    return at;
  };
  DptBackwardLayout o{};
  o.logits = take(od * full), o.hidden = take(Hh * full), o.up = take(Cin * full), o.head_in = take(Fh * fused_hw);
  o.fused = take(F * fused_hw), o.c = take(l0), o.b = take(l0), o.a = take(l0), o.r = take(l0), o.u = take(l0);
  for (int i = 0; i < 4; ++i) o.rn[i] = take(F * g.level_size(i));
  o.level = take(max_level), o.proj = take(max_oc * P), o.normed = take(P * D), o.dnormed = take(P * D);
  o.scratch = take(scratch_size), o.image_a = take(In > 0 ? Iw * full : 0), o.image_b = take(In > 0 ? Iw * full : 0);
  o.d_image = take(In > 0 ? Ci * full : 0);
  o.total = cursor;
  return o;
}
}  // namespace detail

// Backward of dpt_head_forward_train. Adds into `grads` (null slots skipped), into d_layers[i] (parallel to
// `layers`; entries or the whole span may be empty/null): only the patch-token rows of the intermediate layers
// receive gradient, the special tokens get none; and, with image_channels, into d_image (may be null, as the image).
// `layers` must hold the values the forward saw.
template <class T>
void dpt_head_backward(std::span<T* const> d_layers, const DptHeadGrads<T>& grads, const DptHeadOutputGrads<T>& d_out,
                       DptHeadCache<T>& k, const DptHeadConfig& cfg, const DptHeadWeights<T>& wt,
                       std::span<const T* const> layers, T* d_image = nullptr) {
  cfg.validate();
  require(k.frames >= 1 && !k.up.empty(), "DPT head backward: the cache is empty (run dpt_head_forward_train first)");
  const DptGeometry g(k.image_h / cfg.patch_size, k.image_w / cfg.patch_size, cfg.patch_size);
  const index_t P = g.patch_h * g.patch_w, F = cfg.features, Fh = cfg.head_features(), D = cfg.dim_in;
  const index_t Ci = cfg.image_channels, Cin = cfg.conv2_in(), Co = cfg.image_out(), Iw = cfg.image_width,
                In = cfg.image_convs;
  require(static_cast<index_t>(k.up.size()) == k.frames * Cin * g.out_h * g.out_w &&
              static_cast<index_t>(k.image_act.size()) == k.frames * In * Iw * g.out_h * g.out_w,
          "DPT head backward: the cache was filled for another configuration");
  for (index_t idx : cfg.intermediate_layer_idx)
    require(idx < static_cast<index_t>(layers.size()) && layers[idx] != nullptr, "DPT head backward: intermediate layer ",
            idx, " is not among the ", layers.size(), " aggregator outputs given");
  require(d_layers.empty() || d_layers.size() == layers.size(), "DPT head backward: ", d_layers.size(),
          " layer gradients for ", layers.size(), " layers");
  const auto& oc = cfg.out_channels;
  const index_t full = g.out_h * g.out_w, fused_hw = g.fused_h * g.fused_w;
  const index_t od = cfg.output_dim, np = od - 1;
  constexpr index_t Hh = DptHeadConfig::head_hidden;
  const auto L = detail::dpt_workspace_layout(cfg, g);
  const auto O = detail::dpt_backward_layout(cfg, g, L.scratch_size);
  if (static_cast<index_t>(k.grad_ws.size()) < O.total) k.grad_ws.resize(static_cast<std::size_t>(O.total));
  T* ws = k.grad_ws.data();
  std::span<T> scratch(ws + O.scratch, static_cast<std::size_t>(L.scratch_size));
  auto zero = [](T* p, index_t n) { std::fill(p, p + n, T(0)); };

  for (index_t f = 0; f < k.frames; ++f) {
    // Activations.
    T* d_logits = ws + O.logits;
    const T* logits = k.logits.data() + f * od * full;
    parallel_for(full, [&](index_t p0, index_t p1, int) {
      for (index_t p = p0; p < p1; ++p) {
        for (index_t c = 0; c < np; ++c)
          d_logits[c * full + p] = d_out.preds ? d_out.preds[(f * full + p) * np + c] *
                                                     detail::dpt_activate_grad(logits[c * full + p], cfg.activation)
                                               : T(0);
        d_logits[np * full + p] = d_out.conf ? d_out.conf[f * full + p] * detail::dpt_conf_activate_grad(
                                                                              logits[np * full + p], cfg.conf_activation)
                                             : T(0);
      }
    });
    // output_conv2: 1x1 after the ReLU'd 3x3.
    const T* hidden = k.hidden.data() + f * Hh * full;
    T* d_hidden = ws + O.hidden;
    zero(d_hidden, Hh * full);
    detail::conv2d_same_backward(d_hidden, grads.output_conv2_2.weight, grads.output_conv2_2.bias, d_logits, hidden,
                                 wt.output_conv2_2.weight, Hh, od, g.out_h, g.out_w, 1, scratch);
    detail::relu_mask(d_hidden, hidden, Hh * full);
    T* d_up = ws + O.up;
    if (d_out.features) std::copy(d_out.features + f * Fh * full, d_out.features + (f + 1) * Fh * full, d_up);
    else zero(d_up, Fh * full);
    zero(d_up + Fh * full, Co * full);
    detail::conv2d_same_backward(d_up, grads.output_conv2_0.weight, grads.output_conv2_0.bias, d_hidden,
                                 k.up.data() + f * Cin * full, wt.output_conv2_0.weight, Cin, Hh, g.out_h, g.out_w, 3,
                                 scratch);
    if (d_image && Ci > 0 && In == 0) detail::add_into(d_image + f * Ci * full, d_up + Fh * full, Ci * full);
    // The image convs, last to first; d_y is the gradient of conv j's ReLU'd output.
    T* d_y = d_up + Fh * full;
    for (index_t j = In - 1; j >= 0; --j) {
      detail::relu_mask(d_y, k.image_act.data() + (f * In + j) * Iw * full, Iw * full);
      const index_t cin = j == 0 ? Ci : Iw;
      const T* x = j == 0 ? k.image.data() + f * Ci * full : k.image_act.data() + (f * In + j - 1) * Iw * full;
      T* d_x = j == 0 ? (d_image ? ws + O.d_image : nullptr) : ws + (j % 2 == 1 ? O.image_a : O.image_b);
      if (d_x) zero(d_x, cin * full);
      detail::conv2d_same_backward(d_x, grads.image_conv[j].weight, grads.image_conv[j].bias, d_y, x,
                                   wt.image_conv[j].weight, cin, Iw, g.out_h, g.out_w, 3, scratch);
      if (j == 0 && d_image) detail::add_into(d_image + f * Ci * full, d_x, Ci * full);
      d_y = d_x;
    }
    // The uv embedding is a constant add; the upsampling and output_conv1 are linear.
    T* d_head_in = ws + O.head_in;
    if (d_out.fused_features)
      std::copy(d_out.fused_features + f * Fh * fused_hw, d_out.fused_features + (f + 1) * Fh * fused_hw, d_head_in);
    else zero(d_head_in, Fh * fused_hw);
    detail::resize_align_corners_backward(d_head_in, d_up, Fh, g.fused_h, g.fused_w, g.out_h, g.out_w);
    T* d_fused = ws + O.fused;
    zero(d_fused, F * fused_hw);
    detail::conv2d_same_backward(d_fused, grads.output_conv1.weight, grads.output_conv1.bias, d_head_in,
                                 k.fused.data() + f * F * fused_hw, wt.output_conv1.weight, F, Fh, g.fused_h, g.fused_w,
                                 3, scratch);

    // Fusion, fine to coarse, into the layer_rn outputs' gradients ws + O.rn[i].
    T* const d_rn[4] = {ws + O.rn[0], ws + O.rn[1], ws + O.rn[2], ws + O.rn[3]};
    detail::dpt_fusion_backward(d_rn, d_fused, k, wt, grads, g, F, f, ws + O.c, ws + O.b, ws + O.a, ws + O.r, ws + O.u,
                                scratch);

    // Token pyramid, per level: layer_rn, resize layer, embedding (constant), projection, norm.
    for (int i = 0; i < 4; ++i) {
      const index_t ls = g.level_size(i);
      T* d_level = ws + O.level;
      zero(d_level, oc[i] * ls);
      detail::conv2d_same_backward(d_level, grads.layer_rn[i], static_cast<T*>(nullptr), ws + O.rn[i],
                                   k.level[i].data() + f * oc[i] * ls, wt.layer_rn[i], oc[i], F, g.h[i], g.w[i], 3,
                                   scratch);
      T* d_proj = d_level;
      if (i != 2) {
        d_proj = ws + O.proj;
        zero(d_proj, oc[i] * P);
        const T* proj = k.proj[i].data() + f * oc[i] * P;
        if (i == 3) {
          nn::conv2d_backward(d_proj, grads.resize[3].weight, grads.resize[3].bias, d_level, proj, wt.resize[3].weight,
                              {1, oc[3], oc[3], g.patch_h, g.patch_w, 3, 3, 2, 1}, scratch);
        } else {
          const index_t kk = i == 0 ? 4 : 2;
          nn::conv_transpose2d_backward(d_proj, grads.resize[i].weight, grads.resize[i].bias, d_level, proj,
                                        wt.resize[i].weight, {1, oc[i], oc[i], g.patch_h, g.patch_w, kk, kk, kk, 0},
                                        scratch);
        }
      }
      const index_t idx = cfg.intermediate_layer_idx[i];
      const T* tok = layers[idx] + (f * k.tokens + k.patch_start) * D;
      T* normed = ws + O.normed;
      // The norm's output is recomputed from the tokens (bit-identical to the forward's) rather than stored.
      nn::layernorm_forward(normed, tok, wt.norm_weight, wt.norm_bias, P, D, static_cast<T>(cfg.norm_eps));
      if (grads.projects[i].bias)
        for (index_t o = 0; o < oc[i]; ++o) {
          T sum = 0;
          for (index_t p = 0; p < P; ++p) sum += d_proj[o * P + p];
          grads.projects[i].bias[o] += sum;
        }
      if (grads.projects[i].weight)
        gemm(Trans::no, Trans::no, oc[i], D, P, T(1), d_proj, P, normed, D, T(1), grads.projects[i].weight, D);
      T* d_tok = d_layers.empty() || !d_layers[idx] ? nullptr : d_layers[idx] + (f * k.tokens + k.patch_start) * D;
      if (!d_tok && !grads.norm_weight && !grads.norm_bias) continue;
      T* d_normed = ws + O.dnormed;
      gemm(Trans::yes, Trans::no, P, D, oc[i], T(1), d_proj, P, wt.projects[i].weight, D, T(0), d_normed, D);
      nn::layernorm_backward(d_tok, grads.norm_weight, grads.norm_bias, d_normed, tok, wt.norm_weight, P, D,
                             nn::LayerNormCache<T>{k.ln_mean.data() + (f * 4 + i) * P, k.ln_rstd.data() + (f * 4 + i) * P});
    }
  }
}

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
