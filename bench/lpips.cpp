// LPIPS (VGG16 trunk, v0.1) forward and backward time for one pair of images, float, random weights at the real
// VGG16 widths. The trunk's conv FLOPs (2 per multiply-add) are counted for
// both images forward and for the input gradient backward (no weight gradients: LPIPS is a frozen loss).
//   bench/lpips [--size H W] [--batch B] [--reps R] [--target-constant]
// --target-constant: the training loss, a render against a fixed target: in1 gets no gradient and, after the warm-up,
// its trunk activations are reused (reuse_in1), so forward runs one trunk per pair.
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <random>
#include <string>
#include <vector>

#include "flexsplat/loss/lpips.hpp"

using namespace flexsplat;
using Clock = std::chrono::steady_clock;

int main(int argc, char** argv) {
  index_t H = 128, W = 128, B = 1;
  int reps = 3;
  bool target_constant = false;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--size" && i + 2 < argc) H = std::atol(argv[++i]), W = std::atol(argv[++i]);
    else if (a == "--batch" && i + 1 < argc) B = std::atol(argv[++i]);
    else if (a == "--reps" && i + 1 < argc) reps = std::atoi(argv[++i]);
    else if (a == "--target-constant") target_constant = true;
    else {
      std::fprintf(stderr, "usage: %s [--size H W] [--batch B] [--reps R] [--target-constant]\n", argv[0]);
      return 2;
    }
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
  std::printf("lpips %ldx%ld, batch %ld%s, %d threads: forward %.1f ms (%.1f GFLOP/s), backward %.1f ms (%.1f GFLOP/s), "
              "total %.1f ms\n",
              static_cast<long>(H), static_cast<long>(W), static_cast<long>(B), target_constant ? ", target constant (trunk reused)" : "",
              global_pool().size(), best_f * 1e3, fwd_flops / best_f * 1e-9, best_b * 1e3, bwd_flops / best_b * 1e-9,
              (best_f + best_b) * 1e3);
  return 0;
}
