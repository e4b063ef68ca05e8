#include <catch2/catch.hpp>

#include <cmath>

#include "flexsplat/nn/attention.hpp"
#include "flexsplat/testing/gradcheck.hpp"
#include "nn_test_util.hpp"
#include "simd_lanes.hpp"

using namespace flexsplat;

namespace {
// Dense softmax(scale q k^T) v for one head, the definition the tiled kernel must match.
std::vector<double> naive_attention(const std::vector<double>& q, const std::vector<double>& k,
                                    const std::vector<double>& v, const nn::AttentionLayout& L, double scale) {
  std::vector<double> out(L.batch * L.heads * L.n_q * L.head_dim, 0.0);
  for (index_t b = 0; b < L.batch; ++b)
    for (index_t h = 0; h < L.heads; ++h)
      for (index_t i = 0; i < L.n_q; ++i) {
        std::vector<double> s(L.n_kv);
        double m = -INFINITY;
        for (index_t j = 0; j < L.n_kv; ++j) {
          double dot = 0;
          for (index_t c = 0; c < L.head_dim; ++c)
            dot += q[b * L.q.batch + h * L.q.head + i * L.q.row + c] * k[b * L.k.batch + h * L.k.head + j * L.k.row + c];
          s[j] = scale * dot;
          m = std::max(m, s[j]);
        }
        double z = 0;
        for (auto& x : s) z += (x = std::exp(x - m));
        for (index_t j = 0; j < L.n_kv; ++j)
          for (index_t c = 0; c < L.head_dim; ++c)
            out[b * L.out.batch + h * L.out.head + i * L.out.row + c] +=
                s[j] / z * v[b * L.v.batch + h * L.v.head + j * L.v.row + c];
      }
  return out;
}
}  // namespace

TEST_CASE("tiled attention equals dense softmax attention across block boundaries", "[nn][attention]") {
  // 70 queries straddle the 64-row query block; the multi-key-block cases are below.
  auto L = nn::packed_attention_layout(2, 3, 70, 150, 5);
  auto q = random_vector(2 * 70 * 15, 11, 2.0), k = random_vector(2 * 150 * 15, 12, 2.0), v = random_vector(2 * 150 * 15, 13);
  std::vector<double> out(q.size()), lse(2 * 3 * 70);
  std::vector<double> scratch(nn::attention_scratch_per_worker(5) * global_pool().size());
  nn::attention_forward(out.data(), lse.data(), q.data(), k.data(), v.data(), L, 0.4, std::span<double>(scratch));
  auto expect = naive_attention(q, k, v, L, 0.4);
  for (std::size_t i = 0; i < out.size(); ++i) REQUIRE(out[i] == Approx(expect[i]).margin(1e-12));
}

TEST_CASE("attention backward passes the float64 gradient check and is thread-count independent", "[nn][attention]") {
  auto L = nn::packed_attention_layout(1, 2, 70, 131, 4);
  auto q = random_vector(70 * 8, 21), k = random_vector(131 * 8, 22), v = random_vector(131 * 8, 23);
  std::vector<double> out(q.size()), lse(2 * 70), dq(q.size()), dk(k.size()), dv(v.size());
  std::vector<double> scratch(nn::attention_scratch_per_worker(4) * global_pool().size());
  std::span<double> ws(scratch);
  auto result = testing::check_gradients(
      {{"q", q, dq}, {"k", k, dk}, {"v", v, dv}}, out.size(),
      [&](std::span<double> o) { nn::attention_forward(o.data(), lse.data(), q.data(), k.data(), v.data(), L, 0.5, ws); },
      [&](std::span<const double> d) {
        nn::attention_forward(out.data(), lse.data(), q.data(), k.data(), v.data(), L, 0.5, ws);
        nn::attention_backward(dq.data(), dk.data(), dv.data(), d.data(), out.data(), lse.data(), q.data(), k.data(),
                               v.data(), L, 0.5, ws);
      });
  INFO(result.summary());
  CHECK(result.ok());

  auto d_out = random_vector(out.size(), 24);
  auto grads_with = [&](ThreadPool& pool) {
    std::vector<double> a(q.size()), b(k.size()), c(v.size());
    std::vector<double> s(nn::attention_scratch_per_worker(4) * pool.size());
    nn::attention_forward(out.data(), lse.data(), q.data(), k.data(), v.data(), L, 0.5, std::span<double>(s), pool);
    nn::attention_backward(a.data(), b.data(), c.data(), d_out.data(), out.data(), lse.data(), q.data(), k.data(),
                           v.data(), L, 0.5, std::span<double>(s), pool);
    a.insert(a.end(), b.begin(), b.end());
    a.insert(a.end(), c.begin(), c.end());
    return a;
  };
  ThreadPool one(1), two(2);
  CHECK(grads_with(one) == grads_with(two));
}

TEST_CASE("attention with no keys gives zeros, not NaN, and short scratch is a clear error", "[nn][attention]") {
  auto L = nn::packed_attention_layout(1, 1, 3, 0, 2);
  std::vector<double> q(6, 1.0), out(6, 7.0), lse(3);
  std::vector<double> scratch(nn::attention_scratch_per_worker(2) * global_pool().size());
  nn::attention_forward(out.data(), lse.data(), q.data(), q.data(), q.data(), L, 1.0, std::span<double>(scratch));
  for (double o : out) CHECK(o == 0.0);
  std::vector<double> tiny(3);
  CHECK_THROWS_WITH(nn::attention_forward(out.data(), lse.data(), q.data(), q.data(), q.data(), L, 1.0, std::span<double>(tiny)),
                    Catch::Contains("attention scratch has 3 elements"));
}

namespace {
// Dense float64 gradients of sum(d_out * attention(q, k, v)) for one layout (definition, O(n_q n_kv) memory).
void naive_attention_backward(const std::vector<double>& q, const std::vector<double>& k, const std::vector<double>& v,
                              const std::vector<double>& d_out, const nn::AttentionLayout& L, double scale,
                              std::vector<double>& dq, std::vector<double>& dk, std::vector<double>& dv) {
  for (index_t b = 0; b < L.batch; ++b)
    for (index_t h = 0; h < L.heads; ++h)
      for (index_t i = 0; i < L.n_q; ++i) {
        const double* qi = q.data() + b * L.q.batch + h * L.q.head + i * L.q.row;
        const double* gi = d_out.data() + b * L.out.batch + h * L.out.head + i * L.out.row;
        std::vector<double> p(L.n_kv), dp(L.n_kv);
        double m = -INFINITY;
        for (index_t j = 0; j < L.n_kv; ++j) {
          const double* kj = k.data() + b * L.k.batch + h * L.k.head + j * L.k.row;
          double s = 0;
          for (index_t c = 0; c < L.head_dim; ++c) s += qi[c] * kj[c];
          p[j] = scale * s;
          m = std::max(m, p[j]);
        }
        double z = 0;
        for (auto& x : p) z += (x = std::exp(x - m));
        double delta = 0;
        for (index_t j = 0; j < L.n_kv; ++j) {
          p[j] /= z;
          const double* vj = v.data() + b * L.v.batch + h * L.v.head + j * L.v.row;
          for (index_t c = 0; c < L.head_dim; ++c) dp[j] += gi[c] * vj[c];
          delta += p[j] * dp[j];
        }
        for (index_t j = 0; j < L.n_kv; ++j) {
          const double ds = scale * p[j] * (dp[j] - delta);
          const index_t kj = b * L.k.batch + h * L.k.head + j * L.k.row, vj = b * L.v.batch + h * L.v.head + j * L.v.row;
          for (index_t c = 0; c < L.head_dim; ++c) {
            dq[b * L.q.batch + h * L.q.head + i * L.q.row + c] += ds * k[kj + c];
            dk[kj + c] += ds * qi[c];
            dv[vj + c] += p[j] * gi[c];
          }
        }
      }
}

template <class T>
std::vector<T> cast_to(const std::vector<double>& x) {
  return std::vector<T>(x.begin(), x.end());
}

template <class T>
double max_abs_diff(const std::vector<T>& a, const std::vector<double>& b) {
  double m = 0;
  for (std::size_t i = 0; i < a.size(); ++i) m = std::max(m, std::abs(static_cast<double>(a[i]) - b[i]));
  return m;
}

// q | k | v interleaved in one fused [batch * tokens, 3 * heads * head_dim] buffer, as geometry/block.hpp calls it.
struct FusedCase {
  nn::AttentionLayout L;
  std::vector<double> qkv, d_out;
  double scale;
  FusedCase(index_t batch, index_t heads, index_t tokens, index_t head_dim, unsigned seed) {
    const index_t C = heads * head_dim;
    L.batch = batch, L.heads = heads, L.n_q = L.n_kv = tokens, L.head_dim = head_dim;
    L.q = L.k = L.v = {tokens * 3 * C, head_dim, 3 * C};
    L.out = {tokens * C, head_dim, C};
    qkv = random_vector(batch * tokens * 3 * C, seed, 2.0);  // peaked rows: the running max moves between key blocks
    d_out = random_vector(batch * tokens * C, seed + 1);
    scale = 1.0 / std::sqrt(double(head_dim));
  }
  index_t C() const { return L.heads * L.head_dim; }
};

// whole_heads: scratch large enough for the per-(batch, head) copies of K and V.
template <class T>
void run_fused(const FusedCase& c, simd::Lanes lanes, std::vector<T>& out, std::vector<T>& lse, std::vector<T>& d_qkv,
               ThreadPool& pool = global_pool(), bool whole_heads = false) {
  const auto qkv = cast_to<T>(c.qkv), d_out = cast_to<T>(c.d_out);
  const index_t C = c.C();
  out.assign(c.d_out.size(), T(-3));
  lse.assign(c.L.batch * c.L.heads * c.L.n_q, T(0));
  d_qkv.assign(qkv.size(), T(0.25));  // backward adds
  std::vector<T> scratch((whole_heads ? nn::attention_scratch_per_worker(c.L.head_dim, c.L.n_kv)
                                      : nn::attention_scratch_per_worker(c.L.head_dim)) * pool.size());
  const T scale = static_cast<T>(c.scale);
  nn::attention_forward_impl<T>(out.data(), lse.data(), qkv.data(), qkv.data() + C, qkv.data() + 2 * C, c.L, scale,
                                std::span<T>(scratch), lanes, pool);
  nn::attention_backward_impl<T>(d_qkv.data(), d_qkv.data() + C, d_qkv.data() + 2 * C, d_out.data(), out.data(),
                                 lse.data(), qkv.data(), qkv.data() + C, qkv.data() + 2 * C, c.L, scale,
                                 std::span<T>(scratch), lanes, pool);
}
}  // namespace

namespace {
// Fused attention against the dense definition: float with the scalar path and each of `lanes`; with `with_double`,
// double with the scalar and compiled paths.
void check_fused_attention_lanes(const std::vector<simd::Lanes>& lanes, bool with_double) {
  // 520 keys = two full 256-key blocks and a partial one; 300 = one full and a partial one; 2 heads: the one-pass
  // backward on 1 or 2 workers.
  // head_dim 64 (VGGT), 20 (vector tiles plus a lane tail on wide targets), 12 (the small model's decoder) and 5.
  for (index_t head_dim : {64, 20, 12, 5}) {
    CAPTURE(head_dim);
    const index_t tokens = head_dim == 64 ? 520 : 300;
    FusedCase c(1, 2, tokens, head_dim, 31 + unsigned(head_dim));
    const index_t C = c.C();
    std::vector<double> q(c.L.batch * tokens * C), k(q.size()), v(q.size());
    nn::AttentionLayout P = nn::packed_attention_layout(c.L.batch, c.L.heads, tokens, tokens, head_dim);
    for (index_t r = 0; r < c.L.batch * tokens; ++r)
      for (index_t i = 0; i < C; ++i) {
        q[r * C + i] = c.qkv[r * 3 * C + i];
        k[r * C + i] = c.qkv[r * 3 * C + C + i];
        v[r * C + i] = c.qkv[r * 3 * C + 2 * C + i];
      }
    const auto expect_out = naive_attention(q, k, v, P, c.scale);
    std::vector<double> dq(q.size()), dk(q.size()), dv(q.size());
    naive_attention_backward(q, k, v, c.d_out, P, c.scale, dq, dk, dv);
    std::vector<double> expect_grad(c.qkv.size(), 0.25);
    for (index_t r = 0; r < c.L.batch * tokens; ++r)
      for (index_t i = 0; i < C; ++i) {
        expect_grad[r * 3 * C + i] += dq[r * C + i];
        expect_grad[r * 3 * C + C + i] += dk[r * C + i];
        expect_grad[r * 3 * C + 2 * C + i] += dv[r * C + i];
      }

    std::vector<double> out_s, lse_s, g_s, out_v, lse_v, g_v;
    if (with_double) {
      run_fused<double>(c, simd::Lanes::scalar, out_s, lse_s, g_s);
      run_fused<double>(c, simd::Lanes::compiled, out_v, lse_v, g_v, global_pool(), true);
      CHECK(max_abs_diff(out_s, expect_out) < 1e-12);
      CHECK(max_abs_diff(out_v, expect_out) < 1e-12);
      CHECK(max_abs_diff(g_s, expect_grad) < 1e-11);
      CHECK(max_abs_diff(g_v, expect_grad) < 1e-11);
      CHECK(max_abs_diff(lse_v, std::vector<double>(lse_s.begin(), lse_s.end())) < 1e-12);
    }

    // float: scalar and each of `lanes`.
    std::vector<float> out_fs, lse_fs, g_fs;
    run_fused<float>(c, simd::Lanes::scalar, out_fs, lse_fs, g_fs, global_pool(), true);
    CHECK(max_abs_diff(out_fs, expect_out) < 1e-4);
    CHECK(max_abs_diff(g_fs, expect_grad) < 2e-4);
    for (simd::Lanes l : lanes) {
      CAPTURE(simd::lanes_name(l));
      std::vector<float> out_fv, lse_fv, g_fv;
      run_fused<float>(c, l, out_fv, lse_fv, g_fv);
      CHECK(max_abs_diff(out_fv, expect_out) < 1e-4);
      CHECK(max_abs_diff(g_fv, expect_grad) < 2e-4);
      CHECK(max_abs_diff(lse_fv, std::vector<double>(lse_fs.begin(), lse_fs.end())) < 1e-4);
    }
  }
}

void check_fused_attention_dispatch(simd::Lanes lanes) { check_fused_attention_lanes({lanes}, false); }
}  // namespace

TEST_CASE("attention over several key blocks, fused q|k|v rows: scalar and SIMD paths match the dense definition",
          "[nn][attention][simd]") {
  // The build's compiled lanes (float and double); the run-time dispatched ones are the cases below, one per level.
  check_fused_attention_lanes({simd::Lanes::compiled}, true);
}

FLEXSPLAT_DISPATCH_TEST_CASES("attention over several key blocks, fused q|k|v rows: the dispatched lanes match the dense "
                              "definition", "[nn][attention][simd]", check_fused_attention_dispatch)

TEST_CASE("attention over several key blocks: float64 gradient check, 1 and 2 threads bit-identical on every path",
          "[nn][attention]") {
  auto L = nn::packed_attention_layout(1, 1, 70, 270, 3);
  auto q = random_vector(70 * 3, 41, 2.0), k = random_vector(270 * 3, 42, 2.0), v = random_vector(270 * 3, 43);
  std::vector<double> out(q.size()), lse(70), dq(q.size()), dk(k.size()), dv(v.size());
  std::vector<double> scratch(nn::attention_scratch_per_worker(3) * global_pool().size());
  std::span<double> ws(scratch);
  auto result = testing::check_gradients(
      {{"q", q, dq}, {"k", k, dk}, {"v", v, dv}}, out.size(),
      [&](std::span<double> o) { nn::attention_forward(o.data(), lse.data(), q.data(), k.data(), v.data(), L, 0.7, ws); },
      [&](std::span<const double> d) {
        nn::attention_forward(out.data(), lse.data(), q.data(), k.data(), v.data(), L, 0.7, ws);
        nn::attention_backward(dq.data(), dk.data(), dv.data(), d.data(), out.data(), lse.data(), q.data(), k.data(),
                               v.data(), L, 0.7, ws);
      });
  INFO(result.summary());
  CHECK(result.ok());

  FusedCase c(1, 3, 300, 64, 51);
  ThreadPool one(1), two(2);
  std::vector<float> o1, l1, g1, o2, l2, g2;
  std::vector<double> o1d, l1d, g1d, o2d, l2d, g2d;
  run_fused<float>(c, simd::best_lanes<float>(), o1, l1, g1, one);
  run_fused<float>(c, simd::best_lanes<float>(), o2, l2, g2, two);
  CHECK(o1 == o2);
  CHECK(l1 == l2);
  CHECK(g1 == g2);
  run_fused<float>(c, simd::Lanes::scalar, o1, l1, g1, one);
  run_fused<float>(c, simd::Lanes::scalar, o2, l2, g2, two);
  CHECK(o1 == o2);
  CHECK(g1 == g2);
  // Copying whole heads of K and V instead of one key block at a time changes no bit, and neither does the backward
  // schedule: 3 heads on 1 worker run in one pass per head, on 2 workers as key-block then query-block passes.
  run_fused<float>(c, simd::best_lanes<float>(), o1, l1, g1, two, false);
  run_fused<float>(c, simd::best_lanes<float>(), o2, l2, g2, two, true);
  CHECK(o1 == o2);
  CHECK(l1 == l2);
  CHECK(g1 == g2);
  run_fused<float>(c, simd::best_lanes<float>(), o1, l1, g1, one, true);
  CHECK(o1 == o2);
  CHECK(g1 == g2);
  const auto large = [](const FusedCase& f, index_t workers) {
    return static_cast<std::size_t>(nn::attention_scratch_per_worker(f.L.head_dim, f.L.n_kv) * workers);
  };
  const auto small = static_cast<std::size_t>(nn::attention_scratch_per_worker(c.L.head_dim));
  CHECK(nn::attention_backward_one_pass(c.L, large(c, 1), 1));
  CHECK_FALSE(nn::attention_backward_one_pass(c.L, large(c, 2), 2));  // 3 heads do not spread over 2 workers
  CHECK_FALSE(nn::attention_backward_one_pass(c.L, small, 1));        // no room for a head's dQ
  FusedCase even(2, 2, 200, 24, 52);  // 4 heads: one pass on 2 workers too
  CHECK(nn::attention_backward_one_pass(even.L, large(even, 2), 2));
  run_fused<double>(even, simd::Lanes::compiled, o1d, l1d, g1d, two, true);
  run_fused<double>(even, simd::Lanes::compiled, o2d, l2d, g2d, two, false);
  CHECK(o1d == o2d);
  CHECK(g1d == g2d);
  run_fused<double>(even, simd::Lanes::scalar, o1d, l1d, g1d, one, true);
  run_fused<double>(even, simd::Lanes::scalar, o2d, l2d, g2d, two, false);
  CHECK(g1d == g2d);
}

TEST_CASE("attention scratch sizes: whole-head size grows with the key count", "[nn][attention]") {
  CHECK(nn::attention_scratch_per_worker(64, 1000) - nn::attention_scratch_per_worker(64) == 2 * 1000 * 64);
  auto L = nn::packed_attention_layout(1, 1, 3, 2, 2);
  std::vector<double> x(6, 0.5), out(6), lse(3);
  std::vector<double> short_by_one(nn::attention_scratch_per_worker(2) * global_pool().size() - 1);
  CHECK_THROWS_WITH(nn::attention_backward(out.data(), out.data(), out.data(), x.data(), x.data(), lse.data(), x.data(),
                                           x.data(), x.data(), L, 1.0, std::span<double>(short_by_one)),
                    Catch::Contains("attention scratch has"));
}
