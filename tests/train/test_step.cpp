#include <catch2/catch.hpp>

#include <Eigen/Dense>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <numbers>
#include <random>
#include <thread>
#include <vector>

#include "flexsplat/train/step.hpp"
#include "flexsplat/testing/gradcheck.hpp"

using namespace flexsplat;

namespace {
// One procedural scene at the tiny configuration's size: `inputs` input views and `targets` novel views.
data::SceneSample tiny_scene(int inputs, int targets, std::uint64_t seed) {
  data::GeneratorConfig g;
  g.size = 28;
  g.supersample = 2;
  data::BatchOptions o;
  o.inputs = inputs;
  o.targets = targets;
  o.structured_inputs = inputs == 4;
  return data::generate_batch(g, 1, seed, 0, o)[0];
}

// The tensors of the tiny model whose loss gradient is zero by construction in the whole-model check, and why.
std::string zero_reason(const std::string& name) {
  if (name == "aggregator.patch_embed.mask_token") return "stored, never read (nothing is masked)";
  return {};
}

// The derivative of scene_loss along a random direction of every parameter (central differences, step h) and the
// same from `grads` (scene_gradient's); the parameters are restored.
struct Directional {
  double analytic = 0, numeric = 0;
};
Directional directional_derivative(model::SceneWorkspace<double>& ws, model::FlexSplatWeights<double>& w,
                                   const std::vector<double>& grads, const model::TrainExample<double>& e,
                                   const model::StepConfig& sc, unsigned seed, double h) {
  auto& store = w.store();
  const index_t n = store.size();
  std::vector<double> dir(grads.size());
  std::mt19937 rng(seed);
  std::normal_distribution<double> normal;
  Directional d;
  for (std::size_t i = 0; i < dir.size(); ++i) dir[i] = normal(rng), d.analytic += grads[i] * dir[i];
  const std::vector<double> base(store.params(), store.params() + n);
  auto loss_at = [&](double eps) {
    for (std::size_t i = 0; i < base.size(); ++i) store.params()[i] = base[i] + eps * dir[i];
    return model::scene_loss<double>(ws, w, e, sc).loss;
  };
  d.numeric = (loss_at(h) - loss_at(-h)) / (2 * h);
  loss_at(0);
  return d;
}

// The whole-model float64 gradient check: scene_gradient against central differences of scene_loss on every tensor of
// the store (weights of config c, init(seed)), each tensor its own GradParam with its gradient slot junk-seeded by the
// checker (scene_gradient must add into it), the floor on every tensor with a gradient, max_checks entries per tensor
// (the largest analytic one and random others). With sc.appearance off the appearance tensors are not probed; their
// gradient slots must come back untouched. nudge_zeros: parameters that start at exactly 0 are moved off it first.
// report_check(report) checks which loss parts the example reaches.
template <class ReportCheck>
void whole_model_gradient_check(const model::FlexSplatConfig& c, unsigned seed, const model::TrainExample<double>& e,
                                const model::StepConfig& sc, std::size_t max_checks, bool nudge_zeros,
                                ReportCheck report_check) {
  auto w = model::FlexSplatWeights<double>::create(c, true);
  w->init(seed);
  model::SceneWorkspace<double> ws;
  auto& store = w->store();
  if (nudge_zeros) {
    // Biases start at exactly 0: where a 3x3 neighbourhood of a ReLU'd input is all zero, the next ReLU's input is the
    // bias itself, 0, a kink where central differences see half a slope and the backward none. Moved off it.
    std::mt19937 rng(seed);
    std::uniform_real_distribution<double> u(0.01, 0.02), sign(-1, 1);
    for (index_t i = 0; i < store.size(); ++i)
      if (store.params()[i] == 0) store.params()[i] = sign(rng) < 0 ? -u(rng) : u(rng);
  }
  // Hold the camera head's detached feedback at the unperturbed values (see GeometryStage::camera_feedback).
  std::vector<double> scratch(static_cast<std::size_t>(store.size()));
  model::scene_gradient(ws, *w, scratch.data(), e, sc);
  const index_t fb = (c.geometry.camera.iterations - 1) * e.views * 9;
  std::vector<double> feedback(ws.geometry.cache.camera.raw.begin(), ws.geometry.cache.camera.raw.begin() + fb);
  ws.geometry.camera_feedback = feedback.data();

  // Every tensor of the store, its gradient slot junk-seeded by the checker: scene_gradient must add into it. With the
  // appearance objective off, the appearance tensors are not probed (no loss reads them); their slots must come back
  // untouched instead (checked below).
  const auto& appearance = store.segment(model::appearance_segment);
  auto in_appearance = [&](const auto& t) {
    return t.offset >= appearance.offset && t.offset < appearance.offset + appearance.size;
  };
  std::vector<testing::GradParam> params;
  for (const auto& t : store.tensors())
    if (sc.appearance || !in_appearance(t)) params.push_back({t.name, store.param(t), store.grad(t), zero_reason(t.name)});
  if (!sc.appearance) {
    REQUIRE(appearance.size > 0);
    const std::span<double> slots(store.grads() + appearance.offset, static_cast<std::size_t>(appearance.size));
    for (std::size_t i = 0; i < slots.size(); ++i) slots[i] = 0.25 + static_cast<double>(i % 7);
    const std::vector<double> junk(slots.begin(), slots.end());
    model::scene_gradient(ws, *w, store.grads(), e, sc);
    CHECK(std::equal(slots.begin(), slots.end(), junk.begin()));
  }
  // The probes run forward only (scene_loss), which must report scene_gradient's loss to the bit.
  std::fill(scratch.begin(), scratch.end(), 0.0);
  const model::StepReport report = model::scene_gradient(ws, *w, scratch.data(), e, sc);
  report_check(report);  // the loss parts the check is meant to reach are in the checked loss
  const double full = report.loss;
  const double forward = model::scene_loss(ws, *w, e, sc).loss;
  INFO("scene_gradient loss " << full << ", scene_loss " << forward);
  REQUIRE(forward == full);
  testing::GradCheckOptions options;
  options.max_checks_per_param = max_checks;
  options.abs_tol = 1e-8;  // differences land within 1e-9 here; the floor 1e-7 then clears every tensor with a gradient
  options.unit_cotangent = true;
  auto result = testing::check_gradients(
      params, 1, [&](std::span<double> o) { o[0] = model::scene_loss(ws, *w, e, sc).loss; },
      [&](std::span<const double>) { model::scene_gradient(ws, *w, store.grads(), e, sc); }, options);
  INFO(result.summary());
  CHECK(result.tensors.size() == params.size());
  CHECK(params.size() == store.tensors().size() - (sc.appearance ? 0 : static_cast<std::size_t>(std::count_if(
                             store.tensors().begin(), store.tensors().end(), in_appearance))));
  CHECK(result.ok());
}
}  // namespace

TEST_CASE("a procedural scene becomes a training example in the first camera's frame", "[model][train]") {
  const auto c = model::flexsplat_tiny_config();
  const auto e = model::make_train_example<float>(tiny_scene(3, 2, 5), c);
  CHECK(e.views == 3);
  CHECK(e.targets == 2);
  for (int r = 0; r < 3; ++r)
    for (int col = 0; col < 4; ++col) CHECK(e.gt_extrinsics[4 * r + col] == Approx(r == col ? 1.0 : 0.0).margin(1e-5));
  double sum = 0, count = 0;
  for (float d : e.gt_depth) if (d > 0) sum += d, ++count;
  CHECK(count > 0);
  // The first camera's depth is its points' distance scaled down to unit mean distance over all views: order one.
  CHECK(sum / count > 0.3);
  CHECK(sum / count < 3.0);
  // The ground-truth pose encoding of the first camera is the identity rotation and zero translation.
  CHECK(e.gt_pose_enc[0] == Approx(0).margin(1e-6));
  CHECK(std::abs(e.gt_pose_enc[6]) == Approx(1).margin(1e-6));
  auto bad = model::flexsplat_tiny_config();
  bad.image_h = bad.image_w = 35;
  CHECK_THROWS_WITH(model::make_train_example<float>(tiny_scene(1, 0, 5), bad), Catch::Contains("the model takes 35 x 35"));
}

TEST_CASE("the whole model passes the float64 gradient check from the losses to every module's parameters",
          "[model][train]") {
  const auto c = model::flexsplat_tiny_config();
  model::StepConfig sc;
  sc.camera_weight = 0.5;
  sc.depth_weight = 0.2;
  sc.depth_shape_weight = 0.3;
  // The rendered-depth term's weight U is the depth head's confidence held constant by design, so finite differences
  // (which see U move) cannot check it here; test_objective checks that term with the geometry outputs fixed.
  sc.objective.depth = 0;
  sc.gaussians = 24;
  // The largest analytic entry and one at random; every module has its own check.
  whole_model_gradient_check(c, 3, model::make_train_example<double>(tiny_scene(2, 1, 9), c), sc, 2, false,
                             [](const model::StepReport& r) { REQUIRE(r.depth_shape > 0); });
}

TEST_CASE("with the point head, the match head and every camera loss on, the whole model passes the float64 gradient "
          "check, tensor by tensor",
          "[model][train][points]") {
  // The geometry side of the pose runs' models: the point and match heads (the match head reading the pixels through
  // an image convolution), the camera loss and the relative camera loss (pairs and FoV), the
  // depth and depth-shape losses. The appearance objective is the other whole-model check's (the tiny config); here it
  // is off, so the appearance tensors are declared zero and checked to stay so.
  auto c = model::flexsplat_tiny_config();
  c.geometry.point_head = true;
  c.geometry.match_dim = 4;
  c.geometry.match_image = true;
  c.geometry.match_image_convs = 1;
  c.geometry.match_image_width = 4;
  c.validate();
  model::StepConfig sc;
  sc.appearance = false;
  sc.camera_weight = 0.5;
  sc.relative_camera_weight = 0.7;
  sc.depth_weight = 0.2;
  sc.depth_shape_weight = 0.3;
  sc.point_weight = 0.4;
  sc.point_loss.min_valid_pixels = 10;
  sc.match_weight = 0.5;
  const auto e = model::make_train_example<double>(tiny_scene(2, 0, 13), c);
  // On one thread: each of its forward passes is small and splits poorly; on a loaded 2-core machine two workers took
  // 9x as long (145 s against 16 s), and one leaves ctest's other job a core.
  const SerialScope one_thread;
  // The largest analytic entry of every tensor and five at random (every entry of a tensor of at most 6): a slot
  // written with = instead of += is off by the checker's junk in every entry, a wrong row or channel shows on some of
  // the random ones; 2 x 6 forward passes per tensor, about 3700 in all (geometry only: about 15 s on one thread).
  whole_model_gradient_check(c, 5, e, sc, 6, true, [](const model::StepReport& r) {
    CHECK(r.camera > 0);
    CHECK(r.depth > 0);
    CHECK(r.depth_shape > 0);
    CHECK(r.points > 0);
    CHECK(r.match > 0);
  });
}

TEST_CASE("train_step drives the loss on one fixed scene down by 10x", "[model][train]") {
  const auto c = model::flexsplat_tiny_config();
  auto w = model::FlexSplatWeights<float>::create(c, true);
  w->init(11);
  const std::vector<model::TrainExample<float>> batch{model::make_train_example<float>(tiny_scene(2, 2, 21), c)};
  model::StepConfig sc;
  sc.camera_weight = 1.0;
  sc.depth_weight = 0.1;
  sc.gaussians = 48;
  sc.adamw.weight_decay = 0;
  model::StepWorkspace<float> ws;
  train::SoloCommunicator solo;
  const int steps = 300;
  // Decayed as the trainer does: at a constant 3e-3 the loss bottoms out near step 120 and drifts back up.
  const train::CosineSchedule schedule{3e-3, 0.0, 0, steps};
  double first = 0, last = 0;
  for (int s = 0; s < steps; ++s) {
    const auto r = model::train_step<float>(ws, *w, batch, train::contiguous_plan(1, 1), sc,
                                            schedule.lr(static_cast<std::uint64_t>(s)),
                                            static_cast<std::uint64_t>(s), solo);
    REQUIRE(std::isfinite(r.loss));
    if (s == 0) first = r.loss;
    last = r.loss;
  }
  std::printf("train_step on one scene: loss %.5f -> %.5f after %d steps\n", first, last, steps);
  CHECK(last < first / 10);
}

TEST_CASE("a training example's ground-truth points are each view's surface in the first camera's frame",
          "[model][train][points]") {
  const auto c = model::flexsplat_tiny_config();
  const auto e = model::make_train_example<double>(tiny_scene(3, 0, 7), c);
  const index_t px = e.h * e.w;
  REQUIRE(e.gt_points.size() == static_cast<std::size_t>(3 * e.views * px));
  index_t checked = 0;
  for (index_t v = 0; v < e.views; ++v) {
    const double* E = e.gt_extrinsics.data() + 12 * v;
    const double* K = e.gt_K.data() + 9 * v;
    for (index_t y = 0; y < e.h; ++y)
      for (index_t x = 0; x < e.w; ++x) {
        const index_t p = v * px + y * e.w + x;
        const double z = e.gt_depth[static_cast<std::size_t>(p)];
        if (z <= 0) continue;
        // The point seen through view v's camera lands on its pixel centre at its depth.
        const double* X = e.gt_points.data() + 3 * p;
        double cam[3];
        for (int r = 0; r < 3; ++r) cam[r] = E[4 * r] * X[0] + E[4 * r + 1] * X[1] + E[4 * r + 2] * X[2] + E[4 * r + 3];
        CHECK(cam[2] == Approx(z).margin(1e-9));
        CHECK(K[0] * cam[0] / cam[2] + K[2] == Approx(x + 0.5).margin(1e-7));
        CHECK(K[4] * cam[1] / cam[2] + K[5] == Approx(y + 0.5).margin(1e-7));
        ++checked;
      }
  }
  CHECK(checked > 100);
  // Its correspondences join pixels that show one surface point.
  REQUIRE(!e.matches.empty());
  for (const auto& m : e.matches) {
    const double* a = e.gt_points.data() + 3 * (m.view_a * px + m.pixel_a);
    const double* b = e.gt_points.data() + 3 * (m.view_b * px + m.pixel_b);
    const double gap = std::sqrt((a[0] - b[0]) * (a[0] - b[0]) + (a[1] - b[1]) * (a[1] - b[1]) + (a[2] - b[2]) * (a[2] - b[2]));
    CHECK(gap < 0.1);  // within about one pixel's footprint (28 x 28 views of a unit-size object)
    CHECK(m.view_a != m.view_b);
  }
  CHECK(static_cast<index_t>(e.matches.size()) <= e.views * (e.views - 1) * model::matches_per_pair(e.views));
  CHECK(model::matches_per_pair(4) == 64);
  CHECK(model::matches_per_pair(8) == 13);
  CHECK(model::matches_per_pair(1) == 0);
}

TEST_CASE("point_weight and match_weight: scene_gradient is the derivative of scene_loss along a random direction",
          "[model][train][points]") {
  auto c = model::flexsplat_tiny_config();
  c.geometry.point_head = true;
  c.geometry.match_dim = 4;
  auto w = model::FlexSplatWeights<double>::create(c, true);
  w->init(5);
  const auto e = model::make_train_example<double>(tiny_scene(2, 0, 13), c);
  model::StepConfig sc;
  sc.appearance = false;
  sc.point_weight = 1.0;
  sc.point_loss.min_valid_pixels = 10;
  sc.match_weight = 0.5;
  model::SceneWorkspace<double> ws;
  auto& store = w->store();
  const index_t n = store.size();
  std::vector<double> grads(static_cast<std::size_t>(n), 0.0);
  const auto r = model::scene_gradient<double>(ws, *w, grads.data(), e, sc);
  REQUIRE(r.points > 0);
  REQUIRE(r.match > 0);
  double norm = 0;
  for (double g : grads) norm += g * g;
  REQUIRE(norm > 0);
  // Every parameter moves at once, so the third-order error of step 1e-6 reaches 1e-4 here (1e-5: 19.0955, 1e-7:
  // 19.05769, 1e-8: 19.05769, analytic 19.05769); 1e-7 is well inside double precision for a loss of order 10.
  const Directional d = directional_derivative(ws, *w, grads, e, sc, 3, 1e-7);
  INFO("analytic " << d.analytic << ", numeric " << d.numeric);
  CHECK(d.analytic == Approx(d.numeric).epsilon(1e-5));
  // Without the heads the weights are refused by name.
  auto plain = model::FlexSplatWeights<double>::create(model::flexsplat_tiny_config(), true);
  plain->init(5);
  model::SceneWorkspace<double> ws2;
  CHECK_THROWS_WITH(model::scene_loss<double>(ws2, *plain, e, sc), Catch::Contains("needs a model with the point head"));
  sc.point_weight = 0;
  CHECK_THROWS_WITH(model::scene_loss<double>(ws2, *plain, e, sc), Catch::Contains("needs a model with the match head"));
}

TEST_CASE("relative_camera_weight with frame_tokens 1: scene_gradient is the derivative of scene_loss along a random "
          "direction, the loss blind to the order of the views",
          "[model][train]") {
  auto c = model::flexsplat_tiny_config();
  c.geometry.aggregator.frame_tokens = 1;
  c.validate();
  auto w = model::FlexSplatWeights<double>::create(c, true);
  w->init(7);
  const auto e = model::make_train_example<double>(tiny_scene(3, 0, 21), c);
  model::StepConfig sc;
  sc.appearance = false;
  sc.relative_camera_weight = 1.0;
  model::SceneWorkspace<double> ws;
  auto& store = w->store();
  const index_t n = store.size();
  std::vector<double> grads(static_cast<std::size_t>(n), 0.0);
  // Hold the camera head's detached feedback at the unperturbed values (see GeometryStage::camera_feedback).
  model::scene_gradient<double>(ws, *w, grads.data(), e, sc);
  const index_t fb = (c.geometry.camera.iterations - 1) * e.views * 9;
  const std::vector<double> feedback(ws.geometry.cache.camera.raw.begin(), ws.geometry.cache.camera.raw.begin() + fb);
  ws.geometry.camera_feedback = feedback.data();
  std::fill(grads.begin(), grads.end(), 0.0);
  const auto r = model::scene_gradient<double>(ws, *w, grads.data(), e, sc);
  REQUIRE(r.camera > 0);
  const Directional d = directional_derivative(ws, *w, grads, e, sc, 4, 1e-7);
  INFO("analytic " << d.analytic << ", numeric " << d.numeric);
  REQUIRE(std::abs(d.numeric) > 1e-6);
  CHECK(d.analytic == Approx(d.numeric).epsilon(1e-5));
  // The views in another order (the first one included): the same pairs, so the same rotation term (the translations'
  // scale is the mean point distance from the first camera, which the order changes).
  sc.camera_loss.weight_translation = 0;
  ws.geometry.camera_feedback = nullptr;
  const double rotation = model::scene_loss<double>(ws, *w, e, sc).camera;
  const auto scene = tiny_scene(3, 0, 21);
  auto turned = scene;
  const index_t order[3] = {2, 0, 1};
  const index_t px = e.h * e.w;
  for (index_t v = 0; v < 3; ++v) {
    const auto to = static_cast<std::size_t>(v), from = static_cast<std::size_t>(order[v]);
    turned.inputs.cameras[to] = scene.inputs.cameras[from];
    auto copy = [&](const float* src, float* dst, index_t n) {
      std::copy(src + order[v] * n, src + (order[v] + 1) * n, dst + v * n);
    };
    copy(scene.inputs.rgb.data(), turned.inputs.rgb.data(), 3 * px);
    copy(scene.inputs.alpha.data(), turned.inputs.alpha.data(), px);
    copy(scene.inputs.depth.data(), turned.inputs.depth.data(), px);
  }
  const auto e2 = model::make_train_example<double>(turned, c);
  ws.geometry.camera_feedback = nullptr;
  CHECK(rotation > 0);
  CHECK(model::scene_loss<double>(ws, *w, e2, sc).camera == Approx(rotation).epsilon(1e-9));
}

TEST_CASE("decoder_true_cameras: the decoder sees the true cameras and the render loss trains no camera head",
          "[model][train]") {
  const auto c = model::flexsplat_tiny_config();
  auto w = model::FlexSplatWeights<double>::create(c, true);
  w->init(9);
  const auto e = model::make_train_example<double>(tiny_scene(3, 2, 13), c);
  model::StepConfig sc;  // the render objective alone
  model::SceneWorkspace<double> ws;
  auto& store = w->store();
  auto camera_head_grad = [&] {
    double sum = 0;
    index_t tensors = 0;
    for (const auto& t : store.tensors())
      if (t.name.find("camera_head.") != std::string::npos) {
        ++tensors;
        for (double g : store.grad(t)) sum += std::abs(g);
      }
    REQUIRE(tensors > 0);
    return sum;
  };
  store.zero_grads();
  const auto predicted = model::scene_gradient<double>(ws, *w, store.grads(), e, sc);
  CHECK(camera_head_grad() > 0);
  sc.decoder_true_cameras = true;
  store.zero_grads();
  const auto forced = model::scene_gradient<double>(ws, *w, store.grads(), e, sc);
  CHECK(camera_head_grad() == 0.0);
  CHECK(forced.render != predicted.render);
  // The same loss when the predicted cameras are replaced by the true ones by hand (the camera head's output unused).
  for (std::size_t i = 0; i < e.gt_extrinsics.size(); ++i)
    CHECK(ws.true_camera_geometry.extrinsics[i] == e.gt_extrinsics[i]);
  CHECK(model::scene_loss<double>(ws, *w, e, sc).render == forced.render);
  // Other camera-head weights change the predicted cameras, not what the decoder sees.
  for (const auto& t : store.tensors())
    if (t.name.find("camera_head.") != std::string::npos)
      for (double& v : store.param(t)) v *= 1.5;
  CHECK(model::scene_loss<double>(ws, *w, e, sc).render == forced.render);
  sc.decoder_true_cameras = false;
  CHECK(model::scene_loss<double>(ws, *w, e, sc).render != predicted.render);
}

TEST_CASE("train_step with scenes side by side on two threads matches one thread to the bit", "[model][train]") {
  const auto c = model::flexsplat_tiny_config();
  auto serial_w = model::FlexSplatWeights<float>::create(c, true);
  auto paired_w = model::FlexSplatWeights<float>::create(c, true);
  serial_w->init(5);
  paired_w->init(5);
  // Three scenes of 1-3 views: two threads take them unevenly, in whatever order they finish.
  const std::vector<model::TrainExample<float>> batch{model::make_train_example<float>(tiny_scene(3, 1, 31), c),
                                                      model::make_train_example<float>(tiny_scene(1, 2, 32), c),
                                                      model::make_train_example<float>(tiny_scene(2, 1, 33), c)};
  model::StepConfig sc;
  sc.camera_weight = 1.0;
  sc.depth_weight = 0.1;
  sc.gaussians = 48;
  train::SoloCommunicator solo;
  model::StepWorkspace<float> serial_ws, paired_ws;
  ThreadPool two(2);
  for (std::uint64_t step = 0; step < 2; ++step) {
    model::StepReport a, b;
    {
      const SerialScope serial;
      REQUIRE(!model::scenes_side_by_side(3));
      std::vector<int> runs(4, 0);
      const model::SideTasks side{4, [&](index_t i) { ++runs[static_cast<std::size_t>(i)]; }};
      a = model::train_step<float>(serial_ws, *serial_w, batch, train::contiguous_plan(3, 1), sc, 1e-3, step, solo,
                                   nullptr, nullptr, side);
      CHECK(runs == std::vector<int>(4, 1));
    }
    {
      const UsePool use(two);
      REQUIRE(model::scenes_side_by_side(3));
      model::PhaseTimes times;
      // Side tasks (the trainer's next scenes) fill the wait for the last scene and leave the step's result alone.
      std::vector<int> runs(4, 0), pool_sizes(4, 0);
      const model::SideTasks side{4, [&](index_t i) {
                                    pool_sizes[static_cast<std::size_t>(i)] = global_pool().size();
                                    ++runs[static_cast<std::size_t>(i)];
                                  }};
      b = model::train_step<float>(paired_ws, *paired_w, batch, train::contiguous_plan(3, 1), sc, 1e-3, step, solo,
                                   nullptr, &times, side);
      CHECK(runs == std::vector<int>(4, 1));
      CHECK(pool_sizes == std::vector<int>(4, 1));  // each as on one thread
      CHECK(times.geometry_forward > 0);
      CHECK(times.decoder_backward > 0);
    }
    CHECK(a.loss == b.loss);
    CHECK(a.grad_norm == b.grad_norm);
    const auto& sa = serial_w->store();
    const auto& sb = paired_w->store();
    REQUIRE(sa.size() == sb.size());
    index_t differ = 0;
    for (index_t i = 0; i < sa.size(); ++i) differ += sa.params()[i] != sb.params()[i];
    INFO("step " << step << ": " << differ << " of " << sa.size() << " parameters differ");
    CHECK(differ == 0);
  }
}

TEST_CASE("run_scenes: side by side from as many scenes as threads, in order on the caller below that", "[model][train]") {
  ThreadPool two(2);
  const UsePool use(two);
  const std::thread::id caller = std::this_thread::get_id();
  std::vector<index_t> seen;
  model::run_scenes(1, [&](index_t i, int worker) {
    CHECK(worker == 0);
    CHECK(std::this_thread::get_id() == caller);
    seen.push_back(i);
  });
  CHECK(seen == std::vector<index_t>{0});
  // Three scenes and two extra tasks; Catch's checks stay on this thread.
  std::vector<int> runs(5, 0), workers(5, -2), current(5, 0), pool_sizes(5, 0);
  model::run_scenes(
      3,
      [&](index_t i, int worker) {
        const auto k = static_cast<std::size_t>(i);
        ++runs[k];
        workers[k] = worker;
        current[k] = ThreadPool::current_worker();
        pool_sizes[k] = global_pool().size();
      },
      2);
  for (std::size_t i = 0; i < runs.size(); ++i) {
    INFO("task " << i);
    CHECK(runs[i] == 1);
    CHECK((workers[i] == 0 || workers[i] == 1));
    CHECK(current[i] < 0);  // each task runs as on one thread
    CHECK(pool_sizes[i] == 1);
  }
}
