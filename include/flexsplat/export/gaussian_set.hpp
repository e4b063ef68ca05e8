#pragma once
// The public Gaussian set: what reconstructions produce and what the glb / PLY writers and readers exchange.
#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <string>
#include <type_traits>
#include <vector>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {
namespace gaussians {

// Degree-0 real spherical harmonic constant: colour = SH_C0 * dc + 0.5 (3DGS and KHR_gaussian_splatting).
inline constexpr double SH_C0 = 0.28209479177387814;
inline constexpr int kMaxShDegree = 3;
// A stored quaternion counts as unit when its norm is within this of 1 (float32 storage keeps ~1e-7).
inline constexpr double kUnitQuaternionTolerance = 1e-4;
// Export renormalises quaternions whose norm is further than this from 1 and counts them.
inline constexpr double kRenormaliseThreshold = 1e-6;

inline constexpr int sh_coefficients(int degree) { return (degree + 1) * (degree + 1); }

// SH degree for a coefficient count K; only complete degrees 0..3 exist.
inline int sh_degree_for(index_t coefficients, const std::string& context) {
  for (int d = 0; d <= kMaxShDegree; ++d)
    if (coefficients == sh_coefficients(d)) return d;
  fail(context, ": ", coefficients, " SH coefficients per Gaussian is not a complete degree 0-3 (1, 4, 9 or 16)");
}

// A pinhole camera in OpenCV axes (x right, y down, z forward), pixel centres at +0.5.
struct Camera {
  std::string name;
  int width = 0;
  int height = 0;
  std::array<double, 9> K{};    // row-major 3x3 intrinsics
  std::array<double, 12> w2c{};  // row-major 3x4 world-to-camera [R | t]
};

template <class T>
struct GaussianSet {
  Tensor<T, 2> positions;  // [N, 3]
  Tensor<T, 2> rotations;  // [N, 4] unit quaternions, w x y z
  Tensor<T, 2> scales;     // [N, 3] linear standard deviations, >= 0
  Tensor<T, 1> opacities;  // [N] in [0, 1]
  Tensor<T, 3> sh;         // [N, K, 3], K = (degree + 1)^2, coefficient-major with the DC term first
  std::vector<Camera> cameras;

  index_t size() const noexcept { return positions.shape(0); }
  int sh_degree() const { return sh_degree_for(sh.shape(1), "Gaussian set"); }
};

// Identity rotations, zero positions and SH, unit scales and opacity 1: callers overwrite what they need.
template <class T>
GaussianSet<T> make_gaussian_set(index_t count, int sh_degree) {
  require(count >= 0, "Gaussian set: negative count ", count);
  require(sh_degree >= 0 && sh_degree <= kMaxShDegree, "Gaussian set: SH degree ", sh_degree, " outside 0..3");
  GaussianSet<T> set;
  set.positions = Tensor<T, 2>({count, 3});
  set.rotations = Tensor<T, 2>({count, 4});
  for (index_t i = 0; i < count; ++i) set.rotations(i, 0) = T(1);
  set.scales = Tensor<T, 2>({count, 3}, T(1));
  set.opacities = Tensor<T, 1>({count}, T(1));
  set.sh = Tensor<T, 3>({count, sh_coefficients(sh_degree), 3});
  return set;
}

// Element-type conversion (the I/O layer stores float32; gradient checks and tests use double).
template <class To, class From>
GaussianSet<To> convert_set(const GaussianSet<From>& in) {
  GaussianSet<To> out;
  auto copy = [](const auto& src, auto& dst) {
    using Dst = std::remove_reference_t<decltype(dst)>;
    dst = Dst(src.shape());
    for (index_t i = 0; i < src.size(); ++i) dst.data()[i] = static_cast<To>(src.data()[i]);
  };
  copy(in.positions, out.positions);
  copy(in.rotations, out.rotations);
  copy(in.scales, out.scales);
  copy(in.opacities, out.opacities);
  copy(in.sh, out.sh);
  out.cameras = in.cameras;
  return out;
}

// Shapes agree with each other; throws naming the tensor and both shapes otherwise.
template <class T>
void check_shapes(const GaussianSet<T>& set, const std::string& context) {
  const index_t n = set.positions.shape(0);
  auto expect = [&](const char* name, auto shape, auto want) {
    require(shape == want, context, ": tensor '", name, "' has shape ", shape_string(shape), ", expected ",
            shape_string(want));
  };
  expect("positions", set.positions.shape(), Shape<2>{n, 3});
  expect("rotations", set.rotations.shape(), Shape<2>{n, 4});
  expect("scales", set.scales.shape(), Shape<2>{n, 3});
  expect("opacities", set.opacities.shape(), Shape<1>{n});
  require(set.sh.shape(0) == n && set.sh.shape(2) == 3, context, ": tensor 'sh' has shape ",
          shape_string(set.sh.shape()), ", expected [", n, ", K, 3]");
  sh_degree_for(set.sh.shape(1), context);
  for (const Camera& cam : set.cameras) {
    require(cam.width > 0 && cam.height > 0, context, ": camera '", cam.name, "' has image size ", cam.width, "x",
            cam.height);
    for (double v : cam.K) require(std::isfinite(v), context, ": camera '", cam.name, "' has a non-finite K entry");
    for (double v : cam.w2c) require(std::isfinite(v), context, ": camera '", cam.name, "' has a non-finite w2c entry");
    require(cam.K[0] > 0 && cam.K[4] > 0, context, ": camera '", cam.name, "' has focal lengths fx=", cam.K[0],
            " fy=", cam.K[4], " (must be positive)");
  }
}

template <class T>
double quaternion_norm(const GaussianSet<T>& set, index_t i) {
  double s = 0;
  for (int c = 0; c < 4; ++c) s += double(set.rotations(i, c)) * double(set.rotations(i, c));
  return std::sqrt(s);
}

// The invariants of a stored set: finite values, unit quaternions, non-negative scales, opacities in [0, 1].
template <class T>
void validate(const GaussianSet<T>& set, const std::string& context = "Gaussian set") {
  check_shapes(set, context);
  auto finite = [&](const char* name, const auto& tensor, index_t per_gaussian) {
    for (index_t k = 0; k < tensor.size(); ++k)
      require(std::isfinite(double(tensor.data()[k])), context, ": tensor '", name, "' has a non-finite value ",
              double(tensor.data()[k]), " at Gaussian ", k / std::max<index_t>(per_gaussian, 1));
  };
  const index_t n = set.size();
  finite("positions", set.positions, 3);
  finite("rotations", set.rotations, 4);
  finite("scales", set.scales, 3);
  finite("opacities", set.opacities, 1);
  finite("sh", set.sh, set.sh.shape(1) * 3);
  for (index_t i = 0; i < n; ++i) {
    const double norm = quaternion_norm(set, i);
    require(std::abs(norm - 1.0) <= kUnitQuaternionTolerance, context, ": rotation of Gaussian ", i,
            " is not a unit quaternion (norm ", norm, ")");
    for (int c = 0; c < 3; ++c)
      require(set.scales(i, c) >= T(0), context, ": scale ", c, " of Gaussian ", i, " is negative (",
              double(set.scales(i, c)), ")");
    require(set.opacities(i) >= T(0) && set.opacities(i) <= T(1), context, ": opacity of Gaussian ", i, " is ",
            double(set.opacities(i)), ", outside [0, 1]");
  }
}

// What export changed to make a set valid; NaN, negative scales and zero quaternions are errors, not repairs.
struct ExportRepairs {
  index_t opacities_clamped = 0;
  index_t rotations_renormalised = 0;
};

template <class T>
ExportRepairs repair_for_export(GaussianSet<T>& set, const std::string& context = "Gaussian set") {
  check_shapes(set, context);
  ExportRepairs repairs;
  for (index_t i = 0; i < set.size(); ++i) {
    const double norm = quaternion_norm(set, i);
    require(std::isfinite(norm) && norm > 1e-12, context, ": rotation of Gaussian ", i,
            " cannot be normalised (norm ", norm, ")");
    if (std::abs(norm - 1.0) > kRenormaliseThreshold) {
      for (int c = 0; c < 4; ++c) set.rotations(i, c) = T(double(set.rotations(i, c)) / norm);
      ++repairs.rotations_renormalised;
    }
    const T o = set.opacities(i);
    if (std::isfinite(double(o)) && (o < T(0) || o > T(1))) {
      set.opacities(i) = std::clamp(o, T(0), T(1));
      ++repairs.opacities_clamped;
    }
  }
  validate(set, context);
  return repairs;
}

struct Bounds {
  std::array<double, 3> min{};
  std::array<double, 3> max{};
};

// Axis-aligned bounds of the means; an empty set gives all zeros.
template <class T>
Bounds position_bounds(const GaussianSet<T>& set) {
  Bounds b;
  if (set.size() == 0) return b;
  for (int c = 0; c < 3; ++c) b.min[c] = b.max[c] = double(set.positions(0, c));
  for (index_t i = 1; i < set.size(); ++i)
    for (int c = 0; c < 3; ++c) {
      b.min[c] = std::min(b.min[c], double(set.positions(i, c)));
      b.max[c] = std::max(b.max[c], double(set.positions(i, c)));
    }
  return b;
}

}  // namespace gaussians
}  // namespace v0
}  // namespace flexsplat
