// One FlexSplat training step (geometry + appearance, every decoder layer rendered at every view, the paper's losses,
// backward through everything, AdamW): time per phase, and the GEMM-heavy phases' GFLOP/s next to the machine's SGEMM
// rate measured in the same run.
//   bench/train_step [--config tiny|paper] [--views V] [--targets M] [--size N] [--gaussians N] [--steps K]
//                    [--recompute] [--depth D]
// tiny: the test configuration (28x28); paper: VGGT-1B layout with random weights, the paper's decoder, 20K Gaussians.
// --depth D keeps D of the 24 DINO blocks and D aggregator block pairs (full widths), for machines whose memory does
// not hold the full model's training state (params, grads and Adam moments: 16 bytes per parameter).
#include <sys/resource.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>

#include "flexsplat/geometry/flops.hpp"
#include "flexsplat/model/train.hpp"
#include "sgemm_rate.hpp"

using namespace flexsplat;

static double peak_rss_gb() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return static_cast<double>(u.ru_maxrss) * 1024.0 / 1e9;
}

// Linear-layer and attention FLOPs of the decoder forward (UNet, fusion and splatting not counted).
static double decoder_flops(const decoder::DecoderConfig& d, double n, double views, double h, double w) {
  const double dim = double(d.dim), slots = views * double(d.heads * d.points);
  double per_layer = 2 * views * h * w * double(d.value_dim) * dim  // value projection
                     + 2 * n * dim * 3 * slots                       // offsets and logits
                     + 2 * n * dim * dim                             // output projection
                     + 2 * n * dim * 4 * dim                         // self-attention qkv and projection
                     + 4 * n * (d.local_attention ? double(d.window) : n) * dim  // QK^T and PV
                     + 4 * n * dim * double(d.ffn) + 2 * n * dim * double(decoder::splat_values);
  return double(d.layers) * per_layer;
}

int main(int argc, char** argv) {
  std::string config = "tiny";
  index_t views = 4, targets = 2, size = 0, gaussians = 0, steps = 3, depth = 0;
  bool recompute = false;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--config" && i + 1 < argc) config = argv[++i];
    else if (a == "--views" && i + 1 < argc) views = std::atol(argv[++i]);
    else if (a == "--targets" && i + 1 < argc) targets = std::atol(argv[++i]);
    else if (a == "--size" && i + 1 < argc) size = std::atol(argv[++i]);
    else if (a == "--gaussians" && i + 1 < argc) gaussians = std::atol(argv[++i]);
    else if (a == "--steps" && i + 1 < argc) steps = std::atol(argv[++i]);
    else if (a == "--recompute") recompute = true;
    else if (a == "--depth" && i + 1 < argc) depth = std::atol(argv[++i]);
    else {
      std::fprintf(stderr, "usage: %s [--config tiny|paper] [--views V] [--targets M] [--size N] [--gaussians N] "
                           "[--steps K] [--recompute] [--depth D]\n", argv[0]);
      return 2;
    }
  }
  try {
    simd::require_cpu_supports_build();
    model::FlexSplatConfig c = config == "paper" ? model::flexsplat_paper_config() : model::flexsplat_tiny_config();
    require(config == "paper" || config == "tiny", "--config '", config, "': expected tiny or paper");
    if (config == "paper") c.image_h = c.image_w = 252, c.gaussians = 20000;
    if (size > 0) c.image_h = c.image_w = size;
    if (gaussians > 0) c.gaussians = gaussians;
    double full_params = 0;
    for (const auto& spec : geometry::vggt_parameter_specs(c.geometry)) full_params += double(geometry::spec_numel(spec));
    if (depth > 0) {
      auto& a = c.geometry.aggregator;
      a.depth = a.dino.depth = depth;
      for (auto& i : c.geometry.depth.intermediate_layer_idx) i = std::min(i, depth - 1);
      std::printf("reduced depth %lld: the full geometry has %.0f M parameters, %.1f GB of training state\n",
                  (long long)depth, full_params / 1e6, full_params * 16 / 1e9);
    }
    c.appearance.decoder.max_views = std::max(c.appearance.decoder.max_views, views);
    c.geometry.pose_decode.policy = geometry::DegeneratePosePolicy::clamp;  // random weights may give a bad camera
    c.validate();
    const bench::SgemmRate sgemm_before = bench::best_sgemm();
    auto t0 = std::chrono::steady_clock::now();
    auto w = model::FlexSplatWeights<float>::create(c, true);
    w->init(1);
    std::printf("flexsplat train_step bench: %s config, %lld views + %lld targets at %lldx%lld, %lld Gaussians, "
                "%.1f M parameters, %d threads, recompute %s\n",
                config.c_str(), (long long)views, (long long)targets, (long long)c.image_w, (long long)c.image_h,
                (long long)c.gaussians_for(views), double(w->store().tensor_elements()) / 1e6, global_pool().size(),
                recompute ? "on" : "off");
    std::printf("weights created in %.1f s\n",
                std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());

    data::GeneratorConfig g;
    g.size = static_cast<int>(c.image_h);
    data::BatchOptions o;
    o.inputs = static_cast<int>(views), o.targets = static_cast<int>(targets), o.structured_inputs = views == 4;
    t0 = std::chrono::steady_clock::now();
    const std::vector<model::TrainExample<float>> batch{model::make_train_example<float>(data::generate_batch(g, 1, 7, 0, o)[0], c)};
    const double t_data = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();

    model::StepConfig sc;
    sc.camera_weight = 1.0, sc.depth_weight = 0.1;
    model::StepWorkspace<float> ws;
    ws.scene.geometry.recompute = recompute;
    train::SoloCommunicator solo;
    model::PhaseTimes best;
    double best_total = 1e300;
    for (index_t s = 0; s < steps; ++s) {
      model::PhaseTimes t;
      const auto r = model::train_step<float>(ws, *w, batch, 1, sc, 1e-4, static_cast<std::uint64_t>(s), solo, nullptr, &t);
      std::printf("step %lld: %.1f ms, loss %.4f\n", (long long)s, t.total(), r.loss);
      if (t.total() < best_total) best_total = t.total(), best = t;
    }
    const bench::SgemmRate sgemm_after = bench::best_sgemm();
    const bench::SgemmRate sgemm_best = sgemm_before.gflops >= sgemm_after.gflops ? sgemm_before : sgemm_after;
    const double sgemm = sgemm_best.gflops;
    const auto gf = geometry::vggt_forward_flops(c.geometry, views, c.image_h, c.image_w);
    const double df = decoder_flops(c.appearance.decoder, double(c.gaussians_for(views)), double(views),
                                    double(c.image_h), double(c.image_w));
    std::printf("\nbest of %lld steps; %s: %.1f GFLOP/s (best of before/after)\n", (long long)steps,
                bench::sgemm_label(sgemm_best.backend).c_str(), sgemm);
    std::printf("data generation (not in the step): %.1f ms for %lld views\n", t_data * 1e3, (long long)(views + targets));
    auto row = [&](const char* name, double ms, double flops) {
      if (flops > 0)
        std::printf("  %-18s %10.1f ms  %8.2f GFLOP  %7.1f GFLOP/s  (%.2f of SGEMM)\n", name, ms, flops / 1e9,
                    flops / (ms * 1e-3) / 1e9, flops / (ms * 1e-3) / 1e9 / sgemm);
      else
        std::printf("  %-18s %10.1f ms\n", name, ms);
    };
    row("geometry forward", best.geometry_forward, gf.total());
    row("geometry backward", best.geometry_backward, 2 * gf.total());
    row("decoder forward", best.decoder_forward, df);
    row("decoder backward", best.decoder_backward, 2 * df);
    row("raster forward", best.raster_forward, 0);
    row("raster backward", best.raster_backward, 0);
    row("losses", best.losses, 0);
    row("update", best.update, 0);
    const double flops = 3 * gf.total() + 3 * df;
    std::printf("  %-18s %10.1f ms  %8.2f GFLOP  %7.1f GFLOP/s  (%.2f of SGEMM)\n", "whole step", best.total(),
                flops / 1e9, flops / (best.total() * 1e-3) / 1e9, flops / (best.total() * 1e-3) / 1e9 / sgemm);
    std::printf("  peak RSS %.2f GB\n", peak_rss_gb());
  } catch (const std::exception& e) {
    std::fprintf(stderr, "train_step bench: %s\n", e.what());
    return 1;
  }
  return 0;
}
