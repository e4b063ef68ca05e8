#pragma once
// Shared by the geometry head tests: the golden VGGT bundle, its config, and per-tensor comparisons.
#include <catch2/catch.hpp>

#include <cstdio>
#include <fstream>
#include <map>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "flexsplat/core/reference_check.hpp"
#include "flexsplat/io/safetensors.hpp"

namespace heads_test {

inline std::string bundle_path() { return std::string(FLEXSPLAT_SHARED_DIR) + "/reference/vggt_tiny_1234.safetensors"; }

inline const flexsplat::safetensors::File& bundle() {
  static const flexsplat::safetensors::File file = flexsplat::safetensors::File::open(bundle_path());
  return file;
}

inline nlohmann::json bundle_config() { return nlohmann::json::parse(bundle().metadata("config")); }

using ShapeMap = std::map<std::string, std::vector<flexsplat::index_t>>;

// Name -> shape of every VGGT-1B tensor whose name starts with prefix, from the shared layout file.
inline ShapeMap vggt1b_layout_shapes(const std::string& prefix) {
  std::ifstream f(std::string(FLEXSPLAT_SHARED_DIR) + "/reference/vggt1b_state_dict_layout.json");
  REQUIRE(f.good());
  const auto layout = nlohmann::json::parse(f);
  ShapeMap expected;
  for (auto& t : layout.at("tensors")) {
    const std::string name = t.at("name");
    if (name.rfind(prefix, 0) == 0) expected[name] = t.at("shape").get<std::vector<flexsplat::index_t>>();
  }
  return expected;
}

// Name -> shape of a spec list; duplicates would shrink the map, so callers compare sizes too.
template <class Specs>
ShapeMap spec_shapes(const Specs& specs) {
  ShapeMap ours;
  for (auto& s : specs) ours[s.name] = s.shape;
  return ours;
}

// Cases as [S, H, W] from the bundle metadata.
inline std::vector<std::array<long, 3>> bundle_cases() {
  std::vector<std::array<long, 3>> out;
  for (auto& c : nlohmann::json::parse(bundle().metadata("cases"))) out.push_back({c[0], c[1], c[2]});
  return out;
}

template <class T>
std::vector<T> read(const std::string& name) {
  const auto& info = bundle().info(name);
  std::vector<T> v(static_cast<std::size_t>(info.numel()));
  bundle().convert(info, v.data());
  return v;
}

// Compares with the README's rule (max abs error <= tol * max abs of the reference), prints the row, checks it.
template <class T>
void check_close(const std::string& name, const std::vector<T>& actual, const std::vector<float>& expected,
                 double tol = 1e-4) {
  flexsplat::ReferenceReport report;
  auto& row = report.compare(name, std::span<const T>(actual), std::span<const float>(expected),
                             flexsplat::Tolerance{flexsplat::ToleranceKind::relative_to_max_abs, tol});
  std::printf("  %-40s max_abs %.3e  max_rel %.3e  %s\n", name.c_str(), row.max_abs_error, row.max_rel_error,
              row.pass ? "PASS" : "FAIL");
  INFO(name << ": max abs error " << row.max_abs_error << ", reference max abs " << row.reference_max_abs << " "
            << row.note);
  CHECK(row.pass);
}

// Element-wise relative error max |a - e| / |e| over elements with |e| >= floor.
template <class T>
double max_elementwise_rel(const std::vector<T>& actual, const std::vector<float>& expected, double floor) {
  double worst = 0.0;
  for (std::size_t i = 0; i < expected.size(); ++i) {
    const double e = expected[i];
    if (std::abs(e) < floor) continue;
    worst = std::max(worst, std::abs(static_cast<double>(actual[i]) - e) / std::abs(e));
  }
  return worst;
}

}  // namespace heads_test
