// GEMM throughput of flexsplat::gemm on its fp32 backends (Eigen's kernels, the BLAS and oneDNN's matmul when the
// build has them) against a naive triple loop, float; then the reference SGEMM 2048x2048x1024 (C = A B^T) the other
// benchmarks divide by (the fastest backend), and the per-call time of small products on one thread (where
// gemm_blas_min_madds comes from); with oneDNN, its fp32 matmul per call against the BLAS (gemm_onednn_min_madds)
// and the bf16 backend on the reference shape and per call (gemm_bf16_min_madds).
// Usage: build/bench/gemm [max_size] [rounds]   (sizes 256, 512, ... up to max_size, default 2048; rounds default 3)
// Backends and thread counts run interleaved, `rounds` times each, and the best time is kept: the machine is shared.
#include <sys/resource.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <random>
#include <thread>
#include <vector>

#include "flexsplat/core/gemm.hpp"
#include "flexsplat/core/simd.hpp"
#include "sgemm_rate.hpp"

using namespace flexsplat;

namespace {

// i-k-j order: the textbook loop with unit-stride inner access (the compiler may vectorise it).
void naive_gemm(index_t n, const float* A, const float* B, float* C) {
  std::fill(C, C + n * n, 0.0f);
  for (index_t i = 0; i < n; ++i)
    for (index_t k = 0; k < n; ++k) {
      const float a = A[i * n + k];
      for (index_t j = 0; j < n; ++j) C[i * n + j] += a * B[k * n + j];
    }
}

template <class F>
double seconds_per_call(F&& f, double min_seconds) {
  using clock = std::chrono::steady_clock;
  int reps = 0;
  const auto start = clock::now();
  double elapsed = 0;
  do {
    f();
    ++reps;
    elapsed = std::chrono::duration<double>(clock::now() - start).count();
  } while (elapsed < min_seconds);
  return elapsed / reps;
}

std::vector<float> random_floats(index_t n, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(-1.0f, 1.0f);
  std::vector<float> v(static_cast<std::size_t>(n));
  for (auto& x : v) x = u(rng);
  return v;
}

// One row of a per-call table: C = A B^T of M x N x K on one thread through `first` and `second` (each called as
// f(M, N, K, A, B, C)), best of `rounds`, in microseconds, and their ratio.
template <class F, class G>
void per_call_row(index_t M, index_t N, index_t K, int rounds, F&& first, G&& second) {
  const auto A = random_floats(M * K, 1), B = random_floats(N * K, 2);
  std::vector<float> C(M * N);
  double t_first = 1e300, t_second = 1e300;
  for (int r = 0; r < rounds; ++r) {
    t_first = std::min(t_first, seconds_per_call([&] { first(M, N, K, A.data(), B.data(), C.data()); }, 0.05));
    t_second = std::min(t_second, seconds_per_call([&] { second(M, N, K, A.data(), B.data(), C.data()); }, 0.05));
  }
  char label[32];
  std::snprintf(label, sizeof label, "%lldx%lldx%lld", (long long)M, (long long)N, (long long)K);
  std::printf("%16s  %10lld  %9.2f  %9.2f  %8.2f\n", label, static_cast<long long>(M * N * K), t_first * 1e6,
              t_second * 1e6, t_first / t_second);
}

}  // namespace

int main(int argc, char** argv) {
  const index_t max_size = argc > 1 ? std::atoll(argv[1]) : 2048;
  const int rounds = argc > 2 ? std::atoi(argv[2]) : 3;
  std::printf("gemm bench: float, row-major; build: %s; CPU: %s\n", bench::build_label().c_str(),
              simd::describe(simd::cpu_features()).c_str());
  std::vector<GemmBackend> backends{GemmBackend::eigen};
  if (have_blas) backends.push_back(GemmBackend::blas);
  if (have_onednn_gemm) backends.push_back(GemmBackend::onednn);
  auto short_name = [](GemmBackend b) {
    return b == GemmBackend::blas ? "blas" : b == GemmBackend::onednn ? "onednn" : "eigen";
  };
  for (GemmBackend b : backends) std::printf("backend %-6s: %s\n", short_name(b), gemm_backend_name(b).c_str());
  std::printf("default fp32 backend: %s\n", short_name(fastest_fp32_gemm_backend()));
  ThreadPool one(1), two(2);
  ThreadPool* pools[] = {&one, &two};

  std::printf("\nC = A B, n x n x n, GFLOP/s (best of %d interleaved rounds); max rel diff = max |gemm - naive| / "
              "max |naive| over all runs\n", rounds);
  std::printf("%6s  %8s", "n", "naive");
  for (GemmBackend b : backends) std::printf("  %7s 1T  %7s 2T", short_name(b), short_name(b));
  std::printf("  %12s\n", "max rel diff");
  bool all_agree = true;
  for (index_t n = 256; n <= max_size; n *= 2) {
    const auto A = random_floats(n * n, 7), B = random_floats(n * n, 8);
    std::vector<float> C(n * n), Cn(n * n);
    const double flops = 2.0 * double(n) * double(n) * double(n);
    const auto t0 = std::chrono::steady_clock::now();
    naive_gemm(n, A.data(), B.data(), Cn.data());
    const double t_naive = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    double max_ref = 0;
    for (float v : Cn) max_ref = std::max(max_ref, double(std::abs(v)));
    double best[3][2] = {{1e300, 1e300}, {1e300, 1e300}, {1e300, 1e300}}, max_diff = 0;
    for (int r = 0; r < rounds; ++r)
      for (std::size_t b = 0; b < backends.size(); ++b)
        for (int p = 0; p < 2; ++p) {
          auto call = [&] {
            gemm(backends[b], Trans::no, Trans::no, n, n, n, 1.0f, A.data(), n, B.data(), n, 0.0f, C.data(), n,
                 *pools[p]);
          };
          if (r == 0) call();  // warm-up
          best[b][p] = std::min(best[b][p], seconds_per_call(call, 0.2));
          for (index_t i = 0; i < n * n; ++i) max_diff = std::max(max_diff, double(std::abs(C[i] - Cn[i])));
        }
    const double rel = max_diff / max_ref;
    all_agree = all_agree && rel <= 1e-5;
    std::printf("%6lld  %8.2f", static_cast<long long>(n), flops / t_naive * 1e-9);
    for (std::size_t b = 0; b < backends.size(); ++b)
      std::printf("  %10.2f  %10.2f", flops / best[b][0] * 1e-9, flops / best[b][1] * 1e-9);
    std::printf("  %12.2e\n", rel);
    std::fflush(stdout);
  }

  // The reference the "of SGEMM" columns use, with 2 threads, backends interleaved.
  double ref[3] = {0, 0, 0};
  for (int r = 0; r < std::max(rounds, 3); ++r)
    for (std::size_t b = 0; b < backends.size(); ++b)
      ref[b] = std::max(ref[b], bench::sgemm_gflops(backends[b], 2, two));
  std::printf("\nSGEMM 2048x2048x1024 (C = A B^T), 2 threads, best of %d rounds:", 2 * std::max(rounds, 3));
  for (std::size_t b = 0; b < backends.size(); ++b)
    std::printf("%s %s %.1f GFLOP/s (%.2fx eigen)", b ? "," : "", short_name(backends[b]), ref[b], ref[b] / ref[0]);
  std::printf("\n");
#if defined(FLEXSPLAT_HAVE_OPENBLAS)
  {
    // gemm's choice (single-threaded OpenBLAS calls on the pool's 2 workers) against OpenBLAS's own 2 threads.
    const index_t M = 2048, N = 2048, K = 1024;
    const auto A = random_floats(M * K, 3), B = random_floats(N * K, 4);
    std::vector<float> C(M * N);
    double t_split = 1e300, t_own = 1e300;
    for (int r = 0; r < 2 * std::max(rounds, 3); ++r) {
      t_split = std::min(t_split, seconds_per_call([&] {
        gemm(GemmBackend::blas, Trans::no, Trans::yes, M, N, K, 1.0f, A.data(), K, B.data(), K, 0.0f, C.data(), N, two);
      }, 0.0));
      openblas_set_num_threads(2);
      t_own = std::min(t_own, seconds_per_call([&] {
        cblas_sgemm(CblasRowMajor, CblasNoTrans, CblasTrans, int(M), int(N), int(K), 1.0f, A.data(), int(K), B.data(),
                    int(K), 0.0f, C.data(), int(N));
      }, 0.0));
      openblas_set_num_threads(1);
    }
    const double flops = 2.0 * double(M) * double(N) * double(K);
    std::printf("same product on OpenBLAS: gemm's split over the pool (2 x 1 thread) %.1f GFLOP/s, OpenBLAS's own 2 "
                "threads %.1f GFLOP/s\n", flops / t_split * 1e-9, flops / t_own * 1e-9);
    // What OpenBLAS's threads cost after a call returns: CPU time of this process while its caller sleeps 0.3 s.
    auto cpu_seconds = [] {
      rusage u{};
      getrusage(RUSAGE_SELF, &u);
      return double(u.ru_utime.tv_sec + u.ru_stime.tv_sec) + double(u.ru_utime.tv_usec + u.ru_stime.tv_usec) * 1e-6;
    };
    for (int threads : {2, 1}) {
      openblas_set_num_threads(threads);
      cblas_sgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, 512, 512, 512, 1.0f, A.data(), 512, B.data(), 512, 0.0f,
                  C.data(), 512);
      const double c0 = cpu_seconds();
      std::this_thread::sleep_for(std::chrono::milliseconds(300));
      std::printf("CPU seconds the process used during a 0.3 s sleep after a 512^3 OpenBLAS call on %d thread%s: %.3f\n",
                  threads, threads > 1 ? "s" : "", cpu_seconds() - c0);
    }
    openblas_set_num_threads(1);
  }
#endif

#if defined(FLEXSPLAT_HAVE_CBLAS)
  // Small products on one thread: microseconds per call, the BLAS called directly (bypassing gemm_blas_min_madds).
  std::printf("\nsmall C = A B^T on one thread, microseconds per call (best of %d rounds); gemm uses the BLAS from "
              "M N K >= %lld\n", rounds, static_cast<long long>(gemm_blas_min_madds));
  std::printf("%16s  %10s  %9s  %9s  %8s\n", "M x N x K", "M N K", "eigen us", "blas us", "eigen/blas");
  const index_t shapes[][3] = {{4, 4, 4}, {8, 8, 8},    {12, 12, 12}, {16, 16, 16},  {24, 24, 24},  {32, 32, 32},  {48, 48, 48},
                               {64, 64, 64}, {96, 96, 96},  {128, 128, 128}, {4, 256, 256}, {64, 256, 64},
                               {256, 64, 64}, {1024, 64, 16}};
  for (const auto& s : shapes) {
    const index_t M = s[0], N = s[1], K = s[2];
    per_call_row(M, N, K, rounds,
                 [](index_t m, index_t n, index_t k, const float* a, const float* b, float* c) {
                   detail::gemm_block(GemmBackend::eigen, Trans::no, Trans::yes, m, n, k, 1.0f, a, k, b, k, 0.0f, c, n);
                 },
                 [](index_t m, index_t n, index_t k, const float* a, const float* b, float* c) {
                   detail::blas_gemm(Trans::no, Trans::yes, m, n, k, 1.0f, a, k, b, k, 0.0f, c, n);
                 });
  }
#endif
#if defined(FLEXSPLAT_HAVE_DNNL)
  {
    // oneDNN's fp32 matmul against the fp32 fallback, called directly (bypassing gemm_onednn_min_madds).
    const GemmBackend fallback = have_blas ? GemmBackend::blas : GemmBackend::eigen;
    std::printf("\nC = A B^T on one thread, microseconds per call (best of %d rounds); gemm's onednn backend uses "
                "oneDNN from M N K >= %lld\n", rounds, static_cast<long long>(gemm_onednn_min_madds));
    std::printf("%16s  %10s  %9s  %9s  %8s\n", "M x N x K", "M N K", have_blas ? "blas us" : "eigen us", "onednn us",
                "ratio");
    const index_t shapes[][3] = {{16, 16, 16},    {32, 32, 32},     {48, 48, 48},      {64, 64, 64},
                                 {96, 96, 96},    {128, 128, 128},  {256, 64, 64},     {64, 256, 64},
                                 {256, 256, 256}, {512, 512, 512},  {658, 3072, 1024}, {658, 1024, 4096},
                                 {128, 16384, 1152}};
    for (const auto& shape : shapes) {
      per_call_row(shape[0], shape[1], shape[2], rounds,
                   [&](index_t m, index_t n, index_t k, const float* a, const float* b, float* c) {
                     detail::gemm_block(fallback, Trans::no, Trans::yes, m, n, k, 1.0f, a, k, b, k, 0.0f, c, n);
                   },
                   [](index_t m, index_t n, index_t k, const float* a, const float* b, float* c) {
                     detail::onednn_gemm(false, Trans::no, Trans::yes, m, n, k, 1.0f, a, k, b, k, 0.0f, c, n);
                   });
    }
  }
  {
    // How gemm splits C over 2 threads: rows or columns, C = W X (NN) as in the DPT convolutions (weights x im2col),
    // each part one single-threaded oneDNN call; gemm splits columns from N >= 4 M.
    std::printf("\nC = W X (no transposes) on 2 threads, oneDNN fp32, GFLOP/s by how C is split (best of %d rounds)\n",
                2 * rounds);
    std::printf("%18s  %9s  %9s  %8s\n", "M x N x K", "rows", "columns", "cols/rows");
    const index_t split_shapes[][3] = {{256, 1296, 2304}, {256, 1800, 2304}, {256, 5184, 256}, {32, 5000, 1152},
                                       {1024, 1316, 1024}, {3072, 1316, 1024}};
    for (const auto& shape : split_shapes) {
      const index_t M = shape[0], N = shape[1], K = shape[2];
      const auto A = random_floats(M * K, 5), B = random_floats(K * N, 6);
      std::vector<float> C(M * N);
      double t[2] = {1e300, 1e300};
      for (int r = 0; r < 2 * rounds; ++r)
        for (int cols = 0; cols < 2; ++cols)
          t[cols] = std::min(t[cols], seconds_per_call([&] {
            parallel_for(2, [&](index_t k0, index_t k1, int) {
              for (index_t k = k0; k < k1; ++k) {
                const index_t e = cols ? N : M, lo = e * k / 2, hi = e * (k + 1) / 2;
                if (cols)
                  detail::onednn_gemm(false, Trans::no, Trans::no, M, hi - lo, K, 1.0f, A.data(), K, B.data() + lo, N,
                                      0.0f, C.data() + lo, N);
                else
                  detail::onednn_gemm(false, Trans::no, Trans::no, hi - lo, N, K, 1.0f, A.data() + lo * K, K, B.data(),
                                      N, 0.0f, C.data() + lo * N, N);
              }
            }, two);
          }, 0.0));
      const double flops = 2.0 * double(M) * double(N) * double(K);
      char label[40];
      std::snprintf(label, sizeof label, "%lldx%lldx%lld", (long long)M, (long long)N, (long long)K);
      std::printf("%18s  %9.1f  %9.1f  %8.2f\n", label, flops / t[0] * 1e-9, flops / t[1] * 1e-9, t[0] / t[1]);
    }
  }
  {
    // The reference shape in bf16 (operands rounded, fp32 accumulation) next to fp32, interleaved, 2 threads.
    const index_t M = 2048, N = 2048, K = 1024;
    const auto A = random_floats(M * K, 3), B = random_floats(N * K, 4);
    std::vector<float> C(M * N);
    const GemmBackend fp32 = bench::best_gemm_backend();
    double t32 = 1e300, t16 = 1e300;
    for (int r = 0; r < 2 * std::max(rounds, 3); ++r) {
      t32 = std::min(t32, seconds_per_call([&] {
        gemm(fp32, Trans::no, Trans::yes, M, N, K, 1.0f, A.data(), K, B.data(), K, 0.0f, C.data(), N, two);
      }, 0.0));
      t16 = std::min(t16, seconds_per_call([&] {
        gemm(GemmBackend::bf16, Trans::no, Trans::yes, M, N, K, 1.0f, A.data(), K, B.data(), K, 0.0f, C.data(), N, two);
      }, 0.0));
    }
    const double flops = 2.0 * double(M) * double(N) * double(K);
    std::printf("\nbf16: %s\nSGEMM shape 2048x2048x1024, 2 threads: fp32 %.1f GFLOP/s, bf16 %.1f GFLOP/s (%.2fx)\n",
                gemm_backend_name(GemmBackend::bf16).c_str(), flops / t32 * 1e-9, flops / t16 * 1e-9, t32 / t16);
    std::printf("\nC = A B^T on one thread, microseconds per call (best of %d rounds); gemm uses bf16 from M N K >= "
                "%lld\n", rounds, static_cast<long long>(gemm_bf16_min_madds));
    std::printf("%16s  %10s  %9s  %9s  %8s\n", "M x N x K", "M N K", "fp32 us", "bf16 us", "fp32/bf16");
    const index_t shapes[][3] = {{32, 32, 32},    {64, 64, 64},    {96, 96, 96},     {128, 128, 128},
                                 {256, 64, 64},   {256, 256, 64},  {256, 256, 256},  {512, 256, 256},
                                 {512, 512, 512}, {329, 1024, 1024}, {1316, 4096, 1024}};
    for (const auto& shape : shapes) {
      per_call_row(shape[0], shape[1], shape[2], rounds,
                   [&](index_t m, index_t n, index_t k, const float* a, const float* b, float* c) {
                     detail::gemm_block(fp32, Trans::no, Trans::yes, m, n, k, 1.0f, a, k, b, k, 0.0f, c, n);
                   },
                   [](index_t m, index_t n, index_t k, const float* a, const float* b, float* c) {
                     detail::bf16_gemm(Trans::no, Trans::yes, m, n, k, 1.0f, a, k, b, k, 0.0f, c, n);
                   });
    }
    // VGGT's linear layers (1316 tokens split over two workers, and the camera head's 4 rows) with B the weights:
    // reordered per call, or packed once by a GemmWeightCache (what predict does with keep_packed_weights).
    std::printf("\nC = A B^T, B [N, K] fixed weights, one thread, microseconds per call (best of %d rounds)\n", rounds);
    std::printf("%16s  %9s  %9s  %11s  %11s\n", "M x N x K", "fp32 us", "bf16 us", "packed us", "fp32/packed");
    const index_t layers[][3] = {{658, 3072, 1024}, {658, 1024, 1024}, {658, 4096, 1024}, {658, 1024, 4096},
                                 {329, 1024, 1024}, {4, 4096, 1024}};
    for (const auto& shape : layers) {
      const index_t M = shape[0], N = shape[1], K = shape[2];
      const auto A = random_floats(M * K, 5), B = random_floats(N * K, 6);
      std::vector<float> C(M * N);
      GemmWeightCache cache;
      cache.freeze(B.data(), B.size());
      double t[3] = {1e300, 1e300, 1e300};
      for (int r = 0; r < rounds; ++r) {
        t[0] = std::min(t[0], seconds_per_call([&] {
          detail::gemm_block(fp32, Trans::no, Trans::yes, M, N, K, 1.0f, A.data(), K, B.data(), K, 0.0f, C.data(), N);
        }, 0.05));
        t[1] = std::min(t[1], seconds_per_call([&] {
          detail::bf16_gemm(Trans::no, Trans::yes, M, N, K, 1.0f, A.data(), K, B.data(), K, 0.0f, C.data(), N);
        }, 0.05));
        t[2] = std::min(t[2], seconds_per_call([&] {
          cache.multiply(Trans::no, Trans::yes, M, N, K, 1.0f, A.data(), K, B.data(), K, 0.0f, C.data(), N);
        }, 0.05));
      }
      char label[32];
      std::snprintf(label, sizeof label, "%lldx%lldx%lld", (long long)M, (long long)N, (long long)K);
      std::printf("%16s  %9.1f  %9.1f  %11.1f  %11.2f\n", label, t[0] * 1e6, t[1] * 1e6, t[2] * 1e6, t[0] / t[2]);
    }
  }
#endif
  std::printf("\nagreement within 1e-5 relative: %s\n", all_agree ? "yes" : "NO");
  return all_agree ? 0 : 1;
}
