#pragma once
// The library's one camera: a pinhole in OpenCV axes (x right, y down, z forward), pixel centres at +0.5, with its
// look-at and its row-major arrays (K [3, 3], world-to-camera [3, 4]), the encoding of the model's camera tensors.
// The rasterizer's view (raster/render.hpp), VGGT's integer-pixel intrinsics (model/cameras.hpp) and glTF camera
// nodes (export/gltf.hpp) convert from and to it. Usage:
//   Camera cam = look_at(eye, target, 256, 256, intrinsics_from_fov(256, 256, 45.0));
//   double K[9], w2c[12];  camera_arrays(cam, K, w2c);
//   Camera back = camera_from_arrays(K, w2c, 256, 256);
#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>
#include <string>
#include <utility>
#include <vector>

#include <glm/glm.hpp>

#include "flexsplat/core/error.hpp"

namespace flexsplat {
inline namespace v0 {

// World-to-camera x_cam = R * x_world + t; a camera-space point (x, y, z) lands at continuous pixel coordinates
// (u + 0.5, v + 0.5) = (K * (x, y, z)) / z. GLM matrices are column-major: K[col][row].
struct Camera {
  std::string name;  // a photo's file name, a glTF node's name; may be empty
  int width = 0, height = 0;
  glm::dmat3 K{1.0};
  glm::dmat3 R{1.0};
  glm::dvec3 t{0.0};
  double elevation_deg = 0, azimuth_deg = 0;  // orbit parameters when known (the data module's cameras.json)

  glm::dvec3 centre() const { return -glm::transpose(R) * t; }
  glm::dvec3 to_camera(glm::dvec3 world) const { return R * world + t; }
  glm::dvec3 to_world(glm::dvec3 cam) const { return glm::transpose(R) * (cam - t); }
  // Continuous pixel coordinates (pixel (i, j) covers [i, i + 1) x [j, j + 1)) of a camera-space point.
  glm::dvec2 project(glm::dvec3 cam) const {
    const glm::dvec3 h = K * cam;
    return {h.x / h.z, h.y / h.z};
  }
  // Camera-space point at continuous pixel coordinates (u, v) and camera z.
  glm::dvec3 unproject(glm::dvec2 uv, double z) const {
    return glm::inverse(K) * glm::dvec3(uv.x * z, uv.y * z, z);
  }
};

// fx = fy from a horizontal field of view, principal point at the image centre.
inline glm::dmat3 intrinsics_from_fov(int width, int height, double hfov_deg) {
  const double f = 0.5 * width / std::tan(0.5 * hfov_deg * std::numbers::pi / 180.0);
  glm::dmat3 K(1.0);
  K[0][0] = f;
  K[1][1] = f;
  K[2][0] = 0.5 * width;
  K[2][1] = 0.5 * height;
  return K;
}

// Camera at `eye` looking at `target`, image up along `up` (default world z, the shared objects' frame): x right,
// y down, z forward.
inline Camera look_at(glm::dvec3 eye, glm::dvec3 target, int width, int height, const glm::dmat3& K,
                      glm::dvec3 up = glm::dvec3(0, 0, 1)) {
  const glm::dvec3 forward = glm::normalize(target - eye);
  glm::dvec3 right = glm::cross(forward, up);
  require(glm::length(right) > 1e-9, "look_at: viewing direction is parallel to the up axis");
  right = glm::normalize(right);
  const glm::dvec3 down = glm::cross(forward, right);
  Camera cam;
  cam.width = width;
  cam.height = height;
  cam.K = K;
  cam.R = glm::transpose(glm::dmat3(right, down, forward));  // rows are the camera axes in world coordinates
  cam.t = -(cam.R * eye);
  return cam;
}

// A camera position on the orbit of `radius` around the origin: elevation above the xy plane, azimuth from +x towards
// +y (radians); look_at(orbit_eye(...), origin) gives the orbit's camera.
inline glm::dvec3 orbit_eye(double elevation, double azimuth, double radius) {
  return {radius * std::cos(elevation) * std::cos(azimuth), radius * std::cos(elevation) * std::sin(azimuth),
          radius * std::sin(elevation)};
}

// The row-major world-to-camera [I | 0]: the first view's camera in the model's frame.
inline constexpr double identity_w2c[12] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0};

// Row-major K [3, 3] and world-to-camera [R | t] [3, 4]; either pointer may be null.
template <class T>
void camera_arrays(const Camera& c, T* K, T* w2c) {
  for (int r = 0; r < 3; ++r) {
    for (int col = 0; col < 3; ++col) {
      if (K) K[3 * r + col] = static_cast<T>(c.K[col][r]);
      if (w2c) w2c[4 * r + col] = static_cast<T>(c.R[col][r]);
    }
    if (w2c) w2c[4 * r + 3] = static_cast<T>(c.t[r]);
  }
}

template <class T>
Camera camera_from_arrays(const T* K, const T* w2c, int width, int height, std::string name = {}) {
  Camera c;
  c.name = std::move(name);
  c.width = width;
  c.height = height;
  for (int r = 0; r < 3; ++r) {
    for (int col = 0; col < 3; ++col) {
      c.K[col][r] = static_cast<double>(K[3 * r + col]);
      c.R[col][r] = static_cast<double>(w2c[4 * r + col]);
    }
    c.t[r] = static_cast<double>(w2c[4 * r + 3]);
  }
  return c;
}

// out = w2c_i * w2c_j^-1 for rigid row-major [3, 4] cameras: camera j's coordinates to camera i's, the same in every
// world frame. R = R_i R_j^T, t = t_i - R t_j. out must not alias the inputs.
template <class T>
void relative_w2c(T* out, const T* w2c_i, const T* w2c_j) {
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) {
      T s = T(0);
      for (int k = 0; k < 3; ++k) s += w2c_i[4 * r + k] * w2c_j[4 * c + k];
      out[4 * r + c] = s;
    }
  for (int r = 0; r < 3; ++r) {
    T s = w2c_i[4 * r + 3];
    for (int k = 0; k < 3; ++k) s -= out[4 * r + k] * w2c_j[4 * k + 3];
    out[4 * r + 3] = s;
  }
}

// Backward of relative_w2c: adds into d_i and d_j [3, 4] (either may be null) from d_out [3, 4].
template <class T>
void relative_w2c_backward(T* d_i, T* d_j, const T* d_out, const T* w2c_i, const T* w2c_j) {
  T rel[12], dR[9];
  relative_w2c(rel, w2c_i, w2c_j);
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) dR[3 * r + c] = d_out[4 * r + c] - d_out[4 * r + 3] * w2c_j[4 * c + 3];
  for (int r = 0; r < 3; ++r) {
    if (d_i) d_i[4 * r + 3] += d_out[4 * r + 3];
    if (d_j) {
      T s = T(0);
      for (int k = 0; k < 3; ++k) s += rel[4 * k + r] * d_out[4 * k + 3];
      d_j[4 * r + 3] -= s;
    }
    for (int c = 0; c < 3; ++c) {
      T si = T(0), sj = T(0);
      for (int k = 0; k < 3; ++k) {
        si += dR[3 * r + k] * w2c_j[4 * k + c];  // dR_i = dR R_j
        sj += dR[3 * k + r] * w2c_i[4 * k + c];  // dR_j = dR^T R_i
      }
      if (d_i) d_i[4 * r + c] += si;
      if (d_j) d_j[4 * r + c] += sj;
    }
  }
}

// max(|R^T R - I|, |det R - 1|) entrywise: 0 for a rotation, what the camera readers compare with their tolerance.
inline double rotation_defect(const glm::dmat3& R) {
  const glm::dmat3 rtr = glm::transpose(R) * R;
  double err = std::abs(glm::determinant(R) - 1);
  for (int c = 0; c < 3; ++c)
    for (int r = 0; r < 3; ++r) err = std::max(err, std::abs(rtr[c][r] - (c == r ? 1.0 : 0.0)));
  return std::isfinite(err) ? err : std::numeric_limits<double>::infinity();
}

// Image size positive, entries finite, focal lengths positive; throws naming the camera otherwise.
inline void check_cameras(const std::vector<Camera>& cameras, const std::string& context) {
  for (const Camera& cam : cameras) {
    require(cam.width > 0 && cam.height > 0, context, ": camera '", cam.name, "' has image size ", cam.width, "x",
            cam.height);
    for (int col = 0; col < 3; ++col)
      for (int r = 0; r < 3; ++r) {
        require(std::isfinite(cam.K[col][r]), context, ": camera '", cam.name, "' has a non-finite K entry");
        require(std::isfinite(cam.R[col][r]), context, ": camera '", cam.name, "' has a non-finite w2c entry");
      }
    for (int r = 0; r < 3; ++r)
      require(std::isfinite(cam.t[r]), context, ": camera '", cam.name, "' has a non-finite w2c entry");
    require(cam.K[0][0] > 0 && cam.K[1][1] > 0, context, ": camera '", cam.name, "' has focal lengths fx=",
            cam.K[0][0], " fy=", cam.K[1][1], " (must be positive)");
  }
}

}  // namespace v0
}  // namespace flexsplat
