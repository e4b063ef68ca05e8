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

#include "flexsplat/decoder/init.hpp"
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
  std::vector<index_t> order;  // local: position in the Morton order -> query index
  std::vector<T> qkv;          // [N, 3 dim], in attention order
  std::vector<T> attended;     // [N, dim], in attention order
  std::vector<T> attended_query_order;  // [N, dim], input of the output projection
  std::vector<T> lse;          // [heads * N] (per window block)
  std::vector<T> scratch;
};

// Morton order of points quantised to a 2^10 grid over their bounding box; ties keep the index order.
template <class T>
void morton_order(std::vector<index_t>& order, const T* centres, index_t n) {
  double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
  for (index_t i = 0; i < n; ++i)
    for (int j = 0; j < 3; ++j) {
      const double x = static_cast<double>(centres[3 * i + j]);
      if (!std::isfinite(x)) continue;
      lo[j] = std::min(lo[j], x);
      hi[j] = std::max(hi[j], x);
    }
  std::vector<std::uint32_t> code(static_cast<std::size_t>(n));
  for (index_t i = 0; i < n; ++i) {
    std::uint32_t c = 0;
    std::uint32_t cell[3];
    for (int j = 0; j < 3; ++j) {
      const double x = static_cast<double>(centres[3 * i + j]);
      const double extent = hi[j] - lo[j];
      const double t = std::isfinite(x) && extent > 0 ? (x - lo[j]) / extent : 0.0;
      cell[j] = static_cast<std::uint32_t>(std::clamp(t, 0.0, 1.0) * 1023.0);
    }
    for (int bit = 9; bit >= 0; --bit)
      for (int j = 0; j < 3; ++j) c = (c << 1) | ((cell[j] >> bit) & 1u);
    code[i] = c;
  }
  order.resize(static_cast<std::size_t>(n));
  std::iota(order.begin(), order.end(), index_t{0});
  std::stable_sort(order.begin(), order.end(), [&](index_t a, index_t b) { return code[a] < code[b]; });
}

namespace detail {
// Runs fn(first_query, count) over the attention blocks: the whole set, or full windows plus a shorter last one.
template <class Fn>
void for_each_window(index_t n, const SelfAttentionConfig& c, Fn&& fn) {
  if (!c.local) {
    fn(index_t{0}, n, index_t{1});
    return;
  }
  const index_t full = n / c.window;
  if (full > 0) fn(index_t{0}, c.window, full);
  if (n % c.window) fn(full * c.window, n % c.window, index_t{1});
}

inline nn::AttentionLayout window_layout(index_t count, index_t windows, const SelfAttentionConfig& c) {
  nn::AttentionLayout L;
  L.batch = windows;
  L.heads = c.heads;
  L.n_q = L.n_kv = count;
  L.head_dim = c.dim / c.heads;
  L.q = L.k = L.v = {count * 3 * c.dim, L.head_dim, 3 * c.dim};
  L.out = {count * c.dim, L.head_dim, c.dim};
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
  cache.n = n;
  cache.qkv.resize(static_cast<std::size_t>(n * 3 * c.dim));
  nn::linear_forward(cache.qkv.data(), x, params + P.qkv_w, params + P.qkv_b, n, c.dim, 3 * c.dim);
  if (c.local) {
    morton_order(cache.order, centres, n);
    std::vector<T> sorted(cache.qkv.size());
    for (index_t i = 0; i < n; ++i)
      std::copy_n(cache.qkv.data() + cache.order[i] * 3 * c.dim, 3 * c.dim, sorted.data() + i * 3 * c.dim);
    cache.qkv.swap(sorted);
  }
  cache.attended.resize(static_cast<std::size_t>(n * c.dim));
  cache.lse.resize(static_cast<std::size_t>(n * c.heads));
  cache.scratch.resize(static_cast<std::size_t>(nn::attention_scratch_per_worker(c.dim / c.heads) * global_pool().size()));
  const T scale = T(1) / std::sqrt(static_cast<T>(c.dim / c.heads));
  detail::for_each_window(n, c, [&](index_t first, index_t count, index_t windows) {
    const T* qkv = cache.qkv.data() + first * 3 * c.dim;
    nn::attention_forward(cache.attended.data() + first * c.dim, cache.lse.data() + first * c.heads, qkv, qkv + c.dim,
                          qkv + 2 * c.dim, detail::window_layout(count, windows, c), scale, std::span<T>(cache.scratch));
  });
  const T* projected_in = cache.attended.data();
  if (c.local) {
    cache.attended_query_order.resize(cache.attended.size());
    for (index_t i = 0; i < n; ++i)
      std::copy_n(cache.attended.data() + i * c.dim, c.dim, cache.attended_query_order.data() + cache.order[i] * c.dim);
    projected_in = cache.attended_query_order.data();
  }
  nn::linear_forward(out, projected_in, params + P.out_w, params + P.out_b, n, c.dim, c.dim);
}

// Adds into d_x and d_params.
template <class T>
void self_attention_backward(T* d_x, T* d_params, const T* d_out, SelfAttentionCache<T>& cache, const T* x,
                             const T* params, const SelfAttentionConfig& c) {
  const SelfAttentionParamLayout P(c);
  const index_t n = cache.n;
  std::vector<T> d_att(static_cast<std::size_t>(n * c.dim), T(0));
  const T* projected_in = c.local ? cache.attended_query_order.data() : cache.attended.data();
  nn::linear_backward(d_att.data(), d_params + P.out_w, d_params + P.out_b, d_out, projected_in, params + P.out_w, n,
                      c.dim, c.dim);
  if (c.local) {
    std::vector<T> sorted(d_att.size());
    for (index_t i = 0; i < n; ++i) std::copy_n(d_att.data() + cache.order[i] * c.dim, c.dim, sorted.data() + i * c.dim);
    d_att.swap(sorted);
  }
  std::vector<T> d_qkv(static_cast<std::size_t>(n * 3 * c.dim), T(0));
  const T scale = T(1) / std::sqrt(static_cast<T>(c.dim / c.heads));
  detail::for_each_window(n, c, [&](index_t first, index_t count, index_t windows) {
    const T* qkv = cache.qkv.data() + first * 3 * c.dim;
    T* dq = d_qkv.data() + first * 3 * c.dim;
    nn::attention_backward(dq, dq + c.dim, dq + 2 * c.dim, d_att.data() + first * c.dim, cache.attended.data() + first * c.dim,
                           cache.lse.data() + first * c.heads, qkv, qkv + c.dim, qkv + 2 * c.dim,
                           detail::window_layout(count, windows, c), scale, std::span<T>(cache.scratch));
  });
  if (c.local) {
    std::vector<T> unsorted(d_qkv.size());
    for (index_t i = 0; i < n; ++i)
      std::copy_n(d_qkv.data() + i * 3 * c.dim, 3 * c.dim, unsorted.data() + cache.order[i] * 3 * c.dim);
    d_qkv.swap(unsorted);
  }
  nn::linear_backward(d_x, d_params + P.qkv_w, d_params + P.qkv_b, d_qkv.data(), x, params + P.qkv_w, n, c.dim, 3 * c.dim);
}

}  // namespace decoder
}  // namespace v0
}  // namespace flexsplat
