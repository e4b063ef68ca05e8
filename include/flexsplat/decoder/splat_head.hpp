#pragma once
// The splat head: a linear map from query features to the 24-value Gaussian update dG, its composition onto the
// running estimate (additive in depth/offset/log-scale/logit/SH space, quaternion product for rotations), and the
// Splatter Image activations. Per-element f / f_vjp helpers, array kernels over all queries.
#include <algorithm>
#include <cmath>

#include "flexsplat/decoder/constants.hpp"
#include "flexsplat/nn/linear.hpp"

namespace flexsplat {
inline namespace v0 {
namespace decoder {

// ---- quaternions, (w, x, y, z) ----

// out = p * q (Hamilton product).
template <class T>
void quat_multiply(const T* p, const T* q, T* out) {
  const T w = p[0] * q[0] - p[1] * q[1] - p[2] * q[2] - p[3] * q[3];
  const T x = p[0] * q[1] + p[1] * q[0] + p[2] * q[3] - p[3] * q[2];
  const T y = p[0] * q[2] - p[1] * q[3] + p[2] * q[0] + p[3] * q[1];
  const T z = p[0] * q[3] + p[1] * q[2] - p[2] * q[1] + p[3] * q[0];
  out[0] = w;
  out[1] = x;
  out[2] = y;
  out[3] = z;
}

// Adds the gradients of <d_out, p * q> into d_p and d_q: d_p = d_out * conj(q), d_q = conj(p) * d_out.
template <class T>
void quat_multiply_vjp(const T* p, const T* q, const T* d_out, T* d_p, T* d_q) {
  const T q_conj[4] = {q[0], -q[1], -q[2], -q[3]}, p_conj[4] = {p[0], -p[1], -p[2], -p[3]};
  T a[4], b[4];
  quat_multiply(d_out, q_conj, a);
  quat_multiply(p_conj, d_out, b);
  for (int i = 0; i < 4; ++i) {
    d_p[i] += a[i];
    d_q[i] += b[i];
  }
}

// out = q / max(|q|, floor).
template <class T>
void quat_normalize(const T* q, T* out) {
  const T norm = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  const T inv = T(1) / std::max(norm, static_cast<T>(quaternion_norm_floor));
  for (int i = 0; i < 4; ++i) out[i] = q[i] * inv;
}

template <class T>
void quat_normalize_vjp(const T* q, const T* d_out, T* d_q) {
  const T norm = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  if (norm < static_cast<T>(quaternion_norm_floor)) {
    for (int i = 0; i < 4; ++i) d_q[i] += d_out[i] / static_cast<T>(quaternion_norm_floor);
    return;
  }
  const T inv = T(1) / norm;
  T dot = 0;
  for (int i = 0; i < 4; ++i) dot += q[i] * d_out[i];
  for (int i = 0; i < 4; ++i) d_q[i] += inv * (d_out[i] - q[i] * dot * inv * inv);
}

// ---- Splatter Image activations ----

// exp with the argument clamped so a runaway log-scale gives a huge but finite scale, never inf.
inline constexpr double log_scale_max = 20.0, log_scale_min = -30.0;

template <class T>
T scale_activation(T log_scale) {
  return std::exp(std::clamp(log_scale, static_cast<T>(log_scale_min), static_cast<T>(log_scale_max)));
}
template <class T>
T scale_activation_vjp(T log_scale, T d_scale) {
  if (log_scale < static_cast<T>(log_scale_min) || log_scale > static_cast<T>(log_scale_max)) return T(0);
  return d_scale * std::exp(log_scale);
}


// ---- composition of the running estimate ----

// state_out = compose(state_in, delta) for n rows of 24 values; rotations: normalize(dq) * normalize(q).
template <class T>
void compose_forward(T* state_out, const T* state_in, const T* delta, index_t n) {
  for (index_t i = 0; i < n; ++i) {
    const T* s = state_in + i * splat_values;
    const T* d = delta + i * splat_values;
    T* o = state_out + i * splat_values;
    for (index_t k = 0; k < splat_values; ++k) o[k] = s[k] + d[k];
    T qn[4], dn[4];
    quat_normalize(s + splat_quat, qn);
    quat_normalize(d + splat_quat, dn);
    quat_multiply(dn, qn, o + splat_quat);
  }
}

// Adds into d_state_in and d_delta (each may be null).
template <class T>
void compose_backward(T* d_state_in, T* d_delta, const T* d_state_out, const T* state_in, const T* delta, index_t n) {
  for (index_t i = 0; i < n; ++i) {
    const T* s = state_in + i * splat_values;
    const T* d = delta + i * splat_values;
    const T* g = d_state_out + i * splat_values;
    for (index_t k = 0; k < splat_values; ++k) {
      if (k >= splat_quat && k < splat_quat + 4) continue;
      if (d_state_in) d_state_in[i * splat_values + k] += g[k];
      if (d_delta) d_delta[i * splat_values + k] += g[k];
    }
    T qn[4], dn[4], d_qn[4] = {0, 0, 0, 0}, d_dn[4] = {0, 0, 0, 0};
    quat_normalize(s + splat_quat, qn);
    quat_normalize(d + splat_quat, dn);
    quat_multiply_vjp(dn, qn, g + splat_quat, d_dn, d_qn);
    if (d_state_in) quat_normalize_vjp(s + splat_quat, d_qn, d_state_in + i * splat_values + splat_quat);
    if (d_delta) quat_normalize_vjp(d + splat_quat, d_dn, d_delta + i * splat_values + splat_quat);
  }
}

// ---- the head ----

// Constant added to the head's output: the identity rotation for every head, and for the initial head also the
// Splatter Image biases (opacity logit -2, log-scale log 0.02).
template <class T>
void splat_head_fixed_bias(T* bias24, bool initial) {
  std::fill(bias24, bias24 + splat_values, T(0));
  bias24[splat_quat] = T(1);
  if (initial) {
    for (int k = 0; k < 3; ++k) bias24[splat_log_scale + k] = static_cast<T>(log_scale_bias);
    bias24[splat_opacity] = static_cast<T>(opacity_logit_bias);
  }
}

// delta [n, 24] = x [n, dim] W^T + b + fixed bias.
template <class T>
void splat_head_forward(T* delta, const T* x, const T* weight, const T* bias, index_t n, index_t dim, bool initial) {
  nn::linear_forward(delta, x, weight, bias, n, dim, splat_values);
  T fixed[splat_values];
  splat_head_fixed_bias(fixed, initial);
  for (index_t i = 0; i < n; ++i)
    for (index_t k = 0; k < splat_values; ++k) delta[i * splat_values + k] += fixed[k];
}

template <class T>
void splat_head_backward(T* d_x, T* d_weight, T* d_bias, const T* d_delta, const T* x, const T* weight, index_t n,
                         index_t dim) {
  nn::linear_backward(d_x, d_weight, d_bias, d_delta, x, weight, n, dim, splat_values);
}

}  // namespace decoder
}  // namespace v0
}  // namespace flexsplat
