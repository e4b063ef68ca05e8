#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <numeric>

#include "decoder_test_util.hpp"
#include "flexsplat/decoder/deform_core.hpp"
#include "flexsplat/decoder/kernels.hpp"
#include "flexsplat/decoder/morton.hpp"
#include "flexsplat/nn/attention.hpp"
#include "simd_lanes.hpp"

using namespace flexsplat;
namespace k = flexsplat::decoder::kernels;

namespace {
// max |a - b| / max(max |b|, floor)
template <class T>
double rel_diff(const std::vector<T>& a, const std::vector<T>& b, double floor = 1e-30) {
  double err = 0, ref = floor;
  for (std::size_t i = 0; i < a.size(); ++i) {
    err = std::max(err, std::abs(static_cast<double>(a[i]) - static_cast<double>(b[i])));
    ref = std::max(ref, std::abs(static_cast<double>(b[i])));
  }
  return err / ref;
}

struct WindowCase {
  k::WindowAttentionShape s;
  std::vector<double> qkv, d_out;
  WindowCase(index_t n, index_t window) : s{n, window, 2, 8} {
    qkv = random_normal(n * 3 * s.dim(), 93, 1.5);
    d_out = random_normal(n * s.dim(), 94);
  }
};

template <class T, bool Simd>
void run_window(const WindowCase& c, std::vector<T>& out, std::vector<T>& lse, std::vector<T>& d_qkv) {
  const auto qkv = cast_vector<T>(c.qkv), d_out = cast_vector<T>(c.d_out);
  out.assign(c.s.n * c.s.dim(), T(0));
  lse.assign(c.s.n * c.s.heads, T(0));
  d_qkv.assign(qkv.size(), T(0.25));
  std::vector<T> scratch(k::window_attention_scratch_per_worker(c.s) * global_pool().size());
  const T scale = T(1) / std::sqrt(T(c.s.head_dim));
  k::window_attention_forward_impl<T, Simd>(out.data(), lse.data(), qkv.data(), c.s, scale, scratch);
  k::window_attention_backward_impl<T, Simd>(d_qkv.data(), d_out.data(), out.data(), lse.data(), qkv.data(), c.s, scale,
                                              scratch);
}
}  // namespace

TEST_CASE("softmax with log-sum-exp: SIMD and scalar paths agree and sum to one", "[decoder][kernels][simd]") {
  for (index_t n : {1, 3, 16, 17, 100}) {
    auto row = cast_vector<float>(random_normal(n, 95 + static_cast<unsigned>(n), 4.0));
    auto a = row, b = row;
    const float lse_a = k::softmax_lse_impl<float, true>(a.data(), n);
    const float lse_b = k::softmax_lse_impl<float, false>(b.data(), n);
    double expect_lse = 0, mx = -INFINITY;
    for (float x : row) mx = std::max(mx, double(x));
    for (float x : row) expect_lse += std::exp(double(x) - mx);
    expect_lse = mx + std::log(expect_lse);
    CHECK(lse_a == Approx(expect_lse).epsilon(1e-6));
    CHECK(lse_b == Approx(expect_lse).epsilon(1e-6));
    double sum = 0;
    for (index_t i = 0; i < n; ++i) {
      REQUIRE(a[i] == Approx(b[i]).epsilon(1e-6).margin(1e-7));
      REQUIRE(b[i] == Approx(std::exp(double(row[i]) - expect_lse)).epsilon(1e-5).margin(1e-7));
      sum += a[i];
    }
    CHECK(sum == Approx(1.0).epsilon(1e-6));
  }
}

TEST_CASE("window attention: SIMD and scalar paths agree, and each window is full attention over itself",
          "[decoder][kernels][simd]") {
  // 150 queries: windows of 64 (two full, one of 22), of 100 (two 64-row query blocks each, the last window short),
  // of 150 (one window, three query blocks).
  for (index_t window : {64, 100, 150}) {
    WindowCase c(150, window);
    std::vector<double> out_s, lse_s, dq_s, out_v, lse_v, dq_v;
    run_window<double, true>(c, out_v, lse_v, dq_v);
    run_window<double, false>(c, out_s, lse_s, dq_s);
    CHECK(rel_diff(out_v, out_s) < 1e-13);
    CHECK(rel_diff(lse_v, lse_s) < 1e-13);
    CHECK(rel_diff(dq_v, dq_s) < 1e-12);
    std::vector<float> out_f, lse_f, dq_f, out_fs, lse_fs, dq_fs;
    run_window<float, true>(c, out_f, lse_f, dq_f);
    run_window<float, false>(c, out_fs, lse_fs, dq_fs);
    CHECK(rel_diff(out_f, out_fs) < 1e-5);
    CHECK(rel_diff(dq_f, dq_fs) < 1e-5);
    // Reference: nn::attention (tiled online softmax) on each window separately.
    const index_t D = c.s.dim();
    std::vector<double> expect(out_s.size()), expect_dq(c.qkv.size(), 0.25), lse(c.s.n * c.s.heads);
    std::vector<double> scratch(nn::attention_scratch_per_worker(c.s.head_dim) * global_pool().size());
    for (index_t w0 = 0; w0 < c.s.n; w0 += window) {
      const index_t cnt = std::min(window, c.s.n - w0);
      nn::AttentionLayout L;
      L.heads = c.s.heads, L.n_q = L.n_kv = cnt, L.head_dim = c.s.head_dim;
      L.q = L.k = L.v = {cnt * 3 * D, c.s.head_dim, 3 * D};
      L.out = {cnt * D, c.s.head_dim, D};
      const double* q = c.qkv.data() + w0 * 3 * D;
      double* dq = expect_dq.data() + w0 * 3 * D;
      std::vector<double> wl(cnt * c.s.heads);
      nn::attention_forward(expect.data() + w0 * D, wl.data(), q, q + D, q + 2 * D, L, 1 / std::sqrt(8.0),
                            std::span<double>(scratch));
      nn::attention_backward(dq, dq + D, dq + 2 * D, c.d_out.data() + w0 * D, expect.data() + w0 * D, wl.data(), q, q + D,
                             q + 2 * D, L, 1 / std::sqrt(8.0), std::span<double>(scratch));
    }
    CHECK(rel_diff(out_s, expect) < 1e-13);
    CHECK(rel_diff(dq_s, expect_dq) < 1e-12);
  }
}

namespace {
// deform_core on float with each of `lanes` against the scalar path, forward and backward, in two visiting orders; with
// `with_double`, also the double path's compiled lanes against its scalar one.
void check_deform_core_lanes(const std::vector<simd::Lanes>& lanes, bool with_double) {
  std::vector<index_t> hw{9, 11, 6, 7};
  // 12: a head width with compile-time row kernels (the small model's); 37: not a multiple of any vector width.
  for (const index_t D : {index_t(12), index_t(37)}) {
    CAPTURE(D);
    const index_t heads = 2, P = 3, Q = 13;
    const auto L = decoder::make_deform_core_layout(1, Q, heads, D, P, hw);
    const auto value = random_normal(L.value_len() * heads * D, 101);
    const auto loc = random_uniform(L.location_count() * 2, 102, -0.2, 1.2);
    auto w = random_uniform(L.location_count(), 103, 0.0, 1.0);
    w[5] = 0;  // a zero weight: the forward skips its taps, the backward still gives its gradient
    const auto g = random_normal(Q * heads * D, 104);
    std::vector<index_t> reversed(Q);
    std::iota(reversed.rbegin(), reversed.rend(), index_t{0});
    auto run = [&](auto tag, simd::Lanes lanes, const index_t* order, auto& out, auto& dv, auto& dl, auto& dw) {
      using T = decltype(tag);
      const auto v = cast_vector<T>(value), l = cast_vector<T>(loc), ww = cast_vector<T>(w), gg = cast_vector<T>(g);
      out.assign(Q * heads * D, T(0));
      dv.assign(v.size(), T(0)), dl.assign(l.size(), T(0)), dw.assign(ww.size(), T(0));
      decoder::deform_core_forward_impl<T>(out.data(), v.data(), l.data(), ww.data(), L, lanes, global_pool(), order);
      decoder::deform_core_backward_impl<T>(dv.data(), dl.data(), dw.data(), gg.data(), v.data(), l.data(), ww.data(), L,
                                            lanes, global_pool(), order);
    };
    std::vector<float> o0, v0, l0, w0, o1, v1, l1, w1, o3, v3, l3, w3;
    run(0.0f, simd::Lanes::scalar, nullptr, o0, v0, l0, w0);
    for (const simd::Lanes lane : lanes) {
      CAPTURE(simd::lanes_name(lane));
      run(0.0f, lane, nullptr, o1, v1, l1, w1);
      CHECK(rel_diff(o1, o0) < 1e-6);
      CHECK(rel_diff(v1, v0) < 1e-6);
      CHECK(rel_diff(l1, l0) < 1e-5);
      CHECK(rel_diff(w1, w0) < 1e-6);
      run(0.0f, lane, reversed.data(), o3, v3, l3, w3);
      CHECK(o3 == o1);  // each query's output is computed alone: bit-identical in any order
      CHECK(l3 == l1);
      CHECK(w3 == w1);
      CHECK(rel_diff(v3, v1) < 1e-6);  // d_value sums over queries in the visiting order
    }
    if (!with_double) continue;
    std::vector<double> od1, vd1, ld1, wd1, od2, vd2, ld2, wd2;
    run(0.0, simd::Lanes::compiled, nullptr, od1, vd1, ld1, wd1);
    run(0.0, simd::Lanes::scalar, nullptr, od2, vd2, ld2, wd2);
    CHECK(rel_diff(od1, od2) < 1e-14);
    CHECK(rel_diff(vd1, vd2) < 1e-14);
    CHECK(rel_diff(ld1, ld2) < 1e-13);
    CHECK(rel_diff(wd1, wd2) < 1e-14);
    // Sanity: the float path follows the double one.
    CHECK(rel_diff(o0, cast_vector<float>(od2)) < 1e-5);
  }
}
void check_deform_core_dispatch(simd::Lanes lanes) { check_deform_core_lanes({lanes}, false); }
}  // namespace

TEST_CASE("deform_core: every lane set agrees with the scalar path and the visiting order changes nothing",
          "[decoder][kernels][simd]") {
  // The build's compiled lanes (float and double); the run-time dispatched ones are the cases below, one per level.
  check_deform_core_lanes({simd::Lanes::compiled}, true);
}

FLEXSPLAT_DISPATCH_TEST_CASES("deform_core: the dispatched lanes agree with the scalar path in either visiting order",
                              "[decoder][kernels][simd]", check_deform_core_dispatch)

TEST_CASE("radix sort equals a stable sort by key, for Morton items", "[decoder][kernels]") {
  const index_t n = 5000;
  std::mt19937 rng(7);
  std::vector<decoder::MortonKey> items(n), scratch(n);
  for (index_t i = 0; i < n; ++i) {
    const std::uint32_t r = rng();
    items[i] = {r % 3 ? r >> 2 & 0x3ffu : r >> 2 & 0x3fffffffu, std::uint32_t(i)};  // mostly small keys: many ties
  }
  auto expect = items;
  std::stable_sort(expect.begin(), expect.end(), [](const auto& a, const auto& b) { return a.code < b.code; });
  const decoder::MortonKey* sorted =
      radix_sort(items.data(), n, scratch.data(), items.data(), [](const decoder::MortonKey& k) { return k.code; });
  for (index_t i = 0; i < n; ++i) {
    REQUIRE(sorted[i].code == expect[i].code);
    REQUIRE(sorted[i].index == expect[i].index);
  }
}

TEST_CASE("window attention rejects bad shapes and short scratch", "[decoder][kernels]") {
  std::vector<float> buf(64), scratch(8);
  CHECK_THROWS_WITH(k::window_attention_forward(buf.data(), buf.data(), buf.data(), k::WindowAttentionShape{4, 0, 1, 2}, 1.f,
                                                std::span<float>(scratch)),
                    Catch::Contains("window 0"));
  CHECK_THROWS_WITH(k::window_attention_forward(buf.data(), buf.data(), buf.data(), k::WindowAttentionShape{4, 4, 1, 2}, 1.f,
                                                std::span<float>(scratch)),
                    Catch::Contains("scratch has 8 elements"));
}
