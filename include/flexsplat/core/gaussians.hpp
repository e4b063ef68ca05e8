#pragma once
// The one Gaussian-set type: what the decoder produces, the rasterizer renders and export writes, with its gradient
// type and the real spherical-harmonics constants every module uses.
//
//   GaussianSet<T> set = make_gaussian_set<T>(n, sh_degree);   // or resize_gaussian_set(set, n, degree) to reuse
//   set.means [N, 3] world positions; set.quats [N, 4] rotations (w, x, y, z), normalised where used;
//   set.scales [N, 3] linear standard deviations; set.opacities [N] in [0, 1];
//   set.sh [N, K, 3], K = (degree + 1)^2, coefficient-major (the RGB triple of coefficient k is contiguous), DC first;
//   set.features [N, F], optional per-Gaussian features the rasterizer blends (empty: none; not exported).
//   GaussianSetGrad<T> grad = make_gaussian_grad(set);        // zeros of the same shapes; an empty field = not wanted
#include <algorithm>
#include <cmath>
#include <string>
#include <type_traits>
#include <vector>

#include <glm/glm.hpp>
#include <glm/gtc/quaternion.hpp>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {

// Real spherical-harmonics constants of the 3DGS papers, bands 0 to 3.
inline constexpr double sh_c0 = 0.28209479177387814;
inline constexpr double sh_c1 = 0.4886025119029199;
inline constexpr double sh_c2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
                                    -1.0925484305920792, 0.5462742152960396};
inline constexpr double sh_c3[7] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
                                    -0.4570457994644658, 1.445305721320277, -0.5900435899266435};
inline constexpr double sh_color_offset = 0.5;  // colour = SH(direction) + 0.5, clamped at 0
inline constexpr int max_sh_degree = 3;

inline constexpr int sh_coefficients(int degree) { return (degree + 1) * (degree + 1); }

// SH degree for a coefficient count K; only complete degrees 0..3 exist.
inline int sh_degree_for(index_t coefficients, const std::string& context) {
  for (int d = 0; d <= max_sh_degree; ++d)
    if (coefficients == sh_coefficients(d)) return d;
  fail(context, ": ", coefficients, " SH coefficients per Gaussian is not a complete degree 0-3 (1, 4, 9 or 16)");
}

template <class T>
struct GaussianSet {
  Tensor<T, 2> means;      // [N, 3]
  Tensor<T, 2> quats;      // [N, 4] w x y z
  Tensor<T, 2> scales;     // [N, 3] linear standard deviations
  Tensor<T, 1> opacities;  // [N] in [0, 1]
  Tensor<T, 3> sh;         // [N, K, 3]
  Tensor<T, 2> features;   // [N, F] or empty

  index_t size() const noexcept { return means.shape(0); }
  int sh_degree() const { return sh_degree_for(sh.shape(1), "Gaussian set"); }
  index_t feature_count() const noexcept { return features.empty() ? 0 : features.shape(1); }
};

// Gradients of a loss with respect to every field of a GaussianSet, same shapes; backward passes ADD into them.
// An empty field is skipped by producers (no gradient wanted) and read as zero by consumers.
template <class T>
struct GaussianSetGrad {
  Tensor<T, 2> means, quats, scales;
  Tensor<T, 1> opacities;
  Tensor<T, 3> sh;
  Tensor<T, 2> features;

  void zero() {
    for (auto* t : {&means, &quats, &scales, &features}) t->fill(T(0));
    opacities.fill(T(0));
    sh.fill(T(0));
  }
};

// Sizes set for n Gaussians of the given SH degree and feature count, keeping capacity (no allocation when it does
// not grow). Values: zero means, SH and features, identity rotations, unit scales, opacity 1.
template <class T>
void resize_gaussian_set(GaussianSet<T>& set, index_t n, int sh_degree, index_t feature_count = 0) {
  require(n >= 0, "Gaussian set: negative count ", n);
  require(sh_degree >= 0 && sh_degree <= max_sh_degree, "Gaussian set: SH degree ", sh_degree, " outside 0..3");
  require(feature_count >= 0, "Gaussian set: negative feature count ", feature_count);
  set.means.resize({n, 3});
  set.quats.resize({n, 4});
  for (index_t i = 0; i < n; ++i) set.quats(i, 0) = T(1);
  set.scales.resize({n, 3});
  set.scales.fill(T(1));
  set.opacities.resize({n});
  set.opacities.fill(T(1));
  set.sh.resize({n, sh_coefficients(sh_degree), 3});
  set.features.resize({feature_count > 0 ? n : 0, feature_count});
}

template <class T>
GaussianSet<T> make_gaussian_set(index_t n, int sh_degree, index_t feature_count = 0) {
  GaussianSet<T> set;
  resize_gaussian_set(set, n, sh_degree, feature_count);
  return set;
}

// Zero gradients shaped like set (features only if the set has them); reuses g's capacity.
template <class T>
void resize_gaussian_grad(GaussianSetGrad<T>& g, const GaussianSet<T>& set) {
  g.means.resize(set.means.shape());
  g.quats.resize(set.quats.shape());
  g.scales.resize(set.scales.shape());
  g.opacities.resize(set.opacities.shape());
  g.sh.resize(set.sh.shape());
  g.features.resize(set.features.shape());
}

template <class T>
GaussianSetGrad<T> make_gaussian_grad(const GaussianSet<T>& set) {
  GaussianSetGrad<T> g;
  resize_gaussian_grad(g, set);
  return g;
}

// The fields agree with each other ([N,3], [N,4], [N,3], [N], [N,K,3] with K a complete degree, [N,F] or empty);
// throws naming the tensor and both shapes otherwise.
template <class T>
void check_gaussian_shapes(const GaussianSet<T>& set, const std::string& context) {
  const index_t n = set.means.shape(0);
  auto expect = [&](const char* name, auto shape, auto want) {
    if (shape != want)
      fail(context, ": tensor '", name, "' has shape ", shape_string(shape), ", expected ", shape_string(want));
  };
  expect("means", set.means.shape(), Shape<2>{n, 3});
  expect("quats", set.quats.shape(), Shape<2>{n, 4});
  expect("scales", set.scales.shape(), Shape<2>{n, 3});
  expect("opacities", set.opacities.shape(), Shape<1>{n});
  if (set.sh.shape(0) != n || set.sh.shape(2) != 3)
    fail(context, ": tensor 'sh' has shape ", shape_string(set.sh.shape()), ", expected [", n, ", K, 3]");
  sh_degree_for(set.sh.shape(1), context);
  if (!set.features.empty() && set.features.shape(0) != n)
    fail(context, ": tensor 'features' has shape ", shape_string(set.features.shape()), ", expected [", n,
         ", F] or empty");
}

// Element-type conversion (files store float32; gradient checks use double).
template <class To, class From>
GaussianSet<To> convert_gaussian_set(const GaussianSet<From>& in) {
  GaussianSet<To> out;
  auto copy = [](const auto& src, auto& dst) {
    dst.resize(src.shape());
    for (index_t i = 0; i < src.size(); ++i) dst.data()[i] = static_cast<To>(src.data()[i]);
  };
  copy(in.means, out.means);
  copy(in.quats, out.quats);
  copy(in.scales, out.scales);
  copy(in.opacities, out.opacities);
  copy(in.sh, out.sh);
  copy(in.features, out.features);
  return out;
}

// The rows `keep` of a set (in that order), features included.
template <class T>
GaussianSet<T> select_gaussians(const GaussianSet<T>& set, const std::vector<index_t>& keep) {
  const index_t m = static_cast<index_t>(keep.size()), n = set.size();
  const index_t K = set.sh.shape(1), F = set.features.empty() ? 0 : set.features.shape(1);
  GaussianSet<T> c = make_gaussian_set<T>(m, set.sh_degree());
  if (F > 0) c.features = Tensor<T, 2>(Shape<2>{m, F});
  for (index_t j = 0; j < m; ++j) {
    const index_t i = keep[static_cast<std::size_t>(j)];
    require(i >= 0 && i < n, "select_gaussians: row ", i, " of a set of ", n);
    std::copy_n(&set.means(i, 0), 3, &c.means(j, 0));
    std::copy_n(&set.quats(i, 0), 4, &c.quats(j, 0));
    std::copy_n(&set.scales(i, 0), 3, &c.scales(j, 0));
    c.opacities(j) = set.opacities(i);
    std::copy_n(set.sh.data() + i * K * 3, K * 3, c.sh.data() + j * K * 3);
    if (F > 0) std::copy_n(&set.features(i, 0), F, &c.features(j, 0));
  }
  return c;
}

// The set moved by the similarity x -> scale * R x + t (R a rotation): centres mapped, standard deviations times
// scale, orientations turned by R, the SH's view-dependent band 1 turned with the directions it is evaluated on.
// Bands 2-3 would need their own rotation matrices: a set of degree above 1 is refused unless R = I.
template <class T>
void transform_gaussians(GaussianSet<T>& set, const glm::dmat3& R, const glm::dvec3& t, double scale) {
  require(std::isfinite(scale) && scale > 0, "transform_gaussians: scale ", scale, " must be finite and positive");
  require(set.sh_degree() <= 1 || R == glm::dmat3(1.0), "transform_gaussians: SH degree ", set.sh_degree(),
          " cannot be rotated (bands 2-3 are not implemented); degree 0 or 1 only");
  const glm::dquat q = glm::quat_cast(R);
  const index_t K = set.sh.shape(1);
  for (index_t i = 0; i < set.size(); ++i) {
    const glm::dvec3 m = scale * (R * glm::dvec3(set.means(i, 0), set.means(i, 1), set.means(i, 2))) + t;
    const glm::dquat p = q * glm::dquat(set.quats(i, 0), set.quats(i, 1), set.quats(i, 2), set.quats(i, 3));
    for (int r = 0; r < 3; ++r) {
      set.means(i, r) = static_cast<T>(m[r]);
      set.scales(i, r) = static_cast<T>(scale * set.scales(i, r));
    }
    set.quats(i, 0) = static_cast<T>(p.w), set.quats(i, 1) = static_cast<T>(p.x);
    set.quats(i, 2) = static_cast<T>(p.y), set.quats(i, 3) = static_cast<T>(p.z);
    if (K < 4) continue;
    // Band 1 is c1 (-y s1 + z s2 - x s3): the coefficient vector (-s3, -s1, s2) turns as a direction does.
    for (int ch = 0; ch < 3; ++ch) {
      const glm::dvec3 w = R * glm::dvec3(-set.sh(i, 3, ch), -set.sh(i, 1, ch), set.sh(i, 2, ch));
      set.sh(i, 3, ch) = static_cast<T>(-w.x);
      set.sh(i, 1, ch) = static_cast<T>(-w.y);
      set.sh(i, 2, ch) = static_cast<T>(w.z);
    }
  }
}

}  // namespace v0
}  // namespace flexsplat
