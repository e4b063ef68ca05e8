#pragma once
// VGGT's CameraHead (vggt/heads/camera_head.py at 44b3afb), forward and backward. The camera token of the last aggregator
// output goes through token_norm; then, for each refinement iteration, the current (detached, pre-activation)
// encoding - a learned empty encoding on the first pass - is embedded and turned into adaptive-LayerNorm shift,
// scale and gate; the modulated tokens run through the trunk (transformer blocks attending across frames),
// trunk_norm and the pose-branch MLP, whose output is added to the encoding. Every iteration's activated encoding
// (absT_quaR_FoV: translation, quaternion x y z w, fov_h, fov_w) is returned. Backward keeps VGGT's stop-gradient on
// the fed-back encoding.
#include <algorithm>
#include <cmath>
#include <span>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/geometry/block.hpp"
#include "flexsplat/io/param_check.hpp"
#include "flexsplat/io/param_source.hpp"
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
inline void append_camera_head_specs(std::vector<io::TensorSpec>& out, const CameraHeadConfig& c,
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
CameraHeadWeights<T> load_camera_head_weights(io::ParamSource<T>& src, const CameraHeadConfig& c,
                                              const std::string& prefix = "camera_head.") {
  c.validate();
  std::vector<io::TensorSpec> specs;
  append_camera_head_specs(specs, c, prefix);
  io::check_parameters(src, specs, {prefix}, "camera head");
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

template <class T>
T pose_activate_grad(T v, PoseActivation a) {
  switch (a) {
    case PoseActivation::linear: return T(1);
    case PoseActivation::inv_log: return std::exp(std::abs(v));
    case PoseActivation::exp: return std::exp(v);
    case PoseActivation::relu: return v > T(0) ? T(1) : T(0);
  }
  return T(1);
}

// Gradient slots mirroring CameraHeadWeights (null: not wanted).
template <class T>
struct CameraHeadGrads {
  T *token_norm_weight = nullptr, *token_norm_bias = nullptr;
  std::vector<BlockGrads<T>> trunk;
  T *trunk_norm_weight = nullptr, *trunk_norm_bias = nullptr;
  T* empty_pose_tokens = nullptr;
  T *embed_pose_weight = nullptr, *embed_pose_bias = nullptr;
  T *modulation_weight = nullptr, *modulation_bias = nullptr;
  T *branch_fc1_weight = nullptr, *branch_fc1_bias = nullptr;
  T *branch_fc2_weight = nullptr, *branch_fc2_bias = nullptr;
};

// Each weight's gradient at the same offset in the flat gradient block `grads_base` as the weight in the flat
// parameter block `params_base`.
template <class T>
CameraHeadGrads<T> camera_head_grads(const CameraHeadWeights<T>& w, const T* params_base, T* grads_base) {
  auto r = [&](const T* p) { return io::rebase_pointer(p, params_base, grads_base); };
  CameraHeadGrads<T> g;
  g.token_norm_weight = r(w.token_norm_weight);
  g.token_norm_bias = r(w.token_norm_bias);
  for (const auto& b : w.trunk) g.trunk.push_back(block_grads(b, params_base, grads_base));
  g.trunk_norm_weight = r(w.trunk_norm_weight);
  g.trunk_norm_bias = r(w.trunk_norm_bias);
  g.empty_pose_tokens = r(w.empty_pose_tokens);
  g.embed_pose_weight = r(w.embed_pose_weight);
  g.embed_pose_bias = r(w.embed_pose_bias);
  g.modulation_weight = r(w.modulation_weight);
  g.modulation_bias = r(w.modulation_bias);
  g.branch_fc1_weight = r(w.branch_fc1_weight);
  g.branch_fc1_bias = r(w.branch_fc1_bias);
  g.branch_fc2_weight = r(w.branch_fc2_weight);
  g.branch_fc2_bias = r(w.branch_fc2_bias);
  return g;
}

// What camera_head_forward_train keeps for camera_head_backward ([S, C] per frame-row; `it` = iteration).
template <class T>
struct CameraHeadCache {
  index_t frames = 0, iterations = 0, trunk_depth = 0;
  std::vector<T> cam_in;                   // [S, C] camera tokens of the last aggregator output
  std::vector<T> tok_mean, tok_rstd;       // [S] token_norm statistics
  std::vector<T> tok;                      // [S, C] token_norm output
  std::vector<T> adaln, adaln_mean, adaln_rstd;  // [S, C], [S], [S] the affine-free adaLN normalisation
  std::vector<T> enc_in;                   // [it, S, 9] encoding fed to embed_pose (empty tokens, then detached raw)
  std::vector<T> embed_pre;                // [it, S, C] embed_pose output before SiLU
  std::vector<T> mod;                      // [it, S, 3C] shift | scale | gate
  std::vector<BlockCache<T>> blocks;       // [it * trunk_depth]
  std::vector<T> trunk_out, trunk_mean, trunk_rstd;  // [it, S, C] trunk output (trunk_norm's input), [it, S] stats
  std::vector<T> hidden_pre;               // [it, S, C/2] pose_branch fc1 output before GELU
  std::vector<T> raw;                      // [it, S, 9] pre-activation encoding after each iteration
  std::vector<T> grad_ws;                  // camera_head_backward's buffers
  BlockBackwardScratch<T> block_scratch;
};

// Elements a CameraHeadCache holds after camera_head_forward_train on `frames` frames (grad_ws and the block
// backward scratch, sized on the first backward, are not included).
inline index_t camera_head_cache_elements(const CameraHeadConfig& c, index_t frames, bool recompute_blocks) {
  const index_t C = c.dim, S = frames, E = pose_encoding_dim;
  return S * (3 * C + 4) + c.iterations * S * (2 * E + 5 * C + 2 + c.branch_hidden()) +
         c.iterations * c.trunk_depth * block_cache_elements(c.block(), S, recompute_blocks);
}

namespace detail {
template <class T>
void camera_head_run(T* pose_enc, const CameraHeadConfig& c, const CameraHeadWeights<T>& w, const T* last_layer,
                     index_t frames, index_t tokens, std::span<T> workspace, CameraHeadCache<T>* k, bool recompute,
                     const T* feedback) {
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
  const index_t I = c.iterations, depth = c.trunk_depth;
  if (k) {
    k->frames = S, k->iterations = I, k->trunk_depth = depth;
    auto fit = [](std::vector<T>& v, index_t n) { v.resize(static_cast<std::size_t>(n)); };
    fit(k->cam_in, S * C), fit(k->tok_mean, S), fit(k->tok_rstd, S), fit(k->tok, S * C);
    fit(k->adaln, S * C), fit(k->adaln_mean, S), fit(k->adaln_rstd, S);
    fit(k->enc_in, I * S * E), fit(k->embed_pre, I * S * C), fit(k->mod, I * S * 3 * C);
    k->blocks.resize(static_cast<std::size_t>(I * depth));
    fit(k->trunk_out, I * S * C), fit(k->trunk_mean, I * S), fit(k->trunk_rstd, I * S);
    fit(k->hidden_pre, I * S * Hb), fit(k->raw, I * S * E);
  }

  for (index_t s = 0; s < S; ++s) std::copy(last_layer + s * tokens * C, last_layer + s * tokens * C + C, spare + s * C);
  if (k) std::copy(spare, spare + S * C, k->cam_in.data());
  nn::layernorm_forward(tok, spare, w.token_norm_weight, w.token_norm_bias, S, C, static_cast<T>(c.norm_eps),
                        k ? nn::LayerNormCache<T>{k->tok_mean.data(), k->tok_rstd.data()} : nn::LayerNormCache<T>{});
  nn::layernorm_forward<T>(adaln, tok, nullptr, nullptr, S, C, static_cast<T>(c.adaln_eps),
                           k ? nn::LayerNormCache<T>{k->adaln_mean.data(), k->adaln_rstd.data()} : nn::LayerNormCache<T>{});
  if (k) {
    std::copy(tok, tok + S * C, k->tok.data());
    std::copy(adaln, adaln + S * C, k->adaln.data());
  }

  for (index_t it = 0; it < I; ++it) {
    // The feedback is the raw accumulated encoding, detached as in VGGT (camera_head_backward sends no gradient
    // through it); `feedback`, when given, replaces it.
    const T* prev = it == 0 ? nullptr : feedback ? feedback + (it - 1) * S * E : raw;
    for (index_t s = 0; s < S; ++s)
      std::copy(it == 0 ? w.empty_pose_tokens : prev + s * E, (it == 0 ? w.empty_pose_tokens : prev + s * E) + E,
                delta + s * E);
    if (k) std::copy(delta, delta + S * E, k->enc_in.data() + it * S * E);
    nn::linear_forward(embed, delta, w.embed_pose_weight, w.embed_pose_bias, S, E, C);
    if (k) std::copy(embed, embed + S * C, k->embed_pre.data() + it * S * C);
    nn::silu_forward(embed, embed, S * C);
    nn::linear_forward(mod, embed, w.modulation_weight, w.modulation_bias, S, C, 3 * C);
    if (k) std::copy(mod, mod + S * 3 * C, k->mod.data() + it * S * 3 * C);
    parallel_for(S, [&](index_t s0, index_t s1, int) {
      for (index_t s = s0; s < s1; ++s) {
        const T* shift = mod + s * 3 * C;
        const T* scale = shift + C;
        const T* gate = scale + C;
        for (index_t i = 0; i < C; ++i)
          x[s * C + i] = gate[i] * (adaln[s * C + i] * (T(1) + scale[i]) + shift[i]) + tok[s * C + i];
      }
    });
    for (index_t b = 0; b < depth; ++b) {
      if (k)
        block_forward_train<T>(x, 1, S, c.block(), w.trunk[b], nullptr, nullptr, k->blocks[it * depth + b], recompute,
                               block_ws);
      else
        block_forward<T>(x, 1, S, c.block(), w.trunk[b], nullptr, nullptr, block_ws);
    }
    if (k) std::copy(x, x + S * C, k->trunk_out.data() + it * S * C);
    nn::layernorm_forward(normed, x, w.trunk_norm_weight, w.trunk_norm_bias, S, C, static_cast<T>(c.norm_eps),
                          k ? nn::LayerNormCache<T>{k->trunk_mean.data() + it * S, k->trunk_rstd.data() + it * S}
                            : nn::LayerNormCache<T>{});
    nn::linear_forward(hidden, normed, w.branch_fc1_weight, w.branch_fc1_bias, S, C, Hb);
    if (k) std::copy(hidden, hidden + S * Hb, k->hidden_pre.data() + it * S * Hb);
    nn::gelu_forward(hidden, hidden, S * Hb);
    nn::linear_forward(delta, hidden, w.branch_fc2_weight, w.branch_fc2_bias, S, Hb, E);
    T* out = pose_enc + it * S * E;
    for (index_t s = 0; s < S; ++s)
      for (index_t e = 0; e < E; ++e) {
        const T v = it == 0 ? delta[s * E + e] : prev[s * E + e] + delta[s * E + e];
        raw[s * E + e] = v;
        out[s * E + e] = pose_activate(v, e < 3 ? c.trans_act : e < 7 ? c.quat_act : c.fl_act);
      }
    if (k) std::copy(raw, raw + S * E, k->raw.data() + it * S * E);
  }
}
}  // namespace detail

// pose_enc [iterations, frames, 9]: the activated encoding after each refinement iteration (the last is the
// prediction). last_layer is the final aggregator output [frames, tokens, dim]; token 0 of each frame is its camera
// token.
template <class T>
void camera_head_forward(T* pose_enc, const CameraHeadConfig& c, const CameraHeadWeights<T>& w, const T* last_layer,
                         index_t frames, index_t tokens, std::span<T> workspace) {
  detail::camera_head_run<T>(pose_enc, c, w, last_layer, frames, tokens, workspace, nullptr, false, nullptr);
}

// camera_head_forward (same outputs bit for bit) that fills `cache` for camera_head_backward. recompute_blocks: the
// trunk blocks keep only their inputs and rerun their forward in backward. feedback (optional, [iterations - 1,
// frames, 9]): pre-activation encodings fed to iterations 1.. instead of the head's own (with cache.raw of an earlier
// run the outputs are unchanged; holding them fixed is how a gradient check sees VGGT's detach).
template <class T>
void camera_head_forward_train(T* pose_enc, CameraHeadCache<T>& cache, const CameraHeadConfig& c,
                               const CameraHeadWeights<T>& w, const T* last_layer, index_t frames, index_t tokens,
                               std::span<T> workspace, bool recompute_blocks = false, const T* feedback = nullptr) {
  detail::camera_head_run<T>(pose_enc, c, w, last_layer, frames, tokens, workspace, &cache, recompute_blocks, feedback);
}

// Backward of camera_head_forward_train. d_pose_enc [iterations, frames, 9] (gradients of every iteration's activated
// encoding). Adds into `g` (null slots skipped) and into the camera-token rows of d_last_layer [frames, tokens, dim]
// (may be null; other tokens untouched). As in VGGT (pred_pose_enc.detach()), the encoding fed back into the next
// iteration carries no gradient: iteration it's output reaches earlier iterations only through shared weights and
// tokens, never through its input encoding or the accumulated sum.
template <class T>
void camera_head_backward(T* d_last_layer, const CameraHeadGrads<T>& g, const T* d_pose_enc, CameraHeadCache<T>& k,
                          const CameraHeadConfig& c, const CameraHeadWeights<T>& w, index_t tokens) {
  c.validate();
  const index_t C = c.dim, S = k.frames, E = pose_encoding_dim, Hb = c.branch_hidden(), I = c.iterations,
                depth = c.trunk_depth;
  require(S >= 1 && k.iterations == I && k.trunk_depth == depth && static_cast<index_t>(k.tok.size()) == S * C,
          "camera head backward: the cache is empty or was filled for another configuration (run "
          "camera_head_forward_train first)");
  require(d_pose_enc != nullptr, "camera head backward: d_pose_enc is required");
  require(d_last_layer == nullptr || tokens >= 1, "camera head backward: ", tokens, " tokens per frame");
  require(g.trunk.empty() || static_cast<index_t>(g.trunk.size()) == depth, "camera head backward: ", g.trunk.size(),
          " trunk gradient sets for ", depth, " blocks");
  k.grad_ws.assign(static_cast<std::size_t>(S * (6 * C + 3 * C + 2 * Hb + 2 * E)), T(0));
  T* d_tok = k.grad_ws.data();   // [S, C] accumulated over iterations
  T* d_adaln = d_tok + S * C;     // [S, C] accumulated over iterations
  T* d_x = d_adaln + S * C;       // [S, C]
  T* buf = d_x + S * C;           // [S, C] recomputed trunk_norm output, then SiLU output
  T* d_buf = buf + S * C;         // [S, C]
  T* d_embed = d_buf + S * C;     // [S, C]
  T* d_mod = d_embed + S * C;     // [S, 3C]
  T* hidden = d_mod + S * 3 * C;  // [S, C/2] recomputed GELU output
  T* d_hidden = hidden + S * Hb;  // [S, C/2]
  T* d_raw = d_hidden + S * Hb;   // [S, 9]
  T* d_in = d_raw + S * E;        // [S, 9]
  const BlockGrads<T> no_block_grads{};
  const T eps = static_cast<T>(c.norm_eps);

  for (index_t it = I - 1; it >= 0; --it) {
    const T* raw = k.raw.data() + it * S * E;
    const T* d_out = d_pose_enc + it * S * E;
    for (index_t s = 0; s < S; ++s)
      for (index_t e = 0; e < E; ++e)
        d_raw[s * E + e] = d_out[s * E + e] *
                           pose_activate_grad(raw[s * E + e], e < 3 ? c.trans_act : e < 7 ? c.quat_act : c.fl_act);
    // raw = detach(previous raw) + delta: all of d_raw goes to this iteration's delta.
    const T* pre = k.hidden_pre.data() + it * S * Hb;
    nn::gelu_forward(hidden, pre, S * Hb);
    std::fill(d_hidden, d_hidden + S * Hb, T(0));
    nn::linear_backward(d_hidden, g.branch_fc2_weight, g.branch_fc2_bias, d_raw, hidden, w.branch_fc2_weight, S, Hb, E);
    std::fill(hidden, hidden + S * Hb, T(0));  // now d(pre-GELU)
    nn::gelu_backward(hidden, d_hidden, pre, S * Hb);
    const T* x_out = k.trunk_out.data() + it * S * C;
    nn::layernorm_forward(buf, x_out, w.trunk_norm_weight, w.trunk_norm_bias, S, C, eps);
    std::fill(d_buf, d_buf + S * C, T(0));
    nn::linear_backward(d_buf, g.branch_fc1_weight, g.branch_fc1_bias, hidden, buf, w.branch_fc1_weight, S, C, Hb);
    std::fill(d_x, d_x + S * C, T(0));
    nn::layernorm_backward(d_x, g.trunk_norm_weight, g.trunk_norm_bias, d_buf, x_out, w.trunk_norm_weight, S, C,
                           nn::LayerNormCache<T>{k.trunk_mean.data() + it * S, k.trunk_rstd.data() + it * S});
    for (index_t b = depth - 1; b >= 0; --b)
      block_backward<T>(d_x, g.trunk.empty() ? no_block_grads : g.trunk[b], k.blocks[it * depth + b], c.block(),
                        w.trunk[b], nullptr, nullptr, k.block_scratch);
    // x = gate * (adaln * (1 + scale) + shift) + tok.
    const T* mod = k.mod.data() + it * S * 3 * C;
    for (index_t s = 0; s < S; ++s) {
      const T* shift = mod + s * 3 * C;
      const T* scale = shift + C;
      const T* gate = scale + C;
      T* d_shift = d_mod + s * 3 * C;
      T* d_scale = d_shift + C;
      T* d_gate = d_scale + C;
      for (index_t i = 0; i < C; ++i) {
        const T dx = d_x[s * C + i], a = k.adaln[s * C + i];
        d_tok[s * C + i] += dx;
        d_adaln[s * C + i] += dx * gate[i] * (T(1) + scale[i]);
        d_shift[i] = dx * gate[i];
        d_scale[i] = dx * gate[i] * a;
        d_gate[i] = dx * (a * (T(1) + scale[i]) + shift[i]);
      }
    }
    const T* embed_pre = k.embed_pre.data() + it * S * C;
    nn::silu_forward(buf, embed_pre, S * C);
    std::fill(d_embed, d_embed + S * C, T(0));
    nn::linear_backward(d_embed, g.modulation_weight, g.modulation_bias, d_mod, buf, w.modulation_weight, S, C, 3 * C);
    std::fill(d_buf, d_buf + S * C, T(0));
    nn::silu_backward(d_buf, d_embed, embed_pre, S * C);
    // Iteration 0 embeds the learned empty encoding (broadcast over frames); later ones a detached input.
    const bool to_empty = it == 0 && g.empty_pose_tokens;
    if (to_empty) std::fill(d_in, d_in + S * E, T(0));
    nn::linear_backward(to_empty ? d_in : static_cast<T*>(nullptr), g.embed_pose_weight, g.embed_pose_bias, d_buf,
                        k.enc_in.data() + it * S * E, w.embed_pose_weight, S, E, C);
    if (to_empty)
      for (index_t s = 0; s < S; ++s)
        for (index_t e = 0; e < E; ++e) g.empty_pose_tokens[e] += d_in[s * E + e];
  }

  // adaln = LN(tok) without affine, tok = token_norm(camera token).
  nn::layernorm_backward<T>(d_tok, nullptr, nullptr, d_adaln, k.tok.data(), nullptr, S, C,
                            nn::LayerNormCache<T>{k.adaln_mean.data(), k.adaln_rstd.data()});
  std::fill(d_x, d_x + S * C, T(0));
  nn::layernorm_backward(d_last_layer ? d_x : static_cast<T*>(nullptr), g.token_norm_weight, g.token_norm_bias, d_tok,
                         k.cam_in.data(), w.token_norm_weight, S, C,
                         nn::LayerNormCache<T>{k.tok_mean.data(), k.tok_rstd.data()});
  if (d_last_layer)
    for (index_t s = 0; s < S; ++s)
      for (index_t i = 0; i < C; ++i) d_last_layer[s * tokens * C + i] += d_x[s * C + i];
}

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
