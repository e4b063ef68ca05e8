#include <catch2/catch.hpp>

#include <random>
#include <vector>

#include "flexsplat/raster/project.hpp"
#include "flexsplat/testing/gradcheck.hpp"

using namespace flexsplat;
using namespace flexsplat::raster;

namespace {

// Checks every input of project_forward_one (Gaussian and camera) against central differences.
void check_projection(const double mean[3], bool antialiased, unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> normal;
  std::vector<double> m(mean, mean + 3), q(4), s(3), o(1, 0.7);
  for (auto& v : q) v = normal(rng);
  s = {0.05, 0.2, 0.1};
  CameraParams<double> cam;
  const double a = 0.2, c = std::cos(a), si = std::sin(a);
  const double R[9] = {c, 0, si, 0, 1, 0, -si, 0, c};
  std::copy(R, R + 9, cam.R);
  cam.t[0] = 0.1, cam.t[1] = -0.2, cam.t[2] = 3.0;
  cam.fx = 60, cam.fy = 55, cam.cx = 31, cam.cy = 22, cam.width = 64, cam.height = 48;
  ProjectSettings<double> set;
  set.antialiased = antialiased;
  std::vector<double> R_v(cam.R, cam.R + 9), t_v(cam.t, cam.t + 3), intr{cam.fx, cam.fy, cam.cx, cam.cy};
  std::vector<double> dm(3), dq(4), ds(3), dop(1), dR(9), dt(3), dintr(4);
  auto sync = [&] {
    std::copy(R_v.begin(), R_v.end(), cam.R);
    std::copy(t_v.begin(), t_v.end(), cam.t);
    cam.fx = intr[0], cam.fy = intr[1], cam.cx = intr[2], cam.cy = intr[3];
  };
  auto forward = [&](std::span<double> out) {
    sync();
    Projection<double> p;
    REQUIRE(project_forward_one(m.data(), q.data(), s.data(), o[0], cam, set, p));
    const double vals[8] = {p.u, p.v, p.z, p.conic[0], p.conic[1], p.conic[2], p.opacity, 0.0};
    std::copy(vals, vals + 7, out.begin());
  };
  auto backward = [&](std::span<const double> d) {
    sync();
    ProjectionGrad<double> g;
    g.u = d[0], g.v = d[1], g.z = d[2], g.conic[0] = d[3], g.conic[1] = d[4], g.conic[2] = d[5], g.opacity = d[6];
    CameraGradParams<double> dc;
    project_backward_one(m.data(), q.data(), s.data(), o[0], cam, set, g, dm.data(), dq.data(), ds.data(), dop[0], dc);
    for (int i = 0; i < 9; ++i) dR[i] += dc.R[i];
    for (int i = 0; i < 3; ++i) dt[i] += dc.t[i];
    dintr[0] += dc.fx, dintr[1] += dc.fy, dintr[2] += dc.cx, dintr[3] += dc.cy;
  };
  testing::GradCheckOptions opts;
  opts.abs_tol = 1e-6;
  auto result = testing::check_gradients({{"means", m, dm}, {"quats", q, dq}, {"scales", s, ds}, {"opacity", o, dop},
                                          {"R", R_v, dR}, {"t", t_v, dt}, {"intrinsics", intr, dintr}},
                                         7, forward, backward, opts);
  INFO(result.summary());
  CHECK(result.ok());
}

}  // namespace

TEST_CASE("project: float64 gradient check, Gaussian and camera, inside the field of view", "[raster][project]") {
  const double m[3] = {0.2, -0.1, 0.4};
  check_projection(m, false, 1);
  check_projection(m, true, 2);
}

TEST_CASE("project: float64 gradient check with the 1.3x field-of-view clamp active", "[raster][project]") {
  const double right[3] = {4.5, 0.1, 0.0};   // x/z beyond the clamp on the right
  const double up[3] = {0.0, -4.0, 0.2};     // y/z beyond the clamp at the top
  const double left_down[3] = {-5.0, 4.5, 0.5};
  check_projection(right, false, 3);
  check_projection(up, true, 4);
  check_projection(left_down, false, 5);
}

TEST_CASE("project: culls behind the near plane and far plane, keeps a Gaussian on the image", "[raster][project]") {
  CameraParams<double> cam{{1, 0, 0, 0, 1, 0, 0, 0, 1}, {0, 0, 0}, 50, 50, 32, 32, 64, 64};
  ProjectSettings<double> set;
  const double q[4] = {1, 0, 0, 0}, s[3] = {0.1, 0.1, 0.1};
  Projection<double> p;
  const double behind[3] = {0, 0, -1}, at_centre[3] = {0, 0, 0}, below_near[3] = {0, 0, 0.005};
  const double front[3] = {0, 0, 2};
  CHECK_FALSE(project_forward_one(behind, q, s, 0.5, cam, set, p));
  CHECK_FALSE(project_forward_one(at_centre, q, s, 0.5, cam, set, p));
  CHECK_FALSE(project_forward_one(below_near, q, s, 0.5, cam, set, p));
  REQUIRE(project_forward_one(front, q, s, 0.5, cam, set, p));
  CHECK(p.u == Approx(32));
  CHECK(p.v == Approx(32));
  CHECK(p.z == Approx(2));
  // isotropic: cov2d = (fx s / z)^2 + eps2d
  CHECK(p.cov[0] == Approx(2.5 * 2.5 + 0.3));
  CHECK(p.conic[0] == Approx(1.0 / (2.5 * 2.5 + 0.3)));
  CHECK_FALSE(project_forward_one(front, q, s, 0.5 / 255, cam, set, p));  // can never reach alpha 1/255
}
