#include <catch2/catch.hpp>

#include <array>

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

TEST_CASE("bilinear resize equals the per-pixel taps, upsampling and downsampling", "[nn][interpolate]") {
  for (bool align : {true, false})
    for (auto [h, w, oh, ow] : {std::array<index_t, 4>{5, 7, 11, 3}, std::array<index_t, 4>{9, 4, 2, 13}}) {
      const index_t planes = 3;
      const auto in = random_vector(static_cast<std::size_t>(planes * h * w), 52);
      std::vector<double> out(static_cast<std::size_t>(planes * oh * ow));
      nn::bilinear_resize_forward(out.data(), in.data(), planes, h, w, oh, ow, align);
      for (index_t p = 0; p < planes; ++p)
        for (index_t y = 0; y < oh; ++y)
          for (index_t x = 0; x < ow; ++x) {
            const auto ty = nn::bilinear_tap(y, h, oh, align), tx = nn::bilinear_tap(x, w, ow, align);
            const double* s = in.data() + p * h * w;
            const double top = (1 - tx.w1) * s[ty.i0 * w + tx.i0] + tx.w1 * s[ty.i0 * w + tx.i1];
            const double bottom = (1 - tx.w1) * s[ty.i1 * w + tx.i0] + tx.w1 * s[ty.i1 * w + tx.i1];
            INFO("plane " << p << " row " << y << " column " << x << " align " << align);
            // Approx: a -march=native build may contract either side into FMAs differently.
            const double want = (1 - ty.w1) * top + ty.w1 * bottom;
            REQUIRE(out[static_cast<std::size_t>((p * oh + y) * ow + x)] == Approx(want).epsilon(1e-14));
          }
    }
}
