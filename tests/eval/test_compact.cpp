// compact_splat: a Gaussian hidden from every view, one outside the silhouettes and a degenerate one go; what the
// views show stays, bit for bit.
#include <catch2/catch.hpp>

#include <cmath>
#include <vector>

#include "flexsplat/eval/compact.hpp"

using namespace flexsplat;

TEST_CASE("compact_splat drops the hidden, the outside and the degenerate, and keeps the rest", "[model][compact]") {
  const Camera front = look_at({0, -4, 0}, {0, 0, 0}, 48, 48, intrinsics_from_fov(48, 48, 40.0));
  const Camera left = look_at({-4, 0, 0.5}, {0, 0, 0}, 48, 48, intrinsics_from_fov(48, 48, 40.0));
  // 0: a big opaque body; 1: a small one inside it (hidden from both views); 2: visible, beside it; 3: far outside the
  // silhouettes; 4: a zero scale.
  GaussianSet<float> s = make_gaussian_set<float>(5, 1);
  const float centres[5][3] = {{0, 0, 0}, {0, 0.05f, 0}, {0.6f, 0, 0.3f}, {1.4f, 1.4f, -1.2f}, {0, 0, 0.5f}};
  const float scales[5] = {0.35f, 0.03f, 0.06f, 0.06f, 0.0f};
  for (index_t i = 0; i < 5; ++i) {
    for (int k = 0; k < 3; ++k) s.means(i, k) = centres[i][k], s.scales(i, k) = scales[i];
    s.quats(i, 0) = 1;
    s.opacities(i) = i == 0 ? 0.99f : 0.8f;
  }
  // The silhouettes: everything but Gaussian 3 (alpha from a render of the set without it).
  std::vector<Camera> views{front, left};
  std::vector<float> alpha(2 * 48 * 48);
  GaussianSet<float> object = select_gaussians(s, {0, 1, 2});
  raster::RenderOptions ro;
  raster::RenderWorkspace<float> ws;
  raster::RenderOutputs<float> out;
  for (int v = 0; v < 2; ++v) {
    raster::render_forward(object, raster::camera_view<float>(views[static_cast<std::size_t>(v)]), ro, ws, out);
    std::copy(out.alpha.data(), out.alpha.data() + out.alpha.size(), alpha.begin() + v * 48 * 48);
  }
  GaussianSet<float> c = s;
  const model::CompactReport r = model::compact_splat(c, views, alpha.data());
  CHECK(r.before == 5);
  CHECK(r.degenerate == 1);
  CHECK(r.outside == 1);
  CHECK(r.unseen == 1);
  REQUIRE(r.after == 2);
  CHECK(c.means(0, 0) == s.means(0, 0));
  CHECK(c.means(1, 0) == s.means(2, 0));  // rows 0 and 2 kept in order
  CHECK(c.sh(1, 3, 2) == s.sh(2, 3, 2));
  // Without alpha the outside one is seen, so it stays.
  GaussianSet<float> d = s;
  CHECK(model::compact_splat(d, views).after == 3);
  CHECK_THROWS_WITH(model::compact_splat(d, {}), Catch::Contains("no views"));
}
