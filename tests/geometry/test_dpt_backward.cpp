// DPT head backward: float64 gradient checks of the banded convolution and of the whole head (every parameter, the
// aggregator tokens, through depth, confidence and both exposed feature maps), the += contract, zero gradient for
// the special tokens, and the training forward equal to the inference forward bit for bit.
#include <catch2/catch.hpp>

#include <cstring>
#include <random>

#include "flexsplat/geometry/dpt_head.hpp"
#include "flexsplat/testing/gradcheck.hpp"
#include "heads_backward_util.hpp"

using namespace flexsplat;
using namespace flexsplat::geometry;

namespace dpt_backward_test {

std::vector<double> dpt_normal_values(std::size_t n, unsigned seed, double scale = 1.0) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> normal(0.0, scale);
  std::vector<double> v(n);
  for (auto& x : v) x = normal(rng);
  return v;
}

DptHeadConfig dpt_tiny_config() {
  DptHeadConfig c;
  c.dim_in = 8;
  c.patch_size = 4;
  c.features = 8;  // head features 4
  c.out_channels = {4, 4, 8, 4};
  c.intermediate_layer_idx = {0, 2, 1, 2};  // layer 2 feeds two levels: its gradients add up
  return c;
}

// One head on a flat parameter block and a token tensor of `layers_n` layers, run in T.
template <class T>
struct DptRig {
  DptHeadConfig cfg;
  index_t S, H, W, patch_start, layers_n, ph, pw, tokens, full, fused_hw;
  std::vector<T> params, tok, ws;
  DptHeadWeights<T> w;

  DptRig(const DptHeadConfig& c, const heads_backward_test::FlatParams& flat, const std::vector<double>& tokens_in,
         index_t S_, index_t H_, index_t W_, index_t start, index_t n_layers)
      : cfg(c), S(S_), H(H_), W(W_), patch_start(start), layers_n(n_layers) {
    ph = H / c.patch_size, pw = W / c.patch_size, tokens = start + ph * pw;
    full = ph * c.patch_size * pw * c.patch_size;
    fused_hw = 64 * ph * pw;
    params.assign(flat.values.begin(), flat.values.end());
    tok.assign(tokens_in.begin(), tokens_in.end());
    w = bind_dpt_head_weights<T>(c, [&](const std::string& name, const std::vector<index_t>& shape) {
      return params.data() + (flat.get(name, shape) - flat.values.data());
    });
    ws.resize(static_cast<std::size_t>(dpt_head_workspace_size(c, ph, pw)));
  }
  std::vector<const T*> layers() const {
    std::vector<const T*> l;
    for (index_t i = 0; i < layers_n; ++i) l.push_back(tok.data() + i * S * tokens * cfg.dim_in);
    return l;
  }
  std::size_t out_size() const {
    const index_t Fh = cfg.head_features();
    return static_cast<std::size_t>(S * (full * (cfg.output_dim - 1) + full + Fh * full + Fh * fused_hw));
  }
  // preds | conf | features | fused_features, concatenated.
  DptHeadOutputs<T> outputs(T* o) const {
    const index_t Fh = cfg.head_features(), np = cfg.output_dim - 1;
    return {o, o + S * full * np, o + S * full * (np + 1), o + S * full * (np + 1 + Fh)};
  }
};

// Elements the cache's activations hold (grad_ws aside): what dpt_head_cache_elements counts.
template <class T>
index_t cache_held(const DptHeadCache<T>& c) {
  std::size_t held = c.ln_mean.size() + c.ln_rstd.size() + c.fused.size() + c.up.size() + c.image.size() +
                     c.image_act.size() + c.hidden.size() + c.logits.size();
  for (int i = 0; i < 4; ++i)
    held += c.proj[i].size() + c.level[i].size() + c.unit1_r[i].size() + c.unit1_u[i].size() + c.unit2_r[i].size() +
            c.unit2_u[i].size() + c.block_out[i].size();
  return static_cast<index_t>(held);
}

void check_dpt_gradients(const DptHeadConfig& cfg, index_t S, index_t H, index_t W, index_t patch_start,
                         index_t layers_n, std::size_t max_checks) {
  std::vector<io::TensorSpec> specs;
  append_dpt_head_specs(specs, cfg, "");
  // Weight seed 12: with 11 one ReLU input of refinenet1 sits within the 1e-6 step of its kink (central differences
  // across it disagree with the one-sided derivative; a 1e-9 step agrees), which is the checker's limit, not a bug.
  heads_backward_test::FlatParams flat(specs, 12);
  const index_t ph = H / cfg.patch_size, pw = W / cfg.patch_size, tokens = patch_start + ph * pw;
  DptRig<double> rig(cfg, flat, dpt_normal_values(layers_n * S * tokens * cfg.dim_in, 12), S, H, W, patch_start,
                     layers_n);
  // The gradient checker perturbs flat.values: the rig must read them, so bind it to flat's block directly.
  rig.w = bind_dpt_head_weights<double>(cfg, [&](const std::string& n, const std::vector<index_t>& s) { return flat.get(n, s); });
  std::vector<double> d_tok(rig.tok.size());
  // The image the head reads when cfg.image_channels > 0 (at the output grid: whole patches).
  std::vector<double> image = dpt_normal_values(S * cfg.image_channels * rig.full, 13), d_image(image.size());
  const double* pixels = cfg.image_channels > 0 ? image.data() : nullptr;
  DptHeadCache<double> cache;
  const auto grads = dpt_head_grads(rig.w, flat.values.data(), flat.grads.data());
  auto params = flat.grad_params();
  params.push_back({"tokens", std::span<double>(rig.tok), std::span<double>(d_tok)});
  if (pixels) params.push_back({"image", std::span<double>(image), std::span<double>(d_image)});
  testing::GradCheckOptions opt;
  opt.max_checks_per_param = max_checks;
  const auto result = testing::check_gradients(
      params, rig.out_size(),
      [&](std::span<double> out) {
        const auto layers = rig.layers();
        dpt_head_forward_train<double>(rig.outputs(out.data()), cache, cfg, rig.w, layers, S, rig.tokens, patch_start,
                                       H, W, rig.ws, pixels);
      },
      [&](std::span<const double> d) {
        const auto layers = rig.layers();
        std::vector<double*> d_layers;
        for (index_t i = 0; i < layers_n; ++i) d_layers.push_back(d_tok.data() + i * S * rig.tokens * cfg.dim_in);
        const auto o = rig.outputs(const_cast<double*>(d.data()));
        dpt_head_backward<double>(d_layers, grads, {o.preds, o.conf, o.features, o.fused_features}, cache, cfg, rig.w,
                                  layers, pixels ? d_image.data() : nullptr);
      },
      opt);
  INFO(result.summary());
  CHECK(result.ok());
}

}  // namespace dpt_backward_test

using namespace dpt_backward_test;

TEST_CASE("DPT banded convolution backward matches finite differences", "[dpt_head][backward]") {
  for (index_t k : {1, 3}) {
    const index_t cin = 3, cout = 2, h = 5, w = 4;
    auto in = dpt_normal_values(cin * h * w, 1), weight = dpt_normal_values(cout * cin * k * k, 2), bias = dpt_normal_values(cout, 3);
    std::vector<double> d_in(in.size()), d_weight(weight.size()), d_bias(bias.size());
    std::vector<double> scratch(cin * k * k * w * 2);  // two rows per band: three bands
    const auto result = testing::check_gradients(
        {{"in", in, d_in}, {"weight", weight, d_weight}, {"bias", bias, d_bias}}, cout * h * w,
        [&](std::span<double> out) {
          geometry::detail::conv2d_same(out.data(), in.data(), weight.data(), bias.data(), cin, cout, h, w, k,
                                        std::span<double>(scratch));
        },
        [&](std::span<const double> d) {
          geometry::detail::conv2d_same_backward(d_in.data(), d_weight.data(), d_bias.data(), d.data(), in.data(),
                                                 weight.data(), cin, cout, h, w, k, std::span<double>(scratch));
        });
    INFO("k = " << k << ": " << result.summary());
    CHECK(result.ok());
  }
}

TEST_CASE("DPT head backward matches finite differences with exp depth and 1 + exp confidence", "[dpt_head][backward]") {
  // 2 x 2 patch grid of 2-pixel patches: pyramid 8x8, 4x4, 2x2, 1x1; fused 16x16; output 4x4.
  DptHeadConfig cfg = dpt_tiny_config();
  cfg.patch_size = 2;
  check_dpt_gradients(cfg, 2, 4, 4, 2, 3, 8);
}

TEST_CASE("DPT head backward matches finite differences with inv_log and sigmoid on an odd grid", "[dpt_head][backward]") {
  DptHeadConfig cfg = dpt_tiny_config();
  cfg.output_dim = 3;
  cfg.activation = DptActivation::inv_log;
  cfg.conf_activation = DptConfActivation::sigmoid;
  cfg.pos_embed = false;
  cfg.patch_size = 2;
  check_dpt_gradients(cfg, 1, 7, 3, 1, 3, 6);  // 3 x 1 grid, image not a multiple of the patch
}

TEST_CASE("DPT head backward matches finite differences when the image joins, raw or through its convolutions",
          "[dpt_head][backward]") {
  DptHeadConfig cfg = dpt_tiny_config();
  cfg.output_dim = 4;
  cfg.activation = DptActivation::linear;
  cfg.conf_activation = DptConfActivation::sigmoid;
  cfg.patch_size = 2;
  cfg.image_channels = 3;
  cfg.image_convs = GENERATE(0, 1, 3);
  cfg.image_width = 5;
  INFO("image_convs " << cfg.image_convs);
  std::vector<io::TensorSpec> specs;
  append_dpt_head_specs(specs, cfg, "");
  index_t image_conv_tensors = 0;
  for (const auto& s : specs) image_conv_tensors += s.name.rfind("scratch.image_conv.", 0) == 0;
  CHECK(image_conv_tensors == 2 * cfg.image_convs);
  // Training forward = inference forward bit for bit, and the cache holds what dpt_head_cache_elements counts.
  heads_backward_test::FlatParams flat(specs, 14);
  const index_t S = 2, H = 6, W = 4, start = 1, layers_n = 3;  // 3 x 2 grid of 2-pixel patches
  DptRig<double> rig(cfg, flat, dpt_normal_values(layers_n * S * (start + 6) * cfg.dim_in, 15), S, H, W, start,
                     layers_n);
  const auto image = dpt_normal_values(S * 3 * rig.full, 16);
  const auto layers = rig.layers();
  std::vector<double> a(rig.out_size(), 1.0), b(rig.out_size(), 2.0);
  dpt_head_forward<double>(rig.outputs(a.data()), cfg, rig.w, layers, S, rig.tokens, start, H, W, rig.ws, image.data());
  DptHeadCache<double> cache;
  dpt_head_forward_train<double>(rig.outputs(b.data()), cache, cfg, rig.w, layers, S, rig.tokens, start, H, W, rig.ws,
                                 image.data());
  CHECK(a == b);
  CHECK(cache_held(cache) == dpt_head_cache_elements(cfg, rig.ph, rig.pw, S));
  CHECK(cache.image_act.size() == static_cast<std::size_t>(S * cfg.image_convs * cfg.image_width * rig.full));
  check_dpt_gradients(cfg, 2, 4, 6, 1, 3, 6);
}

TEST_CASE("DPT head backward: no gradient for special tokens or unused layers", "[dpt_head][backward]") {
  const DptHeadConfig cfg = dpt_tiny_config();
  std::vector<io::TensorSpec> specs;
  append_dpt_head_specs(specs, cfg, "");
  heads_backward_test::FlatParams flat(specs, 21);
  const index_t S = 2, H = 8, W = 12, start = 3, layers_n = 4;
  DptRig<double> rig(cfg, flat, dpt_normal_values(layers_n * S * (start + 6) * cfg.dim_in, 22), S, H, W, start, layers_n);
  std::vector<double> out(rig.out_size()), d_tok(rig.tok.size(), 0.0);
  DptHeadCache<double> cache;
  const auto layers = rig.layers();
  dpt_head_forward_train<double>(rig.outputs(out.data()), cache, cfg, rig.w, layers, S, rig.tokens, start, H, W, rig.ws);
  const auto d_out = dpt_normal_values(out.size(), 23);
  std::vector<double*> d_layers;
  for (index_t i = 0; i < layers_n; ++i) d_layers.push_back(d_tok.data() + i * S * rig.tokens * cfg.dim_in);
  const auto o = rig.outputs(const_cast<double*>(d_out.data()));
  dpt_head_backward<double>(d_layers, DptHeadGrads<double>{}, {o.preds, o.conf, nullptr, nullptr}, cache, cfg, rig.w,
                            layers);
  const index_t D = cfg.dim_in;
  for (index_t l = 0; l < layers_n; ++l)
    for (index_t s = 0; s < S; ++s)
      for (index_t t = 0; t < rig.tokens; ++t) {
        double norm = 0;
        for (index_t c = 0; c < D; ++c) norm += std::abs(d_tok[((l * S + s) * rig.tokens + t) * D + c]);
        INFO("layer " << l << " frame " << s << " token " << t);
        if (t < start || l == 3) CHECK(norm == 0.0);  // special token, or a layer the head does not read
        else CHECK(norm > 0.0);
      }
}

TEST_CASE("DPT head training forward equals the inference forward bit for bit", "[dpt_head][backward]") {
  DptHeadConfig cfg = dpt_tiny_config();
  cfg.features = 16;
  cfg.out_channels = {8, 8, 16, 8};
  std::vector<io::TensorSpec> specs;
  append_dpt_head_specs(specs, cfg, "");
  heads_backward_test::FlatParams flat(specs, 31);
  const index_t S = 3, H = 21, W = 17, start = 5, layers_n = 3;  // 5 x 4 grid
  DptRig<float> rig(cfg, flat, dpt_normal_values(layers_n * S * (start + 20) * cfg.dim_in, 32), S, H, W, start, layers_n);
  const auto layers = rig.layers();
  std::vector<float> a(rig.out_size(), 1.f), b(rig.out_size(), 2.f);
  dpt_head_forward<float>(rig.outputs(a.data()), cfg, rig.w, layers, S, rig.tokens, start, H, W, rig.ws);
  DptHeadCache<float> cache;
  dpt_head_forward_train<float>(rig.outputs(b.data()), cache, cfg, rig.w, layers, S, rig.tokens, start, H, W, rig.ws);
  CHECK(std::memcmp(a.data(), b.data(), a.size() * sizeof(float)) == 0);
  // The cached depth features are the exposed ones.
  const index_t Fh = cfg.head_features();
  const auto o = rig.outputs(b.data());
  CHECK(std::equal(cache.up.begin(), cache.up.end(), o.features, o.features + S * Fh * rig.full));
  CHECK(cache_held(cache) == dpt_head_cache_elements(cfg, rig.ph, rig.pw, S));
}

TEST_CASE("DPT head backward rejects an empty or mismatched cache", "[dpt_head][backward]") {
  const DptHeadConfig cfg = dpt_tiny_config();
  std::vector<io::TensorSpec> specs;
  append_dpt_head_specs(specs, cfg, "");
  heads_backward_test::FlatParams flat(specs, 41);
  DptRig<double> rig(cfg, flat, dpt_normal_values(3 * (2 + 6) * cfg.dim_in, 42), 1, 8, 12, 2, 3);
  const auto layers = rig.layers();
  DptHeadCache<double> cache;
  CHECK_THROWS_WITH(dpt_head_backward<double>({}, DptHeadGrads<double>{}, {}, cache, cfg, rig.w, layers),
                    Catch::Contains("cache is empty"));
  std::vector<double> out(rig.out_size());
  dpt_head_forward_train<double>(rig.outputs(out.data()), cache, cfg, rig.w, layers, 1, rig.tokens, 2, 8, 12, rig.ws);
  DptHeadConfig other = cfg;
  other.features = 16;
  CHECK_THROWS_WITH(dpt_head_backward<double>({}, DptHeadGrads<double>{}, {}, cache, other, rig.w, layers),
                    Catch::Contains("another configuration"));
}
