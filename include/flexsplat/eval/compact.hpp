#pragma once
// A splat that keeps only what the scene needs: after prediction (and refinement), the Gaussians the input views do not
// need are dropped before rendering and export: degenerate ones (a scale not finite and positive, an opacity below the
// rasterizer's 1/255 alpha floor), with the views' alpha those whose centre projects onto background in some view
// (carve_to_silhouettes), and those whose largest blending weight over the views (raster::max_blend_weights: alpha T
// summed over a view's pixels, at the photos' resolution) is below CompactOptions::min_pixels. Novel views may still
// see a dropped one: the held-out views' PSNR says what that costs (bench/compact).
//
//   const model::CompactReport r = model::compact_splat(p.gaussians, cameras, alpha);   // the input views' cameras, alpha
#include <algorithm>
#include <cmath>
#include <vector>

#include "flexsplat/core/camera.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/core/gaussians.hpp"
#include "flexsplat/eval/refine.hpp"
#include "flexsplat/raster/weights.hpp"

namespace flexsplat {
inline namespace v0 {
namespace model {

// A Gaussian whose blending weight in every input view sums to less than this many pixels is dropped. Chosen with the
// silhouette margin on procedural scenes (bench/compact on make-data objects; docs/app.md).
inline constexpr double compact_min_pixels = 2;

struct CompactOptions {
  double min_pixels = compact_min_pixels;
  // With the views' alpha: Gaussians whose centre projects onto background in some view are dropped first
  // (carve_to_silhouettes, silhouettes widened by this fraction of the longer side, as refinement carves; < 0: none).
  double carve_margin = refine_carve_margin;
};

struct CompactReport {
  index_t before = 0, after = 0;
  index_t degenerate = 0;  // dropped for their scale or opacity
  index_t outside = 0;     // dropped outside the silhouettes
  index_t unseen = 0;      // dropped for their weight
};

// The Gaussians of `set` (in the cameras' world) that the views show; at least one sound Gaussian is kept. alpha
// [V, h, w] (may be null): the views' alpha at the cameras' size, all of one size.
template <class T>
CompactReport compact_splat(GaussianSet<T>& set, const std::vector<Camera>& views, const T* alpha = nullptr,
                            const CompactOptions& o = {}) {
  require(!views.empty(), "compact_splat: no views");
  require(std::isfinite(o.min_pixels) && o.min_pixels >= 0, "compact_splat: min_pixels ", o.min_pixels, " must be >= 0");
  check_cameras(views, "compact_splat");
  CompactReport r;
  r.before = set.size();
  if (r.before == 0) return r;
  // Degenerate rows first: the rasterizer refuses them.
  std::vector<index_t> sound;
  for (index_t i = 0; i < r.before; ++i) {
    bool ok = static_cast<double>(set.opacities(i)) >= 1.0 / 255;
    for (int k = 0; k < 3; ++k) ok = ok && std::isfinite(static_cast<double>(set.scales(i, k))) && set.scales(i, k) > T(0);
    if (ok) sound.push_back(i);
  }
  r.degenerate = r.before - static_cast<index_t>(sound.size());
  if (r.degenerate > 0) set = select_gaussians(set, sound);
  if (set.size() == 0) return r;  // nothing sound is left: an empty set
  if (alpha && o.carve_margin >= 0) {
    const index_t V = static_cast<index_t>(views.size()), h = views[0].height, w = views[0].width;
    std::vector<T> K(static_cast<std::size_t>(9 * V)), E(static_cast<std::size_t>(12 * V));
    for (index_t v = 0; v < V; ++v) {
      require(views[static_cast<std::size_t>(v)].width == w && views[static_cast<std::size_t>(v)].height == h,
              "compact_splat: the views with alpha must share one size");
      camera_arrays(views[static_cast<std::size_t>(v)], K.data() + 9 * v, E.data() + 12 * v);
    }
    const RefineViews<T> rv{V, h, w, nullptr, K.data(), E.data(), alpha};
    r.outside = carve_to_silhouettes(set, rv, alpha,
                                     static_cast<index_t>(std::llround(o.carve_margin * static_cast<double>(std::max(h, w)))));
  }
  std::vector<double> weight;
  raster::RenderOptions ro;
  raster::RenderWorkspace<T> ws;
  for (const Camera& cam : views) raster::max_blend_weights(set, raster::camera_view<T>(cam), ro, ws, weight);
  std::vector<index_t> keep;
  for (index_t i = 0; i < set.size(); ++i)
    if (weight[static_cast<std::size_t>(i)] >= o.min_pixels) keep.push_back(i);
  if (keep.empty()) keep.push_back(0);
  r.unseen = set.size() - static_cast<index_t>(keep.size());
  if (r.unseen > 0) set = select_gaussians(set, keep);
  r.after = set.size();
  return r;
}

}  // namespace model
}  // namespace v0
}  // namespace flexsplat
