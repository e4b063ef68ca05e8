#pragma once
// Cameras at the boundary between VGGT and the rest of the library. VGGT puts pixel u at the integer coordinate u,
// the decoder and rasterizer at u + 0.5 (docs/conventions.md), so the predicted principal point moves by half a
// pixel: the ray through depth sample u stays the same. Both directions have their adjoints.
#include <cmath>
#include <cstdint>
#include <numbers>
#include <random>

#include <Eigen/Geometry>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {
namespace model {

// K [V, 3, 3] in VGGT's integer-pixel convention -> the library's pixel-centre convention.
template <class T>
void intrinsics_from_vggt(T* K, const T* K_vggt, index_t views) {
  for (index_t v = 0; v < views; ++v) {
    for (int i = 0; i < 9; ++i) K[9 * v + i] = K_vggt[9 * v + i];
    K[9 * v + 2] += T(0.5);
    K[9 * v + 5] += T(0.5);
  }
}

// The inverse: the library's pixel-centre convention -> VGGT's integer-pixel one (ground truth for VGGT's heads).
template <class T>
void intrinsics_to_vggt(T* K_vggt, const T* K, index_t views) {
  for (index_t v = 0; v < views; ++v) {
    for (int i = 0; i < 9; ++i) K_vggt[9 * v + i] = K[9 * v + i];
    K_vggt[9 * v + 2] -= T(0.5);
    K_vggt[9 * v + 5] -= T(0.5);
  }
}

// The shift is constant: the gradient passes through unchanged (added into dK_vggt).
template <class T>
void intrinsics_from_vggt_backward(T* dK_vggt, const T* dK, index_t views) {
  for (index_t i = 0; i < 9 * views; ++i) dK_vggt[i] += dK[i];
}

// Rotation noise of `deg` degrees on each camera of w2c [V, 3, 4]: a rotation by exactly deg about an axis drawn
// uniformly on the sphere (a normalised standard-normal 3-vector, std::mt19937_64 seeded with `seed`, views in
// order), applied about the camera's own centre: [R | t] -> [Rn R | Rn t].
template <class T>
void rotation_noise(T* w2c, index_t views, double deg, std::uint64_t seed) {
  require(std::isfinite(deg) && deg >= 0 && deg <= 180, "rotation noise: ", deg, " degrees is not in [0, 180]");
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> normal;
  for (index_t v = 0; v < views; ++v) {
    Eigen::Vector3d axis;
    do axis = Eigen::Vector3d(normal(rng), normal(rng), normal(rng));
    while (axis.norm() < 1e-9);
    const Eigen::Matrix3d Rn = Eigen::AngleAxisd(deg * std::numbers::pi / 180.0, axis.normalized()).toRotationMatrix();
    Eigen::Matrix<double, 3, 4> m;
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 4; ++c) m(r, c) = static_cast<double>(w2c[12 * v + 4 * r + c]);
    m = (Rn * m).eval();
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 4; ++c) w2c[12 * v + 4 * r + c] = static_cast<T>(m(r, c));
  }
}

}  // namespace model
}  // namespace v0
}  // namespace flexsplat
