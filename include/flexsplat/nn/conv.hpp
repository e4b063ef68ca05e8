#pragma once
// 2-D convolution and transposed convolution (PyTorch semantics, NCHW, groups = 1, dilation = 1) via im2col + GEMM.
// Weights: conv [C_out, C_in, kh, kw]; transposed conv [C_in, C_out, kh, kw]. Backward adds into gradients.
#include <algorithm>
#include <array>
#include <span>

#include "flexsplat/core/gemm.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/profile.hpp"

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

// Scratch elements for one image's whole column matrix (one GEMM per image).
inline index_t conv2d_columns_size(const Conv2dShape& s) {
  return s.in_channels * s.kernel_h * s.kernel_w * s.conv_out_h() * s.conv_out_w();
}
inline index_t conv2d_row_scratch_size(const Conv2dShape& s) {
  return s.in_channels * s.kernel_h * s.kernel_w * s.conv_out_w();
}
// Backward's input gradient of a stride-1 square kernel with padding < kernel (detail::conv2d_backward_input_correlate):
// the flipped weight [C_in, C_out * kh * kw], then per band of input rows the columns of d_out, C_out * kh * kw * W each.
// It writes C_out * k * k columns per pixel where the column path writes C_in * k * k, zeroes them and scatters them
// back, but first copies the flipped kernel (C_in * C_out * k * k): taken where C_out <= C_in and the maps have at
// least 8 C_out pixels, where it was faster in bench/conv (slower on VGGT-1B's 256-channel maps up to 16 x 16).
inline bool conv2d_backward_correlates(const Conv2dShape& s) {
  return s.stride == 1 && s.kernel_h == s.kernel_w && s.kernel_h > 1 && s.padding < s.kernel_h &&
         s.out_channels <= s.in_channels && s.batch * s.in_h * s.in_w >= 8 * s.out_channels;
}
inline index_t conv2d_correlate_scratch_size(const Conv2dShape& s, index_t rows) {
  return s.out_channels * s.kernel_h * s.kernel_w * (s.in_channels + rows * s.in_w);
}
// Scratch elements with which conv2d_forward and conv2d_backward run on whole images (one GEMM per image). Both also
// take less, down to one output row's columns (conv2d_row_scratch_size), and then run bands of rows.
inline index_t conv2d_scratch_size(const Conv2dShape& s) {
  const index_t columns = conv2d_columns_size(s);
  return conv2d_backward_correlates(s) ? std::max(columns, conv2d_correlate_scratch_size(s, s.in_h)) : columns;
}
// Stride 1 without a column matrix (detail::conv2d_forward_shifted): the weight as kh*kw matrices [C_out, C_in], and
// per band of output rows the zero-padded input rows it reads (+ kw - 1 elements the last tap reads past them) and the
// output over padded-width rows. Fixed part + rows * per-row part.
inline index_t conv2d_shifted_scratch_size(const Conv2dShape& s, index_t rows) {
  const index_t pw = s.in_w + 2 * s.padding;
  return s.kernel_h * s.kernel_w * s.out_channels * s.in_channels + s.in_channels * (s.kernel_h - 1) * pw +
         (s.kernel_w - 1) + rows * (s.in_channels + s.out_channels) * pw;
}
inline index_t conv_transpose2d_scratch_size(const Conv2dShape& s) {
  return s.out_channels * s.kernel_h * s.kernel_w * s.in_h * s.in_w;
}

namespace detail {
// Output columns ox whose input column ox * stride - pad + j lies in [0, w): [lo, hi).
inline void im2col_valid_columns(index_t& lo, index_t& hi, index_t w, index_t j, index_t stride, index_t pad, index_t ow) {
  const index_t first = pad - j, last = w + pad - j - 1;
  lo = first <= 0 ? 0 : std::min(ow, (first + stride - 1) / stride);
  hi = last < 0 ? 0 : std::min(ow, last / stride + 1);
  hi = std::max(hi, lo);
}

// Output rows [oy0, oy0 + rows) of the column matrix, n = rows * ow columns:
// cols[(c*kh + i)*kw + j, (oy - oy0)*ow + ox] = image[c, oy*stride - pad + i, ox*stride - pad + j] (zero outside).
// Channel x kernel-row pairs split over the pool.
template <class T>
void im2col(T* cols, const T* image, index_t channels, index_t h, index_t w, index_t kh, index_t kw, index_t stride,
            index_t pad, index_t oy0, index_t rows, index_t ow) {
  const index_t n = rows * ow;
  parallel_for(channels * kh, [&](index_t r0, index_t r1, int) {
    for (index_t ci = r0; ci < r1; ++ci) {
      const index_t c = ci / kh, i = ci % kh;
      for (index_t j = 0; j < kw; ++j) {
        index_t lo, hi;
        im2col_valid_columns(lo, hi, w, j, stride, pad, ow);
        T* dst = cols + (ci * kw + j) * n;
        for (index_t oy = oy0; oy < oy0 + rows; ++oy, dst += ow) {
          const index_t y = oy * stride - pad + i;
          if (y < 0 || y >= h) {
            std::fill(dst, dst + ow, T(0));
            continue;
          }
          const T* src = image + (c * h + y) * w;
          const index_t shift = j - pad;
          std::fill(dst, dst + lo, T(0));
          if (stride == 1 && hi > lo)
            std::copy(src + (lo + shift), src + (hi + shift), dst + lo);
          else
            for (index_t ox = lo; ox < hi; ++ox) dst[ox] = src[ox * stride + shift];
          std::fill(dst + hi, dst + ow, T(0));
        }
      }
    }
  });
}

// The adjoint of im2col: image += scatter(cols) over the same band. Channels split over the pool (each adds into its
// own plane, in the same order for any thread count).
template <class T>
void col2im_add(T* image, const T* cols, index_t channels, index_t h, index_t w, index_t kh, index_t kw, index_t stride,
                index_t pad, index_t oy0, index_t rows, index_t ow) {
  const index_t n = rows * ow;
  parallel_for(channels, [&](index_t c0, index_t c1, int) {
    for (index_t c = c0; c < c1; ++c)
      for (index_t i = 0; i < kh; ++i)
        for (index_t j = 0; j < kw; ++j) {
          index_t lo, hi;
          im2col_valid_columns(lo, hi, w, j, stride, pad, ow);
          const T* src = cols + ((c * kh + i) * kw + j) * n;
          for (index_t oy = oy0; oy < oy0 + rows; ++oy, src += ow) {
            const index_t y = oy * stride - pad + i;
            if (y < 0 || y >= h) continue;
            T* dst = image + (c * h + y) * w;
            if (stride == 1) {  // contiguous: the compiler vectorises it
              const index_t shift = j - pad;
              for (index_t ox = lo; ox < hi; ++ox) dst[ox + shift] += src[ox];
            } else {
              for (index_t ox = lo; ox < hi; ++ox) dst[ox * stride + j - pad] += src[ox];
            }
          }
        }
  });
}

// sums[c] += the sum of plane c of [channels, n]: the bias gradient of one image. Channels split over the pool; each
// plane is summed by one worker in a fixed order, so the result does not depend on the thread count.
template <class T>
void add_plane_sums(T* sums, const T* planes, index_t channels, index_t n) {
  parallel_for(channels, [&](index_t c0, index_t c1, int) {
    for (index_t c = c0; c < c1; ++c) {
      // 16 interleaved partial sums: the loop vectorises.
      constexpr index_t lanes = 16;
      std::array<T, lanes> part{};
      const T* x = planes + c * n;
      index_t p = 0;
      for (; p + lanes <= n; p += lanes)
        for (index_t j = 0; j < lanes; ++j) part[static_cast<std::size_t>(j)] += x[p + j];
      for (; p < n; ++p) part[static_cast<std::size_t>(p % lanes)] += x[p];
      T sum = 0;
      for (const T v : part) sum += v;
      sums[c] += sum;
    }
  });
}

// Output rows per band for `scratch` elements of column matrix.
inline index_t conv2d_band_rows(const Conv2dShape& s, std::size_t scratch) {
  const index_t row = conv2d_row_scratch_size(s), band = std::min(s.conv_out_h(), static_cast<index_t>(scratch) / row);
  require(band >= 1, "conv2d: scratch of ", scratch, " elements cannot hold one output row's columns (", row, ")");
  return band;
}

inline bool conv2d_pointwise(const Conv2dShape& s) {
  return s.kernel_h == 1 && s.kernel_w == 1 && s.stride == 1 && s.padding == 0;
}

// Output pixels from which a stride-1 k x k convolution takes the shifted path: on VGGT's DPT shapes it is faster
// from 72 x 72 up and slower from 36 x 36 down (bench/conv, docs/nn.md).
inline constexpr index_t conv2d_shifted_min_pixels = 4096;

// Output rows per band of the shifted path for `scratch` elements (0 if not even one row fits).
inline index_t conv2d_shifted_band_rows(const Conv2dShape& s, std::size_t scratch) {
  const index_t fixed = conv2d_shifted_scratch_size(s, 0), row = conv2d_shifted_scratch_size(s, 1) - fixed;
  const index_t have = static_cast<index_t>(scratch);
  return have < fixed + row ? 0 : std::min(s.conv_out_h(), (have - fixed) / row);
}

// Stride 1, one image: out = sum over taps (i, j) of W_ij [C_out, C_in] x the zero-padded input shifted by (i, j). Per
// band the padded rows are copied once and each tap's B is a window of them (row stride = a padded band plane), so no
// kh*kw-times larger column matrix is written and read back. The output is computed over rows of pw = W + 2 * pad
// columns; the last kw - 1 of each row read across the row edge and are dropped.
template <class T>
void conv2d_forward_shifted(T* y, const T* x, const T* weight, const T* bias, const Conv2dShape& s,
                            std::span<T> scratch) {
  const index_t cin = s.in_channels, cout = s.out_channels, kh = s.kernel_h, kw = s.kernel_w, taps = kh * kw;
  const index_t h = s.in_h, w = s.in_w, pad = s.padding, pw = w + 2 * pad, oh = s.conv_out_h(), ow = s.conv_out_w();
  const index_t band = conv2d_shifted_band_rows(s, scratch.size());
  require(s.stride == 1 && band >= 1, "conv2d (shifted): needs stride 1 and ", conv2d_shifted_scratch_size(s, 1),
          " scratch elements, got stride ", s.stride, " and ", scratch.size());
  T* wt = scratch.data();
  T* padded = wt + taps * cout * cin;
  parallel_for(cout, [&](index_t o0, index_t o1, int) {
    for (index_t o = o0; o < o1; ++o)
      for (index_t c = 0; c < cin; ++c)
        for (index_t t = 0; t < taps; ++t) wt[(t * cout + o) * cin + c] = weight[(o * cin + c) * taps + t];
  });
  for (index_t oy0 = 0; oy0 < oh; oy0 += band) {
    const index_t rows = std::min(band, oh - oy0), prows = rows + kh - 1, plane = prows * pw, n = rows * pw;
    T* wide = padded + cin * plane + (kw - 1);
    parallel_for(cin, [&](index_t c0, index_t c1, int) {
      for (index_t c = c0; c < c1; ++c)
        for (index_t r = 0; r < prows; ++r) {
          T* dst = padded + c * plane + r * pw;
          const index_t yy = oy0 + r - pad;
          if (yy < 0 || yy >= h) {
            std::fill(dst, dst + pw, T(0));
            continue;
          }
          std::fill(dst, dst + pad, T(0));
          std::copy(x + (c * h + yy) * w, x + (c * h + yy + 1) * w, dst + pad);
          std::fill(dst + pad + w, dst + pw, T(0));
        }
    });
    std::fill(padded + cin * plane, wide, T(0));
    for (index_t t = 0; t < taps; ++t)
      gemm(Trans::no, Trans::no, cout, n, cin, T(1), wt + t * cout * cin, cin, padded + (t / kw) * pw + t % kw, plane,
           t == 0 ? T(0) : T(1), wide, n);
    parallel_for(cout, [&](index_t o0, index_t o1, int) {
      for (index_t o = o0; o < o1; ++o)
        for (index_t r = 0; r < rows; ++r) {
          const T* src = wide + o * n + r * pw;
          T* dst = y + (o * oh + oy0 + r) * ow;
          if (bias)
            for (index_t i = 0; i < ow; ++i) dst[i] = src[i] + bias[o];
          else
            std::copy(src, src + ow, dst);
        }
    });
  }
}

// im2col + one GEMM per band of output rows; scratch >= conv2d_row_scratch_size(s) unless pointwise (then unused).
template <class T>
void conv2d_forward_im2col(T* out, const T* in, const T* weight, const T* bias, const Conv2dShape& s,
                           std::span<T> scratch) {
  const index_t oh = s.conv_out_h(), ow = s.conv_out_w(), K = s.in_channels * s.kernel_h * s.kernel_w;
  const bool pointwise = conv2d_pointwise(s);
  const index_t band = pointwise ? oh : conv2d_band_rows(s, scratch.size());
  for (index_t b = 0; b < s.batch; ++b) {
    const T* x = in + b * s.in_channels * s.in_h * s.in_w;
    T* y = out + b * s.out_channels * oh * ow;
    for (index_t oy0 = 0; oy0 < oh; oy0 += band) {
      const index_t rows = std::min(band, oh - oy0), n = rows * ow;
      const T* cols = x;
      if (!pointwise) {
        im2col(scratch.data(), x, s.in_channels, s.in_h, s.in_w, s.kernel_h, s.kernel_w, s.stride, s.padding, oy0, rows,
               ow);
        cols = scratch.data();
      }
      if (bias)
        for (index_t o = 0; o < s.out_channels; ++o)
          std::fill(y + o * oh * ow + oy0 * ow, y + o * oh * ow + oy0 * ow + n, bias[o]);
      gemm(Trans::no, Trans::no, s.out_channels, n, K, T(1), weight, K, cols, n, bias ? T(1) : T(0), y + oy0 * ow,
           oh * ow);
    }
  }
}

// d_in += the adjoint of im2col applied to W^T d_out, per band of output rows (any stride and padding).
template <class T>
void conv2d_backward_input_columns(T* d_in, const T* d_out, const T* weight, const Conv2dShape& s,
                                   std::span<T> scratch) {
  const index_t oh = s.conv_out_h(), ow = s.conv_out_w(), K = s.in_channels * s.kernel_h * s.kernel_w;
  const index_t band = conv2d_band_rows(s, scratch.size());
  for (index_t b = 0; b < s.batch; ++b)
    for (index_t oy0 = 0; oy0 < oh; oy0 += band) {
      const index_t rows = std::min(band, oh - oy0), n = rows * ow;
      gemm(Trans::yes, Trans::no, K, n, s.out_channels, T(1), weight, K, d_out + b * s.out_channels * oh * ow + oy0 * ow,
           oh * ow, T(0), scratch.data(), n);
      col2im_add(d_in + b * s.in_channels * s.in_h * s.in_w, scratch.data(), s.in_channels, s.in_h, s.in_w, s.kernel_h,
                 s.kernel_w, s.stride, s.padding, oy0, rows, ow);
    }
}

// Input rows per band of the correlated input gradient for `scratch` elements (0 if not even one row fits).
inline index_t conv2d_correlate_band_rows(const Conv2dShape& s, std::size_t scratch) {
  const index_t fixed = conv2d_correlate_scratch_size(s, 0), row = conv2d_correlate_scratch_size(s, 1) - fixed;
  const index_t have = static_cast<index_t>(scratch);
  return have < fixed + row ? 0 : std::min(s.in_h, (have - fixed) / row);
}

// d_in += the correlation of d_out with the kernel flipped and its channels swapped, padding k - 1 - p: per band of
// input rows one im2col of d_out and one GEMM that adds into d_in, where the column path writes a C_in * k * k column
// matrix, zeroed first, and scatters it back. Needs conv2d_backward_correlates(s) and one band's scratch.
template <class T>
void conv2d_backward_input_correlate(T* d_in, const T* d_out, const T* weight, const Conv2dShape& s,
                                     std::span<T> scratch) {
  const index_t cin = s.in_channels, cout = s.out_channels, k = s.kernel_h, taps = k * k, K = cout * taps;
  const index_t h = s.in_h, w = s.in_w, oh = s.conv_out_h(), ow = s.conv_out_w();
  const index_t band = conv2d_correlate_band_rows(s, scratch.size());
  require(s.stride == 1 && s.kernel_h == s.kernel_w && s.padding < s.kernel_h && band >= 1,
          "conv2d backward (correlated): needs stride 1, a square kernel, padding below it and ",
          conv2d_correlate_scratch_size(s, 1), " scratch elements, got stride ", s.stride, ", kernel ", s.kernel_h, "x",
          s.kernel_w, ", padding ", s.padding, ", ", scratch.size(), " elements");
  T* flipped = scratch.data();
  T* cols = flipped + cin * K;
  parallel_for(cin, [&](index_t c0, index_t c1, int) {
    for (index_t c = c0; c < c1; ++c)
      for (index_t o = 0; o < cout; ++o)
        for (index_t t = 0; t < taps; ++t) flipped[c * K + o * taps + t] = weight[(o * cin + c) * taps + taps - 1 - t];
  });
  for (index_t b = 0; b < s.batch; ++b) {
    const T* dy = d_out + b * cout * oh * ow;
    T* dx = d_in + b * cin * h * w;
    for (index_t y0 = 0; y0 < h; y0 += band) {
      const index_t rows = std::min(band, h - y0), n = rows * w;
      im2col(cols, dy, cout, oh, ow, k, k, 1, k - 1 - s.padding, y0, rows, w);
      gemm(Trans::no, Trans::no, cin, n, K, T(1), flipped, K, cols, n, T(1), dx + y0 * w, h * w);
    }
  }
}

// The shifted path pays kh*kw GEMMs with K = C_in instead of one; it wins where the column matrix is large
// (bench/conv, docs/nn.md).
inline bool conv2d_use_shifted(const Conv2dShape& s, std::size_t scratch) {
  return s.stride == 1 && !conv2d_pointwise(s) && s.conv_out_h() * s.conv_out_w() >= conv2d_shifted_min_pixels &&
         conv2d_shifted_band_rows(s, scratch) >= 1;
}

inline bool conv2d_use_correlate(const Conv2dShape& s, std::size_t scratch) {
  return conv2d_backward_correlates(s) && conv2d_correlate_band_rows(s, scratch) >= 1;
}
}  // namespace detail

// The least scratch with which conv2d_forward runs as with conv2d_scratch_size(s): the shifted path's band of every
// output row where that is smaller; for callers with no conv2d_backward to follow.
inline index_t conv2d_forward_scratch_size(const Conv2dShape& s) {
  if (detail::conv2d_pointwise(s)) return 0;
  const index_t full = conv2d_columns_size(s);
  if (!detail::conv2d_use_shifted(s, static_cast<std::size_t>(full))) return full;
  return std::min(full, conv2d_shifted_scratch_size(s, s.conv_out_h()));
}

// out [B, C_out, OH, OW]; bias may be null. Stride-1 convolutions with at least detail::conv2d_shifted_min_pixels
// output pixels run detail::conv2d_forward_shifted when scratch >= conv2d_shifted_scratch_size(s, 1); the others
// im2col, which needs scratch >= conv2d_row_scratch_size(s) unless the kernel is 1 x 1, stride 1, no padding.
template <class T>
void conv2d_forward(T* out, const T* in, const T* weight, const T* bias, const Conv2dShape& s, std::span<T> scratch) {
  const profile::Scope timed(profile::Op::conv_forward);
  validate_conv(s, false, "conv2d");
  if (!detail::conv2d_use_shifted(s, scratch.size()))
    return detail::conv2d_forward_im2col(out, in, weight, bias, s, scratch);
  const index_t in_size = s.in_channels * s.in_h * s.in_w, out_size = s.out_channels * s.conv_out_h() * s.conv_out_w();
  for (index_t b = 0; b < s.batch; ++b)
    detail::conv2d_forward_shifted(out + b * out_size, in + b * in_size, weight, bias, s, scratch);
}

// Adds into d_in, d_weight, d_bias (each may be null); scratch as for conv2d_forward, in bands the same way. The input
// gradient is a correlation of d_out (detail::conv2d_backward_input_correlate) for the shapes of
// conv2d_backward_correlates when the scratch holds a band of it, else the adjoint of im2col.
template <class T>
void conv2d_backward(T* d_in, T* d_weight, T* d_bias, const T* d_out, const T* in, const T* weight,
                     const Conv2dShape& s, std::span<T> scratch) {
  const profile::Scope timed(profile::Op::conv_backward);
  validate_conv(s, false, "conv2d");
  const index_t oh = s.conv_out_h(), ow = s.conv_out_w(), K = s.in_channels * s.kernel_h * s.kernel_w;
  const bool pointwise = detail::conv2d_pointwise(s);
  const index_t band = pointwise ? oh : detail::conv2d_band_rows(s, scratch.size());
  for (index_t b = 0; b < s.batch; ++b) {
    const T* x = in + b * s.in_channels * s.in_h * s.in_w;
    const T* dy = d_out + b * s.out_channels * oh * ow;
    if (d_bias) detail::add_plane_sums(d_bias, dy, s.out_channels, oh * ow);
    if (pointwise) {
      if (d_weight) gemm(Trans::no, Trans::yes, s.out_channels, K, oh * ow, T(1), dy, oh * ow, x, oh * ow, T(1), d_weight, K);
      if (d_in)
        gemm(Trans::yes, Trans::no, K, oh * ow, s.out_channels, T(1), weight, K, dy, oh * ow, T(1),
             d_in + b * s.in_channels * s.in_h * s.in_w, oh * ow);
      continue;
    }
    for (index_t oy0 = 0; d_weight && oy0 < oh; oy0 += band) {
      const index_t rows = std::min(band, oh - oy0), n = rows * ow;
      detail::im2col(scratch.data(), x, s.in_channels, s.in_h, s.in_w, s.kernel_h, s.kernel_w, s.stride, s.padding,
                     oy0, rows, ow);
      gemm(Trans::no, Trans::yes, s.out_channels, K, n, T(1), dy + oy0 * ow, oh * ow, scratch.data(), n, T(1), d_weight, K);
    }
  }
  if (!d_in || pointwise) return;
  if (detail::conv2d_use_correlate(s, scratch.size())) detail::conv2d_backward_input_correlate(d_in, d_out, weight, s, scratch);
  else detail::conv2d_backward_input_columns(d_in, d_out, weight, s, scratch);
}

// out [B, C_out, OH, OW] with OH = (H-1)*stride - 2*padding + kh + output_padding. scratch >= conv_transpose2d_scratch_size(s).
template <class T>
void conv_transpose2d_forward(T* out, const T* in, const T* weight, const T* bias, const Conv2dShape& s,
                              std::span<T> scratch) {
  const profile::Scope timed(profile::Op::conv_forward);
  validate_conv(s, true, "conv_transpose2d");
  const index_t oh = s.transposed_out_h(), ow = s.transposed_out_w(), K = s.out_channels * s.kernel_h * s.kernel_w;
  const index_t hw = s.in_h * s.in_w;
  require(static_cast<index_t>(scratch.size()) >= conv_transpose2d_scratch_size(s), "conv_transpose2d: scratch too small");
  for (index_t b = 0; b < s.batch; ++b) {
    const T* x = in + b * s.in_channels * hw;
    T* y = out + b * s.out_channels * oh * ow;
    for (index_t o = 0; o < s.out_channels; ++o) std::fill(y + o * oh * ow, y + (o + 1) * oh * ow, bias ? bias[o] : T(0));
    gemm(Trans::yes, Trans::no, K, hw, s.in_channels, T(1), weight, K, x, hw, T(0), scratch.data(), hw);
    detail::col2im_add(y, scratch.data(), s.out_channels, oh, ow, s.kernel_h, s.kernel_w, s.stride, s.padding, 0, s.in_h,
                       s.in_w);
  }
}

template <class T>
void conv_transpose2d_backward(T* d_in, T* d_weight, T* d_bias, const T* d_out, const T* in, const T* weight,
                               const Conv2dShape& s, std::span<T> scratch) {
  const profile::Scope timed(profile::Op::conv_backward);
  validate_conv(s, true, "conv_transpose2d");
  const index_t oh = s.transposed_out_h(), ow = s.transposed_out_w(), K = s.out_channels * s.kernel_h * s.kernel_w;
  const index_t hw = s.in_h * s.in_w;
  require(static_cast<index_t>(scratch.size()) >= conv_transpose2d_scratch_size(s), "conv_transpose2d: scratch too small");
  for (index_t b = 0; b < s.batch; ++b) {
    const T* x = in + b * s.in_channels * hw;
    const T* dy = d_out + b * s.out_channels * oh * ow;
    if (d_bias) detail::add_plane_sums(d_bias, dy, s.out_channels, oh * ow);
    if (!d_in && !d_weight) continue;
    detail::im2col(scratch.data(), dy, s.out_channels, oh, ow, s.kernel_h, s.kernel_w, s.stride, s.padding, 0, s.in_h, s.in_w);
    if (d_in)
      gemm(Trans::no, Trans::no, s.in_channels, hw, K, T(1), weight, K, scratch.data(), hw, T(1),
           d_in + b * s.in_channels * hw, hw);
    if (d_weight) gemm(Trans::no, Trans::yes, s.in_channels, K, hw, T(1), x, hw, scratch.data(), hw, T(1), d_weight, K);
  }
}

}  // namespace nn
}  // namespace v0
}  // namespace flexsplat
