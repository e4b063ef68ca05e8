#pragma once
// DINOv2 patch embedder as VGGT uses it: a stride-patch convolution (here patchify + GEMM), a class token, the
// learned position embedding resized to the patch grid (antialiased bicubic, PyTorch semantics), register tokens
// inserted after the class token without position embedding, pre-norm blocks with LayerScale, and the final
// LayerNorm applied to the patch tokens (x_norm_patchtokens). dino_forward_train / dino_backward: training, with
// the position-embedding resize's adjoint and the patch convolution's weight / input gradients.
#include <algorithm>
#include <cmath>
#include <span>
#include <string>
#include <vector>

#include "flexsplat/core/gemm.hpp"
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/geometry/block.hpp"
#include "flexsplat/geometry/config.hpp"
#include "flexsplat/io/param_source.hpp"
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
inline void append_dino_specs(std::vector<io::TensorSpec>& out, const std::string& prefix, const DinoConfig& c) {
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
DinoWeights<T> load_dino_weights(io::ParamSource<T>& src, const std::string& prefix, const DinoConfig& c) {
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

// Gradient pointers mirroring DinoWeights (null: not wanted).
template <class T>
struct DinoGrads {
  T *cls_token = nullptr, *pos_embed = nullptr, *register_tokens = nullptr, *patch_weight = nullptr,
    *patch_bias = nullptr, *norm_weight = nullptr, *norm_bias = nullptr;
  std::vector<BlockGrads<T>> blocks;
};

// Gradients of weights bound into one flat parameter block, in a gradient block with the same offsets.
template <class T>
DinoGrads<T> dino_grads(const DinoWeights<T>& w, const T* params_base, T* grads_base) {
  auto g = [&](const T* p) { return io::rebase_pointer(p, params_base, grads_base); };
  DinoGrads<T> d{g(w.cls_token), g(w.pos_embed), g(w.register_tokens), g(w.patch_weight), g(w.patch_bias),
                 g(w.norm_weight), g(w.norm_bias), {}};
  for (const auto& b : w.blocks) d.blocks.push_back(block_grads(b, params_base, grads_base));
  return d;
}

// What dino_backward reads (see BlockCache for the recompute option).
template <class T>
struct DinoCache {
  index_t frames = 0, image_h = 0, image_w = 0;
  std::vector<T, AlignedAllocator<T>> patches;  // [S * P, 3 p p] the images as patch rows
  std::vector<BlockCache<T>> blocks;
  std::vector<T, AlignedAllocator<T>> x_final;  // [S * N, C] tokens after the last block
  std::vector<T, AlignedAllocator<T>> norm_mean, norm_rstd;  // [S * P] final LayerNorm statistics
};

// Elements a DinoCache holds for `frames` images of image_h x image_w.
inline index_t dino_cache_elements(const DinoConfig& c, index_t frames, index_t image_h, index_t image_w, bool recompute) {
  const index_t p = c.patch_size, P = (image_h / p) * (image_w / p), N = 1 + c.num_register_tokens + P;
  return frames * P * 3 * p * p + c.depth * block_cache_elements(c.block(), frames * N, recompute) +
         frames * N * c.embed_dim + 2 * frames * P;
}

namespace detail {
inline void dino_check_input(const DinoConfig& c, const char* what, index_t frames, index_t image_h, index_t image_w,
                             index_t blocks) {
  c.validate();
  const index_t p = c.patch_size;
  require(frames >= 1, what, ": needs at least one image, got ", frames);
  require(image_h >= p && image_w >= p && image_h % p == 0 && image_w % p == 0, what, ": image size ", image_h, " x ",
          image_w, " must be a positive multiple of the patch size ", p);
  require(blocks == c.depth, what, ": weights hold ", blocks, " blocks, config depth is ", c.depth);
}

// patches [S * P, 3 p p]: each patch's pixels in the conv weight's (channel, ky, kx) order.
template <class T>
void dino_patchify(T* patches, const T* images, index_t frames, index_t image_h, index_t image_w, index_t p) {
  const index_t gw = image_w / p, P = (image_h / p) * gw, K = 3 * p * p;
  parallel_for(frames * P, [&](index_t r0, index_t r1, int) {
    for (index_t r = r0; r < r1; ++r) {
      const index_t s = r / P, py = (r % P) / gw, px = (r % P) % gw;
      T* row = patches + r * K;
      for (index_t ch = 0; ch < 3; ++ch)
        for (index_t ky = 0; ky < p; ++ky) {
          const T* src = images + ((s * 3 + ch) * image_h + py * p + ky) * image_w + px * p;
          std::copy(src, src + p, row + (ch * p + ky) * p);
        }
    }
  });
}

// Adjoint of dino_patchify (patches do not overlap): adds patch-row gradients into d_images.
template <class T>
void dino_patchify_backward(T* d_images, const T* d_patches, index_t frames, index_t image_h, index_t image_w, index_t p) {
  const index_t gw = image_w / p, P = (image_h / p) * gw, K = 3 * p * p;
  parallel_for(frames * P, [&](index_t r0, index_t r1, int) {
    for (index_t r = r0; r < r1; ++r) {
      const index_t s = r / P, py = (r % P) / gw, px = (r % P) % gw;
      const T* row = d_patches + r * K;
      for (index_t ch = 0; ch < 3; ++ch)
        for (index_t ky = 0; ky < p; ++ky) {
          T* dst = d_images + ((s * 3 + ch) * image_h + py * p + ky) * image_w + px * p;
          for (index_t kx = 0; kx < p; ++kx) dst[kx] += row[(ch * p + ky) * p + kx];
        }
    }
  });
}

// Tokens x [S, N, C]: class token + pos[0], registers, patch embedding + pos[1 + q].
template <class T>
void dino_embed(T* x, const T* patches, const T* pos, index_t frames, index_t P, const DinoConfig& c,
                const DinoWeights<T>& w) {
  const index_t C = c.embed_dim, R = c.num_register_tokens, N = 1 + R + P, K = 3 * c.patch_size * c.patch_size;
  // Patch embeddings land directly in their token rows: row stride N*C between frames.
  for (index_t s = 0; s < frames; ++s) {
    T* dst = x + (s * N + 1 + R) * C;
    for (index_t q = 0; q < P; ++q) std::copy(w.patch_bias, w.patch_bias + C, dst + q * C);
    gemm(Trans::no, Trans::yes, P, C, K, T(1), patches + s * P * K, K, w.patch_weight, K, T(1), dst, C);
  }
  for (index_t s = 0; s < frames; ++s) {
    T* frame = x + s * N * C;
    for (index_t ch = 0; ch < C; ++ch) frame[ch] = w.cls_token[ch] + pos[ch];
    if (R > 0) std::copy(w.register_tokens, w.register_tokens + R * C, frame + C);
    for (index_t q = 0; q < P; ++q)
      for (index_t ch = 0; ch < C; ++ch) frame[(1 + R + q) * C + ch] += pos[(1 + q) * C + ch];
  }
}

// Adjoint of interpolate_bicubic_antialias (a linear map: width pass, then height pass): adds into d_src.
template <class T>
void interpolate_bicubic_antialias_backward(T* d_src, const T* d_dst, index_t channels, index_t in_h, index_t in_w,
                                            index_t out_h, index_t out_w, const InterpolateScaleFactors& factors) {
  std::vector<T> d_mid;  // [channels, in_h, out_w]: gradient of the width pass output
  const T* mid = d_dst;
  if (in_h != out_h) {
    AntialiasAxisWeights<T> k;
    bicubic_antialias_weights<T>(in_h, out_h, antialias_axis_scale<T>(in_h, out_h, factors.height), k);
    d_mid.assign(static_cast<std::size_t>(channels * in_h * out_w), T(0));
    parallel_for(channels, [&](index_t c0, index_t c1, int) {
      for (index_t ch = c0; ch < c1; ++ch)
        for (index_t y = 0; y < out_h; ++y) {
          const T* g = d_dst + (ch * out_h + y) * out_w;
          const T* wt = &k.weights[static_cast<std::size_t>(y * k.max_taps)];
          for (index_t j = 0; j < k.count[static_cast<std::size_t>(y)]; ++j) {
            T* dst = d_mid.data() + (ch * in_h + k.first[static_cast<std::size_t>(y)] + j) * out_w;
            for (index_t x = 0; x < out_w; ++x) dst[x] += wt[j] * g[x];
          }
        }
    });
    mid = d_mid.data();
  }
  if (in_w == out_w) {
    for (index_t i = 0; i < channels * in_h * in_w; ++i) d_src[i] += mid[i];
    return;
  }
  AntialiasAxisWeights<T> k;
  bicubic_antialias_weights<T>(in_w, out_w, antialias_axis_scale<T>(in_w, out_w, factors.width), k);
  parallel_for(channels * in_h, [&](index_t r0, index_t r1, int) {
    for (index_t r = r0; r < r1; ++r) {
      const T* g = mid + r * out_w;
      T* dst = d_src + r * in_w;
      for (index_t x = 0; x < out_w; ++x) {
        const T* wt = &k.weights[static_cast<std::size_t>(x * k.max_taps)];
        const index_t first = k.first[static_cast<std::size_t>(x)];
        for (index_t j = 0; j < k.count[static_cast<std::size_t>(x)]; ++j) dst[first + j] += wt[j] * g[x];
      }
    }
  });
}
}  // namespace detail

// Adjoint of dino_position_embedding: d_pos [1 + grid_h * grid_w, C] -> adds into d_pos_embed [1 + M*M, C].
template <class T>
void dino_position_embedding_backward(T* d_pos_embed, const T* d_pos, const DinoConfig& c, index_t image_h,
                                      index_t image_w) {
  const index_t C = c.embed_dim, M = c.pos_grid(), N = M * M;
  const index_t gh = image_h / c.patch_size, gw = image_w / c.patch_size, G = gh * gw;
  if (G == N && image_h == image_w) {
    for (index_t i = 0; i < (1 + N) * C; ++i) d_pos_embed[i] += d_pos[i];
    return;
  }
  for (index_t ch = 0; ch < C; ++ch) d_pos_embed[ch] += d_pos[ch];
  InterpolateScaleFactors factors;
  if (c.interpolate_offset != 0.0) {
    factors.height = (static_cast<double>(gh) + c.interpolate_offset) / static_cast<double>(M);
    factors.width = (static_cast<double>(gw) + c.interpolate_offset) / static_cast<double>(M);
  }
  std::vector<T> d_resized(static_cast<std::size_t>(C * G)), d_planar(static_cast<std::size_t>(C * N), T(0));
  for (index_t p = 0; p < G; ++p)
    for (index_t ch = 0; ch < C; ++ch) d_resized[ch * G + p] = d_pos[(1 + p) * C + ch];
  detail::interpolate_bicubic_antialias_backward(d_planar.data(), d_resized.data(), C, M, M, gh, gw, factors);
  for (index_t p = 0; p < N; ++p)
    for (index_t ch = 0; ch < C; ++ch) d_pos_embed[(1 + p) * C + ch] += d_planar[ch * N + p];
}

// Adjoint of imagenet_normalize: adds d_normalized / std into d_images.
template <class T>
void imagenet_normalize_backward(T* d_images, const T* d_normalized, index_t frames, index_t image_h, index_t image_w) {
  static constexpr float stdev[3] = {0.229f, 0.224f, 0.225f};
  const index_t plane = image_h * image_w;
  parallel_for(frames * 3, [&](index_t p0, index_t p1, int) {
    for (index_t p = p0; p < p1; ++p) {
      const T sd = static_cast<T>(stdev[p % 3]);
      for (index_t i = 0; i < plane; ++i) d_images[p * plane + i] += d_normalized[p * plane + i] / sd;
    }
  });
}

namespace detail {
// One forward for inference (cache null) and training.
template <class T>
void dino_forward_impl(T* out, const T* images, index_t frames, index_t image_h, index_t image_w, const DinoConfig& c,
                       const DinoWeights<T>& w, DinoWorkspace<T>& ws, DinoCache<T>* cache, bool recompute) {
  dino_check_input(c, "DINO", frames, image_h, image_w, static_cast<index_t>(w.blocks.size()));
  const index_t p = c.patch_size, C = c.embed_dim, R = c.num_register_tokens;
  const index_t gh = image_h / p, gw = image_w / p, P = gh * gw, N = 1 + R + P, K = 3 * p * p;
  const Tensor<T, 2> pos = dino_position_embedding(c, w, image_h, image_w);
  auto& patches = cache ? cache->patches : ws.patches;
  patches.resize(static_cast<std::size_t>(frames * P * K));
  dino_patchify(patches.data(), images, frames, image_h, image_w, p);
  ws.tokens.resize(static_cast<std::size_t>(frames * N * C));
  T* x = ws.tokens.data();
  dino_embed(x, patches.data(), pos.data(), frames, P, c, w);
  const BlockConfig bc = c.block();
  std::span<T> block_ws = ws.block.get(bc, frames * N);
  if (cache) {
    cache->frames = frames, cache->image_h = image_h, cache->image_w = image_w;
    cache->blocks.resize(w.blocks.size());
    for (std::size_t i = 0; i < w.blocks.size(); ++i)
      block_forward_train<T>(x, frames, N, bc, w.blocks[i], nullptr, nullptr, cache->blocks[i], recompute, block_ws);
    cache->x_final.assign(x, x + frames * N * C);
    cache->norm_mean.resize(static_cast<std::size_t>(frames * P));
    cache->norm_rstd.resize(static_cast<std::size_t>(frames * P));
  } else {
    for (const auto& blk : w.blocks) block_forward<T>(x, frames, N, bc, blk, nullptr, nullptr, block_ws);
  }
  for (index_t s = 0; s < frames; ++s)
    nn::layernorm_forward(out + s * P * C, x + (s * N + 1 + R) * C, w.norm_weight, w.norm_bias, P, C,
                          static_cast<T>(c.norm_eps),
                          cache ? nn::LayerNormCache<T>{cache->norm_mean.data() + s * P, cache->norm_rstd.data() + s * P}
                                : nn::LayerNormCache<T>{});
}
}  // namespace detail

// images [S, 3, H, W], already normalised with the ImageNet mean and std; H and W multiples of the patch size.
// Writes the normalised patch tokens to out [S, (H/p) * (W/p), C].
template <class T>
void dino_forward(T* out, const T* images, index_t frames, index_t image_h, index_t image_w, const DinoConfig& c,
                  const DinoWeights<T>& w, DinoWorkspace<T>& ws) {
  detail::dino_forward_impl<T>(out, images, frames, image_h, image_w, c, w, ws, nullptr, false);
}

// dino_forward that also fills `cache` for dino_backward (block activations, or only block inputs with recompute).
template <class T>
void dino_forward_train(T* out, const T* images, index_t frames, index_t image_h, index_t image_w, const DinoConfig& c,
                        const DinoWeights<T>& w, DinoCache<T>& cache, bool recompute, DinoWorkspace<T>& ws) {
  detail::dino_forward_impl<T>(out, images, frames, image_h, image_w, c, w, ws, &cache, recompute);
}

template <class T>
struct DinoBackwardScratch {
  std::vector<T, AlignedAllocator<T>> d_x, d_pos, d_patches;
  BlockBackwardScratch<T> block;
};

// d_out [S, P, C]: gradient of dino_forward's output. Adds (+=) into the parameter gradients g and, when d_images is
// not null, into d_images [S, 3, H, W] (gradient of the normalised images dino_forward read).
template <class T>
void dino_backward(T* d_images, const DinoGrads<T>& g, const T* d_out, DinoCache<T>& cache, const DinoConfig& c,
                   const DinoWeights<T>& w, DinoBackwardScratch<T>& scratch) {
  const index_t frames = cache.frames, image_h = cache.image_h, image_w = cache.image_w;
  detail::dino_check_input(c, "DINO backward", frames, image_h, image_w, static_cast<index_t>(w.blocks.size()));
  require(g.blocks.size() == w.blocks.size() && cache.blocks.size() == w.blocks.size(), "DINO backward: ",
          g.blocks.size(), " block gradients and ", cache.blocks.size(), " block caches for ", w.blocks.size(), " blocks");
  const index_t p = c.patch_size, C = c.embed_dim, R = c.num_register_tokens;
  const index_t gh = image_h / p, gw = image_w / p, P = gh * gw, N = 1 + R + P, K = 3 * p * p;
  require(static_cast<index_t>(cache.x_final.size()) == frames * N * C, "DINO backward: the cache does not match ",
          frames, " images of ", image_h, " x ", image_w);
  scratch.d_x.assign(static_cast<std::size_t>(frames * N * C), T(0));
  T* d_x = scratch.d_x.data();
  for (index_t s = 0; s < frames; ++s) {
    const index_t at = (s * N + 1 + R) * C;
    nn::layernorm_backward(d_x + at, g.norm_weight, g.norm_bias, d_out + s * P * C, cache.x_final.data() + at,
                           w.norm_weight, P, C,
                           nn::LayerNormCache<T>{cache.norm_mean.data() + s * P, cache.norm_rstd.data() + s * P});
  }
  const BlockConfig bc = c.block();
  for (std::size_t i = w.blocks.size(); i-- > 0;)
    block_backward<T>(d_x, g.blocks[i], cache.blocks[i], bc, w.blocks[i], nullptr, nullptr, scratch.block);

  // Token assembly: class token + pos[0], registers, patch embeddings + pos[1 + q].
  scratch.d_pos.assign(static_cast<std::size_t>((1 + P) * C), T(0));
  T* d_pos = scratch.d_pos.data();
  for (index_t s = 0; s < frames; ++s) {
    const T* frame = d_x + s * N * C;
    for (index_t ch = 0; ch < C; ++ch) d_pos[ch] += frame[ch];
    if (g.cls_token)
      for (index_t ch = 0; ch < C; ++ch) g.cls_token[ch] += frame[ch];
    if (g.register_tokens)
      for (index_t i = 0; i < R * C; ++i) g.register_tokens[i] += frame[C + i];
    for (index_t q = 0; q < P; ++q)
      for (index_t ch = 0; ch < C; ++ch) {
        const T v = frame[(1 + R + q) * C + ch];
        d_pos[(1 + q) * C + ch] += v;
        if (g.patch_bias) g.patch_bias[ch] += v;
      }
  }
  if (g.pos_embed) dino_position_embedding_backward(g.pos_embed, d_pos, c, image_h, image_w);
  for (index_t s = 0; s < frames; ++s) {
    const T* d_emb = d_x + (s * N + 1 + R) * C;  // [P, C], row stride C
    if (g.patch_weight)
      gemm(Trans::yes, Trans::no, C, K, P, T(1), d_emb, C, cache.patches.data() + s * P * K, K, T(1), g.patch_weight, K);
  }
  if (d_images) {
    scratch.d_patches.resize(static_cast<std::size_t>(frames * P * K));
    for (index_t s = 0; s < frames; ++s)
      gemm(Trans::no, Trans::no, P, K, C, T(1), d_x + (s * N + 1 + R) * C, C, w.patch_weight, K, T(0),
           scratch.d_patches.data() + s * P * K, K);
    detail::dino_patchify_backward(d_images, scratch.d_patches.data(), frames, image_h, image_w, p);
  }
}

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
