#include <catch2/catch.hpp>

#include "decoder_test_util.hpp"
#include "flexsplat/decoder/unet.hpp"
#include "flexsplat/testing/gradcheck.hpp"

using namespace flexsplat;

TEST_CASE("UNet keeps the input resolution (odd sizes too) and passes the float64 gradient check", "[decoder][unet]") {
  for (const auto& size : {std::pair<index_t, index_t>{8, 8}, {7, 5}}) {
    const index_t h = size.first, w = size.second;  // named variables: lambdas below capture them
    decoder::UNetConfig c{3, 2, 2};
    std::mt19937_64 rng(3);
    std::vector<double> params(decoder::unet_param_count(c));
    decoder::unet_init(params.data(), c, rng);
    auto noise = random_normal(params.size(), 71, 0.05);
    for (std::size_t i = 0; i < params.size(); ++i) params[i] += noise[i];
    auto images = random_normal(2 * 3 * h * w, 72);
    decoder::UNetCache<double> cache;
    std::vector<double> dimg(images.size()), dp(params.size());
    auto tensors = testing::split_flat(params, dp, appearance_tensors(model_around(c), "unet."));
    tensors.push_back({"images", images, dimg});
    auto result = testing::check_gradients(
        tensors, 2 * 2 * h * w,
        [&](std::span<double> o) { decoder::unet_forward(o.data(), cache, images.data(), 2, h, w, params.data(), c); },
        [&](std::span<const double> g) {
          decoder::unet_backward(dimg.data(), dp.data(), g.data(), cache, images.data(), params.data(), c);
        },
        {1e-6, 1e-7, 1e-5, 24});
    INFO(h << "x" << w << ": " << result.summary());
    CHECK(result.ok());
  }
}

TEST_CASE("UNet rejects zero-size input", "[decoder][unet]") {
  decoder::UNetConfig c{3, 2, 1};
  std::vector<double> params(decoder::unet_param_count(c)), out(16);
  decoder::UNetCache<double> cache;
  CHECK_THROWS_WITH(decoder::unet_forward(out.data(), cache, out.data(), 1, 0, 4, params.data(), c),
                    Catch::Contains("0x4 (zero-size)"));
}

TEST_CASE("UNet cache: a repeated forward reuses its buffers, and another size in between leaves no stale state",
          "[decoder][unet]") {
  decoder::UNetConfig c{3, 2, 2};
  std::mt19937_64 rng(5);
  std::vector<double> params(decoder::unet_param_count(c));
  decoder::unet_init(params.data(), c, rng);
  const auto big = random_normal(2 * 3 * 9 * 7, 73), small = random_normal(3 * 5 * 6, 74);
  decoder::UNetCache<double> cache, fresh;
  std::vector<double> first(2 * 2 * 9 * 7), again(first.size()), other(2 * 5 * 6), expected(other.size());
  decoder::unet_forward(first.data(), cache, big.data(), 2, 9, 7, params.data(), c);
  std::vector<const double*> buffers;
  for (const auto& v : cache.post) buffers.push_back(v.data());
  decoder::unet_forward(other.data(), cache, small.data(), 1, 5, 6, params.data(), c);
  decoder::unet_forward(expected.data(), fresh, small.data(), 1, 5, 6, params.data(), c);
  CHECK(other == expected);
  decoder::unet_forward(again.data(), cache, big.data(), 2, 9, 7, params.data(), c);
  CHECK(again == first);
  for (std::size_t i = 0; i < buffers.size(); ++i) CHECK(cache.post[i].data() == buffers[i]);
}

TEST_CASE("UNet forward only: the same output from the skips and two spare buffers, any size order, backward refused",
          "[decoder][unet]") {
  decoder::UNetConfig c{3, 2, 2};
  std::mt19937_64 rng(7);
  std::vector<double> params(decoder::unet_param_count(c));
  decoder::unet_init(params.data(), c, rng);
  const auto images = random_normal(2 * 3 * 9 * 7, 75), small = random_normal(3 * 5 * 6, 76);
  decoder::UNetCache<double> kept, bare;
  bare.keep_for_backward = false;
  std::vector<double> a(2 * 2 * 9 * 7), b(a.size()), dp(params.size());
  decoder::unet_forward(a.data(), kept, images.data(), 2, 9, 7, params.data(), c);
  decoder::unet_forward(b.data(), bare, images.data(), 2, 9, 7, params.data(), c);
  CHECK(a == b);
  // only the skips (the first conv's and the first down level's outputs) keep a buffer of their own
  const auto convs = decoder::unet_convs(c);
  for (std::size_t i = 0; i < convs.size(); ++i) {
    INFO("conv " << i);
    CHECK(bare.pre[i].empty());
    CHECK(bare.post[i].empty() == (i != 0 && i != 2));
  }
  std::vector<double> other(2 * 5 * 6), expected(other.size()), again(a.size());
  decoder::unet_forward(other.data(), bare, small.data(), 1, 5, 6, params.data(), c);
  decoder::unet_forward(expected.data(), kept, small.data(), 1, 5, 6, params.data(), c);
  CHECK(other == expected);
  decoder::unet_forward(again.data(), bare, images.data(), 2, 9, 7, params.data(), c);
  CHECK(again == a);
  CHECK_THROWS_WITH(
      decoder::unet_backward((double*)nullptr, dp.data(), a.data(), bare, images.data(), params.data(), c),
      Catch::Contains("keep_for_backward"));
}
