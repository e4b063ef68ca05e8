#pragma once
// Row-major GEMM C = alpha * op(A) * op(B) + beta * C on a CBLAS (OpenBLAS) when the build links one
// (FLEXSPLAT_HAVE_CBLAS, set by the flexsplat CMake target), else on Eigen's kernels; rows of C split over the pool.
#include <Eigen/Core>

#include <algorithm>
#include <climits>
#include <cstdlib>
#include <string>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/tensor.hpp"

#if defined(FLEXSPLAT_HAVE_CBLAS)
#include <cblas.h>
#endif

namespace flexsplat {
inline namespace v0 {

enum class Trans { no, yes };
enum class GemmBackend { eigen, blas };

template <class T>
using RowMatrix = Eigen::Matrix<T, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
template <class T>
using ConstMatMap = Eigen::Map<const RowMatrix<T>, 0, Eigen::OuterStride<>>;
template <class T>
using MatMap = Eigen::Map<RowMatrix<T>, 0, Eigen::OuterStride<>>;

#if defined(FLEXSPLAT_HAVE_CBLAS)
inline constexpr bool have_blas = true;
#else
inline constexpr bool have_blas = false;
#endif

// Products below this many multiply-adds stay on Eigen even with a BLAS: there a CBLAS call's fixed cost loses to
// Eigen's inlined kernels (bench/gemm's small-shape table: Eigen 2-4x faster at 4^3, even at 8^3 = 512, OpenBLAS
// faster from 12^3 = 1728 on).
inline constexpr index_t gemm_blas_min_madds = index_t(1) << 10;

// The BLAS when the build has one, Eigen otherwise; FLEXSPLAT_GEMM=eigen|blas overrides it (read once).
inline GemmBackend default_gemm_backend() {
  static const GemmBackend backend = [] {
    const char* env = std::getenv("FLEXSPLAT_GEMM");
    if (!env || !*env) return have_blas ? GemmBackend::blas : GemmBackend::eigen;
    const std::string v = env;
    require(v == "eigen" || v == "blas", "FLEXSPLAT_GEMM='", v, "' is neither 'eigen' nor 'blas'");
    require(v == "eigen" || have_blas, "FLEXSPLAT_GEMM=blas but this build has no BLAS (FLEXSPLAT_USE_BLAS=OFF or "
                                       "OpenBLAS not found at configure time)");
    return v == "blas" ? GemmBackend::blas : GemmBackend::eigen;
  }();
  return backend;
}

namespace detail {

#if defined(FLEXSPLAT_HAVE_OPENBLAS)
// Once per process, before flexsplat's first BLAS call: OpenBLAS runs single-threaded, since the pool splits the work
// and OpenBLAS's own threads would oversubscribe the cores (Debian's libopenblas0-pthread keeps them spinning for a
// while after each call). Its kernels stay OpenBLAS's choice: run-time CPU dispatch, or OPENBLAS_CORETYPE.
inline void openblas_single_threaded() {
  static const bool done = [] {
    openblas_set_num_threads(1);
    return true;
  }();
  (void)done;
}
#endif

#if defined(FLEXSPLAT_HAVE_CBLAS)
// A stored matrix of `rows` x `cols` with row stride ld; with one row the stride is never used, but CBLAS checks it.
inline int blas_ld(index_t rows, index_t cols, index_t ld) {
  return static_cast<int>(rows <= 1 ? std::max<index_t>({ld, cols, 1}) : ld);
}

template <class T>
void blas_gemm(Trans ta, Trans tb, index_t M, index_t N, index_t K, T alpha, const T* A, index_t lda, const T* B,
               index_t ldb, T beta, T* C, index_t ldc) {
#if defined(FLEXSPLAT_HAVE_OPENBLAS)
  openblas_single_threaded();
#endif
  const auto op = [](Trans t) { return t == Trans::no ? CblasNoTrans : CblasTrans; };
  const int a_ld = ta == Trans::no ? blas_ld(M, K, lda) : blas_ld(K, M, lda);
  const int b_ld = tb == Trans::no ? blas_ld(K, N, ldb) : blas_ld(N, K, ldb);
  const int c_ld = blas_ld(M, N, ldc);
  if constexpr (std::is_same_v<T, float>)
    cblas_sgemm(CblasRowMajor, op(ta), op(tb), int(M), int(N), int(K), alpha, A, a_ld, B, b_ld, beta, C, c_ld);
  else
    cblas_dgemm(CblasRowMajor, op(ta), op(tb), int(M), int(N), int(K), alpha, A, a_ld, B, b_ld, beta, C, c_ld);
}
#endif

// One block on one thread: C[:M, :N] = alpha op(A) op(B) + beta C, A/B/C already offset to the block.
template <class T>
void gemm_block(GemmBackend backend, Trans ta, Trans tb, index_t M, index_t N, index_t K, T alpha, const T* A,
                index_t lda, const T* B, index_t ldb, T beta, T* C, index_t ldc) {
  MatMap<T> c(C, M, N, Eigen::OuterStride<>(ldc));
  if (K <= 0 || alpha == T(0)) {
    if (beta == T(0)) c.setZero();
    else if (beta != T(1)) c *= beta;
    return;
  }
#if defined(FLEXSPLAT_HAVE_CBLAS)
  if constexpr (std::is_same_v<T, float> || std::is_same_v<T, double>) {
    if (backend == GemmBackend::blas && M * N * K >= gemm_blas_min_madds) {
      blas_gemm(ta, tb, M, N, K, alpha, A, lda, B, ldb, beta, C, ldc);
      return;
    }
  }
#else
  (void)backend;
#endif
  if (beta == T(0)) c.setZero();
  else if (beta != T(1)) c *= beta;
  auto b = [&](auto&& a_op) {
    if (tb == Trans::no) c.noalias() += alpha * (a_op * ConstMatMap<T>(B, K, N, Eigen::OuterStride<>(ldb)));
    else c.noalias() += alpha * (a_op * ConstMatMap<T>(B, N, K, Eigen::OuterStride<>(ldb)).transpose());
  };
  if (ta == Trans::no) b(ConstMatMap<T>(A, M, K, Eigen::OuterStride<>(lda)));
  else b(ConstMatMap<T>(A, K, M, Eigen::OuterStride<>(lda)).transpose());
}

}  // namespace detail

// "OpenBLAS 0.3.21 NO_LAPACKE DYNAMIC_ARCH NO_AFFINITY SkylakeX ...", "CBLAS" or "Eigen 3.4.0": what gemm runs on.
inline std::string gemm_backend_name(GemmBackend backend = default_gemm_backend()) {
  if (backend == GemmBackend::eigen)
    return concat("Eigen ", EIGEN_WORLD_VERSION, '.', EIGEN_MAJOR_VERSION, '.', EIGEN_MINOR_VERSION);
#if defined(FLEXSPLAT_HAVE_OPENBLAS)
  detail::openblas_single_threaded();
  std::string config = openblas_get_config();  // names the kernels in use
  config.erase(0, config.find_first_not_of(' '));
  return config + ", single-threaded calls";
#else
  return have_blas ? "CBLAS" : "no BLAS in this build";
#endif
}

// op(A) is M x K, op(B) is K x N, C is M x N; lda/ldb/ldc are row strides of the stored matrices. Deterministic for a
// given pool size: the split depends only on the shape and pool.size(), and each block runs single-threaded.
template <class T>
void gemm(GemmBackend backend, Trans ta, Trans tb, index_t M, index_t N, index_t K, T alpha, const T* A, index_t lda,
          const T* B, index_t ldb, T beta, T* C, index_t ldc, ThreadPool& pool = global_pool()) {
  if (M <= 0 || N <= 0) return;
  require(backend == GemmBackend::eigen || have_blas, "gemm: the BLAS backend was requested but this build has none");
  if (backend == GemmBackend::blas) {
    const index_t a_cols = ta == Trans::no ? K : M, b_cols = tb == Trans::no ? N : K;
    const index_t a_rows = ta == Trans::no ? M : K, b_rows = tb == Trans::no ? K : N;
    if (std::max({M, N, K, lda, ldb, ldc}) > index_t(INT_MAX) || (a_rows > 1 && lda < a_cols) ||
        (b_rows > 1 && ldb < b_cols) || (M > 1 && ldc < N))
      fail("gemm: M ", M, " N ", N, " K ", K, " with lda ", lda, " ldb ", ldb, " ldc ", ldc,
           " is not a valid BLAS call (strides shorter than rows, or beyond 32-bit)");
  }
  auto block = [&](index_t r0, index_t r1, index_t c0, index_t c1) {
    const T* a = ta == Trans::no ? A + r0 * lda : A + r0;
    const T* b = tb == Trans::no ? B + c0 : B + c0 * ldb;
    detail::gemm_block(backend, ta, tb, r1 - r0, c1 - c0, K, alpha, a, lda, b, ldb, beta, C + r0 * ldc + c0, ldc);
  };
  const index_t flops = M * N * (K > 0 ? K : 1);
  const index_t workers = pool.size();
  // Inside a parallel region every worker is busy already: one single-threaded call.
  if (flops < (index_t(1) << 18) || workers == 1 || ThreadPool::current_worker() >= 0) {
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

template <class T>
void gemm(Trans ta, Trans tb, index_t M, index_t N, index_t K, T alpha, const T* A, index_t lda, const T* B,
          index_t ldb, T beta, T* C, index_t ldc, ThreadPool& pool = global_pool()) {
  gemm(default_gemm_backend(), ta, tb, M, N, K, alpha, A, lda, B, ldb, beta, C, ldc, pool);
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
  parallel_for(count, [&](index_t b0, index_t b1, int) {
    for (index_t i = b0; i < b1; ++i)
      gemm(ta, tb, M, N, K, alpha, A + i * stride_a, lda, B + i * stride_b, ldb, beta, C + i * stride_c, ldc, pool);
  }, pool);
}

}  // namespace v0
}  // namespace flexsplat
