#include <catch2/catch.hpp>

#include <cmath>

#include "decoder_test_util.hpp"
#include "flexsplat/decoder/splat_head.hpp"
#include "flexsplat/nn/activations.hpp"
#include "flexsplat/testing/gradcheck.hpp"

using namespace flexsplat;

TEST_CASE("quaternion product composes rotations and passes the gradient check", "[decoder][splat_head]") {
  // 90 degrees about z, then 90 degrees about x: q = qx * qz.
  const double s = std::sqrt(0.5);
  const double qz[4] = {s, 0, 0, s}, qx[4] = {s, s, 0, 0};
  double q[4];
  decoder::quat_multiply(qx, qz, q);
  CHECK(q[0] == Approx(0.5));
  CHECK(q[1] == Approx(0.5));
  CHECK(q[2] == Approx(-0.5));
  CHECK(q[3] == Approx(0.5));
  auto p = random_normal(4, 1), r = random_normal(4, 2);
  std::vector<double> dp(4), dr(4);
  auto result = testing::check_gradients(
      {{"p", p, dp}, {"q", r, dr}}, 4, [&](std::span<double> o) { decoder::quat_multiply(p.data(), r.data(), o.data()); },
      [&](std::span<const double> g) { decoder::quat_multiply_vjp(p.data(), r.data(), g.data(), dp.data(), dr.data()); });
  INFO(result.summary());
  CHECK(result.ok());
}

TEST_CASE("quaternion normalisation passes the gradient check and survives zero", "[decoder][splat_head]") {
  auto q = random_normal(4, 3);
  std::vector<double> dq(4);
  auto result = testing::check_gradients(
      {{"q", q, dq}}, 4, [&](std::span<double> o) { decoder::quat_normalize(q.data(), o.data()); },
      [&](std::span<const double> g) { decoder::quat_normalize_vjp(q.data(), g.data(), dq.data()); });
  INFO(result.summary());
  CHECK(result.ok());
  const double zero[4] = {0, 0, 0, 0}, g[4] = {1, 2, 3, 4};
  double out[4], dz[4] = {0, 0, 0, 0};
  decoder::quat_normalize(zero, out);
  decoder::quat_normalize_vjp(zero, g, dz);
  for (int i = 0; i < 4; ++i) {
    CHECK(std::isfinite(out[i]));
    CHECK(std::isfinite(dz[i]));
  }
}

TEST_CASE("activations are finite at the extremes and pass the gradient check", "[decoder][splat_head]") {
  for (double x : {-1e4, -50.0, 0.0, 50.0, 1e4}) {
    CHECK(std::isfinite(decoder::scale_activation(x)));
    const double o = nn::sigmoid(x);
    CHECK((std::isfinite(o) && o >= 0.0 && o <= 1.0));
    CHECK(std::isfinite(nn::sigmoid_vjp(x, 1.0)));
  }
  CHECK(nn::sigmoid(-2.0) == Approx(1.0 / (1.0 + std::exp(2.0))));
  auto x = random_normal(6, 4, 2.0);
  std::vector<double> dx(6);
  auto result = testing::check_gradients(
      {{"x", x, dx}}, 6,
      [&](std::span<double> o) {
        for (int i = 0; i < 3; ++i) o[i] = decoder::scale_activation(x[i]);
        for (int i = 3; i < 6; ++i) o[i] = nn::sigmoid(x[i]);
      },
      [&](std::span<const double> g) {
        for (int i = 0; i < 3; ++i) dx[i] += decoder::scale_activation_vjp(x[i], g[i]);
        for (int i = 3; i < 6; ++i) dx[i] += nn::sigmoid_vjp(x[i], g[i]);
      });
  INFO(result.summary());
  CHECK(result.ok());
}

TEST_CASE("composition adds in parameter space, multiplies rotations, passes the gradient check", "[decoder][splat_head]") {
  const index_t n = 5;
  auto state = random_normal(n * 24, 5), delta = random_normal(n * 24, 6);
  std::vector<double> out(n * 24);
  decoder::compose_forward(out.data(), state.data(), delta.data(), n);
  CHECK(out[decoder::splat_opacity] == Approx(state[decoder::splat_opacity] + delta[decoder::splat_opacity]));
  double qn[4], dn[4], expect[4];
  decoder::quat_normalize(&state[decoder::splat_quat], qn);
  decoder::quat_normalize(&delta[decoder::splat_quat], dn);
  decoder::quat_multiply(dn, qn, expect);
  for (int i = 0; i < 4; ++i) CHECK(out[decoder::splat_quat + i] == Approx(expect[i]));
  std::vector<double> ds(state.size()), dd(delta.size());
  auto result = testing::check_gradients(
      {{"state", state, ds}, {"delta", delta, dd}}, out.size(),
      [&](std::span<double> o) { decoder::compose_forward(o.data(), state.data(), delta.data(), n); },
      [&](std::span<const double> g) { decoder::compose_backward(ds.data(), dd.data(), g.data(), state.data(), delta.data(), n); },
      {1e-6, 1e-7, 1e-5, 200});
  INFO(result.summary());
  CHECK(result.ok());
}

TEST_CASE("splat head adds the fixed Splatter Image biases and passes the gradient check", "[decoder][splat_head]") {
  const index_t n = 3, dim = 7;
  auto x = random_normal(n * dim, 7), w = random_normal(24 * dim, 8, 0.3), b = random_normal(24, 9);
  std::vector<double> zero_w(24 * dim, 0.0), zero_b(24, 0.0), out(n * 24);
  decoder::splat_head_forward(out.data(), x.data(), zero_w.data(), zero_b.data(), n, dim, true);
  CHECK(out[decoder::splat_opacity] == Approx(-2.0));
  CHECK(out[decoder::splat_log_scale] == Approx(std::log(0.02)));
  CHECK(out[decoder::splat_quat] == Approx(1.0));
  CHECK(out[decoder::splat_depth] == 0.0);
  std::vector<double> dx(x.size()), dw(w.size()), db(b.size());
  auto result = testing::check_gradients(
      {{"x", x, dx}, {"weight", w, dw}, {"bias", b, db}}, out.size(),
      [&](std::span<double> o) { decoder::splat_head_forward(o.data(), x.data(), w.data(), b.data(), n, dim, false); },
      [&](std::span<const double> g) {
        decoder::splat_head_backward(dx.data(), dw.data(), db.data(), g.data(), x.data(), w.data(), n, dim);
      });
  INFO(result.summary());
  CHECK(result.ok());
}
