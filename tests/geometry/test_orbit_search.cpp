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

TEST_CASE("orbit search with a depth range: a point may lie anywhere within the range along its ray",
          "[geometry][orbit]") {
  // Two views at their true cameras; the first view's depth scaled by 1 / 0.95, so that one of the five candidate
  // depths of a 10 % range (0.9, 0.95, 1, 1.05, 1.1 of it) is the true depth.
  const Views v = render_views(3, {{20, 0}, {35, 97}}, 48);
  const index_t px = v.size * v.size;
  std::vector<float> scaled = v.depth;
  for (index_t p = 0; p < px; ++p) scaled[static_cast<std::size_t>(p)] /= 0.95f;
  using geometry::orbit_detail::View;
  using geometry::orbit_detail::Placed;
  auto prepare = [&](const std::vector<float>& depth, index_t f, const geometry::OrbitSearchConfig& cfg) {
    View view;
    REQUIRE(geometry::orbit_detail::prepare_view(view, v.images.data(), v.foreground.data(), depth.data(), v.K.data(),
                                                 f, v.size, v.size, cfg));
    return view;
  };
  Placed placed[2];
  for (int f = 0; f < 2; ++f)
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) placed[f].R[c][r] = v.w2c[static_cast<std::size_t>(12 * f + 4 * r + c)];
      placed[f].t[r] = v.w2c[static_cast<std::size_t>(12 * f + 4 * r + 3)];
    }
  geometry::OrbitSearchConfig given, ranged, wide;
  ranged.depth_range = 0.1;
  wide.depth_tolerance = given.depth_tolerance + ranged.depth_range;  // the other view's tolerance under the range
  const View b = prepare(v.depth, 1, given);
  auto cost = [&](const std::vector<float>& depth, const geometry::OrbitSearchConfig& cfg) {
    return geometry::orbit_detail::pair_cost(prepare(depth, 0, cfg), placed[0], b, placed[1], cfg);
  };
  const double exact_wide = cost(v.depth, wide), off_ranged = cost(scaled, ranged);
  // The ranged cost from its definition: each point's cheapest candidate, each candidate costed as a point of its own.
  const View a = prepare(scaled, 0, ranged);
  const index_t n = static_cast<index_t>(a.point.size() / 3);
  REQUIRE(n >= 100);
  double expected = 0;
  index_t elsewhere = 0;  // points whose cheapest depth is not the one given
  for (index_t i = 0; i < n; ++i) {
    double best = 1e9, as_given = 0;
    for (index_t k = 0; k < ranged.depth_candidates; ++k) {
      const double along = 0.9 + 0.05 * static_cast<double>(k);
      View one = a;
      one.point.assign(3, 0.0);
      for (int c = 0; c < 3; ++c) one.point[static_cast<std::size_t>(c)] = along * a.point[static_cast<std::size_t>(3 * i + c)];
      one.point_colour.assign(a.point_colour.begin() + 3 * i, a.point_colour.begin() + 3 * i + 3);
      const double c = geometry::orbit_detail::pair_cost(one, placed[0], b, placed[1], wide);
      if (c < best) best = c;
      if (k == 2) as_given = c;
    }
    if (best < as_given) ++elsewhere;
    expected += best;
  }
  expected /= static_cast<double>(n);
  INFO("true depth " << exact_wide << ", 5 % off within a 10 % range " << off_ranged << " (from the definition "
                     << expected << "); " << elsewhere << " of " << n << " points cheapest at another depth");
  CHECK(off_ranged == Approx(expected).epsilon(1e-12));
  CHECK(off_ranged <= exact_wide + 1e-3);  // the candidate at 0.95 is the true point
  CHECK(elsewhere * 10 >= n);
  // Without a range the candidates are not used.
  geometry::OrbitSearchConfig more = given;
  more.depth_candidates = 9;
  CHECK(cost(scaled, more) == cost(scaled, given));

  geometry::OrbitSearchConfig bad;
  bad.depth_range = 0.6;
  std::vector<float> E(static_cast<std::size_t>(12 * v.n));
  CHECK_THROWS_WITH(geometry::cameras_from_orbit_search<float>(E.data(), nullptr, v.foreground.data(), v.depth.data(),
                                                               v.K.data(), v.n, v.size, v.size, bad),
                    Catch::Contains("depth range 0.6"));
}
