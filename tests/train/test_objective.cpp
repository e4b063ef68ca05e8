#include <catch2/catch.hpp>

#include <cmath>

#include "decoder/decoder_test_util.hpp"
#include "flexsplat/train/objective.hpp"
#include "flexsplat/testing/gradcheck.hpp"

using namespace flexsplat;

namespace {
// Two views of a tiny appearance model, geometry as given inputs, two render views: input view 0 with its predicted
// camera (depth term on, camera gradients) and view 1's camera as a fixed target camera.
struct TinyObjective {
  decoder::ModelConfig cfg;
  index_t n = 12, h = 20, w = 24, fh = 5, fw = 6, fc = 3;
  std::vector<double> params, images, target0, target1, mask0;
  model::GeometryResult<double> g;
  std::vector<model::RenderView<double>> views;
  TinyObjective() {
    cfg.unet = {3, 2, 1};
    cfg.fusion = {fc, 2, 3};
    auto& d = cfg.decoder;
    d.dim = 8, d.ffn = 12, d.heads = 2, d.layers = 2, d.points = 2, d.max_views = 2, d.value_dim = 3, d.max_queries = 16;
    params.resize(decoder::ModelParamLayout(cfg).size);
    decoder::model_init(params.data(), cfg, 5);
    auto noise = random_normal(params.size(), 301, 0.05);
    for (std::size_t i = 0; i < params.size(); ++i) params[i] += noise[i];
    const TestRig rig = make_rig(2, 3.0, w, h, w, h);
    g.resize(2, h, w, fc, fh, fw);
    g.K.assign(rig.K.begin(), rig.K.end());
    g.extrinsics.assign(rig.E.begin(), rig.E.end());
    g.depth.assign(rig.depth.begin(), rig.depth.end());
    const auto conf = random_uniform(g.confidence.size(), 302, 1.0, 3.0);
    g.confidence.assign(conf.begin(), conf.end());
    const auto feat = random_normal(g.features.size(), 303);
    g.features.assign(feat.begin(), feat.end());
    images = random_uniform(2 * 3 * h * w, 304, 0.0, 1.0);
    target0 = random_uniform(h * w * 3, 305, 0.0, 1.0);
    target1 = random_uniform(h * w * 3, 306, 0.0, 1.0);
    mask0 = random_uniform(h * w, 307, 0.0, 1.0);
    model::RenderView<double> v0;
    v0.width = int(w), v0.height = int(h), v0.input_view = 0, v0.target = target0.data(), v0.mask = mask0.data();
    model::RenderView<double> v1;
    std::copy(rig.K.begin() + 9, rig.K.begin() + 18, v1.K.begin());
    std::copy(rig.E.begin() + 12, rig.E.begin() + 24, v1.world_to_camera.begin());
    v1.width = int(w), v1.height = int(h), v1.target = target1.data();
    views = {v0, v1};
  }
};
}  // namespace

TEST_CASE("appearance objective passes the float64 gradient check into parameters and geometry outputs",
          "[model][objective]") {
  TinyObjective t;
  model::ObjectiveWeights weights;
  weights.depth = 0.3;
  weights.lpips = 0.5;
  loss::LpipsWeights<double> lpips(loss::LpipsConfig{{3, 4, 4, 5, 5}});
  std::mt19937_64 rng(41);
  loss::lpips_init_random(std::span<double>(lpips.params), lpips.layout, rng);
  model::ObjectiveWorkspace<double> ws;
  raster::RenderOptions ro;
  ro.background = {1, 1, 1};
  std::vector<double> dp(t.params.size());
  model::GeometryResult<double> dg;
  dg.zero_like(t.g);
  auto run = [&](double* d_params, model::GeometryResult<double>* d_geometry) {
    return model::appearance_objective<double>(ws, t.params.data(), d_params, t.cfg, t.n, t.images.data(), t.g,
                                               d_geometry, t.views, weights, ro, &lpips);
  };
  // The probes run forward only (no gradient pointers), which must score as the full pass does, to the bit.
  {
    std::vector<double> scratch(t.params.size());
    model::GeometryResult<double> sg;
    sg.zero_like(t.g);
    const double full = run(scratch.data(), &sg).total, forward = run(nullptr, nullptr).total;
    INFO("full pass " << full << ", forward only " << forward);
    REQUIRE(forward == full);
  }
  // Junk-seeded by the checker: appearance_objective must add into the parameter and geometry gradients.
  std::vector<testing::GradParam> params = testing::split_flat(t.params, dp, appearance_tensors(t.cfg));
  params.push_back({"extrinsics", t.g.extrinsics, dg.extrinsics});
  params.push_back({"K", t.g.K, dg.K});
  params.push_back({"depth", t.g.depth, dg.depth});
  params.push_back({"features", t.g.features, dg.features});
  testing::GradCheckOptions options;
  options.max_checks_per_param = 3;
  options.unit_cotangent = true;
  auto result = testing::check_gradients(
      params, 1, [&](std::span<double> o) { o[0] = run(nullptr, nullptr).total; },
      [&](std::span<const double>) { run(dp.data(), &dg); }, options);
  INFO(result.summary());
  CHECK(result.ok());
}

TEST_CASE("appearance objective reports its parts and rejects what it cannot score", "[model][objective]") {
  TinyObjective t;
  model::ObjectiveWorkspace<double> ws;
  raster::RenderOptions ro;
  std::vector<double> dp(t.params.size());
  model::ObjectiveWeights weights;
  const auto parts = model::appearance_objective<double>(ws, t.params.data(), dp.data(), t.cfg, t.n, t.images.data(),
                                                         t.g, nullptr, t.views, weights, ro);
  CHECK(parts.rgb_head > 0);
  CHECK(parts.render > 0);
  CHECK(parts.depth > 0);
  CHECK(parts.lpips == 0);
  CHECK(parts.total == Approx(parts.rgb_head + parts.render + parts.depth));
  CHECK(std::isfinite(parts.psnr_last));
  weights.lpips = 1;
  CHECK_THROWS_WITH(model::appearance_objective<double>(ws, t.params.data(), dp.data(), t.cfg, t.n, t.images.data(), t.g,
                                                        nullptr, t.views, weights, ro),
                    Catch::Contains("no LPIPS weights"));
  weights.lpips = 0;
  t.views[0].width = 10;
  CHECK_THROWS_WITH(model::appearance_objective<double>(ws, t.params.data(), dp.data(), t.cfg, t.n, t.images.data(), t.g,
                                                        nullptr, t.views, weights, ro),
                    Catch::Contains("model's input is 24 x 20"));
}
