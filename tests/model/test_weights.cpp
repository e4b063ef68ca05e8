#include <catch2/catch.hpp>

#include <algorithm>
#include <cstring>
#include <filesystem>

#include "flexsplat/model/weights.hpp"

using namespace flexsplat;

TEST_CASE("FlexSplat weights bind VGGT tensors into the store and survive save and load", "[model][weights]") {
  const auto c = model::flexsplat_tiny_config();
  auto w = model::FlexSplatWeights<float>::create(c, true);
  w->init(17);
  auto& store = w->store();
  // The geometry structs point into the store: camera token and the depth head's first projection.
  CHECK(w->geometry().aggregator.camera_token == store.param("aggregator.camera_token").data());
  CHECK(w->geometry().depth.projects[0].weight == store.param("depth_head.projects.0.weight").data());
  CHECK(store.segment(model::appearance_segment).size == decoder::ModelParamLayout(c.appearance).size);
  // Initial values follow the rules: LayerNorm weights 1, biases 0, LayerScale init_values.
  CHECK(store.param("aggregator.frame_blocks.0.norm1.weight")[0] == 1.f);
  CHECK(store.param("aggregator.frame_blocks.0.attn.qkv.bias")[3] == 0.f);
  CHECK(store.param("aggregator.frame_blocks.0.ls1.gamma")[0] == Approx(c.geometry.aggregator.init_values));
  CHECK(store.param("aggregator.frame_blocks.0.attn.qkv.weight")[0] != 0.f);

  const auto path = std::filesystem::temp_directory_path() / "flexsplat_test_model_weights.safetensors";
  w->save(path, 42);
  auto back = model::load_flexsplat<float>(path);
  CHECK(back->config().image_h == c.image_h);
  REQUIRE(back->store().size() == store.size());
  CHECK(std::memcmp(back->store().params(), store.params(), sizeof(float) * store.size()) == 0);
  // A different seed gives different weights; the same seed the same.
  auto other = model::FlexSplatWeights<float>::create(c, false);
  other->init(17);
  CHECK(std::memcmp(other->store().params(), store.params(), sizeof(float) * store.size()) == 0);
  other->init(18);
  CHECK(std::memcmp(other->store().params(), store.params(), sizeof(float) * store.size()) != 0);
  std::filesystem::remove(path);
}

TEST_CASE("loading a model of another configuration names the difference", "[model][weights]") {
  auto c = model::flexsplat_tiny_config();
  auto w = model::FlexSplatWeights<float>::create(c, false);
  w->init(1);
  const auto path = std::filesystem::temp_directory_path() / "flexsplat_test_model_other.safetensors";
  w->save(path);
  c.gaussians = 32;
  auto other = model::FlexSplatWeights<float>::create(c, false);
  CHECK_THROWS_WITH(other->load(path), Catch::Contains("configuration differs"));
  std::filesystem::remove(path);
}

TEST_CASE("init_from_model takes every weight of a model of another image size and refuses another architecture",
          "[model][weights]") {
  const auto c = model::flexsplat_tiny_config();
  auto w = model::FlexSplatWeights<float>::create(c, false);
  w->init(3);
  const auto path = std::filesystem::temp_directory_path() / "flexsplat_test_model_init_from.safetensors";
  w->save(path, 7);
  auto larger = c;
  larger.image_h = larger.image_w = 2 * c.image_h;
  auto fine = model::FlexSplatWeights<float>::create(larger, true);
  fine->init(4);
  REQUIRE(std::memcmp(fine->store().params(), w->store().params(), sizeof(float) * w->store().size()) != 0);
  fine->init_from_model(path);
  CHECK(fine->config().image_h == 2 * c.image_h);
  CHECK(std::memcmp(fine->store().params(), w->store().params(), sizeof(float) * w->store().size()) == 0);
  // The loaded model starts the fine-tune with fresh optimizer moments.
  const auto& m = fine->store();
  CHECK(std::all_of(m.adam_m(), m.adam_m() + m.size(), [](float v) { return v == 0.f; }));

  auto wider = c;
  wider.gaussians = 32;
  auto other = model::FlexSplatWeights<float>::create(wider, false);
  CHECK_THROWS_WITH(other->init_from_model(path), Catch::Contains("has another architecture") &&
                                                      Catch::Contains("only the image size may differ"));
  std::filesystem::remove(path);
}
