#include <catch2/catch.hpp>

#include <cmath>

#include "decoder_test_util.hpp"
#include "flexsplat/decoder/self_attention.hpp"
#include "flexsplat/testing/gradcheck.hpp"

using namespace flexsplat;

namespace {
// softmax(q k^T / sqrt(d)) v per head over the given query set, written out.
std::vector<double> naive_attention(const std::vector<double>& qkv, index_t n, index_t dim, index_t heads,
                                    const std::vector<index_t>& members) {
  const index_t hd = dim / heads;
  std::vector<double> out(n * dim, 0.0);
  for (index_t i : members)
    for (index_t h = 0; h < heads; ++h) {
      std::vector<double> s;
      double mx = -INFINITY;
      for (index_t j : members) {
        double dot = 0;
        for (index_t d = 0; d < hd; ++d) dot += qkv[i * 3 * dim + h * hd + d] * qkv[j * 3 * dim + dim + h * hd + d];
        s.push_back(dot / std::sqrt(double(hd)));
        mx = std::max(mx, s.back());
      }
      double sum = 0;
      for (double& x : s) sum += (x = std::exp(x - mx));
      for (std::size_t jj = 0; jj < members.size(); ++jj)
        for (index_t d = 0; d < hd; ++d)
          out[i * dim + h * hd + d] += s[jj] / sum * qkv[members[jj] * 3 * dim + 2 * dim + h * hd + d];
    }
  return out;
}
}  // namespace

TEST_CASE("full and local self-attention match the written-out definition", "[decoder][self_attention]") {
  const index_t n = 11, dim = 8, heads = 2;
  auto x = random_normal(n * dim, 51), centres = random_normal(n * 3, 52);
  for (bool local : {false, true}) {
    decoder::SelfAttentionConfig c{dim, heads, local, 4};
    auto params = random_normal(decoder::SelfAttentionParamLayout(c).size, 53, 0.4);
    const decoder::SelfAttentionParamLayout P(c);
    // With the identity output projection the module output is the attention output itself.
    std::fill(params.begin() + P.out_w, params.end(), 0.0);
    for (index_t i = 0; i < dim; ++i) params[P.out_w + i * dim + i] = 1.0;
    decoder::SelfAttentionCache<double> cache;
    std::vector<double> out(n * dim), qkv(n * 3 * dim);
    decoder::self_attention_forward(out.data(), cache, x.data(), centres.data(), n, params.data(), c);
    nn::linear_forward(qkv.data(), x.data(), params.data() + P.qkv_w, params.data() + P.qkv_b, n, dim, 3 * dim);
    std::vector<double> expect(n * dim, 0.0);
    if (!local) {
      std::vector<index_t> all(n);
      for (index_t i = 0; i < n; ++i) all[i] = i;
      expect = naive_attention(qkv, n, dim, heads, all);
    } else {
      std::vector<index_t> order;
      decoder::morton_order(order, centres.data(), n);
      for (index_t w0 = 0; w0 < n; w0 += 4) {
        std::vector<index_t> members(order.begin() + w0, order.begin() + std::min(n, w0 + 4));
        auto part = naive_attention(qkv, n, dim, heads, members);
        for (index_t i : members)
          for (index_t d = 0; d < dim; ++d) expect[i * dim + d] = part[i * dim + d];
      }
    }
    for (index_t i = 0; i < n * dim; ++i) REQUIRE(out[i] == Approx(expect[i]).margin(1e-12));
  }
}

TEST_CASE("full and local self-attention pass the float64 gradient check", "[decoder][self_attention]") {
  const index_t n = 10, dim = 8, heads = 2;
  auto x = random_normal(n * dim, 54), centres = random_normal(n * 3, 55);
  for (bool local : {false, true}) {
    decoder::SelfAttentionConfig c{dim, heads, local, 4};
    auto params = random_normal(decoder::SelfAttentionParamLayout(c).size, 56, 0.4);
    decoder::SelfAttentionCache<double> cache;
    std::vector<double> dx(x.size()), dp(params.size());
    const decoder::SelfAttentionParamLayout L(c);
    auto tensors = testing::split_flat(params, dp,
                                       {{"qkv.weight", std::size_t(L.qkv_b - L.qkv_w)},
                                        {"qkv.bias", std::size_t(L.out_w - L.qkv_b)},
                                        {"proj.weight", std::size_t(L.out_b - L.out_w)},
                                        {"proj.bias", std::size_t(L.size - L.out_b)}});
    tensors.push_back({"x", x, dx});
    auto result = testing::check_gradients(
        tensors, n * dim,
        [&](std::span<double> o) {
          decoder::self_attention_forward(o.data(), cache, x.data(), centres.data(), n, params.data(), c);
        },
        [&](std::span<const double> g) {
          decoder::self_attention_backward(dx.data(), dp.data(), g.data(), cache, x.data(), params.data(), c);
        },
        {1e-6, 1e-7, 1e-5, 40});
    INFO((local ? "local: " : "full: ") << result.summary());
    CHECK(result.ok());
  }
}

TEST_CASE("Morton order survives non-finite and identical centres", "[decoder][self_attention]") {
  std::vector<double> centres{0, 0, 0, 0, 0, 0, NAN, INFINITY, 1, 0, 0, 0};
  std::vector<index_t> order;
  decoder::morton_order(order, centres.data(), 4);
  std::vector<index_t> sorted = order;
  std::sort(sorted.begin(), sorted.end());
  CHECK(sorted == std::vector<index_t>{0, 1, 2, 3});
}
