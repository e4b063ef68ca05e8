#pragma once
// Random fills shared by the decoder tests.
#include <algorithm>
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

#include <cmath>

#include "flexsplat/decoder/gaussians.hpp"

// Cameras on a ring of radius `radius` around `target`, looking at it (OpenCV: x right, y down, z forward).
struct TestRig {
  flexsplat::index_t views, w, h, dw, dh;
  std::vector<double> K, E, depth;
  flexsplat::decoder::ViewGeometry<double> geometry() const {
    return {views, w, h, dw, dh, K.data(), E.data(), depth.data()};
  }
};

inline TestRig make_rig(flexsplat::index_t views, double radius = 3.0, flexsplat::index_t w = 24, flexsplat::index_t h = 20,
                        flexsplat::index_t dw = 12, flexsplat::index_t dh = 10, double elevation = 0.3) {
  TestRig r{views, w, h, dw, dh, {}, {}, {}};
  for (flexsplat::index_t v = 0; v < views; ++v) {
    const double az = 2.0 * 3.14159265358979 * static_cast<double>(v) / static_cast<double>(views) + 0.2;
    const double c[3] = {radius * std::cos(az), elevation * radius, radius * std::sin(az)};
    double f[3] = {-c[0], -c[1], -c[2]};
    const double fn = std::sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2]);
    for (double& x : f) x /= fn;
    const double up[3] = {0, -1, 0};
    double rt[3] = {f[1] * up[2] - f[2] * up[1], f[2] * up[0] - f[0] * up[2], f[0] * up[1] - f[1] * up[0]};
    const double rn = std::sqrt(rt[0] * rt[0] + rt[1] * rt[1] + rt[2] * rt[2]);
    for (double& x : rt) x /= rn;
    const double dn[3] = {f[1] * rt[2] - f[2] * rt[1], f[2] * rt[0] - f[0] * rt[2], f[0] * rt[1] - f[1] * rt[0]};
    const double* rows[3] = {rt, dn, f};
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) r.E.push_back(rows[i][j]);
      r.E.push_back(-(rows[i][0] * c[0] + rows[i][1] * c[1] + rows[i][2] * c[2]));
    }
    const double k[9] = {1.1 * w, 0, 0.5 * w + 0.3, 0, 1.0 * w, 0.5 * h - 0.2, 0, 0, 1};
    r.K.insert(r.K.end(), k, k + 9);
    for (flexsplat::index_t i = 0; i < dw * dh; ++i)
      r.depth.push_back(radius + 0.3 * std::sin(0.7 * static_cast<double>(i) + static_cast<double>(v)));
  }
  return r;
}

// A decoder Gaussian set (SH degree 1, no features) as one flat vector for the gradient checker, 23 values per Gaussian:
// means, quats, scales, opacities, sh, each field whole.
inline constexpr flexsplat::index_t flat_set_values = 23;

inline double* flatten_set(const flexsplat::GaussianSet<double>& g, double* p) {
  for (const auto* t : {&g.means, &g.quats, &g.scales}) p = std::copy(t->data(), t->data() + t->size(), p);
  p = std::copy(g.opacities.data(), g.opacities.data() + g.opacities.size(), p);
  return std::copy(g.sh.data(), g.sh.data() + g.sh.size(), p);
}

// The gradient with respect to a flattened set of n Gaussians back as a GaussianSetGrad.
inline flexsplat::GaussianSetGrad<double> unflatten_grad(const double* p, flexsplat::index_t n) {
  flexsplat::GaussianSetGrad<double> d = flexsplat::make_gaussian_grad(flexsplat::make_gaussian_set<double>(n, 1));
  for (auto* t : {&d.means, &d.quats, &d.scales}) {
    std::copy(p, p + t->size(), t->data());
    p += t->size();
  }
  std::copy(p, p + n, d.opacities.data());
  std::copy(p + n, p + n + 12 * n, d.sh.data());
  return d;
}

#include <string>
#include <utility>

#include "flexsplat/decoder/param_names.hpp"

// The named tensors of a decoder-side flat block, in block order, for testing::split_flat: the model tensors whose
// names start with `part` ("unet.", "fusion.", "decoder."; empty: the whole model).
inline std::vector<std::pair<std::string, std::size_t>> appearance_tensors(const flexsplat::decoder::ModelConfig& c,
                                                                           const std::string& part = {}) {
  std::vector<flexsplat::io::TensorSpec> specs;
  flexsplat::decoder::append_model_specs(specs, c);
  std::vector<std::pair<std::string, std::size_t>> out;
  for (const auto& s : specs)
    if (s.name.compare(0, part.size(), part) == 0)
      out.emplace_back(s.name, static_cast<std::size_t>(flexsplat::io::spec_numel(s)));
  return out;
}

// A consistent model around one part's configuration (the other parts at their defaults, channels matched).
inline flexsplat::decoder::ModelConfig model_around(const flexsplat::decoder::UNetConfig& u) {
  flexsplat::decoder::ModelConfig m;
  m.unet = u, m.fusion.unet_channels = u.base, m.fusion.out_channels = m.decoder.value_dim;
  return m;
}
inline flexsplat::decoder::ModelConfig model_around(const flexsplat::decoder::FusionConfig& f) {
  flexsplat::decoder::ModelConfig m;
  m.fusion = f, m.unet.base = f.unet_channels, m.decoder.value_dim = f.out_channels;
  return m;
}
inline flexsplat::decoder::ModelConfig model_around(const flexsplat::decoder::DecoderConfig& d) {
  flexsplat::decoder::ModelConfig m;
  m.decoder = d, m.fusion.out_channels = d.value_dim, m.fusion.unet_channels = m.unet.base;
  return m;
}
