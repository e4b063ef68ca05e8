#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <vector>

#include "flexsplat/geometry/random_weights.hpp"
#include "flexsplat/geometry/vggt.hpp"
#include "flexsplat/geometry/weights.hpp"
#include "flexsplat/testing/gradcheck.hpp"
#include "geometry_test_util.hpp"

using namespace flexsplat;
using namespace flexsplat::geometry;

namespace vggt_backward_test {

VggtConfig tiny_vggt() {
  VggtConfig c;
  auto& a = c.aggregator;
  a.patch_size = 2;
  a.embed_dim = 8;
  a.depth = 2;
  a.num_heads = 2;
  a.mlp_ratio = 2.0;
  a.num_register_tokens = 1;
  a.init_values = 0.5;
  a.dino.img_size = 6;  // 3 x 3 position grid
  a.dino.patch_size = 2;
  a.dino.embed_dim = 8;
  a.dino.depth = 1;
  a.dino.num_heads = 2;
  a.dino.mlp_ratio = 2.0;
  a.dino.num_register_tokens = 1;
  a.dino.init_values = 0.5;
  c.camera.dim = 16;
  c.camera.trunk_depth = 1;
  c.camera.num_heads = 2;
  c.camera.mlp_ratio = 2.0;
  c.camera.iterations = 2;
  c.depth.dim_in = 16;
  c.depth.patch_size = 2;
  c.depth.features = 8;
  c.depth.out_channels = {4, 4, 8, 4};
  c.depth.intermediate_layer_idx = {0, 1, 0, 1};
  return c;
}

// The whole model in one flat block (as the training store holds it): the library's random initialisation (LayerScale
// 0.5) plus noise so no entry sits at 0 or 1, the pose branch scaled and biased so decoded cameras are valid (FoV
// near 1.2 rad, a non-zero quaternion).
template <class T>
struct FlatVggt {
  VggtConfig c;
  std::vector<io::TensorSpec> specs;
  std::vector<T> params, grads;
  io::ParamSource<T> src;
  VggtWeights<T> w;
  VggtGrads<T> g;
  FlatVggt(const VggtConfig& config, unsigned seed) : c(config) {
    specs = vggt_parameter_specs(c);
    std::vector<double> v(static_cast<std::size_t>(io::flat_size(specs)));
    const auto noise = random_doubles(v.size(), seed, 0.1);
    index_t at = 0;
    for (auto& s : specs) {
      random_parameter_values(v.data() + at, s, seed + static_cast<std::uint64_t>(at), 0.5);
      const bool pose_out = s.name.rfind("camera_head.pose_branch.fc2.", 0) == 0;
      for (index_t i = 0; i < io::spec_numel(s); ++i) v[at + i] = (pose_out ? 0.1 : 1.0) * (v[at + i] + noise[at + i]);
      if (s.name == "camera_head.pose_branch.fc2.bias") v[at + 6] += 0.5, v[at + 7] += 0.6, v[at + 8] += 0.6;
      at += io::spec_numel(s);
    }
    params.assign(v.begin(), v.end());
    grads.assign(params.size(), T(0));
    io::add_flat_views(src, specs, params.data());
    w = load_vggt_weights(src, c);
    g = vggt_grads(w, params.data(), grads.data());
  }
  std::vector<testing::GradParam> grad_params() {
    std::vector<testing::GradParam> out;
    index_t at = 0;
    for (auto& s : specs) {
      const auto n = static_cast<std::size_t>(io::spec_numel(s));
      out.push_back({s.name, std::span<T>(params.data() + at, n), std::span<T>(grads.data() + at, n)});
      at += io::spec_numel(s);
    }
    return out;
  }
};

// Every differentiable output, flattened in a fixed order; `grads` views the same layout as VggtOutputGrads.
template <class T>
std::vector<const Tensor<T, 3>*> flat_outputs3(const VggtOutputs<T>& o) {
  return {&o.pose_enc, &o.extrinsics, &o.intrinsics, &o.depth, &o.depth_conf};
}
template <class T>
std::size_t output_size(const VggtOutputs<T>& o) {
  std::size_t n = o.world_points.size() + o.depth_features.size();
  for (auto* t : flat_outputs3(o)) n += t->size();
  return n;
}
template <class T>
void flatten(const VggtOutputs<T>& o, T* out) {
  for (auto* t : flat_outputs3(o)) out = std::copy(t->data(), t->data() + t->size(), out);
  out = std::copy(o.world_points.data(), o.world_points.data() + o.world_points.size(), out);
  std::copy(o.depth_features.data(), o.depth_features.data() + o.depth_features.size(), out);
}
template <class T>
VggtOutputGrads<T> unflatten_grads(const VggtOutputs<T>& o, const T* d) {
  VggtOutputGrads<T> g;
  const T** slots[] = {&g.pose_enc, &g.extrinsics, &g.intrinsics, &g.depth, &g.depth_conf};
  auto outs = flat_outputs3(o);
  for (std::size_t i = 0; i < outs.size(); ++i) *slots[i] = d, d += outs[i]->size();
  g.world_points = d;
  g.depth_features = d + o.world_points.size();
  return g;
}

// Element counts of a filled cache (what the training forward actually keeps).
template <class T>
std::size_t block_cache_size(const BlockCache<T>& k) {
  return k.x_in.size() + k.ln1_mean.size() + k.ln1_rstd.size() + k.qkv.size() + k.attended.size() + k.lse.size() +
         k.proj_out.size() + k.x_mid.size() + k.ln2_mean.size() + k.ln2_rstd.size() + k.hidden.size() + k.mlp_out.size();
}

// Gradient check of every differentiable output (flatten) against params, the camera head's fed-back encoding held
// at the unperturbed run's values (VGGT detaches it); d_images (may be null) receives the images' gradient.
testing::GradCheckResult check_outputs(const VggtConfig& c, FlatVggt<double>& m, std::vector<double>& images, index_t S,
                                       index_t H, index_t W, const std::vector<testing::GradParam>& params,
                                       double* d_images, const testing::GradCheckOptions& options) {
  VggtWorkspace<double> ws;
  VggtCache<double> cache;
  VggtBackwardScratch<double> scratch;
  VggtOptions features;
  features.keep_depth_features = true;
  auto first = vggt_forward_train<double>(images.data(), S, H, W, c, m.w, cache, ws, {}, features);
  const std::vector<double> feedback(cache.camera.raw.begin(),
                                     cache.camera.raw.begin() + (c.camera.iterations - 1) * S * pose_encoding_dim);
  VggtTrainOptions<double> train;
  train.camera_feedback = feedback.data();
  auto forward = [&](std::span<double> out) {
    VggtCache<double> k;
    flatten(vggt_forward_train<double>(images.data(), S, H, W, c, m.w, k, ws, train, features), out.data());
  };
  auto backward = [&](std::span<const double> d_out) {
    const auto o = vggt_forward_train<double>(images.data(), S, H, W, c, m.w, cache, ws, train, features);
    vggt_backward<double>(d_images, m.g, unflatten_grads(o, d_out.data()), o, cache, c, m.w, scratch);
  };
  return testing::check_gradients(params, output_size(first), forward, backward, options);
}

}  // namespace vggt_backward_test

using namespace vggt_backward_test;

TEST_CASE("VGGT end to end: images -> cameras, depth, confidence, world points, depth features, backward matches "
          "central differences for every parameter and the images (also through the depth head's image convolutions)",
          "[geometry][vggt][backward]") {
  VggtConfig c = tiny_vggt();
  const index_t depth_image_convs = GENERATE(0, 2);  // 2: the depth head also reads the pixels through two convolutions
  c.set_depth_image(depth_image_convs, 4);
  INFO("depth_image_convs " << depth_image_convs);
  FlatVggt<double> m(c, 3);
  const index_t S = 2, H = 4, W = 6;  // 2 x 3 patches: DINO's 3 x 3 position grid resized
  auto images = random_doubles(static_cast<std::size_t>(S * 3 * H * W), 4, 0.5);
  std::vector<double> d_images(images.size());
  auto params = m.grad_params();
  for (auto& p : params)
    if (p.name == "aggregator.patch_embed.mask_token") p.zero_reason = "stored, never read (nothing is masked)";
  params.push_back({"images", images, d_images});
  testing::GradCheckOptions options;
  options.max_checks_per_param = 2;  // ~100 tensors, each reached; every op has its own full check
  auto result = check_outputs(c, m, images, S, H, W, params, d_images.data(), options);
  INFO(result.summary());
  CHECK(result.ok());
}

TEST_CASE("VGGT point and match heads: outputs as in inference, backward matches central differences for both heads, "
          "the trunk and the images (also through the match head's image input and its convolutions)",
          "[geometry][vggt][backward]") {
  VggtConfig c = tiny_vggt();
  c.point_head = true;
  c.match_dim = 3;
  // 1: the match head's output_conv2 also reads the image's pixels; 2: through two image convolutions first.
  const int image_mode = GENERATE(0, 1, 2);
  c.match_image = image_mode > 0;
  c.match_image_convs = image_mode == 2 ? 2 : 0;
  c.match_image_width = 4;
  INFO("match_image " << c.match_image << ", match_image_convs " << c.match_image_convs);
  FlatVggt<double> m(c, 5);
  // Output logits near 0.1, where inv_log (sign(x)(exp|x| - 1)) is tame, as a trained head's are: at the random scale
  // they reach the exponential's steep end and central differences of step 1e-6 lose their last digits.
  for (auto& p : m.grad_params())
    if (p.name.rfind("point_head.scratch.output_conv2.2.", 0) == 0)
      for (double& v : p.value) v *= 0.1;
  const index_t S = 2, H = 4, W = 6;
  auto images = random_doubles(static_cast<std::size_t>(S * 3 * H * W), 6, 0.5);
  std::vector<double> d_images(images.size());
  VggtWorkspace<double> ws;
  VggtCache<double> cache;
  VggtBackwardScratch<double> scratch;
  const auto inference = vggt_forward<double>(images.data(), S, H, W, c, m.w, ws);
  const auto first = vggt_forward_train<double>(images.data(), S, H, W, c, m.w, cache, ws);
  REQUIRE(first.points.size() == S * H * W * 3);
  REQUIRE(first.points_conf.size() == S * H * W);
  REQUIRE(first.descriptors.size() == S * H * W * 3);
  REQUIRE(first.foreground.size() == S * H * W);
  auto outputs = [](const VggtOutputs<double>& o) {
    return std::vector<const double*>{o.points.data(), o.points_conf.data(), o.descriptors.data(), o.foreground.data()};
  };
  const std::vector<index_t> sizes{S * H * W * 3, S * H * W, S * H * W * 3, S * H * W};
  for (std::size_t t = 0; t < sizes.size(); ++t)
    for (index_t i = 0; i < sizes[t]; ++i) REQUIRE(outputs(first)[t][i] == outputs(inference)[t][i]);
  for (index_t i = 0; i < S * H * W; ++i) {
    REQUIRE(first.points_conf.data()[i] > 1.0);
    REQUIRE(first.foreground.data()[i] > 0.0);
    REQUIRE(first.foreground.data()[i] < 1.0);
  }
  std::size_t n_out = 0;
  for (index_t n : sizes) n_out += static_cast<std::size_t>(n);
  auto forward = [&](std::span<double> out) {
    VggtCache<double> k;
    const auto o = vggt_forward_train<double>(images.data(), S, H, W, c, m.w, k, ws);
    double* at = out.data();
    for (std::size_t t = 0; t < sizes.size(); ++t) at = std::copy(outputs(o)[t], outputs(o)[t] + sizes[t], at);
  };
  auto backward = [&](std::span<const double> d_out) {
    const auto o = vggt_forward_train<double>(images.data(), S, H, W, c, m.w, cache, ws);
    VggtOutputGrads<double> d;
    const double* at = d_out.data();
    d.points = at, at += sizes[0];
    d.points_conf = at, at += sizes[1];
    d.descriptors = at, at += sizes[2];
    d.foreground = at;
    vggt_backward<double>(d_images.data(), m.g, d, o, cache, c, m.w, scratch);
  };
  std::vector<testing::GradParam> params;
  for (auto& p : m.grad_params())
    if ((p.name.rfind("point_head.", 0) == 0 || p.name.rfind("match_head.", 0) == 0 ||
         p.name.rfind("aggregator.", 0) == 0) && p.name != "aggregator.patch_embed.mask_token")
      params.push_back(p);
  params.push_back({"images", images, d_images});
  testing::GradCheckOptions options;
  options.max_checks_per_param = 2;
  auto result = testing::check_gradients(params, n_out, forward, backward, options);
  INFO(result.summary());
  CHECK(result.ok());
  // The camera and depth heads receive nothing from these outputs.
  for (auto& p : m.grad_params())
    if (p.name.rfind("depth_head.", 0) == 0 || p.name.rfind("camera_head.", 0) == 0)
      for (double g : p.grad) REQUIRE(g == 0.0);
}

TEST_CASE("VGGT frame_tokens: 2 leaves frames after the first order-free, 3 tells frame 2 from frame 1 and shares "
          "the last set with frame 3, and the token gradients match central differences",
          "[geometry][vggt][backward]") {
  const index_t S = 4, H = 4, W = 6;
  auto one = random_doubles(static_cast<std::size_t>(3 * H * W), 9, 0.5);
  std::vector<double> images;
  for (index_t s = 0; s < S; ++s) images.insert(images.end(), one.begin(), one.end());  // four identical frames
  VggtWorkspace<double> ws;
  auto pose = [&](const VggtConfig& c, FlatVggt<double>& m) {
    return vggt_forward<double>(images.data(), S, H, W, c, m.w, ws).pose_enc;
  };
  auto frame_pose = [](const Tensor<double, 3>& p, index_t s) {
    return std::vector<double>(p.data() + s * pose_encoding_dim, p.data() + (s + 1) * pose_encoding_dim);
  };
  VggtConfig vggt = tiny_vggt();
  FlatVggt<double> m2(vggt, 11);
  const auto p2 = pose(vggt, m2);
  CHECK(frame_pose(p2, 1) == frame_pose(p2, 2));
  CHECK(frame_pose(p2, 1) == frame_pose(p2, 3));
  CHECK(frame_pose(p2, 0) != frame_pose(p2, 1));

  VggtConfig ordered = tiny_vggt();
  ordered.aggregator.frame_tokens = 3;
  FlatVggt<double> m3(ordered, 11);
  const auto p3 = pose(ordered, m3);
  CHECK(frame_pose(p3, 1) != frame_pose(p3, 2));
  CHECK(frame_pose(p3, 2) == frame_pose(p3, 3));

  VggtCache<double> cache;
  VggtBackwardScratch<double> scratch;
  auto first = vggt_forward_train<double>(images.data(), S, H, W, ordered, m3.w, cache, ws);
  const std::vector<double> feedback(cache.camera.raw.begin(),
                                     cache.camera.raw.begin() + (ordered.camera.iterations - 1) * S * pose_encoding_dim);
  VggtTrainOptions<double> train;
  train.camera_feedback = feedback.data();
  auto forward = [&](std::span<double> out) {
    VggtCache<double> k;
    const auto o = vggt_forward_train<double>(images.data(), S, H, W, ordered, m3.w, k, ws, train);
    std::copy(o.pose_enc.data(), o.pose_enc.data() + o.pose_enc.size(), out.data());
  };
  auto backward = [&](std::span<const double> d_out) {
    const auto o = vggt_forward_train<double>(images.data(), S, H, W, ordered, m3.w, cache, ws, train);
    VggtOutputGrads<double> d;
    d.pose_enc = d_out.data();
    vggt_backward<double>(nullptr, m3.g, d, o, cache, ordered, m3.w, scratch);
  };
  std::vector<testing::GradParam> tokens;
  for (auto& p : m3.grad_params())
    if (p.name == "aggregator.camera_token" || p.name == "aggregator.register_token") tokens.push_back(p);
  REQUIRE(tokens.size() == 2);
  auto result = testing::check_gradients(tokens, static_cast<std::size_t>(first.pose_enc.size()), forward, backward);
  INFO(result.summary());
  CHECK(result.ok());
}

TEST_CASE("VGGT training forward equals inference, recompute gives bit-identical gradients, aggregator-output "
          "gradients alone reach the trunk",
          "[geometry][vggt][backward]") {
  const VggtConfig c = tiny_vggt();
  FlatVggt<float> m(c, 5);
  const index_t S = 3, H = 6, W = 4;
  auto id = random_doubles(static_cast<std::size_t>(S * 3 * H * W), 6, 0.5);
  const std::vector<float> images(id.begin(), id.end());
  VggtWorkspace<float> ws;
  VggtOptions inference;
  inference.keep_depth_features = true;
  const auto ref = vggt_forward<float>(images.data(), S, H, W, c, m.w, ws, inference);
  std::vector<float> d_flat;
  std::vector<std::vector<float>> grads, d_img;
  for (bool recompute : {false, true}) {
    VggtCache<float> cache;
    VggtBackwardScratch<float> scratch;
    VggtTrainOptions<float> train;
    train.recompute = recompute;
    const auto o = vggt_forward_train<float>(images.data(), S, H, W, c, m.w, cache, ws, train, inference);
    std::vector<float> a(output_size(o)), b(output_size(ref));
    flatten(o, a.data());
    flatten(ref, b.data());
    CHECK(a == b);
    if (d_flat.empty()) {
      auto dd = random_doubles(a.size(), 7);
      d_flat.assign(dd.begin(), dd.end());
    }
    std::vector<float> g(m.params.size(), 0.5f), di(images.size(), -2.0f);
    vggt_backward<float>(di.data(), vggt_grads(m.w, m.params.data(), g.data()), unflatten_grads(o, d_flat.data()), o,
                         cache, c, m.w, scratch);
    grads.push_back(g);
    d_img.push_back(di);
  }
  CHECK(grads[0] == grads[1]);
  CHECK(d_img[0] == d_img[1]);

  // Upstream gradients for the heads' inputs only: the trunk's parameters receive gradient, the heads' do not.
  VggtCache<float> cache;
  VggtBackwardScratch<float> scratch;
  const auto o = vggt_forward_train<float>(images.data(), S, H, W, c, m.w, cache, ws);
  const index_t layer_size = S * o.aggregator.tokens * 2 * c.aggregator.embed_dim;
  auto dl = random_doubles(static_cast<std::size_t>(layer_size), 8);
  const std::vector<float> d_layer(dl.begin(), dl.end());
  std::vector<const float*> d_layers{nullptr, d_layer.data()};
  VggtOutputGrads<float> d_out;
  d_out.layers = d_layers;
  std::vector<float> g(m.params.size(), 0.0f);
  vggt_backward<float>(nullptr, vggt_grads(m.w, m.params.data(), g.data()), d_out, o, cache, c, m.w, scratch);
  index_t at = 0;
  bool trunk_nonzero = false, heads_zero = true;
  for (auto& s : m.specs) {
    const bool head = s.name.rfind("camera_head.", 0) == 0 || s.name.rfind("depth_head.", 0) == 0;
    for (index_t i = 0; i < io::spec_numel(s); ++i) {
      if (head && g[at + i] != 0.0f) heads_zero = false;
      if (!head && g[at + i] != 0.0f) trunk_nonzero = true;
    }
    at += io::spec_numel(s);
  }
  CHECK(trunk_nonzero);
  CHECK(heads_zero);
}

TEST_CASE("VGGT activation memory: the formula equals the tiny training caches, table at VGGT-1B",
          "[geometry][vggt][backward][memory]") {
  const VggtConfig c = tiny_vggt();
  FlatVggt<float> m(c, 9);
  const index_t S = 4, H = 8, W = 8;
  auto id = random_doubles(static_cast<std::size_t>(S * 3 * H * W), 10, 0.5);
  const std::vector<float> images(id.begin(), id.end());
  VggtWorkspace<float> ws;
  for (bool recompute : {false, true}) {
    VggtCache<float> k;
    VggtTrainOptions<float> train;
    train.recompute = recompute;
    const auto o = vggt_forward_train<float>(images.data(), S, H, W, c, m.w, k, ws, train);
    std::size_t dino = k.dino.patches.size() + k.dino.x_final.size() + k.dino.norm_mean.size() + k.dino.norm_rstd.size();
    for (auto& b : k.dino.blocks) dino += block_cache_size(b);
    std::size_t agg = 0;
    for (auto& b : k.aggregator.frame_blocks) agg += block_cache_size(b);
    for (auto& b : k.aggregator.global_blocks) agg += block_cache_size(b);
    std::size_t layers = static_cast<std::size_t>(S * (H / 2) * (W / 2) * c.aggregator.embed_dim);  // DINO tokens
    for (auto& [i, t] : o.aggregator.layers) layers += t.size();
    const auto bytes = vggt_activation_bytes<float>(c, S, H, W, recompute);
    CHECK(bytes.dino == dino * sizeof(float));
    CHECK(bytes.aggregator == agg * sizeof(float));
    CHECK(bytes.layers == layers * sizeof(float));
    CHECK(bytes.camera == static_cast<std::size_t>(camera_head_cache_elements(c.camera, S, recompute)) * sizeof(float));
  }

  struct Row {
    const char* name;
    VggtConfig c;
    index_t frames, size;
  };
  const Row rows[] = {{"tiny (this file)", c, 4, 8}, {"VGGT-1B", VggtConfig{}, 4, 252}, {"VGGT-1B", VggtConfig{}, 4, 518}};
  std::printf("| model | views | image | recompute | DINO | aggregator | tokens + kept outputs | trunk | camera head | "
              "DPT head | total |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|---|---|\n");
  for (const auto& r : rows)
    for (bool recompute : {false, true}) {
      const auto b = vggt_activation_bytes<float>(r.c, r.frames, r.size, r.size, recompute);
      auto mib = [](std::size_t v) { return static_cast<double>(v) / (1024.0 * 1024.0); };  // MiB
      std::printf("| %s | %lld | %lld^2 | %s | %.3f | %.3f | %.3f | %.3f | %.3f | %.3f | %.3f |\n", r.name,
                  static_cast<long long>(r.frames), static_cast<long long>(r.size), recompute ? "on" : "off",
                  mib(b.dino), mib(b.aggregator), mib(b.layers), mib(b.trunk()), mib(b.camera), mib(b.depth),
                  mib(b.total()));
      if (recompute) CHECK(b.total() < vggt_activation_bytes<float>(r.c, r.frames, r.size, r.size, false).total());
    }
}

TEST_CASE("VGGT frame_tokens 1: every frame alike, the cameras re-expressed in the first frame's, reordering the frames "
          "reorders the decoded cameras and depth, and the gradient through the re-expression matches central "
          "differences",
          "[geometry][vggt][backward][permutation]") {
  VggtConfig c = tiny_vggt();
  c.aggregator.frame_tokens = 1;
  FlatVggt<double> m(c, 17);
  const index_t S = 3, H = 4, W = 6, plane = 3 * H * W, px = H * W;
  auto images = random_doubles(static_cast<std::size_t>(S * plane), 18, 0.5);
  const index_t order[S] = {2, 0, 1};
  std::vector<double> permuted(images.size());
  for (index_t s = 0; s < S; ++s)
    std::copy(images.begin() + order[s] * plane, images.begin() + (order[s] + 1) * plane, permuted.begin() + s * plane);
  VggtWorkspace<double> ws;
  const auto a = vggt_forward<double>(images.data(), S, H, W, c, m.w, ws);
  const auto b = vggt_forward<double>(permuted.data(), S, H, W, c, m.w, ws);
  REQUIRE(a.head_extrinsics.size() == S * 12);
  for (int k = 0; k < 12; ++k) CHECK(a.extrinsics.data()[k] == identity_w2c[k]);
  for (index_t s = 0; s < S; ++s) {
    CAPTURE(s);
    for (int k = 0; k < 12; ++k)
      CHECK(b.head_extrinsics.data()[12 * s + k] == Approx(a.head_extrinsics.data()[12 * order[s] + k]).margin(1e-12));
    for (index_t p = 0; p < px; ++p)
      CHECK(b.depth.data()[s * px + p] == Approx(a.depth.data()[order[s] * px + p]).margin(1e-12));
    for (index_t u = 0; u < S; ++u) {
      double ra[12], rb[12];
      relative_w2c(rb, b.extrinsics.data() + 12 * s, b.extrinsics.data() + 12 * u);
      relative_w2c(ra, a.extrinsics.data() + 12 * order[s], a.extrinsics.data() + 12 * order[u]);
      for (int k = 0; k < 12; ++k) CHECK(rb[k] == Approx(ra[k]).margin(1e-12));
    }
  }
  // Not the identity for the other frames: the head's cameras differ between frames with different pictures.
  double off = 0;
  for (int k = 0; k < 12; ++k) off = std::max(off, std::abs(a.extrinsics.data()[12 + k] - identity_w2c[k]));
  CHECK(off > 1e-3);

  std::vector<testing::GradParam> head;
  for (auto& p : m.grad_params())
    if (p.name.rfind("camera_head.", 0) == 0 || p.name == "aggregator.camera_token") head.push_back(p);
  testing::GradCheckOptions options;
  options.max_checks_per_param = 3;
  auto result = check_outputs(c, m, images, S, H, W, head, nullptr, options);
  INFO(result.summary());
  CHECK(result.ok());
}
