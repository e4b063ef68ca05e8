#include <catch2/catch.hpp>

#include <vector>

#include "flexsplat/geometry/dino.hpp"
#include "flexsplat/testing/gradcheck.hpp"
#include "geometry_test_util.hpp"

using namespace flexsplat;
using namespace flexsplat::geometry;

namespace dino_backward_test {

DinoConfig tiny_dino() {
  DinoConfig c;
  c.img_size = 6;
  c.patch_size = 2;  // 3 x 3 position grid
  c.embed_dim = 8;
  c.depth = 2;
  c.num_heads = 2;
  c.mlp_ratio = 2.0;
  c.num_register_tokens = 2;
  c.init_values = 0.5;
  return c;
}

// Every DINO parameter in one flat block; norm weights around 1.
struct FlatDino {
  DinoConfig c;
  std::vector<io::TensorSpec> specs;
  std::vector<double> params, grads;
  io::ParamSource<double> src;
  DinoWeights<double> w;
  DinoGrads<double> g;
  FlatDino(const DinoConfig& config, unsigned seed) : c(config) {
    append_dino_specs(specs, "dino.", c);
    params = random_doubles(static_cast<std::size_t>(io::flat_size(specs)), seed, 0.4);
    index_t at = 0;
    for (auto& s : specs) {
      if (s.name.find("norm") != std::string::npos && s.name.find("weight") != std::string::npos)
        for (index_t i = 0; i < io::spec_numel(s); ++i) params[at + i] += 1.0;
      at += io::spec_numel(s);
    }
    grads.assign(params.size(), 0.0);
    io::add_flat_views(src, specs, params.data());
    w = load_dino_weights(src, "dino.", c);
    g = dino_grads(w, params.data(), grads.data());
  }
  std::vector<testing::GradParam> grad_params() {
    std::vector<testing::GradParam> out;
    index_t at = 0;
    for (auto& s : specs) {
      const auto n = static_cast<std::size_t>(io::spec_numel(s));
      out.push_back({s.name, std::span<double>(params.data() + at, n), std::span<double>(grads.data() + at, n),
                     s.name.find("mask_token") != std::string::npos ? "stored, never read (nothing is masked)" : ""});
      at += io::spec_numel(s);
    }
    return out;
  }
};

}  // namespace dino_backward_test

using namespace dino_backward_test;

TEST_CASE("position-embedding resize backward is the exact adjoint of the forward", "[geometry][dino][backward]") {
  const index_t C = 3, M = 5;
  const auto [oh, ow] = GENERATE(table<index_t, index_t>({{5, 5}, {3, 7}, {8, 2}, {5, 9}, {2, 5}}));
  auto src = random_doubles(static_cast<std::size_t>(C * M * M), 1);
  auto cot = random_doubles(static_cast<std::size_t>(C * oh * ow), 2);
  std::vector<double> out(cot.size()), adj(src.size(), 0.0);
  AntialiasWorkspace<double> ws;
  interpolate_bicubic_antialias<double>(src.data(), C, M, M, out.data(), oh, ow, ws);
  geometry::detail::interpolate_bicubic_antialias_backward(adj.data(), cot.data(), C, M, M, oh, ow, {});
  double lhs = 0, rhs = 0, scale = 0;
  for (std::size_t i = 0; i < out.size(); ++i) lhs += out[i] * cot[i], scale += std::abs(out[i] * cot[i]);
  for (std::size_t i = 0; i < src.size(); ++i) rhs += src[i] * adj[i];
  CHECK(std::abs(lhs - rhs) <= 1e-13 * scale);
}

TEST_CASE("DINO backward matches central differences (patch conv, tokens, resized position embedding, blocks, norm)",
          "[geometry][dino][backward]") {
  DinoConfig c = tiny_dino();
  // 6 x 6: the native grid; 4 x 8: position grid resized 3 -> 2 and 3 -> 4; the offset path as DINOv2's legacy one.
  const auto row = GENERATE(table<index_t, index_t, double>({{6, 6, 0.0}, {4, 8, 0.0}, {4, 8, 0.1}}));
  const auto H = std::get<0>(row), W = std::get<1>(row);  // variables, not bindings: the lambdas below capture them
  const double offset = std::get<2>(row);
  c.interpolate_offset = offset;
  FlatDino d(c, 3);
  const index_t S = 2, P = (H / c.patch_size) * (W / c.patch_size);
  auto images = random_doubles(static_cast<std::size_t>(S * 3 * H * W), 4);
  std::vector<double> d_images(images.size());
  DinoWorkspace<double> ws;
  DinoCache<double> cache;
  DinoBackwardScratch<double> scratch;
  auto forward = [&](std::span<double> out) { dino_forward(out.data(), images.data(), S, H, W, c, d.w, ws); };
  auto backward = [&](std::span<const double> d_out) {
    std::vector<double> out(d_out.size());
    // The offset case runs with recompute on, so the recomputing path is checked too.
    dino_forward_train(out.data(), images.data(), S, H, W, c, d.w, cache, offset != 0.0, ws);
    dino_backward(d_images.data(), d.g, d_out.data(), cache, c, d.w, scratch);
  };
  auto params = d.grad_params();
  params.push_back({"images", images, d_images});
  testing::GradCheckOptions options;
  options.max_checks_per_param = 8;  // 33 tensors: the blocks are checked in full by the block tests
  auto result = testing::check_gradients(params, static_cast<std::size_t>(S * P * c.embed_dim), forward, backward, options);
  INFO(result.summary());
  CHECK(result.ok());
}

TEST_CASE("DINO: training forward equals inference, recompute gives bit-identical gradients", "[geometry][dino][backward]") {
  const DinoConfig c = tiny_dino();
  std::vector<io::TensorSpec> specs;
  append_dino_specs(specs, "d.", c);
  auto rnd = random_doubles(static_cast<std::size_t>(io::flat_size(specs)), 7, 0.3);
  const std::vector<float> params(rnd.begin(), rnd.end());
  io::ParamSource<float> src;
  io::add_flat_views(src, specs, params.data());
  const auto w = load_dino_weights(src, "d.", c);
  const index_t S = 2, H = 4, W = 8, P = 8;
  auto id = random_doubles(static_cast<std::size_t>(S * 3 * H * W), 8);
  const std::vector<float> images(id.begin(), id.end());
  auto dd = random_doubles(static_cast<std::size_t>(S * P * c.embed_dim), 9);
  const std::vector<float> d_out(dd.begin(), dd.end());
  DinoWorkspace<float> ws;
  std::vector<float> ref(d_out.size());
  dino_forward(ref.data(), images.data(), S, H, W, c, w, ws);
  std::vector<std::vector<float>> grads, d_img;
  for (bool recompute : {false, true}) {
    std::vector<float> out(d_out.size()), g(params.size(), 0.25f), di(images.size(), -1.0f);
    DinoCache<float> cache;
    DinoBackwardScratch<float> scratch;
    dino_forward_train(out.data(), images.data(), S, H, W, c, w, cache, recompute, ws);
    CHECK(out == ref);
    dino_backward(di.data(), dino_grads(w, params.data(), g.data()), d_out.data(), cache, c, w, scratch);
    grads.push_back(g);
    d_img.push_back(di);
  }
  CHECK(grads[0] == grads[1]);
  CHECK(d_img[0] == d_img[1]);
}

TEST_CASE("ImageNet normalisation backward matches central differences", "[geometry][dino][backward]") {
  auto images = random_doubles(2 * 3 * 2 * 3, 12);
  std::vector<double> d(images.size());
  auto result = testing::check_gradients(
      {{"images", images, d}}, images.size(),
      [&](std::span<double> out) { imagenet_normalize(out.data(), images.data(), 2, 2, 3); },
      [&](std::span<const double> d_out) { imagenet_normalize_backward(d.data(), d_out.data(), 2, 2, 3); });
  INFO(result.summary());
  CHECK(result.ok());
}
