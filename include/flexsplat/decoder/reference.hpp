#pragma once
// Checks the deformable-attention sampling core against golden bundles of kind "deform_core" (any seed or shape):
// every case<k> of the bundle is run forward and backward in the scalar type T and compared row by row.
#include <string>
#include <vector>

#include "flexsplat/core/reference_check.hpp"
#include "flexsplat/decoder/deform_core.hpp"
#include "flexsplat/io/safetensors.hpp"

namespace flexsplat {
inline namespace v0 {
namespace decoder {

// Case prefixes "case0.", "case1.", ... present in the bundle, in order.
inline std::vector<std::string> deform_core_cases(const safetensors::File& file) {
  std::vector<std::string> cases;
  for (int k = 0; file.contains("case" + std::to_string(k) + ".value"); ++k) cases.push_back("case" + std::to_string(k) + ".");
  require(!cases.empty(), "deform_core bundle '", file.path(), "' has no case0.value tensor");
  return cases;
}

template <class T>
void check_deform_core_bundle(const safetensors::File& file, ReferenceReport& report, double tolerance) {
  for (const std::string& c : deform_core_cases(file)) {
    const auto value = file.get<T, 4>(c + "value");
    const auto shapes = file.get<index_t, 2>(c + "spatial_shapes");
    const auto locations = file.get<T, 6>(c + "sampling_locations");
    const auto weights = file.get<T, 5>(c + "attention_weights");
    const auto d_out = file.get<T, 3>(c + "d_output");
    require(shapes.shape(1) == 2, file.path(), ": ", c, "spatial_shapes has shape ", shape_string(shapes.shape()),
            ", expected [views, 2]");
    const index_t B = value.shape(0), heads = value.shape(2), D = value.shape(3);
    const index_t Q = locations.shape(1), V = shapes.shape(0), P = locations.shape(4);
    const DeformCoreLayout L =
        make_deform_core_layout(B, Q, heads, D, P, std::span<const index_t>(shapes.data(), static_cast<std::size_t>(shapes.size())));
    const Shape<6> want_loc{B, Q, heads, V, P, 2};
    const Shape<5> want_w{B, Q, heads, V, P};
    const Shape<3> want_out{B, Q, heads * D};
    require(value.shape(1) == L.value_len(), file.path(), ": ", c, "value has ", value.shape(1),
            " positions but the spatial shapes sum to ", L.value_len());
    require(locations.shape() == want_loc, file.path(), ": ", c, "sampling_locations has shape ",
            shape_string(locations.shape()), ", expected ", shape_string(want_loc));
    require(weights.shape() == want_w, file.path(), ": ", c, "attention_weights has shape ", shape_string(weights.shape()),
            ", expected ", shape_string(want_w));
    require(d_out.shape() == want_out, file.path(), ": ", c, "d_output has shape ", shape_string(d_out.shape()),
            ", expected ", shape_string(want_out));

    Tensor<T, 3> out(want_out);
    deform_core_forward(out.data(), value.data(), locations.data(), weights.data(), L);
    Tensor<T, 4> d_value(value.shape());
    Tensor<T, 6> d_loc(locations.shape());
    Tensor<T, 5> d_w(weights.shape());
    deform_core_backward(d_value.data(), d_loc.data(), d_w.data(), d_out.data(), value.data(), locations.data(),
                         weights.data(), L);
    const Tolerance tol{ToleranceKind::relative_to_max_abs, tolerance};
    const auto cmp = [&](const std::string& name, std::span<const T> actual) {
      const auto& info = file.info(c + name);
      std::vector<double> expected(static_cast<std::size_t>(info.numel()));
      file.convert(info, expected.data());
      report.compare(c + name, actual, std::span<const double>(expected), tol);
    };
    cmp("output", out.span());
    cmp("d_value", d_value.span());
    cmp("d_sampling_locations", d_loc.span());
    cmp("d_attention_weights", d_w.span());
  }
  const auto cases = deform_core_cases(file);
  std::vector<std::string> names;
  for (const auto& t : file.tensors()) names.push_back(t.name);
  report.fail_unknown(names, [&](const std::string& name) {
    for (const std::string& c : cases)
      for (const char* input : {"value", "spatial_shapes", "sampling_locations", "attention_weights", "d_output"})
        if (name == c + input) return true;
    return false;
  }, "deform_core");
}

}  // namespace decoder
}  // namespace v0
}  // namespace flexsplat
