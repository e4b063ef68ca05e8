#pragma once
// Deterministic random Gaussian sets for the export tests.
#include <cmath>
#include <random>
#include <string>

#include "flexsplat/export/gaussian_set.hpp"

namespace flexsplat_test {

template <class T = float>
flexsplat::GaussianSet<T> random_set(flexsplat::index_t n, int degree, unsigned seed = 7) {
  using namespace flexsplat;
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-1.0, 1.0), u01(0.0, 1.0);
  auto set = make_gaussian_set<T>(n, degree);
  for (index_t i = 0; i < n; ++i) {
    double q[4], norm = 0;
    for (double& v : q) { v = u(rng); norm += v * v; }
    norm = std::sqrt(norm);
    for (int c = 0; c < 4; ++c) set.quats(i, c) = T(q[c] / norm);
    for (int c = 0; c < 3; ++c) {
      set.means(i, c) = T(u(rng));
      set.scales(i, c) = T(0.01 + 0.2 * u01(rng));
    }
    set.opacities(i) = T(u01(rng));
    for (index_t k = 0; k < set.sh.shape(1); ++k)
      for (int c = 0; c < 3; ++c) set.sh(i, k, c) = T(k == 0 ? 1.5 * u(rng) : 0.3 * u(rng));
  }
  return set;
}

inline flexsplat::gaussians::Camera test_camera(double azimuth_deg, const std::string& name) {
  // Looks at the origin from distance 3 in the z = 0.6 plane (Blender-like z-up world, OpenCV camera axes).
  const double a = azimuth_deg * 3.14159265358979323846 / 180.0;
  const double cx = 3 * std::cos(a), cy = 3 * std::sin(a), cz = 0.6;
  double f[3] = {-cx, -cy, -cz};
  double fn = std::sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2]);
  for (double& v : f) v /= fn;
  double r[3] = {f[1] * 1 - f[2] * 0, f[2] * 0 - f[0] * 1, f[0] * 0 - f[1] * 0};  // forward x up(0,0,1)
  double rn = std::sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2]);
  for (double& v : r) v /= rn;
  double d[3] = {f[1] * r[2] - f[2] * r[1], f[2] * r[0] - f[0] * r[2], f[0] * r[1] - f[1] * r[0]};  // down
  flexsplat::gaussians::Camera cam;
  cam.name = name;
  cam.width = 320;
  cam.height = 240;
  cam.K = {300, 0, 161.5, 0, 290, 118.25, 0, 0, 1};
  const double* rows[3] = {r, d, f};
  const double c[3] = {cx, cy, cz};
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) cam.w2c[i * 4 + j] = rows[i][j];
    cam.w2c[i * 4 + 3] = -(rows[i][0] * c[0] + rows[i][1] * c[1] + rows[i][2] * c[2]);
  }
  return cam;
}

}  // namespace flexsplat_test
