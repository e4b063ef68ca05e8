#include <catch2/catch.hpp>

#include "flexsplat/core/reference_check.hpp"
#include "flexsplat/geometry/aggregator.hpp"
#include "geometry_test_util.hpp"

using namespace flexsplat;
using namespace flexsplat::geometry;

TEST_CASE("aggregator trunk reproduces the bundle's aggregator outputs from its DINO patch tokens", "[geometry][aggregator]") {
  const auto file = safetensors::File::open(vggt_bundle_path());
  const auto cfg = aggregator_config_from_json(file.metadata("config"));
  io::ParamSource<float> src(file, "param.");
  const auto weights = load_aggregator_trunk_weights(src, cfg);
  CHECK(src.converted_bytes() == 0);  // F32 bundle: every parameter is a zero-copy view
  AggregatorWorkspace<float> ws;
  int cases = 0;
  for (int k = 0; file.contains("case" + std::to_string(k) + ".images"); ++k, ++cases) {
    const std::string p = "case" + std::to_string(k) + ".";
    const auto images = file.get<float, 5>(p + "images");
    const auto tokens = file.get<float, 3>(p + "dino.x_norm_patchtokens");
    const index_t S = images.shape(1), gh = images.shape(3) / cfg.patch_size, gw = images.shape(4) / cfg.patch_size;
    REQUIRE(tokens.shape(1) == gh * gw);
    const auto out = aggregator_trunk_forward<float>(tokens.data(), S, gh, gw, cfg, weights, {}, ws);
    REQUIRE(static_cast<index_t>(out.layers.size()) == cfg.depth);
    for (index_t i = 0; i < cfg.depth; ++i) {
      const std::string name = p + "aggregator.out." + std::to_string(i);
      const auto expected = file.get<float, 4>(name);
      REQUIRE(expected.size() == out.at(i).size());
      ReferenceReport report;
      auto& row = report.compare<float, float>(name, out.at(i).span(), expected.span(), {ToleranceKind::relative_to_max_abs, 1e-4});
      INFO(name << " max_rel " << row.max_rel_error);
      CHECK(row.pass);
    }
  }
  CHECK(cases == 3);
}

TEST_CASE("aggregator keeps only the requested outputs and rejects bad requests", "[geometry][aggregator]") {
  const auto file = safetensors::File::open(vggt_bundle_path());
  const auto cfg = aggregator_config_from_json(file.metadata("config"));
  io::ParamSource<float> src(file, "param.");
  const auto weights = load_aggregator_trunk_weights(src, cfg);
  const auto tokens = file.get<float, 3>("case2.dino.x_norm_patchtokens");
  AggregatorWorkspace<float> ws;
  const auto out = aggregator_trunk_forward<float>(tokens.data(), 1, 4, 4, cfg, weights, {cfg.depth - 1}, ws);
  CHECK(out.layers.size() == 1);
  CHECK_THROWS_WITH(out.at(0), Catch::Contains("not kept"));
  CHECK_THROWS_WITH(aggregator_trunk_forward<float>(tokens.data(), 1, 4, 4, cfg, weights, {cfg.depth}, ws),
                    Catch::Contains("requested"));
}

TEST_CASE("aggregator config parses the bundle JSON and rejects inconsistent values", "[geometry][config]") {
  const auto cfg = aggregator_config_from_json(std::string(R"({"img_size": 98, "patch_size": 14, "embed_dim": 64,
      "depth": 3, "num_heads": 2, "dino_depth": 2, "dino_heads": 2})"));
  CHECK(cfg.embed_dim == 64);
  CHECK(cfg.dino.img_size == 98);
  CHECK(cfg.dino.pos_grid() == 7);
  CHECK(cfg.dino.depth == 2);
  CHECK(cfg.depth == 3);
  CHECK(cfg.qk_norm);
  CHECK(cfg.rope_freq == 100.0);
  const AggregatorConfig def;
  CHECK(def.embed_dim == 1024);
  CHECK(def.dino.depth == 24);
  CHECK_THROWS_WITH(aggregator_config_from_json(std::string(R"({"embed_dim": 60, "num_heads": 7})")),
                    Catch::Contains("num_heads 7"));
  CHECK_THROWS_WITH(aggregator_config_from_json(std::string(R"({"depth": "x"})")),
                    Catch::Contains("'depth' = \"x\" is not an integer"));
  CHECK_THROWS_WITH(aggregator_config_from_json(std::string("{not json")), Catch::Contains("not valid JSON"));
}
