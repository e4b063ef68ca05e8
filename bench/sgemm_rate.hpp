#pragma once
// The machine's SGEMM rate for the benchmarks' "of SGEMM" columns, and a label naming the build that produced a row.
// The rate is 2048x2048x1024, C = A B^T (nn::linear's form), float, on the pool's threads, best of `reps` after a
// warm-up, the fastest of every fp32 backend the build has (oneDNN's matmul, the BLAS, Eigen): the machine's rate,
// not one backend's.
#include <algorithm>
#include <chrono>
#include <string>
#include <vector>

#include "flexsplat/core/gemm.hpp"
#include "flexsplat/core/simd.hpp"

namespace flexsplat::bench {

// The fp32 backend gemm() picks by default (the backend of the benchmarks' fp32 rows).
inline GemmBackend best_gemm_backend() { return fastest_fp32_gemm_backend(); }

// Every fp32 backend of this build; Eigen only where it is the sole one (it is never the fastest next to the others).
inline std::vector<GemmBackend> fp32_gemm_backends() {
  std::vector<GemmBackend> all;
  if (have_onednn_gemm) all.push_back(GemmBackend::onednn);
  if (have_blas) all.push_back(GemmBackend::blas);
  if (all.empty()) all.push_back(GemmBackend::eigen);
  return all;
}

// GFLOP/s of C = op(A) op(B) + beta C (M x N x K, dense operands of fixed patterns) on `backend`: the best of `reps`
// rounds of `calls` calls each, after one uncounted round (caches, oneDNN's primitive).
inline double gemm_gflops(index_t M, index_t N, index_t K, Trans ta, Trans tb, float beta, GemmBackend backend,
                          int reps, int calls, ThreadPool& pool = global_pool()) {
  std::vector<float> a(M * K), b(N * K), c(M * N);
  for (std::size_t i = 0; i < a.size(); ++i) a[i] = float(i % 7) * 0.125f - 0.375f;
  for (std::size_t i = 0; i < b.size(); ++i) b[i] = float(i % 5) * 0.125f - 0.25f;
  const index_t lda = ta == Trans::yes ? M : K, ldb = tb == Trans::yes ? K : N;
  auto round = [&] {
    const auto t0 = std::chrono::steady_clock::now();
    for (int i = 0; i < calls; ++i)
      gemm(backend, ta, tb, M, N, K, 1.0f, a.data(), lda, b.data(), ldb, beta, c.data(), N, pool);
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() / calls;
  };
  round();  // warm-up
  double best = 1e300;
  for (int r = 0; r < reps; ++r) best = std::min(best, round());
  return 2.0 * double(M) * double(N) * double(K) / best * 1e-9;
}

inline double sgemm_gflops(GemmBackend backend = best_gemm_backend(), int reps = 5, ThreadPool& pool = global_pool()) {
  return gemm_gflops(2048, 2048, 1024, Trans::no, Trans::yes, 0.0f, backend, reps, 1, pool);
}

struct SgemmRate {
  double gflops = 0;
  GemmBackend backend = GemmBackend::eigen;
};

// The machine's SGEMM rate: the best over every fp32 backend, measured interleaved (`rounds` x `reps` calls each).
inline SgemmRate best_sgemm(int reps = 3, ThreadPool& pool = global_pool(), int rounds = 2) {
  SgemmRate best;
  for (int r = 0; r < rounds; ++r)
    for (GemmBackend b : fp32_gemm_backends())
      if (const double g = sgemm_gflops(b, reps, pool); g > best.gflops) best = {g, b};
  return best;
}

// e.g. "portable (sse2 batches), gemm on oneDNN fp32" or "native (avx512bw batches), gemm on Eigen (no BLAS ...)".
inline std::string build_label() {
#if defined(__AVX2__)
  const char* kind = "native";
#else
  const char* kind = "portable";
#endif
  const GemmBackend b = default_gemm_backend();
  return concat(kind, " (", simd::compiled_arch_name(), " batches), gemm on ",
                b == GemmBackend::onednn        ? "oneDNN fp32"
                : b == GemmBackend::blas        ? "BLAS"
                : b == GemmBackend::bf16        ? "oneDNN bf16 (FLEXSPLAT_GEMM=bf16)"
                : have_blas || have_onednn_gemm ? "Eigen (FLEXSPLAT_GEMM=eigen)"
                                                : "Eigen (no BLAS in this build)");
}

// The SGEMM line every such benchmark prints: which backend gave the reference rate, and the build.
inline std::string sgemm_label(GemmBackend rate_backend = best_gemm_backend()) {
  return concat("SGEMM 2048x2048x1024, fastest of ", fp32_gemm_backends().size(), " fp32 backend(s): ",
                gemm_backend_name(rate_backend), "; build: ", build_label());
}

}  // namespace flexsplat::bench
