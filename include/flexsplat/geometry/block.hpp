#pragma once
// The transformer block shared by DINOv2, VGGT's aggregator and its camera-head trunk:
//   x += ls1 * proj(attention(qk_norm(qkv(norm1(x))), rope))
//   x += ls2 * fc2(gelu(fc1(norm2(x))))
// Forward only (inference); x is updated in place, rows are [batch * tokens, dim].
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/geometry/param_source.hpp"
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
inline void append_block_specs(std::vector<TensorSpec>& out, const std::string& prefix, const BlockConfig& c) {
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
BlockWeights<T> load_block_weights(ParamSource<T>& src, const std::string& prefix, const BlockConfig& c) {
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

namespace detail {
// Per-(row, head) LayerNorm of the head_dim features at x[r*row_stride + h*head_dim ...], in place.
template <class T>
void head_layernorm_inplace(T* x, index_t rows, index_t row_stride, index_t heads, index_t head_dim, const T* gamma,
                            const T* beta, double eps) {
  parallel_for(rows, [&](index_t r0, index_t r1, int) {
    for (index_t r = r0; r < r1; ++r)
      for (index_t h = 0; h < heads; ++h) {
        T* v = x + r * row_stride + h * head_dim;
        double sum = 0.0;
        for (index_t i = 0; i < head_dim; ++i) sum += v[i];
        const double mean = sum / static_cast<double>(head_dim);
        double sq = 0.0;
        for (index_t i = 0; i < head_dim; ++i) sq += (v[i] - mean) * (v[i] - mean);
        const T rstd = static_cast<T>(1.0 / std::sqrt(sq / static_cast<double>(head_dim) + eps));
        const T m = static_cast<T>(mean);
        for (index_t i = 0; i < head_dim; ++i) v[i] = (v[i] - m) * rstd * gamma[i] + beta[i];
      }
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

template <class T>
void gelu_parallel(T* x, index_t n) {
  parallel_for((n + 4095) / 4096, [&](index_t c0, index_t c1, int) {
    const index_t b = c0 * 4096, e = std::min(n, c1 * 4096);
    nn::gelu_forward(x + b, x + b, e - b);
  });
}
}  // namespace detail

// x [batch * tokens, dim] is updated in place. rope and positions ([batch * tokens, 2] as (y, x)) may both be null;
// attention runs within each batch entry over its `tokens` rows.
template <class T>
void block_forward(T* x, index_t batch, index_t tokens, const BlockConfig& c, const BlockWeights<T>& w,
                   const Rope2DTable<T>* rope, const std::int32_t* positions, std::span<T> workspace) {
  const index_t rows = batch * tokens, C = c.dim, H = c.mlp_hidden(), hd = c.head_dim(), heads = c.num_heads;
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

  nn::layernorm_forward(normed, x, w.norm1_weight, w.norm1_bias, rows, C, static_cast<T>(c.norm_eps));
  nn::linear_forward(qkv, normed, w.qkv_weight, w.qkv_bias, rows, C, 3 * C);
  if (c.qk_norm) {
    detail::head_layernorm_inplace(qkv, rows, 3 * C, heads, hd, w.q_norm_weight, w.q_norm_bias, c.qk_norm_eps);
    detail::head_layernorm_inplace(qkv + C, rows, 3 * C, heads, hd, w.k_norm_weight, w.k_norm_bias, c.qk_norm_eps);
  }
  if (rope) {
    rope2d_forward(qkv, rows, 3 * C, heads, hd, positions, *rope);
    rope2d_forward(qkv + C, rows, 3 * C, heads, hd, positions, *rope);
  }
  nn::AttentionLayout L;
  L.batch = batch;
  L.heads = heads;
  L.n_q = tokens;
  L.n_kv = tokens;
  L.head_dim = hd;
  L.q = {tokens * 3 * C, hd, 3 * C};
  L.k = L.q;
  L.v = L.q;
  L.out = {tokens * C, hd, C};
  nn::attention_forward<T>(normed, nullptr, qkv, qkv + C, qkv + 2 * C, L, static_cast<T>(1.0 / std::sqrt(double(hd))),
                           attn_scratch);
  nn::linear_forward(qkv, normed, w.proj_weight, w.proj_bias, rows, C, C);
  detail::add_scaled_residual(x, qkv, w.ls1, rows, C);

  for (index_t r0 = 0; r0 < rows; r0 += chunk) {
    const index_t n = std::min(chunk, rows - r0);
    nn::layernorm_forward(normed, x + r0 * C, w.norm2_weight, w.norm2_bias, n, C, static_cast<T>(c.norm_eps));
    nn::linear_forward(hidden, normed, w.fc1_weight, w.fc1_bias, n, C, H);
    detail::gelu_parallel(hidden, n * H);
    nn::linear_forward(qkv, hidden, w.fc2_weight, w.fc2_bias, n, H, C);
    detail::add_scaled_residual(x + r0 * C, qkv, w.ls2, n, C);
  }
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
