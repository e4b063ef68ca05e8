#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <random>
#include <vector>

#include "flexsplat/raster/render.hpp"
#include "flexsplat/testing/gradcheck.hpp"
#include "scene_util.hpp"
#include "simd_lanes.hpp"

using namespace rastertest;

namespace {

// Gaussian and camera gradients of one backward pass.
template <class T>
struct Grads : GaussianSetGrad<T> {
  ViewGrad<T> camera;
  explicit Grads(const Scene<T>& s) : GaussianSetGrad<T>(make_gaussian_grad(s.set())) {}
};

template <class T>
struct Cotangents {
  Tensor<T, 3> image, features;
  Tensor<T, 2> alpha, depth;
  Cotangents(const View<T>& cam, int F, unsigned seed) {
    std::mt19937 rng(seed);
    std::normal_distribution<double> normal;
    image.resize({cam.height, cam.width, 3});
    features.resize({cam.height, cam.width, F});
    alpha.resize({cam.height, cam.width});
    depth.resize({cam.height, cam.width});
    for (auto* t : {&image, &features}) for (auto& v : t->span()) v = T(normal(rng));
    for (auto* t : {&alpha, &depth}) for (auto& v : t->span()) v = T(normal(rng));
  }
  RenderOutputGrads<T> views() const { return {image.view(), alpha.view(), depth.view(), features.view()}; }
};

template <class T>
bool all_finite(std::span<const T> v) {
  for (T x : v)
    if (!std::isfinite(x)) return false;
  return true;
}

template <class T, std::size_t R>
bool same_bits(const Tensor<T, R>& a, const Tensor<T, R>& b) {
  // memcmp must not see the null data pointer of an empty tensor
  return a.shape() == b.shape() &&
         (a.size() == 0 || std::memcmp(a.data(), b.data(), sizeof(T) * std::size_t(a.size())) == 0);
}

// Forward + backward of a scene; returns everything for bitwise comparisons.
struct Run {
  RenderOutputs<float> out;
  Grads<float> grads;
  explicit Run(const Scene<float>& s) : grads(s) {}
};

Run run_scene(const Scene<float>& s, const RenderOptions& opt, unsigned cot_seed = 5) {
  Run r(s);
  RenderWorkspace<float> ws;
  render_forward(s.set(), s.camera, opt, ws, r.out);
  Cotangents<float> cot(s.camera, int(s.features.shape(1)), cot_seed);
  render_backward(s.set(), s.camera, opt, ws, cot.views(), r.grads, &r.grads.camera);
  return r;
}

bool identical(const Run& a, const Run& b) {
  return same_bits(a.out.image, b.out.image) && same_bits(a.out.alpha, b.out.alpha) &&
         same_bits(a.out.depth, b.out.depth) && same_bits(a.out.n_contrib, b.out.n_contrib) &&
         same_bits(a.out.features, b.out.features) && same_bits(a.grads.means, b.grads.means) &&
         same_bits(a.grads.quats, b.grads.quats) && same_bits(a.grads.scales, b.grads.scales) &&
         same_bits(a.grads.opacities, b.grads.opacities) && same_bits(a.grads.sh, b.grads.sh) &&
         same_bits(a.grads.features, b.grads.features) &&
         std::memcmp(&a.grads.camera, &b.grads.camera, sizeof(ViewGrad<float>)) == 0;
}

void full_gradcheck(bool antialiased, bool expected_depth, unsigned seed) {
  SceneSpec spec;
  spec.n = 14;
  spec.width = 20, spec.height = 16;
  spec.sh_degree = 3;
  spec.features = 2;
  spec.scale_min = 0.08, spec.scale_max = 0.3;
  spec.opacity_min = 0.2, spec.opacity_max = 0.8;
  spec.antialiased = antialiased;
  spec.seed = seed;
  auto s = make_scene<double>(spec);
  s.options.expected_depth = expected_depth;
  Grads<double> g(s);
  std::vector<double> view(12), d_view(12), intr(4), d_intr(4);
  for (int i = 0; i < 12; ++i) view[i] = s.camera.world_to_camera[i];
  intr = {s.camera.fx, s.camera.fy, s.camera.cx, s.camera.cy};
  auto sync = [&] {
    for (int i = 0; i < 12; ++i) s.camera.world_to_camera[i] = view[i];
    s.camera.fx = intr[0], s.camera.fy = intr[1], s.camera.cx = intr[2], s.camera.cy = intr[3];
  };
  const index_t pixels = index_t(spec.width) * spec.height;
  const std::size_t out_size = std::size_t(pixels * (3 + 1 + 1 + spec.features));
  RenderWorkspace<double> ws;
  RenderOutputs<double> out;
  auto forward = [&](std::span<double> flat) {
    sync();
    render_forward(s.set(), s.camera, s.options, ws, out);
    double* p = flat.data();
    for (double v : out.image.span()) *p++ = v;
    for (double v : out.alpha.span()) *p++ = v;
    for (double v : out.depth.span()) *p++ = v;
    for (double v : out.features.span()) *p++ = v;
  };
  auto backward = [&](std::span<const double> d) {
    sync();
    render_forward(s.set(), s.camera, s.options, ws, out);
    const double* p = d.data();
    RenderOutputGrads<double> dg{{p, {spec.height, spec.width, 3}},
                                 {p + pixels * 3, {spec.height, spec.width}},
                                 {p + pixels * 4, {spec.height, spec.width}},
                                 {p + pixels * 5, {spec.height, spec.width, spec.features}}};
    // The camera gradient starts from the checker's junk too, so its += contract is checked like the others.
    g.camera = ViewGrad<double>{};
    for (int i = 0; i < 12; ++i) g.camera.world_to_camera[i] = d_view[i];
    g.camera.fx = d_intr[0], g.camera.fy = d_intr[1], g.camera.cx = d_intr[2], g.camera.cy = d_intr[3];
    render_backward(s.set(), s.camera, s.options, ws, dg, g, &g.camera);
    for (int i = 0; i < 12; ++i) d_view[i] = g.camera.world_to_camera[i];
    d_intr = {g.camera.fx, g.camera.fy, g.camera.cx, g.camera.cy};
  };
  testing::GradCheckOptions opts;
  opts.abs_tol = 1e-6;
  opts.rel_tol = 1e-5;
  opts.max_checks_per_param = 40;
  auto result = testing::check_gradients(
      {{"means", s.means.span(), g.means.span()}, {"quats", s.quats.span(), g.quats.span()},
       {"scales", s.scales.span(), g.scales.span()}, {"opacities", s.opacities.span(), g.opacities.span()},
       {"sh", s.sh.span(), g.sh.span()}, {"features", s.features.span(), g.features.span()},
       {"world_to_camera", view, d_view}, {"intrinsics", intr, d_intr}},
      out_size, forward, backward, opts, testing::gradcheck_seed(seed));
  INFO("antialiased " << antialiased << " expected_depth " << expected_depth << ": " << result.summary());
  CHECK(result.ok());
}

}  // namespace

TEST_CASE("render: float64 gradient check of the whole pipeline, Gaussians and camera", "[raster][render]") {
  full_gradcheck(false, false, 101);
  full_gradcheck(true, false, 102);
  full_gradcheck(false, true, 103);
}

TEST_CASE("render: results for 1 and 2 threads are bit-identical (forward and backward)", "[raster][render]") {
  SceneSpec spec;
  spec.n = 3000;
  spec.width = 96, spec.height = 80;
  spec.sh_degree = 3;
  spec.features = 3;
  spec.scale_min = 0.01, spec.scale_max = 0.1;
  auto s = make_scene<float>(spec);
  ThreadPool one(1), two(2);
  RenderOptions opt = s.options;
  opt.pool = &one;
  const Run a = run_scene(s, opt);
  opt.pool = &two;
  const Run b = run_scene(s, opt);
  const Run c = run_scene(s, opt);
  CHECK(identical(a, b));
  CHECK(identical(b, c));
  long contributions = 0;
  for (auto v : a.out.n_contrib.span()) contributions += v;
  CHECK(contributions > 10000);
}

TEST_CASE("render: rasterize_forward's planar channels equal render_forward's outputs", "[raster][render]") {
  SceneSpec spec;
  spec.n = 2000;
  spec.width = 70, spec.height = 50;  // edge tiles narrower and shorter than 16
  spec.sh_degree = 1;
  spec.features = 2;
  spec.scale_min = 0.01, spec.scale_max = 0.1;
  auto s = make_scene<float>(spec);
  RenderWorkspace<float> ws;
  RenderOutputs<float> out;
  render_forward(s.set(), s.camera, s.options, ws, out);
  const int C = ws.channel_count;
  const index_t pixels = index_t(spec.width) * spec.height;
  std::vector<float> planes(std::size_t(pixels * C), -1.0f);
  RasterWorkspace<float> raster_ws;
  BlendState<float> state;
  rasterize_forward(ws.tiles, ws.projections.data(), ws.channels.data(), C, ws.background.data(), s.options.skips,
                    raster_ws, planes.data(), state, global_pool());
  long mismatches = 0, contributions = 0;
  for (index_t p = 0; p < pixels; ++p) {
    for (int c = 0; c < 3; ++c) mismatches += planes[std::size_t(c * pixels + p)] != out.image.data()[p * 3 + c];
    mismatches += planes[std::size_t(3 * pixels + p)] != out.depth.data()[p];
    for (int f = 0; f < C - 4; ++f)
      mismatches += planes[std::size_t((4 + f) * pixels + p)] != out.features.data()[p * (C - 4) + f];
    mismatches += 1.0f - state.final_transmittance[std::size_t(p)] != out.alpha.data()[p];
    mismatches += state.n_contrib[std::size_t(p)] != out.n_contrib.data()[p];
    contributions += state.n_contrib[std::size_t(p)];
  }
  CHECK(contributions > 1000);
  CHECK(mismatches == 0);
}

TEST_CASE("render: every skip leaves forward and backward bit-identical", "[raster][render]") {
  SceneSpec spec;
  spec.n = 600;
  spec.width = 70, spec.height = 50;
  spec.sh_degree = 2;
  spec.scale_min = 0.02, spec.scale_max = 0.3;
  spec.opacity_min = 0.3, spec.opacity_max = 0.99;
  auto s = make_scene<float>(spec);
  const Run all_on = run_scene(s, s.options);
  for (int mask = 0; mask < 7; ++mask) {
    RenderOptions opt = s.options;
    opt.skips.opacity_aware_extent = mask & 1;
    opt.skips.exact_tile_test = mask & 2;
    opt.skips.early_exit = mask & 4;
    INFO("skip mask " << mask);
    CHECK(identical(all_on, run_scene(s, opt)));
  }
}

namespace {
// The blend kernel a dispatch cap selects on this CPU (none: the compiled batches).
detail::BlendKernel kernel_for(simd::DispatchLevel cap) {
  RasterSkips skips;
  skips.dispatch_cap = cap;
  return detail::choose_blend_kernel<float>(skips);
}

// Renders and differentiates one scene with the kernels `cap` selects and compares with the scalar ones.
void check_simd_render_agrees(simd::DispatchLevel cap) {
  SceneSpec spec;
  spec.n = 600;
  spec.width = 70, spec.height = 45;  // partial tiles on both edges
  spec.features = 3;
  spec.scale_min = 0.02, spec.scale_max = 0.3;
  auto s = make_scene<float>(spec);
  RenderOptions opt = s.options;
  opt.skips.force_scalar = true;
  const Run sca = run_scene(s, opt);
  opt.skips.force_scalar = false;
  auto rel_diff = [](const auto& a, const auto& b) {
    double m = 0, scale = 0;
    for (index_t i = 0; i < a.size(); ++i) {
      m = std::max(m, double(std::abs(a.data()[i] - b.data()[i])));
      scale = std::max(scale, double(std::abs(b.data()[i])));
    }
    return m / std::max(scale, 1.0);
  };
  opt.skips.dispatch_cap = cap;
  const Run vec = run_scene(s, opt);
  INFO("dispatch cap " << simd::dispatch_name(cap) << ", CPU level " << simd::dispatch_name(simd::dispatch_level()));
  CHECK(same_bits(vec.out.n_contrib, sca.out.n_contrib));
  CHECK(rel_diff(vec.out.image, sca.out.image) < 1e-5);
  CHECK(rel_diff(vec.out.alpha, sca.out.alpha) < 1e-5);
  CHECK(rel_diff(vec.out.depth, sca.out.depth) < 1e-5);
  CHECK(rel_diff(vec.out.features, sca.out.features) < 1e-5);
  CHECK(rel_diff(vec.grads.means, sca.grads.means) < 1e-4);
  CHECK(rel_diff(vec.grads.quats, sca.grads.quats) < 1e-4);
  CHECK(rel_diff(vec.grads.scales, sca.grads.scales) < 1e-4);
  CHECK(rel_diff(vec.grads.opacities, sca.grads.opacities) < 1e-4);
  CHECK(rel_diff(vec.grads.sh, sca.grads.sh) < 1e-4);
  CHECK(rel_diff(vec.grads.features, sca.grads.features) < 1e-4);
}

// A dispatch level's case: its own kernel must be the one that runs (no quiet fall-back to the compiled batches).
void check_dispatched(simd::Lanes lanes, void (*check)(simd::DispatchLevel)) {
  const auto level = lanes == simd::Lanes::avx512 ? simd::DispatchLevel::avx512 : simd::DispatchLevel::avx2;
  if (!simd::enabled()) FLEXSPLAT_SKIP("FLEXSPLAT_SIMD=scalar: no SIMD kernel runs");
  REQUIRE(kernel_for(level) == (level == simd::DispatchLevel::avx512 ? detail::BlendKernel::avx512 : detail::BlendKernel::avx2));
  check(level);
}
void check_dispatched_render(simd::Lanes lanes) { check_dispatched(lanes, check_simd_render_agrees); }
}  // namespace

TEST_CASE("render: SIMD kernels (compiled batches) agree with the scalar ones", "[raster][render]") {
  check_simd_render_agrees(simd::DispatchLevel::none);
}

FLEXSPLAT_DISPATCH_TEST_CASES("render: the dispatched SIMD kernels agree with the scalar ones", "[raster][render][simd]",
                              check_dispatched_render)

TEST_CASE("render: the batched per-Gaussian pass matches the scalar one and keeps every pair the kernel draws",
          "[raster][render]") {
  SceneSpec spec;
  spec.n = 701;  // not a whole number of blocks
  spec.width = 90, spec.height = 100;  // partial tiles, up to 7 tile rows
  spec.sh_degree = 3;
  spec.features = 3;
  spec.scale_min = 0.005, spec.scale_max = 1.2;
  spec.opacity_min = 0.002, spec.opacity_max = 1.0;
  auto s = make_scene<float>(spec);
  const TileGrid grid(spec.width, spec.height);
  long pairs = 0, tall = 0;
  for (int config = 0; config < 4; ++config) {
    RenderOptions opt = s.options;
    opt.antialiased = config & 1;
    opt.skips.opacity_aware_extent = opt.skips.exact_tile_test = config < 2;
    RenderWorkspace<float> batched, scalar;
    RenderOutputs<float> out;
    render_forward(s.set(), s.camera, opt, batched, out);
    opt.skips.force_scalar = true;
    render_forward(s.set(), s.camera, opt, scalar, out);
    const int C = batched.channel_count;
    const float* rb = batched.raster.splat_records();
    const float* rs = scalar.raster.splat_records();
    const int stride = batched.raster.splat_stride;
    for (index_t g = 0; g < spec.n; ++g) {
      INFO("config " << config << " Gaussian " << g);
      REQUIRE(batched.visible[g] == scalar.visible[g]);
      if (!batched.visible[g]) continue;
      // Projection, colour and channels: bit-identical.
      CHECK(std::memcmp(&batched.projections[g], &scalar.projections[g], sizeof(Projection<float>)) == 0);
      CHECK(std::memcmp(&batched.channels[g * C], &scalar.channels[g * C], sizeof(float) * C) == 0);
      for (int c = 0; c < 3; ++c) CHECK(batched.color_positive[g * 3 + c] == scalar.color_positive[g * 3 + c]);
      // Tiles: the stored count is what the binning emits.
      const Projection<float>& p = batched.projections[g];
      std::vector<std::int64_t> tiles;
      for_each_gaussian_tile(p, batched.tiles.gaussian_tiles[g], grid, opt.skips,
                             [&](std::int64_t t) { tiles.push_back(t); });
      CHECK(std::int64_t(tiles.size()) == batched.tiles.gaussian_counts[g]);
      tall += batched.tiles.gaussian_counts[g] > 0 &&
              batched.tiles.gaussian_tiles[g].rect.y1 - batched.tiles.gaussian_tiles[g].rect.y0 >= GaussianTiles::stored_rows;
      const float* rec = rb + g * stride;
      if (batched.tiles.gaussian_counts[g] > 0 && scalar.tiles.gaussian_counts[g] > 0) {
        const float* ref = rs + g * stride;
        CHECK(std::memcmp(rec, ref, sizeof(float) * 6) == 0);  // u, v, conic, opacity
        CHECK(std::abs(rec[6] - ref[6]) <= 1e-6f * std::max(1.0f, std::abs(ref[6])));  // sigma_max: log rounding
        // Kernel pixel rectangle (first/last x, first/last y): contains the one splat_params gives.
        CHECK(rec[7] <= ref[7]);
        CHECK(rec[8] >= ref[8]);
        CHECK(rec[9] <= ref[9]);
        CHECK(rec[10] >= ref[10]);
        CHECK(std::memcmp(rec + splat_fields, ref + splat_fields, sizeof(float) * C) == 0);
      }
      // Every pixel whose float alpha reaches the threshold is in a listed tile and inside the kernel's extent.
      for (int y = 0; y < spec.height; ++y)
        for (int x = 0; x < spec.width; ++x) {
          const float dx = p.u - (float(x) + 0.5f), dy = p.v - (float(y) + 0.5f);
          const float sigma = 0.5f * (p.conic[0] * dx * dx + p.conic[2] * dy * dy) + p.conic[1] * dx * dy;
          const float alpha = std::min(float(max_alpha), p.opacity * std::exp(-sigma));
          if (!(sigma >= 0.f) || !(alpha >= float(alpha_threshold))) continue;
          ++pairs;
          const std::int64_t tile = std::int64_t(y / tile_size) * grid.tiles_x + x / tile_size;
          INFO("pixel " << x << ", " << y << " alpha " << alpha);
          REQUIRE(batched.tiles.gaussian_counts[g] > 0);
          CHECK(std::find(tiles.begin(), tiles.end(), tile) != tiles.end());
          CHECK((float(x) >= rec[7] && float(x) <= rec[8]));
          CHECK((float(y) >= rec[9] && float(y) <= rec[10]));
          CHECK(sigma <= rec[6]);
        }
    }
  }
  CHECK(pairs > 100000);
  CHECK(tall > 10);  // some Gaussians have rows beyond the stored ones
}

namespace {
// The batched per-Gaussian backward with the kernel `cap` selects against the scalar one, on a scene of hazards.
void check_batched_backward(simd::DispatchLevel cap) {
  SceneSpec spec;
  spec.n = 1001;  // not a whole number of lane blocks or camera blocks
  spec.width = 64, spec.height = 48;
  spec.sh_degree = 3;
  spec.features = 2;
  spec.scale_min = 1e-7, spec.scale_max = 2.0;  // tiny to huge
  spec.opacity_min = 0.0, spec.opacity_max = 1.0;
  spec.half_extent = 4.5;  // beyond the 1.3x field-of-view clamp, behind the camera, off screen
  auto s = make_scene<float>(spec);
  const float near = float(s.options.near_plane), z_cam = float(s.camera.world_to_camera[11]);
  for (index_t g = 0; g < 40; ++g) {  // camera-space z on, just above and just below the near plane, and at 0
    const float dz[4] = {near, near * 1.001f, near * 0.999f, 0.0f};
    s.means(g, 2) = dz[g % 4] - z_cam;
  }
  std::mt19937 rng(41);
  std::normal_distribution<float> normal;
  std::uniform_int_distribution<int> pick(0, 9);
  long with_record = 0, colour_dead = 0, culled = 0;
  for (int config = 0; config < 2; ++config) {
    RenderOptions opt = s.options;
    opt.antialiased = config == 1;
    RenderWorkspace<float> ws;
    RenderOutputs<float> out;
    render_forward(s.set(), s.camera, opt, ws, out);
    // Random entry gradient records; some Gaussians with zero colour cotangents (no SH adjoint) or zero everywhere.
    const int stride = entry_grad_fixed + ws.channel_count;
    std::vector<float>& entries = ws.raster.entry_grads;
    entries.assign(std::size_t(ws.tiles.tile_offsets.back() * stride), 0.0f);
    for (index_t g = 0; g < spec.n; ++g) {
      const int kind = pick(rng);
      for (std::int64_t e = ws.tiles.gaussian_offsets[g]; e < ws.tiles.gaussian_offsets[g] + ws.tiles.gaussian_counts[g];
           ++e) {
        for (int j = 0; j < stride; ++j) entries[e * stride + j] = kind == 0 ? 0.0f : normal(rng);
        if (kind == 1)
          for (int c = 0; c < 3; ++c) entries[e * stride + entry_grad_fixed + c] = 0.0f;
      }
      const bool record = detail::has_backward(ws, g);
      with_record += record, culled += !ws.visible[g];
      colour_dead += record && (kind <= 1 || !(ws.color_positive[g * 3] || ws.color_positive[g * 3 + 1] ||
                                               ws.color_positive[g * 3 + 2]));
    }
    // The += contract: every run starts from the same junk.
    auto junk_grads = [&] {
      Grads<float> gr(s);
      std::mt19937 junk(7);
      std::normal_distribution<float> value;
      for (auto* t : {&gr.means, &gr.quats, &gr.scales, &gr.features})
        for (auto& v : t->span()) v = value(junk);
      for (auto& v : gr.opacities.span()) v = value(junk);
      for (auto& v : gr.sh.span()) v = value(junk);
      return gr;
    };
    auto run = [&](detail::BlendKernel kernel, std::vector<ViewGradParams<float>>& partials) {
      Grads<float> gr = junk_grads();
      detail::gaussians_backward(detail::backward_pass(s.set(), s.camera, opt, ws, gr), kernel, partials, global_pool());
      return gr;
    };
    std::vector<ViewGradParams<float>> ref_partials, partials;
    const Grads<float> ref = run(detail::BlendKernel::scalar, ref_partials);
    const detail::BlendKernel kernel = kernel_for(cap);
    INFO("antialiased " << opt.antialiased << ", dispatch cap " << simd::dispatch_name(cap) << ", lanes "
                        << detail::blend_lane_count<float>(kernel));
    const Grads<float> vec = run(kernel, partials);
    CHECK(same_bits(vec.means, ref.means));
    CHECK(same_bits(vec.quats, ref.quats));
    CHECK(same_bits(vec.scales, ref.scales));
    CHECK(same_bits(vec.opacities, ref.opacities));
    CHECK(same_bits(vec.sh, ref.sh));
    CHECK(same_bits(vec.features, ref.features));
    REQUIRE(partials.size() == ref_partials.size());
    CHECK(std::memcmp(partials.data(), ref_partials.data(), sizeof(ViewGradParams<float>) * partials.size()) == 0);
    CHECK(all_finite<float>(vec.means.span()));
    CHECK(all_finite<float>(vec.quats.span()));
    CHECK(all_finite<float>(vec.scales.span()));
    CHECK(all_finite<float>(vec.sh.span()));
  }
  INFO(with_record << " with records, " << colour_dead << " without colour cotangents, " << culled << " culled");
  CHECK(with_record > 300);
  CHECK(colour_dead > 30);
  CHECK(culled > 100);
}

void check_dispatched_backward(simd::Lanes lanes) { check_dispatched(lanes, check_batched_backward); }
}  // namespace

TEST_CASE("render: the batched per-Gaussian backward (compiled batches) is bit-identical to the scalar one",
          "[raster][render]") {
  if (!simd::enabled()) FLEXSPLAT_SKIP("FLEXSPLAT_SIMD=scalar: no SIMD kernel runs");
  check_batched_backward(simd::DispatchLevel::none);
}

FLEXSPLAT_DISPATCH_TEST_CASES("render: the batched per-Gaussian backward (dispatched) is bit-identical to the scalar one",
                              "[raster][render][simd]", check_dispatched_backward)

TEST_CASE("render: extreme Gaussians give finite outputs and gradients", "[raster][render]") {
  // One scene with each hazard: tiny and huge scales, behind the camera, on the near plane, at the camera centre,
  // needle-thin, opacity 0 and 1, and hundreds of Gaussians on one pixel.
  SceneSpec spec;
  spec.n = 300;
  spec.width = 24, spec.height = 20;
  spec.sh_degree = 3;
  auto s = make_scene<float>(spec);
  s.camera.world_to_camera = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};
  s.camera.cx = 12, s.camera.cy = 10;
  for (index_t i = 0; i < spec.n; ++i) {
    s.means(i, 0) = 0.001f * float(i % 7), s.means(i, 1) = 0.001f * float(i % 5), s.means(i, 2) = 1.0f + 0.01f * float(i);
  }
  const float scales[] = {1e-7f, 1e3f, 1e-7f, 1e3f};
  for (int i = 0; i < 4; ++i) s.scales(i, 0) = s.scales(i, 1) = s.scales(i, 2) = scales[i];
  s.scales(4, 0) = 1e3f, s.scales(4, 1) = 1e-7f, s.scales(4, 2) = 1e-7f;  // needle
  s.means(5, 2) = -2.f;                                                    // behind
  s.means(6, 2) = 0.01f;                                                   // on the near plane
  s.means(7, 0) = s.means(7, 1) = s.means(7, 2) = 0.f;                     // camera centre
  s.means(8, 2) = 0.0100001f, s.scales(8, 0) = 1e3f;                       // huge and just beyond the near plane
  s.opacities(9) = 0.f;
  s.opacities(10) = 1.f;
  s.opacities(11) = 1.f, s.scales(11, 0) = s.scales(11, 1) = 1e3f;
  const Run r = run_scene(s, s.options);
  CHECK(all_finite<float>(r.out.image.span()));
  CHECK(all_finite<float>(r.out.alpha.span()));
  CHECK(all_finite<float>(r.out.depth.span()));
  for (auto* t : {&r.grads.means, &r.grads.quats, &r.grads.scales}) CHECK(all_finite<float>(t->span()));
  CHECK(all_finite<float>(r.grads.opacities.span()));
  CHECK(all_finite<float>(r.grads.sh.span()));
  CHECK(all_finite<float>(std::span<const float>(r.grads.camera.world_to_camera.data(), 16)));
  CHECK(std::isfinite(r.grads.camera.fx));
  long contributions = 0;
  for (auto v : r.out.n_contrib.span()) contributions += v;
  CHECK(contributions > 0);
}

TEST_CASE("render: stress, 10000 random extreme scenes have no non-finite value", "[raster][render][stress]") {
  std::mt19937 rng(2024);
  std::uniform_real_distribution<double> uni(-1, 1), u01(0, 1);
  RenderWorkspace<float> ws;
  RenderOutputs<float> out;
  long bad = 0, scenes = 0, contributions = 0;
  for (int trial = 0; trial < 10000; ++trial) {
    SceneSpec spec;
    spec.n = 6;
    spec.width = 8 + int(u01(rng) * 12), spec.height = 8 + int(u01(rng) * 12);
    spec.sh_degree = trial % 4;
    spec.features = trial % 2;
    spec.antialiased = trial % 3 == 0;
    spec.seed = unsigned(trial);
    auto s = make_scene<float>(spec);
    s.camera.fx = s.camera.fy = float(spec.width) * float(std::exp(2 * uni(rng)));
    for (index_t i = 0; i < spec.n; ++i) {
      for (int k = 0; k < 3; ++k) s.scales(i, k) = float(std::pow(10.0, -7 + 10 * u01(rng)));
      for (int k = 0; k < 3; ++k) s.means(i, k) = float(uni(rng) * std::pow(10.0, 3 * u01(rng) - 1.5));
      s.means(i, 2) -= float(spec.distance) * float(u01(rng) < 0.3);  // some near or behind the camera
      const double r = u01(rng);
      s.opacities(i) = r < 0.1 ? 0.f : r < 0.2 ? 1.f : float(u01(rng));
      if (u01(rng) < 0.1) s.quats(i, 0) = 1e-20f, s.quats(i, 1) = s.quats(i, 2) = 0, s.quats(i, 3) = 1e-20f;
    }
    render_forward(s.set(), s.camera, s.options, ws, out);
    Cotangents<float> cot(s.camera, spec.features, unsigned(trial));
    Grads<float> g(s);
    render_backward(s.set(), s.camera, s.options, ws, cot.views(), g, &g.camera);
    ++scenes;
    for (auto v : out.n_contrib.span()) contributions += v;
    const bool ok = all_finite<float>(out.image.span()) && all_finite<float>(out.alpha.span()) &&
                    all_finite<float>(out.depth.span()) && all_finite<float>(out.features.span()) &&
                    all_finite<float>(g.means.span()) && all_finite<float>(g.quats.span()) &&
                    all_finite<float>(g.scales.span()) && all_finite<float>(g.opacities.span()) &&
                    all_finite<float>(g.sh.span()) && all_finite<float>(g.features.span()) &&
                    all_finite<float>(std::span<const float>(g.camera.world_to_camera.data(), 16)) &&
                    std::isfinite(g.camera.fx) && std::isfinite(g.camera.fy) && std::isfinite(g.camera.cx) &&
                    std::isfinite(g.camera.cy);
    if (!ok) {
      ++bad;
      if (bad <= 3) WARN("non-finite value in scene " << trial);
    }
  }
  CHECK(scenes == 10000);
  CHECK(contributions > 10000);  // the scenes do draw something
  CHECK(bad == 0);
}

TEST_CASE("render: bad input gets a clear error", "[raster][render]") {
  SceneSpec spec;
  spec.n = 5;
  auto s = make_scene<float>(spec);
  RenderWorkspace<float> ws;
  RenderOutputs<float> out;
  auto expect_error = [&](Scene<float>& scene, const std::string& fragment) {
    try {
      render_forward(scene.set(), scene.camera, scene.options, ws, out);
      FAIL("no error; expected one mentioning '" << fragment << "'");
    } catch (const Error& e) {
      INFO(e.what());
      CHECK(std::string(e.what()).find(fragment) != std::string::npos);
    }
  };
  {
    auto t = s;
    for (int k = 0; k < 4; ++k) t.quats(2, k) = 0;
    expect_error(t, "quaternion 2");
  }
  {
    auto t = s;
    t.means(1, 0) = std::numeric_limits<float>::quiet_NaN();
    expect_error(t, "means has a non-finite value");
  }
  {
    auto t = s;
    t.scales(3, 1) = std::numeric_limits<float>::infinity();
    expect_error(t, "scales");
  }
  {
    auto t = s;
    t.opacities(0) = 1.5f;
    expect_error(t, "opacity 0 is 1.5");
  }
  {
    auto t = s;
    t.options.sh_degree = 3;
    expect_error(t, "needs 16 coefficients");
  }
  {
    auto t = s;
    t.camera.world_to_camera[14] = 1;
    expect_error(t, "bottom row");
  }
  {
    auto t = s;
    t.camera.fx = 0;
    expect_error(t, "focal");
  }
  {
    auto t = s;
    t.camera.cy = std::numeric_limits<float>::quiet_NaN();
    expect_error(t, "intrinsics");
  }
  {
    auto t = s;
    t.camera.width = 0;
    expect_error(t, "image size");
  }
  {
    auto t = s;
    t.quats.resize({4, 4});
    expect_error(t, "quats must be [5, 4]");
  }
}

TEST_CASE("a camera's view carries its K and world-to-camera, an empty image is refused", "[raster][view]") {
  Camera cam = look_at({2, 1, 0.5}, {0, 0, 0}, 40, 30, intrinsics_from_fov(40, 30, 60.0));
  const View<float> v = camera_view<float>(cam);
  CHECK(v.width == 40);
  CHECK(v.height == 30);
  CHECK(v.fx == static_cast<float>(cam.K[0][0]));
  CHECK(v.cx == 20.0f);
  CHECK(v.cy == 15.0f);
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) CHECK(v.world_to_camera[static_cast<std::size_t>(4 * r + c)] == static_cast<float>(cam.R[c][r]));
    CHECK(v.world_to_camera[static_cast<std::size_t>(4 * r + 3)] == static_cast<float>(cam.t[r]));
  }
  CHECK(v.world_to_camera[15] == 1.0f);
  const double K[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1}, E[12] = {};
  CHECK_THROWS_WITH(view_from_arrays(K, E, 0, 4), Catch::Contains("empty"));
}
