#pragma once
// The machine's SGEMM rate for the benchmarks' "of SGEMM" columns, and a label naming the build that produced a row.
// The rate is 2048x2048x1024, C = A B^T (nn::linear's form), float, on the pool's threads, best of `reps` after a
// warm-up, through the BLAS when the build has one: the machine's rate, not this build's Eigen rate.
#include <algorithm>
#include <chrono>
#include <string>
#include <vector>

#include "flexsplat/core/gemm.hpp"
#include "flexsplat/core/simd.hpp"

namespace flexsplat::bench {

inline GemmBackend best_gemm_backend() { return have_blas ? GemmBackend::blas : GemmBackend::eigen; }

inline double sgemm_gflops(GemmBackend backend = best_gemm_backend(), int reps = 5, ThreadPool& pool = global_pool()) {
  const index_t M = 2048, N = 2048, K = 1024;
  std::vector<float> a(M * K), b(N * K), c(M * N);
  for (std::size_t i = 0; i < a.size(); ++i) a[i] = float(i % 7) * 0.125f - 0.375f;
  for (std::size_t i = 0; i < b.size(); ++i) b[i] = float(i % 5) * 0.125f - 0.25f;
  auto run = [&] { gemm(backend, Trans::no, Trans::yes, M, N, K, 1.0f, a.data(), K, b.data(), K, 0.0f, c.data(), N, pool); };
  run();  // warm-up
  double best = 1e300;
  for (int r = 0; r < reps; ++r) {
    const auto t0 = std::chrono::steady_clock::now();
    run();
    best = std::min(best, std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
  }
  return 2.0 * double(M) * double(N) * double(K) / best * 1e-9;
}

// e.g. "portable (sse2 batches), gemm on OpenBLAS" or "native (avx512bw batches), gemm on Eigen (no BLAS)".
inline std::string build_label() {
#if defined(__AVX2__)
  const char* kind = "native";
#else
  const char* kind = "portable";
#endif
  const GemmBackend b = default_gemm_backend();
  return concat(kind, " (", simd::compiled_arch_name(), " batches), gemm on ",
                b == GemmBackend::blas   ? "BLAS"
                : b == GemmBackend::bf16 ? "oneDNN bf16 (FLEXSPLAT_GEMM=bf16)"
                : have_blas              ? "Eigen (FLEXSPLAT_GEMM=eigen)"
                                         : "Eigen (no BLAS in this build)");
}

// The SGEMM line every such benchmark prints: which backend gave the reference rate, and the build.
inline std::string sgemm_label() {
  return concat("SGEMM 2048x2048x1024 on ", gemm_backend_name(best_gemm_backend()), "; build: ", build_label());
}

}  // namespace flexsplat::bench
