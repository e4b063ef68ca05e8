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

enum class ToleranceKind { absolute, relative_to_max_abs, exact };

struct Tolerance {
  ToleranceKind kind = ToleranceKind::relative_to_max_abs;
  double value = 0.0;
};

struct TensorComparison {
  std::string name;
  double max_abs_error = 0.0;
  double max_rel_error = 0.0;  // max abs error / max abs of the reference
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
    }
    if (!finite) {
      row.pass = false;
      row.note = "non-finite values";
    }
    rows.push_back(row);
    return rows.back();
  }

  void print(std::FILE* out) const {
    std::fprintf(out, "%s (kind %s)\n", file.c_str(), kind.c_str());
    for (auto& r : rows) {
      const char* tk = r.tolerance.kind == ToleranceKind::absolute ? "abs" : r.tolerance.kind == ToleranceKind::exact ? "exact" : "rel";
      std::fprintf(out, "  %-48s max_abs %.3e  max_rel %.3e  tol %s %.1e  %s%s%s\n", r.name.c_str(), r.max_abs_error,
                   r.max_rel_error, tk, r.tolerance.value, r.pass ? "PASS" : "FAIL", r.note.empty() ? "" : "  ",
                   r.note.c_str());
    }
  }
};

}  // namespace v0
}  // namespace flexsplat
