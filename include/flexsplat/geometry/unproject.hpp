#pragma once
// Depth maps to world points as VGGT's unproject_depth_map_to_point_map: pixel (u, v) at integer coordinates,
// camera point ((u - cx) d / fx, (v - cy) d / fy, d), world point R^T (p - t) for world-to-camera [R | t].
#include <cmath>

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

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
