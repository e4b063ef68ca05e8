#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <vector>

#include "flexsplat/loss/match.hpp"
#include "flexsplat/testing/gradcheck.hpp"
#include "loss_test_util.hpp"

using namespace flexsplat;
using loss_test::uniform;

TEST_CASE("match loss: InfoNCE over the other view's pixels and the mask cross-entropy by hand", "[loss][match]") {
  // Two views of two pixels, 2-D descriptors. View 0 pixel 0 = (1, 0) matches view 1 pixel 1 = (2, 0) (norm 2: only the
  // direction counts); view 1 pixel 0 = (0, 3).
  const std::vector<double> desc{1, 0, 0, 1, 0, 3, 2, 0}, prob{0.5, 0.9, 0.2, 0.6}, alpha{1, 1, 0, 1};
  const std::vector<loss::PixelMatch> m{{0, 0, 1, 1}};
  loss::MatchLossConfig c;
  c.temperature = 0.5;
  c.foreground_weight = 2;
  const auto p = loss::match_loss_forward(desc.data(), prob.data(), alpha.data(), std::span(m), 2, 2, 2, c);
  // s = (0, 2): -log(e^2 / (1 + e^2)), up to the 1e-12 the normalisation adds under its square root.
  CHECK(p.match == Approx(std::log(1 + std::exp(2.0)) - 2.0).epsilon(1e-11));
  CHECK(p.foreground == Approx(-(std::log(0.5) + std::log(0.9) + std::log(0.8) + std::log(0.6)) / 4).epsilon(1e-14));
  CHECK(p.total == Approx(p.match + 2 * p.foreground).epsilon(1e-15));
  const std::vector<loss::PixelMatch> bad{{0, 0, 2, 1}};
  CHECK_THROWS_WITH(loss::match_loss_forward(desc.data(), prob.data(), alpha.data(), std::span(bad), 2, 2, 2, c),
                    Catch::Contains("outside 2 views"));
}

TEST_CASE("match loss: gradient check for descriptors and object probabilities", "[loss][match][gradcheck]") {
  const index_t V = 3, px = 10, D = 4;
  auto desc = uniform(V * px * D, 3, -1, 1), prob = uniform(V * px, 4, 0.05, 0.95), alpha = uniform(V * px, 5, 0, 1);
  std::vector<loss::PixelMatch> m;
  for (index_t i = 0; i < 8; ++i) m.push_back({i % V, (3 * i) % px, (i + 1) % V, (7 * i + 2) % px});
  loss::MatchLossConfig c;
  c.temperature = 0.3;
  std::vector<double> dd(desc.size()), dp(prob.size());
  const auto r = testing::check_gradients(
      {{"descriptors", desc, dd}, {"probability", prob, dp}}, 1,
      [&](std::span<double> out) {
        out[0] = loss::match_loss_forward(desc.data(), prob.data(), alpha.data(), std::span<const loss::PixelMatch>(m), V,
                                          px, D, c).total;
      },
      [&](std::span<const double> d) {
        loss::match_loss_backward(dd.data(), dp.data(), d[0], desc.data(), prob.data(), alpha.data(),
                                  std::span<const loss::PixelMatch>(m), V, px, D, c);
      });
  INFO(r.summary());
  CHECK(r.ok());
}

TEST_CASE("ground_truth_matches pairs pixels that see the same surface point and skips occluded ones",
          "[loss][match]") {
  // A fronto-parallel plane at z = 2 seen by two cameras 0.2 apart along x; view 1 sees it shifted by f * 0.2 / 2 =
  // 1 pixel. A third view sees a nearer plane (z = 1) in front: its pixels are occluders, never matches.
  const index_t h = 6, w = 8, px = h * w;
  std::vector<double> depth(3 * px, 2.0), K, E;
  for (int v = 0; v < 3; ++v) {
    const double k[9] = {10, 0, 4, 0, 10, 3, 0, 0, 1};
    K.insert(K.end(), k, k + 9);
    const double e[12] = {1, 0, 0, v == 1 ? -0.2 : 0.0, 0, 1, 0, 0, 0, 0, 1, 0};
    E.insert(E.end(), e, e + 12);
  }
  for (index_t p = 0; p < px; ++p) depth[2 * px + p] = 1.0;
  const auto m = loss::ground_truth_matches(depth.data(), K.data(), E.data(), 3, h, w, 1000);
  index_t pairs01 = 0;
  for (const auto& x : m) {
    CHECK(x.view_a != x.view_b);
    CHECK(x.view_a != 2);  // view 2's surface is nowhere else at its depth
    CHECK(x.view_b != 2);  // and hides view 0/1's surface
    if (x.view_a == 0 && x.view_b == 1) {
      ++pairs01;
      CHECK(x.pixel_b / w == x.pixel_a / w);
      CHECK(x.pixel_b % w == x.pixel_a % w - 1);
    }
  }
  CHECK(pairs01 == h * (w - 1));
  CHECK(loss::ground_truth_matches(depth.data(), K.data(), E.data(), 3, h, w, 5).size() == 10);
}

TEST_CASE("match_accuracy counts correspondences whose nearest descriptor is within a pixel (or a radius) of the true one",
          "[loss][match]") {
  // Two 6 x 6 views, D = 3: view 0's pixel p has the code of p; view 1 holds the same codes shifted right by `shift`.
  const index_t h = 6, w = 6, px = h * w, D = 3;
  auto codes = [&](int shift) {
    std::vector<double> d(static_cast<std::size_t>(2 * px * D));
    for (index_t v = 0; v < 2; ++v)
      for (index_t p = 0; p < px; ++p) {
        const index_t x = p % w, y = p / w, src = v == 0 ? p : y * w + (x - shift + w) % w;
        const double a = 2 * 3.14159265358979 * static_cast<double>(src) / static_cast<double>(px);
        d[static_cast<std::size_t>((v * px + p) * D)] = std::cos(a);
        d[static_cast<std::size_t>((v * px + p) * D + 1)] = std::sin(a);
        d[static_cast<std::size_t>((v * px + p) * D + 2)] = 0.1;
      }
    return d;
  };
  // The truth: pixel (x, y) of view 0 is pixel (x + 1, y) of view 1, for x < 4 (no shift below wraps round).
  std::vector<loss::PixelMatch> truth;
  for (index_t p = 0; p < px; ++p)
    if (p % w < w - 2) truth.push_back({0, p, 1, p + 1});
  CHECK(loss::match_accuracy(codes(1).data(), truth, 2, h, w, D) == 1.0);
  CHECK(loss::match_accuracy(codes(2).data(), truth, 2, h, w, D) == 1.0);  // one pixel off still counts
  // Three pixels off (each code sits 3 columns, modulo 6, from the truth): none counts.
  CHECK(loss::match_accuracy(codes(4).data(), truth, 2, h, w, D) == 0.0);
  CHECK(loss::match_accuracy(codes(1).data(), {}, 2, h, w, D) == 0.0);
  // Other radii: exact (0) and three pixels; a negative radius is refused.
  CHECK(loss::match_accuracy(codes(1).data(), truth, 2, h, w, D, 0) == 1.0);
  CHECK(loss::match_accuracy(codes(2).data(), truth, 2, h, w, D, 0) == 0.0);
  CHECK(loss::match_accuracy(codes(4).data(), truth, 2, h, w, D, 2) == 0.0);
  CHECK(loss::match_accuracy(codes(4).data(), truth, 2, h, w, D, 3) == 1.0);
  CHECK_THROWS_WITH(loss::match_accuracy(codes(1).data(), truth, 2, h, w, D, -1), Catch::Contains("radius -1 is negative"));
  // One search of the nearest pixels serves every radius: with codes shifted by 4 each nearest pixel is pixel_b moved
  // 3 columns right, modulo 6.
  const std::vector<double> shifted = codes(4);
  const std::vector<index_t> nearest = loss::nearest_descriptor_pixels(shifted.data(), std::span<const loss::PixelMatch>(truth), 2, h, w, D);
  REQUIRE(nearest.size() == truth.size());
  for (std::size_t i = 0; i < truth.size(); ++i) {
    const index_t want = truth[i].pixel_b;
    CHECK(nearest[i] == want / w * w + (want % w + 3) % w);
  }
  for (index_t radius : {0, 1, 2, 3, 4, 5})  // every nearest pixel is 3 columns from the truth
    CHECK(loss::match_hits(nearest, truth, w, radius) == (radius < 3 ? 0.0 : static_cast<double>(truth.size())));
  CHECK(loss::within_pixels(7, 7 + 2 * w + 2, w, 2));
  CHECK_FALSE(loss::within_pixels(7, 7 + 3 * w, w, 2));
  CHECK_THROWS_WITH(loss::match_hits(std::span<const index_t>(nearest).first(3), truth, w),
                    Catch::Contains("3 nearest pixels for 24 correspondences"));
}

TEST_CASE("match loss: the vector exp path gives the scalar path's loss and gradients", "[loss][match][simd]") {
  // 56 x 56 views and 16-channel descriptors, the pose recipe's shapes; runs of matches in every ordered pair.
  const index_t V = 3, px = 56 * 56, D = 16;
  const auto d64 = uniform(V * px * D, 11, -1, 1), p64 = uniform(V * px, 12, 0.05, 0.95), a64 = uniform(V * px, 13, 0, 1);
  const std::vector<float> desc(d64.begin(), d64.end()), prob(p64.begin(), p64.end()), alpha(a64.begin(), a64.end());
  std::vector<loss::PixelMatch> m;
  for (index_t a = 0; a < V; ++a)
    for (index_t b = 0; b < V; ++b)
      if (a != b)
        for (index_t i = 0; i < 40; ++i) m.push_back({a, (97 * i + 13 * a) % px, b, (61 * i + 7 * b) % px});
  loss::MatchLossConfig c;
  c.temperature = 0.1;
  auto run = [&](simd::Lanes lanes, std::vector<float>& dd, std::vector<float>& dp) {
    dd.assign(desc.size(), 0.f), dp.assign(prob.size(), 0.f);
    const auto parts = loss::match_loss_forward(desc.data(), prob.data(), alpha.data(),
                                                std::span<const loss::PixelMatch>(m), V, px, D, c, lanes);
    loss::match_loss_backward(dd.data(), dp.data(), 1.0, desc.data(), prob.data(), alpha.data(),
                              std::span<const loss::PixelMatch>(m), V, px, D, c, lanes);
    return parts.total;
  };
  std::vector<float> dd0, dp0, dd1, dp1;
  const double scalar = run(simd::Lanes::scalar, dd0, dp0);
  const simd::Lanes best = simd::best_lanes<float>();
  INFO("lanes " << simd::lanes_name(best));
  const double vector = run(best, dd1, dp1);
  CHECK(vector == Approx(scalar).epsilon(1e-6));
  double worst = 0, largest = 0;
  for (std::size_t i = 0; i < dd0.size(); ++i) {
    worst = std::max(worst, std::abs(static_cast<double>(dd1[i]) - static_cast<double>(dd0[i])));
    largest = std::max(largest, std::abs(static_cast<double>(dd0[i])));
  }
  REQUIRE(largest > 0);
  CHECK(worst <= 1e-5 * largest);
  CHECK(dp0 == dp1);  // the mask term has no exp
}
