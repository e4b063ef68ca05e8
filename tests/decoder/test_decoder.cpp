#include <catch2/catch.hpp>

#include <algorithm>

#include <atomic>
#include <cmath>
#include <cstdlib>
#include <new>
#include <tuple>

#include "decoder_test_util.hpp"
#include "flexsplat/decoder/decoder.hpp"
#include "flexsplat/testing/gradcheck.hpp"

using namespace flexsplat;

namespace {
struct Tiny {
  decoder::DecoderConfig cfg;
  TestRig rig;
  index_t n = 6, fh = 5, fw = 4;
  std::vector<double> params, features;
  Tiny(index_t views, bool local, index_t view_slots = 0) : rig(make_rig(views)) {
    cfg.dim = 8, cfg.ffn = 12, cfg.heads = 2, cfg.layers = 2, cfg.points = 2, cfg.max_views = std::max<index_t>(2, views);
    cfg.value_dim = 3, cfg.max_queries = 9, cfg.local_attention = local, cfg.window = 4, cfg.view_slots = view_slots;
    params.resize(decoder::DecoderParamLayout(cfg).size);
    decoder::decoder_init(params.data(), cfg, 7);
    auto noise = random_normal(params.size(), 61, 0.1);
    for (std::size_t i = 0; i < params.size(); ++i) params[i] += noise[i];
    features = random_normal(views * cfg.value_dim * fh * fw, 62);
  }
  decoder::FeatureMaps<double> maps() const { return {rig.views, cfg.value_dim, fh, fw, features.data()}; }
};

index_t set_size(index_t n) { return n * flat_set_values; }
}  // namespace

TEST_CASE("decoder returns every layer's Gaussians, finite", "[decoder][decoder]") {
  Tiny t(2, false);
  decoder::DecoderWorkspace<double> st;
  decoder::decoder_forward(st, t.n, t.params.data(), t.cfg, t.maps(), t.rig.geometry());
  REQUIRE(st.gaussians.size() == 3);
  for (const auto& g : st.gaussians) {
    REQUIRE(g.size() == t.n);
    for (double v : g.means.span()) REQUIRE(std::isfinite(v));
    for (double v : g.opacities.span()) REQUIRE((v > 0 && v < 1));
  }
  CHECK(st.scene_centre.from_axes);
}

TEST_CASE("decoder passes the float64 gradient check end to end", "[decoder][decoder]") {
  // Two views with a slot each (global and local self-attention), and three views over two slots: views 2 and 3 share
  // the deformable-attention slot and their queries' embedding rows, whose gradients add.
  for (auto [local, views, view_slots] : {std::tuple<bool, index_t, index_t>{false, 2, 0}, {true, 2, 0}, {false, 3, 2}}) {
    Tiny t(views, local, view_slots);
    decoder::DecoderWorkspace<double> st;
    std::vector<double> dp(t.params.size()), df(t.features.size()), dK(t.rig.K.size()), dE(t.rig.E.size()),
        dD(t.rig.depth.size());
    const index_t per = set_size(t.n), sets = t.cfg.layers + 1;
    auto tensors = testing::split_flat(t.params, dp, appearance_tensors(model_around(t.cfg), "decoder."));
    tensors.push_back({"features", t.features, df});
    tensors.push_back({"K", t.rig.K, dK});
    tensors.push_back({"world_to_camera", t.rig.E, dE});
    tensors.push_back({"depth", t.rig.depth, dD});
    auto result = testing::check_gradients(
        tensors, per * sets,
        [&](std::span<double> o) {
          decoder::decoder_forward(st, t.n, t.params.data(), t.cfg, t.maps(), t.rig.geometry());
          for (index_t s = 0; s < sets; ++s) flatten_set(st.gaussians[s], o.data() + s * per);
        },
        [&](std::span<const double> g) {
          std::vector<GaussianSetGrad<double>> dg;
          for (index_t s = 0; s < sets; ++s) dg.push_back(unflatten_grad(g.data() + s * per, t.n));
          decoder::decoder_backward(dp.data(), df.data(), {dK.data(), dE.data(), dD.data()}, dg, st, t.params.data(), t.cfg,
                                    t.maps(), t.rig.geometry());
        },
        {1e-6, 1e-7, 1e-5, 8});
    INFO((local ? "local, " : "full, ") << views << " views, view_slots " << view_slots << ": " << result.summary());
    CHECK(result.ok());
  }
}

TEST_CASE("decoder handles one view, identical cameras and rejects bad budgets", "[decoder][decoder]") {
  Tiny one(1, false);
  decoder::DecoderWorkspace<double> st;
  decoder::decoder_forward(st, one.n, one.params.data(), one.cfg, one.maps(), one.rig.geometry());
  CHECK_FALSE(st.scene_centre.from_axes);
  for (const auto& g : st.gaussians)
    for (double v : g.means.span()) REQUIRE(std::isfinite(v));
  Tiny same(2, true);
  std::copy(same.rig.E.begin(), same.rig.E.begin() + 12, same.rig.E.begin() + 12);
  decoder::decoder_forward(st, same.n, same.params.data(), same.cfg, same.maps(), same.rig.geometry());
  for (const auto& g : st.gaussians)
    for (double v : g.means.span()) REQUIRE(std::isfinite(v));
  CHECK_THROWS_WITH(decoder::decoder_forward(st, 10, same.params.data(), same.cfg, same.maps(), same.rig.geometry()),
                    Catch::Contains("budget 10 is outside [1, 9]"));
}

// Counts global operator new calls while enabled: proves the workspace-based decoder does not allocate once reserved.
namespace {
std::atomic<long> g_allocations{0};
std::atomic<bool> g_count_allocations{false};
}  // namespace
// GCC cannot see that these replacements pair malloc with free on purpose.
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmismatched-new-delete"
// Every unaligned form is replaced so that all of them pair malloc with free (a partial set mixes allocators).
namespace {
void* counted_malloc(std::size_t bytes) noexcept {
  if (g_count_allocations.load(std::memory_order_relaxed)) g_allocations.fetch_add(1, std::memory_order_relaxed);
  return std::malloc(bytes ? bytes : 1);
}
}  // namespace
void* operator new(std::size_t bytes) {
  if (void* p = counted_malloc(bytes)) return p;
  throw std::bad_alloc();
}
void* operator new[](std::size_t bytes) {
  if (void* p = counted_malloc(bytes)) return p;
  throw std::bad_alloc();
}
void* operator new(std::size_t bytes, const std::nothrow_t&) noexcept { return counted_malloc(bytes); }
void* operator new[](std::size_t bytes, const std::nothrow_t&) noexcept { return counted_malloc(bytes); }
void operator delete(void* p) noexcept { std::free(p); }
void operator delete[](void* p) noexcept { std::free(p); }
void operator delete(void* p, std::size_t) noexcept { std::free(p); }
void operator delete[](void* p, std::size_t) noexcept { std::free(p); }
void operator delete(void* p, const std::nothrow_t&) noexcept { std::free(p); }
void operator delete[](void* p, const std::nothrow_t&) noexcept { std::free(p); }
#pragma GCC diagnostic pop

TEST_CASE("decoder workspace: reserved once, repeated forward/backward neither grows it nor allocates",
          "[decoder][decoder][workspace]") {
  for (bool local : {false, true}) {
    Tiny t(2, local);
    decoder::DecoderWorkspace<double> ws;
    ws.reserve(t.cfg, t.n, 2, t.fh, t.fw, t.rig.dw * t.rig.dh);
    const std::size_t reserved = ws.capacity_bytes();
    REQUIRE(reserved > 0);
    std::vector<double> dp(t.params.size()), df(t.features.size()), dK(t.rig.K.size()), dE(t.rig.E.size()),
        dD(t.rig.depth.size());
    // Gradients of the means and opacities only (the other fields stay empty: no gradient), for budgets n and n - 2.
    auto means_opacities = [&](index_t n) {
      GaussianSetGrad<double> d;
      d.means = Tensor<double, 2>({n, 3}, 1.0);
      d.opacities = Tensor<double, 1>({n}, 1.0);
      return std::vector<GaussianSetGrad<double>>(static_cast<std::size_t>(t.cfg.layers + 1), d);
    };
    const auto dg_full = means_opacities(t.n), dg_smaller = means_opacities(t.n - 2);
    auto round = [&](index_t n) {
      const auto& dg = n == t.n ? dg_full : dg_smaller;
      decoder::decoder_forward(ws, n, t.params.data(), t.cfg, t.maps(), t.rig.geometry());
      decoder::decoder_backward(dp.data(), df.data(), {dK.data(), dE.data(), dD.data()}, dg, ws, t.params.data(), t.cfg,
                                t.maps(), t.rig.geometry());
    };
    round(t.n);
    CHECK(ws.capacity_bytes() == reserved);
    const auto first = copy_of(ws.gaussians.back().means.view());
    g_allocations = 0;
    g_count_allocations = true;
    {  // the counter works: one vector, one allocation
      std::vector<double> probe(16, 1.0);
      asm volatile("" : : "g"(probe.data()) : "memory");
    }
    const long probe_count = g_allocations.exchange(0);
    round(t.n);
    round(t.n - 2);  // a smaller budget fits too
    round(t.n);
    g_count_allocations = false;
    INFO((local ? "local" : "full") << ": " << g_allocations.load() << " heap allocations");
    CHECK(probe_count == 1);
    CHECK(g_allocations.load() == 0);
    CHECK(ws.capacity_bytes() == reserved);
    CHECK(std::ranges::equal(ws.gaussians.back().means.span(), first.span()));  // reuse leaves no stale state behind
  }
}

TEST_CASE("decoder forward without layer caches: same Gaussians from one cache, FFN GELU in place, backward refused",
          "[decoder][decoder][workspace]") {
  for (bool local : {false, true}) {
    Tiny t(2, local);
    decoder::DecoderWorkspace<double> kept, shared;
    shared.keep_for_backward = false;
    decoder::decoder_forward(kept, t.n, t.params.data(), t.cfg, t.maps(), t.rig.geometry());
    decoder::decoder_forward(shared, t.n, t.params.data(), t.cfg, t.maps(), t.rig.geometry());
    REQUIRE(kept.layers.size() == 2);
    REQUIRE(shared.layers.size() == 1);
    CHECK(shared.layers[0].hidden_pre.empty());
    CHECK(kept.layers[0].hidden_pre.size() == kept.layers[0].hidden.size());
    REQUIRE(shared.gaussians.size() == kept.gaussians.size());
    for (std::size_t s = 0; s < kept.gaussians.size(); ++s) {
      CHECK(std::ranges::equal(shared.gaussians[s].means.span(), kept.gaussians[s].means.span()));
      CHECK(std::ranges::equal(shared.gaussians[s].sh.span(), kept.gaussians[s].sh.span()));
      CHECK(std::ranges::equal(shared.gaussians[s].opacities.span(), kept.gaussians[s].opacities.span()));
    }
    CHECK(shared.capacity_bytes() < kept.capacity_bytes());
    std::vector<double> dp(t.params.size());
    GaussianSetGrad<double> d;
    d.means = Tensor<double, 2>({t.n, 3}, 1.0);
    const std::vector<GaussianSetGrad<double>> dg(static_cast<std::size_t>(t.cfg.layers + 1), d);
    CHECK_THROWS_WITH(decoder::decoder_backward(dp.data(), static_cast<double*>(nullptr), {}, dg, shared,
                                                t.params.data(), t.cfg, t.maps(), t.rig.geometry()),
                      Catch::Contains("keep_for_backward"));
  }
}

TEST_CASE("decoder with a query subset: the chosen queries' start as in the whole budget, every query = no subset",
          "[decoder][decoder][workspace]") {
  for (index_t slots : {index_t(0), index_t(2)}) {
    Tiny t(2, false, slots);
    decoder::DecoderWorkspace<double> whole, part, all;
    for (auto* ws : {&whole, &part, &all}) ws->keep_for_backward = false;
    decoder::decoder_forward(whole, t.n, t.params.data(), t.cfg, t.maps(), t.rig.geometry());
    part.subset = {1, 2, 5};
    decoder::decoder_forward(part, t.n, t.params.data(), t.cfg, t.maps(), t.rig.geometry());
    REQUIRE(part.gaussians.size() == whole.gaussians.size());
    // Before the layers each Gaussian depends on its query's embedding and anchor only: the same rows as the whole
    // budget's, to the rounding of a GEMM of another row count; the layers' self-attention then sees fewer queries.
    const auto& g0 = part.gaussians[0];
    REQUIRE(g0.size() == 3);
    for (index_t i = 0; i < 3; ++i) {
      const index_t q = part.subset[static_cast<std::size_t>(i)];
      for (int k = 0; k < 3; ++k) CHECK(g0.means(i, k) == Approx(whole.gaussians[0].means(q, k)).epsilon(1e-12));
      CHECK(g0.opacities(i) == Approx(whole.gaussians[0].opacities(q)).epsilon(1e-12));
    }
    CHECK(part.gaussians.back().size() == 3);
    for (double v : part.gaussians.back().means.span()) CHECK(std::isfinite(v));
    all.subset = {0, 1, 2, 3, 4, 5};
    decoder::decoder_forward(all, t.n, t.params.data(), t.cfg, t.maps(), t.rig.geometry());
    for (std::size_t s = 0; s < whole.gaussians.size(); ++s) {
      CHECK(std::ranges::equal(all.gaussians[s].means.span(), whole.gaussians[s].means.span()));
      CHECK(std::ranges::equal(all.gaussians[s].sh.span(), whole.gaussians[s].sh.span()));
    }
    // Refused: indices out of order or past the budget, and a subset with backward caches.
    part.subset = {2, 1};
    CHECK_THROWS_WITH(decoder::decoder_forward(part, t.n, t.params.data(), t.cfg, t.maps(), t.rig.geometry()),
                      Catch::Contains("query subset entry 1 (1) is not an ascending index"));
    part.subset = {6};
    CHECK_THROWS_WITH(decoder::decoder_forward(part, t.n, t.params.data(), t.cfg, t.maps(), t.rig.geometry()),
                      Catch::Contains("below the budget 6"));
    decoder::DecoderWorkspace<double> training;
    training.subset = {0};
    CHECK_THROWS_WITH(decoder::decoder_forward(training, t.n, t.params.data(), t.cfg, t.maps(), t.rig.geometry()),
                      Catch::Contains("forward only"));
  }
}

TEST_CASE("decoder_layer_offsets agrees with DecoderParamLayout", "[decoder][decoder]") {
  decoder::DecoderConfig c;
  c.dim = 16, c.ffn = 40, c.heads = 4, c.layers = 3, c.points = 2, c.max_views = 3, c.value_dim = 5, c.max_queries = 11;
  const decoder::DecoderParamLayout L(c);
  for (index_t l = 0; l < c.layers; ++l) {
    const auto a = L.layer[l], b = decoder::decoder_layer_offsets(c, l);
    CHECK(a.deform == b.deform);
    CHECK(a.attn == b.attn);
    CHECK(a.ffn_w2 == b.ffn_w2);
    CHECK(a.head_b == b.head_b);
    CHECK(a.ln3_g == b.ln3_g);
  }
  CHECK(decoder::decoder_layer_offsets(c, c.layers - 1).head_b + decoder::splat_values == L.size);
}

TEST_CASE("query embedding rows: one per query with a slot per view, shared by views 2..V with two slots",
          "[decoder][decoder]") {
  decoder::DecoderConfig c;
  c.max_views = 8;
  for (index_t i = 0; i < 20; ++i) CHECK(c.query_row(i, 4) == i);
  CHECK(c.query_rows_used(20, 4) == 20);
  c.view_slots = 2;
  // 4 views: queries 0..3 are cell 0 of views 0..3, queries 4..7 cell 1.
  CHECK(c.query_row(0, 4) == 0);
  CHECK(c.query_row(1, 4) == 1);
  CHECK(c.query_row(2, 4) == 1);
  CHECK(c.query_row(3, 4) == 1);
  CHECK(c.query_row(4, 4) == 2);
  CHECK(c.query_row(7, 4) == 3);
  CHECK(c.query_rows_used(20, 4) == 10);
  CHECK(c.query_rows_used(20, 1) == 40);  // one view reads every other row
  Tiny t(1, false, 2);  // 6 queries of one view read rows 0, 2, ..., 10 of a table of 9
  decoder::DecoderWorkspace<double> st;
  CHECK_THROWS_WITH(decoder::decoder_forward(st, t.n, t.params.data(), t.cfg, t.maps(), t.rig.geometry()),
                    Catch::Contains("reads 12 query embeddings, the table has 9"));
}
