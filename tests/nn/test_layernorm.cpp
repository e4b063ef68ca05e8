#include <catch2/catch.hpp>

#include <cmath>
#include <random>
#include <vector>

#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/simd_dispatch.hpp"
#include "flexsplat/nn/layernorm.hpp"
#include "flexsplat/testing/gradcheck.hpp"
#include "nn_test_util.hpp"
#include "simd_lanes.hpp"

using namespace flexsplat;

TEST_CASE("layernorm normalises rows and passes the float64 gradient check", "[nn][layernorm]") {
  const index_t rows = 6, dim = 9;
  auto x = random_vector(rows * dim, 4, 3.0), g = random_vector(dim, 5), b = random_vector(dim, 6);
  std::vector<double> y(x.size()), mean(rows), rstd(rows);
  nn::layernorm_forward(y.data(), x.data(), (const double*)nullptr, (const double*)nullptr, rows, dim, 1e-6);
  for (index_t r = 0; r < rows; ++r) {
    double s = 0, sq = 0;
    for (index_t i = 0; i < dim; ++i) s += y[r * dim + i], sq += y[r * dim + i] * y[r * dim + i];
    CHECK(s == Approx(0.0).margin(1e-12));
    CHECK(sq / dim == Approx(1.0).epsilon(1e-5));
  }
  std::vector<double> dx(x.size()), dg(dim), db(dim);
  nn::LayerNormCache<double> cache{mean.data(), rstd.data()};
  auto result = testing::check_gradients(
      {{"x", x, dx}, {"gamma", g, dg}, {"beta", b, db}}, y.size(),
      [&](std::span<double> o) { nn::layernorm_forward(o.data(), x.data(), g.data(), b.data(), rows, dim, 1e-5, cache); },
      [&](std::span<const double> d) {
        nn::layernorm_forward(y.data(), x.data(), g.data(), b.data(), rows, dim, 1e-5, cache);
        nn::layernorm_backward(dx.data(), dg.data(), db.data(), d.data(), x.data(), g.data(), rows, dim, cache);
      });
  INFO(result.summary());
  CHECK(result.ok());
}

namespace {
// The float path `lanes` against the scalar one, forward and backward.
void check_layernorm_lanes(simd::Lanes lanes) {
  // Rows with an offset and a few channels 50 times larger (as transformer residual streams have); widths with and
  // without a tail after the lanes. Bounds in float eps times (1 + |scalar|); measured on 1316 x 1024 rows: y 4.3,
  // mean 1.8, rstd 0.4, d_in 4.6 eps; d_gamma within 4 eps of the sum of its terms' magnitudes.
  constexpr double eps = 0x1p-23;
  const index_t rows = 37;
  for (index_t dim : {index_t(1024), index_t(77), index_t(9)}) {
    for (bool affine : {true, false}) {
      INFO("dim " << dim << (affine ? " affine" : " no affine"));
      std::mt19937 rng(static_cast<unsigned>(dim));
      std::normal_distribution<float> normal(0.0f, 1.0f);
      std::vector<float> x(rows * dim), dy(rows * dim), g(dim), b(dim);
      for (index_t r = 0; r < rows; ++r) {
        const float offset = 3 * normal(rng);
        for (index_t i = 0; i < dim; ++i) x[r * dim + i] = offset + normal(rng) * (i % 13 == 5 ? 50.0f : 1.0f);
      }
      for (auto& v : dy) v = normal(rng);
      for (index_t i = 0; i < dim; ++i) g[i] = 1 + 0.1f * normal(rng), b[i] = 0.1f * normal(rng);
      const float* gamma = affine ? g.data() : nullptr;
      const float* beta = affine ? b.data() : nullptr;
      std::vector<float> ys(x.size()), ms(rows), ss(rows), dxs(x.size()), dgs(dim), dbs(dim);
      nn::layernorm_forward_impl<float>(ys.data(), x.data(), gamma, beta, rows, dim, 1e-6f, {ms.data(), ss.data()},
                                        simd::Lanes::scalar);
      nn::layernorm_backward_impl<float>(dxs.data(), affine ? dgs.data() : nullptr, affine ? dbs.data() : nullptr,
                                         dy.data(), x.data(), gamma, rows, dim, {ms.data(), ss.data()}, simd::Lanes::scalar);
      std::vector<double> dg_scale(dim, 1.0);  // 1 + sum_r |dy n|
      for (index_t r = 0; r < rows; ++r)
        for (index_t i = 0; i < dim; ++i) dg_scale[i] += std::abs(double(dy[r * dim + i]) * (x[r * dim + i] - ms[r]) * ss[r]);
      {
        INFO(simd::lanes_name(lanes));
        std::vector<float> y(x.size()), m(rows), s(rows), dx(x.size()), dg(dim), db(dim);
        nn::layernorm_forward_impl<float>(y.data(), x.data(), gamma, beta, rows, dim, 1e-6f, {m.data(), s.data()}, lanes);
        // Backward with the scalar path's statistics, so it is compared on its own.
        nn::layernorm_backward_impl<float>(dx.data(), affine ? dg.data() : nullptr, affine ? db.data() : nullptr, dy.data(),
                                           x.data(), gamma, rows, dim, {ms.data(), ss.data()}, lanes);
        auto close = [](double a, double ref, double tol) { return std::abs(a - ref) <= tol * (1 + std::abs(ref)); };
        for (index_t r = 0; r < rows; ++r) {
          REQUIRE(close(m[r], ms[r], 8 * eps));
          REQUIRE(close(s[r], ss[r], 4 * eps));
        }
        for (std::size_t i = 0; i < x.size(); ++i) {
          REQUIRE(close(y[i], ys[i], 16 * eps));
          REQUIRE(close(dx[i], dxs[i], 16 * eps));
        }
        for (index_t i = 0; affine && i < dim; ++i) {
          REQUIRE(std::abs(double(dg[i]) - dgs[i]) <= 4 * eps * dg_scale[i]);
          REQUIRE(db[i] == dbs[i]);
        }
      }
    }
  }
}

}  // namespace

TEST_CASE("layernorm: every SIMD path agrees with the scalar path (float)", "[nn][layernorm][simd]") {
  // The build's compiled lanes; the run-time dispatched ones are the cases below, one per level.
  check_layernorm_lanes(simd::Lanes::compiled);
}

FLEXSPLAT_DISPATCH_TEST_CASES("layernorm: the dispatched float lanes agree with the scalar path", "[nn][layernorm][simd]",
                              check_layernorm_lanes)

TEST_CASE("layernorm backward: parameter gradients do not depend on the thread count", "[nn][layernorm]") {
  const index_t rows = 50, dim = 200;
  std::mt19937 rng(3);
  std::normal_distribution<float> normal(0.0f, 1.0f);
  std::vector<float> x(rows * dim), dy(rows * dim), g(dim), b(dim), y(rows * dim), m(rows), s(rows);
  for (auto& v : x) v = normal(rng);
  for (auto& v : dy) v = normal(rng);
  for (index_t i = 0; i < dim; ++i) g[i] = 1 + 0.1f * normal(rng), b[i] = 0.1f * normal(rng);
  ThreadPool one(1), two(2);
  std::vector<float> dx1(x.size()), dg1(dim), db1(dim), dx2(x.size()), dg2(dim), db2(dim);
  const simd::Lanes lanes = simd::best_lanes<float>();
  nn::layernorm_forward_impl<float>(y.data(), x.data(), g.data(), b.data(), rows, dim, 1e-6f, {m.data(), s.data()}, lanes, one);
  nn::layernorm_backward_impl<float>(dx1.data(), dg1.data(), db1.data(), dy.data(), x.data(), g.data(), rows, dim,
                                     {m.data(), s.data()}, lanes, one);
  nn::layernorm_backward_impl<float>(dx2.data(), dg2.data(), db2.data(), dy.data(), x.data(), g.data(), rows, dim,
                                     {m.data(), s.data()}, lanes, two);
  CHECK(dx1 == dx2);
  CHECK(dg1 == dg2);
  CHECK(db1 == db2);
}
