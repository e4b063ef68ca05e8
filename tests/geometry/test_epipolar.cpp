#include <catch2/catch.hpp>

#include <cmath>
#include <random>
#include <vector>

#include "flexsplat/core/camera.hpp"
#include "flexsplat/geometry/epipolar.hpp"
#include "flexsplat/model/frames.hpp"

using namespace flexsplat;

namespace {
// Four cameras around the origin (look_at), 60 x 60 pixels, f = 70; their world-to-camera [4, 3, 4].
std::vector<Camera> ring() {
  std::vector<Camera> cams;
  const glm::dmat3 K = intrinsics_from_fov(60, 60, 46);
  for (const auto& [el, az] : std::vector<std::pair<double, double>>{{0.35, 0.0}, {0.6, 1.1}, {0.2, 2.3}, {0.7, 3.9}})
    cams.push_back(look_at(orbit_eye(el, az, 3.0), glm::dvec3(0.0), 60, 60, K));
  return cams;
}

std::vector<double> w2c_of(const std::vector<Camera>& cams) {
  std::vector<double> E(12 * cams.size());
  for (std::size_t i = 0; i < cams.size(); ++i) camera_arrays(cams[i], static_cast<double*>(nullptr), E.data() + 12 * i);
  return E;
}

double mean_error(const std::vector<double>& E, const std::vector<double>& gt, int n) {
  double e = 0;
  for (int v = 1; v < n; ++v) e += model::relative_rotation_error_deg(E.data(), E.data() + 12 * v, gt.data(), gt.data() + 12 * v);
  return e / (n - 1);
}

glm::dvec2 normalised(const Camera& c, glm::dvec3 X) {
  const glm::dvec3 p = c.to_camera(X);
  return {p.x / p.z, p.y / p.z};
}
}  // namespace

TEST_CASE("epipolar refinement: cameras turned by 6 degrees return to the truth through matches, 30 % of them wrong",
          "[geometry][epipolar]") {
  const std::vector<Camera> cams = ring();
  const int n = static_cast<int>(cams.size());
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> u(-0.6, 0.6);
  std::vector<geometry::EpipolarPair> pairs;
  for (int a = 0; a < n; ++a)
    for (int b = a + 1; b < n; ++b) {
      geometry::EpipolarPair pr;
      pr.a = a, pr.b = b, pr.focal = cams[0].K[0][0];
      for (int k = 0; k < 200; ++k) {
        const glm::dvec3 X(u(rng), u(rng), u(rng));
        pr.xa.push_back(normalised(cams[static_cast<std::size_t>(a)], X));
        // A wrong match: another point's image.
        const glm::dvec3 Y = k % 10 < 3 ? glm::dvec3(u(rng), u(rng), u(rng)) : X;
        pr.xb.push_back(normalised(cams[static_cast<std::size_t>(b)], Y));
      }
      pairs.push_back(std::move(pr));
    }
  const std::vector<double> gt = w2c_of(cams);
  // The true cameras explain every right match exactly.
  std::size_t exact = 0;
  for (const auto& pr : pairs)
    for (double e : geometry::epipolar_errors_px(gt.data(), pr)) exact += e < 1e-9;
  CHECK(exact >= static_cast<std::size_t>(0.7 * 200 * 6));
  // Views 2..4 turned by 6 degrees about assorted axes through their centres, view 2's centre moved too.
  std::vector<Camera> start = cams;
  const double turn = 6 * std::numbers::pi / 180;
  for (int v = 1; v < n; ++v) {
    const glm::dvec3 C = start[static_cast<std::size_t>(v)].centre();
    const glm::dvec3 axis = glm::normalize(glm::dvec3(1.0, 0.5 * v, -0.3 * v));
    const double c = std::cos(turn), s = std::sin(turn);
    const glm::dmat3 Kx(0, axis.z, -axis.y, -axis.z, 0, axis.x, axis.y, -axis.x, 0);
    const glm::dmat3 Rot = glm::dmat3(1.0) + s * Kx + (1 - c) * Kx * Kx;
    start[static_cast<std::size_t>(v)].R = Rot * start[static_cast<std::size_t>(v)].R;
    start[static_cast<std::size_t>(v)].t = -(start[static_cast<std::size_t>(v)].R * (v == 2 ? C + glm::dvec3(0.1, -0.1, 0.05) : C));
  }
  std::vector<double> E = w2c_of(start);
  const std::vector<double> first(E.begin(), E.begin() + 12);
  const double before = mean_error(E, gt, n), cost_before = geometry::epipolar_cost(E.data(), pairs, n, 1.0);
  geometry::refine_cameras_epipolar(E.data(), pairs, n);
  const double after = mean_error(E, gt, n), cost_after = geometry::epipolar_cost(E.data(), pairs, n, 1.0);
  INFO("rotation error " << before << " -> " << after << " deg, cost " << cost_before << " -> " << cost_after);
  CHECK(before > 5);
  CHECK(after < 0.5);
  CHECK(cost_after < cost_before);
  CHECK(std::vector<double>(E.begin(), E.begin() + 12) == first);  // the first view is the gauge
  // View 2's centre keeps its distance from view 1's (the scale).
  const double K9[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1};
  const Camera c0 = camera_from_arrays(K9, E.data(), 1, 1), c1 = camera_from_arrays(K9, E.data() + 12, 1, 1);
  CHECK(glm::length(c1.centre() - c0.centre()) == Approx(glm::length(start[1].centre() - start[0].centre())).epsilon(1e-9));
}

TEST_CASE("epipolar matches: mutual nearest descriptors between object pixels, in normalised coordinates",
          "[geometry][epipolar]") {
  // Two 4 x 5 views; view 1's pixel q carries the descriptor of view 0's pixel (q + 7) mod 20, so every pixel has its
  // one mutual partner; view 0's pixel 3 is background, and the partner of view 0's pixel 5 has a descriptor of zero.
  const index_t h = 4, w = 5, px = h * w, dim = 20;
  std::vector<float> fg(2 * px, 1.f), desc(2 * px * dim, 0.f), K(18, 0.f);
  for (int v = 0; v < 2; ++v) {
    K[9 * v + 0] = 10.f, K[9 * v + 4] = 20.f, K[9 * v + 2] = 2.f, K[9 * v + 5] = 1.5f, K[9 * v + 8] = 1.f;
  }
  fg[3] = 0.2f;
  for (index_t p = 0; p < px; ++p) desc[static_cast<std::size_t>(p * dim + p)] = 1.f;  // view 0: one-hot
  const index_t blank = (5 + px - 7) % px;  // view 1's pixel whose partner would be view 0's pixel 5
  for (index_t q = 0; q < px; ++q)
    if (q != blank) desc[static_cast<std::size_t>((px + q) * dim + (q + 7) % px)] = 2.f;  // any length: unit in the match
  const std::vector<geometry::EpipolarPair> pairs =
      geometry::epipolar_matches(fg.data(), desc.data(), dim, K.data(), 2, h, w);
  REQUIRE(pairs.size() == 1);
  const geometry::EpipolarPair& pr = pairs[0];
  CHECK(pr.a == 0);
  CHECK(pr.b == 1);
  CHECK(pr.focal == Approx(15.0));
  REQUIRE(pr.xa.size() == static_cast<std::size_t>(px - 2));  // pixel 3 (background) and pixel 5 (no partner) out
  for (std::size_t m = 0; m < pr.xa.size(); ++m) {
    const int p = static_cast<int>(std::lround(pr.xa[m].x * 10 + 2)) + w * static_cast<int>(std::lround(pr.xa[m].y * 20 + 1.5));
    const int q = static_cast<int>(std::lround(pr.xb[m].x * 10 + 2)) + w * static_cast<int>(std::lround(pr.xb[m].y * 20 + 1.5));
    CHECK(p == (q + 7) % px);
    CHECK(p != 3);
    CHECK(p != 5);
  }
  // Refused: a focal length of zero, named by view.
  K[9] = 0.f;
  CHECK_THROWS_WITH(geometry::epipolar_matches(fg.data(), desc.data(), dim, K.data(), 2, h, w),
                    Catch::Contains("view 1 has intrinsics fx 0"));
}

TEST_CASE("epipolar refinement refuses bad input and leaves one view or coincident centres alone", "[geometry][epipolar]") {
  std::vector<double> E(24, 0.0);
  for (int v = 0; v < 2; ++v) E[12 * v + 0] = E[12 * v + 5] = E[12 * v + 10] = 1.0;
  const std::vector<double> same = E;
  geometry::refine_cameras_epipolar(E.data(), {}, 2);  // both centres at the origin: no baseline
  CHECK(E == same);
  geometry::refine_cameras_epipolar(E.data(), {}, 1);
  CHECK(E == same);
  geometry::EpipolarRefineConfig bad;
  bad.scales_px = {};
  CHECK_THROWS_WITH(geometry::refine_cameras_epipolar(E.data(), {}, 2, bad), Catch::Contains("invalid config"));
  geometry::EpipolarPair off;
  off.a = 0, off.b = 2;
  CHECK_THROWS_WITH(geometry::refine_cameras_epipolar(E.data(), {off}, 2), Catch::Contains("pair (0, 2) does not fit 2 views"));
  E[7] = std::nan("");
  CHECK_THROWS_WITH(geometry::refine_cameras_epipolar(E.data(), {}, 2), Catch::Contains("view 0 extrinsics[1,3]"));
}
