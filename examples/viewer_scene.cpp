// Writes the viewer-test scene: a deterministic coloured torus of Gaussians with one camera (scene.glb) and
// flexsplat's own render of that camera on black (reference.png), which the browser viewers' screenshots must match.
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <random>
#include <string>

#include "flexsplat/io/cameras_json.hpp"
#include "flexsplat/export/gltf.hpp"
#include "flexsplat/export/render_set.hpp"
#include "flexsplat/image/image_io.hpp"

using namespace flexsplat;

int main(int argc, char** argv) {
  if (argc != 3) {
    std::fprintf(stderr, "usage: viewer_scene OUTDIR cameras.json:index\n");
    return 2;
  }
  try {
    const std::filesystem::path dir = argv[1];
    std::filesystem::create_directories(dir);
    const index_t n = 4000;
    auto set = make_gaussian_set<float>(n, 0);
    std::mt19937 rng(2024);
    std::uniform_real_distribution<double> u01(0.0, 1.0);
    const double pi = 3.14159265358979323846;
    for (index_t i = 0; i < n; ++i) {
      const double a = 2 * pi * u01(rng), b = 2 * pi * u01(rng);
      const double R = 0.6, r = 0.25 * std::sqrt(u01(rng));
      set.means(i, 0) = float((R + r * std::cos(b)) * std::cos(a));
      set.means(i, 1) = float((R + r * std::cos(b)) * std::sin(a));
      set.means(i, 2) = float(r * std::sin(b));
      double q[4], norm = 0;
      for (double& v : q) { v = u01(rng) - 0.5; norm += v * v; }
      for (int c = 0; c < 4; ++c) set.quats(i, c) = float(q[c] / std::sqrt(norm));
      for (int c = 0; c < 3; ++c) set.scales(i, c) = float(0.01 + 0.03 * u01(rng));
      set.opacities(i) = float(0.5 + 0.5 * u01(rng));
      // Colour varies smoothly around the ring: display colour c -> DC coefficient (c - 0.5) / sh_c0.
      const double colour[3] = {0.5 + 0.45 * std::cos(a), 0.5 + 0.45 * std::cos(a + 2.1), 0.5 + 0.45 * std::cos(a + 4.2)};
      for (int c = 0; c < 3; ++c) set.sh(i, 0, c) = float((colour[c] - 0.5) / sh_c0);
    }
    gltf::WriteOptions write_options;
    write_options.cameras = io::load_camera_spec(argv[2]);
    const Camera& camera = write_options.cameras.at(0);
    gltf::write_glb(set, dir / "scene.glb", write_options);
    raster::RenderOptions options;
    options.background = {0, 0, 0};
    raster::RenderWorkspace<float> ws;
    raster::RenderOutputs<float> out;
    gaussians::render_set(set, camera, options, ws, out);
    image::write_png(dir / "reference.png", out.image);
    std::printf("%s: %lld Gaussians, camera %dx%d; reference.png written\n", (dir / "scene.glb").string().c_str(),
                static_cast<long long>(n), camera.width, camera.height);
    return 0;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "viewer_scene: error: %s\n", e.what());
    return 1;
  }
}
