#pragma once
// Separable image resampling kernels that reproduce two reference implementations bit for bit:
//
//  * resize_pillow_bicubic: Pillow 9.4 `Image.resize(size, Image.Resampling.BICUBIC)` on 8-bit images
//    (libImaging/Resample.c: Keys cubic with a = -0.5, support 2 scaled by the reduction factor, coefficients
//    normalised in double then rounded to 22-bit fixed point, horizontal pass first with uint8 rounding and
//    clipping of the intermediate image, then the vertical pass; "LA"/"RGBA" are premultiplied around the resize).
//  * interpolate_bicubic_antialias: PyTorch `F.interpolate(x, size=(oh, ow), mode="bicubic", antialias=True,
//    align_corners=False)` on floating-point data (ATen _upsample_bicubic2d_aa, CPU: same filter, weights computed
//    and accumulated in the tensor's scalar type, width pass first, then height).
//
// Memory conventions
//  * Interleaved 8-bit images (Pillow side): row-major, pixel (x, y) channel c at data[(y * width + x) * channels + c];
//    channels 1 (L), 2 (LA), 3 (RGB) or 4 (RGBA); alpha, when present, is the last channel and straight
//    (not premultiplied).
//  * Planar floating-point images (PyTorch side): CHW, value (c, y, x) at data[(c * height + y) * width + x]; a batch
//    NCHW is the same thing with channels = N * C.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <optional>
#include <span>
#include <vector>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/simd.hpp"
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {

// ---------------------------------------------------------------------------------------------------------------
// Shared filter
// ---------------------------------------------------------------------------------------------------------------

// Keys cubic convolution kernel with a = -0.5 (Pillow's BICUBIC and PyTorch's antialiased bicubic), support 2,
// written in the same operation order as both references so the float instantiation rounds like PyTorch's.
template <class T>
inline T keys_cubic_filter(T x) {
  constexpr T a = T(-0.5);
  if (x < T(0)) x = -x;
  if (x < T(1)) return ((a + T(2)) * x - (a + T(3))) * x * x + T(1);
  if (x < T(2)) return ((a * x - T(5) * a) * x + T(8) * a) * x - T(4) * a;
  return T(0);
}

// Pillow's form of the outer lobe, (((x - 5) x + 8) x - 4) a, which rounds differently from PyTorch's in double.
inline double pillow_bicubic_filter(double x) {
  constexpr double a = -0.5;
  if (x < 0.0) x = -x;
  if (x < 1.0) return ((a + 2.0) * x - (a + 3.0)) * x * x + 1;
  if (x < 2.0) return (((x - 5) * x + 8) * x - 4) * a;
  return 0.0;
}

// ---------------------------------------------------------------------------------------------------------------
// Pillow BICUBIC on 8-bit images
// ---------------------------------------------------------------------------------------------------------------

inline constexpr int pillow_precision_bits = 32 - 8 - 2;  // 22 fractional bits; 2 bits of head-room for overshoot
inline constexpr double pillow_bicubic_support = 2.0;

// One axis of a Pillow resample: output sample i reads taps [first[i], first[i] + count[i]) with the weights
// weights[i * ksize + j] (double, normalised to sum 1) and fixed[i * ksize + j] (rounded to 22 fractional bits).
struct PillowAxisCoefficients {
  int ksize = 0;
  std::vector<int> first, count;
  std::vector<double> weights;
  std::vector<std::int32_t> fixed;
};

// Pillow's precompute_coeffs + normalize_coeffs_8bpc for the source interval [in0, in1) (floats, as Pillow's box).
inline void pillow_bicubic_coefficients(int in_size, float in0, float in1, int out_size, PillowAxisCoefficients& c) {
  require(in_size >= 1 && out_size >= 1, "pillow_bicubic_coefficients: sizes must be positive (input ", in_size,
          ", output ", out_size, ")");
  require(in0 >= 0.0f && in1 <= static_cast<float>(in_size) && in1 - in0 >= 0.0f,
          "pillow_bicubic_coefficients: source interval [", in0, ", ", in1, ") is not inside [0, ", in_size, "]");
  const double scale = static_cast<double>(in1 - in0) / out_size;
  const double filterscale = scale < 1.0 ? 1.0 : scale;
  const double support = pillow_bicubic_support * filterscale;
  c.ksize = static_cast<int>(std::ceil(support)) * 2 + 1;
  const std::size_t n = static_cast<std::size_t>(out_size) * static_cast<std::size_t>(c.ksize);
  c.first.assign(static_cast<std::size_t>(out_size), 0);
  c.count.assign(static_cast<std::size_t>(out_size), 0);
  c.weights.assign(n, 0.0);
  c.fixed.assign(n, 0);
  for (int xx = 0; xx < out_size; ++xx) {
    const double center = in0 + (xx + 0.5) * scale;
    const double ss = 1.0 / filterscale;
    int xmin = static_cast<int>(center - support + 0.5);  // truncation toward zero, as Pillow's (int) cast
    if (xmin < 0) xmin = 0;
    int xmax = static_cast<int>(center + support + 0.5);
    if (xmax > in_size) xmax = in_size;
    xmax -= xmin;
    double* k = &c.weights[static_cast<std::size_t>(xx) * c.ksize];
    double ww = 0.0;
    for (int x = 0; x < xmax; ++x) {
      const double w = pillow_bicubic_filter((x + xmin - center + 0.5) * ss);
      k[x] = w;
      ww += w;
    }
    for (int x = 0; x < xmax; ++x)
      if (ww != 0.0) k[x] /= ww;
    c.first[static_cast<std::size_t>(xx)] = xmin;
    c.count[static_cast<std::size_t>(xx)] = xmax;
  }
  for (std::size_t i = 0; i < n; ++i) {
    const double v = c.weights[i] * (1 << pillow_precision_bits);
    c.fixed[i] = static_cast<std::int32_t>(c.weights[i] < 0 ? -0.5 + v : 0.5 + v);
  }
}

// Pillow's clip8: arithmetic shift (floor) of the 22-bit fixed-point sum, clamped to [0, 255].
inline std::uint8_t pillow_clip8(std::int32_t sum) {
  const std::int32_t v = sum >> pillow_precision_bits;
  return static_cast<std::uint8_t>(v < 0 ? 0 : (v > 255 ? 255 : v));
}

// Pillow's MULDIV255 (premultiply) and the CLIP8(255 * v / a) inverse used by its RGBA<->RGBa conversions.
inline std::uint8_t pillow_muldiv255(unsigned value, unsigned alpha) {
  const unsigned t = value * alpha + 128;
  return static_cast<std::uint8_t>(((t >> 8) + t) >> 8);
}
inline std::uint8_t pillow_unpremultiply(unsigned value, unsigned alpha) {
  if (alpha == 255 || alpha == 0) return static_cast<std::uint8_t>(value);
  const unsigned v = (255 * value) / alpha;
  return static_cast<std::uint8_t>(v > 255 ? 255 : v);
}

struct PillowResampleWorkspace {
  PillowAxisCoefficients horizontal, vertical;
  std::vector<std::uint8_t> premultiplied;  // LA / RGBA input converted to La / RGBa
  std::vector<std::uint8_t> temp;           // horizontally resampled rows ybox_first..ybox_last
  bool use_simd = simd::enabled();
};

namespace detail {

// Horizontal pass on interleaved rows [row_begin, row_begin + rows) of src; writes `rows` rows of width out_w.
inline void pillow_horizontal_pass(const std::uint8_t* src, int in_w, int channels, int row_begin, int rows,
                                   const PillowAxisCoefficients& k, std::uint8_t* dst, int out_w) {
  parallel_for(rows, [&](index_t begin, index_t end, int) {
    for (index_t r = begin; r < end; ++r) {
      const std::uint8_t* in_row = src + (static_cast<std::size_t>(row_begin + r) * in_w) * channels;
      std::uint8_t* out_row = dst + static_cast<std::size_t>(r) * out_w * channels;
      for (int xx = 0; xx < out_w; ++xx) {
        const int xmin = k.first[static_cast<std::size_t>(xx)], xcount = k.count[static_cast<std::size_t>(xx)];
        const std::int32_t* w = &k.fixed[static_cast<std::size_t>(xx) * k.ksize];
        for (int c = 0; c < channels; ++c) {
          std::int32_t ss = 1 << (pillow_precision_bits - 1);
          const std::uint8_t* p = in_row + static_cast<std::size_t>(xmin) * channels + c;
          for (int x = 0; x < xcount; ++x) ss += static_cast<std::int32_t>(p[x * channels]) * w[x];
          out_row[static_cast<std::size_t>(xx) * channels + c] = pillow_clip8(ss);
        }
      }
    }
  });
}

// Vertical pass: every output row is a weighted sum of whole input rows (row_len = width * channels bytes).
inline void pillow_vertical_pass(const std::uint8_t* src, std::size_t row_len, const PillowAxisCoefficients& k,
                                 int out_h, std::uint8_t* dst, bool use_simd) {
  parallel_for(out_h, [&](index_t begin, index_t end, int) {
    for (index_t yy = begin; yy < end; ++yy) {
      const int ymin = k.first[static_cast<std::size_t>(yy)], ycount = k.count[static_cast<std::size_t>(yy)];
      const std::int32_t* w = &k.fixed[static_cast<std::size_t>(yy) * k.ksize];
      std::uint8_t* out_row = dst + static_cast<std::size_t>(yy) * row_len;
      std::size_t i = 0;
      if (use_simd) {
        using B = simd::batch<std::int32_t>;
        constexpr std::size_t lanes = B::size;
        alignas(64) std::int32_t lane_in[lanes];
        alignas(64) std::int32_t lane_out[lanes];
        for (; i + lanes <= row_len; i += lanes) {
          B ss(std::int32_t(1) << (pillow_precision_bits - 1));
          for (int y = 0; y < ycount; ++y) {
            const std::uint8_t* p = src + static_cast<std::size_t>(ymin + y) * row_len + i;
            for (std::size_t l = 0; l < lanes; ++l) lane_in[l] = p[l];
            ss += B::load_aligned(lane_in) * B(w[y]);
          }
          (ss >> pillow_precision_bits).store_aligned(lane_out);
          for (std::size_t l = 0; l < lanes; ++l)
            out_row[i + l] = static_cast<std::uint8_t>(std::clamp<std::int32_t>(lane_out[l], 0, 255));
        }
      }
      for (; i < row_len; ++i) {
        std::int32_t ss = 1 << (pillow_precision_bits - 1);
        for (int y = 0; y < ycount; ++y)
          ss += static_cast<std::int32_t>(src[static_cast<std::size_t>(ymin + y) * row_len + i]) * w[y];
        out_row[i] = pillow_clip8(ss);
      }
    }
  });
}

}  // namespace detail

// Pillow 9.4 Image.resize((out_w, out_h), BICUBIC) with the default box and reducing_gap=None.
// src: interleaved in_w x in_h x channels; dst: interleaved out_w x out_h x channels (must not alias src).
inline void resize_pillow_bicubic(const std::uint8_t* src, int in_w, int in_h, int channels, std::uint8_t* dst,
                                  int out_w, int out_h, PillowResampleWorkspace& ws) {
  require(channels >= 1 && channels <= 4, "resize_pillow_bicubic: ", channels,
          " channels (expected 1 L, 2 LA, 3 RGB or 4 RGBA)");
  require(in_w >= 1 && in_h >= 1, "resize_pillow_bicubic: empty source image ", in_w, "x", in_h);
  require(out_w >= 1 && out_h >= 1, "resize_pillow_bicubic: height and width must be > 0 (requested ", out_w, "x",
          out_h, ")");
  require(src != nullptr && dst != nullptr, "resize_pillow_bicubic: null image buffer");
  const std::size_t in_pixels = static_cast<std::size_t>(in_w) * in_h;
  const std::size_t out_pixels = static_cast<std::size_t>(out_w) * out_h;
  // Image.resize returns a copy when nothing changes (and _resize crops when the box already has the output size).
  if (in_w == out_w && in_h == out_h) {
    std::copy(src, src + in_pixels * channels, dst);
    return;
  }
  const bool has_alpha = channels == 2 || channels == 4;
  if (has_alpha) {
    // Image.resize converts LA/RGBA to La/RGBa, resamples, converts back.
    ws.premultiplied.resize(in_pixels * channels);
    for (std::size_t p = 0; p < in_pixels; ++p) {
      const std::uint8_t* s = src + p * channels;
      std::uint8_t* d = ws.premultiplied.data() + p * channels;
      const unsigned alpha = s[channels - 1];
      for (int c = 0; c + 1 < channels; ++c) d[c] = pillow_muldiv255(s[c], alpha);
      d[channels - 1] = static_cast<std::uint8_t>(alpha);
    }
    src = ws.premultiplied.data();
  }
  const bool need_horizontal = out_w != in_w;
  const bool need_vertical = out_h != in_h;
  pillow_bicubic_coefficients(in_w, 0.0f, static_cast<float>(in_w), out_w, ws.horizontal);
  pillow_bicubic_coefficients(in_h, 0.0f, static_cast<float>(in_h), out_h, ws.vertical);
  const int ybox_first = ws.vertical.first.front();
  const int ybox_last = ws.vertical.first.back() + ws.vertical.count.back();

  if (need_horizontal && need_vertical) {
    const int rows = ybox_last - ybox_first;
    ws.temp.resize(static_cast<std::size_t>(rows) * out_w * channels);
    detail::pillow_horizontal_pass(src, in_w, channels, ybox_first, rows, ws.horizontal, ws.temp.data(), out_w);
    for (auto& f : ws.vertical.first) f -= ybox_first;
    detail::pillow_vertical_pass(ws.temp.data(), static_cast<std::size_t>(out_w) * channels, ws.vertical, out_h, dst,
                                 ws.use_simd);
  } else if (need_horizontal) {
    detail::pillow_horizontal_pass(src, in_w, channels, 0, in_h, ws.horizontal, dst, out_w);
  } else {
    detail::pillow_vertical_pass(src, static_cast<std::size_t>(in_w) * channels, ws.vertical, out_h, dst,
                                 ws.use_simd);
  }

  if (has_alpha) {
    for (std::size_t p = 0; p < out_pixels; ++p) {
      std::uint8_t* d = dst + p * channels;
      const unsigned alpha = d[channels - 1];
      for (int c = 0; c + 1 < channels; ++c) d[c] = pillow_unpremultiply(d[c], alpha);
    }
  }
}

// Convenience overload: returns a new interleaved buffer of out_w * out_h * channels bytes.
inline std::vector<std::uint8_t> resize_pillow_bicubic(std::span<const std::uint8_t> src, int in_w, int in_h,
                                                       int channels, int out_w, int out_h) {
  require(in_w >= 1 && in_h >= 1 && channels >= 1 &&
              src.size() == static_cast<std::size_t>(in_w) * static_cast<std::size_t>(in_h) *
                                static_cast<std::size_t>(channels),
          "resize_pillow_bicubic: buffer of ", src.size(), " bytes does not hold a ", in_w, "x", in_h, "x", channels,
          " image");
  require(out_w >= 1 && out_h >= 1, "resize_pillow_bicubic: height and width must be > 0 (requested ", out_w, "x",
          out_h, ")");
  std::vector<std::uint8_t> out(static_cast<std::size_t>(out_w) * out_h * channels);
  PillowResampleWorkspace ws;
  resize_pillow_bicubic(src.data(), in_w, in_h, channels, out.data(), out_w, out_h, ws);
  return out;
}

// ---------------------------------------------------------------------------------------------------------------
// PyTorch bicubic, antialias=True, align_corners=False, on planar floating-point data
// ---------------------------------------------------------------------------------------------------------------

// One axis of the antialiased interpolation: output i reads taps [first[i], first[i] + count[i]) with weights
// weights[i * max_taps + j], computed in T exactly as ATen's _compute_indices_min_size_weights_aa.
template <class T>
struct AntialiasAxisWeights {
  index_t max_taps = 0;
  std::vector<index_t> first, count;
  std::vector<T> weights;
};

// Source-to-output scale of one axis as ATen's area_pixel_compute_scale (align_corners=False): in/out computed in T,
// or 1/scale_factor when F.interpolate received scale_factor (without recompute_scale_factor).
template <class T>
inline T antialias_axis_scale(index_t in_size, index_t out_size, std::optional<double> scale_factor = std::nullopt) {
  if (scale_factor && *scale_factor > 0.0) return static_cast<T>(1.0 / *scale_factor);
  return static_cast<T>(in_size) / static_cast<T>(out_size);
}

template <class T>
inline void bicubic_antialias_weights(index_t in_size, index_t out_size, T scale, AntialiasAxisWeights<T>& w) {
  static_assert(std::is_floating_point_v<T>, "antialiased interpolation works on float or double");
  require(in_size >= 1 && out_size >= 1, "bicubic_antialias_weights: sizes must be positive (input ", in_size,
          ", output ", out_size, ")");
  require(std::isfinite(static_cast<double>(scale)) && scale > T(0), "bicubic_antialias_weights: invalid scale ",
          static_cast<double>(scale));
  constexpr int interp_size = 4;
  // The mixed float/double expressions below follow ATen's: its literals are double, its variables scalar_t.
  const T support = (scale >= 1.0) ? static_cast<T>((interp_size * 0.5) * scale) : static_cast<T>(interp_size * 0.5);
  w.max_taps = static_cast<index_t>(std::ceil(support)) * 2 + 1;
  w.first.assign(static_cast<std::size_t>(out_size), 0);
  w.count.assign(static_cast<std::size_t>(out_size), 0);
  w.weights.assign(static_cast<std::size_t>(out_size * w.max_taps), T(0));
  const T invscale = (scale >= 1.0) ? static_cast<T>(1.0 / scale) : T(1);
  for (index_t i = 0; i < out_size; ++i) {
    const T center = static_cast<T>(scale * (i + 0.5));
    const index_t xmin = std::max(static_cast<index_t>(center - support + 0.5), index_t{0});
    index_t xsize = std::min(static_cast<index_t>(center + support + 0.5), in_size) - xmin;
    xsize = std::clamp(xsize, index_t{0}, w.max_taps);
    T* wt = &w.weights[static_cast<std::size_t>(i * w.max_taps)];
    T total = T(0);
    for (index_t j = 0; j < xsize; ++j) {
      const T x = static_cast<T>((static_cast<T>(j + xmin) - center + 0.5) * invscale);
      wt[j] = keys_cubic_filter<T>(x);
      total += wt[j];
    }
    if (total != 0.0)
      for (index_t j = 0; j < xsize; ++j) wt[j] /= total;
    w.first[static_cast<std::size_t>(i)] = xmin;
    w.count[static_cast<std::size_t>(i)] = xsize;
  }
}

template <class T>
struct AntialiasWorkspace {
  AntialiasAxisWeights<T> horizontal, vertical;
  std::vector<T> temp;  // channels x in_h x out_w after the width pass
  bool use_simd = simd::enabled();
};

// Optional F.interpolate scale_factor per axis (None when the call passed size=, as VGGT's DINOv2 embedder does).
struct InterpolateScaleFactors {
  std::optional<double> height, width;
};

namespace detail {

template <class T>
inline void antialias_width_pass(const T* src, index_t planes_rows, index_t in_w, const AntialiasAxisWeights<T>& k,
                                 T* dst, index_t out_w) {
  parallel_for(planes_rows, [&](index_t begin, index_t end, int) {
    for (index_t r = begin; r < end; ++r) {
      const T* in_row = src + r * in_w;
      T* out_row = dst + r * out_w;
      for (index_t x = 0; x < out_w; ++x) {
        const index_t count = k.count[static_cast<std::size_t>(x)];
        if (count <= 0) {
          out_row[x] = T(0);
          continue;
        }
        const T* p = in_row + k.first[static_cast<std::size_t>(x)];
        const T* w = &k.weights[static_cast<std::size_t>(x * k.max_taps)];
        T acc = p[0] * w[0];
        for (index_t j = 1; j < count; ++j) acc += p[j] * w[j];
        out_row[x] = acc;
      }
    }
  });
}

template <class T>
inline void antialias_height_pass(const T* src, index_t planes, index_t in_h, index_t width,
                                  const AntialiasAxisWeights<T>& k, T* dst, index_t out_h, bool use_simd) {
  parallel_for(planes * out_h, [&](index_t begin, index_t end, int) {
    for (index_t pr = begin; pr < end; ++pr) {
      const index_t plane = pr / out_h, y = pr % out_h;
      const index_t count = k.count[static_cast<std::size_t>(y)];
      const T* base = src + (plane * in_h + k.first[static_cast<std::size_t>(y)]) * width;
      const T* w = &k.weights[static_cast<std::size_t>(y * k.max_taps)];
      T* out_row = dst + (plane * out_h + y) * width;
      if (count <= 0) {
        std::fill(out_row, out_row + width, T(0));
        continue;
      }
      index_t x = 0;
      if (use_simd) {
        using B = simd::batch<T>;
        constexpr index_t lanes = static_cast<index_t>(B::size);
        for (; x + lanes <= width; x += lanes) {
          B acc = B::load_unaligned(base + x) * B(w[0]);
          for (index_t j = 1; j < count; ++j) acc += B::load_unaligned(base + j * width + x) * B(w[j]);
          acc.store_unaligned(out_row + x);
        }
      }
      for (; x < width; ++x) {
        T acc = base[x] * w[0];
        for (index_t j = 1; j < count; ++j) acc += base[j * width + x] * w[j];
        out_row[x] = acc;
      }
    }
  });
}

}  // namespace detail

// F.interpolate(x, size=(out_h, out_w), mode="bicubic", antialias=True, align_corners=False) on planar data:
// src holds `channels` planes of in_h x in_w, dst receives `channels` planes of out_h x out_w (no aliasing).
// T = float reproduces PyTorch's float32 CPU kernel; T = double its float64 kernel.
template <class T>
inline void interpolate_bicubic_antialias(const T* src, index_t channels, index_t in_h, index_t in_w, T* dst,
                                          index_t out_h, index_t out_w, AntialiasWorkspace<T>& ws,
                                          const InterpolateScaleFactors& scale_factors = {}) {
  require(channels >= 1 && in_h >= 1 && in_w >= 1, "interpolate_bicubic_antialias: empty input [", channels, ", ",
          in_h, ", ", in_w, "]");
  require(out_h >= 1 && out_w >= 1, "interpolate_bicubic_antialias: output size (", out_h, ", ", out_w,
          ") must be positive");
  require(src != nullptr && dst != nullptr, "interpolate_bicubic_antialias: null buffer");
  if (in_h == out_h && in_w == out_w) {
    std::copy(src, src + channels * in_h * in_w, dst);
    return;
  }
  const bool need_width = in_w != out_w, need_height = in_h != out_h;
  const T* height_input = src;
  if (need_width) {
    bicubic_antialias_weights<T>(in_w, out_w, antialias_axis_scale<T>(in_w, out_w, scale_factors.width),
                                 ws.horizontal);
    T* width_out = dst;
    if (need_height) {
      ws.temp.resize(static_cast<std::size_t>(channels * in_h * out_w));
      width_out = ws.temp.data();
    }
    detail::antialias_width_pass<T>(src, channels * in_h, in_w, ws.horizontal, width_out, out_w);
    height_input = width_out;
  }
  if (need_height) {
    bicubic_antialias_weights<T>(in_h, out_h, antialias_axis_scale<T>(in_h, out_h, scale_factors.height),
                                 ws.vertical);
    detail::antialias_height_pass<T>(height_input, channels, in_h, out_w, ws.vertical, dst, out_h, ws.use_simd);
  }
}

// Tensor overload: input [C, H, W] (any strides), returns a contiguous [C, out_h, out_w].
template <class T>
inline Tensor<T, 3> interpolate_bicubic_antialias(TensorView<const T, 3> input, index_t out_h, index_t out_w,
                                                  const InterpolateScaleFactors& scale_factors = {}) {
  const Tensor<T, 3> contiguous = copy_of(input);
  Tensor<T, 3> out(Shape<3>{input.shape(0), out_h < 0 ? 0 : out_h, out_w < 0 ? 0 : out_w});
  AntialiasWorkspace<T> ws;
  interpolate_bicubic_antialias<T>(contiguous.data(), input.shape(0), input.shape(1), input.shape(2), out.data(),
                                   out_h, out_w, ws, scale_factors);
  return out;
}

}  // namespace v0
}  // namespace flexsplat
