#include <catch2/catch.hpp>

#include <nlohmann/json.hpp>

#include "flexsplat/train/run_config.hpp"

using namespace flexsplat;

TEST_CASE("train config: structured_inputs and point_weight are read, checked and named in errors", "[train][config]") {
  nlohmann::json j = {{"model", "tiny"},
                      {"stages", {{{"name", "geometry"}, {"appearance", false}, {"point_weight", 0.5}}}}};
  // The tiny model has no point head: the weight would train nothing.
  CHECK_THROWS_WITH(model::parse_train_config(j), Catch::Contains("point_weight 0.5 but the model has no point head"));
  auto m = model::to_json(model::flexsplat_tiny_config());
  m["geometry"]["point_head"] = true;
  j["model"] = m;
  auto c = model::parse_train_config(j);
  CHECK(c.stages[0].step.point_weight == 0.5);
  CHECK(c.structured_inputs);  // the default keeps old recipes' scenes
  j["structured_inputs"] = false;
  CHECK_FALSE(model::parse_train_config(j).structured_inputs);
  j["structured_inputs"] = "no";
  CHECK_THROWS_WITH(model::parse_train_config(j), Catch::Contains("'structured_inputs' is \"no\""));
  j["structured_inputs"] = false;
  j["stages"][0]["point_weight"] = 0.0;
  CHECK_THROWS_WITH(model::parse_train_config(j), Catch::Contains("point_weight and match_weight are 0"));
}

TEST_CASE("train config: the pilots' removed switches are unknown keys", "[train][config]") {
  for (const char* key : {"decoder_camera_noise_deg", "match_coarse_weight", "match_coarse_cell"}) {
    nlohmann::json j = {{"model", "tiny"}, {"stages", {{{"name", "joint"}, {"decoder_true_cameras", true}}}}};
    REQUIRE_NOTHROW(model::parse_train_config(j));
    j["stages"][0][key] = 1;
    CHECK_THROWS_WITH(model::parse_train_config(j), Catch::Contains(key));
  }
}

TEST_CASE("train config: the baseline curriculum grows linearly, then holds, and is checked", "[train][config]") {
  nlohmann::json j = {{"model", "tiny"}, {"structured_inputs", false},
                      {"curriculum", {{"baseline_deg", {20, 180}}, {"steps", 100u}}}};
  const auto c = model::parse_train_config(j);
  CHECK(c.baseline_at(0) == 20.0);
  CHECK(c.baseline_at(50) == Approx(100.0));
  CHECK(c.baseline_at(100) == 180.0);
  CHECK(c.baseline_at(1000) == 180.0);
  CHECK(model::parse_train_config({{"model", "tiny"}}).baseline_at(7) == 0.0);  // none: independent views
  j["structured_inputs"] = true;
  CHECK_THROWS_WITH(model::parse_train_config(j), Catch::Contains("needs structured_inputs false"));
  j["structured_inputs"] = false;
  j["curriculum"]["baseline_deg"] = {0, 90};
  CHECK_THROWS_WITH(model::parse_train_config(j), Catch::Contains("entry 0 must be in (0, 360]"));
  j["curriculum"] = {{"baseline_deg", {20, 90}}};
  CHECK_THROWS_WITH(model::parse_train_config(j), Catch::Contains("needs 'steps'"));
}

TEST_CASE("train config: match_samples sets the correspondences of a training scene", "[train][config]") {
  CHECK(model::parse_train_config({{"model", "tiny"}}).match_samples == 768);
  const auto c = model::parse_train_config({{"model", "tiny"}, {"match_samples", 3072u}});
  CHECK(c.match_samples == 3072);
  CHECK(model::matches_per_pair(4, c.match_samples) == 256);
  CHECK(model::matches_per_pair(8, c.match_samples) == 54);
  CHECK(model::matches_per_pair(8) == 13);
  CHECK(model::matches_per_pair(8, 100) == 8);  // at least 8 per pair
  CHECK(model::matches_per_pair(1, c.match_samples) == 0);
  CHECK_THROWS_WITH(model::parse_train_config({{"model", "tiny"}, {"match_samples", 0u}}), Catch::Contains("match_samples"));
}

TEST_CASE("train config: a count is read from a signed or an unsigned JSON integer, never from a negative one",
          "[train][config]") {
  nlohmann::json j = {{"model", "tiny"}, {"stages", {{{"name", "geometry"}, {"appearance", false}, {"camera_weight", 1.0}}}}};
  j["seed"] = 12;  // signed in nlohmann's storage, as every integer literal from C++ is
  CHECK(j["seed"].is_number_unsigned() == false);
  CHECK(model::parse_train_config(j).seed == 12u);
  j["seed"] = 13u;
  CHECK(model::parse_train_config(j).seed == 13u);
  j["seed"] = nlohmann::json::parse("14");  // a parsed file's integer
  CHECK(model::parse_train_config(j).seed == 14u);
  j["seed"] = -1;
  CHECK_THROWS_WITH(model::parse_train_config(j), Catch::Contains("'seed' is -1, expected an integer in [0, "));
  j["seed"] = 1.5;
  CHECK_THROWS_WITH(model::parse_train_config(j), Catch::Contains("'seed' is 1.5"));
}

TEST_CASE("train config: procedural sets the procedural objects' family, checked and named in errors", "[train][config]") {
  const auto plain = model::parse_train_config({{"model", "tiny"}});
  CHECK(plain.procedural.blob_fraction == 0.0f);  // the defaults keep old recipes' scenes
  CHECK_FALSE(plain.procedural.attached);
  nlohmann::json j = {{"model", "tiny"},
                      {"procedural", {{"blob_fraction", 0.5}, {"attached", true}, {"soft_textures", true},
                                      {"min_primitives", 2u}, {"max_primitives", 5u}}}};
  const auto c = model::parse_train_config(j);
  CHECK(c.procedural.blob_fraction == 0.5f);
  CHECK(c.procedural.attached);
  CHECK(c.procedural.soft_textures);
  CHECK_FALSE(plain.procedural.soft_textures);
  CHECK(c.procedural.min_primitives == 2);
  CHECK(c.procedural.max_primitives == 5);
  j["procedural"]["blob_fraction"] = 2;
  CHECK_THROWS_WITH(model::parse_train_config(j), Catch::Contains("'procedural.blob_fraction' is 2"));
  j["procedural"]["blob_fraction"] = 0.5;
  j["procedural"]["min_primitives"] = 7u;
  CHECK_THROWS_WITH(model::parse_train_config(j), Catch::Contains("'procedural.min_primitives' 7 exceeds"));
  j["procedural"]["min_primitives"] = 1u;
  j["procedural"]["limbs"] = 3u;
  CHECK_THROWS_WITH(model::parse_train_config(j), Catch::Contains("unknown key 'procedural.limbs'"));
}
