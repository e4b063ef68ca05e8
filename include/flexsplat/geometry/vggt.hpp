#pragma once
// End-to-end VGGT forward for FlexSplat: images [S, 3, H, W] in [0, 1] -> ImageNet normalisation -> DINOv2 patch
// tokens -> alternating-attention aggregator -> camera head (pose encodings per refinement iteration, decoded to
// world-to-camera extrinsics and intrinsics) and DPT depth head (depth, confidence) -> world points.
#include <algorithm>
#include <functional>
#include <set>
#include <string>
#include <vector>

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
  Tensor<T, 3> extrinsics;    // [S, 3, 4] world-to-camera (OpenCV)
  Tensor<T, 3> intrinsics;    // [S, 3, 3]
  Tensor<T, 3> depth;         // [S, H, W]
  Tensor<T, 3> depth_conf;    // [S, H, W]
  Tensor<T, 4> world_points;  // [S, H, W, 3]
  Tensor<T, 3> dino_tokens;   // [S, P, C] when VggtOptions::keep_dino_tokens
  AggregatorOutputs<T> aggregator;  // the layers the heads read (all when VggtOptions::keep_all_layers)
};

struct VggtOptions {
  bool keep_dino_tokens = false;
  bool keep_all_layers = false;
  // Called with a stage name ("dino", "aggregator", "camera_head", "depth_head", "unproject") and its progress:
  // step of steps (aggregator: per block pair).
  std::function<void(const std::string&, index_t, index_t)> progress;
};

template <class T>
struct VggtWorkspace {
  std::vector<T, AlignedAllocator<T>> normalized, head;
  DinoWorkspace<T> dino;
  AggregatorWorkspace<T> aggregator;
};

template <class T>
VggtOutputs<T> vggt_forward(const T* images, index_t frames, index_t image_h, index_t image_w, const VggtConfig& c,
                            const VggtWeights<T>& w, VggtWorkspace<T>& ws, const VggtOptions& options = {}) {
  c.validate();
  const index_t p = c.aggregator.patch_size, C = c.aggregator.embed_dim;
  require(frames >= 1, "VGGT: needs at least one image, got ", frames);
  require(image_h >= p && image_w >= p && image_h % p == 0 && image_w % p == 0, "VGGT: image size ", image_h, " x ",
          image_w, " must be a positive multiple of the patch size ", p, " (preprocess the images first)");
  const index_t n = frames * 3 * image_h * image_w;
  for (index_t i = 0; i < n; ++i)
    if (!std::isfinite(static_cast<double>(images[i])))
      fail("VGGT: input image value ", static_cast<double>(images[i]), " at element ", i, " is not finite");
  auto report = [&](const char* stage, index_t step, index_t steps) {
    if (options.progress) options.progress(stage, step, steps);
  };
  const index_t gh = image_h / p, gw = image_w / p, P = gh * gw;
  VggtOutputs<T> out;

  report("dino", 0, 1);
  ws.normalized.resize(static_cast<std::size_t>(n));
  imagenet_normalize(ws.normalized.data(), images, frames, image_h, image_w);
  out.dino_tokens.resize(Shape<3>{frames, P, C});
  dino_forward(out.dino_tokens.data(), ws.normalized.data(), frames, image_h, image_w, c.aggregator.dino, w.dino, ws.dino);
  report("dino", 1, 1);

  std::set<index_t> keep(c.depth.intermediate_layer_idx.begin(), c.depth.intermediate_layer_idx.end());
  keep.insert(c.aggregator.depth - 1);  // the camera head reads the last layer
  std::vector<index_t> keep_list(keep.begin(), keep.end());
  if (options.keep_all_layers) keep_list.clear();
  out.aggregator = aggregator_trunk_forward<T>(out.dino_tokens.data(), frames, gh, gw, c.aggregator, w.aggregator,
                                                keep_list, ws.aggregator,
                                                [&](index_t step, index_t steps) { report("aggregator", step + 1, steps); });
  if (!options.keep_dino_tokens) out.dino_tokens = Tensor<T, 3>();
  const index_t N = out.aggregator.tokens;

  report("camera_head", 0, 1);
  ws.head.resize(static_cast<std::size_t>(camera_head_workspace_size(c.camera, frames)));
  out.pose_enc.resize(Shape<3>{c.camera.iterations, frames, pose_encoding_dim});
  camera_head_forward<T>(out.pose_enc.data(), c.camera, w.camera, out.aggregator.at(c.aggregator.depth - 1).data(),
                         frames, N, std::span<T>(ws.head.data(), ws.head.size()));
  out.extrinsics.resize(Shape<3>{frames, 3, 4});
  out.intrinsics.resize(Shape<3>{frames, 3, 3});
  pose_encoding_to_extri_intri<T>(out.extrinsics.data(), out.intrinsics.data(),
                                  out.pose_enc.data() + (c.camera.iterations - 1) * frames * pose_encoding_dim, frames,
                                  image_h, image_w, c.pose_decode);
  report("camera_head", 1, 1);

  report("depth_head", 0, 1);
  std::vector<const T*> layers(static_cast<std::size_t>(c.aggregator.depth), nullptr);
  for (auto& [index, tensor] : out.aggregator.layers) layers[static_cast<std::size_t>(index)] = tensor.data();
  ws.head.resize(static_cast<std::size_t>(dpt_head_workspace_size(c.depth, gh, gw)));
  out.depth.resize(Shape<3>{frames, image_h, image_w});
  out.depth_conf.resize(Shape<3>{frames, image_h, image_w});
  DptHeadOutputs<T> dpt_out;
  dpt_out.preds = out.depth.data();
  dpt_out.conf = out.depth_conf.data();
  dpt_head_forward<T>(dpt_out, c.depth, w.depth, std::span<const T* const>(layers.data(), layers.size()), frames, N,
                      out.aggregator.patch_start_idx, image_h, image_w, std::span<T>(ws.head.data(), ws.head.size()));
  report("depth_head", 1, 1);

  report("unproject", 0, 1);
  out.world_points.resize(Shape<4>{frames, image_h, image_w, 3});
  unproject_depth_forward<T>(out.world_points.data(), out.depth.data(), out.extrinsics.data(), out.intrinsics.data(),
                             frames, image_h, image_w);
  report("unproject", 1, 1);
  return out;
}

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
