#pragma once
// 2-D max pooling (PyTorch MaxPool2d semantics: no padding, dilation 1, floor output size; ties and NaN go to the
// first such element in row-major window order, as PyTorch's CPU kernel). NCHW planes; backward adds into d_in.
#include <cmath>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {
namespace nn {

struct Pool2dShape {
  index_t planes = 1;  // batch * channels
  index_t in_h = 0, in_w = 0;
  index_t kernel = 2, stride = 2;
  index_t out_h() const { return (in_h - kernel) / stride + 1; }
  index_t out_w() const { return (in_w - kernel) / stride + 1; }
};

inline void validate_pool(const Pool2dShape& s) {
  require(s.planes >= 1 && s.kernel >= 1 && s.stride >= 1, "max_pool2d: bad shape (planes ", s.planes, ", kernel ",
          s.kernel, ", stride ", s.stride, ")");
  require(s.in_h >= s.kernel && s.in_w >= s.kernel, "max_pool2d: input ", s.in_h, "x", s.in_w, " is smaller than the ",
          s.kernel, "x", s.kernel, " window");
}

namespace detail {
// Offset (inside the plane) of the window maximum of output (oy, ox).
template <class T>
index_t max_pool_argmax(const T* plane, const Pool2dShape& s, index_t oy, index_t ox) {
  const index_t y0 = oy * s.stride, x0 = ox * s.stride;
  index_t best = y0 * s.in_w + x0;
  T best_v = plane[best];
  if (std::isnan(best_v)) return best;
  for (index_t i = 0; i < s.kernel; ++i)
    for (index_t j = 0; j < s.kernel; ++j) {
      const index_t at = (y0 + i) * s.in_w + x0 + j;
      const T v = plane[at];
      if (v > best_v || std::isnan(v)) {
        best = at;
        best_v = v;
        if (std::isnan(v)) return best;
      }
    }
  return best;
}
}  // namespace detail

// out [planes, out_h, out_w].
template <class T>
void max_pool2d_forward(T* out, const T* in, const Pool2dShape& s) {
  validate_pool(s);
  const index_t oh = s.out_h(), ow = s.out_w();
  for (index_t p = 0; p < s.planes; ++p) {
    const T* plane = in + p * s.in_h * s.in_w;
    T* o = out + p * oh * ow;
    for (index_t oy = 0; oy < oh; ++oy)
      for (index_t ox = 0; ox < ow; ++ox) o[oy * ow + ox] = plane[detail::max_pool_argmax(plane, s, oy, ox)];
  }
}

// d_in += routing of d_out to each window's maximum, recomputed from the forward input (no index buffer to keep).
template <class T>
void max_pool2d_backward(T* d_in, const T* d_out, const T* in, const Pool2dShape& s) {
  validate_pool(s);
  const index_t oh = s.out_h(), ow = s.out_w();
  for (index_t p = 0; p < s.planes; ++p) {
    const T* plane = in + p * s.in_h * s.in_w;
    T* d = d_in + p * s.in_h * s.in_w;
    const T* g = d_out + p * oh * ow;
    for (index_t oy = 0; oy < oh; ++oy)
      for (index_t ox = 0; ox < ow; ++ox) d[detail::max_pool_argmax(plane, s, oy, ox)] += g[oy * ow + ox];
  }
}

}  // namespace nn
}  // namespace v0
}  // namespace flexsplat
