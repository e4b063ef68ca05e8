#pragma once
// Bilinear resizing of NCHW maps with PyTorch's F.interpolate(mode="bilinear") semantics, align_corners either way.
#include <algorithm>
#include <cmath>

#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {
namespace nn {

struct BilinearTap {
  index_t i0, i1;
  double w1;  // weight of i1; i0 gets 1 - w1
};

// Source coordinate of output index i, clamped the way PyTorch's CPU kernel does.
inline BilinearTap bilinear_tap(index_t i, index_t in_size, index_t out_size, bool align_corners) {
  double src;
  if (align_corners) {
    src = out_size > 1 ? static_cast<double>(i) * static_cast<double>(in_size - 1) / static_cast<double>(out_size - 1) : 0.0;
  } else {
    const double scale = static_cast<double>(in_size) / static_cast<double>(out_size);
    src = std::max(0.0, (static_cast<double>(i) + 0.5) * scale - 0.5);
  }
  const index_t i0 = std::min<index_t>(static_cast<index_t>(std::floor(src)), in_size - 1);
  const index_t i1 = std::min<index_t>(i0 + 1, in_size - 1);
  return {i0, i1, src - static_cast<double>(i0)};
}

// in [planes, H, W] -> out [planes, OH, OW]; planes = batch * channels.
template <class T>
void bilinear_resize_forward(T* out, const T* in, index_t planes, index_t h, index_t w, index_t oh, index_t ow,
                             bool align_corners) {
  require(h >= 1 && w >= 1 && oh >= 1 && ow >= 1, "bilinear_resize: zero-size map (", h, "x", w, " -> ", oh, "x", ow, ")");
  for (index_t p = 0; p < planes; ++p)
    for (index_t y = 0; y < oh; ++y) {
      const BilinearTap ty = bilinear_tap(y, h, oh, align_corners);
      const T wy = static_cast<T>(ty.w1);
      for (index_t x = 0; x < ow; ++x) {
        const BilinearTap tx = bilinear_tap(x, w, ow, align_corners);
        const T wx = static_cast<T>(tx.w1);
        const T* src = in + p * h * w;
        const T top = (T(1) - wx) * src[ty.i0 * w + tx.i0] + wx * src[ty.i0 * w + tx.i1];
        const T bottom = (T(1) - wx) * src[ty.i1 * w + tx.i0] + wx * src[ty.i1 * w + tx.i1];
        out[(p * oh + y) * ow + x] = (T(1) - wy) * top + wy * bottom;
      }
    }
}

template <class T>
void bilinear_resize_backward(T* d_in, const T* d_out, index_t planes, index_t h, index_t w, index_t oh, index_t ow,
                              bool align_corners) {
  for (index_t p = 0; p < planes; ++p)
    for (index_t y = 0; y < oh; ++y) {
      const BilinearTap ty = bilinear_tap(y, h, oh, align_corners);
      const T wy = static_cast<T>(ty.w1);
      for (index_t x = 0; x < ow; ++x) {
        const BilinearTap tx = bilinear_tap(x, w, ow, align_corners);
        const T wx = static_cast<T>(tx.w1);
        const T g = d_out[(p * oh + y) * ow + x];
        T* dst = d_in + p * h * w;
        dst[ty.i0 * w + tx.i0] += (T(1) - wy) * (T(1) - wx) * g;
        dst[ty.i0 * w + tx.i1] += (T(1) - wy) * wx * g;
        dst[ty.i1 * w + tx.i0] += wy * (T(1) - wx) * g;
        dst[ty.i1 * w + tx.i1] += wy * wx * g;
      }
    }
}

}  // namespace nn
}  // namespace v0
}  // namespace flexsplat
