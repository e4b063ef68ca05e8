#include <catch2/catch.hpp>

#include <cmath>
#include <cstring>
#include <limits>
#include <random>
#include <vector>

#include "flexsplat/core/simd.hpp"

using namespace flexsplat;

TEMPLATE_TEST_CASE("simd lane_mul_add rounds the same on the batch and scalar paths", "[simd]", float, double) {
  using V = simd::batch<TestType>;
  constexpr int L = int(V::size);
  std::mt19937 rng(17);
  std::uniform_real_distribution<double> uni(-1, 1);
  long fused_differs = 0;
  for (int trial = 0; trial < 2000; ++trial) {
    alignas(64) TestType a[L], b[L], c[L], r[L];
    for (int l = 0; l < L; ++l) {
      // a b close to -c: the product's low bits decide the sum, so fused and unfused results differ often
      a[l] = TestType(1 + uni(rng)), b[l] = TestType(1 + uni(rng) * 1e-3);
      c[l] = TestType(-double(a[l]) * double(b[l]) * (1 + 1e-6 * uni(rng)));
    }
    simd::lane_store(r, simd::lane_mul_add(simd::lane_load<V>(a), simd::lane_load<V>(b), simd::lane_load<V>(c)));
    for (int l = 0; l < L; ++l) {
      const TestType s = simd::lane_mul_add(a[l], b[l], c[l]);
      CHECK(std::memcmp(&s, &r[l], sizeof s) == 0);
      volatile TestType product = a[l] * b[l];  // rounded on its own: the compiler cannot contract through it
      fused_differs += s != product + c[l];
    }
  }
#if defined(__FMA__)
  CHECK(fused_differs > 0);  // the inputs do tell a fused from an unfused multiply-add
#endif
}

TEMPLATE_TEST_CASE("simd load_columns transposes a block of rows", "[simd]", float, double) {
  using V = simd::batch<TestType>;
  constexpr int L = int(V::size);
  for (int count : {1, 3, 12, 16, 17, 27, 48}) {
    const int stride = count + 5;
    std::vector<TestType> data(std::size_t(L * stride));
    for (std::size_t i = 0; i < data.size(); ++i) data[i] = TestType(i) + TestType(0.25);
    const TestType* rows[L];
    for (int l = 0; l < L; ++l) rows[l] = data.data() + std::min(l, L - 2) * stride;  // the last row repeats one
    V out[48];
    simd::load_columns<V, TestType>(rows, count, out);
    alignas(64) TestType lanes[L];
    for (int j = 0; j < count; ++j) {
      simd::lane_store(lanes, out[j]);
      for (int l = 0; l < L; ++l) CHECK(lanes[l] == rows[l][j]);
    }
  }
}

// Values compare equal (the sign of a zero result may differ: xsimd's own SSE2 floor does not keep it either).
TEMPLATE_TEST_CASE("simd lane_floor and lane_ceil match std::floor and std::ceil", "[simd]", float, double) {
  using V = simd::batch<TestType>;
  constexpr int L = int(V::size);
  const TestType big = TestType(1) / std::numeric_limits<TestType>::epsilon();  // 2^52 (double), 2^23 (float)
  std::vector<TestType> values = {TestType(0), -TestType(0), TestType(0.5), TestType(-0.5), TestType(1), TestType(-1),
                                  TestType(2.5), TestType(-2.5), TestType(1e-30), TestType(-1e-30),
                                  big, -big, big / 2 + TestType(0.5), -big / 2 - TestType(0.5), big * 3, -big * 3,
                                  std::numeric_limits<TestType>::infinity(), -std::numeric_limits<TestType>::infinity(),
                                  std::numeric_limits<TestType>::max(), std::numeric_limits<TestType>::denorm_min()};
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> uni(-1, 1);
  for (int i = 0; i < 400; ++i) values.push_back(TestType(uni(rng) * std::pow(10.0, 8 * uni(rng))));
  while (values.size() % L) values.push_back(TestType(0.75));
  for (std::size_t i = 0; i < values.size(); i += L) {
    alignas(64) TestType f[L], c[L];
    simd::lane_store(f, simd::lane_floor(simd::lane_load<V>(&values[i])));
    simd::lane_store(c, simd::lane_ceil(simd::lane_load<V>(&values[i])));
    for (int l = 0; l < L; ++l) {
      const TestType x = values[i + l], ef = std::floor(x), ec = std::ceil(x);
      INFO(x);
      CHECK(f[l] == ef);
      CHECK(c[l] == ec);
    }
  }
}

TEMPLATE_TEST_CASE("simd lane_exp on batches keeps exp's values at infinities, NaN and past the exponent range",
                   "[simd]", float, double) {
  using V = simd::batch<TestType>;
  constexpr int L = int(V::size);
  constexpr TestType inf = std::numeric_limits<TestType>::infinity(), nan = std::numeric_limits<TestType>::quiet_NaN();
  // -inf is what an online softmax's first rescale exp(-inf - max) feeds it.
  const std::vector<TestType> in{-inf, inf, nan, TestType(-1e30), TestType(1e30), TestType(-1000.5), TestType(0),
                                 TestType(1), TestType(-20)};
  for (std::size_t at = 0; at < in.size(); ++at) {
    alignas(64) TestType x[L], r[L];
    for (int l = 0; l < L; ++l) x[l] = in[(at + std::size_t(l)) % in.size()];
    simd::lane_store(r, simd::lane_exp(simd::lane_load<V>(x)));
    for (int l = 0; l < L; ++l) {
      const TestType want = std::exp(x[l]);
      INFO("exp(" << x[l] << ")");
      if (std::isnan(want)) CHECK(std::isnan(r[l]));
      else if (want == TestType(0) || std::isinf(want)) CHECK(r[l] == want);
      else CHECK(std::abs(r[l] - want) <= TestType(4) * std::numeric_limits<TestType>::epsilon() * want);
    }
  }
}
