#pragma once
// Cameras at the boundary between VGGT and the rest of the library. VGGT puts pixel u at the integer coordinate u,
// the decoder and rasterizer at u + 0.5 (docs/conventions.md), so the predicted principal point moves by half a
// pixel: the ray through depth sample u stays the same. Both directions have their adjoints.
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {
namespace model {

// K [V, 3, 3] in VGGT's integer-pixel convention -> the library's pixel-centre convention.
template <class T>
void intrinsics_from_vggt(T* K, const T* K_vggt, index_t views) {
  for (index_t v = 0; v < views; ++v) {
    for (int i = 0; i < 9; ++i) K[9 * v + i] = K_vggt[9 * v + i];
    K[9 * v + 2] += T(0.5);
    K[9 * v + 5] += T(0.5);
  }
}

// The inverse: the library's pixel-centre convention -> VGGT's integer-pixel one (ground truth for VGGT's heads).
template <class T>
void intrinsics_to_vggt(T* K_vggt, const T* K, index_t views) {
  for (index_t v = 0; v < views; ++v) {
    for (int i = 0; i < 9; ++i) K_vggt[9 * v + i] = K[9 * v + i];
    K_vggt[9 * v + 2] -= T(0.5);
    K_vggt[9 * v + 5] -= T(0.5);
  }
}

// The shift is constant: the gradient passes through unchanged (added into dK_vggt).
template <class T>
void intrinsics_from_vggt_backward(T* dK_vggt, const T* dK, index_t views) {
  for (index_t i = 0; i < 9 * views; ++i) dK_vggt[i] += dK[i];
}

}  // namespace model
}  // namespace v0
}  // namespace flexsplat
