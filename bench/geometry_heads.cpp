// VGGT-1B camera head and DPT depth head with random weights (generated here, nothing downloaded): time per head,
// achieved GFLOP/s next to the machine's SGEMM rate (the BLAS when the build has one) measured in the same run, peak RSS.
// Usage: geometry_heads [frames=4] [size=518 ...]   e.g. `build/bench/geometry_heads 4 518 252`
#include <sys/resource.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <random>
#include <string>
#include <vector>

#include "flexsplat/core/gemm.hpp"
#include "flexsplat/core/simd.hpp"
#include "flexsplat/geometry/camera_head.hpp"
#include "flexsplat/geometry/dpt_head.hpp"
#include "flexsplat/geometry/flops.hpp"
#include "sgemm_rate.hpp"

using namespace flexsplat;
using namespace flexsplat::geometry;

namespace {

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

double peak_rss_mib() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return static_cast<double>(u.ru_maxrss) / 1024.0;
}

// Random normal weights scaled by 1/sqrt(fan_in); norms and LayerScale near their trained magnitudes.
void add_random(io::ParamSource<float>& src, const std::vector<io::TensorSpec>& specs, unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<float> normal;
  for (const auto& s : specs) {
    index_t n = 1;
    for (index_t e : s.shape) n *= e;
    std::vector<float> v(static_cast<std::size_t>(n));
    const bool is_norm_weight = s.name.find("norm") != std::string::npos && s.name.ends_with(".weight");
    const bool is_gamma = s.name.ends_with("gamma");
    const index_t fan_in = s.shape.size() >= 2 ? n / s.shape[0] : 1;
    const float scale = s.shape.size() >= 2 ? 1.0f / std::sqrt(static_cast<float>(fan_in)) : 0.02f;
    for (auto& x : v) x = is_norm_weight ? 1.0f + 0.02f * normal(rng) : is_gamma ? 0.01f : scale * normal(rng);
    src.add(s.name, s.shape, std::move(v));
  }
}

}  // namespace

int main(int argc, char** argv) {
  const index_t frames = argc > 1 ? std::atol(argv[1]) : 4;
  std::vector<index_t> sizes;
  for (int i = 2; i < argc; ++i) sizes.push_back(std::atol(argv[i]));
  if (sizes.empty()) sizes = {518, 252};
  const auto cpu = simd::cpu_features();
  std::printf("threads %d, simd arch %s, avx512f %d\n", global_pool().size(), simd::arch::name(), int(cpu.avx512f));
  const bench::SgemmRate sgemm_rate = bench::best_sgemm();
  const double sgemm = sgemm_rate.gflops;
  std::printf("%s: %.1f GFLOP/s\n", bench::sgemm_label(sgemm_rate.backend).c_str(), sgemm);

  const CameraHeadConfig cam_cfg;  // VGGT-1B
  const DptHeadConfig dpt_cfg;
  io::ParamSource<float> src;
  std::vector<io::TensorSpec> specs;
  append_camera_head_specs(specs, cam_cfg);
  append_dpt_head_specs(specs, dpt_cfg);
  auto t0 = std::chrono::steady_clock::now();
  add_random(src, specs, 1234);
  const auto cam_w = load_camera_head_weights(src, cam_cfg);
  const auto dpt_w = load_dpt_head_weights(src, dpt_cfg);
  index_t n_params = 0;
  for (auto& s : specs) {
    index_t n = 1;
    for (index_t e : s.shape) n *= e;
    n_params += n;
  }
  std::printf("random weights: %.1f M parameters (%.0f MiB) in %.1f s; peak RSS %.0f MiB\n", n_params * 1e-6,
              n_params * 4.0 / (1 << 20), seconds_since(t0), peak_rss_mib());

  for (index_t size : sizes) {
    const index_t ph = size / 14, pw = size / 14, tokens = 5 + ph * pw, C = dpt_cfg.dim_in;
    std::vector<float> layer(static_cast<std::size_t>(frames * tokens * C));
    std::mt19937 rng(7);
    std::normal_distribution<float> normal;
    for (auto& x : layer) x = normal(rng);
    const std::vector<const float*> layers(24, layer.data());  // every block output shares one random tensor

    std::vector<float> cam_ws(static_cast<std::size_t>(camera_head_workspace_size(cam_cfg, frames)));
    std::vector<float> enc(cam_cfg.iterations * frames * 9);
    t0 = std::chrono::steady_clock::now();
    camera_head_forward<float>(enc.data(), cam_cfg, cam_w, layer.data(), frames, tokens, cam_ws);
    const double cam_s = seconds_since(t0);
    const double cam_flops = camera_head_flops(cam_cfg, frames);

    std::vector<float> dpt_ws(static_cast<std::size_t>(dpt_head_workspace_size(dpt_cfg, ph, pw)));
    const index_t full = ph * 14 * pw * 14;
    std::vector<float> depth(frames * full), conf(frames * full);
    DptHeadOutputs<float> out{depth.data(), conf.data()};
    t0 = std::chrono::steady_clock::now();
    dpt_head_forward<float>(out, dpt_cfg, dpt_w, layers, frames, tokens, 5, ph * 14, pw * 14, dpt_ws);
    const double dpt_s = seconds_since(t0);
    const double dpt_flops = geometry::dpt_flops(dpt_cfg, ph, pw) * static_cast<double>(frames);
    double finite = 0;
    for (float d : depth) finite += std::isfinite(d) ? 1 : 0;
    std::printf("%ld frames at %ldx%ld (patch grid %ldx%ld):\n", long(frames), long(ph * 14), long(pw * 14), long(ph),
                long(pw));
    std::printf("  camera head  %8.3f s  %7.1f GFLOP  %6.1f GFLOP/s  (%.2f of SGEMM)\n", cam_s, cam_flops * 1e-9,
                cam_flops / cam_s * 1e-9, cam_flops / cam_s * 1e-9 / sgemm);
    std::printf("  DPT head     %8.3f s  %7.1f GFLOP  %6.1f GFLOP/s  (%.2f of SGEMM)  workspace %.0f MiB\n", dpt_s,
                dpt_flops * 1e-9, dpt_flops / dpt_s * 1e-9, dpt_flops / dpt_s * 1e-9 / sgemm,
                static_cast<double>(dpt_ws.size()) * 4.0 / (1 << 20));
    std::printf("  finite depth values %.0f / %ld; peak RSS so far %.0f MiB\n", finite, long(depth.size()),
                peak_rss_mib());
  }
  return 0;
}
