// The deformable sampling core (decoder::deform_core_*_impl) per lane set against the scalar path: forward and
// backward time (best of --reps, one call each) and the largest difference from the scalar results, at the small
// model's shapes by default (1024 queries, 4 heads of 12, 4 points, 4 views of 56 x 56 maps). Locations are the
// decoder's kind: each query's reference point per view plus offsets of up to 2 pixels, visited in cell order.
// Usage: deform_core [--queries 1024] [--heads 4] [--head-dim 12] [--points 4] [--views 4] [--size 56] [--reps 30]
//   threads: FLEXSPLAT_NUM_THREADS (the training runs use 1)
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <numeric>
#include <random>
#include <string>
#include <vector>

#include "flexsplat/decoder/deform_core.hpp"

using namespace flexsplat;

namespace {
double max_rel(const std::vector<float>& a, const std::vector<float>& b) {
  double worst = 0, scale = 0;
  for (std::size_t i = 0; i < a.size(); ++i) {
    worst = std::max(worst, std::abs(double(a[i]) - double(b[i])));
    scale = std::max(scale, std::abs(double(b[i])));
  }
  return scale > 0 ? worst / scale : worst;
}
}  // namespace

int main(int argc, char** argv) {
  index_t n = 1024, H = 4, D = 12, P = 4, V = 4, size = 56;
  int reps = 30;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    const bool more = i + 1 < argc;
    if (a == "--queries" && more) n = std::stol(argv[++i]);
    else if (a == "--heads" && more) H = std::stol(argv[++i]);
    else if (a == "--head-dim" && more) D = std::stol(argv[++i]);
    else if (a == "--points" && more) P = std::stol(argv[++i]);
    else if (a == "--views" && more) V = std::stol(argv[++i]);
    else if (a == "--size" && more) size = std::stol(argv[++i]);
    else if (a == "--reps" && more) reps = std::stoi(argv[++i]);
    else {
      std::fprintf(stderr, "usage: deform_core [--queries N] [--heads N] [--head-dim N] [--points N] [--views N] "
                           "[--size N] [--reps N] (unknown argument '%s')\n", a.c_str());
      return 2;
    }
  }
  if (n < 1 || H < 1 || D < 1 || P < 1 || V < 1 || size < 2 || reps < 1) {
    std::fprintf(stderr, "deform_core: every size and --reps must be positive (--size at least 2)\n");
    return 2;
  }
  decoder::DeformCoreLayout L;
  decoder::set_deform_core_layout(L, 1, n, H, D, P, V, size, size);
  std::mt19937 rng(1);
  std::uniform_real_distribution<float> centre(0.15f, 0.85f), offset(-2.0f / size, 2.0f / size), weight(0.1f, 1.0f);
  std::normal_distribution<float> normal(0.0f, 1.0f);
  std::vector<float> value(L.value_len() * H * D), loc(L.location_count() * 2), w(L.location_count()), g(n * H * D);
  for (auto& x : value) x = normal(rng);
  for (auto& x : g) x = normal(rng);
  std::vector<float> ref(n * V * 2);
  for (auto& x : ref) x = centre(rng);
  for (index_t s = 0; s < L.location_count(); ++s) {
    const index_t v = s / P % V, q = s / (P * V * H);
    loc[2 * s] = ref[(q * V + v) * 2] + offset(rng);
    loc[2 * s + 1] = ref[(q * V + v) * 2 + 1] + offset(rng);
    w[s] = weight(rng);
  }
  // Queries in 8 x 8 cells of their first view, row by row: neighbours read neighbouring pixels, as in Morton order.
  std::vector<index_t> order(n);
  std::iota(order.begin(), order.end(), index_t{0});
  const auto cell = [&](index_t q) { return int(ref[q * V * 2 + 1] * 8) * 8 + int(ref[q * V * 2] * 8); };
  std::stable_sort(order.begin(), order.end(), [&](index_t a, index_t b) { return cell(a) < cell(b); });

  std::vector<simd::Lanes> lanes{simd::Lanes::scalar, simd::Lanes::compiled};
  if (simd::best_lanes<float>(simd::DispatchLevel::avx2) == simd::Lanes::avx2) lanes.push_back(simd::Lanes::avx2);
  if (simd::best_lanes<float>() == simd::Lanes::avx512) lanes.push_back(simd::Lanes::avx512);
  std::printf("deform_core: %ld queries, %ld heads x %ld, %ld points, %ld views of %ld x %ld, %d threads, best of %d\n",
              long(n), long(H), long(D), long(P), long(V), long(size), long(size), global_pool().size(), reps);
  std::printf("| lanes | forward ms | backward ms | forward vs scalar | backward vs scalar | max rel. diff (out, d_value, "
              "d_loc, d_w) |\n|---|---|---|---|---|---|\n");
  std::vector<float> out0, dv0, dl0, dw0;
  double fwd0 = 0, bwd0 = 0;
  for (const simd::Lanes lane : lanes) {
    std::vector<float> out(n * H * D), dv(value.size()), dl(loc.size()), dw(w.size());
    double fwd = 1e30, bwd = 1e30;
    for (int r = 0; r < reps; ++r) {
      std::fill(dv.begin(), dv.end(), 0.0f), std::fill(dl.begin(), dl.end(), 0.0f), std::fill(dw.begin(), dw.end(), 0.0f);
      const auto t0 = std::chrono::steady_clock::now();
      decoder::deform_core_forward_impl<float>(out.data(), value.data(), loc.data(), w.data(), L, lane, global_pool(),
                                               order.data());
      const auto t1 = std::chrono::steady_clock::now();
      decoder::deform_core_backward_impl<float>(dv.data(), dl.data(), dw.data(), g.data(), value.data(), loc.data(),
                                                w.data(), L, lane, global_pool(), order.data());
      const auto t2 = std::chrono::steady_clock::now();
      fwd = std::min(fwd, std::chrono::duration<double, std::milli>(t1 - t0).count());
      bwd = std::min(bwd, std::chrono::duration<double, std::milli>(t2 - t1).count());
    }
    if (lane == simd::Lanes::scalar) out0 = out, dv0 = dv, dl0 = dl, dw0 = dw, fwd0 = fwd, bwd0 = bwd;
    std::printf("| %s | %.3f | %.3f | %.2fx | %.2fx | %.1e, %.1e, %.1e, %.1e |\n", simd::lanes_name(lane), fwd, bwd,
                fwd0 / fwd, bwd0 / bwd, max_rel(out, out0), max_rel(dv, dv0), max_rel(dl, dl0), max_rel(dw, dw0));
  }
  return 0;
}
