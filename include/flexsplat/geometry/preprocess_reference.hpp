#pragma once
// Checker for reference bundles of kind "preprocess": VGGT's load_and_preprocess_images run by the reference on the
// PNG files listed in __metadata__.files (paths relative to the bundle's folder). Tensors `<mode>.single<i>` hold
// the function applied to [files[i]] alone, `<mode>.all` applied to every file in order; values are the float output
// times 255 stored as U8. Tolerance: every value within 1 (of 255) and mean absolute error under 0.1, per tensor.
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/reference_check.hpp"
#include "flexsplat/geometry/preprocess.hpp"
#include "flexsplat/io/safetensors.hpp"

namespace flexsplat {
inline namespace v0 {

inline constexpr double preprocess_max_abs_tolerance = 1.0;   // units of 1/255
inline constexpr double preprocess_mean_abs_tolerance = 0.1;  // units of 1/255

// Compares our [S, 3, H, W] float output (times 255, rounded as the bundle stored it) with a U8 reference tensor.
inline void compare_preprocess_tensor(const std::string& name, const Tensor<float, 4>& actual,
                                      const safetensors::File& bundle, ReferenceReport& report) {
  const safetensors::TensorInfo& info = bundle.info(name);
  const Tolerance tol{ToleranceKind::absolute, preprocess_max_abs_tolerance};
  std::vector<index_t> actual_shape(actual.shape().begin(), actual.shape().end());
  if (info.shape != actual_shape) {
    TensorComparison row;
    row.name = name;
    row.tolerance = tol;
    row.note = concat("shape ", safetensors::shape_string(actual_shape), " != reference shape ",
                      safetensors::shape_string(info.shape));
    report.rows.push_back(row);
    return;
  }
  std::vector<double> expected(static_cast<std::size_t>(info.numel()));
  bundle.convert(info, expected.data());
  std::vector<double> ours(expected.size());
  double sum_abs = 0.0;
  for (std::size_t i = 0; i < ours.size(); ++i) {
    ours[i] = std::round(static_cast<double>(actual.data()[i]) * 255.0);
    sum_abs += std::abs(ours[i] - expected[i]);
  }
  TensorComparison& row = report.compare(name, std::span<const double>(ours), std::span<const double>(expected), tol);
  const double mean_abs = expected.empty() ? 0.0 : sum_abs / static_cast<double>(expected.size());
  const bool mean_ok = mean_abs < preprocess_mean_abs_tolerance;
  row.pass = row.pass && mean_ok;
  row.note += concat(row.note.empty() ? "" : "; ", "mean_abs ", mean_abs, " (tol < ", preprocess_mean_abs_tolerance,
                     mean_ok ? ")" : ") FAIL");
}

inline void check_preprocess_reference(const safetensors::File& bundle, ReferenceReport& report) {
  const nlohmann::json files_json = [&] {
    try {
      return nlohmann::json::parse(bundle.metadata("files"));
    } catch (const nlohmann::json::exception& e) {
      bundle.error("__metadata__.files is not a JSON list of file names: ", e.what());
    }
  }();
  if (!files_json.is_array() || files_json.empty())
    bundle.error("__metadata__.files must be a non-empty JSON list of file names");
  const std::filesystem::path folder = std::filesystem::path(bundle.path()).parent_path();
  std::vector<std::string> paths;
  for (const auto& f : files_json) {
    if (!f.is_string()) bundle.error("__metadata__.files holds a non-string entry ", f.dump());
    paths.push_back((folder / f.get<std::string>()).string());
  }
  std::vector<InterleavedImage> images;
  for (const auto& p : paths) images.push_back(decode_image_like_pillow(p));

  bool any = false;
  for (const VggtPreprocessMode mode : {VggtPreprocessMode::crop, VggtPreprocessMode::pad}) {
    const std::string prefix = vggt_preprocess_mode_name(mode);
    for (std::size_t i = 0; i < images.size(); ++i) {
      const std::string name = concat(prefix, ".single", i);
      if (!bundle.contains(name)) continue;
      any = true;
      const std::vector<InterleavedImage> one{images[i]};
      compare_preprocess_tensor(name, vggt_preprocess_images(one, mode), bundle, report);
    }
    const std::string all = prefix + ".all";
    if (bundle.contains(all)) {
      any = true;
      compare_preprocess_tensor(all, vggt_preprocess_images(images, mode), bundle, report);
    }
  }
  std::vector<std::string> names;
  for (const auto& t : bundle.tensors()) names.push_back(t.name);
  report.fail_unknown(names, [](const std::string&) { return false; }, "preprocess (<crop|pad>.single<i>, <crop|pad>.all)");
  if (!any) bundle.error("no <crop|pad>.single<i> / <crop|pad>.all tensors to check");
}

}  // namespace v0
}  // namespace flexsplat
