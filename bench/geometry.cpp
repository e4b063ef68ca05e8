// VGGT-1B architecture with random in-process weights: time per stage, achieved GFLOP/s next to the SGEMM rate
// measured in the same run, and peak RSS.
//   bench/geometry [--frames S] [--size N]... [--depth D]   (default: 4 frames at 518 and 252, full depth)
#include <sys/resource.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include "flexsplat/core/gemm.hpp"
#include "flexsplat/core/simd.hpp"
#include "flexsplat/geometry/aggregator.hpp"
#include "flexsplat/geometry/dino.hpp"
#include "flexsplat/geometry/random_weights.hpp"

using namespace flexsplat;
using namespace flexsplat::geometry;
using Clock = std::chrono::steady_clock;

static double seconds_since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

static double peak_rss_gb() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return static_cast<double>(u.ru_maxrss) / (1024.0 * 1024.0);  // ru_maxrss is in KiB on Linux
}

// Multiply-adds x2 of one block over `batch` sequences of `tokens` rows.
static double block_flops(const BlockConfig& c, double batch, double tokens) {
  const double rows = batch * tokens, C = double(c.dim), H = double(c.mlp_hidden());
  const double linear = 2.0 * rows * (3 * C * C + C * C + 2 * C * H);
  const double attention = 4.0 * batch * tokens * tokens * C;  // QK^T and PV over all heads
  return linear + attention;
}

static double sgemm_gflops() {
  const index_t M = 2048, N = 2048, K = 1024;
  std::vector<float> a(M * K, 0.5f), b(K * N, 0.25f), c(M * N);
  gemm(Trans::no, Trans::yes, M, N, K, 1.0f, a.data(), K, b.data(), K, 0.0f, c.data(), N);  // warm-up
  double best = 0;
  for (int rep = 0; rep < 3; ++rep) {
    const auto t0 = Clock::now();
    gemm(Trans::no, Trans::yes, M, N, K, 1.0f, a.data(), K, b.data(), K, 0.0f, c.data(), N);
    best = std::max(best, 2.0 * M * N * K / seconds_since(t0) / 1e9);
  }
  return best;
}

int main(int argc, char** argv) {
  index_t frames = 4, depth_override = -1;
  std::vector<index_t> sizes;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--frames" && i + 1 < argc) frames = std::atol(argv[++i]);
    else if (a == "--size" && i + 1 < argc) sizes.push_back(std::atol(argv[++i]));
    else if (a == "--depth" && i + 1 < argc) depth_override = std::atol(argv[++i]);
    else {
      std::fprintf(stderr, "usage: %s [--frames S] [--size N]... [--depth D]\n", argv[0]);
      return 2;
    }
  }
  if (sizes.empty()) sizes = {518, 252};
  simd::require_cpu_supports_build();
  AggregatorConfig cfg;  // VGGT-1B
  if (depth_override > 0) cfg.depth = cfg.dino.depth = depth_override;
  std::printf("flexsplat geometry bench: VGGT-1B trunk (%s depth), %lld frames, %d threads, arch %s, cpu: %s\n",
              depth_override > 0 ? "reduced" : "full", static_cast<long long>(frames), global_pool().size(),
              simd::compiled_arch_name(), simd::describe(simd::cpu_features()).c_str());

  auto t0 = Clock::now();
  ParamSource<float> src;
  std::vector<TensorSpec> specs;
  append_dino_specs(specs, "aggregator.patch_embed.", cfg.dino);
  append_aggregator_trunk_specs(specs, cfg);
  add_random_parameters(src, specs, 1234);
  double params = 0;
  for (auto& s : specs) {
    double n = 1;
    for (auto e : s.shape) n *= double(e);
    params += n;
  }
  const auto dino_w = load_dino_weights(src, "aggregator.patch_embed.", cfg.dino);
  const auto agg_w = load_aggregator_trunk_weights(src, cfg);
  const double weight_gb = params * 4 / 1e9;
  std::printf("random weights: %.0f M parameters (%.2f GB fp32) in %.1f s, RSS %.2f GB\n", params / 1e6, weight_gb,
              seconds_since(t0), peak_rss_gb());
  const double sgemm = sgemm_gflops();
  std::printf("SGEMM 2048x2048x1024 (core/gemm): %.1f GFLOP/s\n\n", sgemm);

  for (index_t size : sizes) {
    const index_t H = size, W = size, gh = H / cfg.patch_size, gw = W / cfg.patch_size, P = gh * gw;
    std::vector<float> images(frames * 3 * H * W);
    for (std::size_t i = 0; i < images.size(); ++i) images[i] = float((i * 2654435761u) % 1000) / 1000.0f;
    std::vector<float> normalized(images.size()), tokens(frames * P * cfg.embed_dim);
    DinoWorkspace<float> dws;
    AggregatorWorkspace<float> aws;

    t0 = Clock::now();
    imagenet_normalize(normalized.data(), images.data(), frames, H, W);
    dino_forward(tokens.data(), normalized.data(), frames, H, W, cfg.dino, dino_w, dws);
    const double t_dino = seconds_since(t0);
    const double dino_tokens = 1 + cfg.dino.num_register_tokens + P;
    const double f_dino = 2.0 * frames * P * 3 * 14 * 14 * cfg.embed_dim +
                          cfg.dino.depth * block_flops(cfg.dino.block(), frames, dino_tokens);

    t0 = Clock::now();
    const std::vector<index_t> keep{4, 11, 17, 23};
    std::vector<index_t> kept;
    for (index_t k : keep)
      if (k < cfg.depth) kept.push_back(k);
    kept.push_back(cfg.depth - 1);
    const auto out = aggregator_trunk_forward<float>(tokens.data(), frames, gh, gw, cfg, agg_w, kept, aws);
    const double t_agg = seconds_since(t0);
    const double agg_tokens = cfg.patch_start_idx() + P;
    const double f_agg = cfg.depth * (block_flops(cfg.block(), frames, agg_tokens) + block_flops(cfg.block(), 1, frames * agg_tokens));

    std::printf("%lld x %lldx%lld (%lld patches/frame)\n", (long long)frames, (long long)H, (long long)W, (long long)P);
    std::printf("  %-12s %8.2f s  %8.1f GFLOP  %7.1f GFLOP/s  (%.2f of SGEMM)\n", "dino", t_dino, f_dino / 1e9,
                f_dino / t_dino / 1e9, f_dino / t_dino / 1e9 / sgemm);
    std::printf("  %-12s %8.2f s  %8.1f GFLOP  %7.1f GFLOP/s  (%.2f of SGEMM)\n", "aggregator", t_agg, f_agg / 1e9,
                f_agg / t_agg / 1e9, f_agg / t_agg / 1e9 / sgemm);
    const double total = t_dino + t_agg, f_total = f_dino + f_agg;
    std::printf("  %-12s %8.2f s  %8.1f GFLOP  %7.1f GFLOP/s  (%.2f of SGEMM)\n", "trunk total", total, f_total / 1e9,
                f_total / total / 1e9, f_total / total / 1e9 / sgemm);
    std::printf("  peak RSS %.2f GB (weights %.2f GB + %.2f GB)\n\n", peak_rss_gb(), weight_gb, peak_rss_gb() - weight_gb);
    std::fflush(stdout);
    (void)out;
  }
  return 0;
}
