#pragma once
// Random test scenes for the raster tests (not a public header).
#include <cmath>
#include <random>

#include "flexsplat/raster/render.hpp"

namespace rastertest {

using namespace flexsplat;
using namespace flexsplat::raster;

// A Gaussian set with the camera and options it is rendered with.
template <class T>
struct Scene : GaussianSet<T> {
  View<T> camera;
  RenderOptions options;
  const GaussianSet<T>& set() const { return *this; }
};

struct SceneSpec {
  index_t n = 40;
  int width = 40, height = 32, sh_degree = 1, features = 0;
  double scale_min = 0.03, scale_max = 0.15, opacity_min = 0.05, opacity_max = 0.95;
  double half_extent = 1.0, distance = 4.0;
  bool antialiased = false;
  unsigned seed = 1;
};

// Means uniform in a cube centred `distance` in front of a slightly rotated pinhole camera with fx = fy = W.
template <class T>
Scene<T> make_scene(const SceneSpec& spec) {
  std::mt19937 rng(spec.seed);
  std::uniform_real_distribution<double> uni(-1.0, 1.0), u01(0.0, 1.0);
  std::normal_distribution<double> normal(0.0, 1.0);
  Scene<T> s;
  const index_t n = spec.n, K = (spec.sh_degree + 1) * (spec.sh_degree + 1);
  s.means.resize({n, 3});
  s.quats.resize({n, 4});
  s.scales.resize({n, 3});
  s.opacities.resize({n});
  s.sh.resize({n, K, 3});
  s.features.resize({n, spec.features});
  const double a = 0.3, c = std::cos(a), si = std::sin(a);
  s.camera.world_to_camera = {T(c), T(-si), 0, T(0.1), T(si), T(c), 0, T(-0.2), 0, 0, 1, T(spec.distance), 0, 0, 0, 1};
  s.camera.fx = s.camera.fy = T(spec.width);
  s.camera.cx = T(spec.width * 0.5 + 0.3);
  s.camera.cy = T(spec.height * 0.5 - 0.7);
  s.camera.width = spec.width;
  s.camera.height = spec.height;
  for (index_t i = 0; i < n; ++i) {
    for (int k = 0; k < 3; ++k) s.means(i, k) = T(spec.half_extent * uni(rng));
    for (int k = 0; k < 4; ++k) s.quats(i, k) = T(normal(rng));
    const double lmin = std::log(spec.scale_min), lmax = std::log(spec.scale_max);
    for (int k = 0; k < 3; ++k) s.scales(i, k) = T(std::exp(lmin + (lmax - lmin) * u01(rng)));
    s.opacities(i) = T(spec.opacity_min + (spec.opacity_max - spec.opacity_min) * u01(rng));
    for (index_t k = 0; k < K; ++k)
      for (int ch = 0; ch < 3; ++ch) s.sh(i, k, ch) = T((k == 0 ? 0.8 : 0.3) * normal(rng));
    for (int f = 0; f < spec.features; ++f) s.features(i, f) = T(normal(rng));
  }
  s.options.sh_degree = spec.sh_degree;
  s.options.antialiased = spec.antialiased;
  s.options.background = {0.2, 0.5, 0.9};
  return s;
}

}  // namespace rastertest
