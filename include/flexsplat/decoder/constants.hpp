#pragma once
// Every threshold of the decoder in one place, shared by forward and backward.
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {
namespace decoder {

// A point nearer than this to a camera's image plane counts as behind it (its view is masked out).
inline constexpr double near_depth = 1e-2;
// Quaternions are divided by max(norm, this), as torch.nn.functional.normalize does.
inline constexpr double quaternion_norm_floor = 1e-12;
// Optical axes whose normal matrix has a smallest eigenvalue below this (relative to the view count) are "parallel".
inline constexpr double parallel_axes_eigen_floor = 1e-3;
// Splatter Image attribute biases: opacity logit and log-scale of a fresh Gaussian.
inline constexpr double opacity_logit_bias = -2.0;
inline constexpr double log_scale_bias = -3.912023005428146;  // log(0.02)
// LayerNorm epsilon (PyTorch's default).
inline constexpr double layernorm_eps = 1e-5;
// The automatic budget (queries_on_outline) keeps a query whose anchor lies within this many anchor spacings of the
// object's outline: one spacing keeps the queries of the anchor cells the edge crosses.
inline constexpr double outline_margin_cells = 1.0;
// Values of the 24-value Gaussian parameterisation, in order.
inline constexpr index_t splat_depth = 0, splat_offset = 1, splat_log_scale = 4, splat_quat = 7, splat_opacity = 11,
                         splat_sh = 12, splat_values = 24;

}  // namespace decoder
}  // namespace v0
}  // namespace flexsplat
