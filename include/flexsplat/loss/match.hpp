#pragma once
// The match head's losses. match: for each ground-truth correspondence (view a pixel p sees the surface point view b
// sees at pixel q), InfoNCE over every pixel k of view b with unit-length descriptors n:
//   s_k = <n_a(p), n_b(k)> / temperature,   loss = logsumexp_k s_k - s_q,
// averaged over the correspondences. foreground: binary cross-entropy of the per-pixel object probability against
// the object's alpha, averaged over all pixels (probabilities clamped to [1e-6, 1 - 1e-6], no gradient outside).
// total = match + foreground_weight * foreground. Backward adds d_total * d(total)/d(x) (+=).
#include <algorithm>
#include <cmath>
#include <limits>
#include <span>
#include <type_traits>
#include <vector>

#include "flexsplat/core/camera.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/core/gemm.hpp"
#include "flexsplat/core/simd.hpp"
#include "flexsplat/core/simd_dispatch.hpp"
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {
namespace loss {

struct PixelMatch {
  index_t view_a = 0, pixel_a = 0, view_b = 0, pixel_b = 0;  // pixels as y * width + x
};

struct MatchLossConfig {
  double temperature = 0.1;
  double foreground_weight = 1.0;
};

struct MatchLossParts {
  double total = 0, match = 0, foreground = 0;
};

namespace match_detail {
inline constexpr double prob_floor = 1e-6;

// Unit-length copies of every descriptor ([n, D], in T for the products) and their norms (double).
template <class T>
void normalize(const T* desc, index_t n, index_t D, std::vector<T>& unit, std::vector<double>& norm) {
  unit.resize(static_cast<std::size_t>(n * D));
  norm.resize(static_cast<std::size_t>(n));
  for (index_t i = 0; i < n; ++i) {
    double s = 0;
    for (index_t d = 0; d < D; ++d) s += static_cast<double>(desc[i * D + d]) * static_cast<double>(desc[i * D + d]);
    const double r = std::sqrt(s + 1e-12);
    norm[static_cast<std::size_t>(i)] = r;
    for (index_t d = 0; d < D; ++d) unit[static_cast<std::size_t>(i * D + d)] = static_cast<T>(static_cast<double>(desc[i * D + d]) / r);
  }
}

inline void check(const PixelMatch& m, index_t views, index_t px) {
  require(m.view_a >= 0 && m.view_a < views && m.view_b >= 0 && m.view_b < views && m.pixel_a >= 0 &&
              m.pixel_a < px && m.pixel_b >= 0 && m.pixel_b < px,
          "match loss: correspondence (view ", m.view_a, " pixel ", m.pixel_a, ") -> (view ", m.view_b, " pixel ",
          m.pixel_b, ") is outside ", views, " views of ", px, " pixels");
}

// row[k] = exp(row[k] - t) for k < n (V's lanes, then scalar); returns their sum, added in double in k order on
// every path (the paths differ only by exp's rounding).
template <class V, class T>
double exp_shifted_sum(T* row, index_t n, T t) {
  constexpr index_t width = static_cast<index_t>(simd::lane_count<V>::value);
  index_t k = 0;
  if constexpr (width > 1) {
    const V tv(t);
    for (; k + width <= n; k += width) simd::lane_store(row + k, simd::lane_exp(simd::lane_load<V>(row + k) - tv));
  }
  for (; k < n; ++k) row[k] = std::exp(row[k] - t);
  double acc = 0;
  for (index_t i = 0; i < n; ++i) acc += static_cast<double>(row[i]);
  return acc;
}

// Calls f(first, count, q, e, top, sum, picked) for each run of consecutive matches sharing (view_a, view_b): q
// [count, D] their view-a unit descriptors; e [count, px] exp(s - top) of their logits s against every pixel of view b
// (one GEMM per run); per row the maximum logit top, sum of e, and the logit at the true pixel, picked.
template <class T, class F>
void for_each_run(const std::vector<T>& unit, std::span<const PixelMatch> matches, index_t views, index_t px, index_t D,
                  double temperature, simd::Lanes lanes, F&& f) {
  std::vector<T> q, e;
  std::vector<double> top, sum, picked;
  for (std::size_t i0 = 0; i0 < matches.size();) {
    std::size_t i1 = i0;
    while (i1 < matches.size() && matches[i1].view_a == matches[i0].view_a && matches[i1].view_b == matches[i0].view_b) {
      check(matches[i1], views, px);
      ++i1;
    }
    const index_t n = static_cast<index_t>(i1 - i0), vb = matches[i0].view_b;
    q.resize(static_cast<std::size_t>(n * D));
    for (index_t r = 0; r < n; ++r) {
      const PixelMatch& m = matches[i0 + static_cast<std::size_t>(r)];
      std::copy_n(unit.data() + (m.view_a * px + m.pixel_a) * D, D, q.data() + r * D);
    }
    e.resize(static_cast<std::size_t>(n * px));
    gemm(Trans::no, Trans::yes, n, px, D, static_cast<T>(1 / temperature), q.data(), D, unit.data() + vb * px * D, D,
         T(0), e.data(), px);
    top.resize(static_cast<std::size_t>(n)), sum.resize(static_cast<std::size_t>(n)), picked.resize(static_cast<std::size_t>(n));
    simd::with_lanes<T>(lanes, [&](auto* lane_type) {
      using V = std::remove_pointer_t<decltype(lane_type)>;
      for (index_t r = 0; r < n; ++r) {
        T* row = e.data() + r * px;
        T t = row[0];
        for (index_t k = 1; k < px; ++k) t = std::max(t, row[k]);
        picked[static_cast<std::size_t>(r)] = static_cast<double>(row[matches[i0 + static_cast<std::size_t>(r)].pixel_b]);
        top[static_cast<std::size_t>(r)] = static_cast<double>(t);
        sum[static_cast<std::size_t>(r)] = exp_shifted_sum<V>(row, px, t);
      }
    });
    f(i0, n, q, e, top, sum, picked);
    i0 = i1;
  }
}
}  // namespace match_detail

// For each correspondence, the pixel of view_b whose descriptor is most similar (cosine, as the loss's logits) to
// pixel_a's; the first of equal maxima. desc [V, h * w, D]. One pass serves every radius and subset (match_hits).
template <class T>
std::vector<index_t> nearest_descriptor_pixels(const T* desc, std::span<const PixelMatch> matches, index_t views,
                                               index_t h, index_t w, index_t D) {
  require(desc && views >= 1 && h >= 1 && w >= 1 && D >= 1, "match accuracy: null or empty descriptors");
  std::vector<index_t> nearest(matches.size(), 0);
  if (matches.empty()) return nearest;
  const index_t px = h * w;
  std::vector<T> unit;
  std::vector<double> norm;
  match_detail::normalize(desc, views * px, D, unit, norm);
  // Scalar lanes: std::exp gives exactly 1 at the maximum, which the search below looks for.
  match_detail::for_each_run(unit, matches, views, px, D, 1.0, simd::Lanes::scalar,
                             [&](std::size_t i0, index_t n, const std::vector<T>&, const std::vector<T>& e,
                                 const std::vector<double>&, const std::vector<double>&, const std::vector<double>&) {
                               for (index_t r = 0; r < n; ++r) {
                                 const T* row = e.data() + r * px;  // exp(logit - max): exactly 1 at the maximum
                                 nearest[i0 + static_cast<std::size_t>(r)] = std::find(row, row + px, T(1)) - row;
                               }
                             });
  return nearest;
}

// Whether pixels a and b of an image w pixels wide lie within `radius` pixels of each other on both axes.
inline bool within_pixels(index_t a, index_t b, index_t w, index_t radius) {
  return std::abs(a % w - b % w) <= radius && std::abs(a / w - b / w) <= radius;
}

// How many correspondences have their nearest pixel (nearest_descriptor_pixels, same order) within `radius` pixels of
// pixel_b; images w pixels wide.
inline double match_hits(std::span<const index_t> nearest, std::span<const PixelMatch> matches, index_t w,
                         index_t radius = 1) {
  require(radius >= 0, "match accuracy: radius ", radius, " is negative");
  require(nearest.size() == matches.size(), "match accuracy: ", nearest.size(), " nearest pixels for ", matches.size(),
          " correspondences");
  double hits = 0;
  for (std::size_t i = 0; i < matches.size(); ++i) hits += within_pixels(nearest[i], matches[i].pixel_b, w, radius);
  return hits;
}

// The fraction of correspondences whose most similar descriptor among all pixels of view_b lies within `radius`
// pixels (default one), both axes, of pixel_b. desc [V, h * w, D].
template <class T>
double match_accuracy(const T* desc, std::span<const PixelMatch> matches, index_t views, index_t h, index_t w, index_t D,
                      index_t radius = 1) {
  const double hits = match_hits(nearest_descriptor_pixels(desc, matches, views, h, w, D), matches, w, radius);
  return matches.empty() ? 0 : hits / static_cast<double>(matches.size());
}

// desc [V, px, D]; prob [V, px] in (0, 1); alpha [V, px] in [0, 1]. `lanes`: the exp's path (tests run each).
template <class T>
MatchLossParts match_loss_forward(const T* desc, const T* prob, const T* alpha, std::span<const PixelMatch> matches,
                                  index_t views, index_t px, index_t D, const MatchLossConfig& c,
                                  simd::Lanes lanes = simd::best_lanes<T>()) {
  require(desc && prob && alpha && views >= 1 && px >= 1 && D >= 1, "match loss: null or empty maps");
  require(c.temperature > 0 && c.foreground_weight >= 0, "match loss: temperature ", c.temperature,
          " must be positive and foreground_weight ", c.foreground_weight, " non-negative");
  std::vector<T> unit;
  std::vector<double> norm;
  match_detail::normalize(desc, views * px, D, unit, norm);
  for (double r : norm) require(std::isfinite(r), "match loss: a descriptor is not finite");
  MatchLossParts out;
  match_detail::for_each_run(unit, matches, views, px, D, c.temperature, lanes,
                             [&](std::size_t, index_t n, const std::vector<T>&, const std::vector<T>&,
                                 const std::vector<double>& top, const std::vector<double>& sum,
                                 const std::vector<double>& picked) {
                               for (std::size_t r = 0; r < static_cast<std::size_t>(n); ++r)
                                 out.match += top[r] + std::log(sum[r]) - picked[r];
                             });
  if (!matches.empty()) out.match /= static_cast<double>(matches.size());
  for (index_t i = 0; i < views * px; ++i) {
    const double p = std::clamp(static_cast<double>(prob[i]), match_detail::prob_floor, 1 - match_detail::prob_floor);
    const double a = static_cast<double>(alpha[i]);
    require(std::isfinite(p) && std::isfinite(a), "match loss: pixel ", i, " has probability ", static_cast<double>(prob[i]),
            " and alpha ", a);
    out.foreground -= a * std::log(p) + (1 - a) * std::log(1 - p);
  }
  out.foreground /= static_cast<double>(views * px);
  out.total = out.match + c.foreground_weight * out.foreground;
  return out;
}

// Adds d_total * d(total)/d(desc) into d_desc and d_total * d(total)/d(prob) into d_prob (either may be null).
template <class T>
void match_loss_backward(T* d_desc, T* d_prob, double d_total, const T* desc, const T* prob, const T* alpha,
                         std::span<const PixelMatch> matches, index_t views, index_t px, index_t D,
                         const MatchLossConfig& c, simd::Lanes lanes = simd::best_lanes<T>()) {
  if (d_desc && !matches.empty()) {
    std::vector<T> unit, d_unit(static_cast<std::size_t>(views * px * D), T(0)), g, dq;
    std::vector<double> norm;
    match_detail::normalize(desc, views * px, D, unit, norm);
    const double scale = d_total / static_cast<double>(matches.size()) / c.temperature;
    match_detail::for_each_run(
        unit, matches, views, px, D, c.temperature, lanes,
        [&](std::size_t i0, index_t n, const std::vector<T>& q, const std::vector<T>& e, const std::vector<double>&,
            const std::vector<double>& sum, const std::vector<double>&) {
          // g = (softmax - one-hot) x scale; d q = g B_b, d B_b += g^T q.
          g.resize(static_cast<std::size_t>(n * px));
          for (index_t r = 0; r < n; ++r) {
            const T w = static_cast<T>(scale / sum[static_cast<std::size_t>(r)]);
            for (index_t k = 0; k < px; ++k) g[static_cast<std::size_t>(r * px + k)] = e[static_cast<std::size_t>(r * px + k)] * w;
            g[static_cast<std::size_t>(r * px + matches[i0 + static_cast<std::size_t>(r)].pixel_b)] -= static_cast<T>(scale);
          }
          const index_t vb = matches[i0].view_b;
          dq.resize(static_cast<std::size_t>(n * D));
          gemm(Trans::no, Trans::no, n, D, px, T(1), g.data(), px, unit.data() + vb * px * D, D, T(0), dq.data(), D);
          gemm(Trans::yes, Trans::no, px, D, n, T(1), g.data(), px, q.data(), D, T(1), d_unit.data() + vb * px * D, D);
          for (index_t r = 0; r < n; ++r) {
            const PixelMatch& m = matches[i0 + static_cast<std::size_t>(r)];
            T* da = d_unit.data() + (m.view_a * px + m.pixel_a) * D;
            for (index_t d = 0; d < D; ++d) da[d] += dq[static_cast<std::size_t>(r * D + d)];
          }
        });
    // Through the normalisation: d f = (d n - n <n, d n>) / |f|.
    for (index_t i = 0; i < views * px; ++i) {
      const T* n = unit.data() + i * D;
      const T* dn = d_unit.data() + i * D;
      double proj = 0;
      for (index_t d = 0; d < D; ++d) proj += static_cast<double>(n[d]) * static_cast<double>(dn[d]);
      for (index_t d = 0; d < D; ++d)
        d_desc[i * D + d] += static_cast<T>((static_cast<double>(dn[d]) - static_cast<double>(n[d]) * proj) /
                                            norm[static_cast<std::size_t>(i)]);
    }
  }
  if (d_prob && c.foreground_weight > 0) {
    const double scale = d_total * c.foreground_weight / static_cast<double>(views * px);
    for (index_t i = 0; i < views * px; ++i) {
      const double p = static_cast<double>(prob[i]), a = static_cast<double>(alpha[i]);
      if (p < match_detail::prob_floor || p > 1 - match_detail::prob_floor) continue;  // clamped: no gradient
      d_prob[i] += static_cast<T>(scale * (p - a) / (p * (1 - p)));
    }
  }
}

// Ground-truth correspondences of V views of one scene: for each ordered pair (a, b), a != b, up to `per_pair` pixels
// of view a (evenly spaced among the candidates) whose surface point lands inside view b on a pixel showing the same
// surface (its depth within `tolerance` of the point's relative depth: not occluded). depth [V, h, w] camera z (0:
// background); K [V, 3, 3] with pixel centres at +0.5; w2c [V, 3, 4].
template <class T>
std::vector<PixelMatch> ground_truth_matches(const T* depth, const T* K, const T* w2c, index_t views, index_t h,
                                             index_t w, index_t per_pair, double tolerance = 0.03) {
  std::vector<PixelMatch> out;
  const index_t px = h * w;
  std::vector<index_t> hit;
  std::vector<index_t> target;
  for (index_t a = 0; a < views; ++a)
    for (index_t b = 0; b < views; ++b) {
      if (a == b) continue;
      hit.clear(), target.clear();
      const Camera ca = camera_from_arrays(K + 9 * a, w2c + 12 * a, static_cast<int>(w), static_cast<int>(h));
      const Camera cb = camera_from_arrays(K + 9 * b, w2c + 12 * b, static_cast<int>(w), static_cast<int>(h));
      for (index_t p = 0; p < px; ++p) {
        const double z = static_cast<double>(depth[a * px + p]);
        if (!(z > 0)) continue;
        const glm::dvec2 centre{static_cast<double>(p % w) + 0.5, static_cast<double>(p / w) + 0.5};
        const glm::dvec3 seen = cb.to_camera(ca.to_world(ca.unproject(centre, z)));
        if (!(seen.z > 0)) continue;
        const glm::dvec2 uv = cb.project(seen);
        const double u = uv.x, v = uv.y;
        if (!(u >= 0 && v >= 0 && u < static_cast<double>(w) && v < static_cast<double>(h))) continue;
        const index_t q = static_cast<index_t>(v) * w + static_cast<index_t>(u);
        const double zb = static_cast<double>(depth[b * px + q]);
        if (!(zb > 0) || std::abs(zb - seen.z) > tolerance * seen.z) continue;
        hit.push_back(p), target.push_back(q);
      }
      const index_t n = static_cast<index_t>(hit.size()), take = std::min(n, per_pair);
      for (index_t i = 0; i < take; ++i) {
        const index_t at = i * n / take;
        out.push_back({a, hit[static_cast<std::size_t>(at)], b, target[static_cast<std::size_t>(at)]});
      }
    }
  return out;
}

}  // namespace loss
}  // namespace v0
}  // namespace flexsplat
