// Decoder forward: time (wall and process CPU) and memory per stage (profile::Stage) for N_G Gaussians, 4 views,
// 128x128 fused feature maps (C_f 128), C 256, FFN 1024, L 3, full vs local self-attention, and the error of local
// against full.
// Usage: decoder [--local-only] [--window W] [--reps R] [N_G...]   (default 10000 20000; threads: FLEXSPLAT_NUM_THREADS)
#include <sys/resource.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <random>
#include <string>
#include <span>
#include <vector>

#include "flexsplat/core/profile.hpp"
#include "flexsplat/decoder/decoder.hpp"
#include "stages.hpp"

using namespace flexsplat;

namespace {
double peak_rss_mb() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return static_cast<double>(u.ru_maxrss) / 1024.0;
}
double mb(std::size_t bytes) { return static_cast<double>(bytes) / (1024.0 * 1024.0); }

struct Rig {
  index_t views = 4, image = 512, depth = 128;
  std::vector<float> K, E, D;
};

// Four cameras on a ring looking at the origin, depth maps of a bumpy sphere-ish surface.
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

struct Diff {
  double max_abs = 0, ref_max_abs = 0, rms = 0, ref_rms = 0;
};
Diff compare(std::span<const float> a, std::span<const float> ref) {
  Diff d;
  for (std::size_t i = 0; i < a.size(); ++i) {
    const double e = static_cast<double>(a[i]) - static_cast<double>(ref[i]);
    d.max_abs = std::max(d.max_abs, std::abs(e));
    d.ref_max_abs = std::max(d.ref_max_abs, std::abs(static_cast<double>(ref[i])));
    d.rms += e * e;
    d.ref_rms += static_cast<double>(ref[i]) * static_cast<double>(ref[i]);
  }
  d.rms = std::sqrt(d.rms / static_cast<double>(a.size()));
  d.ref_rms = std::sqrt(d.ref_rms / static_cast<double>(a.size()));
  return d;
}
}  // namespace

int main(int argc, char** argv) {
  std::vector<index_t> budgets;
  bool local_only = false;
  index_t window = 512;
  int reps = 1;
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--local-only")) local_only = true;
    else if (!std::strcmp(argv[i], "--window") && i + 1 < argc) window = std::atoll(argv[++i]);
    else if (!std::strcmp(argv[i], "--reps") && i + 1 < argc) reps = std::max(1, std::atoi(argv[++i]));
    else budgets.push_back(std::atoll(argv[i]));
  }
  if (budgets.empty()) budgets = {10000, 20000};
  std::printf("threads %d, simd %s (%s), window %lld, reps %d\n", global_pool().size(), simd::compiled_arch_name(),
              simd::enabled() ? "on" : "off: FLEXSPLAT_SIMD=scalar", static_cast<long long>(window), reps);
  const Rig rig = make_rig();
  const decoder::ViewGeometry<float> geo{rig.views, rig.image, rig.image, rig.depth, rig.depth, rig.K.data(), rig.E.data(),
                                         rig.D.data()};
  const index_t fh = 128, fw = 128;
  decoder::DecoderConfig cfg;
  cfg.window = window;
  std::vector<float> features(static_cast<std::size_t>(rig.views * cfg.value_dim * fh * fw));
  std::mt19937 rng(3);
  std::normal_distribution<float> normal(0.f, 1.f);
  for (float& x : features) x = normal(rng);
  const decoder::FeatureMaps<float> maps{rig.views, cfg.value_dim, fh, fw, features.data()};
  std::vector<float> params(static_cast<std::size_t>(decoder::DecoderParamLayout(cfg).size));
  decoder::decoder_init(params.data(), cfg, 11);
  std::printf("parameters %zu (%.1f MB float32)\n", params.size(), params.size() * 4.0 / 1e6);

  for (index_t n : budgets) {
    std::vector<float> full_means, full_sa;
    for (bool local : {false, true}) {
      if (!local && local_only) continue;
      cfg.local_attention = local;
      decoder::DecoderWorkspace<float> ws;
      ws.reserve(cfg, n, rig.views, fh, fw, rig.depth * rig.depth);
      decoder::decoder_forward(ws, n, params.data(), cfg, maps, geo);  // warm-up: touches every page once
      profile::reset();
      profile::set_enabled(true);
      const auto w0 = std::chrono::steady_clock::now();
      const std::clock_t c0 = std::clock();
      for (int r = 0; r < reps; ++r) decoder::decoder_forward(ws, n, params.data(), cfg, maps, geo);
      const double wall = std::chrono::duration<double>(std::chrono::steady_clock::now() - w0).count() / reps;
      const double cpu = static_cast<double>(std::clock() - c0) / CLOCKS_PER_SEC / reps;
      profile::set_enabled(false);
      std::size_t deform_bytes = 0, attn_bytes = 0;
      for (const auto& k : ws.layers) deform_bytes += k.deform.capacity_bytes(), attn_bytes += k.attention.capacity_bytes();
      std::printf("N_G %6lld %-5s forward wall %.3f s cpu %.3f s | workspace fwd %.0f MB (deform %.0f, self-attn %.0f) + bwd %.0f MB | peak RSS %.0f MB\n",
                  static_cast<long long>(n), local ? "local" : "full", wall, cpu,
                  mb(ws.capacity_bytes() - ws.grad.capacity_bytes()), mb(deform_bytes), mb(attn_bytes),
                  mb(ws.grad.capacity_bytes()), peak_rss_mb());
      bench::print_stages(profile::stages(), reps, 0);
      // Self-attention output of layer 0 on the same inputs, for the local-vs-full error.
      const auto& k = ws.layers[0];
      std::vector<float> sa(static_cast<std::size_t>(n * cfg.dim));
      {
        decoder::SelfAttentionCache<float> sc;
        decoder::self_attention_forward(sa.data(), sc, k.x1.data(), ws.gaussians[0].means.data(), n,
                                        params.data() + decoder::decoder_layer_offsets(cfg, 0).attn, cfg.self_attention());
      }
      if (!local) {
        const auto means = ws.gaussians.back().means.span();
        full_means.assign(means.begin(), means.end());
        full_sa = sa;
      } else if (!full_means.empty()) {
        // Full attention on the local run's layer-0 input, so both see identical queries.
        decoder::SelfAttentionConfig fc = cfg.self_attention();
        fc.local = false;
        decoder::SelfAttentionCache<float> sc;
        decoder::self_attention_forward(full_sa.data(), sc, k.x1.data(), ws.gaussians[0].means.data(), n,
                                        params.data() + decoder::decoder_layer_offsets(cfg, 0).attn, fc);
        const Diff a = compare(sa, full_sa), m = compare(ws.gaussians.back().means.span(), full_means);
        std::printf("N_G %6lld local vs full: layer-0 self-attn output max abs err %.3e rms err %.3e (full: max abs %.3e rms %.3e); "
                    "final means max abs err %.3e rms err %.3e (max abs %.3e)\n",
                    static_cast<long long>(n), a.max_abs, a.rms, a.ref_max_abs, a.ref_rms, m.max_abs, m.rms, m.ref_max_abs);
      }
    }
  }
  return 0;
}
