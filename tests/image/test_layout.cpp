#include <catch2/catch.hpp>

#include <vector>

#include "flexsplat/image/layout.hpp"

using namespace flexsplat;

TEST_CASE("planar and interleaved RGB: round trip, pixel placement, and the adjoint adds", "[image]") {
  const index_t h = 3, w = 5, n = 3 * h * w;
  std::vector<double> hwc(n), chw(n), back(n);
  for (index_t i = 0; i < n; ++i) hwc[i] = double(i);
  image::hwc_to_chw(chw.data(), hwc.data(), h, w);
  CHECK(chw[2 * h * w + 1 * w + 1] == hwc[3 * (1 * w + 1) + 2]);  // channel 2 of pixel (row 1, column 1)
  image::chw_to_hwc(back.data(), chw.data(), h, w);
  CHECK(back == hwc);
  // <hwc_to_chw(x), y> = <x, add_chw_to_hwc(0, y)>, and add_chw_to_hwc adds to what is there.
  std::vector<double> y(n), grad(n, 1.0);
  for (index_t i = 0; i < n; ++i) y[i] = double((i * 7) % 11) - 5.0;
  image::add_chw_to_hwc(grad.data(), y.data(), h, w);
  double lhs = 0, rhs = 0;
  for (index_t i = 0; i < n; ++i) lhs += chw[i] * y[i], rhs += hwc[i] * (grad[i] - 1.0);
  CHECK(lhs == rhs);
}
