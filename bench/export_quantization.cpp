// Size saving and error of the glb quantisation options, on a random set of N Gaussians (SH degree 0 and 3).
//   build/bench/export_quantization [N]
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <random>

#include "flexsplat/export/gltf.hpp"

using namespace flexsplat;

int main(int argc, char** argv) {
  const index_t n = argc > 1 ? std::atoll(argv[1]) : 100000;
  for (int degree : {0, 3}) {
    std::mt19937 rng(5);
    std::uniform_real_distribution<double> u(-1.0, 1.0), u01(0.0, 1.0);
    auto set = make_gaussian_set<float>(n, degree);
    for (index_t i = 0; i < n; ++i) {
      double q[4], norm = 0;
      for (double& v : q) { v = u(rng); norm += v * v; }
      for (int c = 0; c < 4; ++c) set.quats(i, c) = float(q[c] / std::sqrt(norm));
      for (int c = 0; c < 3; ++c) {
        set.means(i, c) = float(u(rng));
        set.scales(i, c) = float(std::exp(-7.0 + 6.0 * u01(rng)));  // 0.0009 .. 0.37, log-uniform like trained sets
      }
      set.opacities(i) = float(u01(rng));
      for (index_t k = 0; k < set.sh.shape(1); ++k)
        for (int c = 0; c < 3; ++c) set.sh(i, k, c) = float(0.5 * u(rng));
    }
    const std::size_t plain = gltf::encode_glb(set).size();
    std::printf("N=%lld SH degree %d: float glb %zu bytes (%.1f bytes/Gaussian)\n", static_cast<long long>(n), degree,
                plain, double(plain) / double(n));
    std::printf("%-8s %-8s %-8s %12s %8s %14s %14s %14s\n", "rotation", "scale", "opacity", "bytes", "saving",
                "max_rot_deg", "max_scale_rel", "max_opacity");
    struct Row { gltf::RotationEncoding r; gltf::UnitEncoding s, o; const char *rn, *sn, *on; };
    const Row rows[] = {
        {gltf::RotationEncoding::Int16Normalized, gltf::UnitEncoding::UInt16Normalized, gltf::UnitEncoding::UInt16Normalized, "int16", "uint16", "uint16"},
        {gltf::RotationEncoding::Int16Normalized, gltf::UnitEncoding::UInt16Normalized, gltf::UnitEncoding::UInt8Normalized, "int16", "uint16", "uint8"},
        {gltf::RotationEncoding::Int8Normalized, gltf::UnitEncoding::UInt16Normalized, gltf::UnitEncoding::UInt8Normalized, "int8", "uint16", "uint8"},
        {gltf::RotationEncoding::Int8Normalized, gltf::UnitEncoding::UInt8Normalized, gltf::UnitEncoding::UInt8Normalized, "int8", "uint8", "uint8"},
    };
    for (const Row& row : rows) {
      gltf::WriteOptions options;
      options.rotation = row.r;
      options.scale = row.s;
      options.opacity = row.o;
      const auto glb = gltf::encode_glb(set, options);
      const auto back = gltf::decode_glb(glb.data(), glb.size(), "quantised");
      double rot = 0, scale = 0, opacity = 0;
      for (index_t i = 0; i < n; ++i) {
        double dot = 0;
        for (int c = 0; c < 4; ++c) dot += double(set.quats(i, c)) * back.quats(i, c);
        rot = std::max(rot, 2 * std::acos(std::min(1.0, std::abs(dot))) * 180 / 3.14159265358979323846);
        for (int c = 0; c < 3; ++c)
          scale = std::max(scale, std::abs(double(back.scales(i, c)) - set.scales(i, c)) / set.scales(i, c));
        opacity = std::max(opacity, std::abs(double(back.opacities(i)) - set.opacities(i)));
      }
      std::printf("%-8s %-8s %-8s %12zu %7.1f%% %14.4g %14.4g %14.4g\n", row.rn, row.sn, row.on, glb.size(),
                  100.0 * (1.0 - double(glb.size()) / double(plain)), rot, scale, opacity);
    }
  }
  return 0;
}
