#include <catch2/catch.hpp>

#include <cmath>
#include <random>
#include <vector>

#include <glm/glm.hpp>

#include "flexsplat/core/camera.hpp"
#include "flexsplat/model/frames.hpp"

using namespace flexsplat;

namespace {
// A world-to-camera [3, 4] looking from `eye` at `target` (OpenCV axes, world y up).
std::vector<double> w2c_looking_at(glm::dvec3 eye, glm::dvec3 target) {
  std::vector<double> m(12);
  camera_arrays<double>(flexsplat::look_at(eye, target, 1, 1, glm::dmat3(1.0), glm::dvec3(0, 1, 0)), nullptr, m.data());
  return m;
}

std::vector<double> ring(int views, double radius, double phase) {
  std::vector<double> all;
  for (int v = 0; v < views; ++v) {
    const double a = phase + 2.0 * 3.14159265358979 * v / views;
    auto m = w2c_looking_at({radius * std::cos(a), 0.4 * radius, radius * std::sin(a)}, {0.1, 0, -0.2});
    all.insert(all.end(), m.begin(), m.end());
  }
  return all;
}
}  // namespace

TEST_CASE("align_cameras recovers a similarity between two camera sets exactly", "[model][frames]") {
  for (int views : {1, 2, 4, 7}) {
    const auto gt = ring(views, 2.5, 0.3);
    model::Similarity s;
    s.R = Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
    s.t = {0.3, -1.0, 2.0};
    s.scale = 0.37;
    auto pred = gt;
    for (int v = 0; v < views; ++v) model::transform_camera(pred.data() + 12 * v, s);  // pred = S(gt)
    const auto fit = model::align_cameras(pred.data(), gt.data(), views);               // fit ~ S^-1
    for (int v = 0; v < views; ++v) {
      std::vector<double> back(pred.begin() + 12 * v, pred.begin() + 12 * v + 12);
      model::transform_camera(back.data(), fit);
      CHECK(model::rotation_error_deg(back.data(), gt.data() + 12 * v) < 1e-5);
      CHECK((model::camera_centre(back.data()) - model::camera_centre(gt.data() + 12 * v)).norm() < 1e-9);
    }
  }
}

TEST_CASE("first_camera_frame maps the first camera to the identity and points to unit mean distance",
          "[model][frames]") {
  const int views = 3, h = 6, w = 5;
  auto cams = ring(views, 3.0, 0.0);
  std::vector<double> K;
  for (int v = 0; v < views; ++v) K.insert(K.end(), {6.0, 0, 2.5, 0, 6.0, 3.0, 0, 0, 1});
  std::vector<double> depth(views * h * w, 0.0);
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> u(2.0, 4.0);
  for (auto& d : depth) d = u(rng);
  depth[4] = 0.0;  // background samples are ignored
  depth[7] = std::nan("");
  const auto f = model::first_camera_frame(cams.data(), K.data(), depth.data(), views, h, w);
  auto first = std::vector<double>(cams.begin(), cams.begin() + 12);
  f.camera(first.data());
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 4; ++c) CHECK(first[4 * r + c] == Approx(r == c ? 1.0 : 0.0).margin(1e-12));
  // The scale is the mean distance of the points to the first camera's centre.
  double sum = 0;
  int count = 0;
  const Eigen::Vector3d c0 = model::camera_centre(cams.data());
  for (int v = 0; v < views; ++v) {
    const Eigen::Matrix4d c2w = model::to_matrix4(cams.data() + 12 * v).inverse();
    for (int y = 0; y < h; ++y)
      for (int x = 0; x < w; ++x) {
        const double z = depth[(v * h + y) * w + x];
        if (!(z > 0) || !std::isfinite(z)) continue;
        const Eigen::Vector4d p((x + 0.5 - 2.5) / 6.0 * z, (y + 0.5 - 3.0) / 6.0 * z, z, 1);
        sum += ((c2w * p).head<3>() - c0).norm();
        ++count;
      }
  }
  CHECK(f.scale == Approx(sum / count).epsilon(1e-12));
  // Relative poses survive up to the scale: the distance between camera centres shrinks by it.
  auto second = std::vector<double>(cams.begin() + 12, cams.begin() + 24);
  f.camera(second.data());
  const double before = (model::camera_centre(cams.data() + 12) - c0).norm();
  CHECK(model::camera_centre(second.data()).norm() == Approx(before / f.scale).epsilon(1e-12));
}

TEST_CASE("first_camera_frame names the problem when no depth is valid", "[model][frames]") {
  auto cams = ring(1, 3.0, 0.0);
  const std::vector<double> K{6.0, 0, 2.5, 0, 6.0, 3.0, 0, 0, 1}, depth(4, 0.0);
  CHECK_THROWS_WITH(model::first_camera_frame(cams.data(), K.data(), depth.data(), 1, 2, 2),
                    Catch::Contains("no valid depth"));
}

TEST_CASE("relative_rotation_error_deg compares camera pairs independently of each set's world frame",
          "[model][frames]") {
  const auto a = ring(3, 3.0, 0.2);
  // The same rig seen from a rotated and shifted world: every relative rotation is unchanged.
  model::Similarity s;
  s.R = Eigen::AngleAxisd(0.7, Eigen::Vector3d(0.3, 1, -0.2).normalized()).toRotationMatrix();
  s.t = Eigen::Vector3d(0.5, -1, 2);
  s.scale = 1.7;
  auto b = a;
  for (int v = 0; v < 3; ++v) model::transform_camera(b.data() + 12 * v, s);
  CHECK(model::relative_rotation_error_deg(a.data(), a.data() + 12, b.data(), b.data() + 12) == Approx(0).margin(1e-6));
  CHECK(model::rotation_error_deg(a.data(), b.data()) > 30);
  // Turning one camera by 20 degrees about its own axis changes its pairs by 20 degrees.
  auto c = a;
  const Eigen::Matrix3d turn = Eigen::AngleAxisd(20 * 3.14159265358979 / 180, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  for (int col = 0; col < 4; ++col) {
    Eigen::Vector3d x(c[12 + col], c[16 + col], c[20 + col]);
    x = turn * x;
    c[12 + col] = x(0), c[16 + col] = x(1), c[20 + col] = x(2);
  }
  CHECK(model::relative_rotation_error_deg(a.data(), a.data() + 12, c.data(), c.data() + 12) == Approx(20).epsilon(1e-9));
  CHECK(model::relative_rotation_error_deg(a.data() + 12, a.data() + 24, c.data() + 12, c.data() + 24) == Approx(20).epsilon(1e-9));
  CHECK(model::relative_rotation_error_deg(a.data(), a.data() + 24, c.data(), c.data() + 24) == Approx(0).margin(1e-6));
}
