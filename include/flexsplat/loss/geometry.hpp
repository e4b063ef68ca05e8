#pragma once
// Supervised geometry losses for pre-training on data with ground truth, with the semantics of VGGT's
// training/loss.py (compute_camera_loss, compute_depth_loss with gradient_loss_fn "grad"):
//   camera: per refinement stage, mean |pred - gt| (or Huber, as the VGGT paper) over the translation (3, each term
//           clamped at 100), quaternion (4) and FoV (2) parts of the absT_quaR_FoV encoding of the valid frames;
//           stage i of n weighted gamma^(n-1-i); averaged over stages; total = w_T L_T + w_R L_R + w_FL L_FL.
//   depth:  conf = mean(gamma |d - d_gt| c - alpha log c), reg = mean |d - d_gt| over valid pixels, grad = the
//           multi-scale finite-difference term (4 scales, subsampling by 2^s): per scale the sum over horizontal and
//           vertical neighbour pairs, both valid, of |Δ(d - d_gt)| (each clamped at 100) divided by the number of valid
//           pixels; averaged over scales. total = conf + reg + grad (VGGT adds all three).
// Not reproduced: VGGT's quantile outlier filter (valid_range 0.98) and its NaN-to-zero repair; non-finite inputs are an
// error here. Backward adds d_loss * dL/dx (+=); |x| has derivative sign(x) with sign(0) = 0, a clamped term none.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "flexsplat/core/camera.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {
namespace loss {

enum class CameraLossType { l1, huber };

struct CameraLossConfig {
  CameraLossType type = CameraLossType::l1;  // VGGT's training code; the paper states Huber
  double huber_delta = 1.0;                  // PyTorch smooth_l1 beta: 0.5 x^2 / delta below delta, |x| - delta/2 above
  double gamma = 0.6;                        // stage weight gamma^(n-1-i)
  double weight_translation = 1.0, weight_rotation = 1.0, weight_fov = 0.5;
  double translation_clamp = 100.0;
};

struct CameraLossParts {
  double total = 0, translation = 0, rotation = 0, fov = 0;
};

namespace camera_detail {
inline double penalty(double x, const CameraLossConfig& c) {
  const double a = std::abs(x);
  if (c.type == CameraLossType::l1) return a;
  return a < c.huber_delta ? 0.5 * x * x / c.huber_delta : a - 0.5 * c.huber_delta;
}
inline double penalty_grad(double x, const CameraLossConfig& c) {
  if (c.type == CameraLossType::huber && std::abs(x) < c.huber_delta) return x / c.huber_delta;
  return (x > 0) - (x < 0);
}
inline index_t valid_count(const std::uint8_t* valid, index_t frames) {
  if (!valid) return frames;
  index_t n = 0;
  for (index_t f = 0; f < frames; ++f) n += valid[f] != 0;
  return n;
}
}  // namespace camera_detail

// stages: n pointers to [frames, 9] pose encodings (the camera head's iterations, last = final); gt [frames, 9];
// valid (may be null): per-frame flag (VGGT: frames with more than 100 valid depth pixels). No valid frame: 0.
template <class T>
CameraLossParts camera_loss_forward(const std::vector<const T*>& stages, const T* gt, const std::uint8_t* valid,
                                    index_t frames, const CameraLossConfig& c) {
  require(!stages.empty() && gt && frames >= 1, "camera loss: no stages, no ground truth or no frames");
  require(c.huber_delta > 0 && c.gamma > 0, "camera loss: huber_delta ", c.huber_delta, " and gamma ", c.gamma,
          " must be positive");
  CameraLossParts out;
  const index_t nv = camera_detail::valid_count(valid, frames);
  if (nv == 0) return out;
  const index_t n = static_cast<index_t>(stages.size());
  for (index_t s = 0; s < n; ++s) {
    const double ws = std::pow(c.gamma, static_cast<double>(n - 1 - s)) / static_cast<double>(n);
    double lt = 0, lr = 0, lf = 0;
    for (index_t f = 0; f < frames; ++f) {
      if (valid && !valid[f]) continue;
      for (index_t k = 0; k < 9; ++k) {
        const double p = static_cast<double>(stages[static_cast<std::size_t>(s)][f * 9 + k]);
        const double g = static_cast<double>(gt[f * 9 + k]);
        if (!(std::isfinite(p) && std::isfinite(g)))
          fail("camera loss: stage ", s, " frame ", f, " entry ", k, ": prediction ", p, ", ground truth ", g);
        const double e = camera_detail::penalty(p - g, c);
        if (k < 3) lt += std::min(e, c.translation_clamp);
        else if (k < 7) lr += e;
        else lf += e;
      }
    }
    out.translation += ws * lt / static_cast<double>(3 * nv);
    out.rotation += ws * lr / static_cast<double>(4 * nv);
    out.fov += ws * lf / static_cast<double>(2 * nv);
  }
  out.total = c.weight_translation * out.translation + c.weight_rotation * out.rotation + c.weight_fov * out.fov;
  return out;
}

// Adds d_total * d(total)/d(stage) into d_stages (entries may be null).
template <class T>
void camera_loss_backward(const std::vector<T*>& d_stages, double d_total, const std::vector<const T*>& stages,
                          const T* gt, const std::uint8_t* valid, index_t frames, const CameraLossConfig& c) {
  require(d_stages.size() == stages.size(), "camera loss: ", d_stages.size(), " gradient buffers for ",
          stages.size(), " stages");
  const index_t nv = camera_detail::valid_count(valid, frames);
  if (nv == 0) return;
  const index_t n = static_cast<index_t>(stages.size());
  for (index_t s = 0; s < n; ++s) {
    T* d = d_stages[static_cast<std::size_t>(s)];
    if (!d) continue;
    const double ws = d_total * std::pow(c.gamma, static_cast<double>(n - 1 - s)) / static_cast<double>(n);
    for (index_t f = 0; f < frames; ++f) {
      if (valid && !valid[f]) continue;
      for (index_t k = 0; k < 9; ++k) {
        const double x = static_cast<double>(stages[static_cast<std::size_t>(s)][f * 9 + k]) -
                         static_cast<double>(gt[f * 9 + k]);
        double w;
        if (k < 3) {
          if (camera_detail::penalty(x, c) >= c.translation_clamp) continue;  // clamped: no gradient
          w = c.weight_translation / static_cast<double>(3 * nv);
        } else if (k < 7) {
          w = c.weight_rotation / static_cast<double>(4 * nv);
        } else {
          w = c.weight_fov / static_cast<double>(2 * nv);
        }
        d[f * 9 + k] += static_cast<T>(ws * w * camera_detail::penalty_grad(x, c));
      }
    }
  }
}

// Smooths the relative pose loss's chordal distance at 0, where its gradient would be undefined.
inline constexpr double relative_pose_eps = 1e-6;

namespace camera_detail {
// Pair (i, j) of a stage and of the ground truth in double: the cameras and their relative transforms.
template <class T>
struct RelativePair {
  double pi[12], pj[12], rp[12], rg[12];
  RelativePair(const T* p, const T* gt, index_t i, index_t j) {
    double gi[12], gj[12];
    for (int k = 0; k < 12; ++k)
      pi[k] = p[12 * i + k], pj[k] = p[12 * j + k], gi[k] = gt[12 * i + k], gj[k] = gt[12 * j + k];
    relative_w2c(rp, pi, pj);
    relative_w2c(rg, gi, gj);
  }
  double rotation_sq() const {  // |dR|_F^2
    double sq = 0;
    for (int r = 0; r < 3; ++r)
      for (int col = 0; col < 3; ++col) sq += (rp[4 * r + col] - rg[4 * r + col]) * (rp[4 * r + col] - rg[4 * r + col]);
    return sq;
  }
};
}  // namespace camera_detail

// Relative pose loss over every ordered pair of views (Pi3's supervision, blind to the world frame): per stage, with
// rel = w2c_i w2c_j^-1 of the prediction and of the ground truth, the chordal rotation distance sqrt(|dR|_F^2 +
// eps^2) - eps (linear in the angle near 0, so an L1 of the rotation) and the penalty of c over the translation's 3
// entries (each clamped at translation_clamp), means over the V (V - 1) pairs; stages weighted as the camera loss.
// stages: n pointers to [frames, 3, 4] world-to-camera extrinsics; gt [frames, 3, 4]. Fewer than 2 frames: 0.
template <class T>
CameraLossParts relative_pose_loss_forward(const std::vector<const T*>& stages, const T* gt, index_t frames,
                                           const CameraLossConfig& c) {
  require(!stages.empty() && gt && frames >= 1, "relative pose loss: no stages, no ground truth or no frames");
  require(c.huber_delta > 0 && c.gamma > 0, "relative pose loss: huber_delta ", c.huber_delta, " and gamma ", c.gamma,
          " must be positive");
  CameraLossParts out;
  if (frames < 2) return out;
  const index_t n = static_cast<index_t>(stages.size());
  const double pairs = static_cast<double>(frames * (frames - 1)), eps = relative_pose_eps;
  for (index_t s = 0; s < n; ++s) {
    const T* p = stages[static_cast<std::size_t>(s)];
    for (index_t k = 0; k < 12 * frames; ++k)
      if (!(std::isfinite(static_cast<double>(p[k])) && std::isfinite(static_cast<double>(gt[k]))))
        fail("relative pose loss: stage ", s, " frame ", k / 12, " entry ", k % 12, ": prediction ",
             static_cast<double>(p[k]), ", ground truth ", static_cast<double>(gt[k]));
    const double ws = std::pow(c.gamma, static_cast<double>(n - 1 - s)) / static_cast<double>(n);
    double lt = 0, lr = 0;
    for (index_t i = 0; i < frames; ++i)
      for (index_t j = 0; j < frames; ++j) {
        if (i == j) continue;
        camera_detail::RelativePair<T> q(p, gt, i, j);
        const double sq = q.rotation_sq(), *rp = q.rp, *rg = q.rg;
        lr += std::sqrt(sq + eps * eps) - eps;
        for (int r = 0; r < 3; ++r)
          lt += std::min(camera_detail::penalty(rp[4 * r + 3] - rg[4 * r + 3], c), c.translation_clamp);
      }
    out.translation += ws * lt / (3 * pairs);
    out.rotation += ws * lr / pairs;
  }
  out.total = c.weight_translation * out.translation + c.weight_rotation * out.rotation;
  return out;
}

// Adds d_total * d(total)/d(stage) into d_stages [frames, 3, 4] (entries may be null).
template <class T>
void relative_pose_loss_backward(const std::vector<T*>& d_stages, double d_total, const std::vector<const T*>& stages,
                                 const T* gt, index_t frames, const CameraLossConfig& c) {
  require(d_stages.size() == stages.size(), "relative pose loss: ", d_stages.size(), " gradient buffers for ",
          stages.size(), " stages");
  if (frames < 2) return;
  const index_t n = static_cast<index_t>(stages.size());
  const double pairs = static_cast<double>(frames * (frames - 1)), eps = relative_pose_eps;
  for (index_t s = 0; s < n; ++s) {
    T* d = d_stages[static_cast<std::size_t>(s)];
    if (!d) continue;
    const T* p = stages[static_cast<std::size_t>(s)];
    const double ws = d_total * std::pow(c.gamma, static_cast<double>(n - 1 - s)) / static_cast<double>(n);
    std::vector<double> acc(static_cast<std::size_t>(12 * frames), 0.0);
    for (index_t i = 0; i < frames; ++i)
      for (index_t j = 0; j < frames; ++j) {
        if (i == j) continue;
        camera_detail::RelativePair<T> q(p, gt, i, j);
        const double sq = q.rotation_sq(), *rp = q.rp, *rg = q.rg;
        double drel[12] = {};
        const double wr = ws * c.weight_rotation / pairs / std::sqrt(sq + eps * eps);
        for (int r = 0; r < 3; ++r) {
          for (int col = 0; col < 3; ++col) drel[4 * r + col] = wr * (rp[4 * r + col] - rg[4 * r + col]);
          const double x = rp[4 * r + 3] - rg[4 * r + 3];
          if (camera_detail::penalty(x, c) < c.translation_clamp)
            drel[4 * r + 3] = ws * c.weight_translation / (3 * pairs) * camera_detail::penalty_grad(x, c);
        }
        relative_w2c_backward(acc.data() + 12 * i, acc.data() + 12 * j, drel, q.pi, q.pj);
      }
    for (index_t k = 0; k < 12 * frames; ++k) d[k] += static_cast<T>(acc[static_cast<std::size_t>(k)]);
  }
}

struct DepthLossConfig {
  double gamma = 1.0, alpha = 0.2;  // VGGT's regression_loss defaults
  bool gradient_term = true;        // gradient_loss_fn "grad"
  index_t gradient_scales = 4;      // gradient_loss_multi_scale_wrapper's default
  double gradient_clamp = 100.0;
  index_t min_valid_pixels = 100;   // fewer valid pixels: the loss is 0 (VGGT skips the batch)
};

struct DepthLossParts {
  double total = 0, conf = 0, reg = 0, grad = 0;
};

namespace depth_detail {
// Calls f(i, j) for every horizontal and vertical neighbour pair (flat indices) of the grid subsampled by `step`
// whose both ends are valid, and returns the number of valid pixels of that grid.
template <class F>
index_t for_each_pair(const std::uint8_t* mask, index_t images, index_t h, index_t w, index_t step, F&& f) {
  index_t valid = 0;
  auto ok = [&](index_t i) { return !mask || mask[i] != 0; };
  for (index_t n = 0; n < images; ++n)
    for (index_t y = 0; y < h; y += step)
      for (index_t x = 0; x < w; x += step) {
        const index_t i = (n * h + y) * w + x;
        if (!ok(i)) continue;
        ++valid;
        if (x + step < w && ok(i + step)) f(i, i + step);
        if (y + step < h && ok(i + step * w)) f(i, i + step * w);
      }
  return valid;
}
}  // namespace depth_detail

// pred, conf, gt: [images, h, w]; mask (may be null: all valid) [images, h, w]. conf must be > 0 at valid pixels
// (VGGT's depth confidence is 1 + exp(x) >= 1).
template <class T>
DepthLossParts depth_loss_forward(const T* pred, const T* conf, const T* gt, const std::uint8_t* mask, index_t images,
                                  index_t h, index_t w, const DepthLossConfig& c) {
  require(pred && conf && gt && images >= 1 && h >= 1 && w >= 1, "depth loss: null or empty maps");
  require(c.gradient_scales >= 1, "depth loss: gradient_scales ", c.gradient_scales, " must be >= 1");
  const index_t total = images * h * w;
  DepthLossParts out;
  index_t valid = 0;
  for (index_t i = 0; i < total; ++i) {
    if (mask && !mask[i]) continue;
    const double p = static_cast<double>(pred[i]), g = static_cast<double>(gt[i]), u = static_cast<double>(conf[i]);
    if (!(std::isfinite(p) && std::isfinite(g) && std::isfinite(u) && u > 0))
      fail("depth loss: pixel ", i, ": depth ", p, ", ground truth ", g, ", confidence ", u,
           " (finite values and a positive confidence needed)");
    const double e = std::abs(p - g);
    out.reg += e;
    out.conf += c.gamma * e * u - c.alpha * std::log(u);
    ++valid;
  }
  if (valid < std::max<index_t>(c.min_valid_pixels, 1)) return {};
  out.reg /= static_cast<double>(valid);
  out.conf /= static_cast<double>(valid);
  if (c.gradient_term) {
    for (index_t s = 0; s < c.gradient_scales; ++s) {
      double sum = 0;
      const index_t m = depth_detail::for_each_pair(mask, images, h, w, index_t{1} << s, [&](index_t i, index_t j) {
        const double d = (static_cast<double>(pred[j]) - static_cast<double>(gt[j])) -
                         (static_cast<double>(pred[i]) - static_cast<double>(gt[i]));
        sum += std::min(std::abs(d), c.gradient_clamp);
      });
      if (m > 0) out.grad += sum / static_cast<double>(m);
    }
    out.grad /= static_cast<double>(c.gradient_scales);
  }
  out.total = out.conf + out.reg + out.grad;
  return out;
}

// Adds d_total * d(total)/d(pred) into d_pred and d_total * d(total)/d(conf) into d_conf (either may be null).
template <class T>
void depth_loss_backward(T* d_pred, T* d_conf, double d_total, const T* pred, const T* conf, const T* gt,
                         const std::uint8_t* mask, index_t images, index_t h, index_t w, const DepthLossConfig& c) {
  const index_t total = images * h * w;
  index_t valid = 0;
  for (index_t i = 0; i < total; ++i) valid += !mask || mask[i];
  if (valid < std::max<index_t>(c.min_valid_pixels, 1)) return;
  const double inv = d_total / static_cast<double>(valid);
  for (index_t i = 0; i < total; ++i) {
    if (mask && !mask[i]) continue;
    const double e = static_cast<double>(pred[i]) - static_cast<double>(gt[i]), u = static_cast<double>(conf[i]);
    const double sg = (e > 0) - (e < 0);
    if (d_pred) d_pred[i] += static_cast<T>(inv * sg * (c.gamma * u + 1.0));
    if (d_conf) d_conf[i] += static_cast<T>(inv * (c.gamma * std::abs(e) - c.alpha / u));
  }
  if (!c.gradient_term || !d_pred) return;
  for (index_t s = 0; s < c.gradient_scales; ++s) {
    const index_t step = index_t{1} << s;
    const index_t m = depth_detail::for_each_pair(mask, images, h, w, step, [](index_t, index_t) {});
    if (m == 0) continue;
    const double scale = d_total / (static_cast<double>(m) * static_cast<double>(c.gradient_scales));
    depth_detail::for_each_pair(mask, images, h, w, step, [&](index_t i, index_t j) {
      const double d = (static_cast<double>(pred[j]) - static_cast<double>(gt[j])) -
                       (static_cast<double>(pred[i]) - static_cast<double>(gt[i]));
      if (std::abs(d) >= c.gradient_clamp) return;
      const double g = scale * ((d > 0) - (d < 0));
      d_pred[j] += static_cast<T>(g);
      d_pred[i] -= static_cast<T>(g);
    });
  }
}

// Depth error after each view's scale (a metric, no gradient): per view, the median (the upper of two middles) of
// gt / pred over the pixels with gt > 0 scales pred, then mean |scale pred - gt| / gt over them; the mean over the
// views with such pixels (0 without one). scales (may be null, [views]): each view's scale, 1 for a view without.
// A constant pred gives a flat depth's error.
template <class T>
double depth_scaled_error(const T* pred, const T* gt, index_t views, index_t pixels, double* scales = nullptr) {
  double total = 0;
  index_t counted = 0;
  std::vector<double> ratio;
  for (index_t v = 0; v < views; ++v) {
    const T *p = pred + v * pixels, *g = gt + v * pixels;
    ratio.clear();
    for (index_t i = 0; i < pixels; ++i)
      if (g[i] > T(0)) {
        require(p[i] > T(0) && std::isfinite(static_cast<double>(p[i])), "depth_scaled_error: predicted depth ",
                static_cast<double>(p[i]), " at pixel ", v * pixels + i, " (view ", v, ") is not a positive number");
        ratio.push_back(static_cast<double>(g[i]) / static_cast<double>(p[i]));
      }
    if (scales) scales[v] = 1;
    if (ratio.empty()) continue;
    std::nth_element(ratio.begin(), ratio.begin() + static_cast<std::ptrdiff_t>(ratio.size() / 2), ratio.end());
    const double scale = ratio[ratio.size() / 2];
    if (scales) scales[v] = scale;
    double err = 0;
    for (index_t i = 0; i < pixels; ++i)
      if (g[i] > T(0)) err += std::abs(scale * static_cast<double>(p[i]) - static_cast<double>(g[i])) / static_cast<double>(g[i]);
    total += err / static_cast<double>(ratio.size());
    ++counted;
  }
  return counted > 0 ? total / static_cast<double>(counted) : 0.0;
}

// Depth shape loss: the per-view relative shape of the depth map, blind to each view's scale (which the view's
// distance absorbs when cameras are solved from depth: solvers/orbit_search.hpp). Per image with at least
// min_valid_pixels valid pixels, r = log d - log d_gt, L = mean |r - mean r| over its valid pixels; total = mean of L
// over those images (0 without one). The absolute depth loss's L1 gradient is sign(d - d_gt): while a view's scale is
// off, every pixel has the same sign and the shape gets no signal from it; this term's gradient is the shape's alone.
namespace detail {
// Image n's residuals r = log d - log d_gt over its valid pixels, in pixel order (the forward and backward share them).
template <class T>
void depth_shape_residuals(std::vector<double>& r, const T* pred, const T* gt, const std::uint8_t* mask, index_t n,
                           index_t px) {
  r.clear();
  for (index_t i = n * px; i < (n + 1) * px; ++i) {
    if (mask && !mask[i]) continue;
    const double p = static_cast<double>(pred[i]), g = static_cast<double>(gt[i]);
    if (!(std::isfinite(p) && std::isfinite(g) && p > 0 && g > 0))
      fail("depth shape loss: pixel ", i, ": depth ", p, ", ground truth ", g, " (finite positive values needed)");
    r.push_back(std::log(p) - std::log(g));
  }
}
}  // namespace detail

template <class T>
double depth_shape_loss_forward(const T* pred, const T* gt, const std::uint8_t* mask, index_t images, index_t h,
                                index_t w, index_t min_valid_pixels = 100) {
  require(pred && gt && images >= 1 && h >= 1 && w >= 1, "depth shape loss: null or empty maps");
  const index_t px = h * w;
  double total = 0;
  index_t counted = 0;
  std::vector<double> r;
  for (index_t n = 0; n < images; ++n) {
    detail::depth_shape_residuals(r, pred, gt, mask, n, px);
    if (static_cast<index_t>(r.size()) < std::max<index_t>(min_valid_pixels, 1)) continue;
    double mean = 0;
    for (const double x : r) mean += x;
    mean /= static_cast<double>(r.size());
    double l = 0;
    for (const double x : r) l += std::abs(x - mean);
    total += l / static_cast<double>(r.size());
    ++counted;
  }
  return counted > 0 ? total / static_cast<double>(counted) : 0.0;
}

// Adds d_total * d(total)/d(pred) into d_pred.
template <class T>
void depth_shape_loss_backward(T* d_pred, double d_total, const T* pred, const T* gt, const std::uint8_t* mask,
                               index_t images, index_t h, index_t w, index_t min_valid_pixels = 100) {
  require(d_pred && pred && gt && images >= 1 && h >= 1 && w >= 1, "depth shape loss backward: null or empty maps");
  const index_t px = h * w, least = std::max<index_t>(min_valid_pixels, 1);
  // An image's residual count is its mask's count (every masked-in pixel is one or an error).
  auto valid = [&](index_t n) {
    if (!mask) return px;
    return static_cast<index_t>(std::count_if(mask + n * px, mask + (n + 1) * px, [](std::uint8_t m) { return m != 0; }));
  };
  index_t counted = 0;
  for (index_t n = 0; n < images; ++n) counted += valid(n) >= least;
  if (counted == 0) return;
  const double per_image = d_total / static_cast<double>(counted);
  std::vector<double> r;
  for (index_t n = 0; n < images; ++n) {
    detail::depth_shape_residuals(r, pred, gt, mask, n, px);
    if (static_cast<index_t>(r.size()) < least) continue;
    const double m = static_cast<double>(r.size());
    double mean = 0, mean_sign = 0;
    for (const double x : r) mean += x;
    mean /= m;
    for (const double x : r) mean_sign += (x > mean) - (x < mean);
    mean_sign /= m;
    // dL/dr_i = (sign(r_i - mean) - mean_j sign(r_j - mean)) / m, dr_i/dd_i = 1 / d_i.
    std::size_t j = 0;
    for (index_t i = n * px; i < (n + 1) * px; ++i) {
      if (mask && !mask[i]) continue;
      const double x = r[j++], sg = (x > mean) - (x < mean);
      d_pred[i] += static_cast<T>(per_image * (sg - mean_sign) / m / static_cast<double>(pred[i]));
    }
  }
}

// Point-map loss (VGGT's regression loss on its point head): per valid pixel e = |pred - gt| (Euclidean, 3-vectors),
// conf = mean(gamma e c - alpha log c), reg = mean e; VGGT's normal-based gradient term is not reproduced. background:
// weight of mean(c - 1) over the invalid pixels, which drives their confidence to its floor of 1 so that a camera
// solved from the map (solvers/procrustes.hpp) ignores them. total = conf + reg + background term.
struct PointLossConfig {
  double gamma = 1.0, alpha = 0.2;
  double background = 0.1;
  index_t min_valid_pixels = 100;  // fewer valid pixels: the loss is 0
};

struct PointLossParts {
  double total = 0, conf = 0, reg = 0, background = 0;
};

// pred, gt: [n, 3]; conf [n] (> 0 where valid); mask [n] (null: all valid).
template <class T>
PointLossParts point_loss_forward(const T* pred, const T* conf, const T* gt, const std::uint8_t* mask, index_t n,
                                  const PointLossConfig& c) {
  require(pred && conf && gt && n >= 1, "point loss: null or empty maps");
  PointLossParts out;
  index_t valid = 0, background = 0;
  for (index_t i = 0; i < n; ++i) {
    const double u = static_cast<double>(conf[i]);
    if (mask && !mask[i]) {
      require(std::isfinite(u), "point loss: background pixel ", i, " has confidence ", u);
      out.background += u - 1.0;
      ++background;
      continue;
    }
    double e2 = 0;
    for (int k = 0; k < 3; ++k) {
      const double p = static_cast<double>(pred[3 * i + k]), g = static_cast<double>(gt[3 * i + k]);
      if (!(std::isfinite(p) && std::isfinite(g)))
        fail("point loss: pixel ", i, " coordinate ", k, ": prediction ", p, ", ground truth ", g);
      e2 += (p - g) * (p - g);
    }
    if (!(std::isfinite(u) && u > 0)) fail("point loss: pixel ", i, " has confidence ", u, " (positive needed)");
    const double e = std::sqrt(e2);
    out.reg += e;
    out.conf += c.gamma * e * u - c.alpha * std::log(u);
    ++valid;
  }
  if (valid < std::max<index_t>(c.min_valid_pixels, 1)) return {};
  out.reg /= static_cast<double>(valid);
  out.conf /= static_cast<double>(valid);
  out.background = background > 0 ? c.background * out.background / static_cast<double>(background) : 0.0;
  out.total = out.conf + out.reg + out.background;
  return out;
}

// Adds d_total * d(total)/d(pred) into d_pred and d_total * d(total)/d(conf) into d_conf (either may be null).
template <class T>
void point_loss_backward(T* d_pred, T* d_conf, double d_total, const T* pred, const T* conf, const T* gt,
                         const std::uint8_t* mask, index_t n, const PointLossConfig& c) {
  index_t valid = 0;
  for (index_t i = 0; i < n; ++i) valid += !mask || mask[i];
  if (valid < std::max<index_t>(c.min_valid_pixels, 1)) return;
  const index_t background = n - valid;
  const double inv = d_total / static_cast<double>(valid);
  const double inv_bg = background > 0 ? d_total * c.background / static_cast<double>(background) : 0.0;
  for (index_t i = 0; i < n; ++i) {
    if (mask && !mask[i]) {
      if (d_conf) d_conf[i] += static_cast<T>(inv_bg);
      continue;
    }
    double diff[3], e2 = 0;
    for (int k = 0; k < 3; ++k) {
      diff[k] = static_cast<double>(pred[3 * i + k]) - static_cast<double>(gt[3 * i + k]);
      e2 += diff[k] * diff[k];
    }
    const double e = std::sqrt(e2), u = static_cast<double>(conf[i]);
    if (d_pred && e > 0)
      for (int k = 0; k < 3; ++k) d_pred[3 * i + k] += static_cast<T>(inv * (c.gamma * u + 1.0) * diff[k] / e);
    if (d_conf) d_conf[i] += static_cast<T>(inv * (c.gamma * e - c.alpha / u));
  }
}

}  // namespace loss
}  // namespace v0
}  // namespace flexsplat
