#include <catch2/catch.hpp>

#include <cmath>
#include <cstring>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "flexsplat/raster/sh.hpp"
#include "flexsplat/testing/gradcheck.hpp"

using namespace flexsplat;
using namespace flexsplat::raster;

TEST_CASE("sh: float64 gradient check of coefficients and direction for degrees 0-3", "[raster][sh]") {
  for (int degree = 0; degree <= 3; ++degree) {
    std::mt19937 rng(7 + degree);
    std::normal_distribution<double> normal;
    std::vector<double> coeffs(16 * 3), dir(3), d_coeffs(coeffs.size()), d_dir(3);
    for (auto& c : coeffs) c = normal(rng);
    for (auto& d : dir) d = 2 * normal(rng);
    auto forward = [&](std::span<double> out) { sh_forward(degree, 3, coeffs.data(), dir.data(), out.data()); };
    auto backward = [&](std::span<const double> d_out) {
      sh_backward(degree, 3, coeffs.data(), dir.data(), d_out.data(), d_coeffs.data(), d_dir.data());
    };
    const std::size_t used = std::size_t(sh_coefficients(degree) * 3);
    const std::string dir_zero = degree == 0 ? "degree 0 is constant over directions" : "";
    auto result = testing::check_gradients({{"coeffs", {coeffs.data(), used}, {d_coeffs.data(), used}},
                                            {"dir", dir, d_dir, dir_zero}},
                                           3, forward, backward);
    INFO("degree " << degree << ": " << result.summary());
    CHECK(result.ok());
  }
}

TEST_CASE("sh: bands above the requested degree are never read", "[raster][sh]") {
  std::vector<double> coeffs(16 * 3, std::numeric_limits<double>::quiet_NaN());
  for (int i = 0; i < 4 * 3; ++i) coeffs[i] = 0.1 * (i + 1);
  const double dir[3] = {0.3, -0.2, 0.9};
  double out[3], d_out[3] = {1, 1, 1}, d_dir[3] = {0, 0, 0};
  std::vector<double> d_coeffs(coeffs.size(), 0.0);
  sh_forward(1, 3, coeffs.data(), dir, out);
  sh_backward(1, 3, coeffs.data(), dir, d_out, d_coeffs.data(), d_dir);
  for (double v : out) CHECK(std::isfinite(v));
  for (double v : d_dir) CHECK(std::isfinite(v));
  for (int i = 12; i < 48; ++i) CHECK(d_coeffs[i] == 0.0);
}

TEST_CASE("sh: degree 0 is the constant band and a zero direction stays finite", "[raster][sh]") {
  const double coeffs[3] = {1.0, -2.0, 0.5};
  const double zero[3] = {0, 0, 0};
  double out[3];
  sh_forward(0, 3, coeffs, zero, out);
  CHECK(out[0] == Approx(sh_c0));
  CHECK(out[1] == Approx(-2 * sh_c0));
  std::vector<double> c3(48, 0.5);
  double o3[3], d_dir[3] = {0, 0, 0}, d_out[3] = {1, 1, 1};
  std::vector<double> dc(48, 0.0);
  sh_forward(3, 3, c3.data(), zero, o3);
  sh_backward(3, 3, c3.data(), zero, d_out, dc.data(), d_dir);
  for (double v : o3) CHECK(std::isfinite(v));
  for (double v : d_dir) CHECK(v == 0.0);
}

TEMPLATE_TEST_CASE("sh: batch lanes are bit-identical to sh_forward", "[raster][sh]", float, double) {
  using T = TestType;
  using V = simd::batch<T>;
  constexpr int L = int(V::size);
  std::mt19937 rng(29);
  std::normal_distribution<double> normal;
  for (int degree = 0; degree <= 3; ++degree)
    for (int trial = 0; trial < 200; ++trial) {
      alignas(64) T coeffs[48][L], dir[3][L], out[3][L];
      for (int l = 0; l < L; ++l) {
        for (int j = 0; j < 48; ++j) coeffs[j][l] = T(normal(rng));
        for (int i = 0; i < 3; ++i) dir[i][l] = T(l == 1 ? 0.0 : 3 * normal(rng));  // lane 1: zero direction
      }
      V cv[48], dv[3], ov[3];
      for (int j = 0; j < 48; ++j) cv[j] = simd::lane_load<V>(coeffs[j]);
      for (int i = 0; i < 3; ++i) dv[i] = simd::lane_load<V>(dir[i]);
      sh_forward_lanes<V>(degree, 3, cv, dv, ov);
      for (int c = 0; c < 3; ++c) simd::lane_store(out[c], ov[c]);
      for (int l = 0; l < L; ++l) {
        T cl[48], dl[3] = {dir[0][l], dir[1][l], dir[2][l]}, expect[3];
        for (int j = 0; j < 48; ++j) cl[j] = coeffs[j][l];
        sh_forward(degree, 3, cl, dl, expect);
        for (int c = 0; c < 3; ++c) {
          INFO("degree " << degree << " lane " << l << " channel " << c << ": " << expect[c] << " vs " << out[c][l]);
          CHECK(std::memcmp(&expect[c], &out[c][l], sizeof(T)) == 0);
        }
      }
    }
}

TEMPLATE_TEST_CASE("sh: backward batch lanes are bit-identical to sh_backward", "[raster][sh]", float, double) {
  using T = TestType;
  using V = simd::batch<T>;
  constexpr int L = int(V::size);
  std::mt19937 rng(37);
  std::normal_distribution<double> normal;
  for (int degree = 0; degree <= 3; ++degree)
    for (int trial = 0; trial < 200; ++trial) {
      // d_dir starts from junk: sh_backward adds into it (nothing for a zero direction).
      alignas(64) T coeffs[48][L], dir[3][L], d_out[3][L], d_dir[3][L], d_coeffs[48][L];
      for (int l = 0; l < L; ++l) {
        for (int j = 0; j < 48; ++j) coeffs[j][l] = T(normal(rng));
        for (int i = 0; i < 3; ++i) dir[i][l] = T(l == 1 ? 0.0 : 3 * normal(rng));  // lane 1: zero direction
        for (int c = 0; c < 3; ++c) d_out[c][l] = T(l == 2 ? 0.0 : normal(rng));   // lane 2: zero cotangent
        for (int i = 0; i < 3; ++i) d_dir[i][l] = T(normal(rng));
      }
      V cv[48], dv[3], gv[3], ddv[3], dcv[48];
      for (int j = 0; j < 48; ++j) cv[j] = simd::lane_load<V>(coeffs[j]);
      for (int i = 0; i < 3; ++i)
        dv[i] = simd::lane_load<V>(dir[i]), gv[i] = simd::lane_load<V>(d_out[i]), ddv[i] = simd::lane_load<V>(d_dir[i]);
      sh_backward_lanes<V>(degree, 3, cv, dv, gv, dcv, ddv);
      const int n = sh_coefficients(degree) * 3;
      for (int j = 0; j < n; ++j) simd::lane_store(d_coeffs[j], dcv[j]);
      alignas(64) T dd[3][L];
      for (int i = 0; i < 3; ++i) simd::lane_store(dd[i], ddv[i]);
      for (int l = 0; l < L; ++l) {
        T cl[48], dl[3] = {dir[0][l], dir[1][l], dir[2][l]}, gl[3] = {d_out[0][l], d_out[1][l], d_out[2][l]};
        T ddl[3] = {d_dir[0][l], d_dir[1][l], d_dir[2][l]}, dcl[48];
        for (int j = 0; j < 48; ++j) cl[j] = coeffs[j][l], dcl[j] = T(-0.0);
        sh_backward(degree, 3, cl, dl, gl, dcl, ddl);  // x + (-0) is x bit for bit: the products themselves
        for (int j = 0; j < n; ++j) {
          INFO("degree " << degree << " lane " << l << " coefficient " << j << ": " << dcl[j] << " vs " << d_coeffs[j][l]);
          CHECK(std::memcmp(&dcl[j], &d_coeffs[j][l], sizeof(T)) == 0);
        }
        for (int i = 0; i < 3; ++i) {
          INFO("degree " << degree << " lane " << l << " d_dir " << i << ": " << ddl[i] << " vs " << dd[i][l]);
          CHECK(std::memcmp(&ddl[i], &dd[i][l], sizeof(T)) == 0);
        }
      }
    }
}
