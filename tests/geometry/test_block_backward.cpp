#include <catch2/catch.hpp>

#include <cstdint>
#include <vector>

#include "flexsplat/geometry/block.hpp"
#include "flexsplat/testing/gradcheck.hpp"
#include "geometry_test_util.hpp"

using namespace flexsplat;
using namespace flexsplat::geometry;

namespace block_backward_test {

// One block's parameters in a flat block (random, norm weights around 1, LayerScale gammas O(1) so every path counts).
struct FlatBlock {
  BlockConfig c;
  std::vector<io::TensorSpec> specs;
  std::vector<double> params, grads;
  io::ParamSource<double> src;
  BlockWeights<double> w;
  BlockGrads<double> g;
  FlatBlock(const BlockConfig& config, unsigned seed) : c(config) {
    append_block_specs(specs, "blk.", c);
    params = random_doubles(static_cast<std::size_t>(io::flat_size(specs)), seed, 0.4);
    index_t at = 0;
    for (auto& s : specs) {
      if (s.name.find("norm") != std::string::npos && s.name.find("weight") != std::string::npos)
        for (index_t i = 0; i < io::spec_numel(s); ++i) params[at + i] += 1.0;
      at += io::spec_numel(s);
    }
    grads.assign(params.size(), 0.0);
    io::add_flat_views(src, specs, params.data());
    w = load_block_weights(src, "blk.", c);
    g = block_grads(w, params.data(), grads.data());
  }
  std::vector<testing::GradParam> grad_params() {
    std::vector<testing::GradParam> out;
    index_t at = 0;
    for (auto& s : specs) {
      const auto n = static_cast<std::size_t>(io::spec_numel(s));
      out.push_back({s.name, std::span<double>(params.data() + at, n), std::span<double>(grads.data() + at, n)});
      at += io::spec_numel(s);
    }
    return out;
  }
};

std::vector<std::int32_t> grid_positions(index_t batch, index_t tokens, index_t special, index_t grid_w) {
  std::vector<std::int32_t> pos(static_cast<std::size_t>(batch * tokens * 2), 0);
  for (index_t r = 0; r < batch * tokens; ++r) {
    const index_t n = r % tokens;
    if (n < special) continue;
    pos[2 * r] = static_cast<std::int32_t>(1 + (n - special) / grid_w);
    pos[2 * r + 1] = static_cast<std::int32_t>(1 + (n - special) % grid_w);
  }
  return pos;
}

BlockConfig tiny_block(bool qk_norm) {
  BlockConfig c;
  c.dim = 8;
  c.num_heads = 2;
  c.mlp_ratio = 2.0;
  c.qk_norm = qk_norm;
  return c;
}

}  // namespace block_backward_test

using namespace block_backward_test;

TEST_CASE("qk-norm (per-head LayerNorm) backward matches central differences", "[geometry][block][backward]") {
  const index_t rows = 5, heads = 3, hd = 4, stride = 2 * heads * hd + 3;  // strided rows, as in the fused qkv buffer
  auto x = random_doubles(static_cast<std::size_t>(rows * stride), 1);
  auto gamma = random_doubles(static_cast<std::size_t>(hd), 2, 0.5), beta = random_doubles(static_cast<std::size_t>(hd), 3);
  for (auto& v : gamma) v += 1.0;
  std::vector<double> dx(x.size()), dgamma(gamma.size()), dbeta(beta.size()), stats(static_cast<std::size_t>(2 * rows * heads));
  const double eps = 1e-5;
  auto forward = [&](std::span<double> out) {
    std::copy(x.begin(), x.end(), out.begin());
    geometry::detail::head_layernorm_inplace(out.data(), rows, stride, heads, hd, gamma.data(), beta.data(), eps);
  };
  auto backward = [&](std::span<const double> d_out) {
    geometry::detail::head_layernorm_backward(dx.data(), dgamma.data(), dbeta.data(), d_out.data(), x.data(), rows, stride, heads, hd,
                                    gamma.data(), eps, stats.data());
    // Entries outside the heads pass through unchanged.
    for (index_t r = 0; r < rows; ++r)
      for (index_t i = heads * hd; i < stride; ++i) dx[r * stride + i] += d_out[r * stride + i];
  };
  auto result = testing::check_gradients({{"x", x, dx}, {"gamma", gamma, dgamma}, {"beta", beta, dbeta}}, x.size(), forward,
                                         backward);
  INFO(result.summary());
  CHECK(result.ok());
}

TEST_CASE("2-D RoPE backward matches central differences", "[geometry][rope][backward]") {
  const index_t rows = 6, heads = 2, hd = 8, stride = 20;
  const auto table = rope2d_table<double>(hd, 5, 100.0);
  const auto pos = grid_positions(1, rows, 1, 2);
  auto x = random_doubles(static_cast<std::size_t>(rows * stride), 4);
  std::vector<double> dx(x.size());
  auto forward = [&](std::span<double> out) {
    std::copy(x.begin(), x.end(), out.begin());
    rope2d_forward(out.data(), rows, stride, heads, hd, pos.data(), table);
  };
  auto backward = [&](std::span<const double> d_out) {
    rope2d_backward(dx.data(), d_out.data(), rows, stride, heads, hd, pos.data(), table);
    for (index_t r = 0; r < rows; ++r)
      for (index_t i = heads * hd; i < stride; ++i) dx[r * stride + i] += d_out[r * stride + i];
  };
  auto result = testing::check_gradients({{"x", x, dx}}, x.size(), forward, backward);
  INFO(result.summary());
  CHECK(result.ok());
}

TEST_CASE("block backward matches central differences (qk-norm, RoPE, LayerScale)", "[geometry][block][backward]") {
  const bool qk_norm = GENERATE(false, true);
  const bool use_rope = GENERATE(false, true);
  const bool recompute = GENERATE(false, true);
  FlatBlock b(tiny_block(qk_norm), 10);
  const index_t batch = 2, tokens = 7, rows = batch * tokens, C = b.c.dim;
  const auto pos = grid_positions(batch, tokens, 1, 3);
  const auto table = rope2d_table<double>(b.c.head_dim(), 4, 100.0);
  const Rope2DTable<double>* rope = use_rope ? &table : nullptr;
  const std::int32_t* positions = use_rope ? pos.data() : nullptr;
  auto x = random_doubles(static_cast<std::size_t>(rows * C), 11);
  std::vector<double> dx(x.size());
  BlockWorkspace<double> ws;
  BlockCache<double> cache;
  BlockBackwardScratch<double> scratch;
  auto forward = [&](std::span<double> out) {
    std::copy(x.begin(), x.end(), out.begin());
    block_forward(out.data(), batch, tokens, b.c, b.w, rope, positions, ws.get(b.c, rows));
  };
  auto backward = [&](std::span<const double> d_out) {
    std::vector<double> y = x, d(d_out.begin(), d_out.end());
    block_forward_train(y.data(), batch, tokens, b.c, b.w, rope, positions, cache, recompute, ws.get(b.c, rows));
    block_backward(d.data(), b.g, cache, b.c, b.w, rope, positions, scratch);
    for (std::size_t i = 0; i < d.size(); ++i) dx[i] += d[i];
  };
  auto params = b.grad_params();
  for (auto& p : params)
    if (!use_rope && p.name == "blk.attn.k_norm.bias")
      p.zero_reason = "without RoPE it shifts all of a query's logits by the same q.b, which the softmax ignores";
  params.push_back({"x", x, dx});
  auto result = testing::check_gradients(params, x.size(), forward, backward);
  INFO(result.summary());
  CHECK(result.ok());
}

TEST_CASE("block backward over more rows than one MLP chunk", "[geometry][block][backward]") {
  BlockConfig c = tiny_block(true);
  c.dim = 4;
  c.num_heads = 1;
  FlatBlock b(c, 20);
  const index_t batch = 8, tokens = 130, rows = batch * tokens;  // > block_mlp_chunk_rows
  REQUIRE(rows > block_mlp_chunk_rows);
  const auto pos = grid_positions(batch, tokens, 4, 11);
  const auto table = rope2d_table<double>(c.head_dim(), 13, 100.0);
  auto x = random_doubles(static_cast<std::size_t>(rows * c.dim), 21);
  std::vector<double> dx(x.size());
  BlockWorkspace<double> ws;
  BlockCache<double> cache;
  BlockBackwardScratch<double> scratch;
  auto forward = [&](std::span<double> out) {
    std::copy(x.begin(), x.end(), out.begin());
    block_forward(out.data(), batch, tokens, b.c, b.w, &table, pos.data(), ws.get(b.c, rows));
  };
  auto backward = [&](std::span<const double> d_out) {
    std::vector<double> y = x, d(d_out.begin(), d_out.end());
    block_forward_train(y.data(), batch, tokens, b.c, b.w, &table, pos.data(), cache, false, ws.get(b.c, rows));
    block_backward(d.data(), b.g, cache, b.c, b.w, &table, pos.data(), scratch);
    for (std::size_t i = 0; i < d.size(); ++i) dx[i] += d[i];
  };
  // The chunked part: the MLP half and the input (the attention half is checked on few rows above).
  std::vector<testing::GradParam> params;
  for (auto& p : b.grad_params())
    if (p.name.find("mlp.") != std::string::npos || p.name.find("norm2") != std::string::npos ||
        p.name.find("ls2") != std::string::npos)
      params.push_back(p);
  params.push_back({"x", x, dx});
  testing::GradCheckOptions options;
  options.max_checks_per_param = 4;
  // 4160 outputs: the objective's round-off over a 1e-6 step is ~5e-7, so a 1e-5 step (truncation error ~1e-10).
  options.step = 1e-5;
  auto result = testing::check_gradients(params, x.size(), forward, backward, options);
  INFO(result.summary());
  CHECK(result.ok());
}

TEST_CASE("block: training forward equals inference forward, recompute gives bit-identical gradients",
          "[geometry][block][backward]") {
  BlockConfig c;
  c.dim = 32;
  c.num_heads = 4;
  c.qk_norm = true;
  std::vector<io::TensorSpec> specs;
  append_block_specs(specs, "b.", c);
  std::vector<float> params(static_cast<std::size_t>(io::flat_size(specs)));
  auto rnd = random_doubles(params.size(), 30, 0.2);
  std::copy(rnd.begin(), rnd.end(), params.begin());
  io::ParamSource<float> src;
  io::add_flat_views(src, specs, params.data());
  const auto w = load_block_weights(src, "b.", c);
  const index_t batch = 3, tokens = 70, rows = batch * tokens;  // two query blocks of the tiled attention
  const auto pos = grid_positions(batch, tokens, 5, 8);
  const auto table = rope2d_table<float>(c.head_dim(), 10, 100.0);
  auto xd = random_doubles(static_cast<std::size_t>(rows * c.dim), 31);
  const std::vector<float> x(xd.begin(), xd.end());
  auto dd = random_doubles(x.size(), 32);
  const std::vector<float> d_out(dd.begin(), dd.end());
  BlockWorkspace<float> ws;

  std::vector<float> y_inf = x;
  block_forward(y_inf.data(), batch, tokens, c, w, &table, pos.data(), ws.get(c, rows));
  std::vector<std::vector<float>> grads, d_in;
  for (bool recompute : {false, true}) {
    std::vector<float> y = x, d = d_out, g(params.size(), 0.5f);
    BlockCache<float> cache;
    BlockBackwardScratch<float> scratch;
    block_forward_train(y.data(), batch, tokens, c, w, &table, pos.data(), cache, recompute, ws.get(c, rows));
    CHECK(y == y_inf);
    block_backward(d.data(), block_grads(w, params.data(), g.data()), cache, c, w, &table, pos.data(), scratch);
    grads.push_back(g);
    d_in.push_back(d);
  }
  CHECK(grads[0] == grads[1]);
  CHECK(d_in[0] == d_in[1]);
  CHECK(block_cache_elements(c, rows, true) == rows * c.dim);
}

TEST_CASE("block_grads rebases weight pointers into the gradient block, null stays null", "[geometry][block][backward]") {
  BlockConfig c = tiny_block(false);
  c.layer_scale = false;
  FlatBlock b(c, 40);
  CHECK(b.g.q_norm_weight == nullptr);
  CHECK(b.g.ls1 == nullptr);
  CHECK(b.g.norm1_weight == b.grads.data());
  CHECK(b.g.fc2_bias - b.grads.data() == b.w.fc2_bias - b.params.data());
}

TEST_CASE("block backward refuses a cache from another shape", "[geometry][block][backward]") {
  FlatBlock b(tiny_block(false), 50);
  BlockCache<double> cache;
  BlockBackwardScratch<double> scratch;
  BlockWorkspace<double> ws;
  auto x = random_doubles(static_cast<std::size_t>(4 * b.c.dim), 51);
  block_forward_train<double>(x.data(), 1, 4, b.c, b.w, nullptr, nullptr, cache, false, ws.get(b.c, 4));
  cache.tokens = 5;
  std::vector<double> d(5 * b.c.dim);
  CHECK_THROWS_WITH(block_backward<double>(d.data(), b.g, cache, b.c, b.w, nullptr, nullptr, scratch), Catch::Contains("cache"));
}
