// Unprojection backward: float64 gradient checks into depth, extrinsics and the four intrinsics, the += contract,
// and the whole camera chain pose_enc -> (extrinsics, intrinsics) -> world points.
#include <catch2/catch.hpp>

#include <random>

#include "flexsplat/geometry/pose_encoding.hpp"
#include "flexsplat/geometry/unproject.hpp"
#include "flexsplat/testing/gradcheck.hpp"

using namespace flexsplat;
using namespace flexsplat::geometry;

namespace unproject_backward_test {

std::vector<double> uniform_values(std::size_t n, unsigned seed, double lo, double hi) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(lo, hi);
  std::vector<double> v(n);
  for (auto& x : v) x = u(rng);
  return v;
}

}  // namespace unproject_backward_test

using namespace unproject_backward_test;

TEST_CASE("unprojection backward matches finite differences", "[unproject][backward]") {
  const index_t S = 2, H = 5, W = 7;
  auto depth = uniform_values(S * H * W, 1, 0.5, 3.0);
  auto ext = uniform_values(S * 12, 2, -1.0, 1.0);
  auto focal_pp = uniform_values(S * 4, 3, 2.0, 8.0);  // fx, fy, cx, cy per frame (zero skew stays exact)
  std::vector<double> d_depth(depth.size()), d_ext(ext.size()), d_fp(focal_pp.size());
  auto build_K = [&] {
    std::vector<double> K(S * 9, 0.0);
    for (index_t f = 0; f < S; ++f) {
      K[f * 9 + 0] = focal_pp[f * 4 + 0];
      K[f * 9 + 4] = focal_pp[f * 4 + 1];
      K[f * 9 + 2] = focal_pp[f * 4 + 2];
      K[f * 9 + 5] = focal_pp[f * 4 + 3];
      K[f * 9 + 8] = 1.0;
    }
    return K;
  };
  const auto result = testing::check_gradients(
      {{"depth", depth, d_depth}, {"extrinsics", ext, d_ext}, {"fx fy cx cy", focal_pp, d_fp}},
      static_cast<std::size_t>(S * H * W * 3),
      [&](std::span<double> out) {
        const auto K = build_K();
        unproject_depth_forward(out.data(), depth.data(), ext.data(), K.data(), S, H, W);
      },
      [&](std::span<const double> d) {
        const auto K = build_K();
        std::vector<double> d_K(S * 9, 0.0);
        unproject_depth_backward(d_depth.data(), d_ext.data(), d_K.data(), d.data(), depth.data(), ext.data(), K.data(),
                                 S, H, W);
        for (index_t f = 0; f < S; ++f) {
          d_fp[f * 4 + 0] += d_K[f * 9 + 0];
          d_fp[f * 4 + 1] += d_K[f * 9 + 4];
          d_fp[f * 4 + 2] += d_K[f * 9 + 2];
          d_fp[f * 4 + 3] += d_K[f * 9 + 5];
        }
      });
  INFO(result.summary());
  CHECK(result.ok());
}

TEST_CASE("pose encoding to world points: chained backward matches finite differences", "[unproject][pose_encoding][backward]") {
  const index_t S = 2, H = 4, W = 6;
  auto depth = uniform_values(S * H * W, 4, 0.5, 3.0);
  auto enc = uniform_values(S * 9, 5, -1.0, 1.0);
  for (index_t f = 0; f < S; ++f) enc[f * 9 + 7] = 0.9 + 0.3 * f, enc[f * 9 + 8] = 1.1 - 0.2 * f;
  std::vector<double> d_depth(depth.size()), d_enc(enc.size());
  std::vector<double> ext(S * 12), K(S * 9);
  const auto result = testing::check_gradients(
      {{"depth", depth, d_depth}, {"pose_enc", enc, d_enc}}, static_cast<std::size_t>(S * H * W * 3),
      [&](std::span<double> out) {
        pose_encoding_to_extri_intri(ext.data(), K.data(), enc.data(), S, H, W);
        unproject_depth_forward(out.data(), depth.data(), ext.data(), K.data(), S, H, W);
      },
      [&](std::span<const double> d) {
        pose_encoding_to_extri_intri(ext.data(), K.data(), enc.data(), S, H, W);
        std::vector<double> d_ext(ext.size(), 0.0), d_K(K.size(), 0.0);
        unproject_depth_backward(d_depth.data(), d_ext.data(), d_K.data(), d.data(), depth.data(), ext.data(), K.data(),
                                 S, H, W);
        pose_encoding_to_extri_intri_backward(d_enc.data(), d_ext.data(), d_K.data(), enc.data(), S, H, W);
      });
  INFO(result.summary());
  CHECK(result.ok());
}

TEST_CASE("unprojection backward: null gradient slots are skipped and zero focal is an error", "[unproject][backward]") {
  const index_t S = 1, H = 2, W = 3;
  const auto depth = uniform_values(H * W, 6, 1.0, 2.0), ext = uniform_values(12, 7, -1.0, 1.0),
             d_world = uniform_values(H * W * 3, 8, -1.0, 1.0);
  std::vector<double> K = {4, 0, 1, 0, 5, 1, 0, 0, 1}, d_depth(H * W, 0.0), d_depth2(H * W, 0.0), d_ext(12, 0.0);
  unproject_depth_backward(d_depth.data(), d_ext.data(), static_cast<double*>(nullptr), d_world.data(), depth.data(),
                           ext.data(), K.data(), S, H, W);
  unproject_depth_backward(d_depth2.data(), static_cast<double*>(nullptr), static_cast<double*>(nullptr),
                           d_world.data(), depth.data(), ext.data(), K.data(), S, H, W);
  CHECK(d_depth == d_depth2);
  K[0] = 0;
  CHECK_THROWS_WITH(unproject_depth_backward(d_depth.data(), d_ext.data(), static_cast<double*>(nullptr), d_world.data(),
                                             depth.data(), ext.data(), K.data(), S, H, W),
                    Catch::Contains("focal lengths (0, 5)"));
}
