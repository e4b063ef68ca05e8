// nn::attention_forward / attention_backward throughput on VGGT shapes (16 heads x 64, q/k/v read from one fused
// [rows, 3 * 1024] buffer as geometry/block.hpp does), next to the SGEMM rate of the same (n x 64) x (64 x n) product
// in the same run, and the max error of the float kernels against a dense float64 reference on a smaller shape.
//   bench/attention [--reps R] [--no-backward] [--heads H] [--head-dim D] [--shape batch:tokens]...
//   (defaults 16 x 64, VGGT-1B; the small model's decoder self-attention is --heads 4 --head-dim 12 --shape 4:1024)
//   bench/attention --elementwise [--reps R]: instead, GELU (nn/activations) and layer norm (nn/layernorm) forward and
//   backward on VGGT-1B's tensors at 4 frames of 252^2 (1316 token rows; GELU on [1316, 4096], layer norm on
//   [1316, 1024]) in every lane type the CPU runs, scalar first: ns per element and GB/s of the tensors read and
//   written once (GELU 8 / 16 bytes per element forward / backward, layer norm 8 / 12).
// FLOPs: forward 4 n_q n_kv d per (batch, head) (QK^T and PV); backward 8 n_q n_kv d (dP, dV, dK, dQ; the
// recomputed score tiles are not counted). fwd/FMA and bwd/FMA: the time the kernels' own multiply-adds would take at
// the run's SGEMM rate (the CPU's FMA throughput as a GEMM reaches it), over the measured time; what is left is the
// softmax (exp, max, sums) and the packing.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <random>
#include <string>
#include <vector>

#include "flexsplat/core/gemm.hpp"
#include "flexsplat/core/simd.hpp"
#include "flexsplat/core/simd_dispatch.hpp"
#include "flexsplat/nn/activations.hpp"
#include "flexsplat/nn/attention.hpp"
#include "flexsplat/nn/layernorm.hpp"
#include "sgemm_rate.hpp"

using namespace flexsplat;
using Clock = std::chrono::steady_clock;

namespace {

double seconds_since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

template <class F>
double best_seconds(F&& f, int reps) {
  f();  // warm-up
  double best = 1e300;
  for (int r = 0; r < reps; ++r) {
    const auto t0 = Clock::now();
    f();
    best = std::min(best, seconds_since(t0));
  }
  return best;
}

// q/k/v of `batch` sequences of `tokens` rows inside one fused [batch * tokens, 3 * heads * d] buffer.
nn::AttentionLayout fused_layout(index_t batch, index_t tokens, index_t heads, index_t d) {
  nn::AttentionLayout L;
  L.batch = batch;
  L.heads = heads;
  L.n_q = L.n_kv = tokens;
  L.head_dim = d;
  const index_t C = heads * d;
  L.q = {tokens * 3 * C, d, 3 * C};
  L.k = L.v = L.q;
  L.out = {tokens * C, d, C};
  return L;
}

template <class T>
std::vector<T> random_values(std::size_t n, unsigned seed, double sigma) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> normal(0.0, sigma);
  std::vector<T> v(n);
  for (auto& x : v) x = static_cast<T>(normal(rng));
  return v;
}

// Dense float64 attention and its gradients for one fused buffer (definition, O(n^2) memory per head).
void dense_reference(const std::vector<double>& qkv, const std::vector<double>& d_out, const nn::AttentionLayout& L,
                     double scale, std::vector<double>& out, std::vector<double>& d_qkv) {
  const index_t d = L.head_dim, n = L.n_q;
  out.assign(L.batch * L.out.batch, 0.0);
  d_qkv.assign(qkv.size(), 0.0);
  std::vector<double> P(n * n), dP(n * n);
  for (index_t b = 0; b < L.batch; ++b)
    for (index_t h = 0; h < L.heads; ++h) {
      auto Q = [&](index_t i, index_t c) { return qkv[b * L.q.batch + h * L.q.head + i * L.q.row + c]; };
      auto K = [&](index_t i, index_t c) { return qkv[b * L.q.batch + h * L.q.head + i * L.q.row + L.heads * d + c]; };
      auto V = [&](index_t i, index_t c) { return qkv[b * L.q.batch + h * L.q.head + i * L.q.row + 2 * L.heads * d + c]; };
      const index_t o0 = b * L.out.batch + h * L.out.head;
      for (index_t i = 0; i < n; ++i) {
        double m = -INFINITY;
        for (index_t j = 0; j < n; ++j) {
          double s = 0;
          for (index_t c = 0; c < d; ++c) s += Q(i, c) * K(j, c);
          P[i * n + j] = scale * s;
          m = std::max(m, scale * s);
        }
        double z = 0;
        for (index_t j = 0; j < n; ++j) z += (P[i * n + j] = std::exp(P[i * n + j] - m));
        for (index_t j = 0; j < n; ++j) P[i * n + j] /= z;
        for (index_t j = 0; j < n; ++j)
          for (index_t c = 0; c < d; ++c) out[o0 + i * L.out.row + c] += P[i * n + j] * V(j, c);
      }
      for (index_t i = 0; i < n; ++i) {
        double delta = 0;
        for (index_t c = 0; c < d; ++c) delta += d_out[o0 + i * L.out.row + c] * out[o0 + i * L.out.row + c];
        for (index_t j = 0; j < n; ++j) {
          double dp = 0;
          for (index_t c = 0; c < d; ++c) dp += d_out[o0 + i * L.out.row + c] * V(j, c);
          dP[i * n + j] = P[i * n + j] * (dp - delta);  // dS
        }
      }
      for (index_t i = 0; i < n; ++i)
        for (index_t j = 0; j < n; ++j) {
          const index_t qi = b * L.q.batch + h * L.q.head + i * L.q.row, kj = b * L.q.batch + h * L.q.head + j * L.q.row;
          for (index_t c = 0; c < d; ++c) {
            d_qkv[qi + c] += scale * dP[i * n + j] * K(j, c);
            d_qkv[kj + L.heads * d + c] += scale * dP[i * n + j] * Q(i, c);
            d_qkv[kj + 2 * L.heads * d + c] += P[i * n + j] * d_out[o0 + i * L.out.row + c];
          }
        }
    }
}

double max_abs_diff(const std::vector<float>& a, const std::vector<double>& b) {
  double m = 0;
  for (std::size_t i = 0; i < a.size(); ++i) m = std::max(m, std::abs(double(a[i]) - b[i]));
  return m;
}
double max_abs(const std::vector<double>& b) {
  double m = 0;
  for (double x : b) m = std::max(m, std::abs(x));
  return m;
}

void accuracy_check(index_t d) {
  const index_t batch = 1, tokens = 333, heads = 2, C = heads * d;
  const auto L = fused_layout(batch, tokens, heads, d);
  const double scale = 1.0 / std::sqrt(double(d));
  // sigma 2 makes the softmax peaked (scores up to ~30), which exercises the running-max rescaling.
  const auto qkv64 = random_values<double>(batch * tokens * 3 * C, 5, 2.0);
  const auto dout64 = random_values<double>(batch * tokens * C, 6, 1.0);
  std::vector<double> out_ref, dqkv_ref;
  dense_reference(qkv64, dout64, L, scale, out_ref, dqkv_ref);
  std::vector<float> qkv(qkv64.begin(), qkv64.end()), dout(dout64.begin(), dout64.end());
  std::vector<float> out(out_ref.size()), lse(batch * heads * tokens), dqkv(qkv.size(), 0.0f);
  std::vector<float> scratch(nn::attention_scratch_per_worker(d, tokens) * global_pool().size());
  nn::attention_forward<float>(out.data(), lse.data(), qkv.data(), qkv.data() + C, qkv.data() + 2 * C, L, float(scale),
                               scratch);
  nn::attention_backward<float>(dqkv.data(), dqkv.data() + C, dqkv.data() + 2 * C, dout.data(), out.data(), lse.data(),
                                qkv.data(), qkv.data() + C, qkv.data() + 2 * C, L, float(scale), scratch);
  std::printf("accuracy vs dense float64 (1 x %lld tokens, %lld heads x %lld, inputs N(0, 2^2)):\n", (long long)tokens,
              (long long)heads, (long long)d);
  std::printf("  forward  max abs err %.3g (max |out| %.3g)\n", max_abs_diff(out, out_ref), max_abs(out_ref));
  std::printf("  backward max abs err %.3g (max |grad| %.3g)\n", max_abs_diff(dqkv, dqkv_ref), max_abs(dqkv_ref));
}

// GELU and layer norm forward / backward at VGGT-1B's 4 x 252^2 sizes, per lane type.
void elementwise_table(int reps) {
  const index_t rows = 4 * (18 * 18 + 5), C = 1024, H = 4096;
  using Aligned = std::vector<float, AlignedAllocator<float>>;  // 64-byte aligned, as the model's activations
  auto values = [](index_t n, unsigned seed, double sigma) {
    const auto v = random_values<float>(n, seed, sigma);
    return Aligned(v.begin(), v.end());
  };
  const Aligned hidden = values(rows * H, 5, 1.5), d_hidden = values(rows * H, 6, 1.0);
  const Aligned x = values(rows * C, 7, 2.0), dy = values(rows * C, 8, 1.0), gamma = values(C, 9, 1.0), beta = values(C, 10, 1.0);
  Aligned act(rows * H), d_act(rows * H), y(rows * C), dx(rows * C), dg(C), db(C);
  std::vector<float> mean(rows), rstd(rows);
  std::vector<simd::Lanes> lanes{simd::Lanes::scalar, simd::Lanes::compiled};
  if (simd::best_lanes<float>(simd::DispatchLevel::avx2) == simd::Lanes::avx2) lanes.push_back(simd::Lanes::avx2);
  if (simd::best_lanes<float>() == simd::Lanes::avx512) lanes.push_back(simd::Lanes::avx512);
  std::printf("GELU [%lld, %lld] and layer norm [%lld, %lld] (VGGT-1B, 4 x 252^2), float, %d threads, best of %d\n",
              (long long)rows, (long long)H, (long long)rows, (long long)C, global_pool().size(), reps);
  std::printf("%-9s %-9s %10s %8s %10s %8s\n", "kernel", "lanes", "fwd ns/el", "fwd GB/s", "bwd ns/el", "bwd GB/s");
  auto row = [&](const char* kernel, simd::Lanes l, double t_fwd, double t_bwd, double n, double fwd_bytes, double bwd_bytes) {
    std::printf("%-9s %-9s %10.3f %8.1f %10.3f %8.1f\n", kernel, simd::lanes_name(l), t_fwd / n * 1e9,
                fwd_bytes * n / t_fwd / 1e9, t_bwd / n * 1e9, bwd_bytes * n / t_bwd / 1e9);
    std::fflush(stdout);
  };
  for (simd::Lanes l : lanes) {
    const double f = best_seconds([&] { nn::gelu_forward_impl<float>(act.data(), hidden.data(), rows * H, l); }, reps);
    const double b = best_seconds([&] {
      nn::gelu_backward_impl<float>(d_act.data(), d_hidden.data(), hidden.data(), rows * H, l);
    }, reps);
    row("gelu", l, f, b, double(rows * H), 8, 16);
  }
  for (simd::Lanes l : lanes) {
    const nn::LayerNormCache<float> cache{mean.data(), rstd.data()};
    const double f = best_seconds([&] {
      nn::layernorm_forward_impl<float>(y.data(), x.data(), gamma.data(), beta.data(), rows, C, 1e-6f, cache, l);
    }, reps);
    const double b = best_seconds([&] {
      nn::layernorm_backward_impl<float>(dx.data(), dg.data(), db.data(), dy.data(), x.data(), gamma.data(), rows, C,
                                         cache, l);
    }, reps);
    row("layernorm", l, f, b, double(rows * C), 8, 12);
  }
}

}  // namespace

int main(int argc, char** argv) {
  int reps = 3;
  index_t heads = 16, d = 64;
  bool backward = true, elementwise = false;
  std::vector<std::pair<index_t, index_t>> shapes;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--reps" && i + 1 < argc) reps = std::atoi(argv[++i]);
    else if (a == "--no-backward") backward = false;
    else if (a == "--elementwise") elementwise = true;
    else if (a == "--heads" && i + 1 < argc) heads = std::atol(argv[++i]);
    else if (a == "--head-dim" && i + 1 < argc) d = std::atol(argv[++i]);
    else if (a == "--shape" && i + 1 < argc) {
      const std::string s = argv[++i];
      const auto colon = s.find(':');
      if (colon == std::string::npos) {
        std::fprintf(stderr, "--shape wants batch:tokens, got '%s'\n", s.c_str());
        return 2;
      }
      shapes.emplace_back(std::atol(s.substr(0, colon).c_str()), std::atol(s.substr(colon + 1).c_str()));
    } else {
      std::fprintf(stderr, "usage: %s [--reps R] [--no-backward] [--heads H] [--head-dim D] [--shape batch:tokens]... | "
                           "--elementwise [--reps R]\n", argv[0]);
      return 2;
    }
  }
  // VGGT at 518^2 with 4 frames: frame attention (4 x 1374), global attention over 2 and 4 frames.
  if (shapes.empty()) shapes = {{4, 1374}, {1, 2 * 1374}, {1, 4 * 1374}};
  simd::require_cpu_supports_build();
  if (heads < 1 || d < 1) {
    std::fprintf(stderr, "--heads and --head-dim must be positive, got %lld and %lld\n", (long long)heads, (long long)d);
    return 2;
  }
  std::printf("attention bench: float, %lld heads x %lld, %d threads, arch %s%s, cpu: %s\n", (long long)heads,
              (long long)d, global_pool().size(),
              simd::compiled_arch_name(), simd::enabled() ? "" : " (FLEXSPLAT_SIMD=scalar)",
              simd::describe(simd::cpu_features()).c_str());
  if (elementwise) {
    elementwise_table(reps);
    return 0;
  }
  accuracy_check(d);
  // The compute-bound reference bench/geometry uses, for comparison with its "of SGEMM" column.
  const bench::SgemmRate sgemm_rate = bench::best_sgemm(reps);
  std::printf("%s: %.1f GFLOP/s\n", bench::sgemm_label(sgemm_rate.backend).c_str(), sgemm_rate.gflops);

  const index_t C = heads * d;
  // Multiply-adds per (query, key) pair that the kernels run: forward QK^T and PV (d each); backward the recomputed
  // scores and dP (d each, twice when it runs two passes), dQ (d) and dV, dK in rows padded to whole vectors.
  const double fwd_madds = 2.0 * double(d);
  auto bwd_madds = [&](bool one_pass) {
    return (one_pass ? 3.0 : 5.0) * double(d) + 2.0 * double(nn::attention_padded_dim(d));
  };
  std::printf("%-14s %9s %10s %10s %9s %8s %10s %9s %10s %8s %8s\n", "batch x tokens", "fwd s", "fwd GF/s",
              "SGEMM GF/s", "fwd/SGEMM", "fwd/FMA", "bwd s", "bwd GF/s", "bwd/SGEMM", "bwd/FMA", "bwd/fwd");
  for (const auto& shape : shapes) {
    const index_t batch = shape.first, tokens = shape.second;
    const auto L = fused_layout(batch, tokens, heads, d);
    const float scale = 1.0f / std::sqrt(float(d));
    const auto qkv = random_values<float>(batch * tokens * 3 * C, 1, 1.0);
    const auto dout = random_values<float>(batch * tokens * C, 2, 1.0);
    std::vector<float> out(batch * tokens * C), lse(batch * heads * tokens), dqkv(qkv.size());
    std::vector<float> scratch(nn::attention_scratch_per_worker(d, tokens) * global_pool().size());
    const double flops = 4.0 * double(batch * heads) * double(tokens) * double(tokens) * double(d);

    // The same product as one head's QK^T: (tokens x 64) x (64 x tokens), C = tokens x tokens.
    std::vector<float> a = random_values<float>(tokens * d, 3, 1.0), bm = random_values<float>(tokens * d, 4, 1.0);
    std::vector<float> c(tokens * tokens);
    const double t_gemm = best_seconds([&] {
      gemm(Trans::no, Trans::yes, tokens, tokens, d, 1.0f, a.data(), d, bm.data(), d, 0.0f, c.data(), tokens);
    }, reps);
    const double sgemm = 2.0 * double(tokens) * double(tokens) * double(d) / t_gemm / 1e9;

    const double t_fwd = best_seconds([&] {
      nn::attention_forward<float>(out.data(), lse.data(), qkv.data(), qkv.data() + C, qkv.data() + 2 * C, L, scale,
                                   scratch);
    }, reps);
    double t_bwd = 0;
    if (backward)
      t_bwd = best_seconds([&] {
        nn::attention_backward<float>(dqkv.data(), dqkv.data() + C, dqkv.data() + 2 * C, dout.data(), out.data(),
                                      lse.data(), qkv.data(), qkv.data() + C, qkv.data() + 2 * C, L, scale, scratch);
      }, reps);
    const double fwd = flops / t_fwd / 1e9, bwd = backward ? 2 * flops / t_bwd / 1e9 : 0.0;
    // The time `madds` multiply-adds per (query, key) pair take at the SGEMM rate, over `seconds`.
    const double pairs = double(batch * heads) * double(tokens) * double(tokens);
    auto of_fma = [&](double madds, double seconds) {
      return 2.0 * pairs * madds / (sgemm_rate.gflops * 1e9) / seconds;
    };
    const bool one_pass = nn::attention_backward_one_pass(L, scratch.size(), global_pool().size());
    const double fma_fwd = of_fma(fwd_madds, t_fwd), fma_bwd = backward ? of_fma(bwd_madds(one_pass), t_bwd) : 0.0;
    char label[32];
    std::snprintf(label, sizeof label, "%lld x %lld", (long long)batch, (long long)tokens);
    std::printf("%-14s %9.4f %10.1f %10.1f %9.2f %8.2f %10.4f %9.1f %10.2f %8.2f %8.2f\n", label, t_fwd, fwd, sgemm,
                fwd / sgemm, fma_fwd, t_bwd, bwd, bwd / sgemm, fma_bwd, t_bwd / t_fwd);
    std::fflush(stdout);
  }
  return 0;
}
