#include <catch2/catch.hpp>

#include "decoder_test_util.hpp"
#include "flexsplat/decoder/init.hpp"

using namespace flexsplat;

TEST_CASE("scene centre is the intersection of converging optical axes", "[decoder][init]") {
  for (index_t views : {2, 3, 4}) {
    const auto rig = make_rig(views, 3.0);
    const auto c = decoder::scene_centre_from_axes(rig.geometry());
    CHECK(c.from_axes);
    for (int i = 0; i < 3; ++i) CHECK(c.centre[i] == Approx(0.0).margin(1e-9));
  }
}

TEST_CASE("one view or identical cameras fall back to the median-depth point", "[decoder][init]") {
  for (index_t copies : {1, 3}) {
    auto rig = make_rig(1, 3.0);
    const auto one = rig;
    for (index_t v = 1; v < copies; ++v) {
      rig.K.insert(rig.K.end(), one.K.begin(), one.K.end());
      rig.E.insert(rig.E.end(), one.E.begin(), one.E.end());
      rig.depth.insert(rig.depth.end(), one.depth.begin(), one.depth.end());
    }
    rig.views = copies;
    for (auto& d : rig.depth) d = 3.0 * std::sqrt(1.09);  // the camera's distance to the origin it looks at
    const auto c = decoder::scene_centre_from_axes(rig.geometry());
    CHECK_FALSE(c.from_axes);
    for (int i = 0; i < 3; ++i) CHECK(c.centre[i] == Approx(0.0).margin(1e-9));
  }
}

TEST_CASE("scene centre rejects bad weights", "[decoder][init]") {
  const auto rig = make_rig(2);
  const double zero[2] = {0, 0}, negative[2] = {1, -1};
  CHECK_THROWS_WITH(decoder::scene_centre_from_axes(rig.geometry(), zero), Catch::Contains("all view weights are zero"));
  CHECK_THROWS_WITH(decoder::scene_centre_from_axes(rig.geometry(), negative), Catch::Contains("view 1 has weight -1"));
}

TEST_CASE("Xavier-uniform stays inside its bound", "[decoder][init]") {
  std::mt19937_64 rng(1);
  std::vector<double> w(24 * 256);
  decoder::xavier_uniform(w.data(), 24, 256, rng);
  const double a = std::sqrt(6.0 / 280.0);
  double max_abs = 0;
  for (double x : w) max_abs = std::max(max_abs, std::abs(x));
  CHECK(max_abs <= a);
  CHECK(max_abs > 0.9 * a);
}
