// How fast a per-view convolutional network learns the depth's shape, to set against the geometry model's DPT head on
// its 8 x 8 tokens: a UNet (decoder/unet.hpp) and a 1 x 1 convolution to log depth, trained alone with the depth shape
// loss (loss::depth_shape_loss_*, AdamW at a constant learning rate) on a recipe's own scenes (procedural or object
// folders), scored like the recipe's validation (`depth_shape_rel`: loss::depth_scaled_error on its procedural and
// object sets) against this process's CPU time.
//   experiments/depth_fit --recipe FILE.train.json [--data procedural|DIR...] [--base C] [--levels L] [--lr X]
//                   [--seconds S] [--every N] [--log OUT.jsonl] [--scenes K]
// --scenes K: the training scenes are those of the first K steps only, again and again (K 1: one batch, a test of
// whether the network can fit what it is shown at all).
// Each view is seen alone: what a network learns here is monocular depth (shading, silhouette, perspective).
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <ctime>
#include <fstream>
#include <random>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "flexsplat/decoder/unet.hpp"
#include "flexsplat/loss/geometry.hpp"
#include "flexsplat/train/run_config.hpp"
#include "flexsplat/train/scenes.hpp"
#include "flexsplat/train/trainer.hpp"
#include "flexsplat/nn/conv.hpp"
#include "flexsplat/optim/optimizer.hpp"
#include "flexsplat/optim/params.hpp"

using namespace flexsplat;

namespace {

struct Options {
  std::string recipe, log;
  std::vector<std::string> data{"procedural"};
  index_t base = 32, levels = 3, every = 100, scenes = 0;
  double lr = 1e-3, seconds = 600;
};

double cpu_seconds() { return static_cast<double>(std::clock()) / CLOCKS_PER_SEC; }

// The UNet's features, the 1 x 1 head and the depth of one batch of views.
struct DepthNet {
  decoder::UNetConfig unet;
  index_t unet_params = 0;
  train::ParamStore<float> store;
  decoder::UNetCache<float> cache;
  AlignedVector<float> features, log_depth, depth, d_depth, d_features, scratch;

  DepthNet(index_t base, index_t levels, std::uint64_t seed) {
    unet = {3, base, levels};
    unet_params = decoder::unet_param_count(unet);
    store.add_segment("depth_net", {{"unet", {unet_params}}, {"head.weight", {1, base, 1, 1}}, {"head.bias", {1}}});
    store.allocate(true);
    std::mt19937_64 rng(seed);
    decoder::unet_init(store.params(), unet, rng);  // the head starts at log depth 0: a flat map
  }
  nn::Conv2dShape head_shape(index_t views, index_t h, index_t w) const {
    return nn::Conv2dShape{views, unet.base, 1, h, w, 1, 1, 1, 0, 0};
  }
  const float* forward(const float* images, index_t views, index_t h, index_t w, bool keep) {
    cache.keep_for_backward = keep;
    const std::size_t px = static_cast<std::size_t>(views * h * w);
    features.resize(px * static_cast<std::size_t>(unet.base));
    log_depth.resize(px), depth.resize(px);
    decoder::unet_forward(features.data(), cache, images, views, h, w, store.params(), unet);
    const nn::Conv2dShape s = head_shape(views, h, w);
    scratch.resize(static_cast<std::size_t>(nn::conv2d_forward_scratch_size(s)) + 1);
    const float* head = store.params() + unet_params;
    nn::conv2d_forward(log_depth.data(), features.data(), head, head + unet.base, s, std::span<float>(scratch));
    for (std::size_t i = 0; i < px; ++i) depth[i] = std::exp(log_depth[i]);
    return depth.data();
  }
  // Adds the loss's gradient into the store's grads; returns the loss.
  double backward(const float* images, const float* gt, index_t views, index_t h, index_t w) {
    const std::size_t px = static_cast<std::size_t>(views * h * w);
    std::vector<std::uint8_t> mask(px);
    for (std::size_t i = 0; i < px; ++i) mask[i] = gt[i] > 0;
    const double loss = loss::depth_shape_loss_forward(depth.data(), gt, mask.data(), views, h, w);
    d_depth.assign(px, 0.f);
    loss::depth_shape_loss_backward(d_depth.data(), 1.0, depth.data(), gt, mask.data(), views, h, w);
    for (std::size_t i = 0; i < px; ++i) d_depth[i] *= depth[i];  // through exp: now d(log depth)
    d_features.assign(features.size(), 0.f);
    const nn::Conv2dShape s = head_shape(views, h, w);
    scratch.resize(std::max(scratch.size(), static_cast<std::size_t>(nn::conv2d_scratch_size(s)) + 1));
    float* head = store.params() + unet_params;
    float* d_head = store.grads() + unet_params;
    nn::conv2d_backward(d_features.data(), d_head, d_head + unet.base, d_depth.data(), features.data(), head, s,
                        std::span<float>(scratch));
    decoder::unet_backward<float>(nullptr, store.grads(), d_features.data(), cache, images, store.params(), unet);
    return loss;
  }
};

Options parse(int argc, char** argv) {
  Options o;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto value = [&]() -> std::string {
      require(i + 1 < argc, a, " needs a value");
      return argv[++i];
    };
    if (a == "--recipe") o.recipe = value();
    else if (a == "--log") o.log = value();
    else if (a == "--base") o.base = std::stoll(value());
    else if (a == "--levels") o.levels = std::stoll(value());
    else if (a == "--every") o.every = std::stoll(value());
    else if (a == "--scenes") o.scenes = std::stoll(value());
    else if (a == "--lr") o.lr = std::stod(value());
    else if (a == "--seconds") o.seconds = std::stod(value());
    else if (a == "--data") {
      o.data.clear();
      while (i + 1 < argc && std::string(argv[i + 1]).rfind("--", 0) != 0) o.data.push_back(argv[++i]);
    } else fail("unknown option '", a, "' (see the header of experiments/depth_fit.cpp)");
  }
  require(!o.recipe.empty(), "--recipe FILE.train.json is required");
  require(o.base >= 1 && o.levels >= 0 && o.levels <= 5 && o.every >= 1 && o.scenes >= 0 && o.lr > 0 && o.seconds > 0,
          "--base ", o.base, ", --levels ", o.levels, ", --every ", o.every, ", --lr ", o.lr, ", --seconds ",
          o.seconds, " out of range");
  return o;
}

}  // namespace

int main(int argc, char** argv) try {
  const Options o = parse(argc, argv);
  std::ifstream f(o.recipe);
  require(f.good(), "cannot read --recipe '", o.recipe, "'");
  const model::TrainRunConfig cfg = model::parse_train_config(nlohmann::json::parse(f));
  const model::TrainData data = model::train_data_from(o.data, cfg);
  const auto sets = model::make_validation_sets(data, cfg);
  DepthNet net(o.base, o.levels, cfg.seed);
  std::printf("depth_fit: UNet base %lld, levels %lld, %lld parameters, lr %g, %lld x %lld, batch %lld\n",
              static_cast<long long>(o.base), static_cast<long long>(o.levels),
              static_cast<long long>(net.store.tensor_elements()), o.lr, static_cast<long long>(cfg.model.image_h),
              static_cast<long long>(cfg.model.image_w), static_cast<long long>(cfg.batch));
  std::ofstream log;
  if (!o.log.empty()) {
    log.open(o.log);
    require(log.good(), "cannot write --log '", o.log, "'");
  }
  const double start = cpu_seconds();
  double loss_sum = 0;
  index_t loss_n = 0;
  for (std::uint64_t step = 0;; ++step) {
    if (step % static_cast<std::uint64_t>(o.every) == 0) {
      nlohmann::json row{{"step", step}, {"cpu_seconds", cpu_seconds() - start}};
      if (loss_n > 0) row["loss"] = loss_sum / static_cast<double>(loss_n);
      loss_sum = 0, loss_n = 0;
      for (const auto& set : sets) {
        double err = 0;
        for (const auto& e : set.scenes)
          err += loss::depth_scaled_error(net.forward(e.images.data(), e.views, e.h, e.w, false), e.gt_depth.data(),
                                          e.views, e.h * e.w);
        row[set.name] = err / static_cast<double>(set.scenes.size());
      }
      std::printf("%s\n", row.dump().c_str());
      std::fflush(stdout);
      if (log.is_open()) log << row.dump() << "\n" << std::flush;
      if (cpu_seconds() - start >= o.seconds) break;
    }
    net.store.zero_grads();
    for (index_t b = 0; b < cfg.batch; ++b) {
      const std::uint64_t drawn = o.scenes > 0 ? step % static_cast<std::uint64_t>(o.scenes) : step;
      const auto e = model::make_train_scene(data, cfg, drawn, b);
      net.forward(e.images.data(), e.views, e.h, e.w, true);
      loss_sum += net.backward(e.images.data(), e.gt_depth.data(), e.views, e.h, e.w);
      ++loss_n;
    }
    float* g = net.store.grads();
    for (index_t i = 0; i < net.store.size(); ++i) g[i] /= static_cast<float>(cfg.batch);
    train::adamw_step(net.store, train::AdamWConfig{}, o.lr, step + 1);
  }
  return 0;
} catch (const std::exception& e) {
  std::fprintf(stderr, "depth_fit: %s\n", e.what());
  return 1;
}
