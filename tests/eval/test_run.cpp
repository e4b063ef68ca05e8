#include <catch2/catch.hpp>

#include <cmath>
#include <vector>

#include "flexsplat/eval/run.hpp"
#include "flexsplat/model/config.hpp"

using namespace flexsplat;

TEST_CASE("eval run: means keep not-measured as NaN, the report writes them as null", "[eval][run]") {
  std::vector<model::ObjectEval> results(2);
  results[0].name = "a", results[1].name = "b";
  results[0].model = {10, 0.5, NAN, 2, 0.01, 1};
  results[1].model = {20, 0.7, NAN, 4, 0.03, 3};
  results[0].score_h = results[1].score_h = 8, results[0].score_w = results[1].score_w = 6;
  const model::ObjectScores m = model::mean_scores(model::score_rows(results, &model::ObjectEval::model));
  CHECK(m.psnr == 15);
  CHECK(m.ssim == Approx(0.6));
  CHECK(std::isnan(m.lpips));
  CHECK(m.rotation_error_deg == 3);
  model::EvalOptions o;
  o.white_baseline = true;
  model::EvalExperiment x;
  x.native = false;
  const nlohmann::json j = model::eval_json("m.safetensors", model::flexsplat_tiny_config(), o, x, results);
  CHECK(j["model"] == "m.safetensors");
  CHECK(j["resolution"] == "model");
  CHECK(j["self_attention"] == "full");
  REQUIRE(j["objects"].size() == 2);
  CHECK(j["objects"][1]["name"] == "b");
  CHECK(j["objects"][1]["resolution"] == nlohmann::json({8, 6}));
  CHECK(j["objects"][0]["lpips"].is_null());
  CHECK(j["mean"]["psnr"] == 15.0);
  CHECK_FALSE(j["objects"][0].contains("refine"));
  // The white baseline is reported; the posed fit, not asked for, is not.
  CHECK(j["baselines"].contains("white"));
  CHECK_FALSE(j["baselines"].contains("posed-fit"));
}
