#include <catch2/catch.hpp>

#include <cmath>

#include "flexsplat/geometry/rope.hpp"
#include "flexsplat/testing/gradcheck.hpp"
#include "geometry_test_util.hpp"

using namespace flexsplat;
using namespace flexsplat::geometry;

// Written from the definition: out = t*cos + rotate_half(t)*sin per axis half, angles p / freq^(2j/half).
static double naive_rope(const std::vector<double>& x, index_t head_dim, int y, int xp, index_t d) {
  const index_t half = head_dim / 2, q = half / 2;
  const index_t axis = d / half, local = d % half;
  const int pos = axis == 0 ? y : xp;
  const index_t j = local % q;
  const double angle = pos / std::pow(100.0, 2.0 * j / half);
  const double self = x[d];
  const double partner = local < q ? -x[axis * half + local + q] : x[axis * half + local - q];
  return self * std::cos(angle) + partner * std::sin(angle);
}

TEST_CASE("2-D RoPE matches the rotate-half definition, leaves position 0 alone and keeps norms", "[geometry][rope]") {
  const index_t heads = 3, hd = 8, rows = 4;
  const auto table = rope2d_table<double>(hd, 9, 100.0);
  auto x = random_doubles(rows * heads * hd, 11);
  std::vector<std::int32_t> pos = {0, 0, 3, 5, 8, 1, 2, 7};
  auto out = x;
  rope2d_forward(out.data(), rows, heads * hd, heads, hd, pos.data(), table);
  for (index_t r = 0; r < rows; ++r)
    for (index_t h = 0; h < heads; ++h) {
      std::vector<double> head(x.begin() + r * heads * hd + h * hd, x.begin() + r * heads * hd + (h + 1) * hd);
      double n0 = 0, n1 = 0;
      for (index_t d = 0; d < hd; ++d) {
        const double got = out[r * heads * hd + h * hd + d];
        CHECK(got == Approx(naive_rope(head, hd, pos[2 * r], pos[2 * r + 1], d)).margin(1e-12));
        n0 += head[d] * head[d];
        n1 += got * got;
        if (r == 0) CHECK(got == head[d]);
      }
      CHECK(n1 == Approx(n0).epsilon(1e-12));
    }
}

TEST_CASE("2-D RoPE backward passes the float64 gradient check", "[geometry][rope]") {
  const index_t heads = 2, hd = 4, rows = 3;
  const auto table = rope2d_table<double>(hd, 6, 100.0);
  auto x = random_doubles(rows * heads * hd, 12);
  std::vector<double> dx(x.size());
  std::vector<std::int32_t> pos = {1, 2, 5, 0, 3, 4};
  auto result = testing::check_gradients(
      {{"x", x, dx}}, x.size(),
      [&](std::span<double> o) {
        std::copy(x.begin(), x.end(), o.begin());
        rope2d_forward(o.data(), rows, heads * hd, heads, hd, pos.data(), table);
      },
      [&](std::span<const double> d) {
        rope2d_backward(dx.data(), d.data(), rows, heads * hd, heads, hd, pos.data(), table);
      });
  INFO(result.summary());
  CHECK(result.ok());
}

TEST_CASE("2-D RoPE rejects bad head sizes and positions outside the table", "[geometry][rope]") {
  CHECK_THROWS_WITH(rope2d_table<float>(6, 4, 100.0), Catch::Contains("divisible by 4"));
  const auto table = rope2d_table<float>(4, 3, 100.0);
  std::vector<float> x(4);
  std::vector<std::int32_t> pos = {0, 3};
  CHECK_THROWS_WITH(rope2d_forward(x.data(), 1, 4, 1, 4, pos.data(), table), Catch::Contains("position 3"));
}
