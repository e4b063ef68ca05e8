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

TEST_CASE("match_accuracy counts correspondences whose nearest descriptor is within a pixel of the true one",
          "[model][validate]") {
  // Two 6 x 6 views, D = 3: view 0's pixel p has the code of p; view 1 holds the same codes shifted right by `shift`.
  const index_t h = 6, w = 6, px = h * w, D = 3;
  auto codes = [&](int shift) {
    std::vector<double> d(static_cast<std::size_t>(2 * px * D));
    for (index_t v = 0; v < 2; ++v)
      for (index_t p = 0; p < px; ++p) {
        const index_t x = p % w, y = p / w, src = v == 0 ? p : y * w + (x - shift + w) % w;
        const double a = 2 * 3.14159265358979 * static_cast<double>(src) / static_cast<double>(px);
        d[static_cast<std::size_t>((v * px + p) * D)] = std::cos(a);
        d[static_cast<std::size_t>((v * px + p) * D + 1)] = std::sin(a);
        d[static_cast<std::size_t>((v * px + p) * D + 2)] = 0.1;
      }
    return d;
  };
  // The truth: pixel (x, y) of view 0 is pixel (x + 1, y) of view 1, for x < 4 (no shift below wraps round).
  std::vector<loss::PixelMatch> truth;
  for (index_t p = 0; p < px; ++p)
    if (p % w < w - 2) truth.push_back({0, p, 1, p + 1});
  CHECK(model::detail::match_accuracy(codes(1).data(), truth, 2, h, w, D) == 1.0);
  CHECK(model::detail::match_accuracy(codes(2).data(), truth, 2, h, w, D) == 1.0);  // one pixel off still counts
  // Three pixels off (each code sits 3 columns, modulo 6, from the truth): none counts.
  CHECK(model::detail::match_accuracy(codes(4).data(), truth, 2, h, w, D) == 0.0);
  CHECK(model::detail::match_accuracy(codes(1).data(), {}, 2, h, w, D) == 0.0);
}
