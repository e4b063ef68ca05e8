#pragma once
// VGGT's alternating-attention aggregator on top of the DINOv2 patch tokens: per frame, a camera token and
// register tokens (frame 0 uses its own pair) are put in front of the patch tokens; frame blocks attend within a
// frame, global blocks across all frames; both use qk-norm, 2-D RoPE (special tokens at position 0, patch (y, x)
// at (y+1, x+1)) and LayerScale. Output i is [frame block i output, global block i output] along channels.
#include <algorithm>
#include <cstdint>
#include <functional>
#include <map>
#include <set>
#include <string>
#include <vector>

#include "flexsplat/core/tensor.hpp"
#include "flexsplat/geometry/block.hpp"
#include "flexsplat/geometry/config.hpp"
#include "flexsplat/geometry/param_source.hpp"
#include "flexsplat/geometry/rope.hpp"

namespace flexsplat {
inline namespace v0 {
namespace geometry {

template <class T>
struct AggregatorWeights {
  const T* camera_token = nullptr;    // [1, 2, 1, C]
  const T* register_token = nullptr;  // [1, 2, R, C]
  std::vector<BlockWeights<T>> frame_blocks, global_blocks;
};

// Parameters of the aggregator outside the DINOv2 embedder ("aggregator." prefix included).
inline void append_aggregator_trunk_specs(std::vector<TensorSpec>& out, const AggregatorConfig& c) {
  const index_t C = c.embed_dim;
  out.push_back({"aggregator.camera_token", {1, 2, 1, C}});
  out.push_back({"aggregator.register_token", {1, 2, c.num_register_tokens, C}});
  for (index_t i = 0; i < c.depth; ++i)
    append_block_specs(out, "aggregator.frame_blocks." + std::to_string(i) + ".", c.block());
  for (index_t i = 0; i < c.depth; ++i)
    append_block_specs(out, "aggregator.global_blocks." + std::to_string(i) + ".", c.block());
}

template <class T>
AggregatorWeights<T> load_aggregator_trunk_weights(ParamSource<T>& src, const AggregatorConfig& c) {
  c.validate();
  const index_t C = c.embed_dim;
  AggregatorWeights<T> w;
  w.camera_token = src.get("aggregator.camera_token", {1, 2, 1, C});
  w.register_token = src.get("aggregator.register_token", {1, 2, c.num_register_tokens, C});
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

// patch_tokens [S, grid_h * grid_w, C] (DINOv2's normalised patch tokens). keep: which outputs to return (all when
// empty). progress (may be empty) is called after each block pair with (pair index, pair count).
template <class T>
AggregatorOutputs<T> aggregator_trunk_forward(const T* patch_tokens, index_t frames, index_t grid_h, index_t grid_w,
                                              const AggregatorConfig& c, const AggregatorWeights<T>& w,
                                              const std::vector<index_t>& keep, AggregatorWorkspace<T>& ws,
                                              const std::function<void(index_t, index_t)>& progress = {}) {
  c.validate();
  require(frames >= 1, "aggregator: needs at least one frame, got ", frames);
  require(grid_h >= 1 && grid_w >= 1, "aggregator: empty patch grid ", grid_h, " x ", grid_w);
  require(static_cast<index_t>(w.frame_blocks.size()) == c.depth && static_cast<index_t>(w.global_blocks.size()) == c.depth,
          "aggregator: weights hold ", w.frame_blocks.size(), " frame and ", w.global_blocks.size(),
          " global blocks, config depth is ", c.depth);
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
    const index_t which = s == 0 ? 0 : 1;  // frame 0 has its own camera and register tokens
    T* frame = x + s * N * C;
    std::copy(w.camera_token + which * C, w.camera_token + (which + 1) * C, frame);
    std::copy(w.register_token + which * R * C, w.register_token + (which + 1) * R * C, frame + C);
    std::copy(patch_tokens + s * P * C, patch_tokens + (s + 1) * P * C, frame + start * C);
  }
  Rope2DTable<T> rope;
  const bool use_rope = c.rope_freq > 0;
  if (use_rope) {
    rope = rope2d_table<T>(c.block().head_dim(), std::max(grid_h, grid_w) + 1, c.rope_freq);
    aggregator_positions(ws.positions, frames, start, grid_h, grid_w);
  }
  const Rope2DTable<T>* rope_ptr = use_rope ? &rope : nullptr;
  const std::int32_t* pos_ptr = use_rope ? ws.positions.data() : nullptr;
  const BlockConfig bc = c.block();
  std::span<T> block_ws = ws.block.get(bc, rows);

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
        if (kind == "frame") {
          block_forward(x, frames, N, bc, w.frame_blocks[layer], rope_ptr, pos_ptr, block_ws);
          save(frame_inter, layer);
        } else {
          block_forward(x, index_t{1}, rows, bc, w.global_blocks[layer], rope_ptr, pos_ptr, block_ws);
          save(global_inter, layer);
        }
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

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
