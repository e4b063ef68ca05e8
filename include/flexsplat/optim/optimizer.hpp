#pragma once
// AdamW over a ParamStore (PyTorch's torch.optim.AdamW: decoupled weight decay, bias-corrected moments), global-norm
// gradient clipping and the warmup + cosine learning-rate schedule. Every element's update depends only on its own
// values and the norm is reduced over fixed-size chunks in a fixed order, so results are bit-identical for any thread
// count.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <numbers>
#include <vector>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/inline.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/profile.hpp"
#include "flexsplat/core/simd.hpp"
#include "flexsplat/optim/params.hpp"

namespace flexsplat {
inline namespace v0 {
namespace train {

struct AdamWConfig {
  double beta1 = 0.9, beta2 = 0.999, eps = 1e-8;
  double weight_decay = 0.05;  // VGGT's training config; applies to tensors with ParamInfo::decay only
};

namespace detail {
inline constexpr index_t adamw_block = 4096;
// One element (T) or one SIMD batch of elements, the same operations in the same order on both paths.
template <class V, class T>
FLEXSPLAT_ALWAYS_INLINE void adamw_lane(V& p, V& m, V& v, V g, T b1, T b2, T shrink, T step_size, T inv_sqrt_c2, T eps) {
  m = V(b1) * m + V(T(1) - b1) * g;
  v = V(b2) * v + V(T(1) - b2) * g * g;
  p = p * V(shrink) - V(step_size) * m / (simd::lane_sqrt(v) * V(inv_sqrt_c2) + V(eps));
}
}  // namespace detail

// One AdamW update with learning rate lr; step is the 1-based number of this update (bias correction). For every
// tensor, with lr_t = lr * ParamInfo::lr_scale, element-wise: p -= lr_t * wd * p (decay tensors only);
// m = b1 m + (1 - b1) g; v = b2 v + (1 - b2) g^2; p -= lr_t * (m / (1 - b1^step)) / (sqrt(v / (1 - b2^step)) + eps).
template <class T>
void adamw_step(ParamStore<T>& store, const AdamWConfig& c, double lr, std::uint64_t step,
                ThreadPool& pool = global_pool()) {
  const profile::Scope timed(profile::Op::update);
  require(step >= 1, "adamw: step must be >= 1 (1-based), got ", step);
  require(std::isfinite(lr) && lr >= 0, "adamw: learning rate ", lr, " must be finite and >= 0");
  require(c.beta1 >= 0 && c.beta1 < 1 && c.beta2 >= 0 && c.beta2 < 1 && c.eps > 0 && c.weight_decay >= 0,
          "adamw: beta1 ", c.beta1, ", beta2 ", c.beta2, " must be in [0, 1), eps ", c.eps, " > 0, weight_decay ",
          c.weight_decay, " >= 0");
  const double c1 = 1.0 - std::pow(c.beta1, static_cast<double>(step));
  const double c2 = 1.0 - std::pow(c.beta2, static_cast<double>(step));
  const T b1 = static_cast<T>(c.beta1), b2 = static_cast<T>(c.beta2);
  const T inv_sqrt_c2 = static_cast<T>(1.0 / std::sqrt(c2)), eps = static_cast<T>(c.eps);
  T* p = store.params();
  T* m = store.adam_m();
  T* v = store.adam_v();
  const T* g = store.grads();
  for (const auto& t : store.tensors()) {
    const double lr_t = lr * t.lr_scale;
    const T shrink = static_cast<T>(1.0 - (t.decay ? lr_t * c.weight_decay : 0.0));
    const T step_size = static_cast<T>(lr_t / c1);
    const index_t o = t.offset;
    // Fixed blocks (a multiple of the SIMD width): whether an element takes the vector or the scalar path depends on
    // its position in the tensor only, never on the thread count.
    const index_t blocks = (t.numel + detail::adamw_block - 1) / detail::adamw_block;
    parallel_for(blocks, [&](index_t k0, index_t k1, int) {
      using V = simd::batch<T>;
      constexpr index_t W = static_cast<index_t>(simd::width<T>);
      for (index_t k = k0; k < k1; ++k) {
        const index_t end = std::min(t.numel, (k + 1) * detail::adamw_block);
        index_t i = k * detail::adamw_block;
        for (; i + W <= end; i += W) {
          V pi = V::load_unaligned(p + o + i), mi = V::load_unaligned(m + o + i), vi = V::load_unaligned(v + o + i);
          detail::adamw_lane(pi, mi, vi, V::load_unaligned(g + o + i), b1, b2, shrink, step_size, inv_sqrt_c2, eps);
          pi.store_unaligned(p + o + i), mi.store_unaligned(m + o + i), vi.store_unaligned(v + o + i);
        }
        for (; i < end; ++i)
          detail::adamw_lane(p[o + i], m[o + i], v[o + i], g[o + i], b1, b2, shrink, step_size, inv_sqrt_c2, eps);
      }
    }, pool);
  }
}

namespace detail {
inline constexpr index_t norm_chunk = 8192;
}

// Global L2 norm of every tensor's gradient (double accumulation). A non-finite norm is an error naming the first
// tensor (registration order) holding a non-finite gradient, its index and value.
template <class T>
double grad_norm(const ParamStore<T>& store, ThreadPool& pool = global_pool()) {
  const T* g = store.grads();
  double total = 0;
  std::vector<double> partial;
  for (const auto& t : store.tensors()) {
    const index_t chunks = (t.numel + detail::norm_chunk - 1) / detail::norm_chunk;
    partial.assign(static_cast<std::size_t>(chunks), 0.0);
    parallel_for(chunks, [&](index_t c0, index_t c1, int) {
      for (index_t c = c0; c < c1; ++c) {
        double s = 0;
        const index_t end = std::min(t.numel, (c + 1) * detail::norm_chunk);
        for (index_t i = c * detail::norm_chunk; i < end; ++i) {
          const double x = static_cast<double>(g[t.offset + i]);
          s += x * x;
        }
        partial[static_cast<std::size_t>(c)] = s;
      }
    }, pool);
    for (double s : partial) total += s;
  }
  const double norm = std::sqrt(total);
  if (std::isfinite(norm)) return norm;
  for (const auto& t : store.tensors())
    for (index_t i = 0; i < t.numel; ++i)
      if (!std::isfinite(static_cast<double>(g[t.offset + i])))
        fail("gradient norm is not finite: tensor '", t.name, "' ", safetensors::shape_string(t.shape),
             " has gradient ", static_cast<double>(g[t.offset + i]), " at element ", i);
  fail("gradient norm overflows (", norm, ") although every gradient is finite");
}

// Scales every gradient by max_norm / (norm + 1e-6) when the global norm exceeds max_norm (PyTorch's
// clip_grad_norm_); max_norm <= 0 only measures. Returns the norm before clipping.
template <class T>
double clip_grad_norm(ParamStore<T>& store, double max_norm, ThreadPool& pool = global_pool()) {
  const double norm = grad_norm(store, pool);
  if (max_norm > 0 && norm > max_norm) {
    const T scale = static_cast<T>(max_norm / (norm + 1e-6));
    T* g = store.grads();
    parallel_for(store.size(), [&](index_t i0, index_t i1, int) {
      for (index_t i = i0; i < i1; ++i) g[i] *= scale;
    }, pool);
  }
  return norm;
}

// Linear warmup then cosine decay, as llm.c: for step s (0-based count of updates done before this one)
//   s < warmup:           peak * (s + 1) / warmup
//   warmup <= s < total:  final + (peak - final) * (1 + cos(pi * (s - warmup) / (total - warmup))) / 2
//   s >= total:           final
struct CosineSchedule {
  double peak_lr = 1e-4, final_lr = 0.0;
  std::uint64_t warmup_steps = 0, total_steps = 1;

  void validate() const {
    require(std::isfinite(peak_lr) && std::isfinite(final_lr) && peak_lr >= 0 && final_lr >= 0,
            "cosine schedule: learning rates ", peak_lr, " and ", final_lr, " must be finite and >= 0");
    require(total_steps >= 1 && warmup_steps <= total_steps, "cosine schedule: warmup ", warmup_steps,
            " steps must not exceed the total ", total_steps, " (>= 1)");
  }
  double lr(std::uint64_t s) const {
    validate();
    if (s < warmup_steps) return peak_lr * static_cast<double>(s + 1) / static_cast<double>(warmup_steps);
    if (s >= total_steps) return final_lr;
    const double ratio = static_cast<double>(s - warmup_steps) / static_cast<double>(total_steps - warmup_steps);
    return final_lr + (peak_lr - final_lr) * 0.5 * (1.0 + std::cos(std::numbers::pi * ratio));
  }
};

}  // namespace train
}  // namespace v0
}  // namespace flexsplat
