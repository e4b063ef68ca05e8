#pragma once
// Image losses with forward and backward: masked MSE (the FlexSplat objective's lambda_E and lambda_D terms), masked
// L1 (per-scene fitting as 3DGS), the confidence-weighted L1 between rendered and predicted depth, and PSNR (a metric,
// no backward). Backward adds d_loss * dL/dx into the gradient buffers (+=); any gradient pointer may be null.
// Accumulation is in double.
#include <cmath>
#include <limits>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {
namespace loss {

enum class Layout {
  nchw,  // [batch, channels, height, width]: the decoder's and UNet's images
  nhwc,  // [batch, height, width, channels]: the rasterizer's images
};

struct ImageShape {
  index_t batch = 1, channels = 3, height = 0, width = 0;
  Layout layout = Layout::nchw;

  index_t pixels() const { return batch * height * width; }
  index_t numel() const { return pixels() * channels; }
  index_t index(index_t n, index_t c, index_t y, index_t x) const {
    return layout == Layout::nchw ? ((n * channels + c) * height + y) * width + x
                                  : ((n * height + y) * width + x) * channels + c;
  }
  void validate(const char* what) const {
    require(batch >= 1 && channels >= 1 && height >= 1 && width >= 1, what, ": image shape [", batch, ", ", channels,
            ", ", height, ", ", width, "] has a zero or negative extent");
  }
};

namespace detail {
// Sum of mask weights; they must be finite and >= 0.
template <class T>
double mask_sum(const T* mask, index_t pixels, const char* what) {
  if (!mask) return static_cast<double>(pixels);
  double s = 0;
  for (index_t p = 0; p < pixels; ++p) {
    const double m = static_cast<double>(mask[p]);
    if (!(std::isfinite(m) && m >= 0)) fail(what, ": mask value ", m, " at pixel ", p, " (must be finite and >= 0)");
    s += m;
  }
  return s;
}

// Calls f(i, m) for every element index i of s with the mask weight m of its pixel (1 without a mask).
template <class T, class F>
void for_each_weighted(const T* mask, const ImageShape& s, F&& f) {
  for (index_t n = 0; n < s.batch; ++n)
    for (index_t y = 0; y < s.height; ++y)
      for (index_t x = 0; x < s.width; ++x) {
        const double m = mask ? static_cast<double>(mask[(n * s.height + y) * s.width + x]) : 1.0;
        for (index_t c = 0; c < s.channels; ++c) f(s.index(n, c, y, x), m);
      }
}
}  // namespace detail

// Mean of (pred - target)^2 over pixels and channels; mask (may be null) [batch, height, width] weights each pixel:
// sum_p m_p sum_c (pred - target)^2 / (channels * sum_p m_p). An all-zero mask gives 0 (and zero gradients).
template <class T>
double mse_forward(const T* pred, const T* target, const T* mask, const ImageShape& s) {
  s.validate("mse");
  require(pred && target, "mse: null image");
  const double weight = detail::mask_sum(mask, s.pixels(), "mse");
  if (weight == 0) return 0.0;
  double sum = 0;
  detail::for_each_weighted(mask, s, [&](index_t i, double m) {
    const double d = static_cast<double>(pred[i]) - static_cast<double>(target[i]);
    sum += m * d * d;
  });
  return sum / (weight * static_cast<double>(s.channels));
}

// Adds d_loss * dL/dpred into d_pred and d_loss * dL/dtarget into d_target (either may be null).
template <class T>
void mse_backward(T* d_pred, T* d_target, double d_loss, const T* pred, const T* target, const T* mask,
                  const ImageShape& s) {
  s.validate("mse");
  const double weight = detail::mask_sum(mask, s.pixels(), "mse");
  if (weight == 0) return;
  const double scale = 2.0 * d_loss / (weight * static_cast<double>(s.channels));
  detail::for_each_weighted(mask, s, [&](index_t i, double m) {
    const double g = scale * m * (static_cast<double>(pred[i]) - static_cast<double>(target[i]));
    if (d_pred) d_pred[i] += static_cast<T>(g);
    if (d_target) d_target[i] -= static_cast<T>(g);
  });
}

// Mean of |pred - target| over pixels and channels with the same mask convention as mse_forward (3DGS's L1 term).
template <class T>
double l1_forward(const T* pred, const T* target, const T* mask, const ImageShape& s) {
  s.validate("l1");
  require(pred && target, "l1: null image");
  const double weight = detail::mask_sum(mask, s.pixels(), "l1");
  if (weight == 0) return 0.0;
  double sum = 0;
  detail::for_each_weighted(mask, s, [&](index_t i, double m) {
    sum += m * std::abs(static_cast<double>(pred[i]) - static_cast<double>(target[i]));
  });
  return sum / (weight * static_cast<double>(s.channels));
}

// Adds into d_pred and d_target (either may be null); sign(0) = 0.
template <class T>
void l1_backward(T* d_pred, T* d_target, double d_loss, const T* pred, const T* target, const T* mask,
                 const ImageShape& s) {
  s.validate("l1");
  const double weight = detail::mask_sum(mask, s.pixels(), "l1");
  if (weight == 0) return;
  const double scale = d_loss / (weight * static_cast<double>(s.channels));
  detail::for_each_weighted(mask, s, [&](index_t i, double m) {
    const double d = static_cast<double>(pred[i]) - static_cast<double>(target[i]);
    const double g = scale * m * ((d > 0) - (d < 0));
    if (d_pred) d_pred[i] += static_cast<T>(g);
    if (d_target) d_target[i] -= static_cast<T>(g);
  });
}

// 10 log10(max_value^2 / MSE) over n values; +infinity for identical images.
template <class T>
double psnr(const T* a, const T* b, index_t n, double max_value = 1.0) {
  require(a && b && n >= 1, "psnr: empty or null images");
  require(max_value > 0, "psnr: max_value ", max_value, " must be positive");
  double sum = 0;
  for (index_t i = 0; i < n; ++i) {
    const double d = static_cast<double>(a[i]) - static_cast<double>(b[i]);
    sum += d * d;
  }
  require(std::isfinite(sum), "psnr: the images hold non-finite values");
  if (sum == 0) return std::numeric_limits<double>::infinity();
  return 10.0 * std::log10(max_value * max_value / (sum / static_cast<double>(n)));
}

// FlexSplat's depth term: mean over pixels of |(D_rendered - D_vggt) * U|, with U the depth head's confidence
// (>= 0) and mask (may be null) weighting pixels as in mse_forward. Both depths stay in the gradient path; U is a
// constant (no gradient): with U differentiable the loss would simply drive it to zero, and unlike VGGT's own depth
// loss there is no -alpha log U term to stop that. All arrays are [pixels].
template <class T>
double depth_l1_forward(const T* rendered, const T* vggt_depth, const T* confidence, const T* mask, index_t pixels) {
  require(rendered && vggt_depth && confidence && pixels >= 1, "depth L1: null or empty depth maps");
  const double weight = detail::mask_sum(mask, pixels, "depth L1");
  if (weight == 0) return 0.0;
  double sum = 0;
  for (index_t p = 0; p < pixels; ++p) {
    const double u = static_cast<double>(confidence[p]);
    if (!(std::isfinite(u) && u >= 0)) fail("depth L1: confidence ", u, " at pixel ", p, " (must be finite and >= 0)");
    const double m = mask ? static_cast<double>(mask[p]) : 1.0;
    sum += m * u * std::abs(static_cast<double>(rendered[p]) - static_cast<double>(vggt_depth[p]));
  }
  return sum / weight;
}

// Adds into d_rendered and d_vggt_depth (either may be null); sign(0) = 0 as PyTorch's abs.
template <class T>
void depth_l1_backward(T* d_rendered, T* d_vggt_depth, double d_loss, const T* rendered, const T* vggt_depth,
                       const T* confidence, const T* mask, index_t pixels) {
  const double weight = detail::mask_sum(mask, pixels, "depth L1");
  if (weight == 0) return;
  for (index_t p = 0; p < pixels; ++p) {
    const double d = static_cast<double>(rendered[p]) - static_cast<double>(vggt_depth[p]);
    const double m = mask ? static_cast<double>(mask[p]) : 1.0;
    const double g = d_loss * m * static_cast<double>(confidence[p]) * ((d > 0) - (d < 0)) / weight;
    if (d_rendered) d_rendered[p] += static_cast<T>(g);
    if (d_vggt_depth) d_vggt_depth[p] -= static_cast<T>(g);
  }
}

}  // namespace loss
}  // namespace v0
}  // namespace flexsplat
