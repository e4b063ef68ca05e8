#pragma once
// The transformer block shared by DINOv2, VGGT's aggregator and its camera-head trunk:
//   x += ls1 * proj(attention(qk_norm(qkv(norm1(x))), rope))
//   x += ls2 * fc2(gelu(fc1(norm2(x))))
// x is updated in place, rows are [batch * tokens, dim]. block_forward is the inference path; block_forward_train keeps
// the activations (or only the input, to recompute) that block_backward reads; backward adds (+=) into gradients.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <span>
#include <string>
#include <type_traits>
#include <utility>
#include <vector>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/simd_dispatch.hpp"
#include "flexsplat/io/param_source.hpp"
#include "flexsplat/geometry/rope.hpp"
#include "flexsplat/nn/activations.hpp"
#include "flexsplat/nn/attention.hpp"
#include "flexsplat/nn/layernorm.hpp"
#include "flexsplat/nn/linear.hpp"

namespace flexsplat {
inline namespace v0 {
namespace geometry {

struct BlockConfig {
  index_t dim = 1024;
  index_t num_heads = 16;
  double mlp_ratio = 4.0;
  bool qkv_bias = true;
  bool proj_bias = true;
  bool ffn_bias = true;
  bool qk_norm = false;      // LayerNorm over head_dim on q and k
  bool layer_scale = true;   // ls1/ls2 gamma present (init_values > 0)
  double norm_eps = 1e-5;    // norm1/norm2: DINOv2 uses 1e-6, VGGT's own blocks PyTorch's default 1e-5
  double qk_norm_eps = 1e-5;

  index_t head_dim() const { return num_heads > 0 ? dim / num_heads : 0; }
  // Python's int(dim * mlp_ratio).
  index_t mlp_hidden() const { return static_cast<index_t>(static_cast<double>(dim) * mlp_ratio); }
  void validate(const std::string& what) const {
    require(dim > 0 && num_heads > 0 && dim % num_heads == 0, what, ": dim ", dim,
            " must be a positive multiple of num_heads ", num_heads);
    require(mlp_hidden() > 0, what, ": mlp hidden size ", mlp_hidden(), " (dim ", dim, " x mlp_ratio ", mlp_ratio,
            ") must be positive");
  }
};

// Pointers into parameter storage; optional parts are null when the config leaves them out.
template <class T>
struct BlockWeights {
  const T *norm1_weight = nullptr, *norm1_bias = nullptr;
  const T *qkv_weight = nullptr, *qkv_bias = nullptr;  // [3*dim, dim], [3*dim]
  const T *q_norm_weight = nullptr, *q_norm_bias = nullptr, *k_norm_weight = nullptr, *k_norm_bias = nullptr;
  const T *proj_weight = nullptr, *proj_bias = nullptr;
  const T* ls1 = nullptr;
  const T *norm2_weight = nullptr, *norm2_bias = nullptr;
  const T *fc1_weight = nullptr, *fc1_bias = nullptr;  // [hidden, dim]
  const T *fc2_weight = nullptr, *fc2_bias = nullptr;  // [dim, hidden]
  const T* ls2 = nullptr;
};

// Parameter names (after `prefix`, e.g. "aggregator.frame_blocks.3.") and shapes, as in PyTorch's state_dict.
inline void append_block_specs(std::vector<io::TensorSpec>& out, const std::string& prefix, const BlockConfig& c) {
  const index_t C = c.dim, H = c.mlp_hidden(), hd = c.head_dim();
  out.push_back({prefix + "norm1.weight", {C}});
  out.push_back({prefix + "norm1.bias", {C}});
  out.push_back({prefix + "attn.qkv.weight", {3 * C, C}});
  if (c.qkv_bias) out.push_back({prefix + "attn.qkv.bias", {3 * C}});
  if (c.qk_norm) {
    out.push_back({prefix + "attn.q_norm.weight", {hd}});
    out.push_back({prefix + "attn.q_norm.bias", {hd}});
    out.push_back({prefix + "attn.k_norm.weight", {hd}});
    out.push_back({prefix + "attn.k_norm.bias", {hd}});
  }
  out.push_back({prefix + "attn.proj.weight", {C, C}});
  if (c.proj_bias) out.push_back({prefix + "attn.proj.bias", {C}});
  if (c.layer_scale) out.push_back({prefix + "ls1.gamma", {C}});
  out.push_back({prefix + "norm2.weight", {C}});
  out.push_back({prefix + "norm2.bias", {C}});
  out.push_back({prefix + "mlp.fc1.weight", {H, C}});
  if (c.ffn_bias) out.push_back({prefix + "mlp.fc1.bias", {H}});
  out.push_back({prefix + "mlp.fc2.weight", {C, H}});
  if (c.ffn_bias) out.push_back({prefix + "mlp.fc2.bias", {C}});
  if (c.layer_scale) out.push_back({prefix + "ls2.gamma", {C}});
}

template <class T>
BlockWeights<T> load_block_weights(io::ParamSource<T>& src, const std::string& prefix, const BlockConfig& c) {
  c.validate(prefix + "block");
  const index_t C = c.dim, H = c.mlp_hidden(), hd = c.head_dim();
  BlockWeights<T> w;
  w.norm1_weight = src.get(prefix + "norm1.weight", {C});
  w.norm1_bias = src.get(prefix + "norm1.bias", {C});
  w.qkv_weight = src.get(prefix + "attn.qkv.weight", {3 * C, C});
  if (c.qkv_bias) w.qkv_bias = src.get(prefix + "attn.qkv.bias", {3 * C});
  if (c.qk_norm) {
    w.q_norm_weight = src.get(prefix + "attn.q_norm.weight", {hd});
    w.q_norm_bias = src.get(prefix + "attn.q_norm.bias", {hd});
    w.k_norm_weight = src.get(prefix + "attn.k_norm.weight", {hd});
    w.k_norm_bias = src.get(prefix + "attn.k_norm.bias", {hd});
  }
  w.proj_weight = src.get(prefix + "attn.proj.weight", {C, C});
  if (c.proj_bias) w.proj_bias = src.get(prefix + "attn.proj.bias", {C});
  if (c.layer_scale) w.ls1 = src.get(prefix + "ls1.gamma", {C});
  w.norm2_weight = src.get(prefix + "norm2.weight", {C});
  w.norm2_bias = src.get(prefix + "norm2.bias", {C});
  w.fc1_weight = src.get(prefix + "mlp.fc1.weight", {H, C});
  if (c.ffn_bias) w.fc1_bias = src.get(prefix + "mlp.fc1.bias", {H});
  w.fc2_weight = src.get(prefix + "mlp.fc2.weight", {C, H});
  if (c.ffn_bias) w.fc2_bias = src.get(prefix + "mlp.fc2.bias", {C});
  if (c.layer_scale) w.ls2 = src.get(prefix + "ls2.gamma", {C});
  return w;
}

// The MLP runs over row chunks of this size so its hidden buffer does not grow with the token count.
inline constexpr index_t block_mlp_chunk_rows = 1024;

// Workspace elements block_forward needs for `rows` = batch * tokens rows on a pool of `workers` threads. The attention
// share lets it copy one whole head of K and V per worker (rows bounds the tokens of any batch entry).
inline index_t block_workspace_size(const BlockConfig& c, index_t rows, int workers) {
  const index_t chunk = std::min(rows, block_mlp_chunk_rows);
  return rows * 4 * c.dim + chunk * c.mlp_hidden() + nn::attention_scratch_per_worker(c.head_dim(), rows) * workers;
}

// Gradient pointers mirroring BlockWeights; a null pointer means that parameter's gradient is not wanted.
template <class T>
struct BlockGrads {
  T *norm1_weight = nullptr, *norm1_bias = nullptr;
  T *qkv_weight = nullptr, *qkv_bias = nullptr;
  T *q_norm_weight = nullptr, *q_norm_bias = nullptr, *k_norm_weight = nullptr, *k_norm_bias = nullptr;
  T *proj_weight = nullptr, *proj_bias = nullptr;
  T* ls1 = nullptr;
  T *norm2_weight = nullptr, *norm2_bias = nullptr;
  T *fc1_weight = nullptr, *fc1_bias = nullptr;
  T *fc2_weight = nullptr, *fc2_bias = nullptr;
  T* ls2 = nullptr;
};

// Gradients of weights that live in one flat parameter block, in a gradient block with the same offsets.
template <class T>
BlockGrads<T> block_grads(const BlockWeights<T>& w, const T* params_base, T* grads_base) {
  auto g = [&](const T* p) { return io::rebase_pointer(p, params_base, grads_base); };
  return {g(w.norm1_weight), g(w.norm1_bias), g(w.qkv_weight),   g(w.qkv_bias),     g(w.q_norm_weight),
          g(w.q_norm_bias),  g(w.k_norm_weight), g(w.k_norm_bias), g(w.proj_weight), g(w.proj_bias),
          g(w.ls1),          g(w.norm2_weight), g(w.norm2_bias),  g(w.fc1_weight),   g(w.fc1_bias),
          g(w.fc2_weight),   g(w.fc2_bias),     g(w.ls2)};
}

// What block_backward reads. With `recompute` only x_in is kept and backward reruns the forward from it (bit-identical
// activations, so bit-identical gradients). Buffers keep their capacity across calls.
template <class T>
struct BlockCache {
  using Buffer = std::vector<T, AlignedAllocator<T>>;
  index_t batch = 0, tokens = 0;
  bool recompute = false;
  Buffer x_in;                // [rows, C] block input
  Buffer ln1_mean, ln1_rstd;  // [rows]
  Buffer qkv;                 // [rows, 3C] projection before qk-norm and RoPE
  Buffer attended;            // [rows, C] attention output
  Buffer lse;                 // [batch, heads, tokens] log-sum-exp of the attention rows
  Buffer proj_out;            // [rows, C] attention branch before LayerScale
  Buffer x_mid;               // [rows, C] after the attention residual
  Buffer ln2_mean, ln2_rstd;  // [rows]
  Buffer hidden;              // [rows, H] fc1 output before GELU
  Buffer mlp_out;             // [rows, C] MLP branch before LayerScale

  void resize(const BlockConfig& c, index_t batch_, index_t tokens_, bool recompute_) {
    batch = batch_, tokens = tokens_, recompute = recompute_;
    const auto rows = static_cast<std::size_t>(batch * tokens), C = static_cast<std::size_t>(c.dim);
    x_in.resize(rows * C);
    const std::size_t full = recompute ? 0 : 1;
    ln1_mean.resize(full * rows), ln1_rstd.resize(full * rows), ln2_mean.resize(full * rows), ln2_rstd.resize(full * rows);
    qkv.resize(full * rows * 3 * C);
    attended.resize(full * rows * C), proj_out.resize(full * rows * C), x_mid.resize(full * rows * C);
    mlp_out.resize(full * rows * C);
    lse.resize(full * rows * static_cast<std::size_t>(c.num_heads));
    hidden.resize(full * rows * static_cast<std::size_t>(c.mlp_hidden()));
  }
};

// Elements a BlockCache holds for batch * tokens rows (what block_forward_train keeps alive until backward).
inline index_t block_cache_elements(const BlockConfig& c, index_t rows, bool recompute) {
  const index_t C = c.dim;
  if (recompute) return rows * C;
  return rows * (C + 4 + 3 * C + C + c.num_heads + C + C + c.mlp_hidden() + C);
}

namespace detail {
// Per-(row, head) LayerNorm of the head_dim features at x[r*row_stride + h*head_dim ...], in place: nn's layer norm
// row kernels (same lanes and statistics as nn::layernorm_forward) on this strided layout.
template <class T>
void head_layernorm_inplace(T* x, index_t rows, index_t row_stride, index_t heads, index_t head_dim, const T* gamma,
                            const T* beta, double eps) {
  const simd::Lanes lanes = simd::best_lanes<T>();
  parallel_for(rows, [&](index_t r0, index_t r1, int) {
    simd::with_lanes<T>(lanes, [&](auto* lane_type) {
      using V = std::remove_pointer_t<decltype(lane_type)>;
      for (index_t r = r0; r < r1; ++r)
        for (index_t h = 0; h < heads; ++h) {
          T* v = x + r * row_stride + h * head_dim;
          T mean, rstd;
          nn::detail::layernorm_row<V>(v, v, gamma, beta, head_dim, static_cast<T>(eps), mean, rstd);
        }
    });
  });
}

// Adjoint of head_layernorm_inplace given its input x: adds into d_x (same strides), d_gamma, d_beta (may be null).
// stats: 2 * rows * heads scratch. Statistics are recomputed as in forward, once: the d_x pass keeps them there for the
// d_gamma / d_beta pass, which sums over rows and then heads in a fixed order.
template <class T>
void head_layernorm_backward(T* d_x, T* d_gamma, T* d_beta, const T* d_out, const T* x, index_t rows, index_t row_stride,
                             index_t heads, index_t head_dim, const T* gamma, double eps, T* stats) {
  const simd::Lanes lanes = simd::best_lanes<T>();
  const T e = static_cast<T>(eps);
  T* mean = stats;
  T* rstd = stats + rows * heads;
  parallel_for(rows, [&](index_t r0, index_t r1, int) {
    simd::with_lanes<T>(lanes, [&](auto* lane_type) {
      using V = std::remove_pointer_t<decltype(lane_type)>;
      for (index_t r = r0; r < r1; ++r)
        for (index_t h = 0; h < heads; ++h) {
          const index_t off = r * row_stride + h * head_dim, s = r * heads + h;
          nn::detail::layernorm_row_stats<V>(x + off, head_dim, e, mean[s], rstd[s]);
          nn::detail::layernorm_row_backward<V>(d_x + off, d_out + off, x + off, gamma, head_dim, mean[s], rstd[s]);
        }
    });
  });
  if (!d_gamma && !d_beta) return;
  // A row's heads are contiguous: a [heads, head_dim] block for nn's per-column sums.
  simd::with_lanes<T>(lanes, [&](auto* lane_type) {
    using V = std::remove_pointer_t<decltype(lane_type)>;
    for (index_t r = 0; r < rows; ++r)
      nn::detail::layernorm_columns_backward<V>(d_gamma, d_beta, d_out + r * row_stride, x + r * row_stride, heads,
                                                head_dim, mean + r * heads, rstd + r * heads, 0, head_dim);
  });
}

// x[r, :] += scale[:] * y[r, :] (scale may be null: plain residual).
template <class T>
void add_scaled_residual(T* x, const T* y, const T* scale, index_t rows, index_t dim) {
  parallel_for(rows, [&](index_t r0, index_t r1, int) {
    for (index_t r = r0; r < r1; ++r) {
      T* xr = x + r * dim;
      const T* yr = y + r * dim;
      if (scale)
        for (index_t i = 0; i < dim; ++i) xr[i] += scale[i] * yr[i];
      else
        for (index_t i = 0; i < dim; ++i) xr[i] += yr[i];
    }
  });
}

// Adjoint of add_scaled_residual's branch: d_y = scale * d_x (overwritten), d_scale += sum_r d_x * y (may be null).
template <class T>
void scaled_residual_backward(T* d_y, T* d_scale, const T* d_x, const T* y, const T* scale, index_t rows, index_t dim) {
  parallel_for(rows, [&](index_t r0, index_t r1, int) {
    for (index_t r = r0; r < r1; ++r)
      for (index_t i = 0; i < dim; ++i) d_y[r * dim + i] = scale ? scale[i] * d_x[r * dim + i] : d_x[r * dim + i];
  });
  if (d_scale)
    for (index_t r = 0; r < rows; ++r)
      for (index_t i = 0; i < dim; ++i) d_scale[i] += d_x[r * dim + i] * y[r * dim + i];
}

// Sets columns [col, col + width) of rows x row_stride to zero.
template <class T>
void zero_columns(T* x, index_t rows, index_t row_stride, index_t col, index_t width) {
  parallel_for(rows, [&](index_t r0, index_t r1, int) {
    for (index_t r = r0; r < r1; ++r) std::fill(x + r * row_stride + col, x + r * row_stride + col + width, T(0));
  });
}

template <class T>
void copy_columns(T* dst, const T* src, index_t rows, index_t row_stride, index_t col, index_t width) {
  parallel_for(rows, [&](index_t r0, index_t r1, int) {
    for (index_t r = r0; r < r1; ++r)
      std::copy(src + r * row_stride + col, src + r * row_stride + col + width, dst + r * row_stride + col);
  });
}

inline nn::AttentionLayout block_attention_layout(index_t batch, index_t tokens, const BlockConfig& c) {
  const index_t C = c.dim;
  nn::AttentionLayout L;
  L.batch = batch;
  L.heads = c.num_heads;
  L.n_q = tokens;
  L.n_kv = tokens;
  L.head_dim = c.head_dim();
  L.q = {tokens * 3 * C, L.head_dim, 3 * C};
  L.k = L.q;
  L.v = L.q;
  L.out = {tokens * C, L.head_dim, C};
  return L;
}

// qk-norm then RoPE on the q and k columns of qkv [rows, 3C], in place.
template <class T>
void block_qk_transform(T* qkv, index_t rows, const BlockConfig& c, const BlockWeights<T>& w, const Rope2DTable<T>* rope,
                        const std::int32_t* positions) {
  const index_t C = c.dim, hd = c.head_dim(), heads = c.num_heads;
  if (c.qk_norm) {
    head_layernorm_inplace(qkv, rows, 3 * C, heads, hd, w.q_norm_weight, w.q_norm_bias, c.qk_norm_eps);
    head_layernorm_inplace(qkv + C, rows, 3 * C, heads, hd, w.k_norm_weight, w.k_norm_bias, c.qk_norm_eps);
  }
  if (rope) {
    rope2d_forward(qkv, rows, 3 * C, heads, hd, positions, *rope);
    rope2d_forward(qkv + C, rows, 3 * C, heads, hd, positions, *rope);
  }
}

// One implementation of the block's forward: cache == nullptr is the inference path (activations overwritten in the
// workspace); otherwise every activation backward reads is written into the (already sized) cache.
template <class T>
void block_forward_impl(T* x, index_t batch, index_t tokens, const BlockConfig& c, const BlockWeights<T>& w,
                        const Rope2DTable<T>* rope, const std::int32_t* positions, std::span<T> workspace,
                        BlockCache<T>* cache) {
  const index_t rows = batch * tokens, C = c.dim, H = c.mlp_hidden();
  if (rows == 0) return;
  require(!rope == !positions, "block_forward: RoPE table and positions must be given together");
  const int workers = global_pool().size();
  require(static_cast<index_t>(workspace.size()) >= block_workspace_size(c, rows, workers), "block_forward: workspace has ",
          workspace.size(), " elements, needs ", block_workspace_size(c, rows, workers));
  T* normed = workspace.data();    // [rows, C]: norm1 output, then attention output
  T* qkv = normed + rows * C;      // [rows, 3C]: q|k|v, then projection / fc2 output
  T* hidden = qkv + rows * 3 * C;  // [chunk, H]
  const index_t chunk = std::min(rows, block_mlp_chunk_rows);
  std::span<T> attn_scratch(hidden + chunk * H, workspace.size() - static_cast<std::size_t>(rows * 4 * C + chunk * H));

  if (cache) std::copy(x, x + rows * C, cache->x_in.data());
  nn::LayerNormCache<T> ln1 = cache ? nn::LayerNormCache<T>{cache->ln1_mean.data(), cache->ln1_rstd.data()}
                                    : nn::LayerNormCache<T>{};
  nn::layernorm_forward(normed, x, w.norm1_weight, w.norm1_bias, rows, C, static_cast<T>(c.norm_eps), ln1);
  T* raw = cache ? cache->qkv.data() : qkv;  // the projection as backward needs it; q and k are transformed in qkv
  nn::linear_forward(raw, normed, w.qkv_weight, w.qkv_bias, rows, C, 3 * C);
  if (cache) copy_columns(qkv, raw, rows, 3 * C, 0, 2 * C);
  block_qk_transform(qkv, rows, c, w, rope, positions);
  T* attended = cache ? cache->attended.data() : normed;
  nn::attention_forward<T>(attended, cache ? cache->lse.data() : nullptr, qkv, qkv + C, raw + 2 * C,
                           block_attention_layout(batch, tokens, c), static_cast<T>(1.0 / std::sqrt(double(c.head_dim()))),
                           attn_scratch);
  T* proj = cache ? cache->proj_out.data() : qkv;
  nn::linear_forward(proj, attended, w.proj_weight, w.proj_bias, rows, C, C);
  add_scaled_residual(x, proj, w.ls1, rows, C);
  if (cache) std::copy(x, x + rows * C, cache->x_mid.data());

  for (index_t r0 = 0; r0 < rows; r0 += chunk) {
    const index_t n = std::min(chunk, rows - r0);
    nn::LayerNormCache<T> ln2 = cache ? nn::LayerNormCache<T>{cache->ln2_mean.data() + r0, cache->ln2_rstd.data() + r0}
                                      : nn::LayerNormCache<T>{};
    nn::layernorm_forward(normed, x + r0 * C, w.norm2_weight, w.norm2_bias, n, C, static_cast<T>(c.norm_eps), ln2);
    T* pre = cache ? cache->hidden.data() + r0 * H : hidden;
    nn::linear_forward(pre, normed, w.fc1_weight, w.fc1_bias, n, C, H);
    nn::gelu_forward(hidden, pre, n * H);
    T* mlp = cache ? cache->mlp_out.data() + r0 * C : qkv;
    nn::linear_forward(mlp, hidden, w.fc2_weight, w.fc2_bias, n, H, C);
    add_scaled_residual(x + r0 * C, mlp, w.ls2, n, C);
  }
}
}  // namespace detail

// x [batch * tokens, dim] is updated in place. rope and positions ([batch * tokens, 2] as (y, x)) may both be null;
// attention runs within each batch entry over its `tokens` rows.
template <class T>
void block_forward(T* x, index_t batch, index_t tokens, const BlockConfig& c, const BlockWeights<T>& w,
                   const Rope2DTable<T>* rope, const std::int32_t* positions, std::span<T> workspace) {
  detail::block_forward_impl<T>(x, batch, tokens, c, w, rope, positions, workspace, nullptr);
}

// block_forward that also fills `cache` for block_backward (only the input when `recompute`). Same outputs bit for
// bit; workspace as block_forward's.
template <class T>
void block_forward_train(T* x, index_t batch, index_t tokens, const BlockConfig& c, const BlockWeights<T>& w,
                         const Rope2DTable<T>* rope, const std::int32_t* positions, BlockCache<T>& cache,
                         bool recompute, std::span<T> workspace) {
  cache.resize(c, batch, tokens, recompute);
  if (recompute) {
    std::copy(x, x + batch * tokens * c.dim, cache.x_in.data());
    detail::block_forward_impl<T>(x, batch, tokens, c, w, rope, positions, workspace, nullptr);
  } else {
    detail::block_forward_impl<T>(x, batch, tokens, c, w, rope, positions, workspace, &cache);
  }
}

// Backward temporaries (and, for recompute caches, the rerun forward's activations); one instance serves every block.
template <class T>
struct BlockBackwardScratch {
  std::vector<T, AlignedAllocator<T>> buffer, forward_workspace, x;
  BlockCache<T> recomputed;
};

// Temporary elements block_backward needs besides a recompute cache, for batch * tokens rows.
inline index_t block_backward_scratch_size(const BlockConfig& c, index_t batch, index_t tokens, int workers) {
  const index_t rows = batch * tokens, C = c.dim, H = c.mlp_hidden(), chunk = std::min(rows, block_mlp_chunk_rows);
  return std::max(11 * rows * C, chunk * (3 * C + 3 * H)) +
         nn::attention_scratch_per_worker(c.head_dim(), tokens) * workers;
}

// d_x [batch * tokens, dim]: on entry dL/d(block output), on return dL/d(block input). Parameter gradients are added
// (+=) into g (null entries skipped). rope / positions as given to block_forward_train.
template <class T>
void block_backward(T* d_x, const BlockGrads<T>& g, BlockCache<T>& cache, const BlockConfig& c, const BlockWeights<T>& w,
                    const Rope2DTable<T>* rope, const std::int32_t* positions, BlockBackwardScratch<T>& scratch) {
  using namespace detail;
  const index_t batch = cache.batch, tokens = cache.tokens, rows = batch * tokens, C = c.dim, H = c.mlp_hidden();
  if (rows == 0) return;
  require(static_cast<index_t>(cache.x_in.size()) == rows * C, "block_backward: cache holds ", cache.x_in.size(),
          " input elements, expected ", rows * C, " (was block_forward_train run with this config?)");
  require(!rope == !positions, "block_backward: RoPE table and positions must be given together");
  BlockCache<T>* a = &cache;
  if (cache.recompute) {
    const int workers = global_pool().size();
    scratch.forward_workspace.resize(static_cast<std::size_t>(block_workspace_size(c, rows, workers)));
    scratch.x.assign(cache.x_in.begin(), cache.x_in.end());
    scratch.recomputed.resize(c, batch, tokens, false);
    block_forward_impl<T>(scratch.x.data(), batch, tokens, c, w, rope, positions,
                          std::span<T>(scratch.forward_workspace.data(), scratch.forward_workspace.size()),
                          &scratch.recomputed);
    a = &scratch.recomputed;
  }
  const int workers = global_pool().size();
  scratch.buffer.resize(static_cast<std::size_t>(block_backward_scratch_size(c, batch, tokens, workers)));
  T* base = scratch.buffer.data();
  const index_t chunk = std::min(rows, block_mlp_chunk_rows);
  const index_t shared = std::max(11 * rows * C, chunk * (3 * C + 3 * H));
  std::span<T> attn_scratch(base + shared, scratch.buffer.size() - static_cast<std::size_t>(shared));

  // MLP branch, in row chunks: x_out = x_mid + ls2 * fc2(gelu(fc1(norm2(x_mid)))).
  {
    T* d_mlp = base;              // [chunk, C]
    T* normed = d_mlp + chunk * C;  // [chunk, C]
    T* d_normed = normed + chunk * C;
    T* act = d_normed + chunk * C;  // [chunk, H]
    T* d_act = act + chunk * H;
    T* d_pre = d_act + chunk * H;
    for (index_t r0 = 0; r0 < rows; r0 += chunk) {
      const index_t n = std::min(chunk, rows - r0);
      T* dx = d_x + r0 * C;
      const T* pre = a->hidden.data() + r0 * H;
      const T* x_mid = a->x_mid.data() + r0 * C;
      scaled_residual_backward(d_mlp, g.ls2, dx, a->mlp_out.data() + r0 * C, w.ls2, n, C);
      nn::gelu_forward(act, pre, n * H);
      std::fill(d_act, d_act + n * H, T(0));
      nn::linear_backward(d_act, g.fc2_weight, g.fc2_bias, d_mlp, act, w.fc2_weight, n, H, C);
      std::fill(d_pre, d_pre + n * H, T(0));
      nn::gelu_backward(d_pre, d_act, pre, n * H);
      nn::layernorm_forward(normed, x_mid, w.norm2_weight, w.norm2_bias, n, C, static_cast<T>(c.norm_eps));
      std::fill(d_normed, d_normed + n * C, T(0));
      nn::linear_backward(d_normed, g.fc1_weight, g.fc1_bias, d_pre, normed, w.fc1_weight, n, C, H);
      nn::layernorm_backward(dx, g.norm2_weight, g.norm2_bias, d_normed, x_mid, w.norm2_weight, n, C,
                             nn::LayerNormCache<T>{a->ln2_mean.data() + r0, a->ln2_rstd.data() + r0});
    }
  }

  // Attention branch: x_mid = x_in + ls1 * proj(attention(rope(qk_norm(qkv(norm1(x_in)))))).
  T* d_proj = base;             // [rows, C], then norm1 output
  T* d_att = d_proj + rows * C;  // [rows, C], then d(norm1 output)
  T* qk = d_att + rows * C;      // [rows, 3C] q and k as attention saw them
  T* dA = qk + rows * 3 * C;     // [rows, 3C]
  T* dB = dA + rows * 3 * C;     // [rows, 3C]
  scaled_residual_backward(d_proj, g.ls1, d_x, a->proj_out.data(), w.ls1, rows, C);
  std::fill(d_att, d_att + rows * C, T(0));
  nn::linear_backward(d_att, g.proj_weight, g.proj_bias, d_proj, a->attended.data(), w.proj_weight, rows, C, C);

  const T* raw = a->qkv.data();
  copy_columns(qk, raw, rows, 3 * C, 0, 2 * C);
  block_qk_transform(qk, rows, c, w, rope, positions);
  std::fill(dA, dA + rows * 3 * C, T(0));
  nn::attention_backward<T>(dA, dA + C, dA + 2 * C, d_att, a->attended.data(), a->lse.data(), qk, qk + C, raw + 2 * C,
                            block_attention_layout(batch, tokens, c),
                            static_cast<T>(1.0 / std::sqrt(double(c.head_dim()))), attn_scratch);
  const index_t hd = c.head_dim(), heads = c.num_heads;
  T *cur = dA, *other = dB;
  if (rope) {
    zero_columns(other, rows, 3 * C, 0, 2 * C);
    rope2d_backward(other, cur, rows, 3 * C, heads, hd, positions, *rope);
    rope2d_backward(other + C, cur + C, rows, 3 * C, heads, hd, positions, *rope);
    std::swap(cur, other);
  }
  if (c.qk_norm) {
    T* stats = qk;  // attention_backward was qk's last reader; 3 * rows * C >= 2 * rows * heads
    zero_columns(other, rows, 3 * C, 0, 2 * C);
    head_layernorm_backward(other, g.q_norm_weight, g.q_norm_bias, cur, raw, rows, 3 * C, heads, hd, w.q_norm_weight,
                            c.qk_norm_eps, stats);
    head_layernorm_backward(other + C, g.k_norm_weight, g.k_norm_bias, cur + C, raw + C, rows, 3 * C, heads, hd,
                            w.k_norm_weight, c.qk_norm_eps, stats);
    std::swap(cur, other);
  }
  if (cur != dA) copy_columns(dA, cur, rows, 3 * C, 0, 2 * C);

  T* normed = d_proj;
  T* d_normed = d_att;
  nn::layernorm_forward(normed, a->x_in.data(), w.norm1_weight, w.norm1_bias, rows, C, static_cast<T>(c.norm_eps));
  std::fill(d_normed, d_normed + rows * C, T(0));
  nn::linear_backward(d_normed, g.qkv_weight, g.qkv_bias, dA, normed, w.qkv_weight, rows, C, 3 * C);
  nn::layernorm_backward(d_x, g.norm1_weight, g.norm1_bias, d_normed, a->x_in.data(), w.norm1_weight, rows, C,
                         nn::LayerNormCache<T>{a->ln1_mean.data(), a->ln1_rstd.data()});
}

// Convenience owner of a block's workspace for callers that run one block at a time.
template <class T>
struct BlockWorkspace {
  std::vector<T, AlignedAllocator<T>> buffer;
  std::span<T> get(const BlockConfig& c, index_t rows) {
    const auto need = static_cast<std::size_t>(block_workspace_size(c, rows, global_pool().size()));
    if (buffer.size() < need) buffer.resize(need);
    return {buffer.data(), buffer.size()};
  }
};

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
