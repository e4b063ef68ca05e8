#include <catch2/catch.hpp>

#include "flexsplat/nn/interpolate.hpp"
#include "flexsplat/testing/gradcheck.hpp"
#include "nn_test_util.hpp"

using namespace flexsplat;

TEST_CASE("bilinear resize: known values for both corner conventions", "[nn][interpolate]") {
  const double in[4] = {0.0, 1.0, 2.0, 3.0};  // 2x2
  double out[16];
  nn::bilinear_resize_forward(out, in, 1, 2, 2, 4, 4, true);
  CHECK(out[0] == 0.0);
  CHECK(out[3] == 1.0);
  CHECK(out[15] == 3.0);
  CHECK(out[1] == Approx(1.0 / 3.0));
  nn::bilinear_resize_forward(out, in, 1, 2, 2, 4, 4, false);
  CHECK(out[0] == 0.0);           // source -0.25 clamps to 0
  CHECK(out[1] == Approx(0.25));  // source 0.25
  CHECK(out[15] == 3.0);
}

TEST_CASE("bilinear resize backward passes the float64 gradient check", "[nn][interpolate]") {
  for (bool align : {true, false}) {
    auto x = random_vector(2 * 5 * 6, 51);
    std::vector<double> y(2 * 9 * 4), dx(x.size());
    auto result = testing::check_gradients(
        {{"x", x, dx}}, y.size(), [&](std::span<double> o) { nn::bilinear_resize_forward(o.data(), x.data(), 2, 5, 6, 9, 4, align); },
        [&](std::span<const double> d) { nn::bilinear_resize_backward(dx.data(), d.data(), 2, 5, 6, 9, 4, align); });
    INFO(result.summary());
    CHECK(result.ok());
  }
}
