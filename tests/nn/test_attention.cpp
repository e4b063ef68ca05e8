#include <catch2/catch.hpp>

#include <cmath>

#include "flexsplat/nn/attention.hpp"
#include "flexsplat/testing/gradcheck.hpp"
#include "nn_test_util.hpp"

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
  // 70 queries and 150 keys straddle the 64 / 128 tile sizes.
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

TEST_CASE("attention with no keys gives zeros, not NaN; short scratch is a clear error", "[nn][attention]") {
  auto L = nn::packed_attention_layout(1, 1, 3, 0, 2);
  std::vector<double> q(6, 1.0), out(6, 7.0), lse(3);
  std::vector<double> scratch(nn::attention_scratch_per_worker(2) * global_pool().size());
  nn::attention_forward(out.data(), lse.data(), q.data(), q.data(), q.data(), L, 1.0, std::span<double>(scratch));
  for (double o : out) CHECK(o == 0.0);
  std::vector<double> tiny(3);
  CHECK_THROWS_WITH(nn::attention_forward(out.data(), lse.data(), q.data(), q.data(), q.data(), L, 1.0, std::span<double>(tiny)),
                    Catch::Contains("attention scratch has 3 elements"));
}
