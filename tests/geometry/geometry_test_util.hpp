#pragma once
// Shared helpers for the geometry tests: random fills and the reference bundle path.
#include <random>
#include <string>
#include <vector>

inline std::vector<double> random_doubles(std::size_t n, unsigned seed, double scale = 1.0) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> normal(0.0, scale);
  std::vector<double> v(n);
  for (auto& x : v) x = normal(rng);
  return v;
}

inline std::string vggt_bundle_path() { return std::string(FLEXSPLAT_SHARED_DIR) + "/reference/vggt_tiny_1234.safetensors"; }
