#pragma once
// Row-major GEMM C = alpha * op(A) * op(B) + beta * C on a CBLAS (OpenBLAS) when the build links one
// (FLEXSPLAT_HAVE_CBLAS, set by the flexsplat CMake target), else on Eigen's kernels; C split over the pool.
// With oneDNN (FLEXSPLAT_HAVE_DNNL) float products may run on its fp32 matmul (GemmBackend::onednn, the default where
// oneDNN has AVX-512 kernels for the CPU) or in bf16 with fp32 accumulation (GemmBackend::bf16).
#include <Eigen/Core>

#include <algorithm>
#include <atomic>
#include <climits>
#include <cstdlib>
#include <string>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/tensor.hpp"

#if defined(FLEXSPLAT_HAVE_DNNL)
#include <oneapi/dnnl/dnnl.hpp>
// The OpenMP runtime oneDNN runs on (libgomp): declared here so that no compiler's omp.h is needed.
extern "C" void omp_set_num_threads(int);
#endif
#if defined(FLEXSPLAT_HAVE_CBLAS)
#include <cblas.h>
#endif

namespace flexsplat {
inline namespace v0 {

enum class Trans { no, yes };
// bf16: float products with both operands rounded to bf16, accumulated and returned in fp32 (oneDNN); double
// products and float ones below gemm_bf16_min_madds run on the BLAS (or Eigen) as with `blas`.
// onednn: float products on oneDNN's fp32 matmul; double products and float ones below gemm_onednn_min_madds run on
// the BLAS (or Eigen).
enum class GemmBackend { eigen, blas, bf16, onednn };

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
#if defined(FLEXSPLAT_HAVE_DNNL)
inline constexpr bool have_bf16_gemm = true;
#else
inline constexpr bool have_bf16_gemm = false;
#endif
inline constexpr bool have_onednn_gemm = have_bf16_gemm;  // the fp32 matmul comes with the same library

// Products below this many multiply-adds stay on Eigen even with a BLAS: there a CBLAS call's fixed cost loses to
// Eigen's inlined kernels (bench/gemm's small-shape table: Eigen 2-4x faster at 4^3, even at 8^3 = 512, OpenBLAS
// faster from 12^3 = 1728 on).
inline constexpr index_t gemm_blas_min_madds = index_t(1) << 10;

namespace detail {
inline std::atomic<int>& gemm_backend_override() {
  static std::atomic<int> choice{-1};
  return choice;
}

// Whether oneDNN runs its AVX-512 kernels on this CPU (its own run-time dispatch, capped by DNNL_MAX_CPU_ISA): there
// its fp32 matmul measured 1.6-2.7x OpenBLAS's Haswell kernels from 96^3 on (bench/gemm). Without AVX-512 it was not
// measured, so the BLAS stays the default.
inline bool onednn_has_avx512() {
#if defined(FLEXSPLAT_HAVE_DNNL)
  static const bool yes = [] {
    const int isa = static_cast<int>(dnnl::get_effective_cpu_isa());
    return (isa & dnnl_cpu_isa_avx512_core) == dnnl_cpu_isa_avx512_core;
  }();
  return yes;
#else
  return false;
#endif
}
}  // namespace detail

// The fp32 backend gemm() picks without FLEXSPLAT_GEMM or set_default_gemm_backend: oneDNN's fp32 matmul where it has
// AVX-512 kernels for the CPU, else the BLAS when the build has one, else Eigen.
inline GemmBackend fastest_fp32_gemm_backend() {
  if (have_onednn_gemm && detail::onednn_has_avx512()) return GemmBackend::onednn;
  return have_blas ? GemmBackend::blas : GemmBackend::eigen;
}

// What gemm() without a backend uses: set_default_gemm_backend's choice, else FLEXSPLAT_GEMM=eigen|blas|onednn|bf16
// (read once), else fastest_fp32_gemm_backend().
inline GemmBackend default_gemm_backend() {
  if (const int choice = detail::gemm_backend_override().load(std::memory_order_relaxed); choice >= 0)
    return static_cast<GemmBackend>(choice);
  static const GemmBackend backend = [] {
    const char* env = std::getenv("FLEXSPLAT_GEMM");
    if (!env || !*env) return fastest_fp32_gemm_backend();
    const std::string v = env;
    require(v == "eigen" || v == "blas" || v == "onednn" || v == "bf16", "FLEXSPLAT_GEMM='", v,
            "' is not 'eigen', 'blas', 'onednn' or 'bf16'");
    require(v != "blas" || have_blas, "FLEXSPLAT_GEMM=blas but this build has no BLAS (FLEXSPLAT_USE_BLAS=OFF or "
                                      "OpenBLAS not found at configure time)");
    require((v != "bf16" && v != "onednn") || have_onednn_gemm, "FLEXSPLAT_GEMM=", v, " but this build has no oneDNN "
            "(FLEXSPLAT_USE_DNNL=OFF or libdnnl-dev not found at configure time)");
    return v == "blas" ? GemmBackend::blas : v == "bf16" ? GemmBackend::bf16 : v == "onednn" ? GemmBackend::onednn
                                                                                               : GemmBackend::eigen;
  }();
  return backend;
}

// Selects the backend of every later gemm() call without one (e.g. bf16 for a whole forward pass); call it between
// passes, not while other threads multiply.
inline void set_default_gemm_backend(GemmBackend backend) {
  require(backend != GemmBackend::blas || have_blas, "set_default_gemm_backend: this build has no BLAS");
  require(backend != GemmBackend::bf16 || have_bf16_gemm, "set_default_gemm_backend: this build has no oneDNN (bf16)");
  require(backend != GemmBackend::onednn || have_onednn_gemm, "set_default_gemm_backend: this build has no oneDNN");
  detail::gemm_backend_override().store(static_cast<int>(backend), std::memory_order_relaxed);
}

// Float products below this many multiply-adds stay in fp32 under GemmBackend::bf16: oneDNN's per-call set-up
// (primitive look-up, two reorders) costs tens of microseconds.
inline constexpr index_t gemm_bf16_min_madds = index_t(1) << 20;
// Float products below this many multiply-adds leave GemmBackend::onednn for the BLAS (or Eigen): oneDNN's per-call
// set-up is about 9 us; it lost at 64^3 = 2^18 (0.74-0.95x) and won from 96^3 (1.5x) in bench/gemm's fp32 table.
inline constexpr index_t gemm_onednn_min_madds = index_t(1) << 19;

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

// A stored matrix of `rows` x `cols` with row stride ld; with one row the stride is never used, but CBLAS checks it.
inline int blas_ld(index_t rows, index_t cols, index_t ld) {
  return static_cast<int>(rows <= 1 ? std::max<index_t>({ld, cols, 1}) : ld);
}

#if defined(FLEXSPLAT_HAVE_CBLAS)

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

#if defined(FLEXSPLAT_HAVE_DNNL)
// C[:M, :N] = alpha op(A) op(B) + beta C on the calling thread with oneDNN's matmul. fp32: on the operands in place.
// bf16: oneDNN reorders A and B to bf16 (round to nearest even) in the layouts its matmul prefers, which accumulates
// in fp32 (AVX-512 BF16 kernels where the CPU has them).
inline void onednn_gemm(bool bf16, Trans ta, Trans tb, index_t M, index_t N, index_t K, float alpha, const float* A,
                        index_t lda, const float* B, index_t ldb, float beta, float* C, index_t ldc) {
  using dims = dnnl::memory::dims;
  using dt = dnnl::memory::data_type;
  try {
    static const dnnl::engine engine(dnnl::engine::kind::cpu, 0);
    thread_local dnnl::stream stream(engine);
    omp_set_num_threads(1);  // the pool splits the work, as with OpenBLAS: no OpenMP team per worker
    const index_t a_ld = ta == Trans::no ? blas_ld(M, K, lda) : blas_ld(K, M, lda);
    const index_t b_ld = tb == Trans::no ? blas_ld(K, N, ldb) : blas_ld(N, K, ldb);
    const dnnl::memory::desc a_f32({M, K}, dt::f32, ta == Trans::no ? dims{a_ld, 1} : dims{1, a_ld});
    const dnnl::memory::desc b_f32({K, N}, dt::f32, tb == Trans::no ? dims{b_ld, 1} : dims{1, b_ld});
    const dnnl::memory::desc c_f32({M, N}, dt::f32, dims{blas_ld(M, N, ldc), 1});
    dnnl::primitive_attr attr;
    if (alpha != 1.0f) attr.set_output_scales(0, {alpha});
    if (beta != 0.0f) {
      dnnl::post_ops ops;
      ops.append_sum(beta);
      attr.set_post_ops(ops);
    }
    dnnl::memory a_in(a_f32, engine, const_cast<float*>(A)), b_in(b_f32, engine, const_cast<float*>(B));
    dnnl::memory c(c_f32, engine, C);
    if (!bf16) {
      const dnnl::matmul::primitive_desc pd(dnnl::matmul::desc(a_f32, b_f32, c_f32), attr, engine);
      dnnl::matmul(pd).execute(stream, {{DNNL_ARG_SRC, a_in}, {DNNL_ARG_WEIGHTS, b_in}, {DNNL_ARG_DST, c}});
      stream.wait();
      return;
    }
    const auto any = dnnl::memory::format_tag::any;
    const dnnl::matmul::desc desc(dnnl::memory::desc({M, K}, dt::bf16, any), dnnl::memory::desc({K, N}, dt::bf16, any),
                                  c_f32);
    const dnnl::matmul::primitive_desc pd(desc, attr, engine);
    dnnl::memory a(pd.src_desc(), engine), b(pd.weights_desc(), engine);
    dnnl::reorder(a_in, a).execute(stream, a_in, a);
    dnnl::reorder(b_in, b).execute(stream, b_in, b);
    dnnl::matmul(pd).execute(stream, {{DNNL_ARG_SRC, a}, {DNNL_ARG_WEIGHTS, b}, {DNNL_ARG_DST, c}});
    stream.wait();
  } catch (const dnnl::error& e) {
    fail("gemm (", bf16 ? "bf16" : "fp32", ", oneDNN): M ", M, " N ", N, " K ", K, " lda ", lda, " ldb ", ldb, " ldc ",
         ldc, ": ", e.what());
  }
}

inline void bf16_gemm(Trans ta, Trans tb, index_t M, index_t N, index_t K, float alpha, const float* A, index_t lda,
                      const float* B, index_t ldb, float beta, float* C, index_t ldc) {
  onednn_gemm(true, ta, tb, M, N, K, alpha, A, lda, B, ldb, beta, C, ldc);
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
#if defined(FLEXSPLAT_HAVE_DNNL)
  if constexpr (std::is_same_v<T, float>) {
    if (backend == GemmBackend::bf16 || backend == GemmBackend::onednn) {
      onednn_gemm(backend == GemmBackend::bf16, ta, tb, M, N, K, alpha, A, lda, B, ldb, beta, C, ldc);
      return;
    }
  }
#endif
  if (backend == GemmBackend::bf16 || backend == GemmBackend::onednn)
    backend = have_blas ? GemmBackend::blas : GemmBackend::eigen;
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
#if defined(FLEXSPLAT_HAVE_DNNL)
  if (backend == GemmBackend::bf16) {
    const dnnl_version_t* v = dnnl_version();
    return concat("oneDNN ", v->major, '.', v->minor, '.', v->patch, " bf16 matmul (fp32 accumulation), single-threaded "
                  "calls; small products on ", gemm_backend_name(have_blas ? GemmBackend::blas : GemmBackend::eigen));
  }
  if (backend == GemmBackend::onednn) {
    const dnnl_version_t* v = dnnl_version();
    return concat("oneDNN ", v->major, '.', v->minor, '.', v->patch, " fp32 matmul (",
                  detail::onednn_has_avx512() ? "AVX-512" : "no AVX-512", " kernels), single-threaded calls; products "
                  "under ", gemm_onednn_min_madds, " multiply-adds on ",
                  gemm_backend_name(have_blas ? GemmBackend::blas : GemmBackend::eigen));
  }
#endif
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
  require(backend != GemmBackend::blas || have_blas, "gemm: the BLAS backend was requested but this build has none");
  require(backend != GemmBackend::bf16 || have_bf16_gemm, "gemm: bf16 was requested but this build has no oneDNN");
  require(backend != GemmBackend::onednn || have_onednn_gemm, "gemm: oneDNN was requested but this build has none");
  // Decided for the whole product, so that the pool's split never changes the precision or the summation order.
  if ((backend == GemmBackend::bf16 && (!std::is_same_v<T, float> || M * N * K < gemm_bf16_min_madds)) ||
      (backend == GemmBackend::onednn && (!std::is_same_v<T, float> || M * N * K < gemm_onednn_min_madds)))
    backend = have_blas ? GemmBackend::blas : GemmBackend::eigen;
  if (backend != GemmBackend::eigen) {
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
  // Few rows (e.g. one token per frame), or C at least 4x wider than tall (the DPT convolutions' weight x im2col):
  // split the columns, so that no worker multiplies a thin slice of rows against all of B (oneDNN on 2 threads:
  // 1.0-2.6x faster on the DPT shapes, bench/gemm's split table).
  const bool by_columns = (M < 4 * workers && N >= 16 * workers) || N >= 4 * M;
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
