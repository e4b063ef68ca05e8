#pragma once
// Random fills shared by the decoder tests.
#include <random>
#include <vector>

inline std::vector<double> random_normal(std::size_t n, unsigned seed, double scale = 1.0, double mean = 0.0) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> normal(mean, scale);
  std::vector<double> v(n);
  for (auto& x : v) x = normal(rng);
  return v;
}

inline std::vector<double> random_uniform(std::size_t n, unsigned seed, double lo, double hi) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> uniform(lo, hi);
  std::vector<double> v(n);
  for (auto& x : v) x = uniform(rng);
  return v;
}

template <class To>
std::vector<To> cast_vector(const std::vector<double>& v) {
  return std::vector<To>(v.begin(), v.end());
}
