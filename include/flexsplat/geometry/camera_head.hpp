#pragma once
// VGGT's CameraHead (vggt/heads/camera_head.py at 44b3afb), forward only. The camera token of the last aggregator
// output goes through token_norm; then, for each refinement iteration, the current (detached, pre-activation)
// encoding - a learned empty encoding on the first pass - is embedded and turned into adaptive-LayerNorm shift,
// scale and gate; the modulated tokens run through the trunk (transformer blocks attending across frames),
// trunk_norm and the pose-branch MLP, whose output is added to the encoding. Every iteration's activated encoding
// (absT_quaR_FoV: translation, quaternion x y z w, fov_h, fov_w) is returned.
#include <algorithm>
#include <span>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/geometry/block.hpp"
#include "flexsplat/geometry/param_check.hpp"
#include "flexsplat/geometry/param_source.hpp"
#include "flexsplat/geometry/pose_encoding.hpp"
#include "flexsplat/nn/activations.hpp"
#include "flexsplat/nn/layernorm.hpp"
#include "flexsplat/nn/linear.hpp"

namespace flexsplat {
inline namespace v0 {
namespace geometry {

enum class PoseActivation { linear, inv_log, exp, relu };

struct CameraHeadConfig {
  index_t dim = 2048;  // dim_in: 2 x the aggregator's embed_dim
  index_t trunk_depth = 4;
  index_t num_heads = 16;
  double mlp_ratio = 4.0;
  double init_values = 0.01;  // trunk LayerScale present when > 0
  index_t iterations = 4;
  PoseActivation trans_act = PoseActivation::linear;
  PoseActivation quat_act = PoseActivation::linear;
  PoseActivation fl_act = PoseActivation::relu;  // applied to the two FoV entries
  double norm_eps = 1e-5;                        // token_norm, trunk_norm and the trunk blocks' norms
  double adaln_eps = 1e-6;                       // the affine-free adaLN normalisation

  index_t branch_hidden() const { return dim / 2; }
  BlockConfig block() const {
    return {.dim = dim, .num_heads = num_heads, .mlp_ratio = mlp_ratio,
            .qk_norm = false, .layer_scale = init_values > 0, .norm_eps = norm_eps};
  }
  void validate() const {
    require(trunk_depth >= 0 && iterations >= 1, "camera head config: trunk_depth ", trunk_depth, " and iterations ",
            iterations, " must be >= 0 and >= 1");
    require(dim >= 2, "camera head config: dim ", dim, " must be at least 2");
    block().validate("camera head config");
  }
};

// The camera head of a VGGT whose config JSON uses the reference bundles' keys (embed_dim, trunk_depth, cam_heads);
// absent keys keep VGGT-1B's values.
inline CameraHeadConfig camera_head_config_from_vggt_json(const nlohmann::json& j) {
  CameraHeadConfig c;
  try {
    if (j.contains("embed_dim")) c.dim = 2 * j.at("embed_dim").get<index_t>();
    if (j.contains("trunk_depth")) c.trunk_depth = j.at("trunk_depth").get<index_t>();
    if (j.contains("cam_heads")) c.num_heads = j.at("cam_heads").get<index_t>();
  } catch (const nlohmann::json::exception& e) {
    fail("VGGT config ", j.dump(), ": bad camera head entry: ", e.what());
  }
  c.validate();
  return c;
}

template <class T>
struct CameraHeadWeights {
  const T *token_norm_weight = nullptr, *token_norm_bias = nullptr;
  std::vector<BlockWeights<T>> trunk;
  const T *trunk_norm_weight = nullptr, *trunk_norm_bias = nullptr;
  const T* empty_pose_tokens = nullptr;                           // [1, 1, 9]
  const T *embed_pose_weight = nullptr, *embed_pose_bias = nullptr;  // [dim, 9]
  const T *modulation_weight = nullptr, *modulation_bias = nullptr;  // poseLN_modulation.1: [3 dim, dim]
  const T *branch_fc1_weight = nullptr, *branch_fc1_bias = nullptr;  // [dim/2, dim]
  const T *branch_fc2_weight = nullptr, *branch_fc2_bias = nullptr;  // [9, dim/2]
};

// Parameter names and shapes as in VGGT's state_dict, each prefixed with `prefix`.
inline void append_camera_head_specs(std::vector<TensorSpec>& out, const CameraHeadConfig& c,
                                     const std::string& prefix = "camera_head.") {
  const index_t C = c.dim, Hb = c.branch_hidden(), E = pose_encoding_dim;
  out.push_back({prefix + "token_norm.weight", {C}});
  out.push_back({prefix + "token_norm.bias", {C}});
  for (index_t i = 0; i < c.trunk_depth; ++i) append_block_specs(out, prefix + "trunk." + std::to_string(i) + ".", c.block());
  out.push_back({prefix + "trunk_norm.weight", {C}});
  out.push_back({prefix + "trunk_norm.bias", {C}});
  out.push_back({prefix + "empty_pose_tokens", {1, 1, E}});
  out.push_back({prefix + "embed_pose.weight", {C, E}});
  out.push_back({prefix + "embed_pose.bias", {C}});
  out.push_back({prefix + "poseLN_modulation.1.weight", {3 * C, C}});
  out.push_back({prefix + "poseLN_modulation.1.bias", {3 * C}});
  out.push_back({prefix + "pose_branch.fc1.weight", {Hb, C}});
  out.push_back({prefix + "pose_branch.fc1.bias", {Hb}});
  out.push_back({prefix + "pose_branch.fc2.weight", {E, Hb}});
  out.push_back({prefix + "pose_branch.fc2.bias", {E}});
}

// Checks every parameter first (one error lists all missing, mis-shaped and unexpected `prefix` tensors), then binds.
template <class T>
CameraHeadWeights<T> load_camera_head_weights(ParamSource<T>& src, const CameraHeadConfig& c,
                                              const std::string& prefix = "camera_head.") {
  c.validate();
  std::vector<TensorSpec> specs;
  append_camera_head_specs(specs, c, prefix);
  check_parameters(src, specs, {prefix}, "camera head");
  const index_t C = c.dim, Hb = c.branch_hidden(), E = pose_encoding_dim;
  CameraHeadWeights<T> w;
  w.token_norm_weight = src.get(prefix + "token_norm.weight", {C});
  w.token_norm_bias = src.get(prefix + "token_norm.bias", {C});
  for (index_t i = 0; i < c.trunk_depth; ++i)
    w.trunk.push_back(load_block_weights(src, prefix + "trunk." + std::to_string(i) + ".", c.block()));
  w.trunk_norm_weight = src.get(prefix + "trunk_norm.weight", {C});
  w.trunk_norm_bias = src.get(prefix + "trunk_norm.bias", {C});
  w.empty_pose_tokens = src.get(prefix + "empty_pose_tokens", {1, 1, E});
  w.embed_pose_weight = src.get(prefix + "embed_pose.weight", {C, E});
  w.embed_pose_bias = src.get(prefix + "embed_pose.bias", {C});
  w.modulation_weight = src.get(prefix + "poseLN_modulation.1.weight", {3 * C, C});
  w.modulation_bias = src.get(prefix + "poseLN_modulation.1.bias", {3 * C});
  w.branch_fc1_weight = src.get(prefix + "pose_branch.fc1.weight", {Hb, C});
  w.branch_fc1_bias = src.get(prefix + "pose_branch.fc1.bias", {Hb});
  w.branch_fc2_weight = src.get(prefix + "pose_branch.fc2.weight", {E, Hb});
  w.branch_fc2_bias = src.get(prefix + "pose_branch.fc2.bias", {E});
  return w;
}

// Workspace elements camera_head_forward needs for `frames` frames on a pool of `workers` threads.
inline index_t camera_head_workspace_size(const CameraHeadConfig& c, index_t frames, int workers = global_pool().size()) {
  const index_t C = c.dim;
  return frames * (6 * C + 3 * C + c.branch_hidden() + 2 * pose_encoding_dim) +
         block_workspace_size(c.block(), frames, workers);
}

template <class T>
T pose_activate(T v, PoseActivation a) {
  switch (a) {
    case PoseActivation::linear: return v;
    case PoseActivation::inv_log: return v < T(0) ? -std::expm1(-v) : std::expm1(v);
    case PoseActivation::exp: return std::exp(v);
    case PoseActivation::relu: return v > T(0) ? v : T(0);
  }
  return v;
}

// pose_enc [iterations, frames, 9]: the activated encoding after each refinement iteration (the last is the
// prediction). last_layer is the final aggregator output [frames, tokens, dim]; token 0 of each frame is its camera
// token.
template <class T>
void camera_head_forward(T* pose_enc, const CameraHeadConfig& c, const CameraHeadWeights<T>& w, const T* last_layer,
                         index_t frames, index_t tokens, std::span<T> workspace) {
  c.validate();
  require(frames >= 1 && tokens >= 1, "camera head: needs at least one frame and one token (got ", frames,
          " frames, ", tokens, " tokens)");
  require(static_cast<index_t>(w.trunk.size()) == c.trunk_depth, "camera head: weights hold ", w.trunk.size(),
          " trunk blocks, config says ", c.trunk_depth);
  const index_t need = camera_head_workspace_size(c, frames);
  require(static_cast<index_t>(workspace.size()) >= need, "camera head: workspace has ", workspace.size(),
          " elements, needs ", need);
  const index_t C = c.dim, S = frames, E = pose_encoding_dim, Hb = c.branch_hidden();
  T* tok = workspace.data();    // [S, C] normalised camera tokens
  T* adaln = tok + S * C;       // [S, C] adaln_norm(tok): fixed across iterations
  T* embed = adaln + S * C;     // [S, C] embedded encoding, then its SiLU
  T* x = embed + S * C;         // [S, C] trunk state
  T* normed = x + S * C;        // [S, C] trunk_norm output
  T* spare = normed + S * C;    // [S, C] (keeps the layout 6C per frame)
  T* mod = spare + S * C;       // [S, 3C] shift | scale | gate
  T* hidden = mod + S * 3 * C;  // [S, C/2]
  T* raw = hidden + S * Hb;     // [S, 9] pre-activation encoding
  T* delta = raw + S * E;       // [S, 9]
  std::span<T> block_ws(delta + S * E, workspace.size() - static_cast<std::size_t>(delta + S * E - workspace.data()));

  for (index_t s = 0; s < S; ++s) std::copy(last_layer + s * tokens * C, last_layer + s * tokens * C + C, spare + s * C);
  nn::layernorm_forward(tok, spare, w.token_norm_weight, w.token_norm_bias, S, C, static_cast<T>(c.norm_eps));
  nn::layernorm_forward<T>(adaln, tok, nullptr, nullptr, S, C, static_cast<T>(c.adaln_eps));

  for (index_t it = 0; it < c.iterations; ++it) {
    // The feedback is the raw accumulated encoding (VGGT detaches it; irrelevant for a forward pass).
    for (index_t s = 0; s < S; ++s)
      std::copy(it == 0 ? w.empty_pose_tokens : raw + s * E, (it == 0 ? w.empty_pose_tokens : raw + s * E) + E,
                delta + s * E);
    nn::linear_forward(embed, delta, w.embed_pose_weight, w.embed_pose_bias, S, E, C);
    nn::silu_forward(embed, embed, S * C);
    nn::linear_forward(mod, embed, w.modulation_weight, w.modulation_bias, S, C, 3 * C);
    parallel_for(S, [&](index_t s0, index_t s1, int) {
      for (index_t s = s0; s < s1; ++s) {
        const T* shift = mod + s * 3 * C;
        const T* scale = shift + C;
        const T* gate = scale + C;
        for (index_t i = 0; i < C; ++i)
          x[s * C + i] = gate[i] * (adaln[s * C + i] * (T(1) + scale[i]) + shift[i]) + tok[s * C + i];
      }
    });
    for (const auto& block : w.trunk)
      block_forward<T>(x, 1, S, c.block(), block, nullptr, nullptr, block_ws);
    nn::layernorm_forward(normed, x, w.trunk_norm_weight, w.trunk_norm_bias, S, C, static_cast<T>(c.norm_eps));
    nn::linear_forward(hidden, normed, w.branch_fc1_weight, w.branch_fc1_bias, S, C, Hb);
    nn::gelu_forward(hidden, hidden, S * Hb);
    nn::linear_forward(delta, hidden, w.branch_fc2_weight, w.branch_fc2_bias, S, Hb, E);
    T* out = pose_enc + it * S * E;
    for (index_t s = 0; s < S; ++s)
      for (index_t e = 0; e < E; ++e) {
        const T v = it == 0 ? delta[s * E + e] : raw[s * E + e] + delta[s * E + e];
        raw[s * E + e] = v;
        out[s * E + e] = pose_activate(v, e < 3 ? c.trans_act : e < 7 ? c.quat_act : c.fl_act);
      }
  }
}

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
