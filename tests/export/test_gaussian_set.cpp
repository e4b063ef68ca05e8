#include <catch2/catch.hpp>

#include <cmath>
#include <limits>

#include "export/random_set.hpp"
#include "flexsplat/export/gaussian_set.hpp"

using namespace flexsplat;
using flexsplat_test::random_set;

TEST_CASE("a random set validates and reports its degree and bounds", "[export]") {
  auto set = random_set(50, 2);
  CHECK(set.size() == 50);
  CHECK(set.sh_degree() == 2);
  CHECK_NOTHROW(gaussians::validate(set));
  const auto b = gaussians::position_bounds(set);
  for (int c = 0; c < 3; ++c) {
    CHECK(b.min[c] >= -1.0);
    CHECK(b.max[c] <= 1.0);
    CHECK(b.min[c] < b.max[c]);
  }
}

TEST_CASE("validate names the offending tensor and Gaussian", "[export]") {
  auto set = random_set(10, 1);
  SECTION("NaN position") {
    set.means(3, 1) = std::numeric_limits<float>::quiet_NaN();
    CHECK_THROWS_WITH(gaussians::validate(set), Catch::Contains("'means'") && Catch::Contains("Gaussian 3"));
  }
  SECTION("non-unit quaternion") {
    set.quats(4, 0) *= 2.0f;
    CHECK_THROWS_WITH(gaussians::validate(set), Catch::Contains("rotation of Gaussian 4 is not a unit quaternion"));
  }
  SECTION("opacity above one") {
    set.opacities(5) = 1.5f;
    CHECK_THROWS_WITH(gaussians::validate(set), Catch::Contains("opacity of Gaussian 5 is 1.5"));
  }
  SECTION("negative scale") {
    set.scales(6, 2) = -0.1f;
    CHECK_THROWS_WITH(gaussians::validate(set), Catch::Contains("scale 2 of Gaussian 6 is negative"));
  }
  SECTION("shape mismatch") {
    set.opacities = Tensor<float, 1>({9});
    CHECK_THROWS_WITH(gaussians::validate(set), Catch::Contains("'opacities' has shape [9]"));
  }
  SECTION("incomplete SH degree") {
    set.sh = Tensor<float, 3>({10, 5, 3});
    CHECK_THROWS_WITH(gaussians::validate(set), Catch::Contains("5 SH coefficients"));
  }
}

TEST_CASE("export repairs clamp opacities and renormalise quaternions, counting both", "[export]") {
  auto set = random_set<double>(8, 0);
  set.opacities(0) = -0.25;
  set.opacities(1) = 1.75;
  set.quats(2, 1) += 0.5;
  const auto repairs = gaussians::repair_for_export(set);
  CHECK(repairs.opacities_clamped == 2);
  CHECK(repairs.rotations_renormalised == 1);
  CHECK(set.opacities(0) == 0.0);
  CHECK(set.opacities(1) == 1.0);
  CHECK(gaussians::quaternion_norm(set, 2) == Approx(1.0).epsilon(1e-12));
}

TEST_CASE("export refuses what it cannot repair", "[export]") {
  auto set = random_set<double>(4, 0);
  SECTION("zero quaternion") {
    for (int c = 0; c < 4; ++c) set.quats(1, c) = 0;
    CHECK_THROWS_WITH(gaussians::repair_for_export(set), Catch::Contains("rotation of Gaussian 1 cannot be normalised"));
  }
  SECTION("NaN opacity") {
    set.opacities(2) = std::nan("");
    CHECK_THROWS_WITH(gaussians::repair_for_export(set), Catch::Contains("'opacities' has a non-finite value"));
  }
}

TEST_CASE("element type conversion keeps values and shapes", "[export]") {
  auto set = random_set<float>(5, 3);
  set.features = Tensor<float, 2>({5, 2}, 0.25f);
  const auto d = convert_gaussian_set<double>(set);
  CHECK(d.sh(4, 15, 2) == double(set.sh(4, 15, 2)));
  CHECK(d.quats(3, 1) == double(set.quats(3, 1)));
  CHECK(d.features.shape() == Shape<2>{5, 2});
  CHECK(d.features(4, 1) == 0.25);
}
