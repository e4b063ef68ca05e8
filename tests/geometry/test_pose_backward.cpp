// Pose decoding backward: float64 gradient checks of quat_to_mat and of pose_encoding_to_extri_intri (translation,
// non-unit quaternions, FoV -> focal), the += contract, and zero gradient where the clamp policy replaced a value.
#include <catch2/catch.hpp>

#include <random>

#include "flexsplat/geometry/pose_encoding.hpp"
#include "flexsplat/testing/gradcheck.hpp"

using namespace flexsplat;
using namespace flexsplat::geometry;

namespace pose_backward_test {

// n encodings with translations ~N(0, 1), quaternions ~N(0, 1) (not unit) and FoVs in [0.4, 2.4].
std::vector<double> random_encodings(index_t n, unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> normal;
  std::uniform_real_distribution<double> fov(0.4, 2.4);
  std::vector<double> e(static_cast<std::size_t>(n * pose_encoding_dim));
  for (index_t f = 0; f < n; ++f) {
    for (int c = 0; c < 7; ++c) e[f * 9 + c] = normal(rng);
    e[f * 9 + 7] = fov(rng);
    e[f * 9 + 8] = fov(rng);
  }
  return e;
}

}  // namespace pose_backward_test

using namespace pose_backward_test;

TEST_CASE("quat_to_mat backward matches finite differences", "[pose_encoding][backward]") {
  std::vector<double> q = {0.3, -1.2, 0.7, 0.05};  // not unit: the scale 2 / |q|^2 matters
  std::vector<double> d_q(4);
  const auto result = testing::check_gradients(
      {{"q", q, d_q}}, 9, [&](std::span<double> R) { REQUIRE(quat_to_mat(q.data(), R.data())); },
      [&](std::span<const double> d_R) { quat_to_mat_backward(d_q.data(), d_R.data(), q.data()); });
  INFO(result.summary());
  CHECK(result.ok());
}

TEST_CASE("pose decoding backward matches finite differences", "[pose_encoding][backward]") {
  const index_t n = 3, H = 42, W = 56;
  auto enc = random_encodings(n, 7);
  std::vector<double> d_enc(enc.size());
  const auto result = testing::check_gradients(
      {{"pose_enc", enc, d_enc}}, static_cast<std::size_t>(n * 21),
      [&](std::span<double> out) { pose_encoding_to_extri_intri(out.data(), out.data() + n * 12, enc.data(), n, H, W); },
      [&](std::span<const double> d) {
        pose_encoding_to_extri_intri_backward(d_enc.data(), d.data(), d.data() + n * 12, enc.data(), n, H, W);
      });
  INFO(result.summary());
  CHECK(result.ok());
}

TEST_CASE("pose decoding backward: clamped entries get zero gradient and errors mirror the forward", "[pose_encoding][backward]") {
  auto enc = random_encodings(2, 9);
  enc[7] = 0.0;         // frame 0: fov_h at the relu floor
  enc[9 + 8] = 3.5;     // frame 1: fov_w beyond pi
  std::fill(enc.begin() + 9 + 3, enc.begin() + 9 + 7, 0.0);  // frame 1: no rotation
  std::vector<double> d_ext(24, 1.0), d_int(18, 1.0), d_enc(18, 0.5);
  PoseDecodeOptions clamp{DegeneratePosePolicy::clamp};
  pose_encoding_to_extri_intri_backward(d_enc.data(), d_ext.data(), d_int.data(), enc.data(), 2, 30, 40, clamp);
  CHECK(d_enc[7] == 0.5);
  CHECK(d_enc[8] != 0.5);
  CHECK(d_enc[9 + 7] != 0.5);
  CHECK(d_enc[9 + 8] == 0.5);
  for (int c = 3; c < 7; ++c) CHECK(d_enc[9 + c] == 0.5);
  for (int c = 0; c < 3; ++c) CHECK(d_enc[9 + c] == 1.5);  // translation passes through, added onto the seed
  CHECK_THROWS_WITH(pose_encoding_to_extri_intri_backward(d_enc.data(), d_ext.data(), d_int.data(), enc.data(), 2, 30, 40),
                    Catch::Contains("fov_h = 0 rad"));
  CHECK_THROWS_WITH(pose_encoding_to_extri_intri_backward(d_enc.data(), d_ext.data(), static_cast<const double*>(nullptr), enc.data() + 9, 1, 30, 40),
                    Catch::Contains("has no rotation"));
}
