#include <catch2/catch.hpp>

#include <cmath>
#include <cstdlib>
#include <string>
#include <vector>

#include "flexsplat/testing/gradcheck.hpp"

using namespace flexsplat;

namespace {
// y0 = sin(x0) * x1, y1 = x1^2 + w * x0, y2 = w^3
struct Toy {
  std::vector<double> x{0.3, -1.2}, w{0.7};
  std::vector<double> dx{0, 0}, dw{0};
  double dx1_factor = 1.0;  // 1 is correct; anything else is a planted bug
  bool assign_instead_of_add = false;

  void forward(std::span<double> y) const {
    y[0] = std::sin(x[0]) * x[1];
    y[1] = x[1] * x[1] + w[0] * x[0];
    y[2] = w[0] * w[0] * w[0];
  }
  void backward(std::span<const double> dy) {
    const double g0 = dy[0] * std::cos(x[0]) * x[1] + dy[1] * w[0];
    const double g1 = dx1_factor * (dy[0] * std::sin(x[0]) + dy[1] * 2 * x[1]);
    const double gw = dy[1] * x[0] + dy[2] * 3 * w[0] * w[0];
    if (assign_instead_of_add) {
      dx[0] = g0;
      dx[1] = g1;
      dw[0] = gw;
    } else {
      dx[0] += g0;
      dx[1] += g1;
      dw[0] += gw;
    }
  }
  testing::GradCheckResult check() {
    return testing::check_gradients({{"x", x, dx}, {"w", w, dw}}, 3, [&](std::span<double> y) { forward(y); },
                                    [&](std::span<const double> dy) { backward(dy); }, {}, 42);
  }
};
}  // namespace

TEST_CASE("gradcheck accepts a correct backward and restores the parameters", "[gradcheck]") {
  Toy toy;
  const auto result = toy.check();
  INFO(result.summary());
  CHECK(result.ok());
  CHECK(result.checked == 3);
  CHECK(result.seed == 42);
  CHECK(toy.x == std::vector<double>{0.3, -1.2});
  CHECK(toy.w == std::vector<double>{0.7});
}

TEST_CASE("gradcheck catches a wrong gradient and names the entry", "[gradcheck]") {
  Toy toy;
  toy.dx1_factor = 1.01;
  const auto result = toy.check();
  CHECK_FALSE(result.ok());
  REQUIRE(result.mismatches.size() == 1);
  CHECK(result.mismatches[0].param == "x");
  CHECK(result.mismatches[0].index == 1);
  CHECK(result.summary().find("x[1]") != std::string::npos);
}

TEST_CASE("gradcheck catches a backward that overwrites instead of adding", "[gradcheck]") {
  Toy toy;
  toy.assign_instead_of_add = true;
  const auto result = toy.check();
  CHECK_FALSE(result.ok());
  CHECK(result.mismatches.size() == 3);
}

TEST_CASE("gradcheck subsamples large parameters and rejects mismatched spans", "[gradcheck]") {
  std::vector<double> x(500), dx(500);
  for (std::size_t i = 0; i < x.size(); ++i) x[i] = 0.01 * double(i);
  testing::GradCheckOptions options;
  options.max_checks_per_param = 10;
  const auto result = testing::check_gradients(
      {{"x", x, dx}}, 500,
      [&](std::span<double> y) {
        for (std::size_t i = 0; i < 500; ++i) y[i] = x[i] * x[i];
      },
      [&](std::span<const double> dy) {
        for (std::size_t i = 0; i < 500; ++i) dx[i] += 2 * x[i] * dy[i];
      },
      options, 7);
  CHECK(result.ok());
  CHECK(result.checked == 10);
  std::vector<double> short_grad(3);
  CHECK_THROWS_WITH(testing::check_gradients({{"x", x, short_grad}}, 1, [](std::span<double>) {},
                                             [](std::span<const double>) {}),
                    Catch::Contains("parameter 'x' has 500 values but 3 gradient slots"));
}

TEST_CASE("FLEXSPLAT_GRADCHECK_SEED is parsed strictly", "[gradcheck]") {
  const char* old = std::getenv("FLEXSPLAT_GRADCHECK_SEED");
  const std::string saved = old ? old : "";
  ::setenv("FLEXSPLAT_GRADCHECK_SEED", "123", 1);
  CHECK(testing::gradcheck_seed() == 123);
  ::setenv("FLEXSPLAT_GRADCHECK_SEED", "12x", 1);
  CHECK_THROWS_WITH(testing::gradcheck_seed(), Catch::Contains("'12x' is not an unsigned integer"));
  ::setenv("FLEXSPLAT_GRADCHECK_SEED", "-5", 1);
  CHECK_THROWS(testing::gradcheck_seed());
  ::unsetenv("FLEXSPLAT_GRADCHECK_SEED");
  CHECK(testing::gradcheck_seed(99) == 99);
  if (old) ::setenv("FLEXSPLAT_GRADCHECK_SEED", saved.c_str(), 1);
}
