#pragma once
// VGGT's absT_quaR_FoV camera encoding: [t_x, t_y, t_z, q_x, q_y, q_z, q_w, fov_h, fov_w] per frame <->
// world-to-camera extrinsics [3, 4] (OpenCV axes) and pinhole intrinsics [3, 3] with the principal point at the image
// centre. Rotation conventions follow vggt/utils/rotation.py (scalar-last quaternions, not required to be unit).
#include <algorithm>
#include <cmath>
#include <numbers>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {
namespace geometry {

inline constexpr index_t pose_encoding_dim = 9;

// What decoding does with an encoding that has no finite camera: FoV outside (0, pi) or an all-zero quaternion.
// NaN or infinite entries are an error under every policy.
enum class DegeneratePosePolicy {
  error,  // throw flexsplat::Error naming the frame and the value
  clamp,  // FoV clamped into [pose_min_fov, pi - pose_min_fov]; an all-zero quaternion becomes the identity rotation
};

// Smallest FoV (radians) the clamp policy keeps: focal length stays below ~1000x the image size.
inline constexpr double pose_min_fov = 1e-3;

struct PoseDecodeOptions {
  DegeneratePosePolicy policy = DegeneratePosePolicy::error;
};

// q = (x, y, z, w) -> row-major R; scale-invariant (uses 2 / |q|^2 as VGGT does). Returns false for |q| = 0.
template <class T>
bool quat_to_mat(const T* q, T* R) {
  const double i = q[0], j = q[1], k = q[2], r = q[3];
  const double norm_sq = i * i + j * j + k * k + r * r;
  if (!(norm_sq > 0.0)) return false;
  const double s = 2.0 / norm_sq;
  R[0] = static_cast<T>(1 - s * (j * j + k * k));
  R[1] = static_cast<T>(s * (i * j - k * r));
  R[2] = static_cast<T>(s * (i * k + j * r));
  R[3] = static_cast<T>(s * (i * j + k * r));
  R[4] = static_cast<T>(1 - s * (i * i + k * k));
  R[5] = static_cast<T>(s * (j * k - i * r));
  R[6] = static_cast<T>(s * (i * k - j * r));
  R[7] = static_cast<T>(s * (j * k + i * r));
  R[8] = static_cast<T>(1 - s * (i * i + j * j));
  return true;
}

// Row-major rotation R -> q = (x, y, z, w) with w >= 0: the best-conditioned of the four candidate formulas
// (largest |component|), as PyTorch3D / VGGT's mat_to_quat.
template <class T>
void mat_to_quat(const T* R, T* q) {
  const double m00 = R[0], m01 = R[1], m02 = R[2], m10 = R[3], m11 = R[4], m12 = R[5], m20 = R[6], m21 = R[7],
               m22 = R[8];
  const double squared[4] = {1.0 + m00 + m11 + m22, 1.0 + m00 - m11 - m22, 1.0 - m00 + m11 - m22,
                             1.0 - m00 - m11 + m22};
  double abs_part[4];
  for (int c = 0; c < 4; ++c) abs_part[c] = squared[c] > 0.0 ? std::sqrt(squared[c]) : 0.0;
  const int best = static_cast<int>(std::max_element(abs_part, abs_part + 4) - abs_part);
  // Candidate rows give (r, i, j, k) times 2 * abs_part[best].
  double rijk[4];
  switch (best) {
    case 0: rijk[0] = 0; rijk[1] = m21 - m12; rijk[2] = m02 - m20; rijk[3] = m10 - m01; break;
    case 1: rijk[0] = m21 - m12; rijk[1] = 0; rijk[2] = m10 + m01; rijk[3] = m02 + m20; break;
    case 2: rijk[0] = m02 - m20; rijk[1] = m10 + m01; rijk[2] = 0; rijk[3] = m12 + m21; break;
    default: rijk[0] = m10 - m01; rijk[1] = m20 + m02; rijk[2] = m21 + m12; rijk[3] = 0; break;
  }
  // The diagonal entry is the clamped square root squared, as in PyTorch3D (differs from squared[] only if <= 0).
  rijk[best] = abs_part[best] * abs_part[best];
  const double denom = 2.0 * std::max(abs_part[best], 0.1);
  const double sign = rijk[0] / denom < 0.0 ? -1.0 : 1.0;
  q[0] = static_cast<T>(sign * rijk[1] / denom);
  q[1] = static_cast<T>(sign * rijk[2] / denom);
  q[2] = static_cast<T>(sign * rijk[3] / denom);
  q[3] = static_cast<T>(sign * rijk[0] / denom);
}

// pose_enc [n, 9] -> extrinsics [n, 3, 4] (world-to-camera) and intrinsics [n, 3, 3] (may be null) for images of
// image_h x image_w pixels: fy = (H/2) / tan(fov_h/2), fx = (W/2) / tan(fov_w/2), principal point (W/2, H/2).
template <class T>
void pose_encoding_to_extri_intri(T* extrinsics, T* intrinsics, const T* pose_enc, index_t n, index_t image_h,
                                  index_t image_w, PoseDecodeOptions options = {}) {
  require(n >= 0, "pose_encoding_to_extri_intri: negative frame count ", n);
  require(intrinsics == nullptr || (image_h > 0 && image_w > 0), "pose_encoding_to_extri_intri: image size ", image_h,
          "x", image_w, " must be positive");
  const double pi = std::numbers::pi;
  for (index_t f = 0; f < n; ++f) {
    const T* e = pose_enc + f * pose_encoding_dim;
    for (index_t c = 0; c < pose_encoding_dim; ++c)
      require(std::isfinite(static_cast<double>(e[c])), "pose encoding of frame ", f, ": entry ", c, " is ",
              static_cast<double>(e[c]), " (not finite)");
    T R[9];
    if (!quat_to_mat(e + 3, R)) {
      require(options.policy == DegeneratePosePolicy::clamp, "pose encoding of frame ", f,
              ": quaternion (x, y, z, w) = (0, 0, 0, 0) has no rotation");
      std::fill(R, R + 9, T(0));
      R[0] = R[4] = R[8] = T(1);
    }
    T* E = extrinsics + f * 12;
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) E[r * 4 + c] = R[r * 3 + c];
      E[r * 4 + 3] = e[r];
    }
    if (!intrinsics) continue;
    double fov[2] = {static_cast<double>(e[7]), static_cast<double>(e[8])};  // (fov_h, fov_w)
    for (int a = 0; a < 2; ++a) {
      if (fov[a] > 0.0 && fov[a] < pi) continue;
      require(options.policy == DegeneratePosePolicy::clamp, "pose encoding of frame ", f, ": ",
              a == 0 ? "fov_h" : "fov_w", " = ", fov[a], " rad is outside (0, pi)");
      fov[a] = std::clamp(fov[a], pose_min_fov, pi - pose_min_fov);
    }
    const double fy = 0.5 * static_cast<double>(image_h) / std::tan(0.5 * fov[0]);
    const double fx = 0.5 * static_cast<double>(image_w) / std::tan(0.5 * fov[1]);
    T* K = intrinsics + f * 9;
    std::fill(K, K + 9, T(0));
    K[0] = static_cast<T>(fx);
    K[4] = static_cast<T>(fy);
    K[2] = static_cast<T>(0.5 * static_cast<double>(image_w));
    K[5] = static_cast<T>(0.5 * static_cast<double>(image_h));
    K[8] = T(1);
  }
}

// Adds into d_q (x, y, z, w) the gradient of quat_to_mat's R given d_R (row-major); nothing for |q| = 0.
// R = C + s P(q) with s = 2 / |q|^2, so dR/dq_a = s dP/dq_a - s^2 q_a P.
template <class T>
void quat_to_mat_backward(T* d_q, const T* d_R, const T* q) {
  const double i = q[0], j = q[1], k = q[2], r = q[3];
  const double norm_sq = i * i + j * j + k * k + r * r;
  if (!(norm_sq > 0.0)) return;
  const double s = 2.0 / norm_sq;
  double g[9];
  for (int m = 0; m < 9; ++m) g[m] = static_cast<double>(d_R[m]);
  const double P[9] = {-(j * j + k * k), i * j - k * r, i * k + j * r, i * j + k * r, -(i * i + k * k),
                       j * k - i * r,    i * k - j * r, j * k + i * r, -(i * i + j * j)};
  double gp = 0.0;
  for (int m = 0; m < 9; ++m) gp += g[m] * P[m];
  const double di = g[1] * j + g[2] * k + g[3] * j - 2 * g[4] * i - g[5] * r + g[6] * k + g[7] * r - 2 * g[8] * i;
  const double dj = -2 * g[0] * j + g[1] * i + g[2] * r + g[3] * i + g[5] * k - g[6] * r + g[7] * k - 2 * g[8] * j;
  const double dk = -2 * g[0] * k - g[1] * r + g[2] * i + g[3] * r - 2 * g[4] * k + g[5] * j + g[6] * i + g[7] * j;
  const double dr = -g[1] * k + g[2] * j + g[3] * k - g[5] * i - g[6] * j + g[7] * i;
  const double d[4] = {di, dj, dk, dr};
  for (int a = 0; a < 4; ++a) d_q[a] += static_cast<T>(s * d[a] - s * s * static_cast<double>(q[a]) * gp);
}

// Backward of pose_encoding_to_extri_intri: adds into d_pose_enc [n, 9] from d_extrinsics [n, 3, 4] and
// d_intrinsics [n, 3, 3] (either may be null). Entries the options' clamp replaced by a constant (a FoV outside
// (0, pi), an all-zero quaternion) get zero gradient, as a clamp's derivative is; under the error policy they throw
// as in the forward. The principal point is a constant of the image size: its gradient goes nowhere.
template <class T>
void pose_encoding_to_extri_intri_backward(T* d_pose_enc, const T* d_extrinsics, const T* d_intrinsics,
                                           const T* pose_enc, index_t n, index_t image_h, index_t image_w,
                                           PoseDecodeOptions options = {}) {
  require(n >= 0, "pose_encoding_to_extri_intri_backward: negative frame count ", n);
  require(d_intrinsics == nullptr || (image_h > 0 && image_w > 0), "pose_encoding_to_extri_intri_backward: image size ",
          image_h, "x", image_w, " must be positive");
  const double pi = std::numbers::pi;
  for (index_t f = 0; f < n; ++f) {
    const T* e = pose_enc + f * pose_encoding_dim;
    T* de = d_pose_enc + f * pose_encoding_dim;
    for (index_t c = 0; c < pose_encoding_dim; ++c)
      require(std::isfinite(static_cast<double>(e[c])), "pose encoding of frame ", f, ": entry ", c, " is ",
              static_cast<double>(e[c]), " (not finite)");
    if (d_extrinsics) {
      const T* dE = d_extrinsics + f * 12;
      T dR[9];
      for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 3; ++c) dR[r * 3 + c] = dE[r * 4 + c];
        de[r] += dE[r * 4 + 3];
      }
      const double q_sq = static_cast<double>(e[3]) * e[3] + static_cast<double>(e[4]) * e[4] +
                          static_cast<double>(e[5]) * e[5] + static_cast<double>(e[6]) * e[6];
      require(q_sq > 0.0 || options.policy == DegeneratePosePolicy::clamp, "pose encoding of frame ", f,
              ": quaternion (x, y, z, w) = (0, 0, 0, 0) has no rotation");
      quat_to_mat_backward(de + 3, dR, e + 3);
    }
    if (!d_intrinsics) continue;
    const T* dK = d_intrinsics + f * 9;
    const double size[2] = {static_cast<double>(image_h), static_cast<double>(image_w)};
    const double d_focal[2] = {static_cast<double>(dK[4]), static_cast<double>(dK[0])};  // (fy, fx)
    for (int a = 0; a < 2; ++a) {
      const double fov = static_cast<double>(e[7 + a]);
      if (!(fov > 0.0 && fov < pi)) {
        require(options.policy == DegeneratePosePolicy::clamp, "pose encoding of frame ", f, ": ",
                a == 0 ? "fov_h" : "fov_w", " = ", fov, " rad is outside (0, pi)");
        continue;
      }
      // focal = (size / 2) / tan(fov / 2): d focal / d fov = -(size / 4) / sin^2(fov / 2).
      const double sn = std::sin(0.5 * fov);
      de[7 + a] += static_cast<T>(-0.25 * size[a] / (sn * sn) * d_focal[a]);
    }
  }
}

// The inverse: extrinsics [n, 3, 4] + intrinsics [n, 3, 3] -> pose_enc [n, 9] with fov = 2 atan((size/2) / focal).
template <class T>
void extri_intri_to_pose_encoding(T* pose_enc, const T* extrinsics, const T* intrinsics, index_t n, index_t image_h,
                                  index_t image_w) {
  require(image_h > 0 && image_w > 0, "extri_intri_to_pose_encoding: image size ", image_h, "x", image_w,
          " must be positive");
  for (index_t f = 0; f < n; ++f) {
    const T* E = extrinsics + f * 12;
    const T* K = intrinsics + f * 9;
    const double fx = K[0], fy = K[4];
    require(std::isfinite(fx) && std::isfinite(fy) && fx > 0.0 && fy > 0.0, "intrinsics of frame ", f,
            ": focal lengths (", fx, ", ", fy, ") must be positive and finite");
    T R[9];
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) R[r * 3 + c] = E[r * 4 + c];
    T* e = pose_enc + f * pose_encoding_dim;
    for (int r = 0; r < 3; ++r) e[r] = E[r * 4 + 3];
    mat_to_quat(R, e + 3);
    e[7] = static_cast<T>(2.0 * std::atan(0.5 * static_cast<double>(image_h) / fy));
    e[8] = static_cast<T>(2.0 * std::atan(0.5 * static_cast<double>(image_w) / fx));
  }
}

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
