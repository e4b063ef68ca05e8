#pragma once
// Row-major GEMM C = alpha * op(A) * op(B) + beta * C on Eigen's kernels, rows of C split over the worker pool.
#include <Eigen/Core>

#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {

enum class Trans { no, yes };

template <class T>
using RowMatrix = Eigen::Matrix<T, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
template <class T>
using ConstMatMap = Eigen::Map<const RowMatrix<T>, 0, Eigen::OuterStride<>>;
template <class T>
using MatMap = Eigen::Map<RowMatrix<T>, 0, Eigen::OuterStride<>>;

// op(A) is M x K, op(B) is K x N, C is M x N; lda/ldb/ldc are row strides of the stored matrices.
template <class T>
void gemm(Trans ta, Trans tb, index_t M, index_t N, index_t K, T alpha, const T* A, index_t lda, const T* B,
          index_t ldb, T beta, T* C, index_t ldc, ThreadPool& pool = global_pool()) {
  if (M <= 0 || N <= 0) return;
  // C[r0:r1, c0:c1] = alpha * op(A)[r0:r1, :] * op(B)[:, c0:c1] + beta * C[r0:r1, c0:c1]
  auto block = [&](index_t r0, index_t r1, index_t c0, index_t c1) {
    const index_t rows = r1 - r0, cols = c1 - c0;
    MatMap<T> c(C + r0 * ldc + c0, rows, cols, Eigen::OuterStride<>(ldc));
    if (beta == T(0)) c.setZero();
    else if (beta != T(1)) c *= beta;
    if (K <= 0 || alpha == T(0)) return;
    auto b = [&](auto&& a_op) {
      if (tb == Trans::no) c.noalias() += alpha * (a_op * ConstMatMap<T>(B + c0, K, cols, Eigen::OuterStride<>(ldb)));
      else c.noalias() += alpha * (a_op * ConstMatMap<T>(B + c0 * ldb, cols, K, Eigen::OuterStride<>(ldb)).transpose());
    };
    if (ta == Trans::no) b(ConstMatMap<T>(A + r0 * lda, rows, K, Eigen::OuterStride<>(lda)));
    else b(ConstMatMap<T>(A + r0, K, rows, Eigen::OuterStride<>(lda)).transpose());
  };
  const index_t flops = M * N * (K > 0 ? K : 1);
  const index_t workers = pool.size();
  if (flops < (index_t(1) << 18) || workers == 1) {
    block(0, M, 0, N);
    return;
  }
  // Few rows (e.g. one token per frame): split the columns instead so every worker gets a share of B.
  const bool by_columns = M < 4 * workers && N >= 16 * workers;
  const index_t extent = by_columns ? N : M;
  const index_t chunks = std::min<index_t>(workers, extent);
  parallel_for(chunks, [&](index_t k0, index_t k1, int) {
    for (index_t k = k0; k < k1; ++k) {
      const index_t lo = extent * k / chunks, hi = extent * (k + 1) / chunks;
      if (by_columns) block(0, M, lo, hi);
      else block(lo, hi, 0, N);
    }
  }, pool);
}

// Batched: count independent products with fixed strides between consecutive matrices.
template <class T>
void gemm_batched(index_t count, Trans ta, Trans tb, index_t M, index_t N, index_t K, T alpha, const T* A,
                  index_t lda, index_t stride_a, const T* B, index_t ldb, index_t stride_b, T beta, T* C, index_t ldc,
                  index_t stride_c, ThreadPool& pool = global_pool()) {
  if (count <= 0) return;
  if (count == 1 || count < pool.size()) {
    for (index_t i = 0; i < count; ++i)
      gemm(ta, tb, M, N, K, alpha, A + i * stride_a, lda, B + i * stride_b, ldb, beta, C + i * stride_c, ldc, pool);
    return;
  }
  ThreadPool serial(1);
  parallel_for(count, [&](index_t b0, index_t b1, int) {
    for (index_t i = b0; i < b1; ++i)
      gemm(ta, tb, M, N, K, alpha, A + i * stride_a, lda, B + i * stride_b, ldb, beta, C + i * stride_c, ldc, serial);
  }, pool);
}

}  // namespace v0
}  // namespace flexsplat
