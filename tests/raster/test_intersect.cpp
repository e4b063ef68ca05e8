#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <numeric>
#include <random>
#include <vector>

#include "flexsplat/raster/intersect.hpp"

using namespace flexsplat;
using namespace flexsplat::raster;

TEST_CASE("intersect: exact ellipse-tile test never misses a sampled point inside the ellipse", "[raster][intersect]") {
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> uni(-1, 1);
  int touching = 0, rejected = 0;
  for (int trial = 0; trial < 3000; ++trial) {
    // Random positive-definite conic, including needle-thin ones.
    const double l1 = std::exp(4 * uni(rng)), l2 = std::exp(4 * uni(rng)), th = 3.2 * uni(rng);
    const double c = std::cos(th), s = std::sin(th);
    const double qa = c * c / l1 + s * s / l2, qb = c * s * (1 / l1 - 1 / l2), qc = s * s / l1 + c * c / l2;
    const double u = 20 * uni(rng), v = 20 * uni(rng), r2 = 2 * std::log(255 * (0.5 + 0.5 * uni(rng)));
    const double x0 = 8 * uni(rng), y0 = 8 * uni(rng), x1 = x0 + 15, y1 = y0 + 15;
    const bool touches = ellipse_touches_rect(u, v, qa, qb, qc, r2, x0, x1, y0, y1);
    double best = INFINITY;
    for (int i = 0; i <= 60; ++i)
      for (int j = 0; j <= 60; ++j) {
        const double dx = x0 + (x1 - x0) * i / 60 - u, dy = y0 + (y1 - y0) * j / 60 - v;
        best = std::min(best, qa * dx * dx + 2 * qb * dx * dy + qc * dy * dy);
      }
    if (best <= r2) CHECK(touches);  // a sampled point inside: the test must say yes
    touching += touches;
    rejected += !touches;
  }
  CHECK(touching > 100);  // both outcomes occur, so the test is not vacuous
  CHECK(rejected > 100);
}

TEST_CASE("intersect: per-row tile spans agree with the exact ellipse-tile test", "[raster][intersect]") {
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> uni(-1, 1);
  const TileGrid grid(150, 110);
  long kept = 0, dropped = 0;
  for (int trial = 0; trial < 2000; ++trial) {
    const double l1 = std::exp(5 * uni(rng)), l2 = std::exp(5 * uni(rng)), th = 3.2 * uni(rng);
    const double c = std::cos(th), s = std::sin(th);
    const float conic[3] = {float(c * c / l1 + s * s / l2), float(c * s * (1 / l1 - 1 / l2)), float(s * s / l1 + c * c / l2)};
    const float u = float(75 + 90 * uni(rng)), v = float(55 + 70 * uni(rng));
    const double r2 = 2 * std::log(255 * (0.505 + 0.495 * uni(rng)));  // opacity in [0.01, 1]: r2 > 0 as in use
    const TileRect rect{0, 0, grid.tiles_x - 1, grid.tiles_y - 1};
    for (int ty = 0; ty < grid.tiles_y; ++ty) {
      int tx0 = 0, tx1 = -1;
      const bool any = tile_row_span(u, v, conic, r2, grid, rect, ty, tx0, tx1);
      for (int tx = 0; tx < grid.tiles_x; ++tx) {
        const bool in_span = any && tx >= tx0 && tx <= tx1;
        // Never drops a tile the exact test keeps; keeps a tile only if a slightly larger ellipse touches it.
        if (gaussian_touches_tile(u, v, conic, r2, grid, tx, ty)) CHECK(in_span);
        if (in_span) CHECK(gaussian_touches_tile(u, v, conic, r2 * 1.01 + 0.01, grid, tx, ty));
        kept += in_span;
        dropped += !in_span;
      }
    }
  }
  CHECK(kept > 1000);
  CHECK(dropped > 1000);
}

// Runs sort_items_by_depth on (key, gaussian = input position, emission = 100 + position) items; the Gaussians in
// sorted order, with every item's fields checked to travel together.
template <class U>
std::vector<std::int32_t> sorted_positions(const std::vector<U>& keys) {
  std::vector<TileItem<U>> items(keys.size()), a(keys.size());
  for (std::size_t i = 0; i < keys.size(); ++i)
    items[i] = {keys[i], std::int32_t(i), std::int32_t(100 + i), std::int32_t(7 * i)};
  // the items' own memory as the second buffer, as bin_tiles passes it
  const TileItem<U>* sorted = sort_items_by_depth(items.data(), std::int64_t(keys.size()), a.data(), items.data());
  std::vector<std::int32_t> order;
  for (std::size_t i = 0; i < keys.size(); ++i) {
    CHECK(sorted[i].emission == 100 + sorted[i].gaussian);
    CHECK(sorted[i].column == 7 * sorted[i].gaussian);
    CHECK(sorted[i].key == keys[std::size_t(sorted[i].gaussian)]);
    order.push_back(sorted[i].gaussian);
  }
  return order;
}

TEST_CASE("intersect: per-tile depth sort is ordered, stable and moves whole entries", "[raster][intersect]") {
  const std::vector<float> depths = {3.f, 1.f, 2.f, 1.f, 1e-3f, 70000.f, 2.f};
  std::vector<std::uint32_t> keys;
  for (float z : depths) keys.push_back(depth_key(z));
  CHECK(sorted_positions(keys) == std::vector<std::int32_t>{4, 1, 3, 2, 6, 0, 5});  // ties (1, 2) keep input order
  // double keys, equal keys only, and a long random list against std::stable_sort
  std::vector<std::uint64_t> dk;
  for (double z : {0.5, 0.25, 0.5, 1e6}) dk.push_back(depth_key(z));
  CHECK(sorted_positions(dk) == std::vector<std::int32_t>{1, 0, 2, 3});
  CHECK(sorted_positions(std::vector<std::uint32_t>(5, depth_key(2.f))) == std::vector<std::int32_t>{0, 1, 2, 3, 4});
  std::mt19937 rng(5);
  std::uniform_int_distribution<int> level(0, 40);
  std::vector<float> z(1000);
  for (auto& v : z) v = 0.01f * float(level(rng));  // many ties
  std::vector<std::uint32_t> k;
  for (float v : z) k.push_back(depth_key(v));
  std::vector<std::int32_t> expected(z.size());
  std::iota(expected.begin(), expected.end(), 0);
  std::stable_sort(expected.begin(), expected.end(), [&](int a, int b) { return z[std::size_t(a)] < z[std::size_t(b)]; });
  CHECK(sorted_positions(k) == expected);
}

TEST_CASE("intersect: opacity-aware extent and tile lists of a single Gaussian", "[raster][intersect]") {
  const TileGrid grid(64, 48);
  Projection<float> p{};
  p.u = 20.f, p.v = 20.f, p.z = 2.f;
  p.cov[0] = 4.f, p.cov[1] = 0.f, p.cov[2] = 4.f;
  p.conic[0] = 0.25f, p.conic[1] = 0.f, p.conic[2] = 0.25f;
  p.opacity = 0.9f;
  std::uint8_t visible = 1;
  TileIntersections ti;
  intersect_tiles<float>(1, &visible, &p, grid, RasterSkips{}, ti);
  // radius sqrt(2 ln(255*0.9)) * 2 ~ 6.6 px around (20, 20): tiles x 0..1, y 0..1
  CHECK(ti.gaussian_counts[0] == 4);
  p.opacity = 0.005f;  // radius ~ 1.5 px: only tile (1, 1)
  intersect_tiles<float>(1, &visible, &p, grid, RasterSkips{}, ti);
  CHECK(ti.gaussian_counts[0] == 1);
  const std::int64_t tile = 1 * grid.tiles_x + 1;
  CHECK(ti.tile_offsets[tile + 1] - ti.tile_offsets[tile] == 1);
  CHECK(ti.tile_offsets.back() == 1);
  p.u = -30.f;  // off screen
  intersect_tiles<float>(1, &visible, &p, grid, RasterSkips{}, ti);
  CHECK(ti.gaussian_counts[0] == 0);
  CHECK(ti.tile_entries.empty());
}

TEST_CASE("intersect: lane rectangles and row spans agree with the scalar ones", "[raster][intersect]") {
  using VD = simd::batch<double>;
  constexpr int L = int(VD::size);
  std::mt19937 rng(41);
  std::uniform_real_distribution<double> uni(-1, 1);
  const TileGrid grid(150, 110);
  long same_rect = 0, kept = 0, dropped = 0;
  for (int trial = 0; trial < 3200 / L; ++trial) {  // 3200 Gaussians for any lane count
    alignas(64) double u[L], v[L], cov[3][L], conic[3][L], r2[L];
    float uf[L], vf[L], covf[L][3], conicf[L][3], opacity[L];
    for (int l = 0; l < L; ++l) {
      // Random 2D covariance (some needle-thin) plus blur, its float conic, a mean on or beside the image.
      const double l1 = std::exp(5 * uni(rng)), l2 = std::exp(5 * uni(rng)), th = 3.2 * uni(rng);
      const double c = std::cos(th), s = std::sin(th);
      const double a = c * c * l1 + s * s * l2 + 0.3, b = c * s * (l1 - l2), cc = s * s * l1 + c * c * l2 + 0.3;
      const double det = a * cc - b * b;
      covf[l][0] = float(a), covf[l][1] = float(b), covf[l][2] = float(cc);
      conicf[l][0] = float(cc / det), conicf[l][1] = float(-b / det), conicf[l][2] = float(a / det);
      uf[l] = float(75 + 100 * uni(rng)), vf[l] = float(55 + 80 * uni(rng));
      opacity[l] = float(0.5 + 0.5 * uni(rng) + 0.004);
      u[l] = uf[l], v[l] = vf[l];
      for (int i = 0; i < 3; ++i) cov[i][l] = covf[l][i], conic[i][l] = conicf[l][i];
      r2[l] = cull_radius2(double(opacity[l]), true);
    }
    auto load = [](const double* p) { return simd::lane_load<VD>(p); };
    TileRectLanes<VD> rect;
    const auto hit = tile_rect_lanes(load(u), load(v), load(cov[0]), load(cov[2]), load(r2), grid, rect);
    const EllipseRowsLanes<VD> e = ellipse_rows_lanes(load(u), load(v), load(conic[0]), load(conic[1]), load(conic[2]),
                                                      load(r2));
    alignas(64) double hits[L], x0[L], y0[L], x1[L], y1[L];
    simd::lane_store(hits, simd::lane_select(hit, VD(1.0), VD(0.0)));
    simd::lane_store(x0, rect.x0), simd::lane_store(y0, rect.y0), simd::lane_store(x1, rect.x1), simd::lane_store(y1, rect.y1);
    for (int l = 0; l < L; ++l) {
      TileRect expect;
      double r2_scalar = 0;
      const bool scalar_hit = gaussian_tile_rect(uf[l], vf[l], covf[l], opacity[l], grid, true, expect, r2_scalar);
      REQUIRE(scalar_hit == (hits[l] != 0));
      if (!scalar_hit) continue;
      CHECK(expect.x0 == int(x0[l]));
      CHECK(expect.y0 == int(y0[l]));
      CHECK(expect.x1 == int(x1[l]));
      CHECK(expect.y1 == int(y1[l]));
      ++same_rect;
    }
    // Every row of the grid: never drops a tile the exact test keeps, keeps only tiles a slightly larger ellipse touches.
    const TileRectLanes<VD> full{VD(0.0), VD(0.0), VD(double(grid.tiles_x - 1)), VD(double(grid.tiles_y - 1))};
    for (int ty = 0; ty < grid.tiles_y; ++ty) {
      VD first, last;
      const auto reached = tile_row_span_lanes(e, grid, full, VD(double(ty)), first, last);
      alignas(64) double any[L], f[L], g[L];
      simd::lane_store(any, simd::lane_select(reached, VD(1.0), VD(0.0)));
      simd::lane_store(f, first), simd::lane_store(g, last);
      for (int l = 0; l < L; ++l)
        for (int tx = 0; tx < grid.tiles_x; ++tx) {
          const bool in_span = any[l] != 0 && tx >= f[l] && tx <= g[l];
          if (gaussian_touches_tile(uf[l], vf[l], conicf[l], r2[l], grid, tx, ty)) CHECK(in_span);
          if (in_span) CHECK(gaussian_touches_tile(uf[l], vf[l], conicf[l], r2[l] * 1.01 + 0.01, grid, tx, ty));
          kept += in_span;
          dropped += !in_span;
        }
    }
  }
  CHECK(same_rect > 500);
  CHECK(kept > 1000);
  CHECK(dropped > 1000);
}
