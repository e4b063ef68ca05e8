#include <catch2/catch.hpp>

#include <cmath>
#include <limits>
#include <numbers>
#include <random>
#include <vector>

#include "flexsplat/loss/geometry.hpp"
#include "flexsplat/testing/gradcheck.hpp"
#include "loss_test_util.hpp"

using namespace flexsplat;
using loss_test::uniform;


TEST_CASE("camera loss: VGGT's stage weighting and part weights by hand", "[loss][camera]") {
  // Two stages, one valid frame of two: every error 0.1 in stage 0 and 0.2 in stage 1.
  std::vector<double> gt(18, 0.0), s0(18, 0.1), s1(18, 0.2);
  s1[9] = 500;  // the invalid frame's values do not count
  const std::uint8_t valid[2] = {1, 0};
  loss::CameraLossConfig c;
  const auto parts = loss::camera_loss_forward<double>({s0.data(), s1.data()}, gt.data(), valid, 2, c);
  const double part = (0.6 * 0.1 + 1.0 * 0.2) / 2;
  CHECK(parts.translation == Approx(part).epsilon(1e-14));
  CHECK(parts.rotation == Approx(part).epsilon(1e-14));
  CHECK(parts.fov == Approx(part).epsilon(1e-14));
  CHECK(parts.total == Approx(2.5 * part).epsilon(1e-14));
  // Translation terms clamp at 100; Huber below delta is 0.5 x^2 / delta.
  s1[0] = 400;
  const auto clamped = loss::camera_loss_forward<double>({s1.data()}, gt.data(), valid, 2, c);
  CHECK(clamped.translation == Approx((100 + 0.2 + 0.2) / 3).epsilon(1e-14));
  c.type = loss::CameraLossType::huber;
  const auto huber = loss::camera_loss_forward<double>({s0.data()}, gt.data(), valid, 2, c);
  CHECK(huber.rotation == Approx(0.5 * 0.01).epsilon(1e-14));
  const std::uint8_t none[2] = {0, 0};
  CHECK(loss::camera_loss_forward<double>({s0.data()}, gt.data(), none, 2, c).total == 0.0);
}

TEST_CASE("camera loss: gradient check (L1 with a clamped term, Huber)", "[loss][camera][gradcheck]") {
  for (auto type : {loss::CameraLossType::l1, loss::CameraLossType::huber}) {
    const index_t frames = 3;
    auto gt = uniform(27, 1, -1, 1), a = uniform(27, 2, -2, 2), b = uniform(27, 3, -2, 2), c3 = uniform(27, 4, -2, 2);
    a[1] = 150;  // a clamped translation term
    const std::uint8_t valid[3] = {1, 0, 1};
    loss::CameraLossConfig c;
    c.type = type;
    c.huber_delta = 0.7;
    std::vector<double> da(27), db(27), dc(27);
    const auto r = testing::check_gradients(
        {{"stage0", a, da}, {"stage1", b, db}, {"stage2", c3, dc}}, 1,
        [&](std::span<double> out) {
          out[0] = loss::camera_loss_forward<double>({a.data(), b.data(), c3.data()}, gt.data(), valid, frames, c).total;
        },
        [&](std::span<const double> d) {
          loss::camera_loss_backward<double>({da.data(), db.data(), dc.data()}, d[0], {a.data(), b.data(), c3.data()},
                                             gt.data(), valid, frames, c);
        });
    INFO(r.summary());
    CHECK(r.ok());
  }
}

TEST_CASE("relative pose loss: blind to the world frame, the chordal angle and translation by hand", "[loss][camera]") {
  // Ground truth: camera 0 the identity, camera 1 turned by 60 degrees about y and moved.
  const double a = std::numbers::pi / 3, ca = std::cos(a), sa = std::sin(a);
  const std::vector<double> gt = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, ca, 0, sa, 0.5, 0, 1, 0, -0.2, -sa, 0, ca, 1.5};
  // The same cameras after a world motion x' = Rw x + tw: w2c' = [R Rw^T | t - R Rw^T tw].
  const double b = 0.4, cb = std::cos(b), sb = std::sin(b);
  const double Rw[9] = {cb, -sb, 0, sb, cb, 0, 0, 0, 1}, tw[3] = {0.3, -0.7, 2.0};
  std::vector<double> moved(24);
  for (int v = 0; v < 2; ++v)
    for (int r = 0; r < 3; ++r) {
      double t = gt[12 * v + 4 * r + 3];
      for (int c = 0; c < 3; ++c) {
        double s = 0;
        for (int k = 0; k < 3; ++k) s += gt[12 * v + 4 * r + k] * Rw[3 * c + k];
        moved[12 * v + 4 * r + c] = s;
      }
      for (int c = 0; c < 3; ++c) t -= moved[12 * v + 4 * r + c] * tw[c];
      moved[12 * v + 4 * r + 3] = t;
    }
  loss::CameraLossConfig c;
  const auto same = loss::relative_pose_loss_forward<double>({moved.data()}, gt.data(), 2, c);
  CHECK(same.total == Approx(0.0).margin(1e-9));
  // Camera 1 predicted at 90 degrees instead of 60, same centre offset: both ordered pairs are 30 degrees off, whose
  // chordal distance is 2 sqrt(2) sin(15 degrees) (smoothed by eps).
  std::vector<double> pred = gt;
  const double p = std::numbers::pi / 2;
  pred[12] = std::cos(p), pred[14] = std::sin(p), pred[20] = -std::sin(p), pred[22] = std::cos(p);
  const auto parts = loss::relative_pose_loss_forward<double>({pred.data()}, gt.data(), 2, c);
  const double chord = 2 * std::sqrt(2.0) * std::sin(std::numbers::pi / 12);
  CHECK(parts.rotation == Approx(std::sqrt(chord * chord + 1e-12) - loss::relative_pose_eps).epsilon(1e-12));
  // Pair (1, 0) has the translation t_1 (off by nothing); pair (0, 1) has -R_1^T t_1, which turns with R_1.
  double r0[12], g0[12];
  relative_w2c(r0, pred.data(), pred.data() + 12);
  relative_w2c(g0, gt.data(), gt.data() + 12);
  const double lt = (std::abs(r0[3] - g0[3]) + std::abs(r0[7] - g0[7]) + std::abs(r0[11] - g0[11])) / 6;
  CHECK(parts.translation == Approx(lt).epsilon(1e-12));
  CHECK(parts.total == Approx(parts.rotation + parts.translation).epsilon(1e-14));
  CHECK(loss::relative_pose_loss_forward<double>({pred.data()}, gt.data(), 1, c).total == 0.0);
  // A translation entry off by more than translation_clamp counts as the clamp in both pairs.
  std::vector<double> far = gt;
  far[15] += 300;
  double r1[12], g1[12];
  relative_w2c(r0, far.data(), far.data() + 12);
  relative_w2c(r1, far.data() + 12, far.data());
  relative_w2c(g1, gt.data() + 12, gt.data());
  double clamped = 0;
  for (int r = 0; r < 3; ++r)
    clamped += std::min(std::abs(r0[4 * r + 3] - g0[4 * r + 3]), 100.0) +
               std::min(std::abs(r1[4 * r + 3] - g1[4 * r + 3]), 100.0);
  CHECK(clamped > 200);
  const auto far_parts = loss::relative_pose_loss_forward<double>({far.data()}, gt.data(), 2, c);
  CHECK(far_parts.translation == Approx(clamped / 6).epsilon(1e-12));
  pred[5] = std::numeric_limits<double>::quiet_NaN();
  CHECK_THROWS_WITH(loss::relative_pose_loss_forward<double>({pred.data()}, gt.data(), 2, c),
                    Catch::Contains("relative pose loss: stage 0 frame 0 entry 5"));
}

TEST_CASE("relative pose loss: gradient check over 3 views and 2 stages (L1, Huber)",
          "[loss][camera][gradcheck]") {
  for (auto type : {loss::CameraLossType::l1, loss::CameraLossType::huber}) {
    const index_t frames = 3;
    auto gt = uniform(36, 11, -1, 1), a = uniform(36, 12, -1.5, 1.5), b = uniform(36, 13, -1.5, 1.5);
    loss::CameraLossConfig c;
    c.type = type;
    c.huber_delta = 0.7;
    std::vector<double> da(36), db(36);
    const auto r = testing::check_gradients(
        {{"stage0", a, da}, {"stage1", b, db}}, 1,
        [&](std::span<double> out) {
          out[0] = loss::relative_pose_loss_forward<double>({a.data(), b.data()}, gt.data(), frames, c).total;
        },
        [&](std::span<const double> d) {
          loss::relative_pose_loss_backward<double>({da.data(), db.data()}, d[0], {a.data(), b.data()}, gt.data(),
                                                    frames, c);
        });
    INFO(r.summary());
    CHECK(r.ok());
  }
}

TEST_CASE("depth loss: conf, reg and gradient terms by hand", "[loss][depth]") {
  // One 1x3 image: errors (pred - gt) = 1, -1, 2, confidence 2 everywhere.
  const std::vector<double> pred{2, 1, 5}, gt{1, 2, 3}, conf{2, 2, 2};
  loss::DepthLossConfig c;
  c.min_valid_pixels = 1;
  c.gradient_scales = 2;
  const auto p = loss::depth_loss_forward(pred.data(), conf.data(), gt.data(), nullptr, 1, 1, 3, c);
  CHECK(p.reg == Approx(4.0 / 3).epsilon(1e-14));
  CHECK(p.conf == Approx((1.0 * 4 * 2 - 3 * 0.2 * std::log(2.0)) / 3).epsilon(1e-14));
  // Scale 1: |(-1) - 1| + |2 - (-1)| = 5 over 3 valid pixels; scale 2 (x = 0, 2): |2 - 1| = 1 over 2 pixels.
  CHECK(p.grad == Approx((5.0 / 3 + 1.0 / 2) / 2).epsilon(1e-14));
  CHECK(p.total == Approx(p.conf + p.reg + p.grad).epsilon(1e-15));
  // Too few valid pixels: zero (VGGT skips the batch); a non-positive confidence is an error.
  c.min_valid_pixels = 100;
  CHECK(loss::depth_loss_forward(pred.data(), conf.data(), gt.data(), nullptr, 1, 1, 3, c).total == 0.0);
  const std::vector<double> bad{2, 0, 2};
  CHECK_THROWS_WITH(loss::depth_loss_forward(pred.data(), bad.data(), gt.data(), nullptr, 1, 1, 3, c),
                    Catch::Contains("pixel 1"));
}

TEST_CASE("depth loss: gradient check for depth and confidence with a mask", "[loss][depth][gradcheck]") {
  const index_t n = 2, h = 7, w = 9, total = n * h * w;
  auto pred = uniform(total, 5, 1, 3), gt = uniform(total, 6, 1, 3), conf = uniform(total, 7, 1, 3);
  pred[10] = gt[10] + 150;  // gradient terms next to this pixel are clamped
  std::vector<std::uint8_t> mask(total, 1);
  for (index_t i = 0; i < total; i += 5) mask[i] = 0;
  loss::DepthLossConfig c;
  c.min_valid_pixels = 10;
  std::vector<double> dp(total), dc(total);
  const auto r = testing::check_gradients(
      {{"depth", pred, dp}, {"conf", conf, dc}}, 1,
      [&](std::span<double> out) {
        out[0] = loss::depth_loss_forward(pred.data(), conf.data(), gt.data(), mask.data(), n, h, w, c).total;
      },
      [&](std::span<const double> d) {
        loss::depth_loss_backward(dp.data(), dc.data(), d[0], pred.data(), conf.data(), gt.data(), mask.data(), n, h, w, c);
      });
  INFO(r.summary());
  CHECK(r.ok());
}

TEST_CASE("depth shape loss: by hand, blind to each view's scale, zero below min_valid_pixels", "[loss][depth]") {
  // Two 1x3 images. Image 0: log ratios log 2, 0, 0 -> mean log(2)/3, mean |r - mean| = 4 log(2) / 9.
  // Image 1: pred = 3 gt everywhere -> 0 (a pure scale).
  const std::vector<double> gt{1, 2, 3, 1, 2, 3}, pred{2, 2, 3, 3, 6, 9};
  const double l0 = 4 * std::log(2.0) / 9;
  CHECK(loss::depth_shape_loss_forward(pred.data(), gt.data(), nullptr, 2, 1, 3, 1) == Approx(l0 / 2).epsilon(1e-14));
  // Scaling each view by its own factor changes nothing.
  std::vector<double> scaled = pred;
  for (int i = 0; i < 3; ++i) scaled[i] *= 0.25, scaled[3 + i] *= 7;
  CHECK(loss::depth_shape_loss_forward(scaled.data(), gt.data(), nullptr, 2, 1, 3, 1) == Approx(l0 / 2).epsilon(1e-13));
  // A masked pixel is left out; an image with fewer valid pixels than asked is left out of the mean.
  const std::uint8_t mask[6] = {0, 1, 1, 1, 1, 1};
  CHECK(loss::depth_shape_loss_forward(pred.data(), gt.data(), mask, 2, 1, 3, 4) == 0.0);
  CHECK(loss::depth_shape_loss_forward(pred.data(), gt.data(), mask, 2, 1, 3, 3) == Approx(0.0).margin(1e-15));
  CHECK(loss::depth_shape_loss_forward(pred.data(), gt.data(), mask, 2, 1, 3, 2) == Approx(0.0).margin(1e-15));
  CHECK(loss::depth_shape_loss_forward(pred.data(), gt.data(), nullptr, 2, 1, 3, 100) == 0.0);
  std::vector<double> bad = pred;
  bad[4] = 0;
  CHECK_THROWS_WITH(loss::depth_shape_loss_forward(bad.data(), gt.data(), nullptr, 2, 1, 3, 1), Catch::Contains("pixel 4"));
  std::vector<double> d_bad(6, 0.0);
  CHECK_THROWS_WITH(loss::depth_shape_loss_backward(d_bad.data(), 1.0, bad.data(), gt.data(), nullptr, 2, 1, 3, 1),
                    Catch::Contains("pixel 4"));
}

TEST_CASE("depth error after each view's scale: by hand, views without ground truth left out, bad depth named",
          "[loss][depth]") {
  // Four 1x3 views. 0: a constant against gt 1, 2, 4 -> scale 2, errors 1, 0, 1/2. 1: 3 gt -> scale 1/3, error 0.
  // 2: no ground truth -> left out, scale 1. 3: two valid pixels, ratios 1 and 3 -> the upper middle 3, errors 2, 0.
  const std::vector<double> gt{1, 2, 4, 1, 2, 3, 0, 0, 0, 1, 0, 3}, pred{1, 1, 1, 3, 6, 9, 5, 5, 5, 1, 5, 1};
  std::vector<double> scales(4, 0.0);
  CHECK(loss::depth_scaled_error(pred.data(), gt.data(), 4, 3, scales.data()) == Approx((0.5 + 0 + 1) / 3).epsilon(1e-14));
  CHECK(scales == std::vector<double>{2, 1.0 / 3, 1, 3});
  CHECK(loss::depth_scaled_error(pred.data(), gt.data(), 2, 3) == Approx(0.25).epsilon(1e-14));
  CHECK(loss::depth_scaled_error(pred.data() + 6, gt.data() + 6, 1, 3) == 0.0);  // nothing to measure
  std::vector<double> bad = pred;
  bad[5] = std::numeric_limits<double>::quiet_NaN();
  CHECK_THROWS_WITH(loss::depth_scaled_error(bad.data(), gt.data(), 4, 3), Catch::Contains("pixel 5 (view 1)"));
  bad[5] = 9, bad[11] = 0;
  CHECK_THROWS_WITH(loss::depth_scaled_error(bad.data(), gt.data(), 4, 3), Catch::Contains("pixel 11 (view 3)"));
}

TEST_CASE("depth shape loss: gradient check with a mask", "[loss][depth][gradcheck]") {
  const index_t n = 3, h = 6, w = 7, total = n * h * w;
  auto pred = uniform(total, 11, 1, 3), gt = uniform(total, 12, 1, 3);
  std::vector<std::uint8_t> mask(total, 1);
  for (index_t i = 0; i < total; i += 4) mask[i] = 0;
  for (index_t i = 2 * h * w; i < total; ++i) mask[i] = i % 9 == 0;  // image 2: too few valid pixels, left out
  std::vector<double> dp(total);
  const auto r = testing::check_gradients(
      {{"depth", pred, dp}}, 1,
      [&](std::span<double> out) { out[0] = loss::depth_shape_loss_forward(pred.data(), gt.data(), mask.data(), n, h, w, 10); },
      [&](std::span<const double> d) {
        loss::depth_shape_loss_backward(dp.data(), d[0], pred.data(), gt.data(), mask.data(), n, h, w, 10);
      });
  INFO(r.summary());
  CHECK(r.ok());
  std::vector<double> fresh(total, 0.0);
  loss::depth_shape_loss_backward(fresh.data(), 1.0, pred.data(), gt.data(), mask.data(), n, h, w, 10);
  for (index_t i = 2 * h * w; i < total; ++i) CHECK(fresh[static_cast<std::size_t>(i)] == 0.0);
  CHECK(std::any_of(fresh.begin(), fresh.begin() + 2 * h * w, [](double g) { return g != 0.0; }));
}

TEST_CASE("point loss: Euclidean conf and reg terms and the background term by hand", "[loss][points]") {
  // Two valid pixels with errors (3, 4, 0) -> 5 and (0, 0, 0) -> 0, confidence 2 and 3; one background pixel at 1.5.
  const std::vector<double> pred{4, 4, 1, 1, 2, 3, 9, 9, 9}, gt{1, 0, 1, 1, 2, 3, 0, 0, 0}, conf{2, 3, 1.5};
  const std::uint8_t mask[3] = {1, 1, 0};
  loss::PointLossConfig c;
  c.min_valid_pixels = 2;
  const auto p = loss::point_loss_forward(pred.data(), conf.data(), gt.data(), mask, 3, c);
  CHECK(p.reg == Approx(2.5).epsilon(1e-14));
  CHECK(p.conf == Approx((5.0 * 2 - 0.2 * std::log(2.0) - 0.2 * std::log(3.0)) / 2).epsilon(1e-14));
  CHECK(p.background == Approx(0.1 * 0.5).epsilon(1e-14));
  CHECK(p.total == Approx(p.conf + p.reg + p.background).epsilon(1e-15));
  c.min_valid_pixels = 3;
  CHECK(loss::point_loss_forward(pred.data(), conf.data(), gt.data(), mask, 3, c).total == 0.0);
  const std::vector<double> bad{2, -1, 1.5};
  c.min_valid_pixels = 1;
  CHECK_THROWS_WITH(loss::point_loss_forward(pred.data(), bad.data(), gt.data(), mask, 3, c), Catch::Contains("pixel 1"));
}

TEST_CASE("point loss: gradient check for points and confidence with a mask", "[loss][points][gradcheck]") {
  const index_t n = 40;
  auto pred = uniform(3 * n, 8, -2, 2), gt = uniform(3 * n, 9, -2, 2), conf = uniform(n, 10, 1, 3);
  std::vector<std::uint8_t> mask(n, 1);
  for (index_t i = 0; i < n; i += 4) mask[i] = 0;
  loss::PointLossConfig c;
  c.min_valid_pixels = 10;
  std::vector<double> dp(pred.size()), dc(conf.size());
  const auto r = testing::check_gradients(
      {{"points", pred, dp}, {"conf", conf, dc}}, 1,
      [&](std::span<double> out) {
        out[0] = loss::point_loss_forward(pred.data(), conf.data(), gt.data(), mask.data(), n, c).total;
      },
      [&](std::span<const double> d) {
        loss::point_loss_backward(dp.data(), dc.data(), d[0], pred.data(), conf.data(), gt.data(), mask.data(), n, c);
      });
  INFO(r.summary());
  CHECK(r.ok());
}
