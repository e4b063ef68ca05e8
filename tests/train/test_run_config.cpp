#include <catch2/catch.hpp>

#include <nlohmann/json.hpp>

#include "flexsplat/train/run_config.hpp"

using namespace flexsplat;

TEST_CASE("train config: structured_inputs and point_weight are read, checked and named in errors", "[train][config]") {
  nlohmann::json j = {{"model", "tiny"},
                      {"stages", {{{"name", "geometry"}, {"appearance", false}, {"point_weight", 0.5}}}}};
  // The tiny model has no point head: the weight would train nothing.
  CHECK_THROWS_WITH(train::parse_train_config(j), Catch::Contains("point_weight 0.5 but the model has no point head"));
  auto m = model::to_json(model::flexsplat_tiny_config());
  m["geometry"]["point_head"] = true;
  j["model"] = m;
  auto c = train::parse_train_config(j);
  CHECK(c.stages[0].step.point_weight == 0.5);
  CHECK(c.structured_inputs);  // the default keeps old recipes' scenes
  j["structured_inputs"] = false;
  CHECK_FALSE(train::parse_train_config(j).structured_inputs);
  j["structured_inputs"] = "no";
  CHECK_THROWS_WITH(train::parse_train_config(j), Catch::Contains("'structured_inputs' is \"no\""));
  j["structured_inputs"] = false;
  j["stages"][0]["point_weight"] = 0.0;
  CHECK_THROWS_WITH(train::parse_train_config(j), Catch::Contains("point_weight are 0"));
}
