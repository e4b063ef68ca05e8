#pragma once
// Floating-point operations of a VGGT forward per stage (2 x multiply-adds of the linear layers, attention products
// and convolutions; norms, activations and resizes are not counted), for benchmarks' GFLOP/s and "of SGEMM" columns.
// A backward costs about twice its forward.
#include "flexsplat/geometry/camera_head.hpp"
#include "flexsplat/geometry/config.hpp"
#include "flexsplat/geometry/dpt_head.hpp"

namespace flexsplat {
inline namespace v0 {
namespace geometry {

// One block over `batch` sequences of `tokens` rows: qkv, projection, MLP, QK^T and PV.
inline double block_flops(const BlockConfig& c, double batch, double tokens) {
  const double rows = batch * tokens, C = double(c.dim), H = double(c.mlp_hidden());
  return 2.0 * rows * (3 * C * C + C * C + 2 * C * H) + 4.0 * batch * tokens * tokens * C;
}

// The DPT head's convolutions for one frame of a patch_h x patch_w grid.
inline double dpt_flops(const DptHeadConfig& c, index_t ph, index_t pw) {
  const DptGeometry g(ph, pw, c.patch_size);
  const double P = double(ph * pw), F = double(c.features), Fh = double(c.head_features());
  const auto& oc = c.out_channels;
  double f = 0;
  for (int i = 0; i < 4; ++i) f += 2 * P * double(c.dim_in) * double(oc[i]);
  f += 2 * P * double(oc[0]) * double(oc[0]) * 16 + 2 * P * double(oc[1]) * double(oc[1]) * 4;
  f += 2 * double(g.level_size(3)) * double(oc[3]) * double(oc[3]) * 9;
  for (int i = 0; i < 4; ++i) f += 2 * double(g.level_size(i)) * double(oc[i]) * F * 9;
  const double conv3 = 2 * F * F * 9, conv1 = 2 * F * F;
  for (int i = 0; i < 4; ++i) {
    const double units = i == 3 ? 1 : 2;  // refinenet4 has no skip unit
    // out_conv (1x1) runs before the resize, at the level's own size (it commutes with bilinear resizing)
    f += (units * 2 * conv3 + conv1) * double(g.level_size(i));
  }
  f += 2 * double(g.fused_h * g.fused_w) * F * Fh * 9;
  const double full = double(g.out_h * g.out_w);
  f += 2 * full * double(c.conv2_in()) * DptHeadConfig::head_hidden * 9 +
       2 * full * DptHeadConfig::head_hidden * double(c.output_dim);
  for (index_t j = 0; j < c.image_convs; ++j)
    f += 2 * full * double(j == 0 ? c.image_channels : c.image_width) * double(c.image_width) * 9;
  return f;
}

// The camera head over `frames` camera tokens: per iteration the trunk blocks, pose embedding, adaLN modulation and
// the pose branch MLP.
inline double camera_head_flops(const CameraHeadConfig& c, index_t frames) {
  const double S = double(frames), C = double(c.dim), E = double(pose_encoding_dim);
  const double per_iteration = double(c.trunk_depth) * block_flops(c.block(), 1, S) +
                               2 * S * (E * C + 3 * C * C + C * double(c.branch_hidden()) + double(c.branch_hidden()) * E);
  return double(c.iterations) * per_iteration;
}

struct VggtFlops {
  double dino = 0, aggregator = 0, camera_head = 0, depth_head = 0;
  double total() const { return dino + aggregator + camera_head + depth_head; }
};

inline VggtFlops vggt_forward_flops(const VggtConfig& cfg, index_t frames, index_t image_h, index_t image_w) {
  const auto& a = cfg.aggregator;
  const index_t p = a.patch_size, gh = image_h / p, gw = image_w / p, P = gh * gw;
  const double S = double(frames);
  VggtFlops f;
  f.dino = 2.0 * S * double(P) * 3 * double(p * p) * double(a.embed_dim) +
           double(a.dino.depth) * block_flops(a.dino.block(), S, double(1 + a.dino.num_register_tokens + P));
  const double tokens = double(a.patch_start_idx() + P);
  f.aggregator = double(a.depth) * (block_flops(a.block(), S, tokens) + block_flops(a.block(), 1, S * tokens));
  f.camera_head = camera_head_flops(cfg.camera, frames);
  f.depth_head = S * dpt_flops(cfg.depth, gh, gw);
  return f;
}

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
