// LPIPS (VGG16 trunk, v0.1) forward and backward time for one pair of images, float, random weights at the real
// VGG16 widths. The trunk's conv FLOPs (2 per multiply-add) are counted for
// both images forward and for the input gradient backward (no weight gradients: LPIPS is a frozen loss).
//   bench/lpips [--size H W] [--batch B] [--reps R] [--target-constant]
//   bench/lpips --bundle lpips_bundle.safetensors   (float32 input gradients against a bundle, per case: the
//   checker compares gradients in float64 only, see docs/loss.md)
// --target-constant: the training loss, a render against a fixed target: in1 gets no gradient and, after the warm-up,
// its trunk activations are reused (reuse_in1), so forward runs one trunk per pair.
#include <algorithm>
#include <cmath>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <random>
#include <string>
#include <vector>

#include "flexsplat/loss/lpips.hpp"
#include "flexsplat/loss/lpips_reference.hpp"

using namespace flexsplat;
using Clock = std::chrono::steady_clock;

int main(int argc, char** argv) {
  index_t H = 128, W = 128, B = 1;
  int reps = 3;
  bool target_constant = false;
  std::string bundle;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--bundle" && i + 1 < argc) {
      bundle = argv[++i];
      continue;
    }
    if (a == "--size" && i + 2 < argc) H = std::atol(argv[++i]), W = std::atol(argv[++i]);
    else if (a == "--batch" && i + 1 < argc) B = std::atol(argv[++i]);
    else if (a == "--reps" && i + 1 < argc) reps = std::atoi(argv[++i]);
    else if (a == "--target-constant") target_constant = true;
    else {
      std::fprintf(stderr, "usage: %s [--size H W] [--batch B] [--reps R] [--target-constant] | --bundle FILE\n", argv[0]);
      return 2;
    }
  }
  if (!bundle.empty()) {
    const auto file = safetensors::File::open(bundle);
    const auto w32 = loss::lpips_load_weights<float>(file);
    loss::LpipsCache<float> cache32;
    for (const auto& c : loss::lpips_cases(file)) {
      const auto r = loss::run_lpips_case(file, c, w32, cache32, true);
      for (const char* name : {"grad_in0", "grad_in1"}) {
        const auto e = file.get<double, 4>(c + name);
        const auto& a = std::string(name) == "grad_in0" ? r.grad_in0 : r.grad_in1;
        double err = 0, ref = 0;
        for (index_t i = 0; i < e.size(); ++i) {
          err = std::max(err, std::abs(double(a[static_cast<std::size_t>(i)]) - e.data()[i]));
          ref = std::max(ref, std::abs(e.data()[i]));
        }
        std::printf("float32 %s%s: max abs error %.3e, %.3e of the max abs value\n", c.c_str(), name, err, err / ref);
      }
    }
    return 0;
  }
  loss::LpipsWeights<float> w;
  std::mt19937_64 rng(1);
  loss::lpips_init_random(std::span<float>(w.params), w.layout, rng);
  std::uniform_real_distribution<float> u(-1.f, 1.f);
  std::vector<float> in0(static_cast<std::size_t>(B * 3 * H * W)), in1(in0.size()), d0(in0.size()), d1(in0.size());
  for (auto& v : in0) v = u(rng);
  for (auto& v : in1) v = u(rng);
  std::vector<float> value(static_cast<std::size_t>(B)), ones(static_cast<std::size_t>(B), 1.f);
  loss::LpipsCache<float> cache;
  double conv_flops = 0;  // one image, forward
  {
    index_t h = H, ww = W;
    for (int j = 0; j < loss::lpips_convs; ++j) {
      const int s = loss::lpips_trunk[static_cast<std::size_t>(j)].stage;
      if (s > 0 && j == loss::lpips_first_conv[static_cast<std::size_t>(s)]) h /= 2, ww /= 2;
      conv_flops += 2.0 * 9.0 * double(w.layout.conv_in[static_cast<std::size_t>(j)]) *
                    double(w.layout.conv_out[static_cast<std::size_t>(j)]) * double(h * ww);
    }
  }
  double best_f = 1e300, best_b = 1e300;
  for (int r = 0; r <= reps; ++r) {  // r = 0 is the warm-up
    const auto t0 = Clock::now();
    loss::lpips_forward(value.data(), static_cast<float*>(nullptr), in0.data(), in1.data(), B, H, W, w.params.data(),
                        w.layout, cache, false, target_constant && r > 0);
    const auto t1 = Clock::now();
    loss::lpips_backward(d0.data(), target_constant ? static_cast<float*>(nullptr) : d1.data(), ones.data(),
                         static_cast<const float*>(nullptr), w.params.data(), w.layout, cache);
    const auto t2 = Clock::now();
    if (r == 0) continue;
    best_f = std::min(best_f, std::chrono::duration<double>(t1 - t0).count());
    best_b = std::min(best_b, std::chrono::duration<double>(t2 - t1).count());
  }
  const double fwd_flops = (target_constant ? 1.0 : 2.0) * double(B) * conv_flops;
  const double bwd_flops = (target_constant ? 1.0 : 2.0) * double(B) * conv_flops;
  // Context: the same run's rate of one conv-shaped product (relu3 stage at 128x128: 256 x 1024 x 2304, im2col form).
  double gemm_rate = 0;
  {
    const index_t M = 256, N = 1024, K = 2304;
    std::vector<float> a(static_cast<std::size_t>(M * K), 0.5f), bm(static_cast<std::size_t>(K * N), 0.25f),
        c(static_cast<std::size_t>(M * N));
    double best = 1e300;
    for (int r = 0; r <= 5; ++r) {
      const auto t0 = Clock::now();
      gemm(Trans::no, Trans::no, M, N, K, 1.0f, a.data(), K, bm.data(), N, 0.0f, c.data(), N);
      if (r > 0) best = std::min(best, std::chrono::duration<double>(Clock::now() - t0).count());
    }
    gemm_rate = 2.0 * double(M * N * K) / best * 1e-9;
  }
  std::printf("same-run SGEMM 256x1024x2304: %.1f GFLOP/s\n", gemm_rate);
  std::printf("lpips %ldx%ld, batch %ld%s, %d threads: forward %.1f ms (%.1f GFLOP/s), backward %.1f ms (%.1f GFLOP/s), "
              "total %.1f ms\n",
              static_cast<long>(H), static_cast<long>(W), static_cast<long>(B), target_constant ? ", target constant (trunk reused)" : "",
              global_pool().size(), best_f * 1e3, fwd_flops / best_f * 1e-9, best_b * 1e3, bwd_flops / best_b * 1e-9,
              (best_f + best_b) * 1e3);
  return 0;
}
