#pragma once
// How much of each Gaussian a view shows: its blending weight alpha_i(p) T_i(p) summed over the view's pixels (in
// pixels: a fully opaque Gaussian covering 10 pixels in front of everything weighs 10). Computed as the gradient of a
// constant feature channel's sum, so the weights are exactly the rasterizer's (render_backward's feature adjoint).
//
//   std::vector<double> w(set.size(), 0.0);
//   raster::add_blend_weights(set, raster::camera_view<float>(cam), opt, ws, w);   // once per view; max or sum
#include <algorithm>
#include <vector>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/gaussians.hpp"
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/raster/render.hpp"

namespace flexsplat {
inline namespace v0 {
namespace raster {

// out[i] = max(out[i], Gaussian i's weight in `camera`), out sized to the set (zeros where it was empty).
template <class T>
void max_blend_weights(const GaussianSet<T>& set, const View<T>& camera, const RenderOptions& opt,
                       RenderWorkspace<T>& ws, std::vector<double>& out) {
  const index_t n = set.size();
  require(out.empty() || out.size() == static_cast<std::size_t>(n), "blend weights: ", out.size(), " slots for ", n,
          " Gaussians");
  out.resize(static_cast<std::size_t>(n), 0.0);
  if (n == 0) return;
  GaussianSet<T> one = set;  // the same set with one constant feature channel
  one.features = Tensor<T, 2>(Shape<2>{n, 1}, T(1));
  RenderOutputs<T> rendered;
  render_forward(one, camera, opt, ws, rendered);
  const Tensor<T, 3> d_features(rendered.features.shape(), T(1));
  GaussianSetGrad<T> grads;
  grads.features = Tensor<T, 2>(Shape<2>{n, 1}, T(0));
  RenderOutputGrads<T> d_out;
  d_out.features = TensorView<const T, 3>(d_features.view());
  render_backward(one, camera, opt, ws, d_out, grads);
  for (index_t i = 0; i < n; ++i)
    out[static_cast<std::size_t>(i)] = std::max(out[static_cast<std::size_t>(i)], static_cast<double>(grads.features(i, 0)));
}

}  // namespace raster
}  // namespace v0
}  // namespace flexsplat
