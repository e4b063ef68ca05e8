#pragma once
// Scaled dot-product attention with a tiled online softmax: memory is linear in the token count (the n_q x n_kv
// score matrix never exists). Score tiles are kept transposed (keys x query rows), so the running max / sum, the
// rescale and exp are vectorised across query rows and K, V are read in place as broadcast operands (no packing);
// only the query block is packed, transposed and pre-scaled, once per task. Backward recomputes score tiles from the
// saved log-sum-exp, in two race-free passes (key blocks own dK/dV, query blocks own dQ), so results do not depend on
// the thread count. Each entry point has a scalar path (the reference), the build's simd::batch path and, for float,
// run-time dispatched AVX2 / AVX-512 lanes (simd::Lanes), which a portable build takes on CPUs that have them.
#include <algorithm>
#include <cmath>
#include <limits>
#include <span>
#include <type_traits>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/profile.hpp"
#include "flexsplat/core/simd.hpp"
#include "flexsplat/core/simd_dispatch.hpp"  // its lane overloads must be visible where the lane templates are used
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {
namespace nn {

// Element (b, h, row, d) of a tensor X lives at X[b*batch + h*head + row*row_stride + d].
struct AttentionStrides {
  index_t batch = 0, head = 0, row = 0;
};

struct AttentionLayout {
  index_t batch = 1, heads = 1, n_q = 0, n_kv = 0, head_dim = 0;
  AttentionStrides q, k, v, out;
};

inline constexpr index_t attention_q_block = 64;
inline constexpr index_t attention_kv_block = 256;

// Backward's packed query / dO rows and its dK / dV accumulators have rows of whole 64-byte float vectors, so the
// outer products run in full lanes for any head_dim (12 would otherwise fall to scalar code).
inline index_t attention_padded_dim(index_t head_dim) { return (head_dim + 15) / 16 * 16; }

// Scratch elements one worker needs; pass at least this times the pool size. Key and value rows are then copied into
// contiguous tiles once per (query block, key block).
inline index_t attention_scratch_per_worker(index_t head_dim) {
  constexpr index_t Bq = attention_q_block, Bk = attention_kv_block;
  const index_t dp = attention_padded_dim(head_dim);
  return 3 * Bq * head_dim + 2 * Bq * dp + 2 * Bk * (Bq + head_dim + dp) + 4 * Bq;
}

// Scratch per worker for sequences of at most `tokens` queries and keys (linear in tokens). With at least this times
// the pool size, forward copies K and V once per (batch, head) instead of once per tile, and backward can run in one
// pass per (batch, head) holding that head's dQ (5 instead of 7 tile products). Results are bit-identical either way.
inline index_t attention_scratch_per_worker(index_t head_dim, index_t tokens) {
  const index_t padded = (tokens + attention_q_block - 1) / attention_q_block * attention_q_block;
  return attention_scratch_per_worker(head_dim) + std::max(2 * tokens, padded) * head_dim;
}

// Whether attention_backward (with d_q) runs one pass per (batch, head), given `scratch` elements and `workers`: when
// the scratch holds a head's dQ^T and the heads spread evenly over the workers; otherwise key-block tasks (dK, dV) then
// query-block tasks (dQ), which recompute the score tiles. Both sum every gradient in the same order.
inline bool attention_backward_one_pass(const AttentionLayout& L, std::size_t scratch, index_t workers) {
  const index_t q_blocks = (L.n_q + attention_q_block - 1) / attention_q_block, heads_total = L.batch * L.heads;
  return static_cast<index_t>(scratch) >=
             (attention_scratch_per_worker(L.head_dim) + q_blocks * attention_q_block * L.head_dim) * workers &&
         (heads_total % workers == 0 || heads_total >= 4 * workers);
}

namespace detail {

inline void check_scratch(std::size_t have, index_t head_dim, int workers) {
  require(static_cast<index_t>(have) >= attention_scratch_per_worker(head_dim) * workers, "attention scratch has ", have,
          " elements, needs ", attention_scratch_per_worker(head_dim) * workers, " (head_dim ", head_dim, ", ", workers,
          " workers)");
}

// Register tile of the kernels below: `vecs` lane vectors times `broadcasts` broadcast scalars of accumulators.
template <class V>
struct AttentionTile {
  static constexpr index_t lanes = static_cast<index_t>(simd::lane_count<V>::value);
  static constexpr index_t vecs = 4;
  static constexpr index_t span = lanes * vecs;
  static constexpr index_t broadcasts = sizeof(V) >= 64 ? 6 : 3;  // AVX-512 has 32 vector registers, the others 16
};
static_assert(attention_q_block % AttentionTile<simd::batch<float>>::span == 0 &&
              attention_q_block % AttentionTile<simd::batch<double>>::span == 0);

template <index_t N, class F>
void call_remainder(index_t rest, index_t at, F& f) {
  if constexpr (N >= 1) {
    if (rest == N) f.template operator()<N>(at);
    else call_remainder<N - 1>(rest, at, f);
  }
}

// f.template operator()<Size>(start) over [0, n) in chunks of Max, then one chunk of the remainder.
template <index_t Max, class F>
void for_chunks(index_t n, F&& f) {
  index_t at = 0;
  for (; at + Max <= n; at += Max) f.template operator()<Max>(at);
  call_remainder<Max - 1>(n - at, at, f);
}

// out_t[c*ld + r] = sum_j x[c*x_row + j] * yt[j*ld + r] for c < KC, r < span.
template <class V, index_t KC, class T>
inline void dot_t_tile(T* out_t, index_t ld, const T* x, index_t x_row, const T* yt, index_t d) {
  using Tile = AttentionTile<V>;
  constexpr index_t NV = Tile::vecs, W = Tile::lanes;
  V acc[KC][NV];
  for (index_t a = 0; a < KC; ++a)
    for (index_t v = 0; v < NV; ++v) acc[a][v] = V(T(0));
  for (index_t j = 0; j < d; ++j) {
    V y[NV];
    for (index_t v = 0; v < NV; ++v) y[v] = simd::lane_load<V>(yt + j * ld + v * W);
    for (index_t a = 0; a < KC; ++a) {
      const V b(x[a * x_row + j]);
      for (index_t v = 0; v < NV; ++v) acc[a][v] = simd::lane_fma(b, y[v], acc[a][v]);
    }
  }
  for (index_t a = 0; a < KC; ++a)
    for (index_t v = 0; v < NV; ++v) simd::lane_store(out_t + a * ld + v * W, acc[a][v]);
}

// out_t [cols][ld] = x [cols rows, d] times yt [d][ld]: a transposed score tile. ld is a multiple of Tile::span.
template <class V, class T>
void dot_t_block(T* out_t, index_t ld, const T* x, index_t x_row, index_t cols, const T* yt, index_t d) {
  using Tile = AttentionTile<V>;
  for (index_t r0 = 0; r0 < ld; r0 += Tile::span)
    for_chunks<Tile::broadcasts>(cols, [&]<index_t KC>(index_t c) {
      dot_t_tile<V, KC>(out_t + c * ld + r0, ld, x + c * x_row, x_row, yt + r0, d);
    });
}

// acc_t[j*ld + r] = rescale[r] * acc_t[j*ld + r] + sum_c x[c*x_row + j] * zt[c*ld + r] for j < DC, r < span.
template <class V, index_t DC, class T>
inline void axpy_t_tile(T* acc_t, index_t ld, const T* rescale, const T* x, index_t x_row, const T* zt, index_t cols) {
  using Tile = AttentionTile<V>;
  constexpr index_t NV = Tile::vecs, W = Tile::lanes;
  V acc[DC][NV];
  for (index_t a = 0; a < DC; ++a)
    for (index_t v = 0; v < NV; ++v) acc[a][v] = simd::lane_load<V>(acc_t + a * ld + v * W);
  if (rescale)
    for (index_t v = 0; v < NV; ++v) {
      const V s = simd::lane_load<V>(rescale + v * W);
      for (index_t a = 0; a < DC; ++a) acc[a][v] = acc[a][v] * s;
    }
  for (index_t c = 0; c < cols; ++c) {
    V z[NV];
    for (index_t v = 0; v < NV; ++v) z[v] = simd::lane_load<V>(zt + c * ld + v * W);
    for (index_t a = 0; a < DC; ++a) {
      const V b(x[c * x_row + a]);
      for (index_t v = 0; v < NV; ++v) acc[a][v] = simd::lane_fma(b, z[v], acc[a][v]);
    }
  }
  for (index_t a = 0; a < DC; ++a)
    for (index_t v = 0; v < NV; ++v) simd::lane_store(acc_t + a * ld + v * W, acc[a][v]);
}

// acc_t [d][ld] = rescale (per column, may be null) * acc_t + x^T [d, cols rows] times zt [cols][ld].
template <class V, class T>
void axpy_t_block(T* acc_t, index_t ld, const T* rescale, const T* x, index_t x_row, const T* zt, index_t cols, index_t d) {
  using Tile = AttentionTile<V>;
  for (index_t r0 = 0; r0 < ld; r0 += Tile::span)
    for_chunks<Tile::broadcasts>(d, [&]<index_t DC>(index_t j) {
      axpy_t_tile<V, DC>(acc_t + j * ld + r0, ld, rescale ? rescale + r0 : nullptr, x + j, x_row, zt + r0, cols);
    });
}

// y[c*y_row + j] += sum_{r < rows} zt[c*ld + r] * x[r*x_row + j] for c < KC, j < NV lanes vectors.
template <class V, index_t KC, index_t NV, class T>
inline void outer_tile(T* y, index_t y_row, const T* zt, index_t ld, const T* x, index_t x_row, index_t rows) {
  constexpr index_t W = AttentionTile<V>::lanes;
  V acc[KC][NV];
  for (index_t a = 0; a < KC; ++a)
    for (index_t v = 0; v < NV; ++v) acc[a][v] = simd::lane_load<V>(y + a * y_row + v * W);
  for (index_t r = 0; r < rows; ++r) {
    V xv[NV];
    for (index_t v = 0; v < NV; ++v) xv[v] = simd::lane_load<V>(x + r * x_row + v * W);
    for (index_t a = 0; a < KC; ++a) {
      const V b(zt[a * ld + r]);
      for (index_t v = 0; v < NV; ++v) acc[a][v] = simd::lane_fma(b, xv[v], acc[a][v]);
    }
  }
  for (index_t a = 0; a < KC; ++a)
    for (index_t v = 0; v < NV; ++v) simd::lane_store(y + a * y_row + v * W, acc[a][v]);
}

// y [cols rows, d] += zt [cols][ld] (first `rows` columns) times x [rows, d]; a head_dim tail runs in scalar lanes.
template <class V, class T>
void outer_block(T* y, index_t y_row, index_t cols, const T* zt, index_t ld, const T* x, index_t x_row, index_t rows,
                 index_t d) {
  using Tile = AttentionTile<V>;
  constexpr index_t W = Tile::lanes;
  const index_t full = d / W;
  for_chunks<Tile::vecs>(full, [&]<index_t NV>(index_t v0) {
    for_chunks<Tile::broadcasts>(cols, [&]<index_t KC>(index_t c) {
      outer_tile<V, KC, NV>(y + c * y_row + v0 * W, y_row, zt + c * ld, ld, x + v0 * W, x_row, rows);
    });
  });
  if constexpr (W > 1)
    if (full * W < d) outer_block<T>(y + full * W, y_row, cols, zt, ld, x + full * W, x_row, rows, d - full * W);
}

// dst [rows][ld] contiguous <- rows of src, zero past d: strided key / value rows would cost a TLB miss per row in the
// kernels.
template <class T>
void pack_rows(T* dst, const T* src, index_t row, index_t rows, index_t d, index_t ld) {
  for (index_t r = 0; r < rows; ++r) {
    std::copy(src + r * row, src + r * row + d, dst + r * ld);
    std::fill(dst + r * ld + d, dst + (r + 1) * ld, T(0));
  }
}
template <class T>
void pack_rows(T* dst, const T* src, index_t row, index_t rows, index_t d) {
  pack_rows(dst, src, row, rows, d, d);
}

// y [rows, d] (row stride y_row) += the first d columns of acc [rows][ld].
template <class T>
void add_rows(T* y, index_t y_row, const T* acc, index_t ld, index_t rows, index_t d) {
  for (index_t r = 0; r < rows; ++r)
    for (index_t j = 0; j < d; ++j) y[r * y_row + j] += acc[r * ld + j];
}

// dst[j*ld + r] = scale * src[r*row + j] for r < rows, zero for rows <= r < ld.
// Row-major traversal of src: its rows may be far apart (fused q|k|v buffers), one TLB entry each.
template <class T>
void pack_transposed(T* dst, index_t ld, const T* src, index_t row, index_t rows, index_t d, T scale) {
  for (index_t r = 0; r < rows; ++r)
    for (index_t j = 0; j < d; ++j) dst[j * ld + r] = scale * src[r * row + j];
  for (index_t j = 0; j < d; ++j) std::fill(dst + j * ld + rows, dst + (j + 1) * ld, T(0));
}

// One key block of the online softmax on a transposed tile st [cols][q_block]: st becomes exp(s - new max), the
// running max / sum are updated and rescale[r] = exp(old max - new max) for the output accumulator.
template <class V, class T>
void online_softmax_t(T* st, index_t cols, T* row_max, T* row_sum, T* rescale) {
  constexpr index_t W = AttentionTile<V>::lanes, NB = attention_q_block / W;
  V mx[NB], sum[NB];
  for (index_t v = 0; v < NB; ++v) mx[v] = simd::lane_load<V>(row_max + v * W);
  for (index_t c = 0; c < cols; ++c)
    for (index_t v = 0; v < NB; ++v) mx[v] = simd::lane_max(mx[v], simd::lane_load<V>(st + c * attention_q_block + v * W));
  for (index_t v = 0; v < NB; ++v) {
    simd::lane_store(rescale + v * W, simd::lane_exp(simd::lane_load<V>(row_max + v * W) - mx[v]));  // 0 on the first block
    simd::lane_store(row_max + v * W, mx[v]);
    sum[v] = V(T(0));
  }
  for (index_t c = 0; c < cols; ++c)
    for (index_t v = 0; v < NB; ++v) {
      T* p = st + c * attention_q_block + v * W;
      const V e = simd::lane_exp(simd::lane_load<V>(p) - mx[v]);
      simd::lane_store(p, e);
      sum[v] = sum[v] + e;
    }
  for (index_t v = 0; v < NB; ++v)
    simd::lane_store(row_sum + v * W,
                     simd::lane_fma(simd::lane_load<V>(row_sum + v * W), simd::lane_load<V>(rescale + v * W), sum[v]));
}

// Backward of one transposed tile: st <- P = exp(s - lse), dst <- scale * P * (dP - delta).
template <class V, class T>
void softmax_grad_t(T* st, T* dst, index_t cols, const T* lse, const T* delta, T scale) {
  constexpr index_t W = AttentionTile<V>::lanes, NB = attention_q_block / W;
  V l[NB], dl[NB];
  for (index_t v = 0; v < NB; ++v) {
    l[v] = simd::lane_load<V>(lse + v * W);
    dl[v] = simd::lane_load<V>(delta + v * W);
  }
  const V sc(scale);
  for (index_t c = 0; c < cols; ++c)
    for (index_t v = 0; v < NB; ++v) {
      T* ps = st + c * attention_q_block + v * W;
      T* pd = dst + c * attention_q_block + v * W;
      const V p = simd::lane_exp(simd::lane_load<V>(ps) - l[v]);
      simd::lane_store(ps, p);
      simd::lane_store(pd, sc * p * (simd::lane_load<V>(pd) - dl[v]));
    }
}

}  // namespace detail

// out = softmax(scale * q k^T) v per (batch, head). lse [batch*heads*n_q] (may be null) receives log-sum-exp rows,
// which backward needs. With n_kv == 0 the output is zero and lse is -inf. `lanes` selects the kernels' lane type.
template <class T>
void attention_forward_impl(T* out, T* lse, const T* q, const T* k, const T* v, const AttentionLayout& L, T scale,
                            std::span<T> scratch, simd::Lanes lanes, ThreadPool& pool = global_pool()) {
  using namespace detail;
  const profile::Scope timed(profile::Op::attention_forward,
                             4.0 * double(L.batch * L.heads) * double(L.n_q) * double(L.n_kv) * double(L.head_dim));
  constexpr index_t Bq = attention_q_block, Bk = attention_kv_block;
  const index_t d = L.head_dim;
  const index_t q_blocks = (L.n_q + Bq - 1) / Bq;
  const index_t tasks = L.batch * L.heads * q_blocks;
  check_scratch(scratch.size(), d, pool.size());
  const index_t base = attention_scratch_per_worker(d);
  const bool whole_heads = static_cast<index_t>(scratch.size()) >= (base + 2 * L.n_kv * d) * pool.size();
  const index_t per_worker = base + (whole_heads ? 2 * L.n_kv * d : 0);
  parallel_for(tasks, [&](index_t t0, index_t t1, int worker) {
   simd::with_lanes<T>(lanes, [&](auto* lane_type) {
    using V = std::remove_pointer_t<decltype(lane_type)>;
    T* qt = scratch.data() + worker * per_worker;  // [d][Bq] scale * Q^T
    T* ot = qt + d * Bq;                                                 // [d][Bq] unnormalised output^T
    T* st = ot + d * Bq;                                                 // [Bk][Bq] scores^T, then exp
    T* row_max = st + Bk * Bq;
    T* row_sum = row_max + Bq;
    T* rescale = row_sum + Bq;
    T* kp = rescale + Bq;                                    // [Bk][d] key block, or [n_kv][d] whole head
    T* vp = kp + (whole_heads ? L.n_kv : Bk) * d;             // the same for values
    index_t packed_bh = -1;
    for (index_t t = t0; t < t1; ++t) {
      const index_t bh = t / q_blocks, qb = t % q_blocks, b = bh / L.heads, h = bh % L.heads;
      const index_t r0 = qb * Bq, rows = std::min(Bq, L.n_q - r0);
      pack_transposed(qt, Bq, q + b * L.q.batch + h * L.q.head + r0 * L.q.row, L.q.row, rows, d, scale);
      std::fill(ot, ot + d * Bq, T(0));
      std::fill(row_max, row_max + Bq, -std::numeric_limits<T>::infinity());
      std::fill(row_sum, row_sum + Bq, T(0));
      const T* k_head = k + b * L.k.batch + h * L.k.head;
      const T* v_head = v + b * L.v.batch + h * L.v.head;
      if (whole_heads && bh != packed_bh) {
        pack_rows(kp, k_head, L.k.row, L.n_kv, d);
        pack_rows(vp, v_head, L.v.row, L.n_kv, d);
        packed_bh = bh;
      }
      for (index_t c0 = 0; c0 < L.n_kv; c0 += Bk) {
        const index_t cols = std::min(Bk, L.n_kv - c0);
        if (!whole_heads) {
          pack_rows(kp, k_head + c0 * L.k.row, L.k.row, cols, d);
          pack_rows(vp, v_head + c0 * L.v.row, L.v.row, cols, d);
        }
        const index_t at = whole_heads ? c0 * d : 0;
        dot_t_block<V>(st, Bq, kp + at, d, cols, qt, d);
        online_softmax_t<V>(st, cols, row_max, row_sum, rescale);
        axpy_t_block<V>(ot, Bq, rescale, vp + at, d, st, cols, d);
      }
      T* o = out + b * L.out.batch + h * L.out.head + r0 * L.out.row;
      for (index_t r = 0; r < rows; ++r) {
        const T sum = row_sum[r];
        for (index_t j = 0; j < d; ++j) o[r * L.out.row + j] = sum > T(0) ? ot[j * Bq + r] / sum : T(0);
        if (lse) lse[bh * L.n_q + r0 + r] = row_max[r] + std::log(sum);
      }
    }
   });
  }, pool);
}

// Adds into d_q, d_k, d_v (each may be null). Needs the forward's out and lse. `lanes` selects the kernels' lane type.
// Long (about 170 lines): its packing and block kernels are lambdas over one per-worker scratch layout set up here.
template <class T>
void attention_backward_impl(T* d_q, T* d_k, T* d_v, const T* d_out, const T* out, const T* lse, const T* q, const T* k,
                             const T* v, const AttentionLayout& L, T scale, std::span<T> scratch, simd::Lanes lanes,
                             ThreadPool& pool = global_pool()) {
  using namespace detail;
  const profile::Scope timed(profile::Op::attention_backward,
                             8.0 * double(L.batch * L.heads) * double(L.n_q) * double(L.n_kv) * double(L.head_dim));
  constexpr index_t Bq = attention_q_block, Bk = attention_kv_block;
  const index_t d = L.head_dim;
  const index_t q_blocks = (L.n_q + Bq - 1) / Bq;
  const index_t kv_blocks = (L.n_kv + Bk - 1) / Bk;
  check_scratch(scratch.size(), d, pool.size());
  if (L.n_q == 0 || L.n_kv == 0) return;

  struct Buffers {
    T *qt, *dot, *dqt, *qp, *dop, *st, *dst, *lse, *delta, *dk, *dv, *kp, *vp, *dq_head;
  };
  const index_t dp = attention_padded_dim(d);
  const index_t base = attention_scratch_per_worker(d), heads_total = L.batch * L.heads, workers = pool.size();
  const index_t have = static_cast<index_t>(scratch.size());
  const bool one_pass = d_q && attention_backward_one_pass(L, scratch.size(), workers);
  const bool whole_heads = !one_pass && have >= (base + 2 * L.n_kv * d) * workers;
  const index_t per_worker = base + (one_pass ? q_blocks * Bq * d : whole_heads ? 2 * L.n_kv * d : 0);
  auto buffers = [&](int worker) {
    Buffers s;
    s.qt = scratch.data() + worker * per_worker;  // [d][Bq] scale * Q^T
    s.dot = s.qt + d * Bq;                                              // [d][Bq] dO^T
    s.dqt = s.dot + d * Bq;                                             // [d][Bq] dQ^T of pass 2
    s.qp = s.dqt + d * Bq;                                              // [Bq][dp] Q rows
    s.dop = s.qp + dp * Bq;                                             // [Bq][dp] dO rows
    s.st = s.dop + dp * Bq;                                             // [Bk][Bq] scores^T, then P^T
    s.dst = s.st + Bk * Bq;                                             // [Bk][Bq] dP^T, then scale * dS^T
    s.lse = s.dst + Bk * Bq;
    s.delta = s.lse + Bq;
    s.dk = s.delta + Bq;                                                // [Bk][dp] dK of one key block
    s.dv = s.dk + Bk * dp;                                              // [Bk][dp] dV of one key block
    s.kp = s.dv + Bk * dp;                              // [Bk][d] key block, or [n_kv][d] whole head (dQ pass)
    s.vp = s.kp + (whole_heads ? L.n_kv : Bk) * d;       // the same for values
    s.dq_head = s.qt + base;                            // [q_blocks][d][Bq] dQ^T of one head (one pass)
    return s;
  };
  // Packs query block qb of (b, h): Q^T, dO^T, lse (+inf on padding and non-finite rows: P = 0) and delta = dO . O.
  auto load_queries = [&](const Buffers& s, index_t b, index_t h, index_t qb) {
    const index_t r0 = qb * Bq, rows = std::min(Bq, L.n_q - r0);
    const T* d_o = d_out + b * L.out.batch + h * L.out.head + r0 * L.out.row;
    const T* o = out + b * L.out.batch + h * L.out.head + r0 * L.out.row;
    pack_transposed(s.qt, Bq, q + b * L.q.batch + h * L.q.head + r0 * L.q.row, L.q.row, rows, d, scale);
    pack_transposed(s.dot, Bq, d_o, L.out.row, rows, d, T(1));
    pack_rows(s.qp, q + b * L.q.batch + h * L.q.head + r0 * L.q.row, L.q.row, rows, d, dp);
    pack_rows(s.dop, d_o, L.out.row, rows, d, dp);
    for (index_t r = 0; r < Bq; ++r) {
      const T row_lse = r < rows ? lse[(b * L.heads + h) * L.n_q + r0 + r] : T(0);
      s.lse[r] = r < rows && std::isfinite(row_lse) ? row_lse : std::numeric_limits<T>::infinity();
      T delta = 0;
      if (r < rows)
        for (index_t j = 0; j < d; ++j) delta += d_o[r * L.out.row + j] * o[r * L.out.row + j];
      s.delta[r] = delta;
    }
    return rows;
  };
  // Copies `count` key / value rows from row c0 of head (b, h) to the start of the packed buffers.
  auto load_keys = [&](const Buffers& s, index_t b, index_t h, index_t c0, index_t count) {
    pack_rows(s.kp, k + b * L.k.batch + h * L.k.head + c0 * L.k.row, L.k.row, count, d);
    pack_rows(s.vp, v + b * L.v.batch + h * L.v.head + c0 * L.v.row, L.v.row, count, d);
  };
  // P^T and scale * dS^T of packed keys / values kp, vp (cols rows) against the packed query block.
  auto tile = [&](auto* lane_type, const Buffers& s, const T* kp, const T* vp, index_t cols) {
    using V = std::remove_pointer_t<decltype(lane_type)>;
    dot_t_block<V>(s.st, Bq, kp, d, cols, s.qt, d);
    dot_t_block<V>(s.dst, Bq, vp, d, cols, s.dot, d);
    softmax_grad_t<V>(s.st, s.dst, cols, s.lse, s.delta, scale);
  };

  // dK and dV of key block kb of head (b, h): zeroed, summed over every query block, then added into d_k and d_v.
  auto start_keys = [&](const Buffers& s, index_t cols) {
    std::fill(s.dk, s.dk + cols * dp, T(0));
    std::fill(s.dv, s.dv + cols * dp, T(0));
  };
  auto add_tile_dkv = [&](auto* lane_type, const Buffers& s, index_t cols, index_t rows) {
    using V = std::remove_pointer_t<decltype(lane_type)>;
    if (d_v) outer_block<V>(s.dv, dp, cols, s.st, Bq, s.dop, dp, rows, dp);
    if (d_k) outer_block<V>(s.dk, dp, cols, s.dst, Bq, s.qp, dp, rows, dp);
  };
  auto finish_keys = [&](const Buffers& s, index_t b, index_t h, index_t c0, index_t cols) {
    if (d_v) add_rows(d_v + b * L.v.batch + h * L.v.head + c0 * L.v.row, L.v.row, s.dv, dp, cols, d);
    if (d_k) add_rows(d_k + b * L.k.batch + h * L.k.head + c0 * L.k.row, L.k.row, s.dk, dp, cols, d);
  };

  // dQ^T of query block qb of head (b, h) added into d_q.
  auto add_dq = [&](const T* dqt, index_t b, index_t h, index_t qb) {
    const index_t r0 = qb * Bq, rows = std::min(Bq, L.n_q - r0);
    T* dq = d_q + b * L.q.batch + h * L.q.head + r0 * L.q.row;
    for (index_t r = 0; r < rows; ++r)
      for (index_t j = 0; j < d; ++j) dq[r * L.q.row + j] += dqt[j * Bq + r];
  };

  if (one_pass) {
    parallel_for(heads_total, [&](index_t t0, index_t t1, int worker) {
     simd::with_lanes<T>(lanes, [&](auto* lane_type) {
      using V = std::remove_pointer_t<decltype(lane_type)>;
      const Buffers s = buffers(worker);
      for (index_t bh = t0; bh < t1; ++bh) {
        const index_t b = bh / L.heads, h = bh % L.heads;
        std::fill(s.dq_head, s.dq_head + q_blocks * Bq * d, T(0));
        for (index_t kb = 0; kb < kv_blocks; ++kb) {
          const index_t c0 = kb * Bk, cols = std::min(Bk, L.n_kv - c0);
          load_keys(s, b, h, c0, cols);
          start_keys(s, cols);
          for (index_t qb = 0; qb < q_blocks; ++qb) {
            const index_t rows = load_queries(s, b, h, qb);
            tile(lane_type, s, s.kp, s.vp, cols);
            add_tile_dkv(lane_type, s, cols, rows);
            axpy_t_block<V>(s.dq_head + qb * d * Bq, Bq, static_cast<const T*>(nullptr), s.kp, d, s.dst, cols, d);
          }
          finish_keys(s, b, h, c0, cols);
        }
        for (index_t qb = 0; qb < q_blocks; ++qb) add_dq(s.dq_head + qb * d * Bq, b, h, qb);
      }
     });
    }, pool);
    return;
  }
  if (d_k || d_v) {
    parallel_for(L.batch * L.heads * kv_blocks, [&](index_t t0, index_t t1, int worker) {
     simd::with_lanes<T>(lanes, [&](auto* lane_type) {
      const Buffers s = buffers(worker);
      for (index_t t = t0; t < t1; ++t) {
        const index_t bh = t / kv_blocks, kb = t % kv_blocks, b = bh / L.heads, h = bh % L.heads;
        const index_t c0 = kb * Bk, cols = std::min(Bk, L.n_kv - c0);
        load_keys(s, b, h, c0, cols);
        start_keys(s, cols);
        for (index_t qb = 0; qb < q_blocks; ++qb) {
          const index_t rows = load_queries(s, b, h, qb);
          tile(lane_type, s, s.kp, s.vp, cols);
          add_tile_dkv(lane_type, s, cols, rows);
        }
        finish_keys(s, b, h, c0, cols);
      }
     });
    }, pool);
  }
  if (d_q) {
    parallel_for(L.batch * L.heads * q_blocks, [&](index_t t0, index_t t1, int worker) {
     simd::with_lanes<T>(lanes, [&](auto* lane_type) {
      using V = std::remove_pointer_t<decltype(lane_type)>;
      const Buffers s = buffers(worker);
      index_t packed_bh = -1;
      for (index_t t = t0; t < t1; ++t) {
        const index_t bh = t / q_blocks, qb = t % q_blocks, b = bh / L.heads, h = bh % L.heads;
        load_queries(s, b, h, qb);
        std::fill(s.dqt, s.dqt + d * Bq, T(0));
        if (whole_heads && bh != packed_bh) {
          load_keys(s, b, h, 0, L.n_kv);
          packed_bh = bh;
        }
        for (index_t kb = 0; kb < kv_blocks; ++kb) {
          const index_t c0 = kb * Bk, cols = std::min(Bk, L.n_kv - c0), at = whole_heads ? c0 * d : 0;
          if (!whole_heads) load_keys(s, b, h, c0, cols);
          tile(lane_type, s, s.kp + at, s.vp + at, cols);
          axpy_t_block<V>(s.dqt, Bq, static_cast<const T*>(nullptr), s.kp + at, d, s.dst, cols, d);
        }
        add_dq(s.dqt, b, h, qb);
      }
     });
    }, pool);
  }
}

template <class T>
void attention_forward(T* out, T* lse, const T* q, const T* k, const T* v, const AttentionLayout& L, T scale,
                       std::span<T> scratch, ThreadPool& pool = global_pool()) {
  attention_forward_impl<T>(out, lse, q, k, v, L, scale, scratch, simd::best_lanes<T>(), pool);
}

template <class T>
void attention_backward(T* d_q, T* d_k, T* d_v, const T* d_out, const T* out, const T* lse, const T* q, const T* k,
                        const T* v, const AttentionLayout& L, T scale, std::span<T> scratch,
                        ThreadPool& pool = global_pool()) {
  attention_backward_impl<T>(d_q, d_k, d_v, d_out, out, lse, q, k, v, L, scale, scratch, simd::best_lanes<T>(), pool);
}

// Layout of the usual packed [batch, tokens, heads, head_dim] tensors (PyTorch's "b n (h d)").
inline AttentionLayout packed_attention_layout(index_t batch, index_t heads, index_t n_q, index_t n_kv, index_t head_dim) {
  AttentionLayout L;
  L.batch = batch;
  L.heads = heads;
  L.n_q = n_q;
  L.n_kv = n_kv;
  L.head_dim = head_dim;
  const index_t width = heads * head_dim;
  L.q = {n_q * width, head_dim, width};
  L.out = L.q;
  L.k = {n_kv * width, head_dim, width};
  L.v = L.k;
  return L;
}

}  // namespace nn
}  // namespace v0
}  // namespace flexsplat
