// Decoder forward timing and peak memory: N_G in {10K, 20K}, 4 views, 128x128 fused feature maps (C_f 128), C 256,
// full vs local self-attention, and the error of local against full. Usage: decoder [N_G...] (default 10000 20000).
#include <sys/resource.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <random>
#include <vector>

#include "flexsplat/decoder/decoder.hpp"

using namespace flexsplat;

namespace {
double now() { return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count(); }
double peak_rss_mb() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return static_cast<double>(u.ru_maxrss) / 1024.0;
}

struct Rig {
  index_t views = 4, image = 512, depth = 128;
  std::vector<float> K, E, D;
};

Rig make_rig() {
  Rig r;
  for (index_t v = 0; v < r.views; ++v) {
    const double az = 2.0 * 3.14159265358979 * static_cast<double>(v) / static_cast<double>(r.views);
    const double c[3] = {2.5 * std::cos(az), 0.6, 2.5 * std::sin(az)};
    double f[3] = {-c[0], -c[1], -c[2]};
    const double fn = std::sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2]);
    for (double& x : f) x /= fn;
    double rt[3] = {-f[2], 0.0, f[0]};  // f x (0, -1, 0)
    const double rn = std::sqrt(rt[0] * rt[0] + rt[2] * rt[2]);
    rt[0] /= rn, rt[2] /= rn;
    const double dn[3] = {f[1] * rt[2] - f[2] * rt[1], f[2] * rt[0] - f[0] * rt[2], f[0] * rt[1] - f[1] * rt[0]};
    const double* rows[3] = {rt, dn, f};
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) r.E.push_back(static_cast<float>(rows[i][j]));
      r.E.push_back(static_cast<float>(-(rows[i][0] * c[0] + rows[i][1] * c[1] + rows[i][2] * c[2])));
    }
    const float k[9] = {600.f, 0, 256.f, 0, 600.f, 256.f, 0, 0, 1};
    r.K.insert(r.K.end(), k, k + 9);
    for (index_t i = 0; i < r.depth * r.depth; ++i) r.D.push_back(2.2f + 0.2f * std::sin(0.01f * static_cast<float>(i)));
  }
  return r;
}
}  // namespace

int main(int argc, char** argv) {
  std::vector<index_t> budgets;
  for (int i = 1; i < argc; ++i) budgets.push_back(std::atoll(argv[i]));
  if (budgets.empty()) budgets = {10000, 20000};
  std::printf("threads %d, simd %s (%s)\n", global_pool().size(), simd::compiled_arch_name(),
              simd::enabled() ? "on" : "off: FLEXSPLAT_SIMD=scalar");
  const Rig rig = make_rig();
  const decoder::ViewGeometry<float> geo{rig.views, rig.image, rig.image, rig.depth, rig.depth, rig.K.data(), rig.E.data(),
                                         rig.D.data()};
  const index_t fh = 128, fw = 128;
  decoder::DecoderConfig cfg;
  std::vector<float> features(static_cast<std::size_t>(rig.views * cfg.value_dim * fh * fw));
  std::mt19937 rng(3);
  std::normal_distribution<float> normal(0.f, 1.f);
  for (float& x : features) x = normal(rng);
  const decoder::FeatureMaps<float> maps{rig.views, cfg.value_dim, fh, fw, features.data()};
  std::vector<float> params(static_cast<std::size_t>(decoder::DecoderParamLayout(cfg).size));
  decoder::decoder_init(params.data(), cfg, 11);
  std::printf("parameters %zu (%.1f MB float32)\n", params.size(), params.size() * 4.0 / 1e6);

  for (index_t n : budgets) {
    std::vector<float> full_means;
    for (bool local : {false, true}) {
      cfg.local_attention = local;
      decoder::DecoderState<float> st;
      decoder::decoder_forward(st, std::min<index_t>(n, 256), params.data(), cfg, maps, geo);  // warm-up
      // Per-part timing: run the same stages by hand once, then the whole forward.
      const double t0 = now();
      decoder::decoder_forward(st, n, params.data(), cfg, maps, geo);
      const double t_total = now() - t0;
      // Parts on the first layer's inputs.
      const auto& k = st.layers[0];
      std::vector<float> out(static_cast<std::size_t>(n * cfg.dim));
      decoder::MVDeformCache<float> dc;
      double t = now();
      decoder::mv_deform_forward(out.data(), dc, k.x_in.data(), st.gaussians[0].means.data(), n,
                                 params.data() + decoder::DecoderParamLayout(cfg).layer[0].deform, cfg.deform(), maps, geo);
      const double t_deform = now() - t;
      decoder::SelfAttentionCache<float> sc;
      t = now();
      decoder::self_attention_forward(out.data(), sc, k.x1.data(), st.gaussians[0].means.data(), n,
                                      params.data() + decoder::DecoderParamLayout(cfg).layer[0].attn, cfg.self_attention());
      const double t_attn = now() - t;
      std::vector<float> hidden(static_cast<std::size_t>(n * cfg.ffn));
      const auto& o = decoder::DecoderParamLayout(cfg).layer[0];
      t = now();
      nn::linear_forward(hidden.data(), k.x2.data(), params.data() + o.ffn_w1, params.data() + o.ffn_b1, n, cfg.dim, cfg.ffn);
      decoder::detail::gelu_parallel_forward(hidden.data(), hidden.data(), n * cfg.ffn);
      nn::linear_forward(out.data(), hidden.data(), params.data() + o.ffn_w2, params.data() + o.ffn_b2, n, cfg.ffn, cfg.dim);
      const double t_ffn = now() - t;
      std::printf("N_G %6lld  %-5s  forward %.3f s  | per layer: deform-attn %.3f s  self-attn %.3f s  ffn %.3f s  | peak RSS %.0f MB\n",
                  static_cast<long long>(n), local ? "local" : "full", t_total, t_deform, t_attn, t_ffn, peak_rss_mb());
      const auto& means = st.gaussians.back().means;
      if (!local) {
        full_means = means;
      } else {
        double max_err = 0, max_ref = 0;
        for (std::size_t i = 0; i < means.size(); ++i) {
          max_err = std::max(max_err, static_cast<double>(std::abs(means[i] - full_means[i])));
          max_ref = std::max(max_ref, static_cast<double>(std::abs(full_means[i])));
        }
        // Error of the self-attention output itself on identical inputs.
        decoder::SelfAttentionConfig full_cfg = cfg.self_attention();
        full_cfg.local = false;
        std::vector<float> full_out(out.size());
        decoder::SelfAttentionCache<float> fc;
        decoder::self_attention_forward(full_out.data(), fc, k.x1.data(), st.gaussians[0].means.data(), n,
                                        params.data() + o.attn, full_cfg);
        decoder::self_attention_forward(out.data(), sc, k.x1.data(), st.gaussians[0].means.data(), n,
                                        params.data() + o.attn, cfg.self_attention());
        double sa_err = 0, sa_ref = 0;
        for (std::size_t i = 0; i < out.size(); ++i) {
          sa_err = std::max(sa_err, static_cast<double>(std::abs(out[i] - full_out[i])));
          sa_ref = std::max(sa_ref, static_cast<double>(std::abs(full_out[i])));
        }
        std::printf("N_G %6lld  local vs full: self-attn output max abs err %.3e (max abs %.3e); final means max abs err %.3e (max abs %.3e)\n",
                    static_cast<long long>(n), sa_err, sa_ref, max_err, max_ref);
      }
    }
  }
  return 0;
}
