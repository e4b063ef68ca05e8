#pragma once
// LayerNorm over the last axis; the cache keeps per-row mean and reciprocal standard deviation for backward.
#include <cmath>

#include "flexsplat/core/parallel.hpp"

namespace flexsplat {
inline namespace v0 {
namespace nn {

template <class T>
struct LayerNormCache {
  T* mean = nullptr;  // [rows]
  T* rstd = nullptr;  // [rows]
};

// gamma/beta may be null (no affine part). cache pointers may be null when no backward follows.
template <class T>
void layernorm_forward(T* out, const T* in, const T* gamma, const T* beta, index_t rows, index_t dim, T eps,
                       LayerNormCache<T> cache = {}) {
  parallel_for(rows, [&](index_t r0, index_t r1, int) {
    for (index_t r = r0; r < r1; ++r) {
      const T* x = in + r * dim;
      T* y = out + r * dim;
      double sum = 0.0;
      for (index_t i = 0; i < dim; ++i) sum += x[i];
      const T mean = static_cast<T>(sum / static_cast<double>(dim));
      double sq = 0.0;
      for (index_t i = 0; i < dim; ++i) sq += double(x[i] - mean) * double(x[i] - mean);
      const T rstd = static_cast<T>(1.0 / std::sqrt(sq / static_cast<double>(dim) + static_cast<double>(eps)));
      for (index_t i = 0; i < dim; ++i) {
        const T n = (x[i] - mean) * rstd;
        y[i] = gamma ? n * gamma[i] + (beta ? beta[i] : T(0)) : n + (beta ? beta[i] : T(0));
      }
      if (cache.mean) cache.mean[r] = mean;
      if (cache.rstd) cache.rstd[r] = rstd;
    }
  });
}

// Adds into d_in, d_gamma, d_beta (each may be null). d_gamma/d_beta are summed over rows in a fixed order.
template <class T>
void layernorm_backward(T* d_in, T* d_gamma, T* d_beta, const T* d_out, const T* in, const T* gamma, index_t rows,
                        index_t dim, LayerNormCache<T> cache) {
  require(cache.mean && cache.rstd, "layernorm_backward needs the forward cache (mean, rstd)");
  for (index_t r = 0; r < rows; ++r) {
    const T* x = in + r * dim;
    const T* dy = d_out + r * dim;
    const T mean = cache.mean[r], rstd = cache.rstd[r];
    T sum_dn = 0, sum_dn_n = 0;
    for (index_t i = 0; i < dim; ++i) {
      const T n = (x[i] - mean) * rstd;
      const T dn = gamma ? dy[i] * gamma[i] : dy[i];
      sum_dn += dn;
      sum_dn_n += dn * n;
      if (d_gamma) d_gamma[i] += dy[i] * n;
      if (d_beta) d_beta[i] += dy[i];
    }
    if (!d_in) continue;
    const T inv_dim = T(1) / static_cast<T>(dim);
    for (index_t i = 0; i < dim; ++i) {
      const T n = (x[i] - mean) * rstd;
      const T dn = gamma ? dy[i] * gamma[i] : dy[i];
      d_in[r * dim + i] += rstd * (dn - inv_dim * sum_dn - n * inv_dim * sum_dn_n);
    }
  }
}

}  // namespace nn
}  // namespace v0
}  // namespace flexsplat
