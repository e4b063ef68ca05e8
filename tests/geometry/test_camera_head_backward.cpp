// Camera head backward: float64 gradient check of every weight and the camera tokens with the fed-back encodings
// held fixed (VGGT detaches them), the += contract, the stop-gradient itself, and the training forward equal to the
// inference forward bit for bit (with and without recomputed trunk blocks).
#include <catch2/catch.hpp>

#include <cstring>
#include <random>

#include "flexsplat/geometry/camera_head.hpp"
#include "flexsplat/testing/gradcheck.hpp"
#include "heads_backward_util.hpp"

using namespace flexsplat;
using namespace flexsplat::geometry;

namespace camera_backward_test {

CameraHeadConfig camera_tiny_config() {
  CameraHeadConfig c;
  c.dim = 8;
  c.num_heads = 2;
  c.trunk_depth = 2;
  c.mlp_ratio = 2.0;
  c.iterations = 3;
  return c;
}

std::vector<double> camera_normal_values(std::size_t n, unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> normal;
  std::vector<double> v(n);
  for (auto& x : v) x = normal(rng);
  return v;
}

// Weights bound as views into a flat block (as the training store does), so gradients rebase into flat.grads.
template <class T>
CameraHeadWeights<T> bind_views(io::ParamSource<T>& src, const std::vector<io::TensorSpec>& specs, const T* base,
                                const std::vector<std::size_t>& offsets, const CameraHeadConfig& c) {
  for (std::size_t i = 0; i < specs.size(); ++i) src.add_view(specs[i].name, specs[i].shape, base + offsets[i]);
  return load_camera_head_weights(src, c, "");
}

}  // namespace camera_backward_test

using namespace camera_backward_test;

TEST_CASE("camera head backward matches finite differences with the fed-back encoding held fixed", "[camera_head][backward]") {
  for (PoseActivation fl : {PoseActivation::relu, PoseActivation::exp}) {
    CameraHeadConfig cfg = camera_tiny_config();
    cfg.fl_act = fl;
    cfg.trans_act = PoseActivation::inv_log;
    std::vector<io::TensorSpec> specs;
    append_camera_head_specs(specs, cfg, "");
    heads_backward_test::FlatParams flat(specs, 51);
    io::ParamSource<double> src;
    const auto w = bind_views(src, specs, flat.values.data(), flat.offsets, cfg);
    const index_t S = 3, tokens = 4, C = cfg.dim, I = cfg.iterations;
    auto input = camera_normal_values(S * tokens * C, 52);
    std::vector<double> d_input(input.size());
    std::vector<double> ws(static_cast<std::size_t>(camera_head_workspace_size(cfg, S)));
    CameraHeadCache<double> cache;
    std::vector<double> enc(I * S * 9);
    camera_head_forward_train<double>(enc.data(), cache, cfg, w, input.data(), S, tokens, ws);
    // The detached inputs of iterations 1.. at the unperturbed point: constants of the differentiated function.
    const std::vector<double> feedback(cache.raw.begin(), cache.raw.end() - S * 9);
    const auto grads = camera_head_grads(w, flat.values.data(), flat.grads.data());
    auto params = flat.grad_params();
    params.push_back({"camera tokens", std::span<double>(input), std::span<double>(d_input)});
    testing::GradCheckOptions opt;
    opt.max_checks_per_param = 8;
    // The objective sums 81 outputs up to ~20 (exp / inv_log activations): at the default 1e-6 step its float64
    // rounding (~1e-16 |objective| / step) reaches the 1e-7 absolute tolerance; 1e-5 keeps truncation far below it.
    opt.step = 1e-5;
    const auto result = testing::check_gradients(
        params, enc.size(),
        [&](std::span<double> out) {
          camera_head_forward_train<double>(out.data(), cache, cfg, w, input.data(), S, tokens, ws, false,
                                            feedback.data());
        },
        [&](std::span<const double> d) {
          camera_head_backward<double>(d_input.data(), grads, d.data(), cache, cfg, w, tokens);
        },
        opt);
    INFO(result.summary());
    CHECK(result.ok());
    // Only the camera token (token 0) of each frame receives gradient.
    std::vector<double> d_tok(input.size(), 0.0);
    const auto d_enc = camera_normal_values(enc.size(), 53);
    camera_head_backward<double>(d_tok.data(), CameraHeadGrads<double>{}, d_enc.data(), cache, cfg, w, tokens);
    for (index_t s = 0; s < S; ++s)
      for (index_t t = 0; t < tokens; ++t) {
        double norm = 0;
        for (index_t i = 0; i < C; ++i) norm += std::abs(d_tok[(s * tokens + t) * C + i]);
        CHECK((t == 0 ? norm > 0 : norm == 0));
      }
  }
}

TEST_CASE("camera head backward stops the gradient at the fed-back encoding", "[camera_head][backward]") {
  // The analytic gradient of the last iteration's output equals the difference quotient with the fed-back encodings
  // held fixed, and differs from the undetached one (so the check above could not pass without the detach).
  const CameraHeadConfig cfg = camera_tiny_config();
  std::vector<io::TensorSpec> specs;
  append_camera_head_specs(specs, cfg, "");
  heads_backward_test::FlatParams flat(specs, 61);
  io::ParamSource<double> src;
  const auto w = bind_views(src, specs, flat.values.data(), flat.offsets, cfg);
  const index_t S = 2, tokens = 2, C = cfg.dim, I = cfg.iterations;
  auto input = camera_normal_values(S * tokens * C, 62);
  std::vector<double> ws(static_cast<std::size_t>(camera_head_workspace_size(cfg, S))), enc(I * S * 9), plus(enc.size()),
      minus(enc.size());
  CameraHeadCache<double> cache;
  camera_head_forward_train<double>(enc.data(), cache, cfg, w, input.data(), S, tokens, ws);
  std::vector<double> d_enc(enc.size(), 0.0);
  d_enc[(I - 1) * S * 9 + 0] = 1.0;  // translation x of frame 0 after the last iteration
  std::vector<double> d_input(input.size(), 0.0);
  camera_head_backward<double>(d_input.data(), CameraHeadGrads<double>{}, d_enc.data(), cache, cfg, w, tokens);
  // Undetached central difference of the same output with respect to frame 0's camera token entry 0.
  const double h = 1e-6, saved = input[0];
  input[0] = saved + h;
  camera_head_forward<double>(plus.data(), cfg, w, input.data(), S, tokens, ws);
  input[0] = saved - h;
  camera_head_forward<double>(minus.data(), cfg, w, input.data(), S, tokens, ws);
  input[0] = saved;
  const double undetached = (plus[(I - 1) * S * 9] - minus[(I - 1) * S * 9]) / (2 * h);
  // Detached central difference: the fed-back encodings fixed at their unperturbed values.
  const std::vector<double> feedback(cache.raw.begin(), cache.raw.end() - S * 9);
  input[0] = saved + h;
  camera_head_forward_train<double>(plus.data(), cache, cfg, w, input.data(), S, tokens, ws, false, feedback.data());
  input[0] = saved - h;
  camera_head_forward_train<double>(minus.data(), cache, cfg, w, input.data(), S, tokens, ws, false, feedback.data());
  input[0] = saved;
  const double detached = (plus[(I - 1) * S * 9] - minus[(I - 1) * S * 9]) / (2 * h);
  INFO("analytic " << d_input[0] << ", detached " << detached << ", undetached " << undetached);
  CHECK(d_input[0] == Approx(detached).epsilon(1e-6));
  CHECK(std::abs(detached - undetached) > 1e-4 * std::abs(undetached));
}

TEST_CASE("camera head training forward equals the inference forward bit for bit", "[camera_head][backward]") {
  CameraHeadConfig cfg = camera_tiny_config();
  cfg.dim = 32;
  cfg.num_heads = 4;
  cfg.iterations = 4;
  std::vector<io::TensorSpec> specs;
  append_camera_head_specs(specs, cfg, "");
  heads_backward_test::FlatParams flat(specs, 71);
  const std::vector<float> values(flat.values.begin(), flat.values.end());
  io::ParamSource<float> src;
  const auto w = bind_views(src, specs, values.data(), flat.offsets, cfg);
  const index_t S = 4, tokens = 3;
  const auto in_d = camera_normal_values(S * tokens * cfg.dim, 72);
  const std::vector<float> input(in_d.begin(), in_d.end());
  std::vector<float> ws(static_cast<std::size_t>(camera_head_workspace_size(cfg, S)));
  const std::size_t n = static_cast<std::size_t>(cfg.iterations * S * 9);
  std::vector<float> a(n), b(n, 1.f), c(n, 2.f), d(n, 3.f);
  camera_head_forward<float>(a.data(), cfg, w, input.data(), S, tokens, ws);
  CameraHeadCache<float> cache, cache_re;
  camera_head_forward_train<float>(b.data(), cache, cfg, w, input.data(), S, tokens, ws);
  camera_head_forward_train<float>(c.data(), cache_re, cfg, w, input.data(), S, tokens, ws, true);
  const std::vector<float> feedback(cache.raw.begin(), cache.raw.end() - S * 9);
  CameraHeadCache<float> cache_fb;
  camera_head_forward_train<float>(d.data(), cache_fb, cfg, w, input.data(), S, tokens, ws, false, feedback.data());
  CHECK(std::memcmp(a.data(), b.data(), n * sizeof(float)) == 0);
  CHECK(std::memcmp(a.data(), c.data(), n * sizeof(float)) == 0);
  CHECK(std::memcmp(a.data(), d.data(), n * sizeof(float)) == 0);
  for (bool re : {false, true}) {
    const auto& k = re ? cache_re : cache;
    std::size_t held = k.cam_in.size() + k.tok_mean.size() + k.tok_rstd.size() + k.tok.size() + k.adaln.size() +
                       k.adaln_mean.size() + k.adaln_rstd.size() + k.enc_in.size() + k.embed_pre.size() + k.mod.size() +
                       k.trunk_out.size() + k.trunk_mean.size() + k.trunk_rstd.size() + k.hidden_pre.size() + k.raw.size();
    for (const auto& b : k.blocks)
      held += b.x_in.size() + b.ln1_mean.size() + b.ln1_rstd.size() + b.qkv.size() + b.attended.size() + b.lse.size() +
              b.proj_out.size() + b.x_mid.size() + b.ln2_mean.size() + b.ln2_rstd.size() + b.hidden.size() +
              b.mlp_out.size();
    CHECK(static_cast<index_t>(held) == camera_head_cache_elements(cfg, S, re));
  }
  // Recomputed blocks give the same gradients bit for bit.
  const auto d_enc_d = camera_normal_values(n, 73);
  const std::vector<float> d_enc(d_enc_d.begin(), d_enc_d.end());
  std::vector<float> g1(values.size(), 0.f), g2(values.size(), 0.f), t1(input.size(), 0.f), t2(input.size(), 0.f);
  camera_head_backward<float>(t1.data(), camera_head_grads(w, values.data(), g1.data()), d_enc.data(), cache, cfg, w, tokens);
  camera_head_backward<float>(t2.data(), camera_head_grads(w, values.data(), g2.data()), d_enc.data(), cache_re, cfg, w,
                              tokens);
  CHECK(g1 == g2);
  CHECK(t1 == t2);
}

TEST_CASE("camera head backward rejects an empty or mismatched cache", "[camera_head][backward]") {
  const CameraHeadConfig cfg = camera_tiny_config();
  std::vector<io::TensorSpec> specs;
  append_camera_head_specs(specs, cfg, "");
  heads_backward_test::FlatParams flat(specs, 81);
  io::ParamSource<double> src;
  const auto w = bind_views(src, specs, flat.values.data(), flat.offsets, cfg);
  CameraHeadCache<double> cache;
  std::vector<double> d_enc(cfg.iterations * 2 * 9, 1.0);
  CHECK_THROWS_WITH(camera_head_backward<double>(nullptr, CameraHeadGrads<double>{}, d_enc.data(), cache, cfg, w, 1),
                    Catch::Contains("cache is empty"));
  CameraHeadConfig other = cfg;
  other.iterations = 2;
  std::vector<double> input(2 * cfg.dim, 0.5), ws(static_cast<std::size_t>(camera_head_workspace_size(cfg, 2))),
      enc(d_enc.size());
  input[1] = -0.5;
  camera_head_forward_train<double>(enc.data(), cache, cfg, w, input.data(), 2, 1, ws);
  CHECK_THROWS_WITH(camera_head_backward<double>(nullptr, CameraHeadGrads<double>{}, d_enc.data(), cache, other, w, 1),
                    Catch::Contains("another configuration"));
}
