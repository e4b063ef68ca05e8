#include <catch2/catch.hpp>

#include "flexsplat/nn/linear.hpp"
#include "flexsplat/testing/gradcheck.hpp"
#include "nn_test_util.hpp"

using namespace flexsplat;

TEST_CASE("linear forward matches y = x W^T + b and backward passes the float64 gradient check", "[nn][linear]") {
  const index_t rows = 5, in = 7, out = 4;
  auto x = random_vector(rows * in, 1), w = random_vector(out * in, 2), b = random_vector(out, 3);
  std::vector<double> y(rows * out);
  nn::linear_forward(y.data(), x.data(), w.data(), b.data(), rows, in, out);
  for (index_t r = 0; r < rows; ++r)
    for (index_t o = 0; o < out; ++o) {
      double expect = b[o];
      for (index_t i = 0; i < in; ++i) expect += x[r * in + i] * w[o * in + i];
      CHECK(y[r * out + o] == Approx(expect).epsilon(1e-12));
    }
  std::vector<double> dx(x.size()), dw(w.size()), db(b.size());
  auto result = testing::check_gradients(
      {{"x", x, dx}, {"weight", w, dw}, {"bias", b, db}}, y.size(),
      [&](std::span<double> o) { nn::linear_forward(o.data(), x.data(), w.data(), b.data(), rows, in, out); },
      [&](std::span<const double> d) {
        nn::linear_backward(dx.data(), dw.data(), db.data(), d.data(), x.data(), w.data(), rows, in, out);
      });
  INFO(result.summary());
  CHECK(result.ok());
}
