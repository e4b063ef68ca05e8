#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <vector>

#include "decoder_test_util.hpp"
#include "flexsplat/decoder/gaussians.hpp"
#include "flexsplat/testing/gradcheck.hpp"

using namespace flexsplat;

TEST_CASE("anchors cover every view round-robin at interior pixel centres", "[decoder][gaussians]") {
  const auto a = decoder::make_anchors(10, 3, 30, 20);
  for (index_t i = 0; i < 10; ++i) {
    CHECK(a.view[i] == i % 3);
    CHECK((a.pixel[2 * i] > 0 && a.pixel[2 * i] < 30 && a.pixel[2 * i + 1] > 0 && a.pixel[2 * i + 1] < 20));
  }
  CHECK_THROWS_WITH(decoder::make_anchors(0, 2, 30, 20), Catch::Contains("budget must be positive"));
}

TEST_CASE("queries_on_outline keeps the queries whose anchors lie within the margin of the outline",
          "[decoder][gaussians]") {
  // 2 views of 40 x 40, 32 queries: a 4 x 4 grid per view, anchors 10 pixels apart at 5, 15, 25, 35. View 0 shows
  // a 6 x 6 square at [12, 18) x [12, 18) (it holds anchor (15, 15)); view 1 shows nothing.
  const index_t w = 40, h = 40, views = 2, n = 32;
  std::vector<float> outline(static_cast<std::size_t>(views * h * w), 0.0f);
  for (index_t y = 12; y < 18; ++y)
    for (index_t x = 12; x < 18; ++x) outline[static_cast<std::size_t>(y * w + x)] = 1.0f;
  const auto a = decoder::make_anchors(n, views, w, h);
  // No margin: only the anchor inside the square; query j * 2 of view 0 sits at grid cell j.
  const std::vector<index_t> inside = decoder::queries_on_outline(n, views, w, h, outline.data(), 0.0);
  REQUIRE(inside.size() == 1);
  CHECK(a.view[inside[0]] == 0);
  CHECK(a.pixel[2 * inside[0]] == 15.0);
  CHECK(a.pixel[2 * inside[0] + 1] == 15.0);
  // One spacing (10 pixels): the anchors whose 20 x 20 window meets the square, (5..25) x (5..25): 9 of view 0.
  const std::vector<index_t> near = decoder::queries_on_outline(n, views, w, h, outline.data(), 1.0);
  REQUIRE(near.size() == 9);
  for (index_t q : near) {
    CHECK(a.view[q] == 0);
    CHECK((a.pixel[2 * q] <= 25 && a.pixel[2 * q + 1] <= 25));
  }
  CHECK(std::is_sorted(near.begin(), near.end()));
  // Alpha at 0.5 is not the object; a full outline keeps every query.
  std::fill(outline.begin(), outline.end(), 0.5f);
  CHECK(decoder::queries_on_outline(n, views, w, h, outline.data(), 1.0).empty());
  std::fill(outline.begin(), outline.end(), 1.0f);
  CHECK(decoder::queries_on_outline(n, views, w, h, outline.data(), 0.0).size() == static_cast<std::size_t>(n));
  CHECK_THROWS_WITH(decoder::queries_on_outline(n, views, w, h, outline.data(), -1.0), Catch::Contains("negative"));
}

TEST_CASE("eq. 2 back-projection reproduces the depth-map point for zero offsets", "[decoder][gaussians]") {
  auto rig = make_rig(2, 3.0, 24, 20, 24, 20);
  for (auto& d : rig.depth) d = 2.5;  // constant depth: no interpolation in the way
  const auto g = rig.geometry();
  const auto a = decoder::make_anchors(6, 2, 24, 20);
  std::vector<double> state(6 * 24, 0.0), base(6), centre{0, 0, 0};
  for (index_t i = 0; i < 6; ++i) state[i * 24 + decoder::splat_quat] = 1.0;
  std::vector<unsigned char> used(6);
  decoder::anchor_depths(base.data(), used.data(), g, a, centre.data());
  GaussianSet<double> out;
  decoder::gaussians_forward(out, state.data(), base.data(), a, g);
  for (index_t i = 0; i < 6; ++i) {
    CHECK(used[i]);
    // Projecting the centre back must land on the anchor at depth 2.5.
    const double* E = &rig.E[12 * a.view[i]];
    const double* K = &rig.K[9 * a.view[i]];
    const double* X = out.means.data() + 3 * i;
    const double c[3] = {E[0] * X[0] + E[1] * X[1] + E[2] * X[2] + E[3], E[4] * X[0] + E[5] * X[1] + E[6] * X[2] + E[7],
                         E[8] * X[0] + E[9] * X[1] + E[10] * X[2] + E[11]};
    CHECK(c[2] == Approx(2.5));
    CHECK(K[0] * c[0] / c[2] + K[2] == Approx(a.pixel[2 * i]));
    CHECK(K[4] * c[1] / c[2] + K[5] == Approx(a.pixel[2 * i + 1]));
    CHECK(out.opacities(i) == Approx(0.5));
  }
}

TEST_CASE("gaussians_forward passes the float64 gradient check into state, depth and cameras", "[decoder][gaussians]") {
  auto rig = make_rig(2);
  const auto a = decoder::make_anchors(7, 2, rig.w, rig.h);
  auto state = random_normal(7 * 24, 21, 0.5);
  std::vector<double> centre{0, 0, 0}, base(7);
  std::vector<unsigned char> used(7);
  std::vector<double> dstate(state.size()), dK(rig.K.size()), dE(rig.E.size()), dD(rig.depth.size());
  const index_t n_out = 7 * (3 + 4 + 3 + 1 + 12);
  auto forward = [&](std::span<double> o) {
    const auto g = rig.geometry();
    decoder::anchor_depths(base.data(), used.data(), g, a, centre.data());
    GaussianSet<double> gs;
    decoder::gaussians_forward(gs, state.data(), base.data(), a, g);
    flatten_set(gs, o.data());
  };
  auto result = testing::check_gradients(
      {{"state", state, dstate}, {"K", rig.K, dK}, {"world_to_camera", rig.E, dE}, {"depth", rig.depth, dD}}, n_out, forward,
      [&](std::span<const double> g) {
        const auto geo = rig.geometry();
        decoder::anchor_depths(base.data(), used.data(), geo, a, centre.data());
        const GaussianSetGrad<double> d = unflatten_grad(g.data(), 7);
        decoder::gaussians_backward(dstate.data(), {dK.data(), dE.data(), dD.data()}, d, state.data(), base.data(),
                                    used.data(), a, geo);
      },
      {1e-6, 1e-7, 1e-5, 200});
  INFO(result.summary());
  CHECK(result.ok());
}

TEST_CASE("invalid predicted depth falls back to the scene centre's depth", "[decoder][gaussians]") {
  auto rig = make_rig(1);
  for (auto& d : rig.depth) d = std::nan("");
  const auto a = decoder::make_anchors(3, 1, rig.w, rig.h);
  std::vector<double> centre{0, 0, 0}, base(3);
  std::vector<unsigned char> used(3);
  decoder::anchor_depths(base.data(), used.data(), rig.geometry(), a, centre.data());
  const double* E = rig.E.data();
  for (index_t i = 0; i < 3; ++i) {
    CHECK_FALSE(used[i]);
    CHECK(base[i] == Approx(E[11]));
  }
}

TEST_CASE("bad geometry is a clear error", "[decoder][gaussians]") {
  auto rig = make_rig(2);
  rig.K[9] = 0.0;
  CHECK_THROWS_WITH(decoder::validate_geometry(rig.geometry()), Catch::Contains("view 1 has focal lengths fx 0"));
  rig = make_rig(2);
  rig.E[5] = std::nan("");
  CHECK_THROWS_WITH(decoder::validate_geometry(rig.geometry()), Catch::Contains("world_to_camera[1,1]"));
  rig = make_rig(1);
  rig.dw = 0;
  CHECK_THROWS_WITH(decoder::validate_geometry(rig.geometry()), Catch::Contains("zero-size"));
}
