#include <catch2/catch.hpp>

#include "decoder_test_util.hpp"
#include "flexsplat/decoder/fusion.hpp"
#include "flexsplat/testing/gradcheck.hpp"

using namespace flexsplat;

TEST_CASE("fusion and RGB head pass the float64 gradient check", "[decoder][fusion]") {
  decoder::FusionConfig c{3, 2, 4};
  const index_t V = 2, dh = 3, dw = 4, h = 6, w = 7;
  std::mt19937_64 rng(5);
  std::vector<double> params(decoder::FusionParamLayout(c).size);
  decoder::fusion_init(params.data(), c, rng);
  auto depth = random_normal(V * 3 * dh * dw, 81), unet = random_normal(V * 2 * h * w, 82);
  decoder::FusionCache<double> cache;
  std::vector<double> dd(depth.size()), du(unet.size()), dp(params.size());
  const index_t nf = V * 4 * h * w, nr = V * 3 * h * w;
  auto tensors = testing::split_flat(params, dp, appearance_tensors(model_around(c), "fusion."));
  tensors.push_back({"depth_features", depth, dd});
  tensors.push_back({"unet", unet, du});
  auto result = testing::check_gradients(
      tensors, nf + nr,
      [&](std::span<double> o) {
        decoder::fusion_forward(o.data(), o.data() + nf, cache, depth.data(), dh, dw, unet.data(), V, h, w, params.data(), c);
      },
      [&](std::span<const double> g) {
        decoder::fusion_backward(dd.data(), du.data(), dp.data(), g.data(), g.data() + nf, cache, depth.data(), params.data(), c);
      },
      {1e-6, 1e-7, 1e-5, 24});
  INFO(result.summary());
  CHECK(result.ok());
}

TEST_CASE("fusion rejects zero-size feature maps", "[decoder][fusion]") {
  decoder::FusionConfig c{3, 2, 4};
  std::vector<double> params(decoder::FusionParamLayout(c).size), buf(64);
  decoder::FusionCache<double> cache;
  CHECK_THROWS_WITH(decoder::fusion_forward(buf.data(), (double*)nullptr, cache, buf.data(), 0, 2, buf.data(), 1, 2, 2,
                                            params.data(), c),
                    Catch::Contains("zero-size"));
}

TEST_CASE("fusion forward only: the same fused features without backward caches, backward refused",
          "[decoder][fusion]") {
  decoder::FusionConfig c{3, 2, 4};
  const index_t V = 2, dh = 3, dw = 4, h = 6, w = 7;
  std::mt19937_64 rng(6);
  std::vector<double> params(decoder::FusionParamLayout(c).size);
  decoder::fusion_init(params.data(), c, rng);
  const auto depth = random_normal(V * 3 * dh * dw, 83), unet = random_normal(V * 2 * h * w, 84);
  decoder::FusionCache<double> kept, bare;
  bare.keep_for_backward = false;
  std::vector<double> a(V * 4 * h * w), b(a.size()), dp(params.size());
  const auto forward = [&](std::vector<double>& out, decoder::FusionCache<double>& k) {
    decoder::fusion_forward(out.data(), (double*)nullptr, k, depth.data(), dh, dw, unet.data(), V, h, w, params.data(),
                            c);
  };
  forward(a, kept);
  forward(b, bare);
  CHECK(a == b);
  CHECK(bare.refined_pre.empty());
  CHECK(bare.fused.empty());
  CHECK_THROWS_WITH(decoder::fusion_backward((double*)nullptr, (double*)nullptr, dp.data(), a.data(), (double*)nullptr,
                                             bare, depth.data(), params.data(), c),
                    Catch::Contains("keep_for_backward"));
}
