#pragma once
// LPIPS v0.1 with the VGG16 trunk, as richzhang/PerceptualSimilarity's `lpips.LPIPS(net='vgg')` computes it:
// scaling layer (x - shift) / scale; torchvision vgg16().features up to relu5_3 (3x3 convs, padding 1, ReLU, 2x2
// max-pools before stages 2..5) tapped after relu1_2, relu2_2, relu3_3, relu4_3, relu5_3; each tap normalised per
// pixel over channels, f / (||f|| + 1e-10); squared difference of the two images' taps; a bias-free 1x1 conv to one
// channel (lin<k>); spatial mean; sum over the five layers. Forward and backward with respect to both images, batched.
#include <algorithm>
#include <array>
#include <cmath>
#include <random>
#include <span>
#include <string>
#include <utility>
#include <vector>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/io/safetensors.hpp"
#include "flexsplat/nn/conv.hpp"
#include "flexsplat/nn/pool.hpp"

namespace flexsplat {
inline namespace v0 {
namespace loss {

inline constexpr int lpips_layers = 5;
inline constexpr int lpips_convs = 13;
inline constexpr double lpips_eps = 1e-10;  // added to the channel norm (lpips.normalize_tensor)
// The package's ScalingLayer buffers (ImageNet mean/std expressed for [-1, 1] inputs).
inline constexpr std::array<double, 3> lpips_default_shift{-0.030, -0.088, -0.188};
inline constexpr std::array<double, 3> lpips_default_scale{0.458, 0.448, 0.450};

// The 13 convolutions of the trunk: stage (= slice - 1) and index in torchvision's vgg16().features.
struct LpipsConv {
  int stage;
  int feature_index;
};
inline constexpr std::array<LpipsConv, lpips_convs> lpips_trunk{{{0, 0},  {0, 2},  {1, 5},  {1, 7},  {2, 10},
                                                                 {2, 12}, {2, 14}, {3, 17}, {3, 19}, {3, 21},
                                                                 {4, 24}, {4, 26}, {4, 28}}};
// Last conv of each stage: its ReLU output is the stage's LPIPS tap.
inline constexpr std::array<int, lpips_layers> lpips_tap_conv{1, 3, 6, 9, 12};
inline constexpr std::array<int, lpips_layers> lpips_first_conv{0, 2, 4, 7, 10};

struct LpipsConfig {
  std::array<index_t, lpips_layers> widths{64, 128, 256, 512, 512};  // VGG16's stage widths; tests use narrow ones
};

struct LpipsParamEntry {
  std::string name;  // the lpips package's state_dict name
  std::vector<index_t> shape;
  index_t offset = 0, size = 0;
};

// Offsets of every tensor in the flat parameter block, with the package's state_dict names.
struct LpipsParamLayout {
  LpipsConfig config;
  index_t shift = 0, scale = 0;
  std::array<index_t, lpips_convs> conv_w{}, conv_b{}, conv_in{}, conv_out{};
  std::array<index_t, lpips_layers> lin{};
  index_t size = 0;
  std::vector<LpipsParamEntry> entries;

  explicit LpipsParamLayout(const LpipsConfig& c = {}) : config(c) {
    for (int s = 0; s < lpips_layers; ++s)
      require(c.widths[static_cast<std::size_t>(s)] >= 1, "lpips: stage ", s + 1, " width ",
              c.widths[static_cast<std::size_t>(s)], " is not positive");
    auto take = [&](std::string name, std::vector<index_t> shape) {
      index_t n = 1;
      for (index_t e : shape) n *= e;
      entries.push_back({std::move(name), std::move(shape), size, n});
      size += n;
      return entries.back().offset;
    };
    shift = take("scaling_layer.shift", {1, 3, 1, 1});
    scale = take("scaling_layer.scale", {1, 3, 1, 1});
    index_t in = 3;
    for (int j = 0; j < lpips_convs; ++j) {
      const auto& t = lpips_trunk[static_cast<std::size_t>(j)];
      const index_t out = c.widths[static_cast<std::size_t>(t.stage)];
      const std::string base = concat("net.slice", t.stage + 1, ".", t.feature_index, ".");
      const auto u = static_cast<std::size_t>(j);
      conv_in[u] = in;
      conv_out[u] = out;
      conv_w[u] = take(base + "weight", {out, in, 3, 3});
      conv_b[u] = take(base + "bias", {out});
      in = out;
    }
    for (int k = 0; k < lpips_layers; ++k)
      lin[static_cast<std::size_t>(k)] = take(concat("lin", k, ".model.1.weight"), {1, c.widths[static_cast<std::size_t>(k)], 1, 1});
  }

  const LpipsParamEntry* find(const std::string& name) const {
    for (auto& e : entries)
      if (e.name == name) return &e;
    return nullptr;
  }
};

// The lin layers also appear in the package's state_dict under their ModuleList alias `lins.<k>.model.1.weight`.
inline std::string lpips_alias(const std::string& name) {
  if (name.rfind("lin", 0) == 0 && name.size() > 3 && name[3] >= '0' && name[3] <= '9') return "lins." + name.substr(3);
  return {};
}

// Stage widths read from a state_dict file (the first conv of every slice), so narrow test trunks load too.
inline LpipsConfig lpips_config_from(const safetensors::File& file, const std::string& prefix = "") {
  LpipsConfig c;
  for (int s = 0; s < lpips_layers; ++s) {
    const auto& t = lpips_trunk[static_cast<std::size_t>(lpips_first_conv[static_cast<std::size_t>(s)])];
    const std::string name = concat(prefix, "net.slice", s + 1, ".", t.feature_index, ".weight");
    require(file.contains(name), "lpips weights '", file.path(), "': no tensor '", name, "' (stage ", s + 1,
            " of the VGG16 trunk)");
    const auto& info = file.info(name);
    require(info.shape.size() == 4 && info.shape[0] >= 1, "lpips weights '", file.path(), "': tensor '", name,
            "' has shape ", safetensors::shape_string(info.shape), ", expected [C_out, C_in, 3, 3]");
    c.widths[static_cast<std::size_t>(s)] = info.shape[0];
  }
  return c;
}

// Copies one named tensor into the block (in-memory binding, e.g. from another checkpoint format).
template <class T>
void lpips_set_tensor(std::span<T> params, const LpipsParamLayout& L, const std::string& name, std::span<const T> values) {
  require(static_cast<index_t>(params.size()) == L.size, "lpips: parameter block has ", params.size(),
          " values, the layout needs ", L.size);
  const LpipsParamEntry* e = L.find(name);
  if (!e && name.rfind("lins.", 0) == 0) e = L.find("lin" + name.substr(5));
  require(e != nullptr, "lpips: no parameter named '", name, "'");
  require(static_cast<index_t>(values.size()) == e->size, "lpips: parameter '", name, "' ",
          safetensors::shape_string(e->shape), " needs ", e->size, " values, got ", values.size());
  std::copy(values.begin(), values.end(), params.begin() + e->offset);
}

// Fills the whole block from a file with the package's state_dict names (optionally under a prefix). Every
// missing or mis-shaped tensor is listed in one error; other tensors in the file are ignored.
template <class T>
void lpips_load(std::span<T> params, const LpipsParamLayout& L, const safetensors::File& file,
                const std::string& prefix = "") {
  require(static_cast<index_t>(params.size()) == L.size, "lpips: parameter block has ", params.size(),
          " values, the layout needs ", L.size);
  std::string problems;
  for (const auto& e : L.entries) {
    std::string name = prefix + e.name;
    if (!file.contains(name)) {
      const std::string alias = lpips_alias(e.name);
      if (!alias.empty() && file.contains(prefix + alias)) name = prefix + alias;
    }
    if (!file.contains(name)) {
      problems += concat("\n  missing '", name, "' ", safetensors::shape_string(e.shape));
      continue;
    }
    const auto& info = file.info(name);
    if (info.shape != e.shape) {
      problems += concat("\n  '", name, "' has shape ", safetensors::shape_string(info.shape), ", expected ",
                         safetensors::shape_string(e.shape));
      continue;
    }
    file.convert(info, params.data() + e.offset);
  }
  if (!problems.empty()) fail("lpips weights '", file.path(), "':", problems);
}

// A parameter block with its layout.
template <class T>
struct LpipsWeights {
  LpipsParamLayout layout;
  std::vector<T> params;
  explicit LpipsWeights(const LpipsConfig& c = {}) : layout(c), params(static_cast<std::size_t>(layout.size)) {}
};

// Trunk widths taken from the file, every tensor loaded by name.
template <class T>
LpipsWeights<T> lpips_load_weights(const safetensors::File& file, const std::string& prefix = "") {
  LpipsWeights<T> w(lpips_config_from(file, prefix));
  lpips_load(std::span<T>(w.params), w.layout, file, prefix);
  return w;
}

// Random weights for tests: the package's scaling layer, He-normal convs with small random biases, non-negative
// lin weights (the published ones are clamped at zero).
template <class T>
void lpips_init_random(std::span<T> params, const LpipsParamLayout& L, std::mt19937_64& rng) {
  require(static_cast<index_t>(params.size()) == L.size, "lpips: parameter block has ", params.size(),
          " values, the layout needs ", L.size);
  std::normal_distribution<double> normal(0.0, 1.0);
  std::uniform_real_distribution<double> uniform(0.0, 1.0);
  for (int c = 0; c < 3; ++c) {
    params[static_cast<std::size_t>(L.shift + c)] = static_cast<T>(lpips_default_shift[static_cast<std::size_t>(c)]);
    params[static_cast<std::size_t>(L.scale + c)] = static_cast<T>(lpips_default_scale[static_cast<std::size_t>(c)]);
  }
  for (int j = 0; j < lpips_convs; ++j) {
    const auto u = static_cast<std::size_t>(j);
    const index_t fan_in = L.conv_in[u] * 9;
    const double std_dev = std::sqrt(2.0 / static_cast<double>(fan_in));
    for (index_t i = 0; i < L.conv_out[u] * fan_in; ++i) params[static_cast<std::size_t>(L.conv_w[u] + i)] = static_cast<T>(std_dev * normal(rng));
    for (index_t i = 0; i < L.conv_out[u]; ++i) params[static_cast<std::size_t>(L.conv_b[u] + i)] = static_cast<T>(0.1 * normal(rng));
  }
  for (int k = 0; k < lpips_layers; ++k)
    for (index_t i = 0; i < L.config.widths[static_cast<std::size_t>(k)]; ++i)
      params[static_cast<std::size_t>(L.lin[static_cast<std::size_t>(k)] + i)] = static_cast<T>(uniform(rng));
}

// Activations kept for backward, and per-worker scratch. Buffers grow to the largest batch/size seen and never shrink.
template <class T>
struct LpipsCache {
  index_t batch = 0, height = 0, width = 0;
  bool unit_input = false;
  bool holds_in1 = false;  // the in1 half of the activations is complete (reuse_in1 may skip it)
  std::array<index_t, lpips_layers> h{}, w{};     // feature-map size of each stage
  std::vector<T> input;                            // [2B, 3, H, W] scaling-layer output: in0 images, then in1
  std::array<std::vector<T>, lpips_convs> act;     // ReLU output of every conv, [2B, C, h, w]
  std::array<std::vector<T>, lpips_layers - 1> pooled;  // max-pool outputs feeding stages 2..5
  std::array<std::vector<T>, lpips_layers> norm, inv_norm;  // [2B, h*w]: ||f|| and 1 / (||f|| + eps) per pixel
  struct Work {
    std::vector<T> cols, grad_a, grad_b, pixel;
  };
  std::vector<Work> work;  // one per worker
};

namespace detail {
// fn(i, worker) for i in [0, n): across the pool when every worker gets an item, else in order with the pool free
// for the GEMMs inside.
template <class F>
void lpips_for_each(index_t n, F&& fn) {
  ThreadPool& pool = global_pool();
  const int self = ThreadPool::current_worker();
  if (self < 0 && n >= pool.size() && pool.size() > 1) {
    parallel_for(n, [&](index_t i0, index_t i1, int worker) {
      for (index_t i = i0; i < i1; ++i) fn(i, worker);
    });
    return;
  }
  for (index_t i = 0; i < n; ++i) fn(i, self < 0 ? 0 : self);
}

inline nn::Conv2dShape lpips_conv_shape(const LpipsParamLayout& L, int j, index_t h, index_t w) {
  const auto u = static_cast<std::size_t>(j);
  return nn::Conv2dShape{1, L.conv_in[u], L.conv_out[u], h, w, 3, 3, 1, 1};
}
}  // namespace detail

// in0, in1 [B, 3, H, W] in [-1, 1], or in [0, 1] with unit_input (mapped by 2x - 1, the package's normalize=True).
// Writes lpips [B] and, if not null, per_layer [B, 5] (lpips = their sum). H and W >= 16 (four 2x2 pools).
// reuse_in1: in1 is the same as in the previous call with this cache (a fixed target compared with several renders),
// so its trunk is not run again; in1 may then be null.
template <class T>
void lpips_forward(T* lpips, T* per_layer, const T* in0, const T* in1, index_t batch, index_t height, index_t width,
                   const T* params, const LpipsParamLayout& L, LpipsCache<T>& cache, bool unit_input = false,
                   bool reuse_in1 = false) {
  require(batch >= 1, "lpips: batch ", batch, " must be positive");
  require(height >= 16 && width >= 16, "lpips: images are ", height, "x", width,
          "; the VGG16 trunk needs at least 16x16 (four 2x2 max-pools)");
  require(lpips && in0 && (in1 || reuse_in1) && params, "lpips_forward: null output, input or parameter pointer");
  if (reuse_in1)
    require(cache.holds_in1 && cache.batch == batch && cache.height == height && cache.width == width &&
                cache.unit_input == unit_input &&
                cache.act[0].size() == static_cast<std::size_t>(2 * batch * L.conv_out[0] * height * width),
            "lpips_forward: reuse_in1 needs a previous call with this cache on the same batch, size (", batch, "x", height,
            "x", width, "), input range and layout");
  cache.holds_in1 = false;
  for (index_t c = 0; c < 3; ++c)
    require(std::isfinite(static_cast<double>(params[L.scale + c])) && params[L.scale + c] != T(0),
            "lpips: scaling_layer.scale[", c, "] is ", static_cast<double>(params[L.scale + c]));
  const index_t images = 2 * batch, hw = height * width;
  cache.batch = batch, cache.height = height, cache.width = width, cache.unit_input = unit_input;
  index_t h = height, w = width;
  for (int s = 0; s < lpips_layers; ++s) {
    if (s > 0) h /= 2, w /= 2;
    cache.h[static_cast<std::size_t>(s)] = h, cache.w[static_cast<std::size_t>(s)] = w;
  }
  // Sizes and per-worker scratch.
  cache.input.resize(static_cast<std::size_t>(images * 3 * hw));
  index_t cols = 0, grad = 3 * hw;
  for (int j = 0; j < lpips_convs; ++j) {
    const int s = lpips_trunk[static_cast<std::size_t>(j)].stage;
    const index_t sh = cache.h[static_cast<std::size_t>(s)], sw = cache.w[static_cast<std::size_t>(s)];
    const auto u = static_cast<std::size_t>(j);
    cache.act[u].resize(static_cast<std::size_t>(images * L.conv_out[u] * sh * sw));
    cols = std::max(cols, nn::conv2d_scratch_size(detail::lpips_conv_shape(L, j, sh, sw)));
    grad = std::max(grad, std::max(L.conv_in[u], L.conv_out[u]) * sh * sw);
  }
  for (int s = 1; s < lpips_layers; ++s)
    cache.pooled[static_cast<std::size_t>(s - 1)].resize(static_cast<std::size_t>(
        images * L.config.widths[static_cast<std::size_t>(s - 1)] * cache.h[static_cast<std::size_t>(s)] *
        cache.w[static_cast<std::size_t>(s)]));
  for (int s = 0; s < lpips_layers; ++s) {
    const auto n = static_cast<std::size_t>(images * cache.h[static_cast<std::size_t>(s)] * cache.w[static_cast<std::size_t>(s)]);
    cache.norm[static_cast<std::size_t>(s)].resize(n);
    cache.inv_norm[static_cast<std::size_t>(s)].resize(n);
  }
  cache.work.resize(static_cast<std::size_t>(global_pool().size()));
  for (auto& wk : cache.work) {
    wk.cols.resize(static_cast<std::size_t>(cols));
    wk.grad_a.resize(static_cast<std::size_t>(grad));
    wk.grad_b.resize(static_cast<std::size_t>(grad));
    wk.pixel.resize(static_cast<std::size_t>(hw));
  }

  // Trunk, one image at a time.
  detail::lpips_for_each(reuse_in1 ? batch : images, [&](index_t i, int worker) {
    auto& wk = cache.work[static_cast<std::size_t>(worker)];
    const T* src = i < batch ? in0 + i * 3 * hw : in1 + (i - batch) * 3 * hw;
    T* x = cache.input.data() + i * 3 * hw;
    for (index_t c = 0; c < 3; ++c) {
      const T shift = params[L.shift + c], inv_scale = T(1) / params[L.scale + c];
      for (index_t p = 0; p < hw; ++p) {
        const T v = unit_input ? T(2) * src[c * hw + p] - T(1) : src[c * hw + p];
        if (!std::isfinite(v))
          fail("lpips_forward: in", i < batch ? 0 : 1, " image ", i < batch ? i : i - batch, " channel ", c, " pixel (",
               p % width, ", ", p / width, ") is ", static_cast<double>(src[c * hw + p]));
        x[c * hw + p] = (v - shift) * inv_scale;
      }
    }
    const T* stage_in = x;
    for (int j = 0; j < lpips_convs; ++j) {
      const auto u = static_cast<std::size_t>(j);
      const int s = lpips_trunk[u].stage;
      const index_t sh = cache.h[static_cast<std::size_t>(s)], sw = cache.w[static_cast<std::size_t>(s)];
      if (s > 0 && j == lpips_first_conv[static_cast<std::size_t>(s)]) {
        const index_t ch = L.config.widths[static_cast<std::size_t>(s - 1)];
        const index_t ph = cache.h[static_cast<std::size_t>(s - 1)], pw = cache.w[static_cast<std::size_t>(s - 1)];
        T* pooled = cache.pooled[static_cast<std::size_t>(s - 1)].data() + i * ch * sh * sw;
        nn::max_pool2d_forward(pooled, stage_in, nn::Pool2dShape{ch, ph, pw, 2, 2});
        stage_in = pooled;
      }
      T* y = cache.act[u].data() + i * L.conv_out[u] * sh * sw;
      nn::conv2d_forward(y, stage_in, params + L.conv_w[u], params + L.conv_b[u], detail::lpips_conv_shape(L, j, sh, sw),
                         std::span<T>(wk.cols));
      for (index_t e = 0; e < L.conv_out[u] * sh * sw; ++e) y[e] = y[e] > T(0) ? y[e] : T(0);
      stage_in = y;
    }
    // Per-pixel channel norms of every tap.
    for (int s = 0; s < lpips_layers; ++s) {
      const auto su = static_cast<std::size_t>(s);
      const index_t C = L.config.widths[su], n = cache.h[su] * cache.w[su];
      const T* f = cache.act[static_cast<std::size_t>(lpips_tap_conv[su])].data() + i * C * n;
      T* norm = cache.norm[su].data() + i * n;
      T* inv = cache.inv_norm[su].data() + i * n;
      std::fill(norm, norm + n, T(0));
      for (index_t c = 0; c < C; ++c)
        for (index_t p = 0; p < n; ++p) norm[p] += f[c * n + p] * f[c * n + p];
      for (index_t p = 0; p < n; ++p) {
        norm[p] = std::sqrt(norm[p]);
        inv[p] = T(1) / (norm[p] + static_cast<T>(lpips_eps));
      }
    }
  });

  // Head: weighted squared difference of the normalised taps, spatial mean, sum over layers.
  detail::lpips_for_each(batch, [&](index_t b, int worker) {
    auto& wk = cache.work[static_cast<std::size_t>(worker)];
    T total = T(0);
    for (int s = 0; s < lpips_layers; ++s) {
      const auto su = static_cast<std::size_t>(s);
      const index_t C = L.config.widths[su], n = cache.h[su] * cache.w[su];
      const auto& act = cache.act[static_cast<std::size_t>(lpips_tap_conv[su])];
      const T* f0 = act.data() + b * C * n;
      const T* f1 = act.data() + (b + batch) * C * n;
      const T* inv0 = cache.inv_norm[su].data() + b * n;
      const T* inv1 = cache.inv_norm[su].data() + (b + batch) * n;
      const T* lw = params + L.lin[su];
      T* acc = wk.pixel.data();
      std::fill(acc, acc + n, T(0));
      for (index_t c = 0; c < C; ++c)
        for (index_t p = 0; p < n; ++p) {
          const T d = f0[c * n + p] * inv0[p] - f1[c * n + p] * inv1[p];
          acc[p] += lw[c] * d * d;
        }
      double sum = 0.0;
      for (index_t p = 0; p < n; ++p) sum += static_cast<double>(acc[p]);
      const T layer = static_cast<T>(sum / static_cast<double>(n));
      if (per_layer) per_layer[b * lpips_layers + s] = layer;
      total += layer;
    }
    lpips[b] = total;
  });
  cache.holds_in1 = true;
}

// Adds the gradient of sum_b d_lpips[b] * lpips[b] + sum_{b,k} d_per_layer[b, k] * per_layer[b, k] into d_in0 and
// d_in1 ([B, 3, H, W], in the input convention of the forward call). d_lpips, d_per_layer, d_in0, d_in1 may each be
// null; a null image gradient skips that image's trunk backward (e.g. a constant target). A pixel whose tap is all
// zero takes the subgradient 0 through the norm (PyTorch would give NaN there).
template <class T>
void lpips_backward(T* d_in0, T* d_in1, const T* d_lpips, const T* d_per_layer, const T* params,
                    const LpipsParamLayout& L, LpipsCache<T>& cache) {
  const index_t batch = cache.batch, hw = cache.height * cache.width;
  require(batch >= 1 && cache.input.size() >= static_cast<std::size_t>(2 * batch * 3 * hw),
          "lpips_backward: the cache holds no forward pass");
  require(params != nullptr, "lpips_backward: null parameter pointer");
  if (!d_in0 && !d_in1) return;
  if (!d_lpips && !d_per_layer) return;
  detail::lpips_for_each(2 * batch, [&](index_t i, int worker) {
    const bool second = i >= batch;
    T* d_img = second ? d_in1 : d_in0;
    if (!d_img) return;
    const index_t b = second ? i - batch : i, other = second ? b : b + batch;
    auto& wk = cache.work[static_cast<std::size_t>(worker)];
    T* g = wk.grad_a.data();
    T* g_next = wk.grad_b.data();
    for (int s = lpips_layers - 1; s >= 0; --s) {
      const auto su = static_cast<std::size_t>(s);
      const index_t C = L.config.widths[su], sh = cache.h[su], sw = cache.w[su], n = sh * sw;
      if (s == lpips_layers - 1) std::fill(g, g + C * n, T(0));
      // Head: a = dL/d(normalised tap); through f / (||f|| + eps) including the norm's dependence on f.
      const T gk = (d_lpips ? d_lpips[b] : T(0)) + (d_per_layer ? d_per_layer[b * lpips_layers + s] : T(0));
      if (gk != T(0)) {
        const auto& act = cache.act[static_cast<std::size_t>(lpips_tap_conv[su])];
        const T* f = act.data() + i * C * n;
        const T* fo = act.data() + other * C * n;
        const T* inv = cache.inv_norm[su].data() + i * n;
        const T* invo = cache.inv_norm[su].data() + other * n;
        const T* norm = cache.norm[su].data() + i * n;
        const T* lw = params + L.lin[su];
        const T k = T(2) * gk / static_cast<T>(n);
        T* coef = wk.pixel.data();
        std::fill(coef, coef + n, T(0));
        for (index_t c = 0; c < C; ++c)
          for (index_t p = 0; p < n; ++p) {
            const T a = k * lw[c] * (f[c * n + p] * inv[p] - fo[c * n + p] * invo[p]);
            coef[p] += a * f[c * n + p];
          }
        for (index_t p = 0; p < n; ++p) coef[p] = norm[p] > T(0) ? coef[p] * inv[p] * inv[p] / norm[p] : T(0);
        for (index_t c = 0; c < C; ++c)
          for (index_t p = 0; p < n; ++p) {
            const T a = k * lw[c] * (f[c * n + p] * inv[p] - fo[c * n + p] * invo[p]);
            g[c * n + p] += a * inv[p] - f[c * n + p] * coef[p];
          }
      }
      // Convs of the stage, last to first: ReLU mask, then the input gradient of the conv.
      for (int j = lpips_tap_conv[su]; j >= lpips_first_conv[su]; --j) {
        const auto u = static_cast<std::size_t>(j);
        const T* y = cache.act[u].data() + i * L.conv_out[u] * n;
        for (index_t e = 0; e < L.conv_out[u] * n; ++e)
          if (!(y[e] > T(0))) g[e] = T(0);
        const T* x = j == 0 ? cache.input.data() + i * 3 * hw
                     : j == lpips_first_conv[su] ? cache.pooled[su - 1].data() + i * L.conv_in[u] * n
                                                 : cache.act[u - 1].data() + i * L.conv_in[u] * n;
        std::fill(g_next, g_next + L.conv_in[u] * n, T(0));
        nn::conv2d_backward(g_next, static_cast<T*>(nullptr), static_cast<T*>(nullptr), g, x, params + L.conv_w[u],
                            detail::lpips_conv_shape(L, j, sh, sw), std::span<T>(wk.cols));
        std::swap(g, g_next);
      }
      if (s > 0) {
        // Through the max-pool into the previous stage's tap (which also gets its own head gradient next).
        const auto pu = su - 1;
        const index_t pc = L.config.widths[pu], ph = cache.h[pu], pw = cache.w[pu];
        const T* prev = cache.act[static_cast<std::size_t>(lpips_tap_conv[pu])].data() + i * pc * ph * pw;
        std::fill(g_next, g_next + pc * ph * pw, T(0));
        nn::max_pool2d_backward(g_next, g, prev, nn::Pool2dShape{pc, ph, pw, 2, 2});
        std::swap(g, g_next);
      }
    }
    // Scaling layer (and the [0, 1] -> [-1, 1] map).
    T* d = d_img + b * 3 * hw;
    for (index_t c = 0; c < 3; ++c) {
      const T factor = (cache.unit_input ? T(2) : T(1)) / params[L.scale + c];
      for (index_t p = 0; p < hw; ++p) d[c * hw + p] += factor * g[c * hw + p];
    }
  });
}

}  // namespace loss
}  // namespace v0
}  // namespace flexsplat
