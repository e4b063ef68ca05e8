#include <catch2/catch.hpp>

#include <cmath>
#include <cstring>
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
  ViewParams<double> cam;
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
    // The camera gradient starts from the checker's junk, so its += contract is checked like the others.
    ViewGradParams<double> dc;
    for (int i = 0; i < 9; ++i) dc.R[i] = dR[i];
    for (int i = 0; i < 3; ++i) dc.t[i] = dt[i];
    dc.fx = dintr[0], dc.fy = dintr[1], dc.cx = dintr[2], dc.cy = dintr[3];
    project_backward_one(m.data(), q.data(), s.data(), o[0], cam, set, g, dm.data(), dq.data(), ds.data(), dop[0], dc);
    for (int i = 0; i < 9; ++i) dR[i] = dc.R[i];
    for (int i = 0; i < 3; ++i) dt[i] = dc.t[i];
    dintr[0] = dc.fx, dintr[1] = dc.fy, dintr[2] = dc.cx, dintr[3] = dc.cy;
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
  ViewParams<double> cam{{1, 0, 0, 0, 1, 0, 0, 0, 1}, {0, 0, 0}, 50, 50, 32, 32, 64, 64};
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

namespace {
// A rotated, off-centre 80 x 60 camera 4 units from the origin: the lane tests' Gaussians straddle its frustum.
template <class T>
ViewParams<T> lanes_camera() {
  ViewParams<T> cam;
  const double a = 0.3, c = std::cos(a), si = std::sin(a);
  const double R[9] = {c, -si, 0, si, c, 0.1, 0, -0.1, 1};
  for (int i = 0; i < 9; ++i) cam.R[i] = T(R[i]);
  cam.t[0] = T(0.1), cam.t[1] = T(-0.2), cam.t[2] = T(4);
  cam.fx = T(90), cam.fy = T(85), cam.cx = T(40.3), cam.cy = T(29.7), cam.width = T(80), cam.height = T(60);
  return cam;
}
}  // namespace

TEMPLATE_TEST_CASE("project: batch lanes are bit-identical to project_forward_one", "[raster][project]", float, double) {
  using T = TestType;
  using V = simd::batch<T>;
  constexpr int L = int(V::size);
  std::mt19937 rng(23);
  std::uniform_real_distribution<double> uni(-1, 1), u01(0, 1);
  std::normal_distribution<double> normal;
  const ViewParams<T> cam = lanes_camera<T>();
  long visible = 0, culled = 0;
  for (int trial = 0; trial < 6400 / L; ++trial) {  // 6400 Gaussians for any lane count
    ProjectSettings<T> set;
    set.antialiased = trial % 2 == 1;
    alignas(64) T m[3][L], q[4][L], s[3][L], o[L];
    for (int l = 0; l < L; ++l) {
      // Inside and far outside the field of view (clamp), behind the camera, tiny to huge scales, all opacities.
      const double reach = trial % 3 == 0 ? 8.0 : 1.5;
      for (int i = 0; i < 3; ++i) m[i][l] = T(reach * uni(rng));
      for (int i = 0; i < 4; ++i) q[i][l] = T(normal(rng));
      for (int i = 0; i < 3; ++i) s[i][l] = T(std::pow(10.0, -5 + 7 * u01(rng)));
      o[l] = T(u01(rng));
    }
    if (trial == 7) m[2][0] = T(-3.99), m[2][L - 1] = T(-4);  // just beyond the near plane, behind the camera
    if (trial == 8) o[0] = T(0), o[L - 1] = T(1);
    V mv[3], qv[4], sv[3];
    for (int i = 0; i < 3; ++i) mv[i] = simd::lane_load<V>(m[i]), sv[i] = simd::lane_load<V>(s[i]);
    for (int i = 0; i < 4; ++i) qv[i] = simd::lane_load<V>(q[i]);
    ProjectionLanes<V> pl;
    const auto mask = project_forward_lanes<V, T>(mv, qv, sv, simd::lane_load<V>(o), cam, set, pl);
    alignas(64) T f[10][L];
    const V* fields[10] = {&pl.u, &pl.v, &pl.z, &pl.cov[0], &pl.cov[1], &pl.cov[2], &pl.conic[0], &pl.conic[1],
                           &pl.conic[2], &pl.opacity};
    for (int i = 0; i < 10; ++i) simd::lane_store(f[i], *fields[i]);
    alignas(64) T vis[L];
    simd::lane_store(vis, simd::lane_select(mask, V(T(1)), V(T(0))));
    for (int l = 0; l < L; ++l) {
      const T ml[3] = {m[0][l], m[1][l], m[2][l]}, ql[4] = {q[0][l], q[1][l], q[2][l], q[3][l]};
      const T sl[3] = {s[0][l], s[1][l], s[2][l]};
      Projection<T> p;
      const bool one = project_forward_one(ml, ql, sl, o[l], cam, set, p);
      REQUIRE(one == (vis[l] != T(0)));
      visible += one, culled += !one;
      if (!one) continue;
      const T expect[10] = {p.u, p.v, p.z, p.cov[0], p.cov[1], p.cov[2], p.conic[0], p.conic[1], p.conic[2], p.opacity};
      for (int i = 0; i < 10; ++i) {
        INFO("trial " << trial << " lane " << l << " field " << i << ": " << expect[i] << " vs " << f[i][l]);
        CHECK(std::memcmp(&expect[i], &f[i][l], sizeof(T)) == 0);
      }
    }
  }
  CHECK(visible > 1000);
  CHECK(culled > 100);
}

TEMPLATE_TEST_CASE("project: backward batch lanes are bit-identical to project_backward_one", "[raster][project]", float,
                   double) {
  using T = TestType;
  using V = simd::batch<T>;
  constexpr int L = int(V::size);
  std::mt19937 rng(31);
  std::uniform_real_distribution<double> uni(-1, 1), u01(0, 1);
  std::normal_distribution<double> normal;
  const ViewParams<T> cam = lanes_camera<T>();
  long compared = 0, off_screen = 0;
  for (int trial = 0; trial < 3200 / L; ++trial) {  // 3200 Gaussians for any lane count
    ProjectSettings<T> set;
    set.antialiased = trial % 2 == 1;
    // Inputs, cotangents and the junk the gradients start from (the += contract), one column per lane.
    alignas(64) T m[3][L], q[4][L], s[3][L], o[L], g[7][L], junk[29][L];
    for (int l = 0; l < L; ++l) {
      const double reach = trial % 3 == 0 ? 8.0 : 1.5;  // far outside the field of view: the clamp is active
      for (int i = 0; i < 3; ++i) m[i][l] = T(reach * uni(rng));
      for (int i = 0; i < 4; ++i) q[i][l] = T(normal(rng));
      for (int i = 0; i < 3; ++i) s[i][l] = T(std::pow(10.0, -5 + 7 * u01(rng)));
      o[l] = T(u01(rng));
      for (auto& v : g) v[l] = T(normal(rng));
      for (auto& v : junk) v[l] = T(normal(rng));
    }
    auto load = [](const T* p) { return simd::lane_load<V>(p); };
    V mv[3], qv[4], sv[3], dm[3], dq[4], ds[3];
    for (int i = 0; i < 3; ++i) mv[i] = load(m[i]), sv[i] = load(s[i]), dm[i] = load(junk[i]), ds[i] = load(junk[3 + i]);
    for (int i = 0; i < 4; ++i) qv[i] = load(q[i]), dq[i] = load(junk[6 + i]);
    V dopacity = load(junk[10]);
    ViewGradParams<V> dcam;
    for (int i = 0; i < 9; ++i) dcam.R[i] = load(junk[11 + i]);
    for (int i = 0; i < 3; ++i) dcam.t[i] = load(junk[20 + i]);
    dcam.fx = load(junk[23]), dcam.fy = load(junk[24]), dcam.cx = load(junk[25]), dcam.cy = load(junk[26]);
    ProjectionGrad<V> gv;
    gv.u = load(g[0]), gv.v = load(g[1]), gv.z = load(g[2]), gv.opacity = load(g[6]);
    for (int i = 0; i < 3; ++i) gv.conic[i] = load(g[3 + i]);
    project_backward_lanes<V, T>(mv, qv, sv, load(o), cam, set, gv, dm, dq, ds, dopacity, dcam);
    // Lane results in the order of the scalar ones below.
    const V* fields[27] = {&dm[0], &dm[1], &dm[2], &ds[0], &ds[1], &ds[2], &dq[0], &dq[1], &dq[2], &dq[3], &dopacity,
                           &dcam.R[0], &dcam.R[1], &dcam.R[2], &dcam.R[3], &dcam.R[4], &dcam.R[5], &dcam.R[6],
                           &dcam.R[7], &dcam.R[8], &dcam.t[0], &dcam.t[1], &dcam.t[2], &dcam.fx, &dcam.fy, &dcam.cx,
                           &dcam.cy};
    alignas(64) T f[27][L];
    for (int i = 0; i < 27; ++i) simd::lane_store(f[i], *fields[i]);
    for (int l = 0; l < L; ++l) {
      const T ml[3] = {m[0][l], m[1][l], m[2][l]}, ql[4] = {q[0][l], q[1][l], q[2][l], q[3][l]};
      const T sl[3] = {s[0][l], s[1][l], s[2][l]};
      Projection<T> p;
      if (!project_forward_one(ml, ql, sl, o[l], cam, set, p)) continue;  // the backward runs for visible Gaussians
      T dml[3], dql[4], dsl[3], dol = junk[10][l];
      for (int i = 0; i < 3; ++i) dml[i] = junk[i][l], dsl[i] = junk[3 + i][l];
      for (int i = 0; i < 4; ++i) dql[i] = junk[6 + i][l];
      ViewGradParams<T> dc;
      for (int i = 0; i < 9; ++i) dc.R[i] = junk[11 + i][l];
      for (int i = 0; i < 3; ++i) dc.t[i] = junk[20 + i][l];
      dc.fx = junk[23][l], dc.fy = junk[24][l], dc.cx = junk[25][l], dc.cy = junk[26][l];
      ProjectionGrad<T> gl;
      gl.u = g[0][l], gl.v = g[1][l], gl.z = g[2][l], gl.opacity = g[6][l];
      for (int i = 0; i < 3; ++i) gl.conic[i] = g[3 + i][l];
      project_backward_one(ml, ql, sl, o[l], cam, set, gl, dml, dql, dsl, dol, dc);
      const T expect[27] = {dml[0], dml[1], dml[2], dsl[0], dsl[1], dsl[2], dql[0], dql[1], dql[2], dql[3], dol,
                            dc.R[0], dc.R[1], dc.R[2], dc.R[3], dc.R[4], dc.R[5], dc.R[6], dc.R[7], dc.R[8],
                            dc.t[0], dc.t[1], dc.t[2], dc.fx, dc.fy, dc.cx, dc.cy};
      ++compared;
      off_screen += p.u < 0 || p.u > cam.width || p.v < 0 || p.v > cam.height;
      for (int i = 0; i < 27; ++i) {
        INFO("trial " << trial << " lane " << l << " field " << i << ": " << expect[i] << " vs " << f[i][l]);
        CHECK(std::memcmp(&expect[i], &f[i][l], sizeof(T)) == 0);
      }
    }
  }
  CHECK(compared > 500);
  CHECK(off_screen > 20);  // many beyond the 1.3x field-of-view clamp
}
