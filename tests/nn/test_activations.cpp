#include <catch2/catch.hpp>

#include <cmath>
#include <random>
#include <type_traits>
#include <vector>

#include "flexsplat/core/simd_dispatch.hpp"
#include "flexsplat/nn/activations.hpp"
#include "flexsplat/testing/gradcheck.hpp"
#include "nn_test_util.hpp"
#include "simd_lanes.hpp"

using namespace flexsplat;

namespace {
template <class T>
std::vector<T> uniform_vector(std::size_t n, unsigned seed, double lo, double hi) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> uniform(lo, hi);
  std::vector<T> v(n);
  for (auto& x : v) x = T(uniform(rng));
  return v;
}

// Values spanning the GELU regimes (deep negative, around zero, large positive), not a multiple of any batch width.
template <class T>
std::vector<T> gelu_inputs() {
  auto v = uniform_vector<T>(1001, 91, -9.0, 9.0);
  v[0] = T(0), v[1] = T(-30), v[2] = T(30), v[3] = T(1e-6);
  return v;
}

// The vector path `lanes` within tol (1 + |scalar|) of the scalar path, forward and backward.
template <class T>
void check_gelu_paths(double tol, simd::Lanes lanes) {
  const auto x = gelu_inputs<T>();
  const auto n = static_cast<index_t>(x.size());
  const auto g = uniform_vector<T>(x.size(), 92, -3.0, 3.0);
  std::vector<T> scalar_out(x.size()), scalar_d(x.size(), T(0.5));  // backward adds
  nn::gelu_forward_impl<T>(scalar_out.data(), x.data(), n, simd::Lanes::scalar);
  nn::gelu_backward_impl<T>(scalar_d.data(), g.data(), x.data(), n, simd::Lanes::scalar);
  {
    INFO(simd::lanes_name(lanes));
    std::vector<T> out(x.size()), d(x.size(), T(0.5));
    nn::gelu_forward_impl<T>(out.data(), x.data(), n, lanes);
    nn::gelu_backward_impl<T>(d.data(), g.data(), x.data(), n, lanes);
    for (std::size_t i = 0; i < x.size(); ++i) {
      INFO("x = " << x[i]);
      const double y = static_cast<double>(scalar_out[i]), dy = static_cast<double>(scalar_d[i]);
      REQUIRE(std::abs(static_cast<double>(out[i]) - y) <= tol * (1 + std::abs(y)));
      REQUIRE(std::abs(static_cast<double>(d[i]) - dy) <= tol * (1 + std::abs(dy)));
    }
  }
  // The scalar path is the definition: 0.5 x (1 + erf(x / sqrt 2)).
  for (std::size_t i = 0; i < x.size(); ++i) {
    const double xd = static_cast<double>(x[i]);
    REQUIRE(static_cast<double>(scalar_out[i]) == Approx(0.5 * xd * (1 + std::erf(xd / std::sqrt(2.0)))).epsilon(2e-6).margin(2e-6));
  }
}

// The float path `lanes` as the scalar one on 1001 inputs, and on infinities and NaN: gelu(+inf) = +inf, gelu(-inf)
// and gelu(NaN) are NaN.
void check_gelu_float(simd::Lanes lanes) {
  check_gelu_paths<float>(4 * 0x1p-23, lanes);  // measured: 1.2 (forward) and 1.7 (backward) float eps on 2^22 inputs in [-9, 9]
  float special[3] = {INFINITY, -INFINITY, NAN};
  std::vector<float> in(37, 0.25f), out(37);
  for (int k = 0; k < 3; ++k) in[5 + 7 * k] = special[k];
  nn::gelu_forward_impl<float>(out.data(), in.data(), 37, lanes);
  CHECK(out[5] == INFINITY);
  CHECK(std::isnan(out[12]));
  CHECK(std::isnan(out[19]));
}

}  // namespace

TEST_CASE("GELU: every SIMD path agrees with the scalar path (float and double)", "[nn][activations][simd]") {
  // The build's compiled lanes; the run-time dispatched float ones are the cases below, one per level (double has
  // none).
  check_gelu_float(simd::Lanes::compiled);
  check_gelu_paths<double>(1e-13, simd::Lanes::compiled);
}

FLEXSPLAT_DISPATCH_TEST_CASES("GELU: the dispatched float lanes agree with the scalar path", "[nn][activations][simd]",
                              check_gelu_float)

TEST_CASE("gelu and silu backward pass the float64 gradient check", "[nn][activations]") {
  auto x = random_vector(40, 7, 2.0);
  std::vector<double> y(x.size()), dx(x.size());
  auto gelu = testing::check_gradients(
      {{"x", x, dx}}, y.size(), [&](std::span<double> o) { nn::gelu_forward(o.data(), x.data(), 40); },
      [&](std::span<const double> d) { nn::gelu_backward(dx.data(), d.data(), x.data(), 40); });
  INFO(gelu.summary());
  CHECK(gelu.ok());
  auto silu = testing::check_gradients(
      {{"x", x, dx}}, y.size(), [&](std::span<double> o) { nn::silu_forward(o.data(), x.data(), 40); },
      [&](std::span<const double> d) { nn::silu_backward(dx.data(), d.data(), x.data(), 40); });
  INFO(silu.summary());
  CHECK(silu.ok());
  double big[2] = {-800.0, 800.0}, out[2];
  nn::silu_forward(out, big, 2);
  CHECK(out[0] == 0.0);
  CHECK(out[1] == 800.0);
  nn::gelu_forward(out, big, 2);
  CHECK(out[0] == 0.0);
  CHECK(out[1] == 800.0);
}

TEST_CASE("sigmoid is finite and in [0, 1] at the extremes, logit inverts it and clamps", "[nn][activations]") {
  for (double x : {-1e4, -745.0, -50.0, 0.0, 50.0, 745.0, 1e4}) {
    const double s = nn::sigmoid(x);
    CHECK((std::isfinite(s) && s >= 0.0 && s <= 1.0));
    CHECK(std::isfinite(nn::sigmoid_vjp(x, 1.0)));
  }
  for (float x : {-1e4f, -100.0f, 100.0f, 1e4f}) CHECK(std::isfinite(nn::sigmoid(x)));
  CHECK(nn::sigmoid(-2.0) == Approx(1.0 / (1.0 + std::exp(2.0))));
  CHECK(nn::sigmoid(0.0) == 0.5);
  for (double x : {-30.0, -3.0, -0.25, 0.0, 0.5, 4.0, 12.0}) CHECK(nn::logit(nn::sigmoid(x), 40.0) == Approx(x).margin(1e-9));
  CHECK(nn::logit(0.0, 40.0) == -40.0);
  CHECK(nn::logit(-1.0, 40.0) == -40.0);
  CHECK(nn::logit(1.0, 40.0) == 40.0);
  CHECK(nn::logit(1e-30, 40.0) == -40.0);
  CHECK(std::isnan(nn::logit(std::nan(""), 40.0)));
  auto x = random_vector(8, 11, 3.0);
  std::vector<double> dx(x.size());
  auto result = testing::check_gradients(
      {{"x", x, dx}}, x.size(), [&](std::span<double> o) { for (std::size_t i = 0; i < x.size(); ++i) o[i] = nn::sigmoid(x[i]); },
      [&](std::span<const double> d) { for (std::size_t i = 0; i < x.size(); ++i) dx[i] += nn::sigmoid_vjp(x[i], d[i]); });
  INFO(result.summary());
  CHECK(result.ok());
}
