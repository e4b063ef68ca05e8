#include <catch2/catch.hpp>

#include <cmath>
#include <limits>
#include <random>
#include <vector>

#include "flexsplat/core/gemm.hpp"

using namespace flexsplat;

namespace {
template <class T>
std::vector<T> random_vector(std::size_t n, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<T> u(T(-1), T(1));
  std::vector<T> v(n);
  for (auto& x : v) x = u(rng);
  return v;
}

// Reference: element-by-element definition of op(A) op(B) in long double.
template <class T>
void naive_gemm(Trans ta, Trans tb, index_t M, index_t N, index_t K, T alpha, const T* A, index_t lda, const T* B,
                index_t ldb, T beta, T* C, index_t ldc) {
  for (index_t i = 0; i < M; ++i)
    for (index_t j = 0; j < N; ++j) {
      long double s = 0;
      for (index_t k = 0; k < K; ++k) {
        const T a = ta == Trans::no ? A[i * lda + k] : A[k * lda + i];
        const T b = tb == Trans::no ? B[k * ldb + j] : B[j * ldb + k];
        s += static_cast<long double>(a) * b;
      }
      const long double old = beta == T(0) ? 0.0L : static_cast<long double>(beta) * C[i * ldc + j];
      C[i * ldc + j] = static_cast<T>(static_cast<long double>(alpha) * s + old);
    }
}

template <class T>
double max_abs_diff(const std::vector<T>& a, const std::vector<T>& b) {
  double m = 0;
  for (std::size_t i = 0; i < a.size(); ++i) m = std::max(m, std::abs(double(a[i]) - double(b[i])));
  return m;
}

struct Case {
  index_t M, N, K, pad;
};
}  // namespace

TEMPLATE_TEST_CASE("gemm matches the naive loop for every transpose, stride and beta", "[gemm]", float, double) {
  ThreadPool pool(2);
  const Case cases[] = {{1, 1, 1, 0}, {3, 5, 7, 2}, {17, 9, 33, 3}, {70, 65, 80, 5}, {128, 96, 64, 0}};
  // Per-element bound: K products of values in [-1, 1], with a few ulps of slack per accumulation.
  for (const auto& c : cases)
    for (Trans ta : {Trans::no, Trans::yes})
      for (Trans tb : {Trans::no, Trans::yes})
        for (TestType beta : {TestType(0), TestType(1), TestType(-0.5)}) {
          INFO("M " << c.M << " N " << c.N << " K " << c.K << " pad " << c.pad << " ta " << int(ta) << " tb "
                    << int(tb) << " beta " << beta);
          const index_t a_rows = ta == Trans::no ? c.M : c.K, a_cols = ta == Trans::no ? c.K : c.M;
          const index_t b_rows = tb == Trans::no ? c.K : c.N, b_cols = tb == Trans::no ? c.N : c.K;
          const index_t lda = a_cols + c.pad, ldb = b_cols + 2 * c.pad, ldc = c.N + c.pad;
          const auto A = random_vector<TestType>(static_cast<std::size_t>(a_rows * lda), 11);
          const auto B = random_vector<TestType>(static_cast<std::size_t>(b_rows * ldb), 12);
          auto C = random_vector<TestType>(static_cast<std::size_t>(c.M * ldc), 13);
          auto expected = C;
          const TestType alpha = TestType(1.25);
          gemm(ta, tb, c.M, c.N, c.K, alpha, A.data(), lda, B.data(), ldb, beta, C.data(), ldc, pool);
          naive_gemm(ta, tb, c.M, c.N, c.K, alpha, A.data(), lda, B.data(), ldb, beta, expected.data(), ldc);
          const double tol = 4.0 * double(c.K + 2) * std::numeric_limits<TestType>::epsilon();
          REQUIRE(max_abs_diff(C, expected) <= tol);
          // Padding columns of C are never written.
          if (c.pad > 0) {
            const auto original = random_vector<TestType>(static_cast<std::size_t>(c.M * ldc), 13);
            for (index_t i = 0; i < c.M; ++i)
              for (index_t j = c.N; j < ldc; ++j) REQUIRE(C[i * ldc + j] == original[i * ldc + j]);
          }
        }
}

TEMPLATE_TEST_CASE("gemm with beta 0 ignores NaN in C and K = 0 only scales C", "[gemm]", float, double) {
  const index_t M = 4, N = 3, K = 5;
  const auto A = random_vector<TestType>(M * K, 1), B = random_vector<TestType>(K * N, 2);
  std::vector<TestType> C(M * N, std::numeric_limits<TestType>::quiet_NaN()), expected(M * N, 0);
  gemm(Trans::no, Trans::no, M, N, K, TestType(1), A.data(), K, B.data(), N, TestType(0), C.data(), N);
  naive_gemm(Trans::no, Trans::no, M, N, K, TestType(1), A.data(), K, B.data(), N, TestType(0), expected.data(), N);
  for (auto v : C) REQUIRE(std::isfinite(v));
  CHECK(max_abs_diff(C, expected) <= 1e-5);
  std::vector<TestType> D(M * N, TestType(2));
  gemm(Trans::no, Trans::no, M, N, 0, TestType(1), A.data(), K, B.data(), N, TestType(3), D.data(), N);
  for (auto v : D) CHECK(v == TestType(6));
}

TEMPLATE_TEST_CASE("gemm_batched matches per-matrix products, serial and parallel", "[gemm]", float, double) {
  ThreadPool pool(2);
  const index_t M = 9, N = 11, K = 13, lda = 13, ldb = 11, ldc = 12;
  for (index_t count : {1, 3, 8}) {
    const index_t sa = M * lda + 1, sb = K * ldb + 2, sc = M * ldc + 3;
    const auto A = random_vector<TestType>(static_cast<std::size_t>(count * sa), 21);
    const auto B = random_vector<TestType>(static_cast<std::size_t>(count * sb), 22);
    auto C = random_vector<TestType>(static_cast<std::size_t>(count * sc), 23);
    auto expected = C;
    gemm_batched(count, Trans::no, Trans::yes, M, N, K / 2, TestType(0.5), A.data(), lda, sa, B.data(), ldb, sb,
                 TestType(2), C.data(), ldc, sc, pool);
    for (index_t b = 0; b < count; ++b)
      naive_gemm(Trans::no, Trans::yes, M, N, K / 2, TestType(0.5), A.data() + b * sa, lda, B.data() + b * sb, ldb,
                 TestType(2), expected.data() + b * sc, ldc);
    INFO("count " << count);
    CHECK(max_abs_diff(C, expected) <= 64 * std::numeric_limits<TestType>::epsilon());
  }
}

TEST_CASE("gemm is deterministic across thread counts", "[gemm]") {
  const index_t M = 200, N = 150, K = 120;
  const auto A = random_vector<float>(M * K, 31), B = random_vector<float>(K * N, 32);
  std::vector<float> c1(M * N), c2(M * N), c2_again(M * N);
  ThreadPool one(1), two(2);
  gemm(Trans::no, Trans::no, M, N, K, 1.0f, A.data(), K, B.data(), N, 0.0f, c1.data(), N, one);
  gemm(Trans::no, Trans::no, M, N, K, 1.0f, A.data(), K, B.data(), N, 0.0f, c2.data(), N, two);
  gemm(Trans::no, Trans::no, M, N, K, 1.0f, A.data(), K, B.data(), N, 0.0f, c2_again.data(), N, two);
  CHECK(c2 == c2_again);
  CHECK(max_abs_diff(c1, c2) <= 1e-4);
}
