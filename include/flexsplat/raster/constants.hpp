#pragma once
// Every threshold of the rasterizer, shared by the forward and backward passes (gsplat conventions). The SH
// constants, colour offset and maximum degree are core/gaussians.hpp's.
#include <cstdint>

#include "flexsplat/core/gaussians.hpp"

namespace flexsplat {
inline namespace v0 {
namespace raster {

inline constexpr int tile_size = 16;              // tiles are tile_size x tile_size pixels
inline constexpr double pixel_centre_offset = 0.5;  // pixel (x, y) samples at (x + 0.5, y + 0.5)
inline constexpr double default_eps2d = 0.3;      // isotropic blur added to every projected covariance
inline constexpr double default_near = 0.01;      // Gaussians whose camera z is below this are culled
inline constexpr double default_far = 1e10;
inline constexpr double fov_clamp_margin = 0.3;   // the Jacobian clamps x/z to 1.3x the half field of view
inline constexpr double alpha_threshold = 1.0 / 255.0;  // a Gaussian with alpha below this is skipped
inline constexpr double max_alpha = 0.99;               // alpha = min(max_alpha, o * exp(-sigma))
inline constexpr double transmittance_stop = 1e-4;      // a pixel stops before T would fall to this

// Relative and absolute slack of the culling tests: they may keep a few extra pairs that the per-pixel test
// then rejects, but never drop a pair whose float alpha reaches alpha_threshold.
inline constexpr double cull_slack_relative = 1e-3;
inline constexpr double cull_slack_absolute = 1e-3;
// Extra relative margin of the per-pixel extents per unit of the conic's condition number (trace^2 / det): float
// rounding of sigma grows with it, and a pixel whose float sigma passes must stay inside the extent.
inline constexpr double cull_slack_conditioning = 1e-6;

}  // namespace raster
}  // namespace v0
}  // namespace flexsplat
