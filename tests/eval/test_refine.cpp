#include <catch2/catch.hpp>

#include <cmath>
#include <limits>
#include <random>
#include <vector>

#include <Eigen/Geometry>

#include "flexsplat/eval/refine.hpp"
#include "flexsplat/model/frames.hpp"
#include "flexsplat/raster/render.hpp"

using namespace flexsplat;

namespace {

// A small scene: n coloured Gaussians near the origin seen by `views` cameras on a circle of radius 3 (OpenCV axes,
// world y up), rendered at 24 x 24 on white as the targets.
template <class T>
struct RefineScene {
  static constexpr index_t h = 24, w = 24;
  index_t views = 0;
  GaussianSet<T> truth;
  std::vector<T> K, w2c, images;
  model::RefineViews<T> refine_views() { return {views, h, w, images.data(), K.data(), w2c.data()}; }
};

template <class T>
RefineScene<T> refine_scene(index_t views, index_t n = 24, std::uint64_t seed = 5) {
  RefineScene<T> s;
  s.views = views;
  std::mt19937 rng(static_cast<unsigned>(seed));
  std::uniform_real_distribution<double> uni(-1.0, 1.0);
  s.truth = make_gaussian_set<T>(n, 0);
  for (index_t i = 0; i < n; ++i) {
    for (int k = 0; k < 3; ++k) {
      s.truth.means(i, k) = static_cast<T>(0.6 * uni(rng));
      s.truth.scales(i, k) = static_cast<T>(0.18 + 0.05 * uni(rng));
      s.truth.sh(i, 0, k) = static_cast<T>(1.2 * uni(rng));
    }
    s.truth.opacities(i) = static_cast<T>(0.8);
  }
  for (index_t v = 0; v < views; ++v) {
    const double a = 0.6 * static_cast<double>(v);
    const Eigen::Vector3d c(3 * std::sin(a), 0.8, -3 * std::cos(a));
    const Eigen::Vector3d f = (-c).normalized();
    const Eigen::Vector3d up(0, 1, 0);
    const Eigen::Vector3d down = (-up + up.dot(f) * f).normalized();
    const Eigen::Vector3d right = down.cross(f);
    Eigen::Matrix3d R;
    R.row(0) = right, R.row(1) = down, R.row(2) = f;
    const Eigen::Vector3d t = -R * c;
    for (int r = 0; r < 3; ++r) {
      for (int col = 0; col < 3; ++col) s.w2c.push_back(static_cast<T>(R(r, col)));
      s.w2c.push_back(static_cast<T>(t(r)));
    }
    for (T k : {T(30), T(0), T(12), T(0), T(30), T(12), T(0), T(0), T(1)}) s.K.push_back(k);
  }
  raster::RenderOptions ro;
  ro.background = {1, 1, 1};
  raster::RenderWorkspace<T> rws;
  raster::RenderOutputs<T> out;
  for (index_t v = 0; v < views; ++v) {
    raster::render_forward(s.truth, raster::view_from_arrays(s.K.data() + 9 * v, s.w2c.data() + 12 * v, 24, 24), ro, rws, out);
    for (index_t i = 0; i < out.image.size(); ++i) s.images.push_back(std::clamp(out.image.data()[i], T(0), T(1)));
  }
  return s;
}

// The truth's alpha [V, 24, 24] from every view of the scene.
std::vector<float> truth_alpha(const RefineScene<float>& s) {
  std::vector<float> alpha;
  raster::RenderOptions ro;
  raster::RenderWorkspace<float> rws;
  raster::RenderOutputs<float> out;
  for (index_t v = 0; v < s.views; ++v) {
    raster::render_forward(s.truth, raster::view_from_arrays(s.K.data() + 9 * v, s.w2c.data() + 12 * v, 24, 24), ro, rws, out);
    alpha.insert(alpha.end(), out.alpha.data(), out.alpha.data() + 24 * 24);
  }
  return alpha;
}

// The truth with jittered means, scales and colours.
template <class T>
GaussianSet<T> jittered(const GaussianSet<T>& truth, std::uint64_t seed) {
  GaussianSet<T> g = truth;
  std::mt19937 rng(static_cast<unsigned>(seed));
  std::normal_distribution<double> normal;
  for (index_t i = 0; i < g.size(); ++i)
    for (int k = 0; k < 3; ++k) {
      g.means(i, k) += static_cast<T>(0.1 * normal(rng));
      g.scales(i, k) *= static_cast<T>(1.3);
      g.sh(i, 0, k) += static_cast<T>(0.4 * normal(rng));
    }
  return g;
}

// Rotates camera v by `deg` degrees about `axis` (world frame, about its own centre).
template <class T>
void turn_camera(std::vector<T>& w2c, index_t v, const Eigen::Vector3d& axis, double deg) {
  const Eigen::Matrix3d E = Eigen::AngleAxisd(deg * 3.14159265358979323846 / 180, axis.normalized()).toRotationMatrix();
  Eigen::Matrix<double, 3, 4> M;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 4; ++c) M(r, c) = static_cast<double>(w2c[static_cast<std::size_t>(12 * v + 4 * r + c)]);
  M = (E * M).eval();
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 4; ++c) w2c[static_cast<std::size_t>(12 * v + 4 * r + c)] = static_cast<T>(M(r, c));
}

template <class T>
double turn_error(const std::vector<T>& a, const std::vector<T>& b, index_t v) {
  double A[12], B[12];
  for (int i = 0; i < 12; ++i)
    A[i] = static_cast<double>(a[static_cast<std::size_t>(12 * v + i)]), B[i] = static_cast<double>(b[static_cast<std::size_t>(12 * v + i)]);
  return model::rotation_error_deg(A, B);
}

}  // namespace

TEST_CASE("refine lowers the photometric loss of a perturbed set, deterministically", "[model][refine]") {
  auto s = refine_scene<float>(3);
  const GaussianSet<float> start = jittered(s.truth, 9);
  model::RefineConfig c;
  c.steps = 40;
  c.optimize_cameras = false;
  c.validate = false;
  c.lr_means = 3e-3;
  model::RefineWorkspace<float> ws;
  GaussianSet<float> a = start;
  const model::RefineResult r = model::refine(a, s.refine_views(), c, ws);
  CHECK(r.steps == 40);
  CHECK(r.loss_initial > 0);
  CHECK(r.loss_final < 0.5 * r.loss_initial);
  CHECK(r.extent == Approx(std::sqrt(9.0 + 0.64)).margin(0.5));
  CHECK(a.size() + r.pruned == start.size());
  // The same inputs give the same bits.
  GaussianSet<float> b = start;
  model::RefineWorkspace<float> ws2;
  const model::RefineResult r2 = model::refine(b, s.refine_views(), c, ws2);
  CHECK(r2.loss_final == r.loss_final);
  REQUIRE(b.size() == a.size());
  for (index_t i = 0; i < a.means.size(); ++i) REQUIRE(a.means.data()[i] == b.means.data()[i]);
  for (index_t i = 0; i < a.sh.size(); ++i) REQUIRE(a.sh.data()[i] == b.sh.data()[i]);
}

TEST_CASE("refine's camera increments get the gradient of the loss (float64 central differences)", "[model][refine]") {
  auto s = refine_scene<double>(3);
  GaussianSet<double> g = jittered(s.truth, 3);
  model::RefineConfig c;
  c.steps = 1;
  c.ssim_weight = 1;  // smooth: L1 has kinks where a render equals its target
  model::RefineWorkspace<double> ws;
  const model::RefineViews<double> v = s.refine_views();
  ws.w2c.assign(s.w2c.begin(), s.w2c.end());
  model::refine_detail::build_store(ws.store, g.size(), 1, 3, true);
  ws.set = g;
  const double base = model::refine_detail::views_loss(ws, v, c, true);
  REQUIRE(base > 0);
  const std::vector<double> analytic_r(ws.store.grad("rotations").begin(), ws.store.grad("rotations").end());
  const std::vector<double> analytic_t(ws.store.grad("translations").begin(), ws.store.grad("translations").end());
  for (int j = 0; j < 3; ++j) CHECK(analytic_r[static_cast<std::size_t>(j)] == 0.0);  // camera 0 is fixed
  const double step = 1e-7;  // the rasterizer's alpha cut-off (1/255) makes a step of 1e-6 cross a jump here
  const std::vector<double> w2c0 = ws.w2c;
  double max_r = 0, max_t = 0;
  for (index_t k = 1; k < 3; ++k)
    for (int j = 0; j < 6; ++j) {
      double fd = 0;
      for (double sign : {1.0, -1.0}) {
        ws.w2c = w2c0;
        Eigen::Vector3d d = Eigen::Vector3d::Zero();
        d(j % 3) = sign * step;
        Eigen::Matrix<double, 3, 4> M;
        for (int r = 0; r < 3; ++r)
          for (int col = 0; col < 4; ++col) M(r, col) = w2c0[static_cast<std::size_t>(12 * k + 4 * r + col)];
        if (j < 3) M = (model::refine_detail::exp_so3(d) * M).eval();
        else M.col(3) += d;
        for (int r = 0; r < 3; ++r)
          for (int col = 0; col < 4; ++col) ws.w2c[static_cast<std::size_t>(12 * k + 4 * r + col)] = M(r, col);
        fd += sign * model::refine_detail::views_loss(ws, v, c, false) / (2 * step);
      }
      const double an = j < 3 ? analytic_r[static_cast<std::size_t>(3 * k + j)] : analytic_t[static_cast<std::size_t>(3 * k + j - 3)];
      INFO("camera " << k << " component " << j << ": analytic " << an << ", numeric " << fd);
      CHECK(std::abs(an - fd) <= 1e-6 + 1e-4 * std::abs(fd));
      (j < 3 ? max_r : max_t) = std::max(j < 3 ? max_r : max_t, std::abs(an));
    }
  CHECK(max_r > 1e-4);  // the check is not vacuous
  CHECK(max_t > 1e-4);
}

TEST_CASE("refine with cameras brings a rotated camera back, with fixed cameras none moves", "[model][refine]") {
  auto s = refine_scene<float>(3);
  const std::vector<float> truth_w2c = s.w2c;
  turn_camera(s.w2c, 1, Eigen::Vector3d(0.3, 1, 0.2), 3.0);
  const double before = turn_error(s.w2c, truth_w2c, 1);
  REQUIRE(before == Approx(3.0).epsilon(1e-3));
  model::RefineConfig c;
  c.steps = 60;
  c.lr_means = c.lr_quats = c.lr_scales = c.lr_opacity = c.lr_sh = 0;  // only the cameras learn
  c.lr_rotation = 2e-3;
  c.lr_translation = 0;  // a small turn and a sideways shift look alike on 24 x 24 pixels; check the turn alone
  c.prune_every = 0;
  c.validate = false;  // the held-out view's camera is not refined in the trial, and the Gaussians are fixed
  model::RefineWorkspace<float> ws;
  GaussianSet<float> g = s.truth;
  const std::vector<float> moved = s.w2c;
  const model::RefineResult r = model::refine(g, s.refine_views(), c, ws);
  CHECK(r.loss_final < r.loss_initial);
  CHECK(turn_error(s.w2c, truth_w2c, 1) < 0.3 * before);
  for (int i = 0; i < 12; ++i) CHECK(s.w2c[static_cast<std::size_t>(i)] == moved[static_cast<std::size_t>(i)]);  // camera 0
  for (index_t i = 0; i < g.means.size(); ++i) REQUIRE(g.means.data()[i] == s.truth.means.data()[i]);

  // Cameras fixed: the Gaussians learn, every camera keeps its bits.
  s.w2c = moved;
  model::RefineConfig fixed;
  fixed.steps = 5;
  fixed.optimize_cameras = false;
  GaussianSet<float> h = jittered(s.truth, 4);
  model::refine(h, s.refine_views(), fixed, ws);
  CHECK(s.w2c == moved);
}

TEST_CASE("refine prunes Gaussians whose opacity collapses and keeps their features in step", "[model][refine]") {
  auto s = refine_scene<float>(2, 12);
  GaussianSet<float> g = s.truth;
  g.features = Tensor<float, 2>(Shape<2>{12, 2});
  for (index_t i = 0; i < 12; ++i) g.features(i, 0) = static_cast<float>(i), g.features(i, 1) = -static_cast<float>(i);
  for (index_t i : {2, 7}) g.opacities(i) = 0.001f;  // below the threshold from the start
  model::RefineConfig c;
  c.steps = 3;
  c.prune_every = 1;
  c.optimize_cameras = false;
  c.validate = false;
  model::RefineWorkspace<float> ws;
  const model::RefineResult r = model::refine(g, s.refine_views(), c, ws);
  CHECK(r.pruned >= 2);
  REQUIRE(g.size() == 12 - r.pruned);
  REQUIRE(g.features.shape() == Shape<2>{g.size(), 2});
  for (index_t i = 0; i < g.size(); ++i) {
    CHECK(g.features(i, 0) != 2.0f);
    CHECK(g.features(i, 0) != 7.0f);
    CHECK(g.features(i, 1) == -g.features(i, 0));
  }
}

TEST_CASE("refine's held-out trial chooses the step count: the steps that help the held-out view are kept",
          "[model][refine]") {
  auto s = refine_scene<float>(3);
  const GaussianSet<float> start = jittered(s.truth, 9);
  model::RefineConfig c;
  c.steps = 40;
  c.optimize_cameras = false;
  c.lr_means = 3e-3;
  c.validate = true;
  c.validate_every = 5;
  model::RefineWorkspace<float> ws;
  GaussianSet<float> a = start;
  const model::RefineResult r = model::refine(a, s.refine_views(), c, ws);
  CHECK(r.trial_steps == 40);
  CHECK(r.chosen_steps > 0);
  CHECK(r.chosen_steps % 5 == 0);
  CHECK(r.steps == r.chosen_steps);
  CHECK(r.holdout_best < 0.8 * r.holdout_initial);  // the fit of views 0 and 1 helps view 2: the truth is one set
  CHECK(r.loss_final < 0.7 * r.loss_initial);
  // The same inputs give the same bits.
  GaussianSet<float> b = start;
  const model::RefineResult r2 = model::refine(b, s.refine_views(), c, ws);
  CHECK(r2.chosen_steps == r.chosen_steps);
  CHECK(r2.loss_final == r.loss_final);
  for (index_t i = 0; i < a.means.size(); ++i) REQUIRE(a.means.data()[i] == b.means.data()[i]);
  // One view: nothing to hold out, the whole budget fits it.
  auto one = refine_scene<float>(1);
  GaussianSet<float> g = jittered(one.truth, 2);
  const model::RefineResult r1 = model::refine(g, one.refine_views(), c, ws);
  CHECK(r1.chosen_steps == -1);
  CHECK(r1.trial_steps == 0);
  CHECK(r1.steps == 40);
}

TEST_CASE("refine's held-out trial keeps the input set and cameras when fitting hurts the held-out view",
          "[model][refine]") {
  // Views 0 and 1 show a different scene from view 2's (the truth, which the start is): fitting them moves the set
  // away from what view 2 sees.
  auto s = refine_scene<float>(3);
  const auto other = refine_scene<float>(3, 24, 77);
  std::copy_n(other.images.begin(), 2 * 24 * 24 * 3, s.images.begin());
  GaussianSet<float> g = s.truth;
  g.features = Tensor<float, 2>(Shape<2>{g.size(), 1}, 3.0f);
  const GaussianSet<float> before = g;
  const std::vector<float> w2c = s.w2c;
  model::RefineConfig c;
  c.steps = 20;
  c.validate = true;
  c.validate_every = 4;
  model::RefineWorkspace<float> ws;
  const model::RefineResult r = model::refine(g, s.refine_views(), c, ws);
  CHECK(r.trial_steps == 20);
  CHECK(r.chosen_steps == 0);
  CHECK(r.steps == 0);
  CHECK(r.holdout_best == r.holdout_initial);
  CHECK(r.loss_final == r.loss_initial);
  CHECK(s.w2c == w2c);
  REQUIRE(g.size() == before.size());
  for (const auto& [x, y] : {std::pair{&g.means, &before.means}, {&g.scales, &before.scales}, {&g.quats, &before.quats}})
    for (index_t i = 0; i < x->size(); ++i) REQUIRE(x->data()[i] == y->data()[i]);
  for (index_t i = 0; i < g.sh.size(); ++i) REQUIRE(g.sh.data()[i] == before.sh.data()[i]);
  for (index_t i = 0; i < g.size(); ++i) REQUIRE(g.opacities(i) == before.opacities(i));
  REQUIRE(g.features.shape() == before.features.shape());
  // Without the trial the same budget fits views 0 and 1, and the set moves.
  c.validate = false;
  GaussianSet<float> h = before;
  const model::RefineResult u = model::refine(h, s.refine_views(), c, ws);
  CHECK(u.steps == 20);
  CHECK(u.loss_final < u.loss_initial);
  double moved = 0;
  for (index_t i = 0; i < h.means.size(); ++i) moved = std::max(moved, std::abs(double(h.means.data()[i] - before.means.data()[i])));
  CHECK(moved > 1e-3);
}

TEST_CASE("carve_to_silhouettes removes the Gaussians seen on background and keeps the object's", "[model][refine]") {
  auto s = refine_scene<float>(3);
  const std::vector<float> alpha = truth_alpha(s);
  // Two floaters above the object (inside every picture, outside every silhouette) after the truth's 24.
  GaussianSet<float> g = make_gaussian_set<float>(26, 0);
  g.features = Tensor<float, 2>(Shape<2>{26, 1});
  for (index_t i = 0; i < 26; ++i) {
    const bool floater = i >= 24;
    for (int k = 0; k < 3; ++k) {
      g.means(i, k) = floater ? (k == 1 ? (i == 24 ? -1.05f : -1.1f) : 0.0f) : s.truth.means(i, k);  // y down
      g.scales(i, k) = 0.05f;
    }
    g.opacities(i) = 0.5f;
    g.features(i, 0) = static_cast<float>(i);
  }
  const model::RefineViews<float> v = s.refine_views();
  GaussianSet<float> a = g;
  CHECK(model::carve_to_silhouettes(a, v, alpha.data(), 0) == 2);
  REQUIRE(a.size() == 24);
  for (index_t i = 0; i < 24; ++i) {
    CHECK(a.features(i, 0) == static_cast<float>(i));
    CHECK(a.means(i, 1) == s.truth.means(i, 1));
  }
  // Widened silhouettes keep the floaters that lie within the margin.
  GaussianSet<float> b = g;
  CHECK(model::carve_to_silhouettes(b, v, alpha.data(), 24) == 0);
  // Photos without alpha say nothing: all kept.
  const std::vector<float> opaque(alpha.size(), 1.0f);
  GaussianSet<float> c = g;
  CHECK(model::carve_to_silhouettes(c, v, opaque.data(), 0) == 0);
  // Every centre on background: one Gaussian stays.
  const std::vector<float> empty(alpha.size(), 0.0f);
  GaussianSet<float> d = g;
  CHECK(model::carve_to_silhouettes(d, v, empty.data(), 0) == 25);
  CHECK(d.size() == 1);
  CHECK_THROWS_WITH(model::carve_to_silhouettes(d, v, alpha.data(), -1), Catch::Contains("margin >= 0"));
}

TEST_CASE("refine refuses bad inputs with a message", "[model][refine]") {
  auto s = refine_scene<float>(2, 6);
  model::RefineWorkspace<float> ws;
  model::RefineConfig c;
  GaussianSet<float> g = s.truth;
  CHECK_THROWS_WITH(model::refine(g, s.refine_views(), c, ws), Catch::Contains("give seconds > 0 and/or steps > 0"));
  c.steps = 2;
  GaussianSet<float> empty = make_gaussian_set<float>(0, 0);
  CHECK_THROWS_WITH(model::refine(empty, s.refine_views(), c, ws), Catch::Contains("the Gaussian set is empty"));
  g.scales(3, 1) = 0;
  CHECK_THROWS_WITH(model::refine(g, s.refine_views(), c, ws), Catch::Contains("Gaussian 3 has scale 0"));
  g = s.truth;
  g.opacities(1) = std::numeric_limits<float>::quiet_NaN();
  CHECK_THROWS_WITH(model::refine(g, s.refine_views(), c, ws), Catch::Contains("Gaussian 1 has opacity nan"));
  g = s.truth;
  s.images[17] = 1.5f;
  CHECK_THROWS_WITH(model::refine(g, s.refine_views(), c, ws), Catch::Contains("image value 1.5 at flat index 17"));
  s.images[17] = 0.5f;
  s.w2c[12 + 5] = std::numeric_limits<float>::infinity();
  CHECK_THROWS_WITH(model::refine(g, s.refine_views(), c, ws), Catch::Contains("view 1 world_to_camera[1,1]"));
  s.w2c[12 + 5] = 0;
  s.K[9] = -1;
  CHECK_THROWS_WITH(model::refine(g, s.refine_views(), c, ws), Catch::Contains("view 1 has intrinsics fx -1"));
  model::RefineViews<float> none{0, 24, 24, s.images.data(), s.K.data(), s.w2c.data()};
  CHECK_THROWS_WITH(model::refine(g, none, c, ws), Catch::Contains("0 views"));
  c.ssim_weight = 2;
  CHECK_THROWS_WITH(model::refine(g, s.refine_views(), c, ws), Catch::Contains("ssim_weight 2 outside [0, 1]"));
  c.ssim_weight = 0.2;
  std::vector<float> alpha(static_cast<std::size_t>(2 * 24 * 24), 1.0f);
  alpha[30] = std::numeric_limits<float>::quiet_NaN();
  model::RefineViews<float> with_alpha = s.refine_views();
  with_alpha.alpha = alpha.data();
  CHECK_THROWS_WITH(model::refine(g, with_alpha, c, ws), Catch::Contains("alpha value nan at flat index 30"));
  c.validate_every = 0;
  CHECK_THROWS_WITH(model::refine(g, s.refine_views(), c, ws), Catch::Contains("validate_every 0 must be >= 1"));
}

TEST_CASE("random Gaussians for a posed fit lie in the views' silhouettes", "[model][refine]") {
  auto s = refine_scene<float>(3);
  // Silhouettes from the targets: a pixel is foreground where it is not white.
  std::vector<float> alpha(static_cast<std::size_t>(3 * 24 * 24));
  for (std::size_t p = 0; p < alpha.size(); ++p)
    alpha[p] = std::min({s.images[3 * p], s.images[3 * p + 1], s.images[3 * p + 2]}) < 0.98f ? 1.0f : 0.0f;
  const GaussianSet<float> g = model::random_gaussians_in_views<float>(200, 1, s.refine_views(), alpha.data(), 7);
  REQUIRE(g.size() == 200);
  CHECK(g.sh.shape(1) == 4);
  for (index_t i = 0; i < g.size(); ++i) {
    for (index_t v = 0; v < 3; ++v) {
      const float* E = s.w2c.data() + 12 * v;
      double q[3];
      for (int r = 0; r < 3; ++r) q[r] = E[4 * r] * g.means(i, 0) + E[4 * r + 1] * g.means(i, 1) + E[4 * r + 2] * g.means(i, 2) + E[4 * r + 3];
      const index_t x = static_cast<index_t>(30 * q[0] / q[2] + 12), y = static_cast<index_t>(30 * q[1] / q[2] + 12);
      REQUIRE(x >= 0);
      REQUIRE(y >= 0);
      REQUIRE(x < 24);
      REQUIRE(y < 24);
      REQUIRE(alpha[static_cast<std::size_t>((v * 24 + y) * 24 + x)] == 1.0f);
    }
    CHECK(g.opacities(i) == Approx(model::refine_init_opacity));
  }
  // The same seed, the same set.
  const GaussianSet<float> again = model::random_gaussians_in_views<float>(200, 1, s.refine_views(), alpha.data(), 7);
  for (index_t i = 0; i < g.means.size(); ++i) REQUIRE(again.means.data()[i] == g.means.data()[i]);
}

TEST_CASE("refine grows the set in the silhouettes' visual hull, and growth fits what the start lacks",
          "[model][refine]") {
  auto s = refine_scene<float>(3);
  const std::vector<float> alpha = truth_alpha(s);
  model::RefineViews<float> v = s.refine_views();
  v.alpha = alpha.data();
  // A start that lacks most of the object: 4 of the truth's 24 Gaussians, with features.
  GaussianSet<float> start = make_gaussian_set<float>(4, 0, 1);
  for (index_t i = 0; i < 4; ++i) {
    std::copy_n(&s.truth.means(i, 0), 3, &start.means(i, 0));
    std::copy_n(&s.truth.scales(i, 0), 3, &start.scales(i, 0));
    std::copy_n(s.truth.sh.data() + 3 * i, 3, start.sh.data() + 3 * i);
    start.opacities(i) = s.truth.opacities(i);
    start.features(i, 0) = static_cast<float>(i + 1);
  }
  model::RefineConfig c;
  c.steps = 1;
  c.optimize_cameras = false;
  c.carve = false;
  c.grow = 100;
  c.seed = 3;
  c.lr_means = c.lr_quats = c.lr_scales = c.lr_opacity = c.lr_sh = 0;  // the grown centres stay where they were drawn
  model::RefineWorkspace<float> ws;
  GaussianSet<float> g = start;
  const model::RefineResult r = model::refine(g, v, c, ws);
  CHECK(r.grown == 100);
  REQUIRE(g.size() == 104);
  REQUIRE(g.features.shape() == Shape<2>{104, 1});
  for (index_t i = 0; i < 104; ++i) CHECK(g.features(i, 0) == (i < 4 ? static_cast<float>(i + 1) : 0.0f));
  for (index_t i = 4; i < g.size(); ++i)
    for (index_t k = 0; k < 3; ++k) {
      const float* E = s.w2c.data() + 12 * k;
      double q[3];
      for (int row = 0; row < 3; ++row)
        q[row] = E[4 * row] * g.means(i, 0) + E[4 * row + 1] * g.means(i, 1) + E[4 * row + 2] * g.means(i, 2) + E[4 * row + 3];
      const index_t x = static_cast<index_t>(30 * q[0] / q[2] + 12), y = static_cast<index_t>(30 * q[1] / q[2] + 12);
      REQUIRE((x >= 0 && y >= 0 && x < 24 && y < 24));
      REQUIRE(alpha[static_cast<std::size_t>((k * 24 + y) * 24 + x)] >= model::refine_mask_threshold);
    }
  // Photos without background say nothing about where the object is: nothing grows; nor without alpha.
  const std::vector<float> opaque(alpha.size(), 1.0f);
  model::RefineViews<float> no_background = v;
  no_background.alpha = opaque.data();
  GaussianSet<float> h = start;
  CHECK(model::refine(h, no_background, c, ws).grown == 0);
  CHECK(h.size() == 4);
  h = start;
  CHECK(model::refine(h, s.refine_views(), c, ws).grown == 0);
  // Growth fits what the start lacks: the same steps reach a lower loss on the views with it than without it.
  model::RefineConfig fit;
  fit.steps = 60;
  fit.optimize_cameras = false;
  fit.seed = 3;
  GaussianSet<float> without = start, with = start;
  const model::RefineResult a = model::refine(without, v, fit, ws);
  fit.grow = 100;
  const model::RefineResult b = model::refine(with, v, fit, ws);
  CHECK(b.grown == 100);
  CHECK(b.loss_final < 0.7 * a.loss_final);
  // The configuration eval and reconstruct use: growth at 3DGS's rates with background, the prediction alone without.
  const model::RefineConfig p = model::prediction_refine_config(v, 5.0, 9);
  CHECK(p.grow == model::refine_grow_gaussians);
  CHECK(p.lr_scale == 1.0);
  CHECK(p.seconds == 5.0);
  CHECK(p.seed == 9u);
  const model::RefineConfig q = model::prediction_refine_config(no_background, 5.0, 9);
  CHECK(q.grow == 0);
  CHECK(q.lr_scale == model::refine_prediction_lr_scale);
  const model::RefineConfig none = model::prediction_refine_config(v, 5.0, 9, 0);
  CHECK(none.grow == 0);
  CHECK(none.lr_scale == model::refine_prediction_lr_scale);
  c.grow = -1;
  CHECK_THROWS_WITH(model::refine(h, v, c, ws), Catch::Contains("grow -1 must be >= 0"));
}
