#pragma once
// Shared by the head backward tests: one flat float64 parameter block for a list of specs (weights bind into it, so
// a gradient lives at the same offset of a flat gradient block), with a GradParam per tensor for the checker.
#include <map>
#include <random>
#include <span>
#include <string>
#include <vector>

#include "flexsplat/io/param_source.hpp"
#include "flexsplat/testing/gradcheck.hpp"

namespace heads_backward_test {

struct FlatParams {
  std::vector<flexsplat::io::TensorSpec> specs;
  std::map<std::string, std::size_t> index;  // name -> position in specs
  std::vector<std::size_t> offsets;
  std::vector<double> values, grads;

  FlatParams(std::vector<flexsplat::io::TensorSpec> s, unsigned seed) : specs(std::move(s)) {
    std::mt19937 rng(seed);
    std::normal_distribution<double> normal;
    std::size_t at = 0;
    for (std::size_t i = 0; i < specs.size(); ++i) {
      index[specs[i].name] = i;
      offsets.push_back(at);
      at += count(i);
    }
    values.resize(at);
    grads.assign(at, 0.0);
    for (std::size_t i = 0; i < specs.size(); ++i) {
      const auto& shape = specs[i].shape;
      const std::size_t n = count(i);
      const bool is_norm_weight = specs[i].name.find("norm") != std::string::npos &&
                                  specs[i].name.ends_with(".weight") && shape.size() == 1;
      const double scale = shape.size() >= 2 ? 1.0 / std::sqrt(static_cast<double>(n / shape[0])) : 0.3;
      for (std::size_t j = 0; j < n; ++j) values[offsets[i] + j] = (is_norm_weight ? 1.0 : 0.0) + scale * normal(rng);
    }
  }
  std::size_t count(std::size_t i) const {
    std::size_t n = 1;
    for (auto e : specs[i].shape) n *= static_cast<std::size_t>(e);
    return n;
  }
  // get(name, shape) for the bind functions: the tensor's place in the flat block (shape checked).
  const double* get(const std::string& name, const std::vector<flexsplat::index_t>& shape) const {
    const auto it = index.find(name);
    flexsplat::require(it != index.end(), "test parameters: no '", name, "'");
    flexsplat::require(specs[it->second].shape == shape, "test parameters: '", name, "' shape mismatch");
    return values.data() + offsets[it->second];
  }
  std::vector<flexsplat::testing::GradParam> grad_params() {
    std::vector<flexsplat::testing::GradParam> out;
    for (std::size_t i = 0; i < specs.size(); ++i)
      out.push_back({specs[i].name, std::span<double>(values.data() + offsets[i], count(i)),
                     std::span<double>(grads.data() + offsets[i], count(i))});
    return out;
  }
};

}  // namespace heads_backward_test
