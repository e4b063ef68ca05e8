#include <catch2/catch.hpp>

#include <cmath>

#include "flexsplat/data/dataset.hpp"
#include "flexsplat/loss/image.hpp"
#include "flexsplat/model/validate.hpp"

using namespace flexsplat;

namespace {
model::TrainExample<float> validation_scene(int inputs, int targets, const model::FlexSplatConfig& c) {
  data::GeneratorConfig g;
  g.size = static_cast<int>(c.image_h);
  data::BatchOptions o;
  o.inputs = inputs, o.targets = targets, o.structured_inputs = false;
  return model::make_train_example<float>(data::generate_batch(g, 1, 5, 0, o)[0], c);
}
}  // namespace

TEST_CASE("validate_scene scores each target's render against it and the cameras against the ground truth",
          "[model][validate]") {
  const auto c = model::flexsplat_tiny_config();
  auto w = model::FlexSplatWeights<float>::create(c, true);
  w->init(3);
  model::ValidationWorkspace<float> ws;
  const auto e = validation_scene(3, 2, c);
  std::vector<Tensor<float, 3>> renders;
  const model::ValidationScore s = model::validate_scene(ws, *w, e, &renders);
  REQUIRE(renders.size() == 2);
  const index_t n = 3 * e.h * e.w;
  const double psnr = 0.5 * (loss::psnr(renders[0].data(), e.target_images.data(), n) +
                             loss::psnr(renders[1].data(), e.target_images.data() + n, n));
  CHECK(s.psnr == Approx(psnr).epsilon(1e-12));
  CHECK(std::isfinite(s.ssim));
  CHECK(s.ssim <= 1.0);
  CHECK(s.rotation_deg >= 0.0);
  CHECK(s.rotation_deg <= 180.0);
  CHECK(s.depth_rel > 0.0);
  CHECK(s.views == 3);
  CHECK(s.targets == 2);

  const model::ValidationScore one = model::validate_scene(ws, *w, validation_scene(1, 1, c));
  CHECK(one.rotation_deg == 0.0);
  CHECK_THROWS_WITH(model::validate_scene(ws, *w, validation_scene(2, 0, c)), Catch::Contains("no target views"));
}
