#pragma once
// Element-wise activations as forward/backward pairs on raw arrays; backward adds into d_in.
#include <algorithm>
#include <cmath>

#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/simd.hpp"
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {
namespace nn {

// Exact GELU (erf form, PyTorch's default). The *_impl<T, Simd> bodies are the scalar reference (Simd = false) and
// the simd::batch path; gelu_forward / gelu_backward pick one by simd::enabled() and run over chunks in parallel.
template <class T, bool Simd>
void gelu_forward_impl(T* out, const T* in, index_t n) {
  constexpr T inv_sqrt2 = T(0.70710678118654752440);
  index_t i = 0;
  if constexpr (Simd) {
    using B = simd::batch<T>;
    constexpr index_t w = static_cast<index_t>(B::size);
    const B half(T(0.5)), one(T(1)), k(inv_sqrt2);
    for (; i + w <= n; i += w) {
      const B x = B::load_unaligned(in + i);
      (half * x * (one + xsimd::erf(x * k))).store_unaligned(out + i);
    }
  }
  for (; i < n; ++i) out[i] = T(0.5) * in[i] * (T(1) + std::erf(in[i] * inv_sqrt2));
}

// d_in += d_out * (Phi(x) + x phi(x)).
template <class T, bool Simd>
void gelu_backward_impl(T* d_in, const T* d_out, const T* in, index_t n) {
  constexpr T inv_sqrt2 = T(0.70710678118654752440);
  constexpr T inv_sqrt_2pi = T(0.39894228040143267794);
  index_t i = 0;
  if constexpr (Simd) {
    using B = simd::batch<T>;
    constexpr index_t w = static_cast<index_t>(B::size);
    const B half(T(0.5)), one(T(1)), k(inv_sqrt2), c(inv_sqrt_2pi), minus_half(T(-0.5));
    for (; i + w <= n; i += w) {
      const B x = B::load_unaligned(in + i);
      const B cdf = half * (one + xsimd::erf(x * k));
      const B pdf = c * xsimd::exp(minus_half * x * x);
      xsimd::fma(B::load_unaligned(d_out + i), xsimd::fma(x, pdf, cdf), B::load_unaligned(d_in + i)).store_unaligned(d_in + i);
    }
  }
  for (; i < n; ++i) {
    const T x = in[i];
    const T cdf = T(0.5) * (T(1) + std::erf(x * inv_sqrt2));
    const T pdf = inv_sqrt_2pi * std::exp(T(-0.5) * x * x);
    d_in[i] += d_out[i] * (cdf + x * pdf);
  }
}

inline constexpr index_t elementwise_chunk = 4096;

// out may alias in. Inside another parallel region it runs serially on the calling thread.
template <class T>
void gelu_forward(T* out, const T* in, index_t n, ThreadPool& pool = global_pool()) {
  const bool vec = simd::enabled();
  parallel_for((n + elementwise_chunk - 1) / elementwise_chunk, [&](index_t b0, index_t b1, int) {
    const index_t i0 = b0 * elementwise_chunk, i1 = std::min(n, b1 * elementwise_chunk);
    if (vec) gelu_forward_impl<T, true>(out + i0, in + i0, i1 - i0);
    else gelu_forward_impl<T, false>(out + i0, in + i0, i1 - i0);
  }, pool);
}

template <class T>
void gelu_backward(T* d_in, const T* d_out, const T* in, index_t n, ThreadPool& pool = global_pool()) {
  const bool vec = simd::enabled();
  parallel_for((n + elementwise_chunk - 1) / elementwise_chunk, [&](index_t b0, index_t b1, int) {
    const index_t i0 = b0 * elementwise_chunk, i1 = std::min(n, b1 * elementwise_chunk);
    if (vec) gelu_backward_impl<T, true>(d_in + i0, d_out + i0, in + i0, i1 - i0);
    else gelu_backward_impl<T, false>(d_in + i0, d_out + i0, in + i0, i1 - i0);
  }, pool);
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
