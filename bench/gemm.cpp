// GEMM throughput: flexsplat::gemm (Eigen kernels split over the pool) against a naive triple loop, float.
// Usage: build/bench/gemm [max_size]   (sizes 256, 512, ... up to max_size, default 2048)
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <random>
#include <vector>

#include "flexsplat/core/gemm.hpp"
#include "flexsplat/core/simd.hpp"

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
  f();  // warm-up
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

}  // namespace

int main(int argc, char** argv) {
  const index_t max_size = argc > 1 ? std::atoll(argv[1]) : 2048;
  std::printf("gemm bench: float, row-major C = A B, compiled for %s, CPU: %s\n", simd::compiled_arch_name(),
              simd::describe(simd::cpu_features()).c_str());
  std::printf("%6s  %14s  %14s  %14s  %12s  %12s\n", "n", "naive GFLOP/s", "gemm 1T GFLOP/s", "gemm 2T GFLOP/s",
              "speedup 2T", "max rel diff");
  ThreadPool one(1), two(2);
  bool all_agree = true;
  for (index_t n = 256; n <= max_size; n *= 2) {
    std::mt19937 rng(7);
    std::uniform_real_distribution<float> u(-1.0f, 1.0f);
    std::vector<float> A(n * n), B(n * n), C1(n * n), C2(n * n), Cn(n * n);
    for (auto& x : A) x = u(rng);
    for (auto& x : B) x = u(rng);
    const double flops = 2.0 * double(n) * double(n) * double(n);
    const double min_seconds = 0.5;
    const double t_naive = seconds_per_call([&] { naive_gemm(n, A.data(), B.data(), Cn.data()); }, min_seconds);
    const double t1 = seconds_per_call([&] {
      gemm(Trans::no, Trans::no, n, n, n, 1.0f, A.data(), n, B.data(), n, 0.0f, C1.data(), n, one);
    }, min_seconds);
    const double t2 = seconds_per_call([&] {
      gemm(Trans::no, Trans::no, n, n, n, 1.0f, A.data(), n, B.data(), n, 0.0f, C2.data(), n, two);
    }, min_seconds);
    // Difference relative to the largest magnitude of the naive result.
    double max_diff = 0, max_ref = 0;
    for (index_t i = 0; i < n * n; ++i) {
      max_ref = std::max(max_ref, double(std::abs(Cn[i])));
      max_diff = std::max({max_diff, double(std::abs(C1[i] - Cn[i])), double(std::abs(C2[i] - Cn[i]))});
    }
    const double rel = max_diff / max_ref;
    all_agree = all_agree && rel <= 1e-5;
    std::printf("%6lld  %14.2f  %14.2f  %14.2f  %12.2f  %12.2e\n", static_cast<long long>(n), flops / t_naive * 1e-9,
                flops / t1 * 1e-9, flops / t2 * 1e-9, t1 / t2, rel);
    std::fflush(stdout);
  }
  std::printf("agreement within 1e-5 relative: %s\n", all_agree ? "yes" : "NO");
  return all_agree ? 0 : 1;
}
