#include <catch2/catch.hpp>

#include <cmath>
#include <limits>
#include <random>
#include <vector>

#include "flexsplat/core/simd_kernels.hpp"

using namespace flexsplat;

namespace {
template <class T>
std::vector<T> random_kernel_input(std::size_t n, unsigned seed, T lo = T(-1), T hi = T(1)) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<T> u(lo, hi);
  std::vector<T> v(n);
  for (auto& x : v) x = u(rng);
  return v;
}
template <class T>
constexpr T eps = std::numeric_limits<T>::epsilon();
}  // namespace

// Sizes hit the empty case, pure tails, one batch, the 4-batch unrolled loop and odd remainders.
static const index_t sizes[] = {0, 1, 3, 7, 8, 15, 16, 17, 31, 64, 100, 257, 1000};

TEMPLATE_TEST_CASE("simd dot and axpy agree with the scalar path", "[simd]", float, double) {
  INFO("compiled for " << simd::compiled_arch_name() << ", width " << simd::width<TestType>);
  for (index_t n : sizes) {
    INFO("n = " << n);
    const auto a = random_kernel_input<TestType>(static_cast<std::size_t>(n), 1);
    const auto b = random_kernel_input<TestType>(static_cast<std::size_t>(n), 2);
    double bound = 0;  // |sum a_i b_i| rounding bound of either summation order
    double exact = 0;
    for (index_t i = 0; i < n; ++i) {
      bound += std::abs(double(a[i]) * double(b[i]));
      exact += double(a[i]) * double(b[i]);
    }
    const TestType s = simd::dot_scalar(a.data(), b.data(), n);
    const TestType v = simd::dot_simd(a.data(), b.data(), n);
    CHECK(std::abs(double(s) - exact) <= 2.0 * double(n) * eps<TestType> * bound + 1e-300);
    CHECK(std::abs(double(v) - exact) <= 2.0 * double(n) * eps<TestType> * bound + 1e-300);
    CHECK(simd::dot(a.data(), b.data(), n) == (simd::enabled() ? v : s));

    auto y_scalar = random_kernel_input<TestType>(static_cast<std::size_t>(n), 3);
    auto y_simd = y_scalar;
    simd::axpy_scalar(n, TestType(0.75), a.data(), y_scalar.data());
    simd::axpy_simd(n, TestType(0.75), a.data(), y_simd.data());
    for (index_t i = 0; i < n; ++i)  // fma rounds once, the scalar path twice
      REQUIRE(std::abs(y_scalar[i] - y_simd[i]) <= 2 * eps<TestType> * (std::abs(y_scalar[i]) + 1));
  }
}

TEMPLATE_TEST_CASE("simd softmax matches the scalar path and sums to one", "[simd]", float, double) {
  for (index_t n : sizes) {
    if (n == 0) continue;
    INFO("n = " << n);
    auto x = random_kernel_input<TestType>(static_cast<std::size_t>(n), 4, TestType(-30), TestType(30));
    auto y_scalar = x, y_simd = x;
    simd::softmax_row_scalar(y_scalar.data(), n);
    simd::softmax_row_simd(y_simd.data(), n);
    TestType total = 0;
    for (index_t i = 0; i < n; ++i) {
      REQUIRE(std::abs(y_scalar[i] - y_simd[i]) <= 16 * eps<TestType> * y_scalar[i] + std::numeric_limits<TestType>::min());
      total += y_simd[i];
    }
    CHECK(std::abs(total - 1) <= 4 * double(n) * eps<TestType>);
    // Against an independent double-precision evaluation.
    double m = -INFINITY, sum = 0;
    for (auto v : x) m = std::max(m, double(v));
    for (auto v : x) sum += std::exp(double(v) - m);
    for (index_t i = 0; i < n; ++i)
      REQUIRE(std::abs(double(y_simd[i]) - std::exp(double(x[i]) - m) / sum) <= 32 * eps<TestType> + 1e-300);
  }
}

TEMPLATE_TEST_CASE("softmax handles large values, masked rows and rejects NaN", "[simd]", float, double) {
  const TestType inf = std::numeric_limits<TestType>::infinity();
  for (auto kernel : {&simd::softmax_row_scalar<TestType>, &simd::softmax_row_simd<TestType>}) {
    std::vector<TestType> big(19, TestType(1000));
    big[5] = TestType(1001);
    kernel(big.data(), 19);
    CHECK(big[5] > big[0]);
    CHECK(std::isfinite(big[0]));
    std::vector<TestType> masked(13, -inf);
    kernel(masked.data(), 13);
    for (auto v : masked) CHECK(v == 0);
    std::vector<TestType> partly(13, -inf);
    partly[12] = 2;
    kernel(partly.data(), 13);
    CHECK(partly[12] == 1);
    CHECK(partly[0] == 0);
    for (std::size_t where : {std::size_t(0), std::size_t(9), std::size_t(16)}) {
      std::vector<TestType> bad(17, TestType(0.5));
      bad[where] = std::numeric_limits<TestType>::quiet_NaN();
      CHECK_THROWS_WITH(kernel(bad.data(), 17), Catch::Contains("NaN or +inf"));
    }
    std::vector<TestType> plus_inf(9, 0);
    plus_inf[3] = inf;
    CHECK_THROWS_WITH(kernel(plus_inf.data(), 9), Catch::Contains("NaN or +inf"));
  }
}

TEMPLATE_TEST_CASE("softmax backward adds the vector-Jacobian product on both paths", "[simd]", float, double) {
  const index_t n = 37;
  auto y = random_kernel_input<TestType>(n, 5, TestType(-2), TestType(2));
  simd::softmax_row_scalar(y.data(), n);
  const auto dy = random_kernel_input<TestType>(n, 6);
  const auto junk = random_kernel_input<TestType>(n, 7);
  auto dx_scalar = junk, dx_simd = junk;
  simd::softmax_row_backward_scalar(y.data(), dy.data(), dx_scalar.data(), n);
  simd::softmax_row_backward_simd(y.data(), dy.data(), dx_simd.data(), n);
  // Reference from the explicit Jacobian diag(y) - y y^T.
  for (index_t i = 0; i < n; ++i) {
    double g = 0;
    for (index_t j = 0; j < n; ++j) g += ((i == j ? double(y[i]) : 0.0) - double(y[i]) * double(y[j])) * double(dy[j]);
    CHECK(std::abs(double(dx_scalar[i]) - double(junk[i]) - g) <= 64 * eps<TestType>);
    CHECK(std::abs(double(dx_simd[i]) - double(junk[i]) - g) <= 64 * eps<TestType>);
  }
}

TEST_CASE("cpu feature detection is consistent with the compiled architecture", "[simd]") {
  const auto& f = simd::cpu_features();
  INFO("detected: " << simd::describe(f) << "; compiled for " << simd::compiled_arch_name());
#if defined(__x86_64__)
  CHECK(f.sse2);  // part of x86-64
#endif
  if (f.avx2) CHECK(f.os_avx);
  if (f.avx512f) CHECK(f.os_avx512);
  if (f.avx512bf16) CHECK(f.avx512f);
  if (f.amx_permitted) CHECK(f.amx_tile);
  CHECK_NOTHROW(simd::require_cpu_supports_build());
  CHECK_FALSE(simd::describe(f).empty());
}
