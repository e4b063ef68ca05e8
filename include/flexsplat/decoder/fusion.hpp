#pragma once
// FPN-style fusion of the depth head's features into the appearance features: a 1x1 projection of the depth features
// to the UNet width (applied before the bilinear upsampling: both are linear and commute, and the small map is
// cheaper), added to the UNet features, refined by a 3x3 conv + GELU, reduced by a 1x1 conv to C_f (the keys/values
// of the deformable attention). A light RGB head (1x1 conv + sigmoid) on the fused features serves the lambda_E term.
#include <random>
#include <vector>

#include "flexsplat/core/tensor.hpp"
#include "flexsplat/decoder/init.hpp"
#include "flexsplat/decoder/splat_head.hpp"
#include "flexsplat/nn/activations.hpp"
#include "flexsplat/nn/conv.hpp"
#include "flexsplat/nn/interpolate.hpp"

namespace flexsplat {
inline namespace v0 {
namespace decoder {

struct FusionConfig {
  index_t depth_channels = 128, unet_channels = 64, out_channels = 128;
};

struct FusionParamLayout {
  index_t proj_w, proj_b, refine_w, refine_b, reduce_w, reduce_b, rgb_w, rgb_b, size;
  explicit FusionParamLayout(const FusionConfig& c) {
    index_t at = 0;
    auto take = [&](index_t n) { const index_t o = at; at += n; return o; };
    proj_w = take(c.unet_channels * c.depth_channels);
    proj_b = take(c.unet_channels);
    refine_w = take(c.unet_channels * c.unet_channels * 9);
    refine_b = take(c.unet_channels);
    reduce_w = take(c.out_channels * c.unet_channels);
    reduce_b = take(c.out_channels);
    rgb_w = take(3 * c.out_channels);
    rgb_b = take(3);
    size = at;
  }
};

template <class T>
void fusion_init(T* params, const FusionConfig& c, std::mt19937_64& rng) {
  const FusionParamLayout L(c);
  std::fill(params, params + L.size, T(0));
  xavier_uniform(params + L.proj_w, c.unet_channels, c.depth_channels, rng);
  xavier_uniform_fans(params + L.refine_w, c.unet_channels * c.unet_channels * 9, c.unet_channels * 9, c.unet_channels * 9, rng);
  xavier_uniform(params + L.reduce_w, c.out_channels, c.unet_channels, rng);
  xavier_uniform(params + L.rgb_w, 3, c.out_channels, rng);
}

template <class T>
struct FusionCache {
  index_t views = 0, dh = 0, dw = 0, h = 0, w = 0;
  AlignedVector<T> projected, sum, refined_pre, refined, fused, rgb_logit, scratch;
  AlignedVector<T> d_f, d_logit, d_refined, d_pre, d_sum, d_proj;  // backward's, kept so repeated steps do not allocate
  bool keep_for_backward = true;  // false: forward only (predict), the GELU in place, no copy of the output
};

namespace detail {
inline nn::Conv2dShape fusion_conv(index_t views, index_t in_c, index_t out_c, index_t h, index_t w, index_t k) {
  return nn::Conv2dShape{views, in_c, out_c, h, w, k, k, 1, k / 2, 0};
}
}  // namespace detail

// depth_features [V, depth_channels, dh, dw], unet [V, unet_channels, h, w] -> fused [V, out_channels, h, w] and
// rgb [V, 3, h, w] (rgb may be null).
template <class T>
void fusion_forward(T* fused, T* rgb, FusionCache<T>& k, const T* depth_features, index_t dh, index_t dw, const T* unet,
                    index_t views, index_t h, index_t w, const T* params, const FusionConfig& c) {
  require(views >= 1 && dh >= 1 && dw >= 1 && h >= 1 && w >= 1, "fusion: depth features ", dh, "x", dw,
          " and appearance features ", h, "x", w, " for ", views, " views (zero-size)");
  const FusionParamLayout L(c);
  k.views = views, k.dh = dh, k.dw = dw, k.h = h, k.w = w;
  const auto proj = detail::fusion_conv(views, c.depth_channels, c.unet_channels, dh, dw, 1);
  const auto refine = detail::fusion_conv(views, c.unet_channels, c.unet_channels, h, w, 3);
  const auto reduce = detail::fusion_conv(views, c.unet_channels, c.out_channels, h, w, 1);
  const auto head = detail::fusion_conv(views, c.out_channels, 3, h, w, 1);
  k.scratch.resize(static_cast<std::size_t>(k.keep_for_backward ? nn::conv2d_scratch_size(refine)
                                                                 : nn::conv2d_forward_scratch_size(refine)));
  const index_t hw = h * w;
  k.projected.resize(static_cast<std::size_t>(views * c.unet_channels * dh * dw));
  nn::conv2d_forward(k.projected.data(), depth_features, params + L.proj_w, params + L.proj_b, proj, std::span<T>(k.scratch));
  k.sum.resize(static_cast<std::size_t>(views * c.unet_channels * hw));
  nn::bilinear_resize_forward(k.sum.data(), k.projected.data(), views * c.unet_channels, dh, dw, h, w, false);
  for (std::size_t i = 0; i < k.sum.size(); ++i) k.sum[i] += unet[i];
  k.refined.resize(k.sum.size());
  T* refine_out = k.refined.data();
  if (k.keep_for_backward) {
    k.refined_pre.resize(k.sum.size());
    refine_out = k.refined_pre.data();
  }
  nn::conv2d_forward(refine_out, k.sum.data(), params + L.refine_w, params + L.refine_b, refine,
                     std::span<T>(k.scratch));
  nn::gelu_forward(k.refined.data(), refine_out, static_cast<index_t>(k.refined.size()));
  nn::conv2d_forward(fused, k.refined.data(), params + L.reduce_w, params + L.reduce_b, reduce, std::span<T>(k.scratch));
  if (k.keep_for_backward) k.fused.assign(fused, fused + views * c.out_channels * hw);
  if (!rgb) return;
  k.rgb_logit.resize(static_cast<std::size_t>(views * 3 * hw));
  nn::conv2d_forward(k.rgb_logit.data(), fused, params + L.rgb_w, params + L.rgb_b, head, std::span<T>(k.scratch));
  for (std::size_t i = 0; i < k.rgb_logit.size(); ++i) rgb[i] = nn::sigmoid(k.rgb_logit[i]);
}

// Adds into d_depth_features, d_unet (either may be null) and d_params. d_rgb may be null.
template <class T>
void fusion_backward(T* d_depth_features, T* d_unet, T* d_params, const T* d_fused, const T* d_rgb, FusionCache<T>& k,
                     const T* depth_features, const T* params, const FusionConfig& c) {
  require(k.keep_for_backward, "fusion_backward: the forward kept no caches (FusionCache::keep_for_backward is false)");
  const FusionParamLayout L(c);
  const index_t views = k.views, h = k.h, w = k.w, hw = h * w;
  const auto proj = detail::fusion_conv(views, c.depth_channels, c.unet_channels, k.dh, k.dw, 1);
  const auto refine = detail::fusion_conv(views, c.unet_channels, c.unet_channels, h, w, 3);
  const auto reduce = detail::fusion_conv(views, c.unet_channels, c.out_channels, h, w, 1);
  const auto head = detail::fusion_conv(views, c.out_channels, 3, h, w, 1);
  AlignedVector<T>& d_f = k.d_f;
  d_f.assign(d_fused, d_fused + views * c.out_channels * hw);
  if (d_rgb) {
    AlignedVector<T>& d_logit = k.d_logit;
    d_logit.resize(k.rgb_logit.size());
    for (std::size_t i = 0; i < d_logit.size(); ++i) d_logit[i] = nn::sigmoid_vjp(k.rgb_logit[i], d_rgb[i]);
    nn::conv2d_backward(d_f.data(), d_params + L.rgb_w, d_params + L.rgb_b, d_logit.data(), k.fused.data(), params + L.rgb_w,
                        head, std::span<T>(k.scratch));
  }
  AlignedVector<T>& d_refined = k.d_refined;
  AlignedVector<T>& d_pre = k.d_pre;
  AlignedVector<T>& d_sum = k.d_sum;
  d_refined.assign(k.refined.size(), T(0));
  d_pre.assign(k.refined.size(), T(0));
  d_sum.assign(k.sum.size(), T(0));
  nn::conv2d_backward(d_refined.data(), d_params + L.reduce_w, d_params + L.reduce_b, d_f.data(), k.refined.data(),
                      params + L.reduce_w, reduce, std::span<T>(k.scratch));
  nn::gelu_backward(d_pre.data(), d_refined.data(), k.refined_pre.data(), static_cast<index_t>(d_pre.size()));
  nn::conv2d_backward(d_sum.data(), d_params + L.refine_w, d_params + L.refine_b, d_pre.data(), k.sum.data(),
                      params + L.refine_w, refine, std::span<T>(k.scratch));
  if (d_unet)
    for (std::size_t i = 0; i < d_sum.size(); ++i) d_unet[i] += d_sum[i];
  AlignedVector<T>& d_proj = k.d_proj;
  d_proj.assign(k.projected.size(), T(0));
  nn::bilinear_resize_backward(d_proj.data(), d_sum.data(), views * c.unet_channels, k.dh, k.dw, h, w, false);
  nn::conv2d_backward(d_depth_features, d_params + L.proj_w, d_params + L.proj_b, d_proj.data(), depth_features,
                      params + L.proj_w, proj, std::span<T>(k.scratch));
}

}  // namespace decoder
}  // namespace v0
}  // namespace flexsplat
