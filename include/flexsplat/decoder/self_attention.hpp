#pragma once
// Self-attention over the Gaussian queries: packed QKV projection, multi-head attention with the tiled online softmax
// of nn::attention (the N x N score matrix never exists), output projection. The local variant orders the queries
// along a Morton curve of their current centres and lets each query attend only within its window of consecutive
// queries in that order: a spatial neighbourhood, at a cost linear in N.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <numeric>
#include <random>
#include <vector>

#include "flexsplat/core/tensor.hpp"
#include "flexsplat/decoder/init.hpp"
#include "flexsplat/decoder/kernels.hpp"
#include "flexsplat/decoder/morton.hpp"
#include "flexsplat/nn/attention.hpp"
#include "flexsplat/nn/linear.hpp"

namespace flexsplat {
inline namespace v0 {
namespace decoder {

struct SelfAttentionConfig {
  index_t dim = 256;
  index_t heads = 8;
  bool local = false;
  index_t window = 512;  // queries per neighbourhood in the local variant
};

struct SelfAttentionParamLayout {
  index_t qkv_w, qkv_b, out_w, out_b, size;
  explicit SelfAttentionParamLayout(const SelfAttentionConfig& c) {
    qkv_w = 0;
    qkv_b = qkv_w + 3 * c.dim * c.dim;
    out_w = qkv_b + 3 * c.dim;
    out_b = out_w + c.dim * c.dim;
    size = out_b + c.dim;
  }
};

// Xavier-uniform projections (the QKV block as three dim x dim matrices), zero biases.
template <class T>
void self_attention_init(T* params, const SelfAttentionConfig& c, std::mt19937_64& rng) {
  const SelfAttentionParamLayout L(c);
  std::fill(params, params + L.size, T(0));
  for (int k = 0; k < 3; ++k) xavier_uniform(params + L.qkv_w + k * c.dim * c.dim, c.dim, c.dim, rng);
  xavier_uniform(params + L.out_w, c.dim, c.dim, rng);
}

template <class T>
struct SelfAttentionCache {
  index_t n = 0;
  std::vector<index_t> order;           // local: position in the Morton order -> query index
  std::vector<MortonKey> morton_keys, morton_scratch;  // local: radix-sort items
  AlignedVector<T> x_sorted;              // local: [N, dim] input rows in attention order
  AlignedVector<T> qkv;                   // [N, 3 dim], in attention order
  AlignedVector<T> attended;              // [N, dim], in attention order
  AlignedVector<T> attended_query_order;  // local: [N, dim], input of the output projection
  AlignedVector<T> lse;                   // [heads * N]
  AlignedVector<T> scratch;               // per-worker attention tiles
  // Sizes every buffer for n queries; never shrinks capacity, so a reserved cache does not allocate again.
  void resize(index_t n_queries, const SelfAttentionConfig& c, int workers) {
    n = n_queries;
    const auto z = static_cast<std::size_t>(n_queries);
    const auto d = static_cast<std::size_t>(c.dim);
    qkv.resize(z * 3 * d);
    attended.resize(z * d);
    lse.resize(z * static_cast<std::size_t>(c.heads));
    if (c.local) {
      order.resize(z), morton_keys.resize(z), morton_scratch.resize(z);
      x_sorted.resize(z * d);
      attended_query_order.resize(z * d);
      const kernels::WindowAttentionShape s{n_queries, c.window, c.heads, c.dim / c.heads};
      scratch.resize(static_cast<std::size_t>(kernels::window_attention_scratch_per_worker(s) * workers));
    } else {
      scratch.resize(static_cast<std::size_t>(nn::attention_scratch_per_worker(c.dim / c.heads, n_queries) * workers));
    }
  }
  std::size_t capacity_bytes() const {
    return order.capacity() * sizeof(index_t) + (morton_keys.capacity() + morton_scratch.capacity()) * sizeof(MortonKey) +
           (x_sorted.capacity() + qkv.capacity() + attended.capacity() + attended_query_order.capacity() + lse.capacity() +
            scratch.capacity()) * sizeof(T);
  }
};

// Backward temporaries; one instance can serve every layer.
template <class T>
struct SelfAttentionGradScratch {
  AlignedVector<T> d_att_query_order, d_att, d_qkv, d_x_sorted;
  void resize(index_t n, const SelfAttentionConfig& c) {
    const auto z = static_cast<std::size_t>(n), d = static_cast<std::size_t>(c.dim);
    d_att_query_order.resize(z * d);
    d_att.resize(c.local ? z * d : 0);
    d_qkv.resize(z * 3 * d);
    d_x_sorted.resize(c.local ? z * d : 0);
  }
  std::size_t capacity_bytes() const {
    return (d_att_query_order.capacity() + d_att.capacity() + d_qkv.capacity() + d_x_sorted.capacity()) * sizeof(T);
  }
};

namespace detail {
inline nn::AttentionLayout full_attention_layout(index_t n, const SelfAttentionConfig& c) {
  nn::AttentionLayout L;
  L.batch = 1;
  L.heads = c.heads;
  L.n_q = L.n_kv = n;
  L.head_dim = c.dim / c.heads;
  L.q = L.k = L.v = {n * 3 * c.dim, L.head_dim, 3 * c.dim};
  L.out = {n * c.dim, L.head_dim, c.dim};
  return L;
}
}  // namespace detail

// out [N, dim]. centres [N, 3] are only read by the local variant (to find neighbourhoods).
template <class T>
void self_attention_forward(T* out, SelfAttentionCache<T>& cache, const T* x, const T* centres, index_t n,
                            const T* params, const SelfAttentionConfig& c) {
  require(c.dim % c.heads == 0, "self-attention: dim ", c.dim, " is not divisible by ", c.heads, " heads");
  require(!c.local || c.window >= 1, "self-attention: local window must be positive, got ", c.window);
  const SelfAttentionParamLayout P(c);
  cache.resize(n, c, global_pool().size());
  const T scale = T(1) / std::sqrt(static_cast<T>(c.dim / c.heads));
  if (!c.local) {
    nn::linear_forward(cache.qkv.data(), x, params + P.qkv_w, params + P.qkv_b, n, c.dim, 3 * c.dim);
    const T* qkv = cache.qkv.data();
    nn::attention_forward(cache.attended.data(), cache.lse.data(), qkv, qkv + c.dim, qkv + 2 * c.dim,
                          detail::full_attention_layout(n, c), scale, std::span<T>(cache.scratch));
    nn::linear_forward(out, cache.attended.data(), params + P.out_w, params + P.out_b, n, c.dim, c.dim);
    return;
  }
  morton_order(cache.order.data(), centres, n, cache.morton_keys.data(), cache.morton_scratch.data());
  parallel_for(n, [&](index_t i0, index_t i1, int) {
    for (index_t i = i0; i < i1; ++i) std::copy_n(x + cache.order[i] * c.dim, c.dim, cache.x_sorted.data() + i * c.dim);
  });
  nn::linear_forward(cache.qkv.data(), cache.x_sorted.data(), params + P.qkv_w, params + P.qkv_b, n, c.dim, 3 * c.dim);
  const kernels::WindowAttentionShape s{n, c.window, c.heads, c.dim / c.heads};
  kernels::window_attention_forward(cache.attended.data(), cache.lse.data(), cache.qkv.data(), s, scale,
                                    std::span<T>(cache.scratch));
  parallel_for(n, [&](index_t i0, index_t i1, int) {
    for (index_t i = i0; i < i1; ++i)
      std::copy_n(cache.attended.data() + i * c.dim, c.dim, cache.attended_query_order.data() + cache.order[i] * c.dim);
  });
  nn::linear_forward(out, cache.attended_query_order.data(), params + P.out_w, params + P.out_b, n, c.dim, c.dim);
}

// Adds into d_x and d_params; temporaries live in g (sized here, reused across calls).
template <class T>
void self_attention_backward(T* d_x, T* d_params, const T* d_out, SelfAttentionCache<T>& cache, const T* x,
                             const T* params, const SelfAttentionConfig& c, SelfAttentionGradScratch<T>& g) {
  const SelfAttentionParamLayout P(c);
  const index_t n = cache.n;
  g.resize(n, c);
  std::fill(g.d_att_query_order.begin(), g.d_att_query_order.end(), T(0));
  std::fill(g.d_qkv.begin(), g.d_qkv.end(), T(0));
  const T scale = T(1) / std::sqrt(static_cast<T>(c.dim / c.heads));
  if (!c.local) {
    nn::linear_backward(g.d_att_query_order.data(), d_params + P.out_w, d_params + P.out_b, d_out, cache.attended.data(),
                        params + P.out_w, n, c.dim, c.dim);
    T* dq = g.d_qkv.data();
    const T* qkv = cache.qkv.data();
    nn::attention_backward(dq, dq + c.dim, dq + 2 * c.dim, g.d_att_query_order.data(), cache.attended.data(),
                           cache.lse.data(), qkv, qkv + c.dim, qkv + 2 * c.dim, detail::full_attention_layout(n, c), scale,
                           std::span<T>(cache.scratch));
    nn::linear_backward(d_x, d_params + P.qkv_w, d_params + P.qkv_b, g.d_qkv.data(), x, params + P.qkv_w, n, c.dim,
                        3 * c.dim);
    return;
  }
  nn::linear_backward(g.d_att_query_order.data(), d_params + P.out_w, d_params + P.out_b, d_out,
                      cache.attended_query_order.data(), params + P.out_w, n, c.dim, c.dim);
  parallel_for(n, [&](index_t i0, index_t i1, int) {
    for (index_t i = i0; i < i1; ++i)
      std::copy_n(g.d_att_query_order.data() + cache.order[i] * c.dim, c.dim, g.d_att.data() + i * c.dim);
  });
  const kernels::WindowAttentionShape s{n, c.window, c.heads, c.dim / c.heads};
  kernels::window_attention_backward(g.d_qkv.data(), g.d_att.data(), cache.attended.data(), cache.lse.data(),
                                     cache.qkv.data(), s, scale, std::span<T>(cache.scratch));
  std::fill(g.d_x_sorted.begin(), g.d_x_sorted.end(), T(0));
  nn::linear_backward(g.d_x_sorted.data(), d_params + P.qkv_w, d_params + P.qkv_b, g.d_qkv.data(), cache.x_sorted.data(),
                      params + P.qkv_w, n, c.dim, 3 * c.dim);
  parallel_for(n, [&](index_t i0, index_t i1, int) {
    for (index_t i = i0; i < i1; ++i) {
      T* dst = d_x + cache.order[i] * c.dim;
      const T* src = g.d_x_sorted.data() + i * c.dim;
      for (index_t k = 0; k < c.dim; ++k) dst[k] += src[k];
    }
  });
}

// Convenience form with its own (allocated) temporaries.
template <class T>
void self_attention_backward(T* d_x, T* d_params, const T* d_out, SelfAttentionCache<T>& cache, const T* x,
                             const T* params, const SelfAttentionConfig& c) {
  SelfAttentionGradScratch<T> g;
  self_attention_backward(d_x, d_params, d_out, cache, x, params, c, g);
}

}  // namespace decoder
}  // namespace v0
}  // namespace flexsplat
