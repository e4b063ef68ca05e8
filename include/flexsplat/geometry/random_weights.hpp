#pragma once
// Deterministic random parameters for a list of tensor specs (benchmarks and tests run the real architecture
// without downloading weights). Values follow the usual initialisations closely enough to keep activations finite:
// LayerNorm weights 1, biases 0, LayerScale gammas `layer_scale`, matrices uniform with variance 1/fan_in.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <string>
#include <vector>

#include "flexsplat/core/parallel.hpp"
#include "flexsplat/io/param_source.hpp"

namespace flexsplat {
inline namespace v0 {
namespace geometry {

namespace detail {
inline bool ends_with(const std::string& s, const std::string& tail) {
  return s.size() >= tail.size() && s.compare(s.size() - tail.size(), tail.size(), tail) == 0;
}
// splitmix64: a counter-based generator, so chunks fill in parallel with a result independent of the thread count.
inline std::uint64_t splitmix64(std::uint64_t x) {
  x += 0x9e3779b97f4a7c15ull;
  x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ull;
  x = (x ^ (x >> 27)) * 0x94d049bb133111ebull;
  return x ^ (x >> 31);
}
}  // namespace detail

// Constant-initialised tensors (norm weights, biases, LayerScale gammas) draw no random stream.
inline bool draws_random_values(const io::TensorSpec& spec) {
  const bool is_norm = spec.name.find("norm") != std::string::npos;
  return !(is_norm && detail::ends_with(spec.name, ".weight")) && !detail::ends_with(spec.name, ".bias") &&
         !detail::ends_with(spec.name, ".gamma");
}

// Fills `values` (spec's element count) with spec's deterministic initial values; `stream` seeds a random tensor.
template <class T>
void random_parameter_values(T* values, const io::TensorSpec& spec, std::uint64_t stream, double layer_scale = 0.01) {
  index_t n = 1;
  for (index_t e : spec.shape) n *= e;
  if (!draws_random_values(spec)) {
    const bool gamma = detail::ends_with(spec.name, ".gamma"), bias = detail::ends_with(spec.name, ".bias");
    std::fill(values, values + n, gamma ? static_cast<T>(layer_scale) : bias ? T(0) : T(1));
  } else {
    const index_t fan_in = spec.shape.size() >= 2 ? n / spec.shape[0] : spec.shape.back();
    const double bound = std::sqrt(3.0 / static_cast<double>(fan_in > 0 ? fan_in : 1));
    const std::uint64_t base = detail::splitmix64(stream);
    parallel_for(n, [&](index_t i0, index_t i1, int) {
      for (index_t i = i0; i < i1; ++i) {
        const double u = static_cast<double>(detail::splitmix64(base + static_cast<std::uint64_t>(i)) >> 11) * 0x1.0p-53;
        values[i] = static_cast<T>((2.0 * u - 1.0) * bound);
      }
    });
  }
}

template <class T>
void add_random_parameters(io::ParamSource<T>& src, const std::vector<io::TensorSpec>& specs, std::uint64_t seed,
                           double layer_scale = 0.01) {
  std::uint64_t stream = seed;
  for (const auto& spec : specs) {
    index_t n = 1;
    for (index_t e : spec.shape) n *= e;
    std::vector<T> values(static_cast<std::size_t>(n));
    random_parameter_values(values.data(), spec, draws_random_values(spec) ? stream++ : stream, layer_scale);
    src.add(spec.name, spec.shape, std::move(values));
  }
}

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
