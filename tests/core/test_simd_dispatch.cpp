#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <type_traits>
#include <vector>

#include "flexsplat/core/simd_dispatch.hpp"
#include "skip.hpp"

using namespace flexsplat;

#if FLEXSPLAT_SIMD_DISPATCH
namespace {

// The dispatch vectors only exist inside functions compiled for their target, as in the raster kernels.
template <int N, class Op>
void dispatch_lanes(const float* in, float* out, int count) {
  for (int i = 0; i + N <= count; i += N)
    simd::lane_store(out + i, Op{}(simd::lane_load<simd::wide<float, N>>(in + i)));
}
template <class Op>
__attribute__((target("avx512f,avx512dq,avx512bw,avx512vl,avx2,fma"), flatten)) void dispatch16(const float* in,
                                                                                               float* out, int n) {
  dispatch_lanes<16, Op>(in, out, n);
}
template <class Op>
__attribute__((target("avx2,fma"), flatten)) void dispatch8(const float* in, float* out, int n) {
  dispatch_lanes<8, Op>(in, out, n);
}
// The lane operations under test, as types so each target wrapper is instantiated per operation.
struct LaneExp {
  template <class V> V operator()(V v) const { return simd::lane_exp(v); }
};
struct LaneExpBlend {
  template <class V> V operator()(V v) const { return simd::lane_exp_blend(v); }
};
struct LaneErf {
  template <class V> V operator()(V v) const { return simd::lane_erf(v); }
};

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

// Lane-by-lane results of the math the per-Gaussian pass uses, for doubles (x) and floats (xf, yf, zf), computed with
// the dispatch vectors of one level inside simd::run_*_exact (the pass's own wrappers).
struct LaneMath {
  std::vector<double> sqrt, floor, ceil, log, finite, min, max, select;
  std::vector<float> sqrt_f, mul_add_f, finite_f, columns;
  bool any = false, all = false;
};
template <class V>
void lane_math(const std::vector<double>& x, const std::vector<double>& y, const std::vector<float>& xf,
               const std::vector<float>& yf, const std::vector<float>& zf, LaneMath& r) {
  using VD = typename simd::double_lanes<V>::type;
  constexpr int LD = int(simd::lane_count<VD>::value), L = int(simd::lane_count<V>::value);
  for (std::size_t i = 0; i + LD <= x.size(); i += LD) {
    const VD a = simd::lane_load<VD>(&x[i]), b = simd::lane_load<VD>(&y[i]);
    simd::lane_store(&r.sqrt[i], simd::lane_sqrt(a));
    simd::lane_store(&r.floor[i], simd::lane_floor(a));
    simd::lane_store(&r.ceil[i], simd::lane_ceil(a));
    simd::lane_store(&r.log[i], simd::lane_log(a));
    simd::lane_store(&r.finite[i], simd::lane_select(simd::lane_isfinite(a), VD(1.0), VD(0.0)));
    simd::lane_store(&r.min[i], simd::lane_min(a, b));
    simd::lane_store(&r.max[i], simd::lane_max(a, b));
    simd::lane_store(&r.select[i], simd::lane_select((a < b) | (a == b), a + b, a - b));
  }
  const VD first = simd::lane_load<VD>(&x[0]);
  r.any = simd::lane_any(first > VD(0.0)), r.all = simd::lane_all(first > VD(0.0));
  for (std::size_t i = 0; i + L <= xf.size(); i += L) {
    const V a = simd::lane_load<V>(&xf[i]), b = simd::lane_load<V>(&yf[i]), c = simd::lane_load<V>(&zf[i]);
    simd::lane_store(&r.sqrt_f[i], simd::lane_sqrt(a));
    simd::lane_store(&r.mul_add_f[i], simd::lane_mul_add(a, b, c));
    simd::lane_store(&r.finite_f[i], simd::lane_select(simd::lane_isfinite(a), V(1.0f), V(0.0f)));
  }
  // columns 0..12 of L rows of 13 values: column j of row l at [j * L + l]
  const float* rows[L];
  for (int l = 0; l < L; ++l) rows[l] = &xf[std::size_t(l) * 13];
  V cols[13];
  simd::load_columns<V, float>(rows, 13, cols);
  for (int j = 0; j < 13; ++j) simd::lane_store(&r.columns[std::size_t(j) * L], cols[j]);
}

bool level_available(simd::DispatchLevel level) {
  const auto& f = simd::cpu_features();
  return level == simd::DispatchLevel::avx512 ? f.avx512f && f.avx512dq && f.avx512bw && f.avx512vl && f.fma
                                              : f.avx2 && f.fma;
}

// Op over in[0, n) with `level`'s dispatch vectors.
template <class Op>
void run_dispatch(simd::DispatchLevel level, const float* in, float* out, int n) {
  if (level == simd::DispatchLevel::avx512) dispatch16<Op>(in, out, n);
  else dispatch8<Op>(in, out, n);
}

// Runs check(level), or skips where the CPU lacks the level (one test case per level, so a skip hides nothing).
template <class Check>
void at_level(simd::DispatchLevel level, Check check) {
  if (!level_available(level))
    FLEXSPLAT_SKIP("CPU lacks " << simd::dispatch_name(level) << ": its dispatch vectors cannot run here");
  check(level);
}

}  // namespace

#define DISPATCH_TEST_CASES(name, tags, check)                                          \
  TEST_CASE(name " (avx2)", tags) { at_level(simd::DispatchLevel::avx2, check); }     \
  TEST_CASE(name " (avx512)", tags) { at_level(simd::DispatchLevel::avx512, check); }

namespace {
void check_exp(simd::DispatchLevel level) {
  const int n = 16 * 4096;
  std::vector<float> in(n), out(n);
  for (int i = 0; i < n; ++i) in[i] = -100.0f + 100.0f * float(i) / float(n - 1);  // [-100, 0]: the kernels' -sigma
  std::fill(out.begin(), out.end(), -1.0f);
  run_dispatch<LaneExp>(level, in.data(), out.data(), n);
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
}  // namespace

DISPATCH_TEST_CASES("simd dispatch: exp of dispatch vectors is accurate to float precision", "[simd][dispatch]",
                    check_exp)

namespace {
void check_erf(simd::DispatchLevel level) {
  const int n = 16 * 4096;
  std::vector<float> in(n), out(n);
  for (int i = 0; i < n - 16; ++i) in[i] = -6.0f + 12.0f * float(i) / float(n - 17);  // both branches, |x| < 2/3 and above
  const float special[16] = {INFINITY, -INFINITY, 0.0f, -0.0f, 1e-30f, -1e-30f, 30.0f, -30.0f,
                             3.92f, -3.92f, 0.6666f, 0.6667f, -0.6667f, 10.0f, 1e-6f, 2.0f};
  std::copy(special, special + 16, in.begin() + (n - 16));
  std::fill(out.begin(), out.end(), -2.0f);
  run_dispatch<LaneErf>(level, in.data(), out.data(), n);
  double worst = 0;
  for (int i = 0; i < n; ++i) worst = std::max(worst, std::abs(double(out[i]) - std::erf(double(in[i]))));
  INFO(simd::dispatch_name(level) << ": worst absolute error " << worst);
  CHECK(worst < 1.5e-7);  // measured 9.0e-8 (std::erf in float: 5.4e-8)
  CHECK(out[n - 16] == 1.0f);
  CHECK(out[n - 15] == -1.0f);
  CHECK(out[n - 14] == 0.0f);
}
}  // namespace

DISPATCH_TEST_CASES("simd dispatch: erf of dispatch vectors is accurate to float precision", "[simd][dispatch]",
                    check_erf)

TEST_CASE("simd dispatch: the blend exp is accurate to float precision where the blend uses it (avx512)", "[simd][dispatch]") {
  if (!level_available(simd::DispatchLevel::avx512))
    FLEXSPLAT_SKIP("CPU lacks avx512: the 16-lane blend exp cannot run here");
  // The blend's lanes that matter have -sigma in [-sigma_max, 0], sigma_max < 6 (opacity <= 1).
  const int n = 16 * 4096;
  std::vector<float> in(n), out(n, -1.0f);
  for (int i = 0; i < n; ++i) in[i] = -6.0f + 6.0f * float(i) / float(n - 1);
  dispatch16<LaneExpBlend>(in.data(), out.data(), n);
  double worst = 0;
  for (int i = 0; i < n; ++i) {
    const double ref = std::exp(double(in[i]));
    worst = std::max(worst, std::abs(double(out[i]) - ref) / ref);
  }
  INFO("worst relative error " << worst);
  CHECK(worst < 1.5e-7);
  CHECK(out[n - 1] == 1.0f);
}

namespace {
void check_masks(simd::DispatchLevel level) {
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
}  // namespace

DISPATCH_TEST_CASES("simd dispatch: masks, select, min, any and all of dispatch vectors", "[simd][dispatch]",
                    check_masks)

namespace {
void check_lane_math(simd::DispatchLevel level) {
  std::vector<double> x, y;
  // log-spaced positives over the normal range, the pass's log arguments [1, 255], halves, signs and non-finite values
  for (int i = 0; i < 4096; ++i) x.push_back(std::pow(10.0, -300.0 + 600.0 * i / 4095.0));
  for (int i = 0; i < 4096; ++i) x.push_back(1.0 + 254.0 * i / 4095.0);
  for (double v : {0.5, 1.5, 2.5, -0.5, -1.5, -2.0, 0.0, -0.0, 4503599627370495.5, -1e300, double(INFINITY), -double(INFINITY), double(NAN)})
    x.push_back(v);
  while (x.size() % 16) x.push_back(3.0);
  for (std::size_t i = 0; i < x.size(); ++i) y.push_back(i % 3 == 0 ? x[i] : i % 3 == 1 ? 2.0 : -2.0);
  std::vector<float> xf, yf, zf;
  for (int i = 0; i < 16 * 13; ++i) {
    xf.push_back(float(std::sin(0.37 * i) * 1e3)), yf.push_back(float(std::cos(0.11 * i))), zf.push_back(0.1f * float(i));
  }
  xf[3] = INFINITY, xf[5] = NAN, xf[7] = 2.0f;
  const auto same = [](double a, double b) { return a == b || (std::isnan(a) && std::isnan(b)); };
  INFO(simd::dispatch_name(level));
  LaneMath r;
  for (auto* v : {&r.sqrt, &r.floor, &r.ceil, &r.log, &r.finite, &r.min, &r.max, &r.select}) v->assign(x.size(), -7.0);
  for (auto* v : {&r.sqrt_f, &r.mul_add_f, &r.finite_f, &r.columns}) v->assign(xf.size(), -7.0f);
  auto body = [&](auto* lanes) { lane_math<std::remove_pointer_t<decltype(lanes)>>(x, y, xf, yf, zf, r); };
  if (level == simd::DispatchLevel::avx512) simd::run_avx512_exact(body);
  else simd::run_avx2_exact(body);
  const int L = level == simd::DispatchLevel::avx512 ? 16 : 8;
  double worst_log = 0;
  for (std::size_t i = 0; i < x.size(); ++i) {
    INFO("x = " << x[i]);
    CHECK(same(r.sqrt[i], std::sqrt(x[i])));
    CHECK(same(r.floor[i], std::floor(x[i])));
    CHECK(same(r.ceil[i], std::ceil(x[i])));
    CHECK(r.finite[i] == (std::isfinite(x[i]) ? 1.0 : 0.0));
    CHECK(same(r.min[i], x[i] < y[i] ? x[i] : y[i]));
    CHECK(same(r.max[i], x[i] < y[i] ? y[i] : x[i]));
    CHECK(same(r.select[i], x[i] <= y[i] ? x[i] + y[i] : x[i] - y[i]));
    if (std::isfinite(x[i]) && x[i] > 0) worst_log = std::max(worst_log, std::abs(r.log[i] - std::log(x[i])) /
                                                                              std::max(1.0, std::abs(std::log(x[i]))));
  }
  INFO("log: worst error " << worst_log << " (relative, absolute below 1)");
  CHECK(worst_log < 4e-16);
  CHECK(r.any == (x[0] > 0));
  CHECK(r.all == (x[0] > 0 && x[1] > 0));
  for (std::size_t i = 0; i < xf.size(); ++i) {
    INFO("xf = " << xf[i]);
    CHECK(same(r.sqrt_f[i], std::sqrt(xf[i])));
    // the scalar lane_mul_add of this build: fused with FMA, a product and a sum otherwise
    CHECK(same(r.mul_add_f[i], simd::lane_mul_add(xf[i], yf[i], zf[i])));
    CHECK(r.finite_f[i] == (std::isfinite(xf[i]) ? 1.0f : 0.0f));
  }
  for (int j = 0; j < 13; ++j)
    for (int l = 0; l < L; ++l) CHECK(same(r.columns[std::size_t(j) * L + l], xf[std::size_t(l) * 13 + j]));
}
}  // namespace

DISPATCH_TEST_CASES("simd dispatch: double lanes and the per-Gaussian pass's math match the scalar functions",
                    "[simd][dispatch]", check_lane_math)

#endif
