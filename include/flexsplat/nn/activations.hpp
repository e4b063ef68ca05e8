#pragma once
// Element-wise activations as forward/backward pairs on raw arrays; backward adds into d_in.
#include <cmath>

#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {
namespace nn {

// Exact GELU (erf form, PyTorch's default).
template <class T>
void gelu_forward(T* out, const T* in, index_t n) {
  constexpr T inv_sqrt2 = T(0.70710678118654752440);
  for (index_t i = 0; i < n; ++i) out[i] = T(0.5) * in[i] * (T(1) + std::erf(in[i] * inv_sqrt2));
}

template <class T>
void gelu_backward(T* d_in, const T* d_out, const T* in, index_t n) {
  constexpr T inv_sqrt2 = T(0.70710678118654752440);
  constexpr T inv_sqrt_2pi = T(0.39894228040143267794);
  for (index_t i = 0; i < n; ++i) {
    const T x = in[i];
    const T cdf = T(0.5) * (T(1) + std::erf(x * inv_sqrt2));
    const T pdf = inv_sqrt_2pi * std::exp(T(-0.5) * x * x);
    d_in[i] += d_out[i] * (cdf + x * pdf);
  }
}

template <class T>
void relu_forward(T* out, const T* in, index_t n) {
  for (index_t i = 0; i < n; ++i) out[i] = in[i] > T(0) ? in[i] : T(0);
}

template <class T>
void relu_backward(T* d_in, const T* d_out, const T* in, index_t n) {
  for (index_t i = 0; i < n; ++i) d_in[i] += in[i] > T(0) ? d_out[i] : T(0);
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
