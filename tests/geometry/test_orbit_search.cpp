#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <vector>

#include "flexsplat/data/cameras.hpp"
#include "flexsplat/data/mesh_render.hpp"
#include "flexsplat/data/procedural.hpp"
#include "flexsplat/geometry/orbit_search.hpp"
#include "flexsplat/model/cameras.hpp"
#include "flexsplat/model/frames.hpp"

using namespace flexsplat;

namespace {
// Views of one procedural object rendered from orbit cameras: images [S, 3, H, W], alpha as the foreground, z-depth,
// intrinsics in VGGT's integer-pixel convention, and the true world-to-cameras.
struct Views {
  index_t n = 0, size = 0;
  std::vector<float> images, foreground, depth, K;
  std::vector<double> w2c;
};

Views render_views(std::uint64_t seed, const std::vector<std::pair<double, double>>& orbit, int size) {
  const data::ProceduralObject object = data::make_object(seed);
  Views v;
  v.n = static_cast<index_t>(orbit.size()), v.size = size;
  const index_t px = static_cast<index_t>(size) * size;
  data::RenderWorkspace ws;
  for (const auto& [el, az] : orbit) {
    const Camera cam = data::orbit_camera(el, az, 3.0, 40, size, size);
    data::RenderOutput out;
    data::RenderOptions opt;
    opt.light_direction = object.light_direction, opt.ambient = object.ambient;
    data::render_mesh(object.mesh, cam, opt, out, ws);
    for (index_t k = 0; k < 3; ++k)
      for (index_t p = 0; p < px; ++p) {
        const float a = out.rgba.data()[4 * p + 3];
        v.images.push_back(out.rgba.data()[4 * p + k] * a + (1 - a));
      }
    for (index_t p = 0; p < px; ++p) v.foreground.push_back(out.rgba.data()[4 * p + 3]), v.depth.push_back(out.depth.data()[p]);
    double K[9], E[12];
    camera_arrays(cam, K, E);
    K[2] -= 0.5, K[5] -= 0.5;
    v.K.insert(v.K.end(), K, K + 9);
    v.w2c.insert(v.w2c.end(), E, E + 12);
  }
  return v;
}

double mean_relative_error(const std::vector<float>& E, const std::vector<double>& gt, index_t n) {
  const std::vector<double> pred(E.begin(), E.end());
  double e = 0;
  for (index_t v = 1; v < n; ++v) e += model::relative_rotation_error_deg(pred.data(), pred.data() + 12 * v, gt.data(), gt.data() + 12 * v);
  return e / static_cast<double>(n - 1);
}
}  // namespace

TEST_CASE("orbit search finds the cameras of rendered orbit views from silhouettes and depth", "[geometry][orbit]") {
  // Elevations and azimuths off the search grid (10 degrees); the first view is the world.
  const std::vector<std::pair<double, double>> orbit{{20, 0}, {35, 97}, {12, 183}, {41, 268}};
  for (std::uint64_t seed : {3u, 11u}) {
    const Views v = render_views(seed, orbit, 64);
    std::vector<float> E(static_cast<std::size_t>(12 * v.n));
    bool solved[4];
    double cost = -1;
    geometry::cameras_from_orbit_search<float>(E.data(), v.images.data(), v.foreground.data(), v.depth.data(),
                                               v.K.data(), v.n, v.size, v.size, {}, solved, &cost);
    const double err = mean_relative_error(E, v.w2c, v.n);
    INFO("seed " << seed << ": mean relative rotation error " << err << " deg, cost " << cost);
    CHECK(err < 5);
    CHECK(std::all_of(solved, solved + 4, [](bool b) { return b; }));
    for (int i = 0; i < 12; ++i) CHECK(E[static_cast<std::size_t>(i)] == static_cast<float>(identity_w2c[i]));
  }
}

TEST_CASE("orbit search: a view without object pixels stays at the first camera, unsolved, and bad input is refused",
          "[geometry][orbit]") {
  Views v = render_views(5, {{20, 0}, {30, 120}, {10, 240}}, 48);
  const index_t px = v.size * v.size;
  std::fill(v.foreground.begin() + 2 * px, v.foreground.end(), 0.f);
  std::vector<float> E(static_cast<std::size_t>(12 * v.n));
  bool solved[3];
  geometry::cameras_from_orbit_search<float>(E.data(), nullptr, v.foreground.data(), v.depth.data(), v.K.data(), v.n,
                                             v.size, v.size, {}, solved);
  CHECK(solved[0]);
  CHECK(solved[1]);
  CHECK_FALSE(solved[2]);
  for (int i = 0; i < 12; ++i) CHECK(E[static_cast<std::size_t>(24 + i)] == static_cast<float>(identity_w2c[i]));
  geometry::OrbitSearchConfig bad;
  bad.elevation_max_deg = 90;
  CHECK_THROWS_WITH(geometry::cameras_from_orbit_search<float>(E.data(), nullptr, v.foreground.data(), v.depth.data(),
                                                               v.K.data(), v.n, v.size, v.size, bad),
                    Catch::Contains("invalid config"));
  v.K[0] = -1;
  CHECK_THROWS_WITH(geometry::cameras_from_orbit_search<float>(E.data(), nullptr, v.foreground.data(), v.depth.data(),
                                                               v.K.data(), v.n, v.size, v.size),
                    Catch::Contains("view 0 has intrinsics fx -1"));
}

TEST_CASE("orbit search with a depth range: depth off by up to 8 % in smooth waves, the range finds the cameras",
          "[geometry][orbit]") {
  const std::vector<std::pair<double, double>> orbit{{20, 0}, {35, 97}, {12, 183}};
  for (std::uint64_t seed : {3u, 11u}) {
    const Views v = render_views(seed, orbit, 64);
    // Each view's depth times a factor in [0.92, 1.08] that varies smoothly over the image (a learned depth's errors
    // are in its shape, not per pixel), in a different phase per view.
    std::vector<float> noisy = v.depth;
    const index_t px = v.size * v.size;
    for (index_t f = 0; f < v.n; ++f)
      for (index_t p = 0; p < px; ++p) {
        const double x = static_cast<double>(p % v.size) / static_cast<double>(v.size);
        const double y = static_cast<double>(p / v.size) / static_cast<double>(v.size);
        const double phase = static_cast<double>(f);
        noisy[static_cast<std::size_t>(f * px + p)] *=
            static_cast<float>(1 + 0.08 * std::sin(9.4 * x + phase) * std::cos(7.5 * y + 2 * phase));
      }
    auto error = [&](double range) {
      geometry::OrbitSearchConfig cfg;
      cfg.depth_range = range;
      std::vector<float> E(static_cast<std::size_t>(12 * v.n));
      geometry::cameras_from_orbit_search<float>(E.data(), v.images.data(), v.foreground.data(), noisy.data(),
                                                 v.K.data(), v.n, v.size, v.size, cfg);
      return mean_relative_error(E, v.w2c, v.n);
    };
    const double given = error(0), ranged = error(0.1);
    INFO("seed " << seed << ": mean relative rotation error, depth as given " << given << " deg, within a 10 % range "
                 << ranged << " deg");
    CHECK(given > 60);  // the waves throw the search off
    CHECK(ranged < 20);
  }
  geometry::OrbitSearchConfig bad;
  bad.depth_range = 0.6;
  const Views v = render_views(3, orbit, 32);
  std::vector<float> E(static_cast<std::size_t>(12 * v.n));
  CHECK_THROWS_WITH(geometry::cameras_from_orbit_search<float>(E.data(), nullptr, v.foreground.data(), v.depth.data(),
                                                               v.K.data(), v.n, v.size, v.size, bad),
                    Catch::Contains("depth range 0.6"));
}
