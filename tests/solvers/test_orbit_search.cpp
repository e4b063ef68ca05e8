#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>
#include <vector>

#include <glm/gtc/matrix_transform.hpp>

#include "flexsplat/core/parallel.hpp"
#include "flexsplat/data/cameras.hpp"
#include "flexsplat/data/mesh_render.hpp"
#include "flexsplat/data/procedural.hpp"
#include "flexsplat/solvers/orbit_search.hpp"
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

TEST_CASE("orbit search cost: what the search reports, in any world frame, and higher for a turned view", "[geometry][orbit]") {
  const std::vector<std::pair<double, double>> orbit{{20, 0}, {35, 97}, {12, 183}, {41, 268}};
  const Views v = render_views(3, orbit, 64);
  std::vector<float> E(static_cast<std::size_t>(12 * v.n));
  double cost = -1;
  geometry::cameras_from_orbit_search<float>(E.data(), v.images.data(), v.foreground.data(), v.depth.data(), v.K.data(),
                                             v.n, v.size, v.size, {}, nullptr, &cost);
  auto cost_of = [&](const std::vector<float>& cams) {
    return geometry::orbit_search_cost<float>(cams.data(), v.images.data(), v.foreground.data(), v.depth.data(),
                                              v.K.data(), v.n, v.size, v.size);
  };
  const std::vector<float> truth(v.w2c.begin(), v.w2c.end());
  const double found = cost_of(E), true_cost = cost_of(truth);
  // Another world frame: every camera times the inverse of one rigid motion.
  const glm::dmat3 Q = glm::dmat3(glm::rotate(glm::dmat4(1.0), 0.7, glm::dvec3(0.3, -0.5, 0.8)));
  const glm::dvec3 q(0.4, -1.2, 0.3);
  std::vector<float> moved(truth.size()), turned = truth;
  for (index_t k = 0; k < v.n; ++k) {
    Camera cam = camera_from_arrays(v.K.data() + 9 * k, truth.data() + 12 * k, v.size, v.size);
    cam.R = cam.R * glm::transpose(Q);  // x_world' = Q x_world + q
    cam.t -= cam.R * q;
    camera_arrays<float>(cam, nullptr, moved.data() + 12 * k);
  }
  // View 2 turned by 30 degrees about its own vertical axis.
  const glm::dmat3 Y = glm::dmat3(glm::rotate(glm::dmat4(1.0), 30 * std::numbers::pi / 180, glm::dvec3(0, 1, 0)));
  Camera cam2 = camera_from_arrays(v.K.data() + 18, truth.data() + 24, v.size, v.size);
  cam2.R = Y * cam2.R, cam2.t = Y * cam2.t;
  camera_arrays<float>(cam2, nullptr, turned.data() + 24);
  const double turned_cost = cost_of(turned), moved_cost = cost_of(moved);
  INFO("reported " << cost << ", found " << found << ", truth " << true_cost << ", moved " << moved_cost << ", turned "
                   << turned_cost);
  CHECK(found == Approx(cost).epsilon(0.02));  // the same placement, from float extrinsics
  CHECK(moved_cost == Approx(true_cost).epsilon(1e-4));
  CHECK(turned_cost > 2 * true_cost);
  CHECK(geometry::orbit_search_cost<float>(truth.data(), v.images.data(), v.foreground.data(), v.depth.data(),
                                           v.K.data(), 1, v.size, v.size) == 0);  // one view: nothing to compare
  std::vector<float> broken = truth;
  broken[12 + 3] = std::numeric_limits<float>::quiet_NaN();
  CHECK_THROWS_WITH(cost_of(broken), Catch::Contains("orbit_search_cost: view 1 extrinsics[0,3] = nan is not finite"));
}

TEST_CASE("orbit search cost: its parts sum to it and say what a turned view breaks", "[geometry][orbit]") {
  const std::vector<std::pair<double, double>> orbit{{20, 0}, {35, 97}, {12, 183}};
  const Views v = render_views(3, orbit, 48);
  // Descriptors: each pixel's colour, so that the descriptor term takes part.
  const index_t px = v.size * v.size;
  std::vector<float> desc(static_cast<std::size_t>(v.n * px * 3));
  for (index_t f = 0; f < v.n; ++f)
    for (index_t p = 0; p < px; ++p)
      for (index_t k = 0; k < 3; ++k) desc[static_cast<std::size_t>((f * px + p) * 3 + k)] = v.images[static_cast<std::size_t>((f * 3 + k) * px + p)];
  geometry::OrbitSearchConfig cfg;
  cfg.depth_range = 0.1, cfg.descriptor_weight = 0.5;
  const geometry::OrbitDescriptors<float> d{desc.data(), 3};
  const std::vector<float> truth(v.w2c.begin(), v.w2c.end());
  std::vector<float> turned = truth;
  const glm::dmat3 Y = glm::dmat3(glm::rotate(glm::dmat4(1.0), 25 * std::numbers::pi / 180, glm::dvec3(0, 1, 0)));
  Camera cam = camera_from_arrays(v.K.data() + 9, truth.data() + 12, v.size, v.size);
  cam.R = Y * cam.R, cam.t = Y * cam.t;
  camera_arrays<float>(cam, nullptr, turned.data() + 12);
  geometry::OrbitCostParts at_truth, at_turned;
  const double c_truth = geometry::orbit_search_cost<float>(truth.data(), v.images.data(), v.foreground.data(), v.depth.data(),
                                                            v.K.data(), v.n, v.size, v.size, cfg, d, &at_truth);
  const double c_turned = geometry::orbit_search_cost<float>(turned.data(), v.images.data(), v.foreground.data(),
                                                             v.depth.data(), v.K.data(), v.n, v.size, v.size, cfg, d, &at_turned);
  // Without parts the same cost, to the bit.
  CHECK(c_truth == geometry::orbit_search_cost<float>(truth.data(), v.images.data(), v.foreground.data(), v.depth.data(),
                                                      v.K.data(), v.n, v.size, v.size, cfg, d));
  INFO("truth " << c_truth << ": off image " << at_truth.off_image << ", silhouette " << at_truth.silhouette
                << ", free space " << at_truth.free_space << ", occluded " << at_truth.occluded << ", colour "
                << at_truth.colour << ", descriptor " << at_truth.descriptor << "; turned " << c_turned << ": "
                << at_turned.off_image << ", " << at_turned.silhouette << ", " << at_turned.free_space << ", "
                << at_turned.occluded << ", " << at_turned.colour << ", " << at_turned.descriptor);
  CHECK(at_truth.total() == Approx(c_truth).margin(1e-9));
  CHECK(at_turned.total() == Approx(c_turned).margin(1e-9));
  CHECK(at_truth.descriptor < 0);  // exact descriptors on exact surfaces: a reward
  CHECK(at_truth.silhouette + at_truth.free_space < 0.1 * (at_turned.silhouette + at_turned.free_space));
  geometry::OrbitCostParts twice = at_truth;  // parts add to what they hold
  geometry::orbit_search_cost<float>(truth.data(), v.images.data(), v.foreground.data(), v.depth.data(), v.K.data(), v.n,
                                     v.size, v.size, cfg, d, &twice);
  CHECK(twice.total() == Approx(2 * c_truth).margin(1e-9));
  geometry::OrbitCostParts both = at_truth;
  both += at_turned;
  CHECK(both.silhouette == Approx(at_truth.silhouette + at_turned.silhouette).margin(1e-12));
  CHECK(both.total() == Approx(c_truth + c_turned).margin(1e-9));
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

TEST_CASE("orbit search with descriptors: a sphere's views are placed by what their pixels describe", "[geometry][orbit]") {
  // A sphere at the orbit centre has the same silhouette and depth from every orbit camera, so those alone cannot
  // place its views; descriptors that name the surface point can: 16 waves across the world, as a match head's
  // descriptors vary across the surface.
  const std::vector<std::pair<double, double>> orbit{{20, 0}, {35, 97}, {12, 183}};
  const int size = 48;
  const double radius = 0.8;
  const index_t n = static_cast<index_t>(orbit.size()), px = static_cast<index_t>(size) * size;
  std::vector<float> foreground, depth, K, descriptors;
  const index_t D = 16;
  std::vector<glm::dvec3> frequency;
  for (index_t k = 0; k < D; ++k)
    frequency.push_back(7.0 * glm::normalize(glm::dvec3(std::sin(1.7 * k + 0.3), std::cos(2.3 * k), std::sin(0.9 * k + 1.1))));
  std::vector<double> w2c;
  for (const auto& [el, az] : orbit) {
    const Camera cam = data::orbit_camera(el, az, 3.0, 40, size, size);
    const glm::dvec3 C = cam.centre();
    for (int y = 0; y < size; ++y)
      for (int x = 0; x < size; ++x) {
        const glm::dvec3 d((x + 0.5 - cam.K[2][0]) / cam.K[0][0], (y + 0.5 - cam.K[2][1]) / cam.K[1][1], 1.0);
        const glm::dvec3 dw = glm::transpose(cam.R) * d;
        const double a = glm::dot(dw, dw), b = 2 * glm::dot(C, dw), c = glm::dot(C, C) - radius * radius;
        const double disc = b * b - 4 * a * c;
        const double s = disc > 0 ? (-b - std::sqrt(disc)) / (2 * a) : 0;
        const glm::dvec3 X = C + s * dw;
        foreground.push_back(disc > 0 ? 1.f : 0.f), depth.push_back(static_cast<float>(s));
        for (index_t k = 0; k < D; ++k)
          descriptors.push_back(disc > 0 ? static_cast<float>(std::sin(glm::dot(frequency[static_cast<std::size_t>(k)], X) + k)) : 0.f);
      }
    double k[9], e[12];
    camera_arrays(cam, k, e);
    k[2] -= 0.5, k[5] -= 0.5;
    K.insert(K.end(), k, k + 9);
    w2c.insert(w2c.end(), e, e + 12);
  }
  REQUIRE(std::count(foreground.begin(), foreground.end(), 1.f) > 3 * px / 10);
  geometry::OrbitSearchConfig cfg;
  cfg.descriptor_weight = 1;
  std::vector<float> E(static_cast<std::size_t>(12 * n)), blind(E.size());
  geometry::cameras_from_orbit_search<float>(E.data(), nullptr, foreground.data(), depth.data(), K.data(), n, size, size,
                                             cfg, nullptr, nullptr, {descriptors.data(), D});
  geometry::cameras_from_orbit_search<float>(blind.data(), nullptr, foreground.data(), depth.data(), K.data(), n, size,
                                             size, cfg);
  const double with = mean_relative_error(E, w2c, n), without = mean_relative_error(blind, w2c, n);
  INFO("mean relative rotation error with descriptors " << with << " deg, without " << without << " deg");
  // Not the few degrees of a textured object's silhouettes and depth: far-apart views of a sphere share little surface,
  // and the points one view hides from another (occluded_cost) pull them together (about 10 degrees here).
  CHECK(with < 15);
  CHECK(without > 60);  // the control: silhouettes and depth alone leave the sphere's views anywhere

  // The search's parallel loops on a pool of 2 workers (whatever FLEXSPLAT_NUM_THREADS says) give the same cameras
  // and cost as one thread (a SerialScope: a pool of one worker).
  std::vector<float> serial(E.size()), parallel(E.size());
  double cost_serial = 0, cost_parallel = 0;
  {
    const SerialScope one;
    REQUIRE(global_pool().size() == 1);
    geometry::cameras_from_orbit_search<float>(serial.data(), nullptr, foreground.data(), depth.data(), K.data(), n,
                                               size, size, cfg, nullptr, &cost_serial, {descriptors.data(), D});
  }
  {
    ThreadPool two(2);
    const UsePool use(two);
    REQUIRE(global_pool().size() == 2);
    geometry::cameras_from_orbit_search<float>(parallel.data(), nullptr, foreground.data(), depth.data(), K.data(), n,
                                               size, size, cfg, nullptr, &cost_parallel, {descriptors.data(), D});
  }
  CHECK(serial == parallel);
  CHECK(serial == E);
  CHECK(cost_serial == cost_parallel);
  CHECK(cost_serial != 0);  // written (the descriptor term makes it negative here)

  geometry::OrbitSearchConfig bad;
  bad.descriptor_weight = -1;
  CHECK_THROWS_WITH(geometry::cameras_from_orbit_search<float>(E.data(), nullptr, foreground.data(), depth.data(),
                                                               K.data(), n, size, size, bad),
                    Catch::Contains("descriptor weights 0.5, -1 >= 0"));
}

TEST_CASE("turntable cameras: elevation, direction and distance from silhouettes and depth", "[geometry][orbit]") {
  // Photos in order at equal azimuth steps; clockwise captures (direction -1) too. A wrong elevation of 10 degrees or
  // a wrong direction gives relative rotation errors of 10 to 180 degrees.
  for (const double elevation : {0.0, 20.0, 40.0, 60.0})
    for (const int count : {4, 8})
      for (const int direction : {1, -1}) {
        std::vector<std::pair<double, double>> orbit;
        for (int i = 0; i < count; ++i) orbit.push_back({elevation, 30 + direction * 360.0 * i / count});
        const Views v = render_views(5, orbit, 48);
        std::vector<float> E(static_cast<std::size_t>(12 * v.n));
        const geometry::TurntableResult r = geometry::cameras_from_turntable<float>(
            E.data(), v.images.data(), v.foreground.data(), v.depth.data(), v.K.data(), v.n, v.size, v.size);
        const double err = mean_relative_error(E, v.w2c, v.n);
        INFO(count << " views at elevation " << elevation << ", direction " << direction << ": found elevation "
                   << r.elevation_deg << ", direction " << r.direction << ", relative rotation error " << err << " deg");
        CHECK(r.direction == direction);
        CHECK(std::abs(r.elevation_deg - elevation) < 2.0);
        CHECK(err < 2.0);
        for (int i = 0; i < 12; ++i) CHECK(E[static_cast<std::size_t>(i)] == static_cast<float>(identity_w2c[i]));
      }
}
