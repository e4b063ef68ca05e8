#pragma once
// Small vector kernels on raw pointers, each with a scalar path and an xsimd path (selected by simd::enabled()).
// The scalar path is the reference the tests compare against; both are deterministic for a given input.
#include <cmath>
#include <limits>

#include <xsimd/xsimd.hpp>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/simd.hpp"
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {
namespace simd {

// ---- dot: sum_i a[i] * b[i]
template <class T>
T dot_scalar(const T* a, const T* b, index_t n) noexcept {
  T sum = 0;
  for (index_t i = 0; i < n; ++i) sum += a[i] * b[i];
  return sum;
}

template <class T>
T dot_simd(const T* a, const T* b, index_t n) noexcept {
  using B = batch<T>;
  constexpr index_t w = static_cast<index_t>(B::size);
  // Four independent accumulators hide the FMA latency; summed in a fixed order.
  B acc0(T(0)), acc1(T(0)), acc2(T(0)), acc3(T(0));
  index_t i = 0;
  for (; i + 4 * w <= n; i += 4 * w) {
    acc0 = xsimd::fma(B::load_unaligned(a + i), B::load_unaligned(b + i), acc0);
    acc1 = xsimd::fma(B::load_unaligned(a + i + w), B::load_unaligned(b + i + w), acc1);
    acc2 = xsimd::fma(B::load_unaligned(a + i + 2 * w), B::load_unaligned(b + i + 2 * w), acc2);
    acc3 = xsimd::fma(B::load_unaligned(a + i + 3 * w), B::load_unaligned(b + i + 3 * w), acc3);
  }
  for (; i + w <= n; i += w) acc0 = xsimd::fma(B::load_unaligned(a + i), B::load_unaligned(b + i), acc0);
  T sum = reduce_add((acc0 + acc1) + (acc2 + acc3));
  for (; i < n; ++i) sum += a[i] * b[i];
  return sum;
}

template <class T>
T dot(const T* a, const T* b, index_t n) noexcept {
  return enabled() ? dot_simd(a, b, n) : dot_scalar(a, b, n);
}

// ---- axpy: y[i] += alpha * x[i]
template <class T>
void axpy_scalar(index_t n, T alpha, const T* x, T* y) noexcept {
  for (index_t i = 0; i < n; ++i) y[i] += alpha * x[i];
}

template <class T>
void axpy_simd(index_t n, T alpha, const T* x, T* y) noexcept {
  using B = batch<T>;
  constexpr index_t w = static_cast<index_t>(B::size);
  const B a(alpha);
  index_t i = 0;
  for (; i + w <= n; i += w) xsimd::fma(a, B::load_unaligned(x + i), B::load_unaligned(y + i)).store_unaligned(y + i);
  for (; i < n; ++i) y[i] += alpha * x[i];
}

template <class T>
void axpy(index_t n, T alpha, const T* x, T* y) noexcept {
  if (enabled()) axpy_simd(n, alpha, x, y);
  else axpy_scalar(n, alpha, x, y);
}

// ---- softmax of one row, in place: y = exp(x - max) / sum.
// A row of only -inf (fully masked) becomes all zeros; NaN or +inf anywhere is an error.
namespace detail {
template <class T>
void softmax_finish(T* row, index_t n, T max, T sum) {
  require(!std::isnan(sum) && max != std::numeric_limits<T>::infinity(), "softmax row of ", n,
          " values contains NaN or +inf");
  if (max == -std::numeric_limits<T>::infinity()) {
    for (index_t i = 0; i < n; ++i) row[i] = T(0);
    return;
  }
  const T inv = T(1) / sum;
  for (index_t i = 0; i < n; ++i) row[i] *= inv;
}
}  // namespace detail

template <class T>
void softmax_row_scalar(T* row, index_t n) {
  if (n <= 0) return;
  T max = row[0];
  bool nan = false;
  for (index_t i = 0; i < n; ++i) {
    nan = nan || std::isnan(row[i]);
    max = row[i] > max ? row[i] : max;
  }
  if (nan) max = std::numeric_limits<T>::quiet_NaN();
  T sum = 0;
  if (max != -std::numeric_limits<T>::infinity())
    for (index_t i = 0; i < n; ++i) sum += (row[i] = std::exp(row[i] - max));
  detail::softmax_finish(row, n, max, sum);
}

template <class T>
void softmax_row_simd(T* row, index_t n) {
  if (n <= 0) return;
  using B = batch<T>;
  constexpr index_t w = static_cast<index_t>(B::size);
  index_t i = 0;
  B vmax(-std::numeric_limits<T>::infinity());
  auto nan_seen = B(T(0)) != B(T(0));
  for (; i + w <= n; i += w) {
    const B x = B::load_unaligned(row + i);
    nan_seen = nan_seen || xsimd::isnan(x);
    vmax = xsimd::max(vmax, x);
  }
  T max = reduce_max(vmax);
  bool nan = xsimd::any(nan_seen);
  for (; i < n; ++i) {
    nan = nan || std::isnan(row[i]);
    max = row[i] > max ? row[i] : max;
  }
  if (nan) max = std::numeric_limits<T>::quiet_NaN();
  T sum = 0;
  if (max != -std::numeric_limits<T>::infinity()) {
    const B m(max);
    B vsum(T(0));
    for (i = 0; i + w <= n; i += w) {
      const B e = lane_exp(B::load_unaligned(row + i) - m);
      e.store_unaligned(row + i);
      vsum += e;
    }
    sum = reduce_add(vsum);
    for (; i < n; ++i) sum += (row[i] = std::exp(row[i] - max));
  }
  detail::softmax_finish(row, n, max, sum);
}

template <class T>
void softmax_row(T* row, index_t n) {
  if (enabled()) softmax_row_simd(row, n);
  else softmax_row_scalar(row, n);
}

// ---- softmax backward for one row: dx[i] += y[i] * (dy[i] - sum_j y[j] dy[j]).
template <class T>
void softmax_row_backward_scalar(const T* y, const T* dy, T* dx, index_t n) noexcept {
  const T inner = dot_scalar(y, dy, n);
  for (index_t i = 0; i < n; ++i) dx[i] += y[i] * (dy[i] - inner);
}

template <class T>
void softmax_row_backward_simd(const T* y, const T* dy, T* dx, index_t n) noexcept {
  using B = batch<T>;
  constexpr index_t w = static_cast<index_t>(B::size);
  const T inner = dot_simd(y, dy, n);
  const B vinner(inner);
  index_t i = 0;
  for (; i + w <= n; i += w) {
    const B yb = B::load_unaligned(y + i);
    xsimd::fma(yb, B::load_unaligned(dy + i) - vinner, B::load_unaligned(dx + i)).store_unaligned(dx + i);
  }
  for (; i < n; ++i) dx[i] += y[i] * (dy[i] - inner);
}

template <class T>
void softmax_row_backward(const T* y, const T* dy, T* dx, index_t n) noexcept {
  if (enabled()) softmax_row_backward_simd(y, dy, dx, n);
  else softmax_row_backward_scalar(y, dy, dx, n);
}

}  // namespace simd
}  // namespace v0
}  // namespace flexsplat
