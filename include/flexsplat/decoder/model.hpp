#pragma once
// The appearance-to-Gaussians chain of FlexSplat: input images -> appearance UNet -> FPN fusion with the depth head's
// features (1x1 projection, bilinear upsampling, addition, 3x3 conv + GELU, 1x1 conv to C_f) -> Gaussian decoder, plus
// the RGB head on the fused features for the lambda_E reconstruction term. Parameters of the three parts live in one
// flat block (ModelParamLayout); backward reaches the depth features, predicted depth, K and world-to-camera (not the
// images).
#include <algorithm>
#include <cmath>
#include <random>
#include <vector>

#include "flexsplat/core/profile.hpp"
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/decoder/decoder.hpp"
#include "flexsplat/decoder/fusion.hpp"
#include "flexsplat/decoder/unet.hpp"

namespace flexsplat {
inline namespace v0 {
namespace decoder {

struct ModelConfig {
  UNetConfig unet;       // in_channels 3, base 64, levels 2
  FusionConfig fusion;   // depth_channels from the depth head, unet_channels = unet.base, out_channels = C_f
  DecoderConfig decoder; // value_dim = C_f
};

inline void validate_model_config(const ModelConfig& c) {
  require(c.fusion.unet_channels == c.unet.base, "model: fusion expects ", c.fusion.unet_channels,
          " appearance channels but the UNet gives ", c.unet.base);
  require(c.fusion.out_channels == c.decoder.value_dim, "model: fusion gives ", c.fusion.out_channels,
          " channels but the decoder's deformable attention expects value_dim ", c.decoder.value_dim);
}

struct ModelParamLayout {
  index_t unet, fusion, decoder, size;
  explicit ModelParamLayout(const ModelConfig& c) {
    unet = 0;
    fusion = unet + unet_param_count(c.unet);
    decoder = fusion + FusionParamLayout(c.fusion).size;
    size = decoder + DecoderParamLayout(c.decoder).size;
  }
};

template <class T>
void model_init(T* params, const ModelConfig& c, std::uint64_t seed) {
  validate_model_config(c);
  const ModelParamLayout L(c);
  std::mt19937_64 rng(seed);
  unet_init(params + L.unet, c.unet, rng);
  fusion_init(params + L.fusion, c.fusion, rng);
  decoder_init(params + L.decoder, c.decoder, seed ^ 0x9e3779b97f4a7c15ull);
}

// Forward caches of the three parts and the backward buffers between them.
template <class T>
struct ModelWorkspace {
  index_t views = 0, h = 0, w = 0, dh = 0, dw = 0;
  UNetCache<T> unet;
  FusionCache<T> fusion;
  AlignedVector<T> appearance;  // [V, unet.base, h, w] UNet output
  AlignedVector<T> fused;       // [V, C_f, h, w] keys/values of the deformable attention
  AlignedVector<T> rgb;         // [V, 3, h, w] RGB head output (lambda_E term)
  AlignedVector<T> d_fused, d_appearance;
  DecoderWorkspace<T> decoder;
  // false: forward only (predict): the parts keep no backward caches and the RGB head is skipped (rgb stays empty).
  bool keep_for_backward = true;
  const std::vector<GaussianSet<T>>& gaussians() const { return decoder.gaussians; }
};

// images [V, unet.in_channels, h, w]; depth_features [V, fusion.depth_channels, dh, dw]; g: the geometry stage's
// cameras and depth. Results: ws.gaussians() (every layer's set) and ws.rgb (when keep_for_backward).
template <class T>
void model_forward(ModelWorkspace<T>& ws, index_t n_queries, const T* params, const ModelConfig& c, const T* images,
                   index_t h, index_t w, const T* depth_features, index_t dh, index_t dw, const ViewGeometry<T>& g) {
  validate_model_config(c);
  validate_geometry(g);
  require(images && depth_features, "model: null images or depth features");
  const ModelParamLayout L(c);
  const index_t V = g.views;
  // A NaN / Inf pixel would spread through the UNet into every Gaussian: refused, naming the pixel.
  const index_t plane = h * w, pixels = V * c.unet.in_channels * plane;
  for (index_t i = 0; i < pixels; ++i)
    if (!std::isfinite(static_cast<double>(images[i])))
      fail("decoder: input image ", i / (c.unet.in_channels * plane), " has a non-finite value ",
           static_cast<double>(images[i]), " at channel ", i / plane % c.unet.in_channels, ", row ", i % plane / w,
           ", column ", i % w);
  ws.views = V, ws.h = h, ws.w = w, ws.dh = dh, ws.dw = dw;
  ws.appearance.resize(static_cast<std::size_t>(V * c.unet.base * h * w));
  ws.fused.resize(static_cast<std::size_t>(V * c.fusion.out_channels * h * w));
  ws.rgb.resize(ws.keep_for_backward ? static_cast<std::size_t>(V * 3 * h * w) : 0);
  ws.unet.keep_for_backward = ws.fusion.keep_for_backward = ws.decoder.keep_for_backward = ws.keep_for_backward;
  {
    const profile::Stage stage("UNet");
    unet_forward(ws.appearance.data(), ws.unet, images, V, h, w, params + L.unet, c.unet);
  }
  {
    const profile::Stage stage("fusion");
    fusion_forward(ws.fused.data(), ws.keep_for_backward ? ws.rgb.data() : nullptr, ws.fusion, depth_features, dh, dw,
                   ws.appearance.data(), V, h, w, params + L.fusion, c.fusion);
  }
  const FeatureMaps<T> maps{V, c.fusion.out_channels, h, w, ws.fused.data()};
  decoder_forward(ws.decoder, n_queries, params + L.decoder, c.decoder, maps, g);
}

// d_gaussians: one gradient set per returned Gaussian set; d_rgb [V, 3, h, w] (may be null). Adds into d_params,
// d_depth_features (may be null) and d_geometry (K, world_to_camera, depth; null members skipped).
template <class T>
void model_backward(T* d_params, T* d_depth_features, const ViewGeometryGrad<T>& d_geometry,
                    const std::vector<GaussianSetGrad<T>>& d_gaussians, const T* d_rgb, ModelWorkspace<T>& ws,
                    const T* params, const ModelConfig& c, const T* images, const T* depth_features,
                    const ViewGeometry<T>& g) {
  require(ws.keep_for_backward,
          "model_backward: the forward kept no caches (ModelWorkspace::keep_for_backward is false)");
  const ModelParamLayout L(c);
  ws.d_fused.resize(ws.fused.size());
  ws.d_appearance.resize(ws.appearance.size());
  std::fill(ws.d_fused.begin(), ws.d_fused.end(), T(0));
  std::fill(ws.d_appearance.begin(), ws.d_appearance.end(), T(0));
  const FeatureMaps<T> maps{ws.views, c.fusion.out_channels, ws.h, ws.w, ws.fused.data()};
  decoder_backward(d_params + L.decoder, ws.d_fused.data(), d_geometry, d_gaussians, ws.decoder, params + L.decoder,
                   c.decoder, maps, g);
  fusion_backward(d_depth_features, ws.d_appearance.data(), d_params + L.fusion, ws.d_fused.data(), d_rgb, ws.fusion,
                  depth_features, params + L.fusion, c.fusion);
  unet_backward(static_cast<T*>(nullptr), d_params + L.unet, ws.d_appearance.data(), ws.unet, images, params + L.unet,
                c.unet);
}

}  // namespace decoder
}  // namespace v0
}  // namespace flexsplat
