#pragma once
// Deterministic random Gaussian sets for the export tests.
#include <cmath>
#include <random>
#include <string>

#include <glm/glm.hpp>

#include "flexsplat/core/camera.hpp"
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

inline flexsplat::Camera test_camera(double azimuth_deg, const std::string& name) {
  // Looks at the origin from distance 3 in the z = 0.6 plane (Blender-like z-up world, OpenCV camera axes).
  const double a = azimuth_deg * 3.14159265358979323846 / 180.0;
  glm::dmat3 K(1.0);
  K[0][0] = 300, K[1][1] = 290, K[2][0] = 161.5, K[2][1] = 118.25;
  flexsplat::Camera cam = flexsplat::look_at({3 * std::cos(a), 3 * std::sin(a), 0.6}, glm::dvec3(0.0), 320, 240, K);
  cam.name = name;
  return cam;
}

}  // namespace flexsplat_test
