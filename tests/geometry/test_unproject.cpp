#include <catch2/catch.hpp>

#include <cmath>

#include "flexsplat/geometry/unproject.hpp"
#include "heads_bundle.hpp"

using namespace flexsplat;
using namespace flexsplat::geometry;

TEST_CASE("unprojection reproduces the bundle's world points", "[unproject]") {
  const auto cases = heads_test::bundle_cases();
  for (std::size_t k = 0; k < cases.size(); ++k) {
    const auto [S, H, W] = cases[k];
    const std::string p = "case" + std::to_string(k) + ".";
    const auto depth = heads_test::read<float>(p + "depth");
    const auto extr = heads_test::read<float>(p + "extrinsics");
    const auto intr = heads_test::read<float>(p + "intrinsics");
    const auto expected = heads_test::read<float>(p + "world_points");
    std::vector<float> points(S * H * W * 3);
    unproject_depth_forward(points.data(), depth.data(), extr.data(), intr.data(), S, H, W);
    heads_test::check_close(p + "world_points", points, expected);
    const double rel = heads_test::max_elementwise_rel(points, expected, 1e-3);
    INFO("element-wise relative error " << rel);
    CHECK(rel <= 1e-4);
  }
}

TEST_CASE("unprojection inverts projection", "[unproject]") {
  // World-to-camera: 90 degrees about z, then translate.
  const double E[12] = {0, -1, 0, 0.5, 1, 0, 0, -1, 0, 0, 1, 2};
  const double K[9] = {50, 0, 16, 0, 40, 12, 0, 0, 1};
  const index_t H = 24, W = 32;
  std::vector<double> depth(H * W), points(H * W * 3);
  for (index_t i = 0; i < H * W; ++i) depth[i] = 1.0 + 0.01 * static_cast<double>(i % 37);
  unproject_depth_forward(points.data(), depth.data(), E, K, 1, H, W);
  for (index_t v = 0; v < H; ++v)
    for (index_t u = 0; u < W; ++u) {
      const double* X = points.data() + (v * W + u) * 3;
      double cam[3];
      for (int r = 0; r < 3; ++r) cam[r] = E[r * 4] * X[0] + E[r * 4 + 1] * X[1] + E[r * 4 + 2] * X[2] + E[r * 4 + 3];
      CHECK(cam[2] == Approx(depth[v * W + u]).epsilon(1e-12));
      CHECK(K[0] * cam[0] / cam[2] + K[2] == Approx(static_cast<double>(u)).margin(1e-9));
      CHECK(K[4] * cam[1] / cam[2] + K[5] == Approx(static_cast<double>(v)).margin(1e-9));
    }
}

TEST_CASE("camera-frame points are view f's depth unprojected with its own intrinsics", "[unproject]") {
  const index_t H = 3, W = 4, px = H * W;
  const float K[18] = {10, 0, 1, 0, 10, 1, 0, 0, 1, 20, 0, 1.5f, 0, 25, 0.5f, 0, 0, 1};
  std::vector<float> depth(2 * px);
  for (index_t i = 0; i < 2 * px; ++i) depth[i] = 1.0f + 0.25f * static_cast<float>(i % 5);
  const std::vector<double> cam = camera_frame_points(depth.data(), K, 1, H, W);
  REQUIRE(cam.size() == static_cast<std::size_t>(3 * px));
  for (index_t v = 0; v < H; ++v)
    for (index_t u = 0; u < W; ++u) {
      const double d = depth[px + v * W + u];
      const double* X = cam.data() + 3 * (v * W + u);
      CHECK(X[0] == Approx((static_cast<double>(u) - 1.5) / 20 * d).epsilon(1e-12));
      CHECK(X[1] == Approx((static_cast<double>(v) - 0.5) / 25 * d).epsilon(1e-12));
      CHECK(X[2] == d);
    }
}

TEST_CASE("unprojection rejects bad cameras", "[unproject]") {
  const float E[12] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0};
  const float depth[4] = {1, 1, 1, 1};
  float points[12];
  const float zero_focal[9] = {0, 0, 1, 0, 10, 1, 0, 0, 1};
  CHECK_THROWS_WITH(unproject_depth_forward(points, depth, E, zero_focal, 1, 2, 2), Catch::Contains("focal"));
  const float skew[9] = {10, 0.5f, 1, 0, 10, 1, 0, 0, 1};
  CHECK_THROWS_WITH(unproject_depth_forward(points, depth, E, skew, 1, 2, 2), Catch::Contains("skew"));
  const float nan_focal[9] = {NAN, 0, 1, 0, 10, 1, 0, 0, 1};
  CHECK_THROWS_WITH(unproject_depth_forward(points, depth, E, nan_focal, 1, 2, 2), Catch::Contains("focal"));
  const float K[9] = {10, 0, 1, 0, 10, 1, 0, 0, 1};
  float bad_E[12] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0};
  bad_E[7] = INFINITY;
  CHECK_THROWS_WITH(unproject_depth_forward(points, depth, bad_E, K, 1, 2, 2), Catch::Contains("extrinsics entry 7"));
}
