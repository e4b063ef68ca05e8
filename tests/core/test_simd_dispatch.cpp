#include <catch2/catch.hpp>

#include <cmath>
#include <vector>

#include "flexsplat/core/simd_dispatch.hpp"

using namespace flexsplat;

#if FLEXSPLAT_SIMD_DISPATCH
namespace {

// The dispatch vectors only exist inside functions compiled for their target, as in the raster kernels.
template <int N>
void dispatch_exp_lanes(const float* in, float* out, int count) {
  for (int i = 0; i + N <= count; i += N)
    simd::lane_store(out + i, simd::lane_exp(simd::lane_load<simd::wide<float, N>>(in + i)));
}
__attribute__((target("avx512f,avx512dq,avx512bw,avx512vl,avx2,fma"), flatten)) void dispatch_exp16(const float* in,
                                                                                                   float* out, int n) {
  dispatch_exp_lanes<16>(in, out, n);
}
__attribute__((target("avx2,fma"), flatten)) void dispatch_exp8(const float* in, float* out, int n) {
  dispatch_exp_lanes<8>(in, out, n);
}
__attribute__((target("avx512f,avx512dq,avx512bw,avx512vl,avx2,fma"), flatten)) void blend_exp16(const float* in,
                                                                                                float* out, int n) {
  for (int i = 0; i + 16 <= n; i += 16)
    simd::lane_store(out + i, simd::lane_exp_blend(simd::lane_load<simd::wide<float, 16>>(in + i)));
}

// any / all / select / min of lanes a < b, written back as 0/1 per lane.
template <int N>
void dispatch_mask_lanes(const float* a, const float* b, float* select_out, float* min_out, bool& any, bool& all) {
  using V = simd::wide<float, N>;
  const V x = simd::lane_load<V>(a), y = simd::lane_load<V>(b);
  const auto less = x < y;
  simd::lane_store(select_out, simd::lane_select(less, V(1.0f), V(0.0f)));
  simd::lane_store(min_out, simd::lane_min(x, y));
  any = simd::lane_any(less);
  all = simd::lane_all(less);
}
__attribute__((target("avx512f,avx512dq,avx512bw,avx512vl,avx2,fma"), flatten)) void dispatch_mask16(
    const float* a, const float* b, float* s, float* m, bool& any, bool& all) {
  dispatch_mask_lanes<16>(a, b, s, m, any, all);
}
__attribute__((target("avx2,fma"), flatten)) void dispatch_mask8(const float* a, const float* b, float* s, float* m,
                                                                 bool& any, bool& all) {
  dispatch_mask_lanes<8>(a, b, s, m, any, all);
}

bool level_available(simd::DispatchLevel level) {
  const auto& f = simd::cpu_features();
  return level == simd::DispatchLevel::avx512 ? f.avx512f && f.avx512dq && f.avx512bw && f.avx512vl && f.fma
                                              : f.avx2 && f.fma;
}

}  // namespace

TEST_CASE("simd dispatch: exp of 8- and 16-lane dispatch vectors is accurate to float precision", "[simd][dispatch]") {
  const int n = 16 * 4096;
  std::vector<float> in(n), out(n);
  for (int i = 0; i < n; ++i) in[i] = -100.0f + 100.0f * float(i) / float(n - 1);  // [-100, 0]: the kernels' -sigma
  for (auto level : {simd::DispatchLevel::avx2, simd::DispatchLevel::avx512}) {
    if (!level_available(level)) {
      WARN("CPU lacks " << simd::dispatch_name(level) << ": its dispatch vectors are not exercised here");
      continue;
    }
    std::fill(out.begin(), out.end(), -1.0f);
    if (level == simd::DispatchLevel::avx512) dispatch_exp16(in.data(), out.data(), n);
    else dispatch_exp8(in.data(), out.data(), n);
    double worst = 0;
    for (int i = 0; i < n; ++i) {
      const double ref = std::exp(double(in[i]));
      if (in[i] < -87.0f) {
        CHECK(out[i] == 0.0f);
      } else {
        worst = std::max(worst, std::abs(double(out[i]) - ref) / ref);
      }
    }
    INFO(simd::dispatch_name(level) << ": worst relative error " << worst);
    CHECK(worst < 1.5e-7);  // measured 8.4e-8
    CHECK(out[n - 1] == 1.0f);  // exp(0)
  }
}

TEST_CASE("simd dispatch: the blend exp is accurate to float precision where the blend uses it", "[simd][dispatch]") {
  if (!level_available(simd::DispatchLevel::avx512)) {
    WARN("CPU lacks avx512: the 16-lane blend exp is not exercised here");
    return;
  }
  // The blend's lanes that matter have -sigma in [-sigma_max, 0], sigma_max < 6 (opacity <= 1).
  const int n = 16 * 4096;
  std::vector<float> in(n), out(n, -1.0f);
  for (int i = 0; i < n; ++i) in[i] = -6.0f + 6.0f * float(i) / float(n - 1);
  blend_exp16(in.data(), out.data(), n);
  double worst = 0;
  for (int i = 0; i < n; ++i) {
    const double ref = std::exp(double(in[i]));
    worst = std::max(worst, std::abs(double(out[i]) - ref) / ref);
  }
  INFO("worst relative error " << worst);
  CHECK(worst < 1.5e-7);
  CHECK(out[n - 1] == 1.0f);
}

TEST_CASE("simd dispatch: masks, select, min, any and all of dispatch vectors", "[simd][dispatch]") {
  for (auto level : {simd::DispatchLevel::avx2, simd::DispatchLevel::avx512}) {
    if (!level_available(level)) {
      WARN("CPU lacks " << simd::dispatch_name(level) << ": its dispatch vectors are not exercised here");
      continue;
    }
    const int lanes = level == simd::DispatchLevel::avx512 ? 16 : 8;
    auto run = [&](const std::vector<float>& a, const std::vector<float>& b, std::vector<float>& sel,
                   std::vector<float>& mn, bool& any, bool& all) {
      if (lanes == 16) dispatch_mask16(a.data(), b.data(), sel.data(), mn.data(), any, all);
      else dispatch_mask8(a.data(), b.data(), sel.data(), mn.data(), any, all);
    };
    std::vector<float> a(lanes), b(lanes), sel(lanes), mn(lanes);
    for (int pattern : {0, 1, 2, 3}) {  // none, one (last lane), alternate, all lanes less
      for (int i = 0; i < lanes; ++i) {
        a[i] = float(i);
        const bool less = pattern == 3 || (pattern == 1 && i == lanes - 1) || (pattern == 2 && i % 2 == 0);
        b[i] = less ? a[i] + 0.5f : a[i] - 0.5f;
      }
      bool any = false, all = false;
      run(a, b, sel, mn, any, all);
      bool expect_any = false, expect_all = true;
      for (int i = 0; i < lanes; ++i) {
        const bool less = a[i] < b[i];
        CHECK(sel[i] == (less ? 1.0f : 0.0f));
        CHECK(mn[i] == std::min(a[i], b[i]));
        expect_any = expect_any || less;
        expect_all = expect_all && less;
      }
      INFO(simd::dispatch_name(level) << " pattern " << pattern);
      CHECK(any == expect_any);
      CHECK(all == expect_all);
    }
  }
}
#endif
