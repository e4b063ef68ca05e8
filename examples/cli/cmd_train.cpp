// train: FlexSplat training runs from a JSON configuration (model::run_training), resumable exactly, data parallel
// over MPI when built with it.
#include <cstdio>
#include <limits>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "flexsplat/train/trainer.hpp"
#include "flexsplat/optim/distributed.hpp"
#include "registry.hpp"

namespace flexsplat::cli {
namespace {

int train_command(Args args) {
  std::string config_path, out, init, steps_text, seconds_text;
  std::vector<std::string> data_args;
  for (auto it = args.begin(); it != args.end(); ++it)
    if (*it == "--data") {
      auto end = std::next(it);
      while (end != args.end() && end->rfind("--", 0) != 0) data_args.push_back(*end++);
      args.erase(it, end);
      break;
    }
  const bool quiet = take_flag(args, "--quiet");
  require(take_option(args, "--config", config_path), "train needs --config CFG.json");
  require(take_option(args, "--out", out), "train needs --out RUN_DIR");
  take_option(args, "--init", init);
  const bool has_steps = take_option(args, "--steps", steps_text);
  const bool has_seconds = take_option(args, "--seconds", seconds_text);
  require(args.empty(), "train: unexpected argument '", args.empty() ? "" : args[0], "'");
  require(!data_args.empty(), "train needs --data procedural or --data DIR...");

  // Everything is checked before any compute.
  const nlohmann::json recipe = model::read_train_recipe(config_path);
  const model::TrainRunConfig cfg = model::parse_train_config(recipe);
  model::TrainerOptions o;
  o.run = out;
  o.init = init;
  if (has_steps)
    o.stop_at = static_cast<std::uint64_t>(parse_integer(steps_text, "--steps", 1, std::numeric_limits<long long>::max()));
  if (has_seconds) o.seconds = parse_number(seconds_text, "--seconds", false);
  const model::TrainData data = model::train_data_from(data_args, cfg);

#if defined(FLEXSPLAT_WITH_MPI)
  train::MpiCommunicator comm;
#else
  train::SoloCommunicator comm;
#endif
  int last_width = 0;
  if (!quiet) {
    o.note = [](const std::string& s) { std::fprintf(stderr, "%s\n", s.c_str()); };
    o.progress = [&](const model::TrainerProgress& p) {
      const int bar = 30,
                filled = static_cast<int>(static_cast<double>(bar) * static_cast<double>(p.step) / static_cast<double>(p.total));
      std::string text = "\r[" + std::string(static_cast<std::size_t>(filled), '#') +
                         std::string(static_cast<std::size_t>(bar - filled), ' ') + "] ";
      char tail[160];
      const double rate = static_cast<double>((p.step - p.first_step) * static_cast<std::uint64_t>(p.batch)) /
                          std::max(p.seconds, 1e-9);
      std::snprintf(tail, sizeof tail, "step %llu/%llu %s loss %.4f psnr %.2f %.2f scenes/s %.1f s",
                    static_cast<unsigned long long>(p.step), static_cast<unsigned long long>(p.total), p.stage->c_str(),
                    p.loss, p.psnr, rate, p.seconds);
      text += tail;
      if (static_cast<int>(text.size()) < last_width) text += std::string(static_cast<std::size_t>(last_width) - text.size(), ' ');
      last_width = static_cast<int>(text.size());
      std::fputs(text.c_str(), stderr);
      std::fflush(stderr);
    };
  }
  const model::TrainerResult r = model::run_training(recipe, data, comm, o);
  if (comm.rank() == 0) {
    if (last_width > 0) std::fputc('\n', stderr);
    std::printf("%s: step %llu of %llu, %.1f s, %.3f scenes/s on %d rank(s)%s\n", out.c_str(),
                static_cast<unsigned long long>(r.step), static_cast<unsigned long long>(r.total), r.seconds,
                static_cast<double>((r.step - r.first_step) * static_cast<std::uint64_t>(cfg.batch)) / std::max(r.seconds, 1e-9),
                comm.size(), r.step < r.total ? " (budget reached; rerun the same command to continue)" : "");
  }
  return 0;
}

const RegisterCommand registered_cmd_train(
    "train", {"train a FlexSplat model from a JSON config (resumable exactly; data parallel under mpirun)",
              "--config CFG.json --data procedural|DIR... --out RUN_DIR [--init VGGT.safetensors|MODEL.safetensors] [--steps N] "
              "[--seconds S] [--quiet]\n"
              "  CFG.json keys (all optional): model (\"tiny\" | \"paper\" | FlexSplat config object), seed, batch (global),\n"
              "  inputs [min, max] views per scene, structured_inputs (false: random views and order, no fixed rig),\n"
              "  curriculum {baseline_deg [start, end], steps}: procedural views within a growing angle of the first,\n"
              "  procedural {min_primitives, max_primitives, blob_fraction, attached, soft_textures}: the procedural\n"
              "  objects (blobs: spheres bent by smooth waves; attached: parts on the first part's surface; soft:\n"
              "  no checkers or stripes)\n"
              "  targets, gaussians (0: tied to the view count), max_grad_norm, lpips_weights, checkpoint_every,\n"
              "  log_every, validation, stages [{name, steps, lr, warmup, appearance, train_geometry, camera_weight,\n"
              "  depth_weight, point_weight (model.geometry.point_head), match_weight (model.geometry.match_dim),\n"
              "  objective {rgb_head, render, depth, lpips}}];\n"
              "  unknown keys are errors\n"
              "  validation {every, scenes, targets, objects [DIR...]}: held-out scores in log.jsonl and validation.png\n"
              "  RUN_DIR: config.json, log.jsonl, state.safetensors (resume point), model.safetensors (at the end),\n"
              "  curves.png (loss, PSNR, camera error against the step, redrawn at each checkpoint)\n"
              "  rerunning the same command resumes from state.safetensors; --steps N stops after global step N,\n"
              "  --seconds S after S seconds, both with a checkpoint; --init starts a fresh run from VGGT geometry weights or from\n"
              "  every weight of a flexsplat model of the same architecture (its image size may differ)",
              train_command});

}  // namespace
}  // namespace flexsplat::cli
