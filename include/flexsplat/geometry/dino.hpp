#pragma once
// DINOv2 patch embedder as VGGT uses it: a stride-patch convolution (here patchify + GEMM), a class token, the
// learned position embedding resized to the patch grid (antialiased bicubic, PyTorch semantics), register tokens
// inserted after the class token without position embedding, pre-norm blocks with LayerScale, and the final
// LayerNorm applied to the patch tokens (x_norm_patchtokens).
#include <algorithm>
#include <cmath>
#include <string>
#include <vector>

#include "flexsplat/core/gemm.hpp"
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/geometry/block.hpp"
#include "flexsplat/geometry/config.hpp"
#include "flexsplat/geometry/param_source.hpp"
#include "flexsplat/image/resample.hpp"
#include "flexsplat/nn/layernorm.hpp"

namespace flexsplat {
inline namespace v0 {
namespace geometry {

template <class T>
struct DinoWeights {
  const T* cls_token = nullptr;        // [1, 1, C]
  const T* pos_embed = nullptr;        // [1, 1 + M*M, C]
  const T* register_tokens = nullptr;  // [1, R, C] or null without registers
  const T* patch_weight = nullptr;     // [C, 3, p, p]
  const T* patch_bias = nullptr;       // [C]
  const T *norm_weight = nullptr, *norm_bias = nullptr;
  std::vector<BlockWeights<T>> blocks;
};

// Parameter names under `prefix` ("aggregator.patch_embed." in VGGT); mask_token is stored but unused at inference.
inline void append_dino_specs(std::vector<TensorSpec>& out, const std::string& prefix, const DinoConfig& c) {
  const index_t C = c.embed_dim, M = c.pos_grid();
  out.push_back({prefix + "cls_token", {1, 1, C}});
  out.push_back({prefix + "pos_embed", {1, 1 + M * M, C}});
  if (c.num_register_tokens > 0) out.push_back({prefix + "register_tokens", {1, c.num_register_tokens, C}});
  out.push_back({prefix + "mask_token", {1, C}});
  out.push_back({prefix + "patch_embed.proj.weight", {C, 3, c.patch_size, c.patch_size}});
  out.push_back({prefix + "patch_embed.proj.bias", {C}});
  for (index_t i = 0; i < c.depth; ++i) append_block_specs(out, prefix + "blocks." + std::to_string(i) + ".", c.block());
  out.push_back({prefix + "norm.weight", {C}});
  out.push_back({prefix + "norm.bias", {C}});
}

template <class T>
DinoWeights<T> load_dino_weights(ParamSource<T>& src, const std::string& prefix, const DinoConfig& c) {
  c.validate();
  const index_t C = c.embed_dim, M = c.pos_grid();
  DinoWeights<T> w;
  w.cls_token = src.get(prefix + "cls_token", {1, 1, C});
  w.pos_embed = src.get(prefix + "pos_embed", {1, 1 + M * M, C});
  if (c.num_register_tokens > 0) w.register_tokens = src.get(prefix + "register_tokens", {1, c.num_register_tokens, C});
  w.patch_weight = src.get(prefix + "patch_embed.proj.weight", {C, 3, c.patch_size, c.patch_size});
  w.patch_bias = src.get(prefix + "patch_embed.proj.bias", {C});
  for (index_t i = 0; i < c.depth; ++i)
    w.blocks.push_back(load_block_weights(src, prefix + "blocks." + std::to_string(i) + ".", c.block()));
  w.norm_weight = src.get(prefix + "norm.weight", {C});
  w.norm_bias = src.get(prefix + "norm.bias", {C});
  return w;
}

// Position embedding for an image of image_h x image_w pixels: [1 + grid_h * grid_w, C] (class token first).
// As DINOv2: unchanged when the patch count matches and the image is square, otherwise the M x M grid is resized
// to (grid_h, grid_w) in the channels-first layout.
template <class T>
Tensor<T, 2> dino_position_embedding(const DinoConfig& c, const DinoWeights<T>& w, index_t image_h, index_t image_w) {
  const index_t C = c.embed_dim, M = c.pos_grid(), N = M * M;
  const index_t gh = image_h / c.patch_size, gw = image_w / c.patch_size;
  Tensor<T, 2> out(Shape<2>{1 + gh * gw, C});
  if (gh * gw == N && image_h == image_w) {
    std::copy(w.pos_embed, w.pos_embed + (1 + N) * C, out.data());
    return out;
  }
  std::copy(w.pos_embed, w.pos_embed + C, out.data());
  Tensor<T, 3> planar(Shape<3>{C, M, M});
  // Raw indexing: Tensor::operator() validates its shape on every call, far too slow for per-element loops.
  T* planar_data = planar.data();
  for (index_t p = 0; p < N; ++p)
    for (index_t ch = 0; ch < C; ++ch) planar_data[ch * N + p] = w.pos_embed[(1 + p) * C + ch];
  Tensor<T, 3> resized;
  if (c.interpolate_offset != 0.0) {
    // DINOv2's legacy path: scale factors (grid + offset) / M, output size floor(M * factor).
    InterpolateScaleFactors factors;
    factors.height = (static_cast<double>(gh) + c.interpolate_offset) / static_cast<double>(M);
    factors.width = (static_cast<double>(gw) + c.interpolate_offset) / static_cast<double>(M);
    const index_t oh = static_cast<index_t>(std::floor(M * *factors.height));
    const index_t ow = static_cast<index_t>(std::floor(M * *factors.width));
    require(oh == gh && ow == gw, "DINO position embedding: interpolate_offset ", c.interpolate_offset,
            " gives a ", oh, " x ", ow, " grid for ", gh, " x ", gw, " patches");
    require(c.interpolate_antialias, "DINO position embedding: only the antialiased bicubic resize is implemented");
    resized = interpolate_bicubic_antialias<T>(planar.view(), gh, gw, factors);
  } else {
    require(c.interpolate_antialias, "DINO position embedding: only the antialiased bicubic resize is implemented");
    resized = interpolate_bicubic_antialias<T>(planar.view(), gh, gw);
  }
  const T* resized_data = resized.data();
  T* out_data = out.data();
  for (index_t p = 0; p < gh * gw; ++p)
    for (index_t ch = 0; ch < C; ++ch) out_data[(1 + p) * C + ch] = resized_data[ch * gh * gw + p];
  return out;
}

// (x - mean) / std per channel with ImageNet statistics (VGGT's _resnet_mean / _resnet_std), images [S, 3, H, W].
template <class T>
void imagenet_normalize(T* out, const T* images, index_t frames, index_t image_h, index_t image_w) {
  static constexpr float mean[3] = {0.485f, 0.456f, 0.406f};
  static constexpr float stdev[3] = {0.229f, 0.224f, 0.225f};
  const index_t plane = image_h * image_w;
  parallel_for(frames * 3, [&](index_t p0, index_t p1, int) {
    for (index_t p = p0; p < p1; ++p) {
      const T m = static_cast<T>(mean[p % 3]), sd = static_cast<T>(stdev[p % 3]);
      for (index_t i = 0; i < plane; ++i) out[p * plane + i] = (images[p * plane + i] - m) / sd;
    }
  });
}

template <class T>
struct DinoWorkspace {
  std::vector<T, AlignedAllocator<T>> patches, tokens;
  BlockWorkspace<T> block;
};

// images [S, 3, H, W], already normalised with the ImageNet mean and std; H and W multiples of the patch size.
// Writes the normalised patch tokens to out [S, (H/p) * (W/p), C].
template <class T>
void dino_forward(T* out, const T* images, index_t frames, index_t image_h, index_t image_w, const DinoConfig& c,
                  const DinoWeights<T>& w, DinoWorkspace<T>& ws) {
  c.validate();
  const index_t p = c.patch_size, C = c.embed_dim, R = c.num_register_tokens;
  require(frames >= 1, "DINO: needs at least one image, got ", frames);
  require(image_h >= p && image_w >= p && image_h % p == 0 && image_w % p == 0, "DINO: image size ", image_h, " x ",
          image_w, " must be a positive multiple of the patch size ", p);
  require(static_cast<index_t>(w.blocks.size()) == c.depth, "DINO: weights hold ", w.blocks.size(),
          " blocks, config depth is ", c.depth);
  const index_t gh = image_h / p, gw = image_w / p, P = gh * gw, N = 1 + R + P, K = 3 * p * p;
  const Tensor<T, 2> pos = dino_position_embedding(c, w, image_h, image_w);

  ws.patches.resize(static_cast<std::size_t>(frames * P * K));
  parallel_for(frames * P, [&](index_t r0, index_t r1, int) {
    for (index_t r = r0; r < r1; ++r) {
      const index_t s = r / P, py = (r % P) / gw, px = (r % P) % gw;
      T* row = ws.patches.data() + r * K;
      for (index_t ch = 0; ch < 3; ++ch)
        for (index_t ky = 0; ky < p; ++ky) {
          const T* src = images + ((s * 3 + ch) * image_h + py * p + ky) * image_w + px * p;
          std::copy(src, src + p, row + (ch * p + ky) * p);
        }
    }
  });
  ws.tokens.resize(static_cast<std::size_t>(frames * N * C));
  T* x = ws.tokens.data();
  // Patch embeddings land directly in their token rows: row stride N*C between frames.
  for (index_t s = 0; s < frames; ++s) {
    T* dst = x + (s * N + 1 + R) * C;
    for (index_t q = 0; q < P; ++q) std::copy(w.patch_bias, w.patch_bias + C, dst + q * C);
    gemm(Trans::no, Trans::yes, P, C, K, T(1), ws.patches.data() + s * P * K, K, w.patch_weight, K, T(1), dst, C);
  }
  const T* pos_data = pos.data();
  for (index_t s = 0; s < frames; ++s) {
    T* frame = x + s * N * C;
    for (index_t ch = 0; ch < C; ++ch) frame[ch] = w.cls_token[ch] + pos_data[ch];
    if (R > 0) std::copy(w.register_tokens, w.register_tokens + R * C, frame + C);
    for (index_t q = 0; q < P; ++q)
      for (index_t ch = 0; ch < C; ++ch) frame[(1 + R + q) * C + ch] += pos_data[(1 + q) * C + ch];
  }
  const BlockConfig bc = c.block();
  std::span<T> block_ws = ws.block.get(bc, frames * N);
  for (const auto& blk : w.blocks) block_forward<T>(x, frames, N, bc, blk, nullptr, nullptr, block_ws);
  for (index_t s = 0; s < frames; ++s)
    nn::layernorm_forward(out + s * P * C, x + (s * N + 1 + R) * C, w.norm_weight, w.norm_bias, P, C,
                          static_cast<T>(c.norm_eps));
}

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
