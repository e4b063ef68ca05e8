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
struct ViewParams {
  T R[9];  // world-to-camera rotation block (row-major)
  T t[3];  // world-to-camera translation
  T fx, fy, cx, cy;
  T width, height;
};

template <class T>
struct ViewGradParams {
  T R[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
  T t[3] = {0, 0, 0};
  T fx = 0, fy = 0, cx = 0, cy = 0;
  void add(const ViewGradParams& o) {
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

// Half-extents of the field of view (with the 1.3x margin) used to clamp x/z and y/z in the Jacobian.
template <class T>
FLEXSPLAT_ALWAYS_INLINE void fov_limits(const ViewParams<T>& cam, T& lim_x_pos, T& lim_x_neg, T& lim_y_pos, T& lim_y_neg) {
  const T mx = T(fov_clamp_margin) * T(0.5) * cam.width / cam.fx;
  const T my = T(fov_clamp_margin) * T(0.5) * cam.height / cam.fy;
  lim_x_pos = (cam.width - cam.cx) / cam.fx + mx;
  lim_x_neg = cam.cx / cam.fx + mx;
  lim_y_pos = (cam.height - cam.cy) / cam.fy + my;
  lim_y_neg = cam.cy / cam.fy + my;
}

// The projection with one Gaussian per lane of V (V = T: one Gaussian). Every sum of products is spelled with
// simd::lane_mul_add and no product meets a sum otherwise, so compiler contraction cannot differ between the paths:
// the lanes of a batch are bit-identical to the scalar path (project_forward_one, project_backward_one), and the
// backward sees exactly the forward's values.
template <class V>
struct ProjectionLanes {
  V u, v, z, cov[3], conic[3], opacity;
};

// Intermediate values of the projection, shared by the forward and the vector-Jacobian product.
template <class V>
struct ProjectionTraceLanes {
  V len, qn[4], R[9], M[9];     // |q|, unit quaternion (w, x, y, z), R(qn), M = R diag(s)
  V cw[9], p[3], RC[9], cc[9];  // world covariance M M^T, camera-space mean, Rc cw, camera covariance RC Rc^T
  V rz, txr, tyr;               // 1 / z and the clamped x/z, y/z
  V J00, J02, J11, J12;         // perspective Jacobian (J01 = J10 = 0)
  V c00, c01, c11;              // 2D covariance before the blur
  V a, b, c, det_b;             // blurred covariance [[a, b], [b, c]] and its determinant
  simd::lane_mask<V> x_clamped, y_clamped;
};

namespace detail {
template <class V>
FLEXSPLAT_ALWAYS_INLINE V dot3_lanes(V a0, V b0, V a1, V b1, V a2, V b2) {
  return simd::lane_mul_add(a2, b2, simd::lane_mul_add(a1, b1, a0 * b0));
}
// sum_i a[i] b[i] in index order, the first term a product and the rest multiply-adds.
template <class V, std::size_t N>
FLEXSPLAT_ALWAYS_INLINE V dot_lanes(const V (&a)[N], const V (&b)[N]) {
  V s = a[0] * b[0];
  for (std::size_t i = 1; i < N; ++i) s = simd::lane_mul_add(a[i], b[i], s);
  return s;
}
}  // namespace detail

template <class V, class T>
FLEXSPLAT_ALWAYS_INLINE void projection_trace_lanes(const V m[3], const V q[4], const V s[3], const ViewParams<T>& cam,
                                                    T eps2d, ProjectionTraceLanes<V>& tr) {
  using detail::dot3_lanes;
  using simd::lane_mul_add;
  // World covariance R(q/|q|) diag(s)^2 R^T.
  tr.len = simd::lane_sqrt(lane_mul_add(q[3], q[3], lane_mul_add(q[2], q[2], lane_mul_add(q[1], q[1], q[0] * q[0]))));
  const V w = q[0] / tr.len, x = q[1] / tr.len, y = q[2] / tr.len, z = q[3] / tr.len;
  tr.qn[0] = w, tr.qn[1] = x, tr.qn[2] = y, tr.qn[3] = z;
  const V one = V(T(1)), two = V(T(2)), minus_two = V(T(-2));
  V* R = tr.R;
  R[0] = lane_mul_add(minus_two, lane_mul_add(y, y, z * z), one), R[1] = two * lane_mul_add(x, y, -(w * z));
  R[2] = two * lane_mul_add(x, z, w * y);
  R[3] = two * lane_mul_add(x, y, w * z), R[4] = lane_mul_add(minus_two, lane_mul_add(x, x, z * z), one);
  R[5] = two * lane_mul_add(y, z, -(w * x));
  R[6] = two * lane_mul_add(x, z, -(w * y)), R[7] = two * lane_mul_add(y, z, w * x);
  R[8] = lane_mul_add(minus_two, lane_mul_add(x, x, y * y), one);
  V* M = tr.M;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) M[i * 3 + j] = R[i * 3 + j] * s[j];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      tr.cw[i * 3 + j] = dot3_lanes(M[i * 3], M[j * 3], M[i * 3 + 1], M[j * 3 + 1], M[i * 3 + 2], M[j * 3 + 2]);
  // Camera-space mean and covariance Rc cw Rc^T.
  V Rc[9];
  for (int i = 0; i < 9; ++i) Rc[i] = V(cam.R[i]);
  for (int i = 0; i < 3; ++i)
    tr.p[i] = dot3_lanes(Rc[i * 3], m[0], Rc[i * 3 + 1], m[1], Rc[i * 3 + 2], m[2]) + V(cam.t[i]);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      tr.RC[i * 3 + j] = dot3_lanes(Rc[i * 3], tr.cw[j], Rc[i * 3 + 1], tr.cw[3 + j], Rc[i * 3 + 2], tr.cw[6 + j]);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      tr.cc[i * 3 + j] =
          dot3_lanes(tr.RC[i * 3], Rc[j * 3], tr.RC[i * 3 + 1], Rc[j * 3 + 1], tr.RC[i * 3 + 2], Rc[j * 3 + 2]);
  // Jacobian of the perspective projection with x/z and y/z clamped to 1.3x the field of view.
  const V zc = tr.p[2];
  tr.rz = one / zc;
  T lxp, lxn, lyp, lyn;
  fov_limits(cam, lxp, lxn, lyp, lyn);
  const V xr = tr.p[0] * tr.rz, yr = tr.p[1] * tr.rz;
  const V x_lo = simd::lane_select(V(-lxn) < xr, xr, V(-lxn)), y_lo = simd::lane_select(V(-lyn) < yr, yr, V(-lyn));
  tr.txr = simd::lane_select(x_lo < V(lxp), x_lo, V(lxp)), tr.tyr = simd::lane_select(y_lo < V(lyp), y_lo, V(lyp));
  tr.x_clamped = simd::lane_not((xr <= V(lxp)) & (xr >= V(-lxn)));
  tr.y_clamped = simd::lane_not((yr <= V(lyp)) & (yr >= V(-lyn)));
  const V fx = V(cam.fx), fy = V(cam.fy);
  tr.J00 = fx * tr.rz, tr.J02 = -fx * tr.txr * tr.rz, tr.J11 = fy * tr.rz, tr.J12 = -fy * tr.tyr * tr.rz;
  // cov2d = J cc J^T
  V JC0[3], JC1[3];
  for (int j = 0; j < 3; ++j) {
    JC0[j] = lane_mul_add(tr.J02, tr.cc[6 + j], tr.J00 * tr.cc[j]);
    JC1[j] = lane_mul_add(tr.J12, tr.cc[6 + j], tr.J11 * tr.cc[3 + j]);
  }
  tr.c00 = lane_mul_add(JC0[2], tr.J02, JC0[0] * tr.J00), tr.c01 = lane_mul_add(JC0[2], tr.J12, JC0[1] * tr.J11);
  tr.c11 = lane_mul_add(JC1[2], tr.J12, JC1[1] * tr.J11);
  const V eps = V(eps2d);
  tr.a = tr.c00 + eps, tr.b = tr.c01, tr.c = tr.c11 + eps;
  tr.det_b = lane_mul_add(tr.a, tr.c, -(tr.b * tr.b));
}

// Antialiasing compensation sqrt(det(cov2d) / det(cov2d + eps2d I)), 0 for a degenerate covariance; also det(cov2d).
template <class V>
FLEXSPLAT_ALWAYS_INLINE V compensation_lanes(const ProjectionTraceLanes<V>& tr, V& det0) {
  using S = typename simd::lane_scalar<V>::type;
  const V zero = V(S(0));
  det0 = simd::lane_mul_add(tr.c00, tr.c11, -(tr.b * tr.b));
  return simd::lane_select((det0 > zero) & (tr.det_b > zero), simd::lane_sqrt(det0 / tr.det_b), zero);
}

// Returns the visibility mask; the outputs of culled lanes are unspecified.
template <class V, class T>
FLEXSPLAT_ALWAYS_INLINE simd::lane_mask<V> project_forward_lanes(const V m[3], const V q[4], const V s[3], V opacity,
                                                                 const ViewParams<T>& cam,
                                                                 const ProjectSettings<T>& set, ProjectionLanes<V>& out) {
  ProjectionTraceLanes<V> tr;
  projection_trace_lanes(m, q, s, cam, set.eps2d, tr);
  const V inv = V(T(1)) / tr.det_b;
  out.cov[0] = tr.a, out.cov[1] = tr.b, out.cov[2] = tr.c;
  out.conic[0] = tr.c * inv, out.conic[1] = -tr.b * inv, out.conic[2] = tr.a * inv;
  out.opacity = opacity;
  if (set.antialiased) {  // opacity times sqrt(det(cov2d) / det(cov2d + eps2d I))
    V det0;
    out.opacity = opacity * compensation_lanes(tr, det0);
  }
  const V zc = tr.p[2], fx = V(cam.fx), fy = V(cam.fy);
  out.z = zc;
  out.u = fx * tr.p[0] / zc + V(cam.cx);
  out.v = fy * tr.p[1] / zc + V(cam.cy);
  using simd::lane_isfinite;
  // Calls into named masks first: clang's -Wall flags a bool '&' with a call operand, and lanes must not branch.
  const auto before_far = simd::lane_not(zc > V(set.far_plane)), det_finite = lane_isfinite(tr.det_b),
             c0_finite = lane_isfinite(out.conic[0]), c1_finite = lane_isfinite(out.conic[1]),
             c2_finite = lane_isfinite(out.conic[2]), u_finite = lane_isfinite(out.u), v_finite = lane_isfinite(out.v);
  return (zc >= V(set.near_plane)) & before_far & (tr.det_b > V(T(0))) & det_finite &
         (out.opacity >= V(T(alpha_threshold))) & c0_finite & c1_finite & c2_finite & u_finite & v_finite;
}

// Projects one Gaussian; false when it is culled (near/far, degenerate, or too transparent to reach the alpha
// threshold anywhere).
template <class T>
bool project_forward_one(const T m[3], const T q[4], const T s[3], T opacity, const ViewParams<T>& cam,
                         const ProjectSettings<T>& set, Projection<T>& out) {
  ProjectionLanes<T> p;
  const bool visible = project_forward_lanes<T, T>(m, q, s, opacity, cam, set, p);
  out.u = p.u, out.v = p.v, out.z = p.z, out.opacity = p.opacity;
  for (int i = 0; i < 3; ++i) out.cov[i] = p.cov[i], out.conic[i] = p.conic[i];
  return visible;
}

// Cotangents of one visible Gaussian's projection (one per lane of V).
template <class V>
struct ProjectionGrad {
  V u = 0, v = 0, z = 0, conic[3] = {0, 0, 0}, opacity = 0;
};

// Adds d(q) and d(s) for the (symmetric) cotangent dcov of the world covariance R diag(s)^2 R^T.
template <class V>
FLEXSPLAT_ALWAYS_INLINE void covariance_vjp_lanes(const ProjectionTraceLanes<V>& tr, const V s[3], const V dcov[9],
                                                  V dq[4], V ds[3]) {
  using S = typename simd::lane_scalar<V>::type;
  using detail::dot3_lanes;
  using detail::dot_lanes;
  V dsym[9], dR[9];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) dsym[i * 3 + j] = dcov[i * 3 + j] + dcov[j * 3 + i];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) {  // dM = dsym M; dR = dM diag(s), ds_j = sum_i dM_ij R_ij
      const V dM = dot3_lanes(dsym[i * 3], tr.M[j], dsym[i * 3 + 1], tr.M[3 + j], dsym[i * 3 + 2], tr.M[6 + j]);
      dR[i * 3 + j] = dM * s[j];
      ds[j] = simd::lane_mul_add(dM, tr.R[i * 3 + j], ds[j]);
    }
  // R(w, x, y, z) of the unit quaternion.
  const V w = tr.qn[0], x = tr.qn[1], y = tr.qn[2], z = tr.qn[3];
  const V two = V(S(2)), x2 = two * x, y2 = two * y, z2 = two * z;
  V dqn[4];
  dqn[0] = two * dot_lanes<V, 6>({-z, y, z, -x, -y, x}, {dR[1], dR[2], dR[3], dR[5], dR[6], dR[7]});
  dqn[1] = two * dot_lanes<V, 8>({y, z, y, -x2, -w, z, w, -x2}, {dR[1], dR[2], dR[3], dR[4], dR[5], dR[6], dR[7], dR[8]});
  dqn[2] = two * dot_lanes<V, 8>({-y2, x, w, x, z, -w, z, -y2}, {dR[0], dR[1], dR[2], dR[3], dR[5], dR[6], dR[7], dR[8]});
  dqn[3] = two * dot_lanes<V, 8>({-z2, -w, x, w, -z2, y, x, y}, {dR[0], dR[1], dR[2], dR[3], dR[4], dR[5], dR[6], dR[7]});
  // Through the normalisation q / |q|.
  const V dot = dot_lanes<V, 4>({tr.qn[0], tr.qn[1], tr.qn[2], tr.qn[3]}, {dqn[0], dqn[1], dqn[2], dqn[3]});
  for (int i = 0; i < 4; ++i) dq[i] = dq[i] + simd::lane_mul_add(-tr.qn[i], dot, dqn[i]) / tr.len;
}

// Adds d(mean), d(quat), d(scale), d(opacity) and the camera gradient, one visible Gaussian per lane of V (the
// values of other lanes are unspecified). The same arithmetic per lane as project_backward_one.
template <class V, class T>
FLEXSPLAT_ALWAYS_INLINE void project_backward_lanes(const V m[3], const V q[4], const V s[3], V opacity,
                                                    const ViewParams<T>& cam, const ProjectSettings<T>& set,
                                                    const ProjectionGrad<V>& g, V dm[3], V dq[4], V ds[3],
                                                    V& dopacity, ViewGradParams<V>& dcam) {
  using detail::dot3_lanes;
  using simd::lane_mul_add;
  using simd::lane_select;
  ProjectionTraceLanes<V> tr;
  projection_trace_lanes(m, q, s, cam, set.eps2d, tr);
  const V zero = V(T(0)), half = V(T(0.5)), two = V(T(2));
  const V inv = V(T(1)) / tr.det_b;
  // conic = inverse(cov_b): d cov_b = -Q G Q with G the symmetric cotangent of the conic matrix.
  const V Q0 = tr.c * inv, Q1 = -tr.b * inv, Q3 = tr.a * inv;  // Q2 = Q1
  const V G0 = g.conic[0], G1 = g.conic[1] * half, G3 = g.conic[2];
  const V QG0 = lane_mul_add(Q1, G1, Q0 * G0), QG1 = lane_mul_add(Q1, G3, Q0 * G1);
  const V QG2 = lane_mul_add(Q3, G1, Q1 * G0), QG3 = lane_mul_add(Q3, G3, Q1 * G1);
  // Full symmetric 2x2 cotangent of cov2d (the blur has a unit Jacobian).
  V dC0 = -lane_mul_add(QG1, Q1, QG0 * Q0), dC1 = -lane_mul_add(QG1, Q3, QG0 * Q1);
  V dC2 = -lane_mul_add(QG3, Q1, QG2 * Q0), dC3 = -lane_mul_add(QG3, Q3, QG2 * Q1);
  if (set.antialiased) {
    V det0;
    const V comp = compensation_lanes(tr, det0);
    dopacity = lane_mul_add(g.opacity, comp, dopacity);
    const V dcomp = g.opacity * opacity;
    const V ddet0 = dcomp * comp / (two * det0), ddetb = -dcomp * comp / (two * tr.det_b);
    const auto live = comp > zero;
    const V minus_ddet = -(ddet0 + ddetb);
    dC0 = lane_select(live, dC0 + lane_mul_add(ddetb, tr.c, ddet0 * tr.c11), dC0);
    dC3 = lane_select(live, dC3 + lane_mul_add(ddetb, tr.a, ddet0 * tr.c00), dC3);
    dC1 = lane_select(live, lane_mul_add(minus_ddet, tr.b, dC1), dC1);
    dC2 = lane_select(live, lane_mul_add(minus_ddet, tr.b, dC2), dC2);
  } else {
    dopacity = dopacity + g.opacity;
  }
  // cov2d = J Cc J^T: dJ = (dC + dC^T) J Cc, dCc = J^T dC J (only J00, J02, J11, J12 vary).
  V JC0[3], JC1[3];
  for (int j = 0; j < 3; ++j) {
    JC0[j] = lane_mul_add(tr.J02, tr.cc[6 + j], tr.J00 * tr.cc[j]);
    JC1[j] = lane_mul_add(tr.J12, tr.cc[6 + j], tr.J11 * tr.cc[3 + j]);
  }
  const V S0 = dC0 + dC0, S1 = dC1 + dC2, S2 = dC2 + dC1, S3 = dC3 + dC3;
  const V dJ00 = lane_mul_add(S1, JC1[0], S0 * JC0[0]), dJ02 = lane_mul_add(S1, JC1[2], S0 * JC0[2]);
  const V dJ11 = lane_mul_add(S3, JC1[1], S2 * JC0[1]), dJ12 = lane_mul_add(S3, JC1[2], S2 * JC0[2]);
  // dCc_ij = J0_i A_j + J1_i B_j with A = dC0 J0 + dC1 J1, B = dC2 J0 + dC3 J1 (J0 = (J00, 0, J02), J1 = (0, J11, J12)).
  const V A[3] = {dC0 * tr.J00, dC1 * tr.J11, lane_mul_add(dC1, tr.J12, dC0 * tr.J02)};
  const V B[3] = {dC2 * tr.J00, dC3 * tr.J11, lane_mul_add(dC3, tr.J12, dC2 * tr.J02)};
  V dCc[9];
  for (int j = 0; j < 3; ++j) {
    dCc[j] = tr.J00 * A[j];
    dCc[3 + j] = tr.J11 * B[j];
    dCc[6 + j] = lane_mul_add(tr.J12, B[j], tr.J02 * A[j]);
  }
  // Pixel mean and Jacobian with respect to the camera-space mean and the intrinsics.
  const V fx = V(cam.fx), fy = V(cam.fy);
  const V x = tr.p[0], y = tr.p[1], rz = tr.rz, rz2 = rz * rz;
  V dp[3];
  dp[0] = fx * rz * g.u;
  dp[1] = fy * rz * g.v;
  dp[2] = lane_mul_add(-lane_mul_add(fy * y, g.v, fx * x * g.u), rz2, g.z);
  dcam.fx = lane_mul_add(x * rz, g.u, dcam.fx);
  dcam.fy = lane_mul_add(y * rz, g.v, dcam.fy);
  dcam.cx = dcam.cx + g.u;
  dcam.cy = dcam.cy + g.v;
  // J00 = fx/z, J11 = fy/z, J02 = -fx txr/z, J12 = -fy tyr/z.
  dcam.fx = dcam.fx + lane_mul_add(dJ00, rz, -(dJ02 * tr.txr * rz));
  dcam.fy = dcam.fy + lane_mul_add(dJ11, rz, -(dJ12 * tr.tyr * rz));
  const V e1 = lane_mul_add(fy, dJ11, fx * dJ00), e2 = lane_mul_add(fy * tr.tyr, dJ12, fx * tr.txr * dJ02);
  dp[2] = lane_mul_add(e2 - e1, rz2, dp[2]);
  const V dtxr = -fx * rz * dJ02, dtyr = -fy * rz * dJ12;
  // Inside the clamp txr = x/z; at the clamp txr is a limit (+-(...)/fx) that depends on fx and cx only.
  dp[0] = lane_select(tr.x_clamped, dp[0], lane_mul_add(dtxr, rz, dp[0]));
  dp[2] = lane_select(tr.x_clamped, dp[2], lane_mul_add(-(dtxr * x), rz2, dp[2]));
  dcam.fx = lane_select(tr.x_clamped, lane_mul_add(-(tr.txr / fx), dtxr, dcam.fx), dcam.fx);
  dcam.cx = lane_select(tr.x_clamped, dcam.cx - dtxr / fx, dcam.cx);
  dp[1] = lane_select(tr.y_clamped, dp[1], lane_mul_add(dtyr, rz, dp[1]));
  dp[2] = lane_select(tr.y_clamped, dp[2], lane_mul_add(-(dtyr * y), rz2, dp[2]));
  dcam.fy = lane_select(tr.y_clamped, lane_mul_add(-(tr.tyr / fy), dtyr, dcam.fy), dcam.fy);
  dcam.cy = lane_select(tr.y_clamped, dcam.cy - dtyr / fy, dcam.cy);
  // cov_cam = Rc cw Rc^T: dcw = Rc^T dCc Rc, dRc = (dCc + dCc^T) Rc cw.
  V Rc[9], tmp[9], dcw[9];
  for (int i = 0; i < 9; ++i) Rc[i] = V(cam.R[i]);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) tmp[i * 3 + j] = dot3_lanes(Rc[i], dCc[j], Rc[3 + i], dCc[3 + j], Rc[6 + i], dCc[6 + j]);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      dcw[i * 3 + j] = dot3_lanes(tmp[i * 3], Rc[j], tmp[i * 3 + 1], Rc[3 + j], tmp[i * 3 + 2], Rc[6 + j]);
  // dCc + dCc^T, each sum of products as one multiply-add (rows 0 and 1 of dCc are J00 A and J11 B).
  const V P[2] = {tr.J00, tr.J11};
  const V* X[2] = {A, B};
  V dsym[9];
  for (int i = 0; i < 2; ++i)
    for (int k = 0; k < 3; ++k) dsym[i * 3 + k] = lane_mul_add(P[i], X[i][k], dCc[k * 3 + i]);
  for (int k = 0; k < 2; ++k) dsym[6 + k] = dsym[k * 3 + 2];
  dsym[8] = dCc[8] + dCc[8];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      dcam.R[i * 3 + j] = dcam.R[i * 3 + j] +
                          dot3_lanes(dsym[i * 3], tr.RC[j], dsym[i * 3 + 1], tr.RC[3 + j], dsym[i * 3 + 2], tr.RC[6 + j]);
  // p = Rc m + t
  for (int i = 0; i < 3; ++i) {
    dm[i] = dm[i] + dot3_lanes(Rc[i], dp[0], Rc[3 + i], dp[1], Rc[6 + i], dp[2]);
    dcam.t[i] = dcam.t[i] + dp[i];
    for (int j = 0; j < 3; ++j) dcam.R[i * 3 + j] = lane_mul_add(dp[i], m[j], dcam.R[i * 3 + j]);
  }
  covariance_vjp_lanes(tr, s, dcw, dq, ds);
}

// Adds d(mean), d(quat), d(scale), d(opacity) and the camera gradient for one visible Gaussian.
template <class T>
void project_backward_one(const T m[3], const T q[4], const T s[3], T opacity, const ViewParams<T>& cam,
                          const ProjectSettings<T>& set, const ProjectionGrad<T>& g, T dm[3], T dq[4], T ds[3],
                          T& dopacity, ViewGradParams<T>& dcam) {
  project_backward_lanes<T, T>(m, q, s, opacity, cam, set, g, dm, dq, ds, dopacity, dcam);
}

}  // namespace raster
}  // namespace v0
}  // namespace flexsplat
