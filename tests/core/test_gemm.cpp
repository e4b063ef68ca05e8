#include <catch2/catch.hpp>

#include <cmath>
#include <cstring>
#include <limits>
#include <random>
#include <thread>
#include <vector>

#include "flexsplat/core/gemm.hpp"
#include "flexsplat/core/half.hpp"
#include "skip.hpp"

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

std::vector<GemmBackend> available_backends() {
  std::vector<GemmBackend> all{GemmBackend::eigen};
  if (have_blas) all.push_back(GemmBackend::blas);
  if (have_onednn_gemm) all.push_back(GemmBackend::onednn);
  return all;
}

// Per element, sum_k |op(A)_ik| |op(B)_kj|: any two summation orders differ by at most 2 K eps times this.
std::vector<double> abs_products(index_t M, index_t N, index_t K, const std::vector<float>& A,
                                 const std::vector<float>& B) {
  std::vector<double> s(static_cast<std::size_t>(M * N), 0.0);
  for (index_t i = 0; i < M; ++i)
    for (index_t k = 0; k < K; ++k)
      for (index_t j = 0; j < N; ++j) s[i * N + j] += std::abs(double(A[i * K + k])) * std::abs(double(B[k * N + j]));
  return s;
}
}  // namespace

TEMPLATE_TEST_CASE("gemm matches the naive loop for every transpose, stride and beta", "[gemm]", float, double) {
  ThreadPool pool(2);
  const Case cases[] = {{1, 1, 1, 0}, {3, 5, 7, 2}, {17, 9, 33, 3}, {70, 65, 80, 5}, {128, 96, 64, 0}, {1, 300, 200, 1}};
  // Per-element bound: K products of values in [-1, 1], with a few ulps of slack per accumulation.
  for (GemmBackend backend : available_backends())
    for (const auto& c : cases)
      for (Trans ta : {Trans::no, Trans::yes})
        for (Trans tb : {Trans::no, Trans::yes})
          for (TestType beta : {TestType(0), TestType(1), TestType(-0.5)}) {
            INFO("backend " << gemm_backend_name(backend) << " M " << c.M << " N " << c.N << " K " << c.K << " pad "
                            << c.pad << " ta " << int(ta) << " tb " << int(tb) << " beta " << beta);
            const index_t a_rows = ta == Trans::no ? c.M : c.K, a_cols = ta == Trans::no ? c.K : c.M;
            const index_t b_rows = tb == Trans::no ? c.K : c.N, b_cols = tb == Trans::no ? c.N : c.K;
            const index_t lda = a_cols + c.pad, ldb = b_cols + 2 * c.pad, ldc = c.N + c.pad;
            const auto A = random_vector<TestType>(static_cast<std::size_t>(a_rows * lda), 11);
            const auto B = random_vector<TestType>(static_cast<std::size_t>(b_rows * ldb), 12);
            auto C = random_vector<TestType>(static_cast<std::size_t>(c.M * ldc), 13);
            auto expected = C;
            const TestType alpha = TestType(1.25);
            gemm(backend, ta, tb, c.M, c.N, c.K, alpha, A.data(), lda, B.data(), ldb, beta, C.data(), ldc, pool);
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
  // 40 x 30 x 50 is above gemm_blas_min_madds: the BLAS backend really calls the BLAS.
  for (GemmBackend backend : available_backends())
    for (index_t M : {4, 40}) {
      const index_t N = M == 4 ? 3 : 30, K = M == 4 ? 5 : 50;
      INFO("backend " << gemm_backend_name(backend) << " M " << M);
      if (M == 40) REQUIRE(M * N * K >= gemm_blas_min_madds);
      const auto A = random_vector<TestType>(M * K, 1), B = random_vector<TestType>(K * N, 2);
      std::vector<TestType> C(M * N, std::numeric_limits<TestType>::quiet_NaN()), expected(M * N, 0);
      gemm(backend, Trans::no, Trans::no, M, N, K, TestType(1), A.data(), K, B.data(), N, TestType(0), C.data(), N);
      naive_gemm(Trans::no, Trans::no, M, N, K, TestType(1), A.data(), K, B.data(), N, TestType(0), expected.data(), N);
      for (auto v : C) REQUIRE(std::isfinite(v));
      CHECK(max_abs_diff(C, expected) <= 4.0 * double(K + 2) * std::numeric_limits<TestType>::epsilon());
      std::vector<TestType> D(M * N, TestType(2));
      gemm(backend, Trans::no, Trans::no, M, N, 0, TestType(1), A.data(), K, B.data(), N, TestType(3), D.data(), N);
      for (auto v : D) CHECK(v == TestType(6));
      std::vector<TestType> E(M * N, TestType(2));
      gemm(backend, Trans::no, Trans::no, M, N, K, TestType(0), A.data(), K, B.data(), N, TestType(-1), E.data(), N);
      for (auto v : E) CHECK(v == TestType(-2));
    }
}

TEST_CASE("gemm accepts any stride for single-row operands and rejects short strides on the BLAS path", "[gemm]") {
  // With M = 1 the strides of A and C are never used, so 0 is valid there (a CBLAS would reject it unadjusted).
  const index_t M = 1, N = 600, K = 300;
  const auto A = random_vector<float>(K, 41), B = random_vector<float>(K * N, 42);
  for (GemmBackend backend : available_backends()) {
    INFO("backend " << gemm_backend_name(backend));
    std::vector<float> C(N), expected(N);
    gemm(backend, Trans::no, Trans::no, M, N, K, 1.0f, A.data(), 0, B.data(), N, 0.0f, C.data(), 0);
    naive_gemm(Trans::no, Trans::no, M, N, K, 1.0f, A.data(), K, B.data(), N, 0.0f, expected.data(), N);
    CHECK(max_abs_diff(C, expected) <= 4.0 * double(K + 2) * std::numeric_limits<float>::epsilon());
  }
  if (have_blas) {
    std::vector<float> C(4 * N);
    const auto A4 = random_vector<float>(4 * K, 43);
    CHECK_THROWS_AS(gemm(GemmBackend::blas, Trans::no, Trans::no, index_t(4), N, K, 1.0f, A4.data(), K - 1, B.data(), N,
                         0.0f, C.data(), N),
                    Error);
  } else {
    std::vector<float> C(N);
    CHECK_THROWS_AS(gemm(GemmBackend::blas, Trans::no, Trans::no, M, N, K, 1.0f, A.data(), K, B.data(), N, 0.0f,
                         C.data(), N),
                    Error);
  }
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

TEST_CASE("gemm is bitwise deterministic for a thread count, and the backends agree within 2 K eps", "[gemm]") {
  const index_t M = 200, N = 150, K = 120;
  const auto A = random_vector<float>(M * K, 31), B = random_vector<float>(K * N, 32);
  const auto bound = abs_products(M, N, K, A, B);
  const double eps = std::numeric_limits<float>::epsilon();
  ThreadPool one(1), two(2);
  std::vector<std::vector<float>> results;
  for (GemmBackend backend : available_backends())
    for (ThreadPool* pool : {&one, &two}) {
      INFO("backend " << gemm_backend_name(backend) << " threads " << pool->size());
      std::vector<float> c(M * N), again(M * N, 1.0f);
      gemm(backend, Trans::no, Trans::no, M, N, K, 1.0f, A.data(), K, B.data(), N, 0.0f, c.data(), N, *pool);
      gemm(backend, Trans::no, Trans::no, M, N, K, 1.0f, A.data(), K, B.data(), N, 0.0f, again.data(), N, *pool);
      CHECK(std::memcmp(c.data(), again.data(), c.size() * sizeof(float)) == 0);
      results.push_back(std::move(c));
    }
  // Every pair (thread counts, backends): two summation orders of the same K products.
  for (std::size_t r = 1; r < results.size(); ++r)
    for (std::size_t i = 0; i < bound.size(); ++i) {
      INFO("result " << r << " element " << i);
      REQUIRE(std::abs(double(results[r][i]) - double(results[0][i])) <= 2.0 * double(K) * eps * bound[i]);
    }
}

TEST_CASE("bf16 gemm is the fp32-accumulated product of the bf16-rounded operands", "[gemm]") {
  if constexpr (!have_bf16_gemm) FLEXSPLAT_SKIP("this build has no oneDNN: GemmBackend::bf16 is not available");
  // Every transpose, padded strides, alpha and beta, above gemm_bf16_min_madds so that oneDNN runs.
  const index_t M = 130, N = 110, K = 96, pad = 3;
  REQUIRE(M * N * K >= gemm_bf16_min_madds);
  const double eps = std::numeric_limits<float>::epsilon();
  ThreadPool one(1), two(2);
  for (Trans ta : {Trans::no, Trans::yes})
    for (Trans tb : {Trans::no, Trans::yes}) {
      const index_t lda = (ta == Trans::no ? K : M) + pad, ldb = (tb == Trans::no ? N : K) + pad, ldc = N + pad;
      const auto A = random_vector<float>((ta == Trans::no ? M : K) * lda, 41);
      const auto B = random_vector<float>((tb == Trans::no ? K : N) * ldb, 42);
      const auto C0 = random_vector<float>(M * ldc, 43);
      std::vector<float> Ar(A.size()), Br(B.size());
      for (std::size_t i = 0; i < A.size(); ++i) Ar[i] = float(bf16(A[i]));
      for (std::size_t i = 0; i < B.size(); ++i) Br[i] = float(bf16(B[i]));
      const float alpha = 0.5f, beta = 0.75f;
      std::vector<float> exact = C0, rounded = C0;
      naive_gemm(ta, tb, M, N, K, alpha, A.data(), lda, B.data(), ldb, beta, exact.data(), ldc);
      naive_gemm(ta, tb, M, N, K, alpha, Ar.data(), lda, Br.data(), ldb, beta, rounded.data(), ldc);
      double worst_vs_exact = 0, fp32_bound = 0;
      for (ThreadPool* pool : {&one, &two}) {
        INFO("ta " << int(ta) << " tb " << int(tb) << " threads " << pool->size());
        std::vector<float> c = C0;
        gemm(GemmBackend::bf16, ta, tb, M, N, K, alpha, A.data(), lda, B.data(), ldb, beta, c.data(), ldc, *pool);
        for (index_t i = 0; i < M; ++i)
          for (index_t j = 0; j < N; ++j) {
            double s = 0;  // sum_k |a| |b| of the rounded operands
            for (index_t k = 0; k < K; ++k)
              s += std::abs(double(ta == Trans::no ? Ar[i * lda + k] : Ar[k * lda + i])) *
                   std::abs(double(tb == Trans::no ? Br[k * ldb + j] : Br[j * ldb + k]));
            const std::size_t e = i * ldc + j;
            REQUIRE(std::abs(double(c[e]) - double(rounded[e])) <=
                    2.0 * double(K) * eps * alpha * s + 2.0 * eps * std::abs(double(beta) * C0[e]));
            worst_vs_exact = std::max(worst_vs_exact, std::abs(double(c[e]) - double(exact[e])));
            fp32_bound = std::max(fp32_bound, 2.0 * double(K) * eps * alpha * s);
          }
        for (index_t i = 0; i < M; ++i)
          for (index_t j = N; j < ldc; ++j) REQUIRE(c[i * ldc + j] == C0[i * ldc + j]);  // padding untouched
      }
      // The operands were rounded (8-bit significands): further from the exact product than any fp32 summation order.
      CHECK(worst_vs_exact > fp32_bound);
    }
}

TEST_CASE("GemmWeightCache: covers only operands wholly inside a frozen range", "[gemm]") {
  std::vector<float> w(100);
  GemmWeightCache cache;
  CHECK(cache.empty());
  CHECK_FALSE(cache.covers(w.data(), Trans::no, 10, 10, 10));
  cache.freeze(w.data(), w.size());
  CHECK_FALSE(cache.empty());
  CHECK(cache.covers(w.data(), Trans::no, 10, 10, 10));       // exactly the range
  CHECK(cache.covers(w.data() + 1, Trans::no, 10, 9, 10));    // ends on the last value
  CHECK_FALSE(cache.covers(w.data() + 1, Trans::no, 10, 10, 10));  // one past the end
  CHECK(cache.covers(w.data(), Trans::yes, 20, 5, 20));       // op(B) 20 x 5 stored as 5 rows of 20
  CHECK_FALSE(cache.covers(w.data(), Trans::yes, 21, 5, 21));
  std::vector<float> other(100);
  CHECK_FALSE(cache.covers(other.data(), Trans::no, 2, 2, 2));
  CHECK_THROWS_WITH(cache.freeze(nullptr, 3), Catch::Contains("null data"));
  cache.reset();
  CHECK(cache.empty());
}

TEST_CASE("bf16 gemm with a GemmWeightCache is bitwise the product without it and packs each B once", "[gemm]") {
  if constexpr (!have_bf16_gemm) FLEXSPLAT_SKIP("this build has no oneDNN: GemmBackend::bf16 is not available");
  // Row splits (tall), column splits (4 rows: a camera-head shape) and a single call, every transpose of B, alpha and
  // beta, padded strides, on 1 and 2 threads.
  struct Shape {
    index_t M, N, K;
  };
  ThreadPool one(1), two(2);
  for (const Shape sh : {Shape{130, 110, 96}, Shape{4, 640, 512}, Shape{300, 64, 80}})
    for (Trans ta : {Trans::no, Trans::yes})
      for (Trans tb : {Trans::no, Trans::yes}) {
        const index_t M = sh.M, N = sh.N, K = sh.K, pad = 5;
        REQUIRE(M * N * K >= gemm_bf16_min_madds);
        const index_t lda = (ta == Trans::no ? K : M) + pad, ldb = (tb == Trans::no ? N : K) + pad, ldc = N + pad;
        const auto A = random_vector<float>((ta == Trans::no ? M : K) * lda, 61);
        auto B = random_vector<float>((tb == Trans::no ? K : N) * ldb, 62);
        const auto C0 = random_vector<float>(M * ldc, 63);
        for (ThreadPool* pool : {&one, &two})
          for (float beta : {0.0f, 0.75f}) {
            INFO("M " << M << " ta " << int(ta) << " tb " << int(tb) << " threads " << pool->size() << " beta " << beta);
            std::vector<float> plain = C0;
            gemm(GemmBackend::bf16, ta, tb, M, N, K, 0.5f, A.data(), lda, B.data(), ldb, beta, plain.data(), ldc, *pool);
            GemmWeightCache cache;
            cache.freeze(B.data(), B.size());
            UseGemmWeightCache use(cache);
            std::vector<float> first = C0, second = C0;
            gemm(GemmBackend::bf16, ta, tb, M, N, K, 0.5f, A.data(), lda, B.data(), ldb, beta, first.data(), ldc, *pool);
            const std::size_t packed = cache.packed_bytes();
            CHECK(packed >= std::size_t(K * N * 2));  // every value of op(B) in bf16
            gemm(GemmBackend::bf16, ta, tb, M, N, K, 0.5f, A.data(), lda, B.data(), ldb, beta, second.data(), ldc, *pool);
            CHECK(cache.packed_bytes() == packed);  // reused, not packed again
            CHECK(std::memcmp(first.data(), plain.data(), plain.size() * sizeof(float)) == 0);
            CHECK(std::memcmp(second.data(), plain.data(), plain.size() * sizeof(float)) == 0);
          }
      }
}

TEST_CASE("GemmWeightCache: unfrozen operands, parallel regions and other threads leave it alone, clear() repacks",
          "[gemm]") {
  if constexpr (!have_bf16_gemm) FLEXSPLAT_SKIP("this build has no oneDNN: GemmBackend::bf16 is not available");
  const index_t M = 130, N = 110, K = 96;
  const auto A = random_vector<float>(M * K, 71);
  auto B = random_vector<float>(K * N, 72);
  const auto copy = B;
  GemmWeightCache cache;
  cache.freeze(B.data(), B.size());
  std::vector<float> c(M * N);
  {
    UseGemmWeightCache use(cache);
    gemm(GemmBackend::bf16, Trans::no, Trans::no, M, N, K, 1.0f, A.data(), K, copy.data(), N, 0.0f, c.data(), N);
    CHECK(cache.packed_bytes() == 0);  // B outside the frozen range
    gemm(GemmBackend::onednn, Trans::no, Trans::no, M, N, K, 1.0f, A.data(), K, B.data(), N, 0.0f, c.data(), N);
    CHECK(cache.packed_bytes() == 0);  // fp32 products never use it
    ThreadPool two(2);
    parallel_for(2, [&](index_t, index_t, int) {
      std::vector<float> local(M * N);
      gemm(GemmBackend::bf16, Trans::no, Trans::no, M, N, K, 1.0f, A.data(), K, B.data(), N, 0.0f, local.data(), N);
    }, two);
    CHECK(cache.packed_bytes() == 0);  // inside a parallel region
  }
  std::thread([&] {
    gemm(GemmBackend::bf16, Trans::no, Trans::no, M, N, K, 1.0f, A.data(), K, B.data(), N, 0.0f, c.data(), N);
  }).join();
  CHECK(cache.packed_bytes() == 0);  // no scope on that thread (nor on this one any more)
  UseGemmWeightCache use(cache);
  gemm(GemmBackend::bf16, Trans::no, Trans::no, M, N, K, 1.0f, A.data(), K, B.data(), N, 0.0f, c.data(), N);
  CHECK(cache.packed_bytes() > 0);
  // Changed weights: the stale copy until clear(), then the new values.
  for (float& v : B) v = -v;
  std::vector<float> stale(M * N), fresh(M * N), want(M * N);
  gemm(GemmBackend::bf16, Trans::no, Trans::no, M, N, K, 1.0f, A.data(), K, B.data(), N, 0.0f, stale.data(), N);
  CHECK(std::memcmp(stale.data(), c.data(), c.size() * sizeof(float)) == 0);
  cache.clear();
  CHECK(cache.packed_bytes() == 0);
  gemm(GemmBackend::bf16, Trans::no, Trans::no, M, N, K, 1.0f, A.data(), K, B.data(), N, 0.0f, fresh.data(), N);
  for (std::size_t i = 0; i < c.size(); ++i) want[i] = -c[i];  // bf16 rounding is symmetric
  CHECK(std::memcmp(fresh.data(), want.data(), want.size() * sizeof(float)) == 0);
}

TEST_CASE("bf16 gemm: double products and small float ones keep full precision", "[gemm]") {
  if constexpr (!have_bf16_gemm) FLEXSPLAT_SKIP("this build has no oneDNN: GemmBackend::bf16 is not available");
  const index_t M = 8, N = 8, K = 8;  // far below gemm_bf16_min_madds
  const auto A = random_vector<float>(M * K, 51), B = random_vector<float>(K * N, 52);
  std::vector<float> c(M * N), ref(M * N);
  gemm(GemmBackend::bf16, Trans::no, Trans::no, M, N, K, 1.0f, A.data(), K, B.data(), N, 0.0f, c.data(), N);
  naive_gemm(Trans::no, Trans::no, M, N, K, 1.0f, A.data(), K, B.data(), N, 0.0f, ref.data(), N);
  CHECK(max_abs_diff(c, ref) <= 2.0 * K * std::numeric_limits<float>::epsilon());
  const auto Ad = random_vector<double>(64 * 64, 53), Bd = random_vector<double>(64 * 64, 54);
  std::vector<double> cd(64 * 64), refd(64 * 64);
  gemm(GemmBackend::bf16, Trans::no, Trans::yes, 64, 64, 64, 1.0, Ad.data(), 64, Bd.data(), 64, 0.0, cd.data(), 64);
  naive_gemm(Trans::no, Trans::yes, 64, 64, 64, 1.0, Ad.data(), 64, Bd.data(), 64, 0.0, refd.data(), 64);
  CHECK(max_abs_diff(cd, refd) <= 2.0 * 64 * std::numeric_limits<double>::epsilon());
}

TEST_CASE("onednn gemm is within 2 K eps of the float64 product: every transpose, stride, alpha, beta, 1 and 2 threads",
          "[gemm]") {
  if constexpr (!have_onednn_gemm) FLEXSPLAT_SKIP("this build has no oneDNN: GemmBackend::onednn is not available");
  const double eps = std::numeric_limits<float>::epsilon();
  ThreadPool one(1), two(2);
  // Above gemm_onednn_min_madds, so that oneDNN runs (also for each part of the 2-thread split: rows, then columns
  // of a wide C); the last case is a single row with lda = ldc = 0 (never read for one row).
  const Case cases[] = {{130, 110, 96, 3}, {40, 400, 48, 1}, {1, 1100, 512, 0}};
  for (const auto& cs : cases)
    for (Trans ta : {Trans::no, Trans::yes})
      for (Trans tb : {Trans::no, Trans::yes}) {
        const index_t M = cs.M, N = cs.N, K = cs.K;
        REQUIRE(M * N * K >= gemm_onednn_min_madds);
        const bool row = M == 1;
        const index_t lda = row && ta == Trans::no ? 0 : (ta == Trans::no ? K : M) + cs.pad;
        const index_t ldb = (tb == Trans::no ? N : K) + cs.pad, ldc = row ? 0 : N + cs.pad;
        const auto A = random_vector<float>((ta == Trans::no ? M : K) * std::max(lda, K), 61);
        const auto B = random_vector<float>((tb == Trans::no ? K : N) * ldb, 62);
        const auto C0 = random_vector<float>(M * std::max(ldc, N), 63);
        std::vector<double> exact(M * N, 0.0), abs_sum(M * N, 0.0);  // float64 product and sum_k |a| |b|
        for (index_t i = 0; i < M; ++i)
          for (index_t k = 0; k < K; ++k) {
            const double a = ta == Trans::no ? A[i * lda + k] : A[k * lda + i];
            for (index_t j = 0; j < N; ++j) {
              const double p = a * double(tb == Trans::no ? B[k * ldb + j] : B[j * ldb + k]);
              exact[i * N + j] += p;
              abs_sum[i * N + j] += std::abs(p);
            }
          }
        for (const auto& [alpha, beta] : {std::pair{1.0f, 0.0f}, std::pair{0.5f, 0.75f}, std::pair{-1.25f, 1.0f}}) {
          std::vector<std::vector<float>> results;
          for (ThreadPool* pool : {&one, &one, &two, &two}) {
            INFO("M " << M << " ta " << int(ta) << " tb " << int(tb) << " alpha " << alpha << " beta " << beta
                      << " threads " << pool->size());
            std::vector<float> c = C0;
            gemm(GemmBackend::onednn, ta, tb, M, N, K, alpha, A.data(), lda, B.data(), ldb, beta, c.data(), ldc, *pool);
            for (index_t i = 0; i < M; ++i)
              for (index_t j = 0; j < N; ++j) {
                const std::size_t e = i * ldc + j;
                const double expected = double(alpha) * exact[i * N + j] + double(beta) * C0[e];
                const double bound = 2.0 * double(K) * eps * std::abs(alpha) * abs_sum[i * N + j] +
                                     2.0 * eps * std::abs(double(beta) * C0[e]) + eps * std::abs(expected);
                REQUIRE(std::abs(double(c[e]) - expected) <= bound);
              }
            if (!row)
              for (index_t i = 0; i < M; ++i)
                for (index_t j = N; j < ldc; ++j) REQUIRE(c[i * ldc + j] == C0[i * ldc + j]);  // padding untouched
            results.push_back(std::move(c));
          }
          // Bitwise the same for a given thread count.
          CHECK(std::memcmp(results[0].data(), results[1].data(), results[0].size() * sizeof(float)) == 0);
          CHECK(std::memcmp(results[2].data(), results[3].data(), results[2].size() * sizeof(float)) == 0);
        }
      }
}

TEST_CASE("onednn gemm: calls of one size with other strides, transposes, alpha or beta each get their own product",
          "[gemm]") {
  if constexpr (!have_onednn_gemm) FLEXSPLAT_SKIP("this build has no oneDNN: GemmBackend::onednn is not available");
  ThreadPool one(1);
  const index_t M = 64, N = 96, K = 128;  // above gemm_onednn_min_madds
  REQUIRE(M * N * K >= gemm_onednn_min_madds);
  struct Call {
    Trans ta, tb;
    index_t pad_a, pad_b, pad_c;
    float alpha, beta;
  };
  // Each differs from the one before in one field only, twice over, so that a kernel kept for the wrong call shows.
  const Call calls[] = {{Trans::no, Trans::no, 0, 0, 0, 1.0f, 0.0f},   {Trans::no, Trans::no, 5, 0, 0, 1.0f, 0.0f},
                        {Trans::no, Trans::no, 5, 7, 0, 1.0f, 0.0f},   {Trans::no, Trans::no, 5, 7, 3, 1.0f, 0.0f},
                        {Trans::no, Trans::no, 5, 7, 3, 0.5f, 0.0f},   {Trans::no, Trans::no, 5, 7, 3, 0.5f, 1.0f},
                        {Trans::yes, Trans::no, 5, 7, 3, 0.5f, 1.0f},  {Trans::yes, Trans::yes, 5, 7, 3, 0.5f, 1.0f},
                        {Trans::no, Trans::no, 0, 0, 0, 1.0f, 0.0f},   {Trans::yes, Trans::yes, 5, 7, 3, 0.5f, 1.0f}};
  const double eps = std::numeric_limits<float>::epsilon();
  for (int round = 0; round < 2; ++round)
    for (const Call& cl : calls) {
      const index_t lda = (cl.ta == Trans::no ? K : M) + cl.pad_a, ldb = (cl.tb == Trans::no ? N : K) + cl.pad_b;
      const index_t ldc = N + cl.pad_c;
      const auto A = random_vector<float>((cl.ta == Trans::no ? M : K) * lda, 81);
      const auto B = random_vector<float>((cl.tb == Trans::no ? K : N) * ldb, 82);
      const auto C0 = random_vector<float>(M * ldc, 83);
      std::vector<float> c = C0, expected = C0;
      gemm(GemmBackend::onednn, cl.ta, cl.tb, M, N, K, cl.alpha, A.data(), lda, B.data(), ldb, cl.beta, c.data(), ldc,
           one);
      naive_gemm(cl.ta, cl.tb, M, N, K, cl.alpha, A.data(), lda, B.data(), ldb, cl.beta, expected.data(), ldc);
      INFO("round " << round << " ta " << int(cl.ta) << " tb " << int(cl.tb) << " pads " << cl.pad_a << ' '
                    << cl.pad_b << ' ' << cl.pad_c << " alpha " << cl.alpha << " beta " << cl.beta);
      // |a|, |b| <= 1, so the error is within 2 K eps K; a kernel of another call's shape misses by far more.
      CHECK(max_abs_diff(c, expected) <= 2.0 * double(K) * eps * double(K));
    }
}

TEST_CASE("onednn gemm: double products and small float ones stay on the fp32 fallback", "[gemm]") {
  if constexpr (!have_onednn_gemm) FLEXSPLAT_SKIP("this build has no oneDNN: GemmBackend::onednn is not available");
  const index_t n = 16;  // n^3 far below gemm_onednn_min_madds
  const auto A = random_vector<float>(n * n, 71), B = random_vector<float>(n * n, 72);
  std::vector<float> c(n * n), fallback(n * n);
  const GemmBackend fp32 = have_blas ? GemmBackend::blas : GemmBackend::eigen;
  gemm(GemmBackend::onednn, Trans::no, Trans::yes, n, n, n, 1.0f, A.data(), n, B.data(), n, 0.0f, c.data(), n);
  gemm(fp32, Trans::no, Trans::yes, n, n, n, 1.0f, A.data(), n, B.data(), n, 0.0f, fallback.data(), n);
  CHECK(std::memcmp(c.data(), fallback.data(), c.size() * sizeof(float)) == 0);
  const auto Ad = random_vector<double>(80 * 80, 73), Bd = random_vector<double>(80 * 80, 74);
  std::vector<double> cd(80 * 80), refd(80 * 80);
  gemm(GemmBackend::onednn, Trans::no, Trans::no, 80, 80, 80, 1.0, Ad.data(), 80, Bd.data(), 80, 0.0, cd.data(), 80);
  naive_gemm(Trans::no, Trans::no, 80, 80, 80, 1.0, Ad.data(), 80, Bd.data(), 80, 0.0, refd.data(), 80);
  CHECK(max_abs_diff(cd, refd) <= 2.0 * 80 * std::numeric_limits<double>::epsilon() * 80);
  CHECK(gemm_backend_name(GemmBackend::onednn).find("oneDNN") == 0);
}
