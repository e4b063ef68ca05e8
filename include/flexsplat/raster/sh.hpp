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

// Gradients g[k][3] of the basis values with respect to a unit direction n, bands 1 to degree, one direction per
// lane of V (band 0 is constant); sums of products through simd::lane_mul_add, as sh_basis_values.
template <class V>
FLEXSPLAT_ALWAYS_INLINE void sh_basis_gradients(int degree, const V n[3], V (*g)[3]) {
  using S = typename simd::lane_scalar<V>::type;
  using simd::lane_mul_add;
  const V x = n[0], y = n[1], z = n[2], zero = V(S(0));
  if (degree < 1) return;
  const V c1 = V(S(sh_c1));
  g[1][0] = zero, g[1][1] = -c1, g[1][2] = zero;
  g[2][0] = zero, g[2][1] = zero, g[2][2] = c1;
  g[3][0] = -c1, g[3][1] = zero, g[3][2] = zero;
  if (degree < 2) return;
  const V c20 = V(S(sh_c2[0])), c21 = V(S(sh_c2[1])), c22 = V(S(sh_c2[2])), c23 = V(S(sh_c2[3])), c24 = V(S(sh_c2[4]));
  g[4][0] = c20 * y, g[4][1] = c20 * x, g[4][2] = zero;
  g[5][0] = zero, g[5][1] = c21 * z, g[5][2] = c21 * y;
  g[6][0] = V(S(-2)) * c22 * x, g[6][1] = V(S(-2)) * c22 * y, g[6][2] = V(S(4)) * c22 * z;
  g[7][0] = c23 * z, g[7][1] = zero, g[7][2] = c23 * x;
  g[8][0] = V(S(2)) * c24 * x, g[8][1] = V(S(-2)) * c24 * y, g[8][2] = zero;
  if (degree < 3) return;
  const V c30 = V(S(sh_c3[0])), c31 = V(S(sh_c3[1])), c32 = V(S(sh_c3[2])), c33 = V(S(sh_c3[3])),
          c34 = V(S(sh_c3[4])), c35 = V(S(sh_c3[5])), c36 = V(S(sh_c3[6]));
  const V xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  const V xx_yy = lane_mul_add(x, x, yy), xx_m_yy = lane_mul_add(x, x, -yy);  // x^2 + y^2, x^2 - y^2
  const V three = V(S(3)), four = V(S(4));
  g[9][0] = V(S(6)) * c30 * xy, g[9][1] = c30 * (three * xx_m_yy), g[9][2] = zero;
  g[10][0] = c31 * yz, g[10][1] = c31 * xz, g[10][2] = c31 * xy;
  g[11][0] = V(S(-2)) * c32 * xy, g[11][1] = c32 * lane_mul_add(four, zz, -lane_mul_add(three, yy, xx));
  g[11][2] = V(S(8)) * c32 * yz;
  g[12][0] = V(S(-6)) * c33 * xz, g[12][1] = V(S(-6)) * c33 * yz;
  g[12][2] = c33 * lane_mul_add(V(S(6)), zz, -(three * xx_yy));
  g[13][0] = c34 * lane_mul_add(four, zz, -lane_mul_add(three, xx, yy)), g[13][1] = V(S(-2)) * c34 * xy;
  g[13][2] = V(S(8)) * c34 * xz;
  g[14][0] = V(S(2)) * c35 * xz, g[14][1] = V(S(-2)) * c35 * yz, g[14][2] = c35 * xx_m_yy;
  g[15][0] = c36 * (three * xx_m_yy), g[15][1] = V(S(-6)) * c36 * xy, g[15][2] = zero;
}

// Unit direction of dir per lane, +z for a zero direction (a Gaussian at the camera centre) so the result stays
// finite; returns |dir| and the mask of lanes with a direction.
template <class V>
FLEXSPLAT_ALWAYS_INLINE V sh_direction_lanes(const V dir[3], V n[3], simd::lane_mask<V>& toward) {
  using S = typename simd::lane_scalar<V>::type;
  using simd::lane_mul_add;
  const V len = simd::lane_sqrt(lane_mul_add(dir[2], dir[2], lane_mul_add(dir[1], dir[1], dir[0] * dir[0])));
  toward = len > V(S(0));
  n[0] = simd::lane_select(toward, dir[0] / len, V(S(0)));
  n[1] = simd::lane_select(toward, dir[1] / len, V(S(0)));
  n[2] = simd::lane_select(toward, dir[2] / len, V(S(1)));
  return len;
}

// sh_forward with one Gaussian per lane of V: coeffs[k * channels + c] holds coefficient (k, c) of every lane. The
// scalar path (sh_forward) is this body with V = T, so lanes are bit-identical to it.
template <class V>
FLEXSPLAT_ALWAYS_INLINE void sh_forward_lanes(int degree, int channels, const V* coeffs, const V dir[3], V* out) {
  using S = typename simd::lane_scalar<V>::type;
  using simd::lane_mul_add;
  V n[3], b[16];
  simd::lane_mask<V> toward;
  sh_direction_lanes(dir, n, toward);
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

// The backward of sh_forward_lanes: writes d_coeffs[k * channels + c] = b_k d_out[c] (k < (degree+1)^2; the
// caller adds them) and adds d(dir) into d_dir (nothing for a zero direction or degree 0). The scalar path
// (sh_backward) is this body with V = T, so lanes are bit-identical to it.
template <class V>
FLEXSPLAT_ALWAYS_INLINE void sh_backward_lanes(int degree, int channels, const V* coeffs, const V dir[3],
                                               const V* d_out, V* d_coeffs, V d_dir[3]) {
  using S = typename simd::lane_scalar<V>::type;
  using simd::lane_mul_add;
  V n[3], b[16] = {}, g[16][3];  // (b zeroed: GCC 12 cannot see that bands up to degree are written)
  simd::lane_mask<V> toward;
  const V len = sh_direction_lanes(dir, n, toward);
  sh_basis_values(degree, n, b);
  sh_basis_gradients(degree, n, g);
  const int k_count = sh_coefficients(degree);
  for (int k = 0; k < k_count; ++k)
    for (int c = 0; c < channels; ++c) d_coeffs[k * channels + c] = b[k] * d_out[c];
  if (degree == 0) return;
  V d_n[3] = {V(S(0)), V(S(0)), V(S(0))};
  for (int k = 1; k < k_count; ++k) {
    V dk = coeffs[k * channels] * d_out[0];
    for (int c = 1; c < channels; ++c) dk = lane_mul_add(coeffs[k * channels + c], d_out[c], dk);
    for (int i = 0; i < 3; ++i) d_n[i] = lane_mul_add(dk, g[k][i], d_n[i]);
  }
  // Through the normalisation dir / |dir|.
  const V proj = lane_mul_add(n[2], d_n[2], lane_mul_add(n[1], d_n[1], n[0] * d_n[0]));
  for (int i = 0; i < 3; ++i)
    d_dir[i] = simd::lane_select(toward, d_dir[i] + lane_mul_add(-n[i], proj, d_n[i]) / len, d_dir[i]);
}

// Adds d(coeffs) and d(dir) for the cotangent d_out[channels] (channels <= 3); d_dir may be null.
template <class T>
void sh_backward(int degree, int channels, const T* coeffs, const T dir[3], const T* d_out, T* d_coeffs, T* d_dir) {
  T products[16 * 3], d_dir_local[3] = {0, 0, 0};
  sh_backward_lanes<T>(degree, channels, coeffs, dir, d_out, products, d_dir ? d_dir : d_dir_local);
  for (int j = 0; j < sh_coefficients(degree) * channels; ++j) d_coeffs[j] += products[j];
}

}  // namespace raster
}  // namespace v0
}  // namespace flexsplat
