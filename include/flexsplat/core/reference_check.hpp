#pragma once
// Comparison of library outputs with golden tensors: per-tensor max abs error, max error relative to the
// reference tensor's max abs value, and PASS/FAIL against a tolerance.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <functional>
#include <map>
#include <span>
#include <string>
#include <vector>

#include "flexsplat/core/error.hpp"

namespace flexsplat {
inline namespace v0 {

// per_element: |actual_i - expected_i| <= value * scale_i with a scale per element (compare_scaled).
enum class ToleranceKind { absolute, relative_to_max_abs, exact, per_element };

struct Tolerance {
  ToleranceKind kind = ToleranceKind::relative_to_max_abs;
  double value = 0.0;
};

struct TensorComparison {
  std::string name;
  double max_abs_error = 0.0;
  double max_rel_error = 0.0;  // max abs error / max abs of the reference (per_element: max of error_i / scale_i)
  double reference_max_abs = 0.0;
  Tolerance tolerance;
  bool pass = false;
  std::string note;  // shape mismatch, non-finite values, ...
};

struct ReferenceReport {
  std::string file;
  std::string kind;
  std::vector<TensorComparison> rows;
  bool all_pass() const {
    return !rows.empty() && std::all_of(rows.begin(), rows.end(), [](auto& r) { return r.pass; });
  }

  // Compares element-wise; non-finite values in either side fail the row.
  template <class A, class B>
  TensorComparison& compare(const std::string& name, std::span<const A> actual, std::span<const B> expected,
                            Tolerance tol) {
    TensorComparison row;
    row.name = name;
    row.tolerance = tol;
    if (actual.size() != expected.size()) {
      row.note = concat("size ", actual.size(), " != reference size ", expected.size());
      rows.push_back(row);
      return rows.back();
    }
    bool finite = true;
    for (std::size_t i = 0; i < expected.size(); ++i) {
      const double e = static_cast<double>(expected[i]);
      const double a = static_cast<double>(actual[i]);
      if (!std::isfinite(a) || !std::isfinite(e)) {
        finite = false;
        continue;
      }
      row.reference_max_abs = std::max(row.reference_max_abs, std::abs(e));
      row.max_abs_error = std::max(row.max_abs_error, std::abs(a - e));
    }
    row.max_rel_error = row.reference_max_abs > 0 ? row.max_abs_error / row.reference_max_abs
                                                  : (row.max_abs_error > 0 ? INFINITY : 0.0);
    switch (tol.kind) {
      case ToleranceKind::absolute: row.pass = row.max_abs_error <= tol.value; break;
      case ToleranceKind::relative_to_max_abs:
        row.pass = row.max_abs_error <= tol.value * row.reference_max_abs;
        break;
      case ToleranceKind::exact: row.pass = row.max_abs_error == 0.0; break;
      case ToleranceKind::per_element: fail("reference check '", name, "': per_element tolerances need compare_scaled");
    }
    if (!finite) {
      row.pass = false;
      row.note = "non-finite values";
    }
    rows.push_back(row);
    return rows.back();
  }

  // Element-wise relative comparison: element i passes when |actual_i - expected_i| <= tol * scale[i] (e.g. scale =
  // |expected| for a relative check, or the depth of a world point's pixel). Non-finite values or scales fail the row.
  template <class A, class B>
  TensorComparison& compare_scaled(const std::string& name, std::span<const A> actual, std::span<const B> expected,
                                   std::span<const double> scale, double tol) {
    TensorComparison row;
    row.name = name;
    row.tolerance = {ToleranceKind::per_element, tol};
    if (actual.size() != expected.size() || scale.size() != expected.size()) {
      row.note = concat("size ", actual.size(), " != reference size ", expected.size(), " (scales ", scale.size(), ")");
      rows.push_back(row);
      return rows.back();
    }
    bool finite = true;
    row.pass = true;
    for (std::size_t i = 0; i < expected.size(); ++i) {
      const double e = static_cast<double>(expected[i]), a = static_cast<double>(actual[i]);
      if (!std::isfinite(a) || !std::isfinite(e) || !std::isfinite(scale[i]) || !(scale[i] > 0)) {
        finite = false;
        continue;
      }
      const double err = std::abs(a - e);
      row.reference_max_abs = std::max(row.reference_max_abs, std::abs(e));
      row.max_abs_error = std::max(row.max_abs_error, err);
      row.max_rel_error = std::max(row.max_rel_error, err / scale[i]);
      row.pass = row.pass && err <= tol * scale[i];
    }
    if (!finite) {
      row.pass = false;
      row.note = "non-finite values or non-positive scales";
    }
    rows.push_back(row);
    return rows.back();
  }

  // A failing row for every bundle tensor the checker neither read as an input nor compared: a tensor it does not
  // know is an error, not a skip.
  void fail_unknown(const std::vector<std::string>& bundle_tensors, const std::function<bool(const std::string&)>& is_input,
                    const std::string& checker) {
    for (const std::string& t : bundle_tensors) {
      if (is_input(t)) continue;
      bool compared = false;
      for (const auto& r : rows) compared = compared || r.name == t;
      if (compared) continue;
      TensorComparison row;
      row.name = t;
      row.note = concat("tensor not understood by the ", checker, " checker");
      rows.push_back(row);
    }
  }

  void print(std::FILE* out) const {
    std::fprintf(out, "%s (kind %s)\n", file.c_str(), kind.c_str());
    for (auto& r : rows) {
      const char* tk = r.tolerance.kind == ToleranceKind::absolute      ? "abs"
                       : r.tolerance.kind == ToleranceKind::exact       ? "exact"
                       : r.tolerance.kind == ToleranceKind::per_element ? "elem"
                                                                        : "rel";
      std::fprintf(out, "  %-48s max_abs %.3e  max_rel %.3e  tol %s %.1e  %s%s%s\n", r.name.c_str(), r.max_abs_error,
                   r.max_rel_error, tk, r.tolerance.value, r.pass ? "PASS" : "FAIL", r.note.empty() ? "" : "  ",
                   r.note.c_str());
    }
  }
};

}  // namespace v0
}  // namespace flexsplat
