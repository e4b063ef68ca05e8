#include <catch2/catch.hpp>

#include <cmath>
#include <numbers>
#include <random>

#include "flexsplat/geometry/pose_encoding.hpp"
#include "heads_bundle.hpp"

using namespace flexsplat;
using namespace flexsplat::geometry;

TEST_CASE("pose encoding decodes the bundle's cameras", "[pose_encoding]") {
  const auto cases = heads_test::bundle_cases();
  REQUIRE(cases.size() >= 1);
  for (std::size_t k = 0; k < cases.size(); ++k) {
    const auto [S, H, W] = cases[k];
    const std::string p = "case" + std::to_string(k) + ".";
    const auto enc = heads_test::read<float>(p + "camera_head.pose_enc.3");
    std::vector<float> extr(S * 12), intr(S * 9);
    pose_encoding_to_extri_intri(extr.data(), intr.data(), enc.data(), S, H, W);
    heads_test::check_close(p + "extrinsics", extr, heads_test::read<float>(p + "extrinsics"));
    heads_test::check_close(p + "intrinsics", intr, heads_test::read<float>(p + "intrinsics"));
    // float64 decode of the same encodings agrees as well.
    const auto enc64 = heads_test::read<double>(p + "camera_head.pose_enc.3");
    std::vector<double> extr64(S * 12), intr64(S * 9);
    pose_encoding_to_extri_intri(extr64.data(), intr64.data(), enc64.data(), S, H, W);
    heads_test::check_close(p + "extrinsics (double)", extr64, heads_test::read<float>(p + "extrinsics"));
    heads_test::check_close(p + "intrinsics (double)", intr64, heads_test::read<float>(p + "intrinsics"));
  }
}

TEST_CASE("identity quaternion and 90 degree FoV give the textbook camera", "[pose_encoding]") {
  const double half_pi = std::numbers::pi / 2;
  const double enc[9] = {1, 2, 3, 0, 0, 0, 1, half_pi, half_pi};
  double E[12], K[9];
  pose_encoding_to_extri_intri(E, K, enc, 1, 40, 60);
  const double expected_E[12] = {1, 0, 0, 1, 0, 1, 0, 2, 0, 0, 1, 3};
  for (int i = 0; i < 12; ++i) CHECK(E[i] == Approx(expected_E[i]).margin(1e-15));
  CHECK(K[0] == Approx(30.0));  // (W/2) / tan(pi/4)
  CHECK(K[4] == Approx(20.0));
  CHECK(K[2] == 30.0);
  CHECK(K[5] == 20.0);
  CHECK(K[8] == 1.0);
  CHECK(K[1] == 0.0);
  CHECK(K[3] == 0.0);
}

TEST_CASE("quat_to_mat is scale invariant and orthonormal", "[pose_encoding]") {
  std::mt19937 rng(7);
  std::normal_distribution<double> normal;
  for (int trial = 0; trial < 200; ++trial) {
    double q[4];
    for (auto& c : q) c = normal(rng);
    double R[9], R_scaled[9];
    REQUIRE(quat_to_mat(q, R));
    double q_scaled[4];
    for (int c = 0; c < 4; ++c) q_scaled[c] = -3.7 * q[c];
    REQUIRE(quat_to_mat(q_scaled, R_scaled));
    for (int i = 0; i < 9; ++i) CHECK(R_scaled[i] == Approx(R[i]).margin(1e-12));
    for (int a = 0; a < 3; ++a)
      for (int b = 0; b < 3; ++b) {
        double dot = 0;
        for (int c = 0; c < 3; ++c) dot += R[a * 3 + c] * R[b * 3 + c];
        CHECK(dot == Approx(a == b ? 1.0 : 0.0).margin(1e-12));
      }
    const double det = R[0] * (R[4] * R[8] - R[5] * R[7]) - R[1] * (R[3] * R[8] - R[5] * R[6]) +
                       R[2] * (R[3] * R[7] - R[4] * R[6]);
    CHECK(det == Approx(1.0).margin(1e-12));
  }
}

TEST_CASE("encoding round trip: cameras -> encoding -> cameras", "[pose_encoding]") {
  std::mt19937 rng(11);
  std::normal_distribution<double> normal;
  std::uniform_real_distribution<double> fov(0.2, 2.8);
  const index_t n = 64, H = 37, W = 91;
  std::vector<double> enc(n * 9);
  for (index_t f = 0; f < n; ++f) {
    double* e = enc.data() + f * 9;
    for (int c = 0; c < 7; ++c) e[c] = normal(rng);
    // Include exact half-turns (w = 0) where the trace-based formula is worst conditioned.
    if (f % 8 == 0) e[6] = 0.0;
    e[7] = fov(rng);
    e[8] = fov(rng);
  }
  std::vector<double> E(n * 12), K(n * 9), enc_back(n * 9), E2(n * 12), K2(n * 9);
  pose_encoding_to_extri_intri(E.data(), K.data(), enc.data(), n, H, W);
  extri_intri_to_pose_encoding(enc_back.data(), E.data(), K.data(), n, H, W);
  pose_encoding_to_extri_intri(E2.data(), K2.data(), enc_back.data(), n, H, W);
  for (index_t f = 0; f < n; ++f) {
    const double* e = enc.data() + f * 9;
    const double* b = enc_back.data() + f * 9;
    for (int c = 0; c < 3; ++c) CHECK(b[c] == Approx(e[c]).margin(1e-12));
    CHECK(b[7] == Approx(e[7]).margin(1e-12));
    CHECK(b[8] == Approx(e[8]).margin(1e-12));
    // The decoded quaternion is unit with w >= 0 and equals +-q / |q|.
    const double norm = std::sqrt(e[3] * e[3] + e[4] * e[4] + e[5] * e[5] + e[6] * e[6]);
    CHECK(b[6] >= 0.0);
    double dot = 0;
    for (int c = 0; c < 4; ++c) dot += b[3 + c] * e[3 + c] / norm;
    CHECK(std::abs(dot) == Approx(1.0).margin(1e-10));
  }
  for (index_t i = 0; i < n * 12; ++i) CHECK(E2[i] == Approx(E[i]).margin(1e-10));
  for (index_t i = 0; i < n * 9; ++i) CHECK(K2[i] == Approx(K[i]).epsilon(1e-10));
}

TEST_CASE("degenerate FoV is an error by default and clamped on request", "[pose_encoding][stability]") {
  const double pi = std::numbers::pi;
  for (double bad : {0.0, -0.5, pi, 4.0, -1e-30}) {
    for (int axis : {7, 8}) {
      float enc[9] = {0, 0, 0, 0, 0, 0, 1, 1.0f, 1.0f};
      enc[axis] = static_cast<float>(bad);
      float E[12], K[9];
      CHECK_THROWS_WITH(pose_encoding_to_extri_intri(E, K, enc, 1, 20, 30),
                        Catch::Contains(axis == 7 ? "fov_h" : "fov_w") && Catch::Contains("outside (0, pi)"));
      pose_encoding_to_extri_intri(E, K, enc, 1, 20, 30, {DegeneratePosePolicy::clamp});
      for (float k : K) CHECK(std::isfinite(k));
      const double size = axis == 7 ? 20.0 : 30.0;
      const double focal = axis == 7 ? K[4] : K[0];
      CHECK(focal > 0.0);
      if (bad <= 0.0) CHECK(focal == Approx(0.5 * size / std::tan(0.5 * pose_min_fov)).epsilon(1e-6));
      else CHECK(focal == Approx(0.5 * size / std::tan(0.5 * (pi - pose_min_fov))).epsilon(1e-3));
    }
  }
  // Extrinsics alone never look at the FoV.
  const float enc[9] = {0, 0, 0, 0, 0, 0, 1, 0.0f, -1.0f};
  float E[12];
  pose_encoding_to_extri_intri<float>(E, nullptr, enc, 1, 20, 30);
  CHECK(E[0] == 1.0f);
}

TEST_CASE("zero quaternion is an error by default and the identity when clamping", "[pose_encoding][stability]") {
  const double enc[9] = {0.5, 0, 0, 0, 0, 0, 0, 1.0, 1.0};
  double E[12], K[9];
  CHECK_THROWS_WITH(pose_encoding_to_extri_intri(E, K, enc, 1, 20, 30),
                    Catch::Contains("frame 0") && Catch::Contains("quaternion"));
  pose_encoding_to_extri_intri(E, K, enc, 1, 20, 30, {DegeneratePosePolicy::clamp});
  const double expected[12] = {1, 0, 0, 0.5, 0, 1, 0, 0, 0, 0, 1, 0};
  for (int i = 0; i < 12; ++i) CHECK(E[i] == expected[i]);
  // A tiny but non-zero quaternion still defines a rotation exactly (float squares cannot underflow in double).
  const float tiny[9] = {0, 0, 0, 0, 0, 1e-30f, 1e-30f, 1.0f, 1.0f};
  float Ef[12], Kf[9];
  pose_encoding_to_extri_intri(Ef, Kf, tiny, 1, 20, 30);
  CHECK(Ef[0] == Approx(0.0f).margin(1e-6));  // 90 degrees about z
  CHECK(Ef[1] == Approx(-1.0f));
}

TEST_CASE("non-finite encodings are an error under every policy", "[pose_encoding][stability]") {
  for (auto policy : {DegeneratePosePolicy::error, DegeneratePosePolicy::clamp}) {
    for (int c = 0; c < 9; ++c) {
      for (float bad : {NAN, INFINITY}) {
        float enc[2 * 9] = {0, 0, 0, 0, 0, 0, 1, 1, 1, 0, 0, 0, 0, 0, 0, 1, 1, 1};
        enc[9 + c] = bad;
        float E[24], K[18];
        CHECK_THROWS_WITH(pose_encoding_to_extri_intri(E, K, enc, 2, 20, 30, {policy}),
                          Catch::Contains("frame 1") && Catch::Contains("not finite"));
      }
    }
  }
  double E[12], K[9];
  const double enc[9] = {0, 0, 0, 0, 0, 0, 1, 1, 1};
  CHECK_THROWS_WITH(pose_encoding_to_extri_intri(E, K, enc, 1, 0, 30), Catch::Contains("image size"));
}
