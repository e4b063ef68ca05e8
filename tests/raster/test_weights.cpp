// Blend weights: a Gaussian alone weighs its alpha summed over the pixels; behind an opaque one it weighs nearly
// nothing; the maximum over views is kept.
#include <catch2/catch.hpp>

#include <vector>

#include "flexsplat/raster/weights.hpp"

using namespace flexsplat;

namespace {
GaussianSet<float> blobs(const std::vector<std::array<float, 3>>& centres, float scale, float opacity) {
  GaussianSet<float> s = make_gaussian_set<float>(static_cast<index_t>(centres.size()), 0);
  for (index_t i = 0; i < s.size(); ++i) {
    for (int k = 0; k < 3; ++k) s.means(i, k) = centres[static_cast<std::size_t>(i)][static_cast<std::size_t>(k)], s.scales(i, k) = scale;
    s.quats(i, 0) = 1;
    s.opacities(i) = opacity;
    for (int ch = 0; ch < 3; ++ch) s.sh(i, 0, ch) = 0.2f;
  }
  return s;
}
}  // namespace

TEST_CASE("max_blend_weights: alpha summed over pixels, occlusion, the maximum over views", "[raster][weights]") {
  const Camera front = look_at({0, -4, 0}, {0, 0, 0}, 64, 64, intrinsics_from_fov(64, 64, 40.0));
  const Camera side = look_at({4, 0, 0}, {0, 0, 0}, 64, 64, intrinsics_from_fov(64, 64, 40.0));
  raster::RenderOptions ro;
  raster::RenderWorkspace<float> ws;
  // Alone: the weight is the sum of the rendered alpha.
  GaussianSet<float> one = blobs({{0.3f, 0, 0.2f}}, 0.08f, 0.7f);
  raster::RenderOutputs<float> out;
  raster::render_forward(one, raster::camera_view<float>(front), ro, ws, out);
  double alpha_sum = 0;
  for (index_t i = 0; i < out.alpha.size(); ++i) alpha_sum += out.alpha.data()[i];
  std::vector<double> w;
  raster::max_blend_weights(one, raster::camera_view<float>(front), ro, ws, w);
  REQUIRE(w.size() == 1);
  CHECK(alpha_sum > 5);  // several pixels' worth: a weight of 0 or 1 would be far off
  CHECK(w[0] == Approx(alpha_sum).epsilon(1e-4));
  // Behind an opaque, larger Gaussian (seen from the front) the small one weighs a fraction of what it does alone;
  // from the side both are seen whole.
  GaussianSet<float> pair = blobs({{0, -1, 0}, {0, 1, 0}}, 0.3f, 0.99f);
  pair.scales(1, 0) = pair.scales(1, 1) = pair.scales(1, 2) = 0.05f;
  std::vector<double> wf, wmax;
  raster::max_blend_weights(pair, raster::camera_view<float>(front), ro, ws, wf);
  CHECK(wf[1] < 0.01 * wf[0]);
  wmax = wf;
  raster::max_blend_weights(pair, raster::camera_view<float>(side), ro, ws, wmax);
  CHECK(wmax[1] > 10 * wf[1]);
  CHECK(wmax[0] >= wf[0]);
  std::vector<double> wrong(3, 0.0);
  CHECK_THROWS_WITH(raster::max_blend_weights(pair, raster::camera_view<float>(front), ro, ws, wrong),
                    Catch::Contains("3 slots for 2 Gaussians"));
}
