#include <catch2/catch.hpp>

#include <cmath>
#include <random>
#include <vector>

#include "flexsplat/loss/ssim.hpp"
#include "flexsplat/testing/gradcheck.hpp"
#include "loss_test_util.hpp"

using namespace flexsplat;
using loss_test::uniform;

namespace {

// Direct evaluation: for every pixel, the 11x11 Gaussian-weighted sums over the window with zeros outside the image.
double naive_ssim(const std::vector<double>& a, const std::vector<double>& b, const loss::ImageShape& s) {
  const int r = 5;
  double g[11], gs = 0;
  for (int i = 0; i < 11; ++i) gs += g[i] = std::exp(-double((i - r) * (i - r)) / (2 * 1.5 * 1.5));
  const double C1 = 0.01 * 0.01, C2 = 0.03 * 0.03;
  double total = 0;
  for (index_t n = 0; n < s.batch; ++n)
    for (index_t c = 0; c < s.channels; ++c)
      for (index_t y = 0; y < s.height; ++y)
        for (index_t x = 0; x < s.width; ++x) {
          double mx = 0, my = 0, xx = 0, yy = 0, xy = 0;
          for (int i = 0; i < 11; ++i)
            for (int j = 0; j < 11; ++j) {
              const index_t py = y + i - r, px = x + j - r;
              if (py < 0 || py >= s.height || px < 0 || px >= s.width) continue;
              const double w = g[i] * g[j] / (gs * gs), va = a[s.index(n, c, py, px)], vb = b[s.index(n, c, py, px)];
              mx += w * va, my += w * vb, xx += w * va * va, yy += w * vb * vb, xy += w * va * vb;
            }
          const double sx = xx - mx * mx, sy = yy - my * my, sxy = xy - mx * my;
          total += ((2 * mx * my + C1) * (2 * sxy + C2)) / ((mx * mx + my * my + C1) * (sx + sy + C2));
        }
  return total / double(s.numel());
}
}  // namespace

TEST_CASE("ssim equals a direct windowed evaluation with zero padding (3DGS convention)", "[loss][ssim]") {
  loss::SsimWorkspace ws;
  for (auto layout : {loss::Layout::nchw, loss::Layout::nhwc}) {
    const loss::ImageShape s{2, 3, 13, 17, layout};
    const auto a = uniform(s.numel(), 1);
    auto b = a;
    for (auto& v : b) v = 0.7 * v + 0.3 * std::sin(7 * v);
    const double fast = loss::ssim_forward(a.data(), b.data(), s, {}, ws);
    CHECK(fast == Approx(naive_ssim(a, b, s)).epsilon(1e-13));
    CHECK(fast < 1.0);
    CHECK(loss::ssim_forward(a.data(), a.data(), s, {}, ws) == Approx(1.0).epsilon(1e-15));
  }
  // Images smaller than the window.
  const loss::ImageShape tiny{1, 1, 3, 4, loss::Layout::nchw};
  const auto a = uniform(12, 2), b = uniform(12, 3);
  CHECK(loss::ssim_forward(a.data(), b.data(), tiny, {}, ws) == Approx(naive_ssim(a, b, tiny)).epsilon(1e-13));
}

TEST_CASE("ssim: gradient check for both images", "[loss][ssim][gradcheck]") {
  loss::SsimWorkspace ws;
  const loss::ImageShape s{1, 2, 9, 14, loss::Layout::nhwc};
  auto a = uniform(s.numel(), 4), b = uniform(s.numel(), 5);
  std::vector<double> da(a.size()), db(b.size());
  testing::GradCheckOptions o;
  o.max_checks_per_param = 64;
  const auto r = testing::check_gradients(
      {{"a", a, da}, {"b", b, db}}, 1,
      [&](std::span<double> out) { out[0] = loss::ssim_forward(a.data(), b.data(), s, {}, ws); },
      [&](std::span<const double> d) { loss::ssim_backward(da.data(), db.data(), d[0], a.data(), b.data(), s, {}, ws); }, o);
  INFO(r.summary());
  CHECK(r.ok());
}

TEST_CASE("ssim: float images, results for 1 and 2 threads are identical", "[loss][ssim]") {
  const loss::ImageShape s{1, 3, 20, 24, loss::Layout::nchw};
  const auto ad = uniform(s.numel(), 6), bd = uniform(s.numel(), 7);
  const std::vector<float> a(ad.begin(), ad.end()), b(bd.begin(), bd.end());
  ThreadPool one(1), two(2);
  loss::SsimWorkspace ws;
  std::vector<float> g1(a.size()), g2(a.size());
  const double v1 = loss::ssim_forward(a.data(), b.data(), s, {}, ws, one);
  const double v2 = loss::ssim_forward(a.data(), b.data(), s, {}, ws, two);
  loss::ssim_backward(g1.data(), static_cast<float*>(nullptr), 1.0, a.data(), b.data(), s, {}, ws, one);
  loss::ssim_backward(g2.data(), static_cast<float*>(nullptr), 1.0, a.data(), b.data(), s, {}, ws, two);
  CHECK(v1 == v2);
  CHECK(g1 == g2);
  CHECK_THROWS_WITH(loss::ssim_forward(a.data(), b.data(), s, {10, 1.5}, ws), Catch::Contains("window 10 must be odd"));
}
