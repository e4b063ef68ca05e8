#pragma once
// VGGT's alternating-attention aggregator on top of the DINOv2 patch tokens: per frame, a camera token and
// register tokens (frame 0 uses its own pair) are put in front of the patch tokens; frame blocks attend within a
// frame, global blocks across all frames; both use qk-norm, 2-D RoPE (special tokens at position 0, patch (y, x)
// at (y+1, x+1)) and LayerScale. Output i is [frame block i output, global block i output] along channels.
// aggregator_trunk_forward_train / aggregator_trunk_backward: training, gradients arriving for any of the outputs.
#include <algorithm>
#include <cstdint>
#include <functional>
#include <map>
#include <set>
#include <span>
#include <string>
#include <utility>
#include <vector>

#include "flexsplat/core/tensor.hpp"
#include "flexsplat/geometry/block.hpp"
#include "flexsplat/geometry/config.hpp"
#include "flexsplat/io/param_source.hpp"
#include "flexsplat/geometry/rope.hpp"

namespace flexsplat {
inline namespace v0 {
namespace geometry {

template <class T>
struct AggregatorWeights {
  const T* camera_token = nullptr;    // [1, K, 1, C], K = frame_tokens (VGGT: 2)
  const T* register_token = nullptr;  // [1, K, R, C]
  std::vector<BlockWeights<T>> frame_blocks, global_blocks;
};

// Parameters of the aggregator outside the DINOv2 embedder ("aggregator." prefix included).
inline void append_aggregator_trunk_specs(std::vector<io::TensorSpec>& out, const AggregatorConfig& c) {
  const index_t C = c.embed_dim;
  out.push_back({"aggregator.camera_token", {1, c.frame_tokens, 1, C}});
  out.push_back({"aggregator.register_token", {1, c.frame_tokens, c.num_register_tokens, C}});
  for (index_t i = 0; i < c.depth; ++i)
    append_block_specs(out, "aggregator.frame_blocks." + std::to_string(i) + ".", c.block());
  for (index_t i = 0; i < c.depth; ++i)
    append_block_specs(out, "aggregator.global_blocks." + std::to_string(i) + ".", c.block());
}

template <class T>
AggregatorWeights<T> load_aggregator_trunk_weights(io::ParamSource<T>& src, const AggregatorConfig& c) {
  c.validate();
  const index_t C = c.embed_dim;
  AggregatorWeights<T> w;
  w.camera_token = src.get("aggregator.camera_token", {1, c.frame_tokens, 1, C});
  w.register_token = src.get("aggregator.register_token", {1, c.frame_tokens, c.num_register_tokens, C});
  for (index_t i = 0; i < c.depth; ++i)
    w.frame_blocks.push_back(load_block_weights(src, "aggregator.frame_blocks." + std::to_string(i) + ".", c.block()));
  for (index_t i = 0; i < c.depth; ++i)
    w.global_blocks.push_back(load_block_weights(src, "aggregator.global_blocks." + std::to_string(i) + ".", c.block()));
  return w;
}

// Aggregator outputs that were asked for: layer index -> [S, tokens, 2C].
template <class T>
struct AggregatorOutputs {
  index_t frames = 0, tokens = 0, channels = 0, patch_start_idx = 0, grid_h = 0, grid_w = 0;
  std::map<index_t, Tensor<T, 3>> layers;
  const Tensor<T, 3>& at(index_t layer) const {
    auto it = layers.find(layer);
    require(it != layers.end(), "aggregator output ", layer, " was not kept (kept: ", layers.size(), " layers)");
    return it->second;
  }
};

// Caller-held buffers reused across calls.
template <class T>
struct AggregatorWorkspace {
  std::vector<T, AlignedAllocator<T>> tokens;
  std::vector<std::int32_t> positions;
  BlockWorkspace<T> block;
};

// Token positions (y, x) for S frames of `tokens` rows each: special tokens at 0, patches shifted by one.
inline void aggregator_positions(std::vector<std::int32_t>& pos, index_t frames, index_t patch_start, index_t grid_h,
                                 index_t grid_w) {
  const index_t tokens = patch_start + grid_h * grid_w;
  pos.assign(static_cast<std::size_t>(frames * tokens * 2), 0);
  for (index_t s = 0; s < frames; ++s)
    for (index_t p = 0; p < grid_h * grid_w; ++p) {
      const index_t r = s * tokens + patch_start + p;
      pos[2 * r] = static_cast<std::int32_t>(p / grid_w + 1);
      pos[2 * r + 1] = static_cast<std::int32_t>(p % grid_w + 1);
    }
}

// Gradient pointers mirroring AggregatorWeights (null: not wanted).
template <class T>
struct AggregatorGrads {
  T* camera_token = nullptr;
  T* register_token = nullptr;
  std::vector<BlockGrads<T>> frame_blocks, global_blocks;
};

template <class T>
AggregatorGrads<T> aggregator_grads(const AggregatorWeights<T>& w, const T* params_base, T* grads_base) {
  AggregatorGrads<T> g;
  g.camera_token = io::rebase_pointer(w.camera_token, params_base, grads_base);
  g.register_token = io::rebase_pointer(w.register_token, params_base, grads_base);
  for (const auto& b : w.frame_blocks) g.frame_blocks.push_back(block_grads(b, params_base, grads_base));
  for (const auto& b : w.global_blocks) g.global_blocks.push_back(block_grads(b, params_base, grads_base));
  return g;
}

// What aggregator_trunk_backward reads: one BlockCache per block (only its input with recompute), RoPE table and
// token positions.
template <class T>
struct AggregatorCache {
  index_t frames = 0, grid_h = 0, grid_w = 0;
  std::vector<BlockCache<T>> frame_blocks, global_blocks;
  Rope2DTable<T> rope;
  std::vector<std::int32_t> positions;
};

// Elements the block caches of one aggregator pass hold (the kept outputs are counted by their consumer).
inline index_t aggregator_cache_elements(const AggregatorConfig& c, index_t frames, index_t grid_h, index_t grid_w,
                                         bool recompute) {
  const index_t rows = frames * (c.patch_start_idx() + grid_h * grid_w);
  return 2 * c.depth * block_cache_elements(c.block(), rows, recompute);
}

namespace detail {
inline void aggregator_check(const AggregatorConfig& c, index_t frames, index_t grid_h, index_t grid_w,
                             std::size_t frame_blocks, std::size_t global_blocks) {
  c.validate();
  require(frames >= 1, "aggregator: needs at least one frame, got ", frames);
  require(grid_h >= 1 && grid_w >= 1, "aggregator: empty patch grid ", grid_h, " x ", grid_w);
  require(static_cast<index_t>(frame_blocks) == c.depth && static_cast<index_t>(global_blocks) == c.depth,
          "aggregator: weights hold ", frame_blocks, " frame and ", global_blocks, " global blocks, config depth is ",
          c.depth);
}

// The blocks in execution order: (is_global, layer).
inline std::vector<std::pair<bool, index_t>> aggregator_schedule(const AggregatorConfig& c) {
  std::vector<std::pair<bool, index_t>> order;
  for (index_t g = 0; g < c.depth / c.aa_block_size; ++g)
    for (const auto& kind : c.aa_order)
      for (index_t k = 0; k < c.aa_block_size; ++k) order.emplace_back(kind == "global", g * c.aa_block_size + k);
  return order;
}

// One forward for inference (cache null) and training.
template <class T>
AggregatorOutputs<T> aggregator_forward_impl(const T* patch_tokens, index_t frames, index_t grid_h, index_t grid_w,
                                             const AggregatorConfig& c, const AggregatorWeights<T>& w,
                                             const std::vector<index_t>& keep, AggregatorWorkspace<T>& ws,
                                             const std::function<void(index_t, index_t)>& progress,
                                             AggregatorCache<T>* cache, bool recompute) {
  aggregator_check(c, frames, grid_h, grid_w, w.frame_blocks.size(), w.global_blocks.size());
  std::set<index_t> wanted(keep.begin(), keep.end());
  if (keep.empty())
    for (index_t i = 0; i < c.depth; ++i) wanted.insert(i);
  for (index_t i : wanted) require(i >= 0 && i < c.depth, "aggregator: output ", i, " requested, depth is ", c.depth);

  const index_t C = c.embed_dim, R = c.num_register_tokens, start = c.patch_start_idx(), P = grid_h * grid_w;
  const index_t N = start + P, rows = frames * N;
  AggregatorOutputs<T> out;
  out.frames = frames;
  out.tokens = N;
  out.channels = 2 * C;
  out.patch_start_idx = start;
  out.grid_h = grid_h;
  out.grid_w = grid_w;

  ws.tokens.resize(static_cast<std::size_t>(rows * C));
  T* x = ws.tokens.data();
  for (index_t s = 0; s < frames; ++s) {
    const index_t which = c.frame_token(s);
    T* frame = x + s * N * C;
    std::copy(w.camera_token + which * C, w.camera_token + (which + 1) * C, frame);
    std::copy(w.register_token + which * R * C, w.register_token + (which + 1) * R * C, frame + C);
    std::copy(patch_tokens + s * P * C, patch_tokens + (s + 1) * P * C, frame + start * C);
  }
  Rope2DTable<T> local_rope;
  Rope2DTable<T>& rope = cache ? cache->rope : local_rope;
  std::vector<std::int32_t>& positions = cache ? cache->positions : ws.positions;
  const bool use_rope = c.rope_freq > 0;
  if (use_rope) {
    rope = rope2d_table<T>(c.block().head_dim(), std::max(grid_h, grid_w) + 1, c.rope_freq);
    aggregator_positions(positions, frames, start, grid_h, grid_w);
  }
  const Rope2DTable<T>* rope_ptr = use_rope ? &rope : nullptr;
  const std::int32_t* pos_ptr = use_rope ? positions.data() : nullptr;
  const BlockConfig bc = c.block();
  std::span<T> block_ws = ws.block.get(bc, rows);
  if (cache) {
    cache->frames = frames, cache->grid_h = grid_h, cache->grid_w = grid_w;
    cache->frame_blocks.resize(static_cast<std::size_t>(c.depth));
    cache->global_blocks.resize(static_cast<std::size_t>(c.depth));
  }

  // Intermediates of the current group, per kind, until both kinds have run.
  std::vector<Tensor<T, 3>> frame_inter, global_inter;
  auto save = [&](std::vector<Tensor<T, 3>>& dst, index_t layer) {
    if (!wanted.count(layer)) {
      dst.emplace_back();
      return;
    }
    Tensor<T, 3> t(Shape<3>{frames, N, C});
    std::copy(x, x + rows * C, t.data());
    dst.push_back(std::move(t));
  };
  const index_t groups = c.depth / c.aa_block_size;
  for (index_t g = 0; g < groups; ++g) {
    frame_inter.clear();
    global_inter.clear();
    for (const auto& kind : c.aa_order) {
      for (index_t k = 0; k < c.aa_block_size; ++k) {
        const index_t layer = g * c.aa_block_size + k;
        const bool global = kind == "global";
        // Frame blocks attend within each frame, global blocks across all of them.
        const index_t batch = global ? 1 : frames, tokens = global ? rows : N;
        const auto& blk = global ? w.global_blocks[layer] : w.frame_blocks[layer];
        if (cache)
          block_forward_train<T>(x, batch, tokens, bc, blk, rope_ptr, pos_ptr,
                                 (global ? cache->global_blocks : cache->frame_blocks)[layer], recompute, block_ws);
        else
          block_forward<T>(x, batch, tokens, bc, blk, rope_ptr, pos_ptr, block_ws);
        save(global ? global_inter : frame_inter, layer);
      }
    }
    for (index_t k = 0; k < c.aa_block_size; ++k) {
      const index_t layer = g * c.aa_block_size + k;
      if (!wanted.count(layer)) continue;
      Tensor<T, 3> cat(Shape<3>{frames, N, 2 * C});
      const T* f = frame_inter[k].data();
      const T* gl = global_inter[k].data();
      for (index_t r = 0; r < rows; ++r) {
        std::copy(f + r * C, f + (r + 1) * C, cat.data() + r * 2 * C);
        std::copy(gl + r * C, gl + (r + 1) * C, cat.data() + r * 2 * C + C);
      }
      out.layers.emplace(layer, std::move(cat));
    }
    if (progress) progress(g, groups);
  }
  return out;
}
}  // namespace detail

// patch_tokens [S, grid_h * grid_w, C] (DINOv2's normalised patch tokens). keep: which outputs to return (all when
// empty). progress (may be empty) is called after each block pair with (pair index, pair count).
template <class T>
AggregatorOutputs<T> aggregator_trunk_forward(const T* patch_tokens, index_t frames, index_t grid_h, index_t grid_w,
                                              const AggregatorConfig& c, const AggregatorWeights<T>& w,
                                              const std::vector<index_t>& keep, AggregatorWorkspace<T>& ws,
                                              const std::function<void(index_t, index_t)>& progress = {}) {
  return detail::aggregator_forward_impl<T>(patch_tokens, frames, grid_h, grid_w, c, w, keep, ws, progress, nullptr,
                                            false);
}

// aggregator_trunk_forward that also fills `cache` for aggregator_trunk_backward (with `recompute`, each block keeps
// only its input and reruns its forward in backward). Outputs are bit-identical to the inference forward's.
template <class T>
AggregatorOutputs<T> aggregator_trunk_forward_train(const T* patch_tokens, index_t frames, index_t grid_h, index_t grid_w,
                                                    const AggregatorConfig& c, const AggregatorWeights<T>& w,
                                                    const std::vector<index_t>& keep, AggregatorCache<T>& cache,
                                                    bool recompute, AggregatorWorkspace<T>& ws,
                                                    const std::function<void(index_t, index_t)>& progress = {}) {
  return detail::aggregator_forward_impl<T>(patch_tokens, frames, grid_h, grid_w, c, w, keep, ws, progress, &cache,
                                            recompute);
}

template <class T>
struct AggregatorBackwardScratch {
  std::vector<T, AlignedAllocator<T>> d_x;
  BlockBackwardScratch<T> block;
};

// d_layers[i] (size depth; null = no gradient): gradient of output i, [S, tokens, 2C], whether or not the forward kept
// it. Adds (+=) into the parameter gradients g and, when not null, into d_patch_tokens [S, grid_h * grid_w, C].
template <class T>
void aggregator_trunk_backward(T* d_patch_tokens, const AggregatorGrads<T>& g, std::span<const T* const> d_layers,
                               AggregatorCache<T>& cache, const AggregatorConfig& c, const AggregatorWeights<T>& w,
                               AggregatorBackwardScratch<T>& scratch) {
  const index_t frames = cache.frames, grid_h = cache.grid_h, grid_w = cache.grid_w;
  detail::aggregator_check(c, frames, grid_h, grid_w, w.frame_blocks.size(), w.global_blocks.size());
  require(static_cast<index_t>(d_layers.size()) == c.depth, "aggregator backward: ", d_layers.size(),
          " output gradients for depth ", c.depth);
  require(static_cast<index_t>(g.frame_blocks.size()) == c.depth && static_cast<index_t>(g.global_blocks.size()) == c.depth,
          "aggregator backward: gradients hold ", g.frame_blocks.size(), " frame and ", g.global_blocks.size(),
          " global blocks, config depth is ", c.depth);
  require(static_cast<index_t>(cache.frame_blocks.size()) == c.depth &&
              static_cast<index_t>(cache.global_blocks.size()) == c.depth,
          "aggregator backward: the cache was not filled by aggregator_trunk_forward_train with this config");
  const index_t C = c.embed_dim, R = c.num_register_tokens, start = c.patch_start_idx(), P = grid_h * grid_w;
  const index_t N = start + P, rows = frames * N;
  const bool use_rope = c.rope_freq > 0;
  const Rope2DTable<T>* rope_ptr = use_rope ? &cache.rope : nullptr;
  const std::int32_t* pos_ptr = use_rope ? cache.positions.data() : nullptr;
  const BlockConfig bc = c.block();

  scratch.d_x.assign(static_cast<std::size_t>(rows * C), T(0));
  T* d_x = scratch.d_x.data();
  const auto schedule = detail::aggregator_schedule(c);
  for (auto it = schedule.rbegin(); it != schedule.rend(); ++it) {
    const auto [global, layer] = *it;
    // Output `layer` holds this block's result in its first (frame) or second (global) half of the channels.
    if (const T* d_out = d_layers[static_cast<std::size_t>(layer)]) {
      const index_t half = global ? C : 0;
      parallel_for(rows, [&](index_t r0, index_t r1, int) {
        for (index_t r = r0; r < r1; ++r)
          for (index_t i = 0; i < C; ++i) d_x[r * C + i] += d_out[r * 2 * C + half + i];
      });
    }
    block_backward<T>(d_x, (global ? g.global_blocks : g.frame_blocks)[layer],
                      (global ? cache.global_blocks : cache.frame_blocks)[layer], bc,
                      (global ? w.global_blocks : w.frame_blocks)[layer], rope_ptr, pos_ptr, scratch.block);
  }
  for (index_t s = 0; s < frames; ++s) {
    const index_t which = c.frame_token(s);
    const T* frame = d_x + s * N * C;
    if (g.camera_token)
      for (index_t i = 0; i < C; ++i) g.camera_token[which * C + i] += frame[i];
    if (g.register_token)
      for (index_t i = 0; i < R * C; ++i) g.register_token[which * R * C + i] += frame[C + i];
    if (d_patch_tokens)
      for (index_t i = 0; i < P * C; ++i) d_patch_tokens[s * P * C + i] += frame[start * C + i];
  }
}

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
