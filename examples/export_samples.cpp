// Writes the .glb files the glTF-Validator test checks: SH degrees 0-3, quantised variants, cameras, and one file
// broken on purpose (wrong POSITION max) so the test proves the validator does catch errors.
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <random>
#include <string>

#include <nlohmann/json.hpp>

#include "flexsplat/io/cameras_json.hpp"
#include "flexsplat/export/gltf.hpp"

using namespace flexsplat;

namespace {

GaussianSet<float> sample_set(index_t n, int degree, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-1.0, 1.0), u01(0.0, 1.0);
  auto set = make_gaussian_set<float>(n, degree);
  for (index_t i = 0; i < n; ++i) {
    double q[4], norm = 0;
    for (double& v : q) { v = u(rng); norm += v * v; }
    for (int c = 0; c < 4; ++c) set.quats(i, c) = float(q[c] / std::sqrt(norm));
    for (int c = 0; c < 3; ++c) {
      set.means(i, c) = float(0.8 * u(rng));
      set.scales(i, c) = float(0.005 + 0.05 * u01(rng));
    }
    set.opacities(i) = float(u01(rng));
    for (index_t k = 0; k < set.sh.shape(1); ++k)
      for (int c = 0; c < 3; ++c) set.sh(i, k, c) = float(k == 0 ? 1.5 * u(rng) : 0.2 * u(rng));
  }
  return set;
}

// Rewrites the JSON chunk of a glb with POSITION's max off by one, a genuine ACCESSOR_MAX_MISMATCH.
void write_broken(const std::vector<unsigned char>& glb, const std::filesystem::path& path) {
  std::uint32_t length = 0;
  std::memcpy(&length, glb.data() + 12, 4);
  auto json = nlohmann::json::parse(glb.begin() + 20, glb.begin() + 20 + length);
  const int acc = json["meshes"][0]["primitives"][0]["attributes"]["POSITION"];
  json["accessors"][acc]["max"][0] = json["accessors"][acc]["max"][0].get<double>() + 1.0;
  std::string text = json.dump();
  while (text.size() % 4) text += ' ';
  std::vector<unsigned char> out(glb.begin(), glb.begin() + 20);
  out.insert(out.end(), text.begin(), text.end());
  out.insert(out.end(), glb.begin() + 20 + length, glb.end());
  const std::uint32_t new_length = static_cast<std::uint32_t>(text.size()), total = static_cast<std::uint32_t>(out.size());
  std::memcpy(out.data() + 12, &new_length, 4);
  std::memcpy(out.data() + 8, &total, 4);
  std::ofstream(path, std::ios::binary).write(reinterpret_cast<const char*>(out.data()), std::streamsize(out.size()));
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 2 || argc > 3) {
    std::fprintf(stderr, "usage: export_samples OUTDIR [cameras.json]\n");
    return 2;
  }
  try {
    const std::filesystem::path dir = argv[1];
    std::filesystem::create_directories(dir);
    for (int degree = 0; degree <= 3; ++degree) {
      const auto report = gltf::write_glb(sample_set(500, degree, 1 + degree), dir / ("sh" + std::to_string(degree) + ".glb"));
      std::printf("sh%d.glb: %zu bytes\n", degree, report.bytes);
    }
    auto set = sample_set(500, 3, 9);
    gltf::WriteOptions small;
    small.rotation = gltf::RotationEncoding::Int8Normalized;
    small.scale = gltf::UnitEncoding::UInt8Normalized;
    small.opacity = gltf::UnitEncoding::UInt8Normalized;
    std::printf("quantized8.glb: %zu bytes\n", gltf::write_glb(set, dir / "quantized8.glb", small).bytes);
    gltf::WriteOptions medium;
    medium.rotation = gltf::RotationEncoding::Int16Normalized;
    medium.scale = gltf::UnitEncoding::UInt16Normalized;
    medium.opacity = gltf::UnitEncoding::UInt16Normalized;
    medium.color_space = "lin_rec709_display";
    std::printf("quantized16.glb: %zu bytes\n", gltf::write_glb(set, dir / "quantized16.glb", medium).bytes);
    gltf::WriteOptions with_cameras;
    if (argc == 3) with_cameras.cameras = io::load_cameras_json(argv[2]);
    else {
      const double K[9] = {60, 0, 32, 0, 60, 24, 0, 0, 1}, w2c[12] = {1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 3};
      with_cameras.cameras = {camera_from_arrays(K, w2c, 64, 48, "synthetic")};
    }
    std::printf("cameras.glb: %zu bytes, %zu cameras\n", gltf::write_glb(set, dir / "cameras.glb", with_cameras).bytes,
                with_cameras.cameras.size());
    write_broken(gltf::encode_glb(set, with_cameras), dir / "broken_max.glb");
    return 0;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "export_samples: error: %s\n", e.what());
    return 1;
  }
}
