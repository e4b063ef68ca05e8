#pragma once
// Hot kernels of the decoder, each with a scalar path (the reference) and a simd::batch path, chosen at run time by
// simd::enabled(); the *_impl<T, Simd> templates are public so tests can run both paths in one process:
//   in-place softmax of a row returning its log-sum-exp, windowed self-attention (every
//   consecutive window of queries attends within itself; whole-window softmax, no online rescaling) forward/backward
//   as small GEMMs per (window, head) on caller scratch.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <span>

#include <Eigen/Core>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/gemm.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/profile.hpp"
#include "flexsplat/core/simd.hpp"
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {
namespace decoder {
namespace kernels {

// ---- row softmax with log-sum-exp ----

// row <- softmax(row) in place; returns log(sum(exp(row))) of the input. n >= 1; a NaN input propagates.
template <class T, bool Simd>
T softmax_lse_impl(T* row, index_t n) {
  index_t i = 0;
  T max = -std::numeric_limits<T>::infinity();
  using B = simd::batch<T>;
  constexpr index_t w = static_cast<index_t>(B::size);
  if constexpr (Simd) {
    if (n >= w) {
      B m = B::load_unaligned(row);
      for (i = w; i + w <= n; i += w) m = xsimd::max(m, B::load_unaligned(row + i));
      max = simd::reduce_max(m);
    }
  }
  for (; i < n; ++i) max = row[i] > max ? row[i] : max;
  T sum = 0;
  i = 0;
  if constexpr (Simd) {
    const B mb(max);
    B acc(T(0));
    for (; i + w <= n; i += w) {
      const B e = simd::lane_exp(B::load_unaligned(row + i) - mb);
      e.store_unaligned(row + i);
      acc += e;
    }
    sum = simd::reduce_add(acc);
  }
  for (; i < n; ++i) sum += (row[i] = std::exp(row[i] - max));
  const T inv = T(1) / sum;
  i = 0;
  if constexpr (Simd) {
    const B ib(inv);
    for (; i + w <= n; i += w) (B::load_unaligned(row + i) * ib).store_unaligned(row + i);
  }
  for (; i < n; ++i) row[i] *= inv;
  return max + std::log(sum);
}

// Backward of P = exp(S - lse) for one row, in place on the buffers: p <- exp(s - lse) (s is overwritten with p),
// ds <- p * (dp - delta) (dp is overwritten with ds).
template <class T, bool Simd>
void softmax_grad_row_impl(T* s_to_p, T* dp_to_ds, T lse, T delta, index_t n) {
  index_t i = 0;
  if constexpr (Simd) {
    using B = simd::batch<T>;
    constexpr index_t w = static_cast<index_t>(B::size);
    const B l(lse), d(delta);
    for (; i + w <= n; i += w) {
      const B p = simd::lane_exp(B::load_unaligned(s_to_p + i) - l);
      p.store_unaligned(s_to_p + i);
      (p * (B::load_unaligned(dp_to_ds + i) - d)).store_unaligned(dp_to_ds + i);
    }
  }
  for (; i < n; ++i) {
    const T p = std::exp(s_to_p[i] - lse);
    s_to_p[i] = p;
    dp_to_ds[i] = p * (dp_to_ds[i] - delta);
  }
}

// ---- windowed self-attention ----

// qkv [n, 3 * heads * head_dim] rows (q | k | v, each heads x head_dim); windows of `window` consecutive rows, the last
// one shorter; out [n, heads * head_dim]; lse [n, heads].
struct WindowAttentionShape {
  index_t n = 0, window = 1, heads = 1, head_dim = 1;
  index_t dim() const { return heads * head_dim; }
  index_t windows() const { return (n + window - 1) / window; }
};

inline constexpr index_t window_q_block = 64;

// Scratch elements per worker; pass at least this times the pool size.
inline index_t window_attention_scratch_per_worker(const WindowAttentionShape& s) {
  return 2 * window_q_block * std::min(s.window, std::max<index_t>(s.n, 1));
}

namespace detail {
template <class T>
using Rows = Eigen::Map<const Eigen::Matrix<T, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>, 0, Eigen::OuterStride<>>;
template <class T>
using MutRows = Eigen::Map<Eigen::Matrix<T, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>, 0, Eigen::OuterStride<>>;
template <class T>
using Dense = Eigen::Map<Eigen::Matrix<T, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>>;

inline void check_window_shape(const WindowAttentionShape& s, std::size_t scratch, int workers) {
  require(s.n >= 0 && s.window >= 1 && s.heads >= 1 && s.head_dim >= 1, "window attention: n ", s.n, ", window ",
          s.window, ", heads ", s.heads, ", head_dim ", s.head_dim, " (window, heads and head_dim must be positive)");
  require(static_cast<index_t>(scratch) >= window_attention_scratch_per_worker(s) * workers, "window attention: scratch has ",
          scratch, " elements, needs ", window_attention_scratch_per_worker(s) * workers);
}
}  // namespace detail

template <class T, bool Simd>
void window_attention_forward_impl(T* out, T* lse, const T* qkv, const WindowAttentionShape& s, T scale,
                                   std::span<T> scratch, ThreadPool& pool = global_pool()) {
  using namespace detail;
  check_window_shape(s, scratch.size(), pool.size());
  const index_t D = s.dim(), hd = s.head_dim, stride = 3 * D;
  parallel_for(s.windows() * s.heads, [&](index_t t0, index_t t1, int worker) {
    T* ws = scratch.data() + worker * window_attention_scratch_per_worker(s);
    for (index_t t = t0; t < t1; ++t) {
      const index_t win = t / s.heads, h = t % s.heads;
      const index_t w0 = win * s.window, cnt = std::min(s.window, s.n - w0);
      const T* K = qkv + w0 * stride + D + h * hd;
      const T* V = qkv + w0 * stride + 2 * D + h * hd;
      for (index_t r0 = 0; r0 < cnt; r0 += window_q_block) {
        const index_t rows = std::min(window_q_block, cnt - r0);
        // S = scale Q K^T and O = P V through core/gemm: its BLAS kernels follow the CPU, Eigen's the build flags.
        gemm(Trans::no, Trans::yes, rows, cnt, hd, scale, qkv + (w0 + r0) * stride + h * hd, stride, K, stride,
             T(0), ws, cnt, pool);
        for (index_t r = 0; r < rows; ++r) lse[(w0 + r0 + r) * s.heads + h] = softmax_lse_impl<T, Simd>(ws + r * cnt, cnt);
        gemm(Trans::no, Trans::no, rows, hd, cnt, T(1), ws, cnt, V, stride, T(0), out + (w0 + r0) * D + h * hd, D,
             pool);
      }
    }
  }, pool);
}

// Adds into d_qkv [n, 3 * dim] (q | k | v parts). Each (window, head) task owns its slice: race-free and the same for
// any thread count.
template <class T, bool Simd>
void window_attention_backward_impl(T* d_qkv, const T* d_out, const T* out, const T* lse, const T* qkv,
                                    const WindowAttentionShape& s, T scale, std::span<T> scratch,
                                    ThreadPool& pool = global_pool()) {
  using namespace detail;
  check_window_shape(s, scratch.size(), pool.size());
  const index_t D = s.dim(), hd = s.head_dim, stride = 3 * D;
  parallel_for(s.windows() * s.heads, [&](index_t t0, index_t t1, int worker) {
    T* ws = scratch.data() + worker * window_attention_scratch_per_worker(s);
    for (index_t t = t0; t < t1; ++t) {
      const index_t win = t / s.heads, h = t % s.heads;
      const index_t w0 = win * s.window, cnt = std::min(s.window, s.n - w0);
      Rows<T> K(qkv + w0 * stride + D + h * hd, cnt, hd, Eigen::OuterStride<>(stride));
      Rows<T> V(qkv + w0 * stride + 2 * D + h * hd, cnt, hd, Eigen::OuterStride<>(stride));
      MutRows<T> dK(d_qkv + w0 * stride + D + h * hd, cnt, hd, Eigen::OuterStride<>(stride));
      MutRows<T> dV(d_qkv + w0 * stride + 2 * D + h * hd, cnt, hd, Eigen::OuterStride<>(stride));
      for (index_t r0 = 0; r0 < cnt; r0 += window_q_block) {
        const index_t rows = std::min(window_q_block, cnt - r0);
        Rows<T> Q(qkv + (w0 + r0) * stride + h * hd, rows, hd, Eigen::OuterStride<>(stride));
        Rows<T> dO(d_out + (w0 + r0) * D + h * hd, rows, hd, Eigen::OuterStride<>(D));
        Rows<T> O(out + (w0 + r0) * D + h * hd, rows, hd, Eigen::OuterStride<>(D));
        MutRows<T> dQ(d_qkv + (w0 + r0) * stride + h * hd, rows, hd, Eigen::OuterStride<>(stride));
        Dense<T> P(ws, rows, cnt), dS(ws + window_q_block * cnt, rows, cnt);
        P.noalias() = scale * (Q * K.transpose());
        dS.noalias() = dO * V.transpose();
        for (index_t r = 0; r < rows; ++r) {
          const T delta = dO.row(r).dot(O.row(r));
          softmax_grad_row_impl<T, Simd>(ws + r * cnt, ws + window_q_block * cnt + r * cnt,
                                         lse[(w0 + r0 + r) * s.heads + h], delta, cnt);
        }
        dV.noalias() += P.transpose() * dO;
        dK.noalias() += scale * (dS.transpose() * Q);
        dQ.noalias() += scale * (dS * K);
      }
    }
  }, pool);
}

template <class T>
void window_attention_forward(T* out, T* lse, const T* qkv, const WindowAttentionShape& s, T scale,
                              std::span<T> scratch, ThreadPool& pool = global_pool()) {
  const profile::Scope timed(profile::Op::attention_forward);  // its products count as GEMM FLOPs
  if (simd::enabled()) window_attention_forward_impl<T, true>(out, lse, qkv, s, scale, scratch, pool);
  else window_attention_forward_impl<T, false>(out, lse, qkv, s, scale, scratch, pool);
}

template <class T>
void window_attention_backward(T* d_qkv, const T* d_out, const T* out, const T* lse, const T* qkv,
                               const WindowAttentionShape& s, T scale, std::span<T> scratch,
                               ThreadPool& pool = global_pool()) {
  const profile::Scope timed(profile::Op::attention_backward);
  if (simd::enabled()) window_attention_backward_impl<T, true>(d_qkv, d_out, out, lse, qkv, s, scale, scratch, pool);
  else window_attention_backward_impl<T, false>(d_qkv, d_out, out, lse, qkv, s, scale, scratch, pool);
}

}  // namespace kernels
}  // namespace decoder
}  // namespace v0
}  // namespace flexsplat
