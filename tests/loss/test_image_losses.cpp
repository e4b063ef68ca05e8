#include <catch2/catch.hpp>

#include <cmath>
#include <random>
#include <vector>

#include "flexsplat/loss/image.hpp"
#include "flexsplat/testing/gradcheck.hpp"
#include "loss_test_util.hpp"

using namespace flexsplat;
using loss_test::uniform;


TEST_CASE("mse: masked mean over pixels and channels, both layouts", "[loss][mse]") {
  const loss::ImageShape s{2, 3, 4, 5, loss::Layout::nchw};
  const auto a = uniform(s.numel(), 1), b = uniform(s.numel(), 2);
  double direct = 0;
  for (index_t i = 0; i < s.numel(); ++i) direct += (a[i] - b[i]) * (a[i] - b[i]);
  CHECK(loss::mse_forward(a.data(), b.data(), static_cast<const double*>(nullptr), s) ==
        Approx(direct / double(s.numel())).epsilon(1e-14));
  // A 0/1 mask: the mean over the selected pixels only; the same images in nhwc give the same value.
  std::vector<double> mask(s.pixels(), 0.0);
  double selected = 0;
  for (index_t p = 0; p < s.pixels(); p += 3) {
    mask[p] = 1;
    const index_t n = p / (4 * 5), y = p / 5 % 4, x = p % 5;
    for (index_t c = 0; c < 3; ++c) {
      const index_t i = s.index(n, c, y, x);
      selected += (a[i] - b[i]) * (a[i] - b[i]);
    }
  }
  const index_t count = (s.pixels() + 2) / 3;
  const double masked = loss::mse_forward(a.data(), b.data(), mask.data(), s);
  CHECK(masked == Approx(selected / double(3 * count)).epsilon(1e-14));
  loss::ImageShape t = s;
  t.layout = loss::Layout::nhwc;
  std::vector<double> at(a.size()), bt(b.size());
  for (index_t n = 0; n < 2; ++n)
    for (index_t c = 0; c < 3; ++c)
      for (index_t y = 0; y < 4; ++y)
        for (index_t x = 0; x < 5; ++x) at[t.index(n, c, y, x)] = a[s.index(n, c, y, x)], bt[t.index(n, c, y, x)] = b[s.index(n, c, y, x)];
  CHECK(loss::mse_forward(at.data(), bt.data(), mask.data(), t) == Approx(masked).epsilon(1e-14));
  std::vector<double> zero(s.pixels(), 0.0);
  CHECK(loss::mse_forward(a.data(), b.data(), zero.data(), s) == 0.0);
  mask[1] = -1;
  CHECK_THROWS_WITH(loss::mse_forward(a.data(), b.data(), mask.data(), s), Catch::Contains("mask value -1 at pixel 1"));
}

TEST_CASE("mse: gradient check with a weighted mask (both inputs)", "[loss][mse][gradcheck]") {
  for (auto layout : {loss::Layout::nchw, loss::Layout::nhwc}) {
    const loss::ImageShape s{2, 3, 3, 4, layout};
    auto a = uniform(s.numel(), 3), b = uniform(s.numel(), 4), mask = uniform(s.pixels(), 5);
    std::vector<double> da(a.size()), db(b.size());
    const auto r = testing::check_gradients(
        {{"pred", a, da}, {"target", b, db}}, 1,
        [&](std::span<double> out) { out[0] = loss::mse_forward(a.data(), b.data(), mask.data(), s); },
        [&](std::span<const double> d) { loss::mse_backward(da.data(), db.data(), d[0], a.data(), b.data(), mask.data(), s); });
    INFO(r.summary());
    CHECK(r.ok());
  }
}

TEST_CASE("l1: masked mean of absolute differences, gradient check", "[loss][l1][gradcheck]") {
  const loss::ImageShape s{2, 3, 3, 4, loss::Layout::nhwc};
  auto a = uniform(s.numel(), 10), b = uniform(s.numel(), 11), mask = uniform(s.pixels(), 12);
  double direct = 0, msum = 0;
  for (index_t n = 0; n < 2; ++n)
    for (index_t y = 0; y < 3; ++y)
      for (index_t x = 0; x < 4; ++x) {
        const double m = mask[(n * 3 + y) * 4 + x];
        msum += m;
        for (index_t c = 0; c < 3; ++c) direct += m * std::abs(a[s.index(n, c, y, x)] - b[s.index(n, c, y, x)]);
      }
  CHECK(loss::l1_forward(a.data(), b.data(), mask.data(), s) == Approx(direct / (3 * msum)).epsilon(1e-14));
  std::vector<double> da(a.size()), db(b.size());
  const auto r = testing::check_gradients(
      {{"pred", a, da}, {"target", b, db}}, 1,
      [&](std::span<double> out) { out[0] = loss::l1_forward(a.data(), b.data(), mask.data(), s); },
      [&](std::span<const double> d) { loss::l1_backward(da.data(), db.data(), d[0], a.data(), b.data(), mask.data(), s); });
  INFO(r.summary());
  CHECK(r.ok());
}

TEST_CASE("depth L1: confidence-weighted, confidence held constant, both depths differentiated", "[loss][depth][gradcheck]") {
  const index_t n = 40;
  auto r = uniform(n, 6, 1, 3), v = uniform(n, 7, 1, 3), u = uniform(n, 8, 1, 4), m = uniform(n, 9);
  double direct = 0, msum = 0;
  for (index_t i = 0; i < n; ++i) direct += m[i] * std::abs((r[i] - v[i]) * u[i]), msum += m[i];
  CHECK(loss::depth_l1_forward(r.data(), v.data(), u.data(), m.data(), n) == Approx(direct / msum).epsilon(1e-14));
  std::vector<double> dr(n), dv(n);
  const auto res = testing::check_gradients(
      {{"rendered", r, dr}, {"vggt_depth", v, dv}}, 1,
      [&](std::span<double> out) { out[0] = loss::depth_l1_forward(r.data(), v.data(), u.data(), m.data(), n); },
      [&](std::span<const double> d) {
        loss::depth_l1_backward(dr.data(), dv.data(), d[0], r.data(), v.data(), u.data(), m.data(), n);
      });
  INFO(res.summary());
  CHECK(res.ok());
  u[3] = -1;
  CHECK_THROWS_WITH(loss::depth_l1_forward(r.data(), v.data(), u.data(), m.data(), n), Catch::Contains("confidence -1 at pixel 3"));
}

TEST_CASE("psnr: known values", "[loss][psnr]") {
  const std::vector<float> a{0.f, 0.5f, 1.f, 0.25f}, b{0.1f, 0.4f, 0.9f, 0.35f};
  CHECK(loss::psnr(a.data(), b.data(), 4) == Approx(20.0).epsilon(1e-6));  // MSE 0.01
  CHECK(loss::psnr(a.data(), b.data(), 4, 255.0) == Approx(10 * std::log10(255.0 * 255.0 / 0.01)).epsilon(1e-6));
  CHECK(std::isinf(loss::psnr(a.data(), a.data(), 4)));
}
