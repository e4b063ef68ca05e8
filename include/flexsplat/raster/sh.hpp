#pragma once
// Real spherical harmonics of degree 0-3 evaluated in a view direction, and their vector-Jacobian product.
// Coefficients are [K, channels] row-major with K = (degree+1)^2 or more; bands above `degree` are never read.
#include <cmath>

#include "flexsplat/core/inline.hpp"
#include "flexsplat/core/simd.hpp"
#include "flexsplat/core/simd_dispatch.hpp"  // its lane overloads must be visible where the lane templates are defined
#include "flexsplat/raster/constants.hpp"

namespace flexsplat {
inline namespace v0 {
namespace raster {

// Basis values b[k] for unit directions n, one per lane of V (T: one direction); bands above degree are not written.
// Sums of products go through simd::lane_mul_add (the same rounding on the scalar and batch paths).
template <class V>
FLEXSPLAT_ALWAYS_INLINE void sh_basis_values(int degree, const V n[3], V* b) {
  using S = typename simd::lane_scalar<V>::type;
  using simd::lane_mul_add;
  const V x = n[0], y = n[1], z = n[2];
  b[0] = V(S(sh_c0));
  if (degree < 1) return;
  const V c1 = V(S(sh_c1));
  b[1] = -c1 * y;
  b[2] = c1 * z;
  b[3] = -c1 * x;
  if (degree < 2) return;
  const V yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  const V xx_yy = lane_mul_add(x, x, yy), xx_m_yy = lane_mul_add(x, x, -yy);  // x^2 + y^2, x^2 - y^2
  b[4] = V(S(sh_c2[0])) * xy;
  b[5] = V(S(sh_c2[1])) * yz;
  b[6] = V(S(sh_c2[2])) * lane_mul_add(V(S(2)), zz, -xx_yy);
  b[7] = V(S(sh_c2[3])) * xz;
  b[8] = V(S(sh_c2[4])) * xx_m_yy;
  if (degree < 3) return;
  const V xx = x * x;
  b[9] = V(S(sh_c3[0])) * y * lane_mul_add(V(S(3)), xx, -yy);
  b[10] = V(S(sh_c3[1])) * xy * z;
  b[11] = V(S(sh_c3[2])) * y * lane_mul_add(V(S(4)), zz, -xx_yy);
  b[12] = V(S(sh_c3[3])) * z * lane_mul_add(V(S(2)), zz, V(S(-3)) * xx_yy);
  b[13] = V(S(sh_c3[4])) * x * lane_mul_add(V(S(4)), zz, -xx_yy);
  b[14] = V(S(sh_c3[5])) * z * xx_m_yy;
  b[15] = V(S(sh_c3[6])) * x * lane_mul_add(V(S(-3)), yy, xx);
}

// Basis values b[k] for a unit direction n, and (optionally) their gradients g[k][3] with respect to n.
template <class T>
FLEXSPLAT_ALWAYS_INLINE void sh_basis(int degree, const T n[3], T* b, T (*g)[3]) {
  const T x = n[0], y = n[1], z = n[2];
  b[0] = T(sh_c0);
  if (g) g[0][0] = g[0][1] = g[0][2] = T(0);
  if (degree < 1) return;
  const T c1 = T(sh_c1);
  b[1] = -c1 * y;
  b[2] = c1 * z;
  b[3] = -c1 * x;
  if (g) {
    g[1][0] = 0, g[1][1] = -c1, g[1][2] = 0;
    g[2][0] = 0, g[2][1] = 0, g[2][2] = c1;
    g[3][0] = -c1, g[3][1] = 0, g[3][2] = 0;
  }
  if (degree < 2) return;
  const T xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  const T c20 = T(sh_c2[0]), c21 = T(sh_c2[1]), c22 = T(sh_c2[2]), c23 = T(sh_c2[3]), c24 = T(sh_c2[4]);
  b[4] = c20 * xy;
  b[5] = c21 * yz;
  b[6] = c22 * (T(2) * zz - xx - yy);
  b[7] = c23 * xz;
  b[8] = c24 * (xx - yy);
  if (g) {
    g[4][0] = c20 * y, g[4][1] = c20 * x, g[4][2] = 0;
    g[5][0] = 0, g[5][1] = c21 * z, g[5][2] = c21 * y;
    g[6][0] = T(-2) * c22 * x, g[6][1] = T(-2) * c22 * y, g[6][2] = T(4) * c22 * z;
    g[7][0] = c23 * z, g[7][1] = 0, g[7][2] = c23 * x;
    g[8][0] = T(2) * c24 * x, g[8][1] = T(-2) * c24 * y, g[8][2] = 0;
  }
  if (degree < 3) return;
  const T c30 = T(sh_c3[0]), c31 = T(sh_c3[1]), c32 = T(sh_c3[2]), c33 = T(sh_c3[3]), c34 = T(sh_c3[4]),
          c35 = T(sh_c3[5]), c36 = T(sh_c3[6]);
  b[9] = c30 * y * (T(3) * xx - yy);
  b[10] = c31 * xy * z;
  b[11] = c32 * y * (T(4) * zz - xx - yy);
  b[12] = c33 * z * (T(2) * zz - T(3) * xx - T(3) * yy);
  b[13] = c34 * x * (T(4) * zz - xx - yy);
  b[14] = c35 * z * (xx - yy);
  b[15] = c36 * x * (xx - T(3) * yy);
  if (g) {
    g[9][0] = T(6) * c30 * xy, g[9][1] = c30 * (T(3) * xx - T(3) * yy), g[9][2] = 0;
    g[10][0] = c31 * yz, g[10][1] = c31 * xz, g[10][2] = c31 * xy;
    g[11][0] = T(-2) * c32 * xy, g[11][1] = c32 * (T(4) * zz - xx - T(3) * yy), g[11][2] = T(8) * c32 * yz;
    g[12][0] = T(-6) * c33 * xz, g[12][1] = T(-6) * c33 * yz, g[12][2] = c33 * (T(6) * zz - T(3) * xx - T(3) * yy);
    g[13][0] = c34 * (T(4) * zz - T(3) * xx - yy), g[13][1] = T(-2) * c34 * xy, g[13][2] = T(8) * c34 * xz;
    g[14][0] = T(2) * c35 * xz, g[14][1] = T(-2) * c35 * yz, g[14][2] = c35 * (xx - yy);
    g[15][0] = c36 * (T(3) * xx - T(3) * yy), g[15][1] = T(-6) * c36 * xy, g[15][2] = 0;
  }
}

// Unit direction of dir; a zero direction (Gaussian at the camera centre) maps to +z so the result stays finite.
template <class T>
T sh_normalize(const T dir[3], T n[3]) {
  const T len = std::sqrt(dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]);
  if (!(len > T(0))) {
    n[0] = 0, n[1] = 0, n[2] = 1;
    return T(0);
  }
  n[0] = dir[0] / len, n[1] = dir[1] / len, n[2] = dir[2] / len;
  return len;
}

// sh_forward with one Gaussian per lane of V: coeffs[k * channels + c] holds coefficient (k, c) of every lane. The
// scalar path (sh_forward) is this body with V = T, so lanes are bit-identical to it.
template <class V>
FLEXSPLAT_ALWAYS_INLINE void sh_forward_lanes(int degree, int channels, const V* coeffs, const V dir[3], V* out) {
  using S = typename simd::lane_scalar<V>::type;
  using simd::lane_mul_add;
  const V len = simd::lane_sqrt(lane_mul_add(dir[2], dir[2], lane_mul_add(dir[1], dir[1], dir[0] * dir[0])));
  const auto toward = len > V(S(0));  // else the +z direction, as sh_normalize
  const V n[3] = {simd::lane_select(toward, dir[0] / len, V(S(0))), simd::lane_select(toward, dir[1] / len, V(S(0))),
                  simd::lane_select(toward, dir[2] / len, V(S(1)))};
  V b[16];
  sh_basis_values(degree, n, b);
  const int k_count = sh_coefficients(degree);
  for (int c = 0; c < channels; ++c) {
    V s = V(S(0));
    for (int k = 0; k < k_count; ++k) s = lane_mul_add(b[k], coeffs[k * channels + c], s);
    out[c] = s;
  }
}

// out[c] = sum_k b_k(dir / |dir|) * coeffs[k * channels + c]; no offset, no clamp.
template <class T>
void sh_forward(int degree, int channels, const T* coeffs, const T dir[3], T* out) {
  sh_forward_lanes<T>(degree, channels, coeffs, dir, out);
}

// Adds d(coeffs) and d(dir) for the cotangent d_out[channels]; d_dir may be null.
template <class T>
void sh_backward(int degree, int channels, const T* coeffs, const T dir[3], const T* d_out, T* d_coeffs, T* d_dir) {
  T n[3], b[16], g[16][3];
  const T len = sh_normalize(dir, n);
  sh_basis<T>(degree, n, b, g);
  const int k_count = sh_coefficients(degree);
  T d_n[3] = {0, 0, 0};
  for (int k = 0; k < k_count; ++k) {
    T dk = 0;
    for (int c = 0; c < channels; ++c) {
      d_coeffs[k * channels + c] += b[k] * d_out[c];
      dk += coeffs[k * channels + c] * d_out[c];
    }
    d_n[0] += dk * g[k][0], d_n[1] += dk * g[k][1], d_n[2] += dk * g[k][2];
  }
  if (!d_dir || !(len > T(0)) || degree == 0) return;
  const T proj = n[0] * d_n[0] + n[1] * d_n[1] + n[2] * d_n[2];
  for (int i = 0; i < 3; ++i) d_dir[i] += (d_n[i] - n[i] * proj) / len;
}

}  // namespace raster
}  // namespace v0
}  // namespace flexsplat
