// nn::conv2d_forward's two stride-1 paths on the VGGT DPT head's k x k convolutions, each in bands of output rows
// within the DPT's scratch (geometry::dpt_conv_scratch_budget elements): im2col + one GEMM per band, and one GEMM per
// kernel tap on a window of the padded input (detail::conv2d_forward_shifted). Time (best of reps), fraction of the
// machine's SGEMM rate in the same run, and the largest difference between the two outputs over the largest output.
// Then the same for conv2d_backward's two input-gradient paths.
// Usage: conv [size=252] [reps=5]
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <random>
#include <vector>

#include "flexsplat/core/gemm.hpp"
#include "flexsplat/geometry/dpt_head.hpp"
#include "flexsplat/nn/conv.hpp"
#include "sgemm_rate.hpp"

using namespace flexsplat;

namespace {

template <class F>
double best_seconds(F&& f, int reps) {
  double best = 1e300;
  for (int r = 0; r < reps; ++r) {
    const auto t0 = std::chrono::steady_clock::now();
    f();
    best = std::min(best, std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
  }
  return best;
}

std::vector<float> random_values(std::size_t n, unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<float> dist(0.0f, 1.0f);
  std::vector<float> v(n);
  for (float& x : v) x = dist(rng);
  return v;
}

// One table row: both paths' times, their fractions of the SGEMM rate, the largest difference between their
// outputs over the largest output, and the path the library takes.
void print_row(const char* name, const nn::Conv2dShape& s, const std::vector<float>& a, const std::vector<float>& b,
               double ta, double tb, double sgemm_gflops, const char* taken) {
  const double flops = 2.0 * double(s.out_channels) * double(s.in_channels * s.kernel_h * s.kernel_w) *
                       double(s.conv_out_h() * s.conv_out_w());
  double diff = 0, scale = 0;
  for (std::size_t i = 0; i < a.size(); ++i) {
    diff = std::max(diff, double(std::abs(a[i] - b[i])));
    scale = std::max(scale, double(std::abs(a[i])));
  }
  std::printf("%-14s %5ld %5ld %4ldx%-4ld %10.2f %7.2f %10.2f %7.2f %9.1e %s\n", name, long(s.in_channels),
              long(s.out_channels), long(s.in_h), long(s.in_w), ta * 1e3, flops / ta * 1e-9 / sgemm_gflops, tb * 1e3,
              flops / tb * 1e-9 / sgemm_gflops, diff / scale, taken);
}

struct Case {
  const char* name;
  index_t cin, cout, h, w, k;
};

}  // namespace

int main(int argc, char** argv) {
  const index_t size = argc > 1 ? std::atol(argv[1]) : 252;
  const int reps = argc > 2 ? std::atoi(argv[2]) : 5;
  if (size < 28 || size % 14 != 0 || reps < 1) {
    std::fprintf(stderr, "usage: conv [size: a multiple of 14, >= 28] [reps >= 1]\n");
    return 2;
  }
  const bench::SgemmRate rate = bench::best_sgemm(reps);
  std::printf("%s: %.1f GFLOP/s; %s\n", bench::sgemm_label(rate.backend).c_str(), rate.gflops,
              gemm_backend_name().c_str());
  // VGGT-1B's DPT (features 256, out_channels 256/512/1024/1024, head 128 -> 32) at one frame of size x size.
  const index_t t = size / 14;
  const Case cases[] = {
      {"layer_rn[0]", 256, 256, 4 * t, 4 * t, 3},  {"layer_rn[1]", 512, 256, 2 * t, 2 * t, 3},
      {"layer_rn[2]", 1024, 256, t, t, 3},         {"layer_rn[3]", 1024, 256, (t + 1) / 2, (t + 1) / 2, 3},
      {"unit 256 @4t", 256, 256, 4 * t, 4 * t, 3}, {"unit 256 @2t", 256, 256, 2 * t, 2 * t, 3},
      {"unit 256 @t", 256, 256, t, t, 3},          {"output_conv1", 256, 128, 8 * t, 8 * t, 3},
      {"output_conv2", 128, 32, size, size, 3},
      // the small models' (features 32 at 56 x 56, the UNet's 16 and 32 channels), then channel ratios around the
      // input gradient's switch (C_out <= C_in takes the correlation)
      {"dpt 32 @56", 32, 32, 56, 56, 3}, {"unet 16 @56", 16, 16, 56, 56, 3}, {"unet 32 @28", 32, 32, 28, 28, 3},
      {"48->24 @56", 48, 24, 56, 56, 3}, {"16->32 @56", 16, 32, 56, 56, 3}, {"8->32 @56", 8, 32, 56, 56, 3},
      {"3->16 @56", 3, 16, 56, 56, 3},
  };
  std::printf("forward\n%-14s %5s %5s %9s %10s %7s %10s %7s %9s %s\n", "conv", "cin", "cout", "map", "im2col ms",
              "/SGEMM", "shifted ms", "/SGEMM", "rel diff", "taken");
  for (const Case& c : cases) {
    const nn::Conv2dShape s{1, c.cin, c.cout, c.h, c.w, c.k, c.k, 1, (c.k - 1) / 2};
    const auto x = random_values(std::size_t(c.cin * c.h * c.w), 1);
    const auto wt = random_values(std::size_t(c.cout * c.cin * c.k * c.k), 2);
    const auto b = random_values(std::size_t(c.cout), 3);
    std::vector<float> y0(std::size_t(c.cout * c.h * c.w)), y1(y0.size());
    std::vector<float> scratch(std::size_t(std::max({geometry::dpt_conv_scratch_budget, nn::conv2d_row_scratch_size(s),
                                                     nn::conv2d_shifted_scratch_size(s, 1)})));
    const std::span<float> sp(scratch);
    const double t0 = best_seconds(
        [&] { nn::detail::conv2d_forward_im2col(y0.data(), x.data(), wt.data(), b.data(), s, sp); }, reps);
    const double t1 = best_seconds(
        [&] { nn::detail::conv2d_forward_shifted(y1.data(), x.data(), wt.data(), b.data(), s, sp); }, reps);
    print_row(c.name, s, y0, y1, t0, t1, rate.gflops, nn::detail::conv2d_use_shifted(s, scratch.size()) ? "shifted" : "im2col");
  }
  // The input gradient's two stride-1 paths (conv2d_backward's d_in): the adjoint of im2col (a GEMM into a zeroed
  // C_in * k * k column matrix, scattered back) and the correlation of d_out with the flipped kernel.
  std::printf("\ninput gradient\n%-14s %5s %5s %9s %10s %7s %10s %7s %9s %s\n", "conv", "cin", "cout", "map",
              "columns ms", "/SGEMM", "correl. ms", "/SGEMM", "rel diff", "taken");
  for (const Case& c : cases) {
    const nn::Conv2dShape s{1, c.cin, c.cout, c.h, c.w, c.k, c.k, 1, (c.k - 1) / 2};
    const auto dy = random_values(std::size_t(c.cout * c.h * c.w), 4);
    const auto wt = random_values(std::size_t(c.cout * c.cin * c.k * c.k), 5);
    std::vector<float> dx0(std::size_t(c.cin * c.h * c.w)), dx1(dx0.size());
    std::vector<float> scratch(std::size_t(std::max({geometry::dpt_conv_scratch_budget, nn::conv2d_row_scratch_size(s),
                                                     nn::conv2d_correlate_scratch_size(s, 1)})));
    const std::span<float> sp(scratch);
    const double t0 = best_seconds(
        [&] {
          std::fill(dx0.begin(), dx0.end(), 0.0f);
          nn::detail::conv2d_backward_input_columns(dx0.data(), dy.data(), wt.data(), s, sp);
        },
        reps);
    const double t1 = best_seconds(
        [&] {
          std::fill(dx1.begin(), dx1.end(), 0.0f);
          nn::detail::conv2d_backward_input_correlate(dx1.data(), dy.data(), wt.data(), s, sp);
        },
        reps);
    print_row(c.name, s, dx0, dx1, t0, t1, rate.gflops,
              nn::detail::conv2d_use_correlate(s, scratch.size()) ? "correlation" : "columns");
  }
  return 0;
}
