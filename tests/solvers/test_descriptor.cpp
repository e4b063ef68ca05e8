#include <catch2/catch.hpp>

#include <cmath>
#include <limits>
#include <vector>

#include "flexsplat/solvers/descriptor.hpp"

using namespace flexsplat;
using namespace flexsplat::geometry;

TEST_CASE("unit descriptors: unit length, direction kept, blank and broken vectors refused", "[descriptor]") {
  const std::vector<float> d = {3.f, 0.f, -4.f};
  std::vector<float> out(3, 7.f);
  REQUIRE(unit_descriptor(d.data(), 3, out.data()));
  CHECK(out[0] == Approx(0.6f).epsilon(1e-7));
  CHECK(out[1] == 0.f);
  CHECK(out[2] == Approx(-0.8f).epsilon(1e-7));

  // Lengths whose square overflows float are summed in double.
  const std::vector<float> big = {3e30f, 4e30f};
  std::vector<float> ob(2);
  REQUIRE(unit_descriptor(big.data(), 2, ob.data()));
  CHECK(ob[0] == Approx(0.6f).epsilon(1e-7));
  CHECK(ob[1] == Approx(0.8f).epsilon(1e-7));

  const std::vector<double> dd = {0.0, 2.0};
  std::vector<float> od(2);
  REQUIRE(unit_descriptor(dd.data(), 2, od.data()));
  CHECK(od[0] == 0.f);
  CHECK(od[1] == 1.f);

  const float nan = std::numeric_limits<float>::quiet_NaN(), inf = std::numeric_limits<float>::infinity();
  for (const std::vector<float>& bad : {std::vector<float>{0.f, 0.f}, std::vector<float>{1.f, nan},
                                        std::vector<float>{inf, 1.f}, std::vector<float>{}}) {
    std::vector<float> o(2, 7.f);
    CHECK_FALSE(unit_descriptor(bad.data(), static_cast<index_t>(bad.size()), o.data()));
    CHECK(o[0] == 7.f);  // untouched
    CHECK(o[1] == 7.f);
  }
}
