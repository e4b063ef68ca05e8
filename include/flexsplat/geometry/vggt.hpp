#pragma once
// End-to-end VGGT forward for FlexSplat: images [S, 3, H, W] in [0, 1] -> ImageNet normalisation -> DINOv2 patch
// tokens -> alternating-attention aggregator -> camera head (pose encodings per refinement iteration, decoded to
// world-to-camera extrinsics and intrinsics) and DPT depth head (depth, confidence, depth features) -> world points.
// vggt_forward_train / vggt_backward: the same chain for training, gradients from any output to every parameter.
#include <algorithm>
#include <cmath>
#include <functional>
#include <optional>
#include <set>
#include <span>
#include <string>
#include <vector>

#include "flexsplat/core/camera.hpp"
#include "flexsplat/core/profile.hpp"
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/geometry/aggregator.hpp"
#include "flexsplat/geometry/camera_head.hpp"
#include "flexsplat/geometry/config.hpp"
#include "flexsplat/geometry/dino.hpp"
#include "flexsplat/geometry/dpt_head.hpp"
#include "flexsplat/geometry/pose_encoding.hpp"
#include "flexsplat/geometry/unproject.hpp"
#include "flexsplat/geometry/weights.hpp"

namespace flexsplat {
inline namespace v0 {
namespace geometry {

template <class T>
struct VggtOutputs {
  Tensor<T, 3> pose_enc;      // [iterations, S, 9] (absT_quaR_FoV, quaternion xyzw); the last is the prediction
  Tensor<T, 3> extrinsics;    // [S, 3, 4] world-to-camera (OpenCV), the first view's camera the identity
  // [S, 3, 4] the cameras as decoded, in the frame the head chose, when frame_tokens is 1 (`extrinsics` is then each
  // camera re-expressed in the first view's frame); empty otherwise.
  Tensor<T, 3> head_extrinsics;
  Tensor<T, 3> intrinsics;    // [S, 3, 3]
  Tensor<T, 3> depth;         // [S, H, W]
  Tensor<T, 3> depth_conf;    // [S, H, W]
  Tensor<T, 4> world_points;  // [S, H, W, 3]
  Tensor<T, 4> points;        // [S, H, W, 3] the point head's map in the first frame's camera frame (point_head)
  Tensor<T, 3> points_conf;   // [S, H, W] its confidence (point_head)
  Tensor<T, 4> descriptors;   // [S, H, W, match_dim] the match head's per-pixel descriptors (match_dim > 0)
  Tensor<T, 3> foreground;    // [S, H, W] its probability that the pixel shows the object (match_dim > 0)
  Tensor<T, 4> depth_features;  // [S, features/2, H, W] the DPT map the decoder's fusion reads (keep_depth_features)
  Tensor<T, 3> dino_tokens;   // [S, P, C] when VggtOptions::keep_dino_tokens
  AggregatorOutputs<T> aggregator;  // the layers the heads read (all when VggtOptions::keep_all_layers)
};

struct VggtOptions {
  bool keep_dino_tokens = false;
  bool keep_all_layers = false;
  bool keep_depth_features = false;
  // Called with a stage name ("dino", "aggregator", "camera_head", "depth_head", "point_head", "match_head",
  // "unproject") and its progress:
  // step of steps (aggregator: per block pair).
  std::function<void(const std::string&, index_t, index_t)> progress;
};

template <class T>
struct VggtWorkspace {
  std::vector<T, AlignedAllocator<T>> normalized, head;
  DinoWorkspace<T> dino;
  AggregatorWorkspace<T> aggregator;
};

// Training options: recompute makes every transformer block (DINO, aggregator, camera trunk) keep only its input and
// rerun its forward in backward. camera_feedback (optional, [iterations - 1, S, 9]) replaces the camera head's own
// detached feedback encodings (a gradient check holds them fixed, as VGGT's detach does for the gradient).
template <class T>
struct VggtTrainOptions {
  bool recompute = false;
  const T* camera_feedback = nullptr;
};

// What vggt_backward reads besides the forward's outputs (which it takes again).
template <class T>
struct VggtCache {
  index_t frames = 0, image_h = 0, image_w = 0;
  DinoCache<T> dino;
  AggregatorCache<T> aggregator;
  CameraHeadCache<T> camera;
  DptHeadCache<T> depth;
  DptHeadCache<T> point;
  DptHeadCache<T> match;
};

// Gradient slots mirroring VggtWeights.
template <class T>
struct VggtGrads {
  DinoGrads<T> dino;
  AggregatorGrads<T> aggregator;
  CameraHeadGrads<T> camera;
  DptHeadGrads<T> depth;
  DptHeadGrads<T> point;  // empty unless the config has the point head
  DptHeadGrads<T> match;  // empty unless the config has the match head
};

// Gradients of weights bound into one flat parameter block (e.g. a ParamStore's), at the same offsets in grads_base.
template <class T>
VggtGrads<T> vggt_grads(const VggtWeights<T>& w, const T* params_base, T* grads_base) {
  VggtGrads<T> g;
  g.dino = dino_grads(w.dino, params_base, grads_base);
  g.aggregator = aggregator_grads(w.aggregator, params_base, grads_base);
  g.camera = camera_head_grads(w.camera, params_base, grads_base);
  g.depth = dpt_head_grads(w.depth, params_base, grads_base);
  if (w.point.norm_weight) g.point = dpt_head_grads(w.point, params_base, grads_base);
  if (w.match.norm_weight) g.match = dpt_head_grads(w.match, params_base, grads_base);
  return g;
}

// Gradients with respect to VggtOutputs; every pointer may be null (no gradient from that output). layers (empty or
// one entry per aggregator output, null where none) adds gradients straight into the aggregator outputs.
template <class T>
struct VggtOutputGrads {
  const T* pose_enc = nullptr;        // [iterations, S, 9]
  const T* extrinsics = nullptr;      // [S, 3, 4]
  const T* intrinsics = nullptr;      // [S, 3, 3]
  const T* depth = nullptr;           // [S, H, W]
  const T* depth_conf = nullptr;      // [S, H, W]
  const T* world_points = nullptr;    // [S, H, W, 3]
  const T* depth_features = nullptr;  // [S, features/2, H, W]
  const T* points = nullptr;          // [S, H, W, 3]
  const T* points_conf = nullptr;     // [S, H, W]
  const T* descriptors = nullptr;     // [S, H, W, match_dim]
  const T* foreground = nullptr;      // [S, H, W]
  std::span<const T* const> layers;   // [S, tokens, 2C] by aggregator output index
};

// Activation memory of one training forward (what lives until backward), in bytes of T.
struct VggtActivationBytes {
  std::size_t dino = 0;        // DINO block caches, patch rows, final-norm input
  std::size_t aggregator = 0;  // aggregator block caches
  std::size_t layers = 0;      // DINO tokens and the aggregator outputs the heads read
  std::size_t camera = 0;      // camera head cache
  std::size_t depth = 0;       // DPT head cache
  std::size_t point = 0;       // point head cache (point_head)
  std::size_t match = 0;       // match head cache (match_dim > 0)
  std::size_t trunk() const { return dino + aggregator + layers; }
  std::size_t total() const { return trunk() + camera + depth + point + match; }
};

// Activation memory of vggt_forward_train for `frames` images of image_h x image_w (outputs and backward scratch
// excluded).
template <class T = float>
VggtActivationBytes vggt_activation_bytes(const VggtConfig& c, index_t frames, index_t image_h, index_t image_w,
                                          bool recompute) {
  const auto& a = c.aggregator;
  const index_t gh = image_h / a.patch_size, gw = image_w / a.patch_size, P = gh * gw, N = a.patch_start_idx() + P;
  std::set<index_t> kept(c.depth.intermediate_layer_idx.begin(), c.depth.intermediate_layer_idx.end());
  kept.insert(a.depth - 1);
  auto bytes = [](index_t elements) { return static_cast<std::size_t>(elements) * sizeof(T); };
  VggtActivationBytes b;
  b.dino = bytes(dino_cache_elements(a.dino, frames, image_h, image_w, recompute));
  b.aggregator = bytes(aggregator_cache_elements(a, frames, gh, gw, recompute));
  b.layers = bytes(frames * P * a.embed_dim + static_cast<index_t>(kept.size()) * frames * N * 2 * a.embed_dim);
  b.camera = bytes(camera_head_cache_elements(c.camera, frames, recompute));
  b.depth = bytes(dpt_head_cache_elements(c.depth, gh, gw, frames));
  if (c.point_head) b.point = bytes(dpt_head_cache_elements(c.point(), gh, gw, frames));
  if (c.match_dim > 0) b.match = bytes(dpt_head_cache_elements(c.match(), gh, gw, frames));
  return b;
}

namespace detail {
// One forward for inference (cache null) and training.
template <class T>
VggtOutputs<T> vggt_forward_impl(const T* images, index_t frames, index_t image_h, index_t image_w, const VggtConfig& c,
                                 const VggtWeights<T>& w, VggtWorkspace<T>& ws, const VggtOptions& options,
                                 VggtCache<T>* cache, const VggtTrainOptions<T>& train) {
  c.validate();
  const index_t p = c.aggregator.patch_size, C = c.aggregator.embed_dim;
  require(frames >= 1, "VGGT: needs at least one image, got ", frames);
  require(image_h >= p && image_w >= p && image_h % p == 0 && image_w % p == 0, "VGGT: image size ", image_h, " x ",
          image_w, " must be a positive multiple of the patch size ", p, " (preprocess the images first)");
  const index_t n = frames * 3 * image_h * image_w;
  const index_t plane = image_h * image_w;
  for (index_t i = 0; i < n; ++i)
    if (!std::isfinite(static_cast<double>(images[i])))
      fail("VGGT: input image ", i / (3 * plane), " has a non-finite value ", static_cast<double>(images[i]),
           " at channel ", i / plane % 3, ", row ", i % plane / image_w, ", column ", i % image_w);
  auto report = [&](const char* stage, index_t step, index_t steps) {
    if (options.progress) options.progress(stage, step, steps);
  };
  const index_t gh = image_h / p, gw = image_w / p, P = gh * gw;
  VggtOutputs<T> out;
  if (cache) cache->frames = frames, cache->image_h = image_h, cache->image_w = image_w;

  {
    const profile::Stage stage("dino");
    report("dino", 0, 1);
    ws.normalized.resize(static_cast<std::size_t>(n));
    imagenet_normalize(ws.normalized.data(), images, frames, image_h, image_w);
    out.dino_tokens.resize(Shape<3>{frames, P, C});
    if (cache)
      dino_forward_train(out.dino_tokens.data(), ws.normalized.data(), frames, image_h, image_w, c.aggregator.dino, w.dino,
                         cache->dino, train.recompute, ws.dino);
    else
      dino_forward(out.dino_tokens.data(), ws.normalized.data(), frames, image_h, image_w, c.aggregator.dino, w.dino,
                   ws.dino);
    report("dino", 1, 1);
  }

  std::set<index_t> keep(c.depth.intermediate_layer_idx.begin(), c.depth.intermediate_layer_idx.end());
  keep.insert(c.aggregator.depth - 1);  // the camera head reads the last layer
  std::vector<index_t> keep_list(keep.begin(), keep.end());
  if (options.keep_all_layers) keep_list.clear();
  auto progress = [&](index_t step, index_t steps) { report("aggregator", step + 1, steps); };
  std::optional<profile::Stage> aggregator_stage(std::in_place, "aggregator");
  out.aggregator = cache ? aggregator_trunk_forward_train<T>(out.dino_tokens.data(), frames, gh, gw, c.aggregator,
                                                             w.aggregator, keep_list, cache->aggregator, train.recompute,
                                                             ws.aggregator, progress)
                         : aggregator_trunk_forward<T>(out.dino_tokens.data(), frames, gh, gw, c.aggregator,
                                                       w.aggregator, keep_list, ws.aggregator, progress);
  aggregator_stage.reset();
  if (!options.keep_dino_tokens) out.dino_tokens = Tensor<T, 3>();
  const index_t N = out.aggregator.tokens;

  {
    const profile::Stage stage("camera head");
    report("camera_head", 0, 1);
    ws.head.resize(static_cast<std::size_t>(camera_head_workspace_size(c.camera, frames)));
    out.pose_enc.resize(Shape<3>{c.camera.iterations, frames, pose_encoding_dim});
    const T* last = out.aggregator.at(c.aggregator.depth - 1).data();
    std::span<T> head_ws(ws.head.data(), ws.head.size());
    if (cache)
      camera_head_forward_train<T>(out.pose_enc.data(), cache->camera, c.camera, w.camera, last, frames, N, head_ws,
                                   train.recompute, train.camera_feedback);
    else
      camera_head_forward<T>(out.pose_enc.data(), c.camera, w.camera, last, frames, N, head_ws);
    out.extrinsics.resize(Shape<3>{frames, 3, 4});
    out.intrinsics.resize(Shape<3>{frames, 3, 3});
    pose_encoding_to_extri_intri<T>(out.extrinsics.data(), out.intrinsics.data(),
                                    out.pose_enc.data() + (c.camera.iterations - 1) * frames * pose_encoding_dim, frames,
                                    image_h, image_w, c.pose_decode);
    if (c.aggregator.frame_tokens == 1) {
      // Reference-free: no frame is told it is the first, so the first view's frame is chosen here.
      out.head_extrinsics = out.extrinsics;
      const T* raw = out.head_extrinsics.data();
      std::copy(identity_w2c, identity_w2c + 12, out.extrinsics.data());
      for (index_t v = 1; v < frames; ++v) relative_w2c(out.extrinsics.data() + 12 * v, raw + 12 * v, raw);
    }
    report("camera_head", 1, 1);
  }

  std::optional<profile::Stage> depth_stage(std::in_place, "depth head");
  report("depth_head", 0, 1);
  std::vector<const T*> layers(static_cast<std::size_t>(c.aggregator.depth), nullptr);
  for (auto& [index, tensor] : out.aggregator.layers) layers[static_cast<std::size_t>(index)] = tensor.data();
  ws.head.resize(static_cast<std::size_t>(dpt_head_workspace_size(c.depth, gh, gw)));
  out.depth.resize(Shape<3>{frames, image_h, image_w});
  out.depth_conf.resize(Shape<3>{frames, image_h, image_w});
  DptHeadOutputs<T> dpt_out;
  dpt_out.preds = out.depth.data();
  dpt_out.conf = out.depth_conf.data();
  if (options.keep_depth_features) {
    out.depth_features.resize(Shape<4>{frames, c.depth.head_features(), image_h, image_w});
    dpt_out.features = out.depth_features.data();
  }
  const std::span<const T* const> layer_span(layers.data(), layers.size());
  if (cache)
    dpt_head_forward_train<T>(dpt_out, cache->depth, c.depth, w.depth, layer_span, frames, N,
                              out.aggregator.patch_start_idx, image_h, image_w,
                              std::span<T>(ws.head.data(), ws.head.size()), images);
  else
    dpt_head_forward<T>(dpt_out, c.depth, w.depth, layer_span, frames, N, out.aggregator.patch_start_idx, image_h,
                        image_w, std::span<T>(ws.head.data(), ws.head.size()), images);
  report("depth_head", 1, 1);
  depth_stage.reset();

  // The optional heads read the same layers: preds [frames, H, W, channels] and a per-pixel map.
  auto extra_head = [&](const char* name, const DptHeadConfig& hc, const DptHeadWeights<T>& hw, DptHeadCache<T>* hk,
                        Tensor<T, 4>& preds, Tensor<T, 3>& map) {
    const profile::Stage stage(name);
    report(name, 0, 1);
    ws.head.resize(static_cast<std::size_t>(dpt_head_workspace_size(hc, gh, gw)));
    preds.resize(Shape<4>{frames, image_h, image_w, hc.output_dim - 1});
    map.resize(Shape<3>{frames, image_h, image_w});
    DptHeadOutputs<T> o;
    o.preds = preds.data();
    o.conf = map.data();
    if (hk)
      dpt_head_forward_train<T>(o, *hk, hc, hw, layer_span, frames, N, out.aggregator.patch_start_idx, image_h, image_w,
                                std::span<T>(ws.head.data(), ws.head.size()), images);
    else
      dpt_head_forward<T>(o, hc, hw, layer_span, frames, N, out.aggregator.patch_start_idx, image_h, image_w,
                          std::span<T>(ws.head.data(), ws.head.size()), images);
    report(name, 1, 1);
  };
  if (c.point_head)
    extra_head("point_head", c.point(), w.point, cache ? &cache->point : nullptr, out.points, out.points_conf);
  if (c.match_dim > 0)
    extra_head("match_head", c.match(), w.match, cache ? &cache->match : nullptr, out.descriptors, out.foreground);

  {
    const profile::Stage stage("unproject");
    report("unproject", 0, 1);
    out.world_points.resize(Shape<4>{frames, image_h, image_w, 3});
    unproject_depth_forward<T>(out.world_points.data(), out.depth.data(), out.extrinsics.data(), out.intrinsics.data(),
                               frames, image_h, image_w);
    report("unproject", 1, 1);
  }
  return out;
}
}  // namespace detail

template <class T>
VggtOutputs<T> vggt_forward(const T* images, index_t frames, index_t image_h, index_t image_w, const VggtConfig& c,
                            const VggtWeights<T>& w, VggtWorkspace<T>& ws, const VggtOptions& options = {}) {
  return detail::vggt_forward_impl<T>(images, frames, image_h, image_w, c, w, ws, options, nullptr, {});
}

// vggt_forward (same outputs bit for bit) that fills `cache` for vggt_backward.
template <class T>
VggtOutputs<T> vggt_forward_train(const T* images, index_t frames, index_t image_h, index_t image_w, const VggtConfig& c,
                                  const VggtWeights<T>& w, VggtCache<T>& cache, VggtWorkspace<T>& ws,
                                  const VggtTrainOptions<T>& train = {}, const VggtOptions& options = {}) {
  return detail::vggt_forward_impl<T>(images, frames, image_h, image_w, c, w, ws, options, &cache, train);
}

template <class T>
struct VggtBackwardScratch {
  std::vector<T, AlignedAllocator<T>> d_depth, d_extrinsics, d_head_extrinsics, d_intrinsics, d_pose_enc, d_dino,
      d_normalized;
  std::vector<std::vector<T, AlignedAllocator<T>>> d_layers;
  DinoBackwardScratch<T> dino;
  AggregatorBackwardScratch<T> aggregator;
};

// Backward of vggt_forward_train: world points -> depth and cameras, cameras -> pose encoding -> camera head, depth,
// confidence and depth features -> DPT head, points / descriptors and their maps -> point / match head, the heads ->
// aggregator outputs -> aggregator -> DINO. Adds (+=) into the parameter gradients g (null slots skipped) and, when
// not null, into d_images [S, 3, H, W]. `out` is the forward's result, unchanged. The camera head's fed-back
// encodings carry no gradient (VGGT detaches them).
template <class T>
void vggt_backward(T* d_images, const VggtGrads<T>& g, const VggtOutputGrads<T>& d_out, const VggtOutputs<T>& out,
                   VggtCache<T>& cache, const VggtConfig& c, const VggtWeights<T>& w, VggtBackwardScratch<T>& scratch) {
  c.validate();
  const index_t S = cache.frames, H = cache.image_h, W = cache.image_w, E = pose_encoding_dim, I = c.camera.iterations;
  const index_t depth = c.aggregator.depth, C = c.aggregator.embed_dim;
  require(S >= 1 && out.depth.size() == S * H * W && out.pose_enc.size() == I * S * E,
          "VGGT backward: the cache and outputs do not come from one vggt_forward_train call");
  require(d_out.layers.empty() || static_cast<index_t>(d_out.layers.size()) == depth, "VGGT backward: ",
          d_out.layers.size(), " aggregator output gradients for depth ", depth);
  const index_t N = out.aggregator.tokens, P = (H / c.aggregator.patch_size) * (W / c.aggregator.patch_size);
  auto init = [](auto& v, index_t size, const T* from) {
    if (from) v.assign(from, from + size);
    else v.assign(static_cast<std::size_t>(size), T(0));
    return v.data();
  };

  // Unprojection and pose decoding.
  T* d_depth = init(scratch.d_depth, S * H * W, d_out.depth);
  T* d_extr = init(scratch.d_extrinsics, S * 12, d_out.extrinsics);
  T* d_intr = init(scratch.d_intrinsics, S * 9, d_out.intrinsics);
  if (d_out.world_points)
    unproject_depth_backward<T>(d_depth, d_extr, d_intr, d_out.world_points, out.depth.data(), out.extrinsics.data(),
                                out.intrinsics.data(), S, H, W);
  if (c.aggregator.frame_tokens == 1) {
    // Back through the re-expression in the first view's frame (the first camera is the constant identity).
    require(out.head_extrinsics.size() == S * 12, "VGGT backward: frame_tokens 1 without the decoded cameras");
    scratch.d_head_extrinsics.assign(static_cast<std::size_t>(S * 12), T(0));
    const T* raw = out.head_extrinsics.data();
    T* d_raw = scratch.d_head_extrinsics.data();
    for (index_t v = 1; v < S; ++v) relative_w2c_backward(d_raw + 12 * v, d_raw, d_extr + 12 * v, raw + 12 * v, raw);
    d_extr = d_raw;
  }
  T* d_pose = init(scratch.d_pose_enc, I * S * E, d_out.pose_enc);
  pose_encoding_to_extri_intri_backward<T>(d_pose + (I - 1) * S * E, d_extr, d_intr,
                                           out.pose_enc.data() + (I - 1) * S * E, S, H, W, c.pose_decode);

  // Heads -> gradients of the aggregator outputs they read.
  scratch.d_layers.resize(static_cast<std::size_t>(depth));
  std::vector<T*> d_layers(static_cast<std::size_t>(depth), nullptr);
  std::vector<const T*> layers(static_cast<std::size_t>(depth), nullptr);
  for (index_t i = 0; i < depth; ++i) {
    const auto it = out.aggregator.layers.find(i);
    const T* given = d_out.layers.empty() ? nullptr : d_out.layers[static_cast<std::size_t>(i)];
    if (it == out.aggregator.layers.end() && !given) continue;
    d_layers[static_cast<std::size_t>(i)] = init(scratch.d_layers[static_cast<std::size_t>(i)], S * N * 2 * C, given);
    if (it != out.aggregator.layers.end()) layers[static_cast<std::size_t>(i)] = it->second.data();
  }
  camera_head_backward<T>(d_layers[static_cast<std::size_t>(depth - 1)], g.camera, d_pose, cache.camera, c.camera,
                          w.camera, N);
  DptHeadOutputGrads<T> d_dpt;
  d_dpt.preds = d_depth;
  d_dpt.conf = d_out.depth_conf;
  d_dpt.features = d_out.depth_features;
  dpt_head_backward<T>(std::span<T* const>(d_layers.data(), d_layers.size()), g.depth, d_dpt, cache.depth, c.depth,
                       w.depth, std::span<const T* const>(layers.data(), layers.size()), d_images);
  auto extra_head = [&](const DptHeadGrads<T>& hg, const T* d_preds, const T* d_map, DptHeadCache<T>& hk,
                        const DptHeadConfig& hc, const DptHeadWeights<T>& hw) {
    DptHeadOutputGrads<T> d;
    d.preds = d_preds;
    d.conf = d_map;
    dpt_head_backward<T>(std::span<T* const>(d_layers.data(), d_layers.size()), hg, d, hk, hc, hw,
                         std::span<const T* const>(layers.data(), layers.size()), d_images);
  };
  if (c.point_head && (d_out.points || d_out.points_conf))
    extra_head(g.point, d_out.points, d_out.points_conf, cache.point, c.point(), w.point);
  if (c.match_dim > 0 && (d_out.descriptors || d_out.foreground))
    extra_head(g.match, d_out.descriptors, d_out.foreground, cache.match, c.match(), w.match);

  // Trunk.
  std::vector<const T*> d_layers_const(d_layers.begin(), d_layers.end());
  T* d_dino = init(scratch.d_dino, S * P * C, nullptr);
  aggregator_trunk_backward<T>(d_dino, g.aggregator, std::span<const T* const>(d_layers_const.data(), d_layers_const.size()),
                               cache.aggregator, c.aggregator, w.aggregator, scratch.aggregator);
  T* d_norm = d_images ? init(scratch.d_normalized, S * 3 * H * W, nullptr) : nullptr;
  dino_backward<T>(d_norm, g.dino, d_dino, cache.dino, c.aggregator.dino, w.dino, scratch.dino);
  if (d_images) imagenet_normalize_backward(d_images, d_norm, S, H, W);
}

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
