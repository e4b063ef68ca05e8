// model::reconstruct, what `flexsplat reconstruct` runs: without compaction it is the prediction itself, compaction
// and the automatic budget keep fewer Gaussians and say so, bad inputs are refused; the turntable strip has its size.
#include <catch2/catch.hpp>

#include <algorithm>
#include <filesystem>
#include <string>
#include <vector>

#include "flexsplat/eval/reconstruct.hpp"
#include "flexsplat/image/image_io.hpp"

using namespace flexsplat;

namespace {
const std::filesystem::path spot = std::filesystem::path(FLEXSPLAT_SOURCE_DIR) / "examples/data/spot/images";
const std::filesystem::path small_model = std::filesystem::path(FLEXSPLAT_SOURCE_DIR) / "models/flexsplat-small.safetensors";

std::vector<Tensor<float, 3>> rig_photos() {
  std::vector<Tensor<float, 3>> rgba;
  for (const char* f : {"008.png", "010.png", "012.png", "014.png"}) rgba.push_back(image::read_float<float>(spot / f, 4));
  return rgba;
}
}  // namespace

TEST_CASE("reconstruct: the prediction itself without compaction, fewer with compaction or the automatic budget",
          "[model][reconstruct]") {
  REQUIRE(std::filesystem::exists(small_model));
  const auto w = model::load_flexsplat<float>(small_model);
  const std::vector<Tensor<float, 3>> rgba = rig_photos();

  model::PredictWorkspace<float> ws;
  model::ModelPhotos<float> photos = model::model_photos<float>(rgba, w->config());
  ws.silhouettes = photos.silhouettes;
  const model::Prediction<float> direct = model::predict<float>(ws, *w, TensorView<const float, 4>(photos.images.view()));

  model::ReconstructOptions o;
  o.compact = false;
  o.names = {"008.png", "010.png", "012.png", "014.png"};
  std::vector<std::string> lines;
  o.log = [&](const std::string& line) { lines.push_back(line); };
  const model::Reconstruction plain = model::reconstruct(*w, rgba, o);
  CHECK(std::ranges::equal(plain.prediction.gaussians.means.span(), direct.gaussians.means.span()));
  CHECK(std::ranges::equal(plain.prediction.gaussians.sh.span(), direct.gaussians.sh.span()));
  CHECK((!plain.refine && !plain.compact));
  REQUIRE(plain.cameras.size() == 4);
  CHECK(plain.cameras[2].name == "012.png");
  CHECK(plain.cameras[0].width == direct.w);
  REQUIRE(!lines.empty());
  CHECK(lines[0] == "predicting at 56 x 56");

  o.compact = true;
  lines.clear();
  const model::Reconstruction compacted = model::reconstruct(*w, rgba, o);
  REQUIRE(compacted.compact);
  CHECK(compacted.compact->before == direct.gaussians.size());
  CHECK(compacted.compact->after == compacted.prediction.gaussians.size());
  // The rig's photos show the object on a white background: most of the 1024 are haze off it (379 kept on the 7
  // objects' views on average); keeping all or none would be a broken filter.
  CHECK(compacted.compact->after < direct.gaussians.size() / 2);
  CHECK(compacted.compact->after > 100);
  CHECK(std::ranges::any_of(lines, [](const std::string& l) { return l.starts_with("compact: "); }));

  o.compact = false;
  o.auto_budget = true;
  lines.clear();
  const model::Reconstruction automatic = model::reconstruct(*w, rgba, o);
  CHECK(automatic.prediction.budget == 1024);
  CHECK(automatic.prediction.budget_queries == automatic.prediction.gaussians.size());
  CHECK(automatic.prediction.budget_queries < 1024);
  CHECK(automatic.prediction.budget_queries > 100);
  CHECK(std::ranges::any_of(lines, [](const std::string& l) { return l.starts_with("--budget auto: the decoder ran "); }));

  // The turntable: 8 frames of 40 x 30 with 7 gaps of 2 pixels, the object drawn (not all white).
  const Tensor<float, 3> strip = model::turntable_strip(plain.prediction, 8, 30, 40);
  CHECK(strip.shape(0) == 30);
  CHECK(strip.shape(1) == 8 * 40 + 7 * 2);
  CHECK(std::ranges::any_of(strip.span(), [](float v) { return v < 0.9f; }));

  model::ReconstructOptions bad;
  bad.cameras = model::CameraSource::given;
  CHECK_THROWS_WITH(model::reconstruct(*w, rgba, bad), Catch::Contains("0 given cameras for 4 photos"));
  bad = {};
  bad.names = {"a.png"};
  CHECK_THROWS_WITH(model::reconstruct(*w, rgba, bad), Catch::Contains("1 names for 4 photos"));
  std::vector<Tensor<float, 3>> many = rgba;
  for (int i = 0; i < 5; ++i) many.push_back(rgba[0]);
  CHECK_THROWS_WITH(model::reconstruct(*w, many, {}), Catch::Contains("9 images; the model takes 1 to"));
  CHECK_THROWS_WITH(model::reconstruct(*w, {}, {}), Catch::Contains("no photos"));
}
