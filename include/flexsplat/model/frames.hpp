#pragma once
// Coordinate frames of a pose-free model. The model predicts cameras in the frame of its first input camera with a
// scale it chooses, so ground truth is brought into that frame for training (as VGGT trains: the first camera becomes
// the identity and the scene is divided by the mean distance of the first-camera-frame points), and predictions are
// brought back to the evaluation frame by a similarity transform fitted to the camera centres (Umeyama's
// least-squares estimator) for evaluation.
#include <algorithm>
#include <cmath>
#include <vector>

#include <Eigen/Dense>
#include <Eigen/Geometry>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {
namespace model {

// A similarity x -> scale * R x + t.
struct Similarity {
  Eigen::Matrix3d R = Eigen::Matrix3d::Identity();
  Eigen::Vector3d t = Eigen::Vector3d::Zero();
  double scale = 1.0;
  Eigen::Vector3d apply(const Eigen::Vector3d& x) const { return scale * (R * x) + t; }
};

inline Eigen::Matrix4d to_matrix4(const double* w2c) {
  Eigen::Matrix4d m = Eigen::Matrix4d::Identity();
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 4; ++c) m(r, c) = w2c[4 * r + c];
  return m;
}

// Camera centre -R^T t of a row-major world-to-camera [3, 4].
inline Eigen::Vector3d camera_centre(const double* w2c) {
  const Eigen::Matrix4d m = to_matrix4(w2c);
  return -m.block<3, 3>(0, 0).transpose() * m.block<3, 1>(0, 3);
}

// Ground truth in the model's frame: the first camera becomes [I | 0]; the scale is the mean distance to its centre of
// the valid (depth > 0, finite) points of the input views' depth maps, as VGGT normalises its training data.
struct FirstCameraFrame {
  Eigen::Matrix4d first_w2c = Eigen::Matrix4d::Identity();
  double scale = 1.0;  // divide lengths by this

  // A world-to-camera [3, 4] of the old frame -> the new frame (in place).
  void camera(double* w2c) const {
    Eigen::Matrix4d m = to_matrix4(w2c) * first_w2c.inverse();
    m.block<3, 1>(0, 3) /= scale;
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 4; ++c) w2c[4 * r + c] = m(r, c);
  }
};

// w2c [V, 3, 4] and K [V, 3, 3] of the input views (pixel-centre convention), depth [V, h, w] metric camera z (0 = no
// surface). Throws when no depth sample is valid.
inline FirstCameraFrame first_camera_frame(const double* w2c, const double* K, const double* depth, index_t views,
                                           index_t h, index_t w) {
  require(views >= 1 && h >= 1 && w >= 1, "first_camera_frame: need at least one view of positive size, got ", views,
          " views of ", w, " x ", h);
  FirstCameraFrame f;
  f.first_w2c = to_matrix4(w2c);
  const Eigen::Matrix4d to_first = f.first_w2c;
  double sum = 0.0;
  index_t count = 0;
  for (index_t v = 0; v < views; ++v) {
    const Eigen::Matrix4d cam_to_world = to_matrix4(w2c + 12 * v).inverse();
    const Eigen::Matrix4d cam_to_first = to_first * cam_to_world;
    const double* k = K + 9 * v;
    for (index_t y = 0; y < h; ++y)
      for (index_t x = 0; x < w; ++x) {
        const double z = depth[(v * h + y) * w + x];
        if (!(z > 0.0) || !std::isfinite(z)) continue;
        const Eigen::Vector4d p((static_cast<double>(x) + 0.5 - k[2]) / k[0] * z,
                                (static_cast<double>(y) + 0.5 - k[5]) / k[4] * z, z, 1.0);
        sum += (cam_to_first * p).head<3>().norm();
        ++count;
      }
  }
  require(count > 0, "first_camera_frame: no valid depth in ", views, " input views (all zero or non-finite)");
  f.scale = sum / static_cast<double>(count);
  require(f.scale > 0.0 && std::isfinite(f.scale), "first_camera_frame: mean point distance ", f.scale,
          " is not a usable scale");
  return f;
}

// The similarity that maps predicted camera centres onto the ground-truth ones in the least-squares sense (Umeyama,
// with scale). Two or fewer cameras leave rotation about their baseline undetermined, so then the rotation comes from
// the first camera's orientation (pred camera 0 is rotated onto gt camera 0) and scale/translation from the centres.
inline Similarity align_cameras(const double* w2c_pred, const double* w2c_gt, index_t views) {
  require(views >= 1, "align_cameras: no cameras");
  Similarity s;
  std::vector<Eigen::Vector3d> cp(static_cast<std::size_t>(views)), cg(static_cast<std::size_t>(views));
  for (index_t v = 0; v < views; ++v) {
    cp[static_cast<std::size_t>(v)] = camera_centre(w2c_pred + 12 * v);
    cg[static_cast<std::size_t>(v)] = camera_centre(w2c_gt + 12 * v);
  }
  if (views >= 3) {
    Eigen::Matrix3Xd a(3, views), b(3, views);
    for (index_t v = 0; v < views; ++v) a.col(v) = cp[static_cast<std::size_t>(v)], b.col(v) = cg[static_cast<std::size_t>(v)];
    const Eigen::Matrix4d m = Eigen::umeyama(a, b, true);
    const double scale = m.block<3, 3>(0, 0).determinant();
    if (std::isfinite(scale) && scale > 1e-12) {
      s.scale = std::cbrt(scale);
      s.R = m.block<3, 3>(0, 0) / s.scale;
      s.t = m.block<3, 1>(0, 3);
      return s;
    }
  }
  // R maps predicted world directions to gt world directions: C_gt = R C_pred for camera 0 (C = camera-to-world).
  const Eigen::Matrix3d Rp = to_matrix4(w2c_pred).block<3, 3>(0, 0), Rg = to_matrix4(w2c_gt).block<3, 3>(0, 0);
  s.R = Rg.transpose() * Rp;
  if (views >= 2) {
    const double dp = (cp[1] - cp[0]).norm(), dg = (cg[1] - cg[0]).norm();
    s.scale = dp > 1e-12 ? dg / dp : 1.0;
  }
  s.t = cg[0] - s.scale * (s.R * cp[0]);
  return s;
}

// Applies a similarity (in the world) to a world-to-camera [3, 4]: the camera keeps seeing the same transformed scene.
inline void transform_camera(double* w2c, const Similarity& s) {
  const Eigen::Matrix4d m = to_matrix4(w2c);
  const Eigen::Matrix3d R = m.block<3, 3>(0, 0) * s.R.transpose();
  const Eigen::Vector3d c = s.apply(-m.block<3, 3>(0, 0).transpose() * m.block<3, 1>(0, 3));
  const Eigen::Vector3d t = -R * c;
  for (int r = 0; r < 3; ++r) {
    for (int col = 0; col < 3; ++col) w2c[4 * r + col] = R(r, col);
    w2c[4 * r + 3] = t(r);
  }
}

// Angle in degrees between the relative rotations from camera i to camera j of two camera sets (the pair error of
// RRA@15/30: independent of each set's world frame).
inline double relative_rotation_error_deg(const double* a_i, const double* a_j, const double* b_i, const double* b_j) {
  const Eigen::Matrix3d ra = to_matrix4(a_j).block<3, 3>(0, 0) * to_matrix4(a_i).block<3, 3>(0, 0).transpose();
  const Eigen::Matrix3d rb = to_matrix4(b_j).block<3, 3>(0, 0) * to_matrix4(b_i).block<3, 3>(0, 0).transpose();
  // Through the quaternion (atan2): acos of the trace loses half its digits near 0 degrees.
  return Eigen::AngleAxisd(Eigen::Quaterniond(ra * rb.transpose()).normalized()).angle() * 180.0 / 3.14159265358979323846;
}

// Angle in degrees between the orientations of two world-to-camera matrices.
inline double rotation_error_deg(const double* w2c_a, const double* w2c_b) {
  const Eigen::Matrix3d Ra = to_matrix4(w2c_a).block<3, 3>(0, 0), Rb = to_matrix4(w2c_b).block<3, 3>(0, 0);
  const double c = std::clamp(((Ra * Rb.transpose()).trace() - 1.0) / 2.0, -1.0, 1.0);
  return std::acos(c) * 180.0 / 3.14159265358979323846;
}

}  // namespace model
}  // namespace v0
}  // namespace flexsplat
