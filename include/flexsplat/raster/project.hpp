#pragma once
// EWA projection of one 3D Gaussian (gsplat semantics) and its vector-Jacobian product, including the gradients
// with respect to the camera (rotation, translation, fx, fy, cx, cy). Matrices are 3x3 row-major arrays.
#include <cmath>

#include "flexsplat/core/inline.hpp"
#include "flexsplat/core/simd.hpp"
#include "flexsplat/core/simd_dispatch.hpp"  // its lane overloads must be visible where the lane templates are defined
#include "flexsplat/raster/constants.hpp"

namespace flexsplat {
inline namespace v0 {
namespace raster {

template <class T>
struct CameraParams {
  T R[9];  // world-to-camera rotation block (row-major)
  T t[3];  // world-to-camera translation
  T fx, fy, cx, cy;
  T width, height;
};

template <class T>
struct CameraGradParams {
  T R[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
  T t[3] = {0, 0, 0};
  T fx = 0, fy = 0, cx = 0, cy = 0;
  void add(const CameraGradParams& o) {
    for (int i = 0; i < 9; ++i) R[i] += o.R[i];
    for (int i = 0; i < 3; ++i) t[i] += o.t[i];
    fx += o.fx, fy += o.fy, cx += o.cx, cy += o.cy;
  }
};

template <class T>
struct ProjectSettings {
  T eps2d = T(default_eps2d);
  T near_plane = T(default_near);
  T far_plane = T(default_far);
  bool antialiased = false;
};

// What the rasterizer needs of one visible Gaussian.
template <class T>
struct Projection {
  T u, v, z;        // pixel-space mean and camera-space depth of the mean
  T cov[3];         // blurred 2D covariance (a, b, c) of [[a, b], [b, c]]
  T conic[3];       // its inverse
  T opacity;        // opacity times the antialiasing compensation
};

// Rotation matrix of a unit quaternion (w, x, y, z).
template <class T>
FLEXSPLAT_ALWAYS_INLINE void quat_to_rotmat(const T q[4], T R[9]) {
  const T w = q[0], x = q[1], y = q[2], z = q[3];
  R[0] = 1 - 2 * (y * y + z * z), R[1] = 2 * (x * y - w * z), R[2] = 2 * (x * z + w * y);
  R[3] = 2 * (x * y + w * z), R[4] = 1 - 2 * (x * x + z * z), R[5] = 2 * (y * z - w * x);
  R[6] = 2 * (x * z - w * y), R[7] = 2 * (y * z + w * x), R[8] = 1 - 2 * (x * x + y * y);
}

template <class T>
FLEXSPLAT_ALWAYS_INLINE void quat_to_rotmat_vjp(const T q[4], const T dR[9], T dq[4]) {
  const T w = q[0], x = q[1], y = q[2], z = q[3];
  dq[0] += 2 * (-z * dR[1] + y * dR[2] + z * dR[3] - x * dR[5] - y * dR[6] + x * dR[7]);
  dq[1] += 2 * (y * dR[1] + z * dR[2] + y * dR[3] - 2 * x * dR[4] - w * dR[5] + z * dR[6] + w * dR[7] - 2 * x * dR[8]);
  dq[2] += 2 * (-2 * y * dR[0] + x * dR[1] + w * dR[2] + x * dR[3] + z * dR[5] - w * dR[6] + z * dR[7] - 2 * y * dR[8]);
  dq[3] += 2 * (-2 * z * dR[0] - w * dR[1] + x * dR[2] + w * dR[3] - 2 * z * dR[4] + y * dR[5] + x * dR[6] + y * dR[7]);
}

template <class T>
FLEXSPLAT_ALWAYS_INLINE void mat3_mul(const T A[9], const T B[9], T C[9]) {
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) C[i * 3 + j] = A[i * 3] * B[j] + A[i * 3 + 1] * B[3 + j] + A[i * 3 + 2] * B[6 + j];
}
template <class T>
FLEXSPLAT_ALWAYS_INLINE void mat3_mul_bt(const T A[9], const T B[9], T C[9]) {  // A * B^T
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      C[i * 3 + j] = A[i * 3] * B[j * 3] + A[i * 3 + 1] * B[j * 3 + 1] + A[i * 3 + 2] * B[j * 3 + 2];
}
template <class T>
FLEXSPLAT_ALWAYS_INLINE void mat3_mul_at(const T A[9], const T B[9], T C[9]) {  // A^T * B
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) C[i * 3 + j] = A[i] * B[j] + A[3 + i] * B[3 + j] + A[6 + i] * B[6 + j];
}

// World covariance R(q/|q|) diag(s)^2 R^T; also returns the unit quaternion and M = R diag(s).
template <class T>
FLEXSPLAT_ALWAYS_INLINE void covariance_forward(const T q[4], const T s[3], T qn[4], T M[9], T cov[9]) {
  const T len = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  for (int i = 0; i < 4; ++i) qn[i] = q[i] / len;
  T R[9];
  quat_to_rotmat(qn, R);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) M[i * 3 + j] = R[i * 3 + j] * s[j];
  mat3_mul_bt(M, M, cov);
}

// Adds d(q) and d(s) for the (symmetric) cotangent dcov of the world covariance.
template <class T>
void covariance_vjp(const T q[4], const T s[3], const T dcov[9], T dq[4], T ds[3]) {
  T qn[4], M[9], cov[9], R[9];
  covariance_forward(q, s, qn, M, cov);
  quat_to_rotmat(qn, R);
  T dsym[9], dM[9];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) dsym[i * 3 + j] = dcov[i * 3 + j] + dcov[j * 3 + i];
  mat3_mul(dsym, M, dM);
  T dR[9];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) {
      dR[i * 3 + j] = dM[i * 3 + j] * s[j];
      ds[j] += dM[i * 3 + j] * R[i * 3 + j];
    }
  T dqn[4] = {0, 0, 0, 0};
  quat_to_rotmat_vjp(qn, dR, dqn);
  const T len = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  const T dot = qn[0] * dqn[0] + qn[1] * dqn[1] + qn[2] * dqn[2] + qn[3] * dqn[3];
  for (int i = 0; i < 4; ++i) dq[i] += (dqn[i] - qn[i] * dot) / len;
}

// Half-extents of the field of view (with the 1.3x margin) used to clamp x/z and y/z in the Jacobian.
template <class T>
FLEXSPLAT_ALWAYS_INLINE void fov_limits(const CameraParams<T>& cam, T& lim_x_pos, T& lim_x_neg, T& lim_y_pos, T& lim_y_neg) {
  const T mx = T(fov_clamp_margin) * T(0.5) * cam.width / cam.fx;
  const T my = T(fov_clamp_margin) * T(0.5) * cam.height / cam.fy;
  lim_x_pos = (cam.width - cam.cx) / cam.fx + mx;
  lim_x_neg = cam.cx / cam.fx + mx;
  lim_y_pos = (cam.height - cam.cy) / cam.fy + my;
  lim_y_neg = cam.cy / cam.fy + my;
}

// Intermediate values shared by the forward and the vector-Jacobian product.
template <class T>
struct ProjectionTrace {
  T qn[4], M[9], cov_world[9], p[3], cov_cam[9], J[6], txr, tyr;
  bool x_clamped, y_clamped;
  T cov2d[3], det0, det_b, comp;
};

template <class T>
FLEXSPLAT_ALWAYS_INLINE void projection_trace(const T m[3], const T q[4], const T s[3], const CameraParams<T>& cam, T eps2d,
                      ProjectionTrace<T>& tr) {
  covariance_forward(q, s, tr.qn, tr.M, tr.cov_world);
  for (int i = 0; i < 3; ++i)
    tr.p[i] = cam.R[i * 3] * m[0] + cam.R[i * 3 + 1] * m[1] + cam.R[i * 3 + 2] * m[2] + cam.t[i];
  T tmp[9];
  mat3_mul(cam.R, tr.cov_world, tmp);
  mat3_mul_bt(tmp, cam.R, tr.cov_cam);
  const T z = tr.p[2], rz = T(1) / z;
  T lxp, lxn, lyp, lyn;
  fov_limits(cam, lxp, lxn, lyp, lyn);
  const T xr = tr.p[0] * rz, yr = tr.p[1] * rz;
  tr.x_clamped = !(xr <= lxp && xr >= -lxn);
  tr.y_clamped = !(yr <= lyp && yr >= -lyn);
  tr.txr = std::min(lxp, std::max(-lxn, xr));
  tr.tyr = std::min(lyp, std::max(-lyn, yr));
  T* J = tr.J;
  J[0] = cam.fx * rz, J[1] = 0, J[2] = -cam.fx * tr.txr * rz;
  J[3] = 0, J[4] = cam.fy * rz, J[5] = -cam.fy * tr.tyr * rz;
  // cov2d = J cov_cam J^T
  T JC[6];
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j)
      JC[i * 3 + j] = J[i * 3] * tr.cov_cam[j] + J[i * 3 + 1] * tr.cov_cam[3 + j] + J[i * 3 + 2] * tr.cov_cam[6 + j];
  tr.cov2d[0] = JC[0] * J[0] + JC[1] * J[1] + JC[2] * J[2];
  tr.cov2d[1] = JC[0] * J[3] + JC[1] * J[4] + JC[2] * J[5];
  tr.cov2d[2] = JC[3] * J[3] + JC[4] * J[4] + JC[5] * J[5];
  tr.det0 = tr.cov2d[0] * tr.cov2d[2] - tr.cov2d[1] * tr.cov2d[1];
  tr.det_b = (tr.cov2d[0] + eps2d) * (tr.cov2d[2] + eps2d) - tr.cov2d[1] * tr.cov2d[1];
  tr.comp = tr.det0 > T(0) && tr.det_b > T(0) ? std::sqrt(tr.det0 / tr.det_b) : T(0);
}

// The forward projection with one Gaussian per lane of V (V = T: one Gaussian). Every sum of products is spelled
// with simd::lane_mul_add and no product meets a sum otherwise, so compiler contraction cannot differ between the
// paths: the lanes of a batch are bit-identical to the scalar path (project_forward_one). The values agree with
// projection_trace (used by the backward pass) up to rounding. Returns the visibility mask; the outputs of culled
// lanes are unspecified.
template <class V>
struct ProjectionLanes {
  V u, v, z, cov[3], conic[3], opacity;
};

namespace detail {
template <class V>
FLEXSPLAT_ALWAYS_INLINE V dot3_lanes(V a0, V b0, V a1, V b1, V a2, V b2) {
  return simd::lane_mul_add(a2, b2, simd::lane_mul_add(a1, b1, a0 * b0));
}
}  // namespace detail

template <class V, class T>
FLEXSPLAT_ALWAYS_INLINE simd::lane_mask<V> project_forward_lanes(const V m[3], const V q[4], const V s[3], V opacity,
                                                                 const CameraParams<T>& cam,
                                                                 const ProjectSettings<T>& set, ProjectionLanes<V>& out) {
  using detail::dot3_lanes;
  using simd::lane_mul_add;
  // World covariance R(q/|q|) diag(s)^2 R^T.
  const V len = simd::lane_sqrt(lane_mul_add(q[3], q[3], lane_mul_add(q[2], q[2], lane_mul_add(q[1], q[1], q[0] * q[0]))));
  const V w = q[0] / len, x = q[1] / len, y = q[2] / len, z = q[3] / len;
  const V one = V(T(1)), two = V(T(2)), minus_two = V(T(-2));
  const V R[9] = {lane_mul_add(minus_two, lane_mul_add(y, y, z * z), one), two * lane_mul_add(x, y, -(w * z)),
                  two * lane_mul_add(x, z, w * y),
                  two * lane_mul_add(x, y, w * z), lane_mul_add(minus_two, lane_mul_add(x, x, z * z), one),
                  two * lane_mul_add(y, z, -(w * x)),
                  two * lane_mul_add(x, z, -(w * y)), two * lane_mul_add(y, z, w * x),
                  lane_mul_add(minus_two, lane_mul_add(x, x, y * y), one)};
  V M[9], cw[9];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) M[i * 3 + j] = R[i * 3 + j] * s[j];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      cw[i * 3 + j] = dot3_lanes(M[i * 3], M[j * 3], M[i * 3 + 1], M[j * 3 + 1], M[i * 3 + 2], M[j * 3 + 2]);
  // Camera-space mean and covariance Rc cw Rc^T.
  V Rc[9], p[3], tmp[9], cc[9];
  for (int i = 0; i < 9; ++i) Rc[i] = V(cam.R[i]);
  for (int i = 0; i < 3; ++i) p[i] = dot3_lanes(Rc[i * 3], m[0], Rc[i * 3 + 1], m[1], Rc[i * 3 + 2], m[2]) + V(cam.t[i]);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      tmp[i * 3 + j] = dot3_lanes(Rc[i * 3], cw[j], Rc[i * 3 + 1], cw[3 + j], Rc[i * 3 + 2], cw[6 + j]);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      cc[i * 3 + j] = dot3_lanes(tmp[i * 3], Rc[j * 3], tmp[i * 3 + 1], Rc[j * 3 + 1], tmp[i * 3 + 2], Rc[j * 3 + 2]);
  // Jacobian of the perspective projection with x/z and y/z clamped to 1.3x the field of view.
  const V zc = p[2], rz = one / zc;
  T lxp, lxn, lyp, lyn;
  fov_limits(cam, lxp, lxn, lyp, lyn);
  const V xr = p[0] * rz, yr = p[1] * rz;
  const V x_lo = simd::lane_select(V(-lxn) < xr, xr, V(-lxn)), y_lo = simd::lane_select(V(-lyn) < yr, yr, V(-lyn));
  const V txr = simd::lane_select(x_lo < V(lxp), x_lo, V(lxp)), tyr = simd::lane_select(y_lo < V(lyp), y_lo, V(lyp));
  const V fx = V(cam.fx), fy = V(cam.fy);
  const V J00 = fx * rz, J02 = -fx * txr * rz, J11 = fy * rz, J12 = -fy * tyr * rz;  // J01 = J10 = 0
  // cov2d = J cc J^T
  V JC0[3], JC1[3];
  for (int j = 0; j < 3; ++j) {
    JC0[j] = lane_mul_add(J02, cc[6 + j], J00 * cc[j]);
    JC1[j] = lane_mul_add(J12, cc[6 + j], J11 * cc[3 + j]);
  }
  const V c00 = lane_mul_add(JC0[2], J02, JC0[0] * J00), c01 = lane_mul_add(JC0[2], J12, JC0[1] * J11);
  const V c11 = lane_mul_add(JC1[2], J12, JC1[1] * J11);
  const V eps = V(set.eps2d);
  const V a = c00 + eps, b = c01, c = c11 + eps;
  const V det_b = lane_mul_add(a, c, -(b * b));
  const V inv = one / det_b;
  out.cov[0] = a, out.cov[1] = b, out.cov[2] = c;
  out.conic[0] = c * inv, out.conic[1] = -b * inv, out.conic[2] = a * inv;
  out.opacity = opacity;
  if (set.antialiased) {  // opacity times sqrt(det(cov2d) / det(cov2d + eps2d I))
    const V zero = V(T(0)), det0 = lane_mul_add(c00, c11, -(b * b));
    out.opacity = opacity * simd::lane_select((det0 > zero) & (det_b > zero), simd::lane_sqrt(det0 / det_b), zero);
  }
  out.z = zc;
  out.u = fx * p[0] / zc + V(cam.cx);
  out.v = fy * p[1] / zc + V(cam.cy);
  using simd::lane_isfinite;
  return (zc >= V(set.near_plane)) & simd::lane_not(zc > V(set.far_plane)) & (det_b > V(T(0))) & lane_isfinite(det_b) &
         (out.opacity >= V(T(alpha_threshold))) & lane_isfinite(out.conic[0]) & lane_isfinite(out.conic[1]) &
         lane_isfinite(out.conic[2]) & lane_isfinite(out.u) & lane_isfinite(out.v);
}

// Projects one Gaussian; false when it is culled (near/far, degenerate, or too transparent to reach the alpha
// threshold anywhere).
template <class T>
bool project_forward_one(const T m[3], const T q[4], const T s[3], T opacity, const CameraParams<T>& cam,
                         const ProjectSettings<T>& set, Projection<T>& out) {
  ProjectionLanes<T> p;
  const bool visible = project_forward_lanes<T, T>(m, q, s, opacity, cam, set, p);
  out.u = p.u, out.v = p.v, out.z = p.z, out.opacity = p.opacity;
  for (int i = 0; i < 3; ++i) out.cov[i] = p.cov[i], out.conic[i] = p.conic[i];
  return visible;
}

// Cotangents of one visible Gaussian's projection.
template <class T>
struct ProjectionGrad {
  T u = 0, v = 0, z = 0, conic[3] = {0, 0, 0}, opacity = 0;
};

// Adds d(mean), d(quat), d(scale), d(opacity) and the camera gradient for one visible Gaussian.
template <class T>
void project_backward_one(const T m[3], const T q[4], const T s[3], T opacity, const CameraParams<T>& cam,
                          const ProjectSettings<T>& set, const ProjectionGrad<T>& g, T dm[3], T dq[4], T ds[3],
                          T& dopacity, CameraGradParams<T>& dcam) {
  ProjectionTrace<T> tr;
  projection_trace(m, q, s, cam, set.eps2d, tr);
  const T eps = set.eps2d;
  const T a = tr.cov2d[0] + eps, b = tr.cov2d[1], c = tr.cov2d[2] + eps;
  const T inv = T(1) / tr.det_b;
  // conic = inverse(cov_b): d cov_b = -Q G Q with G the symmetric cotangent of the conic matrix.
  const T Q[4] = {c * inv, -b * inv, -b * inv, a * inv};
  const T G[4] = {g.conic[0], g.conic[1] * T(0.5), g.conic[1] * T(0.5), g.conic[2]};
  T QG[4] = {Q[0] * G[0] + Q[1] * G[2], Q[0] * G[1] + Q[1] * G[3], Q[2] * G[0] + Q[3] * G[2], Q[2] * G[1] + Q[3] * G[3]};
  T dC[4] = {-(QG[0] * Q[0] + QG[1] * Q[2]), -(QG[0] * Q[1] + QG[1] * Q[3]), -(QG[2] * Q[0] + QG[3] * Q[2]),
             -(QG[2] * Q[1] + QG[3] * Q[3])};  // full symmetric 2x2 cotangent of cov2d (blur has unit Jacobian)
  if (set.antialiased) {
    dopacity += g.opacity * tr.comp;
    if (tr.comp > T(0)) {
      const T dcomp = g.opacity * opacity;
      const T ddet0 = dcomp * tr.comp / (T(2) * tr.det0);
      const T ddetb = -dcomp * tr.comp / (T(2) * tr.det_b);
      dC[0] += ddet0 * tr.cov2d[2] + ddetb * c;
      dC[3] += ddet0 * tr.cov2d[0] + ddetb * a;
      dC[1] -= (ddet0 + ddetb) * b;
      dC[2] -= (ddet0 + ddetb) * b;
    }
  } else {
    dopacity += g.opacity;
  }
  const T* J = tr.J;
  // cov2d = J Cc J^T: dJ = (dC + dC^T) J Cc, dCc = J^T dC J.
  T JC[6];
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j)
      JC[i * 3 + j] = J[i * 3] * tr.cov_cam[j] + J[i * 3 + 1] * tr.cov_cam[3 + j] + J[i * 3 + 2] * tr.cov_cam[6 + j];
  const T S[4] = {dC[0] + dC[0], dC[1] + dC[2], dC[2] + dC[1], dC[3] + dC[3]};
  T dJ[6];
  for (int j = 0; j < 3; ++j) {
    dJ[j] = S[0] * JC[j] + S[1] * JC[3 + j];
    dJ[3 + j] = S[2] * JC[j] + S[3] * JC[3 + j];
  }
  T dCc[9];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      dCc[i * 3 + j] = J[i] * (dC[0] * J[j] + dC[1] * J[3 + j]) + J[3 + i] * (dC[2] * J[j] + dC[3] * J[3 + j]);
  // Pixel mean and Jacobian with respect to the camera-space mean and the intrinsics.
  const T x = tr.p[0], y = tr.p[1], z = tr.p[2], rz = T(1) / z, rz2 = rz * rz;
  T dp[3] = {0, 0, g.z};
  dp[0] += cam.fx * rz * g.u;
  dp[1] += cam.fy * rz * g.v;
  dp[2] -= (cam.fx * x * g.u + cam.fy * y * g.v) * rz2;
  dcam.fx += x * rz * g.u;
  dcam.fy += y * rz * g.v;
  dcam.cx += g.u;
  dcam.cy += g.v;
  // J00 = fx/z, J11 = fy/z, J02 = -fx txr/z, J12 = -fy tyr/z.
  dcam.fx += dJ[0] * rz - dJ[2] * tr.txr * rz;
  dcam.fy += dJ[4] * rz - dJ[5] * tr.tyr * rz;
  dp[2] += -(cam.fx * dJ[0] + cam.fy * dJ[4]) * rz2 + (cam.fx * tr.txr * dJ[2] + cam.fy * tr.tyr * dJ[5]) * rz2;
  const T dtxr = -cam.fx * rz * dJ[2], dtyr = -cam.fy * rz * dJ[5];
  if (!tr.x_clamped) {
    dp[0] += dtxr * rz;
    dp[2] -= dtxr * x * rz2;
  } else {  // txr is a limit (+-(...)/fx): depends on fx and cx only
    dcam.fx -= tr.txr / cam.fx * dtxr;
    dcam.cx -= dtxr / cam.fx;
  }
  if (!tr.y_clamped) {
    dp[1] += dtyr * rz;
    dp[2] -= dtyr * y * rz2;
  } else {
    dcam.fy -= tr.tyr / cam.fy * dtyr;
    dcam.cy -= dtyr / cam.fy;
  }
  // cov_cam = R cov R^T
  T tmp[9], dcov[9];
  mat3_mul_at(cam.R, dCc, tmp);
  mat3_mul(tmp, cam.R, dcov);
  T RC[9];
  mat3_mul(cam.R, tr.cov_world, RC);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) {
      T acc = 0;
      for (int k = 0; k < 3; ++k) acc += (dCc[i * 3 + k] + dCc[k * 3 + i]) * RC[k * 3 + j];
      dcam.R[i * 3 + j] += acc;
    }
  // p = R m + t
  for (int i = 0; i < 3; ++i) {
    dm[i] += cam.R[i] * dp[0] + cam.R[3 + i] * dp[1] + cam.R[6 + i] * dp[2];
    dcam.t[i] += dp[i];
    for (int j = 0; j < 3; ++j) dcam.R[i * 3 + j] += dp[i] * m[j];
  }
  covariance_vjp(q, s, dcov, dq, ds);
}

}  // namespace raster
}  // namespace v0
}  // namespace flexsplat
