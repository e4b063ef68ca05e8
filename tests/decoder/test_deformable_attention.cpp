#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <utility>

#include "decoder_test_util.hpp"
#include "flexsplat/decoder/deformable_attention.hpp"
#include "flexsplat/testing/gradcheck.hpp"

using namespace flexsplat;

namespace {
struct Setup {
  decoder::MVDeformConfig cfg{8, 3, 2, 2, 3};
  TestRig rig;
  index_t n = 5, fh = 5, fw = 6;
  std::vector<double> x, centres, params, features;
  explicit Setup(index_t views, index_t view_slots = 0) : rig(make_rig(views)) {
    cfg.view_slots = view_slots;
    x = random_normal(n * cfg.dim, 31);
    centres = random_normal(n * 3, 32, 0.4);
    params = random_normal(decoder::MVDeformParamLayout(cfg).size, 33, 0.3);
    features = random_normal(views * cfg.value_dim * fh * fw, 34);
  }
  decoder::FeatureMaps<double> maps() const { return {rig.views, cfg.value_dim, fh, fw, features.data()}; }
};
}  // namespace

TEST_CASE("multi-view deformable attention passes the float64 gradient check", "[decoder][deformable_attention]") {
  // {views, view_slots}: one slot per view, and two slots with views 2 and 3 sharing the second (gradients add).
  for (auto [views, view_slots] : {std::pair<index_t, index_t>{1, 0}, {2, 0}, {3, 2}}) {
    Setup s(views, view_slots);
    decoder::MVDeformCache<double> cache;
    std::vector<double> dx(s.x.size()), dc(s.centres.size()), dp(s.params.size()), df(s.features.size()),
        dK(s.rig.K.size()), dE(s.rig.E.size());
    const decoder::MVDeformParamLayout L(s.cfg);
    const auto size = [](index_t from, index_t to) { return static_cast<std::size_t>(to - from); };
    auto tensors = testing::split_flat(s.params, dp,
                                       {{"value_proj.weight", size(L.value_w, L.value_b)},
                                        {"value_proj.bias", size(L.value_b, L.offset_w)},
                                        {"sampling_offsets.weight", size(L.offset_w, L.offset_b)},
                                        {"sampling_offsets.bias", size(L.offset_b, L.logit_w)},
                                        {"attention_weights.weight", size(L.logit_w, L.logit_b)},
                                        {"attention_weights.bias", size(L.logit_b, L.out_w)},
                                        {"output_proj.weight", size(L.out_w, L.out_b)},
                                        {"output_proj.bias", size(L.out_b, L.size)}});
    tensors.push_back({"x", s.x, dx});
    tensors.push_back({"centres", s.centres, dc});
    tensors.push_back({"features", s.features, df});
    tensors.push_back({"K", s.rig.K, dK});
    tensors.push_back({"world_to_camera", s.rig.E, dE});
    auto result = testing::check_gradients(
        tensors, s.n * s.cfg.dim,
        [&](std::span<double> o) {
          decoder::mv_deform_forward(o.data(), cache, s.x.data(), s.centres.data(), s.n, s.params.data(), s.cfg, s.maps(),
                                     s.rig.geometry());
        },
        [&](std::span<const double> g) {
          decoder::mv_deform_backward(dx.data(), dc.data(), dp.data(), df.data(), {dK.data(), dE.data(), nullptr}, g.data(),
                                      cache, s.x.data(), s.centres.data(), s.params.data(), s.cfg, s.maps(),
                                      s.rig.geometry());
        },
        {1e-6, 1e-7, 1e-5, 48});
    INFO(views << " views, view_slots " << view_slots << ": " << result.summary());
    CHECK(result.ok());
  }
}

TEST_CASE("queries behind every camera get a zero update and finite gradients", "[decoder][deformable_attention]") {
  Setup s(2);
  // The rig looks at the origin from radius 3: a point 100 units behind camera 0 along its axis is behind both.
  for (index_t q = 0; q < s.n; q += 2)
    for (int j = 0; j < 3; ++j) s.centres[3 * q + j] = (j == 1 ? 0.0 : 1e3);
  s.centres[0] = 1e3, s.centres[1] = 1e3, s.centres[2] = 1e3;  // behind or beyond every view
  std::vector<double> out(s.n * s.cfg.dim);
  decoder::MVDeformCache<double> cache;
  // Put query 0 exactly behind both cameras: reflect camera centres through... use a far point with both z < 0.
  const auto& E = s.rig.E;
  const double* X = &s.centres[0];
  bool behind_all = true;
  for (index_t v = 0; v < 2; ++v) behind_all &= E[12 * v + 8] * X[0] + E[12 * v + 9] * X[1] + E[12 * v + 10] * X[2] + E[12 * v + 11] <= 0;
  if (!behind_all) {
    for (int j = 0; j < 3; ++j) s.centres[j] = -1e3 * (E[8 + j] + E[20 + j]);  // against both viewing directions
  }
  decoder::mv_deform_forward(out.data(), cache, s.x.data(), s.centres.data(), s.n, s.params.data(), s.cfg, s.maps(),
                             s.rig.geometry());
  REQUIRE_FALSE(cache.any_visible[0]);
  for (index_t k = 0; k < s.cfg.dim; ++k) CHECK(out[k] == 0.0);
  for (double v : out) REQUIRE(std::isfinite(v));
  std::vector<double> g = random_normal(out.size(), 35), dx(s.x.size()), dc(s.centres.size()), dp(s.params.size()),
                      df(s.features.size()), dK(s.rig.K.size()), dE(s.rig.E.size());
  decoder::mv_deform_backward(dx.data(), dc.data(), dp.data(), df.data(), {dK.data(), dE.data(), nullptr}, g.data(), cache,
                              s.x.data(), s.centres.data(), s.params.data(), s.cfg, s.maps(), s.rig.geometry());
  for (index_t k = 0; k < s.cfg.dim; ++k) CHECK(dx[k] == 0.0);
  for (int j = 0; j < 3; ++j) CHECK(dc[j] == 0.0);
  for (const auto* v : {&dx, &dc, &dp, &df, &dK, &dE})
    for (double e : *v) REQUIRE(std::isfinite(e));
}

TEST_CASE("extreme offsets and off-image centres stay finite", "[decoder][deformable_attention]") {
  Setup s(2);
  const decoder::MVDeformParamLayout P(s.cfg);
  for (index_t i = 0; i < 2 * 3 * 2 * 2; ++i) s.params[P.offset_b + i] = (i % 2 ? -1e30 : 1e30);
  s.centres[3] = 1e6;  // far off to the side: off every image
  std::vector<double> out(s.n * s.cfg.dim);
  decoder::MVDeformCache<double> cache;
  decoder::mv_deform_forward(out.data(), cache, s.x.data(), s.centres.data(), s.n, s.params.data(), s.cfg, s.maps(),
                             s.rig.geometry());
  std::vector<double> g = random_normal(out.size(), 36), dx(s.x.size()), dc(s.centres.size()), dp(s.params.size()),
                      df(s.features.size());
  decoder::mv_deform_backward(dx.data(), dc.data(), dp.data(), df.data(), {}, g.data(), cache, s.x.data(),
                              s.centres.data(), s.params.data(), s.cfg, s.maps(), s.rig.geometry());
  for (const auto* v : {&out, &dx, &dc, &dp, &df})
    for (double e : *v) REQUIRE(std::isfinite(e));
}

TEST_CASE("identical cameras and bad feature maps", "[decoder][deformable_attention]") {
  Setup s(2);
  std::copy(s.rig.E.begin(), s.rig.E.begin() + 12, s.rig.E.begin() + 12);
  std::copy(s.rig.K.begin(), s.rig.K.begin() + 9, s.rig.K.begin() + 9);
  std::vector<double> out(s.n * s.cfg.dim);
  decoder::MVDeformCache<double> cache;
  decoder::mv_deform_forward(out.data(), cache, s.x.data(), s.centres.data(), s.n, s.params.data(), s.cfg, s.maps(),
                             s.rig.geometry());
  for (double v : out) REQUIRE(std::isfinite(v));
  auto maps = s.maps();
  maps.h = 0;
  CHECK_THROWS_WITH(decoder::mv_deform_forward(out.data(), cache, s.x.data(), s.centres.data(), s.n, s.params.data(), s.cfg,
                                               maps, s.rig.geometry()),
                    Catch::Contains("0x6 (zero-size)"));
  maps = s.maps();
  maps.channels = 5;
  CHECK_THROWS_WITH(decoder::mv_deform_forward(out.data(), cache, s.x.data(), s.centres.data(), s.n, s.params.data(), s.cfg,
                                               maps, s.rig.geometry()),
                    Catch::Contains("have 5 channels"));
}

TEST_CASE("with two view slots, reordering views 2..V leaves the update unchanged, with one slot per view it does not",
          "[decoder][deformable_attention]") {
  const index_t views = 3;
  for (index_t view_slots : {2, 0}) {
    Setup s(views, view_slots);
    // The same views in the order 0, 2, 1: features, K and world-to-camera permuted together.
    const index_t order[3] = {0, 2, 1}, fsize = s.cfg.value_dim * s.fh * s.fw;
    TestRig r = s.rig;
    std::vector<double> features(s.features.size());
    for (index_t v = 0; v < views; ++v) {
      const index_t from = order[v];
      std::copy(s.rig.K.begin() + 9 * from, s.rig.K.begin() + 9 * (from + 1), r.K.begin() + 9 * v);
      std::copy(s.rig.E.begin() + 12 * from, s.rig.E.begin() + 12 * (from + 1), r.E.begin() + 12 * v);
      std::copy(s.features.begin() + fsize * from, s.features.begin() + fsize * (from + 1), features.begin() + fsize * v);
    }
    decoder::MVDeformCache<double> cache;
    std::vector<double> a(s.n * s.cfg.dim), b(a.size());
    decoder::mv_deform_forward(a.data(), cache, s.x.data(), s.centres.data(), s.n, s.params.data(), s.cfg, s.maps(),
                               s.rig.geometry());
    decoder::mv_deform_forward(b.data(), cache, s.x.data(), s.centres.data(), s.n, s.params.data(), s.cfg,
                               {views, s.cfg.value_dim, s.fh, s.fw, features.data()}, r.geometry());
    double diff = 0, scale = 0;
    for (std::size_t i = 0; i < a.size(); ++i) diff = std::max(diff, std::abs(a[i] - b[i])), scale = std::max(scale, std::abs(a[i]));
    INFO("view_slots " << view_slots << ": max |difference| " << diff << ", max |update| " << scale);
    REQUIRE(scale > 1e-3);
    if (view_slots == 2) CHECK(diff <= 1e-12 * scale);
    else CHECK(diff > 1e-3 * scale);  // slot identity: the order matters
  }
}

TEST_CASE("view slots: layout size, slot of a view, and more views than slots", "[decoder][deformable_attention]") {
  decoder::MVDeformConfig c{8, 3, 2, 2, 8, 2};
  CHECK(c.slot_count() == 2);
  CHECK(c.slot(0) == 0);
  CHECK(c.slot(1) == 1);
  CHECK(c.slot(7) == 1);
  CHECK(c.used_slots(1) == 1);
  CHECK(c.used_slots(8) == 2);
  decoder::MVDeformConfig per_view{8, 3, 2, 2, 8};
  // Offsets (2 per row) and logits: 3 rows per slot-head-point fewer for every slot not kept.
  CHECK(decoder::MVDeformParamLayout(per_view).size - decoder::MVDeformParamLayout(c).size == 6 * 2 * 2 * (3 * 8 + 3));
}
