#pragma once
// RGB pixel layouts: planar [3, h, w] (the networks' input and LPIPS) and interleaved [h, w, 3] (the rasterizer, PNG).
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {
namespace image {

template <class T>
void hwc_to_chw(T* chw, const T* hwc, index_t h, index_t w) {
  for (index_t p = 0; p < h * w; ++p)
    for (int c = 0; c < 3; ++c) chw[c * h * w + p] = hwc[3 * p + c];
}

template <class T>
void chw_to_hwc(T* hwc, const T* chw, index_t h, index_t w) {
  for (index_t p = 0; p < h * w; ++p)
    for (int c = 0; c < 3; ++c) hwc[3 * p + c] = chw[c * h * w + p];
}

// The adjoint of hwc_to_chw: adds a planar gradient into an interleaved one.
template <class T>
void add_chw_to_hwc(T* hwc, const T* chw, index_t h, index_t w) {
  for (index_t p = 0; p < h * w; ++p)
    for (int c = 0; c < 3; ++c) hwc[3 * p + c] += chw[c * h * w + p];
}

}  // namespace image
}  // namespace v0
}  // namespace flexsplat
