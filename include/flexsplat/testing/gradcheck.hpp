#pragma once
// Generic float64 gradient checker for forward/backward pairs: central differences of <cotangent, forward(x)>,
// random cotangent, gradient buffers seeded with junk to check that backward accumulates (+=), index subsampling per
// tensor for large tensors (always including the entry of largest analytic gradient), and a floor: every tensor must
// have a checked gradient large enough that a backward returning zero for it fails, unless it is declared
// structurally zero (with the reason), which is then checked. The seed is printed and can be set with
// FLEXSPLAT_GRADCHECK_SEED.
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
#include <utility>
#include <vector>

#include "flexsplat/core/error.hpp"

namespace flexsplat {
inline namespace v0 {
namespace testing {

struct GradParam {
  std::string name;
  std::span<double> value;  // perturbed in place, restored afterwards
  std::span<double> grad;   // backward adds into this
  std::string zero_reason = {};  // non-empty: the gradient is structurally zero, for this reason (checked)
};

struct GradCheckOptions {
  double step = 1e-6;
  double abs_tol = 1e-7;
  double rel_tol = 1e-5;
  std::size_t max_checks_per_param = 48;  // random subset for large tensors
  // Each tensor's largest checked |numeric| must exceed floor * abs_tol, so that a zero backward would fail on it.
  double floor = 10.0;
  bool unit_cotangent = false;  // cotangent of ones: backward may call a function that adds d(sum of outputs)/dx
};

struct GradMismatch {
  std::string param;
  std::size_t index;
  double analytic, numeric;
};

// What was checked in one tensor: entries, the largest |numeric| among them, and whether it cleared the floor.
struct GradTensorReport {
  std::string param;
  std::size_t checked = 0;
  double max_numeric = 0.0;
  std::string zero_reason;  // declared structurally zero
  bool below_floor = false;  // not declared zero, yet no checked gradient would catch a zero backward
};

struct GradCheckResult {
  std::uint64_t seed = 0;
  std::size_t checked = 0;
  double max_abs_error = 0.0;
  double floor = 0.0;  // floor * abs_tol of the options
  std::vector<GradMismatch> mismatches;
  std::vector<GradTensorReport> tensors;
  std::size_t below_floor() const {
    std::size_t n = 0;
    for (const auto& t : tensors) n += t.below_floor ? 1 : 0;
    return n;
  }
  bool ok() const { return checked > 0 && mismatches.empty() && below_floor() == 0; }
  std::string summary() const {
    std::string s = concat("gradcheck seed ", seed, ": ", checked, " entries in ", tensors.size(),
                           " tensors, max abs error ", max_abs_error, ", ", mismatches.size(), " mismatches, ",
                           below_floor(), " tensors below the floor ", floor);
    for (std::size_t i = 0; i < std::min<std::size_t>(mismatches.size(), 8); ++i)
      s += concat("\n  ", mismatches[i].param, "[", mismatches[i].index, "] analytic ", mismatches[i].analytic,
                  " numeric ", mismatches[i].numeric);
    for (const auto& t : tensors)
      s += concat("\n  ", t.param, ": ", t.checked, " entries, max |numeric| ", t.max_numeric,
                  t.below_floor ? " BELOW THE FLOOR (a zero backward would pass)" : "",
                  t.zero_reason.empty() ? "" : " structurally zero: ", t.zero_reason);
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

// One GradParam per tensor of a flat block (names and sizes in block order, covering it exactly), so that each tensor
// is sampled and reported on its own.
inline std::vector<GradParam> split_flat(std::span<double> value, std::span<double> grad,
                                         const std::vector<std::pair<std::string, std::size_t>>& tensors,
                                         const std::string& prefix = {}) {
  require(value.size() == grad.size(), "gradcheck: flat block '", prefix, "' has ", value.size(), " values but ",
          grad.size(), " gradient slots");
  std::vector<GradParam> out;
  std::size_t at = 0;
  for (const auto& [name, size] : tensors) {
    require(at + size <= value.size(), "gradcheck: tensor '", prefix, name, "' ends at ", at + size,
            ", past the flat block's ", value.size(), " values");
    out.push_back({prefix + name, value.subspan(at, size), grad.subspan(at, size)});
    at += size;
  }
  require(at == value.size(), "gradcheck: the tensors of flat block '", prefix, "' cover ", at, " of its ",
          value.size(), " values");
  return out;
}

// forward(out): writes every output into `out` (size out_size). backward(d_out): adds gradients into the params' grads.
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

  result.floor = options.floor * options.abs_tol;
  std::vector<double> cotangent(out_size, 1.0);
  if (!options.unit_cotangent)
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
    GradTensorReport report{param.name, 0, 0.0, param.zero_reason, false};
    const auto analytic_at = [&](std::size_t i) { return param.grad[i] - junk[p][i]; };
    std::vector<std::size_t> indices(param.value.size());
    for (std::size_t i = 0; i < indices.size(); ++i) indices[i] = i;
    if (indices.size() > options.max_checks_per_param) {
      // The largest analytic entry first: a correct backward then clears the floor wherever the tensor has a gradient.
      std::size_t top = 0;
      for (std::size_t i = 1; i < indices.size(); ++i)
        if (std::abs(analytic_at(i)) > std::abs(analytic_at(top))) top = i;
      std::swap(indices[0], indices[top]);
      std::shuffle(indices.begin() + 1, indices.end(), rng);
      indices.resize(options.max_checks_per_param);
      std::sort(indices.begin(), indices.end());
    }
    const bool declared_zero = !param.zero_reason.empty();
    // A declared zero gradient is zero everywhere, not only where it is sampled (the first nonzero entry is named).
    for (std::size_t i = 0; declared_zero && i < param.value.size(); ++i)
      if (!(std::abs(analytic_at(i)) <= options.abs_tol)) {
        result.mismatches.push_back({param.name, i, analytic_at(i), 0.0});
        break;
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
      const double analytic = analytic_at(i);
      const double err = std::abs(analytic - numeric);
      result.max_abs_error = std::max(result.max_abs_error, err);
      ++result.checked;
      ++report.checked;
      report.max_numeric = std::max(report.max_numeric, std::abs(numeric));
      if (!(err <= options.abs_tol + options.rel_tol * std::max(std::abs(analytic), std::abs(numeric))) ||
          (declared_zero && !(std::abs(numeric) <= options.abs_tol)))
        result.mismatches.push_back({param.name, i, analytic, numeric});
    }
    report.below_floor = !declared_zero && !(report.max_numeric > result.floor);
    result.tensors.push_back(std::move(report));
  }
  for (const auto& t : result.tensors)
    std::fprintf(stderr, "[gradcheck]   %s: %zu entries, max |numeric| %.3g%s%s\n", t.param.c_str(), t.checked,
                 t.max_numeric, t.below_floor ? " BELOW THE FLOOR" : "", t.zero_reason.empty() ? "" : " (zero by design)");
  std::fprintf(stderr, "[gradcheck] %zu entries in %zu tensors, %zu below the floor %g\n", result.checked,
               result.tensors.size(), result.below_floor(), result.floor);
  forward(out);
  return result;
}

}  // namespace testing
}  // namespace v0
}  // namespace flexsplat
