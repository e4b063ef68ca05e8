#include <catch2/catch.hpp>

#include "flexsplat/core/reference_check.hpp"
#include "flexsplat/geometry/dino.hpp"
#include "geometry_test_util.hpp"

using namespace flexsplat;
using namespace flexsplat::geometry;

TEST_CASE("DINO patch embedder reproduces the bundle's x_norm_patchtokens (pos-embed down- and up-scaled)", "[geometry][dino]") {
  const auto file = safetensors::File::open(vggt_bundle_path());
  const auto cfg = aggregator_config_from_json(file.metadata("config"));
  io::ParamSource<float> src(file, "param.");
  const auto weights = load_dino_weights(src, "aggregator.patch_embed.", cfg.dino);
  DinoWorkspace<float> ws;
  int cases = 0;
  for (int k = 0; file.contains("case" + std::to_string(k) + ".images"); ++k, ++cases) {
    const std::string p = "case" + std::to_string(k) + ".";
    const auto images = file.get<float, 5>(p + "images");
    const auto expected = file.get<float, 3>(p + "dino.x_norm_patchtokens");
    const index_t S = images.shape(1), H = images.shape(3), W = images.shape(4);
    std::vector<float> normalized(images.size()), out(expected.size());
    imagenet_normalize(normalized.data(), images.data(), S, H, W);
    dino_forward(out.data(), normalized.data(), S, H, W, cfg.dino, weights, ws);
    ReferenceReport report;
    auto& row = report.compare<float, float>(p + "dino", std::span<const float>(out), expected.span(),
                                             {ToleranceKind::relative_to_max_abs, 1e-4});
    INFO(p << " max_rel " << row.max_rel_error);
    CHECK(row.pass);
  }
  CHECK(cases == 3);
}

TEST_CASE("DINO position embedding is unchanged on the native square grid", "[geometry][dino]") {
  const auto file = safetensors::File::open(vggt_bundle_path());
  const auto cfg = aggregator_config_from_json(file.metadata("config"));
  io::ParamSource<float> src(file, "param.");
  const auto weights = load_dino_weights(src, "aggregator.patch_embed.", cfg.dino);
  const index_t M = cfg.dino.pos_grid(), C = cfg.embed_dim;
  const auto pos = dino_position_embedding(cfg.dino, weights, M * cfg.patch_size, M * cfg.patch_size);
  REQUIRE(pos.size() == (1 + M * M) * C);
  CHECK(std::equal(pos.data(), pos.data() + pos.size(), weights.pos_embed));
}

TEST_CASE("DINO rejects images that are not whole patches", "[geometry][dino]") {
  const auto file = safetensors::File::open(vggt_bundle_path());
  const auto cfg = aggregator_config_from_json(file.metadata("config"));
  io::ParamSource<float> src(file, "param.");
  const auto weights = load_dino_weights(src, "aggregator.patch_embed.", cfg.dino);
  DinoWorkspace<float> ws;
  std::vector<float> img(3 * 30 * 28), out(100 * cfg.embed_dim);
  CHECK_THROWS_WITH(dino_forward(out.data(), img.data(), 1, 30, 28, cfg.dino, weights, ws),
                    Catch::Contains("multiple of the patch size 14"));
}
