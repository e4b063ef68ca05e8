#pragma once
// Scaled dot-product attention with a tiled online softmax: memory is linear in the token count (the n_q x n_kv
// score matrix never exists). Backward recomputes score tiles from the saved log-sum-exp, in two race-free passes
// (key blocks own dK/dV, query blocks own dQ), so results do not depend on the thread count.
#include <algorithm>
#include <cmath>
#include <limits>
#include <span>

#include <Eigen/Core>

#include "flexsplat/core/parallel.hpp"
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
inline constexpr index_t attention_kv_block = 128;

// Scratch elements one worker needs; pass at least this times the pool size.
inline index_t attention_scratch_per_worker(index_t head_dim) {
  return 2 * attention_q_block * attention_kv_block + 3 * attention_q_block * head_dim + 2 * attention_kv_block * head_dim +
         4 * attention_q_block;
}

namespace detail {
template <class T>
using BlockMatrix = Eigen::Matrix<T, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
template <class T>
using RowsMap = Eigen::Map<const BlockMatrix<T>, 0, Eigen::OuterStride<>>;
template <class T>
using MutRowsMap = Eigen::Map<BlockMatrix<T>, 0, Eigen::OuterStride<>>;
template <class T>
using ScratchMap = Eigen::Map<BlockMatrix<T>>;

inline void check_scratch(std::size_t have, index_t head_dim, int workers) {
  require(static_cast<index_t>(have) >= attention_scratch_per_worker(head_dim) * workers, "attention scratch has ", have,
          " elements, needs ", attention_scratch_per_worker(head_dim) * workers, " (head_dim ", head_dim, ", ", workers,
          " workers)");
}
}  // namespace detail

// out = softmax(scale * q k^T) v per (batch, head). lse [batch*heads*n_q] (may be null) receives log-sum-exp rows,
// which backward needs. With n_kv == 0 the output is zero and lse is -inf.
template <class T>
void attention_forward(T* out, T* lse, const T* q, const T* k, const T* v, const AttentionLayout& L, T scale,
                       std::span<T> scratch, ThreadPool& pool = global_pool()) {
  using namespace detail;
  const index_t d = L.head_dim;
  const index_t q_blocks = (L.n_q + attention_q_block - 1) / attention_q_block;
  const index_t tasks = L.batch * L.heads * q_blocks;
  detail::check_scratch(scratch.size(), d, pool.size());
  parallel_for(tasks, [&](index_t t0, index_t t1, int worker) {
    T* ws = scratch.data() + worker * attention_scratch_per_worker(d);
    for (index_t t = t0; t < t1; ++t) {
      const index_t bh = t / q_blocks, qb = t % q_blocks, b = bh / L.heads, h = bh % L.heads;
      const index_t r0 = qb * attention_q_block, rows = std::min(attention_q_block, L.n_q - r0);
      RowsMap<T> Q(q + b * L.q.batch + h * L.q.head + r0 * L.q.row, rows, d, Eigen::OuterStride<>(L.q.row));
      ScratchMap<T> acc(ws, rows, d);
      ScratchMap<T> S(ws + attention_q_block * d, rows, attention_kv_block);
      T* running_max = ws + attention_q_block * d + attention_q_block * attention_kv_block;
      T* running_sum = running_max + attention_q_block;
      acc.setZero();
      std::fill(running_max, running_max + rows, -std::numeric_limits<T>::infinity());
      std::fill(running_sum, running_sum + rows, T(0));
      for (index_t c0 = 0; c0 < L.n_kv; c0 += attention_kv_block) {
        const index_t cols = std::min(attention_kv_block, L.n_kv - c0);
        RowsMap<T> K(k + b * L.k.batch + h * L.k.head + c0 * L.k.row, cols, d, Eigen::OuterStride<>(L.k.row));
        RowsMap<T> V(v + b * L.v.batch + h * L.v.head + c0 * L.v.row, cols, d, Eigen::OuterStride<>(L.v.row));
        auto s = S.leftCols(cols);
        s.noalias() = scale * (Q * K.transpose());
        for (index_t r = 0; r < rows; ++r) {
          const T block_max = s.row(r).maxCoeff();
          const T new_max = std::max(running_max[r], block_max);
          const T rescale = std::exp(running_max[r] - new_max);  // exp(-inf) = 0 on the first block
          T row_sum = 0;
          for (index_t c = 0; c < cols; ++c) {
            const T p = std::exp(s(r, c) - new_max);
            s(r, c) = p;
            row_sum += p;
          }
          running_sum[r] = running_sum[r] * rescale + row_sum;
          running_max[r] = new_max;
          acc.row(r) *= rescale;
        }
        acc.noalias() += s * V;
      }
      MutRowsMap<T> O(out + b * L.out.batch + h * L.out.head + r0 * L.out.row, rows, d, Eigen::OuterStride<>(L.out.row));
      for (index_t r = 0; r < rows; ++r) {
        if (running_sum[r] > T(0)) O.row(r) = acc.row(r) / running_sum[r];
        else O.row(r).setZero();
        if (lse) lse[bh * L.n_q + r0 + r] = running_max[r] + std::log(running_sum[r]);
      }
    }
  }, pool);
}

// Adds into d_q, d_k, d_v (each may be null). Needs the forward's out and lse.
template <class T>
void attention_backward(T* d_q, T* d_k, T* d_v, const T* d_out, const T* out, const T* lse, const T* q, const T* k,
                        const T* v, const AttentionLayout& L, T scale, std::span<T> scratch,
                        ThreadPool& pool = global_pool()) {
  using namespace detail;
  const index_t d = L.head_dim;
  const index_t q_blocks = (L.n_q + attention_q_block - 1) / attention_q_block;
  const index_t kv_blocks = (L.n_kv + attention_kv_block - 1) / attention_kv_block;
  detail::check_scratch(scratch.size(), d, pool.size());
  if (L.n_q == 0 || L.n_kv == 0) return;

  // P and dS for one (query block, key block) tile, recomputed from lse; returns rows and cols.
  auto tile = [&](T* ws, index_t b, index_t h, index_t qb, index_t kb, index_t& rows, index_t& cols) {
    const index_t bh = b * L.heads + h;
    const index_t r0 = qb * attention_q_block, c0 = kb * attention_kv_block;
    rows = std::min(attention_q_block, L.n_q - r0);
    cols = std::min(attention_kv_block, L.n_kv - c0);
    RowsMap<T> Q(q + b * L.q.batch + h * L.q.head + r0 * L.q.row, rows, d, Eigen::OuterStride<>(L.q.row));
    RowsMap<T> K(k + b * L.k.batch + h * L.k.head + c0 * L.k.row, cols, d, Eigen::OuterStride<>(L.k.row));
    RowsMap<T> V(v + b * L.v.batch + h * L.v.head + c0 * L.v.row, cols, d, Eigen::OuterStride<>(L.v.row));
    RowsMap<T> dO(d_out + b * L.out.batch + h * L.out.head + r0 * L.out.row, rows, d, Eigen::OuterStride<>(L.out.row));
    RowsMap<T> O(out + b * L.out.batch + h * L.out.head + r0 * L.out.row, rows, d, Eigen::OuterStride<>(L.out.row));
    ScratchMap<T> P(ws, rows, cols);
    ScratchMap<T> dS(ws + attention_q_block * attention_kv_block, rows, cols);
    P.noalias() = scale * (Q * K.transpose());
    dS.noalias() = dO * V.transpose();
    for (index_t r = 0; r < rows; ++r) {
      const T row_lse = lse[bh * L.n_q + r0 + r];
      const T delta = dO.row(r).dot(O.row(r));
      for (index_t c = 0; c < cols; ++c) {
        const T p = std::isfinite(row_lse) ? std::exp(P(r, c) - row_lse) : T(0);
        P(r, c) = p;
        dS(r, c) = p * (dS(r, c) - delta);
      }
    }
  };

  if (d_k || d_v) {
    parallel_for(L.batch * L.heads * kv_blocks, [&](index_t t0, index_t t1, int worker) {
      T* ws = scratch.data() + worker * attention_scratch_per_worker(d);
      for (index_t t = t0; t < t1; ++t) {
        const index_t bh = t / kv_blocks, kb = t % kv_blocks, b = bh / L.heads, h = bh % L.heads;
        for (index_t qb = 0; qb < q_blocks; ++qb) {
          index_t rows = 0, cols = 0;
          tile(ws, b, h, qb, kb, rows, cols);
          ScratchMap<T> P(ws, rows, cols);
          ScratchMap<T> dS(ws + attention_q_block * attention_kv_block, rows, cols);
          const index_t r0 = qb * attention_q_block, c0 = kb * attention_kv_block;
          if (d_v) {
            RowsMap<T> dO(d_out + b * L.out.batch + h * L.out.head + r0 * L.out.row, rows, d, Eigen::OuterStride<>(L.out.row));
            MutRowsMap<T> dV(d_v + b * L.v.batch + h * L.v.head + c0 * L.v.row, cols, d, Eigen::OuterStride<>(L.v.row));
            dV.noalias() += P.transpose() * dO;
          }
          if (d_k) {
            RowsMap<T> Q(q + b * L.q.batch + h * L.q.head + r0 * L.q.row, rows, d, Eigen::OuterStride<>(L.q.row));
            MutRowsMap<T> dK(d_k + b * L.k.batch + h * L.k.head + c0 * L.k.row, cols, d, Eigen::OuterStride<>(L.k.row));
            dK.noalias() += scale * (dS.transpose() * Q);
          }
        }
      }
    }, pool);
  }
  if (d_q) {
    parallel_for(L.batch * L.heads * q_blocks, [&](index_t t0, index_t t1, int worker) {
      T* ws = scratch.data() + worker * attention_scratch_per_worker(d);
      for (index_t t = t0; t < t1; ++t) {
        const index_t bh = t / q_blocks, qb = t % q_blocks, b = bh / L.heads, h = bh % L.heads;
        for (index_t kb = 0; kb < kv_blocks; ++kb) {
          index_t rows = 0, cols = 0;
          tile(ws, b, h, qb, kb, rows, cols);
          ScratchMap<T> dS(ws + attention_q_block * attention_kv_block, rows, cols);
          const index_t r0 = qb * attention_q_block, c0 = kb * attention_kv_block;
          RowsMap<T> K(k + b * L.k.batch + h * L.k.head + c0 * L.k.row, cols, d, Eigen::OuterStride<>(L.k.row));
          MutRowsMap<T> dQ(d_q + b * L.q.batch + h * L.q.head + r0 * L.q.row, rows, d, Eigen::OuterStride<>(L.q.row));
          dQ.noalias() += scale * (dS * K);
        }
      }
    }, pool);
  }
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
