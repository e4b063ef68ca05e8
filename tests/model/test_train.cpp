#include <catch2/catch.hpp>

#include <cmath>
#include <cstdio>

#include "flexsplat/model/train.hpp"
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

// The loss model::scene_gradient returns, forward only (a third of its cost): the gradient check's probes need no
// backward. Covers the terms the whole-model check uses (no rendered-depth or LPIPS term); the check compares it with
// scene_gradient's loss, so a divergence fails rather than checking another function.
double whole_model_forward_loss(model::SceneWorkspace<double>& ws, const model::FlexSplatWeights<double>& w,
                                const model::TrainExample<double>& e, const model::StepConfig& sc) {
  REQUIRE(sc.objective.depth == 0);
  REQUIRE(sc.objective.lpips == 0);
  REQUIRE(!sc.objective.initial_layer);
  REQUIRE((sc.appearance && sc.train_geometry && sc.render_inputs));
  const auto& c = w.config();
  const index_t V = e.views, px = e.h * e.w;
  model::geometry_stage_forward(ws.geometry, w, e.images.data(), V, true);  // train: honours camera_feedback
  const auto& g = ws.geometry.result;
  double camera = 0, depth = 0, rgb_head = 0, render = 0;
  if (sc.camera_weight > 0) {
    std::vector<const double*> stages;
    for (index_t i = 0; i < ws.geometry.iterations; ++i) stages.push_back(ws.geometry.pose_enc.data() + i * V * 9);
    camera = sc.camera_weight * loss::camera_loss_forward(stages, e.gt_pose_enc.data(), nullptr, V, sc.camera_loss).total;
  }
  if (sc.depth_weight > 0) {
    ws.depth_mask.resize(static_cast<std::size_t>(V * px));
    for (index_t i = 0; i < V * px; ++i) ws.depth_mask[static_cast<std::size_t>(i)] = e.gt_depth[static_cast<std::size_t>(i)] > 0;
    depth = sc.depth_weight * loss::depth_loss_forward(g.depth.data(), g.confidence.data(), e.gt_depth.data(),
                                                      ws.depth_mask.data(), V, e.h, e.w, sc.depth_loss).total;
  }
  auto& ow = ws.objective;
  const index_t n = sc.gaussians > 0 ? sc.gaussians : c.gaussians_for(V);
  decoder::model_forward(ow.model, n, w.appearance(), c.appearance, e.images.data(), g.h, g.w, g.features.data(),
                         g.feature_h, g.feature_w, g.view_geometry());
  if (sc.objective.rgb_head > 0)
    rgb_head = sc.objective.rgb_head * loss::mse_forward(ow.model.rgb.data(), e.images.data(), static_cast<const double*>(nullptr),
                                                         loss::ImageShape{V, 3, g.h, g.w, loss::Layout::nchw});
  raster::RenderOptions ro;
  ro.background = {e.background[0], e.background[1], e.background[2]};
  ro.expected_depth = true;
  const auto& sets = ow.model.gaussians();
  const double per_view = 1.0 / static_cast<double>(V + e.targets);
  const loss::ImageShape shape{1, 3, e.h, e.w, loss::Layout::nhwc};
  for (index_t v = 0; v < V + e.targets; ++v) {
    const bool input = v < V;
    const auto m = static_cast<std::size_t>(v - V);
    const double* K = input ? g.K.data() + 9 * v : e.target_K[m].data();
    const double* E = input ? g.extrinsics.data() + 12 * v : e.target_w2c[m].data();
    const double* target = input ? e.inputs_hwc.data() + v * px * 3 : e.target_images.data() + (v - V) * px * 3;
    const auto cam = model::render_camera(K, E, static_cast<int>(e.w), static_cast<int>(e.h));
    for (std::size_t l = 1; l < sets.size(); ++l) {
      raster::render_forward(sets[l], cam, ro, ow.render, ow.out);
      if (sc.objective.render > 0)
        render += sc.objective.render * per_view *
                  loss::mse_forward(ow.out.image.data(), target, static_cast<const double*>(nullptr), shape);
    }
  }
  return camera + depth + rgb_head + render;
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
  auto w = model::FlexSplatWeights<double>::create(c, true);
  w->init(3);
  const auto e = model::make_train_example<double>(tiny_scene(2, 1, 9), c);
  model::StepConfig sc;
  sc.camera_weight = 0.5;
  sc.depth_weight = 0.2;
  // The rendered-depth term's weight U is the depth head's confidence held constant by design, so finite differences
  // (which see U move) cannot check it here; test_objective checks that term with the geometry outputs fixed.
  sc.objective.depth = 0;
  sc.gaussians = 24;
  model::SceneWorkspace<double> ws;
  auto& store = w->store();
  // Hold the camera head's detached feedback at the unperturbed values (see GeometryStage::camera_feedback).
  std::vector<double> scratch(static_cast<std::size_t>(store.size()));
  model::scene_gradient(ws, *w, scratch.data(), e, sc);
  const index_t fb = (c.geometry.camera.iterations - 1) * e.views * 9;
  std::vector<double> feedback(ws.geometry.cache.camera.raw.begin(), ws.geometry.cache.camera.raw.begin() + fb);
  ws.geometry.camera_feedback = feedback.data();

  std::vector<testing::GradParam> params;
  for (const char* name : {"aggregator.patch_embed.patch_embed.proj.weight", "aggregator.frame_blocks.1.attn.qkv.weight",
                           "aggregator.global_blocks.0.mlp.fc2.weight", "aggregator.camera_token",
                           "camera_head.pose_branch.fc2.weight", "camera_head.trunk.0.attn.proj.weight",
                           "depth_head.projects.1.weight", "depth_head.scratch.output_conv2.2.weight",
                           "appearance.unet.stem.weight", "appearance.fusion.depth_proj.weight",
                           "appearance.decoder.layers.0.deform_attn.sampling_offsets.weight"}) {
    if (!store.contains(name)) FAIL("no tensor " << name);
    params.push_back({name, store.param(name), store.grad(name)});
  }
  // The probes run forward only; at the unperturbed parameters that loss is scene_gradient's to rounding.
  std::fill(scratch.begin(), scratch.end(), 0.0);
  const double full = model::scene_gradient(ws, *w, scratch.data(), e, sc).loss;
  const double forward = whole_model_forward_loss(ws, *w, e, sc);
  INFO("scene_gradient loss " << full << ", forward-only loss " << forward);
  REQUIRE(forward == Approx(full).epsilon(1e-13).margin(0));
  auto result = testing::check_gradients(
      params, 1, [&](std::span<double> o) { o[0] = whole_model_forward_loss(ws, *w, e, sc); },
      [&](std::span<const double> cot) {
        std::fill(scratch.begin(), scratch.end(), 0.0);
        model::scene_gradient(ws, *w, scratch.data(), e, sc);
        for (index_t i = 0; i < store.size(); ++i) store.grads()[i] += cot[0] * scratch[static_cast<std::size_t>(i)];
      },
      {1e-6, 1e-7, 1e-5, 12});
  INFO(result.summary());
  CHECK(result.ok());
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
  double first = 0, last = 0;
  for (int s = 0; s < steps; ++s) {
    const auto r = model::train_step<float>(ws, *w, batch, 1, sc, 3e-3, static_cast<std::uint64_t>(s), solo);
    REQUIRE(std::isfinite(r.loss));
    if (s == 0) first = r.loss;
    last = r.loss;
  }
  std::printf("train_step on one scene: loss %.5f -> %.5f after %d steps\n", first, last, steps);
  CHECK(last < first / 10);
}
