#pragma once
// SSIM as 3D Gaussian Splatting's loss_utils.ssim() computes it (taken from Po-Hsun-Su/pytorch-ssim): an 11x11
// Gaussian window with sigma 1.5 applied per channel as a convolution with zero padding of 5, so the SSIM map has the
// image's size and border windows see zeros outside the image; C1 = (0.01 L)^2, C2 = (0.03 L)^2 with L the data range;
// the result is the mean of the map over batch, channels and pixels. (pytorch-msssim's ssim() differs: it uses only
// "valid" windows, a smaller map.) The window is separable, so the blur runs as two 1-D passes. Forward and backward
// in double; backward adds d_ssim * dSSIM/dx into the gradient buffers (+=).
#include <algorithm>
#include <cmath>
#include <vector>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/loss/image.hpp"

namespace flexsplat {
inline namespace v0 {
namespace loss {

struct SsimConfig {
  index_t window = 11;
  double sigma = 1.5;
  double k1 = 0.01, k2 = 0.03;
  double data_range = 1.0;
  void validate() const {
    require(window >= 1 && window % 2 == 1, "ssim: window ", window, " must be odd and positive");
    require(sigma > 0 && k1 > 0 && k2 > 0 && data_range > 0, "ssim: sigma ", sigma, ", k1 ", k1, ", k2 ", k2,
            " and data_range ", data_range, " must be positive");
  }
};

// The normalised 1-D Gaussian: w[i] proportional to exp(-(i - window/2)^2 / (2 sigma^2)).
inline std::vector<double> ssim_gaussian_window(const SsimConfig& c) {
  std::vector<double> w(static_cast<std::size_t>(c.window));
  double sum = 0;
  const index_t r = c.window / 2;
  for (index_t i = 0; i < c.window; ++i)
    sum += w[static_cast<std::size_t>(i)] = std::exp(-static_cast<double>((i - r) * (i - r)) / (2 * c.sigma * c.sigma));
  for (double& v : w) v /= sum;
  return w;
}

namespace ssim_detail {
// Same-size blur with zero padding: out[y][x] = sum_ij w[i] w[j] in[y + i - r][x + j - r]. Symmetric window, so the
// operator is its own adjoint.
inline void blur(double* out, const double* in, double* tmp, index_t h, index_t w, const std::vector<double>& k) {
  const index_t r = static_cast<index_t>(k.size()) / 2;
  for (index_t y = 0; y < h; ++y)
    for (index_t x = 0; x < w; ++x) {
      double s = 0;
      const index_t j0 = std::max<index_t>(0, r - x), j1 = std::min<index_t>(2 * r, w - 1 - x + r);
      for (index_t j = j0; j <= j1; ++j) s += k[static_cast<std::size_t>(j)] * in[y * w + x + j - r];
      tmp[y * w + x] = s;
    }
  for (index_t y = 0; y < h; ++y) {
    const index_t i0 = std::max<index_t>(0, r - y), i1 = std::min<index_t>(2 * r, h - 1 - y + r);
    for (index_t x = 0; x < w; ++x) {
      double s = 0;
      for (index_t i = i0; i <= i1; ++i) s += k[static_cast<std::size_t>(i)] * tmp[(y + i - r) * w + x];
      out[y * w + x] = s;
    }
  }
}

// Per-plane buffers: the two images, their blurred moments, and the backward's per-pixel partials.
struct Plane {
  std::vector<double> x, y, mx, my, exx, eyy, exy, tmp, prod, dmx, dmy, dsq, dxy;
  void resize(index_t n) {
    for (auto* v : {&x, &y, &mx, &my, &exx, &eyy, &exy, &tmp, &prod, &dmx, &dmy, &dsq, &dxy})
      v->resize(static_cast<std::size_t>(n));
  }
};

template <class T>
void moments(Plane& p, const T* a, const T* b, const ImageShape& s, index_t n, index_t c,
             const std::vector<double>& k) {
  const index_t h = s.height, w = s.width;
  for (index_t yy = 0; yy < h; ++yy)
    for (index_t xx = 0; xx < w; ++xx) {
      const index_t i = s.index(n, c, yy, xx);
      p.x[yy * w + xx] = static_cast<double>(a[i]);
      p.y[yy * w + xx] = static_cast<double>(b[i]);
    }
  blur(p.mx.data(), p.x.data(), p.tmp.data(), h, w, k);
  blur(p.my.data(), p.y.data(), p.tmp.data(), h, w, k);
  for (index_t i = 0; i < h * w; ++i) p.prod[i] = p.x[i] * p.x[i];
  blur(p.exx.data(), p.prod.data(), p.tmp.data(), h, w, k);
  for (index_t i = 0; i < h * w; ++i) p.prod[i] = p.y[i] * p.y[i];
  blur(p.eyy.data(), p.prod.data(), p.tmp.data(), h, w, k);
  for (index_t i = 0; i < h * w; ++i) p.prod[i] = p.x[i] * p.y[i];
  blur(p.exy.data(), p.prod.data(), p.tmp.data(), h, w, k);
}
}  // namespace ssim_detail

// Reusable buffers (one plane set per worker).
struct SsimWorkspace {
  std::vector<ssim_detail::Plane> planes;
};

// Mean SSIM of images a and b (same shape; nchw or nhwc). Loss use: 1 - ssim.
template <class T>
double ssim_forward(const T* a, const T* b, const ImageShape& s, const SsimConfig& c, SsimWorkspace& ws,
                    ThreadPool& pool = global_pool()) {
  s.validate("ssim");
  c.validate();
  require(a && b, "ssim: null image");
  const auto k = ssim_gaussian_window(c);
  const double C1 = (c.k1 * c.data_range) * (c.k1 * c.data_range), C2 = (c.k2 * c.data_range) * (c.k2 * c.data_range);
  const index_t planes = s.batch * s.channels, hw = s.height * s.width;
  ws.planes.resize(static_cast<std::size_t>(pool.size()));
  std::vector<double> sums(static_cast<std::size_t>(planes));
  parallel_for(planes, [&](index_t p0, index_t p1, int worker) {
    auto& p = ws.planes[static_cast<std::size_t>(worker)];
    p.resize(hw);
    for (index_t pl = p0; pl < p1; ++pl) {
      ssim_detail::moments(p, a, b, s, pl / s.channels, pl % s.channels, k);
      double sum = 0;
      for (index_t i = 0; i < hw; ++i) {
        const double mx = p.mx[i], my = p.my[i];
        const double a1 = 2 * mx * my + C1, a2 = 2 * (p.exy[i] - mx * my) + C2;
        const double b1 = mx * mx + my * my + C1, b2 = (p.exx[i] - mx * mx) + (p.eyy[i] - my * my) + C2;
        sum += (a1 * a2) / (b1 * b2);
      }
      sums[static_cast<std::size_t>(pl)] = sum;
    }
  }, pool);
  double total = 0;
  for (double v : sums) total += v;
  require(std::isfinite(total), "ssim: the images hold non-finite values");
  return total / static_cast<double>(planes * hw);
}

// Adds d_ssim * dSSIM/da into d_a and d_ssim * dSSIM/db into d_b (either may be null). With S the SSIM map,
// A1 = 2 mx my + C1, A2 = 2 sxy + C2, B1 = mx^2 + my^2 + C1, B2 = sxx + syy + C2 and g = d_ssim / count:
//   dS/dmx = (2 my (A2 - A1) - 2 mx S (B2 - B1)) / (B1 B2),  dS/dE[x^2] = -S B1 / (B1 B2),  dS/dE[xy] = 2 A1 / (B1 B2)
//   d_a = blur(g dS/dmx) + 2 a blur(g dS/dE[x^2]) + b blur(g dS/dE[xy])   (the blur is self-adjoint)
template <class T>
void ssim_backward(T* d_a, T* d_b, double d_ssim, const T* a, const T* b, const ImageShape& s, const SsimConfig& c,
                   SsimWorkspace& ws, ThreadPool& pool = global_pool()) {
  s.validate("ssim");
  c.validate();
  const auto k = ssim_gaussian_window(c);
  const double C1 = (c.k1 * c.data_range) * (c.k1 * c.data_range), C2 = (c.k2 * c.data_range) * (c.k2 * c.data_range);
  const index_t planes = s.batch * s.channels, hw = s.height * s.width;
  const double g = d_ssim / static_cast<double>(planes * hw);
  ws.planes.resize(static_cast<std::size_t>(pool.size()));
  parallel_for(planes, [&](index_t p0, index_t p1, int worker) {
    auto& p = ws.planes[static_cast<std::size_t>(worker)];
    p.resize(hw);
    double *dmx = p.dmx.data(), *dmy = p.dmy.data(), *dsq = p.dsq.data(), *dxy = p.dxy.data();
    for (index_t pl = p0; pl < p1; ++pl) {
      const index_t n = pl / s.channels, ch = pl % s.channels;
      ssim_detail::moments(p, a, b, s, n, ch, k);
      for (index_t i = 0; i < hw; ++i) {
        const double mx = p.mx[i], my = p.my[i];
        const double a1 = 2 * mx * my + C1, a2 = 2 * (p.exy[i] - mx * my) + C2;
        const double b1 = mx * mx + my * my + C1, b2 = (p.exx[i] - mx * mx) + (p.eyy[i] - my * my) + C2;
        const double d = b1 * b2, S = a1 * a2 / d;
        dmx[i] = g * (2 * my * (a2 - a1) - 2 * mx * S * (b2 - b1)) / d;
        dmy[i] = g * (2 * mx * (a2 - a1) - 2 * my * S * (b2 - b1)) / d;
        dsq[i] = -g * S * b1 / d;
        dxy[i] = g * 2 * a1 / d;
      }
      // Blur the partials in place (mx, my, exx, exy buffers are free now).
      ssim_detail::blur(p.mx.data(), dmx, p.tmp.data(), s.height, s.width, k);
      ssim_detail::blur(p.my.data(), dmy, p.tmp.data(), s.height, s.width, k);
      ssim_detail::blur(p.exx.data(), dsq, p.tmp.data(), s.height, s.width, k);
      ssim_detail::blur(p.exy.data(), dxy, p.tmp.data(), s.height, s.width, k);
      for (index_t yy = 0; yy < s.height; ++yy)
        for (index_t xx = 0; xx < s.width; ++xx) {
          const index_t i = yy * s.width + xx, o = s.index(n, ch, yy, xx);
          if (d_a) d_a[o] += static_cast<T>(p.mx[i] + 2 * p.x[i] * p.exx[i] + p.y[i] * p.exy[i]);
          if (d_b) d_b[o] += static_cast<T>(p.my[i] + 2 * p.y[i] * p.exx[i] + p.x[i] * p.exy[i]);
        }
    }
  }, pool);
}

}  // namespace loss
}  // namespace v0
}  // namespace flexsplat
