#include <catch2/catch.hpp>

#include <vector>

#include "flexsplat/geometry/aggregator.hpp"
#include "flexsplat/testing/gradcheck.hpp"
#include "geometry_test_util.hpp"

using namespace flexsplat;
using namespace flexsplat::geometry;

namespace aggregator_backward_test {

AggregatorConfig tiny_aggregator(index_t aa_block_size) {
  AggregatorConfig c;
  c.patch_size = 2;
  c.embed_dim = 8;
  c.depth = 2;
  c.num_heads = 2;
  c.mlp_ratio = 2.0;
  c.num_register_tokens = 1;
  c.init_values = 0.5;
  c.aa_block_size = aa_block_size;
  c.dino.img_size = 6;
  c.dino.patch_size = 2;
  c.dino.embed_dim = 8;
  c.dino.num_heads = 2;
  c.dino.depth = 1;
  return c;
}

template <class T>
struct FlatAggregator {
  AggregatorConfig c;
  std::vector<io::TensorSpec> specs;
  std::vector<T> params, grads;
  io::ParamSource<T> src;
  AggregatorWeights<T> w;
  AggregatorGrads<T> g;
  FlatAggregator(const AggregatorConfig& config, unsigned seed) : c(config) {
    append_aggregator_trunk_specs(specs, c);
    auto v = random_doubles(static_cast<std::size_t>(io::flat_size(specs)), seed, 0.4);
    index_t at = 0;
    for (auto& s : specs) {
      if (s.name.find("norm") != std::string::npos && s.name.find("weight") != std::string::npos)
        for (index_t i = 0; i < io::spec_numel(s); ++i) v[at + i] += 1.0;
      at += io::spec_numel(s);
    }
    params.assign(v.begin(), v.end());
    grads.assign(params.size(), T(0));
    io::add_flat_views(src, specs, params.data());
    w = load_aggregator_trunk_weights(src, c);
    g = aggregator_grads(w, params.data(), grads.data());
  }
  std::vector<testing::GradParam> grad_params() {
    std::vector<testing::GradParam> out;
    index_t at = 0;
    for (auto& s : specs) {
      const auto n = static_cast<std::size_t>(io::spec_numel(s));
      out.push_back({s.name, std::span<T>(params.data() + at, n), std::span<T>(grads.data() + at, n)});
      at += io::spec_numel(s);
    }
    return out;
  }
};

}  // namespace aggregator_backward_test

using namespace aggregator_backward_test;

TEST_CASE("aggregator backward matches central differences (frame/global alternation, camera/register tokens, RoPE)",
          "[geometry][aggregator][backward]") {
  const index_t aa_block_size = GENERATE(1, 2);
  // Gradients for every output, or only for the last (the other left null).
  const bool all_layers = GENERATE(true, false);
  const auto c = tiny_aggregator(aa_block_size);
  FlatAggregator<double> a(c, 5);
  const index_t S = 3, gh = 2, gw = 3, N = c.patch_start_idx() + gh * gw, layer_size = S * N * 2 * c.embed_dim;
  auto tokens = random_doubles(static_cast<std::size_t>(S * gh * gw * c.embed_dim), 6);
  std::vector<double> d_tokens(tokens.size());
  std::vector<index_t> keep;
  if (!all_layers) keep = {c.depth - 1};
  const index_t outputs = all_layers ? c.depth : 1;
  AggregatorWorkspace<double> ws;
  AggregatorCache<double> cache;
  AggregatorBackwardScratch<double> scratch;
  auto forward = [&](std::span<double> out) {
    const auto o = aggregator_trunk_forward<double>(tokens.data(), S, gh, gw, c, a.w, keep, ws);
    index_t at = 0;
    for (const auto& [layer, t] : o.layers) {
      std::copy(t.data(), t.data() + layer_size, out.data() + at);
      at += layer_size;
    }
  };
  auto backward = [&](std::span<const double> d_out) {
    aggregator_trunk_forward_train<double>(tokens.data(), S, gh, gw, c, a.w, keep, cache, aa_block_size == 2, ws);
    std::vector<const double*> d_layers(static_cast<std::size_t>(c.depth), nullptr);
    for (index_t i = 0; i < outputs; ++i) d_layers[static_cast<std::size_t>(c.depth - outputs + i)] = d_out.data() + i * layer_size;
    aggregator_trunk_backward<double>(d_tokens.data(), a.g, d_layers, cache, c, a.w, scratch);
  };
  auto params = a.grad_params();
  params.push_back({"patch_tokens", tokens, d_tokens});
  testing::GradCheckOptions options;
  options.max_checks_per_param = 4;  // 38 tensors; every block kind is checked in full by the block tests
  auto result = testing::check_gradients(params, static_cast<std::size_t>(outputs * layer_size), forward, backward, options);
  INFO(result.summary());
  CHECK(result.ok());
}

TEST_CASE("aggregator: training forward equals inference, recompute gives bit-identical gradients",
          "[geometry][aggregator][backward]") {
  const auto c = tiny_aggregator(1);
  FlatAggregator<float> a(c, 7);
  const index_t S = 2, gh = 3, gw = 2, N = c.patch_start_idx() + gh * gw, layer_size = S * N * 2 * c.embed_dim;
  auto td = random_doubles(static_cast<std::size_t>(S * gh * gw * c.embed_dim), 8);
  const std::vector<float> tokens(td.begin(), td.end());
  auto dd = random_doubles(static_cast<std::size_t>(c.depth * layer_size), 9);
  const std::vector<float> d_out(dd.begin(), dd.end());
  AggregatorWorkspace<float> ws;
  const auto ref = aggregator_trunk_forward<float>(tokens.data(), S, gh, gw, c, a.w, {}, ws);
  std::vector<std::vector<float>> grads, d_tok;
  for (bool recompute : {false, true}) {
    AggregatorCache<float> cache;
    AggregatorBackwardScratch<float> scratch;
    const auto out = aggregator_trunk_forward_train<float>(tokens.data(), S, gh, gw, c, a.w, {}, cache, recompute, ws);
    for (index_t i = 0; i < c.depth; ++i)
      CHECK(std::equal(out.at(i).data(), out.at(i).data() + layer_size, ref.at(i).data()));
    std::vector<float> g(a.params.size(), 0.5f), dt(tokens.size(), 1.0f);
    std::vector<const float*> d_layers{d_out.data(), d_out.data() + layer_size};
    aggregator_trunk_backward<float>(dt.data(), aggregator_grads(a.w, a.params.data(), g.data()), d_layers, cache, c, a.w,
                                     scratch);
    grads.push_back(g);
    d_tok.push_back(dt);
  }
  CHECK(grads[0] == grads[1]);
  CHECK(d_tok[0] == d_tok[1]);
}

TEST_CASE("aggregator backward refuses an unfilled cache or a wrong number of output gradients",
          "[geometry][aggregator][backward]") {
  const auto c = tiny_aggregator(1);
  FlatAggregator<float> a(c, 10);
  AggregatorCache<float> cache;
  AggregatorBackwardScratch<float> scratch;
  std::vector<const float*> d_layers(static_cast<std::size_t>(c.depth), nullptr);
  cache.frames = 1, cache.grid_h = 1, cache.grid_w = 1;
  CHECK_THROWS_WITH(aggregator_trunk_backward<float>(nullptr, a.g, d_layers, cache, c, a.w, scratch),
                    Catch::Contains("cache"));
  d_layers.pop_back();
  CHECK_THROWS_WITH(aggregator_trunk_backward<float>(nullptr, a.g, d_layers, cache, c, a.w, scratch),
                    Catch::Contains("output gradients"));
}
