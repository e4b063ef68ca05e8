#pragma once
// Counter-based random numbers for the data generator: every object, view and batch draws from its own stream
// derived from (seed, indices), so results never depend on the thread count or on the order of generation.
#include <cmath>
#include <cstdint>
#include <numbers>

namespace flexsplat {
inline namespace v0 {
namespace data {

// SplitMix64 finaliser: a bijective 64-bit mix used both as the stream step and to derive child seeds.
inline constexpr std::uint64_t mix64(std::uint64_t z) noexcept {
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ULL;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebULL;
  return z ^ (z >> 31);
}

// Seed of child stream `index` under `seed` (e.g. object i of a dataset, view j of an object).
inline constexpr std::uint64_t child_seed(std::uint64_t seed, std::uint64_t index) noexcept {
  return mix64(seed ^ mix64(index + 0x9e3779b97f4a7c15ULL));
}

// Purpose tags keep independent streams of one object apart (shape vs cameras vs batch sampling).
enum class Stream : std::uint64_t { shape = 1, light = 2, cameras = 3, batch = 4, augment = 5, camera_noise = 6 };

inline constexpr std::uint64_t stream_seed(std::uint64_t seed, Stream stream) noexcept {
  return child_seed(seed, 0x5eed0000ULL + static_cast<std::uint64_t>(stream));
}

// SplitMix64 generator; its own uniform/normal so no standard-library distribution (implementation-defined) is used.
class Rng {
public:
  explicit Rng(std::uint64_t seed) noexcept : state_(seed) {}
  std::uint64_t next() noexcept {
    state_ += 0x9e3779b97f4a7c15ULL;
    return mix64(state_);
  }
  // Uniform in [0, 1) with 53 random bits.
  double uniform() noexcept { return static_cast<double>(next() >> 11) * 0x1.0p-53; }
  double uniform(double lo, double hi) noexcept { return lo + (hi - lo) * uniform(); }
  // Uniform integer in [lo, hi] (modulo bias below 2^-50 for the small ranges used here).
  int integer(int lo, int hi) noexcept {
    const auto span = static_cast<std::uint64_t>(static_cast<std::int64_t>(hi) - lo + 1);
    return lo + static_cast<int>(next() % span);
  }
  // Standard normal by Box-Muller (one value per call).
  double normal() noexcept {
    const double u1 = 1.0 - uniform(), u2 = uniform();
    return std::sqrt(-2.0 * std::log(u1)) * std::cos(2.0 * std::numbers::pi * u2);
  }

private:
  std::uint64_t state_;
};

}  // namespace data
}  // namespace v0
}  // namespace flexsplat
