#include <catch2/catch.hpp>

#include <cmath>

#include "flexsplat/data/dataset.hpp"
#include "flexsplat/loss/image.hpp"
#include "flexsplat/train/validate.hpp"

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

  CHECK(std::isnan(s.psnr_true_cameras));

  // With the true cameras handed to the decoder (a decoder_true_cameras stage): its own score, the renders are its,
  // and the model-camera score is as before, bit for bit.
  std::vector<Tensor<float, 3>> true_renders;
  const model::ValidationScore t = model::validate_scene(ws, *w, e, &true_renders, true);
  REQUIRE(true_renders.size() == 2);
  const double true_psnr = 0.5 * (loss::psnr(true_renders[0].data(), e.target_images.data(), n) +
                                  loss::psnr(true_renders[1].data(), e.target_images.data() + n, n));
  CHECK(t.psnr_true_cameras == Approx(true_psnr).epsilon(1e-12));
  CHECK(t.psnr == s.psnr);
  CHECK(t.rotation_deg == s.rotation_deg);
  CHECK(std::isfinite(t.ssim_true_cameras));
  // The untrained camera head is far from the truth (its rotation error above), so the two decoders' Gaussians differ.
  REQUIRE(s.rotation_deg > 1.0);
  CHECK(t.psnr_true_cameras != s.psnr);

  const model::ValidationScore one = model::validate_scene(ws, *w, validation_scene(1, 1, c));
  CHECK(one.rotation_deg == 0.0);
  CHECK_THROWS_WITH(model::validate_scene(ws, *w, validation_scene(2, 0, c)), Catch::Contains("no target views"));
}

TEST_CASE("validate_scene with a match head: the ceiling of matching, accuracy and view pairs by baseline",
          "[model][validate][match]") {
  auto c = model::flexsplat_tiny_config();
  c.geometry.match_dim = 8;
  auto w = model::FlexSplatWeights<float>::create(c, true);
  w->init(3);
  model::ValidationWorkspace<float> ws;
  const auto e = validation_scene(3, 1, c);
  REQUIRE_FALSE(e.matches.empty());
  const model::ValidationScore s = model::validate_scene(ws, *w, e);
  // The renderer's correspondences with the true depth and intrinsics place the views (pixel-snapped matches).
  INFO("oracle " << s.matches_oracle_rotation_deg << " deg, RRA@15 " << s.matches_oracle_rra15);
  CHECK(s.matches_oracle_rotation_deg < 5.0);
  CHECK(s.matches_oracle_rra15 == 1.0);
  // Random descriptors: the bins partition the correspondences and the 3 view pairs, hits never exceed counts.
  double matches = 0, pairs = 0, hits = 0;
  for (std::size_t b = 0; b < 4; ++b) {
    matches += s.matches_by_baseline[b], pairs += s.pairs_by_baseline[b], hits += s.match_hits_by_baseline[b];
    CHECK(s.match_hits_by_baseline[b] <= s.matches_by_baseline[b]);
    CHECK(s.pairs_within15_by_baseline[b] <= s.pairs_by_baseline[b]);
  }
  CHECK(matches == static_cast<double>(e.matches.size()));
  CHECK(pairs == 3.0);
  CHECK(hits == Approx(s.match_accuracy * matches).margin(1e-9));
  CHECK(s.match_accuracy_4px >= s.match_accuracy);
}
