#include <catch2/catch.hpp>

#include <cmath>

#include "flexsplat/geometry/block.hpp"
#include "geometry_test_util.hpp"

using namespace flexsplat;
using namespace flexsplat::geometry;

namespace {

struct NaiveParams {
  std::map<std::string, std::vector<double>> t;
  const std::vector<double>& operator[](const std::string& n) const { return t.at(n); }
};

void naive_layernorm(std::vector<double>& v, const double* g, const double* b, double eps) {
  double m = 0, s = 0;
  for (double e : v) m += e;
  m /= v.size();
  for (double e : v) s += (e - m) * (e - m);
  const double r = 1.0 / std::sqrt(s / v.size() + eps);
  for (std::size_t i = 0; i < v.size(); ++i) v[i] = (v[i] - m) * r * g[i] + b[i];
}

// Straight from the module definitions, with the full score matrix.
std::vector<double> naive_block(std::vector<double> x, index_t batch, index_t tokens, const BlockConfig& c,
                                const NaiveParams& p, const std::vector<std::int32_t>* pos) {
  const index_t C = c.dim, H = c.mlp_hidden(), hd = c.head_dim(), nh = c.num_heads;
  auto lin = [](const std::vector<double>& in, const std::vector<double>& W, const std::vector<double>* b, index_t o) {
    const index_t i_n = in.size();
    std::vector<double> out(o);
    for (index_t r = 0; r < o; ++r) {
      double s = b ? (*b)[r] : 0.0;
      for (index_t k = 0; k < i_n; ++k) s += W[r * i_n + k] * in[k];
      out[r] = s;
    }
    return out;
  };
  for (index_t bt = 0; bt < batch; ++bt) {
    std::vector<std::vector<double>> q(tokens), k(tokens), v(tokens);
    for (index_t n = 0; n < tokens; ++n) {
      std::vector<double> h(x.begin() + (bt * tokens + n) * C, x.begin() + (bt * tokens + n + 1) * C);
      naive_layernorm(h, p["norm1.weight"].data(), p["norm1.bias"].data(), c.norm_eps);
      auto qkv = lin(h, p["attn.qkv.weight"], &p["attn.qkv.bias"], 3 * C);
      q[n].assign(qkv.begin(), qkv.begin() + C);
      k[n].assign(qkv.begin() + C, qkv.begin() + 2 * C);
      v[n].assign(qkv.begin() + 2 * C, qkv.end());
      for (index_t hh = 0; hh < nh; ++hh) {
        std::vector<double> qh(q[n].begin() + hh * hd, q[n].begin() + (hh + 1) * hd);
        std::vector<double> kh(k[n].begin() + hh * hd, k[n].begin() + (hh + 1) * hd);
        if (c.qk_norm) {
          naive_layernorm(qh, p["attn.q_norm.weight"].data(), p["attn.q_norm.bias"].data(), c.qk_norm_eps);
          naive_layernorm(kh, p["attn.k_norm.weight"].data(), p["attn.k_norm.bias"].data(), c.qk_norm_eps);
        }
        if (pos) {
          const index_t half = hd / 2, qq = half / 2;
          auto rot = [&](std::vector<double>& t) {
            std::vector<double> o(hd);
            for (index_t d = 0; d < hd; ++d) {
              const index_t axis = d / half, local = d % half, j = local % qq;
              const int ps = (*pos)[2 * (bt * tokens + n) + axis];
              const double ang = ps / std::pow(100.0, 2.0 * j / half);
              const double partner = local < qq ? -t[axis * half + local + qq] : t[axis * half + local - qq];
              o[d] = t[d] * std::cos(ang) + partner * std::sin(ang);
            }
            t = o;
          };
          rot(qh);
          rot(kh);
        }
        std::copy(qh.begin(), qh.end(), q[n].begin() + hh * hd);
        std::copy(kh.begin(), kh.end(), k[n].begin() + hh * hd);
      }
    }
    std::vector<std::vector<double>> attn(tokens, std::vector<double>(C));
    for (index_t hh = 0; hh < nh; ++hh)
      for (index_t i = 0; i < tokens; ++i) {
        std::vector<double> s(tokens);
        double mx = -1e300;
        for (index_t j = 0; j < tokens; ++j) {
          double d = 0;
          for (index_t e = 0; e < hd; ++e) d += q[i][hh * hd + e] * k[j][hh * hd + e];
          s[j] = d / std::sqrt(double(hd));
          mx = std::max(mx, s[j]);
        }
        double z = 0;
        for (auto& e : s) z += (e = std::exp(e - mx));
        for (index_t j = 0; j < tokens; ++j)
          for (index_t e = 0; e < hd; ++e) attn[i][hh * hd + e] += s[j] / z * v[j][hh * hd + e];
      }
    for (index_t n = 0; n < tokens; ++n) {
      double* xr = x.data() + (bt * tokens + n) * C;
      auto pr = lin(attn[n], p["attn.proj.weight"], &p["attn.proj.bias"], C);
      for (index_t i = 0; i < C; ++i) xr[i] += p["ls1.gamma"][i] * pr[i];
      std::vector<double> h(xr, xr + C);
      naive_layernorm(h, p["norm2.weight"].data(), p["norm2.bias"].data(), c.norm_eps);
      auto f1 = lin(h, p["mlp.fc1.weight"], &p["mlp.fc1.bias"], H);
      for (auto& e : f1) e = 0.5 * e * (1.0 + std::erf(e / std::sqrt(2.0)));
      auto f2 = lin(f1, p["mlp.fc2.weight"], &p["mlp.fc2.bias"], C);
      for (index_t i = 0; i < C; ++i) xr[i] += p["ls2.gamma"][i] * f2[i];
    }
  }
  return x;
}

template <class T>
void fill_source(io::ParamSource<T>& src, NaiveParams& naive, const BlockConfig& c, unsigned seed) {
  std::vector<io::TensorSpec> specs;
  append_block_specs(specs, "blk.", c);
  for (auto& s : specs) {
    index_t n = 1;
    for (auto e : s.shape) n *= e;
    const bool is_norm_weight = s.name.find("norm") != std::string::npos && s.name.find("weight") != std::string::npos;
    auto v = random_doubles(n, seed++, s.shape.size() == 2 ? 0.3 : 0.5);
    if (is_norm_weight)
      for (auto& e : v) e += 1.0;
    naive.t[s.name.substr(4)] = v;
    src.add(s.name, s.shape, std::vector<T>(v.begin(), v.end()));
  }
}

}  // namespace

TEST_CASE("block forward matches a naive float64 transformer block (qk-norm, RoPE, LayerScale)", "[geometry][block]") {
  BlockConfig c;
  c.dim = 16;
  c.num_heads = 2;
  c.qk_norm = GENERATE(false, true);
  const bool use_rope = GENERATE(false, true);
  // 150 tokens spans two key blocks and three query blocks of the tiled attention.
  const index_t batch = 2, tokens = 150;
  io::ParamSource<double> src;
  io::ParamSource<float> srcf;
  NaiveParams naive, unused;
  fill_source(src, naive, c, 100);
  fill_source(srcf, unused, c, 100);
  auto x = random_doubles(batch * tokens * c.dim, 7);
  std::vector<std::int32_t> pos(batch * tokens * 2);
  for (index_t r = 0; r < batch * tokens; ++r) {
    const index_t n = r % tokens;
    pos[2 * r] = n < 5 ? 0 : 1 + (n - 5) / 12;
    pos[2 * r + 1] = n < 5 ? 0 : 1 + (n - 5) % 12;
  }
  const auto expected = naive_block(x, batch, tokens, c, naive, use_rope ? &pos : nullptr);

  const auto table = rope2d_table<double>(c.head_dim(), 20, 100.0);
  const auto tablef = rope2d_table<float>(c.head_dim(), 20, 100.0);
  BlockWorkspace<double> ws;
  auto got = x;
  block_forward(got.data(), batch, tokens, c, load_block_weights(src, "blk.", c), use_rope ? &table : nullptr,
                use_rope ? pos.data() : nullptr, ws.get(c, batch * tokens));
  double max_err = 0, max_abs = 0;
  for (std::size_t i = 0; i < x.size(); ++i) {
    max_err = std::max(max_err, std::abs(got[i] - expected[i]));
    max_abs = std::max(max_abs, std::abs(expected[i]));
  }
  CHECK(max_err <= 1e-10 * max_abs);

  std::vector<float> xf(x.begin(), x.end());
  BlockWorkspace<float> wsf;
  block_forward(xf.data(), batch, tokens, c, load_block_weights(srcf, "blk.", c), use_rope ? &tablef : nullptr,
                use_rope ? pos.data() : nullptr, wsf.get(c, batch * tokens));
  double max_err_f = 0;
  for (std::size_t i = 0; i < x.size(); ++i) max_err_f = std::max(max_err_f, std::abs(double(xf[i]) - expected[i]));
  CHECK(max_err_f <= 1e-5 * max_abs);
}

TEST_CASE("block weights: a mis-shaped or missing tensor is named", "[geometry][block]") {
  BlockConfig c;
  c.dim = 8;
  c.num_heads = 2;
  io::ParamSource<float> src;
  NaiveParams naive;
  fill_source(src, naive, c, 1);
  CHECK_THROWS_WITH(load_block_weights(src, "other.", c), Catch::Contains("other.norm1.weight"));
  c.qk_norm = true;
  CHECK_THROWS_WITH(load_block_weights(src, "blk.", c), Catch::Contains("blk.attn.q_norm.weight"));
  c.qk_norm = false;
  c.mlp_ratio = 2.0;
  CHECK_THROWS_WITH(load_block_weights(src, "blk.", c), Catch::Contains("blk.mlp.fc1.weight' has shape [32, 8], expected [16, 8]"));
  c.num_heads = 3;
  CHECK_THROWS_WITH(load_block_weights(src, "blk.", c), Catch::Contains("num_heads 3"));
}

TEST_CASE("block forward refuses a short workspace", "[geometry][block]") {
  BlockConfig c;
  c.dim = 8;
  c.num_heads = 2;
  io::ParamSource<float> src;
  NaiveParams naive;
  fill_source(src, naive, c, 1);
  std::vector<float> x(3 * 8), ws(10);
  CHECK_THROWS_WITH(block_forward<float>(x.data(), 1, 3, c, load_block_weights(src, "blk.", c), nullptr, nullptr, ws),
                    Catch::Contains("workspace"));
}
