#pragma once
// 2-D rotary position embedding as VGGT uses it: each head's first half rotates with the token's y position, the
// second half with its x position; within a half, feature i pairs with feature i + half/2 (rotate-half convention).
// Position 0 has cos 1 and sin 0, so special tokens placed there stay unrotated.
#include <cmath>
#include <cstdint>
#include <vector>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/parallel.hpp"

namespace flexsplat {
inline namespace v0 {
namespace geometry {

template <class T>
struct Rope2DTable {
  index_t quarter = 0;       // head_dim / 4: frequencies per axis
  index_t positions = 0;     // table rows: valid positions are [0, positions)
  std::vector<T> cos, sin;   // [positions, quarter]
};

// Frequencies 1 / frequency^(2j / (head_dim/2)) for j < head_dim/4, as in VGGT (angles formed in float32 there).
template <class T>
Rope2DTable<T> rope2d_table(index_t head_dim, index_t positions, double frequency) {
  require(head_dim > 0 && head_dim % 4 == 0, "2-D RoPE needs a head dimension divisible by 4, got ", head_dim);
  require(frequency > 0, "2-D RoPE frequency must be positive, got ", frequency);
  require(positions >= 1, "2-D RoPE table needs at least one position, got ", positions);
  Rope2DTable<T> t;
  t.quarter = head_dim / 4;
  t.positions = positions;
  t.cos.resize(static_cast<std::size_t>(positions * t.quarter));
  t.sin.resize(t.cos.size());
  const index_t half = head_dim / 2;
  for (index_t j = 0; j < t.quarter; ++j) {
    const double inv_freq = 1.0 / std::pow(frequency, static_cast<double>(2 * j) / static_cast<double>(half));
    for (index_t p = 0; p < positions; ++p) {
      const double angle = static_cast<double>(p) * inv_freq;
      t.cos[p * t.quarter + j] = static_cast<T>(std::cos(angle));
      t.sin[p * t.quarter + j] = static_cast<T>(std::sin(angle));
    }
  }
  return t;
}

// Rotates in place rows of x: element (r, h, d) at x[r*row_stride + h*head_dim + d], positions[2r] = y,
// positions[2r+1] = x.
template <class T>
void rope2d_forward(T* x, index_t rows, index_t row_stride, index_t heads, index_t head_dim,
                    const std::int32_t* positions, const Rope2DTable<T>& table) {
  require(head_dim == 4 * table.quarter, "2-D RoPE table was built for head_dim ", 4 * table.quarter, ", got ",
          head_dim);
  for (index_t r = 0; r < rows; ++r)
    for (int axis = 0; axis < 2; ++axis) {
      const std::int32_t p = positions[2 * r + axis];
      require(p >= 0 && p < table.positions, "2-D RoPE position ", p, " of row ", r, " is outside [0, ",
              table.positions, ")");
    }
  const index_t q = table.quarter;
  parallel_for(rows, [&](index_t r0, index_t r1, int) {
    for (index_t r = r0; r < r1; ++r) {
      for (int axis = 0; axis < 2; ++axis) {
        const T* c = table.cos.data() + positions[2 * r + axis] * q;
        const T* s = table.sin.data() + positions[2 * r + axis] * q;
        for (index_t h = 0; h < heads; ++h) {
          T* a = x + r * row_stride + h * head_dim + axis * 2 * q;
          T* b = a + q;
          for (index_t j = 0; j < q; ++j) {
            const T a0 = a[j], b0 = b[j];
            a[j] = a0 * c[j] - b0 * s[j];
            b[j] = b0 * c[j] + a0 * s[j];
          }
        }
      }
    }
  });
}

// Adjoint of rope2d_forward (a rotation: the transpose rotates back); adds into d_x (d_x must not alias d_out).
template <class T>
void rope2d_backward(T* d_x, const T* d_out, index_t rows, index_t row_stride, index_t heads, index_t head_dim,
                     const std::int32_t* positions, const Rope2DTable<T>& table) {
  require(head_dim == 4 * table.quarter, "2-D RoPE table was built for head_dim ", 4 * table.quarter, ", got ",
          head_dim);
  const index_t q = table.quarter;
  parallel_for(rows, [&](index_t r0, index_t r1, int) {
    for (index_t r = r0; r < r1; ++r)
      for (int axis = 0; axis < 2; ++axis) {
        const T* c = table.cos.data() + positions[2 * r + axis] * q;
        const T* s = table.sin.data() + positions[2 * r + axis] * q;
        for (index_t h = 0; h < heads; ++h) {
          const index_t off = r * row_stride + h * head_dim + axis * 2 * q;
          for (index_t j = 0; j < q; ++j) {
            const T ga = d_out[off + j], gb = d_out[off + q + j];
            d_x[off + j] += ga * c[j] + gb * s[j];
            d_x[off + q + j] += gb * c[j] - ga * s[j];
          }
        }
      }
  });
}

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
