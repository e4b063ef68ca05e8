#include <catch2/catch.hpp>

#include <cmath>

#include "flexsplat/raster/brute_force.hpp"
#include "scene_util.hpp"

using namespace rastertest;

namespace {

// The tiled renderer (every skip on, and every skip off) against evaluating every Gaussian at every pixel.
void compare_with_brute_force(const SceneSpec& spec, bool expected_depth = false) {
  auto scene = make_scene<float>(spec);
  scene.options.expected_depth = expected_depth;
  RenderOutputs<float> reference, fast;
  render_brute_force(scene.set(), scene.camera, scene.options, reference);
  for (bool skips_on : {true, false}) {
    RenderOptions opt = scene.options;
    opt.skips.opacity_aware_extent = opt.skips.exact_tile_test = opt.skips.early_exit = skips_on;
    RenderWorkspace<float> ws;
    render_forward(scene.set(), scene.camera, opt, ws, fast);
    double err_image = 0, err_alpha = 0, err_depth = 0, err_feat = 0, depth_max = 0;
    long contrib_total = 0, contrib_mismatch = 0;
    for (index_t i = 0; i < reference.image.size(); ++i)
      err_image = std::max(err_image, double(std::abs(fast.image.data()[i] - reference.image.data()[i])));
    for (index_t i = 0; i < reference.alpha.size(); ++i) {
      err_alpha = std::max(err_alpha, double(std::abs(fast.alpha.data()[i] - reference.alpha.data()[i])));
      // expected depth is a quotient by alpha: its error bound scales with 1 / alpha
      const double scale = expected_depth && reference.alpha.data()[i] > 0 ? reference.alpha.data()[i] : 1.0;
      err_depth = std::max(err_depth, scale * double(std::abs(fast.depth.data()[i] - reference.depth.data()[i])));
      depth_max = std::max(depth_max, double(std::abs(reference.depth.data()[i])));
      contrib_total += reference.n_contrib.data()[i];
      contrib_mismatch += fast.n_contrib.data()[i] != reference.n_contrib.data()[i];
    }
    for (index_t i = 0; i < reference.features.size(); ++i)
      err_feat = std::max(err_feat, double(std::abs(fast.features.data()[i] - reference.features.data()[i])));
    INFO("seed " << spec.seed << " skips " << skips_on << ": image " << err_image << " alpha " << err_alpha
                 << " depth " << err_depth << " features " << err_feat << " contributions " << contrib_total);
    CHECK(contrib_total > 0);
    CHECK(contrib_mismatch == 0);
    CHECK(err_image <= 2e-6);
    CHECK(err_alpha <= 2e-6);
    CHECK(err_depth <= 2e-6 * std::max(1.0, depth_max));
    CHECK(err_feat <= 1e-5);
  }
}

}  // namespace

TEST_CASE("brute force: sparse scenes of every SH degree match", "[raster][brute_force]") {
  for (int degree = 0; degree <= 3; ++degree) {
    SceneSpec spec;
    spec.n = 60;
    spec.sh_degree = degree;
    spec.seed = 10 + degree;
    compare_with_brute_force(spec);
  }
}

TEST_CASE("brute force: dense scene where early termination fires, antialiased, features", "[raster][brute_force]") {
  SceneSpec spec;
  spec.n = 400;
  spec.width = 48, spec.height = 40;
  spec.scale_min = 0.1, spec.scale_max = 0.4;
  spec.opacity_min = 0.5, spec.opacity_max = 0.99;
  spec.features = 5;
  spec.seed = 21;
  compare_with_brute_force(spec);
  spec.antialiased = true;
  spec.seed = 22;
  compare_with_brute_force(spec, true);
}

TEST_CASE("brute force: Gaussians off screen, behind the camera and needle-thin", "[raster][brute_force]") {
  SceneSpec spec;
  spec.n = 120;
  spec.half_extent = 5.0;  // many behind the camera (z < 0), near it, and far off screen
  spec.scale_min = 1e-4, spec.scale_max = 0.5;
  spec.width = 37, spec.height = 29;  // partial tiles
  spec.seed = 31;
  compare_with_brute_force(spec);
}
