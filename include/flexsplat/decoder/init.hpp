#pragma once
// Geometric initialisation: the scene centre from the predicted cameras, and the initialisers of the flat parameter
// blocks (Xavier-uniform weights, constant biases).
#include <algorithm>
#include <cmath>
#include <random>
#include <vector>

#include <Eigen/Dense>

#include "flexsplat/decoder/constants.hpp"
#include "flexsplat/decoder/gaussians.hpp"

namespace flexsplat {
inline namespace v0 {
namespace decoder {

struct SceneCentre {
  double centre[3] = {0, 0, 0};
  bool from_axes = false;         // false: the axes were (nearly) parallel and the median-depth fallback was used
  double smallest_eigenvalue = 0;  // of the normalised normal matrix, the parallelism measure
};

// Weighted least-squares point closest to every optical axis: minimises sum_v w_v |(I - a_v a_v^T)(x - c_v)|^2 with
// c_v = -R^T t the camera centre and a_v = R^T e_z its viewing direction. When the normal matrix (divided by the weight
// sum) has an eigenvalue below parallel_axes_eigen_floor the axes do not pin a point down, and the centre becomes the
// mean of the points at each view's median predicted depth along its axis. weights may be null (all 1).
// median_scratch (may be null) holds the depth values of the fallback; reserve depth_w * depth_h to avoid allocating.
namespace detail {
// Camera centre c = -R^T t and unit viewing direction a = R^T e_z of view v; false for a degenerate rotation.
template <class T>
bool camera_axis(const ViewGeometry<T>& g, index_t v, Eigen::Vector3d& c, Eigen::Vector3d& a) {
  const T* E = g.world_to_camera + 12 * v;
  Eigen::Matrix3d R;
  Eigen::Vector3d t;
  for (int r = 0; r < 3; ++r) {
    for (int k = 0; k < 3; ++k) R(r, k) = static_cast<double>(E[4 * r + k]);
    t(r) = static_cast<double>(E[4 * r + 3]);
  }
  c = -R.transpose() * t;
  a = R.row(2).transpose();
  const double norm = a.norm();
  if (!(norm > 0 && std::isfinite(norm))) return false;
  a /= norm;
  return true;
}
}  // namespace detail

template <class T>
SceneCentre scene_centre_from_axes(const ViewGeometry<T>& g, const T* weights = nullptr,
                                   std::vector<double>* median_scratch = nullptr) {
  validate_geometry(g);
  Eigen::Matrix3d A = Eigen::Matrix3d::Zero();
  Eigen::Vector3d b = Eigen::Vector3d::Zero();
  double weight_sum = 0;
  for (index_t v = 0; v < g.views; ++v) {
    Eigen::Vector3d c, a;
    require(detail::camera_axis(g, v, c, a), "scene centre: view ", v, " has a degenerate rotation (zero third row)");
    const double w = weights ? static_cast<double>(weights[v]) : 1.0;
    require(std::isfinite(w) && w >= 0, "scene centre: view ", v, " has weight ", w, " (must be finite and >= 0)");
    const Eigen::Matrix3d P = Eigen::Matrix3d::Identity() - a * a.transpose();
    A += w * P;
    b += w * P * c;
    weight_sum += w;
  }
  require(weight_sum > 0, "scene centre: all view weights are zero");
  SceneCentre out;
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig(A / weight_sum);
  out.smallest_eigenvalue = eig.eigenvalues()(0);
  if (out.smallest_eigenvalue >= parallel_axes_eigen_floor) {
    const Eigen::Vector3d x = A.ldlt().solve(b);
    if (x.allFinite()) {
      for (int i = 0; i < 3; ++i) out.centre[i] = x(i);
      out.from_axes = true;
      return out;
    }
  }
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  std::vector<double> own;
  std::vector<double>& values = median_scratch ? *median_scratch : own;
  for (index_t v = 0; v < g.views; ++v) {
    Eigen::Vector3d centre, axis;
    detail::camera_axis(g, v, centre, axis);
    values.clear();
    const T* D = g.depth + v * g.depth_w * g.depth_h;
    for (index_t i = 0; i < g.depth_w * g.depth_h; ++i)
      if (std::isfinite(D[i]) && D[i] > static_cast<T>(near_depth)) values.push_back(static_cast<double>(D[i]));
    double median = 1.0;  // no usable depth at all: one unit in front of the camera
    if (!values.empty()) {
      std::nth_element(values.begin(), values.begin() + values.size() / 2, values.end());
      median = values[values.size() / 2];
    }
    mean += centre + median * axis;
  }
  mean /= static_cast<double>(g.views);
  for (int i = 0; i < 3; ++i) out.centre[i] = mean(i);
  return out;
}

// Xavier/Glorot uniform: U(-a, a), a = gain * sqrt(6 / (fan_in + fan_out)).
template <class T>
void xavier_uniform(T* w, index_t fan_out, index_t fan_in, std::mt19937_64& rng, double gain = 1.0) {
  const double a = gain * std::sqrt(6.0 / static_cast<double>(fan_in + fan_out));
  std::uniform_real_distribution<double> u(-a, a);
  for (index_t i = 0; i < fan_out * fan_in; ++i) w[i] = static_cast<T>(u(rng));
}

// Convolutions: count weights with the given fans (channels x kernel area).
template <class T>
void xavier_uniform_fans(T* w, index_t count, index_t fan_out, index_t fan_in, std::mt19937_64& rng) {
  const double a = std::sqrt(6.0 / static_cast<double>(fan_in + fan_out));
  std::uniform_real_distribution<double> u(-a, a);
  for (index_t i = 0; i < count; ++i) w[i] = static_cast<T>(u(rng));
}

template <class T>
void normal_init(T* w, index_t n, std::mt19937_64& rng, double stddev) {
  std::normal_distribution<double> d(0.0, stddev);
  for (index_t i = 0; i < n; ++i) w[i] = static_cast<T>(d(rng));
}

}  // namespace decoder
}  // namespace v0
}  // namespace flexsplat
