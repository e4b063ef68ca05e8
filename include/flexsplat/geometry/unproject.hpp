#pragma once
// Depth maps to world points as VGGT's unproject_depth_map_to_point_map: pixel (u, v) at integer coordinates,
// camera point ((u - cx) d / fx, (v - cy) d / fy, d), world point R^T (p - t) for world-to-camera [R | t].
#include <cmath>
#include <vector>

#include "flexsplat/core/camera.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/core/parallel.hpp"

namespace flexsplat {
inline namespace v0 {
namespace geometry {

// world_points [frames, H, W, 3] from depth [frames, H, W], extrinsics [frames, 3, 4], intrinsics [frames, 3, 3].
template <class T>
void unproject_depth_forward(T* world_points, const T* depth, const T* extrinsics, const T* intrinsics, index_t frames,
                             index_t height, index_t width) {
  require(frames >= 0 && height >= 0 && width >= 0, "unproject_depth: negative size ", frames, "x", height, "x", width);
  for (index_t f = 0; f < frames; ++f) {
    const T* K = intrinsics + f * 9;
    const double fx = K[0], fy = K[4], cx = K[2], cy = K[5];
    require(std::isfinite(fx) && std::isfinite(fy) && fx != 0.0 && fy != 0.0, "unproject_depth: frame ", f,
            " has focal lengths (", fx, ", ", fy, "); they must be finite and non-zero");
    require(K[1] == T(0) && K[3] == T(0), "unproject_depth: frame ", f, " intrinsics have skew (K[0,1] = ",
            static_cast<double>(K[1]), ", K[1,0] = ", static_cast<double>(K[3]), "); only zero skew is supported");
    require(std::isfinite(cx) && std::isfinite(cy), "unproject_depth: frame ", f, " principal point (", cx, ", ", cy,
            ") is not finite");
    const T* E = extrinsics + f * 12;
    for (int i = 0; i < 12; ++i)
      require(std::isfinite(static_cast<double>(E[i])), "unproject_depth: frame ", f, " extrinsics entry ", i, " is ",
              static_cast<double>(E[i]));
  }
  parallel_for(frames * height, [&](index_t r0, index_t r1, int) {
    for (index_t row = r0; row < r1; ++row) {
      const index_t f = row / height, v = row % height;
      const T* K = intrinsics + f * 9;
      const T* E = extrinsics + f * 12;
      const double inv_fx = 1.0 / static_cast<double>(K[0]), inv_fy = 1.0 / static_cast<double>(K[4]);
      const double cx = K[2], cy = K[5];
      double R[9], t[3];
      for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 3; ++c) R[r * 3 + c] = E[r * 4 + c];
        t[r] = E[r * 4 + 3];
      }
      const double y_unit = (static_cast<double>(v) - cy) * inv_fy;
      const T* d_row = depth + row * width;
      T* out = world_points + row * width * 3;
      for (index_t u = 0; u < width; ++u) {
        const double d = d_row[u];
        const double cam[3] = {(static_cast<double>(u) - cx) * inv_fx * d - t[0], y_unit * d - t[1], d - t[2]};
        for (int c = 0; c < 3; ++c)
          out[u * 3 + c] = static_cast<T>(R[0 * 3 + c] * cam[0] + R[1 * 3 + c] * cam[1] + R[2 * 3 + c] * cam[2]);
      }
    }
  });
}

// View f's pixels in its own camera frame ([H * W, 3]): its depth unprojected with identity extrinsics, in double.
template <class T>
std::vector<double> camera_frame_points(const T* depth, const T* intrinsics, index_t f, index_t height, index_t width) {
  const index_t px = height * width;
  const std::vector<double> d(depth + f * px, depth + (f + 1) * px), K(intrinsics + 9 * f, intrinsics + 9 * (f + 1));
  std::vector<double> points(static_cast<std::size_t>(3 * px));
  unproject_depth_forward<double>(points.data(), d.data(), identity_w2c, K.data(), 1, height, width);
  return points;
}

// Backward of unproject_depth_forward: adds into d_depth [frames, H, W], d_extrinsics [frames, 3, 4] and
// d_intrinsics [frames, 3, 3] (only fx, fy, cx, cy: K[0], K[4], K[2], K[5]); each may be null. Per-row partial sums of
// the camera gradients are reduced in row order, so the result does not depend on the thread count.
template <class T>
void unproject_depth_backward(T* d_depth, T* d_extrinsics, T* d_intrinsics, const T* d_world_points, const T* depth,
                              const T* extrinsics, const T* intrinsics, index_t frames, index_t height, index_t width) {
  require(frames >= 0 && height >= 0 && width >= 0, "unproject_depth_backward: negative size ", frames, "x", height,
          "x", width);
  for (index_t f = 0; f < frames; ++f) {
    const T* K = intrinsics + f * 9;
    require(std::isfinite(static_cast<double>(K[0])) && std::isfinite(static_cast<double>(K[4])) && K[0] != T(0) &&
                K[4] != T(0),
            "unproject_depth_backward: frame ", f, " has focal lengths (", static_cast<double>(K[0]), ", ",
            static_cast<double>(K[4]), "); they must be finite and non-zero");
  }
  const bool cameras = d_extrinsics || d_intrinsics;
  constexpr int per_row = 16;  // 12 extrinsic entries, then fx, fy, cx, cy
  std::vector<double> partial(cameras ? static_cast<std::size_t>(frames * height * per_row) : 0, 0.0);
  parallel_for(frames * height, [&](index_t r0, index_t r1, int) {
    for (index_t row = r0; row < r1; ++row) {
      const index_t f = row / height, v = row % height;
      const T* K = intrinsics + f * 9;
      const T* E = extrinsics + f * 12;
      const double fx = K[0], fy = K[4], cx = K[2], cy = K[5];
      double R[9], t[3];
      for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 3; ++c) R[r * 3 + c] = E[r * 4 + c];
        t[r] = E[r * 4 + 3];
      }
      const double y_unit = (static_cast<double>(v) - cy) / fy;
      double* acc = cameras ? partial.data() + row * per_row : nullptr;
      for (index_t u = 0; u < width; ++u) {
        const double d = depth[row * width + u];
        const T* dw = d_world_points + (row * width + u) * 3;
        const double x_unit = (static_cast<double>(u) - cx) / fx;
        // world_c = sum_r R[r][c] (p_r - t_r): d p_r = sum_c R[r][c] d world_c.
        double dp[3];
        for (int r = 0; r < 3; ++r) dp[r] = R[r * 3 + 0] * dw[0] + R[r * 3 + 1] * dw[1] + R[r * 3 + 2] * dw[2];
        if (d_depth) d_depth[row * width + u] += static_cast<T>(dp[0] * x_unit + dp[1] * y_unit + dp[2]);
        if (!acc) continue;
        const double p[3] = {x_unit * d, y_unit * d, d};
        for (int r = 0; r < 3; ++r) {
          for (int c = 0; c < 3; ++c) acc[r * 4 + c] += static_cast<double>(dw[c]) * (p[r] - t[r]);
          acc[r * 4 + 3] -= dp[r];
        }
        acc[12] -= dp[0] * p[0] / fx;  // d p0 / d fx = -(u - cx) d / fx^2
        acc[13] -= dp[1] * p[1] / fy;
        acc[14] -= dp[0] * d / fx;
        acc[15] -= dp[1] * d / fy;
      }
    }
  });
  if (!cameras) return;
  for (index_t f = 0; f < frames; ++f) {
    double sum[per_row] = {};
    for (index_t v = 0; v < height; ++v)
      for (int i = 0; i < per_row; ++i) sum[i] += partial[static_cast<std::size_t>((f * height + v) * per_row + i)];
    if (d_extrinsics)
      for (int i = 0; i < 12; ++i) d_extrinsics[f * 12 + i] += static_cast<T>(sum[i]);
    if (d_intrinsics) {
      T* dK = d_intrinsics + f * 9;
      dK[0] += static_cast<T>(sum[12]);
      dK[4] += static_cast<T>(sum[13]);
      dK[2] += static_cast<T>(sum[14]);
      dK[5] += static_cast<T>(sum[15]);
    }
  }
}

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
