#pragma once
// Generic float64 gradient checker for forward/backward pairs: central differences of <cotangent, forward(x)>,
// random cotangent, gradient buffers seeded with junk to check that backward accumulates (+=), and index
// subsampling for large tensors. The seed is printed and can be set with FLEXSPLAT_GRADCHECK_SEED.
#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <functional>
#include <random>
#include <span>
#include <string>
#include <vector>

#include "flexsplat/core/error.hpp"

namespace flexsplat {
inline namespace v0 {
namespace testing {

struct GradParam {
  std::string name;
  std::span<double> value;  // perturbed in place, restored afterwards
  std::span<double> grad;   // backward adds into this
};

struct GradCheckOptions {
  double step = 1e-6;
  double abs_tol = 1e-7;
  double rel_tol = 1e-5;
  std::size_t max_checks_per_param = 48;  // random subset for large tensors
};

struct GradMismatch {
  std::string param;
  std::size_t index;
  double analytic, numeric;
};

struct GradCheckResult {
  std::uint64_t seed = 0;
  std::size_t checked = 0;
  double max_abs_error = 0.0;
  std::vector<GradMismatch> mismatches;
  bool ok() const { return checked > 0 && mismatches.empty(); }
  std::string summary() const {
    std::string s = concat("gradcheck seed ", seed, ": ", checked, " entries, max abs error ", max_abs_error, ", ",
                           mismatches.size(), " mismatches");
    for (std::size_t i = 0; i < std::min<std::size_t>(mismatches.size(), 8); ++i)
      s += concat("\n  ", mismatches[i].param, "[", mismatches[i].index, "] analytic ", mismatches[i].analytic,
                  " numeric ", mismatches[i].numeric);
    return s;
  }
};

inline std::uint64_t gradcheck_seed(std::uint64_t fallback = 20261121) {
  if (const char* env = std::getenv("FLEXSPLAT_GRADCHECK_SEED"); env && *env) {
    char* end = nullptr;
    errno = 0;
    const unsigned long long seed = std::strtoull(env, &end, 10);
    require(errno == 0 && end && *end == '\0' && env[0] != '-', "FLEXSPLAT_GRADCHECK_SEED='", env,
            "' is not an unsigned integer");
    return seed;
  }
  return fallback;
}

// forward(out): writes every output into `out` (size out_size).  backward(d_out): adds gradients into the params' grads.
inline GradCheckResult check_gradients(std::vector<GradParam> params, std::size_t out_size,
                                       const std::function<void(std::span<double>)>& forward,
                                       const std::function<void(std::span<const double>)>& backward,
                                       GradCheckOptions options = {}, std::uint64_t seed = gradcheck_seed()) {
  GradCheckResult result;
  result.seed = seed;
  std::fprintf(stderr, "[gradcheck] seed %llu (set FLEXSPLAT_GRADCHECK_SEED to reproduce)\n",
               static_cast<unsigned long long>(seed));
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> normal(0.0, 1.0);

  std::vector<double> cotangent(out_size);
  for (auto& c : cotangent) c = normal(rng);
  std::vector<std::vector<double>> junk(params.size());
  for (std::size_t p = 0; p < params.size(); ++p) {
    require(params[p].value.size() == params[p].grad.size(), "gradcheck: parameter '", params[p].name,
            "' has ", params[p].value.size(), " values but ", params[p].grad.size(), " gradient slots");
    junk[p].resize(params[p].grad.size());
    for (std::size_t i = 0; i < junk[p].size(); ++i) params[p].grad[i] = junk[p][i] = normal(rng);
  }

  std::vector<double> out(out_size);
  forward(out);
  backward(cotangent);

  auto objective = [&] {
    forward(out);
    double s = 0.0;
    for (std::size_t i = 0; i < out_size; ++i) s += out[i] * cotangent[i];
    return s;
  };

  for (std::size_t p = 0; p < params.size(); ++p) {
    auto& param = params[p];
    std::vector<std::size_t> indices(param.value.size());
    for (std::size_t i = 0; i < indices.size(); ++i) indices[i] = i;
    if (indices.size() > options.max_checks_per_param) {
      std::shuffle(indices.begin(), indices.end(), rng);
      indices.resize(options.max_checks_per_param);
      std::sort(indices.begin(), indices.end());
    }
    for (std::size_t i : indices) {
      const double saved = param.value[i];
      const double h = options.step * std::max(1.0, std::abs(saved));
      param.value[i] = saved + h;
      const double up = objective();
      param.value[i] = saved - h;
      const double down = objective();
      param.value[i] = saved;
      const double numeric = (up - down) / (2.0 * h);
      const double analytic = param.grad[i] - junk[p][i];
      const double err = std::abs(analytic - numeric);
      result.max_abs_error = std::max(result.max_abs_error, err);
      ++result.checked;
      if (!(err <= options.abs_tol + options.rel_tol * std::max(std::abs(analytic), std::abs(numeric))))
        result.mismatches.push_back({param.name, i, analytic, numeric});
    }
  }
  forward(out);
  return result;
}

}  // namespace testing
}  // namespace v0
}  // namespace flexsplat
