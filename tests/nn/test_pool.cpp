#include <catch2/catch.hpp>

#include <cmath>
#include <limits>

#include "flexsplat/nn/pool.hpp"
#include "flexsplat/testing/gradcheck.hpp"
#include "nn_test_util.hpp"

using namespace flexsplat;

TEST_CASE("max_pool2d matches the direct definition with floor sizes and passes the float64 gradient check", "[nn][pool]") {
  // 7x5 planes: the last row and column are dropped (floor), as PyTorch's MaxPool2d(2) does.
  const nn::Pool2dShape s{6, 7, 5, 2, 2};
  REQUIRE(s.out_h() == 3);
  REQUIRE(s.out_w() == 2);
  auto x = random_vector(static_cast<std::size_t>(s.planes * s.in_h * s.in_w), 51);
  std::vector<double> y(static_cast<std::size_t>(s.planes * s.out_h() * s.out_w()));
  nn::max_pool2d_forward(y.data(), x.data(), s);
  for (index_t p = 0; p < s.planes; ++p)
    for (index_t oy = 0; oy < s.out_h(); ++oy)
      for (index_t ox = 0; ox < s.out_w(); ++ox) {
        double m = -std::numeric_limits<double>::infinity();
        for (index_t i = 0; i < 2; ++i)
          for (index_t j = 0; j < 2; ++j) m = std::max(m, x[static_cast<std::size_t>((p * s.in_h + 2 * oy + i) * s.in_w + 2 * ox + j)]);
        REQUIRE(y[static_cast<std::size_t>((p * s.out_h() + oy) * s.out_w() + ox)] == m);
      }
  std::vector<double> dx(x.size());
  auto result = testing::check_gradients(
      {{"x", x, dx}}, y.size(), [&](std::span<double> o) { nn::max_pool2d_forward(o.data(), x.data(), s); },
      [&](std::span<const double> d) { nn::max_pool2d_backward(dx.data(), d.data(), x.data(), s); });
  INFO(result.summary());
  CHECK(result.ok());
}

TEST_CASE("max_pool2d routes a tie to the first element in window order, as PyTorch", "[nn][pool]") {
  const nn::Pool2dShape s{1, 2, 2, 2, 2};
  const double x[4] = {1.0, 3.0, 3.0, 2.0};
  double y = 0, dx[4] = {0.5, 0.5, 0.5, 0.5};
  nn::max_pool2d_forward(&y, x, s);
  CHECK(y == 3.0);
  const double g = 2.0;
  nn::max_pool2d_backward(dx, &g, x, s);
  CHECK(dx[0] == 0.5);
  CHECK(dx[1] == 2.5);
  CHECK(dx[2] == 0.5);
  CHECK(dx[3] == 0.5);
}

TEST_CASE("max_pool2d rejects a window larger than the input", "[nn][pool]") {
  const nn::Pool2dShape s{1, 1, 4, 2, 2};
  std::vector<double> buf(8);
  CHECK_THROWS_WITH(nn::max_pool2d_forward(buf.data(), buf.data(), s), Catch::Contains("1x4 is smaller than the 2x2 window"));
}
