#pragma once
// GeometryResult: the geometry stage's outputs (cameras, depth, confidence, depth features) as the rest of the model
// reads them; inference (predict.hpp) needs it without the training objective.
#include <algorithm>
#include <vector>

#include "flexsplat/core/tensor.hpp"
#include "flexsplat/decoder/gaussians.hpp"

namespace flexsplat {
inline namespace v0 {
namespace model {

// What the appearance side reads from the geometry stage, in the library's conventions (docs/conventions.md). The
// same struct holds the gradients with respect to each field.
template <class T>
struct GeometryResult {
  index_t views = 0, h = 0, w = 0;                            // model input size; depth is [V, h, w]
  index_t feature_channels = 0, feature_h = 0, feature_w = 0;  // depth features [V, C, fh, fw]
  AlignedVector<T> extrinsics;  // [V, 3, 4] world-to-camera
  AlignedVector<T> K;           // [V, 3, 3] pixel centres at +0.5
  AlignedVector<T> depth;       // [V, h, w] camera z
  AlignedVector<T> confidence;  // [V, h, w] the depth head's confidence (>= 1 for VGGT's expp1)
  AlignedVector<T> features;    // [V, C, fh, fw]

  void resize(index_t v, index_t height, index_t width, index_t c, index_t fh, index_t fw) {
    views = v, h = height, w = width, feature_channels = c, feature_h = fh, feature_w = fw;
    extrinsics.resize(static_cast<std::size_t>(12 * v));
    K.resize(static_cast<std::size_t>(9 * v));
    depth.resize(static_cast<std::size_t>(v * h * w));
    confidence.resize(depth.size());
    features.resize(static_cast<std::size_t>(v * c * fh * fw));
  }
  // Same sizes as `like`, all zero (a gradient accumulator).
  void zero_like(const GeometryResult& like) {
    resize(like.views, like.h, like.w, like.feature_channels, like.feature_h, like.feature_w);
    for (auto* v : {&extrinsics, &K, &depth, &confidence, &features}) std::fill(v->begin(), v->end(), T(0));
  }
  decoder::ViewGeometry<T> view_geometry() const {
    return {views, w, h, w, h, K.data(), extrinsics.data(), depth.data()};
  }
};

}  // namespace model
}  // namespace v0
}  // namespace flexsplat
