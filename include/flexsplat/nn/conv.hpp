#pragma once
// 2-D convolution and transposed convolution (PyTorch semantics, NCHW, groups = 1, dilation = 1) via im2col + GEMM.
// Weights: conv [C_out, C_in, kh, kw]; transposed conv [C_in, C_out, kh, kw]. Backward adds into gradients.
#include <algorithm>
#include <span>

#include "flexsplat/core/gemm.hpp"

namespace flexsplat {
inline namespace v0 {
namespace nn {

struct Conv2dShape {
  index_t batch = 1, in_channels = 0, out_channels = 0, in_h = 0, in_w = 0;
  index_t kernel_h = 1, kernel_w = 1, stride = 1, padding = 0;
  index_t output_padding = 0;  // transposed convolution only
  index_t conv_out_h() const { return (in_h + 2 * padding - kernel_h) / stride + 1; }
  index_t conv_out_w() const { return (in_w + 2 * padding - kernel_w) / stride + 1; }
  index_t transposed_out_h() const { return (in_h - 1) * stride - 2 * padding + kernel_h + output_padding; }
  index_t transposed_out_w() const { return (in_w - 1) * stride - 2 * padding + kernel_w + output_padding; }
};

inline void validate_conv(const Conv2dShape& s, bool transposed, const char* what) {
  require(s.batch >= 1 && s.in_channels >= 1 && s.out_channels >= 1, what, ": channels and batch must be positive (batch ",
          s.batch, ", in ", s.in_channels, ", out ", s.out_channels, ")");
  require(s.in_h >= 1 && s.in_w >= 1, what, ": input feature map is ", s.in_h, "x", s.in_w, " (zero-size)");
  require(s.kernel_h >= 1 && s.kernel_w >= 1 && s.stride >= 1 && s.padding >= 0, what, ": bad kernel/stride/padding");
  const index_t oh = transposed ? s.transposed_out_h() : s.conv_out_h();
  const index_t ow = transposed ? s.transposed_out_w() : s.conv_out_w();
  require(oh >= 1 && ow >= 1 && (transposed || s.in_h + 2 * s.padding >= s.kernel_h), what, ": ", s.in_h, "x", s.in_w,
          " input with kernel ", s.kernel_h, "x", s.kernel_w, " gives an empty output");
  require(!transposed || s.output_padding < s.stride, what, ": output_padding must be smaller than stride");
}

// Scratch elements for one image's column matrix.
inline index_t conv2d_scratch_size(const Conv2dShape& s) {
  return s.in_channels * s.kernel_h * s.kernel_w * s.conv_out_h() * s.conv_out_w();
}
inline index_t conv_transpose2d_scratch_size(const Conv2dShape& s) {
  return s.out_channels * s.kernel_h * s.kernel_w * s.in_h * s.in_w;
}

namespace detail {
// cols[(c*kh + i)*kw + j, oy*ow + ox] = image[c, oy*stride - pad + i, ox*stride - pad + j] (zero outside).
template <class T>
void im2col(T* cols, const T* image, index_t channels, index_t h, index_t w, index_t kh, index_t kw, index_t stride,
            index_t pad, index_t oh, index_t ow) {
  for (index_t c = 0; c < channels; ++c)
    for (index_t i = 0; i < kh; ++i)
      for (index_t j = 0; j < kw; ++j) {
        T* row = cols + ((c * kh + i) * kw + j) * oh * ow;
        for (index_t oy = 0; oy < oh; ++oy) {
          const index_t y = oy * stride - pad + i;
          T* dst = row + oy * ow;
          if (y < 0 || y >= h) {
            std::fill(dst, dst + ow, T(0));
            continue;
          }
          const T* src = image + (c * h + y) * w;
          for (index_t ox = 0; ox < ow; ++ox) {
            const index_t x = ox * stride - pad + j;
            dst[ox] = (x >= 0 && x < w) ? src[x] : T(0);
          }
        }
      }
}

// The adjoint of im2col: image += scatter(cols).
template <class T>
void col2im_add(T* image, const T* cols, index_t channels, index_t h, index_t w, index_t kh, index_t kw, index_t stride,
                index_t pad, index_t oh, index_t ow) {
  for (index_t c = 0; c < channels; ++c)
    for (index_t i = 0; i < kh; ++i)
      for (index_t j = 0; j < kw; ++j) {
        const T* row = cols + ((c * kh + i) * kw + j) * oh * ow;
        for (index_t oy = 0; oy < oh; ++oy) {
          const index_t y = oy * stride - pad + i;
          if (y < 0 || y >= h) continue;
          T* dst = image + (c * h + y) * w;
          for (index_t ox = 0; ox < ow; ++ox) {
            const index_t x = ox * stride - pad + j;
            if (x >= 0 && x < w) dst[x] += row[oy * ow + ox];
          }
        }
      }
}
}  // namespace detail

// out [B, C_out, OH, OW]; bias may be null; scratch >= conv2d_scratch_size(s).
template <class T>
void conv2d_forward(T* out, const T* in, const T* weight, const T* bias, const Conv2dShape& s, std::span<T> scratch) {
  validate_conv(s, false, "conv2d");
  const index_t oh = s.conv_out_h(), ow = s.conv_out_w(), K = s.in_channels * s.kernel_h * s.kernel_w;
  require(static_cast<index_t>(scratch.size()) >= conv2d_scratch_size(s), "conv2d: scratch too small");
  const bool pointwise = s.kernel_h == 1 && s.kernel_w == 1 && s.stride == 1 && s.padding == 0;
  for (index_t b = 0; b < s.batch; ++b) {
    const T* x = in + b * s.in_channels * s.in_h * s.in_w;
    T* y = out + b * s.out_channels * oh * ow;
    const T* cols = x;
    if (!pointwise) {
      detail::im2col(scratch.data(), x, s.in_channels, s.in_h, s.in_w, s.kernel_h, s.kernel_w, s.stride, s.padding, oh, ow);
      cols = scratch.data();
    }
    if (bias)
      for (index_t o = 0; o < s.out_channels; ++o) std::fill(y + o * oh * ow, y + (o + 1) * oh * ow, bias[o]);
    gemm(Trans::no, Trans::no, s.out_channels, oh * ow, K, T(1), weight, K, cols, oh * ow, bias ? T(1) : T(0), y, oh * ow);
  }
}

// Adds into d_in, d_weight, d_bias (each may be null). scratch >= conv2d_scratch_size(s).
template <class T>
void conv2d_backward(T* d_in, T* d_weight, T* d_bias, const T* d_out, const T* in, const T* weight,
                     const Conv2dShape& s, std::span<T> scratch) {
  validate_conv(s, false, "conv2d");
  const index_t oh = s.conv_out_h(), ow = s.conv_out_w(), K = s.in_channels * s.kernel_h * s.kernel_w;
  require(static_cast<index_t>(scratch.size()) >= conv2d_scratch_size(s), "conv2d: scratch too small");
  const bool pointwise = s.kernel_h == 1 && s.kernel_w == 1 && s.stride == 1 && s.padding == 0;
  for (index_t b = 0; b < s.batch; ++b) {
    const T* x = in + b * s.in_channels * s.in_h * s.in_w;
    const T* dy = d_out + b * s.out_channels * oh * ow;
    if (d_bias)
      for (index_t o = 0; o < s.out_channels; ++o)
        for (index_t p = 0; p < oh * ow; ++p) d_bias[o] += dy[o * oh * ow + p];
    if (d_weight) {
      const T* cols = x;
      if (!pointwise) {
        detail::im2col(scratch.data(), x, s.in_channels, s.in_h, s.in_w, s.kernel_h, s.kernel_w, s.stride, s.padding, oh, ow);
        cols = scratch.data();
      }
      gemm(Trans::no, Trans::yes, s.out_channels, K, oh * ow, T(1), dy, oh * ow, cols, oh * ow, T(1), d_weight, K);
    }
    if (d_in) {
      T* dx = d_in + b * s.in_channels * s.in_h * s.in_w;
      if (pointwise) {
        gemm(Trans::yes, Trans::no, K, oh * ow, s.out_channels, T(1), weight, K, dy, oh * ow, T(1), dx, oh * ow);
      } else {
        gemm(Trans::yes, Trans::no, K, oh * ow, s.out_channels, T(1), weight, K, dy, oh * ow, T(0), scratch.data(), oh * ow);
        detail::col2im_add(dx, scratch.data(), s.in_channels, s.in_h, s.in_w, s.kernel_h, s.kernel_w, s.stride, s.padding, oh, ow);
      }
    }
  }
}

// out [B, C_out, OH, OW] with OH = (H-1)*stride - 2*padding + kh + output_padding. scratch >= conv_transpose2d_scratch_size(s).
template <class T>
void conv_transpose2d_forward(T* out, const T* in, const T* weight, const T* bias, const Conv2dShape& s,
                              std::span<T> scratch) {
  validate_conv(s, true, "conv_transpose2d");
  const index_t oh = s.transposed_out_h(), ow = s.transposed_out_w(), K = s.out_channels * s.kernel_h * s.kernel_w;
  const index_t hw = s.in_h * s.in_w;
  require(static_cast<index_t>(scratch.size()) >= conv_transpose2d_scratch_size(s), "conv_transpose2d: scratch too small");
  for (index_t b = 0; b < s.batch; ++b) {
    const T* x = in + b * s.in_channels * hw;
    T* y = out + b * s.out_channels * oh * ow;
    for (index_t o = 0; o < s.out_channels; ++o) std::fill(y + o * oh * ow, y + (o + 1) * oh * ow, bias ? bias[o] : T(0));
    gemm(Trans::yes, Trans::no, K, hw, s.in_channels, T(1), weight, K, x, hw, T(0), scratch.data(), hw);
    detail::col2im_add(y, scratch.data(), s.out_channels, oh, ow, s.kernel_h, s.kernel_w, s.stride, s.padding, s.in_h, s.in_w);
  }
}

template <class T>
void conv_transpose2d_backward(T* d_in, T* d_weight, T* d_bias, const T* d_out, const T* in, const T* weight,
                               const Conv2dShape& s, std::span<T> scratch) {
  validate_conv(s, true, "conv_transpose2d");
  const index_t oh = s.transposed_out_h(), ow = s.transposed_out_w(), K = s.out_channels * s.kernel_h * s.kernel_w;
  const index_t hw = s.in_h * s.in_w;
  require(static_cast<index_t>(scratch.size()) >= conv_transpose2d_scratch_size(s), "conv_transpose2d: scratch too small");
  for (index_t b = 0; b < s.batch; ++b) {
    const T* x = in + b * s.in_channels * hw;
    const T* dy = d_out + b * s.out_channels * oh * ow;
    if (d_bias)
      for (index_t o = 0; o < s.out_channels; ++o)
        for (index_t p = 0; p < oh * ow; ++p) d_bias[o] += dy[o * oh * ow + p];
    if (!d_in && !d_weight) continue;
    detail::im2col(scratch.data(), dy, s.out_channels, oh, ow, s.kernel_h, s.kernel_w, s.stride, s.padding, s.in_h, s.in_w);
    if (d_in)
      gemm(Trans::no, Trans::no, s.in_channels, hw, K, T(1), weight, K, scratch.data(), hw, T(1),
           d_in + b * s.in_channels * hw, hw);
    if (d_weight) gemm(Trans::no, Trans::yes, s.in_channels, K, hw, T(1), x, hw, scratch.data(), hw, T(1), d_weight, K);
  }
}

}  // namespace nn
}  // namespace v0
}  // namespace flexsplat
