#pragma once
// Appearance branch: a UNet giving pixel-aligned features at input resolution. Encoder: 3x3 conv to `base` channels,
// then per level a stride-2 3x3 conv doubling the channels and a 3x3 conv; decoder: per level a 2x2 stride-2
// transposed conv halving the channels, cropped to the skip's size (odd sizes), added to the skip, and a 3x3 conv.
// GELU after every 3x3 conv. Batch = views.
#include <algorithm>
#include <random>
#include <vector>

#include "flexsplat/core/tensor.hpp"
#include "flexsplat/decoder/init.hpp"
#include "flexsplat/nn/activations.hpp"
#include "flexsplat/nn/conv.hpp"

namespace flexsplat {
inline namespace v0 {
namespace decoder {

struct UNetConfig {
  index_t in_channels = 3, base = 64, levels = 2;
  index_t channels(index_t level) const { return base << level; }
};

// One convolution of the network: its shape given the input size, and its parameter offsets.
struct UNetConv {
  index_t in_c, out_c, kernel, stride, padding;
  bool transposed, gelu;
  index_t weight, bias;
};

inline std::vector<UNetConv> unet_convs(const UNetConfig& c, index_t* param_count = nullptr) {
  std::vector<UNetConv> convs;
  index_t at = 0;
  auto add = [&](index_t in_c, index_t out_c, index_t k, index_t s, index_t p, bool t, bool g) {
    convs.push_back({in_c, out_c, k, s, p, t, g, at, at + in_c * out_c * k * k});
    at += in_c * out_c * k * k + out_c;
  };
  add(c.in_channels, c.channels(0), 3, 1, 1, false, true);
  for (index_t l = 0; l < c.levels; ++l) {
    add(c.channels(l), c.channels(l + 1), 3, 2, 1, false, true);
    add(c.channels(l + 1), c.channels(l + 1), 3, 1, 1, false, true);
  }
  for (index_t l = c.levels; l-- > 0;) {
    add(c.channels(l + 1), c.channels(l), 2, 2, 0, true, false);
    add(c.channels(l), c.channels(l), 3, 1, 1, false, true);
  }
  if (param_count) *param_count = at;
  return convs;
}

inline index_t unet_param_count(const UNetConfig& c) {
  index_t n = 0;
  unet_convs(c, &n);
  return n;
}

// Xavier-uniform weights (fan = channels x kernel area), zero biases.
template <class T>
void unet_init(T* params, const UNetConfig& c, std::mt19937_64& rng) {
  std::fill(params, params + unet_param_count(c), T(0));
  for (const auto& v : unet_convs(c))
    xavier_uniform_fans(params + v.weight, v.out_c * v.in_c * v.kernel * v.kernel, v.out_c * v.kernel * v.kernel,
                        v.in_c * v.kernel * v.kernel, rng);
}

template <class T>
struct UNetCache {
  index_t views = 0, h = 0, w = 0;
  std::vector<AlignedVector<T>> pre, post;  // per conv: output before and after GELU / skip addition
  std::vector<index_t> out_h, out_w, in_h, in_w;
  AlignedVector<T> scratch;
  AlignedVector<T> spare[2];  // forward only: the outputs no later conv reads again (all but the skips) alternate here
  std::vector<AlignedVector<T>> d_post;  // backward's per-conv gradients, kept so repeated steps do not allocate
  AlignedVector<T> d_pre;
  bool keep_for_backward = true;  // false: forward only (predict), each GELU in place; unet_backward is refused
};

namespace detail {
inline nn::Conv2dShape unet_shape(const UNetConv& v, index_t batch, index_t h, index_t w) {
  nn::Conv2dShape s{batch, v.in_c, v.out_c, h, w, v.kernel, v.kernel, v.stride, v.padding, 0};
  return s;
}
// Whether conv i's output is a skip: the encoder's output at each resolution but the deepest (the first conv and
// every second down conv), which the decoder side adds back.
inline bool unet_is_skip(std::size_t i, index_t levels) {
  return i % 2 == 0 && i + 1 < static_cast<std::size_t>(1 + 2 * levels);
}
// Copies the top-left oh x ow window of every [h, w] plane (or adds its adjoint).
template <class T>
void crop_planes(T* out, const T* in, index_t planes, index_t h, index_t w, index_t oh, index_t ow, bool adjoint_add) {
  for (index_t p = 0; p < planes; ++p)
    for (index_t y = 0; y < oh; ++y)
      for (index_t x = 0; x < ow; ++x) {
        if (adjoint_add) out[(p * h + y) * w + x] += in[(p * oh + y) * ow + x];
        else out[(p * oh + y) * ow + x] = in[(p * h + y) * w + x];
      }
}
}  // namespace detail

// images [V, in_channels, h, w] -> out [V, base, h, w].
template <class T>
void unet_forward(T* out, UNetCache<T>& cache, const T* images, index_t views, index_t h, index_t w, const T* params,
                  const UNetConfig& c) {
  require(views >= 1 && h >= 1 && w >= 1, "unet: input is ", views, " views of ", h, "x", w, " (zero-size)");
  const auto convs = unet_convs(c);
  cache.views = views, cache.h = h, cache.w = w;
  cache.pre.resize(convs.size());  // buffers kept across calls: fresh memory costs its first touch
  cache.post.resize(convs.size());
  cache.in_h.assign(convs.size(), 0), cache.in_w.assign(convs.size(), 0);
  cache.out_h.assign(convs.size(), 0), cache.out_w.assign(convs.size(), 0);
  std::vector<const T*> skips;
  std::vector<index_t> skip_h, skip_w;
  const T* x = images;
  index_t ch = h, cw = w;
  const bool keep = cache.keep_for_backward;
  // Forward only: a spare buffer of n elements other than `avoid`.
  auto spare = [&](std::size_t n, const T* avoid) {
    auto& b = cache.spare[0].data() != avoid ? cache.spare[0] : cache.spare[1];
    if (b.size() < n) b.resize(n);
    return b.data();
  };
  auto sized = [](AlignedVector<T>& v, std::size_t n) {
    v.resize(n);
    return v.data();
  };
  for (std::size_t i = 0; i < convs.size(); ++i) {
    const UNetConv& v = convs[i];
    const nn::Conv2dShape s = detail::unet_shape(v, views, ch, cw);
    nn::validate_conv(s, v.transposed, "unet");
    const index_t oh = v.transposed ? s.transposed_out_h() : s.conv_out_h();
    const index_t ow = v.transposed ? s.transposed_out_w() : s.conv_out_w();
    cache.in_h[i] = ch, cache.in_w[i] = cw, cache.out_h[i] = oh, cache.out_w[i] = ow;
    const index_t need = v.transposed ? nn::conv_transpose2d_scratch_size(s)
                         : keep       ? nn::conv2d_scratch_size(s)
                                      : nn::conv2d_forward_scratch_size(s);
    cache.scratch.resize(static_cast<std::size_t>(std::max(need, static_cast<index_t>(cache.scratch.size()))));
    const bool last = i + 1 == convs.size();
    const auto out_n = static_cast<std::size_t>(views * v.out_c * oh * ow);
    T* y = nullptr;  // this conv's output after GELU / skip addition
    if (v.transposed) {
      T* pre = keep ? sized(cache.pre[i], out_n) : spare(out_n, x);
      nn::conv_transpose2d_forward(pre, x, params + v.weight, params + v.bias, s, std::span<T>(cache.scratch));
      // crop to the skip's size and add the skip
      const T* skip = skips.back();
      const index_t sh = skip_h.back(), sw = skip_w.back();
      skips.pop_back(), skip_h.pop_back(), skip_w.pop_back();
      const auto post_n = static_cast<std::size_t>(views * v.out_c * sh * sw);
      y = keep ? sized(cache.post[i], post_n) : last ? out : spare(post_n, pre);
      detail::crop_planes(y, pre, views * v.out_c, oh, ow, sh, sw, false);
      for (std::size_t k = 0; k < post_n; ++k) y[k] += skip[k];
      ch = sh, cw = sw;
    } else {
      const bool is_skip = detail::unet_is_skip(i, c.levels);
      T* conv_out = nullptr;
      if (keep) y = sized(cache.post[i], out_n), conv_out = sized(cache.pre[i], out_n);
      else y = conv_out = is_skip ? sized(cache.post[i], out_n) : last ? out : spare(out_n, x);
      nn::conv2d_forward(conv_out, x, params + v.weight, params + v.bias, s, std::span<T>(cache.scratch));
      nn::gelu_forward(y, conv_out, static_cast<index_t>(out_n));
      ch = oh, cw = ow;
      if (is_skip) skips.push_back(y), skip_h.push_back(ch), skip_w.push_back(cw);
    }
    x = y;
  }
  if (keep) std::copy(cache.post.back().begin(), cache.post.back().end(), out);
}

// Adds into d_images (may be null) and d_params.
template <class T>
void unet_backward(T* d_images, T* d_params, const T* d_out, UNetCache<T>& cache, const T* images, const T* params,
                   const UNetConfig& c) {
  require(cache.keep_for_backward,
          "unet_backward: the forward kept no pre-activation outputs (UNetCache::keep_for_backward is false)");
  const auto convs = unet_convs(c);
  const index_t views = cache.views;
  auto& d_post = cache.d_post;
  d_post.resize(convs.size());
  for (std::size_t i = 0; i < convs.size(); ++i) d_post[i].assign(cache.post[i].size(), T(0));
  std::copy(d_out, d_out + d_post.back().size(), d_post.back().begin());
  // skip producers, in the order the transposed convs consume them (last pushed first)
  std::vector<std::size_t> producers;
  for (std::size_t i = 0; i < convs.size(); ++i)
    if (detail::unet_is_skip(i, c.levels)) producers.push_back(i);
  std::vector<std::size_t> consumer_skip(convs.size(), 0);
  {
    std::vector<std::size_t> stack = producers;
    for (std::size_t i = 0; i < convs.size(); ++i)
      if (convs[i].transposed) consumer_skip[i] = stack.back(), stack.pop_back();
  }
  for (std::size_t i = convs.size(); i-- > 0;) {
    const UNetConv& v = convs[i];
    const nn::Conv2dShape s = detail::unet_shape(v, views, cache.in_h[i], cache.in_w[i]);
    const T* x = i == 0 ? images : cache.post[i - 1].data();
    T* dx = i == 0 ? d_images : d_post[i - 1].data();
    AlignedVector<T>& d_pre = cache.d_pre;
    d_pre.assign(cache.pre[i].size(), T(0));
    if (v.transposed) {
      auto& d_skip = d_post[consumer_skip[i]];
      for (std::size_t k = 0; k < d_post[i].size(); ++k) d_skip[k] += d_post[i][k];
      detail::crop_planes(d_pre.data(), d_post[i].data(), views * v.out_c, cache.out_h[i], cache.out_w[i], cache.in_h[i + 1],
                          cache.in_w[i + 1], true);
      nn::conv_transpose2d_backward(dx, d_params + v.weight, d_params + v.bias, d_pre.data(), x, params + v.weight, s,
                                    std::span<T>(cache.scratch));
    } else {
      nn::gelu_backward(d_pre.data(), d_post[i].data(), cache.pre[i].data(), static_cast<index_t>(d_pre.size()));
      nn::conv2d_backward(dx, d_params + v.weight, d_params + v.bias, d_pre.data(), x, params + v.weight, s,
                          std::span<T>(cache.scratch));
    }
  }
}

}  // namespace decoder
}  // namespace v0
}  // namespace flexsplat
