#pragma once
// What a stored Gaussian set must satisfy (finite, unit quaternions, scales >= 0, opacities in [0, 1]), the repairs
// export makes, and the cameras files carry alongside the set (the set type itself is core/gaussians.hpp).
#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <string>
#include <type_traits>
#include <vector>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/gaussians.hpp"
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {
namespace gaussians {

// A stored quaternion counts as unit when its norm is within this of 1 (float32 storage keeps ~1e-7).
inline constexpr double kUnitQuaternionTolerance = 1e-4;
// Export renormalises quaternions whose norm is further than this from 1 and counts them.
inline constexpr double kRenormaliseThreshold = 1e-6;

template <class T>
double quaternion_norm(const GaussianSet<T>& set, index_t i) {
  double s = 0;
  for (int c = 0; c < 4; ++c) s += double(set.quats(i, c)) * double(set.quats(i, c));
  return std::sqrt(s);
}

// The invariants of a stored set: finite values, unit quaternions, non-negative scales, opacities in [0, 1].
template <class T>
void validate(const GaussianSet<T>& set, const std::string& context = "Gaussian set") {
  check_gaussian_shapes(set, context);
  auto finite = [&](const char* name, const auto& tensor, index_t per_gaussian) {
    for (index_t k = 0; k < tensor.size(); ++k)
      require(std::isfinite(double(tensor.data()[k])), context, ": tensor '", name, "' has a non-finite value ",
              double(tensor.data()[k]), " at Gaussian ", k / std::max<index_t>(per_gaussian, 1));
  };
  const index_t n = set.size();
  finite("means", set.means, 3);
  finite("quats", set.quats, 4);
  finite("scales", set.scales, 3);
  finite("opacities", set.opacities, 1);
  finite("sh", set.sh, set.sh.shape(1) * 3);
  finite("features", set.features, set.feature_count());
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
  check_gaussian_shapes(set, context);
  ExportRepairs repairs;
  for (index_t i = 0; i < set.size(); ++i) {
    const double norm = quaternion_norm(set, i);
    require(std::isfinite(norm) && norm > 1e-12, context, ": rotation of Gaussian ", i,
            " cannot be normalised (norm ", norm, ")");
    if (std::abs(norm - 1.0) > kRenormaliseThreshold) {
      for (int c = 0; c < 4; ++c) set.quats(i, c) = T(double(set.quats(i, c)) / norm);
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
  for (int c = 0; c < 3; ++c) b.min[c] = b.max[c] = double(set.means(0, c));
  for (index_t i = 1; i < set.size(); ++i)
    for (int c = 0; c < 3; ++c) {
      b.min[c] = std::min(b.min[c], double(set.means(i, c)));
      b.max[c] = std::max(b.max[c], double(set.means(i, c)));
    }
  return b;
}

}  // namespace gaussians
}  // namespace v0
}  // namespace flexsplat
