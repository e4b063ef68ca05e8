#pragma once
// Checks LPIPS against golden bundles of kind "lpips" (any seed, trunk width, case count, B, H, W): weights by the
// lpips package's state_dict names; per case<k>: in0, in1 [B, 3, H, W] in [-1, 1]; lpips [B], per_layer [B, 5],
// grad_in0/grad_in1 = d(sum_b lpips)/d(in), lpips_from_unit = lpips((in0+1)/2, (in1+1)/2) with [0, 1] inputs.
// Tolerances (shared/reference/README.md): float32 lpips, per_layer and lpips_from_unit within 1e-5 relative per
// element; float64 within 1e-7, and float64 gradients within 1e-5 of the tensor's max abs value (where the README says
// the reference code itself lands in float32).
#include <algorithm>
#include <cmath>
#include <limits>
#include <span>
#include <string>
#include <type_traits>
#include <vector>

#include "flexsplat/core/reference_check.hpp"
#include "flexsplat/io/safetensors.hpp"
#include "flexsplat/loss/lpips.hpp"

namespace flexsplat {
inline namespace v0 {
namespace loss {

inline constexpr double lpips_value_tolerance = 1e-5;     // float32, relative, per element
inline constexpr double lpips_value_tolerance64 = 1e-7;   // float64, relative, per element
inline constexpr double lpips_gradient_tolerance = 1e-5;  // float64, of the tensor's max abs value

inline std::vector<std::string> lpips_cases(const safetensors::File& file) {
  std::vector<std::string> cases;
  for (int k = 0; file.contains("case" + std::to_string(k) + ".in0"); ++k) cases.push_back("case" + std::to_string(k) + ".");
  require(!cases.empty(), "lpips bundle '", file.path(), "' has no case0.in0 tensor");
  return cases;
}

// Library outputs for one case in the scalar type T.
template <class T>
struct LpipsCaseResult {
  std::vector<T> lpips, per_layer, grad_in0, grad_in1, lpips_from_unit;
};

template <class T>
LpipsCaseResult<T> run_lpips_case(const safetensors::File& file, const std::string& c, const LpipsWeights<T>& weights,
                                  LpipsCache<T>& cache, bool gradients) {
  const auto in0 = file.get<T, 4>(c + "in0");
  const auto in1 = file.get<T, 4>(c + "in1");
  require(in0.shape() == in1.shape() && in0.shape(1) == 3, file.path(), ": ", c, "in0 ", shape_string(in0.shape()),
          " and in1 ", shape_string(in1.shape()), " must both be [B, 3, H, W]");
  const index_t B = in0.shape(0), H = in0.shape(2), W = in0.shape(3);
  LpipsCaseResult<T> r;
  r.lpips.resize(static_cast<std::size_t>(B));
  r.per_layer.resize(static_cast<std::size_t>(B * lpips_layers));
  r.grad_in0.resize(static_cast<std::size_t>(in0.size()));
  r.grad_in1.resize(static_cast<std::size_t>(in1.size()));
  r.lpips_from_unit.resize(static_cast<std::size_t>(B));
  const std::vector<T> ones(static_cast<std::size_t>(B), T(1));
  const T* p = weights.params.data();
  lpips_forward(r.lpips.data(), r.per_layer.data(), in0.data(), in1.data(), B, H, W, p, weights.layout, cache);
  if (gradients)
    lpips_backward(r.grad_in0.data(), r.grad_in1.data(), ones.data(), static_cast<const T*>(nullptr), p,
                   weights.layout, cache);
  // The same pair as [0, 1] images through the package's normalize=True path.
  std::vector<T> u0(in0.data(), in0.data() + in0.size()), u1(in1.data(), in1.data() + in1.size());
  for (auto& v : u0) v = (v + T(1)) / T(2);
  for (auto& v : u1) v = (v + T(1)) / T(2);
  lpips_forward(r.lpips_from_unit.data(), static_cast<T*>(nullptr), u0.data(), u1.data(), B, H, W, p, weights.layout,
                cache, true);
  return r;
}

// Every case runs in float64 (all rows) and in float32 (the values; rows prefixed "float32 "). Gradients are compared
// in float64 only: a ReLU pre-activation closer to zero than float32's rounding of the trunk (lpips_2024 case0 has
// one of 2.1e-7 at relu4_2, where float32 activations carry ~1.6e-5) takes either side in float32, which reroutes part
// of that image's gradient; the bundle's draw avoids max-pool ties but not these.
// `only` restricts the run to those case prefixes ("case1."); empty runs every case.
inline void check_lpips_bundle(const safetensors::File& file, ReferenceReport& report,
                               const std::vector<std::string>& only = {}) {
  if (file.has_metadata("net"))
    require(file.metadata("net") == "vgg", "lpips bundle '", file.path(), "': net '", file.metadata("net"),
            "' is not supported (only the VGG16 trunk)");
  if (file.has_metadata("version"))
    require(file.metadata("version") == "0.1", "lpips bundle '", file.path(), "': version '",
            file.metadata("version"), "' is not supported (only 0.1)");
  const LpipsWeights<double> weights64 = lpips_load_weights<double>(file);
  LpipsWeights<float> weights32(weights64.layout.config);
  std::transform(weights64.params.begin(), weights64.params.end(), weights32.params.begin(),
                 [](double v) { return static_cast<float>(v); });  // as lpips_load<float> rounds them
  LpipsCache<double> cache64;
  LpipsCache<float> cache32;
  const std::vector<std::string> cases = lpips_cases(file);
  for (const std::string& c : cases) {
    if (!only.empty() && std::find(only.begin(), only.end(), c) == only.end()) continue;
    const auto& in_info = file.info(c + "in0");
    require(in_info.shape.size() == 4, file.path(), ": ", c, "in0 has shape ", safetensors::shape_string(in_info.shape),
            ", expected [B, 3, H, W]");
    const index_t B = in_info.shape[0];
    const std::vector<index_t> image_shape = in_info.shape;
    const auto expected = [&](const std::string& name, const std::vector<index_t>& shape) {
      require(file.contains(c + name), file.path(), ": ", c, name, " is missing");
      const auto& info = file.info(c + name);
      require(info.shape == shape, file.path(), ": ", c, name, " has shape ", safetensors::shape_string(info.shape),
              ", expected ", safetensors::shape_string(shape));
      std::vector<double> v(static_cast<std::size_t>(info.numel()));
      file.convert(info, v.data());
      return v;
    };
    const auto value_rows = [&](const std::string& tag, const auto& r, double tolerance) {
      using V = typename std::decay_t<decltype(r.lpips)>::value_type;
      const auto row = [&](const std::string& name, const std::vector<V>& actual, const std::vector<index_t>& shape) {
        const auto e = expected(name, shape);
        std::vector<double> scale(e.size());
        for (std::size_t i = 0; i < e.size(); ++i)
          scale[i] = e[i] != 0.0 ? std::abs(e[i]) : std::numeric_limits<double>::min();  // 0 must be met exactly
        report.compare_scaled(tag + c + name, std::span<const V>(actual), std::span<const double>(e),
                              std::span<const double>(scale), tolerance);
      };
      row("lpips", r.lpips, {B});
      row("per_layer", r.per_layer, {B, lpips_layers});
      row("lpips_from_unit", r.lpips_from_unit, {B});
    };
    const auto r64 = run_lpips_case(file, c, weights64, cache64, true);
    value_rows("", r64, lpips_value_tolerance64);
    for (const char* name : {"grad_in0", "grad_in1"}) {
      const auto e = expected(name, image_shape);
      const auto& actual = std::string(name) == "grad_in0" ? r64.grad_in0 : r64.grad_in1;
      report.compare(c + name, std::span<const double>(actual), std::span<const double>(e),
                     Tolerance{ToleranceKind::relative_to_max_abs, lpips_gradient_tolerance});
    }
    value_rows("float32 ", run_lpips_case(file, c, weights32, cache32, false), lpips_value_tolerance);
  }
  if (!only.empty()) return;  // the other cases' tensors were skipped on purpose
  std::vector<std::string> names;
  for (const auto& t : file.tensors()) names.push_back(t.name);
  report.fail_unknown(names, [&](const std::string& name) {
    for (const auto& e : weights64.layout.entries)
      if (name == e.name || name == lpips_alias(e.name)) return true;
    for (const std::string& c : cases)
      if (name == c + "in0" || name == c + "in1") return true;
    return false;
  }, "lpips");
}

}  // namespace loss
}  // namespace v0
}  // namespace flexsplat
