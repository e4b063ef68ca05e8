#pragma once
// LayerNorm over the last axis; the cache keeps per-row mean and reciprocal standard deviation for backward.
// The row bodies are written against the lane helpers: V = T is the scalar reference (statistics summed in double),
// simd::batch<T> the build's batches and the dispatch vectors AVX2 / AVX-512 lanes in a portable build (statistics
// summed in T lanes, two passes); layernorm_forward / layernorm_backward take the widest (simd::best_lanes).
#include <algorithm>
#include <cmath>
#include <type_traits>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/simd.hpp"
#include "flexsplat/core/simd_dispatch.hpp"  // its lane overloads must be visible where the lane templates are used

namespace flexsplat {
inline namespace v0 {
namespace nn {

template <class T>
struct LayerNormCache {
  T* mean = nullptr;  // [rows]
  T* rstd = nullptr;  // [rows]
};

namespace detail {
// sum_i f(x[i]) over one row with lanes V (two accumulators), then the tail.
template <class V, class T, class F>
T layernorm_lane_sum(const T* x, index_t dim, F&& f) {
  constexpr index_t w = static_cast<index_t>(simd::lane_count<V>::value);
  V acc0(T(0)), acc1(T(0));
  index_t i = 0;
  for (; i + 2 * w <= dim; i += 2 * w) {
    acc0 += f(simd::lane_load<V>(x + i));
    acc1 += f(simd::lane_load<V>(x + i + w));
  }
  for (; i + w <= dim; i += w) acc0 += f(simd::lane_load<V>(x + i));
  T sum = simd::lane_sum(acc0 + acc1);
  for (; i < dim; ++i) sum += f(x[i]);
  return sum;
}

// Mean and 1 / sqrt(variance + eps) of one row.
template <class V, class T>
void layernorm_row_stats(const T* x, index_t dim, T eps, T& mean, T& rstd) {
  if constexpr (simd::lane_count<V>::value == 1) {
    double sum = 0.0;
    for (index_t i = 0; i < dim; ++i) sum += x[i];
    mean = static_cast<T>(sum / static_cast<double>(dim));
    double sq = 0.0;
    for (index_t i = 0; i < dim; ++i) sq += double(x[i] - mean) * double(x[i] - mean);
    rstd = static_cast<T>(1.0 / std::sqrt(sq / static_cast<double>(dim) + static_cast<double>(eps)));
  } else {
    const T m = layernorm_lane_sum<V>(x, dim, [](auto v) { return v; }) / static_cast<T>(dim);
    const V mv(m);
    const T sq = layernorm_lane_sum<V>(x, dim, [&](auto v) {
      if constexpr (std::is_same_v<decltype(v), T>) return (v - m) * (v - m);
      else return (v - mv) * (v - mv);
    });
    mean = m;
    rstd = static_cast<T>(1.0 / std::sqrt(static_cast<double>(sq) / static_cast<double>(dim) + static_cast<double>(eps)));
  }
}

// One row: statistics, then y = (x - mean) rstd gamma + beta (gamma, beta may be null). y may alias x.
template <class V, class T>
void layernorm_row(T* y, const T* x, const T* gamma, const T* beta, index_t dim, T eps, T& mean_out, T& rstd_out) {
  constexpr index_t w = static_cast<index_t>(simd::lane_count<V>::value);
  T mean, rstd;
  layernorm_row_stats<V>(x, dim, eps, mean, rstd);
  index_t i = 0;
  if constexpr (w > 1) {
    const V mv(mean), rv(rstd), zero(T(0)), one(T(1));
    for (; i + w <= dim; i += w) {
      const V n = (simd::lane_load<V>(x + i) - mv) * rv;
      const V g = gamma ? simd::lane_load<V>(gamma + i) : one;
      const V b = beta ? simd::lane_load<V>(beta + i) : zero;
      simd::lane_store(y + i, n * g + b);
    }
  }
  for (; i < dim; ++i) {
    const T n = (x[i] - mean) * rstd;
    y[i] = gamma ? n * gamma[i] + (beta ? beta[i] : T(0)) : n + (beta ? beta[i] : T(0));
  }
  mean_out = mean;
  rstd_out = rstd;
}

// d_in[i] += rstd (dn_i - mean(dn) - n_i mean(dn n)) of one row, dn = dy * gamma (gamma may be null).
template <class V, class T>
void layernorm_row_backward(T* d_in, const T* dy, const T* x, const T* gamma, index_t dim, T mean, T rstd) {
  constexpr index_t w = static_cast<index_t>(simd::lane_count<V>::value);
  T sum_dn = 0, sum_dn_n = 0;
  index_t i = 0;
  if constexpr (w > 1) {
    const V mv(mean), rv(rstd), one(T(1));
    V s0(T(0)), s1(T(0));
    for (; i + w <= dim; i += w) {
      const V n = (simd::lane_load<V>(x + i) - mv) * rv;
      const V dn = simd::lane_load<V>(dy + i) * (gamma ? simd::lane_load<V>(gamma + i) : one);
      s0 += dn;
      s1 += dn * n;
    }
    sum_dn = simd::lane_sum(s0);
    sum_dn_n = simd::lane_sum(s1);
  }
  for (; i < dim; ++i) {
    const T n = (x[i] - mean) * rstd;
    const T dn = gamma ? dy[i] * gamma[i] : dy[i];
    sum_dn += dn;
    sum_dn_n += dn * n;
  }
  const T inv_dim = T(1) / static_cast<T>(dim);
  const T a = inv_dim * sum_dn, b = inv_dim * sum_dn_n;
  i = 0;
  if constexpr (w > 1) {
    const V mv(mean), rv(rstd), one(T(1)), av(a), bv(b);
    for (; i + w <= dim; i += w) {
      const V n = (simd::lane_load<V>(x + i) - mv) * rv;
      const V dn = simd::lane_load<V>(dy + i) * (gamma ? simd::lane_load<V>(gamma + i) : one);
      simd::lane_store(d_in + i, simd::lane_load<V>(d_in + i) + rv * (dn - av - n * bv));
    }
  }
  for (; i < dim; ++i) {
    const T n = (x[i] - mean) * rstd;
    const T dn = gamma ? dy[i] * gamma[i] : dy[i];
    d_in[i] += rstd * (dn - a - n * b);
  }
}

// d_gamma[j] += sum_r dy[r, j] n[r, j], d_beta[j] += sum_r dy[r, j] for columns [c0, c1), rows in order.
template <class V, class T>
void layernorm_columns_backward(T* d_gamma, T* d_beta, const T* d_out, const T* in, index_t rows, index_t dim,
                                const T* mean, const T* rstd, index_t c0, index_t c1) {
  constexpr index_t w = static_cast<index_t>(simd::lane_count<V>::value);
  for (index_t r = 0; r < rows; ++r) {
    const T* x = in + r * dim;
    const T* dy = d_out + r * dim;
    index_t j = c0;
    if constexpr (w > 1) {
      const V mv(mean[r]), rv(rstd[r]);
      for (; j + w <= c1; j += w) {
        const V d = simd::lane_load<V>(dy + j);
        if (d_gamma)
          simd::lane_store(d_gamma + j, simd::lane_load<V>(d_gamma + j) + d * ((simd::lane_load<V>(x + j) - mv) * rv));
        if (d_beta) simd::lane_store(d_beta + j, simd::lane_load<V>(d_beta + j) + d);
      }
    }
    for (; j < c1; ++j) {
      if (d_gamma) d_gamma[j] += dy[j] * ((x[j] - mean[r]) * rstd[r]);
      if (d_beta) d_beta[j] += dy[j];
    }
  }
}

inline constexpr index_t layernorm_column_block = 64;
}  // namespace detail

// gamma/beta may be null (no affine part). cache pointers may be null when no backward follows. `lanes` selects the
// path (tests run each).
template <class T>
void layernorm_forward_impl(T* out, const T* in, const T* gamma, const T* beta, index_t rows, index_t dim, T eps,
                            LayerNormCache<T> cache, simd::Lanes lanes, ThreadPool& pool = global_pool()) {
  parallel_for(rows, [&](index_t r0, index_t r1, int) {
    simd::with_lanes<T>(lanes, [&](auto* lane_type) {
      using V = std::remove_pointer_t<decltype(lane_type)>;
      for (index_t r = r0; r < r1; ++r) {
        T mean, rstd;
        detail::layernorm_row<V>(out + r * dim, in + r * dim, gamma, beta, dim, eps, mean, rstd);
        if (cache.mean) cache.mean[r] = mean;
        if (cache.rstd) cache.rstd[r] = rstd;
      }
    });
  }, pool);
}

// Adds into d_in, d_gamma, d_beta (each may be null). Rows in parallel for d_in; d_gamma / d_beta in parallel over
// column blocks, each column summed over rows in order (the same sums for any thread count).
template <class T>
void layernorm_backward_impl(T* d_in, T* d_gamma, T* d_beta, const T* d_out, const T* in, const T* gamma, index_t rows,
                             index_t dim, LayerNormCache<T> cache, simd::Lanes lanes, ThreadPool& pool = global_pool()) {
  require(cache.mean && cache.rstd, "layernorm_backward needs the forward cache (mean, rstd)");
  if (d_gamma || d_beta) {
    constexpr index_t cb = detail::layernorm_column_block;
    parallel_for((dim + cb - 1) / cb, [&](index_t b0, index_t b1, int) {
      simd::with_lanes<T>(lanes, [&](auto* lane_type) {
        detail::layernorm_columns_backward<std::remove_pointer_t<decltype(lane_type)>>(
            d_gamma, d_beta, d_out, in, rows, dim, cache.mean, cache.rstd, b0 * cb, std::min(dim, b1 * cb));
      });
    }, pool);
  }
  if (!d_in) return;
  parallel_for(rows, [&](index_t r0, index_t r1, int) {
    simd::with_lanes<T>(lanes, [&](auto* lane_type) {
      using V = std::remove_pointer_t<decltype(lane_type)>;
      for (index_t r = r0; r < r1; ++r)
        detail::layernorm_row_backward<V>(d_in + r * dim, d_out + r * dim, in + r * dim, gamma, dim, cache.mean[r],
                                          cache.rstd[r]);
    });
  }, pool);
}

template <class T>
void layernorm_forward(T* out, const T* in, const T* gamma, const T* beta, index_t rows, index_t dim, T eps,
                       LayerNormCache<T> cache = {}) {
  layernorm_forward_impl(out, in, gamma, beta, rows, dim, eps, cache, simd::best_lanes<T>());
}

template <class T>
void layernorm_backward(T* d_in, T* d_gamma, T* d_beta, const T* d_out, const T* in, const T* gamma, index_t rows,
                        index_t dim, LayerNormCache<T> cache) {
  layernorm_backward_impl(d_in, d_gamma, d_beta, d_out, in, gamma, rows, dim, cache, simd::best_lanes<T>());
}

}  // namespace nn
}  // namespace v0
}  // namespace flexsplat
