// One FlexSplat training step (geometry + appearance, every decoder layer rendered at every view, the paper's losses,
// backward through everything, AdamW): time per phase, and the GEMM-heavy phases' GFLOP/s next to the machine's SGEMM
// rate measured in the same run.
//   bench/train_step --recipe FILE.train.json [--state STATE] [--stage NAME] [--start STEP] [--steps K]
//                    [--gemm-shapes N]
//   bench/train_step [--config tiny|paper] [--views V] [--targets M] [--size N] [--gaussians N] [--steps K]
//                    [--recompute] [--depth D]
// --recipe: the steps `flexsplat train` runs for that recipe (its scenes, view counts, stage objective, batch) in one
// process, from --state (a run's state.safetensors) or fresh weights; steps START.. (default: the state's step, else
// the first step of --stage, default the last stage). Prints scenes/s, time and profiled FLOPs per phase, time per op family (self time:
// a GEMM inside a convolution counts as GEMM) and the step as a fraction of the same run's SGEMM rate. --gemm-shapes N:
// the N GEMM shapes that took the most time, each also timed alone on warm operands (what the step's data flow costs).
// tiny: the test configuration (28x28); paper: VGGT-1B layout with random weights, the paper's decoder, 20K Gaussians.
// --depth D keeps D of the 24 DINO blocks and D aggregator block pairs (full widths), for machines whose memory does
// not hold the full model's training state (params, grads and Adam moments: 16 bytes per parameter).
#include <sys/resource.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <memory>
#include <sstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "flexsplat/geometry/flops.hpp"
#include "flexsplat/core/profile.hpp"
#include "flexsplat/train/step.hpp"
#include "flexsplat/train/scenes.hpp"
#include "flexsplat/model/weights.hpp"
#include "flexsplat/train/run_config.hpp"
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


struct RecipeOptions {
  std::string recipe, state, stage;
  long long start = -1;
  index_t steps = 10;
  index_t gemm_shapes = 0;
};

// One shape's GFLOP/s called repeatedly on one thread with operands that stay in cache (best of 3 rounds).
static double gemm_alone_gflops(const profile::GemmShape& g) {
  ThreadPool one(1);
  const double flops = 2.0 * double(g.m) * double(g.n) * double(g.k);
  const int calls = static_cast<int>(std::clamp(2e8 / std::max(flops, 1.0), 1.0, 200.0));
  return bench::gemm_gflops(g.m, g.n, g.k, g.ta ? Trans::yes : Trans::no, g.tb ? Trans::yes : Trans::no, 1.0f,
                            default_gemm_backend(), 3, calls, one);
}

// The recipe's own steps in one process with one communicator (the global batch on this process, as one MPI rank).
static int run_recipe(const RecipeOptions& ro) {
  std::ifstream f(ro.recipe);
  require(f.good(), "train_step bench: cannot read --recipe '", ro.recipe, "'");
  std::stringstream text;
  text << f.rdbuf();
  nlohmann::json raw;
  try {
    raw = nlohmann::json::parse(text.str());
  } catch (const nlohmann::json::exception& e) {
    fail("train_step bench: '", ro.recipe, "' is not valid JSON: ", e.what());
  }
  const model::TrainRunConfig cfg = model::parse_train_config(raw);
  std::size_t si = cfg.stages.size() - 1;
  if (!ro.stage.empty()) {
    si = cfg.stages.size();
    for (std::size_t i = 0; i < cfg.stages.size(); ++i)
      if (cfg.stages[i].name == ro.stage) si = i;
    require(si < cfg.stages.size(), "train_step bench: the recipe has no stage '", ro.stage, "'");
  }
  auto w = model::FlexSplatWeights<float>::create(cfg.model, true);
  w->init(cfg.seed);
  std::uint64_t state_step = 0;
  if (!ro.state.empty()) {
    const train::CheckpointInfo info = w->load(ro.state, true);
    require(info.format == "training_state", "train_step bench: '", ro.state, "' is not a training state");
    state_step = info.state.step;
  }
  std::uint64_t stage_start = 0;
  for (std::size_t i = 0; i < si; ++i) stage_start += cfg.stages[i].steps;
  const std::uint64_t start = ro.start >= 0           ? static_cast<std::uint64_t>(ro.start)
                              : ro.state.empty() || !ro.stage.empty() ? stage_start
                                                                       : state_step;
  std::uint64_t at_start = 0;
  const model::TrainStage& stage = cfg.stages[cfg.stage_at(start, at_start)];
  std::unique_ptr<loss::LpipsWeights<float>> lpips;
  if (!cfg.lpips_weights.empty())
    lpips = std::make_unique<loss::LpipsWeights<float>>(
        loss::lpips_load_weights<float>(safetensors::File::open(cfg.lpips_weights)));
  model::TrainData data;
  data.generator.size = static_cast<int>(cfg.model.image_h);
  data::check_generator(data.generator);

  const bench::SgemmRate sgemm = bench::best_sgemm();
  std::printf("flexsplat train_step bench: recipe %s, stage '%s', steps %llu..%llu, batch %lld, %d thread(s), "
              "%.2f M parameters%s\n",
              ro.recipe.c_str(), stage.name.c_str(), (unsigned long long)start,
              (unsigned long long)(start + static_cast<std::uint64_t>(ro.steps) - 1), (long long)cfg.batch,
              global_pool().size(), double(w->store().size()) / 1e6, ro.state.empty() ? ", fresh weights" : "");
  std::printf("%s: %.1f GFLOP/s\n", bench::sgemm_label(sgemm.backend).c_str(), sgemm.gflops);

  model::StepWorkspace<float> ws;
  train::SoloCommunicator solo;
  model::PhaseTimes phases;
  double data_s = 0, step_s = 0;
  index_t scenes = 0;
  const train::ScenePlan plan = train::contiguous_plan(cfg.batch, 1);
  for (index_t k = -1; k < ro.steps; ++k) {  // k = -1: warm-up (workspaces, first-touch), not counted
    const std::uint64_t step = start + static_cast<std::uint64_t>(std::max<index_t>(k, 0));
    if (k == 0) {
      profile::reset();
      profile::set_gemm_shapes(ro.gemm_shapes > 0);
      profile::set_enabled(true);
    }
    const auto t0 = std::chrono::steady_clock::now();
    const std::vector<model::TrainExample<float>> batch = model::make_train_scenes(data, cfg, step, plan.scenes_of(0));
    const auto t1 = std::chrono::steady_clock::now();
    const model::StepSchedule at = cfg.schedule_at(step);
    const model::TrainStage& st = cfg.stages[at.stage];
    const double lr = at.lr;
    // train_step adds into the PhaseTimes it is given: the counted steps accumulate in `phases`.
    const auto r = model::train_step<float>(ws, *w, batch, plan, st.step, lr, step, solo, lpips.get(),
                                            k < 0 ? nullptr : &phases);
    const auto t2 = std::chrono::steady_clock::now();
    require(std::isfinite(r.loss), "train_step bench: the loss is ", r.loss, " at step ", step);
    if (k < 0) continue;
    data_s += std::chrono::duration<double>(t1 - t0).count();
    step_s += std::chrono::duration<double>(t2 - t1).count();
    scenes += cfg.batch;
  }
  profile::set_enabled(false);
  profile::set_gemm_shapes(false);
  const profile::Totals ops = profile::totals();
  const double n = double(ro.steps), wall_s = data_s + step_s;
  // Scenes side by side: every phase and op family is time summed over the threads, so shares are of the threads' time.
  const int threads = model::scenes_side_by_side(cfg.batch) ? global_pool().size() : 1;
  const double total_s = wall_s * threads;
  std::printf("\n%lld steps, %lld scenes: %.2f scenes/s with data generation, %.2f without; %.1f ms per step "
              "(data %.1f ms)\n", (long long)ro.steps, (long long)scenes, double(scenes) / wall_s,
              double(scenes) / step_s, wall_s / n * 1e3, data_s / n * 1e3);
  if (threads > 1)
    std::printf("scenes side by side on %d threads: times below are summed over the threads (%.1f ms of thread time "
                "per step), shares are of that\n", threads, total_s / n * 1e3);
  std::printf("\n%-20s %10s %7s %10s %9s\n", "phase", "ms/step", "share", "GFLOP", "GFLOP/s");
  auto phase = [&](const char* name, double ms, double flops) {
    std::printf("%-20s %10.2f %6.1f%% %10.3f %9.1f\n", name, ms / n, ms / 10 / total_s,
                flops / n / 1e9, ms > 0 ? flops / (ms * 1e-3) / 1e9 : 0.0);
  };
  phase("data generation", data_s * threads * 1e3, 0);
  phase("geometry forward", phases.geometry_forward, phases.flops.geometry_forward);
  phase("geometry backward", phases.geometry_backward, phases.flops.geometry_backward);
  phase("decoder forward", phases.decoder_forward, phases.flops.decoder_forward);
  phase("decoder backward", phases.decoder_backward, phases.flops.decoder_backward);
  phase("raster forward", phases.raster_forward, phases.flops.raster_forward);
  phase("raster backward", phases.raster_backward, phases.flops.raster_backward);
  phase("losses", phases.losses, phases.flops.losses);
  phase("update", phases.update * threads, phases.flops.update);
  const double step_flops = phases.flops.total();
  std::printf("%-20s %10.2f %6.1f%% %10.3f %9.1f  (%.3f of SGEMM on %d thread(s))\n", "whole step", wall_s / n * 1e3,
              100.0, step_flops / n / 1e9, step_flops / wall_s / 1e9, step_flops / wall_s / 1e9 / sgemm.gflops,
              global_pool().size());

  std::printf("\n%-20s %10s %7s %10s %10s %9s\n", "op family (self)", "ms/step", "share", "calls/step", "GFLOP",
              "GFLOP/s");
  double profiled = 0;
  for (int i = 0; i < profile::op_count; ++i) {
    profiled += ops.seconds[i];
    std::printf("%-20s %10.2f %6.1f%% %10.1f %10.3f %9.1f\n", profile::op_name(static_cast<profile::Op>(i)),
                ops.seconds[i] / n * 1e3, ops.seconds[i] / total_s * 100, double(ops.calls[i]) / n,
                ops.flops[i] / n / 1e9, ops.seconds[i] > 0 ? ops.flops[i] / ops.seconds[i] / 1e9 : 0.0);
  }
  std::printf("%-20s %10.2f %6.1f%%%s\n", "everything else", (total_s - profiled) / n * 1e3,
              (total_s - profiled) / total_s * 100, threads > 1 ? "  (with the threads' idle time)" : "");
  const double fwd = ops.seconds[int(profile::Op::attention_forward)], bwd = ops.seconds[int(profile::Op::attention_backward)];
  std::printf("\nattention backward / forward: %.2f\n", fwd > 0 ? bwd / fwd : 0.0);
  if (ro.gemm_shapes > 0) {
    const std::vector<profile::GemmShapeTotals> shapes = profile::gemm_shapes();
    double all = 0;
    for (const auto& g : shapes) all += g.seconds;
    std::printf("\nGEMM shapes (%zu in all, %.1f ms/step of calls), the %lld with the most time; alone: the same call "
                "repeated on one thread, operands in cache\n", shapes.size(), all / n * 1e3, (long long)ro.gemm_shapes);
    std::printf("%-22s %4s %4s %10s %7s %10s %13s %13s\n", "M x N x K", "tA", "tB", "ms/step", "share", "calls/step",
                "GFLOP/s step", "GFLOP/s alone");
    for (std::size_t i = 0; i < shapes.size() && static_cast<index_t>(i) < ro.gemm_shapes; ++i) {
      const auto& g = shapes[i];
      const double flops = 2.0 * double(g.shape.m) * double(g.shape.n) * double(g.shape.k) * double(g.calls);
      const std::string dims = std::to_string(g.shape.m) + " x " + std::to_string(g.shape.n) + " x " +
                               std::to_string(g.shape.k);
      std::printf("%-22s %4s %4s %10.2f %6.1f%% %10.1f %13.1f %13.1f\n", dims.c_str(), g.shape.ta ? "T" : "N",
                  g.shape.tb ? "T" : "N", g.seconds / n * 1e3, all > 0 ? 100 * g.seconds / all : 0.0,
                  double(g.calls) / n, g.seconds > 0 ? flops / g.seconds / 1e9 : 0.0, gemm_alone_gflops(g.shape));
    }
  }
  std::printf("peak RSS %.2f GB\n", peak_rss_gb());
  return 0;
}

int main(int argc, char** argv) {
  std::string config = "tiny";
  RecipeOptions ro;
  index_t views = 4, targets = 2, size = 0, gaussians = 0, steps = 3, depth = 0;
  bool recompute = false, steps_given = false;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--config" && i + 1 < argc) config = argv[++i];
    else if (a == "--recipe" && i + 1 < argc) ro.recipe = argv[++i];
    else if (a == "--state" && i + 1 < argc) ro.state = argv[++i];
    else if (a == "--stage" && i + 1 < argc) ro.stage = argv[++i];
    else if (a == "--start" && i + 1 < argc) ro.start = std::atoll(argv[++i]);
    else if (a == "--views" && i + 1 < argc) views = std::atol(argv[++i]);
    else if (a == "--targets" && i + 1 < argc) targets = std::atol(argv[++i]);
    else if (a == "--size" && i + 1 < argc) size = std::atol(argv[++i]);
    else if (a == "--gaussians" && i + 1 < argc) gaussians = std::atol(argv[++i]);
    else if (a == "--steps" && i + 1 < argc) steps = std::atol(argv[++i]), steps_given = true;
    else if (a == "--gemm-shapes" && i + 1 < argc) ro.gemm_shapes = std::atol(argv[++i]);
    else if (a == "--recompute") recompute = true;
    else if (a == "--depth" && i + 1 < argc) depth = std::atol(argv[++i]);
    else {
      std::fprintf(stderr, "usage: %s --recipe FILE.train.json [--state STATE] [--stage NAME] [--start STEP] [--steps K]\n"
                           "       [--gemm-shapes N]\n"
                           "       %s [--config tiny|paper] [--views V] [--targets M] [--size N] [--gaussians N] "
                           "[--steps K] [--recompute] [--depth D]\n", argv[0], argv[0]);
      return 2;
    }
  }
  try {
    simd::require_cpu_supports_build();
    require(ro.gemm_shapes >= 0, "train_step bench: --gemm-shapes must be >= 0, got ", ro.gemm_shapes);
    require(ro.gemm_shapes == 0 || !ro.recipe.empty(), "train_step bench: --gemm-shapes needs --recipe");
    if (!ro.recipe.empty()) {
      ro.steps = steps_given ? steps : 10;
      require(ro.steps >= 1, "train_step bench: --steps must be >= 1");
      return run_recipe(ro);
    }
    model::FlexSplatConfig c = config == "paper" ? model::flexsplat_paper_config() : model::flexsplat_tiny_config();
    require(config == "paper" || config == "tiny", "--config '", config, "': expected tiny or paper");
    if (config == "paper") c.image_h = c.image_w = 252, c.gaussians = 20000;
    if (size > 0) c.image_h = c.image_w = size;
    if (gaussians > 0) c.gaussians = gaussians;
    double full_params = 0;
    for (const auto& spec : geometry::vggt_parameter_specs(c.geometry)) full_params += double(io::spec_numel(spec));
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
    ws.recompute = recompute;
    train::SoloCommunicator solo;
    model::PhaseTimes best;
    double best_total = 1e300;
    for (index_t s = 0; s < steps; ++s) {
      model::PhaseTimes t;
      const auto r = model::train_step<float>(ws, *w, batch, train::contiguous_plan(1, 1), sc, 1e-4,
                                              static_cast<std::uint64_t>(s), solo, nullptr, &t);
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
