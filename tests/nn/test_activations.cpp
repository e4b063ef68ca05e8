#include <catch2/catch.hpp>

#include "flexsplat/nn/activations.hpp"
#include "flexsplat/testing/gradcheck.hpp"
#include "nn_test_util.hpp"

using namespace flexsplat;

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
