// End-to-end `flexsplat reconstruct` at the paper's size with random in-process weights: VGGT-1B geometry, the paper's
// appearance side (UNet base 64, decoder width 256, 3 layers), photos resized to --size, then the stages reconstruct
// --verbose prints (decode images, preprocess, geometry, decoder, export) per Gaussian budget and self-attention, in
// the same process and interleaved. The weights are made in memory (a 5 GB file would time the disk, not the model).
// Then the roofline of each round: every stage (profile::Stage) with its counted FLOPs, time and fraction of the run's
// own GEMM rate (gemm's default backend, FLEXSPLAT_GEMM), and the total against the fp32 floor (VGGT's FLOPs over
// the machine's best SGEMM rate); the rates are measured after the rounds, so the first round starts cold.
// --budget auto runs only the budget's queries on the photos' outline (PredictWorkspace::auto_budget).
//   bench/reconstruct IMAGE... [--size 252] [--gaussians N]... [--self-attention full|local|both] [--repeats R]
//                    [--budget full|auto|both]
#include <chrono>
#include <ctime>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <string>
#include <vector>

#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/profile.hpp"
#include "flexsplat/core/simd.hpp"
#include "flexsplat/export/file.hpp"
#include "flexsplat/geometry/flops.hpp"
#include "flexsplat/image/image_io.hpp"
#include "flexsplat/model/predict.hpp"
#include "sgemm_rate.hpp"
#include "stages.hpp"

using namespace flexsplat;
using Clock = std::chrono::steady_clock;

static double ms_since(Clock::time_point t) { return std::chrono::duration<double, std::milli>(Clock::now() - t).count(); }

// CPU seconds of every thread of the process: on a loaded machine the steadier number (wall ~ CPU / threads when idle).
static double process_cpu_seconds() {
  timespec ts{};
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

int main(int argc, char** argv) try {
  index_t size = 252;
  int repeats = 1;
  std::vector<index_t> budgets;
  std::string attention = "full", budget = "full";
  std::vector<std::string> files;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--size" && i + 1 < argc) size = std::atol(argv[++i]);
    else if (a == "--gaussians" && i + 1 < argc) budgets.push_back(std::atol(argv[++i]));
    else if (a == "--self-attention" && i + 1 < argc) attention = argv[++i];
    else if (a == "--repeats" && i + 1 < argc) repeats = std::atoi(argv[++i]);
    else if (a == "--budget" && i + 1 < argc) budget = argv[++i];
    else if (!a.empty() && a[0] != '-') files.push_back(a);
    else files.clear(), i = argc;
  }
  if (files.empty() || repeats < 1 || (attention != "full" && attention != "local" && attention != "both") ||
      (budget != "full" && budget != "auto" && budget != "both")) {
    std::fprintf(stderr, "usage: %s IMAGE... [--size 252] [--gaussians N]... [--self-attention full|local|both] "
                         "[--repeats R] [--budget full|auto|both]\n", argv[0]);
    return 2;
  }
  if (budgets.empty()) budgets = {20000};
  simd::require_cpu_supports_build();
  model::FlexSplatConfig c = model::flexsplat_paper_config();
  c.image_h = c.image_w = size;
  c.appearance.decoder.max_views = std::max<index_t>(c.appearance.decoder.max_views, static_cast<index_t>(files.size()));
  c.geometry.pose_decode.policy = geometry::DegeneratePosePolicy::clamp;  // random weights may give a bad camera
  c.validate();
  auto t0 = Clock::now();
  auto w = model::FlexSplatWeights<float>::create(c, /*training=*/false);
  w->init(1);
  std::printf("paper-size model, random weights: %.0f M parameters in %.1f s; %zu views at %lldx%lld, %d threads, "
              "arch %s\n", double(w->store().tensor_elements()) / 1e6, ms_since(t0) / 1e3, files.size(),
              (long long)size, (long long)size, global_pool().size(), simd::compiled_arch_name());
  std::printf("%-10s %-6s %-6s %9s %11s %10s %9s %8s %9s %8s\n", "gaussians", "attn", "budget", "decode ms", "preproc ms", "geometry ms",
              "decoder ms", "export ms", "total ms", "CPU s");  // decoder: the camera solvers and the appearance side
  const std::filesystem::path out = std::filesystem::temp_directory_path() / "flexsplat_bench_reconstruct.glb";
  model::PredictWorkspace<float> ws;
  std::vector<bool> modes;
  if (attention != "local") modes.push_back(false);
  if (attention != "full") modes.push_back(true);
  struct Round {
    std::string label;
    double total_ms = 0;
    std::vector<profile::StageTotals> stages;
  };
  std::vector<Round> rounds;
  profile::set_enabled(true);
  std::vector<bool> autos;
  if (budget != "auto") autos.push_back(false);
  if (budget != "full") autos.push_back(true);
  for (int r = 0; r < repeats; ++r)
    for (index_t n : budgets)
      for (bool local : modes)
        for (bool automatic : autos) {
          w->set_self_attention(local, 512);
          ws.auto_budget = automatic;
          profile::reset();
          const double cpu0 = process_cpu_seconds();
          auto t = Clock::now();
          std::vector<Tensor<float, 3>> rgba;
          {
            const profile::Stage stage("decode images");
            for (const auto& f : files) rgba.push_back(image::read_float<float>(f, 4));
          }
          const double decode = ms_since(t);
          t = Clock::now();
          model::ModelPhotos<float> photos;
          {
            const profile::Stage stage("preprocess");
            photos = model::model_photos<float>(rgba, w->config());
          }
          ws.silhouettes = std::move(photos.silhouettes);
          const double preprocess = ms_since(t);
          const model::Prediction<float> p = model::predict<float>(ws, *w, TensorView<const float, 4>(photos.images.view()), n);
          t = Clock::now();
          {
            const profile::Stage stage("export");
            gaussians::write_gaussians(p.gaussians, out);
          }
          const double write = ms_since(t);
          const double total = decode + preprocess + p.geometry_ms + p.cameras_ms + p.decoder_ms + write;
          std::printf("%-10lld %-6s %-6s %9.0f %11.0f %10.0f %9.0f %8.0f %9.0f %8.1f\n", (long long)p.budget_queries,
                      local ? "local" : "full", automatic ? "auto" : "full", decode, preprocess, p.geometry_ms,
                      p.cameras_ms + p.decoder_ms, write, total, process_cpu_seconds() - cpu0);
          std::fflush(stdout);
          char label[128];
          std::snprintf(label, sizeof label, "round %d of %d, %lld of %lld Gaussians (budget %s), %s self-attention",
                        r + 1, repeats, (long long)p.budget_queries, (long long)n, automatic ? "auto" : "full",
                        local ? "local" : "full");
          rounds.push_back({label, total, profile::stages()});
        }
  profile::set_enabled(false);
  // The rates after the rounds: measuring first would start the threads and oneDNN's primitives for round 1.
  const GemmBackend backend = default_gemm_backend();
  const double rate = bench::gemm_gflops(2048, 2048, 1024, Trans::no, Trans::yes, 0.0f, backend, 3, 1);
  const bench::SgemmRate sgemm = bench::best_sgemm();
  const double vggt_flops = geometry::vggt_forward_flops(c.geometry, static_cast<index_t>(files.size()), size, size).total();
  const double floor_s = vggt_flops / (sgemm.gflops * 1e9);
  std::printf("\nGEMM rate of this run's backend (%s, 2048x2048x1024): %.1f GFLOP/s; the machine's best SGEMM (%s): "
              "%.1f GFLOP/s\nfp32 floor: VGGT's %.1f GFLOP at the best SGEMM rate = %.2f s\n",
              gemm_backend_name(backend).c_str(), rate, gemm_backend_name(sgemm.backend).c_str(), sgemm.gflops, vggt_flops / 1e9,
              floor_s);
  for (const Round& r : rounds) {
    std::printf("\n%s: %.2f s = %.2fx the fp32 floor\n", r.label.c_str(), r.total_ms / 1e3, r.total_ms / 1e3 / floor_s);
    bench::print_stages(r.stages, 1, rate);
  }
  std::filesystem::remove(out);
  return 0;
} catch (const std::exception& e) {
  std::fprintf(stderr, "bench/reconstruct: error: %s\n", e.what());
  return 1;
}
