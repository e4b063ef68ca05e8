#include <catch2/catch.hpp>

#include <cmath>

#include "decoder_test_util.hpp"
#include "flexsplat/decoder/model.hpp"
#include "flexsplat/testing/gradcheck.hpp"

using namespace flexsplat;

namespace {
struct TinyModel {
  decoder::ModelConfig cfg;
  TestRig rig = make_rig(2);
  index_t n = 5, h = 6, w = 5, dh = 3, dw = 3;
  std::vector<double> params, images, depth_features;
  TinyModel() {
    cfg.unet = {3, 2, 1};
    cfg.fusion = {3, 2, 3};
    auto& d = cfg.decoder;
    d.dim = 8, d.ffn = 12, d.heads = 2, d.layers = 2, d.points = 2, d.max_views = 2, d.value_dim = 3, d.max_queries = 7;
    d.local_attention = true, d.window = 3;
    params.resize(decoder::ModelParamLayout(cfg).size);
    decoder::model_init(params.data(), cfg, 5);
    auto noise = random_normal(params.size(), 201, 0.1);
    for (std::size_t i = 0; i < params.size(); ++i) params[i] += noise[i];
    images = random_uniform(2 * 3 * h * w, 202, 0.0, 1.0);
    depth_features = random_normal(2 * 3 * dh * dw, 203);
  }
};
}  // namespace

TEST_CASE("model chains UNet, fusion and decoder with the RGB head in (0, 1)", "[decoder][model]") {
  TinyModel t;
  decoder::ModelWorkspace<double> ws;
  decoder::model_forward(ws, t.n, t.params.data(), t.cfg, t.images.data(), t.h, t.w, t.depth_features.data(), t.dh, t.dw,
                         t.rig.geometry());
  REQUIRE(ws.gaussians().size() == 3);
  REQUIRE(ws.rgb.size() == static_cast<std::size_t>(2 * 3 * t.h * t.w));
  for (double v : ws.rgb) REQUIRE((v > 0 && v < 1));
  for (const auto& g : ws.gaussians())
    for (double v : g.means.span()) REQUIRE(std::isfinite(v));
  // The decoder really reads the fused features: changing the depth features moves the refined Gaussians.
  const auto before = copy_of(ws.gaussians().back().means.view());
  for (double& v : t.depth_features) v += 0.5;
  decoder::model_forward(ws, t.n, t.params.data(), t.cfg, t.images.data(), t.h, t.w, t.depth_features.data(), t.dh, t.dw,
                         t.rig.geometry());
  double moved = 0;
  for (index_t i = 0; i < before.size(); ++i)
    moved = std::max(moved, std::abs(before.data()[i] - ws.gaussians().back().means.data()[i]));
  CHECK(moved > 1e-6);
}

TEST_CASE("model passes the float64 gradient check end to end (params, depth features, depth, K, extrinsics)",
          "[decoder][model]") {
  TinyModel t;
  decoder::ModelWorkspace<double> ws;
  const index_t per = t.n * flat_set_values, sets = t.cfg.decoder.layers + 1, n_rgb = 2 * 3 * t.h * t.w;
  std::vector<double> dp(t.params.size()), dfeat(t.depth_features.size()), dK(t.rig.K.size()), dE(t.rig.E.size()),
      dD(t.rig.depth.size());
  auto tensors = testing::split_flat(t.params, dp, appearance_tensors(t.cfg));
  tensors.push_back({"depth_features", t.depth_features, dfeat});
  tensors.push_back({"K", t.rig.K, dK});
  tensors.push_back({"world_to_camera", t.rig.E, dE});
  tensors.push_back({"depth", t.rig.depth, dD});
  auto result = testing::check_gradients(
      tensors, per * sets + n_rgb,
      [&](std::span<double> o) {
        decoder::model_forward(ws, t.n, t.params.data(), t.cfg, t.images.data(), t.h, t.w, t.depth_features.data(), t.dh,
                               t.dw, t.rig.geometry());
        double* p = o.data();
        for (const auto& g : ws.gaussians()) p = flatten_set(g, p);
        std::copy(ws.rgb.begin(), ws.rgb.end(), p);
      },
      [&](std::span<const double> g) {
        std::vector<GaussianSetGrad<double>> dg;
        for (index_t s = 0; s < sets; ++s) dg.push_back(unflatten_grad(g.data() + s * per, t.n));
        decoder::model_backward(dp.data(), dfeat.data(), {dK.data(), dE.data(), dD.data()}, dg, g.data() + per * sets, ws,
                                t.params.data(), t.cfg, t.images.data(), t.depth_features.data(), t.rig.geometry());
      },
      {1e-6, 1e-7, 1e-5, 6});
  INFO(result.summary());
  CHECK(result.ok());
}

TEST_CASE("model rejects inconsistent channel counts", "[decoder][model]") {
  TinyModel t;
  t.cfg.fusion.out_channels = 4;
  decoder::ModelWorkspace<double> ws;
  CHECK_THROWS_WITH(decoder::model_forward(ws, t.n, t.params.data(), t.cfg, t.images.data(), t.h, t.w,
                                           t.depth_features.data(), t.dh, t.dw, t.rig.geometry()),
                    Catch::Contains("value_dim 3"));
}
