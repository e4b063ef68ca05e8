#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <limits>
#include <utility>
#include <vector>

#include <glm/glm.hpp>

#include "flexsplat/core/camera.hpp"

using namespace flexsplat;

TEST_CASE("look_at puts the target on the optical axis, image up along the up axis", "[core][camera]") {
  const glm::dvec3 eye(2.0, -1.0, 0.7), target(0.1, 0.2, -0.3);
  for (const glm::dvec3 up : {glm::dvec3(0, 0, 1), glm::dvec3(0.2, 1.0, 0.1)}) {
    const Camera cam = look_at(eye, target, 64, 48, intrinsics_from_fov(64, 48, 50.0), up);
    const glm::dvec3 t_cam = cam.to_camera(target);
    CHECK(std::abs(t_cam.x) < 1e-12);
    CHECK(std::abs(t_cam.y) < 1e-12);
    CHECK(t_cam.z == Approx(glm::length(target - eye)));
    const glm::dvec2 uv = cam.project(t_cam);
    CHECK(uv.x == Approx(32.0));
    CHECK(uv.y == Approx(24.0));
    CHECK(glm::length(cam.centre() - eye) < 1e-12);
    // A point further along `up` lands higher in the image (smaller v): OpenCV's y points down.
    CHECK(cam.project(cam.to_camera(target + 0.1 * up)).y < uv.y);
    const glm::dmat3 rtr = glm::transpose(cam.R) * cam.R;
    for (int c = 0; c < 3; ++c)
      for (int r = 0; r < 3; ++r) CHECK(rtr[c][r] == Approx(c == r ? 1.0 : 0.0).margin(1e-12));
    CHECK(glm::determinant(cam.R) == Approx(1.0));
  }
  CHECK_THROWS_WITH(look_at({0, 0, 2}, {0, 0, 0}, 8, 8, glm::dmat3(1.0)), Catch::Contains("parallel to the up axis"));
}

TEST_CASE("camera arrays are row-major K and [R | t] and convert back exactly", "[core][camera]") {
  Camera cam = look_at({3, 1, 0.5}, {0, 0, 0}, 320, 240, intrinsics_from_fov(320, 240, 45.0));
  cam.K[1][0] = 0.25;  // skew: K(0, 1)
  double K[9], w2c[12];
  camera_arrays(cam, K, w2c);
  CHECK(K[0] == cam.K[0][0]);
  CHECK(K[1] == 0.25);
  CHECK(K[2] == 160.0);
  CHECK(K[5] == 120.0);
  CHECK(K[8] == 1.0);
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) CHECK(w2c[4 * r + c] == cam.R[c][r]);
    CHECK(w2c[4 * r + 3] == cam.t[r]);
  }
  const Camera back = camera_from_arrays(K, w2c, 320, 240, "photo.png");
  CHECK(back.name == "photo.png");
  CHECK(back.width == 320);
  CHECK(back.height == 240);
  CHECK(back.K == cam.K);
  CHECK(back.R == cam.R);
  CHECK(back.t == cam.t);
  float Kf[9];
  camera_arrays(cam, Kf, static_cast<float*>(nullptr));
  CHECK(Kf[0] == static_cast<float>(cam.K[0][0]));
}

TEST_CASE("cameras are checked for size, finiteness and focal lengths", "[core][camera]") {
  std::vector<Camera> cams{look_at({3, 0, 1}, {0, 0, 0}, 32, 24, intrinsics_from_fov(32, 24, 45.0))};
  cams[0].name = "cam";
  CHECK_NOTHROW(check_cameras(cams, "test"));
  cams[0].K[1][1] = -1;
  CHECK_THROWS_WITH(check_cameras(cams, "test"), Catch::Contains("camera 'cam' has focal lengths"));
  cams[0].K[1][1] = 10;
  cams[0].t.y = std::numeric_limits<double>::quiet_NaN();
  CHECK_THROWS_WITH(check_cameras(cams, "test"), Catch::Contains("non-finite w2c entry"));
  cams[0].t.y = 0;
  cams[0].height = 0;
  CHECK_THROWS_WITH(check_cameras(cams, "test"), Catch::Contains("image size 32x0"));
}

TEST_CASE("relative_w2c maps camera j's coordinates to camera i's in any world frame, and its backward",
          "[core][camera]") {
  const Camera a = look_at({2.0, -1.0, 0.7}, {0, 0, 0}, 32, 32, intrinsics_from_fov(32, 32, 50.0));
  const Camera b = look_at({-0.5, 2.2, 1.3}, {0.1, 0, 0}, 32, 32, intrinsics_from_fov(32, 32, 50.0));
  double ea[12], eb[12], rel[12];
  camera_arrays(a, static_cast<double*>(nullptr), ea);
  camera_arrays(b, static_cast<double*>(nullptr), eb);
  relative_w2c(rel, ea, eb);
  // A world point seen by b, carried to a's coordinates by rel, is where a sees it.
  const glm::dvec3 x(0.3, -0.2, 0.4), xb = b.to_camera(x), xa = a.to_camera(x);
  for (int r = 0; r < 3; ++r) {
    const double y = rel[4 * r] * xb.x + rel[4 * r + 1] * xb.y + rel[4 * r + 2] * xb.z + rel[4 * r + 3];
    CHECK(y == Approx(xa[r]).margin(1e-12));
  }
  // Moving both cameras' world by one rigid motion leaves rel unchanged.
  const glm::dmat3 Rw = glm::dmat3(look_at({1, 2, 3}, {0, 0, 0}, 8, 8, glm::dmat3(1.0)).R);
  const glm::dvec3 tw(0.5, -1.0, 2.0);
  double ma[12], mb[12], rel2[12];
  for (const auto& [cam, out] : {std::pair{&a, ma}, std::pair{&b, mb}}) {
    Camera moved = *cam;  // x_cam = R (Rw^T (x' - tw)) + t for x' = Rw x + tw
    moved.R = cam->R * glm::transpose(Rw);
    moved.t = cam->t - moved.R * tw;
    camera_arrays(moved, static_cast<double*>(nullptr), out);
  }
  relative_w2c(rel2, ma, mb);
  for (int k = 0; k < 12; ++k) CHECK(rel2[k] == Approx(rel[k]).margin(1e-12));
  // Backward against central differences of a fixed linear read-out (entries of i and j perturbed freely).
  const double wout[12] = {0.3, -1.1, 0.7, 0.2, 0.9, 0.4, -0.6, -0.8, 0.5, 1.3, -0.2, 0.1};
  double di[12] = {}, dj[12] = {};
  relative_w2c_backward(di, dj, wout, ea, eb);
  auto f = [&](const double* i, const double* j) {
    double r[12], s = 0;
    relative_w2c(r, i, j);
    for (int k = 0; k < 12; ++k) s += wout[k] * r[k];
    return s;
  };
  for (int k = 0; k < 12; ++k) {
    double ip[12], im[12], jp[12], jm[12];
    std::copy(ea, ea + 12, ip), std::copy(ea, ea + 12, im), std::copy(eb, eb + 12, jp), std::copy(eb, eb + 12, jm);
    ip[k] += 1e-6, im[k] -= 1e-6, jp[k] += 1e-6, jm[k] -= 1e-6;
    CHECK(di[k] == Approx((f(ip, eb) - f(im, eb)) / 2e-6).margin(1e-8));
    CHECK(dj[k] == Approx((f(ea, jp) - f(ea, jm)) / 2e-6).margin(1e-8));
  }
}
