// End-to-end `flexsplat reconstruct` at the paper's size with random in-process weights: VGGT-1B geometry, the paper's
// appearance side (UNet base 64, decoder width 256, 3 layers), photos resized to --size, then the stages reconstruct
// --verbose prints (decode images, preprocess, geometry, decoder, export) per Gaussian budget and self-attention, in
// the same process and interleaved. The weights are made in memory (a 5 GB file would time the disk, not the model).
//   bench/reconstruct IMAGE... [--size 252] [--gaussians N]... [--self-attention full|local|both] [--repeats R]
#include <chrono>
#include <ctime>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <string>
#include <vector>

#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/simd.hpp"
#include "flexsplat/export/file.hpp"
#include "flexsplat/image/image_io.hpp"
#include "flexsplat/model/predict.hpp"

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
  std::string attention = "full";
  std::vector<std::string> files;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--size" && i + 1 < argc) size = std::atol(argv[++i]);
    else if (a == "--gaussians" && i + 1 < argc) budgets.push_back(std::atol(argv[++i]));
    else if (a == "--self-attention" && i + 1 < argc) attention = argv[++i];
    else if (a == "--repeats" && i + 1 < argc) repeats = std::atoi(argv[++i]);
    else if (!a.empty() && a[0] != '-') files.push_back(a);
    else files.clear(), i = argc;
  }
  if (files.empty() || repeats < 1 || (attention != "full" && attention != "local" && attention != "both")) {
    std::fprintf(stderr, "usage: %s IMAGE... [--size 252] [--gaussians N]... [--self-attention full|local|both] "
                         "[--repeats R]\n", argv[0]);
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
  std::printf("%-10s %-6s %9s %11s %10s %9s %8s %9s %8s\n", "gaussians", "attn", "decode ms", "preproc ms", "geometry ms",
              "decoder ms", "export ms", "total ms", "CPU s");
  const std::filesystem::path out = std::filesystem::temp_directory_path() / "flexsplat_bench_reconstruct.glb";
  model::PredictWorkspace<float> ws;
  std::vector<bool> modes;
  if (attention != "local") modes.push_back(false);
  if (attention != "full") modes.push_back(true);
  for (int r = 0; r < repeats; ++r)
    for (index_t n : budgets)
      for (bool local : modes) {
        w->set_self_attention(local, 512);
        const double cpu0 = process_cpu_seconds();
        auto t = Clock::now();
        std::vector<Tensor<float, 3>> rgba;
        for (const auto& f : files) rgba.push_back(image::read_float<float>(f, 4));
        const double decode = ms_since(t);
        t = Clock::now();
        const Tensor<float, 4> input = model::model_input<float>(rgba, w->config());
        const double preprocess = ms_since(t);
        const model::Prediction<float> p = model::predict<float>(ws, *w, TensorView<const float, 4>(input.view()), n);
        t = Clock::now();
        gaussians::write_gaussians(p.gaussians, out);
        const double write = ms_since(t);
        std::printf("%-10lld %-6s %9.0f %11.0f %10.0f %9.0f %8.0f %9.0f %8.1f\n", (long long)n, local ? "local" : "full",
                    decode, preprocess, p.geometry_ms, p.decoder_ms, write,
                    decode + preprocess + p.geometry_ms + p.decoder_ms + write, process_cpu_seconds() - cpu0);
        std::fflush(stdout);
      }
  std::filesystem::remove(out);
  return 0;
} catch (const std::exception& e) {
  std::fprintf(stderr, "bench/reconstruct: error: %s\n", e.what());
  return 1;
}
