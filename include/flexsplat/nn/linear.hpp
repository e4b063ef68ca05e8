#pragma once
// Fully connected layer with PyTorch's weight layout [out, in]: y = x W^T + b over rows of x.
#include "flexsplat/core/gemm.hpp"

namespace flexsplat {
inline namespace v0 {
namespace nn {

// out [rows, out_features], in [rows, in_features], weight [out_features, in_features], bias [out_features] or null.
template <class T>
void linear_forward(T* out, const T* in, const T* weight, const T* bias, index_t rows, index_t in_features,
                    index_t out_features) {
  if (bias) {
    for (index_t r = 0; r < rows; ++r) std::copy(bias, bias + out_features, out + r * out_features);
  }
  gemm(Trans::no, Trans::yes, rows, out_features, in_features, T(1), in, in_features, weight, in_features,
       bias ? T(1) : T(0), out, out_features);
}

// Adds into d_in, d_weight, d_bias; any of them may be null when not wanted.
template <class T>
void linear_backward(T* d_in, T* d_weight, T* d_bias, const T* d_out, const T* in, const T* weight, index_t rows,
                     index_t in_features, index_t out_features) {
  if (d_in)
    gemm(Trans::no, Trans::no, rows, in_features, out_features, T(1), d_out, out_features, weight, in_features, T(1),
         d_in, in_features);
  if (d_weight)
    gemm(Trans::yes, Trans::no, out_features, in_features, rows, T(1), d_out, out_features, in, in_features, T(1),
         d_weight, in_features);
  if (d_bias)
    for (index_t r = 0; r < rows; ++r)
      for (index_t o = 0; o < out_features; ++o) d_bias[o] += d_out[r * out_features + o];
}

}  // namespace nn
}  // namespace v0
}  // namespace flexsplat
