#pragma once
// Element-wise activations as forward/backward pairs on raw arrays; backward adds into d_in.
#include <algorithm>
#include <cmath>
#include <type_traits>

#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/simd.hpp"
#include "flexsplat/core/simd_dispatch.hpp"  // its lane overloads must be visible where the lane templates are used
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {
namespace nn {

// Exact GELU (erf form, PyTorch's default). The lane bodies serve every path: V = T is the scalar reference
// (std::erf), simd::batch<T> the build's batches, the dispatch vectors AVX2 / AVX-512 lanes in a portable build.
namespace detail {
inline constexpr double gelu_inv_sqrt2 = 0.70710678118654752440, gelu_inv_sqrt_2pi = 0.39894228040143267794;

template <class V, class T>
void gelu_forward_lanes(T* out, const T* in, index_t n) {
  constexpr T k = T(gelu_inv_sqrt2);
  constexpr index_t w = static_cast<index_t>(simd::lane_count<V>::value);
  index_t i = 0;
  if constexpr (w > 1) {
    const V half(T(0.5)), one(T(1)), kv(k);
    for (; i + w <= n; i += w) {
      const V x = simd::lane_load<V>(in + i);
      simd::lane_store(out + i, half * x * (one + simd::lane_erf(x * kv)));
    }
  }
  for (; i < n; ++i) out[i] = T(0.5) * in[i] * (T(1) + std::erf(in[i] * k));
}

// d_in += d_out * (Phi(x) + x phi(x)).
template <class V, class T>
void gelu_backward_lanes(T* d_in, const T* d_out, const T* in, index_t n) {
  constexpr T k = T(gelu_inv_sqrt2), c = T(gelu_inv_sqrt_2pi);
  constexpr index_t w = static_cast<index_t>(simd::lane_count<V>::value);
  index_t i = 0;
  if constexpr (w > 1) {
    const V half(T(0.5)), one(T(1)), kv(k), cv(c), minus_half(T(-0.5));
    for (; i + w <= n; i += w) {
      const V x = simd::lane_load<V>(in + i);
      const V cdf = half * (one + simd::lane_erf(x * kv));
      const V pdf = cv * simd::lane_exp(minus_half * x * x);
      simd::lane_store(d_in + i, simd::lane_load<V>(d_in + i) + simd::lane_load<V>(d_out + i) * (cdf + x * pdf));
    }
  }
  for (; i < n; ++i) {
    const T x = in[i];
    const T cdf = T(0.5) * (T(1) + std::erf(x * k));
    const T pdf = c * std::exp(T(-0.5) * x * x);
    d_in[i] += d_out[i] * (cdf + x * pdf);
  }
}
}  // namespace detail

inline constexpr index_t elementwise_chunk = 4096;

// out may alias in. Inside another parallel region it runs serially on the calling thread. `lanes` selects the
// path (tests run each); gelu_forward / gelu_backward take the widest (simd::best_lanes).
template <class T>
void gelu_forward_impl(T* out, const T* in, index_t n, simd::Lanes lanes, ThreadPool& pool = global_pool()) {
  parallel_for((n + elementwise_chunk - 1) / elementwise_chunk, [&](index_t b0, index_t b1, int) {
    const index_t i0 = b0 * elementwise_chunk, i1 = std::min(n, b1 * elementwise_chunk);
    simd::with_lanes<T>(lanes, [&](auto* lane_type) {
      detail::gelu_forward_lanes<std::remove_pointer_t<decltype(lane_type)>>(out + i0, in + i0, i1 - i0);
    });
  }, pool);
}

template <class T>
void gelu_backward_impl(T* d_in, const T* d_out, const T* in, index_t n, simd::Lanes lanes,
                        ThreadPool& pool = global_pool()) {
  parallel_for((n + elementwise_chunk - 1) / elementwise_chunk, [&](index_t b0, index_t b1, int) {
    const index_t i0 = b0 * elementwise_chunk, i1 = std::min(n, b1 * elementwise_chunk);
    simd::with_lanes<T>(lanes, [&](auto* lane_type) {
      detail::gelu_backward_lanes<std::remove_pointer_t<decltype(lane_type)>>(d_in + i0, d_out + i0, in + i0, i1 - i0);
    });
  }, pool);
}

template <class T>
void gelu_forward(T* out, const T* in, index_t n, ThreadPool& pool = global_pool()) {
  gelu_forward_impl(out, in, n, simd::best_lanes<T>(), pool);
}

template <class T>
void gelu_backward(T* d_in, const T* d_out, const T* in, index_t n, ThreadPool& pool = global_pool()) {
  gelu_backward_impl(d_in, d_out, in, n, simd::best_lanes<T>(), pool);
}

template <class T>
void relu_forward(T* out, const T* in, index_t n) {
  for (index_t i = 0; i < n; ++i) out[i] = in[i] > T(0) ? in[i] : T(0);
}

template <class T>
void relu_backward(T* d_in, const T* d_out, const T* in, index_t n) {
  for (index_t i = 0; i < n; ++i) d_in[i] += in[i] > T(0) ? d_out[i] : T(0);
}

// Logistic sigmoid in the form that never overflows (exp of a non-positive argument only).
template <class T>
T sigmoid(T x) {
  if (x >= T(0)) return T(1) / (T(1) + std::exp(-x));
  const T e = std::exp(x);
  return e / (T(1) + e);
}

template <class T>
T sigmoid_vjp(T x, T d_out) {
  const T s = sigmoid(x);
  return d_out * s * (T(1) - s);
}

// Inverse of sigmoid; p at or beyond 0 or 1 (infinite logits) maps to -max_magnitude or +max_magnitude.
template <class T>
T logit(T p, T max_magnitude) {
  if (p <= T(0)) return -max_magnitude;
  if (p >= T(1)) return max_magnitude;
  return std::clamp(std::log(p) - std::log1p(-p), -max_magnitude, max_magnitude);
}

// SiLU x * sigmoid(x), written to stay finite for large |x|.
template <class T>
void silu_forward(T* out, const T* in, index_t n) {
  for (index_t i = 0; i < n; ++i) out[i] = in[i] / (T(1) + std::exp(-in[i]));
}

template <class T>
void silu_backward(T* d_in, const T* d_out, const T* in, index_t n) {
  for (index_t i = 0; i < n; ++i) {
    const T s = T(1) / (T(1) + std::exp(-in[i]));
    d_in[i] += d_out[i] * s * (T(1) + in[i] * (T(1) - s));
  }
}

}  // namespace nn
}  // namespace v0
}  // namespace flexsplat
