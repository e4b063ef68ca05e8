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

TEST_CASE("gradcheck fails a zero backward for a gradient below the tolerance (the floor)", "[gradcheck]") {
  // y = 1e-8 x: a backward returning zero is within abs_tol 1e-7 of every entry, so only the floor catches it.
  std::vector<double> x{0.5, -0.25}, dx(2);
  bool zero = false;
  const auto run = [&](double scale) {
    return testing::check_gradients(
        {{"x", x, dx}}, 2, [&](std::span<double> y) { y[0] = scale * x[0], y[1] = scale * x[1]; },
        [&](std::span<const double> dy) {
          if (!zero) dx[0] += scale * dy[0], dx[1] += scale * dy[1];
        },
        {}, 3);
  };
  zero = true;
  const auto tiny = run(1e-8);
  CHECK(tiny.mismatches.empty());
  CHECK_FALSE(tiny.ok());
  REQUIRE(tiny.tensors.size() == 1);
  CHECK(tiny.tensors[0].below_floor);
  CHECK(tiny.summary().find("x: 2 entries") != std::string::npos);
  CHECK(tiny.summary().find("BELOW THE FLOOR") != std::string::npos);
  zero = false;
  CHECK_FALSE(run(1e-8).ok());  // a correct backward of a gradient this small cannot clear the floor either
  const auto fine = run(1.0);
  INFO(fine.summary());
  CHECK(fine.ok());
  zero = true;
  CHECK_FALSE(run(1.0).ok());
}

TEST_CASE("gradcheck samples the largest analytic entry of a large tensor, so a sparse gradient is reached",
          "[gradcheck]") {
  // Only x[317] reaches the output: 4 random entries of 500 would miss it, and the floor would fail a correct backward.
  std::vector<double> x(500, 0.3), dx(500);
  bool zero = false;
  testing::GradCheckOptions options;
  options.max_checks_per_param = 4;
  const auto run = [&] {
    return testing::check_gradients(
        {{"x", x, dx}}, 1, [&](std::span<double> y) { y[0] = x[317] * x[317]; },
        [&](std::span<const double> dy) {
          if (!zero) dx[317] += 2 * x[317] * dy[0];
        },
        options, 11);
  };
  const auto good = run();
  INFO(good.summary());
  CHECK(good.ok());
  CHECK(good.checked == 4);
  zero = true;
  const auto bad = run();
  CHECK_FALSE(bad.ok());
  CHECK(bad.below_floor() == 1);
}

TEST_CASE("gradcheck checks a declared structurally zero gradient and reports its reason", "[gradcheck]") {
  std::vector<double> x{0.4, 0.9}, unused{1.5, 2.5}, dx(2), du(2);
  double leak = 0;  // a backward writing into the unused tensor
  const auto run = [&] {
    return testing::check_gradients(
        {{"x", x, dx}, {"unused", unused, du, "not read by the toy forward"}}, 2,
        [&](std::span<double> y) { y[0] = x[0] * x[1], y[1] = x[0]; },
        [&](std::span<const double> dy) {
          dx[0] += dy[0] * x[1] + dy[1], dx[1] += dy[0] * x[0];
          du[1] += leak;
        },
        {}, 5);
  };
  const auto good = run();
  INFO(good.summary());
  CHECK(good.ok());
  CHECK(good.summary().find("unused: 2 entries, max |numeric| 0 structurally zero: not read by the toy forward") !=
        std::string::npos);
  leak = 1e-3;
  const auto bad = run();
  CHECK_FALSE(bad.ok());
  REQUIRE_FALSE(bad.mismatches.empty());
  CHECK(bad.mismatches[0].param == "unused");
  CHECK(bad.mismatches[0].index == 1);
}

TEST_CASE("gradcheck with a unit cotangent checks a function that adds its whole gradient itself", "[gradcheck]") {
  // f(x) = sum x_i^3, "library" gradient added straight into the checker's buffer (no cotangent to scale by).
  std::vector<double> x{0.5, -1.5, 2.0}, dx(3);
  bool assign = false;
  const auto library_gradient = [&](double* grad) {
    for (std::size_t i = 0; i < 3; ++i) grad[i] = (assign ? 0.0 : grad[i]) + 3 * x[i] * x[i];
  };
  testing::GradCheckOptions options;
  options.unit_cotangent = true;
  const auto run = [&] {
    return testing::check_gradients(
        {{"x", x, dx}}, 1,
        [&](std::span<double> y) { y[0] = x[0] * x[0] * x[0] + x[1] * x[1] * x[1] + x[2] * x[2] * x[2]; },
        [&](std::span<const double> dy) {
          REQUIRE(dy[0] == 1.0);
          library_gradient(dx.data());
        },
        options, 9);
  };
  const auto good = run();
  INFO(good.summary());
  CHECK(good.ok());
  assign = true;
  CHECK_FALSE(run().ok());
}

TEST_CASE("gradcheck splits a flat block into its tensors and refuses names that do not cover it", "[gradcheck]") {
  std::vector<double> v(7), g(7);
  const auto params = testing::split_flat(v, g, {{"a.weight", 4}, {"a.bias", 2}, {"b", 1}}, "m.");
  REQUIRE(params.size() == 3);
  CHECK(params[1].name == "m.a.bias");
  CHECK(params[1].value.data() == v.data() + 4);
  CHECK(params[2].grad.data() == g.data() + 6);
  CHECK_THROWS_WITH(testing::split_flat(v, g, {{"a", 4}, {"b", 2}}), Catch::Contains("cover 6 of its 7 values"));
  CHECK_THROWS_WITH(testing::split_flat(v, g, {{"a", 4}, {"b", 4}}), Catch::Contains("'b' ends at 8"));
}
