#pragma once
// VGGT's DPT head as used for depth (vggt/heads/dpt_head.py at 44b3afb, feature_only = False), forward only.
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
#include "flexsplat/geometry/param_check.hpp"
#include "flexsplat/geometry/param_source.hpp"
#include "flexsplat/nn/conv.hpp"
#include "flexsplat/nn/interpolate.hpp"
#include "flexsplat/nn/layernorm.hpp"

namespace flexsplat {
inline namespace v0 {
namespace geometry {

enum class DptActivation { exp, linear, relu, inv_log, sigmoid };
enum class DptConfActivation { expp1, expp0, sigmoid };

struct DptHeadConfig {
  index_t dim_in = 2048;  // channels of the aggregator outputs (2 x embed_dim: frame and global halves)
  index_t patch_size = 14;
  index_t output_dim = 2;  // output_dim - 1 prediction channels, then one confidence channel
  index_t features = 256;
  std::array<index_t, 4> out_channels{256, 512, 1024, 1024};
  std::array<index_t, 4> intermediate_layer_idx{4, 11, 17, 23};
  DptActivation activation = DptActivation::exp;
  DptConfActivation conf_activation = DptConfActivation::expp1;
  bool pos_embed = true;
  double pos_embed_ratio = 0.1;
  double pos_embed_omega = 100.0;
  double norm_eps = 1e-5;

  index_t head_features() const { return features / 2; }  // channels after output_conv1
  static constexpr index_t head_hidden = 32;                // output_conv2's hidden channels
  void validate() const {
    require(dim_in > 0 && patch_size > 0 && features >= 2 && output_dim >= 2, "DPT head config: dim_in ", dim_in,
            ", patch_size ", patch_size, ", features ", features, ", output_dim ", output_dim,
            " (need positive sizes, features >= 2, output_dim >= 2)");
    for (index_t oc : out_channels) require(oc > 0, "DPT head config: out_channels entry ", oc, " must be positive");
    for (index_t i : intermediate_layer_idx)
      require(i >= 0, "DPT head config: intermediate_layer_idx entry ", i, " must be non-negative");
    if (pos_embed) {
      for (index_t oc : out_channels)
        require(oc % 4 == 0, "DPT head config: positional embedding needs out_channels divisible by 4, got ", oc);
      require(head_features() % 4 == 0, "DPT head config: positional embedding needs features/2 divisible by 4, got ",
              head_features());
    }
  }
};

// The depth head of a VGGT whose config JSON uses the reference bundles' keys (embed_dim, patch_size, features,
// out_channels, intermediate_layer_idx); absent keys keep VGGT-1B's values.
inline DptHeadConfig dpt_head_config_from_vggt_json(const nlohmann::json& j) {
  DptHeadConfig c;
  try {
    if (j.contains("embed_dim")) c.dim_in = 2 * j.at("embed_dim").get<index_t>();
    if (j.contains("patch_size")) c.patch_size = j.at("patch_size").get<index_t>();
    if (j.contains("features")) c.features = j.at("features").get<index_t>();
    if (j.contains("out_channels")) c.out_channels = j.at("out_channels").get<std::array<index_t, 4>>();
    if (j.contains("intermediate_layer_idx"))
      c.intermediate_layer_idx = j.at("intermediate_layer_idx").get<std::array<index_t, 4>>();
  } catch (const nlohmann::json::exception& e) {
    fail("VGGT config ", j.dump(), ": bad DPT head entry: ", e.what());
  }
  c.validate();
  return c;
}

template <class T>
struct ConvWeights {
  const T* weight = nullptr;
  const T* bias = nullptr;
};

template <class T>
struct ResidualConvUnitWeights {
  ConvWeights<T> conv1, conv2;
};

template <class T>
struct FusionBlockWeights {
  ResidualConvUnitWeights<T> unit1;  // resConfUnit1: absent (null) in refinenet4, which has no skip input
  ResidualConvUnitWeights<T> unit2;
  ConvWeights<T> out_conv;
};

template <class T>
struct DptHeadWeights {
  const T *norm_weight = nullptr, *norm_bias = nullptr;
  std::array<ConvWeights<T>, 4> projects;
  std::array<ConvWeights<T>, 4> resize;  // [2] is the identity (no weights)
  std::array<const T*, 4> layer_rn{};    // bias-free 3x3 convs
  std::array<FusionBlockWeights<T>, 4> refinenet;  // [0] = refinenet1 (finest) .. [3] = refinenet4
  ConvWeights<T> output_conv1, output_conv2_0, output_conv2_2;
};

// Parameter names and shapes as in VGGT's state_dict, each prefixed with `prefix`.
inline void append_dpt_head_specs(std::vector<TensorSpec>& out, const DptHeadConfig& c,
                                  const std::string& prefix = "depth_head.") {
  const index_t F = c.features;
  const auto& oc = c.out_channels;
  auto conv = [&](const std::string& name, std::vector<index_t> shape, bool bias = true) {
    const index_t o = shape[0];
    out.push_back({prefix + name + ".weight", std::move(shape)});
    if (bias) out.push_back({prefix + name + ".bias", {o}});
  };
  out.push_back({prefix + "norm.weight", {c.dim_in}});
  out.push_back({prefix + "norm.bias", {c.dim_in}});
  for (int i = 0; i < 4; ++i) conv("projects." + std::to_string(i), {oc[i], c.dim_in, 1, 1});
  conv("resize_layers.0", {oc[0], oc[0], 4, 4});
  conv("resize_layers.1", {oc[1], oc[1], 2, 2});
  conv("resize_layers.3", {oc[3], oc[3], 3, 3});
  for (int i = 0; i < 4; ++i) conv("scratch.layer" + std::to_string(i + 1) + "_rn", {F, oc[i], 3, 3}, false);
  for (int r = 1; r <= 4; ++r) {
    const std::string p = "scratch.refinenet" + std::to_string(r) + ".";
    conv(p + "out_conv", {F, F, 1, 1});
    for (int u = (r == 4 ? 2 : 1); u <= 2; ++u)
      for (int k = 1; k <= 2; ++k) conv(p + "resConfUnit" + std::to_string(u) + ".conv" + std::to_string(k), {F, F, 3, 3});
  }
  conv("scratch.output_conv1", {c.head_features(), F, 3, 3});
  conv("scratch.output_conv2.0", {DptHeadConfig::head_hidden, c.head_features(), 3, 3});
  conv("scratch.output_conv2.2", {c.output_dim, DptHeadConfig::head_hidden, 1, 1});
}

// Binds every pointer through get(name, shape) -> const T* (the name relative to the head), in the order above.
template <class T, class Get>
DptHeadWeights<T> bind_dpt_head_weights(const DptHeadConfig& c, Get&& get) {
  c.validate();
  DptHeadWeights<T> w;
  auto conv = [&](ConvWeights<T>& cw, const std::string& p, std::vector<index_t> shape) {
    cw.weight = get(p + "weight", shape);
    cw.bias = get(p + "bias", std::vector<index_t>{shape[0]});
  };
  const index_t F = c.features;
  const auto& oc = c.out_channels;
  w.norm_weight = get("norm.weight", std::vector<index_t>{c.dim_in});
  w.norm_bias = get("norm.bias", std::vector<index_t>{c.dim_in});
  for (int i = 0; i < 4; ++i) conv(w.projects[i], "projects." + std::to_string(i) + ".", {oc[i], c.dim_in, 1, 1});
  conv(w.resize[0], "resize_layers.0.", {oc[0], oc[0], 4, 4});
  conv(w.resize[1], "resize_layers.1.", {oc[1], oc[1], 2, 2});
  conv(w.resize[3], "resize_layers.3.", {oc[3], oc[3], 3, 3});
  for (int i = 0; i < 4; ++i)
    w.layer_rn[i] = get("scratch.layer" + std::to_string(i + 1) + "_rn.weight", std::vector<index_t>{F, oc[i], 3, 3});
  for (int r = 1; r <= 4; ++r) {
    const std::string p = "scratch.refinenet" + std::to_string(r) + ".";
    auto& fb = w.refinenet[r - 1];
    conv(fb.out_conv, p + "out_conv.", {F, F, 1, 1});
    if (r != 4) {
      conv(fb.unit1.conv1, p + "resConfUnit1.conv1.", {F, F, 3, 3});
      conv(fb.unit1.conv2, p + "resConfUnit1.conv2.", {F, F, 3, 3});
    }
    conv(fb.unit2.conv1, p + "resConfUnit2.conv1.", {F, F, 3, 3});
    conv(fb.unit2.conv2, p + "resConfUnit2.conv2.", {F, F, 3, 3});
  }
  conv(w.output_conv1, "scratch.output_conv1.", {c.head_features(), F, 3, 3});
  conv(w.output_conv2_0, "scratch.output_conv2.0.", {DptHeadConfig::head_hidden, c.head_features(), 3, 3});
  conv(w.output_conv2_2, "scratch.output_conv2.2.", {c.output_dim, DptHeadConfig::head_hidden, 1, 1});
  return w;
}

// Checks every parameter first (one error lists all missing, mis-shaped and unexpected `prefix` tensors), then binds.
template <class T>
DptHeadWeights<T> load_dpt_head_weights(ParamSource<T>& src, const DptHeadConfig& c,
                                        const std::string& prefix = "depth_head.") {
  c.validate();
  std::vector<TensorSpec> specs;
  append_dpt_head_specs(specs, c, prefix);
  check_parameters(src, specs, {prefix}, "DPT head");
  return bind_dpt_head_weights<T>(c, [&](const std::string& name, const std::vector<index_t>& shape) {
    return src.get(prefix + name, shape);
  });
}

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

// Convolutions larger than this run over horizontal bands so their im2col matrix stays within it (elements).
inline constexpr index_t dpt_conv_scratch_budget = index_t(1) << 22;

namespace detail {
inline index_t dpt_band_scratch(index_t cin, index_t k, index_t h, index_t w) {
  const index_t row = cin * k * k * w;
  return std::min(row * h, std::max(row, dpt_conv_scratch_budget));
}

// Offsets (in elements) of one frame's buffers inside the workspace.
struct DptWorkspaceLayout {
  index_t normed = 0, proj = 0, level[4]{}, rn[4]{}, a = 0, b = 0, c = 0, d = 0, fused = 0, head_in = 0, up = 0,
          hidden = 0, out = 0, pos_table = 0, scratch = 0, total = 0;
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
  L.up = take(Fh * full);
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
  s = std::max(s, dpt_band_scratch(Fh, 3, g.out_h, g.out_w));
  L.scratch = take(s);
  L.scratch_size = s;
  L.total = cursor;
  return L;
}

// k x k convolution, stride 1, zero padding (k-1)/2, NCHW single image; bands of output rows bound the im2col size.
template <class T>
void conv2d_same(T* out, const T* in, const T* weight, const T* bias, index_t cin, index_t cout, index_t h, index_t w,
                 index_t k, std::span<T> scratch) {
  const index_t hw = h * w;
  if (k == 1) {
    if (bias)
      for (index_t o = 0; o < cout; ++o) std::fill(out + o * hw, out + (o + 1) * hw, bias[o]);
    gemm(Trans::no, Trans::no, cout, hw, cin, T(1), weight, cin, in, hw, bias ? T(1) : T(0), out, hw);
    return;
  }
  const index_t pad = (k - 1) / 2, K = cin * k * k, row_cols = K * w;
  const index_t band = std::min(h, static_cast<index_t>(scratch.size()) / row_cols);
  require(band >= 1, "DPT conv: scratch of ", scratch.size(), " elements cannot hold one row (", row_cols, ")");
  T* cols = scratch.data();
  for (index_t r0 = 0; r0 < h; r0 += band) {
    const index_t rows = std::min(band, h - r0), n = rows * w;
    parallel_for(cin * k, [&](index_t b0, index_t b1, int) {
      for (index_t ci = b0; ci < b1; ++ci) {
        const index_t c = ci / k, i = ci % k;
        for (index_t j = 0; j < k; ++j) {
          T* dst = cols + ((c * k + i) * k + j) * n;
          for (index_t oy = 0; oy < rows; ++oy, dst += w) {
            const index_t y = r0 + oy + i - pad;
            if (y < 0 || y >= h) {
              std::fill(dst, dst + w, T(0));
              continue;
            }
            const T* src = in + c * hw + y * w;
            const index_t x_lo = std::max<index_t>(0, pad - j), x_hi = std::min<index_t>(w, w + pad - j);
            std::fill(dst, dst + x_lo, T(0));
            std::copy(src + x_lo + j - pad, src + x_hi + j - pad, dst + x_lo);
            std::fill(dst + x_hi, dst + w, T(0));
          }
        }
      }
    });
    if (bias)
      for (index_t o = 0; o < cout; ++o) std::fill(out + o * hw + r0 * w, out + o * hw + r0 * w + n, bias[o]);
    gemm(Trans::no, Trans::no, cout, n, K, T(1), weight, K, cols, n, bias ? T(1) : T(0), out + r0 * w, hw);
  }
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
    case DptActivation::sigmoid: return T(1) / (T(1) + std::exp(-v));
  }
  return v;
}

template <class T>
T dpt_conf_activate(T v, DptConfActivation a) {
  switch (a) {
    case DptConfActivation::expp1: return T(1) + std::exp(v);
    case DptConfActivation::expp0: return std::exp(v);
    case DptConfActivation::sigmoid: return T(1) / (T(1) + std::exp(-v));
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
  T* features = nullptr;       // [frames, features/2, OH, OW]: the full-resolution map entering output_conv2
  T* fused_features = nullptr; // [frames, features/2, 8 patch_h, 8 patch_w]: output_conv1, before upsampling
};

// layers[i] points to aggregator block output i as [frames, tokens, dim_in] (one batch entry); tokens =
// patch_start + patch_h * patch_w with patch_h = image_h / patch, patch_w = image_w / patch (integer division).
template <class T>
void dpt_head_forward(const DptHeadOutputs<T>& out, const DptHeadConfig& cfg, const DptHeadWeights<T>& wt,
                      std::span<const T* const> layers, index_t frames, index_t tokens, index_t patch_start,
                      index_t image_h, index_t image_w, std::span<T> workspace) {
  cfg.validate();
  require(out.preds && out.conf, "DPT head: the prediction and confidence outputs are required");
  require(image_h >= cfg.patch_size && image_w >= cfg.patch_size, "DPT head: image ", image_h, "x", image_w,
          " is smaller than one ", cfg.patch_size, "-pixel patch");
  const DptGeometry g(image_h / cfg.patch_size, image_w / cfg.patch_size, cfg.patch_size);
  const index_t P = g.patch_h * g.patch_w;
  require(patch_start >= 0 && tokens == patch_start + P, "DPT head: ", tokens, " tokens per frame, expected ",
          patch_start, " special + ", P, " patch tokens (", g.patch_h, "x", g.patch_w, " grid of a ", image_h, "x",
          image_w, " image)");
  for (index_t idx : cfg.intermediate_layer_idx)
    require(idx < static_cast<index_t>(layers.size()) && layers[idx] != nullptr, "DPT head: intermediate layer ", idx,
            " is not among the ", layers.size(), " aggregator outputs given");
  const auto L = detail::dpt_workspace_layout(cfg, g);
  require(static_cast<index_t>(workspace.size()) >= L.total, "DPT head: workspace has ", workspace.size(),
          " elements, needs ", L.total);
  T* ws = workspace.data();
  std::span<T> scratch(ws + L.scratch, static_cast<std::size_t>(L.scratch_size));
  const index_t F = cfg.features, Fh = cfg.head_features(), D = cfg.dim_in;
  const double aspect = static_cast<double>(image_w) / static_cast<double>(image_h);
  const auto& oc = cfg.out_channels;

  for (index_t f = 0; f < frames; ++f) {
    // Token pyramid: norm, 1x1 projection (straight from token-major rows), embedding, resize.
    for (int i = 0; i < 4; ++i) {
      const T* tok = layers[cfg.intermediate_layer_idx[i]] + (f * tokens + patch_start) * D;
      T* normed = ws + L.normed;
      nn::layernorm_forward(normed, tok, wt.norm_weight, wt.norm_bias, P, D, static_cast<T>(cfg.norm_eps));
      T* proj = i == 2 ? ws + L.level[2] : ws + L.proj;
      for (index_t o = 0; o < oc[i]; ++o) std::fill(proj + o * P, proj + (o + 1) * P, wt.projects[i].bias[o]);
      gemm(Trans::no, Trans::yes, oc[i], P, D, T(1), wt.projects[i].weight, D, normed, D, T(1), proj, P);
      if (cfg.pos_embed)
        detail::add_uv_pos_embed(proj, oc[i], g.patch_h, g.patch_w, aspect, cfg.pos_embed_ratio, cfg.pos_embed_omega,
                                 ws + L.pos_table);
      if (i == 0 || i == 1) {
        const index_t k = i == 0 ? 4 : 2;
        nn::conv_transpose2d_forward(ws + L.level[i], proj, wt.resize[i].weight, wt.resize[i].bias,
                                     {1, oc[i], oc[i], g.patch_h, g.patch_w, k, k, k, 0}, scratch);
      } else if (i == 3) {
        nn::conv2d_forward(ws + L.level[3], proj, wt.resize[3].weight, wt.resize[3].bias,
                           {1, oc[3], oc[3], g.patch_h, g.patch_w, 3, 3, 2, 1}, scratch);
      }
      detail::conv2d_same(ws + L.rn[i], ws + L.level[i], wt.layer_rn[i], static_cast<const T*>(nullptr), oc[i], F,
                          g.h[i], g.w[i], 3, scratch);
    }

    // Fusion, coarse to fine. Each block: [prev + unit1(skip)] -> unit2 -> out_conv -> resize to the next level.
    T* A = ws + L.a;
    T* B = ws + L.b;
    T* C = ws + L.c;
    T* Dbuf = ws + L.d;
    auto unit = [&](T* result, const T* x, const ResidualConvUnitWeights<T>& u, T* tmp1, T* tmp2, index_t h,
                    index_t w) {  // result = relu(x) + conv2(relu(conv1(relu(x))))
      const index_t n = F * h * w;
      detail::relu_copy(result, x, n);
      detail::conv2d_same(tmp1, result, u.conv1.weight, u.conv1.bias, F, F, h, w, 3, scratch);
      detail::relu_copy(tmp1, tmp1, n);
      detail::conv2d_same(tmp2, tmp1, u.conv2.weight, u.conv2.bias, F, F, h, w, 3, scratch);
      detail::add_into(result, tmp2, n);
    };
    // prev (the coarser block's resized output) lives in Dbuf between levels.
    bool has_prev = false;
    for (int level = 3; level >= 0; --level) {
      const auto& fb = wt.refinenet[level];
      const index_t h = g.h[level], w = g.w[level], n = F * h * w;
      const T* x = ws + L.rn[level];
      if (has_prev) {
        unit(A, x, fb.unit1, B, C, h, w);
        detail::add_into(A, Dbuf, n);
        x = A;
      }
      unit(B, x, fb.unit2, C, Dbuf, h, w);
      // The 1x1 out_conv commutes with bilinear resizing (weights sum to one), so it runs at the smaller size.
      detail::conv2d_same(C, B, fb.out_conv.weight, fb.out_conv.bias, F, F, h, w, 1, scratch);
      if (level > 0) detail::resize_align_corners(Dbuf, C, F, h, w, g.h[level - 1], g.w[level - 1]);
      else detail::resize_align_corners(ws + L.fused, C, F, h, w, g.fused_h, g.fused_w);
      has_prev = true;
    }

    // Head: output_conv1, upsample to the image grid, embedding, output_conv2, activations.
    T* fused = ws + L.fused;
    T* head_in = ws + L.head_in;
    detail::conv2d_same(head_in, fused, wt.output_conv1.weight, wt.output_conv1.bias, F, Fh, g.fused_h, g.fused_w, 3,
                        scratch);
    const index_t full = g.out_h * g.out_w;
    if (out.fused_features)
      std::copy(head_in, head_in + Fh * g.fused_h * g.fused_w, out.fused_features + f * Fh * g.fused_h * g.fused_w);
    T* up = ws + L.up;
    detail::resize_align_corners(up, head_in, Fh, g.fused_h, g.fused_w, g.out_h, g.out_w);
    if (cfg.pos_embed)
      detail::add_uv_pos_embed(up, Fh, g.out_h, g.out_w, aspect, cfg.pos_embed_ratio, cfg.pos_embed_omega,
                               ws + L.pos_table);
    if (out.features) std::copy(up, up + Fh * full, out.features + f * Fh * full);
    T* hidden = ws + L.hidden;
    detail::conv2d_same(hidden, up, wt.output_conv2_0.weight, wt.output_conv2_0.bias, Fh, DptHeadConfig::head_hidden,
                        g.out_h, g.out_w, 3, scratch);
    detail::relu_copy(hidden, hidden, DptHeadConfig::head_hidden * full);
    T* logits = ws + L.out;
    detail::conv2d_same(logits, hidden, wt.output_conv2_2.weight, wt.output_conv2_2.bias, DptHeadConfig::head_hidden,
                        cfg.output_dim, g.out_h, g.out_w, 1, scratch);
    const index_t np = cfg.output_dim - 1;
    T* preds = out.preds + f * full * np;
    T* conf = out.conf + f * full;
    parallel_for(full, [&](index_t p0, index_t p1, int) {
      for (index_t p = p0; p < p1; ++p) {
        for (index_t c = 0; c < np; ++c) preds[p * np + c] = detail::dpt_activate(logits[c * full + p], cfg.activation);
        conf[p] = detail::dpt_conf_activate(logits[np * full + p], cfg.conf_activation);
      }
    });
  }
}

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
