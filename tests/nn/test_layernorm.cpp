#include <catch2/catch.hpp>

#include "flexsplat/nn/layernorm.hpp"
#include "flexsplat/testing/gradcheck.hpp"
#include "nn_test_util.hpp"

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
