#pragma once
// Bilinear resizing of NCHW maps with PyTorch's F.interpolate(mode="bilinear") semantics, align_corners either way.
#include <algorithm>
#include <cmath>
#include <vector>

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

namespace detail {
// The taps of every output row and column, computed once per call: per output pixel and plane, the taps' floor and
// divisions cost more than the four loads.
template <class T>
struct BilinearTaps {
  std::vector<index_t> x0, x1, y0, y1;
  std::vector<T> wx, wy;
  BilinearTaps(index_t h, index_t w, index_t oh, index_t ow, bool align_corners)
      : x0(static_cast<std::size_t>(ow)), x1(x0.size()), y0(static_cast<std::size_t>(oh)), y1(y0.size()),
        wx(x0.size()), wy(y0.size()) {
    require(h >= 1 && w >= 1 && oh >= 1 && ow >= 1, "bilinear_resize: zero-size map (", h, "x", w, " -> ", oh, "x",
            ow, ")");
    for (std::size_t x = 0; x < x0.size(); ++x) {
      const BilinearTap t = bilinear_tap(static_cast<index_t>(x), w, ow, align_corners);
      x0[x] = t.i0, x1[x] = t.i1, wx[x] = static_cast<T>(t.w1);
    }
    for (std::size_t y = 0; y < y0.size(); ++y) {
      const BilinearTap t = bilinear_tap(static_cast<index_t>(y), h, oh, align_corners);
      y0[y] = t.i0, y1[y] = t.i1, wy[y] = static_cast<T>(t.w1);
    }
  }
};
}  // namespace detail

// in [planes, H, W] -> out [planes, OH, OW]; planes = batch * channels.
template <class T>
void bilinear_resize_forward(T* out, const T* in, index_t planes, index_t h, index_t w, index_t oh, index_t ow,
                             bool align_corners) {
  const detail::BilinearTaps<T> t(h, w, oh, ow, align_corners);
  for (index_t p = 0; p < planes; ++p)
    for (std::size_t y = 0; y < t.y0.size(); ++y) {
      const T wy = t.wy[y];
      const T* top_row = in + p * h * w + t.y0[y] * w;
      const T* bottom_row = in + p * h * w + t.y1[y] * w;
      T* o = out + (p * oh + static_cast<index_t>(y)) * ow;
      for (std::size_t x = 0; x < t.x0.size(); ++x) {
        const T wx = t.wx[x];
        const T top = (T(1) - wx) * top_row[t.x0[x]] + wx * top_row[t.x1[x]];
        const T bottom = (T(1) - wx) * bottom_row[t.x0[x]] + wx * bottom_row[t.x1[x]];
        o[x] = (T(1) - wy) * top + wy * bottom;
      }
    }
}

template <class T>
void bilinear_resize_backward(T* d_in, const T* d_out, index_t planes, index_t h, index_t w, index_t oh, index_t ow,
                              bool align_corners) {
  const detail::BilinearTaps<T> t(h, w, oh, ow, align_corners);
  for (index_t p = 0; p < planes; ++p)
    for (std::size_t y = 0; y < t.y0.size(); ++y) {
      const T wy = t.wy[y];
      T* top_row = d_in + p * h * w + t.y0[y] * w;
      T* bottom_row = d_in + p * h * w + t.y1[y] * w;
      const T* g_row = d_out + (p * oh + static_cast<index_t>(y)) * ow;
      for (std::size_t x = 0; x < t.x0.size(); ++x) {
        const T wx = t.wx[x], g = g_row[x];
        top_row[t.x0[x]] += (T(1) - wy) * (T(1) - wx) * g;
        top_row[t.x1[x]] += (T(1) - wy) * wx * g;
        bottom_row[t.x0[x]] += wy * (T(1) - wx) * g;
        bottom_row[t.x1[x]] += wy * wx * g;
      }
    }
}

}  // namespace nn
}  // namespace v0
}  // namespace flexsplat
