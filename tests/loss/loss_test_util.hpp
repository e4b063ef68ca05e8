#pragma once
#include <random>
#include <vector>

namespace loss_test {
inline std::vector<double> uniform(std::size_t n, unsigned seed, double lo = 0, double hi = 1) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(lo, hi);
  std::vector<double> v(n);
  for (auto& x : v) x = u(rng);
  return v;
}
}  // namespace loss_test
